"""The simulation as a layer over the artist's own asset, composed back with pxr: an asset authored here the way
Blender's exporter writes one (Y-up, centimetres, 24 time codes per second, a non-identity transform, UVs, two
materials) is simulated at 60 fps in warpspring's Z-up metres, and the layer written over it is composed onto the
untouched asset by a sublayer and by a reference (from the layer), and by a shot that stacks the layer's bare
overrides over the asset (both orders of composition): the composed world points equal the simulation's within
1e-6 m at every frame, the dressing is the asset's, and the asset file is byte for byte as it was. Then the
accelerations: in free flight the written acceleration is the integrator's exact one, so the quadratic
x + v Δt + ½ a Δt² lands on the next sample; across an impact, the quadratic's error half-way between samples
against the path sampled there."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdShade, Vt

import warpspring as ws
from warpspring.core.mesh_files import convert_up_axis
from warpspring.errors import ConfigError
from warpspring.io.usd import UsdWriter

NX, NY, CELL = 6, 4, 5.0  # quads across and along, their side [cm]
PRIM = "/Root/Sheet"
FPS, SUBSTEPS, FRAMES = 60.0, 4, 4


def _author(path: Path, *, normals_primvar: bool = False) -> None:
    """The artist's sheet: Y-up, centimetres, 24 time codes per second, moved, turned and scaled; faceVarying UVs,
    a uniform custom primvar, two subsets bound to two materials under the default prim."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(24.0)
    stage.SetFramesPerSecond(24.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/Root").GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, PRIM)
    xform = UsdGeom.Xformable(mesh)
    xform.AddTranslateOp().Set(Gf.Vec3d(10.0, 150.0, -20.0))
    xform.AddRotateXYZOp().Set(Gf.Vec3f(-90.0, 0.0, 30.0))
    xform.AddScaleOp().Set(Gf.Vec3f(1.0, 1.5, 1.0))
    points = np.array([(i * CELL, j * CELL, 0.0) for j in range(NY + 1) for i in range(NX + 1)])
    quads = np.array([(j * (NX + 1) + i, j * (NX + 1) + i + 1, (j + 1) * (NX + 1) + i + 1, (j + 1) * (NX + 1) + i)
                      for j in range(NY) for i in range(NX)])
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(quads)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(quads.reshape(-1).astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    Usd.ModelAPI(mesh.GetPrim()).SetKind(Kind.Tokens.component)
    api = UsdGeom.PrimvarsAPI(mesh)
    st = points[quads.reshape(-1), :2] / np.array([NX * CELL, NY * CELL])
    api.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying).Set(
        Vt.Vec2fArray.FromNumpy(st.astype(np.float32)))
    api.CreatePrimvar("panel", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform).Set(
        Vt.IntArray.FromNumpy(np.arange(len(quads), dtype=np.int32) % 3))
    up = Vt.Vec3fArray([Gf.Vec3f(0.0, 0.0, 1.0)] * len(points))
    if normals_primvar:  # indexed, as some exporters write them
        normals = api.CreatePrimvar("normals", Sdf.ValueTypeNames.Normal3fArray, UsdGeom.Tokens.vertex)
        normals.Set(Vt.Vec3fArray([Gf.Vec3f(0.0, 0.0, 1.0)]))
        normals.SetIndices(Vt.IntArray([0] * len(points)))
    else:
        mesh.CreateNormalsAttr(up)
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
    half = len(quads) // 2
    for name, faces, color in (("Red", range(half), (1, 0, 0)), ("Blue", range(half, len(quads)), (0, 0, 1))):
        material = UsdShade.Material.Define(stage, f"/Root/Looks/{name}")
        shader = UsdShade.Shader.Define(stage, f"/Root/Looks/{name}/Principled")
        shader.CreateIdAttr("UsdPreviewSurface")
        shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*color))
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        subset = binding.CreateMaterialBindSubset(name, Vt.IntArray(list(faces)), UsdGeom.Tokens.face)
        UsdShade.MaterialBindingAPI.Apply(subset.GetPrim()).Bind(material)
    binding.SetMaterialBindSubsetsFamilyType(UsdGeom.Tokens.partition)
    stage.GetRootLayer().Save()


