"""The self-collision torture battery: scenes that press cloth onto itself hard, each run with every substep
audited (:class:`~warpspring.analysis.audit.SubstepAudit`: continuous crossings, intersections, pairs closer than
half the thickness). ``bench/torture.py`` runs it at full size on a device and writes its table;
``tests/test_torture.py`` runs it at small sizes.

Scenes (:data:`SCENES`), each at a ``size`` ("full" or "small": the grid's spacing and the run's length):

* ``twist720``, ``twist1440``: a 0.6 × 0.3 m cloth whose one short edge turns 720° (1440°) about the long axis
  while it approaches the other, pinned, short edge by 0.2 m (τ = 5 mm); then held.
* ``ring``: a square cloth pulled by its centre down through a ring (twelve capsules on a circle) smaller than it.
* ``stack``: five cloths dropped onto a box, their left edges lowered with them, then pulled off sideways.
* ``crumple``: a cloth draped over a sphere that sinks, turning, until it presses the folded pile into the ground.
* ``turntable``: a cloth dropped onto a turning box in the wind.

:func:`run_case` runs one scene under one integrator and returns a :class:`CaseResult`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..core.builder import ModelBuilder, SpringMaterial
from ..core.integrators import make_integrator
from ..core.guard_records import GuardLimits
from ..core.simulator import Simulator
from ..core.tracks import Track
from ..errors import ConfigError, SimulationError
from .audit import SubstepAudit
from .step_choice import pin_substeps

#: The sizes: each scene's grid spacing [m] and the share of its full duration that is run.
SIZES = {"full": dict(spacing=0.015, duration=1.0), "small": dict(spacing=0.03, duration=1.0)}
INTEGRATORS = ("symplectic_euler", "rk4", "implicit_euler")
THICKNESS = 0.005  # [m]: τ of every scene (the twist), below 0.7 × the finest grid's altitude (7.4 mm)
FPS = 60.0
#: The fewest substeps per frame; more where the pins move fast (``step_choice.pin_substeps``: a pin moves at most
#: a quarter of the cap's reach γ τ a step).
SUBSTEPS = 20
FRICTION = 0.2


def _cloth(builder: ModelBuilder, width: float, height: float, spacing: float, origin, *, name: str,
           rotation=(0.0, 0.0, 0.0, 1.0)) -> np.ndarray:
    """A cloth of width × height [m] at ``spacing`` [m], 1 kg/m², soft in-plane springs scaled to keep the
    step's stability as the spacing changes (ke ∝ spacing², so that ω² = ke/m does not grow as the mesh refines);
    returns its particles, shape [ny, nx]."""
    nx, ny = int(round(width / spacing)) + 1, int(round(height / spacing)) + 1
    scale = (spacing / 0.015) ** 2  # the full size's values at 0.015 m
    mass = 1.0 * width * height
    return builder.add_cloth_grid(
        nx=nx, ny=ny, spacing=spacing, origin=origin, rotation=rotation, mass=mass, radius=0.004, name=name,
        structural=SpringMaterial(100.0 * scale, 0.02 * scale), shear=SpringMaterial(30.0 * scale, 0.005 * scale),
        bend=SpringMaterial(0.2 * scale, 0.0002 * scale)).reshape(ny, nx)


def twist(turns: float):
    def build(builder: ModelBuilder, spacing: float, duration: float) -> float:
        ids = _cloth(builder, 0.6, 0.3, spacing, (0.0, -0.15, 1.0), name="strip")
        builder.add_pin_group(ids[:, 0], name="fixed")
        turn = 2.5 * duration
        builder.add_pin_group(
            ids[:, -1], name="turned",
            rotation=Track.rotation([0.0, turn], axis=(1, 0, 0), degrees=[0.0, 360.0 * turns], interpolation="smooth"),
            translation=Track([0.0, turn], [[0, 0, 0], [-0.2, 0, 0]], interpolation="smooth"))
        return 4.0 * duration

    return build


def ring(builder: ModelBuilder, spacing: float, duration: float) -> float:
    ids = _cloth(builder, 0.4, 0.4, spacing, (-0.2, -0.2, 0.6), name="cloth")
    ny, nx = ids.shape
    centre = ids[ny // 2 - 1:ny // 2 + 1, nx // 2 - 1:nx // 2 + 1].ravel()
    pull = 2.0 * duration
    builder.add_pin_group(centre, name="pull",
                          translation=Track([0.0, pull], [[0, 0, 0], [0, 0, -0.5]], interpolation="smooth"))
    radius, count = 0.07, 12
    for k in range(count):  # a ring in the plane z = 0.45 around the vertical through the cloth's centre
        angle = 2.0 * np.pi * (k + 0.5) / count
        tangent = angle + 0.5 * np.pi
        half = 0.5 * np.pi / count  # the half angle of the rotation from z onto the tangent
        axis = np.array([-np.sin(tangent), np.cos(tangent), 0.0])  # z about this axis by 90° → the tangent
        q = np.append(axis * np.sin(np.pi / 4), np.cos(np.pi / 4))
        builder.add_collider_capsule(center=(radius * np.cos(angle), radius * np.sin(angle), 0.45), radius=0.012,
                                     half_height=radius * np.sin(half) * 1.05, orientation=tuple(q), friction=0.3,
                                     name=f"ring{k}")
    return 3.0 * duration


def stack(builder: ModelBuilder, spacing: float, duration: float) -> float:
    builder.add_ground_plane(friction=0.5)
    builder.add_collider_box(center=(0.0, 0.0, 0.1), half_extents=(0.12, 0.12, 0.1), friction=0.5)
    land, pull = 0.5 * duration, 1.0 * duration
    for i in range(5):
        z = 0.26 + 0.02 * i
        ids = _cloth(builder, 0.36, 0.36, spacing, (-0.18, -0.18, z), name=f"cloth{i}")
        drop = 0.2 + 0.012 * i - z  # the left edge laid down beside the box's top, layer on layer
        builder.add_pin_group(ids[:, 0], name=f"edge{i}", translation=Track(
            [0.0, land, land + 0.3 * duration, land + 0.3 * duration + pull],
            [[0, 0, 0], [0, 0, drop], [0, 0, drop], [-0.6, 0, drop]], interpolation="smooth"))
    return land + 0.3 * duration + pull + 0.3 * duration


def crumple(builder: ModelBuilder, spacing: float, duration: float) -> float:
    builder.add_ground_plane(friction=0.8)
    _cloth(builder, 0.6, 0.6, spacing, (-0.3, -0.3, 0.3), name="cloth")
    drop, sink = 0.5 * duration, 1.0 * duration
    # The cloth drapes over the sphere, which then sinks until its top is 1 cm above the ground: the skirt
    # folds onto the ground and the sphere presses the pile into it, turning.
    builder.add_collider_sphere(
        center=(0.0, 0.0, 0.13), radius=0.12, friction=0.8,
        translation=Track([0.0, drop, drop + sink], [[0, 0, 0], [0, 0, 0], [0, 0, -0.24]], interpolation="smooth"),
        rotation=Track.rotation([0.0, drop, drop + sink], axis=(0, 0, 1), degrees=[0.0, 0.0, 180.0],
                                interpolation="smooth"))
    return drop + sink + 0.5 * duration


def turntable(builder: ModelBuilder, spacing: float, duration: float) -> float:
    builder.add_ground_plane(friction=0.5)
    ids = _cloth(builder, 0.9, 0.9, spacing, (-0.45, -0.45, 0.32), name="cloth")
    builder.add_collider_box(center=(0.0, 0.0, 0.15), half_extents=(0.1, 0.1, 0.15), friction=0.8,
                             rotation=Track.rotation([0.0, 3.0 * duration], axis=(0, 0, 1), degrees=[0.0, 540.0]))
    builder.add_aerodynamics(wind=(3.0, 1.0, 0.0))
    del ids
    return 3.0 * duration


SCENES = {"twist720": twist(2.0), "twist1440": twist(4.0), "ring": ring, "stack": stack, "crumple": crumple,
          "turntable": turntable}


#: Amplitude [m] of a perturbed start (``build_case(perturb=seed)``): each coordinate of each free particle moved by
#: up to this much, uniformly. A coiling strip is chaotic: such a start is another equally valid run, as a run on
#: CUDA (whose atomics sum in no fixed order) is.
PERTURBATION = 1.0e-6


def build_case(scene: str, *, size: str = "full", device=None, spacing: float | None = None,
               duration: float | None = None, thickness: float = THICKNESS, perturb: int | None = None):
    """The model of ``scene`` at ``size`` (``spacing`` [m] and ``duration`` [-] override the size's) and its
    length [s]; ``perturb``: the seed of a start whose free particles are moved by up to PERTURBATION."""
    if scene not in SCENES:
        raise ConfigError(f"unknown torture scene {scene!r}: choose from {', '.join(SCENES)}")
    if size not in SIZES:
        raise ConfigError(f"unknown size {size!r}: choose from {', '.join(SIZES)}")
    spacing = SIZES[size]["spacing"] if spacing is None else spacing
    duration = SIZES[size]["duration"] if duration is None else duration
    builder = ModelBuilder()
    seconds = SCENES[scene](builder, spacing, duration)
    builder.add_self_collision(thickness=thickness, friction=FRICTION)
    model = builder.finalize(device)
    if perturb is not None:
        q = model.particle_q.numpy()
        free = ~model.kinematic_mask()[:, None]
        jitter = np.random.default_rng(perturb).uniform(-PERTURBATION, PERTURBATION, q.shape)
        model.particle_q.assign((q + np.where(free, jitter, 0.0)).astype(q.dtype))
    return model, seconds


#: The battery's guard: the default. Its energy balance counts the work the self-collision pass does (a driven pin
#: pressing free cloth against itself works through that pass, not through a force); left out, it stopped twist1440
#: (small, duration 0.7, 58 substeps, symplectic Euler) at frame 47 for 0.226 J "created" while the run was clean.
GUARD = GuardLimits()


def scene_substeps(model) -> int:
    """A scene's substeps per 1/FPS frame: :data:`SUBSTEPS`, or more where its pins move further than a quarter of
    the self-collision cap's reach a step (:func:`~warpspring.analysis.step_choice.pin_substeps`)."""
    pins = pin_substeps(model, fps=FPS)
    return SUBSTEPS if pins is None else max(SUBSTEPS, pins[0])


@dataclass
class CaseResult:
    """One scene under one integrator: the substep audit's totals and what the run did.

    Attributes:
        scene, integrator, device: what ran.
        particles: the model's particles; frames, substeps: frames run and substeps per frame.
        audit: the :class:`SubstepAudit` (crossings, intersections, close pairs, minimum distance, first finding).
        pairs, capped: the self-collision's pairs pushed apart and vertices capped over the run.
        overflow: pairs dropped for a full pair list.
        outrun: pair-steps beyond the cap (a pinned side closing in on a free one that could not give way; the
            guarantee does not cover them).
        error: the simulation's error message, if it stopped (a guard), else ``None``.
        wall: wall time [s] of the run (simulation and audit), audit: of the audit alone.
    """

    scene: str
    integrator: str
    device: str
    particles: int
    frames: int
    substeps: int
    audit: SubstepAudit
    pairs: int
    capped: int
    overflow: int
    outrun: int
    error: str | None
    wall: float
    audit_wall: float

    @property
    def clean(self) -> bool:
        return self.error is None and self.audit.clean

    def row(self) -> list:
        a = self.audit
        first = "" if a.first is None else f"{a.first[0]:.3f} s: {a.first[2]}"
        return [self.scene, self.integrator, self.particles, self.substeps, self.frames * self.substeps, a.crossings,
                a.intersections, a.close, f"{a.min_distance * 1e3:.3f}" if np.isfinite(a.min_distance) else "-",
                self.pairs, self.capped, self.overflow, self.outrun,
                "; ".join(filter(None, [first, self.error and f"stopped: {self.error}"])), f"{self.wall:.0f}"]


HEADER = ["scene", "integrator", "particles", "substeps/frame", "substeps", "crossings", "intersections", "pairs < τ/2", "min d [mm]",
          "pairs pushed", "capped", "overflow", "pins outran", "first finding", "wall [s]"]


class _Timed(SubstepAudit):
    """The substep audit, timing itself."""

    wall = 0.0

    def after_frame(self, sim, frame: int) -> None:
        start = time.perf_counter()
        super().after_frame(sim, frame)
        self.wall += time.perf_counter() - start


def run_case(scene: str, integrator: str, *, size: str = "full", device=None, frames: int | None = None,
             substeps: int | None = None, spacing: float | None = None, duration: float | None = None,
             thickness: float = THICKNESS, progress=None, guard: GuardLimits | None = None,
             audit_from: int = 0, perturb: int | None = None, audit_workers: int = 1) -> CaseResult:
    """Run ``scene`` under ``integrator`` for its length (or ``frames``) at FPS and ``substeps`` (default: the
    scene's, :func:`scene_substeps`), auditing every substep; a guard stop ends the run and is reported, not raised.
    ``perturb``: the seed of a perturbed start (:func:`build_case`; the row's scene names it).
    ``progress(frame, frames, audit)`` is called after every frame, if given. ``guard``: default :data:`GUARD`.
    ``audit_from``: the first frame audited (the frames before it run unaudited: a test's way to skip the part of a
    scene where the surface is far from itself). ``audit_workers``: processes auditing each frame's substeps
    (:class:`SubstepAudit`'s ``workers``; the same findings, sooner)."""
    model, seconds = build_case(scene, size=size, device=device, spacing=spacing, duration=duration,
                                thickness=thickness, perturb=perturb)
    frames = int(round(seconds * FPS)) if frames is None else frames
    substeps = scene_substeps(model) if substeps is None else substeps
    guard = GUARD if guard is None else guard
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=FPS, substeps=substeps, guard=guard)
    audit = _Timed(thickness=thickness, workers=audit_workers)
    error = None
    start = time.perf_counter()
    try:
        for frame in range(frames):
            if frame == audit_from:
                audit.attach(sim)
            try:
                sim.step_frame()
            except SimulationError as failure:
                error = str(failure)
                break
            if progress is not None:
                progress(frame + 1, frames, audit)
        if error is None:
            try:
                sim.settle()  # the last frame's verdict (on CUDA read a frame later)
            except SimulationError as failure:
                error = str(failure)
    finally:
        audit.close_workers()
    wall = time.perf_counter() - start
    counts = model.self_contact.counts()
    label = scene if perturb is None else f"{scene} (seed {perturb})"
    return CaseResult(scene=label, integrator=integrator, device=str(model.device), particles=model.particle_count,
                      frames=sim.frame, substeps=substeps, audit=audit, pairs=int(counts["pairs"].sum()),
                      capped=int(counts["capped"].sum()), overflow=int(counts["overflow"].sum()),
                      outrun=int(counts["outrun"].sum()), error=error, wall=wall, audit_wall=audit.wall)
