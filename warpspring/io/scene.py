"""Scene files: a TOML description of cloth, materials, pins, colliders, gravity, integrator and output.

Every key is checked: an unknown key, a wrong type or a bad value is a :class:`ConfigError` naming the
file, the table and the key. See the README's scene-file reference, or ``examples/*.toml``.

Scene files are versioned: a top-level ``version = 2`` declares the format (:data:`SCENE_FORMAT_VERSION`);
a file without it is format 1, and every format-1 file still reads as before. Format 2 adds keyframe
tracks wherever a live input takes a value (``[world] gravity = { times = [...], values = [...] }``),
pin groups moved by tracks (``[[cloth.pin_group]]``), and renames ``[guard] max_strain`` to
``tear_strain``. A renamed key is still read under its old name, with a :class:`DeprecatedKeyWarning`
(renames are listed in ``_RENAMED_KEYS``, one line each).

Worlds (format 2): a ``[worlds]`` table runs ``count`` independent copies of the scene in one model, each
with its own values of the keys it lists: a list of one entry per world, where an entry of a live input
is a constant or a track table, as in ``[world]``::

    [worlds]
    count = 3
    gravity = [[0, 0, -9.81], [0, 0, -1.62], { times = [0, 1], values = [[0, 0, -9.81], [0, 0, 0]] }]
    stiffness_scale = [1.0, 2.0, 0.5]

Its entries replace the ``[world]`` / ``[stabilizers]`` value of that input in their world. ``[output]``
``world`` exports one world only; otherwise every world is written as its own prim, laid out on a grid
``world_spacing`` metres apart (see :class:`warpspring.io.usd.UsdWriter`).

Colliders: each ``[[collider]]`` has a ``type`` and the keys of that type (any other key is an error)::

    type = "ground"   height, friction, restitution
    type = "plane"    point, normal, friction, restitution, translation, rotation
    type = "sphere"   center, radius, friction, restitution, translation, rotation
    type = "box"      center, half_extents, orientation, friction, restitution, translation, rotation
    type = "capsule"  center, radius, half_height, orientation, friction, restitution, translation, rotation
    type = "mesh"     file, prim, center, orientation, scale, sides, winding_number, depth, deforming, friction,
                      restitution, translation, rotation

(and ``name`` for each; every type but the ground also takes ``thickness`` [m], a shell around its surface,
and ``static_friction``, μ_s ≥ ``friction``, the kinetic μ_k). A mesh collider's ``file`` is any mesh file
trimesh reads, or USD (``prim`` names the mesh; time-sampled points make it deform), relative to the scene;
its coordinates are the collider's own frame, placed at ``center`` and ``orientation`` and multiplied by
``scale``; ``sides`` says how it tells inside from outside: "closed" (default: a watertight solid, signed
by its pseudo-normals, or with ``winding_number = true`` by its winding number, robust to holes),
"one_sided" (an open mesh, outside where its normals point) or "two_sided" (an open shell); ``depth`` [m]
is how far from an open mesh it is looked for (one-sided: how deep behind it is inside; default a tenth of
its bounding box's diagonal). ``orientation`` is the rest orientation, a quaternion [x, y, z, w]; a capsule
spans -half_height..+half_height along its own z axis, plus its radius. ``restitution`` in [0, 1] is the
share of the normal speed an impact keeps (default 0). Format 2 moves a collider by keyframe tracks, as it
moves a pin group: ``translation = { times = [...], values = [[x, y, z], ...] }`` is an offset [m] added to
its rest position, ``rotation = { times = [...], axis = [x, y, z], degrees = [...] }`` turns it about its
own origin (its centre, or the plane's point), both with optional ``interpolation`` and
``extrapolation``::

    [[collider]]
    type = "box"
    center = [0.0, 0.0, 0.3]
    half_extents = [0.4, 0.4, 0.3]
    rotation = { times = [0.0, 2.0, 6.0], axis = [0, 0, 1], degrees = [0.0, 30.0, 270.0], interpolation = "smooth" }

A ``[contacts]`` table (format 2) sets how contacts are resolved: ``stage`` (true: through the contact
stage and its per-particle buffer; false: every collider tested in the update; default: the stage when a
collider moves) and ``slots``, the contacts one particle holds in that buffer (1 to 64; default: the
number of colliders, at most 4; contacts beyond it are dropped and counted in the run summary),
``triangles`` (true: cloth triangles are pushed out of spheres and capsules too, so one smaller than the
particle spacing cannot slip between particles; default false) and ``swept`` (false: particles' paths over
a step are not swept against spheres, boxes, capsules and meshes; default true).
The new collider types and keys (box, capsule, restitution, orientation, tracks) need format 2.
"""

from __future__ import annotations

import copy
import math
import os
import sys
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..core.aero import AIR_DENSITY, DEFAULT_DRAG, DEFAULT_LIFT
from ..core.builder import ModelBuilder, SpringMaterial
from ..core.builder.spring_materials import DEFAULT_BEND, DEFAULT_SHEAR, DEFAULT_STRUCTURAL, spring_law_options
from ..core.springs import SpringPlasticity
from ..errors import ConfigError
from ..version import __version__
from ..core.guards import GuardLimits
from ..core.integrators import INTEGRATORS
from ..core.model import Model
from ..core.records import MAX_CONTACT_SLOTS, STABILIZER_INPUTS, Stabilizers
from ..core.tracks import EXTRAPOLATIONS, INTERPOLATIONS, Track
from ..core.transforms import quat_from_axis_angle

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

PRECISIONS = ("float32", "float64")
COLLIDER_TYPES = ("ground", "plane", "sphere", "box", "capsule", "mesh")

#: The scene format this warpspring reads (and every older one): a file's top-level ``version``.
SCENE_FORMAT_VERSION = 2


class DeprecatedKeyWarning(FutureWarning):
    """A scene file uses a key under a name that a later scene format renamed: it is still read, and the
    message names the file, the old key and the new one."""


@dataclass(frozen=True)
class PinGroupSpec:
    """A checked ``[[cloth.pin_group]]`` table: particles of one cloth that keyframe tracks move rigidly.

    Attributes:
        pin: which particles, as in ``[cloth] pin``: corner/edge names or indices r·nx + c (grid), vertex
            indices (mesh).
        name: the group's name (made unique in the model).
        pivot: the rotation's centre in world coordinates [m], shape [3], or ``None`` (the group's centroid).
        translation: track of the translation [m] (3-vectors), or ``None``.
        rotation: track of the rotation vector [rad] about ``pivot``, or ``None``.
    """

    pin: list
    name: str = "pins"
    pivot: list | None = None
    translation: Track | None = None
    rotation: Track | None = None


@dataclass(frozen=True)
class HandleSpec:
    """A checked ``[[cloth.handle]]`` table: a PD-controlled handle dragging particles of one cloth
    (``ModelBuilder.add_handle``).

    Attributes:
        particles: which particles, as in ``[cloth] pin``.
        kp: stiffness gain [N/m]; kd: damping gain [N·s/m]; max_force: force cap [N] or ``None``.
        name, pivot, translation, rotation: as for a pin group (the targets' motion).
    """

    particles: list
    kp: float
    kd: float = 0.0
    max_force: float | None = None
    name: str = "handle"
    pivot: list | None = None
    translation: Track | None = None
    rotation: Track | None = None


#: The per-world keys of ``[worlds]`` that scale a parameter of every spring or particle of their world.
WORLD_SCALES = {"stiffness_scale": "spring_stiffness", "damping_scale": "spring_damping", "mass_scale": "particle_mass"}


