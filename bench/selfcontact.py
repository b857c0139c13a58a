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

    python bench/selfcontact.py --device cuda:0 --baseline-tree OLD   # the cost table, against OLD's warpspring
    python bench/selfcontact.py --device cuda:0 --sizes 64 256 1024 --timed-frames 16 --example-frames 60 \
        --baseline-tree build/baseline-303e64f   # the same 16 frames in both trees (the pass's bits are the same)
    python bench/selfcontact.py --device cuda:0 --profile  # where the pass's time goes, per launch
    python bench/selfcontact.py --device cuda:0 --sizes 64 256 1024 --broad-forms  # the cache's build by launch form
    python bench/selfcontact.py --device cuda:0 --sizes 64 --broad-forms --broad-trees 1 2 4 8  # ... and by BVH leaf size
    python bench/selfcontact.py --device cpu --sizes 16 32 --example-frames 3 --baseline 65f7792
    python bench/selfcontact.py --device cpu --sizes 16 --radius-study   # the cap's pair counts by radius
    python bench/selfcontact.py --device cpu --sizes 32 64 --rebuild-study 4   # the cache's rebuilds by rule
    python bench/selfcontact.py --device cpu --sizes 64 128 --patch-study 8   # the cache's rebuilds by patch grouping
    python bench/selfcontact.py --device cpu --sizes 32 64 --stage-study 4   # how often the pair stages run, and why
    python bench/selfcontact.py --device cuda:0 --sizes 64 256 --captured-parts 4   # the captured pass, part by part

