"""The speed/accuracy trade of the integrators, measured.

For every registered integrator × time step × precision (float32, float64) a study measures the wall
time per simulated second and the error against a reference, on three problems:

* ``spring``, the seed case: a 45 kg block on a spring (k = 180 N/m, c = 18 N·s/m: ω₀ = 2 rad/s, ζ = 0.1)
  pushed from rest by a constant 75 N: it overshoots to 1.73× its 0.42 m equilibrium and rings down over
  the 10 s run (3.2 periods);
* ``stiff-spring``: 1 kg on k = 10⁴ N/m (ω₀ = 100 rad/s) with ζ = 0.01, pushed by 100 N, for 1 s (16 periods);
* ``cloth``: the hanging cloth of ANCHORS.md (0.1 m spacing, 0.1 kg particles, structural + shear + bend
  springs with ke = 1e3 N/m and kd = 10 N·s/m, two top corners pinned) released flat and swinging down
  for 1 s.

The springs are one particle tied by a spring to a pinned anchor, moving along x without gravity: the
closed form of :class:`~warpspring.analysis.analytic.DampedOscillator` is the reference. The cloth's reference is
a float64 RK4 run (the highest-order fixed-step integrator when RK4 is not registered) at a step
``REFERENCE_REFINEMENT`` times smaller than the finest one tested.

Cost: each configuration first runs two uncaptured steps (compilation and module loading stay out of
the timing), then is timed as the median of ``repeats`` batches of graph replays (CUDA graphs on GPUs,
Warp's CPU graphs on the CPU), each batch at least ``min_batch`` seconds of wall time, the device
synchronised before every timer read. Adaptive integrators are timed over the very run whose error is
reported (also as graph replays), since their cost depends on the trajectory. A configuration whose run
would take longer than the plan's ``run_limit`` is reported as skipped, with its measured cost, and so are the finer steps of that
integrator. Adaptive integrators (those taking a ``tolerance`` option) are swept over tolerances at a
fixed output interval instead of over steps.

Only the integrator steps are timed: no Simulator run-time guards, no export.

Outputs (:func:`warpspring.analysis.trade_report.write_report`): ``trade.csv`` (every measurement), ``trade.md`` (tables with the fitted
convergence orders), ``pareto.png`` (error against cost), ``convergence.png`` (error against step, with
fitted orders) and ``seed.png`` (x(t) and v(t) of the seed block under each integrator against the
exact solution). :func:`choose` picks the cheapest measured configuration that meets an error target.
"""

from __future__ import annotations

import datetime
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import warp as wp

from .analytic import DampedOscillator
from ..core.builder import ModelBuilder, SpringMaterial
from ..checks import format_duration
from ..errors import ConfigError, SimulationError
from ..core.integrators import INTEGRATORS, Integrator, make_integrator
from .engines import map_jobs
from .stability import estimate_omega_max
from ..core.model import Model
from ..core.control import Control
from ..core.stepper import StepHook, Stepper

#: A run whose position error exceeds this many times the problem's length scale has blown up.
BLOWUP_FACTOR = 10.0
#: ... and so has one that ends with more energy than the reference by more than this many times the
#: energy the motion was given: these damped systems cannot gain energy, so the integrator drove it.
ENERGY_BLOWUP = 1.0
#: The cloth reference runs at the finest tested step divided by this.
REFERENCE_REFINEMENT = 16
#: Most steps captured in one graph (capturing costs as much Python time per step as running uncaptured).
MAX_CHUNK = 64
#: Fits of the convergence order keep steps with ω_max·h at most this (coarser ones are pre-asymptotic) ...
ASYMPTOTIC_OMEGA_H = 0.5
#: ... errors below this fraction of the problem's length scale (larger ones are saturated) ...
ASYMPTOTIC_CEILING = 0.1
#: ... and above this multiple of the noise floor (float64 rounding accumulated over the run, and the
#: cloth reference's own error, estimated by its difference from a run at twice its step).
NOISE_MARGIN = 10.0
#: Status of a measured configuration (see :class:`Measurement`).
STATUSES = ("ok", "non-finite", "blown up", "failed", "skipped")


