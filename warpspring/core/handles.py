"""PD-controlled handles on the host: the family of every handle of a model (``kernels/handles.py`` has the
control law and the hooks), built by :meth:`ModelBuilder.add_handle`, and the pass that writes each
handle's target frame at a state's time."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.handles import HandleSpec, handle_arrays_type, handle_frames_kernel
from .families import ElementFamily, build_incidence, incidence_bytes
from .tracks import Track, as_track


@dataclass(frozen=True)
class Handle:
    """One handle as built (per-world particle indices; see :meth:`ModelBuilder.add_handle`)."""

    name: str
    particles: np.ndarray  # int64, [k]
    rest: np.ndarray  # [m], [k, 3]: the grabbed particles' positions at t = 0
    pivot: np.ndarray  # [m], [3]
    kp: float  # [N/m]
    kd: float  # [N·s/m]
    max_force: float | None  # [N], or None (no cap)
    translation: Track | None
    rotation: Track | None


class HandleFamily(ElementFamily):
    """Every PD handle of a model: one element per grabbed particle of a handle."""

    name = "handle grabs"
    does_work = True

    def __init__(self):
        self.handles: list[Handle] = []

    @property
    def element_count(self) -> int:
        return sum(len(h.particles) for h in self.handles)

    def device_bytes(self, particle_count: int, scalar_bytes: int, worlds: int) -> int:
        """Per grab its handle and rest position; per handle the pivot, gains, cap, four frame vectors per
        world and two track indices; the incidence table."""
        grabs = np.concatenate([h.particles for h in self.handles])
        count = len(self.handles)
        return (28 * len(grabs) + count * (24 + 3 * scalar_bytes + 4 * 24 * worlds + 8)
                + incidence_bytes(grabs[:, None], particle_count))

    def tracks(self) -> tuple:
        return tuple(t for h in self.handles for t in (h.translation, h.rotation) if t is not None)

    def finalize(self, model) -> None:
        device, scalar = model.device, model.scalar
        grabs = np.concatenate([h.particles for h in self.handles])
        owner = np.concatenate([np.full(len(h.particles), k) for k, h in enumerate(self.handles)])
        self.incidence, self.shape = build_incidence(grabs[:, None], model.particle_count,
                                                     np.zeros((len(grabs), 1), np.int64), -1, device=device)
        count, worlds = len(self.handles), model.world_count

        def per_handle(values):
            return wp.array(np.asarray(values, dtype=np.float64)[None, :], dtype=scalar, device=device)

        self._handle = wp.array(owner.astype(np.int32), dtype=wp.int32, device=device)
        self._rest = wp.array(np.concatenate([h.rest for h in self.handles]), dtype=wp.vec3d, device=device)
        self._pivot = wp.array(np.array([h.pivot for h in self.handles]), dtype=wp.vec3d, device=device)
        self._kp = per_handle([h.kp for h in self.handles])
        self._kd = per_handle([h.kd for h in self.handles])
        self._max_force = per_handle([np.inf if h.max_force is None else h.max_force for h in self.handles])
        self._frames = [wp.zeros((worlds, count), dtype=wp.vec3d, device=device) for _ in range(4)]
        index = model.track_table.index

        def track_indices(attribute):
            return wp.array([-1 if getattr(h, attribute) is None else index(getattr(h, attribute))
                             for h in self.handles], dtype=wp.int32, device=device)

        self._translation_track = track_indices("translation")
        self._rotation_track = track_indices("rotation")
        self._animated = any(h.translation is not None or h.rotation is not None for h in self.handles)

    def set_target(self, handle: int, translation, *, velocity=(0.0, 0.0, 0.0), world: int | None = None) -> None:
        """Move a handle without a translation track from the host, between frames (a user dragging cloth):
        its targets become x₀ + ``translation`` [m] (about the pivot, rotated if it has a rotation track),
        moving at ``velocity`` [m/s] (the ė of the damping term), in every world or in one. A live value:
        nothing recompiles or re-captures.

        Raises:
            ConfigError: an unknown handle or world, a handle whose translation follows a track, or a
                non-finite value.
        """
        h = self._handle_index(handle)
        if self.handles[h].translation is not None:
            raise ConfigError(f"handle {self.handles[h].name!r} follows a translation track: remove the track to "
                              "move it from the host")
        rows = self._rows(world)
        for array, value, what in ((self._frames[0], translation, "translation"),
                                   (self._frames[1], velocity, "velocity")):
            values = array.numpy()
            values[rows, h] = checks.vector(f"handle {what}", value)
            array.assign(values)

    def set_gains(self, handle: int, *, kp: float | None = None, kd: float | None = None,
                  max_force: float | None = None) -> None:
        """Change a handle's gains between frames (kp = 0 lets go): live values, in every world. A cap can be
        changed only where one was compiled in (some handle was built with max_force)."""
        h = self._handle_index(handle)
        for array, value, name, check in ((self._kp, kp, "kp", checks.non_negative),
                                          (self._kd, kd, "kd", checks.non_negative),
                                          (self._max_force, max_force, "max_force", checks.positive)):
            if value is None:
                continue
            if name == "max_force" and not any(x.max_force is not None for x in self.handles):
                raise ConfigError("no handle was built with max_force, so no cap is compiled in: build one with it")
            values = array.numpy()
            values[:, h] = check(f"handle {name}", value)
            array.assign(values)

    def live_arrays(self) -> dict:
        """The gains (kp [N/m], kd [N·s/m], max_force [N]: [1, handle_count]) and the targets' frames (translation [m],
        velocity [m/s], rotation [rad], angular velocity [rad/s]: [world_count, handle_count] 3-vectors; set from
        the host by :meth:`set_target` or by the tracks at every force evaluation), for checkpoints."""
        return {"kp": self._kp, "kd": self._kd, "max_force": self._max_force,
                **dict(zip(("translation", "velocity", "rotation", "angular"), self._frames))}

    def _handle_index(self, handle) -> int:
        names = [h.name for h in self.handles]
        if isinstance(handle, str):
            if handle not in names:
                raise ConfigError(f"no handle named {handle!r}; handles: {', '.join(names)}")
            return names.index(handle)
        index = checks.count("handle", handle, minimum=0)
        if index >= len(self.handles):
            raise ConfigError(f"handle {index} does not exist: the model has handles 0..{len(self.handles) - 1}")
        return index

    def _rows(self, world: int | None) -> list:
        worlds = self._frames[0].shape[0]
        if world is None:
            return list(range(worlds))
        world = checks.count("world", world, minimum=0)
        if world >= worlds:
            raise ConfigError(f"world {world} does not exist: the model has worlds 0..{worlds - 1}")
        return [world]

    def time_dependent(self, model) -> bool:
        """Only where a handle is animated (still handles' target frames stay zero: their particles' starts)."""
        return bool(self._animated)

    def at_time(self, model, state) -> None:
        """Write every handle's target frame at the time of ``state`` (each world's at its own time)."""
        if not self.time_dependent(model):
            return  # the frames stay zero: every target is where its particle started
        wp.launch(handle_frames_kernel, dim=(model.world_count, len(self.handles)),
                  inputs=[self._translation_track, self._rotation_track, model.track_table.table, state.time],
                  outputs=self._frames, device=model.device)

    def damping_rates(self, model, positions: np.ndarray) -> np.ndarray:
        """Kd of every handle holding each particle (D = Kd I on a grabbed particle)."""
        rates = np.zeros(model.particle_count)
        for h in self.handles:
            np.add.at(rates, h.particles, h.kd)
        return np.broadcast_to(rates, (model.world_count, model.particle_count)).copy()

    def spec(self, model, *, linear: bool = False) -> HandleSpec:
        return HandleSpec(incidence=self.shape, rotation=any(h.rotation is not None for h in self.handles),
                          cap=any(h.max_force is not None for h in self.handles))

    def arrays(self, model, *, stiffness=None):
        arrays = handle_arrays_type(model.scalar)()
        arrays.handle, arrays.rest, arrays.pivot = self._handle, self._rest, self._pivot
        arrays.kp, arrays.kd, arrays.max_force = self._kp, self._kd, self._max_force
        arrays.translation, arrays.velocity, arrays.rotation, arrays.angular = self._frames
        arrays.incidence = self.incidence
        return arrays

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None) -> np.ndarray:
        """K = Kp I on each grabbed particle: its row gains Kp of every handle holding it."""
        rows = np.zeros(model.particle_count)
        for h in self.handles:
            np.add.at(rows, h.particles, h.kp)
        return np.broadcast_to(rows, (model.world_count, model.particle_count)).copy()

    def describe_element(self, model, element: int) -> str:
        for h in self.handles:
            if element < len(h.particles):
                return f"handle {h.name!r} on particle {int(h.particles[element])}"
            element -= len(h.particles)
        return f"handle grab {element}"


def make_handle(name: str, particles: np.ndarray, rest: np.ndarray, *, kp, kd, max_force, translation, rotation,
                pivot) -> Handle:
    """A checked :class:`Handle` (the builder resolves ``particles`` and ``rest``)."""
    if len(particles) == 0:
        raise ConfigError("a handle needs at least one particle")
    return Handle(
        name=name,
        particles=particles,
        rest=rest,
        pivot=rest.mean(axis=0) if pivot is None else checks.vector("handle pivot", pivot),
        kp=checks.positive("handle kp [N/m]", kp),
        kd=checks.non_negative("handle kd [N·s/m]", kd),
        max_force=None if max_force is None else checks.positive("handle max_force [N]", max_force),
        translation=None if translation is None else as_track("a handle's translation", translation, 3),
        rotation=None if rotation is None else as_track("a handle's rotation", rotation, 3),
    )
