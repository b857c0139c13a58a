"""Scene files: the schema parse_scene enforces (keys, types, ranges, exclusive choices) and how a scene maps
onto the model it builds. Nothing here simulates, so no kernel is compiled."""

import copy
import os
import pathlib

import numpy as np
import pytest

import warpspring as ws
from warpspring.io.scene import DeprecatedKeyWarning, load_scene, parse_scene
from warpspring.io.scene_schema import SCENE_FORMAT_VERSION

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"


def minimal() -> dict:
    """The smallest valid scene: one 3 × 4 grid cloth."""
    return {"cloth": {"grid": {"nx": 3, "ny": 4, "spacing": 0.1}, "mass": 0.12}}


def changed(edit) -> dict:
    """The minimal scene after ``edit(scene)``."""
    data = copy.deepcopy(minimal())
    edit(data)
    return data


def set_path(data: dict, dotted: str, value) -> None:
    """Set ``data["a"]["b"]... = value`` for dotted = "a.b...", creating tables on the way."""
    *tables, key = dotted.split(".")
    for t in tables:
        data = data.setdefault(t, {})
    data[key] = value


def parse_error(data: dict) -> str:
    """The message of the ConfigError that parse_scene raises for ``data`` (checked to be one line naming the file)."""
    with pytest.raises(ws.ConfigError) as info:
        parse_scene(data, path="/some/folder/scene.toml")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("scene.toml: ")
    return message


# -- defaults and values ----------------------------------------------------------------------------------


def test_defaults_of_a_minimal_scene():
    """A scene with only a cloth gets 60 fps, 120 frames, substeps chosen before the run ("auto"), symplectic
    Euler, float32 and no output."""
    scene = parse_scene(minimal(), path="s.toml")
    assert (scene.fps, scene.frames, scene.substeps) == (60.0, 120, "auto")
    assert (scene.integrator, scene.precision) == ("symplectic_euler", "float32")
    assert scene.device is None and scene.output is None
    assert scene.export_particles is False and scene.export_springs is False
    assert scene.colliders == [] and len(scene.cloths) == 1


def test_values_are_carried_over():
    """Simulation, output and world values reach the Scene (an integer fps becomes a float)."""
    data = minimal()
    data["simulation"] = {"fps": 30, "frames": 7, "substeps": 3, "precision": "float64", "device": "cpu"}
    data["output"] = {"path": "x.usdc", "particles": True, "springs": True}
    data["world"] = {"up_axis": "Y", "gravity": [0.0, -1.62, 0.0], "drag": 0.5}
    scene = parse_scene(data, path="s.toml")
    assert scene.fps == 30.0 and isinstance(scene.fps, float)
    assert (scene.frames, scene.substeps, scene.precision, scene.device) == (7, 3, "float64", "cpu")
    assert (scene.output, scene.export_particles, scene.export_springs) == ("x.usdc", True, True)
    assert scene.world == {"up_axis": "Y", "gravity": [0.0, -1.62, 0.0], "drag": 0.5}


# -- the schema ---------------------------------------------------------------------------------------------

