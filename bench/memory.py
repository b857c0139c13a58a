"""Memory estimates against measured peaks, and the refusals of models and sweeps that do not fit.

Two tables, each row measured in a fresh Python process (a peak is per process):

1. **Estimate vs measured**: for grids, cloth meshes, soft bodies (voxel, grid, tetrahedral, Delaunay),
   emitter pools, many worlds, self-collision, mesh colliders (from OBJ and USD files too) and the substep audit,
   at several sizes, the estimate the
   pre-allocation checks use against the growth of the process's peak resident memory (Linux ``VmHWM``, reset
   through ``/proc/self/clear_refs`` after a warm-up that loads the modules) on the host.
2. **Device**: each row's model finalized on ``--device`` and a simulator's first frame (the default guard on),
   their peak device memory against the estimate's device bytes (less the USD writer's, as no writer is made):
   on a CUDA device the growth of the memory pool's high-water mark (``wp.get_mempool_used_mem_high``) with the
   drop of the device's free memory (``wp.get_device(...).free_memory``, which also holds what is not pooled)
   beside it; on the CPU the peak of every Warp allocation, native ones (BVHs, meshes) included (Warp's
   allocation tracker).

The bound held in both: measured ≤ estimate ≤ 2 × measured.
3. **Refusals**: the oversized scenes at their full sizes, each in a process whose host memory is capped at
   ``--limit`` (8 GiB; the OBJ also at 2 GiB as a cloth and at 1 GiB as a mesh collider, as it fits in 8, and the
   same sheet as a .usdc and a .usda mesh collider at 1 GiB) through
   ``WARPSPRING_MEMORY_LIMIT``: the time, the process's peak resident memory (``VmHWM``, imports included) and
   the one line each is refused with ("ran": it fitted and was built).

Run: ``python bench/memory.py [--device cuda:0] [--quick] [--no-cases] [--out FILE]`` (results in
``bench/results/memory.md``; on CUDA ``memory-cuda.md``, whose refusals are the CPU's: give ``--no-cases``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
CHILD_ENV = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}

# -- the matrix: (kind, size, label) --------------------------------------------------------------------------

MATRIX = [
    ("grid", 256, "cloth grid 256²"), ("grid", 512, "cloth grid 512²"), ("grid", 1024, "cloth grid 1024²"),
    ("mesh", 300, "cloth mesh, 179k triangles"), ("mesh", 600, "cloth mesh, 718k triangles"),
    ("mesh_dihedral", 400, "cloth mesh + hinges, 319k triangles"),
    ("voxel_sphere", 0.005, "voxel sphere r=0.1, 5 mm"), ("voxel_sphere", 0.0025, "voxel sphere r=0.1, 2.5 mm"),
    ("voxel_box", 0.0025, "voxel box 0.3×0.1×0.05, 2.5 mm"),
    ("grid_sphere", 0.006, "grid sphere r=0.1, 6 mm"), ("grid_sphere", 0.004, "grid sphere r=0.1, 4 mm"),
    ("tetrahedral_sphere", 0.008, "tetrahedral sphere r=0.1, 8 mm"),
    ("tetrahedral_sphere", 0.005, "tetrahedral sphere r=0.1, 5 mm"),
    ("delaunay_sphere", 0.006, "Delaunay sphere r=0.1, 6 mm"),
    ("emitter", 1_000_000, "emitter pool 1e6"), ("emitter", 10_000_000, "emitter pool 1e7"),
    ("worlds", 20_000, "20k worlds of 6×6, a frame"), ("worlds", 100_000, "100k worlds of 6×6, a frame"),
    ("selfcontact", 128, "cloth grid 128² + self-collision"), ("selfcontact", 256, "cloth grid 256² + self-collision"),
    ("selfcontact", 512, "cloth grid 512² + self-collision"),
    ("collider_file", 300, "mesh collider from an OBJ, 179k triangles"),
    ("collider_file", 700, "mesh collider from an OBJ, 977k triangles"),
    ("collider", 300, "mesh collider, 179k triangles"), ("collider", 700, "mesh collider, 977k triangles"),
    ("collider_winding", 700, "mesh collider (winding number), 977k triangles"),
    ("collider_usd", 700, "mesh collider from a USD file (quads), 977k triangles"),
    ("collider_usd_triangles", 700, "mesh collider from a USD file (triangles), 977k triangles"),
    ("collider_usd_samples", 300, "mesh collider from a USD file (quads), 179k triangles, 4 time samples"),
    ("audit", 60, "substep audit: two stacked 60² sheets, 4 substeps"),
    ("audit", 120, "substep audit: two stacked 120² sheets, 4 substeps"),
    ("audit_thick", 60, "substep audit with a thickness both sheets lie within: 60², 4 substeps"),
    ("audit_thick", 120, "substep audit with a thickness both sheets lie within: 120², 4 substeps"),
]
QUICK = {("grid", 256), ("mesh", 300), ("voxel_sphere", 0.005), ("tetrahedral_sphere", 0.008),
         ("emitter", 1_000_000), ("worlds", 20_000), ("selfcontact", 128), ("collider_file", 300), ("collider", 300),
         ("collider_usd", 700), ("audit", 60), ("audit_thick", 60)}
#: Rows whose host peak is not compared (the device table holds them): a winding-number mesh's tables on the CPU are
#: allocated in full but touched in part, so the resident memory is below what is allocated (and reserved).
DEVICE_ONLY = {"collider_winding"}
#: Rows measured on the host only (reading a file: nothing on the device).
HOST_ONLY = {"collider_file", "collider_usd", "collider_usd_triangles", "collider_usd_samples"}
#: Substeps a frame of the audit rows (each recorded and audited).
AUDIT_SUBSTEPS = 4

# -- the oversized scenes at full size ---------------------------------------------------------------------------

CASES = {
    "grid 5000²": "b = ws.ModelBuilder(); b.add_cloth_grid(nx=5000, ny=5000, spacing=0.01, mass=1.0); b.finalize('cpu')",
    "grid nx=2 ny=1e7 spacing=1e30": "b = ws.ModelBuilder(); b.add_cloth_grid(nx=2, ny=10_000_000, spacing=1e30, "
                                     "mass=1.0); b.finalize('cpu')",
    "1e6 worlds of 6×6": "b = ws.ModelBuilder(); b.add_cloth_grid(nx=6, ny=6, spacing=0.1, mass=1.0); "
                         "m = b.finalize('cpu', worlds=1_000_000); ws.Simulator(m, fps=60, substeps=1)",
    "tetrahedral at 3 mm": "ws.ModelBuilder().add_soft_body(sphere(0.2), method='tetrahedral', youngs_modulus=1e5, "
                           "density=1000.0, spacing=0.003)",
    "voxel at 2 mm": "ws.ModelBuilder().add_soft_body(sphere(0.2), method='voxel', youngs_modulus=1e5, "
                     "density=1000.0, spacing=0.002)",
    "emitter rate 1e9": "ws.ModelBuilder().add_emitter(rate=1e9, life=1.0)",
    "self-collision on a 1024² cloth": "b = ws.ModelBuilder(); b.add_cloth_grid(nx=1024, ny=1024, spacing=0.001, "
                                       "mass=1.0); b.add_self_collision(thickness=0.0002); b.finalize('cpu')",
    "5M-triangle OBJ": "ws.ModelBuilder().add_cloth_mesh(OBJ, mass=1.0)",
    "5M-triangle OBJ, capped at 2 GiB": "ws.ModelBuilder().add_cloth_mesh(OBJ, mass=1.0)",
    "5M-triangle OBJ as a mesh collider, capped at 1 GiB": "ws.ModelBuilder().add_collider_mesh(OBJ, sides='two_sided')",
    "5M-triangle USD as a mesh collider, capped at 1 GiB": "ws.ModelBuilder().add_collider_mesh(USD, sides='two_sided')",
    "5M-triangle text USD as a mesh collider, capped at 1 GiB": "ws.ModelBuilder().add_collider_mesh(USDA, "
                                                                "sides='two_sided')",
    "sweep 10 axes × 10 values": "plan_sweep({'scene': SCENE, 'axes': {f'cloth.structural.ke{i}': {'log': [1.0, 10.0], "
                                 "'count': 10} for i in range(10)}})",
    "sweep count = 1e9": "plan_sweep({'scene': SCENE, 'axes': {'world.drag': {'range': [0.0, 1.0], "
                         "'count': 1_000_000_000}}})",
    "sweep 1e4 variants": "plan_sweep({'scene': SCENE, 'axes': {'world.drag': {'range': [0.0, 1.0], 'count': 10_000}}})",
}
CASE_PRELUDE = """
import os, sys, time, json, numpy as np, trimesh
import warpspring as ws
from warpspring.analysis.sweep_plan import plan_sweep
def sphere(r): return trimesh.creation.icosphere(subdivisions=4, radius=r)
OBJ = os.environ.get("BENCH_OBJ")
USD = os.environ.get("BENCH_USD")
USDA = os.environ.get("BENCH_USDA")
SCENE = {"cloth": {"nx": 4, "ny": 4, "spacing": 0.1, "mass": 0.1}, "simulation": {"frames": 2}}
start = time.perf_counter()
try:
    CASE
    outcome = "ran"
