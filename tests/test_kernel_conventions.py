"""Kernel parameter conventions, checked from the source (AST only: nothing is compiled or imported).

Every ``@wp.kernel`` and ``@flat_kernel`` in ``warpspring/kernels/``, at module level or made inside a factory
(kernels are made with these decorators: a ``wp.kernel(f)`` call would escape the check, so it is reported):

* **Written parameters end in ``_out``, read-only ones do not.** A parameter (an array, or a struct of arrays)
  is written when the kernel stores into it (``a[i] = …``, ``a[i] += …``, ``a[i][j] = …``, ``s.field[i] = …``
  for a struct ``s``), makes it the target of an ``atomic_*`` or ``tile_store`` call, or passes it (or one of its fields) to a
  ``@wp.func`` of the package that writes that argument, followed through the funcs it calls in turn. A func
  is followed where its name resolves statically: a ``def`` in scope, a sibling-module import, or a name
  bound to what a factory returns (an item of its tuple, a field of its NamedTuple); a call the analysis
  cannot follow to a func of the name of one that writes its arguments is itself reported. Calls through a
  family's hooks are not followed (the family protocol's hooks only gather). A read-and-written parameter
  is named ``…_in_out`` (or ``…_out``). Writes into a memo field (``MEMO_FIELDS``: the mesh colliders'
  candidate cache ``Shapes.cache``, which changes the work and never the answer) do not make the struct
  holding it an output.
* **Parameters grouped by role, inputs first.** A kernel of more than ``UNGROUPED_MAX`` parameters opens
  its parameter list with a full-line comment header (``# Model:``, ``# State in:``, ``# Control:``,
  ``# Out:`` …) and every parameter falls under one; an output group (a header with the word "out":
  ``# Out:``, ``# State out:``, ``# In/out:``) holds exactly the ``_out`` parameters and no input group
  follows one. Without headers (short kernels), ``_out`` parameters still come after all others.
"""
from __future__ import annotations

import ast
import pathlib
import re

KERNELS = pathlib.Path(__file__).resolve().parents[1] / "warpspring" / "kernels"
PACKAGE = "warpspring.kernels"

UNGROUPED_MAX = 3  # a kernel with more parameters than this needs group headers
MEMO_FIELDS = frozenset({"cache"})  # struct fields whose writes are a memo, not an output
HEADER = re.compile(r"^\s*#\s*([A-Za-z][^#:]*):\s*$")
OUT_GROUP = re.compile(r"\bout\b", re.IGNORECASE)
WRITTEN_SUFFIX = "_out"


def _decorator_name(node: ast.expr) -> str:
    """``wp.kernel`` / ``flat_kernel`` / ``wp.func`` of a decorator, with or without a call."""
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.Name):
        return node.id
    return ""


def _is_kernel(node: ast.FunctionDef) -> bool:
    return any(_decorator_name(d) in ("kernel", "flat_kernel") for d in node.decorator_list)


def _is_func(node: ast.FunctionDef) -> bool:
    return any(_decorator_name(d) == "func" for d in node.decorator_list)


def _chain(node: ast.expr):
    """(root name, attribute names, whether it passes a subscript) of ``a.b[i].c[j]``-like expressions, or
    None when the chain does not start at a plain name."""
    attributes, subscripted = [], False
    while True:
        if isinstance(node, ast.Subscript):
            subscripted = True
            node = node.value
        elif isinstance(node, ast.Attribute):
            attributes.append(node.attr)
            node = node.value
        elif isinstance(node, ast.Name):
            return node.id, attributes[::-1], subscripted
        else:
            return None


