"""The contact scenes of the speed/accuracy study (:mod:`warpspring.analysis.trade_contact` measures them): each
builds its model for one set of contact options and names the quantity of interest it is judged by at rest.

* ``drape``: a square cloth dropped flat onto a sphere standing on the ground; it drapes over the sphere and
  its corners reach the ground. Quantity: the drape coefficient DC = (A_shadow − A_sphere) / (A_cloth −
  A_sphere), the shadow from :func:`~warpspring.analysis.drape.shadow_area` (the Cusick test's measure with the
  sphere's disc for the pedestal's).
* ``stack``: two cloths, the top one half a spacing aside, dropped onto a box with self-collision between them.
  Quantity: the sag, how far the top cloth hangs below the box's top [m].
* ``tablecloth``: a cloth lying on a table pulled off it sideways by a PD handle on its left edge (a keyframe
  track: up 5 cm in 0.5 s, then 1.2 m towards −x by 2 s), falling onto the ground. Quantity: the sag, the
  cloth's height span (top minus bottom) at the end [m].
* ``softball`` (a voxel body) and ``softball-neohookean`` (neo-Hookean Delaunay tets): an icosphere of radius
  0.2 m, E = 20 kPa, ρ = 1000 kg/m³, dropped from 15 cm onto a slab given as a closed triangle mesh collider.
  Quantity: the volume its surface (the skin as authored) encloses, over its rest volume [-].

Contact options (:data:`OPTIONS`, per scene; each one's settings as the builder and ``finalize`` name them):
``contact_triangles`` (the cloth's triangles pushed out of spheres too, or particle contacts only),
``thickness`` (the self-collision's τ [m]), ``contact_slots`` (contacts a particle can hold), ``max_strain``
(strain limiting, :class:`~warpspring.core.records.Stabilizers`) and ``winding_number`` (the mesh
collider's inside test). The self-collision has no broad-phase interval to set: its pair cache rebuilds itself
when a vertex moved too far (``kernels/selfcontact_cache.py``). The first option of each scene is its reference
option: the most faithful one, which the float64 references run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

from ..core.builder import ModelBuilder, SpringMaterial
from ..core.model import Model
from ..core.records import Stabilizers
from ..core.tracks import Track
from ..errors import ConfigError
from .drape import shadow_area

#: The ball's radius [m] (an icosphere of 320 faces, as examples/meshes/ball.obj).
BALL_RADIUS = 0.2


@dataclass(frozen=True)
class Option:
    """One set of contact options.

    Attributes:
        label: its name in tables and plots ("triangle contacts", "τ = 4 mm", ...).
        settings: the option's values by name (see the module docstring); absent: the scene's default.
    """

    label: str
    settings: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Scene:
    """A contact scene.

    Attributes:
        name: the problem's name.
        quantity: what the quantity of interest is, with its unit ("drape coefficient [-]").
        length_scale: the scene's size [m] (its blow-up scale).
        options: the contact options measured, the reference option first.
        self_collision: whether the scene has self-collision (then crossings are audited).
    """

    name: str
    quantity: str
    length_scale: float
    options: tuple[Option, ...]
    self_collision: bool = False

    def option(self, label: str) -> Option:
        for option in self.options:
            if option.label == label:
                return option
        raise ConfigError(f"scene {self.name!r} has no contact option {label!r}: "
                          f"it has {', '.join(o.label for o in self.options)}")


def _finalize(builder: ModelBuilder, device, precision: str, settings: dict) -> Model:
    return builder.finalize(device, precision=precision, contact_slots=settings.get("contact_slots"),
                            contact_triangles=settings.get("contact_triangles"), check_memory=False)


def _builder(settings: dict, drag: float) -> ModelBuilder:
    strain = settings.get("max_strain")
    return ModelBuilder(drag=drag, stabilizers=Stabilizers(max_strain=strain) if strain is not None else None)


# -- drape --------------------------------------------------------------------------------------------------

DRAPE_SIDE = 0.9  # [m]
DRAPE_SPHERE = ((0.0, 0.0, 0.25), 0.2)  # centre [m], radius [m]


def build_drape(size: int, device, precision: str, settings: dict) -> Model:
    """``size`` × ``size`` particles over 0.9 m, 0.3 kg, ke = 300 / 80 / 8 N/m (structural, shear, bend), contact
    radius 12 mm, drag 0.01 N·s/m per particle, turned 20° about z, its centre 8 cm and 5 cm off the sphere's axis
    in x and y, 5 cm above a sphere of radius 0.2 m (μ = 0.4) on the ground (μ = 0.6)."""
    builder = _builder(settings, drag=0.01)
    half = 0.5 * DRAPE_SIDE
    centre, radius = DRAPE_SPHERE
    # Off centre and turned by 20° (about z): the folds follow the geometry, not the rounding of a symmetric start.
    turn = math.radians(20.0)
    corner = np.array([-half, -half]) @ np.array([[math.cos(turn), math.sin(turn)], [-math.sin(turn), math.cos(turn)]])
    builder.add_cloth_grid(nx=size, ny=size, spacing=DRAPE_SIDE / (size - 1),
                           origin=(corner[0] + 0.08, corner[1] + 0.05, centre[2] + radius + 0.05),
                           rotation=(0.0, 0.0, math.sin(0.5 * turn), math.cos(0.5 * turn)),
                           mass=0.3, radius=0.012, structural=SpringMaterial(300.0, 0.05),
                           shear=SpringMaterial(80.0, 0.01), bend=SpringMaterial(8.0, 0.002))
    builder.add_collider_sphere(center=centre, radius=radius, friction=0.4)
    builder.add_ground_plane(friction=0.6)
    return _finalize(builder, device, precision, settings)


def drape_coefficient(q: np.ndarray, faces: np.ndarray) -> float:
    """DC [-] of the drape at positions ``q`` [m], shape [n, 3] (triangles ``faces``): shadow on pixels of 2 mm."""
    disc = math.pi * DRAPE_SPHERE[1] ** 2
    return (shadow_area(q, faces, pixel=0.002) - disc) / (DRAPE_SIDE**2 - disc)


# -- stack --------------------------------------------------------------------------------------------------

STACK_SIDE = 0.6  # [m]
STACK_BOX = ((0.0, 0.0, 0.15), (0.15, 0.15, 0.15))  # centre, half extents [m]


def build_stack(size: int, device, precision: str, settings: dict) -> Model:
    """Two cloths of ``size`` × ``size`` particles over 0.6 m, 0.15 kg each, ke = 150 / 40 / 2 N/m, contact radius
    8 mm, 4 and 7 cm above a box of 0.3 m (μ = 0.5) on the ground, the top one shifted half a spacing in x and
    y; self-collision of thickness ``settings["thickness"]`` (default 4 mm), μ = 0.3."""
    builder = _builder(settings, drag=0.01)
    spacing = STACK_SIDE / (size - 1)
    top = STACK_BOX[0][2] + STACK_BOX[1][2]
    for k, name in enumerate(("bottom", "top")):
        shift = 0.5 * spacing * k
        builder.add_cloth_grid(nx=size, ny=size, spacing=spacing, origin=(-0.3 + shift, -0.3 + shift, top + 0.04 + 0.03 * k),
                               mass=0.15, radius=0.008, structural=SpringMaterial(150.0, 0.02),
                               shear=SpringMaterial(40.0, 0.005), bend=SpringMaterial(2.0, 0.001), name=name)
    builder.add_self_collision(thickness=settings.get("thickness", 0.004), friction=0.3)
    builder.add_collider_box(center=STACK_BOX[0], half_extents=STACK_BOX[1], friction=0.5)
    builder.add_ground_plane(friction=0.6)
    return _finalize(builder, device, precision, settings)


def stack_sag(q: np.ndarray) -> float:
    """How far the top cloth (the second half of the particles) hangs below the box's top [m]."""
    top = STACK_BOX[0][2] + STACK_BOX[1][2]
    return float(top - q[len(q) // 2:, 2].min())


# -- tablecloth ---------------------------------------------------------------------------------------------

TABLE = ((0.0, 0.0, 0.4), (0.6, 0.45, 0.4))  # centre, half extents [m]


def build_tablecloth(size: int, device, precision: str, settings: dict) -> Model:
    """A 1.0 m × 0.7 m cloth (``size`` particles along x), 0.2 kg, ke = 300 / 60 / 2 N/m, contact radius 10 mm,
    2 cm above a 1.2 m × 0.9 m table 0.8 m high (μ = 0.4); its left edge held by a handle (Kp = 4 N/m, Kd = 0.05
    N·s/m, at most 0.3 N, per particle, scaled by 10 / ``size``: the same pull at any resolution) on a smooth track
    up 5 cm by 0.5 s, then 1.2 m towards −x by 2 s; the ground μ = 0.6."""
    builder = _builder(settings, drag=0.002)
    nx = size
    spacing = 1.0 / (nx - 1)
    ny = int(round(0.7 / spacing)) + 1
    top = TABLE[0][2] + TABLE[1][2]
    ids = builder.add_cloth_grid(nx=nx, ny=ny, spacing=spacing, origin=(-0.5, -0.5 * (ny - 1) * spacing, top + 0.02),
                                 mass=0.2, radius=0.01, structural=SpringMaterial(300.0, 0.05),
                                 shear=SpringMaterial(60.0, 0.01), bend=SpringMaterial(2.0, 0.001)).reshape(ny, nx)
    share = 10.0 / ny  # the handle's total pull does not change with the number of grabbed particles
    builder.add_handle(ids[:, 0], kp=4.0 * share, kd=0.05 * share, max_force=0.3 * share, name="hand",
                       translation=Track([0.0, 0.5, 2.0], [[0, 0, 0], [0, 0, 0.05], [-1.2, 0, 0.05]],
                                         interpolation="smooth"))
    builder.add_collider_box(center=TABLE[0], half_extents=TABLE[1], friction=0.4, name="table")
    builder.add_ground_plane(friction=0.6)
    return _finalize(builder, device, precision, settings)


def tablecloth_sag(q: np.ndarray) -> float:
    """The cloth's height span at the end (its top minus its bottom) [m]."""
    return float(np.ptp(q[:, 2]))


# -- soft balls ---------------------------------------------------------------------------------------------


def _slab() -> tuple[np.ndarray, np.ndarray]:
    """A closed box mesh 1.2 m × 1.2 m × 0.1 m whose top face is at z = 0 (vertices [m], faces)."""
    box = trimesh.creation.box(extents=(1.2, 1.2, 0.1))
    return np.asarray(box.vertices) - (0.0, 0.0, 0.05), np.asarray(box.faces)


def build_softball(method: str, device, precision: str, settings: dict) -> Model:
    """The ball (``method``: "voxel" springs at 8 cm, or "neohookean" Delaunay tets at 8 cm, ν = 1/4), E = 20 kPa,
    ρ = 1000 kg/m³, β = 5 ms, drag 0.5 N·s/m per particle, its bottom 15 cm above a slab mesh collider (μ = 0.5)."""
    builder = _builder(settings, drag=0.5)
    common = dict(youngs_modulus=2.0e4, density=1000.0, spacing=0.08, damping=5.0e-3, origin=(0.0, 0.0, 0.35),
                  name="ball")
    ball = trimesh.creation.icosphere(subdivisions=2, radius=BALL_RADIUS)
    if method == "voxel":
        builder.add_soft_body(ball, method="voxel", **common)
    else:
        builder.add_soft_body(ball, method="delaunay", elasticity="neohookean", **common)
    vertices, faces = _slab()
    builder.add_collider_mesh(vertices, faces=faces, friction=0.5, name="slab",
                              winding_number=bool(settings.get("winding_number", False)))
    return _finalize(builder, device, precision, settings)


def skin_volume_ratio(model: Model, q: np.ndarray, rest: np.ndarray) -> float:
    """The volume the ball's skin encloses at positions ``q`` over that at ``rest`` [-] (divergence theorem)."""
    skin = model.skins[0]

    def volume(x):
        p = skin.points(x)[skin.faces]
        return float(np.einsum("ti,ti->t", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)

    return volume(q) / volume(rest)


# -- the table ----------------------------------------------------------------------------------------------

SCENES = {
    "drape": Scene("drape", "drape coefficient [-]", DRAPE_SIDE, (
        Option("particle contacts", {"contact_triangles": False}),
        Option("triangle contacts", {"contact_triangles": True}),
        Option("particle contacts, 1 slot", {"contact_triangles": False, "contact_slots": 1}),
    )),
    "stack": Scene("stack", "sag [m]", STACK_SIDE, (
        Option("τ = 4 mm", {"thickness": 0.004}),
        Option("τ = 10 mm", {"thickness": 0.010}),
        Option("τ = 4 mm, strain ≤ 10 %", {"thickness": 0.004, "max_strain": 0.1}),
    ), self_collision=True),
    "tablecloth": Scene("tablecloth", "sag [m]", 1.0, (
        Option("2 slots", {"contact_slots": 2}),
        Option("1 slot", {"contact_slots": 1}),
        Option("2 slots, strain ≤ 10 %", {"contact_slots": 2, "max_strain": 0.1}),
    )),
    "softball": Scene("softball", "volume / rest volume [-]", 0.4, (
        Option("winding number", {"winding_number": True}),
        Option("pseudo-normals", {"winding_number": False}),
        Option("pseudo-normals, strain ≤ 10 %", {"winding_number": False, "max_strain": 0.1}),
    )),
    "softball-neohookean": Scene("softball-neohookean", "volume / rest volume [-]", 0.4, (
        Option("winding number", {"winding_number": True}),
        Option("pseudo-normals", {"winding_number": False}),
    )),
}


def build(scene: str, size: int, device, precision: str, option: Option) -> Model:
    """The model of ``scene`` at resolution ``size`` (particles along the cloth's side; the balls ignore it)."""
    if scene == "drape":
        return build_drape(size, device, precision, option.settings)
    if scene == "stack":
        return build_stack(size, device, precision, option.settings)
    if scene == "tablecloth":
        return build_tablecloth(size, device, precision, option.settings)
    if scene in ("softball", "softball-neohookean"):
        return build_softball("voxel" if scene == "softball" else "neohookean", device, precision, option.settings)
    raise ConfigError(f"unknown contact scene {scene!r}: choose from {', '.join(SCENES)}")


def quantity(scene: str, model: Model, q: np.ndarray, rest: np.ndarray) -> float:
    """The scene's quantity of interest at positions ``q`` [m] (one world, float64 [n, 3]); ``rest``: the start."""
    if scene == "drape":
        return drape_coefficient(q, model.tri_indices.numpy().reshape(-1, 3))
    if scene == "stack":
        return stack_sag(q)
    if scene == "tablecloth":
        return tablecloth_sag(q)
    return skin_volume_ratio(model, q, rest)
