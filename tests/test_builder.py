"""ModelBuilder: cloth topology, masses, pins, incidence lists and input validation (no kernels run)."""

import numpy as np
import pytest

import warpspring as ws
from helpers import SEAM_OBJ
from warpspring.core.transforms import quat_to_matrix


def grid_model(nx=5, ny=4, **options):
    builder = ws.ModelBuilder()
    ids = builder.add_cloth_grid(nx=nx, ny=ny, spacing=0.1, mass=2.0, **options)
    return builder.finalize("cpu"), ids


def spring_set(model):
    return {tuple(sorted(p)) for p in model.spring_indices.numpy().tolist()}


def test_grid_spring_families_and_counts():
    """An nx × ny grid has nx(ny-1) + ny(nx-1) structural, 2(nx-1)(ny-1) shear and nx(ny-2) + ny(nx-2)
    bend springs, each at its rest distance (spacing, √2·spacing, 2·spacing)."""
    nx, ny, s = 5, 4, 0.1
    model, ids = grid_model(nx, ny)
    structural, shear, bend = nx * (ny - 1) + ny * (nx - 1), 2 * (nx - 1) * (ny - 1), nx * (ny - 2) + ny * (nx - 2)
    assert model.spring_count == structural + shear + bend
    rest = model.spring_rest_length.numpy()
    np.testing.assert_allclose(np.sort(rest), np.sort(np.r_[[s] * structural, [s * 2**0.5] * shear, [2 * s] * bend]), rtol=1e-6)
    assert len(spring_set(model)) == model.spring_count  # no duplicates
    assert (ids[0, 0], ids[0, 1]) in spring_set(model) and (ids[0, 0], ids[1, 1]) in spring_set(model)
    assert (ids[0, 0], ids[0, 2]) in spring_set(model)
    assert model.tri_count == 2 * (nx - 1) * (ny - 1)


def test_grid_families_can_be_switched_off_and_carry_their_materials():
    """Each family is optional and gets its own ke/kd."""
    model, _ = grid_model(structural=ws.SpringMaterial(10.0, 1.0), shear=None, bend=ws.SpringMaterial(3.0, 0.5))
    ke, kd, rest = model.spring_stiffness.numpy()[0], model.spring_damping.numpy()[0], model.spring_rest_length.numpy()
    assert set(np.round(rest / 0.1, 5)) == {1.0, 2.0}  # no √2 diagonals
    np.testing.assert_array_equal(ke[np.isclose(rest, 0.1)], 10.0)
    np.testing.assert_array_equal(kd[np.isclose(rest, 0.2)], 0.5)


def test_grid_mass_placement_uv_and_pins():
    """Total mass is shared equally; origin + rotation place the grid; UVs span [0, 1]²; named corners
    and edges pin the right particles (zero inverse mass)."""
    rot = ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2)
    model, ids = grid_model(origin=(1.0, 2.0, 3.0), rotation=rot, pin=["top-left", "bottom-right", 7])
    np.testing.assert_allclose(model.particle_mass.numpy().sum(), 2.0, rtol=1e-6)
    q = model.particle_q.numpy()
    np.testing.assert_allclose(q[ids[0, 0]], [1.0, 2.0, 3.0], atol=1e-6)
    np.testing.assert_allclose(q[ids[3, 0]], [1.0, 2.0, 3.3], atol=1e-6)  # local +y → world +z
    pinned = np.flatnonzero(model.kinematic_mask())
    assert set(pinned) == {ids[3, 0], ids[0, 4], 7}
    uv = model.meshes[0].uvs
    np.testing.assert_allclose(uv[ids[3, 4]], [1.0, 1.0]) and np.testing.assert_allclose(uv[ids[0, 0]], [0.0, 0.0])
    model, ids = grid_model(pin=["top"])
    assert set(np.flatnonzero(model.kinematic_mask())) == set(ids[-1])


def test_grid_triangles_face_local_plus_z():
    """Triangles wind counter-clockwise seen from local +z (their normals point along the front normal)."""
    model, _ = grid_model()
    q = model.particle_q.numpy()
    t = model.tri_indices.numpy()
    n = np.cross(q[t[:, 1]] - q[t[:, 0]], q[t[:, 2]] - q[t[:, 0]])
    assert (n[:, 2] > 0).all()