class Module:
    """One parsed source file: its functions, each with its enclosing scope, and every scope's bindings."""

    def __init__(self, name: str, source: str, filename: str, package: "Package | None" = None):
        self.name, self.source, self.filename, self.package = name, source, filename, package
        self.lines = source.splitlines()
        self.tree = ast.parse(source, filename)
        self.parent: dict[ast.AST, ast.AST] = {}  # function -> enclosing function or the module
        self.bindings: dict[ast.AST, dict[str, tuple]] = {}
        self._scan(self.tree)

    def _scan(self, scope: ast.AST) -> None:
        bindings = self.bindings.setdefault(scope, {})
        if isinstance(scope, ast.FunctionDef):  # a parameter shadows outer names (a factory's ``entry``)
            bindings.update({a.arg: ("parameter",) for a in scope.args.args + scope.args.kwonlyargs})
        for node in self._own_nodes(scope):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                bindings[node.name] = ("def", node)
                if not isinstance(node, ast.ClassDef):
                    self.parent[node] = scope
                    self._scan(node)
            elif isinstance(node, ast.ImportFrom) and scope is self.tree:
                for alias in node.names:
                    bindings[alias.asname or alias.name] = ("import", node.level, node.module, alias.name)
            elif isinstance(node, ast.Assign):
                for target in node.targets:
                    if isinstance(target, ast.Name):
                        bindings[target.id] = ("value", node.value, None)
                    elif isinstance(target, (ast.Tuple, ast.List)):
                        for k, element in enumerate(target.elts):
                            if isinstance(element, ast.Name):
                                bindings[element.id] = ("value", node.value, k)

    @staticmethod
    def _own_nodes(scope: ast.AST):
        """The statements of a scope, nested blocks included, not descending into functions or classes."""
        stack = list(scope.body)
        while stack:
            node = stack.pop(0)
            yield node
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                continue
            for field in ("body", "orelse", "finalbody", "handlers"):
                stack.extend(getattr(node, field, []) or [])

    def kernels(self) -> list[ast.FunctionDef]:
        return [node for node in self.parent if isinstance(node, ast.FunctionDef) and _is_kernel(node)]

    # -- name resolution -------------------------------------------------------------------------------------

    def resolve(self, name: str, scope: ast.AST, depth: int = 0) -> list:
        """Every (module, FunctionDef) a name may mean in ``scope``, following sibling imports and what factories
        return (each ``return`` of a factory is a candidate); empty if it cannot be told statically."""
        binding = self._binding(name, scope)
        if binding is None or depth > 20:
            return []
        kind = binding[0]
        if kind == "def":
            return [(self, binding[1])] if isinstance(binding[1], ast.FunctionDef) else []
        if kind == "import":
            target = self._imported(binding)
            return [] if target is None else target.resolve(binding[3], target.tree, depth + 1)
        if kind == "value":
            return self._resolve_value(binding[1], binding[2], binding[3], depth + 1)
        return []  # a parameter: a func handed to the factory

    def _binding(self, name: str, scope: ast.AST):
        """The binding of ``name`` seen from ``scope``, with the scope holding it appended."""
        while scope is not None:
            binding = self.bindings.get(scope, {}).get(name)
            if binding is not None:
                return (*binding, scope)
            scope = self.parent.get(scope)
        return None

    def _imported(self, binding: tuple) -> "Module | None":
        _, level, module, _, _ = binding
        if level != 1 or self.package is None:
            return None
        return self.package.module(f"{PACKAGE}.{module}" if module else PACKAGE)

    def _resolve_value(self, value: ast.expr, index, scope: ast.AST, depth: int) -> list:
        """What ``value`` (a name, a factory call, ``call[k]``, ``call.field``) gives: itself (``index`` None),
        item ``index`` of the tuple it is (an int), or the field of that name of the NamedTuple it is (a str)."""
        if depth > 20:
            return []
        if isinstance(value, ast.Subscript) and index is None and isinstance(value.slice, ast.Constant):
            return self._resolve_value(value.value, value.slice.value, scope, depth + 1)
        if isinstance(value, ast.Attribute) and index is None:
            return self._resolve_value(value.value, value.attr, scope, depth + 1)
        if isinstance(value, ast.Name):
            if index is None:
                return self.resolve(value.id, scope, depth + 1)
            binding = self._binding(value.id, scope)  # a name bound to a factory's result
            if binding is not None and binding[0] == "value" and binding[2] is None:
                return self._resolve_value(binding[1], index, binding[3], depth + 1)
            return []
        if isinstance(value, ast.Call) and isinstance(value.func, ast.Name):
            found = []
            for module, factory in self.resolve(value.func.id, scope, depth + 1):
                found.extend(module.returned(factory, index, depth + 1))
            return found
        return []

    def _fields(self, name: str, scope: ast.AST, depth: int) -> list[str]:
        """The field names of a NamedTuple class ``name`` seen from ``scope`` (in this module or a sibling)."""
        binding = self._binding(name, scope)
        if binding is None or depth > 20:
            return []
        if binding[0] == "def" and isinstance(binding[1], ast.ClassDef):
            return [s.target.id for s in binding[1].body if isinstance(s, ast.AnnAssign)
                    and isinstance(s.target, ast.Name)]
        if binding[0] == "import":
            target = self._imported(binding)
            return [] if target is None else target._fields(binding[3], target.tree, depth + 1)
        return []

    def returned(self, factory: ast.FunctionDef, index, depth: int) -> list:
        """What each ``return`` of a factory gives (``index`` as in ``_resolve_value``), resolved in it."""
        found = []
        for node in self._own_nodes(factory):
            if not isinstance(node, ast.Return) or node.value is None:
                continue
            value, item = node.value, index
            if isinstance(value, ast.Call) and isinstance(value.func, ast.Name) and value.func.id[:1].isupper():
                keywords = {k.arg: k.value for k in value.keywords if k.arg}  # a NamedTuple of funcs
                if isinstance(item, str):
                    fields = self._fields(value.func.id, factory, depth + 1)
                    if item in keywords:
                        value, item = keywords[item], None
                    elif item in fields and fields.index(item) < len(value.args):
                        value, item = value.args[fields.index(item)], None
                    else:
                        continue
                elif item is not None:
                    value = ast.Tuple(elts=value.args)
            if isinstance(value, ast.Tuple) and isinstance(item, int):
                if item >= len(value.elts):
                    continue
                value, item = value.elts[item], None
            found.extend(self._resolve_value(value, item, factory, depth + 1))
        return found

    # -- what a function writes ------------------------------------------------------------------------------

    def written(self, function: ast.FunctionDef, seen: frozenset = frozenset()) -> dict[str, str]:
        """The parameters of ``function`` it writes, each with the first reason found (statement and line)."""
        key = (self.filename, function.lineno, function.name)
        cache = self.package.written_cache if self.package is not None else {}
        if key in cache:
            return cache[key]
        if key in seen:
            return {}
        seen = seen | {key}
        params = {a.arg for a in function.args.args}
        aliases: dict[str, tuple[str, bool]] = {p: (p, False) for p in params}  # local -> (parameter, via memo)
        result: dict[str, str] = {}

        def root_of(expr: ast.expr):
            chain = _chain(expr)
            if chain is None or chain[0] not in aliases:
                return None
            parameter, memo = aliases[chain[0]]
            return parameter, memo or any(a in MEMO_FIELDS for a in chain[1]), chain[2]

        def mark(expr: ast.expr, why: str, need_subscript: bool) -> None:
            found = root_of(expr)
            if found is None:
                return
            parameter, memo, subscripted = found
            if memo or (need_subscript and not subscripted):
                return
            result.setdefault(parameter, f"{why} (line {expr.lineno})")

        for node in _walk_function(function):
            if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
                chain = _chain(node.value)
                if chain is not None and chain[0] in aliases and not chain[2]:
                    parameter, memo = aliases[chain[0]]
                    aliases[node.targets[0].id] = (parameter, memo or any(a in MEMO_FIELDS for a in chain[1]))
            targets = []
            if isinstance(node, ast.Assign):
                targets = node.targets
            elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
                targets = [node.target]
            for target in targets:
                for element in (target.elts if isinstance(target, (ast.Tuple, ast.List)) else [target]):
                    if isinstance(element, (ast.Subscript, ast.Attribute)):
                        mark(element, "a store", need_subscript=True)
            if isinstance(node, ast.Call):
                name = _decorator_name(node.func)
                if (name.startswith("atomic_") or name == "tile_store") and node.args:
                    mark(node.args[0], f"{name}'s target", need_subscript=False)
                elif isinstance(node.func, ast.Name):
                    for module, definition in self.resolve(node.func.id, function):
                        if not _is_func(definition):
                            continue
                        written = module.written(definition, seen)
                        names = [a.arg for a in definition.args.args]
                        pairs = list(zip(names, node.args)) + [(k.arg, k.value) for k in node.keywords if k.arg]
                        for parameter, argument in pairs:
                            if parameter in written:
                                mark(argument, f"passed to {definition.name}, which writes it: {written[parameter]}",
                                     need_subscript=False)
        cache[key] = result
        return result


