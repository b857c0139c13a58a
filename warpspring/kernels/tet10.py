"""The quadratic (10-node) neo-Hookean tet family: the energy of ``neohookean.py`` integrated over T10 elements at four
Gauss points, plugged into every kernel through the hooks of ``families.py``.

A T10 has its four corners x_0..x_3 and a node at the middle of each edge, x_4..x_9 on the edges (0, 1), (0, 2),
(0, 3), (1, 2), (1, 3), (2, 3); straight at rest, so the rest map is affine: with the linear tet's shape-function
gradients G_c (rows of D_m⁻¹, G_0 = −ΣG_k) and barycentric coordinates L_c, the quadratic shape functions are
N_c = L_c (2L_c − 1) at the corners and N_cd = 4 L_c L_d at the edges, with gradients (4L_c − 1) G_c and
4 (L_c G_d + L_d G_c). At a point the deformation gradient F = Σ_a x_a ⊗ ∇N_a regroups by corner,

    F = Σ_c y_c ⊗ G_c = [y_1 − y_0, y_2 − y_0, y_3 − y_0] D_m⁻¹,   y_c = (4L_c − 1) x_c + 4 Σ_{d ≠ c} L_d x_cd,

so the linear family's ``deformation`` of the four y_c gives it (and Ḟ of the velocities).

**Quadrature.** Four Gauss points q = 0..3 with L_q = α = (5 + 3√5)/20 and the other three L = β = (5 − √5)/20, weight
¼ each, exact for quadratic polynomials: the stiffness at rest, ∇N ⊗ ∇N, is integrated exactly.

**Energy, forces, stiffness, damper** at each Gauss point are the linear family's (``neohookean.py``): Ψ = μ/2 (I_C − 3)
+ λ/2 (J − α)² − μ²/(2λ) per unit rest volume with J = det F, the first Piola stress P = μF + λ(J − α) cof F plus the
Rayleigh damper's β (2μ F sym(FᵀḞ) + λ_L⁻ tr(FᵀḞ) F + λ_L⁺ J̇ cof F), J̇ = cof F : Ḟ; node a's force
f_a = −¼V₀ Σ_q P_q ∇N_a(q). The stiffness (the ``product`` hook) is the Green strain's Gauss-Newton K̃ at each point,
δP = 2μ F sym(FᵀδF) + λ_L⁻ tr(FᵀδF) F + λ_L⁺ (cof F : δF) cof F, (K̃ δx)_a = ¼V₀ Σ_q δP_q ∇N_a(q): symmetric,
positive semi-definite, zero on rigid rotations, and at rest linear elasticity's T10 stiffness. D = βK̃.

Incidence entries are (element, role of the particle: 0..9); padding entries have role −1. No strain for the guards.
By default (``Tet10Spec.precomputed``) a pass computes each element's four P_q once per force evaluation and a node's
entry reads them.
"""

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import warp as wp

from .families import (
    FamilyFuncs,
    Incidence,
    IncidenceShape,
    gathered_force,
    gathered_product,
    masked_operand,
    no_strain_func,
)
from .neohookean import neohookean_tet_funcs
from .precision import mat33_type, vec3_type
from .volume import tet_volume_funcs

wp.set_module_options({"enable_backward": False})

#: The Gauss points' barycentric coordinates: L_q = α at point q, β at the others (weight ¼ each).
QUADRATURE_ALPHA = 0.5854101966249685  # (5 + 3√5)/20
QUADRATURE_BETA = 0.1381966011250105  # (5 − √5)/20

#: A T10's ten particle indices.
vec10i = wp.types.vector(length=10, dtype=wp.int32)


class Tet10Funcs(NamedTuple):
    """The ``@wp.func`` helpers of the element in one precision (see ``tet10_funcs``)."""

    node_gradient: wp.Function
    combine: wp.Function
    deformation_at: wp.Function
    point_stress: wp.Function
    cofactor: wp.Function


