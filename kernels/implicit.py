"""Kernels of linearised implicit (backward) Euler in the Baraff-Witkin form.

One step solves  A Δv = b,  A = M - h ∂f/∂v - h² ∂f/∂x,  b = h (f + h ∂f/∂x v),  then v' = v + Δv,
x' = x + h v'. Per spring (i, j) with stiffness block Kₛ = ∂fᵢ/∂xⱼ (compressive transverse part
clamped, so Kₛ ⪰ 0) and damper block Dₛ = kd d̂d̂ᵀ, the matrix is never assembled: a product gathers

    (A p)ᵢ = (mᵢ + h c) pᵢ + Σₛ (h Dₛ + h² Kₛ)(pᵢ - pⱼ)        (c: the world's drag)

over the particle's incidence table, and also writes the per-block partial sums of p·Ap for the
conjugate-gradient iteration of ``linalg.py`` (one system per world). Kinematic particles are filtered out (Baraff-Witkin's S): their rows are the identity,
their columns are dropped and their right-hand side is zero, so A stays symmetric positive definite
and their Δv is exactly zero. A driven pin j has a prescribed Δvⱼ = zⱼ instead: with its position at t + h
already written (the kinematics pass), zⱼ = (xⱼ(t + h) - xⱼ)/h - vⱼ, so that the linearisation moves it
by exactly h (vⱼ + zⱼ) = xⱼ(t + h) - xⱼ, and its dropped column moves to the right-hand side of every
free neighbour i: bᵢ += (h Dₛ + h² Kₛ) zⱼ.
"""

import functools

import warp as wp

from .forces import SPRING_KERNEL_OPTIONS, SpringLaw, spring_funcs, spring_law_type
from .inputs import INPUT_DRAG
from .kinematics import is_kinematic
from .linalg import CG_PAP, reduction_funcs
from .precision import mat33_type, vec3_type
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})


