"""Worlds: many copies of a scene in one model, each solved on its own.

The reference for a world of a batch is the same world run alone: a model of one world given that world's
parameters. Worlds share every launch but no value (each reduction, solver scalar and step-size
controller is per world, and no float atomics reach the state), so a world's trajectory must not depend
on its neighbours. We compare bit for bit: the explicit methods evaluate the same float operations in the
same order in both runs; implicit Euler's CG and dopri5's controller reduce each world's values in a fixed
order over the same blocks, and stop by the world's own test, so they too must agree exactly (the issue
allows a tolerance derived from the solvers' own; exact agreement is the stronger check).
"""

import numpy as np
import pytest

import warpspring as ws
from warpspring.core.integrators import make_integrator

WORLDS = 256
STEPS = 8
DT = 2.0e-3
INTEGRATORS = ["symplectic_euler", "explicit_euler", "midpoint", "rk4", "velocity_verlet", "implicit_euler", "dopri5"]


def cloth_builder() -> ws.ModelBuilder:
    """A 4 × 4 cloth whose top edge is a pin group swung by a translation track."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=4, ny=4, spacing=0.1, rotation=(0.7071068, 0.0, 0.0, 0.7071068), mass=16.0)
    builder.add_pin_group([12, 13, 14, 15], translation=ws.Track([0.0, 1.0], [[0, 0, 0], [0.1, 0, 0]]), name="edge")
    return builder


def parameters(worlds: int) -> dict:
    """Per-world parameters, all different: gravity, drag, stiffness, damping, mass, a speed limit, and the
    pin group's track."""
    rng = np.random.default_rng(7)
    return {
        "gravity": np.stack([rng.uniform(-1, 1, worlds), rng.uniform(-1, 1, worlds), -rng.uniform(1, 20, worlds)], 1),
        "drag": rng.uniform(0.01, 0.2, worlds),
        "stiffness": rng.uniform(0.25, 4.0, worlds),
        "damping": rng.uniform(0.0, 2.0, worlds),
        "mass": rng.uniform(0.5, 2.0, worlds),
        "max_speed": rng.uniform(0.5, 5.0, worlds),
        "swing": [ws.Track([0.0, 0.02], [[0, 0, 0], [a, 0, 0]]) for a in rng.uniform(-0.2, 0.2, worlds)],
    }


def configure(model: ws.Model, p: dict, worlds: slice) -> None:
    """Give the model's worlds the parameters of ``worlds`` (all of them, or one world's alone)."""
    base_ke = model.world_values("spring_stiffness")[0]
    base_kd = np.full_like(base_ke, 0.5)
    base_mass = model.world_values("particle_mass")[0]
    model.stabilizers = ws.Stabilizers(max_speed=1.0)
    model.set_world_values("gravity", p["gravity"][worlds])
    model.set_world_values("drag", p["drag"][worlds])
    model.set_world_values("max_speed", p["max_speed"][worlds])
    model.set_world_values("spring_stiffness", base_ke[None, :] * p["stiffness"][worlds, None])
    model.set_world_values("spring_damping", base_kd[None, :] * p["damping"][worlds, None])
    model.set_world_values("particle_mass", base_mass[None, :] * p["mass"][worlds, None])
    for w, track in enumerate(p["swing"][worlds]):
        model.set_pin_group_tracks("edge", translation=track, world=w)


def run(model: ws.Model, integrator: str, steps: int = STEPS):
    state_in, state_out = model.state(), model.state()
    stepper = make_integrator(integrator, model)
    for _ in range(steps):
        stepper.step(state_in, state_out, None, DT)
        state_in, state_out = state_out, state_in
    return state_in, stepper


@pytest.fixture(scope="module")
def batch_parameters():
    return parameters(WORLDS)


