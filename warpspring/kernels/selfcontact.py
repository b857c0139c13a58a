"""Self-collision of triangle surfaces whose vertices are particles: repulsion, friction and a displacement cap.

A post-step pass: it reads the step's start x⁰ (``state_in``, assumed free of intersections) and the
integrator's result x¹ (``state_out``), and rewrites ``state_out``. Pairs are vertex–triangle (VT) and
edge–edge (EE) pairs of primitives that share no vertex. The pass's two stages work on lists of pairs, each
pair once, which they evaluate pair by pair and gather one thread per vertex; the lists come from a cache
that the broad phase rebuilds only when it may miss a pair (``selfcontact_cache``, which proves that the
stages keep the same pairs as a broad phase every step):

* **broad phase** (``broad_kernel``: on CUDA one thread per surface vertex and one per edge, an edge keeping its
  pairs with the higher edges, each querying the world's BVH of triangle boxes (``wp.Bvh``, refit at each broad
  phase) around its own box; on the CPU one thread per triangle for the vertices and edges it reports, one query
  around their boxes, each reported triangle tested against each primitive's own box): topological neighbours
  rejected by index before any geometry,
  then the pair's distance D at x⁰ decides. A kept pair takes a slot of its world's buffer through an
  integer atomic counter; pairs beyond ``capacity`` are counted (``COUNT_OVERFLOW``) and dropped. It lists
  the worlds an ``active`` array names (``reset_kernel`` empties theirs), the others keep their lists;
* **CSR** (``fill_kernel``): every pair's four vertices were counted per particle as it was written;
  an exclusive scan of the counts within each world (``scan_kernels``: tiled, no allocation: it runs inside
  conditional graph nodes) gives each particle its segment of entries (slot · 4 + role), filled through a
  per-particle integer cursor;
* **narrow phase** (``repel_pairs_kernel``): one thread per particle walks its world's pairs and writes each
  pair's four vertices' corrections and weights to the pair's own slots;
* **gather** (``repel_gather_kernel``, ``selfcontact_cap.cap_gather_kernel``): one thread per vertex sorts its segment by
  the pairs' keys (a pair's identity: (vertex, triangle) or (edge, edge)), then folds it in that order. The
  atomics decide only where a pair is stored, never the order of a sum: results are the same bits run to
  run (unless a buffer overflows, when which pairs were kept depends on the atomics; see the cap).

1. **Repulsion and friction.** Pairs closer than ``REPULSION_REACH`` × thickness τ at x⁰ (the cached pairs
   cut at that distance) predict their separation at
   the end, linearised at x⁰: d + n·Σₖ wₖΔₖ, with n the unit vector between the closest points, wₖ the
   signed barycentric weights of the pair's four vertices (one side +, the other −) and Δₖ = x¹ₖ − x⁰ₖ. A
   pair predicted closer than τ is pushed apart by c = τ − (d + n·Σ wₖΔₖ) along n, shared by inverse mass
   like an inelastic impulse (Bridson, Fedkiw & Anderson 2002): vertex k moves by wₖ mₖ⁻¹ c / Σⱼ wⱼ² mⱼ⁻¹ · n.
   A kinematic vertex has mₖ⁻¹ = 0: the free side takes the whole correction. Coulomb friction removes up to
   μc of the pair's relative tangential displacement the same way (all of it when μc covers it: static
   friction). A vertex takes a weighted mean of its pairs' corrections (Jacobi): their sum over
   max(1, Σ|wₖ|), its weights in its pairs, so several pairs at one vertex do not add up to an overshoot.
2. **The displacement cap** (Chen et al. 2024, "Offset Geometric Contact", as in Newton's VBD, with separating
   planes). Let x̂ be the repelled positions, each free vertex's step Δ̂ᵢ = x̂ᵢ − x⁰ᵢ first limited to
   γ · ``SEARCH_REACH`` · τ (δᵢ = |Δ̂ᵢ|; γ < 1/2 the relaxation); kinematic vertices keep their prescribed x¹.
   The cap keeps pairs a floor h = ``CAP_FLOOR`` τ apart, not only apart. Its pairs are those whose swept boxes
   overlap at (x⁰, x̂): the vertex's or edge's swept box (x⁰ and x̂ of its ends, and around each free end's x⁰ the
   cube of half-width ρ, where the later passes may place it: ρ = γ τ in a world whose pins move, 0 elsewhere,
   ``cube_reach``), grown by h, against the triangles' swept boxes (likewise, not grown; tested on the cached pairs
   by ``selfcontact_cache.cap_bounds_kernel``, or listed by the swept broad phase where the cache may miss one); a
   pair is kept unless neither side can come within h of the other: 2 max(K, δ) < D − h and δ ≤ γ (D − K), with
   δ = maxₖ free max(δₖ, ρ) and K the largest prescribed displacement among its kinematic vertices (0 when it has
   none). Each free vertex i then ends at x⁰ᵢ + sᵢ Δ̂ᵢ, sᵢ in [0, 1] the largest that keeps two
   bounds over its kept pairs (module ``selfcontact_cap``, ``cap_gather_kernel``), or where it is jammed, where the later passes put it:

   * **planes**. A kept pair's n is a unit vector from side B (the triangle, the second edge) to side A (the
     vertex, the first edge): of the direction between the closest points at x⁰ and the triangle's normal or the
     edges' cross product, the one with the wider slab, D_n = min over A's vertices of n·x⁰ − max over B's of
     n·x⁰ (D where n is the closest points' exact direction; any n gives a true slab; the normal keeps its
     accuracy where a close pair's rounded closest points would tilt n); G = D_n − 2 pad (``plane_funcs``), and
     G' = max(G − h, 0) its room above the floor. K_A, K_B are each side's kinematic approach: the largest
     displacement of its kinematic vertices toward the other side along n (at least 0). A free vertex of A may
     approach B along n by at most its share s_A = min(γ (G' − K_B), (1 − γ) G' − K_B), one of B by
     s_B = min(γ (G' − K_A), (1 − γ) G' − K_A): a pin's approach is taken off the other side's share, and where it
     exceeds (1 − γ) G' the share is negative: the free side must give way, along its repelled step (which the
     repulsion pointed away from the pin) rather than held where the pin runs into it. A pair at the floor or
     below (G' = 0, no pin) has shares 0: it may part, not close in. A vertex that retreats along n takes its
     whole step there. A pair with G ≤ 0 (closer than the precision resolves) holds its free vertices.
   * **lengths**, for a vertex no share asks to give way: it also moves at most γ · min over its kept pairs of
     (D − K − pad), as with no planes, so that its step stays short in every direction, not only along the
     pairs' normals (neighbours that pass beside it, (a) below, stay as far apart as a length cap keeps them). A
     position that rounds past that bound is pulled back by the pad (held at x⁰ only where the bound is below it).
   * **the later passes** (``cap_place_kernel``), for a jammed vertex, one that a negative share asks to give
     way further along its step than its other bounds let it (a free vertex squeezed between a pin and more
     cloth). A pass places its movers anew and leaves the others where they are: of each kept pair a mover
     approaches the other side along n by at most the room that side leaves, (1 − γ) G' minus that side's largest
     approach as placed (a pusher's, below: the larger of that and where it wanted to go), and where the other
     side holds a mover of the same pass, also at most its share; anywhere in its swept box and no further than
     max(δᵢ, ρ): alternating projections onto these half-spaces, the box and the ball (``RELEASE_ROUNDS``),
     accepted where every bound then holds, else it stays and becomes a pusher. Where a pusher wants to go is the
     same projections onto its bounds against what cannot make room only (its pairs' kinematic vertices, pushers
     as they want to go), its box and its ball: the free vertices across its other pairs are the next pass's
     movers and make room for that point (a point that also kept their bounds as they stand asked them for none,
     and a pin's squeeze was never passed on to the layers behind). A pusher counts as where it wants to go (the
     larger of that and where it is) also for the pushers placed in its own pass: a layer squeezed through several
     others is a chain of pushers, and one placed against where the next stands would stay, drop its role and
     leave the next jammed, the two taking turns at every level. A pusher has a depth, its place in the chain: 0
     for one the first pass could not place, one more than the deepest pusher across its kept pairs for a mover
     that could not be placed (the deepest, not the nearest: a coiled strip's layers also lie across pairs from the
     front pusher). Its wanted point counts the pushers no deeper than it (those in front, pressing on it), as they
     want to go, and the pushers no deeper that a sub-pass placed, where they went (they keep their depth); the
     deeper ones, behind it, make room for it, and it asks no placed pusher in front of it to move
     (``cap_mark_kernel``). The pushers' pass runs as ``PUSHER_COLOURS`` sub-passes
     (``selfcontact_cap``), the depths ≡ c (mod ``PUSHER_COLOURS``) in the c-th, the highest c first: two pushers
     across a kept pair of adjacent depths are never placed in one sub-pass (where each would be held to its share
     of the other's room, γ G', however far the one behind moved). Where the one behind has the higher colour
     (depth 1 behind 0, with two colours) it is placed first and the one in front then against where it went;
     else the one in front is placed first against where the one behind stands, and follows a level later. The
     jammed vertices are the first pass's movers; then, level after level while a vertex stays a pusher (at most
     ``CAP_LEVELS``, ``core/selfcontact.py``), the free vertices across a kept pair from a pusher are movers (they
     make room, ``cap_mark_kernel``), then the pushers in their sub-passes: a level launches the mark, the movers'
     pass and ``PUSHER_COLOURS`` pushers' sub-passes. Room is made from the back, a layer a level. The levels are
     a loop on the device (``wp.capture_while``, ``LEVELS_PER_ROUND`` levels a round, ``cap_loop_gate_kernel``
     deciding after each): a step with no jammed vertex runs none.

   Why no pair crosses within the step, and none that starts it at least h apart ends closer. Every point of a
   primitive is a fixed convex combination of its vertices, each moving on a straight line that stays in its
   swept box (the segment x⁰ᵢ → x̂ᵢ for sᵢ ≤ 1, or the later passes' point) and is no longer than max(δᵢ, ρ), so
   the point stays in the primitive's swept box, moves at most the largest displacement among its vertices, and
   along any fixed n moves at most as far as the furthest of its vertices. (a) The pair's swept boxes, one grown
   by h, are disjoint: the primitives stay more than h apart. (b) The boxes overlap but the pair was not kept:
   every vertex of it moves at most max(K, δ) < (D − h)/2, so the two sides stay more than h apart, whichever
   hold kinematic vertices (and with no pin at least (1 − 2γ) D). (c) It was kept: side A's lowest point along n
   stays above min_A n·x⁰ − α_A and side B's highest below max_B n·x⁰ + α_B, α a side's largest approach among
   its vertices: at most max(K_A, s_A) for A where each free vertex keeps its share (for B likewise; a side
   without kinematic vertices: its share). The slab between them, G + h ≥ h + G' wide at the start, stays open by
   at least h + G' − max(K_A, s_A) − max(K_B, s_B), which is ≥ h + (1 − 2γ) G' where no pin exceeds its side's
   share, ≥ h + γ G' where one does (K_A + s_B ≤ (1 − γ) G'), and h + G' − K_A − K_B where both sides' pins do:
   above h whenever at most one side holds kinematic vertices, and when both do and close in by less than G'. A
   later pass keeps this: a mover placed against a side that stays approaches by at most (1 − γ) G' minus that
   side's approach (the slab stays open by h + γ G'), and against a side that moves in the same pass (for the
   pushers: the same sub-pass), by at most its share and that room, whether the other side's movers are placed
   (shares) or stay (room); a side placed in an earlier sub-pass stays during this one, and counts where it went.
   A pusher's wanted point enters a mover's or another pusher's room only as the larger of it and where the pusher
   is, so the bound holds whatever that point is (it, and which pushers it counts, decide only how much room the
   others make). With no
   kinematic vertex this is the bound γ G' per vertex along n and the margin h + (1 − 2γ) G'. G takes two pads
   off D_n: one for the rounding of the dot products, one for the rounded end positions. A pair closer than h at
   the start (G' = 0: one a pin pressed there) keeps its slab: it does not close in. Such a pair's share is 0, which
   leaves no pad for the rounding of the end: a capped end x⁰ + s Δ̂ rounds coordinate by coordinate (a small
   coordinate keeps its part of the step where a large one drops it), so it can approach along n where Δ̂ retreats,
   a few ulps a step, compounded while the pair stays on the floor. Where no share asks a vertex to give way, the
   cap checks its capped end, as stored, against each pair that leaves it no approach, and holds the vertex at x⁰
   where it approaches one; the later passes check their bounds on the stored end too. Without the floor (h = 0) a
   kept pair closed to (1 − 2γ) of its gap a step, which compounded wherever the repulsion could not part it (a
   vertex pressed from both sides, whose corrections' mean cancels): pairs came within micrometres.
   A share that cannot be kept puts the pair beyond the cap: a free vertex asked to give way that no pass can
   place (the room its neighbours leave, after they made what room they could within ρ, does not suffice: layers
   squeezed by a pin), or two kinematic sides closing in by G' or more. ``cap_check_kernel`` counts, after the cap,
   each kept pair one of whose sides closes in along n while their approaches add up to D_n − pad or more
   (COUNT_OUTRUN), so that a run says where the guarantee did not hold.
   If the world's cap buffer overflowed, a listed pair may be missing: every free vertex of that world then
   stays at x⁰ for the step (s = 0 keeps every bound of every pair), and the overflow is counted.
   The BVH is single precision: query and leaf boxes are padded by ``BOX_PAD`` relative to the coordinates.

Velocities of the vertices the pass moved become v = (x − x⁰)/h; the others keep the integrator's.
No float atomics: each pair writes its own slots and each vertex only itself; integer counters per world
(pairs pushed, vertices capped, pairs dropped on overflow) and the buffer's counters use atomics.
"""