BAD_VALUES = [
    # key, value, words the message must hold
    ("simulation.frames", 2.5, ["simulation.frames", "integer"]),
    ("simulation.frames", 0, ["simulation.frames", ">= 1"]),
    ("simulation.substeps", 0, ["simulation.substeps", ">= 1"]),
    ("simulation.substeps", -4, ["simulation.substeps", ">= 1"]),
    ("simulation.fps", 0, ["simulation.fps", "> 0"]),
    ("simulation.fps", -30.0, ["simulation.fps", "> 0"]),
    ("simulation.fps", float("nan"), ["simulation.fps"]),
    ("simulation.fps", "60", ["simulation.fps", "number"]),
    ("simulation.fps", True, ["simulation.fps", "number"]),
    ("simulation.precision", "float16", ["simulation.precision", "float32", "float64"]),
    ("simulation.integrator", "rk9", ["'rk9'", "symplectic_euler"]),
    ("simulation.integrator_options", 3, ["simulation.integrator_options", "table"]),
    ("world.gravity", [0.0, -9.81], ["world.gravity", "3"]),
    ("world.gravity", [0.0, 0.0, "down"], ["world.gravity", "3"]),
    ("world.gravity", [0.0, 0.0, float("inf")], ["world.gravity", "finite"]),
    ("world.gravity", [0.0, 0.0, True], ["world.gravity"]),
    ("world.drag", -1.0, ["world.drag", ">= 0"]),
    ("cloth.origin", "0 0 1", ["cloth.origin", "3"]),
    ("cloth.name", 7, ["cloth.name", "string"]),
    ("cloth.mass", -0.1, ["cloth.mass", "> 0"]),
    ("cloth.mass", 0, ["cloth.mass", "> 0"]),
    ("cloth.radius", -0.01, ["cloth.radius", ">= 0"]),
    ("cloth.grid.nx", 1, ["cloth.grid.nx", ">= 2"]),
    ("cloth.grid.ny", 3.0, ["cloth.grid.ny", "integer"]),
    ("cloth.grid.spacing", 0.0, ["cloth.grid.spacing", "> 0"]),
    ("cloth.structural.ke", -100.0, ["cloth.structural.ke", ">= 0"]),
    ("cloth.shear.kd", -1.0, ["cloth.shear.kd", ">= 0"]),
    ("cloth.bend", "soft", ["cloth.bend", "ke", "false"]),
    ("cloth.pin", "top", ["cloth.pin", "list"]),
    ("cloth.pin", [1.5], ["cloth.pin", "1.5"]),
    ("cloth.rotation.axis", [0, 0, 0], ["cloth.rotation.axis", "nonzero"]),
    ("output.particles", 1, ["output.particles", "true or false"]),
    ("output.path", ["a.usdc"], ["output.path", "string"]),
]


@pytest.mark.parametrize("key, value, words", BAD_VALUES, ids=[f"{k}={v!r}" for k, v, _ in BAD_VALUES])
def test_bad_value_is_named(key, value, words):
    """A value of the wrong type, shape or range is a one-line ConfigError naming the key."""
    message = parse_error(changed(lambda d: set_path(d, key, value)))
    for word in words:
        assert word in message


UNKNOWN_KEYS = [
    ("simulaton", {}, "top level"),
    ("simulation.dt", 0.001, "[simulation]"),
    ("world.up", "Z", "[world]"),
    ("cloth.stifness", 1.0, "[cloth]"),
    ("cloth.structural.stifness", 1.0, "[cloth.structural]"),
    ("cloth.grid.nz", 3, "[cloth.grid]"),
    ("output.file", "a.usdc", "[output]"),
]


@pytest.mark.parametrize("key, value, table", UNKNOWN_KEYS, ids=[k for k, *_ in UNKNOWN_KEYS])
def test_unknown_key_is_named_with_its_table(key, value, table):
    """A misspelt key is an error naming the key and its table, never silently ignored."""
    message = parse_error(changed(lambda d: set_path(d, key, value)))
    assert repr(key.split(".")[-1]) in message and table in message and "allowed:" in message


def test_grid_needs_nx_ny_and_spacing():
    """A grid without spacing (or nx, ny) is an error listing what is missing."""
    message = parse_error(changed(lambda d: d["cloth"]["grid"].pop("spacing")))
    assert "spacing" in message and "missing" in message
    message = parse_error(changed(lambda d: d["cloth"].update(grid={"spacing": 0.1})))
    assert "missing: nx, ny" in message


