"""A checkpoint knows the model that made it: resuming into a scene that builds another model (a spring's
stiffness, a pin, the step) is refused with exit status 2 and one line naming the keys that differ; the end
time and live inputs (gravity) may change; a checkpoint from another warpspring version resumes with a
warning. A damaged header (a field of the wrong type or out of range, valid CRC and all) and a state that is
not finite are refused with one line naming the checkpoint."""

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd

import warpspring as ws
from warpspring.app.cli import EXIT_CONFIG, main
from warpspring.core.checkpoint import Checkpoint
from warpspring.core.checkpoint_checks import model_fingerprint
from warpspring.core.integrators import make_integrator
from warpspring.errors import ConfigError
from warpspring.io.scene import load_scene, parse_scene

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]

SCENE = """\
[simulation]
fps = 60
frames = 8
substeps = 8

[world]
gravity = [0.0, 0.0, -9.81]

[cloth]
grid = { nx = 4, ny = 4, spacing = 0.1 }
particle_mass = 0.1
pin = ["top-left", "top-right"]
structural = { ke = 100.0, kd = 1.0 }
shear = { ke = 50.0, kd = 0.5 }
bend = false
"""


def load_scene_text(text: str):
    return parse_scene(tomllib.loads(text))


def sim_under(gravity: float, frames: int) -> np.ndarray:
    """SCENE's positions after ``frames`` frames under gravity [m/s²] (downwards) throughout."""
    scene = load_scene_text(SCENE.replace("-9.81", f"-{gravity}"))
    model = scene.finalize("cpu")
    sim = ws.Simulator(model, integrator=make_integrator(scene.integrator, model), fps=scene.fps,
                       substeps=scene.substeps, guard=scene.guard)
    for _ in range(frames):
        sim.step_frame()
    return sim.state.particle_q.numpy()


def run(capsys, *args) -> tuple[int, list[str], list[str]]:
    status = main(["run", *map(str, args), "--device", "cpu", "-q"])
    out, err = capsys.readouterr()
    return status, out.splitlines(), err.splitlines()


@pytest.fixture
def saved(tmp_path, capsys):
    """A run of SCENE stopped at frame 4 with a checkpoint at frame 4: (scene path, output, checkpoint)."""
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    out = tmp_path / "out.usdc"
    status, _, err = run(capsys, scene, "-o", out, "--frames", 4, "--checkpoint-every", 4)
    assert status == 0, err
    return scene, out, tmp_path / "out.checkpoint.npz"


