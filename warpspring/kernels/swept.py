"""Paths over a step: a particle's path swept against thin shapes, and the shapes' own motion.

**Swept paths** (``ContactFeatures.swept``). A particle that moved h v in a step may have passed through a
thin shape. Its path x0 = x - h v → x (x0 against the shape's frame at the step's start, x against the one
at its end: the path relative to the shape) is tested for entering a sphere, a box (slab test) or a capsule
(cylinder and caps), each grown by the particle's radius and the thickness (a path that grazes it within
the radius is caught too), or a mesh (a ray cast on its BVH against the surface itself; any face of a
two-sided mesh, a face's front otherwise); a path that entered is resolved against the plane of the
entered face, on the side it came from, whatever the closest point says (through a thin box the closest
face is the far one). For symplectic Euler x0 is exactly the step's start (and strain limiting, which
turns Δx into Δv = Δx / h, keeps it); for the other integrators it is the start of the straight path the
final velocity implies. A plane is a half-space: nothing passes it unseen.

**Motion.** ``shape_motion_kernel`` writes the frames of animated shapes at a step's start and end from
keyframe tracks: the shape's rest frame translated by T(t) and turned by the rotation vector φ(t) [rad]
about its own origin, R(φ(t)) R₀ (as pin groups move, ``kinematics.py``).
"""

import functools

import warp as wp

from .flatten import flat_kernel
from .mesh_colliders import mesh_cache_funcs, mesh_funcs
from .precision import transform_type, vec3_type
from .shapes import SHAPE_BOX, SHAPE_CAPSULE, SHAPE_MESH, SHAPE_SPHERE, ContactFeatures, shapes_type
from .tracks import Tracks, track_sample

wp.set_module_options({"enable_backward": False})

#: The kinds a particle's path is swept against (a plane is a half-space: nothing passes it unseen).
SWEPT_KINDS = (SHAPE_SPHERE, SHAPE_BOX, SHAPE_CAPSULE, SHAPE_MESH)


