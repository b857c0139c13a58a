"""The stability advisor: for a model, an integrator and a step, each world's ω_max (:mod:`.omega`) at the
states the run reaches (:mod:`.under_load`), the damping of its modes (:mod:`.damping`) and the exact theory
of the integrator (:mod:`.stability`) give each world's largest stable step, and the verdict says whether
the step is stable and what to change (:func:`advise`, :class:`Advice`); with several worlds each world gets
its own limit and the smallest binds. After a run the guard stopped, :func:`diagnose` tells numerical
instability from physical over-stretch at the last good frame.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from .. import checks
from ..checks import format_duration
from ..errors import ConfigError
from ..core.guard_records import describe_suspects, remedy_substeps
from ..core.integrators import ImplicitEuler
from ..core.model import Model
from ..core.state import State
from .damping import _damping_ranges
from .omega import (_check_iteration, _gershgorin, _power_iteration, _stiffness_values, free_particles,
                    transverse_omega_max)
from .stability import _integrator_class, _world_limits, passed_step, spectral_radius
from .step_trial import (FREE_ENERGY_FLOOR, TRIAL_CEILING, StepTrial, trial_scope, try_step, world_energy_scales,
                         world_free_energies)
from .under_load import (PROBE_HORIZON, TransientPeak, _keeps_plasticity, has_loads, in_motion, loaded_state,
                         transient_peak)

#: Estimates of ω_max (see :func:`advise`).
OMEGA_ESTIMATES = ("power_iteration", "gershgorin")

# -- the advisor --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Advice:
    """Whether a step is stable for a model and an integrator, and what to change if not.

    With several worlds every world is analysed with its own parameters, and the verdict is that of the
    binding world (the smallest stable step; among equals, the stiffest).

    Attributes:
        integrator: the integrator's registry name.
        dt: the step asked about [s].
        omega_max: the binding world's highest angular frequency used [rad/s].
        omega_source: how ``omega_max`` was obtained: "power iteration" or "Gershgorin bound" (an upper
            bound: the step limit is then conservative).
        dt_stable: the largest stable step [s] of the binding world; ∞ when unconditionally stable, 0 when
            unstable at every step. For an adaptive integrator: the stability limit of its internal step.
        stable: whether ``dt`` is stable in every world (always true for adaptive integrators, which shrink
            their step).
        adaptive: whether the integrator chooses its own internal step.
        fps: frame rate [1/s] the substep count refers to.
        substeps: the fewest steps per 1/fps frame that keep the step ≤ ``dt_stable`` (for adaptive
            integrators: the fewest internal steps per ``dt``); ``None`` when no step is stable.
        message: one line for the user, with a suggestion when ``dt`` is unstable; names the binding world
            when the model has several.
        world: the binding world.
        world_omega_max: each world's ω_max [rad/s], float64, shape [world_count].
        world_dt_stable: each world's largest stable step [s], float64, shape [world_count].
        dry_run: simulated time of the dry run that found the peak ω_max [s] (0: none was run).
        transverse_growth: how much an integrator that needs damping (explicit Euler, midpoint) grows the
            undamped transverse modes of the binding world's stretched springs over ``horizon`` at ``dt``
            (amplitude factor, by their highest frequency and the world's least drag); 1
            where none grows.
        peak_time: when the binding world's ω_max peaked in the dry run [s] (0: at the state linearised
            about, not later).
        top_growth: the amplitude factor of the binding world's top mode (ω_max, its least damping) over
            ``horizon`` at ``dt``, ρ^(horizon/dt): above 1 exactly when ``dt`` is past the limit, and how slowly
            it grows there (explicit Euler and midpoint just past theirs: barely); 1 for adaptive integrators.
        dry_run_cut_short: why the dry run stopped at its budget (:attr:`~.under_load.TransientPeak.cut_short`), in
            which case ω_max is the Gershgorin bound and the verdict conservative (the message says so); empty
            otherwise.
        dt_passed: the largest step [s] the verdict passes in the binding world: ``dt_stable``, or less where the
            linear limit is not enough (:func:`~.stability.passed_step`): a margin for explicit Euler and midpoint,
            the three-wave limit of a weakly damped cloth for the others; ``stable`` is ``dt`` ≤ it, ``substeps``
            its substeps. NaN where not set.
        passed_reason: why ``dt_passed`` is below ``dt_stable`` ("" where it is not).
        world_dt_passed: each world's ``dt_passed`` [s], float64, shape [world_count] (NaN where not set).
        trial: the trial runs that judged ``dt`` (:func:`~.step_trial.try_step`) where it lies between ``dt_passed`` and
            ``TRIAL_CEILING`` × the smallest of ``world_dt_stable`` and a trial was asked for (:func:`advise`'s
            ``trial``); ``stable`` is then whether it passed. ``None`` where none was run.
    """

    integrator: str
    dt: float
    omega_max: float
    omega_source: str
    dt_stable: float
    stable: bool
    adaptive: bool
    fps: float
    substeps: int | None
    message: str
    world: int = 0
    world_omega_max: np.ndarray = field(default_factory=lambda: np.zeros(1), compare=False)
    world_dt_stable: np.ndarray = field(default_factory=lambda: np.zeros(1), compare=False)
    dry_run: float = 0.0
    peak_time: float = 0.0
    transverse_growth: float = 1.0
    top_growth: float = 1.0
    dry_run_cut_short: str = ""
    dt_passed: float = math.nan
    passed_reason: str = ""
    world_dt_passed: np.ndarray = field(default_factory=lambda: np.full(1, math.nan), compare=False)
    trial: StepTrial | None = field(default=None, compare=False)


#: The transverse growth (:attr:`Advice.transverse_growth`) from which the advisor's message mentions it.
TRANSVERSE_NOTE = 1.01


def _transverse_growth(model: Model, integrator: str, dt: float, stiffness: np.ndarray, positions, rates: np.ndarray,
                       horizon: float, world: int) -> float:
    """ρ^(horizon/dt) of the undamped transverse modes of ``world`` (frequencies up to
    :func:`~.omega.transverse_omega_max`, damped by the least drag ``rates``), for the integrators whose undamped modes grow (explicit Euler,
    midpoint); 1 for the others."""
    if _integrator_class(integrator).adaptive or spectral_radius(integrator, 1.0e-3, 0.0) <= 1.0:
        return 1.0
    omega = transverse_omega_max(model, positions, world, stiffness=stiffness)
    if omega <= 0.0:
        return 1.0
    drag = float(np.min(rates))
    rho = max(spectral_radius(integrator, w * dt, drag / (2.0 * w)) for w in omega * np.geomspace(1e-2, 1.0, 9))
    return _over_run(rho, horizon, dt) if rho > 1.0 else 1.0


def _over_run(rho: float, horizon: float, dt: float) -> float:
    """ρ^(horizon/dt): a growth factor ρ per step of ``dt`` [s] over ``horizon`` [s], capped at e^700."""
    return float(np.exp(min(math.log(rho) * horizon / dt, 700.0)))


def _top_growth(integrator: str, dt: float, omega: float, ranges: tuple, horizon: float) -> float:
    """ρ^(horizon/dt) of the top mode (angular frequency ``omega`` [rad/s]) at its least damping among the
    world's ``ranges`` (kd/k ratios, drag rates) (:func:`_over_run`)."""
    if omega <= 0.0:
        return 1.0
    ratios, rates = ranges
    zeta = (float(np.min(ratios)) * omega * omega + float(np.min(rates))) / (2.0 * omega)
    return _over_run(spectral_radius(integrator, omega * dt, zeta), horizon, dt)

