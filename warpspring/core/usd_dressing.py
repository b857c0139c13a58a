"""What a USD mesh prim carries besides its geometry, read so that a simulated surface is written back dressed like
its input (:class:`UsdDressing`, :func:`read_dressing`, by :func:`~warpspring.core.mesh_files.read_usd_mesh`): every
primvar as authored, ``GeomSubset`` prims with their family names and material bindings, ``subdivisionScheme``,
``orientation``, the prim's path, name and kind, and how its normals are interpolated, with the smoothing groups
that keep its hard edges hard (:func:`smoothing_groups`: edges across which the authored normals differ, and
infinitely sharp creases). pxr and scipy load inside the functions that need them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SMOOTH_TOLERANCE", "UsdDressing", "UsdPrimvar", "UsdSubset", "int_array", "read_dressing", "smoothing_groups"]


@dataclass(frozen=True)
class UsdPrimvar:
    """One authored primvar of a mesh prim, as authored (no unit or axis conversion).

    Attributes:
        name: its name without the ``primvars:`` namespace (``"st"``, ``"panel"``).
        type_name: its USD value type name (``"texCoord2f[]"``: the role is kept).
        interpolation: ``constant``, ``uniform``, ``vertex``, ``varying`` or ``faceVarying``.
        value: the authored value (at the time read): a numpy array for an array type (one row per element;
            strings and tokens as a numpy string array, asset paths as a list of strings), else the value as
            pxr gives it in Python (a float, a string, a ``Gf.Vec3d``, ...).
        indices: ``[n]`` int32 for an indexed primvar, else ``None``.
        element_size: the primvar's elementSize (1 unless authored).
    """

    name: str
    type_name: str
    interpolation: str
    value: object
    indices: np.ndarray | None = None
    element_size: int = 1


@dataclass(frozen=True)
class UsdSubset:
    """One authored ``GeomSubset`` of a mesh prim.

    Attributes:
        name: the subset prim's name.
        element_type: ``face`` (or ``point``, ``edge``, ...), as authored.
        family: its ``familyName`` (``"materialBind"``), ``""`` when none is authored.
        family_type: the family's type on the mesh (``nonOverlapping``, ``partition``, ``unrestricted``).
        indices: ``[n]`` int32 element indices, as authored.
        material: path of the Material its direct binding targets in the source, or ``None``.
    """

    name: str
    element_type: str
    family: str
    family_type: str
    indices: np.ndarray
    material: str | None = None


@dataclass(frozen=True)
class UsdDressing:
    """What a mesh prim carries besides its geometry, kept so that the output is dressed like the input.

    Attributes:
        source: the file read.
        prim_name: the mesh prim's name.
        kind: its model kind (``""`` when none).
        subdivision_scheme: its ``subdivisionScheme`` (``catmullClark`` when not authored, USD's fallback).
        orientation: its ``orientation`` as authored (``rightHanded`` or ``leftHanded``).
        mirrored: whether its world transform mirrors (the reader's faces are reversed when
            ``orientation`` is left-handed xor this).
        face_vertex_indices: ``[sum(polygon_counts)]`` int32: ``faceVertexIndices`` as authored (the order a
            faceVarying primvar follows).
        primvars: every authored primvar (:class:`UsdPrimvar`) except ``normals`` (recomputed every frame).
        subsets: every ``GeomSubset`` (:class:`UsdSubset`).
        material: path of the Material the mesh's own direct binding targets, or ``None``.
        prim_path: the mesh prim's path in the source (where a layer over the source overrides it).
        normals: the interpolation of the normals to write: the authored one (``vertex``, ``uniform`` or
            ``faceVarying``; ``varying`` and ``constant`` as ``vertex``), ``faceVarying`` where hard creases are
            authored, ``None`` when the prim authors neither (vertex normals).
        normals_primvar: whether the authored normals are ``primvars:normals`` (which USD prefers over the
            ``normals`` attribute), so that a layer over the source overrides that one.
        normals_indexed: whether the authored ``primvars:normals`` is indexed (a layer over it blocks the indices).
        smoothing: ``[sum(polygon_counts)]`` int32 for ``faceVarying`` normals: per face-vertex (authored order),
            its smoothing group; the corners of one group share one normal, the area-weighted sum of their faces'
            (:func:`smoothing_groups`); ``None`` otherwise.
    """

    source: str
    prim_name: str
    kind: str
    subdivision_scheme: str
    orientation: str
    mirrored: bool
    face_vertex_indices: np.ndarray
    primvars: tuple = ()
    subsets: tuple = ()
    material: str | None = None
    prim_path: str = ""
    normals: str | None = None
    normals_primvar: bool = False
    normals_indexed: bool = False
    smoothing: np.ndarray | None = None

    @property
    def materials(self) -> list[str]:
        """The source paths of every Material bound (by the mesh or a subset), without repeats, in order."""
        found = [self.material] + [s.material for s in self.subsets]
        return list(dict.fromkeys(m for m in found if m))


def read_dressing(mesh, file: str, code, authored: np.ndarray, mirrored: bool, counts: np.ndarray) -> UsdDressing:
    """What a ``UsdGeom.Mesh`` carries besides its geometry, read at time code ``code`` (:class:`UsdDressing`).

    Args:
        mesh: the mesh prim (a ``UsdGeom.Mesh``) of ``file``.
        file: the file read (kept as the dressing's source).
        code: the ``Usd.TimeCode`` to read values at.
        authored: ``[sum(counts)]`` its faceVertexIndices as authored.
        mirrored: whether its world transform mirrors.
        counts: ``[p]`` its faceVertexCounts.
    """
    from pxr import Usd, UsdGeom, UsdShade  # optional: usd-core

    prim = mesh.GetPrim()
    primvars = []
    for primvar in UsdGeom.PrimvarsAPI(prim).GetAuthoredPrimvars():
        name = str(primvar.GetPrimvarName())
        if name == "normals" or not primvar.HasAuthoredValue():
            continue  # normals are recomputed every frame
        raw = primvar.Get(code)
        value = np.array(raw) if primvar.GetTypeName().isArray else raw  # a scalar (Gf.Vec3d, str, ...) as is
        if isinstance(value, np.ndarray) and value.dtype == object:  # asset paths
            value = [str(getattr(v, "path", v)) for v in raw]
        indices = primvar.GetIndices(code) if primvar.IsIndexed() else None
        primvars.append(UsdPrimvar(name=name, type_name=str(primvar.GetTypeName()),
                                   interpolation=str(primvar.GetInterpolation()), value=value,
                                   indices=None if indices is None else int_array(indices).astype(np.int32),
                                   element_size=int(primvar.GetElementSize())))
    imageable = UsdGeom.Imageable(prim)
    subsets = []
    for subset in UsdGeom.Subset.GetAllGeomSubsets(imageable):
        family = str(subset.GetFamilyNameAttr().Get() or "")
        subsets.append(UsdSubset(
            name=subset.GetPrim().GetName(), element_type=str(subset.GetElementTypeAttr().Get()), family=family,
            family_type=str(UsdGeom.Subset.GetFamilyType(imageable, family)) if family else "",
            indices=int_array(subset.GetIndicesAttr().Get(code)).astype(np.int32),
            material=_bound_material(UsdShade, subset.GetPrim())))
    normals, interpolation, as_primvar, indexed = None, None, False, False
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
    if primvar and primvar.HasAuthoredValue():
        normals, interpolation = primvar.ComputeFlattened(code), str(primvar.GetInterpolation())
        as_primvar, indexed = True, primvar.IsIndexed()
    elif mesh.GetNormalsAttr().HasAuthoredValue():
        normals, interpolation = mesh.GetNormalsAttr().Get(code), str(mesh.GetNormalsInterpolation())
    hard = _hard_edges(mesh, code)
    if interpolation in ("vertex", "varying", "constant"):
        interpolation = "vertex"
    corner_normals = None
    if interpolation == "faceVarying" and normals is not None and len(normals) == len(authored):
        corner_normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    elif interpolation == "faceVarying":
        interpolation = "vertex"  # a faceVarying value of the wrong length: USD ignores it too
    smoothing = None
    if interpolation == "faceVarying" or len(hard):
        interpolation = "faceVarying"
        smoothing = smoothing_groups(counts, authored, corner_normals=corner_normals, hard_edges=hard)
    return UsdDressing(
        source=file, prim_name=prim.GetName(), kind=str(Usd.ModelAPI(prim).GetKind() or ""),
        subdivision_scheme=str(mesh.GetSubdivisionSchemeAttr().Get()),
        orientation=str(mesh.GetOrientationAttr().Get()), mirrored=mirrored, face_vertex_indices=authored,
        primvars=tuple(primvars), subsets=tuple(subsets), material=_bound_material(UsdShade, prim),
        prim_path=str(prim.GetPath()), normals=interpolation, normals_primvar=as_primvar,
        normals_indexed=bool(indexed), smoothing=smoothing)


def _hard_edges(mesh, code) -> np.ndarray:
    """``[e, 2]`` vertex pairs (smaller first) of the edges an infinitely sharp crease marks (sharpness ≥
    ``UsdGeom.Mesh.SHARPNESS_INFINITE``): edges that normals do not smooth across."""
    from pxr import UsdGeom  # optional: usd-core

    indices = int_array(mesh.GetCreaseIndicesAttr().Get(code))
    lengths = int_array(mesh.GetCreaseLengthsAttr().Get(code))
    sharpness = np.asarray(mesh.GetCreaseSharpnessesAttr().Get(code) or [], dtype=np.float64)
    if not len(indices) or not len(lengths) or lengths.sum() != len(indices):
        return np.zeros((0, 2), dtype=np.int64)
    crease = np.repeat(np.arange(len(lengths)), lengths)
    same = crease[1:] == crease[:-1]  # consecutive vertices of one crease: an edge
    a, b = indices[:-1][same], indices[1:][same]
    if len(sharpness) == len(lengths):  # one sharpness per crease
        edge_sharpness = sharpness[crease[:-1][same]]
    elif len(sharpness) == len(a):  # one per edge
        edge_sharpness = sharpness
    else:
        return np.zeros((0, 2), dtype=np.int64)
    hard = edge_sharpness >= UsdGeom.Mesh.SHARPNESS_INFINITE
    return np.stack([np.minimum(a, b)[hard], np.maximum(a, b)[hard]], axis=1)


#: Authored corner normals closer than this (unit vectors, Euclidean) count as one smooth normal.
SMOOTH_TOLERANCE = 1.0e-4


def smoothing_groups(counts: np.ndarray, indices: np.ndarray, *, corner_normals: np.ndarray | None = None,
                     hard_edges: np.ndarray | None = None) -> np.ndarray:
    """The smoothing groups of a polygon mesh's face-vertices: two faces that share an edge smooth across it at
    one of its vertices when their normals there agree (authored ``corner_normals`` within
    :data:`SMOOTH_TOLERANCE` after normalising; any, when none are given) and the edge is not hard; a group is
    a connected set of face-vertices of one vertex. An edge of more than two faces (non-manifold) is hard.

    Args:
        counts: ``[p]`` vertices per face.
        indices: ``[sum(counts)]`` the faces' vertices, in order (face-vertex order: a faceVarying primvar's).
        corner_normals: ``[sum(counts), 3]`` authored normals per face-vertex, or ``None``.
        hard_edges: ``[e, 2]`` vertex pairs of hard edges (either order), or ``None``.

    Returns:
        ``[sum(counts)]`` int32: a group index per face-vertex, 0 .. groups - 1.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    counts = np.asarray(counts, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    n = len(indices)
    offsets = np.concatenate(([0], np.cumsum(counts)[:-1])).astype(np.int64)
    following = np.arange(1, n + 1)
    following[offsets + counts - 1] = offsets  # the next face-vertex around each face
    a, b = indices, indices[following]
    span = int(indices.max()) + 1 if n else 1
    key = np.minimum(a, b) * span + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    run = np.flatnonzero(np.diff(sorted_key) == 0)  # positions i where half-edges i, i + 1 share an edge
    twin = ((run == 0) | (sorted_key[np.maximum(run - 1, 0)] != sorted_key[run])) & (  # exactly two half-edges
        (run + 2 >= n) | (sorted_key[np.minimum(run + 2, n - 1)] != sorted_key[run]))
    h1, h2 = order[run[twin]], order[run[twin] + 1]
    keep = a[h1] != b[h1]  # a degenerate edge joins nothing
    if hard_edges is not None and len(hard_edges):
        hard = np.asarray(hard_edges, dtype=np.int64).reshape(-1, 2)
        hard_key = np.minimum(hard[:, 0], hard[:, 1]) * span + np.maximum(hard[:, 0], hard[:, 1])
        keep &= ~np.isin(key[h1], hard_key)
    h1, h2 = h1[keep], h2[keep]
    same_way = a[h1] == a[h2]  # both faces walk the edge the same way (inconsistent winding)
    first = np.concatenate([h1, following[h1]])  # the face-vertex of each end in face 1 ...
    second = np.concatenate([np.where(same_way, h2, following[h2]), np.where(same_way, following[h2], h2)])  # ... in 2
    if corner_normals is not None:
        unit = np.asarray(corner_normals, dtype=np.float64).reshape(-1, 3)
        length = np.linalg.norm(unit, axis=1, keepdims=True)
        unit = np.divide(unit, length, out=np.zeros_like(unit), where=length > 0.0)
        agree = np.linalg.norm(unit[first] - unit[second], axis=1) <= SMOOTH_TOLERANCE
        first, second = first[agree], second[agree]
    graph = coo_matrix((np.ones(len(first)), (first, second)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int32)


def _bound_material(UsdShade, prim) -> str | None:
    """The path of the Material a prim's direct (all-purpose) binding targets, or None."""
    targets = UsdShade.MaterialBindingAPI(prim).GetDirectBindingRel().GetTargets()
    return str(targets[0]) if targets else None


def int_array(value) -> np.ndarray:
    """An authored int array as a 1-d int64 array (empty when not authored)."""
    if value is None:
        return np.zeros(0, dtype=np.int64)
    return np.asarray(value, dtype=np.int64).reshape(-1)
