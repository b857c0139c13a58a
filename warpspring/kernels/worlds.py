"""Worlds that are held: a world whose ``world_enabled`` entry is 0 keeps its state through a step.

Worlds are independent copies of a scene in one model (``forces.py`` describes the layout);
``world_and_index`` locates an entry of a state's arrays. Every
integrator steps all worlds in the same launches; when some may be held (switched off by the user, or
stopped by the run-time guard), one pass after the step copies the held worlds' input state over their
output, so a held world's positions, velocities and time stay exactly as they were.
"""

import functools

import warp as wp

from .precision import vec3_type

wp.set_module_options({"enable_backward": False})


@wp.func
def world_and_index(p: int, particle_count: int):
    """(world, index within the world) of entry ``p`` of a state's arrays (``particle_count`` per world).

    Per-particle kernels launch over all worlds' particles in one dimension and derive the world with one
    32-bit division: a two-dimensional launch (world, particle) has Warp unravel a 64-bit linear index,
    which cost the one-world fused step 18-31 % on an H100 (bench/RESULTS.md §8). World 0's entries skip the
    division: on the CPU, where a kernel's threads run in a loop, the division costs ~1 ns per particle (a
    one-world model's per-particle pass 5.1 → 4.3 µs at 1,024 particles, bench/results/performance_cpu.md)."""
    if p < particle_count:
        return 0, p
    world = p // particle_count
    return world, p - world * particle_count


@functools.cache
def hold_worlds_kernel(scalar: type):
    """Kernel copying the state of every held world from ``*_in`` to ``*_out`` (one thread per particle)."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def hold_worlds(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        # State out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if world_enabled[world] != 0:
            return
        if i == 0:
            time_out[world] = time_in[world]
        particle_q_out[p] = particle_q_in[p]
        particle_qd_out[p] = particle_qd_in[p]

    return hold_worlds