except Exception as exc:
    outcome = f"{type(exc).__name__}: {exc}"
with open("/proc/self/status") as status:  # VmHWM: this process's own peak (ru_maxrss may carry the parent's)
    peak = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmHWM:"))
print(json.dumps(dict(seconds=time.perf_counter() - start, peak=peak, outcome=outcome)))
"""


def _status(key: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024
    raise KeyError(key)


def _reset_peak() -> int:
    """Reset the high-water mark (Linux) and return the resident memory now [B]; the heap's free pages are handed
    back first (glibc's ``malloc_trim``), so that what the row allocates shows as growth rather than reusing pages
    a warm-up freed."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: the pages stay, the growth may read low
        pass
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    return _status("VmRSS")


def _sheet(k: int):
    """A k × k vertex sheet, wavy (no two vertices at one position): (vertices, faces)."""
    import numpy as np

    xs, ys = np.meshgrid(np.linspace(0.0, 1.0, k), np.linspace(0.0, 1.0, k))
    vertices = np.column_stack([xs.ravel(), ys.ravel(), 0.01 * np.sin(7.0 * xs.ravel())])
    i = np.arange(k * k).reshape(k, k)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, 1:].ravel(), i[1:, :-1].ravel()
    return vertices, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def measure(kind: str, size, device: str) -> dict:
    """In this (fresh) process: one matrix row's host estimate and measured peak growth [B], and on a CUDA
    ``device`` the device estimate and the memory pool's high-water mark [B]."""
    import trimesh
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    import warpspring as ws
    from warpspring.core import memory, soft_topologies
    from warpspring.core.builder import cloth
    from warpspring.core.builder.model_builder import EMITTER_POOL_TEMPORARY

    row = dict(kind=kind, size=size)
    if kind == "grid":
        warm = ws.ModelBuilder()
        warm.add_cloth_grid(nx=8, ny=8, spacing=0.1, mass=1.0)
        warm.finalize("cpu")  # warm-up
        base = _reset_peak()
        b = ws.ModelBuilder()
        b.add_cloth_grid(nx=size, ny=size, spacing=1.0 / size, mass=1.0, pin=["top-left"])
        estimate = b.estimate_memory("cpu")
        b.finalize("cpu")
        row.update(measured=_status("VmHWM") - base, estimate=estimate.finalize_peak,
                   what="build + finalize on the CPU: builder + finalize's copies + model")
    elif kind in ("mesh", "mesh_dihedral"):
        hinges = kind == "mesh_dihedral"
        options = {"dihedral": ws.DihedralMaterial(1.0, 0.0)} if hinges else {}
        vertices, faces = _sheet(size)
        v8, f8 = _sheet(8)
        ws.ModelBuilder().add_cloth_mesh(trimesh.Trimesh(v8, f8, process=False), mass=1.0, **options)
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        base = _reset_peak()
        b = ws.ModelBuilder()
        b.add_cloth_mesh(mesh, mass=1.0, **options)
        per = cloth.MESH_HINGE_TEMPORARY_PER_TRIANGLE if hinges else cloth.MESH_TEMPORARY_PER_TRIANGLE
        t = len(faces)
        e = memory.estimate_memory(particles=len(vertices), springs=3 * t, hinges=3 * t // 2 if hinges else 0,
                                   triangles=t)
        row.update(measured=_status("VmHWM") - base, estimate=e.builder + per * t, triangles=t,
                   what="add_cloth_mesh: builder arrays + temporaries")
    elif kind.endswith("_sphere") or kind.endswith("_box"):
        method, shape = kind.rsplit("_", 1)
        mesh = (trimesh.creation.icosphere(subdivisions=3, radius=0.1) if shape == "sphere"
                else trimesh.creation.box(extents=(0.3, 0.1, 0.05)))
        soft_topologies.build_topology(mesh, method, youngs_modulus=1e5, spacing=0.03)  # warm-up
        planned = soft_topologies.estimate_topology(mesh, method, spacing=size)
        base = _reset_peak()
        topology = soft_topologies.build_topology(mesh, method, youngs_modulus=1e5, spacing=size)
        row.update(measured=_status("VmHWM") - base, estimate=planned.host, particles=topology.particle_count,
                   particles_estimate=planned.particles,
                   springs=sum(len(p) for p, _ in topology.springs.values()), springs_estimate=planned.springs,
                   what="topology: peak of making it (tetrahedral: this process; fTetWild's child is capped)")
    elif kind == "emitter":
        ws.ModelBuilder().add_emitter(rate=10.0, life=1.0)
        base = _reset_peak()
        b = ws.ModelBuilder()
        emitter = b.add_emitter(rate=size / 1.05, life=1.0)
        e = memory.estimate_memory(particles=emitter.capacity)
        row.update(measured=_status("VmHWM") - base, estimate=e.builder + EMITTER_POOL_TEMPORARY * emitter.capacity,
                   what="add_emitter: the pool's builder arrays")
    elif kind == "worlds":
        b, worlds = _builder(kind, size)
        _frame(*_builder(kind, 2), "cpu")  # warm-up: kernels compiled
        estimate = b.estimate_memory("cpu", worlds=worlds)
        base = _reset_peak()
        _frame(b, worlds, "cpu")
        row.update(measured=_status("VmHWM") - base,
                   estimate=max(estimate.finalize_host + estimate.model,
                                estimate.run_host + estimate.device_bytes - estimate.writer),
                   what="finalize + a frame (guard on) on the CPU")
    elif kind in ("selfcontact", "collider", "collider_winding"):
        _builder(kind, 8 if kind == "selfcontact" else 20)[0].finalize("cpu")  # warm-up
        b, _ = _builder(kind, size)
        estimate = b.estimate_memory("cpu")
        base = _reset_peak()
        b.finalize("cpu")
        row.update(measured=_status("VmHWM") - base, estimate=estimate.finalize_peak - estimate.builder,
                   what="finalize on the CPU: finalize's copies + model" + (" + self-collision" if kind == "selfcontact"
                                                                             else " (the mesh's native memory too)"))
    elif kind == "collider_file":
        from warpspring.core.mesh_colliders import MESH_COLLIDER_FILE_FIXED, MESH_COLLIDER_FILE_PER_FACE
        from warpspring.core.mesh_counts import mesh_file_counts

        path = _obj(size)
        ws.ModelBuilder().add_collider_mesh(_obj(20), sides="two_sided")  # warm-up
        vertices, faces = mesh_file_counts(path)
        base = _reset_peak()
        ws.ModelBuilder().add_collider_mesh(path, sides="two_sided")
        needed = MESH_COLLIDER_FILE_PER_FACE * faces + 24 * vertices + MESH_COLLIDER_FILE_FIXED
        row.update(measured=_status("VmHWM") - base, estimate=needed,
                   triangles=faces, what="add_collider_mesh(file): the pre-check's estimate against reading it")
    elif kind.startswith("collider_usd"):
        from warpspring.core.mesh_colliders import usd_collider_bytes
        from warpspring.core.mesh_counts import usd_mesh_counts

        path = _usd(size, triangles=kind.endswith("triangles"), samples=4 if kind.endswith("samples") else 0)
        ws.ModelBuilder().add_collider_mesh(_usd(20), sides="two_sided")  # warm-up: USD loaded
        base = _reset_peak()
        ws.ModelBuilder().add_collider_mesh(path, sides="two_sided")
        counts = usd_mesh_counts(path)
        row.update(measured=_status("VmHWM") - base, estimate=usd_collider_bytes(counts), triangles=counts.triangles,
                   what="add_collider_mesh(USD file): the pre-check's estimate against reading it")
    elif kind.startswith("audit"):
        from warpspring.analysis.audit import SubstepAudit

        b, _ = _builder(kind, size)
        thickness = _audit_thickness(kind, size)
        estimate = b.estimate_memory("cpu", audit_substeps=AUDIT_SUBSTEPS, audit_thickness=thickness is not None)
        sim = ws.Simulator(b.finalize("cpu"), fps=60, substeps=AUDIT_SUBSTEPS)
        sim.step_frame()  # warm-up: the run's kernels and buffers
        small = ws.Simulator(_builder(kind, 6)[0].finalize("cpu"), fps=60, substeps=AUDIT_SUBSTEPS)
        SubstepAudit().attach(small)
        small.step_frame()  # warm-up: IPC Toolkit loaded
        base = _reset_peak()
        SubstepAudit(thickness=thickness).attach(sim)
        sim.step_frame()
        row.update(measured=_status("VmHWM") - base, estimate=estimate.audit_host + estimate.audit,
                   what="attach SubstepAudit and a frame on the CPU: the record, read back, the surface's pairs")
    if kind in DEVICE_ONLY:
        row.update(measured=None)
    if kind not in HOST_ONLY:
        row.update(_measure_device(kind, size, device))
    return row


