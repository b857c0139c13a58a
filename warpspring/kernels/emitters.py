"""Particle emitters: births and deaths in a fixed pool of particles, on the device, without host round trips.

An emitter owns ``capacity`` consecutive particles of every world (its pool). Births are numbered by a
serial s = 0, 1, 2, ... per world; serial s lives in pool slot s mod capacity, so the slots are recycled in
birth order (a ring: the oldest particle gives way when the pool is full — the stated policy — and each such
early recycling is counted). A step of length h ending at time t gives floor(a + rate·h) births from the
rate (a carries the fraction to the next step) plus the bursts whose time falls in [t − h, t). A particle
dies when its age reaches the life span: it becomes kinematic and still (a pinned particle that no force
moves and no collider touches) until its slot is reused. Births and deaths run after every step, as one
kernel over the pool's slots (each slot decides alone: no search, no atomics but an integer count of the
recycled) and one over the worlds (the counters).

A newborn is placed on the emitter's shape (a point, a box, or a triangle mesh's surface, area-weighted),
with the velocity v₀ plus an isotropic Gaussian spread of standard deviation σ per component, drawn from
Warp's random stream seeded by (seed, serial, world): the same serial always gets the same start.
"""

import functools

import warp as wp

from .kinematics import PARTICLE_KINEMATIC
from .precision import vec3_type

wp.set_module_options({"enable_backward": False})

SHAPE_POINT, SHAPE_BOX, SHAPE_MESH = 0, 1, 2
#: ``serial`` of a slot holding no live particle.
DEAD = -1


@wp.struct
class EmitterArrays:
    """One emitter's parameters and counters (float64 geometry and times)."""

    first: int  # the pool's first particle (per-world index)
    capacity: int  # the pool's size
    rate: wp.array[wp.float64]  # [1/s], [1]: births per second (a live value)
    life: wp.array[wp.float64]  # [s], [1]: the life span
    velocity: wp.array[wp.vec3d]  # [m/s], [1]: v₀
    spread: wp.array[wp.float64]  # [m/s], [1]: σ of each velocity component
    seed: int
    center: wp.array[wp.vec3d]  # [m], [1]: the point, or the box's centre (a live value)
    half_extents: wp.array[wp.vec3d]  # [m], [1]: the box's half sizes (axis-aligned)
    mesh_points: wp.array[wp.vec3d]  # [m], the mesh's vertices
    mesh_faces: wp.array[wp.vec3i]  # the mesh's triangles
    mesh_cdf: wp.array[wp.float64]  # [t], the triangles' cumulative area, normalised to end at 1
    burst_time: wp.array[wp.float64]  # [s], [bursts]
    burst_count: wp.array[wp.int32]  # [bursts]
    births: wp.array[wp.int32]  # [world_count]: serials used so far
    fraction: wp.array[wp.float64]  # [world_count]: the rate's births carried to the next step
    recycled: wp.array[wp.int32]  # [world_count]: particles recycled before their life span ended
    serial: wp.array[wp.int32]  # [world_count · capacity]: each slot's serial, or DEAD
    birth_time: wp.array[wp.float64]  # [s], [world_count · capacity]


@wp.func
def births_in_step(emitter: EmitterArrays, world: int, t_end: wp.float64, h: wp.float64) -> int:
    """Births in the step [t_end − h, t_end): the rate's whole births and the bursts that fall in it."""
    count = int(wp.floor(emitter.fraction[world] + emitter.rate[0] * h))
    for b in range(emitter.burst_time.shape[0]):
        tb = emitter.burst_time[b]
        if tb >= t_end - h and tb < t_end:
            count += emitter.burst_count[b]
    return count


