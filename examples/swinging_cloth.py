"""Swinging cloth: a cloth held by its top edge is swung side to side and turned by keyframe tracks, and
gravity drops to the Moon's halfway through.

Shows the live inputs of a model: a pin group driven by keyframe tracks (a smooth, cyclic translation and
a rotation about the vertical through the edge's centre, both evaluated on the device at every substep),
and gravity changed between frames while each frame replays one captured graph (nothing re-captures,
nothing compiles: the kernels read gravity from device memory).

    python examples/swinging_cloth.py --stage-path swinging_cloth.usdc --num-frames 360
"""

import argparse

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.app.cli import init_warp
from warpspring.io.usd import UsdWriter

EARTH, MOON = (0.0, 0.0, -9.81), (0.0, 0.0, -1.62)  # [m/s²]


class Example:
    def __init__(self, stage_path: str | None = "swinging_cloth.usdc", *, n: int = 24):
        fps = 60
        self.frame_dt = 1.0 / fps
        self.sim_time = 0.0
        self.frame = 0

        builder = ws.ModelBuilder(gravity=EARTH, drag=0.002)
        grid = builder.add_cloth_grid(
            nx=n,
            ny=n,
            spacing=1.2 / (n - 1),
            origin=(-0.6, 0.0, 2.4),
            rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), -np.pi / 2),  # hangs down from its top edge
            mass=0.6,
            structural=ws.SpringMaterial(ke=400.0, kd=0.02),
            shear=ws.SpringMaterial(ke=100.0, kd=0.005),
            bend=ws.SpringMaterial(ke=10.0, kd=0.001),
        )
        # The top edge (row 0 after the rotation) swings 0.4 m to either side every 2 s and turns ±30°
        # about the vertical through its centre, both as smooth keyframe tracks repeating forever.
        swing = ws.Track([0.0, 0.5, 1.0, 1.5, 2.0], [[0, 0, 0], [0.4, 0, 0], [0, 0, 0], [-0.4, 0, 0], [0, 0, 0]],
                         interpolation="smooth", extrapolation="cycle")
        turn = ws.Track.rotation([0.0, 1.0, 2.0, 3.0, 4.0], axis=(0, 0, 1), degrees=[0, 30, 0, -30, 0],
                                 interpolation="smooth", extrapolation="cycle")
        builder.add_pin_group(grid[0], translation=swing, rotation=turn, name="edge")
        self.model = builder.finalize()

        self.sim = ws.Simulator(self.model, integrator=ws.VelocityVerlet(self.model), fps=fps, substeps=16)
        self.usd = UsdWriter(stage_path, self.model, fps=fps) if stage_path else None
        self.render()

    def step(self):
        # A live input: set between frames, seen by the next replay of the captured frame.
        if self.frame == 180:
            self.model.gravity = MOON
        self.sim.step_frame()
        self.frame += 1
        self.sim_time += self.frame_dt

    def render(self):
        if self.usd:
            self.usd.write_frame(self.sim.state)

    def edge_height(self) -> float:
        """Height [m] of the lowest particle below the swinging edge."""
        return float(np.min(self.sim.state.particle_q.numpy()[:, 2]))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument(
        "--stage-path",
        type=lambda x: None if x == "None" else str(x),
        default="swinging_cloth.usdc",
        help="Path to the output USD file (None: no output).",
    )
    parser.add_argument("--num-frames", type=int, default=360, help="Total number of frames.")
    args = parser.parse_known_args()[0]
    init_warp(args.device)  # without Warp's banner, module-load lines and (on the CPU) its CUDA-driver warning

    with wp.ScopedDevice(args.device):
        example = Example(stage_path=args.stage_path)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        if example.usd:
            example.usd.close()
        print(f"t = {example.sim_time:.2f} s: lowest particle at z = {example.edge_height():.3f} m, "
              f"{example.sim.stepper.captures} graph capture(s)")
