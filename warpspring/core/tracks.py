"""Keyframe tracks: one way to animate any input over time, evaluated on the device inside the substeps.

A :class:`Track` is a list of keys (times in seconds, values) and an interpolation. Gravity, drag and
every stabiliser threshold take one (``model.set_track("gravity", track)``, or a table of keys in a scene
file), and so do the translation and rotation of a pin group (``ModelBuilder.add_pin_group``). A model
packs all its tracks into one float64 table (``kernels/tracks.py``); the integrators evaluate them at the
time of every state they evaluate forces at (stage times included), so an animated input is exact at
each substep and each Runge-Kutta stage, with no host round trip.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ..errors import ConfigError
from ..kernels.inputs import INPUTS
from ..kernels.tracks import (
    EXTRAPOLATE_CYCLE,
    EXTRAPOLATE_HOLD,
    TRACK_LINEAR,
    TRACK_SMOOTH,
    TRACK_STEP,
    Tracks,
    apply_input_tracks_kernel,
)

#: Interpolation names and their kernel codes.
INTERPOLATIONS = {"step": TRACK_STEP, "linear": TRACK_LINEAR, "smooth": TRACK_SMOOTH}
#: Extrapolation names and their kernel codes.
EXTRAPOLATIONS = {"hold": EXTRAPOLATE_HOLD, "cycle": EXTRAPOLATE_CYCLE}


@dataclass(frozen=True, eq=False)
class Track:
    """Keyframes of an input: its value at given times, and how to fill the time between them.

    Attributes:
        times: key times [s], shape [k], strictly increasing, k ≥ 1.
        values: key values in the input's unit, shape [k] (a scalar input) or [k, 3] (a vector input:
            gravity [m/s²], a translation [m], a rotation vector [rad]).
        interpolation: "step" (hold each key's value until the next key), "linear", or "smooth" (C¹
            cubic Hermite with monotone derivatives, Fritsch-Carlson/PCHIP: it never overshoots its keys).
        extrapolation: "hold" (the first value before the first key, the last after the last) or "cycle"
            (the track repeats with period times[-1] - times[0]).

    Example:
        >>> Track([0.0, 1.0, 2.0], [[0, 0, -9.81], [0, 0, -1.62], [0, 0, -9.81]], interpolation="linear")
    """

    times: np.ndarray
    values: np.ndarray
    interpolation: str = "linear"
    extrapolation: str = "hold"

    def __init__(self, times, values, *, interpolation: str = "linear", extrapolation: str = "hold"):
        t = np.asarray(times, dtype=np.float64)
        if t.ndim != 1 or len(t) == 0:
            raise ConfigError(f"track times must be a non-empty list of seconds, got shape {t.shape}")
        if not np.isfinite(t).all():
            raise ConfigError("track times must be finite")
        steps = np.diff(t)
        if (steps <= 0.0).any():
            k = int(np.flatnonzero(steps <= 0.0)[0])
            raise ConfigError(
                f"track times must increase strictly: key {k + 1} at {t[k + 1]:g} s does not come after key {k} "
                f"at {t[k]:g} s"
            )
        v = np.asarray(values, dtype=np.float64)
        if v.ndim not in (1, 2) or len(v) != len(t) or (v.ndim == 2 and v.shape[1] not in (1, 3)):
            raise ConfigError(
                f"a track of {len(t)} keys needs {len(t)} values, each a number or 3 numbers; got shape {v.shape}"
            )
        if not np.isfinite(v).all():
            raise ConfigError("track values must be finite")
        if interpolation not in INTERPOLATIONS:
            raise ConfigError(f"track interpolation must be one of {', '.join(INTERPOLATIONS)}, got {interpolation!r}")
        if extrapolation not in EXTRAPOLATIONS:
            raise ConfigError(f"track extrapolation must be one of {', '.join(EXTRAPOLATIONS)}, got {extrapolation!r}")
        if extrapolation == "cycle" and len(t) < 2:
            raise ConfigError("a cyclic track needs at least two keys (its period is times[-1] - times[0])")
        t.flags.writeable = False
        v = v.reshape(len(t), -1)
        v.flags.writeable = False
        object.__setattr__(self, "times", t)
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "interpolation", interpolation)
        object.__setattr__(self, "extrapolation", extrapolation)

    @property
    def width(self) -> int:
        """Components per value: 1 (a scalar track) or 3 (a vector track)."""
        return self.values.shape[1]

    @classmethod
    def rotation(cls, times, *, axis, degrees, interpolation: str = "linear", extrapolation: str = "hold") -> Track:
        """A rotation about a fixed ``axis`` by ``degrees`` [°] at each key: a track of rotation vectors
        [rad]. Angles interpolate as numbers, so a segment may turn by more than 180° and "smooth" applies."""
        a = np.asarray(axis, dtype=np.float64)
        if a.shape != (3,) or not np.isfinite(a).all() or not np.linalg.norm(a) > 0.0:
            raise ConfigError(f"a rotation axis must be 3 finite numbers, not all zero; got {axis!r}")
        angles = np.radians(np.asarray(degrees, dtype=np.float64))
        if angles.ndim != 1:
            raise ConfigError(f"rotation degrees must be a list of numbers, one per key; got shape {angles.shape}")
        return cls(times, angles[:, None] * (a / np.linalg.norm(a)), interpolation=interpolation,
                   extrapolation=extrapolation)

    def tangents(self) -> np.ndarray:
        """The derivative [value/s] at each key used by smooth interpolation, shape [k, width]: PCHIP's
        monotone (Fritsch-Carlson) choice, zero for a single key, the slope for two."""
        if len(self.times) < 2:
            return np.zeros_like(self.values)
        from scipy.interpolate import PchipInterpolator

        return PchipInterpolator(self.times, self.values, axis=0).derivative()(self.times)

    def sample(self, t) -> tuple[np.ndarray, np.ndarray]:
        """The value and rate of change at times ``t`` [s], evaluated on the host in float64 (the reference
        the device evaluation is tested against): shapes [len(t), width]."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        times, values = self.times, self.values
        if self.extrapolation == "cycle":
            period = times[-1] - times[0]
            t = t - np.floor((t - times[0]) / period) * period
        value = np.empty((len(t), self.width))
        rate = np.zeros((len(t), self.width))
        before, after = t < times[0], t > times[-1]
        value[before] = values[0]
        value[after] = values[-1]
        inside = ~(before | after)
        if len(times) == 1:
            value[inside] = values[0]
            return value, rate
        a = np.clip(np.searchsorted(times, t[inside], side="right") - 1, 0, len(times) - 2)
        h = times[a + 1] - times[a]
        s = ((t[inside] - times[a]) / h)[:, None]
        va, vb = values[a], values[a + 1]
        if self.interpolation == "step":
            value[inside] = np.where(t[inside, None] >= times[a + 1, None], vb, va)
        elif self.interpolation == "linear":
            value[inside] = va + s * (vb - va)
            rate[inside] = (vb - va) / h[:, None]
        else:
            m = self.tangents()
            ma, mb = m[a] * h[:, None], m[a + 1] * h[:, None]
            value[inside] = ((2 * s**3 - 3 * s**2 + 1) * va + (s**3 - 2 * s**2 + s) * ma + (3 * s**2 - 2 * s**3) * vb
                             + (s**3 - s**2) * mb)
            rate[inside] = ((6 * s**2 - 6 * s) * (va - vb) + (3 * s**2 - 4 * s + 1) * ma + (3 * s**2 - 2 * s) * mb) / h[
                :, None
            ]
        return value, rate


