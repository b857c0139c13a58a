"""The advisor on free, undamped and large-motion cloth: does ``--strict`` pass a step whose run blows up or grows
(its shadow energy's 1 s mean more than 1 % of the released energy above its start within 10 s), and is its step
within 10 % of the largest that does neither? Cloth, cases and protocol: ``warpspring/analysis/stability_battery.py``.
Writes a markdown table with the command, device, Warp version and date.

    python bench/advisor_battery.py --device cpu --sizes 8 16 --no-exact --out bench/results/advisor_battery_cpu.md
    # 64² on a GPU, ~3 min (undamped) and ~1 min (the lightly damped flat cloth, whose back-swing whip the dry run
    # must see: under_load.PROBE_PERIODS):
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 0 --factors 1.0 1.111 --substeps 20 --no-exact \
        --out bench/results/advisor_battery_64_h100.md
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 1e-5 --releases flat --gravity on \
        --factors 1.0 1.111 --substeps 20 --no-exact --out bench/results/advisor_battery_64_flat_damped_h100.md
    # 64², undamped, with the runs' own ω_max peaks (--trace 3), then lightly damped; one GPU command each:
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 0 --factors 1.0 1.05 1.111 --substeps 20 \
        --no-exact --trace 3 --out bench/results/advisor_battery_64_h100.md
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 1e-5 --factors 1.0 1.111 --substeps 20 \
        --no-exact --out bench/results/advisor_battery_64_damped_h100.md
    # the 64² folded cloth without gravity (it moves by itself: under_load.off_balance), where growth starts:
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 0 1e-5 --releases folded --gravity off \
        --integrators symplectic_euler velocity_verlet --factors 1.0 1.111 1.15 1.18 --substeps 20 --no-exact \
        --trace 3 --out bench/results/advisor_battery_64_nogravity_h100.md
    # the motion's upper band along each undamped case (what the three-wave triads past √3 draw on), and the step the
    # energy-weighted bound would pass (analysis/stability_triads.py):
    python bench/advisor_battery.py --device cpu --sizes 8 16 32 --taus 0 --bands
    # the largest step that neither blows up nor grows, bracketed by bisection, against the advisor's (~6 min at 64² on a
    # CPU, ~2 min at 8²-32²; on a GPU the 64² cases in two commands of ~3 and ~6 min):
    python bench/advisor_battery.py --device cpu --sizes 8 16 32 --taus 0 --bisect 5
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 0 --releases flat --bisect 5 --substeps 20 \
        --out bench/results/advisor_battery_64_bisect_flat_h100.md
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 0 --releases folded --bisect 5 --substeps 20 \
        --out bench/results/advisor_battery_64_bisect_folded_h100.md
    # the runs on a grid of steps 1 % apart, where holding past √3/ω_max is not monotone in the step (the motion is
    # chaotic): S, the largest sampled step at and below which every sampled step holds, against P (~7 min on a CPU at
    # 8²-32²; at 64² ~3-4 min per command on a CPU or a GPU, the host's energy sum dominating):
    python bench/advisor_battery.py --device cpu --sizes 8 16 32 --taus 0 --scan 0.9 1.2 0.01
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 0 --releases flat --scan 1.0 1.2 0.01 \
        --substeps 20 --out bench/results/advisor_battery_64_scan_flat_h100.md
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 0 --releases folded --gravity on \
        --scan 1.0 1.2 0.01 --substeps 20 --out bench/results/advisor_battery_64_scan_folded_h100.md
    python bench/advisor_battery.py --device cuda:0 --sizes 64 --taus 0 --releases folded --gravity off \
        --scan 1.0 1.2 0.01 --substeps 20 --out bench/results/advisor_battery_64_scan_nogravity_h100.md
    # the 64² folded cloth under gravity alone on a CPU (~10 min):
    python bench/advisor_battery.py --device cpu --sizes 64 --taus 0 --releases folded --gravity on \
        --factors 1.0 1.111 --substeps 20 --no-exact --trace 3

The 64² cloth has 24k springs: the host's float64 energy sum (~20 ms a frame on a CPU core) outweighs the GPU's
steps, so ``--substeps 20`` reads it every 20 steps (≥ 30 readings a second, enough for the 1 s mean).
"""

import argparse
import datetime
import math
import os
import pathlib
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # this checkout's warpspring

