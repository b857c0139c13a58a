"""Particle forces: springs with axial dampers, gravity, viscous drag and external forces.

Springs are evaluated in one of two ways, both deterministic:

* gather (default on CUDA): each particle sums the springs of its incidence table, so every force is
  written exactly once, without atomics, and the force can be fused into an integrator's update kernel;
  each spring is evaluated twice (once per end), which a GPU hides behind memory traffic. The table is
  ELL-shaped, [slots, particle_count]: slot k of consecutive particles is contiguous (coalesced loads);
  unused slots point a particle at itself (a coincident pair: exactly zero force), so the slot loop has
  a compile-time length, unrolls without branches, and the loads of all slots are in flight at once;
* scatter (default on the CPU, where Warp runs a kernel's threads in sequence): each spring is evaluated
  once and added to both ends, after a per-particle pass wrote gravity, drag and external forces.

Worlds: a model holds ``world_count`` copies of one topology. Per-particle kernels launch one thread per
particle of every world (``worlds.world_and_index`` finds its world), per-spring ones over (world,
spring); particle i of world w is entry w·n + i of a state's arrays (n particles per world), and the
incidence table, rest lengths and other topology are shared, in per-world indices. Parameters a user may
vary per world are 2-D arrays with one row for all worlds or one per world, read at row
``min(world, rows - 1)`` (the rows are 1 or world_count: a comparison, where ``world % rows`` would cost an
integer division per array): stiffness and damping [rows, spring_count], masses [rows, n]; the input
table has one row per world. A world never reads another world's entries, so worlds never couple.
"""

import functools
from typing import NamedTuple

import warp as wp

from .inputs import (
    INPUT_BIPHASIC_RATIO,
    INPUT_BIPHASIC_STRAIN,
    INPUT_DRAG,
    INPUT_GRAVITY,
    INPUT_MAX_PARTICLE_FORCE,
    INPUT_MAX_SPRING_FORCE,
    input_funcs,
)
from .precision import mat33_type, vec3_type
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})

#: Particles closer than this [m] are coincident: their spring has no direction and exerts no force.
COINCIDENT_DISTANCE = 1.0e-12

#: Module options of the kernels that evaluate spring forces. Fast math (approximate float32 division
#: and square root, a few ulp; float64 is unaffected) speeds the fused symplectic Euler step by 7-14 %
#: on an H200 (bench/RESULTS.md), well inside float32's own rounding of a swinging cloth.
SPRING_KERNEL_OPTIONS = {"fast_math": True}


class SpringLaw(NamedTuple):
    """Which parts of the spring force law beyond Hooke's spring with an axial damper a kernel compiles.

    Only the switches live here; the values (knee strain, stiffness ratio, force limit) are live inputs
    read from the input table (``inputs.py``), so changing them compiles nothing.

    Attributes:
        biphasic: springs stiffen by ``INPUT_BIPHASIC_RATIO`` beyond the strain ``INPUT_BIPHASIC_STRAIN``.
        clamp_force: a spring's force magnitude, elastic plus damping, is clamped to ``INPUT_MAX_SPRING_FORCE``.
    """

    biphasic: bool = False
    clamp_force: bool = False


#: The plain law: f = (ke (|d| - L) + kd (vj - vi)·d̂) d̂.
HOOKE = SpringLaw()


class ForceFeatures(NamedTuple):
    """Which force terms a kernel evaluates; each absent term is compiled out (values come from the inputs)."""

    spring_slots: int  # slots of the gathered incidence table (max springs per particle); 0: no gathered springs
    gravity: bool
    drag: bool
    external: bool
    spring_law: SpringLaw = HOOKE
    clamp_particle_force: bool = False  # clamp the total force on a particle to INPUT_MAX_PARTICLE_FORCE


@functools.cache
def spring_law_type(scalar: type):
    """The struct of a spring law's values, read once per thread from the input table."""

    @wp.struct
    class SpringLawValues:
        knee_strain: scalar  # strain beyond which a biphasic spring stiffens [-]
        extra_stiffness: scalar  # stiffness ratio beyond the knee, minus one [-]
        max_force: scalar  # largest magnitude of a spring's force [N]

    return SpringLawValues


