"""The self-collision pass's pair cache: the broad phase runs when the pairs it listed may no longer hold every
pair the pass needs, not every step.

The cache of a world is the list of vertex–triangle and edge–edge pairs closer than R = ``CACHE_REACH`` τ at
its *anchor* positions xᵃ (the step's start when it was built), with a CSR of their vertices, in the layout
of ``kernels/selfcontact.py``'s pair buffers. Every point of a primitive is a convex combination of its
vertices, and a translation c of all of them changes no distance, so while every surface vertex stays
within m of its anchor moved by c, a pair's distance differs from its distance at the anchor by at most 2m.
c is the world's reference vertex's displacement from its anchor (a fixed surface vertex): a cloth that
falls or slides as a whole keeps its cache. Each step:

1. ``check_kernel``: a world whose surface vertex drifted further than m = (R - REPULSION_REACH τ)/2 (less a
   slack for rounding) from its anchor moved by c at the step's start x⁰ is flagged for a rebuild
   (FLAG_REBUILD): pairs outside the cache are then at least REPULSION_REACH τ apart at x⁰. The world's largest kinematic displacement K_w
   of the step is reduced into FLAG_KINEMATIC (an integer maximum of K_w rounded up, order-free). A world
   that was never built has R = 0 and is flagged; so is one whose τ grew or whose state was replaced.
2. The flagged worlds' broad phase (BVH refit and queries, as ``kernels/selfcontact.py``) at x⁰ with reach R,
   then ``anchor_kernel`` (xᵃ = x⁰, R = CACHE_REACH τ): a conditional graph node, launched only when a world
   is flagged.
3. The repulsion runs over the cache: its narrow phase keeps the pairs closer than REPULSION_REACH τ at x⁰,
   which the cache holds all of (1.), with the same distance arithmetic as the broad phase: the same pairs,
   summed in the same key order, as a list cut at that reach — the same bits.
4. The cap: a pair outside the cache has D ≥ REPULSION_REACH τ at x⁰ and K ≤ K_w, so the cap would keep it
   (max δ > γ (D - K)) only if some free vertex of the world moved further than γ (REPULSION_REACH τ - K_w).
   The repulsion's gather flags the worlds where one does, or whose cache overflowed (FLAG_FALLBACK); they
   run the cap's swept broad phase as before (a conditional node). The others test each cached pair as the
   swept broad phase would (``cap_bounds_kernel``: the same single-precision swept boxes, the same overlap
   and keep tests), so the cap keeps exactly the pairs it kept before, and ends at the same bits.

The cache changes the work and never the answer: results equal those of a broad phase every step, whenever
it was built.
"""

import functools

import warp as wp

from .flatten import flat_kernel
from .kinematics import particle_funcs
from .precision import vec3_type
from .selfcontact import (
    BOX_PAD,
    CACHE_REACH,
    COUNT_FALLBACKS,
    COUNT_REBUILDS,
    FLAG_FALLBACK,
    FLAG_KINEMATIC,
    FLAG_REBUILD,
    KINEMATIC_STEPS,
    PARAM_RELAXATION,
    PARAM_THICKNESS,
    REPULSION_REACH,
    SAFETY,
    SEARCH_REACH,
    Pairs,
    Surface,
    _pair_funcs,
    _vertex_extent,
    flag_slot,
    geometry_funcs,
    raise_flag,
)
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})


@wp.func
def base_index(world: int, particle_count: int):
    """World ``world``'s first entry in a state's arrays."""
    return world * particle_count

#: Bound stored for a cached pair the cap does not keep (no bound).
NO_BOUND = 1.0e30


