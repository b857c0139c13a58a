"""Scene files: a TOML description of cloth, materials, pins, colliders, gravity, integrator and output.

Every key is checked: an unknown key, a wrong type or a bad value is a :class:`ConfigError` naming the
file, the table and the key. See the README's scene-file reference, or ``examples/*.toml``.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field

from ..core.builder import DEFAULT_BEND, DEFAULT_SHEAR, DEFAULT_STRUCTURAL, ModelBuilder, SpringMaterial
from ..errors import ConfigError
from ..core.guards import GuardLimits
from ..core.integrators import INTEGRATORS
from ..core.model import Stabilizers
from ..core.transforms import quat_from_axis_angle

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

PRECISIONS = ("float32", "float64")
COLLIDER_TYPES = ("ground", "plane", "sphere")


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
        world: the ``[world]`` table (up_axis, gravity, drag).
        cloths: the ``[cloth]`` tables, checked.
        colliders: the ``[[collider]]`` tables, checked.
        stabilizers: the ``[stabilizers]`` table (clamps, strain limiting, biphasic springs).
        guard: the ``[guard]`` table (run-time checks).
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
    world: dict = field(default_factory=dict)
    cloths: list = field(default_factory=list)
    colliders: list = field(default_factory=list)
    stabilizers: Stabilizers = field(default_factory=Stabilizers)
    guard: GuardLimits = field(default_factory=GuardLimits)

    def builder(self) -> ModelBuilder:
        """A ModelBuilder holding the scene's cloth and colliders.

        Raises:
            ConfigError: a value the builder rejects (e.g. a mesh file that is missing or holds NaN),
                prefixed with the scene file and the table.
        """
        where = os.path.basename(self.path)
        world = self.world
        with _context(where, "world"):
            builder = ModelBuilder(
                up_axis=world.get("up_axis", "Z"),
                gravity=world.get("gravity"),
                drag=world.get("drag", 0.0),
                stabilizers=self.stabilizers,
            )
        for i, cloth in enumerate(self.cloths):
            with _context(where, _label("cloth", i, len(self.cloths))):
                _add_cloth(builder, cloth, os.path.dirname(self.path))
        for i, collider in enumerate(self.colliders):
            with _context(where, _label("collider", i, len(self.colliders))):
                _add_collider(builder, collider)
        return builder


# -- schema: key -> expected type -------------------------------------------------------------------------
# A value spec is a Python type (str, bool, list, dict), a _Number, VECTOR, a nested schema dict, or a
# tuple of alternatives (bool or a nested schema: a spring family given as a table or as true/false).


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


NUMBER = _Number()
NON_NEGATIVE = _Number(0.0)
POSITIVE = _Number(0.0, inclusive=False)
VECTOR = "vector"  # a list of 3 finite numbers

_TYPE_NAMES = {str: "a string", bool: "true or false", list: "a list", dict: "a table"}

_SPRING = {"ke": NON_NEGATIVE, "kd": NON_NEGATIVE}
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
    "world": {"up_axis": str, "gravity": VECTOR, "drag": NON_NEGATIVE},
    "cloth": {
        "name": str,
        "grid": {"nx": _Number(2, integer=True), "ny": _Number(2, integer=True), "spacing": POSITIVE},
        "mesh": str,
        "scale": POSITIVE,
        "origin": VECTOR,
        "rotation": {"axis": VECTOR, "degrees": NUMBER},
        "mass": POSITIVE,
        "particle_mass": POSITIVE,
        "density": POSITIVE,
        "radius": NON_NEGATIVE,
        "velocity": VECTOR,
        "pin": list,
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
        "friction": NON_NEGATIVE,
    },
    "output": {"path": str, "particles": bool, "springs": bool},
    "stabilizers": {
        "max_spring_force": POSITIVE,
        "max_particle_force": POSITIVE,
        "max_speed": POSITIVE,
        "max_strain": POSITIVE,
        "strain_iterations": _Number(1, integer=True),
        "biphasic_strain": POSITIVE,
        "biphasic_ratio": _Number(1.0),
    },
    "guard": {"every": _Number(1, integer=True), "max_strain": POSITIVE, "max_kinetic_energy": POSITIVE},
}

# Keys that apply to one kind of cloth or collider only (anything else would be silently ignored).
_GRID_ONLY = {"grid", "particle_mass", "shear"}
_MESH_ONLY = {"mesh", "density", "scale"}
_COLLIDER_KEYS = {
    "ground": {"type", "name", "height", "friction"},
    "plane": {"type", "name", "point", "normal", "friction"},
    "sphere": {"type", "name", "center", "radius", "friction"},
}


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and check a scene file.

    Raises:
        ConfigError: the file is missing or unreadable, not valid TOML, or breaks the schema.
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
    return parse_scene(data, path=path)


def parse_scene(data: dict, *, path: str = "<scene>") -> Scene:
    """Check a scene given as a dict (the parsed TOML) and return it as a :class:`Scene`.

    Raises:
        ConfigError: naming the file, the table and the key that is unknown, of the wrong type or out of range.
    """
    where = os.path.basename(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: a scene must be a table of tables, got {type(data).__name__}")
    _check_table(data, {k: (dict, list) if k in ("cloth", "collider") else dict for k in _SCHEMA}, where, "")
    for name in ("simulation", "world", "output", "stabilizers", "guard"):
        _check_table(data.get(name, {}), _SCHEMA[name], where, name)
    cloths = _table_list(data.get("cloth", []), where, "cloth")
    colliders = _table_list(data.get("collider", []), where, "collider")
    if not cloths:
        raise ConfigError(f"{where}: the scene has no [cloth] table: add one with grid = {{...}} or mesh = '...'")
    for i, c in enumerate(cloths):
        _check_cloth(c, where, _label("cloth", i, len(cloths)))
    for i, c in enumerate(colliders):
        _check_collider(c, where, _label("collider", i, len(colliders)))

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

    scene = Scene(path=path, world=data.get("world", {}), cloths=cloths, colliders=colliders)
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
    scene.stabilizers = Stabilizers(**data.get("stabilizers", {}))
    scene.guard = GuardLimits(**data.get("guard", {}))
    check_run_settings(fps=scene.fps, frames=scene.frames, substeps=scene.substeps, where=where)
    return scene


def check_run_settings(*, fps, frames, substeps, where: str = "options") -> None:
    """Raise ConfigError unless fps > 0, frames ≥ 1 and substeps ≥ 1 (so that dt = 1 / (fps · substeps) > 0)."""
    if not (POSITIVE.accepts(fps)):
        raise ConfigError(f"{where}: fps must be a finite number > 0 (dt = 1 / (fps * substeps)), got {fps!r}")
    if not _Number(1, integer=True).accepts(frames):
        raise ConfigError(f"{where}: frames must be an integer >= 1, got {frames!r}")
    if not _Number(1, integer=True).accepts(substeps):
        raise ConfigError(f"{where}: substeps must be an integer >= 1 (dt = 1 / (fps * substeps)), got {substeps!r}")


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


def _check_cloth(c: dict, where: str, label: str) -> None:
    _check_table(c, _SCHEMA["cloth"], where, label)
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
    for p in c.get("pin", []):
        ok = isinstance(p, int) and not isinstance(p, bool)
        if grid:
            ok = ok or isinstance(p, str)
        if not ok:
            kinds = "corner/edge names or particle indices" if grid else "vertex indices (names are for grid cloths)"
            raise ConfigError(f"{where}: {label}.pin takes {kinds}, got {p!r}")


def _check_collider(c: dict, where: str, label: str) -> None:
    _check_table(c, _SCHEMA["collider"], where, label)
    kind = c.get("type")
    if kind is None:
        raise ConfigError(f"{where}: {label}.type is missing: set type = one of {', '.join(COLLIDER_TYPES)}")
    if kind not in COLLIDER_TYPES:
        raise ConfigError(f"{where}: {label}.type must be one of {', '.join(COLLIDER_TYPES)}, got {kind!r}")
    extra = sorted(set(c) - _COLLIDER_KEYS[kind])
    if extra:
        raise ConfigError(
            f"{where}: {label}.{extra[0]} does not apply to a {kind} collider; "
            f"it takes: {', '.join(sorted(_COLLIDER_KEYS[kind] - {'type'}))}"
        )
    if kind == "sphere" and not {"center", "radius"} <= set(c):
        raise ConfigError(f"{where}: a sphere collider ([{label}]) needs center = [x, y, z] and radius")


def _check_table(table: dict, schema: dict, where: str, name: str) -> None:
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: [{name}] must be a table")
    for key, value in table.items():
        if key not in schema:
            raise ConfigError(
                f"{where}: unknown key {key!r} in [{name or 'top level'}]; allowed: {', '.join(schema)}"
            )
        _check_value(value, schema[key], where, f"{name}.{key}" if name else key)


def _check_value(value, expected, where: str, key: str) -> None:
    if isinstance(expected, dict):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: {key} must be a table {{{', '.join(expected)}}}, got {value!r}")
        _check_table(value, expected, where, key)
        return
    if isinstance(expected, tuple) and any(isinstance(e, dict) for e in expected):
        if isinstance(value, dict):
            _check_table(value, next(e for e in expected if isinstance(e, dict)), where, key)
        elif not isinstance(value, bool):
            raise ConfigError(f"{where}: {key} must be a table {{ke = ..., kd = ...}}, true or false, got {value!r}")
        return
    if expected is VECTOR:
        ok = isinstance(value, list) and len(value) == 3 and all(NUMBER.accepts(v) for v in value)
        if not ok:
            raise ConfigError(f"{where}: {key} must be a list of 3 finite numbers [x, y, z], got {value!r}")
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


# -- building ---------------------------------------------------------------------------------------------


def _springs(cloth: dict, key: str, default: SpringMaterial) -> SpringMaterial | None:
    spec = cloth.get(key, True)
    if spec is False:
        return None
    if spec is True:
        return default
    return SpringMaterial(ke=spec.get("ke", default.ke), kd=spec.get("kd", default.kd))


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
        builder.add_cloth_grid(
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
            builder.add_cloth_mesh(path, scale=cloth.get("scale", 1.0), density=cloth.get("density"), **common)
        except ConfigError as exc:  # name the mesh file in every message about its contents
            raise exc if path in str(exc) else ConfigError(f"mesh {path}: {exc}") from None


def _add_collider(builder: ModelBuilder, c: dict) -> None:
    friction = c.get("friction", 0.5)
    if c["type"] == "ground":
        builder.add_ground_plane(height=c.get("height", 0.0), friction=friction, name=c.get("name", "ground"))
    elif c["type"] == "plane":
        builder.add_collider_plane(
            point=c.get("point", (0.0, 0.0, 0.0)),
            normal=c.get("normal"),
            friction=friction,
            name=c.get("name", "plane"),
        )
    else:
        builder.add_collider_sphere(
            center=c["center"], radius=c["radius"], friction=friction, name=c.get("name", "sphere")
        )
