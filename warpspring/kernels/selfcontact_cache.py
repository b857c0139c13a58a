"""The self-collision pass's pair cache: the broad phase runs when the pairs it listed may no longer hold every
pair the pass needs, not every step.

The cache of a world is the list of vertex–triangle and edge–edge pairs closer than ``CACHE_REACH`` τ at
its *anchor* positions xᵃ (the step's start when it was built), with a CSR of their vertices, in the layout
of ``kernels/selfcontact.py``'s pair buffers, and its *watch list*: the pairs between CACHE_REACH τ and
``WATCH_REACH`` τ apart at the anchors (key and vertices only), whose distances each step checks. R, the cache's
reach below, is WATCH_REACH τ (CACHE_REACH τ in a world whose watch list overflowed): every pair closer than R at
the anchors is cached or watched. A cloth's own in-plane pairs (3.5τ apart in the benchmark's 0.1 m grid at
τ = 2 cm) are watched, not cached: the pair stages never walk them, and they stop no drift. Every point of a primitive is a convex combination of its
vertices, p = Σ wᵢ xᵢ, so two points p, q of a pair move apart or together by at most the largest |Δᵢ - Δⱼ| over
a vertex i of one side and j of the other, Δ = x - xᵃ the drifts from the anchors: a pair's distance differs
from its distance at the anchors by at most that. Drifts are measured relative to the world's reference vertex
(a fixed surface vertex), r = Δ - Δ_ref, which changes no difference Δᵢ - Δⱼ: a cloth that falls or slides as a
whole keeps its cache. Each step:

1. ``check_kernel`` reduces, per *patch* (a group of triangles close at rest, ``core/selfcontact.py``'s
   ``surface_patches``; one block each, block-wide integer maxima, no atomics), the box of its corners' drifts r
   at the step's start x⁰ and the box of their positions x⁰, in units of τ / KINEMATIC_STEPS rounded outward and
   padded for rounding; and per world the largest |r| (an integer maximum, order-free). Every vertex and edge lies
   in the boxes of its owner triangle's patch (``vertex_owner``, ``edge_owner``). ``decide_kernel`` keeps the cache
   when every pair outside it stays at least REPULSION_REACH τ apart at x⁰, by either bound: the largest |r| at
   most (R - REPULSION_REACH τ)/2 (less a slack ``SAFETY``), or, for every two patches P, Q (P = Q included):
   their position boxes lie at least REPULSION_REACH τ (1 + SAFETY) apart (every pair across them is that far
   apart now, whatever its drifts), or the largest |r_a - r_b| over a corner a of P and b of Q, read from their
   drift boxes, is at most R - REPULSION_REACH τ (less SAFETY): a pair outside the cache was R apart at its
   anchors and came closer by at most that. A sheet falling past a still part of itself keeps its cache while
   the two stay apart; a patch pair in contact or close, while their relative drift stays small (the patches
   refine the world's single box of drifts, which a sliding skirt spreads along one axis).
   ``watch_kernel`` checks each watched pair's distance at x⁰ (the narrow phase's arithmetic): one closer than
   REPULSION_REACH τ (1 + SAFETY) flags its world. It runs only in the worlds ``decide_kernel`` flags FLAG_WATCH:
   where the same bounds with CACHE_REACH τ for R fail (elsewhere every pair outside the cache, watched or not,
   was CACHE_REACH τ apart at the anchors and the drifts keep it REPULSION_REACH τ apart). The pairs outside the cache are then at least REPULSION_REACH τ
   apart at x⁰: the watched ones by their own distance, the others by the drifts.
   Otherwise the world is flagged for a rebuild (FLAG_REBUILD). A world that was never built has R = 0 and is
   flagged; so is one whose state was replaced. R and the reach of every pair outside the cache (CACHE_REACH τ) are
   the τ of the last build (``cache_reach``, ``cache_floor``), the repulsion's reach the τ of this step: a τ raised
   since leaves less slack (down to a rebuild), never a bound the cache does not hold. The world's largest
   kinematic displacement K_w of the step is reduced into FLAG_KINEMATIC, and its free surface vertices' largest
   step into FLAG_STEP.
2. The flagged worlds' broad phase (BVH refit and queries, as ``kernels/selfcontact.py``) at x⁰, caching the pairs
   within CACHE_REACH τ and watching those within WATCH_REACH τ, then ``anchor_kernel`` (xᵃ = x⁰, R = WATCH_REACH τ,
   or CACHE_REACH τ where the watch list overflowed): a conditional graph node, launched only when a world
   is flagged.
3. The repulsion runs over the cache: its narrow phase keeps the pairs closer than REPULSION_REACH τ at x⁰,
   which the cache holds all of (1.), with the same distance arithmetic as the broad phase: the same pairs,
   summed in the same key order, as a list cut at that reach — the same bits.
4. The cap: a pair outside the cache has D ≥ A_w at x⁰ and K ≤ K_w, so the cap would keep it
   (2 max(K, δ) ≥ D - h or δ > γ (D - K), h = CAP_FLOOR τ its floor) only if K_w ≥ (A_w - h) / 2 or some free
   vertex of the world moved further than min(γ (A_w - K_w), (A_w - h) / 2). A_w is the least distance at x⁰ the
   step's check knows of those pairs (FLAG_APART, each thread of ``decide_kernel`` recording the bound that holds
   for its two patches: their boxes' gap, or the reach at the anchors less their drifts' spread, the build's
   CACHE_REACH τ for all pairs outside the cache, R for the unwatched ones where ``watch_kernel`` records the watched
   ones' own distances; the world's drift bound where it decides alone), CACHE_REACH τ where the cache was rebuilt at
   x⁰, and at least REPULSION_REACH τ (1. guarantees that much), less SAFETY: a cloth gliding 0.6 τ a step caps from
   its cache (γ 3 τ = 0.75 τ), where REPULSION_REACH τ alone allowed γ 2 τ = 0.5 τ. The repulsion's gather flags
   the worlds where either holds, or whose cache
   overflowed (FLAG_FALLBACK); they run the cap's swept broad phase as before (a conditional node). The others
   test each cached pair as the swept broad phase would (``cap_bounds_kernel``: the same single-precision swept
   boxes, the same overlap and keep tests, the same D - K), so the cap keeps exactly the pairs it kept before,
   bounds them alike (``cap_gather_kernel`` recomputes each kept pair's plane from the same positions), and ends
   at the same bits.
5. The pair stages (3. and 4., the swept broad phase's node nested) run in one conditional node on FLAG_WORK, which ``decide_kernel`` and
   ``anchor_kernel`` raise where a world has cached pairs that may lie within REPULSION_REACH τ (1 + SAFETY) at x⁰
   (their least distance at the anchors, recorded by the broad phase in ``cache_near``, less twice the largest |r|:
   a pair's distance changes by at most max |rᵢ - rⱼ|; beyond it a cached pair is as far as one outside the cache,
   and the same test on the step holds for both; where that bound gives up, ``watch_kernel`` checks the cached pairs'
   own distances at x⁰ in the same launch as the watched pairs' (FLAG_CACHED) and raises FLAG_WORK only where one
   lies within that reach: a skirt sliding 0.3 τ a step no longer runs the stages for pairs elsewhere resting at 3 τ;
   a world whose cache overflowed keeps the bound alone, its dropped pairs being in ``cache_near`` only), or where a
   free vertex's step (FLAG_STEP) may exceed
   what the repulsion's gather allows without the swept broad phase, or whose pins move (REPULSION_REACH - CAP_FLOOR)
   τ / 2 or more.
   Where none does, the stages would push no pair, run no swept broad phase and cap no vertex (each step is below γ SEARCH_REACH τ), so ``state_out`` is
   left as the integrator wrote it: a substep without pairs nearby costs the check, one thread per world and
   one conditional node: the rebuild's node (2.) and the stages' sit inside a node on FLAG_BUSY, which every
   raise of FLAG_REBUILD or FLAG_WORK raises too (``raise_flag``, ``raise_work``), so a step that needs neither
   evaluates one condition instead of two.

The cache changes the work and never the answer: results equal those of a broad phase every step, whenever
it was built.
"""

