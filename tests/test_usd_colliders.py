"""USD export and rendering of box and capsule colliders, and of colliders moved by keyframe tracks: prim
types, guide purpose, sizes, extents, a moving collider's time-sampled pose (against ``ShapeInfo.frame``,
the host float64 reference), multi-world copies, and what the renderer draws at a frame."""

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdValidation
from scipy.spatial.transform import Rotation

import warpspring as ws
from warpspring.io.render import render_usd
from warpspring.io.usd import UsdWriter, world_prim_name

FPS = 24.0
FRAMES = 4  # frames written: time codes 0..3, t = 0, 1/24, 2/24, 3/24 s
SOFT = ws.SpringMaterial(ke=10.0, kd=0.01)
HALF = (0.3, 0.2, 0.1)  # the static box's half extents [m]
TILT = ws.quat_from_axis_angle((1.0, 1.0, 0.0), 0.4)  # the static box's and the capsule's rest orientation
# The moving box slides 1 m along x and climbs 0.3 m while it turns 180° about a tilted axis, in 3/24 s:
# every written frame has its own pose.
SLIDE = ws.Track([0.0, 3.0 / FPS], [[0.0, 0.0, 0.0], [1.0, 0.0, 0.3]])
SPIN = ws.Track.rotation([0.0, 3.0 / FPS], axis=(0.2, 0.3, 1.0), degrees=[0.0, 180.0], interpolation="smooth")
# Rendering: a sample is a collider's when it is blue-grey (the renderer's collider colour, lit).
WIDTH = 160


def collider_model(device, *, worlds: int = 1, placed=None) -> ws.Model:
    """A small cloth well above a static box, a capsule and a box moved by SLIDE and SPIN, over the ground;
    with ``placed`` = (position, quaternion), that box stands still there instead."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=4, ny=4, spacing=0.1, mass=0.1, origin=(-0.15, -0.15, 2.0), structural=SOFT,
                           shear=SOFT, bend=SOFT)
    builder.add_collider_box(center=(-0.8, 0.4, 0.3), half_extents=HALF, orientation=TILT, name="crate")
    builder.add_collider_capsule(center=(0.6, 0.7, 0.25), radius=0.15, half_height=0.4, orientation=TILT,
                                 name="log")
    if placed is None:
        builder.add_collider_box(center=(0.0, -0.5, 0.4), half_extents=(0.25, 0.25, 0.25), translation=SLIDE,
                                 rotation=SPIN, name="mover")
    else:
        builder.add_collider_box(center=placed[0], half_extents=(0.25, 0.25, 0.25), orientation=placed[1],
                                 name="mover")
    builder.add_ground_plane()
    return builder.finalize(device, worlds=worlds)


def write(path, model: ws.Model, frames: int = FRAMES, **options) -> str:
    """``frames`` frames of the model's rest state (the cloth stays put; only the colliders move)."""
    with UsdWriter(path, model, fps=FPS, **options) as writer:
        for _ in range(frames):
            writer.write_frame(model.state())
    return str(path)


def shape(model: ws.Model, name: str):
    return next(s for s in model.shapes if s.name == name)


def ops(prim) -> dict:
    """The prim's xform ops by name ("translate", "orient", "scale")."""
    return {op.GetOpName().split(":")[1]: op for op in UsdGeom.Xformable(prim).GetOrderedXformOps()}


def local_to_world(prim, time: float) -> np.ndarray:
    """The prim's 4 × 4 local-to-world matrix at ``time``, acting on column vectors."""
    matrix = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode(time))
    return np.array(matrix).T


def rotation_matrix(quat_xyzw) -> np.ndarray:
    return Rotation.from_quat(quat_xyzw).as_matrix()


# -- export ---------------------------------------------------------------------------------------------


