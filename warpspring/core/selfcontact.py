"""Self-collision of the model's triangle surfaces (cloth, soft-body skins): the host side of
``kernels/selfcontact.py``.

``ModelBuilder.add_self_collision(thickness=..., friction=...)`` asks for it; the model then holds a
:class:`SelfContact` (``Model.self_contact``), and :class:`~warpspring.core.constraints.StepFinisher` runs it
last in every step of every integrator, reading the step's start and its result. Scenes without it compile
and launch none of it.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..errors import ConfigError
from ..kernels.flatten import flat_launch, launch_bounds
from ..kernels.selfcontact import (
    CACHE_REACH,
    CACHE_SLOTS,
    COUNT_CAPPED,
    COUNT_FALLBACKS,
    COUNT_FILL,
    COUNT_OUTRUN,
    COUNT_OVERFLOW,
    COUNT_PAIRS,
    COUNT_REBUILDS,
    COUNT_SQUEEZED,
    COUNT_STAGES,
    COUNTER_COUNT,
    FILL_UNITS,
    FLAG_BUSY,
    FLAG_KINDS,
    FLAG_WORK,
    PAIRS_PER_VERTEX,
    PARAM_COUNT,
    PARAM_FRICTION,
    PARAM_RELAXATION,
    PARAM_THICKNESS,
    PATCH_CHUNK,
    PATCH_COLUMNS,
    PATCH_THREADS,
    SCAN_BLOCK,
    SCAN_THREADS,
    WATCH_PATCHES,
    WATCH_REACH,
    Pairs,
    Surface,
    broad_kernel,
    fill_kernel,
    leaf_kernel,
    mat33i,
    patch_count,
    proximity_kernel,
    repel_gather_kernel,
    repel_pairs_kernel,
    reset_kernel,
    scan_kernels,
)
from ..kernels.selfcontact_cache import (
    anchor_kernel,
    cap_bounds_kernel,
    check_kernel,
    decide_kernel,
    watch_kernel,
)
from ..kernels.selfcontact_cap import (
    LEVELS_PER_ROUND,
    LOOP_CONDITION,
    LOOP_SIZE,
    PUSHER_COLOURS,
    ROLE_MOVER,
    ROLE_PUSHER,
    cap_check_kernel,
    cap_gather_kernel,
    cap_loop_gate_kernel,
    cap_mark_kernel,
    cap_place_kernel,
)

#: The default relaxation γ of the displacement cap: a vertex moves at most a quarter of its distance to the
#: nearest primitive, so a pair beyond the repulsion's reach (2 τ) ends a step at least τ apart.
DEFAULT_RELAXATION = 0.25
#: The most levels of the cap's making room for its jammed vertices (``SelfContact._cap_stage``): a jammed vertex's
#: neighbours across its kept pairs move away, then it is placed again, level after level while a vertex stays
#: jammed (a loop on the device, ``wp.capture_while``: a step with none runs no level). A pin squeezing n free layers,
#: each on the floor of the next, needs about n (a layer a level, the pushers placed from the back; five layers: 5;
#: the small 720° twist's squeezes went through three to six). Where a CUDA driver lacks conditional graph nodes, a
#: captured step runs CAP_LEVELS_UNCONDITIONAL levels.
CAP_LEVELS = 16
CAP_LEVELS_UNCONDITIONAL = 6
#: The thickness must stay below this share of the surface's smallest triangle altitude: at rest, a vertex and
#: a triangle of its neighbourhood that do not share it are an altitude apart or more, and must not repel.
MAX_THICKNESS_SHARE = 0.7


#: Threads per multiprocessor the broad phase aims for on CUDA (``broad_split``): a BVH query is a chain of dependent
#: reads, hidden only by other threads' work.
BROAD_THREADS_PER_SM = 512
#: The most threads that share one query (``broad_split``); ``BROAD_SPLIT``: ``None``, or an int to force a split.
BROAD_SPLIT_MAX = 8
BROAD_SPLIT = None
#: The broad phase's queries: one per surface vertex and one per edge, each around its own box (True), or one per
#: triangle around the union of its vertices' and edges' boxes (False); the same pairs (``broad_kernel``). ``None``:
#: per primitive on CUDA, where its lighter threads made the draped cloth's pass 1.2-1.3x cheaper at 64²-1024² on an
#: H200, per triangle on the CPU, where its half as many queries made it 1.3-1.4x cheaper at 32²-64²
#: (``bench/results/selfcontact.md``).
BROAD_PER_PRIMITIVE = None
#: With one query per primitive, the vertices' and the edges' queries as two launches, each kernel holding one kind
#: of leaf test (True), or one launch over both (False); ``None``: two on CUDA. The draped cloth's cache build on an
#: H200 (blocks of 64), one launch against two: 7.8 against 6.1 ms at 1024², 573 against 531 µs at 256², 220 against
#: 284 µs at 64²; but one launch made ``stacked_cloths`` 1.3x slower (``bench/results/selfcontact.md``, "The edges'
#: queries read their triangle's sides at once").
BROAD_SEPARATE = None
#: With two launches on CUDA, the vertices' launch on a stream of its own beside the edges' (True: forked from the
#: step's stream and joined back, so that a capture records them side by side), or one after the other (False, the
#: default). Side by side on an H200 the draped cloth's pass was 1.14x cheaper at 64², 1.06x at 256², the same at
#: 1024², and ``twisted_cloth`` 1.15x faster, but ``stacked_cloths`` 0.8x as fast (its builds ~4x dearer), as with
#: one launch over both (``BROAD_SEPARATE``): not the default (``bench/results/selfcontact.md``, "Fewer conditional
#: nodes").
BROAD_CONCURRENT = False
#: Threads per block of the broad phase on CUDA (``None``: the model's block size). Each thread keeps its BVH
#: traversal's stack in shared memory (132 B): in blocks of 256 the shared memory holds one block a multiprocessor
#: (12.5 % occupancy); in blocks of 64 the registers bound it (the same build: 11.6 -> 8.5 ms at 1024² in one launch).
BROAD_BLOCK = 64
#: The broad phase's blocks a multiprocessor its registers must allow on CUDA (``__launch_bounds__``; ``None``: the
#: compiler's choice).
BROAD_MIN_BLOCKS = None


def broad_split(device, queries: int) -> int:
    """Threads per query of the broad phase (``kernels/selfcontact.py``, ``broad_kernel``; per watched pairs' list of
    ``watch_kernel`` likewise): on CUDA, enough that ``queries`` (over all worlds) fill BROAD_THREADS_PER_SM threads a
    multiprocessor, at most BROAD_SPLIT_MAX;
    1 on the CPU (a thread there is a loop iteration: the split would only repeat the traversal). ``BROAD_SPLIT``
    overrides it (benchmarks)."""
    if BROAD_SPLIT is not None:
        return int(BROAD_SPLIT)
    if not device.is_cuda:
        return 1
    wanted = device.sm_count * BROAD_THREADS_PER_SM
    return int(min(BROAD_SPLIT_MAX, max(1, -(-wanted // max(queries, 1)))))


def check_settings(thickness: float, friction: float, relaxation: float) -> tuple[float, float, float]:
    """The three live values checked: τ > 0 [m], μ ≥ 0 [-], γ in (0, 1/2) [-]."""
    values = []
    for name, value, ok, rule in (
        ("thickness", thickness, lambda v: v > 0.0, "> 0 [m]"),
        ("friction", friction, lambda v: v >= 0.0, ">= 0"),
        ("relaxation", relaxation, lambda v: 0.0 < v < 0.5, "in (0, 0.5): the cap's proof needs γ < 1/2"),
    ):
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"self-collision {name} must be a number {rule}, got {value!r}") from None
        if not np.isfinite(value) or not ok(value):
            raise ConfigError(f"self-collision {name} must be {rule}, got {value!r}")
        values.append(value)
    return tuple(values)


def surface_topology(triangles: np.ndarray, particle_count: int) -> dict:
    """The arrays of :class:`~warpspring.kernels.selfcontact.Surface` (but the meshes) for ``triangles``
    [triangle_count, 3] of per-world particle indices, as NumPy int32 arrays (vectorised: no loop per
    element)."""
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    count = len(triangles)
    sides = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)  # [3 · count, 2], side k of t at 3t + k
    edges, side_edge = np.unique(sides, axis=0, return_inverse=True)
    side_edge = side_edge.reshape(-1)
    triangle_edges = side_edge.reshape(count, 3)
    # Each edge (vertex) is reported by the first triangle that holds it.
    edge_owner = np.full(len(edges), -1, dtype=np.int64)
    edge_owner[side_edge[::-1]] = np.repeat(np.arange(count), 3)[::-1]
    vertex_owner = np.full(particle_count, -1, dtype=np.int64)
    vertex_owner[triangles.ravel()[::-1]] = np.repeat(np.arange(count), 3)[::-1]

    # Each triangle's sides that it reports, with their vertices (``owned_sides``: -1 for a side it does not report).
    owned = np.where(edge_owner[triangle_edges] == np.arange(count)[:, None], triangle_edges, -1)
    owned_sides = np.concatenate([owned[:, :, None], edges[triangle_edges]], axis=2)  # [count, 3, 3]

    as32 = lambda a: np.ascontiguousarray(a, dtype=np.int32)  # noqa: E731
    return dict(triangle=as32(triangles), owned_sides=as32(owned_sides), edge=as32(edges),
                edge_owner=as32(edge_owner), vertex_owner=as32(vertex_owner))


def surface_patches(positions: np.ndarray, triangles: np.ndarray, *, cuda: bool) -> tuple[np.ndarray, np.ndarray]:
    """The surface's patches for the cache's check (``kernels/selfcontact_cache.py``): its triangles halved along
    the longest axis of their centres' box at ``positions`` [particle_count, 3] (a median split), level by level,
    into ``kernels/selfcontact.py``'s ``patch_count`` patches (fewer on the CPU than on CUDA). Returns (the triangles'
    indices grouped by patch, each patch's first entry and the end) as int32 arrays [triangle_count], [patches +
    1]. Any grouping is correct; triangles close at rest make the patches' boxes tight."""
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    centres = np.asarray(positions, dtype=np.float64)[triangles].mean(axis=1)
    count = len(triangles)
    order = np.arange(count)
    bounds = [0, count]
    for _ in range(patch_count(count, cuda).bit_length() - 1):
        split = [0]
        for first, last in zip(bounds[:-1], bounds[1:]):
            group = order[first:last]
            points = centres[group]
            axis = int(np.argmax(points.max(axis=0) - points.min(axis=0)))
            half = (last - first) // 2
            order[first:last] = group[np.argsort(points[:, axis], kind="stable")]
            split += [first + half, last]
        bounds = split
    return np.ascontiguousarray(order, dtype=np.int32), np.asarray(bounds, dtype=np.int32)