# On the CPU the worlds of the batch run alone as references are every 7th (0, 7, ..., 252) and the last. 7 is
# odd, so the 37 multiples cover every residue modulo 32: each position inside any power-of-two block of up to
# 32 worlds (how launches, tiles and reductions group worlds) is checked, no block of 8 worlds is skipped, and
# the last world (the partial block's edge) is in. Running all 256 alone cost 6-14 s per integrator on the
# CPU; these 38 cost a seventh of it, while the batch itself still holds all 256 worlds. On CUDA all 256 run.
CHECKED_ON_CPU = sorted({*range(0, WORLDS, 7), WORLDS - 1})


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_each_world_of_a_batch_equals_the_world_run_alone(device, integrator, batch_parameters):
    """A batch of 256 worlds, each with its own parameters, steps; each world (on the CPU those in
    ``CHECKED_ON_CPU``) equals, bit for bit, that world run alone (positions, velocities and time)."""
    p = batch_parameters
    batch = cloth_builder().finalize(device, worlds=WORLDS)
    configure(batch, p, slice(None))
    state, _ = run(batch, integrator)
    n = batch.particle_count
    q = state.particle_q.numpy().reshape(WORLDS, n, 3)
    qd = state.particle_qd.numpy().reshape(WORLDS, n, 3)
    # Every world reaches the same time (an adaptive world sums its own steps: equal to rounding).
    np.testing.assert_allclose(state.time.numpy(), STEPS * DT, rtol=1e-14)
    alone_builder = cloth_builder()
    spread = []
    for w in CHECKED_ON_CPU if device == "cpu" else range(WORLDS):
        alone = alone_builder.finalize(device)
        configure(alone, p, slice(w, w + 1))
        reference, _ = run(alone, integrator)
        np.testing.assert_array_equal(q[w], reference.particle_q.numpy(), err_msg=f"world {w} positions")
        np.testing.assert_array_equal(qd[w], reference.particle_qd.numpy(), err_msg=f"world {w} velocities")
        np.testing.assert_array_equal(state.time.numpy()[w], reference.time.numpy()[0])
        spread.append(np.abs(q[w] - q[0]).max())
    # The worlds really differ (the comparison would pass for copies of one world otherwise).
    assert np.median(spread[1:]) > 1e-4


def test_cg_iterations_and_dopri5_steps_are_per_world(device):
    """Stiffer worlds need more CG iterations and more dopri5 steps; each world's count equals its count alone."""
    scales = np.array([1.0, 30.0, 1000.0])
    batch = cloth_builder().finalize(device, worlds=len(scales))
    base = batch.world_values("spring_stiffness")[0]
    batch.set_world_values("spring_stiffness", base[None, :] * scales[:, None])
    batch.gravity = (0.0, 0.0, -9.81)
    _, implicit = run(batch, "implicit_euler", steps=2)
    iterations, residual, rhs = implicit.world_solve_report()
    assert iterations[0] < iterations[1] < iterations[2]
    assert (residual <= implicit.cg_tolerance * rhs).all()
    _, dopri5 = run(batch, "dopri5", steps=2)
    accepted = dopri5.world_steps()["accepted"]
    assert accepted[0] < accepted[1] < accepted[2]
    for w, scale in enumerate(scales):
        alone = cloth_builder().finalize(device)
        alone.set_world_values("spring_stiffness", base * scale)
        alone.gravity = (0.0, 0.0, -9.81)
        _, solo = run(alone, "implicit_euler", steps=2)
        assert solo.solve_report()[0] == iterations[w]
        _, solo = run(alone, "dopri5", steps=2)
        assert solo.accepted_steps == accepted[w]


def test_a_world_that_blows_up_is_named_and_held_without_touching_the_others(device):
    worlds, bad = 6, 3
    stiffness = np.ones(worlds)
    healthy = cloth_builder().finalize(device, worlds=worlds)
    blowing = cloth_builder().finalize(device, worlds=worlds)
    base = healthy.world_values("spring_stiffness")[0]
    for model in (healthy, blowing):
        model.gravity = (0.0, 0.0, -9.81)
    stiffness[bad] = 1.0e7  # ω h ≫ 2: symplectic Euler diverges within a few substeps
    blowing.set_world_values("spring_stiffness", base[None, :] * stiffness[:, None])
    guard = ws.GuardLimits(stop="world", every=1)
    sims = [ws.Simulator(m, fps=60, substeps=8, guard=guard) for m in (healthy, blowing)]
    for _ in range(5):
        for sim in sims:
            sim.step_frame()
    ok, failed = sims
    assert list(failed.world_failures) == [bad] and not ok.world_failures
    frame, report = failed.world_failures[bad]
    assert frame == 1 and report.world == bad
    assert f"world {bad} stopped at frame 1" in failed.describe_failure(bad)
    n = healthy.particle_count
    q_ok = ok.state.particle_q.numpy().reshape(worlds, n, 3)
    q_failed = failed.state.particle_q.numpy().reshape(worlds, n, 3)
    others = [w for w in range(worlds) if w != bad]
    np.testing.assert_array_equal(q_failed[others], q_ok[others])
    # The failed world is held from its failing check on: its clock stopped within frame 1.
    times = failed.state.time.numpy()
    assert times[bad] < 1.0 / 60.0 + 1e-12 and np.allclose(times[others], 5.0 / 60.0)
    assert failed.model.world_enabled.numpy().tolist() == [1, 1, 1, 0, 1, 1]


