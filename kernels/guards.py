"""Run-time guards: detect a state going bad on the device, per world, without a host synchronisation per
substep.

A check is four launches captured with the substeps: ``measure`` (per particle: non-finite position or
velocity, the largest strain of its elements (the families' ``strain`` hook), kinetic energy (of the free
particles: a kinematic one moves as prescribed), and the work
the loads did on it since the previous check; per-block partials, no float atomics), ``gather`` (per
world: the world's kinetic energy and work, summed in a fixed order, and its largest strain), ``locate``
(the particle, element and family holding the largest strain), ``decide`` (per world: add the work put in
to the world's running total, compare with the world's limits, latch the world's first failure with its
substep, reset the accumulators, and with ``stop_world`` set hold the failed world: ``world_enabled`` 0).

**The work put in.** With dissipative damping and drag, a world's kinetic energy can never exceed its
energy at the start plus the work its loads did since: KE(t) ≤ E(0) + W(t). The kinetic-energy limit is
therefore ``limit + factor · W⁺`` rather than a fixed number: W⁺ sums, check by check, the positive part
of Σᵢ Fᵢ · (xᵢ - xᵢ') over the world's particles, xᵢ' the positions at the previous check, with Fᵢ the
loads at this check: weight mᵢ g and the control's external force on free particles, and for kinematic
particles (pins, tracks) the negative of the elements' force on them, i.e. the force the driver applies
through them. Exact for constant loads and still pins; for varying ones a one-sample rule whose error is
far inside the factor (10⁶ by default) — what it removes is a limit that a pushed body at rest, whose
energy scale is ~0, reaches within a fraction of a second. Once a world's record is latched, later
checks leave it untouched, so the host reads each world's first failure at the end of the frame. Held
worlds are not checked. The records are one row per world, laid out by the slots below.
"""

import functools

import warp as wp

from .families import elements
from .inputs import INPUT_GRAVITY, input_funcs
from .kinematics import is_kinematic
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
GUARD_WORK = 2  # Σ F · Δx of the loads since the previous check [J] (W⁺, the running sum: ``work_total``)
GUARD_FLOATS = 3
# float64 slots of the limits: live settings, read by ``decide``
GUARD_LIMIT_STRAIN = 0  # an element strain beyond this tears the run [-]
GUARD_LIMIT_KINETIC_ENERGY = 1  # a total kinetic energy beyond this is a runaway [J]
GUARD_STOP_WORLD = 2  # 1: a failed world is held and the others go on; 0: the run stops
GUARD_WORK_FACTOR = 3  # the kinetic-energy limit grows by this factor times the work put in [-]
GUARD_LIMITS = 4
# reasons
GUARD_NONFINITE = 1
GUARD_STRAIN = 2
GUARD_ENERGY = 3
NO_PARTICLE = 2**31 - 1


@functools.cache
def guard_kernels(scalar: type, families: tuple, tiled: bool, external: bool):
    """(measure, gather, locate, decide) kernels of one precision and tuple of family specs; ``external``:
    the control has an external force (part of the loads' work)."""
    vec3 = vec3_type(scalar)
    block_sum, block_max = reduction_funcs(tiled)
    composed = elements(scalar, families)
    Elements = composed.arrays
    element_strain = composed.strain
    element_force = composed.force
    input_vec3 = input_funcs(scalar)

    @flat_kernel(module="unique", enable_backward=False, last=composed.last("element_arrays"))
    def measure(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out:
        previous_q: wp.array[vec3],
        status: wp.array2d[wp.int32],
        partials: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        i = block * wp.block_dim() + lane
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        work = wp.float64(0.0)
        if i < particle_count:
            base = world * particle_count
            p = base + i
            x = particle_q[p]
            v = particle_qd[p]
            if wp.isfinite(x) and wp.isfinite(v):
                mass = particle_mass[wp.min(world, particle_mass.shape[0] - 1), i]
                worst, _, _ = element_strain(world, i, base, x, element_arrays, particle_q)
                if is_kinematic(particle_flags[p]):  # prescribed motion: no runaway of its own, a drive's work
                    load = -element_force(world, i, base, x, v, element_arrays, inputs, particle_q, particle_qd)
                else:
                    energy = wp.float64(scalar(0.5) * mass * wp.dot(v, v))
                    load = mass * input_vec3(inputs, world, INPUT_GRAVITY)
                    if wp.static(external):
                        load += particle_force_ext[p]
                work = wp.float64(wp.dot(load, x - previous_q[p]))
            else:
                wp.atomic_min(status, world, GUARD_NONFINITE_PARTICLE, i)
                wp.atomic_add(status, world, GUARD_NONFINITE_COUNT, 1)
            previous_q[p] = x
        energy = block_sum(energy)
        worst = block_max(worst)
        work = block_sum(work)
        if lane == 0:
            partials[world, block, GUARD_KINETIC_ENERGY] = energy
            partials[world, block, GUARD_MAX_STRAIN] = worst
            partials[world, block, GUARD_WORK] = work

    @wp.kernel(module="unique", enable_backward=False)
    def gather(
        world_enabled: wp.array[wp.int32],
        partials: wp.array3d[wp.float64],
        status: wp.array2d[wp.int32],
        # Out:
        values: wp.array2d[wp.float64],
        work_total: wp.array[wp.float64],
    ):
        """A world's kinetic energy and the work put in since the last check (its blocks' partials summed in
        order; the positive part of the work added to the world's running total), and its largest strain."""
        world = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        work = wp.float64(0.0)
        for b in range(partials.shape[1]):
            energy += partials[world, b, GUARD_KINETIC_ENERGY]
            worst = wp.max(worst, partials[world, b, GUARD_MAX_STRAIN])
            work += partials[world, b, GUARD_WORK]
        values[world, GUARD_KINETIC_ENERGY] = energy
        values[world, GUARD_MAX_STRAIN] = worst
        values[world, GUARD_WORK] = work
        if wp.isfinite(work):
            work_total[world] += wp.max(work, wp.float64(0.0))

    @flat_kernel(module="unique", enable_backward=False, last=composed.last("element_arrays"))
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
        work_total: wp.array[wp.float64],
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
        elif values[world, GUARD_KINETIC_ENERGY] > (
            limits[world, GUARD_LIMIT_KINETIC_ENERGY] + limits[world, GUARD_WORK_FACTOR] * work_total[world]
        ):
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
