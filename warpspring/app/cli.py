"""The ``warpspring`` command line.

Errors a user can fix (a missing file, a malformed scene, a bad option, a model too large for the memory,
an unstable run, a full disk) end with one line on stderr and a non-zero exit status, never a traceback:

* 2 (:data:`EXIT_CONFIG`): bad input, or a model that does not fit in memory; also an output another run is
  writing (the line names its process: ``the USD output 'out.usdc' is being written by another run (process
  1234); ...``) and a scene's ``[output] path`` that leads out of the scene's folder;
* 3 (:data:`EXIT_SIMULATION`): a simulation that went numerically bad (a guard stop);
* 4 (:data:`EXIT_IO`): an output that cannot be written (a full disk, a file removed mid-run), with the OS's
  reason (``cannot write frame 17 to the USD file 'out.usdc': No space left on device [ENOSPC]; the file holds
  frames 0..16``; USD's own diagnostics are folded into that line, never printed beside it); a USD file keeps
  every frame written before;
* 5 (:data:`EXIT_NO_CHOICE`): ``warpspring choose`` found no measured configuration that meets the error target
  within the budget (it still prints the closest one and what to change).
* 6 (:data:`EXIT_AUDIT`): ``warpspring audit`` found a surface passing through itself (or, with --thickness,
  layers closer than half the thickness); likewise ``warpspring run --audit-substeps`` over any substep.

Commands that use Warp initialise it without its CUDA-driver warning ("Could not find or load the NVIDIA CUDA
driver"), which concerns GPUs only, unless the command asks for a CUDA device.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import os
import shlex
import sys
import tempfile
import time
import warnings

import warp as wp

from .. import checks
from ..analysis import (engines, load_battery, stability_map, stability_map_report, sweep, sweep_plan, sweep_report, trade,
                        trade_choice, trade_contact, trade_report)
from ..analysis.audit import SubstepAudit, audit_usd
from ..analysis import fit as fit_analysis
from ..analysis.sweep_ray import RayEngine  # Ray itself loads only when an engine starts (optional: ray)
from ..core.memory import out_of_memory
from ..errors import ConfigError, OutputError, SimulationError, os_error_reason
from ..io.render import render_usd
from ..io.scene import DeprecatedKeyWarning, load_scene
from ..plotting import pyplot
from .runner import run_scene
from .viewer_file import FileView
from .viewer_live import LiveView

EXIT_CONFIG = 2
EXIT_SIMULATION = 3
EXIT_IO = 4
EXIT_NO_CHOICE = 5
EXIT_AUDIT = 6

#: The line Warp's native library prints at initialisation on a machine without an NVIDIA driver.
CUDA_DRIVER_WARNING = "Could not find or load the NVIDIA CUDA driver"


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own errors: the same one-line form as every other error, exit 2
        self.exit(EXIT_CONFIG, f"warpspring: error: {message} (see {self.prog} --help)\n")


def _substeps(text: str) -> int | str:
    return "auto" if text == "auto" else _positive_int(text)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _add_study_options(parser: argparse.ArgumentParser, name: str) -> None:
    """The options shared by the measurement commands (trade, stability)."""
    parser.add_argument("--device", help="Warp device: cpu, cuda:0, ... (default: Warp's default)")
    parser.add_argument("--out", default=name, help=f"output directory (default: {name})")
    parser.add_argument("--quick", action="store_true", help="a CI-sized run (about a minute on a CPU)")
    parser.add_argument("--integrators", nargs="+", metavar="NAME", help="measure only these integrators")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="warpspring", description="Mass-spring cloth on NVIDIA Warp, exported to USD.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    run = sub.add_parser("run", help="simulate a TOML scene and write the animation to USD")
    run.add_argument("scene", help="scene file (.toml); see examples/")
    run.add_argument("-o", "--output",
                     help="output USD file (.usdc, or .usda for text), written as given; default: the scene's "
                          "[output] path, taken in the scene file's folder and refused if it leads out of it "
                          "(absolute, '..', a symbolic link). One run owns an output: while it writes, it holds a "
                          "lock on OUT.lock beside it (naming its process), and another run on the same output "
                          "exits with status 2")
    run.add_argument("--device", help="Warp device: cpu, cuda:0, ... (default: the scene's, else Warp's default)")
    run.add_argument("--frames", type=_positive_int, help="frames to simulate")
    run.add_argument("--fps", type=_positive_float, help="frames per second [1/s]")
    run.add_argument("--substeps", type=_substeps, metavar="N|auto",
                     help="integrator steps per frame, or auto: the fewest the stability advisor passes with a margin "
                          "(implicit Euler: an accuracy floor), chosen before the run and printed (default: the "
                          "scene's [simulation] substeps, else auto)")
    run.add_argument("-q", "--quiet", action="store_true", help="no progress bar or lines")
    run.add_argument("--audit-substeps", action="store_true",
                     help="audit every substep in float64 (continuous crossings, intersections, pairs closer than "
                          "half the self-collision thickness; slow: a check, not a production run) and exit with "
                          "status 6 when anything was found (pip install 'warpspring[audit]')")
    run.add_argument("--audit-workers", type=_positive_int, default=1, metavar="N",
                     help="with --audit-substeps: N processes audit each frame's substeps side by side (the same "
                          "findings, about N times sooner where a frame has N substeps or more; default 1)")
    run.add_argument("--world", type=_non_negative_int, metavar="K",
                     help="write only world K of a scene of several worlds (default: the scene's [output] world, "
                          "else every world, each as its own prim /World/world_NNNN)")
    run.add_argument("--world-spacing", type=_non_negative_float, metavar="M",
                     help="distance in metres between the written worlds, laid out on a grid in the ground plane "
                          "(default: the scene's [output] world_spacing, else twice the cloth's extent, >= 1 m)")
    run.add_argument(
        "--strict", action="store_true",
        help="refuse to run when the stability advisor finds the step unstable (default: warn and run)",
    )
    run.add_argument("--watch-every", type=_non_negative_int, metavar="N", default=None,
                     help="re-check the step's stability at the state reached every N frames (a few power "
                          "iterations, off the critical path on CUDA) and warn with the substeps it needs; 0: "
                          "off (default: 10)")
    run.add_argument("--checkpoint-every", type=_non_negative_int, metavar="N", default=0,
                     help="save the whole simulation every N frames to OUT.checkpoint.npz beside the output "
                          "(atomically replaced; default 0: never), to continue a stopped run with --resume")
    run.add_argument("--resume", metavar="CHECKPOINT",
                     help="continue a stopped run from its checkpoint: the output (the same -o) keeps its frames "
                          "up to the checkpoint's and the run goes on to the end, bit for bit as if uninterrupted "
                          "on the same device")
    run.add_argument("--layer-over", metavar="ASSET",
                     help="write the simulation as a layer over the artist's USD file ASSET (never written): overrides "
                          "at its prim paths of what the simulation changes (points, normals, velocities, "
                          "accelerations, extent), in its units, up axis and time codes, the asset as a sublayer; the "
                          "scene must read a cloth or soft body from ASSET")
    run.add_argument("--layer-arc", choices=("sublayer", "reference", "none"), default="sublayer",
                     help="with --layer-over: the asset as the layer's sublayer (default), referenced at its root "
                          "prims, or not at all (bare overrides, for a shot that stacks them over the asset)")
    _add_view_options(run, "--view", "serve a page in the browser that shows the run as it goes, with its live "
                                     "inputs (gravity, drag, wind, stiffness, stabilisers; pause, step, reset) "
                                     "(pip install 'warpspring[view]')")
    run.set_defaults(handler=_cmd_run)

    view = sub.add_parser("view", help="show a USD file in the browser: play, scrub, colour by speed or a primvar; "
                                       "follows a file still being written (pip install 'warpspring[view]')")
    view.add_argument("usd", help="a USD file written by warpspring run")
    view.add_argument("--no-follow", action="store_true", help="do not re-read the file as it grows")
    _add_view_options(view, None, None)
    view.set_defaults(handler=_cmd_view)

    render = sub.add_parser("render", help="render a frame of a USD animation to PNG (needs matplotlib)")
    render.add_argument("usd", help="USD file written by 'warpspring run'")
    render.add_argument("-o", "--output", required=True, help="PNG file")
    render.add_argument("--frame", type=int, default=-1, help="frame to render; negative counts from the end")
    render.add_argument("--size", type=_positive_int, default=900, help="image width in pixels")
    render.set_defaults(handler=_cmd_render)

    trade_cmd = sub.add_parser(
        "trade",
        help="measure each integrator's error against its cost: tables, CSV, plots (x(t), v(t) of the seed spring too)",
    )
    _add_study_options(trade_cmd, "trade")
    trade_cmd.add_argument("--problems", nargs="+", metavar="NAME",
                           help="measure these problems: spring, stiff-spring, cloth (the default three), and the contact "
                                "scenes drape, stack, tablecloth, softball, softball-neohookean")
    trade_cmd.add_argument("--reduced", action="store_true",
                           help="contact problems at full size with fewer runs (every integrator at 20 and 40 substeps, "
                                "the reference option, one reference refinement)")
    trade_cmd.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    trade_cmd.set_defaults(handler=_cmd_trade)
    _add_ray_option(trade_cmd)

    choose = sub.add_parser("choose", help="pick the cheapest integrator and step that meet an error target")
    choose.add_argument("--error", type=_positive_float, required=True, help="largest acceptable position error [m]")
    choose.add_argument("--budget", type=_positive_float, help="most wall seconds per simulated second")
    choose.add_argument("--study", default="trade/trade.csv", help="CSV of 'warpspring trade' (default: %(default)s)")
    choose.add_argument("--problem", default="cloth", help="the study's problem: cloth, spring, drape, stack, tablecloth, softball, ... "
                             "(default: cloth)")
    choose.set_defaults(handler=_cmd_choose)

    stability = sub.add_parser(
        "stability",
        help="measure each integrator's largest stable step (one spring, the cloth, the seed case) beside theory",
    )
    _add_study_options(stability, "stability")
    stability.add_argument("--report", metavar="PATH",
                           help="write the full Markdown report here too (default: OUT/stability.md only); the "
                                "terminal gets a short summary")
    stability.add_argument("--battery", nargs="*", metavar="SCENE",
                           help="also measure the advisor under load (analysis/load_battery.py): where the battery's "
                                "cloth really blows up against what --strict passes, for the explicit integrators, "
                                "in these scenes (hanging, forced, driven, windy, pulled; none named: all), and the "
                                "linear limits (at the hanging and forced cloth's equilibrium; along every scene's "
                                "runs), table in OUT/battery.md; --quick: one step per integrator, 6 worlds, 2 s runs, "
                                "no linear limits")
    stability.set_defaults(handler=_cmd_stability)
    _add_ray_option(stability)

    sweep_cmd = sub.add_parser(
        "sweep",
        help="run many variants of a scene (a sweep file's axes over scene keys) on Ray, locally or on a cluster: "
             "a table (CSV, Parquet) and a plot of their metrics",
    )
    sweep_cmd.add_argument("sweep", help="sweep file (.toml); see examples/sweep.toml")
    sweep_cmd.add_argument("--address", metavar="ADDR",
                           help="run on the Ray cluster at ADDR (ray://host:10001, host:6379 or auto); default: start "
                                "Ray on this machine, bound to 127.0.0.1")
    sweep_cmd.add_argument("--workers", type=_positive_int, metavar="N",
                           help="tasks in flight at once (locally also the CPUs Ray uses); default: every CPU")
    sweep_cmd.add_argument("--gpus", type=_non_negative_float, default=0.0, metavar="F",
                           help="GPUs per task, fractional to share one (0.25: four tasks per GPU); default 0: the CPU")
    sweep_cmd.add_argument("--out", default="sweep", help="output directory (default: %(default)s)")
    sweep_cmd.add_argument("--resume", action="store_true",
                           help="continue a sweep in --out: variants whose result is there are skipped")
    sweep_cmd.add_argument("--no-ray", action="store_true",
                           help="run every variant in this process, one batch after the other (no Ray needed)")
    sweep_cmd.add_argument("--device", help="Warp device of every task (default: cuda:0 in a task given a GPU, else "
                                            "the CPU)")
    sweep_cmd.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    sweep_cmd.set_defaults(handler=_cmd_sweep)

    fit_cmd = sub.add_parser("fit", help="fit a scene's parameters to a target motion (a USD file of the same mesh, or "
                                         "markers at times in a .npz) by differentiable runs and L-BFGS-B")
    fit_cmd.add_argument("scene", help="scene file (.toml); each fitted parameter's value in it is the first guess")
    fit_cmd.add_argument("--target", required=True,
                         help="the motion: a USD file of the same mesh (its points at every time sample after the "
                              "first) or a .npz of times [s], particles (indices) and positions [m]")
    fit_cmd.add_argument("--param", action="append", required=True, metavar="KEY",
                         help="a dotted key of the scene file to fit, e.g. cloth.material.stretch or world.drag "
                              "(repeat for several)")
    fit_cmd.add_argument("--prim", help="the target USD file's mesh prim (default: the first mesh)")
    fit_cmd.add_argument("--starts", type=_positive_int, default=4,
                         help="starting points, run together as worlds (default 4)")
    fit_cmd.add_argument("--integrator", choices=("symplectic_euler", "velocity_verlet"), default=None,
                         help="default: the scene's when differentiable, else symplectic_euler")
    fit_cmd.add_argument("--substeps", type=_positive_int, help="steps per frame (default: the scene's)")
    fit_cmd.add_argument("--device", help="Warp device (default: the scene's, else Warp's default)")
    fit_cmd.add_argument("--max-iterations", type=_positive_int, default=100)
    fit_cmd.set_defaults(handler=_cmd_fit)

    audit = sub.add_parser("audit", help="check every frame of a USD file for surfaces passing through themselves "
                                         "(float64 segment-triangle tests, minimum distances)")
    audit.add_argument("usd", help="a USD file written by warpspring run")
    audit.add_argument("--thickness", type=_positive_float, metavar="METRES",
                       help="also count the frames whose layers are closer than half this thickness [m]")
    audit.set_defaults(handler=_cmd_audit)
    return parser


def _add_view_options(parser: argparse.ArgumentParser, switch: str | None, help_text: str | None) -> None:
    """The viewer's options: its switch (``run --view``), address and port."""
    if switch is not None:
        parser.add_argument(switch, action="store_true", help=help_text)
    parser.add_argument("--view-host", default="127.0.0.1", metavar="ADDR",
                        help="address the viewer listens on (default: %(default)s, this machine only; another "
                             "address serves plain HTTP to the network, the URL's token the only key)")
    parser.add_argument("--view-port", type=_non_negative_int, default=8080, metavar="PORT",
                        help="the viewer's port (default: %(default)s; 0: any free port)")


