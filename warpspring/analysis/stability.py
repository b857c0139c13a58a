"""Explicit-integration stability: the theory of each integrator, a spring network's highest frequency,
and an advisor that turns both into a largest stable step.

**One damped spring.** The test oscillator ẍ = -ω²x - 2ζωẋ in the coordinates u = (ωx, v) reads
h u̇ = Z u with Z = [[0, a], [-a, -b]], a = ωh, b = 2ζωh. Every fixed-step integrator of the registry maps
u₀ to u₁ = R u₀ with R = N(a, b) / q(a, b): N a 2 × 2 matrix of polynomials, q a scalar polynomial (1 for
explicit methods). They are built here with exact rational arithmetic from each integrator's own update
equations, as the integrator implements them:

* explicit Runge-Kutta methods (explicit Euler, midpoint, RK4, and the 5th-order solution of dopri5)
  from the Butcher tableau of the class, stage by stage;
* symplectic Euler: v₁ = v₀ + h a(x₀, v₀), x₁ = x₀ + h v₁ (spring damping explicit, at v₀);
* velocity Verlet with its damping corrector: v½ = v₀ + ½h a(x₀, v₀), x₁ = x₀ + h v½,
  v* = v½ + ½h a(x₁, v½), v₁ = v½ + ½h a(x₁, v*);
* (linearised) implicit Euler, exact for a linear spring: (I - Z) u₁ = u₀, R = adj(I - Z) / det(I - Z).

The spectral radius satisfies ρ(R) ≤ 1 exactly when (Schur-Cohn/Jury, 2 × 2) |det R| ≤ 1 and
|tr R| ≤ 1 + det R, i.e. with q² > 0 when the three polynomials

    g₁ = q² - det N,    g₂ = q² + det N - q tr N,    g₃ = q² + det N + q tr N

are all ≥ 0. Along a ray (a, b) = s (α, β) each gᵢ is a polynomial in s with exact rational
coefficients, so the largest stable step is found without a tolerance on ρ: the lowest nonzero
coefficient decides the sign as s → 0 (explicit Euler and midpoint on an undamped spring are unstable
for every h, exactly), the real roots bracket the first sign change, and bisection pins it down to the
polynomials' floating-point rounding (~1e-12 relative). :func:`stable_step` and :func:`stable_omega_h`
return it; implicit Euler has none (∞).

**A spring network.** Its modes have angular frequencies ω ∈ (0, ω_max], ω_max² = λ_max(M⁻¹K). An axial
damper adds kd d̂d̂ᵀ, which is (kd/k) times the spring's stiffness block k d̂d̂ᵀ at rest length:
stiffness-proportional (Rayleigh) damping, so a mode of frequency ω has the damping rate
2ζω = (kd/k) ω², and viscous drag c adds c/m: ζ(ω) = (kd/k) ω/2 + c/(2mω). (Stretched springs also have
a transverse stiffness, which the damper does not damp: for the modes it carries the model assumes more
damping than there is, which errs on the safe side for symplectic Euler and on the other for explicit
Euler and midpoint, which rely on damping.) The network's limit is the smallest stable step over a log-spaced sweep of
ω up to ω_max (and ω → 0, where drag alone acts) — :func:`network_stable_step`. When kd/k or c/m differ
between springs or particles the modes no longer decouple exactly; the sweep then runs at each ratio
given and keeps the smallest step (more damping lowers the limit of symplectic Euler but raises that
of midpoint, so one value alone is not safe). The advisor passes the least damped springs' kd/k and the
top mode's own damping (see :func:`advise`).

**ω_max of a model** (:func:`estimate_omega_max`): power iteration on M⁻¹K on the model's device, with K
the springs' stiffness matrices at the current positions (compressive transverse part clamped, so
K ⪰ 0; clamping only adds stiffness, so the estimate is not lowered by it), pinned particles filtered
out, matrix-free through a gather over the incidence table (``kernels/stability.py``). Its Rayleigh
quotient never exceeds λ_max; the Gershgorin bound ω_max² ≤ maxᵢ (Σₛ kₛ + Σ_{s to free j} kₛ) / mᵢ
(:func:`gershgorin_omega_max`, host NumPy; each clamped spring block has spectral norm kₛ) never falls
below it, and is the cheap fallback. A model of several worlds gets one ω_max per world (each world's
stiffness and masses), all worlds iterating in the same launches, each to its own tolerance.

**Under load** (:func:`loaded_state`, :func:`transient_peak`). A stretched spring of tension T and length
l adds the transverse stiffness T/l = k(1 - L/l) to the axial k: a cloth hanging from two pins has stiffer
modes than the same cloth at rest, up to √2 times the frequency of its in-plane modes when every spring is
far stretched (a flat cloth at rest has no transverse stiffness at all). Linearised about its initial
state, the advisor overrated a 20 × 20 RK4 cloth's stable stiffness by 1/0.65 under gravity. So when loads
act (gravity, the control's external force), the advisor linearises about the state they carry the model
to: the static equilibrium x_eq (pins held at their t = 0 place), found by quasi-static implicit Euler
steps (each one a regularised Newton step on the potential, the velocities zeroed after it). That is not
yet the stiffest state of the run: released unstretched, the cloth swings past its static stretch before
it settles, and the advisor linearised at x_eq was 2.5–13.5 % optimistic for symplectic Euler, velocity
Verlet and RK4 at small steps (bench/RESULTS.md §11). A swing along the ray x₀ + s (x_eq - x₀) does not
model it (the cloth reaches equilibrium through large rotations, which the ray turns into stretch). So
when the model moves by itself, the advisor also takes each world's peak ω_max over a dry run of the
scene (:func:`transient_peak`): velocity Verlet at half the step the Gershgorin bound proves stable at
any state, ω_max re-estimated along the way by warm-started power iterations, until the peaks stop rising
(or the run's duration). Measured with it on the battery (three scenes, five integrators, two steps
each): no run it passes blows up; it is within 10 % for symplectic Euler, velocity Verlet and RK4, and
14–41 % conservative for explicit Euler and midpoint over 10 s runs. Against the exact one-step map of the
linearised cloth (:mod:`.modal`, :func:`step_matrix`) the advisor linearised at the equilibrium is the top
mode's limit for all five (to the power iteration's ~1e-4), so those two integrators' runs past it are
linearly unstable, only too slowly to show in 10 s. They rely on damping, and the transverse modes have
none (see above): those grow slowly at any step, and over 100 s explicit Euler blows up inside the
advisor's limit.

**The advisor** (:func:`advise`) combines both for a model, an integrator and a step; with several worlds
each world gets its own limit and the smallest binds.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np
import warp as wp

from .. import checks
from ..checks import format_duration
from ..errors import ConfigError
from ..core.integrators import INTEGRATORS, ExplicitRungeKutta, ImplicitEuler, SymplecticEuler, VelocityVerlet
from ..kernels.kinematics import PARTICLE_KINEMATIC
from ..kernels.flatten import flat_launch
from ..kernels.linalg import reduce_lanes, reduce_launch_dim, sum_partials_kernel
from ..kernels.stability import (PI_LAMBDA, PI_PARTIALS, PI_RESIDUAL, PI_SCALARS, PI_XKX,
                                 power_iteration_kernels)
from ..core.model import Model
from ..core.state import State
from ..core.springs import SPRING_LAWS, SpringFamily, spring_law_codes

#: Estimates of ω_max (see :func:`advise`).
OMEGA_ESTIMATES = ("power_iteration", "gershgorin")
#: The network sweep covers ω from ω_max · SWEEP_DECADES decades below up to ω_max, ...
SWEEP_DECADES = 4
#: ... with this many log-spaced frequencies per decade, then refines around the smallest step.
SWEEP_PER_DECADE = 8

# -- exact polynomial arithmetic ---------------------------------------------------------------------------


class _Poly:
    """A polynomial in a = ωh and b = 2ζωh with exact rational coefficients: {(i, j): c} is Σ c aⁱ bʲ."""

    __slots__ = ("terms",)

    def __init__(self, terms: dict):
        self.terms = {k: c for k, c in terms.items() if c != 0}

    @staticmethod
    def lift(value) -> _Poly:
        return value if isinstance(value, _Poly) else _Poly({(0, 0): Fraction(value)})

    def __add__(self, other):
        terms = dict(self.terms)
        for key, c in _Poly.lift(other).terms.items():
            terms[key] = terms.get(key, 0) + c
        return _Poly(terms)

    __radd__ = __add__

    def __neg__(self):
        return _Poly({key: -c for key, c in self.terms.items()})

    def __sub__(self, other):
        return self + -_Poly.lift(other)

    def __rsub__(self, other):
        return _Poly.lift(other) + -self

    def __mul__(self, other):
        if isinstance(other, _Row):
            return NotImplemented
        terms: dict = {}
        for (i, j), c in self.terms.items():
            for (k, l), d in _Poly.lift(other).terms.items():
                terms[i + k, j + l] = terms.get((i + k, j + l), 0) + c * d
        return _Poly(terms)

    __rmul__ = __mul__

    def along(self, alpha: Fraction, beta: Fraction) -> list[Fraction]:
        """Exact coefficients c_k of Σ c_k sᵏ, the polynomial on the ray (a, b) = s (α, β)."""
        degree = max((i + j for i, j in self.terms), default=0)
        alpha_pow = [alpha**i for i in range(degree + 1)]
        beta_pow = [beta**j for j in range(degree + 1)]
        coefficients = [Fraction(0)] * (degree + 1)
        for (i, j), c in self.terms.items():
            coefficients[i + j] += c * alpha_pow[i] * beta_pow[j]
        return coefficients

    def __call__(self, a: float, b: float) -> float:
        return sum(float(c) * a**i * b**j for (i, j), c in self.terms.items())


class _Row:
    """A linear form p_x ωx₀ + p_v v₀ on the initial state, with polynomial coefficients: one state
    quantity (a position or a velocity) of a step, as a function of the step's input."""

    __slots__ = ("x", "v")

    def __init__(self, x, v):
        self.x, self.v = _Poly.lift(x), _Poly.lift(v)

    def __add__(self, other: _Row) -> _Row:
        return _Row(self.x + other.x, self.v + other.v)

    def __sub__(self, other: _Row) -> _Row:
        return _Row(self.x - other.x, self.v - other.v)

    def __rmul__(self, factor) -> _Row:
        return _Row(factor * self.x, factor * self.v)


