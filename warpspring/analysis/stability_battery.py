"""The advisor on free, undamped and large-motion cloth, measured: does ``--strict`` ever pass a step whose run
blows up or grows, and how close does it come to the largest step that does neither?

Cloth: n × n particles 0.1 m apart, 1/256 kg each (the 16² cloth weighs 1 kg), structural / shear / bend springs
of 1000 / 200 / 20 N/m with kd = τ · ke (τ = 0: undamped; ``LIGHT`` = 1e-5 s: lightly damped), no drag, pinned at
its two top corners (row n-1). Released at rest:

* ``flat``: horizontal at z = 1 m; it swings down under gravity (large motion: rotations of 90°);
* ``folded``: its lower half folded under its upper half one spacing below it (a U fold of the cloth), so that its
  shear and bend springs across the fold start compressed; with gravity it falls and unfolds, without it the fold
  springs open it.

Protocol. For each case and integrator the advisor judges a 10 s run (``advise(..., horizon=10)``, as
``warpspring run --strict`` does) and gives the largest step it passes, P (:attr:`~.advisor.Advice.dt_passed`).
The cloth then runs for ``seconds`` at steps f · P for the factors ``FACTORS`` (each its own run; ``SUBSTEPS``
steps per output frame, so the step is any number). Every frame its energy is summed in float64 on the host
(:class:`EnergyMeter`), and judged against the energy the release sets free, F (:func:`free_energy`: the start's
energy over the static equilibrium's, which gravity's arbitrary zero leaves alone; 7.4 J for the 16² flat cloth).
A run

* **blows up** when its state turns non-finite, a spring passes ``TORN`` × its rest length, or its energy rises
  above its start by ``BLOWN`` × F;
* **grows** when its energy, averaged over ``MEAN_WINDOW`` (1 s), rises more than ``GROWTH`` = 1 % of F above
  its start within the run: the issue's criterion, read on the energy the integrator conserves. Symplectic Euler
  and velocity Verlet keep a shadow energy H̃, not H (:class:`EnergyMeter`); H itself swings by O(h) (O(h²)) about
  it, 12 % of F within 10 s on the 16² flat cloth at the three-wave step (symplectic Euler) however stable the
  run. H̃ through its O(h²) terms (error O(h⁴)) holds to 1e-5 of F for the first 2 s of that run; as the motion
  spreads into the cloth's top modes (ωh up to √3, where the series converges slowly) its residual becomes a bias
  of about -1 % of F that settles (-0.8 % at 0.8 of that step over 40 s, Verlet); the 1 s mean removes the
  residual's swing. A run past the step that holds crosses +1 % seconds before it turns non-finite, and does so
  whatever the round-off: 8² flat, Verlet, at 1.111 × the three-wave step, at 5.7-7.8 s over eight perturbations
  of its start by 1e-7 m, where half the motion's energy in the last 2 s (this battery's former threshold) missed
  two of them. Measurements: ``bench/results/advisor_battery_cpu.md``. The table gives, per run, the highest 1 s
  mean and, in brackets, the highest single value of H̃ - H̃(0), in % of F; RK4 has no shadow energy (its H falls:
  it dissipates at large steps).

A case passes when every run at f ≤ 1 neither blows up nor grows (one-sided) and some run at f ≤ 1/0.9 does
(tight: the advisor's step is within 10 % of the largest step that does neither, as far as the grid of factors
can tell). Explicit Euler and midpoint rely on damping: on undamped cloth the advisor must refuse every step
(P = 0) and recommend symplectic Euler or Verlet; on damped cloth its step must stay below their linear limit by
:data:`~.stability.DAMPED_MARGIN`, so that the step at the limit itself (the exact-limit case, kd = 1e-4 s · ke
under explicit Euler at dt = 0.1 ms) is refused.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..core.builder import ModelBuilder, SpringMaterial
from ..core.integrators import make_integrator
from ..core.model import Model
from ..core.simulator import Simulator
from .advisor import Advice, advise
from .stability import DAMPED_MARGIN
from ..kernels.stability import PI_LAMBDA
from .omega import PowerIteration, _power_iteration, _stiffness_values, free_particles
from .under_load import static_equilibrium

#: The integrators whose passes are measured for one-sidedness and tightness, and those that rely on damping.
CONSERVATIVE = ("symplectic_euler", "velocity_verlet", "rk4")
DISSIPATIVE = ("explicit_euler", "midpoint")
#: Light damping: kd = LIGHT · ke [s].
LIGHT = 1.0e-5
#: The exact-limit case's damping: kd = EXACT · ke [s] (explicit Euler's limit is then τ itself, 0.1 ms).
EXACT = 1.0e-4
#: Step factors of the runs, around the advisor's step P (1.0: P itself; 1.111 = 1/0.9).
FACTORS = (0.8, 0.9, 1.0, 1.05, 1.111, 1.25, 1.5)
SUBSTEPS = 10  # steps per output frame (energy read once a frame)
GROWTH = 0.01  # of the free energy: the 1 % (the module docstring)
MEAN_WINDOW = 1.0  # [s], the shadow energy's moving mean (the module docstring)
BLOWN = 10.0  # of the free energy
TORN = 10.0  # × rest length
SPACING = 0.1  # [m]
PARTICLE_MASS = 1.0 / 256.0  # [kg]
STIFFNESS = {"structural": 1000.0, "shear": 200.0, "bend": 20.0}  # [N/m]
RELEASES = ("flat", "folded")


@dataclass(frozen=True)
class Case:
    """One cloth of the battery: n × n particles, kd/k ratio ``tau`` [s], ``release`` ("flat" or "folded"),
    ``gravity`` on or off; ``columns``: a strip of that many columns of n particles instead (0: n)."""

    n: int
    tau: float
    release: str
    gravity: bool
    columns: int = 0

    @property
    def label(self) -> str:
        damping = "undamped" if self.tau == 0.0 else f"kd = {self.tau:g} s·ke"
        size = f"{self.columns} × {self.n}" if self.columns else f"{self.n}²"
        return f"{size} {self.release}, {damping}, {'gravity' if self.gravity else 'no gravity'}"


def cases(sizes=(8, 16, 32, 64), taus=(0.0, LIGHT)) -> list[Case]:
    """Every case of the battery for ``sizes`` and ``taus``: flat with gravity, folded with and without (flat
    without gravity does not move)."""
    return [Case(n, tau, release, gravity) for n in sizes for tau in taus
            for release, gravity in (("flat", True), ("folded", True), ("folded", False))]


def battery_cloth(case: Case, device, *, precision: str = "float32") -> Model:
    """The cloth of ``case`` (this module's docstring), finalized on ``device``. Folded: rows h-1-k (k = 0, 1, …,
    h = n // 2) lie under rows h+k one spacing below them, a U fold whose turn spans one spacing vertically, so
    that the structural and shear springs start at their rest lengths and only the bend springs across the fold
    start compressed (2s against √2 s)."""
    n, columns = case.n, case.columns or case.n
    builder = ModelBuilder(gravity=(0.0, 0.0, -9.81) if case.gravity else (0.0, 0.0, 0.0))
    families = {name: SpringMaterial(ke, case.tau * ke) for name, ke in STIFFNESS.items()}
    builder.add_cloth_grid(nx=columns, ny=n, spacing=SPACING, origin=(0.0, 0.0, 1.0), particle_mass=PARTICLE_MASS,
                           pin=["top-left", "top-right"], **families)
    model = builder.finalize(device, precision=precision)
    if case.release == "folded":  # the rest lengths stay the flat grid's
        q = model.particle_q.numpy().reshape(n, columns, 3)
        h = n // 2
        for k in range(h):
            q[h - 1 - k, :, 1] = SPACING * (h + k)
            q[h - 1 - k, :, 2] = 1.0 - SPACING
        model.particle_q.assign(np.ascontiguousarray(q.reshape(-1, 3)))
    return model


class EnergyMeter:
    """The energy of one world's state, summed in float64 on the host, and the energy the integrator conserves.

    H = ½ Σ m v² + Σ ½ k (|d| - L)² - Σ m g·x [J] is what a run's energy is. A symplectic integrator does not
    keep H: it keeps a modified (shadow) energy H̃ = H + h H₁ + h² H₂ + … exactly conserved by the flow that
    interpolates its steps, so H oscillates about H̃ by the first correction (O(h) for symplectic Euler, O(h²) for
    velocity Verlet) however stable the step. The meter returns H̃ through the step's leading corrections
    (Hairer, Lubich & Wanner, *Geometric Numerical Integration*, IX.3 and IX.8), with f = -∇U the conservative
    forces (springs and weight), |f|²_M⁻¹ = Σ |f_i|² / m_i over the free particles and U''(v, v) the springs'
    Hessian on the velocities (k ((d̂·u)² + (1 - L/|d|)(|u|² - (d̂·u)²)) per spring, u the velocity difference):

    * ``velocity_verlet``: H̃ = H + h² (U''(v, v) / 12 - |f|²_M⁻¹ / 24), error O(h⁴);
    * ``symplectic_euler`` (v' = v + h M⁻¹ f(x), x' = x + h v'): its positions are leapfrog's and its velocity is
      leapfrog's half-step one, v_n = v_(n-½), so it conserves Verlet's H̃ at the synchronised velocity
      v + (h/2) M⁻¹ f(x) (error O(h⁴)); to first order that is H + (h/2) v·f, the first-order modified energy of
      symplectic Euler, and to second order it adds (h²/12) (|f|²_M⁻¹ + U''(v, v)) (Hairer, Lubich & Wanner IX.3);
    * any other integrator: H (RK4 is not symplectic; its energy error is O(h⁴), and dissipative at large steps).

    On a linear system H̃ is an exact invariant of the map (Verlet: ½ v² + ½ ω² x² (1 - (ωh)²/4); symplectic
    Euler: ½ v² + ½ ω² x² - (h/2) ω² x v), which is what makes it fit the cloth's stiff modes near the step's
    limit; measured on one swinging spring (``tests/test_stability_battery.py``) H's range scales as h (h² for
    Verlet) and H̃'s as h⁴ for both. Dampers and drag are not in H̃: they only take energy out.
    """

    def __init__(self, model: Model, integrator: str, dt: float):
        self.integrator, self.h = integrator, float(dt)
        self.pairs = model.spring_indices.numpy()
        self.rest = model.spring_rest_length.numpy().astype(np.float64)
        self.k = model.spring_stiffness.numpy()[0].astype(np.float64)
        self.mass = model.particle_mass.numpy()[0].astype(np.float64)
        self.inv_mass = np.where(free_particles(model)[0], 1.0 / self.mass, 0.0)
        self.weight = self.mass[:, None] * np.asarray(model.gravity, dtype=np.float64)[None, :]  # m g [N]

    def potential(self, x: np.ndarray) -> float:
        """U(x) = Σ ½ k (|d| - L)² - Σ m g·x [J]."""
        d = np.linalg.norm(x[self.pairs[:, 0]] - x[self.pairs[:, 1]], axis=1)
        return 0.5 * float((self.k * (d - self.rest) ** 2).sum()) - float((self.weight * x).sum())

    def __call__(self, x: np.ndarray, v: np.ndarray) -> tuple[float, float, float, float]:
        """(H, H̃, kinetic energy [J], largest spring stretch |d|/L) of positions ``x`` [m] and velocities ``v``
        [m/s], float64, shape [particle_count, 3]."""
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        delta = x[i] - x[j]
        length = np.linalg.norm(delta, axis=1)
        safe = np.maximum(length, 1e-12)
        kinetic = 0.5 * float((self.mass * (v * v).sum(axis=1)).sum())
        total = kinetic + 0.5 * float((self.k * (length - self.rest) ** 2).sum()) - float((self.weight * x).sum())
        stretch = float((length / self.rest).max())
        if self.integrator not in ("symplectic_euler", "velocity_verlet"):
            return total, total, kinetic, stretch
        unit = delta / safe[:, None]
        pull = (self.k * (length - self.rest))[:, None] * unit  # the spring's force on j [N]
        count = len(x)
        force = self.weight + np.stack([np.bincount(j, pull[:, c], count) - np.bincount(i, pull[:, c], count)
                                        for c in range(3)], axis=1)
        h = self.h
        if self.integrator == "symplectic_euler":  # v_n is leapfrog's v_(n-1/2): synchronise it
            v = v + (0.5 * h) * self.inv_mass[:, None] * force
        u = v[i] - v[j]
        along = (unit * u).sum(axis=1)
        hessian = float((self.k * (along ** 2 + (1.0 - self.rest / safe) * ((u * u).sum(axis=1) - along ** 2))).sum())
        inverse = float((self.inv_mass * (force * force).sum(axis=1)).sum())
        synchronised = total - kinetic + 0.5 * float((self.mass * (v * v).sum(axis=1)).sum())
        shadow = synchronised + h * h * (hessian / 12.0 - inverse / 24.0)
        return total, shadow, kinetic, stretch


def free_energy(model: Model) -> float:
    """The energy the release sets free [J]: the start's energy (at rest) over the lowest the cloth can reach,
    its static equilibrium under gravity with the pins held (:func:`~.under_load.static_equilibrium`), or
    zero without gravity (every spring at its rest length: the flat cloth). Gravity's potential has an arbitrary
    zero; this difference does not."""
    meter = EnergyMeter(model, "rk4", 0.0)
    x0 = model.particle_q.numpy().astype(np.float64)
    lowest = meter.potential(static_equilibrium(model).positions) if np.any(model.gravity) else 0.0
    return meter.potential(x0) - lowest


@functools.cache
def case_free_energy(case: Case, device: str) -> float:
    """:func:`free_energy` of ``case``'s cloth on ``device`` (once per case: the equilibrium of a 64² cloth takes
    seconds)."""
    return free_energy(battery_cloth(case, device))


@dataclass(frozen=True)
class RunResult:
    """One run of a case at a step (:func:`run`)."""

    factor: float  # the step over the advisor's P
    dt: float  # [s]
    blown: bool
    grows: bool
    excess: float  # the highest 1 s mean of the shadow energy over its start, over the free energy [-]
    peak: float  # the highest shadow energy over its start, over the free energy [-]
    raw_excess: float  # the highest energy H over its start, over the free energy [-]
    seconds: float  # wall time [s]
    cause: str = ""  # why it blew up: "non-finite", "torn" (a spring past TORN × its rest length) or "energy"
    until: float = math.nan  # the simulated time it reached [s] (its end, or the frame it blew up at)

    @property
    def ok(self) -> bool:
        return not (self.blown or self.grows)


def run(case: Case, integrator: str, dt: float, device, *, seconds: float = 10.0, factor: float = math.nan,
        precision: str = "float32", released: float | None = None, substeps: int = SUBSTEPS) -> RunResult:
    """Run ``case`` with ``integrator`` at step ``dt`` [s] for ``seconds`` and judge it (this module's docstring);
    ``released``: the energy to measure against [J] (default the case's :func:`free_energy`); the energy is read
    every ``substeps`` steps."""
    t0 = time.perf_counter()
    model = battery_cloth(case, device, precision=precision)
    meter = EnergyMeter(model, integrator, dt)
    released = case_free_energy(case, str(device)) if released is None else released
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=1.0 / (substeps * dt),
                    substeps=substeps, guard=None)
    frames = int(math.ceil(seconds / (substeps * dt)))
    raw_start, start, _, _ = meter(model.particle_q.numpy().astype(np.float64),
                                   model.particle_qd.numpy().astype(np.float64))
    shadows, raw_peak, cause = [], -math.inf, ""
    for _ in range(frames):
        sim.step_frame()
        x = sim.state.particle_q.numpy().astype(np.float64)
        v = sim.state.particle_qd.numpy().astype(np.float64)
        if not (np.isfinite(x).all() and np.isfinite(v).all()):
            cause = "non-finite"
            break
        total, shadow, _, stretch = meter(x, v)
        shadows.append(shadow)
        raw_peak = max(raw_peak, total)
        cause = "torn" if stretch > TORN else "energy" if shadow - start > BLOWN * released else ""
        if cause:
            break
    blown = bool(cause)
    window = max(1, int(round(MEAN_WINDOW / (substeps * dt))))
    if blown or len(shadows) < window:
        excess = peak = raw_excess = math.inf
    else:
        means = np.convolve(np.asarray(shadows) - start, np.full(window, 1.0 / window), mode="valid")
        excess, peak = float(means.max()) / released, (max(shadows) - start) / released
        raw_excess = (raw_peak - raw_start) / released
    return RunResult(factor, dt, blown, excess > GROWTH, excess, peak, raw_excess, time.perf_counter() - t0,
                     cause=cause, until=sim.time)


@dataclass
class CaseResult:
    """A case under one integrator: the advisor's verdict and the runs around it (:func:`measure`)."""

    case: Case
    integrator: str
    advice: Advice
    runs: list = field(default_factory=list)

    @property
    def passed_step(self) -> float:
        return self.advice.dt_passed

    def one_sided(self) -> bool:
        """No run at a step the advisor passes blew up or grew."""
        return all(r.ok for r in self.runs if r.factor <= 1.0)

    def tight(self) -> bool:
        """Some run at a step within 1/0.9 of the advisor's fails (or none is needed: no such run exists)."""
        above = [r for r in self.runs if 1.0 < r.factor <= 1.0 / 0.9 + 1e-9]
        return not above or any(not r.ok for r in above)

    def largest_ok(self) -> float:
        """The largest factor of the grid below which every run is fine [-]."""
        best = 0.0
        for r in sorted(self.runs, key=lambda r: r.factor):
            if not r.ok:
                break
            best = r.factor
        return best


def measure(case: Case, integrator: str, device, *, seconds: float = 10.0, factors=FACTORS,
            substeps: int = SUBSTEPS) -> CaseResult:
    """The advisor's verdict on ``case`` under ``integrator`` (its step P) and the runs at f · P for ``factors``
    (:func:`run`); none where it refuses every step (P = 0)."""
    model = battery_cloth(case, device)
    advice = advise(model, integrator, 1.0e-4, horizon=seconds)
    result = CaseResult(case, integrator, advice)
    if advice.dt_passed > 0.0:
        for f in factors:
            result.runs.append(run(case, integrator, f * advice.dt_passed, device, seconds=seconds, factor=f,
                                   substeps=substeps))
    return result


#: The bracket :func:`largest_step` starts from, × the advisor's step P, and its halvings.
BISECT_HIGH, BISECT_HALVINGS = 1.3, 5


@dataclass
class LargestStep:
    """Where the largest step that neither blows up nor grows lies (:func:`largest_step`).

    Attributes:
        holds: the largest step [s] whose run held (0: none did).
        fails: the smallest step [s] whose run blew up or grew (∞: none did).
        runs: every run, in the order made (their ``factor``: the step over the advisor's P).
    """

    holds: float
    fails: float
    runs: list = field(default_factory=list)


def largest_step(case: Case, integrator: str, device, passed: float, *, high: float = BISECT_HIGH,
                 halvings: int = BISECT_HALVINGS, seconds: float = 10.0, substeps: int = SUBSTEPS) -> LargestStep:
    """Bracket the largest step S [s] whose run of ``case`` (:func:`run`) neither blows up nor grows: runs at the
    advisor's step ``passed`` [s] and at ``high`` × it, then ``halvings`` bisections between the last that held and
    the first that failed (none where the run at ``passed`` fails or the one at ``high`` × it holds). The advisor is
    within 10 % of S where ``passed`` ≥ 0.9 × :attr:`LargestStep.fails`. Growth past the three-wave step is not
    monotone in the step (a resonance met at one step and missed at the next: the 8² folded cloth under gravity,
    symplectic Euler, grows at 1.010 √3/ω_max and holds at 1.005, 1.0125 and 1.015; the motion is chaotic, and a step
    4e-6 shorter turns which: bench/results/advisor_battery_bisect_cpu.md), so
    the bracket is where this bisection saw the change, not a guarantee for every step below it (:func:`scan` runs
    every step of a grid)."""
    result = LargestStep(0.0, math.inf)

    def holds(step: float) -> bool:
        outcome = run(case, integrator, step, device, seconds=seconds, factor=step / passed, substeps=substeps)
        result.runs.append(outcome)
        if outcome.ok:
            result.holds = max(result.holds, step)
        else:
            result.fails = min(result.fails, step)
        return outcome.ok

    if not holds(passed) or holds(high * passed):
        return result
    low, top = passed, high * passed
    for _ in range(halvings):
        middle = 0.5 * (low + top)
        low, top = (middle, top) if holds(middle) else (low, middle)
    return result


@dataclass
class StepScan:
    """The runs of a case at a grid of steps (:func:`scan`), and what they say of the largest step that neither blows
    up nor grows where holding is not monotone in the step: past the three-wave step the motion is chaotic, and a
    step can hold above one that fails (:func:`largest_step`), which a bisection may land on.

    Attributes:
        passed: the advisor's step P [s].
        runs: every run, by increasing step (their ``factor``: the step over P).
    """

    passed: float
    runs: list = field(default_factory=list)

    @property
    def fails(self) -> float:
        """The smallest sampled step [s] whose run blew up or grew (∞: none did)."""
        return min((r.dt for r in self.runs if not r.ok), default=math.inf)

    @property
    def holds(self) -> float:
        """S, the step a user can rely on as far as the grid tells: the largest sampled step [s] at and below which
        every sampled step held (0: the smallest failed). The first failure lies between it and :attr:`fails`."""
        return max((r.dt for r in self.runs if r.dt < self.fails), default=0.0)

    @property
    def lucky(self) -> float:
        """The largest sampled step [s] that held, past a failure or not (0: none did)."""
        return max((r.dt for r in self.runs if r.ok), default=0.0)

    def one_sided(self) -> bool:
        """Every sampled step at or below the advisor's held."""
        return self.holds >= self.passed

    def within(self, share: float = 0.9) -> str:
        """Whether P ≥ ``share`` × S with S = :attr:`holds`'s bracket [holds, fails): "yes" where P ≥ ``share`` ×
        :attr:`fails`, "no" where P < ``share`` × :attr:`holds`, "?" between (the grid too coarse to tell, or no
        sampled step failed)."""
        if self.passed >= share * self.fails:
            return "yes"
        return "no" if self.passed < share * self.holds else "?"


def scan(case: Case, integrator: str, device, passed: float, factors, *, seconds: float = 10.0,
         substeps: int = SUBSTEPS, report=None) -> StepScan:
    """Run ``case`` with ``integrator`` (:func:`run`) at every step f · ``passed`` [s] for ``factors``, smallest first;
    ``report``: called with each :class:`RunResult` as it ends (a long scan's progress)."""
    result = StepScan(passed)
    for f in sorted(factors):
        result.runs.append(run(case, integrator, f * passed, device, seconds=seconds, factor=f, substeps=substeps))
        if report is not None:
            report(result.runs[-1])
    return result


def omega_trace(case: Case, integrator: str, dt: float, device, *, seconds: float = 3.0,
                every: float = 1.0 / 120.0, iterations: int = 40) -> np.ndarray:
    """ω_max [rad/s] of the states a run of ``case`` with ``integrator`` at step ``dt`` [s] passes through: rows of
    (time [s], ω_max) every ``every`` [s] (rounded to whole steps) for ``seconds``, each by ``iterations`` power
    iterations warm-started from the last (as the advisor's dry run re-estimates, :func:`~.under_load.transient_peak`),
    float64, shape [samples, 2]. What the advisor's ω_max must bound: its verdict is on the run's states."""
    model = battery_cloth(case, device)
    k = _stiffness_values(model, None)
    iteration = PowerIteration(model, k, _power_iteration(model, k, None, 1000, 1.0e-4, 0).world_mode)
    substeps = max(1, round(every / dt))
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=1.0 / (substeps * dt),
                    substeps=substeps, guard=None)
    rows = []
    while sim.time < seconds:
        sim.step_frame()
        iteration.restart(np.ones(model.world_count, dtype=bool), max_iterations=iterations, tolerance=1.0e-4)
        for _ in range(iterations):
            iteration.iterate(sim.state.particle_q)
        rows.append((sim.time, math.sqrt(max(float(iteration.scalars.numpy()[0, PI_LAMBDA]), 0.0))))
    return np.asarray(rows, dtype=np.float64)


def exact_limit(device, *, n: int = 16) -> tuple[Advice, Advice]:
    """The exact-limit case: a 16² cloth with kd = ``EXACT`` · ke under explicit Euler, whose linear limit is τ
    itself (0.1 ms at every stiffness; 0.1 % below it where the swing's stretch adds transverse stiffness, which the
    springs' dampers do not damp): the advisor's verdicts at τ and at ``DAMPED_MARGIN`` of its limit."""
    case = Case(n, EXACT, "flat", True)
    model = battery_cloth(case, device)
    at = advise(model, "explicit_euler", EXACT, horizon=10.0)
    below = advise(model, "explicit_euler", 0.999 * DAMPED_MARGIN * at.dt_stable, horizon=10.0)
    return at, below


def table(results: list[CaseResult]) -> list[str]:
    """A markdown table of the results: the advisor's step, the runs' verdicts by factor, one-sided, tight."""
    factors = sorted({r.factor for res in results for r in res.runs}) or list(FACTORS)
    head = "| case | integrator | P [ms] | linear [ms] | " + " | ".join(f"{f:g}·P" for f in factors) + \
        " | one-sided | tight |"
    lines = [head, "|" + "---|" * (6 + len(factors))]
    for res in results:
        by = {r.factor: r for r in res.runs}
        cells = []
        for f in factors:
            r = by.get(f)
            cells.append("" if r is None else "blows up" if r.blown else
                         f"{'ok' if r.ok else 'grows'} {100 * r.excess:.2g} % ({100 * r.peak:.2g} %)")
        p = res.advice.dt_passed
        lines.append(f"| {res.case.label} | {res.integrator} | {p * 1e3:.4g} | {res.advice.dt_stable * 1e3:.4g} | "
                     + " | ".join(cells) + f" | {'yes' if res.one_sided() else 'NO'} | "
                     f"{'yes' if res.tight() else 'no'} |")
    return lines
