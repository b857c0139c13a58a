"""The streaming USD writer: stage metadata, mesh samples, colliders, optional prims, validation, formats,
streaming and the refusal of non-finite frames. Every file is reopened with pxr (or in a fresh process)."""

import json
import subprocess
import sys

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdValidation

import warpspring as ws
from warpspring.io.usd import UsdWriter

NX, NY, SPACING = 4, 5, 0.1  # nx ≠ ny, so a transposed grid or uv layout cannot pass
SOFT = ws.SpringMaterial(ke=10.0, kd=0.01)
ORIGIN = np.array([0.2, -0.1, 1.0])


def grid_builder(up_axis: str = "Z") -> ws.ModelBuilder:
    """A flat NX × NY cloth whose front normal is the up axis (the grid's local +z turned onto +y for Y-up)."""
    builder = ws.ModelBuilder(up_axis=up_axis)
    rotation = (0.0, 0.0, 0.0, 1.0) if up_axis == "Z" else ws.quat_from_axis_angle((1.0, 0.0, 0.0), -np.pi / 2)
    builder.add_cloth_grid(
        nx=NX, ny=NY, spacing=SPACING, mass=0.2, origin=ORIGIN, rotation=rotation,
        structural=SOFT, shear=SOFT, bend=SOFT,
    )
    return builder


def state_at(model: ws.Model, q: np.ndarray) -> ws.State:
    """A state of ``model`` holding positions ``q`` [m], shape [particle_count, 3]."""
    state = model.state()
    state.particle_q.assign(np.asarray(q, dtype=np.float64 if model.precision == "float64" else np.float32))
    return state


def flat_frames(model: ws.Model, count: int) -> list[np.ndarray]:
    """``count`` distinct flat poses: frame k is the rest grid stretched ×(1 + 0.1 k) in x, shifted k·(1, 2, -3) cm."""
    q0 = model.particle_q.numpy().astype(np.float64)
    frames = []
    for k in range(count):
        q = q0.copy()
        q[:, 0] = ORIGIN[0] + (q[:, 0] - ORIGIN[0]) * (1.0 + 0.1 * k)
        frames.append(q + k * np.array([0.01, 0.02, -0.03]))
    return frames


def write(path, model, frames, **options) -> None:
    with UsdWriter(path, model, fps=options.pop("fps", 30.0), **options) as writer:
        for q in frames:
            writer.write_frame(state_at(model, q))


def samples(attr) -> list[float]:
    return list(attr.GetTimeSamples())


