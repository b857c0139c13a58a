"""The speed/accuracy trade on contact scenes: integrator × substeps × precision × contact options, each
against a float64 fine-step reference (the scenes: :mod:`warpspring.analysis.trade_scenes`).

Why these errors. A contact run is a sequence of events (a particle meets the sphere, slides, sticks), and a
small change of step moves an event and, after enough of them, the whole trajectory: no two runs agree
pointwise for long, not even the reference with itself at half its step. So a configuration is judged by

* its **trajectory error over a horizon**: the largest distance of any particle from its place in the
  reference, over the frames up to ``horizon`` [s], chosen per problem to cover the first contacts (the
  cloth lands on the sphere, the ball hits the slab, the handle drags the cloth across the table) and to end
  before the runs diverge; the convergence table shows that the reference itself converges there;
* the **final shape**: the symmetric Hausdorff distance [m] between the particles at the end and the
  reference's (a point set: a cloth that came to rest in the same shape one particle along still counts as the
  same shape), when the scene is at or near rest;
* the scene's **quantity of interest** at the end (drape coefficient, sag, the ball's volume), as the
  difference from the reference's;
* **crossings** (self-colliding scenes: frame ends at which two triangles of the surface intersect, IPC
  Toolkit's exact test) and **guard stops** (the Simulator's run-time guard stopped the run: status
  "stopped").

The headline error, ``error_max`` (what ``warpspring choose`` compares with its target), is the larger of the
trajectory error over the horizon and the Hausdorff distance at the end, in metres. ``warpspring choose``
also refuses a configuration with a crossing.

The reference: symplectic Euler (:data:`REFERENCE_INTEGRATOR`: the contact response is first order whatever
the integrator) in float64 with the scene's reference option (its first: particle contacts where the
builder's rule needs no triangle contacts, the thinner self-collision, two contact slots, the winding-number
inside test), at ``reference_substeps`` per frame, and again at twice and (full
plans) four times as many; the finest is the reference, the others show the convergence: each measure of a
run at h against the run at h/2 (a first-order scheme: the error at the finest is about the last difference).

Cost: wall time per simulated second of a :class:`~warpspring.core.simulator.Simulator` run (its frame
graphs, default guards on), the first frame (compilation, capture) excluded, device synchronised at both ends;
the frame ends are copied on the device into a buffer read after the run. Runs projected past the plan's
``run_limit`` are skipped with the finer ones of that integrator.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np
import warp as wp
from scipy.spatial.distance import directed_hausdorff

from ..core.integrators import INTEGRATORS, make_integrator
from ..core.model import Model
from ..core.simulator import Simulator
from ..errors import ConfigError, SimulationError
from .audit import SurfaceAudit
from .trade import FULL, QUICK, Measurement, StudyPlan
from .trade_problems import BLOWUP_FACTOR, SpringNetwork
from .trade_scenes import SCENES, Option, Scene, build, quantity

#: Output frames per second of every contact run [1/s]; a configuration's step is 1 / (FPS · substeps).
FPS = 60.0
#: The integrators that apply to contact scenes: all but explicit Euler, unstable on any undamped spring at
#: any step (its amplification is √(1 + (ωh)²) > 1).
CONTACT_INTEGRATORS = ("symplectic_euler", "velocity_verlet", "midpoint", "rk4", "implicit_euler", "dopri5")
#: The references' integrator. The contact response is a first-order projection after every step whatever the
#: integrator, so a higher-order one buys no order at contact: the references use the cheapest step, refined.
REFERENCE_INTEGRATOR = "symplectic_euler"
#: A multi-stage integrator run at the references' two finest steps, against the reference: whether its
#: difference shrinks with the step, i.e. whether it approaches the same motion (its stages do not see the
#: contacts, which the response handles after the step).
CROSS_CHECK = "rk4"


@dataclass(frozen=True)
class ContactReference:
    """The float64 references of one option of a contact problem.

    Attributes:
        integrator: integrator name; substeps: per frame of each run, coarse to fine (the last is the reference).
        frames: frame-end positions [m] of the finest run, shape [frames + 1, particles, 3] (row 0: the start).
        quantity: the scene's quantity of interest at the end of the finest run.
        convergence: per refinement, the measures of the run at h against the run at h/2 (:func:`measures`),
            and its wall time [s]: a list of dicts, coarse to fine.
        cross_check: :data:`CROSS_CHECK` (float64, reference option) at the two finest reference steps against
            the reference (full plans): the same list of dicts with ``integrator``; empty in quick plans.
        max_strain: the finest run's largest spring strain at the end, or ``None`` without springs.
        wall: wall time of all the reference runs [s].
    """

    integrator: str
    substeps: tuple[int, ...]
    frames: np.ndarray
    quantity: float
    convergence: list = field(default_factory=list)
    cross_check: list = field(default_factory=list)
    max_strain: float | None = None
    wall: float = 0.0


@dataclass(frozen=True)
class ContactProblem:
    """A contact scene in the study.

    Attributes:
        name: the scene's name (a key of :data:`~warpspring.analysis.trade_scenes.SCENES`) and the problem's.
        size: the cloth's particles along a side (ignored by the balls).
        duration: simulated time of each run [s]; horizon: of the trajectory error [s].
        substeps: the fixed-step runs, as steps per frame at :data:`FPS`, coarse to fine.
        options: the contact options' labels measured (``None``: all of the scene's).
        reference_substeps: the coarsest reference's steps per frame.
        refinements: reference runs beyond the coarsest (each at twice the steps): 1 or 2.
        integrators: the integrators measured (those of ``CONTACT_INTEGRATORS`` that are registered).
        tolerances: the adaptive integrators' tolerances, loose to tight.
    """

    contact: ClassVar[bool] = True
    records_trajectory: ClassVar[bool] = False

    name: str
    size: int
    duration: float
    horizon: float
    substeps: tuple[int, ...]
    options: tuple[str, ...] | None = None
    reference_substeps: int = 160
    refinements: int = 2
    integrators: tuple[str, ...] = CONTACT_INTEGRATORS
    tolerances: tuple[float, ...] = (1e-3, 1e-5)

    @property
    def scene(self) -> Scene:
        return SCENES[self.name]

    @property
    def length_scale(self) -> float:
        return self.scene.length_scale

    @property
    def measured_options(self) -> tuple[Option, ...]:
        if self.options is None:
            return self.scene.options
        return tuple(self.scene.option(label) for label in self.options)

    @property
    def frames(self) -> int:
        return int(round(self.duration * FPS))

    def describe(self) -> str:
        """One line: the scene at its size, the run and the horizon."""
        size = "" if self.name.startswith("softball") else f" at {self.size} particles a side"
        return (f"{self.name}{size} ({build.__module__}.build_{self.name.split('-')[0]}); {self.duration:g} s "
                f"simulated at {FPS:g} frames/s, trajectory error over the first {self.horizon:g} s; quantity of "
                f"interest: {self.scene.quantity}")

    def applicable(self, names) -> list[str]:
        """The integrators of ``names`` that apply to contact scenes."""
        return [n for n in names if n in self.integrators]

    def configurations(self, name: str, plan: StudyPlan) -> list[tuple[int, float | None]]:
        """(substeps, tolerance) of each run of integrator ``name``, cheapest first (adaptive: the coarsest
        substeps as their output interval, over the plan's tolerances)."""
        if INTEGRATORS[name].adaptive:
            return [(min(self.substeps), tol) for tol in self.tolerances]
        return [(n, None) for n in sorted(self.substeps)]

    def count(self, names, plan: StudyPlan) -> int:
        """Runs measured for ``names`` (per precision, all options)."""
        return sum(len(self.configurations(n, plan)) for n in self.applicable(names)) * len(self.measured_options)

    def build(self, device, precision: str, option: Option) -> Model:
        return build(self.name, self.size, device, precision, option)

    def measure(self, device, plan: StudyPlan, names, *, done=None) -> tuple[list[Measurement], ContactReference]:
        """The reference (the scene's reference option), then every applicable integrator × configuration ×
        precision × option. ``done()`` is called after each run."""
        reference = compute_reference(self, device)
        rows = []
        for precision in plan.precisions:
            for option in self.measured_options:
                for name in self.applicable(names):
                    too_slow = False
                    for substeps, tolerance in self.configurations(name, plan):
                        if too_slow:
                            row = _row(self, name, precision, device, substeps, tolerance, option, status="skipped")
                        else:
                            row = measure_run(self, device, precision, option, name, substeps, tolerance, reference,
                                              plan.run_limit)
                            too_slow = row.status == "skipped"
                        rows.append(row)
                        if done is not None:
                            done()
        return rows, reference


# -- runs ---------------------------------------------------------------------------------------------------


@dataclass
class _Run:
    frames: np.ndarray | None  # [frames + 1, particles, 3], float64, row 0 the start; None when not run
    wall_per_second: float | None
    steps_per_second: float | None
    error: str | None = None  # the guard's message when it stopped the run
    crossings: int | None = None


def run(problem: ContactProblem, model: Model, name: str, substeps: int, tolerance: float | None, *,
        run_limit: float | None = None, audit: bool = False) -> _Run:
    """Run ``model`` for the problem's duration; frame ends copied on the device, read after the run. A run
    whose second frame projects past ``run_limit`` [s] stops there (``frames`` is ``None``)."""
    options = {} if tolerance is None else {"tolerance": tolerance}
    integrator = make_integrator(name, model, **options)
    sim = Simulator(model, integrator=integrator, fps=FPS, substeps=substeps)
    n, frames = model.particle_count, problem.frames
    buffer = wp.empty((frames + 1) * n, dtype=model.vec3, device=model.device)
    wp.copy(buffer, sim.state.particle_q, dest_offset=0, count=n)
    error, wall, done = None, 0.0, 0
    try:
        sim.step_frame()  # compiles and captures: not timed
        wp.copy(buffer, sim.state.particle_q, dest_offset=n, count=n)
        done = 1
        wp.synchronize_device(model.device)
        start = time.perf_counter()
        for frame in range(2, frames + 1):
            sim.step_frame()
            wp.copy(buffer, sim.state.particle_q, dest_offset=frame * n, count=n)
            done = frame
            if frame == 2 and run_limit is not None:
                wp.synchronize_device(model.device)
                if (time.perf_counter() - start) * (frames - 1) > run_limit:
                    return _Run(None, (time.perf_counter() - start) * FPS, None)
        wp.synchronize_device(model.device)
        wall = time.perf_counter() - start
    except SimulationError as failure:
        error = str(failure)
    q = buffer.numpy().reshape(frames + 1, n, 3)[: done + 1].astype(np.float64)  # frames after a stop: unwritten
    steps = _steps_per_second(integrator, sim, substeps)
    per_second = wall / ((done - 1) / FPS) if error is None and done > 1 else None
    crossings = _crossings(model, q) if audit and error is None else None
    return _Run(q, per_second, steps, error, crossings)


def _steps_per_second(integrator, sim: Simulator, substeps: int) -> float:
    accepted = getattr(integrator, "accepted_steps", None)
    if accepted:  # adaptive: accepted + rejected internal steps over the simulated time
        return (accepted + getattr(integrator, "rejected_steps", 0)) / max(sim.time, 1e-12)
    return FPS * substeps


def _crossings(model: Model, q: np.ndarray) -> int | None:
    """Frame ends (after the start) at which two triangles of the self-colliding surface intersect; ``None``
    where IPC Toolkit (the audit's optional dependency) is missing."""
    triangles = model.self_contact.surface.triangle.numpy()
    surface = SurfaceAudit(triangles)
    try:
        return int(sum(len(surface.intersections(x)) > 0 for x in q[1:]))
    except ConfigError:  # no ipctk: crossings unmeasured ("—" in the table), the study goes on
        return None


def measures(problem: ContactProblem, model: Model, q: np.ndarray, reference_frames: np.ndarray,
             reference_quantity: float) -> dict:
    """The errors of frame ends ``q`` [m] (shape [frames + 1, n, 3]) against a reference's: the
    :class:`~warpspring.analysis.trade.Measurement` fields they determine."""
    horizon = int(round(problem.horizon * FPS)) + 1
    distance = np.linalg.norm(q[:horizon] - reference_frames[:horizon], axis=2)
    end, ref_end = q[-1], reference_frames[-1]
    hausdorff = max(directed_hausdorff(end, ref_end)[0], directed_hausdorff(ref_end, end)[0])
    value = quantity(problem.name, model, end, q[0])
    return {
        "error_horizon": float(distance.max()),
        "error_rms": float(np.sqrt(np.mean(distance**2))),
        "hausdorff": float(hausdorff),
        "error_end": float(np.linalg.norm(end - ref_end, axis=1).max()),
        "quantity": float(value),
        "quantity_error": float(abs(value - reference_quantity)),
    }


def _max_strain(model: Model, q: np.ndarray) -> float | None:
    if model.spring_count == 0:
        return None
    return SpringNetwork.of(model).max_strain(q)


def compute_reference(problem: ContactProblem, device) -> ContactReference:
    """The float64 runs of the reference option at ``reference_substeps`` × 1, 2 (, 4) per frame."""
    name = REFERENCE_INTEGRATOR
    option = problem.scene.options[0]
    model = problem.build(device, "float64", option)
    start = time.perf_counter()
    runs, counts = [], [problem.reference_substeps * 2**k for k in range(problem.refinements + 1)]
    for substeps in counts:
        begun = time.perf_counter()
        result = run(problem, model, name, substeps, None)
        if result.error is not None or not np.isfinite(result.frames).all():
            raise SimulationError(f"the {problem.name} reference ({name}, {substeps} substeps per frame, float64) "
                                  f"failed: {result.error or 'non-finite positions'}")
        runs.append((result.frames, time.perf_counter() - begun))
    finest = runs[-1][0]
    end_quantity = quantity(problem.name, model, finest[-1], finest[0])
    convergence = []
    for k in range(len(runs) - 1):
        (coarse, _), (fine, wall) = runs[k], runs[k + 1]
        fine_quantity = quantity(problem.name, model, fine[-1], fine[0])
        row = measures(problem, model, coarse, fine, fine_quantity)
        row.update(substeps=counts[k], wall=wall, quantity_fine=fine_quantity)
        convergence.append(row)
    cross_check = []
    if problem.refinements >= 2 and CROSS_CHECK in INTEGRATORS:
        for substeps in counts[-2:]:
            begun = time.perf_counter()
            result = run(problem, model, CROSS_CHECK, substeps, None)
            if result.error is not None or not np.isfinite(result.frames).all():
                cross_check.append(dict(integrator=CROSS_CHECK, substeps=substeps, error=result.error or "non-finite"))
                continue
            row = measures(problem, model, result.frames, finest, end_quantity)
            row.update(integrator=CROSS_CHECK, substeps=substeps, wall=time.perf_counter() - begun)
            cross_check.append(row)
    return ContactReference(integrator=name, substeps=tuple(counts), frames=finest, quantity=end_quantity,
                            convergence=convergence, cross_check=cross_check,
                            max_strain=_max_strain(model, finest[-1]), wall=time.perf_counter() - start)


def _row(problem, name, precision, device, substeps, tolerance, option, **fields) -> Measurement:
    cls = INTEGRATORS[name]
    adaptive = cls.adaptive
    named = dict(steps_per_second=None if adaptive else FPS * substeps,
                 mean_step=None if adaptive else 1.0 / (FPS * substeps), wall_per_second=None)
    return Measurement(problem=problem.name, integrator=name, order=cls.order, precision=precision,
                       device=wp.get_device(device).alias, dt=1.0 / (FPS * substeps), tolerance=tolerance,
                       option=option.label, horizon=problem.horizon, **{**named, **fields})


def measure_run(problem: ContactProblem, device, precision: str, option: Option, name: str, substeps: int,
                tolerance: float | None, reference: ContactReference, run_limit: float) -> Measurement:
    """One configuration: run it and judge it against ``reference``."""
    model = problem.build(device, precision, option)
    result = run(problem, model, name, substeps, tolerance, run_limit=run_limit, audit=problem.scene.self_collision)
    fields = dict(wall_per_second=result.wall_per_second)
    if result.frames is None:
        return _row(problem, name, precision, device, substeps, tolerance, option, status="skipped", **fields)
    if INTEGRATORS[name].adaptive and result.steps_per_second:
        fields.update(steps_per_second=result.steps_per_second, mean_step=1.0 / result.steps_per_second)
    if result.error is not None:
        return _row(problem, name, precision, device, substeps, tolerance, option, status="stopped", **fields)
    q = result.frames
    if not np.isfinite(q).all():
        return _row(problem, name, precision, device, substeps, tolerance, option, status="non-finite", **fields)
    judged = measures(problem, model, q, reference.frames, reference.quantity)
    if max(judged["error_horizon"], judged["hausdorff"]) > BLOWUP_FACTOR * problem.length_scale:
        return _row(problem, name, precision, device, substeps, tolerance, option, status="blown up", **fields)
    return _row(problem, name, precision, device, substeps, tolerance, option, status="ok",
                error_max=max(judged["error_horizon"], judged["hausdorff"]), max_strain=_max_strain(model, q[-1]),
                crossings=result.crossings, **judged, **fields)


# -- plans --------------------------------------------------------------------------------------------------

#: The full contact problems: a few minutes each on a CPU.
FULL_PROBLEMS = {
    "drape": ContactProblem("drape", size=16, duration=2.0, horizon=0.5, substeps=(10, 20, 40, 80),
                            reference_substeps=160),
    "stack": ContactProblem("stack", size=10, duration=1.0, horizon=0.4, substeps=(10, 20, 40),
                            reference_substeps=80),
    "tablecloth": ContactProblem("tablecloth", size=16, duration=3.0, horizon=1.5, substeps=(10, 20, 40, 80),
                                 reference_substeps=160),
    "softball": ContactProblem("softball", size=0, duration=1.5, horizon=0.4, substeps=(5, 10, 20, 40),
                               reference_substeps=80),
    "softball-neohookean": ContactProblem("softball-neohookean", size=0, duration=1.5, horizon=0.4,
                                          substeps=(10, 20, 40), reference_substeps=80),
}

#: The quick contact problems: small, few configurations, one refinement of the reference.
QUICK_PROBLEMS = {
    "drape": ContactProblem("drape", size=8, duration=1.0, horizon=0.4, substeps=(10, 20),
                            options=("triangle contacts", "particle contacts"), reference_substeps=40, refinements=1,
                            integrators=("symplectic_euler",)),
    # The landing of both layers only: past it, sliding off the box's edges, 6² runs at 10-20 substeps part ways from
    # the reference (measured: 27-32 mm at 0.2 s, 0.14-0.15 m at 0.3 s, growing as the step shrinks).
    "stack": ContactProblem("stack", size=6, duration=0.15, horizon=0.15, substeps=(10, 20), options=("τ = 4 mm",),
                            reference_substeps=40, refinements=1, integrators=("symplectic_euler",)),
    "tablecloth": ContactProblem("tablecloth", size=8, duration=1.5, horizon=1.0, substeps=(10, 20),
                                 options=("2 slots",), reference_substeps=40, refinements=1,
                                 integrators=("symplectic_euler",)),
    "softball": ContactProblem("softball", size=0, duration=0.5, horizon=0.4, substeps=(10, 20),
                               options=("pseudo-normals",), reference_substeps=40, refinements=1,
                               integrators=("symplectic_euler",)),
    "softball-neohookean": ContactProblem("softball-neohookean", size=0, duration=0.5, horizon=0.4,
                                          substeps=(10, 20), options=("pseudo-normals",), reference_substeps=40,
                                          refinements=1, integrators=("symplectic_euler",)),
}

def _reduced(problem: ContactProblem) -> ContactProblem:
    """The full-size scene with fewer runs: its reference option, 20 and 40 substeps, dopri5 at 1e-3, one reference
    refinement (the errors against the reference at 2 × ``reference_substeps``)."""
    return replace(problem, options=(problem.scene.options[0].label,), substeps=(20, 40), refinements=1,
                   tolerances=(1e-3,))


#: The reduced contact problems: the full scenes' sizes and durations (costs comparable with the full study's rows),
#: every integrator at two steps, the reference option only; about a minute for all five on a CPU (the GPU rows).
REDUCED_PROBLEMS = {name: _reduced(problem) for name, problem in FULL_PROBLEMS.items()}

#: Every problem's name: the closed forms and the hanging cloth first, then the contact scenes.
PROBLEMS = tuple(p.name for p in FULL.problems) + tuple(FULL_PROBLEMS)


def study_plan(problems=None, *, quick: bool = False, reduced: bool = False) -> StudyPlan:
    """The plan of ``problems`` (names of :data:`PROBLEMS`; ``None``: the closed forms and the hanging cloth, as
    :data:`~warpspring.analysis.trade.FULL` / :data:`~warpspring.analysis.trade.QUICK`), full or quick; ``reduced``:
    the contact problems of :data:`REDUCED_PROBLEMS` (the closed forms and the cloth as in the full plan).

    Raises:
        ConfigError: an unknown problem name, or quick and reduced together.
    """
    if quick and reduced:
        raise ConfigError("choose one of quick and reduced")
    base = QUICK if quick else FULL
    if problems is None:
        return base
    names = list(dict.fromkeys(problems))
    unknown = [n for n in names if n not in PROBLEMS]
    if unknown:
        raise ConfigError(f"unknown problem {unknown[0]!r}: choose from {', '.join(PROBLEMS)}")
    contact = QUICK_PROBLEMS if quick else REDUCED_PROBLEMS if reduced else FULL_PROBLEMS
    chosen = [p for p in base.problems if p.name in names] + [contact[n] for n in names if n in contact]
    return StudyPlan(name="reduced" if reduced else base.name, problems=tuple(chosen), precisions=base.precisions, tolerances=base.tolerances,
                     repeats=base.repeats, min_batch=base.min_batch, run_limit=base.run_limit)