@pytest.mark.parametrize("which", ["both", "neither"])
def test_cloth_needs_exactly_one_of_grid_or_mesh(which):
    """A cloth with both grid and mesh, or with neither, is rejected."""
    if which == "both":
        data = changed(lambda d: d["cloth"].update(mesh="cloth.obj"))
    else:
        data = changed(lambda d: d["cloth"].pop("grid"))
    assert "exactly one of grid" in parse_error(data)


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda c: c.update(density=0.3), ["cloth.density", "mesh cloth only"]),
        (lambda c: c.update(particle_mass=0.01), ["exactly one of mass", "particle_mass"]),
        (lambda c: c.pop("mass"), ["exactly one of mass", "particle_mass"]),
    ],
    ids=["grid-with-density", "grid-with-mass-and-particle-mass", "grid-without-mass"],
)
def test_grid_mass_options(edit, words):
    """A grid takes exactly one of mass or particle_mass, and no mesh-only key."""
    message = parse_error(changed(lambda d: edit(d["cloth"])))
    for word in words:
        assert word in message


@pytest.mark.parametrize(
    "extra, words",
    [
        ({"particle_mass": 0.01}, ["cloth.particle_mass", "grid cloth only"]),
        ({"shear": {"ke": 1.0}}, ["cloth.shear", "grid cloth only"]),
        ({"pin": ["top-left"]}, ["cloth.pin", "vertex indices", "'top-left'"]),
        ({"density": 0.2}, ["exactly one of mass", "density"]),
    ],
    ids=["particle-mass", "shear", "named-pin", "mass-and-density"],
)
def test_mesh_cloth_options(extra, words):
    """A mesh cloth takes mass or density, vertex-index pins and no grid-only key."""
    data = {"cloth": {"mesh": "cloth.obj", "mass": 0.1, **extra}}
    message = parse_error(data)
    for word in words:
        assert word in message


@pytest.mark.parametrize(
    "collider, words",
    [
        ({"type": "box"}, ["collider.type", "ground, plane, sphere", "'box'"]),
        ({"radius": 1.0}, ["collider.type", "missing"]),
        ({"type": "sphere", "center": [0, 0, 1]}, ["sphere collider", "radius"]),
        ({"type": "sphere", "radius": 0.5}, ["sphere collider", "center"]),
        ({"type": "sphere", "center": [0, 0, 1], "radius": -0.5}, ["collider.radius", "> 0"]),
        ({"type": "sphere", "center": [0, 0, 1], "radius": 0.5, "normal": [0, 0, 1]}, ["collider.normal", "sphere"]),
        ({"type": "ground", "center": [0, 0, 1]}, ["collider.center", "ground"]),
        ({"type": "plane", "radius": 1.0}, ["collider.radius", "plane"]),
        ({"type": "ground", "friction": -0.1}, ["collider.friction", ">= 0"]),
    ],
    ids=["unknown-type", "no-type", "sphere-no-radius", "sphere-no-center", "sphere-negative-radius",
         "sphere-with-normal", "ground-with-center", "plane-with-radius", "negative-friction"],
)
def test_collider_type_and_keys(collider, words):
    """A collider has a known type, the keys that type needs, and no key of another type."""
    message = parse_error(changed(lambda d: d.update(collider=[collider])))
    for word in words:
        assert word in message


def test_several_cloths_are_named_by_index():
    """With an array of [[cloth]] tables the message says which one is wrong."""
    data = {"cloth": [minimal()["cloth"], {**minimal()["cloth"], "mass": -1.0}]}
    assert "cloth[1].mass" in parse_error(data)


def test_scene_without_cloth_is_rejected():
    """A scene must hold a cloth: nothing would be simulated otherwise."""
    assert "no [cloth]" in parse_error({"simulation": {"fps": 60}})


# -- building --------------------------------------------------------------------------------------------


