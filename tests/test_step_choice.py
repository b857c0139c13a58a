"""substeps = "auto" (analysis/step_choice.py): the fewest substeps the advisor passes with its margin, the accuracy
floor of implicit Euler, the contacts' travel bound, the maximum over worlds; the Simulator's step chooser; scene
files and ``warpspring run`` defaulting to it, printing their choice, and an explicit count still ruling."""

import functools
import json
import math
import pathlib

import numpy as np
import pytest

import warpspring as ws
from warpspring.analysis.advisor import advise
from warpspring import checks
from warpspring.analysis import trade_contact, trade_table
from warpspring.analysis.step_choice import (CONTACT_TRAVEL, STABILITY_MARGIN, auto_substeps, choose_substeps,
                                             contact_substeps)
from warpspring.analysis.trade_table import TABLE_PATH, load_table, signature
from warpspring.app.cli import main
from warpspring.core.integrators import make_integrator
from warpspring.app.runner import run_scene
from warpspring.io.scene import load_scene
from helpers import hanging_cloth, write_scene

FPS = 60.0


def test_fewest_the_advisor_passes(device):
    # The ANCHORS cloth (12², ke = 1e3, kd = 10, 0.1 kg): the choice passes the advisor's --strict with the
    # margin, and one substep fewer would not keep the margin.
    model, _ = hanging_cloth(device)
    choice = choose_substeps(model, "symplectic_euler", fps=FPS)
    n = choice.substeps
    limit = choice.advice.dt_passed
    assert choice.dt == pytest.approx(1.0 / (FPS * n)) and choice.dt <= STABILITY_MARGIN * limit
    assert n == 1 or 1.0 / (FPS * (n - 1)) > STABILITY_MARGIN * limit
    advise(model, "symplectic_euler", choice.dt, fps=FPS, strict=True)  # does not raise
    assert f"{n} substeps" in choice.reason and "the advisor passes" in choice.reason


def test_the_steps_judged_share_one_dry_run(device, monkeypatch):
    """choose_substeps judges several steps of one model: its static solve and its dry run, which do not depend on
    the step, run once (shared_estimates), and the choice is the one that computing them for every step gives. Outside
    it each advise() computes its own; a value written between two judgements (input_version) is not shared."""
    import contextlib

    from warpspring.analysis import advisor, step_choice

    model, _ = hanging_cloth(device)
    runs = []
    dry_run = advisor.transient_peak

    def counted(*args, **kwargs):
        runs.append(1)
        return dry_run(*args, **kwargs)

    monkeypatch.setattr(advisor, "transient_peak", counted)
    shared = choose_substeps(model, "symplectic_euler", fps=FPS)
    assert len(runs) == 1
    monkeypatch.setattr(step_choice, "shared_estimates", contextlib.nullcontext)
    alone = choose_substeps(model, "symplectic_euler", fps=FPS)
    assert len(runs) >= 3  # the probe's and the verdicts'
    assert (shared.substeps, shared.reason) == (alone.substeps, alone.reason)
    runs.clear()
    with advisor.shared_estimates():
        advise(model, "symplectic_euler", shared.dt, fps=FPS)
        advise(model, "symplectic_euler", 0.5 * shared.dt, fps=FPS)
        assert len(runs) == 1
        model.set_world_values("drag", float(model.world_values("drag")[0, 0]) + 0.01)
        advise(model, "symplectic_euler", shared.dt, fps=FPS)
        assert len(runs) == 2


def test_simulator_takes_the_chooser(device):
    model, _ = hanging_cloth(device)
    sim = ws.Simulator(model, substeps=auto_substeps, fps=FPS)
    assert sim.substeps == choose_substeps(model, "symplectic_euler", fps=FPS).substeps
    assert sim.dt == pytest.approx(1.0 / (FPS * sim.substeps))
    sim.step_frame()  # and it runs at that step
    assert np.isfinite(sim.state.particle_q.numpy()).all()


