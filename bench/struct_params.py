"""What a Warp struct kernel parameter costs a gather kernel, with everything else equal.

One 12-slot ELL spring gather over an N × N grid (the hanging cloth's stencil: 4 structural, 4 shear,
4 bend neighbours; 0.01 m spacing, ke = 100 N/m, kd = 0.1 N·s/m), the same arrays and the same
arithmetic, four ways of handing the arrays to the kernel:

* ``flat``: five array parameters (how the force kernels took the springs before the element families);
* ``struct``: one ``wp.struct`` parameter holding the five arrays;
* ``nested``: the element families' layout (``kernels/families.py``): a chain struct holding the
  spring struct holding an incidence struct, with the unused fields (spring indices, CSR tail) too;
* ``built``: five array parameters packed into the same struct inside the kernel;
* ``array``: the struct of ``struct`` stored in a one-element device array, read at the kernel's start;
* ``flattened``: ``nested`` compiled by ``kernels/flatten.py``'s ``flat_kernel`` (one parameter per leaf,
  the struct rebuilt in the body), the four leaves it never reads (spring indices, CSR tail) where the
  struct declares them, between the ones it reads;
* ``flattened, idle last``: the same with ``flat_kernel(last=...)``, those four leaves the last parameters.

Each variant is 50 launches captured in one CUDA graph; reported is the median time per launch over
rounds that alternate the variants, and its ratio to ``flat`` (above 1 is faster). On the GPU the
struct parameter, not the struct, is what costs: see ``bench/RESULTS.md`` §9.

    python bench/struct_params.py --device cuda:0 --sizes 64 256 1024
"""


import argparse
import datetime
import time

import numpy as np
import warp as wp

from cloth import emit_table
from warpspring.kernels.flatten import flat_inputs, flat_kernel

SLOTS = 12
STENCIL = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1), (2, 0), (-2, 0), (0, 2), (0, -2)]
LAUNCHES = 50


@wp.func
def spring_force(xi: wp.vec3, xj: wp.vec3, vi: wp.vec3, vj: wp.vec3, rest: float, ke: float, kd: float) -> wp.vec3:
    d = xj - xi
    length = wp.length(d)
    n = d * wp.where(length > 1.0e-12, 1.0 / length, 0.0)
    return n * (ke * (length - rest) + kd * wp.dot(vj - vi, n))


@wp.func
def gather(
    i: int, neighbour: wp.array2d[wp.int32], element: wp.array2d[wp.int32], rest: wp.array[float],
    ke: wp.array2d[float], kd: wp.array2d[float], q: wp.array[wp.vec3], qd: wp.array[wp.vec3],
) -> wp.vec3:
    xi = q[i]
    vi = qd[i]
    f = wp.vec3(0.0)
    for k in range(wp.static(SLOTS)):
        j = neighbour[k, i]
        s = element[k, i]
        f += spring_force(xi, q[j], vi, qd[j], rest[s], ke[0, s], kd[0, s])
    return f


@wp.struct
class Springs:
    neighbour: wp.array2d[wp.int32]
    element: wp.array2d[wp.int32]
    rest: wp.array[float]
    ke: wp.array2d[float]
    kd: wp.array2d[float]


@wp.struct
class Incidence:
    head_element: wp.array2d[wp.int32]
    head_local: wp.array2d[wp.int32]
    tail_start: wp.array[wp.int32]
    tail_element: wp.array[wp.int32]
    tail_local: wp.array[wp.int32]


@wp.struct
class SpringFamily:
    indices: wp.array[wp.vec2i]
    rest_length: wp.array[float]
    stiffness: wp.array2d[float]
    damping: wp.array2d[float]
    incidence: Incidence


@wp.struct
class Chain:
    head: SpringFamily


@wp.kernel(enable_backward=False)
def flat(
    neighbour: wp.array2d[wp.int32], element: wp.array2d[wp.int32], rest: wp.array[float], ke: wp.array2d[float],
    kd: wp.array2d[float], q: wp.array[wp.vec3], qd: wp.array[wp.vec3], out: wp.array[wp.vec3],
):
    i = wp.tid()
    out[i] = gather(i, neighbour, element, rest, ke, kd, q, qd)


@wp.kernel(enable_backward=False)
def struct(springs: Springs, q: wp.array[wp.vec3], qd: wp.array[wp.vec3], out: wp.array[wp.vec3]):
    i = wp.tid()
    out[i] = gather(i, springs.neighbour, springs.element, springs.rest, springs.ke, springs.kd, q, qd)


@wp.kernel(enable_backward=False)
def nested(chain: Chain, q: wp.array[wp.vec3], qd: wp.array[wp.vec3], out: wp.array[wp.vec3]):
    i = wp.tid()
    family = chain.head
    out[i] = gather(i, family.incidence.head_local, family.incidence.head_element, family.rest_length,
                    family.stiffness, family.damping, q, qd)


def nested_body(chain: Chain, q: wp.array[wp.vec3], qd: wp.array[wp.vec3], out: wp.array[wp.vec3]):
    i = wp.tid()
    family = chain.head
    out[i] = gather(i, family.incidence.head_local, family.incidence.head_element, family.rest_length,
                    family.stiffness, family.damping, q, qd)


flattened = flat_kernel(nested_body, module="unique", enable_backward=False)
flattened_idle_last = flat_kernel(nested_body, module="unique", enable_backward=False,
                                  last=("chain__head__indices", "chain__head__incidence__tail_start",
                                        "chain__head__incidence__tail_element", "chain__head__incidence__tail_local"))


