"""What the run-time guard costs per substep, and what counting the dampers' dissipation in its energy
balance adds (``GuardLimits(dissipation=...)``: one launch per damped family and one for drag after every
substep, ``kernels/guards.py``), and with ``--wind`` what counting the wind's work per substep adds (a gusting wind
across the cloth, ``add_aerodynamics``; the balance then evaluates the wind's force once more per substep, at its
midpoint state: ``guard_work_kernel``).

The scene is the soak's cloth (``bench/soak.py``: n × n particles of 0.1 kg 0.1 m apart, springs of 1 kN/m and
kd = 10 N·s/m in every family, drag 0.01 N·s/m) with its whole top row, not its two corners, swung by the track (two
corners cannot carry the weight of a cloth much larger than the soak's 32²: at 128² it tore and the guard stopped
it), symplectic Euler, 16 substeps per 1/60 s frame replayed as one captured graph. Each configuration is timed over
``--frames`` frames after ``--warmup`` frames (compiles, captures), ``wp.synchronize_device`` before every timer
read; the table gives µs per substep and the ratio to the run without a guard.

    python bench/guard_cost.py --device cpu --sizes 16 32
    python bench/guard_cost.py --device cuda:0 --sizes 32 128 512 --out guard_cost.md
    python bench/guard_cost.py --device cuda:0 --sizes 64 256 --wind
"""

import argparse
import datetime
import time

import numpy as np
import warp as wp

import warpspring as ws
from cloth import emit_table
from soak import handle_swing

SUBSTEPS = 16
CONFIGS = (("no guard", None), ("guard, balance without D", ws.GuardLimits(dissipation=False)),
           ("guard, balance with D (default)", ws.GuardLimits()))
WIND_CONFIGS = (("no guard", None), ("guard without the balance", ws.GuardLimits(energy_balance=0.0)),
                ("guard, balance without D", ws.GuardLimits(dissipation=False)),
                ("guard, balance with D (default)", ws.GuardLimits()))


def row_driven_cloth(device, n: int, *, wind: bool = False) -> ws.Model:
    """The soak's n × n cloth hung from its whole top row, which the soak's track swings; with ``wind``, in gusts
    across it (4 → 10 m/s and back every 2 s, drag 1.2, lift 1.0 on every triangle)."""
    builder = ws.ModelBuilder(drag=0.01)
    spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
    ids = builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, particle_mass=0.1, origin=(0.0, 0.0, 4.0),
                                 structural=spring, shear=spring, bend=spring,
                                 rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2))
    builder.add_pin_group(ids[-1, :], translation=handle_swing(), name="handle")
    if wind:
        builder.add_aerodynamics(wind=(0.0, 4.0, 0.0), drag=1.2, lift=1.0)
        builder.set_track("wind", ws.Track([0.0, 1.0, 2.0], [[0, 4, 0], [0, 10, 0], [0, 4, 0]], interpolation="smooth",
                                           extrapolation="cycle"))
    return builder.finalize(device)


def time_substep(device, n: int, guard, *, frames: int, warmup: int, wind: bool = False) -> float:
    """µs per substep of the row-driven n × n cloth under ``guard`` (``None``: no guard)."""
    model = row_driven_cloth(device, n, wind=wind)
    sim = ws.Simulator(model, fps=60, substeps=SUBSTEPS, guard=guard)
    for _ in range(warmup):
        sim.step_frame()
    wp.synchronize_device(device)
    started = time.perf_counter()
    for _ in range(frames):
        sim.step_frame()
    wp.synchronize_device(device)
    return (time.perf_counter() - started) / (frames * SUBSTEPS) * 1e6


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 128])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--wind", action="store_true", help="the cloth in gusting wind (the wind's work counted)")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    scene = "the soak's cloth in gusting wind" if args.wind else "the soak's cloth"
    lines = [f"Guard cost on {device.name}, Warp {wp.config.version}, {datetime.date.today()}: {scene}, "
             f"symplectic Euler, {SUBSTEPS} substeps per frame as one graph, {args.frames} frames timed", "",
             "| particles | configuration | µs per substep | × no guard |", "|---|---|---|---|"]
    for n in args.sizes:
        base = None
        for name, guard in WIND_CONFIGS if args.wind else CONFIGS:
            us = time_substep(device, n, guard, frames=args.frames, warmup=args.warmup, wind=args.wind)
            base = base or us
            lines.append(f"| {n * n} | {name} | {us:.1f} | {us / base:.2f} |")
            print(lines[-1], flush=True)
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
