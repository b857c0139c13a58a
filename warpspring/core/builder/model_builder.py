"""ModelBuilder: the scene's particles, springs, dihedral hinges, element families, PD handles, emitters, wind,
self-collision, pin groups and keyframe tracks, collected in bulk on the host; composed with the cloth, soft-body
and collider recipes and with finalize (the sibling modules of this package)."""

from __future__ import annotations

import os
import re

import numpy as np

from ... import checks
from .. import memory
from ...errors import ConfigError
from ..aero import AIR_DENSITY, DEFAULT_DRAG, DEFAULT_LIFT, AeroFamily
from ..emitters import Emitter, make_emitter
from ..families import ElementFamily
from ..handles import HandleFamily, make_handle
from ..hinges import dihedral_angle
from ..kinematics import PinGroup
from ..mesh_files import load_mesh_file
from ..records import MeshGroup, ShapeInfo, SkinGroup, Stabilizers
from ..selfcontact import DEFAULT_RELAXATION, check_settings
from ..springs import SpringPlasticity, spring_law_code
from ..tracks import Track, as_track, input_track
from ..transforms import quat_to_matrix
from .arguments import RESERVED_PRIM_NAMES, _indices, _per_item, _points, _quaternion
from .cloth import ClothRecipes
from .colliders import ColliderRecipes
from .finalize import Finalization
from .soft_body import SoftBodyRecipes

#: Host bytes per pool particle that adding an emitter's pool holds beyond the builder's arrays (its pin mask
#: and the broadcast centre's checks).
EMITTER_POOL_TEMPORARY = 8

_AXES = {"Y": 1, "Z": 2}  # USD knows only Y-up and Z-up stages


class ModelBuilder(ClothRecipes, SoftBodyRecipes, ColliderRecipes, Finalization):
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

    def _check_room(self, what: str, *, particles: int, springs: int = 0, hinges: int = 0, triangles: int = 0,
                    temporary: int = 0, remedy: str) -> None:
        """Refuse, before any of its arrays is made, an addition whose host memory exceeds what is available: the
        builder's arrays with it, plus the larger of its own temporaries (``temporary`` [B]) and the host copies
        :meth:`finalize` makes of the whole scene (``memory.estimate_memory``'s ``finalize_host``, whatever the
        device). :meth:`finalize` checks the model's arrays on its device later."""
        estimate = memory.estimate_memory(
            particles=self._particle_count + particles, springs=self._spring_count + springs,
            hinges=self._hinge_count + hinges, triangles=sum(len(g.faces) for g in self._meshes) + triangles)
        memory.check_host_room(what, estimate.builder + max(int(temporary), estimate.finalize_host), remedy=remedy)

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
        # The pool: kinematic (dead) and still until born, at the emitter's centre; checked before it is made.
        self._check_room(f"emitter {name!r}: a pool of {emitter.capacity:,} particles", particles=emitter.capacity,
                         temporary=EMITTER_POOL_TEMPORARY * emitter.capacity,
                         remedy=f"lower its rate × life ({emitter.rate:g}/s × {emitter.life:g} s) or give a smaller "
                                "capacity= (the oldest particles are then recycled early)")
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

    # -- helpers --------------------------------------------------------------------------------------

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

    @staticmethod
    def _place(local: np.ndarray, origin, rotation) -> np.ndarray:
        R = quat_to_matrix(_quaternion(rotation))
        return local @ R.T + checks.vector("origin", origin)

    @staticmethod
    def _unique_name(name: str, taken: list[str]) -> str:
        base = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "mesh"
        if base[0].isdigit():
            base = "_" + base
        candidate, k = base, 1
        while candidate in taken:
            candidate, k = f"{base}_{k}", k + 1
        return candidate
