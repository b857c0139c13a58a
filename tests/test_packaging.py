"""The wheel ships every module of the package, its kernels (``warpspring/kernels/``) among them, and a copy of
the sources run from its own folder imports itself, never the installed checkout."""

import ast
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).parent.parent


def test_wheel_contains_every_module(tmp_path):
    """Building the wheel includes every module under ``warpspring/`` (the kernels too) and nothing else."""
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-w", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    (wheel,) = tmp_path.glob("warpspring-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    sources = {p.relative_to(ROOT).as_posix() for p in (ROOT / "warpspring").rglob("*.py")}
    assert any(s.startswith("warpspring/kernels/") for s in sources), "no kernel sources found"
    for source in sources:
        assert source in names, f"{source} missing from the wheel"
    assert "warpspring/analysis/trade_table.json" in names  # package data: the trade table auto reads
    assert not any(n.startswith(("kernels/", "tests/", "bench/")) for n in names)
    entry_points = next(n for n in names if n.endswith("entry_points.txt"))
    assert "warpspring = warpspring.app.cli:main" in zipfile.ZipFile(wheel).read(entry_points).decode()


def test_a_copy_imports_its_own_kernels(tmp_path):
    """A second copy of the sources, run from its own folder while this checkout is installed (editable),
    imports its own package and kernels, never this checkout's. A marker in the copy's kernels tells the two
    apart."""
    import shutil

    copy = tmp_path / "other_checkout"
    shutil.copytree(ROOT / "warpspring", copy / "warpspring", ignore=shutil.ignore_patterns("__pycache__"))
    init = copy / "warpspring" / "kernels" / "__init__.py"
    init.write_text(init.read_text() + "\nCOPY = True\n")
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


def test_kernels_are_a_leaf():
    """``warpspring/kernels/`` imports only ``warp`` and its sibling modules (replaces the test of the removed
    sibling-folder binding: the kernels now live inside the package)."""
    allowed_roots = {"warp", "functools", "math", "dataclasses", "typing", "__future__", "enum", "itertools",
                     "collections", "ast", "inspect", "textwrap", "types", "linecache", "hashlib", "weakref"}
    offenders = []
    for path in sorted((ROOT / "warpspring" / "kernels").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level == 0 and node.module.split(".")[0] not in allowed_roots:
                    offenders.append(f"{path.name}: from {node.module}")
                if node.level > 1:
                    offenders.append(f"{path.name}: from {'.' * node.level}{node.module or ''}")
            elif isinstance(node, ast.Import):
                offenders += [f"{path.name}: import {a.name}" for a in node.names
                              if a.name.split(".")[0] not in allowed_roots]
    assert not offenders, "the kernels import outside warp and their siblings: " + ", ".join(offenders)
