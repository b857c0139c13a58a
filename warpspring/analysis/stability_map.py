"""The stability map: largest stable steps measured by simulation, beside the theory and the advisor.

Three studies, each running the registry's integrator classes on real models in float64:

1. **One damped spring** per ζ ∈ {0, 0.01, 0.1, 1}: the largest stable ωh, against
   :func:`~warpspring.analysis.stability.stable_omega_h`. Many independent oscillators (a particle on a spring to a
   pinned anchor, moving along the spring, so exactly linear) run side by side in one model at h = 1 s,
   oscillator j with k = m (ωh)ⱼ² and kd = 2ζ m (ωh)ⱼ. A first run spans ωh = 10⁻² … 10² log-spaced; each
   further run subdivides every ζ's bracket [largest stable, first unstable] (bisection, many points at a
   time).
2. **The hanging cloth** of ANCHORS.md at a small size (0.1 m spacing, 0.1 kg per particle, structural +
   shear + bend springs with kd = ``CLOTH_DAMPING_RATIO`` · ke, the two top corners pinned) over
   ke = 10⁻² … 10⁷ N/m: the largest stable step of each integrator by bisection on dt (one run per
   step), against the advisor's prediction from the power-iteration ω_max. Gravity is off and the flat
   cloth starts from rest, displaced in its plane by 10⁻⁸ of its spacing (:func:`perturbed_state`): the
   runs follow the linearisation the advisor analyses, and growth means numerical instability, never the
   cloth falling. (Out-of-plane modes have no stiffness about a flat, unstretched cloth; in-plane
   displacements never excite them.)
3. **The seed observation** "a 4th-order Runge-Kutta cloth at a fixed step became unstable for k > 22".
   Its layout is not recorded; :func:`seed_cloth` assumes the public Unity project
   Darkgrouptw/Cloth-Simulation. The advisor gives the fixed step at which RK4's threshold on that layout
   is k = 22 N/m; bisection on k by simulation at that step then locates the threshold.

**Growth test.** After every step a kernel records each spring's stretch e and stretch rate ė; a run is
reduced to E = Σₛ kₛ (eₛ² + ėₛ²/Ω²) per oscillator or per cloth, Ω² = Σkₛ / Σμₛ over its springs (μₛ a
spring's reduced mass). For one spring E is twice its mechanical energy; for the cloth both terms are
quadratic forms in the stiffness matrix, so the modes of a Rayleigh-damped network add up in E without
cross terms (no beats). A run of S steps is unstable when E turns non-finite or exceeds ``ENERGY_CAP``
times its first value (reached while the springs are still linear, see ``CLOTH_PERTURBATION``), or
when the mean of E over its last quarter exceeds the mean over its second quarter by more than
(1 + ``GROWTH``)²; it is stable when that ratio is ≤ 1 or E decayed below ``DECAYED`` of its start.
Ratios in between are undecided: the run goes on to 2S, 4S, … (``MapPlan.doublings`` times) and is
called stable if still undecided. Window means rather than maxima: a symplectic method near its limit
moves on an elongated invariant ellipse, E swinging by large factors within each period; sampled
extremes in two windows can differ by those factors when the rotation per step is near a rational
angle, while window means agree to within a few 1/S. The test sees growth faster than about
(1 + GROWTH)^(4/S) per step, so explicit Euler and midpoint on an undamped spring (unstable at every
step in theory) show growth only above a floor set by S, and weakly damped cloths (small ke, where ζ at
ω_max is ~10⁻²) only above their limit by a few per cent.

Every measured value is a bracket [largest value found stable, smallest found unstable]. Steps run as
CUDA or CPU graphs of ``BLOCK`` steps.
"""

from __future__ import annotations

import datetime
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..core.builder import ModelBuilder, SpringMaterial
from ..errors import ConfigError
from ..core.forces import eval_forces
from ..core.integrators import INTEGRATORS, ImplicitEuler, Integrator
from ..kernels.stability import spring_motion_kernel
from ..core.model import Model
from ..core.state import State
from ..core.stepper import StepHook, Stepper
from .advisor import advise
from .engines import map_jobs
from .omega import free_particles, world_dynamic_inv_mass
from .stability import network_stable_step, stable_omega_h