def test_worlds_take_the_binding_one(device):
    # Two worlds, the second 4× stiffer: its ω_max doubles and so, about, do the substeps; the two-world choice
    # is the stiff world's own.
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, particle_mass=0.1, origin=(0, 0, 1), pin=["top-left", "top-right"],
                           structural=ws.SpringMaterial(1.0e3, 10.0), shear=ws.SpringMaterial(1.0e3, 10.0),
                           bend=False)
    both = builder.finalize(device, worlds=2)
    k = both.world_values("spring_stiffness")[0]
    both.set_world_values("spring_stiffness", np.stack([k, 4.0 * k]))
    stiff = builder.finalize(device)
    stiff.set_world_values("spring_stiffness", 4.0 * k[None, :])
    soft = builder.finalize(device)
    n_both, n_stiff, n_soft = (choose_substeps(m, "symplectic_euler", fps=FPS).substeps for m in (both, stiff, soft))
    assert n_both == n_stiff > n_soft


def test_explicit_euler_on_undamped_springs_is_refused(device):
    # No damping, no drag: explicit Euler grows every mode at every step; auto refuses and names the remedy.
    model, _ = hanging_cloth(device, structural=ws.SpringMaterial(1.0e3, 0.0), shear=ws.SpringMaterial(1.0e3, 0.0),
                             bend=ws.SpringMaterial(1.0e3, 0.0))
    with pytest.raises(ws.ConfigError, match="symplectic_euler"):
        choose_substeps(model, "explicit_euler", fps=FPS)


