"""Mesh colliders (``SHAPE_MESH``): how they tell inside from outside, their distance and path crossing by Warp's
own queries, their pseudo-normals, and the per-particle candidate cache with exact closest points.

A mesh collider is a ``wp.Mesh`` BVH in the shape's frame. A particle's contacts with one come from
:func:`mesh_cache_funcs`: the nearest triangle within the contact reach by an exact closest point per
triangle, signed by the pseudo-normal of its closest feature, from a per-particle candidate cache refreshed by
a BVH query only when the particle moved more than a margin (the cache changes the work, never the answer;
the argument is in its docstring). Warp's own queries (:func:`mesh_funcs`) serve points that are no
particle's (``p_index`` = -1), winding-number meshes, and meshes switched to them: the closest point
within the mesh's depth (``size[0]``; a query costs with the distance it may search: for points anywhere
around a 5120-triangle sphere, 40× more within 3 m than within 5 cm on the CPU, ``bench/mesh_queries.py``),
signed by the closest feature's angle-weighted pseudo-normal (closed and one-sided meshes; exact for a
watertight mesh) or the winding number (closed meshes that ask for it: robust to holes, 5.7× the cost near
the surface), or not at all
(two-sided open meshes); a point deep inside a closed mesh looks farther; the surface's
velocity adds the mesh's per-vertex velocities at the closest point (a deforming mesh). Warp's mesh
queries are float32: a float64 model rounds the query point.
"""

import functools

import warp as wp

from .precision import vec3_type

wp.set_module_options({"enable_backward": False})

#: How a mesh collider tells outside from inside (values of ``Shapes.sides``).
MESH_CLOSED = 0  # a closed mesh, signed by the closest feature's angle-weighted pseudo-normal (exact if watertight)
MESH_ONE_SIDED = 1  # an open mesh whose outside is the side its faces' normals point to (counter-clockwise)
MESH_TWO_SIDED = 2  # an open mesh with no inside: a shell of ``thickness`` on either side
MESH_WINDING = 3  # a closed mesh, inside where its winding number is above ½ (robust to holes; ~5× the cost)
MESH_SIDES = {"closed": MESH_CLOSED, "one_sided": MESH_ONE_SIDED, "two_sided": MESH_TWO_SIDED}


