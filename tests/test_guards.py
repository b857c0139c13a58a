"""Run-time guards: the first failure of a frame is caught on the device and reported with its frame,
substep, particle or spring — and healthy runs are never stopped."""

import numpy as np
import pytest

import warpspring as ws
from helpers import ZERO_GRAVITY, battery_cloth, hanging_cloth, run_frames


def test_healthy_run_is_not_stopped(device):
    """A stable hanging cloth with a sphere runs 60 frames with guards checking every substep."""
    model, _ = hanging_cloth(device, n=10, sphere=True)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(every=1))
    assert np.isfinite(run_frames(sim, 60)).all()


@pytest.mark.parametrize("every, expected_substep", [(None, 16), (1, 1), (4, 4)])
def test_non_finite_particle_is_named_with_its_substep(device, every, expected_substep):
    """A NaN velocity planted in free particle 7 is reported as particle 7 at the first check after it:
    substep 1 when checking every substep, 4 every fourth, 16 (the frame's end) once per frame."""
    builder = ws.ModelBuilder()
    builder.add_particles(np.arange(30.0).reshape(10, 3), mass=1.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(every=every))
    run_frames(sim, 2)
    qd = sim.state.particle_qd.numpy()
    qd[7] = np.nan
    sim.state.particle_qd.assign(qd)
    with pytest.raises(ws.SimulationError) as failure:
        sim.step_frame()
        sim.settle()  # (on CUDA the verdict comes a frame later: Simulator.defer_verdict)
    assert failure.value.frame == 3 and failure.value.substep == expected_substep
    assert str(failure.value).startswith(f"frame 3, substep {expected_substep} of 16 (t ≤ ")
    assert str(failure.value).endswith("particle 7 has a non-finite position or velocity")
    assert sim.frame == 2  # the failed frame does not count


def test_non_finite_state_spreading_through_springs_is_counted(device):
    """A NaN spreads to the neighbours within a substep; the report counts the non-finite particles."""
    model, _ = hanging_cloth(device, n=6)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(every=1))
    qd = sim.state.particle_qd.numpy()
    qd[14] = np.nan
    sim.state.particle_qd.assign(qd)
    with pytest.raises(ws.SimulationError, match=r"frame 1, substep 1 of 16 .*: (\d+) of 36 particles have non-finite") as failure:
        sim.step_frame()
        sim.settle()  # (on CUDA the verdict comes a frame later: Simulator.defer_verdict)
    count = int(str(failure.value).split(": ")[1].split(" of ")[0])
    assert 2 <= count <= 13  # particle 14 and, at most, its twelve spring neighbours


def test_torn_spring_is_named(device):
    """A spring pulled to 30× its rest length (the guard's default limit is 11×) is named with its two
    particles and its stretch."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], mass=1.0)
    builder.add_springs([[0, 1], [1, 2], [2, 3]], stiffness=1.0, rest_length=[1.0, 1.0 / 30.0, 1.0])
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=4)
    with pytest.raises(ws.SimulationError, match=r"spring 1 \(particles 1-2\) stretched to [0-9.]+× its rest length"):
        sim.step_frame()
        sim.settle()  # (on CUDA the verdict comes a frame later: Simulator.defer_verdict)


def test_runaway_kinetic_energy_is_caught(device):
    """Kinetic energy beyond the configured limit stops the run with the energy named."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0, 0, 0]], velocities=[[10.0, 0, 0]], mass=2.0)  # ½ m v² = 100 J
    model = builder.finalize(device)
    ws.Simulator(model, fps=60, substeps=2, guard=ws.GuardLimits(max_kinetic_energy=150.0)).step_frame()
    sim = ws.Simulator(model, fps=60, substeps=2, guard=ws.GuardLimits(max_kinetic_energy=50.0))
    with pytest.raises(ws.SimulationError, match=r"kinetic energy ran away to 100 J"):
        sim.step_frame()
        sim.settle()  # (on CUDA the verdict comes a frame later: Simulator.defer_verdict)


