"""The guard's power counted in the integrator's own force pass (``core/forces.PowerSums``): symplectic Euler's fused
step with gathered springs (the CUDA default; here forced on the CPU too), its update after scattered springs (the
CPU default: drag and the loads from outside; the springs' pass counts their own dampers) and RK4's evaluation at
each step's start.
The balance it keeps matches closed forms as the passes of its own did, the run it watches is the same to the last
bit, and it launches nothing per substep."""

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from helpers import damped_gathered_cloth, run_frames
from warpspring.core.guards import WATCH_FRAMES
from warpspring.kernels import flatten

# A 2 kg mass on a 200 N/m spring with 5 % of critical damping, hanging from a pin, released 0.1 m below its static
# equilibrium at rest: ω = 10 rad/s, kd = 2 ζ √(k m) = 2 N·s/m (``test_dissipation.py``'s oscillator).
MASS, K, G, ZETA, AMPLITUDE = 2.0, 200.0, 9.81, 0.05, 0.1
OMEGA = np.sqrt(K / MASS)
KD = 2.0 * ZETA * np.sqrt(K * MASS)


def oscillator_energy(t: float) -> float:
    """½ m v² + ½ k y² [J] of the damped oscillation about its static equilibrium at time t [s] (closed form)."""
    wd = OMEGA * np.sqrt(1.0 - ZETA**2)
    decay = np.exp(-ZETA * OMEGA * t)
    y = -AMPLITUDE * decay * (np.cos(wd * t) + ZETA * OMEGA / wd * np.sin(wd * t))
    v = AMPLITUDE * OMEGA**2 / wd * decay * np.sin(wd * t)
    return 0.5 * MASS * v * v + 0.5 * K * y * y


def oscillator(device, evaluation: str) -> ws.Model:
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -G))
    builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0 - MASS * G / K - AMPLITUDE]], mass=[1.0, MASS])
    builder.pin_particles([0])
    builder.add_springs([[0, 1]], stiffness=K, damping=KD, rest_length=1.0)
    return builder.finalize(device, spring_evaluation=evaluation)


@pytest.mark.parametrize("integrator, order", [("rk4", 2), ("symplectic_euler", 1)])
@pytest.mark.parametrize("evaluation", ["gather", "scatter"])
def test_power_in_the_force_pass_is_the_oscillators_lost_energy(device, integrator, order, evaluation):
    """Over 2 s (fps 60, 8 substeps: ωh = 0.021) D equals the closed-form energy loss from the first check on and the
    balance closes, within (ωh)^order of the loss as ``test_dissipation.py`` derives it: RK4's trapezoid of the
    power at the steps' starts (closed at each check) is second order; symplectic Euler's mean-rate rule (each
    step's f_d·(v + v')/2 h, what its damper changed the kinetic energy by, closed at the checks) first order."""
    model = oscillator(device, evaluation)
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=8)
    run_frames(sim, 120)
    # (scattered springs under symplectic Euler: their own pass counts them, DamperSums, and nothing else is left)
    assert (sim.guard._power is not None) == (integrator == "rk4" or evaluation == "gather")
    tolerance = (OMEGA * sim.dt) ** order
    lost = oscillator_energy(1.0 / 60.0) - oscillator_energy(2.0)
    balance = sim.guard.energy_balance()
    assert lost > 0.8 * oscillator_energy(0.0)
    assert balance.dissipated[0] == pytest.approx(lost, rel=tolerance)
    assert abs(balance.created[0]) <= tolerance * oscillator_energy(0.0)


