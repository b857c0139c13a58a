#!/usr/bin/env python3
"""Check how Blender imports a USD file: what arrives, what plays, what a Blender user must set.

Run it in a Python that has Blender's PyPI build ``bpy`` (it is large, so it is not part of the project's
dependencies nor of the test suite)::

    python -m venv bpyvenv && bpyvenv/bin/pip install bpy usd-core
    bpyvenv/bin/python tools/blender_check.py out.usdc [--fps 60] [--frames 0 30] [--option import_guide=True]

or inside a Blender install: ``blender -b --factory-startup --python tools/blender_check.py -- out.usdc``.

It resets Blender to factory settings (an empty scene), imports the file with
``bpy.ops.wm.usd_import`` and prints one JSON report on stdout (Blender's own log lines go to stderr):

- ``blender``: Blender's version;
- ``import_options``: every option of ``wm.usd_import`` in this Blender with its default, and
  ``options_used``: the ones given with ``--option KEY=VALUE`` (the rest stay at their defaults);
- ``scene_before`` / ``scene_after``: the scene's fps, fps_base, frame_start and frame_end before and after
  the import (does Blender take the file's frame rate? its frame range?);
- ``cache_files``: the CacheFile data-blocks the import made (their time and velocity settings);
- ``objects``: each imported object with its USD prim path, the prim's purpose, whether it is hidden
  (viewport, render), its modifiers (a Mesh Sequence Cache with its ``read_data``) and constraints (a
  Transform Cache), and for meshes the vertex and polygon counts, a histogram of polygon sizes
  (``{"3": n, "4": m}``: do quads stay quads?), the attributes (is there a ``velocity`` or ``velocities``?),
  UV maps, materials and the faces per material slot (do face sets arrive as anything?);
- ``usd``: what the file holds, read with ``pxr`` (usd-core) in a separate Python process so that its USD
  libraries and Blender's never share one process: stage metadata, each prim's type, purpose, time-sampled
  attributes, primvars and GeomSubsets; ``not_imported`` lists the geometry prims that became no object;
- ``samples``: at the first, a quarter, the middle and the last frame (or the given ones), after
  ``scene.frame_set(f)`` and evaluating the depsgraph, each object's world matrix, world-space vertex
  centroid (the origin for objects without vertices) and the means of its point attributes, next to the same
  quantities that pxr computes from the file at the candidate time codes ``frame`` and
  ``frame / scene_fps * timeCodesPerSecond`` (Blender's frame number read as a time code, or Blender's time in
  seconds converted): ``reads_time_code`` says which one Blender sampled (objects that are the same at both
  candidates say ``same_at_time_codes`` instead); ``velocity_equals_usd_velocities`` and
  ``normals_max_angle_deg_vs_usd`` compare the velocities and the shading normals with the file's (per
  vertex, or per corner where the file's normals are faceVarying);
  ``points_max_error_vs_usd`` [m] compares every evaluated vertex (mesh, curve or point) with the file's points
  at the time code read, and ``primvars_max_error_vs_usd`` every value of each vertex primvar (a soft body's or
  cloth's ``strain``, ``pinned``, ``rest``, ``st``; a spring curve's ``strain``) with Blender's point attribute
  (or UV map) of the same name, or says why it could not (no such attribute, another count);
- with ``--fps N``: ``samples_at_fps``: the same after ``scene.render.fps = N`` (fps_base 1), each frame k
  with its time in seconds, k / N, beside the seconds of the USD time code that Blender read;
- ``summary``: the answers in short: the scene's fps and range after the import, which time code each
  sampled frame read, and per mesh the polygon sizes (Blender's and the file's), the velocity attribute's
  name, the face sets of the file beside Blender's material slots, vertex groups and face attributes, the
  largest point and primvar differences over the sampled frames (meshes, and in ``other_geometry`` the
  spring curves and particles), and which guide prims were imported and whether they render.

``--write-sample PATH`` writes a small hand-authored ``.usda`` that exercises every question at once (no
bpy nor pxr needed for that): a quad mesh with time-sampled ``points``, ``velocities`` and a vertex primvar,
GeomSubset face sets (a ``materialBind`` partition bound to two materials, and a ``warpspring`` family the
way warpspring writes the face sets of a USD input), a mesh of purpose ``guide`` and two meshes that inherit
purpose ``guide`` from their Xform, at ``timeCodesPerSecond = framesPerSecond = 60``.

Checked with bpy 5.0.1 (Blender 5.0.1) from PyPI on Python 3.11, with usd-core 26.11 for the reference.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import subprocess
import sys
from collections import Counter

# Properties of the import operator that belong to its file browser, not to the import.
_BROWSER_OPTIONS = {"filepath", "check_existing", "filemode", "relative_path", "display_type", "sort_method",
                    "filter_glob"}

# The pxr side, run as `python -c _PXR_PROBE REQUEST_JSON` with REQUEST_JSON = {"file": ..., "time_codes": [...]}.
# It prints one JSON object; it never imports bpy. Positions and matrices are given in Blender's frame: Blender's
# importer turns a Y-up stage Z-up (+90 degrees about X) and scales by metersPerUnit.
_PXR_PROBE = r'''
import json, sys
from collections import Counter
request = json.loads(sys.argv[1])
try:
    from pxr import Usd, UsdGeom, UsdShade
except ImportError as error:
    print(json.dumps({"available": False, "error": str(error)}))
    raise SystemExit(0)

def mean(values):
    values = list(values)
    if not values:
        return None
    if isinstance(values[0], (int, float)):
        return sum(values) / len(values)
    return [sum(v[i] for v in values) / len(values) for i in range(len(values[0]))]

stage = Usd.Stage.Open(request["file"])
up = UsdGeom.GetStageUpAxis(stage)
mpu = UsdGeom.GetStageMetersPerUnit(stage)
report = {
    "available": True,
    "stage": {"framesPerSecond": stage.GetFramesPerSecond(), "timeCodesPerSecond": stage.GetTimeCodesPerSecond(),
              "startTimeCode": stage.GetStartTimeCode(), "endTimeCode": stage.GetEndTimeCode(),
              "upAxis": up, "metersPerUnit": mpu},
    "prims": [], "samples": {},
}

def to_blender(p):
    x, y, z = (c * mpu for c in p)
    return [x, -z, y] if up == "Y" else [x, y, z]

def matrix_to_blender(world):
    # Gf matrices act on row vectors: transpose to Blender's column-vector rows, then turn and scale as above.
    rows = [[world[c][r] for c in range(4)] for r in range(4)]
    turn = [[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]] if up == "Y" else \
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    turn = [[v * mpu if r < 3 else v for v in row] for r, row in enumerate(turn)]
    return [[sum(turn[r][k] * rows[k][c] for k in range(4)) for c in range(4)] for r in range(4)]

gprims = []
for prim in stage.Traverse():
    entry = {"path": str(prim.GetPath()), "type": prim.GetTypeName()}
    if prim.IsA(UsdGeom.Imageable):
        imageable = UsdGeom.Imageable(prim)
        entry["purpose"] = imageable.GetPurposeAttr().Get()
        entry["computed_purpose"] = imageable.ComputePurpose()
    entry["time_sampled"] = sorted(a.GetName() for a in prim.GetAttributes() if a.GetNumTimeSamples() > 1)
    if prim.IsA(UsdGeom.Gprim):
        entry["primvars"] = {pv.GetPrimvarName(): pv.GetInterpolation()
                             for pv in UsdGeom.PrimvarsAPI(prim).GetPrimvars() if pv.HasAuthoredValue()}
        if prim.IsA(UsdGeom.Mesh):
            counts = UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get() or []
            entry["polygon_sizes"] = {str(k): v for k, v in sorted(Counter(counts).items())}
            entry["subsets"] = []
            for subset in UsdGeom.Subset.GetAllGeomSubsets(UsdGeom.Imageable(prim)):
                binding = UsdShade.MaterialBindingAPI(subset.GetPrim()).GetDirectBindingRel()
                entry["subsets"].append({
                    "name": subset.GetPrim().GetName(), "familyName": subset.GetFamilyNameAttr().Get(),
                    "elementType": subset.GetElementTypeAttr().Get(),
                    "indices": len(subset.GetIndicesAttr().Get() or []),
                    "material": [str(t) for t in binding.GetTargets()] if binding else []})
        gprims.append(prim)
    if prim.IsA(UsdGeom.Imageable) or prim.IsA(UsdGeom.Xformable):
        report["prims"].append(entry)

for code in request.get("time_codes", []):
    cache = UsdGeom.XformCache(code)
    per_prim = {}
    for prim in gprims:
        world = cache.GetLocalToWorldTransform(prim)
        sample = {"matrix_world": matrix_to_blender(world)}
        points = prim.GetAttribute("points").Get(code) if prim.HasAttribute("points") else None
        if points:
            sample["centroid"] = to_blender(mean(world.Transform(p) for p in points))
        else:
            sample["centroid"] = to_blender(world.Transform((0.0, 0.0, 0.0)))
        if points and request.get("points"):  # every point, compared with Blender's, then dropped
            sample["points"] = [to_blender(world.Transform(p)) for p in points]
        normals = prim.GetAttribute("normals").Get(code) if prim.HasAttribute("normals") else None
        if normals and points and len(normals) == len(points):  # per vertex: compared, then dropped
            sample["normals"] = [list(n) for n in normals]
        elif normals and points and prim.HasAttribute("faceVertexCounts"):  # faceVarying: per corner, likewise
            counts = prim.GetAttribute("faceVertexCounts").Get(code)
            if counts is not None and len(normals) == sum(counts):
                sample["corner_normals"] = [list(n) for n in normals]
        velocities = prim.GetAttribute("velocities").Get(code) if prim.HasAttribute("velocities") else None
        if velocities:
            sample["velocities_mean"] = mean(tuple(v) for v in velocities)
        for pv in UsdGeom.PrimvarsAPI(prim).GetPrimvars():
            value = pv.Get(code)
            if value is None or pv.GetInterpolation() not in ("vertex", "varying") or not len(value):
                continue
            try:
                sample["primvar:" + pv.GetPrimvarName()] = mean(v if isinstance(v, (int, float)) else tuple(v)
                                                                 for v in value)
                if request.get("points"):  # every value, compared with Blender's attribute, then dropped
                    sample["primvar_values:" + pv.GetPrimvarName()] = [v if isinstance(v, (int, float)) else list(v)
                                                                        for v in value]
            except TypeError:
                pass
        per_prim[str(prim.GetPath())] = sample
    report["samples"][repr(float(code))] = per_prim
print(json.dumps(report))
'''


# ------------------------------------------------------------------------------------------------ sample file

def sample_usda(frames: int = 60, fps: int = 60) -> str:
    """A small hand-authored USD layer: a 2×2-quad mesh moving at 1 m/s along x (and accelerating at 1 m/s²
    along z) with matching time-sampled ``velocities`` and a vertex primvar ``strain`` equal to t [s], so the
    centroid (x = t) and each mean tell which time code was read; GeomSubset face sets; guide geometry."""
    grid = [(float(i % 3), float(i // 3)) for i in range(9)]  # 3×3 vertices, 1 m apart, in the z = 1 plane
    quads = [(0, 1, 4, 3), (1, 2, 5, 4), (3, 4, 7, 6), (4, 5, 8, 7)]

    def vec3s(values):
        return "[" + ", ".join(f"({x:.6g}, {y:.6g}, {z:.6g})" for x, y, z in values) + "]"

    points, velocities, strain = [], [], []
    for code in range(frames + 1):
        t = code / fps
        points.append(f"            {code}: " + vec3s((x + t, y, 1.0 + 0.5 * t * t) for x, y in grid))
        velocities.append(f"            {code}: " + vec3s([(1.0, 0.0, t)] * len(grid)))
        strain.append(f"            {code}: [" + ", ".join([f"{t:.6g}"] * len(grid)) + "]")
    counts = ", ".join("4" for _ in quads)
    indices = ", ".join(str(i) for q in quads for i in q)
    flat_quad = "[(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]"

    def material(name, rgb):
        return f'''
        def Material "{name}"
        {{
            token outputs:surface.connect = </World/Looks/{name}/surface.outputs:surface>

            def Shader "surface"
            {{
                uniform token info:id = "UsdPreviewSurface"
                color3f inputs:diffuseColor = {rgb}
                token outputs:surface
            }}
        }}'''

    nl = ",\n"
    return f'''#usda 1.0
(
    doc = "blender_check sample: quads, time-sampled points/velocities/primvar, face sets, guide prims"
    defaultPrim = "World"
    startTimeCode = 0
    endTimeCode = {frames}
    timeCodesPerSecond = {fps}
    framesPerSecond = {fps}
    metersPerUnit = 1
    upAxis = "Z"
)

def Xform "World"
{{
    def Mesh "cloth" (
        prepend apiSchemas = ["MaterialBindingAPI"]
    )
    {{
        int[] faceVertexCounts = [{counts}]
        int[] faceVertexIndices = [{indices}]
        uniform token subdivisionScheme = "none"
        uniform token orientation = "rightHanded"
        uniform bool doubleSided = 1
        uniform token subsetFamily:materialBind:familyType = "partition"
        point3f[] points.timeSamples = {{
{nl.join(points)}
        }}
        vector3f[] velocities.timeSamples = {{
{nl.join(velocities)}
        }}
        float[] primvars:strain (
            interpolation = "vertex"
        )
        float[] primvars:strain.timeSamples = {{
{nl.join(strain)}
        }}

        def GeomSubset "front" (
            prepend apiSchemas = ["MaterialBindingAPI"]
        )
        {{
            uniform token elementType = "face"
            uniform token familyName = "materialBind"
            int[] indices = [0, 1]
            rel material:binding = </World/Looks/red>
        }}

        def GeomSubset "back" (
            prepend apiSchemas = ["MaterialBindingAPI"]
        )
        {{
            uniform token elementType = "face"
            uniform token familyName = "materialBind"
            int[] indices = [2, 3]
            rel material:binding = </World/Looks/blue>
        }}

        def GeomSubset "hem" (
            doc = "a face set as warpspring writes those of a USD input: family warpspring, no material"
        )
        {{
            uniform token elementType = "face"
            uniform token familyName = "warpspring"
            int[] indices = [0, 1]
        }}
    }}

    def Mesh "guide_plane"
    {{
        uniform token purpose = "guide"
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = {flat_quad}
        uniform token subdivisionScheme = "none"
    }}

    def Xform "guides" (
        doc = "purpose guide on the parent only: the child inherits it (computed purpose guide)"
    )
    {{
        uniform token purpose = "guide"
        double3 xformOp:translate = (0, 0, -0.5)
        uniform token[] xformOpOrder = ["xformOp:translate"]

        def Mesh "inherited_guide"
        {{
            int[] faceVertexCounts = [4]
            int[] faceVertexIndices = [0, 1, 2, 3]
            point3f[] points = {flat_quad}
            uniform token subdivisionScheme = "none"
        }}

        def Mesh "inherited_guide_2"
        {{
            int[] faceVertexCounts = [4]
            int[] faceVertexIndices = [0, 1, 2, 3]
            point3f[] points = {flat_quad}
            uniform token subdivisionScheme = "none"
        }}
    }}

    def Scope "Looks"
    {{{material("red", "(1, 0, 0)")}{material("blue", "(0, 0, 1)")}
    }}
}}
'''


# ------------------------------------------------------------------------------------------------ Blender side

def _json_value(value):
    """An RNA value as JSON: sets (enum flags) as sorted lists, data-blocks by name, the rest as is."""
    if isinstance(value, set):
        return sorted(value)
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    if hasattr(value, "name"):
        return value.name
    try:
        return [_json_value(v) for v in value]
    except TypeError:
        return str(value)


def import_options(bpy) -> dict:
    """Every option of ``wm.usd_import`` in this Blender, with its label in the import dialog and its default."""
    options = {}
    for prop in bpy.ops.wm.usd_import.get_rna_type().properties:
        name = prop.identifier
        if name == "rna_type" or name in _BROWSER_OPTIONS or name.startswith("filter_"):
            continue
        if prop.type == "ENUM":
            default = sorted(prop.default_flag) if prop.is_enum_flag else prop.default
            options[name] = {"label": prop.name, "default": default,
                             "choices": [item.identifier for item in prop.enum_items]}
        else:
            options[name] = {"label": prop.name, "default": _json_value(getattr(prop, "default", None))}
    return options


def parse_option(text: str):
    """``KEY=VALUE`` -> (key, value), the value read as a Python literal (True, 1.5, 'x') or kept as text."""
    key, sep, raw = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"--option wants KEY=VALUE, got {text!r}")
    try:
        value = ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        value = raw
    return key.strip(), value


def scene_settings(scene) -> dict:
    return {"fps": scene.render.fps, "fps_base": scene.render.fps_base,
            "frame_start": scene.frame_start, "frame_end": scene.frame_end, "frame_current": scene.frame_current}


def usd_path(obj) -> tuple[str, str]:
    """The USD prim path of an imported object, and where it was found: the Mesh Sequence Cache modifier's or
    the Transform Cache constraint's object path, else the chain of parent names (Blender names objects after
    their prims; a name clash adds a ``.001`` suffix, which is dropped here)."""
    for mod in obj.modifiers:
        if mod.type == "MESH_SEQUENCE_CACHE" and mod.object_path:
            return mod.object_path, "modifier"
    for con in obj.constraints:
        if con.type == "TRANSFORM_CACHE" and con.object_path:
            return con.object_path, "constraint"
    names = []
    while obj is not None:
        base, dot, suffix = obj.name.rpartition(".")
        names.append(base if dot and suffix.isdigit() else obj.name)
        obj = obj.parent
    return "/" + "/".join(reversed(names)), "parent names"


def describe_object(obj) -> dict:
    path, path_source = usd_path(obj)
    entry = {
        "name": obj.name, "type": obj.type, "parent": obj.parent.name if obj.parent else None,
        "usd_path": path, "usd_path_from": path_source,
        "hide_render": obj.hide_render, "hide_viewport": obj.hide_viewport, "hidden_in_view_layer": obj.hide_get(),
        "display_type": obj.display_type,
        "collections": [c.name for c in obj.users_collection],
        "custom_properties": sorted(obj.keys()) + sorted(f"data:{k}" for k in (obj.data.keys() if obj.data else [])),
        "vertex_groups": [g.name for g in obj.vertex_groups],
        "modifiers": [], "constraints": [],
    }
    for mod in obj.modifiers:
        item = {"type": mod.type, "name": mod.name}
        if mod.type == "MESH_SEQUENCE_CACHE":
            item.update(object_path=mod.object_path, read_data=sorted(mod.read_data),
                        velocity_scale=mod.velocity_scale, use_vertex_interpolation=mod.use_vertex_interpolation,
                        cache_file=mod.cache_file.name if mod.cache_file else None)
        elif mod.type == "SUBSURF":
            item.update(levels=mod.levels, render_levels=mod.render_levels)
        entry["modifiers"].append(item)
    for con in obj.constraints:
        item = {"type": con.type, "name": con.name}
        if con.type == "TRANSFORM_CACHE":
            item.update(object_path=con.object_path, cache_file=con.cache_file.name if con.cache_file else None)
        entry["constraints"].append(item)
    if obj.type == "MESH":
        entry["mesh"] = describe_mesh(obj.data)
    elif obj.type in ("POINTCLOUD", "CURVES") and obj.data is not None:
        entry["geometry"] = {"points": len(obj.data.attributes["position"].data)
                             if "position" in obj.data.attributes else None,
                             "attributes": [[a.name, a.domain, a.data_type] for a in obj.data.attributes]}
    elif obj.type == "CURVE" and obj.data is not None:
        entry["geometry"] = {"splines": len(obj.data.splines)}
    return entry


def describe_mesh(mesh) -> dict:
    import numpy as np

    sizes = np.zeros(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("loop_total", sizes)
    material_index = np.zeros(len(mesh.polygons), dtype=np.int32)
    mesh.polygons.foreach_get("material_index", material_index)
    names = [a.name for a in mesh.attributes]
    return {
        "vertices": len(mesh.vertices), "polygons": len(mesh.polygons),
        "polygon_sizes": {str(k): int(v) for k, v in sorted(Counter(sizes.tolist()).items())},
        "has_velocity_attribute": "velocity" in names, "has_velocities_attribute": "velocities" in names,
        "attributes": [[a.name, a.domain, a.data_type] for a in mesh.attributes],
        "uv_maps": [uv.name for uv in mesh.uv_layers],
        "color_attributes": [c.name for c in mesh.color_attributes],
        "has_custom_normals": mesh.has_custom_normals,
        "materials": [m.name if m else None for m in mesh.materials],
        "faces_per_material_slot": {str(k): int(v) for k, v in sorted(Counter(material_index.tolist()).items())},
        **({"faces_of_material_slot": {str(k): [i for i, m in enumerate(material_index.tolist()) if m == k]
                                       for k in sorted(set(material_index.tolist()))}}
           if len(mesh.polygons) <= 64 else {}),
    }


def _mean_attribute(attribute):
    """Mean of a point attribute's values (a number, or a list per component), or None for other types."""
    import numpy as np

    width = {"FLOAT": 1, "INT": 1, "BOOLEAN": 1, "FLOAT_VECTOR": 3, "FLOAT2": 2}.get(attribute.data_type)
    if width is None or not len(attribute.data):
        return None
    key = {"FLOAT_VECTOR": "vector", "FLOAT2": "vector"}.get(attribute.data_type, "value")
    dtype = bool if attribute.data_type == "BOOLEAN" else np.float64
    values = np.zeros(len(attribute.data) * width, dtype=dtype)
    attribute.data.foreach_get(key, values)
    values = values.astype(np.float64).reshape(-1, width).mean(axis=0)
    return float(values[0]) if width == 1 else values.tolist()