import functools

import warp as wp

from .kinematics import particle_funcs
from .precision import vec3_type
from .worlds import world_and_index
from .flatten import flat_kernel, launch_bounds_option
from .linalg import atomic_raise, atomic_slot

wp.set_module_options({"enable_backward": False})

#: Pairs closer than this many thicknesses at the step's start are checked for repulsion.
REPULSION_REACH = 2.0
#: The cap's floor, in thicknesses: it bounds each kept pair's approach by its distance less CAP_FLOOR τ (and keeps
#: the pairs that could come that close), so a pair at least CAP_FLOOR τ apart at a step's start ends it, and stays
#: all through it, at least that far apart; a closer pair may part but not close in (module docstring, 2.).
CAP_FLOOR = 0.5
#: D - h of a pair outside the cache at its reach, in thicknesses (REPULSION_REACH - CAP_FLOOR: one constant, so that a
#: kernel reads it as one value of its precision).
FLOOR_OFFSET = REPULSION_REACH - CAP_FLOOR
#: A free vertex moves at most γ times this many thicknesses per step (it bounds the cap's swept boxes).
SEARCH_REACH = 32.0
#: Relative padding of the single-precision BVH's boxes (float32 rounding of the points is 6e-8).
BOX_PAD = 1.0e-6
#: Slots of a world's pair buffer per surface vertex (pairs beyond are dropped and counted).
PAIRS_PER_VERTEX = 24

#: Columns of ``SelfContact.params`` [rows, PARAM_COUNT]: live values per world.
PARAM_THICKNESS = 0  # τ [m]: the separation the repulsion keeps
PARAM_FRICTION = 1  # μ [-]: Coulomb friction between the surface's layers
PARAM_RELAXATION = 2  # γ [-] in (0, 1/2): the cap's share of the distance to the nearest primitive
PARAM_COUNT = 3

#: Columns of the per-world counters [world_count, COUNTER_COUNT] (int32, summed over the steps).
COUNT_PAIRS = 0  # pairs pushed apart by the repulsion
COUNT_CAPPED = 1  # vertices whose displacement the cap shortened
COUNT_OVERFLOW = 2  # pairs dropped because the world's pair buffer was full
COUNT_REBUILDS = 3  # steps that rebuilt the world's pair cache (module selfcontact_cache)
COUNT_FALLBACKS = 4  # steps whose cap ran the swept broad phase instead of the cache
COUNT_OUTRUN = 5  # kept pairs the cap could not hold apart (a pin closing in on a free side that cannot give way)
COUNT_FILL = 6  # the fullest list's share of its slots past FILL_WATCHED, in FILL_UNITS (a maximum, not a sum)
COUNT_SQUEEZED = 7  # kept pairs held apart but pressed below the floor τ/2 along their separating direction
COUNT_STAGES = 8  # steps whose pair stages ran (module selfcontact_cache, 5.: some world's FLAG_WORK)
COUNTER_COUNT = 9

#: Fill of a pair list is recorded (``COUNT_FILL``) once it passes this share of its slots, in units of its
#: 1/FILL_UNITS: only the upper part of a list pays the atomic maximum.
FILL_WATCHED = 0.5
FILL_UNITS = 1000

