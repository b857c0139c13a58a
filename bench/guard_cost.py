"""What the run-time guard costs: the default ``Simulator`` (``GuardLimits()``, energy balance and dissipation on)
beside the same run with ``guard=None``, in one process, their timed batches interleaved (round k times every
configuration once, so that a load which comes and goes on a shared host falls on all of them alike), with
NVIDIA Newton's ``SolverSemiImplicit`` in the same run where it is importable (``cloth.NewtonRunner``).

The scene is ANCHORS.md's hanging cloth (N × N particles 0.1 m apart, 0.1 kg each, structural + shear + bend
springs of ke = 1 kN/m, kd = 10 N·s/m, gravity) hung from its whole top row (two corners cannot carry the heavy
cloth at N ≥ 128: its corner springs tear), 16 substeps per 1/60 s frame, one captured graph per frame; ``--worlds W``
runs W worlds of it in one model. Per size and integrator: substeps/s of each configuration (median of
``--batches`` batches, ``wp.synchronize_device`` before every timer read), the spread of its batches
((max - min) / median), the guard's ratio (median over rounds of guard-off time / default time: ≥ 0.91 on the GPU,
≥ 0.87 on the CPU is the target) and the default run against Newton's semi-implicit Euler at the same step (timed
again beside each integrator, in its rounds).

    python bench/guard_cost.py --device cpu --sizes 32 --batches 7
    python bench/guard_cost.py --device cuda:0 --sizes 64 256 1024 --worlds-sizes 4096 --batches 5 --seconds 0.5 \
        --sync-verdict
    python bench/guard_cost.py --device cuda:0 --sizes 32 64 256 --integrators symplectic_euler --where --no-newton

``--where`` also times the default run with its verdict read after each frame (``defer_verdict=False``), with no host
read at all (the verdict's read replaced by nothing: what the device's work costs alone), and with the check in its
own launches after a one-launch frame (``guards.CHECK_IN_FRAME`` off while it is captured): where a default frame's
time goes, in µs per frame above guard off. The default's check spans up to ``GuardLimits.check_frames`` frames in
this scene (springs and gravity, read a frame later and not frame by frame); ``--every-frame`` also times it with a
check every frame (``check_frames=1``).
"""

from __future__ import annotations

import argparse
import datetime
import gc
import statistics
import time

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.core import guards
from warpspring.core.guards import WATCH_FRAMES
from warpspring.kernels import flatten
from cloth import KD, KE, MASS, SPACING, NewtonRunner, emit_table, installed_newton, set_up

FPS, SUBSTEPS = 60, 16
INTEGRATORS = ("symplectic_euler", "rk4", "implicit_euler")
#: The stepper's settings timed beside the ones shipped, the default guard and guard off with each value K given:
#: (option, ``SymplecticEuler`` attribute, its tag in the labels, help). For the register bounds 0 stands for none.
STUDIES = (
    ("--min-blocks", "FRAME_MIN_BLOCKS", "",
     "the one-launch frame kernel's registers bounded so that K blocks of 256 threads fit a multiprocessor, each K "
     "(0: no bound, the compiler's choice): what its occupancy is worth"),
    ("--step-min-blocks", "STEP_MIN_BLOCKS", "step ",
     "symplectic Euler's per-substep fused step's registers bounded so that K blocks fit a multiprocessor, each K "
     "(0: no bound)"),
    ("--check-min-blocks", "CHECK_MIN_BLOCKS", "check ",
     "the register bound of the check's own launch after a one-launch frame, each K (0: the compiler's choice)"),
    ("--particles-per-lane", "ONE_LAUNCH_PARTICLES_PER_LANE", "particles a lane ",
     "each lane of a one-block-per-world frame taking K particles a substep, each K"),
)


