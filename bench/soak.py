"""Soak: 100,000 substeps of a driven cloth with the default guard and the run-time stability watch, to show
that memory stays constant and energy stays bounded over a long run.

The scene: the reference cloth of ``bench/cloth.py`` at 32 × 32 (0.1 m spacing, 0.1 kg particles,
structural + shear + bend springs of 1 kN/m and 10 N·s/m) hanging from its two top corners, which a handle
swings ±0.2 m sideways at 0.5 Hz (a pin-group track: energy goes in and out), light air drag, symplectic Euler with 16 substeps per 1/60 s frame, each
frame one captured graph. Sampled every ``--every`` frames: the process's resident memory (RSS), Python's
own allocations (tracemalloc), the device's memory in use (CUDA), and the guard's energy balance: kinetic +
elastic energy E, the loads' net work W, the energy the dampers and drag took out D, and the energy
created, E - (E_ref + W - D).

Verdict: the growth of each memory measure over the second half of the run (a leak per frame shows up
there; the first half holds compilation and the first captures), and the largest energy created relative
to the budget E_ref + W and to D (≈ 0 up to the integrator's energy error: the run neither gains energy nor
drifts).

    python bench/soak.py --device cuda:0 --out bench/results
    python bench/soak.py --device cpu --steps 20000
"""

import argparse
import datetime
import os
import time
import tracemalloc

import numpy as np
import warp as wp

import warpspring as ws

from cloth import emit_table

FPS, SUBSTEPS = 60, 16


def driven_cloth(device, *, n: int = 32) -> ws.Model:
    """The soak's n × n cloth (the module docstring); ``tests/test_soak.py`` runs a copy of it (``tests/helpers.py``)
    at 12 × 12."""
    builder = ws.ModelBuilder(drag=0.01)
    spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
    ids = builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, particle_mass=0.1, origin=(0.0, 0.0, 4.0),
                                 structural=spring, shear=spring, bend=spring,
                                 rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2))
    builder.add_pin_group([ids[-1, 0], ids[-1, -1]], translation=handle_swing(), name="handle")
    return builder.finalize(device)


def handle_swing() -> ws.Track:
    """The handle's track: ±0.2 m along x and back every 2 s, smooth, cycled [m]."""
    return ws.Track([0.0, 0.5, 1.0, 1.5, 2.0], [[0, 0, 0], [0.2, 0, 0], [0, 0, 0], [-0.2, 0, 0], [0, 0, 0]],
                    interpolation="smooth", extrapolation="cycle")


def resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def device_bytes(device) -> int:
    """Memory in use on a CUDA device [B] (total - free, as the driver sees it); 0 on the CPU."""
    if not device.is_cuda:
        return 0
    return int(device.total_memory - device.free_memory)


def soak(device, steps: int, every: int):
    model = driven_cloth(device)
    sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS)
    ws.StabilityWatch.attach(sim, every=10)
    frames = steps // SUBSTEPS
    tracemalloc.start()
    rows = []
    started = time.perf_counter()
    for frame in range(1, frames + 1):
        sim.step_frame()
        if frame % every == 0 or frame == frames:
            balance = sim.guard.energy_balance()
            budget = balance.reference[0] + balance.work[0]
            rows.append((frame * SUBSTEPS, resident_bytes(), tracemalloc.get_traced_memory()[0], device_bytes(device),
                         balance.energy[0], balance.work[0], balance.created[0], budget, balance.peak[0],
                         balance.dissipated[0]))
    wall = time.perf_counter() - started
    tracemalloc.stop()
    return np.array(rows, dtype=np.float64), wall


def plot(rows: np.ndarray, path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    step = rows[:, 0]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    top.plot(step, rows[:, 4], label="kinetic + elastic energy E")
    top.plot(step, rows[:, 7], label="budget E_ref + W (start + loads' net work)")
    top.plot(step, rows[:, 9], label="dissipated D (dampers and drag)")
    top.plot(step, rows[:, 6], label="energy created E - (E_ref + W - D)")
    top.set_ylabel("energy [J]")
    top.legend(fontsize=8)
    top.set_title(title, fontsize=9)
    for column, label in ((1, "resident (RSS)"), (2, "Python (tracemalloc)"), (3, "CUDA device in use")):
        if rows[:, column].any():
            bottom.plot(step, (rows[:, column] - rows[0, column]) / 2**20, label=label)
    bottom.set_ylabel("memory since the first sample [MiB]")
    bottom.set_xlabel("substep")
    bottom.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--steps", type=int, default=100_000, help="substeps to run (16 per frame)")
    parser.add_argument("--every", type=int, default=125, help="frames between samples")
    parser.add_argument("--out", default=None, help="folder for soak.md and soak.png")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    rows, wall = soak(device, args.steps, args.every)
    half = rows[rows[:, 0] >= rows[-1, 0] / 2]
    growth = {name: half[-1, c] - half[0, c] for name, c in (("RSS", 1), ("Python", 2), ("device", 3))}
    created = float(np.max(rows[:, 6] / np.maximum(rows[:, 8], 1e-30)))
    closure = float(np.max(np.abs(rows[:, 6]) / np.maximum(rows[:, 9], 1e-30)))
    title = (f"Soak on {device.name}, Warp {wp.config.version}, {datetime.date.today()}: {int(rows[-1, 0])} substeps "
             f"of a driven 32 × 32 cloth")
    lines = [
        title, "",
        "| substeps | wall [s] | RSS growth, 2nd half | Python growth, 2nd half | device growth, 2nd half | "
        "largest energy created / budget | largest \\|created\\| / D | largest E [J] | W at the end [J] | "
        "D at the end [J] |",
        "|---|---|---|---|---|---|---|---|---|---|",
        f"| {int(rows[-1, 0])} | {wall:.1f} | {growth['RSS'] / 1024:+.0f} KiB | {growth['Python'] / 1024:+.1f} KiB | "
        + (f"{growth['device'] / 1024:+.0f} KiB" if device.is_cuda else "—")
        + f" | {created:+.2e} | {closure:.2e} | {rows[:, 4].max():.4g} | {rows[-1, 5]:.4g} | {rows[-1, 9]:.4g} |",
    ]
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        plot(rows, os.path.join(args.out, "soak.png"), title)
    emit_table(lines, os.path.join(args.out, "soak.md") if args.out else None)


if __name__ == "__main__":
    main()
