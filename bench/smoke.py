"""The benchmarks still build and run: every ``bench/*.py`` imports and has a ``main``, and each benchmark scene,
built by its own script's builder at a tiny size, steps a frame or two to a state that obeys something checkable
in closed form (pins held, free fall where no force has reached yet, pin tracks followed). Speed is not checked
here: it lives in ``RESULTS.md``. ``tests/test_bench_smoke.py`` runs this script (one process for every check)
and reports each check as a test.

    python bench/smoke.py                                  # every check on the CPU, one line each
    python bench/smoke.py --device cpu --device cuda:0 --report smoke.json
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import math
import os
import sys
import tempfile
import traceback
from pathlib import Path

import numpy as np
import warp as wp

import warpspring as ws

import cloth  # (the bench's scenes and runners)

HERE = Path(__file__).resolve().parent
G = 9.81  # [m/s²], the default gravity of every bench scene but worlds.py's
H = 1.0 / (cloth.FPS * cloth.SUBSTEPS)  # [s], the bench's substep

#: The checks, by name: (function, its parameters or (None,), whether it takes a device).
CHECKS: dict = {}


class Skip(Exception):
    """A check that cannot run here (an optional package missing); its message says why."""


def check(*params, device: bool = True):
    """Register a check: ``fn(param, device)``, ``fn(param)``, ``fn(device)`` or ``fn()``."""

    def register(fn):
        CHECKS[fn.__name__] = (fn, params or (None,), device)
        return fn

    return register


def needs(module: str) -> None:
    """Skip the check unless ``module`` can be imported."""
    if importlib.util.find_spec(module) is None:
        raise Skip(f"could not import {module!r}")


def raises(exception, match: str, fn, *args) -> None:
    """``fn(*args)`` raises ``exception`` with a message containing ``match``."""
    try:
        fn(*args)
    except exception as exc:
        assert match in str(exc), f"{exception.__name__} without {match!r}: {exc}"
    else:
        raise AssertionError(f"no {exception.__name__} raised")


def free_fall_drop(g: float, steps: int) -> float:
    """Symplectic Euler's exact drop [m] after ``steps`` steps of H from rest: v_k = g H k, x_k = g H² k(k+1)/2."""
    return g * H * H * steps * (steps + 1) / 2


def positions(state) -> np.ndarray:
    return state.particle_q.numpy().astype(np.float64)


# -- the checks -------------------------------------------------------------------------------------------------


@check(*sorted(path.stem for path in HERE.glob("*.py")), device=False)
def every_bench_script_imports(script):
    assert hasattr(importlib.import_module(script), "main")


@check()
def the_hanging_cloth_holds_its_pins_and_its_bottom_row_falls_freely(device):
    """The ANCHORS cloth (``cloth.warpspring_model``), 16 × 16, one frame of 16 substeps: the pinned corners
    stay exactly where they were; the bottom row, 1.5 m below the pins, falls as a free particle does. The
    pins' pull travels at the longitudinal wave speed, ≈ 0.1 m · √(6 ke / m) ≈ 25 m/s with the bend springs,
    so ~0.4 m in 1/60 s; what the discrete scheme carries ahead of the front decays fast with distance
    (measured: 5e-6 m at 0.9 m, 8e-7 m at 1.1 m, 2e-8 m at 1.5 m), and float32 positions near 1 m round to
    6e-8 m per step: 1e-6 m bounds both at 1.5 m."""
    model = cloth.warpspring_model(16, device)
    start = model.state()
    runner = cloth.WarpspringRunner(model)
    runner.frame()
    q0, q = positions(start), runner.positions().astype(np.float64)
    assert np.isfinite(q).all()
    pinned = model.kinematic_mask()
    np.testing.assert_array_equal(q[pinned], q0[pinned])
    bottom = np.isclose(q0[:, 2], q0[:, 2].min())
    np.testing.assert_allclose(q0[bottom, 2] - q[bottom, 2], free_fall_drop(G, cloth.SUBSTEPS), rtol=0, atol=1e-6)
    np.testing.assert_allclose(q[bottom, :2], q0[bottom, :2], atol=1e-6)


