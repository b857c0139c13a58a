"""Struct parameters flattened into array parameters, for kernels written with struct parameters.

A Warp struct is the natural way to hand a kernel a family's arrays (one argument, no positional list to
keep in order), but a struct *kernel parameter* is slower than the same arrays as separate parameters:
2-7 % for one gather, 9-15 % for the fused cloth step (``bench/struct_params.py``, ``bench/RESULTS.md``
§9). A struct built inside the kernel from array parameters costs nothing. So the kernels are written
with struct parameters, and :func:`flat_kernel` compiles them with one parameter per leaf field instead,
rebuilding the structs as the body's first statements:

    def step(n: int, elements: Elements, x: wp.array[wp.vec3]): ...

becomes, for ``Elements = {head: {rest: array, stiffness: array2d}}``,

    def step(n: int, elements__head__rest: wp.array[float], elements__head__stiffness: wp.array2d[float],
             x: wp.array[wp.vec3]):
        _flat_struct_1 = Springs()
        _flat_struct_1.rest = elements__head__rest
        _flat_struct_1.stiffness = elements__head__stiffness
        elements = Elements()
        elements.head = _flat_struct_1
        ...

The generated source is registered with ``linecache`` (Warp reads kernel source through ``inspect``), and
runs in the original function's globals plus its closure's values. Launch such a kernel with
:func:`flat_launch`, which expands every struct instance in the argument lists into its leaf fields and
puts them in the kernel's parameter order.

Parameters the specialised body never reads cost time where they sit *between* the ones it reads: they
spread those over more of the constant bank, whose misses a short, latency-bound kernel pays at its start
(4-11 % for 5-40 idle array parameters interleaved with a 12-slot gather's five, nothing when the same
parameters come last; H100, ``bench/RESULTS.md`` §9). So ``flat_kernel(last=...)`` takes the leaves a
factory knows its specialisation compiles out (a family's CSR tail when no particle has one, the colliders
when the scene has none) and moves them to the end of the parameter list. Naming a leaf that is in fact
read is harmless: it is still passed, only placed last.
"""

from __future__ import annotations

import ast
import hashlib
import inspect
import linecache
import textwrap

import warp as wp

_SEPARATOR = "__"


def _is_struct(annotation) -> bool:
    return hasattr(annotation, "vars") and hasattr(annotation, "ctype") and hasattr(annotation, "cls")


def _leaves(struct, path: tuple = ()):
    """(path, annotation) of every leaf field of ``struct``, depth first in declaration order."""
    for name, var in struct.vars.items():
        if _is_struct(var.type):
            yield from _leaves(var.type, (*path, name))
        else:
            yield (*path, name), var.type


