"""The neo-Hookean tet family: a tetrahedral body's elasticity carried by its tets (instead of springs along their
edges), plugged into every kernel through the hooks of ``families.py``.

Tet t joins particles (x0, x1, x2, x3), wound so that its rest volume V₀ is positive. With the rest edge matrix
D_m = [X1 - X0, X2 - X0, X3 - X0] (columns) and the current one D_s, the deformation gradient is
F = D_s D_m⁻¹ = Σ_a x_a ⊗ G_a, where the shape-function gradients G_1, G_2, G_3 are the rows of D_m⁻¹ and
G_0 = -(G_1 + G_2 + G_3). With J = det F = V/V₀ (V the signed volume) and I_C = tr(FᵀF) = |F|², the energy is

    Ψ = V₀ [ μ/2 (I_C - 3) + λ/2 (J - α)² ],   α = 1 + μ/λ,

the stable neo-Hookean energy of Smith, de Goes & Kim (2018), "Stable Neo-Hookean Flesh Simulation", without its
log term: rest-stable (below), rotation invariant (I_C and J are), and, J being signed, an inverted tet costs more
than a flat one and is pushed back. The energy hook reports Ψ - Ψ_rest, Ψ_rest = V₀ μ²/(2λ) (zero at rest; a
constant changes no force).

**Linearisation at rest.** With F = I + H (H = ∇u small, ε = sym H, tr H = tr ε):
I_C - 3 = 2 tr H + H:H and J = 1 + tr H + ½((tr H)² - H:Hᵀ) + O(H³), so

    Ψ/V₀ = μ tr H + μ/2 H:H + λ/2 (tr H)² - μ (tr H + ½ (tr H)² - ½ H:Hᵀ) + μ²/(2λ) + O(H³)
         = μ²/(2λ) + μ/2 (H:H + H:Hᵀ) + (λ - μ)/2 (tr H)² = μ²/(2λ) + μ ε:ε + (λ - μ)/2 (tr ε)²,

(the first-order terms cancel: α makes the rest state stress-free, and H:H + H:Hᵀ = 2 ε:ε), which is linear
elasticity with the Lamé constants μ_L = μ, λ_L = λ - μ. So for Young's modulus E and Poisson ratio ν:
μ = E/(2(1 + ν)), λ = Eν/((1 + ν)(1 - 2ν)) + μ (:func:`stable_lame`); ``tests/test_neohookean.py`` checks the
forces' Jacobian at rest against linear elasticity's stiffness on the same tets.

**Forces.** ∂(μ/2 V₀ I_C)/∂x_a = μ V₀ F G_a = μ V₀ Σ_b (G_a · G_b) x_b (linear in x), and
∂(λ/2 V₀ (J - α)²)/∂x_a = λ (J - α) ∇_aV (the volume family's shape with K → λ, 1 → α; ∇_aV from
``volume.tet_volume_funcs``), so f_a = -μ V₀ F G_a - λ (J - α) ∇_aV.

**Stiffness** (the ``product`` hook: implicit Euler's system and the advisor's power iteration). The exact
Hessian, μ V₀ (G_a · G_b) I + (λ/V₀) ∇_aV ∇_bVᵀ + λ (J - α) ∇²V, is indefinite; dropping the last term (the
volume family's Gauss-Newton) is not exact at rest here, where λ (J - α) = -μ: the result would hold rigid
rotations with stiffness μ (a Rayleigh damper built on it would brake a spinning body, and implicit Euler's step
would) and halve the shear stiffness. The family uses instead the Gauss-Newton stiffness of the Green strain
E = ½(FᵀF - I) with linear elasticity's constants, in terms of δF = Σ_b δx_b ⊗ G_b:

    K̃: δP = 2μ F sym(FᵀδF) + λ_L⁻ tr(FᵀδF) F + λ_L⁺ (g : δF) g,   (K̃ δx)_a = V₀ δP G_a,

with g = cof F = ∂J/∂F (so V₀ g G_a = ∇_aV and the last term is the volume family's Gauss-Newton
(λ_L⁺/V₀) ∇_aV ∇_bVᵀ), λ_L⁺ = max(λ_L, 0), λ_L⁻ = min(λ_L, 0). It is symmetric and positive semi-definite
(2μ |sym C|² + λ_L⁻ (tr C)² ≥ (2μ/3 + λ_L⁻)(tr C)² ≥ 0 for ν > -1), zero on every infinitesimal rigid rotation
at any F (FᵀWF is skew for skew W, and g : WF = J tr W = 0), and at rest (F = g = I) exactly the energy's
Hessian, linear elasticity's stiffness. Away from rest it is an approximation of the Jacobian (implicit Euler's
step is then an inexact Newton step; its fixed point, f = 0, is unchanged).

**Damping** (β [s] per tet ≥ 0), Rayleigh's stiffness-proportional damper on K̃: f^d = -β K̃ v, i.e.
f_a^d = -β (V₀ (2μ F sym(FᵀḞ) + λ_L⁻ tr(FᵀḞ) F) G_a + λ_L⁺ J̇ ∇_aV), Ḟ = Σ_b v_b ⊗ G_b, J̇ = Σ_b ∇_bV · v_b / V₀. At
rest a mode of angular frequency ω is damped by ζ = βω/2, as the springs' kd = β ke; it exerts nothing on rigid
motions. Its power is β vᵀK̃v = β V₀ (2μ |sym(FᵀḞ)|² + λ_L⁻ (tr FᵀḞ)² + λ_L⁺ J̇²) ≥ 0 (the ``dissipation`` hook), and
D = β K̃ enters the product exactly: (α K̃ + β_arg D) x = (α + β_arg β) K̃ x.

Incidence entries are (tet, role of the particle: 0..3); padding entries have role -1 and
contribute nothing. No strain for the guards. Worlds: μ, λ and β have one row for every world or one per world;
V₀ and D_m⁻¹ are shared. By default (``NeoHookeanSpec.precomputed``) a pass computes each tet's S and p once per force
evaluation (f_a = -V₀ S G_a - p ∇_aV, below) and a corner's entry reads them and computes only its own ∇_aV.
"""

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import warp as wp