@functools.cache
def tet10_combine(scalar: type):
    """``combine(q, x0 … x9, rest_inverse) -> mat33``: F (or Ḟ, δF) at Gauss point q from the ten nodes' values: the
    y_c of the module into the linear family's ``deformation``."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    linear = neohookean_tet_funcs(scalar)

    @wp.func
    def combine(q: int, x0: vec3, x1: vec3, x2: vec3, x3: vec3, x4: vec3, x5: vec3, x6: vec3, x7: vec3, x8: vec3,
                x9: vec3, rest_inverse: mat33) -> mat33:
        l0 = wp.where(q == 0, scalar(0.5854101966249685), scalar(0.1381966011250105))
        l1 = wp.where(q == 1, scalar(0.5854101966249685), scalar(0.1381966011250105))
        l2 = wp.where(q == 2, scalar(0.5854101966249685), scalar(0.1381966011250105))
        l3 = wp.where(q == 3, scalar(0.5854101966249685), scalar(0.1381966011250105))
        four = scalar(4.0)
        one = scalar(1.0)
        y0 = (four * l0 - one) * x0 + four * (l1 * x4 + l2 * x5 + l3 * x6)
        y1 = (four * l1 - one) * x1 + four * (l0 * x4 + l2 * x7 + l3 * x8)
        y2 = (four * l2 - one) * x2 + four * (l0 * x5 + l1 * x7 + l3 * x9)
        y3 = (four * l3 - one) * x3 + four * (l0 * x6 + l1 * x8 + l2 * x9)
        return linear.deformation(y0, y1, y2, y3, rest_inverse)

    return combine


@functools.cache
def tet10_funcs(scalar: type) -> Tet10Funcs:
    """The element's helpers typed by ``scalar``. Positions [m], D_m⁻¹ [1/m] (``rest_inverse``), μ and λ [Pa], β [s];
    Gauss points q = 0..3, nodes (roles) 0..9."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    linear = neohookean_tet_funcs(scalar)
    gradient_of_role = tet_volume_funcs(scalar).gradient_of_role
    combine = tet10_combine(scalar)

    @wp.func
    def bary(c: int, q: int) -> scalar:
        """L_c at Gauss point q."""
        return wp.where(c == q, scalar(0.5854101966249685), scalar(0.1381966011250105))

    @wp.func
    def node_gradient(a: int, q: int, rest_inverse: mat33) -> vec3:
        """∇N_a [1/m] of node a at Gauss point q: (4L_a − 1) G_a at a corner, 4 (L_c G_d + L_d G_c) at edge (c, d)."""
        g1 = rest_inverse[0]
        g2 = rest_inverse[1]
        g3 = rest_inverse[2]
        g0 = -(g1 + g2 + g3)
        if a < 4:
            return (scalar(4.0) * bary(a, q) - scalar(1.0)) * gradient_of_role(a, g0, g1, g2, g3)
        c = wp.where(a < 7, 0, wp.where(a < 9, 1, 2))
        d = wp.where(a == 4, 1, wp.where(a == 5 or a == 7, 2, 3))
        return scalar(4.0) * (bary(c, q) * gradient_of_role(d, g0, g1, g2, g3)
                              + bary(d, q) * gradient_of_role(c, g0, g1, g2, g3))

    @wp.func
    def deformation_at(q: int, ids: vec10i, base: int, values: wp.array[vec3], rest_inverse: mat33) -> mat33:
        """F [-] at Gauss point q of the element with particles ``ids`` (Ḟ [1/s] of velocities)."""
        return combine(q, values[base + ids[0]], values[base + ids[1]], values[base + ids[2]], values[base + ids[3]],
                       values[base + ids[4]], values[base + ids[5]], values[base + ids[6]], values[base + ids[7]],
                       values[base + ids[8]], values[base + ids[9]], rest_inverse)

    @wp.func
    def cofactor(f: mat33) -> mat33:
        """cof F = ∂ det F/∂F: its columns are f_1 × f_2, f_2 × f_0, f_0 × f_1 (f_k F's columns)."""
        f0 = vec3(f[0, 0], f[1, 0], f[2, 0])
        f1 = vec3(f[0, 1], f[1, 1], f[2, 1])
        f2 = vec3(f[0, 2], f[1, 2], f[2, 2])
        return wp.transpose(wp.matrix_from_rows(wp.cross(f1, f2), wp.cross(f2, f0), wp.cross(f0, f1)))

    @wp.func
    def point_stress(f: mat33, rate: mat33, mu: scalar, lam: scalar, beta: scalar) -> mat33:
        """P [Pa] at a point of deformation F and rate Ḟ: μF + λ(J − α) cof F + β (2μ F sym(FᵀḞ) + λ_L⁻ tr(FᵀḞ) F
        + λ_L⁺ J̇ cof F)."""
        g = cofactor(f)
        pressure = lam * ((wp.determinant(f) - scalar(1.0)) - mu / lam) \
            + beta * wp.max(lam - mu, scalar(0.0)) * wp.ddot(g, rate)
        return mu * f + beta * linear.tangent_stress(f, rate, mu, lam) + pressure * g

    return Tet10Funcs(node_gradient, combine, deformation_at, point_stress, cofactor)


