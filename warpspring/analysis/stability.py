"""Explicit-integration stability, exactly: each integrator's one-step map of a damped spring, built from its
own update equations with rational arithmetic, and from it the largest stable step of a spring and of a
spring network whose modes span (0, ω_max].

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
top mode's own damping (see :func:`~warpspring.analysis.advisor.advise`).

The network's ω_max comes from :mod:`.omega`, the states the advisor linearises about from
:mod:`.under_load`, the damping of its modes from :mod:`.damping`; :mod:`.advisor` combines them.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from .. import checks
from ..errors import ConfigError
from ..core.integrators import INTEGRATORS, ExplicitRungeKutta, ImplicitEuler, SymplecticEuler, VelocityVerlet

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


#: Three-wave resonance: a spring network's forces are nonlinear (quadratic in the displacement to leading order),
#: so three modes whose numerical phases per step θ₁ + θ₂ + θ₃ meet 2π (the step aliases their sum) trade energy,
#: and a step whose map neither damps nor dissipates feeds them. The sum of three phases in [0, π] reaches 2π only
#: where one of them reaches 2π/3: the top mode's phase below it excludes every such triad. For symplectic Euler
#: and velocity Verlet without damping, cos θ = 1 - (ωh)²/2, so ωh ≤ √3 (0.866 of their linear limit of 2):
#: measured, an undamped 16² cloth released flat (bench/advisor_battery.py) grows at ωh = 1.84 and not at 1.67.
TRIAD_PHASE = 2.0 * math.pi / 3.0
#: ... where the top mode decays more slowly than this [1/s] (its damping and the map's own loss per step): the
#: same cloth with kd/k = 1e-6 s (a decay of 0.6/s) no longer grows at ωh = 1.84; the undamped one grows at
#: ~0.4/s in amplitude, so 2/s keeps a factor of 5.
TRIAD_DECAY = 2.0
#: The share of the three-wave step the advisor passes, below the measured resonance band. Against the highest ω_max
#: a run's own states reach (``stability_battery.omega_trace``; the advisor's dry run, which lasts the cloth's first
#: swing, finds the folded cloth's to 0.3 %; a flat cloth's back-swing whips it 4-5 % higher for an instant, 32² at
#: 2.6 s, 64² at 4.0 s, and those runs hold at ωh = 1.72 there), the undamped cloth of bench/advisor_battery.py released folded under gravity grows (its
#: shadow energy's 1 s mean past 1 % of what the release set free) within 10 s from ωh = 1.79 = 1.035 √3 (32²,
#: velocity Verlet, at ~9 s) and at 1.87 = 1.08 √3 (64², symplectic Euler and Verlet), not within 10 s at 1.83 (64²)
#: nor at 1.70 = 0.98 √3 (32², but past 1 % at ~15 s), and settles at 1.61 = 0.93 √3; the 8² and 16² cloths hold at
#: 0.9975 √3 and grow at 1.055 √3. So the largest step that neither blows up nor grows within 10 s lies between
#: 0.98 √3 and 1.08 √3 of the peak ω_max: 0.975 passes below the lowest of them and within 0.9 of the highest
#: (0.975/1.08 = 0.903). Where a run lasts longer than 10 s, near the band's lower edge growth comes later (the 32²
#: cloth at 0.98 √3 passes 1 % at ~15 s): the margin is set for the issue's 10 s (bench/results/advisor_battery_cpu.md).
#: Bracketed by bisection since (``stability_battery.largest_step``, 10 s runs on the CPU,
#: bench/results/advisor_battery_bisect_cpu.md; in units of √3 over the first swing's peak ω_max, the one the verdict
#: takes), the largest step that neither blows up nor grows lies at 1.021-1.030 for the folded cloth under gravity at
#: 8²-32² and 1.057-1.076 at 64²; 1.030-1.048 for the flat one at 8²-32² and 1.112-1.121 at 64² (where its back-swing
#: whip passes the linear limit); 1.030-1.057 for the folded one without gravity at 8² and 16², 1.103-1.130 at 32² and
#: 1.149-1.158 at 64² (its linear limit, 1.155). Past √3 growth is not monotone in the step (the swinging cloth is
#: chaotic): the 8² folded cloth under gravity (symplectic Euler) grows at 1.010 √3 and holds at 1.005, 1.0125 and
#: 1.015, or grows at 1.0125 for a step 4e-6 shorter; Verlet comes to 0.91 % at 0.9975 √3. So a share above 1 passes
#: into that lottery (1.0125 passed a run that grew by 1.2 %), while the 64² flat cloth needs at least 1.009 (its
#: 1.121 over 1/0.9) and the 64² folded one without gravity 1.042 for a run 1/0.9 past the passed step to fail: no
#: share of √3/ω_max is both one-sided and within 10 % of every case; 0.975 keeps one-sided.
TRIAD_MARGIN = 0.975
#: Explicit Euler and midpoint rely on damping: at their limit the least damped mode is neutral, and the
#: undamped transverse modes of stretched springs grow at any step; the advisor passes steps up to this share
#: of their limit only (the exact-limit battery case: kd/k = 1e-4 s at dt = 0.1 ms = the limit blows up).
DAMPED_MARGIN = 0.9


def _phase(integrator: str, omega_h: float, zeta: float) -> float:
    """The phase per step [rad] of the test oscillator's least decaying eigenvalue (π for a negative real one)."""
    values = np.linalg.eigvals(amplification_matrix(integrator, omega_h, zeta))
    top = values[np.argmax(np.abs(values))]
    return float(abs(np.angle(top)))


