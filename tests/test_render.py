"""The PNG renderer: facts about the picture of tiny hand-made USD scenes (depth, lighting, framing)."""

import numpy as np
import pytest

pytest.importorskip("matplotlib")
import matplotlib.pyplot as plt
from pxr import Usd, UsdGeom

from warpspring.errors import ConfigError
from warpspring.io.render import _BACKGROUND, render_usd

WIDTH = 160
BALL = ((0.0, 0.0, 0.0), 0.5)  # center, radius
SHEET = np.array([[-2.0, -2.0, 0.6], [2.0, -2.0, 0.6], [2.0, 2.0, 0.6], [-2.0, 2.0, 0.6]])
# A closed box around BALL: it hides the ball from any camera, and the centroids of its faces lie
# behind the ball's front, which fools an algorithm that sorts triangles by depth.
BOX_POINTS = 0.6 * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
BOX_FACES = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]


def _write(path, *, meshes=(), spheres=(), up_axis="Z") -> str:
    """A USD file: ``meshes`` as (points per frame (f, n, 3), faces) under /World, each frame a time
    sample, and ``spheres`` as (center, radius) under /World/colliders, placed by a translate op."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, up_axis)
    for i, (frames, faces) in enumerate(meshes):
        mesh = UsdGeom.Mesh.Define(stage, f"/World/cloth{i}")
        mesh.CreateFaceVertexCountsAttr([len(face) for face in faces])
        mesh.CreateFaceVertexIndicesAttr([int(v) for face in faces for v in face])
        for time, points in enumerate(frames):
            mesh.CreatePointsAttr().Set([tuple(map(float, p)) for p in points], time)
    for i, (center, radius) in enumerate(spheres):
        sphere = UsdGeom.Sphere.Define(stage, f"/World/colliders/ball{i}")
        sphere.CreateRadiusAttr(radius)
        sphere.AddTranslateOp().Set(tuple(map(float, center)))
    stage.GetRootLayer().Save()
    return str(path)


def _render(folder, **scene) -> np.ndarray:
    """Render a scene described as for ``_write`` to an RGB image with values in [0, 1].

    Every scene file has the same name, so that the captions of the pictures match.
    """
    folder.mkdir(exist_ok=True)
    png = render_usd(_write(folder / "scene.usda", **scene), str(folder / "scene.png"), width=WIDTH)
    return plt.imread(png)[..., :3]


def _center(image: np.ndarray) -> np.ndarray:
    return image[image.shape[0] // 2, image.shape[1] // 2]


def test_image_has_the_requested_size_and_background_around_the_subject(tmp_path):
    image = _render(tmp_path, spheres=[BALL])
    assert image.shape == (round(0.75 * WIDTH), WIDTH, 3)
    for corner in (image[0, 0], image[0, -1], image[-1, 0], image[-1, -1]):
        np.testing.assert_allclose(corner, _BACKGROUND, atol=1 / 255)
    r, g, b = _center(image)
    assert b > r + 0.05  # the sphere's blue-grey fills the middle


def test_cloth_between_camera_and_sphere_hides_the_sphere(tmp_path):
    image = _render(tmp_path, spheres=[BALL], meshes=[([BOX_POINTS], BOX_FACES)])
    r, g, b = _center(image)
    assert r > b + 0.15  # the cloth's red
    bluish = image[..., 2] > image[..., 0] + 0.02
    assert not bluish.any(), f"{bluish.sum()} pixels show the sphere through the cloth"


def test_the_half_of_a_sphere_facing_the_light_is_brighter(tmp_path):
    image = _render(tmp_path, spheres=[BALL])
    rows = np.nonzero((image < 0.98).any(axis=2))[0]
    middle = int(rows.mean())
    brightness = [part[(part < 0.98).any(axis=2)].mean() for part in (image[:middle], image[middle:])]
    assert brightness[0] > brightness[1] + 0.15  # the light comes from above


def test_both_sides_of_a_sheet_are_lit_alike(tmp_path):
    up = _render(tmp_path / "up", meshes=[([SHEET], [[0, 1, 2, 3]])])
    down = _render(tmp_path / "down", meshes=[([SHEET], [[3, 2, 1, 0]])])
    np.testing.assert_allclose(up, down, atol=1 / 255)
    assert _center(up)[0] > 0.6  # lit by the key light, not by ambient light alone


def test_y_up_stages_look_like_their_z_up_equivalent(tmp_path):
    to_y_up = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # (x, y, z) → (x, z, -y)
    slope = SHEET + np.array([[0, 0, 0], [0, 0, 0], [0, 0, 1.5], [0, 0, 1.5]])
    ball = np.array([0.3, 0.2, 2.2])
    z_up = _render(tmp_path / "z", meshes=[([slope], [[0, 1, 2, 3]])], spheres=[(ball, 0.5)])
    y_up = _render(tmp_path / "y", meshes=[([slope @ to_y_up.T], [[0, 1, 2, 3]])],
                   spheres=[(to_y_up @ ball, 0.5)], up_axis="Y")
    differ = np.abs(y_up - z_up).max(axis=2) > 2 / 255
    assert differ.mean() < 0.002  # the sphere's triangles turn with the axes: its outline may move a pixel


def test_frames_count_from_either_end_of_the_time_samples(tmp_path):
    sliding = [SHEET + (dx, 0.0, 0.0) for dx in (0.0, 1.0, 2.0)]
    usd = _write(tmp_path / "anim.usda", meshes=[(sliding, [[0, 1, 2, 3]])], spheres=[BALL])
    last, third = (plt.imread(render_usd(usd, str(tmp_path / f"{f}.png"), frame=f, width=WIDTH)) for f in (-1, 2))
    first = plt.imread(render_usd(usd, str(tmp_path / "first.png"), frame=-3, width=WIDTH))
    np.testing.assert_array_equal(last, third)
    assert not np.array_equal(first, last)
    for frame in (3, -4):
        with pytest.raises(ConfigError, match=f"frame {frame} is out of range: the file has 3 frames"):
            render_usd(usd, str(tmp_path / "x.png"), frame=frame)


def test_unusable_inputs_raise_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="USD file not found"):
        render_usd(str(tmp_path / "missing.usdc"), str(tmp_path / "x.png"))
    empty = _write(tmp_path / "empty.usda")
    with pytest.raises(ConfigError, match="holds no mesh or sphere"):
        render_usd(empty, str(tmp_path / "x.png"))
    garbage = tmp_path / "garbage.usda"
    garbage.write_text("not a USD layer")
    with pytest.raises(ConfigError, match="garbage.usda.*cannot open it .*valid .usda"):  # its layers read first
        render_usd(str(garbage), str(tmp_path / "x.png"))
    scene = _write(tmp_path / "ball.usda", spheres=[BALL])
    with pytest.raises(ConfigError, match="output folder does not exist"):
        render_usd(scene, str(tmp_path / "no" / "x.png"))
