"""The closed-form damped oscillator against an independent numerical solution and against its own ODE.

References: scipy's DOP853 at rtol = atol = 1e-13 (relative to the motion's size; its global error on
these ~10-period runs stays below ~1e-10 of it, checked against 40-digit mpmath), and the ODE residual
m ẍ + c ẋ + k x − F of central differences of the closed form (truncation error h²/6 · |x⁽³⁾|, rounding
ε |x| / h).
"""

import math

import numpy as np
import pytest
from scipy.integrate import quad, solve_ivp

from warpspring.analysis.analytic import DampedOscillator
from warpspring.errors import ConfigError

CASES = {
    # The seed block: 45 kg on k = 180 N/m (ω₀ = 2 rad/s), c = 18 N·s/m (ζ = 0.1), pushed by 75 N from rest.
    "seed": DampedOscillator(mass=45.0, damping=18.0, stiffness=180.0, force=75.0),
    "stiff": DampedOscillator.from_frequency(omega=100.0, zeta=0.01, force=100.0, x0=0.02, v0=-1.0),
    "undamped": DampedOscillator(mass=2.0, damping=0.0, stiffness=50.0, x0=0.3, v0=0.5),
    "critical": DampedOscillator.from_frequency(omega=3.0, zeta=1.0, mass=2.0, force=-4.0, x0=0.5, v0=2.0),
    "near-critical-under": DampedOscillator.from_frequency(omega=3.0, zeta=1.0 - 1e-9, x0=0.5, v0=2.0),
    "near-critical-over": DampedOscillator.from_frequency(omega=3.0, zeta=1.0 + 1e-9, x0=0.5, v0=2.0),
    "overdamped": DampedOscillator.from_frequency(omega=3.0, zeta=2.5, mass=0.7, force=1.0, x0=-0.2, v0=4.0),
    "strongly-overdamped": DampedOscillator.from_frequency(omega=1.0, zeta=50.0, x0=1.0, v0=-3.0),
}


def fastest_rate(osc: DampedOscillator) -> float:
    """The largest |root| of m r² + c r + k = 0 [1/s]: ω₀ when underdamped, σ + √(σ² − ω₀²) when overdamped."""
    sigma, w = osc.decay_rate, osc.natural_frequency
    return max(w, sigma + math.sqrt(max(sigma * sigma - w * w, 0.0)))


def periods(osc: DampedOscillator, count: float = 10.0) -> float:
    """``count`` natural periods [s]."""
    return count * 2.0 * math.pi / osc.natural_frequency


def scale(osc: DampedOscillator) -> float:
    """Size of the motion [m]: the larger of the initial offset from equilibrium and v₀/ω₀, and F/k."""
    return max(abs(osc.x0 - osc.equilibrium), abs(osc.v0) / osc.natural_frequency, abs(osc.equilibrium))


@pytest.mark.parametrize("name", list(CASES))
def test_matches_numerical_solution(name):
    osc = CASES[name]
    m, c, k, f = osc.mass, osc.damping, osc.stiffness, osc.force
    t = np.linspace(0.0, periods(osc), 801)
    ref = solve_ivp(
        lambda _, y: [y[1], (f - c * y[1] - k * y[0]) / m],
        (0.0, t[-1]),
        [osc.x0, osc.v0],
        method="DOP853",
        t_eval=t,
        rtol=1e-13,
        atol=1e-13 * scale(osc),
    )
    assert ref.success
    x, v = osc.state(t)
    np.testing.assert_allclose(x, ref.y[0], rtol=0, atol=1e-9 * scale(osc))
    np.testing.assert_allclose(v, ref.y[1], rtol=0, atol=1e-9 * scale(osc) * fastest_rate(osc))


