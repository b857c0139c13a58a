"""A sweep's jobs: variants of one topology batched as the worlds of one model, run and measured.

**Batching.** Variants whose scenes differ only in values a model holds per world (see "Worlds" in
docs/architecture.md: gravity, drag, the stabiliser thresholds, the wind's inputs, and each spring
family's ``ke``/``kd`` and the particle masses of a cloth) run as the worlds of one model, ``batch`` at most
per task; whether a value is zero is part of the topology (a zero switches a term off, which specialises
kernels). Worlds never couple, so a variant's metrics are the same alone or batched, bit for bit.

**Metrics** (:class:`VariantResult`), per variant, in float64 on the host from each frame's state: the
largest spring strain over the run, the mechanical energy at the start and the end (kinetic +
gravitational + spring elastic), the smallest signed distance from a particle's surface to a collider over
the run (where colliders exist), whether the run-time guard stopped it and its message, the error of the
final positions against the reference run's, and the wall time of its model's run (shared by the variants
batched together: ``worlds`` says how many).
"""

from __future__ import annotations

import copy
import dataclasses
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .. import checks
from ..core.integrators import make_integrator
from ..core.simulator import Simulator
from ..errors import ConfigError, SimulationError
from ..io.usd import UsdWriter
from .sweep_plan import check_scene, digest, one_line

#: Statuses of a variant: ran to the end; stopped by the run-time guard (or an adaptive integrator gave
#: up); raised an error (its message says what).
STATUSES = ("ok", "stopped", "error")


# -- batches: variants that share a topology ------------------------------------------------------------------

#: Live inputs a batch sets per world: the scene table and key -> the model's input name (constants only:
#: a track is part of the topology).
_WORLD_INPUTS = {
    ("world", "gravity"): "gravity",
    ("world", "drag"): "drag",
    **{("stabilizers", k): k for k in ("max_spring_force", "max_particle_force", "max_speed", "max_strain",
                                       "biphasic_strain", "biphasic_ratio")},
    ("wind", "velocity"): "wind",
    ("wind", "air_density"): "air_density",
    ("wind", "noise"): "wind_noise",
}
#: Cloth keys whose values a batch gives per world through the model's spring and mass rows.
_FAMILIES = ("structural", "shear", "bend")
_MASS_KEYS = ("mass", "particle_mass")


def _live(value) -> dict:
    """What of a live value is topology: whether it is zero (a zero switches a term off)."""
    zero = not any(value) if isinstance(value, list) else value == 0
    return {"live": "zero" if zero else "nonzero"}


def topology(scene: dict) -> str:
    """A digest of what a variant's model compiles and allocates: its scene with the per-world values
    (constants of the live inputs, spring ke/kd, cloth masses) replaced by whether they are zero. Variants
    of one topology can run as worlds of one model."""
    skeleton = copy.deepcopy(scene)
    if "worlds" in skeleton:  # a scene of several worlds runs alone
        return digest(scene)
    for (table, key) in _WORLD_INPUTS:
        values = skeleton.get(table)
        if isinstance(values, dict) and key in values and not isinstance(values[key], dict):
            values[key] = _live(values[key])
    cloths = skeleton.get("cloth")
    for cloth in [cloths] if isinstance(cloths, dict) else (cloths or []):
        for family in _FAMILIES:
            if isinstance(cloth.get(family), dict):
                cloth[family] = {k: _live(v) for k, v in cloth[family].items()}
        for key in _MASS_KEYS:
            if key in cloth:
                cloth[key] = "live"
    return digest(skeleton)


@dataclass(frozen=True)
class Batch:
    """Variants of one topology, run as the worlds of one model in one task.

    Attributes:
        variants: the variants (world k runs ``variants[k]``).
        scene_path: the base scene's path (relative file names in the scenes resolve against its folder).
    """

    variants: tuple
    scene_path: str


def make_batches(variants: list, scene_path: str, batch: int) -> list[Batch]:
    """Group ``variants`` by :func:`topology`, ``batch`` at most per group, in plan order."""
    groups: dict[str, list] = {}
    for v in variants:
        groups.setdefault(topology(v.scene), []).append(v)
    batches = []
    for members in groups.values():
        for start in range(0, len(members), batch):
            batches.append(Batch(tuple(members[start : start + batch]), scene_path))
    return sorted(batches, key=lambda b: b.variants[0].index)


