"""A cloth read from a dressed USD asset comes back dressed: the round trip a DCC tool makes (an asset authored
here with pxr the way Blender's exporter writes one: Y-up, centimetres, a non-identity transform, two UV sets,
two GeomSubsets bound to two materials, custom primvars of every interpolation) run as a cloth for a few
frames on the CPU, then the output reopened with pxr: every primvar with its values, interpolation, indices and
role, the subsets with their family and bindings resolving to materials in the output, the subdivision scheme,
orientation, prim name and kind as authored, and the faces in their authored order."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdShade, Vt

import warpspring as ws
from warpspring.io.usd import UsdWriter

NX, NY, CELL = 6, 4, 5.0  # quads across and along, and their side [cm]
PRIM = "/Root/Sheet"


def _material(stage: Usd.Stage, path: str, color) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, path)
    shader = UsdShade.Shader.Define(stage, f"{path}/Principled")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*color))
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    return material


def _author(path: Path, *, mirror: float = 1.0, orientation: str = "leftHanded") -> dict:
    """Write the dressed sheet; return what was authored, to compare the output with."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/Root").GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, PRIM)
    xform = UsdGeom.Xformable(mesh)
    xform.AddTranslateOp().Set(Gf.Vec3d(10.0, 150.0, -20.0))
    xform.AddRotateXYZOp().Set(Gf.Vec3f(-90.0, 0.0, 30.0))
    xform.AddScaleOp().Set(Gf.Vec3f(mirror, 1.5, 1.0))
    points = np.array([(i * CELL, j * CELL, 0.0) for j in range(NY + 1) for i in range(NX + 1)])
    quads = np.array([(j * (NX + 1) + i, j * (NX + 1) + i + 1, (j + 1) * (NX + 1) + i + 1, (j + 1) * (NX + 1) + i)
                      for j in range(NY) for i in range(NX)])
    quads = np.array([np.roll(q, k) for k, q in enumerate(quads)])  # face-vertex orders that do not start alike
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(quads)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(quads.reshape(-1).astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.bilinear)
    mesh.CreateOrientationAttr(orientation)
    Usd.ModelAPI(mesh.GetPrim()).SetKind(Kind.Tokens.component)

    api = UsdGeom.PrimvarsAPI(mesh)
    corners = points[quads.reshape(-1), :2] / np.array([NX * CELL, NY * CELL])  # per face-vertex, in authored order
    unique, index = np.unique(np.round(corners, 6), axis=0, return_inverse=True)
    st = api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray.FromNumpy(unique.astype(np.float32)))
    st.SetIndices(Vt.IntArray.FromNumpy(index.reshape(-1).astype(np.int32)))
    uv2 = api.CreatePrimvar("uv2", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    uv2.Set(Vt.Vec2fArray.FromNumpy((points[:, :2] / 7.0 + 0.25).astype(np.float32)))
    panel = np.arange(len(quads), dtype=np.int32) % 3
    api.CreatePrimvar("panel", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(Vt.IntArray.FromNumpy(panel))
    api.CreatePrimvar("fabric", Sdf.ValueTypeNames.String, UsdGeom.Tokens.constant).Set("denim")
    api.CreatePrimvar("grain", Sdf.ValueTypeNames.Double3, UsdGeom.Tokens.constant).Set(Gf.Vec3d(0.0, 1.0, 0.5))
    api.CreatePrimvar("tags", Sdf.ValueTypeNames.TokenArray, UsdGeom.Tokens.constant).Set(Vt.TokenArray(["hem", "seam"]))
    api.CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.constant).Set(
        Vt.Vec3fArray([Gf.Vec3f(0.2, 0.3, 0.4)]))
    api.CreatePrimvar("weight", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.varying).Set(
        Vt.FloatArray.FromNumpy(np.linspace(0.0, 1.0, len(points)).astype(np.float32)))

    red, blue = _material(stage, "/Root/Looks/Red", (1, 0, 0)), _material(stage, "/Root/Looks/Blue", (0, 0, 1))
    binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
    half = len(quads) // 2
    for name, faces, material in (("Red", range(half), red), ("Blue", range(half, len(quads)), blue)):
        subset = binding.CreateMaterialBindSubset(name, Vt.IntArray(list(faces)), UsdGeom.Tokens.face)
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(material)
    binding.SetMaterialBindSubsetsFamilyType(UsdGeom.Tokens.partition)
    stage.GetRootLayer().Save()
    return {"indices": quads.reshape(-1)}


def _run(asset: Path, out: Path) -> None:
    builder = ws.ModelBuilder(up_axis="Y")
    builder.add_cloth_mesh(str(asset), prim=PRIM, density=0.2, pin=[0, NX])
    model = builder.finalize("cpu")
    sim = ws.Simulator(model, integrator=ws.make_integrator("implicit_euler", model), fps=60, substeps=4)
    with UsdWriter(out, model, fps=60, primvars=["strain", "pinned", "rest"]) as writer:
        writer.write_frame(sim.state)
        for _ in range(3):
            sim.step_frame()
            writer.write_frame(sim.state)


def _primvars(prim: Usd.Prim) -> dict:
    out = {}
    for primvar in UsdGeom.PrimvarsAPI(prim).GetAuthoredPrimvars():
        indices = primvar.GetIndices() if primvar.IsIndexed() else None
        out[primvar.GetPrimvarName()] = (str(primvar.GetTypeName()), primvar.GetInterpolation(), primvar.Get(),
                                         None if indices is None else list(indices), primvar.GetElementSize())
    return out


def _subsets(prim: Usd.Prim) -> dict:
    out = {}
    for subset in UsdGeom.Subset.GetAllGeomSubsets(UsdGeom.Imageable(prim)):
        material, _ = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()
        color = None
        if material:
            shader = material.ComputeSurfaceSource()[0]
            color = tuple(shader.GetInput("diffuseColor").Get())
        out[subset.GetPrim().GetName()] = (subset.GetElementTypeAttr().Get(), subset.GetFamilyNameAttr().Get(),
                                           list(subset.GetIndicesAttr().Get()), color)
    return out


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_a_dressed_asset_comes_back_dressed(tmp_path: Path, suffix: str):
    asset, out = tmp_path / f"sheet{suffix}", tmp_path / f"out{suffix}"
    authored = _author(asset)
    _run(asset, out)
    source_stage = Usd.Stage.Open(str(asset))
    source = source_stage.GetPrimAtPath(PRIM)
    stage = Usd.Stage.Open(str(out))
    prim = stage.GetPrimAtPath("/World/Sheet")  # the prim's own name
    assert prim.IsValid() and prim.IsA(UsdGeom.Mesh)
    mesh = UsdGeom.Mesh(prim)

    # faces in authored order, so faceVarying and uniform data still land on their faces and corners
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == authored["indices"].tolist()
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [4] * (NX * NY)
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.bilinear
    assert mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    assert Usd.ModelAPI(prim).GetKind() == Kind.Tokens.component

    expected, got = _primvars(source), _primvars(prim)
    for name, value in expected.items():
        assert name in got, f"primvar {name} lost"
        assert got[name] == value, f"primvar {name}: {got[name]} != {value}"
    assert got["st"][0] == "texCoord2f[]" and got["uv2"][0] == "texCoord2f[]"  # the role kept
    for name in ("strain", "pinned", "rest"):  # the simulation's own primvars beside them
        assert got[name][1] == UsdGeom.Tokens.vertex

    subsets = _subsets(prim)
    assert subsets == {"Red": ("face", "materialBind", list(range(NX * NY // 2)), (1.0, 0.0, 0.0)),
                       "Blue": ("face", "materialBind", list(range(NX * NY // 2, NX * NY)), (0.0, 0.0, 1.0))}
    assert UsdGeom.Subset.GetFamilyType(UsdGeom.Imageable(prim), "materialBind") == UsdGeom.Tokens.partition
    for name in ("Red", "Blue"):  # the bound materials are in the output stage itself, which stands alone
        target = UsdShade.MaterialBindingAPI(stage.GetPrimAtPath(f"/World/Sheet/{name}")).GetDirectBindingRel().GetTargets()
        assert len(target) == 1 and stage.GetRootLayer().GetPrimAtPath(target[0]) is not None
    assert not stage.GetRootLayer().GetExternalReferences()


def test_an_authored_primvar_named_like_the_simulations_is_kept_and_the_simulations_skipped(tmp_path: Path):
    """The asset authors ``pinned`` (uniform) and ``strain`` (constant): the output keeps both as authored, with
    no time samples, and still writes the simulation's ``rest``, which the asset does not author."""
    asset, out = tmp_path / "sheet.usda", tmp_path / "out.usda"
    _author(asset)
    stage = Usd.Stage.Open(str(asset))
    api = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(PRIM))
    api.CreatePrimvar("pinned", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(Vt.IntArray([1] * NX * NY))
    api.CreatePrimvar("strain", Sdf.ValueTypeNames.Float, UsdGeom.Tokens.constant).Set(0.5)
    stage.Save()
    _run(asset, out)
    output = Usd.Stage.Open(str(out))
    got = UsdGeom.PrimvarsAPI(output.GetPrimAtPath("/World/Sheet"))
    pinned, strain, rest = got.GetPrimvar("pinned"), got.GetPrimvar("strain"), got.GetPrimvar("rest")
    assert pinned.GetInterpolation() == UsdGeom.Tokens.uniform and list(pinned.Get()) == [1] * NX * NY
    assert strain.GetInterpolation() == UsdGeom.Tokens.constant and strain.Get() == 0.5
    assert not pinned.GetAttr().GetTimeSamples() and not strain.GetAttr().GetTimeSamples()
    assert rest.GetInterpolation() == UsdGeom.Tokens.vertex and len(rest.Get()) == (NX + 1) * (NY + 1)


def test_a_mirroring_transform_flips_the_written_orientation_and_the_normals_face_the_front(tmp_path: Path):
    """Points are written in world space, so a right-handed mesh under a mirroring transform (scale x -1) is
    written left-handed, with its faces as authored; the normals written face that orientation's front (the
    left-hand rule on the authored face order), as the asset's front faces in world space."""
    asset, out = tmp_path / "sheet.usda", tmp_path / "out.usda"
    authored = _author(asset, mirror=-1.0, orientation=UsdGeom.Tokens.rightHanded)
    _run(asset, out)
    stage = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Sheet"))
    assert mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == authored["indices"].tolist()
    x = np.array(mesh.GetPointsAttr().Get(0.0), dtype=np.float64)
    normals = np.array(mesh.GetNormalsAttr().Get(0.0), dtype=np.float64)
    for face in authored["indices"].reshape(-1, 4):
        a, b, c = x[face[0]], x[face[1]], x[face[2]]
        left_hand = -np.cross(b - a, c - a)
        assert np.dot(left_hand, normals[face[0]]) > 0.0


# -- soft bodies: the same dressing, by the same path ---------------------------------------------------------------

CUBE = "/Root/Box"


def _author_cube(path: Path, *, normals: str | None = None, creases: bool = False) -> dict:
    """A dressed box of quads (40 cm, Y-up, centimetres, moved and turned), with UVs per face-vertex, a custom
    uniform primvar, two subsets bound to two materials; ``normals``: authored ``faceVarying`` (flat faces: every
    edge hard), ``vertex`` (smooth), or none; ``creases``: every edge an infinitely sharp crease."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/Root").GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, CUBE)
    xform = UsdGeom.Xformable(mesh)
    xform.AddTranslateOp().Set(Gf.Vec3d(5.0, 60.0, -10.0))
    xform.AddRotateXYZOp().Set(Gf.Vec3f(10.0, 25.0, 0.0))
    corners = np.array([[x, y, z] for z in (0.0, 40.0) for y in (0.0, 40.0) for x in (0.0, 40.0)])
    quads = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(corners.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * 6))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(quads.reshape(-1).astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    Usd.ModelAPI(mesh.GetPrim()).SetKind(Kind.Tokens.component)
    api = UsdGeom.PrimvarsAPI(mesh)
    st = np.tile([[0, 0], [1, 0], [1, 1], [0, 1]], (6, 1)).astype(np.float32)
    api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying).Set(Vt.Vec2fArray.FromNumpy(st))
    api.CreatePrimvar("panel", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(Vt.IntArray([0, 1, 2, 0, 1, 2]))
    centre = corners.mean(axis=0)
    face_normal = np.array([np.cross(corners[q[1]] - corners[q[0]], corners[q[2]] - corners[q[0]]) for q in quads])
    face_normal /= np.linalg.norm(face_normal, axis=1, keepdims=True)
    assert all(np.dot(n, corners[q].mean(axis=0) - centre) > 0 for n, q in zip(face_normal, quads))  # outward
    if normals == "faceVarying":
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.repeat(face_normal, 4, axis=0).astype(np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    elif normals == "vertex":
        smooth = (corners - centre) / np.linalg.norm(corners - centre, axis=1, keepdims=True)
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(smooth.astype(np.float32)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    if creases:
        edges = sorted({tuple(sorted((int(q[k]), int(q[(k + 1) % 4])))) for q in quads for k in range(4)})
        mesh.CreateCreaseIndicesAttr(Vt.IntArray([v for e in edges for v in e]))
        mesh.CreateCreaseLengthsAttr(Vt.IntArray([2] * len(edges)))
        mesh.CreateCreaseSharpnessesAttr(Vt.FloatArray([UsdGeom.Mesh.SHARPNESS_INFINITE] * len(edges)))
    red, blue = _material(stage, "/Root/Looks/Red", (1, 0, 0)), _material(stage, "/Root/Looks/Blue", (0, 0, 1))
    binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
    for name, faces, material in (("Red", [0, 1, 2], red), ("Blue", [3, 4, 5], blue)):
        subset = binding.CreateMaterialBindSubset(name, Vt.IntArray(faces), UsdGeom.Tokens.face)
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()
    return {"indices": quads.reshape(-1), "face_normal": face_normal}


def _run_cube(asset: Path, out: Path, frames: int = 3) -> None:
    builder = ws.ModelBuilder(up_axis="Y")
    builder.add_soft_body(str(asset), prim=CUBE, method="voxel", youngs_modulus=2.0e4, density=100.0, spacing=0.1)
    model = builder.finalize("cpu")
    sim = ws.Simulator(model, integrator=ws.make_integrator("implicit_euler", model), fps=60, substeps=4)
    with UsdWriter(out, model, fps=60, primvars=["strain", "pinned", "rest"]) as writer:
        writer.write_frame(sim.state)
        for _ in range(frames):
            sim.step_frame()
            writer.write_frame(sim.state)


def test_a_soft_body_from_a_dressed_asset_comes_back_dressed(tmp_path: Path):
    """The soft body's skin goes through the cloth's path: its UVs, custom primvar, subsets with their family and
    materials, kind and the prim's own name come back."""
    asset, out = tmp_path / "box.usda", tmp_path / "out.usda"
    authored = _author_cube(asset)
    _run_cube(asset, out)
    source_stage = Usd.Stage.Open(str(asset))
    source = source_stage.GetPrimAtPath(CUBE)
    stage = Usd.Stage.Open(str(out))
    prim = stage.GetPrimAtPath("/World/Box")
    assert prim.IsValid() and prim.IsA(UsdGeom.Mesh)
    assert list(UsdGeom.Mesh(prim).GetFaceVertexIndicesAttr().Get()) == authored["indices"].tolist()
    assert Usd.ModelAPI(prim).GetKind() == Kind.Tokens.component
    expected, got = _primvars(source), _primvars(prim)
    for name, value in expected.items():
        assert got.get(name) == value, f"primvar {name}: {got.get(name)} != {value}"
    for name in ("strain", "pinned", "rest"):
        assert got[name][1] == UsdGeom.Tokens.vertex and len(UsdGeom.PrimvarsAPI(prim).GetPrimvar(name).Get(0.0)) == 8
    assert _subsets(prim) == {"Red": ("face", "materialBind", [0, 1, 2], (1.0, 0.0, 0.0)),
                              "Blue": ("face", "materialBind", [3, 4, 5], (0.0, 0.0, 1.0))}


# -- normals with the authored interpolation; hard edges stay hard --------------------------------------------------


def _world_normals(asset: Path, normals_local: np.ndarray) -> np.ndarray:
    """Local normals of the box in warpspring's Y-up world frame: the inverse transpose of its transform."""
    stage = Usd.Stage.Open(str(asset))
    prim = stage.GetPrimAtPath(CUBE)
    linear = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(0.0))[:3, :3]
    n = normals_local @ np.linalg.inv(linear).T
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.mark.parametrize("how", ["faceVarying", "creases"])
def test_hard_edges_stay_hard(tmp_path: Path, how: str):
    """A box whose every edge is hard (flat faceVarying normals, or smooth vertex normals with every edge an
    infinitely sharp crease) comes back with faceVarying normals, each face-vertex's normal its own face's: at rest
    the authored flat normals (turned into world space), and every frame the face's normal of the points written
    (a box's faces stay nearly flat). Smoothing across the edges would give the corner's diagonal instead, 55°
    away."""
    asset, out = tmp_path / "box.usda", tmp_path / "out.usda"
    authored = _author_cube(asset, normals="faceVarying" if how == "faceVarying" else "vertex", creases=how == "creases")
    _run_cube(asset, out)
    output = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(output.GetPrimAtPath("/World/Box"))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.faceVarying
    at_rest = np.array(mesh.GetNormalsAttr().Get(0.0), dtype=np.float64)
    expected = _world_normals(asset, np.repeat(authored["face_normal"], 4, axis=0))
    np.testing.assert_allclose(at_rest, expected, atol=1e-6)  # float32 points of a 40 cm box
    quads = authored["indices"].reshape(6, 4)
    for t in (1.0, 2.0, 3.0):
        x = np.array(mesh.GetPointsAttr().Get(t), dtype=np.float64)
        n = np.array(mesh.GetNormalsAttr().Get(t), dtype=np.float64).reshape(6, 4, 3)
        for face, corner_normals in zip(quads, n):
            p = x[face] - x[face[0]]
            newell = np.cross(p, np.roll(p, -1, axis=0)).sum(axis=0)
            np.testing.assert_allclose(corner_normals, np.tile(newell / np.linalg.norm(newell), (4, 1)), atol=1e-5)


def test_vertex_normals_stay_smooth_and_uniform_ones_per_face(tmp_path: Path):
    """Authored vertex normals (no crease): vertex normals, one per point, each an area-weighted mean of the three
    faces at the box's corner (a blend with positive weights of their normals: smooth across the edges);
    authored uniform normals: one per face, the face's own."""
    asset, out = tmp_path / "box.usda", tmp_path / "out.usda"
    authored = _author_cube(asset, normals="vertex")
    _run_cube(asset, out, frames=1)
    output = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(output.GetPrimAtPath("/World/Box"))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    normals = np.array(mesh.GetNormalsAttr().Get(0.0), dtype=np.float64)
    assert normals.shape == (8, 3)
    faces = _world_normals(asset, authored["face_normal"])
    quads = authored["indices"].reshape(6, 4)
    for vertex, n in enumerate(normals):
        around = faces[[f for f, q in enumerate(quads) if vertex in q]]  # the corner's three faces
        weights = np.linalg.solve(around.T, n)
        assert (weights > 0.1).all(), weights  # each face counts: no edge is hard

    stage = Usd.Stage.Open(str(asset))
    box = UsdGeom.Mesh(stage.GetPrimAtPath(CUBE))
    box.GetNormalsAttr().Set(Vt.Vec3fArray([Gf.Vec3f(0, 0, 1)] * 6))
    box.SetNormalsInterpolation(UsdGeom.Tokens.uniform)
    stage.Save()
    _run_cube(asset, out, frames=1)
    output = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(output.GetPrimAtPath("/World/Box"))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.uniform
    flat = _author_cube(tmp_path / "flat.usda")["face_normal"]
    np.testing.assert_allclose(np.array(mesh.GetNormalsAttr().Get(0.0)), _world_normals(asset, flat), atol=1e-6)
