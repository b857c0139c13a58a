"""Checking a parsed scene file against its schema (:mod:`~warpspring.io.scene_schema`): the format version
and renamed keys, every table's keys and value types, the rules a cloth, a collider, a pin group, a handle or a
soft body adds, keyframe tracks (made :class:`~warpspring.core.tracks.Track` objects), and the run settings.
Every error is a :class:`ConfigError` naming the file, the table and the key."""

from __future__ import annotations

import math
import re

from ..core.builder.spring_materials import spring_law_options
from ..core.tet10 import ELEMENTS
from ..core.tracks import EXTRAPOLATIONS, INTERPOLATIONS, Track
from ..errors import ConfigError
from ..version import __version__
from .scene_schema import (
    COLLIDER_KEYS,
    COLLIDER_NEEDS,
    COLLIDER_TYPES,
    FORMAT_1_COLLIDERS,
    GRID_ONLY,
    MESH_ONLY,
    NUMBER,
    POSITIVE,
    QUATERNION,
    RENAMED_KEYS,
    ROTATION_TRACK_TABLE,
    SCENE_FORMAT_VERSION,
    SCHEMA,
    SUBSTEPS,
    TRACK_TABLE,
    TYPE_NAMES,
    VECTOR,
    HandleSpec,
    Live,
    Number,
    PerWorld,
    PinGroupSpec,
    Since,
    Tables,
    TrackTable,
)
from .usd_prims import PRIMVARS, PURPOSES


def check_run_settings(*, fps, frames, substeps, where: str = "options") -> None:
    """Raise ConfigError unless fps > 0, frames ≥ 1 and substeps ≥ 1 (so that dt = 1 / (fps · substeps) > 0) or
    "auto" (chosen before the run: :mod:`warpspring.analysis.step_choice`)."""
    if not (POSITIVE.accepts(fps)):
        raise ConfigError(f"{where}: fps must be a finite number > 0 (dt = 1 / (fps * substeps)), got {fps!r}")
    if not Number(1, integer=True).accepts(frames):
        raise ConfigError(f"{where}: frames must be an integer >= 1, got {frames!r}")
    if not SUBSTEPS.accepts(substeps):
        raise ConfigError(f"{where}: substeps must be an integer >= 1 (dt = 1 / (fps * substeps)) or \"auto\" (the "
                          f"fewest the stability advisor passes), got {substeps!r}")


# -- bounded nesting --------------------------------------------------------------------------------------

#: The deepest nesting of arrays and inline tables a scene file may hold (a table header counts one level per
#: dotted part). The deepest the schema uses is 5 (a per-world track's keyframes of vectors); the limit
#: keeps the parser and every check after it (recursive, like TOML's own parser) far from Python's
#: recursion limit.
MAX_NESTING = 32

#: What the nesting scan stops at: a bracket, a string's quote or a comment.
_SCAN = re.compile(r"[\[\]{}\"'#]")


def _string_end(text: str, start: int, quote: str) -> int:
    """Where the string opening at ``start`` (its first quote) ends, just past its closing quote(s); -1 when it
    does not end (the parser refuses the file). Linear: each search starts past the last."""
    multi = text.startswith(quote * 3, start)
    close = quote * 3 if multi else quote
    i = start + len(close)
    while True:
        j = text.find(close, i)
        line = -1 if multi else text.find("\n", i, j if j >= 0 else len(text))
        if j < 0 or line >= 0:
            return -1
        backslashes = 0
        while quote == '"' and text[j - 1 - backslashes] == "\\":  # an escaped quote does not close it
            backslashes += 1
        if backslashes % 2 == 0:
            return j + len(close)
        i = j + 1


def check_nesting(text: str, where: str) -> None:
    """Refuse a scene file's text whose arrays and inline tables nest deeper than :data:`MAX_NESTING`, before
    it is parsed: one pass over its brackets outside strings and comments, in time linear in its length (a
    malformed file may miscount; the parser then refuses it)."""
    depth, i = 0, 0
    while (match := _SCAN.search(text, i)) is not None:
        char, i = match.group(), match.end()
        if char == "#":
            i = text.find("\n", i)
        elif char in "\"'":
            i = _string_end(text, match.start(), char)
        else:
            depth += 1 if char in "[{" else -1
            if depth > MAX_NESTING:
                raise ConfigError(f"{where}: arrays and inline tables nest deeper than {MAX_NESTING} levels; no "
                                  "scene needs more: flatten the value")
        if i < 0:
            return


