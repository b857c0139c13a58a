"""The guard's battery: every example scene, and each cloth example again with wind, a PD handle and a moving collider
added, run under the default guard (the scene's ``[guard]``).

Three kinds of case (``run_case``):

* ``advisor``: every integrator at the step the advisor passes (``substeps = "auto"``:
  :func:`~warpspring.analysis.step_choice.choose_substeps`): the run must not be stopped (a false stop).
* ``twice``: each fixed-step explicit integrator at twice the advisor's limit (h = 2 ``dt_stable`` of the scene at
  its start, ``START_HORIZON``; a frame of 1/fps holds ``substeps`` of them, or one step and a longer frame where the limit is above
  half a frame): the run must be stopped within ``STOP_FRAMES`` frames, for an instability (not a non-finite
  state: the guard must see it before the state overflows), with a message naming what the scene contains.
* ``stiff``: each fixed-step explicit integrator at the advisor's step, and after ``STIFF_AT`` frames the stiffest
  spring made 100 times stiffer (a live write between frames): stopped as ``twice``. Scenes without springs
  have no such case, nor those whose Gershgorin bound still certifies the step after the write (one spring of a
  dense lattice: its own ω grows tenfold, the network's bound less).

Each run is as ``warpspring run`` makes it: with its stability watch (``watch.StabilityWatch``, every
``WATCH_EVERY`` frames and after the first), which stops a state past ``WATCH_STOP`` times its step's stable limit, and
so with every frame read (the checks never span frames);
``run_case(watch=False)`` runs the simulator alone, as the API gives it.

The battery needs no GPU; ``bench/guard_battery.py`` runs it and writes its results, and ``tests/test_guard_battery.py``
runs a subset.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time
import warnings

import numpy as np

from ..core.guard_records import STABLE_OMEGA_H, scene_suspects, spring_bounds
from ..core.integrators import make_integrator
from ..core.simulator import Simulator
from ..core.tracks import Track
from ..errors import ConfigError, SimulationError, StabilityWarning
from ..io.scene import load_scene
from ..io.scene_build import scene_builder
from .advisor import advise
from .step_choice import choose_substeps
from .watch import WATCH_EVERY, WATCH_STOP, StabilityWatch

#: The integrators of the ``advisor`` case: all of them.
INTEGRATORS = ("explicit_euler", "symplectic_euler", "velocity_verlet", "midpoint", "rk4", "dopri5", "implicit_euler")
#: The fixed-step explicit integrators of the injected instabilities (``twice``, ``stiff``).
EXPLICIT = ("explicit_euler", "symplectic_euler", "velocity_verlet", "midpoint", "rk4")
#: An injected instability must be stopped within this many frames.
STOP_FRAMES = 60
#: The frame after which ``stiff`` makes its spring 100 times stiffer.
STIFF_AT = 10
#: Scene files of examples/ that are not scenes.
NOT_SCENES = ("sweep.toml",)
CASES = ("advisor", "twice", "stiff")
#: The ``twice`` case's advisor horizon [s]: the start state alone.
START_HORIZON = 1.0e-9
_CHOICES: dict = {}  # the advisor's choice per (scene, variant, integrator, device)
VARIANTS = ("as is", "loaded")


def example_scenes(folder: str | pathlib.Path) -> list[pathlib.Path]:
    """The scene files of ``folder`` (examples/), sorted."""
    return sorted(p for p in pathlib.Path(folder).glob("*.toml") if p.name not in NOT_SCENES)


def variants(path: pathlib.Path) -> tuple:
    """The variants of a scene: as it is, and for a cloth scene "loaded" (wind, a handle, a moving collider)."""
    return VARIANTS if load_scene(str(path)).cloths else VARIANTS[:1]


def build(path: pathlib.Path, variant: str, device, integrator: str, spring_evaluation: str = "auto"):
    """(scene, model) of ``variant``: the scene's model, or with "loaded" its first cloth in a 3 m/s wind across it
    (added where the scene has none), its free particle nearest the cloth's centre grabbed by a PD handle (ω = 20
    rad/s, ζ = 0.2 on that particle's mass) whose target moves a fifth of the cloth's size sideways over 1 s and
    back, and a sphere of a tenth of its size rising into it from below over 2 s. ``spring_evaluation``: the
    model's (``ModelBuilder.finalize``; "gather" on the CPU builds CUDA's default form)."""
    scene = load_scene(str(path))
    builder = scene_builder(scene)
    if variant == "loaded":
        positions = np.concatenate(builder._q)
        masses = np.concatenate(builder._mass)
        # The first cloth's particles: a scene adds its cloths first, the first cloth's grid or mesh at index 0.
        count = _first_cloth_count(builder)
        cloth = positions[:count]
        centre = cloth.mean(axis=0)
        size = float(np.ptp(cloth, axis=0).max())
        free = np.flatnonzero(masses[:count] > 0.0)
        grabbed = int(free[np.argmin(np.linalg.norm(cloth[free] - centre, axis=1))])
        m = float(masses[grabbed])
        kp = m * 20.0**2
        if scene.wind is None:
            builder.add_aerodynamics(wind=(3.0, 0.0, 0.0))
        side = np.array([0.2 * size, 0.0, 0.0])
        builder.add_handle([grabbed], kp=kp, kd=2.0 * 0.2 * math.sqrt(kp * m),
                           translation=Track([0.0, 1.0, 2.0], [[0.0, 0.0, 0.0], side, [0.0, 0.0, 0.0]],
                                             interpolation="smooth", extrapolation="cycle"))
        low = cloth[:, 2].min()
        radius = 0.1 * size
        start = np.array([centre[0], centre[1], low - 2.0 * radius])
        builder.add_collider_sphere(center=tuple(start), radius=radius, friction=0.3,
                                    translation=Track([0.0, 2.0], [[0.0, 0.0, 0.0], [0.0, 0.0, 2.5 * radius]],
                                                      interpolation="smooth"))
    model = builder.finalize(device, precision=scene.precision, worlds=scene.world_count,
                             contact_stage=scene.contact_stage, contact_slots=scene.contact_slots,
                             integrator=integrator, contact_triangles=scene.contact_triangles,
                             spring_evaluation=spring_evaluation)
    if not scene.contact_swept:
        model.contact_swept = False
    return scene, model


def _first_cloth_count(builder) -> int:
    """How many particles the builder's first cloth holds (its first particle block)."""
    return len(builder._q[0])


