"""The advisor under load, measured: where a loaded cloth really blows up, against the largest stiffness
the advisor (``advise``, ``--strict``) passes.

Scenes, each a 20 × 20 cloth of 0.1 kg particles 0.1 m apart hanging in the xz plane from its two top
corners, structural springs only (kd = 0.01 N·s/m), gravity:

* ``hanging``: as it is (the cloth of the "trustworthy runs" report);
* ``forced``: plus a steady sideways push of ``PUSH`` on every particle through ``Control`` (half its weight);
* ``driven``: its two corners carried by a pin group on a track, ±``SHAKE`` sideways at 1 Hz;
* ``windy``: hanging in gusty wind across it (``add_aerodynamics``: 4 to 10 m/s and back every 2 s, C_D = 1.2,
  C_L = 1.0);
* ``pulled``: hanging, its bottom row dragged ±``PULL`` sideways at 0.5 Hz by a PD handle (``add_handle``:
  Kp = 20 N/m, Kd = 0.5 N·s/m per particle, capped at 5 N).

Protocol. Each stiffness is one world of one model, run for ``seconds`` (10 s) with the default guard
stopping only the failing world (``GuardLimits(stop="world")``). A world *blows up* when the guard stops
it (non-finite state, torn spring, runaway kinetic energy, or energy created by the integration beyond the
balance's tolerance) or its state is non-finite. Worlds that fail below the lowest surviving stiffness
tear because the cloth is too soft for its weight (physical over-stretch), not because of the step: they
are listed, not counted. The advisor's verdict per world is ``advise(...)`` as ``--strict`` uses it
(ω_max at the peak of a dry run of the scene from its start, at least the static equilibrium's; the run's
duration as its horizon). Bisection on ke, in
parallel: a first grid of ``worlds`` stiffnesses from the limit the advisor finds at rest down by ``span``
(loads only lower it) and up by span^¼, then a second over ±10 % around the two transitions found.

A run past its linear limit is unstable however slowly it grows, which 10 s runs do not always show (explicit
Euler and midpoint grow their top modes only slowly), so a case can also carry two linear limits, and its
limit is then the lowest of the three:

* where the scene has a static equilibrium (``hanging``, ``forced``), the exact one (:func:`linear_limit`): the
  stiffness from which the top mode of the cloth linearised there grows (dense float64, :mod:`.modal`);
* in every scene, the smallest stiffness of the grids whose run does not blow up but whose top mode, frozen at
  its states every ``sample_every`` frames of the run's second half, grows on average (:func:`frozen_growth`):
  the measure for cloth that never comes to rest.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .. import checks
from ..core.builder import ModelBuilder, SpringMaterial
from ..core.guard_records import GuardLimits
from ..core.integrators import make_integrator
from ..core.model import Model
from ..core.control import Control
from ..core.simulator import Simulator
from ..core.tracks import Track
from ..core.transforms import quat_from_axis_angle
from ..errors import ConfigError, SimulationError
from . import modal
from .advisor import advise
from .under_load import static_equilibrium

#: The explicit integrators of the battery.
EXPLICIT = ("explicit_euler", "symplectic_euler", "velocity_verlet", "midpoint", "rk4")
#: Two steps per integrator (substeps of a 1/60 s frame), chosen so that the limit lies above the stiffness
#: at which the cloth tears by its own weight (~300 N/m).
STEPS = {"explicit_euler": (2000, 8000), "symplectic_euler": (2, 8), "velocity_verlet": (2, 8), "midpoint": (16, 64),
         "rk4": (1, 4)}
SCENES = ("hanging", "forced", "driven", "windy", "pulled")
#: The scenes with a static equilibrium, where :func:`linear_limit` applies.
STATIC_SCENES = ("hanging", "forced")
FPS = 60.0
PUSH = 0.5  # [N] per particle, sideways (forced)
SHAKE = 0.1  # [m] amplitude of the handle at 1 Hz (driven)
PULL = 0.3  # [m] amplitude of the PD handle at 0.5 Hz (pulled)


def battery_cloth(scene: str, stiffness, device, *, n: int = 20, precision: str = "float32") -> Model:
    """The battery's cloth of ``scene``, n × n particles, one world per value of ``stiffness`` [N/m]."""
    if scene not in SCENES:
        raise ConfigError(f"unknown battery scene {scene!r}: choose from {', '.join(SCENES)}")
    stiffness = np.atleast_1d(np.asarray(stiffness, dtype=np.float64))
    builder = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    grid = dict(nx=n, ny=n, spacing=0.1, particle_mass=0.1, structural=SpringMaterial(ke=1.0, kd=0.01), shear=None,
                bend=None, rotation=quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2))
    if scene == "driven":
        ids = builder.add_cloth_grid(**grid)
        shake = Track([0.0, 0.25, 0.5, 0.75, 1.0], [[0, 0, 0], [0, SHAKE, 0], [0, 0, 0], [0, -SHAKE, 0], [0, 0, 0]],
                      interpolation="smooth", extrapolation="cycle")
        builder.add_pin_group([ids[-1, 0], ids[-1, -1]], translation=shake, name="handle")  # row ny-1: the top
    else:
        ids = builder.add_cloth_grid(**grid, pin=["top-left", "top-right"])
    if scene == "windy":
        gusts = Track([0.0, 1.0, 2.0], [[0, 4, 0], [0, 10, 0], [0, 4, 0]], interpolation="smooth", extrapolation="cycle")
        builder.add_aerodynamics(wind=(0.0, 4.0, 0.0), drag=1.2, lift=1.0)
        builder.set_track("wind", gusts)
    elif scene == "pulled":
        sway = Track([0.0, 0.5, 1.0, 1.5, 2.0], [[0, 0, 0], [0, PULL, 0], [0, 0, 0], [0, -PULL, 0], [0, 0, 0]],
                     interpolation="smooth", extrapolation="cycle")
        builder.add_handle(ids[0], kp=20.0, kd=0.5, max_force=5.0, translation=sway)  # row 0: the bottom
    model = builder.finalize(device, worlds=len(stiffness), precision=precision)
    model.set_world_values("spring_stiffness", stiffness[:, None] * np.ones((1, model.spring_count)))
    return model