The cost table (the default mode) times, at each size, the substep without and with self-collision
(``none``, ``self``; ``--pass-alone`` adds ``pass``), and each self-collision example's simulation loop
(``--examples``: its scene, integrator, fps and substeps, no guard and no USD writing; the first frame, which
compiles, untimed; ``--example-frames`` caps the frames, default the scene's) in µs per substep. With
``--baseline REV`` (a ``git worktree`` of REV, made in a temporary folder) or ``--baseline-tree PATH`` (a
checkout, or any folder holding an older ``warpspring/`` package) the same measurement runs again in a
subprocess that imports that tree's ``warpspring`` (this script and its bench helpers are the same), in the
same call, and the table puts the two side by side. ``--json PATH`` writes the numbers.

``--rebuild-study FRAMES`` replays the ``self`` scene's substeps over FRAMES frames after the settling on the host
in float64 and counts the cache's rebuilds under its rules: the pass's before and now, per patch pair, a local check,
anchors per vertex re-anchored where the bound gives up (a partial rebuild's share of the surface), the per-pair bound
no pass can evaluate (it needs every pair), and the pairs' true distances (the fewest rebuilds any rule can make);
``--study-reach TAUS`` sets its cache reach (CACHE_REACH τ by default).

``--radius-study`` steps the ``self`` scene through its fall (the settling frames, every substep uncaptured)
and, every fourth substep, counts on the host in float64 the pairs a radius-based cap would have to examine
(pairs with D < max over their vertices of r, r = min(δ/γ, 32τ) from each vertex's repelled displacement δ,
and with r = 32τ) against the pairs the swept-box cap listed.
"""

from __future__ import annotations

import argparse
import collections
import datetime
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

# This checkout's warpspring (not an installed one), or with --import-from (a baseline run) that tree's.
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
if "--import-from" in sys.argv:
    sys.path.insert(0, os.path.abspath(sys.argv[sys.argv.index("--import-from") + 1]))

import numpy as np
import warp as wp

import warpspring as ws
from cloth import FPS, SUBSTEPS, emit_table, measure
from contacts import SETTLE_FRAMES, contact_model

THICKNESS = 0.02  # [m]
COUNT_FRAMES = 4  # frames after the timing over which the pass's counts are taken
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


#: ``--guard default``: the cost table's runs (the draped cloth with and without self-collision, the examples) with the
#: default guard (``GuardLimits()``, what a user gets) instead of none.
GUARDED = False


class Runner:
    def __init__(self, model: ws.Model):
        self.sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=ws.GuardLimits() if GUARDED else None)
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


def bare_name(name: str) -> str:
    """A CUDA activity's name as Warp gives it, less the module hash."""
    return re.sub(r"_[0-9a-f]{8}$", "", name)


def launch_labels(model) -> tuple[dict, object]:
    """The pass's kernels in words: (by id of the kernel object, a function naming a CUDA activity)."""
    import warpspring.core.selfcontact as host

    kernels = host.__dict__
    labelled = []
    for swept, stage in ((False, "repulsion"), (True, "cap")):
        labelled.append((kernels["leaf_kernel"](model.scalar, swept), f"triangle boxes ({stage})"))
        launches = getattr(model.self_contact, "broad_launches", None)
        if launches is not None:  # its launches as the tree sets them (one, or the vertices' and the edges')
            contact = model.self_contact
            names = {"both": "VT + EE", "vertices": "VT", "edges": "EE"}
            for primitives, _, _ in launches:
                kernel = kernels["broad_kernel"](model.scalar, swept, contact.broad_per_primitive, primitives,
                                                 contact.broad_bounds)
                labelled.append((kernel, f"broad phase {names[primitives]} ({stage})"))
        elif "broad_kernel" in kernels:  # one query per triangle, or per primitive (an earlier tree: its setting)
            per_primitive = getattr(model.self_contact, "broad_per_primitive", None)
            kernel = kernels["broad_kernel"](model.scalar, swept, *([per_primitive] if per_primitive is not None else []))
            labelled.append((kernel, f"broad phase VT + EE ({stage})"))
        else:  # one per vertex and one per edge
            labelled += [(kernels["broad_vt_kernel"](model.scalar, swept), f"broad phase VT ({stage})"),
                         (kernels["broad_ee_kernel"](model.scalar, swept), f"broad phase EE ({stage})")]
    labelled += [(kernels["fill_kernel"](), "CSR fill"),
                 (kernels["repel_pairs_kernel"](model.scalar), "narrow phase: repulsion per pair"),
                 (kernels["repel_gather_kernel"](model.scalar), "gather: repulsion per vertex"),
                 (kernels["cap_gather_kernel"](model.scalar), "gather: cap per vertex")]
    for name, text in (("check_kernel", "cache check per patch corner"), ("cap_bounds_kernel", "cap bounds per cached pair"),
                       ("anchor_kernel", "cache anchors (rebuild)"), ("decide_kernel", "cache decisions per patch pair"),
                       ("watch_kernel", "watched pairs' check"), ("cap_place_kernel", "cap: placing jammed vertices"),
                       ("cap_mark_kernel", "cap: marking movers"), ("cap_check_kernel", "cap: final check")):
        if name in kernels:
            labelled.append((kernels[name](model.scalar), text))
    for name, text in (("reset_kernel", "pair buffer reset"), ("cap_loop_gate_kernel", "cap: loop gate")):
        if name in kernels:
            labelled.append((kernels[name](), text))
    by_id = {id(kernel): text for kernel, text in labelled}
    by_name = {}
    for kernel, text in labelled:
        try:
            by_name[kernel.get_mangled_name()] = text
        except RuntimeError:  # not loaded on this device
            pass

    def label(name: str) -> str:
        """A CUDA activity's name in words (kernels of the pass; other activities as Warp names them, less the
        module hash)."""
        for mangled, text in by_name.items():
            if name.startswith(mangled) or mangled in name:
                return text
        return bare_name(name)

    return by_id, label


def profile_frames(n: int, device, frames: int) -> list[str]:
    """Markdown rows: the kernels of the moving draped cloth's substeps after the settling (uncaptured, so the
    self-collision branches are host tests), CUDA activity time per substep [µs], with and without
    self-collision, over ``frames`` frames."""
    rows = []
    for self_collision in (False, True):
        runner = Runner(scene(n, device, self_collision))
        model = runner.sim.model
        sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=None, use_graph=False)
        sim.reset(runner.sim.state)
        sim.step_frame()  # loads every module the uncaptured path needs
        label = launch_labels(model)[1] if self_collision else bare_name
        times = collections.defaultdict(float)
        calls = collections.Counter()
        with wp.ScopedTimer("frames", cuda_filter=wp.TIMING_ALL, synchronize=True, print=False,
                            report_func=lambda *args: None) as timer:
            for _ in range(frames):
                sim.step_frame()
        for result in timer.timing_results:
            times[label(result.name)] += result.elapsed * 1e3
            calls[label(result.name)] += 1
        substeps = frames * SUBSTEPS
        variant = "with" if self_collision else "without"
        for name, total in sorted(times.items(), key=lambda item: -item[1]):
            rows.append(f"| {n} | {variant} | {name} | {calls[name] / substeps:.3g} | {total / substeps:.1f} |")
        rows.append(f"| {n} | {variant} | **sum** | | **{sum(times.values()) / substeps:.1f}** |")
    return rows


def broad_forms(n: int, device, repeats: int, min_blocks=(), leaf_sizes=()) -> list[str]:
    """Markdown rows: the cache's build (the broad phase without ``swept``, its CSR and its watch list) on the settled
    ``self`` scene, forced for every world, in each form of its launch: the vertices' and the edges' queries in one
    launch or in two (``BROAD_SEPARATE``), by threads per block (``BROAD_BLOCK``); device time per build [µs] (CUDA
    activity timer, mean of ``repeats`` uncaptured builds), the broad kernels' share, and the pairs and watched pairs
    listed (the same in every form). Each K of ``min_blocks`` adds two launches in blocks of 64 whose registers allow
    K blocks a multiprocessor (``BROAD_MIN_BLOCKS``). Each L of ``leaf_sizes`` adds the shipped form on trees of L
    triangles a leaf, built at rest as the pass builds its own and refit to the settled state, by Warp's GPU
    constructor ("lbvh") and its CPU one ("sah")."""
    from warpspring.kernels.flatten import launch_bounds
    from warpspring.kernels.selfcontact import CACHE_REACH

    if not device.is_cuda:
        raise SystemExit("--broad-forms times the CUDA form of the broad phase (one query per primitive): give "
                         "--device cuda:0")
    runner = Runner(scene(n, device, True))
    model = runner.sim.model
    contact = model.self_contact
    start = runner.sim.state.particle_q
    worlds = model.world_count
    active = contact.flags[2:2 + worlds]

    def build():
        active.fill_(1)
        contact._list_pairs(contact.cache, contact.cache_bound, start, start, swept=False, reach_factor=CACHE_REACH,
                            reach_add=0.0, counters=contact.counters, active=active, watch=True)

    def trees(leaf: int, constructor: str):
        """The worlds' BVHs built at rest with ``leaf`` triangles a leaf by ``constructor``, refit to the settled
        state (the pass's own: built at rest, refit at every build)."""
        T = contact.triangle_count
        surface = contact.surface
        contact._leaves(model.particle_q, model.particle_q, swept=False, refit=False)
        contact.bvhs = [wp.Bvh(surface.leaf_lower[w * T:(w + 1) * T], surface.leaf_upper[w * T:(w + 1) * T],
                               constructor=constructor, leaf_size=leaf) for w in range(worlds)]
        surface.bvh = wp.array(np.array([b.id for b in contact.bvhs], dtype=np.uint64), dtype=wp.uint64,
                               device=device)
        contact._leaves(start, start, swept=False)

    rows = []
    shipped = (contact.broad_launches, contact.broad_block, contact.broad_bounds)
    forms = [(separate, block, None, None) for separate in (False, True) for block in (32, 64, 128, 256)]
    forms += [(True, 64, k, None) for k in min_blocks]
    forms += [(None, None, None, (leaf, constructor)) for leaf in leaf_sizes for constructor in ("lbvh", "sah")]
    for separate, block, blocks, tree in forms:
        if tree is None:
            contact.broad_launches = contact.broad_launch_forms(separate)
            contact.broad_block = block
            contact.broad_bounds = launch_bounds(block, blocks)
        else:
            contact.broad_launches, contact.broad_block, contact.broad_bounds = shipped
            trees(*tree)
        build()
        wp.synchronize_device(device)
        with wp.ScopedTimer("build", cuda_filter=wp.TIMING_ALL, synchronize=True, print=False,
                            report_func=lambda *args: None) as timer:
            for _ in range(repeats):
                build()
        per_kernel = collections.defaultdict(float)  # (in launch order: dicts keep their first insertion's)
        for result in timer.timing_results:
            if "broad" in result.name:
                per_kernel[result.name] += result.elapsed * 1e3 / repeats
        broad = list(per_kernel.values())
        every = sum(r.elapsed for r in timer.timing_results) * 1e3 / repeats
        parts = " + ".join(f"{t:.0f}" for t in broad)
        if tree is None:
            bound = f" (≥ {blocks} blocks)" if blocks else ""
            form = f"{'two' if separate else 'one'} | {block}{bound}"
        else:
            form = f"as shipped, trees of {tree[0]} a leaf ({tree[1]}) | {contact.broad_block}"
        rows.append(f"| {n} | {form} | {sum(broad):.0f} ({parts}) | "
                    f"{every:.0f} | {int(contact.cache.count.numpy().sum())} | {int(contact.watch_count.numpy().sum())} |")
    return rows


def profile(n: int, device, repeats: int) -> list[str]:
    """Markdown rows: each launch of the pass, its calls and time per pass [µs], on the settled ``self`` scene."""
    import warpspring.core.selfcontact as host

    WATCH_REACH = getattr(host, "WATCH_REACH", 0.0)
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
    by_id, label = launch_labels(model)
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
        depth = [0]

        def timed(name_of, call):
            def wrapper(*args, **kwargs):
                wp.synchronize_device(device)
                t0 = time.perf_counter()
                depth[0] += 1
                try:
                    call(*args, **kwargs)
                finally:
                    depth[0] -= 1
                wp.synchronize_device(device)
                name = name_of(*args) + (" (inside a branch)" if depth[0] else "")
                times[name] += (time.perf_counter() - t0) * 1e6
                calls[name] += 1
            return wrapper

        saved = [(host, "flat_launch", host.flat_launch), (wp.utils, "array_scan", wp.utils.array_scan),
                 (wp.Bvh, "refit", wp.Bvh.refit)]
        host.flat_launch = timed(lambda kernel, *a: by_id.get(id(kernel), kernel.key), host.flat_launch)
        wp.utils.array_scan = timed(lambda *a: "array_scan", wp.utils.array_scan)
        wp.Bvh.refit = timed(lambda *a: "Bvh.refit", wp.Bvh.refit)
        for branch in ("_rebuild", "_fallback", "_stages"):
            if hasattr(host.SelfContact, branch):
                saved.append((host.SelfContact, branch, getattr(host.SelfContact, branch)))
                setattr(host.SelfContact, branch, timed(lambda *a, b=branch: f"branch {b} (whole)",
                                                        getattr(host.SelfContact, branch)))
        try:
            for _ in range(repeats):
                one_pass()
        finally:
            for owner, name, value in saved:
                setattr(owner, name, value)
    wp.synchronize_device(device)
    wall = (time.perf_counter() - wall) / repeats * 1e6
    listed = {k: int(v.sum()) for k, v in sc.listed().items()}
    rows = []
    for name, total in sorted(times.items(), key=lambda item: -item[1]):
        rows.append(f"| {n} | {name} | {calls[name] / repeats:g} | {total / repeats:.1f} |")
    top = sum(t for name, t in times.items() if "inside a branch" not in name)
    rows.append(f"| {n} | sum of the above (outermost calls) | | {top / repeats:.1f} |")
    rows.append(f"| {n} | the pass, wall clock (profiler on) | | {wall:.1f} |")
    first = listed.get("cache", listed.get("repel"))
    rows.append(f"| {n} | pairs listed: {'cache' if 'cache' in listed else 'repulsion'} / cap | | {first} / "
                f"{listed['cap']} (capacity {sc.capacity}) |")
    if hasattr(sc, "watch_count"):
        rows.append(f"| {n} | pairs watched (between 3τ and {WATCH_REACH:g}τ at the anchors) | | "
                    f"{int(sc.watch_count.numpy().sum())} |")
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


#: The patch groupings ``patch_study`` compares: (at most this many patches, at least this many triangles each).
PATCH_STUDY = ((32, 32), (256, 32), (1024, 8), (4096, 4))


def patches_past_slack(position_low, position_high, drift_low, drift_high, near: float, slack: float) -> np.ndarray:
    """[P, P] booleans: the pairs of patches whose position boxes lie closer than ``near`` [m] and whose drift boxes
    spread further than ``slack`` [m] (``decide_kernel``'s test where the bound gives up), each box given by its
    (low, high) corners, [P, 3] arrays [m]."""
    gap = np.maximum(0.0, np.maximum(position_low[None] - position_high[:, None],
                                     position_low[:, None] - position_high[None]))
    spread = np.maximum(drift_high[:, None] - drift_low[None], drift_high[None] - drift_low[:, None])
    return (np.linalg.norm(gap, axis=-1) < near) & (np.linalg.norm(spread, axis=-1) > slack)


def rebuild_cause(sc) -> tuple[str, int, int]:
    """Which rule asked for the rebuild ``sc`` is about to make (read before it, from the step's flags and patch boxes,
    in float64 as ``kernels/selfcontact_cache.py``'s ``decide_kernel`` tests them, world 0): "decide" where two
    patches closer than 2τ drift apart past the slack (and the world's drift past half of it), "watch" where not but
    the watched pairs were checked, "first" for a cache never built, else "other"; and how many patch pairs were past
    the slack, and how many of those are one patch with itself."""
    from warpspring.kernels.selfcontact import (FLAG_DRIFT, FLAG_WATCH, KINEMATIC_STEPS, PATCH_DRIFT, PATCH_POSITION,
                                                REPULSION_REACH, SAFETY, flag_slot)
    from warpspring.kernels.selfcontact_cache import LENGTH_LIMIT

    worlds = sc.model.world_count
    flags = sc.flags.numpy()
    box = sc.patch_box.numpy()[0].astype(np.int64) - LENGTH_LIMIT
    thickness = float(sc.params.numpy()[0, 0])
    unit = thickness / KINEMATIC_STEPS
    reach = float(sc.cache_reach.numpy()[0])
    if reach == 0.0:
        return "first", 0, 0
    slack = (reach - REPULSION_REACH * thickness) * (1.0 - SAFETY)
    drift = flags[flag_slot(FLAG_DRIFT, 0, worlds)] * unit
    # The boxes [-low, high] in units, as (low, high) corners [m].
    position = (-box[:, PATCH_POSITION + 3:PATCH_POSITION + 6] * unit, box[:, PATCH_POSITION:PATCH_POSITION + 3] * unit)
    drifts = (-box[:, PATCH_DRIFT + 3:PATCH_DRIFT + 6] * unit, box[:, PATCH_DRIFT:PATCH_DRIFT + 3] * unit)
    past = patches_past_slack(*position, *drifts, REPULSION_REACH * thickness * (1.0 + SAFETY), slack)
    pairs, itself = int(np.triu(past).sum()), int(np.trace(past))
    if pairs and drift > 0.5 * slack:
        return "decide", pairs, itself
    return ("watch" if flags[flag_slot(FLAG_WATCH, 0, worlds)] else "other"), pairs, itself


def patch_study(n: int, device, frames: int) -> list[str]:
    """Markdown rows: the cache's rebuilds per substep of the ``self`` scene over ``frames`` frames after the settling,
    the pass as it runs (its own rule, uncaptured: each rebuild a host branch), for each patch grouping of
    ``PATCH_STUDY`` (``kernels/selfcontact.py``'s PATCH_LIMIT, PATCH_LIMIT_CPU and PATCH_TRIANGLES, set before the model
    is made and restored after), with the rule that asked for each (``rebuild_cause``)."""
    import collections

    import warpspring.core.selfcontact as host
    import warpspring.kernels.selfcontact as kernels_module

    saved = (kernels_module.PATCH_LIMIT, kernels_module.PATCH_LIMIT_CPU, kernels_module.PATCH_TRIANGLES)
    rebuild = host.SelfContact._rebuild
    rows = []
    try:
        for limit, least in PATCH_STUDY:
            kernels_module.PATCH_LIMIT = kernels_module.PATCH_LIMIT_CPU = limit
            kernels_module.PATCH_TRIANGLES = least
            model = scene(n, device, True)
            sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=None, use_graph=False)
            for _ in range(SETTLE_FRAMES):
                sim.step_frame()
            causes = []

            def asked(self, start, causes=causes):
                causes.append(rebuild_cause(self))
                return rebuild(self, start)

            host.SelfContact._rebuild = asked
            sc = model.self_contact
            for _ in range(frames):
                sim.step_frame()
            host.SelfContact._rebuild = rebuild
            substeps = frames * SUBSTEPS
            kinds = collections.Counter(cause for cause, _, _ in causes)
            pairs = [p for cause, p, _ in causes if cause == "decide"]
            itself = [s for cause, _, s in causes if cause == "decide"]
            rows.append(f"| {n} | {sc.patch_count} (≤ {limit}, ≥ {least} triangles) | {len(causes) / substeps:.3f} | "
                        + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items()))
                        + f" | {np.mean(pairs) if pairs else 0:.1f} ({np.mean(itself) if itself else 0:.1f}) "
                        f"| {int(sc.watch_count.numpy().sum())} |")
    finally:
        kernels_module.PATCH_LIMIT, kernels_module.PATCH_LIMIT_CPU, kernels_module.PATCH_TRIANGLES = saved
        host.SelfContact._rebuild = rebuild
    return rows


