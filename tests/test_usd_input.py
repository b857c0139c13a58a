"""Reading a polygon mesh from a USD file (:mod:`warpspring.core.mesh_files`): placement (transform, units, up
axis), triangulation, orientation, face sets, time, and the one-line errors. Host only: no Warp kernels.

Expected values are computed here from what the test authors, independently of the module's helpers.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, Vt

from warpspring.errors import ConfigError
from warpspring.core.mesh_files import UsdMesh, read_usd_mesh


def _stage(path: Path, *, up: str = "Z", meters_per_unit: float = 1.0) -> Usd.Stage:
    """A new stage at ``path`` with its up axis and units authored."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
    return stage


def _mesh(stage: Usd.Stage, prim: str, points, counts, indices, *, orientation: str | None = None) -> UsdGeom.Mesh:
    """A mesh prim authored with default (untimed) values."""
    mesh = UsdGeom.Mesh.Define(stage, prim)
    mesh.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, p)) for p in points]))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([int(c) for c in counts]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(i) for i in indices]))
    if orientation is not None:
        mesh.CreateOrientationAttr(orientation)
    return mesh


def _write(path: Path, points, counts, indices, *, prim: str = "/World/cloth", up: str = "Z",
           meters_per_unit: float = 1.0, orientation: str | None = None) -> Path:
    """A file holding one mesh."""
    stage = _stage(path, up=up, meters_per_unit=meters_per_unit)
    UsdGeom.Xform.Define(stage, "/World")
    _mesh(stage, prim, points, counts, indices, orientation=orientation)
    stage.GetRootLayer().Save()
    return path


def _normal(v: np.ndarray, tri) -> np.ndarray:
    a, b, c = (v[int(i)] for i in tri)
    return np.cross(b - a, c - a)


TRI = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)]


# ------------------------------------------------------------------------------------------ placement


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_quad_grid_placement_units_up_axis_and_short_diagonals(tmp_path: Path, suffix: str):
    # A 3 x 2 grid of sheared (non-square) quads in a Y-up, centimetre stage, under a transformed Xform.
    nx, ny = 3, 2
    local = np.array([(i * 4.0 + j * 1.5, 0.0, j * 2.0) for j in range(ny + 1) for i in range(nx + 1)])
    counts, indices = [], []
    for j in range(ny):
        for i in range(nx):
            a = j * (nx + 1) + i
            counts.append(4)
            indices += [a, a + 1, a + nx + 2, a + nx + 1]
    path = tmp_path / f"grid{suffix}"
    stage = _stage(path, up="Y", meters_per_unit=0.01)
    xform = UsdGeom.Xform.Define(stage, "/World")
    xform.AddTranslateOp().Set(Gf.Vec3d(10.0, 20.0, 30.0))
    xform.AddRotateXOp().Set(30.0)
    xform.AddScaleOp().Set(Gf.Vec3f(2.0, 3.0, 0.5))
    _mesh(stage, "/World/grid", local, counts, indices)
    stage.GetRootLayer().Save()
    del stage

    mesh = read_usd_mesh(path)
    assert isinstance(mesh, UsdMesh)
    assert mesh.path == str(path) and mesh.prim == "/World/grid"

    # Analytic: scale, then rotate 30 degrees about X, then translate (column vectors), in cm, Y-up;
    # then metres, then Y-up -> Z-up: (x, y, z) -> (x, -z, y).
    s = local * np.array([2.0, 3.0, 0.5])
    c, n = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    r = np.stack([s[:, 0], s[:, 1] * c - s[:, 2] * n, s[:, 1] * n + s[:, 2] * c], axis=1)
    w = (r + np.array([10.0, 20.0, 30.0])) * 0.01
    expected = np.stack([w[:, 0], -w[:, 2], w[:, 1]], axis=1)
    assert mesh.vertices.dtype == np.float64 and mesh.vertices.shape == (12, 3)
    np.testing.assert_allclose(mesh.vertices, expected, rtol=0.0, atol=1e-12 * np.abs(expected).max())

    assert mesh.polygon_counts.dtype == np.int32 and mesh.polygon_counts.tolist() == counts
    assert mesh.polygon_indices.dtype == np.int32 and mesh.polygon_indices.tolist() == indices
    assert mesh.triangles.dtype == np.int32 and mesh.triangles.shape == (12, 3)
    assert mesh.triangle_polygon.dtype == np.int32
    assert mesh.triangle_polygon.tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5]

    v = mesh.vertices
    for f in range(len(counts)):
        a, b, cc, d = indices[4 * f:4 * f + 4]
        tris = mesh.triangles[2 * f:2 * f + 2]
        assert set(tris.ravel().tolist()) == {a, b, cc, d}
        # The two triangles cover the quad: areas add up to the quad's (half |diagonal x diagonal|).
        quad_area = 0.5 * np.linalg.norm(np.cross(v[cc] - v[a], v[d] - v[b]))
        areas = [0.5 * np.linalg.norm(_normal(v, t)) for t in tris]
        assert sum(areas) == pytest.approx(quad_area, rel=1e-12)
        assert min(areas) > 0.0
        # Both triangles face the quad's way.
        quad_normal = np.cross(v[cc] - v[a], v[d] - v[b])
        assert all(np.dot(_normal(v, t), quad_normal) > 0.0 for t in tris)
        # The split is along the shorter diagonal: both triangles hold its two ends.
        ac, bd = np.linalg.norm(v[cc] - v[a]), np.linalg.norm(v[d] - v[b])
        assert abs(ac - bd) > 1e-3 * max(ac, bd)  # a non-square quad
        short = {a, cc} if ac < bd else {b, d}
        assert all(short <= set(t.tolist()) for t in tris)