def _obj(k: int) -> str:
    """A k × k-vertex sheet as an OBJ file in the temporary folder (written once)."""
    path = os.path.join(tempfile.gettempdir(), f"warpspring-bench-sheet-{k}.obj")
    if not os.path.exists(path):
        _write_obj(path + ".part", k)
        os.replace(path + ".part", path)
    return path


def _usd(k: int, *, triangles: bool = False, samples: int = 0) -> str:
    """A k × k-vertex sheet of quads (or triangles) as a .usdc file in the temporary folder (written once), its points
    with ``samples`` time samples."""
    import numpy as np
    from pxr import Usd, UsdGeom, Vt

    path = os.path.join(tempfile.gettempdir(), f"warpspring-bench-sheet-{k}-{'t' if triangles else 'q'}{samples}.usdc")
    if os.path.exists(path):
        return path
    vertices, faces = _sheet(k)
    if not triangles:  # _sheet's two triangles of each square, (a, b, c) and (a, c, d), as the quad (a, b, c, d)
        half = len(faces) // 2
        faces = np.column_stack([faces[:half], faces[half:, 2]])
    stage = Usd.Stage.CreateNew(path + ".part.usdc")
    mesh = UsdGeom.Mesh.Define(stage, "/World/sheet")
    mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(faces), faces.shape[1], dtype=np.int32)))
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(faces.astype(np.int32).ravel()))
    for t in range(max(samples, 1)):
        points = Vt.Vec3fArray.FromNumpy((vertices + [0.0, 0.0, 0.01 * t]).astype(np.float32))
        mesh.GetPointsAttr().Set(points, t) if samples else mesh.GetPointsAttr().Set(points)
    stage.GetRootLayer().Save()
    del stage
    os.replace(path + ".part.usdc", path)
    return path


