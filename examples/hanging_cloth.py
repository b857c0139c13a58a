"""Hanging cloth: a square cloth held by two corners falls, swings and hangs.

Shows the low-level API in the pattern of Warp's examples: build a model, pick an integrator (whose
contract is ``step(state_in, state_out, control, dt)``), let a ``Stepper`` run a frame's substeps as one
captured graph (a CUDA graph on GPUs, Warp's CPU graph on the CPU), and stream each frame to USD.

    python examples/hanging_cloth.py --stage-path hanging_cloth.usdc --num-frames 300
"""

import argparse

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.app.cli import init_warp
from warpspring.io.usd import UsdWriter


class Example:
    def __init__(self, stage_path: str | None = "hanging_cloth.usdc", *, n: int = 32):
        fps = 60
        self.sim_substeps = 16
        self.frame_dt = 1.0 / fps
        self.sim_dt = self.frame_dt / self.sim_substeps
        self.sim_time = 0.0

        builder = ws.ModelBuilder(drag=0.002)
        spacing = 1.5 / (n - 1)
        builder.add_cloth_grid(
            nx=n,
            ny=n,
            spacing=spacing,
            origin=(-0.75, -0.75, 2.0),
            mass=1.0,
            structural=ws.SpringMaterial(ke=400.0, kd=0.02),
            shear=ws.SpringMaterial(ke=100.0, kd=0.005),
            bend=ws.SpringMaterial(ke=10.0, kd=0.001),
            pin=["top-left", "top-right"],
        )
        builder.add_ground_plane(friction=0.6)
        self.model = builder.finalize()

        self.integrator = ws.SymplecticEuler(self.model)
        # The stepper owns the two state buffers, the warm-up that compiles every kernel, the capture of a
        # frame's substeps into one graph, and its replay; it re-captures only if the model's structure changes.
        self.stepper = ws.Stepper(self.model, self.integrator, dt=self.sim_dt, steps=self.sim_substeps,
                                  control=self.model.control())

        self.usd = UsdWriter(stage_path, self.model, fps=fps) if stage_path else None
        if self.usd:
            self.usd.write_frame(self.stepper.state)

    def step(self):
        self.stepper.advance()
        self.sim_time += self.frame_dt

    def render(self):
        if self.usd:
            self.usd.write_frame(self.stepper.state)

    def lowest_point(self) -> float:
        """Height [m] of the lowest particle."""
        return float(np.min(self.stepper.state.particle_q.numpy()[:, 2]))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument(
        "--stage-path",
        type=lambda x: None if x == "None" else str(x),
        default="hanging_cloth.usdc",
        help="Path to the output USD file (None: no output).",
    )
    parser.add_argument("--num-frames", type=int, default=300, help="Total number of frames.")
    args = parser.parse_known_args()[0]
    init_warp(args.device)  # without Warp's banner, module-load lines and (on the CPU) its CUDA-driver warning

    with wp.ScopedDevice(args.device):
        example = Example(stage_path=args.stage_path)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        if example.usd:
            example.usd.close()
        print(f"t = {example.sim_time:.2f} s: lowest particle at z = {example.lowest_point():.3f} m")