# -- running one batch ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunSettings:
    """How a task runs its batch.

    Attributes:
        device: Warp device name; ``None``: Warp's default in the process that runs it (a Ray task without
            a GPU sees none, so its default is the CPU).
        usd_dir: folder of the variants' USD files, or ``None`` (none written).
        reference_q: the reference run's final positions [m], float64, shape [particles, 3], or ``None``.
        task_hook: called with the batch at the start of every task, in the process that runs it (logging,
            or a test's fault injection), or ``None``.
        metrics_every: frames between the metrics' samples (the first and the last frame always).
    """

    device: str | None = None
    usd_dir: str | None = None
    reference_q: np.ndarray | None = None
    task_hook: Callable | None = None
    metrics_every: int = 1


@dataclass
class VariantResult:
    """What one variant's run gave: a row of the sweep's table (with its parameters).

    Attributes:
        index: the variant's place in the plan.
        key: its hash.
        status: "ok", "stopped" (the guard stopped it, or an adaptive integrator gave up) or "error".
        message: the guard's or the error's message ("" when ok).
        frames: frames completed (the frame it stopped in excluded).
        wall_time: wall time [s] of the frames of the model it ran in (after the first frame, which compiles
            and captures); shared by the ``worlds`` variants batched in it.
        setup_time: wall time [s] to build the model and run its first frame.
        frames_per_second: frames advanced per wall second by that model (all its worlds at once).
        worlds: variants run as worlds of the same model (1: alone).
        particles: particles of the variant.
        max_strain: largest spring strain (|d| − L) / L over the run's frames [-] (NaN without springs).
        energy_start, energy_end: kinetic + gravitational (zero at the start) + spring elastic energy at the
            first and the last completed frame [J].
        min_contact_distance: smallest distance from a particle's surface (its radius) to a collider over
            the run's frames [m], negative when inside; ``None`` without colliders.
        error_max, error_rms: max and RMS over the particles of |x − x_ref| at the end [m], against the
            reference run; ``None`` without one (or when it stopped, or has another particle count).
        device: the Warp device that ran it.
        usd: its USD file, or "".
    """

    index: int
    key: str
    status: str
    message: str = ""
    frames: int = 0
    wall_time: float | None = None
    setup_time: float | None = None
    frames_per_second: float | None = None
    worlds: int = 1
    particles: int = 0
    max_strain: float | None = None
    energy_start: float | None = None
    energy_end: float | None = None
    min_contact_distance: float | None = None
    error_max: float | None = None
    error_rms: float | None = None
    device: str = ""
    usd: str = ""


@dataclass
class BatchOutput:
    """A task's result: its variants' rows, and their final positions [m] (float64, [particles, 3]; ``None``
    for a variant that did not finish) by key."""

    results: list
    final_q: dict = field(default_factory=dict)


def run_batch(batch: Batch, settings: RunSettings) -> BatchOutput:
    """Run a batch's variants as the worlds of one model and measure each (:class:`VariantResult`). When the
    shared model cannot be built (a value one variant's builder refuses), each variant runs alone, so only
    that variant's row holds the error."""
    if settings.task_hook is not None:
        settings.task_hook(batch)
    if len(batch.variants) > 1:
        try:
            return _run_worlds(batch.variants, batch.scene_path, settings)
        except Exception:  # noqa: BLE001  (which variant is at fault is found by running each alone)
            pass
    output = BatchOutput(results=[])
    for v in batch.variants:
        try:
            one = _run_worlds((v,), batch.scene_path, settings)
        except Exception as exc:  # noqa: BLE001  (a variant that raises is a row with its error)
            one = BatchOutput([VariantResult(index=v.index, key=v.key, status="error", message=one_line(exc))])
        output.results += one.results
        output.final_q.update(one.final_q)
    return output


def _batched_model(variants, scene_path: str, device):
    """The model holding ``variants`` as its worlds, their scenes, and the first one's scene."""
    scenes = [check_scene(v.scene, scene_path) for v in variants]
    first = scenes[0]
    n = len(variants)
    if n == 1:
        return first.finalize(device), scenes
    shared = dataclasses.replace(first, world_count=n, world_inputs={}, world_scales={})
    for (table, key), name in _WORLD_INPUTS.items():
        values = [v.scene.get(table, {}).get(key) for v in variants]
        if values[0] is not None and not isinstance(values[0], dict) and any(x != values[0] for x in values):
            shared.world_inputs[name] = [[float(x) for x in val] if isinstance(val, list) else float(val)
                                         for val in values]
    model = shared.finalize(device)
    rows = [s.builder().world_rows() for s in scenes] if _cloth_values_differ(variants) else []
    for name in ("spring_stiffness", "spring_damping", "particle_mass"):
        if rows and any(not np.array_equal(r[name], rows[0][name]) for r in rows):
            model.set_world_values(name, np.stack([r[name] for r in rows]))
    return model, scenes


