"""docs/architecture.md stays true: every file its layout names exists, every module of the package appears in
the layout, and every code name it cites (``Simulator.reset``, ``kernels/inputs.py``, ``eval_forces``) is a
name the code defines. Read from the sources' AST; nothing is imported."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import warp as wp

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "architecture.md"
IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*(\(\))?$")
PATH = re.compile(r"^[\w./-]+\.(py|md|toml|json|usda|usdc|png)$")
#: Words set in code type that are values or keywords, not names the code defines.
NOT_NAMES = {"True", "False", "None", "float32", "float64", "cpu", "cuda", "auto", "inf", "nan"}
#: Modules of other libraries whose names the page cites (``wp.Mesh``, ``ray.put``): checked against the library.
EXTERNAL = {"wp": "warp", "warp": "warp", "np": "numpy", "ray": None, "trimesh": None, "pxr": None, "Usd": None}


def defined_names() -> set[str]:
    """Every name the package, its tests and its benchmarks define: modules, classes, functions, methods,
    parameters, assignments and attributes."""
    names: set[str] = set()
    for folder in ("warpspring", "tests", "bench", "tools", "examples"):
        for path in (ROOT / folder).rglob("*.py"):
            if path.resolve() == Path(__file__).resolve():
                continue  # this file's own made-up names
            names.add(path.stem)
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    names.add(node.name)
                elif isinstance(node, ast.arg):
                    names.add(node.arg)
                elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                    names.add(node.id)
                elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
                    names.add(node.attr)
                elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "wp":
                    names.add(f"wp.{node.attr}")  # Warp's kernel builtins are no module attributes
                elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                    names.add(node.target.id)
                elif isinstance(node, ast.keyword) and node.arg:
                    names.add(node.arg)
                elif isinstance(node, ast.Constant) and isinstance(node.value, str) and IDENTIFIER.match(node.value):
                    names.add(node.value)  # names of scene keys, inputs and families live in strings
    return names


def external_name_exists(module: str | None, parts: list[str]) -> bool:
    """Whether ``module.parts`` exists (an optional library the page cites, not installed here, passes)."""
    if module is None:
        return True
    value = importlib.import_module(module)
    for part in parts:
        if not hasattr(value, part):
            return False
        value = getattr(value, part)
    return True


def layout_block(text: str) -> str:
    """The layout's tree: the first code block after "## Layout" that starts at ``warpspring/``."""
    position = text.index("## Layout")
    while True:
        opening = text.index("```", position) + 3
        closing = text.index("```", opening)
        if text[opening:closing].lstrip("\n").startswith("warpspring/"):
            return text[opening:closing]
        position = closing + 3


def layout_files(block: str) -> list[Path]:
    """The files and folders the layout names, each under the folder its indentation puts it in."""
    found, stack = [], []  # stack of (indent, folder)
    for line in block.splitlines():
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        entry = line.strip().split("  ")[0].strip()
        while stack and stack[-1][0] >= indent:
            stack.pop()
        parent = Path(*(folder for _, folder in stack)) if stack else Path()
        for name in (n.strip() for n in entry.split(",")):
            if re.match(r"^[\w./-]+$", name) and (name.endswith((".py", "/"))):
                found.append(parent / name)
        if entry.endswith("/"):
            stack.append((indent, entry.rstrip("/")))
    return found


def test_every_file_in_the_layout_exists():
    missing = [str(p) for p in layout_files(layout_block(DOC.read_text())) if not (ROOT / p).exists()]
    assert not missing, f"docs/architecture.md's layout names files that do not exist: {missing}"


def test_every_module_is_in_the_layout():
    named = {p.as_posix().rstrip("/") for p in layout_files(layout_block(DOC.read_text()))}
    modules = [p.relative_to(ROOT).as_posix() for p in (ROOT / "warpspring").rglob("*.py") if p.name != "__init__.py"]
    absent = [m for m in modules if m not in named and not any(m.startswith(folder + "/") and folder.count("/") >= 2
                                                             for folder in named)]
    assert not absent, f"modules missing from docs/architecture.md's layout: {absent}"


def test_every_cited_name_exists():
    text = DOC.read_text()
    names = defined_names()
    unknown = []
    for token in sorted(set(re.findall(r"`([^`\n]+)`", text))):
        token = token.strip()
        if PATH.match(token) and ("/" in token or token.endswith((".py", ".md"))):
            candidates = [ROOT / token, ROOT / "warpspring" / token]
            if not any(c.exists() for c in candidates):
                unknown.append(token)
        elif IDENTIFIER.match(token) and token not in NOT_NAMES and not PATH.match(token):
            parts = token.removesuffix("()").split(".")
            if parts[0] in EXTERNAL:
                if token.removesuffix("()") not in names and not external_name_exists(EXTERNAL[parts[0]], parts[1:]):
                    unknown.append(token)
            elif not all(part in names or hasattr(wp, part) for part in parts):
                unknown.append(token)
    assert not unknown, f"docs/architecture.md cites names the code does not define: {unknown}"


def test_the_check_can_fail():
    """A made-up name and a made-up file are reported (the checks above are not vacuous)."""
    names = defined_names()
    assert "Simulator" in names and "NoSuchThing" not in names
    assert layout_files("warpspring/\n  core/\n    a.py, b.py   text\n") == [
        Path("warpspring"), Path("warpspring/core"), Path("warpspring/core/a.py"), Path("warpspring/core/b.py")]
