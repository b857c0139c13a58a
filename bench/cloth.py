"""Hanging-cloth throughput: warpspring and NVIDIA Newton side by side, in one process, on one device.

The reference scene of ANCHORS.md: N × N particles 0.1 m apart, 0.1 kg each, structural + shear + bend
springs (ke = 1e3 N/m, kd = 10 N·s/m), gravity, no contacts, symplectic Euler, 16 substeps per 1/60 s frame,
each frame captured as one graph (CUDA graph on GPUs, Warp's CPU graph on the CPU), hung from its whole top row
(``--pin corners``: ANCHORS.md's two top corners, which tear at N ≥ 128 and the default guard stops). The
warpspring rows are what a user gets, the default ``Simulator`` (its guard ``GuardLimits()`` on), beside the
engine with the guard off (``--guard``). Newton gets the very same particles and springs (copied from
warpspring's model), no particle self-contact, and its documented loop (clear_forces + SolverSemiImplicit.step).

Reported per engine and size: setup (solver creation, kernel compilation from an empty cache, graph
capture and the first frame) apart from the steady rate; substeps/s and particle-substeps/s (median of
timed batches, device synchronised before every timer read); the speed ratio; and the largest position
difference between the engines after 1 s simulated from the same start (both integrate the same
equations, so it measures float32 summation-order drift).

With ``--bytes``, a second table puts each gather row's rate beside the bytes its kernel moves per
particle-substep (``traffic.py``: from its data layout), the bandwidth that rate draws, a device copy's
bandwidth measured in the same run, and, on CUDA where ``ncu`` exists, Nsight Compute's DRAM bytes of one
launch of the kernel.

    python bench/cloth.py --device cuda:0                       # 64² … 512², with Newton if installed
    python bench/cloth.py --device cpu --sizes 32 64 --seconds 2
    python bench/cloth.py --device cpu --sizes 32 64 --batches 9 --interleave   # a host shared with other jobs
    python bench/cloth.py --device cuda:0 --sizes 256 1024 --evaluation gather --bytes
    python bench/cloth.py --device cuda:0 --sizes 64 256 1024 --interleave    # default guard, guard off, Newton
"""

from __future__ import annotations

import argparse
import datetime
import shlex
import statistics
import sys
import tempfile
import time

import numpy as np
import warp as wp

import warpspring as ws
from cloth_scene import FPS, KD, KE, MASS, SPACING, SUBSTEPS, WarpspringRunner, warpspring_model  # noqa: F401
from traffic import copy_bandwidth, gather_traffic, ncu_dram_bytes, per_particle

DEFAULT_SIZES = {"cuda": [64, 128, 256, 512], "cpu": [32, 64]}


#: ``--evaluation`` names of the gather's spring layouts (``Model.spring_layout``) beyond the default ("gather":
#: neighbours from the grid's rows and columns, each group's values once): (spring_evaluation, finalize options).
EVALUATIONS = {"gather-table": ("gather", {"spring_grid": False}),
               "gather-per-spring": ("gather", {"spring_groups": False})}


