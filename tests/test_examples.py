"""Every example script runs end to end for a couple of frames and writes a USD file."""

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).parent.parent / "examples").glob("*.py"))


@pytest.mark.parametrize("script", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs(script, tmp_path):
    """``python examples/X.py --num-frames 2`` exits 0, prints its one line and nothing of Warp's, and writes 3 frames
    (initial + 2) to USD."""
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
    # Quiet: the example's own line only, no Warp banner, module-load lines or CUDA-driver warning.
    assert result.stdout.strip().count("\n") == 0 and result.stderr == "", (result.stdout, result.stderr)
    stage = Usd.Stage.Open(str(stage_path))
    mesh = next(p for p in stage.Traverse() if p.GetTypeName() == "Mesh" and "colliders" not in str(p.GetPath()))
    assert mesh.GetAttribute("points").GetTimeSamples() == [0.0, 1.0, 2.0]


SOFT_BODY_SCENES = ("soft_ball", "jelly_cube", "voxel_torus", "plastic_bar")


@pytest.mark.parametrize("name", SOFT_BODY_SCENES)
def test_soft_body_scene_exports_valid_usd(name, tmp_path):
    """``warpspring run examples/X.toml --frames 1`` (in process): the soft body's authored surface is written at
    2 time samples, moved by the run and finite, and every registered pxr.UsdValidation validator passes."""
    import numpy as np
    from pxr import Usd, UsdGeom, UsdValidation

    from warpspring.app.cli import main

    out = tmp_path / f"{name}.usdc"
    assert main(["run", str(Path(__file__).parent.parent / "examples" / f"{name}.toml"), "-o", str(out),
                 "--frames", "1", "--device", "cpu"]) == 0
    stage = Usd.Stage.Open(str(out))
    skins = [UsdGeom.Mesh(p) for p in stage.Traverse()
             if p.GetTypeName() == "Mesh" and "colliders" not in str(p.GetPath())]
    assert skins
    for mesh in skins:
        points = mesh.GetPointsAttr()
        assert points.GetTimeSamples() == [0.0, 1.0]
        first, last = (np.asarray(points.Get(t), dtype=np.float64) for t in (0.0, 1.0))
        assert np.isfinite(last).all() and np.abs(last - first).max() > 0.0
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert [e.GetMessage() for e in UsdValidation.ValidationContext(validators).Validate(stage)] == []
