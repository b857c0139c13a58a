"""The Cusick drape test by simulation (``warpspring.analysis.drape``): the drape coefficient's convergence as
the spacing goes from c/2 to c/8 (c the material's bending length), three perturbed starts each, for
materials from light to stiff; prints the table, writes it into bench/results/cloth_materials.md and a
picture (top view of the shadow and side view) of each material's finest drape.

Scene (the issue's): specimen radius 0.15 m on a pedestal (closed mesh cylinder) of radius 0.09 m,
friction 0.5, contact radius 1 mm at every spacing; symplectic Euler at its stability step (h ω_max ≤ 1.6, ω_max
by Gershgorin) with a drag of 20 /s as a rate (``--damping-rate``) until the kinetic energy is below 1e-6 J and
no particle moved 0.1 mm in the last 0.1 s (at most ``--max-time`` s). Starts: the flat cloth raised by uniform
random heights below 0.1 mm, seeds 0, 1, 2. Reported per spacing: the mean drape coefficient, its spread
(max - min) over the starts, the folds of each start, the largest final kinetic energy, creep and imbalance (the
force no Coulomb contact can balance over the weight: 0 at an equilibrium), the substeps and the simulated time;
and whether the two finest means are within ±0.02; for a preset with a measured drape coefficient
(``material.MEASURED_DRAPE``), the error of each spacing's mean against it. ``--integrator implicit_euler`` runs the former settling
(4 substeps, solves to 1e-7), whose settled states are not equilibria (imbalance ~200: analysis/drape.py);
The hinges are ``grid_hinges``' straight layout (no checkerboard mode); ``--hinges crossed`` runs the material
grid's crossed hinges and ``--hinges triangles`` the triangles' own hinges (the bending before those).
``--folds n`` starts from n lobes instead (the coefficient of an n-fold drape at each spacing: the random starts
settle with different numbers of folds, and the coefficient follows them); ``--precision float64`` runs the model
in float64. Each invocation writes its own section (keyed by its options) and prints each row's wall time.

    python bench/drape.py --device cuda:0        # silk, study, cotton_polyester at c/2, c/4, c/8, seeds 0 1 2
    python bench/drape.py --device cuda:0 --materials silk --fractions 8                     # one material, one spacing
    python bench/drape.py --device cuda:0 --materials study silk cotton_polyester --seeds 0 --folds 8
    python bench/drape.py --device cuda:0 --hinges crossed --materials study
    python bench/drape.py --device cuda:0 --hinges triangles --materials study
    python bench/drape.py --device cuda:0 --materials study --contact-radius 0     # radius = spacing / 4
    python bench/drape.py --device cpu --materials study --fractions 1 2 --seeds 0   # a small check
    python bench/drape.py --device cuda:0 --materials polyester_twill polyester_plain wool_blend_twill \
        polyester_viscose_twill polyester_elastane_plain cotton_blend_twill --fractions 2 4 8   # against measured DCs
    python bench/drape.py --device cpu --materials study --spacings 0.015 0.0075 --seeds 0 --integrator implicit_euler --hinges crossed --drag 2e-3 --fixed-time 1.5
"""

from __future__ import annotations

import argparse
import datetime
import pathlib
import time

import numpy as np
import warp as wp
from d1388 import MATERIALS, write_section

import warpspring as ws
from warpspring.analysis import drape, elastica
from warpspring.core.material import MEASURED_DRAPE

PICTURES = pathlib.Path(__file__).parent / "results"


