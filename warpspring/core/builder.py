"""ModelBuilder: assemble particles, springs, triangles and colliders in bulk, then finalize to a Model.

Everything is vectorised over NumPy arrays: a cloth is a handful of array operations, never one Python
call per particle (a 1024 × 1024 cloth with its 6.3 M springs builds in seconds).
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.shapes import SHAPE_BOX, SHAPE_CAPSULE, SHAPE_NAMES, SHAPE_PLANE, SHAPE_SPHERE
from ..kernels.shapes import SHAPE_MESH
from ..kernels.kinematics import PARTICLE_KINEMATIC
from ..kernels.precision import scalar_type, vec3_type
from .bending import DihedralMaterial
from . import memory
from .aero import AIR_DENSITY, DEFAULT_DRAG, DEFAULT_LIFT, AeroFamily
from .families import ElementFamily, build_incidence, head_slots
from .emitters import Emitter, make_emitter
from .handles import HandleFamily, make_handle
from .hinges import dihedral_angle, mesh_hinges
from .kinematics import PinGroup, PinGroupTable
from .material import ClothMaterial, edge_springs, grid_masses, grid_springs, hinge_parameters, lumped_masses
from .model import Model
from .records import MeshGroup, ShapeInfo, SkinGroup, Stabilizers
from .selfcontact import DEFAULT_RELAXATION, check_settings, make_self_contact
from .springs import SPRING_LAWS, SpringPlasticity, set_spring_layout, spring_law_code
from ..kernels.springs import SpringLaw
from .tracks import Track, as_track, input_track
from .transforms import quat_between, quat_to_matrix

_AXES = {"Y": 1, "Z": 2}  # USD knows only Y-up and Z-up stages
#: Prim names under /World that the USD writer uses itself: a mesh named so gets a suffix.
RESERVED_PRIM_NAMES = ("particles", "springs", "colliders")
USD_EXTENSIONS = (".usd", ".usda", ".usdc")  # mesh files read through USD, not trimesh

#: Host bytes of the temporaries of making a cloth grid, per spring and per particle (measured; see
#: ``ModelBuilder._check_grid_room``).
GRID_TEMPORARY_PER_SPRING = 72
GRID_TEMPORARY_PER_PARTICLE = 48

_GRID_PINS = ("top-left", "top-right", "bottom-left", "bottom-right", "top", "bottom", "left", "right")


@dataclass(frozen=True)
class SpringMaterial:
    """Stiffness and damping of a family of springs, and the law it follows.

    Attributes:
        ke: stiffness [N/m] (square law: [N/m²]), ≥ 0.
        kd: axial damping [N·s/m], ≥ 0.
        law: "linear" (T = ke Δ) or "square" (T = ke Δ|Δ|) at the stretch Δ (``ModelBuilder.add_springs``).
        compression_ke: the stiffness in compression (same unit as ke), ≥ 0; ``None``: ke.
        plasticity: how the springs yield and break (:class:`~warpspring.core.springs.SpringPlasticity`);
            ``None``: elastic.
    """

    ke: float
    kd: float = 0.0
    law: str = "linear"
    compression_ke: float | None = None
    plasticity: SpringPlasticity | None = None

    def spring_options(self) -> dict:
        """The law's keyword arguments of :meth:`ModelBuilder.add_springs`."""
        return dict(law=self.law, compression_stiffness=self.compression_ke, plasticity=self.plasticity)


#: Default cloth spring families (structural, shear, bend) of ``add_cloth_grid``/``add_cloth_mesh``.
DEFAULT_STRUCTURAL = SpringMaterial(ke=1.0e3, kd=1.0)
DEFAULT_SHEAR = SpringMaterial(ke=1.0e3, kd=1.0)
DEFAULT_BEND = SpringMaterial(ke=1.0e2, kd=0.1)


def _mesh_collider_bytes(meshes: list) -> int:
    """Device bytes of mesh colliders (``mesh_colliders.MeshCollider``): the ``wp.Mesh``'s points, velocities and
    triangle indices, and for a cached mesh (not signed by its winding number) the pseudo-normals' face terms and
    CSR tables (per vertex, per corner, per edge group); the BVH lives in Warp's native memory, not counted."""
    from .mesh_colliders import edge_groups

    total = 0
    for info in meshes:
        v, f = len(info.points_at(0.0)), len(info.faces)
        total += 24 * v + 12 * f
        if not info.winding_number:
            groups = int(edge_groups(info.faces.astype(np.int64)).max()) + 1 if f else 0
            total += 48 * f + 4 * (v + 1) + 36 * f + 4 * (groups + 1)
    return total


