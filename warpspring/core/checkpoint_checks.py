"""What a checkpoint is checked against before it is restored: the model's fingerprint (:func:`model_fingerprint`,
which the header records and a resumed run compares with the model it built) and the header's fields
(:func:`check_header`: each field's type and range) and state (:func:`check_finite`), each refused with one
line naming the checkpoint."""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import math

import numpy as np
import warp as wp

from ..errors import ConfigError
from .guard_records import GuardReport
from .records import STABILIZER_INPUTS, Stabilizers


def integrator_settings(integrator) -> dict:
    """The integrator's settings that are live values: the keyword-only options of its class that are
    settable properties (dopri5's ``tolerance`` and ``max_steps``, implicit Euler's ``cg_iterations`` and
    ``cg_tolerance``), by name."""
    cls = type(integrator)
    names = [p.name for p in inspect.signature(cls).parameters.values() if p.kind is p.KEYWORD_ONLY]
    return {name: getattr(integrator, name) for name in names
            if isinstance(getattr(cls, name, None), property) and getattr(cls, name).fset is not None}


# -- the model's fingerprint ----------------------------------------------------------------------------------

#: The model's arrays a fingerprint hashes, each its own key: what the scene builds and a run does not change
#: (the live inputs, held worlds, plastic springs' state and the families' host-set values are not here).
FINGERPRINT_ARRAYS = (
    "particle_q",  # the initial positions [m]
    "particle_qd",  # the initial velocities [m/s]
    "particle_mass", "particle_radius", "particle_flags",  # flags: pins (an emitter's pool is masked out)
    "spring_indices", "spring_rest_length", "spring_stiffness", "spring_damping",
    "spring_yield_strain", "spring_yield_force", "spring_yield_rate", "spring_hardening", "spring_break_strain",
    "spring_compression_ratio",
    "hinge_indices", "hinge_rest_angle", "hinge_stiffness", "hinge_damping",
    "tri_indices",
    "shape_rest", "shape_translation_track", "shape_rotation_track",
)

#: Element families' live arrays that a run moves (the handles' target frames, which their tracks set at every
#: force evaluation): not part of the fingerprint (their tracks are).
FAMILY_TARGETS = ("translation", "velocity", "rotation", "angular")


def model_fingerprint(sim) -> dict[str, dict[str, str]]:
    """The model ``sim`` runs, as built, by key: ``{"hash": 16 hex digits, "summary": a short readable
    description}``. Keys: the counts and precision, each of :data:`FINGERPRINT_ARRAYS` (hashed over dtype,
    shape and bytes), the spring law, the colliders as built (shapes, their tracks and meshes), the element
    families (names and fixed values), pin groups, emitters, the contact options, the integrator with its
    settings, fps, substeps and dt. Live inputs (gravity, drag, stabiliser limits and their tracks; which
    stabilisers are on is part of it), the end time and the output are not part of it: a resumed run may change them. Reads the device."""
    model = sim.model
    found = {
        "precision": model.precision,
        "worlds": model.world_count,
        "particles": model.particle_count,
        "integrator": sim.integrator.name,
        "integrator_settings": integrator_settings(sim.integrator),
        "fps": float(sim.fps),
        "substeps": int(sim.substeps),
        "dt": float(sim.dt),
        "spring_law": model.spring_material_law,
        "colliders": list(model.shapes),
        "families": [(family.name, family.tracks(), {name: array for name, array in family.live_arrays().items()
                                                     if name not in FAMILY_TARGETS}) for family in model.families],
        "pin_groups": model.pin_groups,
        "emitters": [(e.name, e.first, e.capacity) for e in model.emitters],
        "contacts": (model.contact_stage, model.contact_slots, model.contact_triangles, model.contact_swept),
        "stabilizers": sorted(name for name in STABILIZER_INPUTS if model.stabilizers.enabled(name)),
    }
    for name in FINGERPRINT_ARRAYS:
        array = getattr(model, name, None)
        if array is None:
            continue
        values = array.numpy()
        if name == "particle_flags" and model.emitters:  # births and deaths flip an emitter pool's flags
            values = values.reshape(model.world_count, model.particle_count).copy()
            for e in model.emitters:
                values[:, e.first: e.first + e.capacity] = 0
        found[name] = values
    return {key: {"hash": _digest(value), "summary": _describe(value)} for key, value in found.items()}


