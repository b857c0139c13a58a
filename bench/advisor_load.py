"""The stability advisor under load: where a cloth really blows up, against the largest stiffness the
advisor (``warpspring stability``, ``--strict``) passes, for every explicit integrator at two steps, on a
hanging, a forced and a handle-driven cloth. Scenes and protocol: ``warpspring/analysis/load_battery.py``.

    python bench/advisor_load.py --device cpu --integrators rk4 --substeps 1 --scenes hanging
    python bench/advisor_load.py --device cuda:0                        # the whole battery
"""

import argparse
import datetime

import warp as wp

from warpspring.analysis.load_battery import EXPLICIT, SCENES, STEPS, run_case, table

from cloth import emit_table


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--integrators", nargs="+", default=list(EXPLICIT), choices=EXPLICIT)
    parser.add_argument("--substeps", type=int, nargs="+", default=None,
                        help="substeps per 1/60 s frame (default: two per integrator, load_battery.STEPS)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--worlds", type=int, default=32)
    parser.add_argument("--span", type=float, default=4.0, help="the first grid spans guess/span .. guess·span^¼")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--linear", action="store_true",
                        help="also the exact linear limit at the equilibrium (hanging and forced; dense float64 on the "
                             "host) and, in every scene, the stiffness from which the top mode frozen at the states "
                             "of a run's second half grows on average (load_battery.frozen_growth)")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    cases = []
    for scene in args.scenes:
        for name in args.integrators:
            for substeps in args.substeps or STEPS[name]:
                cases.append(run_case(scene, name, substeps, device, worlds=args.worlds, span=args.span,
                                      seconds=args.seconds, linear=args.linear))
                print(table(cases[-1:])[2], f"({cases[-1].seconds:.0f} s)", flush=True)
    lines = [f"Advisor under load on {device.name}, Warp {wp.config.version}, {datetime.date.today()}: 20 × 20 cloth, "
             f"{args.worlds} stiffnesses per grid as worlds, two grids, {args.seconds:g} s runs", "", *table(cases)]
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
