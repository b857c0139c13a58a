"""Symplectic (semi-implicit) Euler: v' = v + h M⁻¹ f(x, v); x' = x + h v'. First order, symplectic for
conservative forces. With gathered springs a step is one fused kernel (forces, update and contacts in one pass):
on CUDA one thread per particle; on the CPU one thread per world sweeping its particles in order, each spring
evaluated once (``kernels/sweep.py``). With scattered springs it is force evaluation then the update."""

from __future__ import annotations

import functools

import warp as wp

from ...kernels.frames import FRAME_MAX_LANES, symplectic_euler_frame_kernel
from ...kernels.guards import frame_check_arrays_type
from ...kernels.integrators import (symplectic_euler_blocks_kernel, symplectic_euler_kernel,
                                     symplectic_euler_update_kernel)
from ...kernels.shapes import NO_CONTACTS
from ...kernels.sweep import sweeps, symplectic_euler_sweep_kernel
from ...kernels.kinematics import PinGroups
from ...kernels.tracks import WorldInputs
from ..contacts import update_shape_frames
from ..forces import eval_forces, force_inputs
from ..kinematics import NO_PIN_TARGETS, apply_kinematics
from ..state import State
from ..control import Control
from ..tracks import evaluate_input_tracks
from .base import Integrator, step_arguments
from ...kernels.flatten import flat_launch, launch_bounds