@dataclass
class Scene:
    """A parsed scene file: how to build the model, and how to run and write it.

    Attributes:
        path: the scene file.
        fps: output frames per second [1/s].
        frames: frames to simulate.
        substeps: integrator steps per frame.
        integrator: integrator name (see ``warpspring.INTEGRATORS``).
        integrator_options: keyword options of the integrator.
        precision: "float32" or "float64".
        device: Warp device name, or ``None`` for Warp's default.
        output: output USD path (relative paths are relative to the working directory), or ``None``.
        export_particles, export_springs: also write particles / springs to USD.
        export_options: the ``[output]`` table's other options of :class:`~warpspring.io.usd.UsdWriter`
            (``primvars``, ``start_frame``, ``collider_purpose``), as given.
        world: the ``[world]`` table (up_axis, gravity, drag) as written (a track as its table).
        cloths: the ``[cloth]`` tables, checked; a cloth's ``pin_group`` is a list of :class:`PinGroupSpec`.
        colliders: the ``[[collider]]`` tables, checked; their ``translation`` and ``rotation`` tracks as
            :class:`Track` objects.
        stabilizers: the ``[stabilizers]`` table (clamps, strain limiting, biphasic springs); a threshold
            given as a track holds the track's first value.
        guard: the ``[guard]`` table (run-time checks).
        wind: the ``[wind]`` table as written (aerodynamics on cloth triangles), or ``None``.
        emitters: the ``[[emitter]]`` tables, checked (particle emitters).
        soft_bodies: the ``[[soft_body]]`` tables, checked (soft bodies from meshes: ModelBuilder.add_soft_body).
        tracks: keyframe tracks of the live inputs the file animates, by input name ("gravity", "drag",
            "max_strain", ...).
        world_count: independent copies of the scene in the model (``[worlds] count``; 1 without ``[worlds]``).
        world_inputs: per-world live inputs of ``[worlds]``, by input name: one entry per world, a constant
            (a float, or a list of 3 for gravity) or a :class:`Track`.
        world_scales: per-world factors of ``[worlds]``, by model parameter ("spring_stiffness",
            "spring_damping", "particle_mass"): one float per world.
        export_world: ``[output] world``: the one world to write, or ``None`` (every world).
        world_spacing: ``[output] world_spacing``: distance [m] between the exported worlds, or ``None``
            (the writer's default).
        world_columns: ``[output] world_columns``: worlds per row of the export grid, or ``None``.
        contact_stage: ``[contacts] stage``: resolve contacts through the contact stage (True) or the fused
            update (False); ``None``: the model's default (the stage when a collider moves).
        contact_slots: ``[contacts] slots``: contacts a particle holds in the stage's buffer, or ``None`` (the
            model's default).
        contact_triangles: ``[contacts] triangles``: push cloth triangles out of spheres and capsules too.
        contact_swept: ``[contacts] swept``: sweep particles' paths against spheres, boxes, capsules and meshes (default
            true).
        version: the file's scene format (1 for a file without ``version``).
        deprecations: one message per deprecated key the file uses (each also a
            :class:`DeprecatedKeyWarning` when the file is read).
    """

    path: str
    fps: float = 60.0
    frames: int = 120
    substeps: int = 16
    integrator: str = "symplectic_euler"
    integrator_options: dict = field(default_factory=dict)
    precision: str = "float32"
    device: str | None = None
    output: str | None = None
    export_particles: bool = False
    export_springs: bool = False
    export_options: dict = field(default_factory=dict)
    world: dict = field(default_factory=dict)
    cloths: list = field(default_factory=list)
    colliders: list = field(default_factory=list)
    stabilizers: Stabilizers = field(default_factory=Stabilizers)
    guard: GuardLimits = field(default_factory=GuardLimits)
    tracks: dict = field(default_factory=dict)
    wind: dict | None = None
    emitters: list = field(default_factory=list)
    soft_bodies: list = field(default_factory=list)
    world_count: int = 1
    world_inputs: dict = field(default_factory=dict)
    world_scales: dict = field(default_factory=dict)
    export_world: int | None = None
    world_spacing: float | None = None
    world_columns: int | None = None
    contact_stage: bool | None = None
    contact_slots: int | None = None
    contact_triangles: bool = False
    contact_swept: bool = True
    self_collision: dict | None = None
    version: int = SCENE_FORMAT_VERSION
    deprecations: list = field(default_factory=list)

    def builder(self) -> ModelBuilder:
        """A ModelBuilder holding the scene's cloth and colliders.

        Raises:
            ConfigError: a value the builder rejects (e.g. a mesh file that is missing or holds NaN),
                prefixed with the scene file and the table.
        """
        where = os.path.basename(self.path)
        world = self.world
        tracks = self.tracks
        with _context(where, "world"):
            builder = ModelBuilder(
                up_axis=world.get("up_axis", "Z"),
                gravity=tracks["gravity"].values[0] if "gravity" in tracks else world.get("gravity"),
                drag=float(tracks["drag"].values[0, 0]) if "drag" in tracks else world.get("drag", 0.0),
                stabilizers=self.stabilizers,
            )
        wind_inputs = set(_WIND_INPUTS.values())
        for name, track in tracks.items():
            if name not in wind_inputs:  # (the wind's tracks once the aerodynamics is added, below)
                with _context(where, "world" if name in ("gravity", "drag") else "stabilizers"):
                    builder.set_track(name, track)
        for i, cloth in enumerate(self.cloths):
            with _context(where, _label("cloth", i, len(self.cloths))):
                _add_cloth(builder, cloth, os.path.dirname(self.path))
        if self.wind is not None:
            with _context(where, "wind"):
                _add_wind(builder, self.wind, tracks)
        for i, emitter in enumerate(self.emitters):
            with _context(where, _label("emitter", i, len(self.emitters))):
                _add_emitter(builder, emitter, os.path.dirname(self.path))
        for i, body in enumerate(self.soft_bodies):
            with _context(where, _label("soft_body", i, len(self.soft_bodies))):
                _add_soft_body(builder, body, os.path.dirname(self.path))
        for i, collider in enumerate(self.colliders):
            with _context(where, _label("collider", i, len(self.colliders))):
                _add_collider(builder, collider, os.path.dirname(self.path))
        if self.self_collision is not None:
            with _context(where, "self_collision"):
                builder.add_self_collision(**self.self_collision)
        return builder

    def finalize(self, device=None) -> Model:
        """The scene's model on ``device``: :meth:`builder` finalized in the scene's precision with
        :attr:`world_count` worlds, each given its ``[worlds]`` values and tracks, and the ``[contacts]``
        options.

        Raises:
            ConfigError: as :meth:`builder`, or a per-world value the model rejects (prefixed with the file
                and the table).
        """
        model = self.builder().finalize(device, precision=self.precision, worlds=self.world_count,
                                        contact_stage=self.contact_stage, contact_slots=self.contact_slots,
                                        integrator=self.integrator)
        if self.contact_triangles:
            model.contact_triangles = True
        if not self.contact_swept:
            model.contact_swept = False
        with _context(os.path.basename(self.path), "worlds"):
            for name, entries in self.world_inputs.items():
                # Constants first (this stops any track of the input), then each world's own track.
                model.set_world_values(name, [e.values[0] if isinstance(e, Track) else e for e in entries])
                for w, entry in enumerate(entries):
                    if isinstance(entry, Track):
                        model.set_track(name, entry, world=w)
            for name, scale in self.world_scales.items():
                base = model.world_values(name)[0]
                model.set_world_values(name, np.asarray(scale)[:, None] * base[None, :])
        return model


# -- schema: key -> expected type -------------------------------------------------------------------------
# A value spec is a Python type (str, bool, list, dict), a _Number, VECTOR, QUATERNION, a nested schema dict, a
# tuple of alternatives (bool or a nested schema: a spring family given as a table or as true/false), a _Live
# input (a constant, or a track table), a _Track table, _Tables (a table or an array of tables), or _Since (a
# key that a later scene format introduced).


@dataclass(frozen=True)
class _Number:
    """A finite number (never a bool), optionally an integer and bounded below."""

    minimum: float | None = None
    inclusive: bool = True
    integer: bool = False

    def describe(self) -> str:
        text = "an integer" if self.integer else "a number"
        if self.minimum is not None:
            text += f" {'>=' if self.inclusive else '>'} {self.minimum:g}"
        return text

    def accepts(self, value) -> bool:
        if isinstance(value, bool) or not isinstance(value, int if self.integer else (int, float)):
            return False
        if not math.isfinite(value):
            return False
        if self.minimum is None:
            return True
        return value >= self.minimum if self.inclusive else value > self.minimum


@dataclass(frozen=True)
class _Track:
    """A track table: ``{ times, values, interpolation, extrapolation }`` with each value fitting ``value``
    (a value spec); or, with ``rotation``, ``{ times, axis, degrees, interpolation, extrapolation }``."""

    value: object = None
    rotation: bool = False


@dataclass(frozen=True)
class _Live:
    """A live input of the model: a constant fitting ``value``, or (from scene format ``tracks_since`` on) a
    track table of such values."""

    value: object
    tracks_since: int = 2


@dataclass(frozen=True)
class _Tables:
    """A table or an array of tables, each of ``schema``."""

    schema: dict


@dataclass(frozen=True)
class _Since:
    """A key the scene format ``version`` introduced (a file of an older format must declare it)."""

    version: int
    spec: object


