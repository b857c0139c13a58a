"""Float64 audits of a triangle surface on the host: does anything pass through anything?

Per state (:func:`audit_frame`): segment–triangle intersections between an edge and a triangle that share no
vertex (zero expected; two triangles that intersect always have an edge of one through the other) and the
vertex–triangle and edge–edge distances between elements that share no vertex. Per substep
(:func:`audit_motion`, :meth:`SurfaceAudit.motion`): continuous collision detection over the straight path of
every vertex from one state to the next, each vertex–triangle and edge–edge pair sharing no vertex decided by IPC
Toolkit's Tight-Inclusion CCD in float64 (certified: it misses no touch). :class:`SurfaceAudit` prepares a
surface once for many substeps; :class:`SubstepAudit` audits every substep of a run (``warpspring run
--audit-substeps``): a :class:`~warpspring.core.stepper.StepHook` keeps the substeps' positions on the device,
a :class:`~warpspring.core.simulator.FrameHook` audits them after each frame.

Candidates of the per-state audit come from SciPy's k-d tree over bounding spheres (exact pruning: a pair is
skipped only when its bounding spheres are farther apart than the distance of interest), those of the
continuous one from IPC Toolkit's broad phase over swept boxes; :func:`brute_pairs` is the all-pairs reference
the device's broad phase is tested against. ``warpspring audit OUT.usdc`` runs the per-state audit on every
frame of a written USD file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..core import memory
from ..core.mesh_files import check_usd_layers
from ..core.simulator import FrameHook
from ..core.stepper import StepHook
from ..errors import ConfigError


def surface_edges(triangles: np.ndarray) -> np.ndarray:
    """The unique edges [edge_count, 2] (sorted ends) of ``triangles`` [triangle_count, 3]."""
    sides = np.sort(np.asarray(triangles)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(sides, axis=0)


def point_segment_distance(p, a, b) -> np.ndarray:
    """|p - closest point of segment ab| for arrays of points [..., 3] (float64)."""
    ab = b - a
    denom = np.einsum("...i,...i", ab, ab)
    t = np.clip(np.einsum("...i,...i", p - a, ab) / np.where(denom > 0, denom, 1.0), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def vertex_triangle_distance(p, a, b, c) -> np.ndarray:
    """Distance from points p to triangles abc, elementwise over [..., 3] arrays (float64): the distance to
    the plane where the projection falls inside, else the nearest of the three sides."""
    n = np.cross(b - a, c - a)
    area2 = np.einsum("...i,...i", n, n)
    safe = np.where(area2 > 0, area2, 1.0)
    # Barycentric coordinates of the projection.
    u = np.einsum("...i,...i", np.cross(c - b, p - b), n) / safe
    v = np.einsum("...i,...i", np.cross(a - c, p - c), n) / safe
    w = 1.0 - u - v
    inside = (area2 > 0) & (u >= 0) & (v >= 0) & (w >= 0)
    plane = np.abs(np.einsum("...i,...i", p - a, n)) / np.sqrt(safe)
    sides = np.minimum(np.minimum(point_segment_distance(p, a, b), point_segment_distance(p, b, c)),
                       point_segment_distance(p, c, a))
    return np.where(inside, plane, sides)


def edge_edge_distance(p1, q1, p2, q2) -> np.ndarray:
    """Distance between segments p1q1 and p2q2, elementwise (float64; Ericson 5.1.9, vectorised). The
    minimum over the interior critical point (where it lies inside both segments) and the four
    endpoint-to-segment distances is exact for any pair, parallel ones included."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a = np.einsum("...i,...i", d1, d1)
    e = np.einsum("...i,...i", d2, d2)
    b = np.einsum("...i,...i", d1, d2)
    c = np.einsum("...i,...i", d1, r)
    f = np.einsum("...i,...i", d2, r)
    denom = a * e - b * b
    ok = denom > 1e-14 * a * e
    safe = np.where(ok, denom, 1.0)
    s = (b * f - c * e) / safe
    t = (a * f - b * c) / safe
    interior = ok & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    gap = np.linalg.norm((p1 + s[..., None] * d1) - (p2 + t[..., None] * d2), axis=-1)
    ends = np.minimum(np.minimum(point_segment_distance(p1, p2, q2), point_segment_distance(q1, p2, q2)),
                      np.minimum(point_segment_distance(p2, p1, q1), point_segment_distance(q2, p1, q1)))
    return np.where(interior, np.minimum(gap, ends), ends)