def _cmd_view(args) -> int:
    view = FileView(args.usd, host=args.view_host, port=args.view_port, follow=not args.no_follow)
    print(f"viewer of {args.usd} at {view.url} (Ctrl-C to stop)", flush=True)
    _serve_until_interrupted(view)
    return 0


def _serve_until_interrupted(view) -> None:
    """Keep a viewer's page up until Ctrl-C, then close it."""
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        view.close()


def _add_ray_option(parser: argparse.ArgumentParser) -> None:
    """``--ray [ADDRESS]`` of the studies: their plans' jobs as Ray tasks (the same tables)."""
    parser.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                        help="run the study's jobs as Ray tasks: on a local Ray (no ADDRESS; bound to 127.0.0.1) or "
                             "the cluster at ADDRESS; the same tables, but timings are taken concurrently "
                             "(pip install 'warpspring[cluster]')")
    parser.add_argument("--workers", type=_positive_int, metavar="N",
                        help="with --ray: jobs in flight at once (default: every CPU)")


def _study_engine(args):
    """The engine of a study's jobs: a RayEngine for --ray, else None (in this process, in order)."""
    if args.ray is None:
        return None
    gpus = 1.0 if wp.get_device(args.device).is_cuda else 0.0  # a task runs where the study was asked to
    return RayEngine(None if args.ray == "local" else args.ray, workers=args.workers, gpus_per_task=gpus)


