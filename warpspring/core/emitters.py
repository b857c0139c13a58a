"""Particle emitters on the host: their pools, made by :meth:`ModelBuilder.add_emitter`, and the step hook
that runs their births and deaths on the device (``kernels/emitters.py`` describes the policy).

A :class:`~warpspring.Simulator` runs every emitter of its model after each step (before the guard); a
run's summary reports a pool too small for its emitter (the particles recycled before their life span
ended). ``Model.emitters`` lists them; :meth:`Emitter.alive` tells which pool particles live.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.emitters import DEAD, SHAPE_BOX, SHAPE_MESH, SHAPE_POINT, EmitterArrays, emit_counts_kernel, emit_kernel
from .stepper import StepHook

SHAPES = {"point": SHAPE_POINT, "box": SHAPE_BOX, "mesh": SHAPE_MESH}


class PoolTooSmallWarning(UserWarning):
    """An emitter's pool holds fewer particles than its rate and bursts keep alive at once: the oldest are
    recycled before their life span ends."""


@dataclass
class Emitter:
    """An emitter as built: its shape, rate, bursts, launch velocity, life span and pool (see
    :meth:`ModelBuilder.add_emitter`); after ``finalize`` its device arrays."""

    name: str
    shape: str
    first: int  # the pool's first particle (per-world index)
    capacity: int
    rate: float  # [1/s]
    life: float  # [s]
    velocity: np.ndarray  # [m/s], [3]
    spread: float  # [m/s]
    seed: int
    center: np.ndarray  # [m], [3]
    half_extents: np.ndarray  # [m], [3]
    mesh_points: np.ndarray  # [m], [v, 3]
    mesh_faces: np.ndarray  # [t, 3]
    bursts: np.ndarray  # [b, 2]: time [s], count

    def finalize(self, model) -> None:
        device, worlds = model.device, model.world_count
        arrays = EmitterArrays()
        arrays.first, arrays.capacity, arrays.seed = self.first, self.capacity, self.seed
        arrays.rate = wp.array([self.rate], dtype=wp.float64, device=device)
        arrays.life = wp.array([self.life], dtype=wp.float64, device=device)
        arrays.velocity = wp.array([self.velocity], dtype=wp.vec3d, device=device)
        arrays.spread = wp.array([self.spread], dtype=wp.float64, device=device)
        arrays.center = wp.array([self.center], dtype=wp.vec3d, device=device)
        arrays.half_extents = wp.array([self.half_extents], dtype=wp.vec3d, device=device)
        points, faces = self.mesh_points, self.mesh_faces
        if len(faces):
            area = 0.5 * np.linalg.norm(np.cross(points[faces[:, 1]] - points[faces[:, 0]],
                                                 points[faces[:, 2]] - points[faces[:, 0]]), axis=1)
            cdf = np.cumsum(area) / area.sum()
            cdf[-1] = 1.0
        else:
            points, faces, cdf = np.zeros((1, 3)), np.zeros((1, 3), np.int32), np.ones(1)
        arrays.mesh_points = wp.array(points, dtype=wp.vec3d, device=device)
        arrays.mesh_faces = wp.array(np.asarray(faces, dtype=np.int32), dtype=wp.vec3i, device=device)
        arrays.mesh_cdf = wp.array(cdf, dtype=wp.float64, device=device)
        arrays.burst_time = wp.array(self.bursts[:, 0].copy(), dtype=wp.float64, device=device)
        arrays.burst_count = wp.array(self.bursts[:, 1].astype(np.int32), dtype=wp.int32, device=device)
        arrays.births = wp.zeros(worlds, dtype=wp.int32, device=device)
        arrays.fraction = wp.zeros(worlds, dtype=wp.float64, device=device)
        arrays.recycled = wp.zeros(worlds, dtype=wp.int32, device=device)
        arrays.serial = wp.full(worlds * self.capacity, DEAD, dtype=wp.int32, device=device)
        arrays.birth_time = wp.zeros(worlds * self.capacity, dtype=wp.float64, device=device)
        self.arrays = arrays

    def set(self, *, rate: float | None = None, life: float | None = None, velocity=None, spread: float | None = None,
            center=None, half_extents=None) -> None:
        """Change the emitter between frames (live values: nothing recompiles or re-captures): its rate [1/s],
        life span [s] (for births from now on and the living alike), launch velocity [m/s] and spread [m/s],
        and where it emits (its point or box centre [m], the box's half sizes [m]). The pool stays as built:
        a higher rate or a longer life than it holds recycles the oldest (counted)."""
        a = self.arrays
        for value, array, check, name in ((rate, a.rate, checks.non_negative, "rate"),
                                          (life, a.life, checks.positive, "life"),
                                          (spread, a.spread, checks.non_negative, "spread")):
            if value is not None:
                value = check(f"emitter {name}", value)
                array.assign([value])
                setattr(self, name, value)
        for value, array, name in ((velocity, a.velocity, "velocity"), (center, a.center, "center"),
                                   (half_extents, a.half_extents, "half_extents")):
            if value is not None:
                value = checks.vector(f"emitter {name}", value)
                if name == "half_extents" and not (value > 0).all():
                    raise ConfigError(f"emitter half_extents must be > 0 [m], got {tuple(value)}")
                array.assign([value])
                setattr(self, name, value)

    def history(self) -> list:
        """The device arrays a run carries from step to step (restored after a capture's warm-up, saved in a
        checkpoint with the model's particle flags)."""
        a = self.arrays
        return [a.births, a.fraction, a.recycled, a.serial, a.birth_time]

    def alive(self, world: int = 0) -> np.ndarray:
        """Which pool particles of ``world`` live, bool, shape [capacity] (reads the device)."""
        serial = self.arrays.serial.numpy().reshape(-1, self.capacity)[world]
        return serial != DEAD

    def serials(self, world: int = 0) -> np.ndarray:
        """Each pool particle's birth serial in ``world`` (a stable id for DCC tools), int32, shape [capacity];
        -1 where none lives (reads the device)."""
        return self.arrays.serial.numpy().reshape(-1, self.capacity)[world].copy()

    def recycled(self) -> np.ndarray:
        """Particles recycled before their life span ended (the pool was full), per world, int (reads the
        device)."""
        return self.arrays.recycled.numpy().copy()

    def device_bytes(self, worlds: int) -> int:
        """Bytes of the device arrays :meth:`finalize` makes: per slot its serial and birth time, per world the
        counters, the parameters, the mesh (vertices, faces, cumulative areas) and the bursts."""
        faces = max(len(self.mesh_faces), 1)
        points = len(self.mesh_points) if len(self.mesh_faces) else 1
        return (12 * self.capacity * worlds + 16 * worlds + 8 + 8 + 24 + 8 + 48 + 24 * points + 20 * faces
                + 12 * len(self.bursts))

    @property
    def expected_live(self) -> int:
        """The most particles the rate and bursts keep alive at once (rate × life plus the bursts)."""
        return math.ceil(self.rate * self.life) + int(self.bursts[:, 1].sum())


class EmitterHook(StepHook):
    """Runs the births and deaths of every emitter of a model after each step (a :class:`StepHook`)."""

    def __init__(self, model, dt: float):
        self.model = model
        self.dt = float(dt)

    def after_step(self, state, step: int, steps: int) -> None:
        model = self.model
        for emitter in model.emitters:
            kind = SHAPES[emitter.shape]
            wp.launch(emit_kernel(model.scalar, kind), dim=(model.world_count, emitter.capacity),
                      inputs=[model.particle_count, model.world_enabled, state.time, wp.float64(self.dt)],
                      outputs=[emitter.arrays, model.particle_flags, state.particle_q, state.particle_qd],
                      device=model.device)
            wp.launch(emit_counts_kernel, dim=model.world_count,
                      inputs=[model.world_enabled, state.time, wp.float64(self.dt), emitter.arrays],
                      device=model.device)

    def history(self) -> list:
        return [self.model.particle_flags] + [a for e in self.model.emitters for a in e.history()]


def make_emitter(name: str, first: int, *, shape: str, center, half_extents, mesh, rate: float, bursts, life: float,
                 velocity, spread: float, seed: int, capacity: int | None) -> Emitter:
    """A checked :class:`Emitter` whose pool starts at particle ``first`` (the builder adds the pool)."""
    if shape not in SHAPES:
        raise ConfigError(f"emitter shape must be one of {', '.join(SHAPES)}, got {shape!r}")
    rate = checks.non_negative("emitter rate [1/s]", rate)
    life = checks.positive("emitter life [s]", life)
    pairs = np.zeros((0, 2))
    if bursts:
        try:
            pairs = np.array([[float(t), int(n)] for t, n in bursts], dtype=np.float64).reshape(-1, 2)
        except (TypeError, ValueError):
            raise ConfigError(f"emitter bursts must be (time [s], count) pairs, got {bursts!r}") from None
        if not np.isfinite(pairs).all() or (pairs[:, 0] < 0).any() or (pairs[:, 1] < 1).any():
            raise ConfigError("emitter bursts need times >= 0 [s] and counts >= 1")
    if rate == 0.0 and not len(pairs):
        raise ConfigError("an emitter needs a rate > 0 [1/s] or bursts = [(time, count), ...]")
    points = faces = np.zeros((0, 3))
    if shape == "mesh":
        if mesh is None:
            raise ConfigError("a mesh emitter needs mesh= (vertices [m], faces) or a trimesh.Trimesh")
        points, faces = mesh
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        if not len(faces) or faces.min() < 0 or faces.max() >= len(points) or not np.isfinite(points).all():
            raise ConfigError("the emitter mesh needs finite vertices and at least one triangle indexing them")
    emitter = Emitter(
        name=name, shape=shape, first=first, capacity=0, rate=rate, life=life,
        velocity=checks.vector("emitter velocity", velocity), spread=checks.non_negative("emitter spread", spread),
        seed=checks.count("emitter seed", seed, minimum=0),
        center=checks.vector("emitter center", center), half_extents=checks.vector("emitter half_extents", half_extents),
        mesh_points=points, mesh_faces=faces, bursts=pairs,
    )
    if shape == "box" and not (emitter.half_extents > 0).all():
        raise ConfigError(f"a box emitter needs half_extents > 0 [m], got {tuple(emitter.half_extents)}")
    expected = emitter.expected_live
    emitter.capacity = (max(1, math.ceil(1.05 * expected)) if capacity is None
                        else checks.count("emitter capacity", capacity, minimum=1))
    if emitter.capacity < expected:
        warnings.warn(PoolTooSmallWarning(
            f"emitter {name!r}: a pool of {emitter.capacity} particles is smaller than the {expected} its rate × life "
            f"and bursts keep alive: the oldest are recycled early (counted in the run's summary); give "
            f"capacity >= {expected}"), stacklevel=3)
    return emitter