@functools.cache
def tet10_arrays_type(scalar: type):
    """The struct of the family's arrays in one precision."""
    mat33 = mat33_type(scalar)

    @wp.struct
    class Tet10Arrays:
        indices: wp.array[vec10i]  # [tet_count]: corners x0 … x3 (wound so that V₀ > 0), then the mid-edge nodes
        rest_volume: wp.array[scalar]  # V₀ [m³], [tet_count], > 0
        rest_inverse: wp.array[mat33]  # D_m⁻¹ [1/m] of the corners, [tet_count]: its rows are G_1, G_2, G_3
        mu: wp.array2d[scalar]  # μ [Pa], [1 or world_count, tet_count]
        lam: wp.array2d[scalar]  # λ [Pa] (> 0; not the Lamé λ_L = λ − μ), [1 or world_count, tet_count]
        damping: wp.array2d[scalar]  # β [s], [1 or world_count, tet_count]
        stress: wp.array[mat33]  # P [Pa] at each Gauss point, [4 · world_count · tet_count] (slot 4(world·T + t) + q),
        #   at the state of the last force evaluation (where precomputed; one entry otherwise)
        incidence: Incidence  # entries (element, role 0..9); padding (0, -1)

    return Tet10Arrays


@dataclass(frozen=True)
class Tet10Spec:
    """Compile-time switches of the quadratic neo-Hookean family: its incidence table's shape, and whether each
    element's four Gauss-point stresses are computed once per force evaluation (``tet10_stresses``) or by every node."""

    incidence: IncidenceShape
    precomputed: bool = False

    def funcs(self, scalar: type) -> FamilyFuncs:
        return tet10_family_funcs(scalar, self)


class Tet10FamilyFuncs(NamedTuple):
    """:class:`FamilyFuncs` and the kernel that precomputes the elements' Gauss-point stresses."""

    arrays: type
    force: Any
    product: Any
    strain: Any
    energy: Any
    idle: tuple
    dissipation: Any
    tet10_stresses: Any