class NewtonRunner:
    name = "newton"

    def __init__(self, model: ws.Model):
        import newton

        # Every world's particles and springs, as one flat set: Newton's semi-implicit particle and spring
        # kernels do not tell worlds apart, so W cloths in one model are W copies side by side.
        worlds, n = model.world_count, model.particle_count
        q = model.particle_q.numpy()
        kinematic = np.concatenate([model.kinematic_mask(world=w) for w in range(worlds)])
        springs = (model.spring_indices.numpy()[None] + n * np.arange(worlds)[:, None, None]).reshape(-1, 2)
        # Gravity as a 3-vector: Newton 1.8 takes nothing else, 1.5 takes it too (its scalar form, along the up
        # axis, is deprecated there).
        builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, -9.81))
        builder.add_particles(
            pos=[tuple(p) for p in q],
            vel=[(0.0, 0.0, 0.0)] * len(q),
            mass=np.where(kinematic, 0.0, MASS).tolist(),  # Newton: zero mass = kinematic
        )
        # Bulk-extend the spring lists (Newton's add_spring is one Python call per spring).
        builder.spring_indices.extend(springs.ravel().tolist())
        builder.spring_rest_length.extend(np.tile(model.spring_rest_length.numpy(), worlds).tolist())
        builder.spring_stiffness.extend([KE] * len(springs))
        builder.spring_damping.extend([KD] * len(springs))
        builder.spring_control.extend([0.0] * len(springs))
        self.model = builder.finalize(device=model.device)
        self.model.particle_grid = None  # no particle self-contact, as in warpspring
        self.solver = newton.solvers.SolverSemiImplicit(self.model)
        self.state_0, self.state_1 = self.model.state(), self.model.state()
        self.control = self.model.control()
        self.dt = 1.0 / (FPS * SUBSTEPS)
        self.graph = None

    def simulate(self):
        for _ in range(SUBSTEPS):
            self.state_0.clear_forces()
            self.solver.step(self.state_0, self.state_1, self.control, None, self.dt)
            self.state_0, self.state_1 = self.state_1, self.state_0

    def frame(self):
        if self.graph is None:
            with wp.ScopedCapture(device=self.model.device) as capture:
                self.simulate()
            self.graph = capture.graph
        wp.capture_launch(self.graph)

    def positions(self) -> np.ndarray:
        return self.state_0.particle_q.numpy()


def installed_newton(wanted: bool) -> str | None:
    """Newton's version where it is wanted and installed (the peer timed beside warpspring), else None (said once)."""
    if not wanted:
        return None
    try:
        import newton
    except ImportError:
        print("newton is not installed: timing warpspring alone")
        return None
    return newton.__version__


def set_up(make_runner, device):
    """A runner and its setup time [s]: engine model + solver creation, kernel compilation, graph capture and the
    first frame."""
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    runner = make_runner()
    runner.frame()
    wp.synchronize_device(device)
    return runner, time.perf_counter() - t0


def timed_batch(runner, device, batch: int) -> float:
    """Seconds per frame over ``batch`` frames, device synchronised before each timer read."""
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(batch):
        runner.frame()
    wp.synchronize_device(device)
    return (time.perf_counter() - t0) / batch


def batch_size(runner, device, seconds: float) -> int:
    """Frames per batch, doubled until a batch takes ``seconds``."""
    batch = 1
    while timed_batch(runner, device, batch) * batch <= seconds and batch <= 1 << 16:
        batch *= 2
    return batch


def summary(first: float, times: list[float]) -> dict:
    frame_time = statistics.median(times)
    return {"first_frame_s": first, "frame_s": frame_time, "spread": (max(times) - min(times)) / frame_time,
            "times": times}


def measure(make_runner, device, seconds: float, batches: int = 5) -> dict:
    """Setup time (``set_up``) and the median steady frame time of ``batches`` timed batches."""
    runner, first = set_up(make_runner, device)
    batch = batch_size(runner, device, seconds / batches)
    return summary(first, [timed_batch(runner, device, batch) for _ in range(batches)])


def measure_interleaved(makers: dict, device, seconds: float, batches: int = 5) -> dict:
    """``measure`` for several engines at once, their timed batches taken in turn (round k times every engine
    once), so that a load which comes and goes on a shared machine falls on all of them alike: compare
    them through ``round_ratio``."""
    runners, firsts, sizes = {}, {}, {}
    for name, make_runner in makers.items():
        runners[name], firsts[name] = set_up(make_runner, device)
        sizes[name] = batch_size(runners[name], device, seconds / batches)
    times = {name: [] for name in makers}
    for _ in range(batches):
        for name, runner in runners.items():
            times[name].append(timed_batch(runner, device, sizes[name]))
    return {name: summary(firsts[name], times[name]) for name in makers}


def round_ratio(a: dict, b: dict) -> float:
    """Median over rounds of b's frame time over a's: a's speed relative to b's, from interleaved batches."""
    return statistics.median(tb / ta for ta, tb in zip(a["times"], b["times"]))


def emit_table(lines: list[str], out: str | None) -> None:
    """Print the Markdown table made of ``lines``, and write it to ``out`` when given."""
    table = "\n".join(lines)
    print()
    print(table)
    if out:
        with open(out, "w") as f:
            f.write(table + "\n")


