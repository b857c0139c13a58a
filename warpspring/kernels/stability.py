"""Kernels of the stability analysis: power iteration and Lanczos on M⁻¹K, and a per-step record of spring motion.

Power iteration estimates λ_max of M⁻¹K, the square of the network's highest angular frequency, with K
the stiffness matrix -∂f/∂x of the element families (their ``product`` hook with α = 1, β = 0; springs'
compressive transverse part clamped, as in implicit Euler, so K ⪰ 0) and pinned particles filtered out. M⁻¹K is self-adjoint in the mass inner product ⟨x, y⟩_M = xᵀMy,
so one iteration is

    y = K x,    θ = xᵀy / xᵀMx  (Rayleigh quotient, ≤ λ_max),    x ← M⁻¹y / ‖M⁻¹y‖_M

with the residual ‖M⁻¹y - θx‖_M² = yᵀM⁻¹y - 2θ xᵀy + θ² xᵀMx as the convergence measure. The product
gathers at each particle like the implicit-Euler matvec (``implicit.py``); for springs

    (K x)ᵢ = Σₛ Kₛ (xᵢ - xⱼ),    Kₛ = ∂fᵢ/∂xⱼ of spring s = (i, j)

Worlds: every world of a model runs its own iteration in the same launches (vectors world-major, like a
state; stiffness and mass rows ``world % rows``). The product launches on the [world, block, lane] grid
of ``linalg.py`` and writes per-block partial sums of xᵀKx, xᵀMx and yᵀM⁻¹y (float64); its
``sum_partials_kernel`` adds them per world in a fixed order (no float atomics: a world's result has the
same bits however many worlds share the launch). Each world keeps its Rayleigh quotient, residual and
iteration count in its own row, stops at its own tolerance (its iterate is then left untouched), and a
device-side counter of the worlds still iterating drives ``wp.capture_while``.
"""

import functools

import warp as wp

from .families import elements
from .spring_laws import COINCIDENT_DISTANCE
from .kinematics import is_kinematic, particle_funcs
from .linalg import reduction_funcs
from .precision import vec3_type
from .worlds import world_and_index
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})

# Slots of the float64 scalars of a power iteration, one row per world (the first PI_PARTIALS are also the
# slots of the per-block partial sums).
PI_XKX = 0  # xᵀKx of the current iterate
PI_XMX = 1  # xᵀMx of the current iterate
PI_YMY = 2  # yᵀM⁻¹y of the current iterate (y = Kx)
PI_PARTIALS = 3  # slots with per-block partial sums (PI_XKX, PI_XMX, PI_YMY: consecutive, one pass sums them)
PI_LAMBDA = 3  # Rayleigh quotient θ of the world's last completed iteration [1/s²]
PI_RESIDUAL = 4  # ‖M⁻¹Kx - θx‖_M / (θ ‖x‖_M) of the world's last completed iteration [-]
PI_SCALARS = 5


@functools.cache
def dot64_func(scalar: type):
    """The dot product of two 3-vectors of ``scalar`` evaluated in float64."""
    vec3 = vec3_type(scalar)

    @wp.func
    def dot64(a: vec3, b: vec3) -> wp.float64:
        return (
            wp.float64(a[0]) * wp.float64(b[0])
            + wp.float64(a[1]) * wp.float64(b[1])
            + wp.float64(a[2]) * wp.float64(b[2])
        )

    return dot64


