"""Per-particle update kernels of the integrators.

Symplectic Euler with gathered springs is one fused kernel per substep: each thread gathers its
particle's forces, updates velocity then position, and resolves the particle's contacts, reading
``state_in`` and writing ``state_out`` (so no thread sees another's update). With scattered springs the
forces come precomputed and only the update runs here. Particles with zero inverse mass are kinematic:
they move with their velocity and feel no force.
"""

import functools

import warp as wp

from .contacts import project_contacts_func
from .forces import ForceFeatures, particle_force_func
from .precision import transform_type, vec3_type

wp.set_module_options({"enable_backward": False})


@functools.cache
def symplectic_euler_funcs(scalar: type):
    """The symplectic Euler update of one particle."""
    vec3 = vec3_type(scalar)

    @wp.func
    def symplectic_euler_update(x: vec3, v: vec3, f: vec3, inv_mass: scalar, dt: scalar):
        """v' = v + h f / m, x' = x + h v' for position x [m], velocity v [m/s], force f [N]."""
        v_new = v + (dt * inv_mass) * f
        return x + dt * v_new, v_new

    return symplectic_euler_update


@functools.cache
def symplectic_euler_update_kernel(scalar: type, shape_types: tuple):
    """Symplectic Euler + contact kernel from precomputed forces (the scatter path)."""
    vec3 = vec3_type(scalar)
    transform = transform_type(scalar)
    update = symplectic_euler_funcs(scalar)
    project_contacts = project_contacts_func(scalar, shape_types)
    has_contacts = len(shape_types) > 0

    @wp.kernel(module="unique", enable_backward=False)
    def symplectic_euler_from_forces(
        # Model:
        particle_inv_mass: wp.array[scalar],
        particle_radius: wp.array[scalar],
        shape_type: wp.array[wp.int32],
        shape_transform: wp.array[transform],
        shape_size: wp.array[vec3],
        shape_friction: wp.array[scalar],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        particle_f_in: wp.array[vec3],
        dt: scalar,
        # State out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
    ):
        i = wp.tid()
        x, v = update(particle_q_in[i], particle_qd_in[i], particle_f_in[i], particle_inv_mass[i], dt)
        if wp.static(has_contacts):
            if particle_inv_mass[i] != scalar(0.0):
                x, v = project_contacts(
                    x, v, particle_radius[i], shape_type, shape_transform, shape_size, shape_friction
                )
        particle_q_out[i] = x
        particle_qd_out[i] = v

    return symplectic_euler_from_forces


@functools.cache
def symplectic_euler_kernel(scalar: type, features: ForceFeatures, shape_types: tuple):
    """Fused force + symplectic Euler + contact kernel: v' = v + h M⁻¹ f(x, v); x' = x + h v'."""
    vec3 = vec3_type(scalar)
    transform = transform_type(scalar)
    particle_force = particle_force_func(scalar, features)
    update = symplectic_euler_funcs(scalar)
    project_contacts = project_contacts_func(scalar, shape_types)
    has_contacts = len(shape_types) > 0

    @wp.kernel(module="unique", enable_backward=False)
    def symplectic_euler(
        # Model:
        particle_mass: wp.array[scalar],
        particle_inv_mass: wp.array[scalar],
        particle_radius: wp.array[scalar],
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array[scalar],
        spring_damping: wp.array[scalar],
        shape_type: wp.array[wp.int32],
        shape_transform: wp.array[transform],
        shape_size: wp.array[vec3],
        shape_friction: wp.array[scalar],
        gravity: vec3,
        drag: scalar,
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        dt: scalar,
        # State out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
    ):
        i = wp.tid()
        x = particle_q_in[i]
        v = particle_qd_in[i]
        inv_mass = particle_inv_mass[i]
        if inv_mass == scalar(0.0):
            particle_q_out[i] = x + dt * v
            particle_qd_out[i] = v
            return
        f = particle_force(
            i,
            x,
            v,
            particle_mass,
            particle_spring_neighbor,
            particle_spring_id,
            spring_rest_length,
            spring_stiffness,
            spring_damping,
            gravity,
            drag,
            particle_force_ext,
            particle_q_in,
            particle_qd_in,
        )
        x, v = update(x, v, f, inv_mass, dt)
        if wp.static(has_contacts):
            x, v = project_contacts(
                x, v, particle_radius[i], shape_type, shape_transform, shape_size, shape_friction
            )
        particle_q_out[i] = x
        particle_qd_out[i] = v

    return symplectic_euler