@pytest.mark.parametrize("omega_h", [0.5, 1.0, 1.5])
def test_symplectic_euler_fused_counts_its_loss_at_large_steps(device, omega_h):
    """``test_dissipation.py``'s large-step oscillator (no gravity, 1 substep of 1/60 s at ωh as given, kd h/m = 0.01)
    through the fused step with gathered springs: after 10 s D is the energy lost since the first check within 1 %
    as there (the step's exact energy closed by the quarter of h P at the checks: the mean-rate rule kd ((r + r')/2)²
    per step, whose first step, from rest to v₁ = hω²A, took out h kd (v₁/2)² before the first check; the trapezoid
    of kd v² at the steps' ends is 7 to 130 % off)."""
    h = 1.0 / 60.0
    stiffness = MASS * (omega_h / h) ** 2
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0 - AMPLITUDE]], mass=[1.0, MASS])
    builder.pin_particles([0])
    kd = 0.01 * MASS / h
    builder.add_springs([[0, 1]], stiffness=stiffness, damping=kd, rest_length=1.0)
    model = builder.finalize(device, spring_evaluation="gather")
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=1,
                       guard=ws.GuardLimits(energy_balance=10.0))
    start = 0.5 * stiffness * AMPLITUDE**2
    run_frames(sim, 600)
    balance = sim.guard.energy_balance()
    assert sim.guard._power is not None
    assert balance.energy[0] < 0.01 * start
    first = h * kd * (h * omega_h**2 / h**2 * AMPLITUDE / 2.0) ** 2
    assert balance.dissipated[0] == pytest.approx(start - balance.energy[0] - first, rel=1.0e-2)


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4"])
def test_drag_and_wind_counted_in_the_force_pass(device, integrator):
    """A 6 × 6 cloth hung from its top row in a 3 m/s wind (aerodynamics) with viscous drag (0.02 N·s/m per
    particle): the force pass counts the dampers and drag against still air, c v·v̄, as D, and the wind's push
    through drag, c u·v̄, and its drag and lift on the triangles as work of loads. Over 1 s the balance closes to
    the integrators' energy error, bounded by (ω_max h)^order of the budget (ω_max ≈ 2√(ke/m)·2 for the crossed
    springs of ke = 100 N/m on 0.05 kg: 180 rad/s, h = 1/480 s)."""
    builder = ws.ModelBuilder(drag=0.02)
    spring = ws.SpringMaterial(ke=100.0, kd=0.5)
    builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, particle_mass=0.05, structural=spring, shear=spring,
                           pin=["top"])
    builder.add_aerodynamics(wind=(3.0, 0.0, 0.0))
    model = builder.finalize(device, spring_evaluation="gather")
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=8)
    run_frames(sim, 60)
    assert sim.guard._power is not None
    balance = sim.guard.energy_balance()
    order = 2 if integrator == "rk4" else 1
    assert balance.work[0] > 0.01 * balance.peak[0]  # the wind did work worth checking
    assert balance.dissipated[0] > 0.01 * balance.peak[0]
    assert abs(balance.created[0]) <= (180.0 * sim.dt) ** order * balance.peak[0]


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4"])
def test_the_guarded_run_is_the_unguarded_run_bit_for_bit(device, integrator):
    """Counting the power changes no force: a hanging cloth's positions after 10 frames are the same to the last bit
    with the default guard and with none."""
    def cloth():
        builder = ws.ModelBuilder(drag=0.05)
        spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
        builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, particle_mass=0.1, structural=spring, shear=spring,
                               bend=spring, pin=["top"])
        return builder.finalize(device, spring_evaluation="gather")

    positions = []
    for guard in (ws.GuardLimits(), None):
        model = cloth()
        sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=8, guard=guard)
        run_frames(sim, 10)
        positions.append(sim.state.particle_q.numpy())
    assert sim.guard is None
    assert np.array_equal(positions[0], positions[1])


def test_no_launch_per_substep_for_the_guard(device):
    """Symplectic Euler with gathered springs and drag: the default guard adds no launch to a substep; its check
    runs once per frame (frames of 16 and 32 substeps: the launches of the guarded frame less the unguarded frame's
    are the same whatever the substeps)."""
    def launches(guard, substeps):
        builder = ws.ModelBuilder(drag=0.05)
        spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
        builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, particle_mass=0.1, structural=spring, shear=spring,
                               pin=["top"])
        model = builder.finalize(device, spring_evaluation="gather")
        sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=substeps,
                           guard=guard, use_graph=False)
        for _ in range(WATCH_FRAMES + 1):  # past the frames a guard watches from the start (``Guard._watch``)
            sim.step_frame()
        count = [0]
        launch, flat = wp.launch, flatten._launch

        def counted(*args, **kwargs):
            count[0] += 1
            return launch(*args, **kwargs)

        def counted_flat(*args, **kwargs):  # a flat kernel's launch (replayed on the CPU: no ``wp.launch``)
            count[0] += 1
            wp.launch = launch  # (its own ``wp.launch`` is not a second launch)
            try:
                return flat(*args, **kwargs)
            finally:
                wp.launch = counted

        wp.launch, flatten._launch = counted, counted_flat
        try:
            sim.step_frame()
        finally:
            wp.launch, flatten._launch = launch, flat
        return count[0]

    # (at 4 its dampers are unstable; a check every frame, as the frame counted is then always checked)
    extra = [launches(ws.GuardLimits(check_frames=1), n) - launches(None, n) for n in (16, 32)]
    assert extra[0] == extra[1] > 0