def _simulate(asset: Path, out: Path, **options) -> tuple[list, list]:
    """Run the sheet (pinned at two corners) in warpspring's Z-up metres; the particles' positions and velocities
    of every frame written, float64."""
    builder = ws.ModelBuilder(up_axis="Z")
    builder.add_cloth_mesh(str(asset), prim=PRIM, density=0.2, pin=[0, NX])
    model = builder.finalize("cpu")
    sim = ws.Simulator(model, integrator=ws.make_integrator("implicit_euler", model), fps=FPS, substeps=SUBSTEPS)
    q, v = [], []
    with UsdWriter(out, model, fps=FPS, layer_over=asset, primvars=["strain"], **options) as writer:
        for frame in range(FRAMES):
            if frame:
                sim.step_frame()
            writer.write_frame(sim.state)
            q.append(sim.state.particle_q.numpy().astype(np.float64))
            v.append(sim.state.particle_qd.numpy().astype(np.float64))
    return q, v


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _composed(how: str, asset: Path, layer: Path) -> Usd.Stage:
    if how in ("sublayer", "reference"):  # the layer opened on its own
        return Usd.Stage.Open(str(layer))
    if how == "shot":  # a shot stacks the bare overrides over the asset
        shot = Sdf.Layer.CreateAnonymous(".usda")
        shot.subLayerPaths.append(str(layer))
        shot.subLayerPaths.append(str(asset))
        return Usd.Stage.Open(shot)
    stage = Usd.Stage.Open(str(asset))  # "session": the asset opened, the overrides laid over it, the file untouched
    stage.GetSessionLayer().subLayerPaths.append(str(layer))
    return stage


def _world(stage: Usd.Stage, time_code: float, attribute: str = "points") -> np.ndarray:
    """The sheet's composed world values in warpspring's frame (metres, Z-up): points, or with ``velocities``
    the local vectors turned by the transform's linear part."""
    prim = stage.GetPrimAtPath(PRIM)
    matrix = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time_code), dtype=np.float64)
    local = np.array(prim.GetAttribute(attribute).Get(time_code), dtype=np.float64)
    world = local @ matrix[:3, :3] + (matrix[3, :3] if attribute == "points" else 0.0)
    units = UsdGeom.GetStageMetersPerUnit(stage)
    return convert_up_axis(world * units, str(UsdGeom.GetStageUpAxis(stage)), "Z")


@pytest.mark.parametrize("arc, how", [("sublayer", "sublayer"), ("reference", "reference"), ("none", "shot"),
                                      ("none", "session")])
def test_the_layer_composes_onto_the_untouched_asset(tmp_path: Path, arc: str, how: str):
    asset, layer = tmp_path / "sheet.usda", tmp_path / "sim.usda"
    _author(asset)
    before = _digest(asset)
    q, v = _simulate(asset, layer, layer_arc=arc)
    assert _digest(asset) == before  # never written
    stage = _composed(how, asset, layer)
    assert stage.GetTimeCodesPerSecond() == 24.0 and UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    step = 24.0 / FPS  # time codes per simulated frame
    moved = 0.0
    for frame in range(FRAMES):
        t = frame * step
        # float32 points of ~2 m in centimetres round at ~1e-5 cm = 1e-7 m, well within 1e-6 m
        np.testing.assert_allclose(_world(stage, t), q[frame], atol=1e-6)
        np.testing.assert_allclose(_world(stage, t, "velocities"), v[frame], atol=1e-5)
        moved = max(moved, float(np.abs(q[frame] - q[0]).max()))
    assert moved > 1e-3  # the sheet fell: the comparison is not of the rest pose alone
    # the dressing is the asset's: topology, UVs, the custom primvar, the materials bound per subset
    prim = stage.GetPrimAtPath(PRIM)
    source_stage = Usd.Stage.Open(str(asset))
    source = source_stage.GetPrimAtPath(PRIM)
    for name in ("st", "panel"):
        assert list(UsdGeom.PrimvarsAPI(prim).GetPrimvar(name).Get()) == list(UsdGeom.PrimvarsAPI(source).GetPrimvar(name).Get())
    for name, color in (("Red", (1.0, 0.0, 0.0)), ("Blue", (0.0, 0.0, 1.0))):
        material, _ = UsdShade.MaterialBindingAPI(stage.GetPrimAtPath(f"{PRIM}/{name}")).ComputeBoundMaterial()
        assert tuple(material.ComputeSurfaceSource()[0].GetInput("diffuseColor").Get()) == color
    assert Usd.ModelAPI(prim).GetKind() == Kind.Tokens.component
    # the layer holds only what the simulation changes
    written = Sdf.Layer.FindOrOpen(str(layer))
    spec = written.GetPrimAtPath(PRIM)
    assert spec.specifier == Sdf.SpecifierOver
    assert sorted(spec.attributes.keys()) == ["accelerations", "extent", "normals", "points", "primvars:strain",
                                              "velocities"]
    assert not written.GetPrimAtPath("/World") and not written.GetPrimAtPath("/warpspring")  # nothing else


