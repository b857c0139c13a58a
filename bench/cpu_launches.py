"""The hanging cloth on the CPU: two source trees of warpspring (e.g. today's and an older commit's, checked out
in a git worktree) and Newton, timed in turn, with each tree's launches per substep and each launch's cost.

Each tree runs in a worker process of its own (a tree's ``warpspring`` package on its ``sys.path``), and Newton
runs inside the first tree's worker, so that the warpspring rows of that tree and Newton share one process. The
driver asks every engine of every worker for one timed batch per round, round after round, so that a load that
comes and goes on a shared host falls on all of them alike; it reports each engine's median frame rate over the
rounds, the spread ((max - min) / median) and the median over rounds of the per-round ratio to Newton and to the
first tree.

The scene is ``cloth_scene.py``'s reference cloth (N × N particles, structural + shear + bend springs, two top
corners pinned or, with ``--pin top``, its whole top row, symplectic Euler, 16 substeps per 1/60 s frame, one
captured graph per frame: Warp's CPU graph).
With ``--launches`` every worker also counts the launches of one frame (a wrapper around ``wp.launch`` during an
uncaptured frame, and the operations of the captured frame's graph) and times every distinct launch of a substep
alone, replayed inside a CPU graph of ``--repeat`` copies of it (what it costs in the frame's graph; the minimum of
15 replays, as the host's load only ever adds time).

    python bench/cpu_launches.py --sizes 32 64 --batches 7
    python bench/cpu_launches.py --tree old=/path/to/old/worktree --sizes 32 64 --batches 7 --launches
    python bench/cpu_launches.py --sizes 32 --engines off default --batches 7 --out bench/results/x.md
    python bench/cpu_launches.py --device cuda:0 --tree main=../main --sizes 64 256 1024 --engines off default

The last compares two trees on a GPU the same way (each tree's process replays its CUDA graphs in turn).
"""

from __future__ import annotations

import argparse
import collections
import datetime
import json
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

#: Engines a worker can time: warpspring rows (spring evaluation, guard, graph[, the CPU sweep]) and Newton.
ENGINES = {
    "off": ("auto", False, True),  # what a user gets with the guard switched off
    "default": ("auto", True, True),  # the default Simulator (guard on)
    "gather": ("gather", False, True),
    "scatter": ("scatter", False, True),
    "default-gather": ("gather", True, True),
    "default-scatter": ("scatter", True, True),
    "off-nograph": ("auto", False, False),  # every launch from Python: the host's cost per launch
    "gather-nograph": ("gather", False, False),
    "scatter-nograph": ("scatter", False, False),
    # The gathered springs' per-particle step on the CPU (as on CUDA) instead of the sweep (kernels/sweep.py).
    "particles": ("gather", False, True, False),
    "default-particles": ("gather", True, True, False),
    "newton": None,
}


# --------------------------------------------------------------------------------------------------- worker


