"""The ``warpspring`` command: example scenes, option overrides, one-line errors with exit status 2 for bad input,
and exit status 3 with a readable partial file for an unstable run.

Commands run in-process through ``warpspring.app.cli.main`` (fast: kernels stay loaded); one test runs the real
``python -m warpspring`` entry point. Every scene here has the hanging-cloth example's feature set (springs,
gravity, drag, a ground plane, float32), so they all share its compiled kernel.
"""

import pathlib
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest

from helpers import points_samples, write_scene
from warpspring.app.cli import EXIT_CONFIG, EXIT_SIMULATION, main
from warpspring.io.scene import DeprecatedKeyWarning

EXAMPLES = pathlib.Path(__file__).resolve().parent.parent / "examples"

# Tiny masses on stiff springs, one substep per frame: ω·dt ≈ 100 ≫ 2, so symplectic Euler diverges within frames.
UNSTABLE = {
    "mass = 0.25": "particle_mass = 1.0e-3",
    "structural = { ke = 40.0, kd = 0.01 }": "structural = { ke = 1.0e4, kd = 0.0 }",
    "substeps = 4": "substeps = 1",
    "frames = 5": "frames = 40",
}


def run_cli(capsys, *args) -> tuple[int, str, list[str]]:
    """Exit status, stdout and the lines of stderr of ``warpspring run ARGS --device cpu``."""
    status = main(["run", *map(str, args), "--device", "cpu"])
    out, err = capsys.readouterr()
    return status, out, err.splitlines()


# -- runs that succeed ------------------------------------------------------------------------------------


# Examples run on a coarser grid of the same size: the flag's pre-run advisor (a static solve of up to 200
# implicit Euler steps under gravity and wind) took 25 of the test's 29 s at 31 × 21 on the CPU; at 16 × 11
# (the same 0.9 m × 0.6 m flag, twice the spacing) the scene keeps every feature (wind track, noise, lift,
# ground, implicit Euler) and the advisor's pass.
COARSER = {"flag_in_wind.toml": {
    "grid = { nx = 31, ny = 21, spacing = 0.03 }": "grid = { nx = 16, ny = 11, spacing = 0.06 }",
}}


@pytest.mark.parametrize("example, frames, prim", [("hanging_cloth.toml", 2, "/World/cloth"),
                                                   ("cloth_on_sphere.toml", 3, "/World/cloth"),
                                                   ("flag_in_wind.toml", 2, "/World/flag"),
                                                   ("tablecloth_pull.toml", 2, "/World/tablecloth"),
                                                   ("sparks.toml", 2, "/World/sparks")])
def test_example_scene_runs(tmp_path, capsys, example, frames, prim):
    """An example runs for a few frames: exit 0, the summary line, and frames + 1 samples at the scene's 60 fps.
    Examples in ``COARSER`` run from a copy with a coarser grid."""
    out = tmp_path / "example.usdc"
    scene = EXAMPLES / example
    if example in COARSER:
        text = scene.read_text()
        for full, coarse in COARSER[example].items():
            assert text.count(full) == 1, full
            text = text.replace(full, coarse)
        scene = tmp_path / example
        scene.write_text(text)
    status, stdout, stderr = run_cli(capsys, scene, "-o", out, "--frames", frames)
    assert status == 0, stderr
    assert stderr == []
    assert stdout.startswith(f"wrote {frames + 1} frames ") and str(out) in stdout and stdout.count("\n") == 1
    points, times, fps = points_samples(out, prim)
    assert times == [float(k) for k in range(frames + 1)] and fps == 60.0
    assert not np.array_equal(points[0], points[-1])  # gravity moved the cloth


