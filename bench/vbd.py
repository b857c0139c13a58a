"""warpspring's implicit Euler against Newton's VBD (``SolverVBD``) on the same spring cloth, at matched accuracy.

Newton's VBD takes springs: its particle solve adds every spring's force and Hessian (``accumulate_spring_
force_and_hessian``: ke (L − |d|) d/|d|, and a damping force kd/h times the length change over the step, along
the spring) to each vertex's block, beside the inertia m/h² and the triangle, edge and tet elements (none
here). A VBD step therefore minimises backward Euler's incremental potential of the very spring network
warpspring integrates: the same equations, the same time discretisation, two solvers — warpspring's
implicit Euler takes one Newton step of it (linearised Baraff–Witkin, PCG to a relative residual of 1e-5),
VBD ``iterations`` sweeps of block Gauss–Seidel over a colouring of the particles. Newton's
``ModelBuilder.color()`` colours the graph of triangles, bending edges and tets only, so with springs alone
it would put every particle in one colour (a Jacobi sweep); the cloth here is coloured on its spring graph
(Warp's ``graph_coloring_assign``, the algorithm ``color()`` uses), so that no spring joins two particles
of one colour.

The scene is ``cloth.py``'s (the ANCHORS cloth, float32, two corners pinned: Newton zero mass); both solvers
run frames of ``s`` substeps captured as one graph. For each solver and configuration (substeps per 1/60 s
frame; VBD also its iterations), the largest position error after 1 s against a float64 RK4 reference at
``--reference-substeps`` per frame, and the wall time per simulated second (median of timed batches, warm-up
and capture excluded; the configurations of one size take their batches in turn). Then, at matched accuracy:
for each implicit-Euler row's error, the cheapest VBD configuration that reaches it, and VBD's cost at that
error on its Pareto front.

    python bench/vbd.py --device cuda:0 --sizes 64 256 --with-newton --out vbd.md
    python bench/vbd.py --device cpu --sizes 32 --with-newton
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import math

import numpy as np
import warp as wp

from cloth import FPS, KD, KE, emit_table, measure_interleaved
from integrators import ENERGY_BLOWUP, StepperRunner, anchors_model, energy_excess, reference
from warpspring.analysis.trade_problems import SpringNetwork


def spring_coloring(springs: np.ndarray, particle_count: int) -> list[np.ndarray]:
    """Particle indices of each colour of a colouring of the spring graph (``springs``: [spring_count, 2])."""
    edges = wp.array(np.ascontiguousarray(springs, dtype=np.int32), dtype=wp.int32, device="cpu")
    colors = wp.empty(particle_count, dtype=wp.int32, device="cpu")
    count = wp.utils.graph_coloring_assign(edges, colors, wp.utils.GraphColoringAlgorithm.MCS)
    wp.utils.graph_coloring_balance(edges, colors, count, 1.1)
    return [np.asarray(group, dtype=np.int32) for group in
            wp.utils.graph_coloring_get_groups(colors, count, return_wp_array=False)]


class VBDRunner:
    """Newton's ``SolverVBD`` (Newton 1.5 or 1.8) on the particles and springs of a warpspring model, frames of
    ``substeps`` steps captured as one graph."""

    def __init__(self, model, substeps: int, iterations: int):
        import newton

        q = model.particle_q.numpy()
        springs = model.spring_indices.numpy().reshape(-1, 2)
        builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, -9.81))
        mass = np.where(model.kinematic_mask(), 0.0, model.world_values("particle_mass")[0])
        builder.add_particles(pos=[tuple(p) for p in q], vel=[(0.0, 0.0, 0.0)] * len(q),
                              mass=mass.tolist())  # Newton: zero mass = kinematic
        builder.spring_indices.extend(springs.ravel().tolist())
        builder.spring_rest_length.extend(model.spring_rest_length.numpy().tolist())
        builder.spring_stiffness.extend(model.world_values("spring_stiffness")[0].tolist())
        builder.spring_damping.extend(model.world_values("spring_damping")[0].tolist())
        builder.spring_control.extend([0.0] * len(springs))
        self.colors = spring_coloring(springs, len(q))
        builder.set_coloring(self.colors)
        self.model = builder.finalize(device=model.device)
        self.model.particle_grid = None  # no particle self-contact
        self.solver = newton.solvers.SolverVBD(self.model, iterations=iterations)
        self.state_0, self.state_1 = self.model.state(), self.model.state()
        self.control = self.model.control()
        self.substeps, self.dt = substeps, 1.0 / (FPS * substeps)
        self.graph = None

    def simulate(self):
        a, b = self.state_0, self.state_1
        for _ in range(self.substeps):
            a.clear_forces()
            self.solver.step(a, b, self.control, None, self.dt)
            a, b = b, a
        if a is not self.state_0:  # an odd count: the frame ends in state_0, as the graph's next replay expects
            wp.copy(self.state_0.particle_q, a.particle_q)
            wp.copy(self.state_0.particle_qd, a.particle_qd)

    def frame(self):
        if self.graph is None:
            self.simulate()  # loads every module outside the capture (the first frame runs uncaptured)
            with wp.ScopedCapture(device=self.model.device) as capture:
                self.simulate()
            self.graph = capture.graph
            return
        wp.capture_launch(self.graph)

    def final(self) -> tuple[np.ndarray, np.ndarray]:
        return self.state_0.particle_q.numpy().astype(np.float64), self.state_0.particle_qd.numpy().astype(np.float64)


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The (cost, error) points no other point beats in both, by increasing cost (so by decreasing error)."""
    front = []
    for cost, error in sorted(points):
        if not front or error < front[-1][1]:
            front.append((cost, error))
    return front