def test_default_energy_limit_tolerates_fast_initial_motion(device):
    """Particles launched at 1e3 m/s are not runaway energy: the default limit scales with the scene's own
    initial kinetic energy."""
    builder = ws.ModelBuilder()
    builder.add_particles(np.random.default_rng(0).uniform(-1, 1, (20, 3)),
                          velocities=np.full((20, 3), 1.0e3 / np.sqrt(3)), mass=0.1)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=8)
    assert np.isfinite(run_frames(sim, 10)).all()


INTEGRATORS = sorted(ws.INTEGRATORS)
PUSH_MASS, PUSH_FORCE, PUSH_STIFFNESS = 45.0, 75.0, 100.0  # [kg], [N], [N/m]


def pushed_block(device):
    """A 45 kg block on a 100 N/m spring to a pin, no gravity, at rest: its energy scale is ~0, so a limit
    that ignores the work put in is 1 J, which the 75 N push exceeds within 0.2 s."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], mass=[1.0, PUSH_MASS])
    builder.pin_particles([0])
    builder.add_springs([[0, 1]], stiffness=PUSH_STIFFNESS, damping=0.0)
    return builder.finalize(device)


@pytest.mark.parametrize("integrator", INTEGRATORS)
def test_forced_run_is_not_stopped_and_its_work_is_counted(device, integrator):
    """The pushed block runs 10 s (≈ 2.4 periods) with the default guard under every integrator, and the
    work the guard counted after the first half period is the push's 2F²/k (F = 75 N through the block's
    travel 0 → 2F/k, exact for a constant force up to the integrator's error at the frame's time)."""
    model = pushed_block(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=8)
    sim.control.set_particle_force([[0.0, 0.0, 0.0], [PUSH_FORCE, 0.0, 0.0]])
    omega = np.sqrt(PUSH_STIFFNESS / PUSH_MASS)
    half = round(np.pi / omega * 60)  # frame nearest the first turning point
    run_frames(sim, half)
    expected = 2.0 * PUSH_FORCE**2 / PUSH_STIFFNESS * (1.0 - np.cos(omega * half / 60)) / 2.0
    tolerance = 0.05 if integrator == "implicit_euler" else 0.01  # implicit Euler's damping shortens the swing
    assert sim.guard.work()[0] == pytest.approx(expected, rel=tolerance)
    assert np.isfinite(run_frames(sim, 600 - half)).all()


def test_driven_run_is_not_stopped(device):
    """A chain shaken by a pin on a cyclic track (±0.5 m at 1 Hz), no gravity, runs 20 s: the drive's work
    raises the limit as it puts energy in, where a limit fixed at the start (1 J) stops it at once."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles(np.column_stack([np.arange(6) * 0.5, np.zeros(6), np.zeros(6)]), mass=1.0)
    builder.add_springs([[i, i + 1] for i in range(5)], stiffness=200.0, damping=1.0)
    shake = ws.Track([0.0, 0.25, 0.5, 0.75, 1.0], [[0, 0, 0], [0, 0.5, 0], [0, 0, 0], [0, -0.5, 0], [0, 0, 0]],
                     interpolation="smooth", extrapolation="cycle")
    builder.add_pin_group([0], translation=shake)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=8)
    assert np.isfinite(run_frames(sim, 1200)).all()
    speeds = np.linalg.norm(sim.state.particle_qd.numpy()[1:], axis=1)
    assert speeds.max() > 1.0  # really driven: ½ m v² ≫ 1 J was reached at some point
    assert sim.guard.work()[0] > 1.0


