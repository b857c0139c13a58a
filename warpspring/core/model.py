"""Model (static arrays and live inputs), State (what every step changes) and Control (time-varying inputs)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.forces import ForceFeatures, SpringLaw
from ..kernels.inputs import INPUT_COUNT, INPUTS
from ..kernels.kinematics import PARTICLE_KINEMATIC
from ..kernels.precision import vec3_type
from .kinematics import PinGroupTable, apply_kinematics
from .tracks import Track, TrackTable, input_track

#: The stabiliser thresholds that are live inputs (their names in ``kernels.inputs.INPUTS``).
STABILIZER_INPUTS = ("max_spring_force", "max_particle_force", "max_speed", "max_strain", "biphasic_strain",
                     "biphasic_ratio")
#: The lower bound of each bounded input, and whether the bound itself is allowed (gravity has none).
INPUT_BOUNDS = {"drag": (0.0, True), "biphasic_ratio": (1.0, True),
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


@dataclass(frozen=True)
class InputTracks:
    """The animated live inputs of a model, as the device arrays ``evaluate_input_tracks`` launches over.

    Attributes:
        names: the animated inputs, in launch order.
        track: their tracks' indices in the model's track table, int32, shape [count].
        slot: the first input-table column of each, int32, shape [count].
        width: components of each (1 or 3), int32, shape [count].
    """

    names: tuple
    track: wp.array
    slot: wp.array
    width: wp.array

    @property
    def count(self) -> int:
        return len(self.names)


class Model:
    """Static description of a scene on one device, produced by :meth:`ModelBuilder.finalize`, and its live
    inputs.

    Arrays are Warp arrays on :attr:`device` in the model's precision (:attr:`scalar`); the layout is
    documented per attribute as [unit], shape. Two kinds of change are allowed between steps:

    * values: write into the arrays in place (``model.spring_stiffness.assign(...)``), or set a live input
      (:attr:`gravity`, :attr:`drag`, :attr:`stabilizers`, :meth:`set_track`). Kernels read every value
      from device memory, so a captured frame graph sees the change and nothing compiles;
    * structure: switching a term on or off (gravity or drag from zero to nonzero, a stabiliser on or
      off, a track added or removed) or replacing an array. This bumps :attr:`revision`, and a
      :class:`~warpspring.core.stepper.Stepper` re-captures its graph at its next frame (a newly switched-on
      term compiles once). Replacing an array attribute counts as structure too.
    """

    device: wp.Device
    precision: str  # "float32" or "float64"
    scalar: type  # wp.float32 or wp.float64
    vec3: type  # wp.vec3f or wp.vec3d
    up_axis: str  # "Y" or "Z"
    block_dim: int  # CUDA threads per block of the per-particle kernels (see ModelBuilder.finalize)
    revision: int  # counts structural changes since finalize (see the class docstring)
    input_version: int  # counts host writes of live-input values (what a default guard limit is derived from)

    inputs: wp.array2d  # live inputs, shape [1, INPUT_COUNT] in the model's precision (kernels/inputs.py)
    track_table: TrackTable  # every keyframe track of the model (pin groups' first, then the inputs')
    input_tracks: InputTracks | None  # the animated inputs, or None
    unit_step: wp.array  # float64, shape [1], holding 1.0: the "step" of launches whose offsets are in seconds

    particle_count: int
    particle_q: wp.array  # [m], shape [particle_count], initial positions
    particle_qd: wp.array  # [m/s], shape [particle_count], initial velocities
    particle_mass: wp.array  # [kg], shape [particle_count]
    particle_inv_mass: wp.array  # [1/kg], shape [particle_count], 1 / particle_mass (kinematic particles too)
    particle_radius: wp.array  # [m], shape [particle_count], contact radius
    particle_flags: wp.array  # int32, shape [particle_count]: PARTICLE_KINEMATIC for pinned (prescribed)
    #   particles; a live value (see set_kinematic)
    pin_groups: PinGroupTable | None  # the driven pin groups and every kinematic particle, or None (no group)

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
        self.revision = 0
        self.input_version = 0
        self.pin_groups = None
        self.input_tracks = None
        self.inputs = wp.zeros((1, INPUT_COUNT), dtype=scalar, device=device)
        self.unit_step = wp.ones(1, dtype=wp.float64, device=device)
        self._stabilizers = Stabilizers()
        self._gravity_on = False
        self._drag_on = False
        self._tracks: dict[str, Track] = {}
        self._pin_tracks: list[Track] = []
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

    # -- live inputs ------------------------------------------------------------------------------------------

    @property
    def gravity(self) -> tuple:
        """Gravitational acceleration [m/s²], 3 floats. Set a 3-vector between frames (a keyframe track:
        :meth:`set_track`). Reading it reads the device (the value a track wrote last, if animated)."""
        slot, width = INPUTS["gravity"]
        return tuple(float(g) for g in self.inputs.numpy()[0, slot : slot + width])

    @gravity.setter
    def gravity(self, value) -> None:
        g = checks.vector("gravity", value)
        self._set_constant("gravity", g)
        if g.any() and not self._gravity_on:
            self._gravity_on = True
            self._structure_changed()

    @property
    def drag(self) -> float:
        """Viscous drag coefficient [N·s/m]: f = -drag · v on every particle. Set a number ≥ 0 between
        frames (a keyframe track: :meth:`set_track`). Reading it reads the device."""
        return float(self.inputs.numpy()[0, INPUTS["drag"][0]])

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
            if name not in self._tracks or getattr(value, name) != getattr(self._stabilizers, name):
                self._set_constant(name, np.array([getattr(value, name)], dtype=np.float64))
        self._stabilizers = value
        if changed:
            self._rebuild_tracks()
            self._structure_changed()

    def set_track(self, name: str, track: Track | None) -> None:
        """Animate the live input ``name`` by a keyframe :class:`Track`, or stop animating it (``None``: it
        keeps the value the track gave it last).

        Inputs: "gravity" (3-vectors, [m/s²]), "drag" [N·s/m], and the thresholds of the stabilisers that
        are on: "max_spring_force" [N], "max_particle_force" [N], "max_speed" [m/s], "max_strain" [-],
        "biphasic_strain" [-], "biphasic_ratio" [-]. The track is evaluated on the device at the time of
        every state the integrators evaluate (stages included). A structural change.

        Raises:
            ConfigError: an unknown input, a track of the wrong width, or a threshold of a stabiliser that is off.
        """
        track = input_track(name, track)
        if track is None:
            if self._tracks.pop(name, None) is not None:
                self._rebuild_tracks()
                self._structure_changed()
            return
        if name in STABILIZER_INPUTS and not self._stabilizers.enabled(name):
            owner = "biphasic_strain" if name == "biphasic_ratio" else name
            raise ConfigError(
                f"cannot animate {name}: its stabiliser is off; switch it on first, e.g. "
                f"model.stabilizers = Stabilizers({owner}=...)"
            )
        self._check_input(name, track.values, "a key of a track of")
        # Until a step evaluates it, the input holds the track's value at t = 0.
        self._write_input(name, track.sample(0.0)[0][0])
        if name == "gravity":
            self._gravity_on = True
        elif name == "drag":
            self._drag_on = True
        self._tracks[name] = track
        self._rebuild_tracks()
        self._structure_changed()

    def track(self, name: str) -> Track | None:
        """The track animating the live input ``name``, or ``None``."""
        return self._tracks.get(name)

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
        """Write a constant value of an input to the device and stop animating it."""
        self._write_input(name, values)
        if self._tracks.pop(name, None) is not None:
            self._rebuild_tracks()
            self._structure_changed()

    def _write_input(self, name: str, values: np.ndarray) -> None:
        """Check and write a value of an input into its columns of the device table."""
        slot, width = INPUTS[name]
        values = np.asarray(values, dtype=np.float64).reshape(1, width)
        self._check_input(name, values)
        wp.copy(self.inputs, wp.array(values, dtype=self.scalar, device="cpu"), dest_offset=slot, count=width)
        self.input_version += 1

    def _rebuild_tracks(self) -> None:
        # Pin groups' tracks come first, so their indices (held by the pin-group table) never move.
        names = tuple(self._tracks)
        self.__dict__["track_table"] = TrackTable(self._pin_tracks + [self._tracks[n] for n in names], self.device)
        if not names:
            self.__dict__["input_tracks"] = None
            return
        first = len(self._pin_tracks)
        self.__dict__["input_tracks"] = InputTracks(
            names=names,
            track=wp.array(np.arange(first, first + len(names)), dtype=wp.int32, device=self.device),
            slot=wp.array([INPUTS[n][0] for n in names], dtype=wp.int32, device=self.device),
            width=wp.array([INPUTS[n][1] for n in names], dtype=wp.int32, device=self.device),
        )

    # -- derived feature sets (what the kernels are specialized for) -------------------------------------------

    @property
    def spring_law(self) -> SpringLaw:
        """The spring force law (Hooke's, or biphasic and/or force-clamped by the stabilizers)."""
        return self._stabilizers.spring_law

    def force_features(self, control: Control | None) -> ForceFeatures:
        """The force terms a step of this model under ``control`` evaluates."""
        return ForceFeatures(
            spring_slots=self.spring_max_degree if self.spring_count and self.spring_gather else 0,
            gravity=self._gravity_on,
            drag=self._drag_on,
            external=control is not None and control.particle_force is not None,
            spring_law=self.spring_law,
            clamp_particle_force=self._stabilizers.max_particle_force is not None,
        )

    def kinematic_mask(self) -> np.ndarray:
        """Which particles are kinematic (pinned), bool, shape [particle_count] (reads the device)."""
        return (self.particle_flags.numpy() & PARTICLE_KINEMATIC) != 0

    def set_kinematic(self, particles, kinematic: bool = True) -> None:
        """Pin (``kinematic=True``) or release particles between frames, by global index: a live value.

        A released particle is integrated from its current position and velocity at the next step (a pin of
        a group stops following the group); a newly pinned one moves on with its velocity. Nothing compiles
        or re-captures. In a model with pin groups, only particles pinned when it was built can be pinned
        again (the kinematics pass keeps the list of those).

        Raises:
            ConfigError: an index out of range, or a particle the pin groups' list does not hold.
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
        flags = self.particle_flags.numpy()
        flags[idx] = np.where(kinematic, flags[idx] | PARTICLE_KINEMATIC, flags[idx] & ~PARTICLE_KINEMATIC)
        self.particle_flags.assign(flags)

    def dynamic_inv_mass(self) -> np.ndarray:
        """The inverse masses the dynamics sees [1/kg], float64, shape [particle_count]: 1/m, and 0 for
        kinematic particles (reads the device)."""
        return np.where(self.kinematic_mask(), 0.0, self.particle_inv_mass.numpy().astype(np.float64))

    # -- factories ----------------------------------------------------------------------------------------------

    def state(self) -> State:
        """A new State holding the model's initial positions and velocities, at time 0; driven pins are at
        their prescribed place and velocity at t = 0 (a pin group's velocity at t = 0 is its tracks' rate,
        not the velocity the particles were built with: the first step must see the motion it is in)."""
        state = State(
            particle_q=wp.clone(self.particle_q),
            particle_qd=wp.clone(self.particle_qd),
            particle_f=wp.zeros_like(self.particle_q),
            time=wp.zeros(1, dtype=wp.float64, device=self.device),
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
        return (
            f"{self.particle_count} particles, {self.spring_count} springs, {self.tri_count} triangles{pins}, "
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
        time: the state's time [s], float64, shape [1], on the device: every step advances it by its dt,
            and keyframe tracks and driven pins are evaluated at it.
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


class Control:
    """Time-varying inputs of a step, made by :meth:`Model.control`.

    Attributes:
        model: the model it belongs to.
        particle_force: external force per particle [N], shape [particle_count], or ``None`` when the
            scene applies none (then no kernel reads it).
        pin_targets: targets of the pin groups driven through Control (a device struct; see
            :meth:`set_pin_targets`), or ``None`` when the model has no such group.
        revision: counts structural changes (an input allocated or replaced): a Stepper re-captures.
    """

    def __init__(self, model: Model):
        object.__setattr__(self, "revision", 0)
        self.model = model
        self.particle_force = None
        pins = model.pin_groups
        self.pin_targets = pins.new_targets(model.device) if pins is not None and pins.control_driven else None

    def __setattr__(self, name: str, value) -> None:
        # Replacing an input (an array a captured graph points to) is a structural change.
        if name != "revision":
            object.__setattr__(self, "revision", self.revision + 1)
        object.__setattr__(self, name, value)

    def clear_pin_targets(self) -> None:
        """Forget every pin target: control-driven groups rest where they are until new targets come."""
        if self.pin_targets is not None:
            from ..kernels.kinematics import NO_TARGET_TIME

            self.pin_targets.time.fill_(NO_TARGET_TIME)

    def set_particle_force(self, force) -> None:
        """Set the external force [N]: one 3-vector for every particle, or an array of shape [particle_count, 3].

        The array is allocated on first use (a structural change); later calls overwrite it in place, so
        captured graphs see the new values.
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

    def set_pin_targets(self, group, positions, *, time: float) -> None:
        """Send the particles of a control-driven pin group to ``positions`` [m], reached at ``time`` [s].

        From the state the next step starts at, each particle moves in a straight line at the constant
        velocity that reaches its target at ``time``, exactly on the line at every substep and stage, and
        rests there until new targets come. A ``time`` at or before the state's time leaves the group where
        it is. (``Simulator.set_pin_targets`` picks the end of the next frame.)

        Args:
            group: the group's index or name (a group added with ``add_pin_group`` without tracks).
            positions: shape [n, 3] for the group's n particles in ascending index order (or [3] when n = 1).
            time: when the targets are reached [s].
        """
        pins = self.model.pin_groups
        try:
            g = pins.group_index(group) if pins is not None else None
        except KeyError as exc:
            raise ConfigError(str(exc.args[0])) from None
        if g is None:
            raise ConfigError("the model has no pin groups: add one with ModelBuilder.add_pin_group(particles)")
        pin_group = pins.groups[g]
        if pin_group.driver != "control":
            raise ConfigError(f"pin group {pin_group.name!r} is driven by its tracks, not by Control")
        n = len(pin_group.particles)
        values = np.asarray(positions, dtype=np.float64)
        if values.shape == (3,) and n == 1:
            values = values[None]
        if values.shape != (n, 3) or not np.isfinite(values).all():
            raise ConfigError(f"pin group {pin_group.name!r} needs {n} finite target positions, shape ({n}, 3); "
                              f"got shape {values.shape}")
        when = checks.number("pin target time", time)
        part = pins.slices[g]
        wp.copy(self.pin_targets.position, wp.array(values, dtype=wp.vec3d, device="cpu"), dest_offset=part.start,
                count=n)
        wp.copy(self.pin_targets.time, wp.array([when], dtype=wp.float64, device="cpu"), dest_offset=g, count=1)