def _cmd_sweep(args) -> int:
    plan = sweep_plan.load_sweep(args.sweep)  # every variant checked before anything starts
    checks.output_dir(args.out)
    pyplot("the sweep's plot")
    if args.no_ray:
        if args.address is not None:
            raise ConfigError("--no-ray runs in this process: drop --address (or --no-ray)")
        engine = engines.LocalEngine()
    else:
        engine = RayEngine(args.address, workers=args.workers, gpus_per_task=args.gpus)
    try:
        print(f"sweep {args.sweep}: {len(plan.variants)} variants on {engine.describe()}", flush=True)
        result = sweep.run_sweep(plan, args.out, engine=engine, resume=args.resume, device=args.device,
                                 progress=not args.quiet and sys.stderr.isatty())
    except KeyboardInterrupt:
        print(f"warpspring: interrupted; the results so far are in {args.out}: continue with --resume",
              file=sys.stderr)
        return 130
    finally:
        engine.close()
    paths = sweep_report.write_report(result, args.out)
    for line in sweep_report.summary(result):
        print(line)
    print(f"wrote {', '.join(paths)}")
    return 0


def _cmd_fit(args) -> int:
    wp.config.log_level = wp.LOG_WARNING
    scene = load_scene(args.scene)
    substeps = args.substeps or scene.substeps
    if not isinstance(substeps, int):
        raise ConfigError("the scene's substeps are 'auto': give --substeps N for the fit's step")
    integrator = args.integrator or (scene.integrator if scene.integrator in ("symplectic_euler", "velocity_verlet")
                                     else "symplectic_euler")
    device = args.device or scene.device
    build, guess = fit_analysis.scene_parameters(args.scene, args.param)
    motion = fit_analysis.motion_from_file(args.target, prim=args.prim)
    print(f"fit {', '.join(guess)} of {args.scene} to {args.target}: {len(motion.times)} times, "
          f"{len(motion.particles)} points, {args.starts} starts, {integrator} at {substeps} substeps", flush=True)
    result = fit_analysis.fit(functools.partial(build, device=device), guess, motion,
                              dt=1.0 / (scene.fps * substeps), integrator=integrator, starts=args.starts,
                              max_iterations=args.max_iterations, device=device)
    print(result.table())
    return 0


