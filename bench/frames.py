"""A frame's substeps in one launch against one launch per substep, for one world and many.

The ANCHORS hanging cloth of ``bench/cloth.py`` (n × n, hung from its top row, symplectic Euler, 16 substeps per
1/60 s frame, one captured graph per frame) as ``worlds`` worlds of one model, through the public API: a
``Simulator`` with ``SymplecticEuler(model, one_launch=True)`` beside ``one_launch=False``, with the default guard
(``GuardLimits()``: what a user gets) and with the guard off. The configurations' timed batches alternate (the
median of each configuration's batches, and the median of the per-round ratios); before timing, both paths run the
same frames and their positions are compared (they must be equal to the bit). The "auto" column says which path a
default ``SymplecticEuler(model)`` takes there.

    python bench/frames.py --device cuda:0 --sizes 32 --worlds 1 66 132 264 1056 4096 --out bench/results/frames.md
    python bench/frames.py --device cuda:0 --sizes 16 64 --worlds 1 264 1056
    python bench/frames.py --device cpu --sizes 16 32 --worlds 1 8
    python bench/frames.py --device cuda:0 --sizes 32 64 --worlds 1 1056 --scene flag  # pins, gusts, wind inside

``--scene flag`` times the same cloth as a flag on a moving pole in a gusting wind (driven pins, an animated input
and the aerodynamic family, which the one-launch frame evaluates inside).

``--fallbacks`` times instead what the features that keep a scene on one launch per substep cost: the contact
benchmark's cloth (``bench/contacts.py``) draped over a sphere on the ground, after its settling frames, with the
sphere analytic (the default path: one launch where the rule takes it), the same forced to one launch per substep
(``one_launch=False``: the fallback's own cost), the sphere as a triangle mesh (``core/mesh_colliders.py``) and the
analytic sphere with self-collision (τ = 0.02 m), each with the default guard and with it off, batches interleaved:

    python bench/frames.py --device cuda:0 --sizes 32 64 128 --fallbacks
"""

import argparse
import datetime
import statistics
import time

import numpy as np
import warp as wp

import warpspring as ws
from cloth_scene import FPS, SUBSTEPS, warpspring_model