@functools.cache
def sweep_funcs(scalar: type):
    """Where a particle's path p0 → p1 (in a shape's frame) first enters a sphere, a box or a capsule that p0 is
    outside."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)
    one = scalar(1.0)

    @wp.func
    def sphere_entry(p0: vec3, d: vec3, radius: scalar) -> scalar:
        """The fraction t ∈ [0, 1] of the path p0 → p0 + d at which it enters the sphere of ``radius`` [m] at the
        origin from outside, or -1."""
        a = wp.dot(d, d)
        b = wp.dot(p0, d)
        c = wp.dot(p0, p0) - radius * radius
        disc = b * b - a * c
        if c > zero and a > zero and disc >= zero:
            t = (-b - wp.sqrt(disc)) / a
            if t >= zero and t <= one:
                return t
        return -one

    @wp.func
    def sphere_crossing(p0: vec3, p1: vec3, radius: scalar):
        """Whether p0 → p1 enters the sphere of ``radius`` [m] at the origin, the entry point and its normal."""
        t = sphere_entry(p0, p1 - p0, radius)
        if t >= zero:
            hit = p0 + t * (p1 - p0)
            return True, hit, wp.normalize(hit)
        return False, p1, vec3(zero, zero, one)

    @wp.func
    def capsule_crossing(p0: vec3, p1: vec3, radius: scalar, half_height: scalar):
        """Whether p0 → p1 enters the capsule of ``radius`` [m] around the segment z ∈ [-half_height,
        half_height] from outside: its side (a cylinder) or a cap (a sphere), whichever comes first; the entry
        point and its outward normal."""
        d = p1 - p0
        best = scalar(2.0)
        normal = vec3(zero, zero, one)
        a = d[0] * d[0] + d[1] * d[1]
        b = p0[0] * d[0] + p0[1] * d[1]
        c = p0[0] * p0[0] + p0[1] * p0[1] - radius * radius
        disc = b * b - a * c
        if c > zero and a > zero and disc >= zero:
            t = (-b - wp.sqrt(disc)) / a
            z = p0[2] + t * d[2]
            if t >= zero and t <= one and z >= -half_height and z <= half_height:
                best = t
                normal = vec3(p0[0] + t * d[0], p0[1] + t * d[1], zero) / radius
        for k in range(2):
            cap = vec3(zero, zero, wp.where(k == 0, half_height, -half_height))
            t = sphere_entry(p0 - cap, d, radius)
            if t >= zero and t < best:
                best = t
                normal = wp.normalize(p0 + t * d - cap)
        if best <= one:
            return True, p0 + best * d, normal
        return False, p1, vec3(zero, zero, one)

    @wp.func
    def box_crossing(p0: vec3, p1: vec3, half: vec3):
        """Whether p0 → p1 enters the axis-aligned box of half extents ``half`` [m] at the origin from outside
        (slab test), the entry point and the entry face's outward normal."""
        d = p1 - p0
        enter = zero
        leave = one
        axis = int(-1)
        for k in range(3):
            if wp.abs(d[k]) > zero:
                ta = (-half[k] - p0[k]) / d[k]
                tb = (half[k] - p0[k]) / d[k]
                if wp.min(ta, tb) > enter:
                    enter = wp.min(ta, tb)
                    axis = k
                leave = wp.min(leave, wp.max(ta, tb))
            elif wp.abs(p0[k]) > half[k]:
                leave = -one  # parallel to this slab and outside it: no entry
        if axis >= 0 and enter <= leave:
            n = vec3(zero)
            n[axis] = wp.where(d[axis] > zero, scalar(-1.0), scalar(1.0))
            return True, p0 + enter * d, n
        return False, p1, vec3(zero, zero, one)

    @wp.func
    def box_distance(p: vec3, half: vec3) -> scalar:
        """The distance [m] of p from the box of half extents ``half`` at the origin (0 inside)."""
        q = vec3(wp.max(wp.abs(p[0]) - half[0], zero), wp.max(wp.abs(p[1]) - half[1], zero),
                 wp.max(wp.abs(p[2]) - half[2], zero))
        return wp.length(q)

    @wp.func
    def rounded_box_crossing(p0: vec3, p1: vec3, half: vec3, grow: scalar):
        """Whether p0 → p1 enters, from outside, the points within ``grow`` [m] of the box of half extents
        ``half`` (what a particle of radius ``grow`` touches: faces moved out by ``grow``, edges and corners
        rounded), the entry point and its outward normal. The slab test of the square-cornered grown box gives the
        entry where it lands on a face; where it lands in an edge's or a corner's square region, which a sphere
        does not reach, the path's distance from the box (convex along it) is searched for its first point at
        ``grow``, if it has one (a square corner held a particle sliding off a table's edge until its centre was
        a radius past it, where the rounded one lets it fall)."""
        crossed, hit, normal = box_crossing(p0, p1, half + vec3(grow, grow, grow))
        if not crossed:
            return crossed, hit, normal
        out = int(0)
        for k in range(3):
            if wp.abs(hit[k]) > half[k] + grow * scalar(1.0e-6) and normal[k] == zero:
                out += 1
        if out == 0:
            return crossed, hit, normal  # on a face
        d = p1 - p0
        length = wp.length(d)
        start = wp.length(hit - p0) / wp.max(length, scalar(1.0e-30))
        lo = start
        hi = one
        for _ in range(48):  # the distance's minimum along [start, 1] (convex): ternary search
            a = lo + (hi - lo) / scalar(3.0)
            b = hi - (hi - lo) / scalar(3.0)
            if box_distance(p0 + a * d, half) <= box_distance(p0 + b * d, half):
                hi = b
            else:
                lo = a
        nearest = scalar(0.5) * (lo + hi)
        if box_distance(p0 + nearest * d, half) > grow:
            return False, p1, vec3(zero, zero, one)
        lo = start
        hi = nearest
        for _ in range(48):  # its first point at ``grow``: bisection (outside at ``start``, within at ``nearest``)
            m = scalar(0.5) * (lo + hi)
            if box_distance(p0 + m * d, half) > grow:
                lo = m
            else:
                hi = m
        point = p0 + hi * d
        core = vec3(wp.clamp(point[0], -half[0], half[0]), wp.clamp(point[1], -half[1], half[1]),
                    wp.clamp(point[2], -half[2], half[2]))
        away = point - core
        if wp.length(away) > zero:
            normal = wp.normalize(away)
        return True, point, normal

    return sphere_crossing, rounded_box_crossing, capsule_crossing