def test_z_up_stage_read_as_y_up(tmp_path: Path):
    points = [(1.0, 2.0, 3.0), (4.0, 5.0, 7.0), (-1.0, 6.0, 0.5)]
    path = _write(tmp_path / "zup.usda", points, [3], [0, 1, 2], up="Z")
    p = np.array(points)
    y_up = read_usd_mesh(path, up_axis="Y")
    np.testing.assert_allclose(y_up.vertices, np.stack([p[:, 0], p[:, 2], -p[:, 1]], axis=1), atol=1e-12)
    z_up = read_usd_mesh(path, up_axis="Z")
    np.testing.assert_allclose(z_up.vertices, p, atol=1e-12)
    # The rotation keeps the winding: the normal turns with the points.
    n_z, n_y = _normal(z_up.vertices, z_up.triangles[0]), _normal(y_up.vertices, y_up.triangles[0])
    np.testing.assert_allclose(n_y, [n_z[0], n_z[2], -n_z[1]], atol=1e-12)


# -------------------------------------------------------------------------------------- triangulation


def test_mixed_faces_triangulate_in_face_order(tmp_path: Path):
    points = [(0, 0, 0), (1, 0, 0), (0, 1, 0),                      # triangle 0 1 2
              (2, 0, 0), (3, 0, 0), (3, 1, 0), (2, 1, 0),            # quad 3 4 5 6
              (5, 0, 0), (6, 0, 0), (6.5, 1, 0), (5.5, 2, 0), (4.5, 1, 0)]  # convex pentagon 7..11
    counts = [3, 4, 5]
    indices = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11]
    mesh = read_usd_mesh(_write(tmp_path / "mixed.usdc", points, counts, indices))
    assert mesh.triangle_polygon.tolist() == [0, 1, 1, 2, 2, 2]
    assert mesh.triangles[0].tolist() == [0, 1, 2]
    assert set(mesh.triangles[1:3].ravel().tolist()) == {3, 4, 5, 6}
    assert mesh.triangles[3:].tolist() == [[7, 8, 9], [7, 9, 10], [7, 10, 11]]  # fan from the first vertex
    assert all(_normal(mesh.vertices, t)[2] > 0.0 for t in mesh.triangles)


def test_concave_quad_is_split_inside(tmp_path: Path):
    # A dart: vertex 2 is reflex; the short diagonal 1-3 lies outside, so the split must be 0-2.
    points = [(0, 0, 0), (4, 1, 0), (1, 1, 0), (1, 4, 0)]
    mesh = read_usd_mesh(_write(tmp_path / "dart.usda", points, [4], [0, 1, 2, 3]))
    assert all({0, 2} <= set(t.tolist()) for t in mesh.triangles)
    assert all(_normal(mesh.vertices, t)[2] > 0.0 for t in mesh.triangles)


def test_non_convex_polygon_is_refused_naming_the_face(tmp_path: Path):
    # An L-shaped hexagon whose first vertex does not see the whole polygon, as face 1.
    hexagon = [(2, 0, 0), (2, 1, 0), (1, 1, 0), (1, 2, 0), (0, 2, 0), (0, 0, 0)]
    points = TRI + hexagon
    path = _write(tmp_path / "ell.usda", points, [3, 6], [0, 1, 2, 3, 4, 5, 6, 7, 8])
    with pytest.raises(ConfigError) as info:
        read_usd_mesh(path)
    message = str(info.value)
    assert "face 1" in message and "ell.usda" in message and "/World/cloth" in message
    assert "triangulate" in message and "\n" not in message


# ------------------------------------------------------------------------------------------ orientation