def test_a_drive_s_first_work_starts_from_its_load_at_the_start(device):
    """A pin moving at u = 0.1 m/s along x pushes a 1 kg mass through a 100 N/m spring, unstretched at the
    start, no gravity, undamped. The drive's load is 0 at the start, so the first check's trapezoid is
    ½ F₁ Δx, F₁ = k (L - l₁) along the spring and Δx = u / 60 (the load at the check alone would double it);
    and it is the energy the system holds then, ½ m v² + ½ k (l - L)², up to the trapezoid's error on a
    force that grows as k u t (1 - (ωt)²/6): (ωt)²/12 ≈ 2e-3 at ω = 10 rad/s, t = 1/60 s."""
    speed, k, mass = 0.1, 100.0, 1.0
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], mass=mass)
    builder.add_springs([[0, 1]], stiffness=k, damping=0.0)
    builder.add_pin_group([0], translation=ws.Track([0.0, 10.0], [[0.0, 0.0, 0.0], [10.0 * speed, 0.0, 0.0]]))
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("velocity_verlet", model), fps=60, substeps=16)
    run_frames(sim, 1)
    q = sim.state.particle_q.numpy().astype(np.float64)
    v = sim.state.particle_qd.numpy().astype(np.float64)
    stretch = np.linalg.norm(q[1] - q[0]) - 1.0
    assert q[0, 0] == pytest.approx(speed / 60.0, rel=1e-5)
    assert stretch < 0.0  # the pin moves toward the mass: it pushes, against the compressed spring
    assert sim.guard.work()[0] == pytest.approx(-0.5 * k * stretch * speed / 60.0, rel=1e-4)
    assert sim.guard.work()[0] == pytest.approx(0.5 * mass * v[1] @ v[1] + 0.5 * k * stretch**2, rel=3e-3)


def test_work_does_not_hide_a_blow_up(device):
    """Symplectic Euler at 3× its stable step on a pushed block diverges: the work the push puts in grows
    with the displacement, the kinetic energy with its square, so the guard still stops it."""
    model = pushed_block(device)
    omega = np.sqrt(PUSH_STIFFNESS / PUSH_MASS)
    fps = omega / 6.0  # one substep of ωh = 6 > 2: unstable
    sim = ws.Simulator(model, fps=fps, substeps=1)
    sim.control.set_particle_force([[0.0, 0.0, 0.0], [PUSH_FORCE, 0.0, 0.0]])
    with pytest.raises(ws.SimulationError, match="kinetic energy ran away|non-finite|stretched"):
        run_frames(sim, 400)


@pytest.mark.parametrize("kwargs, message", [
    ({"every": 0}, "guard every must be an integer >= 1"),
    ({"every": 2.5}, "guard every must be an integer >= 1"),
    ({"tear_strain": 0.0}, "guard tear_strain must be a finite number > 0"),
    ({"tear_strain": float("nan")}, "guard tear_strain must be a finite number > 0"),
    ({"max_kinetic_energy": -1.0}, "guard max_kinetic_energy must be a finite number > 0"),
    ({"dissipation": 1}, "guard dissipation must be true or false"),
])
def test_guard_limits_reject_bad_values_when_made(kwargs, message):
    with pytest.raises(ws.ConfigError, match=message):
        ws.GuardLimits(**kwargs)


def test_guard_max_strain_is_a_deprecated_name_of_tear_strain():
    """GuardLimits.max_strain was renamed tear_strain (not Stabilizers.max_strain, the strain limit): the old
    keyword and attribute still work, with a DeprecationWarning; both names at once are refused."""
    with pytest.warns(DeprecationWarning, match="tear_strain"):
        limits = ws.GuardLimits(every=2, max_strain=3.0)
    assert limits == ws.GuardLimits(every=2, tear_strain=3.0) and limits.tear_strain == 3.0
    with pytest.warns(DeprecationWarning, match="tear_strain"):
        assert limits.max_strain == 3.0
    with pytest.warns(DeprecationWarning), pytest.raises(ws.ConfigError, match="guard max_strain must be"):
        ws.GuardLimits(max_strain=-1.0)
    with pytest.raises(TypeError, match="pass tear_strain only"):
        ws.GuardLimits(tear_strain=3.0, max_strain=3.0)
    assert ws.GuardLimits().tear_strain == 10.0


