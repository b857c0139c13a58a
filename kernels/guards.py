"""Run-time guards: detect a state going bad on the device, without a host synchronisation per substep.

A check is three launches captured with the substeps: ``measure`` (per particle: non-finite position or
velocity, the largest strain of its springs, kinetic energy), ``locate`` (the particle and spring holding
the largest strain), ``decide`` (one thread: compare with the limits, latch the first failure with its
substep, reset the accumulators). Once latched, later checks leave the record untouched, so the host
reads the first failure at the end of the frame. The status arrays are laid out by the slots below.
"""

import functools

import warp as wp

from .linalg import reduction_funcs
from .precision import vec3_type

wp.set_module_options({"enable_backward": False})

# int32 status slots
GUARD_TRIPPED = 0  # 0 = fine, else one of the GUARD_* reasons
GUARD_SUBSTEP = 1  # substep (within the frame) of the check that tripped
GUARD_NONFINITE_PARTICLE = 2  # smallest index of a particle with a non-finite position or velocity
GUARD_STRAIN_PARTICLE = 3  # smallest index of a particle holding the largest strain
GUARD_STRAIN_SPRING = 4  # smallest index of a spring with the largest strain
GUARD_NONFINITE_COUNT = 5  # particles with a non-finite position or velocity
GUARD_INTS = 6
# float64 slots
GUARD_MAX_STRAIN = 0  # largest spring strain (|d|/L - 1) of the check
GUARD_KINETIC_ENERGY = 1  # Σ ½ m v² of the check [J]
GUARD_FLOATS = 2
# float64 slots of the limits: live settings, read by ``decide``
GUARD_LIMIT_STRAIN = 0  # a spring strain beyond this tears the run [-]
GUARD_LIMIT_KINETIC_ENERGY = 1  # a total kinetic energy beyond this is a runaway [J]
GUARD_LIMITS = 2
# reasons
GUARD_NONFINITE = 1
GUARD_STRAIN = 2
GUARD_ENERGY = 3
NO_PARTICLE = 2**31 - 1


@functools.cache
def guard_funcs(scalar: type):
    """The strain |d|/L - 1 of one spring; -1 for a padding slot or a zero-rest-length spring."""
    vec3 = vec3_type(scalar)

    @wp.func
    def spring_strain(i: int, j: int, xi: vec3, xj: vec3, rest: scalar) -> wp.float64:
        if j == i or rest <= scalar(0.0):
            return wp.float64(-1.0)
        return wp.float64(wp.length(xj - xi) / rest) - wp.float64(1.0)

    return spring_strain


@functools.cache
def guard_kernels(scalar: type, slots: int, tiled: bool):
    """(measure, locate, decide) kernels of one precision and incidence-table width."""
    vec3 = vec3_type(scalar)
    accumulate = reduction_funcs(tiled)
    spring_strain = guard_funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def measure(
        count: int,
        # Model:
        particle_mass: wp.array[scalar],
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out:
        status: wp.array[wp.int32],
        values: wp.array[wp.float64],
    ):
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        energy = wp.float64(0.0)
        if i < count and status[GUARD_TRIPPED] == 0:
            x = particle_q[i]
            v = particle_qd[i]
            if wp.isfinite(x) and wp.isfinite(v):
                energy = wp.float64(scalar(0.5) * particle_mass[i] * wp.dot(v, v))
                worst = wp.float64(-1.0)
                for k in range(wp.static(slots)):
                    j = particle_spring_neighbor[k, i]
                    rest = spring_rest_length[particle_spring_id[k, i]]
                    worst = wp.max(worst, spring_strain(i, j, x, particle_q[j], rest))
                wp.atomic_max(values, GUARD_MAX_STRAIN, worst)
            else:
                wp.atomic_min(status, GUARD_NONFINITE_PARTICLE, i)
                wp.atomic_add(status, GUARD_NONFINITE_COUNT, 1)
        accumulate(values, GUARD_KINETIC_ENERGY, energy, lane)

    @wp.kernel(module="unique", enable_backward=False)
    def locate(
        # Model:
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        # State in:
        particle_q: wp.array[vec3],
        # In/out:
        status: wp.array[wp.int32],
        values: wp.array[wp.float64],
    ):
        i = wp.tid()
        largest = values[GUARD_MAX_STRAIN]
        if status[GUARD_TRIPPED] != 0 or largest < wp.float64(0.0):
            return
        x = particle_q[i]
        for k in range(wp.static(slots)):
            j = particle_spring_neighbor[k, i]
            s = particle_spring_id[k, i]
            if spring_strain(i, j, x, particle_q[j], spring_rest_length[s]) == largest:  # as computed in measure
                wp.atomic_min(status, GUARD_STRAIN_PARTICLE, i)
                wp.atomic_min(status, GUARD_STRAIN_SPRING, s)

    @wp.kernel(module="unique", enable_backward=False)
    def decide(
        substep: int,
        limits: wp.array[wp.float64],
        # In/out:
        status: wp.array[wp.int32],
        values: wp.array[wp.float64],
    ):
        if status[GUARD_TRIPPED] != 0:
            return
        reason = 0
        if status[GUARD_NONFINITE_PARTICLE] != NO_PARTICLE or not wp.isfinite(values[GUARD_KINETIC_ENERGY]):
            reason = GUARD_NONFINITE
        elif values[GUARD_MAX_STRAIN] > limits[GUARD_LIMIT_STRAIN]:
            reason = GUARD_STRAIN
        elif values[GUARD_KINETIC_ENERGY] > limits[GUARD_LIMIT_KINETIC_ENERGY]:
            reason = GUARD_ENERGY
        if reason != 0:
            status[GUARD_TRIPPED] = reason
            status[GUARD_SUBSTEP] = substep
            return
        values[GUARD_MAX_STRAIN] = wp.float64(-1.0)
        values[GUARD_KINETIC_ENERGY] = wp.float64(0.0)
        status[GUARD_STRAIN_PARTICLE] = NO_PARTICLE
        status[GUARD_STRAIN_SPRING] = NO_PARTICLE

    return measure, locate, decide