class ModelBuilder:
    """Collects a scene on the host and finalizes it into a :class:`Model` on a device.

    Args:
        up_axis: world up axis, "Y" or "Z" (also written to USD).
        gravity: gravitational acceleration [m/s²]: a 3-vector, or ``None`` for 9.81 m/s² down the up axis.
        drag: viscous drag coefficient [N·s/m], f = -drag · v on every particle (per particle: at a
            finer resolution the same cloth feels more drag in total; scale it with 1 / particle count).
        stabilizers: optional clamps, strain limiting and biphasic springs (:class:`Stabilizers`).

    Gravity, drag and the stabiliser thresholds are live inputs of the model: they can change between
    frames (``model.gravity = ...``) or follow keyframe tracks (:meth:`set_track`).

    Example:
        >>> builder = ModelBuilder()
        >>> builder.add_cloth_grid(nx=32, ny=32, spacing=0.05, mass=0.5, pin=["top-left", "top-right"])
        >>> model = builder.finalize("cpu")
    """

    def __init__(self, *, up_axis: str = "Z", gravity=None, drag: float = 0.0, stabilizers: Stabilizers | None = None):
        axis = str(up_axis).upper()
        if axis not in _AXES:
            raise ConfigError(f"up_axis must be 'Y' or 'Z' (the two axes USD supports), got {up_axis!r}")
        self.up_axis = axis
        up = np.zeros(3)
        up[_AXES[axis]] = 1.0
        self.up_vector = up
        self.gravity = checks.vector("gravity", -9.81 * up if gravity is None else gravity)
        self.drag = checks.non_negative("drag", drag)
        if stabilizers is not None and not isinstance(stabilizers, Stabilizers):
            raise ConfigError(f"stabilizers must be a warpspring.Stabilizers, got {type(stabilizers).__name__}")
        self.stabilizers = stabilizers or Stabilizers()

        self._q: list[np.ndarray] = []
        self._qd: list[np.ndarray] = []
        self._mass: list[np.ndarray] = []
        self._radius: list[np.ndarray] = []
        self._pinned: list[np.ndarray] = []
        self._extra_pins: list[np.ndarray] = []
        self._particle_count = 0
        self._pin_groups: list[PinGroup] = []
        self._tracks: dict[str, Track] = {}

        self._springs: list[np.ndarray] = []
        self._spring_rest: list[np.ndarray] = []
        self._spring_family: list[str] = []  # the family name of each block of springs
        self._spring_ke: list[np.ndarray] = []
        self._spring_kd: list[np.ndarray] = []
        self._spring_count = 0
        self._spring_law: list[tuple] = []  # per group: count, law code, compression ratio, plastic, plasticity row
        self._cloth_grids: list[tuple] = []  # (first particle, nx, ny) of each add_cloth_grid (the grid layout)

        self._hinges: list[np.ndarray] = []
        self._hinge_rest: list[np.ndarray] = []
        self._hinge_ke: list[np.ndarray] = []
        self._hinge_kd: list[np.ndarray] = []
        self._hinge_count = 0

        self._families: list[ElementFamily] = []  # element families beyond springs, in the order added
        self._air: dict = {}  # the wind's live inputs at the start, once aerodynamics is added
        self._emitters: list[Emitter] = []

        self._meshes: list[MeshGroup] = []
        self._skins: list[SkinGroup] = []  # surfaces that follow particles by weights (soft bodies)
        self._shapes: list[ShapeInfo] = []
        self._self_collision: dict | None = None  # add_self_collision's settings

    # -- counts ---------------------------------------------------------------------------------------

    @property
    def particle_count(self) -> int:
        """Number of particles added so far."""
        return self._particle_count

    @property
    def spring_count(self) -> int:
        """Number of springs added so far."""
        return self._spring_count

    # -- primitives -----------------------------------------------------------------------------------

    def add_particles(self, positions, *, velocities=None, mass=1.0, radius=0.01, pinned=None) -> np.ndarray:
        """Add particles in bulk.

        Args:
            positions: positions [m], shape [n, 3].
            velocities: initial velocities [m/s], shape [n, 3] or [3]; default zero.
            mass: mass per particle [kg], > 0: a scalar or shape [n].
            radius: contact radius [m], ≥ 0: a scalar or shape [n].
            pinned: boolean mask of shape [n] (or indices into the new particles) of pinned particles.
                Pinned particles are kinematic: no force moves them (they keep their mass); they move on
                with their velocity, or as a pin group prescribes (:meth:`add_pin_group`).

        Returns:
            The global indices of the new particles, shape [n].
        """
        q = _points("particle positions", positions)
        n = len(q)
        qd = np.zeros((n, 3)) if velocities is None else _points("particle velocities", velocities, count=n)
        m = _per_item("particle mass", mass, n, positive=True)
        r = _per_item("particle radius", radius, n)
        pin_mask = np.zeros(n, dtype=bool)
        if pinned is not None:
            pinned = np.asarray(pinned)
            if pinned.dtype == bool:
                if pinned.shape != (n,):
                    raise ConfigError(f"pinned mask must have shape ({n},), got {pinned.shape}")
                pin_mask = pinned.copy()
            else:
                pin_mask[_indices("pinned", pinned, n)] = True
        start = self._particle_count
        self._q.append(q)
        self._qd.append(qd)
        self._mass.append(m)
        self._radius.append(r)
        self._pinned.append(pin_mask)
        self._particle_count += n
        return np.arange(start, start + n)

    def particle_positions(self, indices) -> np.ndarray:
        """The positions [m], shape [n, 3], of particles added so far, by global index (float64 copies)."""
        return np.concatenate(self._q)[_indices("particle", indices, self._particle_count)].astype(np.float64)

    def pin_particles(self, indices) -> None:
        """Pin particles (make them kinematic: no force moves them) by global index."""
        self._extra_pins.append(_indices("pinned particle", indices, self._particle_count))

    def add_pin_group(self, particles, *, translation: Track | None = None, rotation: Track | None = None,
                      pivot=None, name: str = "pins") -> int:
        """Pin particles and drive them together: by keyframe tracks of a rigid motion, or through Control.

        With tracks, a particle that starts at x₀ is at p + T(t) + R(φ(t)) (x₀ - p) at time t, with the
        velocity of that motion, exactly at every substep and every Runge-Kutta stage. Without tracks the
        group is driven by ``Control.set_pin_targets`` (straight to each frame's targets), and rests where
        it is until the first target comes.

        Args:
            particles: global particle indices (a particle belongs to one group at most).
            translation: :class:`Track` of T(t) [m], 3-vectors added to the rest positions.
            rotation: :class:`Track` of the rotation vector φ(t) [rad] about ``pivot`` (axis × angle; see
                :meth:`Track.rotation`).
            pivot: the rotation's centre [m] (default: the centroid of the group's initial positions).
            name: the group's name (made unique), to address it in ``Control.set_pin_targets``.

        Returns:
            The group's index.
        """
        idx = np.unique(_indices("pin group particle", particles, self._particle_count))
        if len(idx) == 0:
            raise ConfigError("a pin group needs at least one particle")
        for group in self._pin_groups:
            shared = np.intersect1d(group.particles, idx)
            if len(shared):
                raise ConfigError(f"particle {int(shared[0])} is already in pin group {group.name!r}: "
                                  "a particle follows one group")
        translation = None if translation is None else as_track("a pin group's translation", translation, 3)
        rotation = None if rotation is None else as_track("a pin group's rotation", rotation, 3)
        rest = np.concatenate(self._q)[idx]
        centre = rest.mean(axis=0) if pivot is None else checks.vector("pin group pivot", pivot)
        self._pin_groups.append(PinGroup(
            name=self._unique_name(name, [g.name for g in self._pin_groups]),
            particles=idx,
            translation=translation,
            rotation=rotation,
            pivot=centre,
        ))
        self._extra_pins.append(idx)
        return len(self._pin_groups) - 1

    def set_track(self, name: str, track: Track | None) -> None:
        """Animate a live input of the model by a keyframe :class:`Track` (see :meth:`Model.set_track`:
        "gravity", "drag" or a threshold of a stabiliser that is on); ``None`` removes it."""
        track = input_track(name, track)
        if track is None:
            self._tracks.pop(name, None)
        else:
            self._tracks[name] = track

    def add_springs(self, pairs, *, stiffness, damping=0.0, rest_length=None, family: str = "springs",
                    law: str = "linear", compression_stiffness=None, plasticity: SpringPlasticity | None = None
                    ) -> np.ndarray:
        """Add springs in bulk.

        Args:
            pairs: global particle indices of each spring, shape [s, 2]; the two must differ.
            stiffness: ke [N/m] (square law: [N/m²]), ≥ 0: a scalar or shape [s].
            damping: kd [N·s/m], ≥ 0: a scalar or shape [s].
            rest_length: [m], ≥ 0, scalar or shape [s]; default: the current distance of the pair.
            family: the name the springs are grouped under for export (one USD curves prim per family;
                the cloth builders use ``structural``, ``shear`` and ``bend``); a valid USD identifier.
            law: the tension T at the stretch Δ = |d| - L: "linear" (T = ke Δ) or "square" (T = ke Δ|Δ|, the
                seed's square spring: soft for small stretches, stiff for large ones).
            compression_stiffness: kc (same unit as ke), ≥ 0, a scalar or shape [s]: the stiffness when
                compressed (Δ < 0); default ke. Stored as the ratio kc/ke, so per-world stiffness rows
                (``Model.set_world_values``) scale both branches.
            plasticity: how the springs yield and break (:class:`SpringPlasticity`); default: elastic.

        Returns:
            The indices of the new springs, shape [s].
        """
        pairs = self._element_particles(pairs, 2, what="spring pairs", shape="[s, 2]", noun="spring",
                                         verb="joins")
        s = len(pairs)
        same = np.flatnonzero(pairs[:, 0] == pairs[:, 1])
        if len(same):
            raise ConfigError(f"spring {int(same[0])} joins particle {int(pairs[same[0], 0])} to itself")
        ke = _per_item("spring stiffness", stiffness, s)
        kd = _per_item("spring damping", damping, s)
        if rest_length is None:
            q = np.concatenate(self._q) if self._q else np.zeros((0, 3))
            rest = np.linalg.norm(q[pairs[:, 1]] - q[pairs[:, 0]], axis=1)
        else:
            rest = _per_item("spring rest length", rest_length, s)
        ratio = 1.0  # a scalar unless a compression branch is given: a linear group stores no per-spring law
        if compression_stiffness is not None:
            kc = _per_item("spring compression_stiffness", compression_stiffness, s)
            soft = np.flatnonzero((ke == 0.0) & (kc > 0.0))
            if len(soft):
                raise ConfigError(f"spring {int(soft[0])} has compression_stiffness {kc[soft[0]]:g} but stiffness 0: "
                                  "give it a stiffness > 0 (the compression branch is stored as kc/ke)")
            ratio = np.divide(kc, ke, out=np.ones(s), where=ke > 0.0)
        row = np.full(5, np.inf)
        if plasticity is not None:
            if not isinstance(plasticity, SpringPlasticity):
                raise ConfigError(f"plasticity must be a warpspring.SpringPlasticity, got {type(plasticity).__name__}")
            if len(rest) and rest.min() <= 0.0:
                raise ConfigError(f"plastic spring {int(np.argmin(rest))} has rest length 0: plastic strains are "
                                  "measured against the rest length, so it must be > 0")
            row[:] = plasticity.row
        # One entry per group (count, law code, ratio: a scalar or per spring, plastic, plasticity row), expanded to
        # per-spring arrays at finalize only where some group needs them.
        self._spring_law.append((s, spring_law_code(law), ratio, plasticity is not None, row))
        start = self._spring_count
        self._springs.append(pairs)
        self._spring_ke.append(ke)
        self._spring_kd.append(kd)
        self._spring_rest.append(rest)
        self._spring_family.append(checks.identifier("spring family", family))
        self._spring_count += s
        return np.arange(start, start + s)

    def _finalize_spring_laws(self, model: Model, farray, iarray) -> None:
        """The spring groups' laws and plasticity on the model: only the arrays and switches the groups use."""
        groups = [group for group in self._spring_law if group[0]]
        counts = np.array([group[0] for group in groups], dtype=np.int64)
        codes = np.array([group[1] for group in groups], dtype=np.int32)
        plastic_groups = np.array([group[3] for group in groups], dtype=bool)
        square = bool((codes == SPRING_LAWS["square"]).any())
        asymmetric = any(np.any(np.asarray(group[2]) != 1.0) for group in groups)
        model.spring_material_law = SpringLaw(square=square, asymmetric=asymmetric, plastic=bool(plastic_groups.any()))
        if square or asymmetric:
            model.spring_law_code = iarray(np.repeat(codes, counts))
            ratio = np.concatenate([np.broadcast_to(np.asarray(group[2], dtype=np.float64), (group[0],))
                                    for group in groups])
            model.spring_compression_ratio = farray(ratio, name="a spring compression ratio [-]")
        if plastic_groups.any():
            worlds = model.world_count
            plastic = np.repeat(plastic_groups, counts)
            rows = np.repeat(np.array([group[4] for group in groups]), counts, axis=0)
            model.spring_plastic_count = int(plastic.sum())
            model.spring_plastic_index = iarray(np.flatnonzero(plastic))
            dtype = np.float64 if model.scalar is wp.float64 else np.float32
            for column, name in enumerate(("yield_strain", "yield_force", "yield_rate", "hardening", "break_strain")):
                # inf (no limit, instant flow) is a value here: stored as is, not refused as an overflow.
                setattr(model, f"spring_{name}", wp.array(rows[:, column].astype(dtype), dtype=model.scalar,
                                                          device=model.device))
            model.spring_plastic_rest_length = farray(np.tile(np.concatenate(self._spring_rest), worlds),
                                                      name="a spring rest length [m]")
            model.spring_plastic_strain = farray(np.zeros(worlds * len(plastic)))

    def add_hinges(self, hinges, *, stiffness, damping=0.0, rest_angle=None) -> np.ndarray:
        """Add dihedral (angular) springs in bulk: hinge (x0, x1, x2, x3) resists folding about the edge
        x0 → x1 shared by the triangles (x0, x1, x2) and (x1, x0, x3) (``kernels/bending.py``).

        Args:
            hinges: global particle indices of each hinge, shape [h, 4], four different particles.
            stiffness: ke [N·m/rad], ≥ 0: a scalar or shape [h]; energy ½ ke (θ - θ0)².
            damping: kd [N·m·s/rad], ≥ 0: a scalar or shape [h].
            rest_angle: θ0 [rad] in (-π, π], a scalar or shape [h]; default: the current angle.

        Returns:
            The indices of the new hinges, shape [h].
        """
        hinges = self._element_particles(hinges, 4, what="hinges", shape="[h, 4] (edge x0, x1, wings x2, x3)",
                                         noun="hinge", verb="names")
        h = len(hinges)
        repeated = np.flatnonzero((np.diff(np.sort(hinges, axis=1), axis=1) == 0).any(axis=1))
        if len(repeated):
            raise ConfigError(f"hinge {int(repeated[0])} names a particle twice: {tuple(hinges[repeated[0]])}")
        ke = _per_item("hinge stiffness", stiffness, h)
        kd = _per_item("hinge damping", damping, h)
        if rest_angle is None:
            q = np.concatenate(self._q)[hinges] if h else np.zeros((0, 4, 3))
            rest = dihedral_angle(q[:, 0], q[:, 1], q[:, 2], q[:, 3])
        else:
            rest = np.broadcast_to(np.asarray(rest_angle, dtype=np.float64), (h,)).copy()
            if not (np.isfinite(rest).all() and (np.abs(rest) <= np.pi).all()):
                raise ConfigError("hinge rest angles must be finite and in [-π, π] radians")
        start = self._hinge_count
        self._hinges.append(hinges)
        self._hinge_ke.append(ke)
        self._hinge_kd.append(kd)
        self._hinge_rest.append(rest)
        self._hinge_count += h
        return np.arange(start, start + h)

    def add_family(self, family: ElementFamily) -> ElementFamily:
        """Add an element family (``warpspring.core.families.ElementFamily``) beyond the springs; the kernels sum
        the families in the order added. Its particle indices refer to this builder's particles.

        Returns:
            The family.
        """
        if not isinstance(family, ElementFamily):
            raise ConfigError(f"add_family takes a warpspring ElementFamily, got {type(family).__name__}")
        if any(f is family for f in self._families):
            raise ConfigError(f"this {family.name} family was added already")
        self._families.append(family)
        return family

    def add_handle(self, particles, *, kp: float, kd: float = 0.0, max_force: float | None = None,
                   translation: Track | None = None, rotation: Track | None = None, pivot=None,
                   name: str = "handle") -> int:
        """Grab particles with a PD-controlled handle: each is pulled toward its target by u = Kp e + Kd ė,
        e = x* − x, ė = v* − v, the force's magnitude capped at ``max_force`` (as a user grabs and drags
        cloth). A particle grabbed at x₀ has the target x*(t) = p + T(t) + R(φ(t)) (x₀ − p), moving at v*(t)
        (``kernels/handles.py``); without tracks the targets stay at the start positions.

        Args:
            particles: global particle indices (a particle may be held by several handles; it stays free
                otherwise: a handle is a force, not a pin).
            kp: stiffness gain Kp [N/m], > 0.
            kd: damping gain Kd [N·s/m], ≥ 0.
            max_force: the largest force [N] on one grabbed particle, > 0; ``None``: no cap.
            translation: :class:`Track` of T(t) [m], 3-vectors added to the targets.
            rotation: :class:`Track` of the rotation vector φ(t) [rad] about ``pivot``.
            pivot: the rotation's centre [m] (default: the centroid of the grabbed particles at the start).
            name: the handle's name, for messages.

        Returns:
            The handle's index.
        """
        idx = np.unique(_indices("handle particle", particles, self._particle_count))
        family = next((f for f in self._families if isinstance(f, HandleFamily)), None)
        if family is None:
            family = self.add_family(HandleFamily())
        rest = np.concatenate(self._q)[idx] if len(idx) else np.zeros((0, 3))
        family.handles.append(make_handle(self._unique_name(name, [h.name for h in family.handles]), idx, rest,
                                          kp=kp, kd=kd, max_force=max_force, translation=translation,
                                          rotation=rotation, pivot=pivot))
        return len(family.handles) - 1

    def add_emitter(self, *, shape: str = "point", center=(0.0, 0.0, 0.0), half_extents=(0.1, 0.1, 0.1), mesh=None,
                    rate: float = 0.0, bursts=(), life: float, velocity=(0.0, 0.0, 0.0), spread: float = 0.0,
                    capacity: int | None = None, mass: float = 1.0e-3, radius: float = 0.005, seed: int = 0,
                    name: str = "emitter") -> Emitter:
        """Add a particle emitter: free particles born on a shape at a rate and in bursts, each living ``life``
        seconds, from a fixed pool of particles recycled on the device (``kernels/emitters.py``). Its particles
        feel gravity, drag (relative to the wind where there is wind) and the colliders, and are written to
        USD as ``UsdGeom.Points`` with stable ``ids``.

        Args:
            shape: "point" (at ``center``), "box" (``center`` ± ``half_extents``, axis-aligned, uniform) or
                "mesh" (uniform over the area of ``mesh``: (vertices [m], faces), a ``trimesh.Trimesh`` or a
                file trimesh reads).
            center: the point, or the box's centre [m]; half_extents: the box's half sizes [m].
            rate: births per second [1/s], ≥ 0.
            bursts: (time [s], count) pairs: ``count`` births at ``time``.
            life: each particle's life span [s], > 0.
            velocity: the launch velocity v₀ [m/s]; spread: the standard deviation σ [m/s] of each of its
                components (an isotropic Gaussian).
            capacity: the pool's size; default 5 % above rate × life plus the bursts. A smaller pool recycles
                its oldest particles early (a :class:`~warpspring.core.emitters.PoolTooSmallWarning` now, and
                the count in the run's summary).
            mass: each particle's mass [kg]; radius: its contact radius [m].
            seed: the random stream's seed (the same serial always starts the same).
            name: the emitter's name (USD prim name, made unique).

        Returns:
            The :class:`~warpspring.core.emitters.Emitter`.
        """
        if isinstance(mesh, (str, os.PathLike)):
            mesh = load_mesh_file(mesh, what="emitter mesh")
        if mesh is not None and hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
            mesh = (np.asarray(mesh.vertices), np.asarray(mesh.faces))
        name = self._unique_name(name, [e.name for e in self._emitters] + [m.name for m in self._meshes]
                                 + list(RESERVED_PRIM_NAMES) + [k.name for k in self._skins])
        emitter = make_emitter(name, self._particle_count, shape=shape, center=center, half_extents=half_extents,
                               mesh=mesh, rate=rate, bursts=list(bursts), life=life, velocity=velocity,
                               spread=spread, seed=seed, capacity=capacity)
        # The pool: kinematic (dead) and still until born, at the emitter's centre.
        self.add_particles(np.broadcast_to(emitter.center, (emitter.capacity, 3)), mass=mass, radius=radius,
                           pinned=np.ones(emitter.capacity, dtype=bool))
        self._emitters.append(emitter)
        return emitter

    def add_aerodynamics(self, *, meshes=None, drag=DEFAULT_DRAG, lift=DEFAULT_LIFT, wind=(0.0, 0.0, 0.0),
                         air_density: float = AIR_DENSITY, noise: float = 0.0, noise_scale: float = 1.0,
                         seed: int = 0, precompute: bool | None = None) -> AeroFamily:
        """Let the wind act on cloth triangles: flat-plate drag and lift from each triangle's velocity relative
        to the air, its area and normal, either side (``kernels/aero.py`` gives the model and its source).

        Args:
            meshes: names of the meshes whose triangles feel the wind; ``None``: every mesh added so far.
            drag, lift: C_D and C_L [-], ≥ 0 (defaults: a flat plate's C_D = 1.2, C_L = 1.0).
            wind: the wind's velocity [m/s] at the start; a live input ("wind": set it between frames, per
                world, or by a keyframe track of gusts).
            air_density: ρ [kg/m³], > 0 (a live input, "air_density"); default: air at 20 °C.
            noise: relative amplitude a [-] of the wind's spatial noise, w · (1 + a · N(x / L)) with N Warp's
                Perlin noise in [-1, 1] (a live input, "wind_noise").
            noise_scale: L [m], > 0, the noise's length scale (the size of its gusts in space).
            seed: the noise's seed, ≥ 0.
            precompute: each triangle's force computed once per evaluation and gathered (True), or by each
                of its corners (False); ``None``: by the triangle count (``AeroFamily``).

        The noise is compiled in when ``noise`` > 0 here; with 0 it is absent (set a value here to animate it
        later). Returns the family (``model.families`` lists it as "wind triangles").
        """
        names = [m.name for m in self._meshes]
        chosen = names if meshes is None else [meshes] if isinstance(meshes, str) else list(meshes)
        unknown = [m for m in chosen if m not in names]
        if unknown:
            raise ConfigError(f"no mesh named {unknown[0]!r} to put in the wind; meshes: {', '.join(names) or 'none'}")
        if any(isinstance(f, AeroFamily) for f in self._families):
            raise ConfigError("aerodynamics was added already: add it once, naming every mesh (meshes=[...])")
        groups = [m for m in self._meshes if m.name in chosen]
        triangles = np.concatenate([g.particles[g.faces] for g in groups]) if groups else np.zeros((0, 3), np.int64)
        noise = checks.non_negative("wind noise", noise)
        scale = checks.positive("wind noise_scale", noise_scale)
        family = AeroFamily(triangles, drag=drag, lift=lift, noise_scale=scale if noise > 0.0 else 0.0, seed=seed,
                            precompute=precompute)
        self._air = {"wind": checks.vector("wind", wind), "air_density": checks.positive("air_density", air_density),
                     "wind_noise": noise}
        return self.add_family(family)

    def add_self_collision(self, *, thickness: float, friction: float = 0.0, relaxation: float = DEFAULT_RELAXATION,
                           meshes=None) -> None:
        """Keep the cloth and mesh surfaces from passing through themselves and each other: vertex–triangle and
        edge–edge pairs that share no vertex repel within ``thickness``, with Coulomb friction, and a
        per-vertex displacement cap makes a crossing within a step impossible (``kernels/selfcontact.py``
        gives the method and its proof). Runs after every step of every integrator.

        Args:
            thickness: τ [m], > 0, below 0.7 × the smallest triangle altitude: the separation kept between
                layers (a live value: ``model.self_contact.set(thickness=...)``, per world).
            friction: μ [-], ≥ 0: Coulomb friction between layers (live).
            relaxation: γ [-] in (0, 1/2): a vertex moves at most γ times its distance to the nearest primitive
                per step (live).
            meshes: names of the meshes whose triangles collide (with themselves and each other); ``None``:
                every mesh of the scene at finalize.
        """
        check_settings(thickness, friction, relaxation)
        if meshes is not None:
            meshes = [meshes] if isinstance(meshes, str) else list(meshes)
            names = [m.name for m in self._meshes]
            unknown = [m for m in meshes if m not in names]
            if unknown:
                raise ConfigError(f"no mesh named {unknown[0]!r} for self-collision; meshes: {', '.join(names) or 'none'}")
        self._self_collision = dict(thickness=thickness, friction=friction, relaxation=relaxation, meshes=meshes)

    def add_triangles(self, faces, *, name: str = "mesh", uvs=None, polygon_counts=None, polygon_indices=None,
                      face_sets=None) -> MeshGroup:
        """Add a triangle mesh over existing particles (exported as one USD mesh; later used by
        aerodynamics and collisions).

        Args:
            faces: global particle indices, shape [t, 3].
            name: mesh name; made unique and a valid USD identifier.
            uvs: texture coordinates per referenced particle in ascending index order, shape [v, 2];
                or per triangle corner, shape [t, 3, 2] (a mesh with UV seams: one particle, two UVs).
            polygon_counts, polygon_indices: the authored faces the triangles come from, written to USD in
                their place (quads stay quads): vertices per face, shape [p], each ≥ 3, and their global
                particle indices, shape [polygon_counts.sum()]; they must use the triangles' particles.
                Not with per-corner ``uvs``.
            face_sets: named subsets of the authored faces (or of the triangles without polygons), kept on
                export as USD face sets: a mapping name -> face indices.
        """
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ConfigError(f"triangles must have shape [t, 3] with t > 0, got {faces.shape}")
        faces = _indices("triangle vertex", faces, self._particle_count).reshape(-1, 3)
        used = np.zeros(self._particle_count, dtype=bool)
        used[faces] = True
        particles = np.flatnonzero(used)  # ascending, like np.unique, in O(n) instead of a sort
        remap = np.empty(self._particle_count, dtype=np.int64)
        remap[particles] = np.arange(len(particles))
        local = remap[faces]
        if uvs is not None:
            uvs = np.asarray(uvs, dtype=np.float64)
            if uvs.shape not in ((len(particles), 2), (len(faces), 3, 2)):
                raise ConfigError(f"uvs must have shape ({len(particles)}, 2) per vertex or ({len(faces)}, 3, 2) "
                                  f"per triangle corner, got {uvs.shape}")
            if not np.isfinite(uvs).all():
                raise ConfigError("uvs are not finite")
        counts = indices = None
        if (polygon_counts is None) != (polygon_indices is None):
            raise ConfigError("give polygon_counts and polygon_indices together, or neither")
        if polygon_counts is not None:
            counts = np.asarray(polygon_counts)
            if counts.ndim != 1 or len(counts) == 0 or not np.issubdtype(counts.dtype, np.integer) or counts.min() < 3:
                raise ConfigError("polygon_counts must be a non-empty list of integers >= 3 (vertices per face)")
            indices = _indices("polygon vertex", np.asarray(polygon_indices).ravel(), self._particle_count)
            if len(indices) != counts.sum():
                raise ConfigError(f"polygon_indices holds {len(indices)} entries, polygon_counts needs {counts.sum()}")
            if not used[indices].all():
                raise ConfigError("the polygons use a particle that no triangle uses: they must cover the same vertices")
            if uvs is not None and uvs.ndim == 3:
                raise ConfigError("per-corner uvs go with triangles, not with polygons: give uvs per vertex")
            counts, indices = counts.astype(np.int32), remap[indices].astype(np.int32)
        face_count = len(faces) if counts is None else len(counts)
        sets = {}
        for set_name, members in (face_sets or {}).items():
            members = np.unique(np.asarray(members, dtype=np.int64).ravel())
            if len(members) and (members[0] < 0 or members[-1] >= face_count):
                raise ConfigError(f"face set {set_name!r} names face {int(members[-1] if members[-1] >= face_count else members[0])}, "
                                  f"but the mesh has faces 0..{face_count - 1}")
            sets[checks.identifier("face set name", set_name)] = members.astype(np.int32)
        group = MeshGroup(
            name=self._unique_name(name, [m.name for m in self._meshes] + list(RESERVED_PRIM_NAMES)
                                   + [k.name for k in self._skins]),
            particles=particles,
            faces=local.reshape(-1, 3).astype(np.int32),
            uvs=uvs,
            polygon_counts=counts,
            polygon_indices=indices,
            face_sets=sets,
        )
        self._meshes.append(group)
        return group

    # -- cloth ----------------------------------------------------------------------------------------

    def add_cloth_grid(
        self,
        *,
        nx: int,
        ny: int,
        spacing: float,
        origin=(0.0, 0.0, 0.0),
        rotation=(0.0, 0.0, 0.0, 1.0),
        mass: float | None = None,
        particle_mass: float | None = None,
        velocity=(0.0, 0.0, 0.0),
        radius: float | None = None,
        structural: SpringMaterial | dict | bool | None = DEFAULT_STRUCTURAL,
        shear: SpringMaterial | dict | bool | None = DEFAULT_SHEAR,
        bend: SpringMaterial | dict | bool | None = DEFAULT_BEND,
        dihedral: DihedralMaterial | bool | None = None,
        material: ClothMaterial | None = None,
        pin=(),
        name: str = "cloth",
    ) -> np.ndarray:
        """Add a rectangular cloth of nx × ny particles.

        The grid lies in its local xy plane: column c at x = c·spacing, row r at y = r·spacing, local
        +z its front normal; ``rotation`` then ``origin`` place it in the world. Row ny-1 is the "top"
        edge, column 0 the "left" one.

        Without ``material``, the spring families take their constants as given: the cloth's response then
        depends on the resolution (a finer grid of the same springs is stiffer in bending and softer in
        stretch). With a :class:`ClothMaterial` the cloth is the same at any resolution: masses from
        :func:`~warpspring.core.material.grid_masses` (density × each particle's dual cell), structural and
        shear springs from :func:`~warpspring.core.material.grid_springs` (structural springs along the
        outer rows and columns at half stiffness and damping: each spans half a cell), no skip-one bend
        springs, and dihedral hinges on every interior edge of the triangles with
        :func:`~warpspring.core.material.hinge_parameters` and rest angle 0 (flat).

        Args:
            nx, ny: particles per row and per column (≥ 2).
            spacing: distance between neighbouring particles [m].
            origin: world position of particle (row 0, column 0) [m].
            rotation: orientation as a quaternion (x, y, z, w).
            mass: total mass [kg], shared equally; or give ``particle_mass`` [kg] instead (neither with
                ``material``).
            velocity: initial velocity of every particle [m/s].
            radius: contact radius [m]; default a quarter of the spacing.
            structural: springs to the 4-neighbours (ke [N/m], kd [N·s/m]). Each spring family takes what a
                scene file takes: a :class:`SpringMaterial`, a mapping ``{"ke": ..., "kd": ...}`` (a missing
                one takes the family's default), ``True`` for the default, or ``False``/``None`` for none.
            shear: springs along both diagonals of each quad (as ``structural``).
            bend: springs skipping one particle along rows and columns (as ``structural``).
            dihedral: dihedral springs on every interior edge of the cloth's triangles (ke [N·m/rad],
                kd [N·m·s/rad]), or ``None``/``False``.
            material: the cloth in physical units (stretch, shear [N/m], bending [N·m], density [kg/m²]),
                which then decides masses, springs, hinges and their damping: ``mass``/``particle_mass``
                must not be given, nor ``structural``, ``shear``, ``bend`` or ``dihedral`` other than
                their defaults (a :class:`~warpspring.ConfigError` says which).
            pin: corners/edges by name ("top-left", "top-right", "bottom-left", "bottom-right", "top",
                "bottom", "left", "right") and/or local particle indices r·nx + c.
            name: mesh name for export.

        Returns:
            Global particle indices, shape [ny, nx].
        """
        nx, ny = checks.count("nx", nx, minimum=2), checks.count("ny", ny, minimum=2)
        spacing = checks.positive("spacing", spacing)
        n = nx * ny
        structural = spring_family("structural", structural, DEFAULT_STRUCTURAL)
        shear = spring_family("shear", shear, DEFAULT_SHEAR)
        bend = spring_family("bend", bend, DEFAULT_BEND)
        dihedral = None if dihedral is False else dihedral
        self._check_grid_room(nx, ny, structural=structural, shear=shear, bend=bend,
                              hinges=material is not None or dihedral is not None, material=material is not None)
        if material is None:
            m = _mass_per_particle(mass, particle_mass, n)
        else:
            _material_decides(material, "add_cloth_grid", mass=mass is not None,
                              particle_mass=particle_mass is not None, structural=structural != DEFAULT_STRUCTURAL,
                              shear=shear != DEFAULT_SHEAR, bend=bend != DEFAULT_BEND, dihedral=dihedral is not None)
            m = grid_masses(material, nx, ny, spacing)
        rows, cols = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
        local = np.stack([cols * spacing, rows * spacing, np.zeros_like(rows, dtype=float)], axis=-1).reshape(-1, 3)
        q = self._place(local, origin, rotation)
        ids = self.add_particles(
            q,
            velocities=np.broadcast_to(checks.vector("velocity", velocity), (n, 3)),
            mass=m,
            radius=0.25 * spacing if radius is None else radius,
            pinned=self._grid_pins(pin, nx, ny),
        )
        grid = ids.reshape(ny, nx)
        self._cloth_grids.append((int(ids[0]), nx, ny))

        def pairs(a, b):
            return np.stack([a.ravel(), b.ravel()], axis=1)

        along_rows, along_columns = pairs(grid[:, :-1], grid[:, 1:]), pairs(grid[:-1, :], grid[1:, :])
        diagonals = np.concatenate([pairs(grid[:-1, :-1], grid[1:, 1:]), pairs(grid[:-1, 1:], grid[1:, :-1])])
        if material is None:
            families = [
                ("structural", structural, np.concatenate([along_rows, along_columns])),
                ("shear", shear, diagonals),
                ("bend", bend, np.concatenate([pairs(grid[:, :-2], grid[:, 2:]), pairs(grid[:-2, :], grid[2:, :])])),
            ]
            for family, springs, blocks in families:
                if springs is not None:
                    self.add_springs(blocks, stiffness=springs.ke, damping=springs.kd, family=family,
                                     **springs.spring_options())
        else:
            k = grid_springs(material)
            # A structural spring on an outer row or column spans half a cell: half stiffness and damping.
            row_share, column_share = np.ones((ny, nx - 1)), np.ones((ny - 1, nx))
            row_share[[0, -1], :] = column_share[:, [0, -1]] = 0.5
            share = np.concatenate([row_share.ravel(), column_share.ravel()])
            self.add_springs(np.concatenate([along_rows, along_columns]), stiffness=k.structural_stiffness * share,
                             damping=k.structural_damping * share, family="structural")
            self.add_springs(diagonals, stiffness=k.shear_stiffness, damping=k.shear_damping, family="shear")

        a, b = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()
        c, d = grid[1:, 1:].ravel(), grid[1:, :-1].ravel()
        faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
        uv = np.stack([cols / (nx - 1), rows / (ny - 1)], axis=-1).reshape(-1, 2)
        quads = np.stack([a, b, c, d], 1)  # written to USD as quads, as a modeller would make the grid
        self.add_triangles(faces, name=name, uvs=uv, polygon_counts=np.full(len(quads), 4), polygon_indices=quads)
        if material is not None:
            self._add_mesh_hinges(q, faces - ids[0], ids, material, rest="flat")
        elif dihedral is not None:
            self._add_mesh_hinges(q, faces - ids[0], ids, dihedral)
        return grid

    def add_cloth_mesh(
        self,
        mesh,
        faces=None,
        *,
        origin=(0.0, 0.0, 0.0),
        rotation=(0.0, 0.0, 0.0, 1.0),
        scale: float = 1.0,
        mass: float | None = None,
        density: float | None = None,
        velocity=(0.0, 0.0, 0.0),
        radius: float | None = None,
        structural: SpringMaterial | dict | bool | None = DEFAULT_STRUCTURAL,
        bend: SpringMaterial | dict | bool | None = DEFAULT_BEND,
        dihedral: DihedralMaterial | bool | None = None,
        material: ClothMaterial | None = None,
        pin=(),
        name: str = "cloth",
        prim: str | None = None,
    ) -> np.ndarray:
        """Add a cloth from any triangle or polygon mesh.

        Every mesh edge becomes a structural spring; for every interior edge, the two vertices opposite
        it are joined by a bend spring. Mass is lumped to the vertices by triangle area. With a
        :class:`ClothMaterial` the cloth is the same at any resolution: masses from
        :func:`~warpspring.core.material.lumped_masses`, one spring per edge with
        :func:`~warpspring.core.material.edge_springs` (Van Gelder's rule), no bend springs, and dihedral
        hinges on every interior edge with :func:`~warpspring.core.material.hinge_parameters`, rest angles
        from the mesh as given. A file or
        ``trimesh.Trimesh`` is welded first: vertices at the same position (which loaders split along UV
        seams) become one particle, in order of first appearance (an OBJ file's ``v`` order), and the UVs
        are kept per triangle corner where a seam needs two.

        Args:
            mesh: a ``trimesh.Trimesh``, a file path trimesh can load (OBJ, STL, PLY, GLB, ...), a USD file
                (``.usd``, ``.usda``, ``.usdc``: see :func:`~warpspring.io.usd_mesh.read_usd_mesh` for what is
                applied; its polygons are written back as authored, its face sets kept), or a vertex array
                [m], shape [v, 3] (then ``faces`` is required).
            faces: vertex indices of each triangle, shape [t, 3], when ``mesh`` is an array.
            origin, rotation, scale: placement; world = origin + rotation · (scale · vertex).
            mass: total mass [kg]; or ``density``: areal density [kg/m²] (neither with ``material``).
            velocity: initial velocity [m/s].
            radius: contact radius [m]; default a quarter of the mean edge length.
            structural, bend: spring families (ke [N/m], kd [N·s/m]) as in :meth:`add_cloth_grid`: a
                :class:`SpringMaterial`, a mapping ``{"ke": ..., "kd": ...}``, ``True`` (the default) or
                ``False``/``None`` (none).
            dihedral: dihedral springs on every interior edge (ke [N·m/rad], kd [N·m·s/rad]), or
                ``None``/``False``.
            material: the cloth in physical units (stretch [N/m], bending [N·m], density [kg/m²]; an edge
                network's shear modulus is 3/8 stretch whatever ``shear`` says), which then decides masses,
                springs, hinges and their damping: ``mass``/``density`` must not be given, nor
                ``structural``, ``bend`` or ``dihedral`` other than their defaults.
            pin: vertex indices of pinned particles.
            name: mesh name for export.
            prim: for a USD file, the path of the mesh prim to read (``"/World/cloth"``); ``None``: the
                file's only mesh.

        Returns:
            Global particle indices of the mesh vertices, shape [v].
        """
        import trimesh

        structural = spring_family("structural", structural, DEFAULT_STRUCTURAL)
        bend = spring_family("bend", bend, DEFAULT_BEND)
        dihedral = None if dihedral is False else dihedral
        uv = polygons = None
        face_sets = {}
        usd = isinstance(mesh, (str, os.PathLike)) and os.fspath(mesh).lower().endswith(USD_EXTENSIONS)
        if prim is not None and not usd:
            raise ConfigError(f"prim= chooses a mesh of a USD file ({', '.join(USD_EXTENSIONS)}), not of {mesh!r}")
        if usd:
            from ..io.usd_mesh import read_usd_mesh

            read = read_usd_mesh(mesh, prim=prim, up_axis=self.up_axis)
            vertices, faces = read.vertices, read.triangles
            polygons = (read.polygon_counts, read.polygon_indices)
            face_sets = read.face_sets
        elif isinstance(mesh, (str, os.PathLike)):
            mesh = load_mesh_file(mesh)
        loaded = not usd and isinstance(mesh, trimesh.Trimesh)
        if loaded:
            vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
            visual_uv = getattr(getattr(mesh, "visual", None), "uv", None)
            if visual_uv is not None and len(visual_uv) == len(vertices):
                uv = np.asarray(visual_uv, dtype=np.float64)
        elif not usd:
            if faces is None:
                raise ConfigError("add_cloth_mesh needs faces= when the mesh is given as a vertex array")
            vertices = np.asarray(mesh, dtype=np.float64)
        vertices = _points("mesh vertices", vertices)
        faces = np.asarray(faces)
        if len(vertices) == 0 or faces.size == 0:
            raise ConfigError("the cloth mesh is empty: it needs at least one triangle")
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise ConfigError(f"mesh faces must be triangles, shape [t, 3], got {faces.shape}")
        faces = _indices("mesh face vertex", faces, len(vertices)).reshape(-1, 3)
        if loaded:  # loaders split a vertex wherever its UVs differ (a texture seam): the cloth must not tear
            vertices, faces, uv = _weld_seams(vertices, faces, uv)
        scale = checks.positive("scale", scale)

        tri = trimesh.Trimesh(vertices * scale, faces, process=False, validate=False)
        area = tri.area_faces
        if not (area > 0.0).any():
            raise ConfigError("every triangle of the cloth mesh has zero area")
        lumped = np.bincount(faces.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(vertices))
        lonely = np.flatnonzero(lumped <= 0.0)
        if len(lonely):
            raise ConfigError(
                f"mesh vertex {int(lonely[0])} belongs to no triangle of nonzero area "
                f"({len(lonely)} such vertices): remove unreferenced vertices and degenerate faces"
            )
        if material is None:
            if (mass is None) == (density is None):
                raise ConfigError("give exactly one of mass= (total, kg) or density= (kg/m²) for a cloth mesh, "
                                  "or material=")
            areal = checks.positive("mass", mass) / area.sum() if density is None else checks.positive("density", density)
            particle_mass = lumped * areal
        else:
            _material_decides(material, "add_cloth_mesh", mass=mass is not None, density=density is not None,
                              structural=structural != DEFAULT_STRUCTURAL, bend=bend != DEFAULT_BEND,
                              dihedral=dihedral is not None)
            particle_mass = lumped_masses(material, vertices * scale, faces)

        edges = tri.edges_unique
        ids = self.add_particles(
            self._place(vertices * scale, origin, rotation),
            velocities=np.broadcast_to(checks.vector("velocity", velocity), (len(vertices), 3)),
            mass=particle_mass,
            radius=0.25 * float(tri.edges_unique_length.mean()) if radius is None else radius,
            pinned=_indices("pinned vertex", np.atleast_1d(pin), len(vertices)) if np.size(pin) else None,
        )
        if material is not None:
            ke, kd = edge_springs(material, vertices * scale, faces, edges)
            self.add_springs(ids[edges], stiffness=ke, damping=kd, family="structural")
        else:
            if structural is not None and len(edges):
                self.add_springs(ids[edges], stiffness=structural.ke, damping=structural.kd, family="structural",
                                 **structural.spring_options())
            if bend is not None:
                opposite = tri.face_adjacency_unshared
                if len(opposite):
                    self.add_springs(ids[opposite], stiffness=bend.ke, damping=bend.kd, family="bend",
                                     **bend.spring_options())
        self.add_triangles(ids[faces], name=name, uvs=uv, face_sets=face_sets,
                           polygon_counts=None if polygons is None else polygons[0],
                           polygon_indices=None if polygons is None else ids[polygons[1]])
        if material is not None:
            self._add_mesh_hinges(vertices * scale, faces, ids, material, rest="mesh")
        elif dihedral is not None:
            self._add_mesh_hinges(vertices * scale, faces, ids, dihedral)
        return ids

    # -- soft bodies ----------------------------------------------------------------------------------

    def add_soft_body(
        self,
        mesh,
        *,
        method: str = "voxel",
        youngs_modulus: float,
        density: float | None = None,
        mass: float | None = None,
        spacing: float | None = None,
        damping: float = 0.0,
        origin=(0.0, 0.0, 0.0),
        rotation=(0.0, 0.0, 0.0, 1.0),
        scale: float = 1.0,
        velocity=(0.0, 0.0, 0.0),
        radius: float | None = None,
        mass_distribution: str = "volume",
        mass_weights=None,
        skin_mass_factor: float = 1.0,
        mass_gradient=(0.0, 0.0, 0.0),
        options: Mapping | None = None,
        name: str = "soft_body",
        prim: str | None = None,
        plasticity: SpringPlasticity | None = None,
        volume: bool = False,
        bulk_modulus: float | None = None,
        elasticity: str = "springs",
        poisson_ratio: float = 0.25,
    ):
        """Add a soft body made from a closed mesh by one of the seven mass-spring topologies.

        The topology, its springs' stiffness from E and the particles' volume shares come from
        :mod:`warpspring.core.softbody` (where each method and each E → k mapping is stated). The mesh as
        authored (its faces, UVs, face sets) is exported as a USD mesh whose vertices follow the particles
        through the method's embedding weights (:class:`~warpspring.core.records.SkinGroup`).

        Args:
            mesh: a ``trimesh.Trimesh``, a file trimesh reads (OBJ, STL, PLY, GLB, ...) or a USD file (``prim``
                chooses its mesh). Vertices at one position are welded for the topology (a seam does not split
                the body); the export keeps the authored vertices.
            method: ``"brute_force"``, ``"voxel"``, ``"grid"``, ``"scaffold"``, ``"shell"``, ``"tetrahedral"``
                (needs ``pip install warpspring[tet]``) or ``"delaunay"``; all but brute force and scaffold need a
                closed (watertight) mesh.
            youngs_modulus: E [Pa], > 0.
            density: ρ [kg/m³] (the mass is ρ × the mesh's volume: a closed mesh); or ``mass``: total [kg].
            spacing: the method's resolution [m] (voxel pitch, grid spacing, tet edge length, Poisson-disk
                radius); default a sixth of the largest extent.
            damping: stiffness-proportional damping β [s], ≥ 0: each spring's kd = β·ke [N·s/m] (a mode of
                angular frequency ω is damped by ζ = βω/2 whatever the resolution).
            origin, rotation, scale: placement; world = origin + rotation · (scale · vertex).
            velocity: initial velocity [m/s].
            radius: particles' contact radius [m]; default a quarter of the mean spring length.
            mass_distribution: ``"volume"`` (each particle's volume share) or ``"uniform"``.
            mass_weights, skin_mass_factor, mass_gradient: relative weights per particle (an array or a function
                of the rest positions), a factor on the particles the surface follows (a heavier skin), a linear
                bias g [1/m] (weights × (1 + g·(x − centroid)): a body heavier on one side rights itself); see
                :func:`~warpspring.core.softbody.distribute_mass`. Positions are in the mesh's scaled frame.
            options: the method's own options (``body_diagonals``, ``neighbours``, ``ties``, ``scaffold``,
                ``thickness``, ``epsilon``, ``optimize``, ``seed``, ``max_vertices``, ...).
            name: the exported mesh's name; the spring families are ``<name>_<group>``.
            prim: for a USD file, the path of the mesh prim to read.
            plasticity: how every spring of the body yields and breaks (:class:`SpringPlasticity`, its limits
                per spring, e.g. ``yield_strain``); default: elastic.
            volume: add a bulk energy ½ K V₀ (J − 1)² per tet on the signed volume (the tet volume family,
                :mod:`warpspring.core.volume`), for the ``"tetrahedral"`` and ``"delaunay"`` methods (their tets).
                Use it when the body meets strains beyond ~10 % (a drop, a squash, a soft jelly under its own
                weight): springs alone do not resist a change of volume, and tets pushed through themselves stay
                inverted (``bench/RESULTS.md`` §18b, §18d). It raises the body's bulk stiffness, so the
                stable step shrinks and E in tension grows (measured on a bar at the default K: by 11–14 %
                for tetrahedral bodies, ν from ~0.27 to ~0.39; by 19–20 % for Delaunay ones).
            bulk_modulus: the term's K [Pa], > 0; default E / (3(1 − 2ν)) = 2E/3 at the networks' ν = 1/4. Its
                damper has kd = ``damping`` × K [Pa·s]. Live per world after finalize
                (``VolumeFamily.set_values``).
            elasticity: what carries the body's elasticity: ``"springs"`` (the method's spring network), or, for the
                ``"tetrahedral"`` and ``"delaunay"`` methods, ``"neohookean"``: the tets carry it as the energy
                V₀[μ/2 (I_C − 3) + λ/2 (J − 1 − μ/λ)²] per tet (the neo-Hookean family,
                :mod:`warpspring.core.neohookean`), whose linearisation at rest is linear elasticity of (E, ν) and
                passes the patch test; no springs are made (masses as with springs). Its damper (β = ``damping``) acts
                on the strain rate: at rest it is Rayleigh's −β K v, and it spares rigid motions. Live per world
                after finalize (``NeoHookeanFamily.set_values``).
            poisson_ratio: ν of the ``"neohookean"`` material, in (−1, ½) (the spring networks are fixed at ¼).

        Returns:
            A :class:`~warpspring.core.softbody.SoftBody`: the particles and springs added, per group counts,
            the embedding, the E → k rule, for tets the sliver report, and with ``volume`` the family's tets.
        """
        import time

        import trimesh

        from . import softbody

        started = time.perf_counter()
        source = os.fspath(mesh) if isinstance(mesh, (str, os.PathLike)) else name
        neohookean = _elasticity(elasticity, poisson_ratio, method=method, volume=volume, bulk_modulus=bulk_modulus,
                                 plasticity=plasticity, source=name)
        uv = polygons = None
        face_sets = {}
        usd = isinstance(mesh, (str, os.PathLike)) and os.fspath(mesh).lower().endswith(USD_EXTENSIONS)
        if prim is not None and not usd:
            raise ConfigError(f"prim= chooses a mesh of a USD file ({', '.join(USD_EXTENSIONS)}), not of {mesh!r}")
        if usd:
            from ..io.usd_mesh import read_usd_mesh

            read = read_usd_mesh(mesh, prim=prim, up_axis=self.up_axis)
            vertices, faces = read.vertices, read.triangles
            polygons, face_sets = (read.polygon_counts, read.polygon_indices), read.face_sets
        else:
            if isinstance(mesh, (str, os.PathLike)):
                mesh = load_mesh_file(mesh, what="soft-body mesh")
            if not isinstance(mesh, trimesh.Trimesh):
                raise ConfigError(f"a soft body's mesh must be a trimesh.Trimesh or a mesh file, got {type(mesh).__name__}")
            vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
            visual_uv = getattr(getattr(mesh, "visual", None), "uv", None)
            if visual_uv is not None and len(visual_uv) == len(vertices):
                uv = np.asarray(visual_uv, dtype=np.float64)
        vertices = _points("soft-body mesh vertices", vertices)
        faces = np.asarray(faces)
        if len(vertices) == 0 or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ConfigError(f"{source}: a soft body needs a triangle mesh with at least one face, got faces of "
                              f"shape {faces.shape}")
        faces = _indices("mesh face vertex", faces, len(vertices)).reshape(-1, 3)
        scale = checks.positive("scale", scale)
        welded, first, inverse = np.unique(vertices * scale, axis=0, return_index=True, return_inverse=True)
        body = trimesh.Trimesh(welded, inverse.reshape(-1)[faces], process=False, validate=False)

        if (mass is None) == (density is None):
            raise ConfigError("give exactly one of density= (kg/m³) or mass= (total, kg) for a soft body")
        if options is not None and not isinstance(options, Mapping):
            raise ConfigError(f"a soft body's options must be a mapping of the method's options, got {options!r}")
        topology = softbody.build_topology(body, method, youngs_modulus=checks.positive("youngs_modulus", youngs_modulus),
                                           spacing=spacing, source=source, **dict(options or {}))
        if mass is None:
            if not body.is_watertight:
                raise ConfigError(f"{source}: density= needs the mesh's volume, and an open mesh has none: give mass= "
                                  "(total, kg)")
            mass = checks.positive("density", density) * float(body.volume)
        masses = softbody.distribute_mass(topology, checks.positive("mass", mass), distribution=mass_distribution,
                                          weights=mass_weights, skin_factor=skin_mass_factor, gradient=mass_gradient)
        beta = checks.non_negative("damping", damping)

        lengths = np.concatenate([np.linalg.norm(topology.positions[p[:, 1]] - topology.positions[p[:, 0]], axis=1)
                                  for p, _ in topology.springs.values()] or [np.ones(1)])
        ids = self.add_particles(
            self._place(topology.positions, origin, rotation),
            velocities=np.broadcast_to(checks.vector("velocity", velocity), (topology.particle_count, 3)),
            mass=masses,
            radius=0.25 * float(lengths.mean()) if radius is None else radius,
        )
        name = self._unique_name(name, [m.name for m in self._meshes] + [k.name for k in self._skins]
                                 + [e.name for e in self._emitters] + list(RESERVED_PRIM_NAMES))
        springs = {}
        for group, (pairs, ke) in topology.springs.items():
            if len(pairs) and not neohookean:
                springs[group] = self.add_springs(ids[pairs], stiffness=ke, damping=beta * ke, family=f"{name}_{group}",
                                                  plasticity=plasticity)
        skin = SkinGroup(
            name=name,
            indices=ids[topology.skin_indices][inverse.reshape(-1)],
            weights=topology.skin_weights[inverse.reshape(-1)],
            faces=faces.astype(np.int32),
            uvs=uv,
            polygon_counts=None if polygons is None else np.asarray(polygons[0], dtype=np.int32),
            polygon_indices=None if polygons is None else np.asarray(polygons[1], dtype=np.int32),
            face_sets={checks.identifier("face set name", k): np.asarray(v, dtype=np.int32) for k, v in face_sets.items()},
        )
        self._skins.append(skin)
        volume_tets = None
        if volume or bulk_modulus is not None:
            from .volume import add_volume_term

            volume_tets = add_volume_term(self, topology, ids, volume=volume, method=method, youngs_modulus=youngs_modulus,
                                          bulk_modulus=bulk_modulus, damping=beta, source=name)
        elastic_tets = None
        if neohookean:
            from .neohookean import add_neohookean_term

            elastic_tets = add_neohookean_term(self, topology, ids, method=method, youngs_modulus=youngs_modulus,
                                               poisson_ratio=poisson_ratio, damping=beta, source=name)
        return softbody.SoftBody(
            name=name, method=method, particles=ids, springs=springs, skin=skin,
            stiffness_rule=(f"neo-Hookean tets (E = {float(youngs_modulus):g} Pa, ν = {float(poisson_ratio):g}), no springs"
                            if neohookean else topology.stiffness_rule),
            youngs_modulus=float(youngs_modulus), mass=float(masses.sum()), slivers=topology.slivers,
            topology=topology, build_seconds=time.perf_counter() - started, volume_tets=volume_tets,
            elasticity=elasticity, elastic_tets=elastic_tets,
        )

    # -- colliders ------------------------------------------------------------------------------------

    def add_collider_plane(self, *, point=(0.0, 0.0, 0.0), normal=None, friction: float = 0.5,
                           restitution: float = 0.0, translation: Track | None = None,
                           rotation: Track | None = None, name="ground", static_friction: float | None = None,
                           thickness: float = 0.0) -> int:
        """Add an infinite plane; particles stay on the side its normal points to.

        Args:
            point: a point on the plane [m].
            normal: plane normal (normalised here); default the up axis.
            friction: Coulomb coefficient μ [-], ≥ 0.
            restitution: coefficient of restitution e [-] in [0, 1]: the normal speed an impact keeps.
            translation, rotation: keyframe tracks moving the plane (see :meth:`add_collider_box`).
            name: prim name for export.

        Returns:
            The collider's index.
        """
        n = self.up_vector if normal is None else checks.vector("plane normal", normal)
        length = np.linalg.norm(n)
        if length == 0.0:
            raise ConfigError("plane normal must be a nonzero vector")
        orientation = quat_between(np.array([0.0, 0.0, 1.0]), n / length)
        return self._add_shape(SHAPE_PLANE, checks.vector("plane point", point), orientation, (0.0, 0.0, 0.0),
                               friction, restitution, translation, rotation, name, static_friction=static_friction,
                               thickness=thickness)

    def add_ground_plane(self, *, height: float = 0.0, friction: float = 0.5, restitution: float = 0.0,
                         name: str = "ground") -> int:
        """Add the ground: a plane through ``height`` [m] along the up axis, normal up."""
        height = checks.number("ground height", height, minimum=-np.inf, inclusive=True)
        return self.add_collider_plane(point=self.up_vector * height, friction=friction, restitution=restitution,
                                       name=name)

    def add_collider_sphere(self, *, center, radius: float, friction: float = 0.5, restitution: float = 0.0,
                            translation: Track | None = None, rotation: Track | None = None,
                            name="sphere", static_friction: float | None = None, thickness: float = 0.0) -> int:
        """Add a sphere of ``radius`` [m] at ``center`` [m] (other arguments as :meth:`add_collider_box`)."""
        size = (checks.positive("sphere radius", radius), 0.0, 0.0)
        return self._add_shape(SHAPE_SPHERE, checks.vector("sphere center", center), (0.0, 0.0, 0.0, 1.0), size,
                               friction, restitution, translation, rotation, name, static_friction=static_friction,
                               thickness=thickness)

    def add_collider_box(self, *, center, half_extents, orientation=(0.0, 0.0, 0.0, 1.0), friction: float = 0.5,
                         restitution: float = 0.0, translation: Track | None = None,
                         rotation: Track | None = None, name="box", static_friction: float | None = None,
                         thickness: float = 0.0) -> int:
        """Add a box collider.

        Args:
            center: the box's centre [m] at rest (time 0 without tracks).
            half_extents: half the box's size along its own x, y, z axes [m], each > 0.
            orientation: the box's rest orientation, a quaternion (x, y, z, w).
            friction: Coulomb coefficient μ [-], ≥ 0, against the moving surface.
            restitution: coefficient of restitution e [-] in [0, 1] (applies to impacts faster than two steps of
                gravity, so that a resting particle does not hop).
            translation: :class:`Track` of T(t) [m], 3-vectors added to ``center``.
            rotation: :class:`Track` of the rotation vector φ(t) [rad] (axis × angle, see
                :meth:`Track.rotation`) turning the box about its centre: orientation R(φ(t)) · rest.
            name: prim name for export.
            static_friction: Coulomb μ_s [-] ≥ ``friction`` (then the kinetic μ_k): a contact sticks while its
                tangential speed change stays within μ_s times the normal one; default μ_k.
            thickness: a shell around the surface [m], ≥ 0: particles stay radius + thickness from it.

        Returns:
            The collider's index. With a track the collider moves; particles touching it take its surface
            velocity (friction acts relative to it), and it is exported with time-sampled transforms.
        """
        half = checks.vector("box half_extents", half_extents)
        if not (half > 0.0).all():
            raise ConfigError(f"box half_extents must all be > 0 [m], got {tuple(half)}")
        return self._add_shape(SHAPE_BOX, checks.vector("box center", center), _quaternion(orientation),
                               tuple(half), friction, restitution, translation, rotation, name,
                               static_friction=static_friction, thickness=thickness)

    def add_collider_capsule(self, *, center, radius: float, half_height: float,
                             orientation=(0.0, 0.0, 0.0, 1.0), friction: float = 0.5, restitution: float = 0.0,
                             translation: Track | None = None, rotation: Track | None = None,
                             name="capsule", static_friction: float | None = None, thickness: float = 0.0) -> int:
        """Add a capsule: the points within ``radius`` [m] of the segment from -``half_height`` to
        +``half_height`` [m] along its own z axis (USD's ``Capsule`` with axis "Z" and height 2 ·
        half_height). Other arguments as :meth:`add_collider_box`."""
        size = (checks.positive("capsule radius", radius), checks.non_negative("capsule half_height", half_height),
                0.0)
        return self._add_shape(SHAPE_CAPSULE, checks.vector("capsule center", center), _quaternion(orientation),
                               size, friction, restitution, translation, rotation, name,
                               static_friction=static_friction, thickness=thickness)

    def add_collider_mesh(self, mesh, *, faces=None, prim: str | None = None, center=(0.0, 0.0, 0.0),
                          orientation=(0.0, 0.0, 0.0, 1.0), scale=1.0, sides: str = "closed", thickness: float = 0.0,
                          friction: float = 0.5, static_friction: float | None = None, restitution: float = 0.0,
                          deforming: bool = False, depth: float | None = None, winding_number: bool = False,
                          translation: Track | None = None, rotation: Track | None = None, name: str = "mesh",
                          cache_candidates: int = 32, cache_margin: float | None = None) -> int:
        """Add a triangle-mesh collider (``core/mesh_colliders.py``).

        Args:
            mesh: a file (any format trimesh reads, or ``.usd``/``.usda``/``.usdc``: see
                :func:`~warpspring.io.usd_mesh.read_usd_mesh`, whose time-sampled points make the collider
                deform), a ``trimesh.Trimesh``, or vertices [m], shape [v, 3] (then ``faces`` is required).
                Its coordinates are the collider's own frame.
            faces: vertex indices of each triangle, shape [t, 3], counter-clockwise seen from outside.
            prim: the USD mesh prim to read (a file of one mesh needs none).
            center: where the collider's frame origin is at rest [m]; orientation: its rest orientation,
                a quaternion (x, y, z, w); scale: a factor [-] (or one per axis) on the vertices.
            sides: "closed" (a watertight solid: inside by the pseudo-normals of its closest features, or with
                ``winding_number=True`` by its winding number: robust to holes, ~5× the cost), "one_sided" (an
                open mesh whose outside is where its normals point) or "two_sided" (an open shell, kept apart on
                both sides).
            depth: how far from its surface the mesh is looked for [m] (one-sided: up to this deep behind it,
                beyond its border edges too, is inside; a point deep inside a closed mesh looks as far as it
                must); default a tenth of its bounding box's diagonal; more than the particles' radius plus the
                thickness. A closest-point query costs with it.
            thickness: a shell around the surface [m], ≥ 0: particles stay radius + thickness from it.
            friction: kinetic Coulomb coefficient μ_k [-]; static_friction: μ_s ≥ μ_k [-], default μ_k.
            restitution: coefficient of restitution e [-] in [0, 1] (see :meth:`add_collider_box`).
            deforming: its points may change between frames (``model.mesh_collider(name).set_points``);
                implied by time-sampled USD points.
            translation, rotation: keyframe tracks moving its frame (see :meth:`add_collider_box`).
            name: prim name for export.
            cache_candidates, cache_margin: each particle's candidate cache (at most this many triangles; a full
                query only after it moved more than the margin [m]; see ``core/mesh_colliders.py``).

        Returns:
            The collider's index.
        """
        from .mesh_colliders import mesh_shape

        samples = None
        if isinstance(mesh, (str, os.PathLike)):
            path = os.fspath(mesh)
            if path.lower().endswith((".usd", ".usda", ".usdc")):
                from ..io.usd_mesh import read_usd_mesh, read_usd_mesh_samples

                read = read_usd_mesh(path, prim=prim, up_axis=self.up_axis)
                vertices, faces = read.vertices, read.triangles
                samples = read_usd_mesh_samples(path, prim=read.prim, up_axis=self.up_axis)
            else:
                loaded = load_mesh_file(path, what="mesh collider")
                vertices, faces = np.asarray(loaded.vertices), np.asarray(loaded.faces)
        elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
            vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        else:
            if faces is None:
                raise ConfigError("add_collider_mesh: vertices need faces=[t, 3] (or pass a file or a trimesh.Trimesh)")
            vertices = mesh
        factor = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
        if not (np.isfinite(factor).all() and (factor > 0.0).all()):
            raise ConfigError(f"mesh collider scale must be > 0 (a number or one per axis), got {scale!r}")
        vertices = np.asarray(vertices, dtype=np.float64)
        times, points = (None, None) if samples is None else samples
        info = mesh_shape(vertices * factor if vertices.ndim == 2 else vertices, faces, sides=sides,
                          deforming=deforming, sample_times=times, depth=depth, winding_number=winding_number,
                          sample_points=None if points is None else points * factor,
                          cache_candidates=cache_candidates, cache_margin=cache_margin)
        return self._add_shape(SHAPE_MESH, checks.vector("mesh center", center), _quaternion(orientation),
                               (0.0, 0.0, 0.0), friction, restitution, translation, rotation, name,
                               static_friction=static_friction, thickness=thickness, mesh=info)

    def world_rows(self) -> dict[str, np.ndarray]:
        """The per-world parameters this builder gives one world, as ``Model.set_world_values`` takes them
        (float64, in the order ``finalize`` stores them): ``spring_stiffness`` [N/m] and ``spring_damping``
        [N·s/m], shape [spring_count]; ``particle_mass`` [kg], shape [particle_count]. A sweep builds each
        variant's builder on the host and gives its rows to one world of a shared model."""
        def joined(blocks):
            return np.concatenate(blocks).astype(np.float64) if blocks else np.zeros(0)

        return {"spring_stiffness": joined(self._spring_ke), "spring_damping": joined(self._spring_kd),
                "particle_mass": joined(self._mass)}

    # -- finalize -------------------------------------------------------------------------------------

    def finalize(self, device=None, *, precision: str = "float32", spring_evaluation: str = "auto",
                 worlds: int = 1, contact_stage: bool | None = None, contact_slots: int | None = None,
                 integrator: str = "symplectic_euler", check_memory: bool = True, spring_groups: bool = True,
                 spring_grid: bool = True) -> Model:
        """Copy the scene to ``device`` as a :class:`Model`.

        Before it allocates anything, finalize estimates the memory of the model and of a run of it
        (:meth:`estimate_memory`) and refuses, with a :class:`~warpspring.ConfigError` naming the estimate, what is
        free and a remedy, a model that cannot fit: on a CUDA device its arrays against the device's free memory,
        and the host's peak (on the CPU, the arrays too) against the available host memory. A failed device
        allocation becomes the same error.

        Args:
            device: Warp device ("cpu", "cuda:0", ...); default Warp's default device.
            worlds: independent copies of the scene in the model, stepped together in every launch and never
                coupled (a batch of environments, a parameter sweep). Each starts as this builder's scene;
                give them their own parameters with :meth:`Model.set_world_values` and
                :meth:`Model.set_track`.
            precision: "float32" (default) or "float64" for every floating-point array and kernel.
            spring_evaluation: "gather" (per particle, no atomics, fusable, any number of springs per particle),
                "scatter" (per spring, each evaluated once, atomic adds: deterministic only on the CPU) or
                "auto": gather on CUDA, scatter on the CPU (the faster choice on each).
            contact_stage: resolve contacts through the contact stage (``collide`` fills a per-particle contact
                buffer, the response reads it) instead of testing every collider in the update (the fused path).
                Default: the stage when a collider moves, the fused path for static ones.
            contact_slots: contacts a particle can hold in the stage's buffer [1, 64]; default min(colliders, 4).
                More contacts at one particle are dropped, counted and reported (``Contacts.overflow``, the
                guard, the run summary).
            integrator: the name of the integrator the model will be stepped with; only the memory check uses it
                (its scratch states count in the estimate). The default, symplectic Euler, needs the least.
            check_memory: refuse a model whose estimate does not fit (default); ``False`` skips the check.
            spring_groups: with gathered springs, read each spring group's rest length, ke and kd once per
                group where every spring of the group has the same ones (``Model.spring_slot_groups``), instead
                of once per spring; ``False`` reads them per spring.
            spring_grid: with ``spring_groups``, where the scene is one :meth:`add_cloth_grid` and nothing else
                (its particles in grid order), find a uniform group's neighbours from the particle's row and
                column instead of the incidence table (``Model.spring_layout`` "grid"; the same bits, fewer bytes
                per step); ``False`` keeps the table ("groups").

        Raises:
            ConfigError: a bad option, a scene beyond the kernels' 32-bit indices, or a model that does not fit in
                memory.
        """
        if spring_evaluation not in ("auto", "gather", "scatter"):
            raise ConfigError(f"spring_evaluation must be 'auto', 'gather' or 'scatter', got {spring_evaluation!r}")
        if self._particle_count == 0:
            raise ConfigError("the scene has no particles: add a cloth, a mesh or particles first")
        try:
            scalar = scalar_type(precision)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        device = wp.get_device(device)
        worlds = checks.count("worlds", worlds, minimum=1)
        n = self._particle_count
        spring_total = sum(len(k) for k in self._springs)
        if max(n * worlds, 2 * spring_total) >= 2**31:
            raise ConfigError(
                f"{worlds} world(s) of {n} particles and {spring_total} springs exceed the 32-bit indices of the "
                "kernels (at most 2^31 - 1 particles in all worlds and 2^30 springs): use fewer worlds per model"
            )
        estimate = self.estimate_memory(device, precision=precision, worlds=worlds, integrator=integrator,
                                        contact_stage=contact_stage, contact_slots=contact_slots)
        if check_memory:
            memory.check_fits(estimate, memory.available_memory(device), precision=precision)
        try:
            return self._finalize(device, precision, scalar, worlds, spring_evaluation, contact_stage, contact_slots,
                                  spring_groups=spring_groups, spring_grid=spring_grid)
        except (RuntimeError, MemoryError) as exc:
            if not memory.out_of_memory(exc):
                raise
            raise ConfigError(
                f"out of memory while finalizing the model on {device} ({exc}); the estimate was "
                f"{estimate.describe()}. " + memory.remedy(estimate, 1.25, precision=precision)
            ) from None

    def estimate_memory(self, device=None, *, precision: str = "float32", worlds: int = 1,
                        integrator: str = "symplectic_euler", contact_stage: bool | None = None,
                        contact_slots: int | None = None) -> memory.MemoryEstimate:
        """Estimate the memory :meth:`finalize` and a run of the model will need, before anything is allocated
        (:func:`warpspring.core.memory.estimate_memory` with this builder's counts and its incidence tables'
        exact widths).

        Args:
            device: the Warp device the model will live on (default: Warp's default).
            precision, worlds, contact_stage, contact_slots: as :meth:`finalize`.
            integrator: the integrator's name (its scratch states count).

        Returns:
            The :class:`~warpspring.core.memory.MemoryEstimate`.
        """
        device = wp.get_device(device)
        n = self._particle_count
        spring_degree = np.zeros(n, dtype=np.int64)
        for block in self._springs:  # per block: no concatenated copy of every spring
            spring_degree += np.bincount(block.ravel(), minlength=n)
        hinge_degree = np.zeros(n, dtype=np.int64)
        for block in self._hinges:
            hinge_degree += np.bincount(block.ravel(), minlength=n)
        spring_slots, hinge_slots = head_slots(spring_degree), head_slots(hinge_degree)
        moving = any(s.translation_track is not None or s.rotation_track is not None for s in self._shapes)
        stage = bool(self._shapes) and (moving if contact_stage is None else bool(contact_stage))
        slots = max(1, min(len(self._shapes), 4)) if contact_slots is None else contact_slots
        pinned = sum(len(g.particles) for g in self._pin_groups)
        if pinned:  # the table holds every kinematic particle once there are groups
            mask = np.concatenate(self._pinned)
            for extra in self._extra_pins:
                mask[extra] = True
            pinned = int(mask.sum())
        cached = [s for s in self._shapes if getattr(s, "mesh", None) is not None and not s.mesh.winding_number]
        return memory.estimate_memory(
            particles=n,
            springs=self._spring_count,
            hinges=self._hinge_count,
            triangles=sum(len(g.faces) for g in self._meshes),
            colliders=len(self._shapes),
            worlds=worlds,
            precision=precision,
            device=str(device),
            integrator=integrator,
            spring_slots=spring_slots,
            spring_tail=int(np.maximum(spring_degree - spring_slots, 0).sum()),
            hinge_slots=hinge_slots,
            hinge_tail=int(np.maximum(hinge_degree - hinge_slots, 0).sum()),
            pinned=pinned,
            mesh_vertices=sum(len(g.particles) for g in self._meshes),
            strain_limiting=self.stabilizers.max_strain is not None,
            contact_slots=slots if stage else 0,
            moving_colliders=moving,
            block_dim=_block_dim(device, n * worlds),
            family_bytes=sum(f.device_bytes(n, 8 if precision == "float64" else 4, worlds) for f in self._families)
            + sum(e.device_bytes(worlds) for e in self._emitters),
            cached_meshes=len(cached),
            mesh_faces=sum(len(s.mesh.faces) for s in cached),
            mesh_candidates=max([s.mesh.cache_candidates for s in cached], default=1),
            mesh_bytes=_mesh_collider_bytes([s.mesh for s in self._shapes if getattr(s, "mesh", None) is not None]),
        )

    def _finalize(self, device, precision: str, scalar, worlds: int, spring_evaluation: str,
                  contact_stage: bool | None, contact_slots: int | None, *, spring_groups: bool = True,
                  spring_grid: bool = True) -> Model:
        """The model's arrays on ``device`` (the arguments checked by :meth:`finalize`)."""
        vec3 = vec3_type(scalar)
        float_np = np.float64 if scalar is wp.float64 else np.float32
        model = Model(device, precision, scalar, world_count=worlds)
        model.up_axis = self.up_axis
        model.gravity = self.gravity
        model.drag = float(self.drag)
        for name, value in self._air.items():
            model.set_world_values(name, value)
        model.stabilizers = self.stabilizers
        n = self._particle_count

        mass = np.concatenate(self._mass)
        pinned = np.concatenate(self._pinned)
        for extra in self._extra_pins:
            pinned[extra] = True

        def farray(values, dtype=None, *, name="a shape parameter"):
            with np.errstate(over="ignore"):
                cast = np.asarray(values, dtype=float_np)
            if not np.isfinite(cast).all():
                raise ConfigError(
                    f"{name} overflows {precision} (largest magnitude {np.max(np.abs(values)):.3g}): "
                    "rescale the scene to SI units of sensible size or finalize with precision='float64'"
                )
            return wp.array(cast, dtype=dtype or scalar, device=device)

        def iarray(values, dtype=wp.int32):
            return wp.array(np.ascontiguousarray(values, dtype=np.int32), dtype=dtype, device=device)

        def every_world(values):  # one world's per-particle values, repeated for every world (world-major)
            return np.tile(values, (worlds,) + (1,) * (np.ndim(values) - 1))

        model.particle_count = n
        model.block_dim = _block_dim(device, n * worlds)
        model.particle_q = farray(every_world(np.concatenate(self._q)), vec3, name="a particle position [m]")
        model.particle_qd = farray(every_world(np.concatenate(self._qd)), vec3, name="a particle velocity [m/s]")
        model.particle_mass = farray(mass[None, :], name="a particle mass [kg]")
        model.particle_inv_mass = farray(1.0 / mass[None, :], name="an inverse particle mass [1/kg]")
        model.particle_radius = farray(np.concatenate(self._radius), name="a particle radius [m]")
        model.particle_flags = iarray(every_world(np.where(pinned, PARTICLE_KINEMATIC, 0)))
        # Tracks: the colliders' and pin groups' first (their indices stay put), then the animated inputs.
        model._shape_tracks = [t for shape in self._shapes for t in (shape.translation_track, shape.rotation_track)
                               if t is not None]
        model._pin_tracks = [t for g in self._pin_groups for t in (g.translation, g.rotation) if t is not None]
        model._family_tracks = [t for family in self._families for t in family.tracks()]
        model._rebuild_tracks()
        if self._pin_groups:
            model.pin_groups = PinGroupTable(
                np.flatnonzero(pinned), self._pin_groups, np.concatenate(self._q), model.track_table.index, device
            )
        for name, track in self._tracks.items():
            model.set_track(name, track)

        springs = np.concatenate(self._springs) if self._springs else np.zeros((0, 2), dtype=np.int64)
        s = len(springs)
        model.spring_count = s
        model.spring_indices = iarray(springs, wp.vec2i)
        names = np.repeat(np.array(self._spring_family, dtype=object), [len(b) for b in self._springs])
        model.spring_families = {name: np.flatnonzero(names == name) for name in dict.fromkeys(self._spring_family)}
        model.spring_rest_length = farray(np.concatenate(self._spring_rest) if s else [], name="a spring rest length [m]")
        model.spring_stiffness = farray(np.concatenate(self._spring_ke)[None, :] if s else np.zeros((1, 0)),
                                        name="a spring stiffness [N/m]")
        model.spring_damping = farray(np.concatenate(self._spring_kd)[None, :] if s else np.zeros((1, 0)),
                                      name="a spring damping [N·s/m]")
        degree = np.bincount(springs.ravel(), minlength=n) if s else np.zeros(n, dtype=np.int64)
        model.spring_max_degree = int(degree.max())
        if spring_evaluation == "auto":
            spring_evaluation = "gather" if device.is_cuda else "scatter"  # the faster choice on each
        model.spring_gather = spring_evaluation == "gather"
        # The incidence also serves the stiffness products of implicit integration and stability analysis.
        model.spring_incidence, model.spring_incidence_shape = build_incidence(
            springs, n, springs[:, ::-1], lambda particles: particles, device=device
        )
        self._finalize_spring_laws(model, farray, iarray)
        model._spring_grouping = spring_groups
        # The grid layout: one cloth grid holding every particle, in grid order (its first particle is 0).
        grids = self._cloth_grids
        if len(grids) == 1 and grids[0][0] == 0 and grids[0][1] * grids[0][2] == n:
            model.spring_grid_shape = grids[0][1:]
        model._spring_grid = bool(spring_grid)
        set_spring_layout(model, spring_groups)

        hinges = np.concatenate(self._hinges) if self._hinges else np.zeros((0, 4), dtype=np.int64)
        model.hinge_count = len(hinges)
        model.hinge_indices = iarray(hinges, wp.vec4i)
        model.hinge_rest_angle = farray(np.concatenate(self._hinge_rest) if len(hinges) else [])
        model.hinge_stiffness = farray(np.concatenate(self._hinge_ke)[None, :] if len(hinges) else np.zeros((1, 0)),
                                       name="a hinge stiffness [N·m/rad]")
        model.hinge_damping = farray(np.concatenate(self._hinge_kd)[None, :] if len(hinges) else np.zeros((1, 0)),
                                     name="a hinge damping [N·m·s/rad]")
        model.hinge_incidence, model.hinge_incidence_shape = build_incidence(
            hinges, n, np.broadcast_to(np.arange(4), hinges.shape), -1, device=device
        )

        tris = [g.particles[g.faces] for g in self._meshes]
        tri_indices = np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)
        model.tri_count = len(tri_indices)
        model.tri_indices = wp.array(tri_indices.astype(np.int32), dtype=wp.int32, device=device)
        model.meshes = list(self._meshes)
        model.skins = list(self._skins)

        model.shapes = list(self._shapes)
        model._finalize_shapes(
            size=farray(np.array([shape.size for shape in self._shapes]).reshape(-1, 3), vec3,
                        name="a collider size [m]"),
            stage=contact_stage,
            slots=contact_slots,
        )
        for family in self._families:
            family.finalize(model)
        model.extra_families = tuple(self._families)
        for emitter in self._emitters:
            emitter.finalize(model)
        model.emitters = list(self._emitters)
        if self._self_collision is not None:
            chosen = self._self_collision["meshes"]
            groups = [g for g in self._meshes if chosen is None or g.name in chosen]
            surface = np.concatenate([g.particles[g.faces] for g in groups]) if groups else np.zeros((0, 3), np.int64)
            model.self_contact = make_self_contact(model, surface, np.concatenate(self._q), self._self_collision)
        model._finalized = True
        return model

    # -- helpers --------------------------------------------------------------------------------------

    def _check_grid_room(self, nx: int, ny: int, *, structural, shear, bend, hinges: bool, material: bool) -> None:
        """Refuse, before any array is made, a grid whose builder arrays (and the temporaries of making them)
        exceed the host memory available (``memory.available_memory``): a ConfigError with the estimate and a
        smaller grid that fits. ``finalize`` checks the whole model later."""
        n = nx * ny
        structural_count = ny * (nx - 1) + (ny - 1) * nx
        shear_count = 2 * (nx - 1) * (ny - 1)
        bend_count = ny * max(nx - 2, 0) + max(ny - 2, 0) * nx
        if material:
            springs = structural_count + shear_count
        else:
            springs = sum(c for family, c in ((structural, structural_count), (shear, shear_count), (bend, bend_count))
                          if family is not None)
        triangles = 2 * (nx - 1) * (ny - 1)
        edges = structural_count + (nx - 1) * (ny - 1)
        interior = edges - 2 * (nx - 1) - 2 * (ny - 1)
        estimate = memory.estimate_memory(particles=n, springs=springs, hinges=interior if hinges else 0,
                                          triangles=triangles)
        # Making the grid holds each family's pairs twice (built, then checked as int64) and its rest-length
        # differences (float64) beside the arrays it keeps; ~70 bytes per spring, measured.
        needed = estimate.builder + GRID_TEMPORARY_PER_SPRING * springs + GRID_TEMPORARY_PER_PARTICLE * n
        available = memory.available_memory(None).host  # the host's (Warp need not be initialised yet)
        if available is not None and needed > available:
            share = available / (needed * 1.05)
            side = max(int(math.sqrt(share * n)), 2)
            raise ConfigError(
                f"a {nx} × {ny} cloth grid needs an estimated {memory.format_bytes(needed)} of host memory to build "
                f"({n:,} particles, {springs:,} springs), but {memory.format_bytes(available)} is available: use a "
                f"smaller grid (about {side} × {side} fits), and see warpspring.estimate_memory for the run's needs"
            )

    def _element_particles(self, value, arity: int, *, what: str, shape: str, noun: str, verb: str) -> np.ndarray:
        """The particles of each element, int64 [k, arity], checked to be integers of existing particles;
        ``what``, ``shape``, ``noun`` and ``verb`` word the errors ("spring 3 joins particles ...")."""
        members = np.asarray(value)
        if members.ndim != 2 or members.shape[1] != arity:
            raise ConfigError(f"{what} must have shape {shape}, got {members.shape}")
        if len(members) and not np.issubdtype(members.dtype, np.integer):
            raise ConfigError(f"{what} must be integer particle indices")
        members = members.astype(np.int64)
        if len(members) and (members.min() < 0 or members.max() >= self._particle_count):
            bad = int(np.flatnonzero((members < 0).any(1) | (members >= self._particle_count).any(1))[0])
            raise ConfigError(f"{noun} {bad} {verb} particles {tuple(members[bad])}, but only "
                              f"{self._particle_count} particles exist: add the particles first")
        return members

    def _add_mesh_hinges(self, vertices: np.ndarray, faces: np.ndarray, ids: np.ndarray,
                         material: DihedralMaterial | ClothMaterial, *, rest: str = "mesh") -> None:
        """Hinges on every interior edge of a mesh (local ``faces`` into ``vertices`` [m], particles ``ids``).

        A :class:`DihedralMaterial` gives every hinge its ke, kd and rest rule; a :class:`ClothMaterial`
        gives each hinge its own k_θ [N·m/rad] and kd_θ [N·m·s/rad] from its rest geometry
        (:func:`~warpspring.core.material.hinge_parameters`), with rest angles by ``rest``: "mesh" (as
        given) or "flat" (0).
        """
        if not isinstance(material, (DihedralMaterial, ClothMaterial)):
            raise ConfigError(f"dihedral must be a warpspring.DihedralMaterial, got {type(material).__name__}")
        try:
            hinges, mesh_rest = mesh_hinges(vertices, faces)
        except ValueError as exc:
            raise ConfigError(f"cannot add dihedral springs: {exc}") from None
        if isinstance(material, ClothMaterial):
            stiffness, damping = hinge_parameters(material, vertices, hinges)
        else:
            stiffness, damping, rest = material.ke, material.kd, material.rest
        self.add_hinges(ids[hinges], stiffness=stiffness, damping=damping,
                        rest_angle=mesh_rest if rest == "mesh" else 0.0)

    def _add_shape(self, kind, position, orientation, size, friction, restitution, translation, rotation, name, *,
                   static_friction=None, thickness=0.0, mesh=None):
        friction = checks.non_negative("friction", friction)
        thickness = checks.non_negative("collider thickness", thickness)
        if static_friction is not None:
            static_friction = checks.non_negative("static_friction", static_friction)
            if static_friction < friction:
                raise ConfigError(f"static_friction ({static_friction}) must be at least the kinetic friction "
                                  f"({friction}): a contact slides above μ_s and then feels μ_k ≤ μ_s")
        restitution = checks.number("restitution", restitution, minimum=0.0)
        if restitution > 1.0:
            raise ConfigError(f"restitution must be in [0, 1] (the share of the normal speed an impact keeps), "
                              f"got {restitution}")
        translation = None if translation is None else as_track("a collider's translation", translation, 3)
        rotation = None if rotation is None else as_track("a collider's rotation", rotation, 3)
        self._shapes.append(ShapeInfo(
            kind=SHAPE_NAMES[kind],
            name=self._unique_name(name, [s.name for s in self._shapes]),
            position=tuple(float(x) for x in position),
            rotation=tuple(float(x) for x in orientation),
            size=tuple(float(x) for x in size),
            friction=friction,
            restitution=restitution,
            translation_track=translation,
            rotation_track=rotation,
            thickness=thickness,
            static_friction=static_friction,
            mesh=mesh,
        ))
        return len(self._shapes) - 1

    @staticmethod
    def _place(local: np.ndarray, origin, rotation) -> np.ndarray:
        R = quat_to_matrix(_quaternion(rotation))
        return local @ R.T + checks.vector("origin", origin)

    @staticmethod
    def _grid_pins(pin, nx: int, ny: int) -> np.ndarray:
        if isinstance(pin, (str, int, np.integer)):
            pin = [pin]
        mask = np.zeros((ny, nx), dtype=bool)
        for p in pin:
            if isinstance(p, str):
                key = p.strip().lower()
                if key not in _GRID_PINS:
                    raise ConfigError(f"unknown pin {p!r}: use one of {', '.join(_GRID_PINS)} or particle indices")
                top, right = "top" in key, "right" in key
                if "-" in key:
                    mask[ny - 1 if top else 0, nx - 1 if right else 0] = True
                elif key in ("top", "bottom"):
                    mask[ny - 1 if top else 0, :] = True
                else:
                    mask[:, nx - 1 if right else 0] = True
            else:
                mask.flat[_indices("pin", [p], nx * ny)] = True
        return mask.ravel()

    @staticmethod
    def _unique_name(name: str, taken: list[str]) -> str:
        base = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "mesh"
        if base[0].isdigit():
            base = "_" + base
        candidate, k = base, 1
        while candidate in taken:
            candidate, k = f"{base}_{k}", k + 1
        return candidate


