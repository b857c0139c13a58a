"""Cloth over a sphere and the ground: what contacts cost, fused into the update or through the contact stage.

The hanging-cloth benchmark's cloth (``bench/cloth.py``: 0.1 m spacing, 0.1 kg per particle, ke = 1e3 N/m,
kd = 10 N·s/m on structural, shear and bend springs), contact radius 0.04 m, starts flat one spacing above a
sphere of a quarter of its width's radius resting on the ground, and falls onto both; symplectic Euler at 16 substeps per 1/60 s frame, each frame one
captured graph. Timed after 30 frames of settling, so that the cloth lies on both colliders.

Variants, side by side in one run:

* ``fused``: the default for static colliders: every collider tested inside the update kernel;
* ``stage``: ``finalize(contact_stage=True)``: ``collide`` fills the contact buffer, the response reads it
  (the path moving colliders take);
* ``none``: the same cloth without colliders (the floor: what the springs and the update cost);
* ``unswept``: ``fused`` without the swept paths (``model.contact_swept = False``): what anti-tunnelling costs
  against analytic shapes;
* ``mesh``: the sphere as a closed mesh collider (an icosphere of 5120 triangles: closest point signed by
  pseudo-normals, a ray test per swept path, from each particle's candidate cache), fused; ``mesh-unswept``
  without the ray test; ``mesh-stage`` through the contact stage; ``mesh-moving`` moved by a translation
  track (frames per step, surface velocity); ``mesh-deforming`` built ``deforming=True`` with its points set
  (and the BVH refit, and every cache invalidated) every frame; ``mesh-open``: the ground as a one-sided open
  mesh too (two mesh queries per particle);
* ``…-full``: the same mesh variant with the full BVH query at every use (``cache_margin = 0``: the same
  results, bit for bit); ``…-warp``: with Warp's own closest-point query and ray cast, the path before the
  cache (``MeshCollider.use_warp_query()``);
* ``triangles``: ``fused`` with ``model.contact_triangles``: the cloth's triangles kept out of the sphere too
  (two more launches per substep: per triangle, then per particle).

``--shares`` prints, instead of the ratios, each variant's contact work as a share of its substep,
(t - t_none) / t, where t is the substep's time, and for mesh variants the full BVH queries per
particle-substep over the timed frames (the cache's refreshes; "–" where the path keeps no count): what the
issue's table asks (one command, one table)::

    python bench/contacts.py --device cuda:0 --sizes 64 256 --shares

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
from warpspring.core.mesh_colliders import mesh_cache_counts
from cloth import FPS, KD, KE, MASS, SPACING, SUBSTEPS, emit_table, measure, measure_interleaved

RADIUS = 0.4 * SPACING
SETTLE_FRAMES = 30


VARIANTS = ["fused", "stage", "none", "unswept", "mesh", "mesh-full", "mesh-warp", "mesh-unswept", "mesh-stage",
            "mesh-stage-full", "mesh-stage-warp", "mesh-moving", "mesh-moving-full", "mesh-deforming",
            "mesh-deforming-full", "mesh-open", "mesh-open-full", "triangles"]
#: A track that barely moves the mesh sphere (1 mm over 10 s): its frames are written every step, as for any
#: moving collider, while the cloth's contact stays the same as the static sphere's.
CREEP = ws.Track([0.0, 10.0], [[0.0, 0.0, 0.0], [0.001, 0.0, 0.0]], interpolation="linear")


def contact_model(n: int, device, variant: str) -> ws.Model:
    import trimesh

    query = "full" if variant.endswith("-full") else "warp" if variant.endswith("-warp") else "cached"
    variant = variant.removesuffix("-full").removesuffix("-warp")

    builder = ws.ModelBuilder()
    width = (n - 1) * SPACING
    sphere = 0.25 * width
    if variant != "none":
        if variant.startswith("mesh"):
            ball = trimesh.creation.icosphere(subdivisions=4, radius=sphere)
            builder.add_collider_mesh(ball, center=(0.0, 0.0, sphere), friction=0.4,
                                      translation=CREEP if variant == "mesh-moving" else None,
                                      deforming=variant == "mesh-deforming", name="ball")
        else:
            builder.add_collider_sphere(center=(0.0, 0.0, sphere), radius=sphere, friction=0.4)
        if variant == "mesh-open":
            t = np.array([-1.0, 1.0]) * width
            ground = np.array([[t[0], t[0], 0.0], [t[1], t[0], 0.0], [t[1], t[1], 0.0], [t[0], t[1], 0.0]])
            builder.add_collider_mesh(ground, faces=[[0, 1, 2], [0, 2, 3]], sides="one_sided", depth=width,
                                      friction=0.6, name="ground")
        else:
            builder.add_ground_plane(friction=0.6)
    spring = ws.SpringMaterial(ke=KE, kd=KD)
    builder.add_cloth_grid(nx=n, ny=n, spacing=SPACING, origin=(-0.5 * width, -0.5 * width, 2 * sphere + SPACING),
                           particle_mass=MASS, structural=spring, shear=spring, bend=spring, radius=RADIUS)
    stage = {"contact_stage": True} if variant in ("stage", "mesh-stage") else {}
    model = builder.finalize(device, **stage)
    if variant.endswith("unswept"):
        model.contact_swept = False
    if variant == "triangles":
        model.contact_triangles = True
    for collider in model.mesh_colliders:
        if query == "full":
            collider.cache_margin = 0.0
        elif query == "warp":
            collider.use_warp_query()
    return model


class Runner:
    def __init__(self, model: ws.Model):
        self.sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=None)
        self.deforming = [c for c in model.mesh_colliders if c.info.deforming]
        self.frames = 0
        for _ in range(SETTLE_FRAMES):
            self.frame()
        self.frames = 0
        self.refreshes = self.mesh_queries()

    def frame(self):
        for collider in self.deforming:  # the same points, set and refit every frame as a deforming mesh's are
            collider.set_points(collider.points(), dt=1.0 / FPS)
        self.sim.step_frame()
        self.frames += 1

    def mesh_queries(self) -> int:
        """Full BVH queries the mesh caches made so far, every world together."""
        model = self.sim.model
        return int(mesh_cache_counts(model)["refreshes"].sum()) if model.mesh_colliders else 0

    def queries_per_particle_substep(self) -> float:
        """Full BVH queries per particle-substep since the settling (only the cached path counts them)."""
        particle_substeps = self.sim.model.particle_count * SUBSTEPS * max(1, self.frames)
        return (self.mesh_queries() - self.refreshes) / particle_substeps


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--variants", nargs="+", default=None, choices=VARIANTS,
                        help="default: fused, stage, none; with --shares every variant")
    parser.add_argument("--shares", action="store_true",
                        help="each variant's contact work as a share of its substep, (t - t_none) / t")
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--interleaved", action="store_true",
                        help="set every variant of a size up first, then time their batches in turn (round k "
                             "times each once), so a load that comes and goes on a shared machine falls on all alike")
    parser.add_argument("--out", default=None, help="also write the table to this file")
    args = parser.parse_args()
    if args.variants is None:
        args.variants = VARIANTS if args.shares else ["fused", "stage", "none"]
    if args.shares and "none" not in args.variants:
        args.variants = ["none", *args.variants]
    wp.init()
    device = wp.get_device(args.device)
    lines = [
        f"Cloth over a sphere and the ground on {device.name}, Warp {wp.config.version}, {datetime.date.today()}, "
        f"symplectic Euler, {SUBSTEPS} substeps per frame",
        "",
    ]
    lines += (["| N | variant | substep [µs] | contacts' share of the substep | BVH queries per particle-substep |",
               "|---|---|---|---|---|"] if args.shares
              else ["| N | variant | particle-substeps/s | vs fused |", "|---|---|---|---|"])
    for n in args.sizes:
        rates, queries, made = {}, {}, {}

        def maker(variant):
            model = contact_model(n, device, variant)
            return lambda: made.setdefault(variant, Runner(model))

        if args.interleaved:
            frame_s = {v: r["frame_s"] for v, r in measure_interleaved({v: maker(v) for v in args.variants}, device,
                                                                         args.seconds).items()}
        else:
            frame_s = {v: measure(maker(v), device, args.seconds)["frame_s"] for v in args.variants}
        for variant in args.variants:
            rates[variant] = n * n * SUBSTEPS / frame_s[variant]
            counted = variant.startswith("mesh") and not variant.endswith(("-full", "-warp"))
            queries[variant] = f"{made[variant].queries_per_particle_substep():.4f}" if counted else "–"
            print(f"N={n} {variant}: {rates[variant]:.4g} particle-substeps/s", flush=True)
        for variant, rate in rates.items():
            if args.shares:
                substep, floor = n * n / rate, n * n / rates["none"]
                share = "–" if variant == "none" else f"{100 * (substep - floor) / substep:.0f} %"
                lines.append(f"| {n} | {variant} | {substep * 1e6:.1f} | {share} | {queries[variant]} |")
                continue
            ratio = f"{rate / rates['fused']:.2f}×" if "fused" in rates else "–"
            lines.append(f"| {n} | {variant} | {rate:.3e} | {ratio} |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
