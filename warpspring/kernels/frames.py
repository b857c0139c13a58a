"""A frame's substeps in one launch: the fused symplectic Euler step looped over the substeps by each world's
threads, which meet at a barrier between substeps.

Between launches a GPU idles: a small scene's substep is a few microseconds of work behind a launch of its own
(~1.2 µs a graph node on an H100, more for the data to come back through L2). Here a world's threads (``lanes``
per block, ``blocks`` blocks) stay resident for the whole frame: thread l of a world updates its particles
l, l + L, ... (L the world's threads) with the same per-particle step as
:func:`~warpspring.kernels.integrators.symplectic_euler_kernel` (forces gathered, velocity then position updated,
contacts resolved), then waits at a barrier, so a substep reads only what the previous one finished writing. The
barrier is the block's own (``__syncthreads``) where a world is one block; where it spreads over several, each
block's first thread counts its block in with an integer atomic on the world's counter and waits for all of
them, reading the counter past its cache (the blocks must all be resident: the caller launches at most one per
multiprocessor). The state alternates between the two buffers as the per-substep path's does (substep k reads
buffer k mod 2): the same operations in the same order.

On the CPU a launch runs its threads one after another, so the kernel is launched with one thread per world:
each substep then runs over the whole world before the next begins, and the barriers are empty.

The guard's power sums are kept by each lane in registers over the frame (float64) and added to one entry of the
power sums per lane at its end (the per-substep fused step adds to every particle's entry every substep, the CPU's
sweep to the world's first entry every substep); the check sums a world's entries, so the guard counts the same
energy up to the order of its additions.
"""

import functools

import warp as wp

from .families import FORCE_KERNEL_OPTIONS, elements
from .forces import ForceFeatures, counts_work, power_sums_funcs
from .integrators import symplectic_euler_particle_energy_func, symplectic_euler_particle_func
from .guards import (GUARD_TRIPPED, POWER_RULE_NONE, FrameCheck, energy_lanes_func, frame_check_arrays_type,
                     guard_lane_funcs)
from .linalg import block_barrier, reduction_funcs
from .precision import vec3_type
from .shapes import ContactFeatures, shapes_type
from .kinematics import PinGroups, PinTargets, is_kinematic, prescribed_func
from .swept import shape_motion_func
from .tracks import Tracks, WorldInputs, world_inputs_func
from .flatten import flat_kernel, launch_bounds_option

wp.set_module_options({"enable_backward": False})


@wp.func_native("""
#if defined(__CUDA_ARCH__)
__threadfence();
#endif
""")
def memory_fence():
    """This thread's writes to memory are seen by every thread of the device before its later ones
    (``__threadfence``; nothing on the CPU)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
volatile int* count = &barrier[world];
while (*count < target) { }
__threadfence();
#endif
""")
def wait_for_arrivals(barrier: wp.array[wp.int32], world: int, target: int):
    """Spin until ``barrier[world]`` reaches ``target`` (read past the multiprocessor's cache), then order this
    thread's later reads after it; nothing on the CPU."""
    ...


#: The leaves of the frame kernel's animated-input, pin and check parameters (moved last where unread).
ANIMATED_LEAVES = tuple(f"animated_inputs__{name}" for name in WorldInputs.vars)
TRACK_LEAVES = tuple(f"tracks__{name}" for name in Tracks.vars)
PIN_LEAVES = tuple(f"groups__{name}" for name in PinGroups.vars)
TARGET_LEAVES = tuple(f"pin_targets__{name}" for name in PinTargets.vars)
CHECK_LEAVES = tuple(f"check_arrays_in_out__{name}" for name in frame_check_arrays_type(wp.float32).vars)


#: The most threads a block of the frame kernel may have (its launch bound; ``SymplecticEuler.launch_shape`` picks
#: 32-256 and clamps its spread blocks to it, ``advance_frame`` refuses more).
FRAME_MAX_LANES = 256


