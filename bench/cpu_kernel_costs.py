"""What a CPU kernel pays for its indexing: the spring scatter of the reference cloth written seven ways, the
per-particle pass with three ways of finding a particle's world, and a launch's own cost inside a CPU graph.

Warp runs a CPU kernel's threads one after another in a loop, so arithmetic done per thread to find *which*
element it is (a two-dimensional ``wp.tid()``, an integer division, the address of a 2-D per-world array) is
paid once per element, serially, where a GPU hides it behind memory latency. Each variant below adds one such
piece to the scatter of 8543a2f (1-D launch, flat arrays); each is timed inside a CPU graph of ``--repeat``
launches, and the minimum over ``--samples`` replays is reported (the machine's load only ever adds time).

    python bench/cpu_kernel_costs.py --sizes 32 64
    python bench/cpu_kernel_costs.py --sizes 32 --out bench/results/x.md
"""

import argparse
import datetime
import os
import statistics
import sys
import time

import numpy as np
import warp as wp

from warpspring.kernels.flatten import flat_kernel, flat_launch

wp.set_module_options({"enable_backward": False})
OPTIONS = {"fast_math": True}


@wp.func
def spring_force(xi: wp.vec3, xj: wp.vec3, vi: wp.vec3, vj: wp.vec3, rest: float, ke: float, kd: float) -> wp.vec3:
    d = xj - xi
    length = wp.length(d)
    if length > 1.0e-9:
        n = d / length
        return n * (ke * (length - rest) + kd * wp.dot(vj - vi, n))
    return wp.vec3()


@wp.kernel(module="unique", module_options=OPTIONS)
def flat_1d(ends: wp.array[wp.vec2i], rest: wp.array[float], ke: wp.array[float], kd: wp.array[float],
            q: wp.array[wp.vec3], qd: wp.array[wp.vec3], f_in_out: wp.array[wp.vec3]):
    s = wp.tid()
    e = ends[s]
    fs = spring_force(q[e[0]], q[e[1]], qd[e[0]], qd[e[1]], rest[s], ke[s], kd[s])
    wp.atomic_add(f_in_out, e[0], fs)
    wp.atomic_sub(f_in_out, e[1], fs)


@wp.kernel(module="unique", module_options=OPTIONS)
def launch_2d(particle_count: int, ends: wp.array[wp.vec2i], rest: wp.array[float], ke: wp.array[float],
              kd: wp.array[float], q: wp.array[wp.vec3], qd: wp.array[wp.vec3], f_in_out: wp.array[wp.vec3]):
    world, s = wp.tid()
    base = world * particle_count
    e = ends[s]
    i = base + e[0]
    j = base + e[1]
    fs = spring_force(q[i], q[j], qd[i], qd[j], rest[s], ke[s], kd[s])
    wp.atomic_add(f_in_out, i, fs)
    wp.atomic_sub(f_in_out, j, fs)


@wp.kernel(module="unique", module_options=OPTIONS)
def launch_2d_rows_2d(particle_count: int, ends: wp.array[wp.vec2i], rest: wp.array[float], ke: wp.array2d[float],
                      kd: wp.array2d[float], q: wp.array[wp.vec3], qd: wp.array[wp.vec3],
                      f_in_out: wp.array[wp.vec3]):
    world, s = wp.tid()
    base = world * particle_count
    e = ends[s]
    i = base + e[0]
    j = base + e[1]
    fs = spring_force(q[i], q[j], qd[i], qd[j], rest[s], ke[wp.min(world, ke.shape[0] - 1), s],
                      kd[wp.min(world, kd.shape[0] - 1), s])
    wp.atomic_add(f_in_out, i, fs)
    wp.atomic_sub(f_in_out, j, fs)


@wp.struct
class Springs:
    ends: wp.array[wp.vec2i]
    rest: wp.array[float]
    ke: wp.array2d[float]
    kd: wp.array2d[float]