#: The largest magnitude each precision holds (a float32 value past it becomes infinite on the device).
_LARGEST = {"float32": 3.4028234663852886e38, "float64": 1.7976931348623157e308}


def check_representable(data, where: str, precision: str) -> None:
    """Refuse a number of the scene (in any table, at any depth) that the model's ``precision`` cannot hold: a
    float32 scene's 1e300 became infinite when it reached the device, and a NaN later, far from its key."""
    largest = _LARGEST.get(precision, _LARGEST["float64"])
    pending = [(data, "")]
    while pending:
        value, key = pending.pop()
        if isinstance(value, dict):
            pending.extend((v, f"{key}.{k}" if key else str(k)) for k, v in value.items())
        elif isinstance(value, (list, tuple)):
            pending.extend((v, f"{key}[{i}]") for i, v in enumerate(value))
        elif isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) > largest:
            if isinstance(value, float) and not math.isfinite(value):
                continue  # NaN and ±inf: each key's own check names them
            if key.rsplit(".", 1)[-1] in ("seed", "version"):
                continue  # integers that never reach the device as floats (their own checks bound them)
            raise ConfigError(f"{where}: {key} = {value:g} is beyond what {precision} holds (±{largest:.3g}); "
                              "use a smaller value" + (" or precision = \"float64\"" if precision == "float32" else ""))


def check_depth(data, where: str) -> None:
    """Refuse a parsed scene (dicts and lists) that nests deeper than :data:`MAX_NESTING` (without recursion)."""
    pending = [(data, 0)]
    while pending:
        value, depth = pending.pop()
        if depth > MAX_NESTING:
            raise ConfigError(f"{where}: tables and arrays nest deeper than {MAX_NESTING} levels; no scene needs "
                              "more: flatten the value")
        if isinstance(value, dict):
            pending.extend((v, depth + 1) for v in value.values())
        elif isinstance(value, (list, tuple)):
            pending.extend((v, depth + 1) for v in value)


# -- versions and renames ---------------------------------------------------------------------------------


def format_version(data: dict, where: str) -> int:
    """The file's scene format: its top-level ``version``, 1 when absent."""
    version = data.get("version", 1)
    reads = f"scene formats 1 to {SCENE_FORMAT_VERSION}"
    if not Number(1, integer=True).accepts(version):
        raise ConfigError(f"{where}: version must be an integer >= 1 (the scene format; this warpspring reads "
                          f"{reads}), got {version!r}")
    if version > SCENE_FORMAT_VERSION:
        raise ConfigError(f"{where}: scene format version {version} needs a newer warpspring: warpspring "
                          f"{__version__} reads {reads}; upgrade it (pip install --upgrade warpspring)")
    return version


def _needs(version: int, where: str, what: str) -> ConfigError:
    """The error for a feature of scene format ``version`` in a file of an older format."""
    return ConfigError(f"{where}: {what} needs scene format {version}: add version = {version} at the top of the "
                       "file, before the first [table]")


def _tables_at(data: dict, dotted: str) -> list[tuple[str, dict]]:
    """(label, table) of every table at the dotted path: each element of an array of tables, labelled
    "cloth[1]" when there are several. What is not a table is left to the schema checks."""
    found = [("", data)]
    for part in dotted.split("."):
        inner = []
        for label, table in found:
            value, name = table.get(part), f"{label}.{part}" if label else part
            if isinstance(value, dict):
                inner.append((name, value))
            elif isinstance(value, list):
                inner += [(table_label(name, i, len(value)), t) for i, t in enumerate(value) if isinstance(t, dict)]
        found = inner
    return found


