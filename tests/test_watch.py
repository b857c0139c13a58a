"""The stability advisor during a run (StabilityWatch): a state that stiffens toward its step's limit is
warned about, with the substeps it needs, before the run blows up; a run well inside it is not."""

import warnings

import numpy as np
import pytest

import warpspring as ws
from helpers import battery_cloth, run_frames
from warpspring.analysis.watch import WATCH_MARGIN, StabilityWatch


def _run(device, stiffness, *, frames, substeps=1, integrator="rk4", watch=5):
    model = battery_cloth(device, [stiffness])
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=substeps,
                       guard=ws.GuardLimits(energy_balance=0.0))
    stability_watch = StabilityWatch.attach(sim, every=watch)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_frames(sim, frames)
    return sim, stability_watch, [w.message for w in caught if isinstance(w.message, ws.StabilityWarning)]


def test_a_cloth_stiffening_under_load_is_warned_before_it_blows_up(device):
    """RK4 at 1/60 s on the battery cloth at ke = 480 N/m: stable where it starts (flat and unstretched), not
    once its corners stretch under its weight (the energy balance stops it near frame 32). The watch, every
    5 frames, warns within the first 30, naming the substeps; the ω_max it sees is the loaded one, above
    the start's."""
    _, watch, found = _run(device, 480.0, frames=30)
    assert found, "no StabilityWarning"
    message = str(found[0])
    assert message.startswith("frame ") and int(message.split(":")[0].split()[1]) <= 30
    needed = watch.warned[0]
    assert needed >= 2 and f"--substeps {needed}" in message
    assert watch.omega[0] >= WATCH_MARGIN * watch.omega_limit[0]


def test_a_run_inside_its_limit_is_not_warned(device):
    """The same cloth at 10 substeps (a tenth of the step) sags to the same state without a warning; the
    watch's ω_max there agrees with the advisor linearised about the frame's state within 1 %."""
    from warpspring.analysis.omega import estimate_omega_max

    sim, watch, found = _run(device, 480.0, frames=30, substeps=10)
    assert not found
    reference = estimate_omega_max(sim.model, state=sim.state, tolerance=1e-6, max_iterations=5000).omega_max
    watch.collect()  # on CUDA the re-check after frame 30 is read at the next one
    assert watch.frame == 30
    assert watch.omega[0] == pytest.approx(reference, rel=0.01)


def test_implicit_euler_is_not_watched(device):
    """An unconditionally stable step has no limit to approach: the watch stays idle."""
    _, watch, found = _run(device, 480.0, frames=5, integrator="implicit_euler")
    assert not found and not watch.active and np.isinf(watch.omega_limit).all()


