"""Floating-point precision as a kernel-factory axis.

Every kernel factory takes the scalar type (``wp.float32`` or ``wp.float64``) and builds its kernels
with the matching vector and transform types, so one kernel source serves both precisions.
"""

import warp as wp

SCALAR_TYPES = {"float32": wp.float32, "float64": wp.float64}

_VEC3 = {wp.float32: wp.vec3f, wp.float64: wp.vec3d}
_TRANSFORM = {wp.float32: wp.transformf, wp.float64: wp.transformd}
_MAT33 = {wp.float32: wp.mat33f, wp.float64: wp.mat33d}


def scalar_type(precision: str) -> type:
    """The Warp scalar type of a precision name ("float32" or "float64")."""
    try:
        return SCALAR_TYPES[precision]
    except KeyError:
        raise ValueError(f"precision must be one of {sorted(SCALAR_TYPES)}, got {precision!r}") from None


def vec3_type(scalar: type) -> type:
    """The 3-vector type of a scalar type."""
    return _VEC3[scalar]


def transform_type(scalar: type) -> type:
    """The rigid-transform type of a scalar type."""
    return _TRANSFORM[scalar]


def mat33_type(scalar: type) -> type:
    """The 3 × 3 matrix type of a scalar type."""
    return _MAT33[scalar]