def test_scene_builds_the_model_it_describes():
    """Grid size, spring families, pins, gravity and colliders of the scene appear in the finalized model."""
    data = {
        "world": {"up_axis": "Y", "drag": 0.1},
        "cloth": {
            "grid": {"nx": 3, "ny": 4, "spacing": 0.1},
            "particle_mass": 0.01,
            "pin": ["top-left", 1],
            "structural": {"ke": 50.0, "kd": 0.5},
            "shear": False,
            "bend": False,
        },
        "collider": [
            {"type": "ground", "height": 0.5, "friction": 0.3},
            {"type": "sphere", "center": [0.0, 1.0, 0.0], "radius": 0.25, "name": "ball"},
        ],
    }
    model = parse_scene(data, path="s.toml").builder().finalize("cpu")
    nx, ny = 3, 4
    assert model.particle_count == nx * ny
    assert model.spring_count == (nx - 1) * ny + nx * (ny - 1)  # structural only
    np.testing.assert_allclose(model.spring_stiffness.numpy(), 50.0)
    np.testing.assert_allclose(model.spring_damping.numpy(), 0.5)
    pinned = np.flatnonzero(model.kinematic_mask())
    np.testing.assert_array_equal(pinned, [1, (ny - 1) * nx])  # index 1 and the top-left corner (row ny-1, col 0)
    np.testing.assert_allclose(model.gravity, [0.0, -9.81, 0.0])  # default gravity is down the up axis
    assert model.drag == np.float32(0.1)  # the value the float32 kernels read
    ground, ball = model.shapes
    assert (ground.kind, ground.position, ground.friction) == ("plane", (0.0, 0.5, 0.0), 0.3)
    assert (ball.kind, ball.name, ball.position, ball.size[0]) == ("sphere", "ball", (0.0, 1.0, 0.0), 0.25)


def test_builder_errors_name_the_file_and_table():
    """A value only the builder can judge (an unknown pin name) is reported with the scene file and the table."""
    data = changed(lambda d: d["cloth"].update(pin=["top-middle"]))
    with pytest.raises(ws.ConfigError) as info:
        parse_scene(data, path="scene.toml").builder()
    assert str(info.value).startswith("scene.toml: in [cloth]: ") and "'top-middle'" in str(info.value)


def test_mesh_path_is_relative_to_the_scene_file(tmp_path, monkeypatch):
    """A relative mesh path is found next to the scene file, whatever the working directory."""
    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    (folder / "s.toml").write_text('[cloth]\nmesh = "tri.obj"\nmass = 0.4\npin = [0]\n')
    monkeypatch.chdir(tmp_path)
    model = load_scene(os.path.join("scenes", "s.toml")).builder().finalize("cpu")
    assert (model.particle_count, model.tri_count) == (4, 2)
    # Only a mass: the default material, one spring per edge and a hinge across the shared one.
    assert (model.spring_count, model.hinge_count) == (5, 1)
    np.testing.assert_allclose(model.particle_mass.numpy().sum(), 0.4)


# -- files ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, particles, kinds", [
    ("hanging_cloth.toml", 32 * 32, ["plane"]),
    ("cloth_on_sphere.toml", 48 * 48, ["sphere", "plane"]),
])
def test_example_scenes_parse_and_build(name, particles, kinds):
    """The shipped examples pass the schema and build the cloth and colliders their comments describe."""
    model = load_scene(EXAMPLES / name).builder().finalize("cpu")
    assert model.particle_count == particles
    assert [s.kind for s in model.shapes] == kinds


def test_load_scene_reports_missing_and_malformed_files(tmp_path):
    """A missing file and a TOML syntax error are one-line ConfigErrors naming the file."""
    with pytest.raises(ws.ConfigError, match="scene file not found: .*nowhere.toml"):
        load_scene(tmp_path / "nowhere.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[cloth]\ngrid = { nx = 4, ny = \n")
    with pytest.raises(ws.ConfigError) as info:
        load_scene(bad)
    assert "bad.toml: not valid TOML" in str(info.value) and "\n" not in str(info.value)