@check()
def newton_runs_the_same_cloth_to_the_same_positions(device):
    """``cloth.NewtonRunner`` (Newton 1.5 or 1.8) on two worlds of the 8 × 8 cloth: both engines integrate the
    same equations, so two frames (32 substeps) agree to float32 summation order: measured 3e-11 m on the
    CPU; on a GPU the orders differ more (2e-6 m after a whole second at 64², RESULTS §1), so 1e-6 m."""
    needs("newton")
    model = cloth.warpspring_model(8, device, worlds=2)
    finals = []
    for engine in (cloth.WarpspringRunner, cloth.NewtonRunner):
        runner = engine(model)
        for _ in range(2):
            runner.frame()
        finals.append(runner.positions())
    np.testing.assert_allclose(finals[1], finals[0], rtol=0, atol=1e-6)


@check()
def worlds_fall_under_their_own_gravity(device):
    """``worlds.batch``: three 32² cloths, each with its own gravity and stiffness, one frame: each world's
    bottom row (3.1 m below its pins) has fallen freely under its own g (tolerance as above)."""
    import worlds

    model = worlds.batch(3, device)
    start = model.state()
    runner = worlds.Batch(model)
    runner.frame()
    n = model.particle_count
    q0, q = positions(start).reshape(3, n, 3), positions(runner.sim.state).reshape(3, n, 3)
    g = -model.world_values("gravity")[:, 2]
    bottom = np.isclose(q0[0, :, 2], q0[0, :, 2].min())
    for w in range(3):
        np.testing.assert_allclose(q0[w, bottom, 2] - q[w, bottom, 2], free_fall_drop(g[w], cloth.SUBSTEPS),
                                   rtol=0, atol=1e-6)


@check("fused", "stage")
def the_contact_scene_falls_as_one_body_before_it_touches(variant, device):
    """``contacts.contact_model`` (a free 6 × 6 cloth 0.1 m above a sphere, the ground below), one frame after
    no settling: nothing touches yet and the springs start at rest, so every particle falls the free-fall
    drop (float32 rounding of |d| - L leaves spring forces ~1e-5 N against 0.98 N of weight)."""
    import contacts

    settle = contacts.SETTLE_FRAMES
    contacts.SETTLE_FRAMES = 0
    try:
        model = contacts.contact_model(6, device, variant)
        q0 = positions(model.state())
        runner = contacts.Runner(model)
        runner.frame()
        q = positions(runner.sim.state)
    finally:
        contacts.SETTLE_FRAMES = settle
    np.testing.assert_allclose(q0[:, 2] - q[:, 2], free_fall_drop(G, cloth.SUBSTEPS), rtol=1e-3)
    np.testing.assert_allclose(q[:, :2], q0[:, :2], atol=1e-6)


@check("wind", "handle", "emitter", "strain limit")
def scene_force_benches_run_and_hold_their_pins(scene, device):
    """The scenes of ``scene_forces.py`` and ``stabilizers.py`` at 6 × 6, two frames: a finite state whose
    pinned corners have not moved (the handle grabs the top row but pins outrank it)."""
    import scene_forces
    import stabilizers

    if scene == "wind":
        model = scene_forces.model_with_wind(6, device, noise=False)
    elif scene == "handle":
        model = scene_forces.model_with_handle(6, device)
    elif scene == "emitter":
        model = scene_forces.model_with_emitter(6, device)
    else:
        model = stabilizers.soft_cloth(6, ws.Stabilizers(max_strain=0.1, strain_iterations=4), device)
    q0 = positions(model.state())[: model.particle_count]
    sim = ws.Simulator(model, fps=cloth.FPS, substeps=cloth.SUBSTEPS, guard=None)
    for _ in range(2):
        sim.step_frame()
    q = positions(sim.state)
    assert np.isfinite(q).all()
    pinned = model.kinematic_mask()
    np.testing.assert_array_equal(q[: model.particle_count][pinned], q0[pinned])