@functools.cache
def check_kernel(scalar: type):
    """Kernel of the cache's check (module docstring, 1.), one thread per particle of every world."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)

    @flat_kernel(module="unique", enable_backward=False)
    def check(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        cache_reach: wp.array[scalar],
        cache_anchor: wp.array[vec3],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_end: wp.array[vec3],
        # Out:
        flags_out: wp.array[wp.int32],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if world_enabled[world] == 0 or surface.vertex_owner[i] < 0:
            return
        world_count = cache_reach.shape[0]
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        thickness = params[wp.min(world, params.shape[0] - 1), PARAM_THICKNESS]
        start = particle_q_start[p]
        # Drift relative to the world's reference vertex (a middle triangle's first corner): a translation of the
        # whole surface changes no pair's distance.
        ref = base_index(world, particle_count) + surface.triangle[surface.triangle.shape[0] // 2][0]
        shift = particle_q_start[ref] - cache_anchor[ref]
        anchor = cache_anchor[p] + shift
        drift = wp.length(start - anchor)
        margin = (scalar(0.5) * (cache_reach[world] - scalar(REPULSION_REACH) * thickness) * scalar(1.0 - SAFETY)
                  - scalar(BOX_PAD) * (wp.max(wp.abs(start)) + wp.max(wp.abs(anchor)) + wp.max(wp.abs(shift))
                                       + scalar(1.0)))
        if not (drift <= margin):  # NaN included
            raise_flag(flags_out, FLAG_REBUILD, world, world_count)
        if effective_inv_mass(particle_flags[p], particle_inv_mass[mass_row, i]) == scalar(0.0):
            steps = wp.length(particle_q_end[p] - start) / thickness * scalar(KINEMATIC_STEPS)
            level = int(1 << 30)
            if steps < scalar(1 << 29):  # else (or NaN) the largest level
                level = int(steps) + 1  # rounded up
            wp.atomic_max(flags_out, flag_slot(FLAG_KINEMATIC, world, world_count), level)

    return check


@functools.cache
def anchor_kernel(scalar: type):
    """Kernel ending a rebuild (module docstring, 2.): the flagged worlds' anchors become the step's start and
    their reach CACHE_REACH τ."""
    vec3 = vec3_type(scalar)

    @flat_kernel(module="unique", enable_backward=False)
    def anchor(
        # Model:
        particle_count: int,
        params: wp.array2d[scalar],
        flags: wp.array[wp.int32],
        # State in:
        particle_q_start: wp.array[vec3],
        # Out:
        cache_reach_out: wp.array[scalar],
        cache_anchor_out: wp.array[vec3],
        counters_out: wp.array2d[wp.int32],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if flags[flag_slot(FLAG_REBUILD, world, cache_reach_out.shape[0])] == 0:
            return
        cache_anchor_out[p] = particle_q_start[p]
        if i == 0:
            cache_reach_out[world] = scalar(CACHE_REACH) * params[wp.min(world, params.shape[0] - 1), PARAM_THICKNESS]
            counters_out[world, COUNT_REBUILDS] += 1  # one thread per world

    return anchor


@functools.cache
def cap_bounds_kernel(scalar: type):
    """Kernel of the cap's narrow phase over the cache (module docstring, 4.), one thread per particle of every
    world taking its world's slots local, local + particle_count, ...: each cached pair's D - K where the swept
    broad phase would have kept it (its swept single-precision boxes overlap and max δ > γ (D - K) > 0),
    ``NO_BOUND`` elsewhere. Worlds flagged FLAG_FALLBACK are skipped (their cap reads the swept list)."""
    vec3 = vec3_type(scalar)
    triangle_closest, edge_closest = geometry_funcs(scalar)
    box_of, _, _, sweep_bounds, _ = _pair_funcs(scalar)
    extend = _vertex_extent(scalar, True)

    @wp.func
    def boxes_overlap(lower_a: vec3, upper_a: vec3, lower_b: vec3, upper_b: vec3):
        return (lower_a[0] <= upper_b[0] and lower_a[1] <= upper_b[1] and lower_a[2] <= upper_b[2]
                and upper_a[0] >= lower_b[0] and upper_a[1] >= lower_b[1] and upper_a[2] >= lower_b[2])

    @wp.func
    def swept_box(ends: wp.vec3i, corners: int, base: int, mass_row: int, limit: scalar,
                  particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
                  particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3]):
        """The swept box of a primitive's first ``corners`` vertices, unpadded, in the broad phase's order."""
        lower = particle_q_start[base + ends[0]]
        upper = lower
        for k in range(corners):
            lower, upper = extend(lower, upper, base + ends[k], ends[k], mass_row, particle_flags, particle_inv_mass,
                                  particle_q_start, particle_q_end, limit)
        return lower, upper

    @wp.func
    def bound_of(
        s: int, base: int, mass_row: int, relaxation: scalar, limit: scalar, particle_count: int,
        particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar], surface: Surface, cache: Pairs,
        particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3],
    ):
        triangle_count = surface.triangle.shape[0]
        key = cache.key[s]
        vertex = cache.vertex[s]
        zero = scalar(0.0)
        distance = zero
        if key < wp.int64(particle_count) * wp.int64(triangle_count):  # VT: the vertex's query box, the leaf's box
            t = int(key % wp.int64(triangle_count))
            tri = surface.triangle[t]
            lower, upper = swept_box(wp.vec3i(vertex[0], vertex[0], vertex[0]), 2, base, mass_row, limit,
                                     particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
            query_lower, query_upper = box_of(lower, upper, zero)
            lower, upper = swept_box(tri, 3, base, mass_row, limit, particle_flags, particle_inv_mass,
                                     particle_q_start, particle_q_end)
            leaf_lower, leaf_upper = box_of(lower, upper, zero)
            if not boxes_overlap(vec3(query_lower), vec3(query_upper), vec3(leaf_lower), vec3(leaf_upper)):
                return scalar(NO_BOUND)
            p = particle_q_start[base + vertex[0]]
            a = particle_q_start[base + vertex[1]]
            b = particle_q_start[base + vertex[2]]
            c = particle_q_start[base + vertex[3]]
            bary = triangle_closest(p, a, b, c)
            distance = wp.length(p - (bary[0] * a + bary[1] * b + bary[2] * c))
        else:  # EE: the lower edge's query box, the other edge's owner triangle's leaf box, the other edge's box
            rest = key - wp.int64(particle_count) * wp.int64(triangle_count)
            f = int(rest % wp.int64(surface.edge.shape[0]))
            tri = surface.triangle[surface.edge_owner[f]]
            lower, upper = swept_box(wp.vec3i(vertex[0], vertex[1], vertex[1]), 2, base, mass_row, limit,
                                     particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
            query_lower, query_upper = box_of(lower, upper, zero)
            lower, upper = swept_box(tri, 3, base, mass_row, limit, particle_flags, particle_inv_mass,
                                     particle_q_start, particle_q_end)
            leaf_lower, leaf_upper = box_of(lower, upper, zero)
            if not boxes_overlap(vec3(query_lower), vec3(query_upper), vec3(leaf_lower), vec3(leaf_upper)):
                return scalar(NO_BOUND)
            other_lower, other_upper = swept_box(wp.vec3i(vertex[2], vertex[3], vertex[3]), 2, base, mass_row, limit,
                                                 particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
            if not boxes_overlap(other_lower, other_upper, vec3(query_lower), vec3(query_upper)):
                return scalar(NO_BOUND)
            p1 = particle_q_start[base + vertex[0]]
            q1 = particle_q_start[base + vertex[1]]
            p2 = particle_q_start[base + vertex[2]]
            q2 = particle_q_start[base + vertex[3]]
            st = edge_closest(p1, q1, p2, q2)
            distance = wp.length((p1 + st[0] * (q1 - p1)) - (p2 + st[1] * (q2 - p2)))
        kinematic, free_step = sweep_bounds(vertex, base, mass_row, limit, particle_flags, particle_inv_mass,
                                            particle_q_start, particle_q_end)
        gap = distance - kinematic
        if gap > zero and free_step > relaxation * gap:
            return gap
        return scalar(NO_BOUND)

    @flat_kernel(module="unique", enable_backward=False)
    def cap_bounds(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        cache: Pairs,
        flags: wp.array[wp.int32],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_end: wp.array[vec3],
        # Out:
        cache_bound_out: wp.array[scalar],
        counters_out: wp.array2d[wp.int32],
    ):
        p = wp.tid()
        world, local = world_and_index(p, particle_count)
        world_count = cache.count.shape[0]
        if world_enabled[world] == 0:
            return
        if flags[flag_slot(FLAG_FALLBACK, world, world_count)] != 0:
            if local == 0:
                counters_out[world, COUNT_FALLBACKS] += 1  # one thread per world
            return
        capacity = cache.key.shape[0] // world_count
        base = world * particle_count
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        row = wp.min(world, params.shape[0] - 1)
        relaxation = params[row, PARAM_RELAXATION]
        limit = relaxation * scalar(SEARCH_REACH) * params[row, PARAM_THICKNESS]
        for slot in range(local, wp.min(cache.count[world], capacity), particle_count):
            s = world * capacity + slot
            cache_bound_out[s] = bound_of(s, base, mass_row, relaxation, limit, particle_count, particle_flags,
                                          particle_inv_mass, surface, cache, particle_q_start, particle_q_end)

    return cap_bounds