def test_stabilizers_and_guard_tables_reach_the_model_and_simulation():
    """[stabilizers] configures the model's stabilizers (biphasic law included) and [guard] the run-time
    checks; their values are range-checked like every other key."""
    data = changed(lambda d: d.update(
        version=2,
        stabilizers={"max_strain": 0.1, "strain_iterations": 8, "biphasic_strain": 0.2, "biphasic_ratio": 5.0},
        guard={"every": 4, "tear_strain": 3.0},
    ))
    scene = parse_scene(data)
    model = scene.builder().finalize("cpu")
    assert model.stabilizers == ws.Stabilizers(max_strain=0.1, strain_iterations=8, biphasic_strain=0.2,
                                               biphasic_ratio=5.0)
    assert model.spring_law.biphasic and scene.guard == ws.GuardLimits(every=4, tear_strain=3.0)
    assert "stabilizers.max_strain must be a number > 0" in parse_error(changed(
        lambda d: d.update(stabilizers={"max_strain": -0.1})))
    assert "unknown key 'often' in [guard]" in parse_error(changed(lambda d: d.update(guard={"often": 2})))


# -- format versions --------------------------------------------------------------------------------------


def test_a_file_without_version_is_format_1_and_reads_as_before():
    """No version: format 1, no deprecation, and the same scene as before versions existed."""
    scene = parse_scene(minimal(), path="s.toml")
    assert scene.version == 1 and scene.deprecations == [] and scene.tracks == {}
    assert load_scene(EXAMPLES / "hanging_cloth.toml").version == 1


def test_version_2_is_read():
    """version = 2 (this warpspring's format) reads the same scene as the same file without it."""
    assert SCENE_FORMAT_VERSION == 2
    v2 = parse_scene(changed(lambda d: d.update(version=2)), path="s.toml")
    v1 = parse_scene(minimal(), path="s.toml")
    assert v2.version == 2
    assert (v2.cloths, v2.world, v2.stabilizers, v2.guard) == (v1.cloths, v1.world, v1.stabilizers, v1.guard)


def test_a_newer_format_asks_for_a_newer_warpspring():
    """A file of a format above SCENE_FORMAT_VERSION is refused first, in one line naming its version, the
    versions this warpspring reads and the fix (even if its tables hold keys unknown here)."""
    message = parse_error(changed(lambda d: d.update(version=3, hologram={"on": True})))
    assert "version 3" in message and "newer warpspring" in message and "1 to 2" in message
    assert "upgrade" in message and "hologram" not in message


@pytest.mark.parametrize("version", ["2", 2.0, True, 0, -1], ids=["string", "float", "bool", "zero", "negative"])
def test_version_must_be_an_integer_of_at_least_1(version):
    message = parse_error(changed(lambda d: d.update(version=version)))
    assert "version must be an integer >= 1" in message and repr(version) in message


def test_version_inside_a_table_is_pointed_to_the_top():
    """TOML puts a key written after [simulation] into that table: the error says where version belongs."""
    message = parse_error(changed(lambda d: d.update(simulation={"version": 2})))
    assert "unknown key 'version' in [simulation]" in message and "top of the file" in message


# -- renamed keys -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("version", [None, 2], ids=["format-1", "format-2"])
def test_old_guard_max_strain_is_read_with_a_deprecation(version):
    """[guard] max_strain, renamed tear_strain in format 2, is still read in every format: a
    DeprecatedKeyWarning naming the file and both keys, the same message in Scene.deprecations, and its
    value in GuardLimits.tear_strain. A format-1 file is also told to declare version = 2."""
    data = changed(lambda d: d.update(guard={"max_strain": 3.0}))
    if version is not None:
        data["version"] = version
    with pytest.warns(DeprecatedKeyWarning, match=r"scene\.toml: \[guard\] max_strain .* tear_strain") as caught:
        scene = parse_scene(data, path="/a/scene.toml")
    assert len(caught) == 1 and caught[0].filename == __file__  # the warning points at the caller
    assert scene.guard.tear_strain == 3.0 and scene.guard == ws.GuardLimits(tear_strain=3.0)
    assert scene.deprecations == [str(caught[0].message)]
    assert ("add version = 2" in scene.deprecations[0]) == (version is None)
    assert data["guard"] == {"max_strain": 3.0}  # the caller's dict is left as it was