def struct_scatter(decorate):
    """The 2-D launch with per-world 2-D ke, kd, its arrays in one struct parameter (``decorate``: ``wp.kernel`` or
    ``flat_kernel``, which compiles the struct as flat parameters and rebuilds it in the body)."""

    @decorate(module="unique", module_options=OPTIONS)
    def scatter(particle_count: int, springs: Springs, q: wp.array[wp.vec3], qd: wp.array[wp.vec3],
                f_in_out: wp.array[wp.vec3]):
        world, s = wp.tid()
        base = world * particle_count
        e = springs.ends[s]
        i = base + e[0]
        j = base + e[1]
        fs = spring_force(q[i], q[j], qd[i], qd[j], springs.rest[s],
                          springs.ke[wp.min(world, springs.ke.shape[0] - 1), s],
                          springs.kd[wp.min(world, springs.kd.shape[0] - 1), s])
        wp.atomic_add(f_in_out, i, fs)
        wp.atomic_sub(f_in_out, j, fs)

    return scatter


@wp.kernel(module="unique", module_options=OPTIONS)
def flat_1d_rows_2d(ends: wp.array[wp.vec2i], rest: wp.array[float], ke: wp.array2d[float], kd: wp.array2d[float],
                    q: wp.array[wp.vec3], qd: wp.array[wp.vec3], f_in_out: wp.array[wp.vec3]):
    s = wp.tid()
    world = 0
    e = ends[s]
    fs = spring_force(q[e[0]], q[e[1]], qd[e[0]], qd[e[1]], rest[s], ke[wp.min(world, ke.shape[0] - 1), s],
                      kd[wp.min(world, kd.shape[0] - 1), s])
    wp.atomic_add(f_in_out, e[0], fs)
    wp.atomic_sub(f_in_out, e[1], fs)


@wp.kernel(module="unique", module_options=OPTIONS)
def divided_1d(spring_count: int, particle_count: int, ends: wp.array[wp.vec2i], rest: wp.array[float],
               ke: wp.array[float], kd: wp.array[float], q: wp.array[wp.vec3], qd: wp.array[wp.vec3],
               f_in_out: wp.array[wp.vec3]):
    t = wp.tid()
    world = t // spring_count
    s = t - world * spring_count
    base = world * particle_count
    e = ends[s]
    i = base + e[0]
    j = base + e[1]
    fs = spring_force(q[i], q[j], qd[i], qd[j], rest[s], ke[s], kd[s])
    wp.atomic_add(f_in_out, i, fs)
    wp.atomic_sub(f_in_out, j, fs)


@wp.kernel(module="unique", module_options=OPTIONS)
def branched_1d_rows_flat(spring_count: int, particle_count: int, rows: int, ends: wp.array[wp.vec2i],
                          rest: wp.array[float], ke: wp.array[float], kd: wp.array[float], q: wp.array[wp.vec3],
                          qd: wp.array[wp.vec3], f_in_out: wp.array[wp.vec3]):
    t = wp.tid()
    world = int(0)
    s = t
    if t >= spring_count:  # world 0 skips the division
        world = t // spring_count
        s = t - world * spring_count
    base = world * particle_count
    row = wp.min(world, rows - 1) * spring_count + s  # per-world values as one flat array, rows × springs
    e = ends[s]
    i = base + e[0]
    j = base + e[1]
    fs = spring_force(q[i], q[j], qd[i], qd[j], rest[s], ke[row], kd[row])
    wp.atomic_add(f_in_out, i, fs)
    wp.atomic_sub(f_in_out, j, fs)


@wp.func
def world_divided(p: int, particle_count: int):
    world = p // particle_count
    return world, p - world * particle_count


@wp.func
def world_branched(p: int, particle_count: int):
    if p < particle_count:
        return 0, p
    world = p // particle_count
    return world, p - world * particle_count