@dataclass(frozen=True)
class _PerWorld:
    """A list of one entry per world, each fitting ``value`` (its length is checked against ``[worlds]
    count`` once the whole table is read)."""

    value: object


@dataclass(frozen=True)
class _Rename:
    """A key that scene format ``version`` renamed from ``old`` to ``new`` in the table(s) at ``table`` (a
    dotted path; each element of an array of tables). The old name is still read, with a deprecation."""

    table: str
    old: str
    new: str
    version: int
    note: str = ""


#: Renamed keys, oldest first: a rename is one line here (the schema knows the new name only).
_RENAMED_KEYS = (
    _Rename("guard", "max_strain", "tear_strain", 2,
            "the strain at which a spring counts as torn and the run stops; [stabilizers] max_strain is the "
            "strain limit"),
)

NUMBER = _Number()
NON_NEGATIVE = _Number(0.0)
POSITIVE = _Number(0.0, inclusive=False)
VECTOR = "vector"  # a list of 3 finite numbers
QUATERNION = "quaternion"  # a list of 4 finite numbers (x, y, z, w), not all zero

_TYPE_NAMES = {str: "a string", bool: "true or false", list: "a list", dict: "a table"}

_SPRING = {"ke": NON_NEGATIVE, "kd": NON_NEGATIVE,
           # The law and plasticity (warpspring.SpringMaterial, SpringPlasticity):
           "law": str, "compression_ke": NON_NEGATIVE, "yield_strain": POSITIVE, "yield_force": POSITIVE,
           "yield_rate": POSITIVE, "hardening": NON_NEGATIVE, "break_strain": POSITIVE}
_TRACK_TABLE = {"times": list, "values": list, "interpolation": str, "extrapolation": str}
_ROTATION_TRACK_TABLE = {"times": list, "axis": VECTOR, "degrees": list, "interpolation": str, "extrapolation": str}
_RIGID_MOTION = {"pivot": VECTOR, "translation": _Track(VECTOR), "rotation": _Track(rotation=True)}
_PIN_GROUP = {"pin": list, "name": str, **_RIGID_MOTION}
_HANDLE = {"particles": list, "kp": POSITIVE, "kd": NON_NEGATIVE, "max_force": POSITIVE, "name": str, **_RIGID_MOTION}
_EMITTER = {
    "name": str,
    "shape": str,
    "center": VECTOR,
    "half_extents": VECTOR,
    "mesh": str,
    "rate": NON_NEGATIVE,
    "bursts": list,
    "life": POSITIVE,
    "velocity": VECTOR,
    "spread": NON_NEGATIVE,
    "capacity": _Number(1, integer=True),
    "mass": POSITIVE,
    "radius": NON_NEGATIVE,
    "seed": _Number(0, integer=True),
}
#: A ``[[soft_body]]`` table: ModelBuilder.add_soft_body's arguments (mesh and youngs_modulus required, density
#: or mass; ``options`` the method's own, checked by the builder).
_SOFT_BODY = {
    "name": str,
    "mesh": str,
    "prim": str,
    "method": str,
    "youngs_modulus": POSITIVE,
    "density": POSITIVE,
    "mass": POSITIVE,
    "spacing": POSITIVE,
    "damping": NON_NEGATIVE,
    "scale": POSITIVE,
    "origin": VECTOR,
    "rotation": {"axis": VECTOR, "degrees": NUMBER},
    "velocity": VECTOR,
    "radius": NON_NEGATIVE,
    "mass_distribution": str,
    "skin_mass_factor": POSITIVE,
    "mass_gradient": VECTOR,
    "options": dict,
    "pin": {"min": VECTOR, "max": VECTOR},
    "plasticity": {"yield_strain": POSITIVE, "yield_force": POSITIVE, "yield_rate": POSITIVE,
                   "hardening": NON_NEGATIVE, "break_strain": POSITIVE},
    "volume": bool,  # the tet volume term (tetrahedral and delaunay methods)
    "bulk_modulus": POSITIVE,  # its K [Pa]; default 2E/3
    "elasticity": str,  # "springs" or "neohookean" (tetrahedral and delaunay methods: the tets carry it)
    "poisson_ratio": NUMBER,  # ν of the neohookean material, in (-1, 0.5)
}
_SCHEMA = {
    "simulation": {
        "fps": POSITIVE,
        "frames": _Number(1, integer=True),
        "substeps": _Number(1, integer=True),
        "integrator": str,
        "precision": str,
        "device": str,
        "integrator_options": dict,
    },
    "world": {"up_axis": str, "gravity": _Live(VECTOR), "drag": _Live(NON_NEGATIVE)},
    "cloth": {
        "name": str,
        "grid": {"nx": _Number(2, integer=True), "ny": _Number(2, integer=True), "spacing": POSITIVE},
        "mesh": str,
        "prim": _Since(2, str),
        "scale": POSITIVE,
        "origin": VECTOR,
        "rotation": {"axis": VECTOR, "degrees": NUMBER},
        "mass": POSITIVE,
        "particle_mass": POSITIVE,
        "density": POSITIVE,
        "radius": NON_NEGATIVE,
        "velocity": VECTOR,
        "pin": list,
        "pin_group": _Since(2, _Tables(_PIN_GROUP)),
        "handle": _Since(2, _Tables(_HANDLE)),
        "structural": (bool, _SPRING),
        "shear": (bool, _SPRING),
        "bend": (bool, _SPRING),
    },
    "collider": {
        "type": str,
        "name": str,
        "point": VECTOR,
        "normal": VECTOR,
        "height": NUMBER,
        "center": VECTOR,
        "radius": POSITIVE,
        "half_extents": _Since(2, VECTOR),
        "half_height": _Since(2, NON_NEGATIVE),
        "orientation": _Since(2, QUATERNION),
        "friction": NON_NEGATIVE,
        "restitution": _Since(2, NON_NEGATIVE),
        "translation": _Since(2, _Track(VECTOR)),
        "rotation": _Since(2, _Track(rotation=True)),
        "file": _Since(2, str),
        "prim": _Since(2, str),
        "scale": _Since(2, POSITIVE),
        "sides": _Since(2, str),
        "deforming": _Since(2, bool),
        "depth": _Since(2, POSITIVE),
        "winding_number": _Since(2, bool),
        "thickness": _Since(2, NON_NEGATIVE),
        "static_friction": _Since(2, NON_NEGATIVE),
    },
    "contacts": {"stage": bool, "slots": _Number(1, integer=True), "triangles": _Since(2, bool),
                 "swept": _Since(2, bool)},
    "output": {
        "path": str,
        "particles": bool,
        "springs": bool,
        "world": _Since(2, _Number(0, integer=True)),
        "world_spacing": _Since(2, NON_NEGATIVE),
        "world_columns": _Since(2, _Number(1, integer=True)),
        "primvars": _Since(2, list),
        "start_frame": _Since(2, _Number(0, integer=True)),
        "collider_purpose": _Since(2, str),
    },
    "stabilizers": {
        "max_spring_force": _Live(POSITIVE),
        "max_particle_force": _Live(POSITIVE),
        "max_speed": _Live(POSITIVE),
        "max_strain": _Live(POSITIVE),
        "strain_iterations": _Number(1, integer=True),
        "biphasic_strain": _Live(POSITIVE),
        "biphasic_ratio": _Live(_Number(1.0)),
    },
    "guard": {
        "every": _Number(1, integer=True),
        "tear_strain": POSITIVE,
        "max_kinetic_energy": POSITIVE,
        "energy_balance": NON_NEGATIVE,
        "dissipation": _Since(2, bool),
        "stop": _Since(2, str),
    },
    "wind": {
        "velocity": _Live(VECTOR),
        "air_density": _Live(POSITIVE),
        "noise": _Live(NON_NEGATIVE),
        "noise_scale": POSITIVE,
        "seed": _Number(0, integer=True),
        "drag": NON_NEGATIVE,
        "lift": NON_NEGATIVE,
        "meshes": list,
    },
    "worlds": {
        "count": _Number(1, integer=True),
        "gravity": _PerWorld(_Live(VECTOR)),
        "wind": _PerWorld(_Live(VECTOR)),
        "air_density": _PerWorld(_Live(POSITIVE)),
        "wind_noise": _PerWorld(_Live(NON_NEGATIVE)),
        "drag": _PerWorld(_Live(NON_NEGATIVE)),
        "max_spring_force": _PerWorld(_Live(POSITIVE)),
        "max_particle_force": _PerWorld(_Live(POSITIVE)),
        "max_speed": _PerWorld(_Live(POSITIVE)),
        "max_strain": _PerWorld(_Live(POSITIVE)),
        "biphasic_strain": _PerWorld(_Live(POSITIVE)),
        "biphasic_ratio": _PerWorld(_Live(_Number(1.0))),
        "stiffness_scale": _PerWorld(NON_NEGATIVE),
        "damping_scale": _PerWorld(NON_NEGATIVE),
        "mass_scale": _PerWorld(POSITIVE),
    },
}
_TOP_LEVEL = {"version": _Number(1, integer=True), **{k: (dict, list) if k in ("cloth", "collider") else dict
                                                      for k in _SCHEMA}, "worlds": _Since(2, dict),
              "wind": _Since(2, dict), "emitter": _Since(2, (dict, list)),
              "soft_body": _Since(2, (dict, list)),
              "contacts": _Since(2, dict)}