def _moving_collider_cloth(device, *, moving: bool):
    """An 8 × 8 cloth of 10 g particles on 1 kN/m springs hung from its top row, and a sphere 5 m below it that
    never reaches it; ``moving``: the sphere slides sideways (a moving collider: the guard's energy balance off)."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=1.0e3, kd=0.01)
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, particle_mass=0.01, structural=spring, shear=spring,
                           pin=["top"])
    track = ws.Track([0.0, 1.0], [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]) if moving else None
    builder.add_collider_sphere(center=(0.35, 0.0, -5.0), radius=0.5, translation=track)
    return builder.finalize(device)


def _run_watched(device, *, moving: bool, factor: float, frames: int):
    """The cloth above under symplectic Euler at ``factor`` times the advisor's stable step at its start, watched
    after every frame with ``stop = WATCH_STOP``; returns the simulator, the watch and the stop (or ``None``)."""
    from warpspring.analysis.watch import WATCH_STOP

    model = _moving_collider_cloth(device, moving=moving)
    advice = ws.advise(model, "symplectic_euler", 1.0e-3, fps=60)
    h = factor * advice.dt_stable
    substeps = max(1, int(1.0 / (60.0 * h)))
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=1.0 / (substeps * h),
                       substeps=substeps)
    watch = StabilityWatch.attach(sim, every=1, advice=advice, stop=WATCH_STOP)
    watch.notify = lambda message: None
    try:
        run_frames(sim, frames)
    except ws.SimulationError as stop:
        return sim, watch, stop
    return sim, watch, None


def test_a_state_past_its_limit_stops_the_run_where_the_balance_is_off(device):
    """With a moving collider the guard's balance is off, and a step twice the stable limit is stopped by the watch
    at its first re-check (frame 1 on the CPU, read at the next frame on CUDA), for the stability limit, the
    message naming the ratio, why the balance is off, the springs and the collider, and a remedy."""
    sim, watch, stop = _run_watched(device, moving=True, factor=2.0, frames=10)
    assert not sim.guard.balance_applies()
    assert stop is not None and stop.reason == "stability limit", stop
    assert stop.frame == (1 if str(device) == "cpu" else 2)
    ratio = watch.omega[0] / watch.omega_limit[0]
    assert 1.9 < ratio < 2.1  # (the start's ω_max, the step twice its limit)
    message = str(stop)
    assert message.startswith("frame 1: ") and f"{ratio:.2f}× the" in message
    assert "energy balance off in this scene (the work of moving colliders is not counted) no growth is seen" in message
    assert "the springs at particle" in message and "contacts with 1 collider" in message
    assert "Remedy: run with substeps = " in message


def test_the_watch_leaves_a_stable_run_alone_and_stops_past_the_limit_with_the_balance_on(device):
    """The same scene at 0.9 times the stable limit runs on; without the moving collider (the balance on) the step
    twice the limit is stopped too, by the watch where the balance has not yet seen the growth (its verdict is the
    advisor's), the message saying what the balance does not count."""
    _, watch, stop = _run_watched(device, moving=True, factor=0.9, frames=10)
    assert stop is None and watch.frame >= 9 and watch.omega[0] < watch.omega_limit[0]
    sim, _, stop = _run_watched(device, moving=False, factor=2.0, frames=10)
    assert sim.guard.balance_applies()
    assert stop is not None and stop.frame <= 2, stop
    if stop.reason == "stability limit":
        assert "the guard's energy balance, which does not count" in str(stop), str(stop)


def test_with_stop_world_the_watch_holds_the_world_past_its_limit(device):
    """Two worlds of the moving-collider cloth, the second's springs 1.6 times stiffer (1.26 times the first's ω_max)
    at 0.9 of the first's stable step (1.14 times the second's), the guard stopping single worlds: the watch holds the
    second after its first re-check (on CUDA read a frame later; the top mode grows 64 times a frame at that step, so
    the guard's own checks have not yet seen it) and records it at the frame it judged (reason "stability limit", its
    ratio, a line that names it); the first runs on, and its positions move while the held world's stay as they
    were."""
    from warpspring.analysis.watch import WATCH_STOP

    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=1.0e3, kd=0.01)
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, particle_mass=0.01, structural=spring, shear=spring, pin=["top"])
    builder.add_collider_sphere(center=(0.35, 0.0, -5.0), radius=0.5,
                                translation=ws.Track([0.0, 1.0], [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]))
    model = builder.finalize(device, worlds=2)
    stiffness = model.world_values("spring_stiffness").copy()
    stiffness[1] *= 1.6
    model.set_world_values("spring_stiffness", stiffness)
    advice = ws.advise(model, "symplectic_euler", 1.0e-3, fps=60)
    h = 0.9 * advice.world_dt_stable[0]
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=1.0 / (4 * h), substeps=4,
                       guard=ws.GuardLimits(stop="world"))
    watch = StabilityWatch.attach(sim, every=1, advice=advice, stop=WATCH_STOP)
    watch.notify = lambda message: None
    run_frames(sim, 2)
    before = sim.state.particle_q.numpy().reshape(2, -1, 3).copy()
    run_frames(sim, 3)
    assert list(sim.world_failures) == [1]
    frame, report = sim.world_failures[1]
    assert frame == 1 and report.reason == "stability limit", (frame, report)
    assert 0.9 * 1.6 ** 0.5 * 0.95 < report.stability_ratio <= 0.9 * 1.6 ** 0.5 * 1.001  # (estimated from below)
    assert "passed its step's stability limit" in sim.describe_failure(1)
    positions = sim.state.particle_q.numpy().reshape(2, -1, 3)
    assert np.array_equal(positions[1], before[1])
    assert np.isfinite(positions[0]).all() and not np.array_equal(positions[0], before[0]) and sim.frame == 5


def test_a_re_check_left_pending_across_a_reset_is_dropped(device):
    """A re-check read a frame later (CUDA) judges the frame it was started after: one still pending when the
    simulator was reset (or loaded a checkpoint) is dropped, not read at the new run's frames; a report of the watch
    without its ratio reads as a sentence."""
    from warpspring.core.guard_records import GuardReport

    sim, watch, stop = _run_watched(device, moving=True, factor=0.9, frames=3)
    assert stop is None
    read = []
    collect = watch.collect
    watch.collect = lambda: (read.append(watch._pending), collect())
    watch._pending = 7  # (as if frame 7's re-check were still running when the run was reset)
    sim.reset()
    sim.step_frame()
    watch.collect()  # (frame 1's re-check: read at once on the CPU, at the next frame on CUDA)
    assert 7 not in read and watch.frame == 1
    report = GuardReport(world=0, reason="stability limit", substep=0, particle=None, spring=None, strain=-1.0,
                         kinetic_energy=0.0)
    assert report.describe(sim.model) == "the state passed its step's stability limit (by the stability watch)"