def _orient(a, b, c, d) -> np.ndarray:
    """Six times the signed volume of tetrahedron abcd (float64)."""
    return np.einsum("...i,...i", np.cross(b - a, c - a), d - a)


def segment_crosses_triangle(p, q, a, b, c) -> np.ndarray:
    """Whether segment pq passes through triangle abc, strictly (its ends on opposite sides of the plane and
    the line through the triangle's interior), elementwise (float64 orientation tests)."""
    sp, sq = _orient(a, b, c, p), _orient(a, b, c, q)
    s1, s2, s3 = _orient(p, q, a, b), _orient(p, q, b, c), _orient(p, q, c, a)
    same = ((s1 > 0) & (s2 > 0) & (s3 > 0)) | ((s1 < 0) & (s2 < 0) & (s3 < 0))
    return (sp * sq < 0) & same


def _spheres(x, elements):
    """Centre and radius of a bounding sphere of each element (rows of vertex indices)."""
    points = x[elements]
    centre = points.mean(axis=1)
    return centre, np.max(np.linalg.norm(points - centre[:, None], axis=2), axis=1)


def candidate_pairs(x: np.ndarray, triangles: np.ndarray, edges: np.ndarray, reach: float):
    """Every vertex–triangle (vertex, triangle) and edge–edge (edge, edge with a larger index) pair sharing no
    vertex whose elements may be closer than ``reach`` [m] at positions ``x`` (a superset: bounding spheres)."""
    from scipy.spatial import cKDTree

    vertices = np.unique(triangles)
    tc, tr = _spheres(x, triangles)
    tree = cKDTree(x[vertices])
    lists = tree.query_ball_point(tc, tr + reach)
    counts = np.fromiter((len(v) for v in lists), dtype=np.int64, count=len(lists))
    vt_tri = np.repeat(np.arange(len(triangles)), counts)
    vt_vertex = vertices[np.concatenate(lists).astype(np.int64)] if counts.sum() else np.zeros(0, np.int64)
    keep = ~(triangles[vt_tri] == vt_vertex[:, None]).any(axis=1)
    ec, er = _spheres(x, edges)
    tree = cKDTree(ec)
    pairs = tree.query_pairs(2 * er.max() + reach, output_type="ndarray") if len(edges) else np.zeros((0, 2), int)
    pairs = pairs[np.linalg.norm(ec[pairs[:, 0]] - ec[pairs[:, 1]], axis=1) <= er[pairs[:, 0]] + er[pairs[:, 1]] + reach]
    e1, e2 = edges[pairs[:, 0]], edges[pairs[:, 1]]
    share = (e1[:, :1] == e2).any(axis=1) | (e1[:, 1:] == e2).any(axis=1)
    return np.stack([vt_vertex[keep], vt_tri[keep]], axis=1), pairs[~share]


