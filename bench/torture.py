"""The self-collision torture battery at full size (``warpspring/analysis/torture.py``): every scene under every
integrator, every substep audited in float64 (continuous crossings by Tight-Inclusion CCD, intersections and pairs
closer than τ/2 at each substep's end). Prints a table and writes it (command, device, Warp version, date) to
``--out``; exits 1 when any run crossed, intersected, came closer than τ/2 or stopped.

    python bench/torture.py --device cuda:0                       # the battery, full size
    python bench/torture.py --device cpu --scenes twist720 --integrators symplectic_euler
    python bench/torture.py --device cpu --size small --seconds 0.5  # a quick look
    python bench/torture.py --device cpu --size small --duration 0.4 --scenes twist720  # the suite's twist

    python bench/torture.py --device cuda:0 --size small --duration 0.4 --scenes twist720 twist1440 --jobs 6

The audit runs on the host after every frame (the substeps' positions are kept on the device, one copy per
substep); its wall time is reported apart from the run's. ``--jobs N`` runs N cases at once, each in a process of
its own (the audit is most of a case's time and uses one core): their wall times then share the host.
"""

from __future__ import annotations

import argparse
import datetime
import multiprocessing
import pathlib
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # this checkout's warpspring

import warp as wp  # noqa: E402

from warpspring.analysis.torture import HEADER, INTEGRATORS, SCENES, SIZES, run_case  # noqa: E402


def _case(scene: str, integrator: str, options: dict) -> tuple[list, bool]:
    """One case's table row and whether it ran clean (a process of its own under ``--jobs``)."""
    wp.config.log_level = wp.LOG_WARNING
    result = run_case(scene, integrator, **options)
    return result.row() + [f"{result.audit_wall:.0f}"], result.clean


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--integrators", nargs="+", default=list(INTEGRATORS), choices=list(INTEGRATORS))
    parser.add_argument("--size", default="full", choices=list(SIZES))
    parser.add_argument("--seconds", type=float, help="run each scene this long [s] (default: the whole scene)")
    parser.add_argument("--duration", type=float, default=None,
                        help="each scene's time scale as a share of the size's (0.4: the suite's twist, faster)")
    parser.add_argument("--substeps", type=int, default=None,
                        help="substeps per frame (default: each scene's, torture.scene_substeps)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="cases run at once, each in its own process (the host's audit is most of a case's time)")
    parser.add_argument("--out", default=None, help="results file (default: bench/results/torture_<device>.md)")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    frames = None if args.seconds is None else max(1, int(round(args.seconds * 60.0)))
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / f"torture_{device.alias.replace(':', '')}.md")
    out.parent.mkdir(parents=True, exist_ok=True)
    header = HEADER + ["audit [s]"]
    rows, clean = [], True
    started = time.perf_counter()

    def write() -> list:  # after every row: a long battery keeps what it measured
        lines = [
            f"# Self-collision torture battery ({args.size} size, {device})",
            "",
            f"Command: `python bench/torture.py {' '.join(sys.argv[1:] if argv is None else argv)}`  ",
            f"Device: {device} ({device.name}), Warp {wp.config.version}, {datetime.date.today().isoformat()}, "
            f"{time.perf_counter() - started:.0f} s in all.",
            "",
            "Every substep audited in float64: crossings (continuous, over the substep's straight path), intersections "
            "and pairs closer than τ/2 = 2.5 mm at its end, each summed over substeps; min d: the smallest distance "
            "at a substep's end; pins outran: pair-steps beyond the cap (a pinned side closing in on a free one that "
            "could not give way: `SelfContact.outrun()`).",
            "",
            "| " + " | ".join(header) + " |",
            "|" + "---|" * len(header),
            *("| " + " | ".join(map(str, row)) + " |" for row in rows),
            "",
        ]
        out.write_text("\n".join(lines))
        return lines

    cases = [(scene, integrator) for scene in args.scenes for integrator in args.integrators]
    options = dict(size=args.size, device=args.device, frames=frames, duration=args.duration, substeps=args.substeps)
    if args.jobs > 1:
        done = {}
        with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(_case, scene, integrator, options): (scene, integrator)
                       for scene, integrator in cases}
            for future in as_completed(futures):
                done[futures[future]] = row, ok = future.result()
                print(" | ".join(map(str, row)), flush=True)
        for case in cases:  # the table in the order asked
            row, ok = done[case]
            rows.append(row)
            clean &= ok
        write()
    for scene, integrator in cases if args.jobs <= 1 else []:
        row, ok = _case(scene, integrator, options)
        rows.append(row)
        clean &= ok
        print(" | ".join(map(str, rows[-1])), flush=True)
        write()
    print(f"wrote {out}")
    return 0 if clean else 1


if __name__ == "__main__":
    sys.exit(main())
