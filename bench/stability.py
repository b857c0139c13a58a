"""Stability map of every integrator. The same as ``warpspring stability`` (see ``warpspring.analysis.stability_map``).

Largest stable steps measured by simulation beside the theory of ``warpspring.analysis.stability`` (one damped
spring, ζ = 0 … 1), the advisor's prediction (the ANCHORS cloth over ke = 10⁻² … 10⁷ N/m) and the seed
observation (RK4 unstable for k > 22 on an assumed seed layout). Writes stability.md, spring.csv,
cloth.csv, seed.csv, spring.png and cloth.png to --out.

    python bench/stability.py --quick --out /tmp/stab_quick      # CI-sized, well under a minute on a CPU
    python bench/stability.py --device cuda:0 --out stability    # the full map
"""

import sys

from warpspring.app.cli import main

if __name__ == "__main__":
    sys.exit(main(["stability", *sys.argv[1:]]))