def stage_study(n: int, device, frames: int) -> list[str]:
    """Markdown rows: how often the pass's pair stages run over ``frames`` frames of the ``self`` scene after the
    settling (the pass as it runs, uncaptured: each stage run a host branch), and at each run the least distance of
    any pair at the step's start (the device's broad phase within 3τ, ``SelfContact.proximity``) and what asked for
    the run: a pair within the repulsion's reach 2τ (1 + SAFETY), a free vertex's step past the repulsion's budget
    (FLAG_STEP), or neither (the stages ran for nothing)."""
    import warpspring.core.selfcontact as host
    from warpspring.kernels.selfcontact import (FLAG_KINEMATIC, FLAG_STEP, FLOOR_OFFSET, KINEMATIC_STEPS,
                                                PARAM_RELAXATION, REPULSION_REACH, SAFETY, flag_slot)

    model = scene(n, device, True)
    sim = ws.Simulator(model, fps=FPS, substeps=SUBSTEPS, guard=None, use_graph=False)
    for _ in range(SETTLE_FRAMES):
        sim.step_frame()
    sc = model.self_contact
    tau = sc.thickness
    reach = REPULSION_REACH * tau * (1.0 + SAFETY)
    runs = []
    stages = host.SelfContact._stages

    def counted(self, start, particle_q, state_out, dt):
        flags = self.flags.numpy()
        unit = tau / KINEMATIC_STEPS
        kinematic = flags[flag_slot(FLAG_KINEMATIC, 0, 1)] * unit
        step = flags[flag_slot(FLAG_STEP, 0, 1)] * unit
        gamma = float(self.params.numpy()[0, PARAM_RELAXATION])
        budget = min(gamma * (REPULSION_REACH * tau - kinematic), 0.5 * FLOOR_OFFSET * tau) * (1.0 - SAFETY) ** 2
        at_start = type("Start", (), {"particle_q": start})()
        nearest, count = self.proximity(at_start, 3.0 * tau)
        least = float(nearest[count > 0].min()) if (count > 0).any() else np.inf
        runs.append((least, least < reach, step > budget))
        return stages(self, start=start, particle_q=particle_q, state_out=state_out, dt=dt)

    host.SelfContact._stages = counted
    try:
        for _ in range(frames):
            sim.step_frame()
    finally:
        host.SelfContact._stages = stages
    substeps = frames * SUBSTEPS
    least = [r[0] for r in runs if np.isfinite(r[0])]
    within = sum(r[1] for r in runs)
    stepped = sum(r[2] and not r[1] for r in runs)
    return [f"| {n} | {sc.patch_count} | {len(runs)} / {substeps} | "
            + (f"{min(least) / tau:.3f}-{max(least) / tau:.3f} τ" if least else "none within 3τ")
            + f" | {within} | {stepped} | {len(runs) - within - stepped} |"]


