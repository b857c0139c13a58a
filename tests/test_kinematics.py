"""Kinematic particles: a flag separate from the mass, motion prescribed by keyframe tracks or by Control
targets, exact at every substep, and the right boundary condition for every integrator (each keeps its
order on a cloth swung by its pinned edge, against an independent float64 SciPy reference)."""

import functools
import math

import numpy as np
import pytest
import warp as wp
from scipy.integrate import solve_ivp

import warpspring as ws

ORDERS = {"explicit_euler": 1, "symplectic_euler": 1, "implicit_euler": 1, "midpoint": 2, "velocity_verlet": 2,
          "rk4": 4}


class Recorder(ws.StepHook):
    """Copies positions and velocities after every step of an advance (device copies, capturable)."""

    def __init__(self, model, steps):
        self.model, self.steps = model, steps
        n = model.particle_count
        self.q = wp.empty(steps * n, dtype=model.vec3, device=model.device)
        self.qd = wp.empty(steps * n, dtype=model.vec3, device=model.device)

    def after_step(self, state, step, steps):
        n = self.model.particle_count
        wp.copy(self.q, state.particle_q, dest_offset=step * n, count=n)
        wp.copy(self.qd, state.particle_qd, dest_offset=step * n, count=n)

    def read(self):
        shape = (self.steps, self.model.particle_count, 3)
        return self.q.numpy().reshape(shape).astype(np.float64), self.qd.numpy().reshape(shape).astype(np.float64)


def circling_corner(device, precision):
    """Particle 0 pinned and driven around a circle of radius 0.3 m about (1, 2, 3) at one turn per second
    (a rotation track), particle 1 hanging from it on a spring."""
    builder = ws.ModelBuilder()
    builder.add_particles([[1.3, 2.0, 3.0], [1.3, 2.0, 2.7]], mass=0.1)
    builder.add_springs([[0, 1]], stiffness=50.0, damping=0.1)
    turn = ws.Track.rotation([0.0, 1.0], axis=(0.0, 0.0, 1.0), degrees=[0.0, 360.0], extrapolation="cycle")
    builder.add_pin_group([0], rotation=turn, pivot=(1.0, 2.0, 3.0), name="crank")
    return builder.finalize(device, precision=precision)


@pytest.mark.parametrize("name", sorted(ws.INTEGRATORS))
def test_driven_corner_is_on_its_circle_at_every_substep(device, precision, name):
    """At every substep time tₖ the driven corner is at c + r(cos 2πtₖ, sin 2πtₖ, 0) and moves at 2πr
    tangentially, to the rounding of the precision, under every integrator (1.3 turns of 96 substeps)."""
    model = circling_corner(device, precision)
    steps = 96
    record = Recorder(model, steps)
    stepper = ws.Stepper(model, ws.make_integrator(name, model), dt=1.3 / steps, steps=steps, hooks=[record])
    stepper.advance()
    q, qd = record.read()
    t = 1.3 / steps * np.arange(1, steps + 1)
    circle = np.stack([1.0 + 0.3 * np.cos(2 * np.pi * t), 2.0 + 0.3 * np.sin(2 * np.pi * t), np.full(steps, 3.0)], 1)
    speed = 2 * np.pi * 0.3 * np.stack([-np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), np.zeros(steps)], 1)
    # float64: the rotation's own rounding; float32: a coordinate near 3 m rounds to 2.4e-7 m.
    tolerance = 1e-12 if precision == "float64" else 6e-7
    np.testing.assert_allclose(q[:, 0], circle, rtol=0, atol=tolerance)
    np.testing.assert_allclose(qd[:, 0], speed, rtol=0, atol=tolerance * 10)
    assert np.abs(q[:, 1] - q[0, 1]).max() > 0.05  # the hanging particle was swung along


def test_pins_keep_their_mass_and_their_flag(device):
    """Pinning sets a flag; the particle's mass and inverse mass stay its own."""
    model = circling_corner(device, "float32")
    assert model.kinematic_mask().tolist() == [True, False]
    np.testing.assert_allclose(model.particle_mass.numpy(), 0.1)
    np.testing.assert_allclose(model.particle_inv_mass.numpy(), 10.0)


# -- a cloth swung by its pinned edge, against a float64 SciPy reference -------------------------------------

N, SPACING, MASS, KE, KD = 4, 0.1, 0.05, 10.0, 0.05
DURATION = 0.3
OMEGA = math.radians(120.0)  # [rad/s] the edge turns about the vertical through its centre
DRIFT = np.array([0.4, -0.2, 0.3])  # [m/s] while it moves at constant velocity


