"""Sweeps (warpspring.analysis.sweep): plans, validation, batching as worlds, metrics, resume, and the
same sweep on a local Ray with a worker killed mid-sweep (one Ray session for the module, 2 CPUs).

Kernel-running tests take the ``device`` fixture; the scenes share one feature set (a 5 × 5 cloth of
structural and shear springs, gravity, drag on or off, a ground plane, symplectic Euler) with the rest of
the file so compiles happen once."""

from __future__ import annotations

import copy
import csv
import os
import sys

import numpy as np
import pytest

from helpers import CUDA
from warpspring.analysis.sweep import results_dir, run_sweep
from warpspring.analysis.sweep_batch import make_batches
from warpspring.analysis.sweep_plan import plan_sweep
from warpspring.app.cli import EXIT_CONFIG, main
from warpspring.errors import ConfigError

FRAMES, SUBSTEPS, FPS = 5, 4, 60.0
RADIUS = 0.01
BASE = {
    "version": 2,
    "simulation": {"fps": FPS, "frames": FRAMES, "substeps": SUBSTEPS},
    "world": {"gravity": [0.0, 0.0, -9.81], "drag": 0.0},
    "cloth": {"grid": {"nx": 5, "ny": 5, "spacing": 0.1}, "origin": [-0.2, -0.2, 1.0], "particle_mass": 0.1,
              "radius": RADIUS, "pin": ["top-left", "top-right"], "structural": {"ke": 1.0e3, "kd": 1.0},
              "shear": {"ke": 1.0e3, "kd": 1.0}, "bend": False},
    "collider": [{"type": "ground", "friction": 0.5}],
}
#: ke = 1e9 N/m on 0.1 kg gives ωh = 1e5 · 4.2 ms ≫ 2, symplectic Euler's limit: it blows up in its first
#: frame, and the guard stops it (and only it: the others are worlds of the same models).
UNSTABLE_KE = 1.0e9
PLAN = {
    "scene": BASE,
    "sweep": {"reference": {"simulation.substeps": 4 * SUBSTEPS}, "batch": 8},
    "axes": {"cloth.structural.ke": [1.0e2, 1.0e3, UNSTABLE_KE], "world.drag": [0.0, 0.05]},
}
METRICS = ("status", "message", "frames", "worlds", "particles", "max_strain", "energy_start", "energy_end",
           "min_contact_distance", "error_max", "error_rms")


def plan_of(data=None, **sweep):
    data = copy.deepcopy(PLAN if data is None else data)
    data["sweep"].update(sweep)
    return plan_sweep(data, path="plan.toml")


_LOCAL = {}


def local_sweep(device, tmp_path_factory):
    """The plan run in this process (once per device for the module): (result, out folder)."""
    if device not in _LOCAL:
        out = str(tmp_path_factory.mktemp(f"local-{device.replace(':', '')}"))
        _LOCAL[device] = run_sweep(plan_of(), out, device=device), out
    return _LOCAL[device]


# -- plans --------------------------------------------------------------------------------------------------


def test_axes_expand_lists_ranges_logs_and_seeded_samples():
    data = {"scene": BASE, "axes": {
        "simulation.substeps": {"range": [2, 8], "step": 2},
        "world.drag": {"log": [1.0e-3, 1.0e-1], "count": 3},
        "cloth.shear.kd": {"random": [0.1, 10.0], "count": 2, "seed": 3, "log": True},
    }}
    plan = plan_sweep(data)
    assert plan.axes["simulation.substeps"] == [2, 4, 6, 8]
    np.testing.assert_allclose(plan.axes["world.drag"], [1.0e-3, 1.0e-2, 1.0e-1], rtol=1e-12)
    u = np.random.default_rng(3).random(2)  # the documented sampler: log-uniform from a seeded generator
    np.testing.assert_allclose(plan.axes["cloth.shear.kd"], 0.1 * 100.0**u, rtol=1e-12)
    assert len(plan.variants) == 4 * 3 * 2 and len({v.key for v in plan.variants}) == 24
    assert plan_sweep(data).axes == plan.axes  # the seed makes the samples reproducible
    sparse = plan_sweep({**data, "sweep": {"metrics_every": 10}})
    assert {v.key for v in sparse.variants}.isdisjoint(v.key for v in plan.variants)  # results not mixed up
    v = plan.variants[-1]
    assert v.scene["cloth"]["shear"] == {"ke": 1.0e3, "kd": v.params["cloth.shear.kd"]}
    assert v.scene["simulation"]["substeps"] == 8 and BASE["simulation"]["substeps"] == SUBSTEPS  # base untouched

    zipped = plan_sweep({"scene": BASE, "sweep": {"combine": "zip"},
                            "axes": {"world.drag": [0.0, 0.1], "cloth.bend": [False, True]}})
    assert [v.params for v in zipped.variants] == [{"world.drag": 0.0, "cloth.bend": False},
                                                   {"world.drag": 0.1, "cloth.bend": True}]