def _builder(kind: str, size):
    """A row's scene as a builder, and its worlds."""
    import trimesh

    import warpspring as ws

    b = ws.ModelBuilder()
    worlds = 1
    if kind in ("grid", "selfcontact"):
        b.add_cloth_grid(nx=size, ny=size, spacing=1.0 / size, mass=1.0, pin=["top-left"])
        if kind == "selfcontact":
            b.add_self_collision(thickness=0.2 / size)
    elif kind in ("mesh", "mesh_dihedral"):
        vertices, faces = _sheet(size)
        options = {"dihedral": ws.DihedralMaterial(1.0, 0.0)} if kind == "mesh_dihedral" else {}
        b.add_cloth_mesh(trimesh.Trimesh(vertices, faces, process=False), mass=1.0, **options)
    elif kind.endswith("_sphere") or kind.endswith("_box"):
        method, shape = kind.rsplit("_", 1)
        mesh = (trimesh.creation.icosphere(subdivisions=3, radius=0.1) if shape == "sphere"
                else trimesh.creation.box(extents=(0.3, 0.1, 0.05)))
        b.add_soft_body(mesh, method=method, youngs_modulus=1e5, density=1000.0, spacing=size)
    elif kind == "emitter":
        b.add_emitter(rate=size / 1.05, life=1.0)
    elif kind == "worlds":
        b.add_cloth_grid(nx=6, ny=6, spacing=0.1, mass=1.0, pin=["top-left"])
        worlds = size
    elif kind.startswith("audit"):  # two sheets 0.2 spacings apart, a third of a spacing aside: ~9 candidate pairs a vertex
        h = 1.0 / size  # 1 kg a particle: stable at 4 substeps of a 60 fps frame
        b.add_cloth_grid(nx=size, ny=size, spacing=h, particle_mass=1.0)
        b.add_cloth_grid(nx=size, ny=size, spacing=h, particle_mass=1.0, origin=(0.3 * h, 0.3 * h, 0.2 * h),
                         name="upper")
    elif kind in ("collider", "collider_winding"):
        b.add_cloth_grid(nx=4, ny=4, spacing=0.1, mass=1.0)
        winding = kind == "collider_winding"
        b.add_collider_mesh(_obj(size), sides="closed" if winding else "two_sided", winding_number=winding)
    return b, worlds


