"""A sweep's plan: the sweep file's schema, its axes expanded into variants, and each variant's key.

A sweep file (TOML) names a base scene and axes over its keys::

    [sweep]
    scene = "hanging_cloth.toml"       # the base scene, relative to this file (or a [scene] table inline)
    combine = "product"                # every combination of the axes ("zip": the axes side by side)
    reference = { "simulation.substeps" = 64 }   # optional: the run the variants' error is measured against
    usd = false                        # write each variant's animation to OUT/usd/<hash>.usdc
    batch = 16                         # variants of one topology run as worlds of one model, this many at most
    max_variants = 1000                # refuse a sweep of more variants (the default; raise it for a larger one)
    metrics_every = 1                  # frames between the metrics' samples (the first and last always)

    [set]                              # overrides of every variant (and of the reference)
    "simulation.frames" = 30

    [axes]
    "cloth.structural.ke" = { log = [1e2, 1e4], count = 5 }        # log-spaced, ends included
    "simulation.substeps" = { range = [8, 32], step = 8 }          # 8, 16, 24, 32
    "world.drag" = [0.0, 0.01]                                     # a list
    "cloth.bend.kd" = { random = [1e-3, 1e-1], count = 4, seed = 7, log = true }   # seeded samples

An axis key is a dotted path into the scene file (``collider[1].friction`` names the second of several
``[[collider]]``); a variant is the base scene with the keys of its axes overridden, checked by the scene
parser itself (:func:`warpspring.io.scene.parse_scene`). Before any job starts every variant is checked, and
the offending ones are reported, the first :data:`SHOWN_PROBLEMS` one line each, with their count
(:func:`plan_sweep`).

Variants stream: the plan holds the axes, not their product (:class:`Variants` makes each variant when it is
read), so a plan's memory does not grow with its variant count. A sweep of more than :data:`MAX_VARIANTS`
variants is refused at once, from its axes' lengths, before any value is generated, unless ``[sweep]
max_variants`` raises the limit (``max_variants = 50000``). A sweep file holds data only: keys must
be dotted scene paths and values TOML numbers, booleans, strings without control characters, or lists of
them; nothing in it is evaluated or passed to a shell.

Each variant is keyed by :func:`variant_hash`, a hash of its scene (and of what its metrics depend on: the
reference, the USD option); a sweep's results are stored and resumed by that key
(:mod:`warpspring.analysis.sweep`).
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import os
import re
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from ..io.scene import DeprecatedKeyWarning, parse_scene, read_toml

#: The sweep file's format; part of every variant's hash, so results of another format are not reused.
SWEEP_FORMAT_VERSION = 1
#: Default most worlds (variants) in one model.
DEFAULT_BATCH = 16
#: Default most variants of a sweep (``[sweep] max_variants`` raises it): a larger one is refused at once.
MAX_VARIANTS = 1000
#: Offending variants a refused plan names, one line each (their count is given in full).
SHOWN_PROBLEMS = 20

#: A key: dotted names, each optionally indexed ("collider[1].friction").
_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\[[0-9]+\])?(\.[A-Za-z_][A-Za-z0-9_]*(\[[0-9]+\])?)*")
_SEGMENT = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)(?:\[([0-9]+)\])?")
#: Scene keys a sweep chooses itself: a variant's output file and its device, and the file's format.
_RESERVED = {"output.path": "the sweep writes each variant's USD to OUT/usd/<hash>.usdc (set [sweep] usd = true)",
             "simulation.device": "the engine chooses each task's device (warpspring sweep --device, --gpus)",
             "version": "set it in the base scene"}
_SWEEP_KEYS = {"scene", "combine", "reference", "usd", "batch", "metrics_every", "max_variants"}
_AXIS_KEYS = {"range": ("step", "count"), "log": ("count",), "random": ("count", "seed", "log", "integer")}


# -- plans ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Variant:
    """One scene of a sweep.

    Attributes:
        index: its place in the plan (0-based).
        params: the axes' values, by key (the table's parameter columns).
        scene: the scene file's tables with every override applied (a dict, as parsed from TOML).
        key: :func:`variant_hash` of it.
    """

    index: int
    params: dict
    scene: dict
    key: str


class Variants(Sequence):
    """A sweep's variants, made when read (by index or in order), never held: the base scene, the axes and
    how they combine are all it keeps, so its memory is flat in the variant count.

    Variant ``i`` of a product is the mixed-radix decomposition of ``i`` over the axes' lengths (the last axis
    fastest, as ``itertools.product``); of a zip, the axes' ``i``-th values.
    """

    def __init__(self, base: dict, axes: dict, combine: str, extras: dict, where: str):
        self._base, self._axes, self._combine, self._extras, self._where = base, axes, combine, extras, where
        lengths = [len(values) for values in axes.values()]
        self._length = math.prod(lengths) if combine == "product" else (lengths[0] if lengths else 0)

    def __len__(self) -> int:
        return self._length

    def combos(self) -> Iterator[tuple]:
        """The axes' values of each variant, in plan order, generated lazily."""
        values = list(self._axes.values())
        return itertools.product(*values) if self._combine == "product" else zip(*values)

    def scene_of(self, params: dict) -> dict:
        """The base scene with ``params`` applied (ConfigError if an override does not apply)."""
        scene = self._base
        for key, value in params.items():
            scene = apply_override(scene, key, value, where=self._where)
        return scene

    def make(self, index: int, combo: tuple) -> Variant:
        params = dict(zip(self._axes, combo))
        scene = self.scene_of(params)
        return Variant(index=index, params=params, scene=scene, key=variant_hash(scene, **self._extras))

    def _combo(self, index: int) -> tuple:
        values = list(self._axes.values())
        if self._combine == "zip":
            return tuple(v[index] for v in values)
        combo = []
        for axis in reversed(values):
            index, digit = divmod(index, len(axis))
            combo.append(axis[digit])
        return tuple(reversed(combo))

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(self._length))]
        index = int(index)
        if index < 0:
            index += self._length
        if not 0 <= index < self._length:
            raise IndexError(f"variant {index} of {self._length}")
        return self.make(index, self._combo(index))

    def __iter__(self) -> Iterator[Variant]:
        for i, combo in enumerate(self.combos()):
            yield self.make(i, combo)

    def __repr__(self) -> str:
        return f"Variants({self._length} of {', '.join(self._axes)}, {self._combine})"


