"""Sweeps: many variants of one scene, each run and measured, on one machine or a Ray cluster.

A sweep file (TOML) names a base scene and axes over its keys::

    [sweep]
    scene = "hanging_cloth.toml"       # the base scene, relative to this file (or a [scene] table inline)
    combine = "product"                # every combination of the axes ("zip": the axes side by side)
    reference = { "simulation.substeps" = 64 }   # optional: the run the variants' error is measured against
    usd = false                        # write each variant's animation to OUT/usd/<hash>.usdc
    batch = 16                         # variants of one topology run as worlds of one model, this many at most
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
every offending one is reported, one line each (:func:`plan_sweep`). A sweep file holds data only: keys must
be dotted scene paths and values TOML numbers, booleans, strings without control characters, or lists of
them; nothing in it is evaluated or passed to a shell.

Each variant is keyed by :func:`variant_hash`, a hash of its scene (and of what its metrics depend on: the
reference, the USD option). Its result is written, atomically (temporary file, then rename), to
``OUT/results/<hash>.json`` as soon as it arrives, so an interrupted sweep resumes by skipping the variants
whose result exists (:func:`run_sweep` ``resume=True``).

**Batching.** Variants whose scenes differ only in values a model holds per world (see "Worlds" in
docs/architecture.md: gravity, drag, the stabiliser thresholds, the wind's inputs, and each spring
family's ``ke``/``kd`` and the particle masses of a cloth) run as the worlds of one model, ``batch`` at most
per task; whether a value is zero is part of the topology (a zero switches a term off, which specialises
kernels). Worlds never couple, so a variant's metrics are the same alone or batched, bit for bit.

**Metrics** (:class:`VariantResult`), per variant, in float64 on the host from each frame's state: the
largest spring strain over the run, the mechanical energy at the start and the end (kinetic +
gravitational + spring elastic), the smallest signed distance from a particle's surface to a collider over
the run (where colliders exist), whether the run-time guard stopped it and its message, the error of the
final positions against the reference run's, and the wall time of its model's run (shared by the variants
batched together: ``worlds`` says how many).

**Engines.** A sweep's jobs go through an engine: :class:`LocalEngine` runs them one after the other in
this process; :class:`warpspring.analysis.sweep_ray.RayEngine` runs them as Ray tasks (retried when a
worker dies, the kernel cache warmed once per node). Both give the same metrics, timings aside. The trade
and stability studies run their plans through the same engines (``run_study(engine=...)``,
``run_map(engine=...)``).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import itertools
import json
import math
import os
import re
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from .. import checks
from ..errors import ConfigError, SimulationError

#: The sweep file's format; part of every variant's hash, so results of another format are not reused.
SWEEP_FORMAT_VERSION = 1
#: Statuses of a variant: ran to the end; stopped by the run-time guard (or an adaptive integrator gave
#: up); raised an error (its message says what).
STATUSES = ("ok", "stopped", "error")
#: Default most worlds (variants) in one model.
DEFAULT_BATCH = 16

#: A key: dotted names, each optionally indexed ("collider[1].friction").
_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\[[0-9]+\])?(\.[A-Za-z_][A-Za-z0-9_]*(\[[0-9]+\])?)*")
_SEGMENT = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)(?:\[([0-9]+)\])?")
#: Scene keys a sweep chooses itself: a variant's output file and its device, and the file's format.
_RESERVED = {"output.path": "the sweep writes each variant's USD to OUT/usd/<hash>.usdc (set [sweep] usd = true)",
             "simulation.device": "the engine chooses each task's device (warpspring sweep --device, --gpus)",
             "version": "set it in the base scene"}
_SWEEP_KEYS = {"scene", "combine", "reference", "usd", "batch", "metrics_every"}
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


@dataclass(frozen=True)
class SweepPlan:
    """A checked sweep: its variants and how they are run.

    Attributes:
        path: the sweep file (or "<sweep>").
        scene_path: the base scene's file: relative paths inside it (meshes) are relative to its folder.
        axes: each axis's key and values, in the file's order.
        variants: the variants, in plan order.
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
    variants: list
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
    from ..io.scene import tomllib

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ConfigError(f"sweep file not found: {path}")
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {' '.join(str(exc).split())}") from None
    return plan_sweep(data, path=path)


