"""Gather cost for a wide degree distribution: a random 3-D Delaunay spring network.

The edges of a Delaunay tetrahedralisation of uniformly random points are springs (ke = 1e3 N/m,
kd = 1 N·s/m, 0.1 kg particles, mean spacing 0.1 m), the bottom 5 % of the block pinned, gravity on,
symplectic Euler at 16 substeps per 1/60 s frame, each frame one captured graph. A vertex of such a
network has ~15 springs on average and up to ~40 or more: the tetrahedral-like distribution soft bodies
have, unlike a cloth's uniform 12.

Timed, side by side in one run, the spring evaluations of the same model:

* ``hybrid``: the default incidence (``warpspring.core.families``): an ELL head of the width the cost
  model picks and a CSR tail for the particles beyond it;
* ``ELL``: the head as wide as the largest degree, no tail (what the gather was before the hybrid
  layout; above 32 springs it fell back to scatter);
* ``scatter``: one thread per spring with atomic adds (non-deterministic on a GPU; for reference).

Reported: particle-substeps/s (median of timed batches, device synchronised before every timer read) and
each variant's ratio to ``hybrid``.

    python bench/adjacency.py --device cuda:0
    python bench/adjacency.py --device cpu --sizes 4096 --seconds 2
"""

from __future__ import annotations

import argparse
import datetime

import numpy as np
import warp as wp

import warpspring as ws
from cloth import FPS, SUBSTEPS, emit_table, measure
from warpspring.core.families import build_incidence
from worlds import Batch

SIZES = {"cuda": [32_768, 262_144], "cpu": [4_096]}


def delaunay_springs(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``count`` uniformly random points in a cube of mean spacing 0.1 m and the unique edges of their
    Delaunay tetrahedralisation, shape [s, 2]."""
    from scipy.spatial import Delaunay

    side = 0.1 * count ** (1.0 / 3.0)
    points = np.random.default_rng(seed).uniform(0.0, side, size=(count, 3))
    tets = Delaunay(points).simplices
    pairs = tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
    return points, np.unique(np.sort(pairs, axis=1), axis=0)


def network_model(points: np.ndarray, springs: np.ndarray, device, evaluation: str, *, slots=None) -> ws.Model:
    builder = ws.ModelBuilder()
    low = points[:, 2] < 0.05 * points[:, 2].max()
    builder.add_particles(points + [0.0, 0.0, 1.0], mass=0.1, pinned=low)
    builder.add_springs(springs, stiffness=1.0e3, damping=1.0)
    model = builder.finalize(device, spring_evaluation=evaluation)
    if slots is not None:  # the same springs with another head width (an attribute change: a new struct)
        model.spring_incidence, model.spring_incidence_shape = build_incidence(
            springs, len(points), springs[:, ::-1], lambda particles: particles, device=model.device, slots=slots
        )
    return model


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    parser.add_argument("--sizes", type=int, nargs="+", help="particle counts")
    parser.add_argument("--seconds", type=float, default=1.0, help="timed seconds per variant and size")
    parser.add_argument("--out", help="also write the Markdown table to this file")
    args = parser.parse_args()

    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    sizes = args.sizes or SIZES["cuda" if device.is_cuda else "cpu"]
    lines = [
        f"Random 3-D Delaunay spring network, symplectic Euler, {SUBSTEPS} substeps per 1/{FPS} s frame, one graph "
        f"per frame. Device: {device.name} ({device.alias}); Warp {wp.__version__}; {datetime.date.today().isoformat()}.",
        "",
        "| particles | springs | degree mean / max | variant | head slots | tail entries | particle-substeps/s | vs hybrid |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for count in sizes:
        points, springs = delaunay_springs(count)
        degree = np.bincount(springs.ravel(), minlength=count)
        variants = {"hybrid": ("gather", None), "ELL": ("gather", int(degree.max())), "scatter": ("scatter", None)}
        rates = {}
        for name, (evaluation, slots) in variants.items():
            model = network_model(points, springs, device, evaluation, slots=slots)
            shape = model.spring_incidence_shape
            tail = int(np.maximum(degree - shape.head_slots, 0).sum())
            result = measure(lambda: Batch(model), device, args.seconds)
            rates[name] = SUBSTEPS * count / result["frame_s"]
            head, tail = (f"{shape.head_slots}", f"{tail:,}") if evaluation == "gather" else ("–", "–")
            lines.append(
                f"| {count:,} | {len(springs):,} | {degree.mean():.1f} / {degree.max()} | {name} | {head} | "
                f"{tail} | {rates[name] / 1e9:.3f} G | "
                f"{rates[name] / rates['hybrid']:.2f}× |"
            )
            print(lines[-1], flush=True)
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
