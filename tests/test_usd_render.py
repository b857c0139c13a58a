"""What a lighting or FX artist needs from the USD cache: velocities, optional primvars (strain, pinned,
rest), a start frame, collider purpose, the faces as authored, and files that are the same bytes when a run
is repeated. Values are checked against their definitions computed here from the model's arrays."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdValidation

import warpspring as ws
from warpspring.io.usd import UsdWriter


def hanging_builder(nx: int = 7, ny: int = 5) -> ws.ModelBuilder:
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=nx, ny=ny, spacing=0.1, origin=(0.0, 0.0, 1.0), particle_mass=0.01,
                           pin=["top-left", "top-right"], structural=ws.SpringMaterial(40.0, 0.01),
                           shear=ws.SpringMaterial(10.0, 0.01), bend=ws.SpringMaterial(1.0, 0.001))
    builder.add_collider_sphere(center=(0.3, 0.2, 0.5), radius=0.1)
    return builder


def run(path, model, frames: int, **options) -> list[tuple[np.ndarray, np.ndarray]]:
    """Simulate ``frames`` frames (symplectic Euler, 60 fps, 4 substeps) writing every frame to ``path``;
    the (positions, velocities) written, float64."""
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=4)
    written = []
    with UsdWriter(path, model, fps=60, **options) as usd:
        for k in range(frames):
            if k:
                sim.step_frame()
            usd.write_frame(sim.state)
            written.append((sim.state.particle_q.numpy().astype(np.float64),
                            sim.state.particle_qd.numpy().astype(np.float64)))
    return written


def test_velocities_strain_pinned_rest_and_start_frame(tmp_path, device):
    """Per frame: velocities = the state's [m/s]; strain = per vertex the largest (l − L)/L of its springs;
    pinned = 1 for kinematic particles, with a release mid-run showing; rest = the start positions, once. Frame
    k is time code 1001 + k."""
    builder = hanging_builder()
    model = builder.finalize(device)
    path = tmp_path / "attrs.usdc"
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=4)
    written, pinned = [], []
    released = int(np.flatnonzero(model.kinematic_mask())[0])
    with UsdWriter(path, model, fps=60, primvars=["strain", "pinned", "rest"], start_frame=1001) as usd:
        for k in range(4):
            if k == 2:
                model.set_kinematic([released], False)  # release a pin between frames
            if k:
                sim.step_frame()
            usd.write_frame(sim.state)
            written.append((sim.state.particle_q.numpy().astype(np.float64), sim.state.particle_qd.numpy().copy()))
            pinned.append(model.kinematic_mask().copy())

    stage = Usd.Stage.Open(str(path))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1001.0, 1004.0)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth"))
    primvars = UsdGeom.PrimvarsAPI(mesh)
    assert list(mesh.GetVelocitiesAttr().GetTimeSamples()) == [1001.0, 1002.0, 1003.0, 1004.0]
    ends = model.spring_indices.numpy()
    rest = model.spring_rest_length.numpy().astype(np.float64)
    for k, (q, v) in enumerate(written):
        t = 1001 + k
        np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get(t)), q, atol=1e-6)
        np.testing.assert_allclose(np.array(mesh.GetVelocitiesAttr().Get(t)), v, rtol=1e-6, atol=1e-7)
        strain = np.linalg.norm(q[ends[:, 1]] - q[ends[:, 0]], axis=1) / rest - 1.0
        expected = np.full(model.particle_count, -np.inf)
        for side in (0, 1):
            np.maximum.at(expected, ends[:, side], strain)
        np.testing.assert_allclose(np.array(primvars.GetPrimvar("strain").Get(t)), expected, atol=1e-5)
        np.testing.assert_array_equal(np.array(primvars.GetPrimvar("pinned").Get(t)), pinned[k].astype(int))
    assert pinned[1][released] and not pinned[2][released]  # the release is in the file
    assert written[-1][0][:, 2].min() < 0.99  # the cloth moved: strains and velocities are not all zero
    rest_pv = primvars.GetPrimvar("rest")
    assert rest_pv.GetInterpolation() == UsdGeom.Tokens.vertex and rest_pv.GetAttr().GetNumTimeSamples() == 0
    np.testing.assert_allclose(np.array(rest_pv.Get()), model.particle_q.numpy(), atol=1e-7)
    for name in ("strain", "pinned"):
        assert primvars.GetPrimvar(name).GetInterpolation() == UsdGeom.Tokens.vertex


def test_colliders_are_guides_unless_asked_and_bad_options_are_refused(tmp_path):
    model = hanging_builder().finalize("cpu")
    run(tmp_path / "guide.usdc", model, 1)
    run(tmp_path / "render.usdc", model, 1, collider_purpose="render")
    for name, purpose in (("guide", "guide"), ("render", "render")):
        stage = Usd.Stage.Open(str(tmp_path / f"{name}.usdc"))
        assert UsdGeom.Imageable(stage.GetPrimAtPath("/World/colliders/sphere")).ComputePurpose() == purpose
    with pytest.raises(ws.ConfigError, match="unknown primvar 'stress': choose from strain, pinned, rest"):
        UsdWriter(tmp_path / "x.usdc", model, fps=60, primvars=["stress"])
    with pytest.raises(ws.ConfigError, match="collider_purpose must be one of guide, default, render, proxy"):
        UsdWriter(tmp_path / "x.usdc", model, fps=60, collider_purpose="hidden")
    with pytest.raises(ws.ConfigError, match="start_frame must be an integer >= 0"):
        UsdWriter(tmp_path / "x.usdc", model, fps=60, start_frame=-1)
    assert not (tmp_path / "x.usdc").exists()


def test_vertex_normals_are_the_area_weighted_normals(tmp_path, device):
    """The normals written are the unit area-weighted sums of the incident triangles' normals, computed here in
    float64 from the written points (a crumpled frame, so the weights matter)."""
    model = hanging_builder().finalize(device)
    written = run(tmp_path / "n.usdc", model, 12)
    stage = Usd.Stage.Open(str(tmp_path / "n.usdc"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth"))
    tris = model.tri_indices.numpy()
    for k in (0, 11):
        q = written[k][0]
        cross = np.cross(q[tris[:, 1]] - q[tris[:, 0]], q[tris[:, 2]] - q[tris[:, 0]])
        n = np.zeros_like(q)
        for c in range(3):
            np.add.at(n, tris[:, c], cross)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        np.testing.assert_allclose(np.array(mesh.GetNormalsAttr().Get(k)), n, atol=2e-6)


def test_a_rerun_writes_the_same_bytes(tmp_path, device):
    """Two runs of the same scene on the same device write byte-identical files (normals are gathered per vertex
    in a fixed order, not summed with atomics)."""
    paths = [tmp_path / "a.usdc", tmp_path / "b.usdc"]
    for path in paths:
        run(path, hanging_builder(24, 24).finalize(device), 20, particles=True, springs=True,
            primvars=["strain", "pinned", "rest"])
    assert paths[0].read_bytes() == paths[1].read_bytes()


def test_faces_as_authored_from_the_api_and_validators_pass(tmp_path):
    """add_triangles with polygons: the file holds the authored quads and a pentagon with their face sets, the
    simulation their triangles; every USD validator passes on a file with every option on."""
    builder = ws.ModelBuilder()
    points = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1], [2, 0, 1], [2, 1, 1], [2.5, 0.5, 1]], float)
    ids = builder.add_particles(points, mass=0.1)
    polygons = [[0, 1, 2, 3], [1, 4, 6, 5, 2]]
    triangles = [[0, 1, 2], [0, 2, 3], [1, 4, 6], [1, 6, 5], [1, 5, 2]]
    builder.add_springs(ids[[[0, 1], [1, 2], [2, 3], [3, 0], [1, 4], [4, 6], [6, 5], [5, 2]]], stiffness=10.0)
    builder.add_triangles(ids[triangles], name="panel", polygon_counts=[4, 5], polygon_indices=np.concatenate(polygons),
                          face_sets={"front": [0], "back": [1]})
    builder.add_ground_plane()
    model = builder.finalize("cpu")
    path = tmp_path / "panel.usdc"
    run(path, model, 3, particles=True, springs=True, primvars=["strain", "pinned", "rest"], start_frame=1)
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/panel"))
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [4, 5]
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == sum(polygons, [])
    subsets = {s.GetPrim().GetName(): list(s.GetIndicesAttr().Get()) for s in UsdGeom.Subset.GetAllGeomSubsets(mesh)}
    assert subsets == {"front": [0], "back": [1]}
    np.testing.assert_array_equal(model.tri_indices.numpy(), triangles)
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert [e.GetMessage() for e in UsdValidation.ValidationContext(validators).Validate(stage)] == []
    with pytest.raises(ws.ConfigError, match="polygon_indices holds 8 entries, polygon_counts needs 9"):
        builder.add_triangles(ids[triangles], polygon_counts=[4, 5], polygon_indices=np.concatenate(polygons)[:8])
    with pytest.raises(ws.ConfigError, match="face set 'top' names face 2, but the mesh has faces 0..1"):
        builder.add_triangles(ids[triangles], polygon_counts=[4, 5], polygon_indices=np.concatenate(polygons),
                              face_sets={"top": [2]})


def quad_sheet_usd(path, *, n: int = 5) -> np.ndarray:
    """A Y-up, centimetre USD file of an n × n quad sheet (1 m wide, in the x-z plane at height 150 cm) at
    /Asset/geo/sheet, with its vertices in a shuffled order and face sets "hem" (the first row of quads) and
    "body" (the rest). Returns its vertices in metres, Z-up, in the file's order."""
    from pxr import Gf, Sdf, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.Xform.Define(stage, "/Asset")
    geo = UsdGeom.Xform.Define(stage, "/Asset/geo")
    geo.AddTranslateOp().Set(Gf.Vec3d(0.0, 150.0, 0.0))
    mesh = UsdGeom.Mesh.Define(stage, "/Asset/geo/sheet")
    UsdGeom.Mesh.Define(stage, "/Asset/geo/other")  # a second mesh: the scene must name its prim
    r, c = np.divmod(np.arange(n * n), n)
    grid = np.stack([c * 100.0 / (n - 1), np.zeros(n * n), r * 100.0 / (n - 1)], 1)  # cm, x-z plane
    order = np.random.default_rng(7).permutation(n * n)  # file vertex i is grid vertex order[i]
    rank = np.argsort(order)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(grid[order].astype(np.float32)))
    cells = np.arange((n - 1) * (n - 1))
    cr, cc = np.divmod(cells, n - 1)
    corner = cr * n + cc
    quads = rank[np.stack([corner, corner + 1, corner + n + 1, corner + n], 1)]
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(quads)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(quads.ravel().astype(np.int32)))
    UsdGeom.Subset.CreateGeomSubset(mesh, "hem", UsdGeom.Tokens.face, Vt.IntArray(list(range(n - 1))))
    UsdGeom.Subset.CreateGeomSubset(mesh, "body", UsdGeom.Tokens.face, Vt.IntArray(list(range(n - 1, len(quads)))))
    stage.GetRootLayer().Save()
    del Sdf
    placed = (grid[order] + [0.0, 150.0, 0.0]) * 0.01  # metres, Y-up
    return np.stack([placed[:, 0], -placed[:, 2], placed[:, 1]], 1), quads  # Y-up → Z-up: (x, -z, y)