_A = _Poly({(1, 0): Fraction(1)})  # a = ωh
_B = _Poly({(0, 1): Fraction(1)})  # b = 2ζωh


def _kick(x: _Row, v: _Row) -> _Row:
    """h × acceleration of the test oscillator at (x, v), in the coordinates (ωx, v): -a ωx - b v."""
    return (-_A) * x - _B * v


def _drift(v: _Row) -> _Row:
    """h × the rate of ωx: a v."""
    return _A * v


def _tableau_rational(value: float) -> Fraction:
    # Butcher coefficients are rationals with small denominators (dopri5's largest: 339200); recovering
    # them from their float values keeps the order conditions exact, so the low-order coefficients of the
    # stability polynomials cancel exactly instead of leaving rounding residues of either sign.
    return Fraction(value).limit_denominator(1_000_000)


@dataclass(frozen=True)
class _Algebra:
    """What an integrator's update equations act on: the step's input (x₀, v₀) as elements of a linear
    algebra, ``kick`` (h × the acceleration at (x, v)), ``drift`` (h × the rate of x at v) and how a
    coefficient of the method enters (``coefficient``). The test oscillator's algebra is that of
    :class:`_Row` with exact rational coefficients; :func:`step_matrix` uses dense matrices."""

    x0: object
    v0: object
    kick: object
    drift: object
    coefficient: object


_OSCILLATOR = _Algebra(_Row(1, 0), _Row(0, 1), _kick, _drift, _tableau_rational)


def _runge_kutta(a: tuple, b: tuple, algebra: _Algebra) -> tuple:
    x0, v0, c = algebra.x0, algebra.v0, algebra.coefficient
    stage_x, stage_v = [], []
    for k in range(len(b)):
        x, v = x0, v0
        for j, value in enumerate(a[k]):
            if value:
                x, v = x + c(value) * stage_x[j], v + c(value) * stage_v[j]
        stage_x.append(algebra.drift(v))
        stage_v.append(algebra.kick(x, v))
    x, v = x0, v0
    for j, value in enumerate(b):
        if value:
            x, v = x + c(value) * stage_x[j], v + c(value) * stage_v[j]
    return x, v


def _symplectic_euler(algebra: _Algebra) -> tuple:
    v1 = algebra.v0 + algebra.kick(algebra.x0, algebra.v0)
    x1 = algebra.x0 + algebra.drift(v1)
    return x1, v1


def _velocity_verlet(algebra: _Algebra) -> tuple:
    # The corrector runs only for velocity-dependent forces; without damping (b = 0) it changes nothing,
    # so one expression covers both cases.
    half, kick = algebra.coefficient(0.5), algebra.kick
    v_half = algebra.v0 + half * kick(algebra.x0, algebra.v0)
    x1 = algebra.x0 + algebra.drift(v_half)
    v_star = v_half + half * kick(x1, v_half)
    v1 = v_half + half * kick(x1, v_star)
    return x1, v1


def _explicit_update(integrator: str, algebra: _Algebra) -> tuple | None:
    """(x₁, v₁) of one step of the named integrator in ``algebra``; None for an implicit one."""
    cls = _integrator_class(integrator)
    if issubclass(cls, ExplicitRungeKutta):
        return _runge_kutta(cls.a, cls.b, algebra)
    if issubclass(cls, SymplecticEuler):
        return _symplectic_euler(algebra)
    if issubclass(cls, VelocityVerlet):
        return _velocity_verlet(algebra)
    return None


def _implicit_euler() -> tuple[tuple[_Row, _Row], _Poly]:
    # (I - Z) u₁ = u₀ with I - Z = [[1, -a], [a, 1 + b]]: u₁ = adj(I - Z) u₀ / det(I - Z).
    return (_Row(1 + _B, _A), _Row(-_A, 1)), 1 + _B + _A * _A


@functools.cache
def _propagator(integrator: str) -> tuple[tuple[tuple[_Poly, _Poly], tuple[_Poly, _Poly]], _Poly]:
    """(N, q) of the named integrator: its one-step map of the test oscillator is N / q."""
    update = _explicit_update(integrator, _OSCILLATOR)
    if update is not None:
        (x1, v1), q = update, _Poly.lift(1)
    elif issubclass(_integrator_class(integrator), ImplicitEuler):
        (x1, v1), q = _implicit_euler()
    else:
        raise ConfigError(f"no stability theory for the {integrator!r} integrator "
                          f"({_integrator_class(integrator).__name__})")
    return ((x1.x, x1.v), (v1.x, v1.v)), q


@functools.cache
def _jury_polynomials(integrator: str) -> tuple[_Poly, _Poly, _Poly]:
    """g₁, g₂, g₃: ρ(N/q) ≤ 1 exactly where all three are ≥ 0."""
    (n00, n01), (n10, n11) = _propagator(integrator)[0]
    q = _propagator(integrator)[1]
    trace, det, q2 = n00 + n11, n00 * n11 - n01 * n10, q * q
    return q2 - det, q2 + det - q * trace, q2 + det + q * trace


def _integrator_class(integrator: str):
    try:
        return INTEGRATORS[integrator]
    except KeyError:
        raise ConfigError(
            f"unknown integrator {integrator!r}: choose one of {', '.join(sorted(INTEGRATORS))}"
        ) from None


# -- the stable interval along a ray ------------------------------------------------------------------------


def _float_sign(approx: np.ndarray, s: float) -> int:
    """Sign of Σ c_k sᵏ in floating point: ±1, or 0 when the sum is within rounding of zero."""
    terms = approx * s ** np.arange(len(approx))
    value = float(terms.sum())
    if abs(value) <= 1e-12 * float(np.abs(terms).sum()):
        return 0
    return 1 if value > 0.0 else -1


def _is_negative(exact: list[Fraction], approx: np.ndarray, s: float) -> bool:
    """Whether Σ c_k sᵏ < 0: in floating point when the sum is clearly away from zero, else exactly."""
    sign = _float_sign(approx, s)
    if sign:
        return sign < 0
    point = Fraction(s)
    return sum(c * point**k for k, c in enumerate(exact)) < 0


def _first_negative(coefficients: list[Fraction]) -> float:
    """The largest s* with Σ c_k sᵏ ≥ 0 on all of (0, s*]: 0 when negative just above 0, ∞ when never.

    Finite s* are located to within the polynomial's floating-point rounding (~1e-12 relative).
    """
    lowest = next((k for k, c in enumerate(coefficients) if c != 0), None)
    if lowest is None:  # identically zero: the condition holds with equality everywhere
        return math.inf
    exact = coefficients[lowest:]  # divided by s^lowest, which is positive for s > 0
    if exact[0] < 0:
        return 0.0
    approx = np.array([float(c) for c in exact])
    # Sign changes lie at real roots; real parts of all roots (complex ones included, since a close pair
    # of real roots may come back as a complex pair) give points on both sides of every crossing.
    roots = np.roots(approx[::-1]) if len(approx) > 1 else np.empty(0)
    samples, previous = [], 0.0
    for root in sorted({float(r.real) for r in roots if r.real > 0.0}):
        samples += [0.5 * (previous + root), root]
        previous = root
    samples.append(2.0 * previous + 1.0)  # past every root the sign no longer changes
    low = 0.0
    for s in samples:
        if _is_negative(exact, approx, s):
            high = s
            while high - low > 4.0 * np.finfo(float).eps * high:
                mid = 0.5 * (low + high)
                sign = _float_sign(approx, mid)
                if sign == 0:  # within rounding of the root
                    break
                low, high = (low, mid) if sign < 0 else (mid, high)
            return low
        low = s
    return math.inf


def _stable_scale(integrator: str, omega: float, rate: float) -> float:
    """Largest h with ρ ≤ 1 for the mode of angular frequency ``omega`` [rad/s] and damping rate
    ``rate`` = 2ζω [1/s] (both ≥ 0, not both 0): on the ray (a, b) = s (ω, rate)/(ω + rate), h = s/(ω + rate)."""
    w, r = Fraction(omega), Fraction(rate)
    alpha, beta = w / (w + r), r / (w + r)
    s = min(_first_negative(g.along(alpha, beta)) for g in _jury_polynomials(integrator))
    return s / (omega + rate)


# -- public theory -----------------------------------------------------------------------------------------


def amplification_matrix(integrator: str, omega_h: float, zeta: float) -> np.ndarray:
    """The one-step map of the test oscillator ẍ = -ω²x - 2ζωẋ under ``integrator``.

    Args:
        integrator: registry name (see ``warpspring.INTEGRATORS``); for dopri5, a fixed step of its
            5th-order solution.
        omega_h: ωh [-], ≥ 0.
        zeta: damping ratio ζ [-], ≥ 0.

    Returns:
        R, shape [2, 2], float64, acting on (ωx, v): (ωx₁, v₁) = R (ωx₀, v₀).
    """
    (n00, n01), (n10, n11) = _propagator(integrator)[0]
    q = _propagator(integrator)[1]
    a, b = float(omega_h), 2.0 * float(zeta) * float(omega_h)
    return np.array([[n00(a, b), n01(a, b)], [n10(a, b), n11(a, b)]]) / q(a, b)


