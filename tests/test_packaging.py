"""The wheel ships the top-level kernels/ folder as the warpspring.kernels package."""

import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).parent.parent


def test_wheel_contains_every_kernels_module(tmp_path):
    """Building the wheel maps kernels/*.py to warpspring/kernels/*.py and includes every subpackage."""
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-w", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    (wheel,) = tmp_path.glob("warpspring-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    kernels = {p.relative_to(ROOT).as_posix() for p in (ROOT / "kernels").rglob("*.py")}
    assert kernels, "no kernel sources found"
    for source in kernels:
        assert "warpspring/" + source in names, f"{source} missing from the wheel"
    for source in (ROOT / "warpspring").rglob("*.py"):
        assert source.relative_to(ROOT).as_posix() in names
    assert not any(n.startswith(("kernels/", "tests/")) for n in names)
    entry_points = next(n for n in names if n.endswith("entry_points.txt"))
    assert "warpspring = warpspring.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()