def hanging_cloth(n: int, device, worlds: int = 1, evaluation: str = "auto") -> ws.Model:
    """ANCHORS.md's cloth hung from its top row (``worlds`` copies in one model; springs evaluated as
    ``finalize``'s ``spring_evaluation`` says)."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=KE, kd=KD)
    builder.add_cloth_grid(nx=n, ny=n, spacing=SPACING, origin=(0.0, 0.0, 0.5 * n * SPACING),
                           rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), particle_mass=MASS,
                           structural=spring, shear=spring, bend=spring, pin=["top"])
    return builder.finalize(device, worlds=worlds, spring_evaluation=evaluation)


class Run:
    """One ``Simulator`` of the cloth: ``guard`` ``None`` (off) or a ``GuardLimits``, its verdict read a frame later as
    shipped (``defer_verdict=None``: after the next frame is queued, on both devices); with ``probe`` (guard off) a small device array read
    after every frame, as the guard without deferral reads its status: what the host's wait for the frame costs alone
    (on a GPU the next frame's launch then waits for the host)."""

    def __init__(self, model: ws.Model, integrator: str, guard, probe: bool = False, defer_verdict: bool | None = None,
                 settings: dict | None = None):
        stepper = ws.make_integrator(integrator, model)
        # The stepper's settings other than shipped (``STUDIES``, ``--check-at-end``).
        for name, value in (settings or {}).items():
            setattr(stepper, name, value)
        self.sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=guard, defer_verdict=defer_verdict,
                                integrator=stepper)
        self.probe = wp.zeros((model.world_count, 7), dtype=wp.int32, device=model.device) if probe else None

    def frame(self):
        self.sim.step_frame()
        if self.probe is not None:
            self.probe.numpy()

    def settle(self):
        """The last frame's verdict (a batch's time includes it)."""
        self.sim.settle()


def unread(run: Run) -> Run:
    """``run`` with its guard's verdict never read (what the device's work costs alone: the guard still checks): read
    after each frame, by a ``reports`` that reads nothing (the deferred path's ``post`` and ``collect`` are not taken)."""
    run.sim.defer_verdict = False
    run.sim.guard.reports = lambda: []
    return run


def check_apart(make) -> Run:
    """The run ``make()`` gives, its frame captured with the guard's check in launches of its own after a one-launch
    frame (``guards.CHECK_IN_FRAME`` off during the capture: its first frame)."""
    saved = dict(guards.CHECK_IN_FRAME)
    guards.CHECK_IN_FRAME.update({True: False, False: False})
    try:
        run = make()
        run.frame()
    finally:
        guards.CHECK_IN_FRAME.update(saved)
    return run


def timed_batch(runner, device, batch: int) -> float:
    """Seconds per frame over ``batch`` frames, the last frame's verdict included (``Run.settle``), the device
    synchronised before each timer read."""
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(batch):
        runner.frame()
    getattr(runner, "settle", lambda: None)()
    wp.synchronize_device(device)
    return (time.perf_counter() - t0) / batch


def batch_size(runner, device, seconds: float) -> int:
    """Frames per batch, doubled until a batch takes ``seconds``."""
    batch = 1
    while timed_batch(runner, device, batch) * batch <= seconds and batch <= 1 << 16:
        batch *= 2
    return batch


def launches_per_substep(model: ws.Model, integrator: str, guard) -> float:
    """Kernel launches per substep of one uncaptured frame past the frames a guard watches from its start
    (``wp.launch`` and flat kernels' launches counted)."""
    sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=guard, integrator=ws.make_integrator(integrator, model),
                       use_graph=False)
    for _ in range(WATCH_FRAMES + 1):
        sim.step_frame()
    count = [0]
    launch, flat = wp.launch, flatten._launch

    def counted(*args, **kwargs):
        count[0] += 1
        return launch(*args, **kwargs)

    def counted_flat(*args, **kwargs):  # (replayed on the CPU: no ``wp.launch``; its own is not a second launch)
        count[0] += 1
        wp.launch = launch
        try:
            return flat(*args, **kwargs)
        finally:
            wp.launch = counted

    wp.launch, flatten._launch = counted, counted_flat
    try:
        sim.step_frame()
    finally:
        wp.launch, flatten._launch = launch, flat
    sim.settle()
    return count[0] / SUBSTEPS


def kernel_times(model: ws.Model, integrator: str, guard, frames: int = 4) -> dict:
    """Device time per frame [µs] of each kernel (and memset, copy) of ``frames`` uncaptured frames past the frames a
    guard watches from its start (CUDA activity timer), by name less the module hash."""
    import re

    sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=guard, integrator=ws.make_integrator(integrator, model),
                       use_graph=False)
    for _ in range(WATCH_FRAMES + 1):
        sim.step_frame()
    sim.settle()
    with wp.ScopedTimer("frames", cuda_filter=wp.TIMING_ALL, synchronize=True, print=False,
                        report_func=lambda *args: None) as timer:
        for _ in range(frames):
            sim.step_frame()
        sim.settle()
    times = {}
    for result in timer.timing_results:
        name = re.sub(r"_[0-9a-f]{8}$", "", result.name)
        calls, total = times.get(name, (0, 0.0))
        times[name] = (calls + 1, total + result.elapsed * 1e3)
    return {name: (calls / frames, total / frames) for name, (calls, total) in times.items()}