def test_normals_over_an_indexed_primvar_override_it(tmp_path: Path):
    """An asset whose normals are an indexed ``primvars:normals`` (which USD prefers over ``normals``): the layer
    overrides that primvar, its indices blocked, so the composed normals are the simulation's."""
    asset, layer = tmp_path / "sheet.usda", tmp_path / "sim.usdc"
    _author(asset, normals_primvar=True)
    _simulate(asset, layer)
    stage = Usd.Stage.Open(str(layer))
    normals = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(PRIM)).GetPrimvar("normals")
    assert not normals.IsIndexed() and normals.GetInterpolation() == UsdGeom.Tokens.vertex
    last = (FRAMES - 1) * 24.0 / FPS
    n = np.array(normals.ComputeFlattened(last), dtype=np.float64)
    assert n.shape == ((NX + 1) * (NY + 1), 3)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    assert np.abs(n - (0.0, 0.0, 1.0)).max() > 1e-3  # the sheet bent: not the asset's flat normals


def test_a_layer_needs_a_surface_read_from_the_asset(tmp_path: Path):
    asset = tmp_path / "sheet.usda"
    _author(asset)
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=2, ny=2, spacing=0.1, mass=0.1)
    model = builder.finalize("cpu")
    with pytest.raises(ConfigError, match="reads no mesh from that file"):
        UsdWriter(tmp_path / "sim.usda", model, fps=FPS, layer_over=asset)
    with pytest.raises(ConfigError, match="layer_arc"):
        UsdWriter(tmp_path / "sim.usda", model, fps=FPS, layer_over=asset, layer_arc="payload")


# -- accelerations --------------------------------------------------------------------------------------------------