def _cloth_values_differ(variants) -> bool:
    def values(scene):
        cloths = scene.get("cloth")
        cloths = [cloths] if isinstance(cloths, dict) else (cloths or [])
        return [{k: c.get(k) for k in _FAMILIES + _MASS_KEYS} for c in cloths]

    first = values(variants[0].scene)
    return any(values(v.scene) != first for v in variants[1:])


def _run_worlds(variants, scene_path: str, settings: RunSettings) -> BatchOutput:
    """Run ``variants`` as the worlds of one model (the guard holds a failed world, the others go on)."""
    t0 = time.perf_counter()
    device = checks.device(settings.device)
    model, scenes = _batched_model(variants, scene_path, device)
    scene = scenes[0]
    n, worlds = model.particle_count, len(variants)
    try:
        integrator = make_integrator(scene.integrator, model, **scene.integrator_options)
    except ConfigError as exc:
        raise ConfigError(f"[simulation] {exc}") from None
    guard = scene.guard
    limits = type(guard)(every=guard.every, tear_strain=guard.tear_strain, max_kinetic_energy=guard.max_kinetic_energy,
                         energy_balance=guard.energy_balance, stop="world")
    sim = Simulator(model, integrator=integrator, fps=scene.fps, substeps=scene.substeps, guard=limits)
    writers = _writers(model, scene, variants, settings)
    metrics = _Metrics(model)
    done = np.zeros(worlds, dtype=np.int64)  # frames each world completed
    stopped: dict[int, str] = {}
    t1, completed = None, 0
    try:
        for frame in range(scene.frames + 1):
            if frame > 0:
                try:
                    sim.step_frame()
                    sim.settle()  # this frame's verdict (on CUDA read a frame later): its failures are its own
                except SimulationError as exc:  # every world failed, or an adaptive integrator gave up
                    for w in range(worlds):
                        if w not in stopped:
                            stopped[w] = (_failure(sim, w, scene.substeps) if w in sim.world_failures
                                          else one_line(exc))
                    break
                for w in sorted(set(sim.world_failures) - set(stopped)):
                    stopped[w] = _failure(sim, w, scene.substeps)
            running = np.array([w not in stopped for w in range(worlds)])
            if frame % settings.metrics_every == 0 or frame == scene.frames:
                wp.synchronize_device(device)
                q = sim.state.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
                qd = sim.state.particle_qd.numpy().astype(np.float64).reshape(worlds, n, 3)
                metrics.record(running, q, qd, frame / scene.fps)
            done[running] = frame
            for w in np.flatnonzero(running) if writers else ():
                writers[w][1].write_frame(sim.state)
            completed = frame
            if frame == 1:
                wp.synchronize_device(device)
                t1 = time.perf_counter()
    finally:
        for path, writer in writers:
            writer.close()
    end = time.perf_counter()
    wall = end - t1 if t1 is not None and completed > 1 else None
    reference = settings.reference_q
    output = BatchOutput(results=[])
    for w, v in enumerate(variants):
        row = VariantResult(
            index=v.index, key=v.key, status="stopped" if w in stopped else "ok", message=stopped.get(w, ""),
            frames=int(done[w]), wall_time=wall, setup_time=(t1 or end) - t0,
            frames_per_second=(completed - 1) / wall if wall else None, worlds=worlds,
            particles=n, device=str(device), **metrics.row(w),
        )
        if w not in stopped:
            output.final_q[v.key] = metrics.last_q[w]
            if reference is not None and reference.shape == metrics.last_q[w].shape:
                diff = np.linalg.norm(metrics.last_q[w] - reference, axis=1)
                row.error_max, row.error_rms = float(diff.max()), float(np.sqrt(np.mean(diff**2)))
        if writers:
            row.usd = _publish(writers[w][0])
        output.results.append(row)
    return output


def _failure(sim, world: int, substeps: int) -> str:
    """The guard's message for a stopped world, without its index (the same words alone or batched)."""
    frame, report = sim.world_failures[world]
    return f"frame {frame}, substep {report.substep + 1} of {substeps}: {report.describe(sim.model, name_world=False)}"