def _attribute_values(attribute):
    """A point attribute's values, shape [n, width] (float64), for the types :func:`_mean_attribute` reads."""
    import numpy as np

    width = {"FLOAT": 1, "INT": 1, "BOOLEAN": 1, "FLOAT_VECTOR": 3, "FLOAT2": 2}[attribute.data_type]
    key = {"FLOAT_VECTOR": "vector", "FLOAT2": "vector"}.get(attribute.data_type, "value")
    values = np.zeros(len(attribute.data) * width, dtype=bool if attribute.data_type == "BOOLEAN" else np.float64)
    attribute.data.foreach_get(key, values)
    return values.astype(np.float64).reshape(-1, width)


def sample_object(obj, depsgraph) -> dict:
    """World-space centroid of the evaluated geometry (its origin when it has no vertices) and the means of
    its evaluated point-domain attributes, at the scene's current frame."""
    import numpy as np

    evaluated = obj.evaluated_get(depsgraph)
    matrix = np.array(evaluated.matrix_world)
    sample = {"location": [float(c) for c in matrix[:3, 3]], "matrix_world": matrix.tolist()}
    data, mesh = None, None
    if obj.type in ("MESH", "CURVE", "SURFACE", "FONT", "META"):
        mesh = data = evaluated.to_mesh()
    elif obj.type in ("POINTCLOUD", "CURVES"):
        data = evaluated.data
    try:
        if data is not None and "position" in data.attributes and len(data.attributes["position"].data):
            positions = np.zeros(len(data.attributes["position"].data) * 3)
            data.attributes["position"].data.foreach_get("vector", positions)
            positions = positions.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]
            sample["centroid"] = positions.mean(axis=0).tolist()
            sample["_positions"] = positions  # compared with the file's points, then dropped
        else:
            sample["centroid"] = sample["location"]
        if mesh is not None and len(mesh.loops):
            # Each vertex's normal as Blender shades it (custom normals where the file gave normals), taken at
            # the vertex's first corner; compared with the file's vertex normals, then dropped.
            corner_vertex = np.zeros(len(mesh.loops), dtype=np.int64)
            mesh.loops.foreach_get("vertex_index", corner_vertex)
            corner_normals = np.zeros(len(mesh.loops) * 3)
            mesh.corner_normals.foreach_get("vector", corner_normals)
            first = np.full(len(mesh.vertices), -1, dtype=np.int64)
            first[corner_vertex[::-1]] = np.arange(len(corner_vertex))[::-1]
            sample["_normals"] = np.where(first[:, None] >= 0, corner_normals.reshape(-1, 3)[first], 0.0)
            sample["_corner_normals"] = corner_normals.reshape(-1, 3)  # every corner, for faceVarying normals
            for layer in mesh.uv_layers:  # a UV map (corners) at each vertex's first corner, for a vertex primvar
                uv = np.zeros(len(mesh.loops) * 2)
                layer.uv.foreach_get("vector", uv)
                sample[f"_values:{layer.name}"] = np.where(first[:, None] >= 0, uv.reshape(-1, 2)[first], np.nan)
        if data is not None:
            for attribute in data.attributes:
                if attribute.domain == "POINT" and attribute.name != "position" and not attribute.name.startswith("."):
                    value = _mean_attribute(attribute)
                    if value is not None:
                        sample[f"mean:{attribute.name}"] = value
                        sample[f"_values:{attribute.name}"] = _attribute_values(attribute)
    finally:
        if mesh is not None:
            evaluated.to_mesh_clear()
    return sample


