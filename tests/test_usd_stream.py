"""The USD file while a run writes it and after the run is killed: another process opening it again and again
never fails and never sees the frame count go backwards; a run killed with SIGKILL leaves a valid file with
every frame it wrote and no temporary files; a finished run leaves one self-contained file."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
from pxr import Usd

import warpspring as ws
from warpspring.io.usd import UsdWriter

LINUX = sys.platform.startswith("linux")

# A writer of synthetic frames: frame k moves every particle by k · (1, 2, -3) mm from the start, so a reader
# can check each frame's values. Run as a script: WRITE PATH [START_FRAME].
WRITER = textwrap.dedent("""
    import sys
    import numpy as np
    import warp as wp
    wp.config.quiet = True
    import warpspring as ws
    from warpspring.io.usd import UsdWriter
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=12, ny=12, spacing=0.05, origin=(0.0, 0.0, 1.0), particle_mass=0.01)
    builder.add_ground_plane()
    model = builder.finalize("cpu")
    state = model.state()
    q0 = model.particle_q.numpy().astype(np.float64)
    with UsdWriter(sys.argv[1], model, fps=60, springs=True, primvars=["strain"]) as usd:
        for k in range(int(sys.argv[2])):
            state.particle_q.assign((q0 + k * np.array([1e-3, 2e-3, -3e-3])).astype(np.float32))
            usd.write_frame(state)
""")

# A reader that opens the file OPENS times (a new stage each time), and reports per open the number of frames
# it held and whether the last one had the right values, or the error.
READER = textwrap.dedent("""
    import json, sys
    import numpy as np
    from pxr import Usd
    path, opens, q0 = sys.argv[1], int(sys.argv[2]), np.array(json.loads(sys.argv[3]))
    report = []
    for _ in range(opens):
        try:
            stage = Usd.Stage.Open(path)
            points = stage.GetPrimAtPath("/World/cloth").GetAttribute("points")
            times = points.GetTimeSamples()
            k = len(times)
            good = times == [float(t) for t in range(k)]
            if k:
                q = np.array(points.Get(times[-1]), dtype=np.float64)
                good = good and np.allclose(q, q0 + (k - 1) * np.array([1e-3, 2e-3, -3e-3]), atol=1e-5)
            report.append([k, bool(good)])
            del stage, points
        except Exception as exc:
            report.append([-1, str(exc).splitlines()[0] if str(exc) else type(exc).__name__])
    print(json.dumps(report))