@dataclass(frozen=True)
class SweepPlan:
    """A checked sweep: its variants and how they are run.

    Attributes:
        path: the sweep file (or "<sweep>").
        scene_path: the base scene's file: relative paths inside it (meshes) are relative to its folder.
        axes: each axis's key and values, in the file's order.
        variants: the variants, in plan order (:class:`Variants`: made when read, never all held).
        reference: the reference run's scene (base scene + ``[set]`` + ``[sweep] reference``), or ``None``.
        reference_key: its hash, or ``None``.
        usd: write each variant's USD.
        batch: most variants run as worlds of one model.
        metrics_every: frames between the samples the metrics are taken from (the first and the last frame
            always); the host's float64 pass over every particle then costs that much less.
    """

    path: str
    scene_path: str
    axes: dict
    variants: Sequence
    reference: dict | None = None
    reference_key: str | None = None
    usd: bool = False
    batch: int = DEFAULT_BATCH
    metrics_every: int = 1

    @property
    def keys(self) -> list[str]:
        """The axes' keys (the table's parameter columns)."""
        return list(self.axes)


def load_sweep(path: str | os.PathLike) -> SweepPlan:
    """Read a sweep file and plan it (:func:`plan_sweep`).

    Raises:
        ConfigError: the file is missing or not TOML, or the plan is refused (every offending variant named).
    """
    path = os.fspath(path)
    return plan_sweep(read_toml(path, "sweep file"), path=path)