def take_samples(bpy, scene, frames, objects) -> dict:
    """Each object's sample at each frame, after ``scene.frame_set(frame)``, and the frame's time in seconds."""
    samples = {}
    for frame in frames:
        scene.frame_set(frame)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        fps = scene.render.fps / scene.render.fps_base
        samples[str(frame)] = {"seconds": frame / fps,
                               "objects": {obj.name: sample_object(obj, depsgraph) for obj in objects}}
    return samples


def drop_private(samples: dict) -> dict:
    """Remove the per-vertex arrays kept for the comparison with the file."""
    for sample in samples.values():
        for obj_sample in sample["objects"].values():
            for key in [k for k in obj_sample if k.startswith("_")]:
                del obj_sample[key]
    return samples


# ------------------------------------------------------------------------------------------------ reference

def pxr_reference(python: str, path: str, time_codes=(), points: bool = False) -> dict:
    """What pxr reads from the file (see ``_PXR_PROBE``), computed by ``python`` in its own process; with
    ``points``, every point and vertex primvar value at the time codes too."""
    request = json.dumps({"file": path, "time_codes": sorted(set(float(c) for c in time_codes)), "points": points})
    try:
        done = subprocess.run([python, "-c", _PXR_PROBE, request], capture_output=True, text=True, timeout=600)
    except OSError as error:
        return {"available": False, "error": str(error)}
    if done.returncode != 0:
        return {"available": False, "error": done.stderr.strip()[-2000:]}
    return json.loads(done.stdout)