def plan_sweep(data: dict, *, path: str = "<sweep>") -> SweepPlan:
    """Check a sweep (the parsed TOML of a sweep file) and expand its variants.

    Every variant (and the reference) is checked by the scene parser before anything runs; the error lists
    every offending variant, one line each.

    Raises:
        ConfigError: a malformed sweep table, an axis key that is not a scene key, a value of a type a scene
            file cannot hold, or variants the scene parser refuses.
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
    fixed = _overrides(data.get("set", {}), where, "set")
    for key, value in fixed.items():
        base = apply_override(base, key, value, where=f"{where}: [set]")
    axes = {key: _axis_values(spec, where, key) for key, spec in _table(data.get("axes"), where, "axes").items()}
    if not axes:
        raise ConfigError(f'{where}: [axes] is empty: give at least one axis, e.g. "world.drag" = [0.0, 0.01]')
    reference = None
    if "reference" in sweep:
        reference = base
        for key, value in _overrides(sweep["reference"], where, "sweep.reference").items():
            reference = apply_override(reference, key, value, where=f"{where}: sweep.reference")

    if combine == "zip":
        lengths = {key: len(values) for key, values in axes.items()}
        if len(set(lengths.values())) > 1:
            shown = ", ".join(f"{k}: {n}" for k, n in lengths.items())
            raise ConfigError(f"{where}: combine = 'zip' needs axes of one length, got {shown}")
        combos = list(zip(*axes.values()))
    else:
        combos = list(itertools.product(*axes.values()))
    extras = {"reference": reference is not None and _digest(reference), "usd": usd, "metrics_every": every}
    variants, problems, durations = [], [], []
    for i, combo in enumerate(combos):
        params = dict(zip(axes, combo))
        try:
            scene = base
            for key, value in params.items():
                scene = apply_override(scene, key, value, where=where)
            parsed = _check_scene(scene, scene_path)
        except ConfigError as exc:
            problems.append(f"variant {i} ({describe_params(params)}): {_one_line(exc)}")
            continue
        variants.append(Variant(index=i, params=params, scene=scene, key=variant_hash(scene, **extras)))
        durations.append(parsed.frames / parsed.fps)
    reference_key = None
    if reference is not None:
        try:
            ref = _check_scene(reference, scene_path)
        except ConfigError as exc:
            problems.insert(0, f"reference: {_one_line(exc)}")
        else:
            reference_key = variant_hash(reference, reference=False, usd=False)
            for v, duration in zip(variants, durations):
                if not math.isclose(duration, ref.frames / ref.fps, rel_tol=1e-12):
                    problems.append(f"variant {v.index} ({describe_params(v.params)}): runs {duration:.6g} s but the "
                                    f"reference {ref.frames / ref.fps:.6g} s: the error compares end states at one time")
    if problems:
        count = len(problems)
        raise ConfigError(f"{where}: {count} of {len(combos)} variant{'s' if len(combos) > 1 else ''} refused"
                          f"{' (and the reference)' if problems[0].startswith('reference') else ''}; nothing ran:\n  "
                          + "\n  ".join(problems))
    return SweepPlan(path=path, scene_path=scene_path, axes=axes, variants=variants, reference=reference,
                     reference_key=reference_key, usd=usd, batch=batch, metrics_every=every)


def _base_scene(data: dict, sweep: dict, path: str, where: str) -> tuple[dict, str]:
    """The base scene's tables and the path its relative file names resolve against."""
    from ..io.scene import tomllib

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
    if not os.path.isfile(scene_path):
        raise ConfigError(f"{where}: sweep.scene {name!r} not found (looked for {scene_path})")
    try:
        with open(scene_path, "rb") as f:
            return tomllib.load(f), scene_path
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{scene_path}: not valid TOML: {_one_line(exc)}") from None


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


def _check_scene(data: dict, scene_path: str):
    """The scene parser's verdict on one variant (deprecation warnings silenced: the base scene's own)."""
    from ..io.scene import DeprecatedKeyWarning, parse_scene

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecatedKeyWarning)
        return parse_scene(data, path=scene_path)


def variant_hash(scene: dict, *, reference=False, usd: bool = False, metrics_every: int = 1) -> str:
    """The key of a variant's result: a SHA-256 (16 hex digits) of its scene's tables (canonical JSON,
    keys sorted), the sweep format, its reference's digest, whether its USD is written and how often its
    metrics are sampled."""
    return _digest({"format": SWEEP_FORMAT_VERSION, "scene": scene, "reference": reference, "usd": usd,
                    "metrics_every": metrics_every})[:16]


