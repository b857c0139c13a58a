"""Every input path is a regular file, checked before it is opened: a named pipe (FIFO) as a scene file, as a
cloth, soft-body or collider mesh (trimesh or USD), or among the layers a USD mesh file pulls in (a sublayer,
a reference, a payload) ends the run with exit status 2 and one line naming it — it never blocks. Each case
runs the command line in a child process under a timeout, so that a reader that blocks (as USD's did on a
FIFO) fails the test instead of stalling the suite."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from warpspring.app.cli import main
from warpspring.core.mesh_files import USD_EXTENSIONS, check_regular_file, check_usd_layers, load_mesh_file, read_usd_mesh
from warpspring.errors import ConfigError

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="named pipes are POSIX")

ROOT = Path(__file__).resolve().parents[1]
#: Generous: the child imports warpspring and Warp (a few seconds); a blocked reader never returns.
TIMEOUT = 120

CLOTH_MESH = """\
[simulation]
frames = 1
substeps = 2

[cloth]
mesh = "{mesh}"
mass = 0.1
"""
SOFT_BODY = """\
version = 2

[simulation]
frames = 1
substeps = 2

[[soft_body]]
mesh = "{mesh}"
youngs_modulus = 1e4
density = 100.0
"""
COLLIDER = """\
version = 2

[simulation]
frames = 1
substeps = 2

[cloth]
grid = {{ nx = 3, ny = 3, spacing = 0.1 }}
particle_mass = 0.1

[[collider]]
type = "mesh"
file = "{mesh}"
"""
LAYER = {
    "sublayer": '#usda 1.0\n(\n    subLayers = [@./pipe.usda@]\n)\n',
    "reference": '#usda 1.0\ndef Xform "World" (\n    references = @./pipe.usda@\n)\n{\n}\n',
    "payload": '#usda 1.0\ndef Xform "World" (\n    payload = @./pipe.usda@\n)\n{\n}\n',
    "nested": '#usda 1.0\n(\n    subLayers = [@./middle.usda@]\n)\n',
}


def cli(tmp_path, scene_text: str | None, *, scene: Path | None = None, child: bool = True, capsys=None):
    """``warpspring run`` of a scene in a child process (this checkout's package), under TIMEOUT; or, with
    ``child=False`` (a reader that cannot block: trimesh's), in this process."""
    if scene is None:
        scene = tmp_path / "scene.toml"
        scene.write_text(scene_text)
    if not child:
        status = main(["run", str(scene), "-o", str(tmp_path / "out.usdc"), "--device", "cpu", "-q"])
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess([], status, out, err)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "warpspring", "run", str(scene), "-o", str(tmp_path / "out.usdc"),
                           "--device", "cpu", "-q"], capture_output=True, text=True, timeout=TIMEOUT, cwd=ROOT,
                          env=env)


def assert_one_line(result, *words) -> None:
    err = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(err) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for word in words:
        assert word in err[0], err[0]


@pytest.mark.parametrize("template", [CLOTH_MESH, SOFT_BODY, COLLIDER], ids=["cloth", "soft_body", "collider"])
@pytest.mark.parametrize("suffix", [".obj", ".usda"])
def test_a_pipe_as_mesh_file_is_refused(tmp_path, capsys, template, suffix):
    pipe = tmp_path / f"pipe{suffix}"
    os.mkfifo(pipe)
    result = cli(tmp_path, template.format(mesh=pipe), child=suffix in USD_EXTENSIONS, capsys=capsys)
    assert_one_line(result, str(pipe), "named pipe (FIFO)")


@pytest.mark.parametrize("kind", sorted(LAYER))
def test_a_pipe_among_a_usd_files_layers_is_refused(tmp_path, kind):
    """A USD mesh file whose sublayer, reference or payload (or a sublayer's sublayer) is a FIFO: refused
    before the stage composes (Usd.Stage.Open blocked forever on it)."""
    os.mkfifo(tmp_path / "pipe.usda")
    (tmp_path / "middle.usda").write_text(LAYER["sublayer"])
    root = tmp_path / "cloth.usda"
    root.write_text(LAYER[kind])
    assert_one_line(cli(tmp_path, CLOTH_MESH.format(mesh=root)), str(root), str(tmp_path / "pipe.usda"),
                    "named pipe (FIFO)")


def test_a_pipe_as_scene_file_is_refused(tmp_path):
    pipe = tmp_path / "scene.toml"
    os.mkfifo(pipe)
    assert_one_line(cli(tmp_path, None, scene=pipe), str(pipe), "named pipe (FIFO)")


def test_the_checks_in_process(tmp_path):
    """The checks themselves, without a child process: a folder and a pipe are refused by a stat alone; a
    regular file, and a USD file whose missing sublayer USD itself reports, pass."""
    pipe, folder, plain = tmp_path / "pipe.usda", tmp_path / "folder.obj", tmp_path / "plain.usda"
    os.mkfifo(pipe)
    folder.mkdir()
    plain.write_text('#usda 1.0\n(\n    subLayers = [@./absent.usda@]\n)\n')
    with pytest.raises(ConfigError, match="is a named pipe"):
        check_regular_file(pipe, "mesh file")
    with pytest.raises(ConfigError, match="is a named pipe"):
        read_usd_mesh(pipe)
    with pytest.raises(ConfigError, match="is a named pipe"):
        load_mesh_file(tmp_path / "pipe.usda")
    with pytest.raises(ConfigError, match="is a folder"):
        load_mesh_file(folder)
    assert check_regular_file(plain) == str(plain)
    assert len(check_usd_layers(str(plain))) == 1  # the absent sublayer is USD's to report


def command(tmp_path, *args: str):
    """A ``warpspring`` command in a child process of this checkout, under TIMEOUT."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "warpspring", *args], capture_output=True, text=True,
                          timeout=TIMEOUT, cwd=ROOT, env=env)


@pytest.mark.parametrize("verb", ["audit", "render"])
def test_audit_and_render_refuse_a_pipe_among_the_layers(tmp_path, verb):
    """``warpspring audit`` and ``warpspring render`` read a USD file the same way: a sublayer that is a FIFO
    is refused in one line before USD composes the stage (it would block there)."""
    os.mkfifo(tmp_path / "pipe.usda")
    root = tmp_path / "frames.usda"
    root.write_text(LAYER["sublayer"])
    extra = ["-o", str(tmp_path / "frame.png")] if verb == "render" else []
    assert_one_line(command(tmp_path, verb, str(root), *extra), str(tmp_path / "pipe.usda"), "named pipe (FIFO)")


def test_a_sweep_file_is_read_like_a_scene_file(tmp_path):
    """A sweep file that is a FIFO, and one whose arrays nest past the parser's limit, are refused in one
    line (the sweep reader shares the scene reader's checks)."""
    pipe = tmp_path / "sweep.toml"
    os.mkfifo(pipe)
    assert_one_line(command(tmp_path, "sweep", str(pipe), "--no-ray"), str(pipe), "named pipe (FIFO)")
    deep = tmp_path / "deep.toml"
    deep.write_text("x = " + "[" * 400 + "]" * 400 + "\n")
    assert_one_line(command(tmp_path, "sweep", str(deep), "--no-ray"), str(deep), "nest deeper")
