"""The cost of the scene forces: the hanging cloth of ``bench/cloth.py`` with wind, with wind and its noise, and
with a PD handle, side by side in one process.

Variants per size: the reference cloth (springs only); with aerodynamics on every triangle in a steady wind
(``add_aerodynamics``: the wind family gathered per particle with the springs); with the spatial noise
compiled in as well; with a handle grabbing the cloth's top row and dragging it along a track (the
handle family plus its per-step target pass); and with an emitter keeping 1,000 particles alive (its pool
joins the particles; births and deaths are two launches after every step). Symplectic Euler, 16 substeps per frame, each frame one graph;
the steady rate is the median of timed batches (``cloth.measure``). Reported: substeps/s of each and the
share of a substep the feature takes, 1 − rate(with) / rate(without).

    python bench/scene_forces.py --device cuda:0 --sizes 64 256 1024
    python bench/scene_forces.py --device cpu --sizes 32 64
"""

from __future__ import annotations

import argparse
import datetime

import numpy as np
import warp as wp

import warpspring as ws
from cloth import FPS, KD, KE, MASS, SPACING, SUBSTEPS, WarpspringRunner, emit_table, measure, warpspring_model


def reference_builder(n: int) -> tuple[ws.ModelBuilder, np.ndarray]:
    """The reference cloth's builder and its particle indices, shape [n, n] (row n − 1 is the top)."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=KE, kd=KD)
    ids = builder.add_cloth_grid(nx=n, ny=n, spacing=SPACING, origin=(0.0, 0.0, 0.5 * n * SPACING),
                                 rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), particle_mass=MASS,
                                 structural=spring, shear=spring, bend=spring, pin=["top-left", "top-right"])
    return builder, ids


def model_with_wind(n: int, device, *, noise: bool, precompute: bool | None = None) -> ws.Model:
    """The reference cloth in a 5 m/s wind across it (with ±30 % spatial noise of 1 m patches if ``noise``),
    each triangle's force computed by its corners or once per evaluation (``precompute``)."""
    builder, _ = reference_builder(n)
    builder.add_aerodynamics(wind=(0.0, 5.0, 0.0), noise=0.3 if noise else 0.0, noise_scale=1.0, seed=1,
                             precompute=precompute)
    return builder.finalize(device)


def model_with_handle(n: int, device) -> ws.Model:
    """The reference cloth with a handle (Kp = 1 kN/m, Kd = 10 N·s/m, capped at 50 N) on its top row, moving
    it 1 m sideways and back every 2 s."""
    builder, ids = reference_builder(n)
    sway = ws.Track([0.0, 1.0, 2.0], [[0, 0, 0], [1, 0, 0], [0, 0, 0]], interpolation="smooth", extrapolation="cycle")
    builder.add_handle(ids[-1], kp=1.0e3, kd=10.0, max_force=50.0, translation=sway)
    return builder.finalize(device)


def model_with_emitter(n: int, device) -> ws.Model:
    """The reference cloth and an emitter keeping 1,000 particles alive (2,000 per second, 0.5 s each)."""
    builder, _ = reference_builder(n)
    builder.add_emitter(center=(0.0, -1.0, 0.5 * n * SPACING), rate=2000.0, life=0.5, velocity=(0.0, -2.0, 2.0),
                        spread=0.5)
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
            "+ wind": lambda: WarpspringRunner(model_with_wind(n, device, noise=False, precompute=False)),
            "+ wind + noise": lambda: WarpspringRunner(model_with_wind(n, device, noise=True, precompute=False)),
            "+ wind, once": lambda: WarpspringRunner(model_with_wind(n, device, noise=False, precompute=True)),
            "+ wind + noise, once": lambda: WarpspringRunner(model_with_wind(n, device, noise=True, precompute=True)),
            "+ handle": lambda: WarpspringRunner(model_with_handle(n, device)),
            "+ emitter": lambda: WarpspringRunner(model_with_emitter(n, device)),
        }
        rates = {name: SUBSTEPS / measure(make, device, args.seconds)["frame_s"] for name, make in variants.items()}
        base = rates["springs"]
        rows.append(f"| {n}² | {base:,.0f} | " + " | ".join(
            f"{rates[name]:,.0f} | {1 - rates[name] / base:.0%}"
            for name in ("+ wind", "+ wind + noise", "+ wind, once", "+ wind + noise, once", "+ handle", "+ emitter"))
            + " |")
        print(rows[-1], flush=True)
    name = device.name if device.is_cuda else "CPU"
    lines = [
        f"`python bench/scene_forces.py --device {device} --sizes {' '.join(map(str, args.sizes))}` — {name}, Warp "
        f"{wp.__version__}, {datetime.date.today().isoformat()}; symplectic Euler, {SUBSTEPS} substeps per "
        f"1/{FPS} s frame, one graph per frame",
        "",
        "| cloth | springs only [substeps/s] | + wind [substeps/s] | share | + wind + noise [substeps/s] | share | "
        "+ wind, once per triangle [substeps/s] | share | + wind + noise, once [substeps/s] | share | "
        "+ handle (top row) [substeps/s] | share | + emitter (1,000 live) [substeps/s] | share |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
