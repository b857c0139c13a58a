"""Argument checks shared by the public API: each raises a ConfigError that names the quantity and
says what it must be; and the readable formatting of durations used in messages."""

from __future__ import annotations

import math
import os

import numpy as np
import warp as wp

from .errors import ConfigError

_REAL = (int, float, np.integer, np.floating)


def number(name: str, value, *, minimum: float = -math.inf, inclusive: bool = True) -> float:
    """``value`` as a float if it is a finite real number (not a bool) ≥ (or >) ``minimum``."""
    ok = isinstance(value, _REAL) and not isinstance(value, bool)
    v = float(value) if ok else float("nan")
    if not math.isfinite(v) or v < minimum or (v == minimum and not inclusive):
        bound = "" if minimum == -math.inf else f" {'>=' if inclusive else '>'} {minimum:g}"
        raise ConfigError(f"{name} must be a finite number{bound}, got {value!r}")
    return v


def positive(name: str, value) -> float:
    """``value`` as a float if it is a finite number > 0."""
    return number(name, value, minimum=0.0, inclusive=False)


def non_negative(name: str, value) -> float:
    """``value`` as a float if it is a finite number ≥ 0."""
    return number(name, value, minimum=0.0, inclusive=True)


def vector(name: str, value) -> np.ndarray:
    """``value`` as a float64 array of shape [3] if it is 3 finite numbers."""
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        v = None
    if v is None or v.shape != (3,):
        raise ConfigError(f"{name} must be 3 numbers [x, y, z], got {value!r}")
    if not np.isfinite(v).all():
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return v


def count(name: str, value, *, minimum: int) -> int:
    """``value`` if it is an integer (not a bool) ≥ ``minimum``."""
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < minimum:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def output_dir(path: str | os.PathLike) -> str:
    """``path`` as a string if it names a folder that exists and is writable, or can be created."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise ConfigError(f"output directory {path!r} is a file: name a folder")
    existing = os.path.abspath(path)
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"output directory {path!r} cannot be written: {existing} is not writable")
    return path


def format_duration(seconds: float) -> str:
    """A duration in readable units: "1.81 ms", "0.152 s", "3.2 µs"."""
    if seconds >= 1.0:
        return f"{seconds:.4g} s"
    if seconds >= 1e-3:
        return f"{seconds * 1e3:.4g} ms"
    return f"{seconds * 1e6:.4g} µs"


def identifier(name: str, value) -> str:
    """``value`` if it is a valid USD prim name (letters, digits and ``_``, not starting with a digit)."""
    if not isinstance(value, str) or not value.isascii() or not value.replace("_", "a").isalnum() or value[0].isdigit():
        raise ConfigError(f"{name} must be a name of letters, digits and _ that does not start with a digit "
                          f"(it names a USD prim), got {value!r}")
    return value


def device(name: str | None):
    """The Warp device called ``name`` (None: Warp's default), or a ConfigError listing those present."""
    if name is None:
        return wp.get_device()
    try:
        device = wp.get_device(name)
    except (RuntimeError, ValueError):
        device = None
    if device is None:
        found = ", ".join(d.alias for d in wp.get_devices())
        raise ConfigError(f"device {name!r} is not available; this machine has: {found}")
    return device