def _digest(value) -> str:
    """A hash of ``value`` that depends only on its contents (arrays by dtype, shape and bytes; dataclasses,
    dicts and objects by their fields, in name order), 16 hex digits."""
    h = hashlib.sha256()
    _feed(h, value, 0)
    return h.hexdigest()[:16]


def _feed(h, value, depth: int) -> None:
    if depth > 12:  # a reference loop or a deep object: its type stands in
        h.update(f"<{type(value).__name__}>".encode())
        return
    if isinstance(value, wp.array):
        value = value.numpy()
    if isinstance(value, np.ndarray):
        h.update(f"array{value.dtype.str}{value.shape}".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif value is None or isinstance(value, (bool, int, float, str, np.generic)):
        h.update(f"{type(value).__name__}:{value!r};".encode())
    elif isinstance(value, (list, tuple)):
        h.update(f"[{len(value)}".encode())
        for item in value:
            _feed(h, item, depth + 1)
        h.update(b"]")
    elif isinstance(value, dict):
        h.update(f"{{{len(value)}".encode())
        for key in sorted(value, key=str):
            h.update(f"{key}=".encode())
            _feed(h, value[key], depth + 1)
        h.update(b"}")
    elif dataclasses.is_dataclass(value):
        _feed(h, {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}, depth + 1)
    elif hasattr(value, "__dict__"):
        h.update(type(value).__name__.encode())
        _feed(h, {k: v for k, v in vars(value).items() if not k.startswith("_")}, depth + 1)
    else:  # a Warp struct, a device, a function: its type only (no address-bearing repr)
        h.update(f"<{type(value).__name__}>".encode())


def _describe(value) -> str:
    """A short readable summary of a fingerprint's value (what a refusal shows beside the key)."""
    if isinstance(value, np.ndarray):
        text = f"{value.dtype} {list(value.shape)}"
        if value.size and value.dtype.kind in "fiu" and value.dtype.names is None:
            flat = value.astype(np.float64).reshape(-1)
            low, high = float(flat.min()), float(flat.max())
            text += f" {low:.6g}" if low == high else f" {low:.6g}…{high:.6g}"
        return text
    if isinstance(value, (bool, int, float, str)) or value is None:
        return repr(value)
    if dataclasses.is_dataclass(value):
        fields = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
        return ", ".join(f"{k}={v!r}" for k, v in fields.items() if isinstance(v, (bool, int, float, str)))[:120]
    if isinstance(value, dict):
        return ", ".join(f"{k}={_describe(v)}" for k, v in sorted(value.items()))[:120]
    if isinstance(value, (list, tuple)):
        return f"{len(value)} item{'s' if len(value) != 1 else ''}"
    return type(value).__name__


def summary(entry) -> str:
    return "absent" if not isinstance(entry, dict) else str(entry.get("summary", "?"))


# -- the header's checks --------------------------------------------------------------------------------------


def _is_int(value, minimum: int = 0) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _header_rules() -> dict:
    """Each header field: (a test of its value, what it must be)."""
    text = (lambda v: isinstance(v, str), "a string")
    count = (_is_int, "an integer >= 0")
    return {
        "format_version": (lambda v: _is_int(v, 1), "an integer >= 1"),
        "warpspring_version": text,
        "warp_version": text,
        "device": text,
        "precision": (lambda v: v in ("float32", "float64"), '"float32" or "float64"'),
        "worlds": (lambda v: _is_int(v, 1), "an integer >= 1"),
        "particles": count,
        "springs": count,
        "hinges": count,
        "families": (lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v), "a list of names"),
        "colliders": count,
        "integrator": text,
        "integrator_settings": (lambda v: isinstance(v, dict) and all(
            isinstance(k, str) and (_is_number(x) or isinstance(x, bool) or x is None) for k, x in v.items()),
            "a table of finite numbers (or null: the integrator chooses it, e.g. implicit Euler's cg_iterations)"),
        "fps": (lambda v: _is_number(v) and v > 0, "a finite number > 0"),
        "substeps": (lambda v: _is_int(v, 1), "an integer >= 1"),
        "frame": count,
        "switches": (_switches_ok, "a table of gravity, drag, hold_worlds (true or false) and stabilizers"),
        "world_failures": (lambda v: isinstance(v, list), "a list"),
        "arrays": (lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v), "a list of array names"),
    }


