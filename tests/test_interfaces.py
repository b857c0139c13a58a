"""The interfaces around a run: spring families given as a scene file gives them, output errors with their
reasons, a full disk mid-run (exit 4, every frame before it kept), no CUDA-driver warning on a CPU run, the
stability report in a file with a short summary, and `warpspring choose`'s exit status.

CLI runs go through ``warpspring.app.cli.main`` in-process with ``tests/test_cli.py``'s scene (the hanging-cloth
feature set, so its compiled kernels are shared); one test runs the real ``python -m warpspring``.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from pxr import Sdf, Tf, Usd

import warpspring as ws
from helpers import points_samples, write_scene
from warpspring.app.cli import EXIT_CONFIG, EXIT_IO, EXIT_NO_CHOICE, main, os_error_line
from warpspring.core.builder.spring_materials import DEFAULT_SHEAR, spring_family
from warpspring.io import usd as usd_module
from warpspring.io.scene import load_scene
from warpspring.io.usd import UsdWriter
from warpspring.io.usd_stream import check_output_path

LINUX = sys.platform.startswith("linux")


def springs_of(builder: ws.ModelBuilder) -> tuple:
    """The springs a builder holds: pairs, ke and kd (sorted by pair), for comparing two ways of making them."""
    model = builder.finalize("cpu")
    pairs = model.spring_indices.numpy().reshape(-1, 2)
    order = np.lexsort(pairs.T[::-1])
    return (pairs[order], model.spring_stiffness.numpy()[0][order], model.spring_damping.numpy()[0][order])


def api_builder(**families) -> ws.ModelBuilder:
    """helpers.SCENE (the CLI tests' scene) through the API, with ``families`` replacing its spring families."""
    builder = ws.ModelBuilder(drag=0.002)
    options = dict(structural=ws.SpringMaterial(40.0, 0.01), shear=ws.SpringMaterial(10.0, 0.01),
                   bend=ws.SpringMaterial(1.0, 0.001))
    options.update(families)
    builder.add_cloth_grid(nx=5, ny=5, spacing=0.1, origin=(0.0, 0.0, 1.0), mass=0.25, pin=["top-left", "top-right"],
                           **options)
    builder.add_ground_plane()
    return builder


# -- spring families: what a scene file takes, the API takes --------------------------------------------------


@pytest.mark.parametrize("family", ["structural", "shear", "bend"])
def test_a_family_switched_off_equals_the_scene_files_false(tmp_path, family):
    """``add_cloth_grid(shear=False)`` (once an AttributeError) builds what ``shear = false`` in a scene does."""
    line = {"structural": "structural = { ke = 40.0, kd = 0.01 }", "shear": "shear = { ke = 10.0, kd = 0.01 }",
            "bend": "bend = { ke = 1.0, kd = 0.001 }"}[family]
    scene = load_scene(str(write_scene(tmp_path, {line: f"{family} = false"})))
    from_file = springs_of(scene.builder())
    for off in (False, None):
        for a, b in zip(springs_of(api_builder(**{family: off})), from_file):
            np.testing.assert_array_equal(a, b)
    full = springs_of(api_builder())
    assert len(from_file[0]) < len(full[0])


def test_a_family_as_a_table_or_true_equals_the_scene_file(tmp_path):
    """A mapping {"ke", "kd"} (kd defaulting to the family's default) and True (the default family) as in a
    scene file; anything else is a ConfigError naming the family."""
    text = {"shear = { ke = 10.0, kd = 0.01 }": "shear = { ke = 10.0 }", "bend = { ke = 1.0, kd = 0.001 }": "bend = true"}
    from_file = springs_of(load_scene(str(write_scene(tmp_path, text))).builder())
    from_api = springs_of(api_builder(shear={"ke": 10.0}, bend=True))
    for a, b in zip(from_api, from_file):
        np.testing.assert_array_equal(a, b)
    assert spring_family("shear", {"ke": 10.0}, DEFAULT_SHEAR) == ws.SpringMaterial(10.0, DEFAULT_SHEAR.kd)
    assert spring_family("bend", {"kd": 0.5}, DEFAULT_SHEAR) == ws.SpringMaterial(DEFAULT_SHEAR.ke, 0.5)
    for bad, words in ((1.5, "shear springs must be"), ({"k": 1.0}, "unknown key 'k'"), ({"ke": -1.0}, "shear spring ke")):
        with pytest.raises(ws.ConfigError, match=words):
            api_builder(shear=bad)
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.1, mass=0.1, dihedral=False)  # as None: no hinges
    assert builder.finalize("cpu").hinge_count == 0


