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
steps per output frame, so the step is any number). Every frame its energy is summed in float64 on the host:
kinetic, springs' ½ k (|d| - L)², gravity's m g z. A run

* **blows up** when its state turns non-finite, a spring passes ``TORN`` × its rest length, or the energy rises
  above its start by ``BLOWN`` × the motion's energy scale S;
* **grows** when its energy's highest value over its last ``WINDOW`` seconds exceeds its start by more than
  ``GROWTH`` (half) of S, S the largest kinetic energy of the first ``WINDOW`` seconds: the energy the release
  sets in motion. Not 1 %: symplectic Euler's own first-order error of the measured energy widens as the motion
  spreads into the cloth's higher modes and passes 1 % of S at any practical step (measured on the 16² flat
  case after 10 s: 1.5 % of S at 0.3 P, 3 % at 0.5 P, 12 % at P, rising with h and with time), while a run past
  the step that holds grows to 10 S and then turns non-finite (1.06 P). The table shows each run's excess.

A case passes when every run at f ≤ 1 neither blows up nor grows (one-sided) and some run at f ≤ 1/0.9 does
(tight: the advisor's step is within 10 % of the largest step that does neither, as far as the grid of factors
can tell). Explicit Euler and midpoint rely on damping: on undamped cloth the advisor must refuse every step
(P = 0) and recommend symplectic Euler or Verlet; on damped cloth its step must stay below their linear limit by
:data:`~.stability.DAMPED_MARGIN`, so that the step at the limit itself (the exact-limit case, kd = 1e-4 s · ke
under explicit Euler at dt = 0.1 ms) is refused.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..core.builder import ModelBuilder, SpringMaterial
from ..core.integrators import make_integrator
from ..core.model import Model
from ..core.simulator import Simulator
from .advisor import Advice, advise

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
WINDOW = 2.0  # [s], the first and the last window of a run compared
GROWTH = 0.5  # of the motion's energy S (see the module docstring: not the 1 % of the issue)
BLOWN = 100.0  # of S
TORN = 10.0  # × rest length
SPACING = 0.1  # [m]
PARTICLE_MASS = 1.0 / 256.0  # [kg]
STIFFNESS = {"structural": 1000.0, "shear": 200.0, "bend": 20.0}  # [N/m]
RELEASES = ("flat", "folded")


@dataclass(frozen=True)
class Case:
    """One cloth of the battery: n × n particles, kd/k ratio ``tau`` [s], ``release`` ("flat" or "folded"),
    ``gravity`` on or off."""

    n: int
    tau: float
    release: str
    gravity: bool

    @property
    def label(self) -> str:
        damping = "undamped" if self.tau == 0.0 else f"kd = {self.tau:g} s·ke"
        return f"{self.n}² {self.release}, {damping}, {'gravity' if self.gravity else 'no gravity'}"


def cases(sizes=(8, 16, 32, 64), taus=(0.0, LIGHT)) -> list[Case]:
    """Every case of the battery for ``sizes`` and ``taus``: flat with gravity, folded with and without (flat
    without gravity does not move)."""
    return [Case(n, tau, release, gravity) for n in sizes for tau in taus
            for release, gravity in (("flat", True), ("folded", True), ("folded", False))]


def battery_cloth(case: Case, device) -> Model:
    """The cloth of ``case`` (this module's docstring), finalized on ``device``. Folded: rows h-1-k (k = 0, 1, …,
    h = n // 2) lie under rows h+k one spacing below them, a U fold whose turn spans one spacing vertically, so
    that the structural and shear springs start at their rest lengths and only the bend springs across the fold
    start compressed (2s against √2 s)."""
    n = case.n
    builder = ModelBuilder(gravity=(0.0, 0.0, -9.81) if case.gravity else (0.0, 0.0, 0.0))
    families = {name: SpringMaterial(ke, case.tau * ke) for name, ke in STIFFNESS.items()}
    builder.add_cloth_grid(nx=n, ny=n, spacing=SPACING, origin=(0.0, 0.0, 1.0), particle_mass=PARTICLE_MASS,
                           pin=["top-left", "top-right"], **families)
    model = builder.finalize(device)
    if case.release == "folded":  # the rest lengths stay the flat grid's
        q = model.particle_q.numpy().reshape(n, n, 3)
        h = n // 2
        for k in range(h):
            q[h - 1 - k, :, 1] = SPACING * (h + k)
            q[h - 1 - k, :, 2] = 1.0 - SPACING
        model.particle_q.assign(np.ascontiguousarray(q.reshape(-1, 3)))
    return model


