"""The stability advisor under load: where a hanging cloth really blows up, against the advisor's
verdict linearised at rest and at the static equilibrium.

The cloth of the "trustworthy runs" report: 20 × 20 particles 0.1 m apart, 0.1 kg each, structural springs
only (kd = 0.01 N·s/m), the two top corners pinned, gravity. Each stiffness is one world of one model (a
geometric grid of ``--worlds`` values of ke over ``--range``), run for ``--seconds`` with the default guard
stopping only the failing world (``GuardLimits(stop="world")``). Protocol: a world *blows up* when the guard
stops it or its state is non-finite. Worlds that fail below the lowest surviving stiffness tear because the
cloth is too soft for its weight (physical over-stretch), not because of the step: they are listed, not
counted. Reported per integrator and step: the smallest stiffness that blew up, the largest the advisor
passes (``advise(..., loaded=False)``: linearised about the initial state; ``loaded=True``: about the
static equilibrium), and how many worlds the advisor passed that blew up (must be 0).

    python bench/advisor_load.py --device cpu --integrators rk4 --fps 60 --range 300 1500
"""

import argparse
import datetime
import time

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.analysis.stability import advise

from cloth import emit_table


def hanging_cloth(worlds: int, device, *, n: int = 20) -> ws.Model:
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, particle_mass=0.1, structural=ws.SpringMaterial(ke=1.0, kd=0.01),
                           shear=None, bend=None, rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2),
                           pin=["top-left", "top-right"])
    return builder.finalize(device, worlds=worlds)


def battery(integrator: str, fps: float, substeps: int, ke_range, *, worlds: int, seconds: float, device) -> dict:
    model = hanging_cloth(worlds, device)
    ke = np.geomspace(*ke_range, worlds)
    model.set_world_values("spring_stiffness", ke[:, None] * np.ones((1, model.spring_count)))
    dt = 1.0 / (fps * substeps)
    t0 = time.perf_counter()
    passed = {loaded: dt <= advise(model, integrator, dt, fps=fps, loaded=loaded).world_dt_stable
              for loaded in (False, True)}
    t1 = time.perf_counter()
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=fps, substeps=substeps,
                       guard=ws.GuardLimits(stop="world"))
    try:
        for _ in range(int(seconds * fps)):
            sim.step_frame()
    except ws.SimulationError:
        pass  # every world failed
    q = sim.state.particle_q.numpy().reshape(worlds, -1, 3)
    failed = np.array([w in sim.world_failures or not np.isfinite(q[w]).all() for w in range(worlds)])
    alive = np.flatnonzero(~failed)
    torn = failed & (np.arange(worlds) < (alive.min() if len(alive) else worlds))
    blown = failed & ~torn
    largest = {loaded: float(ke[ok & ~torn].max()) if (ok & ~torn).any() else 0.0 for loaded, ok in passed.items()}
    return {
        "integrator": integrator, "dt": dt, "ke": ke, "torn": ke[torn], "blow_up": float(ke[blown].min()) if blown.any() else np.inf,
        "rest": largest[False], "loaded": largest[True],
        "unsafe_rest": int((passed[False] & blown).sum()), "unsafe_loaded": int((passed[True] & blown).sum()),
        "advise_s": t1 - t0, "run_s": time.perf_counter() - t1,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--integrators", nargs="+", default=["rk4"])
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--substeps", type=int, default=1)
    parser.add_argument("--range", type=float, nargs=2, default=[300.0, 1500.0], metavar=("KE_MIN", "KE_MAX"))
    parser.add_argument("--worlds", type=int, default=24)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    lines = [
        f"Advisor under load on {device.name}, Warp {wp.config.version}, {datetime.date.today()}: 20 × 20 hanging "
        f"cloth, {args.worlds} stiffnesses in [{args.range[0]:g}, {args.range[1]:g}] N/m as worlds, {args.seconds:g} s runs",
        "",
        "| integrator | dt | blows up from ke | advisor at rest passes up to | (ratio) | advisor at equilibrium "
        "passes up to | (ratio) | passed but blew up (rest / equilibrium) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in args.integrators:
        r = battery(name, args.fps, args.substeps, args.range, worlds=args.worlds, seconds=args.seconds, device=device)
        lines.append(f"| {name} | {r['dt'] * 1e3:.4g} ms | {r['blow_up']:.4g} N/m | {r['rest']:.4g} N/m | "
                     f"{r['rest'] / r['blow_up']:.3f} | {r['loaded']:.4g} N/m | {r['loaded'] / r['blow_up']:.3f} | "
                     f"{r['unsafe_rest']} / {r['unsafe_loaded']} |")
        if len(r["torn"]):
            lines.append(f"<!-- {name}: torn by their weight (too soft): ke ≤ {r['torn'].max():.4g} N/m -->")
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
