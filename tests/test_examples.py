"""Every example script runs end to end for a couple of frames and writes a USD file."""

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).parent.parent / "examples").glob("*.py"))


@pytest.mark.parametrize("script", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs(script, tmp_path):
    """``python examples/X.py --num-frames 2`` exits 0 and writes 3 frames (initial + 2) to USD."""
    from pxr import Usd

    stage_path = tmp_path / f"{script.stem}.usdc"
    result = subprocess.run(
        [sys.executable, str(script), "--device", "cpu", "--num-frames", "2", "--stage-path", str(stage_path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stderr
    assert "t = 0.03 s" in result.stdout
    stage = Usd.Stage.Open(str(stage_path))
    mesh = next(p for p in stage.Traverse() if p.GetTypeName() == "Mesh" and "colliders" not in str(p.GetPath()))
    assert mesh.GetAttribute("points").GetTimeSamples() == [0.0, 1.0, 2.0]
