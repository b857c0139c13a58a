"""Small scenes and drivers shared by the physics tests."""

from __future__ import annotations

import numpy as np
import warp as wp

import warpspring as ws

ZERO_GRAVITY = (0.0, 0.0, 0.0)


def hanging_cloth(device, *, n=12, precision="float32", sphere=False, ground=False, drag=0.0, **grid):
    """A horizontal n × n cloth at z = 1 pinned at its two top corners (the ANCHORS cloth layout), with
    air drag ``drag`` [N·s/m]."""
    builder = ws.ModelBuilder(drag=drag)
    options = dict(
        nx=n,
        ny=n,
        spacing=0.1,
        origin=(-0.05 * (n - 1), -0.05 * (n - 1), 1.0),
        particle_mass=0.1,
        structural=ws.SpringMaterial(1.0e3, 10.0),
        shear=ws.SpringMaterial(1.0e3, 10.0),
        bend=ws.SpringMaterial(1.0e3, 10.0),
        pin=["top-left", "top-right"],
    )
    options.update(grid)
    ids = builder.add_cloth_grid(**options)
    if sphere:
        builder.add_collider_sphere(center=(0.0, 0.0, 0.5), radius=0.3, friction=0.5)
    if ground:
        builder.add_ground_plane(friction=0.5)
    return builder.finalize(device, precision=precision), ids


def trajectory(model, integrator, dt, steps, *, control=None, every=1):
    """Positions [steps // every + 1, particle_count, 3] (float64) of ``steps`` steps of ``dt``."""
    a, b = model.state(), model.state()
    out = [a.particle_q.numpy().astype(np.float64)]
    for k in range(1, steps + 1):
        integrator.step(a, b, control, dt)
        a, b = b, a
        if k % every == 0:
            out.append(a.particle_q.numpy().astype(np.float64))
    return np.stack(out)


def run_frames(sim: ws.Simulator, frames: int) -> np.ndarray:
    """Advance ``frames`` frames and return the final positions (float64)."""
    for _ in range(frames):
        sim.step_frame()
    wp.synchronize_device(sim.model.device)
    return sim.state.particle_q.numpy().astype(np.float64)


def loaded_modules() -> int:
    """Kernel modules loaded so far in this process, over all devices (each (module, device, block size)
    load counts once): a new compile-time constant would load a new one."""
    try:
        from warp._src.context import user_modules
    except ImportError:  # older Warp layouts
        from warp.context import user_modules
    return sum(len(module.execs) for module in list(user_modules.values()))