def rewrite_header(path, change) -> None:
    """Rewrite the checkpoint at ``path`` with ``change(header)`` applied (a well-formed file: the zip's CRCs
    are the new ones, only the content is wrong)."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    header = json.loads(str(arrays.pop("header")))
    change(header)
    np.savez(path, header=np.array(json.dumps(header)), **arrays)


def rewrite_array(path, key, change) -> None:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    arrays[key] = change(arrays[key].copy())
    np.savez(path, **arrays)


@pytest.mark.parametrize("edit, key", [
    (lambda s: s.replace("ke = 100.0", "ke = 400.0"), "spring_stiffness"),
    (lambda s: s.replace('pin = ["top-left", "top-right"]', 'pin = ["top-left"]'), "particle_flags"),
    (lambda s: s.replace("particle_mass = 0.1", "particle_mass = 0.2"), "particle_mass"),
    (lambda s: s.replace("spacing = 0.1", "spacing = 0.12"), "spring_rest_length"),
])
def test_a_changed_model_is_refused_naming_the_key(saved, capsys, edit, key):
    """The issue's case (ke 100 → 400: before, the run resumed silently with ke = 100) and its kin: exit 2,
    one line naming the checkpoint and the key that differs; the output is left as it was."""
    scene, out, checkpoint = saved
    scene.write_text(edit(SCENE))
    before = out.read_bytes()
    status, _, err = run(capsys, scene, "-o", out, "--resume", checkpoint)
    assert status == EXIT_CONFIG and len(err) == 1, err
    assert str(checkpoint) in err[0] and f"{key} (saved:" in err[0], err[0]
    assert out.read_bytes() == before


def test_a_changed_step_is_refused(saved, capsys):
    scene, out, checkpoint = saved
    status, _, err = run(capsys, scene, "-o", out, "--resume", checkpoint, "--substeps", 16)
    assert status == EXIT_CONFIG and len(err) == 1 and "substeps" in err[0], err


def test_the_end_time_and_live_inputs_may_change(saved, capsys):
    """More frames and another gravity (a live input) resume, and the frames after the checkpoint follow the
    scene's new gravity: the file's last frame is that of the same simulator stepped 4 frames under g = 9.81
    and 6 under g = 5 m/s² (set between frames through the API), to float32 rounding of the same operations."""
    scene, out, checkpoint = saved
    scene.write_text(SCENE.replace("frames = 8", "frames = 10").replace("-9.81", "-5.0"))
    status, lines, err = run(capsys, scene, "-o", out, "--resume", checkpoint)
    assert status == 0 and err == [], err
    assert "frames 5..10 after resuming" in lines[0]

    reference = load_scene_text(SCENE)
    model = reference.finalize("cpu")
    sim = ws.Simulator(model, integrator=make_integrator(reference.integrator, model), fps=reference.fps,
                       substeps=reference.substeps, guard=reference.guard)
    for frame in range(10):
        if frame == 4:
            model.set_world_values("gravity", [0.0, 0.0, -5.0])
        sim.step_frame()
    stage = Usd.Stage.Open(str(out))
    points = np.array(stage.GetPrimAtPath("/World/cloth").GetAttribute("points").Get(10))
    expected = sim.state.particle_q.numpy()
    # The same float32 operations in the same order: equal but for nothing (a tolerance of a few ulps of 1 m).
    np.testing.assert_allclose(points, expected, rtol=0, atol=1e-6)
    kept = sim_under(9.81, 10)  # the saved run's gravity kept would land elsewhere: the check can tell
    assert np.abs(kept - expected).max() > 1e-3


def test_another_version_warns(saved, capsys):
    scene, out, checkpoint = saved
    rewrite_header(checkpoint, lambda h: h.update(warpspring_version="0.0.1"))
    status, _, err = run(capsys, scene, "-o", out, "--resume", checkpoint)
    assert status == 0 and len(err) == 1 and "saved by warpspring 0.0.1" in err[0], err


@pytest.mark.parametrize("field, value, must", [
    ("frame", "x", "an integer >= 0"),
    ("frame", -5, "an integer >= 0"),
    ("frame", 2.5, "an integer >= 0"),
    ("frame", True, "an integer >= 0"),
    ("fps", float("nan"), "a finite number > 0"),
    ("substeps", 0, "an integer >= 1"),
    ("worlds", "1", "an integer >= 1"),
    ("precision", "float16", '"float32" or "float64"'),
    ("switches", {"gravity": 1}, "a table of gravity"),
    ("world_failures", [{"world": 7, "frame": 1, "report": {}}], "a table of world"),
    ("arrays", "state/particle_q", "a list of array names"),
    ("model", {"spring_stiffness": 3}, "a table of {hash, summary}"),
])
def test_every_header_field_is_checked(saved, capsys, field, value, must):
    """``"frame": "x"`` gave a ValueError traceback, ``"frame": -5`` an error that did not name the checkpoint:
    each bad field is one line naming the checkpoint, the field and what it must be."""
    scene, out, checkpoint = saved
    rewrite_header(checkpoint, lambda h: h.update({field: value}))
    status, _, err = run(capsys, scene, "-o", out, "--resume", checkpoint)
    assert status == EXIT_CONFIG and len(err) == 1, err
    assert str(checkpoint) in err[0] and f"{field} is" in err[0] and must in err[0], err[0]


def test_a_missing_header_field_is_refused(saved, capsys):
    scene, out, checkpoint = saved
    rewrite_header(checkpoint, lambda h: h.pop("frame"))
    status, _, err = run(capsys, scene, "-o", out, "--resume", checkpoint)
    assert status == EXIT_CONFIG and len(err) == 1 and "lacks frame" in err[0] and str(checkpoint) in err[0], err


@pytest.mark.parametrize("key", ["state/particle_q", "state/particle_qd", "state/time"])
def test_a_non_finite_state_is_refused(saved, capsys, key):
    """A checkpoint holding NaN positions was accepted and the run stopped later: now it is refused at once."""
    scene, out, checkpoint = saved

    def poison(values):
        values.reshape(-1)[-1] = np.nan
        return values

    rewrite_array(checkpoint, key, poison)
    status, _, err = run(capsys, scene, "-o", out, "--resume", checkpoint)
    assert status == EXIT_CONFIG and len(err) == 1, err
    assert str(checkpoint) in err[0] and "non-finite" in err[0] and key.split("/")[1] in err[0], err[0]


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")
def test_a_checkpoint_that_is_a_pipe_is_refused(tmp_path):
    fifo = tmp_path / "pipe.npz"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="named pipe"):
        Checkpoint.load(fifo)


@pytest.mark.parametrize("example", ["tablecloth_pull", "sparks", "plastic_bar", "turntable"])
def test_a_run_keeps_its_fingerprint(example):
    """What a run changes by itself — handles' targets set by their tracks, an emitter's births and deaths,
    plastic springs' yield, a collider's motion — is not the model: after a few frames its fingerprint is that
    of the model as built, so that a resumed run of an unchanged scene is never refused (each example holds
    one of those)."""
    scene = load_scene(ROOT / "examples" / f"{example}.toml")

    def build():
        model = scene.finalize("cpu")
        return ws.Simulator(model, integrator=make_integrator(scene.integrator, model, **scene.integrator_options),
                            fps=scene.fps, substeps=scene.substeps, guard=scene.guard)

    sim = build()
    for _ in range(3):
        sim.step_frame()
    assert model_fingerprint(sim) == model_fingerprint(build())