def test_implicit_euler_meets_the_accuracy_floor(device, tmp_path):
    # Implicit Euler passes any step: the choice is the fewest substeps (doubling) whose error over a frame is
    # within the floor. Checked against a run at 8× the chosen substeps: the error of the first 0.25 s, per
    # frame, within 2× the floor (step doubling estimates a first-order error to within its second-order
    # remainder: a factor below 2 where the estimate is within the floor); and the halved count misses it.
    # The floor is the measured trade table's (a looser table's floor takes fewer substeps).
    model, _ = hanging_cloth(device, n=8)
    integrator = ws.ImplicitEuler(model)
    choice = choose_substeps(model, integrator, fps=FPS)
    n = choice.substeps
    ACCURACY_FLOOR = load_table().floor
    assert choice.error <= ACCURACY_FLOOR and n > 1 and f"accuracy floor of {ACCURACY_FLOOR:.3g} m" in choice.reason
    first = load_table().floor_rows[0]  # the table's row it comes from: symplectic Euler on the cloth
    assert f"{first.integrator} {first.error:.3g} m at dt = {first.dt * 1e3:.4g} ms" in choice.reason

    def frames(substeps):
        sim = ws.Simulator(model, integrator=integrator, fps=FPS, substeps=substeps, guard=None)
        out = []
        for _ in range(15):
            sim.step_frame()
            out.append(sim.state.particle_q.numpy().astype(np.float64))
        return np.stack(out)

    reference = frames(8 * n)
    error = np.linalg.norm(frames(n) - reference, axis=-1).max(axis=-1)
    per_frame = np.max(np.diff(np.concatenate([[0.0], error])))
    assert per_frame <= 2.0 * ACCURACY_FLOOR, per_frame
    coarse = np.linalg.norm(frames(n // 2) - reference, axis=-1).max(axis=-1)
    assert np.max(np.diff(np.concatenate([[0.0], coarse]))) > 0.5 * ACCURACY_FLOOR
    loose = choose_substeps(model, integrator, fps=FPS, table=_table(tmp_path, floor=8.0 * ACCURACY_FLOOR))
    assert loose.substeps < n and loose.error <= 8.0 * ACCURACY_FLOOR


def test_dopri5_meets_the_floor(device):
    # dopri5 passes any step and meets its tolerance (1e-6) at one substep: step doubling confirms the floor.
    # The dry runs use an integrator of their own: the run's (an instance) starts untouched.
    model, _ = hanging_cloth(device, n=6)
    choice = choose_substeps(model, "dopri5", fps=FPS)
    assert choice.substeps == 1 and choice.error <= load_table().floor and "accuracy floor" in choice.reason
    integrator = make_integrator("dopri5", model, tolerance=1e-4)
    assert choose_substeps(model, integrator, fps=FPS).substeps == 1 and integrator.accepted_steps == 0


def _table(tmp_path, *, floor=None, problems=None):
    """A copy of the package's trade table with its floor [m] or its contact problems replaced."""
    data = json.loads(TABLE_PATH.read_text())
    if floor is not None:
        data["floor"]["value"] = floor
    if problems is not None:
        data["problems"] = problems
    path = tmp_path / f"table{len(list(tmp_path.glob('table*.json')))}.json"
    path.write_text(json.dumps(data))
    return load_table(path)


def test_a_measured_contact_scene_takes_the_tables_substeps(device, tmp_path):
    """Where the model is one the table measured, its fewest substeps within the floor, when fewer than the rules':
    a small cloth over the ground (the contact rule asks 12 substeps) measured at 4 within the floor, at 2 above it;
    another integrator's row, a float64 build (no float64 rows) and a heavier cloth (another scene) are not taken."""
    model, _ = hanging_cloth(device, n=6, ground=True, radius=0.025, pin=[])
    floor = load_table().floor
    runs = [dict(integrator="symplectic_euler", precision="float32", tolerance=None,
                 rows=[[2, 3.0 * floor], [4, 0.5 * floor], [8, 0.2 * floor]]),
            dict(integrator="velocity_verlet", precision="float32", tolerance=None, rows=[[1, 0.1 * floor]])]
    entry = dict(problem="floor cloth", option="plain", source=1, fps=FPS, signature=signature(model), runs=runs)
    table, bare = _table(tmp_path, problems=[entry]), _table(tmp_path, problems=[])
    rules = choose_substeps(model, "symplectic_euler", fps=FPS, table=bare)
    assert rules.substeps > 4 and rules.row is None
    choice = choose_substeps(model, "symplectic_euler", fps=FPS, table=table)
    assert choice.substeps == 4 and choice.dt == pytest.approx(1.0 / (4 * FPS)) and choice.row.error == 0.5 * floor
    assert "its row floor cloth, plain: symplectic_euler, float32, dt = 4.167 ms" in choice.reason
    assert f"fewer than the {rules.substeps} the rules ask" in choice.reason
    assert f"measured on {table.provenance(choice.row)}" in choice.reason and "Warp " in choice.reason
    sim = ws.Simulator(model, substeps=functools.partial(auto_substeps, table=table), fps=FPS)  # the Simulator's path
    assert sim.substeps == 4
    double, _ = hanging_cloth(device, n=6, ground=True, radius=0.025, pin=[], precision="float64")
    heavy, _ = hanging_cloth(device, n=6, ground=True, radius=0.025, pin=[], particle_mass=0.2)
    assert table.match(double) == ("floor cloth", "plain") and table.match(heavy) is None
    for other in (double, heavy):
        assert choose_substeps(other, "symplectic_euler", fps=FPS, table=table).row is None


def test_the_cli_prints_the_table_row_it_chose_and_a_count_rules(tmp_path, capsys, monkeypatch):
    """``warpspring run`` with no count: the package's table (here one that measured the CLI's test scene at 4
    substeps within the floor, where the contact rule asks 12) gives the count, and the printed line names the row;
    ``--substeps 3`` still rules."""
    path = write_scene(tmp_path, {"substeps = 4\n": ""})
    model = load_scene(str(path)).finalize(checks.device("cpu"))
    runs = [dict(integrator="symplectic_euler", precision="float32", tolerance=None, rows=[[4, 0.5 * load_table().floor]])]
    entry = dict(problem="test scene", option="ground", source=1, fps=FPS, signature=signature(model), runs=runs)
    monkeypatch.setattr(trade_table, "TABLE_PATH", pathlib.Path(_table(tmp_path, problems=[entry]).path))
    assert main(["run", str(path), "-o", str(tmp_path / "a.usdc"), "--device", "cpu", "-q"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("substeps auto: 4 substeps per 1/60 s frame (dt = 4.167 ms)")
    assert "its row test scene, ground: symplectic_euler, float32, dt = 4.167 ms" in first
    assert "fewer than the 12 the rules ask" in first
    assert main(["run", str(path), "-o", str(tmp_path / "b.usdc"), "--device", "cpu", "-q", "--substeps", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert not any(line.startswith("substeps auto") for line in lines) and "dt = 5.556 ms" in lines[0]


def test_the_shipped_table_names_what_a_measured_drape_needs():
    """The trade study's drape (16², particle contacts, float64) is in the package's table: the rules ask fewer
    substeps than its rows need for the floor (40: 1.05 mm; 20: 2.5 mm), so the choice keeps the rules' count and its
    reason names the measured row."""
    spec = trade_contact.FULL_PROBLEMS["drape"]
    model = spec.build("cpu", "float64", spec.scene.option("particle contacts"))
    choice = choose_substeps(model, "symplectic_euler", fps=FPS)
    assert choice.substeps < 40 and choice.row is None
    assert ("reaches the accuracy floor of 0.00126 m at 40 substeps on the trade table's row drape, particle "
            "contacts: symplectic_euler, float64, dt = 0.4167 ms, error 1.05e-03 m") in choice.reason


def test_contact_travel_bound(device):
    # A cloth 1 m above the ground, particles of 2.5 cm radius: v = √(2 g · 1 m) = 4.43 m/s, dt ≤ r/4 / v.
    model, _ = hanging_cloth(device, ground=True, radius=0.025, pin=[])
    top = float(model.particle_q.numpy()[:, 2].max())
    v = math.sqrt(2.0 * 9.81 * top)
    substeps, why = contact_substeps(model, fps=FPS)
    assert substeps == math.ceil(v / (FPS * CONTACT_TRAVEL * 0.025))
    assert "radius 0.025 m" in why
    assert contact_substeps(hanging_cloth(device)[0], fps=FPS) is None  # no colliders: no bound
    choice = choose_substeps(model, "symplectic_euler", fps=FPS)
    assert choice.substeps == max(substeps, choose_substeps(hanging_cloth(device, radius=0.025, pin=[])[0],
                                                            "symplectic_euler", fps=FPS).substeps)


def _quad_grid_usd(path, n=12, width=1.0):
    """A USD file of an n × n quad grid, ``width`` metres wide, standing in the xz plane (Z up)."""
    pytest.importorskip("pxr", reason="usd-core writes the mesh cloth's file")
    from pxr import Gf, Usd, UsdGeom
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, "/World/cloth")
    xs = np.linspace(0.0, width, n + 1)
    mesh.CreatePointsAttr([Gf.Vec3f(float(x), 0.0, float(z)) for z in xs for x in xs])
    faces = [i for r in range(n) for c in range(n)
             for i in (r * (n + 1) + c, r * (n + 1) + c + 1, (r + 1) * (n + 1) + c + 1, (r + 1) * (n + 1) + c)]
    mesh.CreateFaceVertexCountsAttr([4] * (n * n))
    mesh.CreateFaceVertexIndicesAttr(faces)
    stage.Save()


def test_mesh_cloth_with_defaults_runs_to_its_end(device, tmp_path):
    # The case: a 12 × 12 quad grid 1 m wide read from USD, mass 0.5 kg, its two top corners pinned,
    # everything else default. At 16 substeps the guard stops it at frame 1 (the advisor wants 33); with no
    # substeps given, auto takes what it needs and the run reaches its last frame.
    _quad_grid_usd(tmp_path / "quads.usda")
    path = tmp_path / "mesh.toml"
    path.write_text('version = 2\n[simulation]\nframes = 30\n[world]\ngravity = [0.0, 0.0, -9.81]\n'
                    '[cloth]\nmesh = "quads.usda"\nmass = 0.5\npin = [156, 168]\n')
    notes = []
    summary = run_scene(load_scene(str(path)), output=str(tmp_path / "mesh.usdc"), device=device, progress=False,
                        note=notes.append)
    assert summary.frames == 30 and not summary.world_failures
    assert notes and notes[0].startswith(f"substeps auto: {summary.substeps} substeps")
    assert summary.substeps > 16  # the 16 substeps that stop it (below)
    with pytest.raises(ws.SimulationError):
        run_scene(load_scene(str(path)), output=str(tmp_path / "mesh16.usdc"), device=device, progress=False,
                  substeps=16)


@pytest.mark.slow
def test_cli_prints_its_choice_and_a_count_rules(tmp_path, capsys):
    path = write_scene(tmp_path, {"substeps = 4\n": ""})
    assert main(["run", str(path), "-o", str(tmp_path / "a.usdc"), "--device", "cpu", "-q"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("substeps auto: ") and lines[-1].startswith("wrote ")
    assert main(["run", str(path), "-o", str(tmp_path / "b.usdc"), "--device", "cpu", "-q", "--substeps", "7"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1 and "dt = 2.381 ms" in lines[0]  # 1 / (60 · 7) s
    assert main(["run", str(write_scene(tmp_path, name="fixed.toml")), "--substeps", "auto", "--frames", "1", "-o",
                 str(tmp_path / "c.usdc"), "--device", "cpu", "-q"]) == 0  # "auto" over the file's 4
    assert capsys.readouterr().out.startswith("substeps auto: ")


def test_a_drag_track_takes_its_worst_value(device):
    # Drag lowers symplectic Euler's limit (ω²(h² + 2h c/m) < 4 for drag alone): a track from 0 to 10 N·s/m chooses
    # as the constant 10 N·s/m does, and the track is still there after.
    model, _ = hanging_cloth(device, n=6)
    heavy, _ = hanging_cloth(device, n=6, drag=10.0)
    track = ws.Track([0.0, 1.0], [0.0, 10.0])
    model.set_track("drag", track)
    tracked, fixed = (choose_substeps(m, "symplectic_euler", fps=FPS) for m in (model, heavy))
    assert tracked.substeps == fixed.substeps > choose_substeps(hanging_cloth(device, n=6)[0], "symplectic_euler",
                                                                fps=FPS).substeps
    assert model.track("drag") is track and "drag track" in tracked.reason


def test_simulator_names_the_chooser_for_auto():
    model, _ = hanging_cloth("cpu", n=3)
    with pytest.raises(ws.ConfigError, match="auto_substeps"):
        ws.Simulator(model, substeps="auto")


def test_a_colliders_top_errs_low():
    """The contact bound's fall ends at a lower bound of each collider's top (a lower top: a longer fall, more
    substeps): a capsule lying flat reaches its radius, a box turned on its side its smallest half extent, a mesh
    hanging below its frame's origin its highest vertex."""
    from types import SimpleNamespace

    from warpspring.analysis.step_choice import _top

    up = np.array([0.0, 0.0, 1.0])
    flat = (math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4))  # the capsule's z axis turned into y
    capsule = SimpleNamespace(kind="capsule", position=(0.0, 0.0, 1.0), rotation=flat, size=(0.1, 0.5, 0.0))
    assert _top(capsule, up) == pytest.approx(1.1)
    box = SimpleNamespace(kind="box", position=(0.0, 0.0, 0.0), rotation=flat, size=(0.5, 0.2, 0.3))
    assert _top(box, up) == pytest.approx(0.2)  # ≤ its true top, 0.2 (y turned up)
    hanging = SimpleNamespace(vertices=np.array([[0.0, 0.0, -0.5], [1.0, 0.0, -0.2], [0.0, 1.0, -0.4]]))
    mesh = SimpleNamespace(kind="mesh", position=(0.0, 0.0, 2.0), rotation=(0.0, 0.0, 0.0, 1.0), size=(0, 0, 0),
                           mesh=hanging)
    assert _top(mesh, up) == pytest.approx(1.8)
