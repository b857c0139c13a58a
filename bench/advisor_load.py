"""The stability advisor under load: where a cloth really blows up, against the largest stiffness the
advisor (``warpspring stability``, ``--strict``) passes, for every explicit integrator at two steps.

Scenes, each a 20 × 20 cloth of 0.1 kg particles 0.1 m apart hanging in the xz plane from its two top
corners, structural springs only (kd = 0.01 N·s/m), gravity:

* ``hanging``: as it is (the cloth of the "trustworthy runs" report);
* ``forced``: plus a steady sideways push of 0.5 N on every particle through ``Control`` (half its weight);
* ``driven``: its two corners carried by a handle on a track, ±0.1 m sideways at 1 Hz.

Protocol. Each stiffness is one world of one model, run for ``--seconds`` (10 s) with the default guard
stopping only the failing world (``GuardLimits(stop="world")``). A world *blows up* when the guard stops
it (non-finite state, torn spring, runaway kinetic energy, or energy created by the integration beyond the
balance's tolerance) or its state is non-finite. Worlds that fail below the lowest surviving stiffness
tear because the cloth is too soft for its weight (physical over-stretch), not because of the step: they
are listed, not counted. The advisor's verdict per world is ``advise(...)`` as ``--strict`` uses it
(linearised about the static equilibrium under the loads; the pins at their t = 0 place). Bisection on ke,
done in parallel: a first grid of ``--worlds`` stiffnesses over a factor ``--span`` around the limit the
advisor finds at rest, then a second over ±10 % around the two transitions found. Reported: the smallest
stiffness that blew up, the largest the advisor passes, their ratio (1 = exact, < 1 conservative), and how
many worlds the advisor passed that blew up (must be 0).

    python bench/advisor_load.py --device cpu --integrators rk4 --substeps 1 --scenes hanging
    python bench/advisor_load.py --device cuda:0                        # the whole battery
"""

import argparse
import datetime
import time

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.analysis.stability import advise

from cloth import emit_table

EXPLICIT = ["explicit_euler", "symplectic_euler", "velocity_verlet", "midpoint", "rk4"]
#: Two steps per integrator (substeps of a 1/60 s frame), chosen so that the limit lies above the
#: stiffness at which the cloth tears by its own weight (~300 N/m).
STEPS = {"explicit_euler": (2000, 8000), "symplectic_euler": (2, 8), "velocity_verlet": (2, 8), "midpoint": (2, 8),
         "rk4": (1, 4)}
SCENES = ("hanging", "forced", "driven")
PUSH = 0.5  # [N] per particle, sideways (forced)
SHAKE = 0.1  # [m] amplitude of the handle, 1 Hz (driven)


def cloth(scene: str, worlds: int, device, *, n: int = 20) -> ws.Model:
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    grid = dict(nx=n, ny=n, spacing=0.1, particle_mass=0.1, structural=ws.SpringMaterial(ke=1.0, kd=0.01),
                shear=None, bend=None, rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2))
    if scene == "driven":
        ids = builder.add_cloth_grid(**grid)
        shake = ws.Track([0.0, 0.25, 0.5, 0.75, 1.0], [[0, 0, 0], [0, SHAKE, 0], [0, 0, 0], [0, -SHAKE, 0], [0, 0, 0]],
                         interpolation="smooth", extrapolation="cycle")
        builder.add_pin_group([ids[-1, 0], ids[-1, -1]], translation=shake, name="handle")  # row ny-1: the top
    else:
        builder.add_cloth_grid(**grid, pin=["top-left", "top-right"])
    return builder.finalize(device, worlds=worlds)


def control_for(scene: str, model: ws.Model) -> ws.Control:
    control = model.control()
    if scene == "forced":
        control.set_particle_force([0.0, PUSH, 0.0])
    return control


def with_stiffness(scene: str, ke: np.ndarray, device) -> ws.Model:
    model = cloth(scene, len(ke), device)
    model.set_world_values("spring_stiffness", ke[:, None] * np.ones((1, model.spring_count)))
    return model


def advisor_passes(scene: str, integrator: str, dt: float, ke: np.ndarray, device) -> np.ndarray:
    model = with_stiffness(scene, ke, device)
    return dt <= advise(model, integrator, dt, fps=60.0, control=control_for(scene, model)).world_dt_stable


