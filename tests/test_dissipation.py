"""The energy the dampers take out (D) in the guard's energy balance: it equals the energy a damped
oscillator loses, and with it the balance of a long damped run still catches energy an unstable step
creates, which the balance without D let pass as slack."""

import numpy as np
import pytest

import warpspring as ws
from helpers import hanging_cloth, run_frames

# A 2 kg mass on a 200 N/m spring with 5 % of critical damping, hanging from a pin, released 0.1 m below its
# static equilibrium at rest: ω = 10 rad/s, kd = 2 ζ √(k m) = 2 N·s/m.
MASS, K, G, ZETA, AMPLITUDE = 2.0, 200.0, 9.81, 0.05, 0.1
OMEGA = np.sqrt(K / MASS)
KD = 2.0 * ZETA * np.sqrt(K * MASS)


def oscillator_energy(t: float) -> float:
    """½ m v² + ½ k y² [J] of the damped oscillation about the static equilibrium at time t [s] (closed
    form: y = -A e^(-ζωt) (cos ω_d t + ζω/ω_d sin ω_d t), v = A ω²/ω_d e^(-ζωt) sin ω_d t)."""
    wd = OMEGA * np.sqrt(1.0 - ZETA**2)
    decay = np.exp(-ZETA * OMEGA * t)
    y = -AMPLITUDE * decay * (np.cos(wd * t) + ZETA * OMEGA / wd * np.sin(wd * t))
    v = AMPLITUDE * OMEGA**2 / wd * decay * np.sin(wd * t)
    return 0.5 * MASS * v * v + 0.5 * K * y * y


@pytest.mark.parametrize("integrator, order", [("rk4", 2), ("velocity_verlet", 2), ("symplectic_euler", 1)])
def test_dissipation_of_a_damped_spring_mass_is_its_lost_energy(device, integrator, order):
    """Over 2 s (fps 60, 8 substeps: ωh = 0.021) the guard's D equals the oscillator's closed-form energy
    loss from its reference (the first check, t = 1/60 s) to the end, and the balance E - (E_ref + W - D)
    closes. Tolerance (ωh)^order of the loss: the per-substep trapezoid of the power, which oscillates at
    2ω_d, is second order, and so is the energy error of RK4 and velocity Verlet; symplectic Euler's is
    first order. (Measured on the CPU: 7e-6, 1e-4 and 5e-4 of the loss.)"""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -G))
    builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0 - MASS * G / K - AMPLITUDE]], mass=[1.0, MASS])
    builder.pin_particles([0])
    builder.add_springs([[0, 1]], stiffness=K, damping=KD, rest_length=1.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=8)
    run_frames(sim, 120)
    tolerance = (OMEGA * sim.dt) ** order
    lost = oscillator_energy(1.0 / 60.0) - oscillator_energy(2.0)
    balance = sim.guard.energy_balance()
    assert lost > 0.8 * oscillator_energy(0.0)  # most of the 1 J is gone: the check has something to check
    assert balance.dissipated[0] == pytest.approx(lost, rel=tolerance)
    assert abs(balance.created[0]) <= tolerance * oscillator_energy(0.0)
    # Without D, the loss is slack: the balance shows it as energy missing.
    assert balance.created[0] - balance.dissipated[0] < -0.8 * lost


@pytest.mark.parametrize("omega_h", [0.5, 1.0, 1.5])
def test_symplectic_euler_counts_its_damper_loss_at_large_steps(device, omega_h):
    """Symplectic Euler's damper acts with the step's first velocity over the displacement of its last, so its loss
    per step is not the trapezoid of kd v² at the step's ends: that over-counts by ~(ωh)²/4 of the loss (NumPy, this
    oscillator: +6.7 %, +33 %, +129 % at ωh = 0.5, 1, 1.5), which the balance reads as energy created, and a driven
    cloth near its step limit was stopped (the next test). The guard samples the power at the step's midpoint state
    ((x_n + x_{n+1})/2, (v_n + v_{n+1})/2). A 2 kg mass on a spring without gravity, released 0.1 m from rest, 1
    substep of 1/60 s at ωh as given, kd h/m = 0.01: after 10 s, when ~99.8 % of its energy is gone, D is the energy
    lost within 1 % (NumPy: 1e-4 to 1e-3; the trapezoid's error is 7 to 130 %). The balance's limit is raised out of
    the way: while the oscillation lasts, the energy at a step's end swings about what the step conserves by up to
    1/(1 - ωh/2) (+33 % at ωh = 0.5), which a cloth, whose top modes hold little of its energy, keeps inside the
    limit, but one mode holding all of it does not."""
    h = 1.0 / 60.0
    stiffness = MASS * (omega_h / h) ** 2
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0 - AMPLITUDE]], mass=[1.0, MASS])
    builder.pin_particles([0])
    kd = 0.01 * MASS / h
    builder.add_springs([[0, 1]], stiffness=stiffness, damping=kd, rest_length=1.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=1,
                       guard=ws.GuardLimits(energy_balance=10.0))
    start = 0.5 * stiffness * AMPLITUDE**2
    run_frames(sim, 600)
    balance = sim.guard.energy_balance()
    assert sim.guard.counts_dissipation
    assert balance.energy[0] < 0.01 * start  # the check has something to check: nearly all of it was lost
    assert balance.work[0] == 0.0
    # D counts from the first check on: the first step, from rest to v₁ = hω²A, took out h kd (v₁/2)² (1.1 % of
    # the start at ωh = 1.5) before it.
    first = h * kd * (h * omega_h**2 / h**2 * AMPLITUDE / 2.0) ** 2
    assert balance.dissipated[0] == pytest.approx(start - balance.energy[0] - first, rel=1.0e-2)