@functools.cache
def power_iteration_kernels(scalar: type, families: tuple, tiled: bool):
    """(product, normalize, condition) kernels of power iteration on M⁻¹K, one per world, for one precision
    and tuple of family specs (linearised: ``Model.family_specs(linear=True)``); ``tiled``: the product's block sums use tiles (CUDA), else one-thread blocks
    (CPU). Per iteration: ``product`` (grid [world, block, lane]), ``sum_partials_kernel(tiled)`` over slots
    [PI_XKX, PI_XKX + PI_PARTIALS), ``normalize`` (grid [world, particle]), ``condition`` (grid [world])."""
    vec3 = vec3_type(scalar)
    block_sum, _ = reduction_funcs(tiled)
    dot64 = dot64_func(scalar)
    composed = elements(scalar, families)
    Elements = composed.arrays
    element_product = composed.product
    effective_inv_mass = particle_funcs(scalar)

    @flat_kernel(module="unique", enable_backward=False, last=composed.last("element_arrays"))
    def product(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        # Operand:
        active: wp.array[wp.int32],
        x: wp.array[vec3],
        # Out:
        y_out: wp.array[vec3],
        partials_out: wp.array3d[wp.float64],
    ):
        """y = K x on dynamic particles (0 on kinematic ones), and the block partial sums of xᵀKx, xᵀMx and
        yᵀM⁻¹y, in the worlds still iterating."""
        world, block, lane = wp.tid()
        if active[world] == 0:
            return  # a whole block (it lies within one world) skips the reduction together
        i = block * wp.block_dim() + lane
        xkx = wp.float64(0.0)
        xmx = wp.float64(0.0)
        ymy = wp.float64(0.0)
        if i < particle_count:
            base = world * particle_count
            p = base + i
            yi = vec3(scalar(0.0))
            if not is_kinematic(particle_flags[p]):
                xi = x[p]
                yi, _ = element_product(world, i, base, particle_q[p], element_arrays, inputs, particle_q,
                                        particle_flags, x, True, scalar(1.0), scalar(0.0))
                mass = wp.float64(particle_mass[wp.min(world, particle_mass.shape[0] - 1), i])
                xkx = dot64(xi, yi)
                xmx = mass * dot64(xi, xi)
                ymy = dot64(yi, yi) / mass
            y_out[p] = yi
        xkx = block_sum(xkx)
        xmx = block_sum(xmx)
        ymy = block_sum(ymy)
        if lane == 0:
            partials_out[world, block, PI_XKX] = xkx
            partials_out[world, block, PI_XMX] = xmx
            partials_out[world, block, PI_YMY] = ymy

    @wp.kernel(module="unique", enable_backward=False)
    def normalize(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        # In:
        active: wp.array[wp.int32],
        y: wp.array[vec3],
        scalars: wp.array2d[wp.float64],
        # Out:
        x_out: wp.array[vec3],
    ):
        """x = M⁻¹y / ‖M⁻¹y‖_M (x = 0 when y = 0, and on kinematic particles), in the worlds still iterating."""
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if active[world] == 0:
            return
        ymy = scalars[world, PI_YMY]
        scale = wp.where(ymy > wp.float64(0.0), wp.float64(1.0) / wp.sqrt(ymy), wp.float64(0.0))
        inv_mass = effective_inv_mass(particle_flags[p], particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i])
        x_out[p] = (inv_mass * scalar(scale)) * y[p]

    @wp.kernel(module="unique", enable_backward=False)
    def condition(
        # Settings:
        tolerance: wp.float64,
        max_iterations: int,
        # In/out:
        scalars_in_out: wp.array2d[wp.float64],
        iteration_in_out: wp.array[wp.int32],
        active_in_out: wp.array[wp.int32],
        keep_going_out: wp.array[wp.int32],
    ):
        """Per world still iterating: θ and the relative residual of the iteration; stop when the residual
        is within the tolerance, when the iterations are spent or when it is not finite."""
        world = wp.tid()
        if active_in_out[world] == 0:
            return
        xkx = scalars_in_out[world, PI_XKX]
        xmx = scalars_in_out[world, PI_XMX]
        theta = wp.where(xmx > wp.float64(0.0), xkx / xmx, wp.float64(0.0))
        residual2 = scalars_in_out[world, PI_YMY] - wp.float64(2.0) * theta * xkx + theta * theta * xmx
        positive = theta > wp.float64(0.0)
        scale = wp.where(positive, theta * theta * xmx, wp.float64(1.0))
        relative = wp.where(positive, wp.sqrt(wp.max(residual2, wp.float64(0.0)) / scale), wp.float64(0.0))
        scalars_in_out[world, PI_LAMBDA] = theta
        scalars_in_out[world, PI_RESIDUAL] = relative
        iteration_in_out[world] = iteration_in_out[world] + 1
        if relative <= tolerance or iteration_in_out[world] >= max_iterations or not wp.isfinite(relative):
            active_in_out[world] = 0
            wp.atomic_sub(keep_going_out, 0, 1)

    return product, normalize, condition


# Slots of a Lanczos run's float64 coefficients, shape [world_count, steps + 1, LZ_SLOTS]: row j holds α_j and β_j.
LZ_ALPHA = 0  # α_j = v_jᵀ K v_j, the diagonal of the tridiagonal T [1/s²]
LZ_BETA = 1  # β_j = ‖w_(j-1)‖_M, its off-diagonal (row 0: 0) [1/s²]
LZ_SLOTS = 2