def _digest(value) -> str:
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=repr)
    return hashlib.sha256(text.encode()).hexdigest()


def describe_params(params: dict) -> str:
    """"cloth.structural.ke=1000, world.drag=0.01"."""
    return ", ".join(f"{k}={v:g}" if _is_number(v) else f"{k}={v!r}" for k, v in params.items())


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


# -- batches: variants that share a topology ------------------------------------------------------------------

#: Live inputs a batch sets per world: the scene table and key -> the model's input name (constants only:
#: a track is part of the topology).
_WORLD_INPUTS = {
    ("world", "gravity"): "gravity",
    ("world", "drag"): "drag",
    **{("stabilizers", k): k for k in ("max_spring_force", "max_particle_force", "max_speed", "max_strain",
                                       "biphasic_strain", "biphasic_ratio")},
    ("wind", "velocity"): "wind",
    ("wind", "air_density"): "air_density",
    ("wind", "noise"): "wind_noise",
}
#: Cloth keys whose values a batch gives per world through the model's spring and mass rows.
_FAMILIES = ("structural", "shear", "bend")
_MASS_KEYS = ("mass", "particle_mass")


def _live(value) -> dict:
    """What of a live value is topology: whether it is zero (a zero switches a term off)."""
    zero = not any(value) if isinstance(value, list) else value == 0
    return {"live": "zero" if zero else "nonzero"}


def topology(scene: dict) -> str:
    """A digest of what a variant's model compiles and allocates: its scene with the per-world values
    (constants of the live inputs, spring ke/kd, cloth masses) replaced by whether they are zero. Variants
    of one topology can run as worlds of one model."""
    skeleton = copy.deepcopy(scene)
    if "worlds" in skeleton:  # a scene of several worlds runs alone
        return _digest(scene)
    for (table, key) in _WORLD_INPUTS:
        values = skeleton.get(table)
        if isinstance(values, dict) and key in values and not isinstance(values[key], dict):
            values[key] = _live(values[key])
    cloths = skeleton.get("cloth")
    for cloth in [cloths] if isinstance(cloths, dict) else (cloths or []):
        for family in _FAMILIES:
            if isinstance(cloth.get(family), dict):
                cloth[family] = {k: _live(v) for k, v in cloth[family].items()}
        for key in _MASS_KEYS:
            if key in cloth:
                cloth[key] = "live"
    return _digest(skeleton)


@dataclass(frozen=True)
class Batch:
    """Variants of one topology, run as the worlds of one model in one task.

    Attributes:
        variants: the variants (world k runs ``variants[k]``).
        scene_path: the base scene's path (relative file names in the scenes resolve against its folder).
    """

    variants: tuple
    scene_path: str


def make_batches(variants: list, scene_path: str, batch: int) -> list[Batch]:
    """Group ``variants`` by :func:`topology`, ``batch`` at most per group, in plan order."""
    groups: dict[str, list] = {}
    for v in variants:
        groups.setdefault(topology(v.scene), []).append(v)
    batches = []
    for members in groups.values():
        for start in range(0, len(members), batch):
            batches.append(Batch(tuple(members[start : start + batch]), scene_path))
    return sorted(batches, key=lambda b: b.variants[0].index)


# -- running one batch ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunSettings:
    """How a task runs its batch.

    Attributes:
        device: Warp device name; ``None``: Warp's default in the process that runs it (a Ray task without
            a GPU sees none, so its default is the CPU).
        usd_dir: folder of the variants' USD files, or ``None`` (none written).
        reference_q: the reference run's final positions [m], float64, shape [particles, 3], or ``None``.
        task_hook: called with the batch at the start of every task, in the process that runs it (logging,
            or a test's fault injection), or ``None``.
        metrics_every: frames between the metrics' samples (the first and the last frame always).
    """

    device: str | None = None
    usd_dir: str | None = None
    reference_q: np.ndarray | None = None
    task_hook: Callable | None = None
    metrics_every: int = 1