def _cmd_audit(args) -> int:
    found = audit_usd(args.usd)
    print(f"{args.usd}: {found.line(args.thickness)}")
    close = args.thickness is not None and any(d < 0.5 * args.thickness for d in found.min_distance)
    return EXIT_AUDIT if found.total_intersections or close else 0


def _cmd_run(args) -> int:
    def warn(message: str) -> None:
        print(f"warpspring: warning: {message}", file=sys.stderr)

    wp.config.log_level = wp.LOG_WARNING  # no init banner or module-load lines in CLI output
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecatedKeyWarning)  # printed once below, in the CLI's own form
        scene = load_scene(args.scene)
    for message in scene.deprecations:
        warn(message)
    device = args.device or scene.device
    if device is not None and str(device).startswith("cuda") and _CUDA_DRIVER_MISSING:
        raise ConfigError(f"device {device!r} is not available: Warp could not find or load the NVIDIA CUDA driver "
                          "on this machine; run on the CPU with --device cpu")
    if args.layer_over is not None:  # the writer's options: the layer over the asset
        scene.export_options = {**scene.export_options, "layer_over": args.layer_over, "layer_arc": args.layer_arc}
    live = LiveView(host=args.view_host, port=args.view_port, title=os.path.basename(args.scene)) if args.view else None
    if args.audit_workers > 1 and not args.audit_substeps:
        raise ConfigError("--audit-workers splits the substep audit between processes: add --audit-substeps")
    audit = SubstepAudit(workers=args.audit_workers) if args.audit_substeps else None
    summary = run_scene(
        scene,
        output=args.output,
        device=args.device,
        frames=args.frames,
        fps=args.fps,
        substeps=args.substeps,
        progress=not args.quiet,  # a bar on a terminal, else a line every few seconds (runner.PROGRESS_EVERY)
        strict=args.strict,
        warn=warn,
        watch=args.watch_every,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume,
        world=args.world,
        world_spacing=args.world_spacing,
        on_start=functools.partial(_on_start, live, audit),
        note=lambda line: print(line, flush=True),  # what the run chose by itself (substeps, contacts)
    )
    print(summary.line())
    if audit is not None:
        audit.close_workers()
        print(audit.line())
    if live is not None:  # (a run that fails ends the process, and the page's threads with it)
        if sys.stdin.isatty():  # someone is there to look: the page stays
            print(f"the run has ended; the viewer stays at {live.url} until Ctrl-C", flush=True)
            _serve_until_interrupted(live)
        else:
            live.close()
    return EXIT_AUDIT if audit is not None and not audit.clean else 0