def brute_pairs(x: np.ndarray, triangles: np.ndarray, reach: float):
    """All-pairs reference: the vertex–triangle and edge–edge pairs sharing no vertex closer than ``reach``
    [m], with their distances: (vt [k, 2], vt_distance [k], ee [m, 2] (edge indices, first < second),
    ee_distance [m]). Quadratic: for small meshes."""
    x = np.asarray(x, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    edges = surface_edges(triangles)
    vertices = np.unique(triangles)
    v, t = np.meshgrid(vertices, np.arange(len(triangles)), indexing="ij")
    v, t = v.ravel(), t.ravel()
    keep = ~(triangles[t] == v[:, None]).any(axis=1)
    v, t = v[keep], t[keep]
    d = vertex_triangle_distance(x[v], *(x[triangles[t, k]] for k in range(3)))
    near = d < reach
    e1, e2 = np.triu_indices(len(edges), 1)
    a, b = edges[e1], edges[e2]
    keep = ~((a[:, :1] == b).any(axis=1) | (a[:, 1:] == b).any(axis=1))
    e1, e2 = e1[keep], e2[keep]
    de = edge_edge_distance(x[edges[e1, 0]], x[edges[e1, 1]], x[edges[e2, 0]], x[edges[e2, 1]])
    close = de < reach
    return np.stack([v[near], t[near]], axis=1), d[near], np.stack([e1[close], e2[close]], axis=1), de[close]


@dataclass
class FrameAudit:
    """What :func:`audit_frame` found in one frame.

    Attributes:
        intersections: (edge, triangle) pairs sharing no vertex where the edge passes through the triangle,
            shape [k, 2] (zero rows expected).
        min_vertex_triangle: the smallest vertex–triangle distance [m] between elements sharing no vertex
            (``inf`` when none is within the audit's reach).
        min_edge_edge: the smallest edge–edge distance [m] likewise.
        vertex_triangle, edge_edge: the distances [m] of the pairs the reach kept (a superset of those closer
            than it), one per pair.
    """

    intersections: np.ndarray
    min_vertex_triangle: float
    min_edge_edge: float
    vertex_triangle: np.ndarray
    edge_edge: np.ndarray

    @property
    def min_distance(self) -> float:
        return min(self.min_vertex_triangle, self.min_edge_edge)


def edge_triangle_intersections(x: np.ndarray, triangles: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The (edge, triangle) pairs sharing no vertex where the edge passes through the triangle at ``x`` [m]
    (:func:`segment_crosses_triangle`), shape [k, 2]; candidates from the triangles' and edges' bounding spheres."""
    from scipy.spatial import cKDTree

    tc, tr = _spheres(x, triangles)
    ec, er = _spheres(x, edges)
    lists = cKDTree(ec).query_ball_point(tc, tr + er.max())
    counts = np.fromiter((len(v) for v in lists), dtype=np.int64, count=len(lists))
    tri = np.repeat(np.arange(len(triangles)), counts)
    edge = np.concatenate(lists).astype(np.int64) if counts.sum() else np.zeros(0, np.int64)
    keep = ~((triangles[tri][:, :, None] == edges[edge][:, None, :]).any(axis=(1, 2)))
    tri, edge = tri[keep], edge[keep]
    hit = segment_crosses_triangle(x[edges[edge, 0]], x[edges[edge, 1]], *(x[triangles[tri, k]] for k in range(3)))
    return np.stack([edge[hit], tri[hit]], axis=1)


def audit_frame(x: np.ndarray, triangles: np.ndarray, *, reach: float | None = None,
                edges: np.ndarray | None = None) -> FrameAudit:
    """Audit one configuration ``x`` [vertex_count, 3] of the surface ``triangles`` in float64.

    Args:
        reach: distances are measured for pairs closer than this [m] (default: the longest edge, which
            covers every intersection test too); a farther minimum reads as ``inf``.
        edges: :func:`surface_edges` of ``triangles``, if already known.
    """
    x = np.asarray(x, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    edges = surface_edges(triangles) if edges is None else edges
    if reach is None:
        reach = float(np.max(np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)))
    vt, ee = candidate_pairs(x, triangles, edges, reach)
    dvt = vertex_triangle_distance(x[vt[:, 0]], *(x[triangles[vt[:, 1], k]] for k in range(3)))
    dee = edge_edge_distance(x[edges[ee[:, 0], 0]], x[edges[ee[:, 0], 1]], x[edges[ee[:, 1], 0]], x[edges[ee[:, 1], 1]])
    return FrameAudit(
        intersections=edge_triangle_intersections(x, triangles, edges),
        min_vertex_triangle=float(dvt.min()) if len(dvt) else np.inf,
        min_edge_edge=float(dee.min()) if len(dee) else np.inf,
        vertex_triangle=dvt,
        edge_edge=dee,
    )


#: Tight-Inclusion CCD's settings: its time tolerance [-] and its iteration cap. A query that reaches the cap (only
#: a pair touching, or coplanar and within ~tolerance over a stretch of the step: a degenerate touch) is reported
#: as a touch, never dropped; its default cap (1e7) spends minutes on such a pair.
CCD_TOLERANCE = 1.0e-6
CCD_ITERATIONS = 100_000
#: Relative distance [-] (of the coordinates' magnitude) at which a pair counts as touching already at a step's start.
CONTACT = 1.0e-12


def _ipctk():
    """IPC Toolkit's Python module (Tight-Inclusion CCD, its broad phases), its log quietened to errors, or a
    ConfigError saying how to get it."""
    try:
        import ipctk  # optional: ipctk (pip install 'warpspring[audit]'), for the continuous audits only
    except ImportError:
        raise ConfigError("the continuous audit needs IPC Toolkit's Python module: pip install 'warpspring[audit]' "
                          "(or pip install ipctk)") from None
    ipctk.set_logger_level(ipctk.LoggerLevel.error)  # not a warning per pair that starts in contact
    return ipctk


def _fortran(a, dtype) -> np.ndarray:
    return np.asfortranarray(a, dtype=dtype)


class SurfaceAudit:
    """The float64 audits of one triangle surface, its topology prepared once (every call takes positions
    [vertex_count, 3] indexed like ``triangles``).

    * :meth:`motion`: continuous collision detection over the straight path x⁰ → x¹ of every vertex (one
      substep's motion): every vertex–triangle and edge–edge pair sharing no vertex whose primitives touch at
      some t in [0, 1]. IPC Toolkit's Tight-Inclusion CCD (Wang et al. 2021) decides each pair in float64 with
      a certified error bound: it never misses a touch (no false negatives); it may report a pair that comes
      within its numerical tolerance (~1e-6 of the pair's extent) without touching, far below any thickness.
      Candidates come from its broad phase over the swept boxes (not O(n²)).
    * :meth:`frame`: the state at one time: edge–triangle intersections between primitives sharing no vertex
      (any two intersecting triangles have an edge of one through the other), and the distances.
    * :meth:`step`: both, for one substep (``thickness``: also the pairs closer than τ/2 at its end).

    Args:
        triangles: [triangle_count, 3] vertex indices.
    """

    def __init__(self, triangles: np.ndarray):
        self.triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.edges = surface_edges(self.triangles)
        self.vertices = np.unique(self.triangles)  # the surface's vertices; others (interiors, points) are skipped
        local = np.searchsorted(self.vertices, self.triangles)
        self._faces = _fortran(local, np.int32)
        self._edges = _fortran(np.searchsorted(self.vertices, self.edges), np.int32)
        self._mesh = self.rest = None

    def _collision_mesh(self, x: np.ndarray):
        """IPC Toolkit's mesh of the surface, its rest positions (:attr:`rest`) those of the first call's ``x``."""
        if self._mesh is None:
            self.rest = np.array(x, dtype=np.float64)
            self._mesh = _ipctk().CollisionMesh(_fortran(x[self.vertices], np.float64), self._edges, self._faces)
        return self._mesh

    def _candidates(self, x0: np.ndarray, x1: np.ndarray):
        """The straight paths' positions (local, Fortran order), the collision mesh, the CCD and its candidates."""
        ipctk = _ipctk()
        v0 = _fortran(np.asarray(x0, dtype=np.float64)[self.vertices], np.float64)
        v1 = _fortran(np.asarray(x1, dtype=np.float64)[self.vertices], np.float64)
        mesh = self._collision_mesh(np.asarray(x0, dtype=np.float64))
        ccd = ipctk.TightInclusionCCD(CCD_TOLERANCE, CCD_ITERATIONS)
        candidates = ipctk.Candidates()
        candidates.build(mesh, v0, v1, 0.0)
        return v0, v1, mesh, ccd, candidates

    def touches_any(self, x0: np.ndarray, x1: np.ndarray) -> bool:
        """Whether any pair touches on the straight paths from ``x0`` to ``x1`` [m] (the same certified CCD as
        :meth:`motion`, stopping at the first touch: where many pairs touch, far cheaper than listing them)."""
        v0, v1, mesh, ccd, candidates = self._candidates(x0, x1)
        return not candidates.is_step_collision_free(mesh, v0, v1, 0.0, ccd)

    def motion(self, x0: np.ndarray, x1: np.ndarray) -> MotionAudit:
        """The pairs that touch while every vertex moves on the straight line from ``x0`` to ``x1`` [m]."""
        v0, v1, mesh, ccd, candidates = self._candidates(x0, x1)
        pairs = len(candidates.fv_candidates) + len(candidates.ee_candidates)
        if candidates.is_step_collision_free(mesh, v0, v1, 0.0, ccd):
            return MotionAudit(touches=np.zeros((0, 3), np.int64), time=np.zeros(0), pairs=pairs)
        # The pairs: (vertex, triangle) and (edge, edge) in this surface's local indices.
        fv = np.array([(c.vertex_id, c.face_id) for c in candidates.fv_candidates], np.int64).reshape(-1, 2)
        ee = np.array([(c.edge0_id, c.edge1_id) for c in candidates.ee_candidates], np.int64).reshape(-1, 2)
        e = self._edges
        start = np.concatenate([
            vertex_triangle_distance(v0[fv[:, 0]], *(v0[self._faces[fv[:, 1], k]] for k in range(3))),
            edge_edge_distance(v0[e[ee[:, 0], 0]], v0[e[ee[:, 0], 1]], v0[e[ee[:, 1], 0]], v0[e[ee[:, 1], 1]])])
        # A pair already touching at the start touches at t = 0 (Tight-Inclusion's retries on it can take minutes).
        touching = start <= CONTACT * max(1.0, float(np.abs(v0).max()))
        rows, times = [], []
        for i, c in enumerate(list(candidates.fv_candidates) + list(candidates.ee_candidates)):
            if touching[i]:
                hit, toi = True, 0.0
            else:
                hit, toi = c.ccd(c.dof(v0, self._edges, self._faces), c.dof(v1, self._edges, self._faces),
                                 narrow_phase_ccd=ccd)
            if hit:
                rows.append((0, self.vertices[fv[i, 0]], fv[i, 1]) if i < len(fv) else (1, *ee[i - len(fv)]))
                times.append(toi)
        touches = np.array(rows, dtype=np.int64).reshape(-1, 3)
        ee = touches[:, 0] == 1
        touches[ee, 1:] = np.sort(touches[ee, 1:], axis=1)
        return MotionAudit(touches=touches, time=np.array(times, dtype=np.float64), pairs=pairs)

    def frame(self, x: np.ndarray, *, reach: float | None = None) -> FrameAudit:
        """:func:`audit_frame` of this surface at ``x`` [m]."""
        return audit_frame(x, self.triangles, reach=reach, edges=self.edges)

    def intersections(self, x: np.ndarray) -> np.ndarray:
        """The (edge, triangle) intersections at ``x`` [m] (:func:`edge_triangle_intersections`), looked for only
        where IPC Toolkit's robust test says the surface intersects itself (its orientation tests are exact)."""
        x = np.asarray(x, dtype=np.float64)
        if not _ipctk().has_intersections(self._collision_mesh(x), _fortran(x[self.vertices], np.float64)):
            return np.zeros((0, 2), np.int64)
        return edge_triangle_intersections(x, self.triangles, self.edges)

    def near(self, x: np.ndarray, reach: float) -> tuple[float, int]:
        """(the smallest distance [m] between primitives sharing no vertex if below ``reach``, else ``inf``; the
        pairs closer than ``reach / 2``) at ``x``: IPC Toolkit's collision set (vertex–triangle pairs whose
        nearest points are on an edge or a corner count once, as vertex–edge or vertex–vertex pairs)."""
        ipctk = _ipctk()
        x = np.asarray(x, dtype=np.float64)
        mesh, v = self._collision_mesh(x), _fortran(x[self.vertices], np.float64)

        def collisions(dhat):
            found = ipctk.NormalCollisions()
            found.build(mesh, v, dhat)
            return found, sum(len(c) for c in (found.vv_collisions, found.ev_collisions, found.ee_collisions,
                                                found.fv_collisions))

        found, count = collisions(reach)
        if count == 0:
            return np.inf, 0
        nearest = float(np.sqrt(found.compute_minimum_distance(mesh, v)))  # it returns the squared distance
        return nearest, (collisions(0.5 * reach)[1] if nearest < 0.5 * reach else 0)

    def step(self, x0: np.ndarray, x1: np.ndarray, *, thickness: float | None = None) -> StepAudit:
        """One substep x⁰ → x¹: :meth:`motion`'s touches, and at x¹ the intersections and, with ``thickness`` τ
        [m], the smallest distance within τ (``inf`` beyond or without τ) and the pairs closer than τ/2."""
        x1 = np.asarray(x1, dtype=np.float64)
        motion = self.motion(x0, x1)
        nearest, close = self.near(x1, thickness) if thickness is not None else (np.inf, 0)
        return StepAudit(crossings=motion.touches, time=motion.time, intersections=self.intersections(x1),
                         min_distance=nearest, close=close)


@dataclass
class MotionAudit:
    """What :func:`audit_motion` (:meth:`SurfaceAudit.motion`) found over one substep.

    Attributes:
        touches: the pairs whose primitives touched during the step, rows (kind, a, b): kind 0 vertex–triangle
            (vertex, triangle), kind 1 edge–edge (edge, edge; indices into :func:`surface_edges`, a < b).
        time: each touch's first time of impact in [0, 1] (the step's parameter t), shape [len(touches)].
        pairs: candidate pairs the broad phase handed to the narrow phase.
    """

    touches: np.ndarray
    time: np.ndarray
    pairs: int


@dataclass
class StepAudit:
    """What :meth:`SurfaceAudit.step` found over one substep x⁰ → x¹.

    Attributes:
        crossings: :attr:`MotionAudit.touches` of the step (rows (kind, a, b)), with ``time`` their times of impact.
        intersections: (edge, triangle) intersections at x¹, shape [k, 2].
        min_distance: the smallest vertex–triangle or edge–edge distance [m] at x¹ within the reach (else ``inf``).
        close: pairs closer than half the thickness at x¹ (0 without one).
    """

    crossings: np.ndarray
    time: np.ndarray
    intersections: np.ndarray
    min_distance: float
    close: int

    @property
    def clean(self) -> bool:
        return not len(self.crossings) and not len(self.intersections) and not self.close


def audit_motion(x0: np.ndarray, x1: np.ndarray, triangles: np.ndarray) -> MotionAudit:
    """The vertex–triangle and edge–edge pairs sharing no vertex that touch while every vertex moves on the
    straight line from ``x0`` to ``x1`` [m] (float64 continuous collision detection:
    :meth:`SurfaceAudit.motion`; for many steps of one surface, make one :class:`SurfaceAudit`)."""
    return SurfaceAudit(triangles).motion(x0, x1)


def _summary(found: StepAudit) -> tuple:
    return len(found.crossings), len(found.intersections), found.close, found.min_distance


_WORKER_SURFACE = None


def _start_worker(triangles: np.ndarray, rest: np.ndarray) -> None:
    """A :class:`SubstepAudit` worker's surface (its process's, built once on the audit's rest positions)."""
    global _WORKER_SURFACE
    _WORKER_SURFACE = SurfaceAudit(triangles)
    _WORKER_SURFACE._collision_mesh(rest)


def _audit_steps(x: np.ndarray, thickness: float | None) -> list:
    """:func:`_summary` of each substep x[k] → x[k + 1] on the worker's surface."""
    return [_summary(_WORKER_SURFACE.step(x[k], x[k + 1], thickness=thickness)) for k in range(len(x) - 1)]


class SubstepRecord(StepHook):
    """Keeps the positions of every substep of a frame on the device (the StepHook half of
    :class:`SubstepAudit`): slot 0 the frame's start, slot k + 1 the end of substep k; capturable."""

    def __init__(self, model, substeps: int):
        self.model = model
        self.substeps = substeps
        self.positions = wp.zeros((substeps + 1) * model.state_size, dtype=model.vec3, device=model.device)

    def before_step(self, state, step: int, steps: int) -> None:
        if step == 0:
            wp.copy(self.positions, state.particle_q, dest_offset=0, count=self.model.state_size)

    def after_step(self, state, step: int, steps: int) -> None:
        n = self.model.state_size
        wp.copy(self.positions, state.particle_q, dest_offset=(step + 1) * n, count=n)

    def read(self) -> np.ndarray:
        """The frame's positions [m], float64, shape [substeps + 1, world_count, particle_count, 3]."""
        model = self.model
        return self.positions.numpy().astype(np.float64).reshape(self.substeps + 1, model.world_count,
                                                                 model.particle_count, 3)


class SubstepAudit(FrameHook):
    """Audits every substep of a run (a :class:`FrameHook` with a :class:`SubstepRecord` in the stepper): after
    each frame, per world and substep, :meth:`SurfaceAudit.step` of the colliding surface (the self-collision's,
    else the model's triangles). Attach with :meth:`attach`; read :attr:`crossings`, :meth:`line`.

    Args:
        thickness: τ [m] whose half no pair may come closer than (default: the self-collision's thickness, or
            none).
        workers: processes auditing a frame's substeps side by side (each a contiguous run of them; default 1:
            in this process). The findings are the same; a frame's audit takes about 1/workers of the time where
            the substeps outnumber the workers. Stop them with :meth:`close_workers`.

    Attributes:
        substeps: substeps audited (all worlds). crossings, intersections, close: their totals.
        min_distance: the smallest distance [m] at any substep's end (within τ; ``inf`` when none came that close).
        first: (time [s], world, what) of the first finding, or ``None``.
        overflow: the self-collision's pairs dropped for a full pair list (0 without self-collision).
        outrun: the self-collision's pair-steps beyond its cap (a pinned element closing in on a free one that could
            not give way; ``SelfContact.outrun``; 0 without self-collision).
        squeezed: the self-collision's pair-steps held apart but pressed below τ/2 (a pin pressing layers held by
            pins; ``SelfContact.squeezed``; 0 without self-collision).
    """

    def __init__(self, *, thickness: float | None = None, workers: int = 1):
        if int(workers) != workers or workers < 1:
            raise ConfigError(f"the substep audit's workers must be a whole number ≥ 1, got {workers!r}")
        self.thickness = thickness
        self.workers = int(workers)
        self.substeps = self.crossings = self.intersections = self.close = self.overflow = self.outrun = 0
        self.squeezed = 0
        self.min_distance = np.inf
        self.first = None
        self._record = self._surface = self._pool = None

    def attach(self, sim) -> SubstepAudit:
        """Audit ``sim``'s substeps from its next frame on (its stepper re-captures once with the record)."""
        model = sim.model
        self_contact = model.self_contact
        triangles = (self_contact.surface.triangle.numpy() if self_contact is not None
                     else model.tri_indices.numpy()[: len(model.tri_indices) // model.world_count])
        if len(triangles) == 0:
            raise ConfigError("the substep audit needs a triangle surface: the model has no cloth or mesh")
        # Refused before anything is made where the record (substeps + 1 states on the device) or a frame's audit
        # on the host does not fit.
        record, host = memory.audit_bytes(particles=model.particle_count, worlds=model.world_count,
                                          substeps=sim.substeps, surface_vertices=len(np.unique(triangles)),
                                          thickness=self.thickness is not None or self_contact is not None,
                                          precision="float64" if model.scalar is wp.float64 else "float32",
                                          cuda=model.device.is_cuda)
        remedy = ("audit a smaller model, fewer worlds or fewer substeps per frame, or run without "
                  "--audit-substeps")
        memory.check_device_room(f"auditing {sim.substeps} substeps a frame (their positions kept)", record,
                                 model.device, remedy=remedy)
        memory.check_host_room("auditing every substep (the record read back, the surface's pairs)",
                               host + (0 if model.device.is_cuda else record), remedy=remedy)
        if self.thickness is None and self_contact is not None:
            self.thickness = self_contact.thickness
        self._surface = SurfaceAudit(triangles)
        self._record = SubstepRecord(model, sim.substeps)
        sim.stepper.hooks.append(self._record)
        sim.add_frame_hook(self)
        return self

    def after_frame(self, sim, frame: int) -> None:
        x = self._record.read()
        start = sim.time - sim.frame_dt
        for world in range(x.shape[1]):
            for k, found in enumerate(self._steps(x[:, world])):
                crossings, intersections, close, nearest = found
                self.substeps += 1
                self.crossings += crossings
                self.intersections += intersections
                self.close += close
                self.min_distance = min(self.min_distance, nearest)
                if self.first is None and (crossings or intersections or close):
                    what = (f"{crossings} crossing(s)" if crossings else
                            f"{intersections} intersection(s)" if intersections else
                            f"{close} pair(s) closer than {0.5 * self.thickness:.4g} m")
                    self.first = (start + (k + 1) * sim.dt, world, what)
        if sim.model.self_contact is not None:
            counts = sim.model.self_contact.counts()
            self.overflow = int(counts["overflow"].sum())
            self.outrun = int(counts["outrun"].sum())
            self.squeezed = int(counts["squeezed"].sum())

    def _steps(self, x: np.ndarray) -> list:
        """(crossings, intersections, pairs closer than τ/2, smallest distance) of each substep of one world's
        frame ``x`` [substeps + 1, particle_count, 3], in order: here, or split into one contiguous run of
        substeps per worker (each worker's surface built on this one's rest positions: the same findings)."""
        steps = len(x) - 1
        if self.workers == 1 or steps == 1:
            return [_summary(self._surface.step(x[k], x[k + 1], thickness=self.thickness)) for k in range(steps)]
        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self._surface._collision_mesh(x[0])  # the rest positions a serial audit would take
            self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_start_worker,
                                             initargs=(self._surface.triangles, self._surface.rest))
        bounds = np.linspace(0, steps, min(self.workers, steps) + 1).round().astype(int)
        runs = [self._pool.submit(_audit_steps, x[a: b + 1], self.thickness) for a, b in zip(bounds, bounds[1:])]
        return [found for run in runs for found in run.result()]

    def close_workers(self) -> None:
        """Stop the workers (``workers`` > 1); the audit's totals stay readable. Also on garbage collection."""
        if getattr(self, "_pool", None) is not None:  # (none where the constructor refused its arguments)
            self._pool.shutdown()
            self._pool = None

    def __del__(self):
        self.close_workers()

    @property
    def clean(self) -> bool:
        return not (self.crossings or self.intersections or self.close)

    def line(self) -> str:
        """One line of findings."""
        text = (f"substep audit: {self.substeps} substeps, {self.crossings} crossings, {self.intersections} "
                f"intersections")
        if self.thickness is not None:
            text += f", {self.close} pairs closer than {0.5 * self.thickness:.4g} m"
            text += f", minimum distance {self.min_distance:.4g} m" if np.isfinite(self.min_distance) else ""
        if self.first is not None:
            text += f"; first at t = {self.first[0]:.4g} s (world {self.first[1]}: {self.first[2]})"
        if self.overflow:
            text += f"; {self.overflow} self-collision pairs dropped for a full pair list"
        if self.outrun:
            text += (f"; {self.outrun} pair-steps where a pinned (kinematic) element closed in on the surface faster "
                     f"than it could give way (beyond the self-collision's cap)")
        if self.squeezed:
            text += (f"; {self.squeezed} pair-steps pressed below half the thickness by pins onto layers held by pins "
                     f"(no room to give way)")
        return text


@dataclass
class UsdAudit:
    """:func:`audit_usd`'s findings: per sampled frame (time code), the intersections and the minimum distance
    [m] over every animated mesh of the file taken together (so layers of different meshes count too)."""

    frames: list
    intersections: list
    min_distance: list

    @property
    def total_intersections(self) -> int:
        return int(sum(self.intersections))

    def line(self, thickness: float | None = None) -> str:
        """One line of findings; with ``thickness`` [m], also the frames closer than half of it."""
        worst = min(self.min_distance) if self.min_distance else np.inf
        text = (f"{len(self.frames)} frames: {self.total_intersections} segment-triangle intersections between "
                f"elements sharing no vertex; minimum vertex-triangle / edge-edge distance {worst:.4g} m")
        if thickness is not None:
            close = sum(d < 0.5 * thickness for d in self.min_distance)
            text += f"; {close} frames closer than half the thickness ({0.5 * thickness:.4g} m)"
        return text


def audit_usd(path: str, *, reach: float | None = None) -> UsdAudit:
    """Run :func:`audit_frame` on every frame of a USD file: the meshes whose points are time-sampled (the
    simulated surfaces), in world space, polygons fan-triangulated, all meshes together.

    Raises:
        ConfigError: the file cannot be opened or holds no animated mesh.
    """
    import os

    from pxr import Tf, Usd, UsdGeom  # optional: usd-core, loaded only for an audit

    if not os.path.isfile(path):
        raise ConfigError(f"USD file not found: {path}")
    try:
        layers = check_usd_layers(str(path))  # every layer a regular file before USD opens it (held: reused)
        stage = Usd.Stage.Open(str(path))
        del layers
    except Tf.ErrorException:
        stage = None
    if stage is None:
        raise ConfigError(f"cannot open {path} as USD: expected a .usd, .usda or .usdc file")
    meshes = [UsdGeom.Mesh(p) for p in stage.Traverse()
              if p.IsA(UsdGeom.Mesh) and UsdGeom.Mesh(p).GetPointsAttr().GetNumTimeSamples() > 0]
    if not meshes:
        raise ConfigError(f"{path} holds no animated mesh to audit")
    triangles, offset = [], 0
    for mesh in meshes:
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
        indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        fan = np.repeat(np.arange(len(counts)), counts - 2)  # polygon of each fan triangle
        k = np.arange(len(fan)) - np.repeat(np.cumsum(counts - 2) - (counts - 2), counts - 2) + 1
        first = starts[fan]
        triangles.append(offset + np.stack([indices[first], indices[first + k], indices[first + k + 1]], axis=1))
        offset += len(mesh.GetPointsAttr().Get(Usd.TimeCode.EarliestTime()))
    triangles = np.concatenate(triangles)
    times = sorted({t for m in meshes for t in m.GetPointsAttr().GetTimeSamples()})
    result = UsdAudit(frames=[], intersections=[], min_distance=[])
    for t in times:
        cache = UsdGeom.XformCache(t)
        points = []
        for mesh in meshes:
            x = np.asarray(mesh.GetPointsAttr().Get(t), dtype=np.float64).reshape(-1, 3)
            m = np.asarray(cache.GetLocalToWorldTransform(mesh.GetPrim()), dtype=np.float64)
            points.append(x @ m[:3, :3] + m[3, :3])  # USD's row-vector convention
        found = audit_frame(np.concatenate(points), triangles, reach=reach)
        result.frames.append(t)
        result.intersections.append(len(found.intersections))
        result.min_distance.append(found.min_distance)
    return result