#: [self_collision]: the surfaces' layers kept apart (ModelBuilder.add_self_collision), from format 2 on.
_SCHEMA["self_collision"] = {"thickness": POSITIVE, "friction": NON_NEGATIVE, "relaxation": POSITIVE, "meshes": list}
_TOP_LEVEL["self_collision"] = _Since(2, dict)
#: How the run-time guard may stop: the whole run, or only the world that failed ([guard] stop).
GUARD_STOPS = ("run", "world")
#: The tables holding live inputs (each may be a track table from format 2 on).
_LIVE_TABLES = ("world", "stabilizers")
#: The live inputs of the [wind] table: its key -> the model's input name.
_WIND_INPUTS = {"velocity": "wind", "air_density": "air_density", "noise": "wind_noise"}

# Keys that apply to one kind of cloth or collider only (anything else would be silently ignored).
_GRID_ONLY = {"grid", "particle_mass", "shear"}
_MESH_ONLY = {"mesh", "density", "scale", "prim"}
_COLLIDER_COMMON = {"type", "name", "friction", "restitution"}
_COLLIDER_MOTION = {"translation", "rotation"}
_COLLIDER_KEYS = {
    "ground": _COLLIDER_COMMON | {"height"},
    "plane": _COLLIDER_COMMON | _COLLIDER_MOTION | {"point", "normal"},
    "sphere": _COLLIDER_COMMON | _COLLIDER_MOTION | {"center", "radius"},
    "box": _COLLIDER_COMMON | _COLLIDER_MOTION | {"center", "half_extents", "orientation"},
    "capsule": _COLLIDER_COMMON | _COLLIDER_MOTION | {"center", "radius", "half_height", "orientation"},
}
# The keys each collider type needs, and how its error shows them.
_COLLIDER_NEEDS = {
    "sphere": ({"center", "radius"}, "center = [x, y, z] and radius"),
    "box": ({"center", "half_extents"}, "center = [x, y, z] and half_extents = [hx, hy, hz]"),
    "capsule": ({"center", "radius", "half_height"}, "center = [x, y, z], radius and half_height"),
}
# Mesh colliders (format 2), and a thickness and static friction on every collider but the ground.
_COLLIDER_KEYS["mesh"] = _COLLIDER_COMMON | _COLLIDER_MOTION | {
    "file", "prim", "center", "orientation", "scale", "sides", "deforming", "depth", "winding_number"}
for _kind in ("plane", "sphere", "box", "capsule", "mesh"):
    _COLLIDER_KEYS[_kind] = _COLLIDER_KEYS[_kind] | {"thickness", "static_friction"}
_COLLIDER_NEEDS["mesh"] = ({"file"}, 'file = "path" (any mesh file trimesh reads, or USD with prim = "/path")')
#: The collider types a scene of format 1 may use (the others came with format 2).
_FORMAT_1_COLLIDERS = ("ground", "plane", "sphere")


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and check a scene file.

    A deprecated key is read under its new name and reported by a :class:`DeprecatedKeyWarning` (and in
    ``Scene.deprecations``).

    Raises:
        ConfigError: the file is missing or unreadable, not valid TOML, of a newer scene format, or breaks
            the schema.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ConfigError(f"scene file not found: {path}")
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {_one_line(exc)}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read: {_one_line(exc)}") from None
    scene = _parse(data, path)
    for message in scene.deprecations:
        warnings.warn(message, DeprecatedKeyWarning, stacklevel=2)
    return scene


def parse_scene(data: dict, *, path: str = "<scene>") -> Scene:
    """Check a scene given as a dict (the parsed TOML) and return it as a :class:`Scene`.

    ``data`` is not modified. A deprecated key is read under its new name and reported by a
    :class:`DeprecatedKeyWarning` (and in ``Scene.deprecations``).

    Raises:
        ConfigError: naming the file, the table and the key that is unknown, of the wrong type or out of
            range; or a scene format newer than :data:`SCENE_FORMAT_VERSION`.
    """
    scene = _parse(data, path)
    for message in scene.deprecations:
        warnings.warn(message, DeprecatedKeyWarning, stacklevel=2)
    return scene


