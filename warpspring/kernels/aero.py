"""The aerodynamic family: wind drag and lift on cloth triangles, plugged into every kernel through the
hooks of ``families.py``.

The model, per triangle of area A and unit normal n (either side: the force does not depend on the
winding), with u = w − v̄ the wind relative to the triangle (the wind w at its centroid, v̄ the mean
velocity of its corners), α the angle between the flow and the plane (sin α = |n·û|) and ρ the air's
density: the flat-plate drag and lift used for cloth by Keckeisen, Kimmerle, Thomaszewski and Wacker
("Modelling effects of wind fields in cloth animations", WSCG 2004), in closed form without angles:

    drag  F_D = ½ ρ C_D A |u|² sin α û           = ½ ρ C_D A |u·n| u
    lift  F_L = ½ ρ C_L A |u|² sin α cos α ℓ̂     = ½ ρ C_L A |u| (u·n) (n − (u·n) u / |u|²)

with ℓ̂ the unit vector of the normal's part across the flow, turned downwind. Both vanish for flow
along the plate (u·n = 0), scale with A |u|², are the same for n and −n, and add up over the triangles of
a flat plate to the plate's force whatever its triangulation. Each corner takes a third of its triangle's
force. The wind is the live input ``wind`` of the world (a constant or a keyframe track: gusts), times
1 + a·N(x / L) where N is Warp's Perlin noise in [−1, 1] seeded per model, L its length scale [m] and a
the live input ``wind_noise`` (compiled in only for models with noise): a spatially varying field, frozen
in space, whose time variation is the track's.

For implicit integration and the stability analysis the family supplies a positive semi-definite damping
matrix (−∂f/∂v, linearised about the cloth at rest in the current wind, u = w: the product hooks see
positions, not velocities): per triangle D_u = ½ ρ A (C_D |u·n| I + (C_D + C_L)
|u| n nᵀ), the drag's isotropic part plus the response of drag and lift to the flow across the plate,
shared as D_u / 9 between every pair of its corners (u depends on the mean of three velocities; each corner
takes a third); the stability advisor adds its largest eigenvalue over three to each corner's drag
(``AeroFamily.damping_rates``). Its stiffness matrix (−∂f/∂x, from the normal's rotation) is left out:
zero. Wind does work on the cloth, so the family has no energy: the guards count its work per substep
(``kernels/guards.py``, ``guard_work_kernel``).
"""

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import warp as wp

from .families import (FamilyFuncs, Incidence, IncidenceShape, gathered_force, gathered_product, masked_operand,
                       no_strain_func)
from .inputs import INPUT_AIR_DENSITY, INPUT_WIND, INPUT_WIND_NOISE, input_funcs
from .precision import mat33_type, vec3_type

wp.set_module_options({"enable_backward": False})


@functools.cache
def aero_arrays_type(scalar: type):
    """The struct of the aerodynamic family's arrays in one precision."""
    vec3 = vec3_type(scalar)

    @wp.struct
    class AeroArrays:
        indices: wp.array[wp.vec3i]  # [triangle_count]: the three particles, per world
        drag: wp.array2d[scalar]  # C_D [-], [1 or world_count, triangle_count]
        lift: wp.array2d[scalar]  # C_L [-], [1 or world_count, triangle_count]
        noise_scale: wp.array[scalar]  # [1]: the noise's length scale L [m]
        noise_seed: wp.array[wp.int32]  # [1]: the noise's seed
        triangle_force: wp.array[vec3]  # [N], [world_count · triangle_count]: each triangle's force at the state
        #   of the last force evaluation (where precomputed; one entry otherwise)
        incidence: Incidence  # entries (triangle, corner 0..2); padding (0, -1)

    return AeroArrays


@dataclass(frozen=True)
class AeroSpec:
    """Compile-time switches of the aerodynamic family: its incidence table's shape, spatial noise, and
    whether each triangle's force is computed once per force evaluation by ``triangle_forces_kernel`` (then
    gathered by the corners) rather than by each of its three corners."""

    incidence: IncidenceShape
    noise: bool
    precomputed: bool = False

    def funcs(self, scalar: type) -> FamilyFuncs:
        return aero_family_funcs(scalar, self)


