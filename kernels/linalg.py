"""Device-side reductions and the preconditioned conjugate-gradient iteration.

Reductions add one float64 value per thread into a slot of a small accumulator array. On CUDA, a
block first sums its values with ``wp.tile_sum`` and one thread adds the block's sum (one atomic per
block); on the CPU, where Warp runs threads in sequence, each thread adds its value directly. Kernels
that reduce are launched on a 2-D grid [blocks, block_dim] (``reduce_launch_dim``): thread (b, l)
handles item b·block_dim + l, and every thread of a block must reach the reduction.

The conjugate-gradient kernels keep every scalar of the iteration on the device (``cg_scalars``
slots below) and update a loop condition, so an entire solve runs inside ``wp.capture_while``: no
host synchronisation, capturable in CUDA and CPU graphs, and it stops as soon as it converges.
The operator product and the block-Jacobi preconditioner are supplied by the caller's kernels.
"""

import functools

import warp as wp

from .precision import mat33_type, vec3_type

wp.set_module_options({"enable_backward": False})

# Slots of the float64 scalar array of a CG solve.
CG_RZ = 0  # r·z of the current iterate
CG_RZ_NEW = 1  # r·z being accumulated
CG_PAP = 2  # p·Ap being accumulated
CG_RR = 3  # r·r being accumulated
CG_BB = 4  # b·b
CG_RR_LAST = 5  # r·r of the last completed iterate (reported)
CG_SCALARS = 6
# Slots of the float64 settings array of a CG solve: live settings, read by ``condition``.
CG_TOLERANCE = 0  # stop when ‖r‖ ≤ tolerance · ‖b‖
CG_MAX_ITERATIONS = 1  # most iterations per solve
CG_SETTINGS = 2


def reduce_launch_dim(count: int, block_dim: int) -> tuple[int, int]:
    """The 2-D launch grid of a reducing kernel over ``count`` items."""
    return ((count + block_dim - 1) // block_dim, block_dim)


@functools.cache
def reduction_funcs(tiled: bool):
    """``accumulate(out, slot, value, lane)``: add every thread's value into ``out[slot]``."""

    @wp.func
    def accumulate(out: wp.array[wp.float64], slot: int, value: wp.float64, lane: int):
        if wp.static(tiled):
            total = wp.tile_sum(wp.tile(value))
            if lane == 0:
                wp.atomic_add(out, slot, total[0])
        else:
            wp.atomic_add(out, slot, value)

    return accumulate


@functools.cache
def cg_kernels(scalar: type, tiled: bool):
    """(start, update_solution, update_direction, condition) kernels of block-Jacobi PCG on vec3 unknowns."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    accumulate = reduction_funcs(tiled)

    @wp.kernel(module="unique", enable_backward=False)
    def start(
        count: int,
        rhs: wp.array[vec3],
        a_x: wp.array[vec3],
        diagonal_inverse: wp.array[mat33],
        # Out:
        r: wp.array[vec3],
        z: wp.array[vec3],
        p: wp.array[vec3],
        scalars: wp.array[wp.float64],
    ):
        """r = b - A x, z = P r, p = z; accumulate r·z, r·r and b·b."""
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        rz = wp.float64(0.0)
        rr = wp.float64(0.0)
        bb = wp.float64(0.0)
        if i < count:
            b = rhs[i]
            ri = b - a_x[i]
            zi = diagonal_inverse[i] * ri
            r[i] = ri
            z[i] = zi
            p[i] = zi
            rz = wp.float64(wp.dot(ri, zi))
            rr = wp.float64(wp.dot(ri, ri))
            bb = wp.float64(wp.dot(b, b))
        accumulate(scalars, CG_RZ_NEW, rz, lane)
        accumulate(scalars, CG_RR, rr, lane)
        accumulate(scalars, CG_BB, bb, lane)

    @wp.kernel(module="unique", enable_backward=False)
    def update_solution(
        count: int,
        p: wp.array[vec3],
        a_p: wp.array[vec3],
        diagonal_inverse: wp.array[mat33],
        # In/out:
        x: wp.array[vec3],
        r: wp.array[vec3],
        z: wp.array[vec3],
        scalars: wp.array[wp.float64],
    ):
        """α = r·z / p·Ap; x += α p; r -= α Ap; z = P r; accumulate the new r·z and r·r."""
        block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        rz = wp.float64(0.0)
        rr = wp.float64(0.0)
        if i < count:
            p_ap = scalars[CG_PAP]
            alpha = scalar(wp.where(p_ap > wp.float64(0.0), scalars[CG_RZ] / p_ap, wp.float64(0.0)))
            x[i] = x[i] + alpha * p[i]
            ri = r[i] - alpha * a_p[i]
            zi = diagonal_inverse[i] * ri
            r[i] = ri
            z[i] = zi
            rz = wp.float64(wp.dot(ri, zi))
            rr = wp.float64(wp.dot(ri, ri))
        accumulate(scalars, CG_RZ_NEW, rz, lane)
        accumulate(scalars, CG_RR, rr, lane)

    @wp.kernel(module="unique", enable_backward=False)
    def update_direction(z: wp.array[vec3], scalars: wp.array[wp.float64], p: wp.array[vec3]):
        """β = (r·z)_new / (r·z)_old; p = z + β p."""
        i = wp.tid()
        rz = scalars[CG_RZ]
        beta = scalar(wp.where(rz > wp.float64(0.0), scalars[CG_RZ_NEW] / rz, wp.float64(0.0)))
        p[i] = z[i] + beta * p[i]

    @wp.kernel(module="unique", enable_backward=False)
    def condition(
        settings: wp.array[wp.float64],
        scalars: wp.array[wp.float64],
        iteration: wp.array[wp.int32],
        keep_going: wp.array[wp.int32],
    ):
        """Count an iteration, keep going while ‖r‖ > tol·‖b‖ and iterations remain; reset accumulators."""
        rr = scalars[CG_RR]
        tolerance = settings[CG_TOLERANCE]
        iteration[0] = iteration[0] + 1
        converged = rr <= wp.max(tolerance * tolerance * scalars[CG_BB], wp.float64(1.0e-300))
        exhausted = wp.float64(iteration[0]) >= settings[CG_MAX_ITERATIONS]
        keep_going[0] = wp.where(converged or exhausted, 0, 1)
        scalars[CG_RR_LAST] = rr
        scalars[CG_RZ] = scalars[CG_RZ_NEW]
        scalars[CG_RZ_NEW] = wp.float64(0.0)
        scalars[CG_PAP] = wp.float64(0.0)
        scalars[CG_RR] = wp.float64(0.0)

    return start, update_solution, update_direction, condition