def rebuild_study(n: int, device, frames: int, patch_widths=(0.2, 0.4, 0.8), reach_tau: float | None = None) -> list[str]:
    """Markdown rows: how often the pair cache must be rebuilt over ``frames`` frames after the settling, by rule,
    replayed on the host in float64 over the ``self`` scene's substeps (the cache reach R = ``reach_tau`` τ,
    CACHE_REACH τ by default; a rule rebuilds at a substep where it can no longer prove every pair outside the cache
    REPULSION_REACH τ apart)."""
    from scipy.spatial import cKDTree

    from warpspring.analysis.audit import edge_edge_distance, surface_edges, vertex_triangle_distance
    from warpspring.kernels.selfcontact import CACHE_REACH, REPULSION_REACH

    model = scene(n, device, True)
    sim = ws.Simulator(model, fps=FPS * SUBSTEPS, substeps=1, guard=None)  # one substep per call: the same steps
    for _ in range(SETTLE_FRAMES * SUBSTEPS):
        sim.step_frame()
    path = []
    for _ in range(frames * SUBSTEPS):
        sim.step_frame()
        path.append(sim.state.particle_q.numpy().astype(np.float64))
    triangles = model.tri_indices.numpy().astype(np.int64)
    edges = surface_edges(triangles)
    surface = np.unique(triangles)
    ref = triangles[len(triangles) // 2][0]
    tau = THICKNESS
    reach, near = (CACHE_REACH if reach_tau is None else reach_tau) * tau, REPULSION_REACH * tau
    # Candidate pairs: every pair sharing no vertex whose elements' centres are within 0.5 m at the first substep
    # (0.5 m: further than any element moves relative to another over the frames studied here).
    x0 = path[0]
    vt = [(v, t) for v, ts in enumerate(cKDTree(x0[triangles].mean(1)).query_ball_point(x0, 0.5)) for t in ts
          if v not in triangles[t]]
    vt = np.array(vt, dtype=np.int64).reshape(-1, 2)
    ee = np.array([(a, b) for a, b in cKDTree(x0[edges].mean(1)).query_pairs(0.5)
                   if len({*edges[a], *edges[b]}) == 4], dtype=np.int64).reshape(-1, 2)
    side_a = np.concatenate([np.repeat(vt[:, :1], 2, axis=1), edges[ee[:, 0]]])
    side_b = np.concatenate([triangles[vt[:, 1]], np.concatenate([edges[ee[:, 1]], edges[ee[:, 1], :1]], axis=1)])

    def distances(x):
        return np.concatenate([
            vertex_triangle_distance(x[vt[:, 0]], *(x[triangles[vt[:, 1], k]] for k in range(3))),
            edge_edge_distance(x[edges[ee[:, 0], 0]], x[edges[ee[:, 0], 1]], x[edges[ee[:, 1], 0]],
                               x[edges[ee[:, 1], 1]])])

    def reference(drift, *_):
        r = drift[surface] - drift[ref]
        return np.linalg.norm(r, axis=1).max() > 0.5 * (reach - near)

    def box(drift, *_):
        r = drift[surface] - drift[ref]
        return reference(drift) and np.linalg.norm(r.max(0) - r.min(0)) > reach - near

    def per_pair(drift, anchored, _):
        apart = np.linalg.norm(drift[side_a][:, :, None] - drift[side_b][:, None], axis=-1).max(axis=(1, 2))
        return np.any((anchored >= reach) & (anchored - apart < near))

    def exact(_, anchored, x):
        return np.any((anchored >= reach) & (distances(x) < near))

    # Patches: each triangle belongs to the cell of its first corner's start position (a grid of width ``w``), a
    # patch's boxes (its drifts', its current positions') cover every corner of its triangles.
    def patch_rule(width):
        cells = np.floor(path[0][triangles[:, 0]] / width).astype(np.int64)
        _, patch = np.unique(cells, axis=0, return_inverse=True)
        patch = patch.reshape(-1)
        count = patch.max() + 1

        def boxes(values):
            corners = values[triangles]  # [T, 3, 3]
            low = np.full((count, 3), np.inf)
            high = np.full((count, 3), -np.inf)
            np.minimum.at(low, patch, corners.min(1))
            np.maximum.at(high, patch, corners.max(1))
            return low, high

        def given_up(drift, x):
            """The patch pairs the bound cannot keep apart: [count, count] booleans."""
            return patches_past_slack(*boxes(x), *boxes(drift), near, reach - near)

        def rule(drift, _, x):
            return np.any(given_up(drift, x))

        # Each candidate pair's two patches: a vertex's (its first triangle's), a triangle's, an edge's (a triangle at
        # its first end). The local rule checks the true distances of the pairs across the patch pairs the bound gives
        # up on, and rebuilds only where one outside the cache has come within 2τ; ``checked`` keeps, per substep,
        # the share of patches in such a pair (what a broad phase of those patches alone would query).
        first_triangle = np.full(len(path[0]), -1)
        first_triangle[triangles[::-1].reshape(-1)] = np.repeat(np.arange(len(triangles))[::-1], 3)
        edge_triangle = first_triangle[edges[:, 0]]  # (an edge's patch: a triangle at its first end)
        pair_a = np.concatenate([patch[first_triangle[vt[:, 0]]], patch[edge_triangle[ee[:, 0]]]])
        pair_b = np.concatenate([patch[vt[:, 1]], patch[edge_triangle[ee[:, 1]]]])
        checked = []

        def local(drift, anchored, x):
            pairs = given_up(drift, x)
            across = pairs[pair_a, pair_b]
            checked.append(float(np.any(pairs, axis=1).mean()))  # the share of patches a local broad phase queries
            return bool(np.any(across & (anchored >= reach) & (distances(x) < near)))

        def partial(offset: bool) -> tuple[float, float, float]:
            """Anchors per vertex, re-anchored where the bound gives up: every corner of the patches in a pair it
            gives up on takes a new anchor, again until it holds, either at its position now or (``offset``) where it
            would be had it moved with the reference vertex since its anchor, xᵃ = x - Δ_ref (so that the parts not
            re-anchored, which moved with the cloth, stay within the slack of it). A pair's distance differs from its
            distance between its vertices' anchors by at most their drifts' difference, whatever the anchors, so the
            bound holds as before; what a partial rebuild would re-query is every triangle with a re-anchored corner.
            Returns the mean and largest share of the triangles re-queried a substep, and the share of substeps with
            any (the first build not counted)."""
            anchor = path[0].copy()
            shares = []
            for x in path[1:]:
                moved = np.zeros(len(x), dtype=bool)
                while True:
                    pairs = given_up(x - anchor, x)
                    if not pairs.any():
                        break
                    corners = np.unique(triangles[np.any(pairs, axis=1)[patch]])
                    if moved[corners].all():  # (cannot happen: re-anchored patches have no spread left)
                        break
                    moved[corners] = True
                    anchor[corners] = x[corners] - ((x[ref] - anchor[ref]) if offset else 0.0)
                shares.append(float(moved[triangles].any(axis=1).mean()))
            return float(np.mean(shares)), float(np.max(shares)), float(np.mean(np.array(shares) > 0))
        return rule, local, checked, count, partial

    rules = [("largest drift from the reference vertex ≤ (R - 2τ)/2 (before)", reference),
             ("that, or the drifts' box diagonal ≤ R - 2τ (now)", box)]
    counted = {}
    partials = []
    for width in patch_widths:
        rule, local, checked, count, partial = patch_rule(width)
        rules.append((f"per patch pair ({count} patches of {width:g} m): apart now, or their drifts' spread ≤ R - 2τ",
                      rule))
        name = (f"that ({width:g} m), and where it gives up the true distances of the pairs across those patch pairs "
                f"(a local check)")
        rules.append((name, local))
        counted[name] = checked
        partials.append((width, count, partial))
    rows = []
    for name, rule in (*rules,
                       ("each pair's own largest drift difference (needs every pair: not implementable)", per_pair),
                       ("the pairs' distances themselves (the least any rule can do)", exact)):
        rebuilds, anchor, anchored = 0, None, None
        for x in path:
            if anchor is None or rule(x - anchor, anchored, x):
                anchor, anchored, rebuilds = x, distances(x), rebuilds + 1
        checked = counted.get(name)
        cost = (f"patches in a pair it gives up on, a substep: mean {100 * np.mean(checked):.0f} %, largest "
                f"{100 * max(checked):.0f} %" if checked else "")
        rows.append(f"| {n} | {name} | {rebuilds} / {len(path)} | {cost} |")
    for width, count, partial in partials:
        for offset, how in ((False, "at its position"), (True, "with the reference vertex's drift kept")):
            mean, largest, busy = partial(offset)
            rows.append(f"| {n} | per patch pair ({count} patches of {width:g} m), anchors per vertex: where the bound "
                        f"gives up, its patches re-anchored ({how}) | partial in {100 * busy:.0f} % of the substeps | "
                        f"triangles re-queried a substep: mean {100 * mean:.1f} %, largest {100 * largest:.0f} % |")
    step = np.linalg.norm(np.diff(np.array(path), axis=0), axis=2)
    rows.append(f"| {n} | (a particle's step per substep: median {np.median(step) * 1e3:.2f} mm, largest "
                f"{step.max() * 1e3:.2f} mm) | | |")
    return rows


EXAMPLES = ["twisted_cloth", "stacked_cloths", "cloth_fold_on_bar", "thin_colliders"]


#: ``--captured-parts``: the pass with parts taken out (timing only: a part taken out changes what the pass does),
#: each as the methods of ``SelfContact`` it empties.
CAPTURED_PARTS = (
    ("the pass as it runs", ()),
    ("no rebuilds (the rebuild's conditional node empty)", ("_rebuild",)),
    ("the check and the decisions alone (no watch, rebuild or stages)", ("_watch", "_rebuild", "_stages")),
    ("the check alone", ("_decide", "_watch", "_rebuild", "_stages")),
    ("the flags' memset and the busy branch alone", ("_check", "_decide", "_watch", "_rebuild", "_stages")),
    ("no pass (the integrator's update and the colliders' projection)", ("_flag", "_branch")),
    ("the pass as it runs, no review after a frame (its copies of the counters)", ("post_review", "collect_review")),
    ("no pass and no review", ("_flag", "_branch", "post_review", "collect_review")),
)


def captured_parts(n: int, device, frames: int) -> list[str]:
    """Rows of ``--captured-parts``: µs per substep of the ``self`` scene's captured frames with parts of the pass
    taken out (``CAPTURED_PARTS``), against the scene without self-collision. Each variant starts from the same
    state and cache: the settled state, then one frame of the whole pass (its cache built there); its first frame
    (the capture) untimed; the cache's rebuilds and the pair stages' runs per substep counted over its timed frames."""
    none = fixed_frames(lambda: Runner(scene(n, device, False)), device, frames)[1]
    runner = Runner(scene(n, device, True))
    sim = runner.sim
    sc = sim.model.self_contact
    settled = sim.model.state()
    settled.assign(sim.state)
    rows = [f"| {n} | without self-collision (the one-launch frame) | {none:.1f} | 1.0× | | |"]
    for label, emptied in CAPTURED_PARTS:
        sim.stepper.state.assign(settled)
        sim.stepper._graph, sim.stepper._graphs = None, {}
        sim.step_frame()  # the whole pass: every variant's cache built at the same state
        for name in emptied:
            setattr(sc, name, lambda *args, **kwargs: None)
        sim.stepper._graph, sim.stepper._graphs = None, {}
        runner.frame()  # the capture, untimed
        sc.reset()
        wp.synchronize_device(device)
        start = time.perf_counter()
        for _ in range(frames):
            runner.frame()
        wp.synchronize_device(device)
        us = (time.perf_counter() - start) / (frames * SUBSTEPS) * 1e6
        for name in emptied:
            delattr(sc, name)
        counts = {k: int(v.sum()) / (frames * SUBSTEPS) for k, v in sc.cache_counts().items()}
        print(f"N={n} {label}: {us:.1f} µs per substep, {counts}", flush=True)
        rows.append(f"| {n} | {label} | {us:.1f} | {us / none:.1f}× | {counts['rebuilds']:.3f} | "
                    f"{counts['stages']:.3f} |")
    return rows


def fixed_frames(make_runner, device, frames: int) -> tuple[object, float]:
    """(the runner, µs per substep over ``frames`` frames right after the settling, one warm-up frame first): every
    variant and every tree times the same stretch of the same motion (the pass's results are the same bits)."""
    runner = make_runner()
    runner.frame()  # the first frame after the settling (a graph capture, module loads) is not timed
    wp.synchronize_device(device)
    start = time.perf_counter()
    for _ in range(frames):
        runner.frame()
    wp.synchronize_device(device)
    return runner, (time.perf_counter() - start) / (frames * SUBSTEPS) * 1e6


def cost(n: int, device, seconds: float, pass_alone: bool, timed_frames: int = 0) -> dict:
    """The draped cloth at N = n: µs per substep without and with self-collision (and the pass alone), the pairs
    pushed, vertices capped, cache rebuilds and cap fallbacks per substep over COUNT_FRAMES frames after the
    timing; with ``timed_frames``, timed over exactly that many frames after the settling and its warm-up frame,
    and counted over those and the warm-up frame."""
    result = {}
    if timed_frames:
        for variant, self_collision in (("none", False), ("self", True)):
            def make(s=self_collision):
                runner = Runner(scene(n, device, s))
                if s:
                    runner.sim.model.self_contact.reset()  # counted from the warm-up frame on
                return runner

            runner, result[variant] = fixed_frames(make, device, timed_frames)
            print(f"N={n} {variant}: {result[variant]:.1f} µs per substep over {timed_frames} frames", flush=True)
            if self_collision:
                sc = runner.sim.model.self_contact
                substeps = (timed_frames + 1) * SUBSTEPS
                counts = {k: int(v.sum()) / substeps for k, v in sc.counts().items()}
                if hasattr(sc, "cache_counts"):
                    counts.update({k: int(v.sum()) / substeps for k, v in sc.cache_counts().items()})
                result["counts"] = counts
                result["dropped"] = int(sc.overflow().sum())
        return result
    variants = [("none", lambda: Runner(scene(n, device, False))), ("self", lambda: Runner(scene(n, device, True)))]
    if pass_alone:
        variants.append(("pass", lambda: PassRunner(scene(n, device, True))))
    for variant, make in variants:
        holder = {}

        def runner():
            holder["runner"] = make()
            return holder["runner"]

        result[variant] = measure(runner, device, seconds)["frame_s"] / SUBSTEPS * 1e6
        print(f"N={n} {variant}: {result[variant]:.1f} µs per substep", flush=True)
        if variant == "self":
            sc = holder["runner"].sim.model.self_contact
            sc.reset()
            for _ in range(COUNT_FRAMES):
                holder["runner"].frame()
            substeps = COUNT_FRAMES * SUBSTEPS
            counts = {k: int(v.sum()) / substeps for k, v in sc.counts().items()}
            if hasattr(sc, "cache_counts"):
                counts.update({k: int(v.sum()) / substeps for k, v in sc.cache_counts().items()})
            result["counts"] = counts
            result["dropped"] = int(sc.overflow().sum())
    return result


def example_cost(name: str, device, frames: int | None) -> dict:
    """An example's simulation loop (its scene, integrator, fps and substeps; no guard unless GUARDED, no USD): µs per
    substep over its frames after the first (which compiles), and its self-collision counts over them."""
    from warpspring.core.integrators import make_integrator
    from warpspring.io.scene import load_scene

    path = pathlib.Path(__file__).resolve().parents[1] / "examples" / f"{name}.toml"
    scene_ = load_scene(path)
    model = scene_.finalize(device)
    integrator = make_integrator(scene_.integrator, model, **scene_.integrator_options)
    sim = ws.Simulator(model, integrator=integrator, fps=scene_.fps, substeps=scene_.substeps,
                       guard=ws.GuardLimits() if GUARDED else None)
    frames = scene_.frames if frames is None else min(frames, scene_.frames)
    sim.step_frame()
    model.self_contact.reset()
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(frames - 1):
        sim.step_frame()
    wp.synchronize_device(device)
    substeps = (frames - 1) * scene_.substeps
    sc = model.self_contact
    counts = {k: int(v.sum()) / max(substeps, 1) for k, v in sc.counts().items()}
    if hasattr(sc, "cache_counts"):
        counts.update({k: int(v.sum()) / max(substeps, 1) for k, v in sc.cache_counts().items()})
    us = (time.perf_counter() - t0) / max(substeps, 1) * 1e6
    print(f"{name}: {us:.1f} µs per substep over {frames - 1} frames", flush=True)
    return {"us": us, "frames": frames - 1, "substeps_per_frame": scene_.substeps,
            "particles": model.particle_count, "counts": counts}


def measure_all(args, device) -> dict:
    return {"device": device.name, "warp": wp.config.version, "warpspring": os.path.relpath(os.path.dirname(ws.__file__)),
            "sizes": {str(n): cost(n, device, args.seconds, args.pass_alone, args.timed_frames) for n in args.sizes},
            "examples": {name: example_cost(name, device, args.example_frames) for name in args.examples}}


def baseline_tree(args) -> tuple[str, object]:
    """(the baseline's folder, a cleanup callable): ``--baseline-tree`` as given, or a git worktree of
    ``--baseline`` in a temporary folder."""
    if args.baseline_tree:
        if not (pathlib.Path(args.baseline_tree) / "warpspring" / "__init__.py").exists():
            sys.exit(f"--baseline-tree {args.baseline_tree}: no warpspring/ package there")
        return args.baseline_tree, lambda: None
    root = pathlib.Path(__file__).resolve().parents[1]
    folder = tempfile.mkdtemp(prefix="selfcontact-baseline-")
    subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", folder, args.baseline], check=True,
                   stdout=subprocess.DEVNULL)

    def cleanup():
        subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", folder], check=False)

    return folder, cleanup


