"""Run-time guards of a simulation: stop with a clear error, naming frame, substep, world, particle or spring
and a remedy, when the state turns non-finite, a spring tears far past its rest length, or the kinetic
energy runs away. The checks run on the device inside the captured frame, per world
(``kernels/guards.py``); the host reads one small status record per world and frame. A failure stops the
run, or (``GuardLimits(stop="world")``) holds only the failed world while the others go on. What the guard
checks and what it reports (``GuardLimits``, ``GuardReport``, ``EnergyBalance``) are in ``guard_records.py``."""

from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..kernels.guards import (
    BALANCE_DISSIPATION,
    DAMPERS_IN_FORCE_PASS,
    BALANCE_ENERGY,
    BALANCE_PEAK,
    BALANCE_REBASE,
    BALANCE_REFERENCE,
    BALANCE_SLOTS,
    BALANCE_WORK,
    CARRY_SLOTS,
    FOLD_ABOVE,
    FOLD_CHUNK,
    FOLD_COLUMNS,
    GUARD_BALANCE,
    GUARD_BALANCE_FLOOR,
    GUARD_BALANCE_TOLERANCE,
    GUARD_BUDGET,
    GUARD_ENERGY,
    GUARD_EXCESS,
    GUARD_FLOATS,
    GUARD_INTS,
    MIRROR_CLOCK,
    MIRROR_COLUMNS,
    GUARD_KINETIC_ENERGY,
    GUARD_LIMIT_KINETIC_ENERGY,
    GUARD_LIMIT_STRAIN,
    GUARD_LIMITS,
    GUARD_MAX_STRAIN,
    GUARD_NONFINITE,
    GUARD_NONFINITE_COUNT,
    GUARD_NONFINITE_PARTICLE,
    GUARD_STRAIN,
    GUARD_STRAIN_PARTICLE,
    GUARD_STRAIN_ELEMENT,
    GUARD_STRAIN_FAMILY,
    GUARD_STOP_WORLD,
    GUARD_SUBSTEP,
    GUARD_WORK_FACTOR,
    GUARD_TRIPPED,
    NO_PARTICLE,
    RUNNING_POWER,
    RUNNING_SLOTS,
    RUNNING_STEP_DISSIPATION,
    RUNNING_WORK,
    guard_damper_kernel,
    guard_dissipation_kernel,
    guard_drag_kernel,
    guard_correction_energy_kernel,
    guard_correction_kinetic_kernel,
    CHECK_FUSED,
    ENERGY_BY_PARTICLES,
    ENERGY_WALK_MIN_BLOCKS,
    guard_check_kernel,
    guard_energy_kernel,
    guard_fold_kernel,
    guard_kernels,
    guard_skip_clear_kernel,
    guard_work_kernel,
    PARTIAL_SLOTS,
    POWER_RULE_MEAN,
    POWER_RULE_NONE,
    POWER_RULE_START,
    step_midpoint_kernel,
    FrameCheck,
    frame_check_arrays_type,
)
from ..kernels.families import elements, fill_elements
from ..kernels.flatten import flat_launch, launch_bounds
from ..kernels.linalg import CPU_PER_LANE, REDUCE_FILL_BLOCKS, REDUCE_PER_LANE, reduce_lanes, reduce_launch_dim, reduce_stride
from ..kernels.forces import POWER_DAMPERS, POWER_NONE, POWER_WORK, counts_work, power_sums_funcs
from ..kernels.springs import DAMPER_MEAN_RATE, DAMPER_TRAPEZOID
from .families import world_elastic_energy
from .forces import DamperSums, PowerSums
from .guard_records import (
    BALANCE_FLOOR,
    DISSIPATION_UNCOUNTED,
    ENERGY_FACTOR,
    MIDPOINT_DISSIPATION,
    POTENTIAL_INPUTS,
    WORK_UNCOUNTED,
    BalanceTerms,
    EnergyBalance,
    GuardLimits,
    STABLE_OMEGA_H,
    UNDAMPED_GROWTH,
    GuardReport,
    balance_terms,
    spring_bounds,
    stop_advice,
)
from .model import Model
from .state import State
from .stepper import StepHook
from .tracks import evaluate_input_tracks

#: Whether symplectic Euler's fused step sums the guard's power per block (``integrators.symplectic_euler_blocks_kernel``)
#: rather than per particle, by device. Off on both: on an H200 (Warp 1.16.0, 1024², bench/results/guard_cost.md) the
#: per-block step took 72.6 µs a substep against the per-particle step's 64.5 µs; on the CPU, where a block is one
#: thread, a block per particle only costs more. A test turns it on to check the sums against the per-particle ones.
STEP_POWER_BLOCKS = {True: False, False: False}

#: Partial sums per world above which a check folds them before its gather (``Guard._fold``; ``None``:
#: ``kernels/guards.py``'s FOLD_ABOVE). A test sets it low to fold small models, on the CPU too.
FOLD_MIN_BLOCKS: int | None = None

#: Whether a frame in one launch ends with the guard's check inside it (``Guard.frame_check``), by device. A test
#: turns it off to compare the check inside the frame with the check's own launches.
CHECK_IN_FRAME = {True: True, False: True}

#: Frames checked after every substep from a restart, or from a write that raised the springs' bound, at a step the bound
#: does not certify stable (``Guard._watch``).
WATCH_FRAMES = 4
#: The most an undamped mode at the springs' bound may grow over a frame under explicit Euler or midpoint before
#: the frames from a restart or a write are watched (``Guard._certified``, ``UNDAMPED_GROWTH``).
WATCH_FRAME_GROWTH = 10.0
#: A count of unchecked frames past any ``GuardLimits.check_frames``: the next frame is checked.
FORCE_CHECK = 1 << 30


