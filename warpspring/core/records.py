"""The model's records: stabiliser settings, mesh and skin groups, collider shapes and input tracks."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from .. import checks
from ..kernels.spring_laws import SpringLaw
from ..kernels.shapes import SHAPE_NAMES
from .tracks import Track


SHAPE_KINDS = {name: kind for kind, name in SHAPE_NAMES.items()}
#: Most contacts one particle can hold in the contact buffer.
MAX_CONTACT_SLOTS = 64

#: The stabiliser thresholds that are live inputs (their names in ``kernels.inputs.INPUTS``).
STABILIZER_INPUTS = ("max_spring_force", "max_particle_force", "max_speed", "max_strain", "biphasic_strain",
                     "biphasic_ratio")
#: The lower bound of each bounded input, and whether the bound itself is allowed (gravity has none).
INPUT_BOUNDS = {"drag": (0.0, True), "biphasic_ratio": (1.0, True), "air_density": (0.0, True), "wind_noise": (0.0, True),
                **{name: (0.0, False) for name in STABILIZER_INPUTS if name != "biphasic_ratio"}}


@dataclass(frozen=True)
class Stabilizers:
    """Optional numerical stabilisers (all off by default; each one off compiles to nothing).

    They trade fidelity for robustness: clamps bound what an unstable step can inject; strain limiting
    and biphasic springs bound stretching (Provot's super-elasticity). The stability advisor accounts
    for biphasic springs with their stiffer branch. Whether each is on specialises the kernels; its value
    is a live input (``Model.stabilizers = ...`` between frames compiles nothing, and a keyframe track can
    animate it: ``Model.set_track("max_strain", track)``).

    Attributes:
        max_spring_force: clamp of each spring's force magnitude, elastic plus damping [N].
        max_particle_force: clamp of the magnitude of the total force on each particle [N].
        max_speed: clamp of each particle's speed after every step [m/s].
        max_strain: strain limiting (Provot 1995) towards (1 + max_strain)·L [-]: after every step,
            ``strain_iterations`` Jacobi passes shorten the springs longer than that, moving both ends
            in proportion to their inverse masses; velocities change by the same displacement / dt.
            A soft limit: a few passes leave a residual overshoot on long chains of stretched springs.
        strain_iterations: Jacobi passes of the strain limiting per step (part of a step's structure:
            changing it re-captures the frame graph, it compiles nothing).
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
        """The spring force law these settings switch on."""
        return SpringLaw(biphasic=self.biphasic_strain is not None, clamp_force=self.max_spring_force is not None)

    def enabled(self, name: str) -> bool:
        """Whether the stabiliser owning the input ``name`` is on (``biphasic_ratio`` belongs to biphasic springs)."""
        return getattr(self, "biphasic_strain" if name == "biphasic_ratio" else name) is not None

    @property
    def structure(self) -> tuple:
        """What these settings make the kernels and the frame graph depend on: the on/off switches and the
        number of strain-limiting passes (values are not part of it)."""
        return tuple(self.enabled(name) for name in STABILIZER_INPUTS) + (self.strain_iterations,)


@dataclass(frozen=True)
class MeshGroup:
    """A triangle mesh over a subset of the particles, exported as one USD mesh.

    Attributes:
        name: prim name of the mesh (a valid USD identifier).
        particles: global indices of the mesh's vertices, shape [vertex_count], int64.
        faces: triangles as indices into ``particles``, shape [face_count, 3], int32.
        uvs: texture coordinates per vertex, shape [vertex_count, 2]; per triangle corner, shape
            [face_count, 3, 2] (meshes with UV seams); or ``None``.
        polygon_counts: the authored faces' vertex counts (quads stay quads on export), shape
            [polygon_count], int32; ``None`` when the triangles are the authored faces.
        polygon_indices: the authored faces' vertices as indices into ``particles``, in order, shape
            [polygon_counts.sum()], int32; ``None`` with ``polygon_counts``.
        face_sets: named subsets of the faces (the polygons where there are, else the triangles), each
            int32 face indices, ascending; written as USD face sets (``UsdGeom.Subset``).
        dressing: what the USD mesh prim the mesh was read from carries besides its geometry (its primvars,
            subsets and their material bindings, subdivision scheme, orientation, name and kind), written
            back on export (:class:`~warpspring.core.usd_dressing.UsdDressing`), or ``None``. With it,
            ``particles`` are the prim's points in order and ``polygon_counts`` its faces in order.
    """

    name: str
    particles: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    polygon_counts: np.ndarray | None = None
    polygon_indices: np.ndarray | None = None
    face_sets: dict = field(default_factory=dict)
    dressing: object | None = None


@dataclass
class SkinGroup:
    """A surface that follows the particles through fixed weights (a soft body's mesh as authored), exported as
    one USD mesh: vertex v is at Σⱼ weights[v, j] · x[indices[v, j]].

    Attributes:
        name: prim name of the mesh (a valid USD identifier).
        indices: global particle indices each vertex follows, shape [vertex_count, w], int64.
        weights: their weights [-], shape [vertex_count, w] (rows sum to 1; padding has weight 0).
        faces: triangles as indices into the skin's vertices, shape [face_count, 3], int32.
        uvs: texture coordinates per vertex, shape [vertex_count, 2], or ``None``.
        polygon_counts, polygon_indices: the authored faces (quads stay quads), as in :class:`MeshGroup`, or
            ``None``.
        face_sets: named subsets of the faces, as in :class:`MeshGroup`.
        dressing: what the USD mesh prim the surface was read from carries besides its geometry, written back on
            export, as in :class:`MeshGroup` (the skin's vertices are the prim's points in order), or ``None``.
    """

    name: str
    indices: np.ndarray
    weights: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    polygon_counts: np.ndarray | None = None
    polygon_indices: np.ndarray | None = None
    face_sets: dict = field(default_factory=dict)
    dressing: object | None = None

    def points(self, q: np.ndarray) -> np.ndarray:
        """The skin's vertices [m] (or velocities [m/s]) for one world's particle values ``q`` [n, 3]: a fixed-order
        host product, so the same positions give the same bytes. Shape [vertex_count, 3], float64."""
        return np.einsum("vj,vjk->vk", self.weights, np.asarray(q, dtype=np.float64)[self.indices])


@dataclass(frozen=True)
class ShapeInfo:
    """Host-side description of one collider, for export and reporting.

    Attributes:
        kind: shape kind name ("plane", "sphere", "box", "capsule").
        name: prim name for export (a valid USD identifier).
        position: position of the shape frame at rest [m], shape [3].
        rotation: orientation of the shape frame at rest as a unit quaternion (x, y, z, w).
        size: kind-specific size [m]: sphere (radius, 0, 0); box (half extents along x, y, z); capsule (radius,
            half height along z, 0); plane (half width, half length, 0) for export only, 0 = fitted to the scene.
        friction: Coulomb friction coefficient [-].
        restitution: coefficient of restitution [-].
        translation_track: :class:`Track` of the offset T(t) [m] added to ``position``, or None.
        rotation_track: :class:`Track` of the rotation vector φ(t) [rad] turning the shape about its origin
            (orientation R(φ(t)) · ``rotation``), or None.
        thickness: a shell around the surface [m], ≥ 0: a particle of radius r touches at distance r + thickness.
        static_friction: Coulomb μ_s [-] ≥ ``friction`` (the kinetic μ_k); None: equal to ``friction``.
        mesh: a mesh collider's points, triangles and sides (``core.mesh_colliders.MeshShape``), or None.
    """

    kind: str
    name: str
    position: tuple
    rotation: tuple
    size: tuple
    friction: float
    restitution: float = 0.0
    translation_track: Track | None = None
    rotation_track: Track | None = None
    thickness: float = 0.0
    static_friction: float | None = None
    mesh: object = None

    @property
    def moving(self) -> bool:
        return self.translation_track is not None or self.rotation_track is not None

    def frame(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The shape's position [m] and orientation quaternion (x, y, z, w) at time ``t`` [s] (float64,
        the host reference of the device's ``shape_frame``)."""
        position = np.asarray(self.position, dtype=np.float64)
        orientation = np.asarray(self.rotation, dtype=np.float64)
        if self.rotation_track is not None:
            turn = Rotation.from_rotvec(self.rotation_track.sample(t)[0][0])
            orientation = (turn * Rotation.from_quat(orientation)).as_quat()
        if self.translation_track is not None:
            position = position + self.translation_track.sample(t)[0][0]
        return position, orientation


@dataclass(frozen=True)
class InputTracks:
    """The animated live inputs of a model, as the device arrays ``evaluate_input_tracks`` launches over:
    one entry per animated input of each world.

    Attributes:
        names: the animated inputs.
        track: each entry's track index in the model's track table, int32, shape [count].
        world: the world whose input row it writes (and whose time it samples at), int32, shape [count].
        slot: the first input-table column of each, int32, shape [count].
        width: components of each (1 or 3), int32, shape [count].
        by_world: the same entries by world (``kernels/tracks.WorldInputs``: a world's own, for a kernel that steps
            a world's substeps itself).
    """

    names: tuple
    track: wp.array
    world: wp.array
    slot: wp.array
    width: wp.array
    by_world: object = None

    @property
    def count(self) -> int:
        return self.track.shape[0]
