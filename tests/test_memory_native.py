"""The memory estimate's parts that live outside the model's own arrays: self-collision (its pair buffers, caches
and per-world BVHs), mesh colliders' ``wp.Mesh`` (boxes, BVH, winding-number tables), and a mesh file's counts
read before the file is (a USD prim's from its arrays' lengths), so that a collider too large is refused before it is
read.

Allocations are measured as Warp makes them: on the CPU by Warp's allocation tracker (arrays and native memory),
on CUDA by the memory pool's counters (``helpers.warp_allocations``).
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

import warpspring as ws
from warpspring.core import memory, mesh_counts
from warpspring.core.builder import colliders as collider_recipes
from warpspring.core.memory import AvailableMemory
from warpspring.core.mesh_colliders import (MESH_COLLIDER_FILE_FIXED, MESH_COLLIDER_FILE_PER_FACE,
                                            MESH_COLLIDER_USD_PER_FACE, MESH_COLLIDER_USD_PER_FANNED_FACE,
                                            MESH_COLLIDER_USD_PER_SAMPLE_VERTEX, USDA_PARSE_PER_BYTE,
                                            usd_collider_bytes)

from helpers import warp_allocations

#: On CUDA the memory pool's counters hold each allocation rounded up to its granularity: a tolerance of 512 B for
#: each of up to 512 allocations (these models make a few hundred).
POOL_SLACK = 512 * 512


def _self_colliding(n: int = 24, m: int = 16, *, second: bool = False) -> ws.ModelBuilder:
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=n, ny=m, spacing=0.02, mass=0.5, pin=["top-left"])
    if second:  # a second cloth that does not collide with itself: its triangles stay out of the surface
        builder.add_cloth_grid(nx=6, ny=5, spacing=0.02, mass=0.1, origin=(0.0, 0.0, 0.5), name="patch")
        builder.add_self_collision(thickness=0.002, meshes="cloth")
    else:
        builder.add_self_collision(thickness=0.002)
    return builder


@pytest.mark.parametrize("precision, worlds, second", [("float32", 1, False), ("float64", 3, True)])
def test_self_collision_is_estimated_as_allocated(device, precision, worlds, second):
    """Self-collision's arrays and BVHs (``memory.self_contact_bytes`` from the surface's counts) with the model's
    arrays equal what finalize leaves allocated: on the CPU within the native descriptors' allowance
    (NATIVE_DESCRIPTOR_BYTES per BVH) and the keyframe tracks' < 1 KiB; on CUDA the BVHs' build temporaries (counted
    as kept: they are the device's peak) come on top. The part is no small share of the model here (a 24 × 16 cloth:
    the pair buffers hold 72 slots per surface vertex), so leaving it out fails the test."""
    builder = _self_colliding(second=second)
    estimate = builder.estimate_memory(device, precision=precision, worlds=worlds)
    builder.finalize(device, precision=precision, worlds=worlds)  # kernels compiled and loaded outside the count
    with warp_allocations(device) as allocated:
        model = builder.finalize(device, precision=precision, worlds=worlds)
    surface = model.self_contact
    expected = estimate.model + estimate.self_contact
    assert estimate.self_contact > estimate.model  # not a negligible part
    assert surface.triangle_count == (2 * 23 * 15) and estimate.self_contact > 0
    slack = memory.NATIVE_DESCRIPTOR_BYTES * (worlds + 1)
    rounding = POOL_SLACK if estimate.cuda else 0
    if estimate.cuda:
        slack += memory.BVH_BUILD_TEMPORARY_CUDA * surface.triangle_count  # freed after each build
    assert allocated["live"] - 1024 - rounding <= expected <= allocated["live"] + slack


def test_counted_self_collision_bounds_the_exact_one():
    """From counts alone (``ws.estimate_memory(self_contact_triangles=...)``) the edges and vertices default to their
    upper bounds (3 per triangle, every particle): never below the builder's exact count, and within 5 % of it on a
    grid."""
    builder = _self_colliding(40, 30)
    exact = builder.estimate_memory("cpu")
    counted = ws.estimate_memory(particles=1200, springs=builder.spring_count, triangles=2 * 39 * 29,
                                 self_contact_triangles=2 * 39 * 29)
    assert exact.self_contact <= counted.self_contact <= 1.05 * exact.self_contact
    assert "self-collision" in counted.describe()


def test_a_self_colliding_model_that_cannot_fit_is_refused_naming_the_part(monkeypatch):
    """A machine with room for the cloth but not for its self-collision refuses it at finalize, before allocating,
    with the part named in the one line."""
    builder = _self_colliding(60, 60)
    estimate = builder.estimate_memory("cpu")
    without = estimate.host_bytes - estimate.self_contact
    monkeypatch.setattr(memory, "available_memory",
                        lambda device=None: AvailableMemory(host=int(without + estimate.self_contact // 2)))
    with pytest.raises(ws.ConfigError) as refused:
        builder.finalize("cpu")
    line = str(refused.value)
    assert "\n" not in line and "self-collision" in line and memory.format_bytes(estimate.self_contact) in line
    assert "add_self_collision(meshes=" in line  # the remedy names the part that does not fit


@pytest.mark.parametrize("winding_number", [False, True])
def test_mesh_colliders_native_memory_is_estimated(device, winding_number):
    """A ``wp.Mesh``'s boxes, BVH and winding-number tables (``mesh_native_bytes``) as Warp allocates them, at two
    sizes (320 and 5120 triangles: per-triangle terms, not a constant): on the CPU the measured bytes within the
    descriptors' allowance; on CUDA its LBVH build's temporaries (freed once built, counted as kept) come on top."""
    import warp as wp

    for subdivisions in (2, 4):
        mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
        faces = len(mesh.faces)
        points = wp.array(mesh.vertices.astype(np.float32), dtype=wp.vec3, device=device)
        indices = wp.array(mesh.faces.reshape(-1).astype(np.int32), dtype=wp.int32, device=device)
        with warp_allocations(device) as allocated:
            native = wp.Mesh(points=points, indices=indices, support_winding_number=winding_number)
        cuda = wp.get_device(device).is_cuda
        estimate = memory.mesh_native_bytes(faces, winding_number=winding_number, cuda=cuda)
        slack = 2 * memory.NATIVE_DESCRIPTOR_BYTES + (memory.BVH_BUILD_TEMPORARY_CUDA * faces if cuda else 0)
        assert allocated["live"] - (POOL_SLACK if cuda else 0) <= estimate <= allocated["live"] + slack
        del native


# -- a mesh file counted before it is read ----------------------------------------------------------------------


def _quad_sheet(k: int) -> tuple[np.ndarray, np.ndarray]:
    """A k × k vertex sheet of (k - 1)² quads."""
    xs, ys = np.meshgrid(np.linspace(0.0, 1.0, k), np.linspace(0.0, 1.0, k))
    vertices = np.column_stack([xs.ravel(), ys.ravel(), 0.05 * np.sin(5.0 * xs.ravel())])
    i = np.arange(k * k).reshape(k, k)
    quads = np.stack([i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, 1:].ravel(), i[1:, :-1].ravel()], axis=1)
    return vertices, quads


def test_an_obj_of_quads_is_counted_as_the_triangles_trimesh_makes(tmp_path, monkeypatch):
    """OBJ lines streamed in blocks (a block smaller than the file here: lines cross its edges): quads count as two
    triangles each, triangles and a pentagon as themselves and three; the counts equal trimesh's once it reads the
    file."""
    vertices, quads = _quad_sheet(30)
    path = tmp_path / "quads.obj"
    with open(path, "w") as f:
        f.write("# a sheet\nmtllib none.mtl\n")
        f.writelines(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in vertices)
        f.writelines("f " + " ".join(f"{q + 1}/{q + 1}" for q in quad) + " \r\n" for quad in quads)
        f.write("f\t1 2 3\nf 1 2 3 4 5")  # a tab, and a last line without its newline
    monkeypatch.setattr(mesh_counts, "BLOCK_BYTES", 997)
    counted = mesh_counts.mesh_file_counts(path)
    loaded = trimesh.load(path, process=False, force="mesh")
    assert counted == (len(vertices), 2 * len(quads) + 1 + 3)
    assert counted[1] == len(loaded.faces)


@pytest.mark.parametrize("kind", ["ply", "ply_ascii", "stl", "stl_ascii", "off", "glb", "gltf"])
def test_headers_give_the_counts_without_reading_the_file(tmp_path, kind):
    """PLY (binary: the polygon size from the file's length; ASCII), STL (binary: its count; ASCII: its facets), OFF
    and glTF / GLB (their JSON) give (vertices, triangles) equal to the mesh trimesh reads (STL before its vertices
    are merged)."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    extension = kind.split("_")[0]
    path = tmp_path / f"sphere.{extension}"
    if kind == "gltf":  # the JSON with its buffer embedded
        data = trimesh.exchange.gltf.export_gltf(trimesh.Scene(mesh), embed_buffers=True)["model.gltf"]
    else:
        data = mesh.export(file_type=extension, encoding="ascii") if kind == "ply_ascii" else \
            trimesh.exchange.stl.export_stl_ascii(mesh) if kind == "stl_ascii" else mesh.export(file_type=extension)
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    loaded = trimesh.load(path, process=False, force="mesh")
    vertices, triangles = mesh_counts.mesh_file_counts(path)
    assert triangles == len(loaded.faces) == len(mesh.faces)
    assert vertices == (3 * len(mesh.faces) if extension == "stl" else len(mesh.vertices))


def test_a_binary_ply_of_quads_counts_two_triangles_each(tmp_path):
    """A binary PLY's faces are polygons of a size its header does not give: the face element's bytes (the file
    less the header and the vertices) give 4 corners here, 2 triangles each, as trimesh reads it."""
    vertices, quads = _quad_sheet(12)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\nproperty float x\n"
              f"property float y\nproperty float z\nelement face {len(quads)}\nproperty list uchar int vertex_indices\n"
              "end_header\n").encode()
    faces = np.zeros(len(quads), dtype=[("n", "u1"), ("v", "<i4", (4,))])
    faces["n"], faces["v"] = 4, quads
    path = tmp_path / "quads.ply"
    path.write_bytes(header + vertices.astype("<f4").tobytes() + faces.tobytes())
    loaded = trimesh.load(path, process=False, force="mesh")
    assert mesh_counts.mesh_file_counts(path) == (len(vertices), 2 * len(quads)) == (len(vertices), len(loaded.faces))