# -- output errors carry their reason -------------------------------------------------------------------------


@pytest.mark.skipif(not LINUX, reason="/proc is Linux's")
def test_an_unwritable_output_names_the_reason(tmp_path, capsys, monkeypatch):
    """An output under /proc: refused before the model is built, one line with the OS's reason, also where the
    writer itself fails to create its files. Where USD fails without a word, the message says so, and nothing
    of the failed writer is left behind."""
    with pytest.raises(ws.ConfigError, match=r"cannot be written: cannot create a file in /proc: \S.* \[E[A-Z]+\]$"):
        check_output_path("/proc/out.usdc")
    assert main(["run", str(write_scene(tmp_path)), "-o", "/proc/out.usdc", "--device", "cpu"]) == EXIT_CONFIG
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and re.search(r"cannot be written: .*: \S+", lines[0]), lines

    model = api_builder().finalize("cpu")
    monkeypatch.setattr(usd_module, "check_output_path", lambda path: os.fspath(path))
    with pytest.raises(ws.ConfigError, match=r"^cannot create the USD file '/proc/out.usdc': \S.* \[E[A-Z]+\]$"):
        UsdWriter("/proc/out.usdc", model, fps=60)  # the frames folder cannot be made: the OS's reason

    def silent(self, layer, path):
        raise Tf.ErrorException()  # str() is "\n\t": the empty reason of the report

    monkeypatch.setattr(UsdWriter, "_export", silent)
    out = tmp_path / "silent.usdc"
    with pytest.raises(ws.ConfigError, match=r"^cannot create the USD file '.*silent.usdc': USD gave no reason$"):
        UsdWriter(out, model, fps=60)
    assert not out.exists() and not (tmp_path / "silent.usdc.frames").exists()  # nothing of it is left behind


def test_os_errors_are_one_line_with_their_reason():
    """Every OS error the CLI prints carries a reason: the OS's words with the errno name and the file, or the
    error's own text, never an empty string."""
    assert os_error_line(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "out.usdc")) == (
        "No space left on device [ENOSPC]: out.usdc")
    assert os_error_line(OSError(errno.EROFS, os.strerror(errno.EROFS))) == "Read-only file system [EROFS]"
    assert os_error_line(OSError("cannot save\n the file")) == "cannot save the file"
    assert os_error_line(OSError()) == "OSError (no reason given)"
    error = ws.OutputError("cannot write frame 3 to the USD file 'x.usdc': why", path="x.usdc", frame=3,
                           code=errno.ENOSPC)
    assert os_error_line(error) == str(error) and error.errno == errno.ENOSPC and isinstance(error, OSError)


def test_a_full_disk_mid_run_exits_4_and_keeps_every_frame_before(tmp_path, capsys, monkeypatch):
    """The disk fills up while frame k is saved: exit 4, one line naming frame k and the reason, and the file on
    disk is a valid stage with frames 0..k-1 exactly (nothing of frame k, no save on close)."""
    k = 3
    save = UsdWriter._save_layer

    def full_disk(self):
        if self.frame_count - 1 == k:  # frame_count counts the frame being saved
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return save(self)

    monkeypatch.setattr(UsdWriter, "_save_layer", full_disk)
    out = tmp_path / "full.usdc"
    assert main(["run", str(write_scene(tmp_path)), "-o", str(out), "--device", "cpu", "--frames", "5"]) == EXIT_IO
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == (f"warpspring: output failed: cannot write frame {k} to the USD file {str(out)!r}: No space "
                            f"left on device [ENOSPC]; the file holds frames 0..{k - 1}\n")
    assert Sdf.Layer.Find(str(out)) is None  # the unsaved layer is gone: the stage below is read from disk
    samples, times, _ = points_samples(out)
    assert times == [float(f) for f in range(k)]
    assert all(np.isfinite(s).all() for s in samples)
    stage = Usd.Stage.Open(str(out))
    assert stage.GetEndTimeCode() == k - 1 and stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")