def swung_cloth(device, precision="float64"):
    builder = ws.ModelBuilder()
    grid = builder.add_cloth_grid(nx=N, ny=N, spacing=SPACING, origin=(0.0, 0.0, 1.0), particle_mass=MASS,
                                  structural=ws.SpringMaterial(KE, KD), shear=ws.SpringMaterial(KE / 2, KD),
                                  bend=None)
    builder.add_pin_group(
        grid[-1],
        translation=ws.Track([0.0, 1.0], [[0.0, 0.0, 0.0], DRIFT]),
        rotation=ws.Track.rotation([0.0, 1.0], axis=(0, 0, 1), degrees=[0.0, 120.0]),
        name="edge",
    )
    return builder.finalize(device, precision=precision)


@functools.cache
def reference():
    """Positions at t = DURATION from DOP853 at rtol 1e-12 on the free particles, the pinned edge moved by
    its own closed form (a rotation by ωt about the vertical through its centre, plus a drift)."""
    model = swung_cloth("cpu")
    q0 = model.particle_q.numpy().astype(np.float64)
    pairs = model.spring_indices.numpy()
    rest = model.spring_rest_length.numpy().astype(np.float64)
    ke = model.spring_stiffness.numpy()[0].astype(np.float64)
    kd = model.spring_damping.numpy()[0].astype(np.float64)
    pinned = model.kinematic_mask()
    free = ~pinned
    pivot = q0[pinned].mean(axis=0)
    arm = q0[pinned] - pivot

    def edge(t):
        c, s = math.cos(OMEGA * t), math.sin(OMEGA * t)
        rotated = arm @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
        return pivot + DRIFT * t + rotated, DRIFT + np.cross([0.0, 0.0, OMEGA], rotated)

    def rhs(t, y):
        x = np.empty_like(q0)
        v = np.empty_like(q0)
        half = len(y) // 2
        x[free], v[free] = y[:half].reshape(-1, 3), y[half:].reshape(-1, 3)
        x[pinned], v[pinned] = edge(t)
        d = x[pairs[:, 1]] - x[pairs[:, 0]]
        length = np.linalg.norm(d, axis=1)
        n = d / length[:, None]
        tension = ke * (length - rest) + kd * np.sum((v[pairs[:, 1]] - v[pairs[:, 0]]) * n, axis=1)
        f = np.tile([0.0, 0.0, -9.81 * MASS], (len(x), 1))
        np.add.at(f, pairs[:, 0], tension[:, None] * n)
        np.add.at(f, pairs[:, 1], -tension[:, None] * n)
        return np.concatenate([v[free].ravel(), (f[free] / MASS).ravel()])

    y0 = np.concatenate([q0[free].ravel(), np.zeros(3 * free.sum())])
    solution = solve_ivp(rhs, (0.0, DURATION), y0, method="DOP853", rtol=1e-12, atol=1e-13)
    assert solution.success
    final = np.empty_like(q0)
    final[free] = solution.y[: y0.size // 2, -1].reshape(-1, 3)
    final[pinned] = edge(DURATION)[0]
    return final


def swing_error(device, name, steps, precision="float64"):
    model = swung_cloth(device, precision)
    options = {"tolerance": 1e-10} if name == "dopri5" else {"cg_tolerance": 1e-12} if name == "implicit_euler" else {}
    stepper = ws.Stepper(model, ws.make_integrator(name, model, **options), dt=DURATION / steps, steps=steps // 4)
    for _ in range(4):
        stepper.advance()
    return float(np.abs(stepper.state.particle_q.numpy() - reference()).max())


@pytest.mark.parametrize("name", sorted(ORDERS))
def test_swung_cloth_converges_at_each_integrators_order(device, name):
    """A 4 × 4 cloth whose top edge turns at 120°/s about a vertical axis while drifting, under gravity,
    against the float64 reference: halving the step divides the error by 2^order (±0.25 in the exponent);
    the pinned edge enters every stage and the implicit solve at its prescribed place."""
    coarse, fine = (swing_error(device, name, steps) for steps in (128, 256))
    assert np.log2(coarse / fine) == pytest.approx(ORDERS[name], abs=0.25)
    assert fine < {1: 2e-2, 2: 1e-4, 4: 1e-8}[ORDERS[name]]


def test_swung_cloth_adaptive_and_float32(device):
    """dopri5 at tolerance 1e-10 lands within 1e-8 m of the reference; RK4 in float32 within float32's
    rounding of the swing (the edge moves by ~0.15 m)."""
    assert swing_error(device, "dopri5", 16) < 1e-8
    assert swing_error(device, "rk4", 128, precision="float32") < 2e-5


# -- targets through Control -----------------------------------------------------------------------------------


def test_control_targets_are_followed_in_straight_lines(device):
    """A pin group without tracks follows per-frame targets set through Control: at every substep it is on
    the straight line from where the frame began to the frame's target, at the constant velocity that
    reaches it at the frame's end; with no new target it rests where it arrived."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0], [0.0, 0.0, 0.8]], mass=0.1)
    builder.add_springs([[0, 1]], stiffness=30.0, damping=0.05)
    builder.add_pin_group([0], name="hand")
    model = builder.finalize(device, precision="float64")
    fps, substeps = 30, 5
    sim = ws.Simulator(model, fps=fps, substeps=substeps)
    record = Recorder(model, substeps)
    sim.stepper.hooks.append(record)
    targets = [np.array([0.1 * k, 0.05 * k * k, 1.0 + 0.02 * k]) for k in range(1, 5)]
    start = np.array([0.0, 0.0, 1.0])
    fraction = np.arange(1, substeps + 1)[:, None] / substeps
    for frame in range(6):
        if frame < len(targets):
            sim.set_pin_targets("hand", targets[frame])
        sim.step_frame()
        q, qd = record.read()
        end = targets[min(frame, len(targets) - 1)]
        if frame < len(targets):
            np.testing.assert_allclose(q[:, 0], start + fraction * (end - start), rtol=0, atol=1e-13)
            np.testing.assert_allclose(qd[:, 0], np.broadcast_to((end - start) * fps, (substeps, 3)), atol=1e-9)
        else:
            np.testing.assert_array_equal(q[:, 0], np.broadcast_to(end, (substeps, 3)))
            assert not qd[:, 0].any()
        start = end
    assert sim.stepper.captures == 1  # new targets are values: they never re-capture


def test_control_target_errors_name_the_group():
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]], mass=0.1)
    builder.add_pin_group([0], name="hand")
    builder.add_pin_group([1], translation=ws.Track([0.0, 1.0], [[0, 0, 0], [1, 0, 0]]), name="crane")
    control = builder.finalize("cpu").control()
    with pytest.raises(ws.ConfigError, match="no pin group named 'foot'"):
        control.set_pin_targets("foot", [0.0, 0.0, 0.0], time=1.0)
    with pytest.raises(ws.ConfigError, match="'crane' is driven by its tracks"):
        control.set_pin_targets("crane", [0.0, 0.0, 0.0], time=1.0)
    with pytest.raises(ws.ConfigError, match="needs 1 finite target positions"):
        control.set_pin_targets("hand", [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], time=1.0)


def test_pin_group_errors():
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]], mass=0.1)
    builder.add_pin_group([0, 1])
    with pytest.raises(ws.ConfigError, match="particle 1 is already in pin group 'pins'"):
        builder.add_pin_group([1])
    with pytest.raises(ws.ConfigError, match="3-vectors"):
        builder.add_pin_group([2], translation=ws.Track([0.0, 1.0], [0.0, 1.0]))
    with pytest.raises(ws.ConfigError, match="out of range"):
        builder.add_pin_group([3])


def test_state_clock_is_exact_in_float32(device):
    """A float32 model's clock still adds its steps in float64: after 600 frames of 7 substeps it is within
    1e-11 s of 600 / 60 s (a float32 step would put it ~4e-7 s off)."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0]], mass=0.1)
    model = builder.finalize(device, precision="float32")
    for name in ("symplectic_euler", "velocity_verlet", "implicit_euler", "rk4"):
        sim = ws.Simulator(model, integrator=ws.make_integrator(name, model), fps=60, substeps=7, guard=None)
        for _ in range(600):
            sim.step_frame()
        assert abs(float(sim.state.time.numpy()[0]) - 10.0) < 1e-11, name


def test_control_targets_never_chase_a_rounding(device):
    """Targets set each frame for 300 frames, then none: the float32 pin never moves faster than its
    fastest straight segment, even at frames whose end the device clock reaches a rounding before or after
    the host's target time, and it is at rest (velocity exactly 0) once the targets stop."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0], [0.0, 0.0, 0.8]], mass=0.1)
    builder.add_springs([[0, 1]], stiffness=30.0, damping=0.05)
    builder.add_pin_group([0], name="hand")
    model = builder.finalize(device, precision="float32")
    substeps = 7
    sim = ws.Simulator(model, fps=60, substeps=substeps)
    record = Recorder(model, substeps)
    sim.stepper.hooks.append(record)
    path = [np.array([0.3 * math.sin(k / 20), 0.0, 1.0]) for k in range(301)]
    fastest = max(np.linalg.norm(b - a) for a, b in zip(path, path[1:])) * 60
    speeds = []
    for frame in range(340):
        if frame < 300:
            sim.set_pin_targets("hand", path[frame + 1])
        sim.step_frame()
        speeds.append(np.linalg.norm(record.read()[1][:, 0], axis=1))
    speeds = np.array(speeds)
    assert speeds[:300].max() <= fastest * (1 + 1e-4)
    assert not speeds[301:].any()
    np.testing.assert_allclose(sim.state.particle_q.numpy()[0], path[300], atol=1e-6)


def test_released_pin_falls_freely(device):
    """Clearing a pin's flag between frames releases it (a live value: no re-capture): from rest, 8
    symplectic Euler substeps of h under g give v = -8 g h and a drop of 36 g h² (Σ k for k = 1..8), to
    rounding; a released member of a driven group stops following its group."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]], mass=0.1)
    builder.pin_particles([0])
    builder.add_pin_group([1], translation=ws.Track([0.0, 10.0], [[0, 0, 0], [10.0, 0, 0]]), name="crane")
    model = builder.finalize(device, precision="float64")
    sim = ws.Simulator(model, fps=60, substeps=8)
    for _ in range(3):
        sim.step_frame()
    np.testing.assert_allclose(sim.state.particle_q.numpy()[0], [0.0, 0.0, 1.0], atol=0)  # pinned: at rest
    model.set_kinematic([0, 1], False)
    start = sim.state.particle_q.numpy().copy()
    velocity = sim.state.particle_qd.numpy().copy()
    sim.step_frame()
    h = 1 / 480
    q, qd = sim.state.particle_q.numpy(), sim.state.particle_qd.numpy()
    np.testing.assert_allclose(qd[0], [0.0, 0.0, -8 * 9.81 * h], rtol=1e-12)
    np.testing.assert_allclose(q[0], start[0] + [0.0, 0.0, -36 * 9.81 * h * h], rtol=0, atol=1e-14)
    # The crane's particle keeps its velocity (1 m/s along x) and starts falling: no longer on its track.
    np.testing.assert_allclose(q[1], start[1] + 8 * h * velocity[1] + [0.0, 0.0, -36 * 9.81 * h * h], atol=1e-14)
    assert sim.stepper.captures == 1


def test_dopri5_controls_no_error_of_prescribed_motion(device):
    """dopri5's error estimate skips kinematic particles: a pin driven along a kinked track costs no extra
    internal steps (the same accepted and rejected steps as the model without the pin group)."""
    counts = []
    for driven in (False, True):
        builder = ws.ModelBuilder()
        builder.add_particles([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]], velocities=[[0.3, 0.0, 2.0], [0.0, 0.0, 0.0]],
                              mass=0.1)
        if driven:
            kinked = ws.Track([0.0, 0.05, 0.1, 0.15], [[0, 0, 0], [0.3, 0, 0], [0.3, 0.2, 0], [0, 0.2, 0]])
            builder.add_pin_group([1], translation=kinked)
        else:
            builder.pin_particles([1])
        model = builder.finalize(device, precision="float64")
        integrator = ws.DormandPrince(model, tolerance=1e-8)
        sim = ws.Simulator(model, integrator=integrator, fps=60, substeps=1)
        for _ in range(10):
            sim.step_frame()
        counts.append((integrator.accepted_steps, integrator.rejected_steps))
    assert counts[0] == counts[1]


def test_reset_forgets_pin_targets(device):
    """After Simulator.reset the control-driven group rests where it starts: targets set for the run before
    (at times the new run will reach again) are forgotten."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0]], mass=0.1)
    builder.add_pin_group([0], name="hand")
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=4)
    for frame in range(3):
        sim.set_pin_targets("hand", [0.1 * (frame + 1), 0.0, 1.0])
        sim.step_frame()
    sim.set_pin_targets("hand", [5.0, 0.0, 1.0])
    sim.reset()
    sim.step_frame()
    np.testing.assert_array_equal(sim.state.particle_q.numpy()[0], [0.0, 0.0, 1.0])


def test_pinning_mid_run_is_limited_to_known_pins_in_models_with_groups():
    """With pin groups, a particle not pinned at build time cannot be pinned mid-run (the kinematics pass
    keeps the list of pins); a released pin can be pinned again, and without groups any particle can."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]], mass=0.1)
    builder.pin_particles([0])
    builder.add_pin_group([1], translation=ws.Track([0.0, 1.0], [[0, 0, 0], [1, 0, 0]]))
    model = builder.finalize("cpu")
    with pytest.raises(ws.ConfigError, match="particle 2 was not pinned when this model"):
        model.set_kinematic([2])
    model.set_kinematic([0, 1], False)
    model.set_kinematic([0, 1])
    assert model.kinematic_mask().tolist() == [True, True, False]
    plain = ws.ModelBuilder()
    plain.add_particles([[0.0, 0.0, 1.0]], mass=0.1)
    free = plain.finalize("cpu")
    free.set_kinematic([0])
    assert free.kinematic_mask().tolist() == [True]