def test_two_simulators_on_one_model_keep_their_own_sums(device):
    """Each guard hands its sums to its own integrator: two simulators of one model, one stepped, leave the other's
    balance untouched, and the stepped one's D is what it is alone."""
    model = oscillator(device, "scatter")
    first = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=8)
    second = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=8)
    assert first.integrator.dampers is not second.integrator.dampers
    assert getattr(model, "_damper_sums", None) is None
    run_frames(first, 30)
    alone = first.guard.energy_balance().dissipated[0]
    assert alone > 0.0
    assert second.guard.energy_balance().dissipated[0] == 0.0
    run_frames(second, 30)
    assert second.guard.energy_balance().dissipated[0] == pytest.approx(alone, rel=1e-6)


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4"])
def test_dampers_past_their_limit_are_caught_in_the_force_pass(device, integrator):
    """``test_dissipation.py``'s unstable dampers with gathered springs: an 8 × 8 cloth swings 1 s, then its dampers
    are raised in place to 21 N·s/m (kd h λ_D/m ≈ 2 on the stiffest damping mode at 16 substeps: the step
    overshoots and grows it; RK4's limit on a damping mode is 2.79: raised to 30 N·s/m for it). The counted D keeps
    every damper's loss ≥ 0 (the mean-rate rule, the trapezoid), so the energy the overshooting step creates shows
    in the balance and the run is stopped for it within 60 frames; an exact count of the step's damper work would
    have read it as the dampers putting energy in."""
    model = damped_gathered_cloth(device)
    # A check every frame: the dampers are raised in place, a write no check spanning frames would see (see
    # ``tests/test_guard_spans.py`` for the same raise written through the model).
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=16,
                       guard=ws.GuardLimits(check_frames=1))
    run_frames(sim, 60)
    before = sim.guard.energy_balance()
    assert abs(before.created[0]) < 0.02 * before.peak[0]  # a correct run: the balance closed
    raised = 21.0 if integrator == "symplectic_euler" else 30.0
    model.spring_damping.assign(np.full(model.spring_damping.shape, raised, dtype=np.float32))
    with pytest.raises(ws.SimulationError, match="energy") as stop:
        run_frames(sim, 60)
    assert stop.value.reason in ("energy balance", "kinetic energy")


def test_scattered_springs_with_drag_count_in_the_update(device):
    """Symplectic Euler with scattered springs (the CPU default) and drag: the springs' pass counts their dampers
    (``DamperSums``), the update the drag (``PowerSums.forces``), and over 2 s the oscillator's balance closes as the
    gathered run's does: the two runs' D agree to float32 round-off of their different summation orders (1e-4)."""
    dissipated = {}
    for evaluation in ("scatter", "gather"):
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, -G), drag=0.5)
        builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0 - MASS * G / K - AMPLITUDE]], mass=[1.0, MASS])
        builder.pin_particles([0])
        builder.add_springs([[0, 1]], stiffness=K, damping=KD, rest_length=1.0)
        model = builder.finalize(device, spring_evaluation=evaluation)
        sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=8)
        run_frames(sim, 120)
        assert sim.guard._power is not None
        assert (sim.guard._power.forces is not None) == (evaluation == "scatter")
        balance = sim.guard.energy_balance()
        assert abs(balance.created[0]) <= OMEGA * sim.dt * balance.peak[0]
        dissipated[evaluation] = balance.dissipated[0]
    assert dissipated["scatter"] == pytest.approx(dissipated["gather"], rel=1e-4)


