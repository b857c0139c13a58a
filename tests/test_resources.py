"""Resources checked before they are spent: every model's host memory estimated before its arrays are made and
refused in one line when it cannot fit, and sweeps that stream their variants and refuse more than a limit.

The machine's memory is stood in for by a small number (``memory.available_memory`` replaced, or
``WARPSPRING_MEMORY_LIMIT`` set), so that the real refusal path runs on small scenes; the full sizes of the
issue (a 5000² grid, 1e6 worlds, tets at 3 mm, a 5 M-triangle OBJ, ...) are measured in ``bench/memory.py``.
Where a refusal must come before the expensive step, that step is replaced by one that fails the test.
"""

from __future__ import annotations

import itertools
import os
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import trimesh

import warpspring as ws
from warpspring.analysis.sweep_plan import MAX_VARIANTS, SHOWN_PROBLEMS, plan_sweep
from warpspring.core import memory, mesh_counts, soft_topologies
from warpspring.core.builder import cloth
from warpspring.core.memory import AvailableMemory

SCENE = {
    "version": 2,
    "simulation": {"fps": 60.0, "frames": 2, "substeps": 2},
    "cloth": {"grid": {"nx": 4, "ny": 4, "spacing": 0.1}, "particle_mass": 0.1, "pin": ["top-left"]},
}


def _host(monkeypatch, available: int) -> None:
    """Stand for a machine with ``available`` bytes of host memory."""
    monkeypatch.setattr(memory, "available_memory", lambda device=None: AvailableMemory(host=int(available)))


def _rss() -> int:
    """This process's resident memory [B] (Linux; 0 elsewhere)."""
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS:"))
    except (OSError, StopIteration):
        return 0


def _one_line(exc: pytest.ExceptionInfo) -> str:
    message = str(exc.value)
    assert "\n" not in message, message
    return message


# -- grids -------------------------------------------------------------------------------------------------------


def _grid_needs(nx: int, ny: int) -> tuple[int, int]:
    """(what the old check counted: the builder's arrays and the grid's temporaries; what building and finalizing
    needs on the host: the builder's arrays and finalize's copies) for a default grid [B]."""
    n = nx * ny
    springs = (ny * (nx - 1) + (ny - 1) * nx) + 2 * (nx - 1) * (ny - 1) + (ny * (nx - 2) + (ny - 2) * nx)
    estimate = ws.estimate_memory(particles=n, springs=springs, triangles=2 * (nx - 1) * (ny - 1))
    temporary = cloth.GRID_TEMPORARY_PER_SPRING * springs + cloth.GRID_TEMPORARY_PER_PARTICLE * n
    return estimate.builder + temporary, estimate.builder + estimate.finalize_host


@pytest.mark.parametrize("nx, ny, spacing", [(300, 300, 0.01), (2, 40_000, 1e30)])
def test_a_grid_whose_finalize_cannot_fit_is_refused_before_it_is_built(monkeypatch, nx, ny, spacing):
    """The 5000² grid and the nx = 2, ny = 1e7, spacing = 1e30 grid of the issue passed the old check, which
    counted the builder's arrays but not finalize's copies (~3× more: the incidence tables' sort), and ground on
    for minutes. With memory for the builder's arrays but not for finalize's copies, the grid is refused at
    once, in one line, with nothing added."""
    old, needed = _grid_needs(nx, ny)
    assert needed > 1.3 * old  # the case the old check let through
    _host(monkeypatch, (old + needed) // 2)
    builder = ws.ModelBuilder()
    with pytest.raises(ws.ConfigError, match=rf"a {nx} × {ny} cloth grid needs an estimated .* with finalize's copies"
                                             rf".* is available: use a smaller grid") as caught:
        builder.add_cloth_grid(nx=nx, ny=ny, spacing=spacing, mass=1.0)
    assert memory.format_bytes(needed) in _one_line(caught)
    assert builder.particle_count == 0
    _host(monkeypatch, needed + 1)  # just enough: built
    assert len(ws.ModelBuilder().add_cloth_grid(nx=nx, ny=ny, spacing=spacing, mass=1.0).ravel()) == nx * ny


def test_a_grid_added_to_a_scene_counts_the_scene(monkeypatch):
    """The check counts what the builder holds already: a second grid that would fit alone is refused beside a
    first one when the two do not fit together."""
    _, one = _grid_needs(200, 200)
    _host(monkeypatch, int(1.5 * one))
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=200, ny=200, spacing=0.01, mass=1.0)
    with pytest.raises(ws.ConfigError, match="a 200 × 200 cloth grid needs"):
        builder.add_cloth_grid(nx=200, ny=200, spacing=0.01, mass=1.0, origin=(0, 0, 1))
    assert builder.particle_count == 200 * 200