#: The pair cache (module ``selfcontact_cache``): it lists the pairs closer than this many thicknesses at its
#: anchor positions, and is rebuilt when a vertex has drifted half the difference to REPULSION_REACH from them.
CACHE_REACH = 3.0
#: Pairs between CACHE_REACH and this many thicknesses apart at the cache's anchors are *watched* (module
#: ``selfcontact_cache``): their distances are checked at every step, so that the drifts need only keep the other
#: pairs, WATCH_REACH τ apart at the anchors, beyond REPULSION_REACH τ.
WATCH_REACH = 4.5
#: The cache's slots per slot of a pair buffer: it holds the pairs within CACHE_REACH τ, where the repulsion's list
#: held those within REPULSION_REACH τ ((3/2)² more between layers, (3/2)³ more in a volume).
CACHE_SLOTS = 3
#: Kinds of the pass's flags (``flag_slot``), one entry per world each. Lengths are integers in units of
#: τ / KINEMATIC_STEPS, rounded up, reduced by integer maxima (order-free).
FLAG_REBUILD = 0  # rebuild the world's cache
FLAG_FALLBACK = 1  # run the world's cap through its swept broad phase
FLAG_KINEMATIC = 2  # K_w, the largest displacement of the world's kinematic vertices
FLAG_DRIFT = 3  # the largest drift from the anchors relative to the reference vertex, padded (module selfcontact_cache)
FLAG_STEP = 4  # the largest step of a free surface vertex (limited to γ SEARCH_REACH τ), padded
FLAG_WORK = 5  # its first entry only: some world's pair stages must run (module selfcontact_cache)
FLAG_WATCH = 6  # the world's watched pairs need their check (module selfcontact_cache)
FLAG_APART = 7  # the least distance at the step's start of a pair outside the cache, in units rounded down, stored as
#   APART_NONE less it (an integer maximum: the least distance; 0: none recorded; module selfcontact_cache)
FLAG_CACHED = 8  # the world's cached pairs need their check (the drifts do not keep them apart; module selfcontact_cache)
FLAG_BUSY = 9  # its first entry only: some world's cache rebuilds or some world's pair stages run (the one conditional
#   node a step without either evaluates; ``raise_flag``, ``raise_work``)
FLAG_KINDS = 10
KINEMATIC_STEPS = 4096
#: FLAG_APART's stored value for a distance of 0 (and for a distance that is not finite): distances of this many
#: units τ / KINEMATIC_STEPS or more are not recorded.
APART_NONE = 1 << 29
#: The surface's patches (module ``selfcontact_cache``): groups of triangles close at rest, at least this many
#: triangles each and at most PATCH_LIMIT of them (2^k by halving), whose boxes the cache's check reduces.
PATCH_TRIANGLES = 32
PATCH_LIMIT = 256
#: The most patches on the CPU, where the decision's thread per pair of patches runs in a loop (~60 ns each).
PATCH_LIMIT_CPU = 32
#: Threads per block of the cache's check, and the most triangles a block takes (of one patch): a patch of a large
#: surface spreads over several blocks.
PATCH_THREADS = 128
PATCH_CHUNK = 4 * PATCH_THREADS
#: Columns of a patch's extents [world_count, patch_count, PATCH_COLUMNS] (integers in units of τ / KINEMATIC_STEPS,
#: rounded outward, padded for rounding): its drifts' box, max (r_k + pad) for k = x, y, z then max (pad - r_k), and
#: likewise its positions' box at the step's start, over every corner of its triangles.
PATCH_DRIFT = 0
PATCH_POSITION = 6
PATCH_COLUMNS = 12
#: A watched pair's tag (``watch_tag``): its sides' patches a · WATCH_PATCHES + b, plus WATCH_EDGE_EDGE for an EE
#: pair; the patches of a surface stay below WATCH_PATCHES (``PATCH_LIMIT``, and ``SelfContact`` checks).
WATCH_PATCHES = 1 << 15
WATCH_EDGE_EDGE = 1 << 30


def patch_count(triangle_count: int, cuda: bool) -> int:
    """The patches of a surface of ``triangle_count`` triangles: the most halvings (2^k patches, at most PATCH_LIMIT
    on CUDA, PATCH_LIMIT_CPU on the CPU) that leave each at least PATCH_TRIANGLES triangles (1 for a smaller
    surface)."""
    limit = PATCH_LIMIT if cuda else PATCH_LIMIT_CPU
    count = 1
    while 2 * count <= limit and triangle_count // (2 * count) >= PATCH_TRIANGLES:
        count *= 2
    return count
#: Relative slack of the cache's bounds (drift, the cap's budget) against rounding.
SAFETY = 1.0 / 64.0
#: A cached pair's bound (``selfcontact_cache.cap_bounds_kernel``) where the cap does not keep it.
NO_BOUND = 1.0e30


#: A triangle's sides that it reports (``Surface.owned_sides``): row k is side k's edge (its index in ``edge``, -1 where
#: another triangle reports that edge) and the edge's two vertices, as ``edge`` lists them.
mat33i = wp.types.matrix(shape=(3, 3), dtype=wp.int32)


@wp.struct
class Surface:
    """The topology of the colliding surface, shared by every world (per-world particle indices)."""

    triangle: wp.array[wp.vec3i]  # the triangles' corners, shape [triangle_count]
    owned_sides: wp.array[mat33i]  # per triangle, the sides it reports with their vertices (``mat33i``): one read
    #   where the edges' queries test a reported triangle's edges, shape [triangle_count]
    edge: wp.array[wp.vec2i]  # the surface's unique edges, shape [edge_count]
    edge_owner: wp.array[wp.int32]  # the triangle through which queries report edge e, [edge_count]
    vertex_owner: wp.array[wp.int32]  # the triangle through which queries report vertex i, or -1 (not on the
    #   surface), shape [particle_count]
    triangle_patch: wp.array[wp.int32]  # each triangle's patch (``kernels/selfcontact_cache.py``), [triangle_count]
    bvh: wp.array[wp.uint64]  # per world, the id of the wp.Bvh of its triangles' boxes (``leaf_lower/upper``)
    leaf_lower: wp.array[wp.vec3f]  # [m], the triangles' boxes, shape [world_count · triangle_count]
    leaf_upper: wp.array[wp.vec3f]  # [m], likewise


@wp.struct
class Pairs:
    """A pair buffer: ``capacity`` slots per world, and the CSR of the particles' entries in its pairs."""

    count: wp.array[wp.int32]  # [world_count], pairs found by the last broad phase (beyond capacity: dropped)
    key: wp.array[wp.int64]  # [world_count · capacity], the pair's identity within its world: VT v·T + t,
    #   EE V·T + e·E + f (V, T, E: the per-world particle, triangle and edge counts)
    vertex: wp.array[wp.vec4i]  # [world_count · capacity], its four vertices: VT (v, a, b, c), EE (p₁, q₁, p₂, q₂)
    vertex_count: wp.array[wp.int32]  # [world_count · particle_count + 1], entries per particle (last: 0)
    vertex_start: wp.array[wp.int32]  # [world_count · particle_count + 1], their exclusive scan within the world,
    #   from 4 · world · capacity (``scan_kernels``); a particle's segment is [start, start + count)
    vertex_cursor: wp.array[wp.int32]  # [world_count · particle_count], entries filled per particle
    entry: wp.array[wp.int32]  # [4 · world_count · capacity], slot · 4 + role, grouped by particle


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
def pair_distance_func(scalar: type):
    """``pair_distance(edge_edge, x0, x1, x2, x3)``: a pair's distance [m] from its four vertices' positions, VT
    (x0 and the triangle x1 x2 x3) or EE (the segments x0 x1 and x2 x3), by ``geometry_funcs``' closest points: the
    one arithmetic every phase that lists or checks pairs by their distance uses, so that they agree to the bit."""
    vec3 = vec3_type(scalar)
    triangle_closest, edge_closest = geometry_funcs(scalar)

    @wp.func
    def pair_distance(edge_edge: bool, x0: vec3, x1: vec3, x2: vec3, x3: vec3) -> scalar:
        if not edge_edge:
            bary = triangle_closest(x0, x1, x2, x3)
            return wp.length(x0 - (bary[0] * x1 + bary[1] * x2 + bary[2] * x3))
        st = edge_closest(x0, x1, x2, x3)
        return wp.length((x0 + st[0] * (x1 - x0)) - (x2 + st[1] * (x3 - x2)))

    return pair_distance


