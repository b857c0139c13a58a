"""Sweeps: how many variants a minute, on Ray with 1 and 2 local workers, and batched as worlds or not.

Two measurements, each printing a Markdown table:

* ``--ray``: a sweep of ``--variants`` small variants (the ``--side``² hanging cloth of ANCHORS.md — 0.1 kg
  particles 0.1 m apart, ke = 1e3 N/m, kd = 10 N·s/m, two top corners pinned — 60 frames of 16 substeps,
  structural stiffness log-spaced over 1e2 … 1e4 N/m and drag on or off) through
  ``warpspring.analysis.sweep.run_sweep`` on a local Ray with 1, then 2 workers: variants per minute of
  the sweep (Ray's start-up apart), both with the sweep's batching (variants of one topology as worlds of
  one model, 16 a task) and with one variant per task. Needs ``pip install 'warpspring[cluster]'``.
* ``--worlds`` (no Ray: the lent GPU machines cannot carry Ray's wheel): N variants of a 32² cloth (the
  same cloth, 60 frames of 16 substeps, stiffness and gravity varied) run by the sweep's own task
  (``run_batch``) as one model of N worlds, against N single-variant tasks one after the other; the
  compile happens in a warm-up task first. The metrics are taken on the host from every frame (or every
  ``--metrics-every`` frames): a float64 pass over every particle that a GPU's batch can outrun.

    python bench/sweep.py --ray --variants 100
    python bench/sweep.py --worlds --device cuda:0 --variants 16 64 256
    python bench/sweep.py --worlds --device cuda:0 --variants 16 64 256 --metrics-every 60
"""

from __future__ import annotations

import argparse
import copy
import datetime
import os
import shutil
import sys
import tempfile
import time

import numpy as np
import warp as wp

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from warpspring.analysis.sweep import run_sweep  # noqa: E402
from warpspring.analysis.sweep_batch import Batch, RunSettings, run_batch  # noqa: E402
from warpspring.analysis.sweep_plan import DEFAULT_BATCH, SweepPlan, Variant, plan_sweep, variant_hash  # noqa: E402

FPS, SUBSTEPS = 60.0, 16


def cloth_scene(side: int, frames: int) -> dict:
    """The ANCHORS hanging cloth, ``side`` particles a side, as a scene file's tables."""
    spring = {"ke": 1.0e3, "kd": 10.0}
    return {
        "version": 2,
        "simulation": {"fps": FPS, "frames": frames, "substeps": SUBSTEPS},
        "world": {"gravity": [0.0, 0.0, -9.81], "drag": 0.0},
        "cloth": {"grid": {"nx": side, "ny": side, "spacing": 0.1}, "origin": [-0.05 * (side - 1)] * 2 + [1.0],
                  "particle_mass": 0.1, "pin": ["top-left", "top-right"], "structural": dict(spring),
                  "shear": dict(spring), "bend": dict(spring)},
    }


