"""The guard's battery (``warpspring/analysis/guard_battery.py``): every example scene, and each cloth example again
with wind, a PD handle and a moving collider added; every integrator at the step the advisor passes (0 stops), and
the fixed-step explicit integrators at twice the advisor's limit and with the stiffest spring made 100 times stiffer
mid-run (each stopped within 60 frames, before any non-finite value, by a message naming what the scene contains).
Prints a table and writes it (command, device, Warp version, date) to ``--out``; exits 1 when any case fails.

    python bench/guard_battery.py --device cpu --frames 60
    python bench/guard_battery.py --device cuda:0 --out bench/results/guard_battery_gpu.md
    python bench/guard_battery.py --device cpu --scenes hanging_cloth --integrators symplectic_euler rk4
"""

from __future__ import annotations

import argparse
import datetime
import pathlib
import sys

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # this checkout's warpspring

import warp as wp  # noqa: E402

from warpspring.analysis.guard_battery import CASES, HEADER, INTEGRATORS, VARIANTS, cases, run_case  # noqa: E402

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scenes", nargs="+", default=None, help="scene names (file stems; default: every example)")
    parser.add_argument("--integrators", nargs="+", default=list(INTEGRATORS), choices=list(INTEGRATORS))
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--frames", type=int, default=120, help="frames of an advisor-step run (at most the scene's)")
    parser.add_argument("--out", default=None, help="results file (default: bench/results/guard_battery_<device>.md)")
    parser.add_argument("--defer-verdict", action="store_true",
                        help="read each verdict a frame later, where the default guard's checks may span frames "
                             "(GuardLimits.check_frames): the simulator's default on both devices (the flag is kept for "
                             "the commands of earlier results, when the CPU's default read each verdict at once)")
    parser.add_argument("--no-watch", action="store_true",
                        help="run the simulator alone, without the stability watch warpspring run attaches (its frames "
                             "then not read one by one, so that the default guard's checks may span frames; as the "
                             "results files with checks spanning frames ran)")
    parser.add_argument("--sync-verdict", action="store_true",
                        help="judge and check every frame before the next (Simulator(defer_verdict=False))")
    parser.add_argument("--spring-evaluation", default="auto", choices=["auto", "gather", "scatter"],
                        help="the models' springs (gather on the CPU builds CUDA's default form)")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    out = pathlib.Path(args.out or f"bench/results/guard_battery_{'gpu' if device.is_cuda else 'cpu'}.md")
    command = "python bench/guard_battery.py " + " ".join(argv if argv is not None else sys.argv[1:])
    lines = [f"`{command}`", "",
             f"*Measured: {device.name}, Warp {wp.config.version}, {datetime.date.today().isoformat()}.*", "", HEADER]
    print("\n".join(lines), flush=True)
    failures = 0
    counts = {}
    for path, variant, integrator, case in cases(EXAMPLES, scenes=args.scenes, integrators=args.integrators,
                                                 kinds=args.cases, variant_names=args.variants):
        try:
            outcome = run_case(path, variant, integrator, case, device=device, frames=args.frames,
                               defer_verdict=False if args.sync_verdict else None,
                               spring_evaluation=args.spring_evaluation, watch=not args.no_watch)
            row, passed = outcome.row(), outcome.passed
        except Exception as exc:  # a case that cannot run is a failure of the battery, reported in its row
            row = f"| {path.stem} | {variant} | {integrator} | {case} | | error | FAIL | {type(exc).__name__}: " \
                  f"{str(exc)[:160]} | |"
            passed = False
        failures += not passed
        key = case
        counts[key] = (counts.get(key, (0, 0))[0] + passed, counts.get(key, (0, 0))[1] + 1)
        lines.append(row.replace("\n", " "))
        print(lines[-1], flush=True)
        out.write_text("\n".join(lines) + "\n")
    summary = "; ".join(f"{case}: {passed} of {total} passed" for case, (passed, total) in counts.items())
    lines += ["", f"**{summary}.**"]
    out.write_text("\n".join(lines) + "\n")
    print(lines[-1])
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