def flat_arguments(kernel, inputs: list) -> list:
    """``inputs`` expanded as ``flat_launch`` does, in the kernel's parameter order."""
    values = flat_inputs(inputs)
    order = getattr(kernel, "flat_order", None)
    return values if order is None else [values[k] for k in order]


@wp.func
def gather_struct(i: int, springs: Springs, q: wp.array[wp.vec3], qd: wp.array[wp.vec3]) -> wp.vec3:
    return gather(i, springs.neighbour, springs.element, springs.rest, springs.ke, springs.kd, q, qd)


@wp.kernel(enable_backward=False)
def built(
    neighbour: wp.array2d[wp.int32], element: wp.array2d[wp.int32], rest: wp.array[float], ke: wp.array2d[float],
    kd: wp.array2d[float], q: wp.array[wp.vec3], qd: wp.array[wp.vec3], out: wp.array[wp.vec3],
):
    i = wp.tid()
    springs = Springs()
    springs.neighbour = neighbour
    springs.element = element
    springs.rest = rest
    springs.ke = ke
    springs.kd = kd
    out[i] = gather_struct(i, springs, q, qd)


@wp.kernel(enable_backward=False)
def in_array(springs: wp.array[Springs], q: wp.array[wp.vec3], qd: wp.array[wp.vec3], out: wp.array[wp.vec3]):
    i = wp.tid()
    out[i] = gather_struct(i, springs[0], q, qd)


def variants(n: int, device) -> dict:
    """The launch arguments of every variant for an n × n grid (clamped stencil at the borders)."""
    count = n * n
    ix, iy = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))
    neighbour = np.empty((SLOTS, count), np.int32)
    for k, (dx, dy) in enumerate(STENCIL):
        neighbour[k] = np.clip(ix + dx, 0, n - 1) * n + np.clip(iy + dy, 0, n - 1)
    element = np.arange(SLOTS * count, dtype=np.int32).reshape(SLOTS, count)
    springs_count = SLOTS * count
    rng = np.random.default_rng(0)
    x = np.stack([ix, iy, np.zeros_like(ix)], 1) * 0.01 + rng.normal(0.0, 1.0e-3, (count, 3))
    arrays = {
        "neighbour": wp.array(neighbour, device=device),
        "element": wp.array(element, device=device),
        "rest": wp.full(springs_count, 0.01, dtype=float, device=device),
        "ke": wp.full((1, springs_count), 100.0, dtype=float, device=device),
        "kd": wp.full((1, springs_count), 0.1, dtype=float, device=device),
    }
    q = wp.array(x.astype(np.float32), dtype=wp.vec3, device=device)
    qd = wp.zeros(count, wp.vec3, device=device)
    out = wp.zeros(count, wp.vec3, device=device)
    springs = Springs()
    for name, a in arrays.items():
        setattr(springs, name, a)
    incidence = Incidence()
    incidence.head_element = arrays["element"]
    incidence.head_local = arrays["neighbour"]
    incidence.tail_start = wp.zeros(count + 1, wp.int32, device=device)
    incidence.tail_element = wp.zeros(0, wp.int32, device=device)
    incidence.tail_local = wp.zeros(0, wp.int32, device=device)
    family = SpringFamily()
    family.indices = wp.zeros(springs_count, wp.vec2i, device=device)
    family.rest_length, family.stiffness, family.damping = arrays["rest"], arrays["ke"], arrays["kd"]
    family.incidence = incidence
    chain = Chain()
    chain.head = family
    flat_args = [*arrays.values(), q, qd, out]
    return {
        "flat": (flat, flat_args),
        "struct": (struct, [springs, q, qd, out]),
        "nested": (nested, [chain, q, qd, out]),
        "built": (built, flat_args),
        "array": (in_array, [wp.array([springs], dtype=Springs, device=device), q, qd, out]),
        "flattened": (flattened, flat_arguments(flattened, [chain, q, qd, out])),
        "flattened, idle last": (flattened_idle_last, flat_arguments(flattened_idle_last, [chain, q, qd, out])),
    }, out


def time_variants(n: int, device, rounds: int) -> dict:
    """Median seconds per launch of every variant, rounds alternating between them; checks all agree."""
    cases, out = variants(n, device)
    graphs, results = {}, {}
    for name, (kernel, args) in cases.items():
        wp.launch(kernel, n * n, inputs=args, device=device)
        results[name] = out.numpy().copy()
        with wp.ScopedCapture(device=device) as capture:
            for _ in range(LAUNCHES):
                wp.launch(kernel, n * n, inputs=args, device=device)
        graphs[name] = capture.graph
    for name, r in results.items():
        if not np.array_equal(r, results["flat"]):
            raise RuntimeError(f"variant {name} computes something else than flat")
    times = {name: [] for name in graphs}
    for _ in range(rounds):
        for name, graph in graphs.items():
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            wp.capture_launch(graph)
            wp.synchronize_device(device)
            times[name].append((time.perf_counter() - t0) / LAUNCHES)
    return {name: float(np.median(t)) for name, t in times.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    if not device.is_cuda:
        parser.error("this benchmark captures CUDA graphs: give a CUDA device, e.g. --device cuda:0")
    lines = [
        f"Struct kernel parameters on {device.name}, Warp {wp.config.version}, {datetime.date.today()}, "
        f"{LAUNCHES} launches per graph, median of {args.rounds} alternating rounds",
        "",
        "| N | variant | µs per launch | speed vs flat |",
        "|---|---|---|---|",
    ]
    for n in args.sizes:
        t = time_variants(n, device, args.rounds)
        for name, seconds in t.items():
            lines.append(f"| {n} | {name} | {seconds * 1e6:.2f} | {t['flat'] / seconds:.3f}× |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