def test_options_override_the_scene(tmp_path, capsys):
    """--fps, --substeps and --frames replace the file's values: the stage's rate, the sample count and dt change."""
    out = tmp_path / "override.usdc"
    scene = write_scene(tmp_path, extra=f"\n[output]\npath = '{out}'\n")
    status, stdout, stderr = run_cli(capsys, scene, "--fps", 30, "--substeps", 3, "--frames", 2)
    assert status == 0, stderr
    assert "dt = 11.11 ms" in stdout  # 1 / (30 fps · 3 substeps)
    _, times, fps = points_samples(out)  # written to the scene's [output] path
    assert fps == 30.0 and times == [0.0, 1.0, 2.0]

    status, stdout, _ = run_cli(capsys, scene, "-o", tmp_path / "plain.usda")
    assert status == 0 and "dt = 4.167 ms" in stdout  # the file's 60 fps · 4 substeps
    _, times, fps = points_samples(tmp_path / "plain.usda")
    assert fps == 60.0 and times == [float(k) for k in range(6)]


PROGRESS_LINE = re.compile(r"^frame (\d+) of (\d+) \((\d+) %\), ([\d.e+]+) frames/s, (\d+) s left$")


def test_run_to_a_pipe_prints_progress_lines(tmp_path, capsys, monkeypatch):
    """A run whose stderr is not a terminal (here pytest's capture, as a log file or CI) prints progress lines:
    with the interval at 0 s one after every frame but the first (the rate is measured from the first frame on,
    which compiles), each naming the frame, the total, frames/s and the seconds left; the summary stays alone on
    stdout. ``-q`` prints none."""
    from warpspring.app import runner

    monkeypatch.setattr(runner, "PROGRESS_EVERY", 0.0)
    status, stdout, stderr = run_cli(capsys, EXAMPLES / "hanging_cloth.toml", "-o", tmp_path / "a.usdc", "--frames", 4)
    assert status == 0 and stdout.startswith("wrote 5 frames ") and stdout.count("\n") == 1
    matches = [PROGRESS_LINE.match(line) for line in stderr]
    assert all(matches), stderr
    assert [int(m.group(1)) for m in matches] == [2, 3, 4] and {m.group(2) for m in matches} == {"4"}
    assert [int(m.group(3)) for m in matches] == [50, 75, 100] and int(matches[-1].group(5)) == 0
    assert all(float(m.group(4)) > 0 for m in matches)

    status, _, stderr = run_cli(capsys, EXAMPLES / "hanging_cloth.toml", "-o", tmp_path / "b.usdc", "--frames", 4,
                                "-q")
    assert status == 0 and stderr == []


def test_progress_lines_keep_their_interval_and_rate(capsys, monkeypatch):
    """On a clock that advances 1 s per frame and an interval of 2.5 s, lines come every third frame after the
    first; the rate is 1 frame/s (the first frame's setup left out) and the time left is the frames left at it."""
    from warpspring.app import runner

    monkeypatch.setattr(runner, "PROGRESS_EVERY", 2.5)
    ticks = iter(range(100))
    bar = runner.ProgressLines(10, clock=lambda: float(next(ticks)))  # t = 0 at the start
    for _ in range(10):
        bar.update(1)  # frame k ends at t = k
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["frame 3 of 10 (30 %), 1 frames/s, 7 s left", "frame 6 of 10 (60 %), 1 frames/s, 4 s left",
                     "frame 9 of 10 (90 %), 1 frames/s, 1 s left"]


