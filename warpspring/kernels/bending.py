"""Dihedral (angular) bending of triangle meshes: the hinge angle, its gradient, forces and Hessian blocks.

A hinge is four particles (x0, x1, x2, x3): the shared edge e = x1 - x0, the wing x2 of the triangle
(x0, x1, x2) and the wing x3 of the triangle (x1, x0, x3), both wound as a mesh's faces are. Their
normals n1 = e × (x2 - x0) and n2 = (x3 - x0) × e point to the same side when the hinge is flat, and the
signed dihedral angle is

    θ = atan2((n̂1 × n̂2)·ê, n̂1·n̂2) ∈ (-π, π],

0 for a flat hinge and positive when the wings fold away from the side the normals point to (a closed
surface with outward normals, such as a sphere, has θ > 0 on every hinge; θ → π as the wings close).

The energy E = ½ ke wrap(θ - θ0)² has the force f_a = -(ke wrap(θ - θ0) + kd θ̇) ∇_a θ on particle a, with
θ̇ = Σ_b ∇_b θ · v_b: an angular spring [N·m/rad] and an angular damper [N·m·s/rad]. The gradient is the
closed form of Bridson, Marino & Fedkiw (2003), "Simulation of clothing with folds and wrinkles":

    ∇₂θ = -|e| n1/|n1|²,   ∇₃θ = -|e| n2/|n2|²,   ∇₁θ = -(α₂ ∇₂θ + α₃ ∇₃θ),   ∇₀θ = -(∇₁θ + ∇₂θ + ∇₃θ),

with α_w = (x_w - x0)·e/|e|² the position along the edge of the foot of wing w. The last line makes the
gradient sum to zero by construction (Σ_a ∇_a θ = 0: the forces exert no net force); being invariant
under rotation, the angle's forces also exert no net torque.

Hinges with a zero-length edge or a degenerate wing (height below ``HINGE_MIN_ASPECT`` |e|) have θ = 0
and a zero gradient: no force and no stiffness, never NaN.
"""

import functools
import math
from typing import NamedTuple

import warp as wp

from .families import four_point_funcs
from .precision import mat33_type, vec3_type

wp.set_module_options({"enable_backward": False})

# Python floats, not ``wp.pi`` arithmetic: ``2.0 * wp.pi`` in a kernel is a float32 product.
_PI = math.pi
_TWO_PI = 2.0 * math.pi

#: Hinges whose shared edge is shorter than this [m] are degenerate.
HINGE_MIN_EDGE = 1.0e-12

#: Hinges with a wing whose height over the edge is below this fraction of the edge's length [-] are
#: degenerate: float32 rounding of a collinear wing alone gives ~1e-7, and the gradient grows as 1/height.
HINGE_MIN_ASPECT = 1.0e-6


class DihedralFuncs(NamedTuple):
    """The ``@wp.func`` helpers of dihedral bending in one precision (see ``dihedral_funcs``)."""

    dihedral_angle_gradient: wp.Function
    gradient_of_role: wp.Function
    wrap_angle: wp.Function
    hinge_energy: wp.Function
    hinge_moment: wp.Function
    hinge_force: wp.Function
    hinge_stiffness_block: wp.Function