def particle_kernel(locate):
    @wp.kernel(module="unique", module_options=OPTIONS)
    def update(particle_count: int, inv_mass: wp.array2d[float], inputs: wp.array2d[float], q: wp.array[wp.vec3],
               qd: wp.array[wp.vec3], q_out: wp.array[wp.vec3], qd_out: wp.array[wp.vec3]):
        p = wp.tid()
        world, i = locate(p, particle_count)
        g = wp.vec3(inputs[world, 0], inputs[world, 1], inputs[world, 2])
        v = qd[p] + 1.0e-3 * inv_mass[wp.min(world, inv_mass.shape[0] - 1), i] * g
        q_out[p] = q[p] + 1.0e-3 * v
        qd_out[p] = v

    return update


@wp.kernel(module="unique", module_options=OPTIONS)
def particle_rows_flat(particle_count: int, rows: int, inv_mass: wp.array[float], inputs: wp.array[float],
                       q: wp.array[wp.vec3], qd: wp.array[wp.vec3], q_out: wp.array[wp.vec3],
                       qd_out: wp.array[wp.vec3]):
    p = wp.tid()
    world, i = world_branched(p, particle_count)
    g = wp.vec3(inputs[world * 15], inputs[world * 15 + 1], inputs[world * 15 + 2])
    v = qd[p] + 1.0e-3 * inv_mass[wp.min(world, rows - 1) * particle_count + i] * g
    q_out[p] = q[p] + 1.0e-3 * v
    qd_out[p] = v


@wp.kernel(module="unique", module_options=OPTIONS)
def particle_flat(inv_mass: wp.array[float], g: wp.vec3, q: wp.array[wp.vec3], qd: wp.array[wp.vec3],
                  q_out: wp.array[wp.vec3], qd_out: wp.array[wp.vec3]):
    p = wp.tid()
    v = qd[p] + 1.0e-3 * inv_mass[p] * g
    q_out[p] = q[p] + 1.0e-3 * v
    qd_out[p] = v


@wp.kernel(module="unique", module_options=OPTIONS)
def touch(a: wp.array[float]):
    a[wp.tid()] += 1.0


def grid_springs(n: int) -> np.ndarray:
    """The reference cloth's springs (structural, shear, bend) on an n × n grid, as index pairs."""
    index = np.arange(n * n).reshape(n, n)
    pairs = [np.stack([index[:n - di, max(0, -dj):n - max(0, dj)].ravel(),
                       index[di:, max(0, dj):n + min(0, dj)].ravel()], 1)
             for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1), (0, 2), (2, 0))]
    return np.concatenate(pairs).astype(np.int32)


