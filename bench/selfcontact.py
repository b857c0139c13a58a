"""Self-collision's cost as a share of the substep: a cloth draped over a sphere on the ground, with and without it.

The contact benchmark's scene (``bench/contacts.py``: the hanging-cloth benchmark's cloth, 0.1 m spacing,
0.1 kg per particle, ke = 1e3 N/m, kd = 10 N·s/m, falling onto a sphere on the ground; symplectic Euler at
16 substeps per 1/60 s frame, each frame one captured graph on CUDA), timed after 30 frames of settling,
when the skirt lies folded on the ground. Variants, side by side in one run:

* ``none``: the scene without self-collision (the colliders' response fused into the update);
* ``self``: ``add_self_collision(thickness=0.02, friction=0.3)`` (τ below 0.7 × the grid's 0.071 m altitude):
  the BVH refit, the repulsion pass and the cap pass after every substep (the update no longer fuses the
  colliders: the finishing pass runs them);
* ``pass``: the self-collision pass alone on the settled state (refit, repel, cap), 16 per frame.

Reported: particle-substeps/s (median of timed batches, device synchronised before every timer read), and
self-collision's share of the substep, 1 - rate(self) / rate(none), and the pass alone against a ``self``
substep. The pairs pushed and vertices capped per substep at the end tell how much contact the scene has, the
pairs the two stages listed at the last substep (repulsion / cap) and the pairs dropped on overflow what the
pair buffers hold.

``--profile`` times each launch of one pass instead (on the settled ``self`` scene, uncaptured, averaged over
``--repeats`` passes): on CUDA Warp's activity timer (``wp.ScopedTimer(cuda_filter=wp.TIMING_ALL)``: kernels,
memsets, the scan's and the BVH refit's own kernels), on the CPU a synchronised wall-clock timer around each
launch, scan and refit.

    python bench/selfcontact.py --device cuda:0            # 64² and 256², the table for bench/RESULTS.md
    python bench/selfcontact.py --device cuda:0 --profile  # where the pass's time goes, per launch
    python bench/selfcontact.py --device cpu --sizes 16 32
    python bench/selfcontact.py --device cpu --sizes 16 --radius-study   # the cap's pair counts by radius

``--radius-study`` steps the ``self`` scene through its fall (the settling frames, every substep uncaptured)
and, every fourth substep, counts on the host in float64 the pairs a radius-based cap would have to examine
(pairs with D < max over their vertices of r, r = min(δ/γ, 32τ) from each vertex's repelled displacement δ,
and with r = 32τ) against the pairs the swept-box cap listed.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import time

import numpy as np
import warp as wp

import warpspring as ws
from cloth import FPS, SUBSTEPS, emit_table, measure
from contacts import SETTLE_FRAMES, contact_model

THICKNESS = 0.02  # [m]
FRICTION = 0.3


def scene(n: int, device, self_collision: bool) -> ws.Model:
    if not self_collision:
        return contact_model(n, device, "fused")
    # contact_model's builder, with self-collision added before finalize.
    original = ws.ModelBuilder.finalize

    def finalize(builder, *args, **kwargs):
        builder.add_self_collision(thickness=THICKNESS, friction=FRICTION)
        return original(builder, *args, **kwargs)

    ws.ModelBuilder.finalize = finalize
    try:
        return contact_model(n, device, "fused")
    finally:
        ws.ModelBuilder.finalize = original


class Runner:
    def __init__(self, model: ws.Model):
        self.sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=None)
        for _ in range(SETTLE_FRAMES):
            self.sim.step_frame()

    def frame(self):
        self.sim.step_frame()


class PassRunner(Runner):
    """The self-collision pass alone, SUBSTEPS times per frame, on the settled state (captured on CUDA)."""

    def __init__(self, model: ws.Model):
        super().__init__(model)
        self.model = model
        self.start = model.state()
        self.start.assign(self.sim.state)
        self.out = model.state()
        self.dt = 1.0 / (FPS * SUBSTEPS)
        self.graph = None
        if model.self_contact.capturable:
            self._substeps()  # loads every module before the capture
            with wp.ScopedCapture(device=model.device) as capture:
                self._substeps()
            self.graph = capture.graph

    def _substeps(self):
        for _ in range(SUBSTEPS):
            wp.copy(self.out.particle_q, self.start.particle_q)
            wp.copy(self.out.particle_qd, self.start.particle_qd)
            self.model.self_contact(self.start, self.out, self.dt)

    def frame(self):
        if self.graph is not None:
            wp.capture_launch(self.graph)
        else:
            self._substeps()


def profile(n: int, device, repeats: int) -> list[str]:
    """Markdown rows: each launch of the pass, its calls and time per pass [µs], on the settled ``self`` scene."""
    import warpspring.core.selfcontact as host

    runner = Runner(scene(n, device, True))
    model, sc = runner.sim.model, runner.sim.model.self_contact
    start, out = model.state(), model.state()
    start.assign(runner.sim.state)
    dt = 1.0 / (FPS * SUBSTEPS)

    def one_pass():
        wp.copy(out.particle_q, start.particle_q)
        wp.copy(out.particle_qd, start.particle_qd)
        sc(start, out, dt)

    one_pass()  # loads every module
    kernels = host.__dict__
    labelled = []
    for swept, stage in ((False, "repulsion"), (True, "cap")):
        labelled += [(kernels["leaf_kernel"](model.scalar, swept), f"triangle boxes ({stage})"),
                     (kernels["broad_vt_kernel"](model.scalar, swept), f"broad phase VT ({stage})"),
                     (kernels["broad_ee_kernel"](model.scalar, swept), f"broad phase EE ({stage})")]
    labelled += [(kernels["fill_kernel"](), "CSR fill (both stages)"),
                 (kernels["repel_pairs_kernel"](model.scalar), "narrow phase: repulsion per pair"),
                 (kernels["repel_gather_kernel"](model.scalar), "gather: repulsion per vertex"),
                 (kernels["cap_gather_kernel"](model.scalar), "gather: cap per vertex")]
    by_id = {id(kernel): text for kernel, text in labelled}
    by_name = {}
    for kernel, text in labelled:
        try:
            by_name[kernel.get_mangled_name()] = text
        except RuntimeError:  # not loaded on this device
            pass

    def label(name: str) -> str:
        """A CUDA activity's name in words (kernels of the pass; other activities as Warp names them)."""
        return next((text for mangled, text in by_name.items() if name.startswith(mangled)), name)

    times = collections.defaultdict(float)
    calls = collections.Counter()
    wp.synchronize_device(device)
    wall = time.perf_counter()
    if device.is_cuda:
        with wp.ScopedTimer("pass", cuda_filter=wp.TIMING_ALL, synchronize=True, print=False,
                            report_func=lambda *args: None) as timer:
            for _ in range(repeats):
                one_pass()
        for result in timer.timing_results:
            times[label(result.name)] += result.elapsed * 1e3
            calls[label(result.name)] += 1
    else:
        def timed(name_of, call):
            def wrapper(*args, **kwargs):
                wp.synchronize_device(device)
                t0 = time.perf_counter()
                call(*args, **kwargs)
                wp.synchronize_device(device)
                name = name_of(*args)
                times[name] += (time.perf_counter() - t0) * 1e6
                calls[name] += 1
            return wrapper

        saved = host.flat_launch, wp.utils.array_scan, wp.Bvh.refit
        host.flat_launch = timed(lambda kernel, *a: by_id.get(id(kernel), kernel.key), host.flat_launch)
        wp.utils.array_scan = timed(lambda *a: "array_scan", wp.utils.array_scan)
        wp.Bvh.refit = timed(lambda *a: "Bvh.refit", wp.Bvh.refit)
        try:
            for _ in range(repeats):
                one_pass()
        finally:
            host.flat_launch, wp.utils.array_scan, wp.Bvh.refit = saved
    wp.synchronize_device(device)
    wall = (time.perf_counter() - wall) / repeats * 1e6
    listed = {k: int(v.sum()) for k, v in sc.listed().items()}
    rows = []
    for name, total in sorted(times.items(), key=lambda item: -item[1]):
        rows.append(f"| {n} | {name} | {calls[name] / repeats:g} | {total / repeats:.1f} |")
    rows.append(f"| {n} | sum of the above | | {sum(times.values()) / repeats:.1f} |")
    rows.append(f"| {n} | the pass, wall clock (profiler on) | | {wall:.1f} |")
    rows.append(f"| {n} | pairs listed: repulsion / cap | | {listed['repel']} / {listed['cap']} "
                f"(capacity {sc.capacity}) |")
    return rows