@functools.cache
def dihedral_funcs(scalar: type) -> DihedralFuncs:
    """The dihedral-bending helpers typed by ``scalar`` (``wp.float32`` or ``wp.float64``).

    Particle roles are 0, 1 (the edge x0 → x1), 2 and 3 (the wings of the triangles (x0, x1, x2) and
    (x1, x0, x3)); positions [m], velocities [m/s], angles [rad].
    """
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)

    @wp.func
    def dihedral_angle_gradient(x0: vec3, x1: vec3, x2: vec3, x3: vec3) -> tuple[scalar, vec3, vec3, vec3, vec3]:
        """The dihedral angle θ [rad] of a hinge and its gradients ∇₀θ … ∇₃θ [rad/m] (module docstring).

        A degenerate hinge (edge below ``HINGE_MIN_EDGE``, or a wing below ``HINGE_MIN_ASPECT`` |e| from
        the edge's line) gives θ = 0 and zero gradients.
        """
        e = x1 - x0
        n1 = wp.cross(e, x2 - x0)
        n2 = wp.cross(x3 - x0, e)
        len_e = wp.length(e)
        len_n1 = wp.length(n1)
        len_n2 = wp.length(n2)
        # |n_w| = |e| × height of wing w: compare the heights with HINGE_MIN_ASPECT |e|.
        min_n = scalar(HINGE_MIN_ASPECT) * len_e * len_e
        valid = len_e > scalar(HINGE_MIN_EDGE) and len_n1 > min_n and len_n2 > min_n
        # Branch-light guard: every inverse is 0 on a degenerate hinge, so θ = atan2(0, 0) = 0 and g = 0.
        inv_e = wp.where(valid, scalar(1.0) / len_e, scalar(0.0))
        inv_n1 = wp.where(valid, scalar(1.0) / len_n1, scalar(0.0))
        inv_n2 = wp.where(valid, scalar(1.0) / len_n2, scalar(0.0))
        e_hat = e * inv_e
        u1 = n1 * inv_n1
        u2 = n2 * inv_n2
        theta = wp.atan2(wp.dot(wp.cross(u1, u2), e_hat), wp.dot(u1, u2))
        # |e|/|n_w| = 1/height of wing w: moving the wing by δ along -n̂_w turns its triangle by δ/height.
        g2 = u1 * (-len_e * inv_n1)
        g3 = u2 * (-len_e * inv_n2)
        alpha2 = wp.dot(x2 - x0, e_hat) * inv_e
        alpha3 = wp.dot(x3 - x0, e_hat) * inv_e
        g1 = -(alpha2 * g2 + alpha3 * g3)
        g0 = -(g1 + g2 + g3)
        return theta, g0, g1, g2, g3

    gradient_of_role = four_point_funcs(scalar).gradient_of_role

    @wp.func
    def wrap_angle(angle: scalar) -> scalar:
        """``angle`` [rad] wrapped into (-π, π] (unchanged there)."""
        return angle - scalar(_TWO_PI) * wp.ceil((angle - scalar(_PI)) / scalar(_TWO_PI))

    @wp.func
    def hinge_energy(x0: vec3, x1: vec3, x2: vec3, x3: vec3, rest: scalar, ke: scalar) -> scalar:
        """Elastic energy [J] ½ ke wrap(θ - θ0)² of a hinge with rest angle θ0 = ``rest`` [rad] and
        stiffness ``ke`` [N·m/rad]."""
        theta, _, _, _, _ = dihedral_angle_gradient(x0, x1, x2, x3)  # the compiler drops the gradient
        d = wrap_angle(theta - rest)
        return scalar(0.5) * ke * d * d

    @wp.func
    def hinge_moment(
        theta: scalar,
        g0: vec3,
        g1: vec3,
        g2: vec3,
        g3: vec3,
        v0: vec3,
        v1: vec3,
        v2: vec3,
        v3: vec3,
        rest: scalar,
        ke: scalar,
        kd: scalar,
    ) -> scalar:
        """The hinge's moment [N·m] ke wrap(θ - θ0) + kd θ̇, θ̇ = Σ_b ∇_b θ · v_b, from θ and its gradient:
        the force on particle a is -moment ∇_a θ (one angle evaluation serves all four particles)."""
        theta_dot = wp.dot(g0, v0) + wp.dot(g1, v1) + wp.dot(g2, v2) + wp.dot(g3, v3)
        return ke * wrap_angle(theta - rest) + kd * theta_dot

    @wp.func
    def hinge_force(
        role: int,
        x0: vec3,
        x1: vec3,
        x2: vec3,
        x3: vec3,
        v0: vec3,
        v1: vec3,
        v2: vec3,
        v3: vec3,
        rest: scalar,
        ke: scalar,
        kd: scalar,
    ) -> vec3:
        """Force [N] on particle ``role`` (0..3) of a hinge: -(ke wrap(θ - θ0) + kd θ̇) ∇_role θ, with the
        rest angle θ0 = ``rest`` [rad], stiffness ``ke`` [N·m/rad] and damping ``kd`` [N·m·s/rad]."""
        theta, g0, g1, g2, g3 = dihedral_angle_gradient(x0, x1, x2, x3)
        moment = hinge_moment(theta, g0, g1, g2, g3, v0, v1, v2, v3, rest, ke, kd)
        return -moment * gradient_of_role(role, g0, g1, g2, g3)

    @wp.func
    def hinge_stiffness_block(role_a: int, role_b: int, x0: vec3, x1: vec3, x2: vec3, x3: vec3, k: scalar) -> mat33:
        """The block k ∇_aθ ∇_bθᵀ of a hinge's 12 × 12 matrix k ∇θ ∇θᵀ (rank one, positive semi-definite).

        With k = ke [N·m/rad] it is the Gauss-Newton Hessian ∂²E/∂x_a∂x_b ≈ -∂f_a/∂x_b [N/m]: the term
        ke wrap(θ - θ0) ∇²θ is dropped (exact at θ = θ0), which keeps the matrix semi-definite for
        implicit Euler. With k = kd [N·m·s/rad] it is the damping block -∂f_a/∂v_b [N·s/m], exactly.
        """
        _, g0, g1, g2, g3 = dihedral_angle_gradient(x0, x1, x2, x3)
        return k * wp.outer(gradient_of_role(role_a, g0, g1, g2, g3), gradient_of_role(role_b, g0, g1, g2, g3))

    return DihedralFuncs(
        dihedral_angle_gradient,
        gradient_of_role,
        wrap_angle,
        hinge_energy,
        hinge_moment,
        hinge_force,
        hinge_stiffness_block,
    )
