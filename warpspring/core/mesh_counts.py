"""A mesh file's vertex and triangle counts, known before the file is read, so that a mesh too large for the
memory is refused before trimesh loads it.

Where the format says it in a header, the header is all that is read: PLY (``element vertex``, ``element face``;
a binary file's polygon size follows from its length), binary STL (its triangle count, checked against the file's
length), OFF (its count line), glTF and GLB (their JSON's accessor counts: positions, and indices / 3 of triangle
primitives, each mesh counted once per node that places it). OBJ and ASCII STL have no header: their lines are
streamed in blocks (constant memory, ~1 s per 100 MB), an OBJ face of k corners counted as the k − 2 triangles
trimesh makes of it. Other formats (3MF, DAE, ...) are not counted (``None``).

A USD mesh prim (:func:`usd_mesh_counts`) is counted from its attributes' array lengths, on the opened stage: its
``faceVertexCounts`` (four bytes a polygon) give the triangles of the fan the reader makes, its points' array
length the vertices (a binary ``.usdc`` maps the arrays it reads, a text ``.usda`` has parsed them into its layer),
and its points' time samples are counted; nothing is triangulated, transformed or copied into float64.
"""

from __future__ import annotations

import json
import os
import struct
from typing import NamedTuple

import numpy as np

from .mesh_files import open_usd_stage

#: Bytes read per block when an OBJ or ASCII STL file is streamed.
BLOCK_BYTES = 1 << 22
#: The longest PLY or OFF header read [B]: a file whose counts are not within it is not counted.
HEADER_BYTES = 1 << 16

_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def mesh_file_counts(path) -> tuple[int, int] | None:
    """(vertices, triangles) of a mesh file, from its header or its streamed lines; ``None`` for a format not
    counted, a file that cannot be read or a header not understood (then nothing is known before it is read)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        return None
    extension = os.path.splitext(path)[1].lower()
    try:
        if extension == ".obj":
            return _obj_counts(path)
        if extension == ".ply":
            return _ply_counts(path)
        if extension == ".stl":
            return _stl_counts(path)
        if extension == ".off":
            return _off_counts(path)
        if extension in (".glb", ".gltf"):
            return _gltf_counts(path, binary=extension == ".glb")
    except (OSError, ValueError, struct.error, KeyError, TypeError, IndexError):
        return None
    return None


class UsdMeshCounts(NamedTuple):
    """A USD mesh prim's counts (:func:`usd_mesh_counts`): its vertices; the triangles the reader makes of its
    polygons, and how many of them come from polygons of four or more corners (the fan, whose test of each polygon
    costs more than a triangle read as it is); its points' time samples."""

    vertices: int
    triangles: int
    fanned: int
    samples: int


def usd_mesh_counts(path, *, prim: str | None = None) -> UsdMeshCounts | None:
    """A USD file's mesh prim's counts (``prim``, or the file's one mesh), from its attributes' array lengths (see
    the module's description); ``None`` where the prim cannot be told (no mesh, several, a bad path: the reader then
    says why in its own words)."""
    from pxr import Usd, UsdGeom  # optional: usd-core

    stage = open_usd_stage(path)
    if prim is None:
        meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
        if len(meshes) != 1:
            return None
        found = meshes[0]
    else:
        try:
            found = stage.GetPrimAtPath(prim)
        except Exception:  # noqa: BLE001 - a malformed path: the reader refuses it with its own message
            return None
        if not found or not found.IsA(UsdGeom.Mesh):
            return None
    mesh = UsdGeom.Mesh(found)
    earliest = Usd.TimeCode.EarliestTime()
    corners = np.asarray(mesh.GetFaceVertexCountsAttr().Get(earliest) or [], dtype=np.int64)
    points = mesh.GetPointsAttr().Get(earliest)
    made = np.maximum(corners - 2, 0)
    return UsdMeshCounts(vertices=len(points) if points else 0, triangles=int(made.sum()),
                         fanned=int(made[corners > 3].sum()), samples=int(mesh.GetPointsAttr().GetNumTimeSamples()))


def _blocks(path: str):
    """The file's complete lines in blocks of about BLOCK_BYTES, each block starting with a newline."""
    carry = b"\n"
    with open(path, "rb") as f:
        while chunk := f.read(BLOCK_BYTES):
            text = carry + chunk
            cut = text.rfind(b"\n")
            carry = text[cut:]
            yield text[:cut + 1]
    if carry.strip():
        yield carry + b"\n"


def _obj_counts(path: str) -> tuple[int, int]:
    """OBJ: ``v`` lines, and the triangles of ``f`` lines (k corners: k − 2 triangles), counted per block with NumPy."""
    vertices = triangles = 0
    for block in _blocks(path):
        vertices += block.count(b"\nv ") + block.count(b"\nv\t")
        if b"\nf" not in block:
            continue
        data = np.frombuffer(block, dtype=np.uint8)
        newline = data == ord("\n")
        blank = (data == ord(" ")) | (data == ord("\t")) | (data == ord("\r"))
        # A token starts where a character that is neither blank nor a newline follows a blank.
        starts = np.zeros(len(data), dtype=np.int32)
        starts[1:] = ~(blank[1:] | newline[1:]) & blank[:-1]
        lines = np.flatnonzero(newline)  # every line runs from one newline to the next
        face = (lines[:-1] + 2 < len(data)) & (data[np.minimum(lines[:-1] + 1, len(data) - 1)] == ord("f"))
        face &= blank[np.minimum(lines[:-1] + 2, len(data) - 1)]
        if not face.any():
            continue
        corners = np.add.reduceat(starts, lines[:-1])[face]  # tokens after "f" on each face line
        triangles += int(np.maximum(corners - 2, 0).sum())
    return vertices, triangles


