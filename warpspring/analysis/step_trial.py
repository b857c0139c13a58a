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

from ..core.guard_records import scene_suspects
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
    """The energy of each world's state, summed in float64 on the host, and the energy the integrator conserves.

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
    gravity only (:func:`trial_scope`); each world with its own stiffness, masses and gravity (``Model.world_values``).
    """

    def __init__(self, model: Model, integrator: str, dt: float):
        self.integrator, self.h = integrator, float(dt)
        self.worlds, self.count = model.world_count, model.particle_count
        self.pairs = model.spring_indices.numpy()
        self.rest = model.spring_rest_length.numpy().astype(np.float64)
        self.k = model.world_values("spring_stiffness")  # [N/m], shape [world_count, spring_count]
        self.mass = model.world_values("particle_mass")  # [kg], shape [world_count, particle_count]
        self.inv_mass = np.where(free_particles(model), 1.0 / self.mass, 0.0)
        self.weight = self.mass[:, :, None] * model.world_values("gravity")[:, None, :]  # m g [N]
        self.stretchable = self.rest > 0.0  # the springs a tear is measured on (a zero rest length has no stretch)

    def _split(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=np.float64).reshape(self.worlds, self.count, 3)

    def world_potentials(self, x: np.ndarray) -> np.ndarray:
        """Each world's U(x) = Σ ½ k (|d| - L)² - Σ m g·x [J], shape [world_count], of positions ``x`` [m], shape
        [world_count · particle_count, 3]."""
        x = self._split(x)
        d = np.linalg.norm(x[:, self.pairs[:, 0]] - x[:, self.pairs[:, 1]], axis=2)
        return 0.5 * (self.k * (d - self.rest) ** 2).sum(axis=1) - (self.weight * x).sum(axis=(1, 2))

    #: The most (world, spring) pairs one pass of :meth:`worlds_energy` holds (its float64 temporaries: ~50 MB each).
    CHUNK = 2_000_000

    def worlds_energy(self, x: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, ...]:
        """Each world's (H, H̃, kinetic energy [J], largest spring stretch |d|/L), float64 arrays of shape
        [world_count], of positions ``x`` [m] and velocities ``v`` [m/s], shape [world_count · particle_count, 3]
        (in chunks of worlds, ``CHUNK`` world-springs each)."""
        x, v = self._split(x), self._split(v)
        step = max(1, self.CHUNK // max(1, len(self.pairs)))
        parts = [self._energy(x[a:a + step], v[a:a + step], slice(a, a + step)) for a in range(0, self.worlds, step)]
        return tuple(np.concatenate(column) for column in zip(*parts))

    def _energy(self, x: np.ndarray, v: np.ndarray, rows: slice) -> tuple[np.ndarray, ...]:
        """:meth:`worlds_energy` of the worlds ``rows``, positions and velocities shape [worlds, particle_count, 3]."""
        k, mass, inv_mass, weight = self.k[rows], self.mass[rows], self.inv_mass[rows], self.weight[rows]
        worlds = len(x)
        i, j = self.pairs[:, 0], self.pairs[:, 1]
        delta = x[:, i] - x[:, j]
        length = np.linalg.norm(delta, axis=2)
        safe = np.maximum(length, 1e-12)
        kinetic = 0.5 * (mass * (v * v).sum(axis=2)).sum(axis=1)
        total = kinetic + 0.5 * (k * (length - self.rest) ** 2).sum(axis=1) - (weight * x).sum(axis=(1, 2))
        stretch = (length[:, self.stretchable] / self.rest[self.stretchable]).max(axis=1, initial=1.0)
        if self.integrator not in ("symplectic_euler", "velocity_verlet"):
            return total, total, kinetic, stretch
        unit = delta / safe[:, :, None]
        pull = (k * (length - self.rest))[:, :, None] * unit  # the spring's force on j [N]
        offsets = (np.arange(worlds) * self.count)[:, None]  # every world's springs in one bincount
        total_count, ends = worlds * self.count, ((offsets + i).ravel(), (offsets + j).ravel())
        force = weight + np.stack([np.bincount(ends[1], pull[:, :, c].ravel(), total_count)
                                   - np.bincount(ends[0], pull[:, :, c].ravel(), total_count)
                                   for c in range(3)], axis=1).reshape(worlds, self.count, 3)
        h = self.h
        if self.integrator == "symplectic_euler":  # v_n is leapfrog's v_(n-1/2): synchronise it
            v = v + (0.5 * h) * inv_mass[:, :, None] * force
        u = v[:, i] - v[:, j]
        along = (unit * u).sum(axis=2)
        hessian = (k * (along ** 2 + (1.0 - self.rest / safe) * ((u * u).sum(axis=2) - along ** 2))).sum(axis=1)
        inverse = (inv_mass * (force * force).sum(axis=2)).sum(axis=1)
        synchronised = total - kinetic + 0.5 * (mass * (v * v).sum(axis=2)).sum(axis=1)
        shadow = synchronised + h * h * (hessian / 12.0 - inverse / 24.0)
        return total, shadow, kinetic, stretch

    def __call__(self, x: np.ndarray, v: np.ndarray) -> tuple[float, float, float, float]:
        """(H, H̃, kinetic energy [J], largest spring stretch |d|/L) of a one-world model's positions ``x`` [m] and
        velocities ``v`` [m/s], float64, shape [particle_count, 3] (:meth:`worlds_energy` for several worlds)."""
        if self.worlds != 1:
            raise ValueError(f"the model has {self.worlds} worlds: use EnergyMeter.worlds_energy")
        return tuple(float(e[0]) for e in self.worlds_energy(x, v))


def world_free_energies(model: Model) -> np.ndarray:
    """The energy each world's start sets free [J], float64, shape [world_count]: its energy (kinetic and potential)
    over the lowest it can reach, its static equilibrium under gravity with the pins held
    (:func:`~.under_load.static_equilibrium`), or zero without gravity (every spring at its rest length). Gravity's
    potential has an arbitrary zero; this difference does not. Without pins a world under gravity falls as a whole,
    which frees no energy into its springs: its start's kinetic and elastic energy."""
    meter = EnergyMeter(model, "rk4", 0.0)
    x0 = model.particle_q.numpy().astype(np.float64)
    total = meter.worlds_energy(x0, model.particle_qd.numpy().astype(np.float64))[0]
    weighted = np.any(meter.weight != 0.0, axis=(1, 2))
    if not weighted.any():
        return total
    lowest = meter.world_potentials(static_equilibrium(model).positions)
    unpinned = free_particles(model).all(axis=1)  # nothing holds it: gravity's part is the fall of the whole
    gravity_part = (meter.weight * meter._split(x0)).sum(axis=(1, 2))
    return np.where(~weighted, total, np.where(unpinned, total + gravity_part, total - lowest))


def free_energy(model: Model) -> float:
    """:func:`world_free_energies` of a one-world model [J]."""
    return float(world_free_energies(model)[0])


#: A free energy below this share of the scene's energy scale (:func:`world_energy_scales`) is round-off: a start at rest at
#: its equilibrium, which a trial cannot judge against (its every wobble would be growth).
FREE_ENERGY_FLOOR = 1.0e-6


def world_energy_scales(model: Model) -> np.ndarray:
    """Each world's energy scale [J], float64, shape [world_count]: its springs' ½ k L², its weight across its extent
    and its start's kinetic energy (what :data:`FREE_ENERGY_FLOOR` is a share of)."""
    meter = EnergyMeter(model, "rk4", 0.0)
    x0 = meter._split(model.particle_q.numpy())
    v0 = meter._split(model.particle_qd.numpy())
    extent = np.linalg.norm(x0.max(axis=1) - x0.min(axis=1), axis=1) if model.particle_count else 0.0
    weight = np.linalg.norm(meter.weight, axis=2).sum(axis=1)
    return (0.5 * (meter.k * meter.rest ** 2).sum(axis=1) + weight * extent
            + 0.5 * (meter.mass * (v0 * v0).sum(axis=2)).sum(axis=1))


def trial_scope(model: Model, control=None) -> str:
    """Why a trial run cannot judge ``model`` ("" where it can): :class:`EnergyMeter` measures Hooke springs with their
    dampers under gravity and drag, with pins held still, in every world, and nothing else may put energy in
    (contacts, loads from outside, other element families, stabilisers, animated inputs, pins moving at the start,
    wind)."""
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
    suspects = scene_suspects(model, control=control)  # contacts, loads from outside, driven pins, emitters
    if suspects:
        return "; ".join(suspects)
    if model.track_table.tracks:  # (any other keyframe track: an element family's values, a collider's motion)
        return "animated values"
    pinned = ~free_particles(model).reshape(-1)
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
        world: the world the verdict is of: the one that blew up, or the one whose energy rose most.
        worlds: how many worlds the run had.
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
    world: int = 0
    worlds: int = 1

    @property
    def ok(self) -> bool:
        return not (self.blown or self.grows)

    def describe(self) -> str:
        """What the run did, as a clause (naming the world where the model has several)."""
        where = f" in world {self.world} of {self.worlds}" if self.worlds > 1 else ""
        if self.blown:
            what = {"non-finite": "turned non-finite", "torn": f"tore a spring past {TORN:g}× its rest length",
                    "energy": f"gained {BLOWN:g}× the free energy"}[self.cause]
            return f"at {format_duration(self.dt)} it {what}{where} at t = {self.until:.3g} s"
        verb = "grew" if self.grows else "held"
        most = " at most" if self.worlds > 1 and not self.grows else ""
        return f"at {format_duration(self.dt)} it {verb}{most} ({100.0 * self.excess:+.2g} % of the free energy{where})"


def _per_world(released, worlds: int) -> np.ndarray:
    """``released`` [J] (one value, or one per world) as one value per world, shape [worlds]."""
    values = np.asarray(released, dtype=np.float64)
    if values.ndim > 1 or values.size not in (1, worlds):
        raise ValueError(f"released must be one energy or one per world ({worlds}), got shape {values.shape}")
    return np.broadcast_to(values.reshape(-1), (worlds,))


def trial_run(model: Model, integrator: str, dt: float, *, seconds: float, released, control=None,
              substeps: int = TRIAL_SUBSTEPS, factor: float = math.nan) -> TrialRun:
    """Run ``model`` from its initial state with ``integrator`` at step ``dt`` [s] for ``seconds`` and judge each world
    against the energy its start sets free, ``released`` [J] (> 0; one value, or one per world: the module docstring);
    the energy is read every ``substeps`` steps (a run shorter than ``MEAN_WINDOW`` is judged on its whole mean). The
    verdict is the worst world's: the first to blow up, else the one whose energy rose most."""
    released = _per_world(released, model.world_count)
    if not (released > 0.0).all():
        raise ValueError(f"a trial needs energy to judge against in every world, got released = {released} J")
    t0 = time.perf_counter()
    meter = EnergyMeter(model, integrator, dt)
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=1.0 / (substeps * dt),
                    substeps=substeps, control=control, guard=None)
    frames = int(math.ceil(seconds / (substeps * dt)))
    raw_start, start, _, _ = meter.worlds_energy(model.particle_q.numpy(), model.particle_qd.numpy())
    shadows, raw_peak, cause, world = [], np.full(model.world_count, -math.inf), "", 0
    for _ in range(frames):
        sim.step_frame()
        x = sim.state.particle_q.numpy().astype(np.float64)
        v = sim.state.particle_qd.numpy().astype(np.float64)
        finite = np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1)
        if not finite.all():
            cause, world = "non-finite", int(np.argmin(finite.reshape(model.world_count, -1).all(axis=1)))
            break
        total, shadow, _, stretch = meter.worlds_energy(x, v)
        shadows.append(shadow)
        raw_peak = np.maximum(raw_peak, total)
        torn, gained = stretch > TORN, shadow - start > BLOWN * released
        if torn.any() or gained.any():
            cause, world = ("torn", int(np.argmax(torn))) if torn.any() else ("energy", int(np.argmax(gained)))
            break
    blown = bool(cause)
    window = min(max(1, int(round(MEAN_WINDOW / (substeps * dt)))), len(shadows))  # a shorter run: its whole mean
    if blown or not shadows:
        excess = peak = raw_excess = math.inf
    else:
        rise = np.asarray(shadows) - start  # [reads, worlds]
        means = np.stack([np.convolve(rise[:, w], np.full(window, 1.0 / window), mode="valid")
                          for w in range(model.world_count)], axis=1)
        shares = means.max(axis=0) / released
        world = int(np.argmax(shares))
        excess, peak = float(shares[world]), float(rise[:, world].max() / released[world])
        raw_excess = float((raw_peak[world] - raw_start[world]) / released[world])
    return TrialRun(factor, dt, blown, excess > GROWTH, excess, peak, raw_excess, time.perf_counter() - t0,
                    cause=cause, until=sim.time, world=world, worlds=model.world_count)