@dataclass
class VariantResult:
    """What one variant's run gave: a row of the sweep's table (with its parameters).

    Attributes:
        index: the variant's place in the plan.
        key: its hash.
        status: "ok", "stopped" (the guard stopped it, or an adaptive integrator gave up) or "error".
        message: the guard's or the error's message ("" when ok).
        frames: frames completed (the frame it stopped in excluded).
        wall_time: wall time [s] of the frames of the model it ran in (after the first frame, which compiles
            and captures); shared by the ``worlds`` variants batched in it.
        setup_time: wall time [s] to build the model and run its first frame.
        frames_per_second: frames advanced per wall second by that model (all its worlds at once).
        worlds: variants run as worlds of the same model (1: alone).
        particles: particles of the variant.
        max_strain: largest spring strain (|d| − L) / L over the run's frames [-] (NaN without springs).
        energy_start, energy_end: kinetic + gravitational (zero at the start) + spring elastic energy at the
            first and the last completed frame [J].
        min_contact_distance: smallest distance from a particle's surface (its radius) to a collider over
            the run's frames [m], negative when inside; ``None`` without colliders.
        error_max, error_rms: max and RMS over the particles of |x − x_ref| at the end [m], against the
            reference run; ``None`` without one (or when it stopped, or has another particle count).
        device: the Warp device that ran it.
        usd: its USD file, or "".
    """

    index: int
    key: str
    status: str
    message: str = ""
    frames: int = 0
    wall_time: float | None = None
    setup_time: float | None = None
    frames_per_second: float | None = None
    worlds: int = 1
    particles: int = 0
    max_strain: float | None = None
    energy_start: float | None = None
    energy_end: float | None = None
    min_contact_distance: float | None = None
    error_max: float | None = None
    error_rms: float | None = None
    device: str = ""
    usd: str = ""


@dataclass
class BatchOutput:
    """A task's result: its variants' rows, and their final positions [m] (float64, [particles, 3]; ``None``
    for a variant that did not finish) by key."""

    results: list
    final_q: dict = field(default_factory=dict)


def run_batch(batch: Batch, settings: RunSettings) -> BatchOutput:
    """Run a batch's variants as the worlds of one model and measure each (:class:`VariantResult`). When the
    shared model cannot be built (a value one variant's builder refuses), each variant runs alone, so only
    that variant's row holds the error."""
    if settings.task_hook is not None:
        settings.task_hook(batch)
    if len(batch.variants) > 1:
        try:
            return _run_worlds(batch.variants, batch.scene_path, settings)
        except Exception:  # noqa: BLE001  (which variant is at fault is found by running each alone)
            pass
    output = BatchOutput(results=[])
    for v in batch.variants:
        try:
            one = _run_worlds((v,), batch.scene_path, settings)
        except Exception as exc:  # noqa: BLE001  (a variant that raises is a row with its error)
            one = BatchOutput([VariantResult(index=v.index, key=v.key, status="error", message=_one_line(exc))])
        output.results += one.results
        output.final_q.update(one.final_q)
    return output


def _batched_model(variants, scene_path: str, device):
    """The model holding ``variants`` as its worlds, their scenes, and the first one's scene."""
    scenes = [_check_scene(v.scene, scene_path) for v in variants]
    first = scenes[0]
    n = len(variants)
    if n == 1:
        return first.finalize(device), scenes
    shared = dataclasses.replace(first, world_count=n, world_inputs={}, world_scales={})
    for (table, key), name in _WORLD_INPUTS.items():
        values = [v.scene.get(table, {}).get(key) for v in variants]
        if values[0] is not None and not isinstance(values[0], dict) and any(x != values[0] for x in values):
            shared.world_inputs[name] = [[float(x) for x in val] if isinstance(val, list) else float(val)
                                         for val in values]
    model = shared.finalize(device)
    rows = [s.builder().world_rows() for s in scenes] if _cloth_values_differ(variants) else []
    for name in ("spring_stiffness", "spring_damping", "particle_mass"):
        if rows and any(not np.array_equal(r[name], rows[0][name]) for r in rows):
            model.set_world_values(name, np.stack([r[name] for r in rows]))
    return model, scenes


def _cloth_values_differ(variants) -> bool:
    def values(scene):
        cloths = scene.get("cloth")
        cloths = [cloths] if isinstance(cloths, dict) else (cloths or [])
        return [{k: c.get(k) for k in _FAMILIES + _MASS_KEYS} for c in cloths]

    first = values(variants[0].scene)
    return any(values(v.scene) != first for v in variants[1:])