def apply_renames(data: dict, version: int, where: str) -> list[str]:
    """Move every renamed key of ``data`` (a copy of the file's tables) to its new name and return one
    deprecation message per old name found. Both names in one table is an error, and so is a new name in
    a file of a format older than the rename (the file must declare the format it uses)."""
    messages = []
    for rename in RENAMED_KEYS:
        for label, table in _tables_at(data, rename.table):
            if rename.old in table and rename.new in table:
                raise ConfigError(f"{where}: [{label}] has both {rename.old} and {rename.new}, its new name: "
                                  f"keep {rename.new} only")
            if rename.new in table and version < rename.version:
                raise _needs(rename.version, where, f"[{label}] {rename.new}")
            if rename.old in table:
                table[rename.new] = table.pop(rename.old)
                upgrade = "" if version >= rename.version else f" and add version = {rename.version} at the top"
                messages.append(
                    f"{where}: [{label}] {rename.old} is deprecated: scene format {rename.version} renamed it "
                    f"{rename.new} ({rename.note}); rename it{upgrade}"
                )
    return messages


# -- checking ---------------------------------------------------------------------------------------------


def table_label(name: str, index: int, count: int) -> str:
    """How an error names a table: "cloth", or "cloth[1]" (0-based) when the file has several."""
    return name if count == 1 else f"{name}[{index}]"


def one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


class in_table:
    """Prefix a ConfigError raised inside with the scene file and the table it came from."""

    def __init__(self, where: str, table: str):
        self.prefix = f"{where}: in [{table}]: "

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if kind is not None and issubclass(kind, ConfigError):
            raise ConfigError(self.prefix + one_line(exc)) from None
        return False


def table_list(value, where: str, name: str) -> list:
    tables = [value] if isinstance(value, dict) else list(value)
    for t in tables:
        if not isinstance(t, dict):
            raise ConfigError(f"{where}: [{name}] must be a table or an array of tables")
    return tables


def _check_pins(pins: list, grid: bool, where: str, key: str) -> None:
    for p in pins:
        ok = isinstance(p, int) and not isinstance(p, bool)
        if grid:
            ok = ok or isinstance(p, str)
        if not ok:
            kinds = "corner/edge names or particle indices" if grid else "vertex indices (names are for grid cloths)"
            raise ConfigError(f"{where}: {key} takes {kinds}, got {p!r}")


def check_cloth(c: dict, where: str, label: str, *, version: int) -> None:
    """Check a [cloth] table, and turn its pin groups into :class:`PinGroupSpec` (``c`` is the scene's copy)."""
    check_table(c, SCHEMA["cloth"], where, label, version=version)
    for key in ("structural", "shear", "bend"):
        if isinstance(c.get(key), dict):  # the law's name and the plasticity's limits, checked together
            try:
                spring_law_options(key, c[key])
            except ConfigError as exc:
                raise ConfigError(f"{where}: {label}.{key}: {one_line(exc)}") from None
    if ("grid" in c) == ("mesh" in c):
        raise ConfigError(f"{where}: [{label}] needs exactly one of grid = {{nx, ny, spacing}} or mesh = 'file'")
    grid = "grid" in c
    if grid:
        missing = [k for k in ("nx", "ny", "spacing") if k not in c["grid"]]
        if missing:
            raise ConfigError(f"{where}: {label}.grid needs nx, ny and spacing; missing: {', '.join(missing)}")
    wrong = sorted((MESH_ONLY if grid else GRID_ONLY) & set(c))
    if wrong:
        kind, other = ("grid", "mesh") if grid else ("mesh", "grid")
        raise ConfigError(f"{where}: {label}.{wrong[0]} applies to a {other} cloth only, not to a {kind} cloth")
    per_particle = "particle_mass" if grid else "density"
    if ("mass" in c and per_particle in c) or ("mass" not in c and per_particle not in c and "material" not in c):
        raise ConfigError(
            f"{where}: [{label}] needs exactly one of mass (total, kg) or {per_particle} "
            f"({'kg per particle' if grid else 'kg/m²'}), or a material (its density)"
        )
    axis = c.get("rotation", {}).get("axis")
    if axis is not None and not any(axis):
        raise ConfigError(f"{where}: {label}.rotation.axis must be a nonzero vector, got {axis!r}")
    _check_pins(c.get("pin", []), grid, where, f"{label}.pin")
    if "pin_group" in c:
        groups = [c["pin_group"]] if isinstance(c["pin_group"], dict) else c["pin_group"]
        c["pin_group"] = [
            _pin_group(g, grid, where, table_label(f"{label}.pin_group", i, len(groups))) for i, g in enumerate(groups)
        ]
    if "handle" in c:
        handles = [c["handle"]] if isinstance(c["handle"], dict) else c["handle"]
        c["handle"] = [_handle(h, grid, where, table_label(f"{label}.handle", i, len(handles)))
                       for i, h in enumerate(handles)]


