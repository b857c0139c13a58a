"""The cost of the wind: the hanging cloth of ``bench/cloth.py`` with and without aerodynamics, side by side in
one process.

Variants per size: the reference cloth (springs only); with aerodynamics on every triangle in a steady wind
(``add_aerodynamics``, the wind family gathered per particle with the springs); and with the spatial noise
compiled in as well. Symplectic Euler, 16 substeps per frame, each frame one graph; the steady rate is the
median of timed batches (``cloth.measure``). Reported: substeps/s of each and the share of a substep the
wind takes, 1 − rate(with) / rate(without).

    python bench/aero.py --device cuda:0 --sizes 64 256 1024
    python bench/aero.py --device cpu --sizes 32 64
"""

from __future__ import annotations

import argparse
import datetime

import numpy as np
import warp as wp

import warpspring as ws
from cloth import FPS, KD, KE, MASS, SPACING, SUBSTEPS, WarpspringRunner, emit_table, measure, warpspring_model


def model_with_wind(n: int, device, *, noise: bool) -> ws.Model:
    """The reference cloth in a 5 m/s wind across it (with ±30 % spatial noise of 1 m patches if ``noise``)."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=KE, kd=KD)
    builder.add_cloth_grid(nx=n, ny=n, spacing=SPACING, origin=(0.0, 0.0, 0.5 * n * SPACING),
                           rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), particle_mass=MASS,
                           structural=spring, shear=spring, bend=spring, pin=["top-left", "top-right"])
    builder.add_aerodynamics(wind=(0.0, 5.0, 0.0), noise=0.3 if noise else 0.0, noise_scale=1.0, seed=1)
    return builder.finalize(device)


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
        variants = {
            "springs": lambda: WarpspringRunner(warpspring_model(n, device)),
            "+ wind": lambda: WarpspringRunner(model_with_wind(n, device, noise=False)),
            "+ wind + noise": lambda: WarpspringRunner(model_with_wind(n, device, noise=True)),
        }
        rates = {name: SUBSTEPS / measure(make, device, args.seconds)["frame_s"] for name, make in variants.items()}
        base = rates["springs"]
        rows.append(f"| {n}² | {base:,.0f} | {rates['+ wind']:,.0f} | {1 - rates['+ wind'] / base:.0%} | "
                    f"{rates['+ wind + noise']:,.0f} | {1 - rates['+ wind + noise'] / base:.0%} |")
        print(rows[-1], flush=True)
    name = device.name if device.is_cuda else "CPU"
    lines = [
        f"`python bench/aero.py --device {device} --sizes {' '.join(map(str, args.sizes))}` — {name}, Warp "
        f"{wp.__version__}, {datetime.date.today().isoformat()}; symplectic Euler, {SUBSTEPS} substeps per "
        f"1/{FPS} s frame, one graph per frame",
        "",
        "| cloth | springs only [substeps/s] | + wind [substeps/s] | wind's share | + wind + noise [substeps/s] | "
        "share |",
        "|---|---|---|---|---|---|",
        *rows,
    ]
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
