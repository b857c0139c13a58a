"""The tet volume family: a volumetric (bulk) energy per tetrahedron of a soft body, so that a body of springs
resists a change of volume and an inverted tet is pushed back, plugged into every kernel through the hooks of
``families.py``.

Tet t joins particles (x0, x1, x2, x3), wound so that its rest volume V₀ is positive. Its signed volume

    V = (x1 - x0) · ((x2 - x0) × (x3 - x0)) / 6

is negative once the tet is inverted (a vertex pushed through its opposite face), where the six springs of a
mass-spring body may all be near rest again. With J = V / V₀ the energy is the volumetric part of linear
elasticity for a bulk modulus K [Pa],

    E = ½ K V₀ (J - 1)² = ½ (K / V₀) (V - V₀)²,

Teschner, Heidelberger, Müller, Pomeranets & Gross (2004), "Versatile and efficient techniques for simulating
deformable objects" (volume preservation: the constraint C = V - V₀ on the signed volume, energy ½ k C²), with
their stiffness k = K / V₀ so that a tet strained uniformly by ε stores the bulk energy ½ K (tr ε)² V₀ whatever
its size. Being signed, J < 0 costs more than J = 0: an inverted tet is pushed back, never held mirrored.

The force on particle a is f_a = -(K (J - 1) + kd J̇) ∇_a V, with the volume gradient (the closed form of the
triple product)

    ∇₁V = (x2 - x0) × (x3 - x0) / 6,   ∇₂V = (x3 - x0) × (x1 - x0) / 6,   ∇₃V = (x1 - x0) × (x2 - x0) / 6,
    ∇₀V = -(∇₁V + ∇₂V + ∇₃V),

and J̇ = Σ_b ∇_b V · v_b / V₀ (a volumetric damper of viscosity kd [Pa·s]). The forces sum to zero and, V being
invariant under rotation, exert no torque. The stiffness matrix is the Gauss-Newton K_ab = (K / V₀) ∇_aV ∇_bVᵀ
(positive semi-definite; the term K (J - 1) ∇²V, indefinite, is dropped: exact at rest), the damping matrix
D_ab = (kd / V₀) ∇_aV ∇_bVᵀ exactly. Incidence entries are (tet, role of the particle: 0..3); padding entries
have role -1 and contribute nothing. The family has no strain for the guards (a compression is not a tear).
Worlds: K and kd have one row for every world or one per world; V₀ is shared.
"""

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import warp as wp

from .families import (FamilyFuncs, Incidence, IncidenceShape, four_point_funcs, gathered_force,
                       gathered_product, no_strain_func)
from .precision import mat33_type, vec3_type

wp.set_module_options({"enable_backward": False})


class TetVolumeFuncs(NamedTuple):
    """The ``@wp.func`` helpers of the volume term in one precision (see ``tet_volume_funcs``)."""

    tet_volume_gradient: wp.Function
    gradient_of_role: wp.Function
    corner_gradient: wp.Function
    tet_pressure: wp.Function
    tet_energy: wp.Function
    tet_force: wp.Function


