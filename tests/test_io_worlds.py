"""I/O of models of several worlds: the USD writer (every world as its own translated prim, or one chosen
world, stopped worlds), the ``[worlds]`` table of scene files, and runs of such scenes through
``run_scene`` and the CLI (per-world results equal single-world runs bit for bit; guard stop = "world").

The runs use the CLI tests' feature set (springs, gravity, drag, a ground plane, float32) to share kernels.
"""

import copy

import numpy as np
import pytest
from pxr import Usd, UsdGeom

import warpspring as ws
from warpspring.app.cli import EXIT_CONFIG, EXIT_SIMULATION, main
from warpspring.io.render import _sampled_frames
from warpspring.app.runner import run_scene
from warpspring.io.scene import parse_scene
from warpspring.io.usd import UsdWriter, default_world_spacing, world_offsets

WORLDS = 3
SOFT = ws.SpringMaterial(ke=10.0, kd=0.01)


def grid_model(worlds: int = WORLDS, up_axis: str = "Z", *, particles: bool = False) -> ws.Model:
    """A 4 × 5 cloth over a ground plane, ``worlds`` copies."""
    builder = ws.ModelBuilder(up_axis=up_axis)
    builder.add_cloth_grid(nx=4, ny=5, spacing=0.1, mass=0.2, origin=(0.2, -0.1, 1.0), structural=SOFT,
                           shear=SOFT, bend=SOFT)
    builder.add_ground_plane()
    return builder.finalize("cpu", worlds=worlds)


def world_poses(model: ws.Model, frame: int) -> np.ndarray:
    """Distinct poses of every world at ``frame``: the rest grid shifted by (w, frame, -w) cm, shape [W, n, 3]."""
    q0 = model.particle_q.numpy().reshape(model.world_count, model.particle_count, 3).astype(np.float64)
    w = np.arange(model.world_count)[:, None, None]
    return q0 + 0.01 * np.concatenate([w, np.full_like(w, frame), -w], axis=2)


def state_of(model: ws.Model, poses: np.ndarray) -> ws.State:
    state = model.state()
    state.particle_q.assign(poses.reshape(-1, 3).astype(np.float32))
    return state


def mesh_points(stage, path: str) -> tuple[list[float], list[np.ndarray]]:
    """Time codes and point samples of the mesh at ``path``."""
    attr = stage.GetPrimAtPath(path).GetAttribute("points")
    times = attr.GetTimeSamples()
    return times, [np.array(attr.Get(t)) for t in times]


def world_transform(stage, path: str) -> np.ndarray:
    """The local-to-world translation of the prim at ``path`` [m]."""
    xform = UsdGeom.Xformable(stage.GetPrimAtPath(path))
    return np.array(xform.ComputeLocalToWorldTransform(Usd.TimeCode.Default()).ExtractTranslation())


# -- USD writer ------------------------------------------------------------------------------------------


