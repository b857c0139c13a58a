"""Trial runs of a scene at a step: whether its run blows up or grows, measured on the energy the integrator conserves.

Between the three-wave step and the linear limit (:func:`~.stability.passed_step`) the theory cannot say whether a
cloth's top modes feed a resonance (three waves whose phases per step add up to 2π): whether a run at such a step
grows is a matter of how its motion spreads into those modes, which differs between scenes and, near the edge, between
steps a few per mille apart (``bench/results/advisor_battery_bisect_cpu.md``). Where the advisor's verdict is asked
for such a step and the scene's energy can be measured exactly (:func:`trial_scope`), it runs the scene itself
(:func:`try_step`): at the step and at ``1 + TRIAL_MARGIN`` times it, each for the run's horizon, and passes the step
when both hold.

A run

* **blows up** when its state turns non-finite, a spring passes ``TORN`` × its rest length, or its energy rises
  above its start by ``BLOWN`` × F, where F is the energy the start sets free (:func:`free_energy`: its energy over
  its static equilibrium's, which gravity's arbitrary zero leaves alone);
* **grows** when its energy, averaged over ``MEAN_WINDOW`` (1 s), rises more than ``GROWTH`` = 1 % of F above its
  start within the run. Symplectic Euler and velocity Verlet keep a shadow energy H̃, not H (:class:`EnergyMeter`):
  H itself swings by O(h) (O(h²)) about it however stable the step (12 % of F within 10 s on an undamped 16² cloth
  released flat at its three-wave step, symplectic Euler), so the measure is H̃ through its O(h²) terms (error O(h⁴));
  the 1 s mean removes the residual's swing. A run past the step that holds crosses +1 % seconds before it turns
  non-finite. RK4 has no shadow energy: its H (which it dissipates at large steps).

The energy is summed in float64 on the host every ``TRIAL_SUBSTEPS`` steps. Measurements of the criterion:
``bench/results/advisor_battery_cpu.md``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..core.integrators import make_integrator
from ..core.model import Model
from ..core.simulator import Simulator
from ..checks import format_duration
from ..kernels.spring_laws import SpringLaw
from ..core.records import STABILIZER_INPUTS
from .omega import free_particles
from .under_load import static_equilibrium

TRIAL_SUBSTEPS = 10  # steps per read of the energy
GROWTH = 0.01  # of the free energy: growth (the module docstring)
MEAN_WINDOW = 1.0  # [s], the shadow energy's moving mean
BLOWN = 10.0  # of the free energy
TORN = 10.0  # × rest length
#: The second trial run's step over the first's: a step passes when the runs at it and at (1 + TRIAL_MARGIN) × it
#: hold. Past the three-wave step growth is not monotone in the step (a resonance met at one step and missed at the
#: next); the second run asks that the step not sit just below one that grows, and that the verdict not rest on one
#: chaotic run's round-off alone.
TRIAL_MARGIN = 0.02
#: The largest step a trial is run for, × the linear limit at the dry run's peak ω_max: a run at a larger one is
#: refused without a trial (the largest steps that held in the battery: 1.012 × it for symplectic Euler and Verlet,
#: 1.159 × it for RK4, whose peak is a transient of the swing).
TRIAL_CEILING = 1.25


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
    Verlet) and H̃'s as h⁴ for both. Dampers and drag are not in H̃: they only take energy out. Hooke springs and
    gravity only (:func:`trial_scope`).
    """

    def __init__(self, model: Model, integrator: str, dt: float):
        self.integrator, self.h = integrator, float(dt)
        self.pairs = model.spring_indices.numpy()
        self.rest = model.spring_rest_length.numpy().astype(np.float64)
        self.k = model.spring_stiffness.numpy()[0].astype(np.float64)
        self.mass = model.particle_mass.numpy()[0].astype(np.float64)
        self.inv_mass = np.where(free_particles(model)[0], 1.0 / self.mass, 0.0)
        self.weight = self.mass[:, None] * np.asarray(model.gravity, dtype=np.float64)[None, :]  # m g [N]
        self.stretchable = self.rest > 0.0  # the springs a tear is measured on (a zero rest length has no stretch)

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
        stretch = float((length[self.stretchable] / self.rest[self.stretchable]).max(initial=1.0))
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
    """The energy the start sets free [J]: its energy (kinetic and potential) over the lowest the model can reach,
    its static equilibrium under gravity with the pins held (:func:`~.under_load.static_equilibrium`), or zero
    without gravity (every spring at its rest length). Gravity's potential has an arbitrary zero; this difference
    does not. Without pins a model under gravity falls as a whole, which frees no energy into its springs: its start's
    kinetic and elastic energy."""
    meter = EnergyMeter(model, "rk4", 0.0)
    x0 = model.particle_q.numpy().astype(np.float64)
    v0 = model.particle_qd.numpy().astype(np.float64)
    total = meter(x0, v0)[0]
    if not np.any(model.gravity):
        return total
    if free_particles(model)[0].all():  # nothing holds it: gravity's part is the fall of the whole
        return total + float((meter.weight * x0).sum())
    return total - meter.potential(static_equilibrium(model).positions)