def _run_worlds(variants, scene_path: str, settings: RunSettings) -> BatchOutput:
    """Run ``variants`` as the worlds of one model (the guard holds a failed world, the others go on)."""
    import warp as wp

    from ..core.integrators import make_integrator
    from ..core.simulator import Simulator

    t0 = time.perf_counter()
    device = checks.device(settings.device)
    model, scenes = _batched_model(variants, scene_path, device)
    scene = scenes[0]
    n, worlds = model.particle_count, len(variants)
    try:
        integrator = make_integrator(scene.integrator, model, **scene.integrator_options)
    except ConfigError as exc:
        raise ConfigError(f"[simulation] {exc}") from None
    guard = scene.guard
    limits = type(guard)(every=guard.every, tear_strain=guard.tear_strain, max_kinetic_energy=guard.max_kinetic_energy,
                         energy_balance=guard.energy_balance, stop="world")
    sim = Simulator(model, integrator=integrator, fps=scene.fps, substeps=scene.substeps, guard=limits)
    writers = _writers(model, scene, variants, settings)
    metrics = _Metrics(model)
    done = np.zeros(worlds, dtype=np.int64)  # frames each world completed
    stopped: dict[int, str] = {}
    t1, completed = None, 0
    try:
        for frame in range(scene.frames + 1):
            if frame > 0:
                try:
                    sim.step_frame()
                except SimulationError as exc:  # every world failed, or an adaptive integrator gave up
                    for w in range(worlds):
                        if w not in stopped:
                            stopped[w] = (_failure(sim, w, scene.substeps) if w in sim.world_failures
                                          else _one_line(exc))
                    break
                for w in sorted(set(sim.world_failures) - set(stopped)):
                    stopped[w] = _failure(sim, w, scene.substeps)
            running = np.array([w not in stopped for w in range(worlds)])
            if frame % settings.metrics_every == 0 or frame == scene.frames:
                wp.synchronize_device(device)
                q = sim.state.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
                qd = sim.state.particle_qd.numpy().astype(np.float64).reshape(worlds, n, 3)
                metrics.record(running, q, qd, frame / scene.fps)
            done[running] = frame
            for w in np.flatnonzero(running) if writers else ():
                writers[w][1].write_frame(sim.state)
            completed = frame
            if frame == 1:
                wp.synchronize_device(device)
                t1 = time.perf_counter()
    finally:
        for path, writer in writers:
            writer.close()
    end = time.perf_counter()
    wall = end - t1 if t1 is not None and completed > 1 else None
    reference = settings.reference_q
    output = BatchOutput(results=[])
    for w, v in enumerate(variants):
        row = VariantResult(
            index=v.index, key=v.key, status="stopped" if w in stopped else "ok", message=stopped.get(w, ""),
            frames=int(done[w]), wall_time=wall, setup_time=(t1 or end) - t0,
            frames_per_second=(completed - 1) / wall if wall else None, worlds=worlds,
            particles=n, device=str(device), **metrics.row(w),
        )
        if w not in stopped:
            output.final_q[v.key] = metrics.last_q[w]
            if reference is not None and reference.shape == metrics.last_q[w].shape:
                diff = np.linalg.norm(metrics.last_q[w] - reference, axis=1)
                row.error_max, row.error_rms = float(diff.max()), float(np.sqrt(np.mean(diff**2)))
        if writers:
            row.usd = _publish(writers[w][0])
        output.results.append(row)
    return output


def _failure(sim, world: int, substeps: int) -> str:
    """The guard's message for a stopped world, without its index (the same words alone or batched)."""
    frame, report = sim.world_failures[world]
    return f"frame {frame}, substep {report.substep + 1} of {substeps}: {report.describe(sim.model, name_world=False)}"