@check()
def the_soak_scene_follows_its_pin_track(device):
    """``soak.driven_cloth`` at 6 × 6, one frame: the two driven pins moved along x only, by the smooth track's
    value at 1/60 s (0 → 0.2 m over 0.5 s; its PCHIP sample on the host), to float32 rounding."""
    import soak

    model = soak.driven_cloth(device, n=6)
    q0 = positions(model.state())
    sim = ws.Simulator(model, fps=cloth.FPS, substeps=cloth.SUBSTEPS, guard=None)
    sim.step_frame()
    q = positions(sim.state)
    swing = ws.Track([0.0, 0.5, 1.0, 1.5, 2.0], [[0, 0, 0], [0.2, 0, 0], [0, 0, 0], [-0.2, 0, 0], [0, 0, 0]],
                     interpolation="smooth", extrapolation="cycle")
    offset = swing.sample(1.0 / cloth.FPS)[0][0]
    assert offset[0] > 1e-4  # the check below is not vacuous
    pinned = model.kinematic_mask()
    np.testing.assert_allclose(q[pinned] - q0[pinned], np.broadcast_to(offset, q[pinned].shape), atol=1e-6)


@check()
def the_delaunay_network_holds_its_pinned_base(device):
    """``adjacency.network_model`` on 200 random points (a hybrid ELL + CSR incidence), one frame: finite, the
    pinned bottom 5 % unmoved."""
    import adjacency

    points, springs = adjacency.delaunay_springs(200)
    model = adjacency.network_model(points, springs, device, "gather")
    q0 = positions(model.state())
    sim = ws.Simulator(model, fps=cloth.FPS, substeps=cloth.SUBSTEPS, guard=None)
    sim.step_frame()
    q = positions(sim.state)
    assert np.isfinite(q).all()
    pinned = model.kinematic_mask()
    assert pinned.any()
    np.testing.assert_array_equal(q[pinned], q0[pinned])


@check()
def the_usd_stream_bench_writes_its_frames(device):
    """``usd_stream.stream`` writes two frames of the 6 × 6 cloth to a file that reads back with both samples."""
    import usd_stream
    from pxr import Usd, UsdGeom

    model = usd_stream.cloth(6, device)
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "stream.usdc")
        result = usd_stream.stream(model, path, frames=2)
        assert len(result["times"]) == 2
        stage = Usd.Stage.Open(path)
        meshes = [prim for prim in stage.Traverse() if prim.IsA(UsdGeom.Mesh)]
        assert meshes and len(UsdGeom.Mesh(meshes[0]).GetPointsAttr().GetTimeSamples()) == 2
        del stage


@check(device=False)
def the_build_bench_counts_the_anchors_springs():
    """``build.warpspring_build``: an n × n cloth has 2n(n-1) structural, 2(n-1)² shear, 2n(n-2) bend springs."""
    import build

    _, particles, springs = build.warpspring_build(8)
    assert (particles, springs) == (64, 2 * 8 * 7 + 2 * 7 * 7 + 2 * 8 * 6)


@check(device=False)
def the_traffic_model_counts_the_gathers_arrays():
    """``traffic.gather_traffic`` on the 8 × 8 cloth, one and four worlds, against counts made by hand from the
    kernel: 48 B of state (x, v in and out, 12 B each), 12 B per particle of flags and masses, 2 × 12 slots ×
    4 B of incidence, 12 B per spring (rest length, ke, kd); shared arrays divide among the worlds."""
    import traffic

    for worlds in (1, 4):
        model = cloth.warpspring_model(8, "cpu", "gather", worlds=worlds, spring_groups=False)
        b = traffic.per_particle(traffic.gather_traffic(model), model)
        assert b["state"] == 48.0
        assert b["topology"] == 2 * 12 * 4 / worlds
        np.testing.assert_allclose(b["spring"], 12 * 306 / (64 * worlds))
        np.testing.assert_allclose(b["particle"], 4 + 8 / worlds + (model.inputs.shape[1] * 4 + 16) / 64)
        assert b["requested"] > b["compulsory"]
    raises(ValueError, "spring_evaluation='gather'", traffic.gather_traffic,
           cloth.warpspring_model(8, "cpu", "scatter"))