# -- validation helpers (each raises ConfigError naming the quantity) -------------------------------------


def _quaternion(value) -> np.ndarray:
    q = np.asarray(value, dtype=np.float64)
    if q.shape != (4,) or not np.isfinite(q).all() or np.linalg.norm(q) == 0.0:
        raise ConfigError(f"rotation must be a nonzero quaternion (x, y, z, w), got {value!r}")
    return q / np.linalg.norm(q)


def load_mesh_file(path, *, what: str = "mesh"):
    """The ``trimesh.Trimesh`` in the file at ``path`` (any format trimesh reads, unprocessed: vertices in the
    file's order), or a one-line ConfigError naming the file."""
    import trimesh

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ConfigError(f"{what} file not found: {path}")
    try:
        return trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ConfigError(f"cannot read {what} file {path}: {exc}") from None


def _weld_seams(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None):
    """Merge vertices at identical positions, keeping the order of their first appearance; with a
    merge, UVs move to the triangle corners, shape [t, 3, 2]."""
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    if len(first) == len(vertices):
        return vertices, faces, uv
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    corner_uv = None if uv is None else uv[faces]
    return vertices[first[order]], rank[inverse.reshape(-1)][faces], corner_uv


def _points(name: str, value, count: int | None = None) -> np.ndarray:
    p = np.asarray(value, dtype=np.float64)
    if count is not None and p.shape == (3,):
        p = np.broadcast_to(p, (count, 3))
    if p.ndim != 2 or p.shape[1] != 3 or (count is not None and len(p) != count):
        want = f"[{count}, 3]" if count is not None else "[n, 3]"
        raise ConfigError(f"{name} must have shape {want}, got {p.shape}")
    bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
    if len(bad):
        raise ConfigError(f"{name}: entry {int(bad[0])} is not finite ({p[bad[0]].tolist()}); fix the input data")
    return np.array(p)


