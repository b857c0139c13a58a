"""Soft bodies from a closed mesh (core/soft_topologies.py, core/softbody.py, ModelBuilder.add_soft_body): each method's
counts on small meshes, springs that stay inside the body, embeddings that reproduce the surface, masses, clear
errors, a model of every method stepping on the device with its surface exported through the weights, and the
lattice's and the tetrahedra's elasticity against closed forms by float64 static solves (NumPy/SciPy; no kernels but
in ``test_every_method_falls_and_exports``)."""

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.csgraph
import trimesh
from scipy.spatial import Delaunay

import warpspring as ws
from warpspring.analysis.softbody_elasticity import (bar_poisson_ratio, bar_stretch, box_topology, cube_shortening,
                                                     linear_fem_stiffness, uniform_stress_compliance)
from warpspring.core import softbody as sb
from warpspring.core.soft_topologies import (METHODS, VOLUME_METHODS, Topology, build_topology, grid_topology,
                                              segments_cross, shell_topology, springs_leave)
from warpspring.errors import ConfigError

try:
    import pytetwild  # noqa: F401  (the tetrahedral method's optional extra, warpspring[tet])

    TET = True
except ImportError:
    TET = False
needs_tet = pytest.mark.skipif(not TET, reason="the tetrahedral method needs pytetwild (pip install warpspring[tet])")

E = 1.0e5  # [Pa]
RHO = 1000.0  # [kg/m³]
G = 9.81  # [m/s²]

MESHES = {
    "box": lambda: trimesh.creation.box((1.0, 1.0, 1.0)),
    "icosphere": lambda: trimesh.creation.icosphere(subdivisions=1, radius=0.5),
    "torus": lambda: trimesh.creation.torus(major_radius=0.5, minor_radius=0.2, major_sections=16, minor_sections=8),
}
#: Resolution [m] per mesh: a voxel of the torus's tube (0.4 across) fits three times.
SPACING = {"box": 0.25, "icosphere": 0.25, "torus": 0.12}
OPTIONS = {"tetrahedral": {"epsilon": 1.0e-2}}  # a coarser envelope: a faster fTetWild on these small meshes


@pytest.fixture(scope="module")
def topologies():
    """Every (mesh, method) topology, built once (fTetWild takes ~0.5 s a mesh)."""
    cache = {}

    def get(mesh: str, method: str) -> tuple:
        if method == "tetrahedral" and not TET:
            pytest.skip("the tetrahedral method needs pytetwild (pip install warpspring[tet])")
        if (mesh, method) not in cache:
            m = MESHES[mesh]()
            cache[mesh, method] = (m, build_topology(m, method, youngs_modulus=E, spacing=SPACING[mesh],
                                                        **OPTIONS.get(method, {})))
        return cache[mesh, method]

    return get


# -- counts -------------------------------------------------------------------------------------------------------

# The unit box: 8 vertices, 12 triangles, 18 unique edges. Voxels of 0.25: 4³ voxels, 5³ corners; each axis has
# 4 × 5 × 5 edges, each of the 3 × 5 planes 4 × 4 squares with 2 diagonals. Grid of 0.25: 4³ nodes at 0.125 from
# the faces, 3 × 3 × 4 × 4 edges and 3 × 4 × 3 × 3 × 2 face diagonals, each vertex tied to its 4 nearest nodes.
BOX_COUNTS = {
    "brute_force": (8, {"brute": 28}),
    "voxel": (125, {"edge": 300, "face_diagonal": 480}),
    "grid": (72, {"edge": 144, "face_diagonal": 216, "tie": 32, "skin": 18}),
    "scaffold": (9, {"skin": 18, "tie": 8}),
    "shell": (16, {"skin": 18, "inner": 18, "radial": 8, "shear": 36}),
}


@pytest.mark.parametrize("method", list(BOX_COUNTS))
def test_counts_on_a_box(topologies, method):
    _, topology = topologies("box", method)
    particles, springs = BOX_COUNTS[method]
    assert topology.particle_count == particles
    assert topology.spring_counts == springs


