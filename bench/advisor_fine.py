"""One battery case on a fine grid of stiffnesses around its limit: per world, the advisor's verdict (as
``--strict`` takes it), whether the 10 s run blew up, and its top mode's growth frozen along the run
(``load_battery.frozen_growth``), per step and over the run. Where the battery's two grids (``advisor_load.py
--linear``) resolve a limit to a few per cent, this resolves it to the grid given.

    python bench/advisor_fine.py --device cuda:0 --scene driven --integrator explicit_euler --substeps 2000 \
        --low 1180 --high 1220
"""

import argparse
import datetime

import numpy as np
import warp as wp

from warpspring.analysis import load_battery as lb
from warpspring.analysis.advisor import advise

from cloth import emit_table


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scene", default="hanging", choices=lb.SCENES)
    parser.add_argument("--integrator", default="explicit_euler", choices=lb.EXPLICIT)
    parser.add_argument("--substeps", type=int, default=2000, help="per 1/60 s frame")
    parser.add_argument("--low", type=float, required=True, help="the grid's lowest stiffness [N/m]")
    parser.add_argument("--high", type=float, required=True, help="the grid's highest stiffness [N/m]")
    parser.add_argument("--worlds", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    ke = np.geomspace(args.low, args.high, args.worlds)
    dt = 1.0 / (lb.FPS * args.substeps)
    model = lb.battery_cloth(args.scene, ke, device)
    advice = advise(model, args.integrator, dt, fps=lb.FPS, control=lb.battery_control(args.scene, model),
                    horizon=args.seconds)
    outcome = lb.blow_ups(args.scene, args.integrator, args.substeps, ke, device, args.seconds, sample_every=6)
    growth = lb.frozen_growth(args.scene, args.integrator, dt, ke, outcome.samples)
    lines = [f"{args.scene}, {args.integrator} at 1/{lb.FPS * args.substeps:g} s on {device.name}, Warp "
             f"{wp.config.version}, {datetime.date.today()}: {args.worlds} worlds, one {args.seconds:g} s run", "",
             "| ke [N/m] | advisor's step / dt | passes | blew up | top mode's growth per step | over the run |",
             "|---|---|---|---|---|---|"]
    for k, limit, blown, g in zip(ke, advice.world_dt_stable, outcome.blown, growth):
        lines.append(f"| {k:.2f} | {limit / dt:.5f} | {'yes' if dt <= limit else 'no'} | {'yes' if blown else 'no'} "
                     f"| {g:.12f} | {g ** (args.seconds / dt):.4g} |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