def test_a_driven_cloth_near_its_step_limit_is_not_stopped(device):
    """The stability battery's driven cloth (``analysis.load_battery``: 20 × 20, corners on a ±0.1 m, 1 Hz
    track) at 11 kN/m under symplectic Euler at 1/480 s, inside the advisor's 12.3 kN/m and stable (it runs
    10 s without the dissipation counted), runs its 10 s with the default guard. With the trapezoid's D it
    was stopped at frame 346 for 19.8 J "created" of a 181 J budget."""
    from warpspring.analysis.load_battery import FPS, battery_cloth, battery_control

    model = battery_cloth("driven", np.array([1.1e4]), device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=FPS, substeps=8,
                       control=battery_control("driven", model))
    assert sim.guard.counts_dissipation
    run_frames(sim, int(10 * FPS))
    balance = sim.guard.energy_balance()
    assert balance.dissipated[0] > 0.25 * balance.peak[0]  # the dampers took out a good part of the budget
    assert balance.created[0] < 0.1 * balance.peak[0]


def _unstable_mid_run(device, dissipation: bool, *, settle: int = 180, frames: int = 60):
    """The damped cloth (8 × 8, ke = 1 kN/m, kd = 10 N·s/m, symplectic Euler at 1/960 s) released and run
    ``settle`` frames, then its dampers raised in place to 21 N·s/m, past the step's limit for them (kd h
    λ_D/m ≈ 2 on the network's stiffest damping mode: the step overshoots and grows it). A write in place
    changes no energy and takes no rebase, so the balance carries its history. Returns (the balance before
    the change, the frame after it the guard stopped at or None, the guard's report, the balance after each
    frame before)."""
    model, _ = hanging_cloth(device, n=8)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(dissipation=dissipation))
    run_frames(sim, settle)
    before = sim.guard.energy_balance()
    model.spring_damping.assign(np.full(model.spring_damping.shape, 21.0, dtype=np.float32))
    balances = []
    for frame in range(frames):
        try:
            sim.step_frame()
            sim.settle()  # (on CUDA the verdict comes a frame later: Simulator.defer_verdict)
        except ws.SimulationError as error:
            assert error.reason == "energy balance" and "unstable" in str(error)
            return before, frame, sim.guard.report(), balances
        balances.append(sim.guard.energy_balance())
    return before, None, None, balances


def test_a_long_damped_run_still_catches_an_unstable_step(device):
    """After 3 s the cloth's dampers have taken out ~10 J, 40 % of the 25 J the start and gravity supplied:
    without D that is slack, and the energy the unstable dampers then create has to exceed it before the
    balance sees anything. With D the balance is ~1 % of its budget before the change and stops the run once
    the created energy passes its 10 %; at that frame the balance without D (the same run: the guard does
    not change the state) still shows energy missing, and it stops later, after the integration created
    several times as much."""
    before, stop, report, _ = _unstable_mid_run(device, True)
    assert before.dissipated[0] > 0.3 * before.peak[0]
    assert abs(before.created[0]) < 0.02 * before.peak[0]
    assert stop is not None and report.energy_created > 0.1 * report.energy_budget
    old_before, old_stop, old_report, old_balances = _unstable_mid_run(device, False)
    assert old_before.dissipated[0] == 0.0
    assert old_before.created[0] < -0.3 * old_before.peak[0]
    assert old_stop is not None and old_stop > stop  # caught, but later
    assert old_balances[stop].created[0] < 0.0  # at the frame the balance with D stopped: still "missing"
    # The energy the integration had created when the balance without D stopped: its own count plus at least
    # the D of the same run up to the change (D only grows).
    created_unseen = old_report.energy_created + before.dissipated[0]
    assert created_unseen > 3.0 * report.energy_created