def test_energy_balance_of_a_conservative_run_is_exact(device):
    """A 2 kg mass on a 200 N/m spring hanging from a pin, released at rest at the spring's rest length
    (undamped; velocity Verlet, ωh = 0.02): after 2 s the guard's counted work is the weight's m g Δz, its
    energy is ½ m v² + ½ k (|d| - L)² of the state, and the energy created is within the integrator's
    O((ωh)²) energy error of zero."""
    mass, k, g = 2.0, 200.0, 9.81
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -g))
    builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]], mass=[1.0, mass])
    builder.pin_particles([0])
    builder.add_springs([[0, 1]], stiffness=k, damping=0.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("velocity_verlet", model), fps=60, substeps=8)
    run_frames(sim, 120)
    q = sim.state.particle_q.numpy().astype(np.float64)
    v = sim.state.particle_qd.numpy().astype(np.float64)
    balance = sim.guard.energy_balance()
    assert balance.work[0] == pytest.approx(mass * g * (-1.0 - q[1, 2]), rel=1e-5)
    expected = 0.5 * mass * v[1] @ v[1] + 0.5 * k * (np.linalg.norm(q[1] - q[0]) - 1.0) ** 2
    assert balance.energy[0] == pytest.approx(expected, rel=1e-5)
    # At rest and unstretched at the start: E_ref, taken at the first check, is 0 but for one frame's error.
    assert balance.reference[0] == pytest.approx(0.0, abs=1e-5 * balance.peak[0])
    assert abs(balance.created[0]) <= 1e-3 * balance.peak[0]  # (ωh)² = 4e-4


def test_energy_created_by_an_unstable_step_is_caught(device):
    """RK4 at one 1/60 s step on the battery cloth: at ke = 300 N/m (stable at the loaded state) the run is
    untouched; at 480 N/m the stretched corners are linearly unstable but their growth saturates, so the
    state stays finite and untorn (with the balance off, 60 frames pass) while holding several times the
    energy of the converged run: the energy balance stops it, diagnosed as instability. With 10 substeps
    both run and create no energy."""
    from warpspring.analysis.advisor import diagnose

    model = battery_cloth(device, [300.0, 480.0])
    rk4 = ws.make_integrator("rk4", model)
    sim = ws.Simulator(model, integrator=rk4, fps=60, substeps=1, guard=ws.GuardLimits(stop="world"))
    last = model.state()
    for frame in range(60):
        if 1 not in sim.world_failures:
            last.particle_q.assign(sim.state.particle_q)
        sim.step_frame()
    assert list(sim.world_failures) == [1]
    report = sim.world_failures[1][1]
    assert report.reason == "energy balance" and report.energy_created > 0.1 * report.energy_budget
    assert "created" in report.describe(model)
    found = diagnose(model, "rk4", sim.dt, fps=60, reason=report.reason, state=last)
    assert found.kind == "instability" and f"--substeps {found.advice.substeps}" in found.remedy

    for substeps, balance in ((1, 0.0), (10, ws.GuardLimits().energy_balance)):
        model = battery_cloth(device, [300.0, 480.0])
        sim = ws.Simulator(model, integrator=ws.make_integrator("rk4", model), fps=60, substeps=substeps,
                           guard=ws.GuardLimits(energy_balance=balance, stop="world"))
        run_frames(sim, 60)
        assert not sim.world_failures
        if substeps == 10:
            created = sim.guard.energy_balance()
            assert (created.created <= 1e-3 * created.peak).all()


def test_energy_balance_rebases_when_values_are_written(device):
    """Tripling a stretched cloth's stiffness between frames adds elastic energy without work: the balance
    takes a new reference and the run goes on."""
    model = battery_cloth(device, [2000.0])
    sim = ws.Simulator(model, fps=60, substeps=20)
    run_frames(sim, 30)
    before = sim.guard.energy_balance()
    model.set_world_values("spring_stiffness", 6000.0)
    run_frames(sim, 30)
    after = sim.guard.energy_balance()
    assert after.reference[0] != before.reference[0]
    assert after.created[0] <= 1e-3 * after.peak[0]