def test_formats_without_counts_and_unreadable_files_are_not_counted(tmp_path):
    assert mesh_counts.mesh_file_counts(tmp_path / "missing.obj") is None
    (tmp_path / "bad.ply").write_bytes(b"not a ply file")
    assert mesh_counts.mesh_file_counts(tmp_path / "bad.ply") is None
    path = tmp_path / "box.dae"  # a format not counted (its content does not matter: nothing is read)
    path.write_bytes(b"<COLLADA/>")
    assert mesh_counts.mesh_file_counts(path) is None
    (tmp_path / "bad.glb").write_bytes(b"glTF" + bytes(16))
    assert mesh_counts.mesh_file_counts(tmp_path / "bad.glb") is None


def test_a_mesh_collider_file_too_large_is_refused_before_it_is_read(tmp_path, monkeypatch):
    """The collider's triangles counted from its file, the host memory its reading needs estimated and refused in one
    line before trimesh opens it (its loader replaced by one that fails the test); a machine with room reads it."""
    vertices, quads = _quad_sheet(40)
    mesh = trimesh.Trimesh(vertices, np.concatenate([quads[:, :3], quads[:, [0, 2, 3]]]), process=False)
    path = tmp_path / "terrain.ply"
    path.write_bytes(mesh.export(file_type="ply"))
    needed = memory.format_bytes(MESH_COLLIDER_FILE_PER_FACE * len(mesh.faces) + 24 * len(vertices)
                                 + MESH_COLLIDER_FILE_FIXED)

    def unread(*args, **kwargs):
        raise AssertionError("the file was read before its size was checked")

    monkeypatch.setattr(memory, "available_memory", lambda device=None: AvailableMemory(host=64 * 1024))
    monkeypatch.setattr(collider_recipes, "load_mesh_file", unread)
    with pytest.raises(ws.ConfigError) as refused:
        ws.ModelBuilder().add_collider_mesh(str(path), sides="one_sided")
    line = str(refused.value)
    assert "\n" not in line and f"{len(mesh.faces):,} triangles" in line and needed in line and "decimate" in line
    monkeypatch.undo()
    assert ws.ModelBuilder().add_collider_mesh(str(path), sides="one_sided") == 0


