"""Scene files with box and capsule colliders, restitution, colliders moved by keyframe tracks and the
``[contacts]`` table: what the model gets, and the one-line errors of bad tables. Then the turntable
example, parsed and run for two frames."""

import pathlib

import numpy as np
import pytest
from pxr import Usd, UsdGeom

import warpspring as ws
from warpspring.app.cli import main
from warpspring.io.scene import load_scene, parse_scene, tomllib

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"

SCENE = """\
version = 2

[cloth]
grid = { nx = 3, ny = 4, spacing = 0.1 }
origin = [-0.1, -0.15, 1.0]
mass = 0.12

[[collider]]
type = "box"
name = "crate"
center = [0.0, 0.0, 0.3]
half_extents = [0.4, 0.3, 0.2]
orientation = [0.0, 0.0, 1.0, 1.0]           # 90° about z, not normalised
friction = 0.7
restitution = 0.25
rotation = { times = [0.0, 1.0, 3.0], axis = [0, 0, 2], degrees = [0.0, 0.0, 90.0], interpolation = "smooth" }

[[collider]]
type = "capsule"
center = [1.0, 0.0, 0.1]
radius = 0.1
half_height = 0.5
translation = { times = [0.0, 2.0], values = [[0, 0, 0], [0, 1, 0]], extrapolation = "cycle" }

[[collider]]
type = "sphere"
center = [0.0, 1.0, 0.5]
radius = 0.2
restitution = 1.0

[[collider]]
type = "plane"
point = [0.0, 0.0, -0.5]
rotation = { times = [0.0, 1.0], axis = [1, 0, 0], degrees = [0.0, 10.0] }

[[collider]]
type = "ground"
restitution = 0.5

[contacts]
slots = 5
stage = true
"""


def scene_data(text: str = SCENE) -> dict:
    return tomllib.loads(text)


def collider_error(text: str) -> str:
    """The one-line message of the ConfigError that parsing ``text`` raises, checked to name the file."""
    with pytest.raises(ws.ConfigError) as info:
        parse_scene(scene_data(text), path="/a/scene.toml")
    message = str(info.value)
    assert "\n" not in message and message.startswith("scene.toml: ")
    return message