def test_left_handed_orientation_reverses_winding(tmp_path: Path):
    points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    right = read_usd_mesh(_write(tmp_path / "right.usda", points, [4], [0, 1, 2, 3]))
    left = read_usd_mesh(_write(tmp_path / "left.usda", points, [4], [0, 1, 2, 3], orientation="leftHanded"))
    assert right.polygon_indices.tolist() == [0, 1, 2, 3]
    assert left.polygon_indices.tolist() == [0, 3, 2, 1]  # reversed, first vertex kept first
    for r, l in zip(right.triangles, left.triangles):
        n_r, n_l = _normal(right.vertices, r), _normal(left.vertices, l)
        assert n_r[2] > 0.0 and n_l[2] < 0.0
        np.testing.assert_allclose(n_l, -n_r, atol=1e-12)


def test_mirroring_transform_keeps_the_front(tmp_path: Path):
    path = tmp_path / "mirror.usda"
    stage = _stage(path)
    UsdGeom.Xform.Define(stage, "/World").AddScaleOp().Set(Gf.Vec3f(-1.0, 1.0, 1.0))
    _mesh(stage, "/World/cloth", TRI, [3], [0, 1, 2])
    stage.GetRootLayer().Save()
    mesh = read_usd_mesh(path)
    np.testing.assert_allclose(mesh.vertices, [(0, 0, 0), (-1, 0, 0), (0, 1, 0)], atol=1e-12)
    assert _normal(mesh.vertices, mesh.triangles[0])[2] > 0.0  # the file's front (+z) stays the front


# ------------------------------------------------------------------------------------------- face sets


def test_face_sets_round_trip(tmp_path: Path):
    path = tmp_path / "sets.usdc"
    stage = _stage(path)
    points = [(i, j, 0) for j in range(2) for i in range(4)]
    mesh = _mesh(stage, "/cloth", points, [4, 4, 4], [0, 1, 5, 4, 1, 2, 6, 5, 2, 3, 7, 6])
    imageable = UsdGeom.Imageable(mesh.GetPrim())
    UsdGeom.Subset.CreateGeomSubset(imageable, "hem", UsdGeom.Tokens.face, Vt.IntArray([2, 0, 2]))
    UsdGeom.Subset.CreateGeomSubset(imageable, "middle", UsdGeom.Tokens.face, Vt.IntArray([1]))
    UsdGeom.Subset.CreateGeomSubset(imageable, "corners", UsdGeom.Tokens.point, Vt.IntArray([0, 7]))
    stage.GetRootLayer().Save()
    sets = read_usd_mesh(path).face_sets
    assert sorted(sets) == ["hem", "middle"]  # point subsets are not face sets
    assert sets["hem"].dtype == np.int32 and sets["hem"].tolist() == [0, 2]
    assert sets["middle"].tolist() == [1]


# ------------------------------------------------------------------------------------------------ time


def test_time_sampled_points_read_at_start_time(tmp_path: Path):
    path = tmp_path / "timed.usda"
    stage = _stage(path)
    stage.SetStartTimeCode(10.0)
    stage.SetEndTimeCode(20.0)
    mesh = _mesh(stage, "/cloth", TRI, [3], [0, 1, 2])
    points = mesh.GetPointsAttr()
    points.Set(Vt.Vec3fArray([Gf.Vec3f(*p) for p in TRI]), 10.0)
    points.Set(Vt.Vec3fArray([Gf.Vec3f(p[0] + 5.0, p[1], p[2]) for p in TRI]), 20.0)
    stage.GetRootLayer().Save()
    np.testing.assert_allclose(read_usd_mesh(path).vertices, TRI, atol=1e-12)
    np.testing.assert_allclose(read_usd_mesh(path, time=20.0).vertices, np.array(TRI) + [5.0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(read_usd_mesh(path, time=15.0).vertices, np.array(TRI) + [2.5, 0, 0], atol=1e-6)


def test_time_samples_without_time_range_read_at_earliest_sample(tmp_path: Path):
    path = tmp_path / "samples.usdc"
    stage = _stage(path)
    mesh = UsdGeom.Mesh.Define(stage, "/cloth")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2]))
    for t, dx in ((3.0, 1.0), (7.0, 2.0)):
        mesh.GetPointsAttr().Set(Vt.Vec3fArray([Gf.Vec3f(p[0] + dx, p[1], p[2]) for p in TRI]), t)
    stage.GetRootLayer().Save()
    np.testing.assert_allclose(read_usd_mesh(path).vertices, np.array(TRI) + [1.0, 0, 0], atol=1e-12)


def test_constant_time_sampled_topology_is_accepted(tmp_path: Path):
    path = tmp_path / "same.usda"
    stage = _stage(path)
    mesh = _mesh(stage, "/cloth", TRI, [3], [0, 1, 2])
    for t in (1.0, 2.0):
        mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray([0, 1, 2]), t)
    stage.GetRootLayer().Save()
    assert read_usd_mesh(path).triangles.tolist() == [[0, 1, 2]]