#: Growth threshold of a run: unstable when its late mean E exceeds its early one by (1 + GROWTH)².
GROWTH = 0.01
#: A run whose E exceeds its first value by this factor is unstable (10⁴ in amplitude).
ENERGY_CAP = 1.0e8
#: A run whose early mean E is below this fraction of its first value has decayed to round-off: stable.
DECAYED = 1.0e-12
#: Steps per captured graph.
BLOCK = 16
#: The single springs: mass [kg], rest length [m] and initial stretch [m]. The particle stays on the
#: spring's axis, so the spring is exactly linear until the particle reaches the anchor; ENERGY_CAP
#: stops a run 10² amplitudes before that.
SPRING_MASS, SPRING_REST, SPRING_AMPLITUDE = 1.0, 1.0, 1.0e-6
#: Range of ωh spanned by the first single-spring run.
OMEGA_H_RANGE = (1.0e-2, 1.0e2)
#: The cloth: kd / ke [s] of every spring (the ANCHORS cloth: 10 N·s/m on 10³ N/m), spacing [m] and
#: particle mass [kg].
CLOTH_DAMPING_RATIO, CLOTH_SPACING, CLOTH_MASS = 1.0e-2, 0.1, 0.1
#: RMS in-plane displacement of the cloth's start, as a fraction of its spacing. An unstable run must hit
#: ENERGY_CAP while the springs are still linear: past strains of ~10⁻² their geometric nonlinearity can
#: saturate the growth into a large but bounded motion, whose window means no longer grow. From 10⁻⁸ the
#: cap is reached at strains of ~10⁻⁴ (and the start is still ~10⁶ roundings of a float64 coordinate).
CLOTH_PERTURBATION = 1.0e-8
#: The assumed seed (Darkgrouptw/Cloth-Simulation): particles per side, spacing [m], particle mass [kg],
#: spring damping [N·s/m], and the observed RK4 threshold [N/m].
SEED_SIZE, SEED_SPACING, SEED_MASS, SEED_DAMPING, SEED_THRESHOLD = 10, 0.6, 1.0, 1.5, 22.0
#: Unity's default fixed time step [s], compared with the inferred seed step.
UNITY_FIXED_STEP = 0.02


@dataclass(frozen=True)
class MapPlan:
    """How much of the map to measure.

    Attributes:
        name: "quick" or "full".
        zetas: damping ratios of the single-spring study.
        spring_points: oscillators per ζ in each single-spring run.
        spring_rounds: single-spring runs (the first spans ``OMEGA_H_RANGE``, each further one subdivides).
        spring_steps: steps S of a single-spring run.
        cloth_size: particles per cloth side.
        cloth_stiffness: ke values [N/m] of the cloth study.
        cloth_steps: steps S of a cloth run.
        cloth_resolution: bisection on dt stops when the bracket's ratio is below 1 + this.
        implicit_steps: steps S of an implicit-Euler cloth run (tested at a few steps, not bisected).
        seed_steps: steps S of a seed run.
        seed_resolution: bisection on k stops when the bracket's ratio is below 1 + this.
        doublings: how often an undecided run is continued to twice its length.
    """

    name: str
    zetas: tuple = (0.0, 0.01, 0.1, 1.0)
    spring_points: int = 48
    spring_rounds: int = 3
    spring_steps: int = 16384
    cloth_size: int = 10
    cloth_stiffness: tuple = tuple(10.0**e for e in range(-2, 8))
    cloth_steps: int = 8192
    cloth_resolution: float = 0.005
    implicit_steps: int = 512
    seed_steps: int = 8192
    seed_resolution: float = 0.002
    doublings: int = 2


FULL = MapPlan(name="full")
QUICK = MapPlan(
    name="quick",
    spring_points=24,
    spring_steps=4096,
    cloth_stiffness=(1.0e-2, 1.0e1, 1.0e4, 1.0e7),
    cloth_steps=2048,
    cloth_resolution=0.01,
    implicit_steps=128,
    seed_steps=2048,
    seed_resolution=0.01,
)