class _Metrics:
    """Every world's running extremes over the frames it passes, in float64 on the host, one vectorised pass
    per frame over all worlds: the largest spring strain (|d| − L) / L, the energy (kinetic + gravitational
    from the start + spring elastic ½ k (|d| − L)²) at the first and the last frame, and the smallest signed
    distance from a particle's surface to a collider."""

    def __init__(self, model):
        worlds, n = model.world_count, model.particle_count
        self.springs = model.spring_indices.numpy().reshape(-1, 2).astype(np.int64)
        self.rest = model.spring_rest_length.numpy().astype(np.float64)
        self.stiffness = model.world_values("spring_stiffness")  # [worlds, springs]
        self.mass = model.world_values("particle_mass")  # [worlds, particles]
        self.gravity = model.world_values("gravity")  # [worlds, 3]
        self.initial_q = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
        self.distance = _ContactDistance(model)
        self.strain = np.full(worlds, -np.inf)
        self.nearest = np.full(worlds, np.inf)
        self.energy_start = np.full(worlds, np.nan)
        self.energy_end = np.full(worlds, np.nan)
        self.last_q: dict[int, np.ndarray] = {}

    def record(self, running: np.ndarray, q: np.ndarray, qd: np.ndarray, t: float) -> None:
        """Take the frame at time ``t`` [s] of the worlds ``running`` (bool, [worlds]); ``q`` [m], ``qd``
        [m/s]: every world's positions and velocities, [worlds, particles, 3]."""
        w = np.flatnonzero(running)
        q, qd = q[w], qd[w]
        energy = 0.5 * np.sum(self.mass[w] * np.sum(qd * qd, axis=2), axis=1)
        energy -= np.sum(self.mass[w] * np.einsum("wpk,wk->wp", q - self.initial_q[w], self.gravity[w]), axis=1)
        if len(self.springs):
            length = np.linalg.norm(q[:, self.springs[:, 1]] - q[:, self.springs[:, 0]], axis=2)
            self.strain[w] = np.maximum(self.strain[w], np.max(length / self.rest - 1.0, axis=1))
            stretch = length - self.rest
            energy += 0.5 * np.sum(self.stiffness[w] * stretch * stretch, axis=1)
        first = np.isnan(self.energy_start[w])
        self.energy_start[w[first]] = energy[first]
        self.energy_end[w] = energy
        nearest = self.distance(q, t)
        if nearest is not None:
            self.nearest[w] = np.minimum(self.nearest[w], nearest)
        for k, world in enumerate(w):
            self.last_q[world] = q[k]

    def row(self, w: int) -> dict:
        def value(x):
            return float(x) if np.isfinite(x) else None

        return dict(max_strain=value(self.strain[w]), energy_start=value(self.energy_start[w]),
                    energy_end=value(self.energy_end[w]),
                    min_contact_distance=value(self.nearest[w]) if self.distance.shapes else None)


class _ContactDistance:
    """Signed distance [m] from the particles' surfaces (their radii) to the nearest collider, the least over
    each world's particles (float64, host); the colliders at time t through ``ShapeInfo.frame`` (their
    tracks)."""

    def __init__(self, model):
        self.shapes = list(model.shapes)
        self.radius = model.particle_radius.numpy().astype(np.float64)[: model.particle_count]

    def __call__(self, q: np.ndarray, t: float) -> np.ndarray | None:
        """The least distance of each world's particles ``q`` [m], [worlds, particles, 3]: [worlds]."""
        if not self.shapes:
            return None
        from scipy.spatial.transform import Rotation

        best = np.full(q.shape[0], np.inf)
        for shape in self.shapes:
            position, orientation = shape.frame(t)
            p = Rotation.from_quat(orientation).inv().apply((q - position).reshape(-1, 3)).reshape(q.shape)
            size = np.asarray(shape.size, dtype=np.float64)
            if shape.kind == "plane":
                d = p[..., 2]
            elif shape.kind == "sphere":
                d = np.linalg.norm(p, axis=-1) - size[0]
            elif shape.kind == "box":
                e = np.abs(p) - size
                d = np.linalg.norm(np.maximum(e, 0.0), axis=-1) + np.minimum(e.max(axis=-1), 0.0)
            elif shape.kind == "capsule":
                axial = np.clip(p[..., 2], -size[1], size[1])
                d = np.linalg.norm(p - np.stack([0.0 * axial, 0.0 * axial, axial], axis=-1), axis=-1) - size[0]
            else:  # a kind added later: no host distance yet
                continue
            best = np.minimum(best, np.min(d - self.radius, axis=1))
        return best


def _writers(model, scene, variants, settings: RunSettings) -> list:
    """One USD writer per world (its own single-world file, written under a temporary name)."""
    if settings.usd_dir is None:
        return []
    os.makedirs(settings.usd_dir, exist_ok=True)
    writers = []
    for w, v in enumerate(variants):
        path = os.path.join(settings.usd_dir, f"{v.key}.partial.usdc")
        writers.append((path, UsdWriter(path, model, fps=scene.fps, particles=scene.export_particles,
                                        springs=scene.export_springs, world=w if len(variants) > 1 else None,
                                        **scene.export_options)))
    return writers


def _publish(partial: str) -> str:
    """Rename a closed ``<key>.partial.usdc`` to ``<key>.usdc`` (atomic: a partial file is never taken as done)."""
    final = partial.replace(".partial.usdc", ".usdc")
    os.replace(partial, final)
    return final
