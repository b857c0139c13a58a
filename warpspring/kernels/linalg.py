"""Device-side reductions per world, and the preconditioned conjugate-gradient iteration.

Every reduction is per world and deterministic, with no float atomics: a kernel that reduces launches
on a 3-D grid [world, block, lane] (``reduce_launch_dim``), thread (w, b, l) handling item b·lanes + l
of world w; on CUDA the lanes of a block sum their values with ``wp.tile_sum`` (a fixed-order tree) and
lane 0 writes the block's total to ``partials[w, b, slot]``; on the CPU a block is one thread. A second
pass (``sum_partials_kernel``) adds each world's partials in a fixed order into ``scalars[w, slot]``.
The same world gives the same bits however many worlds share the launch, and every run gives the same
bits. Every thread of a block must reach the reduction (a block lies within one world, so a whole block
may skip it together).

The conjugate-gradient kernels keep every scalar of the iteration on the device, one row per world
(``CG_*`` slots below), and count the worlds still iterating, so an entire solve runs inside
``wp.capture_while``: no host synchronisation, capturable in CUDA and CPU graphs; each world stops at its
own tolerance (its solution is left untouched while others go on) and the loop ends when all have.
The operator product and the block-Jacobi preconditioner are supplied by the caller's kernels.
"""

import functools

import warp as wp

from .precision import mat33_type, vec3_type
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})

# Slots of the float64 scalars of a CG solve, one row per world (and of its per-block partial sums).
CG_RZ = 0  # r·z of the current iterate
CG_RZ_NEW = 1  # r·z of the new iterate
CG_RR = 2  # r·r of the new iterate
CG_BB = 3  # b·b (CG_RZ_NEW, CG_RR and CG_BB are consecutive: one pass sums them)
CG_PAP = 4  # p·Ap
CG_RR_LAST = 5  # r·r of the last completed iterate (reported)
CG_BETA = 6  # β = (r·z)_new / (r·z)_old of the next direction
CG_SCALARS = 7
# Slots of the float64 settings array of a CG solve: live settings, read by ``condition``.
CG_TOLERANCE = 0  # stop when ‖r‖ ≤ tolerance · ‖b‖
CG_MAX_ITERATIONS = 1  # most iterations per solve
CG_SETTINGS = 2
# Slots of the float64 record of solves that stopped at the iteration cap unconverged, one row per world (kept
# across solves until the host reads and clears it).
CG_SHORT_COUNT = 0  # solves stopped at the cap with ‖r‖ > tolerance · ‖b‖
CG_SHORT_WORST = 1  # the largest ‖r‖² / ‖b‖² such a solve left
CG_SHORT_SLOTS = 2


def reduce_lanes(count: int, block_dim: int, tiled: bool) -> int:
    """Lanes (threads) per block of a reducing kernel over ``count`` items per world: one on the CPU; on
    CUDA ``block_dim``, or the smallest power of two ≥ 32 that covers ``count`` when that is fewer."""
    if not tiled:
        return 1
    return int(min(block_dim, max(32, 1 << max(count - 1, 1).bit_length())))


#: Items each lane of a striding reducing kernel on CUDA takes at most (``reduce_launch_dim``'s ``per_lane``): the
#: guard's check passes. One item a lane left a 1024² cloth's check 4,096 particle blocks and 24,537 spring blocks:
#: no faster a pass (measure 8.2 against 7.7 µs a substep, the springs' energy 10.8 against 7.5; H200), and more
#: partial sums to fold and gather; 8 measured best of 1, 4 and 8 (bench/results/guard_cost.md).
REDUCE_PER_LANE = 8
#: Blocks a striding reducing kernel keeps over all worlds where its items allow (``reduce_launch_dim``'s ``fill``):
#: fewer leave the device idle and each lane's items in a serial chain (a 64² cloth's check pass in 2 blocks of 8
#: items a lane took 54 µs, in 16 blocks of one 16 µs; H200, 132 multiprocessors).
REDUCE_FILL_BLOCKS = 512


#: ``per_lane`` of a striding reducing kernel on the CPU, where a block is one thread: one thread per world walks all
#: its items (no partial sum per item to write and gather).
CPU_PER_LANE = 1 << 62