def _on_start(live: LiveView | None, audit: SubstepAudit | None, sim, advice) -> None:
    if audit is not None:
        audit.attach(sim)
    if live is not None:
        live.attach(sim, advice)
        print(f"viewer at {live.url}", flush=True)


def _cmd_render(args) -> int:
    path = render_usd(args.usd, args.output, frame=args.frame, width=args.size)
    print(f"wrote {path}")
    return 0


def _cmd_trade(args) -> int:
    checks.output_dir(args.out)  # fail before the study runs, not after
    pyplot("the trade plots")
    wp.config.log_level = wp.LOG_WARNING
    device = checks.device(args.device)
    engine = _study_engine(args)
    study = trade.run_study(
        device,
        plan=trade_contact.study_plan(args.problems, quick=args.quick, reduced=args.reduced),
        integrators=args.integrators,
        progress=not args.quiet and sys.stderr.isatty(),
        **({} if engine is None else {"engine": engine}),
    )
    if engine is not None:
        engine.close()
    study.command = "warpspring " + " ".join(shlex.quote(a) for a in args.argv) if getattr(args, "argv", None) else ""
    paths = trade_report.write_report(study, args.out)
    for problem in study.plan.problems:
        if getattr(problem, "contact", False):
            ref = study.references[problem.name].convergence[-1]
            print(f"{problem.name}: reference's own difference {max(ref['error_horizon'], ref['hausdorff']):.2g} m")
            continue
        orders = trade_choice.convergence_orders(study, problem.name)
        fitted = ", ".join(f"{name} {'n/a' if p is None else f'{p:.2f}'}" for name, (p, _) in orders.items())
        print(f"{problem.name}: fitted orders {fitted}")
    unstable = sum(r.status in ("non-finite", "blown up", "stopped") for r in study.rows)
    skipped = sum(r.status == "skipped" for r in study.rows)
    print(
        f"measured {len(study.rows)} configurations ({unstable} unstable or stopped by the guard, {skipped} skipped "
        "as too slow) on "
        f"{study.device} ({study.device_name}) in {study.elapsed:.0f} s; wrote {', '.join(paths)}"
    )
    return 0