def _handle(handle: dict, grid: bool, where: str, key: str) -> HandleSpec:
    """A checked [[cloth.handle]] table (its keys' types are checked already) as a HandleSpec."""
    if not handle.get("particles"):
        example = '["left"]' if grid else "[0, 1]"
        raise ConfigError(f"{where}: {key}.particles is {'empty' if 'particles' in handle else 'missing'}: name "
                          f"the particles the handle grabs, e.g. particles = {example}")
    if "kp" not in handle:
        raise ConfigError(f"{where}: [{key}] needs kp = ..., its stiffness gain [N/m] (and kd, its damping [N·s/m])")
    _check_pins(handle["particles"], grid, where, f"{key}.particles")
    return HandleSpec(
        particles=list(handle["particles"]),
        kp=float(handle["kp"]),
        kd=float(handle.get("kd", 0.0)),
        max_force=float(handle["max_force"]) if "max_force" in handle else None,
        name=handle.get("name", "handle"),
        pivot=handle.get("pivot"),
        translation=make_track(handle["translation"], where, f"{key}.translation") if "translation" in handle
        else None,
        rotation=make_track(handle["rotation"], where, f"{key}.rotation") if "rotation" in handle else None,
    )


def _pin_group(group: dict, grid: bool, where: str, key: str) -> PinGroupSpec:
    """A checked [[cloth.pin_group]] table (its keys' types are checked already) as a PinGroupSpec."""
    if not group.get("pin"):
        example = '["top"]' if grid else "[0, 1]"
        raise ConfigError(f"{where}: {key}.pin is {'empty' if 'pin' in group else 'missing'}: name the particles "
                          f"the group moves, e.g. pin = {example}")
    _check_pins(group["pin"], grid, where, f"{key}.pin")
    if "translation" not in group and "rotation" not in group:
        raise ConfigError(
            f"{where}: [{key}] moves nothing: give translation = {{ times = [...], values = [...] }} and/or "
            "rotation = { times = [...], axis = [x, y, z], degrees = [...] }; for particles that stay put, "
            f"list them in pin = [...] of the cloth instead"
        )
    return PinGroupSpec(
        pin=list(group["pin"]),
        name=group.get("name", "pins"),
        pivot=group.get("pivot"),
        translation=make_track(group["translation"], where, f"{key}.translation")
        if "translation" in group else None,
        rotation=make_track(group["rotation"], where, f"{key}.rotation", rotation=True)
        if "rotation" in group else None,
    )


def check_collider(c: dict, where: str, label: str, *, version: int) -> None:
    """Check a [[collider]] table, and turn its tracks into :class:`Track` objects (``c`` is the scene's copy)."""
    check_table(c, SCHEMA["collider"], where, label, version=version)
    kind = c.get("type")
    if kind is None:
        raise ConfigError(f"{where}: {label}.type is missing: set type = one of {', '.join(COLLIDER_TYPES)}")
    types = COLLIDER_TYPES if version >= 2 else FORMAT_1_COLLIDERS
    if kind not in types:
        newer = [t for t in COLLIDER_TYPES if t not in FORMAT_1_COLLIDERS]
        hint = (f" (in scene format {version}; {', '.join(newer[:-1])} and {newer[-1]} colliders need scene format 2: "
                "add version = 2 at the top of the file, before the first [table])") if kind in COLLIDER_TYPES else ""
        raise ConfigError(f"{where}: {label}.type must be one of {', '.join(types)}, got {kind!r}{hint}")
    extra = sorted(set(c) - COLLIDER_KEYS[kind])
    if extra:
        raise ConfigError(
            f"{where}: {label}.{extra[0]} does not apply to a {kind} collider; "
            f"it takes: {', '.join(sorted(COLLIDER_KEYS[kind] - {'type'}))}"
        )
    needs, shown = COLLIDER_NEEDS.get(kind, (set(), ""))
    missing = sorted(needs - set(c))
    if missing:
        raise ConfigError(f"{where}: a {kind} collider ([{label}]) needs {shown}; missing: {', '.join(missing)}")
    if "half_extents" in c and not all(h > 0 for h in c["half_extents"]):
        raise ConfigError(f"{where}: {label}.half_extents must be 3 numbers > 0 (half the box's size along its own "
                          f"x, y, z [m]), got {c['half_extents']!r}")
    if c.get("restitution", 0.0) > 1.0:
        raise ConfigError(f"{where}: {label}.restitution must be a number from 0 to 1 (the share of the normal speed "
                          f"an impact keeps), got {c['restitution']!r}")
    for key in ("translation", "rotation"):
        if key in c:
            c[key] = make_track(c[key], where, f"{label}.{key}", rotation=key == "rotation")