def _walk_function(function: ast.FunctionDef):
    """Every node of a function's body in source order, not descending into nested functions."""
    def visit(node):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda)):
                continue
            yield child
            yield from visit(child)

    for statement in function.body:
        yield statement
        yield from visit(statement)


class Package:
    """The kernel modules of a directory, parsed once each, by dotted name."""

    def __init__(self, directory: pathlib.Path | None = None, sources: dict[str, str] | None = None):
        self.directory = directory
        self.sources = dict(sources or {})
        self.modules: dict[str, Module | None] = {}
        self.written_cache: dict = {}

    def module(self, name: str) -> Module | None:
        if name not in self.modules:
            source, filename = self.sources.get(name), f"<{name}>"
            if source is None and self.directory is not None:
                stem = name[len(PACKAGE) + 1:] if name.startswith(PACKAGE + ".") else "__init__"
                path = self.directory / f"{stem.replace('.', '/')}.py"
                if path.exists():
                    source, filename = path.read_text(), str(path.relative_to(self.directory.parents[1]))
            self.modules[name] = None if source is None else Module(name, source, filename, self)
        return self.modules[name]

    def all_modules(self) -> list[Module]:
        names = set(self.sources)
        if self.directory is not None:
            names |= {f"{PACKAGE}.{p.stem}" for p in self.directory.glob("*.py") if p.stem != "__init__"}
        return [m for m in (self.module(n) for n in sorted(names)) if m is not None]