def test_load_scene_warns_about_deprecated_keys_too(tmp_path):
    path = tmp_path / "old.toml"
    path.write_text('[cloth]\ngrid = { nx = 3, ny = 3, spacing = 0.1 }\nmass = 0.1\n\n[guard]\nmax_strain = 4.0\n')
    with pytest.warns(DeprecatedKeyWarning, match=r"old\.toml: \[guard\] max_strain") as caught:
        scene = load_scene(path)
    assert caught[0].filename == __file__ and scene.guard.tear_strain == 4.0


def test_old_and_new_name_in_one_table_is_an_error():
    message = parse_error(changed(lambda d: d.update(version=2, guard={"max_strain": 3.0, "tear_strain": 4.0})))
    assert "[guard] has both max_strain and tear_strain" in message and "keep tear_strain only" in message


def test_a_new_name_needs_the_format_that_introduced_it():
    """tear_strain in a file without version: declare the format it uses (older readers do not know it)."""
    message = parse_error(changed(lambda d: d.update(guard={"tear_strain": 4.0})))
    assert "[guard] tear_strain needs scene format 2" in message and "add version = 2" in message


# -- tracks of live inputs --------------------------------------------------------------------------------


def tracked() -> dict:
    """The minimal scene in format 2 with gravity, drag and the strain limit animated."""
    return changed(lambda d: d.update(
        version=2,
        world={
            "gravity": {"times": [0.0, 1.0, 2.0], "values": [[0, 0, -9.81], [0, 0, -1.62], [0, 0, -9.81]],
                        "interpolation": "smooth", "extrapolation": "cycle"},
            "drag": {"times": [0.0, 0.5], "values": [0.0, 0.02], "interpolation": "step"},
        },
        stabilizers={"max_strain": {"times": [0.0, 1.0], "values": [0.2, 0.05]}, "max_speed": 5.0},
    ))


