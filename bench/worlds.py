"""Many worlds in one launch: throughput of batches of small cloths, next to one large cloth.

The scene is the hanging cloth of ``cloth.py`` (ANCHORS.md: 0.1 kg particles 0.1 m apart, ke = 1e3 N/m,
kd = 10 N·s/m, hung from its top row as ``cloth.py``'s default rows, gravity, symplectic Euler, 16 substeps per
1/60 s frame, each frame one captured graph). A batch holds W worlds of a 32² cloth, each with its own gravity and
spring stiffness (a stiffness row per world: the memory traffic of a real parameter sweep); the reference is one
1024² cloth (1,048,576 particles, as many as 1,024 worlds). For small batches the same worlds are also
run the way one would without worlds: W single-world simulators, one graph each, advanced one after the
other.

Reported: the default Simulator's rate (its guard, ``GuardLimits()``: what a user gets) beside the rate with the
guard off and their ratio (their timed batches interleaved, the median of the per-round ratios), particle-substeps/s
(median of timed batches, device synchronised before every timer read), NVIDIA Newton's ``SolverSemiImplicit`` on
the same particles and springs where it is installed (the worlds as one flat set of particles: its builder has
no worlds of this kind) in the same rounds, and the batch's speed-up over the loop of single-world simulators
(guard off).

    python bench/worlds.py --device cuda:0
    python bench/worlds.py --device cpu --worlds 1 16 --no-large --seconds 2
"""

from __future__ import annotations

import argparse
import datetime
import platform

import numpy as np
import warp as wp

import warpspring as ws
from cloth import (FPS, SUBSTEPS, NewtonRunner, installed_newton, measure, measure_interleaved, round_ratio,
                   warpspring_model)

SIDE = 32
WORLDS = [1, 16, 256, 4096]
LARGE = 1024
LOOP_WORLDS = {"cuda": [16, 256], "cpu": [16]}


def batch(worlds: int, device) -> ws.Model:
    """W worlds of the 32² cloth, each with its own gravity and stiffness."""
    model = warpspring_model(SIDE, device, worlds=worlds, pin="top")
    rng = np.random.default_rng(0)
    model.set_world_values("gravity", np.stack([np.zeros(worlds), np.zeros(worlds), -rng.uniform(5, 15, worlds)], 1))
    ke = model.world_values("spring_stiffness")[0]
    model.set_world_values("spring_stiffness", ke[None, :] * rng.uniform(0.5, 1.5, worlds)[:, None])
    return model


class Batch:
    """The worlds in one Simulator: with ``guard`` its default guard (``GuardLimits()``), else none."""

    def __init__(self, model: ws.Model, guard: bool = False):
        self.sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=ws.GuardLimits() if guard else None)

    def frame(self):
        self.sim.step_frame()


class Loop:
    """The same worlds as single-world simulators, advanced one after the other."""

    def __init__(self, worlds: int, device):
        rng = np.random.default_rng(0)
        gravity = -rng.uniform(5, 15, worlds)
        scale = rng.uniform(0.5, 1.5, worlds)
        self.sims = []
        for w in range(worlds):
            model = warpspring_model(SIDE, device, pin="top")
            model.gravity = (0.0, 0.0, gravity[w])
            model.set_world_values("spring_stiffness", model.world_values("spring_stiffness")[0] * scale[w])
            self.sims.append(ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=None))

    def frame(self):
        for sim in self.sims:
            sim.step_frame()


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--worlds", type=int, nargs="+", default=WORLDS)
    parser.add_argument("--seconds", type=float, default=3.0, help="wall time per measurement [s]")
    parser.add_argument("--batches", type=int, default=5, help="interleaved timed batches per configuration")
    parser.add_argument("--no-large", action="store_true", help="skip the 1024² cloth")
    parser.add_argument("--no-newton", action="store_true", help="time warpspring alone")
    args = parser.parse_args()
    wp.init()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    kind = "cuda" if device.is_cuda else "cpu"
    name = device.name if device.is_cuda else platform.processor() or "CPU"
    newton_version = installed_newton(not args.no_newton)
    print(f"# worlds of a {SIDE}² cloth — {name}, Warp {wp.config.version}"
          + (f", Newton {newton_version}" if newton_version else "") + f", {datetime.date.today()}")
    print(f"`python bench/worlds.py --device {device}`\n")
    print("| scene | particles | default guard [substeps/s] | particle-substeps/s | guard off [substeps/s] "
          "| default ÷ off | Newton [substeps/s] | default ÷ Newton | vs loop of single worlds |")
    print("|---|---|---|---|---|---|---|---|---|")
    rows = [(f"{w} × {SIDE}²", w) for w in args.worlds]
    if not args.no_large:
        rows.append((f"1 × {LARGE}²", None))
    for label, worlds in rows:
        def scene(worlds=worlds):
            return warpspring_model(LARGE, device, pin="top") if worlds is None else batch(worlds, device)

        makers = {"default": lambda: Batch(scene(), guard=True), "off": lambda: Batch(scene())}
        if newton_version:
            makers["newton"] = lambda: NewtonRunner(scene())
        particles = scene().state_size
        try:
            results = measure_interleaved(makers, device, args.seconds, args.batches)
        except ws.SimulationError as error:
            print(f"| {label} | the default guard stopped the run: {error} |")
            continue
        rate = {key: SUBSTEPS / r["frame_s"] for key, r in results.items()}
        newton = (f"{rate['newton']:,.0f} | {round_ratio(results['default'], results['newton']):.2f}×"
                  if "newton" in results else " | ")
        speedup = ""
        if worlds in LOOP_WORLDS[kind]:
            loop = measure(lambda: Loop(worlds, device), device, args.seconds)
            speedup = f"{loop['frame_s'] / results['off']['frame_s']:.1f}×"
        print(f"| {label} | {particles:,} | {rate['default']:,.0f} | {rate['default'] * particles:.3g} | "
              f"{rate['off']:,.0f} | {round_ratio(results['default'], results['off']):.3f} | {newton} | {speedup} |",
              flush=True)


if __name__ == "__main__":
    main()
