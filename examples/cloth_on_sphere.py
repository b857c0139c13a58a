"""Round tablecloth on a ball: a disc-shaped triangle mesh (any trimesh mesh works) drops onto a sphere.

Shows ``add_cloth_mesh`` (springs from mesh edges, bend springs across interior edges, mass lumped by
triangle area) and the ``Simulator`` frame loop, which captures each frame as a CUDA graph on GPUs.

    python examples/cloth_on_sphere.py --stage-path cloth_on_sphere.usdc --num-frames 150
"""

import argparse

import numpy as np
import trimesh
import warp as wp

import warpspring as ws
from warpspring.app.cli import init_warp
from warpspring.io.usd import UsdWriter


def disc_mesh(radius: float, cells: int) -> trimesh.Trimesh:
    """A flat disc in the xy plane: a square grid mesh with the faces outside ``radius`` removed."""
    u = np.linspace(-radius, radius, cells + 1)
    x, y = np.meshgrid(u, u, indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    idx = np.arange(x.size).reshape(x.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    inside = (np.linalg.norm(vertices[faces][:, :, :2], axis=2) <= radius).all(axis=1)
    grid = trimesh.Trimesh(vertices, faces[inside], process=False)
    grid.remove_unreferenced_vertices()
    return grid


class Example:
    def __init__(self, stage_path: str | None = "cloth_on_sphere.usdc"):
        builder = ws.ModelBuilder(drag=0.002)
        builder.add_cloth_mesh(
            disc_mesh(radius=0.9, cells=40),
            origin=(0.0, 0.0, 1.3),
            density=0.4,  # [kg/m²]
            structural=ws.SpringMaterial(ke=100.0, kd=0.005),
            bend=ws.SpringMaterial(ke=2.0, kd=0.0005),
            radius=0.012,
            name="tablecloth",
        )
        builder.add_collider_sphere(center=(0.0, 0.0, 0.6), radius=0.45, friction=0.4)
        builder.add_ground_plane(friction=0.6)
        self.model = builder.finalize()
        self.sim = ws.Simulator(self.model, fps=60, substeps=24)
        self.usd = UsdWriter(stage_path, self.model, fps=60) if stage_path else None
        self.render()

    def step(self):
        self.sim.step_frame()

    def render(self):
        if self.usd:
            self.usd.write_frame(self.sim.state)

    def clearance(self) -> float:
        """Smallest distance [m] of a particle centre to the sphere surface (≥ the particle radius)."""
        q = self.sim.state.particle_q.numpy()
        return float(np.linalg.norm(q - np.array([0.0, 0.0, 0.6]), axis=1).min() - 0.45)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument(
        "--stage-path",
        type=lambda x: None if x == "None" else str(x),
        default="cloth_on_sphere.usdc",
        help="Path to the output USD file (None: no output).",
    )
    parser.add_argument("--num-frames", type=int, default=150, help="Total number of frames.")
    args = parser.parse_known_args()[0]
    init_warp(args.device)  # without Warp's banner, module-load lines and (on the CPU) its CUDA-driver warning

    with wp.ScopedDevice(args.device):
        example = Example(stage_path=args.stage_path)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        if example.usd:
            example.usd.close()
        print(f"t = {example.sim.time:.2f} s: closest particle {example.clearance() * 1e3:.1f} mm from the sphere")