#: A free energy below this share of the scene's energy scale (:func:`energy_scale`) is round-off: a start at rest at
#: its equilibrium, which a trial cannot judge against (its every wobble would be growth).
FREE_ENERGY_FLOOR = 1.0e-6


def energy_scale(model: Model) -> float:
    """The scene's energy scale [J]: its springs' ½ k L², its weight across its extent and its start's kinetic energy
    (what :data:`FREE_ENERGY_FLOOR` is a share of)."""
    meter = EnergyMeter(model, "rk4", 0.0)
    x0 = model.particle_q.numpy().astype(np.float64)
    v0 = model.particle_qd.numpy().astype(np.float64)
    extent = float(np.linalg.norm(x0.max(axis=0) - x0.min(axis=0))) if len(x0) else 0.0
    weight = float(np.linalg.norm(meter.weight, axis=1).sum())
    return (0.5 * float((meter.k * meter.rest ** 2).sum()) + weight * extent
            + 0.5 * float((meter.mass * (v0 * v0).sum(axis=1)).sum()))


def trial_scope(model: Model, control=None) -> str:
    """Why a trial run cannot judge ``model`` ("" where it can): :class:`EnergyMeter` measures one world of Hooke
    springs with their dampers under gravity and drag, with pins held still, and nothing else may put energy in
    (contacts, loads from outside, other element families, stabilisers, animated inputs, pins moving at the start,
    wind)."""
    if model.world_count != 1:
        return f"{model.world_count} worlds"
    if model.spring_count == 0:
        return "no springs"
    others = [f.name for f in model.families if f.name != "springs"]
    if others:
        return "element families besides springs (" + ", ".join(others) + ")"
    if model.spring_material_law != SpringLaw():
        return "spring laws besides Hooke's"
    stabilizers = [name for name in STABILIZER_INPUTS if model.stabilizers.enabled(name)]
    if stabilizers:
        return "stabilisers (" + ", ".join(stabilizers) + ")"
    if model.shape_count:
        return "contacts"
    if model.self_contact is not None:
        return "self-collision"
    if control is not None and control.particle_force is not None:
        return "the control's external force"
    if model.pin_groups is not None or model.track_table.tracks or model.emitters:
        return "driven pins, animated inputs or emitters"
    pinned = ~free_particles(model)[0]
    if pinned.any() and np.any(model.particle_qd.numpy()[pinned]):
        return "pins moving at the start"
    if np.any(model.world_values("wind")):
        return "wind"
    return ""