@functools.cache
def _vertex_extent(scalar: type, swept: bool):
    """``extend(lower, upper, j, local, mass_row, particle_flags, particle_inv_mass, particle_q_start,
    particle_q_end, limit, cube) -> (lower, upper)``: the box [lower, upper] grown to hold vertex j's (state entry;
    ``local`` its index in the world) start and, with ``swept``, where it ends the stage at most."""
    vec3 = vec3_type(scalar)
    _, stage_end, is_free, _, _, _ = _pair_funcs(scalar)

    @wp.func
    def extend(lower: vec3, upper: vec3, j: int, local: int, mass_row: int, particle_flags: wp.array[wp.int32],
               particle_inv_mass: wp.array2d[scalar], particle_q_start: wp.array[vec3],
               particle_q_end: wp.array[vec3], limit: scalar, cube: scalar):
        start = particle_q_start[j]
        low = wp.min(lower, start)
        high = wp.max(upper, start)
        if wp.static(swept):
            free = is_free(particle_flags[j], particle_inv_mass[mass_row, local])
            end = stage_end(free, start, particle_q_end[j], limit)
            low = wp.min(low, end)
            high = wp.max(high, end)
            if free:  # and the cube of half-width ρ = ``cube`` around its start (cap_place_kernel)
                grow = vec3(cube, cube, cube)
                low = wp.min(low, start - grow)
                high = wp.max(high, start + grow)
        return low, high

    return extend


@functools.cache
def _pair_funcs(scalar: type):
    """Helpers shared by the stages' kernels, in precision ``scalar``."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)

    @wp.func
    def box_of(lower: vec3, upper: vec3, reach: scalar):
        """A single-precision box around [lower, upper] grown by ``reach`` and the rounding pad."""
        pad = reach + scalar(BOX_PAD) * (wp.max(wp.abs(lower)) + wp.max(wp.abs(upper)) + scalar(1.0))
        grow = vec3(pad, pad, pad)
        return wp.vec3f(lower - grow), wp.vec3f(upper + grow)

    @wp.func
    def stage_end(free: bool, start: vec3, x: vec3, limit: scalar):
        """Where a vertex ends the stage at most: a free vertex's displacement limited to ``limit``, a
        kinematic one's as prescribed."""
        step = wp.length(x - start)
        if free and step > limit:
            return start + (limit / step) * (x - start)
        return x

    @wp.func
    def is_free(flags: wp.int32, inv_mass: scalar):
        return effective_inv_mass(flags, inv_mass) > scalar(0.0)

    @wp.func
    def sweep_bounds(
        vertex: wp.vec4i, base: int, mass_row: int, limit: scalar, cube: scalar, particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar], particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3],
    ):
        """(K, δ): the largest displacement [m] among the pair's kinematic vertices and among its free ones
        (0 where none), free ones limited to ``limit`` and taken as at least ρ = ``cube`` (``cube_reach``: the cap's
        later passes may move a free vertex that far)."""
        kinematic = scalar(0.0)
        free_step = scalar(0.0)
        for k in range(4):
            j = base + vertex[k]
            free = is_free(particle_flags[j], particle_inv_mass[mass_row, vertex[k]])
            step = wp.length(particle_q_end[j] - particle_q_start[j])
            if free:
                free_step = wp.max(free_step, wp.min(wp.max(step, cube), limit))
            else:
                kinematic = wp.max(kinematic, step)
        return kinematic, free_step

    @wp.func
    def kept_by_cap(distance: scalar, floor: scalar, kinematic: scalar, free_step: scalar, relaxation: scalar):
        """Whether the cap keeps a pair whose swept boxes (grown by the floor) overlap (module docstring, 2.): unless
        2 max(K, δ) < D - h, h = ``floor`` (CAP_FLOOR τ), and every free vertex moves at most γ (D - K), when neither
        side can come within h of the other (with h = 0: 2K < D and δ ≤ γ (D - K))."""
        return (scalar(2.0) * wp.max(kinematic, free_step) >= distance - floor
                or free_step > relaxation * (distance - kinematic))

    @wp.func
    def push_pair(
        world: int, base: int, key: wp.int64, vertex: wp.vec4i, distance: scalar, pairs: Pairs,
        pair_distance: wp.array[scalar], counters: wp.array2d[wp.int32],
    ):
        """Store a pair in its world's buffer (or count it as overflow) and count its vertices' entries."""
        capacity = pairs.key.shape[0] // pairs.count.shape[0]
        slot = atomic_slot(pairs.count, world)
        fill = float(slot + 1) / float(capacity)
        if fill > wp.static(FILL_WATCHED):  # the list's fill, where it matters (float: no int32 overflow)
            wp.atomic_max(counters, world, COUNT_FILL, int(wp.min(fill, 1.0) * float(FILL_UNITS)))
        if slot >= capacity:
            wp.atomic_add(counters, world, COUNT_OVERFLOW, 1)
        else:
            s = world * capacity + slot
            pairs.key[s] = key
            pairs.vertex[s] = vertex
            pair_distance[s] = distance
            for k in range(4):
                wp.atomic_add(pairs.vertex_count, base + vertex[k], 1)

    return box_of, stage_end, is_free, sweep_bounds, push_pair, kept_by_cap


@functools.cache
def leaf_kernel(scalar: type, swept: bool):
    """Kernel writing each triangle's single-precision box: at the step's start, or (``swept``) around its
    corners at the start and at the stage's end (``stage_end``)."""
    vec3 = vec3_type(scalar)
    box_of = _pair_funcs(scalar)[0]
    extend = _vertex_extent(scalar, swept)
    cube_reach = cube_reach_func(scalar)

    @flat_kernel(module="unique", enable_backward=False)
    def leaves(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        params: wp.array2d[scalar],
        flags: wp.array[wp.int32],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_end: wp.array[vec3],
        # In/out (the surface; its triangles in, their leaf boxes out):
        surface_in_out: Surface,
    ):
        tid = wp.tid()
        triangle_count = surface_in_out.triangle.shape[0]
        world = tid // triangle_count
        tri = surface_in_out.triangle[tid - world * triangle_count]
        base = world * particle_count
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        row = wp.min(world, params.shape[0] - 1)
        limit = params[row, PARAM_RELAXATION] * scalar(SEARCH_REACH) * params[row, PARAM_THICKNESS]
        cube = cube_reach(flags, world, limit)
        lower = particle_q_start[base + tri[0]]
        upper = lower
        for k in range(3):
            lower, upper = extend(lower, upper, base + tri[k], tri[k], mass_row, particle_flags, particle_inv_mass,
                                  particle_q_start, particle_q_end, limit, cube)
        box_lower, box_upper = box_of(lower, upper, scalar(0.0))
        surface_in_out.leaf_lower[tid] = box_lower
        surface_in_out.leaf_upper[tid] = box_upper

    return leaves