def test_a_failed_save_without_a_reason_is_diagnosed(tmp_path):
    """USD refusing to save without a word: the writer looks at the file system (here: the folder is gone) and
    says so; writing goes no further."""
    model = api_builder().finalize("cpu")
    folder = tmp_path / "gone"
    folder.mkdir()
    writer = UsdWriter(folder / "x.usdc", model, fps=60)
    writer.write_frame(model.state())
    writer._save_layer = lambda: False  # USD's Export() returning False
    shutil.rmtree(folder)
    with pytest.raises(ws.OutputError, match=r"cannot write frame 1 .*: its folder .*gone does not exist; the file "
                                             r"holds frame 0$") as caught:
        writer.write_frame(model.state())
    assert caught.value.frame == 1 and caught.value.frames_saved == 1
    writer.close()  # closed already: nothing more is saved
    with pytest.raises(RuntimeError, match="closed"):
        writer.write_frame(model.state())


def test_a_failed_allocation_in_a_run_is_one_line(tmp_path, capsys, monkeypatch):
    """Warp's "Failed to allocate" while the run sets up (the integrator's or the simulator's buffers) ends with
    one line and exit 2, not a traceback."""
    import warpspring.app.runner as runner

    def no_memory(*args, **kwargs):
        raise RuntimeError("Failed to allocate 1234567 bytes on device 'cuda:0'")

    monkeypatch.setattr(runner, "Simulator", no_memory)
    assert main(["run", str(write_scene(tmp_path)), "-o", str(tmp_path / "x.usdc"), "--device", "cpu"]) == EXIT_CONFIG
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("warpspring: error: out of memory: Failed to allocate 1234567")


# -- no CUDA-driver warning on the CPU ----------------------------------------------------------------------