def flat_kernel(func=None, *, last=(), **kernel_options):
    """``wp.kernel(**kernel_options)`` of ``func`` with its struct parameters flattened (module docstring);
    without ``func``, a decorator: ``@flat_kernel(module="unique", enable_backward=False)``.

    ``last``: flat leaf names (``"shapes__kind"``) or prefixes of them (``"shapes"``, every leaf of that
    parameter) that the body never reads; they become the last parameters."""
    if func is None:
        return lambda f: flat_kernel(f, last=last, **kernel_options)
    signature = inspect.signature(func)
    closure = inspect.getclosurevars(func)
    namespace = {**func.__globals__, **closure.globals, **closure.nonlocals}
    annotations = {name: p.annotation for name, p in signature.parameters.items()}
    if isinstance(next(iter(annotations.values()), None), str):
        raise TypeError(f"{func.__qualname__}: flat_kernel needs evaluated annotations (no `from __future__ "
                        "import annotations` in the kernel's module)")
    structs = {name: a for name, a in annotations.items() if _is_struct(a)}
    if not structs:
        return wp.kernel(func, **kernel_options)

    tree = ast.parse(textwrap.dedent(inspect.getsource(func)))
    definition = tree.body[0]
    definition.decorator_list = []
    last = tuple(last)
    arguments, idle, prologue = [], [], []  # idle: (natural position, argument) of the leaves in ``last``
    for arg in definition.args.args:
        struct = structs.get(arg.arg)
        if struct is None:  # its annotation, already evaluated, by name (it may name factory locals)
            type_name = f"_flat_type_{len(namespace)}"
            namespace[type_name] = annotations[arg.arg]
            arguments.append(ast.arg(arg=arg.arg, annotation=ast.Name(id=type_name)))
            continue
        for path, annotation in _leaves(struct):
            type_name = f"_flat_type_{len(namespace)}"
            namespace[type_name] = annotation
            name = _SEPARATOR.join((arg.arg, *path))
            flat = ast.arg(arg=name, annotation=ast.Name(id=type_name))
            if any(name == p or name.startswith(p + _SEPARATOR) for p in last):
                idle.append((len(arguments) + len(idle), flat))
            else:
                arguments.append(flat)
        prologue.extend(_assemble(arg.arg, arg.arg, struct, (), namespace))
    # The launch's values come in the natural (declaration) order; ``order`` picks them in parameter order.
    busy = sorted(set(range(len(arguments) + len(idle))) - {k for k, _ in idle})
    order = tuple(busy + [k for k, _ in idle])
    definition.args.args = arguments + [flat for _, flat in idle]
    definition.body = [*prologue, *definition.body]
    source = ast.unparse(ast.fix_missing_locations(tree)) + "\n"

    digest = hashlib.sha1(source.encode()).hexdigest()[:12]
    filename = f"<warpspring flat kernel {func.__qualname__} {digest}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(keepends=True), filename)
    exec(compile(source, filename, "exec", dont_inherit=True), namespace)
    flat = namespace[definition.name]
    flat.__qualname__ = func.__qualname__
    flat.__module__ = func.__module__
    kernel = wp.kernel(flat, **kernel_options)
    kernel.flat_order = order if idle else None
    return kernel


def _assemble(root: str, name: str, struct, path: tuple, namespace: dict) -> list:
    """Statements building ``name`` (a struct of type ``struct``, at ``path`` in parameter ``root``) from the
    flat parameters, its nested structs first."""
    statements = []
    class_name = f"_flat_class_{len(namespace)}"
    namespace[class_name] = struct
    fields = []
    for field, var in struct.vars.items():
        if _is_struct(var.type):
            child = f"_flat_struct_{len(namespace)}"
            namespace[child] = None  # reserve the name
            statements.extend(_assemble(root, child, var.type, (*path, field), namespace))
            fields.append((field, child))
        else:
            fields.append((field, _SEPARATOR.join((root, *path, field))))
    statements.append(ast.parse(f"{name} = {class_name}()").body[0])
    statements.extend(ast.parse(f"{name}.{field} = {value}").body[0] for field, value in fields)
    return statements


def flat_launch(kernel, *, inputs=(), outputs=(), **launch_options) -> None:
    """``wp.launch`` of a :func:`flat_kernel` with struct instances among ``inputs`` and ``outputs``."""
    order = getattr(kernel, "flat_order", None)
    if order is None:
        wp.launch(kernel, inputs=flat_inputs(inputs), outputs=flat_inputs(outputs), **launch_options)
        return
    values = flat_inputs(inputs) + flat_inputs(outputs)
    # Idle leaves of the inputs now follow the outputs: everything goes as positional inputs (these kernels
    # have no adjoint, for which Warp tells outputs apart).
    wp.launch(kernel, inputs=[values[k] for k in order], **launch_options)


def flat_inputs(inputs) -> list:
    """A launch's argument list with every struct instance expanded into its leaf fields, in declaration
    order (the order of :func:`flat_kernel`'s parameters when it has no ``last``)."""
    out = []
    for value in inputs:
        if hasattr(value, "_cls") and _is_struct(value._cls):
            out.extend(_leaf_values(value))
        else:
            out.append(value)
    return out


def _leaf_values(instance) -> list:
    values = []
    for field, var in instance._cls.vars.items():
        value = getattr(instance, field)
        values.extend(_leaf_values(value) if _is_struct(var.type) else [value])
    return values
