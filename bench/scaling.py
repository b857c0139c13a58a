"""Throughput against scene size: particle-substeps/s against particle count, warpspring and NVIDIA Newton.

Two families of scenes, both the hanging cloth of ``bench/cloth.py`` (ANCHORS: 0.1 m, 0.1 kg, structural +
shear + bend springs, two top corners pinned, symplectic Euler, 16 substeps per 1/60 s frame, one graph per
frame):

- **one world** of N × N particles, N in ``--sizes``;
- **W worlds** of the 32 × 32 cloth in one model (``finalize(worlds=W)``), W in ``--worlds``; Newton gets the W
  cloths as one flat set of particles and springs (its semi-implicit particle kernels do not tell worlds
  apart), so both engines step W · 1,024 particles per launch.

Each point is the median of ``--batches`` timed batches, the engines' batches taken in turn
(``cloth.measure_interleaved``: setup apart, device synchronised before every timer read). Newton is timed
up to ``--newton-max-particles`` (its Python-list builder takes seconds per million particles). The rows go
to a CSV whose first line names the machine, the Warp and Newton versions, the date, a ``wp.copy``
bandwidth measured in the same run and the gather's compulsory bytes per particle-substep at the largest N
(``traffic.py``); ``scaling_plot.py`` draws it (with ``--plot``, at once).

    python bench/scaling.py --device cuda:0 --out bench/results/scaling_h100.csv --plot bench/results/scaling_h100.png
    python bench/scaling.py --device cpu --sizes 16 32 64 --worlds 4 16 --seconds 1
"""

from __future__ import annotations

import argparse
import csv
import datetime
import platform
import tempfile

import warp as wp

from cloth import SUBSTEPS, NewtonRunner, WarpspringRunner, installed_newton, measure_interleaved, warpspring_model
from traffic import copy_bandwidth, gather_traffic, per_particle

SIDE = 32  # the side of each world's cloth in the many-worlds scenes
DEFAULTS = {
    "cuda": {"sizes": [32, 64, 128, 256, 512, 1024, 2048], "worlds": [4, 16, 64, 256, 1024, 4096]},
    "cpu": {"sizes": [16, 32, 64], "worlds": [4, 16]},
}
COLUMNS = ["engine", "scene", "side", "worlds", "particles", "setup_s", "substeps_per_s", "particle_substeps_per_s",
           "spread"]


def scenes(sizes: list[int], worlds: list[int]) -> list[tuple[str, int, int]]:
    """(scene, side, worlds) of every point: one world of N², then W worlds of 32²."""
    return [("one world", n, 1) for n in sizes] + [("worlds", SIDE, w) for w in worlds]


def machine(device) -> str:
    """The device's name, and the host CPU's model name on the CPU."""
    if device.is_cuda:
        return device.name
    try:
        with open("/proc/cpuinfo") as f:
            name = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        name = platform.processor() or platform.machine()
    return f"{name} (CPU)"


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    parser.add_argument("--sizes", type=int, nargs="+", help="N of the one-world N × N cloths")
    parser.add_argument("--worlds", type=int, nargs="+", help=f"W of the W × {SIDE}² scenes")
    parser.add_argument("--seconds", type=float, default=0.5, help="timed seconds per engine and point")
    parser.add_argument("--batches", type=int, default=5, help="timed batches per engine and point (median)")
    parser.add_argument("--no-newton", action="store_true", help="time warpspring alone")
    parser.add_argument("--newton-max-particles", type=int, default=1 << 20, help="time Newton up to this size")
    parser.add_argument("--out", default="scaling.csv", help="the CSV of the points")
    parser.add_argument("--plot", help="also draw the CSV into this PNG (scaling_plot.py)")
    args = parser.parse_args()

    wp.config.log_level = wp.LOG_WARNING
    wp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="warpspring-bench-")  # setup includes compilation
    device = wp.get_device(args.device)
    defaults = DEFAULTS["cuda" if device.is_cuda else "cpu"]
    newton_version = installed_newton(not args.no_newton)
    if args.plot:
        from warpspring.errors import ConfigError
        from warpspring.plotting import pyplot

        try:
            pyplot("scaling plots")  # know now, not after the measurements, whether matplotlib is there
        except ConfigError as error:
            print(f"{error}: writing the CSV only (draw it elsewhere with bench/scaling_plot.py)")
            args.plot = None

    copy = copy_bandwidth(device)
    largest = warpspring_model(max(args.sizes or defaults["sizes"]), device, "gather")
    gather_bytes = per_particle(gather_traffic(largest), largest)["compulsory"]
    del largest
    header = (
        f"# {machine(device)}; Warp {wp.__version__}"
        + (f"; Newton {newton_version}" if newton_version else "")
        + f"; {datetime.date.today().isoformat()}; wp.copy {copy / 1e9:.1f} GB/s"
        + f"; gather {gather_bytes:.0f} B/particle-substep"
    )
    print(header)
    rows = []
    for scene, side, worlds in scenes(args.sizes or defaults["sizes"], args.worlds or defaults["worlds"]):
        model = warpspring_model(side, device, worlds=worlds)
        particles = model.particle_count * worlds
        engines = {WarpspringRunner(model).name: lambda: WarpspringRunner(model)}
        if newton_version and particles <= args.newton_max_particles:
            engines[f"newton {newton_version}"] = lambda: NewtonRunner(model)
        for engine, r in measure_interleaved(engines, device, args.seconds, args.batches).items():
            rate = SUBSTEPS / r["frame_s"]
            rows.append({
                "engine": engine, "scene": scene, "side": side, "worlds": worlds, "particles": particles,
                "setup_s": f"{r['first_frame_s']:.3f}", "substeps_per_s": f"{rate:.1f}",
                "particle_substeps_per_s": f"{rate * particles:.4g}", "spread": f"{r['spread']:.3f}",
            })
            print(f"{engine:24s} {scene:9s} {worlds:5d} × {side}²: {particles:>10,} particles, "
                  f"{rate * particles / 1e9:7.3f} G particle-substeps/s (spread {r['spread']:.1%})", flush=True)

    with open(args.out, "w", newline="") as f:
        f.write(header + "\n")
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {args.out}")
    if args.plot:
        from scaling_plot import plot

        plot(args.out, args.plot)
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