class _Metrics:
    """Every world's running extremes over the frames it passes, in float64 on the host, one vectorised pass
    per frame over all worlds: the largest spring strain (|d| − L) / L, the energy (kinetic + gravitational
    from the start + spring elastic ½ k (|d| − L)²) at the first and the last frame, and the smallest signed
    distance from a particle's surface to a collider."""

    def __init__(self, model):
        worlds, n = model.world_count, model.particle_count
        self.springs = model.spring_indices.numpy().reshape(-1, 2).astype(np.int64)
        self.rest = model.spring_rest_length.numpy().astype(np.float64)
        self.stiffness = model.world_values("spring_stiffness")  # [worlds, springs]
        self.mass = model.world_values("particle_mass")  # [worlds, particles]
        self.gravity = model.world_values("gravity")  # [worlds, 3]
        self.initial_q = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
        self.distance = _ContactDistance(model)
        self.strain = np.full(worlds, -np.inf)
        self.nearest = np.full(worlds, np.inf)
        self.energy_start = np.full(worlds, np.nan)
        self.energy_end = np.full(worlds, np.nan)
        self.last_q: dict[int, np.ndarray] = {}

    def record(self, running: np.ndarray, q: np.ndarray, qd: np.ndarray, t: float) -> None:
        """Take the frame at time ``t`` [s] of the worlds ``running`` (bool, [worlds]); ``q`` [m], ``qd``
        [m/s]: every world's positions and velocities, [worlds, particles, 3]."""
        w = np.flatnonzero(running)
        q, qd = q[w], qd[w]
        energy = 0.5 * np.sum(self.mass[w] * np.sum(qd * qd, axis=2), axis=1)
        energy -= np.sum(self.mass[w] * np.einsum("wpk,wk->wp", q - self.initial_q[w], self.gravity[w]), axis=1)
        if len(self.springs):
            length = np.linalg.norm(q[:, self.springs[:, 1]] - q[:, self.springs[:, 0]], axis=2)
            self.strain[w] = np.maximum(self.strain[w], np.max(length / self.rest - 1.0, axis=1))
            stretch = length - self.rest
            energy += 0.5 * np.sum(self.stiffness[w] * stretch * stretch, axis=1)
        first = np.isnan(self.energy_start[w])
        self.energy_start[w[first]] = energy[first]
        self.energy_end[w] = energy
        nearest = self.distance(q, t)
        if nearest is not None:
            self.nearest[w] = np.minimum(self.nearest[w], nearest)
        for k, world in enumerate(w):
            self.last_q[world] = q[k]

    def row(self, w: int) -> dict:
        def value(x):
            return float(x) if np.isfinite(x) else None

        return dict(max_strain=value(self.strain[w]), energy_start=value(self.energy_start[w]),
                    energy_end=value(self.energy_end[w]),
                    min_contact_distance=value(self.nearest[w]) if self.distance.shapes else None)


class _ContactDistance:
    """Signed distance [m] from the particles' surfaces (their radii) to the nearest collider, the least over
    each world's particles (float64, host); the colliders at time t through ``ShapeInfo.frame`` (their
    tracks)."""

    def __init__(self, model):
        self.shapes = list(model.shapes)
        self.radius = model.particle_radius.numpy().astype(np.float64)[: model.particle_count]

    def __call__(self, q: np.ndarray, t: float) -> np.ndarray | None:
        """The least distance of each world's particles ``q`` [m], [worlds, particles, 3]: [worlds]."""
        if not self.shapes:
            return None
        from scipy.spatial.transform import Rotation

        best = np.full(q.shape[0], np.inf)
        for shape in self.shapes:
            position, orientation = shape.frame(t)
            p = Rotation.from_quat(orientation).inv().apply((q - position).reshape(-1, 3)).reshape(q.shape)
            size = np.asarray(shape.size, dtype=np.float64)
            if shape.kind == "plane":
                d = p[..., 2]
            elif shape.kind == "sphere":
                d = np.linalg.norm(p, axis=-1) - size[0]
            elif shape.kind == "box":
                e = np.abs(p) - size
                d = np.linalg.norm(np.maximum(e, 0.0), axis=-1) + np.minimum(e.max(axis=-1), 0.0)
            elif shape.kind == "capsule":
                axial = np.clip(p[..., 2], -size[1], size[1])
                d = np.linalg.norm(p - np.stack([0.0 * axial, 0.0 * axial, axial], axis=-1), axis=-1) - size[0]
            else:  # a kind added later: no host distance yet
                continue
            best = np.minimum(best, np.min(d - self.radius, axis=1))
        return best


def _writers(model, scene, variants, settings: RunSettings) -> list:
    """One USD writer per world (its own single-world file, written under a temporary name)."""
    if settings.usd_dir is None:
        return []
    from ..io.usd import UsdWriter

    os.makedirs(settings.usd_dir, exist_ok=True)
    writers = []
    for w, v in enumerate(variants):
        path = os.path.join(settings.usd_dir, f"{v.key}.partial.usdc")
        writers.append((path, UsdWriter(path, model, fps=scene.fps, particles=scene.export_particles,
                                        springs=scene.export_springs, world=w if len(variants) > 1 else None,
                                        **scene.export_options)))
    return writers