def test_every_world_is_a_prim_holding_its_state_translated_by_its_grid_offset(tmp_path):
    """W worlds give /World/world_000w prims; each cloth's points are exactly that world's state (float32),
    and its world-space points are the state plus the world's offset on the grid (spacing 2 m, 2 columns)."""
    model = grid_model()
    path = tmp_path / "worlds.usdc"
    poses = [world_poses(model, k) for k in range(3)]
    with UsdWriter(path, model, fps=30.0, particles=True, world_spacing=2.0) as writer:
        assert writer.worlds == [0, 1, 2]
        for q in poses:
            writer.write_frame(state_of(model, q))

    stage = Usd.Stage.Open(str(path))
    names = [p.GetName() for p in stage.GetPrimAtPath("/World").GetChildren()]
    assert names == ["world_0000", "world_0001", "world_0002"]
    expected_offsets = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])  # ceil(√3) = 2 columns
    np.testing.assert_array_equal(world_offsets(model, spacing=2.0), expected_offsets)
    for w in range(WORLDS):
        root = f"/World/world_{w:04d}"
        np.testing.assert_array_equal(world_transform(stage, root), expected_offsets[w])
        assert stage.GetPrimAtPath(root).GetCustomDataByKey("warpspring:world") == w
        times, points = mesh_points(stage, f"{root}/cloth")
        assert times == [0.0, 1.0, 2.0]
        for k in range(3):
            np.testing.assert_array_equal(points[k], poses[k][w].astype(np.float32))
        # world space: the cloth's points through its transform are the state plus the offset
        m = UsdGeom.Xformable(stage.GetPrimAtPath(f"{root}/cloth")).ComputeLocalToWorldTransform(Usd.TimeCode(2))
        placed = np.array([m.Transform(p) for p in stage.GetPrimAtPath(f"{root}/cloth").GetAttribute("points").Get(2)])
        np.testing.assert_allclose(placed, poses[2][w] + expected_offsets[w], atol=1e-6)
        _, particles = mesh_points(stage, f"{root}/particles")
        np.testing.assert_array_equal(particles[2], poses[2][w].astype(np.float32))
        # each world has its colliders, in the world's frame
        assert stage.GetPrimAtPath(f"{root}/colliders/ground").IsA(UsdGeom.Mesh)
        np.testing.assert_allclose(world_transform(stage, f"{root}/colliders/ground"), expected_offsets[w], atol=1e-12)
    assert stage.GetEndTimeCode() == 2.0


def test_one_chosen_world_is_written_as_a_single_world_scene(tmp_path):
    """world=k writes /World/cloth (no world prims, no offset) holding exactly world k's state."""
    model = grid_model()
    path = tmp_path / "one.usda"
    poses = [world_poses(model, k) for k in range(2)]
    with UsdWriter(path, model, fps=30.0, world=2) as writer:
        for q in poses:
            writer.write_frame(state_of(model, q))
    stage = Usd.Stage.Open(str(path))
    assert [p.GetName() for p in stage.GetPrimAtPath("/World").GetChildren()] == ["cloth", "colliders"]
    assert stage.GetPrimAtPath("/World").GetCustomDataByKey("warpspring:world") == 2
    times, points = mesh_points(stage, "/World/cloth")
    assert times == [0.0, 1.0]
    for k in range(2):
        np.testing.assert_array_equal(points[k], poses[k][2].astype(np.float32))
    np.testing.assert_array_equal(world_transform(stage, "/World/cloth"), 0.0)


def test_normals_of_every_world_match_those_of_a_single_world_model(tmp_path):
    """The per-world normals equal the normals the writer computes for a one-world model in that pose."""
    model, single = grid_model(), grid_model(worlds=1)
    poses = world_poses(model, 1)
    poses[1, :, 2] += 0.05 * np.sin(np.arange(model.particle_count))  # a crumpled world
    with UsdWriter(tmp_path / "all.usdc", model, fps=30.0) as writer:
        writer.write_frame(state_of(model, poses))
    all_worlds = Usd.Stage.Open(str(tmp_path / "all.usdc"))
    for w in range(WORLDS):
        with UsdWriter(tmp_path / f"w{w}.usdc", single, fps=30.0) as writer:
            writer.write_frame(state_of(single, poses[w : w + 1]))
        alone = Usd.Stage.Open(str(tmp_path / f"w{w}.usdc"))
        n_all = np.array(all_worlds.GetPrimAtPath(f"/World/world_{w:04d}/cloth").GetAttribute("normals").Get(0))
        n_one = np.array(alone.GetPrimAtPath("/World/cloth").GetAttribute("normals").Get(0))
        np.testing.assert_array_equal(n_all, n_one)


def test_world_grid_layout_and_default_spacing():
    """Columns run along x, rows along the second horizontal axis (y for Z-up, z for Y-up); the default
    spacing is twice the cloth's horizontal extent, at least 1 m."""
    model = grid_model(worlds=5, up_axis="Y")
    offsets = world_offsets(model, spacing=1.5, columns=2)
    np.testing.assert_array_equal(offsets, [[0, 0, 0], [1.5, 0, 0], [0, 0, 1.5], [1.5, 0, 1.5], [0, 0, 3.0]])
    np.testing.assert_array_equal(world_offsets(model, spacing=0.0), 0.0)  # overlaid
    assert default_world_spacing(model) == 1.0  # a 0.3 m × 0.4 m cloth: the 1 m minimum
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.6, mass=0.1)  # 1.2 m wide
    assert default_world_spacing(builder.finalize("cpu", worlds=2)) == pytest.approx(2.4)


