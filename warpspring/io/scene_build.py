"""Building a scene: its checked tables (a :class:`~warpspring.io.scene.Scene`) turned into
:class:`~warpspring.core.builder.ModelBuilder` calls (cloth, wind, emitters, soft bodies, colliders, self-collision,
tracks), and the model finalized with the scene's worlds, per-world values and contact options. Paths in the
tables are relative to the scene file's folder; a ConfigError the builder raises is prefixed with the file and
the table."""

from __future__ import annotations

import math
import os
from dataclasses import replace

import numpy as np

from ..core.aero import AIR_DENSITY, DEFAULT_DRAG, DEFAULT_LIFT
from ..core.builder import ModelBuilder, SpringMaterial
from ..core.builder.spring_materials import DEFAULT_BEND, DEFAULT_SHEAR, DEFAULT_STRUCTURAL
from ..core.builder.spring_materials import spring_law_options
from ..core.material import DEFAULT_CLOTH, PRESETS, ClothMaterial, with_mass
from ..core.model import Model
from ..core.springs import SpringPlasticity
from ..core.tracks import Track
from ..core.transforms import quat_from_axis_angle
from ..errors import ConfigError
from .scene_checks import in_table, table_label
from .scene_schema import WIND_INPUTS


def scene_builder(scene) -> ModelBuilder:
    """A ModelBuilder holding the cloth and colliders of ``scene`` (a :class:`~warpspring.io.scene.Scene`):
    :meth:`Scene.builder <warpspring.io.scene.Scene.builder>`.

    Raises:
        ConfigError: a value the builder rejects (e.g. a mesh file that is missing or holds NaN),
            prefixed with the scene file and the table.
    """
    where = os.path.basename(scene.path)
    world = scene.world
    tracks = scene.tracks
    with in_table(where, "world"):
        builder = ModelBuilder(
            up_axis=world.get("up_axis", "Z"),
            gravity=tracks["gravity"].values[0] if "gravity" in tracks else world.get("gravity"),
            drag=float(tracks["drag"].values[0, 0]) if "drag" in tracks else world.get("drag", 0.0),
            stabilizers=scene.stabilizers,
        )
    wind_inputs = set(WIND_INPUTS.values())
    for name, track in tracks.items():
        if name not in wind_inputs:  # (the wind's tracks once the aerodynamics is added, below)
            with in_table(where, "world" if name in ("gravity", "drag") else "stabilizers"):
                builder.set_track(name, track)
    for i, cloth in enumerate(scene.cloths):
        with in_table(where, table_label("cloth", i, len(scene.cloths))):
            _add_cloth(builder, cloth, os.path.dirname(scene.path))
    if scene.wind is not None:
        with in_table(where, "wind"):
            _add_wind(builder, scene.wind, tracks)
    for i, emitter in enumerate(scene.emitters):
        with in_table(where, table_label("emitter", i, len(scene.emitters))):
            _add_emitter(builder, emitter, os.path.dirname(scene.path))
    for i, body in enumerate(scene.soft_bodies):
        with in_table(where, table_label("soft_body", i, len(scene.soft_bodies))):
            _add_soft_body(builder, body, os.path.dirname(scene.path))
    for i, collider in enumerate(scene.colliders):
        with in_table(where, table_label("collider", i, len(scene.colliders))):
            _add_collider(builder, collider, os.path.dirname(scene.path))
    if scene.self_collision is not None:
        with in_table(where, "self_collision"):
            builder.add_self_collision(**scene.self_collision)
    return builder