@functools.cache
def broad_kernel(scalar: type, swept: bool, per_primitive: bool = False, primitives: str = "both",
                 bounds: tuple[int, int] | None = None):
    """The broad phase's kernel (module docstring). With ``per_primitive``, ``split`` threads (adjacent) per surface
    vertex (VT pairs) and per edge (EE pairs, kept from the lower edge) of every world, each querying the BVH around
    its primitive's own query box (its start, and with ``swept`` its end, grown by the reach). Without, ``split``
    threads per triangle t, each querying once around the union of the query boxes of the primitives t reports, its
    corners whose ``vertex_owner`` it is and its sides whose ``edge_owner`` it is, and testing each primitive's own box
    against each reported leaf's box before its pairs: the same pairs in half the queries, each thread heavier
    (``core/selfcontact.py``'s ``BROAD_PER_PRIMITIVE`` chooses by device). A thread takes the reported triangles of its
    residue modulo ``split``: a small surface's few queries, each a long chain of dependent reads, spread over more
    threads (the traversal is repeated, the pair tests shared out; ``broad_split``). Without ``swept`` it keeps the
    pairs closer than reach_factor · τ + reach_add at the start and lowers each world's ``near_out`` to the least
    distance among them (``apart_codec``, in units of the τ it lists with); with it the cap's pairs at (start, end).
    ``primitives`` (with ``per_primitive``): "both" in one launch, or only the "vertices"' or the "edges'" queries
    (thread ``me`` of a world then the ``me``-th vertex or edge). ``bounds``: ``flatten.launch_bounds_option``."""
    vec3 = vec3_type(scalar)
    pair_distance = pair_distance_func(scalar)
    box_of, _, _, sweep_bounds, push_pair, kept_by_cap = _pair_funcs(scalar)
    extend = _vertex_extent(scalar, swept)
    cube_reach = cube_reach_func(scalar)
    near_lower, _ = apart_codec(scalar)

    @wp.func
    def boxes_overlap(lower_a: vec3, upper_a: vec3, lower_b: vec3, upper_b: vec3):
        return (lower_a[0] <= upper_b[0] and lower_a[1] <= upper_b[1] and lower_a[2] <= upper_b[2]
                and upper_a[0] >= lower_b[0] and upper_a[1] >= lower_b[1] and upper_a[2] >= lower_b[2])

    @wp.func
    def boxes_overlap_f(lower_a: wp.vec3f, upper_a: wp.vec3f, lower_b: wp.vec3f, upper_b: wp.vec3f):
        return (lower_a[0] <= upper_b[0] and lower_a[1] <= upper_b[1] and lower_a[2] <= upper_b[2]
                and upper_a[0] >= lower_b[0] and upper_a[1] >= lower_b[1] and upper_a[2] >= lower_b[2])

    @wp.func
    def keep(
        distance: scalar, reach: scalar, relaxation: scalar, vertex: wp.vec4i, base: int, mass_row: int,
        limit: scalar, cube: scalar, particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
        particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3],
    ):
        """(kept, the value stored): the distance within the reach, or the cap's pairs (``kept_by_cap``, the floor
        ``reach``) and D - K."""
        if wp.static(not swept):
            return distance < reach, distance
        kinematic, free_step = sweep_bounds(vertex, base, mass_row, limit, cube, particle_flags, particle_inv_mass,
                                            particle_q_start, particle_q_end)
        return kept_by_cap(distance, reach, kinematic, free_step, relaxation), distance - kinematic

    @wp.func
    def query_box(ends: wp.vec2i, base: int, mass_row: int, limit: scalar, cube: scalar, query_reach: scalar,
                  particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
                  particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3]):
        """A vertex's (ends = (v, v)) or an edge's single-precision query box."""
        lower = particle_q_start[base + ends[0]]
        upper = lower
        for k in range(2):
            lower, upper = extend(lower, upper, base + ends[k], ends[k], mass_row, particle_flags, particle_inv_mass,
                                  particle_q_start, particle_q_end, limit, cube)
        return box_of(lower, upper, query_reach)

    @wp.func
    def list_pair(
        world: int, base: int, key: wp.int64, vertex: wp.vec4i, kept: bool, value: scalar, watch_reach: scalar,
        thickness: scalar, first: int, t: int, edge_edge: int, surface: Surface, pairs_out: Pairs,
        pair_distance_out: wp.array[scalar], counters_out: wp.array2d[wp.int32], watch_count_out: wp.array[wp.int32],
        watch_tag_out: wp.array[wp.int32], watch_vertex_out: wp.array[wp.vec4i], near_out: wp.array[wp.int32],
    ):
        """A tested pair stored (``kept``: in the list, its distance lowering ``near_out`` without ``swept``), or
        without ``swept`` watched where closer than ``watch_reach``, tagged with the patches of the owner triangle of
        its first side ``first`` (a vertex, or with ``edge_edge`` an edge) and of the reported triangle ``t``
        (``watch_tag``)."""
        if kept:
            push_pair(world, base, key, vertex, value, pairs_out, pair_distance_out, counters_out)
            if wp.static(not swept):
                near_lower(near_out, world, value, thickness)
        elif wp.static(not swept) and value < watch_reach:
            owner = int(0)
            if edge_edge == 1:
                owner = surface.edge_owner[first]
            else:
                owner = surface.vertex_owner[first]
            tag = (surface.triangle_patch[owner] * WATCH_PATCHES + surface.triangle_patch[t]
                   + edge_edge * WATCH_EDGE_EDGE)
            watch_pair(world, tag, vertex, watch_count_out, watch_tag_out, watch_vertex_out)

    @wp.func
    def vertex_leaf(
        world: int, base: int, v: int, t: int, reach: scalar, relaxation: scalar, mass_row: int, limit: scalar,
        cube: scalar, watch_reach: scalar, thickness: scalar, surface: Surface, particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar], particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3],
        pairs_out: Pairs, pair_distance_out: wp.array[scalar], counters_out: wp.array2d[wp.int32],
        watch_count_out: wp.array[wp.int32], watch_tag_out: wp.array[wp.int32], watch_vertex_out: wp.array[wp.vec4i],
        near_out: wp.array[wp.int32],
    ):
        """The VT pair of vertex v and reported triangle t: kept, watched or neither."""
        tri = surface.triangle[t]
        if tri[0] != v and tri[1] != v and tri[2] != v:  # a topological neighbour: no geometry
            distance = pair_distance(False, particle_q_start[base + v], particle_q_start[base + tri[0]],
                                     particle_q_start[base + tri[1]], particle_q_start[base + tri[2]])
            vertex = wp.vec4i(v, tri[0], tri[1], tri[2])
            kept, value = keep(distance, reach, relaxation, vertex, base, mass_row, limit, cube, particle_flags,
                               particle_inv_mass, particle_q_start, particle_q_end)
            key = wp.int64(v) * wp.int64(surface.triangle.shape[0]) + wp.int64(t)
            list_pair(world, base, key, vertex, kept, value, watch_reach, thickness, v, t, 0,
                      surface, pairs_out, pair_distance_out, counters_out, watch_count_out, watch_tag_out,
                      watch_vertex_out, near_out)

    @wp.func
    def edge_leaf(
        world: int, base: int, particle_count: int, e: int, box_lower: vec3, box_upper: vec3, t: int, reach: scalar,
        relaxation: scalar, mass_row: int, limit: scalar, cube: scalar, watch_reach: scalar, thickness: scalar,
        surface: Surface, particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
        particle_q_start: wp.array[vec3], particle_q_end: wp.array[vec3], pairs_out: Pairs,
        pair_distance_out: wp.array[scalar], counters_out: wp.array2d[wp.int32], watch_count_out: wp.array[wp.int32],
        watch_tag_out: wp.array[wp.int32], watch_vertex_out: wp.array[wp.vec4i], near_out: wp.array[wp.int32],
    ):
        """The EE pairs of edge e (query box [box_lower, box_upper]) with the sides reported triangle t owns."""
        ends = surface.edge[e]
        owned = surface.owned_sides[t]
        for n in range(3):
            f = owned[n, 0]
            other = wp.vec2i(owned[n, 1], owned[n, 2])
            # Each pair once (from its lower edge, through the other edge's owner triangle: f = -1 where t is not
            # its owner), no shared vertex: index tests before any geometry.
            if (f > e and other[0] != ends[0] and other[0] != ends[1]
                    and other[1] != ends[0] and other[1] != ends[1]):
                p2 = particle_q_start[base + other[0]]
                q2 = particle_q_start[base + other[1]]
                # The other edge's own (swept) box against the query box, before the geometry: a pair closer than
                # the reach overlaps it, and a disjoint swept pair cannot meet (proof, (a)).
                other_lower = p2
                other_upper = p2
                for k in range(2):
                    other_lower, other_upper = extend(other_lower, other_upper, base + other[k], other[k], mass_row,
                                                      particle_flags, particle_inv_mass, particle_q_start,
                                                      particle_q_end, limit, cube)
                if boxes_overlap(other_lower, other_upper, box_lower, box_upper):
                    distance = pair_distance(True, particle_q_start[base + ends[0]],
                                             particle_q_start[base + ends[1]], p2, q2)
                    vertex = wp.vec4i(ends[0], ends[1], other[0], other[1])
                    kept, value = keep(distance, reach, relaxation, vertex, base, mass_row, limit, cube,
                                       particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
                    key = (wp.int64(particle_count) * wp.int64(surface.triangle.shape[0])
                           + wp.int64(e) * wp.int64(surface.edge.shape[0]) + wp.int64(f))
                    list_pair(world, base, key, vertex, kept, value, watch_reach, thickness, e, t,
                              1, surface, pairs_out, pair_distance_out, counters_out, watch_count_out, watch_tag_out,
                              watch_vertex_out, near_out)

    @flat_kernel(module="unique", enable_backward=False, **launch_bounds_option(bounds))
    def broad(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        flags: wp.array[wp.int32],
        reach_factor: scalar,
        reach_add: scalar,
        watch_factor: scalar,
        split: int,
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_end: wp.array[vec3],
        # Out:
        pairs_out: Pairs,
        pair_distance_out: wp.array[scalar],
        counters_out: wp.array2d[wp.int32],
        watch_count_out: wp.array[wp.int32],
        watch_tag_out: wp.array[wp.int32],
        watch_vertex_out: wp.array[wp.vec4i],
        near_out: wp.array[wp.int32],
    ):
        tid = wp.tid()
        triangle_count = surface.triangle.shape[0]
        edge_count = surface.edge.shape[0]
        thread = tid // split
        part = tid - thread * split  # this thread takes the reported triangles t ≡ part (mod split)
        per_world = triangle_count
        if wp.static(per_primitive and primitives == "both"):
            per_world = particle_count + edge_count
        if wp.static(per_primitive and primitives == "vertices"):
            per_world = particle_count
        if wp.static(per_primitive and primitives == "edges"):
            per_world = edge_count
        world = thread // per_world
        me = thread - world * per_world
        if wp.static(per_primitive and primitives == "edges"):
            me += particle_count
        base = world * particle_count
        if world_enabled[world] == 0:
            return
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        row = wp.min(world, params.shape[0] - 1)
        thickness = params[row, PARAM_THICKNESS]
        relaxation = params[row, PARAM_RELAXATION]
        limit = relaxation * scalar(SEARCH_REACH) * thickness
        cube = cube_reach(flags, world, limit)
        reach = reach_factor * thickness + reach_add
        watch_reach = watch_factor * thickness  # pairs in [reach, watch_reach) are watched (without swept)
        query_reach = wp.max(reach, watch_reach)
        if wp.static(swept):  # the cap's floor: the query boxes grown by it, and the reach keep() reads as it
            reach = scalar(CAP_FLOOR) * thickness
            query_reach = reach
        if wp.static(per_primitive):
            # One primitive, its own query: a vertex (me < particle_count, where it is on the surface) or an edge.
            is_vertex = me < particle_count
            if wp.static(primitives == "vertices"):
                is_vertex = True
            if wp.static(primitives == "edges"):
                is_vertex = False
            ends = wp.vec2i(me, me)
            if is_vertex:
                if surface.vertex_owner[me] < 0:
                    return
            else:
                ends = surface.edge[me - particle_count]
            lower, upper = query_box(ends, base, mass_row, limit, cube, query_reach, particle_flags, particle_inv_mass,
                                     particle_q_start, particle_q_end)
            query = wp.bvh_query_aabb(surface.bvh[world], lower, upper)
            t = int(0)
            while wp.bvh_query_next(query, t):
                if t % split != part:
                    continue
                if is_vertex:
                    vertex_leaf(world, base, me, t, reach, relaxation, mass_row, limit, cube, watch_reach, thickness,
                                surface, particle_flags, particle_inv_mass, particle_q_start, particle_q_end,
                                pairs_out, pair_distance_out, counters_out, watch_count_out, watch_tag_out,
                                watch_vertex_out, near_out)
                else:
                    edge_leaf(world, base, particle_count, me - particle_count, vec3(lower), vec3(upper), t, reach,
                              relaxation, mass_row, limit, cube, watch_reach, thickness, surface, particle_flags,
                              particle_inv_mass, particle_q_start, particle_q_end, pairs_out, pair_distance_out,
                              counters_out, watch_count_out, watch_tag_out, watch_vertex_out, near_out)
            return
        corners = surface.triangle[me]
        owned = surface.owned_sides[me]
        # The primitives this triangle reports, their query boxes (rows of the matrices) and their union.
        vertex_lower = wp.mat33f()
        vertex_upper = wp.mat33f()
        edge_lower = wp.mat33f()
        edge_upper = wp.mat33f()
        owns_vertex = wp.vec3i(0, 0, 0)
        owns_edge = wp.vec3i(0, 0, 0)
        union_lower = wp.vec3f(3.0e38, 3.0e38, 3.0e38)
        union_upper = wp.vec3f(-3.0e38, -3.0e38, -3.0e38)
        for m in range(3):
            if surface.vertex_owner[corners[m]] == me:
                owns_vertex[m] = 1
                lower, upper = query_box(wp.vec2i(corners[m], corners[m]), base, mass_row, limit, cube, query_reach,
                                         particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
                vertex_lower[m] = lower
                vertex_upper[m] = upper
                union_lower = wp.min(union_lower, lower)
                union_upper = wp.max(union_upper, upper)
            if owned[m, 0] >= 0:
                owns_edge[m] = 1
                lower, upper = query_box(wp.vec2i(owned[m, 1], owned[m, 2]), base, mass_row, limit, cube, query_reach,
                                         particle_flags, particle_inv_mass, particle_q_start, particle_q_end)
                edge_lower[m] = lower
                edge_upper[m] = upper
                union_lower = wp.min(union_lower, lower)
                union_upper = wp.max(union_upper, upper)
        if owns_vertex[0] + owns_vertex[1] + owns_vertex[2] + owns_edge[0] + owns_edge[1] + owns_edge[2] == 0:
            return
        query = wp.bvh_query_aabb(surface.bvh[world], union_lower, union_upper)
        t = int(0)
        while wp.bvh_query_next(query, t):
            if t % split != part:
                continue
            leaf_lower = surface.leaf_lower[world * triangle_count + t]
            leaf_upper = surface.leaf_upper[world * triangle_count + t]
            for m in range(3):
                # VT: the vertex's own query would have reported t where its box overlaps t's leaf box.
                if owns_vertex[m] == 1 and boxes_overlap_f(vertex_lower[m], vertex_upper[m], leaf_lower, leaf_upper):
                    vertex_leaf(world, base, corners[m], t, reach, relaxation, mass_row, limit, cube, watch_reach,
                                thickness, surface, particle_flags, particle_inv_mass, particle_q_start,
                                particle_q_end, pairs_out, pair_distance_out, counters_out, watch_count_out,
                                watch_tag_out, watch_vertex_out, near_out)
                # EE: the edge's own query would have reported t where its box overlaps t's leaf box.
                if owns_edge[m] == 1 and boxes_overlap_f(edge_lower[m], edge_upper[m], leaf_lower, leaf_upper):
                    edge_leaf(world, base, particle_count, owned[m, 0], vec3(edge_lower[m]), vec3(edge_upper[m]), t,
                              reach, relaxation, mass_row, limit, cube, watch_reach, thickness, surface,
                              particle_flags, particle_inv_mass, particle_q_start, particle_q_end, pairs_out,
                              pair_distance_out, counters_out, watch_count_out, watch_tag_out, watch_vertex_out,
                              near_out)

    return broad


@wp.func
def watch_pair(world: int, tag: int, vertex: wp.vec4i, watch_count: wp.array[wp.int32],
               watch_tag: wp.array[wp.int32], watch_vertex: wp.array[wp.vec4i]):
    """Store a watched pair (its tag: its sides' patches and its kind, ``WATCH_PATCHES``) in its world's watch list
    (module ``selfcontact_cache``); beyond its capacity only counted (the world's cache then takes the reach
    CACHE_REACH τ)."""
    capacity = watch_tag.shape[0] // watch_count.shape[0]
    slot = atomic_slot(watch_count, world)
    if slot < capacity:
        watch_tag[world * capacity + slot] = tag
        watch_vertex[world * capacity + slot] = vertex


@functools.cache
def fill_kernel():
    """Kernel writing each listed pair's four entries into its vertices' CSR segments, in the worlds ``active``
    names (one thread per particle of every world, each taking its world's slots local, local +
    particle_count, ...)."""

    @flat_kernel(module="unique", enable_backward=False)
    def fill(particle_count: int, active: wp.array[wp.int32], pairs_in_out: Pairs):
        p = wp.tid()
        world, local = world_and_index(p, particle_count)
        if active[world] == 0:
            return
        capacity = pairs_in_out.key.shape[0] // pairs_in_out.count.shape[0]
        for slot in range(local, wp.min(pairs_in_out.count[world], capacity), particle_count):
            s = world * capacity + slot
            vertex = pairs_in_out.vertex[s]
            for k in range(4):
                j = world * particle_count + vertex[k]
                pairs_in_out.entry[
                    pairs_in_out.vertex_start[j] + wp.atomic_add(pairs_in_out.vertex_cursor, j, 1)
                ] = 4 * s + k

    return fill


@functools.cache
def reset_kernel():
    """Kernel emptying the pair buffer of the worlds ``active`` names (its count, and its particles' entry counts
    and cursors), their watch lists' counts and the least distance of their listed pairs (``near_out``), one thread
    per particle of every world; the others keep theirs."""

    @flat_kernel(module="unique", enable_backward=False)
    def reset(
        # Model:
        particle_count: int,
        active: wp.array[wp.int32],
        # Out:
        pairs_out: Pairs,
        watch_count_out: wp.array[wp.int32],
        near_out: wp.array[wp.int32],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if active[world] == 0:
            return
        if i == 0:
            pairs_out.count[world] = 0
            watch_count_out[world] = 0
            near_out[world] = 0  # none recorded (``apart_codec``)
        pairs_out.vertex_count[p] = 0
        pairs_out.vertex_cursor[p] = 0

    return reset


#: Entries per tile of ``scan_kernels``' exclusive scan, and the threads of each tile's block.
SCAN_BLOCK = 1024
SCAN_THREADS = 256


@functools.cache
def scan_kernels():
    """The CSR's exclusive scan, world by world, in three tiled launches (``wp.launch_tiled``, ``SCAN_THREADS``
    threads per block) and no allocation (so that it may run inside a conditional graph node, where
    ``wp.utils.array_scan``'s temporary buffer may not), over arrays viewed as [world_count, particle_count]:
    world w's prefixes start at w · ``world_stride`` (4 w · capacity for a pair buffer), so that rebuilding one
    world's list moves no other world's entries. Each tile of ``SCAN_BLOCK`` entries sums itself
    (``tile_sums``), one block per world scans its tiles' sums (``tile_offsets``, in chunks of SCAN_BLOCK tiles),
    each tile scans itself from its offset (``tile_prefixes``): every step a block's threads share, none a
    single thread walks alone. Integer sums: the same result every run. A particle's segment is
    [vertex_start[p], vertex_start[p] + vertex_count[p])."""

    @wp.kernel(module="unique", enable_backward=False)
    def tile_sums(values: wp.array2d[wp.int32], tile_total_out: wp.array2d[wp.int32]):
        world, k = wp.tid()
        t = wp.tile_load(values[world], shape=(SCAN_BLOCK,), offset=(k * SCAN_BLOCK,))
        wp.tile_store(tile_total_out[world], wp.tile_sum(t), offset=(k,))

    @wp.kernel(module="unique", enable_backward=False)
    def tile_offsets(world_stride: int, tile_total_in_out: wp.array2d[wp.int32]):
        world = wp.tid()
        carry = world * world_stride
        for chunk in range((tile_total_in_out.shape[1] + SCAN_BLOCK - 1) // SCAN_BLOCK):
            t = wp.tile_load(tile_total_in_out[world], shape=(SCAN_BLOCK,), offset=(chunk * SCAN_BLOCK,))
            inclusive = wp.tile_scan_inclusive(t)
            exclusive = wp.tile_scan_exclusive(t)
            wp.tile_store(tile_total_in_out[world], exclusive + wp.tile_full(shape=(SCAN_BLOCK,), value=carry, dtype=int),
                          offset=(chunk * SCAN_BLOCK,))
            carry += wp.tile_extract(inclusive, SCAN_BLOCK - 1)

    @wp.kernel(module="unique", enable_backward=False)
    def tile_prefixes(
        # In:
        values: wp.array2d[wp.int32],
        tile_offset: wp.array2d[wp.int32],
        # Out:
        prefix_out: wp.array2d[wp.int32],
    ):
        world, k = wp.tid()
        t = wp.tile_load(values[world], shape=(SCAN_BLOCK,), offset=(k * SCAN_BLOCK,))
        start = wp.tile_full(shape=(SCAN_BLOCK,), value=tile_offset[world, k], dtype=int)
        wp.tile_store(prefix_out[world], wp.tile_scan_exclusive(t) + start, offset=(k * SCAN_BLOCK,))

    return tile_sums, tile_offsets, tile_prefixes


@wp.func
def sorted_segment(pairs: Pairs, p: int):
    """Particle p's segment of entries [first, last), sorted in place by the pairs' keys (insertion sort; a
    particle appears once in a pair, so keys do not repeat within a segment)."""
    first = pairs.vertex_start[p]
    last = first + pairs.vertex_count[p]
    for a in range(first + 1, last):
        item = pairs.entry[a]
        key = pairs.key[item // 4]
        b = a - 1
        while b >= first and pairs.key[pairs.entry[b] // 4] > key:
            pairs.entry[b + 1] = pairs.entry[b]
            b -= 1
        pairs.entry[b + 1] = item
    return first, last


@functools.cache
def repel_pairs_kernel(scalar: type):
    """Kernel of the repulsion's narrow phase over a world's listed pairs (one thread per particle of every world,
    each taking its world's slots local, local + particle_count, ...): for each pair closer than the repulsion's
    reach at the step's start, its four vertices' corrections [m] and weights |wₖ| into the pair's slots, zeros
    for the other pairs (they are pushed by nothing); and each enabled world's count of steps whose stages ran."""
    vec3 = vec3_type(scalar)
    vec4 = wp.types.vector(4, scalar)
    triangle_closest, edge_closest = geometry_funcs(scalar)
    effective_inv_mass = particle_funcs(scalar)

    @wp.func
    def repel_pair(
        s: int, world: int, base: int, mass_row: int, thickness: scalar, friction: scalar, particle_count: int,
        particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar], surface: Surface, pairs: Pairs,
        particle_q_start: wp.array[vec3], particle_q_in: wp.array[vec3],
        pair_correction_out: wp.array[vec3], pair_weight_out: wp.array[scalar], counters_out: wp.array2d[wp.int32],
    ):
        for k in range(4):
            pair_correction_out[4 * s + k] = vec3(scalar(0.0))
            pair_weight_out[4 * s + k] = scalar(0.0)
        index = pairs.vertex[s]
        zero, one = scalar(0.0), scalar(1.0)
        x0 = particle_q_start[base + index[0]]
        x1 = particle_q_start[base + index[1]]
        x2 = particle_q_start[base + index[2]]
        x3 = particle_q_start[base + index[3]]
        weight = vec4(zero)
        diff = vec3(zero)
        fallback = vec3(zero)
        if pairs.key[s] < wp.int64(particle_count) * wp.int64(surface.triangle.shape[0]):  # VT
            bary = triangle_closest(x0, x1, x2, x3)
            diff = x0 - (bary[0] * x1 + bary[1] * x2 + bary[2] * x3)
            weight = vec4(one, -bary[0], -bary[1], -bary[2])
            fallback = wp.normalize(wp.cross(x2 - x1, x3 - x1))
        else:  # EE
            st = edge_closest(x0, x1, x2, x3)
            diff = (x0 + st[0] * (x1 - x0)) - (x2 + st[1] * (x3 - x2))
            weight = vec4(one - st[0], st[0], st[1] - one, -st[1])
            fallback = wp.normalize(wp.cross(x1 - x0, x3 - x2))
        d = wp.length(diff)
        # The distance exactly as the broad phase computes it: the same pairs as a list cut at the reach.
        if not (d < scalar(REPULSION_REACH) * thickness):
            return
        n = fallback
        if d > scalar(1.0e-12) * thickness:
            n = diff / d
        if wp.length(n) == zero:
            return
        relative = vec3(zero)
        generalized = zero
        inv_mass = vec4(zero)
        for k in range(4):
            j = base + index[k]
            inv_mass[k] = effective_inv_mass(particle_flags[j], particle_inv_mass[mass_row, index[k]])
            relative += weight[k] * (particle_q_in[j] - particle_q_start[j])
            generalized += weight[k] * weight[k] * inv_mass[k]
        normal = wp.dot(n, relative)
        push = thickness - (d + normal)
        if push <= zero or generalized <= zero:
            return
        tangential = relative - normal * n
        slip = wp.length(tangential)
        dx = push * n
        if slip > zero:
            dx -= (wp.min(friction * push, slip) / slip) * tangential
        for k in range(4):
            pair_correction_out[4 * s + k] = (weight[k] * inv_mass[k] / generalized) * dx
            pair_weight_out[4 * s + k] = wp.abs(weight[k])
        wp.atomic_add(counters_out, world, COUNT_PAIRS, 1)

    @flat_kernel(module="unique", enable_backward=False)
    def repel_pairs(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        pairs: Pairs,
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_in: wp.array[vec3],
        # Out:
        pair_correction_out: wp.array[vec3],
        pair_weight_out: wp.array[scalar],
        counters_out: wp.array2d[wp.int32],
    ):
        p = wp.tid()
        world, local = world_and_index(p, particle_count)
        if world_enabled[world] == 0:
            return
        if local == 0:  # (one thread per world)
            counters_out[world, COUNT_STAGES] += 1
        capacity = pairs.key.shape[0] // pairs.count.shape[0]
        base = world * particle_count
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        row = wp.min(world, params.shape[0] - 1)
        thickness = params[row, PARAM_THICKNESS]
        friction = params[row, PARAM_FRICTION]
        for slot in range(local, wp.min(pairs.count[world], capacity), particle_count):
            repel_pair(world * capacity + slot, world, base, mass_row, thickness, friction, particle_count,
                       particle_flags, particle_inv_mass, surface, pairs, particle_q_start, particle_q_in,
                       pair_correction_out, pair_weight_out, counters_out)

    return repel_pairs


@wp.func
def flag_slot(kind: int, world: int, world_count: int):
    """The entry of world ``world``'s flag ``kind`` (FLAG_*) in the pass's flag array: [any rebuild, any
    fallback, then world_count entries per kind]."""
    return 2 + kind * world_count + world


@functools.cache
def cube_reach_func(scalar: type):
    """``cube_reach(flags, world, limit) -> ρ`` [m]: how far the cap's later passes may move a free vertex of world
    ``world`` in any direction (``cap_place_kernel``): γ τ (= ``limit`` / SEARCH_REACH) where the world's pins move
    (FLAG_KINEMATIC above its lowest level: only a pin's approach asks a vertex to give way), else 0."""

    @wp.func
    def cube_reach(flags: wp.array[wp.int32], world: int, limit: scalar):
        world_count = (flags.shape[0] - 2) // FLAG_KINDS
        if flags[flag_slot(FLAG_KINEMATIC, world, world_count)] > 1:
            return limit / scalar(SEARCH_REACH)
        return scalar(0.0)

    return cube_reach


@wp.func
def raise_flag(flags: wp.array[wp.int32], kind: int, world: int, world_count: int):
    """Set world ``world``'s flag ``kind`` and the matching any-world flag (FLAG_REBUILD or FLAG_FALLBACK; a rebuild
    also FLAG_BUSY)."""
    flags[flag_slot(kind, world, world_count)] = 1
    flags[kind] = 1
    if kind == FLAG_REBUILD:
        flags[flag_slot(FLAG_BUSY, 0, world_count)] = 1


@wp.func
def raise_work(flags: wp.array[wp.int32], world_count: int):
    """Ask for the pair stages (FLAG_WORK's first entry) and so for the step's busy branch (FLAG_BUSY's)."""
    flags[flag_slot(FLAG_WORK, 0, world_count)] = 1
    flags[flag_slot(FLAG_BUSY, 0, world_count)] = 1


@functools.cache
def apart_codec(scalar: type):
    """``(lower, read)``: ``lower(stored, slot, distance, thickness)`` lowers the least distance kept in
    ``stored[slot]`` to ``distance`` [m], rounded down to units of τ / KINEMATIC_STEPS (a negative or non-finite
    distance records 0) and stored as APART_NONE less the units, an integer maximum read first
    (``linalg.atomic_raise``, warp-aggregated on CUDA; order-free: the least distance any thread recorded; 0, the
    storage's zero, is none); ``read(value, thickness)`` the distance [m] a stored value holds (APART_NONE units,
    beyond any reach, for none)."""

    @wp.func
    def lower(stored: wp.array[wp.int32], slot: int, distance: scalar, thickness: scalar):
        units = distance / thickness * scalar(KINEMATIC_STEPS)
        value = int(APART_NONE)  # a distance of 0: a negative one, or NaN
        if units >= scalar(APART_NONE):
            value = int(0)  # too far to record
        elif units >= scalar(0.0):
            value = int(APART_NONE) - int(wp.floor(units))
        atomic_raise(stored, slot, value)

    @wp.func
    def read(value: int, thickness: scalar) -> scalar:
        return scalar(APART_NONE - value) * thickness / scalar(KINEMATIC_STEPS)

    return lower, read


@functools.cache
def apart_funcs(scalar: type):
    """``(record, least)``: ``record(flags, world, world_count, distance, thickness)`` lowers world ``world``'s
    FLAG_APART to ``distance`` [m] (``apart_codec``'s ``lower``); ``least(flags, world, world_count, thickness)``
    reads it back [m] (APART_NONE units, beyond any reach, where none was recorded)."""
    lower, read = apart_codec(scalar)

    @wp.func
    def record(flags: wp.array[wp.int32], world: int, world_count: int, distance: scalar, thickness: scalar):
        lower(flags, flag_slot(FLAG_APART, world, world_count), distance, thickness)

    @wp.func
    def least(flags: wp.array[wp.int32], world: int, world_count: int, thickness: scalar) -> scalar:
        return read(flags[flag_slot(FLAG_APART, world, world_count)], thickness)

    return record, least


@functools.cache
def repel_gather_kernel(scalar: type):
    """Kernel of the repulsion's gather: ``particle_q_in`` (the integrator's result) plus each free surface
    vertex's mean correction over its pairs, summed in key order, into ``particle_q_out``; and whether the cached
    pairs suffice for the cap: a world is flagged for the swept broad phase (FLAG_FALLBACK) when its list
    overflowed, one of its free vertices moves further than min(γ (A_w - K_w), (A_w - CAP_FLOOR τ) / 2) or its pins
    that half (A_w: the least distance at the step's start of a pair outside the cache, FLAG_APART, CACHE_REACH τ
    where the cache was rebuilt at that start, at least REPULSION_REACH τ; K_w: its kinematic vertices' largest
    displacement; module ``selfcontact_cache``)."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)
    _, least = apart_funcs(scalar)

    @flat_kernel(module="unique", enable_backward=False)
    def repel_gather(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        world_enabled: wp.array[wp.int32],
        surface: Surface,
        params: wp.array2d[scalar],
        # Pairs in (repel_pairs' corrections and weights):
        pair_correction: wp.array[vec3],
        pair_weight: wp.array[scalar],
        # State in:
        particle_q_start: wp.array[vec3],
        particle_q_in: wp.array[vec3],
        # In/out (each vertex's segment of pair entries sorted in place; the pass's flags):
        pairs_in_out: Pairs,
        flags_in_out: wp.array[wp.int32],
        # Out:
        particle_q_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        x = particle_q_in[p]
        particle_q_out[p] = x
        if world_enabled[world] == 0 or surface.vertex_owner[i] < 0:
            return
        if effective_inv_mass(particle_flags[p], particle_inv_mass[mass_row, i]) == scalar(0.0):
            return
        first, last = sorted_segment(pairs_in_out, p)
        correction = vec3(scalar(0.0))
        count = scalar(0.0)
        for a in range(first, last):
            e = pairs_in_out.entry[a]
            correction += pair_correction[e]
            count += pair_weight[e]
        if count > scalar(0.0):  # a weighted mean: a pair counts by the vertex's weight in it, the sum by 1 at least
            x = x + correction / wp.max(count, scalar(1.0))
            particle_q_out[p] = x
        # Does the cache hold every pair the cap could keep? (module selfcontact_cache: pairs outside it are at
        # least A_w apart at the step's start, A_w ≥ REPULSION_REACH τ.)
        world_count = pairs_in_out.count.shape[0]
        row = wp.min(world, params.shape[0] - 1)
        thickness = params[row, PARAM_THICKNESS]
        relaxation = params[row, PARAM_RELAXATION]
        start = particle_q_start[p]
        delta = wp.min(wp.length(x - start), relaxation * scalar(SEARCH_REACH) * thickness)
        kinematic = (scalar(flags_in_out[flag_slot(FLAG_KINEMATIC, world, world_count)]) / scalar(KINEMATIC_STEPS)
                     * thickness)
        apart = least(flags_in_out, world, world_count, thickness)
        if flags_in_out[flag_slot(FLAG_REBUILD, world, world_count)] != 0:
            apart = scalar(CACHE_REACH) * thickness  # rebuilt at this step's start: it holds every pair closer
        apart = wp.max(apart * scalar(1.0 - SAFETY), scalar(REPULSION_REACH) * thickness)
        offset = apart - scalar(CAP_FLOOR) * thickness  # D - h of a pair outside the cache, at least
        budget = (wp.min(relaxation * (apart - kinematic), scalar(0.5) * offset)
                  * scalar(1.0 - SAFETY) - scalar(BOX_PAD) * (wp.max(wp.abs(start)) + scalar(1.0)))
        overflow = pairs_in_out.count[world] > pairs_in_out.key.shape[0] // world_count
        # A pin moving half the offset may reach a pair outside the cache (the cap keeps the pairs with 2K >= D - h).
        far = scalar(2.0) * kinematic >= offset * scalar(1.0 - SAFETY)
        if overflow or far or (delta > scalar(0.0) and not (delta <= budget)):
            raise_flag(flags_in_out, FLAG_FALLBACK, world, world_count)

    return repel_gather


@functools.cache
def proximity_kernel(scalar: type):
    """Kernel of the broad phase's audit, after a broad phase without ``swept``: per surface vertex, its
    distance to the nearest listed pair it belongs to (``reach`` [m] when none) and their number (-1 for
    vertices off the surface)."""

    @flat_kernel(module="unique", enable_backward=False)
    def proximity(
        # Model:
        particle_count: int,
        surface: Surface,
        pairs: Pairs,
        pair_distance: wp.array[scalar],
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
        nearest = reach
        for a in range(pairs.vertex_start[p], pairs.vertex_start[p] + pairs.vertex_count[p]):
            nearest = wp.min(nearest, pair_distance[pairs.entry[a] // 4])
        nearest_out[p] = nearest
        count_out[p] = pairs.vertex_count[p]

    return proximity