def _groups(module: Module, kernel: ast.FunctionDef) -> list[str | None]:
    """The group header each parameter falls under (None before the first header)."""
    arguments = kernel.args.args
    if not arguments:
        return []
    headers = []  # (line number, header text)
    for number in range(kernel.lineno, arguments[-1].end_lineno + 1):
        match = HEADER.match(module.lines[number - 1])
        if match:
            headers.append((number, match.group(1).strip()))
    groups = []
    for argument in arguments:
        above = [text for number, text in headers if number < argument.lineno]
        groups.append(above[-1] if above else None)
    return groups


def check_kernel(module: Module, kernel: ast.FunctionDef) -> list[str]:
    """The convention violations of one kernel, each naming kernel, file and parameter."""
    where = f"{module.filename}:{kernel.lineno} kernel {kernel.name}"
    problems = []
    written = module.written(kernel)
    names = [a.arg for a in kernel.args.args]
    for name in names:
        if name in written and not name.endswith(WRITTEN_SUFFIX):
            problems.append(f"{where}: parameter {name!r} is written ({written[name]}) but does not end in "
                            f"{WRITTEN_SUFFIX!r}")
        if name not in written and name.endswith(WRITTEN_SUFFIX):
            problems.append(f"{where}: parameter {name!r} ends in {WRITTEN_SUFFIX!r} but is only read")
    groups = _groups(module, kernel)
    if any(g is not None for g in groups) or len(names) > UNGROUPED_MAX:
        ungrouped = [n for n, g in zip(names, groups) if g is None]
        if ungrouped:
            problems.append(f"{where}: parameters {ungrouped} come before any group header (# Model:, # State "
                            "in:, # Out: ...)")
        seen_out = False
        for name, group in zip(names, groups):
            if group is None:
                continue
            is_out = bool(OUT_GROUP.search(group))
            if seen_out and not is_out:
                problems.append(f"{where}: parameter {name!r} is in input group '# {group}:' after an output group")
            seen_out = seen_out or is_out
            if is_out and not name.endswith(WRITTEN_SUFFIX):
                problems.append(f"{where}: parameter {name!r} is in output group '# {group}:' but does not end "
                                f"in {WRITTEN_SUFFIX!r}")
            if not is_out and name.endswith(WRITTEN_SUFFIX):
                problems.append(f"{where}: parameter {name!r} is in input group '# {group}:' but ends in "
                                f"{WRITTEN_SUFFIX!r}")
    else:
        first_out = next((k for k, n in enumerate(names) if n.endswith(WRITTEN_SUFFIX)), len(names))
        late = [n for n in names[first_out:] if not n.endswith(WRITTEN_SUFFIX)]
        if late:
            problems.append(f"{where}: input parameters {late} come after an output")
    return problems