@pytest.mark.parametrize("method", ["tetrahedral", "delaunay"])
@pytest.mark.parametrize("mesh", list(MESHES))
def test_tetrahedra_fill_the_body(topologies, mesh, method):
    """The tets' volumes sum to the mesh's (fTetWild: within its envelope, 1e-2 of the diagonal; Delaunay of a
    convex box: exactly; of the icosphere and the torus: the tets whose centroid is inside, a little less); the
    springs are their edges (Delaunay: those inside the body), each once; every particle is in a tet."""
    m, topology = topologies(mesh, method)
    tets = topology.tets
    p = topology.positions[tets]
    volume = np.abs(np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))).sum() / 6
    if method == "tetrahedral" or mesh == "box":
        np.testing.assert_allclose(volume, m.volume, rtol=3.0e-2 if method == "tetrahedral" else 1.0e-12)
    else:
        assert 0.7 * m.volume < volume <= m.volume * (1.0 + 1.0e-9)
    np.testing.assert_allclose(topology.volume.sum(), volume, rtol=1.0e-12)
    pairs = np.concatenate([pairs for pairs, _ in topology.springs.values()])
    edges = np.unique(np.sort(tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2), axis=1), axis=0)
    assert len(np.unique(pairs, axis=0)) == len(pairs)
    assert len(pairs) == len(edges) if method == "tetrahedral" else len(pairs) <= len(edges)
    assert set(map(tuple, pairs)) <= set(map(tuple, edges))
    assert np.isin(np.arange(topology.particle_count), tets).all()
    if method == "tetrahedral":
        assert topology.slivers.tet_count == len(tets) and topology.slivers.min_quality > 0.0
        assert not __import__("os").path.exists("__tracked_surface.stl")  # fTetWild's by-product stays out of the cwd


# -- springs inside the body --------------------------------------------------------------------------------------


def _outside_depth(mesh, topology, samples=5) -> float:
    """The largest distance [m] outside ``mesh`` of points along the springs (t = 1/6 … 5/6), by trimesh's
    signed distance (closest points and normals: not the ray tests the builders use)."""
    pairs = np.concatenate([pairs for pairs, _ in topology.springs.values()])
    t = np.arange(1, samples + 1) / (samples + 1)
    a, b = topology.positions[pairs[:, 0]], topology.positions[pairs[:, 1]]
    points = (a[:, None] + t[None, :, None] * (b - a)[:, None]).reshape(-1, 3)
    return float(max(0.0, -trimesh.proximity.signed_distance(mesh, points).min()))


@pytest.mark.parametrize("mesh", ["icosphere", "torus"])
@pytest.mark.parametrize("method", ["grid", "tetrahedral", "delaunay"])
def test_no_spring_leaves_the_body(topologies, mesh, method):
    """Grid and Delaunay keep only springs inside; fTetWild's tets stay inside its envelope (1e-2 × the
    bounding-box diagonal), so a torus's tets do not bridge its hole as a plain Delaunay's would."""
    m, topology = topologies(mesh, method)
    envelope = 1.0e-2 * np.linalg.norm(np.ptp(m.vertices, axis=0)) if method == "tetrahedral" else 1.0e-9
    assert _outside_depth(m, topology) <= envelope


def test_plain_delaunay_of_a_torus_bridges_its_hole(topologies):
    """The reason for the filters: every Delaunay edge of the torus's particles, unfiltered, leaves the body."""
    m, topology = topologies("torus", "delaunay")
    tets = Delaunay(topology.positions).simplices
    pairs = np.unique(np.sort(tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2), axis=1), axis=0)
    plain = Topology(topology.positions, {"all": (pairs, np.ones(len(pairs)))}, topology.volume,
                        topology.skin_indices, topology.skin_weights, "")
    assert _outside_depth(m, plain) > 0.25  # spans the hole (radius 0.3)