def spectral_radius(integrator: str, omega_h: float, zeta: float) -> float:
    """ρ of :func:`amplification_matrix` (float64 eigenvalues): the asymptotic growth factor per step."""
    return float(np.abs(np.linalg.eigvals(amplification_matrix(integrator, omega_h, zeta))).max())


def step_matrix(integrator: str, dt: float, mass, stiffness, damping) -> np.ndarray:
    """The one-step map of the linear system M ẍ + D ẋ + K x = 0 under ``integrator``, built by the same
    update equations as its test-oscillator theory (:func:`amplification_matrix`), in dense float64.

    Args:
        integrator: registry name of an explicit integrator (dopri5: a fixed step of its 5th-order solution).
        dt: the step [s], > 0.
        mass: the coordinates' masses [kg], shape [n], each > 0.
        stiffness: K [N/m], shape [n, n].
        damping: D [N·s/m], shape [n, n].

    Returns:
        R, shape [2n, 2n], float64: (x₁, v₁) = R (x₀, v₀). ρ(R) > 1 means some mode grows.
    """
    dt = checks.positive("dt", dt)
    mass = np.asarray(mass, dtype=np.float64)
    K, D = np.asarray(stiffness, dtype=np.float64), np.asarray(damping, dtype=np.float64)
    n = len(mass)
    if K.shape != (n, n) or D.shape != (n, n) or not (mass > 0.0).all():
        raise ConfigError(f"step_matrix needs masses > 0 of shape [n] and K, D of shape [n, n]; got "
                          f"{mass.shape}, {K.shape}, {D.shape}")
    inverse = dt / mass[:, None]
    eye, zero = np.eye(n), np.zeros((n, n))
    algebra = _Algebra(np.hstack([eye, zero]), np.hstack([zero, eye]),
                       lambda x, v: -inverse * (K @ x + D @ v), lambda v: dt * v, float)
    update = _explicit_update(integrator, algebra)
    if update is None:
        raise ConfigError(f"step_matrix covers explicit integrators only, not {integrator!r}")
    return np.vstack(update)


def stable_omega_h(integrator: str, zeta: float) -> float:
    """The largest ωh [-] such that ρ(R) ≤ 1 for every step up to it, for damping ratio ``zeta`` ≥ 0.

    0 when the integrator is unstable for every h > 0 (explicit Euler and midpoint at ζ = 0), ∞ when it
    is stable for every h (implicit Euler). Exact up to the final bisection (~1e-12 relative).
    """
    zeta = checks.non_negative("zeta", zeta)
    return _stable_scale(integrator, 1.0, 2.0 * zeta)


def stable_step(integrator: str, omega: float, zeta: float) -> float:
    """The largest stable step [s] of ``integrator`` on a spring of angular frequency ``omega`` [rad/s] > 0
    and damping ratio ``zeta`` ≥ 0: :func:`stable_omega_h` / ω (0: unstable for every h; ∞: never unstable)."""
    omega = checks.positive("omega", omega)
    return stable_omega_h(integrator, zeta) / omega


def network_stable_step(integrator: str, omega_max: float, *, rayleigh=0.0, drag_rate=0.0) -> float:
    """The largest stable step [s] of ``integrator`` on a spring network whose modes span (0, ω_max].

    A mode of angular frequency ω has the damping rate 2ζω = r ω² + γ (r: a kd/k ratio, γ: a drag c/m).
    The limit is the smallest stable step over ω = 0 (drag alone) and a sweep of ``SWEEP_DECADES`` decades
    below ω_max to ω_max, refined around its minimum, evaluated at the smallest and the largest r and γ
    given (see the module docstring).

    Args:
        integrator: registry name.
        omega_max: the network's highest angular frequency [rad/s], ≥ 0.
        rayleigh: kd/k ratios [s]: a number or an array (its extremes are used), each ≥ 0.
        drag_rate: c/m rates [1/s]: a number or an array (its extremes are used), each ≥ 0.

    Returns:
        The step [s]; 0 when some mode is unstable for every step, ∞ when none limits it.
    """
    omega_max = checks.non_negative("omega_max", omega_max)
    ratios, rates = _extremes("rayleigh", rayleigh), _extremes("drag_rate", drag_rate)
    count = SWEEP_DECADES * SWEEP_PER_DECADE + 1

    def limit(omega: float) -> float:
        steps = [math.inf]
        for r in ratios:
            for gamma in rates:
                rate = r * omega * omega + gamma
                if omega + rate > 0.0:
                    steps.append(_stable_scale(integrator, omega, rate))
        return min(steps)

    best = limit(0.0)
    if omega_max > 0.0:
        omegas = omega_max * np.geomspace(10.0**-SWEEP_DECADES, 1.0, count)
        steps = np.array([limit(float(w)) for w in omegas])
        k = int(np.argmin(steps))
        # The step varies smoothly with ω: a finer sweep between the neighbours of the coarse minimum.
        fine = np.geomspace(omegas[max(k - 1, 0)], omegas[min(k + 1, count - 1)], 2 * SWEEP_PER_DECADE + 1)
        best = min(best, float(steps[k]), *(limit(float(w)) for w in fine))
    return best


# -- ω_max of a model ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OmegaMaxEstimate:
    """The highest angular frequency of a model's springs by power iteration on M⁻¹K, per world.

    Attributes:
        world_omega_max: √θ [rad/s] of each world, θ its final Rayleigh quotient (θ ≤ λ_max(M⁻¹K)),
            float64, shape [world_count].
        world_iterations: power iterations each world ran, int, shape [world_count].
        world_residual: ‖M⁻¹Kx - θx‖_M / (θ‖x‖_M) of each world's final iterate [-], shape [world_count].
        world_converged: whether each world's residual reached the tolerance within the iteration budget,
            bool, shape [world_count].
        world_gershgorin: the Gershgorin upper bound on each world's ω_max [rad/s], shape [world_count]
            (:func:`world_gershgorin_omega_max`).
        world_mode: each world's final iterate, an approximate top mode shape [-], float64, shape
            [world_count, particle_count, 3], unit mass-norm, zero on pinned particles (zero everywhere in a
            world without stiffness).

    The scalar properties summarise all worlds: ``omega_max`` and ``mode`` are those of the stiffest world
    (``world``), ``iterations``, ``residual`` and ``gershgorin`` the largest over the worlds, ``converged``
    whether every world converged. For a single world they are its values.
    """

    world_omega_max: np.ndarray
    world_iterations: np.ndarray
    world_residual: np.ndarray
    world_converged: np.ndarray
    world_gershgorin: np.ndarray
    world_mode: np.ndarray

    @property
    def world(self) -> int:
        """The stiffest world (largest ω_max; the first of equals)."""
        return int(np.argmax(self.world_omega_max))

    @property
    def omega_max(self) -> float:
        """The largest ω_max over the worlds [rad/s]."""
        return float(self.world_omega_max[self.world])

    @property
    def iterations(self) -> int:
        """The most power iterations a world ran."""
        return int(self.world_iterations.max())

    @property
    def residual(self) -> float:
        """The largest final relative residual over the worlds [-]."""
        return float(self.world_residual.max())

    @property
    def converged(self) -> bool:
        """Whether every world converged."""
        return bool(self.world_converged.all())

    @property
    def gershgorin(self) -> float:
        """The largest Gershgorin bound over the worlds [rad/s]."""
        return float(self.world_gershgorin.max())

    @property
    def mode(self) -> np.ndarray:
        """The stiffest world's mode shape, shape [particle_count, 3]."""
        return self.world_mode[self.world]


def free_particles(model: Model) -> np.ndarray:
    """Which particles of each world move (not kinematic), bool, shape [world_count, particle_count] (reads
    the device once)."""
    flags = model.particle_flags.numpy().reshape(model.world_count, model.particle_count)
    return (flags & PARTICLE_KINEMATIC) == 0


def world_dynamic_inv_mass(model: Model) -> np.ndarray:
    """The inverse masses the dynamics sees in each world [1/kg], float64, shape [world_count,
    particle_count]: 1/m, and 0 for kinematic particles (reads the device)."""
    return np.where(free_particles(model), model.world_values("particle_inv_mass"), 0.0)


def _biphasic_ratio(model: Model) -> np.ndarray:
    """Each world's largest biphasic stiffness ratio [-], shape [world_count]: its live value and the top of
    its track; 1 without biphasic springs."""
    ratio = np.ones(model.world_count)
    if model.spring_law.biphasic:  # the stiffest the ratio gets, its track included
        ratio = np.maximum(ratio, model.world_values("biphasic_ratio")[:, 0])
        for w in range(model.world_count):
            track = model.track("biphasic_ratio", world=w)
            if track is not None:
                ratio[w] = max(ratio[w], float(track.values.max()))
    return ratio


def _stiffness_values(model: Model, stiffness) -> np.ndarray:
    """The spring stiffness [N/m] the analysis uses, float64, shape [1 or world_count, spring_count]: an
    override of shape [spring_count] (every world) or [world_count, spring_count], or the model's own — for
    biphasic springs their stiffer branch, ratio × ke, which bounds the step once a spring stretches past
    its knee."""
    worlds, count = model.world_count, model.spring_count
    if stiffness is None:
        values = model.spring_stiffness.numpy().astype(np.float64)
        ratio = _biphasic_ratio(model)
        if (ratio != 1.0).any():
            values = values * (ratio[:, None] if (ratio != ratio[0]).any() else ratio[0])
        return values
    values = stiffness.numpy() if isinstance(stiffness, wp.array) else np.asarray(stiffness)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[None]
    if values.shape not in ((1, count), (worlds, count)):
        shapes = f"({count},)" + (f" or ({worlds}, {count})" if worlds > 1 else "")
        raise ConfigError(f"stiffness must have shape {shapes}, got {np.shape(stiffness)}")
    if not (np.isfinite(values).all() and (values >= 0.0).all()):
        raise ConfigError("stiffness must be finite and >= 0")
    return values