@pytest.mark.parametrize("options, words", [
    (dict(world=3), ["cannot export world 3", "3 world(s), 0..2"]),
    (dict(world=-1), ["world must be an integer >= 0"]),
    (dict(world_spacing=-1.0), ["world spacing"]),
    (dict(world_columns=0), ["world columns must be an integer >= 1"]),
])
def test_bad_world_options_are_refused_before_the_file_is_made(tmp_path, options, words):
    path = tmp_path / "never.usdc"
    with pytest.raises(ws.ConfigError) as info:
        UsdWriter(path, grid_model(), fps=30.0, **options)
    for word in words:
        assert word in str(info.value)
    assert not path.exists()


def test_a_stopped_world_keeps_its_samples_and_gets_no_more(tmp_path):
    """stop_worlds: the stopped world's samples end at its last good frame, even when its state turns
    non-finite afterwards; the others go on. A non-finite live world is refused, naming the world."""
    model = grid_model()
    path = tmp_path / "stopped.usdc"
    with UsdWriter(path, model, fps=30.0) as writer:
        for k in range(2):
            writer.write_frame(state_of(model, world_poses(model, k)))
        writer.stop_worlds([1])
        for k in range(2, 5):
            poses = world_poses(model, k)
            poses[1] = np.nan  # what a failed world may hold
            writer.write_frame(state_of(model, poses))
        assert writer.stopped_worlds == {1: 2}
        poses = world_poses(model, 5)
        poses[2, 3] = np.inf
        with pytest.raises(ws.SimulationError, match=r"^world 2: particle 3 has a non-finite position"):
            writer.write_frame(state_of(model, poses))
    stage = Usd.Stage.Open(str(path))
    for w, count in [(0, 5), (1, 2), (2, 5)]:
        times, points = mesh_points(stage, f"/World/world_{w:04d}/cloth")
        assert times == [float(k) for k in range(count)]
        assert all(np.isfinite(p).all() for p in points)
    assert stage.GetEndTimeCode() == 4.0
    assert _sampled_frames(stage) == [0, 1, 2, 3, 4]  # the renderer sees every frame, not world 0's only


# -- scene files -----------------------------------------------------------------------------------------


def worlds_scene(**worlds) -> dict:
    """A format-2 scene of a 3 × 4 grid cloth with ``[worlds]`` = ``worlds`` (count 3 unless given)."""
    return {
        "version": 2,
        "cloth": {"grid": {"nx": 3, "ny": 4, "spacing": 0.1}, "mass": 0.12},
        "worlds": {"count": 3, **worlds},
    }


def test_worlds_table_reaches_the_model():
    """Per-world gravity (constants and a track), drag, stabiliser thresholds and the stiffness, damping
    and mass scales give each world of the finalized model its own values."""
    data = worlds_scene(
        gravity=[[0, 0, -9.81], [0, 0, -1.62], {"times": [0.0, 1.0], "values": [[0, 0, -3.0], [0, 0, 0]]}],
        drag=[0.0, 0.1, 0.2],
        max_speed=[1.0, 2.0, 3.0],
        stiffness_scale=[1.0, 2.0, 0.5],
        damping_scale=[1.0, 0.0, 3.0],
        mass_scale=[1.0, 10.0, 0.1],
    )
    data["stabilizers"] = {"max_speed": 5.0}
    scene = parse_scene(data, path="w.toml")
    assert scene.world_count == 3
    assert isinstance(scene.world_inputs["gravity"][2], ws.Track)
    assert scene.world_scales["spring_stiffness"] == [1.0, 2.0, 0.5]

    model = scene.finalize("cpu")
    single = parse_scene(worlds_scene(count=1), path="one.toml").finalize("cpu")
    assert model.world_count == 3 and single.world_count == 1
    np.testing.assert_allclose(model.world_values("gravity"), [[0, 0, -9.81], [0, 0, -1.62], [0, 0, -3.0]], rtol=1e-6)
    assert model.track("gravity", world=2) is not None and model.track("gravity", world=0) is None
    np.testing.assert_allclose(model.world_values("drag")[:, 0], [0.0, 0.1, 0.2], rtol=1e-6)
    np.testing.assert_allclose(model.world_values("max_speed")[:, 0], [1.0, 2.0, 3.0])
    for name, scale in [("spring_stiffness", [1.0, 2.0, 0.5]), ("spring_damping", [1.0, 0.0, 3.0]),
                        ("particle_mass", [1.0, 10.0, 0.1])]:
        base = single.world_values(name)[0]
        np.testing.assert_allclose(model.world_values(name), np.outer(scale, base), rtol=1e-6)