def flag_model(n: int, device, worlds: int) -> ws.Model:
    """The hanging cloth as a flag on a moving pole: its top row a pin group carried along x and back by a smooth
    track (0.2 m over 1 s), the aerodynamic family in a wind whose gust track rises from 2 to 6 m/s and falls: what
    the one-launch frame now evaluates inside (driven pins, animated inputs, the wind)."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
    ids = builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(0.0, 0.0, 0.05 * n),
                                 rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), particle_mass=0.1,
                                 structural=spring, shear=spring, bend=spring, name="flag")
    top = np.asarray(ids).reshape(n, n)[-1]
    builder.add_pin_group(top, translation=ws.Track([0.0, 0.5, 1.0], [(0, 0, 0), (0.2, 0, 0), (0, 0, 0)],
                                                    interpolation="smooth", extrapolation="cycle"), name="pole")
    builder.add_aerodynamics(wind=(2.0, 3.0, 0.0))
    model = builder.finalize(device, worlds=worlds)
    model.set_track("wind", ws.Track([0.0, 0.5, 1.0], [(2.0, 3.0, 0.0), (6.0, 3.0, 0.0), (2.0, 3.0, 0.0)],
                                     interpolation="smooth", extrapolation="cycle"))
    return model


def simulator(n: int, worlds: int, device, *, one_launch, guard: bool, scene: str = "hanging") -> ws.Simulator:
    model = (warpspring_model(n, device, worlds=worlds, pin="top") if scene == "hanging"
             else flag_model(n, device, worlds))
    return ws.Simulator(model, integrator=ws.SymplecticEuler(model, one_launch=one_launch), fps=FPS,
                        substeps=SUBSTEPS, guard=ws.GuardLimits() if guard else None)


FALLBACK_VARIANTS = ("sphere (default path)", "sphere, one launch per substep", "mesh sphere", "sphere + self-collision")


def fallback_simulator(n: int, device, variant: str, guard: bool) -> ws.Simulator:
    """The draped cloth of ``bench/contacts.py`` with ``variant`` (one of FALLBACK_VARIANTS), settled."""
    from contacts import SETTLE_FRAMES, contact_model
    from selfcontact import scene

    if variant == "sphere + self-collision":
        model = scene(n, device, True)
    else:
        model = contact_model(n, device, "mesh" if variant == "mesh sphere" else "fused")
    integrator = ws.SymplecticEuler(model, one_launch=False if variant.endswith("per substep") else None)
    sim = ws.Simulator(model, integrator=integrator, fps=FPS, substeps=SUBSTEPS,
                       guard=ws.GuardLimits() if guard else None)
    for _ in range(SETTLE_FRAMES):
        sim.step_frame()
    sim.settle()
    return sim


def fallbacks(args, device) -> list[str]:
    """Markdown rows: µs per frame of each fallback variant against the default path, guard on and off."""
    lines = [
        f"What keeps the draped cloth on one launch per substep costs: µs per frame after the settling, {SUBSTEPS} "
        f"substeps per 1/{FPS} s frame, symplectic Euler. Device: {device.name} ({device.alias}); Warp {wp.__version__}; "
        f"{datetime.date.today().isoformat()}. `python bench/frames.py --device {args.device} --sizes "
        f"{' '.join(map(str, args.sizes))} --batches {args.batches} --fallbacks`",
        "",
        "| n² | guard | variant | path | µs per frame (median, spread) | ÷ the default path (median of rounds) |",
        "|---|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    for n in args.sizes:
        for guard in (True, False):
            sims = {variant: fallback_simulator(n, device, variant, guard) for variant in FALLBACK_VARIANTS}
            first = sims[FALLBACK_VARIANTS[0]]
            frames = max(3, int(args.seconds / max(timed(first, 3), 1e-6)))
            times = {variant: [] for variant in sims}
            for _ in range(args.batches):
                for variant, sim in sims.items():
                    times[variant].append(timed(sim, frames))
            for variant, sim in sims.items():
                shape = sim.stepper.integrator.frame_shape(sim.control, SUBSTEPS)
                path = "per substep" if shape is None else f"one launch {shape[0]}×{shape[1]}"
                t = times[variant]
                median = statistics.median(t)
                ratio = statistics.median(a / b for a, b in zip(t, times[FALLBACK_VARIANTS[0]]))
                row = (f"| {n}² | {'default' if guard else 'off'} | {variant} | {path} | {1e6 * median:.1f} "
                       f"({(max(t) - min(t)) / median:.0%}) | {ratio:.2f}× |")
                lines.append(row)
                print(row, flush=True)
    return lines


def timed(sim: ws.Simulator, frames: int) -> float:
    """Seconds per frame over ``frames`` frames (device synchronised before each timer read)."""
    wp.synchronize_device(sim.model.device)
    start = time.perf_counter()
    for _ in range(frames):
        sim.step_frame()
    wp.synchronize_device(sim.model.device)
    return (time.perf_counter() - start) / frames


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--sizes", type=int, nargs="+", default=[32])
    parser.add_argument("--worlds", type=int, nargs="+", default=[1, 264, 1056])
    parser.add_argument("--batches", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=0.3, help="timed seconds per batch and configuration")
    parser.add_argument("--scene", choices=["hanging", "flag"], default="hanging",
                        help="the hanging cloth, or the flag on a moving pole in a gusting wind (flag_model)")
    parser.add_argument("--fallbacks", action="store_true",
                        help="time what the features that force one launch per substep cost instead")
    parser.add_argument("--out", help="also write the Markdown table to this file")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    if args.fallbacks:
        lines = fallbacks(args, device)
        if args.out:
            with open(args.out, "w") as f:
                f.write("\n".join(lines) + "\n")
        return
    lines = [
        f"{'Hanging cloth' if args.scene == 'hanging' else 'Flag on a moving pole in a gusting wind'} as worlds of "
        f"one model, symplectic Euler, {SUBSTEPS} substeps per 1/{FPS} s frame. "
        f"Device: {device.name} ({device.alias}"
        + (f", {device.sm_count} multiprocessors" if device.is_cuda else "") + f"); Warp {wp.__version__}; "
        f"{datetime.date.today().isoformat()}. `python bench/frames.py --device {args.device} --sizes "
        f"{' '.join(map(str, args.sizes))} --worlds {' '.join(map(str, args.worlds))} --batches {args.batches} "
        f"--scene {args.scene}`",
        "",
        "| n² × worlds | guard | per substep [G particle-substeps/s] | one launch [G] | one launch ÷ per substep "
        "(median of rounds, spread) | auto takes | max \\|Δx\\| after 10 frames [m] |",
        "|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    for n in args.sizes:
        for worlds in args.worlds:
            for guard in (True, False):
                sims = {key: simulator(n, worlds, device, one_launch=key, guard=guard, scene=args.scene)
                        for key in (False, True)}
                for sim in sims.values():
                    for _ in range(10):
                        sim.step_frame()
                diff = float(np.abs(sims[True].state.particle_q.numpy() - sims[False].state.particle_q.numpy()).max())
                frame = timed(sims[False], 3)
                frames = max(3, int(args.seconds / max(frame, 1e-6)))
                times = {False: [], True: []}
                for _ in range(args.batches):
                    for key, sim in sims.items():
                        times[key].append(timed(sim, frames))
                work = n * n * worlds * SUBSTEPS
                rates = {key: work / statistics.median(t) / 1e9 for key, t in times.items()}
                ratios = [a / b for a, b in zip(times[False], times[True])]
                auto = ws.SymplecticEuler(sims[False].model).frame_shape(sims[False].control, SUBSTEPS)
                row = (f"| {n}² × {worlds} | {'default' if guard else 'off'} | {rates[False]:.3g} | {rates[True]:.3g} | "
                       f"{statistics.median(ratios):.2f}× ({min(ratios):.2f}-{max(ratios):.2f}) | "
                       f"{'per substep' if auto is None else f'one launch {auto[0]}×{auto[1]}'} | {diff:.3g} |")
                lines.append(row)
                print(row, flush=True)
    if args.out:
        with open(args.out, "w") as f:
            f.write("# A frame in one launch\n\n" + "\n".join(lines) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