def _worker(tree: str, device: str, n: int, engines: list[str], launches: bool, repeat: int, pin: str) -> None:
    """Build the engines of one tree and answer the driver's requests on stdin (one JSON line each)."""
    mapped = os.path.join(tree, "warpspring", "kernels")
    if not os.path.exists(mapped) and os.path.isdir(os.path.join(tree, "kernels")):
        # Older trees kept the kernels at the top (pyproject's package-dir maps them to warpspring.kernels).
        os.symlink(os.path.join("..", "kernels"), mapped)
    sys.path.insert(0, tree)
    sys.path.insert(0, HERE)  # cloth_scene (this tree's bench), NewtonRunner
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    import warpspring as ws
    from cloth_scene import FPS, SUBSTEPS

    device = wp.get_device(device)
    runners = {}
    for name in engines:
        if name == "newton":
            from cloth import NewtonRunner

            runners[name] = NewtonRunner(_model(ws, n, device, "auto", pin))
        else:
            evaluation, guard, graph, *sweep = ENGINES[name]
            model = _model(ws, n, device, evaluation, pin)
            runners[name] = _Runner(ws, model, guard, FPS, SUBSTEPS, graph, sweep=sweep[0] if sweep else True)
        runners[name].frame()  # compile, capture
    info = {"warp": wp.__version__, "warpspring": tree, "substeps": SUBSTEPS, "particles": n * n,
            "device": f"{device.alias} ({device.name})"}
    if "newton" in runners:
        import newton

        info["newton"] = newton.__version__
    for name, runner in runners.items():
        if name != "newton":
            swept = device.is_cpu and getattr(runner.sim.integrator, "cpu_sweep", False)  # kernels/sweep.py
            info[f"{name}_evaluation"] = (("sweep" if swept else "gather") if runner.sim.model.spring_gather
                                          else "scatter")
    if launches:
        info["launches"] = {name: _launch_profile(wp, runner, repeat, device) for name, runner in runners.items()}
    print(json.dumps(info), flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        runner = runners[request["engine"]]
        frames = request["frames"]
        t0 = time.perf_counter()
        for _ in range(frames):
            runner.frame()
        wp.synchronize_device(device)
        print(json.dumps({"seconds": (time.perf_counter() - t0) / frames}), flush=True)


def _model(ws, n, device, evaluation, pin: str):
    """cloth_scene's reference cloth, built with this tree's builder (older trees' finalize takes fewer options)."""
    import numpy as np

    from cloth_scene import KD, KE, MASS, SPACING

    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=KE, kd=KD)
    builder.add_cloth_grid(nx=n, ny=n, spacing=SPACING, origin=(0.0, 0.0, 0.5 * n * SPACING),
                           rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), particle_mass=MASS,
                           structural=spring, shear=spring, bend=spring,
                           pin=["top"] if pin == "top" else ["top-left", "top-right"])
    return builder.finalize(device, spring_evaluation=evaluation)


class _Runner:
    def __init__(self, ws, model, guard: bool, fps: int, substeps: int, graph: bool, sweep: bool = True):
        integrator = None
        if not sweep:
            try:
                integrator = ws.SymplecticEuler(model, cpu_sweep=False)
            except TypeError:  # a tree before the sweep: its default step is the per-particle one
                integrator = None
        self.sim = ws.Simulator(model, fps=fps, substeps=substeps, use_graph=graph, integrator=integrator,
                                guard=ws.GuardLimits() if guard else None)

    def frame(self):
        self.sim.step_frame()


def _launch_profile(wp, runner, repeat: int, device) -> dict:
    """Launches of one frame by kernel (an uncaptured frame through a wrapper of ``wp.launch``), the captured
    graph's operations, and each distinct launch's time alone inside a CPU graph of ``repeat`` copies [µs]."""
    calls = []
    original = wp.launch

    def counting(kernel, *args, **kwargs):
        calls.append((kernel, args, kwargs))
        return original(kernel, *args, **kwargs)

    # One frame without the graph (the same launches the graph records), counted; then restore.
    if hasattr(runner, "sim"):
        graph_attr = getattr(getattr(runner.sim, "stepper", runner.sim), "_graph", None)
    else:
        graph_attr = runner.graph
    ops = None
    if graph_attr is not None and getattr(graph_attr, "_apic_capture", None) is not None:
        ops = graph_attr._apic_capture.operation_count
    wp.launch = counting
    # Every launch of the counted frame through wp.launch: a tree whose flat_launch replays recorded launches on the
    # CPU (kernels/flatten.py) records nothing during it.
    flatten = sys.modules.get("warpspring.kernels.flatten")
    key = getattr(flatten, "_launch_key", None)
    if key is not None:
        flatten._launch_key = lambda *args: None
    try:
        if hasattr(runner, "sim"):
            owner = getattr(runner.sim, "stepper", runner.sim)  # the stepper, or an older tree's Simulator
            graph, owner.use_graph = owner.use_graph, False
            runner.sim.step_frame()
            owner.use_graph = graph
        else:  # Newton
            runner.simulate()
    finally:
        wp.launch = original
        if key is not None:
            flatten._launch_key = key
    by_kernel = collections.Counter(_kernel_name(k) for k, _, _ in calls)
    # Each distinct kernel of the frame, timed alone: its first call's arguments, replayed `repeat` times in a graph.
    seen, timing = set(), {}
    for kernel, args, kwargs in calls:
        name = _kernel_name(kernel)
        if name in seen:
            continue
        seen.add(name)
        kwargs = dict(kwargs)
        with wp.ScopedCapture(device=device, force_module_load=False) as capture:
            for _ in range(repeat):
                original(kernel, *args, **kwargs)
        samples = []
        for _ in range(15):
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            wp.capture_launch(capture.graph)
            wp.synchronize_device(device)
            samples.append((time.perf_counter() - t0) / repeat)
        # The host cost of one wp.launch call with these arguments, outside any graph (what an uncaptured run pays).
        host = []
        for _ in range(15):
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            original(kernel, *args, **kwargs)
            wp.synchronize_device(device)
            host.append(time.perf_counter() - t0)
        # Minima: a shared host's load only ever adds time.
        timing[name] = {"graph_us": 1e6 * min(samples), "launch_us": 1e6 * min(host)}
    return {"frame_launches": len(calls), "graph_ops": ops, "by_kernel": dict(by_kernel), "timing": timing}