@dataclasses.dataclass
class Outcome:
    """One case's result."""

    scene: str
    variant: str
    integrator: str
    case: str
    substeps: int
    fps: float
    frames: int  # frames run (to the stop, or all)
    stopped: bool
    reason: str = ""
    passed: bool = False
    why: str = ""  # what failed, or the stop's first words
    message: str = ""
    seconds: float = 0.0

    def row(self) -> str:
        verdict = "pass" if self.passed else "FAIL"
        stop = f"stopped at frame {self.frames}: {self.reason}" if self.stopped else f"ran {self.frames} frames"
        return (f"| {self.scene} | {self.variant} | {self.integrator} | {self.case} | {self.substeps} @ {self.fps:g} fps | "
                f"{stop} | {verdict} | {self.why} | {self.seconds:.1f} |")


HEADER = ("| scene | variant | integrator | case | substeps | outcome | verdict | note | wall [s] |\n"
          "|---|---|---|---|---|---|---|---|---|")


def expected_names(model, control) -> list[str]:
    """What a stop's message must name: the scene's suspects (``scene_suspects``), and its springs where it has some."""
    names = list(scene_suspects(model, control=control))
    if spring_bounds(model) is not None:
        names.append("the springs at particle")
    return names


def run_case(path: pathlib.Path, variant: str, integrator: str, case: str, *, device, frames: int,
             defer_verdict: bool | None = None, spring_evaluation: str = "auto", watch: bool = True) -> Outcome:
    """Run one case (module docstring); ``frames``: the ``advisor`` case's length (at most the scene's);
    ``defer_verdict``: the simulator's (``None``: its default, each verdict read a frame later, where the default
    guard's checks may span frames; ``False``: each frame judged and checked); ``spring_evaluation``: the model's;
    ``watch``: the stability watch ``warpspring run`` attaches (off: the simulator alone, whose frames are then not
    read one by one)."""
    started = time.perf_counter()
    scene, model = build(path, variant, device, integrator, spring_evaluation)
    fps = scene.fps
    control = model.control()
    name = path.stem
    if case != "advisor" and integrator not in EXPLICIT:
        raise ValueError(f"{integrator} is not a fixed-step explicit integrator")
    if case == "stiff" and spring_bounds(model) is None:
        return Outcome(name, variant, integrator, case, 0, fps, 0, False, passed=True, why="no springs")
    key = (str(path), variant, integrator, str(device))
    if key not in _CHOICES:  # the advisor once per scene, variant and integrator (its dry run dominates on a CPU)
        horizon = max(frames, STIFF_AT + STOP_FRAMES) / fps
        try:
            _CHOICES[key] = choose_substeps(model, make_integrator(integrator, model), fps=fps, control=control,
                                            horizon=horizon)  # (an instance: implicit Euler's options)
        except ConfigError as refusal:  # no stable step (explicit Euler on undamped springs): no run to judge
            _CHOICES[key] = refusal
        # (the advisor's dry run stepped the model)
        scene, model = build(path, variant, device, integrator, spring_evaluation)
        control = model.control()
    choice = _CHOICES[key]
    if isinstance(choice, ConfigError):
        return Outcome(name, variant, integrator, case, 0, fps, 0, False, passed=True,
                       why=f"n/a: the advisor passes no step ({str(choice)[:100]})")
    substeps = choice.substeps
    limit = min(frames, scene.frames) if case == "advisor" else STOP_FRAMES
    if case == "twice":
        # The advisor at the start state (no dry run): a dry run cut short by its wall budget (a loaded CPU) falls
        # back to the Gershgorin bound, at twice whose step the flag in wind ran 60 frames stable.
        advice = advise(model, integrator, choice.dt, fps=fps, control=control, horizon=START_HORIZON)
        if not 0.0 < advice.dt_stable < math.inf:
            return Outcome(name, variant, integrator, case, substeps, fps, 0, False, passed=True,
                           why="n/a: no finite limit to double")
        h = 2.0 * advice.dt_stable
        substeps = max(1, math.floor(1.0 / (fps * h)))
        fps = 1.0 / (substeps * h)  # h exactly: a frame holds ``substeps`` of it
    elif case == "stiff":
        limit += STIFF_AT
    elif case != "advisor":
        raise ValueError(case)
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=fps, substeps=substeps, control=control,
                    guard=scene.guard, defer_verdict=defer_verdict)
    watcher = None
    if watch:  # as ``warpspring run`` attaches it (its warnings are not the battery's verdict)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StabilityWarning)
            watcher = StabilityWatch.attach(sim, every=WATCH_EVERY, advice=advice if case == "twice" else choice.advice,
                                            stop=WATCH_STOP)
        watcher.notify = lambda message: None
    outcome = Outcome(name, variant, integrator, case, substeps, fps, 0, False)
    try:
        for frame in range(limit):
            if case == "stiff" and frame == STIFF_AT:
                _stiffen(model)
                limit_h = STABLE_OMEGA_H.get(integrator)
                bound = spring_bounds(model)[2] * sim.dt
                if limit_h is not None and bound <= limit_h:  # the stiffer spring is still stable: nothing to stop
                    outcome.why = f"n/a: stable after the injection (ω_max h ≤ {bound:.2f} ≤ {limit_h:.2f})"
                    outcome.passed = True
                    outcome.frames = frame
                    break
                # The bound (Gershgorin's) is loose: the advisor's own estimate at the state the write left (the
                # verdict its steps are chosen by) may find the step still stable, and no instability injected.
                after = advise(model, integrator, sim.dt, fps=sim.fps, state=sim.state, control=control,
                               horizon=START_HORIZON)
                if after.stable and after.omega_source == "power iteration":
                    outcome.why = (f"n/a: stable after the injection by the advisor's estimate (ω_max h = "
                                   f"{after.omega_max * sim.dt:.2f}, step {sim.dt / after.dt_stable:.2f} of its limit)")
                    outcome.passed = True
                    outcome.frames = frame
                    break
            sim.step_frame()
            outcome.frames = frame + 1
        if watcher is not None:
            watcher.collect()  # the last frame's re-check (on CUDA read a frame later), as ``warpspring run`` does
        sim.settle()  # the last frame's verdict (on CUDA read a frame later)
    except SimulationError as stop:
        outcome.stopped = True
        outcome.frames = stop.frame or sim.frame + 1
        outcome.reason = getattr(stop, "reason", None) or "error"
        outcome.message = str(stop)
    outcome.seconds = time.perf_counter() - started
    _judge(outcome, model, control)
    return outcome