# -- worlds: a process's own limit ---------------------------------------------------------------------------


def test_many_worlds_are_refused_within_the_process_memory_limit(monkeypatch):
    """1e6 worlds of a 6 × 6 cloth passed the check on a machine with the memory free while its watch allowed
    8 GiB. WARPSPRING_MEMORY_LIMIT tells the checks what the process may use: finalize refuses a world count
    whose estimate exceeds it, naming fewer worlds that fit."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, mass=1.0, pin=["top-left"])
    estimate = builder.estimate_memory("cpu", worlds=20_000)
    monkeypatch.setenv("WARPSPRING_MEMORY_LIMIT", str(_rss() + estimate.host_bytes // 2))
    with pytest.raises(ws.ConfigError, match=r"does not fit in memory.*fewer worlds \(about \d+ fit\)") as caught:
        builder.finalize("cpu", worlds=20_000)
    _one_line(caught)


def test_the_memory_limit_variable_is_read_and_checked(monkeypatch):
    """Byte counts with binary or decimal units; a malformed value is a one-line ConfigError."""
    assert memory.parse_bytes("8GiB") == 8 * 2**30 and memory.parse_bytes("1.5 GB") == 1_500_000_000
    assert memory.parse_bytes("512M") == 512 * 2**20 and memory.parse_bytes("1000") == 1000
    monkeypatch.setenv("WARPSPRING_MEMORY_LIMIT", "lots")
    with pytest.raises(ws.ConfigError, match="WARPSPRING_MEMORY_LIMIT must be a number of bytes"):
        memory.host_available_memory()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_AS and /proc are Linux's")
def test_an_address_space_limit_counts_as_the_available_memory():
    """A process started under an address-space limit (ulimit -v, a job scheduler's) has at most that limit less
    what it has mapped available, whatever the machine has free."""
    code = ("import resource; hard = resource.getrlimit(resource.RLIMIT_AS)[1]; "
            "cap = 6 * 2**30 if hard == resource.RLIM_INFINITY else min(6 * 2**30, hard); "
            "resource.setrlimit(resource.RLIMIT_AS, (cap, hard)); "
            "from warpspring.core import memory; print(memory.host_available_memory(), cap)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    available, cap = map(int, done.stdout.split())
    assert 0 < available < cap


# -- soft bodies -------------------------------------------------------------------------------------------------


def _sphere():
    return trimesh.creation.icosphere(subdivisions=3, radius=0.1)


def _no_topology(*args, **kwargs):
    raise AssertionError("the topology was generated before the memory check")


@pytest.mark.parametrize("method, spacing", [("voxel", 0.002), ("tetrahedral", 0.003), ("grid", 0.002),
                                             ("delaunay", 0.002)])
def test_a_soft_body_that_cannot_fit_is_refused_before_its_topology(monkeypatch, method, spacing):
    """Soft bodies were not estimated: tets at 3 mm grew to 8 GiB in 205 s, voxels at 2 mm to 4.3 GiB. The
    topology's counts and host peak are estimated from the body's volume and area and the spacing; one that
    does not fit is refused in one line before anything is generated."""
    _host(monkeypatch, 32 * 2**20)  # below each estimate here (~0.7 GiB for the voxels, ~1 GiB for the tets)
    monkeypatch.setattr(soft_topologies, "build_topology", _no_topology)
    with pytest.raises(ws.ConfigError, match=rf"a {method} soft body at spacing {spacing} \(~[\d,]+ particles.* "
                                             r"needs an estimated .* use a larger spacing") as caught:
        ws.ModelBuilder().add_soft_body(_sphere(), method=method, youngs_modulus=1e5, density=1000.0,
                                        spacing=spacing)
    _one_line(caught)


def test_the_voxel_estimate_bounds_the_counts_it_builds():
    """The voxel estimate's counts are upper bounds of what is built, within 2× (the host peak's bound is held
    on larger bodies in bench/memory.py)."""
    mesh = _sphere()
    planned = soft_topologies.estimate_topology(mesh, "voxel", spacing=0.01)
    topology = soft_topologies.build_topology(mesh, "voxel", youngs_modulus=1e5, spacing=0.01)
    springs = sum(len(p) for p, _ in topology.springs.values())
    assert topology.particle_count <= planned.particles <= 2 * topology.particle_count
    assert springs <= planned.springs <= 2 * springs


def test_ftetwild_runs_in_a_child_capped_in_memory():
    """fTetWild's peak cannot be predicted: it runs in a child process whose address space is capped, and a
    run beyond the cap is refused in one line (here 300 MiB for tets at 3 mm in a 0.1 m sphere), while this
    process's memory stays put."""
    pytest.importorskip("pytetwild")
    mesh = _sphere()
    options = dict(edge_length_abs=0.003, epsilon=1e-3, optimize=True, coarsen=False, num_threads=1, quiet=True)
    before = _rss()
    with pytest.raises(ws.ConfigError, match=r"fTetWild ran out of memory tetrahedralizing 1,280 triangles at edge "
                                             r"length 0.003 m \(its process was limited to .*300 MiB\)") as caught:
        soft_topologies.run_tetwild(np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int32), options,
                                    limit=300 * 2**20)
    _one_line(caught)
    assert _rss() - before < 64 * 2**20