def test_the_run_stops_on_a_failed_world_by_default(device):
    model = cloth_builder().finalize(device, worlds=3)
    base = model.world_values("spring_stiffness")[0]
    model.set_world_values("spring_stiffness", base[None, :] * np.array([1.0, 1.0e7, 1.0])[:, None])
    sim = ws.Simulator(model, fps=60, substeps=8, guard=ws.GuardLimits(every=1))
    with pytest.raises(ws.SimulationError, match="in world 1"):
        sim.step_frame()
        sim.settle()  # (on CUDA the verdict comes a frame later: Simulator.defer_verdict)


def test_held_worlds_keep_their_state_and_time(device):
    model = cloth_builder().finalize(device, worlds=3)
    model.gravity = (0.0, 0.0, -9.81)
    sim = ws.Simulator(model, fps=60, substeps=4)
    sim.step_frame()
    before = sim.state.particle_q.numpy().reshape(3, -1, 3).copy()
    model.set_world_enabled(1, False)
    sim.step_frame()
    after = sim.state.particle_q.numpy().reshape(3, -1, 3)
    np.testing.assert_array_equal(after[1], before[1])
    assert np.abs(after[0] - before[0]).max() > 1e-4
    np.testing.assert_allclose(sim.state.time.numpy(), [2 / 60, 1 / 60, 2 / 60], rtol=1e-12)
    model.set_world_enabled(1, True)
    sim.step_frame()
    assert np.abs(sim.state.particle_q.numpy().reshape(3, -1, 3)[1] - before[1]).max() > 1e-4


def test_per_world_values_broadcast_and_check(device):
    model = cloth_builder().finalize(device, worlds=4)
    model.set_world_values("drag", [0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(model.world_values("drag")[:, 0], [0.1, 0.2, 0.3, 0.4], rtol=1e-6)
    assert model.drag_enabled
    model.set_world_values("gravity", (0.0, 0.0, -1.62))
    np.testing.assert_allclose(model.world_values("gravity"), np.tile([0.0, 0.0, -1.62], (4, 1)), rtol=1e-6)
    ke = model.world_values("spring_stiffness")[0]
    model.set_world_values("spring_stiffness", ke)  # one row for all worlds: stored once
    assert model.spring_stiffness.shape == (1, model.spring_count)
    revision = model.revision
    model.set_world_values("spring_stiffness", ke[None, :] * np.arange(1, 5)[:, None])
    assert model.spring_stiffness.shape == (4, model.spring_count) and model.revision > revision
    with pytest.raises(ws.ConfigError, match="broadcast"):
        model.set_world_values("drag", [0.1, 0.2])
    with pytest.raises(ws.ConfigError, match="> 0"):
        model.set_world_values("particle_mass", np.zeros(model.particle_count))
    with pytest.raises(ws.ConfigError, match="no per-world parameter"):
        model.set_world_values("spring_rest", 1.0)
    with pytest.raises(ws.ConfigError, match="world 4 does not exist"):
        model.set_track("drag", ws.Track([0.0], [0.1]), world=4)


def test_per_world_tracks_animate_their_own_world(device):
    """A gravity track in world 1 only: world 1 falls as the track says, the others keep their gravity."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 0.0]], mass=1.0)
    model = builder.finalize(device, precision="float64", worlds=3)
    model.gravity = (0.0, 0.0, -9.81)
    model.set_track("gravity", ws.Track([0.0, 1.0], [[0, 0, 0], [0, 0, -2.0]]), world=1)
    sim = ws.Simulator(model, integrator=make_integrator("rk4", model), fps=10, substeps=10)
    for _ in range(10):
        sim.step_frame()
    z = sim.state.particle_q.numpy()[:, 2]
    # RK4 is exact for a position cubic in time: z = -t³/3 under g = -2t; z = -g t²/2 with constant g.
    np.testing.assert_allclose(z, [-9.81 / 2, -1.0 / 3.0, -9.81 / 2], rtol=1e-12)