def test_output_world_options_are_read():
    data = worlds_scene()
    data["output"] = {"world": 2, "world_spacing": 3.5, "world_columns": 1}
    scene = parse_scene(data, path="w.toml")
    assert (scene.export_world, scene.world_spacing, scene.world_columns) == (2, 3.5, 1)
    default = parse_scene(worlds_scene(), path="w.toml")
    assert (default.export_world, default.world_spacing, default.world_columns) == (None, None, None)


def _edit(data: dict, **changes) -> dict:
    data = copy.deepcopy(data)
    for dotted, value in changes.items():
        table, key = dotted.split("__")
        if value is None:
            data[table].pop(key)
        else:
            data.setdefault(table, {})[key] = value
    return data


BAD_WORLDS = [
    ({"worlds__count": None}, ["[worlds] needs count = N"]),
    ({"worlds__count": 0}, ["worlds.count must be an integer >= 1"]),
    ({"worlds__drag": [0.1, 0.2]}, ["worlds.drag has 2 entries but count = 3", "one entry per world"]),
    ({"worlds__gravity": [0, 0, -9.81]}, ["worlds.gravity must list one [x, y, z] per world", "[world]"]),
    ({"worlds__gravity": [[0, 0, -9.81], [0, 0], [0, 0, 1]]}, ["worlds.gravity[1] must be a list of 3 finite"]),
    ({"worlds__drag": 0.1}, ["worlds.drag must be a list with one entry per world"]),
    ({"worlds__drag": [0.1, -0.2, 0.0]}, ["worlds.drag[1] must be a number >= 0"]),
    ({"worlds__drag": [0.1, {"times": [0.0], "values": []}, 0.0]}, ["track worlds.drag[1] has 1 times but 0 values"]),
    ({"worlds__mass_scale": [1.0, 0.0, 1.0]}, ["worlds.mass_scale[1] must be a number > 0"]),
    ({"worlds__stiffness_scale": [1.0, {"times": [0.0], "values": [1.0]}, 1.0]},
     ["worlds.stiffness_scale[1] must be a number >= 0"]),
    ({"worlds__max_strain": [0.1, 0.2, 0.3]},
     ["worlds.max_strain sets max_strain per world", "[stabilizers] max_strain"]),
    ({"worlds__biphasic_ratio": [2.0, 3.0, 4.0]}, ["[stabilizers] biphasic_strain"]),
    ({"worlds__speed": [1, 2, 3]}, ["unknown key 'speed' in [worlds]"]),
    ({"output__world": 3}, ["output.world = 3 does not exist", "3 world(s), 0..2"]),
    ({"guard__stop": "frame"}, ["guard.stop must be one of 'run', 'world'"]),
]


@pytest.mark.parametrize("changes, words", BAD_WORLDS, ids=[f"{next(iter(c))}-{i}" for i, (c, _) in
                                                          enumerate(BAD_WORLDS)])