@functools.cache
def tet_volume_funcs(scalar: type) -> TetVolumeFuncs:
    """The volume-term helpers typed by ``scalar`` (``wp.float32`` or ``wp.float64``).

    Particle roles are 0..3 (the tet's corners as wound); positions [m], velocities [m/s], volumes [m³], bulk
    modulus [Pa], volumetric viscosity [Pa·s].
    """
    vec3 = vec3_type(scalar)

    @wp.func
    def tet_volume_gradient(x0: vec3, x1: vec3, x2: vec3, x3: vec3) -> tuple[scalar, vec3, vec3, vec3, vec3]:
        """The signed volume V [m³] of the tet (x0, x1, x2, x3) and its gradients ∇₀V … ∇₃V [m²]."""
        sixth = scalar(1.0) / scalar(6.0)  # (a literal 1/6 would reach the kernel rounded to float32)
        e1 = x1 - x0
        e2 = x2 - x0
        e3 = x3 - x0
        g1 = wp.cross(e2, e3) * sixth
        g2 = wp.cross(e3, e1) * sixth
        g3 = wp.cross(e1, e2) * sixth
        return wp.dot(e1, g1), -(g1 + g2 + g3), g1, g2, g3

    gradient_of_role = four_point_funcs(scalar).gradient_of_role

    @wp.func
    def corner_gradient(role: int, x0: vec3, x1: vec3, x2: vec3, x3: vec3) -> vec3:
        """∇_role V [m²] alone, from the face opposite corner ``role`` (0..3): ±(x_c - x_b) × (x_d - x_b)/6 with
        (b, c, d) the corners after it in cyclic order, + for odd roles and - for even ones (equal to
        ``tet_volume_gradient``'s, one cross product instead of three)."""
        b = wp.where(role == 0, x1, wp.where(role == 1, x2, wp.where(role == 2, x3, x0)))
        c = wp.where(role == 0, x2, wp.where(role == 1, x3, wp.where(role == 2, x0, x1)))
        d = wp.where(role == 0, x3, wp.where(role == 1, x0, wp.where(role == 2, x1, x2)))
        sign = wp.where(role % 2 == 1, scalar(1.0), scalar(-1.0))
        return wp.cross(c - b, d - b) * (sign / scalar(6.0))

    @wp.func
    def tet_pressure(volume: scalar, rate: scalar, rest: scalar, bulk: scalar, viscosity: scalar) -> scalar:
        """The tet's pressure-like factor K (J - 1) + kd J̇ [Pa], J = V/V₀, J̇ = V̇/V₀, from its volume V [m³], volume
        rate V̇ [m³/s], rest volume V₀ [m³] > 0, bulk modulus K [Pa] and viscosity kd [Pa·s]: the force on corner a
        is -factor · ∇_aV (positive: the tet is too large and is pulled in)."""
        inv_rest = scalar(1.0) / rest
        return bulk * (volume - rest) * inv_rest + viscosity * rate * inv_rest

    @wp.func
    def tet_energy(x0: vec3, x1: vec3, x2: vec3, x3: vec3, rest: scalar, bulk: scalar) -> scalar:
        """Elastic energy [J] ½ K V₀ (J - 1)² = ½ (K/V₀)(V - V₀)² of a tet of rest volume V₀ = ``rest`` [m³]."""
        volume, _, _, _, _ = tet_volume_gradient(x0, x1, x2, x3)  # the compiler drops the gradient
        d = volume - rest
        return scalar(0.5) * bulk * d * d / rest

    @wp.func
    def tet_force(
        role: int, x0: vec3, x1: vec3, x2: vec3, x3: vec3, v0: vec3, v1: vec3, v2: vec3, v3: vec3, rest: scalar,
        bulk: scalar, viscosity: scalar,
    ) -> vec3:
        """Force [N] on corner ``role`` (0..3) of a tet: -(K (J - 1) + kd J̇) ∇_role V."""
        volume, g0, g1, g2, g3 = tet_volume_gradient(x0, x1, x2, x3)
        rate = wp.dot(g0, v0) + wp.dot(g1, v1) + wp.dot(g2, v2) + wp.dot(g3, v3)
        return -tet_pressure(volume, rate, rest, bulk, viscosity) * gradient_of_role(role, g0, g1, g2, g3)

    return TetVolumeFuncs(tet_volume_gradient, gradient_of_role, corner_gradient, tet_pressure, tet_energy, tet_force)


@functools.cache
def volume_arrays_type(scalar: type):
    """The struct of the volume family's arrays in one precision."""

    @wp.struct
    class VolumeArrays:
        indices: wp.array[wp.vec4i]  # [tet_count]: x0 … x3, wound so that V₀ > 0, per-world indices
        rest_volume: wp.array[scalar]  # V₀ [m³], [tet_count], > 0
        bulk_modulus: wp.array2d[scalar]  # K [Pa], [1 or world_count, tet_count]
        viscosity: wp.array2d[scalar]  # kd [Pa·s], [1 or world_count, tet_count]
        pressure: wp.array[scalar]  # K (J - 1) + kd J̇ [Pa], [world_count · tet_count], each tet's at the state of the
        #   last force evaluation (where precomputed; one entry otherwise)
        incidence: Incidence  # entries (tet, role 0..3); padding (0, -1)

    return VolumeArrays


@dataclass(frozen=True)
class VolumeSpec:
    """Compile-time switches of the volume family: the shape of its incidence table, and whether each tet's
    factor K (J - 1) + kd J̇ is computed once per force evaluation by ``tet_pressures`` (then the gather reads it
    and computes only its corner's gradient) or by every corner's entry."""

    incidence: IncidenceShape
    precomputed: bool = False

    def funcs(self, scalar: type) -> FamilyFuncs:
        return volume_family_funcs(scalar, self)


class VolumeFuncs(NamedTuple):
    """:class:`FamilyFuncs` and the kernel that precomputes the tets' factors."""

    arrays: type
    force: Any
    product: Any
    strain: Any
    energy: Any
    idle: tuple
    tet_pressures: Any