def _usd_sheet(path, k: int, *, triangles: bool = False, samples: int = 0, text: bool = False) -> str:
    """A k × k-vertex sheet of quads (or triangles) as a USD mesh prim, its points with ``samples`` time samples."""
    from pxr import Usd, UsdGeom  # optional: usd-core

    vertices, quads = _quad_sheet(k)
    faces = np.concatenate([quads[:, :3], quads[:, [0, 2, 3]]]) if triangles else quads
    file = str(path.with_suffix(".usda" if text else ".usdc"))
    stage = Usd.Stage.CreateNew(file)
    mesh = UsdGeom.Mesh.Define(stage, "/World/terrain")
    mesh.GetFaceVertexCountsAttr().Set([faces.shape[1]] * len(faces))
    mesh.GetFaceVertexIndicesAttr().Set(faces.ravel().tolist())
    points = mesh.GetPointsAttr()
    for t in range(max(samples, 1)):
        moved = [tuple(p) for p in (vertices + [0.0, 0.0, 0.01 * t]).tolist()]
        points.Set(moved, t) if samples else points.Set(moved)
    stage.GetRootLayer().Save()
    return file


@pytest.mark.parametrize("triangles, samples, text", [(False, 0, False), (True, 3, False), (False, 0, True)])
def test_a_usd_mesh_collider_too_large_is_refused_before_it_is_read(tmp_path, monkeypatch, triangles, samples, text):
    """A USD collider's counts read from its prim's arrays' lengths (no triangulation, no float64 copy): the
    triangles of the reader's fan, its vertices and its points' time samples; the host memory its reading needs
    refused in one line before the mesh is read (the reader replaced by one that fails the test); a text file's
    parse checked first by its size; a machine with room reads it."""
    file = _usd_sheet(tmp_path / "terrain", 30, triangles=triangles, samples=samples, text=text)
    counts = mesh_counts.usd_mesh_counts(file)
    assert counts == (900, 2 * 29 * 29, 0 if triangles else 2 * 29 * 29, samples)
    assert mesh_counts.usd_mesh_counts(file, prim="/World/terrain") == counts
    assert mesh_counts.usd_mesh_counts(file, prim="/World/none") is None  # the reader says why, in its words
    needed = (MESH_COLLIDER_USD_PER_FACE * (counts.triangles - counts.fanned)
              + MESH_COLLIDER_USD_PER_FANNED_FACE * counts.fanned
              + MESH_COLLIDER_USD_PER_SAMPLE_VERTEX * 900 * max(samples, 1) + MESH_COLLIDER_FILE_FIXED)
    assert usd_collider_bytes(counts) == needed

    def unread(*args, **kwargs):
        raise AssertionError("the mesh was read before its size was checked")

    monkeypatch.setattr(collider_recipes, "read_usd_mesh", unread)
    parse = USDA_PARSE_PER_BYTE * os.path.getsize(file)
    if text:  # its parse is checked first, from its size (far below the reading's estimate for this small file)
        assert parse < needed
        monkeypatch.setattr(memory, "available_memory", lambda device=None: AvailableMemory(host=parse - 1))
        with pytest.raises(ws.ConfigError, match="of text") as refused:
            ws.ModelBuilder().add_collider_mesh(file, sides="one_sided")
        assert "\n" not in str(refused.value) and memory.format_bytes(parse) in str(refused.value)
    monkeypatch.setattr(memory, "available_memory", lambda device=None: AvailableMemory(host=needed - 1))
    with pytest.raises(ws.ConfigError) as refused:
        ws.ModelBuilder().add_collider_mesh(file, sides="one_sided")
    line = str(refused.value)
    assert "\n" not in line and f"{counts.triangles:,} triangles" in line and "decimate" in line
    assert memory.format_bytes(needed) in line and (f"{samples} time samples" in line) == (samples > 1)
    monkeypatch.undo()
    assert ws.ModelBuilder().add_collider_mesh(file, sides="one_sided") == 0