def test_deprecated_key_is_one_warning_line(tmp_path, capsys):
    """A scene using a renamed key ([guard] max_strain, now tear_strain) runs, with exactly one
    'warpspring: warning:' line naming the file and both keys, and no Python warning besides."""
    scene = write_scene(tmp_path, extra="\n[guard]\nmax_strain = 10.0\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        status, stdout, stderr = run_cli(capsys, scene, "-o", tmp_path / "old.usdc", "--frames", 1)
    assert status == 0, stderr
    assert len(stderr) == 1 and stderr[0].startswith("warpspring: warning: scene.toml: [guard] max_strain ")
    assert "tear_strain" in stderr[0] and stdout.startswith("wrote 2 frames ")
    assert not [w for w in caught if issubclass(w.category, DeprecatedKeyWarning)]


# -- bad input: exit 2, one line -------------------------------------------------------------------------

NAN_OBJ = "v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n"
MESH_CLOTH = {
    'grid = { nx = 5, ny = 5, spacing = 0.1 }': 'mesh = "patch.obj"',
    'pin = ["top-left", "top-right"]': "pin = [0]",
    "shear = { ke = 10.0, kd = 0.01 }\n": "",
}

BAD_INPUT = [
    # id, scene edits (or None: no scene file), extra file {name: text}, extra arguments, words the error must hold
    ("missing-scene", None, {}, [], ["scene file not found", "absent.toml"]),
    ("malformed-toml", {"mass = 0.25": "mass = "}, {}, [], ["scene.toml", "not valid TOML"]),
    ("unknown-key", {"structural = { ke": "structural = { stifness"}, {}, [], ["'stifness'", "[cloth.structural]"]),
    ("negative-stiffness", {"ke = 40.0": "ke = -40.0"}, {}, [], ["cloth.structural.ke", ">= 0", "-40.0"]),
    ("negative-mass", {"mass = 0.25": "mass = -0.25"}, {}, [], ["cloth.mass", "> 0", "-0.25"]),
    ("zero-substeps-in-file", {"substeps = 4": "substeps = 0"}, {}, [], ["simulation.substeps", ">= 1"]),
    ("negative-substeps-in-file", {"substeps = 4": "substeps = -2"}, {}, [], ["simulation.substeps", ">= 1"]),
    ("zero-fps-in-file", {"fps = 60": "fps = 0"}, {}, [], ["simulation.fps", "> 0"]),
    ("negative-fps-in-file", {"fps = 60": "fps = -60.0"}, {}, [], ["simulation.fps", "> 0"]),
    ("zero-substeps-option", {}, {}, ["--substeps", "0"], ["--substeps", ">= 1"]),
    ("negative-substeps-option", {}, {}, ["--substeps", "-3"], ["--substeps", ">= 1"]),
    ("zero-fps-option", {}, {}, ["--fps", "0"], ["--fps", "> 0"]),
    ("negative-fps-option", {}, {}, ["--fps", "-24"], ["--fps", "> 0"]),
    ("zero-frames-option", {}, {}, ["--frames", "0"], ["--frames", ">= 1"]),
    ("nan-vertex-in-mesh", MESH_CLOTH, {"patch.obj": NAN_OBJ}, [], ["patch.obj", "not finite"]),
    ("empty-mesh-file", MESH_CLOTH, {"patch.obj": ""}, [], ["patch.obj", "empty"]),
    ("missing-mesh-file", MESH_CLOTH, {}, [], ["patch.obj", "not found"]),
    ("unknown-integrator", {"substeps = 4": 'substeps = 4\nintegrator = "rk9"'}, {}, [], ["'rk9'", "symplectic_euler"]),
    (
        "unknown-integrator-option",
        {"substeps = 4": "substeps = 4\n\n[simulation.integrator_options]\ntolerance = 1e-6"},
        {},
        [],
        ["'tolerance'", "symplectic_euler"],
    ),
    ("unknown-pin", {'"top-right"': '"top-middle"'}, {}, [], ["'top-middle'", "top-right"]),
    ("unavailable-device", {}, {}, ["--device", "cuda:7"], ["'cuda:7'", "not available"]),
    ("bad-output-extension", {}, {}, ["-o", "cloth.abc"], ["cloth.abc", ".usdc"]),
    ("output-is-a-folder", {}, {"taken.usdc/keep": ""}, ["-o", "taken.usdc"], ["taken.usdc", "is a folder"]),
    ("output-folder-missing", {}, {}, ["-o", "nowhere/cloth.usdc"], ["nowhere", "does not exist"]),
]


@pytest.mark.parametrize("edits, files, args, words", [c[1:] for c in BAD_INPUT], ids=[c[0] for c in BAD_INPUT])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch, edits, files, args, words):
    """Bad input exits 2 with one 'warpspring: error:' line naming the problem, no traceback and no output file."""
    monkeypatch.chdir(tmp_path)  # relative names in the cases (cloth.abc) land in tmp_path
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    scene = tmp_path / "absent.toml" if edits is None else write_scene(tmp_path, edits)
    out = tmp_path / "out.usdc"
    status = main(["run", str(scene), "-o", str(out), "--device", "cpu", *args])
    stdout, stderr = capsys.readouterr()
    lines = stderr.splitlines()
    assert status == EXIT_CONFIG, stderr
    assert len(lines) == 1, stderr
    assert lines[0].startswith("warpspring: error: ")
    assert "Traceback" not in stderr and stdout == ""
    for word in words:
        assert word in lines[0]
    assert not out.exists() and not (tmp_path / "cloth.abc").exists()