def _audit_thickness(kind: str, size) -> float | None:
    """The audit rows' thickness [m]: half a spacing for "audit_thick" (the sheets, a fifth of a spacing apart, lie
    within it), none for "audit"."""
    return 0.5 / size if kind == "audit_thick" else None


def _frame(builder, worlds: int, device: str, *, audit: bool = False, thickness: float | None = None):
    """Finalize on ``device`` and run a simulator's first frame (the default guard on; with ``audit`` every substep
    audited); a frame the guard stops has made its allocations all the same. Returns the simulator (its model and
    buffers alive)."""
    import warpspring as ws
    from warpspring.analysis.audit import SubstepAudit

    sim = ws.Simulator(builder.finalize(device, worlds=worlds), fps=60, substeps=AUDIT_SUBSTEPS if audit else 1)
    if audit:
        SubstepAudit(thickness=thickness).attach(sim)
    try:
        sim.step_frame()
    except ws.SimulationError:
        pass
    return sim


def _measure_device(kind: str, size, device: str) -> dict:
    """The row's model on ``device`` and a simulator's first frame: their peak device memory against the estimate's
    device bytes (less the USD writer's: no writer is made). CUDA: the memory pool's high-water mark above the pool's
    use before, and the drop of the device's free memory; CPU: the peak of Warp's allocations (its tracker)."""
    import warp as wp

    from warp._src.context import runtime  # the tracker's counters have no public getter

    b, worlds = _builder(kind, size)
    audit = kind.startswith("audit")
    estimate = b.estimate_memory(device, worlds=worlds, audit_substeps=AUDIT_SUBSTEPS if audit else 0,
                                 audit_thickness=_audit_thickness(kind, size) is not None)
    found = dict(device_estimate=estimate.device_bytes - estimate.writer)
    if wp.get_device(device).is_cuda:  # a fresh process: nothing on the pool yet, its high-water mark at 0
        wp.synchronize_device(device)
        before, free = wp.get_mempool_used_mem_current(device), wp.get_device(device).free_memory
        sim = _frame(b, worlds, device, audit=audit, thickness=_audit_thickness(kind, size))
        wp.synchronize_device(device)  # the free memory read while the model and the simulator are alive
        found.update(device_measured=wp.get_mempool_used_mem_high(device) - before,
                     device_free_drop=free - wp.get_device(device).free_memory, device_how="memory pool high-water mark")
        del sim
    else:
        with wp.ScopedMemoryTracker("bench", print=False):
            runtime.core.wp_alloc_tracker_reset()
            _frame(b, worlds, device, audit=audit, thickness=_audit_thickness(kind, size))
            found.update(device_measured=runtime.core.wp_alloc_tracker_get_peak_bytes(),
                         device_how="Warp allocation tracker peak")
    return found


