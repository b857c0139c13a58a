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
from dataclasses import dataclass, field

import numpy as np

from ..core.builder import ModelBuilder, SpringMaterial
from ..core.integrators import make_integrator
from ..core.model import Model
from ..core.simulator import Simulator
from .advisor import Advice, advise, judged_past, shared_estimates
from .stability import DAMPED_MARGIN
from ..kernels.stability import PI_LAMBDA
from .omega import PowerIteration, _power_iteration, _stiffness_values
from .step_trial import TRIAL_SUBSTEPS, TrialRun, free_energy, trial_run
from .step_trial import BLOWN, GROWTH, MEAN_WINDOW, TORN, EnergyMeter  # noqa: F401  (the battery's criterion, re-exported)

#: The integrators whose passes are measured for one-sidedness and tightness, and those that rely on damping.
CONSERVATIVE = ("symplectic_euler", "velocity_verlet", "rk4")
DISSIPATIVE = ("explicit_euler", "midpoint")
#: Light damping: kd = LIGHT · ke [s].
LIGHT = 1.0e-5
#: The exact-limit case's damping: kd = EXACT · ke [s] (explicit Euler's limit is then τ itself, 0.1 ms).
EXACT = 1.0e-4
#: Step factors of the runs, around the advisor's step P (1.0: P itself; 1.111 = 1/0.9).
FACTORS = (0.8, 0.9, 1.0, 1.05, 1.111, 1.25, 1.5)
SUBSTEPS = TRIAL_SUBSTEPS  # steps per output frame (energy read once a frame)
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


@functools.cache
def case_free_energy(case: Case, device: str) -> float:
    """:func:`free_energy` of ``case``'s cloth on ``device`` (once per case: the equilibrium of a 64² cloth takes
    seconds)."""
    return free_energy(battery_cloth(case, device))


#: One run of a case at a step, judged.
RunResult = TrialRun


def run(case: Case, integrator: str, dt: float, device, *, seconds: float = 10.0, factor: float = math.nan,
        precision: str = "float32", released: float | None = None, substeps: int = SUBSTEPS) -> RunResult:
    """Run ``case`` with ``integrator`` at step ``dt`` [s] for ``seconds`` and judge it (:func:`~.step_trial.trial_run`,
    as the advisor's trials do); ``released``: the energy to measure against [J] (default the case's
    :func:`~.step_trial.free_energy`); the energy is read every ``substeps`` steps."""
    model = battery_cloth(case, device, precision=precision)
    released = case_free_energy(case, str(device)) if released is None else released
    return trial_run(model, integrator, dt, seconds=seconds, released=released, substeps=substeps, factor=factor)


#: The ladder of steps the battery asks the strict verdict about past the advisor's step P: P · LADDER^k, k = 1, 2, …
#: With the trial's second run at (1 + TRIAL_MARGIN) × a rung, the last rung passed Q is within 1 / (LADDER (1 +
#: TRIAL_MARGIN)) = 0.934 of the first step that fails, where holding is monotone in the step.
LADDER = 1.05


def strict_step(model: Model, integrator: str, advice: Advice, *, seconds: float) -> tuple[float, list]:
    """The largest step Q [s] ``--strict`` passes on ``model`` with ``integrator``, from the advisor's ``advice`` (its
    step P, :attr:`~.advisor.Advice.dt_passed`) up a ladder of steps P · ``LADDER``^k, each judged with its trial runs
    over ``seconds`` (:func:`~.advisor.advise` with ``trial``), to the first it refuses; and the verdicts on the
    ladder's rungs, first to last. Q is P where the first rung is refused or no trial judges it (past
    ``TRIAL_CEILING`` × the linear limit, or a scene whose energy the trial cannot measure)."""
    passed, rungs = advice.dt_passed, []
    if not passed > 0.0:
        return passed, rungs
    with shared_estimates():
        step = passed * LADDER
        while judged_past(integrator, step, advice.dt_passed, float(advice.world_dt_stable.min())):
            verdict = advise(model, integrator, step, horizon=seconds, trial=True)
            rungs.append(verdict)
            if not verdict.stable:
                break
            passed, step = step, step * LADDER
    return passed, rungs


@dataclass
class CaseResult:
    """A case under one integrator: the advisor's verdict, the largest step ``--strict`` passes and the runs around it
    (:func:`measure`).

    Attributes:
        case, integrator: what was measured.
        advice: the advisor's verdict (its step P: :attr:`~.advisor.Advice.dt_passed`).
        strict: Q, the largest step ``--strict`` passes [s] (:func:`strict_step`).
        rungs: the strict verdicts on the ladder past P.
        runs: the runs at factors × Q.
    """

    case: Case
    integrator: str
    advice: Advice
    strict: float = math.nan
    rungs: list = field(default_factory=list)
    runs: list = field(default_factory=list)

    @property
    def passed_step(self) -> float:
        """The largest step ``--strict`` passes, Q [s]."""
        return self.strict

    def one_sided(self) -> bool:
        """No run at a step ``--strict`` passes blew up or grew."""
        return all(r.ok for r in self.runs if r.factor <= 1.0)

    def tight(self) -> bool:
        """Some run at a step within 1/0.9 of Q fails (or none is needed: no such run exists)."""
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
            substeps: int = SUBSTEPS, ladder: bool = True) -> CaseResult:
    """The advisor's verdict on ``case`` under ``integrator`` (its step P), the largest step ``--strict`` passes, Q
    (:func:`strict_step`; P without ``ladder``), and the runs at f · Q for ``factors`` (:func:`run`); none where it
    refuses every step (Q = 0)."""
    model = battery_cloth(case, device)
    with shared_estimates():  # one static solve and dry run for the verdicts on P and on the ladder
        advice = advise(model, integrator, 1.0e-4, horizon=seconds)
        strict, rungs = strict_step(model, integrator, advice, seconds=seconds) if ladder else (advice.dt_passed, [])
    result = CaseResult(case, integrator, advice, strict, rungs)
    if strict > 0.0:
        for f in factors:
            result.runs.append(run(case, integrator, f * strict, device, seconds=seconds, factor=f,
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
    head = "| case | integrator | P [ms] | linear [ms] | Q [ms] | " + " | ".join(f"{f:g}·Q" for f in factors) + \
        " | one-sided | tight |"
    lines = [head, "|" + "---|" * (7 + len(factors))]
    for res in results:
        by = {r.factor: r for r in res.runs}
        cells = []
        for f in factors:
            r = by.get(f)
            cells.append("" if r is None else "blows up" if r.blown else
                         f"{'ok' if r.ok else 'grows'} {100 * r.excess:.2g} % ({100 * r.peak:.2g} %)")
        p = res.advice.dt_passed
        lines.append(f"| {res.case.label} | {res.integrator} | {p * 1e3:.4g} | {res.advice.dt_stable * 1e3:.4g} | "
                     f"{res.strict * 1e3:.4g} | "
                     + " | ".join(cells) + f" | {'yes' if res.one_sided() else 'NO'} | "
                     f"{'yes' if res.tight() else 'no'} |")
    return lines