@pytest.mark.parametrize("plastic", [False, True])
@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4"])
def test_a_runs_device_peak_is_estimated(device, integrator, plastic):
    """A simulator's first frame: its states, the integrator's scratch, the guard (what it makes for the run's path
    included) and the stepper's warm-up copies of what a step carries on (the plastic springs' rest lengths and strains
    among them; held until the warm-up step is undone) peak at the estimate's device bytes less the model and the USD
    writer, exactly on the CPU (Warp's allocation tracker) but for the warm-up's allowances; on CUDA what stays
    allocated after it is within that peak by the warm-up copies."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=12, ny=10, spacing=0.02, mass=0.5, pin=["top-left"])
    builder.drag = 0.1
    if plastic:
        builder.add_springs([[0, 13], [1, 14], [2, 15]], stiffness=10.0, damping=0.01, family="plastic",
                            plasticity=ws.SpringPlasticity(yield_strain=0.1))
    estimate = builder.estimate_memory(device, worlds=5, integrator=integrator)
    model = builder.finalize(device, worlds=5, integrator=integrator)
    ws.Simulator(model, fps=60, substeps=100, integrator=ws.make_integrator(integrator, model)).step_frame()  # loaded
    with warp_allocations(device) as allocated:
        sim = ws.Simulator(model, fps=60, substeps=100, integrator=ws.make_integrator(integrator, model))
        sim.step_frame()
    run = estimate.device_bytes - estimate.model - estimate.writer
    assert estimate.warmup > 0 and estimate.guard > 0
    # The warm-up's allowances: each world's stage time, which rk4 does not carry, and 64 bytes a world for the
    # counters this scene lacks (contacts, self-collision, meshes).
    stage_time = 8 * 5 if integrator == "rk4" else 0
    counters = 64 * 5
    carried = 2 * 4 * 5 * model.spring_count if plastic else 0  # the plastic springs' rest lengths and strains
    assert carried == 0 or estimate.warmup > carried
    if allocated["peak"] is not None:
        assert run - stage_time - counters == allocated["peak"]
        assert run - estimate.warmup == allocated["live"]
    else:
        kept = run - estimate.warmup
        assert kept - POOL_SLACK <= allocated["live"] <= kept + POOL_SLACK
