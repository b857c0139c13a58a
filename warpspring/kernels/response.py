"""The contact response: a particle projected out of a shape, with restitution and Coulomb friction relative to
the surface's velocity, against one shape or against every shape in turn.

A particle of radius r touches a shape when the signed distance d of its centre
from the surface is below r; it is projected to d = r. With the surface velocity v_s, the relative
velocity's normal part v_n < 0 (approaching) becomes -e v_n when the approach is faster than two steps
of gravity (2 |g| h: a resting particle does not hop) and 0 otherwise; the tangential part v_t stops when
|v_t| ≤ μ_s j_n (static friction; j_n = (1 + e)|v_n| the normal change) and otherwise shrinks by μ_k j_n
(kinetic friction; μ_s = μ_k unless set). The position takes the
tangential change too, h Δv_t, so a particle that sticks moves exactly with the surface — on a moving
platform it keeps its place — and one that slides travels h Σ v.

The surface velocity is the displacement of the surface point over the step: the point at x at the
step's end was at X₀ X₁⁻¹ x at its start, so v_s = (x - X₀ X₁⁻¹ x) / h.
"""

import functools

import warp as wp

from .inputs import INPUT_GRAVITY
from .precision import vec3_type
from .shapes import ContactFeatures, shapes_type, surface_funcs
from .swept import shape_crossing_func

wp.set_module_options({"enable_backward": False})