import functools

import warp as wp

from .flatten import flat_kernel
from .kinematics import particle_funcs
from .linalg import atomic_raise, block_max_ints_func
from .precision import vec3_type
from .selfcontact import (
    BOX_PAD,
    CACHE_REACH,
    CAP_FLOOR,
    COUNT_FALLBACKS,
    COUNT_REBUILDS,
    FLAG_CACHED,
    FLAG_DRIFT,
    FLAG_FALLBACK,
    FLAG_KINDS,
    FLAG_KINEMATIC,
    FLAG_REBUILD,
    FLAG_STEP,
    FLAG_WATCH,
    FLOOR_OFFSET,
    KINEMATIC_STEPS,
    NO_BOUND,
    PATCH_COLUMNS,
    PATCH_DRIFT,
    PATCH_POSITION,
    PARAM_RELAXATION,
    PARAM_THICKNESS,
    REPULSION_REACH,
    SAFETY,
    WATCH_EDGE_EDGE,
    WATCH_PATCHES,
    WATCH_REACH,
    SEARCH_REACH,
    Pairs,
    Surface,
    _pair_funcs,
    apart_codec,
    apart_funcs,
    _vertex_extent,
    cube_reach_func,
    flag_slot,
    pair_distance_func,
    raise_flag,
    raise_work,
)
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})


