"""The strict verdict past the step the theory passes (analysis/step_trial.py): between the three-wave step and the
linear limit the advisor cannot tell from the theory whether a cloth's top modes feed a resonance, and ``--strict``
decides by trial runs of the scene itself. It passes the steps whose runs hold (within 10 % of the largest that does,
where the theory's step was not: bench/results/advisor_battery_bisect_cpu.md) and refuses those whose runs grow, naming
what the trial saw; scenes whose energy it cannot measure keep the theory's verdict, and say why."""

import dataclasses
import math

import numpy as np
import pytest

import warpspring as ws

from warpspring.analysis import stability_battery as sb
from warpspring.analysis import step_trial, under_load
from warpspring.analysis.advisor import advise, shared_estimates
from warpspring.analysis.watch import StabilityWatch
from warpspring.errors import ConfigError


@pytest.mark.slow
@pytest.mark.parametrize("integrator", ["symplectic_euler", "velocity_verlet"])
def test_strict_passes_past_the_three_wave_step_where_the_runs_hold(device, integrator):
    # The 32² cloth released folded without gravity: the theory passes P = 0.975 √3/ω_max (1.525 ms), but its runs
    # hold to 1.725 ms (symplectic Euler) and 1.754 ms (Verlet) over 10 s, bracketed by bisection on the CPU: P is
    # 0.88 and 0.87 of that, not within 10 %. Up the ladder P · 1.05^k, each rung judged by its trial runs, --strict
    # passes Q ≥ 1.1 P; the runs at 0.9 Q (between the rungs) and Q hold, and the one at Q / 0.9 blows up (tight).
    case = sb.Case(32, 0.0, "folded", False)
    result = sb.measure(case, integrator, device, factors=(0.9, 1.0, 1.111))
    assert "three-wave" in result.advice.passed_reason
    assert result.strict >= 1.1 * result.advice.dt_passed, sb.table([result])
    assert result.one_sided() and result.tight(), sb.table([result])
    assert result.runs[-1].blown
    passed = [r for r in result.rungs if r.stable]
    assert passed and all(r.trial is not None and r.trial.passed and len(r.trial.runs) == 2 for r in passed)
    assert not result.rungs[-1].stable  # the ladder stops at the first refusal
    assert passed[-1].dt == pytest.approx(result.strict)
    assert "on trial" in passed[-1].message and "held" in passed[-1].message
    # The stability watch of a run passed on trial takes its limit from the larger step the trial held at, not from
    # the linear limit (RK4 on trial passes steps past it at a transient peak, which a watch would otherwise stop).
    advice, model = passed[-1], sb.battery_cloth(case, device)
    past = dataclasses.replace(advice.trial.runs[-1], dt=1.1 * advice.dt_stable)  # as an RK4 trial may hold
    for trial, limit in ((None, advice.dt_stable), (advice.trial, advice.dt_stable),
                         (dataclasses.replace(advice.trial, runs=[advice.trial.runs[0], past]), 1.1 * advice.dt_stable)):
        watch = StabilityWatch(model, integrator, advice.dt, fps=60.0, substeps=1, state=model.state(),
                               advice=dataclasses.replace(advice, trial=trial))
        assert watch.omega_limit[0] == pytest.approx(advice.omega_max * limit / advice.dt, rel=1e-12)


@pytest.mark.slow
def test_strict_refuses_on_trial_the_step_that_blows_up(device):
    # The case: the undamped 16² cloth released flat, symplectic Euler at 10 substeps per 1/60 s (1.667 ms),
    # within the linear limit (1.813 ms) and past the three-wave step (1.531 ms). Its run blows up within 10 s (the
    # battery: it grows from 1.075 P); --strict runs it on trial, refuses, and says what the run did. Without
    # strict no trial is run.
    model = sb.battery_cloth(sb.Case(16, 0.0, "flat", True), device)
    with shared_estimates():
        plain = advise(model, "symplectic_euler", 1.0 / 600.0, horizon=10.0)
        assert not plain.stable and plain.trial is None
        with pytest.raises(ConfigError) as error:
            advise(model, "symplectic_euler", 1.0 / 600.0, horizon=10.0, strict=True)
        tried = advise(model, "symplectic_euler", 1.0 / 600.0, horizon=10.0, trial=True)
    assert "1 trial run of this scene for 10 s" in str(error.value)
    assert not tried.stable and len(tried.trial.runs) == 1 and not tried.trial.runs[0].ok
    assert tried.trial.released[0] == pytest.approx(sb.case_free_energy(sb.Case(16, 0.0, "flat", True), device))
    # A step the theory passes needs no trial; one past TRIAL_CEILING × the linear limit gets none.
    with shared_estimates():
        assert advise(model, "symplectic_euler", 1.0 / 660.0, horizon=10.0, strict=True).trial is None
        far = advise(model, "symplectic_euler", 1.3 * plain.dt_stable, horizon=10.0, trial=True)
    assert not far.stable and far.trial is None