@dataclass(frozen=True)
class _Frequencies:
    """Each world's ω_max as :func:`advise` found it, with what its damping ranges and message need.

    Attributes:
        omegas: each world's ω_max [rad/s], float64, shape [world_count]: the power iteration's (at its peak
            in the dry run, if any), or the Gershgorin bound where it did not converge or was not run.
        converged: whether each world's ω_max came from a converged power iteration, bool, shape [world_count].
        modes: each world's top mode shape, shape [particle_count, 3], or ``None`` where the bound stands in.
        positions: the positions the modes were found at [m] (a device array or, after a dry run, float64).
        probe: the dry run, or ``None``.
        swing: each world's ω_max over the dry run's first swing alone [rad/s] (:attr:`~.under_load.TransientPeak.
            world_swing_omega_max`; ``omegas`` where there is none), which the three-wave verdict takes; ``None``: ``omegas``.
    """

    omegas: np.ndarray
    converged: np.ndarray
    modes: list
    positions: object
    probe: TransientPeak | None
    swing: np.ndarray | None = None

    @property
    def swing_omegas(self) -> np.ndarray:
        return self.omegas if self.swing is None else self.swing


#: The frequencies found within :func:`shared_estimates`, by what they depend on (``_estimated_frequencies``).
_SHARED: contextvars.ContextVar[dict | None] = contextvars.ContextVar("advisor_shared_estimates", default=None)