@wp.func
def base_index(world: int, particle_count: int):
    """World ``world``'s first entry in a state's arrays."""
    return world * particle_count

#: Lengths at or beyond this many units (τ / KINEMATIC_STEPS) are not reduced: the world is flagged at once.
LENGTH_LIMIT = 1 << 29


@functools.cache
def length_funcs(scalar: type):
    """``units(length, thickness) -> int``: a length [m] in units of τ / KINEMATIC_STEPS rounded up, or
    LENGTH_LIMIT where it is that large, not finite, or τ is not positive (the caller then flags the world)."""

    @wp.func
    def units(length: scalar, thickness: scalar):
        steps = length / thickness * scalar(KINEMATIC_STEPS)
        if steps < scalar(LENGTH_LIMIT) and steps > -scalar(LENGTH_LIMIT):  # False for NaN
            return int(wp.ceil(steps))
        return int(LENGTH_LIMIT)

    return units


@functools.cache
def check_kernel(scalar: type, tiled: bool = True):
    """Tiled kernel of the cache's check (module docstring, 1.), one block per chunk of a patch's triangles in every
    world (``wp.launch_tiled``, dim (world_count, chunk_count)); chunk c holds ``patch_vertex[chunk_start[c]:
    chunk_start[c + 1]]``, corners of patch ``chunk_patch[c]``'s triangles (each patch's once: v where the patch
    reports v, its owner triangle's, -1 - v elsewhere), and each thread walks a share of them. Per patch: the box of
    the corners' drifts r from their anchors relative to the reference vertex and the box of their positions at the
    step's start, each padded and rounded outward (``patch_box_out``, PATCH_*, stored plus LENGTH_LIMIT so that a
    zeroed box is empty). Per world, from the reported corners: the padded largest |r| (FLAG_DRIFT), the kinematic vertices' largest displacement
    (FLAG_KINEMATIC), the free surface vertices' largest step (FLAG_STEP). Each a block-wide integer maximum (all
    fifteen in one ``linalg.block_max_ints``: two barriers), then one integer atomic maximum per block (order-free).
    ``decide_kernel`` reads them. Without ``tiled`` (the CPU, where a block is one thread) a plain kernel over (world,
    chunk), each thread a block of one."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)
    units = length_funcs(scalar)
    extents = wp.types.vector(PATCH_COLUMNS, wp.int32)
    # The block's maxima, all at once: the patch's PATCH_COLUMNS extents, then the world's drift, kinematic
    # displacement and step.
    reduced = wp.types.vector(PATCH_COLUMNS + 3, wp.int32)
    block_max_ints = block_max_ints_func(PATCH_COLUMNS + 3)

    @wp.kernel(module="unique", enable_backward=False)
    def check(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        triangle: wp.array[wp.vec3i],
        patch_vertex: wp.array[wp.int32],
        chunk_patch: wp.array[wp.int32],
        chunk_start: wp.array[wp.int32],
        params: wp.array2d[scalar],
        cache_anchor: wp.array[vec3],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_end: wp.array[vec3],
        # Out:
        patch_box_out: wp.array3d[wp.int32],
        flags_out: wp.array[wp.int32],
    ):
        world, chunk, lane, threads = int(0), int(0), int(0), int(1)
        if wp.static(tiled):
            world, chunk, lane = wp.tid()
            threads = wp.block_dim()
        else:
            world, chunk = wp.tid()
        if world_enabled[world] == 0:
            return
        world_count = (flags_out.shape[0] - 2) // FLAG_KINDS
        base = base_index(world, particle_count)
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        row = wp.min(world, params.shape[0] - 1)
        thickness = params[row, PARAM_THICKNESS]
        limit = params[row, PARAM_RELAXATION] * scalar(SEARCH_REACH) * thickness
        # Drift relative to the world's reference vertex (a middle triangle's first corner): a translation of the
        # whole surface changes no pair's distance.
        ref = base + triangle[triangle.shape[0] // 2][0]
        shift = particle_q_start[ref] - cache_anchor[ref]
        shift_pad = wp.max(wp.abs(shift))
        extent = extents()
        for k in range(PATCH_COLUMNS):
            extent[k] = -LENGTH_LIMIT
        drift = int(0)
        kinematic = int(0)
        step_units = int(0)
        big = bool(False)
        for a in range(chunk_start[chunk] + lane, chunk_start[chunk + 1], threads):
            entry = patch_vertex[a]
            i = entry
            if entry < 0:
                i = -1 - entry
            p = base + i
            start = particle_q_start[p]
            anchor = cache_anchor[p] + shift
            r = start - anchor
            pad = scalar(BOX_PAD) * (wp.max(wp.abs(start)) + wp.max(wp.abs(anchor)) + shift_pad + scalar(1.0))
            place = scalar(BOX_PAD) * (wp.max(wp.abs(start)) + scalar(1.0))
            for k in range(3):
                high = units(r[k] + pad, thickness)
                low = units(pad - r[k], thickness)
                big = big or high >= LENGTH_LIMIT or low >= LENGTH_LIMIT
                extent[PATCH_DRIFT + k] = wp.max(extent[PATCH_DRIFT + k], high)
                extent[PATCH_DRIFT + 3 + k] = wp.max(extent[PATCH_DRIFT + 3 + k], low)
                # A position beyond the units' range stays at LENGTH_LIMIT: the box only grows (conservative).
                extent[PATCH_POSITION + k] = wp.max(extent[PATCH_POSITION + k], units(start[k] + place, thickness))
                extent[PATCH_POSITION + 3 + k] = wp.max(extent[PATCH_POSITION + 3 + k],
                                                        units(place - start[k], thickness))
            if entry >= 0:  # each vertex's own values once, from the patch of the triangle that reports it
                length = units(wp.length(r) + pad, thickness)
                big = big or length >= LENGTH_LIMIT
                drift = wp.max(drift, length)
                step = wp.length(particle_q_end[p] - start)
                if effective_inv_mass(particle_flags[p], particle_inv_mass[mass_row, i]) == scalar(0.0):
                    level = int(1 << 30)
                    steps = step / thickness * scalar(KINEMATIC_STEPS)
                    if steps < scalar(1 << 29):  # else (or NaN) the largest level
                        level = int(steps) + 1  # rounded up
                    kinematic = wp.max(kinematic, level)
                elif not (step == scalar(0.0)):  # as the repulsion's gather tests it: its step limited, plus its pad
                    limited = wp.min(step, limit)
                    step_units = wp.max(step_units, units(limited + place, thickness))
        if big:  # beyond what the units hold (or NaN): rebuild
            raise_flag(flags_out, FLAG_REBUILD, world, world_count)
        patch = chunk_patch[chunk]
        values = reduced()
        for k in range(PATCH_COLUMNS):
            values[k] = extent[k]
        values[PATCH_COLUMNS] = drift
        values[PATCH_COLUMNS + 1] = kinematic
        values[PATCH_COLUMNS + 2] = step_units
        if wp.static(tiled):
            values = block_max_ints(values)
        if lane == 0:
            for k in range(PATCH_COLUMNS):
                wp.atomic_max(patch_box_out, world, patch, k, values[k] + LENGTH_LIMIT)
            atomic_raise(flags_out, flag_slot(FLAG_DRIFT, world, world_count), values[PATCH_COLUMNS])
            atomic_raise(flags_out, flag_slot(FLAG_KINEMATIC, world, world_count), values[PATCH_COLUMNS + 1])
            atomic_raise(flags_out, flag_slot(FLAG_STEP, world, world_count), values[PATCH_COLUMNS + 2])

    return check


@functools.cache
def decide_kernel(scalar: type):
    """Kernel of the cache's decisions (module docstring, 1.), one thread per ordered pair of patches (P ≤ Q) of
    every world, after ``check_kernel``: the world rebuilds unless its drifts keep every pair outside the cache at
    least REPULSION_REACH τ apart: its padded largest drift at most half the slack, (R - REPULSION_REACH τ)(1 -
    SAFETY) / 2; or, for every two patches whose position boxes lie closer than REPULSION_REACH τ (1 + SAFETY), their
    drifts' spread at most the slack (the length of the vector of max(high_P + low_Q, high_Q + low_P) per axis: the
    largest |r_a - r_b| over a corner a of P and b of Q). The thread of (0, 0) also decides whether the pair stages
    run (FLAG_WORK's first entry): where a world's cache overflowed its ``cache_capacity`` and its cached pairs may lie
    within REPULSION_REACH τ (1 + SAFETY) at the step's start (their least distance at the anchors, ``cache_near``,
    less twice its largest drift, does not keep them beyond; a cache that did not overflow is then flagged FLAG_CACHED
    for ``watch_kernel``'s check of its pairs' own distances), a free vertex steps further than the repulsion's
    gather allows without the swept broad phase at the least (min(γ (REPULSION_REACH τ - K_w), (REPULSION_REACH -
    CAP_FLOOR) τ / 2) (1 - SAFETY), less its pad), or its pins move (REPULSION_REACH - CAP_FLOOR) τ / 2 or more (less
    the SAFETY share). Each thread records in FLAG_APART the least distance at the step's start its bound gives the
    pairs outside the cache across its two patches (module docstring, 4.)."""
    vec3 = vec3_type(scalar)
    record, _ = apart_funcs(scalar)
    _, read_apart = apart_codec(scalar)
    cached_in_reach = cached_in_reach_func(scalar)

    @flat_kernel(module="unique", enable_backward=False)
    def decide(
        # Model:
        world_enabled: wp.array[wp.int32],
        params: wp.array2d[scalar],
        cache_reach: wp.array[scalar],
        cache_floor: wp.array[scalar],
        cache_count: wp.array[wp.int32],
        cache_capacity: int,
        cache_near: wp.array[wp.int32],
        patch_box: wp.array3d[wp.int32],
        # In/out (the pass's flags):
        flags_in_out: wp.array[wp.int32],
        # Out:
        patch_watch_out: wp.array2d[wp.int32],
    ):
        tid = wp.tid()
        patch_count = patch_box.shape[1]
        world = tid // (patch_count * patch_count)
        rest = tid - world * patch_count * patch_count
        first = rest // patch_count
        second = rest - first * patch_count
        if world_enabled[world] == 0 or second < first:
            return
        world_count = cache_reach.shape[0]
        row = wp.min(world, params.shape[0] - 1)
        thickness = params[row, PARAM_THICKNESS]
        unit = thickness / scalar(KINEMATIC_STEPS)
        slack = (cache_reach[world] - scalar(REPULSION_REACH) * thickness) * scalar(1.0 - SAFETY)
        drift = scalar(flags_in_out[flag_slot(FLAG_DRIFT, world, world_count)]) * unit  # the world's largest |r|
        if first == 0 and second == 0:
            kinematic = scalar(flags_in_out[flag_slot(FLAG_KINEMATIC, world, world_count)]) * unit
            step = scalar(flags_in_out[flag_slot(FLAG_STEP, world, world_count)]) * unit
            offset = scalar(FLOOR_OFFSET) * thickness  # as repel_gather
            budget = (wp.min(params[row, PARAM_RELAXATION] * (scalar(REPULSION_REACH) * thickness - kinematic),
                             scalar(0.5) * offset)
                      * scalar(1.0 - SAFETY) * scalar(1.0 - SAFETY))  # the second factor: this test's own rounding
            far = scalar(2.0) * kinematic >= offset * scalar(1.0 - SAFETY)  # as repel_gather
            # The cached pairs: their least distance at the anchors (in units of the build's τ) less the drifts' spread
            # (two largest |r|) bounds them at the step's start; beyond the repulsion's reach they are as far as the
            # pairs outside the cache, for which the test on the step above suffices. Where it does not keep them
            # there, watch_kernel checks their own distances (FLAG_CACHED), unless the cache overflowed (its dropped
            # pairs are in cache_near alone): then the stages run.
            cached = (read_apart(cache_near[world], cache_floor[world] / scalar(CACHE_REACH))
                      - scalar(2.0) * drift)
            if cached_in_reach(cache_count[world], cached, thickness):
                if cache_count[world] <= cache_capacity:
                    flags_in_out[flag_slot(FLAG_CACHED, world, world_count)] = 1
                else:
                    raise_work(flags_in_out, world_count)
            if not (step <= budget) or far:
                raise_work(flags_in_out, world_count)
        # Every pair outside the cache, watched or not, was this far apart at the anchors: CACHE_REACH τ of the τ
        # it was built with (a τ written since changes the repulsion's reach below, not what the cache holds).
        reach_all = wp.min(cache_reach[world], cache_floor[world])  # (0 where never built: R = 0)
        # The slack the cache would have without its watch list: where it suffices, the watched pairs need no check.
        unwatched = (reach_all - scalar(REPULSION_REACH) * thickness) * scalar(1.0 - SAFETY)
        if drift <= scalar(0.5) * unwatched:  # False for a negative slack (R = 0: never built)
            record(flags_in_out, world, world_count, reach_all - scalar(2.0) * drift, thickness)
            return
        gap = vec3(scalar(0.0))
        spread = vec3(scalar(0.0))
        for k in range(3):
            # Integer arithmetic first (exact), then scaled: [-low, high] is each box along axis k.
            # Stored plus LENGTH_LIMIT (check_kernel), taken off each term (no int32 overflow).
            apart = wp.max(0, wp.max(2 * LENGTH_LIMIT - patch_box[world, second, PATCH_POSITION + 3 + k]
                                     - patch_box[world, first, PATCH_POSITION + k],
                                     2 * LENGTH_LIMIT - patch_box[world, first, PATCH_POSITION + 3 + k]
                                     - patch_box[world, second, PATCH_POSITION + k]))
            gap[k] = scalar(apart) * unit
            widest = wp.max((patch_box[world, first, PATCH_DRIFT + k] - LENGTH_LIMIT)
                            + (patch_box[world, second, PATCH_DRIFT + 3 + k] - LENGTH_LIMIT),
                            (patch_box[world, second, PATCH_DRIFT + k] - LENGTH_LIMIT)
                            + (patch_box[world, first, PATCH_DRIFT + 3 + k] - LENGTH_LIMIT))
            spread[k] = scalar(widest) * unit
        # The least distance of a pair across these patches (FLAG_APART) by the bound that holds: their boxes' gap,
        # or the reach at the anchors less the drifts' spread (all pairs outside the cache; the unwatched ones
        # from the cache's own reach, the watched ones by their own distances, watch_kernel).
        across = reach_all - wp.length(spread)
        if wp.length(gap) >= scalar(REPULSION_REACH) * thickness * scalar(1.0 + SAFETY):
            record(flags_in_out, world, world_count, wp.max(wp.length(gap), across), thickness)
            return  # every pair across these patches is that far apart now
        if wp.length(spread) <= unwatched:
            record(flags_in_out, world, world_count, across, thickness)
            return
        flags_in_out[flag_slot(FLAG_WATCH, world, world_count)] = 1  # the watched pairs need their check
        patch_watch_out[world, first] = 1  # those between these two patches (watch_kernel)
        patch_watch_out[world, second] = 1
        record(flags_in_out, world, world_count,
               cache_reach[world] - wp.min(scalar(2.0) * drift, wp.length(spread)), thickness)
        if drift <= scalar(0.5) * slack:
            return
        if not (wp.length(spread) <= slack):
            raise_flag(flags_in_out, FLAG_REBUILD, world, world_count)

    return decide


@functools.cache
def cached_in_reach_func(scalar: type):
    """``cached_in_reach(count, least, thickness)``: whether a world's ``count`` cached pairs, none closer than
    ``least`` [m] at the step's start, may hold one within the repulsion's reach REPULSION_REACH τ (1 + SAFETY): then
    the pair stages run for them (module docstring, 5.)."""

    @wp.func
    def cached_in_reach(count: int, least: scalar, thickness: scalar) -> bool:
        return count > 0 and not (least >= scalar(REPULSION_REACH) * thickness * scalar(1.0 + SAFETY))

    return cached_in_reach


@functools.cache
def watch_kernel(scalar: type):
    """Kernel of the watched and the cached pairs' checks (module docstring, 1. and 5.), after ``decide_kernel``,
    ``split`` threads per particle of every world (adjacent), the k-th taking its world's list slots local + k ·
    particle_count, then every split · particle_count-th (``core/selfcontact.py``'s ``broad_split``: a small cloth's long
    lists spread over more threads). In the worlds ``decide_kernel`` flagged FLAG_WATCH (elsewhere the drifts keep the
    watched pairs apart too): each watched pair whose sides' patches (their owner triangles', in its tag) were
    both marked by ``decide_kernel`` (``patch_watch``), its distance at the step's start, with the narrow phase's
    arithmetic; a world with one closer than REPULSION_REACH τ (1 + SAFETY) is flagged for a rebuild (FLAG_REBUILD),
    and every distance checked is recorded in FLAG_APART (module docstring, 4.). In the worlds flagged FLAG_CACHED
    (the drifts no longer keep the cached pairs beyond the repulsion's reach): each cached pair's distance at the
    step's start likewise; one closer than REPULSION_REACH τ (1 + SAFETY) raises FLAG_WORK, and where none is, the
    pair stages would push no pair (module docstring, 5.)."""
    vec3 = vec3_type(scalar)
    pair_distance = pair_distance_func(scalar)
    record, _ = apart_funcs(scalar)

    @wp.func
    def start_distance(edge_edge: bool, index: wp.vec4i, base: int, particle_q_start: wp.array[vec3]) -> scalar:
        """A listed pair's distance at the step's start [m] (VT, or EE with ``edge_edge``), with the narrow phase's
        arithmetic."""
        return pair_distance(edge_edge, particle_q_start[base + index[0]], particle_q_start[base + index[1]],
                             particle_q_start[base + index[2]], particle_q_start[base + index[3]])

    @flat_kernel(module="unique", enable_backward=False)
    def watch(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        watch_count: wp.array[wp.int32],
        watch_tag: wp.array[wp.int32],
        watch_vertex: wp.array[wp.vec4i],
        cache: Pairs,
        patch_watch: wp.array2d[wp.int32],
        split: int,
        # State in:
        particle_q_start: wp.array[vec3],
        # In/out (the pass's flags):
        flags_in_out: wp.array[wp.int32],
    ):
        tid = wp.tid()
        p = tid // split
        part = tid - p * split
        world, local = world_and_index(p, particle_count)
        world_count = watch_count.shape[0]
        if world_enabled[world] == 0:
            return
        base = base_index(world, particle_count)
        thickness = params[wp.min(world, params.shape[0] - 1), PARAM_THICKNESS]
        near = scalar(REPULSION_REACH) * thickness * scalar(1.0 + SAFETY)
        vt_keys = wp.int64(particle_count) * wp.int64(surface.triangle.shape[0])
        if flags_in_out[flag_slot(FLAG_WATCH, world, world_count)] != 0:
            capacity = watch_tag.shape[0] // world_count
            count = wp.min(watch_count[world], capacity)
            for slot in range(local + part * particle_count, count, particle_count * split):
                s = world * capacity + slot
                # The patches of the pair's sides (their owner triangles', in its tag): unless decide_kernel marked
                # both, the pair's patches lie 2τ apart now or drift by at most the slack of CACHE_REACH τ: it is that
                # far apart.
                tag = watch_tag[s]
                edge_edge = tag >= WATCH_EDGE_EDGE
                sides = tag - wp.where(edge_edge, WATCH_EDGE_EDGE, 0)
                if patch_watch[world, sides // WATCH_PATCHES] == 0 or patch_watch[world, sides % WATCH_PATCHES] == 0:
                    continue
                d = start_distance(edge_edge, watch_vertex[s], base, particle_q_start)
                if not (d >= near):
                    raise_flag(flags_in_out, FLAG_REBUILD, world, world_count)
                    return  # (the rebuild's anchors decide the stages for the new cache: anchor_kernel)
                record(flags_in_out, world, world_count, d, thickness)  # (its own rounding: the reader's SAFETY)
        if flags_in_out[flag_slot(FLAG_CACHED, world, world_count)] != 0:
            capacity = cache.key.shape[0] // world_count
            count = wp.min(cache.count[world], capacity)
            for slot in range(local + part * particle_count, count, particle_count * split):
                s = world * capacity + slot
                if not (start_distance(cache.key[s] >= vt_keys, cache.vertex[s], base, particle_q_start) >= near):
                    raise_work(flags_in_out, world_count)
                    return

    return watch


@functools.cache
def anchor_kernel(scalar: type):
    """Kernel ending a rebuild (module docstring, 2.): the flagged worlds' anchors become the step's start and
    their reach WATCH_REACH τ (CACHE_REACH τ where the watch list overflowed); a rebuilt world that found pairs within
    REPULSION_REACH τ (1 + SAFETY) (``cache_near``, their least distance) sets FLAG_WORK."""
    vec3 = vec3_type(scalar)
    _, read_apart = apart_codec(scalar)
    cached_in_reach = cached_in_reach_func(scalar)

    @flat_kernel(module="unique", enable_backward=False)
    def anchor(
        # Model:
        particle_count: int,
        params: wp.array2d[scalar],
        cache: Pairs,
        cache_near: wp.array[wp.int32],
        watch_count: wp.array[wp.int32],
        watch_capacity: int,
        # State in:
        particle_q_start: wp.array[vec3],
        # In/out (the pass's flags):
        flags_in_out: wp.array[wp.int32],
        # Out:
        cache_reach_out: wp.array[scalar],
        cache_floor_out: wp.array[scalar],
        cache_anchor_out: wp.array[vec3],
        counters_out: wp.array2d[wp.int32],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        world_count = cache_reach_out.shape[0]
        if flags_in_out[flag_slot(FLAG_REBUILD, world, world_count)] == 0:
            return
        cache_anchor_out[p] = particle_q_start[p]
        if i == 0:
            # The watched pairs' reach where the watch list held them all, else the cache's own.
            reach = scalar(CACHE_REACH)
            if watch_count[world] <= watch_capacity:
                reach = scalar(WATCH_REACH)
            thickness = params[wp.min(world, params.shape[0] - 1), PARAM_THICKNESS]
            cache_reach_out[world] = reach * thickness
            cache_floor_out[world] = scalar(CACHE_REACH) * thickness
            counters_out[world, COUNT_REBUILDS] += 1  # one thread per world
            # (its pairs at the step's start are at their anchors: the least of them as listed)
            if cached_in_reach(cache.count[world], read_apart(cache_near[world], thickness), thickness):
                raise_work(flags_in_out, world_count)

    return anchor


@functools.cache
def cap_bounds_kernel(scalar: type):
    """Kernel of the cap's narrow phase over the cache (module docstring, 4.), one thread per particle of every
    world taking its world's slots local, local + particle_count, ...: each cached pair's D - K where the swept
    broad phase would have kept it (its swept single-precision boxes overlap and ``kept_by_cap``: 2K ≥ D or
    max δ > γ (D - K)), ``NO_BOUND`` elsewhere. Worlds flagged FLAG_FALLBACK are skipped (their cap reads the swept
    list)."""
    vec3 = vec3_type(scalar)
    pair_distance = pair_distance_func(scalar)
    box_of, _, _, sweep_bounds, _, kept_by_cap = _pair_funcs(scalar)
    extend = _vertex_extent(scalar, True)
    cube_reach = cube_reach_func(scalar)

    @wp.func
    def boxes_overlap(lower_a: vec3, upper_a: vec3, lower_b: vec3, upper_b: vec3):
        return (lower_a[0] <= upper_b[0] and lower_a[1] <= upper_b[1] and lower_a[2] <= upper_b[2]
                and upper_a[0] >= lower_b[0] and upper_a[1] >= lower_b[1] and upper_a[2] >= lower_b[2])

    @wp.func
    def swept_box(ends: wp.vec3i, corners: int, base: int, mass_row: int, limit: scalar, cube: scalar,
                  particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
                  particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3]):
        """The swept box of a primitive's first ``corners`` vertices, unpadded, in the broad phase's order."""
        lower = particle_q_start[base + ends[0]]
        upper = lower
        for k in range(corners):
            lower, upper = extend(lower, upper, base + ends[k], ends[k], mass_row, particle_flags, particle_inv_mass,
                                  particle_q_start, particle_q_end, limit, cube)
        return lower, upper

    @wp.func
    def bound_of(
        s: int, base: int, mass_row: int, relaxation: scalar, limit: scalar, cube: scalar, floor: scalar,
        particle_count: int,
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
            lower, upper = swept_box(wp.vec3i(vertex[0], vertex[0], vertex[0]), 2, base, mass_row, limit, cube,
                                     particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
            query_lower, query_upper = box_of(lower, upper, floor)
            lower, upper = swept_box(tri, 3, base, mass_row, limit, cube, particle_flags, particle_inv_mass,
                                     particle_q_start, particle_q_end)
            leaf_lower, leaf_upper = box_of(lower, upper, zero)
            if not boxes_overlap(vec3(query_lower), vec3(query_upper), vec3(leaf_lower), vec3(leaf_upper)):
                return scalar(NO_BOUND)
            distance = pair_distance(False, particle_q_start[base + vertex[0]], particle_q_start[base + vertex[1]],
                                     particle_q_start[base + vertex[2]], particle_q_start[base + vertex[3]])
        else:  # EE: the lower edge's query box, the other edge's owner triangle's leaf box, the other edge's box
            rest = key - wp.int64(particle_count) * wp.int64(triangle_count)
            f = int(rest % wp.int64(surface.edge.shape[0]))
            tri = surface.triangle[surface.edge_owner[f]]
            lower, upper = swept_box(wp.vec3i(vertex[0], vertex[1], vertex[1]), 2, base, mass_row, limit, cube,
                                     particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
            query_lower, query_upper = box_of(lower, upper, floor)
            lower, upper = swept_box(tri, 3, base, mass_row, limit, cube, particle_flags, particle_inv_mass,
                                     particle_q_start, particle_q_end)
            leaf_lower, leaf_upper = box_of(lower, upper, zero)
            if not boxes_overlap(vec3(query_lower), vec3(query_upper), vec3(leaf_lower), vec3(leaf_upper)):
                return scalar(NO_BOUND)
            other_lower, other_upper = swept_box(wp.vec3i(vertex[2], vertex[3], vertex[3]), 2, base, mass_row, limit, cube,
                                                 particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
            if not boxes_overlap(other_lower, other_upper, vec3(query_lower), vec3(query_upper)):
                return scalar(NO_BOUND)
            distance = pair_distance(True, particle_q_start[base + vertex[0]], particle_q_start[base + vertex[1]],
                                     particle_q_start[base + vertex[2]], particle_q_start[base + vertex[3]])
        kinematic, free_step = sweep_bounds(vertex, base, mass_row, limit, cube, particle_flags, particle_inv_mass,
                                            particle_q_start, particle_q_end)
        if kept_by_cap(distance, floor, kinematic, free_step, relaxation):
            return distance - kinematic
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
        cube = cube_reach(flags, world, limit)
        floor = scalar(CAP_FLOOR) * params[row, PARAM_THICKNESS]
        for slot in range(local, wp.min(cache.count[world], capacity), particle_count):
            s = world * capacity + slot
            cache_bound_out[s] = bound_of(s, base, mass_row, relaxation, limit, cube, floor, particle_count,
                                          particle_flags, particle_inv_mass, surface, cache, particle_q_start,
                                          particle_q_end)

    return cap_bounds