@functools.cache
def aero_funcs(scalar: type):
    """The typed maths of the model (module docstring), for tests and the family hooks."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)

    @wp.func
    def triangle_wind_force(xa: vec3, xb: vec3, xc: vec3, va: vec3, vb: vec3, vc: vec3, wind: vec3, rho: scalar,
                            cd: scalar, cl: scalar) -> vec3:
        """Drag plus lift [N] on a triangle with corners x [m] moving at v [m/s] in wind ``wind`` [m/s] (the
        air's velocity at the triangle), air density rho [kg/m³], coefficients cd, cl [-]; 0 for a degenerate
        triangle or no relative flow."""
        twice_area_normal = wp.cross(xb - xa, xc - xa)
        twice_area = wp.length(twice_area_normal)
        u = wind - (va + vb + vc) / scalar(3.0)
        speed_sq = wp.dot(u, u)
        if twice_area <= scalar(0.0) or speed_sq <= scalar(0.0):
            return vec3(scalar(0.0))
        n = twice_area_normal / twice_area
        un = wp.dot(u, n)
        q = scalar(0.25) * rho * twice_area  # ½ ρ A
        drag = (q * cd * wp.abs(un)) * u
        lift = (q * cl * wp.sqrt(speed_sq) * un) * (n - (un / speed_sq) * u)
        return drag + lift

    @wp.func
    def triangle_wind_damping(xa: vec3, xb: vec3, xc: vec3, va: vec3, vb: vec3, vc: vec3, wind: vec3,
                              rho: scalar, cd: scalar, cl: scalar) -> mat33:
        """D_u = ½ ρ A (C_D |u·n| I + (C_D + C_L) |u| n nᵀ) [N·s/m], positive semi-definite (module docstring)."""
        twice_area_normal = wp.cross(xb - xa, xc - xa)
        twice_area = wp.length(twice_area_normal)
        if twice_area <= scalar(0.0):
            return mat33(scalar(0.0))
        n = twice_area_normal / twice_area
        u = wind - (va + vb + vc) / scalar(3.0)
        q = scalar(0.25) * rho * twice_area
        return (q * cd * wp.abs(wp.dot(u, n))) * wp.identity(n=3, dtype=scalar) + (
            q * (cd + cl) * wp.length(u)) * wp.outer(n, n)

    return triangle_wind_force, triangle_wind_damping


@functools.cache
def aero_family_funcs(scalar: type, spec: AeroSpec) -> FamilyFuncs:
    """The family hooks of wind on triangles (``families.py``) for one precision and spec."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    AeroArrays = aero_arrays_type(scalar)
    triangle_wind_force, triangle_wind_damping = aero_funcs(scalar)
    input_vec3 = input_funcs(scalar)
    operand = masked_operand(scalar)

    @wp.func
    def wind_at(world: int, centroid: vec3, aero: AeroArrays, inputs: wp.array2d[scalar]) -> vec3:
        """The wind [m/s] of ``world`` at a point: the input, modulated by the noise where compiled in."""
        wind = input_vec3(inputs, world, INPUT_WIND)
        if wp.static(spec.noise):
            state = wp.rand_init(aero.noise_seed[0])
            p = wp.vec3(centroid / aero.noise_scale[0])
            wind *= scalar(1.0) + inputs[world, INPUT_WIND_NOISE] * scalar(wp.noise(state, p))
        return wind

    @wp.func
    def whole_triangle_force(world: int, t: int, base: int, aero: AeroArrays, inputs: wp.array2d[scalar],
                             particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> vec3:
        """Triangle t's wind force [N] in ``world`` (its particles from entry ``base``)."""
        ids = aero.indices[t]
        xa, xb, xc = particle_q[base + ids[0]], particle_q[base + ids[1]], particle_q[base + ids[2]]
        wind = wind_at(world, (xa + xb + xc) / scalar(3.0), aero, inputs)
        return triangle_wind_force(xa, xb, xc, particle_qd[base + ids[0]], particle_qd[base + ids[1]],
                                   particle_qd[base + ids[2]], wind, inputs[world, INPUT_AIR_DENSITY],
                                   aero.drag[wp.min(world, aero.drag.shape[0] - 1), t],
                                   aero.lift[wp.min(world, aero.lift.shape[0] - 1), t])

    @wp.func
    def triangle_force_on(
        world: int, t: int, corner: int, i: int, base: int, xi: vec3, vi: vec3, aero: AeroArrays,
        inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ) -> vec3:
        """A third of triangle t's wind force [N] (0 for a padding entry, corner -1)."""
        if corner < 0:
            return vec3(scalar(0.0))
        if wp.static(spec.precomputed):
            return aero.triangle_force[world * aero.indices.shape[0] + t] / scalar(3.0)
        return whole_triangle_force(world, t, base, aero, inputs, particle_q, particle_qd) / scalar(3.0)

    @wp.func
    def product_entry(
        world: int, t: int, corner: int, i: int, base: int, aero: AeroArrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
        alpha: scalar, beta: scalar,
    ):
        """β D_u / 9 Σ_b x_b over triangle t's corners b, and the diagonal block β D_u / 9 (no stiffness)."""
        if corner < 0:
            return vec3(scalar(0.0)), mat33(scalar(0.0))
        ids = aero.indices[t]
        a, b, c = base + ids[0], base + ids[1], base + ids[2]
        xa, xb, xc = particle_q[a], particle_q[b], particle_q[c]
        wind = wind_at(world, (xa + xb + xc) / scalar(3.0), aero, inputs)
        # The velocities enter D_u only through u; the analysis's state has them in particle_qd, which the
        # product does not see: D_u is taken at the triangle at rest (u = w), the flow it meets when still.
        zero = vec3(scalar(0.0))
        damping = (beta / scalar(9.0)) * triangle_wind_damping(
            xa, xb, xc, zero, zero, zero, wind, inputs[world, INPUT_AIR_DENSITY],
            aero.drag[wp.min(world, aero.drag.shape[0] - 1), t], aero.lift[wp.min(world, aero.lift.shape[0] - 1), t])
        total = operand(a, particle_flags, x, free_only) + operand(b, particle_flags, x, free_only) + operand(
            c, particle_flags, x, free_only)
        return damping * total, damping

    force = gathered_force(scalar, AeroArrays, spec.incidence, triangle_force_on)
    product = gathered_product(scalar, AeroArrays, spec.incidence, product_entry)

    strain = no_strain_func(scalar, AeroArrays)  # no strain for the guards

    @wp.func
    def energy(world: int, t: int, base: int, aero: AeroArrays, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3]) -> scalar:
        """Wind stores no energy (it does work, which the guards count)."""
        return scalar(0.0)

    @wp.kernel(module="unique", enable_backward=False)
    def triangle_forces(
        # Model:
        particle_count: int,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out (the triangles' forces written into the family's arrays):
        aero_in_out: AeroArrays,
    ):
        """Each triangle's wind force at a state, once (launch over [world_count, triangle_count])."""
        world, t = wp.tid()
        aero_in_out.triangle_force[world * aero_in_out.indices.shape[0] + t] = whole_triangle_force(
            world, t, world * particle_count, aero_in_out, inputs, particle_q, particle_qd)

    idle = spec.incidence.idle() + (() if spec.precomputed else ("triangle_force",))
    return AeroFuncs(AeroArrays, force, product, strain, energy, idle, triangle_forces)


class AeroFuncs(NamedTuple):
    """:class:`FamilyFuncs` and the kernel that precomputes the triangles' forces."""

    arrays: type
    force: Any
    product: Any
    strain: Any
    energy: Any
    idle: tuple
    triangle_forces: Any