@functools.cache
def tet10_family_funcs(scalar: type, spec: Tet10Spec) -> Tet10FamilyFuncs:
    """The family hooks of quadratic neo-Hookean tets (``families.py``) for one precision and spec."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    Arrays = tet10_arrays_type(scalar)
    funcs = tet10_funcs(scalar)
    linear = neohookean_tet_funcs(scalar)
    operand = masked_operand(scalar)

    @wp.func
    def row(array: wp.array2d[scalar], world: int, t: int) -> scalar:
        return array[wp.min(world, array.shape[0] - 1), t]

    @wp.func
    def gauss_stress(q: int, world: int, t: int, base: int, tets: Arrays, particle_q: wp.array[vec3],
                     particle_qd: wp.array[vec3]) -> mat33:
        """P [Pa] of element t at Gauss point q."""
        ids = tets.indices[t]
        inverse = tets.rest_inverse[t]
        return funcs.point_stress(funcs.deformation_at(q, ids, base, particle_q, inverse),
                                  funcs.deformation_at(q, ids, base, particle_qd, inverse), row(tets.mu, world, t),
                                  row(tets.lam, world, t), row(tets.damping, world, t))

    @wp.func
    def force_entry(
        world: int, t: int, role: int, i: int, base: int, xi: vec3, vi: vec3, tets: Arrays,
        inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ) -> vec3:
        """Force [N] of element t on its node ``role``: −¼V₀ Σ_q P_q ∇N_role(q) (0 for a padding entry, role −1)."""
        if role < 0:
            return vec3(scalar(0.0))
        inverse = tets.rest_inverse[t]
        f = vec3(scalar(0.0))
        slot = 4 * (world * tets.indices.shape[0] + t)
        for q in range(4):
            if wp.static(spec.precomputed):
                stress = tets.stress[slot + q]
            else:
                stress = gauss_stress(q, world, t, base, tets, particle_q, particle_qd)
            f += stress * funcs.node_gradient(role, q, inverse)
        return (scalar(-0.25) * tets.rest_volume[t]) * f

    @wp.func
    def masked_deformation(q: int, ids: vec10i, base: int, particle_flags: wp.array[wp.int32], x: wp.array[vec3],
                           free_only: bool, inverse: mat33) -> mat33:
        """δF at Gauss point q of the operand x, masked (``masked_operand``)."""
        return funcs.combine(q, operand(base + ids[0], particle_flags, x, free_only),
                             operand(base + ids[1], particle_flags, x, free_only),
                             operand(base + ids[2], particle_flags, x, free_only),
                             operand(base + ids[3], particle_flags, x, free_only),
                             operand(base + ids[4], particle_flags, x, free_only),
                             operand(base + ids[5], particle_flags, x, free_only),
                             operand(base + ids[6], particle_flags, x, free_only),
                             operand(base + ids[7], particle_flags, x, free_only),
                             operand(base + ids[8], particle_flags, x, free_only),
                             operand(base + ids[9], particle_flags, x, free_only), inverse)


    @wp.func
    def product_entry(
        world: int, t: int, role: int, i: int, base: int, tets: Arrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
        alpha: scalar, beta: scalar,
    ):
        """Row ``role`` of (α K̃ + β D) x = (α + β β_t) K̃ x for element t (module), and its diagonal block
        (α + β β_t) ¼V₀ Σ_q [μ |g|² F Fᵀ + (μ + λ_L⁻) w wᵀ + λ_L⁺ c cᵀ], g = ∇N_role(q), w = F g, c = cof F g."""
        if role < 0:
            return vec3(scalar(0.0)), mat33(scalar(0.0))
        ids = tets.indices[t]
        inverse = tets.rest_inverse[t]
        mu = row(tets.mu, world, t)
        lam = row(tets.lam, world, t)
        positive = wp.max(lam - mu, scalar(0.0))
        shear = mu + wp.min(lam - mu, scalar(0.0))
        y = vec3(scalar(0.0))
        block = mat33(scalar(0.0))
        for q in range(4):
            f = funcs.deformation_at(q, ids, base, particle_q, inverse)
            cof = funcs.cofactor(f)
            df = masked_deformation(q, ids, base, particle_flags, x, free_only, inverse)
            g = funcs.node_gradient(role, q, inverse)
            y += (linear.tangent_stress(f, df, mu, lam) + (positive * wp.ddot(cof, df)) * cof) * g
            w = f * g
            c = cof * g
            block += (mu * wp.dot(g, g)) * (f * wp.transpose(f)) + shear * wp.outer(w, w) + positive * wp.outer(c, c)
        k = (alpha + beta * row(tets.damping, world, t)) * scalar(0.25) * tets.rest_volume[t]
        return k * y, k * block

    force = gathered_force(scalar, Arrays, spec.incidence, force_entry)
    product = gathered_product(scalar, Arrays, spec.incidence, product_entry)
    strain = no_strain_func(scalar, Arrays)  # no strain for the guards

    @wp.func
    def energy(world: int, t: int, base: int, tets: Arrays, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3]) -> scalar:
        """Elastic energy [J] of element t in ``world`` (zero at rest): ¼V₀ Σ_q [μ/2 (I_C − 3) + λ/2 (J − α)² − μ²/(2λ)]."""
        ids = tets.indices[t]
        inverse = tets.rest_inverse[t]
        mu = row(tets.mu, world, t)
        lam = row(tets.lam, world, t)
        total = scalar(0.0)
        for q in range(4):
            f = funcs.deformation_at(q, ids, base, particle_q, inverse)
            d = (wp.determinant(f) - scalar(1.0)) - mu / lam
            total += scalar(0.5) * mu * (wp.ddot(f, f) - scalar(3.0)) + scalar(0.5) * lam * d * d \
                - scalar(0.5) * mu * mu / lam
        return scalar(0.25) * tets.rest_volume[t] * total

    @wp.func
    def dissipation(world: int, t: int, base: int, tets: Arrays, inputs: wp.array2d[scalar],
                    particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> scalar:
        """Power [W] ≥ 0 the damper of element t takes out in ``world``: β vᵀK̃v = β ¼V₀ Σ_q (2μ |sym C|² + λ_L⁻ (tr C)²
        + λ_L⁺ J̇²), C = FᵀḞ."""
        ids = tets.indices[t]
        inverse = tets.rest_inverse[t]
        mu = row(tets.mu, world, t)
        lam = row(tets.lam, world, t)
        total = scalar(0.0)
        for q in range(4):
            f = funcs.deformation_at(q, ids, base, particle_q, inverse)
            rate = funcs.deformation_at(q, ids, base, particle_qd, inverse)
            c = wp.transpose(f) * rate
            sym = scalar(0.5) * (c + wp.transpose(c))
            trace = wp.trace(c)
            jdot = wp.ddot(funcs.cofactor(f), rate)
            total += scalar(2.0) * mu * wp.ddot(sym, sym) + wp.min(lam - mu, scalar(0.0)) * trace * trace \
                + wp.max(lam - mu, scalar(0.0)) * jdot * jdot
        return row(tets.damping, world, t) * scalar(0.25) * tets.rest_volume[t] * total

    @wp.kernel(module="unique", enable_backward=False)
    def tet10_stresses(
        # Model:
        particle_count: int,
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out (each element's Gauss-point stresses written into the family's arrays):
        tets_in_out: Arrays,
    ):
        """Each element's P at its four Gauss points at a state, once (launch over [world_count, tet_count])."""
        world, t = wp.tid()
        base = world * particle_count
        slot = 4 * (world * tets_in_out.indices.shape[0] + t)
        for q in range(4):
            tets_in_out.stress[slot + q] = gauss_stress(q, world, t, base, tets_in_out, particle_q, particle_qd)

    idle = spec.incidence.idle() + (() if spec.precomputed else ("stress",))
    return Tet10FamilyFuncs(Arrays, force, product, strain, energy, idle, dissipation, tet10_stresses)
