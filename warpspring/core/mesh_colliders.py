"""Mesh colliders: a triangle mesh as a collider kind, static, moved by keyframe tracks, or deforming.

A mesh collider is a ``wp.Mesh`` (its BVH) in the collider's own frame; the contact kernels query it for the
closest point (``kernels.mesh_colliders.mesh_funcs``) and cast each particle's path of the step against it. How a
mesh tells inside from outside is explicit (``sides``):

* ``"closed"``: a closed (watertight) mesh, signed by the closest feature's angle-weighted pseudo-normal (exact
  for a watertight, consistently wound mesh), or with ``winding_number=True`` inside where its winding number
  exceeds ½ (Warp's fast winding number: robust to small holes and flipped slivers, about 5× the cost of a
  query near the surface). It is looked for up to ``depth`` outside it; a point deep inside (found by the
  parity of three skew rays) looks as far as it must.
* ``"one_sided"``: an open mesh (terrain, a slope, a shell) whose outside is the side its faces' normals point
  to (counter-clockwise winding); up to ``depth`` behind it (beyond its border edges too) is inside, and a
  particle there is pushed out to the front; farther away the mesh is out of reach.
* ``"two_sided"``: an open mesh with no inside: particles stay ``thickness`` plus their radius away on whichever
  side they come from (the side is kept by sweeping their path, not by the sign of a distance); it is looked
  for up to ``depth`` away.

Particle contacts with a mesh (not ``winding_number``) keep a per-particle candidate cache (a Verlet list:
``kernels.mesh_colliders.mesh_cache_funcs`` has the argument why it never changes the answer): a full BVH query only
when a particle moved more than ``cache_margin`` [m] in the mesh's frame since its last one, otherwise the exact
closest point on its (at most ``cache_candidates``) cached triangles. ``MeshCollider.cache_margin = 0`` forces
the full query at every use, with the same results.

A mesh's frame moves with the collider's translation and rotation tracks like any collider's; its points may
also change between frames (:meth:`MeshCollider.set_points`: the BVH is refit in place, so captured graphs
stay valid), with per-vertex velocities that the response takes as the surface's velocity. Points sampled in
time (a USD prim's time-sampled points) are applied at every frame by :func:`advance_mesh_colliders`: the
points at the frame's end, the velocity their change over the frame.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..errors import ConfigError
from ..kernels.mesh_colliders import FACE_NORMALS, MESH_SIDES, MeshCache, face_normals_kernel, pseudo_normals_kernel
from . import memory
from .mesh_counts import mesh_file_counts, usd_mesh_counts
from .mesh_files import USD_EXTENSIONS

#: Host bytes of adding a mesh collider read from a file (trimesh's loading, the float64 vertices and faces kept):
#: per triangle and fixed; an OBJ sheet measured 421 B per triangle at 179k triangles and 265 B at 977k
#: (``bench/memory.py``), that is ~230 B per triangle and ~28 MiB, counted as 320 B and 24 MiB.
MESH_COLLIDER_FILE_PER_FACE = 320
MESH_COLLIDER_FILE_FIXED = 24 << 20


#: Host bytes of adding a mesh collider read from a USD file (``read_usd_mesh``: its points in float64, the fan of
#: its polygons, its face-vertex arrays; the builder's copies): per triangle read as a triangle, per triangle of a
#: polygon of four or more corners (the fan and its convexity test), per vertex and time sample of the points (each
#: sample read, kept in float64 and stacked), and fixed. .usdc sheets of 977k triangles measured 203 B per triangle
#: (triangles) and 417 B (quads), with four samples of 90k points 53 B more per vertex and sample
#: (``bench/memory.py``); counted as 240 B, 480 B, 64 B and 24 MiB.
MESH_COLLIDER_USD_PER_FACE = 240
MESH_COLLIDER_USD_PER_FANNED_FACE = 480
MESH_COLLIDER_USD_PER_SAMPLE_VERTEX = 64
#: Host bytes per byte of a text USD file (.usda) of parsing it into its layer before its mesh can be counted:
#: measured 7.1 for a 34 MiB sheet, counted as 8.
USDA_PARSE_PER_BYTE = 8


def check_mesh_file_room(path: str, *, prim: str | None = None) -> None:
    """Refuse a mesh collider's file whose reading would need more host memory than is available, before it is
    read: its triangles counted from its header or streamed lines (:func:`mesh_file_counts`), or for a USD file
    from its mesh prim's array lengths (:func:`usd_mesh_counts`; a text file's parse checked first by its size); a
    format not counted is checked at finalize, with the model."""
    remedy = "decimate the mesh (fewer triangles) or use a simpler collider (a box, a capsule)"
    if path.lower().endswith(USD_EXTENSIONS):
        if os.path.isfile(path) and not _usd_crate(path):
            memory.check_host_room(f"the USD file {path} ({memory.format_bytes(os.path.getsize(path))} of text)",
                                   USDA_PARSE_PER_BYTE * os.path.getsize(path), remedy=remedy + ", or save it as .usdc")
        counts = usd_mesh_counts(path, prim=prim)
        if counts is None:
            return
        memory.check_host_room(
            f"the mesh collider {path} ({counts.triangles:,} triangles, {counts.vertices:,} vertices"
            + (f", {counts.samples} time samples" if counts.samples > 1 else "") + ")",
            usd_collider_bytes(counts), remedy=remedy)
        return
    counts = mesh_file_counts(path)
    if counts is None:
        return
    vertices, faces = counts
    memory.check_host_room(f"the mesh collider {path} ({faces:,} triangles, {vertices:,} vertices)",
                           MESH_COLLIDER_FILE_PER_FACE * faces + 24 * vertices + MESH_COLLIDER_FILE_FIXED,
                           remedy=remedy)


def usd_collider_bytes(counts) -> int:
    """Host bytes [B] of adding a mesh collider read from a USD file of ``counts`` (:class:`UsdMeshCounts`)."""
    return (MESH_COLLIDER_USD_PER_FACE * (counts.triangles - counts.fanned)
            + MESH_COLLIDER_USD_PER_FANNED_FACE * counts.fanned
            + MESH_COLLIDER_USD_PER_SAMPLE_VERTEX * counts.vertices * max(counts.samples, 1) + MESH_COLLIDER_FILE_FIXED)


def _usd_crate(path: str) -> bool:
    """Whether a USD file is binary (a crate file: "PXR-USDC" first), whose arrays are read on demand."""
    with open(path, "rb") as f:
        return f.read(8) == b"PXR-USDC"


@dataclass(eq=False)
class MeshShape:
    """The host description of a mesh collider (``ShapeInfo.mesh``).

    Attributes:
        vertices: the mesh's points in the collider's frame [m], shape [v, 3], float64.
        faces: vertex indices of each triangle, counter-clockwise seen from outside, shape [t, 3], int32.
        sides: "closed", "one_sided" or "two_sided" (see the module docstring).
        sample_times: times [s] of time-sampled points, shape [k], increasing, or None for fixed points.
        sample_points: the points at those times [m], shape [k, v, 3], or None.
        winding_number: a closed mesh's sign from its winding number rather than its pseudo-normals.
        depth: how far from its surface [m] a mesh is looked for (one-sided: how deep behind it is inside); None:
            a tenth of its bounding box's diagonal. It must exceed the particles' radius plus the thickness; a
            closest-point query costs with it.
        deforming: whether its points may change between frames (time samples, or
            :meth:`MeshCollider.set_points`): a deforming mesh does work on the particles, so the guard's energy
            balance is off for it.
        cache_candidates: C, the triangles a particle's cache holds (more: a full query at that use, counted).
        cache_margin: m [m], how far a particle moves in the mesh's frame before it queries the BVH again; None:
            a quarter of the particles' largest radius plus the thickness.
    """

    vertices: np.ndarray
    faces: np.ndarray
    sides: str = "closed"
    sample_times: np.ndarray | None = None
    sample_points: np.ndarray | None = None
    deforming: bool = False
    depth: float | None = None
    winding_number: bool = False
    cache_candidates: int = 32
    cache_margin: float | None = None

    @property
    def sampled(self) -> bool:
        """Whether its points follow time samples (applied at every frame by :func:`advance_mesh_colliders`)."""
        return self.sample_times is not None and len(self.sample_times) > 1

    def bounds(self, points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Its bounding box in its frame [m] (of every time sample): lower and upper corners, shape [3] each."""
        p = self.vertices if points is None else points
        if points is None and self.sample_points is not None:
            p = self.sample_points.reshape(-1, 3)
        return p.min(axis=0), p.max(axis=0)

    def query_range(self, points: np.ndarray | None = None) -> tuple[float, float]:
        """How far from the mesh [m] its distance is computed (``depth``; default a tenth of its bounding box's
        diagonal) — beyond, a particle is out of its reach — and how far a point inside a closed mesh looks
        for its surface (twice the diagonal: always farther than its nearest surface point)."""
        lower, upper = self.bounds(points)
        diagonal = float(np.linalg.norm(upper - lower))
        return (0.1 * diagonal if self.depth is None else self.depth), 2.0 * diagonal + 1.0e-6

    def points_at(self, t: float) -> np.ndarray:
        """The points at time ``t`` [s] (linear between samples, held outside them), float64, shape [v, 3]."""
        if self.sample_times is None:
            return self.vertices
        times = self.sample_times
        k = int(np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 1))
        if k == len(times) - 1 or t <= times[0]:
            return self.sample_points[k]
        w = (t - times[k]) / (times[k + 1] - times[k])
        return (1.0 - w) * self.sample_points[k] + w * self.sample_points[k + 1]


