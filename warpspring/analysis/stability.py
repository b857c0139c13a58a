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
below it, and is the cheap fallback.

**The advisor** (:func:`advise`) combines both for a model, an integrator and a step.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import warp as wp

from .. import checks
from ..checks import format_duration
from ..errors import ConfigError
from ..core.integrators import INTEGRATORS, ExplicitRungeKutta, ImplicitEuler, SymplecticEuler, VelocityVerlet
from ..kernels.linalg import reduce_launch_dim
from ..kernels.stability import PI_LAMBDA, PI_RESIDUAL, PI_SCALARS, power_iteration_kernels
from ..core.model import Model, State

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
_HALF = Fraction(1, 2)


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


def _runge_kutta(a: tuple, b: tuple) -> tuple[tuple[_Row, _Row], _Poly]:
    x0, v0 = _Row(1, 0), _Row(0, 1)
    stage_x, stage_v = [], []
    for k in range(len(b)):
        x, v = x0, v0
        for j, c in enumerate(a[k]):
            if c:
                x, v = x + _tableau_rational(c) * stage_x[j], v + _tableau_rational(c) * stage_v[j]
        stage_x.append(_drift(v))
        stage_v.append(_kick(x, v))
    x, v = x0, v0
    for j, c in enumerate(b):
        if c:
            x, v = x + _tableau_rational(c) * stage_x[j], v + _tableau_rational(c) * stage_v[j]
    return (x, v), _Poly.lift(1)


def _symplectic_euler() -> tuple[tuple[_Row, _Row], _Poly]:
    x0, v0 = _Row(1, 0), _Row(0, 1)
    v1 = v0 + _kick(x0, v0)
    x1 = x0 + _drift(v1)
    return (x1, v1), _Poly.lift(1)


def _velocity_verlet() -> tuple[tuple[_Row, _Row], _Poly]:
    # The corrector runs only for velocity-dependent forces; without damping (b = 0) it changes nothing,
    # so one expression covers both cases.
    x0, v0 = _Row(1, 0), _Row(0, 1)
    v_half = v0 + _HALF * _kick(x0, v0)
    x1 = x0 + _drift(v_half)
    v_star = v_half + _HALF * _kick(x1, v_half)
    v1 = v_half + _HALF * _kick(x1, v_star)
    return (x1, v1), _Poly.lift(1)


def _implicit_euler() -> tuple[tuple[_Row, _Row], _Poly]:
    # (I - Z) u₁ = u₀ with I - Z = [[1, -a], [a, 1 + b]]: u₁ = adj(I - Z) u₀ / det(I - Z).
    return (_Row(1 + _B, _A), _Row(-_A, 1)), 1 + _B + _A * _A


@functools.cache
def _propagator(integrator: str) -> tuple[tuple[tuple[_Poly, _Poly], tuple[_Poly, _Poly]], _Poly]:
    """(N, q) of the named integrator: its one-step map of the test oscillator is N / q."""
    cls = _integrator_class(integrator)
    if issubclass(cls, ExplicitRungeKutta):
        (x1, v1), q = _runge_kutta(cls.a, cls.b)
    elif issubclass(cls, SymplecticEuler):
        (x1, v1), q = _symplectic_euler()
    elif issubclass(cls, VelocityVerlet):
        (x1, v1), q = _velocity_verlet()
    elif issubclass(cls, ImplicitEuler):
        (x1, v1), q = _implicit_euler()
    else:
        raise ConfigError(f"no stability theory for the {integrator!r} integrator ({cls.__name__})")
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
    """The highest angular frequency of a model's springs by power iteration on M⁻¹K.

    Attributes:
        omega_max: √θ [rad/s], θ the final Rayleigh quotient (θ ≤ λ_max(M⁻¹K)).
        iterations: power iterations run.
        residual: ‖M⁻¹Kx - θx‖_M / (θ‖x‖_M) of the final iterate [-].
        converged: whether the residual reached the tolerance within the iteration budget.
        gershgorin: the Gershgorin upper bound on ω_max [rad/s] (:func:`gershgorin_omega_max`).
        mode: the final iterate, an approximate top mode shape [-], shape [particle_count, 3], float64,
            unit mass-norm, zero on pinned particles (zero everywhere when the model has no stiffness).
    """

    omega_max: float
    iterations: int
    residual: float
    converged: bool
    gershgorin: float
    mode: np.ndarray


