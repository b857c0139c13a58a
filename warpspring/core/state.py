"""State: everything a step changes (positions, velocities, forces, each world's time)."""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from ..errors import ConfigError



@dataclass
class State:
    """Everything a step changes.

    Every array holds all worlds of the model, world-major: particle i of world w is entry
    w · particle_count + i (``state.particle_q.numpy().reshape(world_count, particle_count, 3)``).

    Attributes:
        particle_q: positions [m], shape [world_count · particle_count].
        particle_qd: velocities [m/s], shape [world_count · particle_count].
        particle_f: forces [N], shape [world_count · particle_count]; ``eval_forces`` writes it, and
            integrators write the forces at ``state_in`` into ``state_in.particle_f`` (fused gather kernels
            skip it).
        time: each world's time [s], float64, shape [world_count], on the device: every step advances it by
            its dt (a held world's stays), and keyframe tracks and driven pins are evaluated at it.
    """

    particle_q: wp.array
    particle_qd: wp.array
    particle_f: wp.array
    time: wp.array

    def assign(self, other: State) -> None:
        """Copy positions, velocities, forces and time from ``other`` (a state of the same model) into this one.

        Raises:
            ConfigError: ``other`` has another particle count, precision or device.
        """
        check_compatible(self, other)
        wp.copy(self.particle_q, other.particle_q)
        wp.copy(self.particle_qd, other.particle_qd)
        wp.copy(self.particle_f, other.particle_f)
        wp.copy(self.time, other.time)


def check_compatible(state: State, other: State) -> None:
    """Raise a ConfigError unless ``other`` could stand in for ``state`` (same particle count, precision and
    device): a state of another model would otherwise fail inside a kernel launch, or copy only a part."""
    mine, theirs = state.particle_q, other.particle_q
    if (mine.shape, mine.dtype, str(mine.device)) != (theirs.shape, theirs.dtype, str(theirs.device)):
        raise ConfigError(
            f"the state has {theirs.shape[0]} particles of {theirs.dtype.__name__} on {theirs.device}, but this model's "
            f"have {mine.shape[0]} of {mine.dtype.__name__} on {mine.device}: use a state made by this model's state()"
        )