def cost_at_error(points: list[tuple[float, float]], error: float) -> float | None:
    """The cost at ``error`` on the Pareto front of (cost, error) ``points``, linear in log cost and log error between
    the two front points around it; None outside the front's errors."""
    front = pareto_front(points)
    for (c0, e0), (c1, e1) in zip(front, front[1:]):
        if e1 <= error <= e0:
            t = math.log(e0 / error) / math.log(e0 / e1)
            return math.exp(math.log(c0) + t * math.log(c1 / c0))
    return None


def run_one_second(runner) -> tuple[np.ndarray, np.ndarray]:
    for _ in range(FPS):
        runner.frame()
    return runner.final()


def sweep(n: int, device, args, newton_version: str | None) -> tuple[list[str], list[str]]:
    """Rows of every configuration at size ``n`` and the matched-accuracy rows."""
    model = anchors_model(n, device)
    network = SpringNetwork.of(model)
    ref, self_error = reference(n, device, args.reference_substeps)
    configurations = [("warpspring implicit_euler", s, None) for s in args.substeps]
    if newton_version:
        configurations += [(f"Newton {newton_version} VBD", s, k) for s in args.substeps for k in args.iterations]
    results = []  # (solver, substeps, iterations, error or None, wall per simulated second)
    rows, makers, shown = [], {}, {}
    colors = None
    for solver, substeps, iterations in configurations:
        if iterations is None:
            def make(substeps=substeps):
                return StepperRunner(model, "implicit_euler", substeps)
        else:
            def make(substeps=substeps, iterations=iterations):
                return VBDRunner(model, substeps, iterations)
        runner = make()
        if iterations is not None:
            colors = len(runner.colors)
        q, qd = run_one_second(runner)
        del runner
        excess = energy_excess(network, q, qd)
        error = float(np.linalg.norm(q - ref, axis=1).max()) if excess < math.inf else None
        key = (solver, substeps, iterations)
        makers[key] = make
        shown[key] = "non-finite" if error is None else f"{error:.2e}"
        if error is not None and excess > ENERGY_BLOWUP:  # finite, but it ends above its start's energy
            shown[key] += f" (energy created: {excess:.0%} of the released)"
        results.append((solver, substeps, iterations, error))
    # Batches of every configuration taken in turn, so that a load which comes and goes falls on all alike.
    timed = measure_interleaved(makers, device, args.seconds, args.batches)
    for i, (solver, substeps, iterations, error) in enumerate(results):
        r = timed[(solver, substeps, iterations)]
        cost = r["frame_s"] * FPS
        results[i] = (solver, substeps, iterations, error, cost)
        rows.append(f"| {n} | {solver} | {substeps} | {1e3 / (FPS * substeps):.3g} | "
                    f"{'' if iterations is None else iterations} | {shown[(solver, substeps, iterations)]} | "
                    f"{cost * 1e3:,.1f} | {substeps * FPS / cost:,.0f} | {r['spread']:.0%} |")
        print(rows[-1], flush=True)
    matched = []
    vbd_points = [(r[4], r[3]) for r in results if r[2] is not None and r[3] is not None]
    for solver, substeps, _, error, cost in results:
        if not solver.startswith("warpspring") or error is None or not newton_version:
            continue
        reaching = [r for r in results if r[2] is not None and r[3] is not None and r[3] <= error]
        at_equal = cost_at_error(vbd_points, error)
        equal = "" if at_equal is None else f"{at_equal * 1e3:,.1f} ({at_equal / cost:.2f}×)"
        if not reaching:
            matched.append(f"| {n} | {error:.2e} | {substeps} substeps: {cost * 1e3:,.1f} | none reaches it | | "
                           f"{equal} |")
            continue
        best = min(reaching, key=lambda r: r[4])
        matched.append(f"| {n} | {error:.2e} | {substeps} substeps: {cost * 1e3:,.1f} | {best[1]} substeps × "
                       f"{best[2]} iterations (error {best[3]:.2e}): {best[4] * 1e3:,.1f} | {best[4] / cost:.2f}× | "
                       f"{equal} |")
    notes = [f"{n}²: the reference (float64 RK4, {args.reference_substeps} substeps per frame) differs from itself at "
             f"half the step by {self_error:.1e} m"
             + (f"; VBD's spring colouring has {colors} colours." if colors else ".")]
    return rows + notes, matched


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="cloth sizes N (default 64 256; CPU 32)")
    parser.add_argument("--substeps", type=int, nargs="+", default=[1, 2, 4, 8, 16], help="substeps per frame")
    parser.add_argument("--iterations", type=int, nargs="+", default=[5, 10, 20], help="VBD iterations per substep")
    parser.add_argument("--reference-substeps", type=int, default=64, help="substeps per frame of the reference")
    parser.add_argument("--seconds", type=float, default=1.0, help="timed seconds per configuration")
    parser.add_argument("--batches", type=int, default=5, help="timed batches per configuration (median)")
    parser.add_argument("--with-newton", action="store_true", help="Newton's VBD rows (else implicit Euler alone)")
    parser.add_argument("--out", help="also write the Markdown tables to this file")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    newton_version = None
    if args.with_newton:
        if importlib.util.find_spec("newton") is None:
            parser.error("--with-newton: newton is not installed")
        import newton

        newton_version = newton.__version__
    sizes = args.sizes or ([64, 256] if device.is_cuda else [32])
    lines = [
        f"The ANCHORS cloth (ke = {KE:g} N/m, kd = {KD:g} N·s/m), float32, the same springs in both solvers, both "
        f"backward Euler: max |x − x_ref| after 1 s against float64 RK4, and wall time per simulated second "
        f"(frames of 1/{FPS} s, one graph each). Device: {device.name} ({device.alias}); Warp {wp.__version__}"
        + (f"; Newton {newton_version}" if newton_version else " (Newton not run: --with-newton)")
        + f"; {datetime.date.today().isoformat()}.",
        "",
        "| N | solver | substeps per frame | dt [ms] | VBD iterations | max error after 1 s [m] | "
        "wall per simulated s [ms] | substeps/s | spread |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    matched, notes = [], []
    for n in sizes:
        rows, match = sweep(n, device, args, newton_version)
        lines += [r for r in rows if r.startswith("|")]
        notes += [r for r in rows if not r.startswith("|")]
        matched += match
    lines += ["", *notes]
    if matched:
        lines += [
            "",
            "Matched accuracy (wall time per simulated second): for each implicit-Euler row's error, the cheapest "
            "VBD configuration whose error is at most that, and VBD's cost at exactly that error on its Pareto front "
            "(log-log between the two configurations around it).",
            "",
            "| N | error ≤ [m] | warpspring implicit_euler [ms] | cheapest VBD reaching it [ms] | VBD / implicit "
            "Euler | VBD at equal error [ms] |",
            "|---|---|---|---|---|---|",
            *matched,
        ]
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