def plan_sweep(data: dict, *, path: str = "<sweep>", max_variants: int | None = None) -> SweepPlan:
    """Check a sweep (the parsed TOML of a sweep file) and plan its variants.

    The variant count comes from the axes' lengths before any value is generated: above the limit
    (``max_variants``, else ``[sweep] max_variants``, else :data:`MAX_VARIANTS`) the sweep is refused at once.
    Then every variant (and the reference) is checked by the scene parser before anything runs, streaming (one
    variant at a time); the error names the first :data:`SHOWN_PROBLEMS` offending variants, one line each, and
    their count.

    Raises:
        ConfigError: a malformed sweep table, an axis key that is not a scene key, a value of a type a scene
            file cannot hold, more variants than the limit, or variants the scene parser refuses.
    """
    where = os.path.basename(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: a sweep must be a table")
    unknown = sorted(set(data) - {"sweep", "scene", "set", "axes"})
    if unknown:
        raise ConfigError(f"{where}: unknown table {unknown[0]!r}; a sweep file has [sweep], [scene], [set] and [axes]")
    sweep = data.get("sweep", {})
    if not isinstance(sweep, dict):
        raise ConfigError(f"{where}: [sweep] must be a table")
    extra = sorted(set(sweep) - _SWEEP_KEYS)
    if extra:
        raise ConfigError(f"{where}: unknown key {extra[0]!r} in [sweep]; allowed: {', '.join(sorted(_SWEEP_KEYS))}")
    base, scene_path = _base_scene(data, sweep, path, where)
    combine = sweep.get("combine", "product")
    if combine not in ("product", "zip"):
        raise ConfigError(f"{where}: sweep.combine must be 'product' (every combination) or 'zip' (the axes side by "
                          f"side, equally long), got {combine!r}")
    usd = sweep.get("usd", False)
    if not isinstance(usd, bool):
        raise ConfigError(f"{where}: sweep.usd must be true or false, got {usd!r}")
    batch = sweep.get("batch", DEFAULT_BATCH)
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ConfigError(f"{where}: sweep.batch must be an integer >= 1 (most variants per model), got {batch!r}")
    every = sweep.get("metrics_every", 1)
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ConfigError(f"{where}: sweep.metrics_every must be an integer >= 1 (frames between the metrics' "
                          f"samples), got {every!r}")
    limit = sweep.get("max_variants", MAX_VARIANTS) if max_variants is None else max_variants
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise ConfigError(f"{where}: sweep.max_variants must be an integer >= 1 (most variants the sweep may have), "
                          f"got {limit!r}")
    specs = _table(data.get("axes"), where, "axes")
    if not specs:
        raise ConfigError(f'{where}: [axes] is empty: give at least one axis, e.g. "world.drag" = [0.0, 0.01]')
    lengths = {key: _axis_length(spec, where, key) for key, spec in specs.items()}
    total = math.prod(lengths.values()) if combine == "product" else min(lengths.values())
    if total > limit:
        shown = " × ".join(f"{n:,}" for n in lengths.values()) if combine == "product" else f"{total:,}"
        raise ConfigError(f"{where}: the sweep has {total:,} variants ({shown}), more than the limit of {limit:,}; "
                          f"nothing ran: use fewer or shorter axes, or raise the limit with [sweep] max_variants = "
                          f"{total}")
    fixed = _overrides(data.get("set", {}), where, "set")
    for key, value in fixed.items():
        base = apply_override(base, key, value, where=f"{where}: [set]")
    axes = {key: _axis_values(spec, where, key) for key, spec in specs.items()}
    if combine == "zip" and len({len(values) for values in axes.values()}) > 1:
        shown = ", ".join(f"{k}: {len(v)}" for k, v in axes.items())
        raise ConfigError(f"{where}: combine = 'zip' needs axes of one length, got {shown}")
    reference = None
    if "reference" in sweep:
        reference = base
        for key, value in _overrides(sweep["reference"], where, "sweep.reference").items():
            reference = apply_override(reference, key, value, where=f"{where}: sweep.reference")

    extras = {"reference": reference is not None and digest(reference), "usd": usd, "metrics_every": every}
    variants = Variants(base, axes, combine, extras, where)
    problems, count = [], 0
    ref_duration = reference_key = None
    if reference is not None:
        try:
            ref = check_scene(reference, scene_path)
        except ConfigError as exc:
            problems.append(f"reference: {one_line(exc)}")
            count += 1
        else:
            reference_key = variant_hash(reference, reference=False, usd=False)
            ref_duration = ref.frames / ref.fps
    for i, combo in enumerate(variants.combos()):  # streamed: one variant's scene at a time
        params = dict(zip(axes, combo))
        problem = None
        try:
            parsed = check_scene(variants.scene_of(params), scene_path)
        except ConfigError as exc:
            problem = one_line(exc)
        else:
            duration = parsed.frames / parsed.fps
            if ref_duration is not None and not math.isclose(duration, ref_duration, rel_tol=1e-12):
                problem = (f"runs {duration:.6g} s but the reference {ref_duration:.6g} s: the error compares end "
                           "states at one time")
        if problem is not None:
            count += 1
            if len(problems) < SHOWN_PROBLEMS:
                problems.append(f"variant {i} ({describe_params(params)}): {problem}")
    if count:
        refused = count - (1 if problems[0].startswith("reference") else 0)
        more = f"\n  ... and {count - len(problems)} more" if count > len(problems) else ""
        raise ConfigError(f"{where}: {refused} of {len(variants)} variant{'s' if len(variants) > 1 else ''} refused"
                          f"{' (and the reference)' if problems[0].startswith('reference') else ''}; nothing ran"
                          f"{f' (the first {len(problems)} shown)' if more else ''}:\n  " + "\n  ".join(problems) + more)
    return SweepPlan(path=path, scene_path=scene_path, axes=axes, variants=variants, reference=reference,
                     reference_key=reference_key, usd=usd, batch=batch, metrics_every=every)


def _base_scene(data: dict, sweep: dict, path: str, where: str) -> tuple[dict, str]:
    """The base scene's tables and the path its relative file names resolve against."""
    if ("scene" in sweep) == ("scene" in data):
        raise ConfigError(f"{where}: name the base scene once: [sweep] scene = 'file.toml', or a [scene] table")
    if "scene" in data:
        if not isinstance(data["scene"], dict):
            raise ConfigError(f"{where}: [scene] must be a table holding a scene's tables")
        return data["scene"], path
    name = sweep["scene"]
    if not isinstance(name, str):
        raise ConfigError(f"{where}: sweep.scene must be a file name, got {name!r}")
    scene_path = name if os.path.isabs(name) else os.path.join(os.path.dirname(os.path.abspath(path)), name)
    if not os.path.exists(scene_path):
        raise ConfigError(f"{where}: sweep.scene {name!r} not found (looked for {scene_path})")
    return read_toml(scene_path, "sweep scene"), scene_path


def _table(value, where: str, name: str) -> dict:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"{where}: [{name}] must be a table of quoted keys, e.g. \"world.drag\" = [0.0, 0.01]")
    return value