def test_bad_worlds_tables_are_named(changes, words):
    with pytest.raises(ws.ConfigError) as info:
        parse_scene(_edit(worlds_scene(), **changes), path="/x/scene.toml")
    message = str(info.value)
    assert message.startswith("scene.toml: ") and "\n" not in message
    for word in words:
        assert word in message, message


def test_worlds_and_their_output_options_need_format_2():
    data = worlds_scene()
    del data["version"]
    with pytest.raises(ws.ConfigError, match=r"\[worlds\] needs scene format 2: add version = 2"):
        parse_scene(data, path="s.toml")
    one = {"cloth": data["cloth"], "output": {"world_spacing": 2.0}}
    with pytest.raises(ws.ConfigError, match=r"output.world_spacing needs scene format 2"):
        parse_scene(one, path="s.toml")


# -- runs --------------------------------------------------------------------------------------------------

SCENE = """\
version = 2

[simulation]
fps = 60
frames = {frames}
substeps = 4

[world]
drag = 0.002
{world}
[cloth]
grid = {{ nx = 5, ny = 5, spacing = 0.1 }}
origin = [0.0, 0.0, 1.0]
mass = 0.25
pin = ["top-left", "top-right"]
structural = {{ ke = 40.0, kd = 0.01 }}
shear = {{ ke = 10.0, kd = 0.01 }}
bend = {{ ke = 1.0, kd = 0.001 }}

[[collider]]
type = "ground"
{extra}"""

GRAVITIES = [[0.0, 0.0, -9.81], [0.0, 0.0, -1.62], [1.0, 0.5, -3.71]]


def write_scene(tmp_path, name: str, *, frames: int = 6, world: str = "", extra: str = ""):
    path = tmp_path / name
    path.write_text(SCENE.format(frames=frames, world=world, extra=extra))
    return path


def test_each_world_equals_the_single_world_run_of_its_gravity(tmp_path):
    """Three worlds of different gravity, written as three prims: world k's samples equal, bit for bit (CPU,
    symplectic Euler), those of a one-world scene with world k's gravity."""
    from warpspring.io.scene import load_scene

    worlds = f"\n[worlds]\ncount = 3\ngravity = {GRAVITIES}\n"
    summary = run_scene(load_scene(write_scene(tmp_path, "three.toml", extra=worlds)),
                        output=str(tmp_path / "three.usdc"), device="cpu", progress=False)
    assert summary.worlds == 3 and summary.world_failures == []
    assert "; every world written" in summary.line()
    three = Usd.Stage.Open(str(tmp_path / "three.usdc"))
    for k, g in enumerate(GRAVITIES):
        scene = load_scene(write_scene(tmp_path, f"g{k}.toml", world=f"gravity = {g}\n"))
        run_scene(scene, output=str(tmp_path / f"g{k}.usdc"), device="cpu", progress=False)
        times, alone = mesh_points(Usd.Stage.Open(str(tmp_path / f"g{k}.usdc")), "/World/cloth")
        times_k, in_three = mesh_points(three, f"/World/world_{k:04d}/cloth")
        assert times == times_k == [float(f) for f in range(7)]
        for a, b in zip(alone, in_three):
            np.testing.assert_array_equal(a, b)
    _, last = mesh_points(three, "/World/world_0000/cloth")
    _, moon = mesh_points(three, "/World/world_0001/cloth")
    assert not np.array_equal(last[-1], moon[-1])  # the gravities did differ


# World 1's springs 10⁴ times stiffer: ω·dt ≈ 26 ≫ 2, so symplectic Euler diverges there within a frame or two.
STOP_WORLD = "\n[guard]\nstop = \"world\"\n\n[worlds]\ncount = 3\nstiffness_scale = [1.0, 1.0e4, 1.0]\n"