@contextlib.contextmanager
def shared_estimates():
    """Within this block, :func:`advise` calls that judge different steps of the same model share its ω_max estimate:
    the static solve, the power iterations and the dry run depend on the model (its structure, values and inputs:
    :attr:`Model.revision`, :attr:`Model.input_version`), the control, the stiffness and the options, never on the step
    judged. For a caller that judges several steps of one model it does not change in between
    (:func:`~.step_choice.choose_substeps`: the 287-substep flag of ``examples/flag_in_wind.toml`` judged twice took
    two static solves and two dry runs, 56 of its 59 s on a CPU). A block within another shares the outer one's."""
    if _SHARED.get() is not None:
        yield
        return
    token = _SHARED.set({})
    try:
        yield
    finally:
        _SHARED.reset(token)


def _estimated_frequencies(model: Model, integrator: str, k: np.ndarray, *, stiffness, state: State | None, control,
                           loaded: bool, transient: bool, horizon: float, max_iterations: int,
                           tolerance: float) -> _Frequencies:
    """ω_max by power iteration (:func:`advise`, ``omega_estimate="power_iteration"``): about ``state``, or,
    judging the run (``loaded`` and no ``state``), about the loaded state and at each world's peak over a dry
    run when the model moves by itself and the step limits the integrator (shared within :func:`shared_estimates`)."""
    shared = _SHARED.get()
    if shared is None:
        return _frequencies(model, integrator, k, stiffness=stiffness, state=state, control=control, loaded=loaded,
                            transient=transient, horizon=horizon, max_iterations=max_iterations, tolerance=tolerance)
    cls = _integrator_class(integrator)
    step_limited = not (cls.adaptive or getattr(cls, "unconditionally_stable", False))
    key = (id(model), model.revision, model.input_version, id(control), id(state), id(stiffness),
           hashlib.sha1(np.ascontiguousarray(k).tobytes()).hexdigest(), step_limited, integrator == "explicit_euler",
           loaded, transient, float(horizon), int(max_iterations), float(tolerance))
    if key not in shared:
        shared[key] = _frequencies(model, integrator, k, stiffness=stiffness, state=state, control=control,
                                   loaded=loaded, transient=transient, horizon=horizon,
                                   max_iterations=max_iterations, tolerance=tolerance)
    return shared[key]


def _frequencies(model: Model, integrator: str, k: np.ndarray, *, stiffness, state: State | None, control,
                 loaded: bool, transient: bool, horizon: float, max_iterations: int, tolerance: float) -> _Frequencies:
    """:func:`_estimated_frequencies`, computed."""
    cls = _integrator_class(integrator)
    worlds = model.world_count
    _check_iteration(max_iterations, tolerance)
    judge_run = state is None and loaded
    if judge_run and has_loads(model, control):
        state = loaded_state(model, control=control)
    estimate = _power_iteration(model, k, state, max_iterations, tolerance, 0)
    positions = model.particle_q if state is None else state.particle_q
    converged = estimate.world_converged
    peaks, probe = estimate.world_omega_max, None
    step_limited = not (cls.adaptive or getattr(cls, "unconditionally_stable", False))
    if judge_run and transient and step_limited and in_motion(model, control):
        probe = transient_peak(model, control=control, stiffness=stiffness, horizon=horizon, start=estimate,
                               start_positions=positions.numpy().astype(np.float64),
                               lowest_ratio=integrator == "explicit_euler")
        peaks, positions = probe.world_omega_max, probe.positions
        estimate = dataclasses.replace(estimate, world_mode=probe.world_mode)
    swung = converged.copy()  # worlds whose first swing's peak stands (the three-wave verdict's)
    if probe is not None and probe.cut_short:  # its peaks are not the run's: the bound holds at any state
        swung &= probe.swing_complete  # ... but a first swing it got past is that swing's
        converged = np.zeros(worlds, dtype=bool)
    omegas = np.where(converged, peaks, estimate.world_gershgorin)  # the bound where not
    swing = None
    if probe is not None and probe.world_swing_omega_max is not None:
        swing = np.where(swung, np.minimum(probe.world_swing_omega_max, peaks), omegas)
    modes = [estimate.world_mode[w] if converged[w] else None for w in range(worlds)]
    return _Frequencies(omegas, converged, modes, positions, probe, swing)