def run_baseline(args, argv: list[str]) -> dict:
    """The same measurement in a subprocess importing the baseline's warpspring."""
    folder, cleanup = baseline_tree(args)
    try:
        with tempfile.TemporaryDirectory() as scratch:
            out = os.path.join(scratch, "baseline.json")
            drop = {"--baseline": 1, "--baseline-tree": 1, "--json": 1, "--out": 1}
            rest, skip = [], 0
            for item in argv:
                if skip:
                    skip -= 1
                    continue
                if item in drop:
                    skip = drop[item]
                    continue
                rest.append(item)
            subprocess.run([sys.executable, os.path.abspath(__file__), *rest, "--import-from", folder, "--json", out],
                           check=True)
            with open(out) as f:
                return json.load(f)
    finally:
        cleanup()


def ratio(a, b) -> str:
    return f"{a / b:.1f}×" if a and b else "–"


def counts_text(counts: dict | None) -> str:
    """Cache rebuilds / cap fallbacks / pair stages' runs per substep (a dash for what a tree does not count)."""
    if not counts or "rebuilds" not in counts:
        return "–"
    stages = f"{counts['stages']:.3f}" if "stages" in counts else "–"
    return f"{counts['rebuilds']:.3f} / {counts['fallbacks']:.3f} / {stages}"


