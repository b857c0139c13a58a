"""A long run in short (bench/soak.py runs 100,000 substeps): a driven cloth with the default guard and the
run-time watch keeps its memory constant frame after frame and neither gains nor drifts in energy."""

import tracemalloc

import numpy as np
import warp as wp

import warpspring as ws


def driven_cloth(device):
    """bench/soak.py's cloth at 12 × 12: 0.1 kg particles 0.1 m apart, 1 kN/m springs, two top corners swung
    ±0.2 m at 0.5 Hz by a handle, light drag."""
    builder = ws.ModelBuilder(drag=0.01)
    spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
    ids = builder.add_cloth_grid(nx=12, ny=12, spacing=0.1, particle_mass=0.1, origin=(0.0, 0.0, 2.0),
                                 structural=spring, shear=spring, bend=spring,
                                 rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2))
    swing = ws.Track([0.0, 0.5, 1.0, 1.5, 2.0], [[0, 0, 0], [0.2, 0, 0], [0, 0, 0], [-0.2, 0, 0], [0, 0, 0]],
                     interpolation="smooth", extrapolation="cycle")
    builder.add_pin_group([ids[-1, 0], ids[-1, -1]], translation=swing, name="handle")
    return builder.finalize(device)


def used_device_memory(device) -> int:
    d = wp.get_device(device)
    return int(d.total_memory - d.free_memory) if d.is_cuda else 0


def test_a_long_driven_run_keeps_its_memory_and_its_energy(device):
    """4,800 substeps (300 frames of 16, two handle cycles and a half): after the first 100 frames (compiles,
    captures) Python's allocations grow by less than 16 KiB over the remaining 200 (no per-frame leak: a
    frame's record alone is ~1 KiB) and device memory not at all; the guard's energy balance never shows
    energy created beyond 0.5 % of what the start and the handle supplied (symplectic Euler's O(h) energy
    error at h = 1/960 s; a leak of energy into the cloth would grow without bound) while the handle really
    works on the cloth (W changes sign as it pulls and brakes)."""
    model = driven_cloth(device)
    sim = ws.Simulator(model, fps=60, substeps=16, watch=10)
    for _ in range(100):
        sim.step_frame()
    tracemalloc.start()
    python_before, device_before = tracemalloc.get_traced_memory()[0], used_device_memory(device)
    created, work = [], []
    for frame in range(200):
        sim.step_frame()
        if frame % 10 == 9:
            balance = sim.guard.energy_balance()
            created.append(balance.created[0] / balance.peak[0])
            work.append(balance.work[0])
    python_growth = tracemalloc.get_traced_memory()[0] - python_before
    tracemalloc.stop()
    assert python_growth < 16 * 1024, python_growth
    assert used_device_memory(device) == device_before
    assert max(created) <= 5e-3, max(created)
    assert np.ptp(work) > 1.0 and not sim.watch.warned.any()