def _bounded_frequencies(model: Model, k: np.ndarray, state: State | None) -> _Frequencies:
    """ω_max by the Gershgorin bound (:func:`advise`, ``omega_estimate="gershgorin"``): no modes, no dry run."""
    worlds = model.world_count
    converged = np.zeros(worlds, dtype=bool)
    omegas = _gershgorin(model, k, free_particles(model))
    modes = [None] * worlds
    positions = model.particle_q if state is None else state.particle_q
    return _Frequencies(omegas, converged, modes, positions, None)


def _springs_phrase(found: _Frequencies, w: int, peak_time: float, worlds: int) -> str:
    """How the message names the binding world ``w``'s ω_max: its value and source, when it peaked in the dry
    run, and which world it is when the model has several."""
    omega = float(found.omegas[w])
    source = "power iteration" if found.converged[w] else "Gershgorin bound"
    springs = f"ω_max = {omega:.4g} rad/s by {source}"
    if peak_time > 0.0:
        springs += f" at its peak, t = {peak_time:.3g} s into a {found.probe.duration:.3g} s dry run"
    if found.probe is not None and found.probe.cut_short:
        springs += (f", conservative: the dry run was cut short ({found.probe.cut_short}), so the bound, which "
                    "holds at any state, stands in for its peak")
    if worlds > 1:
        springs += f" in world {w}, the binding one of {worlds} worlds"
    return springs


def _verdict(integrator: str, dt: float, fps: float, limit: float, springs: str, top: float, horizon: float,
             found: _Frequencies, ranges: list) -> tuple[bool, int | None, str]:
    """Whether ``dt`` [s] is stable against the binding world's ``limit`` [s], the substeps (:attr:`Advice.substeps`)
    and the message, for an adaptive integrator, one stable at any step, one stable at none and one whose
    step the springs limit; ``top``: the top mode's growth over ``horizon`` [s] (:func:`_top_growth`)."""
    cls = _integrator_class(integrator)
    frame = f"1/{fps:g} s frame"
    if cls.adaptive:
        internal = math.ceil(dt / limit) if 0.0 < limit < math.inf else None
        stable, substeps = True, internal
        if internal is None:
            cap = f"the springs do not cap that step ({springs})"
        elif internal > 1:
            cap = (f"stability caps that step near {format_duration(limit)} ({springs}): at least {internal} internal "
                   f"steps per dt = {format_duration(dt)}")
        else:
            cap = f"stability caps that step near {format_duration(limit)} ({springs}), above dt = {format_duration(dt)}"
        message = f"{integrator} adapts its internal step to its tolerance; {cap}"
    elif limit == math.inf:
        stable, substeps = True, 1
        message = (
            f"{integrator} is unconditionally stable ({springs}): dt = {format_duration(dt)} is limited by accuracy only"
            if issubclass(cls, ImplicitEuler) else
            f"{integrator} is stable at any dt for these springs ({springs})"
        )
    elif limit == 0.0:
        stable, substeps = False, None
        fallback = min(passed_step("symplectic_euler", float(o), float(lim), rayleigh=r[0], drag_rate=r[1])[0]
                       for o, lim, r in zip(found.omegas, _world_limits("symplectic_euler", found.omegas, ranges),
                                             ranges))
        message = (
            f"{integrator} is unstable at every dt for these springs (their weakly damped modes grow at any step; "
            f"{springs}): use symplectic_euler or velocity_verlet (dt ≤ {format_duration(fallback)}) or implicit_euler "
            "(unconditionally stable)"
        )
    else:
        substeps = max(1, math.ceil(1.0 / (fps * limit)))
        stable = dt <= limit
        if stable:
            message = (
                f"{integrator} is stable at dt = {format_duration(dt)}: the springs ({springs}) allow up to "
                f"{format_duration(limit)}, i.e. at least {substeps} substeps per {frame}"
            )
        else:
            grows = f"×{top:.3g}" if top < 1e6 else f"×1e{math.log10(top):.0f}"
            past = (f"past it their top mode grows {grows} over a {horizon:g} s run" if top > 1.0 + 1e-9 else
                    "past it the step is within the springs' linear limit but not passed")
            message = (
                f"{integrator} is unstable at dt = {format_duration(dt)}: the springs ({springs}) allow at most "
                f"{format_duration(limit)} ({past}); use a smaller dt, at least {substeps} substeps per {frame}, or "
                f"implicit_euler (unconditionally stable)"
            )
    return stable, substeps, message


