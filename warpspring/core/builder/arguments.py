"""Argument checks the builder's recipes share (points, per-item values, indices, quaternions: each raises a
one-line ConfigError naming the quantity), and the prim names a recipe's mesh must not take."""

from __future__ import annotations

import numpy as np

from ...errors import ConfigError

#: Prim names under /World that the USD writer uses itself: a mesh named so gets a suffix.
RESERVED_PRIM_NAMES = ("particles", "springs", "colliders")


def _quaternion(value) -> np.ndarray:
    q = np.asarray(value, dtype=np.float64)
    if q.shape != (4,) or not np.isfinite(q).all() or np.linalg.norm(q) == 0.0:
        raise ConfigError(f"rotation must be a nonzero quaternion (x, y, z, w), got {value!r}")
    return q / np.linalg.norm(q)


def _points(name: str, value, count: int | None = None) -> np.ndarray:
    p = np.asarray(value, dtype=np.float64)
    if count is not None and p.shape == (3,):
        p = np.broadcast_to(p, (count, 3))
    if p.ndim != 2 or p.shape[1] != 3 or (count is not None and len(p) != count):
        want = f"[{count}, 3]" if count is not None else "[n, 3]"
        raise ConfigError(f"{name} must have shape {want}, got {p.shape}")
    bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
    if len(bad):
        raise ConfigError(f"{name}: entry {int(bad[0])} is not finite ({p[bad[0]].tolist()}); fix the input data")
    return np.array(p)


def _per_item(name: str, value, n: int, *, positive: bool = False) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(n, float(v))
    if v.shape != (n,):
        raise ConfigError(f"{name} must be a number or an array of shape ({n},), got shape {v.shape}")
    bad = np.flatnonzero(~np.isfinite(v) | ((v <= 0.0) if positive else (v < 0.0)))
    if len(bad):
        need = "> 0" if positive else ">= 0"
        raise ConfigError(f"{name} must be finite and {need}, got {v[bad[0]]} (entry {int(bad[0])})")
    return v


def _indices(name: str, value, bound: int) -> np.ndarray:
    idx = np.asarray(value)
    if idx.size and not np.issubdtype(idx.dtype, np.integer):
        raise ConfigError(f"{name} indices must be integers, got {idx.dtype}")
    idx = idx.astype(np.int64).ravel()
    bad = idx[(idx < 0) | (idx >= bound)]
    if len(bad):
        raise ConfigError(f"{name} index {int(bad[0])} is out of range: valid indices are 0..{bound - 1}")
    return idx
