"""``substeps = "auto"``: the step a run takes when none is given, chosen once before capture.

* **Explicit integrators** (explicit Euler, symplectic Euler, velocity Verlet, midpoint, RK4): the fewest substeps
  per frame whose step the advisor passes with a margin, dt ≤ ``STABILITY_MARGIN`` × the largest step it passes
  in the binding world (:attr:`~.advisor.Advice.dt_passed`: every world, the states the run reaches, its tracks
  over the dry run; a drag track at its least and its most drag). Where the advisor finds no stable step
  (explicit Euler and midpoint on springs without damping) the choice is refused with its message, which
  recommends symplectic Euler, velocity Verlet or implicit Euler.
* **Implicit Euler** passes any step: the fewest substeps, doubling from 1, whose position error over a frame
  stays within the accuracy floor [m], estimated by step doubling (a first-order method's error at n substeps is
  about twice its difference from 2n) over the first ``ACCURACY_HORIZON`` seconds of the run. The floor is read
  from the measured trade table the package ships (:mod:`~warpspring.analysis.trade_table`): on the hanging
  cloth, the geometric mean of the errors of symplectic Euler and velocity Verlet at the coarsest steps they ran
  stably (3.15e-3 and 5.08e-4 m over its 1 s run on the CPU study: a floor of 1.26e-3 m), so that implicit Euler on
  auto lands among the explicit integrators on theirs.
* **dopri5** meets its own tolerance at any outer step (``tolerance``): one substep per frame, more where the
  internal steps that stability caps per frame would pass a tenth of its ``max_steps``, and more (doubling) until
  the same step-doubling estimate meets the floor (twice the difference is an upper estimate for any order ≥ 1).
* **Contacts** (any integrator, with colliders): contacts are projections after each step, which the advisor
  does not analyse; a particle may move at most ``CONTACT_TRAVEL`` × its contact radius r per step at the speed
  it can reach, v = its start speed + √(2 g Δh), Δh its fall from its highest start to the lowest collider's top:
  dt ≤ ``CONTACT_TRAVEL`` · r / v. The quarter is measured: seed 002's soft cloth dropped 0.26 m onto a 4 cm
  sphere keeps its surface outside the sphere from r/4 per step (16 substeps: 4.6 cm from its centre) and not at
  r/2 (8 substeps: 2.7 cm); ``tests/test_contact_rule.py``.
* **Pins and self-collision**: where a model with self-collision has pins driven by tracks, each step moves a pin
  at most ``PIN_TRAVEL`` × ρ, ρ = γ τ the most the self-collision cap's passes move a free vertex in a step to give
  way to it (γ the relaxation, τ the thickness): dt ≤ ``PIN_TRAVEL`` · γ τ / v, v the pins' fastest speed on their
  tracks (sampled at the keys and ``PIN_SAMPLES`` times between each two). The quarter is measured: the torture
  battery's twist1440 (pins at 3.8 m/s, γ τ = 1.25 mm) crossed at 20 substeps (2.5 ρ a step) and at 60 (0.84 ρ),
  and ran clean at 101 (0.5 ρ); at half the reach a step, pins squeezing a coil of free layers still closed pairs
  below τ/2 (the 720° twist at full duration, 21 substeps, and a start moved by 1 µm, on the CPU; the full-size
  1440° twist under RK4 on CUDA, 41 substeps), where at a quarter (42 substeps) the 720° twist ran clean from five
  starts under symplectic Euler and RK4 (``bench/results/torture_cpu_full.md``); ``tests/test_torture.py``.
* **A measured contact scene**: where the model is one the trade table measured (:meth:`~.trade_table.TradeTable.match`:
  the same counts, colliders, contact options, masses, springs and start), the table's rows of its integrator,
  precision and contact option (and tolerance) that ran clean within the accuracy floor (their error: the larger of
  the trajectory error over the problem's horizon and the final shape's Hausdorff distance, against a float64
  fine-step reference, an upper bound of what any frame adds) give the fewest measured substeps; they are taken
  when fewer than the rules above ask (the measured run replaces the travel bound and the margin; the advisor still
  judges the step before the run). Where the table needs more than the rules give for the floor, the reason says so.
  The rows cover the measured problem's own run (1-3 s, to rest or near it; ``trade_contact.FULL_PROBLEMS``).

The core's :class:`~warpspring.core.simulator.Simulator` cannot reach this layer: it takes a step chooser,
``Simulator(model, substeps=auto_substeps)``, and calls it once before it captures; scene files and
``warpspring run`` use :func:`choose_substeps` (the runner prints its reason).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .. import checks
from ..errors import ConfigError
from ..core.integrators import Integrator, ImplicitEuler, make_integrator
from ..core.model import Model
from ..core.selfcontact import PARAM_RELAXATION, PARAM_THICKNESS
from ..core.simulator import Simulator
from ..core.transforms import quat_to_matrix
from .advisor import Advice, advise, shared_estimates
from .stability import _integrator_class
from .trade_table import TableRow, TradeTable, load_table
from .under_load import PROBE_HORIZON, _keeps_plasticity

#: Auto substeps keep dt at most this fraction of the advisor's largest stable step.
STABILITY_MARGIN = 0.9
#: Implicit Euler's and dopri5's position error over a frame (the accuracy floor) is measured over this much of
#: the run [s].
ACCURACY_HORIZON = 0.25
#: The most substeps per frame auto chooses for accuracy (implicit Euler); beyond it, set them by hand.
MAX_ACCURACY_SUBSTEPS = 256
#: With colliders, a particle moves at most this fraction of its contact radius per step.
CONTACT_TRAVEL = 0.25
#: With self-collision, a driven pin moves at most this fraction of the cap's reach γ τ per step.
PIN_TRAVEL = 0.25
#: Samples of a pin track between each two of its keys, where its speed is read.
PIN_SAMPLES = 256


@dataclass(frozen=True)
class SubstepChoice:
    """What ``substeps = "auto"`` chose and why.

    Attributes:
        substeps: integrator steps per 1/fps frame.
        dt: the step [s], 1 / (fps · substeps).
        reason: one line for the run summary (what bound it: the stability limit and the margin, or the
            accuracy floor).
        advice: the advisor's verdict at ``dt`` (None for implicit Euler, which the accuracy floor binds).
        error: implicit Euler, dopri5: the estimated position error over a frame at ``substeps`` [m]; a measured
            contact scene's row: its error [m]; else NaN.
        row: the trade table's row the choice was taken from (a measured contact scene), or ``None``.
    """

    substeps: int
    dt: float
    reason: str
    advice: Advice | None = None
    error: float = math.nan
    row: TableRow | None = None


def choose_substeps(model: Model, integrator: Integrator | str, *, fps: float = 60.0, control=None,
                    horizon: float = PROBE_HORIZON, table: TradeTable | str | None = None) -> SubstepChoice:
    """The substeps ``"auto"`` stands for (this module's docstring), for ``model`` stepped by ``integrator`` (an
    instance, or a registry name for the explicit ones and dopri5) at ``fps`` [1/s] with ``control``;
    ``horizon`` [s]: how long the run lasts, for the advisor's growth figures and dry run. The larger of the
    integrator's choice and the contacts' (:func:`contact_substeps`), or fewer where the trade table measured this
    scene within the accuracy floor. ``table``: the measured trade table (a :class:`~.trade_table.TradeTable` or
    its path; default: the package's, :func:`~.trade_table.load_table`).

    Raises:
        ConfigError: an integrator that is unstable at every step for these springs (the advisor's message); a
            missing or malformed table.
    """
    fps = checks.positive("fps", fps)
    table = table if isinstance(table, TradeTable) else load_table(table)
    with shared_estimates():  # the steps judged below share the model's ω_max (the static solve, the dry run)
        return _choose(model, integrator, fps, control, horizon, table)


def _choose(model: Model, integrator: Integrator | str, fps: float, control, horizon: float,
            table: TradeTable) -> SubstepChoice:
    """:func:`choose_substeps`' body."""
    choice = _over_drag_track(model, lambda: _integrator_substeps(model, integrator, fps, control, horizon, table))
    contact = max(filter(None, [contact_substeps(model, fps=fps), pin_substeps(model, fps=fps)]), default=None)
    if contact is not None and contact[0] > choice.substeps:
        substeps, why = contact
        dt = 1.0 / (fps * substeps)
        name = integrator if isinstance(integrator, str) else integrator.name
        advice = choice.advice
        if advice is not None and not _integrator_class(name).adaptive:  # the verdict at the step taken
            advice = advise(model, name, dt, fps=fps, control=control, horizon=horizon)
        reason = (f"{substeps} substeps per 1/{fps:g} s frame (dt = {dt * 1e3:.4g} ms) for the contacts: {why} (the "
                  f"integrator alone: {choice.reason})")
        choice = SubstepChoice(substeps, dt, reason, advice, choice.error)
    return _measured(model, integrator, fps, table, choice)


def _measured(model: Model, integrator: Integrator | str, fps: float, table: TradeTable,
              choice: SubstepChoice) -> SubstepChoice:
    """``choice``, or the trade table's fewest substeps within the floor where the model is a measured contact scene
    and they are fewer (this module's docstring)."""
    if not model.shape_count and model.self_contact is None:
        return choice
    key = table.match(model)
    if key is None:
        return choice
    name = integrator if isinstance(integrator, str) else integrator.name
    tolerance = getattr(integrator, "tolerance", None) if _integrator_class(name).adaptive else None
    _, rows = table.problems[key]
    fits = [r for r in rows if r.integrator == name and r.precision == model.precision and r.error <= table.floor
            and (r.tolerance is None) == (tolerance is None)
            and (tolerance is None or math.isclose(r.tolerance, tolerance, rel_tol=1e-9))]
    if not fits:
        return choice
    row = min(fits, key=lambda r: (r.substeps(fps), r.error))
    substeps = row.substeps(fps)
    measured = f"the trade table's row {row.describe()} (measured on {table.provenance(row)})"
    if substeps >= choice.substeps:
        extra = "" if substeps == choice.substeps else (
            f"; this scene reaches the accuracy floor of {table.floor:.3g} m at {substeps} substeps on {measured}: "
            "give more substeps for that accuracy")
        return SubstepChoice(choice.substeps, choice.dt, choice.reason + extra, choice.advice, choice.error)
    dt = 1.0 / (fps * substeps)
    reason = (f"{substeps} substep{'s' if substeps > 1 else ''} per 1/{fps:g} s frame (dt = {dt * 1e3:.4g} ms): this "
              f"scene is one the trade table measured, its row {row.describe()} within the accuracy floor of "
              f"{table.floor:.3g} m (measured on {table.provenance(row)}); fewer than the {choice.substeps} the rules "
              f"ask ({choice.reason})")
    return SubstepChoice(substeps, dt, reason, None, row.error, row)


def _over_drag_track(model: Model, choose) -> SubstepChoice:
    """``choose()`` at the model's drag, or, where a world's drag is a keyframe track, at the least and the most drag
    its tracks reach (drag lowers symplectic Euler's limit and raises explicit Euler's): the choice of more
    substeps. The tracks are put back after."""
    tracks = [model.track("drag", world=w) for w in range(model.world_count)]
    if all(t is None for t in tracks):
        return choose()
    values = np.concatenate([np.asarray(t.values, dtype=np.float64).ravel() for t in tracks if t is not None])
    current = model.world_values("drag")[:, 0]
    values = np.concatenate([values, current])
    try:
        choices = []
        for drag in sorted({float(values.min()), float(values.max())}):
            model.set_world_values("drag", drag)
            choices.append(choose())
    finally:
        model.set_world_values("drag", current)
        for w, track in enumerate(tracks):
            if track is not None:
                model.set_track("drag", track, world=w)
    best = max(choices, key=lambda c: c.substeps)
    return SubstepChoice(best.substeps, best.dt, best.reason + f" (over the drag track's {values.min():g}…"
                         f"{values.max():g} N·s/m)", best.advice, best.error)


def contact_substeps(model: Model, *, fps: float) -> tuple[int, str] | None:
    """The substeps per 1/``fps`` frame the contacts need (this module's docstring: dt ≤ ``CONTACT_TRAVEL`` · r / v),
    and why; ``None`` without colliders, gravity or start speed, or with particles of no contact radius."""
    n = model.particle_count
    if not model.shape_count or n == 0:
        return None
    radius = float(np.min(model.particle_radius.numpy()))
    gravity = np.asarray(model.world_values("gravity"), dtype=np.float64).reshape(-1, 3)
    for w in range(model.world_count):
        track = model.track("gravity", world=w)
        if track is not None:
            gravity = np.concatenate([gravity, np.asarray(track.values, dtype=np.float64).reshape(-1, 3)])
    g = float(np.linalg.norm(gravity, axis=1).max())
    q = model.particle_q.numpy().astype(np.float64).reshape(-1, 3)
    speed = float(np.linalg.norm(model.particle_qd.numpy().astype(np.float64).reshape(-1, 3), axis=1).max())
    if radius <= 0.0 or (g == 0.0 and speed == 0.0):
        return None
    up = -np.mean(gravity, axis=0) if g > 0.0 else np.zeros(3)
    norm = float(np.linalg.norm(up))
    up = up / norm if norm > 0.0 else np.zeros(3)
    drop = max(0.0, float((q @ up).max()) - min(_top(shape, up) for shape in model.shapes)) if norm > 0.0 else 0.0
    v = speed + math.sqrt(2.0 * g * drop)
    if v <= 0.0:
        return None
    dt = CONTACT_TRAVEL * radius / v
    substeps = max(1, math.ceil(1.0 / (fps * dt)))
    why = (f"a particle of radius {radius:g} m reaching {v:.3g} m/s (a {drop:.3g} m fall) moves at most "
           f"{CONTACT_TRAVEL:g} r per step")
    return substeps, why


def pin_substeps(model: Model, *, fps: float) -> tuple[int, str] | None:
    """The substeps per 1/``fps`` frame that move no driven pin further than ``PIN_TRAVEL`` × γ τ per step (this
    module's docstring), and why; ``None`` without self-collision or pins driven by tracks, or where they stand."""
    pins, contact = model.pin_groups, model.self_contact
    if contact is None or pins is None or not pins.groups:
        return None
    rows = pins.world_tracks or [[(g.translation, g.rotation) for g in pins.groups]]
    speed = 0.0
    for row in rows:
        for group, part, (translation, rotation) in zip(pins.groups, pins.slices, row):
            tracks = [t for t in (translation, rotation) if t is not None]
            if not tracks:
                continue
            keys = np.unique(np.concatenate([np.asarray(t.times, dtype=np.float64) for t in tracks]))
            t = np.unique(np.concatenate([keys, *(np.linspace(a, b, PIN_SAMPLES + 2) for a, b in zip(keys, keys[1:]))]))
            moved = dataclasses.replace(group, translation=translation, rotation=rotation)
            speed = max(speed, float(np.linalg.norm(moved.position(pins.rest[part], t)[1], axis=-1).max()))
    if speed == 0.0:
        return None
    params = contact.params.numpy().astype(np.float64)  # read from the device only where a pin moves
    reach = float((params[:, PARAM_THICKNESS] * params[:, PARAM_RELAXATION]).min())
    substeps = max(1, math.ceil(speed / (fps * PIN_TRAVEL * reach)))
    why = (f"pins moving at up to {speed:.3g} m/s move at most {PIN_TRAVEL:g} γ τ = {PIN_TRAVEL * reach * 1e3:.3g} mm "
           "per step (the self-collision cap's reach)")
    return substeps, why


def _top(shape, up: np.ndarray) -> float:
    """A lower bound of how high a collider reaches along ``up`` at rest [m] (a lower top means a longer fall and
    more substeps: the safe side): a sphere's top exactly; a capsule's at least its radius above its centre (lying
    flat); a box's at least its smallest half extent; a mesh's highest vertex in the world (rotation applied, or
    its frame's origin where its points are not at hand); a plane's height."""
    position = np.asarray(shape.position, dtype=np.float64)
    height = float(position @ up)
    if shape.kind in ("sphere", "capsule"):
        return height + float(shape.size[0])
    if shape.kind == "box":
        return height + float(np.min(np.abs(shape.size)))
    vertices = getattr(getattr(shape, "mesh", None), "vertices", None)
    if vertices is not None and len(vertices):
        rotation = quat_to_matrix(shape.rotation)
        return height + float((np.asarray(vertices, dtype=np.float64) @ rotation.T @ up).max())
    return height


#: The most substeps per frame ``auto`` searches before it refuses (the advisor's dry run at each try costs a run).
MAX_AUTO_SUBSTEPS = 4096


def _integrator_substeps(model: Model, integrator: Integrator | str, fps: float, control,
                         horizon: float, table: TradeTable) -> SubstepChoice:
    """The integrator's part of :func:`choose_substeps`."""
    name = integrator if isinstance(integrator, str) else integrator.name
    cls = _integrator_class(name)
    if issubclass(cls, ImplicitEuler):
        if isinstance(integrator, str):
            raise ConfigError("choose_substeps needs the implicit_euler instance (its options), not its name")
        return _accurate_substeps(model, integrator, fps, control, table)
    probe = advise(model, name, 1.0 / (16.0 * fps), fps=fps, control=control, horizon=horizon)
    limit = probe.dt_stable if cls.adaptive else probe.dt_passed
    if cls.adaptive:
        internal = math.inf if limit <= 0.0 else 1.0 / (fps * limit)
        budget = 0.1 * getattr(integrator, "max_steps", 100_000)
        substeps = max(1, math.ceil(internal / budget))
        # The dry runs on an integrator of their own: the run's starts with its own step control and counts.
        options = {} if isinstance(integrator, str) else dict(tolerance=integrator.tolerance,
                                                               max_steps=integrator.max_steps)
        accurate = _accurate_substeps(model, make_integrator(name, model, **options), fps, control, table,
                                      start=substeps)
        reason = (f"{accurate.reason} (stability caps its internal step near {limit * 1e3:.3g} ms: at least "
                  f"{substeps} for its max_steps)")
        return SubstepChoice(accurate.substeps, accurate.dt, reason, probe, accurate.error)
    if limit <= 0.0:
        raise ConfigError(f"substeps = \"auto\" finds no stable step: {probe.message}")
    substeps = max(1, math.ceil(1.0 / (fps * STABILITY_MARGIN * limit)))
    dt = 1.0 / (fps * substeps)
    advice = advise(model, name, dt, fps=fps, control=control, horizon=horizon)
    while not advice.stable or dt > STABILITY_MARGIN * advice.dt_passed:  # the dry run at dt may find more
        if advice.dt_passed <= 0.0 or substeps >= MAX_AUTO_SUBSTEPS:
            raise ConfigError(f"substeps = \"auto\" finds no stable step within {MAX_AUTO_SUBSTEPS} substeps per frame: "
                              f"{advice.message}")
        substeps = max(substeps + 1, math.ceil(1.0 / (fps * STABILITY_MARGIN * advice.dt_passed)))
        dt = 1.0 / (fps * substeps)
        advice = advise(model, name, dt, fps=fps, control=control, horizon=horizon)
    reason = (f"{substeps} substep{'s' if substeps > 1 else ''} per 1/{fps:g} s frame (dt = {dt * 1e3:.4g} ms): the "
              f"fewest within "
              f"{STABILITY_MARGIN:g} × the step the advisor passes, {advice.dt_passed * 1e3:.4g} ms ({advice.omega_source}, "
              f"ω_max = {advice.omega_max:.4g} rad/s{'; ' + advice.passed_reason if advice.passed_reason else ''})")
    return SubstepChoice(substeps, dt, reason, advice)


def auto_substeps(model: Model, integrator: Integrator, *, fps: float, control=None,
                  table: TradeTable | str | None = None) -> int:
    """A step chooser for :class:`~warpspring.core.simulator.Simulator`: ``Simulator(model,
    substeps=auto_substeps)`` runs :func:`choose_substeps` once, before it captures (``table``: the trade table,
    default the package's; ``functools.partial(auto_substeps, table=path)`` for another)."""
    return choose_substeps(model, integrator, fps=fps, control=control, table=table).substeps


def _frames(model: Model, integrator: Integrator, fps: float, substeps: int, control, frames: int) -> np.ndarray:
    """Positions [m] after each of ``frames`` frames from the model's start, float64, shape [frames, n·worlds, 3]."""
    sim = Simulator(model, integrator=integrator, fps=fps, substeps=substeps, control=control, guard=None)
    out = []
    for _ in range(frames):
        sim.step_frame()
        out.append(sim.state.particle_q.numpy().astype(np.float64))
    return np.stack(out)


@_keeps_plasticity  # its runs step the model: plastic springs start the real run as built
def _accurate_substeps(model: Model, integrator: Integrator, fps: float, control, table: TradeTable, *,
                       start: int = 1) -> SubstepChoice:
    """Implicit Euler and dopri5: the fewest substeps (``start``, 2 ``start``, 4 ``start``, …) whose error over a
    frame, 2 × the largest change of a frame's end positions from n to 2n substeps (first order: e(n) ≈ 2 (x(n) -
    x(2n)); higher orders less), stays within the table's accuracy floor over the first ``ACCURACY_HORIZON``
    seconds."""
    floor = table.floor
    frames = max(1, round(ACCURACY_HORIZON * fps))
    substeps, coarse = start, _frames(model, integrator, fps, start, control, frames)
    while True:
        fine = _frames(model, integrator, fps, 2 * substeps, control, frames)
        # The error over one frame: how much each frame adds to the gap, at most.
        gap = 2.0 * np.linalg.norm(coarse - fine, axis=-1).max(axis=-1)
        error = float(np.max(np.diff(np.concatenate([[0.0], gap]))))
        if error <= floor or substeps >= MAX_ACCURACY_SUBSTEPS:
            break
        substeps, coarse = 2 * substeps, fine
    bound = "within" if error <= floor else "still above"
    stable = "stable at any step" if isinstance(integrator, ImplicitEuler) else "meets its tolerance at any step"
    reason = (f"{substeps} substep{'s' if substeps > 1 else ''} per 1/{fps:g} s frame: {integrator.name} is "
              f"{stable}; its position error over a frame, {error:.2g} m by step doubling, is {bound} "
              f"{table.floor_reason()}")
    return SubstepChoice(substeps, 1.0 / (fps * substeps), reason, None, error)
