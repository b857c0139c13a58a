"""The package's layers point one way, read from the source's own imports (no module is imported here).

    kernels → base (errors, checks, version, plotting) → core → io → analysis → app

A module imports only from its own layer or a lower one; no set of modules imports each other in a circle
(imports under ``if TYPE_CHECKING:`` count: a circle a type checker needs is still a circle); and an import
of a warpspring module inside a function is allowed only for an optional dependency, with a comment that
says so (``# optional: ray``). The kernels are a leaf (tests/test_packaging.py checks they import only
``warp`` and each other).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "warpspring"

#: Layers, lowest first: a module may import from its own layer and those before it.
LAYERS = ("kernels", "base", "core", "io", "analysis", "app", "package")
BASE_MODULES = {"warpspring.errors", "warpspring.checks", "warpspring.version", "warpspring.plotting"}
PACKAGE_MODULES = {"warpspring", "warpspring.__main__"}


def layer_of(module: str) -> str:
    """The layer of a dotted module name inside warpspring."""
    if module in PACKAGE_MODULES:
        return "package"
    if module in BASE_MODULES:
        return "base"
    parts = module.split(".")
    if len(parts) >= 2 and parts[1] in LAYERS:
        return parts[1]
    raise AssertionError(f"{module} belongs to no layer: add it to LAYERS or BASE_MODULES in tests/test_layers.py")


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute name that a relative ``from`` import names."""
    if node.level == 0:
        return node.module or ""
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


class Import:
    """One import of a warpspring module: who imports what, where, and whether inside a function."""

    def __init__(self, source: str, target: str, line: int, local: bool, comment: str):
        self.source, self.target, self.line, self.local, self.comment = source, target, line, local, comment

    def __repr__(self) -> str:
        return f"{self.source}:{self.line} -> {self.target}"


def imports_of(module: str, source: str, is_package: bool, known: set[str]) -> list[Import]:
    """Every import of a module in ``known`` made by ``source`` (the text of ``module``)."""
    tree = ast.parse(source)
    lines = source.splitlines()
    found: list[Import] = []

    def add(target: str, node: ast.stmt, local: bool) -> None:
        while target and target not in known:  # `import warpspring.core.x.name` names a module or one above it
            target = target.rpartition(".")[0]
        if target:
            text = lines[node.lineno - 1]
            comment = text.partition("#")[2]
            found.append(Import(module, target, node.lineno, local, comment))

    def visit(node: ast.AST, local: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = local or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                for alias in child.names:
                    if alias.name.split(".")[0] == "warpspring":
                        add(alias.name, child, local)
            elif isinstance(child, ast.ImportFrom):
                target = _resolve(module, is_package, child)
                if target.split(".")[0] != "warpspring":
                    continue
                for alias in child.names:  # `from . import checks` imports the module warpspring.checks
                    sub = f"{target}.{alias.name}"
                    add(sub if sub in known else target, child, local)
            visit(child, inner)

    visit(tree, False)
    return found


def package_imports(root: Path = PACKAGE) -> list[Import]:
    files = {module_name(p, root): p for p in sorted(root.rglob("*.py"))}
    known = set(files)
    edges = []
    for module, path in files.items():
        edges += imports_of(module, path.read_text(), path.name == "__init__.py", known)
    return edges


def upward(edges: list[Import]) -> list[Import]:
    rank = {name: i for i, name in enumerate(LAYERS)}
    return [e for e in edges if rank[layer_of(e.target)] > rank[layer_of(e.source)]]


def circles(edges: list[Import]) -> list[list[str]]:
    """The strongly connected sets of more than one module (Tarjan), and modules that import themselves."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
        graph.setdefault(e.target, set())
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in graph[v]:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return found


def unexplained_local_imports(edges: list[Import]) -> list[Import]:
    return [e for e in edges if e.local and "optional" not in e.comment.lower()]


def test_no_module_imports_from_a_layer_above():
    bad = upward(package_imports())
    assert not bad, "imports from a higher layer (" + " → ".join(LAYERS) + "): " + ", ".join(map(repr, bad))


def test_no_import_circle():
    found = circles(package_imports())
    assert not found, "modules that import each other in a circle: " + "; ".join(" ↔ ".join(c) for c in found)


def test_function_local_imports_are_only_for_optional_dependencies():
    bad = unexplained_local_imports(package_imports())
    assert not bad, ("warpspring modules imported inside functions without an `# optional: <dependency>` comment "
                     "(move them to the top of the module): " + ", ".join(map(repr, bad)))


def test_every_module_has_a_layer():
    for e in package_imports():
        layer_of(e.source), layer_of(e.target)


@pytest.fixture
def fake_package(tmp_path):
    """A small package with one of each fault, to show that the checks above can fail."""
    root = tmp_path / "warpspring"
    for folder in ("core", "io", "analysis", "kernels"):
        (root / folder).mkdir(parents=True)
        (root / folder / "__init__.py").write_text("")
    (root / "__init__.py").write_text("from .core.a import A\n")
    (root / "errors.py").write_text("")
    (root / "core" / "a.py").write_text("from ..io.b import B\nfrom .c import C\n")  # upward: core → io
    (root / "core" / "c.py").write_text("from . import a\n")  # circle a ↔ c
    (root / "io" / "b.py").write_text("def f():\n    from ..analysis import d  # to dodge a cycle\n")
    (root / "analysis" / "d.py").write_text("def g():\n    from ..io import b  # optional: nothing really\n")
    (root / "kernels" / "k.py").write_text("import warp\n")
    return root


def test_the_checks_find_each_fault(fake_package):
    edges = package_imports(fake_package)
    assert sorted((e.source, e.target) for e in upward(edges)) == [
        ("warpspring.core.a", "warpspring.io.b"), ("warpspring.io.b", "warpspring.analysis.d")]
    assert circles(edges) == [["warpspring.analysis.d", "warpspring.io.b"], ["warpspring.core.a", "warpspring.core.c"]]
    assert [(e.source, e.target) for e in unexplained_local_imports(edges)] == [
        ("warpspring.io.b", "warpspring.analysis.d")]
