"""Integrators: error against cost, measured (issue #3). A thin runner over ``warpspring.trade``.

Every registered integrator × step × precision on the seed spring (45 kg, 75 N), a stiff lightly
damped spring and the ANCHORS hanging cloth: wall time per simulated second (graph replays, device
synchronised, compilation excluded, median of repeats) and error against the closed form or a
float64 RK4 reference. Writes trade.csv, trade.md, pareto.png, convergence.png and seed.png to --out
and prints the Markdown report. Same as ``warpspring trade``.

    python bench/trade.py --device cpu --quick          # about a minute
    python bench/trade.py --device cuda:0 --out trade   # the full study
"""

from __future__ import annotations

import argparse

import warp as wp

from warpspring.trade import FULL, QUICK, run_study, to_markdown, write_report


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    parser.add_argument("--out", default="trade", help="output directory")
    parser.add_argument("--quick", action="store_true", help="the CI-sized plan")
    parser.add_argument("--integrators", nargs="+", help="measure only these integrators")
    args = parser.parse_args()

    wp.config.log_level = wp.LOG_WARNING
    study = run_study(args.device, plan=QUICK if args.quick else FULL, integrators=args.integrators, progress=True)
    paths = write_report(study, args.out)
    print(to_markdown(study))
    print("wrote " + ", ".join(paths))


if __name__ == "__main__":
    main()