def _close(a, b, tolerance=1e-4) -> bool:
    if a is None or b is None:
        return False
    a = a if isinstance(a, list) else [a]
    b = b if isinstance(b, list) else [b]
    scale = max(1.0, *(abs(x) for x in a + b))
    return len(a) == len(b) and all(abs(x - y) <= tolerance * scale for x, y in zip(a, b))


def _flat(matrix) -> list:
    return [float(v) for row in matrix for v in row]


def _compare_points(obj_sample: dict, usd: dict | None) -> None:
    """Every point and every vertex primvar of the file at the time code Blender read (or, where it read none,
    at the frame's number) against Blender's evaluated positions and point attributes (or UV maps, read at each
    vertex's first corner) of the same name:
    ``points_max_error_vs_usd`` [m] and ``primvars_max_error_vs_usd`` (a number, or why none: the attribute is
    missing, or its count differs)."""
    import numpy as np

    if not usd:
        return
    positions = obj_sample.get("_positions")
    if usd.get("points") is not None and positions is not None:
        points = np.asarray(usd["points"], dtype=np.float64)
        if points.shape == positions.shape:
            obj_sample["points_max_error_vs_usd"] = float(np.abs(points - positions).max())
        else:
            obj_sample["points_max_error_vs_usd"] = f"counts differ: Blender {len(positions)}, file {len(points)}"
    errors = {}
    for key, values in usd.items():
        if not key.startswith("primvar_values:"):
            continue
        name = key.split(":", 1)[1]
        mine = obj_sample.get(f"_values:{name}")
        values = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
        if mine is None:
            errors[name] = "no point attribute or UV map of this name"
        elif mine.shape != values.shape:
            errors[name] = f"shape differs: Blender {list(mine.shape)}, file {list(values.shape)}"
        else:
            errors[name] = float(np.abs(mine - values).max())
    if errors:
        obj_sample["primvars_max_error_vs_usd"] = errors