@dataclass(frozen=True)
class TrialRun:
    """One run of a scene at a step, judged (:func:`trial_run`).

    Attributes:
        factor: the step over a reference step of the caller's (NaN: none) [-].
        dt: the step [s].
        blown: whether it blew up (the module docstring).
        grows: whether it grew.
        excess: the highest 1 s mean of the shadow energy over its start, over the free energy [-] (∞ where blown).
        peak: the highest shadow energy over its start, over the free energy [-].
        raw_excess: the highest energy H over its start, over the free energy [-].
        seconds: wall time [s].
        cause: why it blew up: "non-finite", "torn" (a spring past ``TORN`` × its rest length) or "energy".
        until: the simulated time it reached [s] (its end, or the read it blew up at).
    """

    factor: float
    dt: float
    blown: bool
    grows: bool
    excess: float
    peak: float
    raw_excess: float
    seconds: float
    cause: str = ""
    until: float = math.nan

    @property
    def ok(self) -> bool:
        return not (self.blown or self.grows)

    def describe(self) -> str:
        """What the run did, as a clause."""
        if self.blown:
            what = {"non-finite": "turned non-finite", "torn": f"tore a spring past {TORN:g}× its rest length",
                    "energy": f"gained {BLOWN:g}× the free energy"}[self.cause]
            return f"at {format_duration(self.dt)} it {what} at t = {self.until:.3g} s"
        verb = "grew" if self.grows else "held"
        return f"at {format_duration(self.dt)} it {verb} ({100.0 * self.excess:+.2g} % of the free energy)"


def trial_run(model: Model, integrator: str, dt: float, *, seconds: float, released: float, control=None,
              substeps: int = TRIAL_SUBSTEPS, factor: float = math.nan) -> TrialRun:
    """Run ``model`` from its initial state with ``integrator`` at step ``dt`` [s] for ``seconds`` and judge it against
    the energy ``released`` [J] (> 0; the module docstring); the energy is read every ``substeps`` steps (a run
    shorter than ``MEAN_WINDOW`` is judged on its whole mean)."""
    if not released > 0.0:
        raise ValueError(f"a trial needs energy to judge against, got released = {released} J")
    t0 = time.perf_counter()
    meter = EnergyMeter(model, integrator, dt)
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=1.0 / (substeps * dt),
                    substeps=substeps, control=control, guard=None)
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
    window = min(max(1, int(round(MEAN_WINDOW / (substeps * dt)))), len(shadows))  # a shorter run: its whole mean
    if blown or not shadows:
        excess = peak = raw_excess = math.inf
    else:
        means = np.convolve(np.asarray(shadows) - start, np.full(window, 1.0 / window), mode="valid")
        excess, peak = float(means.max()) / released, (max(shadows) - start) / released
        raw_excess = (raw_peak - raw_start) / released
    return TrialRun(factor, dt, blown, excess > GROWTH, excess, peak, raw_excess, time.perf_counter() - t0,
                    cause=cause, until=sim.time)


@dataclass(frozen=True)
class StepTrial:
    """The trial of a step (:func:`try_step`): its runs, first to last, and the energy they are judged against.

    Attributes:
        dt: the step tried [s].
        seconds: each run's length [s].
        released: the free energy [J] (:func:`free_energy`).
        runs: the runs at ``dt`` and at (1 + ``TRIAL_MARGIN``) × it, in that order; the second is not run where the
            first fails.
    """

    dt: float
    seconds: float
    released: float
    runs: list = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return len(self.runs) == 2 and all(r.ok for r in self.runs)

    def describe(self) -> str:
        """The trial's outcome, as a clause."""
        done = "; ".join(r.describe() for r in self.runs)
        return (f"{len(self.runs)} trial run{'s' if len(self.runs) > 1 else ''} of this scene for {self.seconds:g} s "
                f"({done}; {100.0 * GROWTH:g} % of the {self.released:.3g} J its start sets free is growth)")


def try_step(model: Model, integrator: str, dt: float, *, seconds: float, released: float, control=None) -> StepTrial:
    """Try ``dt`` [s] on ``model`` (the module docstring): a run at ``dt``, then, if it held, one at
    (1 + ``TRIAL_MARGIN``) × ``dt``, each for ``seconds``, judged against the energy ``released`` [J]."""
    trial = StepTrial(dt, seconds, released)
    for step in (dt, (1.0 + TRIAL_MARGIN) * dt):
        trial.runs.append(trial_run(model, integrator, step, seconds=seconds, released=released, control=control,
                                    factor=step / dt))
        if not trial.runs[-1].ok:
            break
    return trial