@functools.cache
def shape_crossing_func(scalar: type, features: ContactFeatures):
    """Whether a particle's path over the step entered one shape, specialised for the scene's kinds."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    _, mesh_crossing = mesh_funcs(scalar)
    _, mesh_crossing_cached, _, _ = mesh_cache_funcs(scalar)
    sphere_crossing, box_crossing, capsule_crossing = sweep_funcs(scalar)
    kinds = features.kinds
    zero = scalar(0.0)
    zero32 = wp.float32(0.0)

    @wp.func
    def shape_crossing(shapes: Shapes, s: int, world: int, p_index: int, x0: vec3, x: vec3, pad: scalar):
        """Whether the path from x0 (at the step's start, against the shape's start frame) to x (its end frame)
        entered shape s; if so, x's signed distance [m] from the plane of the entered face less the thickness
        (the response's distance), that face's normal on x0's side (world), and the fraction of the step at
        which the path entered. Spheres, boxes and capsules
        are grown by ``pad`` [m] (the particle's radius) and the thickness, so a path that only grazes them
        within the radius is caught too; a mesh is a ray cast against its surface."""
        row = wp.min(world, shapes.transform_end.shape[0] - 1)
        X1 = shapes.transform_end[row, s]
        p0 = wp.transform_point(wp.transform_inverse(shapes.transform_start[row, s]), x0)
        p1 = wp.transform_point(wp.transform_inverse(X1), x)
        kind = shapes.kind[s]
        size = shapes.size[s]
        grow = pad + shapes.thickness[s]
        crossed = bool(False)
        hit = p1
        normal = vec3(zero, zero, scalar(1.0))
        offset = -shapes.thickness[s]  # the entered surface's distance from the response's zero
        if wp.static(SHAPE_SPHERE in kinds):
            if kind == SHAPE_SPHERE:
                crossed, hit, normal = sphere_crossing(p0, p1, size[0] + grow)
                offset = pad
        if wp.static(SHAPE_BOX in kinds):
            if kind == SHAPE_BOX:
                crossed, hit, normal = box_crossing(p0, p1, size, grow)
                offset = pad
        if wp.static(SHAPE_CAPSULE in kinds):
            if kind == SHAPE_CAPSULE:
                crossed, hit, normal = capsule_crossing(p0, p1, size[0] + grow, size[1])
                offset = pad
        if wp.static(SHAPE_MESH in kinds):
            if kind == SHAPE_MESH:
                if p_index >= 0 and shapes.cache.slot[s] >= 0 and shapes.cache.margin[s] >= zero32:
                    crossed, hit, normal = mesh_crossing_cached(shapes.mesh[s], shapes.cache, s, shapes.sides[s],
                                                                shapes.lower[s], shapes.upper[s], p_index, p0, p1)
                else:
                    crossed, hit, normal = mesh_crossing(shapes.mesh[s], shapes.sides[s], p0, p1)
        d = p1 - p0
        entry = wp.where(wp.dot(d, d) > zero, wp.clamp(wp.dot(hit - p0, d) / wp.dot(d, d), zero, scalar(1.0)), zero)
        return crossed, wp.dot(p1 - hit, normal) + offset, wp.transform_vector(X1, normal), entry

    return shape_crossing


@wp.func
def rotation_vector_quat(phi: wp.vec3d) -> wp.quatd:
    """The unit quaternion of the rotation vector φ [rad] (axis × angle)."""
    angle = wp.length(phi)
    if angle < wp.float64(1.0e-12):
        return wp.quatd(phi[0] * wp.float64(0.5), phi[1] * wp.float64(0.5), phi[2] * wp.float64(0.5), wp.float64(1.0))
    return wp.quat_from_axis_angle(phi / angle, angle)


@wp.func
def shape_frame(
    tracks: Tracks, rest: wp.transformd, translation: int, rotation: int, t: wp.float64
) -> wp.transformd:
    """A shape's frame at time t: the rest frame turned by R(φ(t)) about its origin and moved by T(t)."""
    position = wp.transform_get_translation(rest)
    orientation = wp.transform_get_rotation(rest)
    if rotation >= 0:
        phi, phi_rate = track_sample(tracks, rotation, t)
        orientation = wp.normalize(rotation_vector_quat(phi) * orientation)
    if translation >= 0:
        offset, offset_rate = track_sample(tracks, translation, t)
        position = position + offset
    return wp.transformd(position, orientation)


@functools.cache
def shape_motion_func(scalar: type):
    """``move_shape(world, s, rest, translation_track, rotation_track, tracks, t1, dt, shapes_out)``: shape s's
    frames in world ``world`` at the start t₁ - dt and the end t₁ [s] of a step (``shape_motion_kernel``'s, for a
    kernel that steps a world's substeps itself)."""
    vec3 = vec3_type(scalar)
    transform = transform_type(scalar)
    quat = wp.types.quaternion(dtype=scalar)
    Shapes = shapes_type(scalar)

    @wp.func
    def rounded(X: wp.transformd) -> transform:
        return transform(vec3(wp.transform_get_translation(X)), quat(wp.transform_get_rotation(X)))

    @wp.func
    def move_shape(world: int, s: int, rest: wp.array[wp.transformd], translation_track: wp.array[wp.int32],
                   rotation_track: wp.array[wp.int32], tracks: Tracks, t1: wp.float64, dt: wp.float64,
                   shapes_out: Shapes):
        X0 = shape_frame(tracks, rest[s], translation_track[s], rotation_track[s], t1 - dt)
        X1 = shape_frame(tracks, rest[s], translation_track[s], rotation_track[s], t1)
        shapes_out.transform_start[world, s] = rounded(X0)
        shapes_out.transform_end[world, s] = rounded(X1)

    return move_shape


@functools.cache
def shape_motion_kernel(scalar: type):
    """Kernel writing every shape's frame at the start t₁ - dt and end t₁ = ``time[world]`` + ``ahead`` [s] of
    a step (each world at its own time). Launch over [world_count, shape_count]; shapes without tracks keep
    their rest frame."""
    Shapes = shapes_type(scalar)
    move_shape = shape_motion_func(scalar)

    @flat_kernel(module="unique", enable_backward=False)
    def shape_motion(
        # Model:
        rest: wp.array[wp.transformd],
        translation_track: wp.array[wp.int32],
        rotation_track: wp.array[wp.int32],
        tracks: Tracks,
        # State in:
        time: wp.array[wp.float64],
        dt: wp.float64,
        ahead: wp.float64,
        # Out (the shapes' frames):
        shapes_out: Shapes,
    ):
        world, s = wp.tid()
        move_shape(world, s, rest, translation_track, rotation_track, tracks, time[world] + ahead, dt, shapes_out)

    return shape_motion