def compare(samples: dict, reference: dict, scene_fps: float, paths: dict) -> None:
    """Add to each object's sample the pxr values at the candidate time codes and say which one matches."""
    import numpy as np

    tcps = reference["stage"]["timeCodesPerSecond"]
    for frame, sample in samples.items():
        frame = float(frame)
        candidates = {"frame": frame, "seconds": frame / scene_fps * tcps}
        sample["candidate_time_codes"] = candidates
        for name, obj_sample in sample["objects"].items():
            path = paths.get(name)
            usd = {kind: reference["samples"].get(repr(float(code)), {}).get(path)
                   for kind, code in candidates.items()}
            if not any(usd.values()):
                continue
            obj_sample["usd"] = {kind: {"time_code": candidates[kind],
                                        **{k: v for k, v in (value or {}).items()
                                           if k not in ("normals", "corner_normals", "points")
                                           and not k.startswith("primvar_values:")}}
                                 for kind, value in usd.items()}
            # The same vertex centroid and the same world matrix (a turning box keeps its centroid).
            matches = [kind for kind, value in usd.items() if value
                       and _close(obj_sample["centroid"], value["centroid"])
                       and _close(_flat(obj_sample["matrix_world"]), _flat(value["matrix_world"]))]
            codes = sorted({candidates[kind] for kind in matches})
            if len(codes) == 1:
                obj_sample["reads_time_code"] = codes[0]
            elif codes:  # the object is the same at every candidate: it tells nothing about the time
                obj_sample["same_at_time_codes"] = codes
            else:
                obj_sample["matches_no_candidate"] = True
            reference_values = usd[matches[0]] if matches else None
            _compare_points(obj_sample, reference_values or usd["frame"])
            blender_normals = obj_sample.pop("_normals", None)
            blender_corners = obj_sample.pop("_corner_normals", None)
            usd_normals = reference_values.get("normals") if reference_values else None
            if usd_normals is None and reference_values and reference_values.get("corner_normals") is not None:
                usd_normals, blender_normals = reference_values["corner_normals"], blender_corners  # per corner
            if usd_normals is not None and blender_normals is not None and len(usd_normals) == len(blender_normals):
                # Are the normals Blender shades with the file's normals of that time code?
                unit = np.asarray(usd_normals, dtype=np.float64)
                unit /= np.maximum(np.linalg.norm(unit, axis=1, keepdims=True), 1e-12)
                cosine = np.clip(np.sum(unit * blender_normals, axis=1), -1.0, 1.0)
                obj_sample["normals_max_angle_deg_vs_usd"] = float(np.degrees(np.arccos(cosine.min())))
            if reference_values and "velocities_mean" in reference_values:
                for key in ("mean:velocity", "mean:velocities"):
                    if key in obj_sample:
                        obj_sample["velocity_equals_usd_velocities"] = _close(obj_sample[key],
                                                                              reference_values["velocities_mean"])