def test_topology_batches_variants_that_differ_in_per_world_values_only():
    plan = plan_of()
    batches = make_batches(plan.variants, plan.scene_path, 8)
    # drag 0 and drag > 0 compile differently; the stiffnesses are per-world rows.
    assert [[v.index for v in b.variants] for b in batches] == [[0, 2, 4], [1, 3, 5]]
    assert len(make_batches(plan.variants, plan.scene_path, 2)) == 4


def test_a_bad_sweep_names_every_offending_variant_before_anything_runs():
    data = {"scene": BASE, "axes": {"cloth.structural.ke": [-1.0, 1.0e3, -5.0],
                                    "simulation.integrator": ["symplectic_euler", "no_such_method"]}}
    with pytest.raises(ConfigError) as caught:
        plan_sweep(data, path="bad.toml")
    lines = str(caught.value).splitlines()
    assert lines[0] == "bad.toml: 5 of 6 variants refused; nothing ran:"
    assert len(lines) == 6
    assert lines[1].startswith("  variant 0 (cloth.structural.ke=-1, simulation.integrator='symplectic_euler'): ")
    assert "cloth.structural.ke must be a number >= 0, got -1.0" in lines[1]
    assert lines[3].startswith("  variant 3 (") and "unknown integrator 'no_such_method'" in lines[3]  # ke = 1e3, the bad integrator
    for bad, message in [({"axes": {"cloth.stiffness": [1.0]}}, "unknown key 'stiffness' in [cloth]"),
                         ({"axes": {"world.drag": []}}, "lists no values"),
                         ({"axes": {"output.path": ["x.usdc"]}}, "cannot be swept"),
                         ({"axes": {"world.drag": {"log": [0.0, 1.0], "count": 3}}}, "needs ends > 0"),
                         ({"sweep": {"combine": "zip"}, "axes": {"world.drag": [0.0], "cloth.radius": [0.1, 0.2]}},
                          "axes of one length"),
                         ({"sweep": {"reference": {"simulation.frames": 9}}, "axes": {"world.drag": [0.0]}},
                          "the error compares end states at one time")]:
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace("[", r"\[")):
            plan_sweep({"scene": BASE, "sweep": {}, **bad})


def test_a_sweep_file_holds_data_only(tmp_path):
    """Code or shell in a key or a value is refused, and nothing of it runs."""
    marker = tmp_path / "pwned"
    payload = f"__import__('os').system('touch {marker}')"
    attempts = [
        ({payload: [1.0]}, "is not a scene key"),
        ({"simulation.integrator": [f"symplectic_euler; touch {marker}"]}, "unknown integrator"),
        ({"simulation.integrator": [payload]}, "unknown integrator"),
        ({"cloth.name": ["cloth\n[simulation]\nintegrator = 'x'"]}, "must be printable"),
        ({"simulation.__class__": [1]}, "unknown key '__class__' in [simulation]"),
        ({"world.drag": [{"__reduce__": payload}]}, "unknown key '__reduce__' in [world.drag]"),
    ]
    for axes, message in attempts:
        with pytest.raises(ConfigError) as caught:
            plan_sweep({"scene": BASE, "axes": axes})
        assert message in str(caught.value)
    sweep_file = tmp_path / "evil.toml"
    sweep_file.write_text('[sweep]\nscene = "x.toml"\n[axes]\n"{payload}" = [1]\n'.replace("'", "\\'"))
    assert main(["sweep", str(sweep_file), "--no-ray", "--out", str(tmp_path / "out")]) == EXIT_CONFIG
    assert not marker.exists()


# -- running ------------------------------------------------------------------------------------------------