def radius_study(n: int, device) -> list[str]:
    """Markdown rows: mean and peak pairs per substep by the cap's candidate rule, through the fall."""
    from warpspring.analysis.audit import brute_pairs, surface_edges
    from warpspring.kernels.selfcontact import SEARCH_REACH

    model = scene(n, device, True)
    sc = model.self_contact
    integrator = ws.SymplecticEuler(model)
    a, b = model.state(), model.state()
    dt = 1.0 / (FPS * SUBSTEPS)
    triangles = model.tri_indices.numpy()
    edges = surface_edges(triangles)
    gamma = 0.25
    counts = {"listed": [], "radius": [], "fixed": []}
    for k in range(SETTLE_FRAMES * SUBSTEPS):
        integrator.step(a, b, None, dt)
        if k % 4 == 3:
            x0 = a.particle_q.numpy().astype(np.float64)
            step = np.linalg.norm(sc.corrected.numpy().astype(np.float64) - x0, axis=1)
            reach = SEARCH_REACH * THICKNESS
            radius = np.minimum(step / gamma, reach)
            vt, dvt, ee, dee = brute_pairs(x0, triangles, reach)
            members = np.concatenate([np.concatenate([vt[:, :1], triangles[vt[:, 1]]], axis=1),
                                      np.concatenate([edges[ee[:, 0]], edges[ee[:, 1]]], axis=1)])
            distance = np.concatenate([dvt, dee])
            counts["radius"].append(int(np.sum(distance < radius[members].max(axis=1))))
            counts["fixed"].append(len(distance))
            counts["listed"].append(int(sc.listed()["cap"].sum()))
        a, b = b, a
    return [f"| {n} | {name} | {np.mean(v):.0f} | {np.max(v)} |" for name, v in (
        ("swept boxes, kept when max δ > γ(D - K) (this pass)", counts["listed"]),
        ("D < max r over the pair's vertices, r = min(δ/γ, 32τ)", counts["radius"]),
        ("D < 32τ", counts["fixed"]))]


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 256])
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--out", default=None, help="also write the table to this file")
    parser.add_argument("--profile", action="store_true", help="time each launch of one pass instead")
    parser.add_argument("--repeats", type=int, default=20, help="passes averaged by --profile")
    parser.add_argument("--radius-study", action="store_true", help="count the cap's pairs by candidate rule instead")
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    if args.radius_study:
        lines = [
            f"The cap's pairs per substep by candidate rule on {device.name}, Warp {wp.config.version}, "
            f"{datetime.date.today()}: the draped cloth's fall ({SETTLE_FRAMES} frames, every 4th substep), "
            f"τ = {THICKNESS} m, γ = 0.25",
            "",
            "| N | pairs examined by the cap | mean per substep | peak |",
            "|---|---|---|---|",
        ]
        for n in args.sizes:
            lines += radius_study(n, device)
        emit_table(lines, args.out)
        return
    if args.profile:
        lines = [
            f"Self-collision pass per launch on {device.name}, Warp {wp.config.version}, {datetime.date.today()}, "
            f"the settled draped cloth (τ = {THICKNESS} m, μ = {FRICTION}), mean of {args.repeats} uncaptured passes "
            + ("(CUDA activity timer)" if device.is_cuda else "(synchronised wall clock around each launch)"),
            "",
            "| N | launch | calls per pass | µs per pass |",
            "|---|---|---|---|",
        ]
        for n in args.sizes:
            lines += profile(n, device, args.repeats)
        emit_table(lines, args.out)
        return
    lines = [
        f"Cloth draped over a sphere on the ground on {device.name}, Warp {wp.config.version}, "
        f"{datetime.date.today()}, symplectic Euler, {SUBSTEPS} substeps per frame, self-collision τ = "
        f"{THICKNESS} m, μ = {FRICTION}",
        "",
        "| N | without (particle-substeps/s) | with | self-collision's share of the substep | the pass alone, "
        "share of a substep with it | pairs pushed / capped vertices per substep | pairs listed at the last "
        "substep: repulsion / cap (dropped) |",
        "|---|---|---|---|---|---|---|",
    ]
    for n in args.sizes:
        rates = {}
        for variant, make in (("none", lambda: Runner(scene(n, device, False))),
                              ("self", lambda: Runner(scene(n, device, True))),
                              ("pass", lambda: PassRunner(scene(n, device, True)))):
            holder = {}

            def runner():
                holder["runner"] = make()
                return holder["runner"]

            frame_s = measure(runner, device, args.seconds)["frame_s"]
            rates[variant] = n * n * SUBSTEPS / frame_s
            print(f"N={n} {variant}: {rates[variant]:.4g} particle-substeps/s", flush=True)
            if variant == "self":
                sc = holder["runner"].sim.model.self_contact
                sc.reset()
                holder["runner"].frame()
                counts = {k: int(v.sum()) / SUBSTEPS for k, v in sc.counts().items()}
                listed = {k: int(v.sum()) for k, v in sc.listed().items()}
                dropped = int(sc.overflow().sum())
        share = 1.0 - rates["self"] / rates["none"]
        alone = rates["self"] / rates["pass"]
        lines.append(f"| {n} | {rates['none']:.3e} | {rates['self']:.3e} | {100 * share:.0f} % | {100 * alone:.0f} % "
                     f"| {counts['pairs']:.0f} / {counts['capped']:.0f} | {listed['repel']} / {listed['cap']} ({dropped}) |")
    emit_table(lines, args.out)


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
