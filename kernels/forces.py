"""Particle forces: springs with axial dampers, gravity, viscous drag and external forces.

Spring forces are gathered per particle through a CSR incidence list (each particle reads the springs
that touch it), so a force evaluation writes every particle's force exactly once: no atomics, the same
summation order on every device, and the force can be fused into an integrator's update kernel.
"""

import functools
from typing import NamedTuple

import warp as wp

from .precision import vec3_type

wp.set_module_options({"enable_backward": False})

#: Particles closer than this [m] are coincident: their spring has no direction and exerts no force.
COINCIDENT_DISTANCE = 1.0e-12


class ForceFeatures(NamedTuple):
    """Which force terms a scene uses; each ``False`` term is compiled out."""

    springs: bool
    gravity: bool
    drag: bool
    external: bool


@functools.cache
def spring_funcs(scalar: type):
    """The spring force and energy functions of one precision."""
    vec3 = vec3_type(scalar)

    @wp.func
    def spring_force(
        xi: vec3, xj: vec3, vi: vec3, vj: vec3, rest: scalar, ke: scalar, kd: scalar
    ) -> vec3:
        """Force [N] on particle i of the spring (i, j): (ke (|d| - L) + kd (vj - vi)·d̂) d̂, d = xj - xi.

        Coincident particles (|d| below ``COINCIDENT_DISTANCE``) give a zero force, never NaN.
        """
        d = xj - xi
        length = wp.length(d)
        if length <= scalar(COINCIDENT_DISTANCE):
            return vec3(scalar(0.0))
        n = d / length
        return n * (ke * (length - rest) + kd * wp.dot(vj - vi, n))

    @wp.func
    def spring_energy(xi: vec3, xj: vec3, rest: scalar, ke: scalar) -> scalar:
        """Elastic energy [J] of the spring (i, j): ½ ke (|xj - xi| - L)²."""
        stretch = wp.length(xj - xi) - rest
        return scalar(0.5) * ke * stretch * stretch

    @wp.func
    def gather_spring_forces(
        i: int,
        xi: vec3,
        vi: vec3,
        # Model:
        particle_spring_offset: wp.array[wp.int32],
        particle_spring_neighbor: wp.array[wp.int32],
        particle_spring_id: wp.array[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array[scalar],
        spring_damping: wp.array[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
    ) -> vec3:
        """Sum of the forces [N] of all springs incident to particle i."""
        f = vec3(scalar(0.0))
        for e in range(particle_spring_offset[i], particle_spring_offset[i + 1]):
            j = particle_spring_neighbor[e]
            s = particle_spring_id[e]
            f += spring_force(
                xi, particle_q[j], vi, particle_qd[j], spring_rest_length[s], spring_stiffness[s], spring_damping[s]
            )
        return f

    return spring_force, spring_energy, gather_spring_forces


@functools.cache
def particle_force_func(scalar: type, features: ForceFeatures):
    """The total force on one particle, specialized for the scene's force terms."""
    vec3 = vec3_type(scalar)
    _, _, gather_spring_forces = spring_funcs(scalar)

    @wp.func
    def particle_force(
        i: int,
        xi: vec3,
        vi: vec3,
        # Model:
        particle_mass: wp.array[scalar],
        particle_spring_offset: wp.array[wp.int32],
        particle_spring_neighbor: wp.array[wp.int32],
        particle_spring_id: wp.array[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array[scalar],
        spring_damping: wp.array[scalar],
        gravity: vec3,
        drag: scalar,
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
    ) -> vec3:
        """Force [N] on particle i: m g - drag v + f_ext + springs."""
        f = vec3(scalar(0.0))
        if wp.static(features.gravity):
            f += particle_mass[i] * gravity
        if wp.static(features.drag):
            f -= drag * vi
        if wp.static(features.external):
            f += particle_force_ext[i]
        if wp.static(features.springs):
            f += gather_spring_forces(
                i,
                xi,
                vi,
                particle_spring_offset,
                particle_spring_neighbor,
                particle_spring_id,
                spring_rest_length,
                spring_stiffness,
                spring_damping,
                particle_q,
                particle_qd,
            )
        return f

    return particle_force


@functools.cache
def eval_forces_kernel(scalar: type, features: ForceFeatures):
    """Kernel writing the total force on every particle (one thread per particle)."""
    vec3 = vec3_type(scalar)
    particle_force = particle_force_func(scalar, features)

    @wp.kernel(module="unique", enable_backward=False)
    def eval_forces(
        # Model:
        particle_mass: wp.array[scalar],
        particle_spring_offset: wp.array[wp.int32],
        particle_spring_neighbor: wp.array[wp.int32],
        particle_spring_id: wp.array[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array[scalar],
        spring_damping: wp.array[scalar],
        gravity: vec3,
        drag: scalar,
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Out:
        particle_f: wp.array[vec3],
    ):
        i = wp.tid()
        particle_f[i] = particle_force(
            i,
            particle_q[i],
            particle_qd[i],
            particle_mass,
            particle_spring_offset,
            particle_spring_neighbor,
            particle_spring_id,
            spring_rest_length,
            spring_stiffness,
            spring_damping,
            gravity,
            drag,
            particle_force_ext,
            particle_q,
            particle_qd,
        )

    return eval_forces