def run_matrix(device: str, quick: bool) -> list[dict]:
    rows = []
    for kind, size, label in MATRIX:
        if quick and (kind, size) not in QUICK:
            continue
        done = subprocess.run([sys.executable, __file__, "--one", kind, repr(size), "--device", device],
                              capture_output=True, text=True, env=CHILD_ENV, timeout=900)
        if done.returncode != 0:
            print(f"{label}: failed: {done.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
            continue
        row = json.loads(done.stdout.splitlines()[-1])
        row["label"] = label
        rows.append(row)
        host = (f"host: measured {row['measured'] / 2**20:.1f} MiB, estimate {row['estimate'] / 2**20:.1f} MiB "
                f"({row['estimate'] / row['measured']:.2f}×)") if row.get("measured") else "host: —"
        gpu = (f"; device: measured {row['device_measured'] / 2**20:.1f} MiB, estimate "
               f"{row['device_estimate'] / 2**20:.1f} MiB ({row['device_estimate'] / row['device_measured']:.2f}×)"
               if row.get("device_measured") else "")
        print(f"{label}: {host}{gpu}", flush=True)
    return rows


def run_cases(limit: str, quick: bool) -> list[dict]:
    """The issue's cases, each in a process capped at ``limit`` through WARPSPRING_MEMORY_LIMIT."""
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        obj = os.path.join(folder, "sheet.obj")
        usd, usda = os.path.join(folder, "sheet.usdc"), os.path.join(folder, "sheet.usda")
        if not quick:
            _write_obj(obj, 1582)  # 1581² × 2 = 5.0 M triangles
            os.replace(_usd(1582), usd)  # 1581² quads: 5.0 M triangles of the reader's fan
            _usda(usd, usda)
        for name, code in CASES.items():
            if quick and ("OBJ" in name or "USD" in name):
                continue
            cap = next((f"{g}GiB" for g in (1, 2) if f"capped at {g} GiB" in name), limit)
            env = {**CHILD_ENV, "WARPSPRING_MEMORY_LIMIT": cap, "BENCH_OBJ": obj, "BENCH_USD": usd, "BENCH_USDA": usda}
            started = time.perf_counter()
            done = subprocess.run([sys.executable, "-c", CASE_PRELUDE.replace("CASE", code)], capture_output=True,
                                  text=True, env=env, timeout=600)
            wall = time.perf_counter() - started
            if done.returncode != 0 or not done.stdout.strip():
                rows.append(dict(case=name, wall=wall, seconds=None, peak=None,
                                 outcome=f"process failed: {done.stderr.strip().splitlines()[-1:]}"))
                continue
            row = json.loads(done.stdout.splitlines()[-1])
            row.update(case=name, wall=wall)
            rows.append(row)
            print(f"{name}: {row['seconds']:.1f} s, peak {row['peak'] / 2**30:.2f} GiB: {row['outcome'][:160]}",
                  flush=True)
    return rows


def _usda(usdc: str, usda: str) -> None:
    """The .usdc file ``usdc`` saved as text (``usda``), in a child process (its layer's memory freed with it)."""
    code = f"from pxr import Sdf; Sdf.Layer.FindOrOpen({usdc!r}).Export({usda!r})"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=900)