from warpspring.analysis import stability_battery as sb  # noqa: E402
from warpspring.analysis import stability_triads as st  # noqa: E402
from warpspring.analysis import under_load  # noqa: E402
from warpspring.analysis.advisor import advise, shared_estimates  # noqa: E402
from warpspring.analysis.stability import DAMPED_MARGIN, TRIAD_MARGIN  # noqa: E402

from cloth import emit_table  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 16, 32, 64])
    parser.add_argument("--taus", type=float, nargs="+", default=[0.0, sb.LIGHT], help="kd/k ratios [s]")
    parser.add_argument("--releases", nargs="+", default=list(sb.RELEASES), choices=sb.RELEASES)
    parser.add_argument("--gravity", nargs="+", default=["on", "off"], choices=["on", "off"],
                        help="cases with gravity, without, or both (flat without gravity does not move)")
    parser.add_argument("--integrators", nargs="+", default=list(sb.CONSERVATIVE), choices=sb.CONSERVATIVE)
    parser.add_argument("--factors", type=float, nargs="+", default=list(sb.FACTORS))
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--substeps", type=int, default=sb.SUBSTEPS, help="steps between two energy readings")
    parser.add_argument("--no-exact", action="store_true",
                        help="skip the runs of the exact-limit case (16², kd = 1e-4 s·ke, explicit Euler and midpoint "
                             "at f · P: 0.1 ms steps, ~1e5 per run)")
    parser.add_argument("--trace", type=float, default=0.0,
                        help="also run each case at P for this long [s] and report the highest ω_max its states "
                             "reach (stability_battery.omega_trace, every 1/120 s) against the advisor's")
    parser.add_argument("--probe-budget", type=float, default=None,
                        help="the advisor's dry-run CPU-time budget [s] (under_load.PROBE_TIME_BUDGET, 10 s; the 64² "
                             "cloth's 2.8 s dry run takes ~6 s of it on a CPU; past the budget the advisor judges by "
                             "the Gershgorin bound)")
    parser.add_argument("--dry-runs", action="store_true",
                        help="only time the advisor's dry run (under_load.transient_peak to its end, no budget) of each "
                             "case: its CPU and wall seconds, peak ω_max and when")
    parser.add_argument("--bands", action="store_true",
                        help="only record each case's motion (velocity Verlet at --band-step for --seconds) and report its "
                             "upper band above the pumps of the triads at 1.02, 1.055 and 1.083 √3/ω_max, and the step the "
                             "energy-weighted bound passes (stability_triads.growth_step)")
    parser.add_argument("--band-step", type=float, default=4.0e-4, help="the recording's step [s] (ωh ≈ 0.5)")
    parser.add_argument("--bisect", type=int, default=0, metavar="HALVINGS",
                        help="only bracket, per case and integrator, the largest step that neither blows up nor grows "
                             "(stability_battery.largest_step: runs at P and at 1.3 P, then this many bisections) and "
                             "report P against it")
    parser.add_argument("--scan", type=float, nargs=3, default=None, metavar=("LO", "HI", "STEP"),
                        help="only run, per case and integrator, the steps LO, LO + STEP, ... HI × the advisor's P "
                             "(stability_battery.scan) and report each run and S, the largest sampled step at and "
                             "below which every sampled step holds, against P")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    if args.probe_budget is not None:
        under_load.PROBE_TIME_BUDGET = args.probe_budget
    t0 = time.perf_counter()
    results = []
    chosen = [c for c in sb.cases(args.sizes, args.taus)
              if c.release in args.releases and ("on" if c.gravity else "off") in args.gravity]
    if args.dry_runs:
        dry_runs(chosen, device, args)
        return
    if args.bands:
        bands(chosen, device, args)
        return
    if args.bisect:
        bisections(chosen, device, args)
        return
    if args.scan:
        scans(chosen, device, args)
        return
    for case in chosen:
        for integrator in args.integrators:
            results.append(sb.measure(case, integrator, device, seconds=args.seconds, factors=args.factors,
                                      substeps=args.substeps))
            print(sb.table(results[-1:])[2], f"({time.perf_counter() - t0:.0f} s)", flush=True)
    traces = []
    for res in results if args.trace > 0.0 else []:  # the run's own peak ω_max against the advisor's
        p = res.advice.dt_passed
        if p > 0.0:
            rows = sb.omega_trace(res.case, res.integrator, p, device, seconds=args.trace)
            top = int(rows[:, 1].argmax())
            traces.append(f"| {res.case.label} | {res.integrator} | {res.advice.omega_max:.5g} | {rows[top, 1]:.5g} "
                          f"at {rows[top, 0]:.3g} s | {rows[top, 1] * p:.4g} |")
            print(traces[-1], flush=True)
    if not args.no_exact:  # explicit Euler and midpoint on damped cloth: P keeps DAMPED_MARGIN below the limit
        for name in sb.DISSIPATIVE:
            results.append(sb.measure(sb.Case(16, sb.EXACT, "flat", True), name, device, seconds=args.seconds,
                                      factors=args.factors, substeps=args.substeps))
            print(sb.table(results[-1:])[2], flush=True)
    refusals = []
    for n in args.sizes:  # explicit Euler and midpoint on undamped cloth: refused, with the remedy named
        model = sb.battery_cloth(sb.Case(n, 0.0, "flat", True), device)
        for name in sb.DISSIPATIVE:
            advice = advise(model, name, 1.0e-4, horizon=args.seconds)
            named = "symplectic_euler" in advice.message and "velocity_verlet" in advice.message
            refusals.append(f"| {n}² flat, undamped | {name} | {'refused' if advice.dt_passed == 0 else 'PASSED'} | "
                            f"{'yes' if named else 'no'} |")
    at, below = sb.exact_limit(device)
    command, where = _provenance(device)
    asked = [r for r in results if r.integrator in sb.CONSERVATIVE]  # explicit Euler and midpoint: refusals, margins
    one_sided = all(r.one_sided() for r in asked)
    tight = sum(r.tight() for r in asked)
    lines = [
        f"Advisor battery on {where}: `python bench/advisor_battery.py {command}`; {args.seconds:g} s runs; "
        f"{time.perf_counter() - t0:.0f} s in all. Per run: \"ok\" or \"grows\" with the highest 1 s mean of the "
        f"shadow energy over its start and (in brackets) its highest value, in % of the released energy; "
        f"grows above {100 * sb.GROWTH:g} %.", "",
        "P: the step the theory passes; Q: the largest step `--strict` passes with its trial runs, up the ladder "
        "P · 1.05^k (stability_battery.strict_step); the runs at factors of Q.", "",
        f"Symplectic Euler, velocity Verlet and RK4: one-sided in every case: {'yes' if one_sided else 'NO'}; tight (a "
        f"run within 1/0.9 of Q fails) in {tight} of {len(asked)}. Explicit Euler and midpoint (the exact-limit case's "
        "rows, if run) are kept DAMPED_MARGIN below their limit, not judged on growth: their undamped transverse "
        "modes grow at any step (the advisor's note).", "",
        *sb.table(results), "",
        *([f"ω_max along each run at P (its first {args.trace:g} s, every 1/120 s) against the advisor's:", "",
           "| case | integrator | advisor's ω_max [rad/s] | the run's highest [rad/s] | its ω·P |", "|---|---|---|---|---|",
           *traces, ""] if traces else []),
        f"Explicit Euler and midpoint on undamped cloth ({where}):", "",
        "| case | integrator | verdict | names symplectic_euler and velocity_verlet |", "|---|---|---|---|",
        *refusals, "",
        f"Exact limit (16² flat, kd = {sb.EXACT:g} s·ke, explicit Euler, linear limit {at.dt_stable * 1e3:.4g} ms): "
        f"at dt = {sb.EXACT * 1e3:g} ms {'refused' if not at.stable else 'PASSED'}; at {DAMPED_MARGIN:g} of it "
        f"{'passed' if below.stable else 'refused'}.",
    ]
    emit_table(lines, args.out)