def test_incidence_table_holds_every_spring_twice():
    """The gather's incidence table lists, for each particle, exactly the springs touching it with the other
    end, then padding slots naming the particle itself (zero force); a cloth's uniform degree gives a head as
    wide as the largest degree and no tail. (The per-spring layout: the grouped one, whose padding sits in
    each group's slots, is tested in test_spring_groups.py.)"""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=5, ny=4, spacing=0.1, mass=2.0)
    model = builder.finalize("cpu", spring_evaluation="gather", spring_groups=False)
    table, shape = model.spring_incidence, model.spring_incidence_shape
    neighbor, sid = table.head_local.numpy(), table.head_element.numpy()
    pairs = model.spring_indices.numpy()
    degree = np.bincount(pairs.ravel(), minlength=model.particle_count)
    assert shape == (11, False) and neighbor.shape == (degree.max(), model.particle_count) == (11, 20)  # 4 + 4 + 3
    used = neighbor != np.arange(model.particle_count)
    for i in range(model.particle_count):
        assert used[:, i].sum() == degree[i] and used[: degree[i], i].all()  # padding only at the end
        for j, s in zip(neighbor[used[:, i], i], sid[used[:, i], i]):
            assert set(pairs[s]) == {i, j}
    np.testing.assert_array_equal(np.bincount(sid[used]), 2)


def test_cloth_mesh_springs_bends_and_area_lumped_mass():
    """From a triangle mesh: one structural spring per edge, one bend spring per interior edge joining the
    two opposite vertices, and vertex masses lumped by a third of each adjacent triangle's area."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=1)
    builder = ws.ModelBuilder()
    ids = builder.add_cloth_mesh(mesh, density=2.0, scale=0.5, pin=[0])
    model = builder.finalize("cpu")
    edges = len(mesh.edges_unique)
    assert model.spring_count == 2 * edges  # closed mesh: every edge is interior
    area = mesh.area * 0.25
    np.testing.assert_allclose(model.particle_mass.numpy().sum(), 2.0 * area, rtol=1e-5)
    lumped = np.bincount(mesh.faces.ravel(), weights=np.repeat(mesh.area_faces * 0.25 / 3, 3))
    np.testing.assert_allclose(model.particle_mass.numpy()[0, ids], 2.0 * lumped, rtol=1e-5)
    assert model.kinematic_mask()[ids[0]]
    bends = {tuple(sorted(p)) for p in mesh.face_adjacency_unshared.tolist()}
    assert bends <= spring_set(model)


def test_cloth_mesh_from_arrays_and_file(tmp_path):
    """A two-triangle quad from arrays and from an OBJ file gives 5 structural + 1 bend spring."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    path = tmp_path / "quad.obj"
    path.write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v) + "f 1 2 3\nf 1 3 4\n")
    for source in ((v, f), (str(path), None)):
        builder = ws.ModelBuilder()
        builder.add_cloth_mesh(source[0], source[1], mass=1.0)
        model = builder.finalize("cpu")
        assert model.spring_count == 6
        assert {(1, 3)} <= spring_set(model)  # the bend spring across the diagonal 0-2
        np.testing.assert_allclose(model.particle_mass.numpy()[0], [1 / 3, 1 / 6, 1 / 3, 1 / 6], rtol=1e-6)