def _write_obj(path: str, k: int) -> None:
    """A k × k-vertex sheet as an OBJ file, written in blocks (2(k-1)² triangles)."""
    import numpy as np

    vertices, faces = _sheet(k)
    with open(path, "w") as f:
        for start in range(0, len(vertices), 1 << 20):
            np.savetxt(f, vertices[start:start + (1 << 20)], fmt="v %.6f %.6f %.6f")
        for start in range(0, len(faces), 1 << 20):
            np.savetxt(f, faces[start:start + (1 << 20)] + 1, fmt="f %d %d %d")


def report(rows: list[dict], cases: list[dict], device: str, limit: str, command: str) -> str:
    import warp as wp

    # Said above every table (tests/test_readme.py): the device, the Warp version and the date.
    measured_on = (f"Device: {device}{'' if str(device) == 'cpu' else ' (' + wp.get_device(device).name + ')'} "
                   f"({platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores); "
                   f"Warp {wp.config.version}; {datetime.date.today().isoformat()}")
    lines = [
        "# Memory: estimates against measured peaks, and refusals", "",
        f"Command: `{command}`  ",
        measured_on, "",
        "## Estimate vs measured (host: growth of the peak resident memory)", "",
        "| scene | what | measured | estimate | estimate / measured |", "|---|---|---|---|---|",
    ]
    for r in rows:
        if not r.get("measured"):
            continue
        ratio = r["estimate"] / r["measured"]
        lines.append(f"| {r['label']} | {r['what']} | {r['measured'] / 2**20:.1f} MiB | {r['estimate'] / 2**20:.1f} MiB"
                     f" | {ratio:.2f}{'' if 1.0 <= ratio <= 2.0 else ' **outside [1, 2]**'} |")
    unmeasured = [r["label"] for r in rows if r.get("measured", 0) is None]
    if unmeasured:
        lines += ["", f"Not compared on the host (the device table holds them): {', '.join(unmeasured)}: a winding-number "
                  "mesh's tables are allocated in full but touched in part on the CPU, so its resident memory stays "
                  "below what is allocated."]
    gpu = [r for r in rows if r.get("device_measured")]
    if gpu:
        cuda = str(device).startswith("cuda")
        how = ("growth of the memory pool's high-water mark; the drop of the device's free memory beside it" if cuda
               else "peak of Warp's allocations, native ones included (its allocation tracker)")
        lines += ["", f"## Device ({device}: the model and a simulator's first frame; measured: {how})", "",
                  measured_on, "",
                  "| scene | measured | " + ("free memory drop | " if cuda else "") + "estimate | estimate / measured |",
                  "|---|---|" + ("---|" if cuda else "") + "---|---|"]
        for r in gpu:
            ratio = r["device_estimate"] / r["device_measured"]
            drop = f"{r['device_free_drop'] / 2**20:.1f} MiB | " if cuda else ""
            lines.append(f"| {r['label']} | {r['device_measured'] / 2**20:.1f} MiB | {drop}"
                         f"{r['device_estimate'] / 2**20:.1f} MiB | {ratio:.2f}"
                         f"{'' if 1.0 <= ratio <= 2.0 else ' **outside [1, 2]**'} |")
    if cases:
        lines += ["", f"## The issue's cases, host memory capped at {limit} (WARPSPRING_MEMORY_LIMIT)", "", measured_on, "",
                  "| case | time to refusal | peak RSS | the line |", "|---|---|---|---|"]
        for c in cases:
            seconds = "—" if c.get("seconds") is None else f"{c['seconds']:.1f} s"
            peak = "—" if c.get("peak") is None else f"{c['peak'] / 2**30:.2f} GiB"
            text = c["outcome"].replace("|", "\\|").replace("\n", " ⏎ ")
            lines.append(f"| {c['case']} | {seconds} | {peak} | {text[:400]} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true", help="the smaller sizes only, no 5M-triangle OBJ")
    parser.add_argument("--limit", default="8GiB", help="host memory cap of the issue's cases")
    parser.add_argument("--no-cases", action="store_true")
    parser.add_argument("--out", help="results file (default bench/results/memory.md, on CUDA memory-cuda.md)")
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        import ast

        print(json.dumps(measure(args.one[0], ast.literal_eval(args.one[1]), args.device)))
        return
    rows = run_matrix(args.device, args.quick)
    cases = [] if args.no_cases else run_cases(args.limit, args.quick)
    command = "python bench/memory.py " + " ".join(sys.argv[1:])
    text = report(rows, cases, args.device, args.limit, command.strip())
    out = args.out or os.path.join(HERE, "results", "memory.md" if args.device == "cpu" else "memory-cuda.md")
    with open(out, "w") as f:
        f.write(text)
    print(text)


if __name__ == "__main__":
    main()