# ---------------------------------------------------------------------------------------------- errors


def _garbage(tmp_path: Path) -> tuple[Path, dict]:
    path = tmp_path / "garbage.usda"
    path.write_text("#usda 1.0\n(\n  this is not ((( usd\n")
    return path, {}


def _no_mesh(tmp_path: Path) -> tuple[Path, dict]:
    path = tmp_path / "empty_stage.usda"
    stage = _stage(path)
    UsdGeom.Xform.Define(stage, "/World")
    stage.GetRootLayer().Save()
    return path, {}


def _several(tmp_path: Path) -> tuple[Path, dict]:
    path = tmp_path / "several.usda"
    stage = _stage(path)
    for k in range(7):
        _mesh(stage, f"/World/m{k}", TRI, [3], [0, 1, 2])
    stage.GetRootLayer().Save()
    return path, {}


def _one(name: str, points=TRI, counts=(3,), indices=(0, 1, 2), **kwargs):
    def make(tmp_path: Path) -> tuple[Path, dict]:
        return _write(tmp_path / name, points, counts, indices), kwargs
    return make


def _not_a_mesh(tmp_path: Path) -> tuple[Path, dict]:
    path, _ = _one("xform.usda")(tmp_path)
    return path, {"prim": "/World"}


def _varying_topology(tmp_path: Path) -> tuple[Path, dict]:
    path = tmp_path / "varying.usdc"
    stage = _stage(path)
    mesh = _mesh(stage, "/World/cloth", TRI + [(1.0, 1.0, 0.0)], [3], [0, 1, 2])
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray([0, 1, 2]), 1.0)
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray([1, 3, 2]), 2.0)
    stage.GetRootLayer().Save()
    return path, {}


def _bad_face_set(tmp_path: Path) -> tuple[Path, dict]:
    path = tmp_path / "bad_set.usda"
    stage = _stage(path)
    mesh = _mesh(stage, "/World/cloth", TRI, [3], [0, 1, 2])
    UsdGeom.Subset.CreateGeomSubset(UsdGeom.Imageable(mesh.GetPrim()), "hem", UsdGeom.Tokens.face,
                                    Vt.IntArray([0, 4]))
    stage.GetRootLayer().Save()
    return path, {}


NAN_POINTS = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (math.nan, 1.0, 0.0)]

ERRORS = {
    # case: (make the file and read_usd_mesh's options, prim named in the message or None, words in it)
    "missing file": (lambda tmp: (tmp / "nowhere.usda", {}), None, ["no such file"]),
    "not usd": (_garbage, None, ["cannot open"]),
    "no mesh": (_no_mesh, None, ["no mesh"]),
    "several meshes": (_several, None, ["7 meshes", "/World/m0", "/World/m4", "2 more", "prim = "]),
    "prim not there": (_one("absent.usda", prim="/World/nothing"), "/World/nothing", ["no prim", "/World/cloth"]),
    "prim not a mesh": (_not_a_mesh, "/World", ["Xform", "not Mesh"]),
    "varying topology": (_varying_topology, "/World/cloth", ["faceVertexIndices", "constant topology"]),
    "non-finite point": (_one("nan.usda", points=NAN_POINTS), "/World/cloth", ["vertex 2", "not finite"]),
    "index out of range": (_one("range.usda", indices=(0, 1, 3)), "/World/cloth", ["face 0", "vertex 3"]),
    "face of 2 vertices": (_one("two.usda", counts=(3, 2), indices=(0, 1, 2, 0, 1)), "/World/cloth",
                           ["face 1", "2 vertices"]),
    "counts vs indices": (_one("sum.usda", counts=(3,), indices=(0, 1, 2, 0)), "/World/cloth",
                          ["add up to 3", "4 entries"]),
    "empty mesh": (_one("empty.usda", points=[], counts=(), indices=()), "/World/cloth", ["empty"]),
    "up axis": (_one("axis.usda", up_axis="X"), None, ["up_axis", "'X'"]),
    "face set out of range": (_bad_face_set, "/World/cloth", ["hem", "face 4"]),
}


@pytest.mark.parametrize("case", list(ERRORS))
def test_errors_are_one_line_naming_file_and_prim(tmp_path: Path, case: str):
    make, prim, words = ERRORS[case]
    path, options = make(tmp_path)
    with pytest.raises(ConfigError) as info:
        read_usd_mesh(path, **options)
    message = str(info.value)
    assert "\n" not in message, message
    assert path.name in message, message
    if prim is not None:
        assert prim in message, message
    for word in words:
        assert word in message, message