class SymplecticEuler(Integrator):
    """Symplectic Euler with explicit spring damping. Stable for undamped springs while ω_max·h < 2.

    Args:
        model: the model.
        one_launch: run a frame's substeps in one launch (``kernels/frames.py``; the same bits on the CPU, within
            float32 rounding on a GPU). ``None`` (default): where it pays, on a GPU: a world spread over blocks of
            :attr:`SPREAD_LANES` threads (one particle each) where every world's blocks fit one per multiprocessor
            (one world up to 128² on an H200: 1.36-1.51× at 32²-128²), else one block per world where the worlds
            give at least :attr:`ONE_LAUNCH_THREADS_PER_SM` threads per multiprocessor (1.02-1.18×) and the step
            evaluates no more than springs, gravity and fixed colliders (:meth:`launch_shape`). ``True``:
            wherever the scene allows it (on the CPU too, one thread per world). ``False``: never. The scene allows it
            with gathered springs, analytic colliders whose contacts are fused into the update (moving ones with
            ``contact_stage=False``), no stabiliser, contact stage, triangle contacts or self-collision, no family
            with time-dependent arrays (a precomputed wind's or tets', an animated handle's:
            ``ElementFamily.time_dependent``), no held worlds, and step hooks that work at the frame's end alone (the
            default guard does); animated inputs and driven pins are evaluated inside. On the CPU it runs the per-particle step (``cpu_sweep`` does not apply).
        cpu_sweep: on the CPU, with gathered springs, step each world in one thread sweeping its particles in
            order, each spring evaluated once (``kernels/sweep.py``; 1.7-1.8x the per-particle step at 32²-64²,
            bench/results/performance_cpu.md §0); False: one thread per particle, as on CUDA. Both give the same
            forces, summed in another order (float rounding). No effect on CUDA or with scattered springs.
    """

    name = "symplectic_euler"
    order = 1
    #: Threads (worlds × lanes) per streaming multiprocessor from which a frame in one launch, one block per world,
    #: is faster than one launch per substep (H200, bench/results/frames.md, 16² to 64² cloth): 128 per SM gave
    #: 0.81-0.94×, 256 gave 1.02-1.10×, 512-2048 gave 1.03-1.18× (the default guard's rows at the low end).
    ONE_LAUNCH_THREADS_PER_SM = 256
    #: Particles each lane of a one-block-per-world frame takes per substep (the fastest of 2-8 at 16²-64², H200).
    ONE_LAUNCH_PARTICLES_PER_LANE = 8
    #: Threads per block where a world spreads over several blocks (one particle each; 32²-128², H200).
    SPREAD_LANES = 128
    #: Particles per world from which a world is spread over blocks by default (the smallest size measured faster).
    SPREAD_MIN_PARTICLES = 1024
    #: Blocks of the frame kernel (up to 256 threads each) a multiprocessor must hold at once (``kernels.frames``'
    #: ``bounds``: at most 128 registers a thread; ``None``: the compiler's choice, 202 with the guard's power
    #: sums, 12.5 % occupancy). Measured on an H200 (bench/results/guard_cost.md), µs per frame, the compiler's
    #: choice → 2 → 3: guard off 62.8 → 51.1 → 56.9 at 32², 63.4 → 55.0 → 62.3 at 64², 2607 → 2577 → 2599 for
    #: 4,096 worlds of 32²; the default guard 110.1 → 98.6 → 118.1, 100.4 → 100.3 → 107.7, 4364 → 3717 → 3904.
    FRAME_MIN_BLOCKS = 2
    #: Blocks of ``model.block_dim`` threads of the per-substep fused step a multiprocessor must hold at once (a bound
    #: on its registers, ``kernels.integrators.symplectic_euler_kernel``'s ``bounds``); ``None``: the compiler's choice.
    STEP_MIN_BLOCKS = None
    #: Particles (all worlds) from which the per-substep fused step adds the guard's power sums a warp at a time on CUDA
    #: (``kernels.integrators.symplectic_euler_kernel``'s ``warp_totals``): one entry's read and write a warp instead
    #: of one a particle, for a few instructions more in every thread. On an H200 (Warp 1.16.0, hanging cloth, default
    #: guard ÷ guard off, bench/results/guard_cost.md) 1024² gained (0.754-0.761 → 0.797-0.798), where the step's
    #: memory traffic bounds it, and 256² lost (0.725-0.734 → 0.693-0.696), where one wave of threads' latency does;
    #: between the two it is unmeasured.
    POWER_WARP_TOTALS_FROM = 1 << 19
    #: Whether the guard's check that a frame in one launch takes over (``advance_frame``'s ``check``) runs in a launch
    #: of its own right after the frame kernel, by device (CUDA, CPU), rather than at the frame kernel's end: the same
    #: functions and sums either way (``kernels.frames``' ``frame_steps``), but inside one kernel the check's code
    #: made the compiler's loop slower. On an H200 (Warp 1.16.0, 64², bench/results/guard_cost.md), µs a substep +
    #: µs a frame, the verdict not read: check at the end 3.64 + 21.5, guarded frame without it 2.67 (guard off 2.86).
    CHECK_LAUNCH_APART = {True: True, False: False}
    #: Blocks of the check's own launch (``CHECK_LAUNCH_APART``) a multiprocessor must hold at once, as
    #: ``FRAME_MIN_BLOCKS`` for the frame's (``None``: the compiler's choice). The check is bound by latency, not by
    #: its spills: on an H200 (4,096 worlds of 32², bench/results/guard_cost.md) it took 570 µs at 2 (128 registers,
    #: 91 MB of spills), 751 µs with no bound (200 registers, none), 715 µs at 1 (255); 3 timed the same as 2.
    CHECK_MIN_BLOCKS = 2

    def __init__(self, model, *, one_launch: bool | None = None, cpu_sweep: bool = True):
        super().__init__(model)
        self.one_launch = one_launch
        self.cpu_sweep = bool(cpu_sweep)
        self._barrier = None  # per world: the block arrivals of a world spread over several blocks

    def frame_shape(self, control: Control | None, steps: int) -> tuple[int, int] | None:
        """(threads per block, blocks per world) of a frame in one launch, or ``None``. Few worlds (a world's
        blocks, one particle per thread, all resident at once: at most one block per multiprocessor) spread each
        world over blocks that meet at a barrier in memory between substeps; many worlds (filling the device) take
        one block each. On the CPU, one thread per world."""
        model = self.model
        if self.one_launch is False or steps < 2 or model.particle_count == 0:
            return None
        if self.one_launch is None and not model.device.is_cuda:
            return None
        if not (model.spring_gather or model.spring_count == 0) or not self.finish_step.only_contacts:
            return None
        if model.holds_worlds:
            return None
        if any(family.time_dependent(model) for family in model.extra_families):
            return None
        if model.device.is_cpu:
            return 1, 1  # a CPU launch runs its threads in turn: one per world, each substep over the whole world
        pins = model.pin_groups
        heavy = bool(model.extra_families or model.input_tracks is not None or model.shape_moving
                     or (pins is not None and pins.driven))
        return self.launch_shape(model.particle_count, model.world_count, model.device.sm_count,
                                 heavy=heavy, forced=bool(self.one_launch))

    def launch_shape(self, particles: int, worlds: int, sms: int, *, heavy: bool = False,
                     forced: bool = False) -> tuple[int, int] | None:
        """(threads per block, blocks per world) of a frame in one launch on a GPU of ``sms`` multiprocessors, for
        ``worlds`` worlds of ``particles`` particles, or ``None`` where one launch per substep is faster (unless
        ``forced``). ``heavy``: the scene evaluates more than springs, gravity and fixed colliders inside (element
        families such as the wind's, animated inputs, driven pins, moving colliders). A world spread over blocks
        where they all fit at once (from :attr:`SPREAD_MIN_PARTICLES`); else one block per world where the worlds give
        :attr:`ONE_LAUNCH_THREADS_PER_SM` threads a multiprocessor, and the scene is not ``heavy``: a flag on a moving
        pole in a gusting wind took 0.86-0.89x (32²), 0.57-0.59x (64²) and 0.40-0.41x (128²) the per-substep path's
        rate at 1,056 and 4,096 worlds so (H200, bench/results/frames.md), where the hanging cloth gained 1.02-1.18x."""
        spread_lanes = min(int(self.SPREAD_LANES), FRAME_MAX_LANES)  # (the frame kernel's launch bound)
        spread = -(-particles // spread_lanes)
        if spread > 1 and worlds * spread <= sms and (forced or particles >= self.SPREAD_MIN_PARTICLES):
            return spread_lanes, spread
        lanes = int(min(FRAME_MAX_LANES, max(32, 32 * -(-particles // (32 * self.ONE_LAUNCH_PARTICLES_PER_LANE)))))
        if not forced and (heavy or worlds * lanes < self.ONE_LAUNCH_THREADS_PER_SM * sms):
            return None  # too few blocks to fill the device, too many to spread, or a heavy step: one launch per substep
        return lanes, 1

    def advance_frame(self, state_a: State, state_b: State, control: Control | None, dt: float, steps: int,
                      shape: tuple[int, int], check=None) -> bool:
        model = self.model
        lanes, blocks = shape
        if lanes > FRAME_MAX_LANES:
            raise ValueError(f"a frame in one launch takes at most {FRAME_MAX_LANES} threads a block "
                             f"(kernels.frames.FRAME_MAX_LANES, its launch bound), got {lanes}")
        if self._barrier is None or len(self._barrier) != model.world_count:
            self._barrier = wp.zeros(model.world_count, dtype=wp.int32, device=model.device)
        if blocks > 1:
            self._barrier.zero_()
        features = model.force_features(control)
        contacts = model.contact_features()
        animated = model.input_tracks
        pins = model.pin_groups if model.pin_groups is not None and model.pin_groups.driven else None
        targets = pins is not None and control is not None and control.pin_targets is not None
        apart = check is not None and self.CHECK_LAUNCH_APART[model.device.is_cuda]
        kernel = functools.partial(symplectic_euler_frame_kernel, model.scalar, features, contacts,
                                   None if self.power is None else self.power.modes, animated is not None,
                                   pins is not None, targets, bool(model.shape_moving))
        bounds = launch_bounds(FRAME_MAX_LANES, self.FRAME_MIN_BLOCKS)
        # The frame's steps, then (``apart``) the check alone: a launch of the checked kernel with no steps of its own.
        launches = (((None, steps, bounds), (check, 0, launch_bounds(FRAME_MAX_LANES, self.CHECK_MIN_BLOCKS)))
                    if apart else ((check, steps, bounds),))
        for launch_check, launch_steps, launch_bound in launches:
            self._launch_frame(kernel(None if launch_check is None else launch_check[0], launch_bound), launch_steps,
                               steps, state_a, state_b, control, dt, shape, launch_check, animated, pins, targets,
                               features)
        if steps % 2:
            wp.copy(state_b.time, state_a.time)  # the clock advanced in A; the result is B
        return check is not None

    def _launch_frame(self, kernel, steps: int, frame_steps: int, state_a: State, state_b: State, control, dt: float,
                      shape: tuple[int, int], check, animated, pins, targets: bool, features) -> None:
        """One launch of a frame kernel (``advance_frame``): ``steps`` of its substeps, ``frame_steps`` the frame's."""
        model = self.model
        lanes, blocks = shape
        flat_launch(
            kernel,
            inputs=[
                model.particle_count,
                lanes,
                blocks,
                model.particle_flags,
                model.particle_inv_mass,
                model.particle_radius,
                model.shape_arrays,
                *force_inputs(model, control, features),
                model.track_table.table,
                _no_world_inputs(str(model.device)) if animated is None else animated.by_world,
                _NO_PINS if pins is None else pins.table,
                model.shape_rest,
                model.shape_translation_track,
                model.shape_rotation_track,
                control.pin_targets if targets else NO_PIN_TARGETS,
                steps,
                frame_steps,
                *step_arguments(model.scalar, dt),
                wp.float64(dt),
            ],
            outputs=[model.inputs, model.shape_arrays, state_a.particle_q, state_a.particle_qd, state_b.particle_q,
                     state_b.particle_qd, state_a.time, None if self.power is None else self.power.sums,
                     _no_check(model.scalar, str(model.device)) if check is None else check[1], self._barrier],
            dim=model.world_count * lanes * blocks, block_dim=lanes, device=model.device,
        )

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        # Contacts fuse into the update unless other post-step passes (or the contact stage) must run first.
        fused = self.finish_step.only_contacts
        contacts = model.contact_features() if fused else NO_CONTACTS
        if fused:
            update_shape_frames(model, state_in.time, dt, ahead=True)
        common = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        if model.spring_gather or model.spring_count == 0:
            evaluate_input_tracks(model, state_in)
            features = model.force_features(control)
            power = None if self.power is None else self.power.modes
            swept = self.cpu_sweep and model.device.is_cpu and sweeps(features)
            blocks = self.power_blocks if power is not None and not swept else None
            # The fused step's inputs, whichever kernel takes them.
            inputs = [
                model.particle_count,
                model.particle_flags,
                model.particle_inv_mass,
                model.particle_radius,
                model.shape_arrays,
                *force_inputs(model, control, features),
                state_in.particle_q,
                state_in.particle_qd,
                state_in.time,
                *step_arguments(model.scalar, dt),
            ]
            if blocks is not None:  # the guard's power summed per block (``symplectic_euler_blocks_kernel``)
                running, grid, taken_slot, worked_slot = blocks
                flat_launch(
                    symplectic_euler_blocks_kernel(model.scalar, features, contacts, power, model.device.is_cuda),
                    inputs=inputs + [taken_slot, worked_slot],
                    outputs=[state_out.particle_q, state_out.particle_qd, state_out.time, running],
                    dim=grid, block_dim=grid[2], device=model.device,
                )
            elif swept:  # one thread per world: the particles in order, each spring once
                kernel = symplectic_euler_sweep_kernel(model.scalar, features, contacts, power)
                # Its scratch: the two states' force arrays (the step's to use; left zero).
                common["dim"], scratch = model.world_count, [state_in.particle_f, state_out.particle_f]
            else:
                warp_totals = (power is not None and model.device.is_cuda
                               and model.world_count * model.particle_count >= self.POWER_WARP_TOTALS_FROM)
                kernel = symplectic_euler_kernel(model.scalar, features, contacts, power,
                                                 launch_bounds(model.block_dim, self.STEP_MIN_BLOCKS), warp_totals)
                scratch = []
            if blocks is None:
                flat_launch(
                    kernel,
                    inputs=inputs,
                    outputs=[state_out.particle_q, state_out.particle_qd, state_out.time,
                             None if self.power is None else self.power.sums, *scratch],
                    **common,
                )
        else:
            power = self.power
            eval_forces(model, state_in, control, dampers=self.dampers, power=power)
            counted = power is not None and power.forces is not None
            flat_launch(
                symplectic_euler_update_kernel(model.scalar, contacts, counted, counted and power.work),
                inputs=[
                    model.particle_count,
                    model.particle_flags,
                    model.particle_inv_mass,
                    model.particle_radius,
                    model.shape_arrays,
                    model.inputs,
                    state_in.particle_q,
                    state_in.particle_qd,
                    state_in.particle_f,
                    state_in.time,
                    *step_arguments(model.scalar, dt),
                    *(power.forces if counted else (None, None)),
                ],
                outputs=[state_out.particle_q, state_out.particle_qd, state_out.time,
                         power.sums if counted else None],
                **common,
            )
        apply_kinematics(model, control, state_in, state_out.particle_q, state_out.particle_qd, dt)
        if not fused:
            self.finish_step(state_out, dt, state_in)
        self.hold_worlds(state_in, state_out)


@functools.cache
def _no_world_inputs(device: str) -> WorldInputs:
    """The frame kernel's animated inputs where none is animated (never read: empty arrays, one world's start)."""
    empty = WorldInputs()
    empty.track = empty.slot = empty.width = empty.order = wp.zeros(0, dtype=wp.int32, device=device)
    empty.start = wp.zeros(2, dtype=wp.int32, device=device)
    return empty


@functools.cache
def _no_check(scalar, device: str):
    """The frame kernel's check arrays where the frame ends without the check (never read: empty arrays)."""
    return frame_check_arrays_type(scalar)()


#: The frame kernel's pin groups where none is driven (never read).
_NO_PINS = PinGroups()
