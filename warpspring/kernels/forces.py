"""Particle forces: gravity, viscous drag, external forces and the element families' forces.

The elements (springs, hinges, any family of ``families.py``) are gathered per particle: each particle sums
the forces of the elements at it, so every force is written exactly once, without atomics, and the force
can be fused into an integrator's update kernel; each element is evaluated once per particle it touches,
which a GPU hides behind memory traffic. On the CPU, where Warp runs a kernel's threads in sequence,
springs may instead be scattered (``springs.spring_scatter_kernel``: each evaluated once, added to both
ends) after a per-particle pass wrote everything else.

Worlds: a model holds ``world_count`` copies of one topology. Per-particle kernels launch one thread per
particle of every world (``worlds.world_and_index`` finds its world); particle i of world w is entry
w·n + i of a state's arrays (n particles per world), and topology is shared, in per-world indices.
Parameters a user may vary per world are 2-D arrays with one row for all worlds or one per world, read at
row ``min(world, rows - 1)`` (the rows are 1 or world_count: a comparison, where ``world % rows`` would cost
an integer division per array); the input table has one row per world. A world never reads another
world's entries, so worlds never couple.
"""

import functools
from typing import NamedTuple

import warp as wp

from .families import FORCE_KERNEL_OPTIONS, elements
from .kinematics import is_kinematic
from .inputs import INPUT_DRAG, INPUT_GRAVITY, INPUT_MAX_PARTICLE_FORCE, INPUT_WIND, input_funcs
from .precision import vec3_type
from .worlds import world_and_index
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})


class ForceFeatures(NamedTuple):
    """Which force terms a kernel evaluates; each absent term is compiled out (values come from the inputs)."""

    families: tuple  # the specs of the element families (``families.py``), in the model's order
    gravity: bool
    drag: bool
    external: bool
    clamp_particle_force: bool = False  # clamp the total force on a particle to INPUT_MAX_PARTICLE_FORCE
    wind: bool = False  # the model has wind: drag acts on the velocity relative to the air, v - INPUT_WIND


@functools.cache
def particle_force_func(scalar: type, features: ForceFeatures):
    """The force on one particle, specialized for the scene's force terms and element families."""
    vec3 = vec3_type(scalar)
    composed = elements(scalar, features.families)
    Elements = composed.arrays
    element_force = composed.force
    input_vec3 = input_funcs(scalar)

    @wp.func
    def particle_force(
        world: int,
        i: int,
        base: int,
        xi: vec3,
        vi: vec3,
        # Model:
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
    ) -> vec3:
        """Force [N] on particle i of ``world`` (entry base + i): m g - drag v + f_ext + the elements' forces,
        magnitude clamped if the features say so (with scattered springs the clamp is a separate pass:
        ``clamp_forces_kernel``); g, drag and the limits from the world's row of the input table."""
        f = vec3(scalar(0.0))
        if wp.static(features.gravity):
            f += particle_mass[wp.min(world, particle_mass.shape[0] - 1), i] * input_vec3(inputs, world, INPUT_GRAVITY)
        if wp.static(features.drag):
            if wp.static(features.wind):
                f -= inputs[world, INPUT_DRAG] * (vi - input_vec3(inputs, world, INPUT_WIND))
            else:
                f -= inputs[world, INPUT_DRAG] * vi
        if wp.static(features.external):
            f += particle_force_ext[base + i]
        f += element_force(world, i, base, xi, vi, element_arrays, inputs, particle_q, particle_qd)
        if wp.static(features.clamp_particle_force):
            max_force = inputs[world, INPUT_MAX_PARTICLE_FORCE]
            magnitude = wp.length(f)
            if magnitude > max_force:
                f = f * (max_force / magnitude)
        return f

    return particle_force