def _cmd_choose(args) -> int:
    choice = trade_choice.choose(trade_report.read_csv(args.study), args.error, time_budget=args.budget, problem=args.problem)
    print(choice.explanation)
    row = choice.row
    met = (row is not None and row.error_max is not None and row.error_max <= args.error
           and (args.budget is None or row.wall_per_second <= args.budget))
    return 0 if met else EXIT_NO_CHOICE


def _cmd_stability(args) -> int:
    checks.output_dir(args.out)  # fail before the map runs, not after
    if args.report is not None:
        _check_report_path(args.report)
    if args.battery is not None:
        unknown = [s for s in args.battery if s not in load_battery.SCENES]
        if unknown:
            raise ConfigError(f"unknown battery scene {unknown[0]!r}: choose from {', '.join(load_battery.SCENES)}")
    pyplot("the stability plots")
    wp.config.log_level = wp.LOG_WARNING
    started = time.perf_counter()
    engine = _study_engine(args)
    on_ray = {} if engine is None else {"engine": engine}
    plan = stability_map.QUICK if args.quick else stability_map.FULL
    result = stability_map.run_map(plan, checks.device(args.device), integrators=args.integrators, **on_ray)
    if engine is not None:
        engine.close()
    paths = stability_map_report.write_report(result, args.out)
    report = paths[0]  # OUT/stability.md
    if args.report is not None and os.path.abspath(args.report) != os.path.abspath(report):
        with open(args.report, "w") as f:
            f.write(stability_map_report.to_markdown(result))
        report = args.report
    for line in stability_summary(result):
        print(line)
    if args.battery is not None:
        paths.append(_battery(args, checks.device(args.device)))
    print(f"full report: {report}; also wrote {', '.join(p for p in paths if p != report)} "
          f"in {time.perf_counter() - started:.1f} s")
    return 0


