"""USD streaming: file size and per-frame write time over long runs, for ``.usdc`` and ``.usda``.

What it measures (the claims of ``warpspring.io.usd_stream``): a run's file is as small as a re-export of the same
content (within 10 %), and writing a frame costs the same however many frames came before (the median of
the last 1,000 frames' write times within 1.2× the first 1,000's). It writes ``--frames`` frames of an
n × n cloth through :class:`~warpspring.UsdWriter` (points, normals, velocities every frame), then times
the packing into one file on close, re-exports the packed file with USD (``Usd.Stage.Export``: the same
content, written in one go) and compares the sizes.

The frames are synthetic, not simulated: frame k displaces every particle along a travelling wave (a
different value in every frame, so USD cannot share arrays between frames), which keeps the benchmark
about the writer and lets it run 10,000 frames on a CPU in a few minutes. The normals kernel runs on
``--device``.

    python bench/usd_stream.py --frames 10000 --size 64 --formats usdc --out bench/results
    python bench/usd_stream.py --frames 10000 --size 32 --formats usdc usda
"""

import argparse
import datetime
import os
import platform
import shutil
import statistics
import tempfile
import time

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.io.usd import UsdWriter


def cloth(n: int, device) -> ws.Model:
    """The hanging cloth of ``bench/cloth.py`` at n × n (1 m wide), its two top corners pinned."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=n, ny=n, spacing=1.0 / n, origin=(0.0, 0.0, 1.0), particle_mass=0.01,
                           pin=["top-left", "top-right"])
    return builder.finalize(device)


def stream(model: ws.Model, path: str, frames: int, fps: float = 60.0, accelerations: bool = True) -> dict:
    """Write ``frames`` synthetic frames to ``path`` (with ``accelerations``: each frame written again when the next
    comes, as shipped); the write time of each frame [s] and the close time."""
    q0 = model.particle_q.numpy().astype(np.float64)
    phase = q0[:, 0] * 7.0 + q0[:, 1] * 3.0
    state = model.state()
    times = np.empty(frames)
    base = resident = resident_bytes()
    dtype = np.float64 if model.precision == "float64" else np.float32
    writer = UsdWriter(path, model, fps=fps, accelerations=accelerations)
    for k in range(frames):
        t = k / fps
        wave = np.sin(phase + 2.0 * t)
        q = q0 + np.stack([0.01 * wave, 0.02 * np.cos(phase + 1.3 * t), -0.05 * (1.0 + wave)], 1)
        state.particle_q.assign(q.astype(dtype))
        state.particle_qd.assign(np.gradient(q, axis=0).astype(dtype))
        start = time.perf_counter()
        writer.write_frame(state)
        times[k] = time.perf_counter() - start
        if k % 100 == 0:
            resident = max(resident, resident_bytes())
    start = time.perf_counter()
    writer.close()
    return {"times": times, "close": time.perf_counter() - start, "resident": resident - base}


def resident_bytes() -> int:
    """The process's resident memory now [B] (Linux)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def reexport_size(path: str, folder: str) -> tuple[int, float]:
    """The size [B] of the same stage exported by USD in one go, and how long that took [s]."""
    from pxr import Usd

    target = os.path.join(folder, "reexport" + os.path.splitext(path)[1])
    start = time.perf_counter()
    Usd.Stage.Open(path).Export(target)
    seconds = time.perf_counter() - start
    size = os.path.getsize(target)
    os.remove(target)
    return size, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=10000)
    parser.add_argument("--size", type=int, default=64, help="cloth resolution n (n × n particles)")
    parser.add_argument("--formats", nargs="+", default=["usdc", "usda"], choices=["usdc", "usda"])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--window", type=int, default=1000, help="frames in the first and last median")
    parser.add_argument("--out", default=None, help="folder for a markdown table (printed in any case)")
    parser.add_argument("--scratch", default=None, help="folder for the files written (default: a temporary one)")
    parser.add_argument("--accelerations", choices=["on", "off", "both"], default="on",
                        help="write accelerations (on: as shipped; both: a row each, side by side)")
    args = parser.parse_args()

    wp.config.quiet = True
    device = wp.get_device(args.device)
    model = cloth(args.size, device)
    scratch = args.scratch or tempfile.mkdtemp(prefix="usd_stream_")
    rows = []
    modes = {"on": [True], "off": [False], "both": [True, False]}[args.accelerations]
    for fmt, accelerations in [(f, a) for f in args.formats for a in modes]:
        path = os.path.join(scratch, f"stream.{fmt}")
        result = stream(model, path, args.frames, accelerations=accelerations)
        times = result["times"]
        w = min(args.window, len(times) // 2)
        first, last = statistics.median(times[:w]), statistics.median(times[-w:])
        size = os.path.getsize(path)
        again, export_seconds = reexport_size(path, scratch)
        rows.append({
            "format": fmt, "accelerations": "yes" if accelerations else "no", "frames": args.frames, "first": first, "last": last, "ratio": last / first,
            "p99": float(np.percentile(times, 99)), "total": float(times.sum()), "close": result["close"],
            "size": size, "reexport": again, "size_ratio": size / again, "export": export_seconds,
            "resident": result["resident"],
        })
        os.remove(path)
        print(f"{fmt}, accelerations {'on' if accelerations else 'off'}: {args.frames} frames of {args.size}²: median write {first * 1e3:.2f} ms (first {w}) / "
              f"{last * 1e3:.2f} ms (last {w}) = {last / first:.2f}×; pack on close {result['close']:.1f} s; "
              f"{size / 1e6:.1f} MB vs re-export {again / 1e6:.1f} MB = {size / again:.3f}×; resident memory "
              f"grew ≤ {result['resident'] / 1e6:.0f} MB while writing", flush=True)
    if not args.scratch:
        shutil.rmtree(scratch, ignore_errors=True)

    lines = [
        f"`python bench/usd_stream.py --frames {args.frames} --size {args.size} --formats {' '.join(args.formats)} "
        f"--device {args.device} --accelerations {args.accelerations}` — {device.name if device.is_cuda else platform.processor() or 'CPU'}, "
        f"Warp {wp.__version__}, {datetime.date.today().isoformat()}; {args.size}² = {model.particle_count} "
        f"particles (points, normals, velocities per frame; accelerations where said)",
        "",
        f"| format | accelerations | frames | median write, first {w} [ms] | last {w} [ms] | last / first | p99 [ms] | "
        "pack on close [s] | file [MB] | re-export [MB] | file / re-export | memory growth while writing [MB] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| .{r['format']} | {r['accelerations']} | {r['frames']:,} | {r['first'] * 1e3:.2f} | {r['last'] * 1e3:.2f} | "
                     f"{r['ratio']:.2f} | {r['p99'] * 1e3:.1f} | {r['close']:.1f} | {r['size'] / 1e6:.1f} | "
                     f"{r['reexport'] / 1e6:.1f} | {r['size_ratio']:.3f} | {r['resident'] / 1e6:.0f} |")
    table = "\n".join(lines)
    print(table)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "usd_stream.md"), "w") as f:
            f.write(table + "\n")


if __name__ == "__main__":
    main()
