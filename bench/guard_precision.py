"""How much the guard's float32 per-particle power sums (``core/forces.PowerSums``) lose over a check's span.

The integrator's force pass adds each step's energy (the dampers' and drag's loss, the outside loads' work) to one
float32 entry per particle; a check takes the entries into float64 and clears them. A span of ``every`` substeps is
``every`` float32 additions per entry. The guard never changes the run (the guarded run is the unguarded one bit for
bit), so the same trajectory is counted with checks every 1 substep (each entry holds one step: the float64
reference, up to the single rounding of the step's own float32 term) and every 10, 100 and ``substeps`` (a whole
frame: the longest span there is, since the last substep of every frame is checked); each count checks every substep of
its first frame, so that the balance takes its reference at the same state in all. Per span: D and W over the run,
their difference from the one-substep count, and that difference against the balance's budget (the balance stops at
``ENERGY_BALANCE`` = 10 % of it).

The scene: the battery's 16 × 16 cloth hung from its top row, springs of 1 kN/m and 10 N·s/m, drag 0.05 N·s/m and its
triangles in a 3.2 m/s wind (``add_aerodynamics``), springs gathered (their dampers in the per-particle sums too), at ``--substeps`` per 1/60 s frame.

    PYTHONPATH=. python bench/guard_precision.py --device cpu --out bench/results/guard_precision_cpu.md
    PYTHONPATH=. python bench/guard_precision.py --device cuda:0 --size 64 --out bench/results/guard_precision_gpu.md
"""

from __future__ import annotations

import argparse
import datetime

import numpy as np
import warp as wp

import warpspring as ws

FPS = 60


def cloth(n: int, device) -> ws.Model:
    builder = ws.ModelBuilder(drag=0.05)
    spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(0.0, 0.0, 0.05 * n),
                           rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), particle_mass=0.1,
                           structural=spring, shear=spring, bend=spring, pin=["top"])
    builder.add_aerodynamics(wind=(3.0, 1.0, 0.0))
    return builder.finalize(device, spring_evaluation="gather")


def count(n: int, device, integrator: str, substeps: int, frames: int, every: int):
    model = cloth(n, device)
    sim = ws.Simulator(model, fps=FPS, substeps=substeps, integrator=ws.make_integrator(integrator, model),
                       guard=ws.GuardLimits(every=1))
    sim.step_frame()  # the reference taken at the first substep in every count, then the span under test
    sim.guard.limits = ws.GuardLimits(every=every)
    for _ in range(frames - 1):
        sim.step_frame()
    wp.synchronize_device(device)
    balance = sim.guard.energy_balance()
    return float(balance.dissipated[0]), float(balance.work[0]), float(balance.peak[0]), float(balance.created[0])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--size", type=int, default=16)
    parser.add_argument("--substeps", type=int, default=1000)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--integrators", nargs="+", default=["symplectic_euler", "rk4"])
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    device = wp.get_device(args.device)
    spans = [s for s in (1, 10, 100, args.substeps) if s <= args.substeps]
    lines = [f"`python bench/guard_precision.py --device {args.device} --size {args.size} --substeps {args.substeps} "
             f"--frames {args.frames}`", "",
             f"*Measured: {device.name}, Warp {wp.config.version}, {datetime.date.today().isoformat()}; "
             f"{args.size}² cloth, {args.substeps} substeps per frame, {args.frames} frames.*", "",
             "| integrator | span [substeps] | D [J] | W [J] | ΔD vs span 1 | ΔW vs span 1 | (ΔD, ΔW) / budget | "
             "created / budget |", "|---|---|---|---|---|---|---|---|"]
    for integrator in args.integrators:
        reference = None
        for every in spans:
            d, w, peak, created = count(args.size, device, integrator, args.substeps, args.frames, every)
            if reference is None:
                reference = (d, w)
            dd, dw = d - reference[0], w - reference[1]
            lines.append(f"| {integrator} | {every} | {d:.6g} | {w:.6g} | {dd / d:+.2e} | {dw / w:+.2e} | "
                         f"{dd / peak:+.1e}, {dw / peak:+.1e} | {created / peak:+.2e} |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        with open(args.out, "a") as out:
            out.write("\n" + text)


if __name__ == "__main__":
    main()
