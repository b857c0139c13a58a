"""Float64 audits of a triangle surface on the host: does anything pass through anything?

Per frame (:func:`audit_frame`): segment–triangle intersections between an edge and a triangle that share no
vertex (zero expected) and the minimum vertex–triangle and edge–edge distances between elements that share
no vertex. Per step (:func:`audit_motion`): whether any vertex–triangle or edge–edge pair touches while every
vertex moves on the straight line between two states, by conservative advancement, which is a proof: along
linear motion every point of a primitive moves at most as fast as its fastest vertex, so a pair's distance
D(t) is Lipschitz with constant L = (fastest vertex of one) + (fastest of the other) displacement per unit t,
and from any t the pair cannot touch before t + D(t)/L. Stepping by that amount either reaches t = 1 (no
contact, hence no crossing) or finds D below ``resolution`` (a touch, reported).

Candidates come from SciPy's k-d tree over bounding spheres (exact pruning: a pair is skipped only when its
bounding spheres are farther apart than the distance of interest); :func:`brute_pairs` is the all-pairs
reference the device's broad phase is tested against. ``warpspring audit OUT.usdc`` runs the per-frame audit
on a written USD file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.mesh_files import check_usd_layers
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
    """

    intersections: np.ndarray
    min_vertex_triangle: float
    min_edge_edge: float

    @property
    def min_distance(self) -> float:
        return min(self.min_vertex_triangle, self.min_edge_edge)


def audit_frame(x: np.ndarray, triangles: np.ndarray, *, reach: float | None = None) -> FrameAudit:
    """Audit one configuration ``x`` [vertex_count, 3] of the surface ``triangles`` in float64.

    Args:
        reach: distances are measured for pairs closer than this [m] (default: the longest edge, which
            covers every intersection test too); a farther minimum reads as ``inf``.
    """
    x = np.asarray(x, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    edges = surface_edges(triangles)
    if reach is None:
        reach = float(np.max(np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)))
    vt, ee = candidate_pairs(x, triangles, edges, reach)
    dvt = vertex_triangle_distance(x[vt[:, 0]], *(x[triangles[vt[:, 1], k]] for k in range(3)))
    dee = edge_edge_distance(x[edges[ee[:, 0], 0]], x[edges[ee[:, 0], 1]], x[edges[ee[:, 1], 0]], x[edges[ee[:, 1], 1]])
    # Edges against triangles sharing no vertex: candidates from the triangles' and edges' bounding spheres.
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
    return FrameAudit(
        intersections=np.stack([edge[hit], tri[hit]], axis=1),
        min_vertex_triangle=float(dvt.min()) if len(dvt) else np.inf,
        min_edge_edge=float(dee.min()) if len(dee) else np.inf,
    )


@dataclass
class MotionAudit:
    """What :func:`audit_motion` found over one step.

    Attributes:
        touches: pairs whose distance fell below the resolution during the step: rows (kind, a, b) with kind
            0 for vertex–triangle (vertex, triangle) and 1 for edge–edge (edge, edge).
        min_distance: the smallest distance [m] any advancement step evaluated (an upper bound of the true
            minimum over the step; a lower bound is min_distance's pairs' D - L·step, not reported).
        pairs: pairs examined (those that could come within reach of each other).
    """

    touches: np.ndarray
    min_distance: float
    pairs: int


def audit_motion(x0: np.ndarray, x1: np.ndarray, triangles: np.ndarray, *, resolution: float = 1e-9,
                 max_iterations: int = 10000) -> MotionAudit:
    """Whether any vertex–triangle or edge–edge pair sharing no vertex touches (comes within ``resolution``
    [m]) while every vertex moves on a straight line from ``x0`` to ``x1`` (float64 conservative advancement;
    the module's docstring gives the proof). A pair still unresolved after ``max_iterations`` counts as a
    touch."""
    x0 = np.asarray(x0, dtype=np.float64)
    x1 = np.asarray(x1, dtype=np.float64)
    triangles = np.asarray(triangles, dtype=np.int64)
    edges = surface_edges(triangles)
    speed = np.linalg.norm(x1 - x0, axis=1)  # per unit of the step's parameter t in [0, 1]
    vt, ee = candidate_pairs(x0, triangles, edges, 2.0 * float(speed.max()) + resolution)
    kinds = np.concatenate([np.zeros(len(vt), np.int64), np.ones(len(ee), np.int64)])
    first = np.concatenate([vt[:, 0], ee[:, 0]])
    second = np.concatenate([vt[:, 1], ee[:, 1]])
    corners = np.concatenate([
        np.concatenate([vt[:, :1], triangles[vt[:, 1]]], axis=1),
        np.concatenate([edges[ee[:, 0]], edges[ee[:, 1]]], axis=1),
    ]).astype(np.int64)  # four vertices per pair: VT (v, a, b, c); EE (p1, q1, p2, q2)
    split = np.where(kinds == 0, 1, 2)  # the first side's vertex count
    side = np.arange(4)[None, :] < split[:, None]
    lipschitz = (np.where(side, speed[corners], 0).max(axis=1) + np.where(~side, speed[corners], 0).max(axis=1))

    def distance(idx, t):
        x = x0[corners[idx]] + t[:, None, None] * (x1 - x0)[corners[idx]]
        out = np.empty(len(idx))
        is_vt = kinds[idx] == 0
        out[is_vt] = vertex_triangle_distance(x[is_vt, 0], x[is_vt, 1], x[is_vt, 2], x[is_vt, 3])
        out[~is_vt] = edge_edge_distance(x[~is_vt, 0], x[~is_vt, 1], x[~is_vt, 2], x[~is_vt, 3])
        return out

    active = np.arange(len(kinds))
    t = np.zeros(len(kinds))
    touched = np.zeros(len(kinds), dtype=bool)
    smallest = np.inf
    for _ in range(max_iterations):
        if len(active) == 0:
            break
        d = distance(active, t[active])
        smallest = min(smallest, float(d.min()))
        hit = d < resolution
        touched[active[hit]] = True
        moving = lipschitz[active] > 0
        t[active] = np.where(moving, t[active] + d / np.where(moving, lipschitz[active], 1.0), 2.0)
        active = active[~hit & (t[active] < 1.0)]
    else:
        touched[active] = True
    rows = np.stack([kinds, first, second], axis=1)[touched]
    return MotionAudit(touches=rows, min_distance=smallest, pairs=len(kinds))


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
