"""The cost of a gradient over a long run: time per gradient relative to the forward run and peak memory, with
checkpointed recomputation (every k-th state kept, k = ⌈√steps⌉ by default) against one tape over the whole run, and
the run-to-run spread of repeated gradients.

Scene: the hanging cloth of ``analysis/grad_scenes.py`` (n × n, ClothMaterial, two pinned corners) in float64,
``--frames`` frames of 1/60 s at ``--substeps`` steps each, symplectic Euler; the loss is the squared distance of
every particle from its start at every frame's end. Each row runs in a fresh process, so its peak is its own: on
the CPU the peak of Warp's allocation tracker, on CUDA the growth of the memory pool's high-water mark. Times are
the best of ``--repeats``, ``wp.synchronize_device`` before each clock read, after the row's first gradient (which
compiles): the memory is measured by that first gradient (on CUDA the pool's high-water mark only rises).

Spread: ``--spread`` gradients of the driven cloth of ``grad_scenes`` (its 100 steps; every array of ``DiffRun.values``,
the pin-track keys included) repeated in one process, with Warp's default atomics and with ``deterministic=True``;
the spread of an array is max |g_r - g_1| / max |g_1| over the repeats r.

The results file is ``bench/results/gradients_<cpu|cuda>.md`` unless ``--out`` names another:

    python bench/gradients.py --device cpu
    python bench/gradients.py --device cuda:0 --sizes 8 32 128
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # this checkout's warpspring

import numpy as np  # noqa: E402

ROW = "--one"


def measure(device: str, n: int, frames: int, substeps: int, checkpoint: str, repeats: int) -> dict:
    """One row: forward and gradient times [s] and the peak device memory [B] of the gradient."""
    import warp as wp

    from warpspring.analysis.grad_scenes import SCENES, hanging_cloth
    from warpspring.core.adjoint import DiffRun, Target

    wp.config.quiet = True
    steps = frames * substeps
    model = hanging_cloth(SCENES["hanging_cloth"].values, device, n=n)
    every = None if checkpoint == "auto" else steps if checkpoint == "none" else int(checkpoint)
    run = DiffRun(model, dt=1.0 / 60.0 / substeps, steps=steps, checkpoint_every=every)
    q0 = model.particle_q.numpy().astype(np.float64)
    everyone = np.arange(model.particle_count)
    run.set_targets([Target(f * substeps, everyone, q0) for f in range(1, frames + 1)])

    def timed(call):
        best = np.inf
        for _ in range(repeats):
            wp.synchronize_device(device)
            start = time.perf_counter()
            value = call()
            wp.synchronize_device(device)
            best = min(best, time.perf_counter() - start)
        return best, value

    # Memory first: the row's first gradient from nothing of the run allocated (it compiles too: compiles take no
    # pool memory), so its peak holds all the run's arrays; on CUDA the pool's high-water mark only rises.
    wp.synchronize_device(device)
    if wp.get_device(device).is_cuda:
        before, high_before = wp.get_mempool_used_mem_current(device), wp.get_mempool_used_mem_high(device)
        run.gradient()
        wp.synchronize_device(device)
        high = wp.get_mempool_used_mem_high(device)
        peak = high - before
        how = "pool high-water mark" + ("" if high > high_before else " (not raised: an upper bound)")
    else:
        try:  # the allocation tracker's counters have no public getter
            from warp._src import context
        except ImportError:
            from warp import context
        with wp.ScopedMemoryTracker("bench", print=False):
            context.runtime.core.wp_alloc_tracker_reset()
            run.gradient()
            peak = context.runtime.core.wp_alloc_tracker_get_peak_bytes()
        how = "Warp allocation tracker peak"
    forward, loss = timed(run.loss)  # (compiled by the gradient above)
    gradient, (loss_g, _) = timed(run.gradient)
    state = model.particle_count * 2 * 3 * 8  # (q, v) of one world in float64 [B]
    return dict(n=n, particles=model.particle_count, steps=steps, k=run.checkpoint_every,
                stored=-(-steps // run.checkpoint_every), forward=forward, gradient=gradient, peak=int(peak), how=how,
                state=state, loss_match=bool(abs(loss_g[0] - loss[0]) <= 1e-12 * abs(loss[0])))


def spread(device: str, repeats: int) -> list[dict]:
    """The run-to-run spread of ``repeats`` gradients of the driven cloth, per array, without and with Warp's
    deterministic atomics."""
    import warp as wp

    from warpspring.analysis.grad_scenes import SCENES
    from warpspring.core.adjoint import DiffRun, Target

    wp.config.quiet = True
    scene = SCENES["driven_cloth"]
    model = scene.build(scene.values, device)
    q0 = model.particle_q.numpy().astype(np.float64)
    everyone = np.arange(model.particle_count)
    out = []
    for deterministic in (False, True):
        run = DiffRun(model, dt=scene.dt, steps=scene.steps, deterministic=deterministic)
        run.set_targets([Target(scene.steps // 2, everyone, q0), Target(scene.steps, everyone, q0 + 0.01)])
        grads = [run.gradient()[1] for _ in range(repeats)]
        for name in grads[0]:
            scale = np.abs(grads[0][name]).max()
            worst = max(np.abs(g[name] - grads[0][name]).max() for g in grads[1:])
            out.append(dict(deterministic=deterministic, array=name, spread=worst / scale if scale > 0.0 else None))
    return out


def spread_table(rows: list[dict], repeats: int, device: str) -> str:
    cpu = " (on the CPU a run is never built deterministic: its threads run in order anyway)" if device == "cpu" else ""
    lines = ["", f"## Run-to-run spread of {repeats} gradients", "", machine(device), "",
             "The driven cloth of `grad_scenes` (8 × 8, top row on a linear track, 100 steps of 1 ms, float64, symplectic "
             "Euler), its gradient repeated in one process; spread: max |g_r - g_1| / max |g_1| over the repeats; arrays "
             f"whose gradient is zero left out{cpu}.", "",
             "| array | spread (Warp's atomics) | spread (deterministic=True) |", "|---|---|---|"]
    for name in dict.fromkeys(r["array"] for r in rows):
        pair = {r["deterministic"]: r["spread"] for r in rows if r["array"] == name}
        if pair[False] is None:
            continue  # a gradient that is zero here (the contact's, without colliders)
        lines.append(f"| {name} | {pair[False]:.1e} | {pair[True]:.1e} |")
    worst = {d: max(r["spread"] for r in rows if r["deterministic"] == d and r["spread"] is not None)
             for d in (False, True)}
    lines += ["", f"Largest spread: {worst[False]:.1e} with Warp's atomics, {worst[True]:.1e} with deterministic=True."]
    return "\n".join(lines) + "\n"


def machine(device: str) -> str:
    """The device, the host, Warp's version and the date, as the results' tables state them."""
    import warp as wp

    name = device if device == "cpu" else f"{device} ({wp.get_device(device).name})"
    return (f"Device: {name} ({platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores); "
            f"Warp {wp.config.version}; {datetime.date.today().isoformat()}")


def table(rows: list[dict], device: str, command: str) -> str:
    lines = [
        "# Gradients over long runs: time and memory", "",
        f"Command: `{command}`  ",
        machine(device), "",
        "Hanging ClothMaterial cloth, float64, symplectic Euler; loss at every frame's end. k: checkpoint interval "
        "(steps); stored: checkpoints kept; gradient / forward: time of one loss-and-gradient over one forward run; "
        f"peak: the gradient's peak device memory ({rows[0]['how'] if rows else ''}); states: the peak over one "
        "state (q, v) of the cloth.", "",
        "| n | particles | steps | k | stored | forward [s] | gradient [s] | gradient / forward | peak [MiB] | "
        "peak / state |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['n']} | {r['particles']} | {r['steps']} | {r['k']} | {r['stored']} | {r['forward']:.3f} | "
                     f"{r['gradient']:.3f} | {r['gradient'] / r['forward']:.2f} | {r['peak'] / 2**20:.2f} | "
                     f"{r['peak'] / r['state']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 32])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--substeps", type=int, default=8)
    parser.add_argument("--checkpoints", nargs="+", default=["auto", "none"],
                        help="k per row: auto (⌈√steps⌉), none (one tape over the run) or an int; 'none' runs at the "
                             "smallest size only (its memory grows with the horizon)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--spread", type=int, default=5, help="gradients repeated to measure their spread (0: none)")
    parser.add_argument("--out", default=None,
                        help="markdown file to write (default: bench/results/gradients_cpu.md or gradients_cuda.md)")
    parser.add_argument(ROW, nargs=2, metavar=("N", "K"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        row = measure(args.device, int(args.one[0]), args.frames, args.substeps, args.one[1], args.repeats)
        print(json.dumps(row))
        return
    began = time.perf_counter()
    rows = []
    for n in args.sizes:
        for k in args.checkpoints:
            if k == "none" and n != min(args.sizes):
                continue
            done = subprocess.run([sys.executable, __file__, ROW, str(n), k, "--device", args.device, "--frames",
                                   str(args.frames), "--substeps", str(args.substeps), "--repeats", str(args.repeats)],
                                  capture_output=True, text=True)
            if done.returncode != 0:
                print(f"n={n} k={k}: failed: {done.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
                continue
            row = json.loads(done.stdout.strip().splitlines()[-1])
            print(f"n={n} k={row['k']}: forward {row['forward']:.3f} s, gradient {row['gradient']:.3f} s "
                  f"({row['gradient'] / row['forward']:.2f}x), peak {row['peak'] / 2**20:.2f} MiB", flush=True)
            rows.append(row)
    command = "python bench/gradients.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = table(rows, args.device, command)
    if args.spread > 1:
        text += spread_table(spread(args.device, args.spread), args.spread, args.device)
    text += f"\nThe whole benchmark took {time.perf_counter() - began:.0f} s (compiles included).\n"
    print(text)
    out = args.out or str(pathlib.Path(__file__).parent / "results" /
                          f"gradients_{'cpu' if args.device == 'cpu' else 'cuda'}.md")
    with open(out, "w") as f:
        f.write(text)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