def _with_transverse_note(message: str, integrator: str, growth: float, horizon: float) -> str:
    """``message`` with a note on the transverse modes' growth (:attr:`Advice.transverse_growth`) where it
    reaches ``TRANSVERSE_NOTE``."""
    if growth >= TRANSVERSE_NOTE:
        message += (f"; its stretched springs' transverse modes carry no damping and {integrator} grows them at any "
                    f"step: ×{growth:.3g} over a {horizon:g} s run at this dt (symplectic_euler, velocity_verlet and "
                    f"rk4 do not)")
    return message


@_keeps_plasticity
def advise(
    model: Model,
    integrator: str,
    dt: float,
    *,
    fps: float = 60.0,
    strict: bool = False,
    stiffness=None,
    state: State | None = None,
    control=None,
    loaded: bool = True,
    transient: bool = True,
    horizon: float = PROBE_HORIZON,
    omega_estimate: str = "power_iteration",
    max_iterations: int = 1000,
    tolerance: float = 1.0e-3,
    trial: bool | None = None,
    notify=None,
) -> Advice:
    """Check ``dt`` against the springs' stability limit for ``integrator`` and say what to do.

    ω_max of every world comes from :func:`~.omega.estimate_omega_max` (a world whose power iteration does not
    converge within ``max_iterations`` falls back to its Gershgorin bound) or, with
    ``omega_estimate="gershgorin"``, from :func:`~.omega.world_gershgorin_omega_max` directly (cheaper,
    conservative). The modes' damping (:func:`~.stability.network_stable_step`) spans the smallest kd/k of the world's
    springs and its top mode's own kd/k, xᵀDx / xᵀKx on the power-iteration eigenvector (with the
    Gershgorin bound: the largest kd/k), and the world's drag c/m. Each world gets its own stable step; the
    smallest binds, and the message names its world when the model has several. Contacts are not part of
    the analysis. The theory's exact arithmetic costs ~0.1 s of host time per distinct world (worlds with
    the same ω_max and damping share one evaluation).

    Args:
        model: the model.
        integrator: registry name of the integrator.
        dt: the step [s] to check, > 0.
        fps: frame rate [1/s] for the substep count.
        strict: raise a ConfigError carrying the message when ``dt`` is unstable.
        stiffness: spring stiffness [N/m], shape [spring_count] or [world_count, spring_count], also used
            for the springs' kd/k; default the model's, with biphasic springs at their stiffer branch
            (ratio × ke).
        state: positions to linearise about; default the model's initial positions, carried by the loads
            (below).
        control: the run's Control, whose external force is a load (default none).
        loaded: with no ``state`` given, judge the states the run reaches rather than the initial positions:
            with loads acting (gravity or the control's external force), linearise about
            :func:`~.under_load.loaded_state`, and with ``transient``, when the model moves by itself (:func:`~.under_load.in_motion`),
            take each world's peak ω_max over a dry run to ``horizon`` [s] (:func:`~.under_load.transient_peak`: the
            release transient of a loaded cloth swings past its static stretch; not for implicit and
            adaptive integrators, whose step ω_max does not limit). The Gershgorin bound needs
            no state: it bounds every spring block by its full stiffness, stretched or not.
        omega_estimate: "power_iteration" or "gershgorin".
        max_iterations, tolerance: of the power iteration.
        trial: where ``dt`` lies past the passed step (:attr:`Advice.dt_passed`: the three-wave step of a weakly damped
            cloth, or the linear limit) but within ``TRIAL_CEILING`` × the linear limit, judging the run (no ``state``,
            ``loaded``) with an integrator that keeps undamped modes (symplectic Euler, velocity Verlet, RK4), decide it
            by trial runs of the scene itself for ``horizon`` (:func:`~.step_trial.try_step`: at ``dt`` and 2 % above
            it; two runs of the scene, without its guard), where :func:`~.step_trial.trial_scope` can measure the
            scene's energy. The theory cannot tell there whether the cloth's top modes feed a resonance: the largest
            step that holds lies 0-16 % past the passed step (``bench/results/advisor_battery_bisect_cpu.md``).
            Default: with ``strict``.
        notify: called with one line before a trial starts (what it runs and for how long), if given: the CLI's
            note, so a long trial is not a silent wait.

    Raises:
        ConfigError: bad arguments, or (with ``strict``) an unstable step.
    """
    dt, fps = checks.positive("dt", dt), checks.positive("fps", fps)
    cls = _integrator_class(integrator)
    if omega_estimate not in OMEGA_ESTIMATES:
        raise ConfigError(f"omega_estimate must be one of {', '.join(OMEGA_ESTIMATES)}, got {omega_estimate!r}")
    k = _stiffness_values(model, stiffness)
    if omega_estimate == "power_iteration":
        found = _estimated_frequencies(model, integrator, k, stiffness=stiffness, state=state, control=control,
                                       loaded=loaded, transient=transient, horizon=horizon,
                                       max_iterations=max_iterations, tolerance=tolerance)
    else:
        found = _bounded_frequencies(model, k, state)
    probe = found.probe
    ranges = _damping_ranges(model, k, found.modes, found.positions,
                             lowest_top=None if probe is None else probe.world_lowest_ratio)
    limits = _world_limits(integrator, found.omegas, ranges)
    # The linear limit at the dry run's peak; the three-wave limit at its first swing's (a sustained resonance, which
    # a back-swing's instant does not feed: under_load.PROBE_PERIODS).
    passed = [(float(lim), "") if cls.adaptive else passed_step(integrator, float(o), float(lim), rayleigh=r[0],
                                                                  drag_rate=r[1])
              for o, lim, r in zip(found.swing_omegas, limits, ranges)]
    passed_limits = np.array([p[0] for p in passed])
    w = int(np.lexsort((-found.omegas, passed_limits))[0])  # the smallest step; among equals, the stiffest world
    omega, limit = float(found.omegas[w]), float(limits[w])
    passed_limit, passed_reason = float(passed_limits[w]), passed[w][1]
    peak_time = float(probe.world_peak_time[w]) if probe is not None and found.converged[w] else 0.0
    springs = _springs_phrase(found, w, peak_time, model.world_count)
    adaptive = cls.adaptive
    top = 1.0 if adaptive or not 0.0 < limit < math.inf else _top_growth(integrator, dt, omega, ranges[w], horizon)
    stable, substeps, message = _verdict(integrator, dt, fps, passed_limit, springs, top, horizon, found, ranges)
    if passed_reason:
        message += f" (the springs' linear limit is {format_duration(limit)}; passed: {passed_reason})"
    tried = None
    # (the ceiling by the smallest linear limit of any world: every world runs in the trial)
    past = not stable and judged_past(integrator, dt, passed_limit, min(limit, float(np.min(limits))))
    if past and not (strict if trial is None else trial):
        message += "; --strict decides such a step by trial runs of the scene (advise(..., trial=True))"
    elif past:
        scope = ("the state or stiffness it was asked about, not the run's" if state is not None or stiffness is not None
                 else "the unloaded start, not the run" if not loaded else trial_scope(model, control))
        released = np.zeros(model.world_count) if scope else _released(model)
        idle = np.flatnonzero(~(released > FREE_ENERGY_FLOOR * world_energy_scales(model))) if not scope else []
        if len(idle):
            where = f" in world {idle[0]}" if model.world_count > 1 else ""
            scope = f"its start sets {released[idle[0]]:.3g} J free{where}, round-off against its energy scale"
        if scope:
            message += f"; a trial run would decide this step, but cannot judge this scene ({scope})"
        else:
            if notify is not None:
                notify(f"{integrator} at dt = {format_duration(dt)} lies past the step the theory passes "
                       f"({format_duration(passed_limit)}): trying it on up to two runs of the scene, {horizon:g} s each")
            tried = try_step(model, integrator, dt, seconds=horizon, released=released, control=control)
            stable = tried.passed
            message = (f"{integrator} passes dt = {format_duration(dt)} on trial: past the step the theory passes, "
                       f"{format_duration(passed_limit)} ({springs}), the runs decide; {tried.describe()}"
                       if stable else f"{message}; it failed on trial: {tried.describe()}")
    growth = _transverse_growth(model, integrator, dt, k, found.positions, ranges[w][1], horizon, w)
    message = _with_transverse_note(message, integrator, growth, horizon)
    if strict and not stable:
        raise ConfigError(message)
    return Advice(
        integrator=integrator,
        dt=dt,
        omega_max=omega,
        omega_source="power iteration" if found.converged[w] else "Gershgorin bound",
        dt_stable=limit,
        stable=stable,
        adaptive=adaptive,
        fps=fps,
        substeps=substeps,
        message=message,
        world=w,
        world_omega_max=np.asarray(found.omegas, dtype=np.float64),
        world_dt_stable=limits,
        dry_run=probe.duration if probe is not None else 0.0,
        peak_time=peak_time,
        transverse_growth=growth,
        top_growth=top,
        dry_run_cut_short=probe.cut_short if probe is not None else "",
        dt_passed=passed_limit,
        passed_reason=passed_reason,
        world_dt_passed=passed_limits,
        trial=tried,
    )