def test_a_cpu_run_prints_no_cuda_driver_warning(tmp_path):
    """`python -m warpspring run ... --device cpu` on this machine: no "CUDA driver" line (Warp prints one at
    initialisation where no NVIDIA driver exists), and the run's own output as usual."""
    scene, out = write_scene(tmp_path), tmp_path / "cpu.usdc"
    command = [sys.executable, "-m", "warpspring", "run", str(scene), "-o", str(out), "--device", "cpu", "--frames", "1"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "CUDA driver" not in done.stderr + done.stdout
    assert done.stderr == "" and done.stdout.startswith("wrote 2 frames ")


# -- the stability report and choose -----------------------------------------------------------------------


def fake_map(plan, device, integrators=None):
    """A small stability map, as ``run_map`` returns it (the real one takes a minute)."""
    from warpspring.analysis.stability_map import Bracket, ClothLimit, SpringLimit, StabilityMap

    springs = [SpringLimit("symplectic_euler", 0.0, 2.0, Bracket(1.996, 1.998, 12), 4096),
               SpringLimit("symplectic_euler", 0.01, 2.0, Bracket(2.0, 2.002, 12), 4096),
               SpringLimit("rk4", 0.0, 2.828, Bracket(2.830, 2.832, 12), 4096)]
    cloth = [ClothLimit("symplectic_euler", k, 3.0 * k**0.5, 0.66 / k**0.5, Bracket(0.655 / k**0.5, 0.665 / k**0.5, 9),
                        2048) for k in (1e2, 1e4)]
    k = np.geomspace(1e2, 1e4, 5)
    return StabilityMap(plan=plan, device=str(device), springs=springs, cloth=cloth,
                        predictions={"symplectic_euler": (k, 0.66 / np.sqrt(k))}, timings={"spring": 0.1, "cloth": 0.2},
                        date="2026-01-01")


def test_stability_writes_its_report_to_a_file_and_prints_a_summary(tmp_path, capsys, monkeypatch):
    """`warpspring stability`: the ~100-line Markdown report goes to OUT/stability.md (and --report PATH), the
    terminal gets a few lines naming it."""
    import warpspring.analysis.stability_map as stability_map

    monkeypatch.setattr(stability_map, "run_map", fake_map)
    out, report = tmp_path / "stability", tmp_path / "notes" / "report.md"
    report.parent.mkdir()
    assert main(["stability", "--device", "cpu", "--out", str(out), "--report", str(report)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert len(printed) <= 5 and not any(line.startswith("|") for line in printed)
    assert "measured / predicted 0.9985 … 1.0011 over 3 cases (theory)" in printed[1]
    assert printed[-1].startswith(f"full report: {report}; also wrote {out / 'stability.md'}")
    for path in (report, out / "stability.md"):
        text = path.read_text()
        assert text.startswith("# Stability map") and "| symplectic_euler | 0 |" in text
    assert main(["stability", "--device", "cpu", "--out", str(out), "--report", str(tmp_path / "no" / "r.md")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_choose_exits_non_zero_when_nothing_meets_the_budget(tmp_path, capsys):
    """`warpspring choose`: 0 with a measured configuration within the error and the budget; 5 when nothing
    measured meets both (it still names the closest); 2 for a bad study file."""
    from warpspring.analysis.trade import Measurement
    from warpspring.analysis.trade_report import write_csv

    def row(integrator, wall, error, dt):
        return Measurement(problem="cloth", integrator=integrator, order=1, precision="float32", device="cpu", dt=dt,
                           tolerance=None, steps_per_second=1.0 / dt, mean_step=dt, wall_per_second=wall,
                           status="ok", error_max=error)

    study = write_csv([row("symplectic_euler", 1e-3, 1e-3, 1e-3), row("rk4", 4e-3, 1e-6, 2e-3)],
                      str(tmp_path / "trade.csv"))
    assert main(["choose", "--error", "1e-2", "--study", study]) == 0
    assert "symplectic_euler" in capsys.readouterr().out
    assert main(["choose", "--error", "1e-5", "--budget", "5e-3", "--study", study]) == 0
    assert main(["choose", "--error", "1e-5", "--budget", "1e-3", "--study", study]) == EXIT_NO_CHOICE
    assert "No measured configuration" in capsys.readouterr().out
    assert main(["choose", "--error", "1e-9", "--study", study]) == EXIT_NO_CHOICE  # beyond every measurement
    assert main(["choose", "--error", "1e-3", "--study", str(tmp_path / "missing.csv")]) == EXIT_CONFIG



def test_stability_runs_the_advisor_battery_on_request(tmp_path, capsys, monkeypatch):
    """`warpspring stability --battery hanging --quick --integrators rk4`: a line per case, a summary with the
    ratio and the unsafe count (0), and the table in OUT/battery.md; an unknown scene is refused at once."""
    import warpspring.analysis.stability_map as stability_map

    monkeypatch.setattr(stability_map, "run_map", fake_map)
    out = tmp_path / "stability"
    assert main(["stability", "--device", "cpu", "--out", str(out), "--quick", "--integrators", "rk4",
                 "--battery", "hanging"]) == 0
    printed = capsys.readouterr().out
    assert "  battery: | hanging | rk4 | 1/60 s |" in printed
    assert ", 0 passed world(s) blew up" in printed
    table = (out / "battery.md").read_text()
    assert table.startswith("# The advisor under load") and "| hanging | rk4 | 1/60 s |" in table
    assert main(["stability", "--device", "cpu", "--out", str(out), "--battery", "gusty"]) == 2
    assert "unknown battery scene 'gusty'" in capsys.readouterr().err