def measure(makers: dict, device, seconds: float, batches: int) -> dict:
    """Each configuration's batch times [s per frame], their batches taken in turn, after a round of them all that is
    not kept and with the objects made so far frozen out of Python's collector (each configuration first runs two
    spans of frames and settles, untimed: the first check of a frame left to a later check loads its kernels, which,
    inside the batches' sizing, once kept the default's batches at one frame each, settled each: 0.205 of guard off
    at 32² on an H200 where a plain loop gives 1.0). The default's host waits each frame
    for the verdict of the one before, so a pause of the host costs it device time that guard off, queued far ahead,
    hides: on an H200 the first size a process timed kept 10-35 % less of guard off than the same size timed after
    another (64² first 0.680, second 0.749-0.781; 32² first 0.503-0.658, second 0.789), and with this warm-up still
    0.680 at 32² first (bench/results/guard_cost.md)."""
    runners = {name: set_up(make, device)[0] for name, make in makers.items()}
    for runner in runners.values():  # past a span and its settle (the first check of a frame left unchecked loads
        timed_batch(runner, device, 2 * ws.GuardLimits().check_frames)  # its kernels), before the batches are sized
    sizes = {name: batch_size(runner, device, seconds / batches) for name, runner in runners.items()}
    for name, runner in runners.items():  # the round not kept
        timed_batch(runner, device, sizes[name])
    gc.collect()
    gc.freeze()
    times = {name: [] for name in runners}
    for _ in range(batches):
        for name, runner in runners.items():
            times[name].append(timed_batch(runner, device, sizes[name]))
    return times


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sizes", type=int, nargs="*", default=[32], help="single cloths of N × N")
    parser.add_argument("--worlds-sizes", type=int, nargs="*", default=[], help="W worlds of the 32² cloth")
    parser.add_argument("--integrators", nargs="+", default=list(INTEGRATORS))
    parser.add_argument("--seconds", type=float, default=2.0, help="timed seconds per configuration")
    parser.add_argument("--batches", type=int, default=7)
    parser.add_argument("--no-newton", action="store_true")
    parser.add_argument("--evaluation", default="auto", choices=["auto", "gather", "scatter"],
                        help="the springs' evaluation (auto: gather on CUDA, scatter on the CPU; gather on the CPU "
                             "runs the CUDA default's kernels)")
    parser.add_argument("--every-frame", action="store_true",
                        help="also the default guard with a check every frame (GuardLimits(check_frames=1)): what the "
                             "checks spanning frames save")
    parser.add_argument("--check-frames", type=int, nargs="*", default=[],
                        help="also the default guard with checks spanning at most K frames (GuardLimits(check_frames=K)), "
                             "each K: what the span's length is worth")
    parser.add_argument("--probe", action="store_true",
                        help="also guard off with a status-sized read after every frame (the host's wait alone)")
    parser.add_argument("--sync-verdict", action="store_true",
                        help="also the default guard with its verdict read after every frame (defer_verdict=False): "
                             "what reading it a frame later gives")
    parser.add_argument("--parts", action="store_true",
                        help="also the guard without counting dissipation (GuardLimits(dissipation=False)) and without "
                             "the energy balance (energy_balance=0): what the dissipation's sums and the check's "
                             "other parts cost, each as µs per substep above guard off")
    parser.add_argument("--where", action="store_true",
                        help="also the default guard read after each frame, not read at all, and with its check apart "
                             "from a one-launch frame: where a default frame's time goes")
    parser.add_argument("--check-at-end", action="store_true",
                        help="also the default with the check of a one-launch frame at the frame kernel's end rather "
                             "than in a launch of its own (SymplecticEuler.CHECK_LAUNCH_APART off)")
    for flag, name, _, text in STUDIES:
        parser.add_argument(flag, type=int, nargs="*", default=[],
                            help=f"also the default and guard off with {text} (SymplecticEuler.{name})")
    parser.add_argument("--kernels", action="store_true",
                        help="also list each kernel's device time per frame, guard off and default (CUDA, uncaptured)")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    newton_version = installed_newton(not args.no_newton)
    lines = [f"Guard cost on {device.name} ({device.alias}), Warp {wp.config.version}"
             + (f", Newton {newton_version}" if newton_version else "") + f", {datetime.date.today()}: ANCHORS cloth "
             f"hung from its top row, {SUBSTEPS} substeps per 1/{FPS} s frame as one graph, {args.batches} interleaved "
             f"batches, springs {args.evaluation}", "",
             "| scene | integrator | launches/substep (off → default) | guard off [substeps/s] | default [substeps/s] "
             "| spread off / default | default ÷ off | Newton [substeps/s] | default ÷ Newton |",
             "|---|---|---|---|---|---|---|---|---|"]
    notes = []
    # The stepper's settings timed beside the shipped ones (``STUDIES``).
    studies = tuple((name, tag, getattr(args, flag[2:].replace("-", "_"))) for flag, name, tag, _ in STUDIES)
    scenes = [(f"{n}²", n, 1) for n in args.sizes] + [(f"{w} × 32²", 32, w) for w in args.worlds_sizes]
    for label, n, worlds in scenes:
        for integrator in args.integrators:
            def cloth(n=n, worlds=worlds):
                return hanging_cloth(n, device, worlds, args.evaluation)

            makers = {"off": lambda: Run(cloth(), integrator, None),
                      "default": lambda: Run(cloth(), integrator, ws.GuardLimits())}
            if args.every_frame:
                makers["every frame"] = lambda: Run(cloth(), integrator, ws.GuardLimits(check_frames=1))
            for k in args.check_frames:
                makers[f"spans {k}"] = lambda k=k: Run(cloth(), integrator, ws.GuardLimits(check_frames=k))
            if args.probe:
                makers["probe"] = lambda: Run(cloth(), integrator, None, probe=True)
            if args.sync_verdict or args.where:
                makers["sync"] = lambda: Run(cloth(), integrator, ws.GuardLimits(), defer_verdict=False)
            if args.where:
                makers["no host read"] = lambda: unread(Run(cloth(), integrator, ws.GuardLimits()))
                makers["check apart"] = lambda: check_apart(lambda: Run(cloth(), integrator, ws.GuardLimits()))
            for name, tag, values in studies:
                for k in values:  # (a register bound's 0: the compiler's choice, no bound)
                    setting = {name: k or None}
                    makers[f"default {tag}{k}"] = lambda s=setting: Run(cloth(), integrator, ws.GuardLimits(),
                                                                        settings=s)
                    makers[f"off {tag}{k}"] = lambda s=setting: Run(cloth(), integrator, None, settings=s)
            if args.check_at_end:
                makers["check at end"] = lambda: Run(cloth(), integrator, ws.GuardLimits(),
                                                     settings={"CHECK_LAUNCH_APART": {True: False, False: False}})
            if args.parts:
                makers["no dissipation"] = lambda: Run(cloth(), integrator, ws.GuardLimits(dissipation=False))
                makers["no balance"] = lambda: Run(cloth(), integrator, ws.GuardLimits(energy_balance=0.0))
            # Newton's builder takes the worlds as one flat set of particles: single cloths only (the issue's table).
            # (the peer for every integrator: its semi-implicit Euler at the same step.)
            newton = newton_version and worlds == 1
            if newton:
                makers["newton"] = lambda: NewtonRunner(cloth())
            times = measure(makers, device, args.seconds, args.batches)
            rate = {name: SUBSTEPS / statistics.median(t) for name, t in times.items()}
            spread = {name: (max(t) - min(t)) / statistics.median(t) for name, t in times.items()}
            ratio = statistics.median(off / on for off, on in zip(times["off"], times["default"]))
            ratio_range = [off / on for off, on in zip(times["off"], times["default"])]
            launches = (f"{launches_per_substep(cloth(), integrator, None):.2f} → "
                        f"{launches_per_substep(cloth(), integrator, ws.GuardLimits()):.2f}")
            vs_newton = (f"{statistics.median(nt / on for nt, on in zip(times['newton'], times['default'])):.2f}×"
                         if newton else "")
            if args.every_frame:
                every = statistics.median(off / p for off, p in zip(times["off"], times["every frame"]))
                every_newton = (f", {statistics.median(nt / p for nt, p in zip(times['newton'], times['every frame'])):.2f}× "
                                "Newton" if newton else "")
                notes.append(f"- {label}, {integrator}: the default with a check every frame (check_frames=1) ÷ guard "
                             f"off = {every:.3f}{every_newton}")
                print(notes[-1], flush=True)
            if args.check_frames:
                spans = ", ".join(f"{k}: {statistics.median(off / p for off, p in zip(times['off'], times[f'spans {k}'])):.3f}"
                                  for k in args.check_frames)
                notes.append(f"- {label}, {integrator}: the default with checks spanning at most K frames ÷ guard off, "
                             f"K = {spans} (as shipped, {ws.GuardLimits().check_frames}: {ratio:.3f})")
                print(notes[-1], flush=True)
            if args.sync_verdict:
                sync = statistics.median(off / p for off, p in zip(times["off"], times["sync"]))
                notes.append(f"- {label}, {integrator}: default with its verdict read after every frame ÷ guard off = "
                             f"{sync:.3f}")
                print(notes[-1], flush=True)
            if args.parts:
                per_substep = {name: 1e6 * statistics.median(times[name]) / SUBSTEPS for name in
                               ("off", "no balance", "no dissipation", "default")}
                above = {name: per_substep[name] - per_substep["off"] for name in per_substep}
                notes.append(f"- {label}, {integrator}: µs per substep guard off {per_substep['off']:.2f}; above it, "
                             f"the guard without the balance {above['no balance']:.2f}, with the balance but no "
                             f"dissipation counted {above['no dissipation']:.2f}, the default "
                             f"{above['default']:.2f} (the dissipation's sums "
                             f"{above['default'] - above['no dissipation']:.2f})")
                print(notes[-1], flush=True)
            if args.check_at_end:
                frame = {name: 1e6 * statistics.median(times[name]) for name in ("off", "default", "check at end")}
                notes.append(f"- {label}, {integrator}: µs per frame guard off {frame['off']:.1f}, default (the check "
                             f"apart) {frame['default']:.1f} ({frame['off'] / frame['default']:.3f} of off), the check "
                             f"at the frame kernel's end {frame['check at end']:.1f} "
                             f"({frame['off'] / frame['check at end']:.3f})")
                print(notes[-1], flush=True)
            if args.where:
                frame = {name: 1e6 * statistics.median(times[name]) for name in
                         ("off", "default", "sync", "no host read", "check apart")}
                notes.append(f"- {label}, {integrator}: µs per frame guard off {frame['off']:.1f}, default "
                             f"{frame['default']:.1f} ({frame['off'] / frame['default']:.3f} of off), read after each frame "
                             f"{frame['sync']:.1f} ({frame['off'] / frame['sync']:.3f}), not read "
                             f"{frame['no host read']:.1f} ({frame['off'] / frame['no host read']:.3f}), the check apart "
                             f"{frame['check apart']:.1f} ({frame['off'] / frame['check apart']:.3f})")
                print(notes[-1], flush=True)
            if args.kernels and device.is_cuda:
                for name, guard in (("off", None), ("default", ws.GuardLimits())):
                    listed = kernel_times(cloth(), integrator, guard)
                    total = sum(t for _, t in listed.values())
                    notes.append(f"- {label}, {integrator}, guard {name}: device time per frame {total:.1f} µs (uncaptured): "
                                 + "; ".join(f"{kernel} ×{calls:g} {t:.1f}" for kernel, (calls, t) in
                                             sorted(listed.items(), key=lambda item: -item[1][1])))
                    print(notes[-1], flush=True)
            frame = {name: 1e6 * statistics.median(t) for name, t in times.items()}
            for name, tag, values in studies:
                if not values:
                    continue
                bounded = ", ".join(f"{name} = {k}: default {frame[f'default {tag}{k}']:.1f}, "
                                    f"off {frame[f'off {tag}{k}']:.1f}" for k in values)
                notes.append(f"- {label}, {integrator}: µs per frame, as shipped ({name} = "
                             f"{getattr(ws.SymplecticEuler, name)}): default {frame['default']:.1f}, off "
                             f"{frame['off']:.1f}; with {bounded}")
                print(notes[-1], flush=True)
            if args.probe:
                probe = statistics.median(off / p for off, p in zip(times["off"], times["probe"]))
                notes.append(f"- {label}, {integrator}: guard off with a read after every frame ÷ guard off = "
                             f"{probe:.3f}")
                print(notes[-1], flush=True)
            lines.append(f"| {label} | {integrator} | {launches} | {rate['off']:,.0f} | {rate['default']:,.0f} | "
                         f"{spread['off']:.0%} / {spread['default']:.0%} | {ratio:.3f} "
                         f"[{min(ratio_range):.2f}, {max(ratio_range):.2f}] | "
                         f"{rate['newton']:,.0f} | {vs_newton} |" if newton else
                         f"| {label} | {integrator} | {launches} | {rate['off']:,.0f} | {rate['default']:,.0f} | "
                         f"{spread['off']:.0%} / {spread['default']:.0%} | {ratio:.3f} "
                         f"[{min(ratio_range):.2f}, {max(ratio_range):.2f}] | | |")
            print(lines[-1], flush=True)
    emit_table(lines + ([""] + notes if notes else []), args.out)


if __name__ == "__main__":
    main()