@dataclass(frozen=True)
class Bracket:
    """A measured stability limit: ``low`` found stable, ``high`` the smallest value above it found
    unstable, after ``runs`` runs. ``low`` = 0: unstable at every tested value (``high`` the smallest
    tested); ``high`` = ∞: stable at every tested value (``low`` the largest tested)."""

    low: float
    high: float
    runs: int

    @property
    def value(self) -> float:
        """The geometric midpoint; ``low`` when ``high`` is ∞, 0 when ``low`` is."""
        if self.low == 0.0 or math.isinf(self.high):
            return self.low
        return math.sqrt(self.low * self.high)

    @property
    def two_sided(self) -> bool:
        """Whether both ends were found (a stable value and an unstable one above it)."""
        return self.low > 0.0 and math.isfinite(self.high)

    def text(self) -> str:
        """"midpoint ± half-width", or "< high" / "> low" for one-sided brackets."""
        if self.low == 0.0:
            return f"< {self.high:.4g}"
        if math.isinf(self.high):
            return f"> {self.low:.4g}"
        return f"{self.value:.4g} ± {(self.high - self.low) / 2:.1g}"


@dataclass(frozen=True)
class SpringLimit:
    """Largest stable ωh of one integrator on one damped spring.

    Attributes:
        integrator: registry name.
        zeta: damping ratio ζ [-].
        theory: :func:`~warpspring.analysis.stability.stable_omega_h` [-] (for adaptive integrators: the fixed-step
            limit of their tableau).
        measured: bracket of ωh [-] from simulation; ``None`` for adaptive integrators (they choose their step).
        steps: steps S of a run (runs continue up to 2^doublings · S while undecided).
    """

    integrator: str
    zeta: float
    theory: float
    measured: Bracket | None
    steps: int

    @property
    def ratio(self) -> float | None:
        """measured / theory where both are finite and positive."""
        if self.measured is None or not self.measured.two_sided or not 0.0 < self.theory < math.inf:
            return None
        return self.measured.value / self.theory


@dataclass(frozen=True)
class ClothLimit:
    """Largest stable step of one integrator on the cloth of one stiffness.

    Attributes:
        integrator: registry name.
        stiffness: ke of every spring [N/m].
        omega_max: power-iteration ω_max [rad/s].
        predicted: the advisor's largest stable step [s] (∞: unconditionally stable; for adaptive
            integrators: the cap on their internal step).
        measured: bracket of dt [s] from simulation; ``None`` for adaptive integrators.
        steps: steps S of a run.
    """

    integrator: str
    stiffness: float
    omega_max: float
    predicted: float
    measured: Bracket | None
    steps: int


@dataclass(frozen=True)
class SeedResult:
    """The seed reproduction.

    Attributes:
        dt: the fixed step [s] at which the advisor puts RK4's threshold on the seed layout at
            ``SEED_THRESHOLD``.
        omega_max: ω_max of the layout at k = ``SEED_THRESHOLD`` [rad/s] (power iteration).
        threshold: the threshold k [N/m] at ``dt``, measured by simulation.
        unity_threshold: the advisor's RK4 threshold k [N/m] at ``UNITY_FIXED_STEP``.
        steps: steps S of a run.
    """

    dt: float
    omega_max: float
    threshold: Bracket
    unity_threshold: float
    steps: int


@dataclass
class StabilityMap:
    """Everything a map measured, with the advisor's prediction curves for the cloth plot.

    Attributes:
        plan: the plan run.
        device: the Warp device.
        springs: single-spring limits.
        cloth: cloth limits.
        seed: the seed reproduction, or ``None`` when RK4 was not among the integrators.
        predictions: integrator → (ke [N/m], predicted step [s]) on a dense stiffness grid.
        timings: study → wall seconds (kernel compilation included).
        date: ISO date of the run.
    """

    plan: MapPlan
    device: str
    springs: list = field(default_factory=list)
    cloth: list = field(default_factory=list)
    seed: SeedResult | None = None
    predictions: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    date: str = ""


# -- the growth test ------------------------------------------------------------------------------------------