class Guard(StepHook):
    """Device-side checks of one simulator's states, per world; see :class:`GuardLimits`. A :class:`StepHook`:
    it clears its record at the start of every frame and checks after every ``every``-th substep and the
    last (after every substep in the ``WATCH_FRAMES`` frames from a restart, or from a write that raised the springs'
    bound, at a step that bound does not certify: ``_watch``).

    The limits are device values: setting :attr:`limits` between frames changes no captured launch (but
    a new ``every`` does, and switching the energy balance on or off where the guard counts dissipation;
    the stepper re-captures).

    Args:
        model: the model.
        limits: what to check.
        substeps: steps per frame.
        control: the control whose external force counts as work put in (``None``: none).
        integrator: the integrator whose steps are checked.
        dt: the step h [s]; given, the energy the dampers and drag take out is integrated after every step
            (``kernels/guards.py``) and counted in the energy balance (but for the integrators of
            ``DISSIPATION_UNCOUNTED``, adaptive ones and models with contacts or strain limiting:
            :func:`dissipation_exact`); ``None`` leaves it out (one-sided).
    """

    def __init__(self, model: Model, limits: GuardLimits, substeps: int, *, control=None, integrator=None,
                 dt: float | None = None):
        self.model = model
        self.substeps = substeps
        if dt is not None:
            checks.positive("guard dt", dt)
        #: The step [s] over which the dissipation is integrated (``None``: not counted).
        self.dt = dt
        #: The integrator whose steps are checked (an unconditionally stable one has no energy balance).
        self.integrator = integrator
        #: The control whose external force counts as work put in (``None``: no external force).
        self.control = control
        self._tiled = model.device.is_cuda
        self._lanes = reduce_lanes(model.particle_count, model.block_dim, self._tiled)
        device, worlds = model.device, model.world_count
        status = np.tile([0, -1, NO_PARTICLE, NO_PARTICLE, NO_PARTICLE, 0, NO_PARTICLE], (worlds, 1))
        values = np.tile([-1.0, 0.0, 0.0, 0.0, 0.0, 0.0], (worlds, 1))
        assert status.shape[1] == GUARD_INTS and values.shape[1] == GUARD_FLOATS
        self._clear_row = status[0].copy()  # (a host copy: the deferred read builds its record from the mirror)
        self._status_clear = wp.array(status, dtype=wp.int32, device=device)
        self._values_clear = wp.array(values, dtype=wp.float64, device=device)
        self._status = wp.clone(self._status_clear)
        self._values = wp.clone(self._values_clear)
        # The frame's read of the status: a pinned host copy on CUDA (a pageable one is staged: 13 µs of copy a frame
        # on an H200), from a pool that never frees (a guard's pinned buffer freed by the garbage collector while
        # another simulator captured its graph is a cudaFreeHost inside the capture, which invalidates it: CUDA error
        # 901 at the next launch, tests/test_extremes.py on an H200); a collected guard hands its buffer back.
        self._status_host = _pinned(status.shape, wp.int32) if device.is_cuda else self._status
        if self._status_host is not self._status:
            weakref.finalize(self, _pin_back, self._status_host)
        # The reads a frame later (``post``, ``collect``): two in turn, each with an event after its frame (on the CPU
        # a frame is done when its launches return: no event), from a pool that never destroys them either: none is
        # destroyed while another simulator captures.
        self._events = [_pooled_event(device) for _ in range(2)] if device.is_cuda else [None, None]
        self._status_view = self._status_host.numpy() if self._status_host is not self._status else None
        self._pending = []  # the reads posted and not yet collected, oldest first: (event, the frame's end [s])
        self._posted = 0
        # The record's mirror (``kernels/guards.py``): each failure's record and clock, written by the check that
        # latches it, which a frame's deferred read (``collect``) takes with no copy queued behind the frame (that
        # copy took 7.5 µs of a 78 µs frame at 64² on an H200, bench/results/guard_cost.md). On CUDA pinned host memory
        # (from a pool that never frees, as the status reads') that the kernels write through its mapping, on the CPU
        # a host array. Zero where no failure is latched; a reported world's row is cleared with the record.
        mirror_shape = (worlds, MIRROR_COLUMNS)
        self._mirror_host = (_pinned(mirror_shape, wp.float64) if device.is_cuda
                             else wp.zeros(mirror_shape, dtype=wp.float64, device=device))
        if device.is_cuda:
            self._mirror_host.zero_()
            # (a collected guard hands its mirror and events back, but not while a frame it posted may still write)
            weakref.finalize(self, _hand_back, device.alias, self._mirror_host, self._events, self._pending)
            self._mirror = wp.array(ptr=self._mirror_host.ptr, dtype=wp.float64, shape=mirror_shape, device=device)
        else:
            self._mirror = self._mirror_host
        self._mirror_view = self._mirror_host.numpy()
        self._mirror_reported = []  # the worlds reported since the last reset (``_parse``): their rows to clear
        self._clock_base = 0.0  # the state's clock at the restart [s]: a frame's end is this plus its time
        # The check's passes stride (each lane several particles or elements: few partial sums to gather): on CUDA
        # up to REDUCE_PER_LANE a lane, on the CPU one thread per world walks them all (its sums in the same order).
        per_lane, fill = (REDUCE_PER_LANE, REDUCE_FILL_BLOCKS) if self._tiled else (CPU_PER_LANE, 0)
        self._check_grid = reduce_launch_dim(worlds, model.particle_count, self._lanes, per_lane, fill)
        self._partials = wp.zeros((worlds, self._check_grid[1], PARTIAL_SLOTS), dtype=wp.float64, device=device)
        self._limits = wp.zeros((worlds, GUARD_LIMITS), dtype=wp.float64, device=device)
        # The work put in since the start [J] per world, and the positions of the last check (its Δx; the
        # run's start state: :meth:`restart`).
        self._work_total = wp.zeros(worlds, dtype=wp.float64, device=device)
        self._previous_q = wp.clone(model.particle_q)
        # ... and its velocities (the lead of an explicit Euler's kinetic energy over its displacement: ``_lead``).
        self._previous_qd = wp.clone(model.particle_qd)
        # The loads at the last check (the trapezoidal rule; non-finite: none yet) and the energy balance.
        self._previous_load = wp.empty_like(model.particle_q)
        self._balance = wp.zeros((worlds, BALANCE_SLOTS), dtype=wp.float64, device=device)
        # Per-block sums of the elements' elastic energy, the blocks of each family in turn: on CUDA a family with a
        # gathered ``particle_energy`` hook walked by particles over the check's grid (``_walks``), the others by
        # elements.
        self._energy_layout = []
        self._walked = frozenset(family.name for family in model.families if family.element_count
                                 and ENERGY_BY_PARTICLES[device.is_cuda]
                                 and getattr(family.spec(model).funcs(model.scalar), "particle_energy", None))
        blocks = 0
        for family in model.families:
            if not family.element_count:
                continue
            if self._walks(family):
                lanes, grid = self._lanes, self._check_grid
            else:
                lanes = reduce_lanes(family.element_count, model.block_dim, self._tiled)
                grid = reduce_launch_dim(worlds, family.element_count, lanes, per_lane, fill)
            self._energy_layout.append((family, lanes, grid, blocks))
            blocks += grid[1]
        self._energy_partials = wp.zeros((worlds, max(blocks, 1)), dtype=wp.float64, device=device)
        # ... and of their largest strain, where a family measures it per element (``guard_energy_kernel``; -1: none).
        self._strain_partials = wp.full((worlds, max(blocks, 1)), -1.0, dtype=wp.float64, device=device)
        # ... and of the power their dampers take out at the check's state, where the integrator's force pass counts
        # them (the closing term: ``guard_energy_kernel``'s ``power``; zero for the other families).
        self._power_partials = wp.zeros((worlds, max(blocks, 1)), dtype=wp.float64, device=device)
        # Minus each world's share of the closing term at the last check, which the next check's span counts
        # (``guard_kernels``).
        self._carry = wp.zeros((worlds, CARRY_SLOTS), dtype=wp.float64, device=device)
        # Running dissipation per reducing block (``kernels/guards.py``): drag's particle blocks first, then the
        # blocks of each family with dampers.
        # On the CPU one thread per world sums a family's (or drag's) power: one block, launched over worlds.
        self._dissipation_layout = []
        self._drag_grid = reduce_launch_dim(worlds, model.particle_count, self._lanes) if self._tiled else (worlds, 1, 1)
        # ... which symplectic Euler's fused step shares where it sums the power per block (``_attach_power``): one
        # particle a lane (on the CPU, where a block is one thread, only where ``STEP_POWER_BLOCKS`` says so: a block
        # per particle).
        self._step_grid = (reduce_launch_dim(worlds, model.particle_count, self._lanes)
                           if STEP_POWER_BLOCKS[device.is_cuda] else None)
        blocks = max(self._drag_grid[1], self._step_grid[1] if self._step_grid is not None else 0)
        for family, _, _, _ in self._energy_layout:
            if getattr(family.spec(model).funcs(model.scalar), "dissipation", None) is not None:
                # (one element per lane: the dissipation passes do not stride)
                lanes = reduce_lanes(family.element_count, model.block_dim, self._tiled)
                grid = reduce_launch_dim(worlds, family.element_count, lanes) if self._tiled else (worlds, 1, 1)
                self._dissipation_layout.append((family, lanes, grid, blocks))
                blocks += grid[1]
        # ... and the blocks that count the energy the self-collision pass puts in (``_count_corrections``): the kinetic
        # energy's over the check's grid, each family's over its grid of the check's energy pass (at 64², one block
        # per world made the guard cost 12x the run with self-collision on an H200).
        self._correction_layout = None
        if getattr(model, "self_contact", None) is not None:
            self._correction_layout = [(None, self._lanes, self._check_grid, blocks)]
            blocks += self._check_grid[1]
            for family, _, _, _ in self._energy_layout:  # (each family by its elements)
                lanes = reduce_lanes(family.element_count, model.block_dim, self._tiled)
                grid = reduce_launch_dim(worlds, family.element_count, lanes, per_lane, fill)
                self._correction_layout.append((family, lanes, grid, blocks))
                blocks += grid[1]
        self._running = wp.zeros((worlds, blocks, RUNNING_SLOTS), dtype=wp.float64, device=device)
        # The running sums' blocks below the highest any pass has written to (``_running_out``): what a check gathers
        # and clears (a 1024² cloth's layout holds ~29,000 blocks of drag and damper passes that its fused step, which
        # counts that power itself, never launches).
        self._running_end = 0
        self._running_view = None  # (the blocks, their view): one array object while the mark stands
        # Where a world's partial sums outnumber what ``gather``'s one block per world adds in a few reads a lane, a
        # fold (``guard_fold_kernel``) first adds them in chunks, many blocks at once, into arrays of the same layout
        # that ``gather`` reads instead (CUDA: the CPU's passes leave one partial per world): allocated here for the
        # whole layout (a captured graph keeps its arrays), launched where the blocks a check gathers need it
        # (``_folding``).
        self._fold = None
        self._fold_view = None
        most = max(self._check_grid[1], self._energy_partials.shape[1], blocks)
        above = FOLD_MIN_BLOCKS if FOLD_MIN_BLOCKS is not None else FOLD_ABOVE
        if (self._tiled or FOLD_MIN_BLOCKS is not None) and most > above:  # (forced: on the CPU too)
            chunks = -(-most // FOLD_CHUNK)
            self._fold = (wp.zeros((worlds, chunks, PARTIAL_SLOTS), dtype=wp.float64, device=device),
                          wp.zeros((worlds, chunks), dtype=wp.float64, device=device),
                          wp.full((worlds, chunks), -1.0, dtype=wp.float64, device=device),
                          wp.zeros((worlds, chunks), dtype=wp.float64, device=device),
                          wp.zeros((worlds, chunks, RUNNING_SLOTS), dtype=wp.float64, device=device))
        # The springs' dissipation counted by the scattered force pass (``DamperSums``; ``None``: by a pass of its
        # own after every substep), and the power of dampers, drag and loads from outside counted by the integrator's
        # per-particle force pass (``PowerSums``, ``_power_rule``; ``None``: by passes of their own). The integrator
        # carries both to its force passes (``Integrator.dampers``, ``Integrator.power``).
        self._dampers = None
        self._power = None
        self._restart_balance()
        self._revision = 0
        #: Whether the simulator reads each frame's verdict a frame later and checks a frame before it is read
        #: (``Simulator.defer_verdict``, its default) and the frames are not read one by one: only then may a check span frames (``GuardLimits.check_frames``).
        self.deferred = False
        #: Called before a read of the guard's sums where the last frame's end went unchecked (``Simulator.settle``,
        #: which checks it and reads its verdict), or ``None``.
        self.before_read = None
        self._skip_end = False  # this frame's end is left to a later check (``refresh``: a check spans frames)
        self._unchecked = FORCE_CHECK  # frames in a row whose end no check read (FORCE_CHECK: the next is checked)
        self._reported = False
        self._every = None
        self._watching = False  # this frame checks every substep (``refresh``)
        self._watch_left = 0  # frames still to watch
        self._watch_start = True  # the first frame from a restart is watched where the step is not certified
        self._bound = 0.0  # the springs' ω_max bound [rad/s] at the last refresh (``_step_bound``)
        self._rate = 0.0  # ... and their dampers' rate bound [1/s]
        self._dissipating = None
        self._midpoint = False
        self._working = False
        self._step_position = self._step_velocity = self._step_time = self._step_start = None
        # The one-launch frame's check (``frame_check``): its partial sums, one per block of the frame (at most one
        # block per 32 particles on CUDA, one on the CPU; the frame takes a view of its blocks' columns), and the
        # families' element counts. Allocated here: a frame's first check runs inside a capture.
        most = -(-max(model.particle_count, 1) // 32) if self._tiled else 1
        self._frame_partials = (wp.zeros((worlds, most, PARTIAL_SLOTS), dtype=wp.float64, device=device),
                                wp.zeros((worlds, most), dtype=wp.float64, device=device),
                                wp.full((worlds, most), -1.0, dtype=wp.float64, device=device),
                                wp.zeros((worlds, most), dtype=wp.float64, device=device))
        counts = tuple(family.element_count for family in model.families)  # (fixed once the model is finalized)
        self._frame_count_array = wp.array(counts or (0,), dtype=wp.int32, device=device)
        self._frame_checked = False  # the frame's last check ran inside the one-launch frame (``frame_check``)
        self.limits = limits

    @property
    def limits(self) -> GuardLimits:
        """What the guard checks (:class:`GuardLimits`); settable between frames."""
        return self._limits_host

    @limits.setter
    def limits(self, limits: GuardLimits) -> None:
        if not isinstance(limits, GuardLimits):
            raise TypeError(f"guard limits must be a warpspring.GuardLimits, got {type(limits).__name__}")
        self._limits_host = limits
        self._every_set = min(limits.every or self.substeps, self.substeps)
        every = 1 if self._watching else self._every_set
        integrator = self.integrator
        # An unconditionally stable integrator has no balance (``balance_applies``): nothing to count per substep.
        balanced = limits.energy_balance > 0.0 and not getattr(integrator, "unconditionally_stable", False)
        dissipating = (self.dt is not None and balanced and limits.dissipation
                       and getattr(integrator, "name", None) not in DISSIPATION_UNCOUNTED
                       and not getattr(integrator, "adaptive", False))
        self._midpoint = bool(dissipating) and getattr(integrator, "name", None) in MIDPOINT_DISSIPATION
        # Wind and handles: their work counted per substep where the balance needs it (see ``_family_work``).
        working = balanced and self._family_work_countable() and bool(self._working_families())
        if working != self._working or balanced != getattr(self, "_balanced", None):
            # The integrator's force pass counts the power sums by ``balanced`` (``_power_modes``): a switch of the
            # balance re-captures, as a switch of the working families does.
            self._working = working
            self._balanced = balanced
            self._revision += 1
        finish = getattr(integrator, "finish_step", None)
        if finish is not None and self._correction_layout is not None:
            finish.watch = self._count_corrections if balanced else None
        if (self._midpoint or working) and self._step_velocity is None:
            size = self.model.world_count * self.model.particle_count
            self._step_position = wp.zeros(size, dtype=self.model.vec3, device=self.model.device)
            self._step_velocity = wp.zeros(size, dtype=self.model.vec3, device=self.model.device)
            self._step_time = wp.zeros(self.model.world_count, dtype=wp.float64, device=self.model.device)
        if every != self._every or dissipating != self._dissipating:
            if self._dissipating is not None and dissipating != self._dissipating:
                self._clear_running()  # no trapezoid from a power sampled before the switch
            self._every = every
            self._dissipating = dissipating
            self._revision += 1
        if limits.stop == "world":
            self.model.hold_worlds()  # a failed world is held by the integrators' last pass
        self._write_limits()

    def refresh(self) -> None:
        """After the model's values were written (gravity switched on mid-run raises the scene's energy scale;
        a new stiffness changes the elastic energy without work): re-derive the default limits and re-base
        the energy balance at the next check; and clear the record of failures :meth:`reports` read. Value writes, no
        re-capture. Then decide whether the coming frame's end is checked or left to a later check
        (``GuardLimits.check_frames``; a write or a restart has the frame checked). Call between frames (the
        Simulator does)."""
        if self._reported:
            self.reset()
            self._reported = False
        changed = self._watch_start
        if self._input_version != self.model.input_version:
            changed = True
            self._write_limits()
            self.rebase()
            before, rate = self._bound, self._rate
            self._bound = self._step_bound()
            if (self._bound > before or self._rate > rate) and not self._certified():  # (stiffer, or damped harder)
                self._watch_left = WATCH_FRAMES
        if self._watch_start:
            self._bound = self._step_bound()
            self._watch_left = 0 if self._certified() else WATCH_FRAMES
            self._watch_start = False
        self._watch(self._watch_left > 0)
        self._watch_left = max(self._watch_left - 1, 0)
        if changed:
            self._unchecked = FORCE_CHECK  # the balance re-bases at the frame's check: no span across a write
        self._skip_end = self._spans_frames() and self._unchecked + 1 < self._limits_host.check_frames
        self._unchecked = self._unchecked + 1 if self._skip_end else 0

    @property
    def revision(self) -> tuple:
        """What the launches of an advance depend on (``StepHook.revision``): the guard's configuration and whether
        this frame's end is checked (a stepper keeps a graph of each)."""
        return self._revision, self._skip_end

    @property
    def frame_unchecked(self) -> bool:
        """Whether the frame last advanced (or about to be) leaves its end to a later check: a check spans frames
        (``GuardLimits.check_frames``); :meth:`catch_up` checks it before it is read."""
        return self._skip_end

    def _spans_frames(self) -> bool:
        """Whether a check may span frames now (``GuardLimits.check_frames``):
        - the verdict is read a frame later and the frames are not read one by one (``deferred``);
        - the run stops as a whole (``stop="world"`` records each world's failure frame: a batch's data);
        - no frame is watched: a step the springs' bound does not certify is checked after every substep for
          ``WATCH_FRAMES`` frames from a restart or a write, where a fast linear instability shows (a spring's
          tangent stiffness never exceeds its k, so the step's linear stability cannot worsen later without a
          write); explicit Euler and midpoint never span: their limit is their damping's, which the bound cannot
          certify, so the frames after the watched ones could still grow past it unseen but by the balance;
        - nothing is counted between substeps but by the step itself;
        - the model's elements are springs alone (a family with stiffness of its own is outside the bound);
        - the loads cannot change between frames without a write the guard sees (gravity alone: a control force,
          wind, handles, tracks, driven pins, moving colliders, emitters and self-collision each keep a check every
          frame).
        A mode that grows more slowly than the watched frames show is caught by the balance at the span's check, as
        by a frame's."""
        limits, model = self._limits_host, self.model
        if limits.check_frames <= 1 or not self.deferred or self._watching or self._every_set < self.substeps:
            return False
        if limits.stop != "run":
            return False  # (a world's failure frame is what a batch of worlds records: each frame checked)
        if self.dt is None or not self.quiet_between_steps(self.substeps):
            return False
        if any(family.name != "springs" and family.element_count for family in model.families):
            return False
        integrator = self.integrator
        if not (getattr(integrator, "unconditionally_stable", False) or getattr(integrator, "adaptive", False)
                or STABLE_OMEGA_H.get(getattr(integrator, "name", None)) is not None):
            return False  # explicit Euler, midpoint: a damping limit the bound cannot certify
        external = self.control is not None and model.force_features(self.control).external
        pins = getattr(model, "pin_groups", None)
        return not (external or self._working_families() or model.emitters or model.input_tracks is not None
                    or model.shape_moving or getattr(model, "shape_deforming", False)
                    or (pins is not None and pins.driven) or getattr(model, "self_contact", None) is not None)

    def _read_checked(self) -> None:
        """Before a read of the guard's sums: where the last frame's end was left to a later check, have it checked
        (:attr:`before_read`, the simulator's ``settle``), so that what is read is that frame's."""
        if self._skip_end and self.before_read is not None:
            self.before_read()

    def catch_up(self, state: State) -> bool:
        """Check ``state`` (the last advance's result) where the frames since the last check went unchecked (a check
        spanning frames, :attr:`frame_unchecked`), before it is read: launches the check (device only) and returns
        ``True``, or returns ``False`` where the last frame's end was checked."""
        if not self._skip_end:
            return False
        self.check(state, self.substeps - 1, last=True)
        self._skip_end = False
        self._unchecked = 0
        return True

    def _watch(self, watching: bool) -> None:
        """Check every substep of this frame (``watching``) or every ``every`` (a re-capture where it changes). The
        ``WATCH_FRAMES`` frames from a restart or from a write that raised the springs' bound (a stiffer spring, a
        lighter particle) are watched where the bound does not certify the step stable: an unstable mode grows by
        |λ| per substep, up to ~10 at twice an integrator's limit and ~100 past it tenfold, so checked once a frame
        of 40 substeps its state overflows before the check sees it (a spring made 100× stiffer mid-run on
        examples/hanging_cloth.toml at the advisor's 42 substeps: non-finite at the frame's check; RK4 at twice its
        limit on that cloth with a moving collider, whose balance is off: non-finite at frame 2); checked after every
        substep, the balance or the tear limit stops it within a few substeps of its start. A mode that grows more
        slowly is seen by the frames' own checks before it overflows."""
        if watching == self._watching:
            return
        self._watching = watching
        self.limits = self._limits_host  # the effective ``every`` (re-captures)

    def _step_bound(self) -> float:
        """The largest Gershgorin bound of ω_max [rad/s] of the model's springs over its worlds (0 without springs;
        reads the device)."""
        model = self.model
        per_world = any(getattr(model, name).shape[0] > 1 for name in ("spring_stiffness", "particle_mass"))
        worlds = range(model.world_count if per_world else 1)
        bounds = [b for b in (spring_bounds(model, w) for w in worlds) if b is not None]
        self._rate = max((b[3] for b in bounds), default=0.0)  # ... and of the dampers' rate λ_D [1/s]
        return max((b[2] for b in bounds), default=0.0)

    def _certified(self) -> bool:
        """Whether the springs' bound certifies the step stable for the integrator: ω_max h within its undamped limit
        (``STABLE_OMEGA_H``) and the dampers' rate λ_D h ≤ 1, in a model whose only elements are springs (wind
        triangles, handles, hinges and tets have stiffness and damping of their own, outside the bound: the flag in
        wind at twice the advisor's step, its springs' ω_max h ≤ 1.88, overflowed within its first frame). Implicit
        and adaptive integrators and a guard without a step count as certified. Explicit Euler and midpoint, whose
        limit is their damping's, which the bounds (upper bounds) cannot certify, count as certified where an undamped
        mode at the bound grows by at most ``WATCH_FRAME_GROWTH`` over a frame (``UNDAMPED_GROWTH``): a mode past
        their damping limit grows by little more than 1 per step and the frames' checks see it, but a spring made
        100× stiffer grows by several a step and overflowed within the frame after the write."""
        integrator = self.integrator
        name = getattr(integrator, "name", None)
        limit = STABLE_OMEGA_H.get(name)
        growth = UNDAMPED_GROWTH.get(name)
        if (self.dt is None or getattr(integrator, "unconditionally_stable", False)
                or getattr(integrator, "adaptive", False) or (limit is None and growth is None)):
            return True
        if self._bound == 0.0:
            return True  # no springs: nothing the bound could tell (a handle alone, tets alone: not watched)
        if any(family.name != "springs" and family.element_count for family in self.model.families):
            return False
        h = float(self.dt)
        if limit is not None:
            within = self._bound * h <= limit
        else:  # (explicit Euler, midpoint: the undamped growth over a frame)
            within = self.substeps * math.log(growth(self._bound * h)) <= math.log(WATCH_FRAME_GROWTH)
        return within and self._rate * h <= 1.0

    def balance_applies(self) -> bool:
        """Whether the energy balance can be kept for the model as it is now and applies to the integrator
        (see ``GuardLimits``; implicit Euler's one Newton step per step can add energy at large steps,
        which is not an instability)."""
        model = self.model
        stabilizers = model.stabilizers
        return not (model.shape_moving or getattr(model, "shape_deforming", False)
                    or stabilizers.enabled("max_particle_force")
                    or bool(model.emitters)
                    or (bool(self._working_families()) and not self._family_work_countable())
                    or any(name in model._tracks for name in POTENTIAL_INPUTS)
                    or getattr(self.integrator, "unconditionally_stable", False))

    def balance_terms(self) -> BalanceTerms:
        """What the energy balance counts for the model as it is now, term by term, and what it leaves out or why it
        is off (:class:`BalanceTerms`; the run summary prints its ``describe()``)."""
        integrator = self.integrator
        dissipation = (self.dt is not None and self._limits_host.dissipation
                       and getattr(integrator, "name", None) not in DISSIPATION_UNCOUNTED
                       and not getattr(integrator, "adaptive", False))
        return balance_terms(self.model, integrator=integrator, control=self.control, limits=self._limits_host,
                             dissipation=dissipation, work_countable=self._family_work_countable(),
                             counted_losses=dissipation_exact(self.model))

    def _family_work_countable(self) -> bool:
        """Whether the balance can count wind's and handles' work for the integrator (``WORK_UNCOUNTED``; adaptive
        integrators step finer than the guard sees). Where not, the balance is off with wind or handles."""
        integrator = self.integrator
        return getattr(integrator, "name", None) not in WORK_UNCOUNTED and not getattr(integrator, "adaptive", False)

    def rebase(self) -> None:
        """Take the energy balance's reference anew at the next check: call after writing a state's positions
        or velocities directly between frames (the Simulator does it for writes through the model)."""
        balance = self._balance.numpy()
        balance[:, BALANCE_REBASE] = 1.0
        self._balance.assign(balance)

    def _write_limits(self) -> None:
        limits = self._limits_host
        model = self.model
        self._input_version = model.input_version
        if limits.max_kinetic_energy is not None:
            self.world_max_kinetic_energy = np.full(model.world_count, limits.max_kinetic_energy)
        else:
            self.world_max_kinetic_energy = ENERGY_FACTOR * energy_scales(model)
        values = np.zeros((model.world_count, GUARD_LIMITS))
        values[:, GUARD_LIMIT_STRAIN] = limits.tear_strain
        values[:, GUARD_LIMIT_KINETIC_ENERGY] = self.world_max_kinetic_energy
        values[:, GUARD_STOP_WORLD] = 1.0 if limits.stop == "world" else 0.0
        values[:, GUARD_WORK_FACTOR] = ENERGY_FACTOR if limits.max_kinetic_energy is None else 0.0
        values[:, GUARD_BALANCE_TOLERANCE] = limits.energy_balance if self.balance_applies() else 0.0
        values[:, GUARD_BALANCE_FLOOR] = BALANCE_FLOOR * energy_scales(model)
        self._limits.assign(values)

    @property
    def max_kinetic_energy(self) -> float:
        """The kinetic-energy limit of world 0 [J] (every world's: ``world_max_kinetic_energy``)."""
        return float(self.world_max_kinetic_energy[0])

    @property
    def counts_dissipation(self) -> bool:
        """Whether the energy balance counts the dampers' and drag's dissipation D now (a step given, the balance
        and ``GuardLimits.dissipation`` on, an integrator outside ``DISSIPATION_UNCOUNTED`` and not adaptive,
        a model without position corrections: :func:`dissipation_exact`)."""
        return bool(self._dissipating) and dissipation_exact(self.model)

    @property
    def every(self) -> int:
        """Substeps between checks (the last substep of a frame is always checked)."""
        return self._every

    def begin(self) -> None:
        """No launch: a check that passes leaves the record clear for the next (``decide``), and the record of a frame
        whose failures were reported is cleared before the next (:meth:`refresh`). A mark of a check run inside the
        last advance's frame that an error left unconsumed is dropped (:meth:`frame_checked`)."""
        self._frame_checked = False

    def _running_out(self, end: int) -> wp.array:
        """The running sums for a pass that writes their blocks below ``end``: from then on each check gathers them
        (``_running_written``)."""
        self._running_end = max(self._running_end, end)
        return self._running

    def _running_written(self) -> wp.array:
        """The running sums' blocks below the highest any pass has written to (at least one): what a check gathers and
        clears. A pass launches before the checks that gather it (a frame's substeps, then its check), so a graph
        captured after it gathers its blocks; a pass switched off leaves its blocks in the view, cleared. One view
        object while the mark stands (the CPU's launch replay keys arrays by identity)."""
        end = max(self._running_end, 1)
        if self._running_view is None or self._running_view[0] != end:
            self._running_view = (end, self._running[:, :end])
        return self._running_view[1]

    def _folding(self):
        """The fold's launch grid and arrays (views of those made for the whole layout) where the partial sums a check
        gathers per world outnumber ``FOLD_ABOVE`` (``FOLD_MIN_BLOCKS`` where set, on the CPU too), else ``None``."""
        if self._fold is None:
            return None
        most = max(self._check_grid[1], self._energy_partials.shape[1], self._running_written().shape[1])
        above = FOLD_MIN_BLOCKS if FOLD_MIN_BLOCKS is not None else FOLD_ABOVE
        if most <= above:
            return None
        chunks = -(-most // FOLD_CHUNK)
        if self._fold_view is None or self._fold_view[0] != chunks:
            self._fold_view = (chunks, ((self.model.world_count, chunks, FOLD_COLUMNS),
                                        *(array[:, :chunks] for array in self._fold)))
        return self._fold_view[1]

    def history(self) -> list:
        """The arrays a check carries to the next (the work put in, the last check's positions and loads,
        the energy balance, the running dissipation)."""
        dampers = [] if self._dampers is None else [self._dampers.damper, self._dampers.dissipated, self._dampers.skip]
        power = [] if self._power is None else [self._power.sums]
        return [self._work_total, self._previous_q, self._previous_qd, self._previous_load, self._balance, self._running,
                self._status, self._values, *dampers, *power, self._carry]

    def restart(self, state: State | None = None) -> None:
        """Forget the work put in and measure from ``state`` (default the model's initial state) on: the loads
        there start the first check's trapezoid (a pin's drive carries no load on an unstretched cloth at
        the start, and its load at the first check alone would double that check's work); the energy balance
        takes its reference at the next check."""
        state = state if state is not None else self.model.state()
        self._watch_start = True
        self._skip_end = False  # (the frames before are forgotten: the next frame is checked, ``refresh``)
        self._work_total.zero_()
        wp.copy(self._previous_q, state.particle_q)
        wp.copy(self._previous_qd, state.particle_qd)
        self._restart_balance()
        self.reset(every_world=True)
        self._clock_base = float(state.time.numpy().max())  # (a sync, once a restart)
        self._dissipation_kernels()  # the power sums attached to the integrator or not (``_power``)
        gather = self._measure(state)  # Δx = 0: no work, the loads at the start recorded
        if self._power is not None:  # minus the closing term at the start opens the first span
            self._energy_passes(state)
            self._gather(gather, state, 0, carry_only=True)
        self.reset()
        if self._dissipating and not self._midpoint:
            self._dissipate(state)  # the power at the start: the first substep's trapezoid
        air = self._air_kernel()
        if air is not None and not air[1]:
            self._air_work(state)  # the air's power at the start: the first substep's trapezoid
        self._dissipation_kernels()
        if self._dampers is not None:
            self._close_dampers(state, 0.0)  # the dampers at the start: the first step's

    def _restart_balance(self) -> None:
        self._previous_load.fill_(self.model.vec3(math.nan, math.nan, math.nan))
        balance = np.zeros((self.model.world_count, BALANCE_SLOTS))
        balance[:, BALANCE_REBASE] = 1.0
        self._balance.assign(balance)
        self._clear_running()

    def _clear_running(self) -> None:
        """No dissipation pending, no power sampled yet (between frames: the last check gathered the sums)."""
        running = np.zeros(self._running.shape)
        running[..., RUNNING_POWER] = math.nan
        self._running.assign(running)
        if getattr(self, "_dampers", None) is not None:
            self._dampers.dissipated.zero_()
            self._dampers.skip.fill_(1)  # the values kept are stale: the next step starts the count
        if getattr(self, "_power", None) is not None:
            self._power.sums.zero_()
        if getattr(self, "_carry", None) is not None:
            self._carry.zero_()

    def work(self) -> np.ndarray:
        """The work the loads put into each world since the start [J], float64, shape [world_count] (the
        positive parts, check by check; reads the device; a frame whose end was left to a later check is checked
        first: :attr:`before_read`)."""
        self._read_checked()
        return self._work_total.numpy().copy()

    def energy_balance(self) -> EnergyBalance:
        """Each world's energy balance at its last check (reads the device; a frame whose end was left to a later
        check is checked first: :attr:`before_read`)."""
        self._read_checked()
        b = self._balance.numpy().astype(np.float64)
        return EnergyBalance(energy=b[:, BALANCE_ENERGY].copy(), reference=b[:, BALANCE_REFERENCE].copy(),
                             work=b[:, BALANCE_WORK].copy(), peak=b[:, BALANCE_PEAK].copy(),
                             dissipated=b[:, BALANCE_DISSIPATION].copy())

    def _needs_midpoint(self) -> bool:
        """Whether a substep's midpoint state is needed: symplectic Euler's D where something dissipates (drag, a
        family with dampers), or the working families' work."""
        if self._working and self._power is None:
            return True
        if not (self._dissipating and self._midpoint):
            return False
        drag, families = self._dissipation_kernels()
        return drag is not None or bool(families)

    def quiet_between_steps(self, steps: int) -> bool:
        """Whether the guard launches nothing but at the frame's last step: it checks once per frame and its sums
        come from the integrator's force pass alone (no pass of its own per substep: no midpoint state, drag,
        dampers', wind's or families' work counted apart)."""
        if self._every is None or self._every < steps or self._needs_midpoint():
            return False
        if self._dissipating:
            drag, families = self._dissipation_kernels()
            if drag is not None or families or self._dampers is not None:
                return False
        return self._air_kernel() is None and not (self._working and self._power is None)

    def before_step(self, state: State, step: int, steps: int) -> None:
        self._dissipation_kernels()  # the force passes counting the dampers and the power attached or not
        if self._needs_midpoint():
            self._step_start = state  # x_n, v_n: the step leaves its input as it was until after_step

    def after_step(self, state: State, step: int, steps: int) -> None:
        if self._needs_midpoint():
            # The substep's midpoint state, ((x_n + x_{n+1}) / 2, (v_n + v_{n+1}) / 2).
            start = self._step_start
            wp.launch(step_midpoint_kernel(self.model.scalar), dim=len(state.particle_qd),
                      inputs=[start.particle_q, start.particle_qd, start.time, state.particle_q, state.particle_qd,
                              state.time],
                      outputs=[self._step_position, self._step_velocity, self._step_time], device=self.model.device)
        if self._dissipating:
            self._dissipate(state)
        self._air_work(state)
        if self._dampers is not None and self._dissipating and (step == 0 or step % self._every == 0):
            # This step started from a check's state, whose step the check counted: count the next ones.
            wp.launch(guard_skip_clear_kernel(), dim=self.model.world_count, outputs=[self._dampers.skip],
                      device=self.model.device)
        if self._working and self._power is None:
            self._family_work(state)
        if (step + 1) % self._every == 0 or step + 1 == steps:
            if self._frame_checked:  # done at the end of the one-launch frame
                self._frame_checked = False
            elif not (self._skip_end and step + 1 == steps):  # (else a later frame's check spans this one)
                self.check(state, step, last=step + 1 == steps)

    def frame_check(self, steps: int, shape: tuple[int, int], *, integrator, control):
        """The check at the end of a frame in one launch of ``shape`` (threads per block, blocks per world), as
        ``(FrameCheck, arrays)`` for ``symplectic_euler_frame_kernel`` (``kernels/frames.py``), or ``None`` where it
        must run apart: where the guard does anything between substeps (``quiet_between_steps``), folds its partial
        sums first (large worlds), or counts the work of families from outside at its checks (wind, handles). Where
        the frame runs it, the stepper says so (:meth:`frame_checked`). Only for the integrator and control the guard
        checks (a frame stepped by others reads another force and other power sums)."""
        model = self.model
        if self._skip_end:
            return None  # (this frame's end is left to a later check)
        if not CHECK_IN_FRAME[model.device.is_cuda] or not self.quiet_between_steps(steps) or self._folding() is not None:
            return None
        if integrator is not self.integrator or control is not self.control:
            return None
        if self._working_families():
            return None
        specs = model.family_specs()
        if any(getattr(spec, "gathered", True) is False for spec in specs):
            return None
        force = self.control.particle_force if self.control is not None else None
        rule, features, modes = self._power_arguments(specs, force)
        counted = self._dampers_counted()
        powers = tuple(counted.get(family.name, False) for family in model.families)
        spec = FrameCheck(tiled=self._tiled, external=force is not None, power=rule, power_features=features,
                          power_modes=modes, dissipation=self.counts_dissipation, powers=powers)
        blocks = shape[1]
        partials, energy, strain, taken = self._frame_partials
        if blocks > partials.shape[1]:
            return None
        arrays = frame_check_arrays_type(model.scalar)()
        arrays.world_enabled = model.world_enabled
        arrays.status = self._status
        arrays.previous_q, arrays.previous_qd, arrays.previous_load = (self._previous_q, self._previous_qd,
                                                                       self._previous_load)
        # (the gather reads every column it is given: the frame's blocks' alone)
        arrays.partials = partials[:, :blocks]
        arrays.energy_partials, arrays.strain_partials, arrays.power_partials = (energy[:, :blocks], strain[:, :blocks],
                                                                                 taken[:, :blocks])
        arrays.counts = self._frame_count_array
        arrays.limits = self._limits
        arrays.running = self._running_written()
        arrays.values = self._values
        arrays.work_total = self._work_total
        arrays.balance = self._balance
        arrays.carry = self._carry
        arrays.mirror = self._mirror
        arrays.lead = model.scalar(self._lead())
        arrays.power_h = wp.float64(0.0 if self.dt is None else float(self.dt))
        return spec, arrays

    def frame_checked(self) -> None:
        """The frame just launched ran the check of :meth:`frame_check`: the last step's ``after_step`` leaves it out."""
        self._frame_checked = True

    def _family_work(self, state: State) -> None:
        """Add the work wind and handles (the families that do work from outside) did over the last substep to the
        running sums: their forces at the substep's midpoint state over its displacement (``guard_work_kernel``).
        Their forces depend on the velocity and move with the cloth within a frame: sampled at the checks alone,
        by the trapezoid of the loads, their work aliases like the dampers' power, and the balance could not be
        kept with wind or handles (device only; capturable)."""
        model = self.model
        working = self._working_families()
        specs = tuple(_direct(family.spec(model)) for family in working)
        # The animated inputs (the wind's track) and the working families' time-dependent arrays (the handles'
        # targets) at the midpoint's time, then back at the step's end for the passes after this one (launches only
        # where something is animated). Wind's per-triangle precompute is not needed (``_direct``).
        timed = [family for family in working if not getattr(family, "precompute", False)]
        middle = _StepPoint(self._step_position, self._step_velocity, self._step_time)
        evaluate_input_tracks(model, middle, families=timed)
        flat_launch(guard_work_kernel(model.scalar, specs, self._tiled), dim=self._drag_grid, block_dim=self._lanes,
                    inputs=[model.particle_count, model.world_enabled, model.particle_flags,
                            self._work_arrays(working, specs), model.inputs, self._status, self._step_position,
                            self._step_velocity, self._step_start.particle_q, state.particle_q],
                    outputs=[self._running_out(self._drag_grid[1])], device=model.device)
        evaluate_input_tracks(model, state, families=timed)

    def _working_families(self) -> list:
        return [family for family in self.model.families if family.does_work]

    def _air_kernel(self):
        """(kernel, midpoint) counting the work the wind does through viscous drag where the balance leaves the drag's
        dissipation out (``guard_drag_kernel``'s ``air_only``), else ``None``. Drag against moving air,
        -c (v - u), is drag against still air, -c v, whose power -c |v|² is taken out (left out with D, the balance
        stays one-sided), plus the wind's steady push c u, a load whose work c u·v the balance must count wherever it
        is on: left out
        with D (a collider in the scene, explicit Euler), a cloth in wind read as creating the energy the wind gave
        it (``examples/hanging_cloth.toml`` with a ``[wind]`` was stopped at frame 4, "created" energy that did not
        shrink with the step)."""
        model = self.model
        limits = self._limits_host
        integrator = self.integrator
        if (self.dt is None or limits.energy_balance <= 0.0 or getattr(integrator, "adaptive", False)
                or (self._dissipating and dissipation_exact(model)) or self._power_rule() != POWER_RULE_NONE):
            return None  # (with the power counted in the force pass, the wind's push is among its loads)
        features = model.force_features(self.control)
        if not (features.drag and features.wind):
            return None
        midpoint = getattr(integrator, "name", None) in MIDPOINT_DISSIPATION and self._needs_midpoint()
        return guard_drag_kernel(model.scalar, self._tiled, True, midpoint, air_only=True), midpoint

    def _air_work(self, state: State) -> None:
        """Add the wind's work through drag over the last step to the drag blocks' running sums, as negative
        dissipation (``_air_kernel``; device only, capturable)."""
        air = self._air_kernel()
        if air is None:
            return
        kernel, midpoint = air
        model = self.model
        velocity = self._step_velocity if midpoint else state.particle_qd
        wp.launch(kernel, dim=self._drag_grid, block_dim=self._lanes,
                  inputs=[model.particle_count, float(self.dt), model.world_enabled, model.particle_flags, model.inputs,
                          self._status, velocity],
                  outputs=[self._running_out(self._drag_grid[1])], device=model.device)

    def _count_corrections(self, state: State, sign: float) -> None:
        """Add ``sign`` times each world's kinetic (free particles) and elastic energy at ``state`` to the running work:
        called with -1 before the contacts' pass (before the self-collision pass where a stabiliser runs first) and +1
        after the self-collision pass (``StepFinisher.watch``), it counts the energy those passes' corrections put in or
        took out as work. A driven pin pressing free cloth against itself works through the self-collision pass, not
        through a force: in twist1440 (``analysis/torture.py``, small, duration 0.4: 101 substeps, symplectic Euler) that
        pass put in +11.0 J by t = 0.63 s against the drives' 4.5 J, and at duration 0.7 (58 substeps) the balance
        without it stopped the clean run at frame 47 for 0.226 J "created" (14 % of 1.66 J). Pins lowering cloth onto a
        collider work through the contacts' pass likewise (the battery's stack: stopped at frame 36 for 0.053 J, 15 % of
        0.355 J, with that pass left out). The weight's work over the passes' displacement is in the checks' Σ m g·Δx
        already. (Device only, capturable; the check's striding grids, each block adding its sum to its own slot:
        deterministic sums, no atomics.)"""
        model = self.model
        sign = wp.float64(sign)
        for family, lanes, grid, first in self._correction_layout:
            if family is None:
                wp.launch(guard_correction_kinetic_kernel(model.scalar, self._tiled), dim=grid, block_dim=lanes,
                          inputs=[model.particle_count, model.world_enabled, model.particle_flags, model.particle_mass,
                                  self._status, first, reduce_stride(grid), sign, state.particle_qd],
                          outputs=[self._running_out(first + grid[1])], device=model.device)
            else:
                flat_launch(guard_correction_energy_kernel(model.scalar, family.spec(model), self._tiled),
                            dim=grid, block_dim=lanes,
                            inputs=[model.particle_count, family.element_count, model.world_enabled,
                                    family.arrays(model), model.inputs, self._status, first, reduce_stride(grid), sign,
                                    state.particle_q],
                            outputs=[self._running_out(first + grid[1])], device=model.device)

    def _dissipate(self, state: State) -> None:
        """Add the energy the dampers and drag took out over the last step to the blocks' running sums
        (device only; capturable)."""
        model = self.model
        h = float(self.dt)
        drag, families = self._dissipation_kernels()
        position, velocity = state.particle_q, state.particle_qd
        if self._midpoint:  # the power at the step's midpoint state (MIDPOINT_DISSIPATION; after_step wrote it)
            position, velocity = self._step_position, self._step_velocity
        if drag is not None:
            wp.launch(drag, dim=self._drag_grid, block_dim=self._lanes,
                      inputs=[model.particle_count, h, model.world_enabled, model.particle_flags, model.inputs,
                              self._status, velocity],
                      outputs=[self._running_out(self._drag_grid[1])], device=model.device)
        for kernel, family, lanes, grid, offset in families:
            flat_launch(kernel, dim=grid, block_dim=lanes,
                        inputs=[model.particle_count, family.element_count, offset, h, model.world_enabled,
                                family.arrays(model), model.inputs, self._status, position, velocity],
                        outputs=[self._running_out(offset + grid[1])], device=model.device)

    def _dissipation_kernels(self) -> tuple:
        """(the drag kernel or ``None``, [(kernel, family, lanes, grid, offset)] of the damped families whose
        dissipation a pass of its own counts after every substep), rebuilt after a structural change of the model
        (drag switched on or off); the springs' dampers counted in their scattered force pass where they can be
        (``_force_pass_dampers``), drag, the families with a ``split`` hook and the loads from outside in the
        integrator's per-particle force pass where it can (``_power_rule``)."""
        model = self.model
        cached = getattr(self, "_dissipation_cache", None)
        key = (model.revision, self._midpoint, self._dissipating, self._working, self._revision)
        if cached is None or cached[0] != key:
            drag, families = None, []
            midpoint = self._midpoint
            springs = self._force_pass_dampers()
            modes = self._power_modes()
            if dissipation_exact(model) and self._dissipating:
                features = model.force_features(self.control)
                drag = (guard_drag_kernel(model.scalar, self._tiled, features.wind, midpoint)
                        if features.drag and modes is None else None)
                index = {family.name: k for k, family in enumerate(model.families)}
                families = [(guard_dissipation_kernel(model.scalar, family.spec(model), self._tiled, midpoint),
                             family, lanes, grid, offset) for family, lanes, grid, offset in self._dissipation_layout
                            if (springs is None or family is not springs[0])
                            and not self._power_counts(family, modes, index)]
            cached = (key, (drag, families))
            self._dissipation_cache = cached
            self._attach_dampers(springs)
            self._attach_power(modes)
        return cached[1]

    def _power_counts(self, family, modes, index: dict) -> bool:
        """Whether the integrator's force pass counts ``family``'s dampers (``modes``: ``_power_modes``)."""
        if modes is None:
            return False
        return modes[index[family.name]] == POWER_DAMPERS

    def _power_rule(self) -> int:
        """How the integrator's per-particle force pass counts the power for the balance (``POWER_RULE_*`` of
        ``kernels/guards.py``): symplectic Euler's fused step (gathered springs, or none), or its update after the
        force passes stored the dampers' and loads' parts of the force (scattered springs), the energy over each step,
        exactly what the forces changed the kinetic energy by (``POWER_RULE_MEAN``); RK4's evaluation at each step's
        start the power there, a trapezoid the checks close (``POWER_RULE_START``); elsewhere none (passes of their
        own). Not under the particle force clamp (its share of a force is not separable; the balance is off)."""
        integrator = self.integrator
        name = getattr(integrator, "name", None)
        model = self.model
        if (self.dt is None or integrator is None or getattr(integrator, "adaptive", False)
                or getattr(integrator, "unconditionally_stable", False) or self._limits_host.energy_balance <= 0.0
                or model.stabilizers.enabled("max_particle_force") or model.particle_count == 0):
            return POWER_RULE_NONE
        if name == "symplectic_euler":
            if model.spring_gather or model.spring_count == 0:
                return POWER_RULE_MEAN
            # Scattered springs (their dampers counted in their pass, ``DamperSums``): the update counts the rest
            # where there is any (drag, the working families, other damped families with a ``split`` hook).
            features = model.force_features(self.control)
            others = any(family.does_work or (family.name != "springs"
                                              and getattr(family.spec(model).funcs(model.scalar), "split", None))
                         for family in model.families)
            return POWER_RULE_MEAN if features.drag or others else POWER_RULE_NONE
        if name == "rk4":
            return POWER_RULE_START
        return POWER_RULE_NONE

    def _power_modes(self, gathered: bool = False):
        """Each family's ``POWER_*`` mode in the integrator's force pass (``None``: the power not counted there,
        ``_power_rule``): the working families' force as work from outside (where the balance counts it), the
        dampers of a family with a ``split`` hook where D is counted (the springs where gathered, or ``gathered``: the
        check's own evaluation, whose springs are gathered), the rest not. Drag's and the wind's push are always
        counted (the balance uses D only where ``counts_dissipation``)."""
        if self._power_rule() == POWER_RULE_NONE:
            return None
        model = self.model
        counted = bool(self._dissipating) and dissipation_exact(model)
        modes = []
        for family in model.families:
            if family.does_work:
                modes.append(POWER_WORK if self._working else POWER_NONE)
            elif (counted and getattr(family.spec(model).funcs(model.scalar), "split", None) is not None
                  and getattr(family.spec(model).funcs(model.scalar), "dissipation", None) is not None
                  and (family.name != "springs" or model.spring_gather or gathered)):
                modes.append(POWER_DAMPERS)
            else:
                modes.append(POWER_NONE)
        return tuple(modes)

    def _attach_power(self, modes) -> None:
        """Hand the integrator the power sums (``PowerSums``) where its force pass counts them (``modes``), or take
        them back."""
        integrator = self.integrator
        if modes is None:
            if self._power is not None and getattr(integrator, "power", None) is self._power:
                integrator.power = None
                integrator.power_blocks = None
            self._power = None
            return
        model = self.model
        size = model.world_count * model.particle_count
        work = counts_work(model.force_features(self.control), modes)
        if self._power is None or self._power.sums.shape[0] != size or self._power.work != work:
            sums = power_sums_funcs(model.scalar, work).type
            self._power = PowerSums(modes=modes, h=float(self.dt), sums=wp.zeros(size, dtype=sums, device=model.device),
                                    work=work)
        power = self._power
        power.modes = modes
        # Symplectic Euler with scattered springs: the force passes store the parts its update counts.
        stored = self._power_rule() == POWER_RULE_MEAN and model.spring_count > 0 and not model.spring_gather
        if stored and (power.forces is None or power.forces[0].shape[0] != size):
            power.forces = (wp.zeros(size, dtype=model.vec3, device=model.device),
                            wp.zeros(size, dtype=model.vec3, device=model.device))
        elif not stored:
            power.forces = None
        integrator.power = power
        # Symplectic Euler's fused step (gathered springs, or none): its power summed per block into the running sums.
        fused = (getattr(integrator, "name", None) == "symplectic_euler" and (model.spring_gather or model.spring_count == 0)
                 and self._step_grid is not None)
        integrator.power_blocks = ((self._running_out(self._step_grid[1]), self._step_grid, RUNNING_STEP_DISSIPATION,
                                    RUNNING_WORK) if fused else None)

    def _force_pass_dampers(self):
        """The springs' (family, lanes, grid, offset) where their scattered force pass counts their dampers'
        dissipation (``DamperSums``: an integrator of ``DAMPERS_IN_FORCE_PASS``, scattered springs of Hooke's law or
        its biphasic and asymmetric kinds), else ``None``."""
        model = self.model
        law = model.spring_law
        if not (self._dissipating and dissipation_exact(model) and model.spring_count > 0 and not model.spring_gather
                and getattr(self.integrator, "name", None) in DAMPERS_IN_FORCE_PASS
                and not law.clamp_force and not law.plastic):
            return None
        return next((entry for entry in self._dissipation_layout if entry[0].name == "springs"), None)

    def _attach_dampers(self, springs=None) -> None:
        """Hand the integrator the springs' dissipation sums (``Integrator.dampers``) where ``springs`` (the family's
        layout entry) count in the force pass, or take them back."""
        model = self.model
        integrator = self.integrator
        if springs is None:
            if self._dampers is not None and getattr(integrator, "dampers", None) is self._dampers:
                integrator.dampers = None
            self._dampers = None
            return
        if self._dampers is None or self._dampers.damper.shape[0] != model.world_count * model.spring_count:
            size, device = model.world_count * model.spring_count, model.device
            rule = DAMPER_MEAN_RATE if self._midpoint else DAMPER_TRAPEZOID
            self._dampers = DamperSums(rule=rule, h=float(self.dt), skip=wp.ones(model.world_count, dtype=wp.int32,
                                                                                   device=device),
                                       damper=wp.zeros(size, dtype=model.scalar, device=device),
                                       dissipated=wp.zeros(size, dtype=wp.float64, device=device))
        self._dampers.rule = DAMPER_MEAN_RATE if self._midpoint else DAMPER_TRAPEZOID
        self._dampers_entry = springs
        integrator.dampers = self._dampers

    def _close_dampers(self, state: State, h: float) -> None:
        """Count the springs' last step up to ``state`` (h [s]; 0: only record it) and add their sums to the running
        dissipation (``guard_damper_kernel``)."""
        model = self.model
        family, lanes, grid, offset = self._dampers_entry
        dampers = self._dampers
        flat_launch(guard_damper_kernel(model.scalar, model.spring_law, self._tiled, dampers.rule), dim=grid,
                    block_dim=lanes,
                    inputs=[model.particle_count, offset, h, model.spring_arrays(), state.particle_q,
                            state.particle_qd],
                    outputs=[dampers.damper, dampers.dissipated, dampers.skip, self._running_out(offset + grid[1])], device=model.device)

    def reset(self, every_world: bool = False) -> None:
        """Clear the record (device copies: between frames after a reported failure, :meth:`refresh`, and at a
        restart), and the mirror's rows of the worlds the last read reported (their records stand on the device
        until the copies run: no check writes them before), or with ``every_world`` all of them (a restart, once the
        device is done with the frames before)."""
        if every_world:
            if self.model.device.is_cuda:
                wp.synchronize_stream(self.model.device)
            self._mirror_view[:] = 0.0
        else:
            self._mirror_view[self._mirror_reported] = 0.0
        self._mirror_reported = []
        wp.copy(self._status, self._status_clear)
        wp.copy(self._values, self._values_clear)

    def _work_arrays(self, working: list, specs: tuple):
        """The struct of the working families' arrays for their ``specs`` (``guard_kernels``'s and
        ``guard_work_kernel``'s ``work_arrays``), rebuilt after a structural change of the model."""
        model = self.model
        cache = getattr(self, "_work_cache", None)
        if cache is None or cache[0] != model.revision:
            cache = (model.revision, {})
            self._work_cache = cache
        if specs not in cache[1]:
            chain = elements(model.scalar, specs).arrays()
            cache[1][specs] = fill_elements(chain, [family.arrays(model) for family in working])
        return cache[1][specs]

    def _measure(self, state: State) -> tuple:
        """The per-particle pass of a check (kinetic energy, strain, the loads' work since the last check,
        which becomes this one); returns the check's other kernels."""
        model = self.model
        arguments, inputs, outputs = self._particle_pass(state)
        measure, gather, drive = guard_kernels(*arguments)
        # The drives' work first: it reads the last check's positions, which ``measure`` moves on.
        flat_launch(drive, dim=self._check_grid, block_dim=self._lanes,
                    inputs=[model.particle_count, model.particle_flags, model.elements, model.inputs, state.particle_q,
                            state.particle_qd, self._previous_q, reduce_stride(self._check_grid)],
                    outputs=[self._previous_load, self._partials], device=model.device)
        flat_launch(measure, dim=self._check_grid, block_dim=self._lanes, inputs=inputs, outputs=outputs,
                    device=model.device)
        return gather

    def _particle_pass(self, state: State) -> tuple:
        """(:func:`guard_kernels`' arguments, ``measure``'s inputs, its outputs) for a check of ``state``:
        ``guard_check_kernel`` takes the same first."""
        model = self.model
        force = self.control.particle_force if self.control is not None else None
        # The force on kinematic particles (a drive's work) is gathered even where the integrator scatters it.
        specs = tuple(dataclasses.replace(s, gathered=True) if getattr(s, "gathered", True) is False else s
                      for s in model.family_specs())
        # Wind's and handles' work: here by the trapezoid of the checks, or per substep (``_family_work``, or the
        # integrator's force pass: ``PowerSums``).
        working = [] if self._working else self._working_families()
        working_specs = tuple(family.spec(model) for family in working)
        rule, features, modes = self._power_arguments(specs, force)
        arguments = (model.scalar, specs, self._tiled, force is not None, working_specs, rule, features, modes,
                     self.counts_dissipation)
        inputs = [model.particle_count, model.world_enabled, model.particle_flags, model.particle_mass, model.elements,
                  self._work_arrays(working, working_specs), model.inputs,
                  force if force is not None else state.particle_q, state.particle_q, state.particle_qd, self._lead(),
                  reduce_stride(self._check_grid)]
        outputs = [None if self._power is None else self._power.sums, self._previous_q, self._previous_qd,
                   self._previous_load, self._status, self._partials]
        return arguments, inputs, outputs

    def _power_arguments(self, specs: tuple, force) -> tuple:
        """What the check's kernels take of the power the integrator's force pass counts (``guard_kernels``'
        ``power``, ``power_features``, ``power_modes``), for the family ``specs`` they evaluate and the control's
        ``force`` (or ``None``)."""
        if self._power is None:
            return POWER_RULE_NONE, None, ()
        features = self.model.force_features(self.control)._replace(families=specs, clamp_particle_force=False,
                                                                    external=force is not None)
        return self._power_rule(), features, self._power.modes

    def _dampers_counted(self) -> dict:
        """Each family's name → whether the integrator's force pass counts its dampers (mode ``POWER_DAMPERS``):
        their power at the check's state is then summed in the energy pass (the closing term)."""
        power = self._power
        return {} if power is None else {family.name: mode == POWER_DAMPERS
                                         for family, mode in zip(self.model.families, power.modes)}

    def _lead(self) -> float:
        """λ [s] of the steady loads' work on free particles (weight, the control's force: constant within a frame),
        Σ F·(Δx + λ Δv) over a check's span, exact for a constant force: h/2 for explicit Euler,
        whose positions move with each step's first velocity while its kinetic energy takes the mean, so that
        Σ F·Δx lags the energy a constant force puts in by F·h Δv/2 (a 45 kg block pushed from rest by 75 N
        held 0.0062 J "created" at frame 2, 33 % of the work, and was stopped at h = 10 ms, 1/10 of its
        stability limit); 0 for every other integrator (the means of their steps' velocities move them)."""
        if self.dt is None or getattr(self.integrator, "name", None) != "explicit_euler":
            return 0.0
        return 0.5 * float(self.dt)

    def check(self, state: State, substep: int, *, last: bool = False) -> None:
        """Launch the checks of ``state`` after ``substep`` (device only; capturable): the per-particle and per-element
        passes, then ``gather``, whose verdict also finds the most strained element of a world that fails here, so
        that a check's record is complete when it ends (``last``: the frame's last check, no different)."""
        walked = self._fused_walk()
        gather = self._measure(state) if walked is False else self._check_particles(state, walked)
        if self._dampers is not None and self._dissipating:
            self._close_dampers(state, float(self.dt))
        self._energy_passes(state, skip=walked)
        self._gather(gather, state, substep)

    def _fused_walk(self):
        """Whether a check's particle passes run as one launch (``guard_check_kernel``, where ``CHECK_FUSED`` says so
        for the device): ``False`` where not, else the energy layout's entry of the family that launch walks (the
        first walked by particles, ``_walks``) or ``None``."""
        if not CHECK_FUSED[self.model.device.is_cuda]:
            return False
        return next((entry for entry in self._energy_layout if self._walks(entry[0])), None)

    def _check_particles(self, state: State, walked) -> tuple:
        """The check's passes over the particles in one launch (the drives' work, ``measure``, the ``walked`` family's
        energy: ``guard_check_kernel``); returns the check's gather kernel."""
        model = self.model
        arguments, inputs, outputs = self._particle_pass(state)
        _, gather, _ = guard_kernels(*arguments)
        family, offset = (None, 0) if walked is None else (walked[0], walked[3])
        bounds = launch_bounds(self._lanes, ENERGY_WALK_MIN_BLOCKS) if self._tiled else None
        kernel = guard_check_kernel(*arguments, None if family is None else family.spec(model),
                                    family is not None and self._dampers_counted().get(family.name, False), bounds)
        walk_arrays = family.arrays(model) if family is not None else elements(model.scalar, ()).arrays()
        flat_launch(kernel, dim=self._check_grid, block_dim=self._lanes, inputs=[*inputs, walk_arrays, offset],
                    outputs=[*outputs, self._energy_partials, self._strain_partials, self._power_partials],
                    device=model.device)
        return gather

    def _energy_passes(self, state: State, skip=None) -> None:
        """The families' per-block elastic energy, strain and (where the force pass counts their dampers) the power
        their dampers take out at ``state``; but the energy layout's entry ``skip`` (walked by the check's particle
        launch)."""
        model = self.model
        counted = self._dampers_counted()
        for entry in self._energy_layout:
            if entry is skip:
                continue
            family, lanes, grid, offset = entry
            spec, power = family.spec(model), counted.get(family.name, False)
            walk = self._walks(family)
            bounds = launch_bounds(lanes, ENERGY_WALK_MIN_BLOCKS) if walk and self._tiled else None
            kernel = guard_energy_kernel(model.scalar, spec, self._tiled, power, walk, bounds)
            flat_launch(kernel, dim=grid, block_dim=lanes,
                        inputs=[model.particle_count, family.element_count, offset, model.world_enabled,
                                family.arrays(model), model.inputs, self._status, state.particle_q, state.particle_qd,
                                reduce_stride(grid)],
                        outputs=[self._energy_partials, self._strain_partials, self._power_partials],
                        device=model.device)

    def _walks(self, family) -> bool:
        """Whether the check's energy pass walks ``family`` by particles (``guard_energy_kernel``'s ``walk``: its
        gathered ``particle_energy`` hook, where ``ENERGY_BY_PARTICLES`` said so for the device when the guard was
        made, which laid its partial sums out for it) rather than by elements."""
        return family.name in self._walked

    def _gather(self, gather, state: State, substep: int, carry_only: bool = False) -> None:
        """Each world's sums and verdict (``carry_only``: a restart's closing term alone)."""
        model = self.model
        partials = (self._partials, self._energy_partials, self._strain_partials, self._power_partials)
        running = self._running_written()
        fold = self._folding()
        if fold is not None:
            grid, *folded = fold
            wp.launch(guard_fold_kernel(), dim=grid, inputs=list(partials), outputs=[running, *folded],
                      device=model.device)
            partials, running = tuple(folded[:4]), folded[4]
        flat_launch(gather, dim=(model.world_count, self._lanes), block_dim=self._lanes,
                    inputs=[model.particle_count, model.elements, state.particle_q, state.time, *partials, substep,
                            self._limits, 0.0 if self.dt is None else float(self.dt), int(carry_only)],
                    outputs=[model.world_enabled, self._status, running, self._values, self._work_total,
                             self._balance, self._carry, self._mirror], device=model.device)

    def reports(self) -> list[GuardReport]:
        """Each world's first failure since the last reset, in world order (reads the device: synchronises). The
        record is cleared before the next frame (:meth:`refresh`; a held world is not checked again, so it is
        reported once)."""
        if self._status_view is not None:
            wp.copy(self._status_host, self._status)
            wp.synchronize_stream(self.model.device)
            return self._parse(self._status_view)
        return self._parse(self._status.numpy())

    def post(self, until: float | None = None) -> None:
        """Start reading the record as the frame just launched leaves it, without waiting for the device: on CUDA an
        event after the frame (:meth:`collect` waits for it, typically once the next frame is queued behind it, so
        that the device never idles for the host). ``until``: the frame's end [s] from the restart (the failures
        latched by later checks are left for a later read); ``None``: any."""
        k = self._posted % len(self._events)
        self._posted += 1
        if len(self._pending) == len(self._events):
            raise RuntimeError("Guard.post: collect the older frames' records first")
        if self._events[k] is not None:
            wp.get_stream(self.model.device).record_event(self._events[k])
        self._pending.append((k, until))

    def collect(self) -> list[GuardReport]:
        """The failures latched up to the end of the oldest frame :meth:`post` started reading, from the mirror
        (waits for that frame alone; those already reported are in it again while their record stands: the caller
        skips them)."""
        k, until = self._pending.pop(0)
        if self._events[k] is not None:
            wp.synchronize_event(self._events[k])
        # The reasons first, then the rows: a failure latched since (the next frame runs on) may land between the two
        # reads; its reason, written last, keeps it out of this one unless the first read saw it.
        latched = self._mirror_view[:, GUARD_TRIPPED] != 0.0
        if not latched.any():  # the common case, every frame: host memory read, nothing queued on the device
            return []
        rows = self._mirror_view.copy()
        if until is not None and self.dt is not None:  # (a check's clock is the frame's end or a substep's before it)
            latched &= rows[:, MIRROR_CLOCK] - self._clock_base <= until + 0.5 * float(self.dt)
        status = np.tile(self._clear_row, (len(rows), 1))
        status[latched] = rows[latched, :GUARD_INTS].astype(np.int64)
        return self._parse(status)

    def discard(self) -> None:
        """Forget the records posted and not collected (a restart)."""
        self._pending.clear()

    @property
    def pending(self) -> int:
        """Frames whose record :meth:`post` started reading and :meth:`collect` has not returned."""
        return len(self._pending)

    def _parse(self, status: np.ndarray) -> list[GuardReport]:
        """The failures a host copy of the status record holds (reads the values on a failure: synchronises)."""
        reasons = {GUARD_NONFINITE: "non-finite state", GUARD_STRAIN: "strain", GUARD_ENERGY: "kinetic energy",
                   GUARD_BALANCE: "energy balance"}
        families = self.model.families
        found = []
        tripped = status[:, GUARD_TRIPPED]
        if not tripped.any():  # the common case, every frame: one read, nothing allocated that could linger
            return []
        values = self._values.numpy()
        for world in np.flatnonzero(tripped):
            row = status[world]
            reason = reasons[int(row[GUARD_TRIPPED])]
            particle = row[GUARD_NONFINITE_PARTICLE] if reason == "non-finite state" else row[GUARD_STRAIN_PARTICLE]
            index = row[GUARD_STRAIN_FAMILY]
            family = None if index == NO_PARTICLE or reason != "strain" else families[index].name
            element = None if family is None else int(row[GUARD_STRAIN_ELEMENT])
            found.append(GuardReport(
                world=int(world),
                reason=reason,
                substep=int(row[GUARD_SUBSTEP]),
                particle=None if particle == NO_PARTICLE else int(particle),
                spring=element if family == "springs" else None,
                strain=float(values[world, GUARD_MAX_STRAIN]),
                kinetic_energy=float(values[world, GUARD_KINETIC_ENERGY]),
                nonfinite_count=int(row[GUARD_NONFINITE_COUNT]),
                family=family,
                element=element,
                energy_created=float(values[world, GUARD_EXCESS]),
                energy_budget=float(values[world, GUARD_BUDGET]),
            ))
        self._reported = True  # cleared before the next frame (``refresh``)
        self._mirror_reported.extend(report.world for report in found)  # (their mirror rows cleared with the record)
        return found

    def explain(self, report: GuardReport) -> str:
        """``report`` described (:meth:`GuardReport.describe`), with the scene's suspects and a remedy to try after an
        instability (:func:`stop_advice`)."""
        advice = stop_advice(report, self.model, integrator=getattr(self.integrator, "name", None),
                             substeps=self.substeps, dt=float(self.dt) if self.dt is not None else 0.0,
                             control=self.control)
        return report.describe(self.model) + (f"; {advice}" if advice else "")

    def report(self) -> GuardReport | None:
        """The earliest failure since the last reset (the lowest world among equals), or ``None`` (reads the
        device: synchronises)."""
        found = self.reports()
        return min(found, key=lambda r: (r.substep, r.world)) if found else None


#: Pinned host buffers for the guards' status reads and mirrors, by shape and type: taken by a guard, handed back when
#: it is collected, never freed (see ``Guard.__init__``).
_PINNED: dict[tuple, list] = {}


#: CUDA events for the deferred reads of the guards' status (``Guard.post``), by device: taken by a guard, handed back
#: when it is collected, never destroyed (as ``_PINNED``).
_EVENTS: dict[str, list] = {}


def _hand_back(alias: str, mirror: wp.array, events: list, pending: list) -> None:
    """Return a collected guard's mirror and its events to the pools (``Guard.post``), unless a frame it posted was
    never collected: that frame may still write its mirror, and another guard that took the buffer could read a
    failure of this one's; those few bytes are left to the process."""
    if pending:
        return
    _pin_back(mirror)
    _EVENTS[alias].extend(events)


def _pooled_event(device) -> wp.Event:
    """An event of ``device`` from the pool (a new one where none is free)."""
    free = _EVENTS.setdefault(device.alias, [])
    return free.pop() if free else wp.Event(device)


def _pinned(shape: tuple, dtype) -> wp.array:
    """A pinned host array of ``shape`` and ``dtype`` from the pool (a new one where none is free)."""
    free = _PINNED.setdefault((tuple(shape), dtype), [])
    return free.pop() if free else wp.empty(shape, dtype=dtype, device="cpu", pinned=True)


def _pin_back(array: wp.array) -> None:
    """Hand a buffer of :func:`_pinned` back to its pool."""
    _PINNED[(tuple(array.shape), array.dtype)].append(array)


@dataclass(frozen=True)
class _StepPoint:
    """A substep's midpoint as the input tracks read a state: positions [m], velocities [m/s], each world's time [s]."""

    particle_q: wp.array
    particle_qd: wp.array
    time: wp.array


def _direct(spec):
    """``spec`` computing its forces where they are asked for: wind's precomputed per-triangle forces belong to the
    integrator's last force evaluation, not to the state the guard evaluates."""
    return dataclasses.replace(spec, precomputed=False) if getattr(spec, "precomputed", False) else spec


def dissipation_exact(model: Model) -> bool:
    """Whether the energy balance can count the dampers' dissipation for ``model`` as it is now: no stage moves
    particles outside the forces (colliders and the ground, self-collision, strain limiting), whose energy
    change the balance cannot tell from an instability's once the dissipated energy is no longer slack (Provot
    strain limiting on a soft cloth: 11 % of the budget within 0.5 s, tests/test_stabilizers.py). Elsewhere D
    is left out and the balance stays one-sided."""
    return (model.shape_count == 0 and getattr(model, "self_contact", None) is None
            and not model.stabilizers.enabled("max_strain"))


def energy_scales(model: Model) -> np.ndarray:
    """Each world's energy scale [J], float64, shape [world_count]: initial kinetic + elastic energy (every
    family's) + total weight × (extent + 1 m), ≥ 1 µJ; the weight with the largest gravity the world has
    (now, or at any key of its gravity track)."""
    worlds, n = model.world_count, model.particle_count
    q = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
    qd = model.particle_qd.numpy().astype(np.float64).reshape(worlds, n, 3)
    mass = model.world_values("particle_mass")
    kinetic = 0.5 * np.sum(mass * np.sum(qd * qd, axis=2), axis=1)
    elastic = world_elastic_energy(model)
    extent = np.ptp(q, axis=1).max(axis=1) if n else np.zeros(worlds)
    gravity = np.linalg.norm(model.world_values("gravity"), axis=1)
    for w in range(worlds):
        track = model.track("gravity", world=w)
        if track is not None:
            gravity[w] = max(gravity[w], float(np.linalg.norm(track.values, axis=1).max()))
    weight = mass.sum(axis=1) * gravity
    return np.maximum(kinetic + elastic + weight * (extent + 1.0), 1.0e-6)
