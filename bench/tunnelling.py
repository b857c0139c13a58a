"""Fast particles against thin colliders, with and without swept paths: how many end on the wrong side.

Eight particles (radius 2 cm, gravity off) per collider are shot from 0.5 m above it at up to 0.6° from its
normal at each speed, 16 substeps per 1/60 s frame for 4 frames, at: a zero-thickness two-sided mesh plane,
a one-sided mesh plane (from its front), a closed mesh slab 2 mm thick, an analytic box 2 mm thick (each
8 m × 8 m, frictionless), and a capsule pole of radius 2 mm (μ = 5) at which they are aimed within half of
r + 2 mm of its axis. Counted: particles below the plane z = 0 (the pole's axis) at the end, with
``model.contact_swept`` off and on (the scene of ``tests/test_mesh_colliders.py``, where the swept case is
asserted).

    python bench/tunnelling.py --device cpu
"""

from __future__ import annotations

import argparse
import datetime

import numpy as np
import warp as wp

import warpspring as ws

RADIUS = 0.02
COLLIDERS = [(-15.0, "two_sided"), (-5.0, "one_sided"), (5.0, "slab"), (15.0, "box"), (25.0, "pole")]
POLE = 0.002


def scene(device, speed: float, *, swept: bool, precision: str) -> ws.Model:
    import trimesh

    t = np.linspace(-4.0, 4.0, 3)
    xx, yy = np.meshgrid(t, t)
    plane = np.stack([xx.ravel(), yy.ravel(), np.zeros(9)], axis=1)
    a = np.array([0, 1, 3, 4])
    faces = np.concatenate([np.stack([a, a + 1, a + 4], 1), np.stack([a, a + 4, a + 3], 1)])
    builder = ws.ModelBuilder()
    builder.gravity = (0.0, 0.0, 0.0)
    rng = np.random.default_rng(3)
    for x_offset, kind in COLLIDERS:
        if kind == "pole":
            start = np.c_[x_offset + np.linspace(-0.5, 0.5, 8) * (RADIUS + POLE), rng.uniform(-1.0, 1.0, 8),
                          np.full(8, 0.5)]
            builder.add_particles(start, radius=RADIUS, velocities=(0.0, 0.0, -speed))
            builder.add_collider_capsule(center=(x_offset, 0.0, 0.0), radius=POLE, half_height=4.0, friction=5.0,
                                         orientation=(-np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)))  # along y
            continue
        start = np.c_[rng.uniform(-1.0, 1.0, 8) + x_offset, rng.uniform(-1.0, 1.0, 8), np.full(8, 0.5)]
        direction = np.c_[rng.uniform(-0.01, 0.01, (8, 2)), -np.ones(8)]
        direction /= np.linalg.norm(direction, axis=1)[:, None]
        builder.add_particles(start, radius=RADIUS, velocities=speed * direction)
        if kind in ("two_sided", "one_sided"):
            builder.add_collider_mesh(plane, faces=faces, sides=kind, center=(x_offset, 0.0, 0.0), friction=0.0,
                                      name=kind)
        elif kind == "slab":
            builder.add_collider_mesh(trimesh.creation.box(extents=(8.0, 8.0, 0.002)), center=(x_offset, 0.0, -0.001),
                                      friction=0.0, name=kind)
        else:
            builder.add_collider_box(center=(x_offset, 0.0, -0.001), half_extents=(4.0, 4.0, 0.001), friction=0.0)
    model = builder.finalize(device, contact_stage=True, contact_slots=2, precision=precision)
    model.contact_swept = swept
    return model


def wrong_side(model: ws.Model) -> list[int]:
    sim = ws.Simulator(model, fps=60, substeps=16, guard=None)
    for _ in range(4):
        sim.step_frame()
    z = sim.state.particle_q.numpy()[:, 2].reshape(len(COLLIDERS), 8)
    return [int(n) for n in (z < 0.0).sum(axis=1)]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--speeds", type=float, nargs="+", default=[1.0, 10.0, 100.0, 1000.0])
    parser.add_argument("--precision", default="float32", choices=["float32", "float64"])
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    print(f"Particles on the wrong side of a two-sided mesh plane / one-sided mesh plane / 2 mm mesh slab / 2 mm "
          f"box / 2 mm capsule pole on {device.name}, Warp {wp.config.version}, {args.precision}, "
          f"{datetime.date.today()}\n")
    print("| speed [m/s] | path per step | unswept | swept |\n|---|---|---|---|")
    for speed in args.speeds:
        counts = [wrong_side(scene(device, speed, swept=swept, precision=args.precision)) for swept in (False, True)]
        path = speed / (60 * 16)
        print(f"| {speed:g} | {path * 100:.3g} cm | {' / '.join(map(str, counts[0]))} | "
              f"{' / '.join(map(str, counts[1]))} |", flush=True)


if __name__ == "__main__":
    main()