def _cloth(device, *, sphere=False, worlds=1):
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    builder.add_cloth_grid(nx=8, ny=8, spacing=sb.SPACING, origin=(0.0, 0.0, 1.0), particle_mass=sb.PARTICLE_MASS,
                           pin=["top-left", "top-right"],
                           **{name: ws.SpringMaterial(ke, 0.0) for name, ke in sb.STIFFNESS.items()})
    if sphere:
        builder.add_collider_sphere(center=(0.35, 0.35, -5.0), radius=0.5)
    return builder.finalize(device, worlds=worlds)


def test_the_trial_measures_only_what_its_meter_covers(device):
    # Hooke springs under gravity with pins: measured. Contacts, several worlds, wind: not, and --strict past the
    # theory's step then keeps the theory's verdict and says why.
    assert step_trial.trial_scope(_cloth(device)) == ""
    assert step_trial.trial_scope(_cloth(device, worlds=2)) == ""  # each world measured on its own
    with_sphere = _cloth(device, sphere=True)
    assert step_trial.trial_scope(with_sphere) == "contacts with 1 collider"  # named as the guard names suspects
    windy = _cloth(device)
    windy.set_world_values("wind", np.array([[3.0, 0.0, 0.0]]))
    assert step_trial.trial_scope(windy) == "wind"
    moving = _cloth(device)
    moving.particle_qd.assign(np.tile(np.array([[0.0, 0.0, 0.5]], dtype=np.float32), (moving.particle_count, 1)))
    assert step_trial.trial_scope(moving) == "pins moving at the start"  # they do work on the cloth
    with shared_estimates():
        theory = advise(with_sphere, "symplectic_euler", 1.0e-4, horizon=1.0)
        past = 1.05 * theory.dt_passed
        with pytest.raises(ConfigError, match=r"cannot judge this scene \(contacts with 1 collider\)"):
            advise(with_sphere, "symplectic_euler", past, horizon=1.0, strict=True)
    # Without strict no trial runs, and the message says --strict would decide; a trial is not run for another
    # stiffness than the model's (the run's springs are the model's), nor for a start that frees round-off alone.
    plain = _cloth(device)
    with shared_estimates():
        theory = advise(plain, "symplectic_euler", 1.0e-4, horizon=1.0)
        past = 1.05 * theory.dt_passed
        warned = advise(plain, "symplectic_euler", past, horizon=1.0)
        assert warned.trial is None and "--strict decides such a step by trial runs" in warned.message
    stiffer = advise(plain, "symplectic_euler", 1.05 * past, horizon=1.0, trial=True,
                     stiffness=1.1 * plain.spring_stiffness.numpy()[0])
    assert stiffer.trial is None and "cannot judge this scene (the state or stiffness" in stiffer.message
    settled = _cloth(device)
    settled.particle_q.assign(under_load.static_equilibrium(settled).positions.astype(np.float32))
    at_rest = advise(settled, "symplectic_euler", 1.05 * past, horizon=1.0, trial=True)
    assert at_rest.trial is None and "round-off against its energy scale" in at_rest.message


