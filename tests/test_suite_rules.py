"""The suite's own rules, read from its sources: no test module imports another test module or a bench
script (shared code lives in tests/helpers.py and tests/conftest.py, or in the package), and no test reads a
committed results file (bench/results/, bench/RESULTS.md): a test computes what it asserts on."""

from __future__ import annotations

import ast
import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
SHARED = {"helpers", "conftest"}


def imported_modules(source: str) -> list[tuple[int, str]]:
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
    return found


def offences(path: Path, test_modules: set[str], bench_modules: set[str]) -> list[str]:
    source = path.read_text()
    bad = []
    for line, module in imported_modules(source):
        top = module.split(".")[0]
        if top in test_modules and top not in SHARED:
            bad.append(f"{path.name}:{line} imports the test module {top}")
        if top in bench_modules or top == "bench":
            bad.append(f"{path.name}:{line} imports the bench script {module}")
    for match in re.finditer(r"sys\.path\.(insert|append)\([^)]*bench", source):
        bad.append(f"{path.name}: puts bench/ on sys.path ({match.group(0)})")
    for match in re.finditer(r"""["'](bench/(results/[^"'{}]+|RESULTS\.md))["']""", source):  # {…}: a docs check
        bad.append(f"{path.name}: reads the committed results file {match.group(1)}")
    return bad


def test_no_test_imports_another_test_or_a_bench_script():
    test_modules = {p.stem for p in TESTS.glob("*.py")}
    bench_modules = {p.stem for p in (ROOT / "bench").glob("*.py")}
    bad = [o for p in sorted(TESTS.glob("test_*.py")) if p.name != Path(__file__).name
           for o in offences(p, test_modules, bench_modules)]
    assert not bad, "; ".join(bad)


def test_the_rule_finds_each_offence(tmp_path):
    """A made-up test module with each offence is reported (the check above is not vacuous)."""
    fake = tmp_path / "test_fake.py"
    fake.write_text("import sys\nfrom test_cli import SCENE\nimport cloth\nfrom helpers import CUDA\n"
                    "sys.path.insert(0, str(ROOT / 'bench'))\nopen('bench/results/advisor.md')\n")
    found = offences(fake, {"test_cli", "helpers"}, {"cloth"})
    assert len(found) == 4 and not any("helpers" in o for o in found), found