#: Windows [s] of the dry run's ω_max trace whose highest mean the dry-run table reports.
MEAN_WINDOWS = (0.25, 0.5, 1.0)


def _provenance(device) -> tuple[str, str]:
    """This run's arguments (paths inside the repository made relative) and its device, Warp version and date, for a
    results table's heading."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    command = " ".join(os.path.relpath(a, root) if os.path.isabs(a) and a.startswith(root) else a for a in sys.argv[1:])
    return command, f"{device.name} ({device}), Warp {wp.config.version}, {datetime.date.today()}"


def _highest_mean(times: np.ndarray, values: np.ndarray, window: float) -> float:
    """The highest mean of the piecewise-linear trace ``values`` at ``times`` [s] over any ``window`` [s] within it
    (the whole trace's mean where it is shorter), sampled every 1/960 s."""
    grid = np.arange(0.0, float(times[-1]), 1.0 / 960.0)
    trace = np.interp(grid, times, values)
    count = min(len(trace), max(1, int(round(window * 960.0))))
    sums = np.cumsum(np.concatenate([[0.0], trace]))
    return float(((sums[count:] - sums[:-count]) / count).max())


def dry_runs(chosen, device, args):
    """The advisor's dry run of each case timed (the run's CPU seconds, as its budget counts them, and wall seconds;
    the first of two, which compiles, is dropped), with its peak ω_max, when, its duration, its first swing's peak
    and the highest means of its ω_max over ``MEAN_WINDOWS`` (how long the peak is held)."""
    budget, under_load.PROBE_TIME_BUDGET = under_load.PROBE_TIME_BUDGET, float("inf")
    rows = []
    for case in chosen:
        model = sb.battery_cloth(case, device)
        for attempt in range(2):
            wp.synchronize_device(device)
            cpu, wall = time.process_time(), time.perf_counter()
            peak = under_load.transient_peak(model, horizon=args.seconds)
            wp.synchronize_device(device)
            cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        swing = peak.world_swing_omega_max[0] if peak.world_swing_omega_max is not None else peak.world_omega_max[0]
        means = " | ".join(f"{_highest_mean(peak.trace_times, peak.world_trace[:, 0], w):.2f}" for w in MEAN_WINDOWS)
        rows.append(f"| {case.label} | {peak.duration:.3g} | {cpu:.1f} | {wall:.1f} | {peak.world_omega_max[0]:.2f} | "
                    f"{peak.world_peak_time[0]:.3g} | {swing:.2f} | {means} |")
        print(rows[-1], flush=True)
    command, where = _provenance(device)
    emit_table([f"Advisor dry runs on {where}: `python bench/advisor_battery.py {command}` (budget "
                f"{budget:g} CPU seconds, lifted here; each the second of two):", "",
                "| case | dry run [s] | CPU [s] | wall [s] | peak ω_max [rad/s] | at [s] | first swing's peak [rad/s] | "
                + " | ".join(f"highest {w:g} s mean [rad/s]" for w in MEAN_WINDOWS) + " |",
                "|---|---|---|---|---|---|---|" + "---|" * len(MEAN_WINDOWS),
                *rows], args.out)


def _over(a: float, b: float) -> float:
    """a / b, infinite where b is 0 (no step held: a scan whose smallest step failed)."""
    return a / b if b else math.inf


def _advised(chosen, device, args, *, ladder: bool = False):
    """Each case's integrators with the advisor's verdict on them (one dry run a case) and the step it passes: P, or
    with ``ladder`` the largest step ``--strict`` passes with its trial runs, Q (:func:`~warpspring.analysis.
    stability_battery.strict_step`): (case, integrator, advice, P or Q), where it passes one."""
    for case in chosen:
        model = sb.battery_cloth(case, device)
        with shared_estimates():  # one dry run for the case's integrators
            advices = [advise(model, name, 1.0e-4, horizon=args.seconds) for name in args.integrators]
            steps = [sb.strict_step(model, name, advice, seconds=args.seconds)[0] if ladder else advice.dt_passed
                     for name, advice in zip(args.integrators, advices)]
        for integrator, advice, step in zip(args.integrators, advices, steps):
            if step > 0.0:
                yield case, integrator, advice, step


def bisections(chosen, device, args):
    """The largest step that neither blows up nor grows, bracketed by bisection for each case and integrator
    (:func:`~warpspring.analysis.stability_battery.largest_step`), against the advisor's P: P/S, whether the run at P
    holds (one-sided) and P is within 10 % of S, and S over the linear limit and (where P is the three-wave step's ``TRIAD_MARGIN``) over the three-wave
    step √3/ω_max. Each bracket as "a-b": S lies between the largest step that held and the smallest that failed."""
    rows = []
    t0 = time.perf_counter()
    for case, integrator, advice, p in _advised(chosen, device, args, ladder=True):
        found = sb.largest_step(case, integrator, device, p, halvings=args.bisect, seconds=args.seconds,
                                substeps=args.substeps)
        holds, fails = found.holds, found.fails
        one_sided = found.runs[0].ok  # the run at P itself
        within = "-" if not one_sided else "yes" if p >= 0.9 * fails else "no" if p < 0.9 * holds else "?"
        three = TRIAD_MARGIN / advice.dt_passed if "three-wave" in advice.passed_reason else math.nan
        runs = ", ".join(f"{r.factor:.4g} {'ok' if r.ok else 'blows up' if r.blown else 'grows'}"
                         for r in sorted(found.runs, key=lambda r: r.factor))
        rows.append(f"| {case.label} | {integrator} | {advice.dt_passed * 1e3:.4g} | {p * 1e3:.4g} | "
                    f"{advice.dt_stable * 1e3:.4g} | "
                    f"{holds * 1e3:.4g}-{fails * 1e3:.4g} | {_span(_over(p, fails), _over(p, holds))} | "
                    f"{'yes' if one_sided else 'NO'} | {within} | "
                    f"{_span(holds / advice.dt_stable, fails / advice.dt_stable)} | "
                    f"{_span(holds * three, fails * three)} | {runs} |")
        print(rows[-1], f"({time.perf_counter() - t0:.0f} s)", flush=True)
    command, where = _provenance(device)
    emit_table([f"The largest step that neither blows up nor grows (S, bracketed by bisection) on {where}: "
                f"`python bench/advisor_battery.py {command}`; {args.seconds:g} s runs; "
                f"{time.perf_counter() - t0:.0f} s in all. P: the step the theory passes; Q: the largest step "
                "`--strict` passes with its trial runs, up the ladder P · 1.05^k (stability_battery.strict_step); the "
                "bisection starts from Q; runs by their step over Q; S / three-wave: over √3/ω_max (ω_max of the first "
                "swing), where P is the three-wave verdict.", "",
                "| case | integrator | P [ms] | Q [ms] | linear [ms] | S [ms] | Q / S | one-sided | within 10 % | "
                "S / linear | S / three-wave | runs |", "|---|---|---|---|---|---|---|---|---|---|---|---|", *rows],
               args.out)


def scan_factors(low: float, high: float, step: float) -> list[float]:
    """The factors low, low + step, ... up to high (included where the steps meet it to 1e-6 of a step)."""
    count = int(math.floor((high - low) / step + 1e-6)) + 1
    return [round(low + i * step, 9) for i in range(count)]


def _verdict(r) -> str:
    """A run's verdict and why: "holds", "grows" or "blows up (its cause at t s)"."""
    return f"blows up ({r.cause} at {r.until:.3g} s)" if r.blown else "grows" if r.grows else "holds"


def scans(chosen, device, args):
    """Per case and integrator, the runs at ``--scan`` LO..HI × the advisor's P (:func:`~warpspring.analysis.
    stability_battery.scan`): a summary (S, the largest sampled step at and below which every sampled step holds; the
    first that fails; the largest that holds, past a failure or not; P against them) and a table of the runs."""
    factors = scan_factors(*args.scan)
    command, where = _provenance(device)
    summary, details = [], []
    t0 = time.perf_counter()
    for case, integrator, advice, p in _advised(chosen, device, args):
        rows = []

        def report(r):
            rows.append(f"| {r.factor:.4g} | {r.dt * 1e3:.4g} | {_verdict(r)} | "
                        + (f"{100 * r.excess:.3g} | {100 * r.peak:.3g} | {100 * r.raw_excess:.3g} |"
                           if not r.blown else "- | - | - |"))
            print(f"{case.label}, {integrator}:", rows[-1], f"({time.perf_counter() - t0:.0f} s)", flush=True)

        found = sb.scan(case, integrator, device, p, factors, seconds=args.seconds, substeps=args.substeps,
                        report=report)
        above = sum(r.ok for r in found.runs if r.dt > found.fails)
        three = TRIAD_MARGIN / advice.dt_passed if "three-wave" in advice.passed_reason else math.nan
        summary.append(f"| {case.label} | {integrator} | {p * 1e3:.4g} | {found.holds / p:.4g} | "
                       f"{found.fails / p:.4g} | {found.lucky / p:.4g} | {above} | "
                       f"{_bracket(_over(p, found.fails), _over(p, found.holds))} | {'yes' if found.one_sided() else 'NO'} | "
                       f"{found.within()} | {_over(p, found.lucky):.3f} | "
                       f"{_bracket(found.holds * three, found.fails * three)} |")
        reason = f" ({advice.passed_reason})" if advice.passed_reason else ""
        details += [f"{case.label}, {integrator}, P = {p * 1e3:.4g} ms{reason}; {where}:", "",
                    "| step / P | step [ms] | verdict | highest 1 s mean [% F] | highest [% F] | H's highest [% F] |",
                    "|---|---|---|---|---|---|", *rows, ""]
    emit_table([f"The runs on a grid of steps on {where}: `python bench/advisor_battery.py {command}`; "
                f"{args.seconds:g} s runs; {time.perf_counter() - t0:.0f} s in all. Steps × the advisor's P; S: the "
                "largest sampled step at and below which every sampled step holds (neither blows up nor grows); first "
                "failure: the smallest that does not; largest lucky: the largest that holds, past a failure or not; "
                "P / S: P over the bracket [S, first failure) of the largest step that holds; within 10 %: P ≥ 0.9 × "
                "the first failure (yes), P < 0.9 × S (no); P / lucky: against the largest lucky step; S / three-wave: "
                "[S, first failure) over √3/ω_max (ω_max of the first swing), where P is the three-wave verdict.", "",
                "| case | integrator | P [ms] | S / P | first failure / P | largest lucky / P | lucky steps past "
                "the first failure | P / S | one-sided | within 10 % | P / lucky | S / three-wave |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|", *summary, "",
                "Each run: its verdict and the shadow energy's highest 1 s mean and highest value over its start, and "
                "H's highest over its start, in % of the energy the release sets free (F); grows above "
                f"{100 * sb.GROWTH:g} % (1 s mean).", "", *details], args.out)


def _bracket(low: float, high: float) -> str:
    """:func:`_span`, written "≤ high" or "≥ low" where the other end is 0 or ∞ (no sampled step failed)."""
    if math.isinf(high) and math.isfinite(low):
        return f"≥ {low:.3f}"
    return f"≤ {high:.3f}" if low == 0.0 and math.isfinite(high) else _span(low, high)


def _span(low: float, high: float) -> str:
    """A bracket "low-high" (3 decimals; "-" where neither end is finite, e.g. no three-wave verdict)."""
    return f"{low:.3f}-{high:.3f}" if math.isfinite(low) or math.isfinite(high) else "-"


#: The triads' steps the band table reports, × √3/ω_max.
BAND_STEPS = (1.02, 1.055, 1.083)


def bands(chosen, device, args):
    """Each case's motion recorded (:func:`~warpspring.analysis.stability_triads.record_motion`) and its upper band: the
    highest kinetic energy above the pump edge of the triads at ``BAND_STEPS`` × √3/ω_max (% of the motion's highest
    kinetic energy), when the band above 0.7 ω_max first holds 1 % of it, the coherent-pump bound's e-folds against
    the e-folds a visible growth needs, and the step the bound passes (× √3/ω_max)."""
    rows = []
    head = ("| case | ω_max [rad/s] | KE_max [J] | " +
            " | ".join(f"band at {r:g} √3 (ω > {math.sqrt(4.0 - 3.0 * r * r):.3g} ω_max) [% KE_max]" for r in BAND_STEPS)
            + " | band > 0.7 ω_max passes 1 % at [s] | bound's e-folds at " + ", ".join(f"{r:g}" for r in BAND_STEPS)
            + " √3 (needed) | bound passes [× √3/ω] | record [s] |")
    for case in chosen:
        model = sb.battery_cloth(case, device)
        t0 = time.perf_counter()
        record = st.record_motion(model, args.seconds, step=args.band_step)
        omega, top = float(record.omega.max()), float(record.kinetic.max())
        cells = []
        for r in BAND_STEPS:
            cut = math.sqrt(4.0 - 3.0 * r * r)
            column = int(np.searchsorted(np.asarray(st.CUTS), cut, side="right")) - 1
            cells.append(f"{100.0 * record.energy[:, column].max() / top:.3g}")
        seventy = st.CUTS.index(0.7)
        over = np.flatnonzero(record.energy[:, seventy] > st.GROWTH * top)
        passes = f"{record.times[over[0]]:.3g}" if over.size else "never"
        growth = [st.triad_growth(record, omega, r * math.sqrt(3.0) / omega, args.seconds) for r in BAND_STEPS]
        efolds = ", ".join(f"{g:.3g} ({n:.2g})" for g, n in growth)
        step = st.growth_step("symplectic_euler", omega, 2.0 / omega, record, args.seconds) * omega / math.sqrt(3.0)
        rows.append(f"| {case.label} | {omega:.5g} | {top:.4g} | " + " | ".join(cells) +
                    f" | {passes} | {efolds} | {step:.4g} | {time.perf_counter() - t0:.0f} |")
        print(rows[-1], flush=True)
    command, where = _provenance(device)
    emit_table([f"Upper bands on {where}: `python bench/advisor_battery.py {command}`; velocity Verlet at "
                f"{args.band_step * 1e3:g} ms for {args.seconds:g} s, sampled every {st.RECORD_EVERY:g} s:", "",
                head, "|" + "---|" * (8 + len(BAND_STEPS) - 1), *rows], args.out)


if __name__ == "__main__":
    main()