from .families import (FamilyFuncs, Incidence, IncidenceShape, four_point_funcs, gathered_force, gathered_product,
                       masked_operand, no_strain_func)
from .precision import mat33_type, vec3_type
from .volume import tet_volume_funcs

wp.set_module_options({"enable_backward": False})


def stable_lame(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """(μ, λ) [Pa] of the energy for Young's modulus E [Pa] and Poisson ratio ν ∈ (-1, ½): μ = E/(2(1 + ν)),
    λ = Eν/((1 + ν)(1 - 2ν)) + μ, so that its linearisation at rest has the Lamé constants (μ, λ - μ) of (E, ν)
    (see the module)."""
    e, nu = float(youngs_modulus), float(poisson_ratio)
    mu = e / (2.0 * (1.0 + nu))
    return mu, e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)) + mu


class NeoHookeanTetFuncs(NamedTuple):
    """The ``@wp.func`` helpers of the energy in one precision (see ``neohookean_tet_funcs``)."""

    deformation: wp.Function
    shape_gradient: wp.Function
    tangent_stress: wp.Function
    tet_stress: wp.Function
    tet_energy: wp.Function
    tet_force: wp.Function
    tet_power: wp.Function


@functools.cache
def neohookean_tet_funcs(scalar: type) -> NeoHookeanTetFuncs:
    """The energy's helpers typed by ``scalar`` (``wp.float32`` or ``wp.float64``). Positions [m], velocities
    [m/s], D_m⁻¹ [1/m] (``rest_inverse``), V₀ [m³], μ and λ [Pa], β [s]; roles 0..3."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    volume = tet_volume_funcs(scalar)
    volume_gradient = volume.tet_volume_gradient
    gradient_of_role = volume.gradient_of_role

    @wp.func
    def deformation(x0: vec3, x1: vec3, x2: vec3, x3: vec3, rest_inverse: mat33) -> mat33:
        """F = D_s D_m⁻¹ [-] (also Ḟ from velocities)."""
        e1 = x1 - x0
        e2 = x2 - x0
        e3 = x3 - x0
        ds = mat33(e1[0], e2[0], e3[0], e1[1], e2[1], e3[1], e1[2], e2[2], e3[2])
        return ds * rest_inverse

    @wp.func
    def shape_gradient(role: int, rest_inverse: mat33) -> vec3:
        """G_role [1/m]: row ``role`` - 1 of D_m⁻¹, G_0 = -(G_1 + G_2 + G_3)."""
        g1 = rest_inverse[0]
        g2 = rest_inverse[1]
        g3 = rest_inverse[2]
        return gradient_of_role(role, -(g1 + g2 + g3), g1, g2, g3)

    @wp.func
    def tet_energy(x0: vec3, x1: vec3, x2: vec3, x3: vec3, rest_inverse: mat33, rest: scalar, mu: scalar,
                   lam: scalar) -> scalar:
        """Ψ - Ψ_rest [J] = V₀ [μ/2 (I_C - 3) + λ/2 (J - α)² - μ²/(2λ)], α = 1 + μ/λ (λ > 0)."""
        f = deformation(x0, x1, x2, x3, rest_inverse)
        v, _, _, _, _ = volume_gradient(x0, x1, x2, x3)  # the compiler drops the gradient
        # I_C - 3 summed per column, (J - α) as (J - 1) - μ/λ: no cancellation of large terms near rest
        ic = wp.ddot(f, f) - scalar(3.0)
        d = (v - rest) / rest - mu / lam
        return rest * (scalar(0.5) * mu * ic + scalar(0.5) * lam * d * d - scalar(0.5) * mu * mu / lam)

    @wp.func
    def tangent_stress(f: mat33, df: mat33, mu: scalar, lam: scalar) -> mat33:
        """2μ F sym(FᵀδF) + λ_L⁻ tr(FᵀδF) F [Pa·(unit of δF)]: K̃'s part beside the volume Gauss-Newton (module)."""
        c = wp.transpose(f) * df
        negative = wp.min(lam - mu, scalar(0.0))
        return f * (mu * (c + wp.transpose(c)) + (negative * wp.trace(c)) * wp.identity(n=3, dtype=scalar))

    @wp.func
    def tet_stress(x0: vec3, x1: vec3, x2: vec3, x3: vec3, v0: vec3, v1: vec3, v2: vec3, v3: vec3,
                   rest_inverse: mat33, rest: scalar, mu: scalar, lam: scalar, beta: scalar):
        """The tet's (S [Pa], p [Pa]) with the force on corner a = -V₀ S G_a - p ∇_aV: S = μF + β (2μ F sym(FᵀḞ) +
        λ_L⁻ tr(FᵀḞ) F), p = λ (J - α) + β λ_L⁺ J̇."""
        v, g0, g1, g2, g3 = volume_gradient(x0, x1, x2, x3)
        rate = (wp.dot(g0, v0) + wp.dot(g1, v1) + wp.dot(g2, v2) + wp.dot(g3, v3)) / rest
        f = deformation(x0, x1, x2, x3, rest_inverse)
        stress = mu * f + beta * tangent_stress(f, deformation(v0, v1, v2, v3, rest_inverse), mu, lam)
        pressure = lam * ((v - rest) / rest - mu / lam) + beta * wp.max(lam - mu, scalar(0.0)) * rate
        return stress, pressure

    @wp.func
    def tet_force(role: int, x0: vec3, x1: vec3, x2: vec3, x3: vec3, v0: vec3, v1: vec3, v2: vec3, v3: vec3,
                  rest_inverse: mat33, rest: scalar, mu: scalar, lam: scalar, beta: scalar) -> vec3:
        """Force [N] on corner ``role`` (0..3): -μ V₀ F G_a - λ (J - α) ∇_aV - β (K̃ v)_a."""
        stress, pressure = tet_stress(x0, x1, x2, x3, v0, v1, v2, v3, rest_inverse, rest, mu, lam, beta)
        return -rest * (stress * shape_gradient(role, rest_inverse)) - pressure * volume.corner_gradient(
            role, x0, x1, x2, x3)

    @wp.func
    def tet_power(x0: vec3, x1: vec3, x2: vec3, x3: vec3, v0: vec3, v1: vec3, v2: vec3, v3: vec3,
                  rest_inverse: mat33, rest: scalar, mu: scalar, lam: scalar, beta: scalar) -> scalar:
        """Power [W] ≥ 0 the damper takes out: β vᵀK̃v = β V₀ (2μ |sym C|² + λ_L⁻ (tr C)² + λ_L⁺ J̇²), C = FᵀḞ."""
        _, g0, g1, g2, g3 = volume_gradient(x0, x1, x2, x3)
        rate = (wp.dot(g0, v0) + wp.dot(g1, v1) + wp.dot(g2, v2) + wp.dot(g3, v3)) / rest
        c = wp.transpose(deformation(x0, x1, x2, x3, rest_inverse)) * deformation(v0, v1, v2, v3, rest_inverse)
        sym = scalar(0.5) * (c + wp.transpose(c))
        trace = wp.trace(c)
        return beta * rest * (scalar(2.0) * mu * wp.ddot(sym, sym) + wp.min(lam - mu, scalar(0.0)) * trace * trace
                              + wp.max(lam - mu, scalar(0.0)) * rate * rate)

    return NeoHookeanTetFuncs(deformation, shape_gradient, tangent_stress, tet_stress, tet_energy, tet_force, tet_power)