@functools.cache
def volume_family_funcs(scalar: type, spec: VolumeSpec) -> VolumeFuncs:
    """The family hooks of tet volumes (``families.py``) for one precision and spec."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    VolumeArrays = volume_arrays_type(scalar)
    funcs = tet_volume_funcs(scalar)
    volume_gradient = funcs.tet_volume_gradient
    corner_gradient = funcs.corner_gradient
    tet_pressure = funcs.tet_pressure
    gauss_newton_entry = four_point_funcs(scalar).gauss_newton_entry

    @wp.func
    def whole_tet_pressure(world: int, t: int, base: int, tets: VolumeArrays, particle_q: wp.array[vec3],
                           particle_qd: wp.array[vec3]) -> scalar:
        """Tet t's factor K (J - 1) + kd J̇ [Pa] in ``world``."""
        ids = tets.indices[t]
        volume, g0, g1, g2, g3 = volume_gradient(particle_q[base + ids[0]], particle_q[base + ids[1]],
                                                 particle_q[base + ids[2]], particle_q[base + ids[3]])
        rate = wp.dot(g0, particle_qd[base + ids[0]]) + wp.dot(g1, particle_qd[base + ids[1]])
        rate += wp.dot(g2, particle_qd[base + ids[2]]) + wp.dot(g3, particle_qd[base + ids[3]])
        return tet_pressure(volume, rate, tets.rest_volume[t],
                            tets.bulk_modulus[wp.min(world, tets.bulk_modulus.shape[0] - 1), t],
                            tets.viscosity[wp.min(world, tets.viscosity.shape[0] - 1), t])

    @wp.func
    def tet_force_on(
        world: int, t: int, role: int, i: int, base: int, xi: vec3, vi: vec3, tets: VolumeArrays,
        inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ) -> vec3:
        """Force [N] of tet t on its corner ``role`` (0 for a padding entry, role -1)."""
        if role < 0:
            return vec3(scalar(0.0))
        ids = tets.indices[t]
        if wp.static(spec.precomputed):
            factor = tets.pressure[world * tets.indices.shape[0] + t]
        else:
            factor = whole_tet_pressure(world, t, base, tets, particle_q, particle_qd)
        return -factor * corner_gradient(role, particle_q[base + ids[0]], particle_q[base + ids[1]],
                                         particle_q[base + ids[2]], particle_q[base + ids[3]])

    @wp.func
    def product_entry(
        world: int, t: int, role: int, i: int, base: int, tets: VolumeArrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
        alpha: scalar, beta: scalar,
    ):
        """((α K + β kd) / V₀) ∇_role V Σ_b ∇_b V · x_b for tet t, and its diagonal block."""
        if role < 0:
            return vec3(scalar(0.0)), mat33(scalar(0.0))
        ids = tets.indices[t]
        _, g0, g1, g2, g3 = volume_gradient(particle_q[base + ids[0]], particle_q[base + ids[1]],
                                            particle_q[base + ids[2]], particle_q[base + ids[3]])
        k = (alpha * tets.bulk_modulus[wp.min(world, tets.bulk_modulus.shape[0] - 1), t]
             + beta * tets.viscosity[wp.min(world, tets.viscosity.shape[0] - 1), t]) / tets.rest_volume[t]
        product, block = gauss_newton_entry(k, role, base, ids, g0, g1, g2, g3, particle_flags, x, free_only)
        return product, block

    force = gathered_force(scalar, VolumeArrays, spec.incidence, tet_force_on)
    product = gathered_product(scalar, VolumeArrays, spec.incidence, product_entry)

    strain = no_strain_func(scalar, VolumeArrays)  # no strain for the guards

    @wp.func
    def energy(world: int, t: int, base: int, tets: VolumeArrays, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3]) -> scalar:
        """Elastic energy [J] of tet t in ``world``."""
        ids = tets.indices[t]
        return funcs.tet_energy(particle_q[base + ids[0]], particle_q[base + ids[1]], particle_q[base + ids[2]],
                                particle_q[base + ids[3]], tets.rest_volume[t],
                                tets.bulk_modulus[wp.min(world, tets.bulk_modulus.shape[0] - 1), t])

    @wp.kernel(module="unique", enable_backward=False)
    def tet_pressures(
        # Model:
        particle_count: int,
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out (each tet's pressure written into the family's arrays):
        tets_in_out: VolumeArrays,
    ):
        """Each tet's factor K (J - 1) + kd J̇ at a state, once (launch over [world_count, tet_count])."""
        world, t = wp.tid()
        tets_in_out.pressure[world * tets_in_out.indices.shape[0] + t] = whole_tet_pressure(
            world, t, world * particle_count, tets_in_out, particle_q, particle_qd)

    idle = spec.incidence.idle() + (() if spec.precomputed else ("pressure",))
    return VolumeFuncs(VolumeArrays, force, product, strain, energy, idle, tet_pressures)
