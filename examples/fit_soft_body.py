"""Fit a soft body's Young's modulus to a captured drop: E recovered from a held-out target.

The target is made apart from the fit: the voxel ball of ``warpspring.analysis.grad_scenes`` (radius 0.1 m, E = 20
kPa, ρ = 100 kg/m³) dropped at 0.5 m/s from 2 cm above the ground, run by velocity Verlet at 4× the fit's substeps,
with 1 mm Gaussian noise on every point of every frame. The fit runs symplectic Euler from two starts (1.5× the
truth and a second within a factor 2.5 of it), run together as worlds, with L-BFGS-B; the ground is met by the
differentiable runs' smooth contact (``SmoothContact``, ε = 2 mm) in the target and in the fit alike. It prints the
recovered E against the truth and writes the fitted run to USD.

    python examples/fit_soft_body.py --num-frames 12 --stage-path fit_soft_body.usdc --plot fit_soft_body.png
"""

import argparse

import numpy as np
import warp as wp

from warpspring.analysis.fit import Motion, fit
from warpspring.analysis.grad_scenes import SCENES
from warpspring.app.cli import init_warp
from warpspring.core.adjoint import DiffRun
from warpspring.io.usd import UsdWriter
from warpspring.plotting import pyplot

SCENE = SCENES["voxel_ball"]
#: The held-out values: the scene's own (E = 20 kPa, spring damping 2e-4 s, dropped at 0.5 m/s).
TRUTH = dict(SCENE.values)


class Example:
    def __init__(self, stage_path: str | None = "fit_soft_body.usdc", *, num_frames: int = 12, substeps: int = 64,
                 noise: float = 1.0e-3, seed: int = 5):
        self.fps = 60
        self.substeps = substeps
        self.sim_time = 0.0
        self.frame = 0
        self.target = self.capture(num_frames, noise, seed)
        E = TRUTH["youngs_modulus"]
        self.guess = {"youngs_modulus": 1.5 * E}
        self.result = fit(self.build, self.guess, self.target, dt=self.dt, contact=SCENE.contact, starts=2,
                          spread=2.5, bounds={"youngs_modulus": (E / 4.0, E * 4.0)})
        # The fitted run, frame by frame, to USD (the differentiable run itself: its smooth contact is the model fitted).
        self.model = self.build(dict(zip(self.result.names, self.result.values)), 1)
        self.frames = self.run_of(dict(zip(self.result.names, self.result.values)), num_frames)[:, 0]
        self.state = self.model.state()
        self.usd = UsdWriter(stage_path, self.model, fps=self.fps) if stage_path else None
        if self.usd:
            self.usd.write_frame(self.state)

    @property
    def dt(self) -> float:
        return 1.0 / self.fps / self.substeps

    @staticmethod
    def build(values: dict, worlds: int):
        return SCENE.build({**TRUTH, **values}, worlds=worlds)

    def capture(self, frames: int, noise: float, seed: int) -> Motion:
        """The held-out target: velocity Verlet at 4× the substeps, every point with Gaussian noise [m]."""
        fine = 4 * self.substeps
        run = DiffRun(self.build({}, 1), dt=1.0 / self.fps / fine, steps=frames * fine, integrator="velocity_verlet",
                      contact=SCENE.contact)
        x = run.positions(np.arange(1, frames + 1) * fine)[:, 0]
        x = x + np.random.default_rng(seed).normal(scale=noise, size=x.shape)
        return Motion(times=np.arange(1, frames + 1) / self.fps, particles=np.arange(x.shape[1]), positions=x)

    def run_of(self, values: dict, frames: int) -> np.ndarray:
        """Positions [m] of the fit's run at ``values`` at every frame, 0 … ``frames``: [frames + 1, 1, n, 3]."""
        run = DiffRun(self.build(values, 1), dt=self.dt, steps=frames * self.substeps, contact=SCENE.contact)
        return run.positions(np.arange(frames + 1) * self.substeps)

    def step(self):
        self.frame += 1
        self.state.particle_q.assign(self.frames[self.frame].astype(self.state.particle_q.numpy().dtype))
        self.sim_time += 1.0 / self.fps

    def render(self):
        if self.usd:
            self.usd.write_frame(self.state)

    def plot(self, path: str) -> None:
        """The target against the fitted run and the first guess: the ball's centroid height over time (the target's
        points averaged), and each run's rms distance from the target's points per frame (the noise alone: 1 mm)."""
        plt = pyplot("the fit's plot")
        frames = len(self.target.times)
        runs = {"fit": self.run_of(dict(zip(self.result.names, self.result.values)), frames)[1:, 0],
                "first guess": self.run_of(self.guess, frames)[1:, 0]}
        styles = {"fit": ("C0-", f"fit: E = {self.result.values[0] / 1e3:.2f} kPa"),
                  "first guess": ("C1:", f"first guess: E = {self.guess['youngs_modulus'] / 1e3:.0f} kPa")}
        t = self.target.times
        fig, (height, distance) = plt.subplots(1, 2, figsize=(9, 3.6))
        height.plot(t, self.target.positions[..., 2].mean(axis=-1), "k.", label="target (1 mm noise)")
        for name, x in runs.items():
            height.plot(t, x[..., 2].mean(axis=-1), styles[name][0], label=styles[name][1])
            rms = np.sqrt(((x - self.target.positions) ** 2).sum(axis=-1).mean(axis=-1))
            distance.plot(t, rms * 1e3, styles[name][0], label=styles[name][1])
        distance.axhline(np.sqrt(3.0), color="k", lw=0.8, ls="--", label="the noise: √3 mm")
        height.set_ylabel("centroid height z [m]")
        distance.set_ylabel("rms distance from the target [mm]")
        for ax in (height, distance):
            ax.set_xlabel("t [s]")
        height.legend(fontsize=8)
        distance.legend(fontsize=8)
        fig.suptitle(f"voxel ball dropped on the ground: E recovered (truth {TRUTH['youngs_modulus'] / 1e3:.0f} kPa)")
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)

    def errors(self) -> str:
        E, error = self.result.values[0], self.result.standard_error[0]
        truth = TRUTH["youngs_modulus"]
        return f"youngs_modulus {E:.5g} Pa ({E / truth - 1.0:+.1%} ± {error / truth:.1%})"


if __name__ == "__main__":
    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument(
        "--stage-path",
        type=lambda x: None if x == "None" else str(x),
        default="fit_soft_body.usdc",
        help="Path to the output USD file (None: no output).",
    )
    parser.add_argument("--num-frames", type=int, default=12, help="Frames of the captured motion (and of the output).")
    parser.add_argument("--plot", type=str, default=None, help="PNG of the target against the fit (needs matplotlib).")
    args = parser.parse_known_args()[0]
    init_warp(args.device)  # without Warp's banner, module-load lines and (on the CPU) its CUDA-driver warning

    with wp.ScopedDevice(args.device):
        example = Example(stage_path=args.stage_path, num_frames=args.num_frames)
        for _ in range(args.num_frames):
            example.step()
            example.render()
        if example.usd:
            example.usd.close()
        if args.plot:
            example.plot(args.plot)
        print(f"t = {example.sim_time:.2f} s: fitted {example.errors()}; residual rms "
              f"{example.result.residual_rms * 1e3:.3f} mm")