def _stiffness_array(model: Model, values: np.ndarray) -> wp.array:
    """``values`` (from :func:`_stiffness_values`) on the model's device in its precision."""
    dtype = np.float64 if model.scalar is wp.float64 else np.float32
    return wp.array(np.ascontiguousarray(values, dtype=dtype), dtype=model.scalar, device=model.device)


def _gershgorin(model: Model, stiffness: np.ndarray, free: np.ndarray, positions=None) -> np.ndarray:
    """Each world's Gershgorin bound [rad/s], shape [world_count], for spring stiffness rows ``stiffness`` and
    free particles ``free`` [world_count, particle_count]: every family's row bounds, summed. The springs'
    rows take each law's tangent at ``positions`` (default the model's initial ones; ``SpringFamily.
    tangent_factor``): a square spring counts as 2 ke |Δ| at that stretch, a tension/compression spring with
    the stiffness of the branch it is on."""
    rows = np.zeros((model.world_count, model.particle_count))
    overrides = {"springs": stiffness}
    for family in model.families:
        if isinstance(family, SpringFamily):
            rows += family.gershgorin_rows(model, free, stiffness, positions=positions)
            continue
        rows += family.gershgorin_rows(model, free, overrides.get(family.name))
    ratio = np.where(free, rows / model.world_values("particle_mass"), 0.0)
    return np.sqrt(ratio.max(axis=1)) if model.particle_count else np.zeros(model.world_count)


def world_gershgorin_omega_max(model: Model, *, stiffness=None) -> np.ndarray:
    """Upper bound [rad/s] on each world's ω_max from Gershgorin's theorem for 3 × 3 blocks (host NumPy),
    float64, shape [world_count].

    Row i of M⁻¹K holds the diagonal block Σₛ Kₛ / mᵢ and one block Kₛ / mᵢ per spring to a free particle;
    each clamped spring block has spectral norm kₛ, so λ_max ≤ maxᵢ (Σₛ kₛ + Σ_{s to free j} kₛ) / mᵢ over
    free particles, with each world's stiffness and masses. (2 Σₛ kₛ / mᵢ, the bound usually quoted, is
    this with every neighbour free.) Other element families add their own row bounds
    (``ElementFamily.gershgorin_rows``). 0 in a world without stiffness or free particles.

    Args:
        model: the model.
        stiffness: spring stiffness [N/m] to use instead of the model's, shape [spring_count] or
            [world_count, spring_count].
    """
    return _gershgorin(model, _stiffness_values(model, stiffness), free_particles(model))


def gershgorin_omega_max(model: Model, *, stiffness=None) -> float:
    """The largest of :func:`world_gershgorin_omega_max` over the worlds [rad/s] (for one world: its bound)."""
    return float(world_gershgorin_omega_max(model, stiffness=stiffness).max())


def estimate_omega_max(
    model: Model,
    *,
    state: State | None = None,
    stiffness=None,
    max_iterations: int = 1000,
    tolerance: float = 1.0e-3,
    seed: int = 0,
) -> OmegaMaxEstimate:
    """ω_max = √λ_max(M⁻¹K) of each world's springs by power iteration, all worlds in the same launches on
    the model's device.

    K is assembled matrix-free from the clamped spring stiffness matrices at ``state``'s positions (default
    the model's initial ones), with each world's stiffness and masses; pinned particles are filtered out.
    Each world stops when its relative residual ‖M⁻¹Kx - θx‖_M / (θ‖x‖_M) ≤ ``tolerance`` or after
    ``max_iterations``; its Rayleigh quotient θ then approximates λ_max from below, its relative error
    typically well under the residual (a residual of 1e-3 leaves ω_max within ~2e-4 on cloths). Every world
    starts from the same random vector (restricted to its free particles), so a world's result does not
    depend on the others: it is the one a model of that world alone gives.

    Args:
        model: the model.
        state: positions to linearise about; default the model's initial positions.
        stiffness: spring stiffness [N/m], shape [spring_count] (every world) or [world_count,
            spring_count]; default the model's, with biphasic springs at their stiffer branch (ratio × ke).
        max_iterations: iteration budget per world (≥ 1).
        tolerance: relative residual at which a world stops, in (0, 1).
        seed: seed of the random start vector.
    """
    _check_iteration(max_iterations, tolerance)
    return _power_iteration(model, _stiffness_values(model, stiffness), state, max_iterations, tolerance, seed)


def _check_iteration(max_iterations: int, tolerance: float) -> None:
    checks.count("max_iterations", max_iterations, minimum=1)
    if checks.positive("tolerance", tolerance) >= 1.0:
        raise ConfigError(f"tolerance must be a number in (0, 1), got {tolerance!r}")


class PowerIteration:
    """The device buffers and launches of power iteration on M⁻¹K for every world of a model at once
    (``kernels/stability.py``): :func:`estimate_omega_max` runs it to convergence in a ``capture_while``
    loop, the run-time :class:`~warpspring.analysis.watch.StabilityWatch` a few warm-started iterations at a
    time. ``stiffness`` as in :func:`estimate_omega_max` (values, shape [spring_count] or [world_count,
    spring_count]); ``start``: the initial iterate, shape [world_count, particle_count, 3]."""

    def __init__(self, model: Model, stiffness: np.ndarray, start: np.ndarray):
        worlds, n, device = model.world_count, model.particle_count, model.device
        self.model = model
        tiled = device.is_cuda
        self.lanes = reduce_lanes(n, model.block_dim, tiled)
        self.grid = reduce_launch_dim(worlds, n, self.lanes)
        self.kernels = power_iteration_kernels(model.scalar, model.family_specs(linear=True), tiled)
        self.sum_partials = sum_partials_kernel(tiled)
        self.element_arrays = model.element_arrays(linear=True, stiffness={"springs": _stiffness_array(model, stiffness)})
        self.x = wp.array(np.asarray(start).reshape(-1, 3), dtype=model.vec3, device=device)
        self.y = wp.zeros(worlds * n, dtype=model.vec3, device=device)
        self.partials = wp.zeros((worlds, self.grid[1], PI_PARTIALS), dtype=wp.float64, device=device)
        self.scalars = wp.zeros((worlds, PI_SCALARS), dtype=wp.float64, device=device)
        self.iteration = wp.zeros(worlds, dtype=wp.int32, device=device)
        self.active = wp.zeros(worlds, dtype=wp.int32, device=device)
        self.keep_going = wp.zeros(1, dtype=wp.int32, device=device)
        self.tolerance, self.max_iterations = 1.0e-3, 1

    def restart(self, running: np.ndarray, *, max_iterations: int, tolerance: float) -> None:
        """Iterate the worlds where ``running`` (bool, [world_count]) from the current iterate, each until
        its residual reaches ``tolerance`` or for ``max_iterations`` more iterations."""
        self.tolerance, self.max_iterations = float(tolerance), int(max_iterations)
        self.iteration.zero_()
        self.active.assign(np.asarray(running, dtype=np.int32))
        self.keep_going.assign(np.array([int(np.count_nonzero(running))], dtype=np.int32))

    def iterate(self, particle_q: wp.array) -> None:
        """One iteration about the positions ``particle_q`` on the current stream (device launches only)."""
        model, device = self.model, self.model.device
        product, normalize, condition = self.kernels
        flat_launch(
            product, dim=self.grid, block_dim=self.lanes, device=device,
            inputs=[model.particle_count, model.particle_flags, model.particle_mass, self.element_arrays, model.inputs,
                    particle_q, self.active, self.x],
            outputs=[self.y, self.partials],
        )
        wp.launch(self.sum_partials, dim=(model.world_count, self.lanes), block_dim=self.lanes, device=device,
                  inputs=[PI_XKX, PI_PARTIALS, self.partials], outputs=[self.scalars])
        wp.launch(normalize, dim=model.particle_dim, block_dim=model.block_dim, device=device,
                  inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, self.active, self.y,
                          self.scalars], outputs=[self.x])
        wp.launch(condition, dim=model.world_count, device=device,
                  inputs=[wp.float64(self.tolerance), self.max_iterations],
                  outputs=[self.scalars, self.iteration, self.active, self.keep_going])


def _power_iteration(model: Model, stiffness: np.ndarray, state: State | None, max_iterations: int,
                     tolerance: float, seed: int) -> OmegaMaxEstimate:
    worlds, n = model.world_count, model.particle_count
    free = free_particles(model)
    bound = _gershgorin(model, stiffness, free, None if state is None else state.particle_q)
    start = np.random.default_rng(seed).normal(size=(n, 3))[None] * free[..., None]
    if not bound.any():
        return OmegaMaxEstimate(
            world_omega_max=np.zeros(worlds), world_iterations=np.zeros(worlds, dtype=np.int64),
            world_residual=np.zeros(worlds), world_converged=np.ones(worlds, dtype=bool), world_gershgorin=bound,
            world_mode=np.zeros((worlds, n, 3)),
        )
    iteration = PowerIteration(model, stiffness, start)
    # A world without stiffness or free particles has λ_max = 0: nothing to iterate.
    iteration.restart(bound > 0.0, max_iterations=max_iterations, tolerance=tolerance)
    q = model.particle_q if state is None else state.particle_q
    wp.capture_while(iteration.keep_going, lambda: iteration.iterate(q))
    values = iteration.scalars.numpy()
    residual = values[:, PI_RESIDUAL].copy()
    return OmegaMaxEstimate(
        world_omega_max=np.sqrt(np.maximum(values[:, PI_LAMBDA], 0.0)),
        world_iterations=iteration.iteration.numpy().astype(np.int64),
        world_residual=residual,
        world_converged=residual <= tolerance,
        world_gershgorin=bound,
        world_mode=iteration.x.numpy().astype(np.float64).reshape(worlds, n, 3),
    )


# -- under load ---------------------------------------------------------------------------------------------