# ------------------------------------------------------------------------------------------------ main

def compact_json(value, indent: str = "", width: int = 110) -> str:
    """JSON indented by one space per level, with every list or object that fits in ``width`` on one line."""
    flat = json.dumps(value)
    if len(indent) + len(flat) <= width or not isinstance(value, (list, dict)) or not value:
        return flat
    inner = indent + " "
    if isinstance(value, dict):
        items = [f"{inner}{json.dumps(k)}: {compact_json(v, inner, width)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    items = [inner + compact_json(v, inner, width) for v in value]
    return "[\n" + ",\n".join(items) + "\n" + indent + "]"


def check(args) -> dict:
    import bpy

    path = os.path.abspath(args.usd_file)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    report = {"blender": bpy.app.version_string, "file": path}
    options = import_options(bpy)
    report["import_options"] = options
    used = dict(args.option)
    unknown = sorted(set(used) - set(options))
    if unknown:
        raise SystemExit(f"unknown wm.usd_import option(s) {unknown} in Blender {bpy.app.version_string}; "
                         f"it has: {', '.join(sorted(options))}")
    report["options_used"] = used
    report["scene_before"] = scene_settings(scene)
    report["import_result"] = sorted(bpy.ops.wm.usd_import(filepath=path, **used))
    report["scene_after"] = scene_settings(scene)
    report["cache_files"] = [{
        "name": c.name, "filepath": c.filepath, "is_sequence": c.is_sequence, "override_frame": c.override_frame,
        "frame": c.frame, "frame_offset": c.frame_offset, "scale": c.scale,
        "velocity_name": c.velocity_name, "velocity_unit": c.velocity_unit,
    } for c in bpy.data.cache_files]

    objects = sorted(scene.objects, key=lambda o: o.name)
    described = [describe_object(obj) for obj in objects]
    paths = {entry["name"]: entry["usd_path"] for entry in described}
    report["objects"] = described

    reference = pxr_reference(args.reference_python, path) if not args.no_reference else {"available": False}
    if reference.get("available"):
        prims = {p["path"]: p for p in reference["prims"]}
        for entry in described:
            prim = prims.get(entry["usd_path"])
            if prim is not None:
                entry["usd_type"] = prim["type"]
                entry["usd_purpose"] = prim.get("purpose")
                entry["usd_computed_purpose"] = prim.get("computed_purpose")
        imported = set(paths.values())
        geometry = [p for p in reference["prims"] if "primvars" in p]  # the Gprims
        reference["not_imported"] = [{"path": p["path"], "type": p["type"], "computed_purpose": p["computed_purpose"]}
                                     for p in geometry if p["path"] not in imported]
        reference["guide_prims"] = [{
            "path": p["path"], "imported": p["path"] in imported,
            "hide_render": next((e["hide_render"] for e in described if e["usd_path"] == p["path"]), None),
        } for p in geometry if p["computed_purpose"] == "guide"]
    report["usd"] = reference

    start, end = scene.frame_start, scene.frame_end
    # The quarter and middle frames tell the candidates apart; at the last one the later candidate is often
    # past the file's end, where USD holds the last sample, so that both candidates read the same.
    frames = args.frames or sorted({start, start + (end - start) // 4, (start + end) // 2, end})
    # Empties without a Transform Cache cannot move: leave them out of the samples.
    moving = [obj for obj in objects if obj.type != "EMPTY" or obj.constraints]
    report["samples"] = take_samples(bpy, scene, frames, moving)
    runs = [("samples", scene.render.fps / scene.render.fps_base)]
    if args.fps:
        scene.render.fps, scene.render.fps_base = args.fps, 1.0
        report["scene_with_fps"] = scene_settings(scene)
        report["samples_at_fps"] = take_samples(bpy, scene, frames, moving)
        runs.append(("samples_at_fps", float(args.fps)))

    if reference.get("available"):
        codes = set()
        for _, fps in runs:
            codes.update(f for f in frames)
            codes.update(f / fps * reference["stage"]["timeCodesPerSecond"] for f in frames)
        reference.update({k: v for k, v in pxr_reference(args.reference_python, path, codes, points=True).items()
                          if k == "samples"})
        for key, fps in runs:
            compare(report[key], reference, fps, paths)
        tcps = reference["stage"]["timeCodesPerSecond"]
        for key, _ in runs:
            for sample in report[key].values():
                for obj_sample in sample["objects"].values():
                    if "reads_time_code" in obj_sample:
                        obj_sample["usd_seconds"] = obj_sample["reads_time_code"] / tcps
        del reference["samples"]  # already merged into the samples
    for key, _ in runs:
        drop_private(report[key])
    report["summary"] = summary(report)
    return report


def summary(report: dict) -> dict:
    """The answers, read off the report: one line per question."""
    usd = report["usd"] if report["usd"].get("available") else None
    after = report["scene_after"]
    out = {"scene_fps_after_import": after["fps"] / after["fps_base"],
           "scene_frame_range_after_import": [after["frame_start"], after["frame_end"]]}
    if usd:
        out["file_fps"] = usd["stage"]["framesPerSecond"]
        out["file_time_code_range"] = [usd["stage"]["startTimeCode"], usd["stage"]["endTimeCode"]]
    for key in ("samples", "samples_at_fps"):
        if key not in report:
            continue
        read = {}
        for frame, sample in report[key].items():
            codes = {o["reads_time_code"] for o in sample["objects"].values() if "reads_time_code" in o}
            read[frame] = {"blender_seconds": sample["seconds"],
                           "usd_time_code_read": sorted(codes) or None,
                           "objects_matching_no_candidate": sorted(name for name, o in sample["objects"].items()
                                                                   if o.get("matches_no_candidate")),
                           "objects_same_at_every_candidate": sorted(name for name, o in sample["objects"].items()
                                                                     if "same_at_time_codes" in o),
                           "usd_seconds": sorted({o["usd_seconds"] for o in sample["objects"].values()
                                                  if "usd_seconds" in o}) or None}
        out["frame_reads" if key == "samples" else "frame_reads_at_fps"] = read
    meshes = [o for o in report["objects"] if "mesh" in o]
    prims = {p["path"]: p for p in usd["prims"]} if usd else {}

    def worst(name: str, key: str):
        """The largest of an object's per-sample comparisons ``key`` (a number [m], or the first reason none
        was made), over every sampled frame; per primvar for ``primvars_max_error_vs_usd``."""
        found = [s["objects"][name][key] for s in report["samples"].values() if key in s["objects"].get(name, {})]
        if key == "primvars_max_error_vs_usd":
            names = sorted({n for f in found for n in f})
            return {n: worst_of([f[n] for f in found if n in f]) for n in names} or None
        return worst_of(found)

    def worst_of(values):
        reasons = [v for v in values if isinstance(v, str)]
        return reasons[0] if reasons else max(values, default=None)

    out["meshes"] = {o["usd_path"]: {
        "points_max_error_vs_usd": worst(o["name"], "points_max_error_vs_usd"),
        "usd_primvars": prims.get(o["usd_path"], {}).get("primvars") if usd else None,
        "primvars_max_error_vs_usd": worst(o["name"], "primvars_max_error_vs_usd"),
        "polygon_sizes_blender": o["mesh"]["polygon_sizes"],
        "polygon_sizes_usd": prims.get(o["usd_path"], {}).get("polygon_sizes") if usd else None,
        "velocity_attribute": [n for n in ("velocity", "velocities") if o["mesh"][f"has_{n}_attribute"]] or None,
        "normals_max_angle_deg_vs_usd": max((s["objects"][o["name"]]["normals_max_angle_deg_vs_usd"]
                                             for s in report["samples"].values()
                                             if "normals_max_angle_deg_vs_usd" in s["objects"].get(o["name"], {})),
                                            default=None),
        "velocity_matches_usd": sorted({s["objects"][o["name"]]["velocity_equals_usd_velocities"]
                                        for s in report["samples"].values()
                                        if "velocity_equals_usd_velocities" in s["objects"].get(o["name"], {})})
                                or None,
        "usd_face_sets": [f"{s['familyName']}:{s['name']}" + (f" -> {s['material'][0]}" if s["material"] else "")
                          for s in prims.get(o["usd_path"], {}).get("subsets", [])] if usd else None,
        "material_slots": o["mesh"]["materials"],
        "faces_per_material_slot": o["mesh"].get("faces_of_material_slot", o["mesh"]["faces_per_material_slot"]),
        "uv_maps": o["mesh"]["uv_maps"],
        "other_modifiers": [m["type"] for m in o["modifiers"] if m["type"] != "MESH_SEQUENCE_CACHE"],
        "vertex_groups": o["vertex_groups"],
        "face_attributes": [a[0] for a in o["mesh"]["attributes"] if a[1] == "FACE" and not a[0].startswith(".")],
        "sequence_cache": [m["read_data"] for m in o["modifiers"] if m["type"] == "MESH_SEQUENCE_CACHE"] or None,
    } for o in meshes}
    out["other_geometry"] = {o["usd_path"]: {
        "type": o["type"], "usd_type": o.get("usd_type"), "points": o.get("geometry", {}).get("points"),
        "attributes": [a[0] for a in o.get("geometry", {}).get("attributes", []) if not a[0].startswith(".")],
        "points_max_error_vs_usd": worst(o["name"], "points_max_error_vs_usd"),
        "usd_primvars": prims.get(o["usd_path"], {}).get("primvars") if usd else None,
        "primvars_max_error_vs_usd": worst(o["name"], "primvars_max_error_vs_usd"),
    } for o in report["objects"] if o["type"] in ("CURVES", "POINTCLOUD", "CURVE")}
    if usd:
        out["guide_prims"] = usd["guide_prims"]
        out["not_imported"] = [p["path"] for p in usd["not_imported"]]
    return out


def main(argv=None) -> int:
    if argv is None:  # inside `blender -b --python tools/blender_check.py -- ARGS`, the script's own are after --
        argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("usd_file", nargs="?", help="the USD file to import (.usd, .usda, .usdc)")
    parser.add_argument("--fps", type=int, help="after the import, set scene.render.fps = N and sample again")
    parser.add_argument("--frames", type=int, nargs="+",
                        help="frames to sample (default: the first, quarter, middle and last frame of the scene's "
                             "range after the import)")
    parser.add_argument("--option", type=parse_option, action="append", default=[], metavar="KEY=VALUE",
                        help="an option of bpy.ops.wm.usd_import, e.g. import_guide=True (repeatable)")
    parser.add_argument("--reference-python", default=sys.executable,
                        help="a Python with pxr (usd-core) to read the file for comparison (default: this one)")
    parser.add_argument("--no-reference", action="store_true", help="do not read the file with pxr")
    parser.add_argument("--write-sample", metavar="PATH", help="write the hand-authored sample .usda to PATH and stop")
    args = parser.parse_args(argv)
    if args.write_sample:
        with open(args.write_sample, "w", encoding="utf-8") as f:
            f.write(sample_usda())
        print(f"wrote {args.write_sample}", file=sys.stderr)
        return 0
    if not args.usd_file:
        parser.error("a USD file is needed (or --write-sample PATH)")

    # Blender writes its log to stdout (the C stdout): send everything to stderr while it works, and keep the
    # real stdout for the JSON report alone.
    sys.stdout.flush()
    report_fd = os.dup(1)
    os.dup2(2, 1)
    stdout, sys.stdout = sys.stdout, sys.stderr
    try:
        report = check(args)
    finally:
        sys.stdout.flush()
        os.dup2(report_fd, 1)
        os.close(report_fd)
        sys.stdout = stdout
    print(compact_json(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