# -- an unstable run: exit 3 -------------------------------------------------------------------------------


def test_unstable_run_is_stopped_by_the_watch_at_its_first_frame(tmp_path, capsys):
    """A run outside the stability limit is warned about up front, and the stability watch's first re-check (after
    frame 1) stops it: exit 3, one line naming frame 1, the ratio of its ω_max to the step's limit, what the
    balance does not count and the substeps; the file holds frame 0."""
    out = tmp_path / "unstable.usdc"
    status, stdout, stderr = run_cli(capsys, write_scene(tmp_path, UNSTABLE), "-o", out)
    assert status == EXIT_SIMULATION, stderr
    assert stdout == "" and len(stderr) == 2, stderr
    assert stderr[0].startswith("warpspring: warning: symplectic_euler is unstable at dt = ")
    failure = stderr[1]
    assert re.match(r"warpspring: simulation failed: frame 1: the state is past the stability limit of "
                    r"symplectic_euler: ω_max ≈ [0-9.]+ rad/s is [0-9.]+× the", failure), failure
    assert "--substeps" in failure and "frames 0..0" in failure
    points, times, _ = points_samples(out)
    assert times == [0.0] and np.isfinite(points[0]).all()


def test_unstable_run_warns_exits_3_and_leaves_finite_frames(tmp_path, capsys):
    """Without the watch (``--watch-every 0``) the guard stops the same run: it diverges and exits 3 with one line
    naming frame k, the substep, what the guard saw (the energy the unstable step created, before any spring
    tears) and the advisor's remedy; the file holds the finite frames 0..k-1 and not the blown-up one."""
    out = tmp_path / "unstable.usdc"
    status, stdout, stderr = run_cli(capsys, write_scene(tmp_path, UNSTABLE), "-o", out, "--watch-every", "0")
    assert status == EXIT_SIMULATION, stderr
    assert stdout == "" and len(stderr) == 2
    assert stderr[0].startswith("warpspring: warning: symplectic_euler is unstable at dt = ")
    failure = stderr[1]
    assert failure.startswith("warpspring: simulation failed: ")
    match = re.search(r"\bframe (\d+), substep (\d+) of 1 \(t ≤ ", failure)
    assert match, failure
    k = int(match.group(1))
    assert 1 <= k < 40
    assert "--substeps" in failure and f"frames 0..{k - 1}" in failure
    assert "the integration created" in failure  # the energy balance caught it before springs tore

    points, times, _ = points_samples(out)
    assert times == [float(i) for i in range(k)]
    assert all(np.isfinite(p).all() for p in points)


def test_strict_refuses_an_unstable_step_before_writing(tmp_path, capsys):
    """--strict turns the advisor's warning into a one-line error (exit 2) and no output file."""
    out = tmp_path / "never.usdc"
    status, stdout, stderr = run_cli(capsys, write_scene(tmp_path, UNSTABLE), "-o", out, "--strict")
    assert status == EXIT_CONFIG and stdout == "" and len(stderr) == 1
    assert stderr[0].startswith("warpspring: error: symplectic_euler is unstable at dt = ")
    assert "substeps per 1/60 s frame" in stderr[0]
    assert not out.exists()


