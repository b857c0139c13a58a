"""Where the guard's time goes, robust to a loaded host: every kernel launch of uncaptured frames timed on its own,
the fastest launch of each kernel kept, times its launches per substep (``intrinsic``: it includes Warp's eager
launch overhead, ~15 µs a launch on the CPU, which a captured graph partly avoids). The scene is ``guard_cost.py``'s
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
from guard_cost import SUBSTEPS, hanging_cloth


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--integrator", default="symplectic_euler")
    parser.add_argument("--guard", choices=["off", "default"], default="default")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--evaluation", default="auto", choices=["auto", "gather", "scatter"],
                        help="the springs' evaluation (gather on the CPU runs the CUDA default's kernels)")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    model = hanging_cloth(args.size, device, evaluation=args.evaluation)
    sim = ws.Simulator(model, fps=60, substeps=SUBSTEPS, guard=ws.GuardLimits() if args.guard == "default" else None,
                       integrator=ws.make_integrator(args.integrator, model), use_graph=False)
    for _ in range(3):
        sim.step_frame()
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

    wp.launch = timed
    try:
        for _ in range(args.frames):
            sim.step_frame()
    finally:
        wp.launch = launch
    substeps = args.frames * SUBSTEPS
    print(f"{args.size}², {args.integrator}, springs {args.evaluation}, guard {args.guard}, {device.name}, "
          f"Warp {wp.config.version}: "
          f"{sum(count.values()) / substeps:.2f} launches per substep")
    print("| kernel | launches/substep | fastest launch [µs] |\n|---|---|---|")
    for key, seconds in sorted(fastest.items(), key=lambda kv: -kv[1] * count[kv[0]]):
        print(f"| {key.split('__locals__')[-1][:48]} | {count[key] / substeps:.2f} | {seconds * 1e6:.1f} |")
    intrinsic = sum(fastest[k] * count[k] for k in fastest) / substeps
    print(f"intrinsic: {intrinsic * 1e6:.1f} µs per substep")


if __name__ == "__main__":
    main()