def _publish(partial: str) -> str:
    """Rename a closed ``<key>.partial.usdc`` to ``<key>.usdc`` (atomic: a partial file is never taken as done)."""
    final = partial.replace(".partial.usdc", ".usdc")
    os.replace(partial, final)
    return final


# -- engines --------------------------------------------------------------------------------------------------


class LocalEngine:
    """Runs jobs one after the other in this process (no Ray)."""

    name = "local"

    def describe(self) -> str:
        return "this process"

    def run(self, fn: Callable, jobs: list, *, shared: tuple = (), on_error: Callable | None = None
            ) -> Iterator[tuple[int, object]]:
        """Yield (job index, ``fn(job, *shared)``) in job order; a job that raises gives
        ``on_error(job, exception)``, or raises when ``on_error`` is ``None``."""
        for i, job in enumerate(jobs):
            try:
                value = fn(job, *shared)
            except Exception as exc:
                if on_error is None:
                    raise
                value = on_error(job, exc)
            yield i, value

    def warm_up(self, fn: Callable, jobs: list, *, shared: tuple = ()) -> None:
        """Nothing: the first job compiles the kernels in this process."""

    def close(self) -> None:
        pass


def map_jobs(engine, fn: Callable, jobs: list, *, shared: tuple = (), done: Callable | None = None) -> list:
    """``[fn(job, *shared) for job in jobs]`` through ``engine`` (:class:`LocalEngine` when ``None``), in job
    order whatever order they finish in; ``done(result)`` is called as each arrives. A job that raises
    raises here."""
    engine = engine or LocalEngine()
    results = [None] * len(jobs)
    for i, value in engine.run(fn, jobs, shared=shared):
        results[i] = value
        if done is not None:
            done(value)
    return results


# -- the sweep ------------------------------------------------------------------------------------------------


@dataclass
class SweepResult:
    """A finished sweep: its plan and one row per variant, in plan order.

    Attributes:
        plan: the plan.
        rows: the variants' results.
        ran: variants run by this call (the others' results were found: resumed).
        elapsed: wall time of this call [s].
        engine: where it ran.
        reference: the reference run's result, or ``None``.
    """

    plan: SweepPlan
    rows: list
    ran: int
    elapsed: float
    engine: str
    reference: VariantResult | None = None


def results_dir(out_dir: str) -> str:
    """Where a sweep keeps one result file per variant."""
    return os.path.join(out_dir, "results")


