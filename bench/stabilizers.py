"""What each stabilizer does to a hanging cloth: peak and final strain, and the cost per substep.

A cloth pinned at two corners (0.01 kg particles 0.1 m apart, structural and shear ke = 200 N/m, bend
20 N/m) stretches far past its rest lengths near the pins while it falls and swings (Provot's
super-elasticity: the corner springs carry half the cloth's weight). The clamps are set above the
static loads (~30 N per corner), so they only bound spikes. Each row runs the same scene
for 2 s with one stabilizer, symplectic Euler, 16 substeps per 1/60 s frame, a frame as one graph.
Peak strain is the largest spring strain over all frames (sampled per frame); cost is the steady time
per substep (median of timed batches after the sampled run, so compilation is excluded; device
synchronised before each timer read) and its ratio to the unstabilized run, in the same process.

    python bench/stabilizers.py --device cpu
    python bench/stabilizers.py --device cuda:0 --n 128
"""

from __future__ import annotations

import argparse
import datetime
import time

import numpy as np
import warp as wp

import warpspring as ws

FPS, SUBSTEPS, FRAMES = 60, 16, 120

#: (label, stabilizers) rows of the study.
ROWS = [
    ("none", ws.Stabilizers()),
    ("spring force clamp 50 N", ws.Stabilizers(max_spring_force=50.0)),
    ("particle force clamp 50 N", ws.Stabilizers(max_particle_force=50.0)),
    ("speed clamp 5 m/s", ws.Stabilizers(max_speed=5.0)),
    ("strain limit 10 %, 4 passes", ws.Stabilizers(max_strain=0.1, strain_iterations=4)),
    ("strain limit 10 %, 16 passes", ws.Stabilizers(max_strain=0.1, strain_iterations=16)),
    ("biphasic ×10 beyond 10 %", ws.Stabilizers(biphasic_strain=0.1, biphasic_ratio=10.0)),
]


def soft_cloth(n: int, stabilizers: ws.Stabilizers, device) -> ws.Model:
    builder = ws.ModelBuilder(stabilizers=stabilizers)
    cloth = ws.SpringMaterial(ke=200.0, kd=0.5)
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(0.0, 0.0, 3.0), particle_mass=0.01, structural=cloth,
                           shear=cloth, bend=ws.SpringMaterial(ke=20.0, kd=0.05), pin=["top-left", "top-right"])
    return builder.finalize(device)


def run_row(n: int, stabilizers: ws.Stabilizers, device, repeats: int = 5, batch: int = 20) -> dict:
    model = soft_cloth(n, stabilizers, device)
    pairs, rest = model.spring_indices.numpy(), model.spring_rest_length.numpy()
    sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=None)
    peak = 0.0
    for _ in range(FRAMES):
        sim.step_frame()
        x = sim.state.particle_q.numpy().astype(np.float64)
        strain = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1) / rest - 1.0
        peak = max(peak, float(strain.max()))
    times = []
    for _ in range(repeats):  # the cost, apart from the strain sampling: median of timed batches
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        for _ in range(batch):
            sim.step_frame()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - t0) / (batch * SUBSTEPS))
    return {"peak": peak, "final": float(strain.max()), "substep_us": 1e6 * float(np.median(times)),
            "finite": bool(np.isfinite(x).all())}


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--n", type=int, default=24, help="cloth size N (N × N particles)")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    print(f"Hanging cloth {args.n}×{args.n}, {FRAMES / FPS:.0f} s, symplectic Euler, {SUBSTEPS} substeps per "
          f"1/{FPS} s frame. Device: {device.name} ({device.alias}); Warp {wp.__version__}; "
          f"{datetime.date.today().isoformat()}.\n")
    print("| stabilizer | peak strain | final strain | µs / substep | cost vs none |")
    print("|---|---|---|---|---|")
    baseline = None
    for label, stabilizers in ROWS:
        r = run_row(args.n, stabilizers, device)
        baseline = baseline or r["substep_us"]
        peak = f"{r['peak']:.1%}" if r["finite"] else "diverged"
        print(f"| {label} | {peak} | {r['final']:.1%} | {r['substep_us']:.1f} | {r['substep_us'] / baseline:.2f}× |",
              flush=True)


if __name__ == "__main__":
    main()
