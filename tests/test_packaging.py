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


def test_kernels_come_from_the_same_checkout(tmp_path):
    """A second copy of the sources, run from its own folder while this checkout is installed (editable),
    imports its own kernels/, never this checkout's: both ``warpspring`` and ``warpspring.kernels`` resolve
    inside the copy. A marker in the copy's kernels tells the two apart."""
    import shutil

    copy = tmp_path / "other_checkout"
    shutil.copytree(ROOT / "warpspring", copy / "warpspring", ignore=shutil.ignore_patterns("__pycache__", "kernels"))
    shutil.copytree(ROOT / "kernels", copy / "kernels", ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "kernels" / "__init__.py").write_text((ROOT / "kernels" / "__init__.py").read_text() + "\nCOPY = True\n")
    probe = (
        "import warpspring, warpspring.kernels as k, warpspring.kernels.forces as f; "
        "print(warpspring.__file__); print(k.__file__); print(f.__file__); print(getattr(k, 'COPY', False))"
    )
    result = subprocess.run([sys.executable, "-c", probe], cwd=copy, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    package, kernels, forces, marker = result.stdout.split()
    for path in (package, kernels, forces):
        assert Path(path).resolve().is_relative_to(copy.resolve()), path
    assert marker == "True"


def test_missing_kernels_are_a_clear_import_error(tmp_path):
    """A copy of the package without its kernels fails to import with a message that says what is missing
    and how to fix it (instead of falling back to another checkout's kernels)."""
    import shutil

    copy = tmp_path / "broken"
    shutil.copytree(ROOT / "warpspring", copy / "warpspring", ignore=shutil.ignore_patterns("__pycache__", "kernels"))
    result = subprocess.run([sys.executable, "-c", "import warpspring"], cwd=copy, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode != 0
    assert "warpspring's kernels are missing" in result.stderr and "pip install -e ." in result.stderr
