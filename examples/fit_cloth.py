"""Fit a cloth's material to a captured motion: stretch, bending and damping recovered from a held-out target.

The target is made apart from the fit: the hanging 8 × 8 cloth of ``warpspring.analysis.grad_scenes`` (a
ClothMaterial, two pinned corners, released flat) run by velocity Verlet at 4× the fit's substeps, with 1 mm
Gaussian noise on every point of every frame. The fit runs symplectic Euler (the ordinary kernels' force, with
adjoints) from three starts, run together as worlds, with L-BFGS-B; it prints the recovered values against the
truth, and writes the fitted model's run to USD.

    python examples/fit_cloth.py --num-frames 30 --stage-path fit_cloth.usdc
"""

import argparse

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.analysis.fit import Motion, fit
from warpspring.analysis.grad_scenes import SCENES, hanging_cloth
from warpspring.app.cli import init_warp
from warpspring.core.adjoint import DiffRun
from warpspring.io.usd import UsdWriter
from warpspring.plotting import pyplot

#: The held-out material: a soft, viscous fabric with a bending length of ~10 cm (stretch 20 N/m, bending 2e-3 N·m,
#: stretch damping 0.5 N·s/m), the scene's other values as they are.
TRUTH = {**SCENES["hanging_cloth"].values, "stretch": 20.0, "bending": 2.0e-3, "stretch_damping": 0.5}
FITTED = ("stretch", "bending", "stretch_damping")


class Example:
    def __init__(self, stage_path: str | None = "fit_cloth.usdc", *, num_frames: int = 30, substeps: int = 32,
                 noise: float = 1.0e-3, seed: int = 3):
        self.fps = 60
        self.substeps = substeps
        self.sim_time = 0.0
        self.target = self.capture(num_frames, noise, seed)
        guess = {"stretch": TRUTH["stretch"] * 1.4, "bending": TRUTH["bending"] * 0.7,
                 "stretch_damping": TRUTH["stretch_damping"] * 1.4}
        self.result = fit(self.build, guess, self.target, dt=1.0 / self.fps / substeps, starts=3, spread=1.5,
                          bounds={k: (TRUTH[k] / 3.0, TRUTH[k] * 3.0) for k in FITTED})
        # The fitted material's run, by the ordinary simulator, to USD.
        fitted = dict(zip(self.result.names, self.result.values))
        self.model = hanging_cloth({**TRUTH, **fitted})
        self.sim = ws.Simulator(self.model, integrator=ws.SymplecticEuler(self.model), fps=self.fps,
                                substeps=substeps)
        self.usd = UsdWriter(stage_path, self.model, fps=self.fps) if stage_path else None
        if self.usd:
            self.usd.write_frame(self.sim.state)

    @staticmethod
    def build(values: dict, worlds: int) -> ws.Model:
        return hanging_cloth({**TRUTH, **values}, worlds=worlds)

    def capture(self, frames: int, noise: float, seed: int) -> Motion:
        """The held-out target: velocity Verlet at 4× the substeps, every point with Gaussian noise [m]."""
        fine = 4 * self.substeps
        run = DiffRun(self.build({}, 1), dt=1.0 / self.fps / fine, steps=frames * fine, integrator="velocity_verlet")
        x = run.positions(np.arange(1, frames + 1) * fine)[:, 0]
        x = x + np.random.default_rng(seed).normal(scale=noise, size=x.shape)
        return Motion(times=np.arange(1, frames + 1) / self.fps, particles=np.arange(x.shape[1]), positions=x)

    def step(self):
        self.sim.step_frame()
        self.sim_time += 1.0 / self.fps

    def render(self):
        if self.usd:
            self.usd.write_frame(self.sim.state)

    def plot(self, path: str) -> None:
        """The target's points (noisy) against the fitted run and the first guess: height of the two free corners
        and of the middle of the bottom edge over time."""
        plt = pyplot("the fit's plot")
        frames = len(self.target.times)
        steps = np.arange(1, frames + 1) * self.substeps
        fitted = dict(zip(self.result.names, self.result.values))
        runs = {}
        for label, values in (("fit", fitted), ("first guess", self.result.starts[0]["start"])):
            run = DiffRun(self.build(values, 1), dt=1.0 / self.fps / self.substeps, steps=int(steps[-1]))
            runs[label] = run.positions(steps)[:, 0]
        n = int(round(np.sqrt(self.target.positions.shape[1])))
        corners = {"bottom-left corner": 0, "bottom middle": n // 2, "bottom-right corner": n - 1}
        fig, ax = plt.subplots(figsize=(7, 4))
        for (name, i), color in zip(corners.items(), ("C0", "C1", "C2")):
            ax.plot(self.target.times, self.target.positions[:, i, 2], ".", color=color, label=f"target: {name}")
            ax.plot(self.target.times, runs["fit"][:, i, 2], "-", color=color)
            ax.plot(self.target.times, runs["first guess"][:, i, 2], ":", color=color)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("height z [m]")
        ax.set_title("held-out target (dots), fitted run (lines), first guess (dotted)")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(path, dpi=120)
        plt.close(fig)

    def errors(self) -> str:
        return ", ".join(f"{name} {value:.4g} ({value / TRUTH[name] - 1.0:+.1%} ± {error / TRUTH[name]:.1%})"
                         for name, value, error in zip(self.result.names, self.result.values,
                                                       self.result.standard_error))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument(
        "--stage-path",
        type=lambda x: None if x == "None" else str(x),
        default="fit_cloth.usdc",
        help="Path to the output USD file (None: no output).",
    )
    parser.add_argument("--num-frames", type=int, default=30, help="Frames of the captured motion (and of the output).")
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