def ray_plan(variants: int, batch: int, side: int) -> SweepPlan:
    return plan_sweep({
        "scene": cloth_scene(side, 60),
        "sweep": {"batch": batch},
        "axes": {"cloth.structural.ke": {"log": [1.0e2, 1.0e4], "count": variants // 2},
                 "world.drag": [0.0, 0.01]},
    }, path="bench-sweep")


def measure_ray(variants: int, workers_list: list[int], device: str | None, side: int) -> list[str]:
    from warpspring.analysis.sweep_ray import RayEngine

    rows = ["| cloth | workers | batching | variants | Ray start-up [s] | sweep [s] | variants / min |",
            "|---|---|---|---|---|---|---|"]
    for workers in workers_list:
        started = time.perf_counter()
        engine = RayEngine(workers=workers)
        startup = time.perf_counter() - started
        try:
            for batch, label in ((DEFAULT_BATCH, f"worlds, {DEFAULT_BATCH} a task"), (1, "one variant a task")):
                plan = ray_plan(variants, batch, side)
                out = tempfile.mkdtemp(prefix="bench-sweep-")
                try:
                    result = run_sweep(plan, out, engine=engine, device=device)
                finally:
                    shutil.rmtree(out, ignore_errors=True)
                bad = sum(r.status != "ok" for r in result.rows)
                note = f" ({bad} not ok)" if bad else ""
                rows.append(f"| {side}² | {workers} | {label} | {len(plan.variants)}{note} | {startup:.1f} | "
                            f"{result.elapsed:.1f} | {60.0 * len(plan.variants) / result.elapsed:.0f} |")
                print(rows[-1], flush=True)
        finally:
            engine.close()
    return rows


def worlds_variants(count: int) -> tuple[list, str]:
    base = cloth_scene(32, 60)
    rng = np.random.default_rng(0)
    variants = []
    for i in range(count):
        scene = copy.deepcopy(base)
        scene["cloth"]["structural"]["ke"] = float(1.0e3 * rng.uniform(0.5, 2.0))
        scene["world"]["gravity"] = [0.0, 0.0, float(-rng.uniform(5.0, 15.0))]
        variants.append(Variant(index=i, params={}, scene=scene, key=variant_hash(scene)))
    return variants, "bench-sweep"


def measure_worlds(counts: list[int], device: str, metrics_every: int) -> list[str]:
    settings = RunSettings(device=device, metrics_every=metrics_every)
    warm, path = worlds_variants(2)
    run_batch(Batch(tuple(warm), path), settings)  # compile (and load) the kernels
    run_batch(Batch(tuple(warm[:1]), path), settings)
    rows = ["| variants | one model of N worlds [s] | one variant at a time [s] | variants / s (worlds) | "
            "variants / s (one at a time) | speed-up |", "|---|---|---|---|---|---|"]
    for count in counts:
        variants, path = worlds_variants(count)
        start = time.perf_counter()
        batched = run_batch(Batch(tuple(variants), path), settings)
        wp.synchronize_device(device)
        together = time.perf_counter() - start
        start = time.perf_counter()
        alone = [run_batch(Batch((v,), path), settings) for v in variants]
        wp.synchronize_device(device)
        apart = time.perf_counter() - start
        same = all(a.results[0].max_strain == b.max_strain for a, b in zip(alone, batched.results))
        rows.append(f"| {count} | {together:.2f} | {apart:.2f} | {count / together:.1f} | {count / apart:.1f} | "
                    f"{apart / together:.1f}×{'' if same else ' (metrics differ!)'} |")
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ray", action="store_true", help="variants per minute on a local Ray, 1 and 2 workers")
    parser.add_argument("--worlds", action="store_true", help="one model of N worlds against N runs (no Ray)")
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    parser.add_argument("--variants", type=int, nargs="+", default=None,
                        help="--ray: the sweep's size (default 100); --worlds: the N to measure (default 16 64 256)")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="--ray: worker counts (default 1 2)")
    parser.add_argument("--side", type=int, default=16, help="--ray: particles per side of the cloth (default 16)")
    parser.add_argument("--metrics-every", type=int, default=1,
                        help="--worlds: frames between the metrics' host samples (default 1: every frame)")
    args = parser.parse_args()
    if not (args.ray or args.worlds):
        parser.error("choose --ray or --worlds")
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    where = device.name if device.is_cuda else f"{os.cpu_count()} CPU cores"
    header = (f"`python bench/sweep.py {' '.join(sys.argv[1:])}` on {device.alias} ({where}), Warp {wp.__version__}, "
              f"{datetime.date.today()}")
    lines = [header, ""]
    if args.ray:
        lines += measure_ray((args.variants or [100])[0], args.workers, args.device, args.side)
    if args.worlds:
        lines += ([""] if args.ray else []) + measure_worlds(args.variants or [16, 64, 256], device.alias,
                                                             args.metrics_every)
    print("\n" + "\n".join(lines))


if __name__ == "__main__":
    main()