@functools.cache
def neohookean_arrays_type(scalar: type):
    """The struct of the family's arrays in one precision."""
    mat33 = mat33_type(scalar)

    @wp.struct
    class NeoHookeanArrays:
        indices: wp.array[wp.vec4i]  # [tet_count]: x0 … x3, wound so that V₀ > 0, per-world indices
        rest_volume: wp.array[scalar]  # V₀ [m³], [tet_count], > 0
        rest_inverse: wp.array[mat33]  # D_m⁻¹ [1/m], [tet_count]: its rows are G_1, G_2, G_3
        mu: wp.array2d[scalar]  # μ [Pa], [1 or world_count, tet_count]
        lam: wp.array2d[scalar]  # λ [Pa] (> 0; not the Lamé λ_L = λ - μ), [1 or world_count, tet_count]
        damping: wp.array2d[scalar]  # β [s], [1 or world_count, tet_count]
        stress: wp.array[mat33]  # S [Pa], [world_count · tet_count], each tet's at the state of the last force
        #   evaluation (where precomputed; one entry otherwise)
        pressure: wp.array[scalar]  # p [Pa], likewise
        incidence: Incidence  # entries (tet, role 0..3); padding (0, -1)

    return NeoHookeanArrays


@dataclass(frozen=True)
class NeoHookeanSpec:
    """Compile-time switches of the neo-Hookean family: the shape of its incidence table, and whether each tet's
    (S, p) is computed once per force evaluation by ``tet_stresses`` (then a corner's gather reads it and computes
    only its own face's gradient) or by every corner's entry."""

    incidence: IncidenceShape
    precomputed: bool = False

    def funcs(self, scalar: type) -> FamilyFuncs:
        return neohookean_family_funcs(scalar, self)