@functools.cache
def spring_funcs(scalar: type, law: SpringLaw = HOOKE):
    """(spring_law_values, spring_force, spring_energy, spring_stiffness_matrix) of one precision and law.

    ``spring_law_values(inputs, world)`` loads the law's values from the input table (only those the law uses);
    the other three take them as their last argument.
    """
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    SpringLawValues = spring_law_type(scalar)

    @wp.func
    def spring_law_values(inputs: wp.array2d[scalar], world: int) -> SpringLawValues:
        """The law's values from a world's row of the input table."""
        values = SpringLawValues()
        if wp.static(law.biphasic):
            values.knee_strain = inputs[world, INPUT_BIPHASIC_STRAIN]
            values.extra_stiffness = inputs[world, INPUT_BIPHASIC_RATIO] - scalar(1.0)
        if wp.static(law.clamp_force):
            values.max_force = inputs[world, INPUT_MAX_SPRING_FORCE]
        return values

    @wp.func
    def excess(length: scalar, rest: scalar, values: SpringLawValues) -> scalar:
        """Stretch beyond the biphasic knee [m] (0 below it)."""
        return wp.max(length - rest * (scalar(1.0) + values.knee_strain), scalar(0.0))

    @wp.func
    def tension(length: scalar, rest: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """Elastic tension T(|d|) [N], positive when stretched."""
        t = ke * (length - rest)
        if wp.static(law.biphasic):
            t += values.extra_stiffness * ke * excess(length, rest, values)
        return t

    @wp.func
    def tension_slope(length: scalar, rest: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """dT/d|d| [N/m]."""
        if wp.static(law.biphasic):
            stiffer = ke * (scalar(1.0) + values.extra_stiffness)
            return wp.where(excess(length, rest, values) > scalar(0.0), stiffer, ke)
        return ke

    @wp.func
    def spring_force(
        xi: vec3, xj: vec3, vi: vec3, vj: vec3, rest: scalar, ke: scalar, kd: scalar, values: SpringLawValues
    ) -> vec3:
        """Force [N] on particle i of the spring (i, j): (T(|d|) + kd (vj - vi)·d̂) d̂, d = xj - xi, with
        T = ke (|d| - L) for Hooke's law (see ``SpringLaw``); its magnitude clamped if the law says so.

        Coincident particles (|d| below ``COINCIDENT_DISTANCE``) give a zero force, never NaN.
        """
        d = xj - xi
        length = wp.length(d)
        # Branch-free guard (the gather's unrolled slots stay free of branches): n = 0 when coincident.
        n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        magnitude = tension(length, rest, ke, values) + kd * wp.dot(vj - vi, n)
        if wp.static(law.clamp_force):
            magnitude = wp.clamp(magnitude, -values.max_force, values.max_force)
        return n * magnitude

    @wp.func
    def spring_stiffness_matrix(
        xi: vec3, xj: vec3, rest: scalar, ke: scalar, clamp: bool, values: SpringLawValues
    ) -> mat33:
        """∂f_i/∂x_j [N/m] of the spring (i, j): T'(|d|) d̂d̂ᵀ + (T/|d|)(I - d̂d̂ᵀ), for Hooke's law
        ke (d̂d̂ᵀ + (1 - L/|d|)(I - d̂d̂ᵀ)); ∂f_i/∂x_i is its negative. (The force clamp is not
        differentiated: implicit integration linearises the unclamped law.)

        With ``clamp`` the transverse term of a compressed spring (|d| < L, negative) is dropped, so the
        matrix stays positive semi-definite, as implicit integration needs. Coincident particles give 0.
        """
        d = xj - xi
        length = wp.length(d)
        inv_length = wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        n = d * inv_length
        nn = wp.outer(n, n)
        transverse = tension(length, rest, ke, values) * inv_length
        if clamp:
            transverse = wp.max(transverse, scalar(0.0))
        axial = wp.where(
            length > scalar(COINCIDENT_DISTANCE), tension_slope(length, rest, ke, values), scalar(0.0)
        )
        return axial * nn + transverse * (wp.identity(n=3, dtype=scalar) - nn)

    @wp.func
    def spring_energy(xi: vec3, xj: vec3, rest: scalar, ke: scalar, values: SpringLawValues) -> scalar:
        """Elastic energy [J] of the spring (i, j): ∫ T = ½ ke (|d| - L)² (+ the biphasic excess term)."""
        length = wp.length(xj - xi)
        stretch = length - rest
        energy = scalar(0.5) * ke * stretch * stretch
        if wp.static(law.biphasic):
            e = excess(length, rest, values)
            energy += scalar(0.5) * values.extra_stiffness * ke * e * e
        return energy

    return spring_law_values, spring_force, spring_energy, spring_stiffness_matrix


@functools.cache
def gather_springs_func(scalar: type, slots: int, law: SpringLaw):
    """Sum of the spring forces on one particle from an ELL incidence table with ``slots`` slots."""
    vec3 = vec3_type(scalar)
    _, spring_force, _, _ = spring_funcs(scalar, law)
    SpringLawValues = spring_law_type(scalar)

    @wp.func
    def gather_spring_forces(
        world: int,
        i: int,
        base: int,
        xi: vec3,
        vi: vec3,
        # Model:
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array2d[scalar],
        spring_damping: wp.array2d[scalar],
        law_values: SpringLawValues,
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
    ) -> vec3:
        """Sum of the forces [N] of all springs incident to particle i of ``world``, whose particles start
        at entry ``base`` of the state arrays."""
        stiffness_row = wp.min(world, spring_stiffness.shape[0] - 1)
        damping_row = wp.min(world, spring_damping.shape[0] - 1)
        f = vec3(scalar(0.0))
        for k in range(wp.static(slots)):
            j = base + particle_spring_neighbor[k, i]
            s = particle_spring_id[k, i]
            f += spring_force(
                xi,
                particle_q[j],
                vi,
                particle_qd[j],
                spring_rest_length[s],
                spring_stiffness[stiffness_row, s],
                spring_damping[damping_row, s],
                law_values,
            )
        return f

    return gather_spring_forces


@functools.cache
def particle_force_func(scalar: type, features: ForceFeatures):
    """The force on one particle, specialized for the scene's force terms (springs only when gathered)."""
    vec3 = vec3_type(scalar)
    gather_spring_forces = gather_springs_func(scalar, features.spring_slots, features.spring_law)
    spring_law_values, _, _, _ = spring_funcs(scalar, features.spring_law)
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
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array2d[scalar],
        spring_damping: wp.array2d[scalar],
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
    ) -> vec3:
        """Force [N] on particle i of ``world`` (entry base + i): m g - drag v + f_ext (+ gathered springs),
        magnitude clamped if the features say so (with scattered springs the clamp is a separate pass:
        ``clamp_forces_kernel``); g, drag and the limits from the world's row of the input table."""
        f = vec3(scalar(0.0))
        if wp.static(features.gravity):
            f += particle_mass[wp.min(world, particle_mass.shape[0] - 1), i] * input_vec3(inputs, world, INPUT_GRAVITY)
        if wp.static(features.drag):
            f -= inputs[world, INPUT_DRAG] * vi
        if wp.static(features.external):
            f += particle_force_ext[base + i]
        if wp.static(features.spring_slots > 0):
            f += gather_spring_forces(
                world,
                i,
                base,
                xi,
                vi,
                particle_spring_neighbor,
                particle_spring_id,
                spring_rest_length,
                spring_stiffness,
                spring_damping,
                spring_law_values(inputs, world),
                particle_q,
                particle_qd,
            )
        if wp.static(features.clamp_particle_force):
            max_force = inputs[world, INPUT_MAX_PARTICLE_FORCE]
            magnitude = wp.length(f)
            if magnitude > max_force:
                f = f * (max_force / magnitude)
        return f

    return particle_force


@functools.cache
def eval_forces_kernel(scalar: type, features: ForceFeatures):
    """Kernel writing the total force on every particle (one thread per particle of every world)."""
    vec3 = vec3_type(scalar)
    particle_force = particle_force_func(scalar, features)

    @wp.kernel(module="unique", enable_backward=False, module_options=SPRING_KERNEL_OPTIONS)
    def eval_forces(
        # Model:
        particle_count: int,
        particle_mass: wp.array2d[scalar],
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array2d[scalar],
        spring_damping: wp.array2d[scalar],
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Out:
        particle_f: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        base = p - i
        particle_f[p] = particle_force(
            world,
            i,
            base,
            particle_q[p],
            particle_qd[p],
            particle_mass,
            particle_spring_neighbor,
            particle_spring_id,
            spring_rest_length,
            spring_stiffness,
            spring_damping,
            inputs,
            particle_force_ext,
            particle_q,
            particle_qd,
        )

    return eval_forces


@functools.cache
def spring_scatter_kernel(scalar: type, law: SpringLaw):
    """Kernel adding every spring's force to its two particles (one thread per spring of every world)."""
    vec3 = vec3_type(scalar)
    spring_law_values, spring_force, _, _ = spring_funcs(scalar, law)

    @wp.kernel(module="unique", enable_backward=False, module_options=SPRING_KERNEL_OPTIONS)
    def scatter_springs(
        # Model:
        particle_count: int,
        spring_indices: wp.array[wp.vec2i],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array2d[scalar],
        spring_damping: wp.array2d[scalar],
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out:
        particle_f_in_out: wp.array[vec3],
    ):
        world, s = wp.tid()
        base = world * particle_count
        ends = spring_indices[s]
        i = base + ends[0]
        j = base + ends[1]
        f = spring_force(
            particle_q[i], particle_q[j], particle_qd[i], particle_qd[j], spring_rest_length[s],
            spring_stiffness[wp.min(world, spring_stiffness.shape[0] - 1), s], spring_damping[wp.min(world, spring_damping.shape[0] - 1), s],
            spring_law_values(inputs, world),
        )
        wp.atomic_add(particle_f_in_out, i, f)
        wp.atomic_sub(particle_f_in_out, j, f)

    return scatter_springs


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
