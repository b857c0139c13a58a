"""The advisor against the exact linear limit of the loaded cloth, and how slowly a run past it grows.

For the battery's hanging and forced cloth (``warpspring/analysis/load_battery.py``, 20 × 20: the scenes with a
static equilibrium) and each explicit integrator at its two battery steps, linearised at the static equilibrium
of each stiffness (dense float64, ``warpspring/analysis/modal.py``):

* the stiffness where the top mode turns unstable (its exact ρ = 1);
* the largest stiffness the advisor passes linearised there (``advise(transient=False)``; ``--strict``
  also follows the release transient, which lowers it: the battery's table);
* the stiffnesses at which the top mode's energy grows ×10, ×10³ and ×10⁶ over a run of ``--seconds``
  (ρ^(2T/h)): where a guard can see a run blow up in that time, against the battery's measured blow-ups.

    python bench/advisor_linear.py --integrators midpoint explicit_euler --scenes hanging forced
"""

import argparse
import datetime
import math
import time

import warp as wp

from warpspring.analysis.load_battery import (EXPLICIT, FPS, STATIC_SCENES, STEPS, battery_cloth, battery_control,
                                              linear_limit, linearised)
from warpspring.analysis.modal import log_bisect
from warpspring.analysis.advisor import advise

from cloth import emit_table

GROWTHS = (10.0, 1.0e3, 1.0e6)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--integrators", nargs="+", default=list(EXPLICIT), choices=EXPLICIT)
    parser.add_argument("--scenes", nargs="+", default=["hanging"], choices=STATIC_SCENES)
    parser.add_argument("--seconds", type=float, default=10.0, help="the run whose growth is reported [s]")
    parser.add_argument("--rtol", type=float, default=1e-3, help="bisection tolerance on ke")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    cache = {}

    def modes(scene: str, ke: float):
        if (scene, ke) not in cache:
            cache[scene, ke] = linearised(scene, ke, device).modes()
        return cache[scene, ke]

    growths = " | ".join(f"×{g:.0e} over {args.seconds:g} s from" for g in GROWTHS)
    lines = [f"| scene | integrator | dt | top mode unstable from | advisor (at the equilibrium) passes up to | ratio | {growths} |",
             "|---|---|---|---|---|---|" + "---|" * len(GROWTHS)]
    cases = [(scene, name, substeps) for scene in args.scenes for name in args.integrators for substeps in STEPS[name]]
    for scene, name, substeps in cases:
        started = time.perf_counter()
        dt = 1.0 / (FPS * substeps)

        def rho(ke: float) -> float:
            return float(modes(scene, ke).growth(name, dt, top=1)[0])

        def advisor(ke: float) -> bool:
            model = battery_cloth(scene, [ke], device)
            return dt <= advise(model, name, dt, fps=FPS, control=battery_control(scene, model),
                                transient=False).dt_stable

        exact = linear_limit(scene, name, dt, device, rtol=args.rtol)
        passed = log_bisect(advisor, exact / 2.0, exact * 2.0, args.rtol)
        steps = 2.0 * args.seconds / dt  # energy: ρ² per step

        def below(ke: float, growth: float) -> bool:  # in logarithms: RK4's ρ^steps overflows
            return steps * math.log(rho(ke)) < math.log(growth)

        at = []
        for growth in GROWTHS:
            top = exact
            while below(top, growth):
                top *= 1.25
            at.append(log_bisect(lambda ke, g=growth: below(ke, g), exact, top, args.rtol))
        row = (f"| {scene} | {name} | 1/{FPS * substeps:g} s | {exact:.4g} N/m | {passed:.4g} N/m | {passed / exact:.4f} | "
               + " | ".join(f"{ke:.4g} N/m ({ke / exact:.2f}×)" for ke in at) + " |")
        print(row, f"({time.perf_counter() - started:.0f} s)", flush=True)
        lines.append(row)
    head = [f"The advisor against the linear system on {device.name}, Warp {wp.config.version}, {datetime.date.today()}: "
            "the battery's 20 × 20 cloth linearised at its static equilibrium, dense float64 modes", ""]
    emit_table(head + lines, args.out)


if __name__ == "__main__":
    main()
