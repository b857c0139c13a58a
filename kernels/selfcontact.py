"""Self-collision of triangle surfaces whose vertices are particles: repulsion, friction and a displacement cap.

A post-step pass: it reads the step's start x⁰ (``state_in``, assumed free of intersections) and the
integrator's result x¹ (``state_out``), and rewrites ``state_out``. Pairs are vertex–triangle (VT) and
edge–edge (EE) pairs of primitives that share no vertex, found through a BVH of each world's triangles at
x⁰ (``wp.Mesh``, refit every step; ``wp.mesh_query_aabb``).

1. **Repulsion and friction** (``repel_kernel``). Every pair closer than ``REPULSION_REACH`` × thickness τ
   at x⁰ predicts its separation at the end, linearised at x⁰: d + n·Σₖ wₖΔₖ, with n the unit vector between
   the closest points, wₖ the signed barycentric weights of the pair's four vertices (one side +, the other
   −) and Δₖ = x¹ₖ − x⁰ₖ. A pair predicted closer than τ is pushed apart by c = τ − (d + n·Σ wₖΔₖ) along n,
   shared by inverse mass like an inelastic impulse (Bridson, Fedkiw & Anderson 2002): vertex k moves by
   wₖ mₖ⁻¹ c / Σⱼ wⱼ² mⱼ⁻¹ · n. Coulomb friction removes up to μc of the pair's relative tangential
   displacement the same way (all of it when μc covers it: static friction). A vertex takes a weighted mean
   of its pairs' corrections (Jacobi): their sum over max(1, Σ|wₖ|), its weights in its pairs, so several
   pairs at one vertex do not add up to an overshoot, and a pair in which it barely takes part (a triangle
   corner far from the closest point) does not dilute the others.
2. **The displacement cap** (``cap_kernel``; Chen et al. 2024, "Offset Geometric Contact", as in Newton's
   VBD): vertex i moves from x⁰ᵢ by at most γ·min(rᵢ, dᵢ), where dᵢ is its distance at x⁰ to the nearest
   primitive pair it belongs to in any role (as the vertex or a triangle corner of a VT pair, as an end of
   an EE pair) within the search radius rᵢ = min(|Δᵢ| / γ, ``SEARCH_REACH`` × τ), and γ < 1/2 the relaxation.

   Why no pair can cross: take a pair at distance D at x⁰, and any vertex k of it. If D ≥ rₖ, k moves at most
   γrₖ ≤ γD. Otherwise k's search found the pair, so dₖ ≤ D and k moves at most γD again. Every point of
   either primitive is a convex combination of its vertices, so it moves at most γD along the straight path
   x⁰ → x, and the primitives stay at least D(1 − 2γ) > 0 apart throughout the step. Kinematic particles
   follow their prescribed motion and are not capped: the proof covers pairs whose vertices are all free.
   The BVH is single precision: query boxes are padded by ``BOX_PAD`` relative to the coordinates.

Velocities of the vertices the pass moved become v = (x − x⁰)/h; the others keep the integrator's.
Deterministic without float atomics: each vertex gathers the pairs it belongs to in the BVH's traversal
order and writes only itself; two integer counters per world (pairs pushed, vertices capped) use atomics.
"""

import functools

import warp as wp

from .kinematics import particle_funcs
from .precision import vec3_type
from .worlds import world_and_index
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})

#: Pairs closer than this many thicknesses at the step's start are checked for repulsion.
REPULSION_REACH = 2.0
#: The cap's search radius is at most this many thicknesses (a faster vertex is capped to γ of it).
SEARCH_REACH = 32.0
#: Relative padding of the single-precision BVH's query boxes (float32 rounding of the points is 6e-8).
BOX_PAD = 1.0e-6

#: Columns of ``SelfContact.params`` [rows, PARAM_COUNT]: live values per world.
PARAM_THICKNESS = 0  # τ [m]: the separation the repulsion keeps
PARAM_FRICTION = 1  # μ [-]: Coulomb friction between the surface's layers
PARAM_RELAXATION = 2  # γ [-] in (0, 1/2): the cap's share of the distance to the nearest primitive
PARAM_COUNT = 3

#: Columns of the per-world counters [world_count, COUNTER_COUNT] (int32, summed over the steps).
COUNT_PAIRS = 0  # pairs pushed apart by the repulsion
COUNT_CAPPED = 1  # vertices whose displacement the cap shortened
COUNTER_COUNT = 2