def _parse(data: dict, path: str) -> Scene:
    """parse_scene without the warnings (the callers warn, so that a warning points at their caller)."""
    where = os.path.basename(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: a scene must be a table of tables, got {type(data).__name__}")
    version = _format_version(data, where)  # first: a newer file's keys would only confuse the checks below
    data = copy.deepcopy(data)
    deprecations = _apply_renames(data, version, where)
    _check_table(data, _TOP_LEVEL, where, "", version=version)
    for name in ("simulation", "world", "output", "stabilizers", "guard", "worlds", "contacts", "wind"):
        _check_table(data.get(name, {}), _SCHEMA[name], where, name, version=version)
    cloths = _table_list(data.get("cloth", []), where, "cloth")
    colliders = _table_list(data.get("collider", []), where, "collider")
    emitters = _table_list(data.get("emitter", []), where, "emitter")
    soft_bodies = _table_list(data.get("soft_body", []), where, "soft_body")
    for i, body in enumerate(soft_bodies):
        label = _label("soft_body", i, len(soft_bodies))
        _check_table(body, _SOFT_BODY, where, label, version=version)
        missing = [key for key in ("mesh", "youngs_modulus") if key not in body]
        if missing:
            raise ConfigError(f"{where}: [{label}] needs {missing[0]} = ... (the mesh file, and Young's modulus E [Pa])")
        if ("density" in body) == ("mass" in body):
            raise ConfigError(f"{where}: [{label}] needs exactly one of density = ... [kg/m³] or mass = ... [kg]")
        _check_soft_body_pin(body.get("pin"), where, label)
        if "plasticity" in body and not ({"yield_strain", "yield_force"} & set(body["plasticity"])):
            raise ConfigError(f"{where}: {label}.plasticity needs yield_strain = ... [-] or yield_force = ... [N] "
                              "(its elastic limit)")
    if not cloths and not emitters and not soft_bodies:
        raise ConfigError(f"{where}: the scene has no [cloth] table: add one with grid = {{...}} or mesh = '...' "
                          "(or particles from an [[emitter]])")
    for i, e in enumerate(emitters):
        label = _label("emitter", i, len(emitters))
        _check_table(e, _EMITTER, where, label, version=version)
        if "life" not in e:
            raise ConfigError(f"{where}: [{label}] needs life = ..., each particle's life span [s]")
    for i, c in enumerate(cloths):
        _check_cloth(c, where, _label("cloth", i, len(cloths)), version=version)
    for i, c in enumerate(colliders):
        _check_collider(c, where, _label("collider", i, len(colliders)), version=version)

    sim, out = data.get("simulation", {}), data.get("output", {})
    integrator = sim.get("integrator", Scene.integrator)
    if integrator not in INTEGRATORS:
        raise ConfigError(
            f"{where}: unknown integrator {integrator!r} in [simulation]: "
            f"choose one of {', '.join(sorted(INTEGRATORS))}"
        )
    precision = sim.get("precision", Scene.precision)
    if precision not in PRECISIONS:
        raise ConfigError(f"{where}: simulation.precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")

    tracks = {
        name: _make_track(value, where, f"{table}.{name}")
        for table in _LIVE_TABLES
        for name, value in data.get(table, {}).items()
        if isinstance(_SCHEMA[table][name], _Live) and isinstance(value, dict)
    }
    wind = data.get("wind")
    if wind is not None:
        tracks.update({_WIND_INPUTS[key]: _make_track(value, where, f"wind.{key}") for key, value in wind.items()
                       if key in _WIND_INPUTS and isinstance(value, dict)})
    # A threshold given as a track starts at its first value; the track is set on the builder.
    stabilizers = {k: float(tracks[k].values[0, 0]) if k in tracks else v
                   for k, v in data.get("stabilizers", {}).items()}
    scene = Scene(path=path, world=data.get("world", {}), cloths=cloths, colliders=colliders, tracks=tracks,
                  wind=wind, emitters=emitters, version=version, deprecations=deprecations)
    scene.soft_bodies = soft_bodies
    scene.fps = float(sim.get("fps", scene.fps))
    scene.frames = sim.get("frames", scene.frames)
    scene.substeps = sim.get("substeps", scene.substeps)
    scene.integrator = integrator
    scene.integrator_options = dict(sim.get("integrator_options", {}))
    scene.precision = precision
    scene.device = sim.get("device")
    scene.output = out.get("path")
    scene.export_particles = out.get("particles", False)
    scene.export_springs = out.get("springs", False)
    scene.export_options = _export_options(out, where)
    scene.stabilizers = Stabilizers(**stabilizers)
    for name in tracks:
        if name in STABILIZER_INPUTS and not scene.stabilizers.enabled(name):  # only biphasic_ratio can be
            raise ConfigError(f"{where}: stabilizers.{name} is a track, but biphasic springs are off: set "
                              "stabilizers.biphasic_strain too (the strain beyond which springs stiffen)")
    guard = data.get("guard", {})
    if guard.get("stop", "run") not in GUARD_STOPS:
        raise ConfigError(f"{where}: guard.stop must be one of {', '.join(map(repr, GUARD_STOPS))} (stop the whole "
                          f"run, or hold only the failing world and go on), got {guard['stop']!r}")
    scene.guard = GuardLimits(**guard)
    contacts = data.get("contacts", {})
    if contacts.get("slots", 1) > MAX_CONTACT_SLOTS:
        raise ConfigError(f"{where}: contacts.slots must be an integer from 1 to {MAX_CONTACT_SLOTS} (the contacts one "
                          f"particle holds), got {contacts['slots']!r}")
    scene.contact_stage = contacts.get("stage")
    scene.contact_slots = contacts.get("slots")
    scene.contact_triangles = contacts.get("triangles", False)
    scene.contact_swept = contacts.get("swept", True)
    self_collision = data.get("self_collision")
    if self_collision is not None:
        _check_table(self_collision, _SCHEMA["self_collision"], where, "self_collision", version=version)
        if "thickness" not in self_collision:
            raise ConfigError(f"{where}: [self_collision] needs thickness = ..., the separation [m] kept between "
                              "layers (below 0.7 × the mesh's smallest triangle altitude)")
        scene.self_collision = dict(self_collision)
    _parse_worlds(scene, data.get("worlds"), out, where)
    check_run_settings(fps=scene.fps, frames=scene.frames, substeps=scene.substeps, where=where)
    return scene


def _parse_worlds(scene: Scene, worlds: dict | None, out: dict, where: str) -> None:
    """Fill the scene's world fields from its checked ``[worlds]`` and ``[output]`` tables (types are
    checked already; here: the count, the list lengths, and what the values need)."""
    if worlds is not None:
        if "count" not in worlds:
            raise ConfigError(f"{where}: [worlds] needs count = N, the number of worlds (each key of [worlds] then "
                              "lists one entry per world)")
        count = scene.world_count = worlds["count"]
        for key, entries in worlds.items():
            if key == "count":
                continue
            if len(entries) != count:
                raise ConfigError(f"{where}: worlds.{key} has {len(entries)} entr{'y' if len(entries) == 1 else 'ies'} "
                                  f"but count = {count}: give one entry per world")
            if key in WORLD_SCALES:
                scene.world_scales[WORLD_SCALES[key]] = [float(e) for e in entries]
                continue
            if key in STABILIZER_INPUTS and not scene.stabilizers.enabled(key):
                owner = "biphasic_strain" if key == "biphasic_ratio" else key
                raise ConfigError(f"{where}: worlds.{key} sets {key} per world, but its stabiliser is off: set "
                                  f"[stabilizers] {owner} too (it switches the stabiliser on; [worlds] replaces its "
                                  "value in each world)")
            scene.world_inputs[key] = [
                _make_track(e, where, f"worlds.{key}[{i}]") if isinstance(e, dict)
                else (float(e) if not isinstance(e, list) else [float(x) for x in e])
                for i, e in enumerate(entries)
            ]
    count = scene.world_count
    if "world" in out and out["world"] >= count:
        raise ConfigError(f"{where}: output.world = {out['world']} does not exist: the scene has {count} world(s), "
                          f"0..{count - 1} (set [worlds] count, or leave output.world out to write every world)")
    scene.export_world = out.get("world")
    scene.world_spacing = float(out["world_spacing"]) if "world_spacing" in out else None
    scene.world_columns = out.get("world_columns")


def check_run_settings(*, fps, frames, substeps, where: str = "options") -> None:
    """Raise ConfigError unless fps > 0, frames ≥ 1 and substeps ≥ 1 (so that dt = 1 / (fps · substeps) > 0)."""
    if not (POSITIVE.accepts(fps)):
        raise ConfigError(f"{where}: fps must be a finite number > 0 (dt = 1 / (fps * substeps)), got {fps!r}")
    if not _Number(1, integer=True).accepts(frames):
        raise ConfigError(f"{where}: frames must be an integer >= 1, got {frames!r}")
    if not _Number(1, integer=True).accepts(substeps):
        raise ConfigError(f"{where}: substeps must be an integer >= 1 (dt = 1 / (fps * substeps)), got {substeps!r}")


# -- versions and renames ---------------------------------------------------------------------------------


def _format_version(data: dict, where: str) -> int:
    """The file's scene format: its top-level ``version``, 1 when absent."""
    version = data.get("version", 1)
    reads = f"scene formats 1 to {SCENE_FORMAT_VERSION}"
    if not _Number(1, integer=True).accepts(version):
        raise ConfigError(f"{where}: version must be an integer >= 1 (the scene format; this warpspring reads "
                          f"{reads}), got {version!r}")
    if version > SCENE_FORMAT_VERSION:
        raise ConfigError(f"{where}: scene format version {version} needs a newer warpspring: warpspring "
                          f"{__version__} reads {reads}; upgrade it (pip install --upgrade warpspring)")
    return version


def _needs(version: int, where: str, what: str) -> ConfigError:
    """The error for a feature of scene format ``version`` in a file of an older format."""
    return ConfigError(f"{where}: {what} needs scene format {version}: add version = {version} at the top of the "
                       "file, before the first [table]")


def _tables_at(data: dict, dotted: str) -> list[tuple[str, dict]]:
    """(label, table) of every table at the dotted path: each element of an array of tables, labelled
    "cloth[1]" when there are several. What is not a table is left to the schema checks."""
    found = [("", data)]
    for part in dotted.split("."):
        inner = []
        for label, table in found:
            value, name = table.get(part), f"{label}.{part}" if label else part
            if isinstance(value, dict):
                inner.append((name, value))
            elif isinstance(value, list):
                inner += [(_label(name, i, len(value)), t) for i, t in enumerate(value) if isinstance(t, dict)]
        found = inner
    return found


def _apply_renames(data: dict, version: int, where: str) -> list[str]:
    """Move every renamed key of ``data`` (a copy of the file's tables) to its new name and return one
    deprecation message per old name found. Both names in one table is an error, and so is a new name in
    a file of a format older than the rename (the file must declare the format it uses)."""
    messages = []
    for rename in _RENAMED_KEYS:
        for label, table in _tables_at(data, rename.table):
            if rename.old in table and rename.new in table:
                raise ConfigError(f"{where}: [{label}] has both {rename.old} and {rename.new}, its new name: "
                                  f"keep {rename.new} only")
            if rename.new in table and version < rename.version:
                raise _needs(rename.version, where, f"[{label}] {rename.new}")
            if rename.old in table:
                table[rename.new] = table.pop(rename.old)
                upgrade = "" if version >= rename.version else f" and add version = {rename.version} at the top"
                messages.append(
                    f"{where}: [{label}] {rename.old} is deprecated: scene format {rename.version} renamed it "
                    f"{rename.new} ({rename.note}); rename it{upgrade}"
                )
    return messages


# -- checking ---------------------------------------------------------------------------------------------


def _label(name: str, index: int, count: int) -> str:
    """How an error names a table: "cloth", or "cloth[1]" (0-based) when the file has several."""
    return name if count == 1 else f"{name}[{index}]"


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


class _context:
    """Prefix a ConfigError raised inside with the scene file and the table it came from."""

    def __init__(self, where: str, table: str):
        self.prefix = f"{where}: in [{table}]: "

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if kind is not None and issubclass(kind, ConfigError):
            raise ConfigError(self.prefix + _one_line(exc)) from None
        return False


def _table_list(value, where: str, name: str) -> list:
    tables = [value] if isinstance(value, dict) else list(value)
    for t in tables:
        if not isinstance(t, dict):
            raise ConfigError(f"{where}: [{name}] must be a table or an array of tables")
    return tables


def _check_pins(pins: list, grid: bool, where: str, key: str) -> None:
    for p in pins:
        ok = isinstance(p, int) and not isinstance(p, bool)
        if grid:
            ok = ok or isinstance(p, str)
        if not ok:
            kinds = "corner/edge names or particle indices" if grid else "vertex indices (names are for grid cloths)"
            raise ConfigError(f"{where}: {key} takes {kinds}, got {p!r}")


def _check_cloth(c: dict, where: str, label: str, *, version: int) -> None:
    """Check a [cloth] table, and turn its pin groups into :class:`PinGroupSpec` (``c`` is the scene's copy)."""
    _check_table(c, _SCHEMA["cloth"], where, label, version=version)
    for key in ("structural", "shear", "bend"):
        if isinstance(c.get(key), dict):  # the law's name and the plasticity's limits, checked together
            try:
                spring_law_options(key, c[key])
            except ConfigError as exc:
                raise ConfigError(f"{where}: {label}.{key}: {_one_line(exc)}") from None
    if ("grid" in c) == ("mesh" in c):
        raise ConfigError(f"{where}: [{label}] needs exactly one of grid = {{nx, ny, spacing}} or mesh = 'file'")
    grid = "grid" in c
    if grid:
        missing = [k for k in ("nx", "ny", "spacing") if k not in c["grid"]]
        if missing:
            raise ConfigError(f"{where}: {label}.grid needs nx, ny and spacing; missing: {', '.join(missing)}")
    wrong = sorted((_MESH_ONLY if grid else _GRID_ONLY) & set(c))
    if wrong:
        kind, other = ("grid", "mesh") if grid else ("mesh", "grid")
        raise ConfigError(f"{where}: {label}.{wrong[0]} applies to a {other} cloth only, not to a {kind} cloth")
    per_particle = "particle_mass" if grid else "density"
    if ("mass" in c) == (per_particle in c):
        raise ConfigError(
            f"{where}: [{label}] needs exactly one of mass (total, kg) or {per_particle} "
            f"({'kg per particle' if grid else 'kg/m²'})"
        )
    axis = c.get("rotation", {}).get("axis")
    if axis is not None and not any(axis):
        raise ConfigError(f"{where}: {label}.rotation.axis must be a nonzero vector, got {axis!r}")
    _check_pins(c.get("pin", []), grid, where, f"{label}.pin")
    if "pin_group" in c:
        groups = [c["pin_group"]] if isinstance(c["pin_group"], dict) else c["pin_group"]
        c["pin_group"] = [
            _pin_group(g, grid, where, _label(f"{label}.pin_group", i, len(groups))) for i, g in enumerate(groups)
        ]
    if "handle" in c:
        handles = [c["handle"]] if isinstance(c["handle"], dict) else c["handle"]
        c["handle"] = [_handle(h, grid, where, _label(f"{label}.handle", i, len(handles)))
                       for i, h in enumerate(handles)]


def _handle(handle: dict, grid: bool, where: str, key: str) -> HandleSpec:
    """A checked [[cloth.handle]] table (its keys' types are checked already) as a HandleSpec."""
    if not handle.get("particles"):
        example = '["left"]' if grid else "[0, 1]"
        raise ConfigError(f"{where}: {key}.particles is {'empty' if 'particles' in handle else 'missing'}: name "
                          f"the particles the handle grabs, e.g. particles = {example}")
    if "kp" not in handle:
        raise ConfigError(f"{where}: [{key}] needs kp = ..., its stiffness gain [N/m] (and kd, its damping [N·s/m])")
    _check_pins(handle["particles"], grid, where, f"{key}.particles")
    return HandleSpec(
        particles=list(handle["particles"]),
        kp=float(handle["kp"]),
        kd=float(handle.get("kd", 0.0)),
        max_force=float(handle["max_force"]) if "max_force" in handle else None,
        name=handle.get("name", "handle"),
        pivot=handle.get("pivot"),
        translation=_make_track(handle["translation"], where, f"{key}.translation") if "translation" in handle
        else None,
        rotation=_make_track(handle["rotation"], where, f"{key}.rotation") if "rotation" in handle else None,
    )


def _pin_group(group: dict, grid: bool, where: str, key: str) -> PinGroupSpec:
    """A checked [[cloth.pin_group]] table (its keys' types are checked already) as a PinGroupSpec."""
    if not group.get("pin"):
        example = '["top"]' if grid else "[0, 1]"
        raise ConfigError(f"{where}: {key}.pin is {'empty' if 'pin' in group else 'missing'}: name the particles "
                          f"the group moves, e.g. pin = {example}")
    _check_pins(group["pin"], grid, where, f"{key}.pin")
    if "translation" not in group and "rotation" not in group:
        raise ConfigError(
            f"{where}: [{key}] moves nothing: give translation = {{ times = [...], values = [...] }} and/or "
            "rotation = { times = [...], axis = [x, y, z], degrees = [...] }; for particles that stay put, "
            f"list them in pin = [...] of the cloth instead"
        )
    return PinGroupSpec(
        pin=list(group["pin"]),
        name=group.get("name", "pins"),
        pivot=group.get("pivot"),
        translation=_make_track(group["translation"], where, f"{key}.translation")
        if "translation" in group else None,
        rotation=_make_track(group["rotation"], where, f"{key}.rotation", rotation=True)
        if "rotation" in group else None,
    )


def _check_collider(c: dict, where: str, label: str, *, version: int) -> None:
    """Check a [[collider]] table, and turn its tracks into :class:`Track` objects (``c`` is the scene's copy)."""
    _check_table(c, _SCHEMA["collider"], where, label, version=version)
    kind = c.get("type")
    if kind is None:
        raise ConfigError(f"{where}: {label}.type is missing: set type = one of {', '.join(COLLIDER_TYPES)}")
    types = COLLIDER_TYPES if version >= 2 else _FORMAT_1_COLLIDERS
    if kind not in types:
        newer = [t for t in COLLIDER_TYPES if t not in _FORMAT_1_COLLIDERS]
        hint = (f" (in scene format {version}; {', '.join(newer[:-1])} and {newer[-1]} colliders need scene format 2: "
                "add version = 2 at the top of the file, before the first [table])") if kind in COLLIDER_TYPES else ""
        raise ConfigError(f"{where}: {label}.type must be one of {', '.join(types)}, got {kind!r}{hint}")
    extra = sorted(set(c) - _COLLIDER_KEYS[kind])
    if extra:
        raise ConfigError(
            f"{where}: {label}.{extra[0]} does not apply to a {kind} collider; "
            f"it takes: {', '.join(sorted(_COLLIDER_KEYS[kind] - {'type'}))}"
        )
    needs, shown = _COLLIDER_NEEDS.get(kind, (set(), ""))
    missing = sorted(needs - set(c))
    if missing:
        raise ConfigError(f"{where}: a {kind} collider ([{label}]) needs {shown}; missing: {', '.join(missing)}")
    if "half_extents" in c and not all(h > 0 for h in c["half_extents"]):
        raise ConfigError(f"{where}: {label}.half_extents must be 3 numbers > 0 (half the box's size along its own "
                          f"x, y, z [m]), got {c['half_extents']!r}")
    if c.get("restitution", 0.0) > 1.0:
        raise ConfigError(f"{where}: {label}.restitution must be a number from 0 to 1 (the share of the normal speed "
                          f"an impact keeps), got {c['restitution']!r}")
    for key in ("translation", "rotation"):
        if key in c:
            c[key] = _make_track(c[key], where, f"{label}.{key}", rotation=key == "rotation")


def _check_table(table: dict, schema: dict, where: str, name: str, *, version: int) -> None:
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: [{name}] must be a table")
    for key, value in table.items():
        if key not in schema:
            hint = " (version belongs at the top of the file, before the first [table])" if key == "version" else ""
            raise ConfigError(
                f"{where}: unknown key {key!r} in [{name or 'top level'}]; allowed: {', '.join(schema)}{hint}"
            )
        _check_value(value, schema[key], where, f"{name}.{key}" if name else key, version=version)


def _add_emitter(builder: ModelBuilder, e: dict, base: str) -> None:
    """An ``[[emitter]]`` table (types checked); a mesh file's path is relative to the scene's folder."""
    mesh = None
    if "mesh" in e:
        mesh = e["mesh"] if os.path.isabs(e["mesh"]) else os.path.join(base, e["mesh"])
    bursts = e.get("bursts", [])
    if not all(isinstance(b, list) and len(b) == 2 for b in bursts):
        raise ConfigError(f"bursts must list [time, count] pairs, e.g. bursts = [[0.5, 100]], got {bursts!r}")
    builder.add_emitter(
        shape=e.get("shape", "mesh" if mesh is not None else "point"), center=e.get("center", (0.0, 0.0, 0.0)),
        half_extents=e.get("half_extents", (0.1, 0.1, 0.1)), mesh=mesh, rate=e.get("rate", 0.0), bursts=bursts,
        life=e["life"], velocity=e.get("velocity", (0.0, 0.0, 0.0)), spread=e.get("spread", 0.0),
        capacity=e.get("capacity"), mass=e.get("mass", 1.0e-3), radius=e.get("radius", 0.005), seed=e.get("seed", 0),
        name=e.get("name", "emitter"),
    )


def _add_soft_body(builder: ModelBuilder, body: dict, base: str) -> None:
    """A ``[[soft_body]]`` table (types checked); the mesh file's path is relative to the scene's folder."""
    mesh = body["mesh"] if os.path.isabs(body["mesh"]) else os.path.join(base, body["mesh"])
    soft = builder.add_soft_body(
        mesh, method=body.get("method", "voxel"), youngs_modulus=body["youngs_modulus"], density=body.get("density"),
        mass=body.get("mass"), spacing=body.get("spacing"), damping=body.get("damping", 0.0),
        origin=body.get("origin", (0.0, 0.0, 0.0)), rotation=_rotation(body), scale=body.get("scale", 1.0),
        velocity=body.get("velocity", (0.0, 0.0, 0.0)), radius=body.get("radius"),
        mass_distribution=body.get("mass_distribution", "volume"), skin_mass_factor=body.get("skin_mass_factor", 1.0),
        mass_gradient=body.get("mass_gradient", (0.0, 0.0, 0.0)), options=body.get("options"),
        name=body.get("name", "soft_body"), prim=body.get("prim"),
        plasticity=SpringPlasticity(**body["plasticity"]) if "plasticity" in body else None,
        volume=body.get("volume", False), bulk_modulus=body.get("bulk_modulus"),
        elasticity=body.get("elasticity", "springs"), poisson_ratio=body.get("poisson_ratio", 0.25),
    )
    if "pin" in body:
        placed = builder.particle_positions(soft.particles)
        inside = np.all((placed >= body["pin"]["min"]) & (placed <= body["pin"]["max"]), axis=1)
        if not inside.any():
            raise ConfigError(f"soft body {soft.name!r}: its pin box {body['pin']['min']} … {body['pin']['max']} [m] "
                              "holds none of its particles: widen the box (particles lie on the method's lattice)")
        builder.pin_particles(soft.particles[inside])


def _check_soft_body_pin(pin, where: str, label: str) -> None:
    """A soft body's ``pin = { min = [x, y, z], max = [x, y, z] }`` (types checked): both corners, min ≤ max."""
    if pin is None:
        return
    if "min" not in pin or "max" not in pin:
        raise ConfigError(f"{where}: {label}.pin needs min = [x, y, z] and max = [x, y, z], the corners [m] of the box "
                          "whose particles are pinned")
    if any(lo > hi for lo, hi in zip(pin["min"], pin["max"])):
        raise ConfigError(f"{where}: {label}.pin has min {pin['min']} above max {pin['max']} on some axis: swap them")


def _add_wind(builder: ModelBuilder, wind: dict, tracks: dict) -> None:
    """The ``[wind]`` table: aerodynamics on the named meshes (all by default), its inputs' first values, and
    their tracks."""
    start = {}
    for key, name in _WIND_INPUTS.items():
        if name in tracks:
            start[key] = tracks[name].values[0] if name == "wind" else float(tracks[name].values[0, 0])
        elif key in wind:
            start[key] = wind[key]
    builder.add_aerodynamics(
        meshes=wind.get("meshes"), drag=wind.get("drag", DEFAULT_DRAG), lift=wind.get("lift", DEFAULT_LIFT),
        wind=start.get("velocity", (0.0, 0.0, 0.0)), air_density=start.get("air_density", AIR_DENSITY),
        noise=start.get("noise", 0.0), noise_scale=wind.get("noise_scale", 1.0), seed=wind.get("seed", 0),
    )
    for name in _WIND_INPUTS.values():
        if name in tracks:
            builder.set_track(name, tracks[name])


def _export_options(out: dict, where: str) -> dict:
    """The ``[output]`` options passed to the USD writer as they are, their names and choices checked."""
    from .usd import PRIMVARS, PURPOSES  # (no pxr: the writer's module loads it only when it writes)

    options = {key: out[key] for key in ("primvars", "start_frame", "collider_purpose") if key in out}
    for name in options.get("primvars", []):
        if name not in PRIMVARS:
            raise ConfigError(f"{where}: output.primvars lists {name!r}: choose from {', '.join(map(repr, PRIMVARS))}")
    purpose = options.get("collider_purpose", "guide")
    if purpose not in PURPOSES:
        raise ConfigError(f"{where}: output.collider_purpose must be one of {', '.join(map(repr, PURPOSES))}, got "
                          f"{purpose!r}")
    return options


def _check_value(value, expected, where: str, key: str, *, version: int) -> None:
    if isinstance(expected, _Since):
        if version < expected.version:
            raise _needs(expected.version, where, f"[{key}]" if expected.spec is dict else key)
        _check_value(value, expected.spec, where, key, version=version)
        return
    if isinstance(expected, _PerWorld):
        vector = isinstance(expected.value, _Live) and expected.value.value is VECTOR
        if vector and isinstance(value, list) and value and all(NUMBER.accepts(v) for v in value):
            raise ConfigError(f"{where}: {key} must list one [x, y, z] per world, e.g. [[0, 0, -9.81], [0, 0, -1.62]], "
                              f"got {value!r}; for one value in every world, set it in [world]")
        if not isinstance(value, list):
            entry = "a value or a track table" if isinstance(expected.value, _Live) else "a number"
            raise ConfigError(f"{where}: {key} must be a list with one entry per world ({entry} each), got {value!r}")
        for i, entry in enumerate(value):
            _check_value(entry, expected.value, where, f"{key}[{i}]", version=version)
        return
    if isinstance(expected, _Live):
        if not isinstance(value, dict):
            _check_value(value, expected.value, where, key, version=version)
            return
        if version < expected.tracks_since:
            raise _needs(expected.tracks_since, where, f"{key} as a track table")
        expected = _Track(expected.value)
    if isinstance(expected, _Track):
        _check_track(value, expected, where, key, version=version)
        return
    if isinstance(expected, _Tables):
        tables = [value] if isinstance(value, dict) else value
        if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
            raise ConfigError(f"{where}: {key} must be a table or an array of tables [[{key}]], got {value!r}")
        for i, t in enumerate(tables):
            _check_table(t, expected.schema, where, _label(key, i, len(tables)), version=version)
        return
    if isinstance(expected, dict):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: {key} must be a table {{{', '.join(expected)}}}, got {value!r}")
        _check_table(value, expected, where, key, version=version)
        return
    if isinstance(expected, tuple) and any(isinstance(e, dict) for e in expected):
        if isinstance(value, dict):
            _check_table(value, next(e for e in expected if isinstance(e, dict)), where, key, version=version)
        elif not isinstance(value, bool):
            raise ConfigError(f"{where}: {key} must be a table {{ke = ..., kd = ...}}, true or false, got {value!r}")
        return
    if expected is VECTOR:
        ok = isinstance(value, list) and len(value) == 3 and all(NUMBER.accepts(v) for v in value)
        if not ok:
            raise ConfigError(f"{where}: {key} must be a list of 3 finite numbers [x, y, z], got {value!r}")
        return
    if expected is QUATERNION:
        ok = isinstance(value, list) and len(value) == 4 and all(NUMBER.accepts(v) for v in value) and any(value)
        if not ok:
            raise ConfigError(f"{where}: {key} must be a quaternion [x, y, z, w] of 4 finite numbers, not all zero "
                              f"(the identity is [0, 0, 0, 1]), got {value!r}")
        return
    if isinstance(expected, _Number):
        if not expected.accepts(value):
            raise ConfigError(f"{where}: {key} must be {expected.describe()}, got {value!r}")
        return
    types = expected if isinstance(expected, tuple) else (expected,)
    ok = isinstance(value, types) and not (isinstance(value, bool) and bool not in types)
    if not ok:
        names = " or ".join(_TYPE_NAMES.get(t, t.__name__) for t in types)
        raise ConfigError(f"{where}: {key} must be {names}, got {value!r}")


def _check_track(table, spec: _Track, where: str, key: str, *, version: int) -> None:
    """Check a track table's keys, key counts and every value (the ordering of its times: _make_track)."""
    schema, values = (_ROTATION_TRACK_TABLE, "degrees") if spec.rotation else (_TRACK_TABLE, "values")
    shape = (f"{{ times = [...], axis = [x, y, z], {values} = [...] }}" if spec.rotation
             else f"{{ times = [...], {values} = [...] }}")
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: {key} must be a track table {shape}, got {table!r}")
    _check_table(table, schema, where, key, version=version)
    missing = [k for k in schema if k not in table and k not in ("interpolation", "extrapolation")]
    if missing:
        raise ConfigError(f"{where}: track {key} needs {shape}; missing: {', '.join(missing)}")
    times = table["times"]
    if not times:
        raise ConfigError(f"{where}: {key}.times is empty: give at least one key time [s]")
    for i, t in enumerate(times):
        _check_value(t, NUMBER, where, f"{key}.times[{i}]", version=version)
    if len(table[values]) != len(times):
        raise ConfigError(f"{where}: track {key} has {len(times)} times but {len(table[values])} {values}: give "
                          f"one per time")
    for i, v in enumerate(table[values]):
        _check_value(v, NUMBER if spec.rotation else spec.value, where, f"{key}.{values}[{i}]", version=version)
    for option, names in (("interpolation", INTERPOLATIONS), ("extrapolation", EXTRAPOLATIONS)):
        if option in table and table[option] not in names:
            raise ConfigError(f"{where}: {key}.{option} must be one of {', '.join(names)}, got {table[option]!r}")


def _make_track(table: dict, where: str, key: str, *, rotation: bool = False) -> Track:
    """A checked track table as a :class:`Track` (which checks that the times increase); ``rotation``: a
    rotation track ``{ times, axis, degrees }``."""
    options = dict(interpolation=table.get("interpolation", "linear"), extrapolation=table.get("extrapolation", "hold"))
    try:
        if rotation:
            return Track.rotation(table["times"], axis=table["axis"], degrees=table["degrees"], **options)
        return Track(table["times"], table["values"], **options)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {key}: {_one_line(exc)}") from None


# -- building ---------------------------------------------------------------------------------------------


def _springs(cloth: dict, key: str, default: SpringMaterial) -> SpringMaterial | None:
    spec = cloth.get(key, True)
    if spec is False:
        return None
    if spec is True:
        return default
    return SpringMaterial(ke=spec.get("ke", default.ke), kd=spec.get("kd", default.kd),
                          **spring_law_options(key, spec))


def _rotation(cloth: dict):
    rot = cloth.get("rotation")
    if rot is None:
        return (0.0, 0.0, 0.0, 1.0)
    return quat_from_axis_angle(rot.get("axis", [1.0, 0.0, 0.0]), math.radians(rot.get("degrees", 0.0)))


def _add_cloth(builder: ModelBuilder, cloth: dict, base: str) -> None:
    common = dict(
        origin=cloth.get("origin", (0.0, 0.0, 0.0)),
        rotation=_rotation(cloth),
        velocity=cloth.get("velocity", (0.0, 0.0, 0.0)),
        radius=cloth.get("radius"),
        structural=_springs(cloth, "structural", DEFAULT_STRUCTURAL),
        bend=_springs(cloth, "bend", DEFAULT_BEND),
        pin=cloth.get("pin", []),
        name=cloth.get("name", "cloth"),
        mass=cloth.get("mass"),
    )
    if "grid" in cloth:
        g = cloth["grid"]
        ids = builder.add_cloth_grid(
            nx=g["nx"],
            ny=g["ny"],
            spacing=g["spacing"],
            particle_mass=cloth.get("particle_mass"),
            shear=_springs(cloth, "shear", DEFAULT_SHEAR),
            **common,
        )
    else:
        mesh = cloth["mesh"]
        path = mesh if os.path.isabs(mesh) else os.path.join(base, mesh)
        try:
            ids = builder.add_cloth_mesh(path, scale=cloth.get("scale", 1.0), density=cloth.get("density"),
                                         prim=cloth.get("prim"), **common)
        except ConfigError as exc:  # name the mesh file in every message about its contents
            raise exc if path in str(exc) else ConfigError(f"mesh {path}: {exc}") from None
    groups = cloth.get("pin_group", [])
    for i, group in enumerate(groups):
        try:
            builder.add_pin_group(_group_particles(ids, group.pin), translation=group.translation,
                                  rotation=group.rotation, pivot=group.pivot, name=group.name)
        except ConfigError as exc:
            raise ConfigError(f"{_label('pin_group', i, len(groups))}: {exc}") from None
    handles = cloth.get("handle", [])
    for i, handle in enumerate(handles):
        try:
            builder.add_handle(_group_particles(ids, handle.particles), kp=handle.kp, kd=handle.kd,
                               max_force=handle.max_force, translation=handle.translation, rotation=handle.rotation,
                               pivot=handle.pivot, name=handle.name)
        except ConfigError as exc:
            raise ConfigError(f"{_label('handle', i, len(handles))}: {exc}") from None


def _group_particles(ids: np.ndarray, pin: list) -> np.ndarray:
    """The global indices of the particles a pin group names: ``ids`` are a grid cloth's, shape [ny, nx]
    (corner/edge names or indices r·nx + c), or a mesh cloth's, shape [v] (vertex indices)."""
    if ids.ndim == 2:
        ny, nx = ids.shape
        return ids.ravel()[ModelBuilder._grid_pins(pin, nx, ny)]
    index = np.asarray(pin, dtype=np.int64)
    bad = index[(index < 0) | (index >= len(ids))]
    if len(bad):
        raise ConfigError(f"pin vertex index {int(bad[0])} is out of range: the mesh has {len(ids)} vertices "
                          f"(0..{len(ids) - 1})")
    return ids[index]


def _add_collider(builder: ModelBuilder, c: dict, base: str = "") -> None:
    kind = c["type"]
    common = dict(friction=c.get("friction", 0.5), restitution=c.get("restitution", 0.0), name=c.get("name", kind))
    if kind == "ground":
        builder.add_ground_plane(height=c.get("height", 0.0), **common)
        return
    common.update(translation=c.get("translation"), rotation=c.get("rotation"))
    common.update({key: c[key] for key in ("thickness", "static_friction") if key in c})
    if kind == "mesh":
        path = c["file"] if os.path.isabs(c["file"]) else os.path.join(base, c["file"])
        builder.add_collider_mesh(path, prim=c.get("prim"), center=c.get("center", (0.0, 0.0, 0.0)),
                                  orientation=c.get("orientation", (0.0, 0.0, 0.0, 1.0)), scale=c.get("scale", 1.0),
                                  sides=c.get("sides", "closed"), deforming=c.get("deforming", False),
                                  depth=c.get("depth"), winding_number=c.get("winding_number", False), **common)
        return
    if kind == "plane":
        builder.add_collider_plane(point=c.get("point", (0.0, 0.0, 0.0)), normal=c.get("normal"), **common)
    elif kind == "sphere":
        builder.add_collider_sphere(center=c["center"], radius=c["radius"], **common)
    elif kind == "box":
        builder.add_collider_box(center=c["center"], half_extents=c["half_extents"],
                                 orientation=c.get("orientation", (0.0, 0.0, 0.0, 1.0)), **common)
    else:
        builder.add_collider_capsule(center=c["center"], radius=c["radius"], half_height=c["half_height"],
                                     orientation=c.get("orientation", (0.0, 0.0, 0.0, 1.0)), **common)
