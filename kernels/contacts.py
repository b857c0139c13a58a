"""Particle-collider contact: position projection with inelastic normal response and Coulomb friction.

A particle of radius r touches a collider when the signed distance of its centre to the collider's
surface is below r. The contact pass, run after a step of length h, projects it back onto the surface
(no interpenetration, also at rest), removes the approaching normal velocity and reduces the tangential
velocity by at most μ·|Δv_n| (Coulomb friction as an impulse; it sticks when the tangential speed is
smaller). The position takes the same tangential change, h·Δv_t, so that it stays x_prev + h·v for the
velocity friction leaves: a particle that sticks does not move, and one that slides travels exactly
h·Σv (for symplectic Euler).

Colliders are static rigid shapes stored as a table (type, transform, size, friction). A kernel is
specialized for the set of shape types the scene holds; new types add a signed-distance function here
and a branch in ``shape_distance``.
"""

import functools

import warp as wp

from .kinematics import is_kinematic
from .precision import transform_type, vec3_type
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})

#: Collider shape types (values of ``Model.shape_type``).
SHAPE_PLANE = 0
SHAPE_SPHERE = 1
SHAPE_NAMES = {SHAPE_PLANE: "plane", SHAPE_SPHERE: "sphere"}


@functools.cache
def contact_funcs(scalar: type):
    """Signed distances and the contact response of one precision."""
    vec3 = vec3_type(scalar)

    @wp.func
    def plane_distance(p: vec3):
        """Signed distance [m] of a local point to the plane z = 0, and the plane's normal +z."""
        return p[2], vec3(scalar(0.0), scalar(0.0), scalar(1.0))

    @wp.func
    def sphere_distance(p: vec3, radius: scalar):
        """Signed distance [m] of a local point to a sphere at the origin, and the outward normal."""
        length = wp.length(p)
        if length > scalar(0.0):
            return length - radius, p / length
        # At the centre every direction is outward: push along +z.
        return -radius, vec3(scalar(0.0), scalar(0.0), scalar(1.0))

    @wp.func
    def contact_response(
        x: vec3, v: vec3, radius: scalar, distance: scalar, normal: vec3, friction: scalar, dt: scalar
    ):
        """Project a particle out of a collider and apply inelastic, Coulomb-frictional velocity response.

        Args:
            x: particle position [m]; v: particle velocity [m/s]; radius: particle radius [m];
            distance: signed distance of x to the surface [m]; normal: outward unit normal;
            friction: Coulomb coefficient μ [-]; dt: the step that produced x and v [s].
        """
        penetration = radius - distance
        if penetration <= scalar(0.0):
            return x, v
        x_out = x + normal * penetration
        vn = wp.dot(v, normal)
        if vn >= scalar(0.0):
            return x_out, v
        vt = v - normal * vn
        vt_len = wp.length(vt)
        slip = vt_len + friction * vn  # tangential speed left after the friction impulse μ|vn|
        v_out = vec3(scalar(0.0))
        if slip > scalar(0.0):
            v_out = vt * (slip / vt_len)
        return x_out + dt * (v_out - vt), v_out

    return plane_distance, sphere_distance, contact_response


@functools.cache
def project_contacts_func(scalar: type, shape_types: tuple):
    """Contact projection of one particle against every collider, specialized for the scene's shape types."""
    vec3 = vec3_type(scalar)
    transform = transform_type(scalar)
    plane_distance, sphere_distance, contact_response = contact_funcs(scalar)
    has_plane = SHAPE_PLANE in shape_types
    has_sphere = SHAPE_SPHERE in shape_types

    @wp.func
    def project_contacts(
        x: vec3,
        v: vec3,
        radius: scalar,
        dt: scalar,
        # Model:
        shape_type: wp.array[wp.int32],
        shape_transform: wp.array[transform],
        shape_size: wp.array[vec3],
        shape_friction: wp.array[scalar],
    ):
        """Resolve the contacts of one particle (position x [m], velocity v [m/s], radius [m]) after a
        step of ``dt`` [s]."""
        for s in range(shape_type.shape[0]):
            X = shape_transform[s]
            p = wp.transform_point(wp.transform_inverse(X), x)
            kind = shape_type[s]
            distance = scalar(1.0e30)
            normal = vec3(scalar(0.0), scalar(0.0), scalar(1.0))
            if wp.static(has_plane):
                if kind == SHAPE_PLANE:
                    distance, normal = plane_distance(p)
            if wp.static(has_sphere):
                if kind == SHAPE_SPHERE:
                    distance, normal = sphere_distance(p, shape_size[s][0])
            x, v = contact_response(x, v, radius, distance, wp.transform_vector(X, normal), shape_friction[s], dt)
        return x, v

    return project_contacts


@functools.cache
def project_contacts_kernel(scalar: type, shape_types: tuple):
    """Kernel applying the contact projection to every dynamic (not kinematic) particle of a state, in place
    (the colliders are shared by every world: each world has the same scene around it)."""
    vec3 = vec3_type(scalar)
    transform = transform_type(scalar)
    project_contacts = project_contacts_func(scalar, shape_types)

    @wp.kernel(module="unique", enable_backward=False)
    def project(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_radius: wp.array[scalar],
        shape_type: wp.array[wp.int32],
        shape_transform: wp.array[transform],
        shape_size: wp.array[vec3],
        shape_friction: wp.array[scalar],
        dt: scalar,
        # State in/out:
        particle_q_in_out: wp.array[vec3],
        particle_qd_in_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if is_kinematic(particle_flags[p]):
            return
        x, v = project_contacts(
            particle_q_in_out[p],
            particle_qd_in_out[p],
            particle_radius[i],
            dt,
            shape_type,
            shape_transform,
            shape_size,
            shape_friction,
        )
        particle_q_in_out[p] = x
        particle_qd_in_out[p] = v

    return project