def test_box_and_capsule_prims_sizes_extents_and_purpose(tmp_path, device):
    """A box is a Cube of size 2 (extent ±1) scaled by its half extents; a capsule a Capsule of its radius,
    height 2·half_height along Z, extent ±(r, r, half_height + r); every collider prim is a guide; and the
    world transform puts their corners and caps where the model's shapes are."""
    model = collider_model(device)
    stage = Usd.Stage.Open(write(tmp_path / "colliders.usdc", model))
    for name in ("crate", "log", "mover", "ground"):
        prim = stage.GetPrimAtPath(f"/World/colliders/{name}")
        assert UsdGeom.Imageable(prim).GetPurposeAttr().Get() == UsdGeom.Tokens.guide, name

    crate = stage.GetPrimAtPath("/World/colliders/crate")
    assert crate.IsA(UsdGeom.Cube)
    cube = UsdGeom.Cube(crate)
    assert cube.GetSizeAttr().Get() == 2.0
    np.testing.assert_array_equal(np.array(cube.GetExtentAttr().Get()), [[-1, -1, -1], [1, 1, 1]])
    np.testing.assert_allclose(np.array(ops(crate)["scale"].Get()), HALF, rtol=1e-12)
    assert UsdGeom.Xformable(crate).GetXformOpOrderAttr().Get() == ["xformOp:translate", "xformOp:orient",
                                                                       "xformOp:scale"]
    # The cube's corner (1, 1, 1) lands on the box's corner centre + R · half extents.
    info = shape(model, "crate")
    corner = local_to_world(crate, 0.0) @ [1.0, 1.0, 1.0, 1.0]
    np.testing.assert_allclose(corner[:3], np.array(info.position) + rotation_matrix(info.rotation) @ HALF, atol=1e-9)

    log = stage.GetPrimAtPath("/World/colliders/log")
    assert log.IsA(UsdGeom.Capsule)
    capsule = UsdGeom.Capsule(log)
    assert capsule.GetRadiusAttr().Get() == pytest.approx(0.15)
    assert capsule.GetHeightAttr().Get() == pytest.approx(0.8)
    assert capsule.GetAxisAttr().Get() == UsdGeom.Tokens.z
    np.testing.assert_allclose(np.array(capsule.GetExtentAttr().Get()), [[-0.15, -0.15, -0.55], [0.15, 0.15, 0.55]],
                               rtol=1e-6)
    assert "scale" not in ops(log)
    info = shape(model, "log")
    tip = local_to_world(log, 0.0) @ [0.0, 0.0, 0.55, 1.0]  # the end of its upper cap on its own z axis
    np.testing.assert_allclose(tip[:3], np.array(info.position) + rotation_matrix(info.rotation) @ [0, 0, 0.55],
                               atol=1e-9)


def test_moving_collider_is_sampled_at_every_frame_and_static_ones_are_not(tmp_path, device):
    """The moving box's translate and orient ops hold one sample per written frame, at its time code k,
    equal to ShapeInfo.frame(k / fps); the static colliders' ops hold a default value and no sample."""
    model = collider_model(device)
    stage = Usd.Stage.Open(write(tmp_path / "moving.usdc", model))
    mover = shape(model, "mover")
    assert mover.moving
    prim = stage.GetPrimAtPath("/World/colliders/mover")
    translate, orient = ops(prim)["translate"], ops(prim)["orient"]
    assert translate.GetTimeSamples() == orient.GetTimeSamples() == [float(k) for k in range(FRAMES)]
    poses = []
    for k in range(FRAMES):
        position, quat = mover.frame(k / FPS)
        np.testing.assert_allclose(np.array(translate.Get(k)), position, atol=1e-6)
        q = orient.Get(k)
        np.testing.assert_allclose([*q.GetImaginary(), q.GetReal()], quat, atol=1e-6)
        # The composed transform too: the box's corner (+1, +1, +1) of the unit cube, scaled and turned.
        corner = local_to_world(prim, k) @ [1.0, 1.0, 1.0, 1.0]
        np.testing.assert_allclose(corner[:3], position + rotation_matrix(quat) @ [0.25, 0.25, 0.25], atol=1e-6)
        poses.append(position)
    assert len({tuple(np.round(p, 6)) for p in poses}) == FRAMES  # every frame has its own pose

    for name in ("crate", "log", "ground"):
        static = stage.GetPrimAtPath(f"/World/colliders/{name}")
        for op in ops(static).values():
            assert op.GetTimeSamples() == [], f"{name}: {op.GetOpName()} is time-sampled"
        position, quat = shape(model, name).frame(0.0)
        np.testing.assert_allclose(np.array(ops(static)["translate"].Get()), position, atol=1e-12)


def test_every_world_gets_its_own_moving_colliders(tmp_path, device):
    """With every world of a model of two exported, each world's copy of the moving box is sampled at the
    shared frame times with the same local pose (its world's prim places it)."""
    model = collider_model(device, worlds=2)
    stage = Usd.Stage.Open(write(tmp_path / "worlds.usdc", model, frames=3))
    mover = shape(model, "mover")
    for w in range(2):
        root = f"/World/{world_prim_name(w, 2)}/colliders"
        assert stage.GetPrimAtPath(f"{root}/crate").IsA(UsdGeom.Cube)
        assert stage.GetPrimAtPath(f"{root}/log").IsA(UsdGeom.Capsule)
        translate = ops(stage.GetPrimAtPath(f"{root}/mover"))["translate"]
        assert translate.GetTimeSamples() == [0.0, 1.0, 2.0]
        for k in range(3):
            np.testing.assert_allclose(np.array(translate.Get(k)), mover.frame(k / FPS)[0], atol=1e-6)


