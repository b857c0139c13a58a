"""Run-time guards: detect a state going bad on the device, per world, without a host synchronisation per
substep.

A check is four launches captured with the substeps: ``measure`` (per particle: non-finite position or
velocity, the largest strain of its elements (the families' ``strain`` hook), kinetic energy; per-block
partials, no float atomics), ``gather`` (per world: the world's kinetic energy, summed in a fixed order,
and its largest strain), ``locate`` (the particle, element and family holding the largest strain), ``decide`` (per world: compare with the
world's limits, latch the world's first failure with its substep, reset the accumulators, and with
``stop_world`` set hold the failed world: ``world_enabled`` 0). Once a world's record is latched, later
checks leave it untouched, so the host reads each world's first failure at the end of the frame. Held
worlds are not checked. The records are one row per world, laid out by the slots below.
"""

import functools

import warp as wp

from .families import elements
from .linalg import reduction_funcs
from .precision import vec3_type
from .worlds import world_and_index
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})

# int32 status slots
GUARD_TRIPPED = 0  # 0 = fine, else one of the GUARD_* reasons
GUARD_SUBSTEP = 1  # substep (within the frame) of the check that tripped
GUARD_NONFINITE_PARTICLE = 2  # smallest index of a particle with a non-finite position or velocity
GUARD_STRAIN_PARTICLE = 3  # smallest index of a particle holding the largest strain
GUARD_STRAIN_ELEMENT = 4  # smallest index of an element with the largest strain
GUARD_NONFINITE_COUNT = 5  # particles with a non-finite position or velocity
GUARD_STRAIN_FAMILY = 6  # smallest index (in the model's families) of a family with the largest strain
GUARD_INTS = 7
# float64 slots
GUARD_MAX_STRAIN = 0  # largest element strain (springs: |d|/L - 1) of the check
GUARD_KINETIC_ENERGY = 1  # Σ ½ m v² of the check [J]
GUARD_FLOATS = 2
# float64 slots of the limits: live settings, read by ``decide``
GUARD_LIMIT_STRAIN = 0  # an element strain beyond this tears the run [-]
GUARD_LIMIT_KINETIC_ENERGY = 1  # a total kinetic energy beyond this is a runaway [J]
GUARD_STOP_WORLD = 2  # 1: a failed world is held and the others go on; 0: the run stops
GUARD_LIMITS = 3
# reasons
GUARD_NONFINITE = 1
GUARD_STRAIN = 2
GUARD_ENERGY = 3
NO_PARTICLE = 2**31 - 1


@functools.cache
def guard_kernels(scalar: type, families: tuple, tiled: bool):
    """(measure, gather, locate, decide) kernels of one precision and tuple of family specs."""
    vec3 = vec3_type(scalar)
    block_sum, block_max = reduction_funcs(tiled)
    composed = elements(scalar, families)
    Elements = composed.arrays
    element_strain = composed.strain

    @flat_kernel(module="unique", enable_backward=False)
    def measure(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out:
        status: wp.array2d[wp.int32],
        partials: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        i = block * wp.block_dim() + lane
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        if i < particle_count:
            base = world * particle_count
            x = particle_q[base + i]
            v = particle_qd[base + i]
            if wp.isfinite(x) and wp.isfinite(v):
                energy = wp.float64(scalar(0.5) * particle_mass[wp.min(world, particle_mass.shape[0] - 1), i] * wp.dot(v, v))
                worst, _, _ = element_strain(world, i, base, x, element_arrays, particle_q)
            else:
                wp.atomic_min(status, world, GUARD_NONFINITE_PARTICLE, i)
                wp.atomic_add(status, world, GUARD_NONFINITE_COUNT, 1)
        energy = block_sum(energy)
        worst = block_max(worst)
        if lane == 0:
            partials[world, block, GUARD_KINETIC_ENERGY] = energy
            partials[world, block, GUARD_MAX_STRAIN] = worst

    @wp.kernel(module="unique", enable_backward=False)
    def gather(
        world_enabled: wp.array[wp.int32],
        partials: wp.array3d[wp.float64],
        status: wp.array2d[wp.int32],
        # Out:
        values: wp.array2d[wp.float64],
    ):
        """A world's kinetic energy (its blocks' partials summed in order) and largest strain."""
        world = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        for b in range(partials.shape[1]):
            energy += partials[world, b, GUARD_KINETIC_ENERGY]
            worst = wp.max(worst, partials[world, b, GUARD_MAX_STRAIN])
        values[world, GUARD_KINETIC_ENERGY] = energy
        values[world, GUARD_MAX_STRAIN] = worst

    @flat_kernel(module="unique", enable_backward=False)
    def locate(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        element_arrays: Elements,
        # State in:
        particle_q: wp.array[vec3],
        # In/out:
        status: wp.array2d[wp.int32],
        values: wp.array2d[wp.float64],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        largest = values[world, GUARD_MAX_STRAIN]
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0 or largest < wp.float64(0.0):
            return
        strain, element, family = element_strain(world, i, p - i, particle_q[p], element_arrays, particle_q)
        if strain == largest:  # the same evaluation as in measure
            wp.atomic_min(status, world, GUARD_STRAIN_PARTICLE, i)
            wp.atomic_min(status, world, GUARD_STRAIN_ELEMENT, element)
            wp.atomic_min(status, world, GUARD_STRAIN_FAMILY, family)

    @wp.kernel(module="unique", enable_backward=False)
    def decide(
        substep: int,
        limits: wp.array2d[wp.float64],
        # In/out:
        world_enabled: wp.array[wp.int32],
        status: wp.array2d[wp.int32],
        values: wp.array2d[wp.float64],
    ):
        world = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        reason = 0
        if status[world, GUARD_NONFINITE_PARTICLE] != NO_PARTICLE or not wp.isfinite(values[world, GUARD_KINETIC_ENERGY]):
            reason = GUARD_NONFINITE
        elif values[world, GUARD_MAX_STRAIN] > limits[world, GUARD_LIMIT_STRAIN]:
            reason = GUARD_STRAIN
        elif values[world, GUARD_KINETIC_ENERGY] > limits[world, GUARD_LIMIT_KINETIC_ENERGY]:
            reason = GUARD_ENERGY
        if reason != 0:
            status[world, GUARD_TRIPPED] = reason
            status[world, GUARD_SUBSTEP] = substep
            if limits[world, GUARD_STOP_WORLD] != wp.float64(0.0):
                world_enabled[world] = 0
            return
        values[world, GUARD_MAX_STRAIN] = wp.float64(-1.0)
        values[world, GUARD_KINETIC_ENERGY] = wp.float64(0.0)
        status[world, GUARD_STRAIN_PARTICLE] = NO_PARTICLE
        status[world, GUARD_STRAIN_ELEMENT] = NO_PARTICLE
        status[world, GUARD_STRAIN_FAMILY] = NO_PARTICLE

    return measure, gather, locate, decide