def test_every_variant_is_a_row_with_its_metrics(device, tmp_path_factory):
    """Against the scene run alone and measured here: the batched worlds give each variant's own bits."""
    import warp as wp

    from warpspring.analysis.trade_problems import SpringNetwork
    from warpspring.core.simulator import Simulator
    from warpspring.io.scene import parse_scene

    result, out = local_sweep(device, tmp_path_factory)
    plan = result.plan
    assert [r.index for r in result.rows] == list(range(6)) and result.ran == 6
    assert [r.worlds for r in result.rows] == [3] * 6
    for v, row in zip(plan.variants, result.rows):
        if v.params["cloth.structural.ke"] == UNSTABLE_KE:
            # recorded with the guard's message, the other worlds of its model unharmed
            assert row.status == "stopped" and row.frames == 0
            assert row.message.startswith("frame 1, substep ") and "guard limit exceeded" in row.message
            assert row.error_max is None
            continue
        assert row.status == "ok" and row.frames == FRAMES and row.message == ""
        scene = parse_scene(v.scene)
        model = scene.finalize(device)
        sim = Simulator(model, fps=FPS, substeps=SUBSTEPS)
        network = SpringNetwork.of(model)
        strain = network.max_strain(model.particle_q.numpy().astype(np.float64))
        for _ in range(FRAMES):
            sim.step_frame()
            wp.synchronize_device(device)
            strain = max(strain, network.max_strain(sim.state.particle_q.numpy().astype(np.float64)))
        q = sim.state.particle_q.numpy().astype(np.float64)
        qd = sim.state.particle_qd.numpy().astype(np.float64)
        assert row.max_strain == strain
        # The energy as trade.SpringNetwork sums it (another summation order: float64 roundings apart).
        assert row.energy_end == pytest.approx(network.energy(q, qd), rel=1e-12)
        assert row.energy_start == pytest.approx(network.energy(network.initial_q, 0 * q), rel=1e-12, abs=1e-15)
        # The cloth falls all the way: its lowest particle surface is nearest the ground at the last frame
        # (the radius as the model stores it, in its precision).
        radius = model.particle_radius.numpy().astype(np.float64)
        assert row.min_contact_distance == np.min(q[:, 2] - radius)
        ref = np.load(os.path.join(results_dir(out), f"{plan.reference_key}.npy"))
        assert row.error_max == np.linalg.norm(q - ref, axis=1).max()
        # Symplectic Euler is first order: 4× the substeps leaves ~3/4 of the error, which the pinned
        # cloth's fall after 5 frames (|a| ~ g, t = 0.083 s) bounds by ~ g t h ≈ 3e-3 m.
        assert 0.0 < row.error_max < 9.81 * (FRAMES / FPS) * (1.0 / (FPS * SUBSTEPS))

    from warpspring.analysis.sweep_report import write_report

    paths = write_report(result, out)
    with open(paths[0]) as f:
        rows = list(csv.DictReader(f))
    assert [(float(r["cloth.structural.ke"]), float(r["world.drag"])) for r in rows] == \
        [(v.params["cloth.structural.ke"], v.params["world.drag"]) for v in plan.variants]
    assert [r["status"] for r in rows] == [r.status for r in result.rows]
    assert [float(r["max_strain"]) for r in rows if r["status"] == "ok"] == \
        [r.max_strain for r in result.rows if r.status == "ok"]
    assert os.path.getsize(paths[-1]) > 10_000  # the summary plot


def test_resume_runs_only_what_is_missing(device, tmp_path_factory):
    result, out = local_sweep(device, tmp_path_factory)
    with pytest.raises(ConfigError, match="pass --resume"):
        run_sweep(result.plan, out, device=device)
    folder = results_dir(out)
    missing = [result.plan.variants[i].key for i in (1, 4)]
    for key in missing:
        os.replace(os.path.join(folder, f"{key}.json"), os.path.join(folder, f"{key}.json.tmp999"))  # as if killed
    again = run_sweep(result.plan, out, device=device, resume=True)
    assert again.ran == 2
    same = [m for m in METRICS if m != "worlds"]
    for a, b in zip(again.rows, result.rows):
        assert [getattr(a, m) for m in same] == [getattr(b, m) for m in same]
    # Variants 1 and 4 differ in whether drag is on: each ran alone now, and gave its batched bits.
    assert [again.rows[i].worlds for i in (1, 4)] == [1, 1] and again.rows[0].worlds == 3


def test_cli_sweep_without_ray(device, tmp_path):
    scene = tmp_path / "scene.toml"
    scene.write_text(_toml(BASE))
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text('[sweep]\nscene = "scene.toml"\nusd = true\n[axes]\n"world.drag" = [0.0, 0.05]\n')
    out = tmp_path / "out"
    assert main(["sweep", str(sweep_file), "--no-ray", "--out", str(out), "--device", device, "-q"]) == 0
    names = sorted(os.listdir(out))
    assert {"results", "sweep.csv", "sweep.png", "usd"} <= set(names)
    usd = sorted(os.listdir(out / "usd"))
    assert len(usd) == 2 and all(name.endswith(".usdc") and ".partial" not in name for name in usd)
    from pxr import Usd

    stage = Usd.Stage.Open(str(out / "usd" / usd[0]))
    assert stage.GetEndTimeCode() - stage.GetStartTimeCode() == FRAMES