def mesh_shape(vertices, faces, *, sides: str, deforming: bool = False, sample_times=None,
               sample_points=None, depth: float | None = None, winding_number: bool = False,
               cache_candidates: int = 32, cache_margin: float | None = None) -> MeshShape:
    """A checked :class:`MeshShape` (one-line errors for bad input)."""
    if sides not in MESH_SIDES:
        raise ConfigError(f"mesh collider sides must be one of {', '.join(map(repr, MESH_SIDES))} (closed: a "
                          f"watertight solid; one_sided: an open mesh, outside where its normals point; two_sided: an "
                          f"open shell), got {sides!r}")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.isfinite(v).all():
        raise ConfigError(f"mesh collider vertices must be finite, shape [v, 3] with v ≥ 3, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or not np.issubdtype(f.dtype, np.integer):
        raise ConfigError(f"mesh collider faces must be integer triangles, shape [t, 3], got shape {f.shape}")
    if f.min() < 0 or f.max() >= len(v):
        raise ConfigError(f"mesh collider faces index vertices 0 … {len(v) - 1}, got indices {f.min()} … {f.max()}")
    if sample_times is not None:
        sample_times = np.asarray(sample_times, dtype=np.float64).reshape(-1)
        sample_points = np.asarray(sample_points, dtype=np.float64)
        if sample_points.shape != (len(sample_times), *v.shape) or not np.isfinite(sample_points).all():
            raise ConfigError(f"mesh collider time samples: points must be finite, shape ({len(sample_times)}, "
                              f"{len(v)}, 3) for {len(sample_times)} times, got shape {sample_points.shape}")
        if len(sample_times) > 1 and not (np.diff(sample_times) > 0.0).all():
            raise ConfigError("mesh collider time samples: times must increase")
        deforming = deforming or len(sample_times) > 1
    if depth is not None and not (np.isfinite(depth) and depth > 0.0):
        raise ConfigError(f"mesh collider depth must be > 0 [m] (how far from an open mesh it is looked for), got "
                          f"{depth!r}")
    if winding_number and sides != "closed":
        raise ConfigError(f"winding_number applies to closed mesh colliders only (an open one has no inside), got "
                          f"sides={sides!r}")
    if isinstance(cache_candidates, bool) or not isinstance(cache_candidates, (int, np.integer)) \
            or not 1 <= cache_candidates <= 4096:
        raise ConfigError(f"mesh collider cache_candidates must be an integer in 1 … 4096 (triangles a particle's "
                          f"cache holds), got {cache_candidates!r}")
    if cache_margin is not None and not (np.isfinite(cache_margin) and cache_margin >= 0.0):
        raise ConfigError(f"mesh collider cache_margin must be ≥ 0 [m] (0: a full query at every use), got "
                          f"{cache_margin!r}")
    return MeshShape(vertices=v, faces=f.astype(np.int32), sides=sides, sample_times=sample_times,
                     sample_points=sample_points, deforming=bool(deforming), depth=depth,
                     winding_number=bool(winding_number), cache_candidates=int(cache_candidates),
                     cache_margin=None if cache_margin is None else float(cache_margin))


class MeshCollider:
    """A mesh collider of a finalized model: the ``wp.Mesh`` its kernels query (``Model.mesh_colliders``).

    Attributes:
        index: the collider's index among the model's colliders.
        mesh: the ``wp.Mesh`` (points and per-vertex velocities in the collider's frame, float32).
        info: its :class:`MeshShape`.
    """

    def __init__(self, model, index: int, info: MeshShape):
        self.model = model
        self.index = index
        self.info = info
        device = model.device
        points = info.points_at(0.0)
        self.mesh = wp.Mesh(
            points=wp.array(points.astype(np.float32), dtype=wp.vec3, device=device),
            indices=wp.array(info.faces.reshape(-1), dtype=wp.int32, device=device),
            velocities=wp.zeros(len(points), dtype=wp.vec3, device=device),
            support_winding_number=info.winding_number,
        )
        self._points = np.array(points)
        self._range = info.query_range()
        self._bounds = info.bounds()
        self.slot = -1  # its row of the particles' mesh cache (-1: Warp's own queries, a winding-number mesh)
        self.normal_offset = 0  # its first pseudo-normal in the model's MeshCache.normals
        self._topology = None  # the CSR tables pseudo_normals_kernel sums over (made with the cache)

    @property
    def name(self) -> str:
        return self.model.shapes[self.index].name

    def points(self) -> np.ndarray:
        """The current points in the collider's frame [m], float64, shape [v, 3] (the host's copy)."""
        return self._points

    def set_points(self, points, *, velocities=None, dt: float | None = None) -> None:
        """Move the mesh's points (between frames; a captured graph stays valid).

        Args:
            points: the new points in the collider's frame [m], shape [v, 3] (same vertex count and order).
            velocities: the surface's velocity at each point [m/s], shape [v, 3] or [3], which the response
                moves particles with (friction acts relative to it); default (points - previous points) / dt
                with ``dt``, else zero.
            dt: the time [s] over which the points moved (e.g. the frame's), to derive the velocities.
        """
        if not self.info.deforming:
            raise ConfigError(f"mesh collider {self.name!r} was built static: add it with deforming=True to move its "
                              "points between frames")
        points = np.asarray(points, dtype=np.float64)
        if points.shape != self._points.shape or not np.isfinite(points).all():
            raise ConfigError(f"mesh collider {self.name!r}: points must be finite, shape {self._points.shape} (its "
                              f"vertex count and order), got shape {points.shape}")
        if velocities is None:
            if dt is None:
                velocities = np.zeros_like(points)
            elif not dt > 0.0:
                raise ConfigError(f"mesh collider {self.name!r}: dt must be > 0 [s], got {dt}")
            else:
                velocities = (points - self._points) / dt
        velocities = np.broadcast_to(np.asarray(velocities, dtype=np.float64), points.shape)
        if not np.isfinite(velocities).all():
            raise ConfigError(f"mesh collider {self.name!r}: velocities must be finite, shape {points.shape} or (3,)")
        self.mesh.points.assign(points.astype(np.float32))
        self.mesh.velocities.assign(np.ascontiguousarray(velocities, dtype=np.float32))
        self.mesh.refit()
        self._points = np.array(points)
        if self.slot >= 0:  # new pseudo-normals (device work); every particle's candidates are stale
            self.update_pseudo_normals()
            self.model.shape_arrays.cache.side[self.slot].zero_()
        lower, upper = self.info.bounds(points)
        if (lower < self._bounds[0]).any() or (upper > self._bounds[1]).any():  # grown: widen its box and reach
            self._bounds = (np.minimum(lower, self._bounds[0]), np.maximum(upper, self._bounds[1]))
            depth, reach = MeshShape(vertices=np.array(self._bounds), faces=self.info.faces, sides=self.info.sides,
                                     depth=self.info.depth).query_range()
            self._range = (self._range[0], max(reach, self._range[1]))
            self._write_box()
        self.model.input_version += 1

    def _write_box(self) -> None:
        """Write the box its points have swept and its query range to its rows of the model's shape arrays."""
        _write_row(self.model.shape_arrays.size, self.index, (*self._range, 0.0))
        _write_row(self.model.shape_arrays.lower, self.index, self._bounds[0])
        _write_row(self.model.shape_arrays.upper, self.index, self._bounds[1])

    #: The names of a :meth:`snapshot`'s entries.
    SNAPSHOT = ("points", "velocities", "bounds", "range")

    def snapshot(self) -> dict[str, np.ndarray]:
        """What a checkpoint keeps of a deforming mesh, by name: its ``points`` [m] (the host's float64 copy, shape
        [v, 3]), the surface ``velocities`` the response uses [m/s] (float32, shape [v, 3]), and the box its points
        have swept so far (``bounds`` [m], shape [2, 3]) with its query ``range`` [m] (shape [2])."""
        return {"points": self._points.copy(), "velocities": self.mesh.velocities.numpy().copy(),
                "bounds": np.array(self._bounds), "range": np.array(self._range, dtype=np.float64)}

    def restore_snapshot(self, values: dict[str, np.ndarray]) -> None:
        """Put a :meth:`snapshot` back: the same float32 points and velocities on the device, its BVH and
        pseudo-normals refit to them, its swept box and query range as saved."""
        points = np.asarray(values["points"], dtype=np.float64)
        bounds, reach = np.asarray(values["bounds"], dtype=np.float64), np.asarray(values["range"], dtype=np.float64)
        if bounds.shape != (2, 3) or reach.shape != (2,):
            raise ConfigError(f"mesh collider {self.name!r}: a snapshot's bounds must have shape (2, 3) and its range "
                              f"(2,), got {bounds.shape} and {reach.shape}")
        # The saved box holds the saved points (it is the union of every set of points the run had), so
        # set_points does not grow it.
        self._bounds, self._range = (bounds[0].copy(), bounds[1].copy()), (float(reach[0]), float(reach[1]))
        self.set_points(points, velocities=np.asarray(values["velocities"], dtype=np.float64))
        self._write_box()


    @property
    def cache_margin(self) -> float:
        """m [m]: how far a particle moves in the mesh's frame before its cache is refreshed by a full query; 0:
        a full query at every use (the same results, for timing and tests). A live value (no recompilation)."""
        return float(self.model.shape_arrays.cache.margin.numpy()[self.index])

    @cache_margin.setter
    def cache_margin(self, value: float) -> None:
        if not (np.isfinite(value) and value >= 0.0):
            raise ConfigError(f"mesh collider {self.name!r}: cache_margin must be ≥ 0 [m], got {value!r}")
        cache = self.model.shape_arrays.cache
        _write_row(cache.margin, self.index, value)
        if self.slot >= 0:
            cache.side[self.slot].zero_()
        self.model.input_version += 1

    def update_pseudo_normals(self) -> None:
        """Write its faces' pseudo-normals from its current points into the model's ``MeshCache.normals``
        (two launches: the faces' normals and angles, then their sums; the same values as :func:`pseudo_normals`
        to float32 rounding)."""
        if self._topology is None:
            faces = self.info.faces.astype(np.int64)
            corners = faces.reshape(-1)
            groups = edge_groups(faces).reshape(-1)

            def csr(keys, count):
                order = np.argsort(keys, kind="stable").astype(np.int32)
                start = np.zeros(count + 1, dtype=np.int32)
                np.cumsum(np.bincount(keys, minlength=count), out=start[1:])
                return start, order

            vertex_start, vertex_corner = csr(corners, len(self._points))
            edge_start, edge_entry = csr(groups, int(groups.max()) + 1)
            device = self.model.device
            count = len(faces)
            self._terms = [wp.zeros(count, dtype=wp.vec3d, device=device),
                           wp.zeros(3 * count, dtype=wp.float64, device=device)]
            self._topology = [wp.array(a, dtype=wp.int32, device=device) for a in
                              (vertex_start, vertex_corner, groups.astype(np.int32), edge_start, edge_entry // 3)]
        count = len(self.info.faces)
        wp.launch(face_normals_kernel, dim=count, inputs=[self.mesh.id], outputs=self._terms, device=self.model.device)
        wp.launch(pseudo_normals_kernel, dim=count, inputs=[self.mesh.id, *self._terms, *self._topology,
                                                            self.normal_offset],
                  outputs=[self.model.shape_arrays.cache.normals], device=self.model.device)

    def use_warp_query(self) -> None:
        """Resolve particle contacts with Warp's own closest-point query up to the depth and its ray cast (the
        path before the candidate cache, for comparisons: its closest points may differ from the cached path's
        in the last bits); setting :attr:`cache_margin` goes back to the exact triangle path."""
        _write_row(self.model.shape_arrays.cache.margin, self.index, -1.0)
        self.model.input_version += 1


def edge_groups(faces: np.ndarray) -> np.ndarray:
    """For each face's edges ab, bc, ca, the index of the undirected edge it is (faces sharing an edge share
    it), int64, shape [t, 3]: the topology :func:`pseudo_normals` sums over, computed once per mesh."""
    f = np.asarray(faces, dtype=np.int64)
    ends = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1), axis=2).reshape(-1, 2)
    keys = ends[:, 0] * (int(f.max()) + 1) + ends[:, 1]
    return np.unique(keys, return_inverse=True)[1].reshape(-1, 3)


def pseudo_normals(points: np.ndarray, faces: np.ndarray, edges: np.ndarray | None = None) -> np.ndarray:
    """Unit angle-weighted pseudo-normals (Bærentzen and Aanæs) of each face's features, float32, shape
    [t, 7, 3]: the face's normal, its edges ab, bc, ca (the sum of the normals of the faces sharing the edge)
    and its corners a, b, c (the sum of the incident faces' normals weighted by their angles there). The sign
    of (p - c) · n, n the pseudo-normal of the feature that p's closest point c lies on, tells inside from
    outside for a watertight mesh. Computed in float64 (``edges``: :func:`edge_groups` of the faces, if known);
    a degenerate face has a zero normal. The host reference of ``kernels.mesh_colliders.pseudo_normals_kernel``."""
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    edges = edge_groups(f) if edges is None else edges
    corners = p[f]  # [t, 3, 3]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normal, axis=1)
    normal = np.divide(normal, length[:, None], out=np.zeros_like(normal), where=length[:, None] > 0.0)
    # The angle of each face at each of its corners.
    u = np.roll(corners, -1, axis=1) - corners
    w = np.roll(corners, -2, axis=1) - corners
    nu, nw = np.linalg.norm(u, axis=2), np.linalg.norm(w, axis=2)
    ok = (nu > 0.0) & (nw > 0.0)
    cosine = np.einsum("tki,tki->tk", u, w) / np.where(ok, nu * nw, 1.0)
    angle = np.where(ok, np.arccos(np.clip(cosine, -1.0, 1.0)), 0.0)
    edge = np.empty((len(f), 3, 3))
    vertex = np.empty((len(f), 3, 3))
    groups = int(edges.max()) + 1
    for axis in range(3):  # sums by bincount: faces sharing an edge, faces around a vertex
        by_edge = np.bincount(edges.reshape(-1), weights=np.repeat(normal[:, axis], 3), minlength=groups)
        edge[:, :, axis] = by_edge[edges]
        by_vertex = np.bincount(f.reshape(-1), weights=(angle * normal[:, axis, None]).reshape(-1), minlength=len(p))
        vertex[:, :, axis] = by_vertex[f]
    out = np.concatenate([normal[:, None, :], edge, vertex], axis=1)
    norm = np.linalg.norm(out, axis=2, keepdims=True)
    out = np.divide(out, norm, out=np.zeros_like(out), where=norm > 0.0)
    return out.astype(np.float32)


def make_mesh_cache(model, colliders: list) -> MeshCache:
    """The device struct of the mesh colliders' pseudo-normals and every particle's candidate cache (one row per
    mesh collider that is not signed by its winding number; tiny arrays when there is none)."""
    device, count = model.device, model.shape_count
    radius = float(model.particle_radius.numpy().max()) if model.particle_count else 0.0
    cached = [c for c in colliders if not c.info.winding_number]
    slot = np.full(count, -1, dtype=np.int32)
    reach = np.zeros(count, dtype=np.float32)
    margin = np.zeros(count, dtype=np.float32)
    offset = np.zeros(count, dtype=np.int32)
    start = 0
    for k, c in enumerate(cached):
        c.slot, c.normal_offset = k, start
        thickness = model.shapes[c.index].thickness
        slot[c.index], offset[c.index] = k, start
        # R: what the response and collide can touch (one-sided: its depth, up to which behind it is inside).
        reach[c.index] = c._range[0] if c.info.sides == "one_sided" else radius + thickness
        margin[c.index] = 0.25 * (radius + thickness) if c.info.cache_margin is None else c.info.cache_margin
        start += FACE_NORMALS * len(c.info.faces)
    rows, size = max(1, len(cached)), model.state_size if cached else 1
    candidates = max([c.info.cache_candidates for c in cached], default=1)
    cache = MeshCache()
    cache.slot = wp.array(slot, dtype=wp.int32, device=device)
    cache.reach = wp.array(reach, dtype=wp.float32, device=device)
    cache.margin = wp.array(margin, dtype=wp.float32, device=device)
    cache.normal_offset = wp.array(offset, dtype=wp.int32, device=device)
    cache.normals = wp.zeros(max(1, start), dtype=wp.vec3f, device=device)
    cache.ref = wp.zeros((rows, size), dtype=wp.vec3f, device=device)
    cache.side = wp.zeros((rows, size), dtype=wp.int32, device=device)  # every entry invalid: a first full query
    cache.count = wp.zeros((rows, size), dtype=wp.int32, device=device)
    cache.face = wp.zeros((rows, size, candidates), dtype=wp.int32, device=device)
    cache.overflow = wp.zeros(max(1, model.world_count), dtype=wp.int32, device=device)
    cache.refreshes = wp.zeros(max(1, model.world_count), dtype=wp.int32, device=device)
    model.shape_arrays.cache = cache
    for c in cached:
        c.update_pseudo_normals()
    return cache


def mesh_cache_counts(model) -> dict[str, np.ndarray]:
    """The mesh cache's counters since finalize (reads the device), per world, int64: ``refreshes`` (full BVH
    queries made with the cache on, including each particle's first) and ``overflow`` (full queries because a
    particle had more than ``cache_candidates`` triangles within reach plus margin)."""
    cache = model.shape_arrays.cache
    worlds = model.world_count
    return {"refreshes": cache.refreshes.numpy()[:worlds].astype(np.int64),
            "overflow": cache.overflow.numpy()[:worlds].astype(np.int64)}


def make_mesh_colliders(model) -> list:
    """The :class:`MeshCollider` of every mesh collider of ``model`` (called at finalize), with its mesh id and
    query range written into the model's collider arrays."""
    colliders = [MeshCollider(model, i, s.mesh) for i, s in enumerate(model.shapes) if s.kind == "mesh"]
    radius = float(model.particle_radius.numpy().max()) if model.particle_count else 0.0
    for c in colliders:
        thickness = model.shapes[c.index].thickness
        if c._range[0] <= radius + thickness:
            raise ConfigError(f"mesh collider {c.name!r}: its depth ({c._range[0]:.4g} m) must exceed the particle "
                              f"radius plus its thickness ({radius + thickness:.4g} m), or contacts would be missed: "
                              "pass a larger depth")
        _write_row(model.shape_arrays.mesh, c.index, c.mesh.id)
        _write_row(model.shape_arrays.size, c.index, (*c._range, 0.0))
        _write_row(model.shape_arrays.lower, c.index, c._bounds[0])
        _write_row(model.shape_arrays.upper, c.index, c._bounds[1])
    make_mesh_cache(model, colliders)
    return colliders


def _write_row(array: wp.array, index: int, value) -> None:
    """Write entry ``index`` of a device array (a host round trip of the whole array: colliders are few)."""
    values = array.numpy()
    values[index] = value
    array.assign(values)


def advance_mesh_colliders(model, t0: float, t1: float) -> None:
    """Put every mesh collider with time-sampled points at its points of time ``t1`` [s], moving with the
    velocity of their change from ``t0`` (a frame's start and end). Nothing happens without such a mesh."""
    for collider in getattr(model, "mesh_colliders", ()):
        if collider.info.sampled and t1 > t0:
            collider.set_points(collider.info.points_at(t1),
                                velocities=(collider.info.points_at(t1) - collider.info.points_at(t0)) / (t1 - t0))