def _switches_ok(value) -> bool:
    if not isinstance(value, dict) or not all(isinstance(value.get(k), bool) for k in ("gravity", "drag", "hold_worlds")):
        return False
    stabilizers = value.get("stabilizers")
    names = {f.name for f in dataclasses.fields(Stabilizers)}
    return isinstance(stabilizers, dict) and set(stabilizers) <= names and all(
        x is None or isinstance(x, bool) or _is_number(x) for x in stabilizers.values())


def check_header(header: dict, name: str) -> None:
    """Every field of a checkpoint's header of the right type and in range, else one line naming the checkpoint
    and the field."""
    def bad(field: str, value, must: str) -> ConfigError:
        shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:57] + "..."
        return ConfigError(f"{name} has a damaged header: {field} is {shown}, but must be {must}; save it again")

    for field, (test, must) in _header_rules().items():
        if field not in header:
            if field in ("warpspring_version", "warp_version", "device"):
                continue  # informative only
            raise ConfigError(f"{name} has a damaged header: it lacks {field}; save it again")
        if not test(header[field]):
            raise bad(field, header[field], must)
    report_fields = {f.name for f in dataclasses.fields(GuardReport)}
    for item in header["world_failures"]:
        if not (isinstance(item, dict) and _is_int(item.get("world")) and item["world"] < header["worlds"]
                and _is_int(item.get("frame")) and item["frame"] <= header["frame"]
                and isinstance(item.get("report"), dict) and set(item["report"]) <= report_fields):
            raise bad("world_failures", item, f"a table of world (0..{header['worlds'] - 1}), frame "
                      f"(0..{header['frame']}) and the guard's report")
    model = header.get("model")
    if model is not None and not (isinstance(model, dict) and all(
            isinstance(entry, dict) and isinstance(entry.get("hash"), str) and isinstance(entry.get("summary"), str)
            for entry in model.values())):
        raise bad("model", model, "a table of {hash, summary} entries")


def check_finite(header: dict, arrays: dict[str, np.ndarray], name: str) -> None:
    """Refuse a checkpoint whose state (positions, velocities, clocks) is not finite in a world the guard did
    not stop (a stopped world's last state may be anything: it is held, never stepped again)."""
    worlds = header["worlds"]
    stopped = {item["world"] for item in header["world_failures"]}
    for key in ("state/particle_q", "state/particle_qd", "state/time"):
        values = arrays.get(key)
        if values is None:
            continue
        if values.dtype.kind not in "fc" or values.size == 0:
            continue
        if values.shape[0] % worlds:
            raise ConfigError(f"{name} holds {key} of shape {values.shape}, not a multiple of its {worlds} "
                              "worlds: it is damaged; save it again")
        per_world = values.reshape(worlds, -1)
        bad = [w for w in range(worlds) if w not in stopped and not np.isfinite(per_world[w]).all()]
        if bad:
            raise ConfigError(f"{name} holds a non-finite {key.split('/', 1)[1]} (NaN or infinite) in world "
                              f"{bad[0]}: the run had already gone bad when it was saved; resume from an earlier "
                              "checkpoint or start over")