def test_voxel_lattice_hugs_the_body(topologies):
    """The lattice covers the voxels whose centre is inside: no spring point lies farther outside than a voxel's
    diagonal, so none spans the torus's hole (0.6 across)."""
    m, topology = topologies("torus", "voxel")
    assert _outside_depth(m, topology) <= np.sqrt(3.0) * SPACING["torus"]


def _slit_ring(subdivisions: int = 2) -> trimesh.Trimesh:
    """A 1 m bar of 0.2 m square section (its faces subdivided) bent about z through 356° into a ring whose ends
    face each other across a slit 1.1 cm wide on the centreline: non-convex, with thin outside space inside it."""
    bar = trimesh.creation.box((1.0, 0.2, 0.2))
    for _ in range(subdivisions):
        bar = bar.subdivide()
    bar.merge_vertices()
    x, y, z = bar.vertices.T
    radius = 1.0 / np.deg2rad(356.0)  # the centreline's: its length stays 1 m
    ring = trimesh.Trimesh(np.column_stack([(radius + y) * np.sin(x / radius), (radius + y) * np.cos(x / radius), z]),
                           bar.faces)
    assert ring.is_watertight and ring.volume > 0.0
    return ring


def _depth_outside(mesh, positions: np.ndarray, pairs: np.ndarray, samples: int = 64) -> np.ndarray:
    """Per spring, how far [m] outside ``mesh`` its farthest of ``samples`` evenly spaced points lies (0: all in)."""
    t = (np.arange(samples) + 0.5) / samples
    a, b = positions[pairs[:, 0]], positions[pairs[:, 1]]
    points = (a[:, None] + t[None, :, None] * (b - a)[:, None]).reshape(-1, 3)
    depth = np.zeros(len(points))
    outside = np.flatnonzero(~mesh.contains(points))
    if len(outside):
        depth[outside] = mesh.nearest.on_surface(points[outside])[1]
    return depth.reshape(len(pairs), samples).max(axis=1)


