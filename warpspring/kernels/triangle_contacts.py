"""Cloth triangles against colliders: a sphere smaller than the particle spacing, or a thin capsule (a pole),
cannot slip between particles.

Particle contacts (``contacts.py``) keep every vertex out of the colliders; a shape smaller than a triangle
can still pass through its interior. For each cloth triangle (a, b, c), of thickness r (the mean of its
vertices' radii), and each sphere or capsule, the closest points of the triangle, p = w_a a + w_b b + w_c c,
and of the shape's core, q (a sphere's centre, a capsule's segment), give the penetration
δ = r + R + thickness - |p - q| along n = (p - q) / |p - q| (the triangle's normal, turned towards the side
it came from, when the core touches the triangle). Moving each vertex by w_i δ n / Σ w_j² moves p by exactly
δ n with the least total displacement (the barycentric weighting of Bridson, Fedkiw and Anderson 2002).

Two launches, no float atomics: :func:`triangle_push_kernel` (per triangle of every world) writes each
corner's correction; :func:`triangle_gather_kernel` (per particle) reads those of its incident triangles from
a CSR table, moves the particle by their mean, and removes its velocity into the shape along it (inelastic,
frictionless). Only spheres and capsules are tested (planes, boxes and meshes are larger than a triangle's
hole, their vertex contacts suffice, and box and mesh against triangle is not implemented).
"""

import functools

import warp as wp

from .shapes import SHAPE_CAPSULE, SHAPE_SPHERE, ContactFeatures, shapes_type
from .flatten import flat_kernel
from .kinematics import is_kinematic
from .precision import vec3_type
from .selfcontact import geometry_funcs
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})

#: The kinds a triangle is tested against.
TRIANGLE_KINDS = (SHAPE_SPHERE, SHAPE_CAPSULE)


@functools.cache
def triangle_funcs(scalar: type):
    """Closest points of a triangle to a point and to a segment (Ericson, Real-Time Collision Detection, 5.1)."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)
    one = scalar(1.0)

    triangle_closest, edge_closest = geometry_funcs(scalar)  # the closest points self-collision uses

    @wp.func
    def closest_on_triangle(p: vec3, a: vec3, b: vec3, c: vec3):
        """The point of triangle (a, b, c) nearest p, and its barycentric weights (w_a, w_b, w_c)."""
        w = triangle_closest(p, a, b, c)
        return w[0] * a + w[1] * b + w[2] * c, w

    @wp.func
    def closest_segments(p1: vec3, q1: vec3, p2: vec3, q2: vec3):
        """The parameters s, t ∈ [0, 1] of the closest points p1 + s (q1 - p1) and p2 + t (q2 - p2)."""
        st = edge_closest(p1, q1, p2, q2)
        return st[0], st[1]

    @wp.func
    def closest_to_segment(p0: vec3, p1: vec3, a: vec3, b: vec3, c: vec3):
        """The closest points of triangle (a, b, c) and segment p0 → p1: the triangle's point, its weights, and
        the segment's point (equal where the segment crosses the triangle)."""
        # Crossing (Möller–Trumbore on the segment).
        d = p1 - p0
        e1 = b - a
        e2 = c - a
        h = wp.cross(d, e2)
        det = wp.dot(e1, h)
        if wp.abs(det) > zero:
            f = one / det
            start = p0 - a
            u = f * wp.dot(start, h)
            qv = wp.cross(start, e1)
            v = f * wp.dot(d, qv)
            t = f * wp.dot(e2, qv)
            if u >= zero and v >= zero and u + v <= one and t >= zero and t <= one:
                hit = p0 + t * d
                return hit, vec3(one - u - v, u, v), hit
        # Otherwise the nearest of: the segment's ends to the triangle, the triangle's edges to the segment.
        best_p, best_w = closest_on_triangle(p0, a, b, c)
        best_q = p0
        best = wp.length_sq(best_p - best_q)
        end_p, end_w = closest_on_triangle(p1, a, b, c)
        if wp.length_sq(end_p - p1) < best:
            best_p = end_p
            best_w = end_w
            best_q = p1
            best = wp.length_sq(end_p - p1)
        s, t = closest_segments(a, b, p0, p1)
        edge_p = a + s * (b - a)
        if wp.length_sq(edge_p - (p0 + t * d)) < best:
            best_p = edge_p
            best_w = vec3(one - s, s, zero)
            best_q = p0 + t * d
            best = wp.length_sq(best_p - best_q)
        s, t = closest_segments(b, c, p0, p1)
        edge_p = b + s * (c - b)
        if wp.length_sq(edge_p - (p0 + t * d)) < best:
            best_p = edge_p
            best_w = vec3(zero, one - s, s)
            best_q = p0 + t * d
            best = wp.length_sq(best_p - best_q)
        s, t = closest_segments(c, a, p0, p1)
        edge_p = c + s * (a - c)
        if wp.length_sq(edge_p - (p0 + t * d)) < best:
            best_p = edge_p
            best_w = vec3(s, zero, one - s)
            best_q = p0 + t * d
        return best_p, best_w, best_q

    return closest_on_triangle, closest_segments, closest_to_segment