def cost_table(new: dict, old: dict | None, args) -> list[str]:
    lines = [
        f"Self-collision's cost on {new['device']}, Warp {new['warp']}, {datetime.date.today()}: the cloth draped "
        f"over a sphere on the ground (symplectic Euler, {SUBSTEPS} substeps per 1/{FPS} s frame, each frame one "
        f"captured graph on CUDA, timed after {SETTLE_FRAMES} frames of settling; self-collision τ = {THICKNESS} m, "
        f"μ = {FRICTION}), µs per substep"
        + (", with the default guard (GuardLimits()) in every run" if GUARDED else ", no guard")
        + (f", against the baseline's warpspring ({old['warpspring']}) measured in the same call" if old else ""),
        "",
        "| N | without | with | with / without | pass cost (with - without) | baseline: with | baseline: with / "
        "without | baseline: pass cost | pass cost, baseline / now | pairs pushed / capped vertices per substep | "
        "cache rebuilds / cap fallbacks / pair stages' runs per substep | baseline: the same |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n, now in new["sizes"].items():
        then = (old or {}).get("sizes", {}).get(n, {})
        c = now["counts"]
        extra_now = now["self"] - now["none"]
        extra_then = then.get("self", 0) - then.get("none", 0) if then else 0
        lines.append(
            f"| {n} | {now['none']:.1f} | {now['self']:.1f} | {ratio(now['self'], now['none'])} | {extra_now:.1f} | "
            f"{then.get('self', float('nan')):.1f} | {ratio(then.get('self'), then.get('none'))} | "
            f"{extra_then if then else float('nan'):.1f} | "
            f"{ratio(extra_then, extra_now) if then else '–'} | {c['pairs']:.1f} / {c['capped']:.1f} | "
            f"{counts_text(c)} | {counts_text(then.get('counts'))} |")
    if new["examples"]:
        lines += [
            "",
            f"Examples, the same call ({new['device']}, Warp {new['warp']}, {datetime.date.today()}): the scene's "
            f"simulation loop (its integrator, fps, substeps; {'the default guard' if GUARDED else 'no guard'}, no USD "
            "writing), µs per substep over the frames after the first",
            "",
            "| example | particles | frames | µs per substep | baseline | baseline / now | pairs pushed per substep "
            "| cache rebuilds / cap fallbacks / pair stages' runs per substep | baseline: the same |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for name, now in new["examples"].items():
            then = (old or {}).get("examples", {}).get(name, {})
            c = now["counts"]
            lines.append(
                f"| {name} | {now['particles']} | {now['frames']} | {now['us']:.1f} | {then.get('us', float('nan')):.1f} "
                f"| {ratio(then.get('us'), now['us'])} | {c['pairs']:.1f} | {counts_text(c)} | "
                f"{counts_text(then.get('counts'))} |")
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=None)
    parser.add_argument("--sizes", type=int, nargs="*", default=[64, 256, 1024],
                        help="cloth sizes N (N × N particles); none (a bare --sizes) times the examples only")
    parser.add_argument("--seconds", type=float, default=1.0)
    parser.add_argument("--out", default=None, help="also write the table to this file")
    parser.add_argument("--json", default=None, help="write the cost table's numbers to this file")
    parser.add_argument("--pass-alone", action="store_true", help="also time the pass alone on the settled state")
    parser.add_argument("--timed-frames", type=int, default=0,
                        help="time exactly this many frames after the settling (the same motion in every run and tree; "
                             "the counts over them) instead of --seconds of batches")
    parser.add_argument("--examples", nargs="*", default=EXAMPLES, help="self-collision examples to time")
    parser.add_argument("--example-frames", type=int, default=None, help="frames per example (default: the scene's)")
    parser.add_argument("--baseline", default=None, help="git revision to measure alongside (a temporary worktree)")
    parser.add_argument("--baseline-tree", default=None, help="a folder holding the baseline's warpspring/ package")
    parser.add_argument("--import-from", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--profile", action="store_true", help="time each launch of one pass instead")
    parser.add_argument("--repeats", type=int, default=20, help="passes averaged by --profile")
    parser.add_argument("--profile-frames", type=int, default=0, metavar="FRAMES",
                        help="time each kernel of FRAMES moving frames after the settling instead (CUDA only)")
    parser.add_argument("--broad-split", type=int, default=None,
                        help="threads per triangle of the broad phase (default: core/selfcontact.py's broad_split)")
    parser.add_argument("--broad-per-triangle", action="store_true",
                        help="the broad phase's queries one per triangle (default: core/selfcontact.py's setting)")
    parser.add_argument("--broad-launches", choices=["one", "two"], default=None,
                        help="the broad phase's vertex and edge queries in one launch or two (default: "
                             "core/selfcontact.py's BROAD_SEPARATE rule)")
    parser.add_argument("--guard", choices=["none", "default"], default="none",
                        help="the cost table's runs with the default guard (GuardLimits()) or none (the default)")
    parser.add_argument("--broad-concurrent", choices=["on", "off"], default=None,
                        help="the broad phase's two launches side by side on two streams or one after the other "
                             "(default: core/selfcontact.py's BROAD_CONCURRENT, off)")
    parser.add_argument("--broad-forms", action="store_true",
                        help="time the cache's build in each form of the broad phase's launch instead (CUDA only)")
    parser.add_argument("--broad-min-blocks", type=int, nargs="*", default=[],
                        help="with --broad-forms, also two launches in blocks of 64 with their registers bounded so "
                             "that K blocks fit a multiprocessor, each K")
    parser.add_argument("--broad-trees", type=int, nargs="*", default=[], metavar="LEAF",
                        help="with --broad-forms, also the shipped form on BVHs of LEAF triangles a leaf (built at "
                             "rest by Warp's GPU and CPU constructors, refit), each LEAF")
    parser.add_argument("--captured-parts", type=int, default=0, metavar="FRAMES",
                        help="time FRAMES captured frames of the pass with parts taken out instead (CAPTURED_PARTS)")
    parser.add_argument("--radius-study", action="store_true", help="count the cap's pairs by candidate rule instead")
    parser.add_argument("--patch-study", type=int, default=0, metavar="FRAMES",
                        help="the cache's rebuilds per substep over FRAMES frames for each patch grouping (PATCH_STUDY)")
    parser.add_argument("--stage-study", type=int, default=0, metavar="FRAMES",
                        help="count the pair stages' runs over FRAMES frames after the settling, and what asked for each")
    parser.add_argument("--rebuild-study", type=int, default=0, metavar="FRAMES",
                        help="count the cache's rebuilds by rule over FRAMES frames after the settling instead")
    parser.add_argument("--study-reach", type=float, default=None, metavar="TAUS",
                        help="the rebuild study's cache reach R in units of τ (default CACHE_REACH; the pass as it "
                             "runs holds WATCH_REACH with its watch list)")
    args = parser.parse_args()
    wp.init()
    device = wp.get_device(args.device)
    if args.broad_split is not None:
        import warpspring.core.selfcontact as host

        host.BROAD_SPLIT = args.broad_split
    if args.broad_per_triangle:
        import warpspring.core.selfcontact as host

        host.BROAD_PER_PRIMITIVE = False
    if args.broad_launches is not None:
        import warpspring.core.selfcontact as host

        host.BROAD_SEPARATE = args.broad_launches == "two"
    global GUARDED
    GUARDED = args.guard == "default"
    if args.broad_concurrent is not None:
        import warpspring.core.selfcontact as host

        host.BROAD_CONCURRENT = args.broad_concurrent == "on"
    today = datetime.date.today()
    # The studies other than the cost table: (asked for, heading, columns, rows for one size); the first asked runs.
    studies = (
        (args.stage_study,
         f"The pair stages' runs on {device.name}, Warp {wp.config.version}, {today}: the draped cloth's "
         f"{args.stage_study} frames after {SETTLE_FRAMES} frames of settling, the pass as it runs, uncaptured "
         f"(τ = {THICKNESS} m)",
         ["N", "patches", "stage runs / substeps", "least pair distance at a run's start",
          "runs with a pair within 2τ (1 + SAFETY)", "runs for a vertex's step past the budget", "runs for neither"],
         lambda n: stage_study(n, device, args.stage_study)),
        (args.rebuild_study,
         f"The pair cache's rebuilds by rule on {device.name}, Warp {wp.config.version}, {today}: the draped cloth's "
         f"{args.rebuild_study} frames after {SETTLE_FRAMES} frames of settling, every substep, replayed on the host in "
         f"float64 (τ = {THICKNESS} m, cache reach R = {args.study_reach or 3:g}τ)",
         ["N", "the cache holds while", "rebuilds / substeps", "its work"],
         lambda n: rebuild_study(n, device, args.rebuild_study, reach_tau=args.study_reach)),
        (args.patch_study,
         f"The pair cache's rebuilds by patch grouping on {device.name}, Warp {wp.config.version}, {today}: the draped "
         f"cloth's {args.patch_study} frames after {SETTLE_FRAMES} frames of settling, the pass as it runs, uncaptured "
         f"(τ = {THICKNESS} m), and the rule that asked for each rebuild (world 0)",
         ["N", "patches", "rebuilds per substep", "asked by", "patch pairs past the slack per decide rebuild "
          "(of them a patch with itself)", "pairs watched at the end"],
         lambda n: patch_study(n, device, args.patch_study)),
        (args.captured_parts,
         f"Self-collision's parts, captured, on {device.name}, Warp {wp.config.version}, {today}: the draped cloth's "
         f"{args.captured_parts} frames after {SETTLE_FRAMES} frames of settling and one untimed, each variant from the "
         f"same state (τ = {THICKNESS} m); a part taken out changes the motion, so the rows time the launches, not the "
         f"scene",
         ["N", "variant", "µs per substep", "over the substep without self-collision", "rebuilds per substep",
          "stage runs per substep"],
         lambda n: captured_parts(n, device, args.captured_parts)),
        (args.radius_study,
         f"The cap's pairs per substep by candidate rule on {device.name}, Warp {wp.config.version}, {today}: the draped "
         f"cloth's fall ({SETTLE_FRAMES} frames, every 4th substep), τ = {THICKNESS} m, γ = 0.25",
         ["N", "pairs examined by the cap", "mean per substep", "peak"],
         lambda n: radius_study(n, device)),
        (args.profile_frames,
         f"Self-collision per kernel on {device.name}, Warp {wp.config.version}, {today}: the draped cloth's "
         f"{args.profile_frames} frames after {SETTLE_FRAMES} frames of settling, uncaptured (CUDA activity timer; the "
         f"branches are host tests), µs of device time per substep (τ = {THICKNESS} m, μ = {FRICTION})",
         ["N", "self-collision", "kernel", "calls per substep", "µs per substep"],
         lambda n: profile_frames(n, device, args.profile_frames)),
        (args.broad_forms,
         f"The pair cache's build per form of the broad phase's launch on {device.name}, Warp {wp.config.version}, "
         f"{today}: the settled draped cloth (τ = {THICKNESS} m), every world rebuilt, device time [µs] a build "
         f"(CUDA activity timer, mean of {args.repeats} uncaptured builds)",
         ["N", "launches (vertices, edges)", "threads a block", "broad kernels (each)", "the whole build",
          "pairs listed", "pairs watched"],
         lambda n: broad_forms(n, device, args.repeats, args.broad_min_blocks, args.broad_trees)),
        (args.profile,
         f"Self-collision pass per launch on {device.name}, Warp {wp.config.version}, {today}, the settled draped cloth "
         f"(τ = {THICKNESS} m, μ = {FRICTION}), mean of {args.repeats} uncaptured passes "
         + ("(CUDA activity timer)" if device.is_cuda else "(synchronised wall clock around each launch)"),
         ["N", "launch", "calls per pass", "µs per pass"],
         lambda n: profile(n, device, args.repeats)),
    )
    for asked, heading, columns, rows in studies:
        if asked:
            lines = [heading, "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
            for n in args.sizes:
                lines += rows(n)
            emit_table(lines, args.out)
            return
    new = measure_all(args, device)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(new, f, indent=1)
    if args.import_from:  # a baseline run: its numbers go back through --json
        return
    old = run_baseline(args, sys.argv[1:]) if (args.baseline or args.baseline_tree) else None
    emit_table(cost_table(new, old, args), args.out)


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