def _battery(args, device) -> str:
    """Run the advisor-under-load battery for ``warpspring stability --battery``: one line per case as it
    ends, a summary line, and the table in OUT/battery.md (its path is returned)."""
    scenes = args.battery or list(load_battery.SCENES)
    names = [n for n in (args.integrators or load_battery.EXPLICIT) if n in load_battery.EXPLICIT]
    worlds, seconds = (6, 2.0) if args.quick else (32, 10.0)
    cases = []
    for scene in scenes:
        for name in names:
            for substeps in load_battery.STEPS[name][:1] if args.quick else load_battery.STEPS[name]:
                cases.append(load_battery.run_case(scene, name, substeps, device, worlds=worlds, seconds=seconds,
                                                   linear=not args.quick))
                print(f"  battery: {load_battery.table(cases[-1:])[2]} ({cases[-1].seconds:.0f} s)", flush=True)
    path = os.path.join(args.out, "battery.md")
    header = (f"# The advisor under load\n\n`warpspring stability --battery {' '.join(scenes)}"
              f"{' --quick' if args.quick else ''}` on {device}, Warp {wp.__version__}, {datetime.date.today()}: "
              f"the 20 × 20 cloth of warpspring/analysis/load_battery.py, {worlds} stiffnesses per grid as worlds, "
              f"two grids, {seconds:g} s runs.\n\n")
    with open(path, "w") as f:
        f.write(header + "\n".join(load_battery.table(cases)) + "\n")
    ratios = [c.ratio for c in cases if c.ratio == c.ratio]
    unsafe = sum(c.unsafe for c in cases)
    spread = f"advisor / blow-up {min(ratios):.3f} … {max(ratios):.3f}" if ratios else "no blow-up in the grids"
    lowest = [c.ratio_to_limit for c in cases if c.linear == c.linear or c.grows == c.grows]
    if lowest:
        spread += f", advisor / the lowest of blow-up and linear limits {min(lowest):.3f} … {max(lowest):.3f}"
    print(f"  advisor under load: {len(cases)} cases, {spread}, {unsafe} passed world(s) blew up")
    return path


def stability_summary(result) -> list[str]:
    """A few lines on a stability map (:class:`~warpspring.analysis.stability_map.StabilityMap`): how the
    measured limits compare with theory and the advisor, and the seed case; the tables go to the report."""
    lines = [f"stability map on {result.device}:"]

    def spread(pairs) -> str:  # measured / predicted over the two-sided brackets
        ratios = [m.value / p for m, p in pairs if m is not None and m.two_sided and 0.0 < p < float("inf")]
        if not ratios:
            return "no two-sided bracket to compare"
        return f"measured / predicted {min(ratios):.4f} … {max(ratios):.4f} over {len(ratios)} cases"

    if result.springs:
        lines.append(f"  one damped spring, largest stable ωh: {spread((r.measured, r.theory) for r in result.springs)} "
                     "(theory)")
    if result.cloth:
        stiffness = [r.stiffness for r in result.cloth]
        lines.append(f"  cloth, ke {min(stiffness):.0e} … {max(stiffness):.0e} N/m, largest stable dt: "
                     f"{spread((r.measured, r.predicted) for r in result.cloth)} (advisor)")
    seed = result.seed
    if seed is not None:
        t = seed.threshold
        lines.append(f"  seed case: RK4 threshold measured at {t.low:.4g} … {t.high:.4g} N/m for dt = {seed.dt:.4g} s")
    return lines