def _falling(tmp_path: Path, *, ground: bool, fps: float, substeps: int, frames: int):
    """A free 8 × 8 cloth dropped from 5 cm (onto a ground plane at z = 0 with ``ground``): the written points,
    velocities and accelerations of the cloth per frame."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.05, origin=(0.0, 0.0, 0.05), mass=1.0)
    if ground:
        builder.add_collider_plane(friction=0.3)
    model = builder.finalize("cpu")
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=fps, substeps=substeps)
    path = tmp_path / f"fall_{fps:g}.usdc"
    with UsdWriter(path, model, fps=fps) as writer:
        writer.write_frame(sim.state)
        for _ in range(frames):
            sim.step_frame()
            writer.write_frame(sim.state)
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth"))
    read = [[np.array(a.Get(float(k)), dtype=np.float64) for k in range(frames + 1)]
            for a in (mesh.GetPointsAttr(), mesh.GetVelocitiesAttr(), mesh.GetAccelerationsAttr())]
    return read, mesh.GetAccelerationsAttr().GetTimeSamples()


def test_accelerations_in_free_flight_land_on_the_next_sample(tmp_path: Path):
    """Symplectic Euler with n substeps of h = Δt/n gives x(Δt) = x + v Δt + ½ g Δt² (1 + 1/n) exactly, so the
    acceleration written must be g (1 + 1/n) (not g: it is the one whose quadratic meets the next sample), and the
    quadratic lands on the next sample to the float32 rounding of the points, where velocities alone miss by
    ½ g Δt² (1 + 1/n)."""
    fps, n, frames = 30.0, 32, 4
    (x, v, a), times = _falling(tmp_path, ground=False, fps=fps, substeps=n, frames=frames)
    dt = 1.0 / fps
    assert list(times) == [float(k) for k in range(frames + 1)]
    np.testing.assert_array_equal(a[frames], a[frames - 1])  # the last frame has no next one: the frame before's
    expected = np.array([0.0, 0.0, -9.81 * (1.0 + 1.0 / n)])
    for k in range(frames):
        # a = 2 (x₁ − x₀ − v₀ Δt) / Δt² from float32 points of ~0.4 m: rounding 2 · 3e-8 m / Δt² ≈ 5e-5 m/s²
        np.testing.assert_allclose(a[k], np.broadcast_to(expected, a[k].shape), atol=1e-3)
        quadratic = x[k] + v[k] * dt + 0.5 * a[k] * dt * dt
        np.testing.assert_allclose(quadratic, x[k + 1], atol=1e-6)
        assert np.abs(x[k] + v[k] * dt - x[k + 1]).max() == pytest.approx(0.5 * 9.81 * dt * dt * (1 + 1 / n), rel=1e-3)


def test_accelerations_across_an_impact_measured_half_way(tmp_path: Path):
    """A cloth dropped from 5 cm lands on the ground in frame 2 (30 fps). At every frame the quadratic with the
    written accelerations lands on the next sample (frame k's acceleration is frame k's, also at the impact and at
    rest). Half-way between samples it is compared with the same run sampled there (twice the frame rate, the same
    substep): in free flight it is off by g h Δt / 8 exactly (the integrator's own departure from a parabola), 30×
    better than the velocities alone; across the impact no quadratic follows the kink of the path, and both errors are
    printed (docs/usd.md quotes them)."""
    frames, fps, substeps = 6, 30.0, 32
    (x, v, a), _ = _falling(tmp_path, ground=True, fps=fps, substeps=substeps, frames=frames)
    (fine, _, _), _ = _falling(tmp_path, ground=True, fps=2 * fps, substeps=substeps // 2, frames=2 * frames)
    dt, h = 1.0 / fps, 1.0 / (fps * substeps)
    linear, quadratic = [], []
    for k in range(frames):
        np.testing.assert_allclose(x[k] + v[k] * dt + 0.5 * a[k] * dt * dt, x[k + 1], atol=1e-6)
        half = fine[2 * k + 1]
        linear.append(np.abs(x[k] + v[k] * dt / 2 - half).max())
        quadratic.append(np.abs(x[k] + v[k] * dt / 2 + a[k] * dt * dt / 8 - half).max())
    linear, quadratic = np.array(linear), np.array(quadratic)
    print(f"half-way error [mm] per frame: velocities {np.round(1e3 * linear, 3)}, "
          f"with accelerations {np.round(1e3 * quadratic, 3)}")
    free = [0, 1]  # 5 cm take 0.1 s: frames 0 and 1 are in free flight
    # n/2 substeps of symplectic Euler reach x + v Δt/2 − g h² n(n + 2)/8, the quadratic x + v Δt/2 − g h² n(n + 1)/8:
    # they differ by g h Δt / 8 exactly (float32 points add ~1e-7 m)
    np.testing.assert_allclose(quadratic[free], 9.81 * h * dt / 8, atol=2e-7)
    assert quadratic[free].max() < linear[free].min() / 30
    assert np.ptp(linear) > 1e-4  # the impact changed the motion (velocities alone miss differently there)


def test_the_command_line_writes_a_layer_over_the_scenes_asset(tmp_path: Path):
    """``warpspring run scene.toml --layer-over asset.usda``: the scene reads the sheet from the asset (its output
    prim named by the prim), and the layer, opened on its own, shows the asset's sheet moved by the simulation."""
    from warpspring.app.cli import main

    asset, layer = tmp_path / "sheet.usda", tmp_path / "sim.usdc"
    _author(asset)
    scene = tmp_path / "scene.toml"
    scene.write_text(f"""\
version = 2
[simulation]
fps = 60
frames = 3
substeps = 4
integrator = "implicit_euler"

[cloth]
mesh = "sheet.usda"
prim = "{PRIM}"
density = 0.2
pin = [0, {NX}]
""")
    assert main(["run", str(scene), "-o", str(layer), "--layer-over", str(asset), "--device", "cpu", "--quiet",
                 "--watch-every", "0"]) == 0
    stage = Usd.Stage.Open(str(layer))
    points = stage.GetPrimAtPath(PRIM).GetAttribute("points")
    assert points.GetTimeSamples() == pytest.approx([0.0, 0.4, 0.8, 1.2])  # 24 time codes per second, 60 fps
    source_stage = Usd.Stage.Open(str(asset))
    rest = np.array(source_stage.GetPrimAtPath(PRIM).GetAttribute("points").Get(), dtype=np.float64)
    np.testing.assert_allclose(np.array(points.Get(0.0)), rest, atol=1e-4)  # frame 0: the asset's own points [cm]
    assert np.abs(np.array(points.Get(1.2)) - rest).max() > 0.05  # then it moves (> 0.5 mm)
    assert Sdf.Layer.FindOrOpen(str(layer)).subLayerPaths == ["./sheet.usda"]


def test_a_soft_bodys_skin_over_its_asset_keeps_its_hard_edges(tmp_path: Path):
    """A soft box read from a dressed asset (Y-up, centimetres, a transform that turns and stretches unequally,
    flat faceVarying normals: every edge hard) written as a layer over it: the composed world points equal the skin's
    (its particles' weighted sums) within 1e-6 m at every frame, and the composed normals, turned into the prim's
    local space by the transform's inverse transpose, are at rest the asset's own flat normals."""
    asset, layer = tmp_path / "box.usda", tmp_path / "sim.usdc"
    stage = Usd.Stage.CreateNew(str(asset))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(24.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/Root").GetPrim())
    mesh = UsdGeom.Mesh.Define(stage, "/Root/Box")
    xform = UsdGeom.Xformable(mesh)
    xform.AddTranslateOp().Set(Gf.Vec3d(5.0, 60.0, -10.0))
    xform.AddRotateXYZOp().Set(Gf.Vec3f(10.0, 25.0, 0.0))
    xform.AddScaleOp().Set(Gf.Vec3f(1.0, 1.5, 0.8))
    corners = np.array([[x, y, z] for z in (0.0, 30.0) for y in (0.0, 30.0) for x in (0.0, 30.0)])
    quads = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
    flat = np.array([np.cross(corners[q[1]] - corners[q[0]], corners[q[2]] - corners[q[0]]) for q in quads])
    flat /= np.linalg.norm(flat, axis=1, keepdims=True)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(corners.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * 6))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(quads.reshape(-1).astype(np.int32)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.repeat(flat, 4, axis=0).astype(np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    stage.GetRootLayer().Save()
    del stage

    builder = ws.ModelBuilder(up_axis="Z")
    builder.add_soft_body(str(asset), prim="/Root/Box", method="voxel", youngs_modulus=2.0e4, density=100.0,
                          spacing=0.1)
    model = builder.finalize("cpu")
    sim = ws.Simulator(model, integrator=ws.make_integrator("implicit_euler", model), fps=FPS, substeps=SUBSTEPS)
    skin = model.skins[0]
    expected = []
    with UsdWriter(layer, model, fps=FPS, layer_over=asset) as writer:
        for frame in range(FRAMES):
            if frame:
                sim.step_frame()
            writer.write_frame(sim.state)
            expected.append(skin.points(sim.state.particle_q.numpy().astype(np.float64)))
    composed = Usd.Stage.Open(str(layer))
    prim = composed.GetPrimAtPath("/Root/Box")
    for frame in range(FRAMES):
        t = frame * 24.0 / FPS
        matrix = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t))
        local = np.array(prim.GetAttribute("points").Get(t), dtype=np.float64)
        world = convert_up_axis((local @ matrix[:3, :3] + matrix[3, :3]) * 0.01, "Y", "Z")
        np.testing.assert_allclose(world, expected[frame], atol=1e-6)
    assert np.abs(expected[-1] - expected[0]).max() > 1e-3  # it fell
    box = UsdGeom.Mesh(prim)
    assert box.GetNormalsInterpolation() == UsdGeom.Tokens.faceVarying
    np.testing.assert_allclose(np.array(box.GetNormalsAttr().Get(0.0)), np.repeat(flat, 4, axis=0), atol=1e-5)


def test_a_layer_resumes_like_a_stage(tmp_path: Path):
    """``keep_frames`` over an asset (``--resume``): the layer's own first frames are kept (not the asset's values
    beneath them) at their time codes, exact multiples of 24/60 (3 × 24/60 is 1.2, not 1.2000000000000002), and the
    frames written again equal the first run's."""
    asset, layer = tmp_path / "sheet.usda", tmp_path / "sim.usdc"
    _author(asset)
    q, _ = _simulate(asset, layer)
    stage = Usd.Stage.Open(str(layer))
    first = {t: np.array(stage.GetPrimAtPath(PRIM).GetAttribute("points").Get(t))
             for t in stage.GetPrimAtPath(PRIM).GetAttribute("points").GetTimeSamples()}
    del stage
    assert sorted(first) == [k * 24.0 / FPS for k in range(FRAMES)]
    builder = ws.ModelBuilder(up_axis="Z")
    builder.add_cloth_mesh(str(asset), prim=PRIM, density=0.2, pin=[0, NX])
    model = builder.finalize("cpu")
    state = model.state()
    with UsdWriter(layer, model, fps=FPS, layer_over=asset, primvars=["strain"], keep_frames=2) as writer:
        for frame in range(2, FRAMES):
            state.particle_q.assign(q[frame].astype(np.float32))
            writer.write_frame(state)
    stage = Usd.Stage.Open(str(layer))
    points = stage.GetPrimAtPath(PRIM).GetAttribute("points")
    assert points.GetTimeSamples() == sorted(first)
    for t, value in first.items():
        np.testing.assert_array_equal(np.array(points.Get(t)), value)


def test_particles_and_colliders_over_an_asset_only_when_asked(tmp_path: Path):
    """Colliders and the particles are not written over an asset unless asked; asked, they go under /warpspring, whose
    transform takes warpspring's Z-up metres into the asset's Y-up centimetres: their composed world positions are
    the simulation's."""
    asset = tmp_path / "sheet.usda"
    _author(asset)
    builder = ws.ModelBuilder(up_axis="Z")
    builder.add_cloth_mesh(str(asset), prim=PRIM, density=0.2, pin=[0, NX])
    builder.add_collider_sphere(center=(0.3, -0.2, 1.0), radius=0.1)
    model = builder.finalize("cpu")
    state = model.state()
    with UsdWriter(tmp_path / "bare.usda", model, fps=FPS, layer_over=asset) as writer:
        writer.write_frame(state)
    assert not Sdf.Layer.FindOrOpen(str(tmp_path / "bare.usda")).GetPrimAtPath("/warpspring")
    with UsdWriter(tmp_path / "sim.usda", model, fps=FPS, layer_over=asset, particles=True,
                   layer_colliders=True) as writer:
        writer.write_frame(state)
    stage = Usd.Stage.Open(str(tmp_path / "sim.usda"))
    points = UsdGeom.Points(stage.GetPrimAtPath("/warpspring/particles"))
    matrix = np.array(points.ComputeLocalToWorldTransform(0.0))
    world = np.array(points.GetPointsAttr().Get(0.0), dtype=np.float64) @ matrix[:3, :3] + matrix[3, :3]
    np.testing.assert_allclose(convert_up_axis(world * 0.01, "Y", "Z"), state.particle_q.numpy(), atol=1e-6)
    sphere = stage.GetPrimAtPath("/warpspring/colliders/sphere")
    centre = np.array(UsdGeom.Xformable(sphere).ComputeLocalToWorldTransform(0.0))[3, :3]
    np.testing.assert_allclose(convert_up_axis(centre[None] * 0.01, "Y", "Z")[0], (0.3, -0.2, 1.0), atol=1e-9)
