"""The named small scenes whose gradients are checked against finite differences (tests/test_grad*.py) and
timed (bench/gradients.py): a hanging 8 × 8 cloth, the same cloth draped on a sphere, a voxel ball dropped on the
ground, a flag in wind, a neo-Hookean ball (E, ν), and the hanging cloth swung by its top row (pin-track keys). Each is a builder of one world for a dict of parameter
values, the parameters' nominal values, and the run's step, horizon and contact."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..core.adjoint import SmoothContact
from ..core.builder.model_builder import ModelBuilder
from ..core.material import ClothMaterial
from ..core.model import Model
from ..core.tracks import Track


@dataclass(frozen=True)
class GradScene:
    """A scene of differentiable runs.

    Attributes:
        name: its name.
        build: (values {name: float}, device, precision) → a model of one world.
        values: the parameters and their nominal values (SI units, see each scene).
        dt: the step [s].
        steps: the horizon [steps].
        contact: the smooth contact's values, or None (no colliders).
        integrator: the integrator of the run.
    """

    name: str
    build: Callable[..., Model]
    values: dict
    dt: float
    steps: int
    contact: SmoothContact | None = None
    integrator: str = "symplectic_euler"
    observed: tuple = field(default=())  # the particles the loss sees (empty: all)


def _cloth_material(values: dict) -> ClothMaterial:
    return ClothMaterial(stretch=values.get("stretch", 60.0), shear=values.get("shear", 20.0),
                         bending=values.get("bending", 2.0e-4), density=values.get("density", 0.2),
                         stretch_damping=values.get("stretch_damping", 0.2),
                         bending_damping=values.get("bending_damping", 0.0))


def hanging_cloth(values: dict, device=None, precision: str = "float64", *, n: int = 8, worlds: int = 1) -> Model:
    """An n × n cloth of 0.1 m cells, horizontal at z = 1 m, pinned at its two top corners, falling under gravity
    with air drag ``drag`` [N·s/m] and an initial downward speed ``speed`` [m/s]; material from ``values``
    (``ClothMaterial``'s stretch [N/m], shear [N/m], bending [N·m], density [kg/m²], stretch_damping [N·s/m])."""
    builder = ModelBuilder(drag=values.get("drag", 0.01))
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(-0.05 * (n - 1), -0.05 * (n - 1), 1.0),
                           material=_cloth_material(values), velocity=(0.0, 0.0, -values.get("speed", 0.0)),
                           pin=["top-left", "top-right"])
    return builder.finalize(device, precision=precision, worlds=worlds)


#: Key times [s] of the driven cloth's track (between steps of 1 ms, so no step's time meets a key).
DRIVEN_KEY_TIMES = (0.0, 0.0405, 0.0805)


def driven_cloth(values: dict, device=None, precision: str = "float64", *, n: int = 8, worlds: int = 1) -> Model:
    """The hanging cloth's material with its whole top row pinned and driven by a linear translation track (pin
    group "top"): at rest at t = 0, at (``key1_x``, ``key1_y``, ``key1_z``) [m] at 40.5 ms and (``key2_x``,
    ``key2_y``, ``key2_z``) at 80.5 ms, held after."""
    builder = ModelBuilder(drag=values.get("drag", 0.01))
    grid = builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(-0.05 * (n - 1), -0.05 * (n - 1), 1.0),
                                  material=_cloth_material(values))
    keys = [[0.0, 0.0, 0.0], [values.get(f"key1_{c}", 0.0) for c in "xyz"], [values.get(f"key2_{c}", 0.0) for c in "xyz"]]
    builder.add_pin_group(grid[-1], translation=Track(DRIVEN_KEY_TIMES, keys, interpolation="linear"), name="top")
    return builder.finalize(device, precision=precision, worlds=worlds)


def draped_cloth(values: dict, device=None, precision: str = "float64", *, n: int = 8, worlds: int = 1) -> Model:
    """The same cloth, unpinned, 2 cm above a sphere of radius 0.3 m (friction ``friction`` [-]), falling onto it
    at ``speed`` [m/s]."""
    builder = ModelBuilder(drag=values.get("drag", 0.01))
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(-0.05 * (n - 1), -0.05 * (n - 1), 0.82),
                           material=_cloth_material(values), velocity=(0.0, 0.0, -values.get("speed", 1.0)),
                           radius=0.005)
    builder.add_collider_sphere(center=(0.0, 0.0, 0.5), radius=0.3, friction=values.get("friction", 0.4))
    return builder.finalize(device, precision=precision, worlds=worlds)