def test_a_trial_leaves_the_model_as_it_was_and_counts_the_start_s_motion(device):
    # A trial steps its own state: the model's initial positions are untouched, and a second trial repeats the first.
    # The free energy counts what the start carries: a chain at its rest lengths without gravity, moving at 2 m/s,
    # frees ½ m v² (the equilibrium is the rest lengths: zero).
    model = _cloth(device)
    before = model.particle_q.numpy().copy()
    released = step_trial.free_energy(model)
    first = step_trial.trial_run(model, "symplectic_euler", 1.0e-3, seconds=1.0, released=released)
    again = step_trial.trial_run(model, "symplectic_euler", 1.0e-3, seconds=1.0, released=released)
    np.testing.assert_array_equal(model.particle_q.numpy(), before)
    assert first.ok and first.excess == again.excess and math.isfinite(first.excess)
    # A run shorter than the 1 s mean is judged on its whole mean, not called grown for want of a window.
    short = step_trial.trial_run(model, "symplectic_euler", 1.0e-3, seconds=0.3, released=released)
    assert short.ok and math.isfinite(short.excess) and short.until == pytest.approx(0.3)
    with pytest.raises(ValueError, match="energy to judge against"):
        step_trial.trial_run(model, "symplectic_euler", 1.0e-3, seconds=0.3, released=0.0)
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles([[0.25 * i, 0.0, 1.0] for i in range(5)], mass=0.1)
    builder.add_springs([[i, i + 1] for i in range(4)], stiffness=100.0, rest_length=0.25)
    chain = builder.finalize(device)
    chain.particle_qd.assign(np.tile(np.array([[0.0, 2.0, 0.0]], dtype=np.float32), (5, 1)))
    assert step_trial.free_energy(chain) == pytest.approx(0.5 * 0.5 * 4.0, rel=1e-6)
    # Under gravity and with no pin, the chain falls as a whole: what the start frees into its springs is its stretch
    # (one spring 0.05 m long: ½ k Δ² = 0.125 J), not gravity's unbounded fall. A spring of zero rest length (a tether)
    # has no stretch to tear.
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    builder.add_particles([[0.25 * i + (0.05 if i == 4 else 0.0), 0.0, 1.0] for i in range(5)], mass=0.1)
    builder.add_springs([[i, i + 1] for i in range(4)], stiffness=100.0, rest_length=0.25)
    builder.add_springs([[0, 4]], stiffness=1.0, rest_length=0.0)
    falling = builder.finalize(device)
    x = falling.particle_q.numpy().astype(np.float64)
    tether = 0.5 * 1.0 * float(np.sum((x[4] - x[0]) ** 2))
    assert step_trial.free_energy(falling) == pytest.approx(0.125 + tether, rel=1e-5)
    meter = step_trial.EnergyMeter(falling, "symplectic_euler", 1.0e-3)
    assert meter(x, np.zeros_like(x))[3] == pytest.approx(0.30 / 0.25, rel=1e-6)


@pytest.mark.slow
def test_a_trial_judges_every_world(device):
    # The 32² folded cloth without gravity as two worlds, the second 0.8× as stiff: the first binds (its P is the
    # smaller), and at 1.1 P both worlds' runs hold (each judged against its own free energy), so --strict passes
    # it. Two worlds of the flat release under gravity, 16², the second the stiffer, at 1.667 ms: that world
    # blows up, and the refusal names it.
    def worlds(case, factors):
        model = sb.battery_cloth(case, device)
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81) if case.gravity else (0.0, 0.0, 0.0))
        builder.add_cloth_grid(nx=case.n, ny=case.n, spacing=sb.SPACING, origin=(0.0, 0.0, 1.0),
                               particle_mass=sb.PARTICLE_MASS, pin=["top-left", "top-right"],
                               **{name: ws.SpringMaterial(ke, 0.0) for name, ke in sb.STIFFNESS.items()})
        two = builder.finalize(device, worlds=2)
        two.particle_q.assign(np.tile(model.particle_q.numpy(), (2, 1)))
        two.set_world_values("spring_stiffness", two.spring_stiffness.numpy()[0] * np.array(factors)[:, None])
        return two

    folded = worlds(sb.Case(32, 0.0, "folded", False), [1.0, 0.8])
    meter = step_trial.EnergyMeter(folded, "symplectic_euler", 1.0e-3)
    x = folded.particle_q.numpy().astype(np.float64)
    energies = meter.worlds_energy(x, np.zeros_like(x))[0]  # the fold's elastic energy, 0.8× in the softer world
    assert energies[1] == pytest.approx(0.8 * energies[0], rel=1e-9) and energies[0] > 0.0
    moving = np.random.default_rng(7).normal(0.0, 0.3, x.shape)  # a world at a time (CHUNK) gives the same numbers
    whole = meter.worlds_energy(x, moving)
    meter.CHUNK = 1
    for a, b in zip(meter.worlds_energy(x, moving), whole):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match=r"one energy or one per world \(2\)"):
        step_trial.trial_run(folded, "symplectic_euler", 1.0e-3, seconds=0.1, released=[1.0, 1.0, 1.0])
    with shared_estimates():
        theory = advise(folded, "symplectic_euler", 1.0e-4, horizon=10.0)
        passed = advise(folded, "symplectic_euler", 1.1 * theory.dt_passed, horizon=10.0, trial=True)
    assert theory.world == 0 and passed.stable and passed.trial.passed, passed.message
    np.testing.assert_allclose(passed.trial.released, step_trial.world_free_energies(folded))
    assert passed.trial.released[1] == pytest.approx(0.8 * passed.trial.released[0], rel=1e-6)
    flat = worlds(sb.Case(16, 0.0, "flat", True), [0.8, 1.0])  # the stiffer second
    with pytest.raises(ConfigError, match=r"it failed on trial: .*in world 1 of 2"):
        advise(flat, "symplectic_euler", 1.0 / 600.0, horizon=10.0, strict=True)