def _kernel_name(kernel) -> str:
    return getattr(kernel, "key", None) or getattr(kernel, "__name__", str(kernel))


# --------------------------------------------------------------------------------------------------- driver


class Worker:
    def __init__(self, label: str, tree: str, n: int, engines: list[str], launches: bool, repeat: int,
                 device: str = "cpu", pin: str = "corners"):
        self.label = label
        cmd = [sys.executable, os.path.abspath(__file__), "--worker", tree, "--device", device, "--sizes", str(n),
               "--engines", *engines, "--repeat", str(repeat),
               "--pin", pin] + (["--launches"] if launches else [])
        # The tree first, then whatever the caller's path held (a Warp installed outside site-packages).
        inherited = os.environ.get("PYTHONPATH")
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([tree] + ([inherited] if inherited else [])))
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
                                     cwd=tree)
        self.info = json.loads(self._line())
        self.engines = engines

    def _line(self) -> str:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"worker {self.label} ended (exit {self.proc.wait()})")
        return line

    def batch(self, engine: str, frames: int) -> float:
        self.proc.stdin.write(json.dumps({"engine": engine, "frames": frames}) + "\n")
        self.proc.stdin.flush()
        return json.loads(self._line())["seconds"]

    def close(self):
        self.proc.stdin.close()
        self.proc.wait()