def battery_control(scene: str, model: Model) -> Control:
    control = model.control()
    if scene == "forced":
        control.set_particle_force([0.0, PUSH, 0.0])
    return control


def advisor_passes(scene: str, integrator: str, dt: float, stiffness: np.ndarray, device, *,
                   seconds: float = 10.0) -> np.ndarray:
    """Whether the advisor passes ``dt`` at each stiffness for a run of ``seconds`` (its dry run's
    horizon, as ``warpspring run`` passes the run's duration), bool, shape [len(stiffness)]."""
    model = battery_cloth(scene, stiffness, device)
    advice = advise(model, integrator, dt, fps=FPS, control=battery_control(scene, model), horizon=seconds)
    return dt <= advice.world_dt_passed


@dataclass(frozen=True)
class Outcome:
    """One run of a grid of stiffnesses (:func:`blow_ups`).

    Attributes:
        blown: worlds that blew up, bool, shape [worlds].
        torn: worlds torn by their own weight (below the lowest survivor), bool, shape [worlds].
        samples: (positions [m], velocities [m/s], each [worlds · particles, 3], times [s], [worlds]) every
            ``sample_every`` frames of the run's second half, for :func:`frozen_growth`; empty without.
    """

    blown: np.ndarray
    torn: np.ndarray
    samples: list


def blow_ups(scene: str, integrator: str, substeps: int, stiffness: np.ndarray, device, seconds: float, *,
             sample_every: int = 0) -> Outcome:
    """Which of the worlds of ``stiffness`` [N/m] blow up in one run of ``seconds``, and which are torn by their
    weight; with ``sample_every`` (frames), the states of the run's second half to judge it by."""
    model = battery_cloth(scene, stiffness, device)
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=FPS, substeps=substeps,
                    control=battery_control(scene, model), guard=GuardLimits(stop="world"))
    frames, samples = int(round(seconds * FPS)), []
    try:
        for frame in range(1, frames + 1):
            sim.step_frame()
            if sample_every and frame > frames // 2 and (frame - frames // 2) % sample_every == 0:
                samples.append((sim.state.particle_q.numpy(), sim.state.particle_qd.numpy(), sim.state.time.numpy()))
        sim.settle()  # the last frame's verdict (on CUDA read a frame later)
    except SimulationError:
        pass  # every world failed
    q = sim.state.particle_q.numpy().reshape(len(stiffness), -1, 3)
    failed = np.array([w in sim.world_failures or not np.isfinite(q[w]).all() for w in range(len(stiffness))])
    alive = np.flatnonzero(~failed)
    torn = failed & (np.arange(len(stiffness)) < (alive.min() if len(alive) else len(stiffness)))
    return Outcome(blown=failed & ~torn, torn=torn, samples=samples)


