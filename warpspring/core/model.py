"""Model: the static arrays of a scene and its live inputs (gravity, drag, stabilisers, per-world values)."""

from __future__ import annotations


import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.families import elements as composed_elements
from ..kernels.families import fill_elements
from ..kernels.forces import ForceFeatures
from ..kernels.spring_laws import SpringLaw
from ..kernels.families import Incidence, IncidenceShape
from ..kernels.shapes import NO_CONTACTS, ContactFeatures, shapes_type
from ..kernels.mesh_colliders import MESH_SIDES, MESH_WINDING
from ..kernels.swept import SWEPT_KINDS
from ..kernels.inputs import INPUT_COUNT, INPUTS
from ..kernels.tracks import WorldInputs
from ..kernels.kinematics import PARTICLE_KINEMATIC
from ..kernels.precision import transform_type, vec3_type
from .kinematics import PinGroupTable, apply_kinematics
from .mesh_colliders import make_mesh_colliders
from .bending import HingeFamily
from .springs import SpringFamily, set_spring_layout
from .tracks import Track, TrackTable, as_track, input_track

from .records import INPUT_BOUNDS, MAX_CONTACT_SLOTS, SHAPE_KINDS, STABILIZER_INPUTS, InputTracks, Stabilizers
from .state import State
from .control import Control
from .kinematics import pin_group_index


