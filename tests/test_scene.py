"""Scene files: the schema parse_scene enforces (keys, types, ranges, exclusive choices) and how a scene maps
onto the model it builds. Nothing here simulates, so no kernel is compiled."""

import copy
import os
import pathlib

import numpy as np
import pytest

import warpspring as ws
from warpspring.io.scene import load_scene, parse_scene

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
    """A scene with only a cloth gets 60 fps, 120 frames, 16 substeps, symplectic Euler, float32 and no output."""
    scene = parse_scene(minimal(), path="s.toml")
    assert (scene.fps, scene.frames, scene.substeps) == (60.0, 120, 16)
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
    assert model.spring_count == 5 + 1  # five edges, one bend spring across the shared edge
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
        stabilizers={"max_strain": 0.1, "strain_iterations": 8, "biphasic_strain": 0.2, "biphasic_ratio": 5.0},
        guard={"every": 4, "max_strain": 3.0},
    ))
    scene = parse_scene(data)
    model = scene.builder().finalize("cpu")
    assert model.stabilizers == ws.Stabilizers(max_strain=0.1, strain_iterations=8, biphasic_strain=0.2,
                                               biphasic_ratio=5.0)
    assert model.spring_law.biphasic and scene.guard == ws.GuardLimits(every=4, max_strain=3.0)
    assert "stabilizers.max_strain must be a number > 0" in parse_error(changed(
        lambda d: d.update(stabilizers={"max_strain": -0.1})))
    assert "unknown key 'often' in [guard]" in parse_error(changed(lambda d: d.update(guard={"often": 2})))