def blow_ups(scene: str, integrator: str, substeps: int, ke: np.ndarray, device, seconds: float) -> tuple:
    """(blown up, torn) per world."""
    model = with_stiffness(scene, ke, device)
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60.0, substeps=substeps,
                       control=control_for(scene, model), guard=ws.GuardLimits(stop="world"))
    try:
        for _ in range(int(round(seconds * 60))):
            sim.step_frame()
    except ws.SimulationError:
        pass  # every world failed
    q = sim.state.particle_q.numpy().reshape(len(ke), -1, 3)
    failed = np.array([w in sim.world_failures or not np.isfinite(q[w]).all() for w in range(len(ke))])
    alive = np.flatnonzero(~failed)
    torn = failed & (np.arange(len(ke)) < (alive.min() if len(alive) else len(ke)))
    return failed & ~torn, torn


def at_rest_limit(integrator: str, dt: float, device) -> float:
    """The stiffness [N/m] the advisor passes linearised at rest (ω_max ∝ √ke: one evaluation)."""
    ke = 1000.0
    model = with_stiffness("hanging", np.array([ke]), device)
    advice = advise(model, integrator, dt, fps=60.0, loaded=False)
    if not np.isfinite(advice.dt_stable) or advice.dt_stable <= 0.0:
        return float("nan")
    return ke * (advice.dt_stable / dt) ** 2


def case(scene: str, integrator: str, substeps: int, *, worlds: int, span: float, seconds: float, device) -> dict:
    dt = 1.0 / (60.0 * substeps)
    guess = at_rest_limit(integrator, dt, device)
    t0 = time.perf_counter()
    result = {"scene": scene, "integrator": integrator, "dt": dt, "passed": 0.0, "blow_up": np.inf, "unsafe": 0,
              "torn": 0.0, "note": ""}
    if not np.isfinite(guess):
        result["note"] = "the advisor finds no stable step for these springs"
        return result
    low, high = guess / span, guess * span ** 0.25
    for stage in range(2):
        ke = np.geomspace(low, high, worlds)
        passes = advisor_passes(scene, integrator, dt, ke, device)
        blown, torn = blow_ups(scene, integrator, substeps, ke, device, seconds)
        result["unsafe"] += int((passes & blown).sum())
        if torn.any():
            result["torn"] = max(result["torn"], float(ke[torn].max()))
        if (passes & ~torn).any():
            result["passed"] = max(result["passed"], float(ke[passes & ~torn].max()))
        if blown.any():
            result["blow_up"] = min(result["blow_up"], float(ke[blown].min()))
        # The second grid: ±10 % around both transitions, or on past the first grid where one was not found.
        found = [v for v in (result["passed"], result["blow_up"]) if 0.0 < v < np.inf]
        low = min(found) / 1.1 if result["passed"] > 0.0 else low / span
        high = max(found) * 1.1 if np.isfinite(result["blow_up"]) else high * span
    result["seconds"] = time.perf_counter() - t0
    return result


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--integrators", nargs="+", default=EXPLICIT, choices=EXPLICIT)
    parser.add_argument("--substeps", type=int, nargs="+", default=None,
                        help="substeps per 1/60 s frame (default: two per integrator, STEPS)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--worlds", type=int, default=32)
    parser.add_argument("--span", type=float, default=4.0, help="the first grid spans guess/span .. guess·span^¼")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    device = wp.get_device(args.device)
    lines = [
        f"Advisor under load on {device.name}, Warp {wp.config.version}, {datetime.date.today()}: 20 × 20 cloth, "
        f"{args.worlds} stiffnesses per grid as worlds, two grids, {args.seconds:g} s runs",
        "",
        "| scene | integrator | dt | blows up from ke | advisor passes up to | ratio | passed but blew up |",
        "|---|---|---|---|---|---|---|",
    ]
    worst = []
    for scene in args.scenes:
        for name in args.integrators:
            for substeps in args.substeps or STEPS[name]:
                r = case(scene, name, substeps, worlds=args.worlds, span=args.span, seconds=args.seconds, device=device)
                ratio = r["passed"] / r["blow_up"] if np.isfinite(r["blow_up"]) else float("nan")
                worst.append((ratio, r["unsafe"]))
                blow = f"{r['blow_up']:.4g} N/m" if np.isfinite(r["blow_up"]) else "none in the grids"
                lines.append(f"| {scene} | {name} | 1/{60 * substeps} s | {blow} | {r['passed']:.4g} N/m | "
                             f"{ratio:.3f} | {r['unsafe']} |" + (f" {r['note']}" if r["note"] else ""))
                print(lines[-1], flush=True)
    ratios = [w[0] for w in worst if np.isfinite(w[0])]
    if ratios:
        lines += ["", f"Most conservative: {min(ratios):.3f}; worlds passed that blew up: {sum(w[1] for w in worst)}."]
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