def reduce_launch_dim(worlds: int, count: int, lanes: int, per_lane: int = 1, fill: int = 0) -> tuple[int, int, int]:
    """The 3-D launch grid [world, block, lane] of a reducing kernel over ``count`` items per world: one item a lane,
    or with ``per_lane`` > 1 a striding kernel (item ``block * lanes + lane``, then every ``reduce_stride``-th after
    it) whose lanes take up to ``per_lane`` items each while the worlds keep at least ``fill`` blocks in all."""
    one_each = (count + lanes - 1) // lanes
    blocks = (count + lanes * per_lane - 1) // (lanes * per_lane)
    if fill:
        blocks = max(blocks, -(-fill // max(worlds, 1)))
    return (worlds, min(blocks, one_each), lanes)


def reduce_stride(grid: tuple[int, int, int]) -> int:
    """The items between one lane's successive items in a striding reducing kernel launched over ``grid``."""
    return int(grid[1] * grid[2])


@wp.func_native("""
#if defined(__CUDA_ARCH__)
__threadfence_system();
#endif
""")
def system_fence():
    """This thread's writes before it are seen by the host (mapped pinned memory) before its writes after it
    (``__threadfence_system``; nothing on the CPU, whose kernels return before the host reads)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
__syncthreads();
#endif
""")
def block_barrier():
    """Every lane of the block waits here until all have arrived (``__syncthreads``; nothing on the CPU)."""
    ...


def _warp_peers(array: str) -> str:
    """C++ opening a warp-aggregated update of ``array[index]`` (``atomic_slot``, ``atomic_raise``): its ``address``,
    the active lanes that update the same one (``peers``), the first of them (``leader``) and this lane's number."""
    return f"""int* address = &{array}.data[index];
const unsigned int active = __activemask();
const unsigned int peers = __match_any_sync(active, (unsigned long long)address);
const int leader = __ffs(peers) - 1;
const unsigned int lane = threadIdx.x & 31u;
"""


@wp.func_native("""
#if defined(__CUDA_ARCH__)
""" + _warp_peers("counts") + """int first = 0;
if (lane == (unsigned int)leader) first = atomicAdd(address, __popc(peers));
first = __shfl_sync(peers, first, leader);
return first + __popc(peers & ((1u << lane) - 1u));
#else
return wp::atomic_add(&counts.data[index], 1);
#endif
""")
def atomic_slot(counts: wp.array[wp.int32], index: int) -> int:
    """``counts[index]`` before adding 1 to it, atomically: a slot of a list that ``counts[index]`` counts. On CUDA the
    active lanes of a warp that claim from the same counter add their number in one atomic and take consecutive
    slots (warp-aggregated): a broad phase listing millions of pairs into one world's list otherwise queues them
    all on one address. Which lane gets which slot is as arbitrary as with one atomic each. ``counts``
    contiguous. (Named ``atomic_*``: the kernel conventions' check reads ``counts`` as written.)"""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
""" + _warp_peers("values") + """int largest = value;
#if __CUDA_ARCH__ >= 800
largest = __reduce_max_sync(peers, value);
#else
for (unsigned int others = peers; others != 0u; others &= others - 1u) {
    const int other = __shfl_sync(peers, value, __ffs(others) - 1);
    largest = other > largest ? other : largest;
}
#endif
if (lane == (unsigned int)leader && largest > *((volatile int*)address)) atomicMax(address, largest);
#else
if (value > values.data[index]) wp::atomic_max(&values.data[index], value);
#endif
""")
def atomic_raise(values: wp.array[wp.int32], index: int, value: int):
    """``values[index] = max(values[index], value)``, an integer maximum (order-free), read first so that a value below
    the one stored costs no atomic. On CUDA the active lanes of a warp that raise the same entry take their largest
    first and one of them raises it (warp-aggregated): a pass whose every thread records a bound into its world's
    entry otherwise queues them all on one address. A stale read costs one more atomic, never a wrong result.
    ``values`` contiguous. (Named ``atomic_*``: the kernel conventions' check reads ``values`` as written.)"""
    ...


def _warp_total_source(ctype: str) -> str:
    """C++ of ``warp_total`` for values of ``ctype``."""
    return f"""
#if defined(__CUDA_ARCH__)
if (__activemask() != 0xffffffffu) return value;
if (!__all_sync(0xffffffffu, __shfl_sync(0xffffffffu, group, 0) == group)) return value;
{ctype} a = value;
for (int offset = 16; offset > 0; offset >>= 1) a += __shfl_down_sync(0xffffffffu, a, offset);
return (threadIdx.x & 31u) == 0u ? a : ({ctype})0;
#else
return value;
#endif
"""


@wp.func_native(_warp_total_source("float"))
def _warp_total_f32(value: wp.float32, group: int) -> wp.float32:
    """``warp_total`` in single precision."""
    ...


@wp.func_native(_warp_total_source("double"))
def _warp_total_f64(value: wp.float64, group: int) -> wp.float64:
    """``warp_total`` in double precision."""
    ...


@functools.cache
def warp_total_func(scalar: type):
    """``warp_total(value, group) -> scalar``: on CUDA, where the 32 lanes of the warp call it together (converged:
    ``__activemask`` full) and all are in the same ``group`` (a world), the sum of their values (a fixed tree of
    shuffles) in lane 0 and zero in the others; else (a warp at the end of a launch, one that spans two worlds, or
    lanes that reach the call apart) each lane's own value. A lane that gets zero has nothing to add: a per-item sum
    kept this way (``integrators.symplectic_euler_particle_func``'s power) reads and writes one entry a warp instead
    of one an item, and a reader summing a group's entries gets the same total up to the order of its additions (the
    lanes' convergence decides how much is saved, never the total). On the CPU the value itself."""
    if scalar == wp.float64:
        return _warp_total_f64
    return _warp_total_f32


def block_max_ints_func(length: int):
    """``block_max_ints(values) -> vector(length, int32)``: the largest of each entry of ``values`` over the lanes of
    the block, in every lane (the values themselves on the CPU, where a block is one thread): each warp's lanes by
    shuffles, then each lane over the warps' results in shared memory. Two barriers a call for every entry at once
    (a ``tile_reduce`` per entry took two shared-memory rounds and their barriers each). Every lane of the block must
    call it; ``blockDim.x`` a multiple of 32."""
    return _block_max_ints(int(length))


@functools.cache
def _block_max_ints(length: int):
    vector = wp.types.vector(length, wp.int32)
    source = f"""
#if defined(__CUDA_ARCH__)
__shared__ int warp_results[{length}][32];
const unsigned int lane = threadIdx.x & 31u;
const unsigned int warp = threadIdx.x >> 5;
const unsigned int warps = (blockDim.x + 31u) >> 5;
for (int k = 0; k < {length}; ++k) {{
    int a = values.c[k];
#if __CUDA_ARCH__ >= 800
    a = __reduce_max_sync(0xffffffffu, a);
#else
    for (int offset = 16; offset > 0; offset >>= 1) {{
        const int b = __shfl_xor_sync(0xffffffffu, a, offset);
        a = b > a ? b : a;
    }}
#endif
    if (lane == 0u) warp_results[k][warp] = a;
}}
__syncthreads();
wp::vec_t<{length}, wp::int32> result;
for (int k = 0; k < {length}; ++k) {{
    int a = warp_results[k][0];
    for (unsigned int w = 1u; w < warps; ++w) a = warp_results[k][w] > a ? warp_results[k][w] : a;
    result.c[k] = a;
}}
__syncthreads();
return result;
#else
return values;
#endif
"""

    @wp.func_native(source)
    def block_max_ints(values: vector) -> vector:
        ...

    return block_max_ints


def _block_reduce_source(sums: int, maxes: int, vector: bool) -> str:
    """C++ of a block-wide reduction of ``sums + maxes`` float64s, the first ``sums`` entries added and the others'
    largest taken: of the argument ``values``, a vector of them (``block_reduce_funcs``), or where not ``vector`` of the
    one float64 ``value`` (``reduction_funcs``). Each entry by the same tree: each warp's lanes by shuffles, then warp 0
    over the warps' results, then every lane reads the block's. Two barriers a call, however many entries
    (``tile_sum(tile(value))[0]`` took four and shared-memory tiles: a check pass's blocks reduced in it spent most of
    its time there, 221 µs against 62 µs for the same pass writing one value a thread; ncu on an H200). A call reuses
    its shared slots safely: the next call writes a warp's slot after the barrier that follows warp 0's reads, and the
    totals after the barrier that follows every lane's read of them. Every lane of the block must call it (as a tile
    operation); ``blockDim.x`` a multiple of 32. On the CPU, where a block is one thread, the values themselves."""
    length = sums + maxes
    argument = "values" if vector else "value"
    if vector:
        read, results = f"{argument}.c[k]", (f"wp::vec_t<{length}, wp::float64> result;\n"
                                             f"for (int k = 0; k < {length}; ++k) result.c[k] = block_results[k];\n"
                                             "return result;")
    else:
        read, results = argument, "return block_results[0];"
    combine = "a + b" if not maxes else "(b > a ? b : a)" if not sums else f"(k < {sums} ? a + b : (b > a ? b : a))"
    return f"""
#if defined(__CUDA_ARCH__)
__shared__ double warp_results[{length}][32];
__shared__ double block_results[{length}];
const unsigned int lane = threadIdx.x & 31u;
const unsigned int warp = threadIdx.x >> 5;
const unsigned int warps = (blockDim.x + 31u) >> 5;
for (int k = 0; k < {length}; ++k) {{
    double a = {read};
    for (int offset = 16; offset > 0; offset >>= 1) {{
        const double b = __shfl_down_sync(0xffffffffu, a, offset);
        a = {combine};
    }}
    if (lane == 0u) warp_results[k][warp] = a;
}}
__syncthreads();
if (warp == 0u) {{
    for (int k = 0; k < {length}; ++k) {{
        double a = lane < warps ? warp_results[k][lane] : warp_results[k][0];
        for (int offset = 16; offset > 0; offset >>= 1) {{
            const double b = __shfl_down_sync(0xffffffffu, a, offset);
            a = (lane + offset < warps) ? {combine} : a;
        }}
        if (lane == 0u) block_results[k] = a;
    }}
}}
__syncthreads();
{results}
#else
return {argument};
#endif
"""


@wp.func_native(_block_reduce_source(1, 0, vector=False))
def _block_sum_native(value: wp.float64) -> wp.float64:
    """The sum of ``value`` over the block's lanes (``_block_reduce_source``)."""
    ...


@wp.func_native(_block_reduce_source(0, 1, vector=False))
def _block_max_native(value: wp.float64) -> wp.float64:
    """The largest ``value`` over the block's lanes (``_block_reduce_source``)."""
    ...


@functools.cache
def block_reduce_funcs(tiled: bool, sums: int, maxes: int):
    """``(vector, block_reduce)``: ``vector`` the type of ``sums + maxes`` float64s, and ``block_reduce(values) ->
    vector``: over the lanes of a block, in every lane, the sum of each of the first ``sums`` entries of ``values`` and
    the largest of each of the other ``maxes`` (the values themselves where not ``tiled``: the CPU, where a block is one
    thread). Each entry by the very tree of :func:`reduction_funcs`' ``block_sum`` and ``block_max`` (one source,
    ``_block_reduce_source``: the same bits), all entries in one round: two barriers a call, where those take two an
    entry. Every lane of the block must call it; ``blockDim.x`` a multiple of 32."""
    vector = wp.types.vector(sums + maxes, wp.float64)
    native = _block_reduce(int(sums), int(maxes))

    @wp.func
    def block_reduce(values: vector) -> vector:
        if wp.static(tiled):
            return native(values)
        return values

    return vector, block_reduce


@functools.cache
def _block_reduce(sums: int, maxes: int):
    vector = wp.types.vector(sums + maxes, wp.float64)

    @wp.func_native(_block_reduce_source(sums, maxes, vector=True))
    def block_reduce(values: vector) -> vector:
        ...

    return block_reduce


@functools.cache
def reduction_funcs(tiled: bool):
    """``block_sum(value)``: the sum of a value over the lanes of a block (every lane gets it; the value
    itself on the CPU, where a block is one thread), and ``block_max``. Deterministic: a fixed-order tree (warp
    shuffles, then the warps' results)."""

    @wp.func
    def block_sum(value: wp.float64) -> wp.float64:
        if wp.static(tiled):
            return _block_sum_native(value)
        return value

    @wp.func
    def block_max(value: wp.float64) -> wp.float64:
        if wp.static(tiled):
            return _block_max_native(value)
        return value

    return block_sum, block_max


@functools.cache
def sum_partials_kernel(tiled: bool):
    """Kernel adding the per-block partials of slots [first, first + count) of every world, in a fixed
    order, into ``scalars[world, slot]``. Launch over [world_count, lanes] with ``block_dim`` = lanes."""
    block_sum, _ = reduction_funcs(tiled)

    @wp.kernel(module="unique", enable_backward=False)
    def sum_partials(
        # In:
        first: int,
        count: int,
        partials: wp.array3d[wp.float64],
        # Out:
        scalars_out: wp.array2d[wp.float64],
    ):
        world, lane = wp.tid()
        lanes = wp.block_dim()
        blocks = partials.shape[1]
        for c in range(count):
            total = wp.float64(0.0)
            b = lane
            while b < blocks:
                total += partials[world, b, first + c]
                b += lanes
            total = block_sum(total)
            if lane == 0:
                scalars_out[world, first + c] = total

    return sum_partials


@functools.cache
def cg_kernels(scalar: type, tiled: bool):
    """(begin, start, update_solution, update_direction, condition) kernels of block-Jacobi PCG on vec3
    unknowns, one system per world (see the module docstring for the grids)."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    block_sum, _ = reduction_funcs(tiled)

    @wp.kernel(module="unique", enable_backward=False)
    def begin(
        # Model:
        world_enabled: wp.array[wp.int32],
        # Out:
        scalars_out: wp.array2d[wp.float64],
        iteration_out: wp.array[wp.int32],
        active_out: wp.array[wp.int32],
        keep_going_out: wp.array[wp.int32],
    ):
        """Start a solve in every enabled world (``keep_going`` zeroed beforehand counts them)."""
        world = wp.tid()
        for slot in range(CG_SCALARS):
            scalars_out[world, slot] = wp.float64(0.0)
        iteration_out[world] = -1
        active_out[world] = world_enabled[world]
        if world_enabled[world] != 0:
            wp.atomic_add(keep_going_out, 0, 1)

    @wp.kernel(module="unique", enable_backward=False)
    def start(
        # In (the system):
        count: int,
        active: wp.array[wp.int32],
        rhs: wp.array[vec3],
        a_x: wp.array[vec3],
        diagonal_inverse: wp.array[mat33],
        # Out:
        r_out: wp.array[vec3],
        z_out: wp.array[vec3],
        p_out: wp.array[vec3],
        partials_out: wp.array3d[wp.float64],
    ):
        """r = b - A x, z = P r, p = z; partial sums of r·z, r·r and b·b."""
        world, block, lane = wp.tid()
        if active[world] == 0:
            return
        i = block * wp.block_dim() + lane
        rz = wp.float64(0.0)
        rr = wp.float64(0.0)
        bb = wp.float64(0.0)
        if i < count:
            k = world * count + i
            b = rhs[k]
            ri = b - a_x[k]
            zi = diagonal_inverse[k] * ri
            r_out[k] = ri
            z_out[k] = zi
            p_out[k] = zi
            rz = wp.float64(wp.dot(ri, zi))
            rr = wp.float64(wp.dot(ri, ri))
            bb = wp.float64(wp.dot(b, b))
        rz = block_sum(rz)
        rr = block_sum(rr)
        bb = block_sum(bb)
        if lane == 0:
            partials_out[world, block, CG_RZ_NEW] = rz
            partials_out[world, block, CG_RR] = rr
            partials_out[world, block, CG_BB] = bb

    @wp.kernel(module="unique", enable_backward=False)
    def update_solution(
        # In:
        count: int,
        active: wp.array[wp.int32],
        p: wp.array[vec3],
        a_p: wp.array[vec3],
        diagonal_inverse: wp.array[mat33],
        scalars: wp.array2d[wp.float64],
        # In/out:
        x_in_out: wp.array[vec3],
        r_in_out: wp.array[vec3],
        z_out: wp.array[vec3],
        partials_out: wp.array3d[wp.float64],
    ):
        """α = r·z / p·Ap; x += α p; r -= α Ap; z = P r; partial sums of the new r·z and r·r."""
        world, block, lane = wp.tid()
        if active[world] == 0:
            return
        i = block * wp.block_dim() + lane
        rz = wp.float64(0.0)
        rr = wp.float64(0.0)
        if i < count:
            k = world * count + i
            p_ap = scalars[world, CG_PAP]
            alpha = scalar(wp.where(p_ap > wp.float64(0.0), scalars[world, CG_RZ] / p_ap, wp.float64(0.0)))
            x_in_out[k] = x_in_out[k] + alpha * p[k]
            ri = r_in_out[k] - alpha * a_p[k]
            zi = diagonal_inverse[k] * ri
            r_in_out[k] = ri
            z_out[k] = zi
            rz = wp.float64(wp.dot(ri, zi))
            rr = wp.float64(wp.dot(ri, ri))
        rz = block_sum(rz)
        rr = block_sum(rr)
        if lane == 0:
            partials_out[world, block, CG_RZ_NEW] = rz
            partials_out[world, block, CG_RR] = rr

    @wp.kernel(module="unique", enable_backward=False)
    def update_direction(
        # In:
        count: int,
        active: wp.array[wp.int32],
        z: wp.array[vec3],
        scalars: wp.array2d[wp.float64],
        # In/out:
        p_in_out: wp.array[vec3],
    ):
        """p = z + β p."""
        k = wp.tid()
        world, i = world_and_index(k, count)
        if active[world] == 0:
            return
        p_in_out[k] = z[k] + scalar(scalars[world, CG_BETA]) * p_in_out[k]

    @wp.kernel(module="unique", enable_backward=False)
    def condition(
        # Settings:
        settings: wp.array[wp.float64],
        # In/out:
        scalars_in_out: wp.array2d[wp.float64],
        iteration_in_out: wp.array[wp.int32],
        active_in_out: wp.array[wp.int32],
        keep_going_out: wp.array[wp.int32],
        shortfall_in_out: wp.array2d[wp.float64],
    ):
        """Per world: count an iteration; stop when ‖r‖ ≤ tol·‖b‖, when the iterations are spent, or when the
        residual is not finite (a diverged world: the guards report it); else take β and go on. A solve that
        stops at the cap unconverged (finite) is counted in the world's row of ``shortfall`` with its ‖r‖²/‖b‖²
        (the largest so far kept): one thread per world writes it, no atomics."""
        world = wp.tid()
        if active_in_out[world] == 0:
            return
        rr = scalars_in_out[world, CG_RR]
        tolerance = settings[CG_TOLERANCE]
        iteration_in_out[world] = iteration_in_out[world] + 1
        converged = rr <= wp.max(tolerance * tolerance * scalars_in_out[world, CG_BB], wp.float64(1.0e-300))
        exhausted = wp.float64(iteration_in_out[world]) >= settings[CG_MAX_ITERATIONS]
        rz = scalars_in_out[world, CG_RZ]
        rz_new = scalars_in_out[world, CG_RZ_NEW]
        scalars_in_out[world, CG_BETA] = wp.where(rz > wp.float64(0.0), rz_new / rz, wp.float64(0.0))
        scalars_in_out[world, CG_RZ] = rz_new
        scalars_in_out[world, CG_RR_LAST] = rr
        if converged or exhausted or not wp.isfinite(rr):
            active_in_out[world] = 0
            wp.atomic_sub(keep_going_out, 0, 1)
            if exhausted and not converged and wp.isfinite(rr):
                relative = rr / wp.max(scalars_in_out[world, CG_BB], wp.float64(1.0e-300))
                shortfall_in_out[world, CG_SHORT_COUNT] = shortfall_in_out[world, CG_SHORT_COUNT] + wp.float64(1.0)
                shortfall_in_out[world, CG_SHORT_WORST] = wp.max(shortfall_in_out[world, CG_SHORT_WORST], relative)

    return begin, start, update_solution, update_direction, condition