def frozen_growth(scene: str, integrator: str, dt: float, stiffness: np.ndarray, samples: list) -> np.ndarray:
    """Each world's top-mode growth per step, e^⟨log ρ⟩ [-], shape [len(stiffness)]: ρ of its top mode frozen
    at each of ``samples`` (:func:`.modal.top_modes`, float64 on the host), averaged on the log. Above 1 the
    top mode grows on average over the states the run passes through, slowly as it may: the adiabatic
    measure of a run's linear instability where it has no equilibrium to linearise at. NaN for a world with a
    sampled state that is not finite or torn apart."""
    model = battery_cloth(scene, stiffness, "cpu", precision="float64")
    control = battery_control(scene, model)
    logs, shapes = [], None
    for q, qd, t in samples:
        modes = modal.top_modes(model, q, qd, t, control=control, starts=shapes)
        logs.append(np.log(modes.growth(integrator, dt)))
        shapes = modes.shapes
    return np.exp(np.mean(logs, axis=0)) if logs else np.full(len(stiffness), np.nan)


def at_rest_limit(integrator: str, dt: float, device, *, iterations: int = 24) -> float:
    """The largest stiffness [N/m] the advisor passes for the hanging cloth linearised at rest (bisection on
    log ke over [1e-2, 1e8] N/m; NaN where it passes none)."""
    def passes(ke):
        model = battery_cloth("hanging", [ke], device)
        return dt <= advise(model, integrator, dt, fps=FPS, loaded=False).dt_stable

    low, high = 1.0e-2, 1.0e8
    if not passes(low):
        return float("nan")
    for _ in range(iterations):
        middle = float(np.sqrt(low * high))
        low, high = (middle, high) if passes(middle) else (low, middle)
    return low


def linearised(scene: str, stiffness: float, device) -> modal.Linearisation:
    """The battery's cloth of ``scene`` at ``stiffness`` [N/m], linearised at its static equilibrium under the
    scene's loads (dense float64)."""
    model = battery_cloth(scene, [stiffness], device)
    return modal.linearise(model, static_equilibrium(model, control=battery_control(scene, model)).positions)


def linear_limit(scene: str, integrator: str, dt: float, device, *, rtol: float = 1.0e-3) -> float:
    """The stiffness [N/m] from which the top mode of the battery's cloth of ``scene``, linearised at its
    static equilibrium, grows under ``integrator`` at step ``dt`` [s] (:func:`.modal.top_mode_limit` to
    ``rtol``; NaN for a scene without a static equilibrium). Each stiffness tried costs a relaxation and a
    dense eigenproblem of the 1,194 free coordinates (~3 s on a CPU core)."""
    if scene not in STATIC_SCENES:
        return float("nan")
    return modal.top_mode_limit(lambda ke: linearised(scene, ke, device), integrator, dt, start=100.0, rtol=rtol)


@dataclass(frozen=True)
class LoadCase:
    """One case of the battery.

    Attributes:
        scene, integrator: what ran; substeps: per 1/60 s frame; dt: the step [s].
        blow_up: the smallest stiffness [N/m] that blew up (∞: none in the grids).
        passed: the largest stiffness [N/m] the advisor passes (0: none).
        unsafe: worlds the advisor passed that blew up (must be 0).
        torn: the largest stiffness [N/m] torn by the cloth's weight (0: none).
        runs: the worlds run; seconds: wall time [s].
        linear: the exact linear limit [N/m] (:func:`linear_limit`; NaN: not computed or no static
            equilibrium).
        grows: the smallest stiffness [N/m] of the grids whose run did not blow up but whose top mode grows on
            average over its second half (:func:`frozen_growth`; ∞: none; NaN: not computed).
        passed_growing: worlds the advisor passed whose top mode grows so (must be 0).
    """

    scene: str
    integrator: str
    substeps: int
    dt: float
    blow_up: float
    passed: float
    unsafe: int
    torn: float
    runs: int
    seconds: float
    linear: float = float("nan")
    grows: float = float("nan")
    passed_growing: int = 0

    @property
    def ratio(self) -> float:
        """passed / blow_up: 1 exact, < 1 conservative, > 1 unsafe; NaN without a blow-up."""
        return self.passed / self.blow_up if np.isfinite(self.blow_up) and self.blow_up > 0.0 else float("nan")

    @property
    def limit(self) -> float:
        """The case's limit [N/m]: the lowest of the blow-up, the linear limit and where the run's top mode
        grows (those known; NaN without any)."""
        known = [v for v in (self.blow_up, self.linear, self.grows) if np.isfinite(v) and v > 0.0]
        return min(known) if known else float("nan")

    @property
    def ratio_to_limit(self) -> float:
        """passed / :attr:`limit`."""
        return self.passed / self.limit