def unfollowed_writers(package: Package) -> list[str]:
    """Calls the write analysis cannot follow to a func that writes an argument: a call through an attribute,
    or a name that does not resolve, where a func of that name writes its arguments. They would hide a
    write, so they are violations too."""
    writers = {}
    for module in package.all_modules():
        for function in module.parent:
            if isinstance(function, ast.FunctionDef) and _is_func(function) and module.written(function):
                writers.setdefault(function.name, module.filename)
    problems = []
    for module in package.all_modules():
        for function in module.parent:
            if not (isinstance(function, ast.FunctionDef) and (_is_func(function) or _is_kernel(function))):
                continue
            for node in _walk_function(function):
                if not isinstance(node, ast.Call):
                    continue
                if isinstance(node.func, ast.Name):
                    hidden = node.func.id in writers and not module.resolve(node.func.id, function)
                    name = node.func.id
                else:
                    name = _decorator_name(node.func)
                    hidden = name in writers and not (isinstance(node.func.value, ast.Name)
                                                      and node.func.value.id == "wp")
                if hidden:
                    problems.append(f"{module.filename}:{node.lineno} {function.name}: the call of {name!r} is not "
                                    f"followed statically, and {name} ({writers[name]}) writes its arguments")
    return problems


def undecorated_kernels(package: Package) -> list[str]:
    """``wp.kernel(f)`` / ``flat_kernel(f)`` calls: kernels the check would not see (``flatten.py``, which
    implements ``flat_kernel``, aside)."""
    problems = []
    for module in package.all_modules():
        if module.name == f"{PACKAGE}.flatten":
            continue
        for node in ast.walk(module.tree):
            if (isinstance(node, ast.Call) and _decorator_name(node.func) in ("kernel", "flat_kernel")
                    and node.args):
                problems.append(f"{module.filename}:{node.lineno}: a kernel made by a call, not a decorator: "
                                "the convention check cannot see it")
    return problems


def check(package: Package) -> tuple[list[str], int]:
    """Every violation in the package and the number of kernels checked."""
    problems, count = [], 0
    for module in package.all_modules():
        for kernel in module.kernels():
            count += 1
            problems.extend(check_kernel(module, kernel))
    return problems + unfollowed_writers(package) + undecorated_kernels(package), count


# -- the tests -----------------------------------------------------------------------------------------------


def test_kernels_follow_the_parameter_conventions():
    problems, count = check(Package(KERNELS))
    assert count >= 60, f"only {count} kernels found: is the scan still finding factory kernels?"
    assert not problems, "kernel parameter conventions (tests/test_kernel_conventions.py):\n" + "\n".join(problems)


