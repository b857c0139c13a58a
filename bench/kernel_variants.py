"""Launch-configuration study of the fused symplectic Euler kernel (the ANCHORS cloth, CUDA graph).

For each cloth size: substeps/s at several CUDA block sizes, without fast math (on by default), and
the same frame with the springs removed (the floor set by graph-node launch and the particle update alone).
The defaults in ``ModelBuilder.finalize`` (``_block_dim``) were chosen from this table.

    python bench/kernel_variants.py --device cuda:0 --sizes 64 128 512
"""

from __future__ import annotations

import argparse

import warp as wp

import warpspring as ws
from cloth import FPS, SUBSTEPS, WarpspringRunner, measure, warpspring_model
from warpspring.kernels.integrators import symplectic_euler_kernel


def rate(model, device, seconds) -> float:
    return SUBSTEPS / measure(lambda: WarpspringRunner(model), device, seconds)["frame_s"]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0")
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 512])
    parser.add_argument("--blocks", type=int, nargs="+", default=[32, 64, 128, 256])
    parser.add_argument("--seconds", type=float, default=0.5)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    print(f"{device.name}, Warp {wp.__version__}: substeps/s of the fused kernel ({SUBSTEPS} per 1/{FPS} s frame)\n")
    print("| N | default block | " + " | ".join(f"block {b}" for b in args.blocks) + " | no fast math (default block) | no springs |")
    print("|---|---|" + "---|" * len(args.blocks) + "---|---|")
    for n in args.sizes:
        model = warpspring_model(n, device, "gather")
        default = model.block_dim
        cells = []
        for block in args.blocks:
            model.block_dim = block
            cells.append(f"{rate(model, device, args.seconds):,.0f}")
        model.block_dim = default
        kernel = symplectic_euler_kernel(model.scalar, model.force_features(None), model.contact_features())
        kernel.module.options["fast_math"] = False  # the default is on (SPRING_KERNEL_OPTIONS)
        exact = rate(model, device, args.seconds)
        kernel.module.options["fast_math"] = True
        bare = ws.ModelBuilder()
        bare.add_particles(model.particle_q.numpy(), mass=0.1)
        floor = rate(bare.finalize(device), device, args.seconds)
        print(f"| {n} | {default} | " + " | ".join(cells) + f" | {exact:,.0f} | {floor:,.0f} |", flush=True)


if __name__ == "__main__":
    main()