@wp.struct
class Surface:
    """The topology of the colliding surface, shared by every world (per-world particle indices)."""

    triangle: wp.array[wp.vec3i]  # the triangles' corners, shape [triangle_count]
    triangle_edges: wp.array[wp.vec3i]  # each triangle's three edges (indices into ``edge``), [triangle_count]
    edge: wp.array[wp.vec2i]  # the surface's unique edges, shape [edge_count]
    edge_owner: wp.array[wp.int32]  # the triangle through which queries report edge e, [edge_count]
    vertex_owner: wp.array[wp.int32]  # the triangle through which queries report vertex i, or -1 (not on the
    #   surface), shape [particle_count]
    vertex_triangle_start: wp.array[wp.int32]  # CSR of the triangles at each vertex, [particle_count + 1]
    vertex_triangle: wp.array[wp.int32]  # their indices, [3 · triangle_count]
    vertex_edge_start: wp.array[wp.int32]  # CSR of the edges at each vertex, [particle_count + 1]
    vertex_edge: wp.array[wp.int32]  # their indices, [2 · edge_count]
    mesh: wp.array[wp.uint64]  # per world, the id of the wp.Mesh of its triangles at the step's start


@functools.cache
def geometry_funcs(scalar: type):
    """Closest points of the two pair kinds in precision ``scalar``: ``triangle_closest(p, a, b, c)`` → the
    barycentric weights (u, v, w) of the point of triangle abc nearest p; ``edge_closest(p1, q1, p2, q2)``
    → (s, t) of the nearest points p1 + s(q1 - p1), p2 + t(q2 - p2) of two segments (Ericson, Real-Time
    Collision Detection, 5.1.5 and 5.1.9)."""
    vec3 = vec3_type(scalar)
    vec2 = wp.types.vector(2, scalar)

    @wp.func
    def triangle_closest(p: vec3, a: vec3, b: vec3, c: vec3):
        zero, one = scalar(0.0), scalar(1.0)
        ab, ac, ap = b - a, c - a, p - a
        d1, d2 = wp.dot(ab, ap), wp.dot(ac, ap)
        if d1 <= zero and d2 <= zero:
            return vec3(one, zero, zero)
        bp = p - b
        d3, d4 = wp.dot(ab, bp), wp.dot(ac, bp)
        if d3 >= zero and d4 <= d3:
            return vec3(zero, one, zero)
        vc = d1 * d4 - d3 * d2
        if vc <= zero and d1 >= zero and d3 <= zero:
            v = d1 / (d1 - d3)
            return vec3(one - v, v, zero)
        cp = p - c
        d5, d6 = wp.dot(ab, cp), wp.dot(ac, cp)
        if d6 >= zero and d5 <= d6:
            return vec3(zero, zero, one)
        vb = d5 * d2 - d1 * d6
        if vb <= zero and d2 >= zero and d6 <= zero:
            w = d2 / (d2 - d6)
            return vec3(one - w, zero, w)
        va = d3 * d6 - d5 * d4
        if va <= zero and (d4 - d3) >= zero and (d5 - d6) >= zero:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            return vec3(zero, one - w, w)
        total = va + vb + vc
        if total <= zero:  # a degenerate (zero-area) triangle: its first corner
            return vec3(one, zero, zero)
        v = vb / total
        w = vc / total
        return vec3(one - v - w, v, w)

    @wp.func
    def edge_closest(p1: vec3, q1: vec3, p2: vec3, q2: vec3):
        zero, one = scalar(0.0), scalar(1.0)
        d1, d2, r = q1 - p1, q2 - p2, p1 - p2
        a, e, f = wp.dot(d1, d1), wp.dot(d2, d2), wp.dot(d2, r)
        tiny = scalar(1.0e-30)
        s, t = zero, zero
        if a <= tiny and e <= tiny:
            return vec2(s, t)
        if a <= tiny:
            t = wp.clamp(f / e, zero, one)
        else:
            c = wp.dot(d1, r)
            if e <= tiny:
                s = wp.clamp(-c / a, zero, one)
            else:
                b = wp.dot(d1, d2)
                denom = a * e - b * b
                if denom > scalar(1.0e-12) * a * e:  # else parallel: any s, here 0
                    s = wp.clamp((b * f - c * e) / denom, zero, one)
                t = (b * s + f) / e
                if t < zero:
                    t = zero
                    s = wp.clamp(-c / a, zero, one)
                elif t > one:
                    t = one
                    s = wp.clamp((b - c) / a, zero, one)
        return vec2(s, t)

    return triangle_closest, edge_closest