# -- emitters and meshes -------------------------------------------------------------------------------------


def test_an_emitter_pool_that_cannot_fit_is_refused_before_it_is_made(monkeypatch):
    """An emitter of rate 1e9 allocated its pool before any check (8 GiB at 87 s). The pool (rate × life plus 5 %)
    is checked first: refused in one line naming the rate and life, and nothing is added."""
    _host(monkeypatch, 16 * 2**20)
    builder = ws.ModelBuilder()
    with pytest.raises(ws.ConfigError, match=r"emitter 'emitter': a pool of 1,050,000 particles needs an estimated "
                                             r".* lower its rate × life \(1e\+06/s × 1 s\)") as caught:
        builder.add_emitter(rate=1e6, life=1.0)
    _one_line(caught)
    assert builder.particle_count == 0
    _host(monkeypatch, 2**30)
    assert builder.add_emitter(rate=1e6, life=1.0).capacity == 1_050_000


def _sheet_obj(path, k: int) -> int:
    xs, ys = np.meshgrid(np.linspace(0.0, 1.0, k), np.linspace(0.0, 1.0, k))
    vertices = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(k * k)])
    i = np.arange(k * k).reshape(k, k)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, 1:].ravel(), i[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    return len(faces)


def test_a_mesh_file_too_large_is_refused_before_it_is_read(monkeypatch, tmp_path):
    """A 5 M-triangle OBJ as a cloth passed 6 GiB. An OBJ's faces are counted by streaming its lines before
    trimesh reads it, and a cloth mesh that cannot fit is refused before it is read."""
    path = tmp_path / "sheet.obj"
    faces = _sheet_obj(path, 120)
    assert mesh_counts.mesh_file_counts(path) == (120 * 120, faces)
    _host(monkeypatch, 2 * 2**20)
    monkeypatch.setattr(cloth, "load_mesh_file", _no_topology)
    with pytest.raises(ws.ConfigError, match=rf"a cloth mesh of {faces:,} triangles \(.*sheet.obj\) needs an "
                                             r"estimated .* decimate the mesh") as caught:
        ws.ModelBuilder().add_cloth_mesh(str(path), mass=1.0)
    _one_line(caught)


def test_a_mesh_given_as_arrays_is_checked_before_its_springs(monkeypatch):
    """A mesh given in memory is checked from its vertex and triangle counts before its edges and springs."""
    mesh = trimesh.creation.icosphere(subdivisions=5)
    _host(monkeypatch, 2 * 2**20)
    builder = ws.ModelBuilder()
    with pytest.raises(ws.ConfigError, match=rf"a cloth mesh of {len(mesh.faces):,} triangles \(cloth\)") as caught:
        builder.add_cloth_mesh(mesh, mass=1.0)
    _one_line(caught)
    assert builder.particle_count == 0


# -- sweeps --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("axes, count", [
    ({f"cloth.structural.ke_{i}": {"log": [1.0, 10.0], "count": 10} for i in range(10)}, 10**10),
    ({"world.drag": {"range": [0.0, 1.0], "count": 1_000_000_000}}, 10**9),
    ({"world.drag": {"range": [0.0, 1.0], "step": 1e-6}}, 1_000_001),
])
def test_a_sweep_beyond_the_limit_is_refused_at_once(axes, count):
    """10 axes × 10 values, or one axis of count = 1e9, built the whole product in memory (4 GiB in 15 s). The
    count comes from the axes' lengths before any value is made: refused in one line, in milliseconds, with
    almost no memory."""
    tracemalloc.start()
    started = time.perf_counter()
    with pytest.raises(ws.ConfigError, match=rf"the sweep has {count:,} variants .* more than the limit of "
                                             rf"{MAX_VARIANTS:,}; nothing ran.*max_variants = {count}") as caught:
        plan_sweep({"scene": SCENE, "axes": axes})
    elapsed = time.perf_counter() - started
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    _one_line(caught)
    assert elapsed < 1.0 and peak < 2**20