class Model:
    """Static description of a scene on one device, produced by :meth:`ModelBuilder.finalize`, and its live
    inputs.

    Arrays are Warp arrays on :attr:`device` in the model's precision (:attr:`scalar`); the layout is
    documented per attribute as [unit], shape.

    Worlds: a model holds :attr:`world_count` independent copies (worlds) of one scene, stepped together
    in one launch and never coupled. Topology (springs, incidence table, pin groups, meshes, colliders)
    is shared and indexed per world (0 .. :attr:`particle_count` - 1); a state's arrays hold every world,
    world-major: particle i of world w is entry w · particle_count + i. Per-world parameters are 2-D
    arrays with one row serving all worlds or one row per world (:meth:`set_world_values`); live inputs
    have a row per world.

    Two kinds of change are allowed between steps:

    * values: write into the arrays in place (``model.spring_stiffness.assign(...)``), set a live input
      (:attr:`gravity`, :attr:`drag`, :attr:`stabilizers`, :meth:`set_track`, :meth:`set_world_values`)
      or switch worlds on and off (:meth:`set_world_enabled`). Kernels read every value from device
      memory, so a captured frame graph sees the change and nothing compiles;
    * structure: switching a term on or off (gravity or drag from zero to nonzero, a stabiliser on or
      off, a track added or removed) or replacing an array. This bumps :attr:`revision`, and a
      :class:`~warpspring.core.stepper.Stepper` re-captures its graph at its next frame (a newly switched-on
      term compiles once). Replacing an array attribute counts as structure too.

    Spring data per group: where every spring of a group (``spring_families``) has the same rest length, ke
    and kd, the gather reads them once per group (:attr:`spring_slot_groups`), from the group's spring in
    :attr:`spring_group_spring`. An in-place write that keeps each group uniform stays a value write; values
    that differ within a group go through :meth:`set_world_values`, or call :meth:`refresh_spring_layout`
    after writing them in place: either reads that group per spring from then on (a structural change).
    """

    device: wp.Device
    precision: str  # "float32" or "float64"
    scalar: type  # wp.float32 or wp.float64
    vec3: type  # wp.vec3f or wp.vec3d
    up_axis: str  # "Y" or "Z"
    block_dim: int  # CUDA threads per block of the per-particle kernels (see ModelBuilder.finalize)
    revision: int  # counts structural changes since finalize (see the class docstring)
    input_version: int  # counts host writes of live inputs and per-world values (what the guard derives from)

    world_count: int  # independent copies of the scene (worlds), stepped together
    world_enabled: wp.array  # int32, shape [world_count]: 1 = stepped, 0 = held as it is (a live value)
    inputs: wp.array2d  # live inputs, shape [world_count, INPUT_COUNT] in the model's precision (kernels/inputs.py)
    track_table: TrackTable  # every keyframe track of the model (pin groups' first, then the inputs')
    input_tracks: InputTracks | None  # the animated inputs, or None
    unit_step: wp.array  # float64, shape [1], holding 1.0: the "step" of launches whose offsets are in seconds

    particle_count: int  # particles per world
    particle_q: wp.array  # [m], shape [world_count · particle_count], initial positions
    particle_qd: wp.array  # [m/s], shape [world_count · particle_count], initial velocities
    particle_mass: wp.array2d  # [kg], shape [1 or world_count, particle_count]
    particle_inv_mass: wp.array2d  # [1/kg], same shape, 1 / particle_mass (kinematic particles too)
    particle_radius: wp.array  # [m], shape [particle_count], contact radius (every world)
    particle_flags: wp.array  # int32, shape [world_count · particle_count]: PARTICLE_KINEMATIC for pinned
    #   (prescribed) particles; a live value (see set_kinematic)
    pin_groups: PinGroupTable | None  # the driven pin groups and every kinematic particle, or None (no group)

    spring_count: int
    spring_indices: wp.array  # wp.vec2i, shape [spring_count], the two particles of each spring
    spring_rest_length: wp.array  # [m], shape [spring_count] (every world)
    spring_families: dict  # host-side: family name -> int64 spring indices (export groups springs by family)
    spring_stiffness: wp.array2d  # ke [N/m], shape [1 or world_count, spring_count]
    spring_damping: wp.array2d  # kd [N·s/m], shape [1 or world_count, spring_count], axial damper
    spring_gather: bool  # evaluate springs per particle (gather, CUDA default) or per spring (scatter, CPU)
    spring_max_degree: int  # most springs at one particle
    spring_incidence: Incidence  # the springs at each particle: entries (spring, other particle), HYB layout
    #   (kernels/families.py); padding entries (0, the particle itself)
    spring_incidence_shape: IncidenceShape  # its ELL head width and whether it has a CSR tail
    spring_slot_groups: tuple  # host-side: per head slot, the spring group (spring_families' order) whose values
    #   the gather reads once per group (a uniform group), or -1 (read per spring); () for the per-spring
    #   layout (core/springs.spring_layout)
    spring_group_spring: wp.array | None  # int32, shape [group_count]: one spring of each group (its values
    #   are the group's), or None
    spring_grid_shape: tuple | None  # host-side: (nx, ny) when the particles are one add_cloth_grid in grid order
    spring_grid_slots: tuple  # host-side: per head slot, the grid direction (dx, dy) [columns, rows] the gather
    #   finds a uniform group's neighbour in, instead of the table (see spring_layout); () for the table
    spring_grid_size: wp.array | None  # int32, shape [2]: (nx, ny) on the device, or None
    spring_material_law: SpringLaw  # the laws the spring groups use (square, asymmetric, plastic switches)
    spring_law_code: wp.array | None  # int32, shape [spring_count]: SPRING_LINEAR or SPRING_SQUARE (laws in use)
    spring_compression_ratio: wp.array | None  # kc / ke [-], shape [spring_count] (laws in use)
    spring_plastic_count: int  # springs that may yield or break (0: no plastic pass)
    spring_plastic_index: wp.array | None  # int32, shape [spring_plastic_count]: those springs
    spring_yield_strain: wp.array | None  # ε_y0 [-], shape [spring_count] (inf: no limit; SpringPlasticity)
    spring_yield_force: wp.array | None  # F_y [N], shape [spring_count] (inf: no limit)
    spring_yield_rate: wp.array | None  # r [1/s], shape [spring_count] (inf: instant)
    spring_hardening: wp.array | None  # H [-], shape [spring_count]
    spring_break_strain: wp.array | None  # [-], shape [spring_count] (inf: never breaks)
    spring_plastic_rest_length: wp.array | None  # [m], shape [world_count · spring_count], world-major: each
    #   world's current rest lengths (state the plastic pass moves; negative: broken)
    spring_plastic_strain: wp.array | None  # α [-], shape [world_count · spring_count]: accumulated plastic strain

    hinge_count: int
    hinge_indices: wp.array  # wp.vec4i, shape [hinge_count]: shared edge x0 → x1, wings x2, x3 (kernels/bending.py)
    hinge_rest_angle: wp.array  # θ0 [rad], shape [hinge_count] (every world)
    hinge_stiffness: wp.array2d  # ke [N·m/rad], shape [1 or world_count, hinge_count]
    hinge_damping: wp.array2d  # kd [N·m·s/rad], shape [1 or world_count, hinge_count]
    hinge_incidence: Incidence  # the hinges at each particle: entries (hinge, role 0..3), HYB layout
    hinge_incidence_shape: IncidenceShape

    extra_families: tuple  # element families beyond springs and hinges (a user's), in kernel order

    tri_count: int
    tri_indices: wp.array  # int32, shape [tri_count, 3], global particle indices

    shape_count: int
    shapes: list  # list[ShapeInfo], host-side: the colliders as built (rest frames, tracks), for export
    shape_arrays: object  # kernels.shapes.shapes_type(scalar): the colliders on the device (struct of arrays)
    shape_types: tuple  # sorted collider kinds present (kernels.shapes.SHAPE_*): the kernels' specialization
    shape_moving: bool  # some collider has a track: its frames are per world, written every step
    shape_rest: wp.array  # wp.transformd, shape [shape_count], each collider's frame at rest
    shape_translation_track: wp.array  # int32, shape [shape_count], track table index of T(t), or -1
    shape_rotation_track: wp.array  # int32, shape [shape_count], track table index of φ(t), or -1
    contact_stage: bool  # contacts go through collide() and the contact buffer (else: fused, every collider)
    contact_slots: int  # contacts a particle holds in the buffer
    contact_swept: bool  # paths over a step swept against spheres, boxes, capsules and meshes (anti-tunnelling)
    contact_triangles: bool  # cloth triangles are pushed out of spheres and capsules too (off by default; structural)
    mesh_colliders: list  # list[MeshCollider]: the Warp meshes of the mesh colliders (points settable between frames)
    shape_deforming: bool  # some mesh collider's points may change between frames

    meshes: list  # list[MeshGroup], host-side, for export
    skins: list  # list[SkinGroup], host-side, for export: surfaces embedded in the particles (soft bodies)
    self_contact: object  # core.selfcontact.SelfContact: self-collision of the triangles (add_self_collision), or None

    def __init__(self, device: wp.Device, precision: str, scalar: type, world_count: int = 1):
        self.device = device
        self.world_count = world_count
        self.world_enabled = wp.ones(world_count, dtype=wp.int32, device=device)
        self._world_hold = False
        self.precision = precision
        self.scalar = scalar
        self.vec3 = vec3_type(scalar)
        self.meshes = []
        self.skins = []
        self.spring_families = {}
        self.spring_slot_groups = ()
        self.spring_group_spring = None
        self.spring_grid_shape = None
        self.spring_grid_slots = ()
        self.spring_grid_size = None
        self._spring_grouping = False  # finalize(spring_groups=): whether the layout follows the values
        self._spring_grid = False  # finalize(spring_grid=): whether a grid's neighbours may be implicit
        self.spring_material_law = SpringLaw()
        self.spring_plastic_count = 0
        for name in ("spring_law_code", "spring_compression_ratio", "spring_plastic_index", "spring_yield_strain",
                     "spring_yield_force", "spring_yield_rate", "spring_hardening", "spring_break_strain",
                     "spring_plastic_rest_length", "spring_plastic_strain"):
            setattr(self, name, None)
        self.emitters = []  # list[Emitter] (core/emitters.py), run after every step by the Simulator
        self.self_contact = None  # SelfContact (core/selfcontact.py) when the scene asks for self-collision
        self.shapes = []
        self.shape_count = 0
        self.shape_types = ()
        self.shape_moving = False
        self.contact_stage = False
        self.contact_slots = 1
        self.contact_swept = False
        self.contact_triangles = False
        self.mesh_colliders = []
        self.shape_deforming = False
        self._shape_tracks: list[Track] = []
        self.revision = 0
        self.input_version = 0
        self.pin_groups = None
        self.extra_families = ()
        self.hinge_count = 0
        self.input_tracks = None
        self.inputs = wp.zeros((world_count, INPUT_COUNT), dtype=scalar, device=device)
        self.unit_step = wp.ones(1, dtype=wp.float64, device=device)
        self._stabilizers = Stabilizers()
        self._gravity_on = False
        self._drag_on = False
        self._tracks: dict[str, list] = {}  # input name -> its track in each world (None: not animated there)
        self._pin_tracks: list[Track] = []
        self._family_tracks: list[Track] = []  # the element families' (their indices fixed at finalize)
        self.track_table = TrackTable([], device)

    def __setattr__(self, name: str, value) -> None:
        # After finalize, replacing a public attribute (an array, a count) changes what captured graphs
        # and compiled kernels were made for: a structural change. Properties decide for themselves.
        if getattr(self, "_finalized", False) and not name.startswith("_") and name not in ("revision", "input_version"):
            if not isinstance(getattr(type(self), name, None), property):
                object.__setattr__(self, "revision", self.revision + 1)
        object.__setattr__(self, name, value)

    def _structure_changed(self) -> None:
        object.__setattr__(self, "revision", self.revision + 1)

    @property
    def particle_dim(self) -> int:
        """The launch size of per-particle kernels: one thread per particle of every world,
        world_count · particle_count (each thread finds its world: ``kernels.worlds.world_and_index``)."""
        return self.world_count * self.particle_count

    @property
    def state_size(self) -> int:
        """Entries of a state's per-particle arrays: world_count · particle_count."""
        return self.world_count * self.particle_count

    # -- live inputs ------------------------------------------------------------------------------------------

    @property
    def gravity(self) -> tuple:
        """Gravitational acceleration [m/s²], 3 floats (world 0's; every world's: ``world_values("gravity")``).
        Setting a 3-vector between frames sets it in every world (per world: :meth:`set_world_values`; a
        keyframe track: :meth:`set_track`). Reading it reads the device (the value a track wrote last)."""
        return tuple(float(g) for g in self.world_values("gravity")[0])

    @gravity.setter
    def gravity(self, value) -> None:
        g = checks.vector("gravity", value)
        self._set_constant("gravity", g)
        if g.any() and not self._gravity_on:
            self._gravity_on = True
            self._structure_changed()

    @property
    def drag(self) -> float:
        """Viscous drag coefficient [N·s/m]: f = -drag · v on every particle (world 0's). Setting a number
        ≥ 0 between frames sets it in every world (per world: :meth:`set_world_values`; a keyframe track:
        :meth:`set_track`). Reading it reads the device."""
        return float(self.world_values("drag")[0, 0])

    @drag.setter
    def drag(self, value) -> None:
        c = checks.non_negative("drag", value)
        self._set_constant("drag", np.array([c]))
        if c != 0.0 and not self._drag_on:
            self._drag_on = True
            self._structure_changed()

    @property
    def gravity_enabled(self) -> bool:
        """Whether the kernels include gravity (on once a nonzero value or a track was set)."""
        return self._gravity_on

    @property
    def drag_enabled(self) -> bool:
        """Whether the kernels include viscous drag (on once a nonzero value or a track was set)."""
        return self._drag_on

    @property
    def stabilizers(self) -> Stabilizers:
        """The stabilisers (:class:`Stabilizers`) as last set from the host. Setting new values between
        frames compiles nothing; switching one on or off, or changing ``strain_iterations``, is a
        structural change. Switching one off removes a track that animated its value."""
        return self._stabilizers

    @stabilizers.setter
    def stabilizers(self, value: Stabilizers) -> None:
        if not isinstance(value, Stabilizers):
            raise ConfigError(f"stabilizers must be a warpspring.Stabilizers, got {type(value).__name__}")
        changed = value.structure != self._stabilizers.structure
        for name in STABILIZER_INPUTS:
            if not value.enabled(name):
                self._tracks.pop(name, None)
                continue
            if not self._stabilizers.enabled(name) or getattr(value, name) != getattr(self._stabilizers, name):
                self._set_constant(name, np.array([getattr(value, name)], dtype=np.float64))
        self._stabilizers = value
        if changed:
            self._rebuild_tracks()
            self._structure_changed()

    def set_track(self, name: str, track: Track | None, *, world: int | None = None) -> None:
        """Animate the live input ``name`` by a keyframe :class:`Track`, or stop animating it (``None``: it
        keeps the value the track gave it last), in every world or in one (``world``).

        Inputs: "gravity" (3-vectors, [m/s²]), "drag" [N·s/m], "wind" (3-vectors, [m/s]), "air_density"
        [kg/m³] and "wind_noise" [-] (with aerodynamics), and the thresholds of the stabilisers that
        are on: "max_spring_force" [N], "max_particle_force" [N], "max_speed" [m/s], "max_strain" [-],
        "biphasic_strain" [-], "biphasic_ratio" [-]. The track is evaluated on the device at the time of
        every state the integrators evaluate (stages included), in each world at that world's time. A
        structural change.

        Raises:
            ConfigError: an unknown input, a track of the wrong width, a threshold of a stabiliser that is
                off, or a world out of range.
        """
        track = input_track(name, track)
        worlds = self._world_rows(world)
        current = self._tracks.get(name, [None] * self.world_count)
        if track is None:
            if any(current[w] is not None for w in worlds):
                current = [None if w in worlds else t for w, t in enumerate(current)]
                self._store_tracks(name, current)
            return
        if name in STABILIZER_INPUTS and not self._stabilizers.enabled(name):
            owner = "biphasic_strain" if name == "biphasic_ratio" else name
            raise ConfigError(
                f"cannot animate {name}: its stabiliser is off; switch it on first, e.g. "
                f"model.stabilizers = Stabilizers({owner}=...)"
            )
        self._check_input(name, track.values, "a key of a track of")
        # Until a step evaluates it, the input holds the track's value at t = 0.
        self._write_input(name, track.sample(0.0)[0][0], worlds)
        if name == "gravity":
            self._gravity_on = True
        elif name == "drag":
            self._drag_on = True
        self._store_tracks(name, [track if w in worlds else t for w, t in enumerate(current)])

    def set_pin_group_tracks(self, group, *, translation: Track | None = None, rotation: Track | None = None,
                             world: int | None = None) -> None:
        """Move a track-driven pin group by other tracks, in every world or in one (``world``): the translation
        T(t) [m] and the rotation vector φ(t) [rad] about the group's pivot (see ``ModelBuilder.add_pin_group``;
        ``None``: that part of the motion is absent). A structural change (the track table is rebuilt).

        Raises:
            ConfigError: no such group, a group driven through Control, neither track given, or a track of
                the wrong width.
        """
        pins = self.pin_groups
        g = pin_group_index(pins, group)
        if pins.groups[g].driver != "tracks":
            raise ConfigError(f"pin group {pins.groups[g].name!r} is driven through Control: it has no tracks to replace")
        if translation is None and rotation is None:
            raise ConfigError("give a translation track, a rotation track, or both")
        pair = (None if translation is None else as_track("a pin group translation", translation, 3),
                None if rotation is None else as_track("a pin group rotation", rotation, 3))
        rows = pins.world_tracks or [[(p.translation, p.rotation) for p in pins.groups]] * self.world_count
        rows = [list(row) for row in rows]
        for w in self._world_rows(world):
            rows[w][g] = pair
        self._pin_tracks = []
        for t in (t for row in rows for pair in row for t in pair):
            if t is not None and not any(t is u for u in self._pin_tracks):
                self._pin_tracks.append(t)
        self._rebuild_tracks()
        self.__dict__["pin_groups"] = pins.retrack(rows, self.track_table.index, self.device)
        self._structure_changed()

    def track(self, name: str, *, world: int = 0) -> Track | None:
        """The track animating the live input ``name`` in ``world``, or ``None``."""
        return self._tracks.get(name, [None] * self.world_count)[self._world_rows(world)[0]]

    def _store_tracks(self, name: str, per_world: list) -> None:
        if any(t is not None for t in per_world):
            self._tracks[name] = per_world
        else:
            self._tracks.pop(name, None)
        self._rebuild_tracks()
        self._structure_changed()

    # -- worlds -------------------------------------------------------------------------------------------------

    def _world_rows(self, world: int | None) -> list[int]:
        """The worlds a call addresses: all (``None``) or one, checked."""
        if world is None:
            return list(range(self.world_count))
        w = checks.count("world", world, minimum=0)
        if w >= self.world_count:
            raise ConfigError(f"world {w} does not exist: the model has {self.world_count} world(s), 0..{self.world_count - 1}")
        return [w]

    def set_world_values(self, name: str, values) -> None:
        """Give each world its own value of a parameter (or one value for all worlds).

        ``values`` is broadcast (NumPy rules) to the parameter's per-world shape:

        * a live input (``gravity`` [m/s²]: shape [world_count, 3]; ``drag`` [N·s/m] and the stabiliser
          thresholds: [world_count]): written into each world's row of the input table, stopping any
          track of it; a value write (nothing compiles or re-captures, unless it switches gravity or drag on);
        * ``spring_stiffness`` [N/m] or ``spring_damping`` [N·s/m]: shape [world_count, spring_count], or
          [spring_count] for one value per spring in every world; ``hinge_stiffness`` [N·m/rad] and
          ``hinge_damping`` [N·m·s/rad] likewise per hinge; ``particle_mass`` [kg]: shape
          [world_count, particle_count] or [particle_count]. One row for all worlds is stored once
          (the kernels broadcast it); a change between one row and one per world replaces the array (a
          structural change: the next frame re-captures), and so does a spring value that makes a group read
          per group non-uniform, or one read per spring uniform again (:meth:`refresh_spring_layout`).

        E.g. a sweep of stiffness over 16 worlds:
        ``model.set_world_values("spring_stiffness", ke[None, :] * np.geomspace(0.1, 10, 16)[:, None])``.

        Raises:
            ConfigError: an unknown name, a shape that does not broadcast, or a value out of range.
        """
        if name in INPUTS:
            slot, width = INPUTS[name]
            try:
                table = np.broadcast_to(np.asarray(values, dtype=np.float64).reshape(-1, width) if width == 3 else
                                        np.asarray(values, dtype=np.float64).reshape(-1, 1), (self.world_count, width))
            except ValueError:
                raise ConfigError(f"per-world {name} must broadcast to shape ({self.world_count}, {width}) or "
                                  f"({self.world_count},), got shape {np.shape(values)}") from None
            if name in STABILIZER_INPUTS and not self._stabilizers.enabled(name):
                raise ConfigError(f"cannot set {name} per world: its stabiliser is off; switch it on first")
            self._write_input(name, table, list(range(self.world_count)))
            if name in self._tracks:
                self._tracks.pop(name)
                self._rebuild_tracks()
                self._structure_changed()
            if name == "gravity" and table.any() and not self._gravity_on:
                self._gravity_on = True
                self._structure_changed()
            if name == "drag" and table.any() and not self._drag_on:
                self._drag_on = True
                self._structure_changed()
            return
        columns = {"spring_stiffness": self.spring_count, "spring_damping": self.spring_count,
                   "hinge_stiffness": self.hinge_count, "hinge_damping": self.hinge_count,
                   "particle_mass": self.particle_count}
        if name not in columns:
            raise ConfigError(f"there is no per-world parameter {name!r}; parameters: "
                              f"{', '.join(list(columns) + list(INPUTS))}")
        count = columns[name]
        array = np.asarray(values, dtype=np.float64)
        rows = 1 if array.ndim <= 1 else self.world_count
        try:
            table = np.broadcast_to(array, (rows, count))
        except ValueError:
            raise ConfigError(f"per-world {name} must broadcast to shape ({self.world_count}, {count}) or ({count},), "
                              f"got shape {array.shape}") from None
        if not np.isfinite(table).all():
            raise ConfigError(f"per-world {name} must be finite")
        if name == "particle_mass" and not (table > 0.0).all():
            raise ConfigError("per-world particle_mass must be > 0 (pin a particle to make it immovable)")
        if name != "particle_mass" and (table < 0.0).any():
            raise ConfigError(f"per-world {name} must be >= 0, got {table.min():g}")
        targets = [(name, table)]
        if name == "particle_mass":
            targets.append(("particle_inv_mass", 1.0 / table))
        for attribute, data in targets:
            with np.errstate(over="ignore"):
                cast = data.astype(np.float32 if self.scalar is wp.float32 else np.float64)
            if not np.isfinite(cast).all():
                raise ConfigError(f"per-world {name} overflows {self.precision}")
            current = getattr(self, attribute)
            if current.shape == cast.shape:
                current.assign(cast)
            else:
                setattr(self, attribute, wp.array(np.ascontiguousarray(cast), dtype=self.scalar, device=self.device))
        if name in ("spring_stiffness", "spring_damping"):
            self.refresh_spring_layout()
        self.input_version += 1  # the energy scale and the elastic energy changed (the guard re-derives them)

    def world_values(self, name: str) -> np.ndarray:
        """Every world's value of a per-world parameter (see :meth:`set_world_values`), float64, shape
        [world_count, width] for a live input and [world_count, count] for the others (reads the device)."""
        if name in INPUTS:
            slot, width = INPUTS[name]
            return self.inputs.numpy()[:, slot : slot + width].astype(np.float64)
        if name not in ("spring_stiffness", "spring_damping", "hinge_stiffness", "hinge_damping", "particle_mass",
                        "particle_inv_mass"):
            raise ConfigError(f"there is no per-world parameter {name!r}")
        values = getattr(self, name).numpy().astype(np.float64)
        return np.broadcast_to(values, (self.world_count, values.shape[1]))

    def set_world_enabled(self, worlds, enabled: bool = True) -> None:
        """Step (``enabled=True``) or hold worlds between frames: a held world keeps its state (positions,
        velocities, time) unchanged by every step until it is enabled again. A live value: nothing compiles
        or re-captures, but the first call switches on the pass that holds worlds (a structural change).

        Args:
            worlds: a world index or indices.
            enabled: whether they are stepped.
        """
        idx = np.unique(np.asarray(worlds, dtype=np.int64).ravel())
        if len(idx) and (idx.min() < 0 or idx.max() >= self.world_count):
            raise ConfigError(f"world index out of range: valid indices are 0..{self.world_count - 1}")
        flags = self.world_enabled.numpy()
        flags[idx] = 1 if enabled else 0
        self.world_enabled.assign(flags)
        self.hold_worlds()

    def hold_worlds(self) -> None:
        """Switch on the pass that keeps held worlds (``world_enabled`` 0) unchanged by a step (a structural
        change, once; the run-time guard does it when it may stop single worlds)."""
        if not self._world_hold:
            self._world_hold = True
            self._structure_changed()

    @property
    def holds_worlds(self) -> bool:
        """Whether steps run the pass that keeps held worlds unchanged."""
        return self._world_hold

    def _check_input(self, name: str, values: np.ndarray, what: str = "") -> None:
        """Raise a ConfigError unless every value of the input ``name`` is finite, within its bound and
        representable in the model's precision."""
        values = np.asarray(values, dtype=np.float64)
        label = f"{what} {name}".strip()
        if not np.isfinite(values).all():
            raise ConfigError(f"{label} must be finite, got {values.ravel().tolist()}")
        minimum, inclusive = INPUT_BOUNDS.get(name, (-np.inf, True))
        if (values < minimum).any() or (not inclusive and (values == minimum).any()):
            raise ConfigError(f"{label} must be {'>=' if inclusive else '>'} {minimum:g}, got {values.min():g}")
        with np.errstate(over="ignore"):
            if not np.isfinite(values.astype(np.float32 if self.scalar is wp.float32 else np.float64)).all():
                raise ConfigError(f"{label} overflows {self.precision} (largest magnitude {np.abs(values).max():.3g})")

    def _set_constant(self, name: str, values: np.ndarray) -> None:
        """Write a constant value of an input to every world and stop animating it."""
        self._write_input(name, values, list(range(self.world_count)))
        if self._tracks.pop(name, None) is not None:
            self._rebuild_tracks()
            self._structure_changed()

    def _write_input(self, name: str, values: np.ndarray, worlds: list[int]) -> None:
        """Check and write a value of an input (one for all ``worlds``, or one row each) into its columns of
        those worlds' rows of the device table."""
        slot, width = INPUTS[name]
        values = np.broadcast_to(np.asarray(values, dtype=np.float64).reshape(-1, width), (len(worlds), width))
        self._check_input(name, values)
        if len(worlds) == self.world_count == 1:
            wp.copy(self.inputs, wp.array(values, dtype=self.scalar, device="cpu"), dest_offset=slot, count=width)
        else:
            table = self.inputs.numpy()
            table[worlds, slot : slot + width] = values
            self.inputs.assign(table)
        self.input_version += 1

    def _rebuild_tracks(self) -> None:
        # Colliders', pin groups' and families' tracks come first, so their indices (held by their tables)
        # never move.
        names = tuple(self._tracks)
        tracks = []
        for t in (*self._shape_tracks, *self._pin_tracks, *self._family_tracks):
            if not any(t is u for u in tracks):
                tracks.append(t)
        for name in names:
            for t in self._tracks[name]:
                if t is not None and not any(t is u for u in tracks):
                    tracks.append(t)
        table = TrackTable(tracks, self.device)
        self.__dict__["track_table"] = table
        if not names:
            self.__dict__["input_tracks"] = None
            return
        entries = [(table.index(t), w, *INPUTS[name]) for name in names for w, t in enumerate(self._tracks[name])
                   if t is not None]
        track, world, slot, width = (np.array(column, dtype=np.int32) for column in zip(*entries))
        arrays = {name: wp.array(values, dtype=wp.int32, device=self.device)
                  for name, values in (("track", track), ("world", world), ("slot", slot), ("width", width))}
        by_world = WorldInputs()
        by_world.track, by_world.slot, by_world.width = arrays["track"], arrays["slot"], arrays["width"]
        by_world.order = wp.array(np.argsort(world, kind="stable").astype(np.int32), dtype=wp.int32, device=self.device)
        by_world.start = wp.array(np.searchsorted(np.sort(world), np.arange(self.world_count + 1)).astype(np.int32),
                                  dtype=wp.int32, device=self.device)
        self.__dict__["input_tracks"] = InputTracks(names=names, **arrays, by_world=by_world)

    def _finalize_shapes(self, *, size: wp.array, stage: bool | None, slots: int | None) -> None:
        """The colliders' device arrays from ``self.shapes`` (called by ``ModelBuilder.finalize``)."""
        shapes, device = self.shapes, self.device
        count = len(shapes)
        self.shape_count = count
        self.shape_types = tuple(sorted({SHAPE_KINDS[s.kind] for s in shapes}))
        self.shape_moving = any(s.moving for s in shapes)
        self.contact_stage = count > 0 and (self.shape_moving if stage is None else bool(stage))
        slots = max(1, min(count, 4)) if slots is None else checks.count("contact_slots", slots, minimum=1)
        if slots > MAX_CONTACT_SLOTS:
            raise ConfigError(f"contact_slots must be at most {MAX_CONTACT_SLOTS}, got {slots}")
        self.contact_slots = slots

        def track_index(track):
            return -1 if track is None else self.track_table.index(track)

        def int_array(values):
            return wp.array(np.asarray(values, dtype=np.int32).reshape(-1), dtype=wp.int32, device=device)

        self.shape_rest = wp.array([wp.transformd(wp.vec3d(*s.position), wp.quatd(*s.rotation)) for s in shapes],
                                   dtype=wp.transformd, device=device)
        self.shape_translation_track = int_array([track_index(s.translation_track) for s in shapes])
        self.shape_rotation_track = int_array([track_index(s.rotation_track) for s in shapes])
        scalar_np = np.float64 if self.scalar is wp.float64 else np.float32
        arrays = shapes_type(self.scalar)()
        arrays.kind = int_array([SHAPE_KINDS[s.kind] for s in shapes])
        arrays.size = size
        arrays.scale = wp.array(np.ones((count, 3), dtype=scalar_np), dtype=self.vec3, device=device)
        arrays.mesh = wp.zeros(count, dtype=wp.uint64, device=device)
        arrays.friction = wp.array(np.asarray([s.friction for s in shapes], dtype=scalar_np), dtype=self.scalar,
                                   device=device)
        arrays.restitution = wp.array(np.asarray([s.restitution for s in shapes], dtype=scalar_np),
                                      dtype=self.scalar, device=device)
        # Frames at t = 0 in every row: one row shared by every world when nothing moves, else one per world.
        rows = self.world_count if self.shape_moving else 1
        frames = np.array([np.concatenate(s.frame(0.0)) for s in shapes], dtype=scalar_np).reshape(count, 7)
        frames = np.ascontiguousarray(np.broadcast_to(frames, (rows, count, 7)))
        transform = transform_type(self.scalar)
        arrays.transform_start = wp.array(frames, dtype=transform, device=device)
        arrays.transform_end = wp.array(frames, dtype=transform, device=device)
        arrays.thickness = wp.array(np.asarray([s.thickness for s in shapes], dtype=scalar_np), dtype=self.scalar,
                                    device=device)
        arrays.static_friction = wp.array(
            np.asarray([s.friction if s.static_friction is None else s.static_friction for s in shapes],
                       dtype=scalar_np), dtype=self.scalar, device=device)
        arrays.sides = int_array([(MESH_WINDING if s.mesh.winding_number else MESH_SIDES[s.mesh.sides])
                                  if s.mesh is not None else 0 for s in shapes])
        arrays.lower = wp.zeros(count, dtype=self.vec3, device=device)  # a mesh's bounding box, written with its mesh
        arrays.upper = wp.zeros(count, dtype=self.vec3, device=device)
        self.shape_arrays = arrays
        # Mesh colliders: their Warp meshes (ids and query ranges go into the arrays above); a path swept against
        # spheres, boxes, capsules and meshes unless switched off (``contact_swept = False``, a structural change).
        self.mesh_colliders = make_mesh_colliders(self)
        self.shape_deforming = any(s.mesh is not None and s.mesh.deforming for s in shapes)
        self.contact_swept = any(kind in SWEPT_KINDS for kind in self.shape_types)

    def contact_features(self) -> ContactFeatures:
        """What the contact kernels compile for this model (no kinds: no contact code)."""
        if self.shape_count == 0:
            return NO_CONTACTS
        return ContactFeatures(kinds=self.shape_types, moving=self.shape_moving, buffered=self.contact_stage,
                               swept=self.contact_swept and any(kind in SWEPT_KINDS for kind in self.shape_types))

    def mesh_collider(self, name_or_index):
        """The :class:`~warpspring.core.mesh_colliders.MeshCollider` of a mesh collider, by its name or its index
        among the colliders (e.g. to :meth:`~MeshCollider.set_points` between frames)."""
        for collider in self.mesh_colliders:
            if name_or_index in (collider.index, collider.name):
                return collider
        names = ", ".join(repr(c.name) for c in self.mesh_colliders) or "none"
        raise ConfigError(f"no mesh collider {name_or_index!r} in this model (mesh colliders: {names})")

    # -- derived feature sets (what the kernels are specialized for) -------------------------------------------

    @property
    def spring_law(self) -> SpringLaw:
        """The spring force law (Hooke's, or biphasic and/or force-clamped by the stabilizers), with the laws
        of the spring groups (:attr:`spring_material_law`)."""
        material = self.spring_material_law
        return self._stabilizers.spring_law._replace(square=material.square, asymmetric=material.asymmetric,
                                                     plastic=material.plastic)

    def spring_rest_lengths(self) -> np.ndarray:
        """Each world's current spring rest lengths [m], float64, shape [world_count, spring_count] (reads the
        device): the built ones, or for plastic springs where they have moved (negative: broken)."""
        if self.spring_material_law.plastic:
            return self.spring_plastic_rest_length.numpy().astype(np.float64).reshape(self.world_count, -1)
        rest = self.spring_rest_length.numpy().astype(np.float64)
        return np.broadcast_to(rest, (self.world_count, self.spring_count)).copy()

    def reset_plasticity(self) -> None:
        """Put every plastic spring back as built: rest lengths L₀, no plastic strain, none broken (device
        copies only; a no-op without plastic springs)."""
        if not self.spring_material_law.plastic:
            return
        self.spring_plastic_rest_length.assign(np.tile(self.spring_rest_length.numpy(), self.world_count))
        self.spring_plastic_strain.zero_()

    @property
    def families(self) -> tuple:
        """The model's element families (:class:`~warpspring.core.families.ElementFamily`), in the order the
        kernels sum them: springs, hinges (each when there are any), then :attr:`extra_families`."""
        springs = (SpringFamily(self),) if self.spring_count else ()
        hinges = (HingeFamily(self),) if self.hinge_count else ()
        return springs + hinges + tuple(self.extra_families)

    @property
    def handles(self):
        """The model's PD handles (:class:`~warpspring.core.handles.HandleFamily`: ``set_target``,
        ``set_gains``), or ``None`` without handles."""
        return next((f for f in self.extra_families if f.name == "handle grabs"), None)

    def family_specs(self, *, linear: bool = False) -> tuple:
        """The kernel specs of :attr:`families` (what the kernels are compiled for); ``linear``: those of the
        stability analysis."""
        return tuple(family.spec(self, linear=linear) for family in self.families)

    @property
    def elements(self):
        """The arrays of every element family as the one struct the kernels take (``kernels/families.py``);
        rebuilt after a structural change."""
        cached = getattr(self, "_elements_cache", None)
        if cached is None or cached[0] != self.revision:
            cached = (self.revision, self.element_arrays())
            object.__setattr__(self, "_elements_cache", cached)
        return cached[1]

    def element_arrays(self, *, linear: bool = False, stiffness: dict | None = None):
        """A new struct of every family's arrays for the specs ``family_specs(linear=linear)``; ``stiffness``
        maps a family's name to a device array replacing its stiffness (the stability analysis's override,
        e.g. ``{"springs": ke}``)."""
        stiffness = stiffness or {}
        chain = composed_elements(self.scalar, self.family_specs(linear=linear)).arrays()
        arrays = [family.arrays(self, stiffness=stiffness.get(family.name)) for family in self.families]
        if linear and self.spring_slot_groups:  # the analysis's spring spec reads values per spring
            arrays[0] = self.families[0].arrays(self, stiffness=stiffness.get("springs"), grouped=False)
        return fill_elements(chain, arrays)

    def spring_arrays(self):
        """The spring family's struct (``kernels/springs.py``): the head of :attr:`elements`, where springs
        come first."""
        if not self.spring_count:
            raise ConfigError("the model has no springs")
        if self.spring_slot_groups:  # the gather's struct also holds the groups: the per-spring one here
            cached = getattr(self, "_spring_arrays_cache", None)
            if cached is None or cached[0] != self.revision:
                cached = (self.revision, SpringFamily(self).arrays(self, grouped=False))
                self._spring_arrays_cache = cached
            return cached[1]
        return self.elements.head

    @property
    def spring_layout(self) -> str:
        """How the spring force is evaluated: "scatter" (per spring, atomic adds), or gathered per particle over
        the incidence table with values per spring ("springs"), each uniform group's values once ("groups"),
        or those and, in a uniform group's slots, the neighbour from the particle's row and column of the
        model's one grid instead of the table ("grid"; the slots of a group read per spring still use the
        table). Chosen by finalize (``spring_groups=``, ``spring_grid=``) and :meth:`refresh_spring_layout`."""
        if not self.spring_gather:
            return "scatter"
        if not self.spring_slot_groups:
            return "springs"
        return "grid" if self.spring_grid_slots else "groups"

    def refresh_spring_layout(self) -> None:
        """After in-place writes of spring rest lengths, stiffness or damping: lay the springs out as their
        values now call for (a group that no longer has one value is read per spring, one that has again per
        group; no group left: the per-spring table), as a model built with these values would be. A new
        layout is a structural change (the next frame re-captures); the same one changes nothing. A model
        finalized with ``spring_groups=False`` keeps its per-spring layout."""
        if self._spring_grouping:
            set_spring_layout(self, True)

    def force_features(self, control: Control | None) -> ForceFeatures:
        """The force terms a step of this model under ``control`` evaluates."""
        return ForceFeatures(
            families=self.family_specs(),
            gravity=self._gravity_on,
            drag=self._drag_on,
            external=control is not None and control.particle_force is not None,
            clamp_particle_force=self._stabilizers.max_particle_force is not None,
            wind=any(getattr(family, "moves_air", False) for family in self.extra_families),
        )

    def kinematic_mask(self, *, world: int = 0) -> np.ndarray:
        """Which particles of ``world`` are kinematic (pinned), bool, shape [particle_count] (reads the device)."""
        w = self._world_rows(world)[0]
        flags = self.particle_flags.numpy()[w * self.particle_count : (w + 1) * self.particle_count]
        return (flags & PARTICLE_KINEMATIC) != 0

    def set_kinematic(self, particles, kinematic: bool = True, *, world: int | None = None) -> None:
        """Pin (``kinematic=True``) or release particles between frames, by index within a world, in every
        world or in one (``world``): a live value.

        A released particle is integrated from its current position and velocity at the next step (a pin of
        a group stops following the group); a newly pinned one moves on with its velocity. Nothing compiles
        or re-captures. In a model with pin groups, only particles pinned when it was built can be pinned
        again (the kinematics pass keeps the list of those).

        Raises:
            ConfigError: an index or world out of range, or a particle the pin groups' list does not hold.
        """
        idx = np.unique(np.asarray(particles, dtype=np.int64).ravel())
        if len(idx) and (idx.min() < 0 or idx.max() >= self.particle_count):
            raise ConfigError(f"particle index out of range: valid indices are 0..{self.particle_count - 1}")
        if kinematic and self.pin_groups is not None:
            new = np.setdiff1d(idx, self.pin_groups.kinematic)
            if len(new):
                raise ConfigError(
                    f"particle {int(new[0])} was not pinned when this model (which has pin groups) was built, so it "
                    "cannot be pinned mid-run: pin it in the builder (pin_particles) and release it until needed"
                )
        entries = (np.array(self._world_rows(world))[:, None] * self.particle_count + idx[None, :]).ravel()
        flags = self.particle_flags.numpy()
        flags[entries] = np.where(kinematic, flags[entries] | PARTICLE_KINEMATIC, flags[entries] & ~PARTICLE_KINEMATIC)
        self.particle_flags.assign(flags)
        self.input_version += 1  # a released particle's energy joins its world's without work

    def dynamic_inv_mass(self, *, world: int = 0) -> np.ndarray:
        """The inverse masses the dynamics sees in ``world`` [1/kg], float64, shape [particle_count]: 1/m, and 0
        for kinematic particles (reads the device)."""
        w = self._world_rows(world)[0]
        return np.where(self.kinematic_mask(world=w), 0.0, self.world_values("particle_inv_mass")[w])

    # -- factories ----------------------------------------------------------------------------------------------

    def state(self) -> State:
        """A new State holding the model's initial positions and velocities, at time 0; driven pins are at
        their prescribed place and velocity at t = 0 (a pin group's velocity at t = 0 is its tracks' rate,
        not the velocity the particles were built with: the first step must see the motion it is in)."""
        state = State(
            particle_q=wp.clone(self.particle_q),
            particle_qd=wp.clone(self.particle_qd),
            particle_f=wp.zeros_like(self.particle_q),
            time=wp.zeros(self.world_count, dtype=wp.float64, device=self.device),
        )
        apply_kinematics(self, None, state, state.particle_q, state.particle_qd, 0.0)
        return state

    def control(self) -> Control:
        """A new Control with no time-varying input set."""
        return Control(self)

    def describe(self) -> str:
        """One line naming the model's size, e.g. for a run summary."""
        shapes = ", ".join(s.kind for s in self.shapes) or "none"
        pins = ""
        if self.pin_groups is not None:
            pins = f", {len(self.pin_groups.groups)} pin group(s)"
        worlds = f"{self.world_count} worlds of " if self.world_count > 1 else ""
        hinges = f", {self.hinge_count} hinges" if self.hinge_count else ""
        extra = "".join(f", {f.element_count} {f.name}" for f in self.extra_families)
        extra += "".join(f", emitter {e.name!r} (pool {e.capacity})" for e in self.emitters)
        layout = f" ({self.spring_layout})" if self.spring_count else ""
        return (
            f"{worlds}{self.particle_count} particles, {self.spring_count} springs{layout}{hinges}{extra}, "
            f"{self.tri_count} triangles{pins}, "
            f"colliders: {shapes} ({self.precision} on {self.device})"
        )