def _per_item(name: str, value, n: int, *, positive: bool = False) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(n, float(v))
    if v.shape != (n,):
        raise ConfigError(f"{name} must be a number or an array of shape ({n},), got shape {v.shape}")
    bad = np.flatnonzero(~np.isfinite(v) | ((v <= 0.0) if positive else (v < 0.0)))
    if len(bad):
        need = "> 0" if positive else ">= 0"
        raise ConfigError(f"{name} must be finite and {need}, got {v[bad[0]]} (entry {int(bad[0])})")
    return v


def _indices(name: str, value, bound: int) -> np.ndarray:
    idx = np.asarray(value)
    if idx.size and not np.issubdtype(idx.dtype, np.integer):
        raise ConfigError(f"{name} indices must be integers, got {idx.dtype}")
    idx = idx.astype(np.int64).ravel()
    bad = idx[(idx < 0) | (idx >= bound)]
    if len(bad):
        raise ConfigError(f"{name} index {int(bad[0])} is out of range: valid indices are 0..{bound - 1}")
    return idx


def _mass_per_particle(mass, particle_mass, n: int) -> float:
    if (mass is None) == (particle_mass is None):
        raise ConfigError("give exactly one of mass= (total, kg) or particle_mass= (kg per particle), or material=")
    return checks.positive("mass", mass) / n if particle_mass is None else checks.positive("particle_mass", particle_mass)