def test_a_usd_mesh_runs_and_comes_back_with_its_own_faces(tmp_path, capsys):
    """A scene's cloth from a USD file (a prim chosen among two, centimetres, Y-up, under a transform): it is
    placed in metres Z-up; the output holds its quads in its vertex order, its face sets, velocities and the
    primvars; the run moved it (gravity, two pinned corners)."""
    from warpspring.app.cli import main

    source = tmp_path / "asset.usda"
    vertices, quads = quad_sheet_usd(source)
    top = np.flatnonzero(np.isclose(vertices[:, 2], vertices[:, 2].max()))
    scene = tmp_path / "scene.toml"
    scene.write_text(f"""\
version = 2
[simulation]
fps = 60
frames = 6
substeps = 8

[cloth]
mesh = "asset.usda"
prim = "/Asset/geo/sheet"
density = 0.2
pin = [{int(top[0])}, {int(top[-1])}]
structural = {{ ke = 50.0, kd = 0.01 }}
bend = {{ ke = 1.0, kd = 0.001 }}

[output]
primvars = ["strain", "pinned", "rest"]
start_frame = 1
""")
    out = tmp_path / "out.usdc"
    assert main(["run", str(scene), "-o", str(out), "--device", "cpu", "--quiet"]) == 0
    stage = Usd.Stage.Open(str(out))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1.0, 7.0)  # the start and 6 frames after it
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/sheet"))  # the prim's own name
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [4] * len(quads)
    np.testing.assert_array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()), quads.ravel())
    np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get(1)), vertices, atol=1e-6)
    subsets = {s.GetPrim().GetName(): list(s.GetIndicesAttr().Get()) for s in UsdGeom.Subset.GetAllGeomSubsets(mesh)}
    assert subsets == {"hem": list(range(4)), "body": list(range(4, 16))}
    last = np.array(mesh.GetPointsAttr().Get(7))
    assert (last[:, 2] < vertices[:, 2] - 1e-3).sum() > len(vertices) // 2  # it fell where it is not pinned
    np.testing.assert_allclose(last[top[[0, -1]]], vertices[top[[0, -1]]], atol=1e-6)
    assert mesh.GetVelocitiesAttr().GetNumTimeSamples() == 7
    assert list(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("pinned").Get(7)).count(1) == 2

    # a wrong prim is one line naming the file and the prim
    scene.write_text(scene.read_text().replace('prim = "/Asset/geo/sheet"', 'prim = "/Asset/geo/shet"'))
    capsys.readouterr()
    assert main(["run", str(scene), "-o", str(out), "--device", "cpu", "--quiet"]) == 2
    error = capsys.readouterr().err.splitlines()
    assert len(error) == 1 and "asset.usda" in error[0] and "/Asset/geo/shet" in error[0], error
