"""Kernels of linearised implicit (backward) Euler in the Baraff-Witkin form.

One step solves  A Δv = b,  A = M - h ∂f/∂v - h² ∂f/∂x,  b = h (f + h ∂f/∂x v),  then v' = v + Δv,
x' = x + h v'. The element families supply -∂f/∂x ≈ K ⪰ 0 and -∂f/∂v = D ⪰ 0 through their ``product``
hook (``families.py``; springs: Kₛ with its compressive transverse part clamped, Dₛ = kd d̂d̂ᵀ), so the
matrix is never assembled: a product gathers

    (A p)ᵢ = (mᵢ + h c) pᵢ + ((h D + h² K) p)ᵢ        (c: the world's drag)

at each particle, and also writes the per-block partial sums of p·Ap for the conjugate-gradient iteration
of ``linalg.py`` (one system per world). Kinematic particles are filtered out (Baraff-Witkin's S): their
rows are the identity, their columns are dropped and their right-hand side is zero, so A stays symmetric
positive definite and their Δv is exactly zero. A driven pin j has a prescribed Δvⱼ = zⱼ instead: with
its position at t + h already written (the kinematics pass), zⱼ = (xⱼ(t + h) - xⱼ)/h - vⱼ, so that the
linearisation moves it by exactly h (vⱼ + zⱼ) = xⱼ(t + h) - xⱼ, and its dropped column moves to the
right-hand side of every free particle: b -= (h D + h² K) z (z is zero at free particles).
"""

import functools

import warp as wp

from .families import FORCE_KERNEL_OPTIONS, elements
from .inputs import INPUT_DRAG
from .kinematics import is_kinematic
from .linalg import CG_PAP, reduction_funcs
from .precision import mat33_type, vec3_type
from .worlds import world_and_index
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})


@functools.cache
def implicit_kernels(scalar: type, families: tuple, tiled: bool, drag: bool, driven: bool):
    """(prescribed, prepare, matvec, update) kernels of one precision and tuple of family specs; ``tiled``:
    the matvec's p·Ap reduction uses block tiles (CUDA), else one-thread blocks (CPU); ``drag``: the viscous
    drag input enters A; ``driven``: driven pins have been put at t + h (their Δv enters the right-hand
    side, and the update leaves them where the kinematics pass put them)."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    block_sum, _ = reduction_funcs(tiled)
    composed = elements(scalar, families)
    Elements = composed.arrays
    element_product = composed.product

    @wp.func
    def mass_term(mass: scalar, inputs: wp.array2d[scalar], world: int, dt: scalar) -> scalar:
        """m + h c [kg]: the diagonal of M - h ∂f/∂v from the mass and the world's viscous drag c."""
        if wp.static(drag):
            return mass + dt * inputs[world, INPUT_DRAG]
        return mass

    @wp.kernel(module="unique", enable_backward=False)
    def prescribed(
        # Model:
        particle_flags: wp.array[wp.int32],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        particle_q_end: wp.array[vec3],
        dt: scalar,
        # Out:
        delta_qd_out: wp.array[vec3],
    ):
        """z = the prescribed Δv of driven pins, (x(t + h) - x)/h - v, and 0 at free particles."""
        p = wp.tid()
        z = vec3(scalar(0.0))
        if is_kinematic(particle_flags[p]):
            z = (particle_q_end[p] - particle_q[p]) / dt - particle_qd[p]
        delta_qd_out[p] = z

    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 last=composed.last("element_arrays"))
    def prepare(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        particle_f: wp.array[vec3],
        dt: scalar,
        prescribed_delta_qd: wp.array[vec3],
        # Out:
        rhs_out: wp.array[vec3],
        diagonal_inverse_out: wp.array[mat33],
    ):
        """b = h f - h² K v (- (h D + h² K) z with driven pins) and the inverse 3 × 3 diagonal blocks of A
        (block-Jacobi preconditioner)."""
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        base = p - i
        if is_kinematic(particle_flags[p]):
            rhs_out[p] = vec3(scalar(0.0))
            diagonal_inverse_out[p] = wp.identity(n=3, dtype=scalar)
            return
        xi = particle_q[p]
        h = dt
        kv, stiffness_diagonal = element_product(world, i, base, xi, element_arrays, inputs, particle_q,
                                                 particle_flags, particle_qd, False, h * h, scalar(0.0))
        b = h * particle_f[p] - kv
        if wp.static(driven):
            bz, blocks = element_product(world, i, base, xi, element_arrays, inputs, particle_q, particle_flags,
                                         prescribed_delta_qd, False, h * h, h)
            b -= bz
        else:
            unused, blocks = element_product(world, i, base, xi, element_arrays, inputs, particle_q, particle_flags,
                                             particle_qd, False, h * h, h)
        rhs_out[p] = b
        mass = mass_term(particle_mass[wp.min(world, particle_mass.shape[0] - 1), i], inputs, world, h)
        diagonal_inverse_out[p] = wp.inverse(mass * wp.identity(n=3, dtype=scalar) + blocks)

    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 last=composed.last("element_arrays"))
    def matvec(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        dt: scalar,
        # Operand:
        active: wp.array[wp.int32],
        p: wp.array[vec3],
        # Out:
        a_p_out: wp.array[vec3],
        partials_out: wp.array3d[wp.float64],
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
                coupled, _ = element_product(world, i, base, particle_q[k], element_arrays, inputs, particle_q,
                                             particle_flags, p, True, dt * dt, dt)
                api = mass_term(particle_mass[wp.min(world, particle_mass.shape[0] - 1), i], inputs, world, dt) * pi
                api += coupled
            a_p_out[k] = api
            p_ap = wp.float64(wp.dot(pi, api))
        p_ap = block_sum(p_ap)
        if lane == 0:
            partials_out[world, block, CG_PAP] = p_ap

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

    return prescribed, prepare, matvec, update
