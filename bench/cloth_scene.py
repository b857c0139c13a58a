"""The hanging cloth of the speed benchmarks (the reference cloth: N × N particles 0.1 m apart, 0.1 kg
each, structural, shear and bend springs of ke = 1e3 N/m and kd = 10 N·s/m) and its warpspring runner, shared by
``cloth.py``, ``traffic.py``, ``worlds.py`` and ``adjacency.py``."""

from __future__ import annotations

import numpy as np

import warpspring as ws

FPS, SUBSTEPS = 60, 16
KE, KD, MASS, SPACING = 1.0e3, 10.0, 0.1, 0.1



def warpspring_model(n: int, device, spring_evaluation: str = "auto", worlds: int = 1, *,
                     spring_groups: bool = True, spring_grid: bool = True, pin: str = "corners") -> ws.Model:
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=KE, kd=KD)
    builder.add_cloth_grid(
        nx=n,
        ny=n,
        spacing=SPACING,
        origin=(0.0, 0.0, 0.5 * n * SPACING),
        rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2),  # vertical, top edge up
        particle_mass=MASS,
        structural=spring,
        shear=spring,
        bend=spring,
        pin=["top"] if pin == "top" else ["top-left", "top-right"],
    )
    return builder.finalize(device, spring_evaluation=spring_evaluation, worlds=worlds, spring_groups=spring_groups,
                            spring_grid=spring_grid)


class WarpspringRunner:
    name = "warpspring"

    def __init__(self, model: ws.Model, guard: bool = False):
        self.model = model
        self.name = f"warpspring ({'gather' if model.spring_gather else 'scatter'}"
        self.name += {"springs": ", per spring", "groups": ", table"}.get(model.spring_layout, "")
        self.name += ", default guard)" if guard else ", guard off)"
        # The default Simulator (its GuardLimits()) is what a user gets; guard off is the engine alone, as Newton has
        # no guard. The heavy ANCHORS cloth (0.1 kg per particle) hung from two corners stretches its corner springs
        # past the guard's tear limit at N ≥ 128: with the guard, hang it from its top row (``--pin top``).
        self.sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, use_graph=True,
                                guard=ws.GuardLimits() if guard else None)

    def frame(self):
        self.sim.step_frame()

    def positions(self) -> np.ndarray:
        return self.sim.state.particle_q.numpy()


def main():
    """Describe the reference cloth at the sizes asked: particles, springs and the spring layout a device picks."""
    import argparse

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--sizes", type=int, nargs="+", default=[32])
    args = parser.parse_args()
    for n in args.sizes:
        model = warpspring_model(n, args.device)
        print(f"{n}²: {model.particle_count} particles, {model.spring_count} springs, "
              f"{model.spring_layout} on {args.device}")


if __name__ == "__main__":
    main()