def _stiffness_array(model: Model, stiffness) -> wp.array:
    """The spring stiffness [N/m] on the model's device: an override of shape [spring_count], or the
    model's own — for biphasic springs their stiffer branch, ratio × ke, which bounds the step once a
    spring stretches past its knee."""
    if stiffness is None:
        ratio = 1.0
        if model.spring_law.biphasic:  # the stiffest the ratio gets, its track included
            track = model.track("biphasic_ratio")
            ratio = max(model.stabilizers.biphasic_ratio, float(track.values.max()) if track is not None else 1.0)
        if ratio == 1.0 or model.spring_count == 0:
            return model.spring_stiffness
        stiffness = model.spring_stiffness.numpy().astype(np.float64) * ratio
    values = stiffness.numpy() if isinstance(stiffness, wp.array) else np.asarray(stiffness)
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (model.spring_count,):
        raise ConfigError(f"stiffness must have shape ({model.spring_count},), got {values.shape}")
    if not (np.isfinite(values).all() and (values >= 0.0).all()):
        raise ConfigError("stiffness must be finite and >= 0")
    return wp.array(values.astype(np.float64 if model.scalar is wp.float64 else np.float32), dtype=model.scalar,
                    device=model.device)


def gershgorin_omega_max(model: Model, *, stiffness=None) -> float:
    """Upper bound [rad/s] on ω_max from Gershgorin's theorem for 3 × 3 blocks (host NumPy).

    Row i of M⁻¹K holds the diagonal block Σₛ Kₛ / mᵢ and one block Kₛ / mᵢ per spring to a free particle;
    each clamped spring block has spectral norm kₛ, so λ_max ≤ maxᵢ (Σₛ kₛ + Σ_{s to free j} kₛ) / mᵢ over
    free particles. (2 Σₛ kₛ / mᵢ, the bound usually quoted, is this with every neighbour free.)

    Args:
        model: the model.
        stiffness: spring stiffness [N/m] to use instead of ``model.spring_stiffness``, shape [spring_count].
    """
    free = ~model.kinematic_mask()
    if model.spring_count == 0 or not free.any():
        return 0.0
    k = _stiffness_array(model, stiffness).numpy().astype(np.float64)
    i, j = model.spring_indices.numpy().reshape(-1, 2).T
    n = model.particle_count
    row = np.bincount(i, weights=k, minlength=n) + np.bincount(j, weights=k, minlength=n)
    row += np.bincount(i, weights=k * free[j], minlength=n) + np.bincount(j, weights=k * free[i], minlength=n)
    mass = model.particle_mass.numpy().astype(np.float64)
    return float(math.sqrt((row[free] / mass[free]).max()))


def estimate_omega_max(
    model: Model,
    *,
    state: State | None = None,
    stiffness=None,
    max_iterations: int = 1000,
    tolerance: float = 1.0e-3,
    seed: int = 0,
) -> OmegaMaxEstimate:
    """ω_max = √λ_max(M⁻¹K) of the model's springs by power iteration on its device.

    K is assembled matrix-free from the clamped spring stiffness matrices at ``state``'s positions (default
    the model's initial ones); pinned particles are filtered out. The iteration stops when the relative
    residual ‖M⁻¹Kx - θx‖_M / (θ‖x‖_M) ≤ ``tolerance`` or after ``max_iterations``; the Rayleigh quotient
    θ then approximates λ_max from below, its relative error typically well under the residual (a
    residual of 1e-3 leaves ω_max within ~2e-4 on cloths).

    Args:
        model: the model.
        state: positions to linearise about; default the model's initial positions.
        stiffness: spring stiffness [N/m], shape [spring_count]; default the model's, with biphasic
            springs at their stiffer branch (ratio × ke).
        max_iterations: iteration budget (≥ 1).
        tolerance: relative residual at which to stop, in (0, 1).
        seed: seed of the random start vector.
    """
    checks.count("max_iterations", max_iterations, minimum=1)
    if checks.positive("tolerance", tolerance) >= 1.0:
        raise ConfigError(f"tolerance must be a number in (0, 1), got {tolerance!r}")
    bound = gershgorin_omega_max(model, stiffness=stiffness)
    if bound == 0.0:
        return OmegaMaxEstimate(omega_max=0.0, iterations=0, residual=0.0, converged=True, gershgorin=0.0,
                                mode=np.zeros((model.particle_count, 3)))
    n, device, vec3 = model.particle_count, model.device, model.vec3
    k = _stiffness_array(model, stiffness)
    q = model.particle_q if state is None else state.particle_q
    tiled = device.is_cuda
    block = model.block_dim if tiled else 1
    product, normalize, condition = power_iteration_kernels(model.scalar, model.spring_max_degree, tiled)

    free = ~model.kinematic_mask()
    start = np.random.default_rng(seed).normal(size=(n, 3)) * free[:, None]
    x = wp.array(start, dtype=vec3, device=device)
    y = wp.zeros(n, dtype=vec3, device=device)
    scalars = wp.zeros(PI_SCALARS, dtype=wp.float64, device=device)
    iteration = wp.zeros(1, dtype=wp.int32, device=device)
    keep_going = wp.ones(1, dtype=wp.int32, device=device)
    model_inputs = [
        model.particle_flags,
        model.particle_mass,
        model.particle_spring_neighbor,
        model.particle_spring_id,
        model.spring_rest_length,
        k,
    ]

    def iterate():
        wp.launch(product, dim=reduce_launch_dim(n, block), block_dim=block, inputs=[n, *model_inputs, q, x],
                  outputs=[y, scalars], device=device)
        wp.launch(normalize, dim=n, block_dim=model.block_dim, inputs=[model.particle_flags, model.particle_inv_mass, y, scalars],
                  outputs=[x], device=device)
        wp.launch(condition, dim=1, inputs=[wp.float64(tolerance), max_iterations, scalars],
                  outputs=[iteration, keep_going], device=device)

    wp.capture_while(keep_going, iterate)
    values = scalars.numpy()
    residual = float(values[PI_RESIDUAL])
    return OmegaMaxEstimate(
        omega_max=math.sqrt(max(float(values[PI_LAMBDA]), 0.0)),
        iterations=int(iteration.numpy()[0]),
        residual=residual,
        converged=residual <= tolerance,
        gershgorin=bound,
        mode=x.numpy().astype(np.float64),
    )


