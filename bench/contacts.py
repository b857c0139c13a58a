"""Cloth over a sphere and the ground: what contacts cost, fused into the update or through the contact stage.

The hanging-cloth benchmark's cloth (``bench/cloth.py``: 0.1 m spacing, 0.1 kg per particle, ke = 1e3 N/m,
kd = 10 N·s/m on structural, shear and bend springs), contact radius 0.04 m, starts flat one spacing above a
sphere of a quarter of its width's radius resting on the ground, and falls onto both; symplectic Euler at 16 substeps per 1/60 s frame, each frame one
captured graph. Timed after 30 frames of settling, so that the cloth lies on both colliders.

Variants, side by side in one run:

* ``fused``: the default for static colliders: every collider tested inside the update kernel;
* ``stage``: ``finalize(contact_stage=True)``: ``collide`` fills the contact buffer, the response reads it
  (the path moving colliders take);
* ``none``: the same cloth without colliders (the floor: what the springs and the update cost).

Reported: particle-substeps/s (median of timed batches, device synchronised before every timer read) and
each variant's ratio to ``fused``. ``--variants fused`` runs code without the contact stage too (the
comparison with the code before it in ``bench/RESULTS.md``).

    python bench/contacts.py --device cuda:0 --sizes 64 256 1024
    python bench/contacts.py --device cpu --sizes 32 64
"""

from __future__ import annotations

import argparse
import datetime

import numpy as np
import warp as wp

import warpspring as ws
from cloth import FPS, KD, KE, MASS, SPACING, SUBSTEPS, emit_table, measure

RADIUS = 0.4 * SPACING
SETTLE_FRAMES = 30


def contact_model(n: int, device, variant: str) -> ws.Model:
    builder = ws.ModelBuilder()
    width = (n - 1) * SPACING
    sphere = 0.25 * width
    if variant != "none":
        builder.add_collider_sphere(center=(0.0, 0.0, sphere), radius=sphere, friction=0.4)
        builder.add_ground_plane(friction=0.6)
    spring = ws.SpringMaterial(ke=KE, kd=KD)
    builder.add_cloth_grid(nx=n, ny=n, spacing=SPACING, origin=(-0.5 * width, -0.5 * width, 2 * sphere + SPACING),
                           particle_mass=MASS, structural=spring, shear=spring, bend=spring, radius=RADIUS)
    stage = {"contact_stage": True} if variant == "stage" else {}
    return builder.finalize(device, **stage)


class Runner:
    def __init__(self, model: ws.Model):
        self.sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=None)
        for _ in range(SETTLE_FRAMES):
            self.sim.step_frame()

    def frame(self):
        self.sim.step_frame()


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--variants", nargs="+", default=["fused", "stage", "none"],
                        choices=["fused", "stage", "none"])
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    lines = [
        f"Cloth over a sphere and the ground on {device.name}, Warp {wp.config.version}, {datetime.date.today()}, "
        f"symplectic Euler, {SUBSTEPS} substeps per frame",
        "",
        "| N | variant | particle-substeps/s | vs fused |",
        "|---|---|---|---|",
    ]
    for n in args.sizes:
        rates = {}
        for variant in args.variants:
            model = contact_model(n, device, variant)
            frame_s = measure(lambda: Runner(model), device, args.seconds)["frame_s"]
            rates[variant] = n * n * SUBSTEPS / frame_s
            print(f"N={n} {variant}: {rates[variant]:.4g} particle-substeps/s", flush=True)
        for variant, rate in rates.items():
            ratio = f"{rate / rates['fused']:.2f}×" if "fused" in rates else "–"
            lines.append(f"| {n} | {variant} | {rate:.3e} | {ratio} |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