def spring_family(name: str, value, default: SpringMaterial) -> SpringMaterial | None:
    """A cloth's spring family argument as the builder uses it, accepting what a scene file accepts.

    Args:
        name: the family's name ("structural", "shear", "bend"), for messages.
        value: a :class:`SpringMaterial`; a mapping with ``ke`` [N/m] and/or ``kd`` [N·s/m] (each missing one is
            ``default``'s, as in a scene file's table), and optionally the law's keys (:data:`SPRING_TABLE_KEYS`);
            ``True`` (``default``); ``False`` or ``None`` (no springs of the family).
        default: the family's default material.

    Returns:
        The material, or ``None`` for a family switched off.

    Raises:
        ConfigError: any other value, an unknown key, or a stiffness or damping that is not a finite number ≥ 0.
    """
    if value is None or value is False:
        return None
    if value is True:
        return default
    if isinstance(value, SpringMaterial):
        material = value
    elif isinstance(value, Mapping):
        unknown = sorted(map(str, set(value) - {"ke", "kd", *SPRING_TABLE_KEYS}))
        if unknown:
            raise ConfigError(f"{name} springs: unknown key {unknown[0]!r}: a mapping takes 'ke' [N/m], 'kd' "
                              f"[N·s/m] and {', '.join(map(repr, SPRING_TABLE_KEYS))}")
        material = SpringMaterial(ke=value.get("ke", default.ke), kd=value.get("kd", default.kd),
                                  **spring_law_options(name, value))
    else:
        raise ConfigError(f"{name} springs must be a warpspring.SpringMaterial, a mapping {{'ke': ..., 'kd': ...}}, "
                          f"True (the default) or False (none), got {value!r}")
    checks.non_negative(f"{name} spring ke", material.ke)
    checks.non_negative(f"{name} spring kd", material.kd)
    return material