def growth_verdict(energy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unstable, undecided) flags of runs from their E after every step, shape [steps, runs] (steps ≥ 4);
    see the module docstring."""
    quarter = len(energy) // 4
    with np.errstate(over="ignore", invalid="ignore"):
        start = energy[0]
        early = energy[quarter : 2 * quarter].mean(axis=0)
        ratio = energy[len(energy) - quarter :].mean(axis=0) / early
        broken = ~np.isfinite(energy).all(axis=0) | (energy.max(axis=0) > ENERGY_CAP * start)
        live = ~broken & (early > DECAYED * start)  # not decayed to round-off, whose noise has no trend
        grown = ratio > (1.0 + GROWTH) ** 2
        return broken | (live & grown), live & ~grown & (ratio > 1.0)


class _MotionRecord(StepHook):
    """Records every spring's stretch and stretch rate in every world after each step of a block, row by
    row: ``motion`` has shape [BLOCK, world_count · spring_count], world-major."""

    def __init__(self, model: Model):
        self.model = model
        self.motion = wp.zeros((BLOCK, model.world_count * model.spring_count), dtype=wp.vec2d, device=model.device)
        self._kernel = spring_motion_kernel(model.scalar)

    def after_step(self, state: State, step: int, steps: int) -> None:
        model = self.model
        wp.launch(self._kernel, dim=(model.world_count, model.spring_count),
                  inputs=[model.particle_count, model.spring_indices, model.spring_rest_length, state.particle_q,
                          state.particle_qd, step],
                  outputs=[self.motion], device=model.device)


class _Recorder:
    """Steps a model at a fixed dt in captured blocks of ``BLOCK`` steps (a :class:`Stepper`), recording after
    every step the norm E of each group of springs (groups: consecutive ranges of the world-major springs
    of all worlds, w · spring_count + s, starting at ``group_starts``)."""

    def __init__(self, model: Model, integrator: Integrator, dt: float, group_starts):
        self.model = model
        self.group_starts = np.asarray(group_starts)
        ends = model.spring_indices.numpy().reshape(-1, 2)
        inv_mass = world_dynamic_inv_mass(model)[:, ends].sum(axis=2).ravel()
        self._reduced_mass = np.where(inv_mass > 0.0, 1.0 / np.where(inv_mass > 0.0, inv_mass, 1.0), 0.0)
        self._record = _MotionRecord(model)
        self._stepper = Stepper(model, integrator, dt=dt, steps=BLOCK, hooks=[self._record])

    def run(self, start: State | None, steps: int) -> np.ndarray:
        """E after each of ``steps`` steps (rounded up to whole blocks) from ``start`` (``None``: go on
        from where the last run ended), shape [steps, groups]."""
        if start is not None:
            self._stepper.reset(start)
        k = self.model.world_values("spring_stiffness").ravel()
        sizes = np.diff(np.append(self.group_starts, len(k)))
        omega2 = np.add.reduceat(k, self.group_starts) / np.add.reduceat(self._reduced_mass, self.group_starts)
        rate_weight = k / np.repeat(omega2, sizes)
        energy = []
        with np.errstate(over="ignore", invalid="ignore"):
            for _ in range(-(-steps // BLOCK)):
                self._stepper.advance()
                motion = self._record.motion.numpy()
                per_spring = k * motion[..., 0] ** 2 + rate_weight * motion[..., 1] ** 2
                energy.append(np.add.reduceat(per_spring, self.group_starts, axis=1))
        return np.concatenate(energy)

    def unstable(self, start: State, steps: int, doublings: int) -> np.ndarray:
        """Which groups grow in a run of ``steps`` steps from ``start``, continued to up to
        2^``doublings`` times its length while some are undecided; shape [groups], bool."""
        energy = self.run(start, steps)
        for _ in range(doublings):
            if not growth_verdict(energy)[1].any():
                break
            energy = np.concatenate([energy, self.run(None, len(energy))])
        return growth_verdict(energy)[0]


def _bisect(is_stable: Callable[[float], bool], guess: float, resolution: float, *, factor: float = 1.25,
            max_runs: int = 64) -> Bracket:
    """Bracket the largest stable value of a parameter that is stable when small, starting at ``guess``
    (> 0): step by ``factor``, squaring it after each step that did not close the bracket, then bisect
    geometrically until high / low < 1 + ``resolution``. After ``max_runs`` runs without a bracket the
    result is one-sided (low = 0: unstable down to the smallest value tried; high = ∞: stable up to the
    largest)."""
    low, high, runs = 0.0, math.inf, 1
    if is_stable(guess):
        low = guess
    else:
        high = guess
    while (low == 0.0 or math.isinf(high)) and runs < max_runs:
        trial = low * factor if low > 0.0 else high / factor
        runs += 1
        if is_stable(trial):
            low = trial
        else:
            high = trial
        factor *= factor  # a wider next step while the bracket is still open
    while low > 0.0 and high / low > 1.0 + resolution and runs < max_runs:
        mid = math.sqrt(low * high)
        runs += 1
        if is_stable(mid):
            low = mid
        else:
            high = mid
    return Bracket(low=low, high=high, runs=runs)


def _measurable(integrator: str) -> bool:
    """Fixed-step integrators are measured; adaptive ones choose their step."""
    return not INTEGRATORS[integrator].adaptive


# -- 1. one damped spring -----------------------------------------------------------------------------------


def _oscillators(count: int, device) -> Model:
    """``count`` independent oscillators: particle 2j+1 on a spring (rest ``SPRING_REST``) to pinned
    particle 2j, stretched by ``SPRING_AMPLITUDE`` along x; stiffness and damping are set per run."""
    anchors = np.zeros((count, 3))
    anchors[:, 1] = np.arange(count) * 2.0 * SPRING_REST  # apart, though nothing couples them
    positions = np.empty((2 * count, 3))
    positions[0::2] = anchors
    positions[1::2] = anchors + [SPRING_REST + SPRING_AMPLITUDE, 0.0, 0.0]
    builder = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles(positions, mass=SPRING_MASS, pinned=np.arange(0, 2 * count, 2))
    pairs = np.stack([np.arange(0, 2 * count, 2), np.arange(1, 2 * count, 2)], axis=1)
    builder.add_springs(pairs, stiffness=1.0, damping=0.0, rest_length=SPRING_REST)
    return builder.finalize(device, precision="float64")


def _tune(model: Model, omega_h: np.ndarray, zeta: np.ndarray) -> None:
    """Set oscillator j to ω = (ωh)ⱼ rad/s and damping ratio ζⱼ (the runs use h = 1 s)."""
    model.set_world_values("spring_stiffness", SPRING_MASS * omega_h**2)
    model.set_world_values("spring_damping", 2.0 * zeta * SPRING_MASS * omega_h)


def measure_spring_limits(integrator: str, plan: MapPlan, device=None) -> list[SpringLimit]:
    """Largest stable ωh of ``integrator`` on one damped spring for each ζ of the plan, measured beside
    :func:`~warpspring.analysis.stability.stable_omega_h` (theory only for adaptive integrators)."""
    zetas, points = np.asarray(plan.zetas, dtype=np.float64), plan.spring_points
    theory = [stable_omega_h(integrator, float(z)) for z in zetas]
    if not _measurable(integrator):
        return [SpringLimit(integrator, float(z), t, None, 0) for z, t in zip(zetas, theory)]
    model = _oscillators(len(zetas) * points, device)
    grids = np.tile(np.geomspace(*OMEGA_H_RANGE, points), (len(zetas), 1))
    # Tuned before the integrator is built: velocity Verlet decides from the damping whether to correct.
    _tune(model, grids.ravel(), np.repeat(zetas, points))
    recorder = _Recorder(model, INTEGRATORS[integrator](model), 1.0, np.arange(len(zetas) * points))
    low, high = np.zeros(len(zetas)), np.full(len(zetas), np.inf)
    for round_ in range(plan.spring_rounds):
        if round_:
            if not np.any((low > 0.0) & np.isfinite(high)):
                break  # every bracket is one-sided: nothing left to subdivide
            _tune(model, grids.ravel(), np.repeat(zetas, points))
        unstable = recorder.unstable(model.state(), plan.spring_steps, plan.doublings).reshape(len(zetas), points)
        for z in range(len(zetas)):
            if not (round_ == 0 or (low[z] > 0.0 and math.isfinite(high[z]))):
                continue
            # The grid spans the first range, then lies strictly inside the bracket of the last run.
            if unstable[z].any():
                first = int(np.argmax(unstable[z]))
                high[z] = grids[z, first]
                if first:
                    low[z] = grids[z, first - 1]
            else:
                low[z] = grids[z, -1]
            if low[z] > 0.0 and math.isfinite(high[z]):
                grids[z] = np.linspace(low[z], high[z], points + 2)[1:-1]
        runs = round_ + 1
    return [
        SpringLimit(integrator, float(z), t, Bracket(float(lo), float(hi), runs), plan.spring_steps)
        for z, t, lo, hi in zip(zetas, theory, low, high)
    ]


# -- 2. the cloth ---------------------------------------------------------------------------------------------


def cloth_model(stiffness: float, *, size: int, device=None) -> Model:
    """The ANCHORS cloth layout, size × size, flat in the plane z = 1, gravity off, float64: 0.1 m spacing,
    0.1 kg particles, structural + shear + bend springs with ke = ``stiffness`` [N/m] and
    kd = ``CLOTH_DAMPING_RATIO`` · ke, the two top corners pinned."""
    spring = SpringMaterial(ke=stiffness, kd=CLOTH_DAMPING_RATIO * stiffness)
    builder = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=size, ny=size, spacing=CLOTH_SPACING, origin=(0.0, 0.0, 1.0),
                           particle_mass=CLOTH_MASS, structural=spring, shear=spring, bend=spring,
                           pin=["top-left", "top-right"])
    return builder.finalize(device, precision="float64")


def perturbed_state(model: Model, amplitude: float, *, seed: int = 0, sharpening: int = 2) -> State:
    """The model's initial state, at rest, with the free particles of a flat model (in a plane z = const)
    displaced in that plane by RMS ``amplitude`` [m] in every world, weighted towards each world's stiffest
    modes.

    A random in-plane displacement x is replaced ``sharpening`` times by M⁻¹ f(q₀ + x), the model's own
    spring forces (-M⁻¹K x for displacements this small), which multiplies each mode's share by ω² each
    time. Instability starts in the stiff modes; weighting the start towards them keeps the slowly
    decaying soft modes from diluting a slow growth of the stiff ones in E.
    """
    shape = (model.world_count, model.particle_count, 3)
    q0 = model.particle_q.numpy().astype(np.float64).reshape(shape)
    inv_mass = world_dynamic_inv_mass(model)[..., None]
    x = np.random.default_rng(seed).normal(size=shape[1:]) * free_particles(model)[..., None]
    x[..., 2] = 0.0

    def displaced(x):  # positions with each world's displacement scaled to RMS amplitude
        rms = np.sqrt((x * x).sum(axis=2).mean(axis=1))[:, None, None]
        return (q0 + x * (amplitude / rms)).reshape(-1, 3)

    probe = model.state()
    for _ in range(sharpening):
        probe.particle_q.assign(displaced(x))
        eval_forces(model, probe, None)
        x = probe.particle_f.numpy().astype(np.float64).reshape(shape) * inv_mass
    state = model.state()
    state.particle_q.assign(displaced(x))
    return state


def measure_cloth_limits(integrator: str, plan: MapPlan, device=None) -> list[ClothLimit]:
    """Largest stable step of ``integrator`` on the cloth at each stiffness of the plan, measured beside
    the advisor's prediction. Adaptive integrators are not measured. Implicit Euler is run at the four
    steps ω_max·dt = 10⁻¹, 1, 10, 10² and reported stable up to the largest that was."""
    results = []
    for k in plan.cloth_stiffness:
        model = cloth_model(k, size=plan.cloth_size, device=device)
        advice = advise(model, integrator, 1.0)
        measured, steps = None, 0
        if _measurable(integrator):
            start = perturbed_state(model, CLOTH_PERTURBATION * CLOTH_SPACING)
            stepper = INTEGRATORS[integrator](model)
            steps = plan.implicit_steps if isinstance(stepper, ImplicitEuler) else plan.cloth_steps

            def is_stable(dt: float) -> bool:
                return not _Recorder(model, stepper, dt, [0]).unstable(start, steps, plan.doublings)[0]

            if math.isinf(advice.dt_stable):
                tested = [float(x) for x in np.geomspace(0.1, 100.0, 4) / advice.omega_max]
                outcome = [is_stable(dt) for dt in tested]
                bad = outcome.index(False) if False in outcome else len(tested)
                measured = Bracket(low=tested[bad - 1] if bad else 0.0,
                                   high=tested[bad] if bad < len(tested) else math.inf, runs=len(tested))
            else:
                guess = advice.dt_stable if advice.dt_stable > 0.0 else 1.0 / advice.omega_max
                measured = _bisect(is_stable, guess, plan.cloth_resolution)
        results.append(ClothLimit(integrator, float(k), advice.omega_max, advice.dt_stable, measured, steps))
    return results


def cloth_predictions(integrator: str, plan: MapPlan, reference: ClothLimit, *, per_decade: int = 4) -> tuple:
    """The advisor's step [s] over a dense ke grid spanning the plan's, scaled from one measured ``reference``
    row: K is linear in ke, so ω_max ∝ √ke, and kd/ke stays ``CLOTH_DAMPING_RATIO``. Returns (ke, dt)."""
    lo, hi = np.log10(min(plan.cloth_stiffness)), np.log10(max(plan.cloth_stiffness))
    grid = np.union1d(np.logspace(lo, hi, int(round((hi - lo) * per_decade)) + 1), plan.cloth_stiffness)
    omega_per_root_k = reference.omega_max / math.sqrt(reference.stiffness)
    steps = [network_stable_step(integrator, omega_per_root_k * math.sqrt(k), rayleigh=CLOTH_DAMPING_RATIO)
             for k in grid]
    return grid, np.array(steps)


# -- 3. the seed observation ----------------------------------------------------------------------------------


def seed_cloth(stiffness: float, *, device=None) -> Model:
    """The assumed seed layout, after the public Unity project Darkgrouptw/Cloth-Simulation
    (``ClothSystem.cs``, ``SpringSystem.cs``): 10 × 10 particles 0.6 m apart, 1 kg each; springs to the
    4-neighbours (structural), along both diagonals (shear), skipping one along rows and columns (bend)
    and skipping one along both diagonals, all with ke = ``stiffness`` [N/m] and an axial damper
    kd = 1.5 N·s/m; two corners of one edge pinned. Float64.

    Assumptions: the seed's own step is unknown (it is inferred, see :func:`reproduce_seed`); warpspring's
    classic RK4 stands for the seed's RK4 (that project's script evaluates its stages differently and
    uses Ks = 500 N/m); gravity is off and the cloth flat, as in the cloth study.
    """
    spring = SpringMaterial(ke=stiffness, kd=SEED_DAMPING)
    builder = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    grid = builder.add_cloth_grid(nx=SEED_SIZE, ny=SEED_SIZE, spacing=SEED_SPACING, origin=(0.0, 0.0, 5.0),
                                  particle_mass=SEED_MASS, structural=spring, shear=spring, bend=spring,
                                  pin=["top-left", "top-right"])
    skip_diagonals = np.concatenate([
        np.stack([grid[:-2, :-2].ravel(), grid[2:, 2:].ravel()], axis=1),
        np.stack([grid[:-2, 2:].ravel(), grid[2:, :-2].ravel()], axis=1),
    ])
    builder.add_springs(skip_diagonals, stiffness=spring.ke, damping=spring.kd)
    return builder.finalize(device, precision="float64")


def seed_threshold(dt: float, omega_per_root_k: float) -> float:
    """The advisor's RK4 threshold k [N/m] on the seed layout at step ``dt`` [s]: there ω_max = c √k (K is
    linear in k, c = ``omega_per_root_k``) and kd/k = ``SEED_DAMPING`` / k; bisection on k to 0.1 %."""

    def stable(k: float) -> bool:
        return dt <= network_stable_step("rk4", omega_per_root_k * math.sqrt(k), rayleigh=SEED_DAMPING / k)

    low, high = 1.0e-3, 1.0e9
    while high / low > 1.001:
        mid = math.sqrt(low * high)
        low, high = (mid, high) if stable(mid) else (low, mid)
    return math.sqrt(low * high)


def seed_step(*, device=None) -> tuple[float, float]:
    """(dt [s], ω_max [rad/s]): the fixed step at which the advisor puts RK4's threshold on the seed layout
    at ``SEED_THRESHOLD``, and that layout's power-iteration ω_max."""
    advice = advise(seed_cloth(SEED_THRESHOLD, device=device), "rk4", UNITY_FIXED_STEP)
    return advice.dt_stable, advice.omega_max


