"""The speed/accuracy trade of the integrators, measured.

For every registered integrator × time step × precision (float32, float64) a study measures the wall
time per simulated second and the error against a reference, on the problems of
:mod:`warpspring.analysis.trade_problems` (the seed spring, a stiff spring, the hanging cloth). The cloth's
reference is a float64 RK4 run (the highest-order fixed-step integrator when RK4 is not registered) at a step
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
exact solution). :func:`warpspring.analysis.trade_choice.choose` picks the cheapest measured configuration
that meets an error target.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from ..core.control import Control
from ..core.integrators import INTEGRATORS, Integrator, make_integrator
from ..core.model import Model
from ..core.stepper import StepHook, Stepper
from ..errors import ConfigError, SimulationError
from .engines import map_jobs
from .omega import estimate_omega_max
from .trade_problems import SEED, STIFF, ClothProblem, ClothReference, SpringNetwork, SpringProblem

#: The cloth reference runs at the finest tested step divided by this.
REFERENCE_REFINEMENT = 16
#: Most steps captured in one graph (capturing costs as much Python time per step as running uncaptured).
MAX_CHUNK = 64
#: Status of a measured configuration (see :class:`Measurement`).
STATUSES = ("ok", "non-finite", "blown up", "failed", "skipped", "stopped")


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
            (SimulationError); "skipped": the run would take longer than the plan's ``run_limit``; "stopped":
            the Simulator's run-time guard stopped a contact run.
        error_max: springs: max over the steps of |x − x_exact| [m]; cloth: max over the particles of
            |x − x_ref| at the end [m].
        error_rms: the RMS of the same errors (over steps, or over particles) [m].
        error_end: springs: |x − x_exact| at the end [m]; cloth: ``None`` (compared at the end only).
        energy_drift: mechanical energy at the end minus the reference's, over the energy the motion
            is given [-]: springs: E(0) − E(rest); cloth: the gravitational energy the reference
            released. > 0: energy gained, < 0: lost (numerical damping).
        max_strain: cloth: max over the springs of (|d| − L) / L at the end [-]; springs: ``None``.
        option: contact scenes: the contact options' label (:mod:`warpspring.analysis.trade_scenes`); else ``None``.
        horizon: contact scenes: the trajectory error's horizon [s].
        error_horizon: contact scenes: max over the frames up to the horizon and the particles of |x − x_ref| [m].
        hausdorff: contact scenes: symmetric Hausdorff distance of the particles at the end to the reference's [m].
        quantity: contact scenes: the quantity of interest at the end (drape coefficient, sag [m], volume ratio).
        quantity_error: contact scenes: |quantity − the reference's| (the quantity's unit).
        crossings: self-colliding scenes: frame ends at which triangles of the surface intersect; else ``None``.
        device_name: the device's name (GPU model, or CPU model and cores), as :attr:`Study.device_name`; ``None``
            in studies written before it was recorded.
        (Contact scenes: ``error_max`` is max(error_horizon, hausdorff), ``error_rms`` the RMS of the distances
        over the horizon, ``error_end`` the max distance at the end: :mod:`warpspring.analysis.trade_contact`.)
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
    option: str | None = None
    horizon: float | None = None
    error_horizon: float | None = None
    hausdorff: float | None = None
    quantity: float | None = None
    quantity_error: float | None = None
    crossings: int | None = None
    device_name: str | None = None

    @property
    def setting(self) -> str:
        """The step or tolerance: "dt = 1.042 ms" or "tolerance 1e-06"."""
        return f"dt = {_ms(self.dt)}" if self.tolerance is None else f"tolerance {self.tolerance:g}"

    @property
    def label(self) -> str:
        """Short configuration name: "rk4, dt = 1.042 ms, float32", "dopri5, tolerance 1e-06, float64", or with
        contact options "symplectic_euler, dt = 0.8333 ms, float32, triangle contacts"."""
        label = f"{self.integrator}, {self.setting}, {self.precision}"
        return label if self.option is None else f"{label}, {self.option}"


@dataclass
class Study:
    """The result of :func:`run_study`.

    Attributes:
        plan: what was measured.
        rows: one measurement per configuration.
        device: Warp device alias.
        device_name: the device's name (GPU model, or CPU model and core count).
        references: the cloth's and the contact scenes' references by problem name.
        trajectories: the seed plot's runs: label → (t [s], x [m], v [m/s]), each of shape [samples].
        elapsed: wall time of the whole study [s].
        warp_version, date, command: provenance for the report (the command line, when the caller sets it).
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
    command: str = ""

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
        if any(_is_contact(p) for p in plan.problems):
            raise ConfigError("a sweep engine runs the closed forms and the hanging cloth only: measure the contact "
                              "problems without --ray")
        _run_on(engine, study, device.alias, names, progress)
        study.rows = [dataclasses.replace(r, device_name=study.device_name) for r in study.rows]
        study.elapsed = time.perf_counter() - start
        return study
    total = sum(
        problem.count(names, plan) * len(plan.precisions) if _is_contact(problem) else
        sum(len(_configurations(problem, INTEGRATORS[name], plan)) * len(plan.precisions) for name in names)
        for problem in plan.problems
    )
    with tqdm(total=total, unit="run", disable=not progress, dynamic_ncols=True, leave=False) as bar:
        for problem in plan.problems:
            if _is_contact(problem):  # a contact scene measures itself (warpspring.analysis.trade_contact)
                bar.set_description(f"{problem.name}: reference and runs")
                rows, study.references[problem.name] = problem.measure(device, plan, names, done=lambda: bar.update(1))
                study.rows += rows
                continue
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
    study.rows = [dataclasses.replace(r, device_name=study.device_name) for r in study.rows]  # each row names it
    study.elapsed = time.perf_counter() - start
    return study


def _is_contact(problem) -> bool:
    """Whether ``problem`` is a contact scene (:class:`~warpspring.analysis.trade_contact.ContactProblem`)."""
    return getattr(problem, "contact", False)


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


# -- formatting ---------------------------------------------------------------------------------------------


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:.4g} ms"