@check(device=False)
def the_traffic_model_counts_spring_data_per_group():
    """With spring data per group over the incidence table (``spring_grid=False``; structural, shear and bend each
    uniform), by hand: the same 48 B of state and 12 B of flags and masses, 12 slots × 4 B of other particles
    (no spring index), and per group its spring and three values, 3 × (4 + 3 × 4) B for the whole model; a
    non-uniform group's slots add their spring index and its springs' values."""
    import traffic

    for worlds in (1, 4):
        model = cloth.warpspring_model(8, "cpu", "gather", worlds=worlds, spring_grid=False)
        assert model.spring_slot_groups == (0,) * 4 + (1,) * 4 + (2,) * 4 and model.spring_layout == "groups"
        rows = traffic.gather_traffic(model)
        assert "head_element" not in [r.name for r in rows]
        b = traffic.per_particle(rows, model)
        assert b["state"] == 48.0
        assert b["topology"] == 12 * 4 / worlds
        np.testing.assert_allclose(b["spring"], 3 * (4 + 3 * 4) / (64 * worlds))
        np.testing.assert_allclose(b["particle"], 4 + 8 / worlds + (model.inputs.shape[1] * 4 + 16) / 64)
    # One structural spring's ke doubled: the structural slots read per spring again, spring index and values
    # of its 112 springs, each 4 B of index and 12 B of values; shear and bend stay per group.
    ke = model.world_values("spring_stiffness")[0].copy()
    ke[0] *= 2.0
    model.set_world_values("spring_stiffness", ke)
    assert model.spring_slot_groups == (-1,) * 4 + (1,) * 4 + (2,) * 4
    b = traffic.per_particle(traffic.gather_traffic(model), model)
    assert b["topology"] == (12 + 4) * 4 / 4
    np.testing.assert_allclose(b["spring"], (3 * (4 + 3 * 4) + 112 * 12) / (64 * 4))


@check(device=False)
def the_traffic_model_counts_the_grid_layout():
    """On the grid layout (the gathered cloth's default), by hand: 48 B of state, 12 B of flags and masses, the
    groups' 3 × (4 + 3 × 4) B, and of topology only the grid's size (nx, ny), 8 B for the model: a uniform
    group's slot loads no table entry. A non-uniform group's 4 slots load the table's two ints again."""
    import traffic

    for worlds in (1, 4):
        model = cloth.warpspring_model(8, "cpu", "gather", worlds=worlds)
        assert model.spring_layout == "grid"
        rows = traffic.gather_traffic(model)
        assert not {"head_element", "head_local"} & {r.name for r in rows}
        b = traffic.per_particle(rows, model)
        assert (b["state"], b["topology"]) == (48.0, 8 / (64 * worlds))
        np.testing.assert_allclose(b["spring"], 3 * (4 + 3 * 4) / (64 * worlds))
        np.testing.assert_allclose(b["particle"], 4 + 8 / worlds + (model.inputs.shape[1] * 4 + 16) / 64)
    ke = model.world_values("spring_stiffness")[0].copy()
    ke[0] *= 2.0
    model.set_world_values("spring_stiffness", ke)
    assert model.spring_layout == "grid" and model.spring_slot_groups == (-1,) * 4 + (1,) * 4 + (2,) * 4
    b = traffic.per_particle(traffic.gather_traffic(model), model)
    assert b["topology"] == (4 + 4) * 4 / 4 + 8 / (64 * 4)


@check(device=False)
def ncu_output_is_read_in_base_units():
    """``traffic.parse_ncu_csv`` on Nsight Compute's CSV layout: values with thousands separators and unit
    prefixes come back in bytes and seconds; other lines are ignored."""
    import traffic

    header = '"ID","Kernel Name","Metric Name","Metric Unit","Metric Value"'
    text = "\n".join([
        "==PROF== Connected to process 1",
        header,
        '"0","symplectic_euler","dram__bytes_read.sum","byte","244,891,136"',
        '"0","symplectic_euler","dram__bytes_write.sum","Mbyte","25.5"',
        '"0","symplectic_euler","gpu__time_duration.sum","usecond","111.9"',
    ])
    parsed = traffic.parse_ncu_csv(text)
    assert set(parsed) == {"dram__bytes_read.sum", "dram__bytes_write.sum", "gpu__time_duration.sum"}
    assert parsed["dram__bytes_read.sum"] == 244891136.0 and parsed["dram__bytes_write.sum"] == 25.5e6
    assert math.isclose(parsed["gpu__time_duration.sum"], 111.9e-6, rel_tol=1e-6)
    # `--print-units base` as the H100 machine's Nsight Compute prints a duration: "ns"
    base = text.replace('"usecond","111.9"', '"ns","111,900"')
    assert math.isclose(traffic.parse_ncu_csv(base)["gpu__time_duration.sum"], 111.9e-6, rel_tol=1e-6)