def check_table(table: dict, schema: dict, where: str, name: str, *, version: int) -> None:
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: [{name}] must be a table")
    for key, value in table.items():
        if key not in schema:
            hint = " (version belongs at the top of the file, before the first [table])" if key == "version" else ""
            raise ConfigError(
                f"{where}: unknown key {key!r} in [{name or 'top level'}]; allowed: {', '.join(schema)}{hint}"
            )
        _check_value(value, schema[key], where, f"{name}.{key}" if name else key, version=version)


def check_soft_body_pin(pin, where: str, label: str) -> None:
    """A soft body's ``pin = { min = [x, y, z], max = [x, y, z] }`` (types checked): both corners, min ≤ max."""
    if pin is None:
        return
    if "min" not in pin or "max" not in pin:
        raise ConfigError(f"{where}: {label}.pin needs min = [x, y, z] and max = [x, y, z], the corners [m] of the box "
                          "whose particles are pinned")
    if any(lo > hi for lo, hi in zip(pin["min"], pin["max"])):
        raise ConfigError(f"{where}: {label}.pin has min {pin['min']} above max {pin['max']} on some axis: swap them")


def check_soft_body_element(element, where: str, label: str) -> None:
    """A soft body's ``element`` (types checked): one of the tet elements; the builder checks that it goes with
    ``elasticity = "neohookean"``."""
    if element is not None and element not in ELEMENTS:
        raise ConfigError(f"{where}: {label}.element must be one of {', '.join(map(repr, ELEMENTS))}, got {element!r} "
                          "(\"tet10\": quadratic tets, with elasticity = \"neohookean\")")


def check_export_options(out: dict, where: str) -> dict:
    """The ``[output]`` options passed to the USD writer as they are, their names and choices checked."""
    options = {key: out[key] for key in ("primvars", "start_frame", "collider_purpose") if key in out}
    for name in options.get("primvars", []):
        if name not in PRIMVARS:
            raise ConfigError(f"{where}: output.primvars lists {name!r}: choose from {', '.join(map(repr, PRIMVARS))}")
    purpose = options.get("collider_purpose", "guide")
    if purpose not in PURPOSES:
        raise ConfigError(f"{where}: output.collider_purpose must be one of {', '.join(map(repr, PURPOSES))}, got "
                          f"{purpose!r}")
    return options


