"""Implicit Euler's CG: the iterations a solve needs by problem and step, against the automatic iteration cap
(``ImplicitEuler(cg_iterations=None)``, ``auto_iteration_cap``): a T10 and a linear-tet ball dropped on the ground and
the hanging cloth of the test suite, stepped with a cap that never binds. Results: ``bench/results/softbody_tet10.md``.

    python bench/implicit_cg.py --device cpu --out FILE
"""

from __future__ import annotations

import argparse
import datetime
import os

import numpy as np
import trimesh
import warp as wp

import warpspring as ws

RHO = 1000.0  # [kg/m³]
BALL = os.path.join(os.path.dirname(__file__), "..", "examples", "meshes", "ball.obj")
BALL_E, BALL_SPACING, BALL_DAMPING = 2.0e4, 0.05, 1.0e-3  # [Pa], [m], [s]: bench/softbody.py's dropped balls


def cg_study(device, *, steps: int = 25, dts=(1.0 / 60.0, 1.0 / 240.0)) -> str:
    """What implicit Euler's CG needs: the ball of the drop (Delaunay, E = 20 kPa, β = 1 ms) as T10 and as linear
    neo-Hookean tets, falling from 0.3 m onto the ground, and the 32 × 32 hanging cloth of the test suite (k = 1000
    N/m, 0.1 kg a particle, two corners pinned), ``steps`` steps of each ``dt`` [s] with a cap that never binds
    (20000) at the default tolerance 1e-5: the most and median iterations a solve took, against h ω_max (the
    Gershgorin bound) and the automatic cap (``auto_iteration_cap``) that the default ``cg_iterations=None``
    chooses."""
    from warpspring.core.integrators.implicit_euler import auto_iteration_cap, gershgorin_bound

    ball = trimesh.load(BALL, force="mesh", process=False)

    def ball_model(element):
        builder = ws.ModelBuilder()
        builder.add_soft_body(ball, method="delaunay", youngs_modulus=BALL_E, density=RHO, spacing=BALL_SPACING,
                              damping=BALL_DAMPING, origin=(0.0, 0.0, 0.5), elasticity="neohookean", element=element)
        builder.add_ground_plane(friction=0.5)
        return builder.finalize(device)

    def cloth_model():
        builder = ws.ModelBuilder()
        material = ws.SpringMaterial(1.0e3, 10.0)
        builder.add_cloth_grid(nx=32, ny=32, spacing=0.1, origin=(-1.55, -1.55, 1.0), particle_mass=0.1,
                               structural=material, shear=material, bend=material, pin=["top-left", "top-right"])
        return builder.finalize(device)

    cases = {"T10 ball (Delaunay)": lambda: ball_model("tet10"), "linear-tet ball (Delaunay)": lambda: ball_model("tet4"),
             "hanging cloth 32 × 32": cloth_model}
    lines = [
        f"Implicit Euler's CG iterations by problem and step, {datetime.date.today()}, Warp {wp.config.version}, "
        f"{device}: {steps} steps from rest, tolerance 1e-5, cap 20000 (never reached); h ω_max by the Gershgorin bound "
        "at the initial positions; the automatic cap ⌈ln(2/tol)(1 + h ω_max)⌉ ≥ 100.",
        "",
        "| problem | particles | h [ms] | h ω_max | most iterations | median | most / h ω_max | automatic cap |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, make in cases.items():
        model = make()
        omega = gershgorin_bound(model)
        for dt in dts:
            integrator = ws.make_integrator("implicit_euler", model, cg_iterations=20000, cg_unconverged="ignore")
            a, b = model.state(), model.state()
            iterations = []
            for _ in range(steps):
                integrator.step(a, b, None, dt)
                a, b = b, a
                iterations.append(integrator.solve_report()[0])
            lines.append(f"| {name} | {model.particle_count} | {1e3 * dt:.2f} | {dt * omega:.1f} | {max(iterations)} | "
                         f"{int(np.median(iterations))} | {max(iterations) / (dt * omega):.1f} | "
                         f"{auto_iteration_cap(dt * omega, 1e-5)} |")
            print(lines[-1], flush=True)
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--steps", type=int, default=25, help="steps per problem and step size")
    parser.add_argument("--out", default=None, help="write the table here too")
    args = parser.parse_args()
    wp.init()
    text = cg_study(args.device, steps=args.steps)
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "w") as f:
            f.write(text)
    print(text)


if __name__ == "__main__":
    main()