@wp.func
def sample_shape(emitter: EmitterArrays, kind: int, state: wp.uint32) -> wp.vec3d:
    """A point of the emitter's shape [m]: the point, uniform in the box, or uniform on the mesh's area."""
    if kind == SHAPE_BOX:
        u = wp.vec3d(wp.float64(wp.randf(state)), wp.float64(wp.randf(state)), wp.float64(wp.randf(state)))
        h = emitter.half_extents[0]
        return emitter.center[0] + wp.vec3d((wp.float64(2.0) * u[0] - wp.float64(1.0)) * h[0],
                                         (wp.float64(2.0) * u[1] - wp.float64(1.0)) * h[1],
                                         (wp.float64(2.0) * u[2] - wp.float64(1.0)) * h[2])
    if kind == SHAPE_MESH:
        pick = wp.float64(wp.randf(state))
        lo = int(0)
        hi = emitter.mesh_cdf.shape[0] - 1
        while lo < hi:  # the first triangle whose cumulative area reaches the pick
            mid = (lo + hi) // 2
            if emitter.mesh_cdf[mid] < pick:
                lo = mid + 1
            else:
                hi = mid
        face = emitter.mesh_faces[lo]
        r1 = wp.sqrt(wp.float64(wp.randf(state)))
        r2 = wp.float64(wp.randf(state))
        return ((wp.float64(1.0) - r1) * emitter.mesh_points[face[0]] + (r1 * (wp.float64(1.0) - r2))
                * emitter.mesh_points[face[1]] + (r1 * r2) * emitter.mesh_points[face[2]])
    return emitter.center[0]


@functools.cache
def emit_kernel(scalar: type, kind: int):
    """Deaths and births of one emitter's pool after a step; launch over [world_count, capacity]."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def emit(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        # State in (the step's result):
        time: wp.array[wp.float64],
        h: wp.float64,
        # In/out (in place):
        emitter_in_out: EmitterArrays,
        particle_flags_in_out: wp.array[wp.int32],
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
    ):
        world, j = wp.tid()
        if world_enabled[world] == 0:
            return  # a held world: nothing is born or dies
        capacity = emitter_in_out.capacity
        slot = world * capacity + j
        p = world * particle_count + emitter_in_out.first + j
        t = time[world]
        serial = emitter_in_out.serial[slot]
        if serial != DEAD and t - emitter_in_out.birth_time[slot] >= emitter_in_out.life[0]:
            serial = DEAD  # its life span is over: kinematic, still, until the slot is reused
            emitter_in_out.serial[slot] = DEAD
            particle_flags_in_out[p] = particle_flags_in_out[p] | PARTICLE_KINEMATIC
            particle_qd_out[p] = vec3(scalar(0.0))
        n = births_in_step(emitter_in_out, world, t, h)
        first = emitter_in_out.births[world]
        k = (j - first % capacity + capacity) % capacity  # this slot's first new serial is first + k
        if k >= n:
            return
        latest = first + k + ((n - 1 - k) // capacity) * capacity  # several in one step: the last one stays
        dropped = (n - 1 - k) // capacity + wp.where(serial != DEAD, 1, 0)
        if dropped > 0:
            wp.atomic_add(emitter_in_out.recycled, world, dropped)
        state = wp.rand_init(emitter_in_out.seed * 7919 + world, latest)  # a stream per world, an offset per serial
        x = sample_shape(emitter_in_out, wp.static(kind), state)
        sigma = emitter_in_out.spread[0]
        v = emitter_in_out.velocity[0] + sigma * wp.vec3d(wp.float64(wp.randn(state)),
                                                          wp.float64(wp.randn(state)), wp.float64(wp.randn(state)))
        emitter_in_out.serial[slot] = latest
        emitter_in_out.birth_time[slot] = t
        particle_q_out[p] = vec3(x)
        particle_qd_out[p] = vec3(v)
        particle_flags_in_out[p] = particle_flags_in_out[p] & ~PARTICLE_KINEMATIC

    return emit


@wp.kernel(enable_backward=False)
def emit_counts_kernel(
    # Model:
    world_enabled: wp.array[wp.int32],
    # State in:
    time: wp.array[wp.float64],
    h: wp.float64,
    # In/out:
    emitter_in_out: EmitterArrays,
):
    """After ``emit``: the serials used and the rate's fraction carried on; launch over [world_count]."""
    world = wp.tid()
    if world_enabled[world] == 0:
        return
    n = births_in_step(emitter_in_out, world, time[world], h)
    carried = emitter_in_out.fraction[world] + emitter_in_out.rate[0] * h
    emitter_in_out.fraction[world] = carried - wp.floor(carried)
    emitter_in_out.births[world] = emitter_in_out.births[world] + n