""")


def grid_model() -> ws.Model:
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=12, ny=12, spacing=0.05, origin=(0.0, 0.0, 1.0), particle_mass=0.01)
    builder.add_ground_plane()
    return builder.finalize("cpu")


def frames_held(path) -> list[float]:
    stage = Usd.Stage.Open(str(path))
    return list(stage.GetPrimAtPath("/World/cloth").GetAttribute("points").GetTimeSamples())


def test_a_reader_reopening_the_file_during_a_run_never_fails_nor_goes_back(tmp_path):
    """A second process opens the file 200 times while frames are written: every open succeeds, holds frames
    0..k-1 with the right values in its last frame, and k never decreases; the run ends with one file."""
    model = grid_model()
    q0 = model.particle_q.numpy().astype(np.float64)
    path = tmp_path / "live.usdc"
    state = model.state()
    with UsdWriter(path, model, fps=60, springs=True, primvars=["strain"]) as usd:
        usd.write_frame(state)
        reader = subprocess.Popen([sys.executable, "-c", READER, str(path), "200", json.dumps(q0.tolist())],
                                  stdout=subprocess.PIPE, text=True)
        k = 1
        while reader.poll() is None and k < 5000:
            state.particle_q.assign((q0 + k * np.array([1e-3, 2e-3, -3e-3])).astype(np.float32))
            usd.write_frame(state)
            k += 1
            time.sleep(0.002)  # a run's pace: a frame every few milliseconds
        report = json.loads(reader.communicate(timeout=120)[0])
    assert len(report) == 200
    failures = [entry for entry in report if entry[0] < 0 or entry[1] is not True]
    assert failures == []
    counts = [entry[0] for entry in report]
    assert counts == sorted(counts) and counts[-1] > counts[0] >= 1  # the reader saw the frames grow
    assert frames_held(path) == [float(t) for t in range(k)]
    assert sorted(os.listdir(tmp_path)) == ["live.usdc"]  # packed: one file, no frames folder
    assert Usd.Stage.Open(str(path)).GetRootLayer().subLayerPaths == []


@pytest.mark.skipif(not LINUX, reason="SIGKILL and the companion process are tested on Linux")
def test_a_run_killed_at_any_frame_leaves_every_frame_and_no_temporary_file(tmp_path):
    """SIGKILL at 10 seeded frames: each time the file opens, holds frames 0..m-1 with their values, m at least
    the frames the run had finished writing when it was killed (all but a frame still being added), and beside it
    lie only the file and its frames folder, which holds only frame and chunk layers, the static layer and the
    manifest. Each kill costs a writer process (~1.5 s to start on the CPU, ~2 s in all), so the kill frames are
    drawn by stratum rather than 20 uniformly: 4 before the first chunk of 100 frames is gathered and 6 after,
    across the first and second chunks (the file's two layouts)."""
    rng = random.Random(20261124)
    q0 = grid_model().particle_q.numpy().astype(np.float64)
    held = []
    targets = [rng.randint(1, 99) for _ in range(4)] + [rng.randint(100, 250) for _ in range(6)]
    for trial, target in enumerate(targets):
        folder = tmp_path / f"kill{trial}"
        folder.mkdir()
        path = folder / "out.usdc"
        parts = folder / "out.usdc.frames"
        writer = subprocess.Popen([sys.executable, "-c", WRITER, str(path), "100000"],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and writer.poll() is None:
            done = {n.split(".")[1] for n in os.listdir(parts) if n.startswith("frame.") and n.endswith(".usdc")} \
                if parts.is_dir() else set()  # frame numbers (a frame given its accelerations has a second file)
            if len(done) >= target:
                break
            time.sleep(0.001)
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait()
        assert writer.returncode == -signal.SIGKILL, writer.stderr.read()
        finished = len({n.split(".")[1] for n in os.listdir(parts) if n.startswith("frame.")})
        for _ in range(200):  # the companion process removes USD's temporary files once the run is gone
            names = sorted(os.listdir(folder)) + sorted(os.listdir(parts))
            stray = [n for n in names if not (n in ("out.usdc", "out.usdc.frames", "static.usdc", "manifest.usda")
                                              or (n.startswith(("frame.", "chunk.")) and n.endswith(".usdc")))]
            if not stray:
                break
            time.sleep(0.05)
        assert stray == [], f"kill {trial} at frame {target}"
        times = frames_held(path)
        m = len(times)
        assert times == [float(t) for t in range(m)] and m >= min(target, finished - 1), (trial, target, finished)
        if m:
            stage = Usd.Stage.Open(str(path))
            points = stage.GetPrimAtPath("/World/cloth").GetAttribute("points")
            np.testing.assert_allclose(np.array(points.Get(m - 1)), q0 + (m - 1) * np.array([1e-3, 2e-3, -3e-3]),
                                       atol=1e-5)
        held.append(m)
    assert max(held) > 100  # some kills came after the first chunk of frames was gathered


def test_a_killed_runs_file_can_be_resumed_into(tmp_path):
    """A writer that never closes (its process killed) leaves the clip layout; a new writer keeping its first
    frames (warpspring run --resume) reads them through the frames folder and packs one file with them."""
    model = grid_model()
    q0 = model.particle_q.numpy().astype(np.float64)
    state = model.state()
    path = tmp_path / "killed.usdc"
    step = np.array([1e-3, 2e-3, -3e-3])
    writer = UsdWriter(path, model, fps=60, start_frame=1)
    for k in range(5):
        state.particle_q.assign((q0 + k * step).astype(np.float32))
        writer.write_frame(state)
    writer._reaper.finish()  # as if the process had died here: no close, no packing, the output's lock let go
    writer._lock.release()
    assert (tmp_path / "killed.usdc.frames").is_dir()
    with UsdWriter(path, model, fps=60, start_frame=1, keep_frames=3) as resumed:
        for k in range(3, 6):
            state.particle_q.assign((q0 + k * step + 1e-2).astype(np.float32))  # the resumed run's own frames
            resumed.write_frame(state)
    assert sorted(os.listdir(tmp_path)) == ["killed.usdc"]
    stage = Usd.Stage.Open(str(path))
    points = stage.GetPrimAtPath("/World/cloth").GetAttribute("points")
    assert list(points.GetTimeSamples()) == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    for k in range(6):
        expected = q0 + k * step + (1e-2 if k >= 3 else 0.0)
        np.testing.assert_allclose(np.array(points.Get(1 + k)), expected, atol=1e-6)
