"""The self-collision pass's displacement cap (``kernels/selfcontact.py``'s module docstring, 2., gives the cap and
its proof): each kept pair's separating plane and its sides' shares (``plane_funcs``), the first pass along each
free vertex's repelled step (``cap_gather_kernel``), the later passes that place a jammed vertex again after its
neighbours made room (``cap_place_kernel``, ``cap_mark_kernel``), and the count of the pairs left beyond the cap
(``cap_check_kernel``). The kept pairs are the cache's (``selfcontact_cache.cap_bounds_kernel``) or the swept broad
phase's list (``selfcontact.broad_kernel``)."""

import functools

import warp as wp

from .flatten import flat_kernel
from .kinematics import is_kinematic, particle_funcs
from .precision import vec3_type
from .selfcontact import (
    BOX_PAD,
    CAP_FLOOR,
    COUNT_CAPPED,
    COUNT_OUTRUN,
    COUNT_SQUEEZED,
    FLAG_FALLBACK,
    NO_BOUND,
    PARAM_RELAXATION,
    PARAM_THICKNESS,
    SEARCH_REACH,
    Pairs,
    Surface,
    _pair_funcs,
    cube_reach_func,
    flag_slot,
    geometry_funcs,
)
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})


@functools.cache
def plane_funcs(scalar: type):
    """The separating planes of the cap's pairs (module docstring, 2.), in precision ``scalar``:

    ``pair_plane(vt, vertex, base, particle_q_start) -> (n, gap)``: n the unit vector from side B's closest point
    to side A's at the step's start (side A: a VT pair's vertex, an EE pair's first edge; side B: the triangle, the
    second edge; a normal of the pair where the points coincide), and the gap D_n = min over A's vertices of n·x
    - max over B's of n·x (the width of the slab between the two primitives along n: D where n is exact).

    ``pair_shares(vt, vertex, base, mass_row, relaxation, floor, particle_flags, particle_inv_mass, particle_q_start,
    particle_q_end) -> (n, shares, gap)``: with G = D_n - 2 pad (pad the rounding pad of the coordinates) and the room
    G' = max(G - h, 0) above the floor h = ``floor`` (CAP_FLOOR τ), each side's kinematic approach K_A, K_B (the
    largest of its kinematic vertices' displacements toward the other side along n, at least 0) and the share of
    each side's free vertices, ``shares`` = (s_A, s_B): a free vertex of A approaches B along n by at most
    s_A = min(γ (G' - K_B), (1 - γ) G' - K_B), likewise for B (negative: it must give way; 0 for a pair at the floor
    or below without pins: it may part, not close in)."""
    vec3 = vec3_type(scalar)
    vec2 = wp.types.vector(2, scalar)
    triangle_closest, edge_closest = geometry_funcs(scalar)
    is_free = _pair_funcs(scalar)[2]

    @wp.func
    def on_side_a(vt: bool, role: int):
        """Whether a pair's vertex ``role`` (0-3, as ``Pairs.vertex``) is on side A."""
        return role == 0 or (role == 1 and not vt)

    @wp.func
    def slab(vt: bool, n: vec3, x0: vec3, x1: vec3, x2: vec3, x3: vec3):
        """The width of the slab between the pair's sides along n: min over A's vertices of n·x - max over B's."""
        low_a = wp.dot(n, x0)
        high_b = wp.dot(n, x3)
        if vt:
            high_b = wp.max(high_b, wp.max(wp.dot(n, x1), wp.dot(n, x2)))
        else:
            low_a = wp.min(low_a, wp.dot(n, x1))
            high_b = wp.max(high_b, wp.dot(n, x2))
        return low_a - high_b

    @wp.func
    def pair_plane(vt: bool, vertex: wp.vec4i, base: int, particle_q_start: wp.array[vec3]):
        x0 = particle_q_start[base + vertex[0]]
        x1 = particle_q_start[base + vertex[1]]
        x2 = particle_q_start[base + vertex[2]]
        x3 = particle_q_start[base + vertex[3]]
        diff = vec3(scalar(0.0))
        normal = vec3(scalar(0.0))
        if vt:
            bary = triangle_closest(x0, x1, x2, x3)
            diff = x0 - (bary[0] * x1 + bary[1] * x2 + bary[2] * x3)
            normal = wp.cross(x2 - x1, x3 - x1)
            if wp.dot(normal, x0 - x1) < scalar(0.0):
                normal = -normal
        else:
            st = edge_closest(x0, x1, x2, x3)
            diff = (x0 + st[0] * (x1 - x0)) - (x2 + st[1] * (x3 - x2))
            normal = wp.cross(x1 - x0, x3 - x2)
            if wp.dot(normal, diff) < scalar(0.0):
                normal = -normal
        # Two candidates, the wider slab kept: the closest points' direction (exact in exact arithmetic, but its
        # rounding, |δx| / D, tilts it where the pair is close and long), and the triangle's normal or the edges'
        # cross product (from the elements' own sides: accurate, and the same direction where the closest points
        # are inner points).
        n = vec3(scalar(0.0))
        width = scalar(-NO_BOUND)
        d = wp.length(diff)
        if d > scalar(0.0):
            n = diff / d
            width = slab(vt, n, x0, x1, x2, x3)
        if wp.length(normal) > scalar(0.0):
            m = wp.normalize(normal)
            other = slab(vt, m, x0, x1, x2, x3)
            if other > width:
                n = m
                width = other
        return n, width

    @wp.func
    def pair_shares(
        vt: bool, vertex: wp.vec4i, base: int, mass_row: int, relaxation: scalar, floor: scalar,
        particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
        particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3],
    ):
        n, width = pair_plane(vt, vertex, base, particle_q_start)
        zero = scalar(0.0)
        kinematic_a = zero
        kinematic_b = zero
        pad = zero
        for k in range(4):
            j = base + vertex[k]
            start = particle_q_start[j]
            pad = wp.max(pad, wp.max(wp.abs(start)))
            if not is_free(particle_flags[j], particle_inv_mass[mass_row, vertex[k]]):
                toward = wp.dot(n, particle_q_end[j] - start)  # along n: away from B for side A, toward A for B
                if on_side_a(vt, k):
                    kinematic_a = wp.max(kinematic_a, -toward)
                else:
                    kinematic_b = wp.max(kinematic_b, toward)
        gap = width - scalar(2.0 * BOX_PAD) * (pad + scalar(1.0))
        room = wp.max(gap - floor, zero)
        shares = vec2(wp.min(relaxation * (room - kinematic_b), (scalar(1.0) - relaxation) * room - kinematic_b),
                      wp.min(relaxation * (room - kinematic_a), (scalar(1.0) - relaxation) * room - kinematic_a))
        return n, shares, gap

    return on_side_a, pair_plane, pair_shares