def _header_lines(path: str) -> tuple[list[str], int]:
    """The ASCII header lines of a PLY file up to ``end_header``, and the header's length [B]."""
    with open(path, "rb") as f:
        head = f.read(HEADER_BYTES)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise ValueError("not a PLY header")
    stop = head.find(b"\n", end) + 1
    return head[:stop].decode("ascii", "replace").split("\n"), stop


def _ply_counts(path: str) -> tuple[int, int]:
    """PLY: the vertex and face elements' counts; a binary file's face size from its length (uniform polygons),
    an ASCII file's faces taken as triangles."""
    lines, header = _header_lines(path)
    fmt = next((line.split()[1] for line in lines if line.startswith("format")), "ascii")
    elements: list[list] = []  # [name, count, properties: (size, list count size, list item size)]
    for line in lines:
        words = line.split()
        if words[:1] == ["element"] and len(words) == 3:
            elements.append([words[1], int(words[2]), []])
        elif words[:1] == ["property"] and elements:
            if words[1] == "list" and len(words) >= 4:
                elements[-1][2].append((0, _PLY_SIZES[words[2]], _PLY_SIZES[words[3]]))
            elif len(words) >= 3:
                elements[-1][2].append((_PLY_SIZES[words[1]], 0, 0))
    counts = {name: count for name, count, _ in elements}
    vertices, faces = counts.get("vertex", 0), counts.get("face", 0)
    if fmt == "ascii" or not faces:
        return vertices, faces
    # Binary: the bytes the face element takes are what the other elements leave; with its one list of corners
    # (and fixed properties) that gives the mean corners per face.
    fixed = {name: sum(p[0] for p in props) for name, _, props in elements}
    lists = {name: [p for p in props if p[1]] for name, _, props in elements}
    if any(lists[name] for name in counts if name != "face") or len(lists.get("face", [])) != 1:
        return vertices, faces
    others = sum(count * fixed[name] for name, count, _ in elements if name != "face")
    _, count_size, item_size = lists["face"][0]
    face_bytes = os.path.getsize(path) - header - others - faces * (fixed["face"] + count_size)
    corners = face_bytes / (faces * item_size)
    return vertices, max(faces, int(round(faces * (corners - 2.0))))


def _stl_counts(path: str) -> tuple[int, int]:
    """STL: a binary file's triangle count (its length must be 84 + 50 per triangle), else ASCII ``facet`` lines;
    three vertices per triangle before trimesh merges them."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        head = f.read(84)
    if len(head) == 84:
        (count,) = struct.unpack("<I", head[80:84])
        if size == 84 + 50 * count:
            return 3 * count, count
    triangles = sum(block.count(b"endfacet") for block in _blocks(path))
    return 3 * triangles, triangles


def _off_counts(path: str) -> tuple[int, int]:
    """OFF: the count line after the ``OFF`` keyword (comments skipped); faces taken as triangles."""
    with open(path, "rb") as f:
        head = f.read(HEADER_BYTES).decode("ascii", "replace")
    words = []
    for line in head.split("\n"):
        line = line.split("#", 1)[0].strip()
        if line:
            words.extend(line.split())
        if len(words) >= 3 and words[0].upper().endswith("OFF") or len(words) >= 4:
            break
    if words and words[0].upper().endswith("OFF"):
        words = words[1:]
    if len(words) < 2:
        raise ValueError("no OFF count line")
    return int(words[0]), int(words[1])


def _gltf_counts(path: str, *, binary: bool) -> tuple[int, int]:
    """glTF / GLB: the JSON's accessors (a GLB's first chunk, read alone): each triangle primitive's positions and
    indices / 3 (or positions / 3 without indices), a mesh counted once per node that uses it (at least once)."""
    with open(path, "rb") as f:
        if binary:
            magic, _, _, length, kind = struct.unpack("<4sIIII", f.read(20))
            if magic != b"glTF" or kind != 0x4E4F534A:  # "JSON"
                raise ValueError("not a GLB file")
            document = json.loads(f.read(length))
        else:
            document = json.load(f)
    accessors = document.get("accessors", [])
    uses = [0] * len(document.get("meshes", []))
    for node in document.get("nodes", []):
        if "mesh" in node:
            uses[node["mesh"]] += 1
    vertices = triangles = 0
    for mesh, used in zip(document.get("meshes", []), uses):
        for primitive in mesh.get("primitives", []):
            if primitive.get("mode", 4) != 4:  # not TRIANGLES: trimesh reads no faces from it
                continue
            points = accessors[primitive["attributes"]["POSITION"]]["count"]
            corners = accessors[primitive["indices"]]["count"] if "indices" in primitive else points
            vertices += max(used, 1) * points
            triangles += max(used, 1) * (corners // 3)
    return vertices, triangles