class NeoHookeanFuncs(NamedTuple):
    """:class:`FamilyFuncs` and the kernel that precomputes the tets' (S, p)."""

    arrays: type
    force: Any
    product: Any
    strain: Any
    energy: Any
    idle: tuple
    dissipation: Any
    tet_stresses: Any


@functools.cache
def neohookean_family_funcs(scalar: type, spec: NeoHookeanSpec) -> NeoHookeanFuncs:
    """The family hooks of neo-Hookean tets (``families.py``) for one precision and spec."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    Arrays = neohookean_arrays_type(scalar)
    funcs = neohookean_tet_funcs(scalar)
    volume_gradient = tet_volume_funcs(scalar).tet_volume_gradient
    corner_gradient = tet_volume_funcs(scalar).corner_gradient
    gauss_newton_entry = four_point_funcs(scalar).gauss_newton_entry
    operand = masked_operand(scalar)

    @wp.func
    def row(array: wp.array2d[scalar], world: int, t: int) -> scalar:
        return array[wp.min(world, array.shape[0] - 1), t]

    @wp.func
    def tet_force_on(
        world: int, t: int, role: int, i: int, base: int, xi: vec3, vi: vec3, tets: Arrays,
        inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ) -> vec3:
        """Force [N] of tet t on its corner ``role`` (0 for a padding entry, role -1)."""
        if role < 0:
            return vec3(scalar(0.0))
        ids = tets.indices[t]
        if wp.static(spec.precomputed):
            slot = world * tets.indices.shape[0] + t
            return -tets.rest_volume[t] * (tets.stress[slot] * funcs.shape_gradient(role, tets.rest_inverse[t])) \
                - tets.pressure[slot] * corner_gradient(role, particle_q[base + ids[0]], particle_q[base + ids[1]],
                                                        particle_q[base + ids[2]], particle_q[base + ids[3]])
        return funcs.tet_force(role, particle_q[base + ids[0]], particle_q[base + ids[1]], particle_q[base + ids[2]],
                               particle_q[base + ids[3]], particle_qd[base + ids[0]], particle_qd[base + ids[1]],
                               particle_qd[base + ids[2]], particle_qd[base + ids[3]], tets.rest_inverse[t],
                               tets.rest_volume[t], row(tets.mu, world, t), row(tets.lam, world, t),
                               row(tets.damping, world, t))

    @wp.func
    def product_entry(
        world: int, t: int, role: int, i: int, base: int, tets: Arrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
        alpha: scalar, beta: scalar,
    ):
        """Row ``role`` of (α K̃ + β D) x = (α + β β_t) K̃ x for tet t (module), X = Σ_b x_b ⊗ G_b, and its diagonal
        block (α + β β_t) [V₀ (μ |G_a|² F Fᵀ + (μ + λ_L⁻) w wᵀ) + (λ_L⁺/V₀) ∇_aV ∇_aVᵀ], w = F G_a."""
        if role < 0:
            return vec3(scalar(0.0)), mat33(scalar(0.0))
        ids = tets.indices[t]
        x0 = particle_q[base + ids[0]]
        x1 = particle_q[base + ids[1]]
        x2 = particle_q[base + ids[2]]
        x3 = particle_q[base + ids[3]]
        _, g0, g1, g2, g3 = volume_gradient(x0, x1, x2, x3)
        rest = tets.rest_volume[t]
        mu = row(tets.mu, world, t)
        lam = row(tets.lam, world, t)
        scale = alpha + beta * row(tets.damping, world, t)
        product, block = gauss_newton_entry(scale * wp.max(lam - mu, scalar(0.0)) / rest, role, base, ids, g0, g1, g2,
                                            g3, particle_flags, x, free_only)
        inverse = tets.rest_inverse[t]
        xs = funcs.deformation(operand(base + ids[0], particle_flags, x, free_only),
                               operand(base + ids[1], particle_flags, x, free_only),
                               operand(base + ids[2], particle_flags, x, free_only),
                               operand(base + ids[3], particle_flags, x, free_only), inverse)
        ga = funcs.shape_gradient(role, inverse)
        f = funcs.deformation(x0, x1, x2, x3, inverse)
        w = f * ga
        k = scale * rest
        block += k * ((mu * wp.dot(ga, ga)) * (f * wp.transpose(f))
                      + (mu + wp.min(lam - mu, scalar(0.0))) * wp.outer(w, w))
        return product + k * (funcs.tangent_stress(f, xs, mu, lam) * ga), block

    force = gathered_force(scalar, Arrays, spec.incidence, tet_force_on)
    product = gathered_product(scalar, Arrays, spec.incidence, product_entry)

    strain = no_strain_func(scalar, Arrays)  # no strain for the guards

    @wp.func
    def energy(world: int, t: int, base: int, tets: Arrays, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3]) -> scalar:
        """Elastic energy [J] of tet t in ``world`` (zero at rest)."""
        ids = tets.indices[t]
        return funcs.tet_energy(particle_q[base + ids[0]], particle_q[base + ids[1]], particle_q[base + ids[2]],
                                particle_q[base + ids[3]], tets.rest_inverse[t], tets.rest_volume[t],
                                row(tets.mu, world, t), row(tets.lam, world, t))

    @wp.func
    def dissipation(world: int, t: int, base: int, tets: Arrays, inputs: wp.array2d[scalar],
                    particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> scalar:
        """Power [W] ≥ 0 the damper of tet t takes out in ``world``: β vᵀK̃v."""
        ids = tets.indices[t]
        return funcs.tet_power(particle_q[base + ids[0]], particle_q[base + ids[1]], particle_q[base + ids[2]],
                               particle_q[base + ids[3]], particle_qd[base + ids[0]], particle_qd[base + ids[1]],
                               particle_qd[base + ids[2]], particle_qd[base + ids[3]], tets.rest_inverse[t],
                               tets.rest_volume[t], row(tets.mu, world, t), row(tets.lam, world, t),
                               row(tets.damping, world, t))

    @wp.kernel(module="unique", enable_backward=False)
    def tet_stresses(
        # Model:
        particle_count: int,
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out (each tet's stress and pressure written into the family's arrays):
        tets_in_out: Arrays,
    ):
        """Each tet's (S, p) at a state, once (launch over [world_count, tet_count])."""
        world, t = wp.tid()
        base = world * particle_count
        ids = tets_in_out.indices[t]
        stress, pressure = funcs.tet_stress(
            particle_q[base + ids[0]], particle_q[base + ids[1]], particle_q[base + ids[2]], particle_q[base + ids[3]],
            particle_qd[base + ids[0]], particle_qd[base + ids[1]], particle_qd[base + ids[2]],
            particle_qd[base + ids[3]], tets_in_out.rest_inverse[t], tets_in_out.rest_volume[t],
            row(tets_in_out.mu, world, t), row(tets_in_out.lam, world, t), row(tets_in_out.damping, world, t))
        slot = world * tets_in_out.indices.shape[0] + t
        tets_in_out.stress[slot] = stress
        tets_in_out.pressure[slot] = pressure

    idle = spec.incidence.idle() + (() if spec.precomputed else ("stress", "pressure"))
    return NeoHookeanFuncs(Arrays, force, product, strain, energy, idle, dissipation, tet_stresses)
