"""Where the guard's time goes, robust to a loaded host: every kernel launch of uncaptured frames timed on its own,
the fastest launch of each kernel kept, times its launches per substep (``intrinsic``: it includes Warp's eager
launch overhead, ~15 µs a launch on the CPU, which a captured graph partly avoids; flat kernels' launches, replayed
on the CPU, included). The scene is ``guard_cost.py``'s
(ANCHORS cloth hung from its top row, 16 substeps per frame); run it once with the guard off and once with the
default ``GuardLimits()``, against any checkout (``PYTHONPATH``) to compare them.

    PYTHONPATH=. python bench/guard_kernels.py --device cpu --size 32 --integrator symplectic_euler --guard off
    PYTHONPATH=. python bench/guard_kernels.py --device cpu --size 32 --integrator symplectic_euler --guard default
"""

from __future__ import annotations

import argparse
import collections
import time

import warp as wp

import warpspring as ws
from warpspring.kernels import flatten
from guard_cost import SUBSTEPS, hanging_cloth

#: The guard configurations compared: off, as shipped, without D in the balance, without the balance.
GUARDS = {"off": None, "default": ws.GuardLimits(), "no-dissipation": ws.GuardLimits(dissipation=False),
          "no-balance": ws.GuardLimits(energy_balance=0.0)}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--integrator", default="symplectic_euler")
    parser.add_argument("--guard", choices=["off", "default", "no-dissipation", "no-balance"], default="default")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--gpu-timing", action="store_true",
                        help="CUDA: each kernel's time on the device (Warp's timing events), not the host's wall time")
    parser.add_argument("--resources", action="store_true",
                        help="CUDA: each launched kernel's registers, local (spilled) bytes and resident blocks per "
                             "multiprocessor at 256 threads a block (the driver's own figures)")
    parser.add_argument("--evaluation", default="auto", choices=["auto", "gather", "scatter"],
                        help="the springs' evaluation (gather on the CPU runs the CUDA default's kernels)")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    model = hanging_cloth(args.size, device, evaluation=args.evaluation)
    sim = ws.Simulator(model, fps=60, substeps=SUBSTEPS, guard=GUARDS[args.guard],
                       integrator=ws.make_integrator(args.integrator, model), use_graph=False)
    for _ in range(3):
        sim.step_frame()
    if args.gpu_timing:
        device_times(sim, args)
        if args.resources:
            resources(device)
        return
    fastest = collections.defaultdict(lambda: float("inf"))
    count = collections.Counter()
    launch = wp.launch

    def timed(kernel, *a, **k):
        wp.synchronize_device(device)
        started = time.perf_counter()
        result = launch(kernel, *a, **k)
        wp.synchronize_device(device)
        fastest[kernel.key] = min(fastest[kernel.key], time.perf_counter() - started)
        count[kernel.key] += 1
        return result

    flat = flatten._launch

    def timed_flat(kernel, *a, **k):  # a flat kernel's launch (replayed on the CPU: no ``wp.launch``)
        wp.launch = launch  # (its own ``wp.launch`` is not a second launch)
        try:
            wp.synchronize_device(device)
            started = time.perf_counter()
            result = flat(kernel, *a, **k)
            wp.synchronize_device(device)
        finally:
            wp.launch = timed
        fastest[kernel.key] = min(fastest[kernel.key], time.perf_counter() - started)
        count[kernel.key] += 1
        return result

    wp.launch, flatten._launch = timed, timed_flat
    try:
        for _ in range(args.frames):
            sim.step_frame()
    finally:
        wp.launch, flatten._launch = launch, flat
    substeps = args.frames * SUBSTEPS
    print(f"{args.size}², {args.integrator}, springs {args.evaluation}, guard {args.guard}, {device.name}, "
          f"Warp {wp.config.version}: "
          f"{sum(count.values()) / substeps:.2f} launches per substep")
    print("| kernel | launches/substep | fastest launch [µs] |\n|---|---|---|")
    for key, seconds in sorted(fastest.items(), key=lambda kv: -kv[1] * count[kv[0]]):
        print(f"| {key.split('__locals__')[-1][:48]} | {count[key] / substeps:.2f} | {seconds * 1e6:.1f} |")
    intrinsic = sum(fastest[k] * count[k] for k in fastest) / substeps
    print(f"intrinsic: {intrinsic * 1e6:.1f} µs per substep")


def device_times(sim, args) -> None:
    """Each kernel's total device time per substep over ``args.frames`` uncaptured frames (CUDA events around every
    launch: no host overhead in the figures)."""
    for _ in range(3):  # past the watched frames of a restart (``Guard.refresh``)
        sim.step_frame()
    wp.synchronize_device(sim.model.device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
    for _ in range(args.frames):
        sim.step_frame()
    results = wp.timing_end()
    total = collections.defaultdict(float)
    count = collections.Counter()
    for r in results:
        total[r.name] += r.elapsed  # milliseconds
        count[r.name] += 1
    substeps = args.frames * SUBSTEPS
    print(f"{args.size}², {args.integrator}, guard {args.guard}, {sim.model.device.name}, Warp {wp.config.version}, "
          "device time per substep (CUDA events):")
    print("| kernel | launches/substep | µs per substep |\n|---|---|---|")
    for name, ms in sorted(total.items(), key=lambda kv: -kv[1]):
        print(f"| {name.split('__locals__')[-1][:60]} | {count[name] / substeps:.2f} | {ms * 1e3 / substeps:.2f} |")
    print(f"sum: {sum(total.values()) * 1e3 / substeps:.2f} µs per substep")


def resources(device) -> None:
    """Registers per thread, local memory per thread (spills) and resident blocks of 256 threads per multiprocessor of
    every kernel launched so far on ``device`` (``cuFuncGetAttribute``, ``cuOccupancyMaxActiveBlocksPerMultiprocessor``
    through the driver library: what the compiler gave each kernel)."""
    import ctypes
    import gc

    from warp._src.context import ModuleExec

    cuda = ctypes.CDLL("libcuda.so.1")
    num_regs, local_bytes, static_shared = 4, 3, 1  # CUfunction_attribute
    print(f"{device.name}: kernel resources (256 threads a block)")
    print("| kernel | registers | local [B] | static shared [B] | blocks/SM | occupancy |\n|---|---|---|---|---|---|")
    max_threads = 2048  # resident threads per multiprocessor on the H100 and H200 (Warp's Device does not say)
    with wp.ScopedDevice(device):
        for module in [m for m in gc.get_objects() if isinstance(m, ModuleExec) and m.device == device]:
            for name, hooks in module.kernel_hooks.items():
                function = ctypes.c_void_p(hooks.forward)
                values = []
                for attribute in (num_regs, local_bytes, static_shared):
                    value = ctypes.c_int(0)
                    cuda.cuFuncGetAttribute(ctypes.byref(value), attribute, function)
                    values.append(value.value)
                blocks = ctypes.c_int(0)
                cuda.cuOccupancyMaxActiveBlocksPerMultiprocessor(ctypes.byref(blocks), function, 256,
                                                                 ctypes.c_size_t(hooks.forward_smem_bytes))
                print(f"| {name.split('__locals__')[-1][:60]} | {values[0]} | {values[1]} | {values[2]} | "
                      f"{blocks.value} | {blocks.value * 256 / max_threads:.0%} |")


if __name__ == "__main__":
    main()
