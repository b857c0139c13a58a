"""Run a scene to a USD file: build, simulate frame by frame, stream frames out, report."""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from .errors import ConfigError, SimulationError
from .integrators import make_integrator
from .scene import Scene, check_run_settings
from .simulation import Simulator


@dataclass
class RunSummary:
    """What a run did.

    Attributes:
        output: the USD file written.
        frames: frames simulated (the file holds frames + 1 samples: the initial state is frame 0).
        simulated_time: simulated seconds [s].
        wall_time: wall time [s] of frames 2..frames (simulation and USD writing).
        setup_time: wall time [s] to build the model, compile the kernels and run the first frame.
        substeps: integrator steps per frame; dt = 1 / (fps · substeps).
        device: the Warp device used.
        model: one-line model description.
        integrator: integrator name.
    """

    output: str
    frames: int
    simulated_time: float
    wall_time: float
    setup_time: float
    substeps: int
    dt: float
    device: str
    model: str
    integrator: str

    def line(self) -> str:
        """The closing summary line of the CLI."""
        timed = self.frames - 1
        if timed > 0 and self.wall_time > 0:
            rate = timed / self.wall_time
            speed = f"{rate:.1f} frames/s, {rate * self.substeps:.0f} substeps/s"
        else:  # one frame: all of it is setup, there is no rate to report
            speed = "no timed frames"
        return (
            f"wrote {self.frames + 1} frames ({self.simulated_time:.3g} s simulated) to {self.output} in "
            f"{self.wall_time:.2f} s + {self.setup_time:.2f} s setup: {speed}; {self.integrator}, "
            f"dt = {self.dt * 1e3:.4g} ms; {self.model}"
        )


def resolve_device(name: str | None):
    """The Warp device called ``name`` (None: Warp's default), or a ConfigError listing those present."""
    if name is None:
        return wp.get_device()
    try:
        device = wp.get_device(name)
    except (RuntimeError, ValueError):
        device = None
    if device is None:
        found = ", ".join(d.alias for d in wp.get_devices())
        raise ConfigError(f"device {name!r} is not available; this machine has: {found}")
    return device


def run_scene(
    scene: Scene,
    *,
    output: str | None = None,
    device: str | None = None,
    frames: int | None = None,
    fps: float | None = None,
    substeps: int | None = None,
    progress: bool = True,
) -> RunSummary:
    """Simulate ``scene`` and write it to USD. Arguments other than ``scene`` override the file's values.

    Raises:
        ConfigError: bad scene or options (nothing is written).
        SimulationError: the state became non-finite; the file holds every frame before that one.
    """
    frames = scene.frames if frames is None else frames
    fps = scene.fps if fps is None else fps
    substeps = scene.substeps if substeps is None else substeps
    check_run_settings(fps=fps, frames=frames, substeps=substeps)
    output = output or scene.output
    if not output:
        raise ConfigError("no output file: pass -o out.usdc or set [output] path in the scene")
    from .usd import UsdWriter, check_output_path  # pxr loads only for runs that write USD

    output = check_output_path(output)  # fail before the model is built and the kernels compiled

    t0 = time.perf_counter()
    dev = resolve_device(device or scene.device)
    model = scene.builder().finalize(dev, precision=scene.precision)
    try:
        integrator = make_integrator(scene.integrator, model, **scene.integrator_options)
    except ConfigError as exc:
        raise ConfigError(f"{os.path.basename(scene.path)}: [simulation] {exc}") from None
    sim = Simulator(model, integrator=integrator, fps=fps, substeps=substeps, guard=scene.guard)

    with UsdWriter(output, model, fps=fps, particles=scene.export_particles, springs=scene.export_springs) as usd:
        usd.write_frame(sim.state)
        bar = _progress(frames, enabled=progress)
        t1 = None
        try:
            for _ in range(frames):
                sim.step_frame()
                usd.write_frame(sim.state)
                bar.update(1)
                if t1 is None:  # the first frame compiled the kernels and captured the graph: setup time
                    t1 = time.perf_counter()
        except SimulationError as exc:
            # A guard names its frame and substep; the writer's last-line check knows only the frame.
            frame = exc.frame if exc.frame is not None else sim.frame
            where = "" if exc.frame is not None else f"frame {frame} (t = {frame * sim.frame_dt:.4g} s): "
            raise SimulationError(
                f"{where}{exc} (dt = {sim.dt * 1e3:.4g} ms). The run is unstable: "
                f"{_remedy(model, integrator, fps, substeps)}; {output} holds frames 0..{frame - 1}",
                frame=frame,
                substep=exc.substep,
            ) from None
        finally:
            bar.close()
        wall = time.perf_counter() - t1
    return RunSummary(
        output=output,
        frames=frames,
        simulated_time=frames / fps,
        wall_time=wall,
        setup_time=t1 - t0,
        substeps=substeps,
        dt=sim.dt,
        device=str(dev),
        model=model.describe(),
        integrator=integrator.name,
    )


def stable_substeps(model, fps: float) -> int | None:
    """Substeps per frame that keep symplectic Euler's step under the springs' stability limit; None without springs.

    Symplectic Euler keeps a damped spring stable while ω²h² + 2 (c/m) h < 4 (ω² = k/m, damping c). For a network,
    ω² and c/m are bounded per free particle by Gershgorin: 2 Σ k / m and 2 Σ kd / m over its springs. The
    bounds are upper bounds, so the count is enough for the springs (contacts and drag aside), not tight.
    """
    if model.spring_count == 0:
        return None
    ends = model.spring_indices.numpy().reshape(-1, 2).ravel()  # [a0, b0, a1, b1, ...]
    n = model.particle_count
    k_sum = np.bincount(ends, weights=np.repeat(model.spring_stiffness.numpy().astype(np.float64), 2), minlength=n)
    c_sum = np.bincount(ends, weights=np.repeat(model.spring_damping.numpy().astype(np.float64), 2), minlength=n)
    free = model.particle_inv_mass.numpy() > 0.0
    mass = model.particle_mass.numpy().astype(np.float64)[free]
    a, c = 2.0 * k_sum[free] / mass, 2.0 * c_sum[free] / mass
    moving = a > 0.0
    if not moving.any():
        return None
    a, c = a[moving], c[moving]
    h = float(((np.sqrt(c * c + 4.0 * a) - c) / a).min())  # root of a h² + 2 c h − 4 = 0, per particle
    return max(1, math.ceil(1.0 / (fps * h)))


def _remedy(model, integrator, fps: float, substeps: int) -> str:
    """What to change after a run went non-finite, with a substep count where the estimate applies."""
    needed = stable_substeps(model, fps) if integrator.name == "symplectic_euler" else None
    if needed is not None and needed > substeps:
        return (
            f"use more substeps (now {substeps}; the springs' stability bound for {integrator.name} asks for "
            f"{needed}, e.g. --substeps {needed}), lower stiffness, or a more stable integrator"
        )
    return f"use more substeps (now {substeps}), lower stiffness, or a more stable integrator"


def _progress(total: int, *, enabled: bool):
    from tqdm import tqdm

    return tqdm(total=total, unit="frame", disable=not enabled, dynamic_ncols=True, leave=False)
