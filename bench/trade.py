"""Integrators: error against cost, measured. The same as ``warpspring trade`` (see ``warpspring.analysis.trade``).

Every registered integrator × step × precision on the seed spring (45 kg, 75 N), a stiff lightly
damped spring and the ANCHORS hanging cloth: wall time per simulated second (graph replays, device
synchronised, compilation excluded, median of repeats) and error against the closed form or a
float64 RK4 reference. Writes trade.csv, trade.md, pareto.png, convergence.png and seed.png to --out.

    python bench/trade.py --device cpu --quick          # about a minute
    python bench/trade.py --device cuda:0 --out trade   # the full study
"""

import sys

from warpspring.app.cli import main

if __name__ == "__main__":
    sys.exit(main(["trade", *sys.argv[1:]]))