#: Where between the start (0) and the static equilibrium (1) :func:`loaded_state` linearises by default.
OVERSHOOT = 1.0
#: Quasi-static relaxation: the implicit step [s] (a trust region: unsupported directions move g h² per step
#: at most), the most steps, and the convergence test (largest move per step / the model's extent; the
#: 20 × 20 cloth's ω_max agrees to 5e-6 with a 10× tighter test).
RELAX_STEP, RELAX_MAX_STEPS, RELAX_TOLERANCE = 0.2, 200, 1.0e-5


def has_loads(model: Model, control=None) -> bool:
    """Whether gravity acts in some world or the control carries an external force."""
    gravity = np.linalg.norm(model.world_values("gravity"), axis=1)
    return bool(gravity.any()) or (control is not None and control.particle_force is not None)


@dataclass(frozen=True)
class Equilibrium:
    """The static equilibrium :func:`static_equilibrium` found.

    Attributes:
        positions: particle positions [m], float64, shape [world_count · particle_count, 3].
        steps: relaxation steps taken.
        converged: whether the largest move of the last step fell below ``RELAX_TOLERANCE`` × the extent.
        residual: that move over the extent [-].
    """

    positions: np.ndarray
    steps: int
    converged: bool
    residual: float


def static_equilibrium(model: Model, *, control=None, step: float = RELAX_STEP, max_steps: int = RELAX_MAX_STEPS,
                       tolerance: float = RELAX_TOLERANCE) -> Equilibrium:
    """The positions where the loads (gravity, the control's external force) balance the elements, the
    pins held at their t = 0 place: implicit Euler steps of ``step`` from rest, the velocities zeroed and
    the clock and pins put back after each, until the largest move per step is below ``tolerance`` × the
    model's extent (or ``max_steps``). Each step solves (M + h²K) Δx = h² f, a Newton step on the
    potential regularised by the mass (K the elements' stiffness, made positive semi-definite)."""
    from ..core.integrators import ImplicitEuler

    checks.positive("step", step)
    checks.count("max_steps", max_steps, minimum=1)
    integrator = ImplicitEuler(model)
    state, scratch = model.state(), model.state()
    start = state.particle_q.numpy().astype(np.float64)
    pinned = ~free_particles(model).reshape(-1)
    extent = max(float(np.ptp(start, axis=0).max()) if len(start) else 0.0, 1.0e-6)
    previous, residual, steps = start, math.inf, 0
    while steps < max_steps and residual > tolerance:
        state.particle_qd.zero_()
        state.time.zero_()
        integrator.step(state, scratch, control, step)
        q = scratch.particle_q.numpy().astype(np.float64)
        q[pinned] = start[pinned]
        if not np.isfinite(q).all():
            break
        residual = float(np.abs(q - previous).max()) / extent
        state.particle_q.assign(q.astype(wp.dtype_to_numpy(model.scalar)))
        previous, steps = q, steps + 1
    return Equilibrium(positions=previous, steps=steps, converged=residual <= tolerance, residual=residual)


def loaded_state(model: Model, *, control=None, overshoot: float = OVERSHOOT) -> State:
    """A state at x₀ + ``overshoot`` (x_eq - x₀), x_eq the :func:`static_equilibrium` under the loads, at rest
    (default: the equilibrium itself), to linearise the advisor about."""
    start = model.state()
    equilibrium = static_equilibrium(model, control=control)
    q0 = start.particle_q.numpy().astype(np.float64)
    swing = q0 + overshoot * (equilibrium.positions - q0)
    start.particle_q.assign(swing.astype(wp.dtype_to_numpy(model.scalar)))
    return start


#: The dry run (:func:`transient_peak`): velocity Verlet at ``PROBE_FRACTION`` of the step the Gershgorin
#: bound proves stable (no state exceeds that bound, so the dry run is stable wherever it goes; on a linear
#: spring released from rest Verlet's turning points are exact at any stable step, where symplectic Euler's
#: overshoot by 1/√(1 - (ωh/2)²)), ω_max
#: re-estimated every ``PROBE_CHECK`` seconds of simulated time by ``PROBE_ITERATIONS`` power iterations
#: warm-started from the last (a world stops at ``PROBE_TOLERANCE``; 20 iterations leave the 20 × 20 cloth's
#: peak 4e-4 below 200 iterations'), captured once into a graph and replayed. It ends once twice the time of the last rise of some
#: world's peak (by more than ``PROBE_RISE``) has passed, not before ``PROBE_MIN_TIME`` and not after its
#: horizon (``PROBE_HORIZON`` by default; ``warpspring run`` passes the run's duration).
PROBE_FRACTION = 0.5
PROBE_CHECK = 1.0 / 240.0
PROBE_ITERATIONS, PROBE_TOLERANCE = 20, 1.0e-4
PROBE_RISE = 1.0e-3
PROBE_MIN_TIME, PROBE_HORIZON = 0.25, 2.0


def in_motion(model: Model, control=None) -> bool:
    """Whether the model leaves its initial state by itself: loads act (:func:`has_loads`), a keyframe track
    drives pins or inputs, or a particle starts moving."""
    return (has_loads(model, control) or bool(model.track_table.tracks)
            or bool(np.any(model.particle_qd.numpy())))


@dataclass(frozen=True)
class TransientPeak:
    """The highest ω_max each world reached in the dry run of :func:`transient_peak`.

    Attributes:
        world_omega_max: each world's peak ω_max [rad/s], float64, shape [world_count] (at least the
            ``start`` estimate's).
        world_peak_time: when each world reached it [s], float64, shape [world_count] (0: at the start).
        world_mode: each world's power-iteration vector at its peak, float64, shape [world_count,
            particle_count, 3].
        positions: each world's positions at its peak [m], float64, shape [world_count · particle_count, 3].
        duration: simulated time of the dry run [s].
        step: its step [s].
        finite: False when the dry run's state turned non-finite (it stopped there).
        world_lowest_ratio: with ``lowest_ratio``, each world's lowest top-mode damping ratio xᵀDx / xᵀKx [s]
            over the start and the dry run's re-estimates (:func:`top_mode_ratios`), shape [world_count];
            else ``None``.
    """

    world_omega_max: np.ndarray
    world_peak_time: np.ndarray
    world_mode: np.ndarray
    positions: np.ndarray
    duration: float
    step: float
    finite: bool
    world_lowest_ratio: np.ndarray | None = None


def _keeps_plasticity(function):
    """Run ``function(model, ...)`` and put the model's plastic springs back as they were: its static solves and
    dry runs step the model, and plastic springs keep their yield in the model (a plastic bar that sagged in
    the dry run would start the real run collapsed)."""

    @functools.wraps(function)
    def wrapper(model, *args, **kwargs):
        if not model.spring_material_law.plastic:
            return function(model, *args, **kwargs)
        saved = wp.clone(model.spring_plastic_rest_length), wp.clone(model.spring_plastic_strain)
        try:
            return function(model, *args, **kwargs)
        finally:
            wp.copy(model.spring_plastic_rest_length, saved[0])
            wp.copy(model.spring_plastic_strain, saved[1])

    return wrapper


@_keeps_plasticity
def transient_peak(model: Model, *, control=None, stiffness=None, horizon: float = PROBE_HORIZON,
                   start: OmegaMaxEstimate | None = None, start_positions: np.ndarray | None = None,
                   lowest_ratio: bool = False) -> TransientPeak:
    """The highest ω_max each world reaches on its way from the initial state: a dry run of the scene as it
    will run (loads, control, pins and their tracks, colliders), by velocity Verlet at a step that is stable
    at any state, with ω_max re-estimated along it (constants ``PROBE_*``).

    A cloth released unstretched swings past its static stretch before it settles: measured on the 20 × 20
    hanging cloth at 13 kN/m, ω_max is 719 rad/s at the start, 924 at the static equilibrium and 989 at
    t = 0.45 s, and a step that keeps the equilibrium stable (ωh = 1.92 for symplectic Euler) blows up there.

    Args:
        model: the model.
        control: the run's Control (its external force acts in the dry run).
        stiffness: as in :func:`advise` (the power iterations' spring stiffness; the dry run uses the model's).
        horizon: the longest dry run [s] (> 0).
        start: an estimate to start from and to beat (e.g. at the static equilibrium), with
            ``start_positions`` [m], float64, shape [world_count · particle_count, 3], where it was made;
            default: the initial state's.
        lowest_ratio: also keep each world's lowest top-mode damping ratio along the way (explicit Euler's
            limit: the stretch that makes the top mode stiffer across its springs than along them, where their
            dampers act, need not come with the highest ω_max); one host read of the state per re-estimate.
    """
    from ..core.simulator import Simulator
    from ..core.integrators import VelocityVerlet

    horizon = checks.positive("horizon", horizon)
    k = _stiffness_values(model, stiffness)
    worlds, n = model.world_count, model.particle_count
    if start is None:
        start = _power_iteration(model, k, None, 1000, PROBE_TOLERANCE, 0)
        start_positions = model.particle_q.numpy().astype(np.float64)
    peak = start.world_omega_max.copy()
    mode = start.world_mode.copy()
    positions = np.array(start_positions, dtype=np.float64).reshape(worlds, n, 3)
    peak_time = np.zeros(worlds)
    ratio_arrays = _ratio_arrays(model) if lowest_ratio else None  # read once, not at every re-estimate

    def ratios(x: np.ndarray, q: np.ndarray) -> np.ndarray:
        return _top_mode_ratios(_tangent_stiffness(model, k, q.reshape(-1, 3)), ratio_arrays, list(x), q)

    lowest = ratios(mode, positions) if lowest_ratio else None
    bound = _gershgorin(model, k, free_particles(model))
    safe = _world_limits("velocity_verlet", bound, _damping_ranges(model, k, [None] * worlds, model.particle_q))
    safe = float(safe[bound > 0.0].min()) if (bound > 0.0).any() else math.inf
    if not math.isfinite(safe) or safe <= 0.0:
        return TransientPeak(peak, peak_time, mode, positions.reshape(-1, 3), 0.0, 0.0, True, lowest)
    substeps = max(1, math.ceil(PROBE_CHECK / (PROBE_FRACTION * safe)))
    sim = Simulator(model, integrator=VelocityVerlet(model), fps=1.0 / PROBE_CHECK, substeps=substeps,
                    control=control, guard=None)
    iteration = PowerIteration(model, k, mode)
    iteration.tolerance, iteration.max_iterations = PROBE_TOLERANCE, PROBE_ITERATIONS
    running = wp.array((bound > 0.0).astype(np.int32), dtype=wp.int32, device=model.device)
    snapshot = wp.clone(sim.state.particle_q)

    def recheck():
        iteration.iteration.zero_()
        wp.copy(iteration.active, running)
        for _ in range(PROBE_ITERATIONS):
            iteration.iterate(snapshot)

    recheck()  # uncaptured: loads the modules (a capture must not)
    with wp.ScopedCapture(device=model.device, force_module_load=False) as capture:
        recheck()
    rise, finite, level = 0.0, True, None  # level: the dry run's own running peak (not the start's)
    while sim.time < horizon and (sim.time < PROBE_MIN_TIME or sim.time < 2.0 * rise):
        sim.step_frame()
        wp.copy(snapshot, sim.state.particle_q)
        wp.capture_launch(capture.graph)
        omega = np.sqrt(np.maximum(iteration.scalars.numpy()[:, PI_LAMBDA], 0.0))
        if not np.isfinite(omega).all():
            finite = False
            break
        if level is None or (omega > level * (1.0 + PROBE_RISE)).any():  # still rising somewhere
            rise = sim.time
            level = omega if level is None else np.maximum(level, omega)
        higher = omega > peak
        if higher.any() or lowest_ratio:
            q = sim.state.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
            if not np.isfinite(q[higher]).all():
                finite = False
                break
            x = iteration.x.numpy().astype(np.float64).reshape(worlds, n, 3)
            positions[higher], mode[higher], peak_time[higher], peak[higher] = q[higher], x[higher], sim.time, omega[higher]
            if lowest_ratio:
                lowest = np.fmin(lowest, ratios(x, q))
    return TransientPeak(peak, peak_time, mode, positions.reshape(-1, 3), sim.time, sim.dt, finite, lowest)


