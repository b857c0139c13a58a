"""Scene files: :func:`load_scene` reads a TOML file (:func:`parse_scene` a parsed one) into a :class:`Scene`, how
to build the model and how to run and write it.

Every key is checked: an unknown key, a wrong type or a bad value is a :class:`ConfigError` naming the
file, the table and the key. The format (its tables and keys, versions and renamed keys) is declared in
:mod:`~warpspring.io.scene_schema`, checked by :mod:`~warpspring.io.scene_checks`, and built into a model by
:mod:`~warpspring.io.scene_build`. See the scene-file reference (docs/scenes.md), or ``examples/*.toml``.
"""

from __future__ import annotations

import copy
import os
import sys
import warnings
from dataclasses import dataclass, field

from ..core.builder import ModelBuilder
from ..core.guard_records import GuardLimits
from ..core.integrators import INTEGRATORS
from ..core.mesh_files import open_regular_file
from ..core.model import Model
from ..core.records import MAX_CONTACT_SLOTS, STABILIZER_INPUTS, Stabilizers
from ..errors import ConfigError
from .scene_build import scene_builder, scene_model
from .scene_checks import (
    apply_renames,
    check_cloth,
    check_collider,
    check_depth,
    check_export_options,
    check_nesting,
    check_representable,
    check_run_settings,
    check_soft_body_element,
    check_soft_body_pin,
    check_table,
    format_version,
    make_track,
    one_line,
    table_label,
    table_list,
)
from .scene_schema import (
    EMITTER,
    GUARD_STOPS,
    LIVE_TABLES,
    PRECISIONS,
    SCENE_FORMAT_VERSION,
    SCHEMA,
    SOFT_BODY,
    TOP_LEVEL,
    WIND_INPUTS,
    WORLD_SCALES,
    Live,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib


class DeprecatedKeyWarning(FutureWarning):
    """A scene file uses a key under a name that a later scene format renamed: it is still read, and the
    message names the file, the old key and the new one."""



@dataclass
class Scene:
    """A parsed scene file: how to build the model, and how to run and write it.

    Attributes:
        path: the scene file.
        fps: output frames per second [1/s].
        frames: frames to simulate.
        substeps: integrator steps per frame, or "auto" (the default: the fewest the stability advisor passes with
            a margin, chosen before the run; :mod:`warpspring.analysis.step_choice`).
        integrator: integrator name (see ``warpspring.INTEGRATORS``).
        integrator_options: keyword options of the integrator.
        precision: "float32" or "float64".
        device: Warp device name, or ``None`` for Warp's default.
        output: output USD path as the file gives it (a run takes it in the scene file's folder), or ``None``.
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
        contact_triangles: ``[contacts] triangles``: push cloth triangles out of spheres and capsules too;
            ``None`` (no key): on where a sphere or capsule is too thin for particle contacts
            (:meth:`~warpspring.core.builder.ModelBuilder.triangle_contacts`); false switches them off.
        contact_swept: ``[contacts] swept``: sweep particles' paths against spheres, boxes, capsules and meshes (default
            true).
        version: the file's scene format (1 for a file without ``version``).
        deprecations: one message per deprecated key the file uses (each also a
            :class:`DeprecatedKeyWarning` when the file is read).
    """

    path: str
    fps: float = 60.0
    frames: int = 120
    substeps: int | str = "auto"
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
    contact_triangles: bool | None = None
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
        return scene_builder(self)

    def finalize(self, device=None) -> Model:
        """The scene's model on ``device``: :meth:`builder` finalized in the scene's precision with
        :attr:`world_count` worlds, each given its ``[worlds]`` values and tracks, and the ``[contacts]``
        options.

        Raises:
            ConfigError: as :meth:`builder`, or a per-world value the model rejects (prefixed with the file
                and the table).
        """
        return scene_model(self, device)


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and check a scene file.

    A deprecated key is read under its new name and reported by a :class:`DeprecatedKeyWarning` (and in
    ``Scene.deprecations``).

    Raises:
        ConfigError: the file is missing or unreadable, not valid TOML, of a newer scene format, or breaks
            the schema.
    """
    path = os.fspath(path)
    scene = _parse(read_toml(path, "scene file"), path)
    for message in scene.deprecations:
        warnings.warn(message, DeprecatedKeyWarning, stacklevel=2)
    return scene


def read_toml(path: str | os.PathLike[str], what: str) -> dict:
    """The TOML file at ``path`` (a scene or a sweep file, named ``what`` in messages) parsed, or a one-line
    ConfigError: missing, not a regular file (a pipe is refused without blocking), nesting deeper than the
    parser should recurse, not UTF-8, or not valid TOML."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ConfigError(f"{what} not found: {path}")
    try:
        with open_regular_file(path, what) as f:
            text = f.read().decode("utf-8")
        check_nesting(text, path)
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {one_line(exc)}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read: {one_line(exc)}") from None
    except RecursionError:  # a backstop: check_nesting bounds the nesting the parser recurses on
        raise ConfigError(f"{path}: nests too deep to parse; flatten its arrays and inline tables") from None


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
    check_depth(data, where)  # every check below recurses on the values
    version = format_version(data, where)  # first: a newer file's keys would only confuse the checks below
    data = copy.deepcopy(data)
    deprecations = apply_renames(data, version, where)
    check_table(data, TOP_LEVEL, where, "", version=version)
    for name in ("simulation", "world", "output", "stabilizers", "guard", "worlds", "contacts", "wind"):
        check_table(data.get(name, {}), SCHEMA[name], where, name, version=version)
    cloths = table_list(data.get("cloth", []), where, "cloth")
    colliders = table_list(data.get("collider", []), where, "collider")
    emitters = table_list(data.get("emitter", []), where, "emitter")
    soft_bodies = table_list(data.get("soft_body", []), where, "soft_body")
    for i, body in enumerate(soft_bodies):
        label = table_label("soft_body", i, len(soft_bodies))
        check_table(body, SOFT_BODY, where, label, version=version)
        missing = [key for key in ("mesh", "youngs_modulus") if key not in body]
        if missing:
            raise ConfigError(f"{where}: [{label}] needs {missing[0]} = ... (the mesh file, and Young's modulus E [Pa])")
        if ("density" in body) == ("mass" in body):
            raise ConfigError(f"{where}: [{label}] needs exactly one of density = ... [kg/m³] or mass = ... [kg]")
        check_soft_body_pin(body.get("pin"), where, label)
        check_soft_body_element(body.get("element"), where, label)
        if "plasticity" in body and not ({"yield_strain", "yield_force"} & set(body["plasticity"])):
            raise ConfigError(f"{where}: {label}.plasticity needs yield_strain = ... [-] or yield_force = ... [N] "
                              "(its elastic limit)")
    if not cloths and not emitters and not soft_bodies:
        raise ConfigError(f"{where}: the scene has no [cloth] table: add one with grid = {{...}} or mesh = '...' "
                          "(or particles from an [[emitter]])")
    for i, e in enumerate(emitters):
        label = table_label("emitter", i, len(emitters))
        check_table(e, EMITTER, where, label, version=version)
        if "life" not in e:
            raise ConfigError(f"{where}: [{label}] needs life = ..., each particle's life span [s]")
    for i, c in enumerate(cloths):
        check_cloth(c, where, table_label("cloth", i, len(cloths)), version=version)
    for i, c in enumerate(colliders):
        check_collider(c, where, table_label("collider", i, len(colliders)), version=version)

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
    check_representable(data, where, precision)

    tracks = {
        name: make_track(value, where, f"{table}.{name}")
        for table in LIVE_TABLES
        for name, value in data.get(table, {}).items()
        if isinstance(SCHEMA[table][name], Live) and isinstance(value, dict)
    }
    wind = data.get("wind")
    if wind is not None:
        tracks.update({WIND_INPUTS[key]: make_track(value, where, f"wind.{key}") for key, value in wind.items()
                       if key in WIND_INPUTS and isinstance(value, dict)})
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
    scene.export_options = check_export_options(out, where)
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
    scene.contact_triangles = contacts.get("triangles")
    scene.contact_swept = contacts.get("swept", True)
    self_collision = data.get("self_collision")
    if self_collision is not None:
        check_table(self_collision, SCHEMA["self_collision"], where, "self_collision", version=version)
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
                make_track(e, where, f"worlds.{key}[{i}]") if isinstance(e, dict)
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