# -- the advisor --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Advice:
    """Whether a step is stable for a model and an integrator, and what to change if not.

    Attributes:
        integrator: the integrator's registry name.
        dt: the step asked about [s].
        omega_max: the springs' highest angular frequency used [rad/s].
        omega_source: how ``omega_max`` was obtained: "power iteration" or "Gershgorin bound" (an upper
            bound: the step limit is then conservative).
        dt_stable: the largest stable step [s]; ∞ when unconditionally stable, 0 when unstable at every
            step. For an adaptive integrator: the stability limit of its internal step.
        stable: whether ``dt`` is stable (always true for adaptive integrators, which shrink their step).
        adaptive: whether the integrator chooses its own internal step.
        fps: frame rate [1/s] the substep count refers to.
        substeps: the fewest steps per 1/fps frame that keep the step ≤ ``dt_stable`` (for adaptive
            integrators: the fewest internal steps per ``dt``); ``None`` when no step is stable.
        message: one line for the user, with a suggestion when ``dt`` is unstable.
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


def _damping_ranges(model: Model, stiffness: wp.array, estimate: OmegaMaxEstimate | None, positions: wp.array):
    """(kd/k values [s], c/m values [1/s]) for :func:`network_stable_step`.

    kd/k: the springs' smallest ratio (the least damped modes, which explicit Euler and midpoint cannot
    integrate stably without damping) and the top mode's own ratio xᵀDx / xᵀKx on the power-iteration
    eigenvector x (D = Σₛ kdₛ d̂d̂ᵀ): a mode near ω_max strains the stiff springs, so the damping of soft,
    heavily damped families does not reach it. Without an eigenvector (Gershgorin) the largest ratio
    stands in for the top mode's, which is conservative for symplectic Euler but loose when the stiffest
    springs are the least damped. c/m: its extremes over the free particles (drag limits the slowest
    motions, each particle's velocity decaying at its own c/m).
    """
    free = ~model.kinematic_mask()
    k = stiffness.numpy().astype(np.float64)
    kd = model.spring_damping.numpy().astype(np.float64)
    ends = model.spring_indices.numpy().reshape(-1, 2)
    acting = (k > 0.0) & free[ends].any(axis=1)
    mass = model.particle_mass.numpy().astype(np.float64)[free]
    rates = model.drag / mass if len(mass) else np.zeros(1)
    if not acting.any():
        return np.zeros(1), rates
    ratios = kd[acting] / k[acting]
    if estimate is None:
        return ratios, rates
    q = positions.numpy().astype(np.float64)
    mode = estimate.mode * free[:, None]
    i, j = ends[acting].T
    d = q[j] - q[i]
    length = np.linalg.norm(d, axis=1)
    coincident = length == 0.0  # no direction: no stiffness, no damping (as in the kernels)
    safe = np.where(coincident, 1.0, length)
    delta = mode[i] - mode[j]
    axial2 = (np.einsum("sk,sk->s", d, delta) / safe) ** 2
    rest = model.spring_rest_length.numpy().astype(np.float64)[acting]
    transverse = np.where(coincident, 0.0, np.maximum(1.0 - rest / safe, 0.0))  # clamped, as in K
    xkx = float((k[acting] * (axial2 + transverse * (np.einsum("sk,sk->s", delta, delta) - axial2))).sum())
    xdx = float((kd[acting] * axial2).sum())
    top = xdx / xkx if xkx > 0.0 else float(ratios.max())
    return np.array([ratios.min(), top]), rates


def advise(
    model: Model,
    integrator: str,
    dt: float,
    *,
    fps: float = 60.0,
    strict: bool = False,
    stiffness=None,
    state: State | None = None,
    omega_estimate: str = "power_iteration",
    max_iterations: int = 1000,
    tolerance: float = 1.0e-3,
) -> Advice:
    """Check ``dt`` against the springs' stability limit for ``integrator`` and say what to do.

    ω_max comes from :func:`estimate_omega_max` (falling back to the Gershgorin bound when the power
    iteration does not converge within ``max_iterations``) or, with ``omega_estimate="gershgorin"``,
    from :func:`gershgorin_omega_max` directly (cheaper, conservative). The modes' damping
    (:func:`network_stable_step`) spans the smallest kd/k of the springs and the top mode's own kd/k,
    xᵀDx / xᵀKx on the power-iteration eigenvector (with the Gershgorin bound: the largest kd/k), and the
    drag's c/m. Contacts are not part of the analysis.

    Args:
        model: the model.
        integrator: registry name of the integrator.
        dt: the step [s] to check, > 0.
        fps: frame rate [1/s] for the substep count.
        strict: raise a ConfigError carrying the message when ``dt`` is unstable.
        stiffness: spring stiffness [N/m], shape [spring_count], also used for the springs' kd/k; default
            the model's, with biphasic springs at their stiffer branch (ratio × ke).
        state: positions to linearise about; default the model's initial positions.
        omega_estimate: "power_iteration" or "gershgorin".
        max_iterations, tolerance: of the power iteration.

    Raises:
        ConfigError: bad arguments, or (with ``strict``) an unstable step.
    """
    dt, fps = checks.positive("dt", dt), checks.positive("fps", fps)
    cls = _integrator_class(integrator)
    if omega_estimate not in OMEGA_ESTIMATES:
        raise ConfigError(f"omega_estimate must be one of {', '.join(OMEGA_ESTIMATES)}, got {omega_estimate!r}")
    k = _stiffness_array(model, stiffness)
    estimate = None
    if omega_estimate == "power_iteration":
        estimate = estimate_omega_max(model, state=state, stiffness=k, max_iterations=max_iterations,
                                      tolerance=tolerance)
        if not estimate.converged:
            estimate = None  # fall back to the bound
    omega, source = (estimate.omega_max, "power iteration") if estimate else (
        gershgorin_omega_max(model, stiffness=k), "Gershgorin bound")
    positions = model.particle_q if state is None else state.particle_q
    ratios, rates = _damping_ranges(model, k, estimate, positions)
    limit = network_stable_step(integrator, omega, rayleigh=ratios, drag_rate=rates)
    adaptive = cls.adaptive
    springs = f"ω_max = {omega:.4g} rad/s by {source}"
    frame = f"1/{fps:g} s frame"

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
        fallback = network_stable_step("symplectic_euler", omega, rayleigh=ratios, drag_rate=rates)
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
            message = (
                f"{integrator} is unstable at dt = {format_duration(dt)}: the springs ({springs}) allow at most "
                f"{format_duration(limit)}; use a smaller dt, at least {substeps} substeps per {frame}, or implicit_euler "
                f"(unconditionally stable)"
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
    )
    if strict and not stable:
        raise ConfigError(message)
    return advice


# -- helpers ------------------------------------------------------------------------------------------------


def _extremes(name: str, values) -> tuple[float, ...]:
    array = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if array.size == 0:
        array = np.zeros(1)
    if not (np.isfinite(array).all() and (array >= 0.0).all()):
        raise ConfigError(f"{name} must be finite and >= 0")
    return tuple(sorted({float(array.min()), float(array.max())}))
