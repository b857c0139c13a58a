"""Model (static arrays), State (what every step changes) and Control (time-varying inputs)."""

from __future__ import annotations

from dataclasses import dataclass, field


import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.forces import ForceFeatures, SpringLaw
from ..kernels.precision import vec3_type


@dataclass(frozen=True)
class Stabilizers:
    """Optional numerical stabilisers (all off by default; each one off compiles to nothing).

    They trade fidelity for robustness: clamps bound what an unstable step can inject; strain limiting
    and biphasic springs bound stretching (Provot's super-elasticity). The stability advisor accounts
    for biphasic springs with their stiffer branch.

    Attributes:
        max_spring_force: clamp of each spring's force magnitude, elastic plus damping [N].
        max_particle_force: clamp of the magnitude of the total force on each particle [N].
        max_speed: clamp of each particle's speed after every step [m/s].
        max_strain: strain limiting (Provot 1995) towards (1 + max_strain)·L [-]: after every step,
            ``strain_iterations`` Jacobi passes shorten the springs longer than that, moving both ends
            in proportion to their inverse masses; velocities change by the same displacement / dt.
            A soft limit: a few passes leave a residual overshoot on long chains of stretched springs.
        strain_iterations: Jacobi passes of the strain limiting per step.
        biphasic_strain: strain beyond which springs stiffen [-].
        biphasic_ratio: stiffness beyond ``biphasic_strain`` over stiffness below it [-], ≥ 1.
    """

    max_spring_force: float | None = None
    max_particle_force: float | None = None
    max_speed: float | None = None
    max_strain: float | None = None
    strain_iterations: int = 4
    biphasic_strain: float | None = None
    biphasic_ratio: float = 10.0

    def __post_init__(self):
        for name in ("max_spring_force", "max_particle_force", "max_speed", "max_strain", "biphasic_strain"):
            if getattr(self, name) is not None:
                checks.positive(f"stabilizer {name}", getattr(self, name))
        checks.count("stabilizer strain_iterations", self.strain_iterations, minimum=1)
        checks.number("stabilizer biphasic_ratio", self.biphasic_ratio, minimum=1.0)

    @property
    def spring_law(self) -> SpringLaw:
        """The spring force law these settings ask for."""
        return SpringLaw(
            biphasic_strain=self.biphasic_strain,
            biphasic_ratio=float(self.biphasic_ratio) if self.biphasic_strain is not None else 1.0,
            max_force=self.max_spring_force,
        )


@dataclass(frozen=True)
class MeshGroup:
    """A triangle mesh over a subset of the particles, exported as one USD mesh.

    Attributes:
        name: prim name of the mesh (a valid USD identifier).
        particles: global indices of the mesh's vertices, shape [vertex_count], int64.
        faces: triangles as indices into ``particles``, shape [face_count, 3], int32.
        uvs: texture coordinates per vertex, shape [vertex_count, 2]; per triangle corner, shape
            [face_count, 3, 2] (meshes with UV seams); or ``None``.
    """

    name: str
    particles: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None


@dataclass(frozen=True)
class ShapeInfo:
    """Host-side description of one static collider, for export and reporting.

    Attributes:
        kind: shape type name ("plane", "sphere").
        name: prim name for export (a valid USD identifier).
        position: position of the shape frame [m], shape [3].
        rotation: orientation of the shape frame as a quaternion (x, y, z, w).
        size: type-specific size [m]: sphere (radius, 0, 0); plane (half width, half length, 0), 0 = infinite.
        friction: Coulomb friction coefficient [-].
    """

    kind: str
    name: str
    position: tuple
    rotation: tuple
    size: tuple
    friction: float


