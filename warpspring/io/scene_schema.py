"""The scene file format: the tables and keys a scene file (TOML: cloth, materials, pins, colliders, gravity,
integrator and output) may hold, the type of each value, the scene format versions and renamed keys.
Declarations only: :mod:`~warpspring.io.scene_checks` checks a parsed file against them, and
:func:`~warpspring.io.scene.load_scene` reads one. See the scene-file reference (docs/scenes.md), or
``examples/*.toml``.

Scene files are versioned: a top-level ``version = 2`` declares the format (:data:`SCENE_FORMAT_VERSION`);
a file without it is format 1, and every format-1 file still reads as before. Format 2 adds keyframe
tracks wherever a live input takes a value (``[world] gravity = { times = [...], values = [...] }``),
pin groups moved by tracks (``[[cloth.pin_group]]``), and renames ``[guard] max_strain`` to
``tear_strain``. A renamed key is still read under its old name, with a
:class:`~warpspring.io.scene.DeprecatedKeyWarning` (renames are listed in ``RENAMED_KEYS``, one line each).

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
particle spacing cannot slip between particles; default: on where a sphere or capsule is too thin for particle
contacts to hold the cloth, by the rule of ``core/builder/colliders.py``, which the run summary states; false
switches them off) and ``swept`` (false: particles' paths over
a step are not swept against spheres, boxes, capsules and meshes; default true).
The new collider types and keys (box, capsule, restitution, orientation, tracks) need format 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..core.tracks import Track

PRECISIONS = ("float32", "float64")
COLLIDER_TYPES = ("ground", "plane", "sphere", "box", "capsule", "mesh")

#: The scene format this warpspring reads (and every older one): a file's top-level ``version``.
SCENE_FORMAT_VERSION = 2


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


# -- schema: key -> expected type -------------------------------------------------------------------------
# A value spec is a Python type (str, bool, list, dict), a Number, VECTOR, QUATERNION, a nested schema dict, a
# tuple of alternatives (bool or a nested schema: a spring family given as a table or as true/false), a Live
# input (a constant, or a track table), a TrackTable table, Tables (a table or an array of tables), or Since (a
# key that a later scene format introduced).


@dataclass(frozen=True)
class Number:
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
class CountOrAuto(Number):
    """An integer ≥ ``minimum``, or the string "auto" (chosen before the run)."""

    def describe(self) -> str:
        return super().describe() + ' or "auto"'

    def accepts(self, value) -> bool:
        return value == "auto" or super().accepts(value)


#: ``[simulation] substeps``: a count, or "auto" (the default: ``analysis/step_choice.py``).
SUBSTEPS = CountOrAuto(1, integer=True)


@dataclass(frozen=True)
class TrackTable:
    """A track table: ``{ times, values, interpolation, extrapolation }`` with each value fitting ``value``
    (a value spec); or, with ``rotation``, ``{ times, axis, degrees, interpolation, extrapolation }``."""

    value: object = None
    rotation: bool = False


@dataclass(frozen=True)
class Live:
    """A live input of the model: a constant fitting ``value``, or (from scene format ``tracks_since`` on) a
    track table of such values."""

    value: object
    tracks_since: int = 2


@dataclass(frozen=True)
class Tables:
    """A table or an array of tables, each of ``schema``."""

    schema: dict


@dataclass(frozen=True)
class Since:
    """A key the scene format ``version`` introduced (a file of an older format must declare it)."""

    version: int
    spec: object


@dataclass(frozen=True)
class PerWorld:
    """A list of one entry per world, each fitting ``value`` (its length is checked against ``[worlds]
    count`` once the whole table is read)."""

    value: object


@dataclass(frozen=True)
class Rename:
    """A key that scene format ``version`` renamed from ``old`` to ``new`` in the table(s) at ``table`` (a
    dotted path; each element of an array of tables). The old name is still read, with a deprecation."""

    table: str
    old: str
    new: str
    version: int
    note: str = ""


#: Renamed keys, oldest first: a rename is one line here (the schema knows the new name only).
RENAMED_KEYS = (
    Rename("guard", "max_strain", "tear_strain", 2,
           "the strain at which a spring counts as torn and the run stops; [stabilizers] max_strain is the "
           "strain limit"),
)

NUMBER = Number()
NON_NEGATIVE = Number(0.0)
POSITIVE = Number(0.0, inclusive=False)
VECTOR = "vector"  # a list of 3 finite numbers
QUATERNION = "quaternion"  # a list of 4 finite numbers (x, y, z, w), not all zero

TYPE_NAMES = {str: "a string", bool: "true or false", list: "a list", dict: "a table"}

_SPRING = {"ke": NON_NEGATIVE, "kd": NON_NEGATIVE,
           # The law and plasticity (warpspring.SpringMaterial, SpringPlasticity):
           "law": str, "compression_ke": NON_NEGATIVE, "yield_strain": POSITIVE, "yield_force": POSITIVE,
           "yield_rate": POSITIVE, "hardening": NON_NEGATIVE, "break_strain": POSITIVE}
TRACK_TABLE = {"times": list, "values": list, "interpolation": str, "extrapolation": str}
ROTATION_TRACK_TABLE = {"times": list, "axis": VECTOR, "degrees": list, "interpolation": str, "extrapolation": str}
_RIGID_MOTION = {"pivot": VECTOR, "translation": TrackTable(VECTOR), "rotation": TrackTable(rotation=True)}
_PIN_GROUP = {"pin": list, "name": str, **_RIGID_MOTION}
_HANDLE = {"particles": list, "kp": POSITIVE, "kd": NON_NEGATIVE, "max_force": POSITIVE, "name": str, **_RIGID_MOTION}
EMITTER = {
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
    "capacity": Number(1, integer=True),
    "mass": POSITIVE,
    "radius": NON_NEGATIVE,
    "seed": Number(0, integer=True),
}
#: A ``[[soft_body]]`` table: ModelBuilder.add_soft_body's arguments (mesh and youngs_modulus required, density
#: or mass; ``options`` the method's own, checked by the builder).
SOFT_BODY = {
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
    "element": str,  # "tet4" or "tet10": linear or quadratic tets carry the neohookean material
}
SCHEMA = {
    "simulation": {
        "fps": POSITIVE,
        "frames": Number(1, integer=True),
        "substeps": SUBSTEPS,
        "integrator": str,
        "precision": str,
        "device": str,
        "integrator_options": dict,
    },
    "world": {"up_axis": str, "gravity": Live(VECTOR), "drag": Live(NON_NEGATIVE)},
    "cloth": {
        "name": str,
        "grid": {"nx": Number(2, integer=True), "ny": Number(2, integer=True), "spacing": POSITIVE},
        "mesh": str,
        "prim": Since(2, str),
        "scale": POSITIVE,
        "origin": VECTOR,
        "rotation": {"axis": VECTOR, "degrees": NUMBER},
        "mass": POSITIVE,
        "particle_mass": POSITIVE,
        "density": POSITIVE,
        "radius": NON_NEGATIVE,
        "velocity": VECTOR,
        "pin": list,
        "pin_group": Since(2, Tables(_PIN_GROUP)),
        "handle": Since(2, Tables(_HANDLE)),
        "structural": (bool, _SPRING),
        "shear": (bool, _SPRING),
        "bend": (bool, _SPRING),
        # A preset's name or {stretch, shear, bending, density, ...} (ClothMaterial); without it and without
        # springs, DEFAULT_CLOTH at the table's mass (io/scene_build.py).
        "material": Since(2, (str, dict)),
    },
    "collider": {
        "type": str,
        "name": str,
        "point": VECTOR,
        "normal": VECTOR,
        "height": NUMBER,
        "center": VECTOR,
        "radius": POSITIVE,
        "half_extents": Since(2, VECTOR),
        "half_height": Since(2, NON_NEGATIVE),
        "orientation": Since(2, QUATERNION),
        "friction": NON_NEGATIVE,
        "restitution": Since(2, NON_NEGATIVE),
        "translation": Since(2, TrackTable(VECTOR)),
        "rotation": Since(2, TrackTable(rotation=True)),
        "file": Since(2, str),
        "prim": Since(2, str),
        "scale": Since(2, POSITIVE),
        "sides": Since(2, str),
        "deforming": Since(2, bool),
        "depth": Since(2, POSITIVE),
        "winding_number": Since(2, bool),
        "thickness": Since(2, NON_NEGATIVE),
        "static_friction": Since(2, NON_NEGATIVE),
    },
    "contacts": {"stage": bool, "slots": Number(1, integer=True), "triangles": Since(2, bool),
                 "swept": Since(2, bool)},
    "output": {
        "path": str,
        "particles": bool,
        "springs": bool,
        "world": Since(2, Number(0, integer=True)),
        "world_spacing": Since(2, NON_NEGATIVE),
        "world_columns": Since(2, Number(1, integer=True)),
        "primvars": Since(2, list),
        "start_frame": Since(2, Number(0, integer=True)),
        "collider_purpose": Since(2, str),
    },
    "stabilizers": {
        "max_spring_force": Live(POSITIVE),
        "max_particle_force": Live(POSITIVE),
        "max_speed": Live(POSITIVE),
        "max_strain": Live(POSITIVE),
        "strain_iterations": Number(1, integer=True),
        "biphasic_strain": Live(POSITIVE),
        "biphasic_ratio": Live(Number(1.0)),
    },
    "guard": {
        "every": Number(1, integer=True),
        "tear_strain": POSITIVE,
        "max_kinetic_energy": POSITIVE,
        "energy_balance": NON_NEGATIVE,
        "dissipation": Since(2, bool),
        "stop": Since(2, str),
        "check_frames": Number(1, integer=True),
    },
    "wind": {
        "velocity": Live(VECTOR),
        "air_density": Live(POSITIVE),
        "noise": Live(NON_NEGATIVE),
        "noise_scale": POSITIVE,
        "seed": Number(0, integer=True),
        "drag": NON_NEGATIVE,
        "lift": NON_NEGATIVE,
        "meshes": list,
    },
    "worlds": {
        "count": Number(1, integer=True),
        "gravity": PerWorld(Live(VECTOR)),
        "wind": PerWorld(Live(VECTOR)),
        "air_density": PerWorld(Live(POSITIVE)),
        "wind_noise": PerWorld(Live(NON_NEGATIVE)),
        "drag": PerWorld(Live(NON_NEGATIVE)),
        "max_spring_force": PerWorld(Live(POSITIVE)),
        "max_particle_force": PerWorld(Live(POSITIVE)),
        "max_speed": PerWorld(Live(POSITIVE)),
        "max_strain": PerWorld(Live(POSITIVE)),
        "biphasic_strain": PerWorld(Live(POSITIVE)),
        "biphasic_ratio": PerWorld(Live(Number(1.0))),
        "stiffness_scale": PerWorld(NON_NEGATIVE),
        "damping_scale": PerWorld(NON_NEGATIVE),
        "mass_scale": PerWorld(POSITIVE),
    },
}
TOP_LEVEL = {"version": Number(1, integer=True), **{k: (dict, list) if k in ("cloth", "collider") else dict
                                                    for k in SCHEMA}, "worlds": Since(2, dict),
             "wind": Since(2, dict), "emitter": Since(2, (dict, list)),
             "soft_body": Since(2, (dict, list)),
             "contacts": Since(2, dict)}
#: [self_collision]: the surfaces' layers kept apart (ModelBuilder.add_self_collision), from format 2 on.
SCHEMA["self_collision"] = {"thickness": POSITIVE, "friction": NON_NEGATIVE, "relaxation": POSITIVE, "meshes": list}
TOP_LEVEL["self_collision"] = Since(2, dict)
#: How the run-time guard may stop: the whole run, or only the world that failed ([guard] stop).
GUARD_STOPS = ("run", "world")
#: The tables holding live inputs (each may be a track table from format 2 on).
LIVE_TABLES = ("world", "stabilizers")
#: The live inputs of the [wind] table: its key -> the model's input name.
WIND_INPUTS = {"velocity": "wind", "air_density": "air_density", "noise": "wind_noise"}

# Keys that apply to one kind of cloth or collider only (anything else would be silently ignored).
GRID_ONLY = {"grid", "particle_mass", "shear"}
MESH_ONLY = {"mesh", "density", "scale", "prim"}
_COLLIDER_COMMON = {"type", "name", "friction", "restitution"}
_COLLIDER_MOTION = {"translation", "rotation"}
COLLIDER_KEYS = {
    "ground": _COLLIDER_COMMON | {"height"},
    "plane": _COLLIDER_COMMON | _COLLIDER_MOTION | {"point", "normal"},
    "sphere": _COLLIDER_COMMON | _COLLIDER_MOTION | {"center", "radius"},
    "box": _COLLIDER_COMMON | _COLLIDER_MOTION | {"center", "half_extents", "orientation"},
    "capsule": _COLLIDER_COMMON | _COLLIDER_MOTION | {"center", "radius", "half_height", "orientation"},
}
# The keys each collider type needs, and how its error shows them.
COLLIDER_NEEDS = {
    "sphere": ({"center", "radius"}, "center = [x, y, z] and radius"),
    "box": ({"center", "half_extents"}, "center = [x, y, z] and half_extents = [hx, hy, hz]"),
    "capsule": ({"center", "radius", "half_height"}, "center = [x, y, z], radius and half_height"),
}
# Mesh colliders (format 2), and a thickness and static friction on every collider but the ground.
COLLIDER_KEYS["mesh"] = _COLLIDER_COMMON | _COLLIDER_MOTION | {
    "file", "prim", "center", "orientation", "scale", "sides", "deforming", "depth", "winding_number"}
for _kind in ("plane", "sphere", "box", "capsule", "mesh"):
    COLLIDER_KEYS[_kind] = COLLIDER_KEYS[_kind] | {"thickness", "static_friction"}
COLLIDER_NEEDS["mesh"] = ({"file"}, 'file = "path" (any mesh file trimesh reads, or USD with prim = "/path")')
#: The collider types a scene of format 1 may use (the others came with format 2).
FORMAT_1_COLLIDERS = ("ground", "plane", "sphere")