def run_size(n: int, trees: dict[str, str], engines: list[str], batches: int, seconds: float, launches: bool,
             repeat: int, newton: bool, device: str = "cpu",
             pin: str = "corners") -> tuple[list[dict], list[Worker]]:
    workers = []
    own = [e for e in engines if e != "newton"]  # Newton runs once, in the first tree's worker
    for k, (label, tree) in enumerate(trees.items()):
        workers.append(Worker(label, tree, n, own + (["newton"] if newton and k == 0 else []), launches,
                              repeat, device, pin))
    rows = [(w, e) for w in workers for e in w.engines]
    frames = {}
    for w, e in rows:  # frames per batch: doubled until a batch takes `seconds`
        f = 1
        while w.batch(e, f) * f < seconds and f < 1 << 14:
            f *= 2
        frames[(w.label, e)] = f
    times = {(w.label, e): [] for w, e in rows}
    for _ in range(batches):
        for w, e in rows:
            times[(w.label, e)].append(w.batch(e, frames[(w.label, e)]))
    for w in workers:
        w.close()
    substeps = workers[0].info["substeps"]
    first = workers[0].label
    results = []
    for w, e in rows:
        t = times[(w.label, e)]
        med = statistics.median(t)
        row = {"N": n, "tree": w.label, "engine": e, "substeps_per_s": substeps / med,
               "spread": (max(t) - min(t)) / med, "times": t,
               "evaluation": w.info.get(f"{e}_evaluation", "")}
        if newton and e != "newton":
            row["vs_newton"] = statistics.median(b / a for a, b in zip(t, times[(first, "newton")]))
        if w.label != first and (first, e) in times:
            row["vs_first"] = statistics.median(b / a for a, b in zip(t, times[(first, e)]))
        results.append(row)
    return results, workers


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tree", action="append", default=[],
                        help="label=path of a warpspring source tree (repeatable); this tree first, as 'new'")
    parser.add_argument("--device", default="cpu", help="Warp device (the CPU's regression is what this bench is for; "
                        "cuda:0 compares trees on a GPU the same way)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    parser.add_argument("--engines", nargs="+", default=["off", "default"], choices=list(ENGINES),
                        help="warpspring rows (Newton is added to the first tree's worker unless --no-newton)")
    parser.add_argument("--batches", type=int, default=7)
    parser.add_argument("--seconds", type=float, default=0.3, help="seconds per timed batch")
    parser.add_argument("--no-newton", action="store_true")
    parser.add_argument("--launches", action="store_true", help="also count and time each tree's launches")
    parser.add_argument("--repeat", type=int, default=3, help="copies of a launch in its timing graph")
    parser.add_argument("--pin", default="corners", choices=["corners", "top"],
                        help="hang the cloth from its two top corners (default) or its whole top row "
                             "(bench/cloth.py's)")
    parser.add_argument("--out", help="also write the Markdown tables to this file")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:  # (given the driver's ``--pin``: the GPU side-by-side of 2026-11-28, whose workers took their own
        # default, hung its 256² cloth from two corners, whose springs the guard then saw torn at 11×)
        _worker(args.worker, args.device, args.sizes[0], args.engines, args.launches, args.repeat, args.pin)
        return
    trees = {"new": ROOT}
    for spec in args.tree:
        label, _, path = spec.partition("=")
        trees[label] = os.path.abspath(path)
    newton = not args.no_newton
    lines, launch_lines = [], []
    info = None
    for n in args.sizes:
        results, workers = run_size(n, trees, args.engines, args.batches, args.seconds, args.launches, args.repeat,
                                    newton, args.device, args.pin)
        info = info or workers[0].info
        for r in results:
            lines.append(
                f"| {n} | {r['tree']} | {r['engine']}{' (' + r['evaluation'] + ')' if r['evaluation'] else ''} | "
                f"{r['substeps_per_s']:,.0f} | {r['spread']:.0%} | "
                f"{r['vs_newton']:.2f}× | " if "vs_newton" in r else
                f"| {n} | {r['tree']} | {r['engine']} | {r['substeps_per_s']:,.0f} | {r['spread']:.0%} | | ")
            lines[-1] += f"{r['vs_first']:.2f}× |" if "vs_first" in r else " |"
            print(lines[-1], flush=True)
        if args.launches:
            for w in workers:
                for engine, p in w.info["launches"].items():
                    per_substep = p["frame_launches"] / w.info["substeps"]
                    total = sum(p["timing"][k]["graph_us"] * c for k, c in p["by_kernel"].items()) / w.info["substeps"]
                    launch_lines.append(f"| {n} | {w.label} | {engine} | {per_substep:g} | {p['graph_ops']} | "
                                        f"{total:.1f} | " + ", ".join(
                                            f"{k} ×{c / w.info['substeps']:g}: {p['timing'][k]['graph_us']:.1f} / "
                                            f"{p['timing'][k]['launch_us']:.1f}" for k, c in p["by_kernel"].items())
                                        + " |")
                    print(launch_lines[-1], flush=True)
    header = [
        f"Hanging cloth, {info['substeps']} substeps per frame, one graph per frame; device {info['device']}; Warp "
        f"{info['warp']}" + (f", Newton {info['newton']}" if "newton" in info else "") +
        f"; {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; {os.cpu_count()} cores; "
        f"median of {args.batches} interleaved batches of ~{args.seconds} s.",
        f"Command: `python bench/cpu_launches.py {' '.join(sys.argv[1:])}`",
        "",
        "| N | tree | engine | substeps/s | spread | vs Newton | vs new |",
        "|---|---|---|---|---|---|---|",
    ]
    tables = header + lines
    if launch_lines:
        tables += ["", "Launches per substep (an uncaptured frame's `wp.launch` calls / substeps), the captured "
                   "frame's graph operations, the sum of each launch's time inside a graph [µs per substep], and "
                   "per kernel: calls per substep: µs in a graph / µs of an uncaptured `wp.launch`.", "",
                   "| N | tree | engine | launches/substep | graph ops/frame | Σ µs/substep | kernels |",
                   "|---|---|---|---|---|---|---|", *launch_lines]
    print("\n" + "\n".join(tables))
    if args.out:
        with open(args.out, "w") as f:
            f.write("\n".join(tables) + "\n")


if __name__ == "__main__":
    main()