@functools.cache
def implicit_funcs(scalar: type, law: SpringLaw):
    """The per-spring system block h Dₛ + h² Kₛ."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    _, _, _, spring_stiffness_matrix = spring_funcs(scalar, law)
    SpringLawValues = spring_law_type(scalar)

    @wp.func
    def system_block(
        xi: vec3, xj: vec3, rest: scalar, ke: scalar, kd: scalar, dt: scalar, law_values: SpringLawValues
    ) -> mat33:
        """h kd d̂d̂ᵀ + h² Kₛ [kg/s]: the coupling of particles i and j in A."""
        d = xj - xi
        length = wp.length(d)
        n = d * wp.where(length > scalar(0.0), scalar(1.0) / length, scalar(0.0))
        return (dt * kd) * wp.outer(n, n) + (dt * dt) * spring_stiffness_matrix(xi, xj, rest, ke, True, law_values)

    return system_block


@functools.cache
def implicit_kernels(scalar: type, slots: int, tiled: bool, law: SpringLaw, drag: bool, driven: bool):
    """(prepare, matvec, update) kernels of one precision, incidence-table width and spring law;
    ``tiled``: the matvec's p·Ap reduction uses block tiles (CUDA), else one-thread blocks (CPU);
    ``drag``: the viscous drag input enters A; ``driven``: driven pins have been put at t + h (their Δv
    enters the right-hand side, and the update leaves them where the kinematics pass put them)."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    system_block = implicit_funcs(scalar, law)
    block_sum, _ = reduction_funcs(tiled)
    spring_law_values, _, _, spring_stiffness_matrix = spring_funcs(scalar, law)

    @wp.func
    def mass_term(mass: scalar, inputs: wp.array2d[scalar], world: int, dt: scalar) -> scalar:
        """m + h c [kg]: the diagonal of M - h ∂f/∂v from the mass and the world's viscous drag c."""
        if wp.static(drag):
            return mass + dt * inputs[world, INPUT_DRAG]
        return mass

    @wp.kernel(module="unique", enable_backward=False, module_options=SPRING_KERNEL_OPTIONS)
    def prepare(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array2d[scalar],
        spring_damping: wp.array2d[scalar],
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        particle_f: wp.array[vec3],
        dt: scalar,
        particle_q_end: wp.array[vec3],
        # Out:
        rhs: wp.array[vec3],
        diagonal_inverse: wp.array[mat33],
    ):
        """b = h f + h² ∂f/∂x v (+ the driven pins' columns) and the inverse 3 × 3 diagonal blocks of A
        (block-Jacobi preconditioner). ``particle_q_end``: positions at t + h of the driven pins."""
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        base = p - i
        if is_kinematic(particle_flags[p]):
            rhs[p] = vec3(scalar(0.0))
            diagonal_inverse[p] = wp.identity(n=3, dtype=scalar)
            return
        law_values = spring_law_values(inputs, world)
        stiffness_row = wp.min(world, spring_stiffness.shape[0] - 1)
        damping_row = wp.min(world, spring_damping.shape[0] - 1)
        xi = particle_q[p]
        vi = particle_qd[p]
        b = dt * particle_f[p]
        diagonal = mass_term(particle_mass[wp.min(world, particle_mass.shape[0] - 1), i], inputs, world, dt) * wp.identity(
            n=3, dtype=scalar
        )
        for k in range(wp.static(slots)):
            j = base + particle_spring_neighbor[k, i]
            s = particle_spring_id[k, i]
            xj = particle_q[j]
            rest = spring_rest_length[s]
            ke = spring_stiffness[stiffness_row, s]
            b += (dt * dt) * (spring_stiffness_matrix(xi, xj, rest, ke, True, law_values) * (particle_qd[j] - vi))
            block = system_block(xi, xj, rest, ke, spring_damping[damping_row, s], dt, law_values)
            diagonal += block
            if wp.static(driven):
                if is_kinematic(particle_flags[j]):
                    b += block * ((particle_q_end[j] - xj) / dt - particle_qd[j])
        rhs[p] = b
        diagonal_inverse[p] = wp.inverse(diagonal)

    @wp.kernel(module="unique", enable_backward=False, module_options=SPRING_KERNEL_OPTIONS)
    def matvec(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array2d[scalar],
        spring_damping: wp.array2d[scalar],
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        dt: scalar,
        # Operand:
        active: wp.array[wp.int32],
        p: wp.array[vec3],
        # Out:
        a_p: wp.array[vec3],
        partials: wp.array3d[wp.float64],
    ):
        """Ap (kinematic rows: the identity), and the block partial sums of p·Ap, in the worlds still
        iterating."""
        world, block, lane = wp.tid()
        if active[world] == 0:
            return
        i = block * wp.block_dim() + lane
        p_ap = wp.float64(0.0)
        if i < particle_count:
            base = world * particle_count
            k = base + i
            pi = p[k]
            api = pi
            if not is_kinematic(particle_flags[k]):
                law_values = spring_law_values(inputs, world)
                stiffness_row = wp.min(world, spring_stiffness.shape[0] - 1)
                damping_row = wp.min(world, spring_damping.shape[0] - 1)
                xi = particle_q[k]
                api = mass_term(particle_mass[wp.min(world, particle_mass.shape[0] - 1), i], inputs, world, dt) * pi
                for slot in range(wp.static(slots)):
                    j = base + particle_spring_neighbor[slot, i]
                    s = particle_spring_id[slot, i]
                    pj = wp.where(is_kinematic(particle_flags[j]), vec3(scalar(0.0)), p[j])
                    block_ij = system_block(
                        xi, particle_q[j], spring_rest_length[s], spring_stiffness[stiffness_row, s],
                        spring_damping[damping_row, s], dt, law_values,
                    )
                    api += block_ij * (pi - pj)
            a_p[k] = api
            p_ap = wp.float64(wp.dot(pi, api))
        p_ap = block_sum(p_ap)
        if lane == 0:
            partials[world, block, CG_PAP] = p_ap

    @wp.kernel(module="unique", enable_backward=False)
    def update(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        delta_qd: wp.array[vec3],
        dt: scalar,
        dt_rest: scalar,
        # State out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
    ):
        """v' = v + Δv, x' = x + h v' (driven pins keep what the kinematics pass wrote)."""
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if i == 0:
            time_out[world] = time_in[world] + (wp.float64(dt) + wp.float64(dt_rest))
        if wp.static(driven):
            if is_kinematic(particle_flags[p]):
                return
        v = particle_qd_in[p] + delta_qd[p]
        particle_q_out[p] = particle_q_in[p] + dt * v
        particle_qd_out[p] = v

    return prepare, matvec, update