def seed_is_stable(stiffness: float, dt: float, *, steps: int, doublings: int = 2, device=None) -> bool:
    """Whether RK4 at step ``dt`` [s] keeps the seed layout with springs of ``stiffness`` [N/m] stable in a
    recorded run of ``steps`` steps (see the growth test)."""
    model = seed_cloth(stiffness, device=device)
    start = perturbed_state(model, CLOTH_PERTURBATION * SEED_SPACING)
    recorder = _Recorder(model, INTEGRATORS["rk4"](model), dt, [0])
    return not recorder.unstable(start, steps, doublings)[0]


def reproduce_seed(plan: MapPlan, device=None) -> SeedResult:
    """Infer the seed's fixed step with the advisor, then find RK4's threshold k at that step by bisection
    on simulation runs, starting from 1 N/m, far from the expected value."""
    dt, omega = seed_step(device=device)
    model = seed_cloth(SEED_THRESHOLD, device=device)
    start = perturbed_state(model, CLOTH_PERTURBATION * SEED_SPACING)
    recorder = _Recorder(model, INTEGRATORS["rk4"](model), dt, [0])  # one graph: k changes in place

    def is_stable(k: float) -> bool:
        model.spring_stiffness.fill_(k)
        return not recorder.unstable(start, plan.seed_steps, plan.doublings)[0]

    threshold = _bisect(is_stable, 1.0, plan.seed_resolution, factor=4.0)
    unity = seed_threshold(UNITY_FIXED_STEP, omega / math.sqrt(SEED_THRESHOLD))
    return SeedResult(dt=dt, omega_max=omega, threshold=threshold, unity_threshold=unity, steps=plan.seed_steps)