@functools.cache
def eval_forces_kernel(scalar: type, features: ForceFeatures, power: tuple | None = None, store: bool = False):
    """Kernel writing the total force on every particle (one thread per particle of every world).

    With ``power`` (one ``POWER_*`` mode per family of ``features``) each free particle also adds to its own entry of
    the guard's power sums (``core/forces.PowerSums``) h times the power its dampers and drag take out, -f_d·v, and
    the power of the loads from outside, f_w·v, at the state evaluated (a step's start: the guard's trapezoid of the
    power, closed at its checks); with ``store`` it writes the dampers' and the outside loads' parts of the force to
    ``particle_fd_out`` and ``particle_fw_out`` instead (symplectic Euler's update counts them with the step's
    velocities; a scattered spring pass adds its dampers' part after)."""
    vec3 = vec3_type(scalar)
    counted = power is not None
    particle_force = particle_power_func(scalar, features, power) if counted else particle_force_func(scalar, features)
    sums = power_sums_funcs(scalar, counted and counts_work(features, power))
    Sums = sums.type
    pack = sums.pack
    composed = elements(scalar, features.families)
    Elements = composed.arrays

    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 last=composed.last("element_arrays"))
    def eval_forces(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Guard in (the step h [s], read with ``power`` only):
        power_h: scalar,
        # Out:
        particle_f_out: wp.array[vec3],
        particle_fd_out: wp.array[vec3],
        particle_fw_out: wp.array[vec3],
        # In/out (the guard's power sums [J], read with ``power`` only):
        power_in_out: wp.array[Sums],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if wp.static(counted):
            v = particle_qd[p]
            f, dampers, work = particle_force(world, i, p - i, particle_q[p], v, not is_kinematic(particle_flags[p]),
                                              particle_mass, element_arrays, inputs, particle_force_ext, particle_q,
                                              particle_qd)
            particle_f_out[p] = f
            if wp.static(store):
                particle_fd_out[p] = dampers
                particle_fw_out[p] = work
            else:
                power_in_out[p] += pack(-power_h * wp.dot(dampers, v), power_h * wp.dot(work, v))
        else:
            particle_f_out[p] = particle_force(world, i, p - i, particle_q[p], particle_qd[p], particle_mass,
                                               element_arrays, inputs, particle_force_ext, particle_q, particle_qd)

    return eval_forces


@functools.cache
def clamp_forces_kernel(scalar: type):
    """Kernel clamping the magnitude of every particle's total force to the input ``INPUT_MAX_PARTICLE_FORCE`` [N]."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def clamp_forces(particle_count: int, inputs: wp.array2d[scalar], particle_f_in_out: wp.array[vec3]):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        limit = inputs[world, INPUT_MAX_PARTICLE_FORCE]
        f = particle_f_in_out[p]
        magnitude = wp.length(f)
        if magnitude > limit:
            particle_f_in_out[p] = f * (limit / magnitude)

    return clamp_forces


#: How ``particle_power_func`` counts a family's force (``power_modes``): not at all (no dampers of its own, or
#: counted elsewhere), its dampers' part (the ``split`` hook) as dissipation, or all of it as work from outside
#: (wind, handles: ``ElementFamily.does_work``).
POWER_NONE, POWER_DAMPERS, POWER_WORK = 0, 1, 2


class PowerSumsFuncs(NamedTuple):
    """The guard's per-particle power sums in one precision (``power_sums_funcs``): their element type and how a
    kernel packs (energy taken out, work done) into one and reads them back."""

    type: type
    pack: wp.Function
    dissipated: wp.Function
    worked: wp.Function


def counts_work(features: ForceFeatures, modes: tuple) -> bool:
    """Whether the power sums of ``features`` and family ``modes`` (``POWER_*``) carry the loads' work besides the
    dampers' loss: a family whose force does work from outside, or drag in wind (its push)."""
    return POWER_WORK in modes or (features.drag and features.wind)


@functools.cache
def power_sums_funcs(scalar: type, work: bool) -> PowerSumsFuncs:
    """The power sums' element: (energy taken out [J], work done [J]) as a 2-vector with ``work``, else the energy
    taken out alone (half the memory traffic of the step that adds to it: the common scene has no loads from
    outside)."""
    vec2 = wp.types.vector(length=2, dtype=scalar)
    if work:

        @wp.func
        def pack2(dissipated: scalar, worked: scalar) -> vec2:
            return vec2(dissipated, worked)

        @wp.func
        def dissipated2(sums: vec2) -> scalar:
            return sums[0]

        @wp.func
        def worked2(sums: vec2) -> scalar:
            return sums[1]

        return PowerSumsFuncs(vec2, pack2, dissipated2, worked2)

    @wp.func
    def pack1(dissipated: scalar, worked: scalar) -> scalar:
        return dissipated

    @wp.func
    def dissipated1(sums: scalar) -> scalar:
        return sums

    @wp.func
    def worked1(sums: scalar) -> scalar:
        return scalar(0.0)

    return PowerSumsFuncs(scalar, pack1, dissipated1, worked1)


@functools.cache
def split_elements(scalar: type, specs: tuple, modes: tuple):
    """``split(world, i, base, xi, vi, element_arrays, inputs, particle_q, particle_qd) -> (force, dampers, work)``:
    the elements' force [N] on particle i (``elements(scalar, specs).force``), the part of it their dampers exert
    and the part that does work from outside, each family as its mode in ``modes`` (``POWER_*``, one per spec)
    says; ``element_arrays`` is ``elements(scalar, specs).arrays``."""
    vec3 = vec3_type(scalar)
    Elements = elements(scalar, specs).arrays
    if not specs:

        @wp.func
        def split_none(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Elements, inputs: wp.array2d[scalar],
                       particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
            zero = vec3(scalar(0.0))
            return zero, zero, zero

        return split_none
    funcs = specs[0].funcs(scalar)
    mode = modes[0]
    split = getattr(funcs, "split", None)
    if mode == POWER_DAMPERS and split is None:
        raise ValueError(f"{type(specs[0]).__name__} has no split hook: its dampers cannot be counted in its force "
                         "pass")
    head_force = funcs.force
    head_split = split if mode == POWER_DAMPERS else funcs.force

    @wp.func
    def split_head(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: funcs.arrays, inputs: wp.array2d[scalar],
                   particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
        zero = vec3(scalar(0.0))
        if wp.static(mode == POWER_DAMPERS):
            f, dampers = head_split(world, i, base, xi, vi, arrays, inputs, particle_q, particle_qd)
            return f, dampers, zero
        f = head_force(world, i, base, xi, vi, arrays, inputs, particle_q, particle_qd)
        if wp.static(mode == POWER_WORK):
            return f, zero, f
        return f, zero, zero

    if len(specs) == 1:

        @wp.func
        def split_1(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Elements, inputs: wp.array2d[scalar],
                    particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
            return split_head(world, i, base, xi, vi, arrays.head, inputs, particle_q, particle_qd)

        return split_1
    rest = split_elements(scalar, specs[1:], modes[1:])

    @wp.func
    def split_n(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Elements, inputs: wp.array2d[scalar],
                particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
        f, dampers, work = split_head(world, i, base, xi, vi, arrays.head, inputs, particle_q, particle_qd)
        f_rest, dampers_rest, work_rest = rest(world, i, base, xi, vi, arrays.tail, inputs, particle_q, particle_qd)
        return f + f_rest, dampers + dampers_rest, work + work_rest

    return split_n


@functools.cache
def particle_power_func(scalar: type, features: ForceFeatures, modes: tuple):
    """``particle_power(world, i, base, xi, vi, free, ...) -> (force, dampers, work)``: ``particle_force_func``'s force
    [N] on particle i (not clamped: the guard's power is not counted under ``clamp_particle_force``) with the part of
    it that dampers and drag exert (drag against still air, -c v) and the part that does work from outside (the
    wind's push through drag, c u; the families of mode ``POWER_WORK``): ``modes`` one ``POWER_*`` per family of
    ``features``. The guard's power sums (``core/forces.PowerSums``) take -dampers·v̄ and work·v̄ of them. For a
    kinematic particle (``free`` off) only the elements' dampers count: what the drive does against them is in the
    drive's work (the guard's check), their damper's share of the power here, so that D is each damper's whole power;
    drag and the outside loads act on free particles only."""
    vec3 = vec3_type(scalar)
    Elements = elements(scalar, features.families).arrays
    split = split_elements(scalar, features.families, modes)
    input_vec3 = input_funcs(scalar)

    @wp.func
    def particle_power(
        world: int,
        i: int,
        base: int,
        xi: vec3,
        vi: vec3,
        free: bool,
        # Model:
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
    ):
        # The terms in ``particle_force_func``'s order: the same force to the last bit.
        f = vec3(scalar(0.0))
        dampers = vec3(scalar(0.0))
        work = vec3(scalar(0.0))
        if wp.static(features.gravity):
            f += particle_mass[wp.min(world, particle_mass.shape[0] - 1), i] * input_vec3(inputs, world, INPUT_GRAVITY)
        if wp.static(features.drag):
            dampers = -inputs[world, INPUT_DRAG] * vi
            if wp.static(features.wind):
                work = inputs[world, INPUT_DRAG] * input_vec3(inputs, world, INPUT_WIND)
                f -= inputs[world, INPUT_DRAG] * (vi - input_vec3(inputs, world, INPUT_WIND))
            else:
                f -= inputs[world, INPUT_DRAG] * vi
        if wp.static(features.external):
            f += particle_force_ext[base + i]
        elements_f, elements_dampers, elements_work = split(world, i, base, xi, vi, element_arrays, inputs, particle_q,
                                                            particle_qd)
        f += elements_f
        if not free:
            return f, elements_dampers, vec3(scalar(0.0))
        return f, dampers + elements_dampers, work + elements_work

    return particle_power