#: The keys of a spring table (a scene's ``[cloth.structural]``, a ``spring_family`` mapping) that choose its law
#: and plasticity, beyond ``ke`` and ``kd``: ``law`` ("linear" or "square"), ``compression_ke``, and the fields
#: of :class:`~warpspring.core.springs.SpringPlasticity`.
SPRING_TABLE_KEYS = ("law", "compression_ke", "yield_strain", "yield_force", "yield_rate", "hardening", "break_strain")


def spring_law_options(name: str, table: Mapping) -> dict:
    """The ``law``, ``compression_ke`` and ``plasticity`` of :class:`SpringMaterial` from a spring table's keys
    (:data:`SPRING_TABLE_KEYS`; absent ones keep their defaults), checked, with one-line errors naming ``name``."""
    options = {}
    if "law" in table:
        if not isinstance(table["law"], str):
            raise ConfigError(f"{name} springs: law must be a string, one of {', '.join(map(repr, SPRING_LAWS))}")
        spring_law_code(table["law"])
        options["law"] = table["law"]
    if "compression_ke" in table:
        options["compression_ke"] = checks.non_negative(f"{name} spring compression_ke", table["compression_ke"])
    plastic = {key: table[key] for key in SPRING_TABLE_KEYS[2:] if key in table}
    if plastic:
        try:
            options["plasticity"] = SpringPlasticity(**plastic)
        except ConfigError as exc:
            raise ConfigError(f"{name} springs: {exc}") from None
    return options


