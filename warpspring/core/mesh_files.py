"""Read meshes from files for the builder's recipes (cloth meshes, soft bodies, mesh colliders, emitters): one
polygon mesh from a USD file (``.usda``, ``.usdc``, ``.usd``: :func:`read_usd_mesh`, its time samples
:func:`read_usd_mesh_samples`), or a file of any other format trimesh reads (:func:`load_mesh_file`). pxr and
trimesh are optional and slow to import: each loads inside the function that needs it.

Reading a USD mesh, what is applied, in this order, so that the result is in warpspring's frame and units:

* time: points (and transforms, face-set indices) are read at ``time``; by default at the stage's start
  time code when the stage authors a time range, else at the earliest time sample of each attribute
  (an attribute without samples gives its default value). The topology must not change over time;
* orientation: a mesh authored ``orientation = "leftHanded"`` has each face's vertex order reversed (its
  first vertex kept first), so every face of the result is right-handed: its normal by the right-hand rule
  points to the side the file calls the front. A world transform that mirrors (negative determinant)
  reverses the faces as well, as renderers do, so the front stays the front;
* world transform: the prim's local-to-world transform (every ``Xform`` above it), in float64, with USD's
  row-vector convention ``p_world = p · M``;
* units: the stage's ``metersPerUnit``; a stage that does not author it is in centimetres (USD's
  fallback, 0.01), so its points are scaled by 0.01;
* up axis: the stage's ``upAxis`` ("Y" or "Z", USD's fallback "Y") turned into the requested one by a
  rotation of 90° about X: Y-up to Z-up maps (x, y, z) to (x, −z, y), Z-up to Y-up maps (x, y, z) to
  (x, z, −y).

The faces are kept as authored (``polygon_counts``, ``polygon_indices``) and triangulated for the
simulation: a triangle stays; a quad is split along its shorter diagonal (a folded quad bends along that
one; a concave quad along the one diagonal that lies inside it); a polygon of more vertices is fanned from
its first vertex when it is convex in its own plane, and refused otherwise (triangulate it in the DCC
tool). ``GeomSubset`` prims of element type ``face`` are read as face sets.

What the simulation ignores, and the output keeps (:class:`UsdDressing`, written back by
:class:`~warpspring.io.usd.UsdWriter`): every primvar (UVs by any name, custom ones), ``GeomSubset`` prims
with their family names and material bindings, ``subdivisionScheme`` (the cage is simulated as it is, never
subdivided), ``orientation``, the prim's name and kind; authored normals give the interpolation of the
normals written every frame, and where they differ across an edge (or an infinitely sharp crease marks it)
that edge stays hard (:func:`smoothing_groups`). What is ignored altogether: holes (``holeIndices``),
velocities, ``doubleSided`` and any other prim of the file. Vertices that no face uses are kept.

Every input is checked to be a regular file before it is opened (:func:`check_regular_file`,
:func:`open_regular_file`): a named pipe, a device or a socket would block a reader or feed it forever. A USD
file's own layers — sublayers, references and payloads, transitively — are checked the same way before the
stage composes them (:func:`check_usd_layers`); value clips' asset paths are not (no scene reads clips).

Every problem is raised as :class:`~warpspring.errors.ConfigError`, one line naming the file and (where
known) the prim, what is wrong and how to fix it.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import stat
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .usd_dressing import UsdDressing, UsdPrimvar, UsdSubset, int_array, read_dressing, smoothing_groups

__all__ = ["USD_EXTENSIONS", "UsdDressing", "UsdMesh", "UsdPrimvar", "UsdSubset", "check_regular_file", "check_usd_layers",
           "convert_up_axis", "load_mesh_file", "open_regular_file", "open_usd_stage", "read_usd_mesh",
           "read_usd_mesh_samples", "smoothing_groups"]

USD_EXTENSIONS = (".usd", ".usda", ".usdc")  # mesh files read through USD, not trimesh

_UP_AXES = ("Y", "Z")
_LISTED_MESHES = 5


@dataclass(frozen=True)
class UsdMesh:
    """A polygon mesh read from a USD file, in warpspring's frame: world space, metres, the requested up
    axis, right-handed faces.

    Attributes:
        path: the file read, as given.
        prim: the path of the mesh prim read (``"/World/cloth"``).
        vertices: ``[v, 3]`` float64, metres: every point of the mesh (also those no face uses), in world
            space with the requested up axis, in the file's point order.
        polygon_counts: ``[p]`` int32: vertices per face (each >= 3), in the file's face order.
        polygon_indices: ``[sum(polygon_counts)]`` int32, indices into ``vertices``: the vertices of each
            face in turn, as authored, except that a face of a left-handed mesh (or of a mirroring
            transform) has its order reversed behind its first vertex, so that every face is
            right-handed.
        triangles: ``[t, 3]`` int32, indices into ``vertices``: the triangulation the simulation uses,
            right-handed, the triangles of face 0 first, then those of face 1, ...; a face of ``n``
            vertices gives ``n - 2`` triangles.
        triangle_polygon: ``[t]`` int32: the face (index into ``polygon_counts``) each triangle comes from.
        face_sets: ``GeomSubset`` name -> int32 indices of faces (into ``polygon_counts``), sorted and
            unique, for the subsets of element type ``face``.
        dressing: the prim's primvars, subsets, bindings, subdivision scheme, orientation, name and kind
            (:class:`UsdDressing`), or ``None``.
    """

    path: str
    prim: str
    vertices: np.ndarray
    polygon_counts: np.ndarray
    polygon_indices: np.ndarray
    triangles: np.ndarray
    triangle_polygon: np.ndarray
    face_sets: dict[str, np.ndarray] = field(default_factory=dict)
    dressing: UsdDressing | None = None

    @property
    def num_vertices(self) -> int:
        """Number of vertices."""
        return int(self.vertices.shape[0])

    @property
    def num_polygons(self) -> int:
        """Number of authored faces."""
        return int(self.polygon_counts.shape[0])

    @property
    def num_triangles(self) -> int:
        """Number of triangles of the triangulation."""
        return int(self.triangles.shape[0])


def read_usd_mesh(path: str | os.PathLike[str], *, prim: str | None = None, up_axis: str = "Z",
                  time: float | None = None) -> UsdMesh:
    """Read one polygon mesh from a USD file, in world space, metres and the requested up axis.

    Args:
        path: the USD file (``.usda``, ``.usdc`` or ``.usd``).
        prim: path of the ``Mesh`` prim to read (``"/World/cloth"``); ``None`` takes the one mesh of the
            file and refuses a file of several.
        up_axis: the up axis of the result, ``"Z"`` (warpspring's) or ``"Y"``.
        time: the USD time code [stage time codes, i.e. frames at the stage's ``timeCodesPerSecond``] to
            read points and transforms at; ``None``: the stage's start time code when the stage authors a
            time range, else each attribute's earliest time sample (or its default value).

    Returns:
        the mesh; see :class:`UsdMesh` and this module's description of what is applied and ignored.

    Raises:
        ConfigError: one line naming the file (and the prim) for a missing or unreadable file, a file
            without a mesh or with several (and ``prim=None``), a prim that does not exist or is not a
            mesh, topology that changes over time, non-finite points, bad topology (an index out of
            range, a face of fewer than 3 vertices, counts that do not add up to the indices, no faces),
            a non-convex polygon of more than 4 vertices, face-set indices out of range, or an unknown
            ``up_axis``.
    """
    file = os.fspath(path)
    axis = up_axis.upper() if isinstance(up_axis, str) else up_axis
    if axis not in _UP_AXES:
        raise ConfigError(f"{file}: up_axis must be \"Y\" or \"Z\", got {up_axis!r}; "
                          f"pass up_axis=\"Z\" (warpspring's frame) or up_axis=\"Y\"")

    from pxr import UsdGeom  # optional: usd-core (slow to import)

    stage = _open_stage(file)
    mesh_prim = _find_mesh(stage, file, prim)
    where = f"{file}, prim {mesh_prim.GetPath()}"
    code = _time_code(stage, time, where)
    mesh = UsdGeom.Mesh(mesh_prim)

    _constant_topology(mesh.GetFaceVertexCountsAttr(), "faceVertexCounts", where)
    _constant_topology(mesh.GetFaceVertexIndicesAttr(), "faceVertexIndices", where)
    counts = int_array(mesh.GetFaceVertexCountsAttr().Get(code))
    indices = int_array(mesh.GetFaceVertexIndicesAttr().Get(code))
    raw_points = mesh.GetPointsAttr().Get(code)
    points = (np.zeros((0, 3)) if raw_points is None
              else np.asarray(raw_points, dtype=np.float64).reshape(-1, 3))
    _check_topology(points, counts, indices, where)

    matrix = np.array(UsdGeom.Xformable(mesh_prim).ComputeLocalToWorldTransform(code), dtype=np.float64)
    if not np.all(np.isfinite(matrix)):
        raise ConfigError(f"{where}: its world transform is not finite (NaN or infinite); fix the "
                          f"transforms (xformOps) of the prim and of the Xforms above it")
    scale = float(UsdGeom.GetStageMetersPerUnit(stage))
    if not (math.isfinite(scale) and scale > 0.0):
        raise ConfigError(f"{where}: the stage's metersPerUnit is {scale!r}; author a positive "
                          f"metersPerUnit (1 for metres, 0.01 for centimetres)")
    world = (np.c_[points, np.ones(len(points))] @ matrix)[:, :3] * scale
    vertices = convert_up_axis(world, str(UsdGeom.GetStageUpAxis(stage)), axis)
    if not np.all(np.isfinite(vertices)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(vertices), axis=1))[0])
        raise ConfigError(f"{where}: vertex {bad} is not finite after the world transform; "
                          f"fix the transforms (xformOps) of the prim and of the Xforms above it")

    left_handed = mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    mirrored = bool(np.linalg.det(matrix[:3, :3]) < 0.0)
    offsets = np.concatenate(([0], np.cumsum(counts)[:-1])).astype(np.int64)
    authored = indices.astype(np.int32)
    if left_handed != mirrored:
        indices = _reverse_faces(counts, indices, offsets)

    triangles, triangle_polygon = _triangulate(vertices, counts, indices, offsets, where)
    face_sets = _face_sets(mesh_prim, len(counts), code, where)
    dressing = read_dressing(mesh, file, code, authored, mirrored, counts)
    return UsdMesh(path=file, prim=str(mesh_prim.GetPath()), vertices=vertices,
                   polygon_counts=counts.astype(np.int32), polygon_indices=indices.astype(np.int32),
                   triangles=triangles, triangle_polygon=triangle_polygon, face_sets=face_sets,
                   dressing=dressing)


def read_usd_mesh_samples(path: str | os.PathLike[str], *, prim: str | None = None, up_axis: str = "Z"):
    """The time samples of a mesh prim's points, as :func:`read_usd_mesh` reads them at each (world space,
    metres, the requested up axis): (times [s] (time codes over the stage's ``timeCodesPerSecond``), shape
    [k]; points [m], shape [k, v, 3]), or None when the points have fewer than two samples."""
    from pxr import UsdGeom  # optional: usd-core

    file = os.fspath(path)
    stage = _open_stage(file)
    mesh_prim = _find_mesh(stage, file, prim)
    codes = UsdGeom.Mesh(mesh_prim).GetPointsAttr().GetTimeSamples()
    if len(codes) < 2:
        return None
    rate = float(stage.GetTimeCodesPerSecond()) or 24.0
    points = np.stack([read_usd_mesh(file, prim=str(mesh_prim.GetPath()), up_axis=up_axis, time=c).vertices
                       for c in codes])
    return np.asarray(codes, dtype=np.float64) / rate, points


def load_mesh_file(path, *, what: str = "mesh"):
    """The ``trimesh.Trimesh`` in the file at ``path`` (any format trimesh reads, unprocessed: vertices in the
    file's order), or a one-line ConfigError naming the file."""
    import trimesh  # trimesh loads lazily

    path = os.fspath(path)
    if not os.path.exists(path):
        raise ConfigError(f"{what} file not found: {path}")
    check_regular_file(path, f"{what} file")
    try:
        return trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ConfigError(f"cannot read {what} file {path}: {exc}") from None


# ---------------------------------------------------------------------------------------------- input files

#: The most layers a USD mesh file may pull in (sublayers, references, payloads, transitively).
MAX_USD_LAYERS = 1000


def _kind(mode: int) -> str:
    """What a file that is not a regular file is, in words."""
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISSOCK, "a socket"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a regular file"


def check_regular_file(path: str | os.PathLike[str], what: str = "file") -> str:
    """``path`` (as a str) if it is a regular file (a symbolic link is followed); else a one-line ConfigError
    naming ``what`` and the path. Only a stat: a named pipe, a device or a socket is refused without being
    opened, so a reader that would block on it (or read it forever) never starts."""
    path = os.fspath(path)
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        raise ConfigError(f"{what} {path}: no such file; check the path") from None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{what} {path}: cannot read it ({getattr(exc, 'strerror', None) or exc})") from None
    if not stat.S_ISREG(mode):
        raise ConfigError(f"{what} {path}: is {_kind(mode)}, not a regular file; give the path of a file")
    return path


@contextlib.contextmanager
def open_regular_file(path: str | os.PathLike[str], what: str = "file"):
    """Open ``path`` for binary reading if it is a regular file, else a one-line ConfigError naming ``what``.
    It is opened without blocking and checked on the open descriptor (no window between check and open in
    which a pipe could take the file's place), then read as a normal file."""
    path = os.fspath(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
    except FileNotFoundError:
        raise ConfigError(f"{what} {path}: no such file; check the path") from None
    except IsADirectoryError:
        raise ConfigError(f"{what} {path}: is a folder, not a regular file; give the path of a file") from None
    except OSError as exc:
        raise ConfigError(f"{what} {path}: cannot read it ({exc.strerror or exc})") from None
    mode = os.fstat(fd).st_mode
    if not stat.S_ISREG(mode):
        os.close(fd)
        raise ConfigError(f"{what} {path}: is {_kind(mode)}, not a regular file; give the path of a file")
    if hasattr(os, "set_blocking"):
        os.set_blocking(fd, True)
    with open(fd, "rb") as file:
        yield file


def check_usd_layers(file: str) -> list:
    """Check that ``file`` and every layer it pulls in (sublayers, references and payloads, transitively; at
    most ``MAX_USD_LAYERS``) that exists is a regular file, before a stage composes them: each layer is
    opened on its own (``Sdf.Layer``, no composition) only after its path passed :func:`check_regular_file`,
    so a named pipe among them is refused instead of blocking the reader. A dependency that does not exist
    is left to USD (it warns and composes without it).

    Returns:
        the layers opened (``Sdf.Layer``): while the caller holds them, a stage opened on ``file`` reuses them.
    """
    from pxr import Sdf, Tf  # optional: usd-core

    check_regular_file(file, "USD file")
    pending, seen, layers = [os.path.abspath(file)], set(), []
    while pending:
        path = pending.pop()
        if path in seen:
            continue
        seen.add(path)
        if len(seen) > MAX_USD_LAYERS:
            raise ConfigError(f"{file}: pulls in more than {MAX_USD_LAYERS} layers (sublayers, references, "
                              "payloads); flatten it (usdcat --flatten)")
        try:
            layer = Sdf.Layer.FindOrOpen(path)
        except Tf.ErrorException as error:
            raise ConfigError(f"{file}: USD cannot open {'it' if path == os.path.abspath(file) else path} "
                              f"({_usd_reason(error)}); check that it is a valid .usda, .usdc or .usd file (open it "
                              "in usdview or run usdcat on it)") from None
        if layer is None:
            continue  # USD refuses it when the stage opens, with its own reason
        layers.append(layer)
        for asset in layer.GetCompositionAssetDependencies():
            if not asset or asset.startswith("anon:"):
                continue
            resolved = layer.ComputeAbsolutePath(asset.split(":SDF_FORMAT_ARGS:", 1)[0])
            if not resolved or not os.path.exists(resolved):
                continue
            check_regular_file(resolved, f"{file}: the layer {asset!r} it pulls in,")
            pending.append(os.path.abspath(resolved))
    return layers


# ---------------------------------------------------------------------------------------------- stage


def open_usd_stage(path: str | os.PathLike[str]):
    """The ``Usd.Stage`` of a USD file, its layers checked to be regular files first (:func:`check_usd_layers`);
    a one-line ConfigError naming the file when USD cannot open it."""
    return _open_stage(os.fspath(path))


def _open_stage(file: str):
    """The stage of ``file``; ConfigError for a missing or unreadable file."""
    from pxr import Tf, Usd  # optional: usd-core

    if not os.path.exists(file):
        raise ConfigError(f"{file}: no such file; check the path")
    if os.path.isdir(file):
        raise ConfigError(f"{file}: is a folder, not a USD file; give the path of a .usda, .usdc or "
                          f".usd file")
    layers = check_usd_layers(file)  # before the stage composes them: a named pipe among them would block it
    try:
        stage = Usd.Stage.Open(file)
    except Tf.ErrorException as error:
        raise ConfigError(f"{file}: USD cannot open it ({_usd_reason(error)}); check that it is a "
                          f"valid .usda, .usdc or .usd file (open it in usdview or run usdcat on it)") from None
    del layers  # the stage holds what it uses
    if stage is None:
        raise ConfigError(f"{file}: USD cannot open it; check that it is a valid .usda, .usdc or .usd "
                          f"file (open it in usdview or run usdcat on it)")
    return stage


def _usd_reason(error: BaseException) -> str:
    """USD's reasons in an error, on one line, without its call sites ("Error in '...' at line ...")."""
    text = str(error)
    pieces = re.split(r"Error in '[^']*' at line \d+ in file .*? : ", text)
    reasons: list[str] = []
    for piece in pieces:
        words = " ".join(piece.split()).strip()
        if words.startswith("'") and words.endswith("'") and len(words) >= 2:
            words = words[1:-1].strip()
        if words and words not in reasons:
            reasons.append(words)
    if len(reasons) > 1:
        reasons = [r for r in reasons if not r.startswith("Failed to open layer")] or reasons
    reason = "; ".join(reasons) or " ".join(text.split()) or type(error).__name__
    return reason if len(reason) <= 400 else reason[:397] + "..."


def _mesh_paths(stage) -> list[str]:
    """Paths of the active, defined mesh prims of the stage, in traversal order."""
    from pxr import UsdGeom  # optional: usd-core

    return [str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]


def _listed(paths: list[str]) -> str:
    """Up to five paths, comma separated, with a count of the rest."""
    shown = ", ".join(paths[:_LISTED_MESHES])
    more = len(paths) - _LISTED_MESHES
    return shown + (f" and {more} more" if more > 0 else "")


def _find_mesh(stage, file: str, prim: str | None):
    """The mesh prim to read: ``prim``, or the one mesh of the stage."""
    from pxr import Sdf, UsdGeom  # optional: usd-core

    if prim is None:
        meshes = _mesh_paths(stage)
        if not meshes:
            raise ConfigError(f"{file}: no mesh in the file (no active UsdGeom.Mesh prim); export the "
                              f"cloth as a polygon mesh")
        if len(meshes) > 1:
            raise ConfigError(f"{file}: {len(meshes)} meshes in the file ({_listed(meshes)}); choose one "
                              f"with prim = \"/path\" in the scene file (prim=\"/path\" in the API)")
        return stage.GetPrimAtPath(meshes[0])

    if not (isinstance(prim, str) and Sdf.Path.IsValidPathString(prim)
            and Sdf.Path(prim).IsAbsolutePath() and Sdf.Path(prim).IsPrimPath()):
        raise ConfigError(f"{file}: prim {prim!r} is not an absolute prim path; give one such as "
                          f"\"/World/cloth\"")
    found = stage.GetPrimAtPath(prim)
    if not found or not found.IsValid():
        meshes = _mesh_paths(stage)
        known = f"meshes in the file: {_listed(meshes)}" if meshes else "the file has no mesh"
        raise ConfigError(f"{file}: no prim {prim} in the file ({known}); fix the prim path")
    if not found.IsA(UsdGeom.Mesh):
        kind = found.GetTypeName() or "typeless prim"
        raise ConfigError(f"{file}, prim {prim}: its type is {kind}, not Mesh; choose the path of a "
                          f"UsdGeom.Mesh prim")
    if not found.IsActive():
        raise ConfigError(f"{file}, prim {prim}: the mesh is inactive (active = false); activate it "
                          f"or choose another mesh")
    return found


def _time_code(stage, time: float | None, where: str):
    """The time code to read at (see :func:`read_usd_mesh`)."""
    from pxr import Usd  # optional: usd-core

    if time is None:
        if stage.HasAuthoredTimeCodeRange():
            return Usd.TimeCode(stage.GetStartTimeCode())
        return Usd.TimeCode.EarliestTime()
    try:
        value = float(time)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value):
        raise ConfigError(f"{where}: time must be a finite USD time code (a frame number), got {time!r}")
    return Usd.TimeCode(value)


# ------------------------------------------------------------------------------------------- topology




def _constant_topology(attr, name: str, where: str) -> None:
    """ConfigError if ``attr`` has time samples of different values."""
    samples = attr.GetTimeSamples()
    if len(samples) < 2:
        return
    first = int_array(attr.Get(samples[0]))
    for t in samples[1:]:
        if not np.array_equal(first, int_array(attr.Get(t))):
            raise ConfigError(f"{where}: its {name} changes over time (time samples {samples[0]:g} and "
                              f"{t:g} differ); warpspring needs constant topology: export one frame "
                              f"of the mesh, or a mesh whose faces stay the same")


def _check_topology(points: np.ndarray, counts: np.ndarray, indices: np.ndarray, where: str) -> None:
    """ConfigError for an empty mesh, non-finite points or inconsistent faces."""
    if len(points) == 0 or len(counts) == 0:
        what = "no points" if len(points) == 0 else "no faces"
        raise ConfigError(f"{where}: the mesh is empty ({what}: {len(points)} points, {len(counts)} "
                          f"faces); export the mesh with its points and faces")
    finite = np.all(np.isfinite(points), axis=1)
    if not np.all(finite):
        bad = int(np.flatnonzero(~finite)[0])
        raise ConfigError(f"{where}: vertex {bad} is not finite ({_vector(points[bad])}); fix the mesh "
                          f"in the DCC tool and export it again")
    small = np.flatnonzero(counts < 3)
    if len(small):
        face = int(small[0])
        raise ConfigError(f"{where}: face {face} has {int(counts[face])} vertices (a face needs at least "
                          f"3); remove degenerate faces in the DCC tool (merge by distance, clean up)")
    total = int(counts.sum())
    if total != len(indices):
        raise ConfigError(f"{where}: faceVertexCounts add up to {total} but faceVertexIndices has "
                          f"{len(indices)} entries; the file's topology is broken, export the mesh again")
    out = np.flatnonzero((indices < 0) | (indices >= len(points)))
    if len(out):
        position = int(out[0])
        face = int(np.searchsorted(np.cumsum(counts), position, side="right"))
        raise ConfigError(f"{where}: face {face} uses vertex {int(indices[position])}, out of range for "
                          f"{len(points)} points; the file's topology is broken, export the mesh again")


def _vector(v: np.ndarray) -> str:
    """A point as ``(x, y, z)``."""
    return "(" + ", ".join(f"{float(x):g}" for x in v) + ")"


def convert_up_axis(points: np.ndarray, stage_axis: str, axis: str) -> np.ndarray:
    """``[v, 3]`` points (or vectors) of a stage of up axis ``stage_axis`` ("Y" or "Z") in the frame of up axis
    ``axis``: the rotation of 90° about X that the reader applies (its inverse is the call with the axes swapped)."""
    if stage_axis == axis:
        return points
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    if axis == "Z":  # Y-up to Z-up: a rotation of +90° about X
        return np.stack([x, -z, y], axis=1)
    return np.stack([x, z, -y], axis=1)  # Z-up to Y-up: a rotation of -90° about X


def _reverse_faces(counts: np.ndarray, indices: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``indices`` with each face's order reversed behind its first vertex: (a, b, c, d) -> (a, d, c, b)."""
    face = np.repeat(np.arange(len(counts)), counts)
    start = offsets[face]
    n = counts[face]
    local = np.arange(len(indices)) - start
    return indices[start + (n - local) % n]


# ------------------------------------------------------------------------------------- triangulation


def _newell(p: np.ndarray) -> np.ndarray:
    """``[m, 3]`` Newell normals (twice the vector area) of ``[m, n, 3]`` polygons."""
    q = p - p.mean(axis=1, keepdims=True)
    return np.cross(q, np.roll(q, -1, axis=1)).sum(axis=1)


def _facing(p: np.ndarray, local: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """``[m, k]`` dot products of the normals of triangles ``local`` ([k, 3] or [m, k, 3] corner indices)
    of polygons ``p`` ([m, n, 3]) with the polygons' normals ``normal`` ([m, 3])."""
    rows = np.arange(len(p))[:, None]
    if local.ndim == 2:
        local = np.broadcast_to(local, (len(p),) + local.shape)
    a, b, c = (p[rows, local[:, :, k]] for k in range(3))
    return np.einsum("mkj,mj->mk", np.cross(b - a, c - a), normal)


def _triangulate(vertices: np.ndarray, counts: np.ndarray, indices: np.ndarray, offsets: np.ndarray,
                 where: str) -> tuple[np.ndarray, np.ndarray]:
    """``([t, 3] int32 triangles, [t] int32 source face)`` of the faces, in face order (module doc)."""
    per_face = counts - 2
    first = np.concatenate(([0], np.cumsum(per_face)[:-1])).astype(np.int64)
    triangles = np.empty((int(per_face.sum()), 3), dtype=np.int32)
    non_convex: list[tuple[int, int]] = []
    for n in (int(k) for k in np.unique(counts)):
        faces = np.flatnonzero(counts == n)
        poly = indices[offsets[faces][:, None] + np.arange(n)]  # [m, n]
        if n == 3:
            local = np.broadcast_to(np.array([[0, 1, 2]]), (len(faces), 1, 3))
        elif n == 4:
            p = vertices[poly]
            split_ac = np.array([[0, 1, 2], [0, 2, 3]])
            split_bd = np.array([[0, 1, 3], [1, 2, 3]])
            use_ac = (np.sum((p[:, 2] - p[:, 0]) ** 2, axis=1)
                      <= np.sum((p[:, 3] - p[:, 1]) ** 2, axis=1))
            # A concave quad has one diagonal inside it: take that one whatever its length.
            normal = _newell(p)
            ok_ac = np.all(_facing(p, split_ac, normal) > 0.0, axis=1)
            ok_bd = np.all(_facing(p, split_bd, normal) > 0.0, axis=1)
            use_ac = np.where(ok_ac != ok_bd, ok_ac, use_ac)
            local = np.where(use_ac[:, None, None], split_ac, split_bd)
        else:
            fan = np.stack([np.zeros(n - 2, dtype=np.int64), np.arange(1, n - 1), np.arange(2, n)], axis=1)
            p = vertices[poly]
            bad = ~np.all(_facing(p, fan, _newell(p)) > 0.0, axis=1)
            if np.any(bad):
                non_convex.append((int(faces[np.flatnonzero(bad)[0]]), n))
            local = np.broadcast_to(fan, (len(faces), n - 2, 3))
        tris = poly[np.arange(len(faces))[:, None, None], local]  # [m, n - 2, 3]
        triangles[first[faces][:, None] + np.arange(n - 2)] = tris
    if non_convex:
        face, n = min(non_convex)
        raise ConfigError(f"{where}: face {face} ({n} vertices) is not convex in its plane (fanned from "
                          f"its first vertex it gives a flipped or zero-area triangle); triangulate it in "
                          f"the DCC tool (or export triangles and quads) and read the file again")
    triangle_polygon = np.repeat(np.arange(len(counts), dtype=np.int32), per_face)
    return triangles, triangle_polygon


# ------------------------------------------------------------------------------------------ face sets


def _face_sets(mesh_prim, num_faces: int, code, where: str) -> dict[str, np.ndarray]:
    """GeomSubset name -> sorted unique int32 face indices, for the subsets of element type face."""
    from pxr import UsdGeom  # optional: usd-core

    sets: dict[str, np.ndarray] = {}
    for subset in UsdGeom.Subset.GetAllGeomSubsets(UsdGeom.Imageable(mesh_prim)):
        if subset.GetElementTypeAttr().Get() != UsdGeom.Tokens.face:
            continue
        name = subset.GetPrim().GetName()
        idx = int_array(subset.GetIndicesAttr().Get(code))
        out = np.flatnonzero((idx < 0) | (idx >= num_faces))
        if len(out):
            raise ConfigError(f"{where}: face set {name} names face {int(idx[out[0]])}, out of range for "
                              f"{num_faces} faces; fix the GeomSubset {subset.GetPath()} in the DCC tool "
                              f"and export it again")
        sets[name] = np.unique(idx).astype(np.int32)
    return sets
