"""The states a run reaches under its loads, which the stability advisor linearises about: the static
equilibrium (:func:`static_equilibrium`, :func:`loaded_state`) and each world's peak ω_max over a dry run of
the scene (:func:`transient_peak`).

A stretched spring of tension T and length
l adds the transverse stiffness T/l = k(1 - L/l) to the axial k: a cloth hanging from two pins has stiffer
modes than the same cloth at rest, up to √2 times the frequency of its in-plane modes when every spring is
far stretched (a flat cloth at rest has no transverse stiffness at all). Linearised about its initial
state, the advisor overrated a 20 × 20 RK4 cloth's stable stiffness by 1/0.65 under gravity. So when loads
act (gravity, the control's external force), the advisor linearises about the state they carry the model
to: the static equilibrium x_eq (pins held at their t = 0 place), found by quasi-static implicit Euler
steps (each one a regularised Newton step on the potential, the velocities zeroed after it). That is not
yet the stiffest state of the run: released unstretched, the cloth swings past its static stretch before
it settles, and the advisor linearised at x_eq was 2.5–13.5 % optimistic for symplectic Euler, velocity
Verlet and RK4 at small steps (bench/RESULTS.md §11). A swing along the ray x₀ + s (x_eq - x₀) does not
model it (the cloth reaches equilibrium through large rotations, which the ray turns into stretch). So
when the model moves by itself, the advisor also takes each world's peak ω_max over a dry run of the
scene (:func:`transient_peak`): velocity Verlet at half the step the Gershgorin bound proves stable at
any state, ω_max re-estimated along the way by restarted Lanczos, until the peaks stop rising
(or the run's duration). Measured with it on the battery (three scenes, five integrators, two steps
each): no run it passes blows up; it is within 10 % for symplectic Euler, velocity Verlet and RK4, and
14–41 % conservative for explicit Euler and midpoint over 10 s runs. Against the exact one-step map of the
linearised cloth (:mod:`.modal`, :func:`.stability.step_matrix`) the advisor linearised at the equilibrium is the top
mode's limit for all five (to the power iteration's ~1e-4), so those two integrators' runs past it are
linearly unstable, only too slowly to show in 10 s. They rely on damping, and the transverse modes have
none (:mod:`.stability`): those grow slowly at any step, and over 100 s explicit Euler blows up inside the
advisor's limit.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..core.forces import eval_forces
from ..core.integrators import ImplicitEuler, VelocityVerlet
from ..core.model import Model
from ..core.simulator import Simulator
from ..core.state import State
from .damping import _damping_ranges, _ratio_arrays, _tangent_stiffness, _top_mode_ratios
from .omega import (Lanczos, OmegaMaxEstimate, _gershgorin, _gershgorin_rows, _power_iteration, _stiffness_values,
                    free_particles)
from .stability import _world_limits

# -- under load ---------------------------------------------------------------------------------------------

#: Where between the start (0) and the static equilibrium (1) :func:`loaded_state` linearises by default.
OVERSHOOT = 1.0
#: Quasi-static relaxation: the implicit step [s] (a trust region: unsupported directions move g h² per step
#: at most), the most steps, and the convergence test (largest move per step / the model's extent; the
#: 20 × 20 cloth's ω_max agrees to 5e-6 with a 10× tighter test).
RELAX_STEP, RELAX_MAX_STEPS, RELAX_TOLERANCE = 0.2, 200, 1.0e-5


def has_loads(model: Model, control=None) -> bool:
    """Whether gravity acts in some world or the control carries an external force."""
    gravity = np.linalg.norm(model.world_values("gravity"), axis=1)
    return bool(gravity.any()) or (control is not None and control.particle_force is not None)


@dataclass(frozen=True)
class Equilibrium:
    """The static equilibrium :func:`static_equilibrium` found.

    Attributes:
        positions: particle positions [m], float64, shape [world_count · particle_count, 3].
        steps: relaxation steps taken.
        converged: whether the largest move of the last step fell below ``RELAX_TOLERANCE`` × the extent.
        residual: that move over the extent [-].
    """

    positions: np.ndarray
    steps: int
    converged: bool
    residual: float


#: CG iterations of each relaxation step of :func:`static_equilibrium` (implicit Euler's cap before it chose one).
RELAX_CG_ITERATIONS = 100


def static_equilibrium(model: Model, *, control=None, step: float = RELAX_STEP, max_steps: int = RELAX_MAX_STEPS,
                       tolerance: float = RELAX_TOLERANCE) -> Equilibrium:
    """The positions where the loads (gravity, the control's external force) balance the elements, the
    pins held at their t = 0 place: implicit Euler steps of ``step`` from rest, the velocities zeroed and
    the clock and pins put back after each, until the largest move per step is below ``tolerance`` × the
    model's extent (or ``max_steps``). Each step solves (M + h²K) Δx = h² f, a Newton step on the
    potential regularised by the mass (K the elements' stiffness, made positive semi-definite).

    A world without a pinned particle has no such equilibrium: the loads accelerate it as a whole (uniform
    gravity strains a free body in no way) and only contacts, which this analysis leaves out, could hold it. Its
    equilibrium is taken as its start: relaxing it would only let it fall step by step into its colliders (a free
    neo-Hookean ball relaxed onto a slab ended crushed, its ω_max 5.8e8 rad/s against 378 at rest)."""
    checks.positive("step", step)
    checks.count("max_steps", max_steps, minimum=1)
    free = free_particles(model)
    held = free.all(axis=1)  # the worlds without a pin: no static equilibrium under the loads
    if held.all():
        start = model.particle_q.numpy().astype(np.float64)
        return Equilibrium(positions=start, steps=0, converged=True, residual=0.0)
    # A relaxation: each step need only move towards the equilibrium (the loop's residual decides when it is
    # reached), so its solve keeps the fixed cap it always had rather than the run's automatic one, which for a
    # large step asks for thousands of iterations.
    integrator = ImplicitEuler(model, cg_iterations=RELAX_CG_ITERATIONS, cg_unconverged="ignore")
    state, scratch = model.state(), model.state()
    start = state.particle_q.numpy().astype(np.float64)
    pinned = (~free | held[:, None]).reshape(-1)  # (a free world kept at its start, as its pins are)
    extent = max(float(np.ptp(start, axis=0).max()) if len(start) else 0.0, 1.0e-6)
    previous, residual, steps = start, math.inf, 0
    while steps < max_steps and residual > tolerance:
        state.particle_qd.zero_()
        state.time.zero_()
        integrator.step(state, scratch, control, step)
        q = scratch.particle_q.numpy().astype(np.float64)
        q[pinned] = start[pinned]
        if not np.isfinite(q).all():
            break
        residual = float(np.abs(q - previous).max()) / extent
        state.particle_q.assign(q.astype(wp.dtype_to_numpy(model.scalar)))
        previous, steps = q, steps + 1
    return Equilibrium(positions=previous, steps=steps, converged=residual <= tolerance, residual=residual)


def loaded_state(model: Model, *, control=None, overshoot: float = OVERSHOOT) -> State:
    """A state at x₀ + ``overshoot`` (x_eq - x₀), x_eq the :func:`static_equilibrium` under the loads, at rest
    (default: the equilibrium itself), to linearise the advisor about."""
    start = model.state()
    equilibrium = static_equilibrium(model, control=control)
    q0 = start.particle_q.numpy().astype(np.float64)
    swing = q0 + overshoot * (equilibrium.positions - q0)
    start.particle_q.assign(swing.astype(wp.dtype_to_numpy(model.scalar)))
    return start


#: The dry run (:func:`transient_peak`): velocity Verlet at ``PROBE_FRACTION`` of the step the Gershgorin
#: bound proves stable (no state exceeds that bound, so the dry run is stable wherever it goes; on a linear
#: spring released from rest Verlet's turning points are exact at any stable step, where symplectic Euler's
#: overshoot by 1/√(1 - (ωh/2)²)), ω_max re-estimated by ``PROBE_STEPS`` Lanczos steps (:class:`~.omega.Lanczos`)
#: restarted from the last top Ritz vector, captured once into a graph and replayed: every ``PROBE_CHECK`` seconds
#: of simulated time while some world's estimate climbs past its running peak, every ``PROBE_SPARSE``-th such
#: interval while none does (a peak is then sampled every ``PROBE_CHECK`` on its way up and at the first check past
#: it; explicit Euler's lowest damping ratio, which need not come with a peak, every ``PROBE_CHECK``); at the end each world's estimate at the state where it peaked gets ``PROBE_REFINE`` more restarts. Measured
#: on the cloths of :mod:`.stability_battery` (CPU, 2 cores, Warp 1.19.0, bench/results/advisor_battery_cpu.md): the
#: 64² folded cloth's 2.76 s dry run peaks at 1287.09 rad/s in 5.5 s of CPU time, where 20 warm-started power
#: iterations every 1/240 s found 1287.07 in 12.1 s; the 32² flat cloth's at 1120.64 rad/s where they found 1113.58
#: (-0.6 %: a mode that rose elsewhere in the cloth, which they reached late), the 32² folded cloth's at 1146.63
#: (1146.36); a re-estimate every 1/120 s throughout misses 0.14 % of the 64² folded cloth's peak, between two.
#: It ends once twice the time of the last rise of some
#: world's peak (by more than ``PROBE_RISE``) has passed, not before ``PROBE_MIN_TIME`` and not after its
#: horizon (``PROBE_HORIZON`` by default; ``warpspring run`` passes the run's duration). Under gravity it also
#: lasts the cloth's first swing (:func:`swing_time`): a large cloth's stretch peaks when its fall first passes
#: the bottom, after the peaks of its first quarter second have stopped rising (bench/results/advisor_battery_cpu.md),
#: and ``PROBE_PERIODS`` swings (a whole small-swing period): a cloth released flat whips its top mode higher on its
#: back-swing, for an instant, than anywhere in its first swing (32²: 1168.35 rad/s at 2.62 s against 1120.57 at
#: 0.88 s; 64²: 1295 at 3.97 s against 1244 at 1.3 s), and a step at the linear limit of the first swing's peak
#: turns non-finite there (the 32² cloth with kd = 1e-5 s · ke at 1.775 ms, symplectic Euler, and 1.785 ms, Verlet).
#: The first swing's peak is kept apart (:attr:`TransientPeak.world_swing_omega_max`) for the three-wave verdict,
#: whose resonance needs the top mode held past √3, not an instant (:func:`~.stability.passed_step`).
PROBE_FRACTION = 0.5
PROBE_CHECK = 1.0 / 240.0
PROBE_STEPS, PROBE_TOLERANCE, PROBE_REFINE, PROBE_SPARSE = 8, 1.0e-4, 4, 2
PROBE_RISE = 1.0e-3
PROBE_MIN_TIME, PROBE_HORIZON = 0.25, 2.0
PROBE_PERIODS = 2.0
#: The dry run's budget: at most ``PROBE_MAX_STEPS`` velocity Verlet steps (a dry run that would need more
#: to reach ``PROBE_MIN_TIME`` and its first swing is not started) and ``PROBE_TIME_BUDGET`` seconds of this process's CPU time after
#: its first frame (which compiles; CPU time, not wall time, so that the verdict does not depend on what else the
#: machine runs: on a CPU shared with other work the 64² cloth's dry run took 1.5× its CPU time in wall time);
#: past either it stops and says so (:attr:`TransientPeak.cut_short`), and the advisor
#: judges by the Gershgorin bound, which holds at any state the run reaches (conservative): its linear limit, and
#: its three-wave limit too unless the dry run got past its first swing (that swing's peak, ``PROBE_PERIODS``). The examples'
#: dry runs take 180–720 steps.
PROBE_MAX_STEPS, PROBE_TIME_BUDGET = 50_000, 10.0


def swing_time(model: Model) -> float:
    """How long the dry run must last to see a hanging cloth's first swing through the bottom [s]: half the period
    of a pendulum as long as the longest hang, π √(ℓ/|g|), where ℓ [m] is the greatest distance from a free
    particle to the nearest pinned one along springs (their rest lengths; the largest over the worlds); 0 without
    gravity or pins. A pendulum released at an angle θ₀ first passes the bottom after a quarter of its period,
    (2/π) K(sin(θ₀/2)) times its small-swing quarter period (1.18 at 90°, a cloth released flat), so half the
    small-swing period covers releases up to 160°. Measured (velocity Verlet dry runs of 10 s on the undamped cloth of
    :mod:`.stability_battery`, pinned at its two top corners): the 64² cloth released folded reaches its highest
    ω_max, 14 % above its first quarter second's, at 1.23 s; its π √(ℓ/|g|) is 2.76 s (ℓ = 7.6 m)."""
    g = float(np.linalg.norm(np.asarray(model.gravity, dtype=np.float64)))
    free = free_particles(model)
    if g <= 0.0 or model.spring_count == 0 or free.all():
        return 0.0
    from scipy.sparse import csgraph, csr_matrix  # a graph search on the host (scipy, a core dependency)

    pairs = model.spring_indices.numpy().reshape(-1, 2)
    rest = model.spring_rest_length.numpy().astype(np.float64)
    n = model.particle_count
    graph = csr_matrix((np.maximum(rest, 1e-12), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    longest = 0.0
    for world in np.unique(free, axis=0):  # worlds that pin the same particles share their distances
        if world.all():
            continue
        distance = csgraph.dijkstra(graph, directed=False, indices=np.flatnonzero(~world), min_only=True)
        reached = distance[world & np.isfinite(distance)]
        longest = max(longest, float(reached.max()) if reached.size else 0.0)
    return math.pi * math.sqrt(longest / g)


#: :func:`off_balance`: a free particle is off its elastic balance when its elastic force over its stiffness row is
#: more than ``RELAX_TOLERANCE`` × the model's shortest spring rest length (its extent without springs; the static
#: equilibrium's convergence test, per spacing) and more than ``OFF_BALANCE_ROUNDOFF`` × the scalar's machine
#: epsilon × the largest coordinate: the forces' round-off, a few ε max|x| at most (a float32 spring length
#: differences coordinates of that size; measured 0.11-0.16 ε max|x| on the battery's flat cloths at rest).
OFF_BALANCE_ROUNDOFF = 16.0


def off_balance(model: Model) -> np.ndarray:
    """How far each world starts from its elastic equilibrium, in units of its threshold [-], float64, shape
    [world_count]: the largest |fᵢ| / rowᵢ over its free particles, fᵢ [N] the elements' force at the initial state
    at rest (loads, if any, count too: :func:`in_motion` asks only without them) and rowᵢ [N/m] its Gershgorin
    row (the sum of its elements' stiffness, ≥ the diagonal Kᵢᵢ: |fᵢ| / rowᵢ [m] is at most the move one Jacobi
    step of the elastic problem gives the particle), over
    max(``RELAX_TOLERANCE`` × the shortest spring rest length, ``OFF_BALANCE_ROUNDOFF`` ε max|x|). Above 1 the model
    moves by itself when released (a cloth folded against its bend springs or stretched); a model at its rest
    lengths stays at round-off. One force evaluation and one host read of the forces, positions and stiffness rows
    (0.8 and 1.3 ms of CPU for the 32² and 64² cloths of :mod:`.stability_battery`); its values there are in
    bench/results/advisor_battery_cpu.md."""
    worlds, n = model.world_count, model.particle_count
    if n == 0:
        return np.zeros(worlds)
    state = model.state()
    state.particle_qd.zero_()
    state.particle_f.zero_()
    eval_forces(model, state, None)  # without loads (in_motion's case): the elements' forces alone
    force = np.linalg.norm(state.particle_f.numpy().astype(np.float64), axis=-1).reshape(worlds, n)
    q = state.particle_q.numpy().astype(np.float64)
    free = free_particles(model)
    rows = _gershgorin_rows(model, _stiffness_values(model, None), free, positions=q)
    move = np.where(free & (rows > 0.0), force / np.where(rows > 0.0, rows, 1.0), 0.0)
    rest = model.spring_rest_length.numpy() if model.spring_count else np.zeros(0)
    rest = rest[rest > 0.0]
    length = float(rest.min()) if rest.size else max(float(np.ptp(q, axis=0).max()), 1.0e-6)
    eps = float(np.finfo(wp.dtype_to_numpy(model.scalar)).eps)
    threshold = max(RELAX_TOLERANCE * length, OFF_BALANCE_ROUNDOFF * eps * float(np.abs(q).max()), 1.0e-300)
    return move.max(axis=1) / threshold


def in_motion(model: Model, control=None) -> bool:
    """Whether the model leaves its initial state by itself: loads act (:func:`has_loads`), a keyframe track
    drives pins or inputs, a particle starts moving, or, with none of these, some world starts away from its
    elastic equilibrium (:func:`off_balance` above 1: a folded or stretched cloth released from rest; one force
    evaluation, only for a model that none of the others set moving)."""
    if (has_loads(model, control) or bool(model.track_table.tracks)
            or bool(np.any(model.particle_qd.numpy()))):
        return True
    return bool((off_balance(model) > 1.0).any())


@dataclass(frozen=True)
class TransientPeak:
    """The highest ω_max each world reached in the dry run of :func:`transient_peak`.

    Attributes:
        world_omega_max: each world's peak ω_max [rad/s], float64, shape [world_count] (at least the
            ``start`` estimate's).
        world_peak_time: when each world reached it [s], float64, shape [world_count] (0: at the start).
        world_mode: each world's power-iteration vector at its peak, float64, shape [world_count,
            particle_count, 3].
        positions: each world's positions at its peak [m], float64, shape [world_count · particle_count, 3].
        duration: simulated time of the dry run [s].
        step: its step [s].
        finite: False when the dry run's state turned non-finite (it stopped there).
        world_lowest_ratio: with ``lowest_ratio``, each world's lowest top-mode damping ratio xᵀDx / xᵀKx [s]
            over the start and the dry run's re-estimates (:func:`~.damping.top_mode_ratios`), shape [world_count];
            else ``None``.
        cut_short: why the dry run stopped at its budget before it was done (``PROBE_MAX_STEPS``,
            ``PROBE_TIME_BUDGET``), one phrase; empty when it ran its course. The peaks are then not to be
            trusted: judge by a bound.
        world_swing_omega_max: each world's peak ω_max [rad/s] over the first swing alone (the dry run as it ended
            before it lasted ``PROBE_PERIODS`` swings), shape [world_count]; ``None``: the same as ``world_omega_max``.
        swing_complete: whether the dry run got past its first swing before it ended or was cut short (then
            ``world_swing_omega_max`` is that swing's peak even where ``cut_short`` is set).
        trace_times: when ω_max was estimated [s]: 0 (the start's estimate), then every re-estimate, shape [samples];
            ``None`` where no dry run was made.
        world_trace: each world's ω_max at those times [rad/s] (before the refinement at the peak; a world the dry run
            does not track keeps its start's), float64, shape [samples, world_count]; ``None`` with ``trace_times``.
    """

    world_omega_max: np.ndarray
    world_peak_time: np.ndarray
    world_mode: np.ndarray
    positions: np.ndarray
    duration: float
    step: float
    finite: bool
    world_lowest_ratio: np.ndarray | None = None
    cut_short: str = ""
    world_swing_omega_max: np.ndarray | None = None
    swing_complete: bool = True
    trace_times: np.ndarray | None = None
    world_trace: np.ndarray | None = None


def _keeps_plasticity(function):
    """Run ``function(model, ...)`` and put the model's plastic springs back as they were: its static solves and
    dry runs step the model, and plastic springs keep their yield in the model (a plastic bar that sagged in
    the dry run would start the real run collapsed)."""

    @functools.wraps(function)
    def wrapper(model, *args, **kwargs):
        if not model.spring_material_law.plastic:
            return function(model, *args, **kwargs)
        saved = wp.clone(model.spring_plastic_rest_length), wp.clone(model.spring_plastic_strain)
        try:
            return function(model, *args, **kwargs)
        finally:
            wp.copy(model.spring_plastic_rest_length, saved[0])
            wp.copy(model.spring_plastic_strain, saved[1])

    return wrapper


@_keeps_plasticity
def transient_peak(model: Model, *, control=None, stiffness=None, horizon: float = PROBE_HORIZON,
                   start: OmegaMaxEstimate | None = None, start_positions: np.ndarray | None = None,
                   lowest_ratio: bool = False, least: float | None = None) -> TransientPeak:
    """The highest ω_max each world reaches on its way from the initial state: a dry run of the scene as it
    will run (loads, control, pins and their tracks, colliders), by velocity Verlet at a step that is stable
    at any state, with ω_max re-estimated along it (constants ``PROBE_*``).

    A cloth released unstretched swings past its static stretch before it settles: measured on the 20 × 20
    hanging cloth at 13 kN/m, ω_max is 719 rad/s at the start, 924 at the static equilibrium and 989 at
    t = 0.45 s, and a step that keeps the equilibrium stable (ωh = 1.92 for symplectic Euler) blows up there.

    Args:
        model: the model.
        control: the run's Control (its external force acts in the dry run).
        stiffness: as in :func:`~.advisor.advise` (the power iterations' spring stiffness; the dry run uses the model's).
        horizon: the longest dry run [s] (> 0).
        start: an estimate to start from and to beat (e.g. at the static equilibrium), with
            ``start_positions`` [m], float64, shape [world_count · particle_count, 3], where it was made;
            default: the initial state's.
        lowest_ratio: also keep each world's lowest top-mode damping ratio along the way (explicit Euler's
            limit: the stretch that makes the top mode stiffer across its springs than along them, where their
            dampers act, need not come with the highest ω_max); one host read of the state per re-estimate.
        least: the shortest dry run [s] (at most ``horizon``); default ``PROBE_MIN_TIME`` or ``PROBE_PERIODS`` of the
            cloth's swings (:func:`swing_time`), whichever is longer. The first swing's peak
            (:attr:`TransientPeak.world_swing_omega_max`) is the peak when the dry run would have ended had it
            lasted ``PROBE_MIN_TIME`` or one swing (at most ``least``).
    """
    horizon = checks.positive("horizon", horizon)
    k = _stiffness_values(model, stiffness)
    worlds, n = model.world_count, model.particle_count
    if start is None:
        start = _power_iteration(model, k, None, 1000, PROBE_TOLERANCE, 0)
        start_positions = model.particle_q.numpy().astype(np.float64)
    peak = start.world_omega_max.copy()
    mode = start.world_mode.copy()
    positions = np.array(start_positions, dtype=np.float64).reshape(worlds, n, 3)
    peak_time = np.zeros(worlds)
    ratio_arrays = _ratio_arrays(model) if lowest_ratio else None  # read once, not at every re-estimate

    def ratios(x: np.ndarray, q: np.ndarray) -> np.ndarray:
        return _top_mode_ratios(_tangent_stiffness(model, k, q.reshape(-1, 3)), ratio_arrays, list(x), q)

    lowest = ratios(mode, positions) if lowest_ratio else None
    bound = _gershgorin(model, k, free_particles(model))
    safe = _world_limits("velocity_verlet", bound, _damping_ranges(model, k, [None] * worlds, model.particle_q))
    safe = float(safe[bound > 0.0].min()) if (bound > 0.0).any() else math.inf
    if not math.isfinite(safe) or safe <= 0.0:
        return TransientPeak(peak, peak_time, mode, positions.reshape(-1, 3), 0.0, 0.0, True, lowest)
    swing = swing_time(model)
    least = min(horizon, max(PROBE_MIN_TIME, PROBE_PERIODS * swing) if least is None else
                checks.positive("least", least))
    first = min(least, max(PROBE_MIN_TIME, swing))  # the first swing: its peak is kept apart
    swing_peak, swing_end = None, math.inf
    substeps = PROBE_CHECK / (PROBE_FRACTION * safe)  # a float: ~1e16 for an absurd stiffness
    needed = math.ceil(first / PROBE_CHECK) * max(1.0, math.ceil(substeps))
    if needed > PROBE_MAX_STEPS:  # a dry run whose first swing would take too long: none, and the caller bounds ω_max
        return TransientPeak(peak, peak_time, mode, positions.reshape(-1, 3), 0.0, PROBE_FRACTION * safe, True,
                             lowest, cut_short=f"it would take {needed:.3g} steps of {PROBE_FRACTION * safe:.3g} s, "
                             f"past its budget of {PROBE_MAX_STEPS}")
    substeps = max(1, math.ceil(substeps))
    sim = Simulator(model, integrator=VelocityVerlet(model), fps=1.0 / PROBE_CHECK, substeps=substeps,
                    control=control, guard=None)
    iteration = Lanczos(model, k, mode, steps=PROBE_STEPS)
    running = (bound > 0.0).astype(np.int32)
    iteration.active.assign(running)
    snapshot = wp.clone(sim.state.particle_q)
    iteration.expand(snapshot)  # uncaptured: loads the modules (a capture must not)
    iteration.restart()
    with wp.ScopedCapture(device=model.device, force_module_load=False) as capture:
        iteration.expand(snapshot)
    rise, finite, level, climbing = 0.0, True, None, True  # level: the dry run's own running peak (not the start's)
    cut_short, started = "", None
    times, trace = [0.0], [start.world_omega_max.copy()]
    while sim.time < horizon and (sim.time < least or sim.time < 2.0 * rise):
        if swing_peak is None and sim.time >= first and sim.time >= 2.0 * rise:  # where the first swing's run ended
            swing_peak, swing_end = peak.copy(), sim.time
        if sim.frame * substeps >= PROBE_MAX_STEPS:
            cut_short = f"it reached its budget of {PROBE_MAX_STEPS} steps at t = {sim.time:.3g} s"
            break
        if started is not None and time.process_time() - started > PROBE_TIME_BUDGET:
            cut_short = f"it reached its budget of {PROBE_TIME_BUDGET:g} CPU seconds at t = {sim.time:.3g} s"
            break
        sim.step_frame()
        if started is None:
            started = time.process_time()  # after the first frame, which compiles the kernels
        if not (climbing or lowest_ratio) and sim.frame % PROBE_SPARSE:
            continue  # below every world's running peak at the last re-estimate: every PROBE_SPARSE-th frame only
            # (explicit Euler's lowest damping ratio need not come with a peak: it is sampled at every frame)
        wp.copy(snapshot, sim.state.particle_q)
        wp.capture_launch(capture.graph)
        omega = iteration.restart()
        if not np.isfinite(omega).all():
            finite = False
            break
        times.append(sim.time)
        trace.append(np.where(running > 0, omega, trace[0]))
        climbing = level is None or bool((omega > level).any())
        if level is None or (omega > level * (1.0 + PROBE_RISE)).any():  # still rising somewhere
            rise = sim.time
        level = omega if level is None else np.maximum(level, omega)
        higher = omega > peak
        if higher.any() or lowest_ratio:
            q = sim.state.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
            if not np.isfinite(q[higher]).all():
                finite = False
                break
            x = iteration.x.numpy().astype(np.float64).reshape(worlds, n, 3)
            positions[higher], mode[higher], peak_time[higher], peak[higher] = q[higher], x[higher], sim.time, omega[higher]
            if lowest_ratio:
                lowest = np.fmin(lowest, ratios(x, q))
    moved = (peak_time > 0.0) & (running > 0)  # worlds that peaked in the dry run: refine their estimate there
    if finite and not cut_short and moved.any():
        snapshot.assign(positions.reshape(-1, 3).astype(wp.dtype_to_numpy(model.scalar)))
        iteration.rows[0].assign(mode.reshape(-1, 3).astype(wp.dtype_to_numpy(model.scalar)))
        iteration.active.assign(moved.astype(np.int32))
        refined = peak
        for _ in range(PROBE_REFINE):
            wp.capture_launch(capture.graph)
            refined = iteration.restart()
        higher = moved & np.isfinite(refined) & (refined > peak)
        if higher.any():
            peak[higher] = refined[higher]
            mode[higher] = iteration.x.numpy().astype(np.float64).reshape(worlds, n, 3)[higher]
    swing_complete = swing_peak is not None or not cut_short
    if swing_peak is None:
        swing_peak = peak.copy()
    else:  # a world whose peak came within the first swing: its refined peak
        within = peak_time <= swing_end
        swing_peak[within] = peak[within]
        swing_peak = np.minimum(swing_peak, peak)
    return TransientPeak(peak, peak_time, mode, positions.reshape(-1, 3), sim.time, sim.dt, finite, lowest,
                         cut_short=cut_short, world_swing_omega_max=swing_peak, swing_complete=swing_complete,
                         trace_times=np.asarray(times), world_trace=np.asarray(trace, dtype=np.float64))