def test_suggested_substeps_make_the_unstable_run_stable(tmp_path, capsys):
    """The substep count the advisor suggests runs the same scene to the end without a warning; half of it
    still diverges (the power-iteration limit is tight, not a loose bound)."""
    scene = write_scene(tmp_path, UNSTABLE)
    status, _, stderr = run_cli(capsys, scene, "-o", tmp_path / "a.usdc")
    assert status == EXIT_SIMULATION
    suggested = int(re.search(r"--substeps (\d+)", stderr[-1]).group(1))

    status, stdout, stderr = run_cli(capsys, scene, "-o", tmp_path / "b.usdc", "--substeps", suggested, "--strict")
    assert status == 0 and stderr == [], stderr
    points, times, _ = points_samples(tmp_path / "b.usdc")
    assert len(times) == 41 and np.abs(points[-1]).max() < 2.0  # 40 frames; the cloth hangs near its pins

    status, _, _ = run_cli(capsys, scene, "-o", tmp_path / "c.usdc", "--substeps", suggested // 2)
    assert status == EXIT_SIMULATION


# -- the real entry point ----------------------------------------------------------------------------------


def test_python_dash_m_entry_point(tmp_path):
    """`python -m warpspring run` prints the summary and exits 0, and exits 2 with the one-line error for bad input."""
    scene, out = write_scene(tmp_path), tmp_path / "entry.usdc"
    command = [sys.executable, "-m", "warpspring", "run", str(scene), "-o", str(out), "--device", "cpu"]
    command += ["--frames", "2"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("wrote 3 frames ")
    assert "Traceback" not in done.stderr
    assert points_samples(out)[1] == [0.0, 1.0, 2.0]

    done = subprocess.run(command[:-1] + ["0"], capture_output=True, text=True, timeout=120)
    assert done.returncode == EXIT_CONFIG
    assert done.stderr.startswith("warpspring: error: argument --frames") and done.stderr.count("\n") == 1


@pytest.mark.parametrize("command", ["trade", "stability"])
def test_study_output_that_is_a_file_fails_before_the_study_runs(tmp_path, capsys, command):
    """A study's --out naming a file is refused at once (exit 2), not after the hour the study takes."""
    taken = tmp_path / "results"
    taken.write_text("")
    assert main([command, "--quick", "--device", "cpu", "--out", str(taken)]) == EXIT_CONFIG
    stderr = capsys.readouterr().err
    assert "output directory" in stderr and "is a file" in stderr


def test_usd_save_failure_exits_4_with_one_line(tmp_path, capsys, monkeypatch):
    """A USD file that cannot be saved mid-run (full disk) ends with exit 4 and one line naming the file."""
    from warpspring.io.usd import UsdWriter

    def failing_save(self, force=False):
        if self.frame_count >= 2:
            raise OSError(f"cannot save the USD file {self.path!r} (disk full or file removed?)")

    monkeypatch.setattr(UsdWriter, "_save", failing_save)
    out = tmp_path / "out.usdc"
    assert main(["run", str(write_scene(tmp_path, {})), "-o", str(out), "--device", "cpu", "--frames", "4"]) == 4
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpspring: output failed: ") and "out.usdc" in lines[0]


# The advisor battery's cloth (warpspring/analysis/load_battery.py) at a stiffness that is stable at its
# static equilibrium at RK4's 1/240 s, but that the release transient carries past RK4's limit.
TRANSIENT = """\
[simulation]
fps = 60
frames = 40
substeps = 4
integrator = "rk4"

[cloth]
grid = { nx = 20, ny = 20, spacing = 0.1 }
particle_mass = 0.1
rotation = { axis = [1.0, 0.0, 0.0], degrees = 90.0 }
pin = ["top-left", "top-right"]
structural = { ke = 6600.0, kd = 0.01 }
shear = false
bend = false
"""


def test_strict_refuses_a_step_the_release_transient_breaks_and_the_watch_warns_first(tmp_path, capsys):
    """The battery cloth at ke = 6.6 kN/m is stable at its static equilibrium at 4 RK4 substeps, but its
    release swings the springs past that stretch (RESULTS §11: runs blow up from 6.35 kN/m). --strict
    refuses it, naming the dry run's peak and the substeps it needs. Run anyway, the pre-run warning comes
    first, the run-time watch (every 10 frames) warns before the energy balance stops the run as instability,
    each naming the substeps; with the advisor's substeps the run passes --strict and completes without a
    warning."""
    scene = tmp_path / "transient.toml"
    scene.write_text(TRANSIENT)
    status, stdout, stderr = run_cli(capsys, scene, "-o", tmp_path / "a.usdc", "--strict")
    assert status == EXIT_CONFIG and len(stderr) == 1, stderr
    refused = re.search(r"rk4 is unstable at dt = .* at its peak, t = .* dry run.* at least (\d+) substeps", stderr[0])
    assert refused, stderr
    advised = int(refused.group(1))
    status, stdout, stderr = run_cli(capsys, scene, "-o", tmp_path / "a.usdc")
    assert status == EXIT_SIMULATION and len(stderr) == 3, stderr
    assert stderr[0].startswith("warpspring: warning: rk4 is unstable") and f"at least {advised} substeps" in stderr[0]
    warned = re.match(r"warpspring: warning: frame (\d+): the state has stiffened toward the stability limit of rk4: "
                      r".* use at least (\d+) substeps", stderr[1])
    failed = re.search(r"simulation failed: frame (\d+),.*the integration created .*--substeps (\d+)\)", stderr[2])
    assert warned and failed, stderr
    assert int(warned.group(1)) < int(failed.group(1))
    assert int(warned.group(2)) == int(failed.group(2)) > 4
    status, stdout, stderr = run_cli(capsys, scene, "-o", tmp_path / "b.usdc", "--strict", "--substeps", advised)
    assert status == 0 and stderr == [], stderr
    status, stdout, stderr = run_cli(capsys, scene, "-o", tmp_path / "c.usdc", "--watch-every", 0)
    assert status == EXIT_SIMULATION and len(stderr) == 2 and "simulation failed" in stderr[1]  # no watch warning


FLAT_UNDAMPED = """
[simulation]
fps = 60
frames = 600
substeps = 10
integrator = "symplectic_euler"

[world]
gravity = [0.0, 0.0, -9.81]
drag = 0.0

[cloth]
grid = { nx = 16, ny = 16, spacing = 0.1 }
origin = [0.0, 0.0, 1.0]
mass = 1.0
pin = ["top-left", "top-right"]
structural = { ke = 1000.0, kd = 0.0 }
shear = { ke = 200.0, kd = 0.0 }
bend = { ke = 20.0, kd = 0.0 }
"""


def test_strict_tries_the_step_past_the_theory_and_refuses_the_flat_cloth(tmp_path, capsys):
    """Issue 48's undamped 16² cloth released flat, symplectic Euler at 10 substeps per 1/60 s: within the linear
    limit (1.81 ms) but past the three-wave step (1.53 ms), where the theory cannot decide. --strict runs the scene on
    trial for the run's 10 s, sees it blow up, and refuses before writing, saying what the trial run did."""
    out, scene = tmp_path / "never.usdc", tmp_path / "flat.toml"
    scene.write_text(FLAT_UNDAMPED)
    status, stdout, stderr = run_cli(capsys, scene, "-o", out, "--strict")
    assert status == EXIT_CONFIG and len(stderr) == 1, stderr
    assert re.search(r"1 trial run of this scene for 10 s \(at 1\.667 ms it (turned non-finite|tore a spring|gained|grew)",
                     stderr[0]), stderr
    assert "at least 11 substeps per 1/60 s frame" in stderr[0]
    assert "trying it on up to two runs of the scene, 10 s each" in stdout  # a long trial is not a silent wait
    assert not out.exists()