def test_guard_stop_world_ends_only_the_failed_worlds_samples(tmp_path):
    """With [guard] stop = "world" the diverging world 1 is held: the run completes, the summary and a
    warning name world 1 and its frame, world 1's samples end before that frame, and the other worlds
    have every frame and equal the run without the diverging world."""
    from warpspring.io.scene import load_scene

    warnings = []
    scene = load_scene(write_scene(tmp_path, "stop.toml", extra=STOP_WORLD))
    summary = run_scene(scene, output=str(tmp_path / "stop.usdc"), device="cpu", progress=False, warn=warnings.append)
    assert len(summary.world_failures) == 1 and summary.world_failures[0].startswith("world 1 stopped at frame ")
    frame = int(summary.world_failures[0].split("frame ")[1].split(",")[0])
    assert 1 <= frame <= 6
    assert summary.world_failures[0] in warnings
    assert "; every world written; 1 world stopped by the guard" in summary.line()

    stage = Usd.Stage.Open(str(tmp_path / "stop.usdc"))
    times, points = mesh_points(stage, "/World/world_0001/cloth")
    assert times == [float(f) for f in range(frame)] and all(np.isfinite(p).all() for p in points)
    calm = run_scene(load_scene(write_scene(tmp_path, "calm.toml", extra=STOP_WORLD.replace("1.0e4", "1.0"))),
                     output=str(tmp_path / "calm.usdc"), device="cpu", progress=False)
    assert calm.world_failures == []
    reference = Usd.Stage.Open(str(tmp_path / "calm.usdc"))
    for w in (0, 2):
        times, points = mesh_points(stage, f"/World/world_{w:04d}/cloth")
        _, expected = mesh_points(reference, f"/World/world_{w:04d}/cloth")
        assert times == [float(f) for f in range(7)]
        for a, b in zip(points, expected):
            np.testing.assert_array_equal(a, b)


def run_cli(capsys, *args):
    status = main(["run", *map(str, args), "--device", "cpu"])
    out, err = capsys.readouterr()
    return status, out, err.splitlines()


def test_cli_world_flags(tmp_path, capsys):
    """--world K writes world K alone (equal to its prim in the every-world file); --world-spacing sets the
    grid; a world that does not exist and a negative spacing are one-line errors (exit 2)."""
    scene = write_scene(tmp_path, "w.toml", frames=2, extra=f"\n[worlds]\ncount = 3\ngravity = {GRAVITIES}\n")
    status, out, err = run_cli(capsys, scene, "-o", tmp_path / "all.usdc", "--world-spacing", 3)
    assert status == 0 and err == [], err
    assert "3 worlds of 25 particles" in out and "; every world written" in out
    status, out, err = run_cli(capsys, scene, "-o", tmp_path / "one.usdc", "--world", 2)
    assert status == 0 and err == [], err
    assert "; world 2 written" in out

    all_worlds, one = Usd.Stage.Open(str(tmp_path / "all.usdc")), Usd.Stage.Open(str(tmp_path / "one.usdc"))
    np.testing.assert_array_equal(world_transform(all_worlds, "/World/world_0001"), [3.0, 0.0, 0.0])
    _, a = mesh_points(all_worlds, "/World/world_0002/cloth")
    _, b = mesh_points(one, "/World/cloth")
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)

    status, _, err = run_cli(capsys, scene, "-o", tmp_path / "no.usdc", "--world", 3)
    assert status == EXIT_CONFIG and len(err) == 1 and "cannot write world 3: the scene has 3 world(s)" in err[0]
    status, _, err = run_cli(capsys, scene, "-o", tmp_path / "no.usdc", "--world-spacing", -1)
    assert status == EXIT_CONFIG and len(err) == 1 and "--world-spacing" in err[0]
    assert not (tmp_path / "no.usdc").exists()


def test_cli_every_world_failing_exits_3(tmp_path, capsys):
    """With stop = "world", the run fails (exit 3) only once every world has failed; a world that failed
    earlier was a warning line."""
    extra = STOP_WORLD.replace("[1.0, 1.0e4, 1.0]", "[1.0e4, 1.0e4, 1.0e4]")
    scene = write_scene(tmp_path, "all_bad.toml", extra=extra)
    status, out, err = run_cli(capsys, scene, "-o", tmp_path / "bad.usdc")
    assert status == EXIT_SIMULATION and out == ""
    assert err[-1].startswith("warpspring: simulation failed: frame ") and "in world " in err[-1]