@functools.cache
def triangle_push_kernel(scalar: type, features: ContactFeatures):
    """Kernel writing, for every triangle of every world, its corners' corrections out of the spheres and
    capsules (see the module docstring). Launch over world_count · tri_count."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    closest_on_triangle, _, closest_to_segment = triangle_funcs(scalar)
    kinds = features.kinds
    zero = scalar(0.0)

    @flat_kernel(module="unique", enable_backward=False)
    def triangle_push(
        # Model:
        particle_count: int,
        tri_indices: wp.array2d[wp.int32],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        # State in:
        particle_q: wp.array[vec3],
        # Out:
        corner_push_out: wp.array[vec3],
    ):
        k = wp.tid()
        tri_count = tri_indices.shape[0]
        world = k // tri_count
        t = k - world * tri_count
        base = world * particle_count
        i = tri_indices[t, 0]
        j = tri_indices[t, 1]
        l = tri_indices[t, 2]
        thickness = (particle_radius[i] + particle_radius[j] + particle_radius[l]) / scalar(3.0)
        row = wp.min(world, shapes.transform_end.shape[0] - 1)
        push_a = vec3(zero)
        push_b = vec3(zero)
        push_c = vec3(zero)
        for s in range(shapes.kind.shape[0]):
            kind = shapes.kind[s]
            if kind == SHAPE_SPHERE or kind == SHAPE_CAPSULE:
                X = shapes.transform_end[row, s]
                inverse = wp.transform_inverse(X)
                a = wp.transform_point(inverse, particle_q[base + i])
                b = wp.transform_point(inverse, particle_q[base + j])
                c = wp.transform_point(inverse, particle_q[base + l])
                size = shapes.size[s]
                p = vec3(zero)
                w = vec3(zero)
                q = vec3(zero)
                if wp.static(SHAPE_SPHERE in kinds):
                    if kind == SHAPE_SPHERE:
                        p, w = closest_on_triangle(vec3(zero), a, b, c)
                        q = vec3(zero)
                if wp.static(SHAPE_CAPSULE in kinds):
                    if kind == SHAPE_CAPSULE:
                        p, w, q = closest_to_segment(vec3(zero, zero, -size[1]), vec3(zero, zero, size[1]), a, b, c)
                offset = p - q
                length = wp.length(offset)
                depth = thickness + size[0] + shapes.thickness[s] - length
                if depth > zero:
                    n = wp.cross(b - a, c - a)  # the core touches the triangle: out along its normal
                    if length > zero:
                        n = offset
                    elif wp.dot(n, a) < zero:  # towards the side of the triangle's plane the core is not on
                        n = -n
                    n = wp.transform_vector(X, wp.normalize(n)) * (depth / wp.dot(w, w))
                    push_a += w[0] * n
                    push_b += w[1] * n
                    push_c += w[2] * n
        corner_push_out[3 * k + 0] = push_a
        corner_push_out[3 * k + 1] = push_b
        corner_push_out[3 * k + 2] = push_c

    return triangle_push


@functools.cache
def triangle_gather_kernel(scalar: type):
    """Kernel moving every dynamic particle by the mean of its incident triangles' corner corrections (those
    not zero), and removing its velocity into the shape along that correction. Launch over the state's
    entries."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)

    @wp.kernel(module="unique", enable_backward=False)
    def triangle_gather(
        # Model:
        particle_count: int,
        tri_count: int,
        particle_flags: wp.array[wp.int32],
        corner_start: wp.array[wp.int32],  # [particle_count + 1], CSR offsets into corner_index
        corner_index: wp.array[wp.int32],  # 3 · triangle + corner of each particle's incident corners
        # In:
        corner_push: wp.array[vec3],
        # State in/out:
        particle_q_in_out: wp.array[vec3],
        particle_qd_in_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if is_kinematic(particle_flags[p]):
            return
        total = vec3(zero)
        count = int(0)
        offset = 3 * world * tri_count
        for e in range(corner_start[i], corner_start[i + 1]):
            push = corner_push[offset + corner_index[e]]
            if wp.length_sq(push) > zero:
                total += push
                count += 1
        if count > 0:
            delta = total / scalar(count)
            particle_q_in_out[p] = particle_q_in_out[p] + delta
            n = wp.normalize(delta)
            v = particle_qd_in_out[p]
            vn = wp.dot(v, n)
            if vn < zero:
                particle_qd_in_out[p] = v - vn * n

    return triangle_gather