@functools.cache
def mesh_funcs(scalar: type):
    """Distance to a mesh collider and the crossing of a path with it, in the mesh's frame (Warp's mesh queries
    are float32: a float64 model rounds the query point and widens the results)."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)
    one = scalar(1.0)

    @wp.func
    def mesh_distance(mesh: wp.uint64, sides: int, depth: scalar, reach: scalar, lower: vec3, upper: vec3, p: vec3):
        """Signed distance [m] of the point p from the mesh, the outward unit normal, and the surface's velocity
        [m/s] at the closest point (the mesh's per-vertex velocities interpolated), all in the mesh's frame; a
        distance of 1e30 when p is farther than ``depth`` [m] from the surface (and not inside a closed mesh).
        Closed and one-sided meshes take the sign from the closest feature's angle-weighted pseudo-normal
        (exact for a watertight mesh), or from the winding number (``MESH_WINDING``); a point deep inside a
        closed mesh, which the parity of skew rays finds, looks for its closest point up to ``reach`` [m].
        Two-sided meshes are never inside (distance ≥ 0). A point more than ``depth`` outside the bounding
        box ``lower`` … ``upper`` is out of reach at once: a closest-point query costs with the distance it
        may search."""
        far = scalar(1.0e30)
        outside = vec3(wp.max(lower[0] - p[0], p[0] - upper[0]), wp.max(lower[1] - p[1], p[1] - upper[1]),
                       wp.max(lower[2] - p[2], p[2] - upper[2]))
        if wp.max(outside[0], wp.max(outside[1], outside[2])) > depth:
            return far, vec3(zero, zero, one), vec3(zero)
        q = wp.vec3f(p)
        limit = wp.float32(depth)
        found = bool(False)
        face = int(0)
        u = wp.float32(0.0)
        w = wp.float32(0.0)
        sign = wp.float32(1.0)
        if sides == MESH_WINDING:
            winding = wp.mesh_query_point_sign_winding_number(mesh, q, limit)
            found = bool(winding.result)
            face = int(winding.face)
            u = wp.float32(winding.u)
            w = wp.float32(winding.v)
            sign = wp.float32(winding.sign)
        elif sides == MESH_TWO_SIDED:
            shell = wp.mesh_query_point_no_sign(mesh, q, limit)
            found = bool(shell.result)
            face = int(shell.face)
            u = wp.float32(shell.u)
            w = wp.float32(shell.v)
        else:
            # Distances within 1e-5 of the mean edge length count as equal when the closest feature is chosen
            # (Warp's default, 1e-3, lets a slab 2 mm thick with 8 m faces take its far face for the near one).
            near = wp.mesh_query_point_sign_normal(mesh, q, limit, wp.float32(1.0e-5))
            found = bool(near.result)
            face = int(near.face)
            u = wp.float32(near.u)
            w = wp.float32(near.v)
            sign = wp.float32(near.sign)
        # A closed mesh with nothing within depth: p is far outside, or deep inside. The parity of three skew
        # rays (a majority: a ray through an edge or a vertex may count a crossing twice) tells them apart
        # cheaply; a point found inside looks for its closest point as far as it must.
        if not found and (sides == MESH_CLOSED or sides == MESH_WINDING):
            votes = wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(0.267261, 0.534522, 0.801784)) % 2
            votes += wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(-0.707107, 0.408248, 0.57735)) % 2
            votes += wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(0.123091, -0.492366, -0.861640)) % 2
            if votes >= 2:
                deep = wp.mesh_query_point_no_sign(mesh, q, wp.float32(reach))
                found = bool(deep.result)
                face = int(deep.face)
                u = wp.float32(deep.u)
                w = wp.float32(deep.v)
                sign = wp.float32(-1.0)
        if not found:
            return far, vec3(zero, zero, one), vec3(zero)
        sign = wp.where(sign < wp.float32(0.0), wp.float32(-1.0), wp.float32(1.0))
        offset = p - vec3(wp.mesh_eval_position(mesh, face, u, w))
        length = wp.length(offset)
        normal = vec3(wp.mesh_eval_face_normal(mesh, face))  # on the surface: the face's own normal
        if length > zero:
            normal = offset * (scalar(sign) / length)
        return scalar(sign) * length, normal, vec3(wp.mesh_eval_velocity(mesh, face, u, w))

    @wp.func
    def mesh_crossing(mesh: wp.uint64, sides: int, p0: vec3, p1: vec3):
        """Whether the segment p0 → p1 enters the mesh (any face of a two-sided mesh, a face's front otherwise),
        the first crossing point and the crossed face's unit normal on p0's side (mesh frame)."""
        d = p1 - p0
        if wp.length(d) > zero:
            ray = wp.mesh_query_ray(mesh, wp.vec3f(p0), wp.vec3f(d), wp.float32(1.0))  # t in units of |d|
            if ray.result and (sides == MESH_TWO_SIDED or ray.sign > wp.float32(0.0)):
                side = wp.where(ray.sign < wp.float32(0.0), scalar(-1.0), scalar(1.0))
                return True, p0 + scalar(ray.t) * d, vec3(ray.normal) * side
        return False, p1, vec3(zero, zero, one)

    return mesh_distance, mesh_crossing


#: Features of a triangle its closest point lies on (``mesh_cache_funcs``): the face, an edge, a vertex; the
#: index of its pseudo-normal among the face's seven (face, edges ab bc ca, vertices a b c).
FEATURE_FACE = 0
FEATURE_EDGE_AB = 1
FEATURE_EDGE_BC = 2
FEATURE_EDGE_CA = 3
FEATURE_VERTEX_A = 4
FEATURE_VERTEX_B = 5
FEATURE_VERTEX_C = 6
#: Pseudo-normals stored per face (``MeshCache.normals``).
FACE_NORMALS = 7
#: A mesh cache entry that must be refreshed (``MeshCache.side``): no valid candidates.
CACHE_INVALID = 0


@wp.struct
class MeshCache:
    """The mesh colliders' own data beside ``Shapes`` (float32, as Warp's meshes) and each particle's candidate
    cache (a Verlet list; see :func:`mesh_cache_funcs`)."""

    slot: wp.array[wp.int32]  # [shape_count], the shape's row in the cache arrays; -1: Warp's own queries
    reach: wp.array[wp.float32]  # [m], [shape_count], R: the distance from the surface resolved exactly
    margin: wp.array[wp.float32]  # [m], [shape_count], m: how far a particle may move before it queries again
    # (0: a full query at every use; < 0: Warp's own closest-point query, as ``p_index`` = -1 has)
    normal_offset: wp.array[wp.int32]  # [shape_count], the mesh's first entry of ``normals``
    normals: wp.array[wp.vec3f]  # [-], [7 · Σ faces], unit pseudo-normals per face (face, 3 edges, 3 corners)
    ref: wp.array2d[wp.vec3f]  # [m], [cached meshes, state_size], x_ref in the mesh's frame
    side: wp.array2d[wp.int32]  # [cached meshes, state_size], +1 outside, -1 inside at x_ref, 0: refresh
    count: wp.array2d[wp.int32]  # [cached meshes, state_size], candidates held
    face: wp.array3d[wp.int32]  # [cached meshes, state_size, C], the candidate triangles
    overflow: wp.array[wp.int32]  # [world_count], refreshes that found more than C candidates (full query then)
    refreshes: wp.array[wp.int32]  # [world_count], full queries made with the cache on (refreshes), accumulated


@wp.func
def face_unit_normal(mesh: wp.uint64, f: int) -> wp.vec3d:
    """Face f's unit normal (counter-clockwise), float64 from the mesh's float32 points; zero if degenerate."""
    a = wp.vec3d(wp.mesh_get_point(mesh, 3 * f))
    n = wp.cross(wp.vec3d(wp.mesh_get_point(mesh, 3 * f + 1)) - a, wp.vec3d(wp.mesh_get_point(mesh, 3 * f + 2)) - a)
    length = wp.length(n)
    if length > wp.float64(0.0):
        return n / length
    return wp.vec3d()


@wp.func
def face_corner_angle(mesh: wp.uint64, f: int, k: int) -> wp.float64:
    """Face f's interior angle [rad] at its corner k (0 for a degenerate corner)."""
    p = wp.vec3d(wp.mesh_get_point(mesh, 3 * f + k))
    u = wp.vec3d(wp.mesh_get_point(mesh, 3 * f + (k + 1) % 3)) - p
    w = wp.vec3d(wp.mesh_get_point(mesh, 3 * f + (k + 2) % 3)) - p
    lengths = wp.length(u) * wp.length(w)
    if lengths > wp.float64(0.0):
        return wp.acos(wp.clamp(wp.dot(u, w) / lengths, wp.float64(-1.0), wp.float64(1.0)))
    return wp.float64(0.0)


@wp.func
def unit_or_zero(n: wp.vec3d) -> wp.vec3f:
    length = wp.length(n)
    if length > wp.float64(0.0):
        return wp.vec3f(n / length)
    return wp.vec3f()


@wp.kernel(enable_backward=False)
def face_normals_kernel(
    mesh: wp.uint64, face_normal_out: wp.array[wp.vec3d], corner_angle_out: wp.array[wp.float64]
):
    """Each face's unit normal and its angles [rad] at its corners (3 f + k), float64 from the mesh's points:
    the terms :func:`pseudo_normals_kernel` sums. Launch over the faces."""
    f = wp.tid()
    face_normal_out[f] = face_unit_normal(mesh, f)
    for k in range(3):
        corner_angle_out[3 * f + k] = face_corner_angle(mesh, f, k)


@wp.kernel(enable_backward=False)
def pseudo_normals_kernel(
    # Mesh:
    mesh: wp.uint64,
    # In (face_normals_kernel's terms, the mesh's topology):
    face_normal: wp.array[wp.vec3d],  # [t], from face_normals_kernel
    corner_angle: wp.array[wp.float64],  # [rad], [3 t], from face_normals_kernel
    vertex_start: wp.array[wp.int32],  # [v + 1], CSR over the corners (3 f + k) at each vertex
    vertex_corner: wp.array[wp.int32],  # [3 t], in face order
    edge_group: wp.array[wp.int32],  # [3 t], the undirected edge of each face's edge k (ab, bc, ca)
    edge_start: wp.array[wp.int32],  # [edges + 1], CSR over the faces at each edge
    edge_face: wp.array[wp.int32],  # [3 t], in face order
    offset: int,
    # Out:
    normals_out: wp.array[wp.vec3f],
):
    """The seven unit pseudo-normals of face f (``MeshCache.normals``: face, edges ab bc ca, corners a b c),
    summed in float64 in a fixed order (no atomics). Launch over the faces."""
    f = wp.tid()
    base = offset + FACE_NORMALS * f
    normals_out[base] = unit_or_zero(face_normal[f])
    for k in range(3):
        group = edge_group[3 * f + k]
        edge = wp.vec3d()
        for j in range(edge_start[group], edge_start[group + 1]):
            edge += face_normal[edge_face[j]]
        normals_out[base + FEATURE_EDGE_AB + k] = unit_or_zero(edge)
        vertex = wp.mesh_get_index(mesh, 3 * f + k)
        corner_sum = wp.vec3d()
        for j in range(vertex_start[vertex], vertex_start[vertex + 1]):
            corner = vertex_corner[j]
            corner_sum += corner_angle[corner] * face_normal[corner / 3]
        normals_out[base + FEATURE_VERTEX_A + k] = unit_or_zero(corner_sum)


@functools.cache
def mesh_cache_funcs(scalar: type):
    """The mesh path of the particle contacts: exact closest points and path crossings on a mesh collider's
    triangles, from a full BVH query or from a particle's cached candidates, with the same answer either way.

    **The answer.** For a point q (the mesh's frame, float32) the result is the nearest triangle among those
    within R = ``reach`` of q (closest point per triangle by Ericson's regions, ties to the lowest face index,
    so it does not depend on the order triangles are visited), signed by the angle-weighted pseudo-normal of
    the feature (face, edge, vertex) the closest point lies on (closed and one-sided meshes; exact for a
    watertight mesh) or unsigned (two-sided). With none within R: out of reach, unless q is inside a closed mesh
    (the parity of three skew rays, as Warp's queries), which looks for its closest point as far as it must.
    R is the particles' largest radius plus the thickness (what the response and ``collide`` can touch), or
    for a one-sided mesh its depth (up to which behind it is inside). A path's crossing is the first triangle
    Woop's watertight ray test hits on the segment p0 → p1 (ties to the lowest face).

    **The cache.** A full query (``wp.mesh_query_aabb`` around q, then the exact test per triangle) also
    keeps, for its particle: x_ref = q, the side (inside or outside) at x_ref, and every triangle within
    R + m of x_ref (a float32-safe pad added), at most C; more is an overflow (counted; the particle queries
    fully again next time, so the answer never depends on C). Until the particle's point in the mesh's
    frame is more than m from x_ref (δ = |q - x_ref| ≤ m), only the candidates are evaluated:

    * every triangle within R of q is within R + δ ≤ R + m of x_ref, so it is a candidate: the nearest within
      R, and its feature, are the full query's;
    * with no candidate within R, q is out of reach unless it is inside; the side cannot have changed: a
      segment x_ref → q that crossed the surface at c would put c within δ of both ends (convexity of the
      ball of radius δ ≤ m about x_ref), so c's triangle would be a candidate within δ of q. When every
      candidate is farther than δ from q, q is on x_ref's side; otherwise (only when m exceeds R) it queries
      fully;
    * a swept path whose both ends are within m of x_ref lies in that ball (convexity), so every triangle it
      crosses is a candidate.

    A tracked mesh keeps x_ref in its own frame, so its motion needs no bound; a deforming mesh invalidates
    every cache entry when its points are set. Each thread writes only its particle's entries; the counters
    are integer atomics."""
    vec3 = vec3_type(scalar)
    f32 = wp.float32
    zero = scalar(0.0)
    one = scalar(1.0)
    none = f32(0.0)

    @wp.func
    def triangle_closest(a: wp.vec3f, b: wp.vec3f, c: wp.vec3f, p: wp.vec3f):
        """The point of triangle abc closest to p (Ericson's Voronoi regions), its barycentric weights of a and b,
        and the feature it lies on (``FEATURE_*``). A degenerate triangle gives one of its vertices or edges."""
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        if d1 <= none and d2 <= none:
            return a, f32(1.0), none, FEATURE_VERTEX_A
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        if d3 >= none and d4 <= d3:
            return b, none, f32(1.0), FEATURE_VERTEX_B
        vc = d1 * d4 - d3 * d2
        if vc <= none and d1 >= none and d3 <= none and d1 - d3 > none:
            v = d1 / (d1 - d3)
            return a + v * ab, f32(1.0) - v, v, FEATURE_EDGE_AB
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        if d6 >= none and d5 <= d6:
            return c, none, none, FEATURE_VERTEX_C
        vb = d5 * d2 - d1 * d6
        if vb <= none and d2 >= none and d6 <= none and d2 - d6 > none:
            w = d2 / (d2 - d6)
            return a + w * ac, f32(1.0) - w, none, FEATURE_EDGE_CA
        va = d3 * d6 - d5 * d4
        if va <= none and d4 - d3 >= none and d5 - d6 >= none and (d4 - d3) + (d5 - d6) > none:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            return b + w * (c - b), none, f32(1.0) - w, FEATURE_EDGE_BC
        denom = va + vb + vc
        if denom > none:
            v = vb / denom
            w = vc / denom
            return a + ab * v + ac * w, f32(1.0) - v - w, v, FEATURE_FACE
        return a, f32(1.0), none, FEATURE_VERTEX_A

    @wp.func
    def face_closest(mesh: wp.uint64, f: int, q: wp.vec3f):
        """Distance [m] from q to face f of the mesh, the closest point, its weights of the face's first two
        vertices and its feature."""
        a = wp.mesh_get_point(mesh, 3 * f)
        b = wp.mesh_get_point(mesh, 3 * f + 1)
        c = wp.mesh_get_point(mesh, 3 * f + 2)
        closest, wa, wb, feature = triangle_closest(a, b, c, q)
        return wp.length(q - closest), closest, wa, wb, feature

    @wp.func
    def nearer(d: f32, f: int, best_d: f32, best_f: int) -> bool:
        """Whether face f at distance d beats the best so far (ties to the lower index: order-free)."""
        return best_f < 0 or d < best_d or (d == best_d and f < best_f)

    @wp.func
    def ray_triangle(a: wp.vec3f, b: wp.vec3f, c: wp.vec3f, o: wp.vec3f, d: wp.vec3f):
        """Woop, Benthin and Wald's watertight ray-triangle test of the segment o → o + d: whether it hits, the
        fraction t ∈ [0, 1] and whether it hit the front (counter-clockwise) side. A segment through an edge or a
        vertex hits at least one of the triangles that share it."""
        kz = int(0)
        if wp.abs(d[1]) > wp.abs(d[kz]):
            kz = 1
        if wp.abs(d[2]) > wp.abs(d[kz]):
            kz = 2
        kx = (kz + 1) % 3
        ky = (kx + 1) % 3
        if d[kz] < none:
            swap = kx
            kx = ky
            ky = swap
        sx = d[kx] / d[kz]
        sy = d[ky] / d[kz]
        sz = f32(1.0) / d[kz]
        A = a - o
        B = b - o
        C = c - o
        ax = A[kx] - sx * A[kz]
        ay = A[ky] - sy * A[kz]
        bx = B[kx] - sx * B[kz]
        by = B[ky] - sy * B[kz]
        cx = C[kx] - sx * C[kz]
        cy = C[ky] - sy * C[kz]
        # Edge functions from exact products (float32 × float32 fits float64), rounded once: the edge two
        # triangles share gives them opposite values, so no ray slips between them.
        U = f32(wp.float64(cx) * wp.float64(by) - wp.float64(cy) * wp.float64(bx))
        V = f32(wp.float64(ax) * wp.float64(cy) - wp.float64(ay) * wp.float64(cx))
        W = f32(wp.float64(bx) * wp.float64(ay) - wp.float64(by) * wp.float64(ax))
        if (U < none or V < none or W < none) and (U > none or V > none or W > none):
            return False, none, False
        det = U + V + W
        if det == none:
            return False, none, False
        T = U * (sz * A[kz]) + V * (sz * B[kz]) + W * (sz * C[kz])
        t = T / det
        if t < none or t > f32(1.0):
            return False, none, False
        return True, t, det > none

    @wp.func
    def face_ray(mesh: wp.uint64, f: int, o: wp.vec3f, dir: wp.vec3f):
        """``ray_triangle`` of the segment o → o + dir against face f of the mesh: hit, its parameter, front."""
        a = wp.mesh_get_point(mesh, 3 * f)
        b = wp.mesh_get_point(mesh, 3 * f + 1)
        c = wp.mesh_get_point(mesh, 3 * f + 2)
        hit, t, front = ray_triangle(a, b, c, o, dir)
        return hit, t, front

    @wp.func
    def face_result(mesh: wp.uint64, cache: MeshCache, s: int, sides: int, f: int, closest: wp.vec3f, wa: f32, wb: f32,
                    feature: int, p: vec3):
        """Signed distance [m] of p from face f's closest point, the outward unit normal and the surface's
        velocity [m/s] there (mesh frame); the sign from the feature's pseudo-normal (two-sided: unsigned)."""
        n = cache.normals[cache.normal_offset[s] + FACE_NORMALS * f + feature]
        sign = one
        if sides != MESH_TWO_SIDED:
            if wp.dot(wp.vec3f(p) - closest, n) < none:
                sign = -one
        offset = p - vec3(closest)
        length = wp.length(offset)
        normal = vec3(cache.normals[cache.normal_offset[s] + FACE_NORMALS * f])  # on the surface: the face's normal
        if length > zero:
            normal = offset * (sign / length)
        return sign * length, normal, vec3(wp.mesh_eval_velocity(mesh, f, wa, wb))

    @wp.func
    def deep_result(mesh: wp.uint64, cache: MeshCache, s: int, reach: scalar, p: vec3):
        """A point inside a closed mesh farther than R from it: its closest point, however far (distance < 0)."""
        q = wp.vec3f(p)
        deep = wp.mesh_query_point_no_sign(mesh, q, wp.float32(reach))
        if not deep.result:
            return scalar(1.0e30), vec3(zero, zero, one), vec3(zero)
        d, closest, wa, wb, feature = face_closest(mesh, deep.face, q)
        offset = p - vec3(closest)
        length = wp.length(offset)
        normal = vec3(cache.normals[cache.normal_offset[s] + FACE_NORMALS * deep.face])
        if length > zero:
            normal = offset * (-one / length)
        return -length, normal, vec3(wp.mesh_eval_velocity(mesh, deep.face, wa, wb))

    @wp.func
    def parity_inside(mesh: wp.uint64, q: wp.vec3f) -> bool:
        """Whether q is inside a closed mesh: the parity of three skew rays, by majority (a ray through an edge or
        a vertex may count a crossing twice)."""
        votes = wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(0.267261, 0.534522, 0.801784)) % 2
        votes += wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(-0.707107, 0.408248, 0.57735)) % 2
        votes += wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(0.123091, -0.492366, -0.861640)) % 2
        return votes >= 2

    @wp.func
    def pad_for(q: wp.vec3f, lower: vec3, upper: vec3, extent: f32) -> f32:
        """A float32-safe pad [m] on distances of magnitude ``extent`` among coordinates like q's and the
        mesh's: rounding of the closest point, the distances and the displacement stays far below it."""
        size = wp.max(wp.max(wp.abs(q[0]), wp.abs(q[1])), wp.abs(q[2]))
        size = wp.max(size, f32(wp.max(wp.max(wp.abs(lower[0]), wp.abs(lower[1])), wp.abs(lower[2]))))
        size = wp.max(size, f32(wp.max(wp.max(wp.abs(upper[0]), wp.abs(upper[1])), wp.abs(upper[2]))))
        return f32(1.0e-5) * (size + extent) + f32(1.0e-30)

    @wp.func
    def mesh_surface_cached(
        mesh: wp.uint64, cache: MeshCache, s: int, sides: int, deep_reach: scalar, lower: vec3, upper: vec3,
        world: int, p_index: int, p: vec3,
    ):
        """Signed distance [m] of p (the mesh's frame) from mesh collider s, the outward unit normal and the
        surface's velocity [m/s] (see the factory's docstring); 1e30 out of reach. ``p_index`` is the
        particle's state entry (its cache row), -1 for none (a full query that keeps nothing)."""
        far = scalar(1.0e30)
        q = wp.vec3f(p)
        reach = cache.reach[s]
        margin = cache.margin[s]
        slot = cache.slot[s]
        closed = sides == MESH_CLOSED
        if p_index >= 0 and margin > none and cache.side[slot, p_index] != CACHE_INVALID:
            delta = wp.length(q - cache.ref[slot, p_index])
            if delta <= margin:
                best_d = none
                best_f = int(-1)
                best_c = wp.vec3f()
                best_a = none
                best_b = none
                best_feature = int(0)
                nearest = f32(3.0e38)
                for k in range(cache.count[slot, p_index]):
                    f = cache.face[slot, p_index, k]
                    d, closest, wa, wb, feature = face_closest(mesh, f, q)
                    nearest = wp.min(nearest, d)
                    if d <= reach and nearer(d, f, best_d, best_f):
                        best_d = d
                        best_f = f
                        best_c = closest
                        best_a = wa
                        best_b = wb
                        best_feature = feature
                if best_f >= 0:
                    distance, normal, velocity = face_result(mesh, cache, s, sides, best_f, best_c, best_a, best_b,
                                                             best_feature, p)
                    return distance, normal, velocity
                if not closed:
                    return far, vec3(zero, zero, one), vec3(zero)
                if nearest > delta + pad_for(q, lower, upper, delta):  # no crossing since x_ref: x_ref's side
                    if cache.side[slot, p_index] < 0:
                        distance, normal, velocity = deep_result(mesh, cache, s, deep_reach, p)
                        return distance, normal, velocity
                    return far, vec3(zero, zero, one), vec3(zero)
        # The full query (and, with a cache row and a margin, its refresh).
        store = p_index >= 0 and margin > none
        keep = wp.where(store, margin, none)
        pad = pad_for(q, lower, upper, reach + keep)
        extent = reach + keep + pad
        best_d = none
        best_f = int(-1)
        best_c = wp.vec3f()
        best_a = none
        best_b = none
        best_feature = int(0)
        count = int(0)
        overflow = bool(False)
        capacity = cache.face.shape[2]
        outside = wp.max(wp.max(f32(lower[0]) - q[0], q[0] - f32(upper[0])),
                         wp.max(wp.max(f32(lower[1]) - q[1], q[1] - f32(upper[1])),
                                wp.max(f32(lower[2]) - q[2], q[2] - f32(upper[2]))))
        if outside <= extent:
            query = wp.mesh_query_aabb(mesh, q - wp.vec3f(extent, extent, extent), q + wp.vec3f(extent, extent, extent))
            f = int(0)
            while wp.mesh_query_aabb_next(query, f):
                d, closest, wa, wb, feature = face_closest(mesh, f, q)
                if store and d <= extent:
                    if count < capacity:
                        cache.face[slot, p_index, count] = f
                        count += 1
                    else:
                        overflow = True
                if d <= reach and nearer(d, f, best_d, best_f):
                    best_d = d
                    best_f = f
                    best_c = closest
                    best_a = wa
                    best_b = wb
                    best_feature = feature
        side = int(1)
        distance = far
        normal = vec3(zero, zero, one)
        velocity = vec3(zero)
        if best_f >= 0:
            distance, normal, velocity = face_result(mesh, cache, s, sides, best_f, best_c, best_a, best_b,
                                                     best_feature, p)
            if distance < zero:
                side = -1
        elif closed and outside < none:
            if parity_inside(mesh, q):
                side = -1
                distance, normal, velocity = deep_result(mesh, cache, s, deep_reach, p)
        if store:
            cache.ref[slot, p_index] = q
            cache.count[slot, p_index] = count
            cache.side[slot, p_index] = wp.where(overflow, CACHE_INVALID, side)
            wp.atomic_add(cache.refreshes, world, 1)
            if overflow:
                wp.atomic_add(cache.overflow, world, 1)
        return distance, normal, velocity

    @wp.func
    def mesh_crossing_cached(mesh: wp.uint64, cache: MeshCache, s: int, sides: int, lower: vec3, upper: vec3,
                             p_index: int, p0: vec3, p1: vec3):
        """Whether the segment p0 → p1 (mesh frame) enters the mesh (any face of a two-sided mesh, a face's front
        otherwise: the first face it hits decides), the crossing point and the face's unit normal on p0's side:
        over the particle's candidates when both ends are within m of its x_ref, else over the triangles a BVH
        query of the segment's box returns."""
        d = p1 - p0
        if wp.length(d) > zero:
            o = wp.vec3f(p0)
            dir = wp.vec3f(d)
            best_t = none
            best_f = int(-1)
            best_front = bool(False)
            slot = cache.slot[s]
            margin = cache.margin[s]
            cached = bool(False)
            if p_index >= 0 and margin > none and cache.side[slot, p_index] != CACHE_INVALID:
                ref = cache.ref[slot, p_index]
                cached = wp.length(o - ref) <= margin and wp.length(wp.vec3f(p1) - ref) <= margin
            if cached:
                for k in range(cache.count[slot, p_index]):
                    f = cache.face[slot, p_index, k]
                    hit, t, front = face_ray(mesh, f, o, dir)
                    if hit and nearer(t, f, best_t, best_f):
                        best_t = t
                        best_f = f
                        best_front = front
            else:
                end = o + dir
                pad = pad_for(o, lower, upper, wp.length(dir))
                low = wp.vec3f(wp.min(o[0], end[0]) - pad, wp.min(o[1], end[1]) - pad, wp.min(o[2], end[2]) - pad)
                high = wp.vec3f(wp.max(o[0], end[0]) + pad, wp.max(o[1], end[1]) + pad, wp.max(o[2], end[2]) + pad)
                query = wp.mesh_query_aabb(mesh, low, high)
                f = int(0)
                while wp.mesh_query_aabb_next(query, f):
                    hit, t, front = face_ray(mesh, f, o, dir)
                    if hit and nearer(t, f, best_t, best_f):
                        best_t = t
                        best_f = f
                        best_front = front
            if best_f >= 0 and (sides == MESH_TWO_SIDED or best_front):
                n = vec3(cache.normals[cache.normal_offset[s] + FACE_NORMALS * best_f])
                return True, p0 + scalar(best_t) * d, wp.where(best_front, n, -n)
        return False, p1, vec3(zero, zero, one)

    return mesh_surface_cached, mesh_crossing_cached, triangle_closest, ray_triangle