def scene_model(scene, device=None) -> Model:
    """The model of ``scene`` on ``device`` (:meth:`Scene.finalize <warpspring.io.scene.Scene.finalize>`):
    :func:`scene_builder` finalized in the scene's precision with its ``world_count`` worlds, each given its
    ``[worlds]`` values and tracks, and the ``[contacts]`` options (without ``triangles``, triangle contacts
    switch on where a sphere or capsule is too thin for particle contacts: :meth:`ModelBuilder.triangle_contacts`).

    Raises:
        ConfigError: as :func:`scene_builder`, or a per-world value the model rejects (prefixed with the file
            and the table).
    """
    model = scene_builder(scene).finalize(device, precision=scene.precision, worlds=scene.world_count,
                                          contact_stage=scene.contact_stage, contact_slots=scene.contact_slots,
                                          integrator=scene.integrator, contact_triangles=scene.contact_triangles)
    if not scene.contact_swept:
        model.contact_swept = False
    with in_table(os.path.basename(scene.path), "worlds"):
        for name, entries in scene.world_inputs.items():
            # Constants first (this stops any track of the input), then each world's own track.
            model.set_world_values(name, [e.values[0] if isinstance(e, Track) else e for e in entries])
            for w, entry in enumerate(entries):
                if isinstance(entry, Track):
                    model.set_track(name, entry, world=w)
        for name, scale in scene.world_scales.items():
            base = model.world_values(name)[0]
            model.set_world_values(name, np.asarray(scale)[:, None] * base[None, :])
    return model


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
        name=body.get("name"), prim=body.get("prim"),
        plasticity=SpringPlasticity(**body["plasticity"]) if "plasticity" in body else None,
        volume=body.get("volume", False), bulk_modulus=body.get("bulk_modulus"),
        elasticity=body.get("elasticity", "springs"), poisson_ratio=body.get("poisson_ratio", 0.25),
        element=body.get("element", "tet4"),
    )
    if "pin" in body:
        placed = builder.particle_positions(soft.particles)
        inside = np.all((placed >= body["pin"]["min"]) & (placed <= body["pin"]["max"]), axis=1)
        if not inside.any():
            raise ConfigError(f"soft body {soft.name!r}: its pin box {body['pin']['min']} … {body['pin']['max']} [m] "
                              "holds none of its particles: widen the box (particles lie on the method's lattice)")
        builder.pin_particles(soft.particles[inside])


def _add_wind(builder: ModelBuilder, wind: dict, tracks: dict) -> None:
    """The ``[wind]`` table: aerodynamics on the named meshes (all by default), its inputs' first values, and
    their tracks."""
    start = {}
    for key, name in WIND_INPUTS.items():
        if name in tracks:
            start[key] = tracks[name].values[0] if name == "wind" else float(tracks[name].values[0, 0])
        elif key in wind:
            start[key] = wind[key]
    builder.add_aerodynamics(
        meshes=wind.get("meshes"), drag=wind.get("drag", DEFAULT_DRAG), lift=wind.get("lift", DEFAULT_LIFT),
        wind=start.get("velocity", (0.0, 0.0, 0.0)), air_density=start.get("air_density", AIR_DENSITY),
        noise=start.get("noise", 0.0), noise_scale=wind.get("noise_scale", 1.0), seed=wind.get("seed", 0),
    )
    for name in WIND_INPUTS.values():
        if name in tracks:
            builder.set_track(name, tracks[name])


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


#: The keys that give a cloth its springs; a ``[cloth]`` table with none of them and no ``material`` is made of
#: :data:`~warpspring.core.material.DEFAULT_CLOTH`.
SPRING_KEYS = ("structural", "shear", "bend")


