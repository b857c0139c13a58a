"""Every fixed-step integrator on the hanging cloth, and what a 64² substep's time is made of.

``--study rows`` (the default): the ANCHORS cloth of ``cloth.py`` (N × N particles 0.1 m apart, 0.1 kg each,
structural + shear + bend springs ke = 1e3 N/m, kd = 10 N·s/m, the two top corners pinned, hanging vertically
under gravity, float32), each integrator at two steps:

* 16 substeps per 1/60 s frame (the bench's step, 1.04 ms), and
* its largest stable frame step: the fewest substeps per frame whose step is within the stability limit that
  ``warpspring.analysis.stability`` gives (one ``advise`` per size: ω_max at its peak over a 1 s dry run, then
  ``network_stable_step`` of each integrator with the springs' kd/ke; unconditionally stable implicit Euler:
  one step per frame), checked by a 1 s run there and one at a substep fewer (an energy check: a run that
  ends with more than 10 % of the gravitational energy it released as kinetic + elastic + gravitational
  energy above its start has blown up).

Reported per row: substeps/s, particle-substeps/s and wall time per simulated second (frames of ``Stepper``
captured as one graph each, CUDA graph or Warp's CPU graph, timed as ``cloth.py --interleave`` times them:
median of batches, the rows of one size taking their batches in turn, warm-up and capture excluded, device
synchronised before every timer read), and, for the sizes of
``--error-sizes``, the largest position error after 1 s against a float64 RK4 reference at
``--reference-substeps`` substeps per frame (its own error bounded by its difference from a run at half as
many).

``--study floor``: in one run on one device, the time per substep of (a) a captured graph of trivial kernel
launches over as many threads as particles, one per substep, (b) warpspring's symplectic Euler substep on the
64² cloth (the fused gather; on the CPU also its default, the scatter), (c) the fused kernel compiled without
springs (the same particles and pins: the update alone), (d) with ``--with-newton``, Newton's
``SolverSemiImplicit`` substep on the same cloth; with the launches, memsets and copies each substep records,
and on CUDA each substep's kernel execution time (Warp's timing API, one uncaptured substep): what is launch
floor and what is spring work, and what 2× Newton would need.

    python bench/integrators.py --device cuda:0 --sizes 256 1024 --error-sizes 64 256 --out rows.md
    python bench/integrators.py --device cpu --sizes 32 64 --error-sizes 32
    python bench/integrators.py --device cuda:0 --study floor --with-newton --out floor.md
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import math

import numpy as np
import warp as wp

import warpspring as ws
from cloth import (FPS, KD, KE, MASS, SPACING, SUBSTEPS, NewtonRunner, WarpspringRunner, emit_table,
                   measure_interleaved, round_ratio, warpspring_model)
from warpspring.analysis.stability import network_stable_step
from warpspring.analysis.trade_problems import SpringNetwork

#: Fixed-step integrators, cheapest per step first (dopri5 chooses its own step: not a row here).
INTEGRATORS = ["symplectic_euler", "velocity_verlet", "explicit_euler", "midpoint", "rk4", "implicit_euler"]
#: A run has blown up when its mechanical energy ends this fraction of the released gravitational energy
#: above its start (a damped cloth released at rest ends below its start).
ENERGY_BLOWUP = 0.1


def anchors_model(n: int, device, *, precision: str = "float32") -> ws.Model:
    """``cloth.warpspring_model``'s scene (default spring evaluation) in ``precision``."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=KE, kd=KD)
    builder.add_cloth_grid(
        nx=n, ny=n, spacing=SPACING, origin=(0.0, 0.0, 0.5 * n * SPACING),
        rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2),  # vertical, top edge up
        particle_mass=MASS, structural=spring, shear=spring, bend=spring, pin=["top-left", "top-right"],
    )
    return builder.finalize(device, precision=precision)