def input_track(name: str, track: Track | None) -> Track | None:
    """``track`` checked as a keyframe track of the live input ``name`` (see ``kernels.inputs.INPUTS``;
    ``None`` passes once the name is checked), or a ConfigError naming the inputs or the expected width."""
    if name not in INPUTS:
        raise ConfigError(f"there is no live input {name!r} to animate; inputs: {', '.join(INPUTS)}")
    return None if track is None else as_track(name, track, INPUTS[name][1])


def as_track(name: str, value, width: int) -> Track:
    """``value`` as a Track of ``width`` components for the input ``name``, or a ConfigError."""
    if not isinstance(value, Track):
        raise ConfigError(f"{name} must be a warpspring.Track, got {type(value).__name__}")
    if value.width != width:
        unit = "3-vectors" if width == 3 else "numbers"
        raise ConfigError(f"a track of {name} needs values that are {unit}, got {value.width} component(s) per key")
    return value


class TrackTable:
    """The tracks of one model on its device, packed into one :class:`~warpspring.kernels.tracks.Tracks`.

    Attributes:
        tracks: the host tracks, in table order.
        table: the device struct the kernels read.
    """

    def __init__(self, tracks: list[Track], device):
        self.tracks = list(tracks)
        counts = [len(t.times) for t in self.tracks]
        start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)

        def keys(values_of):
            rows = [np.pad(values_of(t), ((0, 0), (0, 3 - t.width))) for t in self.tracks]
            return np.concatenate(rows) if rows else np.zeros((0, 3))

        table = Tracks()
        table.key_start = wp.array(start, dtype=wp.int32, device=device)
        table.time = wp.array(np.concatenate([t.times for t in self.tracks]) if self.tracks else np.zeros(0),
                              dtype=wp.float64, device=device)
        table.value = wp.array(keys(lambda t: t.values), dtype=wp.vec3d, device=device)
        table.tangent = wp.array(keys(lambda t: t.tangents() if t.interpolation == "smooth" else np.zeros_like(t.values)),
                                 dtype=wp.vec3d, device=device)
        table.interpolation = wp.array([INTERPOLATIONS[t.interpolation] for t in self.tracks], dtype=wp.int32,
                                       device=device)
        table.extrapolation = wp.array([EXTRAPOLATIONS[t.extrapolation] for t in self.tracks], dtype=wp.int32,
                                       device=device)
        self.table = table

    def index(self, track: Track) -> int:
        """The table index of ``track`` (by identity)."""
        return next(k for k, t in enumerate(self.tracks) if t is track)


def evaluate_input_tracks(model, state, *, families=None) -> None:
    """Write the model's animated inputs at the time of ``state`` into its input table, each world's at that
    world's time, and bring ``families`` (default: every family beyond the springs) to that time (device work
    only; nothing is launched when no input is animated)."""
    for family in model.extra_families if families is None else families:
        family.at_time(model, state)
    animated = model.input_tracks
    if animated is None:
        return
    wp.launch(
        apply_input_tracks_kernel(model.scalar),
        dim=animated.count,
        inputs=[model.track_table.table, animated.track, animated.world, animated.slot, animated.width, state.time],
        outputs=[model.inputs],
        device=model.device,
    )