def _check_report_path(path: str) -> None:
    """Refuse a ``--report`` path that cannot be written, before the study runs."""
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.isdir(path):
        raise ConfigError(f"--report {path!r} is a folder: name a file")
    if not os.path.isdir(folder):
        raise ConfigError(f"--report {path!r}: the folder {folder} does not exist")
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ConfigError(f"--report {path!r} cannot be written: {os_error_reason(exc)}") from None


def init_warp(device: str | None = None) -> None:
    """Initialise Warp for a command: without its banner, and without its CUDA-driver warning (printed by its
    native library on a machine without an NVIDIA driver, where it concerns nothing a CPU run does) unless
    ``device`` names a CUDA device. Every other line Warp prints while it initialises is passed on to stderr.
    A no-op once Warp is initialised."""
    global _CUDA_DRIVER_MISSING
    wp.config.log_level = wp.LOG_WARNING
    if _warp_initialized():
        return
    if device is not None and str(device).startswith("cuda"):
        wp.init()  # the driver's absence is news to a CUDA run
        return
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            wp.init()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        sink.seek(0)
        printed = sink.read().decode(errors="replace")
    for line in printed.splitlines(keepends=True):
        if CUDA_DRIVER_WARNING in line:
            _CUDA_DRIVER_MISSING = True
        else:
            sys.stderr.write(line)


#: Whether :func:`init_warp` held back Warp's CUDA-driver warning (no NVIDIA driver on this machine).
_CUDA_DRIVER_MISSING = False


def _warp_initialized() -> bool:
    """Whether Warp's runtime exists already (then ``wp.init()`` prints nothing)."""
    try:
        from warp._src import context
    except ImportError:  # older Warp layouts
        from warp import context
    return getattr(context, "runtime", None) is not None


def os_error_line(error: OSError) -> str:
    """An OS error on one line, never without its reason: an :class:`OutputError`'s own message; else the OS's
    words with the errno name and the file ("No space left on device [ENOSPC]: out.usdc"), or its text."""
    if isinstance(error, OutputError):
        return " ".join(str(error).split()) or os_error_reason(error)
    if error.strerror:
        files = [f for f in (error.filename, error.filename2) if f]
        return os_error_reason(error) + (f": {' -> '.join(map(str, files))}" if files else "")
    return os_error_reason(error)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``warpspring`` command; returns the exit status (also for bad arguments and --help;
    the codes are listed in this module's docstring)."""
    try:
        args = build_parser().parse_args(argv)
        args.argv = list(sys.argv[1:] if argv is None else argv)  # the command line, for the results files
    except SystemExit as exc:  # argparse has printed its message (or the help)
        return exc.code if isinstance(exc.code, int) else EXIT_CONFIG if exc.code else 0
    try:
        if args.command in ("run", "trade", "stability", "sweep", "fit"):
            init_warp(args.device)
        return args.handler(args)
    except ConfigError as exc:
        print(f"warpspring: error: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    except SimulationError as exc:
        print(f"warpspring: simulation failed: {exc}", file=sys.stderr)
        return EXIT_SIMULATION
    except OSError as exc:  # a disk that fills up or a file that vanishes while writing
        print(f"warpspring: output failed: {os_error_line(exc)}", file=sys.stderr)
        return EXIT_IO
    except (RuntimeError, MemoryError) as exc:
        if not out_of_memory(exc):
            raise
        print(f"warpspring: error: out of memory: {' '.join(str(exc).split()) or type(exc).__name__}; the "
              "model and the run's buffers do not fit: use a smaller cloth, precision float32 or fewer worlds "
              "(warpspring.estimate_memory estimates what a scene needs)", file=sys.stderr)
        return EXIT_CONFIG
    except KeyboardInterrupt:
        print("warpspring: interrupted; the output holds every frame written so far", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