def run_sweep(plan: SweepPlan, out_dir: str, *, engine=None, resume: bool = False, device: str | None = None,
              progress: bool = False, task_hook: Callable | None = None, log: Callable | None = None) -> SweepResult:
    """Run every variant of ``plan`` (the reference first) and write their results to ``out_dir``.

    Args:
        plan: from :func:`load_sweep` or :func:`plan_sweep`.
        out_dir: the output folder: ``results/<hash>.json`` per variant, ``usd/<hash>.usdc`` with ``usd``.
        engine: :class:`LocalEngine` (default) or a :class:`~warpspring.analysis.sweep_ray.RayEngine`.
        resume: skip the variants whose result is in ``out_dir`` already. Without it, a folder holding
            results of a sweep is refused (nothing is overwritten by accident).
        device: Warp device of every task; default: Warp's default where each task runs.
        progress: a progress bar (tqdm) over the variants, on stderr.
        task_hook: see :class:`RunSettings`.
        log: called with a line when the reference or a batch ends, or ``None``.

    Raises:
        ConfigError: ``out_dir`` holds results and ``resume`` is off; the reference run stopped.
    """
    from tqdm import tqdm

    engine = engine or LocalEngine()
    log = log or (lambda line: None)
    start = time.perf_counter()
    folder = results_dir(out_dir)
    if not resume and os.path.isdir(folder) and any(name.endswith(".json") for name in os.listdir(folder)):
        raise ConfigError(f"{out_dir} holds results of a sweep already: pass --resume to continue it (variants done "
                          "are skipped), or choose another --out")
    os.makedirs(folder, exist_ok=True)
    usd_dir = os.path.join(out_dir, "usd") if plan.usd else None
    settings = RunSettings(device=device, usd_dir=usd_dir, task_hook=task_hook, metrics_every=plan.metrics_every)

    reference = None
    if plan.reference is not None:
        ref = Variant(index=-1, params={}, scene=plan.reference, key=plan.reference_key)
        reference, reference_q = _load(folder, ref.key, positions=True)
        if reference is None:
            job = Batch((ref,), plan.scene_path)
            engine.warm_up(run_batch, _warm_up_jobs([job]), shared=(RunSettings(device=device),))
            [(_, output)] = list(engine.run(run_batch, [job], shared=(settings,), on_error=_failed_batch))
            reference = output.results[0]
            reference_q = output.final_q.get(ref.key)
            _save(folder, reference, reference_q)
        if reference.status != "ok":
            raise ConfigError(f"the reference run {reference.status}: {reference.message}; choose a reference that "
                              "runs to the end ([sweep] reference)")
        log(f"reference: {reference.frames} frames in {reference.wall_time or 0.0:.2f} s")
        settings = dataclasses.replace(settings, reference_q=reference_q)

    found = {}
    if resume:
        for v in plan.variants:
            row, _ = _load(folder, v.key)
            if row is not None:
                row.index = v.index
                found[v.key] = row
    todo = [v for v in plan.variants if v.key not in found]
    batches = make_batches(todo, plan.scene_path, plan.batch)
    with tqdm(total=len(plan.variants), initial=len(found), unit="variant", disable=not progress,
              dynamic_ncols=True, desc=f"sweep on {engine.describe()}") as bar:
        if batches:
            engine.warm_up(run_batch, _warm_up_jobs(batches), shared=(RunSettings(device=device),))
        for i, output in engine.run(run_batch, batches, shared=(settings,), on_error=_failed_batch):
            for row in output.results:
                _save(folder, row, None)
                found[row.key] = row
            bar.update(len(output.results))
            statuses = [r.status for r in output.results]
            log(f"batch of {len(statuses)}: " + ", ".join(f"{statuses.count(s)} {s}" for s in STATUSES
                                                          if s in statuses))
    rows = [found[v.key] for v in plan.variants]
    for v, row in zip(plan.variants, rows):
        row.index = v.index
    return SweepResult(plan=plan, rows=rows, ran=len(todo), elapsed=time.perf_counter() - start,
                       engine=engine.describe(), reference=reference)


def _failed_batch(batch: Batch, exc: BaseException) -> BatchOutput:
    """The rows of a batch whose task failed for good (its worker died at every retry): each its error."""
    message = f"the task failed: {type(exc).__name__}: {_one_line(exc)}"[:2000]
    return BatchOutput([VariantResult(index=v.index, key=v.key, status="error", message=message)
                        for v in batch.variants])


def _warm_up_jobs(batches: list) -> list:
    """One batch per topology of its first variant for one frame (the frame count compiles nothing): what a
    node compiles and loads before the sweep's tasks reach it."""
    seen, jobs = set(), []
    for b in batches:
        v = b.variants[0]
        shape = topology(v.scene)
        if shape not in seen:
            seen.add(shape)
            scene = apply_override(v.scene, "simulation.frames", 1, where="warm-up")
            jobs.append(Batch((dataclasses.replace(v, scene=scene),), b.scene_path))
    return jobs


def _save(folder: str, row: VariantResult, final_q) -> None:
    """Write a variant's result (and the reference's positions) atomically: a temporary file, then rename."""
    path = os.path.join(folder, f"{row.key}.json")
    _atomic_write(path, json.dumps(dataclasses.asdict(row), indent=1).encode())
    if final_q is not None:
        import io

        buffer = io.BytesIO()
        np.save(buffer, final_q)
        _atomic_write(os.path.join(folder, f"{row.key}.npy"), buffer.getvalue())


def _atomic_write(path: str, data: bytes) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _load(folder: str, key: str, *, positions: bool = False):
    """A stored result and (``positions``) final positions, or (None, None)."""
    path = os.path.join(folder, f"{key}.json")
    if not os.path.isfile(path):
        return None, None
    try:
        with open(path) as f:
            row = VariantResult(**json.load(f))
    except (OSError, ValueError, TypeError):  # unreadable: run it again
        return None, None
    q = None
    if positions:
        npy = os.path.join(folder, f"{key}.npy")
        if not os.path.isfile(npy):
            return None, None
        q = np.load(npy)
    return row, q