# -- the whole map --------------------------------------------------------------------------------------------


def run_map(plan: MapPlan = QUICK, device=None, *, integrators=None, log: Callable[[str], None] | None = None,
            engine=None):
    """Measure the three studies of ``plan`` for ``integrators`` (default: the whole registry) on ``device``.

    ``engine``: a sweep engine (:class:`~warpspring.analysis.sweep_ray.RayEngine`) to run the measurements
    on, one job per study × integrator and one for the seed; ``None``: in this process, in order. The
    measured limits are the same either way (each job is deterministic); a study's time is then the sum
    of its jobs' times.

    Returns:
        A :class:`StabilityMap`.
    """
    names = list(INTEGRATORS) if integrators is None else list(integrators)
    unknown = sorted(set(names) - set(INTEGRATORS))
    if unknown:
        raise ConfigError(f"unknown integrator {unknown[0]!r}: choose from {', '.join(sorted(INTEGRATORS))}")
    log = log or (lambda line: None)
    result = StabilityMap(plan=plan, device=str(wp.get_device(device)), date=datetime.date.today().isoformat())
    if engine is not None:
        return _run_on(engine, result, wp.get_device(device).alias, names, log)

    t0 = time.perf_counter()
    for name in names:
        result.springs += measure_spring_limits(name, plan, device)
        log(f"single spring: {name} done")
    result.timings["single spring"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    for name in names:
        rows = measure_cloth_limits(name, plan, device)
        result.cloth += rows
        if any(0.0 < r.predicted < math.inf for r in rows):
            result.predictions[name] = cloth_predictions(name, plan, rows[0])
        log(f"cloth: {name} done")
    result.timings["cloth"] = time.perf_counter() - t0

    if "rk4" in names:
        t0 = time.perf_counter()
        result.seed = reproduce_seed(plan, device)
        result.timings["seed"] = time.perf_counter() - t0
        log("seed: done")
    return result


def _run_on(engine, result: StabilityMap, device: str, names: list, log: Callable[[str], None]) -> StabilityMap:
    """:func:`run_map` through a sweep engine: its jobs gathered in the local loop's order."""
    jobs = [("single spring", n) for n in names] + [("cloth", n) for n in names]
    if "rk4" in names:
        jobs.append(("seed", "rk4"))
    outputs = map_jobs(engine, _map_job, jobs, shared=(result.plan, device),
                       done=lambda out: log(f"{out[0]}: {out[1]} done" if out[0] != "seed" else "seed: done"))
    for study, name, value, wall in outputs:
        result.timings[study] = result.timings.get(study, 0.0) + wall
        if study == "single spring":
            result.springs += value
        elif study == "cloth":
            result.cloth += value
            if any(0.0 < r.predicted < math.inf for r in value):
                result.predictions[name] = cloth_predictions(name, result.plan, value[0])
        else:
            result.seed = value
    return result


def _map_job(job, plan: MapPlan, device: str):
    """One job of the map: (study, integrator, its measurement, wall time [s])."""
    study, name = job
    start = time.perf_counter()
    if study == "single spring":
        value = measure_spring_limits(name, plan, device)
    elif study == "cloth":
        value = measure_cloth_limits(name, plan, device)
    else:
        value = reproduce_seed(plan, device)
    return study, name, value, time.perf_counter() - start
