"""`warpspring run --checkpoint-every N` and `--resume CHECKPOINT`: a stopped run continues into the same USD
file, and the file is then the uninterrupted run's, sample for sample."""

import numpy as np
import pytest
from pxr import Usd

from warpspring.app.cli import EXIT_CONFIG, main

SCENE = """\
[simulation]
fps = 60
frames = 40
substeps = 8

[cloth]
grid = { nx = 8, ny = 8, spacing = 0.1 }
particle_mass = 0.1
pin = ["top-left", "top-right"]
structural = { ke = 1000.0, kd = 1.0 }
shear = { ke = 500.0, kd = 0.5 }
bend = false
"""


def run(capsys, *args) -> tuple[int, list[str], list[str]]:
    status = main(["run", *map(str, args), "--device", "cpu"])
    out, err = capsys.readouterr()
    return status, out.splitlines(), err.splitlines()


def samples(path) -> dict:
    """Every attribute's time samples in the USD file at ``path``: path → [(time code, value as an array)]."""
    stage = Usd.Stage.Open(str(path))
    found = {}
    for prim in stage.Traverse():
        for attribute in prim.GetAttributes():
            times = attribute.GetTimeSamples()
            if times:
                found[str(attribute.GetPath())] = [(t, np.array(attribute.Get(t))) for t in times]
    return found


@pytest.fixture
def scene(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text(SCENE)
    return path


def test_a_resumed_run_writes_the_uninterrupted_file(tmp_path, capsys, scene):
    """Run 40 frames straight; run 25 frames saving every 10 (the last checkpoint is frame 20: the run was
    "stopped" after 25), then resume to 40: the file keeps frames 0..20, rewrites 21..25 and adds the rest,
    and every time sample (points, normals, extents) equals the straight run's bit for bit."""
    status, _, _ = run(capsys, scene, "-o", tmp_path / "straight.usdc")
    assert status == 0
    part = tmp_path / "part.usdc"
    status, _, _ = run(capsys, scene, "-o", part, "--frames", 25, "--checkpoint-every", 10)
    checkpoint = tmp_path / "part.checkpoint.npz"
    assert status == 0 and checkpoint.exists()
    status, out, err = run(capsys, scene, "-o", part, "--resume", checkpoint)
    assert status == 0 and err == [] and "frames 21..40 after resuming" in out[0]
    straight, resumed = samples(tmp_path / "straight.usdc"), samples(part)
    assert straight.keys() == resumed.keys() and "/World/cloth.points" in straight
    for name, expected in straight.items():
        got = resumed[name]
        assert [t for t, _ in got] == [float(k) for k in range(41)], name
        for (_, a), (_, b) in zip(expected, got):
            np.testing.assert_array_equal(a, b, err_msg=name)
    assert Usd.Stage.Open(str(part)).GetEndTimeCode() == 40.0


@pytest.mark.parametrize("case, message", [
    ("past the end", "is at frame 20, at or past the run's end (frame 20): nothing to resume"),
    ("output missing", "the file is missing (resume writes into the stopped run's output"),
    ("other scene", "was saved with particles per world 64, but this simulator has 36"),
    ("damaged", "cannot be read"),
])
def test_resume_refuses_what_it_cannot_continue(tmp_path, capsys, scene, case, message):
    """Each refusal is one line and exit status 2, and leaves the output as it was."""
    out = tmp_path / "out.usdc"
    status, _, _ = run(capsys, scene, "-o", out, "--frames", 25, "--checkpoint-every", 10)
    checkpoint = tmp_path / "out.checkpoint.npz"
    args = [scene, "-o", out, "--resume", checkpoint]
    if case == "past the end":
        args += ["--frames", 20]
    elif case == "output missing":
        args[2] = tmp_path / "elsewhere.usdc"
    elif case == "other scene":
        other = tmp_path / "other.toml"
        other.write_text(SCENE.replace("nx = 8, ny = 8", "nx = 6, ny = 6"))
        args[0] = other
    else:
        checkpoint.write_bytes(b"not a checkpoint")
    before = out.read_bytes()
    status, _, err = run(capsys, *args)
    assert status == EXIT_CONFIG and len(err) == 1 and message in err[0], err
    assert out.read_bytes() == before