@pytest.mark.parametrize("name", list(CASES))
def test_satisfies_ode_and_initial_conditions(name):
    osc = CASES[name]
    assert osc.position(0.0) == pytest.approx(osc.x0, abs=1e-15)
    assert osc.velocity(0.0) == pytest.approx(osc.v0, abs=1e-15)
    r, a = fastest_rate(osc), scale(osc)
    # Central differences with h = 1e-5 / r: the p-th derivative is ~a rᵖ (times p at a double root), so
    # the truncation error of a derivative is (rh)² / 6 · p a rᵖ ≈ 2e-11 p a rᵖ, rounding ε a rᵖ⁻¹ / h ≈ 2e-11 a rᵖ.
    h = 1e-5 / r
    t = np.linspace(h, periods(osc, 3.0), 301)
    dx = (osc.position(t + h) - osc.position(t - h)) / (2 * h)
    dv = (osc.velocity(t + h) - osc.velocity(t - h)) / (2 * h)
    x, v = osc.state(t)
    np.testing.assert_allclose(dx, v, rtol=0, atol=1e-8 * a * r)
    # The residual is a force: compare it with the largest force term, the inertia m a r² of the fastest mode.
    residual = osc.mass * dv + osc.damping * v + osc.stiffness * x - osc.force
    np.testing.assert_allclose(residual, 0.0, atol=1e-8 * osc.mass * a * r * r)


def test_regimes_and_rest():
    assert CASES["seed"].regime == "underdamped"
    assert CASES["overdamped"].regime == "overdamped"
    critical = DampedOscillator(mass=1.0, damping=4.0, stiffness=4.0)  # 4km = c² exactly
    assert critical.regime == "critical"
    for osc in CASES.values():
        # Every damped case settles at F/k: 60 periods (strongly overdamped: 50 / its slow rate ω/(2ζ)).
        if osc.damping > 0.0:
            slow_rate = osc.decay_rate - math.sqrt(max(osc.decay_rate**2 - osc.natural_frequency**2, 0.0))
            late = 50.0 / slow_rate + periods(osc, 60.0)
            assert osc.position(late) == pytest.approx(osc.equilibrium, abs=1e-12 * scale(osc))
            assert np.isfinite(osc.state(1e6 * late)).all()  # no overflow of the growing exponentials


def test_continuous_across_critical_damping():
    """ζ = 1 ± 1e-9 differ from ζ = 1 by O(1e-9): the three forms of S(t) join without cancellation."""
    t = np.linspace(0.0, 5.0, 101)
    exact = DampedOscillator.from_frequency(omega=3.0, zeta=1.0, x0=0.5, v0=2.0)
    assert exact.regime == "critical"
    for name in ("near-critical-under", "near-critical-over"):
        np.testing.assert_allclose(CASES[name].position(t), exact.position(t), rtol=0, atol=1e-8)
        np.testing.assert_allclose(CASES[name].velocity(t), exact.velocity(t), rtol=0, atol=1e-8)


@pytest.mark.parametrize("name", ["seed", "stiff", "overdamped", "critical"])
def test_energy_balance(name):
    """E(t) − E(0) = −c ∫₀ᵗ ẋ² ds: the constant force's potential −F x makes damping the only loss."""
    osc = CASES[name]
    for t in np.linspace(0.0, periods(osc, 2.0), 7)[1:]:
        dissipated, _ = quad(lambda s: osc.damping * osc.velocity(s) ** 2, 0.0, t, epsabs=1e-13, limit=200)
        assert osc.energy(t) - osc.energy(0.0) == pytest.approx(-dissipated, abs=1e-9 * osc.stiffness * scale(osc) ** 2)


def test_energy_constant_without_damping():
    osc = CASES["undamped"]
    e = osc.energy(np.linspace(0.0, periods(osc, 50.0), 1001))
    np.testing.assert_allclose(e, e[0], rtol=1e-12)
    assert osc.oscillation_energy == pytest.approx(e[0])  # F = 0: rest is at x = 0 with zero energy


def test_seed_oscillation_energy():
    """The seed starts at rest at x = 0: E(0) = 0 and E at rest is −F²/2k, so F²/2k is damped away."""
    osc = CASES["seed"]
    assert osc.oscillation_energy == pytest.approx(75.0**2 / (2 * 180.0))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(mass=0.0, damping=1.0, stiffness=1.0), "mass > 0"),
        (dict(mass=1.0, damping=-1.0, stiffness=1.0), "damping >= 0"),
        (dict(mass=1.0, damping=1.0, stiffness=float("nan")), "stiffness must be finite"),
        (dict(mass=1.0, damping=1.0, stiffness=1.0, force="3"), "force must be a number"),
    ],
)
def test_invalid_parameters(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        DampedOscillator(**kwargs)