def test_colliders_tracks_restitution_and_contacts_reach_the_model():
    """Each collider table becomes a ShapeInfo of its kind with its size, rest frame (the orientation
    normalised), friction, restitution and tracks (degrees about the axis turned into rotation vectors
    [rad]); [contacts] sets the model's contact stage and slots."""
    scene = parse_scene(scene_data(), path="s.toml")
    assert (scene.contact_stage, scene.contact_slots) == (True, 5)
    model = scene.finalize("cpu")
    assert model.contact_stage is True and model.contact_slots == 5
    crate, capsule, sphere, plane, ground = model.shapes
    assert [s.kind for s in model.shapes] == ["box", "capsule", "sphere", "plane", "plane"]
    assert [s.name for s in model.shapes] == ["crate", "capsule", "sphere", "plane", "ground"]

    np.testing.assert_allclose(crate.position, [0.0, 0.0, 0.3])
    np.testing.assert_allclose(crate.rotation, [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(crate.size, [0.4, 0.3, 0.2])
    assert (crate.friction, crate.restitution) == (0.7, 0.25)
    assert crate.translation_track is None and crate.moving
    spin = crate.rotation_track
    np.testing.assert_allclose(spin.values, [[0, 0, 0], [0, 0, 0], [0, 0, np.pi / 2]], atol=1e-12)
    assert (spin.interpolation, spin.extrapolation) == ("smooth", "hold")
    # At 3 s the crate has turned 90° more about z: 180° in all, so its quaternion is ±(0, 0, 1, 0).
    position, quat = crate.frame(3.0)
    np.testing.assert_allclose(position, crate.position)
    np.testing.assert_allclose(np.abs(quat), [0.0, 0.0, 1.0, 0.0], atol=1e-12)

    np.testing.assert_allclose(capsule.size, [0.1, 0.5, 0.0])
    np.testing.assert_allclose(capsule.rotation, [0.0, 0.0, 0.0, 1.0])
    assert (capsule.friction, capsule.restitution) == (0.5, 0.0)  # the defaults
    slide = capsule.translation_track
    np.testing.assert_array_equal(slide.values, [[0, 0, 0], [0, 1, 0]])
    assert slide.extrapolation == "cycle" and capsule.rotation_track is None
    np.testing.assert_allclose(capsule.frame(3.0)[0], [1.0, 0.5, 0.1])  # cycling: 3 s is 1 s into the track

    assert sphere.size == (0.2, 0.0, 0.0) and sphere.restitution == 1.0 and not sphere.moving
    assert plane.rotation_track is not None and plane.translation_track is None
    np.testing.assert_allclose(plane.position, [0.0, 0.0, -0.5])
    assert ground.restitution == 0.5 and not ground.moving


def test_contacts_defaults_are_the_models():
    """Without [contacts] the model chooses: the contact stage because a collider moves, and one slot per
    collider up to 4."""
    data = scene_data()
    del data["contacts"]
    scene = parse_scene(data, path="s.toml")
    assert scene.contact_stage is None and scene.contact_slots is None
    model = scene.finalize("cpu")
    assert model.contact_stage is True and model.contact_slots == 4

    data = scene_data()
    data["contacts"] = {"stage": False, "slots": 2}
    model = parse_scene(data, path="s.toml").finalize("cpu")
    assert model.contact_stage is False and model.contact_slots == 2


def _edit(old: str, new: str) -> str:
    assert old in SCENE, old
    return SCENE.replace(old, new, 1)


BAD = [
    # scene, words the message must hold
    (_edit("half_extents = [0.4, 0.3, 0.2]", "half_extent = [0.4, 0.3, 0.2]"),
     ["unknown key 'half_extent' in [collider[0]]", "allowed:", "half_extents"]),
    (_edit("half_extents = [0.4, 0.3, 0.2]\n", ""),
     ["box collider ([collider[0]])", "needs center = [x, y, z] and half_extents", "missing: half_extents"]),
    (_edit("half_height = 0.5\n", ""), ["capsule collider ([collider[1]])", "missing: half_height"]),
    (_edit("half_extents = [0.4, 0.3, 0.2]", "half_extents = [0.4, 0.0, 0.2]"),
     ["collider[0].half_extents", "> 0", "[0.4, 0.0, 0.2]"]),
    (_edit("orientation = [0.0, 0.0, 1.0, 1.0]", "orientation = [0.0, 0.0, 1.0]"),
     ["collider[0].orientation", "quaternion [x, y, z, w]"]),
    (_edit("orientation = [0.0, 0.0, 1.0, 1.0]", "orientation = [0.0, 0.0, 0.0, 0.0]"),
     ["collider[0].orientation", "not all zero"]),
    (_edit("restitution = 0.25", "restitution = 1.5"), ["collider[0].restitution", "from 0 to 1", "1.5"]),
    (_edit("restitution = 0.25", "restitution = -0.1"), ["collider[0].restitution", ">= 0"]),
    (_edit("radius = 0.1\nhalf_height = 0.5", "radius = 0.1\nhalf_height = 0.5\nhalf_extents = [1, 1, 1]"),
     ["collider[1].half_extents does not apply to a capsule collider", "it takes:"]),
    (_edit('type = "ground"\n', 'type = "ground"\ntranslation = { times = [0.0], values = [[0, 0, 1]] }\n'),
     ["collider[4].translation does not apply to a ground collider"]),
    (_edit("degrees = [0.0, 0.0, 90.0]", "degrees = [0.0, 90.0]"), ["collider[0].rotation", "3 times but 2 degrees"]),
    (_edit("times = [0.0, 2.0]", "times = [2.0, 0.0]"), ["collider[1].translation", "increase strictly"]),
    (_edit("axis = [1, 0, 0]", "values = [[0, 0, 0], [1, 0, 0]], axis = [1, 0, 0]"),
     ["unknown key 'values' in [collider[3].rotation]", "degrees"]),
    (_edit('type = "box"', 'type = "cone"'), ["collider[0].type", "ground, plane, sphere, box, capsule", "'cone'"]),
    (_edit("slots = 5", "slots = 0"), ["contacts.slots", ">= 1"]),
    (_edit("slots = 5", "slots = 65"), ["contacts.slots", "1 to 64"]),
    (_edit("stage = true", "buffer = true"), ["unknown key 'buffer' in [contacts]", "allowed: stage, slots"]),
    (_edit("stage = true", "stage = 1"), ["contacts.stage", "true or false"]),
]


@pytest.mark.parametrize("text, words", BAD, ids=[
    "misspelt-half-extents", "box-without-half-extents", "capsule-without-half-height", "flat-box",
    "three-number-orientation", "zero-orientation", "restitution-above-1", "negative-restitution",
    "box-key-on-capsule", "track-on-ground", "rotation-track-short", "translation-times-decrease",
    "rotation-track-with-values", "unknown-type", "no-slots", "too-many-slots", "unknown-contacts-key",
    "stage-not-bool",
])
def test_bad_collider_and_contacts_tables_are_named(text, words):
    """Each fault is a one-line error naming the file, the table (numbered among several) and the key."""
    message = collider_error(text)
    for word in words:
        assert word in message, message


FORMAT_1_CLOTH = "[cloth]\ngrid = { nx = 3, ny = 3, spacing = 0.1 }\nmass = 0.1\n"  # no version: format 1
FORMAT_1_CAPSULE = FORMAT_1_CLOTH + "[[collider]]\ntype = 'capsule'\ncenter = [0, 0, 0]\nradius = 0.1\n"


@pytest.mark.parametrize("text, what", [
    (FORMAT_1_CAPSULE + "half_height = 0.2\n", "collider.half_height needs scene format 2"),
    (FORMAT_1_CAPSULE, "box, capsule and mesh colliders need scene format 2"),  # the type is checked before its keys
    (FORMAT_1_CLOTH + "[[collider]]\ntype = 'ground'\nrestitution = 0.5\n",
     "collider.restitution needs scene format 2"),
    (FORMAT_1_CLOTH + "[contacts]\nslots = 2\n", "[contacts] needs scene format 2"),
], ids=["capsule-key", "capsule-type", "restitution", "contacts"])
def test_new_collider_features_need_format_2(text, what):
    """A file without version = 2 (format 1, read as before) is told to declare it for what format 2 added."""
    message = collider_error(text)
    assert what in message and "add version = 2" in message


# -- the turntable example --------------------------------------------------------------------------------


def test_turntable_example_builds_a_turning_box_and_a_capsule():
    """The example's box turns about the up axis from rest (a smooth start) and its capsule lies on the ground."""
    model = load_scene(EXAMPLES / "turntable.toml").finalize("cpu")
    assert [s.kind for s in model.shapes] == ["box", "capsule", "plane"]
    box, log, _ = model.shapes
    assert box.moving and not log.moving and model.contact_stage and model.contact_slots == 3
    spin = box.rotation_track
    assert np.abs(spin.values[:, :2]).max() == 0.0 and spin.interpolation == "smooth"  # about z only
    angle = spin.sample(np.array([0.5, 1.0, 1.01, 4.0]))[0][:, 2]
    rate = spin.sample(np.array([1.0]))[1][0, 2]
    assert angle[0] == angle[1] == 0.0 and 0.0 < angle[2] < 1e-3 and rate == 0.0 and angle[3] > np.pi / 2
    _, quat = log.frame(0.0)
    axis = quat_axis_z(quat)
    np.testing.assert_allclose(np.abs(axis), [0.0, 1.0, 0.0], atol=1e-6)  # lying along y
    assert log.position[2] == pytest.approx(log.size[0])  # resting on the ground


def quat_axis_z(quat) -> np.ndarray:
    """Where a rotation (x, y, z, w) turns the local z axis."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(quat).apply([0.0, 0.0, 1.0])


def test_turntable_example_runs(tmp_path, capsys, device):
    """``warpspring run examples/turntable.toml --frames 2``: exit 0, and the box's orient op is sampled at
    frames 0, 1, 2 (still at rest: the turntable starts after 1 s)."""
    out = tmp_path / "turntable.usdc"
    status = main(["run", str(EXAMPLES / "turntable.toml"), "-o", str(out), "--frames", "2", "--device", device, "-q"])
    stdout, stderr = capsys.readouterr()
    assert status == 0, stderr
    assert stdout.startswith("wrote 3 frames ") and "box, capsule, plane" in stdout
    stage = Usd.Stage.Open(str(out))
    box = stage.GetPrimAtPath("/World/colliders/turntable")
    assert box.IsA(UsdGeom.Cube) and UsdGeom.Imageable(box).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
    orient = box.GetAttribute("xformOp:orient")
    assert orient.GetTimeSamples() == [0.0, 1.0, 2.0]
    assert stage.GetPrimAtPath("/World/colliders/log").IsA(UsdGeom.Capsule)
