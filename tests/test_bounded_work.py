"""Bounded work on any input: a scene file nested deeper than the schema could use is refused with one line
(1.6 KB of inline tables nested 400 deep gave a RecursionError traceback), and the pre-run advisor's dry run
stops at its step budget with a conservative verdict that says so (``shear = { ke = 1e18 }`` on a tiny cloth
kept it going for minutes)."""

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from helpers import deadline
from warpspring.analysis import under_load
from warpspring.analysis.advisor import advise
from warpspring.app.cli import EXIT_CONFIG, main
from warpspring.errors import ConfigError
from warpspring.io.scene import parse_scene
from warpspring.io.scene_checks import MAX_NESTING, check_nesting

ROOT = Path(__file__).resolve().parents[1]


CLOTH = """\
[simulation]
fps = 60
frames = 2
substeps = 8

[world]
gravity = [0.0, 0.0, -9.81]

[cloth]
grid = { nx = 4, ny = 4, spacing = 0.1 }
particle_mass = 0.1
pin = ["top-left", "top-right"]
structural = { ke = 100.0, kd = 0.1 }
shear = { ke = 50.0 }
bend = false
"""


def run(tmp_path, capsys, text: str) -> tuple[int, list[str]]:
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    status = main(["run", str(scene), "-o", str(tmp_path / "out.usdc"), "--device", "cpu", "-q"])
    return status, capsys.readouterr().err.splitlines()


@pytest.mark.parametrize("nested", [
    "{a = " * 400 + "1" + "}" * 400,  # the case
    "[" * 400 + "1" + "]" * 400,
    "[" * 5000 + "]" * 5000,
    "{a = [" * (MAX_NESTING // 2 + 1) + "1" + "]}" * (MAX_NESTING // 2 + 1),
])
def test_deep_nesting_is_refused_with_one_line(tmp_path, capsys, nested):
    status, err = run(tmp_path, capsys, "[cloth]\ngrid = " + nested + "\n")
    assert status == EXIT_CONFIG and len(err) == 1 and f"deeper than {MAX_NESTING} levels" in err[0], err


def test_brackets_in_strings_and_comments_do_not_count(tmp_path, capsys):
    """A string or a comment full of brackets is not nesting: the scene runs."""
    text = CLOTH.replace("[cloth]", "[cloth]\nname = \"" + "[{" * 100 + "\"  # " + "[" * 100)
    status, err = run(tmp_path, capsys, text)
    assert status == 0, err


DEEP = "[" * (MAX_NESTING + 1) + "]" * (MAX_NESTING + 1)


@pytest.mark.parametrize("text, refused", [
    ('a = "x\\"[[" # [[[\ne = ' + DEEP, True),  # an escaped quote does not end the string
    ('f = "a\\\\"\ng = ' + DEEP, True),  # an escaped backslash does not escape the quote
    ('b = """\n' + DEEP + '\n"""\n', False),
    ("c = '" + DEEP + "'\n", False),
    ("d = '''\n" + DEEP + "\n'''\n", False),
    ("# " + DEEP, False),
    ("[" * MAX_NESTING + "]" * MAX_NESTING, False),
])
def test_the_nesting_scan_skips_strings_and_comments(text, refused):
    if refused:
        with pytest.raises(ConfigError, match="deeper than"):
            check_nesting(text, "scene.toml")
    else:
        check_nesting(text, "scene.toml")


@pytest.mark.parametrize("piece", ['"\\', '"""\\', "'''a\n", '"""a"', '\\"'])
def test_the_nesting_scan_is_linear(piece):
    """Unterminated strings, escapes and quotes by the hundred thousand: one pass (a first, regular-expression
    scan took 150 s on 150 KB of '"\\', quadratic); a deadline turns a regression into a failure, not a
    stall."""
    with deadline(30.0):
        check_nesting(piece * 200_000, "scene.toml")


def test_a_deep_dict_is_refused_without_recursion():
    """parse_scene of a dict nested 100 000 deep (no TOML parser in between): one ConfigError."""
    value: dict = {}
    for _ in range(100_000):
        value = {"a": value}
    with pytest.raises(ConfigError, match=f"deeper than {MAX_NESTING} levels"):
        parse_scene({"cloth": {"grid": value}})


def test_an_absurd_stiffness_gets_a_prompt_conservative_verdict(tmp_path):
    """``shear = { ke = 1e18 }`` on a 4 × 4 cloth: the dry run would need ~1e16 steps; the advisor skips it and
    judges by the Gershgorin bound, and its warning says so. In a child process under a timeout, so that a dry
    run without a budget fails the test rather than stalling the suite (it ran for minutes)."""
    scene = tmp_path / "scene.toml"
    scene.write_text(CLOTH.replace("shear = { ke = 50.0 }", "shear = { ke = 1e18 }"))
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    result = subprocess.run([sys.executable, "-m", "warpspring", "run", str(scene), "-o", str(tmp_path / "out.usdc"),
                             "--device", "cpu", "-q"], capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert result.returncode in (0, 3) and "Traceback" not in result.stderr, result.stderr
    warning = [line for line in result.stderr.splitlines() if line.startswith("warpspring: warning")]
    assert len(warning) == 1 and "Gershgorin bound, conservative: the dry run was cut short" in warning[0], warning
    assert f"past its budget of {under_load.PROBE_MAX_STEPS}" in warning[0]


def test_a_dry_run_cut_short_is_no_less_conservative(monkeypatch):
    """The small cloth's dry run (one step per re-estimate, at least as many as its first swing takes: 141) cut a
    few steps past that, and skipped a few steps short of it: ω_max becomes the Gershgorin bound, which holds at
    every state, so the limit is at most the full dry run's, and the message says why."""
    scene = parse_scene(tomllib.loads(CLOTH))
    model = scene.finalize("cpu")
    dt = 1.0 / (scene.fps * scene.substeps)
    monkeypatch.setattr(under_load, "PROBE_PERIODS", 1.0)  # one swing: the dry run then outlasts it (its last rise)
    full = advise(model, "symplectic_euler", dt, fps=scene.fps)
    assert full.dry_run > 0.0 and not full.dry_run_cut_short
    least = math.ceil(max(under_load.PROBE_MIN_TIME, under_load.swing_time(model)) / under_load.PROBE_CHECK)
    assert full.dry_run > (least + 5) * under_load.PROBE_CHECK  # it runs past the budget below
    for budget, reason in ((least + 5, f"it reached its budget of {least + 5} steps"),
                           (least - 5, f"it would take {least} steps")):
        monkeypatch.setattr(under_load, "PROBE_MAX_STEPS", budget)
        cut = advise(model, "symplectic_euler", dt, fps=scene.fps)
        assert cut.dry_run_cut_short.startswith(reason), cut.dry_run_cut_short
        assert cut.omega_source == "Gershgorin bound" and "conservative" in cut.message
        assert cut.omega_max >= full.omega_max and cut.dt_stable <= full.dt_stable