def agreement(model: ws.Model, frames: int = FPS) -> float:
    """Largest position difference [m] between warpspring and Newton after ``frames`` frames from the same start."""
    finals = []
    for engine in (WarpspringRunner, NewtonRunner):
        runner = engine(model)
        for _ in range(frames):
            runner.frame()
        finals.append(runner.positions())
    return float(np.abs(finals[0] - finals[1]).max())


def size_rows(n: int, device, evaluations: list[str], guards: list[str], newton_version: str | None, *, pin: str,
              seconds: float, batches: int, interleave: bool, newton_max_particles: int | None = None,
              drift_frames: int = FPS):
    """The table rows of size ``n``: every evaluation of ``evaluations`` with every guard of ``guards`` ("default":
    the default Simulator, "off") and Newton where ``newton_version`` is given, timed (interleaved: batches in turn
    and ratios per round), the drift against Newton after ``drift_frames`` frames; returns (Markdown rows, results
    by engine name, warpspring models by engine name)."""
    drift, models, makers = {}, {}, {}
    for mode in evaluations:
        evaluation, options = EVALUATIONS.get(mode, (mode, {}))
        for guard in guards:
            model = warpspring_model(n, device, evaluation, pin=pin, **options)
            name = WarpspringRunner(model, guard == "default").name
            models[name] = model
            makers[name] = lambda model=model, guard=guard: WarpspringRunner(model, guard == "default")
    with_newton = newton_version and model.particle_count <= (newton_max_particles or model.particle_count)
    if with_newton:
        makers["newton"] = lambda: NewtonRunner(model)
    if interleave:
        results = measure_interleaved(makers, device, seconds, batches)
    else:
        results = {name: measure(make, device, seconds, batches) for name, make in makers.items()}
    if with_newton:
        drift = {name: agreement(model, drift_frames) for name, model in models.items()}
    rows = []
    for name, r in results.items():
        rate = SUBSTEPS / r["frame_s"]
        ratio = diff = against_off = ""
        off = name.replace("default guard)", "guard off)")
        if off != name and off in results:  # the default Simulator against the engine alone
            against_off = round_ratio(r, results[off]) if interleave else results[off]["frame_s"] / r["frame_s"]
            against_off = f"{against_off:.3f}"
        if name in drift:
            newton_r = results["newton"]
            ratio = round_ratio(r, newton_r) if interleave else newton_r["frame_s"] / r["frame_s"]
            ratio = f"{ratio:.2f}×"
            diff = f"{drift[name]:.1e}"
        rows.append(
            f"| {n} | {model.particle_count:,} | {model.spring_count:,} | {name} | {r['first_frame_s']:.2f} | "
            f"{rate:,.0f} | {rate * model.particle_count / 1e9:.3f} G | {r['spread']:.1%} | {against_off} | "
            f"{ratio} | {diff} |"
        )
    return rows, results, models


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    parser.add_argument("--sizes", type=int, nargs="+", help="cloth sizes N (N × N particles)")
    parser.add_argument("--seconds", type=float, default=1.0, help="timed seconds per engine and size")
    parser.add_argument("--no-newton", action="store_true", help="time warpspring alone")
    parser.add_argument("--newton-max-particles", type=int, help="time Newton only up to this many particles")
    parser.add_argument(
        "--evaluation", nargs="+", default=["auto"], choices=["auto", "gather", *EVALUATIONS, "scatter"],
        help="warpspring spring-evaluation modes to time (one row each; gather: the grid's neighbours from rows and "
             "columns, each group's values once; gather-table: neighbours from the incidence table, "
             "finalize(spring_grid=False); gather-per-spring: spring data read per spring, "
             "finalize(spring_groups=False), the layout before per-group data)",
    )
    parser.add_argument("--batches", type=int, default=5, help="timed batches per engine and size (median)")
    parser.add_argument("--bytes", action="store_true", help="also the gather rows' bytes and bandwidth")
    parser.add_argument(
        "--interleave", action="store_true",
        help="take the engines' timed batches in turn and give the median of the per-round ratios (shared hosts)",
    )
    parser.add_argument("--guard", nargs="+", default=["default", "off"], choices=["off", "default"],
                        help="warpspring rows with the default Simulator's guard (GuardLimits(): what a user gets) "
                             "and/or the guard off (default: both, the default row first)")
    parser.add_argument("--pin", default="top", choices=["corners", "top"],
                        help="hang the cloth from its whole top row (default: the default guard stops the cloth "
                             "hung from its two top corners, ANCHORS.md, at N ≥ 128, where its corner springs tear)")
    parser.add_argument("--out", help="also write the Markdown table to this file")
    args = parser.parse_args()

    wp.config.log_level = wp.LOG_WARNING
    # A fresh kernel cache, so that "setup" includes each engine's kernel compilation.
    wp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="warpspring-bench-")
    device = wp.get_device(args.device)
    sizes = args.sizes or DEFAULT_SIZES["cuda" if device.is_cuda else "cpu"]
    newton_version = installed_newton(not args.no_newton)

    lines = [
        f"Hanging cloth, {SUBSTEPS} substeps per 1/{FPS} s frame, one graph per frame. "
        f"Device: {device.name} ({device.alias}); Warp {wp.__version__}"
        + (f"; Newton {newton_version}" if newton_version else "")
        + f"; {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}. "
        f"Command: `python {shlex.join(['bench/cloth.py', *sys.argv[1:]])}`",
        "",
        "| N | particles | springs | engine | setup [s] | substeps/s | particle-substeps/s | spread | vs guard off "
        "| vs Newton | max Δx vs Newton [m] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    gathered = []  # (N, model, substeps/s) of the gather rows, for --bytes
    for n in sizes:
        rows, results, models = size_rows(n, device, args.evaluation, args.guard, newton_version, pin=args.pin,
                                          seconds=args.seconds, batches=args.batches, interleave=args.interleave,
                                          newton_max_particles=args.newton_max_particles)
        lines += rows
        print("\n".join(rows), flush=True)
        gathered += [(n, models[name], SUBSTEPS / r["frame_s"]) for name, r in results.items()
                     if name in models and models[name].spring_gather]
    if args.bytes:
        lines += ["", *bytes_table(gathered, device)]
    emit_table(lines, args.out)


def bytes_table(gathered: list[tuple[int, ws.Model, float]], device) -> list[str]:
    """Markdown rows of the gather rows' traffic: (N, model, substeps/s) each."""

    copy = copy_bandwidth(device)
    lines = [
        f"Bytes per particle-substep of the fused gather step (`bench/traffic.py`: compulsory = every array "
        f"once, requested = every load without reuse) and the bandwidth the measured rate draws; "
        f"`wp.copy` of 512 MB on this device in this run: {copy / 1e9:,.0f} GB/s (read + write).",
        "",
        "| N | particle-substeps/s | compulsory | requested | compulsory × rate | of copy | "
        "ncu DRAM read + write | ncu L2 | ncu kernel time | ncu DRAM bandwidth |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n, model, rate in gathered:
        b = per_particle(gather_traffic(model), model)
        throughput = rate * model.particle_count * model.world_count
        achieved = b["compulsory"] * throughput
        ncu = ncu_dram_bytes(n, device, kernel_cache=wp.config.kernel_cache_dir,
                             layout=model.spring_layout) if device.is_cuda else None
        profiled = ["", "", "", ""]
        if isinstance(ncu, dict):
            dram = ncu.get("dram__bytes_read.sum", 0.0) + ncu.get("dram__bytes_write.sum", 0.0)
            seconds = ncu.get("gpu__time_duration.sum", 0.0)
            profiled = [
                f"{dram / model.particle_count:.0f} B",
                f"{ncu['lts__t_bytes.sum'] / model.particle_count:.0f} B" if "lts__t_bytes.sum" in ncu else "",
                f"{seconds * 1e6:.1f} µs",
                f"{dram / seconds / 1e9:,.0f} GB/s" if seconds else "",
            ]
        elif ncu is not None:
            print(ncu)
        lines.append(
            f"| {n} ({model.spring_layout}) | {throughput / 1e9:.3f} G | {b['compulsory']:.0f} B | "
            f"{b['requested']:.0f} B | "
            f"{achieved / 1e9:,.1f} GB/s | {achieved / copy:.0%} | " + " | ".join(profiled) + " |"
        )
        print(lines[-1], flush=True)
    return lines


if __name__ == "__main__":
    main()