# -- problems ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SpringProblem:
    """One particle tied by a spring to a pinned anchor, driven by a constant force along x, without gravity.

    The anchor sits at x = −L and the particle starts at x₀ (the spring at its rest length L when x₀ = 0),
    so the particle's x coordinate is the oscillator's displacement and the spring stays along x: the
    motion is exactly that of :class:`DampedOscillator` with k = ke and c = kd.

    Attributes:
        name: problem name in tables and on the command line.
        oscillator: mass, stiffness, damping, force and initial state.
        duration: simulated time of each run [s].
        steps: fixed-step runs, as numbers of steps over ``duration`` (dt = duration / steps), coarse to fine.
        outputs: steps over ``duration`` of adaptive integrators (their dt, which they subdivide themselves).
        rest_length: L [m].
        plot_steps: the step count of the x(t), v(t) plot (``seed.png``), or ``None`` for no plot.
    """

    records_trajectory: ClassVar[bool] = True  # errors are taken over every step, not only at the end

    name: str
    oscillator: DampedOscillator
    duration: float
    steps: tuple[int, ...]
    outputs: int
    rest_length: float = 1.0
    plot_steps: int | None = None

    def describe(self) -> str:
        """One line naming the problem's parameters (inputs, not measurements)."""
        o = self.oscillator
        return (
            f"one {o.mass:g} kg particle on a spring to a pinned anchor, k = {o.stiffness:g} N/m, "
            f"c = {o.damping:g} N·s/m (ω₀ = {o.natural_frequency:.4g} rad/s, ζ = {o.damping_ratio:.3g}, "
            f"{o.regime}), pushed by F = {o.force:g} N along x from x(0) = {o.x0:g} m, v(0) = {o.v0:g} m/s, "
            f"no gravity; {self.duration:g} s simulated"
        )

    @property
    def fastest_frequency(self) -> float:
        """ω₀ [rad/s], the only frequency of the problem."""
        return self.oscillator.natural_frequency

    @property
    def length_scale(self) -> float:
        """Peak-to-peak excursion [m] of the exact x(t) over the run."""
        x = self.oscillator.position(np.linspace(0.0, self.duration, 20001))
        return float(np.ptp(x))

    def build(self, device, precision: str) -> tuple[Model, Control]:
        """The model (anchor = particle 0, pinned; block = particle 1) and a control holding the force."""
        o = self.oscillator
        builder = ModelBuilder(gravity=(0.0, 0.0, 0.0))
        builder.add_particles(
            [[-self.rest_length, 0.0, 0.0], [o.x0, 0.0, 0.0]],
            velocities=[[0.0, 0.0, 0.0], [o.v0, 0.0, 0.0]],
            mass=o.mass,
            pinned=[0],
        )
        builder.add_springs([[0, 1]], stiffness=o.stiffness, damping=o.damping, rest_length=self.rest_length)
        model = builder.finalize(device, precision=precision)
        control = model.control()
        control.set_particle_force([[0.0, 0.0, 0.0], [o.force, 0.0, 0.0]])
        return model, control

    def evaluate(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray) -> dict:
        """Errors of a run sampled at times ``t`` [s], shape [samples], with positions ``q`` [m] and
        velocities ``qd`` [m/s], shape [samples, 2, 3]: the :class:`Measurement` fields it determines."""
        x, v = q[:, 1, 0], qd[:, 1, 0]
        if not (np.isfinite(x).all() and np.isfinite(v).all()):
            return {"status": "non-finite"}
        exact = self.oscillator.position(t)
        error = np.abs(x - exact)
        if error.max() > BLOWUP_FACTOR * self.length_scale:
            return {"status": "blown up"}
        o = self.oscillator
        drift = float((o.state_energy(x[-1], v[-1]) - o.energy(t[-1])) / o.oscillation_energy)
        if drift > ENERGY_BLOWUP:
            return {"status": "blown up"}
        return {
            "status": "ok",
            "error_max": float(error.max()),
            "error_rms": float(np.sqrt(np.mean(error**2))),
            "error_end": float(error[-1]),
            "energy_drift": drift,
        }


@dataclass(frozen=True)
class ClothProblem:
    """The hanging cloth of ANCHORS.md: ``size`` × ``size`` particles ``spacing`` apart, ``particle_mass`` each,
    structural + shear + bend springs of one material, the two top corners pinned, gravity 9.81 m/s² down z.
    It starts flat, horizontal and at rest at z = 1 m, and swings down.

    Attributes:
        name: problem name in tables and on the command line.
        size: particles per side.
        duration: simulated time of each run [s]; errors are taken at its end.
        steps: fixed-step runs, as numbers of steps over ``duration``, coarse to fine.
        outputs: steps over ``duration`` of adaptive integrators.
        spacing: particle spacing [m].
        particle_mass: [kg].
        spring: stiffness ke [N/m] and damping kd [N·s/m] of every spring.
    """

    records_trajectory: ClassVar[bool] = False

    name: str
    size: int
    duration: float
    steps: tuple[int, ...]
    outputs: int
    spacing: float = 0.1
    particle_mass: float = 0.1
    spring: SpringMaterial = SpringMaterial(ke=1.0e3, kd=10.0)

    def describe(self) -> str:
        """One line naming the problem's parameters (inputs, not measurements)."""
        return (
            f"{self.size} × {self.size} particles {self.spacing:g} m apart, {self.particle_mass:g} kg each, "
            f"structural + shear + bend springs ke = {self.spring.ke:g} N/m, kd = {self.spring.kd:g} N·s/m, "
            f"two top corners pinned, released flat at rest under gravity; {self.duration:g} s simulated"
        )

    @property
    def length_scale(self) -> float:
        """Side length of the cloth [m]."""
        return (self.size - 1) * self.spacing

    def build(self, device, precision: str) -> tuple[Model, Control]:
        """The model and an empty control."""
        builder = ModelBuilder()
        half = 0.5 * self.length_scale
        builder.add_cloth_grid(
            nx=self.size,
            ny=self.size,
            spacing=self.spacing,
            origin=(-half, -half, 1.0),
            particle_mass=self.particle_mass,
            structural=self.spring,
            shear=self.spring,
            bend=self.spring,
            pin=["top-left", "top-right"],
        )
        model = builder.finalize(device, precision=precision)
        return model, model.control()

    def evaluate(self, q: np.ndarray, qd: np.ndarray, reference: ClothReference) -> dict:
        """Errors of the end state (positions ``q`` [m], velocities ``qd`` [m/s], shape [particles, 3])
        against ``reference``: the :class:`Measurement` fields it determines."""
        if not (np.isfinite(q).all() and np.isfinite(qd).all()):
            return {"status": "non-finite"}
        error = np.linalg.norm(q - reference.q, axis=1)
        if error.max() > BLOWUP_FACTOR * self.length_scale:
            return {"status": "blown up"}
        drift = float((reference.geometry.energy(q, qd) - reference.energy) / reference.released)
        if drift > ENERGY_BLOWUP:
            return {"status": "blown up"}
        return {
            "status": "ok",
            "error_max": float(error.max()),
            "error_rms": float(np.sqrt(np.mean(error**2))),
            "energy_drift": drift,
            "max_strain": reference.geometry.max_strain(q),
        }