@functools.cache
def lanczos_kernels(scalar: type, tiled: bool):
    """(direction, advance, ritz) kernels of Lanczos on M⁻¹K in the mass inner product, one run per world, on top of
    the power iteration's ``product`` (y = K v_j with the partial sums of v_jᵀKv_j, v_jᵀMv_j). Step j:

        v̂ = v_j / ‖v_j‖_M,   α_j = v̂ᵀKv̂,   w = M⁻¹K v̂ - α_j v̂ - β_j v_(j-1),   β_(j+1) = ‖w‖_M,   v_(j+1) = w / β_(j+1)

    (``direction`` over [world, block, lane]: v̂, α_j, w and the block partial sums of wᵀMw; ``sum_partials_kernel``;
    ``advance`` over [world, particle]: β_(j+1), v_(j+1)). T, the tridiagonal of the α and β, has eigenvalues
    (Ritz values) within λ_max(M⁻¹K) and above every start's Rayleigh quotient; ``ritz`` over [world, particle]
    writes the host's combination Σ c_j v_j (the top Ritz vector) over v_0 for the next run. ``tiled`` as in
    :func:`power_iteration_kernels`."""
    vec3 = vec3_type(scalar)
    block_sum, _ = reduction_funcs(tiled)
    dot64 = dot64_func(scalar)
    effective_inv_mass = particle_funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def direction(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        particle_inv_mass: wp.array2d[scalar],
        # In:
        active: wp.array[wp.int32],
        step: int,
        scalars: wp.array2d[wp.float64],
        y: wp.array[vec3],
        previous: wp.array[vec3],
        # In/out:
        v_in_out: wp.array[vec3],
        coefficients_in_out: wp.array3d[wp.float64],
        w_out: wp.array[vec3],
        partials_out: wp.array3d[wp.float64],
    ):
        """v_j normalised in place, α_j, w = M⁻¹K v̂ - α_j v̂ - β_j v_(j-1) (0 on kinematic particles) and the block
        partial sums of wᵀMw, in the worlds that run; y = K v_j and ``scalars`` its sums (PI_XKX, PI_XMX)."""
        world, block, lane = wp.tid()
        if active[world] == 0:
            return
        vmv = scalars[world, PI_XMX]
        positive = vmv > wp.float64(0.0)
        scale = wp.where(positive, wp.float64(1.0) / wp.sqrt(vmv), wp.float64(0.0))
        alpha = wp.where(positive, scalars[world, PI_XKX] / vmv, wp.float64(0.0))
        beta = wp.where(step > 0, coefficients_in_out[world, step, LZ_BETA], wp.float64(0.0))
        i = block * wp.block_dim() + lane
        wmw = wp.float64(0.0)
        if i < particle_count:
            p = world * particle_count + i
            wi = vec3(scalar(0.0))
            if not is_kinematic(particle_flags[p]):
                row = wp.min(world, particle_mass.shape[0] - 1)
                inv_mass = effective_inv_mass(particle_flags[p], particle_inv_mass[row, i])
                vi = scalar(scale) * v_in_out[p]
                wi = (inv_mass * scalar(scale)) * y[p] - scalar(alpha) * vi - scalar(beta) * previous[p]
                v_in_out[p] = vi
                wmw = wp.float64(particle_mass[row, i]) * dot64(wi, wi)
            w_out[p] = wi
        wmw = block_sum(wmw)
        if lane == 0:
            partials_out[world, block, 0] = wmw
            if block == 0:
                coefficients_in_out[world, step, LZ_ALPHA] = alpha

    @wp.kernel(module="unique", enable_backward=False)
    def advance(
        # Model:
        particle_count: int,
        # In:
        active: wp.array[wp.int32],
        step: int,
        norms: wp.array2d[wp.float64],
        # In/out:
        v_in_out: wp.array[vec3],
        coefficients_in_out: wp.array3d[wp.float64],
    ):
        """β_(j+1) = ‖w‖_M (``norms[world, 0]`` = wᵀMw) and v_(j+1) = w / β_(j+1) in place (0 where β = 0)."""
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if active[world] == 0:
            return
        beta = wp.sqrt(wp.max(norms[world, 0], wp.float64(0.0)))
        scale = wp.where(beta > wp.float64(0.0), wp.float64(1.0) / beta, wp.float64(0.0))
        v_in_out[p] = scalar(scale) * v_in_out[p]
        if i == 0:
            coefficients_in_out[world, step + 1, LZ_BETA] = beta

    @wp.kernel(module="unique", enable_backward=False)
    def ritz(
        # Model:
        particle_count: int,
        # In:
        active: wp.array[wp.int32],
        combination: wp.array2d[wp.float64],
        # In/out:
        basis_in_out: wp.array2d[vec3],
    ):
        """v_0 = Σ_j c_j v_j (``combination[world, j]``: the top Ritz vector's coordinates in the basis)."""
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if active[world] == 0:
            return
        x = vec3(scalar(0.0))
        for j in range(combination.shape[1]):
            x += scalar(combination[world, j]) * basis_in_out[j, p]
        basis_in_out[0, p] = x

    return direction, advance, ritz


@functools.cache
def spring_motion_kernel(scalar: type):
    """Kernel writing every spring's stretch |d| - L [m] and stretch rate (vⱼ - vᵢ)·d̂ [m/s] (float64) of
    every world into one row of a [rows, world_count · spring_count] array (world-major: spring s of world
    w is column w · spring_count + s); launch over [world_count, spring_count]. A per-step record of the
    springs' motion, from which stability measurements compute energy-like norms without reading whole
    states back every step."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def record_spring_motion(
        # Model:
        particle_count: int,
        spring_indices: wp.array[wp.vec2i],
        spring_rest_length: wp.array[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        row: int,
        # Out:
        motion_out: wp.array2d[wp.vec2d],
    ):
        world, s = wp.tid()
        base = world * particle_count
        ends = spring_indices[s]
        i = base + ends[0]
        j = base + ends[1]
        d = particle_q[j] - particle_q[i]
        length = wp.length(d)
        n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        rate = wp.dot(particle_qd[j] - particle_qd[i], n)
        motion_out[row, world * spring_indices.shape[0] + s] = wp.vec2d(
            wp.float64(length - spring_rest_length[s]), wp.float64(rate)
        )

    return record_spring_motion