def test_damper_and_drag_power_hooks_against_float64(device):
    """The power the guard integrates, per hook, against NumPy float64 on random velocities: two springs'
    kd ((vj - vi)·d̂)², a hinge's kd θ̇² (θ̇ = Σ ∇θ · v) and drag c v·v on the free particle only. Two samples
    of the same state give the trapezoid h P exactly; float32 inputs: rtol 1e-5."""
    from warpspring.core.guards import Guard
    from warpspring.core.hinges import dihedral_gradient
    from warpspring.kernels.guards import RUNNING_DISSIPATION

    q = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.1, 0.1, 0.0], [0.1, -0.09, -0.03]])
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0), drag=0.3)
    builder.add_particles(q, mass=0.01, pinned=[True, True, True, False])
    builder.add_hinges([[0, 1, 2, 3]], stiffness=0.02, damping=0.004, rest_angle=0.0)
    builder.add_springs([[3, 0], [3, 1]], stiffness=100.0, damping=[0.5, 0.2])
    model = builder.finalize(device)
    v = np.random.default_rng(5).normal(size=(4, 3)).astype(np.float32)
    state = model.state()
    state.particle_qd.assign(v)
    h = 1.0e-3
    guard = Guard(model, ws.GuardLimits(), 1, dt=h)
    guard._dissipate(state)  # the first sample: the trapezoid's start
    guard._dissipate(state)
    total = guard._running.numpy()[0, :, RUNNING_DISSIPATION].sum()

    x, u = model.particle_q.numpy().astype(np.float64), v.astype(np.float64)
    springs = 0.0
    for (i, j), kd in (((3, 0), 0.5), ((3, 1), 0.2)):
        d = x[j] - x[i]
        springs += kd * (np.dot(u[j] - u[i], d / np.linalg.norm(d))) ** 2
    g = dihedral_gradient(*(x[None, a] for a in range(4)))[0]
    hinge = 0.004 * np.einsum("ak,ak->", g, u) ** 2
    drag = 0.3 * u[3] @ u[3]
    assert springs > 0.0 and hinge > 0.0
    assert total == pytest.approx(h * (springs + hinge + drag), rel=1e-5)


def test_dissipation_switched_off_and_on_between_frames(device):
    """``GuardLimits(dissipation=False)`` set between frames stops counting D (it stays where it was) and
    re-captures; switched back on, D grows again from a fresh trapezoid. The spring-mass of the first test,
    symplectic Euler."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -G))
    builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0 - MASS * G / K - AMPLITUDE]], mass=[1.0, MASS])
    builder.pin_particles([0])
    builder.add_springs([[0, 1]], stiffness=K, damping=KD, rest_length=1.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=8)
    run_frames(sim, 30)
    first = sim.guard.energy_balance().dissipated[0]
    sim.guard.limits = ws.GuardLimits(dissipation=False)
    run_frames(sim, 30)
    assert sim.guard.energy_balance().dissipated[0] == first > 0.0
    sim.guard.limits = ws.GuardLimits()
    run_frames(sim, 30)
    assert sim.guard.energy_balance().dissipated[0] > first


@pytest.mark.parametrize("integrator, counted", [("symplectic_euler", True), ("velocity_verlet", True),
                                                 ("rk4", True), ("explicit_euler", False), ("midpoint", False),
                                                 ("dopri5", False)])
def test_which_runs_count_the_dissipation(device, integrator, counted):
    """D is counted where the balance with it is exact up to the integrator's error: not for the integrators
    that need damping to be stable (their own energy error on a damped mode nears its damping at their
    limit), not for dopri5 (internal steps), not with a collider or strain limiting (position corrections),
    and not without a step or with ``dissipation=False``. Nothing runs: construction only."""
    from warpspring.core.guards import Guard

    def guard(*, sphere=False, limits=ws.GuardLimits(), dt=1.0 / 480.0, strain_limit=False):
        builder = ws.ModelBuilder(stabilizers=ws.Stabilizers(max_strain=0.1) if strain_limit else None)
        builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]], mass=[1.0, MASS])
        builder.pin_particles([0])
        builder.add_springs([[0, 1]], stiffness=K, damping=KD)
        if sphere:
            builder.add_collider_sphere(center=(0.0, 0.0, -3.0), radius=0.5)
        model = builder.finalize(device)
        return Guard(model, limits, 8, integrator=ws.make_integrator(integrator, model), dt=dt)

    assert guard().counts_dissipation == counted
    assert not guard(sphere=True).counts_dissipation
    assert not guard(strain_limit=True).counts_dissipation
    assert not guard(dt=None).counts_dissipation
    assert not guard(limits=ws.GuardLimits(dissipation=False)).counts_dissipation