@check(device=False)
def the_scaling_plot_draws_a_csv():
    """``scaling_plot.plot`` draws the CSV layout ``scaling.py`` writes into a PNG."""
    needs("matplotlib")
    import scaling
    import scaling_plot

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scaling.csv"
        rows = [",".join(map(str, [engine, scene, side, worlds, side * side * worlds, 0.1, 1000.0,
                                   1000.0 * side * side * worlds, 0.01]))
                for engine in ("warpspring (gather)", "newton 1.8.0")
                for scene, side, worlds in scaling.scenes([16, 32], [4, 16])]
        path.write_text("# test machine; Warp 1.19.0; 2026-11-25; wp.copy 10.0 GB/s; gather 228 B/particle-substep\n"
                        + ",".join(scaling.COLUMNS) + "\n" + "\n".join(rows) + "\n")
        scaling_plot.plot(str(path), str(Path(folder) / "scaling.png"))
        assert (Path(folder) / "scaling.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@check()
def the_integrator_bench_tells_a_stable_run_from_a_blow_up(device):
    """``integrators.one_second`` and ``blown_up`` on the 8 × 8 ANCHORS cloth: symplectic Euler at 16 substeps per
    frame (ω_max h ≈ 305 rad/s × 1.04 ms ≈ 0.32, well within its limit) ends 1 s with less mechanical energy than it
    started with (the springs' damping); at one step per frame (ω_max h ≈ 5) the energy test flags the blow-up.
    Pins hold in the stable run."""
    import integrators
    from warpspring.analysis.trade_problems import SpringNetwork

    model = integrators.anchors_model(8, device)
    network = SpringNetwork.of(model)
    q, qd = integrators.one_second(model, "symplectic_euler", cloth.SUBSTEPS)
    assert not integrators.blown_up(network, q, qd)
    assert network.energy(q, qd) < 0.0  # damped: below the start (at rest, springs at rest)
    pinned = model.kinematic_mask()
    np.testing.assert_array_equal(q[pinned], network.initial_q[pinned])
    assert integrators.blown_up(network, *integrators.one_second(model, "symplectic_euler", 1))


@check()
def the_floor_bench_counts_graph_nodes_and_its_update_only_cloth_falls_freely(device):
    """``integrators.Counting`` counts what a substep records (launches, memsets, copies; a fill inside a copy once),
    and ``update_only_model`` keeps the 8 × 8 cloth's particles and pins without springs: after one frame every
    free particle has fallen exactly symplectic Euler's free-fall drop, the pins not at all."""
    import integrators

    trivial = integrators.TrivialRunner(device, 64)
    trivial.frame()
    scratch, ones = wp.zeros(4, dtype=float, device=device), wp.ones(4, dtype=float, device=device)
    with integrators.Counting() as count:
        for _ in range(3):
            trivial.substep()
        scratch.zero_()
        scratch.assign(np.ones(4, dtype=np.float32))
        wp.copy(scratch, ones)
    assert count.counts == {"launch": 3, "memset": 1, "copy": 2}
    bare = integrators.update_only_model(cloth.warpspring_model(8, device))
    assert bare.spring_count == 0 and bare.particle_count == 64
    q0 = positions(bare.state())
    runner = cloth.WarpspringRunner(bare)
    runner.frame()
    q = runner.positions().astype(np.float64)
    pinned = bare.kinematic_mask()
    assert pinned.sum() == 2
    np.testing.assert_array_equal(q[pinned], q0[pinned])
    np.testing.assert_allclose(q0[~pinned, 2] - q[~pinned, 2], free_fall_drop(G, cloth.SUBSTEPS), rtol=0, atol=1e-6)


@check(device=False)
def the_vbd_bench_colours_the_spring_graph():
    """``vbd.spring_coloring`` of the 8 × 8 cloth's springs: every particle in exactly one colour, no spring
    (structural, shear or bend) joining two particles of one colour, which VBD's Gauss–Seidel sweep needs."""
    import vbd

    model = cloth.warpspring_model(8, "cpu")
    springs = model.spring_indices.numpy().reshape(-1, 2)
    color = np.full(model.particle_count, -1)
    for c, group in enumerate(vbd.spring_coloring(springs, model.particle_count)):
        assert (color[group] == -1).all()
        color[group] = c
    assert (color >= 0).all()
    assert (color[springs[:, 0]] != color[springs[:, 1]]).all()


@check()
def newtons_vbd_and_implicit_euler_take_the_same_backward_euler_step(device):
    """``vbd.VBDRunner`` (Newton 1.5 or 1.8, 50 iterations) and warpspring's implicit Euler on the 8 × 8 cloth, 4
    substeps per frame for 6 frames: both approximate backward Euler of the same springs (VBD solves it, implicit
    Euler takes one linearised Newton step of it), so they differ far less than implicit Euler does from itself at
    half the step (the time discretisation's error): measured 1.4e-5 m against 6.5e-4 m on the CPU."""
    needs("newton")
    import integrators
    import vbd

    model = integrators.anchors_model(8, device)

    def six_frames(runner):
        for _ in range(6):
            runner.frame()
        return runner.final()[0]

    implicit = six_frames(integrators.StepperRunner(model, "implicit_euler", 4))
    finer = six_frames(integrators.StepperRunner(model, "implicit_euler", 8))
    newton_vbd = six_frames(vbd.VBDRunner(model, 4, 50))
    step_error = np.abs(implicit - finer).max()
    assert step_error > 1e-4  # the comparison below is not vacuous
    assert np.abs(newton_vbd - implicit).max() < 0.1 * step_error


@check(device=False)
def the_vbd_bench_reads_cost_at_equal_error_off_the_pareto_front():
    """``vbd.cost_at_error``: a dominated point (dearer and less accurate) leaves the front; between two front points
    the cost is linear in log cost against log error (error 10⁻².⁵ between (3, 10⁻²) and (10, 10⁻³): √30);
    outside the front's errors there is none."""
    import vbd

    points = [(1.0, 0.1), (2.0, 0.2), (3.0, 0.01), (10.0, 0.001)]
    assert vbd.pareto_front(points) == [(1.0, 0.1), (3.0, 0.01), (10.0, 0.001)]
    assert math.isclose(vbd.cost_at_error(points, 0.01), 3.0, rel_tol=1e-6)
    assert math.isclose(vbd.cost_at_error(points, 10**-2.5), 30**0.5, rel_tol=1e-6)
    assert vbd.cost_at_error(points, 0.5) is None and vbd.cost_at_error(points, 1e-4) is None


@check(device=False)
def the_battery_plot_reads_every_case_of_a_battery_table():
    """``plot_advisor_battery.read_rows`` on tables written by ``load_battery.table`` (two sections, as in a
    results file, one case measured again in the second): every case comes back once, the last measurement of a
    case kept, with the cells the table wrote; the reader's ``stiffness`` turns a cell into N/m (NaN for none)."""
    import plot_advisor_battery as plot
    from warpspring.analysis.load_battery import LoadCase, table

    def case(scene, integrator, substeps, blow_up, passed, **limits):
        return LoadCase(scene=scene, integrator=integrator, substeps=substeps, dt=1.0 / (60 * substeps),
                        blow_up=blow_up, passed=passed, unsafe=0, torn=0.0, runs=64, seconds=1.0, **limits)

    first = [case("hanging", "midpoint", 16, 1111.0, 668.6, linear=694.9, grows=718.9),
             case("windy", "midpoint", 16, 1138.0, 668.6, grows=718.9),
             case("driven", "rk4", 4, 6421.0, 5000.0, grows=float("inf"))]
    second = [case("driven", "rk4", 4, 6421.0, 5922.0, grows=float("inf")),
              case("pulled", "rk4", 4, np.inf, 5922.0, grows=6400.0)]
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "battery.md")
        with open(path, "w") as f:
            f.write("# A battery\n\n## First\n\n" + "\n".join(table(first)) + "\n\n## Again\n\n"
                    + "\n".join(table(second)) + "\n")
        rows = plot.read_rows(path)
    expected = [first[0], first[1], second[0], second[1]]
    assert [(r["scene"], r["integrator"]) for r in rows] == [(c.scene, c.integrator) for c in expected]
    for row, c in zip(rows, expected):
        assert plot.stiffness(row["advisor passes up to"]) == float(f"{c.passed:.4g}")
        assert row["passed but blew up"] == "0" and row["passed but grows"] == "0"
        assert float(row["ratio to the lowest"]) == float(f"{c.ratio_to_limit:.3f}")
    assert np.isnan(plot.stiffness(rows[3]["blows up from ke"]))  # "none in the grids"
    assert plot.stiffness("1.247e+04 N/m") == 12470.0 and np.isnan(plot.stiffness("–"))