def triad_step(integrator: str, omega: float, zeta: float, limit: float) -> float:
    """The largest step [s] ≤ ``limit`` at which the mode of angular frequency ``omega`` [rad/s] and damping ratio
    ``zeta`` keeps its phase per step within ``TRIAD_PHASE`` (``limit`` itself if it does up to there): a scan of
    64 steps, then bisection on the first crossing (the phase grows with the step up to it)."""
    if not (omega > 0.0 and 0.0 < limit < math.inf):
        return limit
    steps = limit * np.linspace(1.0 / 64.0, 1.0, 64)
    phases = [_phase(integrator, omega * h, zeta) for h in steps]
    above = [k for k, phase in enumerate(phases) if phase > TRIAD_PHASE]
    if not above:
        return limit
    k = above[0]
    low, high = (steps[k - 1] if k else 0.0), steps[k]
    for _ in range(40):
        mid = 0.5 * (low + high)
        low, high = (mid, high) if _phase(integrator, omega * mid, zeta) <= TRIAD_PHASE else (low, mid)
    return low


def passed_step(integrator: str, omega_max: float, limit: float, *, rayleigh=0.0, drag_rate=0.0) -> tuple[float, str]:
    """The largest step [s] the advisor passes on a network of linear limit ``limit`` [s] (:func:`network_stable_step`)
    whose top mode is ``omega_max`` [rad/s] with the least damping of ``rayleigh`` (kd/k [s]) and ``drag_rate``
    (c/m [1/s]), and why it is below ``limit`` ("" where it is not): ``DAMPED_MARGIN`` × ``limit`` for the
    integrators that rely on damping (explicit Euler, midpoint), ``TRIAD_MARGIN`` × the three-wave limit
    (:func:`triad_step`) where the top mode decays more slowly than ``TRIAD_DECAY``."""
    if not 0.0 < limit < math.inf:
        return limit, ""
    if spectral_radius(integrator, 0.1, 0.0) > 1.0 + 1.0e-9:  # grows undamped modes: relies on damping
        return DAMPED_MARGIN * limit, f"{DAMPED_MARGIN:g} of the limit: {integrator} relies on damping, neutral at its limit"
    ratio, rate = min(_extremes("rayleigh", rayleigh)), min(_extremes("drag_rate", drag_rate))
    zeta = (ratio * omega_max * omega_max + rate) / (2.0 * omega_max) if omega_max > 0.0 else 0.0
    step = triad_step(integrator, omega_max, zeta, limit)
    if step >= limit:
        return limit, ""
    decay = max(0.0, -math.log(max(spectral_radius(integrator, omega_max * step, zeta), 1e-300)) / step)
    if decay >= TRIAD_DECAY:
        return limit, ""
    share = f", {TRIAD_MARGIN:g} of it"
    return TRIAD_MARGIN * step, (
        f"the three-wave limit of a weakly damped cloth (its top mode's phase per step within 2π/3, "
        f"decaying at {decay:.2g}/s < {TRIAD_DECAY:g}/s){share}" if decay > 1e-6 else
        f"the three-wave limit of an undamped cloth (its top mode's phase per step within 2π/3){share}")


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


# -- helpers ------------------------------------------------------------------------------------------------


def _extremes(name: str, values) -> tuple[float, ...]:
    array = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if array.size == 0:
        array = np.zeros(1)
    if not (np.isfinite(array).all() and (array >= 0.0).all()):
        raise ConfigError(f"{name} must be finite and >= 0")
    return tuple(sorted({float(array.min()), float(array.max())}))