def test_switching_the_balance_recaptures(device):
    """The force pass counts the power sums only where the balance is on, so switching it on or off between frames
    re-captures (with dissipation off and no working family, nothing else would)."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -G), drag=0.05)
    builder.add_cloth_grid(nx=4, ny=4, spacing=0.1, mass=0.2, pin=["top-left"])
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=8, guard=ws.GuardLimits(energy_balance=0.0, dissipation=False))
    sim.step_frame()
    assert sim.stepper.captures == 1 and sim.integrator.power is None
    sim.guard.limits = ws.GuardLimits(dissipation=False)
    sim.step_frame()
    assert sim.stepper.captures == 2
    sim.guard.limits = ws.GuardLimits(energy_balance=0.0, dissipation=False)
    sim.step_frame()
    assert sim.stepper.captures == 3


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4"])
@pytest.mark.parametrize("evaluation", ["gather", "scatter"])
def test_a_world_released_without_a_restart_counts_from_its_release(device, integrator, evaluation):
    """Two worlds of a 6 × 6 cloth in drag hung from its top row, the second thrown down at 8 m/s: with a tear strain
    of 5 % it fails at once and is held (``stop="world"``), held 20 frames while the force pass keeps stepping it (and
    throwing the step away), then released (``set_world_enabled``) without a restart. The sums of the held steps
    (its drag's and dampers' loss at 8 m/s, ~300 J against a budget of 87 J) are dropped at every check of the held
    world, so the released world's first checks count only its own steps: over 30 frames it is not stopped and its
    balance closes as the free world's does (within 2 % of its budget: symplectic Euler's O(h) energy error at
    16 substeps; before, it was stopped at its first check, "created" 303 J)."""
    builder = ws.ModelBuilder(drag=0.5)
    spring = ws.SpringMaterial(1.0e3, 1.0)
    builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, origin=(-0.25, -0.25, 1.0), particle_mass=0.1,
                           structural=spring, shear=spring, pin=["top"])
    model = builder.finalize(device, worlds=2, spring_evaluation=evaluation)
    n = model.particle_count
    velocity = model.particle_qd.numpy()
    free = (model.particle_flags.numpy()[n:] & 1) == 0
    velocity[n:, 2] = np.where(free, -8.0, 0.0)
    model.particle_qd.assign(velocity)
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=16,
                       guard=ws.GuardLimits(stop="world", tear_strain=0.05))
    run_frames(sim, 3)
    assert [w for w, (_, report) in sim.world_failures.items() if report.reason == "strain"] == [1]
    sim.guard.limits = ws.GuardLimits(stop="world")
    run_frames(sim, 20)
    model.set_world_enabled(1, True)
    sim.world_failures.clear()
    run_frames(sim, 30)
    assert not sim.world_failures
    balance = sim.guard.energy_balance()
    assert np.all(np.abs(balance.created) <= 0.02 * balance.peak)
    assert balance.dissipated[1] > 0.0  # its drag and dampers counted again once released


def test_power_summed_per_block_is_the_per_particle_sum(device, monkeypatch):
    """Symplectic Euler's fused step sums the guard's power per block into the running sums on CUDA (per particle on
    the CPU, where this test turns the blocks on): the wind-and-drag cloth above gives the same positions to the last
    bit, and the same dissipation and work up to the per-particle sums' float32 rounding (~1e-7 of each step's
    energy, summed over 480 steps: 1e-5 of D and W)."""
    import warpspring.core.guards as guards

    results = []
    for blocks in (True, False):
        monkeypatch.setattr(guards, "STEP_POWER_BLOCKS", {True: blocks, False: blocks})
        builder = ws.ModelBuilder(drag=0.02)
        spring = ws.SpringMaterial(ke=100.0, kd=0.5)
        builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, particle_mass=0.05, structural=spring, shear=spring,
                               pin=["top"])
        builder.add_aerodynamics(wind=(3.0, 0.0, 0.0))
        model = builder.finalize(device, spring_evaluation="gather")
        integrator = ws.make_integrator("symplectic_euler", model, cpu_sweep=False, one_launch=False)
        sim = ws.Simulator(model, integrator=integrator, fps=60, substeps=8)
        q = run_frames(sim, 60)
        assert (integrator.power_blocks is not None) == blocks
        results.append((q, sim.guard.energy_balance()))
    (q_blocks, blocks), (q_particles, particles) = results
    assert np.array_equal(q_blocks, q_particles)
    assert blocks.dissipated[0] > 0.01 * blocks.peak[0] and blocks.work[0] > 0.01 * blocks.peak[0]
    np.testing.assert_allclose(blocks.dissipated, particles.dissipated, rtol=1e-5)
    np.testing.assert_allclose(blocks.work, particles.work, rtol=1e-5)
    np.testing.assert_allclose(blocks.created, particles.created, atol=1e-5 * blocks.peak[0])


def test_power_summed_per_warp_is_the_per_particle_sum(device):
    """With ``POWER_WARP_TOTALS_FROM`` reached, symplectic Euler's per-substep step adds a warp's power to its first
    lane's entry on CUDA where the warp's lanes share a world (each lane its own elsewhere, and on the CPU): three
    worlds of a 48-particle cloth in wind and drag, so that some warps lie in one world, one spans two and the last is
    short, each world thrown with its own velocities. One substep's sums: each world's total as with the sums per
    particle, to float32 rounding, and on CUDA held in fewer entries (the warps' first lanes). Over 60 frames: the same
    positions to the last bit, and each world's dissipation and work as with the sums per particle up to their float32
    rounding (~1e-7 of each step's energy, summed over 480 steps: 1e-5 of D and W)."""
    results = []
    velocities = np.random.default_rng(7).normal(scale=0.05, size=(3 * 48, 3))
    for warps in (True, False):
        builder = ws.ModelBuilder(drag=0.02)
        spring = ws.SpringMaterial(ke=100.0, kd=0.5)
        builder.add_cloth_grid(nx=8, ny=6, spacing=0.1, particle_mass=0.05, structural=spring, shear=spring,
                               pin=["top"])
        builder.add_aerodynamics(wind=(3.0, 0.0, 0.0))
        model = builder.finalize(device, worlds=3, spring_evaluation="gather")
        assert model.particle_count == 48
        integrator = ws.make_integrator("symplectic_euler", model, cpu_sweep=False, one_launch=False)
        integrator.POWER_WARP_TOTALS_FROM = 0 if warps else 1 << 62
        sim = ws.Simulator(model, integrator=integrator, fps=60, substeps=8)
        sim.state.particle_qd.assign(velocities)
        sim.step_frame()  # (the guard hands the integrator its power sums)
        sums = integrator.power.sums
        sums.zero_()
        out = model.state()
        integrator.step(sim.state, out, sim.control, sim.dt)
        step = sums.numpy().reshape(3, 48, -1).astype(np.float64)
        sums.zero_()  # (the next check counts from here: the step's state was not kept)
        q = run_frames(sim, 60)
        results.append((step, q, sim.guard.energy_balance()))
    (step_warps, q_warps, warps), (step_particles, q_particles, particles) = results
    scale = np.abs(step_particles).sum(axis=1)
    assert np.all(scale > 0.0)
    np.testing.assert_allclose(step_warps.sum(axis=1), step_particles.sum(axis=1), atol=1e-6 * scale.max())
    if wp.get_device(device).is_cuda:
        assert np.count_nonzero(step_warps) < np.count_nonzero(step_particles)
    else:
        np.testing.assert_array_equal(step_warps, step_particles)
    assert np.array_equal(q_warps, q_particles)
    assert np.all(warps.dissipated > 0.01 * warps.peak) and np.all(warps.work > 0.01 * warps.peak)
    np.testing.assert_allclose(warps.dissipated, particles.dissipated, rtol=1e-5)
    np.testing.assert_allclose(warps.work, particles.work, rtol=1e-5)
    np.testing.assert_allclose(warps.created, particles.created, atol=1e-5 * warps.peak.max())
