"""The self-collision torture battery at full size (``warpspring/analysis/torture.py``): every scene under every
integrator, every substep audited in float64 (continuous crossings by Tight-Inclusion CCD, intersections and pairs
closer than τ/2 at each substep's end). Prints a table and writes it (command, device, Warp version, date) to
``--out``; exits 1 when any run crossed, intersected, came closer than τ/2 or stopped.

    python bench/torture.py --device cuda:0                       # the battery, full size
    python bench/torture.py --device cpu --scenes twist720 --integrators symplectic_euler
    python bench/torture.py --device cpu --size small --seconds 0.5  # a quick look
    python bench/torture.py --device cpu --size small --duration 0.4 --scenes twist720  # the suite's twist

    python bench/torture.py --device cuda:0 --size small --duration 0.4 --scenes twist720 twist1440 --jobs 6
    python bench/torture.py --device cpu --size small --scenes ring --timing  # µs per substep, unaudited

The audit runs on the host after every frame (the substeps' positions are kept on the device, one copy per
substep); its wall time is reported apart from the run's. ``--jobs N`` runs N cases at once, each in a process of
its own (the audit is most of a case's time and uses one core): their wall times then share the host.
``--audit-workers N`` splits each frame's substeps between N processes (the same findings): a full-size case
whose serial audit outlasts a time limit fits in it.

``--timing`` times the cases instead, unaudited (the simulation's own cost: each case's first frame, which compiles
and captures, untimed; the device synchronised before each timer read), in µs per substep over the scene's other
frames (or ``--seconds``), with the self-collision's counters: run it in two checkouts to compare their cost.
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

from warpspring.analysis.torture import (  # noqa: E402
    FPS,
    GUARD,
    HEADER,
    INTEGRATORS,
    SCENES,
    SIZES,
    build_case,
    run_case,
    scene_substeps,
)
from warpspring.core.integrators import make_integrator  # noqa: E402
from warpspring.core.simulator import Simulator  # noqa: E402

TIMING_HEADER = ["scene", "integrator", "particles", "substeps/frame", "substeps timed", "µs/substep", "pairs pushed",
                 "capped", "cache rebuilds", "swept fallbacks"]


PROGRESS_FRAMES = 20  # a line of the audit's findings every this many frames


def _case(scene: str, integrator: str, options: dict) -> tuple[list, bool]:
    """One case's table row and whether it ran clean (a process of its own under ``--jobs``)."""
    wp.config.log_level = wp.LOG_WARNING

    def progress(frame: int, frames: int, audit) -> None:  # a case cut short by a time limit still says how far
        if frame % PROGRESS_FRAMES == 0:
            print(f"{scene} {integrator}: frame {frame}/{frames}, {audit.line()}", flush=True)

    result = run_case(scene, integrator, progress=progress, **options)
    return result.row() + [f"{result.audit_wall:.0f}"], result.clean


def _timed(scene: str, integrator: str, options: dict) -> tuple[list, bool]:
    """One case's timing row (``--timing``): the run unaudited, its first frame untimed."""
    wp.config.log_level = wp.LOG_WARNING
    model, seconds = build_case(scene, size=options["size"], device=options["device"], duration=options["duration"])
    frames = options["frames"] or int(round(seconds * FPS))
    substeps = options["substeps"] or scene_substeps(model)
    sim = Simulator(model, integrator=make_integrator(integrator, model), fps=FPS, substeps=substeps, guard=GUARD)
    sim.step_frame()  # compiles and captures
    wp.synchronize_device(model.device)
    start = time.perf_counter()
    for _ in range(frames - 1):
        sim.step_frame()
    sim.settle()
    wp.synchronize_device(model.device)
    wall = time.perf_counter() - start
    counts, cache = model.self_contact.counts(), model.self_contact.cache_counts()
    timed = (frames - 1) * substeps
    return [scene, integrator, model.particle_count, substeps, timed, f"{1e6 * wall / max(timed, 1):.0f}",
            int(counts["pairs"].sum()), int(counts["capped"].sum()), int(cache["rebuilds"].sum()),
            int(cache["fallbacks"].sum())], True


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
    parser.add_argument("--perturb", type=int, default=None, metavar="SEED",
                        help="start from positions moved by up to 1 µm (torture.PERTURBATION), seeded: another "
                             "valid run of a chaotic scene, as CUDA's unordered atomics give")
    parser.add_argument("--jobs", type=int, default=1,
                        help="cases run at once, each in its own process (the host's audit is most of a case's time)")
    parser.add_argument("--audit-workers", type=int, default=1, metavar="N",
                        help="processes auditing each case's frames (SubstepAudit's workers: the same findings, "
                             "sooner; with --jobs, N per case)")
    parser.add_argument("--timing", action="store_true",
                        help="time each case unaudited (µs per substep) instead of the audited battery")
    parser.add_argument("--out", default=None,
                        help="results file (default: bench/results/torture_<device>.md, torture_timing_<device>.md)")
    args = parser.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    frames = None if args.seconds is None else max(1, int(round(args.seconds * 60.0)))
    name = f"torture_{'timing_' if args.timing else ''}{device.alias.replace(':', '')}.md"
    out = pathlib.Path(args.out or pathlib.Path(__file__).parent / "results" / name)
    out.parent.mkdir(parents=True, exist_ok=True)
    header = TIMING_HEADER if args.timing else HEADER + ["audit [s]"]
    run_one = _timed if args.timing else _case
    rows, clean = [], True
    started = time.perf_counter()

    def write() -> list:  # after every row: a long battery keeps what it measured
        what = ("Each case unaudited, its first frame (compile, capture) untimed: wall time per substep over the "
                "others; the self-collision's counters over the whole run." if args.timing else
                "Every substep audited in float64: crossings (continuous, over the substep's straight path), "
                "intersections and pairs closer than τ/2 = 2.5 mm at its end, each summed over substeps; min d: the "
                "smallest distance at a substep's end; pins outran: pair-steps beyond the cap (a pinned side closing in "
                "on a free one that could not give way: `SelfContact.outrun()`).")
        lines = [
            f"# Self-collision torture battery ({args.size} size, {device}){' timing' if args.timing else ''}",
            "",
            f"Command: `python bench/torture.py {' '.join(sys.argv[1:] if argv is None else argv)}`  ",
            f"Device: {device} ({device.name}), Warp {wp.config.version}, {datetime.date.today().isoformat()}, "
            f"{time.perf_counter() - started:.0f} s in all.",
            "",
            what,
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
    if args.perturb is not None:
        options["perturb"] = args.perturb
    if args.audit_workers > 1 and not args.timing:
        options["audit_workers"] = args.audit_workers
    if args.jobs > 1:
        done = {}
        with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(run_one, scene, integrator, options): (scene, integrator)
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
        row, ok = run_one(scene, integrator, options)
        rows.append(row)
        clean &= ok
        print(" | ".join(map(str, rows[-1])), flush=True)
        write()
    print(f"wrote {out}")
    return 0 if clean else 1


if __name__ == "__main__":
    sys.exit(main())