def energy(model: Model, x: np.ndarray, v: np.ndarray) -> tuple[float, float, float]:
    """(total, kinetic, largest spring stretch |d|/L) of one world's state, float64: kinetic + ½ k (|d| - L)² +
    m g z [J]."""
    pairs = model.spring_indices.numpy()
    rest = model.spring_rest_length.numpy().astype(np.float64)
    k = model.spring_stiffness.numpy()[0].astype(np.float64)
    mass = model.particle_mass.numpy()[0].astype(np.float64)
    g = np.asarray(model.gravity, dtype=np.float64)
    d = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    kinetic = 0.5 * float((mass * (v * v).sum(axis=1)).sum())
    total = kinetic + 0.5 * float((k * (d - rest) ** 2).sum()) - float((mass * (x @ g)).sum())
    return total, kinetic, float((d / rest).max())


@dataclass(frozen=True)
class RunResult:
    """One run of a case at a step (:func:`run`)."""

    factor: float  # the step over the advisor's P
    dt: float  # [s]
    blown: bool
    grows: bool
    excess: float  # late-window energy peak minus early-window peak, over S
    seconds: float  # wall time [s]

    @property
    def ok(self) -> bool:
        return not (self.blown or self.grows)


def run(case: Case, integrator: str, dt: float, device, *, seconds: float = 10.0, factor: float = math.nan
        ) -> RunResult:
    """Run ``case`` with ``integrator`` at step ``dt`` [s] for ``seconds`` and judge it (this module's docstring)."""
    t0 = time.perf_counter()
    model = battery_cloth(case, device)
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=1.0 / (SUBSTEPS * dt),
                    substeps=SUBSTEPS, guard=None)
    frames = int(math.ceil(seconds / (SUBSTEPS * dt)))
    window = max(1, int(round(WINDOW / (SUBSTEPS * dt))))
    start, _, _ = energy(model, model.particle_q.numpy().astype(np.float64), model.particle_qd.numpy().astype(np.float64))
    totals, kinetics, blown = [], [], False
    for _ in range(frames):
        sim.step_frame()
        x = sim.state.particle_q.numpy().astype(np.float64)
        v = sim.state.particle_qd.numpy().astype(np.float64)
        if not (np.isfinite(x).all() and np.isfinite(v).all()):
            blown = True
            break
        total, kinetic, stretch = energy(model, x, v)
        totals.append(total)
        kinetics.append(kinetic)
        scale = max(kinetics[:window])
        if stretch > TORN or total - start > BLOWN * max(scale, 1e-12):
            blown = True
            break
    scale = max(kinetics[:window], default=0.0)
    if blown or len(totals) < 3 * window:
        excess = math.inf
    else:  # the last window's peak over the start
        excess = (max(totals[-window:]) - start) / max(scale, 1e-12)
    return RunResult(factor, dt, blown, excess > GROWTH, excess, time.perf_counter() - t0)


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


def measure(case: Case, integrator: str, device, *, seconds: float = 10.0, factors=FACTORS) -> CaseResult:
    """The advisor's verdict on ``case`` under ``integrator`` (its step P) and the runs at f · P for ``factors``;
    none where it refuses every step (P = 0)."""
    model = battery_cloth(case, device)
    advice = advise(model, integrator, 1.0e-4, horizon=seconds)
    result = CaseResult(case, integrator, advice)
    if advice.dt_passed > 0.0:
        for f in factors:
            result.runs.append(run(case, integrator, f * advice.dt_passed, device, seconds=seconds, factor=f))
    return result


def exact_limit(device, *, n: int = 16) -> tuple[Advice, Advice]:
    """The exact-limit case: a 16² cloth with kd = ``EXACT`` · ke under explicit Euler, whose linear limit is τ
    itself (0.1 ms at every stiffness): the advisor's verdicts at the limit and at ``DAMPED_MARGIN`` of it."""
    case = Case(n, EXACT, "flat", True)
    model = battery_cloth(case, device)
    at = advise(model, "explicit_euler", EXACT, horizon=10.0)
    below = advise(model, "explicit_euler", 0.9 * EXACT * 0.999, horizon=10.0)
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
            cells.append("" if r is None else ("ok" if r.ok else ("blows up" if r.blown else f"grows {r.excess:.2g}")))
        p = res.advice.dt_passed
        lines.append(f"| {res.case.label} | {res.integrator} | {p * 1e3:.4g} | {res.advice.dt_stable * 1e3:.4g} | "
                     + " | ".join(cells) + f" | {'yes' if res.one_sided() else 'NO'} | "
                     f"{'yes' if res.tight() else 'no'} |")
    return lines