def test_plane_collider_orientation():
    """A plane's transform maps local +z onto its normal."""
    builder = ws.ModelBuilder(up_axis="Y")
    builder.add_particles([[0.0, 1.0, 0.0]])
    builder.add_ground_plane(height=0.5)
    model = builder.finalize("cpu")
    shape = model.shapes[0]
    np.testing.assert_allclose(quat_to_matrix(shape.rotation) @ [0, 0, 1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(shape.position, [0, 0.5, 0])
    np.testing.assert_allclose(model.gravity, (0.0, -9.81, 0.0))


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda b: b.add_particles([[0, 0, 0]], mass=-1.0), "particle mass must be finite and > 0"),
        (lambda b: b.add_particles([[0, 0, np.nan]]), "not finite"),
        (lambda b: b.add_springs([[0, 1]], stiffness=-5.0), "spring stiffness must be finite and >= 0"),
        (lambda b: b.add_springs([[0, 0]], stiffness=5.0), "to itself"),
        (lambda b: b.add_springs([[0, 9]], stiffness=5.0), "only 2 particles exist"),
        (lambda b: b.add_cloth_grid(nx=1, ny=3, spacing=0.1, mass=1.0), "nx must be an integer >= 2"),
        (lambda b: b.add_cloth_grid(nx=3, ny=3, spacing=-0.1, mass=1.0), "spacing must be a finite number > 0"),
        (lambda b: b.add_cloth_grid(nx=3, ny=3, spacing=0.1), "give exactly one of mass="),
        (lambda b: b.add_cloth_grid(nx=3, ny=3, spacing=0.1, mass=1.0, pin=["middle"]), "unknown pin 'middle'"),
        (lambda b: b.add_cloth_mesh(np.zeros((0, 3)), np.zeros((0, 3), int), mass=1.0), "empty"),
        (lambda b: b.add_cloth_mesh([[0, 0, 0], [1, 0, np.nan], [0, 1, 0]], [[0, 1, 2]], mass=1.0), "not finite"),
        (lambda b: b.add_cloth_mesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], mass=1.0), "zero area"),
        (lambda b: b.add_cloth_mesh("no/such/mesh.obj", mass=1.0), "mesh file not found"),
        (lambda b: b.add_collider_sphere(center=(0, 0, 0), radius=0.0), "sphere radius must be a finite number > 0"),
        (lambda b: b.add_ground_plane(friction=-0.1), "friction must be a finite number >= 0"),
    ],
)
def test_bad_input_raises_clear_config_error(call, message):
    """Bad input raises ConfigError whose message names the problem."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0, 0, 0], [1, 0, 0]])
    with pytest.raises(ws.ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        call(builder)


def test_empty_scene_and_bad_precision_are_rejected():
    """finalize refuses a scene without particles and an unknown precision."""
    with pytest.raises(ws.ConfigError, match="no particles"):
        ws.ModelBuilder().finalize("cpu")
    builder = ws.ModelBuilder()
    builder.add_particles([[0, 0, 0]])
    with pytest.raises(ws.ConfigError, match="precision must be one of"):
        builder.finalize("cpu", precision="float16")


@pytest.mark.parametrize(
    "positions, mass, message",
    [
        ([[0.0, 0.0, 1e39]], 1.0, "a particle position [m] overflows float32"),
        ([[0.0, 0.0, 0.0]], 1e-40, "an inverse particle mass [1/kg] overflows float32"),
    ],
)
def test_values_beyond_float32_are_rejected_at_finalize(positions, mass, message):
    """Finite float64 input that float32 cannot hold is refused by name, not turned into inf; float64 holds it."""
    builder = ws.ModelBuilder()
    builder.add_particles(positions, mass=mass)
    with pytest.raises(ws.ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        builder.finalize("cpu")
    model = builder.finalize("cpu", precision="float64")
    assert np.isfinite(model.particle_q.numpy()).all() and np.isfinite(model.particle_inv_mass.numpy()).all()


def test_obj_uv_seam_is_welded_not_torn(tmp_path):
    """An OBJ whose vertex 2 carries two UVs (a seam) gives one particle there, in the file's v order,
    joined by springs to both sides of the seam; the UVs move to the triangle corners."""
    path = tmp_path / "seam.obj"
    path.write_text(SEAM_OBJ)
    builder = ws.ModelBuilder()
    ids = builder.add_cloth_mesh(str(path), mass=1.0, pin=[4], bend=None)
    model = builder.finalize("cpu")
    np.testing.assert_array_equal(ids, np.arange(5))
    np.testing.assert_allclose(model.particle_q.numpy(), [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]])
    assert spring_set(model) == {(0, 1), (1, 2), (0, 2), (2, 3), (0, 3), (1, 4), (2, 4)}
    assert model.kinematic_mask()[4]  # pins name the file's vertices
    np.testing.assert_allclose(model.particle_mass.numpy().sum(), 1.0, rtol=1e-6)
    group = model.meshes[0]
    np.testing.assert_array_equal(group.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    np.testing.assert_allclose(group.uvs, [[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]],
                                           [[0.5, 0.5], [0.2, 0.2], [1, 1]]])