def _toml(data: dict) -> str:
    """A scene dict as TOML (the few types BASE uses)."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + " }"
        return repr(v)

    lines = [f"version = {data['version']}"]
    for table, content in data.items():
        if table == "version":
            continue
        for entry in content if isinstance(content, list) else [content]:
            lines.append(f"[[{table}]]" if isinstance(content, list) else f"[{table}]")
            lines += [f"{k} = {value(v)}" for k, v in entry.items()]
    return "\n".join(lines) + "\n"


# -- on Ray -------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ray_engine():
    pytest.importorskip("ray")
    pytest.importorskip("psutil")
    from warpspring.analysis.sweep_ray import RayEngine

    engine = RayEngine(workers=2, gpus_per_task=0.5 if CUDA else 0.0)
    yield engine
    engine.close()


def _kill_first_attempt(marker: str):
    def hook(batch):
        if not os.path.exists(marker):
            open(marker, "w").close()
            os._exit(1)  # the worker process dies mid-task, as if killed

    return hook


def test_on_ray_a_killed_worker_is_retried_and_the_metrics_match(device, tmp_path_factory, tmp_path, ray_engine):
    import ray

    from warpspring.analysis.sweep_ray import listening_beyond_loopback

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the hook travels to the workers
    local, _ = local_sweep(device, tmp_path_factory)
    marker = str(tmp_path / "killed-once")
    result = run_sweep(plan_of(), str(tmp_path / "out"), engine=ray_engine, device=device,
                          task_hook=_kill_first_attempt(marker))
    assert os.path.exists(marker)  # a worker died, and its task ran again
    assert result.ran == 6
    for a, b in zip(result.rows, local.rows):
        assert [getattr(a, m) for m in METRICS] == [getattr(b, m) for m in METRICS]  # timings aside
    # Every socket of the session (the driver, GCS, raylet, workers, agents) listens on loopback only.
    assert listening_beyond_loopback([os.getpid()]) == []


def test_on_ray_the_trade_study_gives_the_local_rows(device, ray_engine):
    from warpspring.analysis.analytic import DampedOscillator
    from warpspring.analysis.trade import StudyPlan, run_study
    from warpspring.analysis.trade_problems import ClothProblem, SpringProblem

    plan = StudyPlan(
        name="tiny",
        problems=(SpringProblem("spring", DampedOscillator(mass=1.0, damping=0.2, stiffness=4.0, force=1.0),
                                duration=1.0, steps=(16, 32), outputs=4, plot_steps=16),
                  ClothProblem("cloth", size=3, duration=0.02, steps=(4, 8), outputs=2)),
        precisions=("float64",), tolerances=(1e-3,), repeats=1, min_batch=1e-4, run_limit=5.0,
    )
    local = run_study(device, plan=plan, integrators=["symplectic_euler"])
    remote = run_study(device, plan=plan, integrators=["symplectic_euler"], engine=ray_engine)
    timing = {"wall_per_second"}
    assert len(local.rows) == 4
    for a, b in zip(local.rows, remote.rows):
        assert {k: v for k, v in vars(a).items() if k not in timing} == {k: v for k, v in vars(b).items()
                                                                          if k not in timing}
    assert local.trajectories.keys() == remote.trajectories.keys()
    np.testing.assert_array_equal(local.references["cloth"].q, remote.references["cloth"].q)


def test_on_ray_the_stability_map_gives_the_local_limits(device, ray_engine):
    from warpspring.analysis.stability_map import MapPlan, run_map

    plan = MapPlan(name="tiny", zetas=(0.1,), spring_points=4, spring_rounds=1, spring_steps=256, cloth_size=3,
                   cloth_stiffness=(1.0e2,), cloth_steps=256, cloth_resolution=0.2, implicit_steps=32, doublings=0)
    local = run_map(plan, device, integrators=["symplectic_euler"])
    remote = run_map(plan, device, integrators=["symplectic_euler"], engine=ray_engine)
    assert local.springs and local.cloth
    assert remote.springs == local.springs and remote.cloth == local.cloth  # each bracket, bit for bit
    assert remote.predictions.keys() == local.predictions.keys() and set(remote.timings) == set(local.timings)