@functools.cache
def _pass_funcs(scalar: type, repel: bool):
    """The pair walk of one pass: ``visit_pairs`` enumerates every pair vertex i belongs to, in every role,
    and folds each into (correction sum, pairs, nearest distance, pairs counted here): with ``repel`` the
    repulsion and friction corrections and the pairs pushed, else the nearest distance and the pairs closer
    than the reach (the cap, and ``proximity_kernel``)."""
    vec3 = vec3_type(scalar)
    vec4 = wp.types.vector(4, scalar)
    triangle_closest, edge_closest = geometry_funcs(scalar)
    effective_inv_mass = particle_funcs(scalar)

    @wp.func
    def box_of(lower: vec3, upper: vec3, reach: scalar):
        """A single-precision query box around [lower, upper] grown by ``reach`` and the rounding pad."""
        pad = reach + scalar(BOX_PAD) * (wp.max(wp.abs(lower)) + wp.max(wp.abs(upper)) + scalar(1.0))
        grow = vec3(pad, pad, pad)
        return wp.vec3f(lower - grow), wp.vec3f(upper + grow)

    @wp.func
    def fold_pair(
        me: int, index: wp.vec4i, weight: vec4, diff: vec3, fallback: vec3, base: int, mass_row: int,
        thickness: scalar, friction: scalar, particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar], particle_q_start: wp.array[vec3], particle_q_in: wp.array[vec3],
        correction: vec3, count: scalar,
    ):
        """Add the pair (vertices ``index``, signed weights ``weight``, closest-point difference ``diff`` at
        the start) to the repulsion of its vertex ``me`` (0..3): returns the correction sum, the pairs' weight
        at the vertex (each pair counts by the vertex's |weight| in it) and 1 if the pair is pushed."""
        d = wp.length(diff)
        n = fallback
        if d > scalar(1.0e-12) * thickness:
            n = diff / d
        if wp.length(n) == scalar(0.0):
            return correction, count, 0
        relative = vec3(scalar(0.0))
        generalized = scalar(0.0)
        for k in range(4):
            j = base + index[k]
            relative += weight[k] * (particle_q_in[j] - particle_q_start[j])
            generalized += weight[k] * weight[k] * effective_inv_mass(particle_flags[j],
                                                                     particle_inv_mass[mass_row, index[k]])
        normal = wp.dot(n, relative)
        push = thickness - (d + normal)
        if push <= scalar(0.0) or generalized <= scalar(0.0):
            return correction, count, 0
        tangential = relative - normal * n
        slip = wp.length(tangential)
        dx = push * n
        if slip > scalar(0.0):
            dx -= (wp.min(friction * push, slip) / slip) * tangential
        j = base + index[me]
        share = weight[me] * effective_inv_mass(particle_flags[j], particle_inv_mass[mass_row, index[me]])
        return correction + (share / generalized) * dx, count + wp.abs(weight[me]), 1

    @wp.func
    def visit_pairs(
        i: int, base: int, mass_row: int, mesh: wp.uint64, reach: scalar, thickness: scalar, friction: scalar,
        surface: Surface, particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
        particle_q_start: wp.array[vec3], particle_q_in: wp.array[vec3],
    ):
        zero, one = scalar(0.0), scalar(1.0)
        correction = vec3(zero)
        count = zero  # the pairs' weight at i (repel), or the pairs within reach (else)
        nearest = reach
        counted = int(0)  # pairs this vertex counts (VT as the vertex; EE at the lower edge's first end)
        xi = vec3(particle_q_start[base + i])
        first_triangle = surface.vertex_triangle_start[i]
        last_triangle = surface.vertex_triangle_start[i + 1]
        first_edge = surface.vertex_edge_start[i]
        last_edge = surface.vertex_edge_start[i + 1]

        # One query: the box of i's triangles grown by the reach holds every element within the reach of i,
        # of its triangles or of its edges; each element is reported once, through its owner triangle.
        lower = xi
        upper = xi
        for k in range(first_triangle, last_triangle):
            ring = surface.triangle[surface.vertex_triangle[k]]
            for m in range(3):
                corner_x = vec3(particle_q_start[base + ring[m]])
                lower = wp.min(lower, corner_x)
                upper = wp.max(upper, corner_x)
        box_lower, box_upper = box_of(lower, upper, reach)
        query = wp.mesh_query_aabb(mesh, box_lower, box_upper)
        other = int(0)
        while wp.mesh_query_aabb_next(query, other):
            near_tri = surface.triangle[other]

            # i as the vertex of a VT pair.
            if near_tri[0] != i and near_tri[1] != i and near_tri[2] != i:
                ta = vec3(particle_q_start[base + near_tri[0]])
                tb = vec3(particle_q_start[base + near_tri[1]])
                tc = vec3(particle_q_start[base + near_tri[2]])
                bary = triangle_closest(xi, ta, tb, tc)
                diff = xi - (bary[0] * ta + bary[1] * tb + bary[2] * tc)
                nearest = wp.min(nearest, wp.length(diff))
                if wp.length(diff) < reach:
                    if wp.static(not repel):
                        count += one
                    if wp.static(repel):
                        correction, count, pushed = fold_pair(
                            0, wp.vec4i(i, near_tri[0], near_tri[1], near_tri[2]), vec4(one, -bary[0], -bary[1], -bary[2]),
                            diff, wp.normalize(wp.cross(tb - ta, tc - ta)), base, mass_row, thickness, friction,
                            particle_flags, particle_inv_mass, particle_q_start, particle_q_in, correction, count)
                        counted += pushed

            # i as a corner of the triangle of a VT pair: the vertices this triangle reports.
            for m in range(3):
                j = near_tri[m]
                if surface.vertex_owner[j] == other:
                    xj = vec3(particle_q_start[base + j])
                    for k in range(first_triangle, last_triangle):
                        own = surface.vertex_triangle[k]
                        tri = surface.triangle[own]
                        if j != tri[0] and j != tri[1] and j != tri[2]:
                            a = vec3(particle_q_start[base + tri[0]])
                            b = vec3(particle_q_start[base + tri[1]])
                            c = vec3(particle_q_start[base + tri[2]])
                            bary = triangle_closest(xj, a, b, c)
                            diff = xj - (bary[0] * a + bary[1] * b + bary[2] * c)
                            nearest = wp.min(nearest, wp.length(diff))
                            if wp.length(diff) < reach:
                                if wp.static(not repel):
                                    count += one
                                if wp.static(repel):
                                    corner = int(0)
                                    if tri[1] == i:
                                        corner = 1
                                    elif tri[2] == i:
                                        corner = 2
                                    correction, count, pushed = fold_pair(
                                        corner + 1, wp.vec4i(j, tri[0], tri[1], tri[2]),
                                        vec4(one, -bary[0], -bary[1], -bary[2]), diff,
                                        wp.normalize(wp.cross(b - a, c - a)), base, mass_row, thickness, friction,
                                        particle_flags, particle_inv_mass, particle_q_start, particle_q_in,
                                        correction, count)

            # i as an end of an edge of an EE pair: the edges this triangle reports.
            edges = surface.triangle_edges[other]
            for m in range(3):
                f = edges[m]
                if surface.edge_owner[f] == other:
                    near_edge = surface.edge[f]
                    p2 = vec3(particle_q_start[base + near_edge[0]])
                    q2 = vec3(particle_q_start[base + near_edge[1]])
                    for k in range(first_edge, last_edge):
                        e = surface.vertex_edge[k]
                        edge = surface.edge[e]
                        if (near_edge[0] != edge[0] and near_edge[0] != edge[1] and near_edge[1] != edge[0]
                                and near_edge[1] != edge[1]):
                            p1 = vec3(particle_q_start[base + edge[0]])
                            q1 = vec3(particle_q_start[base + edge[1]])
                            st = edge_closest(p1, q1, p2, q2)
                            diff = (p1 + st[0] * (q1 - p1)) - (p2 + st[1] * (q2 - p2))
                            nearest = wp.min(nearest, wp.length(diff))
                            if wp.length(diff) < reach:
                                if wp.static(not repel):
                                    count += one
                                if wp.static(repel):
                                    end = int(0)
                                    if edge[1] == i:
                                        end = 1
                                    correction, count, pushed = fold_pair(
                                        end, wp.vec4i(edge[0], edge[1], near_edge[0], near_edge[1]),
                                        vec4(one - st[0], st[0], st[1] - one, -st[1]), diff,
                                        wp.normalize(wp.cross(q1 - p1, q2 - p2)), base, mass_row, thickness,
                                        friction, particle_flags, particle_inv_mass, particle_q_start, particle_q_in,
                                        correction, count)
                                    if end == 0 and e < f:
                                        counted += pushed
        return correction, count, nearest, counted

    return visit_pairs