def read_in_fresh_process(path) -> dict:
    """What another process sees in the file: sample count and times of the cloth points, and the end time code."""
    snippet = (
        "import json, sys; from pxr import Usd; s = Usd.Stage.Open(sys.argv[1]); "
        "a = s.GetPrimAtPath('/World/cloth').GetAttribute('points'); "
        "print(json.dumps({'times': list(a.GetTimeSamples()), 'end': s.GetEndTimeCode()}))"
    )
    out = subprocess.run([sys.executable, "-c", snippet, str(path)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


# -- stage and mesh -------------------------------------------------------------------------------------


@pytest.mark.parametrize("up_axis", ["Z", "Y"])
def test_stage_metadata_and_normals_follow_up_axis(tmp_path, up_axis):
    """Stage metadata DCC tools need (defaultPrim, upAxis, metres, fps, time range) and normals along the up axis."""
    model = grid_builder(up_axis).finalize("cpu")
    path = tmp_path / "meta.usdc"
    write(path, model, flat_frames(model, 4), fps=25.0)

    stage = Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert UsdGeom.GetStageUpAxis(stage) == up_axis
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.HasAuthoredMetadata("metersPerUnit")  # the unauthored fallback is 0.01 (centimetres)
    assert stage.GetTimeCodesPerSecond() == 25.0 and stage.GetFramesPerSecond() == 25.0
    assert stage.GetStartTimeCode() == 0.0
    assert stage.GetEndTimeCode() == 3.0  # the last frame written, so the range is not empty

    up = np.eye(3)[{"Y": 1, "Z": 2}[up_axis]]
    normals = np.array(stage.GetPrimAtPath("/World/cloth").GetAttribute("normals").Get(2))
    np.testing.assert_allclose(normals, np.broadcast_to(up, normals.shape), atol=1e-6)


def test_mesh_samples_topology_uvs_and_normals(tmp_path, device):
    """One points/extent/normals sample per frame 0..N; topology once, as in the model; no subdivision; grid uvs."""
    model = grid_builder().finalize(device)
    frames = flat_frames(model, 4)
    path = tmp_path / "mesh.usdc"
    write(path, model, frames)

    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth"))
    assert mesh, "the cloth is not a UsdGeom.Mesh at /World/cloth"
    for attr in (mesh.GetPointsAttr(), mesh.GetExtentAttr(), mesh.GetNormalsAttr()):
        assert samples(attr) == [0.0, 1.0, 2.0, 3.0], attr.GetName()
    for k, q in enumerate(frames):  # the mesh's point i is particle i: every particle is a grid vertex
        np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get(k)), q, rtol=0, atol=1e-6)

    group = model.meshes[0]
    counts, indices = mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()
    for attr in (counts, indices):
        assert attr.HasAuthoredValue() and attr.GetNumTimeSamples() == 0, attr.GetName()
    # the grid's cells as quads, as a modeller makes a grid: cell (r, c) = its corners counter-clockwise
    assert list(counts.Get()) == [4] * (NX - 1) * (NY - 1)
    r, c = np.divmod(np.arange((NX - 1) * (NY - 1)), NX - 1)
    corner = r * NX + c
    np.testing.assert_array_equal(np.array(indices.Get()).reshape(-1, 4),
                                  np.stack([corner, corner + 1, corner + NX + 1, corner + NX], 1))
    assert mesh.GetSubdivisionSchemeAttr().HasAuthoredValue()  # the unauthored fallback is catmullClark
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    assert mesh.GetDoubleSidedAttr().Get() is True

    # uv of grid particle (row r, column c) = (c / (nx-1), r / (ny-1)), one per vertex
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st and st.GetInterpolation() == UsdGeom.Tokens.vertex
    i = np.arange(NX * NY)
    np.testing.assert_allclose(np.array(st.Get()), np.stack([(i % NX) / (NX - 1), (i // NX) / (NY - 1)], 1), atol=1e-7)

    # flat grid in the z = const plane, front side +z: unit normals along +z, and the triangles wind the same way
    for k in range(len(frames)):
        normals = np.array(mesh.GetNormalsAttr().Get(k))
        assert normals.shape == (NX * NY, 3)
        np.testing.assert_allclose(normals, np.broadcast_to([0.0, 0.0, 1.0], normals.shape), atol=1e-6)
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    points = np.array(mesh.GetPointsAttr().Get(0))
    tri = points[group.faces]
    assert (np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2] > 0).all()


def test_normals_are_unit_and_extent_matches_points_of_a_crumpled_cloth(tmp_path):
    """For non-flat frames normals are unit length; extent is ComputeExtent of the frame's points and encloses them."""
    model = grid_builder().finalize("cpu")
    rng = np.random.default_rng(7)
    q0 = model.particle_q.numpy().astype(np.float64)
    frames = [q0 + rng.normal(scale=0.02 * (k + 1), size=q0.shape) for k in range(3)]
    path = tmp_path / "crumpled.usdc"
    write(path, model, frames)

    stage = Usd.Stage.Open(str(path))  # held: a prim does not keep its stage alive
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/cloth"))
    for k, q in enumerate(frames):
        points = mesh.GetPointsAttr().Get(k)
        extent = np.array(mesh.GetExtentAttr().Get(k))
        np.testing.assert_array_equal(extent, np.array(UsdGeom.PointBased.ComputeExtent(points)))
        p = np.array(points)
        assert (p >= extent[0]).all() and (p <= extent[1]).all()
        np.testing.assert_allclose(extent, [q.min(0), q.max(0)], atol=1e-6)  # tight, from this frame's points
        np.testing.assert_allclose(np.linalg.norm(np.array(mesh.GetNormalsAttr().Get(k)), axis=1), 1.0, atol=1e-5)


# -- colliders, particles, springs ------------------------------------------------------------------------


@pytest.mark.parametrize("up_axis", ["Z", "Y"])
def test_collider_prims_and_transforms(tmp_path, up_axis):
    """A sphere collider is a UsdGeom.Sphere of its radius at its centre; a plane is a Mesh at its point and normal."""
    builder = grid_builder(up_axis)
    builder.add_collider_sphere(center=(0.1, 0.2, 0.3), radius=0.15, name="ball")
    builder.add_ground_plane(height=0.25)
    tilted = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    builder.add_collider_plane(point=(0.5, -0.2, 0.1), normal=tilted * 3.0, name="ramp")  # not unit: normalised
    model = builder.finalize("cpu")
    path = tmp_path / "colliders.usdc"
    write(path, model, flat_frames(model, 2))

    stage = Usd.Stage.Open(str(path))
    sphere = UsdGeom.Sphere(stage.GetPrimAtPath("/World/colliders/ball"))
    assert sphere, "the sphere collider is not a UsdGeom.Sphere"
    assert sphere.GetRadiusAttr().Get() == pytest.approx(0.15)
    m = sphere.ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    np.testing.assert_allclose(np.array(m.ExtractTranslation()), [0.1, 0.2, 0.3], atol=1e-9)
    np.testing.assert_allclose(np.array(m.ExtractRotationMatrix()), np.eye(3), atol=1e-6)

    up = np.eye(3)[{"Y": 1, "Z": 2}[up_axis]]
    for name, point, normal in [("ground", 0.25 * up, up), ("ramp", np.array([0.5, -0.2, 0.1]), tilted)]:
        plane = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/colliders/{name}"))
        assert plane, f"plane collider {name} is not a UsdGeom.Mesh"
        m = plane.ComputeLocalToWorldTransform(Usd.TimeCode.Default())
        np.testing.assert_allclose(np.array(m.Transform(Gf.Vec3d(0, 0, 0))), point, atol=1e-6)
        np.testing.assert_allclose(np.array(m.TransformDir(Gf.Vec3d(0, 0, 1))), normal, atol=1e-6)
        corners = np.array([m.Transform(Gf.Vec3d(*p)) for p in plane.GetPointsAttr().Get()])
        np.testing.assert_allclose((corners - point) @ normal, 0.0, atol=1e-6)  # the quad lies in the plane
        assert plane.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none


def test_particles_and_springs_written_only_when_requested(tmp_path):
    """Points have widths = 2·radius and the positions; one linear 2-vertex curve per spring joins its two particles."""
    model = grid_builder().finalize("cpu")
    frames = flat_frames(model, 3)
    plain, full = tmp_path / "plain.usdc", tmp_path / "full.usdc"
    write(plain, model, frames)
    write(full, model, frames, particles=True, springs=True)

    stage = Usd.Stage.Open(str(plain))
    assert not stage.GetPrimAtPath("/World/particles") and not stage.GetPrimAtPath("/World/springs")

    stage = Usd.Stage.Open(str(full))
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/particles"))
    assert points, "no UsdGeom.Points at /World/particles"
    np.testing.assert_allclose(np.array(points.GetWidthsAttr().Get()), 2.0 * model.particle_radius.numpy(), rtol=1e-6)
    assert points.GetWidthsInterpolation() == UsdGeom.Tokens.vertex

    ends = model.spring_indices.numpy().reshape(-1, 2)
    rest = model.spring_rest_length.numpy()
    assert sorted(model.spring_families) == ["bend", "shear", "structural"]
    for family, members in model.spring_families.items():
        curves = UsdGeom.BasisCurves(stage.GetPrimAtPath(f"/World/springs/{family}"))
        assert curves, f"no UsdGeom.BasisCurves at /World/springs/{family}"
        assert curves.GetTypeAttr().Get() == UsdGeom.Tokens.linear
        counts = np.array(curves.GetCurveVertexCountsAttr().Get())
        api = UsdGeom.PrimvarsAPI(curves)
        particle = np.array(api.GetPrimvar("warpspring:particle").Get())
        assert len(particle) == counts.sum() < 1.5 * len(members)  # chains share points (2 per spring: 2.0)
        # every spring of the family is one segment of one chain, exactly once
        first = np.cumsum(counts) - counts
        inner = np.ones(len(particle), bool)
        inner[first] = False
        segments = np.sort(np.stack([particle[np.flatnonzero(inner) - 1], particle[inner]], 1), axis=1)
        np.testing.assert_array_equal(np.unique(segments, axis=0), np.unique(np.sort(ends[members], 1), axis=0))
        assert len(segments) == len(members)
        strain = api.GetPrimvar("strain")
        assert strain.GetInterpolation() == UsdGeom.Tokens.vertex
        for k, q in enumerate(frames):
            np.testing.assert_allclose(np.array(curves.GetPointsAttr().Get(k)), q[particle], atol=1e-6)
            # a curve vertex's strain: the larger of its (one or two) segments' (l - L) / L
            length = {tuple(sorted(e)): np.linalg.norm(q[e[1]] - q[e[0]]) / rest[i] - 1.0
                      for i, e in zip(members, ends[members])}
            seg = [length[tuple(pair)] for pair in segments]
            expected = np.full(len(particle), -np.inf)
            where = np.flatnonzero(inner)
            np.maximum.at(expected, where, seg)
            np.maximum.at(expected, where - 1, seg)
            np.testing.assert_allclose(np.array(strain.Get(k)), expected, atol=1e-5)
        assert samples(curves.GetPointsAttr()) == samples(strain.GetAttr()) == [0.0, 1.0, 2.0]
    for k, q in enumerate(frames):
        np.testing.assert_allclose(np.array(points.GetPointsAttr().Get(k)), q, atol=1e-6)
    assert samples(points.GetPointsAttr()) == samples(points.GetVelocitiesAttr()) == [0.0, 1.0, 2.0]


def test_usd_validation_reports_nothing(tmp_path):
    """Every registered pxr.UsdValidation validator passes on a stage with cloth, colliders, particles and springs."""
    builder = grid_builder()
    builder.add_collider_sphere(center=(0.0, 0.0, 0.5), radius=0.2)
    builder.add_ground_plane()
    model = builder.finalize("cpu")
    path = tmp_path / "valid.usdc"
    write(path, model, flat_frames(model, 3), particles=True, springs=True)

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert len(validators) > 0
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    assert [e.GetMessage() for e in errors] == []


# -- formats ----------------------------------------------------------------------------------------------


def test_format_follows_extension(tmp_path):
    """.usda is written as text, .usdc and .usd as binary crate, any other extension is a ConfigError."""
    model = grid_builder().finalize("cpu")
    frames = flat_frames(model, 2)
    for name, head in [("a.usda", b"#usda 1.0"), ("b.usdc", b"PXR-USDC"), ("c.usd", b"PXR-USDC")]:
        write(tmp_path / name, model, frames)
        assert (tmp_path / name).read_bytes().startswith(head), name
        stage = Usd.Stage.Open(str(tmp_path / name))
        assert samples(stage.GetPrimAtPath("/World/cloth").GetAttribute("points")) == [0.0, 1.0]
    for bad in ("cloth.obj", "cloth", "cloth.usdz"):
        with pytest.raises(ws.ConfigError, match=r"\.usdc"):
            UsdWriter(tmp_path / bad, model, fps=30.0)
        assert not (tmp_path / bad).exists()


def test_writer_rejects_a_non_positive_frame_rate(tmp_path):
    """fps sets timeCodesPerSecond: zero, negative, NaN or non-numeric values are ConfigErrors, and no file is made."""
    model = grid_builder().finalize("cpu")
    for fps in (0, -24.0, float("nan"), "24", True):
        with pytest.raises(ws.ConfigError, match="fps"):
            UsdWriter(tmp_path / "rate.usdc", model, fps=fps)
    assert not (tmp_path / "rate.usdc").exists()


# -- streaming and failures -------------------------------------------------------------------------------


def test_usdc_frames_are_on_disk_before_close(tmp_path):
    """After k frames of an open writer, another process reads exactly k samples (0..k-1) and endTimeCode k-1."""
    model = grid_builder().finalize("cpu")
    path = tmp_path / "stream.usdc"
    frames = flat_frames(model, 3)
    writer = UsdWriter(path, model, fps=30.0)
    try:
        writer.write_frame(state_at(model, frames[0]))
        assert read_in_fresh_process(path)["times"] == [0.0]
        writer.write_frame(state_at(model, frames[1]))
        writer.write_frame(state_at(model, frames[2]))
        assert read_in_fresh_process(path) == {"times": [0.0, 1.0, 2.0], "end": 2.0}
    finally:
        writer.close()


@pytest.mark.parametrize("ext", ["usdc", "usda"])
def test_non_finite_frame_is_refused_and_earlier_frames_kept(tmp_path, ext):
    """A NaN position raises SimulationError, nothing of its frame is written, and the earlier frames stay intact."""
    model = grid_builder().finalize("cpu")
    path = tmp_path / f"nan.{ext}"
    frames = flat_frames(model, 2)
    bad = frames[1].copy()
    bad[5, 2] = np.nan
    writer = UsdWriter(path, model, fps=30.0)
    try:
        for q in frames:
            writer.write_frame(state_at(model, q))
        with pytest.raises(ws.SimulationError, match="particle 5"):
            writer.write_frame(state_at(model, bad))
        assert writer.frame_count == 2
        if ext == "usdc":  # streamed: already complete on disk
            assert read_in_fresh_process(path) == {"times": [0.0, 1.0], "end": 1.0}
    finally:
        writer.close()
    assert read_in_fresh_process(path) == {"times": [0.0, 1.0], "end": 1.0}
    stage = Usd.Stage.Open(str(path))
    points = stage.GetPrimAtPath("/World/cloth").GetAttribute("points")
    assert all(np.isfinite(np.array(points.Get(t))).all() for t in points.GetTimeSamples())


def test_float64_position_beyond_float32_range_is_refused(tmp_path):
    """A finite float64 position too large for USD's float32 points (it would be written as inf) is refused."""
    model = grid_builder().finalize("cpu", precision="float64")
    q = model.particle_q.numpy()
    q[3, 0] = 1.0e39  # finite in float64, inf in float32
    path = tmp_path / "huge.usdc"
    with UsdWriter(path, model, fps=30.0) as writer:
        with pytest.raises(ws.SimulationError, match="particle 3"):
            writer.write_frame(state_at(model, q))
    assert read_in_fresh_process(path)["times"] == []


def test_rewriting_a_path_replaces_the_old_animation(tmp_path):
    """Writing a path again in one process (its layer still open) leaves only the new frames, on disk and in memory."""
    model = grid_builder().finalize("cpu")
    path = tmp_path / "again.usdc"
    write(path, model, flat_frames(model, 4))
    held = Usd.Stage.Open(str(path))  # keeps the old layer in this process's registry
    assert samples(held.GetPrimAtPath("/World/cloth").GetAttribute("points")) == [0.0, 1.0, 2.0, 3.0]
    write(path, model, flat_frames(model, 2))
    assert read_in_fresh_process(path) == {"times": [0.0, 1.0], "end": 1.0}
    stage = Usd.Stage.Open(str(path))
    assert samples(stage.GetPrimAtPath("/World/cloth").GetAttribute("points")) == [0.0, 1.0]


def test_uv_seams_are_written_face_varying(tmp_path):
    """A mesh with a UV seam exports its st primvar per face corner, in face-vertex order."""
    from helpers import SEAM_OBJ

    (tmp_path / "seam.obj").write_text(SEAM_OBJ)
    builder = ws.ModelBuilder()
    builder.add_cloth_mesh(str(tmp_path / "seam.obj"), mass=1.0, name="patch")
    model = builder.finalize("cpu")
    write(tmp_path / "seam.usda", model, [model.particle_q.numpy()])
    stage = Usd.Stage.Open(str(tmp_path / "seam.usda"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/patch"))
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    np.testing.assert_allclose(np.array(st.Get()), model.meshes[0].uvs.reshape(-1, 2))
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == [0, 1, 2, 0, 2, 3, 1, 4, 2]


def test_two_cloths_are_separate_meshes_with_local_indices_and_unique_names(tmp_path, device):
    """Cloths "sail", "flag" and a second "sail" in one model: three meshes under /World named sail, flag
    and sail_1 (a repeated name gets a suffix), each with its own particle slice as points every frame
    and face indices local to it (0-based, below its vertex count), and topology matching its grid."""
    builder = ws.ModelBuilder()
    shapes = {"sail": (3, 4), "flag": (5, 2), "sail_1": (2, 3)}  # (nx, ny): all different, so slices cannot mix
    grids = {}
    for (label, (nx, ny)), origin in zip(shapes.items(), ([0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 2.0])):
        grids[label] = builder.add_cloth_grid(
            nx=nx, ny=ny, spacing=SPACING, mass=0.1, origin=origin, structural=SOFT, shear=SOFT, bend=SOFT,
            name="sail" if label.startswith("sail") else label,
        )
    model = builder.finalize(device)
    assert [m.name for m in model.meshes] == ["sail", "flag", "sail_1"]

    rng = np.random.default_rng(3)
    q0 = model.particle_q.numpy().astype(np.float64)
    frames = [q0 + rng.normal(scale=0.01, size=q0.shape) for _ in range(3)]  # every particle distinct per frame
    path = tmp_path / "two.usdc"
    write(path, model, frames)

    stage = Usd.Stage.Open(str(path))
    meshes = [p.GetName() for p in stage.GetPrimAtPath("/World").GetChildren() if p.IsA(UsdGeom.Mesh)]
    assert sorted(meshes) == sorted(shapes)
    start = face_start = 0
    for group in model.meshes:
        nx, ny = shapes[group.name]
        ids = grids[group.name].ravel()
        np.testing.assert_array_equal(ids, np.arange(start, start + nx * ny))  # consecutive global slice
        np.testing.assert_array_equal(group.particles, ids)
        start += nx * ny

        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{group.name}"))
        assert mesh, f"no UsdGeom.Mesh at /World/{group.name}"
        assert samples(mesh.GetPointsAttr()) == [0.0, 1.0, 2.0]
        for k, q in enumerate(frames):
            np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get(k)), q[ids], rtol=0, atol=1e-6)
        quads = np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 4)
        assert len(quads) == (nx - 1) * (ny - 1) and list(mesh.GetFaceVertexCountsAttr().Get()) == [4] * len(quads)
        assert quads.min() == 0 and quads.max() == nx * ny - 1  # local: 0-based within this mesh
        np.testing.assert_array_equal(quads, group.polygon_indices.reshape(-1, 4))
        indices = group.faces  # the triangles simulated: two per quad, global in the model
        assert len(indices) == 2 * len(quads)
        np.testing.assert_array_equal(ids[indices], model.tri_indices.numpy()[face_start : face_start + len(indices)])
        face_start += len(indices)  # the model's global triangles are the meshes' local ones, in mesh order
        assert len(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get()) == nx * ny
    assert start == model.particle_count and face_start == model.tri_count