def _check_value(value, expected, where: str, key: str, *, version: int) -> None:
    if isinstance(expected, Since):
        if version < expected.version:
            raise _needs(expected.version, where, f"[{key}]" if expected.spec is dict else key)
        _check_value(value, expected.spec, where, key, version=version)
        return
    if isinstance(expected, PerWorld):
        vector = isinstance(expected.value, Live) and expected.value.value is VECTOR
        if vector and isinstance(value, list) and value and all(NUMBER.accepts(v) for v in value):
            raise ConfigError(f"{where}: {key} must list one [x, y, z] per world, e.g. [[0, 0, -9.81], [0, 0, -1.62]], "
                              f"got {value!r}; for one value in every world, set it in [world]")
        if not isinstance(value, list):
            entry = "a value or a track table" if isinstance(expected.value, Live) else "a number"
            raise ConfigError(f"{where}: {key} must be a list with one entry per world ({entry} each), got {value!r}")
        for i, entry in enumerate(value):
            _check_value(entry, expected.value, where, f"{key}[{i}]", version=version)
        return
    if isinstance(expected, Live):
        if not isinstance(value, dict):
            _check_value(value, expected.value, where, key, version=version)
            return
        if version < expected.tracks_since:
            raise _needs(expected.tracks_since, where, f"{key} as a track table")
        expected = TrackTable(expected.value)
    if isinstance(expected, TrackTable):
        _check_track(value, expected, where, key, version=version)
        return
    if isinstance(expected, Tables):
        tables = [value] if isinstance(value, dict) else value
        if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
            raise ConfigError(f"{where}: {key} must be a table or an array of tables [[{key}]], got {value!r}")
        for i, t in enumerate(tables):
            check_table(t, expected.schema, where, table_label(key, i, len(tables)), version=version)
        return
    if isinstance(expected, dict):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: {key} must be a table {{{', '.join(expected)}}}, got {value!r}")
        check_table(value, expected, where, key, version=version)
        return
    if isinstance(expected, tuple) and any(isinstance(e, dict) for e in expected):
        if isinstance(value, dict):
            check_table(value, next(e for e in expected if isinstance(e, dict)), where, key, version=version)
        elif not isinstance(value, bool):
            raise ConfigError(f"{where}: {key} must be a table {{ke = ..., kd = ...}}, true or false, got {value!r}")
        return
    if expected is VECTOR:
        ok = isinstance(value, list) and len(value) == 3 and all(NUMBER.accepts(v) for v in value)
        if not ok:
            raise ConfigError(f"{where}: {key} must be a list of 3 finite numbers [x, y, z], got {value!r}")
        return
    if expected is QUATERNION:
        ok = isinstance(value, list) and len(value) == 4 and all(NUMBER.accepts(v) for v in value) and any(value)
        if not ok:
            raise ConfigError(f"{where}: {key} must be a quaternion [x, y, z, w] of 4 finite numbers, not all zero "
                              f"(the identity is [0, 0, 0, 1]), got {value!r}")
        return
    if isinstance(expected, Number):
        if not expected.accepts(value):
            raise ConfigError(f"{where}: {key} must be {expected.describe()}, got {value!r}")
        return
    types = expected if isinstance(expected, tuple) else (expected,)
    ok = isinstance(value, types) and not (isinstance(value, bool) and bool not in types)
    if not ok:
        names = " or ".join(TYPE_NAMES.get(t, t.__name__) for t in types)
        raise ConfigError(f"{where}: {key} must be {names}, got {value!r}")


def _check_track(table, spec: TrackTable, where: str, key: str, *, version: int) -> None:
    """Check a track table's keys, key counts and every value (the ordering of its times: make_track)."""
    schema, values = (ROTATION_TRACK_TABLE, "degrees") if spec.rotation else (TRACK_TABLE, "values")
    shape = (f"{{ times = [...], axis = [x, y, z], {values} = [...] }}" if spec.rotation
             else f"{{ times = [...], {values} = [...] }}")
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: {key} must be a track table {shape}, got {table!r}")
    check_table(table, schema, where, key, version=version)
    missing = [k for k in schema if k not in table and k not in ("interpolation", "extrapolation")]
    if missing:
        raise ConfigError(f"{where}: track {key} needs {shape}; missing: {', '.join(missing)}")
    times = table["times"]
    if not times:
        raise ConfigError(f"{where}: {key}.times is empty: give at least one key time [s]")
    for i, t in enumerate(times):
        _check_value(t, NUMBER, where, f"{key}.times[{i}]", version=version)
    if len(table[values]) != len(times):
        raise ConfigError(f"{where}: track {key} has {len(times)} times but {len(table[values])} {values}: give "
                          f"one per time")
    for i, v in enumerate(table[values]):
        _check_value(v, NUMBER if spec.rotation else spec.value, where, f"{key}.{values}[{i}]", version=version)
    for option, names in (("interpolation", INTERPOLATIONS), ("extrapolation", EXTRAPOLATIONS)):
        if option in table and table[option] not in names:
            raise ConfigError(f"{where}: {key}.{option} must be one of {', '.join(names)}, got {table[option]!r}")


def make_track(table: dict, where: str, key: str, *, rotation: bool = False) -> Track:
    """A checked track table as a :class:`Track` (which checks that the times increase); ``rotation``: a
    rotation track ``{ times, axis, degrees }``."""
    options = dict(interpolation=table.get("interpolation", "linear"), extrapolation=table.get("extrapolation", "hold"))
    try:
        if rotation:
            return Track.rotation(table["times"], axis=table["axis"], degrees=table["degrees"], **options)
        return Track(table["times"], table["values"], **options)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {key}: {one_line(exc)}") from None