@dataclass(frozen=True)
class SpringNetwork:
    """Host copies (float64) of what the energy and strain of a spring network need (one world of a model).

    Attributes:
        mass: particle masses [kg], shape [particles].
        gravity: gravitational acceleration [m/s²], shape [3].
        springs: particle pairs, shape [springs, 2].
        rest_length: [m], shape [springs].
        stiffness: ke [N/m], shape [springs].
        initial_q: initial positions [m], shape [particles, 3].
        free: whether each particle moves (nonzero inverse mass), shape [particles].
    """

    mass: np.ndarray
    gravity: np.ndarray
    springs: np.ndarray
    rest_length: np.ndarray
    stiffness: np.ndarray
    initial_q: np.ndarray
    free: np.ndarray

    @classmethod
    def of(cls, model: Model, *, world: int = 0) -> SpringNetwork:
        """Read the arrays of ``world`` of ``model``."""
        n = model.particle_count
        return cls(
            mass=model.world_values("particle_mass")[world],
            gravity=model.world_values("gravity")[world],
            springs=model.spring_indices.numpy().reshape(-1, 2).astype(np.int64),
            rest_length=model.spring_rest_length.numpy().astype(np.float64),
            stiffness=model.world_values("spring_stiffness")[world],
            initial_q=model.particle_q.numpy().astype(np.float64)[world * n : (world + 1) * n],
            free=~model.kinematic_mask(world=world),
        )

    def lengths(self, q: np.ndarray) -> np.ndarray:
        """Spring lengths [m] at positions ``q`` [m], shape [particles, 3]."""
        return np.linalg.norm(q[self.springs[:, 1]] - q[self.springs[:, 0]], axis=1)

    def energy(self, q: np.ndarray, qd: np.ndarray) -> float:
        """Kinetic + gravitational (zero at the initial positions) + elastic energy [J]."""
        kinetic = 0.5 * float(np.sum(self.mass * np.sum(qd * qd, axis=1)))
        gravitational = -float(np.sum(self.mass * ((q - self.initial_q) @ self.gravity)))
        stretch = self.lengths(q) - self.rest_length
        return kinetic + gravitational + 0.5 * float(np.sum(self.stiffness * stretch * stretch))

    def max_strain(self, q: np.ndarray) -> float:
        """Largest (|d| − L) / L over the springs [-]."""
        return float(np.max(self.lengths(q) / self.rest_length - 1.0))


@dataclass(frozen=True)
class ClothReference:
    """The reference end state of a cloth problem.

    Attributes:
        integrator: integrator name.
        dt: its step [s].
        q: positions at the end [m], shape [particles, 3].
        energy: mechanical energy at the end [J] (see :meth:`SpringNetwork.energy`).
        released: gravitational energy released by the end [J]: the scale of the energy drift.
        max_strain: largest spring strain at the end [-].
        self_difference: max |q(dt) − q(2 dt)| [m]: the reference against itself at twice the step.
        fastest_frequency: ω_max of the cloth at rest [rad/s] (power iteration: ``estimate_omega_max``).
        wall: wall time of the two reference runs [s].
        geometry: the network's host arrays.
    """

    integrator: str
    dt: float
    q: np.ndarray
    energy: float
    released: float
    max_strain: float
    self_difference: float
    fastest_frequency: float
    wall: float
    geometry: SpringNetwork


#: The seed case and the stiff spring; see the module docstring.
SEED = DampedOscillator(mass=45.0, damping=18.0, stiffness=180.0, force=75.0)
STIFF = DampedOscillator.from_frequency(omega=100.0, zeta=0.01, mass=1.0, force=100.0)


# -- plans --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StudyPlan:
    """What a study measures and how long it may take.

    Attributes:
        name: "quick" or "full" (or a name of your own).
        problems: the problems, each with its steps.
        precisions: model precisions.
        tolerances: the sweep of adaptive integrators, loose to tight.
        repeats: timed batches per configuration (the median is reported).
        min_batch: least wall time of one timed batch [s].
        run_limit: configurations whose run would take longer than this [s] are skipped.
    """

    name: str
    problems: tuple
    precisions: tuple[str, ...] = ("float32", "float64")
    tolerances: tuple[float, ...] = (1e-3, 1e-6)
    repeats: int = 5
    min_batch: float = 0.05
    run_limit: float = 20.0


# Adaptive integrators report every 0.5 s (seed) and 20 ms (stiff): ω₀·dt = 1 and 2, outputs coarse enough
# not to cap their internal steps at the looser tolerances.
def _seed(steps, plot_steps):
    return SpringProblem("spring", SEED, duration=10.0, steps=steps, outputs=20, plot_steps=plot_steps)


def _stiff(steps):
    return SpringProblem("stiff-spring", STIFF, duration=1.0, steps=steps, outputs=50)


#: The full study: a few minutes on a CPU.
FULL = StudyPlan(
    name="full",
    problems=(
        _seed(tuple(2**k for k in range(4, 13)), plot_steps=64),  # dt = 0.625 s … 2.4 ms (ω₀h = 1.25 … 0.005)
        _stiff(tuple(2**k for k in range(5, 14))),  # dt = 31 ms … 0.12 ms (ω₀h = 3.1 … 0.012)
        ClothProblem("cloth", size=16, duration=1.0, steps=tuple(60 * 2**k for k in range(7)), outputs=60),
    ),
    tolerances=(1e-2, 1e-4, 1e-6, 1e-8),
    repeats=5,
    min_batch=0.05,
    run_limit=20.0,
)

#: A CI-sized study: about a minute on a CPU once the kernels are cached.
QUICK = StudyPlan(
    name="quick",
    problems=(
        _seed((64, 128, 256, 512), plot_steps=64),
        _stiff((256, 512, 1024, 2048)),
        ClothProblem("cloth", size=8, duration=1.0, steps=(480, 960, 1920, 3840), outputs=60),
    ),
    tolerances=(1e-3, 1e-6),
    repeats=3,
    min_batch=0.01,
    run_limit=2.0,
)