def judged_past(integrator: str, dt: float, passed: float, limit: float) -> bool:
    """Whether a trial (:func:`~.step_trial.try_step`) judges ``dt`` [s] for ``integrator`` with the passed step
    ``passed`` and the linear limit ``limit`` [s]: past the former, within ``TRIAL_CEILING`` × the latter, for an
    integrator with a finite limit that keeps undamped modes (not one that relies on damping: explicit Euler,
    midpoint)."""
    cls = _integrator_class(integrator)
    if cls.adaptive or not 0.0 < passed <= limit < math.inf:
        return False
    return passed < dt <= TRIAL_CEILING * limit and spectral_radius(integrator, 0.1, 0.0) <= 1.0 + 1.0e-9


def _released(model: Model) -> np.ndarray:
    """:func:`~.step_trial.world_free_energies` of ``model``, shared within :func:`shared_estimates` (a static
    solve)."""
    shared = _SHARED.get()
    if shared is None:
        return world_free_energies(model)
    key = ("released", id(model), model.revision, model.input_version)
    if key not in shared:
        shared[key] = world_free_energies(model)
    return shared[key]


# -- after a stop -------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Diagnosis:
    """Why a run the guard stopped went bad, judged at its last good frame.

    Attributes:
        kind: "overstretch" (a stable integration of a material too soft for its load: the springs really
            stretch that far) or "instability" (the step is beyond the limit at the state reached, or the
            state turned non-finite or its energy ran away with the step found stable: see ``remedy``).
        advice: the advisor linearised about the last good frame.
        remedy: what to change, one sentence.
    """

    kind: str
    advice: Advice
    remedy: str