def run_case(scene: str, integrator: str, substeps: int, device, *, worlds: int = 32, span: float = 4.0,
             seconds: float = 10.0, linear: bool = False, sample_every: int = 6) -> LoadCase:
    """Bisect one case in two parallel grids (module docstring); with ``linear``, also its exact linear limit
    (scenes with a static equilibrium) and, from states every ``sample_every`` frames of the same runs' second
    halves, the smallest stiffness whose top mode grows there (:func:`frozen_growth`)."""
    checks.count("worlds", worlds, minimum=2)
    dt = 1.0 / (FPS * substeps)
    started = time.perf_counter()
    guess = at_rest_limit(integrator, dt, device)
    passed, blow_up, unsafe, torn_max, runs = 0.0, np.inf, 0, 0.0, 0
    grows, passed_growing = (np.inf if linear else float("nan")), 0
    if np.isfinite(guess):
        low, high = guess / span, guess * span**0.25
        for _ in range(2):
            ke = np.geomspace(low, high, worlds)
            passes = advisor_passes(scene, integrator, dt, ke, device, seconds=seconds)
            outcome = blow_ups(scene, integrator, substeps, ke, device, seconds,
                               sample_every=sample_every if linear else 0)
            blown, torn = outcome.blown, outcome.torn
            runs += worlds
            unsafe += int((passes & blown).sum())
            if torn.any():
                torn_max = max(torn_max, float(ke[torn].max()))
            if (passes & ~torn).any():
                passed = max(passed, float(ke[passes & ~torn].max()))
            if blown.any():
                blow_up = min(blow_up, float(ke[blown].min()))
            if linear:
                growing = ~(blown | torn) & (frozen_growth(scene, integrator, dt, ke, outcome.samples) > 1.0)
                passed_growing += int((passes & growing).sum())
                if growing.any():
                    grows = min(grows, float(ke[growing].min()))
            # The second grid: ±10 % around the transitions, or on past the first where one was not found.
            found = [v for v in (passed, blow_up, grows) if 0.0 < v < np.inf]
            if not found:
                break
            low = min(found) / 1.1 if passed > 0.0 else low / span
            high = max(found) * 1.1 if np.isfinite(blow_up) or 0.0 < grows < np.inf else high * span
    exact = linear_limit(scene, integrator, dt, device) if linear else float("nan")
    return LoadCase(scene=scene, integrator=integrator, substeps=substeps, dt=dt, blow_up=blow_up, passed=passed,
                    unsafe=unsafe, torn=torn_max, runs=runs, seconds=time.perf_counter() - started, linear=exact,
                    grows=grows, passed_growing=passed_growing)


def table(cases: list[LoadCase]) -> list[str]:
    """Markdown rows of ``cases`` and a closing line with the most conservative ratio and the unsafe count; with
    the linear limits where a case has them (at the equilibrium, and along the run), and the ratio to the lowest
    limit."""
    linear = any(np.isfinite(c.linear) or np.isfinite(c.grows) for c in cases)
    extra = ((" unstable at equilibrium from | top mode grows along the run from | passed but grows | ratio to the "
              "lowest |", "---|---|---|---|") if linear else ("", ""))
    lines = ["| scene | integrator | dt | blows up from ke | advisor passes up to | ratio | passed but blew up |" + extra[0],
             "|---|---|---|---|---|---|---|" + extra[1]]

    def stiffness(value: float, missing: str) -> str:
        return f"{value:.4g} N/m" if np.isfinite(value) else missing

    for c in cases:
        row = (f"| {c.scene} | {c.integrator} | 1/{FPS * c.substeps:g} s | {stiffness(c.blow_up, 'none in the grids')} "
               f"| {c.passed:.4g} N/m | {c.ratio:.3f} | {c.unsafe} |")
        if linear:
            grows = "–" if np.isnan(c.grows) else stiffness(c.grows, "none in the grids")
            row += (f" {stiffness(c.linear, '–')} | {grows} | {c.passed_growing if c.grows == c.grows else '–'} | "
                    f"{c.ratio_to_limit:.3f} |")
        lines.append(row)
    ratios = [c.ratio for c in cases if np.isfinite(c.ratio)]
    if ratios:
        lines += ["", f"Most conservative ratio {min(ratios):.3f}, least {max(ratios):.3f}; worlds the advisor passed "
                      f"that blew up: {sum(c.unsafe for c in cases)}."]
    to_limit = [c.ratio_to_limit for c in cases if np.isfinite(c.ratio_to_limit)]
    if linear and to_limit:
        lines.append(f"Against the lowest of the blow-up and the linear limits: {min(to_limit):.3f} … "
                     f"{max(to_limit):.3f}; worlds the advisor passed whose top mode grows along the run: "
                     f"{sum(c.passed_growing for c in cases)}.")
    return lines
