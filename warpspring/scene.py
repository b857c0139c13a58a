"""Scene files: a TOML description of cloth, materials, pins, colliders, gravity, integrator and output.

Every key is checked: an unknown key, a wrong type or a bad value is a :class:`ConfigError` naming the
file, the table and the key. See the README's scene-file reference, or ``examples/*.toml``.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field

from .builder import DEFAULT_BEND, DEFAULT_SHEAR, DEFAULT_STRUCTURAL, ModelBuilder, SpringMaterial
from .errors import ConfigError
from .transforms import quat_from_axis_angle

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

NUMBER = (int, float)
VECTOR = "vector"  # a list of 3 numbers
_ANY = object()


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

    def builder(self) -> ModelBuilder:
        """A ModelBuilder holding the scene's cloth and colliders."""
        world = self.world
        builder = ModelBuilder(
            up_axis=world.get("up_axis", "Z"), gravity=world.get("gravity"), drag=world.get("drag", 0.0)
        )
        for cloth in self.cloths:
            _add_cloth(builder, cloth, os.path.dirname(self.path))
        for collider in self.colliders:
            _add_collider(builder, collider)
        return builder


# -- schema: key -> expected type (a type, a tuple of types, VECTOR, or a nested schema dict) ---------------

_SPRING = {"ke": NUMBER, "kd": NUMBER}
_SCHEMA = {
    "simulation": {
        "fps": NUMBER,
        "frames": int,
        "substeps": int,
        "integrator": str,
        "precision": str,
        "device": str,
        "integrator_options": _ANY,
    },
    "world": {"up_axis": str, "gravity": VECTOR, "drag": NUMBER},
    "cloth": {
        "name": str,
        "grid": {"nx": int, "ny": int, "spacing": NUMBER},
        "mesh": str,
        "scale": NUMBER,
        "origin": VECTOR,
        "rotation": {"axis": VECTOR, "degrees": NUMBER},
        "mass": NUMBER,
        "particle_mass": NUMBER,
        "density": NUMBER,
        "radius": NUMBER,
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
        "radius": NUMBER,
        "friction": NUMBER,
    },
    "output": {"path": str, "particles": bool, "springs": bool},
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
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read: {exc}") from None
    return parse_scene(data, path=path)


def parse_scene(data: dict, *, path: str = "<scene>") -> Scene:
    """Check a scene given as a dict (the parsed TOML) and return it as a :class:`Scene`."""
    where = os.path.basename(path)
    _check_table(data, {k: (dict, list) if k in ("cloth", "collider") else dict for k in _SCHEMA}, where, "")
    for name in ("simulation", "world", "output"):
        _check_table(data.get(name, {}), _SCHEMA[name], where, name)
    cloths = _table_list(data.get("cloth", []), where, "cloth")
    colliders = _table_list(data.get("collider", []), where, "collider")
    if not cloths:
        raise ConfigError(f"{where}: the scene has no [cloth] table: add one with grid = {{...}} or mesh = '...'")
    for c in cloths:
        _check_table(c, _SCHEMA["cloth"], where, "cloth")
        if ("grid" in c) == ("mesh" in c):
            raise ConfigError(f"{where}: [cloth] needs exactly one of grid = {{nx, ny, spacing}} or mesh = 'file'")
        if "grid" in c and not {"nx", "ny", "spacing"} <= set(c["grid"]):
            raise ConfigError(f"{where}: [cloth] grid needs nx, ny and spacing")
    for c in colliders:
        _check_table(c, _SCHEMA["collider"], where, "collider")
        kind = c.get("type")
        if kind not in ("plane", "ground", "sphere"):
            raise ConfigError(f"{where}: [[collider]] type must be 'ground', 'plane' or 'sphere', got {kind!r}")
        if kind == "sphere" and not {"center", "radius"} <= set(c):
            raise ConfigError(f"{where}: a sphere collider needs center = [x, y, z] and radius")

    sim, out = data.get("simulation", {}), data.get("output", {})
    scene = Scene(path=path, world=data.get("world", {}), cloths=cloths, colliders=colliders)
    scene.fps = float(sim.get("fps", scene.fps))
    scene.frames = sim.get("frames", scene.frames)
    scene.substeps = sim.get("substeps", scene.substeps)
    scene.integrator = sim.get("integrator", scene.integrator)
    scene.integrator_options = dict(sim.get("integrator_options", {}))
    scene.precision = sim.get("precision", scene.precision)
    scene.device = sim.get("device")
    scene.output = out.get("path")
    scene.export_particles = out.get("particles", False)
    scene.export_springs = out.get("springs", False)
    check_run_settings(fps=scene.fps, frames=scene.frames, substeps=scene.substeps, where=where)
    return scene


def check_run_settings(*, fps, frames, substeps, where: str = "options") -> None:
    """Raise ConfigError unless fps > 0, frames ≥ 1 and substeps ≥ 1."""
    if not (isinstance(fps, NUMBER) and math.isfinite(fps) and fps > 0):
        raise ConfigError(f"{where}: fps must be a number > 0, got {fps!r}")
    if not (isinstance(frames, int) and frames >= 1):
        raise ConfigError(f"{where}: frames must be an integer >= 1, got {frames!r}")
    if not (isinstance(substeps, int) and substeps >= 1):
        raise ConfigError(f"{where}: substeps must be an integer >= 1 (the step is 1 / (fps * substeps)), got {substeps!r}")


# -- checking ---------------------------------------------------------------------------------------------


def _table_list(value, where: str, name: str) -> list:
    tables = [value] if isinstance(value, dict) else list(value)
    for t in tables:
        if not isinstance(t, dict):
            raise ConfigError(f"{where}: [{name}] must be a table or an array of tables")
    return tables


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
    if expected is _ANY:
        return
    if isinstance(expected, dict):
        _check_table(value, expected, where, key)
        return
    if isinstance(expected, tuple) and any(isinstance(e, dict) for e in expected):
        if isinstance(value, dict):
            _check_table(value, next(e for e in expected if isinstance(e, dict)), where, key)
        elif not isinstance(value, bool):
            raise ConfigError(f"{where}: {key} must be a table {{ke = ..., kd = ...}} or false")
        return
    if expected is VECTOR:
        ok = isinstance(value, list) and len(value) == 3 and all(_is_number(v) for v in value)
        if not ok:
            raise ConfigError(f"{where}: {key} must be a list of 3 numbers [x, y, z], got {value!r}")
        return
    types = expected if isinstance(expected, tuple) else (expected,)
    ok = _is_number(value) if types == NUMBER else isinstance(value, types) and not (
        isinstance(value, bool) and bool not in types
    )
    if not ok:
        names = "number" if types == NUMBER else " or ".join(t.__name__ for t in types)
        raise ConfigError(f"{where}: {key} must be a {names}, got {value!r}")


def _is_number(v) -> bool:
    return isinstance(v, NUMBER) and not isinstance(v, bool)


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
    axis = rot.get("axis", [1.0, 0.0, 0.0])
    if not any(axis):
        raise ConfigError("cloth rotation axis must be a nonzero vector")
    return quat_from_axis_angle(axis, math.radians(rot.get("degrees", 0.0)))


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
        if "density" in cloth or "scale" in cloth:
            raise ConfigError("a grid cloth takes mass or particle_mass (not density or scale)")
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
        if "particle_mass" in cloth or "shear" in cloth:
            raise ConfigError("a mesh cloth takes mass or density (not particle_mass), and no shear springs")
        mesh = cloth["mesh"]
        path = mesh if os.path.isabs(mesh) else os.path.join(base, mesh)
        builder.add_cloth_mesh(path, scale=cloth.get("scale", 1.0), density=cloth.get("density"), **common)


def _add_collider(builder: ModelBuilder, c: dict) -> None:
    friction = c.get("friction", 0.5)
    if c["type"] == "ground":
        builder.add_ground_plane(height=c.get("height", 0.0), friction=friction)
    elif c["type"] == "plane":
        builder.add_collider_plane(
            point=c.get("point", (0.0, 0.0, 0.0)), normal=c.get("normal"), friction=friction, name=c.get("name", "plane")
        )
    else:
        builder.add_collider_sphere(
            center=c["center"], radius=c["radius"], friction=friction, name=c.get("name", "sphere")
        )
