"""The hinge family: dihedral (angular) springs with angular dampers on the interior edges of a triangle
mesh, plugged into every kernel through the hooks of ``families.py`` (the maths is in ``bending.py``).

Hinge h joins particles (x0, x1, x2, x3) (shared edge x0 → x1, wings x2 and x3) with the energy
½ ke wrap(θ - θ0)² and the force f_a = -(ke wrap(θ - θ0) + kd θ̇) ∇_a θ. Its stiffness matrix is the
Gauss-Newton K = ke ∇θ ∇θᵀ (positive semi-definite; the ke (θ - θ0) ∇²θ term is dropped, exact at rest),
its damping matrix D = kd ∇θ ∇θᵀ (exact). Incidence entries are (hinge, role of the particle: 0..3);
padding entries have role -1 and contribute nothing. Hinges have no strain for the guards (a fold is not a
tear). Worlds: stiffness and damping have one row for every world or one per world.
"""

import functools
from dataclasses import dataclass

import warp as wp

from .bending import dihedral_funcs
from .families import (FamilyFuncs, Incidence, IncidenceShape, four_point_funcs, gathered_force,
                       gathered_product, no_strain_func)
from .precision import mat33_type, vec3_type

wp.set_module_options({"enable_backward": False})


@functools.cache
def hinge_arrays_type(scalar: type):
    """The struct of the hinge family's arrays in one precision."""

    @wp.struct
    class HingeArrays:
        indices: wp.array[wp.vec4i]  # [hinge_count]: x0, x1 (the shared edge), x2, x3 (the wings), per world
        rest_angle: wp.array[scalar]  # θ0 [rad], [hinge_count]
        stiffness: wp.array2d[scalar]  # ke [N·m/rad], [1 or world_count, hinge_count]
        damping: wp.array2d[scalar]  # kd [N·m·s/rad], [1 or world_count, hinge_count]
        incidence: Incidence  # entries (hinge, role 0..3); padding (0, -1)

    return HingeArrays


@dataclass(frozen=True)
class HingeSpec:
    """Compile-time switches of the hinge family: the shape of its incidence table."""

    incidence: IncidenceShape

    def funcs(self, scalar: type) -> FamilyFuncs:
        return hinge_family_funcs(scalar, self)


@functools.cache
def hinge_family_funcs(scalar: type, spec: HingeSpec) -> FamilyFuncs:
    """The family hooks of hinges (``families.py``) for one precision and spec."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    HingeArrays = hinge_arrays_type(scalar)
    bending = dihedral_funcs(scalar)
    angle_gradient = bending.dihedral_angle_gradient
    gradient_of_role = bending.gradient_of_role
    hinge_moment = bending.hinge_moment
    gauss_newton_entry = four_point_funcs(scalar).gauss_newton_entry

    @wp.func
    def hinge_force_on(
        world: int, h: int, role: int, i: int, base: int, xi: vec3, vi: vec3, hinges: HingeArrays,
        inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ) -> vec3:
        """Force [N] of hinge h on its particle ``role`` (0 for a padding entry, role -1)."""
        if role < 0:
            return vec3(scalar(0.0))
        ids = hinges.indices[h]
        theta, g0, g1, g2, g3 = angle_gradient(particle_q[base + ids[0]], particle_q[base + ids[1]],
                                               particle_q[base + ids[2]], particle_q[base + ids[3]])
        moment = hinge_moment(theta, g0, g1, g2, g3, particle_qd[base + ids[0]], particle_qd[base + ids[1]],
                              particle_qd[base + ids[2]], particle_qd[base + ids[3]], hinges.rest_angle[h],
                              hinges.stiffness[wp.min(world, hinges.stiffness.shape[0] - 1), h],
                              hinges.damping[wp.min(world, hinges.damping.shape[0] - 1), h])
        return -moment * gradient_of_role(role, g0, g1, g2, g3)

    @wp.func
    def product_entry(
        world: int, h: int, role: int, i: int, base: int, hinges: HingeArrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
        alpha: scalar, beta: scalar,
    ):
        """(α ke + β kd) ∇_role θ Σ_b ∇_b θ · x_b for hinge h, and its diagonal block."""
        if role < 0:
            return vec3(scalar(0.0)), mat33(scalar(0.0))
        ids = hinges.indices[h]
        theta, g0, g1, g2, g3 = angle_gradient(particle_q[base + ids[0]], particle_q[base + ids[1]],
                                               particle_q[base + ids[2]], particle_q[base + ids[3]])
        k = alpha * hinges.stiffness[wp.min(world, hinges.stiffness.shape[0] - 1), h] + beta * hinges.damping[
            wp.min(world, hinges.damping.shape[0] - 1), h]
        product, block = gauss_newton_entry(k, role, base, ids, g0, g1, g2, g3, particle_flags, x, free_only)
        return product, block

    force = gathered_force(scalar, HingeArrays, spec.incidence, hinge_force_on)
    product = gathered_product(scalar, HingeArrays, spec.incidence, product_entry)

    strain = no_strain_func(scalar, HingeArrays)  # no strain for the guards

    @wp.func
    def energy(world: int, h: int, base: int, hinges: HingeArrays, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3]) -> scalar:
        """Elastic energy [J] of hinge h in ``world``."""
        ids = hinges.indices[h]
        return bending.hinge_energy(particle_q[base + ids[0]], particle_q[base + ids[1]], particle_q[base + ids[2]],
                                    particle_q[base + ids[3]], hinges.rest_angle[h],
                                    hinges.stiffness[wp.min(world, hinges.stiffness.shape[0] - 1), h])

    @wp.func
    def dissipation(world: int, h: int, base: int, hinges: HingeArrays, inputs: wp.array2d[scalar],
                    particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> scalar:
        """Power [W] the angular damper of hinge h takes out in ``world``: kd θ̇² ≥ 0, θ̇ = Σ_b ∇_b θ · v_b."""
        ids = hinges.indices[h]
        theta, g0, g1, g2, g3 = angle_gradient(particle_q[base + ids[0]], particle_q[base + ids[1]],
                                               particle_q[base + ids[2]], particle_q[base + ids[3]])
        rate = wp.dot(g0, particle_qd[base + ids[0]]) + wp.dot(g1, particle_qd[base + ids[1]])
        rate += wp.dot(g2, particle_qd[base + ids[2]]) + wp.dot(g3, particle_qd[base + ids[3]])
        return hinges.damping[wp.min(world, hinges.damping.shape[0] - 1), h] * rate * rate

    return FamilyFuncs(HingeArrays, force, product, strain, energy, spec.incidence.idle(), dissipation=dissipation)
