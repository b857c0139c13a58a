"""Control: the time-varying inputs of a step (external forces, pin targets)."""

from __future__ import annotations


import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError

from ..kernels.kinematics import NO_TARGET_TIME
from .kinematics import pin_group_index


class Control:
    """Time-varying inputs of a step, made by :meth:`Model.control`.

    Attributes:
        model: the model it belongs to.
        particle_force: external force per particle [N], shape [world_count · particle_count], or ``None``
            when the scene applies none (then no kernel reads it).
        pin_targets: targets of the pin groups driven through Control (a device struct; see
            :meth:`set_pin_targets`), or ``None`` when the model has no such group.
        revision: counts structural changes (an input allocated or replaced): a Stepper re-captures.
    """

    def __init__(self, model):  # a Model (not imported here: model.py imports this module)
        object.__setattr__(self, "revision", 0)
        self.model = model
        self.particle_force = None
        pins = model.pin_groups
        self.pin_targets = (pins.new_targets(model.device, model.world_count) if pins is not None and pins.control_driven
                            else None)

    def __setattr__(self, name: str, value) -> None:
        # Replacing an input (an array a captured graph points to) is a structural change.
        if name != "revision":
            object.__setattr__(self, "revision", self.revision + 1)
        object.__setattr__(self, name, value)

    def clear_pin_targets(self) -> None:
        """Forget every pin target: control-driven groups rest where they are until new targets come."""
        if self.pin_targets is not None:
            self.pin_targets.time.fill_(NO_TARGET_TIME)

    def set_particle_force(self, force) -> None:
        """Set the external force [N]: one 3-vector for every particle, an array of shape
        [particle_count, 3] (the same in every world), or [world_count, particle_count, 3].

        The array is allocated on first use (a structural change); later calls overwrite it in place, so
        captured graphs see the new values.
        """
        model = self.model
        n, worlds = model.particle_count, model.world_count
        values = np.asarray(force, dtype=np.float64)
        try:
            values = np.broadcast_to(values, (worlds, n, 3)).reshape(worlds * n, 3)
        except ValueError:
            raise ConfigError(
                f"particle force must have shape (3,), ({n}, 3) or ({worlds}, {n}, 3), got {values.shape}"
            ) from None
        if not np.isfinite(values).all():
            raise ConfigError("particle force contains NaN or infinite values")
        host = wp.array(values, dtype=model.vec3, device="cpu")
        if self.particle_force is None:
            self.particle_force = wp.empty(worlds * n, dtype=model.vec3, device=model.device)
        wp.copy(self.particle_force, host)

    def set_pin_targets(self, group, positions, *, time: float, world: int | None = None) -> None:
        """Send the particles of a control-driven pin group to ``positions`` [m], reached at ``time`` [s].

        From the state the next step starts at, each particle moves in a straight line at the constant
        velocity that reaches its target at ``time``, exactly on the line at every substep and stage, and
        rests there until new targets come. A ``time`` at or before the state's time leaves the group where
        it is. (``Simulator.set_pin_targets`` picks the end of the next frame.)

        Args:
            group: the group's index or name (a group added with ``add_pin_group`` without tracks).
            positions: shape [n, 3] for the group's n particles in ascending index order (or [3] when n = 1);
                with ``world=None``, also [world_count, n, 3] (each world its own targets).
            time: when the targets are reached [s].
            world: the world whose group is sent, or ``None``: every world.
        """
        pins = self.model.pin_groups
        g = pin_group_index(pins, group)
        pin_group = pins.groups[g]
        if pin_group.driver != "control":
            raise ConfigError(f"pin group {pin_group.name!r} is driven by its tracks, not by Control")
        n = len(pin_group.particles)
        worlds = self.model._world_rows(world)
        values = np.asarray(positions, dtype=np.float64)
        if values.shape == (3,) and n == 1:
            values = values[None]
        if values.ndim == 2:
            values = np.broadcast_to(values, (len(worlds), *values.shape))
        if values.shape != (len(worlds), n, 3) or not np.isfinite(values).all():
            raise ConfigError(f"pin group {pin_group.name!r} needs {n} finite target positions, shape ({n}, 3) (or "
                              f"({len(worlds)}, {n}, 3): one set per world); got shape {np.shape(positions)}")
        when = checks.number("pin target time", time)
        part = pins.slices[g]
        kinematic = pins.count
        for k, w in enumerate(worlds):
            wp.copy(self.pin_targets.position, wp.array(values[k], dtype=wp.vec3d, device="cpu"),
                    dest_offset=w * kinematic + part.start, count=n)
        time_row = self.pin_targets.time.numpy()
        time_row[worlds, g] = when
        self.pin_targets.time.assign(time_row)