# -- running them -----------------------------------------------------------------------------------------------


@check(device=False)
def the_cpu_bench_times_two_trees_and_counts_a_plain_cloths_launches():
    """``cpu_launches.run_size`` on the CPU, 4 × 4 cloth, this tree against itself, two rounds: every row has a
    positive rate and a ratio to the first tree (the same code: the ratio is only noise, so it is not bounded
    here), and the counted launches per substep are the plain cloth's one fused step (guard off, ``auto``: on the
    CPU the sweep, ``kernels/sweep.py``)."""
    import cpu_launches

    trees = {"new": str(HERE.parent), "same": str(HERE.parent)}
    rows, workers = cpu_launches.run_size(4, trees, ["off"], batches=2, seconds=0.01, launches=True, repeat=2,
                                          newton=False)
    assert [(r["tree"], r["engine"]) for r in rows] == [("new", "off"), ("same", "off")]
    assert all(r["substeps_per_s"] > 0 and len(r["times"]) == 2 for r in rows)
    assert "vs_first" in rows[1]
    for worker in workers:
        profile = worker.info["launches"]["off"]
        assert profile["frame_launches"] == worker.info["substeps"], profile
        assert list(profile["by_kernel"]) == ["symplectic_euler_sweep_kernel__locals__symplectic_euler_sweep"], profile


