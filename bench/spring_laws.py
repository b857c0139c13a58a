"""The cost of spring laws and plasticity: the hanging cloth of ``bench/cloth.py`` with its springs linear
(the reference), square with a softer compression branch, plastic, and both, side by side in one process.

Variants per size: the reference cloth (structural, shear and bend springs, ke = 1e3 N/m); every spring
square (k = 1e5 N/m², as stiff as the linear ke at a 5 mm stretch) with compression stiffness k/4 (the
per-spring law arrays join the spring struct); every spring plastic (yield strain 0.05, hardening 1, the
post-step pass over every spring each substep); and square and plastic together. Symplectic Euler, 16
substeps per frame, each frame one graph; the steady rate is the median of timed batches
(``cloth.measure``). Reported: substeps/s of each and the share of a substep the variant adds,
1 − rate(variant) / rate(reference).

    python bench/spring_laws.py --device cpu --sizes 32 64
    python bench/spring_laws.py --device cuda:0 --sizes 64 256 1024
"""

from __future__ import annotations

import argparse
import datetime

import numpy as np
import warp as wp

import warpspring as ws
from cloth import FPS, KD, KE, MASS, SPACING, SUBSTEPS, WarpspringRunner, emit_table, measure

#: The square law's k [N/m²]: its tangent 2k|Δ| equals the reference ke at a stretch of 5 mm.
SQUARE_K = KE / (2.0 * 0.005)
PLASTICITY = ws.SpringPlasticity(yield_strain=0.05, hardening=1.0)


def cloth_model(n: int, device, *, square: bool, plastic: bool) -> ws.Model:
    """The reference cloth with every spring family square (compression k/4) and/or plastic."""
    options = {}
    if square:
        options.update(law="square", compression_ke=0.25 * SQUARE_K)
    if plastic:
        options.update(plasticity=PLASTICITY)
    spring = ws.SpringMaterial(ke=SQUARE_K if square else KE, kd=KD, **options)
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=n, ny=n, spacing=SPACING, origin=(0.0, 0.0, 0.5 * n * SPACING),
                           rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), particle_mass=MASS,
                           structural=spring, shear=spring, bend=spring, pin=["top-left", "top-right"])
    return builder.finalize(device)


VARIANTS = {
    "linear": dict(square=False, plastic=False),
    "square + compression": dict(square=True, plastic=False),
    "plastic": dict(square=False, plastic=True),
    "square + plastic": dict(square=True, plastic=True),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default=None)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--seconds", type=float, default=1.0, help="timed seconds per variant and size")
    parser.add_argument("--out", default=None, help="also write the Markdown table to this file")
    args = parser.parse_args()
    wp.config.quiet = True
    device = wp.get_device(args.device)
    rows = []
    for n in args.sizes:
        rates = {}
        for name, switches in VARIANTS.items():
            make = lambda: WarpspringRunner(cloth_model(n, device, **switches))  # noqa: E731
            rates[name] = SUBSTEPS / measure(make, device, args.seconds)["frame_s"]
        base = rates["linear"]
        rows.append(f"| {n}² | {base:,.0f} | " + " | ".join(
            f"{rates[name]:,.0f} | {1 - rates[name] / base:.0%}" for name in list(VARIANTS)[1:]) + " |")
        print(rows[-1], flush=True)
    name = device.name if device.is_cuda else "CPU"
    lines = [
        f"`python bench/spring_laws.py --device {device} --sizes {' '.join(map(str, args.sizes))}` — {name}, Warp "
        f"{wp.__version__}, {datetime.date.today().isoformat()}; symplectic Euler, {SUBSTEPS} substeps per "
        f"1/{FPS} s frame, one graph per frame",
        "",
        "| cloth | linear [substeps/s] | square + compression [substeps/s] | share | plastic [substeps/s] | share | "
        "square + plastic [substeps/s] | share |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
