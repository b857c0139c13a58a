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
import collections
import functools
import hashlib
import inspect
import linecache
import math
import textwrap
import weakref

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


def launch_bounds(threads: int, blocks: int | None) -> tuple[int, int] | None:
    """A kernel factory's ``bounds`` (:func:`launch_bounds_option`): blocks of ``threads`` of which a multiprocessor
    must hold ``blocks``; ``None`` (one cache key for every unbounded kernel) where ``blocks`` is."""
    return None if blocks is None else (threads, blocks)


def launch_bounds_option(bounds: tuple[int, int] | None) -> dict:
    """:func:`flat_kernel`'s option for ``bounds`` (threads a block, blocks a multiprocessor): on CUDA,
    ``__launch_bounds__``, which keeps the registers a thread within 65,536 / (threads · blocks) and refuses a wider
    launch; none for ``None`` (as many registers as the compiler takes)."""
    return {} if bounds is None else {"launch_bounds": (int(bounds[0]), int(bounds[1]))}


def flat_launch(kernel, *, inputs=(), outputs=(), **launch_options) -> None:
    """``wp.launch`` of a :func:`flat_kernel` with struct instances among ``inputs`` and ``outputs``.

    On the CPU, outside a graph capture, a launch whose arguments are the very objects of a recent launch of the
    same kernel (the same arrays, equal values) replays that launch's recorded command (``record_cmd``): Warp's
    packing of the arguments, 15-40 µs a launch of these kernels, is paid once (bench/results/performance_cpu.md
    §2). Captured frames never come here more than once; this is for frames that cannot be captured."""
    order = getattr(kernel, "flat_order", None)
    if order is None:
        _launch(kernel, flat_inputs(inputs), flat_inputs(outputs), launch_options)
        return
    values = flat_inputs(inputs) + flat_inputs(outputs)
    # Idle leaves of the inputs now follow the outputs: everything goes as positional inputs (these kernels
    # have no adjoint, for which Warp tells outputs apart).
    _launch(kernel, [values[k] for k in order], [], launch_options)


#: Recorded launches kept per kernel (the two state buffers of a step alternate: a few variants per call site).
RECORDED_LAUNCHES = 8


def _launch(kernel, inputs: list, outputs: list, options: dict) -> None:
    device = wp.get_device(options.get("device"))
    # Warp's debug and floating-point verification run their checks in its launch path, which a replay skips.
    replayable = device.is_cpu and not device.is_capturing and wp.config.mode != "debug" and not wp.config.verify_fp
    key = _launch_key(inputs, outputs, options) if replayable else None
    if key is None:
        wp.launch(kernel, inputs=inputs, outputs=outputs, **options)
        return
    recorded = kernel.__dict__.setdefault("_recorded_launches", collections.OrderedDict())
    entry = recorded.get(key)
    if entry is not None and all(alive() is not None for alive in entry[0]):
        recorded.move_to_end(key)
        entry[1].launch()
        return
    command = wp.launch(kernel, inputs=inputs, outputs=outputs, record_cmd=True, **options)
    # The command keeps the arrays' addresses, not the arrays: weak references say whether they still live (a dead
    # one's id may be reused by another array, so the entry is recorded anew), and the cache keeps nothing alive.
    command.fwd_args = command.adj_args = None
    recorded[key] = ([weakref.ref(a) for a in (*inputs, *outputs) if isinstance(a, wp.array)], command)
    if len(recorded) > RECORDED_LAUNCHES:
        recorded.popitem(last=False)
    command.launch()


#: Argument types compared by value in a launch's key (Warp's scalars hash and compare by value too).
_BY_VALUE = frozenset((type(None), bool, int, float, wp.float16, wp.float32, wp.float64, wp.int8, wp.int16,
                       wp.int32, wp.int64, wp.uint8, wp.uint16, wp.uint32, wp.uint64))


def _launch_key(inputs: list, outputs: list, options: dict):
    """What identifies a launch's arguments: each array by identity, each scalar by type and value; ``None`` where
    an argument is of another kind (the launch is then not recorded)."""
    key = []
    for value in (*inputs, None, *outputs):
        kind = type(value)
        if kind in _BY_VALUE:
            # -0.0 == 0.0 and both hash alike: the sign goes in the key too (NaN never equals itself: not replayed).
            key.append((kind, value, math.copysign(1.0, value) if kind is float else 1.0))
        elif isinstance(value, wp.array):
            key.append(id(value))
        else:
            return None
    for name, option in sorted(options.items()):
        if isinstance(option, wp.Device):
            option = option.alias
        elif not isinstance(option, (type(None), bool, int, float, str, tuple)):
            return None
        key.append((name, option))
    return tuple(key)


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
    for field, nested in _fields(instance._cls):
        value = getattr(instance, field)
        if nested:
            values.extend(_leaf_values(value))
        else:
            values.append(value)
    return values


@functools.cache
def _fields(struct) -> tuple:
    """(name, whether it is a struct) of every field of ``struct``, in declaration order."""
    return tuple((name, _is_struct(var.type)) for name, var in struct.vars.items())