# -- measurements -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Measurement:
    """One configuration (integrator × step × precision) on one problem: a row of ``trade.csv``.

    Attributes:
        problem: problem name.
        integrator: integrator name (a key of ``INTEGRATORS``).
        order: the integrator's nominal convergence order.
        precision: "float32" or "float64".
        device: Warp device alias.
        dt: step [s]; for adaptive integrators the output interval they subdivide.
        tolerance: the adaptive integrator's tolerance; ``None`` for fixed-step integrators.
        steps_per_second: integrator steps per simulated second [1/s]; adaptive: accepted + rejected
            internal steps.
        mean_step: simulated time per accepted step [s]; ``dt`` for fixed-step integrators.
        wall_per_second: wall time per simulated second [s/s]; ``None`` when not measured.
        status: "ok"; "non-finite" or "blown up" (an error over ``BLOWUP_FACTOR`` × the problem's length
            scale, or an energy drift over ``ENERGY_BLOWUP``): unstable; "failed": the integrator gave up
            (SimulationError); "skipped": the run would take longer than the plan's ``run_limit``.
        error_max: springs: max over the steps of |x − x_exact| [m]; cloth: max over the particles of
            |x − x_ref| at the end [m].
        error_rms: the RMS of the same errors (over steps, or over particles) [m].
        error_end: springs: |x − x_exact| at the end [m]; cloth: ``None`` (compared at the end only).
        energy_drift: mechanical energy at the end minus the reference's, over the energy the motion
            is given [-]: springs: E(0) − E(rest); cloth: the gravitational energy the reference
            released. > 0: energy gained, < 0: lost (numerical damping).
        max_strain: cloth: max over the springs of (|d| − L) / L at the end [-]; springs: ``None``.
    """

    problem: str
    integrator: str
    order: int
    precision: str
    device: str
    dt: float
    tolerance: float | None
    steps_per_second: float | None
    mean_step: float | None
    wall_per_second: float | None
    status: str
    error_max: float | None = None
    error_rms: float | None = None
    error_end: float | None = None
    energy_drift: float | None = None
    max_strain: float | None = None

    @property
    def setting(self) -> str:
        """The step or tolerance: "dt = 1.042 ms" or "tolerance 1e-06"."""
        return f"dt = {_ms(self.dt)}" if self.tolerance is None else f"tolerance {self.tolerance:g}"

    @property
    def label(self) -> str:
        """Short configuration name: "rk4, dt = 1.042 ms, float32" or "dopri5, tolerance 1e-06, float64"."""
        return f"{self.integrator}, {self.setting}, {self.precision}"


@dataclass
class Study:
    """The result of :func:`run_study`.

    Attributes:
        plan: what was measured.
        rows: one measurement per configuration.
        device: Warp device alias.
        device_name: the device's name (GPU model, or CPU model and core count).
        references: the cloth references by problem name.
        trajectories: the seed plot's runs: label → (t [s], x [m], v [m/s]), each of shape [samples].
        elapsed: wall time of the whole study [s].
        warp_version, date: provenance for the report.
    """

    plan: StudyPlan
    rows: list[Measurement]
    device: str
    device_name: str
    references: dict[str, ClothReference] = field(default_factory=dict)
    trajectories: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict)
    elapsed: float = 0.0
    warp_version: str = wp.__version__
    date: str = field(default_factory=lambda: datetime.date.today().isoformat())

    def problem(self, name: str):
        """The plan's problem called ``name``."""
        for problem in self.plan.problems:
            if problem.name == name:
                return problem
        raise ConfigError(f"the study has no problem {name!r}: it has {', '.join(p.name for p in self.plan.problems)}")


def reference_integrator() -> str:
    """The cloth reference: "rk4" when registered, else the highest-order fixed-step integrator."""
    if "rk4" in INTEGRATORS:
        return "rk4"
    fixed = [c for c in INTEGRATORS.values() if not c.adaptive]
    if not fixed:
        raise ConfigError("no fixed-step integrator is registered to compute the cloth reference")
    return max(fixed, key=lambda c: (c.order, c.name)).name


# -- running ------------------------------------------------------------------------------------------------