def test_tracks_reach_the_model():
    """A track table on gravity, drag or a stabiliser threshold becomes the model's track of that input,
    keys and options as written; a threshold's stabiliser is on, starting at the track's first value."""
    scene = parse_scene(tracked(), path="s.toml")
    assert sorted(scene.tracks) == ["drag", "gravity", "max_strain"]
    model = scene.builder().finalize("cpu")
    gravity, drag, strain = model.track("gravity"), model.track("drag"), model.track("max_strain")
    np.testing.assert_array_equal(gravity.times, [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(gravity.values, [[0, 0, -9.81], [0, 0, -1.62], [0, 0, -9.81]])
    assert (gravity.interpolation, gravity.extrapolation) == ("smooth", "cycle")
    np.testing.assert_array_equal(drag.values, [[0.0], [0.02]])
    assert (drag.interpolation, drag.extrapolation) == ("step", "hold")
    np.testing.assert_array_equal(strain.values, [[0.2], [0.05]])
    assert model.stabilizers == ws.Stabilizers(max_strain=0.2, max_speed=5.0)
    assert model.track("max_speed") is None and model.gravity_enabled and model.drag_enabled


def test_a_track_needs_format_2():
    data = tracked()
    del data["version"]
    message = parse_error(data)
    assert "world.gravity as a track table needs scene format 2" in message and "add version = 2" in message


def _track_edit(key, **changes):
    """tracked() with the track table at ``key`` updated by ``changes`` (a value of None removes that key)."""
    def edit(d):
        table = d[key.split(".")[0]][key.split(".")[1]]
        for k, v in changes.items():
            table.pop(k) if v is None else table.update({k: v})
    data = tracked()
    edit(data)
    return data


BAD_TRACKS = [
    # scene, words the message must hold
    (_track_edit("world.gravity", times=[0.0, 2.0, 1.0]), ["world.gravity", "increase strictly"]),
    (_track_edit("world.gravity", values=[[0, 0, -9.81], [0, -1.62], [0, 0, 0]]),
     ["world.gravity.values[1]", "3 finite numbers"]),
    (_track_edit("world.gravity", values=[[0, 0, -9.81]]), ["world.gravity", "3 times but 1 values"]),
    (_track_edit("world.gravity", interpolation="cubic"), ["world.gravity.interpolation", "step, linear, smooth",
                                                          "'cubic'"]),
    (_track_edit("world.gravity", extrapolation="mirror"), ["world.gravity.extrapolation", "hold, cycle"]),
    (_track_edit("world.drag", values=[0.0, -0.1]), ["world.drag.values[1]", ">= 0", "-0.1"]),
    (_track_edit("world.drag", times=[]), ["world.drag.times", "empty"]),
    (_track_edit("world.drag", times=[0.0, "1 s"]), ["world.drag.times[1]", "number"]),
    (_track_edit("world.drag", values=None), ["world.drag", "missing: values"]),
    (_track_edit("world.drag", value=[0.0, 0.1]), ["unknown key 'value' in [world.drag]", "allowed: times, values"]),
    (_track_edit("world.drag", times=[0.0], values=[0.1], extrapolation="cycle"), ["world.drag", "two keys"]),
    (_track_edit("stabilizers.max_strain", values=[0.2, 0.0]), ["stabilizers.max_strain.values[1]", "> 0"]),
    (changed(lambda d: d.update(version=2, stabilizers={"biphasic_ratio": {"times": [0], "values": [5.0]}})),
     ["stabilizers.biphasic_ratio", "biphasic springs are off", "biphasic_strain"]),
]


@pytest.mark.parametrize("data, words", BAD_TRACKS, ids=[
    "decreasing-times", "short-gravity-value", "fewer-values-than-times", "unknown-interpolation",
    "unknown-extrapolation", "negative-drag-key", "no-times", "text-time", "no-values", "misspelt-key",
    "cycle-of-one-key", "zero-threshold-key", "biphasic-ratio-without-biphasic-springs",
])
def test_bad_track_tables_are_named(data, words):
    """Each fault of a track table is a one-line error naming the file, the table and the key."""
    message = parse_error(data)
    for word in words:
        assert word in message


# -- pin groups -------------------------------------------------------------------------------------------

RAISE = {"times": [0.0, 1.0], "values": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]]}


def test_grid_pin_group_moves_the_named_particles():
    """[[cloth.pin_group]] with pin = ["top"] and a translation track: the top row forms the model's first pin
    group, driven by that track, and is kinematic (beside the cloth's own fixed pin)."""
    data = changed(lambda d: d.update(version=2))
    data["cloth"].update(pin=["bottom-left"], pin_group=[{"pin": ["top"], "name": "bar", "translation": RAISE}])
    model = parse_scene(data, path="s.toml").builder().finalize("cpu")
    nx, ny = 3, 4
    top = np.arange((ny - 1) * nx, ny * nx)
    group = model.pin_groups.groups[0]
    np.testing.assert_array_equal(group.particles, top)
    assert group.name == "bar" and group.rotation is None and group.driver == "tracks"
    np.testing.assert_array_equal(group.translation.values, RAISE["values"])
    np.testing.assert_array_equal(np.flatnonzero(model.kinematic_mask()), np.concatenate([[0], top]))