class Model:
    """Static description of a scene on one device, produced by :meth:`ModelBuilder.finalize`.

    Arrays are Warp arrays on :attr:`device` in the model's precision (:attr:`scalar`); the layout
    is documented per attribute as [unit], shape. Changing array values (e.g. stiffness) between
    steps is allowed; adding or removing whole force terms or collider types needs a new model,
    because kernels are specialized for the terms present at finalize time.
    """

    device: wp.Device
    precision: str  # "float32" or "float64"
    scalar: type  # wp.float32 or wp.float64
    vec3: type  # wp.vec3f or wp.vec3d
    up_axis: str  # "Y" or "Z"
    gravity: tuple  # [m/s²], gravitational acceleration (3 floats)
    drag: float  # [N·s/m], global viscous drag coefficient: f = -drag · v
    block_dim: int  # CUDA threads per block of the per-particle kernels (see ModelBuilder.finalize)
    stabilizers: Stabilizers  # optional clamps, strain limiting and biphasic springs

    particle_count: int
    particle_q: wp.array  # [m], shape [particle_count], initial positions
    particle_qd: wp.array  # [m/s], shape [particle_count], initial velocities
    particle_mass: wp.array  # [kg], shape [particle_count]
    particle_inv_mass: wp.array  # [1/kg], shape [particle_count]; 0 for pinned (kinematic) particles
    particle_radius: wp.array  # [m], shape [particle_count], contact radius

    spring_count: int
    spring_indices: wp.array  # wp.vec2i, shape [spring_count], the two particles of each spring
    spring_rest_length: wp.array  # [m], shape [spring_count]
    spring_stiffness: wp.array  # ke [N/m], shape [spring_count]
    spring_damping: wp.array  # kd [N·s/m], shape [spring_count], axial damper
    spring_gather: bool  # evaluate springs per particle (gather, CUDA default) or per spring (scatter, CPU)
    spring_max_degree: int  # most springs at one particle: the slots of the incidence table
    particle_spring_neighbor: wp.array2d  # int32, shape [spring_max_degree, particle_count]: the other particle
    #   of the particle's k-th spring; the particle itself past its last spring (ELL layout)
    particle_spring_id: wp.array2d  # int32, same shape: the index of that spring

    tri_count: int
    tri_indices: wp.array  # int32, shape [tri_count, 3], global particle indices

    shape_count: int
    shape_type: wp.array  # int32, shape [shape_count], kernels.contacts.SHAPE_* values
    shape_transform: wp.array  # wp.transform, shape [shape_count], shape frame in world
    shape_size: wp.array  # [m], vec3, shape [shape_count], see ShapeInfo.size
    shape_friction: wp.array  # [-], shape [shape_count], Coulomb coefficient
    shape_types: tuple  # sorted collider types present: the contact kernels' specialization key

    meshes: list  # list[MeshGroup], host-side, for export
    shapes: list  # list[ShapeInfo], host-side, for export

    def __init__(self, device: wp.Device, precision: str, scalar: type):
        self.device = device
        self.precision = precision
        self.scalar = scalar
        self.vec3 = vec3_type(scalar)
        self.meshes = []
        self.shapes = []

    # -- derived feature sets (what the kernels are specialized for) -------------------------------

    @property
    def spring_law(self) -> SpringLaw:
        """The spring force law (Hooke's, or biphasic and/or force-clamped by the stabilizers)."""
        return self.stabilizers.spring_law

    def force_features(self, control: Control | None) -> ForceFeatures:
        """The force terms a step of this model under ``control`` evaluates."""
        return ForceFeatures(
            spring_slots=self.spring_max_degree if self.spring_count and self.spring_gather else 0,
            gravity=any(g != 0.0 for g in self.gravity),
            drag=self.drag != 0.0,
            external=control is not None and control.particle_force is not None,
            spring_law=self.spring_law,
            max_particle_force=self.stabilizers.max_particle_force,
        )

    # -- factories ----------------------------------------------------------------------------------

    def state(self) -> State:
        """A new State holding the model's initial positions and velocities."""
        return State(
            particle_q=wp.clone(self.particle_q),
            particle_qd=wp.clone(self.particle_qd),
            particle_f=wp.zeros_like(self.particle_q),
        )

    def control(self) -> Control:
        """A new Control with no time-varying input set."""
        return Control(self)

    def describe(self) -> str:
        """One line naming the model's size, e.g. for a run summary."""
        shapes = ", ".join(s.kind for s in self.shapes) or "none"
        return (
            f"{self.particle_count} particles, {self.spring_count} springs, {self.tri_count} triangles, "
            f"colliders: {shapes} ({self.precision} on {self.device})"
        )


@dataclass
class State:
    """Everything a step changes.

    Attributes:
        particle_q: positions [m], shape [particle_count].
        particle_qd: velocities [m/s], shape [particle_count].
        particle_f: forces [N], shape [particle_count]; ``eval_forces`` writes it, and integrators write
            the forces at ``state_in`` into ``state_in.particle_f`` (fused gather kernels skip it).
    """

    particle_q: wp.array
    particle_qd: wp.array
    particle_f: wp.array

    def assign(self, other: State) -> None:
        """Copy positions, velocities and forces from ``other`` (same model) into this state."""
        wp.copy(self.particle_q, other.particle_q)
        wp.copy(self.particle_qd, other.particle_qd)
        wp.copy(self.particle_f, other.particle_f)


@dataclass
class Control:
    """Time-varying inputs of a step.

    Attributes:
        particle_force: external force per particle [N], shape [particle_count], or ``None`` when the
            scene applies none (then no kernel reads it).
    """

    model: Model = field(repr=False)
    particle_force: wp.array | None = None

    def set_particle_force(self, force) -> None:
        """Set the external force [N]: one 3-vector for every particle, or an array of shape [particle_count, 3].

        The array is allocated on first use; later calls overwrite it in place, so captured CUDA
        graphs see the new values.
        """
        model = self.model
        values = np.asarray(force, dtype=np.float64)
        if values.shape == (3,):
            values = np.broadcast_to(values, (model.particle_count, 3))
        if values.shape != (model.particle_count, 3):
            raise ConfigError(
                f"particle force must have shape (3,) or ({model.particle_count}, 3), got {values.shape}"
            )
        if not np.isfinite(values).all():
            raise ConfigError("particle force contains NaN or infinite values")
        host = wp.array(values, dtype=model.vec3, device="cpu")
        if self.particle_force is None:
            self.particle_force = wp.empty(model.particle_count, dtype=model.vec3, device=model.device)
        wp.copy(self.particle_force, host)