def timed(cases: dict, repeat: int, samples: int) -> dict:
    """Minimum seconds per launch of every case (kernel, dim, inputs), replayed in turn inside CPU graphs."""
    graphs = {}
    for name, (kernel, dim, inputs) in cases.items():
        launch = flat_launch if hasattr(kernel, "flat_order") else wp.launch  # flat_kernel's kernels carry flat_order
        launch(kernel, dim=dim, inputs=inputs, device="cpu")
        with wp.ScopedCapture(device="cpu", force_module_load=False) as capture:
            for _ in range(repeat):
                launch(kernel, dim=dim, inputs=inputs, device="cpu")
        graphs[name] = capture.graph
    times = {name: [] for name in cases}
    for _ in range(samples):
        for name, graph in graphs.items():
            t0 = time.perf_counter()
            wp.capture_launch(graph)
            times[name].append((time.perf_counter() - t0) / repeat)
    return {name: (min(t), statistics.median(t)) for name, t in times.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--repeat", type=int, default=3, help="launches per timed graph")
    parser.add_argument("--samples", type=int, default=61, help="replays of each graph (their minimum is reported)")
    parser.add_argument("--out", help="also write the Markdown table to this file")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    lines = [
        f"CPU kernels' indexing costs; Warp {wp.__version__}; {os.cpu_count()} cores; "
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; minimum (and median) over "
        f"{args.samples} replays of a graph of {args.repeat} launches.",
        f"Command: `python bench/cpu_kernel_costs.py {' '.join(sys.argv[1:])}`",
        "",
        "| N | kernel | variant | µs per launch (min) | median | ns per element (min) |",
        "|---|---|---|---|---|---|",
    ]
    for n in args.sizes:
        ends = grid_springs(n)
        springs, particles = len(ends), n * n
        rng = np.random.default_rng(0)
        x = np.stack([np.repeat(np.arange(n), n) * 0.1, np.tile(np.arange(n), n) * 0.1, rng.random(particles) * 0.01], 1)
        q = wp.array(x.astype(np.float32), dtype=wp.vec3, device="cpu")
        qd = wp.array(rng.random((particles, 3)).astype(np.float32), dtype=wp.vec3, device="cpu")
        f, q_out, qd_out = (wp.zeros(particles, dtype=wp.vec3, device="cpu") for _ in range(3))
        e = wp.array(ends, dtype=wp.vec2i, device="cpu")
        rest = wp.full(springs, 0.1, dtype=float, device="cpu")
        ke, kd = wp.full(springs, 1.0e3, dtype=float, device="cpu"), wp.full(springs, 10.0, dtype=float, device="cpu")
        ke2, kd2 = ke.reshape((1, springs)), kd.reshape((1, springs))
        inv_mass2 = wp.full((1, particles), 10.0, dtype=float, device="cpu")
        inputs = wp.zeros((1, 15), dtype=float, device="cpu")
        packed = Springs()
        packed.ends, packed.rest, packed.ke, packed.kd = e, rest, ke2, kd2
        scatter = {
            "1-D launch, flat arrays (8543a2f)": (flat_1d, springs, [e, rest, ke, kd, q, qd, f]),
            "2-D launch (world, spring)": (launch_2d, (1, springs), [particles, e, rest, ke, kd, q, qd, f]),
            "2-D launch, per-world 2-D ke, kd": (launch_2d_rows_2d, (1, springs),
                                                 [particles, e, rest, ke2, kd2, q, qd, f]),
            "the same, arrays in a struct parameter": (struct_scatter(wp.kernel), (1, springs),
                                                       [particles, packed, q, qd, f]),
            "the same, struct flattened (flat_kernel)": (struct_scatter(flat_kernel), (1, springs),
                                                         [particles, packed, q, qd, f]),
            "1-D launch, per-world 2-D ke, kd": (flat_1d_rows_2d, springs, [e, rest, ke2, kd2, q, qd, f]),
            "1-D launch, world by division": (divided_1d, springs, [springs, particles, e, rest, ke, kd, q, qd, f]),
            "1-D, world 0 without division, per-world rows flat": (
                branched_1d_rows_flat, springs, [springs, particles, 1, e, rest, ke, kd, q, qd, f]),
        }
        per_particle = {
            "world by division (world_and_index in main)": (particle_kernel(world_divided), particles,
                                                           [particles, inv_mass2, inputs, q, qd, q_out, qd_out]),
            "world 0 without division (world_and_index now)": (particle_kernel(world_branched), particles,
                                                               [particles, inv_mass2, inputs, q, qd, q_out, qd_out]),
            "world 0 without division, per-world rows and inputs flat": (
                particle_rows_flat, particles, [particles, 1, inv_mass2.flatten(), inputs.flatten(), q, qd, q_out,
                                                qd_out]),
            "flat arrays, gravity by value (8543a2f)": (particle_flat, particles,
                                                        [wp.full(particles, 10.0, dtype=float, device="cpu"),
                                                         wp.vec3(0.0, 0.0, -9.81), q, qd, q_out, qd_out]),
        }
        a = wp.zeros(1, dtype=float, device="cpu")
        launches = {"one thread, 1 array": (touch, 1, [a])}
        for kernel, cases, count in (("spring scatter", scatter, springs), ("particle update", per_particle, particles),
                                     ("launch in a graph", launches, 1)):
            for name, (best, median) in timed(cases, args.repeat, args.samples).items():
                lines.append(f"| {n} | {kernel} | {name} | {best * 1e6:.2f} | {median * 1e6:.2f} | "
                             f"{best * 1e9 / count:.1f} |")
                print(lines[-1], flush=True)
    if args.out:
        with open(args.out, "w") as out:
            out.write("\n".join(lines) + "\n")
    print("\n".join(lines[:5]))


if __name__ == "__main__":
    main()