@check(device=False)
def the_cloth_bench_times_the_default_guard_off_and_newton_on_the_cpu():
    """``cloth.size_rows`` on the CPU, 6 × 6 cloth, interleaved, two rounds of one-frame batches: a row each for the
    default Simulator (guard on), the guard off and Newton where installed, each with a positive rate; the default row
    carries its ratio to guard off, and with Newton both warpspring rows their ratio to it (how fast is not checked)."""
    newton = cloth.installed_newton(importlib.util.find_spec("newton") is not None)
    rows, results, _ = cloth.size_rows(6, wp.get_device("cpu"), ["auto"], ["default", "off"], newton, pin="top",
                                       seconds=0.0, batches=2, interleave=True, drift_frames=2)
    names = ["warpspring (gather, default guard)", "warpspring (gather, guard off)"] + (["newton"] if newton else [])
    assert list(results) == names and len(rows) == len(names), (list(results), rows)
    assert all(r["frame_s"] > 0 and len(r["times"]) == 2 for r in results.values())
    cells = [row.split("|") for row in rows]
    assert cells[0][9].strip() and not cells[1][9].strip()  # the default row's "vs guard off"
    if newton:
        assert all(c[10].strip().endswith("×") for c in cells[:2])


def run(name: str, param, device: str | None) -> dict:
    """Run one check: {"check", "param", "device", "status" ("passed", "failed" or "skipped"), "detail"}."""
    fn, _, _ = CHECKS[name]
    args = [a for a in (param, device) if a is not None]
    result = {"check": name, "param": param, "device": device, "status": "passed", "detail": ""}
    try:
        fn(*args)
    except Skip as exc:
        result.update(status="skipped", detail=str(exc))
    except Exception:  # noqa: BLE001  (a failed check is reported, and the others still run)
        result.update(status="failed", detail=traceback.format_exc())
    return result


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", action="append", help="Warp device of the scene checks, repeatable (default cpu)")
    parser.add_argument("--report", help="also write every check's result to this JSON file")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    devices = args.device or ["cpu"]
    results = []
    for name, (_, params, on_device) in CHECKS.items():
        for param in params:
            for device in devices if on_device else [None]:
                result = run(name, param, device)
                results.append(result)
                label = name + (f"[{param}]" if param is not None else "") + (f" on {device}" if device else "")
                print(f"{result['status']:8} {label}" + (f": {result['detail']}" if result["status"] == "skipped" else ""),
                      flush=True)
                if result["status"] == "failed":
                    print(result["detail"], file=sys.stderr, flush=True)
    if args.report:
        with open(args.report, "w") as f:
            json.dump(results, f, indent=1)
    failed = sum(r["status"] == "failed" for r in results)
    print(f"{len(results)} checks: {failed} failed, {sum(r['status'] == 'skipped' for r in results)} skipped")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