def _stop(sim, frames):
    """Run until the guard stops the run; the positions of the last frame it passed and the error."""
    last = sim.model.state()
    for _ in range(frames):
        try:
            sim.step_frame()
            sim.settle()  # (on CUDA the verdict comes a frame later: Simulator.defer_verdict)
        except ws.SimulationError as error:
            return last, error
        last.particle_q.assign(sim.state.particle_q)
    raise AssertionError(f"the run was not stopped within {frames} frames")


def test_a_too_soft_cloth_is_told_to_stiffen_not_to_substep(device):
    """A 10 N/m cloth carrying 0.1 kg per particle tears under its own weight however small the step: the stop
    is diagnosed at the last good frame as physical over-stretch, with the material as the remedy; the same
    cloth with 4× the substeps stops at the same frame, which is what makes more substeps the wrong advice."""
    from warpspring.analysis.advisor import diagnose

    soft = ws.SpringMaterial(ke=10.0, kd=0.1)
    model, _ = hanging_cloth(device, n=8, structural=soft, shear=soft, bend=soft)
    stops = []
    for substeps in (8, 32):
        sim = ws.Simulator(model, fps=60, substeps=substeps)
        last, error = _stop(sim, 300)
        assert error.reason == "strain"
        stops.append(error.frame)
        found = diagnose(model, "symplectic_euler", sim.dt, fps=60, reason=error.reason, state=last)
        assert found.kind == "overstretch" and found.advice.stable
        assert "too soft for its load" in found.remedy and "max_strain" in found.remedy
    assert abs(stops[0] - stops[1]) <= 1


def test_an_unstable_step_is_told_to_substep(device):
    """The 1 kN/m cloth with RK4 at one 1/60 s step (ω_max h ≈ 19, far past RK4's 2.8) blows up: the stop
    is diagnosed as numerical instability, with the substep count the stretched state needs."""
    from warpspring.analysis.advisor import diagnose

    model, _ = hanging_cloth(device, n=8)
    sim = ws.Simulator(model, integrator=ws.make_integrator("rk4", model), fps=60, substeps=1)
    last, error = _stop(sim, 300)
    found = diagnose(model, "rk4", sim.dt, fps=60, reason=error.reason, state=last)
    assert found.kind == "instability" and not found.advice.stable
    assert f"--substeps {found.advice.substeps}" in found.remedy and found.advice.substeps > 1


def _damped_pushed_block(device, fps: int, substeps: int) -> ws.Simulator:
    """The seed's block as it was stopped: 45 kg on k = 100 N/m, c = 10 N·s/m (ω = 1.49 rad/s, ζ = 0.075: explicit
    Euler is stable below h = 2ζ/ω = 0.1 s), pushed from rest by 75 N, explicit Euler, the default guard."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], mass=[1.0, PUSH_MASS])
    builder.pin_particles([0])
    builder.add_springs([[0, 1]], stiffness=PUSH_STIFFNESS, damping=10.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("explicit_euler", model), fps=fps, substeps=substeps)
    sim.control.set_particle_force([[0.0, 0.0, 0.0], [PUSH_FORCE, 0.0, 0.0]])
    return sim


def test_explicit_euler_pushed_from_rest_is_not_read_as_creating_energy(device):
    """Explicit Euler moves a step with its first velocity while its kinetic energy takes the step's mean: Σ F·Δx
    lags what a constant push puts in by F·h Δv/2, which at the start is a third of the work (0.0062 J of 0.0187 J
    at frame 2: the block was stopped at h = 10 ms and 5 ms, a tenth of its limit). Counted with the lead, the
    block runs 4 s (0.95 of a period) at both steps with the balance closed one-sided (created ≤ 0 up to round-off
    of the 100 J held), and at h = 0.2 s, twice the limit, the balance still stops it (within 60 frames)."""
    for fps, substeps in ((100, 1), (100, 2)):
        sim = _damped_pushed_block(device, fps, substeps)
        for _ in range(400):
            sim.step_frame()
            assert sim.guard.energy_balance().created[0] <= 1.0e-6 * sim.guard.energy_balance().peak[0]
    sim = _damped_pushed_block(device, 5, 1)
    with pytest.raises(ws.SimulationError, match="created"):
        run_frames(sim, 60)