def _overrides(value, where: str, name: str) -> dict:
    """A table of key → value overrides, each value checked to be data (see :func:`check_value`)."""
    table = _table(value, where, name)
    for key, v in table.items():
        check_value(v, where=f"{where}: {name} {key!r}")
    return table


def _axis_length(spec, where: str, key: str) -> int:
    """An axis's value count, from its spec alone (nothing generated): a list's length, a table's ``count``, or
    a range's ``(stop - start) / step + 1``; a malformed spec is left to :func:`_axis_values` (counted 1)."""
    if isinstance(spec, list):
        return max(len(spec), 1)
    if not isinstance(spec, dict):
        return 1
    count = spec.get("count")
    if isinstance(count, int) and not isinstance(count, bool) and count >= 1:
        return count
    ends, step = spec.get("range"), spec.get("step")
    if (isinstance(ends, list) and len(ends) == 2 and all(_is_number(e) for e in ends) and _is_number(step)
            and step != 0 and (ends[1] - ends[0]) / step >= 0):
        return int(math.floor((ends[1] - ends[0]) / step * (1 + 1e-12) + 1e-9)) + 1
    return 1


def _axis_values(spec, where: str, key: str) -> list:
    """An axis's values: a list, or a { range | log | random } table."""
    label = f"{where}: axis {key!r}"
    if isinstance(spec, list):
        if not spec:
            raise ConfigError(f"{label} lists no values")
        for v in spec:
            check_value(v, where=label)
        return list(spec)
    if not isinstance(spec, dict):
        raise ConfigError(f"{label} must be a list of values or a table {{ range | log | random = [a, b], ... }}, got "
                          f"{spec!r}")
    kinds = [k for k in _AXIS_KEYS if k in spec and not (k == "log" and "random" in spec)]  # (a sample's option)
    if len(kinds) != 1:
        raise ConfigError(f"{label} needs exactly one of range = [start, stop], log = [start, stop] or "
                          "random = [low, high]")
    kind = kinds[0]
    extra = sorted(set(spec) - {kind, *_AXIS_KEYS[kind]})
    if extra:
        raise ConfigError(f"{label}: {extra[0]!r} does not apply to a {kind} axis; it takes {', '.join(_AXIS_KEYS[kind])}")
    ends = spec[kind]
    if not (isinstance(ends, list) and len(ends) == 2 and all(_is_number(e) for e in ends)):
        raise ConfigError(f"{label}: {kind} must be [start, stop], two finite numbers, got {ends!r}")
    a, b = ends
    count = spec.get("count")
    if count is not None and (not isinstance(count, int) or isinstance(count, bool) or count < 1):
        raise ConfigError(f"{label}: count must be an integer >= 1, got {count!r}")
    if kind == "range":
        if ("step" in spec) == (count is not None):
            raise ConfigError(f"{label}: a range takes step = s or count = n (one of them)")
        if count is not None:
            values = np.linspace(a, b, count)
        else:
            step = spec["step"]
            if not _is_number(step) or step == 0 or (b - a) / step < 0:
                raise ConfigError(f"{label}: step must be a nonzero number going from {a} towards {b}, got {step!r}")
            n = int(math.floor((b - a) / step * (1 + 1e-12) + 1e-9)) + 1
            values = a + step * np.arange(n)
        integer = all(isinstance(x, int) for x in (a, b, spec.get("step", 0))) and count is None
        return [int(round(v)) for v in values] if integer else [float(v) for v in values]
    if count is None:
        raise ConfigError(f"{label}: a {kind} axis needs count = n")
    logarithmic = kind == "log" or spec.get("log", False)
    if logarithmic and not (a > 0 and b > 0):
        raise ConfigError(f"{label}: a logarithmic axis needs ends > 0, got [{a}, {b}]")
    if kind == "log":
        return [float(v) for v in np.geomspace(a, b, count)]
    seed = spec.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(f"{label}: seed must be an integer >= 0, got {seed!r}")
    for option in ("log", "integer"):
        if not isinstance(spec.get(option, False), bool):
            raise ConfigError(f"{label}: {option} must be true or false, got {spec[option]!r}")
    rng = np.random.default_rng(seed)
    if spec.get("integer", False):
        return [int(v) for v in rng.integers(int(math.ceil(min(a, b))), int(math.floor(max(a, b))) + 1, size=count)]
    u = rng.random(count)
    values = np.exp(np.log(a) + u * (np.log(b) - np.log(a))) if logarithmic else a + u * (b - a)
    return [float(v) for v in values]


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_value(value, *, where: str) -> None:
    """Refuse what a scene file cannot hold: a value must be a number, a boolean, a string of printable
    characters, or a list or table of such values (strings are never evaluated: a scene key of the wrong
    kind is then refused by the scene parser).

    Raises:
        ConfigError: naming ``where`` and the value.
    """
    if isinstance(value, bool) or _is_number(value):
        return
    if isinstance(value, str):
        if not value.isprintable():
            raise ConfigError(f"{where}: a string value must be printable, without control characters, got {value!r}")
        return
    if isinstance(value, list):
        for v in value:
            check_value(v, where=where)
        return
    if isinstance(value, dict):
        for k, v in value.items():
            if not _SEGMENT.fullmatch(k):
                raise ConfigError(f"{where}: {k!r} is not a scene key (letters, digits and _)")
            check_value(v, where=where)
        return
    raise ConfigError(f"{where}: {value!r} is not a value a scene file holds (a number, true/false, a string, or a "
                      "list of them)")