def voxel_ball(values: dict, device=None, precision: str = "float64", *, worlds: int = 1) -> Model:
    """A voxel soft ball of radius 0.1 m (E = ``youngs_modulus`` [Pa], ρ = 100 kg/m³, spring damping ``damping``
    [s]) dropped at ``speed`` [m/s] from 2 cm above the ground (friction 0.3)."""
    import trimesh  # optional: trimesh

    builder = ModelBuilder()
    builder.add_soft_body(trimesh.creation.icosphere(subdivisions=2, radius=0.1), method="voxel", spacing=0.05,
                          youngs_modulus=values.get("youngs_modulus", 2.0e4), density=100.0,
                          damping=values.get("damping", 2.0e-3), origin=(0.0, 0.0, 0.125),
                          velocity=(0.0, 0.0, -values.get("speed", 1.0)), radius=0.01)
    builder.add_ground_plane(friction=0.3)
    return builder.finalize(device, precision=precision, worlds=worlds)


def neohookean_ball(values: dict, device=None, precision: str = "float64", *, worlds: int = 1) -> Model:
    """A neo-Hookean ball of radius 0.1 m (Delaunay tets; E = ``youngs_modulus`` [Pa], ν = ``poisson_ratio``,
    ρ = 100 kg/m³) with an initial spin-free squeeze: its particles start moving inwards at ``speed`` [m/s] per
    metre from the centre, in zero gravity."""
    import trimesh  # optional: trimesh

    builder = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    body = builder.add_soft_body(trimesh.creation.icosphere(subdivisions=1, radius=0.1), method="delaunay",
                                 spacing=0.05, youngs_modulus=values.get("youngs_modulus", 2.0e4), density=100.0,
                                 damping=1.0e-3, elasticity="neohookean",
                                 poisson_ratio=values.get("poisson_ratio", 0.3))
    model = builder.finalize(device, precision=precision, worlds=worlds)
    q = model.particle_q.numpy().astype(np.float64)
    ids = body.particles
    qd = np.zeros_like(q)
    qd[ids] = -values.get("speed", 1.0) * q[ids]
    model.particle_qd.assign(qd.astype(model.particle_qd.numpy().dtype))
    return model


def flag(values: dict, device=None, precision: str = "float64", *, n: int = 8, worlds: int = 1) -> Model:
    """An n × n flag of 0.1 m cells hanging in the xz plane from a pole along its left edge, in a wind of
    (``wind_x``, ``wind_y``, 0) [m/s] with flat-plate drag ``drag_coefficient`` and lift ``lift_coefficient``."""
    builder = ModelBuilder()
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(0.0, 0.0, 1.0), rotation=(0.7071067811865476, 0.0, 0.0,
                                                                                        0.7071067811865476),
                           material=_cloth_material(values), pin=["left"])
    builder.add_aerodynamics(wind=(values.get("wind_x", 5.0), values.get("wind_y", 1.0), 0.0),
                             drag=values.get("drag_coefficient", 1.2), lift=values.get("lift_coefficient", 1.0),
                             precompute=False)
    return builder.finalize(device, precision=precision, worlds=worlds)


#: The named scenes (their parameters' nominal values; steps chosen so a run is ~0.1 s of motion).
SCENES = {
    "hanging_cloth": GradScene(
        "hanging_cloth", hanging_cloth,
        {"stretch": 60.0, "shear": 20.0, "bending": 2.0e-4, "density": 0.2, "stretch_damping": 0.2, "drag": 0.01,
         "speed": 0.3},
        dt=1.0e-3, steps=100),
    "draped_cloth": GradScene(
        "draped_cloth", draped_cloth,
        {"stretch": 60.0, "bending": 2.0e-4, "stretch_damping": 0.2, "friction": 0.4, "speed": 1.0},
        dt=5.0e-4, steps=160, contact=SmoothContact(stiffness=2.0e3, smoothing=2.0e-3, damping=0.05)),
    "voxel_ball": GradScene(
        "voxel_ball", voxel_ball, {"youngs_modulus": 2.0e4, "damping": 2.0e-4, "speed": 0.5},
        dt=2.5e-4, steps=240, contact=SmoothContact(stiffness=3.0e3, smoothing=2.0e-3, damping=0.2, slip_speed=0.2)),
    "flag": GradScene(
        "flag", flag, {"wind_x": 5.0, "wind_y": 1.0, "drag_coefficient": 1.2, "lift_coefficient": 1.0,
                       "stretch": 60.0},
        dt=1.0e-3, steps=100),
    "driven_cloth": GradScene(
        "driven_cloth", driven_cloth,
        {"key1_x": 0.03, "key1_y": -0.02, "key1_z": 0.05, "key2_x": -0.02, "key2_y": 0.01, "key2_z": 0.08},
        dt=1.0e-3, steps=100),
    "neohookean_ball": GradScene(
        "neohookean_ball", neohookean_ball, {"youngs_modulus": 2.0e4, "poisson_ratio": 0.3, "speed": 5.0},
        dt=2.5e-4, steps=120),
}