class _Recording(StepHook):
    """Copies positions and velocities after every step of an advance into device buffers of shape
    [steps · particle_count] (plain copies: no kernel to compile, capturable)."""

    def __init__(self, model: Model, steps: int):
        self.model, self.steps = model, steps
        self._q = wp.empty(steps * model.particle_count, dtype=model.vec3, device=model.device)
        self._qd = wp.empty(steps * model.particle_count, dtype=model.vec3, device=model.device)

    def after_step(self, state, step: int, steps: int) -> None:
        n = self.model.particle_count
        wp.copy(self._q, state.particle_q, dest_offset=step * n, count=n)
        wp.copy(self._qd, state.particle_qd, dest_offset=step * n, count=n)

    def recorded(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions [m] and velocities [m/s] after each step of the last advance: float64, [steps, particles, 3]."""
        shape = (self.steps, self.model.particle_count, 3)
        return self._q.numpy().reshape(shape).astype(np.float64), self._qd.numpy().reshape(shape).astype(np.float64)


def _warm_up(model: Model, integrator: Integrator, control: Control, dt: float) -> float:
    """Two uncaptured steps from the initial state: the first compiles and loads the kernels, the second's
    wall time [s] (device synchronised) is returned. Uses its own states."""
    stepper = Stepper(model, integrator, dt=dt, steps=1, control=control, use_graph=False)
    stepper.advance()
    wp.synchronize_device(model.device)
    start = time.perf_counter()
    stepper.advance()
    wp.synchronize_device(model.device)
    return time.perf_counter() - start


def _chunk(steps: int, most: int) -> int:
    """The largest divisor of ``steps`` that is at most ``most`` (≥ 1)."""
    return max(d for d in range(1, max(1, min(most, steps)) + 1) if steps % d == 0)


def _time_replays(stepper: Stepper, plan: StudyPlan) -> float:
    """Median wall time per simulated second [s/s] of ``plan.repeats`` batches of ``stepper.advance()``."""
    device = stepper.model.device
    stepper.advance()  # capture and first replay
    wp.synchronize_device(device)
    start = time.perf_counter()
    stepper.advance()
    wp.synchronize_device(device)
    frames = max(1, math.ceil(plan.min_batch / max(time.perf_counter() - start, 1e-9)))
    samples = []
    for _ in range(plan.repeats):
        wp.synchronize_device(device)
        start = time.perf_counter()
        for _ in range(frames):
            stepper.advance()
        wp.synchronize_device(device)
        samples.append((time.perf_counter() - start) / (frames * stepper.steps * stepper.dt))
    return statistics.median(samples)


def _run(model, integrator, control, dt, steps, chunk, *, record: bool):
    """Run ``steps`` steps of ``dt`` from the initial state. Returns (wall time [s], sample times [s],
    positions, velocities), float64 of shape [samples, particles, 3]: every step when ``record``, else the
    initial and the final state."""
    recording = _Recording(model, chunk) if record else None
    stepper = Stepper(model, integrator, dt=dt, steps=chunk, control=control, hooks=[recording] if record else [])
    initial_q = stepper.state.particle_q.numpy().astype(np.float64)
    initial_qd = stepper.state.particle_qd.numpy().astype(np.float64)
    qs, qds = [initial_q[None]], [initial_qd[None]]
    wp.synchronize_device(model.device)
    start = time.perf_counter()
    for _ in range(steps // chunk):
        stepper.advance()
        if record:
            q, qd = recording.recorded()
            qs.append(q)
            qds.append(qd)
    wp.synchronize_device(model.device)
    wall = time.perf_counter() - start
    if not record:
        qs.append(stepper.state.particle_q.numpy().astype(np.float64)[None])
        qds.append(stepper.state.particle_qd.numpy().astype(np.float64)[None])
    q, qd = np.concatenate(qs), np.concatenate(qds)
    t = dt * (np.arange(len(q)) if record else np.array([0, steps]))
    return wall, t, q, qd


def _measure(problem, model, control, name, options, dt, steps, plan, reference):
    """Measure one configuration. Returns (Measurement, (t, q, qd) of the run or None when not run)."""
    cls = INTEGRATORS[name]
    row = _configuration(problem, model, cls, options, dt, steps)
    try:
        warm = make_integrator(name, model, **options)
        step_cost = _warm_up(model, warm, control, dt)
        chunk = _chunk(steps, max(1, min(MAX_CHUNK, int(plan.min_batch / max(step_cost, 1e-9)))))
        if cls.adaptive:  # its cost depends on the trajectory: timed below, on the run itself
            projected = step_cost * steps
        else:
            row["wall_per_second"] = _time_replays(Stepper(model, warm, dt=dt, steps=chunk, control=control), plan)
            projected = row["wall_per_second"] * problem.duration
        if projected > plan.run_limit:
            return Measurement(**row, status="skipped"), None
        integrator = make_integrator(name, model, **options)  # fresh: no state carried over from the timing
        wall, t, q, qd = _run(model, integrator, control, dt, steps, chunk, record=problem.records_trajectory)
    except SimulationError:
        return Measurement(**row, status="failed"), None
    if cls.adaptive:
        row["wall_per_second"] = wall / problem.duration
        accepted = getattr(integrator, "accepted_steps", None)
        rejected = getattr(integrator, "rejected_steps", 0)
        if accepted:
            row["steps_per_second"] = (accepted + rejected) / problem.duration
            row["mean_step"] = problem.duration / accepted
    if problem.records_trajectory:
        metrics = problem.evaluate(t, q, qd)
    else:
        metrics = problem.evaluate(q[-1], qd[-1], reference)
    return Measurement(**row, **metrics), (t, q, qd)


def _cloth_reference(problem: ClothProblem, device) -> ClothReference:
    """The float64 reference end state of ``problem`` and its difference from a run at twice its step."""
    name = reference_integrator()
    steps = max(problem.steps) * REFERENCE_REFINEMENT
    model, control = problem.build(device, "float64")
    dt = problem.duration / steps
    integrator = make_integrator(name, model)
    _warm_up(model, integrator, control, dt)
    chunk = _chunk(steps // 2, MAX_CHUNK)
    start = time.perf_counter()
    finals = []
    for n, h in ((steps, dt), (steps // 2, 2.0 * dt)):
        _, _, q, qd = _run(model, make_integrator(name, model), control, h, n, chunk, record=False)
        finals.append((q[-1], qd[-1]))
    wall = time.perf_counter() - start
    (q, qd), (q_coarse, _) = finals
    if not (np.isfinite(q).all() and np.isfinite(q_coarse).all()):
        raise SimulationError(f"the cloth reference ({name}, dt = {_ms(dt)}) went non-finite")
    geometry = SpringNetwork.of(model)
    released = float(np.sum(geometry.mass * ((q - geometry.initial_q) @ geometry.gravity)))
    return ClothReference(
        integrator=name,
        dt=dt,
        q=q,
        energy=geometry.energy(q, qd),
        released=released,
        max_strain=geometry.max_strain(q),
        self_difference=float(np.linalg.norm(q - q_coarse, axis=1).max()),
        fastest_frequency=estimate_omega_max(model).omega_max,
        wall=wall,
        geometry=geometry,
    )


def _configurations(problem, cls, plan: StudyPlan) -> list[tuple[dict, float, int]]:
    """(options, dt, steps) of each run of integrator class ``cls`` on ``problem``, cheapest first."""
    if cls.adaptive:
        return [({"tolerance": tol}, problem.duration / problem.outputs, problem.outputs) for tol in plan.tolerances]
    return [({}, problem.duration / n, n) for n in sorted(problem.steps)]


def run_study(device=None, *, plan: StudyPlan = FULL, integrators=None, progress: bool = False,
              engine=None) -> Study:
    """Measure every integrator × step × precision of ``plan`` on ``device``.

    Args:
        device: Warp device ("cpu", "cuda:0", ...); default Warp's default device.
        plan: :data:`FULL`, :data:`QUICK` or a :class:`StudyPlan` of your own.
        integrators: names of the integrators to measure; default all of ``INTEGRATORS``.
        progress: show a progress bar (tqdm) on stderr.
        engine: a sweep engine (:class:`~warpspring.analysis.sweep_ray.RayEngine`) to run the plan's jobs
            on, one per problem × precision × integrator (the cloth references first); ``None``: in this
            process. The rows are the same, in the same order; only the timings differ where jobs run side
            by side on one device.

    Raises:
        ConfigError: an unknown integrator name.
    """
    from tqdm import tqdm

    names = list(INTEGRATORS) if integrators is None else list(integrators)
    unknown = [n for n in names if n not in INTEGRATORS]
    if unknown:
        raise ConfigError(f"unknown integrator {unknown[0]!r}: choose from {', '.join(INTEGRATORS)}")
    if not names:
        raise ConfigError("no integrator to measure")
    device = wp.get_device(device)
    start = time.perf_counter()
    study = Study(plan=plan, rows=[], device=device.alias, device_name=_device_name(device))
    if engine is not None:
        _run_on(engine, study, device.alias, names, progress)
        study.elapsed = time.perf_counter() - start
        return study
    total = sum(
        len(_configurations(problem, INTEGRATORS[name], plan)) * len(plan.precisions)
        for problem in plan.problems
        for name in names
    )
    with tqdm(total=total, unit="run", disable=not progress, dynamic_ncols=True, leave=False) as bar:
        for problem in plan.problems:
            reference = None
            if isinstance(problem, ClothProblem):
                bar.set_description(f"{problem.name}: reference")
                reference = study.references[problem.name] = _cloth_reference(problem, device)
            for precision in plan.precisions:
                model, control = problem.build(device, precision)
                for name in names:
                    bar.set_description(f"{problem.name}: {name}, {precision}")
                    rows, trajectories = _measure_integrator(problem, model, control, name, plan, reference,
                                                             done=lambda: bar.update(1))
                    study.rows += rows
                    study.trajectories.update(trajectories)
    study.elapsed = time.perf_counter() - start
    return study


def _measure_integrator(problem, model, control, name, plan, reference, *, done=None) -> tuple[list, dict]:
    """Every configuration of integrator ``name`` on ``problem``'s ``model``, cheapest first: the rows and
    the seed plot's trajectories. ``done`` is called after each configuration."""
    cls = INTEGRATORS[name]
    rows, trajectories = [], {}
    too_slow = False  # once a run is over the limit, the finer (costlier) ones are too
    for options, dt, steps in _configurations(problem, cls, plan):
        if too_slow:
            fields = _configuration(problem, model, cls, options, dt, steps)
            row, run = Measurement(**fields, status="skipped"), None
        else:
            row, run = _measure(problem, model, control, name, options, dt, steps, plan, reference)
            too_slow = row.status == "skipped"
        rows.append(row)
        if run is not None and _plotted(problem, row, plan, steps):
            t, q, qd = run
            trajectories[f"{name}, {row.setting}"] = (t, q[:, 1, 0], qd[:, 1, 0])
        if done is not None:
            done()
    return rows, trajectories


def _run_on(engine, study: Study, device: str, names: list, progress: bool) -> None:
    """Measure ``study``'s plan through a sweep engine: the cloth references first, then one job per
    problem × precision × integrator, gathered in the order the local loop measures them."""
    from tqdm import tqdm

    plan = study.plan
    cloth = [i for i, problem in enumerate(plan.problems) if isinstance(problem, ClothProblem)]
    for i, reference in zip(cloth, map_jobs(engine, _reference_job, [(plan, i, device) for i in cloth])):
        study.references[plan.problems[i].name] = reference
    jobs = [(plan, i, precision, name, device, study.references.get(problem.name))
            for i, problem in enumerate(plan.problems) for precision in plan.precisions for name in names]
    total = sum(len(_configurations(plan.problems[job[1]], INTEGRATORS[job[3]], plan)) for job in jobs)
    with tqdm(total=total, unit="run", disable=not progress, dynamic_ncols=True, leave=False) as bar:
        for rows, trajectories in map_jobs(engine, _integrator_job, jobs, done=lambda r: bar.update(len(r[0]))):
            study.rows += rows
            study.trajectories.update(trajectories)


def _reference_job(job) -> ClothReference:
    plan, i, device = job
    return _cloth_reference(plan.problems[i], wp.get_device(device))


def _integrator_job(job) -> tuple[list, dict]:
    plan, i, precision, name, device, reference = job
    problem = plan.problems[i]
    model, control = problem.build(wp.get_device(device), precision)
    return _measure_integrator(problem, model, control, name, plan, reference)


def _device_name(device) -> str:
    """The GPU's name, or the CPU's model (Linux) or architecture, for the report."""
    if device.is_cuda:
        return device.name
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        model = ""
    return f"{model or platform.machine()}, {os.cpu_count()} cores (Warp runs CPU kernels on one)"


def _configuration(problem, model, cls, options, dt, steps) -> dict:
    """The :class:`Measurement` fields that name a configuration, before it is measured."""
    adaptive = cls.adaptive
    return dict(
        problem=problem.name,
        integrator=cls.name,
        order=cls.order,
        precision=model.precision,
        device=model.device.alias,
        dt=dt,
        tolerance=options.get("tolerance"),
        steps_per_second=None if adaptive else steps / problem.duration,
        mean_step=None if adaptive else dt,
        wall_per_second=None,
    )


def _plotted(problem, row: Measurement, plan: StudyPlan, steps: int) -> bool:
    """Whether ``row`` is one of the seed plot's runs: float64, at the plot's step (adaptive: loosest tolerance)."""
    if not isinstance(problem, SpringProblem) or problem.plot_steps is None or row.precision != "float64":
        return False
    if row.tolerance is not None:
        return row.tolerance == plan.tolerances[0]
    return steps == problem.plot_steps


# -- analysis -----------------------------------------------------------------------------------------------


def fit_order(step, error) -> float:
    """The convergence order p of error ≈ C · stepᵖ: the least-squares slope of log(error) against log(step).

    Args:
        step: step sizes [s], shape [n], n ≥ 2 distinct values.
        error: errors (any unit), shape [n], > 0.

    Raises:
        ConfigError: fewer than two distinct steps, mismatched shapes, or a non-positive value.
    """
    step, error = np.asarray(step, dtype=np.float64), np.asarray(error, dtype=np.float64)
    if step.shape != error.shape or step.ndim != 1:
        raise ConfigError(f"step and error must be 1-D arrays of one length, got shapes {step.shape} and {error.shape}")
    if len(np.unique(step)) < 2:
        raise ConfigError("fitting a convergence order needs at least two distinct steps")
    if not (np.all(step > 0) and np.all(error > 0)):
        raise ConfigError("fitting a convergence order needs positive steps and errors")
    return float(np.polyfit(np.log(step), np.log(error), 1)[0])


def asymptotic_range(
    rows: list[Measurement], *, frequency: float, length_scale: float, duration: float, noise: float = 0.0
) -> list[Measurement]:
    """The float64, stable rows in the asymptotic range: for fixed-step integrators a step h with
    ``frequency`` · h at most ``ASYMPTOTIC_OMEGA_H`` (``frequency``: the problem's fastest, ω_max [rad/s];
    adaptive integrators size their steps from their error estimate instead), an error below
    ``ASYMPTOTIC_CEILING`` × ``length_scale`` [m] and above ``NOISE_MARGIN`` × the noise floor: ``noise``
    [m] (e.g. the reference's own error) plus float64 rounding accumulated over the steps of a run of
    ``duration`` [s], ε · length_scale · steps."""
    chosen = []
    for r in rows:
        if r.status != "ok" or r.precision != "float64" or r.error_max is None or r.mean_step is None:
            continue
        if r.tolerance is None and frequency * r.dt > ASYMPTOTIC_OMEGA_H:
            continue
        steps = r.steps_per_second * duration
        floor = NOISE_MARGIN * (noise + np.finfo(np.float64).eps * length_scale * steps)
        if floor < r.error_max <= ASYMPTOTIC_CEILING * length_scale:
            chosen.append(r)
    return chosen


def convergence_orders(study: Study, problem: str) -> dict[str, tuple[float | None, list[Measurement]]]:
    """Fitted order per integrator on ``problem``: name → (order or ``None`` with fewer than 3 usable
    points, the rows fitted). Fixed-step integrators are fitted against dt, adaptive ones against their
    mean accepted step."""
    spec = study.problem(problem)
    reference = study.references.get(problem)
    noise = reference.self_difference if reference is not None else 0.0
    frequency = reference.fastest_frequency if reference is not None else spec.fastest_frequency
    orders = {}
    for name in dict.fromkeys(r.integrator for r in study.rows if r.problem == problem):
        rows = [r for r in study.rows if r.problem == problem and r.integrator == name]
        fitted = asymptotic_range(
            rows, frequency=frequency, length_scale=spec.length_scale, duration=spec.duration, noise=noise
        )
        distinct = len({r.mean_step for r in fitted})
        order = fit_order([r.mean_step for r in fitted], [r.error_max for r in fitted]) if distinct >= 3 else None
        orders[name] = (order, fitted)
    return orders


def pareto_front(rows: list[Measurement]) -> list[Measurement]:
    """The measured rows no other row beats in both wall time and error, by increasing wall time."""
    usable = sorted(
        (r for r in rows if r.status == "ok" and r.wall_per_second is not None and r.error_max is not None),
        key=lambda r: (r.wall_per_second, r.error_max),
    )
    front, best = [], math.inf
    for r in usable:
        if r.error_max < best:
            front.append(r)
            best = r.error_max
    return front


# -- the tolerance knob -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Choice:
    """What :func:`choose` recommends.

    Attributes:
        integrator: integrator name.
        options: its options, e.g. ``{"tolerance": 1e-5}`` for an adaptive integrator.
        dt: the step [s] (adaptive: the output interval measured), or ``None`` when unmeasured.
        precision: "float32" / "float64", or ``None`` when unmeasured.
        row: the measured configuration behind the choice, or ``None`` when the recommendation is untested.
        runner_up: the next-best measured configuration the explanation compares with, or ``None``.
        explanation: one paragraph: what was chosen and why, with the measured error and cost of the
            pick and of the runner-up.
    """

    integrator: str
    options: dict
    dt: float | None
    precision: str | None
    row: Measurement | None
    runner_up: Measurement | None
    explanation: str


def choose(study_rows, target_error: float, *, time_budget: float | None = None, problem: str | None = None) -> Choice:
    """The fastest measured fixed-step configuration whose max error meets ``target_error``, within
    ``time_budget`` if given; when none does, an adaptive integrator with a tolerance.

    Args:
        study_rows: :class:`Measurement` rows (from :func:`run_study` or :func:`warpspring.analysis.trade_report.read_csv`).
        target_error: the largest acceptable max position error [m].
        time_budget: the most wall time per simulated second [s/s], or ``None`` for no limit.
        problem: use only the rows of this problem; needed when the rows hold several.

    Raises:
        ConfigError: a non-positive target or budget, an unknown problem, or rows of several problems
            without ``problem``.
    """
    if not (isinstance(target_error, (int, float)) and math.isfinite(target_error) and target_error > 0):
        raise ConfigError(f"target error must be a finite number > 0 [m], got {target_error!r}")
    if time_budget is not None and not (
        isinstance(time_budget, (int, float)) and math.isfinite(time_budget) and time_budget > 0
    ):
        raise ConfigError(f"time budget must be a finite number > 0 [s per simulated s], got {time_budget!r}")
    rows = list(study_rows)
    problems = list(dict.fromkeys(r.problem for r in rows))
    if problem is not None:
        if problem not in problems:
            raise ConfigError(f"the study has no problem {problem!r}; it has: {', '.join(problems) or 'no rows'}")
        rows = [r for r in rows if r.problem == problem]
    elif len(problems) > 1:
        raise ConfigError(f"the study holds several problems ({', '.join(problems)}): say which one")
    if not rows:
        raise ConfigError("the study has no measurements")

    measured = [r for r in rows if r.status == "ok" and r.error_max is not None and r.wall_per_second is not None]
    fixed = [r for r in measured if r.tolerance is None]
    adaptive = sorted((r for r in measured if r.tolerance is not None), key=lambda r: r.wall_per_second)
    accurate = sorted((r for r in fixed if r.error_max <= target_error), key=lambda r: r.wall_per_second)
    affordable = [r for r in accurate if time_budget is None or r.wall_per_second <= time_budget]
    adaptive_accurate = [r for r in adaptive if r.error_max <= target_error]
    target = f"a max error of at most {target_error:.3g} m"
    if affordable:
        pick = affordable[0]  # fixed steps first: their cost does not depend on how the motion goes
        adaptive_affordable = [r for r in adaptive_accurate if time_budget is None or r.wall_per_second <= time_budget]
        runner_up = _runner_up(sorted(affordable + adaptive_affordable, key=lambda r: r.wall_per_second), pick)
        within = f" within {_rate(time_budget)}" if time_budget is not None else ""
        text = (
            f"{pick.label} is the fastest measured configuration with {target}{within}: error "
            f"{pick.error_max:.3g} m at {_rate(pick.wall_per_second)} on {pick.device}. "
            + _compare(pick, runner_up, f"No other integrator meets the target{within}.")
        )
        return Choice(pick.integrator, {}, pick.dt, pick.precision, pick, runner_up, text)

    if accurate:  # only the budget fails: nothing measured meets both, so name the cheapest that meets the error
        candidates = sorted(accurate + adaptive_accurate, key=lambda r: r.wall_per_second)
        pick = candidates[0]
        runner_up = _runner_up(candidates, pick)
        text = (
            f"No measured configuration has {target} within {_rate(time_budget)}. The cheapest that meets the "
            f"error is {pick.label}: error {pick.error_max:.3g} m at {_rate(pick.wall_per_second)} "
            f"({pick.wall_per_second / time_budget:.3g}× the budget) on {pick.device}. "
            + _compare(pick, runner_up, "No other integrator meets the error.")
            + " Raise the budget or the error target."
        )
        options = {} if pick.tolerance is None else {"tolerance": pick.tolerance}
        return Choice(pick.integrator, options, pick.dt, pick.precision, pick, runner_up, text)

    # No fixed-step configuration reaches the error: an adaptive integrator, measured if possible.
    if fixed:
        closest = min(fixed, key=lambda r: r.error_max)
        why = (
            f"No measured fixed-step configuration reaches {target}: the most accurate, {closest.label}, has "
            f"{closest.error_max:.3g} m at {_rate(closest.wall_per_second)}."
        )
    else:
        closest = None
        why = "The study holds no stable fixed-step measurement."
    if adaptive_accurate:
        pick = adaptive_accurate[0]
        over = time_budget is not None and pick.wall_per_second > time_budget
        text = (
            f"{why} Use {pick.label}: measured error {pick.error_max:.3g} m at {_rate(pick.wall_per_second)}"
            + (f", over the budget of {_rate(time_budget)}." if over else ".")
        )
        return Choice(pick.integrator, {"tolerance": pick.tolerance}, pick.dt, pick.precision, pick, closest, text)
    names = [r.integrator for r in adaptive] or [n for n, c in INTEGRATORS.items() if c.adaptive] or ["dopri5"]
    if adaptive:
        best = min(adaptive, key=lambda r: r.error_max)
        tolerance = _round_down(best.tolerance * target_error / best.error_max)
        text = (
            f"{why} Use {best.integrator} in {best.precision} with a tolerance of about {tolerance:g} (untested: "
            f"scaled from its most accurate measured run, {best.label}, error {best.error_max:.3g} m at "
            f"{_rate(best.wall_per_second)}, assuming error ∝ tolerance); check it with 'warpspring trade'."
        )
        return Choice(best.integrator, {"tolerance": tolerance}, None, best.precision, None, best, text)
    tolerance = _round_down(0.1 * target_error)
    text = (
        f"{why} Use {names[0]} with a tolerance of about {tolerance:g} (a tenth of the target; untested, as the "
        f"study measured no adaptive integrator); check it with 'warpspring trade'."
    )
    return Choice(names[0], {"tolerance": tolerance}, None, None, None, closest, text)


def _runner_up(candidates: list[Measurement], pick: Measurement) -> Measurement | None:
    """The cheapest of ``candidates`` (sorted by cost) with another integrator than ``pick``'s."""
    return next((r for r in candidates if r.integrator != pick.integrator), None)


def _compare(pick: Measurement, runner_up: Measurement | None, otherwise: str) -> str:
    """The sentence on the runner-up: its measured error and cost, relative to the pick's."""
    if runner_up is None:
        return otherwise
    return (
        f"Runner-up: {runner_up.label}, error {runner_up.error_max:.3g} m at {_rate(runner_up.wall_per_second)} "
        f"({runner_up.wall_per_second / pick.wall_per_second:.3g}× the cost)."
    )


def _round_down(value: float) -> float:
    """``value`` rounded down to one significant digit (a tolerance setting)."""
    exponent = math.floor(math.log10(value))
    digit = max(1, math.floor(value / 10**exponent * (1.0 + 1e-12)))  # 0.99999… of a power of ten is that power
    return digit * 10.0**exponent


# -- formatting ---------------------------------------------------------------------------------------------


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.4g} ms"


def _rate(wall_per_second: float) -> str:
    """A cost in wall time per simulated second, in readable units."""
    return f"{format_duration(wall_per_second)} per simulated second"


def _num(value, spec: str) -> str:
    return "—" if value is None else format(value, spec)