def test_a_sweep_above_the_limit_runs_when_the_option_raises_it():
    """10,000 variants started without a word: above the limit a sweep is refused unless [sweep] max_variants
    (or plan_sweep's max_variants) raises it (a stand-in: a limit of 5 and 6 variants)."""
    data = {"scene": SCENE, "sweep": {"max_variants": 5}, "axes": {"world.drag": [0.0, 0.01, 0.02],
                                                                   "simulation.substeps": [2, 4]}}
    with pytest.raises(ws.ConfigError, match=r"the sweep has 6 variants \(3 × 2\), more than the limit of 5"):
        plan_sweep(data)
    assert len(plan_sweep(data, max_variants=6).variants) == 6
    assert len(plan_sweep({**data, "sweep": {"max_variants": 6}}).variants) == 6
    with pytest.raises(ws.ConfigError, match="sweep.max_variants must be an integer >= 1"):
        plan_sweep({**data, "sweep": {"max_variants": 0}})


def test_refused_variants_are_reported_by_their_first_twenty_and_a_count():
    """5,000 invalid variants printed 5,001 lines. The refusal names the first SHOWN_PROBLEMS offenders, one
    line each, and counts them all (a stand-in: 30 of 40 variants refused)."""
    data = {"scene": SCENE, "axes": {"world.drag": [-1.0, -2.0, -3.0, 0.0] * 10}}
    with pytest.raises(ws.ConfigError) as caught:
        plan_sweep(data)
    lines = str(caught.value).splitlines()
    assert lines[0] == f"<sweep>: 30 of 40 variants refused; nothing ran (the first {SHOWN_PROBLEMS} shown):"
    assert len(lines) == 1 + SHOWN_PROBLEMS + 1 and lines[-1] == "  ... and 10 more"
    assert lines[1].startswith("  variant 0 (world.drag=-1") and lines[20].startswith("  variant 25 ")


def test_a_sweeps_variants_stream():
    """The plan holds the axes, not their product: its memory is flat in the variant count (4× the variants,
    the same peak within the axes' own values), and its variants, made when read, are itertools.product's."""
    def plan_peak(n: int):
        data = {"scene": SCENE, "axes": {"world.drag": [0.001 * i for i in range(n)],
                                         "cloth.particle_mass": [0.1 + 0.001 * i for i in range(n)]}}
        plan_sweep(data)  # warm: caches of the parser
        tracemalloc.start()
        plan = plan_sweep(data)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        return plan, peak

    small, small_peak = plan_peak(10)
    large, large_peak = plan_peak(20)
    assert len(small.variants) == 100 and len(large.variants) == 400
    assert large_peak < 1.5 * small_peak
    assert not isinstance(large.variants, list)
    first, last = large.variants[0], large.variants[-1]
    assert (first.index, last.index) == (0, 399)
    assert last.params == {"world.drag": pytest.approx(0.019), "cloth.particle_mass": pytest.approx(0.119)}
    product = list(itertools.product(*large.axes.values()))
    assert [v.params for v in large.variants[18:22]] == [dict(zip(large.axes, c)) for c in product[18:22]]
    assert [v.key for v in large.variants][5] == large.variants[5].key