BAD = '''
import warp as wp
from .helpers import scatter

@wp.func
def bump(values: wp.array[float], i: int):
    wp.atomic_add(values, i, 1.0)

@wp.func
def bump_twice(values: wp.array[float], i: int):
    bump(values, i)

def factory(scalar: type):
    @wp.func
    def store(target: wp.array2d[float], i: int, v: float):
        target[0, i] = v

    def helpers():
        return store, bump_twice

    put, twice = helpers()

    @wp.kernel(module="unique")
    def bad(a: wp.array[float], b_out: wp.array[float], c: wp.array[float], d: wp.array2d[float],
            e: wp.array[float], s: Shapes, n: int):
        i = wp.tid()
        c[i] = a[i]
        put(d, i, a[i])
        twice(e, i)
        s.cache.face[i] = 1
        scatter(b_out, i)
        s.funcs.bump(a, i)  # hides a write

    @wp.kernel
    def unordered(x_out: wp.array[float], y: wp.array[float]):
        i = wp.tid()
        x_out[i] = y[i]

    @wp.kernel
    def grouped(
        # Model:
        n: int,
        a: wp.array[float],
        # Out:
        a_out: wp.array[float],
        # State in:
        x: wp.array[float],
        w_out: wp.array[float],
    ):
        i = wp.tid()
        a_out[i] = a[i] + x[i]
        w_out[i][0] = 1.0

    @wp.kernel
    def good(
        # Model:
        n: int,
        s: Shapes,
        # State in:
        x: wp.array[float],
        # Out:
        total_in_out: wp.array[float],
    ):
        i = wp.tid()
        total_in_out[i] += x[i]
        s.cache.ref[i] = x[i]  # a memo: not an output

    return bad, unordered, grouped, good, wp.kernel(factory)
'''


def test_the_check_reports_violations():
    """The check fails on a kernel that breaks each rule, naming kernel, file and parameter: a store, a store
    through a func of a factory (unpacked from its returned tuple), an atomic through two funcs; a read-only
    ``_out``; missing headers; an output before an input; an input group after ``# Out:``."""
    package = Package(sources={f"{PACKAGE}.bad": BAD})
    problems, count = check(package)
    assert count == 4
    text = "\n".join(problems)

    def reported(kernel: str, fragment: str) -> bool:
        return any(f"kernel {kernel}:" in p and fragment in p and "<warpspring.kernels.bad>" in p for p in problems)

    assert reported("bad", "'c' is written (a store"), text
    assert reported("bad", "'d' is written (passed to store"), text
    assert reported("bad", "'e' is written (passed to bump_twice"), text
    assert reported("bad", "'b_out' ends in '_out' but is only read"), text  # `scatter` is unknown: not followed
    assert reported("bad", "come before any group header"), text
    assert not any("parameter 's'" in p or "parameter 'a'" in p for p in problems), text
    assert reported("unordered", "input parameters ['y'] come after an output"), text
    assert reported("grouped", "'x' is in input group '# State in:' after an output group"), text
    assert reported("grouped", "'w_out' is in input group '# State in:' but ends in '_out'"), text
    assert len([p for p in problems if "kernel grouped:" in p]) == 3, text
    assert not any("kernel good:" in p for p in problems), text
    assert any("the call of 'bump' is not followed" in p for p in problems), text
    assert any("a kernel made by a call" in p for p in problems), text


def test_the_package_docstring_lists_every_module():
    """``warpspring/kernels/__init__.py`` names each kernel module once in its "Modules:" list."""
    docstring = ast.get_docstring(ast.parse((KERNELS / "__init__.py").read_text()))
    entries = docstring.split("Modules:", 1)[1].strip().splitlines()
    listed = [name.strip() for line in entries for name in line.split(":", 1)[0].split(",")]
    modules = sorted(p.stem for p in KERNELS.glob("*.py") if p.stem != "__init__")
    assert sorted(listed) == modules
