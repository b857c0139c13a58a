"""Small rotation helpers on NumPy arrays; quaternions are (x, y, z, w), Warp's convention."""

from __future__ import annotations

import numpy as np


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of a rotation by ``angle`` [rad] about ``axis`` (normalised here)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    half = 0.5 * float(angle)
    return np.array([*(a * np.sin(half)), np.cos(half)])


def quat_to_matrix(q) -> np.ndarray:
    """3 × 3 rotation matrix of a unit quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(q, dtype=np.float64)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_between(a, b) -> np.ndarray:
    """Shortest-arc unit quaternion (x, y, z, w) rotating unit vector ``a`` onto unit vector ``b``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c = np.dot(a, b)
    if c < -1.0 + 1e-12:  # opposite: rotate by π about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        return quat_from_axis_angle(axis, np.pi)
    q = np.array([*np.cross(a, b), 1.0 + c])
    return q / np.linalg.norm(q)
