"""The normals :class:`~warpspring.io.usd.UsdWriter` writes every frame, in a fixed order (no atomics: a rerun
writes the same bytes): per vertex, area-weighted over the triangles (:func:`vertex_normals`; the device gathers a
cloth's, :mod:`warpspring.kernels.geometry`), with a fallback where a vertex's faces cancel or have no area
(:func:`fallback_normals`, :func:`cancelled_vertices`); per face or per smoothing group of face-vertices, so that a
USD input's hard edges stay hard (:class:`FaceNormals`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def vertex_normals(x: np.ndarray, faces: np.ndarray, up_axis: str, previous: np.ndarray | None = None) -> np.ndarray:
    """Area-weighted unit vertex normals of triangles ``faces`` at vertices ``x`` [v, 3], by a host product (a fixed
    order); a vertex whose faces cancel or have no area falls back as :func:`fallback_normals` says (``previous``:
    the normals written the frame before, [v, 3], or ``None``). Shape [v, 3]."""
    corner = x[faces]
    face_normal = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])  # length 2 × area
    normal = np.zeros_like(x)
    total = np.zeros(len(x))  # the lengths summed: what the normal would be without cancellation
    face_length = np.linalg.norm(face_normal, axis=1)
    for k in range(3):
        np.add.at(normal, faces[:, k], face_normal)
        np.add.at(total, faces[:, k], face_length)
    length = np.linalg.norm(normal, axis=1)
    normal = np.divide(normal, length[:, None], out=np.zeros_like(normal), where=length[:, None] > 0.0)
    cancelled = np.flatnonzero(~(length > _CANCELLED * total))  # opposite faces, or no area around it
    if len(cancelled):
        normal[cancelled] = fallback_normals(x, faces, cancelled, up_axis,
                                             None if previous is None else previous[cancelled])
    return normal


def fallback_normals(x: np.ndarray, faces: np.ndarray, vertices: np.ndarray, up_axis: str,
                     previous: np.ndarray | None = None) -> np.ndarray:
    """Unit normals for ``vertices`` whose summed face normals cancel (two faces of the same corners with
    opposite winding, as when two quads triangulate to one triangle both ways) or vanish (faces of no area):
    the normal of the vertex's first face (lowest index) of nonzero area; where it has none, its ``previous``
    frame's normal; where there is none, the up axis. Never a zero vector.

    Args:
        x: positions [m], shape [n, 3].
        faces: triangles, shape [t, 3] (indices into ``x``); those of the vertices suffice, in their order.
        vertices: the vertices to find normals for, shape [k].
        up_axis: "Y" or "Z", the last resort.
        previous: the vertices' normals of the frame before, shape [k, 3], or ``None``.

    Returns:
        Unit normals, shape [k, 3].
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    x = np.asarray(x, dtype=np.float64)
    corner = x[faces]
    face_normal = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    face_length = np.linalg.norm(face_normal, axis=1)
    usable = np.isfinite(face_length) & (face_length > 0.0)
    slot = np.full(len(x), -1, dtype=np.int64)
    slot[vertices] = np.arange(len(vertices))
    first = np.full(len(vertices), len(faces), dtype=np.int64)
    for k in range(3):
        s = slot[faces[:, k]]
        chosen = usable & (s >= 0)
        np.minimum.at(first, s[chosen], np.flatnonzero(chosen))
    out = np.zeros((len(vertices), 3))
    out[:, 1 if up_axis == "Y" else 2] = 1.0
    if previous is not None:
        previous = np.asarray(previous, dtype=np.float64)
        kept = np.linalg.norm(previous, axis=1) > 0.5  # a unit normal written before
        out[kept] = previous[kept]
    found = first < len(faces)
    out[found] = face_normal[first[found]] / face_length[first[found], None]
    return out


def cancelled_vertices(faces: np.ndarray) -> np.ndarray:
    """The vertices every incident triangle of which is cancelled by another of the same three vertices with the
    opposite winding: their area-weighted normal is zero at every frame. Shape [k], ascending.

    Args:
        faces: triangles, shape [t, 3].
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(faces):
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(faces, axis=1, kind="stable")
    key = np.take_along_axis(faces, order, axis=1)  # the corners, sorted
    sign = np.where((order[:, 1] - order[:, 0]) % 3 == 1, 1, -1)  # +1: the sorting was a rotation (same winding)
    rows = np.column_stack([faces.ravel(), np.repeat(key, 3, axis=0)])  # per corner: vertex, triangle's corners
    unique, inverse = np.unique(rows, axis=0, return_inverse=True)
    total = np.zeros(len(unique), dtype=np.int64)
    np.add.at(total, inverse.ravel(), np.repeat(sign, 3))
    return np.setdiff1d(np.unique(faces), unique[total != 0, 0])


#: Relative length below which a vertex's summed face normals count as cancelled (float64 rounding is ~1e-16).
_CANCELLED = 1.0e-9


@dataclass
class FaceNormals:
    """A surface's polygons in authored face-vertex order, for normals per face (``uniform``) or per face-vertex
    (``faceVarying``, one per smoothing group): ``sign`` −1 where the authored order is left-handed in world space
    (a left-handed mesh, or a mirroring transform, not both)."""

    counts: np.ndarray  # [p] vertices per face
    indices: np.ndarray  # [sum(counts)] face-vertex order, as authored
    sign: float
    smoothing: np.ndarray | None  # [sum(counts)] smoothing group per face-vertex, or None

    def normals(self, x: np.ndarray, up_axis: str, per_face: bool) -> np.ndarray:
        """Unit normals facing the front at vertices ``x`` [v, 3]: per face [p, 3] (``per_face``), else per
        face-vertex [sum(counts), 3], each the area-weighted sum over its smoothing group's faces (Newell's
        vector area; a fixed-order sum). A zero sum falls back to the face's normal, then the up axis."""
        offsets = np.concatenate(([0], np.cumsum(self.counts)[:-1]))
        face = np.repeat(np.arange(len(self.counts)), self.counts)
        following = np.arange(1, len(self.indices) + 1)
        following[offsets + self.counts - 1] = offsets
        p = x[self.indices] - x[self.indices[offsets]][face]  # about each face's first vertex (no cancellation)
        area = self.sign * np.add.reduceat(np.cross(p, p[following]), offsets, axis=0)  # 2 × vector area
        up = np.zeros(3)
        up[1 if up_axis == "Y" else 2] = 1.0
        face_normal = unit_or(area, up)
        if per_face:
            return face_normal
        groups = self.smoothing
        count = int(groups.max()) + 1 if len(groups) else 0
        summed = np.stack([np.bincount(groups, weights=area[face, k], minlength=count) for k in range(3)], axis=1)
        return unit_or(summed[groups], face_normal[face])


def unit_or(vectors: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """``vectors`` normalised, ``fallback`` (broadcast) where one is zero or not finite."""
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    good = np.isfinite(length) & (length > 0.0)
    return np.where(good, vectors / np.where(good, length, 1.0), fallback)