def _material_decides(material, method: str, **given: bool) -> None:
    """Check ``material`` is a ClothMaterial and that none of the arguments it decides was ``given``."""
    if not isinstance(material, ClothMaterial):
        raise ConfigError(f"material must be a warpspring.ClothMaterial, got {type(material).__name__}")
    clash = [name for name, value in given.items() if value]
    if clash:
        raise ConfigError(
            f"{method}: material= decides the masses, springs and hinges, so {', '.join(clash)} must not be "
            "given with it (drop them, or drop material= to set them yourself)"
        )


def _block_dim(device, n: int) -> int:
    """Threads per block for per-particle kernels: 256, or fewer for small models so that the blocks
    spread over all multiprocessors (a 4096-particle cloth in 16 blocks would use 16 of 132 SMs)."""
    if not device.is_cuda:
        return 256
    per_sm = n // max(device.sm_count, 1)
    return int(min(256, max(32, 1 << max(per_sm, 1).bit_length() - 1)))


def _elasticity(elasticity, poisson_ratio, *, method: str, volume, bulk_modulus, plasticity, source: str) -> bool:
    """Check a soft body's ``elasticity=`` and ``poisson_ratio=`` before its topology is built (one-line
    ConfigErrors); whether the neo-Hookean tets carry it."""
    from .neohookean import ELASTICITIES, poisson

    if elasticity not in ELASTICITIES:
        raise ConfigError(f"{source}: elasticity must be one of {', '.join(ELASTICITIES)}, got {elasticity!r}")
    nu = poisson(poisson_ratio, source)
    if elasticity == "springs":
        if nu != 0.25:
            raise ConfigError(f"{source}: poisson_ratio={poisson_ratio!r} is the neo-Hookean material's (a spring "
                              "network is fixed at 0.25): give elasticity='neohookean' with it")
        return False
    from .softbody import METHODS

    if method in METHODS and method not in ("tetrahedral", "delaunay"):  # an unknown method: build_topology names it
        raise ConfigError(f"{source}: elasticity='neohookean' needs tets, which the {method} method does not make: use "
                          "method='tetrahedral' or 'delaunay'")
    if volume or bulk_modulus is not None:
        raise ConfigError(f"{source}: the neo-Hookean tets already carry the bulk stiffness (λ of E and ν): drop "
                          "volume=/bulk_modulus=")
    if plasticity is not None:
        raise ConfigError(f"{source}: plasticity= acts on springs, and a neo-Hookean body has none")
    return True