@dataclass(frozen=True)
class StepTrial:
    """The trial of a step (:func:`try_step`): its runs, first to last, and the energy they are judged against.

    Attributes:
        dt: the step tried [s].
        seconds: each run's length [s].
        released: each world's free energy [J] (:func:`world_free_energies`), float64, shape [world_count].
        runs: the runs at ``dt`` and at (1 + ``TRIAL_MARGIN``) × it, in that order; the second is not run where the
            first fails.
    """

    dt: float
    seconds: float
    released: np.ndarray
    runs: list = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return len(self.runs) == 2 and all(r.ok for r in self.runs)

    def describe(self) -> str:
        """The trial's outcome, as a clause."""
        done = "; ".join(r.describe() for r in self.runs)
        low, high = float(self.released.min()), float(self.released.max())
        free = (f"the {low:.3g} J its start sets free" if len(self.released) == 1 else
                f"the {low:.3g} J each world's start sets free" if f"{low:.3g}" == f"{high:.3g}" else
                f"what each world's start sets free, from {low:.3g} to {high:.3g} J")
        return (f"{len(self.runs)} trial run{'s' if len(self.runs) > 1 else ''} of this scene for {self.seconds:g} s "
                f"({done}; {100.0 * GROWTH:g} % of {free} is growth)")


def try_step(model: Model, integrator: str, dt: float, *, seconds: float, released, control=None) -> StepTrial:
    """Try ``dt`` [s] on ``model`` (the module docstring): a run at ``dt``, then, if it held, one at
    (1 + ``TRIAL_MARGIN``) × ``dt``, each for ``seconds``, judged against each world's free energy ``released`` [J]
    (one value or one per world)."""
    trial = StepTrial(dt, seconds, np.array(_per_world(released, model.world_count)))
    for step in (dt, (1.0 + TRIAL_MARGIN) * dt):
        trial.runs.append(trial_run(model, integrator, step, seconds=seconds, released=released, control=control,
                                    factor=step / dt))
        if not trial.runs[-1].ok:
            break
    return trial