def diagnose(model: Model, integrator: str, dt: float, *, fps: float, reason: str, state: State,
             control=None, omega_estimate: str = "power_iteration", substeps_floor: int = 0) -> Diagnosis:
    """Tell numerical instability from physical over-stretch after a guard stop whose ``reason`` is
    "strain", "kinetic energy" or "non-finite state", from ``state``, the last frame the guard passed.

    A spring torn in a step the advisor finds stable *at that frame's stretched state* is over-stretch:
    more substeps or implicit Euler integrate the same tearing more accurately, so the remedy is the
    material (stiffer springs, strain limiting, biphasic springs). A step beyond the limit at that state is
    instability: more substeps (the number that the state needs) or implicit Euler. ``omega_estimate`` as
    in :func:`advise`; ``substeps_floor``: the substeps the run's own verdict asked for (the suggestion is never
    fewer, so that it also passes that verdict, e.g. ``--strict``)."""
    advice = advise(model, integrator, dt, fps=fps, state=state, control=control, omega_estimate=omega_estimate)
    if reason == "strain" and advice.stable:
        return Diagnosis("overstretch", advice, (
            f"the step was stable at the stretched state ({advice.message}), so the springs really stretch that "
            "far: the material is too soft for its load, and neither more substeps nor implicit_euler change "
            "that; use stiffer springs (ke), strain limiting (Stabilizers(max_strain=0.1), [stabilizers] "
            "max_strain) or biphasic springs (biphasic_strain, biphasic_ratio)"))
    if not advice.stable:
        hint = f" (e.g. --substeps {max(advice.substeps, substeps_floor)})" if advice.substeps else ""
        return Diagnosis("instability", advice, (
            f"numerical instability: at the state the run reached, {advice.message}{hint}"))
    substeps = max(1, round(1.0 / (fps * dt)))
    more = max(remedy_substeps(model, integrator=integrator, substeps=substeps, dt=dt), substeps_floor)
    return Diagnosis("instability", advice, (
        f"the advisor found the step stable for the elements at the state the run reached ({advice.message}); the "
        f"scene's other suspects: {describe_suspects(model, control=control)}; run with more substeps (e.g. "
        f"--substeps {more})"))
