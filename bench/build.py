"""Model-building time: warpspring's vectorised builder against Newton's per-particle builder calls.

Both build the ANCHORS cloth (N × N particles, structural + shear + bend springs, two pinned corners)
on the CPU device, so only host-side building and the upload of the arrays are timed (after a warm-up
build of each, so imports and kernel compilation stay out). Newton has no
bulk spring call; its cloth is built the way its API offers: ``add_particle`` per particle and
``add_spring`` per spring (its ``add_cloth_grid`` adds triangles and bending edges instead).

    python bench/build.py --sizes 256 512 1024 --newton-sizes 256 512
"""

from __future__ import annotations

import argparse
import datetime
import time

import numpy as np
import warp as wp

from cloth import KD, KE, MASS, SPACING, warpspring_model


def newton_build(n: int) -> float:
    import newton

    t0 = time.perf_counter()
    builder = newton.ModelBuilder()
    for r in range(n):
        for c in range(n):
            pinned = r == n - 1 and c in (0, n - 1)
            builder.add_particle((c * SPACING, 0.0, r * SPACING), (0.0, 0.0, 0.0), 0.0 if pinned else MASS)
    grid = np.arange(n * n).reshape(n, n)
    pairs = [
        (grid[:, :-1], grid[:, 1:]),
        (grid[:-1, :], grid[1:, :]),
        (grid[:-1, :-1], grid[1:, 1:]),
        (grid[:-1, 1:], grid[1:, :-1]),
        (grid[:, :-2], grid[:, 2:]),
        (grid[:-2, :], grid[2:, :]),
    ]
    for a, b in pairs:
        for i, j in zip(a.ravel().tolist(), b.ravel().tolist()):
            builder.add_spring(i, j, KE, KD, 0.0)
    builder.finalize(device="cpu")
    return time.perf_counter() - t0


def warpspring_build(n: int) -> tuple[float, int, int]:
    t0 = time.perf_counter()
    model = warpspring_model(n, "cpu")
    return time.perf_counter() - t0, model.particle_count, model.spring_count


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--newton-sizes", type=int, nargs="*", default=[256, 512])
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    print(f"Build time on the host (CPU device), Warp {wp.__version__}, {datetime.date.today().isoformat()}.\n")
    warpspring_build(8)  # first calls pay imports and kernel compilation; keep them out of the timings
    if args.newton_sizes:
        newton_build(8)
    print("| N | particles | springs | warpspring [s] | Newton [s] | ratio |")
    print("|---|---|---|---|---|---|")
    for n in args.sizes:
        ours, particles, springs = warpspring_build(n)
        theirs = newton_build(n) if n in args.newton_sizes else None
        ratio = f"{theirs / ours:.0f}×" if theirs else ""
        newton_cell = f"{theirs:.2f}" if theirs else "—"
        print(f"| {n} | {particles:,} | {springs:,} | {ours:.2f} | {newton_cell} | {ratio} |", flush=True)


if __name__ == "__main__":
    main()