def test_usd_validation_reports_nothing(tmp_path, device):
    """Every registered pxr.UsdValidation validator passes on a stage with cubes, a capsule and time-sampled ops."""
    stage = Usd.Stage.Open(write(tmp_path / "valid.usdc", collider_model(device)))
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(stage)
    assert [e.GetMessage() for e in errors] == []


# -- rendering ------------------------------------------------------------------------------------------


def collider_pixels(image: np.ndarray) -> np.ndarray:
    """Where the image shows a collider: blue-grey pixels (the cloth is red, the ground and sky grey-white)."""
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    return (b > r + 0.04) & (b > g)


def render(usd: str, png, **options) -> np.ndarray:
    """The RGB image, values in [0, 1], that ``warpspring render`` makes of ``usd``."""
    plt = pytest.importorskip("matplotlib.pyplot")
    return plt.imread(render_usd(usd, str(png), width=WIDTH, **options))[..., :3]


def test_renderer_draws_a_moving_box_where_it_is_at_the_frame(tmp_path, device):
    """The last frame of the moving box looks like a box placed, static, at its pose of that frame; the
    first frame does not (the renderer reads the xform at the frame's time code)."""
    model = collider_model(device)
    for folder in ("moving", "placed"):  # both files of one name, so that the pictures' captions match
        (tmp_path / folder).mkdir()
    usd = write(tmp_path / "moving" / "scene.usdc", model)
    last = render(usd, tmp_path / "moving" / "last.png", frame=-1)
    first = render(usd, tmp_path / "moving" / "first.png", frame=0)

    still = collider_model(device, placed=shape(model, "mover").frame((FRAMES - 1) / FPS))
    placed = render(write(tmp_path / "placed" / "scene.usdc", still), tmp_path / "placed" / "last.png", frame=-1)

    differ = np.abs(last - placed).max(axis=2) > 2 / 255
    assert differ.mean() < 0.001  # the same pose, up to rounding: an outline may move by a pixel
    assert (np.abs(first - last).max(axis=2) > 2 / 255).mean() > 0.02
    covered = collider_pixels(last).mean()
    assert 0.05 < covered < 0.6, f"colliders cover {covered:.1%} of the image"


def _stage(path, prims) -> str:
    """A USD file of hand-made collider prims: ``prims`` are (kind, attributes, scale) under /World/colliders,
    each at the origin, with a static cloth quad far below (so the file has a frame)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    mesh = UsdGeom.Mesh.Define(stage, "/World/cloth")
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreatePointsAttr().Set([(-0.1, -0.1, -5.0), (0.1, -0.1, -5.0), (0.1, 0.1, -5.0), (-0.1, 0.1, -5.0)], 0.0)
    for i, (kind, attributes, scale) in enumerate(prims):
        prim = getattr(UsdGeom, kind).Define(stage, f"/World/colliders/c{i}")
        for name, value in attributes.items():
            prim.GetPrim().GetAttribute(name).Set(value)
        UsdGeom.Imageable(prim).CreatePurposeAttr(UsdGeom.Tokens.guide)
        if scale is not None:
            prim.AddScaleOp().Set(Gf.Vec3f(*scale))
    stage.GetRootLayer().Save()
    return str(path)


def _shape_of_covered(image: np.ndarray) -> tuple[float, float]:
    """Width and height [pixels] of the part of the image the colliders cover."""
    rows, cols = np.nonzero(collider_pixels(image))
    assert len(rows) > 100, "no collider is drawn"
    return float(np.ptp(cols) + 1), float(np.ptp(rows) + 1)


@pytest.mark.parametrize("kind, lying, standing", [
    ("Cube", ({"size": 2.0}, (1.0, 0.15, 0.15)), ({"size": 2.0}, (0.15, 0.15, 1.0))),
    ("Capsule", ({"radius": 0.15, "height": 1.6, "axis": "X"}, None),
     ({"radius": 0.15, "height": 1.6, "axis": "Z"}, None)),
], ids=["cube-scaled", "capsule-axis"])
def test_a_long_collider_lying_is_wide_and_standing_is_tall(tmp_path, kind, lying, standing):
    """A guide-purpose Cube drawn through its scale op, and a Capsule along its axis: along x it is wider than
    tall in the picture, along z (up) taller than wide."""
    pictures = {}
    for pose, (attributes, scale) in (("lying", lying), ("standing", standing)):
        (tmp_path / pose).mkdir()
        usd = _stage(tmp_path / pose / "c.usda", [(kind, attributes, scale)])
        pictures[pose] = _shape_of_covered(render(usd, tmp_path / pose / "c.png"))
    (w, h), (w_up, h_up) = pictures["lying"], pictures["standing"]
    assert w > 2.0 * h and h_up > 2.0 * w_up, pictures