def _stiffen(model) -> None:
    """Make the spring that bounds the network's ω_max (``spring_bounds``) 100 times stiffer, in every world."""
    particle, ke, _, _ = spring_bounds(model)
    ends = model.spring_indices.numpy()
    stiffness = model.world_values("spring_stiffness").copy()
    at = np.flatnonzero((ends[:, 0] == particle) | (ends[:, 1] == particle))
    spring = at[np.argmax(stiffness[0, at])]
    stiffness[:, spring] *= 100.0
    model.set_world_values("spring_stiffness", stiffness)


def _judge(outcome: Outcome, model, control) -> None:
    if outcome.why.startswith("n/a"):
        return
    if outcome.case == "advisor":
        outcome.passed = not outcome.stopped
        outcome.why = "" if outcome.passed else outcome.message[:160]
        return
    first = STIFF_AT if outcome.case == "stiff" else 0
    if not outcome.stopped:
        outcome.why = f"not stopped within {STOP_FRAMES} frames"
        return
    if outcome.frames <= first:
        outcome.why = "stopped before the injection"
        return
    if outcome.reason == "non-finite state":
        outcome.why = "non-finite before the guard saw it"
        return
    missing = [n for n in expected_names(model, control) if n not in outcome.message]
    if missing:
        outcome.why = "message lacks " + ", ".join(missing)
        return
    outcome.passed = True
    outcome.why = f"frame {outcome.frames - first} after the injection" if first else ""


def cases(folder, *, scenes=None, integrators=INTEGRATORS, kinds=CASES, variant_names=VARIANTS):
    """(path, variant, integrator, case) of the battery, in order."""
    for path in example_scenes(folder):
        if scenes is not None and path.stem not in scenes:
            continue
        for variant in variants(path):
            if variant not in variant_names:
                continue
            for case in kinds:
                for integrator in integrators:
                    if case != "advisor" and integrator not in EXPLICIT:
                        continue
                    yield path, variant, integrator, case