def pair_block_matrix(n: int, i: np.ndarray, j: np.ndarray, blocks: np.ndarray):
    """Σₑ of a two-particle element's 3 × 3 ``blocks`` [e, 3, 3] placed +B on (i, i) and (j, j) and −B on
    (i, j) and (j, i): the stiffness or damping of springs (and their like) over the 3 ``n`` coordinates of
    n particles, a ``scipy.sparse.csr_matrix`` [3n, 3n] (duplicate entries summed)."""
    import scipy.sparse

    rows, cols, values = [], [], []
    for a, b, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.append((3 * a[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2).ravel())
        cols.append((3 * b[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1).ravel())
        values.append(sign * blocks.ravel())
    return scipy.sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                                   shape=(3 * n, 3 * n))


def transverse_omega_max(model: Model, positions, world: int = 0, *, stiffness=None) -> float:
    """The highest frequency [rad/s] of ``world``'s springs' *transverse* stiffness at ``positions`` [m]
    (shape [world_count · particle_count, 3]): λ_max of M⁻¹K_t, K_t = Σₛ kₛ (1 - L/l)⁺ (I - d̂d̂ᵀ) across
    each stretched spring, which its axial damper does not damp; pinned particles held. Sparse Lanczos
    (``scipy.sparse.linalg.eigsh``) on the host; 0 where no spring is stretched."""
    n = model.particle_count
    free = free_particles(model)[world]
    q = np.asarray(positions if isinstance(positions, np.ndarray) else positions.numpy(), dtype=np.float64)
    q = q.reshape(model.world_count, n, 3)[world]
    i, j = model.spring_indices.numpy().reshape(-1, 2).T
    k = np.broadcast_to(_stiffness_values(model, stiffness), (model.world_count, model.spring_count))[world]
    d = q[j] - q[i]
    length = np.linalg.norm(d, axis=1)
    rest = model.spring_rest_lengths()[world]  # plastic springs: where they are now (negative: broken)
    stretched = (length > rest) & (rest >= 0.0)
    if not stretched.any() or not free.any():
        return 0.0
    i, j, d, length = i[stretched], j[stretched], d[stretched], length[stretched]
    # T/l: k (1 - L/l) for a linear spring, k Δ²/l = (k |Δ|)(1 - L/l) for a square one.
    tension_scale = np.where(spring_law_codes(model)[stretched] == SPRING_LAWS["square"],
                             length - rest[stretched], 1.0)
    across = k[stretched] * tension_scale * (1.0 - rest[stretched] / length)
    unit = d / length[:, None]
    blocks = across[:, None, None] * (np.eye(3)[None] - unit[:, :, None] * unit[:, None, :])  # [s, 3, 3]
    keep = np.repeat(free, 3)
    mass = np.repeat(model.world_values("particle_mass")[world], 3)[keep]
    top, _ = top_eigenpair(pair_block_matrix(n, i, j, blocks)[keep][:, keep], mass, tol=1e-6)
    return math.sqrt(max(top, 0.0))


def top_eigenpair(stiffness, mass: np.ndarray, *, start: np.ndarray | None = None, tol: float = 0.0) -> tuple:
    """The largest eigenvalue λ [1/s²] of K x = λ M x and its M-orthonormal eigenvector x (xᵀ M x = 1) [m/√kg],
    shape [n]: ``stiffness`` K a symmetric ``scipy.sparse`` matrix [n, n] [N/m], ``mass`` the diagonal of M
    [kg], shape [n]. Lanczos on M^-½ K M^-½ (``scipy.sparse.linalg.eigsh``, relative accuracy ``tol``; 0:
    machine precision), started from ``start`` (an earlier x, say) where given; dense below 4 coordinates."""
    import scipy.sparse
    import scipy.sparse.linalg

    scale = 1.0 / np.sqrt(np.asarray(mass, dtype=np.float64))
    reduced = scipy.sparse.diags(scale) @ scipy.sparse.csr_matrix(stiffness) @ scipy.sparse.diags(scale)
    if reduced.shape[0] <= 3:
        values, vectors = np.linalg.eigh(reduced.toarray())
        top, y = values[-1], vectors[:, -1]
    else:
        v0 = None if start is None else np.asarray(start, dtype=np.float64) / scale
        values, vectors = scipy.sparse.linalg.eigsh(reduced, k=1, which="LA", tol=tol, v0=v0)
        top, y = values[0], vectors[:, 0]
    return float(top), scale * y


# -- the advisor --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Advice:
    """Whether a step is stable for a model and an integrator, and what to change if not.

    With several worlds every world is analysed with its own parameters, and the verdict is that of the
    binding world (the smallest stable step; among equals, the stiffest).

    Attributes:
        integrator: the integrator's registry name.
        dt: the step asked about [s].
        omega_max: the binding world's highest angular frequency used [rad/s].
        omega_source: how ``omega_max`` was obtained: "power iteration" or "Gershgorin bound" (an upper
            bound: the step limit is then conservative).
        dt_stable: the largest stable step [s] of the binding world; ∞ when unconditionally stable, 0 when
            unstable at every step. For an adaptive integrator: the stability limit of its internal step.
        stable: whether ``dt`` is stable in every world (always true for adaptive integrators, which shrink
            their step).
        adaptive: whether the integrator chooses its own internal step.
        fps: frame rate [1/s] the substep count refers to.
        substeps: the fewest steps per 1/fps frame that keep the step ≤ ``dt_stable`` (for adaptive
            integrators: the fewest internal steps per ``dt``); ``None`` when no step is stable.
        message: one line for the user, with a suggestion when ``dt`` is unstable; names the binding world
            when the model has several.
        world: the binding world.
        world_omega_max: each world's ω_max [rad/s], float64, shape [world_count].
        world_dt_stable: each world's largest stable step [s], float64, shape [world_count].
        dry_run: simulated time of the dry run that found the peak ω_max [s] (0: none was run).
        transverse_growth: how much an integrator that needs damping (explicit Euler, midpoint) grows the
            undamped transverse modes of the binding world's stretched springs over ``horizon`` at ``dt``
            (amplitude factor, by their highest frequency and the world's least drag); 1
            where none grows.
        peak_time: when the binding world's ω_max peaked in the dry run [s] (0: at the state linearised
            about, not later).
        top_growth: the amplitude factor of the binding world's top mode (ω_max, its least damping) over
            ``horizon`` at ``dt``, ρ^(horizon/dt): above 1 exactly when ``dt`` is past the limit, and how slowly
            it grows there (explicit Euler and midpoint just past theirs: barely); 1 for adaptive integrators.
    """

    integrator: str
    dt: float
    omega_max: float
    omega_source: str
    dt_stable: float
    stable: bool
    adaptive: bool
    fps: float
    substeps: int | None
    message: str
    world: int = 0
    world_omega_max: np.ndarray = field(default_factory=lambda: np.zeros(1), compare=False)
    world_dt_stable: np.ndarray = field(default_factory=lambda: np.zeros(1), compare=False)
    dry_run: float = 0.0
    peak_time: float = 0.0
    transverse_growth: float = 1.0
    top_growth: float = 1.0


def _damping_ranges(model: Model, stiffness: np.ndarray, modes: list, positions: wp.array | np.ndarray, *,
                    lowest_top: np.ndarray | None = None) -> list:
    """Each world's (kd/k values [s], c/m values [1/s]) for :func:`network_stable_step`.

    kd/k: the springs' smallest ratio (the least damped modes, which explicit Euler and midpoint cannot
    integrate stably without damping) and the top mode's own ratio xᵀDx / xᵀKx on the world's
    power-iteration eigenvector x (D = Σₛ kdₛ d̂d̂ᵀ): a mode near ω_max strains the stiff springs, so the
    damping of soft, heavily damped families does not reach it. Without an eigenvector (``modes[w]`` is
    ``None``: Gershgorin) the largest ratio stands in for the top mode's, which is conservative for
    symplectic Euler but loose when the stiffest springs are the least damped. c/m: its extremes over the
    world's free particles (drag limits the slowest motions, each particle's velocity decaying at its own
    c/m), the largest with the damping the element families put on a particle's own motion (wind, handles:
    ``ElementFamily.damping_rates``), the smallest without (the wind damps only smooth motions). Stiffness,
    damping, masses and drag are each world's own.
    """
    worlds, n = model.world_count, model.particle_count
    free = free_particles(model)
    k_all = _tangent_stiffness(model, stiffness, positions)
    kd_all = model.world_values("spring_damping")
    mass_all = model.world_values("particle_mass")
    drag = model.world_values("drag")[:, 0]
    ends = model.spring_indices.numpy().reshape(-1, 2)
    q_all = np.asarray(positions if isinstance(positions, np.ndarray) else positions.numpy(), dtype=np.float64)
    q_all = q_all.reshape(worlds, n, 3)
    extra = sum((family.damping_rates(model, q_all) for family in model.extra_families),
                np.zeros((worlds, n)))
    rest_all = model.spring_rest_length.numpy().astype(np.float64)
    tops = _top_mode_ratios(k_all, (free, kd_all, ends, rest_all), modes, q_all)
    if lowest_top is not None:
        tops = np.fmin(tops, lowest_top)
    ranges = []
    for w in range(worlds):
        mass = mass_all[w][free[w]]
        rates = (np.concatenate([drag[w] / mass, (drag[w] + extra[w][free[w]]) / mass]) if len(mass)
                 else np.zeros(1))
        k, kd = k_all[w], kd_all[w]
        acting = (k > 0.0) & free[w][ends].any(axis=1)
        if not acting.any():
            ranges.append((np.zeros(1), rates))
            continue
        ratios = kd[acting] / k[acting]
        if modes[w] is None:
            ranges.append((ratios, rates))
            continue
        top = tops[w] if np.isfinite(tops[w]) else float(ratios.max())
        ranges.append((np.array([ratios.min(), top]), rates))
    return ranges


def _tangent_stiffness(model: Model, stiffness: np.ndarray, positions) -> np.ndarray:
    """Each world's springs' tangent stiffness [N/m] at ``positions``, shape [world_count, spring_count]."""
    springs = next((f for f in model.families if isinstance(f, SpringFamily)), None)
    k_all = np.broadcast_to(stiffness, (model.world_count, model.spring_count))
    if springs is not None:  # each law's tangent at the positions: kd/k is a ratio of tangents
        k_all = k_all * springs.tangent_factor(model, positions)
    return k_all


def top_mode_ratios(model: Model, stiffness, modes: list, positions) -> np.ndarray:
    """Each world's top-mode damping ratio xᵀDx / xᵀKx [s] on its power-iteration vector x (``modes[w]``,
    shape [particle_count, 3]) at ``positions`` [m], shape [world_count, particle_count, 3]: K the springs'
    tangent stiffness (transverse part clamped, as in the kernels), D their axial dampers. Explicit Euler's
    step limit for that mode is this ratio itself (h* = 2ζ/ω). NaN where ``modes[w]`` is ``None`` or no
    stretched direction carries stiffness. Shape [world_count]."""
    q_all = np.asarray(positions, dtype=np.float64).reshape(model.world_count, model.particle_count, 3)
    k_all = _tangent_stiffness(model, _stiffness_values(model, stiffness), q_all.reshape(-1, 3))
    return _top_mode_ratios(k_all, _ratio_arrays(model), modes, q_all)


def _ratio_arrays(model: Model) -> tuple:
    """What :func:`top_mode_ratios` reads of a model besides the stiffness and the state: (free particles
    [world_count, particle_count], kd [world_count, spring_count], spring ends [spring_count, 2], rest lengths
    [spring_count]), from the device."""
    return (free_particles(model), model.world_values("spring_damping"),
            model.spring_indices.numpy().reshape(-1, 2), model.spring_rest_length.numpy().astype(np.float64))


def _top_mode_ratios(k_all: np.ndarray, arrays: tuple, modes: list, q_all: np.ndarray) -> np.ndarray:
    """:func:`top_mode_ratios` from the tangent stiffness ``k_all`` [world_count, spring_count] and
    :func:`_ratio_arrays`."""
    free, kd_all, ends, rest_all = arrays
    tops = np.full(len(q_all), np.nan)
    for w in range(len(q_all)):
        k, kd = k_all[w], kd_all[w]
        acting = (k > 0.0) & free[w][ends].any(axis=1)
        if modes[w] is None or not acting.any():
            continue
        q = q_all[w]
        mode = modes[w] * free[w][:, None]
        i, j = ends[acting].T
        d = q[j] - q[i]
        length = np.linalg.norm(d, axis=1)
        coincident = length == 0.0  # no direction: no stiffness, no damping (as in the kernels)
        safe = np.where(coincident, 1.0, length)
        delta = mode[i] - mode[j]
        axial2 = (np.einsum("sk,sk->s", d, delta) / safe) ** 2
        rest = rest_all[acting]
        transverse = np.where(coincident, 0.0, np.maximum(1.0 - rest / safe, 0.0))  # clamped, as in K
        xkx = float((k[acting] * (axial2 + transverse * (np.einsum("sk,sk->s", delta, delta) - axial2))).sum())
        if xkx > 0.0:
            tops[w] = float((kd[acting] * axial2).sum()) / xkx
    return tops


#: The transverse growth (:attr:`Advice.transverse_growth`) from which the advisor's message mentions it.
TRANSVERSE_NOTE = 1.01


def _transverse_growth(model: Model, integrator: str, dt: float, stiffness: np.ndarray, positions, rates: np.ndarray,
                       horizon: float, world: int) -> float:
    """ρ^(horizon/dt) of the undamped transverse modes of ``world`` (frequencies up to
    :func:`transverse_omega_max`, damped by the least drag ``rates``), for the integrators whose undamped modes grow (explicit Euler,
    midpoint); 1 for the others."""
    if _integrator_class(integrator).adaptive or spectral_radius(integrator, 1.0e-3, 0.0) <= 1.0:
        return 1.0
    omega = transverse_omega_max(model, positions, world, stiffness=stiffness)
    if omega <= 0.0:
        return 1.0
    drag = float(np.min(rates))
    rho = max(spectral_radius(integrator, w * dt, drag / (2.0 * w)) for w in omega * np.geomspace(1e-2, 1.0, 9))
    return _over_run(rho, horizon, dt) if rho > 1.0 else 1.0


def _over_run(rho: float, horizon: float, dt: float) -> float:
    """ρ^(horizon/dt): a growth factor ρ per step of ``dt`` [s] over ``horizon`` [s], capped at e^700."""
    return float(np.exp(min(math.log(rho) * horizon / dt, 700.0)))


def _top_growth(integrator: str, dt: float, omega: float, ranges: tuple, horizon: float) -> float:
    """ρ^(horizon/dt) of the top mode (angular frequency ``omega`` [rad/s]) at its least damping among the
    world's ``ranges`` (kd/k ratios, drag rates) (:func:`_over_run`)."""
    if omega <= 0.0:
        return 1.0
    ratios, rates = ranges
    zeta = (float(np.min(ratios)) * omega * omega + float(np.min(rates))) / (2.0 * omega)
    return _over_run(spectral_radius(integrator, omega * dt, zeta), horizon, dt)


def _world_limits(integrator: str, omegas: np.ndarray, ranges: list) -> np.ndarray:
    """:func:`network_stable_step` of each world [s], shape [world_count]; worlds with the same ω_max and
    damping extremes (e.g. identical worlds) are computed once."""
    cache: dict = {}
    limits = np.empty(len(omegas))
    for w, (omega, (ratios, rates)) in enumerate(zip(omegas, ranges)):
        key = (float(omega), _extremes("rayleigh", ratios), _extremes("drag_rate", rates))
        if key not in cache:
            cache[key] = network_stable_step(integrator, key[0], rayleigh=list(key[1]), drag_rate=list(key[2]))
        limits[w] = cache[key]
    return limits


@_keeps_plasticity
def advise(
    model: Model,
    integrator: str,
    dt: float,
    *,
    fps: float = 60.0,
    strict: bool = False,
    stiffness=None,
    state: State | None = None,
    control=None,
    loaded: bool = True,
    transient: bool = True,
    horizon: float = PROBE_HORIZON,
    omega_estimate: str = "power_iteration",
    max_iterations: int = 1000,
    tolerance: float = 1.0e-3,
) -> Advice:
    """Check ``dt`` against the springs' stability limit for ``integrator`` and say what to do.

    ω_max of every world comes from :func:`estimate_omega_max` (a world whose power iteration does not
    converge within ``max_iterations`` falls back to its Gershgorin bound) or, with
    ``omega_estimate="gershgorin"``, from :func:`world_gershgorin_omega_max` directly (cheaper,
    conservative). The modes' damping (:func:`network_stable_step`) spans the smallest kd/k of the world's
    springs and its top mode's own kd/k, xᵀDx / xᵀKx on the power-iteration eigenvector (with the
    Gershgorin bound: the largest kd/k), and the world's drag c/m. Each world gets its own stable step; the
    smallest binds, and the message names its world when the model has several. Contacts are not part of
    the analysis. The theory's exact arithmetic costs ~0.1 s of host time per distinct world (worlds with
    the same ω_max and damping share one evaluation).

    Args:
        model: the model.
        integrator: registry name of the integrator.
        dt: the step [s] to check, > 0.
        fps: frame rate [1/s] for the substep count.
        strict: raise a ConfigError carrying the message when ``dt`` is unstable.
        stiffness: spring stiffness [N/m], shape [spring_count] or [world_count, spring_count], also used
            for the springs' kd/k; default the model's, with biphasic springs at their stiffer branch
            (ratio × ke).
        state: positions to linearise about; default the model's initial positions, carried by the loads
            (below).
        control: the run's Control, whose external force is a load (default none).
        loaded: with no ``state`` given, judge the states the run reaches rather than the initial positions:
            with loads acting (gravity or the control's external force), linearise about
            :func:`loaded_state`, and with ``transient``, when the model moves by itself (:func:`in_motion`),
            take each world's peak ω_max over a dry run to ``horizon`` [s] (:func:`transient_peak`: the
            release transient of a loaded cloth swings past its static stretch; not for implicit and
            adaptive integrators, whose step ω_max does not limit). The Gershgorin bound needs
            no state: it bounds every spring block by its full stiffness, stretched or not.
        omega_estimate: "power_iteration" or "gershgorin".
        max_iterations, tolerance: of the power iteration.

    Raises:
        ConfigError: bad arguments, or (with ``strict``) an unstable step.
    """
    dt, fps = checks.positive("dt", dt), checks.positive("fps", fps)
    cls = _integrator_class(integrator)
    if omega_estimate not in OMEGA_ESTIMATES:
        raise ConfigError(f"omega_estimate must be one of {', '.join(OMEGA_ESTIMATES)}, got {omega_estimate!r}")
    k = _stiffness_values(model, stiffness)
    worlds = model.world_count
    if omega_estimate == "power_iteration":
        _check_iteration(max_iterations, tolerance)
        judge_run = state is None and loaded
        if judge_run and has_loads(model, control):
            state = loaded_state(model, control=control)
        estimate = _power_iteration(model, k, state, max_iterations, tolerance, 0)
        positions = model.particle_q if state is None else state.particle_q
        converged = estimate.world_converged
        peaks, probe = estimate.world_omega_max, None
        step_limited = not (cls.adaptive or getattr(cls, "unconditionally_stable", False))
        if judge_run and transient and step_limited and in_motion(model, control):
            probe = transient_peak(model, control=control, stiffness=stiffness, horizon=horizon, start=estimate,
                                   start_positions=positions.numpy().astype(np.float64),
                                   lowest_ratio=integrator == "explicit_euler")
            peaks, positions = probe.world_omega_max, probe.positions
            estimate = dataclasses.replace(estimate, world_mode=probe.world_mode)
        omegas = np.where(converged, peaks, estimate.world_gershgorin)  # the bound where not
        modes = [estimate.world_mode[w] if converged[w] else None for w in range(worlds)]
    else:
        converged = np.zeros(worlds, dtype=bool)
        omegas = _gershgorin(model, k, free_particles(model))
        modes = [None] * worlds
        positions = model.particle_q if state is None else state.particle_q
        probe = None
    ranges = _damping_ranges(model, k, modes, positions,
                             lowest_top=None if probe is None else probe.world_lowest_ratio)
    limits = _world_limits(integrator, omegas, ranges)
    w = int(np.lexsort((-omegas, limits))[0])  # the smallest step; among equals, the stiffest world
    omega, limit = float(omegas[w]), float(limits[w])
    source = "power iteration" if converged[w] else "Gershgorin bound"
    adaptive = cls.adaptive
    springs = f"ω_max = {omega:.4g} rad/s by {source}"
    peak_time = float(probe.world_peak_time[w]) if probe is not None and converged[w] else 0.0
    if peak_time > 0.0:
        springs += f" at its peak, t = {peak_time:.3g} s into a {probe.duration:.3g} s dry run"
    if worlds > 1:
        springs += f" in world {w}, the binding one of {worlds} worlds"
    frame = f"1/{fps:g} s frame"
    top = 1.0 if adaptive or not 0.0 < limit < math.inf else _top_growth(integrator, dt, omega, ranges[w], horizon)

    if adaptive:
        internal = math.ceil(dt / limit) if 0.0 < limit < math.inf else None
        stable, substeps = True, internal
        if internal is None:
            cap = f"the springs do not cap that step ({springs})"
        elif internal > 1:
            cap = (f"stability caps that step near {format_duration(limit)} ({springs}): at least {internal} internal "
                   f"steps per dt = {format_duration(dt)}")
        else:
            cap = f"stability caps that step near {format_duration(limit)} ({springs}), above dt = {format_duration(dt)}"
        message = f"{integrator} adapts its internal step to its tolerance; {cap}"
    elif limit == math.inf:
        stable, substeps = True, 1
        message = (
            f"{integrator} is unconditionally stable ({springs}): dt = {format_duration(dt)} is limited by accuracy only"
            if issubclass(cls, ImplicitEuler) else
            f"{integrator} is stable at any dt for these springs ({springs})"
        )
    elif limit == 0.0:
        stable, substeps = False, None
        fallback = float(_world_limits("symplectic_euler", omegas, ranges).min())
        message = (
            f"{integrator} is unstable at every dt for these springs (their weakly damped modes grow at any step; "
            f"{springs}): use symplectic_euler (dt ≤ {format_duration(fallback)}) or implicit_euler (unconditionally stable)"
        )
    else:
        substeps = max(1, math.ceil(1.0 / (fps * limit)))
        stable = dt <= limit
        if stable:
            message = (
                f"{integrator} is stable at dt = {format_duration(dt)}: the springs ({springs}) allow up to "
                f"{format_duration(limit)}, i.e. at least {substeps} substeps per {frame}"
            )
        else:
            grows = f"×{top:.3g}" if top < 1e6 else f"×1e{math.log10(top):.0f}"
            message = (
                f"{integrator} is unstable at dt = {format_duration(dt)}: the springs ({springs}) allow at most "
                f"{format_duration(limit)} (past it their top mode grows {grows} over a {horizon:g} s run); use a "
                f"smaller dt, at least {substeps} substeps per {frame}, or implicit_euler (unconditionally stable)"
            )
    advice = Advice(
        integrator=integrator,
        dt=dt,
        omega_max=omega,
        omega_source=source,
        dt_stable=limit,
        stable=stable,
        adaptive=adaptive,
        fps=fps,
        substeps=substeps,
        message=message,
        world=w,
        world_omega_max=np.asarray(omegas, dtype=np.float64),
        world_dt_stable=limits,
        dry_run=probe.duration if probe is not None else 0.0,
        peak_time=peak_time,
    )
    growth = _transverse_growth(model, integrator, dt, k, positions, ranges[w][1], horizon, w)
    if growth >= TRANSVERSE_NOTE:
        message += (f"; its stretched springs' transverse modes carry no damping and {integrator} grows them at any "
                    f"step: ×{growth:.3g} over a {horizon:g} s run at this dt (symplectic_euler, velocity_verlet and "
                    f"rk4 do not)")
    advice = dataclasses.replace(advice, message=message, transverse_growth=growth, top_growth=top)
    if strict and not stable:
        raise ConfigError(message)
    return advice


# -- after a stop -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Diagnosis:
    """Why a run the guard stopped went bad, judged at its last good frame.

    Attributes:
        kind: "overstretch" (a stable integration of a material too soft for its load: the springs really
            stretch that far) or "instability" (the step is beyond the limit at the state reached, or the
            state turned non-finite or its energy ran away with the step found stable: see ``remedy``).
        advice: the advisor linearised about the last good frame.
        remedy: what to change, one sentence.
    """

    kind: str
    advice: Advice
    remedy: str


def diagnose(model: Model, integrator: str, dt: float, *, fps: float, reason: str, state: State,
             control=None, omega_estimate: str = "power_iteration") -> Diagnosis:
    """Tell numerical instability from physical over-stretch after a guard stop whose ``reason`` is
    "strain", "kinetic energy" or "non-finite state", from ``state``, the last frame the guard passed.

    A spring torn in a step the advisor finds stable *at that frame's stretched state* is over-stretch:
    more substeps or implicit Euler integrate the same tearing more accurately, so the remedy is the
    material (stiffer springs, strain limiting, biphasic springs). A step beyond the limit at that state is
    instability: more substeps (the number that the state needs) or implicit Euler. ``omega_estimate`` as
    in :func:`advise`."""
    advice = advise(model, integrator, dt, fps=fps, state=state, control=control, omega_estimate=omega_estimate)
    if reason == "strain" and advice.stable:
        return Diagnosis("overstretch", advice, (
            f"the step was stable at the stretched state ({advice.message}), so the springs really stretch that "
            "far: the material is too soft for its load, and neither more substeps nor implicit_euler change "
            "that; use stiffer springs (ke), strain limiting (Stabilizers(max_strain=0.1), [stabilizers] "
            "max_strain) or biphasic springs (biphasic_strain, biphasic_ratio)"))
    if not advice.stable:
        hint = f" (e.g. --substeps {advice.substeps})" if advice.substeps else ""
        return Diagnosis("instability", advice, (
            f"numerical instability: at the state the run reached, {advice.message}{hint}"))
    return Diagnosis("instability", advice, (
        f"the advisor found the step stable for the elements at the state the run reached ({advice.message}), "
        "so look at contacts, external forces or extreme parameters; more substeps or implicit_euler may help"))


# -- helpers ------------------------------------------------------------------------------------------------


def _extremes(name: str, values) -> tuple[float, ...]:
    array = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if array.size == 0:
        array = np.zeros(1)
    if not (np.isfinite(array).all() and (array >= 0.0).all()):
        raise ConfigError(f"{name} must be finite and >= 0")
    return tuple(sorted({float(array.min()), float(array.max())}))