def picture(result: drape.Drape, path: pathlib.Path, title: str) -> None:
    import matplotlib  # optional: matplotlib (the picture only)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # optional: matplotlib

    q = result.positions
    fig, (top, side) = plt.subplots(1, 2, figsize=(10, 5))
    top.tripcolor(q[:, 0], q[:, 1], result.faces, q[:, 2], shading="gouraud", cmap="viridis")
    top.add_patch(plt.Circle((0.0, 0.0), 0.09, fill=False, color="w", lw=1))
    top.set_aspect("equal")
    top.set_title(f"{title}: DC {result.coefficient:.3f}, {result.folds} folds")
    side.scatter(q[:, 0], q[:, 2], s=0.2, c="k")
    side.set_aspect("equal")
    side.set_title("side view (x, z) [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--materials", nargs="+", default=["silk", "study", "cotton_polyester"], choices=list(MATERIALS))
    parser.add_argument("--fractions", type=int, nargs="+", default=[2, 4, 8], help="spacing = c / fraction")
    parser.add_argument("--spacings", type=float, nargs="+", help="spacings [m] instead of --fractions")
    parser.add_argument("--drag", type=float, default=0.0, help="per-particle drag [N·s/m] (default none)")
    parser.add_argument("--fixed-time", type=float, help="stop at this time [s], settled or not")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--hinges", default="straight", choices=["straight", "crossed", "triangles"])
    parser.add_argument("--max-time", type=float, default=10.0, help="most simulated seconds per run")
    parser.add_argument("--contact-radius", type=float, default=1.0e-3,
                        help="particles' contact radius [m]; 0: a quarter of the spacing (the builder's default)")
    parser.add_argument("--integrator", default="symplectic_euler", choices=["symplectic_euler", "implicit_euler"],
                        help="symplectic Euler at its stability step (default) or implicit Euler, whose settled states "
                             "are not equilibria (analysis/drape.py)")
    parser.add_argument("--damping-rate", type=float, default=20.0,
                        help="symplectic Euler's drag as a rate [1/s] (drag = rate x an interior particle's mass)")
    parser.add_argument("--substeps", type=int,
                        help="steps per 1/60 s frame (default: symplectic Euler's stability step from the Gershgorin "
                             "bound; implicit Euler 4)")
    parser.add_argument("--rim-radius", type=float, default=0.0,
                        help="the pedestal's rim rounded to this radius [m] (default 0: a sharp rim, the standard's)")
    parser.add_argument("--cg-tolerance", type=float, default=1.0e-7,
                        help="implicit solve's relative residual (a run stops where a solve ends above it)")
    parser.add_argument("--cg-iterations", type=int, default=5000, help="implicit solve's iteration cap")
    parser.add_argument("--precision", default="float32", choices=["float32", "float64"],
                        help="the model's precision (float64: positions and forces without float32's round-off, which at "
                             "c/8 exceeds a particle's weight in the stiff springs' forces)")
    parser.add_argument("--folds", type=int, default=0,
                        help="start the skirt with this many lobes, 5 mm deep at the hem (cusick's folds): the coefficient "
                             "of an n-fold drape at each spacing (default 0: the random starts only)")
    parser.add_argument("--no-picture", action="store_true")
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    rows, verdicts = [], []
    for name in args.materials:
        material = MATERIALS[name]
        c = elastica.bending_length(material.bending, material.density)
        means = []
        spacings = args.spacings or [c / fraction for fraction in args.fractions]
        for spacing in spacings:
            runs, stopped, start = [], [], time.perf_counter()
            for seed in args.seeds:
                try:
                    runs.append(drape.cusick(material, spacing=spacing, seed=seed, hinges=args.hinges,
                                             contact_radius=args.contact_radius or 0.25 * spacing, drag=args.drag,
                                             fixed_time=args.fixed_time, max_time=args.max_time,
                                             substeps=args.substeps, integrator=args.integrator,
                                             damping_rate=args.damping_rate, rim_radius=args.rim_radius,
                                             cg_tolerance=args.cg_tolerance,
                                             cg_iterations=args.cg_iterations, precision=args.precision,
                                             folds=args.folds, device=device))
                except ws.SimulationError as error:  # a run that stopped is reported, not averaged
                    stopped.append(f"- {name} at {spacing * 1e3:.2f} mm, seed {seed}: stopped: {error}")
                    print(stopped[-1], flush=True)
            verdicts.extend(stopped)
            if not runs:
                continue
            dc = np.array([r.coefficient for r in runs])
            means.append(dc.mean() if not stopped else float("nan"))
            rows.append(f"| {name} | {c * 1e3:.2f} | c/{c / spacing:.2f} = {spacing * 1e3:.2f} | {dc.mean():.4f} | "
                        f"{np.ptp(dc):.4f} | {', '.join(str(r.folds) for r in runs)} | "
                        f"{max(r.kinetic_energy for r in runs):.1e} | {max(r.creep for r in runs) * 1e3:.3f} | "
                        f"{max(r.imbalance for r in runs):.3f} | {runs[0].substeps} | "
                        f"{max(r.time for r in runs):.2f} | "
                        f"{time.perf_counter() - start:.0f} |")
            print(rows[-1], flush=True)
            if name in MEASURED_DRAPE:
                measured = MEASURED_DRAPE[name]
                verdicts.append(f"- {name} at {spacing * 1e3:.2f} mm (c/{c / spacing:.2f}): DC {dc.mean():.3f} "
                                f"({', '.join(str(r.folds) for r in runs)} folds) against the measured {measured:.3f}: "
                                f"error {dc.mean() - measured:+.3f} ({dc.mean() / measured - 1.0:+.0%})")
                print(verdicts[-1], flush=True)
            if spacing == spacings[-1] and not args.no_picture:
                path = PICTURES / (f"drape_{name}_{args.hinges}_c{round(c / spacing)}" + (f"_n{args.folds}" if args.folds else "")
                                   + f"_{device.alias.replace(':', '')}.png")
                try:
                    picture(runs[0], path, f"{name}, spacing {spacing * 1e3:.2f} mm")
                    print("wrote", path)
                except ImportError:  # a machine without the plot extra still gets its table
                    print("no picture: matplotlib is not installed (pip install -e .[plot])")
        if len(means) >= 2:
            change = means[-1] - means[-2]
            verdicts.append(f"- {name}: DC {means[-1]:.3f} at {spacings[-1] * 1e3:.2f} mm; change from "
                            f"{spacings[-2] * 1e3:.2f} mm: {change:+.4f} "
                            f"({'within' if abs(change) <= 0.02 else 'outside'} ±0.02)")
    grid = (f"--spacings {' '.join(map(str, args.spacings))}" if args.spacings
            else f"--fractions {' '.join(map(str, args.fractions))}")
    command = (f"python bench/drape.py --device {args.device} --materials {' '.join(args.materials)} {grid} "
               f"--seeds {' '.join(map(str, args.seeds))} --integrator {args.integrator}"
               + (f" --substeps {args.substeps}" if args.substeps else "")
               + (f" --damping-rate {args.damping_rate:g}" if args.integrator == "symplectic_euler" else
                  f" --cg-tolerance {args.cg_tolerance:g} --cg-iterations {args.cg_iterations}")
               + f" --hinges {args.hinges} --contact-radius {args.contact_radius}"
               + f" --max-time {args.max_time:g}" + (f" --precision {args.precision}" if args.precision != "float32" else "")
               + (f" --folds {args.folds}" if args.folds else "")
               + (f" --rim-radius {args.rim_radius:g}" if args.rim_radius else "")
               + (f" --drag {args.drag}" if args.drag else "") + (f" --fixed-time {args.fixed_time}" if args.fixed_time else ""))
    text = "\n".join([
        f"## Cusick drape coefficient against resolution ({args.integrator}, {args.hinges} hinges, contact radius "
        f"{args.contact_radius or 'spacing/4'}, {args.precision})",
        "",
        f"`{command}` — {device.name} ({device.alias}), Warp {wp.config.version}, {datetime.date.today()}",
        "",
        "| material | c [mm] | spacing [mm] | DC mean | spread | folds per start | max KE [J] | max creep [mm/0.1 s] "
        "| max imbalance | substeps | max time [s] | wall [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        *verdicts,
    ])
    print(text)
    key = (f"drape-{args.hinges}-r{args.contact_radius:g}-d{args.drag:g}-t{args.fixed_time or 0:g}"
           + ("-se-" + "-".join(args.materials) + ("" if args.spacings else "-f" + "-".join(map(str, args.fractions)))
              if args.integrator == "symplectic_euler" else "") + (f"-rim{args.rim_radius:g}" if args.rim_radius else "")
           + ("-f64" if args.precision == "float64" else "") + (f"-n{args.folds}" if args.folds else ""))
    write_section(f"{key}-{'s' if args.spacings else 'c'}-{device.alias.replace(':', '')}", text)


if __name__ == "__main__":
    main()