@functools.cache
def coulomb_response_func(scalar: type):
    """The contact response with static and kinetic friction (see the module docstring)."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)

    @wp.func
    def coulomb_response(
        x: vec3, v: vec3, radius: scalar, distance: scalar, normal: vec3, surface_velocity: vec3,
        static_friction: scalar, kinetic_friction: scalar, restitution: scalar, bounce_speed: scalar, dt: scalar,
    ):
        """Project a particle out of a shape, with restitution and Coulomb friction relative to the surface: the
        relative tangential velocity v_t stops when |v_t| ≤ μ_s j_n, and otherwise loses μ_k j_n of its length
        (j_n = (1 + e)|v_n| the normal velocity change).

        Args:
            x: particle position [m]; v: particle velocity [m/s]; radius: particle radius [m];
            distance: signed distance of x from the surface [m]; normal: outward unit normal (world);
            surface_velocity: the surface's velocity at x [m/s]; static_friction: μ_s [-];
            kinetic_friction: μ_k [-]; restitution: e [-]; bounce_speed: approach speed [m/s] above which e
            applies; dt: the step that produced x and v [s].
        """
        penetration = radius - distance
        if penetration <= zero:
            return x, v
        x_out = x + normal * penetration
        relative = v - surface_velocity
        vn = wp.dot(relative, normal)
        if vn >= zero:
            return x_out, v
        vt = relative - normal * vn
        bounce = wp.where(-vn > bounce_speed, restitution, zero)
        vt_len = wp.length(vt)
        vt_out = vec3(zero)
        if vt_len + static_friction * (scalar(1.0) + bounce) * vn > zero:  # |v_t| > μ_s j_n: it slides
            slip = vt_len + kinetic_friction * (scalar(1.0) + bounce) * vn  # tangential speed left after μ_k j_n
            if slip > zero:
                vt_out = vt * (slip / vt_len)
        v_out = surface_velocity + vt_out - normal * (bounce * vn)
        return x_out + dt * (vt_out - vt), v_out

    return coulomb_response


@functools.cache
def contact_response_func(scalar: type):
    """The contact response with one friction coefficient (static = kinetic)."""
    vec3 = vec3_type(scalar)
    coulomb_response = coulomb_response_func(scalar)

    @wp.func
    def contact_response(
        x: vec3, v: vec3, radius: scalar, distance: scalar, normal: vec3, surface_velocity: vec3,
        friction: scalar, restitution: scalar, bounce_speed: scalar, dt: scalar,
    ):
        """Project a particle out of a shape, with restitution and Coulomb friction relative to the surface.

        Args:
            x: particle position [m]; v: particle velocity [m/s]; radius: particle radius [m];
            distance: signed distance of x from the surface [m]; normal: outward unit normal (world);
            surface_velocity: the surface's velocity at x [m/s]; friction: Coulomb μ [-] (static = kinetic);
            restitution: e [-]; bounce_speed: approach speed [m/s] above which e applies;
            dt: the step that produced x and v [s].
        """
        return coulomb_response(x, v, radius, distance, normal, surface_velocity, friction, friction, restitution,
                                bounce_speed, dt)

    return contact_response


@functools.cache
def shape_contact_func(scalar: type, features: ContactFeatures):
    """The response against one shape, specialised for the scene's kinds."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    shape_surface, _ = surface_funcs(scalar, features)
    shape_crossing = shape_crossing_func(scalar, features)
    coulomb_response = coulomb_response_func(scalar)
    zero = scalar(0.0)

    @wp.func
    def shape_contact(
        shapes: Shapes, s: int, world: int, p_index: int, x0: vec3, x: vec3, v: vec3, radius: scalar,
        bounce_speed: scalar, dt: scalar,
    ):
        """Resolve the contact of one particle (x [m], v [m/s], radius [m]; at x0 [m] at the step's start) with
        shape s after a step dt [s]. A path that entered the shape where its end is out of reach or on the far
        side (the closest point's normal against the entered face's) is put back on the side it came from; the
        tangential change then moves it only over the part of the step after it touched (so a particle that
        sticks stays where it hit). Any other contact is the closest point's, as without sweeping."""
        distance, normal, surface_velocity = shape_surface(shapes, s, world, p_index, x)
        contact_dt = dt
        if wp.static(features.swept):
            crossed, crossed_distance, crossed_normal, entry = shape_crossing(shapes, s, world, p_index, x0, x, radius)
            if crossed and (distance >= radius or wp.dot(normal, crossed_normal) < zero):
                distance = crossed_distance
                normal = crossed_normal
                contact_dt = (scalar(1.0) - entry) * dt
        if wp.static(features.moving):
            row = wp.min(world, shapes.transform_end.shape[0] - 1)
            X0 = shapes.transform_start[row, s]
            X1 = shapes.transform_end[row, s]
            surface_velocity = surface_velocity + (
                x - wp.transform_point(X0, wp.transform_point(wp.transform_inverse(X1), x))) / dt
        return coulomb_response(x, v, radius, distance, normal, surface_velocity, shapes.static_friction[s],
                                shapes.friction[s], shapes.restitution[s], bounce_speed, contact_dt)

    return shape_contact


@functools.cache
def project_all_func(scalar: type, features: ContactFeatures):
    """Contact response of one particle against every shape, in shape order (the fused path)."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    shape_contact = shape_contact_func(scalar, features)

    @wp.func
    def bounce_speed(world: int, inputs: wp.array2d[scalar], dt: scalar) -> scalar:
        """Approach speed [m/s] above which restitution applies: two steps of the world's gravity."""
        g = vec3(inputs[world, INPUT_GRAVITY], inputs[world, INPUT_GRAVITY + 1], inputs[world, INPUT_GRAVITY + 2])
        return scalar(2.0) * wp.length(g) * dt

    @wp.func
    def project_contacts_all(
        world: int, p: int, x: vec3, v: vec3, radius: scalar, dt: scalar, shapes: Shapes, inputs: wp.array2d[scalar]
    ):
        """Resolve the contacts of state entry p of ``world`` (position x [m], velocity v [m/s], radius [m])
        with every shape after a step of ``dt`` [s]; its path over the step is x - dt v → x."""
        speed = bounce_speed(world, inputs, dt)
        x0 = x - dt * v
        for s in range(shapes.kind.shape[0]):
            x, v = shape_contact(shapes, s, world, p, x0, x, v, radius, speed, dt)
        return x, v

    return bounce_speed, project_contacts_all
