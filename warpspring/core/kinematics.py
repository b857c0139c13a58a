"""Kinematic particles on the host: pin groups, and the launch of the kinematics pass.

A pinned particle is kinematic (``particle_flags``): no force moves it, its mass stays known. Pins of
a :class:`PinGroup` follow a prescribed motion, from keyframe tracks (a translation and a rotation about
the group's pivot) or from targets set through ``Control.set_pin_targets`` each frame; other pins move
on with their velocity. :func:`apply_kinematics` puts every kinematic particle where its motion says at
a given time; the integrators call it for each step and each stage (``kernels/kinematics.py``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..errors import ConfigError
from ..kernels.kinematics import NO_GROUP, NO_TARGET_TIME, PinGroups, PinTargets, kinematics_kernel
from .tracks import Track


@dataclass(frozen=True, eq=False)
class PinGroup:
    """A group of kinematic particles that move together.

    Attributes:
        name: the group's name (unique in its model).
        particles: global particle indices, shape [n], ascending.
        translation: track of the translation T(t) [m] added to the group's rest positions, or ``None``.
        rotation: track of the rotation vector φ(t) [rad] (axis × angle) about ``pivot``, or ``None``.
        pivot: the centre of the rotation [m], shape [3] (default: the group's centroid at t = 0).
        driver: "tracks" (moved by the tracks) or "control" (no track: moved by ``Control.set_pin_targets``).
    """

    name: str
    particles: np.ndarray
    translation: Track | None
    rotation: Track | None
    pivot: np.ndarray

    @property
    def driver(self) -> str:
        return "control" if self.translation is None and self.rotation is None else "tracks"

    def position(self, rest: np.ndarray, t) -> tuple[np.ndarray, np.ndarray]:
        """Positions [m] and velocities [m/s] at times ``t`` [s] of particles that rest at ``rest`` [m]
        (shape [n, 3]), float64 on the host: shapes [len(t), n, 3]. The reference the device is tested
        against (tracks-driven groups only)."""
        from scipy.spatial.transform import Rotation

        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        r = np.asarray(rest, dtype=np.float64) - self.pivot
        x = np.repeat((self.pivot + r)[None], len(t), axis=0)
        v = np.zeros_like(x)
        if self.rotation is not None:
            phi, phi_rate = self.rotation.sample(t)
            rotated = np.stack([Rotation.from_rotvec(p).apply(r) for p in phi]).reshape(len(t), -1, 3)
            omega = np.stack([_left_jacobian(p) @ d for p, d in zip(phi, phi_rate)])
            x = self.pivot + rotated
            v = np.cross(omega[:, None, :], rotated)
        if self.translation is not None:
            offset, rate = self.translation.sample(t)
            x = x + offset[:, None, :]
            v = v + rate[:, None, :]
        return x, v


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """J(φ) with ω = J(φ) φ̇ for R(t) = exp([φ(t)]×), in float64 (closed form)."""
    theta = np.linalg.norm(phi)
    k = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if theta < 1e-8:
        return np.eye(3) + 0.5 * k
    return np.eye(3) + (1 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * (k @ k)


class PinGroupTable:
    """The kinematic particles of a model on its device, ordered ungrouped first, then group by group
    (each group's entries are contiguous: ``slices[g]``).

    Attributes:
        groups: the host groups, in index order.
        kinematic: indices of every kinematic particle, shape [kinematic_count], in table order.
        slices: per group, its ``slice`` of the table.
        table: the device struct (:class:`~warpspring.kernels.kinematics.PinGroups`).
        driven: whether any group is driven (tracks or Control): only then do integrators run the pass.
    """

    def __init__(self, kinematic: np.ndarray, groups: list[PinGroup], rest: np.ndarray, track_index, device,
                 world_tracks: list | None = None):
        """``world_tracks``: ``None`` (every world moves each group by the group's own tracks), or one list
        per world of (translation, rotation) per group (the rows of a model whose worlds differ)."""
        self.groups = list(groups)
        self.world_tracks = world_tracks
        member = np.full(len(rest), NO_GROUP, dtype=np.int64)
        for g, group in enumerate(self.groups):
            member[group.particles] = g
        order = np.lexsort((kinematic, member[kinematic]))  # by group (ungrouped first), then by index
        self.kinematic = kinematic[order]
        group_of = member[self.kinematic]
        first = np.searchsorted(group_of, np.arange(len(self.groups)))
        self.slices = [slice(int(a), int(a + len(g.particles))) for a, g in zip(first, self.groups)]
        self.driven = bool(self.groups)

        table = PinGroups()
        table.particle = wp.array(self.kinematic.astype(np.int32), dtype=wp.int32, device=device)
        table.group = wp.array(group_of.astype(np.int32), dtype=wp.int32, device=device)
        table.rest = wp.array(rest[self.kinematic], dtype=wp.vec3d, device=device)
        rows = world_tracks if world_tracks is not None else [[(g.translation, g.rotation) for g in self.groups]]
        _set_track_rows(table, rows, track_index, device)
        table.pivot = wp.array(np.array([g.pivot for g in self.groups]).reshape(-1, 3), dtype=wp.vec3d, device=device)
        entry = np.full(len(rest), -1, dtype=np.int32)
        entry[self.kinematic] = np.arange(len(self.kinematic), dtype=np.int32)
        table.entry = wp.array(entry, dtype=wp.int32, device=device)
        self.table = table
        self.rest = rest[self.kinematic]

    def retrack(self, world_tracks: list, track_index, device) -> PinGroupTable:
        """A copy whose groups move by ``world_tracks`` (one list per world of (translation, rotation) per
        group), indexed by ``track_index`` in a new track table."""
        table = copy.copy(self)
        table.world_tracks = world_tracks
        struct = PinGroups()
        for name in ("particle", "group", "rest", "pivot", "entry"):
            setattr(struct, name, getattr(self.table, name))
        _set_track_rows(struct, world_tracks, track_index, device)
        table.table = struct
        return table

    @property
    def count(self) -> int:
        """Number of kinematic particles."""
        return len(self.kinematic)

    @property
    def control_driven(self) -> bool:
        """Whether some group is driven through Control (then a Control carries pin targets)."""
        return any(g.driver == "control" for g in self.groups)

    def group_index(self, group) -> int:
        """The index of a group given by index or name."""
        if isinstance(group, str):
            for g, candidate in enumerate(self.groups):
                if candidate.name == group:
                    return g
            names = ", ".join(g.name for g in self.groups) or "none"
            raise KeyError(f"no pin group named {group!r}; the model has: {names}")
        if not 0 <= int(group) < len(self.groups):
            raise KeyError(f"pin group {group} does not exist; the model has {len(self.groups)}")
        return int(group)

    def new_targets(self, device, world_count: int = 1) -> PinTargets:
        """Pin targets that ask nothing yet, in every world: every control-driven group rests where it is."""
        targets = PinTargets()
        targets.position = wp.array(np.broadcast_to(self.rest, (world_count, *self.rest.shape)).copy(),
                                    dtype=wp.vec3d, device=device)
        targets.time = wp.full((world_count, len(self.groups)), NO_TARGET_TIME, dtype=wp.float64, device=device)
        return targets


def _set_track_rows(table: PinGroups, rows: list, track_index, device) -> None:
    """Fill a pin-group struct's [rows, group_count] track tables from (translation, rotation) per group and
    row (-1 where a track is absent)."""
    shape = (len(rows), len(rows[0]) if rows else 0)
    for field, part in (("translation_track", 0), ("rotation_track", 1)):
        index = [[-1 if pair[part] is None else track_index(pair[part]) for pair in row] for row in rows]
        setattr(table, field, wp.array(np.array(index, dtype=np.int32).reshape(shape), dtype=wp.int32, device=device))


#: Pin targets of no Control (an empty struct: kernels compiled without targets never read it).
NO_PIN_TARGETS = PinTargets()


def apply_kinematics(model, control, state_in, q_out: wp.array, qd_out: wp.array, fraction: float, step=None):
    """Write every kinematic particle's position [m] and velocity [m/s] at t + s into ``q_out``/``qd_out``, in
    every world, where t is ``state_in``'s time and s = ``fraction`` · the world's step (``step``: a device
    array of each world's step [s], for adaptive integrators; default: s = ``fraction`` seconds). Launches
    nothing unless the model has driven pin groups; other kinematic particles are moved by the integrators
    themselves."""
    pins = model.pin_groups
    if pins is None or not pins.driven:
        return
    targets = control is not None and control.pin_targets is not None
    wp.launch(
        kinematics_kernel(model.scalar, targets),
        dim=(model.world_count, pins.count),
        inputs=[
            model.particle_count,
            model.particle_flags,
            pins.table,
            model.track_table.table,
            control.pin_targets if targets else NO_PIN_TARGETS,
            state_in.particle_q,
            state_in.particle_qd,
            state_in.time,
            model.unit_step if step is None else step,
            wp.float64(fraction),
        ],
        outputs=[q_out, qd_out],
        device=model.device,
    )


def pin_group_index(pins: PinGroupTable | None, group) -> int:
    """The index of pin ``group`` (an index or a name) in ``pins``, or a ConfigError saying what exists."""
    if pins is None:
        raise ConfigError("the model has no pin groups: add one with ModelBuilder.add_pin_group(particles)")
    try:
        return pins.group_index(group)
    except KeyError as exc:
        raise ConfigError(str(exc.args[0])) from None