def test_mesh_pin_group_by_vertex_indices(tmp_path):
    """A mesh cloth's pin group names vertices; a rotation track turns degrees about an axis into rotation
    vectors [rad] about the given pivot. Several groups are numbered in errors."""
    (tmp_path / "quad.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    (tmp_path / "s.toml").write_text(
        'version = 2\n[cloth]\nmesh = "quad.obj"\nmass = 0.4\n\n[[cloth.pin_group]]\npin = [2, 3]\n'
        "pivot = [0.5, 1.0, 0.0]\n"
        "rotation = { times = [0.0, 1.0], axis = [1.0, 0.0, 0.0], degrees = [0.0, 90.0], interpolation = 'smooth' }\n"
    )
    model = load_scene(tmp_path / "s.toml").builder().finalize("cpu")
    group = model.pin_groups.groups[0]
    np.testing.assert_array_equal(group.particles, [2, 3])
    np.testing.assert_allclose(group.rotation.values, [[0.0, 0.0, 0.0], [np.pi / 2, 0.0, 0.0]])
    assert group.rotation.interpolation == "smooth" and group.translation is None
    np.testing.assert_array_equal(group.pivot, [0.5, 1.0, 0.0])
    np.testing.assert_array_equal(np.flatnonzero(model.kinematic_mask()), [2, 3])

    extra = "\n[[cloth.pin_group]]\npin = [7]\ntranslation = { times = [0.0], values = [[0, 0, 1]] }\n"
    (tmp_path / "s.toml").write_text((tmp_path / "s.toml").read_text() + extra)
    with pytest.raises(ws.ConfigError) as info:
        load_scene(tmp_path / "s.toml").builder()
    assert str(info.value).startswith("s.toml: in [cloth]: pin_group[1]: ") and "vertex index 7" in str(info.value)


def pin_group_error(group: dict, *, version=2, grid=True) -> str:
    data = changed(lambda d: d.update(version=version)) if grid else {
        "version": version, "cloth": {"mesh": "cloth.obj", "mass": 0.1}}
    data["cloth"]["pin_group"] = [group, {"pin": [0], "translation": RAISE}] if isinstance(group, dict) else group
    return parse_error(data)


def test_a_pin_group_without_tracks_suggests_pin():
    """A group that no track moves is an error pointing to [cloth] pin for particles that stay put."""
    message = pin_group_error({"pin": ["top"], "name": "still"})
    assert "[cloth.pin_group[0]] moves nothing" in message and "translation" in message and "rotation" in message
    assert "pin = [...]" in message


@pytest.mark.parametrize("group, words, options", [
    ({"translation": RAISE}, ["cloth.pin_group[0].pin is missing", 'pin = ["top"]'], {}),
    ({"pin": [], "translation": RAISE}, ["cloth.pin_group[0].pin is empty"], {}),
    ({"pin": [1.5], "translation": RAISE}, ["cloth.pin_group[0].pin", "1.5"], {}),
    ({"pin": ["top"], "translation": RAISE}, ["cloth.pin_group[0].pin", "vertex indices", "'top'"], {"grid": False}),
    ({"pin": [0], "translation": {"times": [0.0], "values": [1.0]}}, ["cloth.pin_group[0].translation.values[0]",
                                                                       "3 finite numbers"], {}),
    ({"pin": [0], "rotation": {"times": [0.0, 1.0], "axis": [0, 0, 0], "degrees": [0, 90]}},
     ["cloth.pin_group[0].rotation", "axis", "not all zero"], {}),
    ({"pin": [0], "rotation": {"times": [0.0, 1.0], "degrees": [0, 90]}},
     ["cloth.pin_group[0].rotation", "missing: axis"], {}),
    ({"pin": [0], "pivot": [0, 0], "translation": RAISE}, ["cloth.pin_group[0].pivot", "3 finite numbers"], {}),
    ({"pin": [0], "translation": RAISE}, ["cloth.pin_group needs scene format 2", "add version = 2"],
     {"version": 1}),
    ("top", ["cloth.pin_group must be a table or an array of tables"], {}),
], ids=["no-pin", "empty-pin", "float-pin", "named-pin-on-mesh", "scalar-translation", "zero-axis", "no-axis",
        "short-pivot", "format-1", "not-a-table"])
def test_bad_pin_groups_are_named(group, words, options):
    message = pin_group_error(group, **options)
    for word in words:
        assert word in message