@functools.cache
def cap_gather_kernel(scalar: type):
    """Kernel of the displacement cap (module docstring, 2.): each free surface vertex of ``particle_q_in`` (the
    repelled result), its step Δ̂ first limited to γ SEARCH_REACH τ, ends at x⁰ + s Δ̂ with s the largest in [0, 1]
    whose approach along each kept pair's separating direction is at most its side's share (``plane_funcs``; a
    vertex that retreats along it takes the whole step), and unless a share asks it to give way, whose length is
    at most γ (D - K - pad) of each kept pair; the kept pairs are the cached pairs with a bound
    (``cap_bounds_kernel``), or in a world flagged FLAG_FALLBACK the swept broad phase's list (where that list
    overflowed: s = 0). A vertex that gives way less than a share asks is marked jammed (``jammed_out``: a mover of
    the later passes, ``cap_place_kernel``). Where no share asks it to give way, a capped end whose rounding
    approaches a pair that leaves the vertex no approach (a share of 0, ``rounds_in``) is held at x⁰. Writes the
    state's positions and, where they changed, its velocities (Δx / h)."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)
    on_side_a, _, pair_shares = plane_funcs(scalar)

    @wp.func
    def bound(
        plane: scalar, allowed: scalar, need: scalar, floored: bool, entry: int, pairs: Pairs,
        gap_less_kinematic: scalar, pad: scalar, base: int, mass_row: int, relaxation: scalar, floor: scalar,
        vertex_pairs: int, step: vec3, particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
        particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3],
    ):
        """The vertex's bounds narrowed by the pair of ``entry`` (slot · 4 + role; D - K its ``gap_less_kinematic``):
        ``plane``, the largest s whose step s Δ̂ approaches the other side along n by at most the vertex's share;
        ``allowed``, the length γ (D - K - pad) at most; ``need``, the smallest s that gives way as far as a negative
        share asks (above 1 where no s does; 0 where no share is negative); ``floored``, whether some pair so far
        leaves the vertex no approach at all (a share of 0 or less: ``rounds_in`` checks its rounded end)."""
        slot = entry // 4
        role = entry - 4 * slot
        allowed = wp.min(allowed, relaxation * wp.max(gap_less_kinematic - pad, scalar(0.0)))
        vt = pairs.key[slot] < wp.int64(vertex_pairs)
        n, shares, gap = pair_shares(vt, pairs.vertex[slot], base, mass_row, relaxation, floor, particle_flags,
                                     particle_inv_mass, particle_q_start, particle_q_end)
        if not (gap > scalar(0.0)):  # no separation the precision resolves: the vertex holds
            return scalar(0.0), scalar(0.0), need, floored
        share = shares[1]
        approach = wp.dot(n, step)  # side B's approach toward A per unit of s
        if on_side_a(vt, role):
            share = shares[0]
            approach = -approach
        if approach > scalar(0.0):
            plane = wp.min(plane, share / approach)
        if share < scalar(0.0):
            if approach < scalar(0.0):
                need = wp.max(need, share / approach)
            else:
                need = scalar(2.0)
        return plane, allowed, need, floored or share <= scalar(0.0)

    @wp.func
    def rounds_in(
        entry: int, pairs: Pairs, moved: vec3, base: int, mass_row: int, relaxation: scalar, floor: scalar,
        vertex_pairs: int, particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
        particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3],
    ):
        """Whether the vertex's rounded displacement ``moved`` (its capped end, as stored, less its start: exact)
        approaches the other side of the pair of ``entry`` along n where its share is 0 or less."""
        slot = entry // 4
        vt = pairs.key[slot] < wp.int64(vertex_pairs)
        n, shares, gap = pair_shares(vt, pairs.vertex[slot], base, mass_row, relaxation, floor, particle_flags,
                                     particle_inv_mass, particle_q_start, particle_q_end)
        share = shares[1]
        approach = wp.dot(n, moved)
        if on_side_a(vt, entry - 4 * slot):
            share = shares[0]
            approach = -approach
        return share <= scalar(0.0) and approach > scalar(0.0)

    @flat_kernel(module="unique", enable_backward=False)
    def cap(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        cache: Pairs,
        cache_bound: wp.array[scalar],
        pairs: Pairs,
        pair_distance: wp.array[scalar],
        flags: wp.array[wp.int32],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_in: wp.array[vec3],
        dt: scalar,
        # State in and out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        # Out:
        jammed_out: wp.array[wp.int32],
        counters_out: wp.array2d[wp.int32],
    ):
        p = wp.tid()
        jammed_out[p] = 0
        world, i = world_and_index(p, particle_count)
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        if world_enabled[world] == 0 or surface.vertex_owner[i] < 0:
            return
        if effective_inv_mass(particle_flags[p], particle_inv_mass[mass_row, i]) == scalar(0.0):
            return
        row = wp.min(world, params.shape[0] - 1)
        relaxation = params[row, PARAM_RELAXATION]
        floor = scalar(CAP_FLOOR) * params[row, PARAM_THICKNESS]
        base = world * particle_count
        vertex_pairs = particle_count * surface.triangle.shape[0]
        start = particle_q_start[p]
        x = particle_q_in[p]
        length = wp.length(x - start)
        limit = relaxation * scalar(SEARCH_REACH) * params[row, PARAM_THICKNESS]
        step = x - start
        if length > limit:
            step = (limit / length) * step
        # A pair's D - K carries the rounding of D (computed from the rounded positions): the length bound takes off a
        # pad above it, so a pair closer than the precision resolves holds its free vertices where they are.
        pad = scalar(BOX_PAD) * (wp.max(wp.abs(start)) + scalar(1.0))
        plane = scalar(1.0)
        allowed = wp.min(length, limit)
        need = scalar(0.0)
        floored = bool(False)
        fallback = flags[flag_slot(FLAG_FALLBACK, world, pairs.count.shape[0])] != 0
        list_pairs = cache
        first = cache.vertex_start[p]
        last = first + cache.vertex_count[p]
        if fallback:
            list_pairs = pairs
            first = pairs.vertex_start[p]
            last = first + pairs.vertex_count[p]
            if pairs.count[world] > pairs.key.shape[0] // pairs.count.shape[0]:
                plane = scalar(0.0)  # overflow: a listed pair may be missing, so nothing free moves
                allowed = scalar(0.0)
                last = first
        for a in range(first, last):
            e = list_pairs.entry[a]
            if fallback:
                plane, allowed, need, floored = bound(plane, allowed, need, floored, e, pairs, pair_distance[e // 4],
                                                      pad, base, mass_row, relaxation, floor, vertex_pairs, step,
                                                      particle_flags, particle_inv_mass, particle_q_start,
                                                      particle_q_in)
            elif cache_bound[e // 4] < scalar(NO_BOUND):
                plane, allowed, need, floored = bound(plane, allowed, need, floored, e, cache, cache_bound[e // 4],
                                                      pad, base, mass_row, relaxation, floor, vertex_pairs, step,
                                                      particle_flags, particle_inv_mass, particle_q_start,
                                                      particle_q_in)
        plane = wp.max(plane, scalar(0.0))
        if need > plane:  # a push that does not fit: the later passes (cap_place_kernel) place it
            jammed_out[p] = 1
        if need > scalar(0.0):  # asked to give way: the planes alone bound it
            if plane < scalar(1.0) or length > limit:
                x = start + plane * step
                wp.atomic_add(counters_out, world, COUNT_CAPPED, 1)
        else:  # the length bound too, as tight as the planes' along the step
            allowed = wp.min(allowed, plane * wp.min(length, limit))
            if length > allowed:
                repelled = x
                x = start + (allowed / length) * (repelled - start)
                # Rounded past the bound (about half the time: the rounding of x - start goes either way): pulled back
                # by the pad, far above the coordinates' rounding; held where it started only where the bound is below
                # that (a pair closer than the precision resolves).
                if not (wp.length(x - start) <= allowed):
                    x = start
                    if allowed > pad:
                        pulled = start + ((allowed - pad) / length) * (repelled - start)
                        if wp.length(pulled - start) <= allowed:
                            x = pulled
                # A pair with no room (share 0: G' = 0, within the pads of the floor or below it) has no pad for the
                # rounding either: the capped end's coordinates round apart (a small one keeps its part of the step,
                # a large one drops it), so it may approach the pair along n where the step retreats, a few ulps a
                # step, which compounds while the pair stays there. Checked on the end as stored; held at x⁰ where
                # it approaches one.
                if floored:
                    for a in range(first, last):
                        e = list_pairs.entry[a]
                        if fallback or cache_bound[e // 4] < scalar(NO_BOUND):
                            if rounds_in(e, list_pairs, x - start, base, mass_row, relaxation, floor, vertex_pairs,
                                         particle_flags, particle_inv_mass, particle_q_start, particle_q_in):
                                x = start
                wp.atomic_add(counters_out, world, COUNT_CAPPED, 1)
        moved = x - particle_q_out[p]
        if wp.dot(moved, moved) > scalar(0.0):
            particle_qd_out[p] = (x - start) / dt
            particle_q_out[p] = x

    return cap


#: Rounds of the cap's later passes (``cap_place_kernel``): alternating projections onto a vertex's bounds.
RELEASE_ROUNDS = 200
#: Roles of the vertices in the cap's later passes (``SelfContact.cap_role``).
ROLE_FROZEN = 0  # stays where it is
ROLE_MOVER = 1  # placed anew by the pass
ROLE_PUSHER = 2  # could not be placed: stays, and the movers make room for where it wanted to go
#: A pusher's role is ROLE_PUSHER + its depth: 0 for a vertex the first pass could not place, 1 + the deepest pusher
#: across its kept pairs for a mover that could not be placed (its distance from the squeeze, in layers). The
#: pushers' pass runs as this many sub-passes, the depths ≡ c (mod PUSHER_COLOURS) in the c-th, the highest c first:
#: two pushers across a kept pair of adjacent depths are never placed in one sub-pass (with two colours, the odd
#: depths go first: depth 1 before the 0 in front of it, 3 before 2).
PUSHER_COLOURS = 2
#: A mover's depth for its bounds (``cap_place_kernel``): beyond every pusher's. A pusher placed in its sub-pass keeps
#: its depth d as the role ROLE_FROZEN - 1 - d (it stays, as ROLE_FROZEN; ``depth_of``): the deeper pushers count it
#: where it went for their wanted points and do not ask it to make room (``cap_mark_kernel``).
MOVER_DEPTH = 1 << 20


@wp.func
def depth_of(role: wp.int32):
    """The depth of a pusher or of a placed pusher of ``role``; MOVER_DEPTH for the others (movers and frozen)."""
    if role >= ROLE_PUSHER:
        return role - ROLE_PUSHER
    if role < ROLE_FROZEN:
        return ROLE_FROZEN - 1 - role
    return MOVER_DEPTH


@wp.func
def in_pass(role: wp.int32, mover_role: int):
    """Whether a vertex of ``role`` is placed by the (sub-)pass of ``mover_role``: ROLE_MOVER for the movers,
    ROLE_PUSHER + c for the pushers whose depth is ≡ c (mod PUSHER_COLOURS)."""
    if mover_role < ROLE_PUSHER:
        return role == mover_role
    return role >= ROLE_PUSHER and (role - ROLE_PUSHER) % PUSHER_COLOURS == mover_role - ROLE_PUSHER


@functools.cache
def cap_place_kernel(scalar: type):
    """Kernel of the cap's later passes (module docstring, 2.), after ``cap_gather_kernel``: each vertex whose role is
    ``mover_role`` is placed anew, the others stay. Of each kept pair its approach along n is at most the room the
    other side leaves, (1 - γ) G minus that side's largest approach (a pusher's, in every pass: the larger of where
    it is and where it wanted to go), and where the other side holds a vertex placed in the same pass, also at most
    its share.
    Its displacement Δ stays in its swept box (the cube of half-width ρ = ``cube_reach``, and its step's box) and no
    longer than max(δ, ρ): alternating projections onto these sets (``RELEASE_ROUNDS``) from where it is, accepted where every
    bound then holds; else it stays, becomes a pusher (``role_out``) and ``desired_out`` keeps where it wants to go:
    the same projections onto its bounds against what cannot make room only (the other sides' kinematic vertices and
    the pushers no deeper than it, as they want to go, those of this pass included), its box and its ball, for which
    the next pass's movers and the deeper pushers make room. ``mover_role`` ROLE_PUSHER + c places the pushers of
    colour c (``in_pass``); a mover that stays takes its depth (``PUSHER_COLOURS``). With
    ``clear``, the other vertices' ``role_out`` is set to ROLE_FROZEN (no memset inside the conditional node)."""
    vec3 = vec3_type(scalar)
    on_side_a, _, pair_shares = plane_funcs(scalar)
    is_free = _pair_funcs(scalar)[2]
    cube_reach = cube_reach_func(scalar)

    @wp.func
    def half_space(
        entry: int, pairs: Pairs, base: int, mass_row: int, relaxation: scalar, floor: scalar, vertex_pairs: int,
        mover_role: int, depth: int,
        particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar], role: wp.array[wp.int32],
        desired: wp.array[vec3], particle_q_start: wp.array[vec3], particle_q_in: wp.array[vec3],
        particle_q_placed: wp.array[vec3],
    ):
        """(g, a, resolved, a_held, held): the bound g·Δ ≤ a (g unit: the vertex's direction of approach along n) of
        the pair of ``entry`` (slot · 4 + role); ``resolved`` False where the pair is closer than the precision
        resolves. ``a_held`` is the same bound counting only the other side's vertices that cannot make room (its
        kinematic vertices and the pushers, as they want to go), ``held`` whether it holds any: the bound that stays
        when the free vertices there are asked to move away (``cap_mark_kernel``). A pusher counts as the larger of
        where it is and where it wants to go in both bounds, also in the pushers' own pass (where it is placed beside
        this vertex and the share bounds the pair as well): a pusher that another must make room for is not placed
        against where that one stands (which it already keeps, so it would stay and lose its role)."""
        slot = entry // 4
        k_mine = entry - 4 * slot
        vt = pairs.key[slot] < wp.int64(vertex_pairs)
        vertex = pairs.vertex[slot]
        n, shares, gap = pair_shares(vt, vertex, base, mass_row, relaxation, floor, particle_flags, particle_inv_mass,
                                     particle_q_start, particle_q_in)
        mine = on_side_a(vt, k_mine)
        sign = scalar(1.0)  # the other side's approach toward mine per unit of n·Δ: +1 for B, -1 for A
        share = shares[0]
        if not mine:
            sign = scalar(-1.0)
            share = shares[1]
        moving = False
        held = False
        other = scalar(-NO_BOUND)
        other_held = scalar(-NO_BOUND)
        for k in range(4):
            if on_side_a(vt, k) != mine:
                j = base + vertex[k]
                start = particle_q_start[j]
                approach = sign * wp.dot(n, particle_q_placed[j] - start)
                other = wp.max(other, approach)
                if not is_free(particle_flags[j], particle_inv_mass[mass_row, vertex[k]]):
                    held = True
                    other_held = wp.max(other_held, approach)
                if in_pass(role[j], mover_role):
                    moving = True
                if role[j] >= ROLE_PUSHER:
                    wanted = wp.max(approach, sign * wp.dot(n, desired[j] - start))
                    other = wp.max(other, wanted)
                    if role[j] - ROLE_PUSHER <= depth:  # a deeper pusher, further back, makes room for this one
                        held = True
                        other_held = wp.max(other_held, wanted)
                elif role[j] < ROLE_FROZEN and depth_of(role[j]) <= depth:  # a placed pusher in front of this one
                    held = True
                    other_held = wp.max(other_held, approach)
        free_room = (scalar(1.0) - relaxation) * wp.max(gap - floor, scalar(0.0))
        room = free_room - other
        if moving:
            room = wp.min(room, share)
        return -sign * n, room, gap > scalar(0.0), free_room - other_held, held

    @wp.func
    def project(
        start_point: vec3, held_only: bool, list_pairs: Pairs, first: int, last: int, fallback: bool,
        cache_bound: wp.array[scalar], base: int, mass_row: int, relaxation: scalar, floor: scalar, vertex_pairs: int,
        mover_role: int, depth: int, pad: scalar, low: vec3, high: vec3, radius: scalar,
        particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar], role: wp.array[wp.int32],
        desired: wp.array[vec3], particle_q_start: wp.array[vec3], particle_q_in: wp.array[vec3],
        particle_q_placed: wp.array[vec3],
    ):
        """Alternating projections (at most RELEASE_ROUNDS) of a displacement onto the vertex's bounds (``held_only``:
        only those against what cannot make room, ``half_space``'s ``a_held``), then onto its box [``low``, ``high``]
        and its ball of ``radius``: (the displacement, whether every pair's plane was resolved). A round that leaves
        the point as it was ends them: the later rounds would repeat it (on the CPU the same bits as all the rounds;
        on CUDA the vertices placed beside it in the pass may still move, which the share bounds already allow)."""
        point = start_point
        resolved = bool(True)
        for _round in range(RELEASE_ROUNDS):
            before = point
            for a in range(first, last):
                e = list_pairs.entry[a]
                if fallback or cache_bound[e // 4] < scalar(NO_BOUND):
                    g, room, ok, held_room, held = half_space(e, list_pairs, base, mass_row, relaxation, floor,
                                                              vertex_pairs, mover_role, depth, particle_flags,
                                                              particle_inv_mass, role, desired, particle_q_start,
                                                              particle_q_in, particle_q_placed)
                    resolved = resolved and ok
                    bound = room
                    counted = True
                    if held_only:
                        bound = held_room
                        counted = held
                    over = wp.dot(g, point) - (bound - pad)
                    if counted and over > scalar(0.0):
                        point = point - over * g
            point = wp.min(wp.max(point, low), high)
            size = wp.length(point)
            if size > radius:
                point = (radius / size) * point
            if point[0] == before[0] and point[1] == before[1] and point[2] == before[2]:
                break
        return point, resolved

    @flat_kernel(module="unique", enable_backward=False)
    def place(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        surface: Surface,
        params: wp.array2d[scalar],
        cache: Pairs,
        cache_bound: wp.array[scalar],
        pairs: Pairs,
        flags: wp.array[wp.int32],
        # Control (the pass; ``into`` the role buffer it writes, whose entry of ``loop_out`` it marks):
        mover_role: int,
        clear: int,
        into: int,
        role: wp.array[wp.int32],
        desired: wp.array[vec3],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_in: wp.array[vec3],
        dt: scalar,
        # State in and out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        # Out (``loop_out[LOOP_LEFT]`` set where a vertex of the round's last level stays a pusher:
        # ``cap_loop_gate_kernel``):
        role_out: wp.array[wp.int32],
        desired_out: wp.array[vec3],
        loop_out: wp.array[wp.int32],
    ):
        p = wp.tid()
        if not in_pass(role[p], mover_role):
            if clear != 0:
                role_out[p] = wp.min(role[p], ROLE_FROZEN)  # a placed pusher keeps its depth
            return
        world, i = world_and_index(p, particle_count)
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        row = wp.min(world, params.shape[0] - 1)
        relaxation = params[row, PARAM_RELAXATION]
        floor = scalar(CAP_FLOOR) * params[row, PARAM_THICKNESS]
        base = world * particle_count
        vertex_pairs = particle_count * surface.triangle.shape[0]
        start = particle_q_start[p]
        step = particle_q_in[p] - start
        length = wp.length(step)
        limit = relaxation * scalar(SEARCH_REACH) * params[row, PARAM_THICKNESS]
        if length > limit:
            step = (limit / length) * step
            length = limit
        pad = scalar(BOX_PAD) * (wp.max(wp.abs(start)) + scalar(1.0))
        list_pairs = cache
        first = cache.vertex_start[p]
        last = first + cache.vertex_count[p]
        fallback = flags[flag_slot(FLAG_FALLBACK, world, pairs.count.shape[0])] != 0
        if fallback:
            list_pairs = pairs
            first = pairs.vertex_start[p]
            last = first + pairs.vertex_count[p]
        reach = cube_reach(flags, world, limit)  # ρ: its swept box holds the cube of half-width ρ
        radius = wp.max(length, reach)  # the pairs not kept let it move that far
        low = wp.min(wp.min(step, vec3(scalar(0.0))), vec3(-reach, -reach, -reach))
        high = wp.max(wp.max(step, vec3(scalar(0.0))), vec3(reach, reach, reach))
        # Its depth among the pushers (a mover's: beyond every pusher's, ``in_pass``'s note): the pushers no deeper
        # bound where it wants to go, the deeper ones make room for it.
        depth = int(MOVER_DEPTH)
        if mover_role >= ROLE_PUSHER:
            depth = int(role[p] - ROLE_PUSHER)
        current = particle_q_out[p] - start
        trial, resolved = project(current, False, list_pairs, first, last, fallback, cache_bound, base, mass_row,
                                  relaxation, floor, vertex_pairs, mover_role, depth, pad, low, high, radius,
                                  particle_flags, particle_inv_mass, role, desired, particle_q_start, particle_q_in,
                                  particle_q_out)
        x = start + trial
        moved = x - start  # the end as stored (its coordinates rounded): what every bound must hold for
        holds = bool(resolved)
        for a in range(first, last):
            e = list_pairs.entry[a]
            if fallback or cache_bound[e // 4] < scalar(NO_BOUND):
                g, room, ok, _held_room, _held = half_space(e, list_pairs, base, mass_row, relaxation, floor,
                                                            vertex_pairs, mover_role, depth, particle_flags,
                                                            particle_inv_mass,
                                                            role, desired, particle_q_start, particle_q_in,
                                                            particle_q_out)
                holds = holds and wp.dot(g, moved) <= room
        if holds:
            particle_qd_out[p] = moved / dt
            particle_q_out[p] = x
            role_out[p] = ROLE_FROZEN
            if mover_role >= ROLE_PUSHER:
                role_out[p] = ROLE_FROZEN - 1 - depth
        else:
            # Where it wants to go: its bounds against what cannot make room only (kinematic vertices, earlier
            # pushers), its box and its ball. The free vertices across its other pairs are the next pass's movers
            # (cap_mark_kernel) and make room for that point; a point that also kept their bounds, as they stand,
            # would ask them for no room (the projections' compromise stops short of the pin's bound).
            wanted, _resolved = project(current, True, list_pairs, first, last, fallback, cache_bound, base,
                                        mass_row, relaxation, floor, vertex_pairs, mover_role, depth, pad, low, high,
                                        radius, particle_flags, particle_inv_mass, role, desired, particle_q_start,
                                        particle_q_in, particle_q_out)
            # Its depth: a pusher keeps its own; a mover is one layer behind the deepest pusher across its pairs (0
            # where none: the first pass's jammed vertices). The deepest, not the nearest: a coiled strip's layers lie
            # across pairs from the front pusher too, and the nearest gives a chain's layers one depth, one sub-pass.
            if mover_role < ROLE_PUSHER:
                depth = int(0)
                for a in range(first, last):
                    e = list_pairs.entry[a]
                    if fallback or cache_bound[e // 4] < scalar(NO_BOUND):
                        slot = e // 4
                        vt = list_pairs.key[slot] < wp.int64(vertex_pairs)
                        vertex = list_pairs.vertex[slot]
                        mine = on_side_a(vt, e - 4 * slot)
                        for k in range(4):
                            j = base + vertex[k]
                            if on_side_a(vt, k) != mine and role[j] >= ROLE_PUSHER:
                                depth = wp.max(depth, role[j] - ROLE_PUSHER + 1)
            role_out[p] = ROLE_PUSHER + depth
            desired_out[p] = start + wanted
            if into == wp.static(LEVELS_PER_ROUND - 1):  # the round's last level (and the first pass) write this buffer
                loop_out[LOOP_LEFT] = 1  # another round (the same value from every such thread: no order)

    return place


#: Entries of the cap's loop state (``SelfContact.cap_loop``, int32 [LOOP_SIZE]): the condition of its loop of levels
#: (``wp.capture_while``), whether the last level left a pusher, and the levels run this step.
LOOP_CONDITION = 0
LOOP_LEFT = 1
LOOP_LEVELS = 2
LOOP_SIZE = 3
#: Levels a round of the cap's loop runs (one into each role buffer: the loop's body is the same every round).
LEVELS_PER_ROUND = 2


@functools.cache
def cap_loop_gate_kernel():
    """Kernel (one thread) deciding whether the cap runs another round of levels: where the last pass (into role
    buffer 1) left a pusher and fewer than ``levels`` have run; ``start`` 1 after the first pass (no level run yet).
    It clears the passes' mark, so that it is clear outside the cap's stage."""

    @flat_kernel(module="unique", enable_backward=False)
    def gate(levels: int, start: int, loop_in_out: wp.array[wp.int32]):
        run = int(0)
        if start == 0:
            run = loop_in_out[LOOP_LEVELS] + LEVELS_PER_ROUND
        loop_in_out[LOOP_LEVELS] = run
        more = int(0)
        if loop_in_out[LOOP_LEFT] != 0 and run < levels:
            more = 1
        loop_in_out[LOOP_CONDITION] = more
        loop_in_out[LOOP_LEFT] = 0

    return gate


@functools.cache
def cap_mark_kernel(scalar: type):
    """Kernel marking, after a pass of ``cap_place_kernel``, the free surface vertices across a kept pair from a pusher
    as movers of the next pass (they make room for it; identical writes, no order), but for the pushers and the
    placed pushers no deeper than it (in front of it: it pressed on them, ``depth_of``)."""

    @flat_kernel(module="unique", enable_backward=False)
    def mark(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        surface: Surface,
        cache: Pairs,
        cache_bound: wp.array[scalar],
        pairs: Pairs,
        flags: wp.array[wp.int32],
        # In/out (the pass's roles):
        role_in_out: wp.array[wp.int32],
    ):
        p = wp.tid()
        if role_in_out[p] < ROLE_PUSHER:
            return
        depth = role_in_out[p] - ROLE_PUSHER
        world, i = world_and_index(p, particle_count)
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        base = world * particle_count
        vertex_pairs = particle_count * surface.triangle.shape[0]
        list_pairs = cache
        first = cache.vertex_start[p]
        last = first + cache.vertex_count[p]
        fallback = flags[flag_slot(FLAG_FALLBACK, world, pairs.count.shape[0])] != 0
        if fallback:
            list_pairs = pairs
            first = pairs.vertex_start[p]
            last = first + pairs.vertex_count[p]
        for a in range(first, last):
            e = list_pairs.entry[a]
            if fallback or cache_bound[e // 4] < scalar(NO_BOUND):
                slot = e // 4
                k_mine = e - 4 * slot
                vt = list_pairs.key[slot] < wp.int64(vertex_pairs)
                vertex = list_pairs.vertex[slot]
                mine = (k_mine == 0) or (k_mine == 1 and not vt)
                for k in range(4):
                    side_a = (k == 0) or (k == 1 and not vt)
                    j = base + vertex[k]
                    if side_a != mine and particle_inv_mass[mass_row, vertex[k]] > scalar(0.0):
                        # Not a pusher, nor a placed pusher in front of this one (which it pressed on).
                        if not is_kinematic(particle_flags[j]) and role_in_out[j] < ROLE_PUSHER:
                            if role_in_out[j] >= ROLE_FROZEN or depth_of(role_in_out[j]) > depth:
                                role_in_out[j] = ROLE_MOVER

    return mark


@functools.cache
def cap_check_kernel(scalar: type):
    """Kernel counting the kept pairs the cap could not hold apart (COUNT_OUTRUN), after ``cap_gather_kernel``, one
    thread per particle of every world taking its world's slots local, local + particle_count, ...: a pair some side
    of which approaches the other along its separating direction, by as much as the gap between them or more in all
    (module docstring, 2.: a pin outrunning a free vertex that cannot give way, or two pins closing in); and those
    held apart but pressed below the floor h = CAP_FLOOR τ along it from at or above it (COUNT_SQUEEZED: a pin
    pressing layers that have no room, themselves held by pins; the pair's distance is at least its separation along
    the direction, so a pair not counted here ends at least h apart)."""
    vec3 = vec3_type(scalar)
    on_side_a, pair_plane, _ = plane_funcs(scalar)

    @wp.func
    def beyond(slot: int, pairs: Pairs, base: int, vertex_pairs: int, floor: scalar, particle_q_start: wp.array[vec3],
               particle_q_end: wp.array[vec3]):
        """(outrun, squeezed) of the pair in ``slot``."""
        vt = pairs.key[slot] < wp.int64(vertex_pairs)
        vertex = pairs.vertex[slot]
        n, width = pair_plane(vt, vertex, base, particle_q_start)
        zero = scalar(0.0)
        approach_a = scalar(-NO_BOUND)
        approach_b = scalar(-NO_BOUND)
        pad = zero
        for k in range(4):
            j = base + vertex[k]
            start = particle_q_start[j]
            pad = wp.max(pad, wp.max(wp.abs(start)))
            toward = wp.dot(n, particle_q_end[j] - start)
            if on_side_a(vt, k):
                approach_a = wp.max(approach_a, -toward)
            else:
                approach_b = wp.max(approach_b, toward)
        closing = approach_a > zero or approach_b > zero
        slack = scalar(BOX_PAD) * (pad + scalar(1.0))
        outrun = closing and not (approach_a + approach_b < width - slack)
        squeezed = (closing and not outrun and width >= floor
                    and width - approach_a - approach_b < floor - slack)
        return outrun, squeezed

    @flat_kernel(module="unique", enable_backward=False)
    def cap_check(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        cache: Pairs,
        cache_bound: wp.array[scalar],
        pairs: Pairs,
        flags: wp.array[wp.int32],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_end: wp.array[vec3],
        # Out:
        counters_out: wp.array2d[wp.int32],
    ):
        p = wp.tid()
        world, local = world_and_index(p, particle_count)
        world_count = cache.count.shape[0]
        if world_enabled[world] == 0:
            return
        base = world * particle_count
        vertex_pairs = particle_count * surface.triangle.shape[0]
        floor = scalar(CAP_FLOOR) * params[wp.min(world, params.shape[0] - 1), PARAM_THICKNESS]
        fallback = flags[flag_slot(FLAG_FALLBACK, world, world_count)] != 0
        list_pairs = cache
        if fallback:
            list_pairs = pairs
        capacity = list_pairs.key.shape[0] // world_count
        for slot in range(local, wp.min(list_pairs.count[world], capacity), particle_count):
            s = world * capacity + slot
            if fallback or cache_bound[s] < scalar(NO_BOUND):
                outrun, squeezed = beyond(s, list_pairs, base, vertex_pairs, floor, particle_q_start, particle_q_end)
                if outrun:
                    wp.atomic_add(counters_out, world, COUNT_OUTRUN, 1)
                if squeezed:
                    wp.atomic_add(counters_out, world, COUNT_SQUEEZED, 1)

    return cap_check