@functools.cache
def points_kernel(scalar: type):
    """Kernel writing the BVH's single-precision points: the step's start positions."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def bvh_points(particle_q_start: wp.array[vec3], points_out: wp.array[wp.vec3f]):
        p = wp.tid()
        points_out[p] = wp.vec3f(particle_q_start[p])

    return bvh_points


@functools.cache
def repel_kernel(scalar: type):
    """Kernel of the repulsion and friction pass: ``particle_q_in`` (the integrator's result) plus each
    vertex's mean correction, into ``particle_q_out``."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)
    visit_pairs = _pass_funcs(scalar, True)

    @flat_kernel(module="unique", enable_backward=False)
    def repel(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_in: wp.array[vec3],
        # Out:
        particle_q_out: wp.array[vec3],
        counters: wp.array2d[wp.int32],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        base = p - i
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        x = particle_q_in[p]
        particle_q_out[p] = x
        if world_enabled[world] == 0 or surface.vertex_owner[i] < 0:
            return
        if effective_inv_mass(particle_flags[p], particle_inv_mass[mass_row, i]) == scalar(0.0):
            return
        row = wp.min(world, params.shape[0] - 1)
        thickness = params[row, PARAM_THICKNESS]
        correction, count, nearest, counted = visit_pairs(
            i, base, mass_row, surface.mesh[world], scalar(REPULSION_REACH) * thickness, thickness,
            params[row, PARAM_FRICTION], surface, particle_flags, particle_inv_mass, particle_q_start, particle_q_in)
        if count > scalar(0.0):  # a weighted mean: a pair counts by the vertex's weight in it, the sum by 1 at least
            particle_q_out[p] = x + correction / wp.max(count, scalar(1.0))
        if counted > 0:
            wp.atomic_add(counters, world, COUNT_PAIRS, counted)

    return repel


@functools.cache
def cap_kernel(scalar: type):
    """Kernel of the displacement cap: each vertex of ``particle_q_in`` (the repelled result) moved back
    toward ``particle_q_start`` until its displacement is at most γ·min(r, d); writes the state's positions
    and, where they changed, its velocities (Δx / h)."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)
    visit_pairs = _pass_funcs(scalar, False)

    @flat_kernel(module="unique", enable_backward=False)
    def cap(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_in: wp.array[vec3],
        dt: scalar,
        # State in and out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        # Out:
        counters: wp.array2d[wp.int32],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        base = p - i
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        if world_enabled[world] == 0 or surface.vertex_owner[i] < 0:
            return
        if effective_inv_mass(particle_flags[p], particle_inv_mass[mass_row, i]) == scalar(0.0):
            return
        row = wp.min(world, params.shape[0] - 1)
        thickness = params[row, PARAM_THICKNESS]
        relaxation = params[row, PARAM_RELAXATION]
        start = particle_q_start[p]
        x = particle_q_in[p]
        step = wp.length(x - start)
        unbounded = step / relaxation  # the search radius at which the cap would allow the whole step
        reach = wp.min(unbounded, scalar(SEARCH_REACH) * thickness)
        allowed = step
        if reach < unbounded:
            allowed = relaxation * reach
        if reach > scalar(0.0):
            correction, count, nearest, counted = visit_pairs(
                i, base, mass_row, surface.mesh[world], reach, thickness, scalar(0.0), surface, particle_flags,
                particle_inv_mass, particle_q_start, particle_q_start)
            if nearest < reach:
                allowed = wp.min(allowed, relaxation * nearest)
        if step > allowed:
            x = start + (allowed / step) * (x - start)
            wp.atomic_add(counters, world, COUNT_CAPPED, 1)
        moved = x - particle_q_out[p]
        if wp.dot(moved, moved) > scalar(0.0):
            particle_qd_out[p] = (x - start) / dt
            particle_q_out[p] = x

    return cap


@functools.cache
def proximity_kernel(scalar: type):
    """Kernel of the broad phase's audit: per surface vertex, its distance to the nearest pair it belongs to
    within ``reach`` [m] (``reach`` when none) and the number of those pairs, at ``particle_q_start``
    (-1 for vertices off the surface). The tests compare both with an all-pairs float64 reference."""
    vec3 = vec3_type(scalar)
    visit_pairs = _pass_funcs(scalar, False)

    @flat_kernel(module="unique", enable_backward=False)
    def proximity(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        surface: Surface,
        # State in:
        particle_q_start: wp.array[vec3],
        reach: scalar,
        # Out:
        nearest_out: wp.array[scalar],
        count_out: wp.array[wp.int32],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        nearest_out[p] = reach
        count_out[p] = -1
        if surface.vertex_owner[i] < 0:
            return
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        correction, count, nearest, counted = visit_pairs(
            i, p - i, mass_row, surface.mesh[world], reach, reach, scalar(0.0), surface, particle_flags,
            particle_inv_mass, particle_q_start, particle_q_start)
        nearest_out[p] = nearest
        count_out[p] = int(count)

    return proximity