@functools.cache
def symplectic_euler_frame_kernel(scalar: type, features: ForceFeatures, contacts: ContactFeatures,
                                  power: tuple | None = None, animated: bool = False, driven: bool = False,
                                  targets: bool = False, moving: bool = False, check: FrameCheck | None = None,
                                  bounds: tuple[int, int] | None = None):
    """``steps`` fused symplectic Euler steps of every world, ``blocks`` blocks of ``lanes`` threads per world
    (module docstring); ``barrier_in_out`` one counter per world, zero at the launch where ``blocks`` > 1.
    Substep k reads buffer A when k is even and writes B, and the other way round when k is odd; an odd
    ``steps`` leaves the result in B. Each world's clock (``time_in_out``) advances by
    ``steps`` · (dt + dt_rest), added one step at a time as the per-substep path adds it: each lane keeps it in a
    register from the launch's start and the world's first lane writes it at the end. With ``animated``, each
    substep first writes the world's animated inputs at its time into ``inputs_out`` (the very table ``inputs``
    is: every block of the world its own copy of the same values, ``tracks.world_inputs_func``), as the per-substep
    path's ``evaluate_input_tracks`` does before each step, and its lanes meet before stepping. With ``driven``,
    the lane that steps a kinematic particle of a pin group then puts it on its prescribed motion at the substep's
    end (``kinematics.prescribed_func``: ``step_f64`` [s] the step in float64, as ``apply_kinematics`` and
    ``update_shape_frames`` take it; ``targets``: groups driven through Control read ``pin_targets``). With ``moving``, each substep first writes
    the world's colliders' frames at its start and end into ``shapes_out`` (the very struct ``shapes`` is, each
    block its own copy, ``swept.shape_motion_func``), as the per-substep path's ``update_shape_frames`` does. With
    ``check``, the frame ends with the guard's check of its last state (``check_arrays_in_out``, the guard's arrays:
    ``guards.frame_check_arrays_type``): each lane adds its power sums to its entry and runs the check's drive and
    measure passes over its particles and the energy pass over its elements (``guards.guard_lane_funcs``,
    ``guards.energy_lanes_func``: the functions of the check's own kernels), each block writes its partial sums, the
    world's blocks meet, and the world's first block gathers them and decides (``gather_lanes``): the check's four
    launches, inside the frame. ``frame_steps`` is the frame's substeps the check reports and follows: ``steps``
    where the frame ends with it; 0 ``steps`` and the frame's own in a launch of the check alone after a frame
    compiled without it (the world's blocks then meet where the frame's barrier count left off), so that the loop is
    compiled apart from the check's code (``SymplecticEuler.CHECK_LAUNCH_APART``). ``bounds`` (threads a block, at
    most ``FRAME_MAX_LANES``, and blocks a multiprocessor): ``flatten.launch_bounds_option``."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    counted = power is not None
    sums = power_sums_funcs(scalar, counted and counts_work(features, power))
    Sums = sums.type
    pack = sums.pack
    composed = elements(scalar, features.families)
    Elements = composed.arrays
    step_particle = symplectic_euler_particle_func(scalar, features, contacts, None)
    step_energy = symplectic_euler_particle_energy_func(scalar, features, contacts, power) if counted else None
    write_world_inputs = world_inputs_func(scalar)
    prescribed = prescribed_func(scalar, targets)
    move_shape = shape_motion_func(scalar)
    checked = check is not None
    CheckArrays = frame_check_arrays_type(scalar)
    # (the unchecked frame never calls ``end_check``: a check of nothing is made for it, never compiled)
    spec = (check if checked
            else FrameCheck(False, False, POWER_RULE_NONE, None, (), False, (False,) * len(features.families)))
    measure_lanes, drive_lanes, gather_lanes = guard_lane_funcs(
        scalar, features.families, spec.tiled, spec.external, (), spec.power, spec.power_features, spec.power_modes,
        spec.dissipation)
    energy_lanes = energy_lanes_func(scalar, features.families, spec.powers)
    block_sum, block_max = reduction_funcs(spec.tiled)
    NoWork = elements(scalar, ()).arrays

    @wp.func
    def end_check(world: int, block: int, lane: int, lanes: int, blocks: int, steps: int, particle_count: int,
                  particle_flags: wp.array[wp.int32], particle_mass: wp.array2d[scalar], element_arrays: Elements,
                  inputs: wp.array2d[scalar], particle_force_ext: wp.array[vec3], q: wp.array[vec3],
                  qd: wp.array[vec3], power_in_out: wp.array[Sums], c: CheckArrays, barrier_in_out: wp.array[wp.int32],
                  clock: wp.float64):
        """The guard's check of the frame's last state (``q``, ``qd``, the world's clock ``clock`` [s]) by the world's
        lanes, then its verdict by the world's first block (``symplectic_euler_frame_kernel``'s ``check``)."""
        stride = lanes * blocks
        drive_lanes(world, block, lane, lanes, particle_count, particle_flags, element_arrays, inputs, q, qd,
                    c.previous_q, stride, c.previous_load, c.partials)
        measure_lanes(world, block, lane, lanes, particle_count, c.world_enabled, particle_flags, particle_mass,
                      element_arrays, NoWork(), inputs, particle_force_ext, q, qd, c.lead, stride, power_in_out,
                      c.previous_q, c.previous_qd, c.previous_load, c.status, c.partials)
        if c.status[world, GUARD_TRIPPED] == 0 and c.world_enabled[world] != 0:  # (the energy pass's skip)
            energy, worst, taken = energy_lanes(world, block * lanes + lane, stride, world * particle_count, c.counts,
                                                0, element_arrays, inputs, q, qd)
            energy = block_sum(energy)
            worst = block_max(worst)
            taken = block_sum(taken)
            if lane == 0:
                c.energy_partials[world, block] = energy
                c.strain_partials[world, block] = worst
                c.power_partials[world, block] = taken
        if blocks > 1 and lane == 0:  # the world's blocks meet once more: every partial sum written
            memory_fence()
            wp.atomic_add(barrier_in_out, world, 1)
            wait_for_arrivals(barrier_in_out, world, (steps + 1) * blocks)  # (after the frame's ``steps`` meetings)
        block_barrier()
        if block == 0:
            gather_lanes(world, lane, lanes, particle_count, element_arrays, q, c.partials, c.energy_partials,
                         c.strain_partials, c.power_partials, steps - 1, c.limits, c.power_h, 0, c.world_enabled,
                         c.status, c.running, c.values, c.work_total, c.balance, c.carry, clock, c.mirror)

    @wp.func
    def substep(world: int, lane: int, lanes: int, particle_count: int,
                particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
                particle_radius: wp.array[scalar], shapes: Shapes, particle_mass: wp.array2d[scalar],
                element_arrays: Elements, inputs: wp.array2d[scalar], particle_force_ext: wp.array[vec3],
                q_in: wp.array[vec3], qd_in: wp.array[vec3], h: scalar, groups: PinGroups, tracks: Tracks,
                pin_targets: PinTargets, clock: wp.float64, step_f64: wp.float64,
                q_out: wp.array[vec3], qd_out: wp.array[vec3], power_in_out: wp.array[Sums]):
        """The lane's particles stepped; with ``power``, what their dampers and drag took out and the loads from
        outside put in over the step [J] (float64), returned for the lane to keep in registers over the frame."""
        base = world * particle_count
        taken = wp.float64(0.0)
        worked = wp.float64(0.0)
        i = lane
        while i < particle_count:
            p = base + i
            if wp.static(counted):
                x, v, t, w = step_energy(world, i, p, base, particle_flags, particle_inv_mass, particle_radius,
                                         shapes, particle_mass, element_arrays, inputs, particle_force_ext, q_in,
                                         qd_in, h)
                taken += wp.float64(t)
                worked += wp.float64(w)
            else:
                x, v = step_particle(world, i, p, base, particle_flags, particle_inv_mass, particle_radius, shapes,
                                     particle_mass, element_arrays, inputs, particle_force_ext, q_in, qd_in, h,
                                     power_in_out)
            if wp.static(driven):  # a pin on its prescribed motion, as ``apply_kinematics`` puts it after a step
                k = groups.entry[i]
                if k >= 0 and is_kinematic(particle_flags[p]):
                    x, v = prescribed(world, k, q_in[p], qd_in[p], clock, step_f64, groups, tracks, pin_targets)
            q_out[p] = x
            qd_out[p] = v
            i += lanes
        return taken, worked

    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 **launch_bounds_option(bounds),
                 last=(contacts.idle() + composed.last("element_arrays") + (() if animated else ANIMATED_LEAVES)
                       + (() if animated or driven or moving else TRACK_LEAVES) + (() if driven else PIN_LEAVES)
                       + (() if targets else TARGET_LEAVES) + (() if checked else CHECK_LEAVES)
                       + (() if moving else ("shape_rest", "shape_translation_track", "shape_rotation_track")
                          + tuple(f"shapes_out__{name}" for name in Shapes.vars))))
    def symplectic_euler_frame(
        # Model:
        particle_count: int,
        lanes: int,
        blocks: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        # Model, the forces:
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # Model, the animated inputs and the pin groups (read with ``animated``, ``driven`` only):
        tracks: Tracks,
        animated_inputs: WorldInputs,
        groups: PinGroups,
        # Model, the colliders' motion (read with ``moving`` only):
        shape_rest: wp.array[wp.transformd],
        shape_translation_track: wp.array[wp.int32],
        shape_rotation_track: wp.array[wp.int32],
        # Control (read with ``targets`` only):
        pin_targets: PinTargets,
        # Step:
        steps: int,
        frame_steps: int,
        dt: scalar,
        dt_rest: scalar,
        step_f64: wp.float64,
        # In/out:
        # (the input table and the colliders' frames, written with ``animated``, ``moving`` only; the two state
        # buffers, the worlds' clocks [s], the guard's power sums [J], read with ``power`` only; the guard's arrays,
        # with ``check`` only)
        inputs_out: wp.array2d[scalar],
        shapes_out: Shapes,
        q_a_in_out: wp.array[vec3],
        qd_a_in_out: wp.array[vec3],
        q_b_in_out: wp.array[vec3],
        qd_b_in_out: wp.array[vec3],
        time_in_out: wp.array[wp.float64],
        power_in_out: wp.array[Sums],
        check_arrays_in_out: CheckArrays,
        barrier_in_out: wp.array[wp.int32],
    ):
        t = wp.tid()
        stride = lanes * blocks  # a world's threads
        world = t / stride
        lane = t - world * stride
        taken = wp.float64(0.0)  # the lane's power sums over the frame (with ``power``)
        worked = wp.float64(0.0)
        clock = time_in_out[world]  # the world's time at each substep's start (written once, at the end)
        k = int(0)
        while k < steps:
            if wp.static(animated):
                write_world_inputs(world, lane % lanes, lanes, tracks, animated_inputs, clock, inputs_out)
            if wp.static(moving):
                c = lane % lanes
                while c < shape_rest.shape[0]:
                    move_shape(world, c, shape_rest, shape_translation_track, shape_rotation_track, tracks,
                               clock + step_f64, step_f64, shapes_out)
                    c += lanes
            if wp.static(animated or moving):
                block_barrier()  # the block's lanes read the inputs and frames its lanes wrote
            if k % 2 == 0:
                step_taken, step_worked = substep(
                    world, lane, stride, particle_count, particle_flags, particle_inv_mass, particle_radius, shapes,
                    particle_mass, element_arrays, inputs, particle_force_ext, q_a_in_out, qd_a_in_out, dt, groups,
                    tracks, pin_targets, clock, step_f64, q_b_in_out, qd_b_in_out, power_in_out)
            else:
                step_taken, step_worked = substep(
                    world, lane, stride, particle_count, particle_flags, particle_inv_mass, particle_radius, shapes,
                    particle_mass, element_arrays, inputs, particle_force_ext, q_b_in_out, qd_b_in_out, dt, groups,
                    tracks, pin_targets, clock, step_f64, q_a_in_out, qd_a_in_out, power_in_out)
            taken += step_taken
            worked += step_worked
            clock = clock + (wp.float64(dt) + wp.float64(dt_rest))
            block_barrier()  # the block's lanes have written their particles
            if blocks > 1 and lane % lanes == 0:  # the world's blocks meet: each block's first lane counts it in
                memory_fence()
                wp.atomic_add(barrier_in_out, world, 1)
                wait_for_arrivals(barrier_in_out, world, (k + 1) * blocks)
            if blocks > 1:
                block_barrier()
            k += 1
        if lane == 0:
            time_in_out[world] = clock
        if wp.static(counted):  # one entry per lane, once a frame (the check sums a world's entries)
            if steps > 0 and lane < particle_count:
                power_in_out[world * particle_count + lane] += pack(scalar(taken), scalar(worked))
        if wp.static(checked):  # (the lane's check reads its own entries: particle ``lane``, then every stride-th)
            block = lane / lanes
            if frame_steps % 2 == 0:
                end_check(world, block, lane - block * lanes, lanes, blocks, frame_steps, particle_count,
                          particle_flags, particle_mass, element_arrays, inputs, particle_force_ext, q_a_in_out,
                          qd_a_in_out, power_in_out, check_arrays_in_out, barrier_in_out, clock)
            else:
                end_check(world, block, lane - block * lanes, lanes, blocks, frame_steps, particle_count, particle_flags,
                          particle_mass, element_arrays, inputs, particle_force_ext, q_b_in_out, qd_b_in_out,
                          power_in_out, check_arrays_in_out, barrier_in_out, clock)

    return symplectic_euler_frame