def _material(cloth: dict, builder: ModelBuilder, path: str | None) -> ClothMaterial | None:
    """The cloth's :class:`ClothMaterial`: its ``material`` (a preset's name or a table of the fields), or, with no
    springs named either, :data:`DEFAULT_CLOTH` whose density gives the table's ``mass`` (or ``particle_mass`` ×
    the grid's particles), or its ``density``; ``None`` for a cloth of springs."""
    spec = cloth.get("material")
    if spec is None and any(key in cloth for key in SPRING_KEYS):
        return None
    if isinstance(spec, str):
        if spec not in PRESETS:
            raise ConfigError(f"material must be one of {', '.join(map(repr, PRESETS))} or a table {{stretch = ..., "
                              f"shear = ..., bending = ..., density = ...}}, got {spec!r}")
        material = PRESETS[spec]
    elif isinstance(spec, dict):
        try:
            material = ClothMaterial(**spec)
        except TypeError as exc:
            raise ConfigError(f"material: {exc} (its keys: stretch, shear [N/m], bending [N·m], density [kg/m²], "
                              "stretch_damping [N·s/m], bending_damping [N·m·s])") from None
    else:
        material = DEFAULT_CLOTH
    mass = cloth.get("mass")
    if "grid" in cloth:
        g = cloth["grid"]
        if "particle_mass" in cloth:
            mass = cloth["particle_mass"] * g["nx"] * g["ny"]
        area = (g["nx"] - 1) * (g["ny"] - 1) * g["spacing"] ** 2
    elif mass is not None:  # the mesh's area: its masses at a density of 1 kg/m²
        probe = ModelBuilder(up_axis=builder.up_axis)
        probe.add_cloth_mesh(path, scale=cloth.get("scale", 1.0), prim=cloth.get("prim"),
                             material=replace(material, density=1.0))
        area = float(probe.world_rows()["particle_mass"].sum())
    if "density" in cloth:
        return replace(material, density=cloth["density"])
    return material if mass is None else with_mass(material, mass, area)


def _add_cloth(builder: ModelBuilder, cloth: dict, base: str) -> None:
    path = None
    if "mesh" in cloth:
        path = cloth["mesh"] if os.path.isabs(cloth["mesh"]) else os.path.join(base, cloth["mesh"])
    material = _material(cloth, builder, path)
    common = dict(
        origin=cloth.get("origin", (0.0, 0.0, 0.0)),
        rotation=_rotation(cloth),
        velocity=cloth.get("velocity", (0.0, 0.0, 0.0)),
        radius=cloth.get("radius"),
        structural=_springs(cloth, "structural", DEFAULT_STRUCTURAL),
        bend=_springs(cloth, "bend", DEFAULT_BEND),
        pin=cloth.get("pin", []),
        name=cloth.get("name", "cloth" if "grid" in cloth else None),  # a mesh: a USD prim's own name
        mass=None if material is not None else cloth.get("mass"),
        material=material,
    )
    if "grid" in cloth:
        g = cloth["grid"]
        ids = builder.add_cloth_grid(
            nx=g["nx"],
            ny=g["ny"],
            spacing=g["spacing"],
            particle_mass=None if material is not None else cloth.get("particle_mass"),
            shear=_springs(cloth, "shear", DEFAULT_SHEAR),
            **common,
        )
    else:
        try:
            ids = builder.add_cloth_mesh(path, scale=cloth.get("scale", 1.0),
                                         density=None if material is not None else cloth.get("density"),
                                         prim=cloth.get("prim"), **common)
        except ConfigError as exc:  # name the mesh file in every message about its contents
            raise exc if path in str(exc) else ConfigError(f"mesh {path}: {exc}") from None
    groups = cloth.get("pin_group", [])
    for i, group in enumerate(groups):
        try:
            builder.add_pin_group(_group_particles(ids, group.pin), translation=group.translation,
                                  rotation=group.rotation, pivot=group.pivot, name=group.name)
        except ConfigError as exc:
            raise ConfigError(f"{table_label('pin_group', i, len(groups))}: {exc}") from None
    handles = cloth.get("handle", [])
    for i, handle in enumerate(handles):
        try:
            builder.add_handle(_group_particles(ids, handle.particles), kp=handle.kp, kd=handle.kd,
                               max_force=handle.max_force, translation=handle.translation, rotation=handle.rotation,
                               pivot=handle.pivot, name=handle.name)
        except ConfigError as exc:
            raise ConfigError(f"{table_label('handle', i, len(handles))}: {exc}") from None


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