@pytest.mark.parametrize("shape, spacing", [("slit ring", 0.1), ("torus", 0.15)])
def test_grid_ties_stay_inside_a_non_convex_body(shape, spacing):
    """Where the grid cuts a non-convex surface a vertex's nearest nodes can lie across outside space: across the
    ring's slit, or around the torus's tube. Every spring and tie stays inside (64 points along each, inside or
    within 1e-9 m: the builder's rays are exact where its 7 test points were not — before, 56 of the ring's ties
    crossed the slit, up to 5 mm outside), every vertex keeps its 4 ties (before: 20 had 2; the torus at 0.15 m
    did not build), the network is one piece, and the embedding reproduces the surface."""
    mesh = _slit_ring() if shape == "slit ring" else MESHES["torus"]()
    topology = grid_topology(mesh, spacing=spacing, youngs_modulus=E)
    for group, (pairs, _) in topology.springs.items():
        assert _depth_outside(mesh, topology.positions, pairs).max() <= 1.0e-9, group
    ties = topology.springs["tie"][0]
    nodes = topology.particle_count - len(mesh.vertices)
    assert (ties[:, 1] < nodes).all()
    np.testing.assert_array_equal(np.bincount(ties[:, 0] - nodes, minlength=len(mesh.vertices)), 4)
    pairs = np.concatenate([p for p, _ in topology.springs.values()])
    graph = scipy.sparse.coo_matrix((np.ones(len(pairs)), tuple(pairs.T)), shape=(topology.particle_count,) * 2)
    assert scipy.sparse.csgraph.connected_components(graph, directed=False)[0] == 1
    w, idx = topology.skin_weights, topology.skin_indices
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0.0, atol=1.0e-12)
    np.testing.assert_allclose(np.einsum("vj,vjk->vk", w, topology.positions[idx]), mesh.vertices, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize("engine", ["default", "rtree"])
def test_a_ray_finds_a_slit_between_test_points(engine):
    """Two blocks 1 mm apart: a 0.77 m segment from one into the other crosses the slit between the 7 test points
    of :func:`springs_leave` (at x = −0.015 and +0.081 m), which finds it inside; the ray test, with Embree or
    trimesh's rtree engine, finds the crossing. A segment ending on the far block's surface crosses; one within a
    block, or ending on its own block's face (the ray's hit there is the end), does not."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    blocks = trimesh.util.concatenate([trimesh.creation.box((0.4, 0.4, 0.4)).apply_translation((x, 0.0, 0.0))
                                       for x in (-0.2005, 0.2005)])
    if engine == "rtree":
        blocks.ray = RayMeshIntersector(blocks)
    ends = np.array([[-0.4, 0.0, 0.0], [0.37, 0.0, 0.0]])
    assert not springs_leave(blocks, ends, np.array([[0, 1]]), tolerance=1.0e-9)[0]
    start = np.array([[-0.3, 0.05, 0.0]] * 4)
    end = np.array([[0.37, 0.0, 0.0], [0.4005, 0.1, 0.1], [-0.05, 0.1, 0.0], [-0.0005, 0.1, 0.1]])
    np.testing.assert_array_equal(segments_cross(blocks, start, end, hair=1.0e-6), [True, True, False, False])


# -- embedding ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mesh", list(MESHES))
@pytest.mark.parametrize("method", METHODS)
def test_embedding_reproduces_the_surface(topologies, mesh, method):
    m, topology = topologies(mesh, method)
    w, idx = topology.skin_weights, topology.skin_indices
    assert idx.shape == w.shape and idx.shape[0] == len(m.vertices)
    assert ((idx >= 0) & (idx < topology.particle_count)).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0.0, atol=1.0e-12)
    surface = np.einsum("vj,vjk->vk", w, topology.positions[idx])
    np.testing.assert_allclose(surface, m.vertices, rtol=0.0, atol=1.0e-12)
    if method == "voxel":  # the 8 corners of one voxel: they span one pitch along every axis
        corners = topology.positions[idx]
        np.testing.assert_allclose(np.ptp(corners, axis=1), SPACING[mesh], rtol=1e-9)
        assert all(len(np.unique(np.round(c / SPACING[mesh], 6), axis=0)) == 8 for c in corners[:5])


# -- errors -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("method", VOLUME_METHODS)
def test_open_mesh_is_refused_by_volume_methods(method, tmp_path):
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.update_faces(np.arange(len(box.faces)) != 0)
    path = tmp_path / "open_box.stl"
    box.export(path)
    with pytest.raises(ConfigError, match=r"open_box\.stl: the .* method .*watertight.* 3 open edge.*fill_holes"):
        ws.ModelBuilder().add_soft_body(path, method=method, youngs_modulus=E, mass=1.0)


def test_open_mesh_suits_brute_force_and_scaffold():
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    box.update_faces(np.arange(len(box.faces)) != 0)
    builder = ws.ModelBuilder()
    for method in ("brute_force", "scaffold"):
        assert builder.add_soft_body(box, method=method, youngs_modulus=E, mass=1.0).particle_count > 0
    with pytest.raises(ConfigError, match="density= needs the mesh's volume.*give mass="):
        builder.add_soft_body(box, method="brute_force", youngs_modulus=E, density=RHO)


def test_brute_force_refuses_a_large_mesh():
    big = trimesh.creation.icosphere(subdivisions=4)  # 2562 vertices
    with pytest.raises(ConfigError, match=r"2562 vertices \(3,280,641 springs\).*more than 2000"):
        build_topology(big, "brute_force", youngs_modulus=E)


def test_bad_options_are_named():
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    with pytest.raises(ConfigError, match="unknown soft-body method 'fem'"):
        build_topology(box, "fem", youngs_modulus=E)
    with pytest.raises(ConfigError, match="the voxel method takes no option 'ties'; its options: body_diagonals"):
        build_topology(box, "voxel", youngs_modulus=E, ties=3)
    with pytest.raises(ConfigError, match="grid neighbours must be one of"):
        build_topology(box, "grid", youngs_modulus=E, neighbours=12)
    with pytest.raises(ConfigError, match="youngs_modulus must be"):
        ws.ModelBuilder().add_soft_body(box, youngs_modulus=-1.0, mass=1.0)
    with pytest.raises(ConfigError, match=r"spacing of 0.001 m .* ~1e\+09 cells, more than 20,000,000"):
        build_topology(box, "voxel", youngs_modulus=E, spacing=1.0e-3)
    inside_out = box.copy()
    inside_out.invert()
    with pytest.raises(ConfigError, match="encloses no volume.*fix_normals"):
        build_topology(inside_out, "grid", youngs_modulus=E)


# -- masses -------------------------------------------------------------------------------------------------------


def test_masses(topologies):
    _, topology = topologies("box", "voxel")
    by_volume = sb.distribute_mass(topology, 8.0)
    np.testing.assert_allclose(by_volume.sum(), 8.0, rtol=1e-12)
    np.testing.assert_allclose(by_volume / by_volume.sum(), topology.volume / topology.volume.sum(), rtol=1e-12)
    # a corner of the 4³ block carries one voxel's eighth, an inner node eight eighths
    assert by_volume.max() / by_volume.min() == pytest.approx(8.0)
    np.testing.assert_allclose(sb.distribute_mass(topology, 8.0, distribution="uniform"), 8.0 / 125)
    skin = np.zeros(125, dtype=bool)
    skin[topology.skin_indices[topology.skin_weights != 0]] = True  # the box's 8 corners
    heavy = sb.distribute_mass(topology, 8.0, distribution="uniform", skin_factor=3.0)
    np.testing.assert_allclose(heavy[skin] / heavy[~skin][0], 3.0)
    biased = sb.distribute_mass(topology, 8.0, distribution="uniform", gradient=(0.0, 0.0, -1.0))
    z = topology.positions[:, 2]
    centre_of_mass = biased @ z / 8.0
    # weights 1 − (z − z̄) over a symmetric lattice: the centre of mass drops by Var(z) [m]
    np.testing.assert_allclose(centre_of_mass, z.mean() - z.var(), rtol=1e-12)
    with pytest.raises(ConfigError, match="mass_gradient .* makes a particle's weight ≤ 0"):
        sb.distribute_mass(topology, 8.0, gradient=(0.0, 0.0, -3.0))


# -- a model of every method --------------------------------------------------------------------------------------


def test_every_method_falls_and_exports(device, tmp_path):
    """Each method's body, finalized on the device, falls freely: springs are internal forces, so the centre of
    mass follows symplectic Euler's exact z_n = z₀ − g·dt²·n(n+1)/2 (float32 positions: 1e-5 m). The exported
    surface is Σ w x of the particles written in the frame (float32 points: 1e-6 m)."""
    from pxr import Usd, UsdGeom

    from warpspring.io.usd import UsdWriter

    builder = ws.ModelBuilder()
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    bodies = [builder.add_soft_body(ball, method=method, youngs_modulus=E, density=RHO, spacing=0.1, damping=1e-3,
                                    origin=(0.6 * i, 0.0, 1.0), name=method, options=OPTIONS.get(method))
              for i, method in enumerate(METHODS) if TET or method != "tetrahedral"]
    model = builder.finalize(device)
    integrator = ws.make_integrator("symplectic_euler", model)
    a, b = model.state(), model.state()
    mass = model.particle_mass.numpy()[0].astype(np.float64)  # one world
    z0 = {body.name: mass[body.particles] @ model.particle_q.numpy()[body.particles, 2] / body.mass for body in bodies}
    dt, steps = 1.0e-4, 20
    path = tmp_path / "soft.usda"
    with UsdWriter(path, model, fps=1.0 / (dt * steps), primvars=("strain", "rest"), springs=True) as writer:
        writer.write_frame(a)
        for _ in range(steps):
            integrator.step(a, b, None, dt)
            a, b = b, a
        writer.write_frame(a)
    q = a.particle_q.numpy().astype(np.float64)
    drop = G * dt * dt * steps * (steps + 1) / 2.0
    for body in bodies:
        np.testing.assert_allclose(mass[body.particles] @ q[body.particles, 2] / body.mass, z0[body.name] - drop,
                                   atol=1.0e-5, err_msg=body.method)
    stage = Usd.Stage.Open(str(path))
    for body in bodies:
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/{body.name}"))
        points = np.asarray(mesh.GetPointsAttr().Get(1), dtype=np.float64)
        expected = np.einsum("vj,vjk->vk", body.skin.weights, q[body.skin.indices])
        np.testing.assert_allclose(points, expected, atol=1.0e-6, err_msg=body.method)
        assert list(mesh.GetFaceVertexIndicesAttr().Get()) == ball.faces.ravel().tolist()
        strain = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("strain").Get(0), dtype=np.float64)
        # the rest frame: every spring at its rest length, up to float32 positions (6e-8 m near 1 m over 5 cm springs)
        np.testing.assert_allclose(strain, 0.0, atol=1.0e-5)
        rest = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("rest").Get(), dtype=np.float64)
        np.testing.assert_allclose(rest, ball.vertices + (0.6 * METHODS.index(body.method), 0.0, 1.0), atol=1e-6)
        for group, springs in body.springs.items():  # one curves prim per spring group, a chain through its springs
            curves = UsdGeom.BasisCurves(stage.GetPrimAtPath(f"/World/springs/{body.name}_{group}"))
            assert sum(n - 1 for n in curves.GetCurveVertexCountsAttr().Get()) == len(springs)


def test_a_usd_mesh_keeps_its_quads(tmp_path):
    """A soft body from a USD prim of quads: the topology uses its triangles, the export its quads as authored."""
    from pxr import Usd, UsdGeom

    from warpspring.io.usd import UsdWriter

    source = tmp_path / "cube.usda"
    stage = Usd.Stage.CreateNew(str(source))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    cube = UsdGeom.Mesh.Define(stage, "/cube")
    corners = np.array([[x, y, z] for z in (0.0, 0.4) for y in (0.0, 0.4) for x in (0.0, 0.4)])
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    cube.CreatePointsAttr([tuple(map(float, c)) for c in corners])
    cube.CreateFaceVertexCountsAttr([4] * 6)
    cube.CreateFaceVertexIndicesAttr(sum(quads, []))
    stage.GetRootLayer().Save()

    builder = ws.ModelBuilder()
    body = builder.add_soft_body(source, prim="/cube", method="voxel", youngs_modulus=E, density=RHO, spacing=0.1)
    assert body.particle_count == 125  # 4³ voxels
    path = tmp_path / "out.usda"
    model = builder.finalize("cpu")
    with UsdWriter(path, model, fps=30.0) as writer:
        writer.write_frame(model.state())
    output = Usd.Stage.Open(str(path))  # held: a prim does not keep its stage alive
    written = UsdGeom.Mesh(output.GetPrimAtPath("/World/cube"))  # the prim's own name
    assert list(written.GetFaceVertexCountsAttr().Get()) == [4] * 6
    assert list(written.GetFaceVertexIndicesAttr().Get()) == sum(quads, [])
    np.testing.assert_allclose(np.asarray(written.GetPointsAttr().Get(0)), corners, atol=1e-6)


# -- elasticity ---------------------------------------------------------------------------------------------------


def _cube(method: str, n: int, **options) -> float:
    """The unit cube's shortening error at ``n`` cells per side (analysis/softbody_elasticity.py)."""
    topology = box_topology(method, (1.0, 1.0, 1.0), youngs_modulus=E, spacing=1.0 / n, **options)
    return cube_shortening(topology, youngs_modulus=E, density=RHO)


def _bar(method: str, n: int, **options) -> float:
    """A 1 m bar of 0.2 m square section: its stretch error at ``n`` cells across."""
    topology = box_topology(method, (1.0, 0.2, 0.2), youngs_modulus=E, spacing=0.2 / n, **options)
    return bar_stretch(topology, youngs_modulus=E)


@pytest.mark.parametrize("body_diagonals", [False, True])
def test_voxel_cube_and_bar_honour_young_modulus(body_diagonals):
    """E = 5k/(2a) on the voxel lattice of edge and face-diagonal springs, E = 5(k₂ + 4k₃/3)/(2a) with body
    diagonals (k₁ = 2k₂, k₃ = 3k₂/8). Measured: cube −1.2, −1.0, −0.8 % (both); bar −0.39, −0.16, −0.07 %
    (−0.43, −0.18, −0.08 % with body diagonals): the error falls with resolution and is within 10 % at the
    finest; the bar contracts sideways with ν = 1/4 (measured 0.25000 ± 1e-5: the lattice is isotropic)."""
    options = {"body_diagonals": body_diagonals}
    cube = [abs(_cube("voxel", n, **options)) for n in (4, 6, 8)]
    bar = [abs(_bar("voxel", n, **options)) for n in (2, 3, 4)]
    for errors in (cube, bar):
        assert errors[0] > errors[1] > errors[2]
        assert errors[2] < 0.10
    bar = box_topology("voxel", (1.0, 0.2, 0.2), youngs_modulus=E, spacing=0.2 / 3, **options)
    assert bar_poisson_ratio(bar) == pytest.approx(0.25, abs=1.0e-3)


@needs_tet
def test_tetrahedral_bar_and_cube_honour_young_modulus():
    """k_e = E·ΣV_t/L_e² on fTetWild's tets at the target edge length (not coarsened). fTetWild has no seed, so
    its meshes and the errors differ from run to run: over 15 builds each (2026-11-26, CPU) the bar at 4 cells
    across measured +0.4 … +6.0 % (other days up to +8.4 %), the cube at 8 per side −4.7 … +9.1 %, so one build
    can fail any bound inside that spread. The springs' error does not shrink with the tets (they fail the patch
    test by 3–19 % in tension: RESULTS §18f), so the bound is the issue's 10 % for both, on the median of five
    builds (a median beyond it needs three of five builds beyond it; a bound of 6 % on the bar's median was
    crossed once in ~10 runs, at +6.05 %)."""
    bar = float(np.median([_bar("tetrahedral", 4) for _ in range(5)]))
    cube = float(np.median([_cube("tetrahedral", 8) for _ in range(5)]))
    assert abs(bar) < 0.10, bar
    assert abs(cube) < 0.10, cube


def test_the_patch_test_passes_linear_tets_and_measures_the_springs():
    """uniform_stress_compliance against closed forms, on the (seeded) Delaunay body of a 1 × 0.6 × 0.4 m box:
    linear elasticity on its own tets reproduces a uniform stress exactly (the patch test), so all six ratios
    are 1 to round-off; judged against a material of ν' = 0.3 instead of the 0.25 it was built with, the
    uniaxial ratios stay 1 and the shear ones become (1 + ν)/(1 + ν') = 0.961538…, which shows the loads and
    the support are the ones intended. The springs on the same tets are measured, not asserted, beyond being
    positive and finite: 1.01–1.18 uniaxial, 1.46–1.51 in shear (RESULTS §18f)."""
    body = box_topology("delaunay", (1.0, 0.6, 0.4), youngs_modulus=E, spacing=0.15)
    fem = linear_fem_stiffness(body.positions, body.tets, youngs_modulus=E)
    assert uniform_stress_compliance(body, youngs_modulus=E, stiffness=fem) == pytest.approx(
        dict.fromkeys(("xx", "yy", "zz", "yz", "xz", "xy"), 1.0), abs=1.0e-10)
    other = uniform_stress_compliance(body, youngs_modulus=E, poisson_ratio=0.3, stiffness=fem)
    assert other == pytest.approx({"xx": 1.0, "yy": 1.0, "zz": 1.0, "yz": 1.25 / 1.3, "xz": 1.25 / 1.3,
                                   "xy": 1.25 / 1.3}, abs=1.0e-10)
    springs = uniform_stress_compliance(body, youngs_modulus=E)
    assert all(0.5 < value < 3.0 for value in springs.values()), springs
    with pytest.raises(ValueError, match="tetrahedra"):
        uniform_stress_compliance(box_topology("voxel", (1.0, 0.6, 0.4), youngs_modulus=E, spacing=0.2),
                                  youngs_modulus=E)


# -- scene files --------------------------------------------------------------------------------------------------

EXAMPLES = __import__("pathlib").Path(__file__).resolve().parent.parent / "examples"


def test_soft_body_scene_runs(tmp_path):
    """``warpspring run examples/soft_ball.toml`` for 2 frames: the ball's icosphere is written as authored and
    moved by gravity; the torus and jelly-cube examples build."""
    from pxr import Usd, UsdGeom

    from warpspring.app.cli import main
    from warpspring.io.scene import load_scene

    out = tmp_path / "ball.usdc"
    assert main(["run", str(EXAMPLES / "soft_ball.toml"), "-o", str(out), "--frames", "2", "--device", "cpu"]) == 0
    stage = Usd.Stage.Open(str(out))  # held: a prim does not keep its stage alive
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/ball"))
    ball = trimesh.load(EXAMPLES / "meshes" / "ball.obj", force="mesh", process=False)
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == ball.faces.ravel().tolist()
    first, last = (np.asarray(mesh.GetPointsAttr().Get(t), dtype=np.float64) for t in (0, 2))
    np.testing.assert_allclose(first, ball.vertices + (0.0, 0.0, 0.5), atol=1e-6)
    assert (last[:, 2] < first[:, 2]).all()

    for example in ("voxel_torus.toml", "jelly_cube.toml"):
        builder = load_scene(EXAMPLES / example).builder()
        assert builder.particle_count > 0 and builder.spring_count > 0


@pytest.mark.parametrize("table, message", [
    ("mesh = 'ball.obj'\ndensity = 1000.0", r"\[soft_body\] needs youngs_modulus"),
    ("mesh = 'ball.obj'\nyoungs_modulus = 1e4\ndensity = 1000.0\nmass = 2.0", "exactly one of density"),
    ("mesh = 'ball.obj'\nyoungs_modulus = -1.0\nmass = 2.0", "youngs_modulus must be"),
    ("mesh = 'ball.obj'\nyoungs_modulus = 1e4\nmass = 2.0\nstiffness = 3.0", "unknown key 'stiffness' in \\[soft_body\\]"),
])
def test_soft_body_table_is_checked(tmp_path, table, message):
    from warpspring.io.scene import load_scene

    scene = tmp_path / "soft.toml"
    scene.write_text(f"version = 2\n\n[[soft_body]]\n{table}\n")
    with pytest.raises(ConfigError, match=message):
        load_scene(scene)


def test_shell_layer_is_offset_with_either_ray_engine():
    """The shell's local feature size comes from rays cast inward from the skin's vertices. trimesh's rtree
    intersector reports the vertex's own triangles at distance ~0 where Embree does not: either way every inner
    vertex must sit at min(thickness, 0.4 × feature size) inside — for a sphere of radius r, 0.4 × 2r — never on
    the skin (a zero offset gives particles of zero mass)."""
    from trimesh.ray.ray_triangle import RayMeshIntersector

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    ball.ray = RayMeshIntersector(ball)  # the engine without Embree
    topology = shell_topology(ball, youngs_modulus=E, thickness=0.5)
    n = len(ball.vertices)
    depth = np.linalg.norm(topology.positions[:n] - topology.positions[n:], axis=1)
    # The chord through the centre is 2r up to the icosphere's facets (its vertices are on the sphere).
    np.testing.assert_allclose(depth, 0.4 * 2.0 * 0.2, rtol=0.02)
    assert np.all(topology.volume > 0.0)