class StepperRunner:
    """Frames of ``substeps`` steps of one integrator, through the ``Stepper`` (one captured graph per frame)."""

    def __init__(self, model: ws.Model, integrator: str, substeps: int):
        self.model = model
        self.stepper = ws.Stepper(model, ws.make_integrator(integrator, model), dt=1.0 / (FPS * substeps),
                                  steps=substeps, control=model.control())

    def frame(self):
        self.stepper.advance()

    def final(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions [m] and velocities [m/s], float64, shape [particles, 3]."""
        state = self.stepper.state
        return state.particle_q.numpy().astype(np.float64), state.particle_qd.numpy().astype(np.float64)


def giga(rate: float) -> str:
    """A rate in G (M below 0.1 G)."""
    return f"{rate / 1e9:.3f} G" if rate >= 1e8 else f"{rate / 1e6:.2f} M"


def one_second(model: ws.Model, integrator: str, substeps: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities after 1 s (``FPS`` frames) from the initial state."""
    runner = StepperRunner(model, integrator, substeps)
    for _ in range(FPS):
        runner.frame()
    return runner.final()


def energy_excess(network: SpringNetwork, q: np.ndarray, qd: np.ndarray) -> float:
    """Mechanical energy (kinetic + elastic + gravitational, zero at the start: at rest, springs at rest) of a run
    from rest that ended at (q, qd), as a fraction of the gravitational energy it released; ∞ when non-finite."""
    if not (np.isfinite(q).all() and np.isfinite(qd).all()):
        return math.inf
    released = float(np.sum(network.mass * ((q - network.initial_q) @ network.gravity)))
    energy = network.energy(q, qd)
    return energy / released if released > 0.0 else (math.inf if energy > 0.0 else 0.0)


def blown_up(network: SpringNetwork, q: np.ndarray, qd: np.ndarray) -> bool:
    """Whether a run from rest that ended at (q, qd) created energy (see ``ENERGY_BLOWUP``) or went non-finite."""
    return energy_excess(network, q, qd) > ENERGY_BLOWUP


def stable_substeps(model: ws.Model) -> tuple[dict[str, int], float]:
    """The fewest substeps per frame within each integrator's stability limit, and the ω_max [rad/s] used:
    one ``advise`` (its ω_max at the peak of a 1 s dry run: the runs last 1 s), then ``network_stable_step``
    with the springs' kd/ke ratios for every integrator (``advise`` does the same for one)."""
    advice = ws.advise(model, "symplectic_euler", 1.0 / (FPS * SUBSTEPS), fps=FPS, horizon=1.0)
    ke = model.world_values("spring_stiffness")
    ratio = model.world_values("spring_damping") / np.where(ke > 0, ke, 1.0)
    substeps = {}
    for name in INTEGRATORS:
        limit = network_stable_step(name, advice.omega_max, rayleigh=ratio)
        substeps[name] = 1 if limit == math.inf else (math.ceil(1.0 / (FPS * limit)) if limit > 0 else 0)
    return substeps, advice.omega_max


def nodes_per_step(model: ws.Model, integrator: str) -> str:
    """Launches + memsets + copies of one uncaptured step from the initial state (``Counting``). Implicit Euler's
    CG loop, one conditional node of a captured graph (``wp.capture_while``), runs here on the host from a cold
    start, so its count includes every CG iteration: marked †, with the iterations."""
    stepper = ws.make_integrator(integrator, model)
    a, b, control = model.state(), model.state(), model.control()
    dt = 1.0 / (FPS * SUBSTEPS)
    stepper.step(a, b, control, dt)  # compiles and loads
    stepper.reset()  # no warm start (the same step again would start from its solution)
    with Counting() as count:
        stepper.step(a, b, control, dt)
    if integrator != "implicit_euler":
        return str(count)
    return f"{count} † ({stepper.solve_report()[0]} CG iterations)"


def reference(n: int, device, substeps: int) -> tuple[np.ndarray, float]:
    """The float64 RK4 positions after 1 s at ``substeps`` per frame, and their largest difference [m] from a run
    at half as many (a bound on the reference's own error: RK4's error falls 16× per halving)."""
    model = anchors_model(n, device, precision="float64")
    fine, _ = one_second(model, "rk4", substeps)
    coarse, _ = one_second(model, "rk4", substeps // 2)
    return fine, float(np.linalg.norm(fine - coarse, axis=1).max())


def rows_study(args, device) -> list[str]:
    sizes = sorted(set(args.sizes) | set(args.error_sizes))
    lines = [
        f"Hanging ANCHORS cloth, float32, frames of 1/{FPS} s through the Stepper (one graph per frame). "
        f"Device: {device.name} ({device.alias}); Warp {wp.__version__}; {datetime.date.today().isoformat()}. "
        f"Largest stable step: fewest substeps per frame within the advisor's limit (ω_max at its peak over a "
        f"1 s dry run); 'check' = 1 s there / 1 s at one substep fewer (energy test). Error: max |x − x_ref| after "
        f"1 s against float64 RK4 at {args.reference_substeps} substeps per frame. Launches, memsets and copies: one "
        f"uncaptured step of 1.04 ms from the start; †: from a cold start, every CG iteration counted (a captured "
        f"frame holds the loop as one conditional node).",
        "",
        "| N | integrator | substeps per frame | dt [ms] | check | launches + memsets + copies per step | substeps/s | "
        "particle-substeps/s | wall per simulated s [ms] | spread | max error after 1 s [m] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    notes = []
    for n in sizes:
        model = anchors_model(n, device)
        network = SpringNetwork.of(model)
        limits, omega = stable_substeps(model)
        ref = None
        if n in args.error_sizes:
            ref, self_error = reference(n, device, args.reference_substeps)
            notes.append(f"{n}²: ω_max {omega:.0f} rad/s at its peak; the reference differs from itself at half the "
                         f"step by {self_error:.1e} m.")
        else:
            notes.append(f"{n}²: ω_max {omega:.0f} rad/s at its peak.")
        specs, nodes = [], {}  # (name, substeps, check, error) of each row; graph nodes per step
        for name in args.integrators:
            largest = limits[name]
            nodes[name] = nodes_per_step(model, name)
            if not largest:
                notes.append(f"{n}²: {name} is unstable at every step for these springs (advisor).")
            for substeps in [SUBSTEPS] + ([largest] if largest and largest != SUBSTEPS else []):
                check, error = "", "—"
                if substeps == largest or ref is not None:
                    q, qd = one_second(model, name, substeps)
                    failed = blown_up(network, q, qd)
                    if ref is not None:
                        error = "blew up" if failed else f"{np.linalg.norm(q - ref, axis=1).max():.1e}"
                if substeps == largest:
                    check = "blew up" if failed else "held"
                    if substeps > 1:
                        fewer = blown_up(network, *one_second(model, name, substeps - 1))
                        check += " / " + ("blew up" if fewer else "held")
                elif substeps < largest or not largest:
                    check = "beyond the advisor's limit"
                specs.append((name, substeps, check, error))
        # Batches of every row taken in turn, so that a load which comes and goes falls on all rows alike.
        timed = measure_interleaved({(name, substeps): lambda name=name, substeps=substeps:
                                     StepperRunner(model, name, substeps) for name, substeps, _, _ in specs},
                                    device, args.seconds, args.batches)
        for name, substeps, check, error in specs:
            r = timed[(name, substeps)]
            rate = substeps / r["frame_s"]
            label = f"{substeps} (largest stable)" if substeps == limits[name] else f"{substeps}"
            lines.append(
                f"| {n} | {name} | {label} | {1e3 / (FPS * substeps):.3g} | {check} | {nodes[name]} | {rate:,.0f} | "
                f"{giga(rate * model.particle_count)} | {r['frame_s'] * FPS * 1e3:,.1f} | {r['spread']:.0%} | "
                f"{error} |"
            )
            print(lines[-1], flush=True)
    return lines + [""] + notes


# -- the 64² floor ------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def _trivial(flag: wp.array[wp.int32]):
    i = wp.tid()
    if i < 0:  # never true: the launch does nothing but exist
        flag[0] = 1


class TrivialRunner:
    """A graph of ``SUBSTEPS`` launches of a kernel that does nothing, over ``threads`` threads."""

    def __init__(self, device, threads: int):
        self.device, self.threads = device, threads
        self.flag = wp.zeros(1, dtype=wp.int32, device=device)
        self.graph = None

    def substep(self):
        wp.launch(_trivial, dim=self.threads, inputs=[self.flag], device=self.device)

    def frame(self):
        if self.graph is None:
            self.substep()  # loads the module outside the capture
            with wp.ScopedCapture(device=self.device) as capture:
                for _ in range(SUBSTEPS):
                    self.substep()
            self.graph = capture.graph
        wp.capture_launch(self.graph)


def update_only_model(model: ws.Model) -> ws.Model:
    """The same particles, masses and pins as ``model`` without springs: its fused step is the update alone."""
    builder = ws.ModelBuilder()
    builder.add_particles(model.particle_q.numpy(), mass=MASS)
    builder.pin_particles(np.flatnonzero(model.kinematic_mask()))
    return builder.finalize(model.device)


class Counting:
    """Counts, while active, the calls of ``wp.launch``, of array fills (``zero_``, ``fill_``: memsets) and of
    ``wp.copy``/``array.assign`` (copies): the graph nodes one substep records (a fill inside a copy counts
    once, as a copy)."""

    def __init__(self):
        self.counts = {"launch": 0, "memset": 0, "copy": 0}
        self._depth = 0

    def _counted(self, kind, function):
        def wrapper(*a, **k):
            if self._depth == 0:
                self.counts[kind] += 1
            self._depth += 1
            try:
                return function(*a, **k)
            finally:
                self._depth -= 1

        return wrapper

    def __enter__(self):
        self._saved = (wp.launch, wp.copy, wp.array.zero_, wp.array.fill_, wp.array.assign)
        wp.launch = self._counted("launch", self._saved[0])
        wp.copy = self._counted("copy", self._saved[1])
        wp.array.zero_ = self._counted("memset", self._saved[2])
        wp.array.fill_ = self._counted("memset", self._saved[3])
        wp.array.assign = self._counted("copy", self._saved[4])
        return self

    def __exit__(self, *exc):
        wp.launch, wp.copy, wp.array.zero_, wp.array.fill_, wp.array.assign = self._saved

    def __str__(self) -> str:
        return " + ".join(str(self.counts[k]) for k in ("launch", "memset", "copy"))


def kernel_times(substep, device) -> float | None:
    """Summed GPU execution time [s] of the kernels and memsets of one uncaptured ``substep()`` (CUDA only)."""
    if not device.is_cuda:
        return None
    substep()  # loaded and warm
    wp.synchronize_device(device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET)
    substep()
    results = wp.timing_end()
    return sum(r.elapsed for r in results) * 1e-3


def floor_study(args, device) -> list[str]:
    n = args.floor_size
    cloth = anchors_model(n, device)
    rows = []  # (label, runner factory, one uncaptured substep)

    def ws_substep(model):
        integrator = ws.make_integrator("symplectic_euler", model)
        state_a, state_b, control = model.state(), model.state(), model.control()
        return lambda: integrator.step(state_a, state_b, control, 1.0 / (FPS * SUBSTEPS))

    trivial = TrivialRunner(device, n * n)
    rows.append((f"(a) trivial kernel, {n * n:,} threads", lambda: trivial, trivial.substep))
    rows.append((f"(b) warpspring substep ({'fused gather' if cloth.spring_gather else 'scatter'})",
                 lambda: WarpspringRunner(cloth), ws_substep(cloth)))
    if not cloth.spring_gather:  # the CPU's default is the scatter: the gather row too, for the GPU's kernel
        cloth_gather = warpspring_model(n, device, "gather")
        rows.append(("(b') warpspring fused substep (gather)", lambda: WarpspringRunner(cloth_gather),
                     ws_substep(cloth_gather)))
    bare = update_only_model(cloth)
    rows.append(("(c) the same kernel without springs (update only)", lambda: WarpspringRunner(bare),
                 ws_substep(bare)))
    if args.with_newton:
        newton = NewtonRunner(cloth)

        def newton_substep():
            newton.state_0.clear_forces()
            newton.solver.step(newton.state_0, newton.state_1, newton.control, None, newton.dt)

        rows.append(("(d) Newton SemiImplicit substep", lambda: newton, newton_substep))
    counts, busy = {}, {}
    for label, _, substep in rows:
        substep()  # compile and load before counting
        with Counting() as count:
            substep()
        counts[label], busy[label] = count, kernel_times(substep, device)
    # Batches taken in turn, so that a load which comes and goes (a shared host) falls on every row alike.
    timed = measure_interleaved({label: make for label, make, _ in rows}, device, args.seconds, args.batches)
    results = {label: (timed[label]["frame_s"] / SUBSTEPS, counts[label], busy[label], timed[label]["spread"])
               for label, _, _ in rows}
    version = ""
    if args.with_newton:
        import newton as newton_module

        version = f"; Newton {newton_module.__version__}"
    lines = [
        f"Time per substep at {n}² ({n * n:,} particles), {SUBSTEPS} substeps per graph-captured frame, median of "
        f"{args.batches} batches taken in turn. Device: {device.name} ({device.alias}); Warp {wp.__version__}"
        f"{version}; {datetime.date.today().isoformat()}.",
        "",
        "| what | µs per substep | substeps/s | launches + memsets + copies per substep | "
        "kernel execution (CUDA, uncaptured) [µs] | spread |",
        "|---|---|---|---|---|---|",
    ]
    for label, (seconds, count, busy, spread) in results.items():
        lines.append(f"| {label} | {seconds * 1e6:,.2f} | {1 / seconds:,.0f} | {count} | "
                     f"{'' if busy is None else f'{busy * 1e6:.2f}'} | {spread:.1%} |")
    floor, fused = results[rows[0][0]][0], results[rows[1][0]][0]
    update = results[rows[-2 if args.with_newton else -1][0]][0]
    lines += ["", f"Launch floor (a): {floor * 1e6:.2f} µs; update alone (c) − (a): {(update - floor) * 1e6:.2f} "
              f"µs; spring work (b) − (c): {(fused - update) * 1e6:.2f} µs."]
    if args.with_newton:
        newton_time = results[rows[-1][0]][0]
        speed = round_ratio(timed[rows[1][0]], timed[rows[-1][0]])
        lines[-1] += (f" Newton (d): {newton_time * 1e6:.2f} µs per substep; warpspring (b) runs {speed:.2f}× "
                      f"Newton's speed (median of the per-round ratios); 2× Newton needs ≤ "
                      f"{newton_time / 2 * 1e6:.2f} µs per substep, i.e. {newton_time / 2 / floor:.2f} launch floors.")
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    parser.add_argument("--study", choices=["rows", "floor"], default="rows")
    parser.add_argument("--sizes", type=int, nargs="+", default=None, help="cloth sizes N (default 256 1024; CPU 32)")
    parser.add_argument("--error-sizes", type=int, nargs="*", default=None,
                        help="sizes whose error after 1 s is measured (default 64; CPU 32)")
    parser.add_argument("--integrators", nargs="+", default=INTEGRATORS, choices=INTEGRATORS)
    parser.add_argument("--reference-substeps", type=int, default=64, help="substeps per frame of the reference")
    parser.add_argument("--seconds", type=float, default=1.0, help="timed seconds per row")
    parser.add_argument("--batches", type=int, default=5, help="timed batches per row (median)")
    parser.add_argument("--floor-size", type=int, default=64, help="floor study: the cloth's N (default 64)")
    parser.add_argument("--with-newton", action="store_true", help="floor study: Newton's substep too")
    parser.add_argument("--out", help="also write the Markdown table to this file")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    device = wp.get_device(args.device)
    if args.with_newton and importlib.util.find_spec("newton") is None:
        parser.error("--with-newton: newton is not installed")
    if args.study == "floor":
        lines = floor_study(args, device)
    else:
        if args.sizes is None:
            args.sizes = [256, 1024] if device.is_cuda else [32]
        if args.error_sizes is None:
            args.error_sizes = [64] if device.is_cuda else [32]
        lines = rows_study(args, device)
    emit_table(lines, args.out)


if __name__ == "__main__":
    main()
