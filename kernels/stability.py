"""Kernels of the stability analysis: power iteration on M⁻¹K, and a per-step record of spring motion.

Power iteration estimates λ_max of M⁻¹K, the square of the network's highest angular frequency, with K
the stiffness matrix -∂f/∂x of the springs (compressive transverse part clamped, as in implicit Euler, so
K ⪰ 0) and pinned particles filtered out. M⁻¹K is self-adjoint in the mass inner product ⟨x, y⟩_M = xᵀMy,
so one iteration is

    y = K x,    θ = xᵀy / xᵀMx  (Rayleigh quotient, ≤ λ_max),    x ← M⁻¹y / ‖M⁻¹y‖_M

with the residual ‖M⁻¹y - θx‖_M² = yᵀM⁻¹y - 2θ xᵀy + θ² xᵀMx as the convergence measure. The product
gathers over the particle's ELL incidence table like the implicit-Euler matvec (``implicit.py``):

    (K x)ᵢ = Σₛ Kₛ (xᵢ - xⱼ),    Kₛ = ∂fᵢ/∂xⱼ of spring s = (i, j)

and accumulates xᵀKx, xᵀMx and yᵀM⁻¹y (in float64, slots below) with the reductions of ``linalg.py``.
A device-side condition updates a loop flag, so the iteration runs in ``wp.capture_while`` like the CG
solve.
"""

import functools

import warp as wp

from .forces import COINCIDENT_DISTANCE, spring_funcs, spring_law_type
from .kinematics import is_kinematic, particle_funcs
from .linalg import reduction_funcs
from .precision import vec3_type

wp.set_module_options({"enable_backward": False})

# Slots of the float64 scalar array of a power iteration.
PI_XKX = 0  # xᵀKx being accumulated
PI_XMX = 1  # xᵀMx being accumulated
PI_YMY = 2  # yᵀM⁻¹y being accumulated (y = Kx)
PI_LAMBDA = 3  # Rayleigh quotient θ of the last completed iteration [1/s²]
PI_RESIDUAL = 4  # ‖M⁻¹Kx - θx‖_M / (θ ‖x‖_M) of the last completed iteration
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
def power_iteration_kernels(scalar: type, slots: int, tiled: bool):
    """(product, normalize, condition) kernels of power iteration on M⁻¹K for one precision and
    incidence-table width; ``tiled``: reductions use block tiles (CUDA), else per-thread atomics (CPU)."""
    vec3 = vec3_type(scalar)
    accumulate = reduction_funcs(tiled)
    dot64 = dot64_func(scalar)
    _, _, _, spring_stiffness_matrix = spring_funcs(scalar)  # Hooke's law: the advisor scales biphasic springs
    SpringLawValues = spring_law_type(scalar)
    effective_inv_mass = particle_funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def product(
        count: int,
        # Model:
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array[scalar],
        particle_spring_neighbor: wp.array2d[wp.int32],
        particle_spring_id: wp.array2d[wp.int32],
        spring_rest_length: wp.array[scalar],
        spring_stiffness: wp.array[scalar],
        # State in:
        particle_q: wp.array[vec3],
        # Operand:
        x: wp.array[vec3],
        # Out:
        y: wp.array[vec3],
        scalars: wp.array[wp.float64],
    ):
        """y = K x on dynamic particles (0 on kinematic ones); accumulate xᵀKx, xᵀMx and yᵀM⁻¹y."""
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        xkx = wp.float64(0.0)
        xmx = wp.float64(0.0)
        ymy = wp.float64(0.0)
        if i < count:
            yi = vec3(scalar(0.0))
            if not is_kinematic(particle_flags[i]):
                hooke = SpringLawValues()
                xi = x[i]
                qi = particle_q[i]
                for k in range(wp.static(slots)):
                    j = particle_spring_neighbor[k, i]
                    s = particle_spring_id[k, i]
                    xj = wp.where(is_kinematic(particle_flags[j]), vec3(scalar(0.0)), x[j])
                    ks = spring_stiffness_matrix(
                        qi, particle_q[j], spring_rest_length[s], spring_stiffness[s], True, hooke
                    )
                    yi += ks * (xi - xj)
                mass = wp.float64(particle_mass[i])
                xkx = dot64(xi, yi)
                xmx = mass * dot64(xi, xi)
                ymy = dot64(yi, yi) / mass
            y[i] = yi
        accumulate(scalars, PI_XKX, xkx, lane)
        accumulate(scalars, PI_XMX, xmx, lane)
        accumulate(scalars, PI_YMY, ymy, lane)

    @wp.kernel(module="unique", enable_backward=False)
    def normalize(
        # Model:
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array[scalar],
        # In:
        y: wp.array[vec3],
        scalars: wp.array[wp.float64],
        # Out:
        x: wp.array[vec3],
    ):
        """x = M⁻¹y / ‖M⁻¹y‖_M (x = 0 when y = 0, and on kinematic particles)."""
        i = wp.tid()
        ymy = scalars[PI_YMY]
        scale = wp.where(ymy > wp.float64(0.0), wp.float64(1.0) / wp.sqrt(ymy), wp.float64(0.0))
        x[i] = (effective_inv_mass(particle_flags[i], particle_inv_mass[i]) * scalar(scale)) * y[i]

    @wp.kernel(module="unique", enable_backward=False)
    def condition(
        tolerance: wp.float64,
        max_iterations: int,
        scalars: wp.array[wp.float64],
        iteration: wp.array[wp.int32],
        keep_going: wp.array[wp.int32],
    ):
        """θ and the relative residual of the iteration; keep going while the residual exceeds the
        tolerance and iterations remain; reset the accumulators."""
        xkx = scalars[PI_XKX]
        xmx = scalars[PI_XMX]
        theta = wp.where(xmx > wp.float64(0.0), xkx / xmx, wp.float64(0.0))
        residual2 = scalars[PI_YMY] - wp.float64(2.0) * theta * xkx + theta * theta * xmx
        positive = theta > wp.float64(0.0)
        scale = wp.where(positive, theta * theta * xmx, wp.float64(1.0))
        relative = wp.where(positive, wp.sqrt(wp.max(residual2, wp.float64(0.0)) / scale), wp.float64(0.0))
        scalars[PI_LAMBDA] = theta
        scalars[PI_RESIDUAL] = relative
        iteration[0] = iteration[0] + 1
        keep_going[0] = wp.where(relative <= tolerance or iteration[0] >= max_iterations, 0, 1)
        scalars[PI_XKX] = wp.float64(0.0)
        scalars[PI_XMX] = wp.float64(0.0)
        scalars[PI_YMY] = wp.float64(0.0)

    return product, normalize, condition


@functools.cache
def spring_motion_kernel(scalar: type):
    """Kernel writing every spring's stretch |d| - L [m] and stretch rate (vⱼ - vᵢ)·d̂ [m/s] (float64) into
    one row of a [rows, spring_count] array: a per-step record of the springs' motion, from which
    stability measurements compute energy-like norms without reading whole states back every step."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def record_spring_motion(
        # Model:
        spring_indices: wp.array[wp.vec2i],
        spring_rest_length: wp.array[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        row: int,
        # Out:
        motion: wp.array2d[wp.vec2d],
    ):
        s = wp.tid()
        ends = spring_indices[s]
        d = particle_q[ends[1]] - particle_q[ends[0]]
        length = wp.length(d)
        n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        rate = wp.dot(particle_qd[ends[1]] - particle_qd[ends[0]], n)
        motion[row, s] = wp.vec2d(wp.float64(length - spring_rest_length[s]), wp.float64(rate))

    return record_spring_motion