def smallest_altitude(positions: np.ndarray, triangles: np.ndarray) -> float:
    """The smallest altitude [m] of the triangles (twice the area over the longest side), float64."""
    x = np.asarray(positions, dtype=np.float64)[np.asarray(triangles)]
    doubled_area = np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    longest = np.max(np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2), axis=1)
    return float(np.min(doubled_area / np.maximum(longest, 1e-300))) if len(x) else np.inf


#: Factor by which the pair buffers grow after a frame that dropped pairs or filled one past GROW_ABOVE
#: (``SelfContact.grow``).
PAIR_GROWTH = 2.0
#: A frame whose fullest pair list used more than this share of its slots grows the buffers before the next: a
#: tightening coil doubles its pairs within a few frames, and pairs dropped in a frame lose their repulsion, which
#: leaves the cap alone to hold them (the full-size 1440° twist under RK4 on CUDA dropped 2,276 pairs before its
#: buffers grew after dropping; with this, none).
GROW_ABOVE = 0.75

class SelfContact:
    """Self-collision of a model's triangle surface: the BVHs, the pair buffers, the live values and the counters.

    Attributes:
        triangle_count: triangles of the colliding surface (per world).
        edge_count: its unique edges.
        capacity: slots of each world's pair buffer of the cap (``PAIRS_PER_VERTEX`` per surface vertex); pairs
            beyond are dropped and counted (:meth:`overflow`), and a world whose cap list overflowed keeps its
            free vertices where the step started (``kernels/selfcontact.py``).
        cache_capacity: slots of each world's pair cache (``CACHE_SLOTS`` × ``capacity``); a world whose cache
            overflowed drops the pairs beyond (counted) and runs the cap's swept broad phase.
        params: live values per world, shape [world_count, 3] in the model's precision: thickness τ [m],
            friction μ [-], relaxation γ [-] (``kernels/selfcontact.py`` PARAM_*); write through :meth:`set`.
        counters: int32, shape [world_count, COUNTER_COUNT] (``kernels/selfcontact.py`` COUNT_*): pairs pushed apart,
            vertices capped, pairs dropped on overflow, steps that rebuilt the pair cache, steps whose cap ran the
            swept broad phase, pair-steps beyond the cap, pair-steps pressed below τ/2 and steps whose pair stages ran,
            summed over the steps since the model was made or :meth:`reset`; and the fullest list's fill past
            FILL_WATCHED (a maximum, in 1/FILL_UNITS of its slots).
    """

    def __init__(self, model, triangles: np.ndarray, *, thickness: float, friction: float, relaxation: float):
        self.model = model
        n, worlds, device = model.particle_count, model.world_count, model.device
        topology = surface_topology(triangles, n)
        self.triangle_count = len(topology["triangle"])
        self.edge_count = len(topology["edge"])
        surface = Surface()
        for name, values in topology.items():
            dtype = {"triangle": wp.vec3i, "owned_sides": mat33i, "edge": wp.vec2i}.get(name, wp.int32)
            setattr(surface, name, wp.array(values, dtype=dtype, device=device))
        leaves = worlds * self.triangle_count
        surface.leaf_lower = wp.zeros(leaves, dtype=wp.vec3f, device=device)
        surface.leaf_upper = wp.zeros(leaves, dtype=wp.vec3f, device=device)
        surface.bvh = wp.zeros(worlds, dtype=wp.uint64, device=device)
        self.surface = surface
        # The cache's check reduces each patch's boxes (kernels/selfcontact_cache.py): triangles grouped at rest.
        # Its blocks take chunks of at most PATCH_CHUNK corners of one patch each: the corners of each patch's triangles,
        # once per patch, v where the patch reports v (its owner triangle's patch), -1 - v elsewhere.
        order, bounds = surface_patches(model.particle_q.numpy()[:n], topology["triangle"], cuda=device.is_cuda)
        self.patch_count = len(bounds) - 1
        triangle_patch = np.repeat(np.arange(self.patch_count), np.diff(bounds))[np.argsort(order)]
        keys = np.unique(triangle_patch[:, None] * np.int64(n) + topology["triangle"].astype(np.int64))
        corner_patch, corner = keys // n, keys % n
        reports = triangle_patch[topology["vertex_owner"][corner]] == corner_patch
        corner_bounds = np.searchsorted(corner_patch, np.arange(self.patch_count + 1))
        sizes = np.diff(corner_bounds)
        chunks = -(-sizes // PATCH_CHUNK)
        chunk_patch = np.repeat(np.arange(self.patch_count), chunks)
        first_chunk = np.cumsum(chunks) - chunks
        chunk_start = (corner_bounds[chunk_patch]
                       + PATCH_CHUNK * (np.arange(len(chunk_patch)) - first_chunk[chunk_patch]))
        self.patch_triangles = [order[bounds[k]:bounds[k + 1]] for k in range(self.patch_count)]  # for tests
        if self.patch_count > WATCH_PATCHES:  # (PATCH_LIMIT keeps it far below: a watched pair's tag holds two)
            raise ValueError(f"{self.patch_count} patches: a watched pair's tag holds at most {WATCH_PATCHES}")
        surface.triangle_patch = wp.array(triangle_patch, dtype=wp.int32, device=device)
        # Sized for the most corners and chunks any grouping can have (3 per triangle; ``memory.self_contact_bytes``).
        entries = np.zeros(3 * len(order), dtype=np.int32)
        entries[:len(corner)] = np.where(reports, corner, -1 - corner)
        self.patch_vertex = wp.array(entries, dtype=wp.int32, device=device)
        self.chunk_count = len(chunk_patch)
        most = 3 * len(order) // PATCH_CHUNK + self.patch_count + 1
        self.chunk_patch = wp.array(np.pad(chunk_patch, (0, most - len(chunk_patch))), dtype=wp.int32, device=device)
        chunk_start = np.append(chunk_start, corner_bounds[-1])
        self.chunk_start = wp.array(np.pad(chunk_start, (0, most + 1 - len(chunk_start))), dtype=wp.int32, device=device)
        self.params = wp.zeros((worlds, PARAM_COUNT), dtype=model.scalar, device=device)
        self.set(thickness=thickness, friction=friction, relaxation=relaxation)
        self.corrected = wp.zeros(model.state_size, dtype=model.vec3, device=device)
        # The cap's later passes (kernels/selfcontact.py, cap_place_kernel): each vertex's role in a pass and where a
        # pusher wanted to go, twice (a pass reads one and writes the other).
        self.cap_role = [wp.zeros(model.state_size, dtype=wp.int32, device=device) for _ in range(2)]
        self.cap_desired = [wp.zeros(model.state_size, dtype=model.vec3, device=device) for _ in range(2)]
        self.cap_loop = wp.zeros(LOOP_SIZE, dtype=wp.int32, device=device)  # the levels' loop state (its gate kernel)
        self.counters = wp.zeros((worlds, COUNTER_COUNT), dtype=wp.int32, device=device)
        self._dropped_seen = 0  # pairs dropped when the buffers last grew (``grow``)
        self._outrun_seen = np.zeros(worlds, dtype=np.int64)  # each world's outrun pair-steps at the last ``review``
        # What ``post_review`` copied at a frame's end for ``collect_review`` (host arrays, pinned on CUDA: the copies
        # queue behind the frame), the model's revision then, and the event after the copies (CUDA); None: nothing
        # posted.
        self._review_mirror = None
        self._review_posted = None
        # The pair cache (kernels/selfcontact_cache.py: its anchors, its reach, 0 until built) and the cap's
        # swept list, for the steps that need it; the pass's flags (any rebuild, any fallback, then per world each
        # kind of kernels/selfcontact.py FLAG_*), zeroed at every step's start.
        self.cache_anchor = wp.zeros(model.state_size, dtype=model.vec3, device=device)
        # The cache's watch list (kernels/selfcontact_cache.py): pairs between CACHE_REACH τ and WATCH_REACH τ apart at
        # the anchors, whose distances every step checks; and an empty one for the broad phases that watch nothing.
        self.watch_count = wp.zeros(worlds, dtype=wp.int32, device=device)
        self._no_watch = (wp.zeros(worlds, dtype=wp.int32, device=device),
                          wp.zeros(worlds, dtype=wp.int32, device=device),
                          wp.zeros(worlds, dtype=wp.vec4i, device=device))
        self.cache_reach = wp.zeros(worlds, dtype=model.scalar, device=device)
        # The least distance of a cached pair at the anchors (kernels/selfcontact.py's apart_codec, in units of the τ
        # of the build; 0: none): where the drifts keep them all beyond the repulsion's reach, the stages are skipped.
        self.cache_near = wp.zeros(worlds, dtype=wp.int32, device=device)
        self._no_near = wp.zeros(worlds, dtype=wp.int32, device=device)  # ... for the lists that are not the cache
        # CACHE_REACH τ at each world's last build: every pair outside the cache was that far apart at the anchors.
        self.cache_floor = wp.zeros(worlds, dtype=model.scalar, device=device)
        # The patches' boxes and marks (kernels/selfcontact_cache.py, check_kernel, decide_kernel) share the flags'
        # storage: one memset empties them all.
        flag_count = 2 + FLAG_KINDS * worlds
        boxes = worlds * self.patch_count * PATCH_COLUMNS
        self._step_scratch = wp.zeros(flag_count + boxes + worlds * self.patch_count, dtype=wp.int32, device=device)
        self.flags = self._step_scratch[:flag_count]
        self.patch_box = self._step_scratch[flag_count:flag_count + boxes].reshape((worlds, self.patch_count,
                                                                                     PATCH_COLUMNS))
        # The patches whose watched pairs need their check (decide_kernel marks, watch_kernel reads).
        self.patch_watch = self._step_scratch[flag_count + boxes:].reshape((worlds, self.patch_count))
        self._scan_blocks = wp.zeros((worlds, (n + SCAN_BLOCK - 1) // SCAN_BLOCK), dtype=wp.int32, device=device)
        self.broad_per_primitive = device.is_cuda if BROAD_PER_PRIMITIVE is None else bool(BROAD_PER_PRIMITIVE)
        self._broad_queries = n + self.edge_count if self.broad_per_primitive else self.triangle_count  # per world
        self.broad_split = broad_split(device, worlds * self._broad_queries)
        self.broad_launches = self.broad_launch_forms(
            (device.is_cuda if BROAD_SEPARATE is None else bool(BROAD_SEPARATE)) and self.broad_per_primitive)
        # The stream the first of two broad launches runs on (``_list_pairs``); None: all on the step's stream.
        self._side_stream = (wp.Stream(device) if BROAD_CONCURRENT and device.is_cuda and len(self.broad_launches) > 1
                             else None)
        self.broad_block = (BROAD_BLOCK or model.block_dim) if device.is_cuda else model.block_dim
        self.broad_bounds = launch_bounds(self.broad_block, BROAD_MIN_BLOCKS if device.is_cuda else None)
        self.watch_split = broad_split(device, worlds * n)  # the watched pairs' check likewise, per particle
        self._allocate(max(64, PAIRS_PER_VERTEX * int(np.count_nonzero(topology["vertex_owner"] >= 0))))
        # One BVH per world over the single-precision boxes of its triangles, built at the model's initial
        # positions (its topology follows them: built on coincident points it would degenerate into a list)
        # and refit at every broad phase (the cache's rebuilds, the cap's swept broad phase).
        self._leaves(model.particle_q, model.particle_q, swept=False, refit=False)
        T = self.triangle_count
        self.bvhs = [wp.Bvh(surface.leaf_lower[w * T:(w + 1) * T], surface.leaf_upper[w * T:(w + 1) * T])
                     for w in range(worlds)]
        surface.bvh = wp.array(np.array([b.id for b in self.bvhs], dtype=np.uint64), dtype=wp.uint64, device=device)
        if device.is_cuda:
            self._load_modules()

    def _load_modules(self) -> None:
        """Load every kernel of the pass, its conditional branches' included, so that a frame's capture never
        loads one (a branch may not run in the stepper's warm-up step)."""
        model = self.model
        scalar = model.scalar
        for kernel in (leaf_kernel(scalar, False), leaf_kernel(scalar, True)):
            kernel.module.load(model.device)  # launched with Warp's default block size
        for kernel in scan_kernels():
            kernel.module.load(model.device, SCAN_THREADS)
        check_kernel(scalar).module.load(model.device, PATCH_THREADS)
        for swept in (False, True):
            for primitives, _, _ in self.broad_launches:
                broad_kernel(scalar, swept, self.broad_per_primitive, primitives,
                             self.broad_bounds).module.load(model.device, self.broad_block)
        flat = [reset_kernel(), fill_kernel(), decide_kernel(scalar), watch_kernel(scalar), anchor_kernel(scalar),
                repel_pairs_kernel(scalar),
                repel_gather_kernel(scalar), cap_bounds_kernel(scalar), cap_gather_kernel(scalar),
                cap_place_kernel(scalar), cap_mark_kernel(scalar), cap_check_kernel(scalar)]
        for kernel in flat:
            kernel.module.load(model.device, model.block_dim)

    def broad_launch_forms(self, separate: bool) -> list[tuple[str, int, int]]:
        """The broad phase's launches, each (primitives, queries per world, threads per query): with ``separate`` (one
        query per primitive only) the vertices' and the edges' apart, else one launch over all its queries."""
        model = self.model
        if not separate:
            return [("both", self._broad_queries, self.broad_split)]
        return [(kind, count, broad_split(model.device, model.world_count * count))
                for kind, count in (("vertices", model.particle_count), ("edges", self.edge_count))]

    def _allocate(self, capacity: int) -> None:
        """The cap's list with ``capacity`` slots per world and the cache with CACHE_SLOTS times as many (emptied:
        the next step rebuilds). ``memory.self_contact_bytes`` counts what this class allocates (change both)."""
        model = self.model
        self.capacity = capacity
        self.cache_capacity = CACHE_SLOTS * capacity
        self.cache, self.cache_bound = self._pair_buffers(self.cache_capacity, 1)
        self.watch_tag = wp.zeros(model.world_count * capacity, dtype=wp.int32, device=model.device)
        self.watch_vertex = wp.zeros(model.world_count * capacity, dtype=wp.vec4i, device=model.device)
        self.cap_pairs, self.pair_distance = self._pair_buffers(capacity, 1)
        slots = model.world_count * self.cache_capacity
        self.pair_correction = wp.zeros(4 * slots, dtype=model.vec3, device=model.device)
        self.pair_weight = wp.zeros(4 * slots, dtype=model.scalar, device=model.device)
        self.cache_reach.zero_()
        self.cache_floor.zero_()
        self.cache_near.zero_()

    def _pair_buffers(self, capacity: int, lists: int):
        """``lists`` pair buffers of ``capacity`` slots per world sharing their storage but their counts, and
        the pairs' distances."""
        model = self.model
        device = model.device
        slots = model.world_count * capacity
        shared = dict(
            key=wp.zeros(slots, dtype=wp.int64, device=device),
            vertex=wp.zeros(slots, dtype=wp.vec4i, device=device),
            vertex_count=wp.zeros(model.particle_dim + 1, dtype=wp.int32, device=device),
            vertex_start=wp.zeros(model.particle_dim + 1, dtype=wp.int32, device=device),
            vertex_cursor=wp.zeros(model.particle_dim, dtype=wp.int32, device=device),
            entry=wp.zeros(4 * slots, dtype=wp.int32, device=device),
        )
        buffers = []
        for _ in range(lists):
            pairs = Pairs()
            pairs.count = wp.zeros(model.world_count, dtype=wp.int32, device=device)
            for name, array in shared.items():
                setattr(pairs, name, array)
            buffers.append(pairs)
        return (*buffers, wp.zeros(slots, dtype=model.scalar, device=device))

    def set(self, *, thickness: float | None = None, friction: float | None = None,
            relaxation: float | None = None, world: int | None = None) -> None:
        """Write live values (in every world, or in ``world``): read by the next step, nothing compiles and a
        captured graph stays valid.

        Args:
            thickness: τ [m], > 0: the separation the repulsion keeps between the surface's layers.
            friction: μ [-], ≥ 0: Coulomb friction between layers in contact.
            relaxation: γ [-] in (0, 1/2): each vertex moves at most γ times its distance to the nearest
                primitive per step.
        """
        current = self.params.numpy()
        rows = range(self.model.world_count) if world is None else [int(world)]
        for row in rows:
            old = current[row]
            tau, mu, gamma = check_settings(
                old[PARAM_THICKNESS] if thickness is None else thickness,
                old[PARAM_FRICTION] if friction is None else friction,
                old[PARAM_RELAXATION] if relaxation is None else relaxation,
            )
            current[row, [PARAM_THICKNESS, PARAM_FRICTION, PARAM_RELAXATION]] = (tau, mu, gamma)
        self.params.assign(current)
        self.model.input_version += 1

    @property
    def thickness(self) -> float:
        """World 0's thickness τ [m]."""
        return float(self.params.numpy()[0, PARAM_THICKNESS])

    def counts(self) -> dict[str, np.ndarray]:
        """Per world, summed since the start or :meth:`reset`, from one read of the device: ``pairs`` pushed apart by
        the repulsion, ``capped`` vertices, and the pairs ``overflow`` dropped, ``outrun`` and ``squeezed`` counted
        (:meth:`overflow`, :meth:`outrun`, :meth:`squeezed`), in this order (int64 arrays [world_count])."""
        counters = self.counters.numpy().astype(np.int64)
        return {"pairs": counters[:, COUNT_PAIRS], "capped": counters[:, COUNT_CAPPED],
                "overflow": counters[:, COUNT_OVERFLOW], "outrun": counters[:, COUNT_OUTRUN],
                "squeezed": counters[:, COUNT_SQUEEZED]}

    def outrun(self) -> np.ndarray:
        """Pairs the cap could not hold apart (beyond it: a pin closing in on a free side that cannot give way along
        its repelled step, or two pinned sides closing in; such a pair may cross), per world, summed over steps since
        the start or :meth:`reset` (int64 [world_count]; reads the device). Zero in a run the no-crossing guarantee
        covers."""
        return self.counts()["outrun"]

    def squeezed(self) -> np.ndarray:
        """Pair-steps the cap held apart but pressed below τ/2 along their separating direction (a pin pressing free
        layers that have no room to give way, themselves held by pins: the pair may end closer than τ/2 without
        crossing), per world, summed over steps since the start or :meth:`reset` (int64 [world_count]; reads the
        device). A pair not counted here or in :meth:`outrun` that started a step at least τ/2 apart ends it so."""
        return self.counts()["squeezed"]

    def overflow(self) -> np.ndarray:
        """Pairs dropped because a world's pair buffer was full, per world, summed since the start or
        :meth:`reset` (int64 [world_count]; reads the device). Zero in a healthy run."""
        return self.counts()["overflow"]

    def listed(self) -> dict[str, np.ndarray]:
        """Pairs listed per world: ``cache`` (closer than CACHE_REACH τ at the cache's last rebuild) and ``cap`` (the
        cap's swept broad phase, at its last run); int64 arrays [world_count], reads the device."""
        return {"cache": self.cache.count.numpy().astype(np.int64),
                "cap": self.cap_pairs.count.numpy().astype(np.int64)}

    def cache_counts(self) -> dict[str, np.ndarray]:
        """Per world, summed since the start or :meth:`reset`: steps that ``rebuilt`` the pair cache, steps whose
        cap ran its swept broad phase (``fallbacks``) and steps whose pair stages ran (``stages``: the repulsion and
        the cap, which a step whose start has no cached pair within the repulsion's reach and no vertex stepping too
        far skips); int64 arrays [world_count], reads the device."""
        counters = self.counters.numpy().astype(np.int64)
        return {"rebuilds": counters[:, COUNT_REBUILDS], "fallbacks": counters[:, COUNT_FALLBACKS],
                "stages": counters[:, COUNT_STAGES]}

    def reset(self) -> None:
        """Zero the counters."""
        self.counters.zero_()
        self._dropped_seen = 0
        self._outrun_seen[:] = 0

    def review(self) -> np.ndarray:
        """After a frame, from one read of the counters and the lists' counts: :meth:`grow` where pairs were dropped
        or a list filled past GROW_ABOVE of its slots (during the frame, or as it stands), and each world's pair-steps
        beyond the cap (:meth:`outrun`) since the last review or :meth:`reset` (int64 [world_count]). Waits for the
        device; :meth:`post_review` and :meth:`collect_review` do the same a frame later without waiting."""
        revision = self.model.revision
        earlier = self.collect_review()  # one posted before: its frame first (its outrun counted in the total)
        # (where that one grew the buffers, what the counters hold now ran on the old ones: no growth again for it)
        new = self._judge_review(self.counters.numpy(), self.cache.count.numpy(), self.cap_pairs.count.numpy(),
                                 grow=revision == self.model.revision)
        return new if earlier is None else earlier + new

    def post_review(self, revision: int | None = None) -> None:
        """Queue, after the frame's work, the copy of what :meth:`review` reads, for :meth:`collect_review` at the
        next frame: the host then reads a frame the device finished while it runs the next one (a review at once
        waits for the device and leaves it idle while the host launches the next frame: 9-16 µs a substep of the
        draped cloth at 64²-256² on an H200, ``bench/results/selfcontact.md``). ``revision``: the model's revision
        the frame ran with (default: the current one)."""
        device = self.model.device
        if self._review_mirror is None:
            pinned = device.is_cuda
            self._review_mirror = (
                wp.empty(self.counters.shape, dtype=wp.int32, device="cpu", pinned=pinned),
                wp.empty(self.cache.count.shape, dtype=wp.int32, device="cpu", pinned=pinned),
                wp.empty(self.cap_pairs.count.shape, dtype=wp.int32, device="cpu", pinned=pinned))
        for mirror, source in zip(self._review_mirror, (self.counters, self.cache.count, self.cap_pairs.count)):
            wp.copy(mirror, source)
        event = device.stream.record_event() if device.is_cuda else None
        self._review_posted = (self.model.revision if revision is None else revision, event)

    def collect_review(self) -> np.ndarray | None:
        """:meth:`review` of the frame :meth:`post_review` followed (waiting for its copies, done by the time the next
        frame runs), or ``None`` where nothing is posted. A growth it asks for applies from the frame after the one
        under way; none where the buffers changed since the post (that frame ran on the old ones)."""
        if self._review_posted is None:
            return None
        revision, event = self._review_posted
        self._review_posted = None
        if event is not None:
            wp.synchronize_event(event)
        counters, cache_count, cap_count = (mirror.numpy() for mirror in self._review_mirror)
        return self._judge_review(counters, cache_count, cap_count, grow=revision == self.model.revision)

    def forget_review(self) -> None:
        """Drop a posted review and count the pins' outrun so far as seen (reads the device): the run it belongs to is
        left behind (a reset, a restored checkpoint, a stop), so that no later review reports it."""
        self._review_posted = None
        self._outrun_seen = self.counters.numpy()[:, COUNT_OUTRUN].astype(np.int64)

    def _judge_review(self, counters: np.ndarray, cache_count: np.ndarray, cap_count: np.ndarray, *,
                      grow: bool) -> np.ndarray:
        """:meth:`review`'s decisions from the counters and the lists' counts read after a frame."""
        counters = counters.astype(np.int64)
        # The lists as they stood (a list built before a capture's replay has no count of its fill).
        fill = max(float(counters[:, COUNT_FILL].max(initial=0)) / FILL_UNITS,
                   float(cache_count.max(initial=0)) / self.cache_capacity,
                   float(cap_count.max(initial=0)) / self.capacity)
        dropped = int(counters[:, COUNT_OVERFLOW].sum())
        if grow:
            self.grow(dropped=dropped, fill=fill)
        else:  # a frame on buffers already replaced: its drops are not the new buffers' (no growth for them later)
            self._dropped_seen = max(self._dropped_seen, dropped)
        outrun = counters[:, COUNT_OUTRUN]
        new, self._outrun_seen = outrun - self._outrun_seen, outrun
        return new

    def grow(self, *, dropped: int | None = None, fill: float = 0.0) -> bool:
        """After a frame in which a world's pair buffer overflowed (pairs dropped since the last call: reads the
        device) or, ``fill``, the fullest list used more than GROW_ABOVE of its slots, give every world PAIR_GROWTH
        times the slots (emptied: the next step rebuilds its cache; the fill's record cleared) and bump the model's
        revision, so that the stepper re-captures. The frame that dropped pairs kept the no-crossing
        guarantee (a world whose list overflowed runs the cap's swept broad phase) but not all of their repulsion;
        a tightly packed surface (a cloth coiled by a 1440° twist) otherwise drops them frame after frame. The
        counters keep the pairs dropped (:meth:`overflow`); ``dropped``: their sum over the worlds, where the caller
        has read it. Returns whether the buffers grew."""
        dropped = int(self.overflow().sum()) if dropped is None else dropped
        if dropped <= self._dropped_seen and fill <= GROW_ABOVE:
            return False
        self._dropped_seen = max(dropped, self._dropped_seen)
        self._allocate(math.ceil(PAIR_GROWTH * self.capacity))
        counters = self.counters.numpy()
        counters[:, COUNT_FILL] = 0  # the new lists' fill starts afresh
        self.counters.assign(counters)
        self.model.revision += 1
        return True

    def history(self) -> list:
        """The device arrays one step leaves to the next: the counters."""
        return [self.counters]

    @property
    def capturable(self) -> bool:
        """Whether a step with self-collision can be captured in a graph: on every device (a CPU graph records the
        BVH's refit and replays it against the current boxes, Warp ≥ 1.16: ``wp.Bvh.refit``'s note; its conditional
        nodes, ``capture_if``, too)."""
        return True

    def _leaves(self, start: wp.array, end: wp.array, *, swept: bool, refit: bool = True) -> None:
        """Write the triangles' boxes (at ``start``, or swept from ``start`` to ``end``) and refit the BVHs."""
        model = self.model
        flat_launch(leaf_kernel(model.scalar, swept),
                    inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, self.params, self.flags,
                            start, end, self.surface],
                    dim=model.world_count * self.triangle_count, device=model.device)
        if refit:
            for bvh in self.bvhs:
                bvh.refit()

    def _list_pairs(self, pairs, pair_distance: wp.array, start: wp.array, end: wp.array, *, swept: bool,
                    reach_factor: float, reach_add: float, counters: wp.array, active: wp.array,
                    watch: bool = False) -> None:
        """The broad phase of the worlds ``active`` names into ``pairs`` and ``pair_distance``, then the CSR of
        its entries (device work only, fixed sizes, no allocation: capturable, also in a conditional node);
        the other worlds' pairs stay as they were. With ``watch`` (the cache's build) also its watch list and the
        least distance of its pairs (``cache_near``)."""
        model = self.model
        watch_lists = (self.watch_count, self.watch_tag, self.watch_vertex) if watch else self._no_watch
        near = self.cache_near if watch else self._no_near
        flat_launch(reset_kernel(), inputs=[model.particle_count, active], outputs=[pairs, watch_lists[0], near],
                    dim=model.particle_dim,
                    block_dim=model.block_dim, device=model.device)
        self._leaves(start, end, swept=swept)
        args = dict(
            particle_count=model.particle_count,
            particle_flags=model.particle_flags,
            particle_inv_mass=model.particle_inv_mass,
            world_enabled=active,
            surface=self.surface,
            params=self.params,
            flags=self.flags,
            reach_factor=model.scalar(reach_factor),
            reach_add=model.scalar(reach_add),
            watch_factor=model.scalar(WATCH_REACH if watch else 0.0),
            split=self.broad_split,
            particle_q_start=start,
            particle_q_end=end,
        )
        outputs = dict(pairs_out=pairs, pair_distance_out=pair_distance, counters_out=counters,
                       watch_count_out=watch_lists[0], watch_tag_out=watch_lists[1], watch_vertex_out=watch_lists[2],
                       near_out=near)
        side = self._side_stream
        for k, (primitives, queries, split) in enumerate(self.broad_launches):
            args["split"] = split
            # With a side stream, the first launch forks onto it after the step's work so far, and the step's stream
            # waits for it after the last: the launches run side by side (atomic slots: the same pairs either way).
            with wp.ScopedStream(side if k == 0 else None, sync_enter=True):
                flat_launch(broad_kernel(model.scalar, swept, self.broad_per_primitive, primitives,
                                         self.broad_bounds),
                            inputs=list(args.values()), outputs=list(outputs.values()),
                            dim=model.world_count * queries * split, block_dim=self.broad_block, device=model.device)
        if side is not None:
            model.device.stream.wait_stream(side)
        tile_sums, tile_offsets, tile_prefixes = scan_kernels()
        tiles = self._scan_blocks
        worlds, n = model.world_count, model.particle_count
        capacity = pairs.key.shape[0] // worlds
        counts = pairs.vertex_count[:worlds * n].reshape((worlds, n))
        starts = pairs.vertex_start[:worlds * n].reshape((worlds, n))
        scan = dict(block_dim=SCAN_THREADS, device=model.device)
        wp.launch_tiled(tile_sums, dim=tiles.shape, inputs=[counts], outputs=[tiles], **scan)
        wp.launch_tiled(tile_offsets, dim=(worlds,), inputs=[4 * capacity], outputs=[tiles], **scan)
        wp.launch_tiled(tile_prefixes, dim=tiles.shape, inputs=[counts, tiles], outputs=[starts], **scan)
        flat_launch(fill_kernel(), inputs=[model.particle_count, active, pairs], dim=model.particle_dim,
                    block_dim=model.block_dim, device=model.device)

    def _unconditional(self) -> bool:
        """Whether a CUDA capture is under way on a device without conditional graph nodes (``_loop``, ``_branch``
        then record their bodies unconditionally)."""
        device = self.model.device
        return device.is_cuda and device.is_capturing and not getattr(wp, "is_conditional_graph_supported", bool)()

    def _loop(self, condition: wp.array, body, *, rounds: int) -> None:
        """``body`` while ``condition`` holds (a conditional graph node where captured, ``wp.capture_while``); where a
        CUDA capture lacks conditional nodes, ``rounds`` times unconditionally (the body must then be harmless when
        the condition is false)."""
        if self._unconditional():
            for _ in range(rounds):
                body()
        else:
            wp.capture_while(condition, body)

    def _branch(self, condition: wp.array, body, **kwargs) -> None:
        """``body(**kwargs)`` when ``condition[0]`` is set: a conditional node in a CUDA capture, a host test
        otherwise. Where the device has no conditional nodes it runs unconditionally inside a capture (its
        kernels skip the worlds not flagged: the same result, at more cost)."""
        if self._unconditional():
            body(**kwargs)
        else:
            wp.capture_if(condition, on_true=body, **kwargs)

    def _rebuild(self, start: wp.array) -> None:
        """The cache of the worlds flagged for a rebuild, at ``start`` (the step's start)."""
        model = self.model
        worlds = model.world_count
        self._list_pairs(self.cache, self.cache_bound, start, start, swept=False, reach_factor=CACHE_REACH,
                         reach_add=0.0, counters=self.counters, active=self.flags[2:2 + worlds], watch=True)
        flat_launch(anchor_kernel(model.scalar),
                    inputs=[model.particle_count, self.params, self.cache, self.cache_near, self.watch_count,
                            self.capacity, start],
                    outputs=[self.flags, self.cache_reach, self.cache_floor, self.cache_anchor, self.counters],
                    dim=model.particle_dim,
                    block_dim=model.block_dim, device=model.device)

    def _fallback(self, start: wp.array, end: wp.array) -> None:
        """The cap's swept broad phase (start → the repelled ``end``) of the worlds flagged for it."""
        worlds = self.model.world_count
        self._list_pairs(self.cap_pairs, self.pair_distance, start, end, swept=True, reach_factor=0.0,
                         reach_add=0.0, counters=self.counters, active=self.flags[2 + worlds:2 + 2 * worlds])

    def _check(self, start: wp.array, particle_q: wp.array, *, tiled: bool) -> None:
        """The cache's check (``kernels/selfcontact_cache.py``) into the zeroed flags and patch boxes: one block per chunk
        with block-wide maxima (``tiled``, on CUDA), or one thread per chunk (on the CPU, where a block is one thread)."""
        model = self.model
        check = dict(inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, model.world_enabled,
                             self.surface.triangle, self.patch_vertex, self.chunk_patch, self.chunk_start, self.params,
                             self.cache_anchor, start, particle_q],
                     outputs=[self.patch_box, self.flags], dim=(model.world_count, self.chunk_count), device=model.device)
        if tiled:
            wp.launch_tiled(check_kernel(model.scalar), block_dim=PATCH_THREADS, **check)
        else:
            wp.launch(check_kernel(model.scalar, False), **check)

    def _flag(self, start: wp.array, particle_q: wp.array) -> None:
        """The step's flags: the cache's check, its decisions and the watched and cached pairs' checks."""
        self._step_scratch.zero_()  # the flags and the patches' boxes
        self._check(start, particle_q, tiled=self.model.device.is_cuda)
        self._decide()
        self._watch(start)

    def _prepare(self, start: wp.array, particle_q: wp.array) -> None:
        """The step's flags, then the cache's rebuild where a world needs one."""
        self._flag(start, particle_q)
        self._branch(self.flags[0:1], self._rebuild, start=start)

    def _decide(self) -> None:
        """The cache's decisions per pair of patches, after its check."""
        model = self.model
        flat_launch(decide_kernel(model.scalar),
                    inputs=[model.world_enabled, self.params, self.cache_reach, self.cache_floor, self.cache.count,
                            self.cache_capacity, self.cache_near, self.patch_box],
                    outputs=[self.flags, self.patch_watch], dim=model.world_count * self.patch_count ** 2, block_dim=model.block_dim,
                    device=model.device)

    def _watch(self, start: wp.array) -> None:
        """The watched and the cached pairs' checks where the decisions asked for them."""
        model = self.model
        flat_launch(watch_kernel(model.scalar),
                    inputs=[model.particle_count, model.world_enabled, self.surface, self.params, self.watch_count,
                            self.watch_tag, self.watch_vertex, self.cache, self.patch_watch,
                            self.watch_split, start],
                    outputs=[self.flags], dim=model.particle_dim * self.watch_split, block_dim=model.block_dim,
                    device=model.device)

    def _first_entry(self, kind: int) -> wp.array:
        """The first entry of the flag ``kind`` (FLAG_*), as a one-element array."""
        slot = 2 + kind * self.model.world_count
        return self.flags[slot:slot + 1]

    @property
    def _work(self) -> wp.array:
        """The flag of the pair stages (FLAG_WORK's first entry), as a one-element array."""
        return self._first_entry(FLAG_WORK)

    def _repel_stage(self, start: wp.array, particle_q: wp.array) -> None:
        """The repulsion over the cached pairs and its gather into ``self.corrected``."""
        model = self.model
        per_particle = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        flat_launch(repel_pairs_kernel(model.scalar),
                    inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, model.world_enabled,
                            self.surface, self.params, self.cache, start, particle_q],
                    outputs=[self.pair_correction, self.pair_weight, self.counters], **per_particle)
        flat_launch(repel_gather_kernel(model.scalar),
                    inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, model.world_enabled,
                            self.surface, self.params, self.pair_correction, self.pair_weight, start, particle_q],
                    outputs=[self.cache, self.flags, self.corrected], **per_particle)

    def _cap_stage(self, start: wp.array, particle_q: wp.array, state_out, dt: float) -> None:
        """The cap's bounds over the cached pairs and its gather into ``state_out``."""
        model = self.model
        per_particle = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        flat_launch(cap_bounds_kernel(model.scalar),
                    inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, model.world_enabled,
                            self.surface, self.params, self.cache, self.flags, start, particle_q],
                    outputs=[self.cache_bound, self.counters], **per_particle)
        flat_launch(cap_gather_kernel(model.scalar),
                    inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, model.world_enabled,
                            self.surface, self.params, self.cache, self.cache_bound, self.cap_pairs,
                            self.pair_distance, self.flags, start, particle_q, model.scalar(dt)],
                    outputs=[state_out.particle_q, state_out.particle_qd, self.cap_role[0], self.counters],
                    **per_particle)
        # The later passes: the jammed vertices placed anew; then, level after level while one stays jammed (at most
        # CAP_LEVELS), the vertices across a kept pair from those still jammed make room, and the jammed are placed
        # against where they went, in PUSHER_COLOURS sub-passes by depth (colour: depth mod PUSHER_COLOURS, the
        # highest first): 2 + PUSHER_COLOURS launches a level, LEVELS_PER_ROUND levels a round of the loop, and a
        # one-thread gate after each round that reads whether the last level left a pusher.
        role, desired = self.cap_role, self.cap_desired
        lists = [model.particle_count, model.particle_flags, model.particle_inv_mass, self.surface, self.params,
                 self.cache, self.cache_bound, self.cap_pairs, self.flags]
        tail = [start, particle_q, model.scalar(dt)]

        def place(mover_role, clear, into):
            flat_launch(cap_place_kernel(model.scalar),
                        inputs=lists + [mover_role, clear, into, role[1 - into], desired[1 - into]] + tail,
                        outputs=[state_out.particle_q, state_out.particle_qd, role[into], desired[into], self.cap_loop],
                        **per_particle)

        def gate(start_loop: int):
            flat_launch(cap_loop_gate_kernel(), inputs=[CAP_LEVELS, start_loop], outputs=[self.cap_loop], dim=1,
                        device=model.device)

        def level_round():
            for into in range(LEVELS_PER_ROUND):
                flat_launch(cap_mark_kernel(model.scalar),
                            inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, self.surface,
                                    self.cache, self.cache_bound, self.cap_pairs, self.flags],
                            outputs=[role[1 - into]], **per_particle)
                place(ROLE_MOVER, 1, into)  # the vertices across a kept pair from a pusher make room
                for colour in reversed(range(PUSHER_COLOURS)):  # the pushers, against where they went, by colour
                    place(ROLE_PUSHER + colour, 0, into)
            gate(0)

        place(ROLE_MOVER, 1, 1)  # the jammed vertices (role[0], from the gather)
        gate(1)
        self._loop(self.cap_loop[LOOP_CONDITION:LOOP_CONDITION + 1], level_round,
                   rounds=-(-CAP_LEVELS_UNCONDITIONAL // LEVELS_PER_ROUND))
        flat_launch(cap_check_kernel(model.scalar),
                    inputs=[model.particle_count, model.world_enabled, self.surface, self.params, self.cache,
                            self.cache_bound, self.cap_pairs, self.flags, start, state_out.particle_q],
                    outputs=[self.counters], **per_particle)

    def repel(self, state_in, particle_q: wp.array) -> wp.array:
        """The repulsion stage alone (with the cache's check and, where needed, its rebuild): ``particle_q`` (the
        integrator's result from ``state_in``) repelled, into ``self.corrected`` (returned)."""
        self._prepare(state_in.particle_q, particle_q)
        self._repel_stage(state_in.particle_q, particle_q)
        return self.corrected

    def cap(self, state_in, particle_q: wp.array, state_out, dt: float) -> None:
        """The cap stage alone, after :meth:`repel` (it reads the flags that left): ``particle_q`` (the repelled
        positions) capped into ``state_out``'s positions and, where they changed, velocities."""
        start = state_in.particle_q
        self._branch(self.flags[1:2], self._fallback, start=start, end=particle_q)
        self._cap_stage(start, particle_q, state_out, dt)

    def _near_pairs(self, state, reach: float):
        """The pairs within ``reach`` [m] at ``state`` in a buffer of their own, grown until none overflows
        (host reads: for audits and tests, never inside a step). Returns (pairs, distances)."""
        model = self.model
        capacity = self.capacity
        everywhere = wp.ones(model.world_count, dtype=wp.int32, device=model.device)
        while True:
            pairs, distance = self._pair_buffers(capacity, 1)
            scratch = wp.zeros((model.world_count, COUNTER_COUNT), dtype=wp.int32, device=model.device)
            self._list_pairs(pairs, distance, state.particle_q, state.particle_q, swept=False, reach_factor=0.0,
                             reach_add=reach, counters=scratch, active=everywhere)
            found = int(pairs.count.numpy().max())
            if found <= capacity:
                return pairs, distance
            capacity = found

    def proximity(self, state, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """The device's broad phase at ``state``, for audits: per particle of every world, the distance [m] to
        the nearest vertex–triangle or edge–edge pair it belongs to within ``reach`` [m] (``reach`` when
        none) and how many such pairs there are (-1 off the surface); NumPy arrays
        [world_count · particle_count]."""
        model = self.model
        pairs, distance = self._near_pairs(state, reach)
        nearest = wp.empty(model.state_size, dtype=model.scalar, device=model.device)
        count = wp.empty(model.state_size, dtype=wp.int32, device=model.device)
        flat_launch(proximity_kernel(model.scalar),
                    inputs=[model.particle_count, self.surface, pairs, distance, model.scalar(reach)],
                    outputs=[nearest, count], dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        return nearest.numpy().astype(np.float64), count.numpy()

    def pairs(self, state, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """The broad phase's pair list at ``state`` within ``reach`` [m], for tests: (vt [k, 3] rows (world,
        vertex, triangle), ee [m, 3] rows (world, edge, edge), first edge < second), each in the order the
        device stored them (an integer atomic's order)."""
        model = self.model
        pairs, _ = self._near_pairs(state, reach)
        count = pairs.count.numpy()
        capacity = pairs.key.shape[0] // model.world_count
        keys = pairs.key.numpy().reshape(model.world_count, capacity)
        n, T, E = model.particle_count, self.triangle_count, self.edge_count
        vt, ee = [], []
        for world in range(model.world_count):
            k = keys[world, :count[world]]
            near = k < n * T
            vt.append(np.stack([np.full(near.sum(), world), k[near] // T, k[near] % T], axis=1))
            rest = k[~near] - n * T
            ee.append(np.stack([np.full(len(rest), world), rest // E, rest % E], axis=1))
        return np.concatenate(vt).astype(np.int64), np.concatenate(ee).astype(np.int64)

    def __call__(self, state_in, state_out, dt: float) -> None:
        """Make ``state_out`` (the integrator's result from ``state_in``) free of self-intersections: repel, then
        cap (device work only, fixed launch sizes: capturable)."""
        start, particle_q = state_in.particle_q, state_out.particle_q
        self._flag(start, particle_q)
        # One conditional node where no world rebuilds and none runs the stages (most steps), the two inside it.
        self._branch(self._first_entry(FLAG_BUSY), self._busy, start=start, particle_q=particle_q,
                     state_out=state_out, dt=dt)

    def _busy(self, start: wp.array, particle_q: wp.array, state_out, dt: float) -> None:
        """The rebuild where a world needs one, then the stages where a world has cached pairs or a vertex steps too
        far for the cache; elsewhere they would leave state_out as it is (kernels/selfcontact_cache.py,
        decide_kernel)."""
        self._branch(self.flags[0:1], self._rebuild, start=start)
        self._branch(self._work, self._stages, start=start, particle_q=particle_q, state_out=state_out, dt=dt)

    def _stages(self, start: wp.array, particle_q: wp.array, state_out, dt: float) -> None:
        """Both stages after the flags: the repulsion, the cap's swept broad phase where flagged (a conditional node
        within this one's), the cap."""
        self._repel_stage(start, particle_q)
        self._branch(self.flags[1:2], self._fallback, start=start, end=self.corrected)
        self._cap_stage(start, self.corrected, state_out, dt)


def make_self_contact(model, triangles: np.ndarray, positions: np.ndarray, settings: dict) -> SelfContact:
    """The model's :class:`SelfContact` for ``triangles`` (per-world particle indices) at rest ``positions``,
    or a ConfigError when the thickness does not fit the mesh."""
    thickness, friction, relaxation = check_settings(settings["thickness"], settings["friction"],
                                                     settings["relaxation"])
    if len(triangles) == 0:
        raise ConfigError("self-collision needs triangles: add a cloth or a mesh before add_self_collision")
    altitude = smallest_altitude(positions, triangles)
    if thickness >= MAX_THICKNESS_SHARE * altitude:
        raise ConfigError(
            f"self-collision thickness {thickness:.4g} m is too large for the mesh: its smallest triangle altitude "
            f"is {altitude:.4g} m, so neighbouring elements would repel at rest; use a thickness below "
            f"{MAX_THICKNESS_SHARE * altitude:.4g} m or a coarser mesh"
        )
    return SelfContact(model, triangles, thickness=thickness, friction=friction, relaxation=relaxation)