def apply_override(scene: dict, key: str, value, *, where: str) -> dict:
    """A copy of ``scene`` (a scene file's tables) with the dotted ``key`` set to ``value``. Tables on the
    way are created; a spring family given as ``true`` becomes a table (its other constant keeps its
    default); an array of tables needs an index unless it holds one table.

    Raises:
        ConfigError: a key that is not a dotted scene path, a key the sweep sets itself, or a path through a
            value that is not a table.
    """
    if not isinstance(key, str) or not _KEY.fullmatch(key):
        raise ConfigError(f"{where}: {key!r} is not a scene key: a dotted path of names such as "
                          "\"cloth.structural.ke\" or \"collider[1].friction\"")
    plain = re.sub(r"\[[0-9]+\]", "", key)
    if plain in _RESERVED:
        raise ConfigError(f"{where}: {key!r} cannot be swept: {_RESERVED[plain]}")
    check_value(value, where=f"{where}: {key!r}")
    scene = copy.deepcopy(scene)
    table, parts = scene, key.split(".")
    for depth, part in enumerate(parts):
        name, index = _SEGMENT.fullmatch(part).groups()
        last = depth == len(parts) - 1
        here = ".".join(parts[: depth + 1])
        current = table.get(name)
        if isinstance(current, list) and (current and all(isinstance(t, dict) for t in current)):
            if index is None and len(current) != 1:
                raise ConfigError(f"{where}: {key!r}: the scene has {len(current)} [[{name}]] tables: name one, e.g. "
                                  f"{name}[0]")
            i = 0 if index is None else int(index)
            if i >= len(current):
                raise ConfigError(f"{where}: {key!r}: the scene has {len(current)} [[{name}]] table(s), 0..{len(current) - 1}")
            if last:
                raise ConfigError(f"{where}: {key!r} names a whole table: name one of its keys")
            table = current[i]
            continue
        if index is not None:
            raise ConfigError(f"{where}: {key!r}: {name} is not an array of tables in the scene")
        if last:
            table[name] = value
            break
        if current is True:  # a spring family switched on with its defaults
            current = table[name] = {}
        elif current is None:
            current = table[name] = {}
        elif not isinstance(current, dict):
            raise ConfigError(f"{where}: {key!r}: {here} is {current!r} in the scene, not a table")
        table = current
    return scene


def check_scene(data: dict, scene_path: str):
    """The scene parser's verdict on one variant (deprecation warnings silenced: the base scene's own)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecatedKeyWarning)
        return parse_scene(data, path=scene_path)


def variant_hash(scene: dict, *, reference=False, usd: bool = False, metrics_every: int = 1) -> str:
    """The key of a variant's result: a SHA-256 (16 hex digits) of its scene's tables (canonical JSON,
    keys sorted), the sweep format, its reference's digest, whether its USD is written and how often its
    metrics are sampled."""
    return digest({"format": SWEEP_FORMAT_VERSION, "scene": scene, "reference": reference, "usd": usd,
                   "metrics_every": metrics_every})[:16]


def digest(value) -> str:
    """SHA-256 (hex) of ``value`` as canonical JSON (keys sorted; what JSON cannot hold by its ``repr``)."""
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=repr)
    return hashlib.sha256(text.encode()).hexdigest()


def describe_params(params: dict) -> str:
    """"cloth.structural.ke=1000, world.drag=0.01"."""
    return ", ".join(f"{k}={v:g}" if _is_number(v) else f"{k}={v!r}" for k, v in params.items())


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (whitespace runs collapsed to one space)."""
    return " ".join(str(exc).split())
