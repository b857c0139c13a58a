"""Mesh colliders: distances and signs against trimesh in float64, Coulomb friction on a mesh slope, restitution,
a mesh moved by a track and one deforming, paths swept through thin colliders, and contact overflow.

Every scene here resolves contacts through the contact stage (``contact_stage=True``) with one mesh kind, so
the tests share three compiled feature sets: a static mesh, a moving mesh, and a static mesh with a box.
"""

import math

import numpy as np
import pytest
import trimesh
import warp as wp

import warpspring as ws
from warpspring.core.checkpoint import Checkpoint
from warpspring.errors import ConfigError, ContactOverflowWarning
from warpspring.io.scene import load_scene
from warpspring.kernels.shapes import SHAPE_MESH, ContactFeatures, shapes_type, surface_funcs

G = 9.81
R = 0.02  # particle radius [m]
THETA = math.radians(30.0)
NORMAL = np.array([0.0, -math.sin(THETA), math.cos(THETA)])  # the slope's outward normal
DOWNHILL = -np.array([0.0, math.cos(THETA), math.sin(THETA)])
# A float32 mesh query rounds coordinates of ~1 m: the closest point is off by a few units of 6e-8 m, the
# projected centre sits at distance r to ~1e-6 m (as on analytic colliders, tests/test_colliders.py).
ON_SURFACE = 2.0e-6


def slope_mesh(half: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """A square of side 2·``half`` [m] through the origin, tilted 30° about x (normal ``NORMAL``), as two
    counter-clockwise triangles: vertices [4, 3], faces [2, 3]."""
    u = np.array([1.0, 0.0, 0.0])
    w = np.cross(NORMAL, u)
    corners = np.array([-u - w, u - w, u + w, -u + w]) * half
    return corners, np.array([[0, 1, 2], [0, 2, 3]])


def floor_mesh(half: float = 2.0, z: float = 0.0, cells: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A horizontal grid of (cells × cells) squares at height z [m], normal +z."""
    t = np.linspace(-half, half, cells + 1)
    xx, yy = np.meshgrid(t, t, indexing="xy")
    vertices = np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], axis=1)
    k = np.arange(cells)
    i, j = np.meshgrid(k, k, indexing="ij")
    a = (i * (cells + 1) + j).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + cells + 2], 1), np.stack([a, a + cells + 2, a + cells + 1], 1)])
    return vertices, faces


def run(model, *, fps=60, substeps=16, frames=60, guard=True):
    sim = ws.Simulator(model, fps=fps, substeps=substeps, **({} if guard else {"guard": None}))
    for _ in range(frames):
        sim.step_frame()
    return sim


def particles(sim) -> tuple[np.ndarray, np.ndarray]:
    """Positions [m] and velocities [m/s] of world 0, float64."""
    n = sim.model.particle_count
    return (sim.state.particle_q.numpy()[:n].astype(np.float64), sim.state.particle_qd.numpy()[:n].astype(np.float64))


# --------------------------------------------------------------------------------------- distance and sign


@pytest.fixture(scope="module")
def distance_kernel():
    features = ContactFeatures(kinds=(SHAPE_MESH,), buffered=True, swept=True)
    _, shape_distance = surface_funcs(wp.float32, features)
    Shapes = shapes_type(wp.float32)

    @wp.kernel(module="unique", enable_backward=False)
    def distances(shapes: Shapes, s: int, points: wp.array[wp.vec3], out: wp.array[float],
                  normals: wp.array[wp.vec3]):
        k = wp.tid()
        d, n = shape_distance(shapes, s, 0, -1, points[k])
        out[k] = d
        normals[k] = n

    return distances


def test_mesh_distance_and_sign_equal_trimesh_in_float64(device, distance_kernel):
    """Closed meshes (an icosphere, a box, a capsule, placed and turned): the signed distance of 300 points
    in and around each equals trimesh's float64 closest-point distance with the sign of its containment
    test, to float32 rounding of 2 m coordinates (1e-5 m); the normal is the direction from the closest
    point (the distance's gradient: one step of d along -n lands on the surface). Signed by the winding
    number, the sphere gives the same. A point deep inside a mesh looked for within a smaller depth finds its
    closest point; one beyond it outside is out of reach. An open height field, one-sided: negative below
    it; two-sided: the unsigned distance less the thickness."""
    rng = np.random.default_rng(7)
    closed = [trimesh.creation.icosphere(subdivisions=2, radius=0.5), trimesh.creation.box(extents=(0.8, 0.4, 0.2)),
              trimesh.creation.capsule(height=0.6, radius=0.2, count=[12, 12])]
    centers = [(0.3, -0.2, 0.5), (-1.0, 0.5, 0.2), (0.0, 1.5, 0.0)]
    orientation = (0.0, 0.0, math.sin(0.3), math.cos(0.3))  # 0.6 rad about z
    t = np.linspace(-1.0, 1.0, 9)
    xx, yy = np.meshgrid(t, t)
    bumps = np.stack([xx.ravel(), yy.ravel(), 0.1 * np.sin(2 * xx.ravel()) * np.cos(3 * yy.ravel())], axis=1)
    field = trimesh.Trimesh(bumps, _grid_faces(9), process=False)
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 5.0]])
    for mesh, center in zip(closed, centers):
        builder.add_collider_mesh(mesh, center=center, orientation=orientation, depth=2.0)
    builder.add_collider_mesh(field, sides="one_sided", depth=1.0)
    builder.add_collider_mesh(field, sides="two_sided", thickness=0.01, depth=1.0)
    builder.add_collider_mesh(closed[0], name="default_depth")  # looked for within 0.17 m, deep inside further
    builder.add_collider_mesh(closed[0], center=centers[0], orientation=orientation, depth=2.0, winding_number=True)
    model = builder.finalize(device, contact_stage=True)

    def device_distance(s, points):
        q = wp.array(points.astype(np.float32), dtype=wp.vec3, device=device)
        out = wp.zeros(len(points), dtype=float, device=device)
        normals = wp.zeros(len(points), dtype=wp.vec3, device=device)
        wp.launch(distance_kernel, dim=len(points), inputs=[model.shape_arrays, s, q], outputs=[out, normals],
                  device=device)
        return out.numpy().astype(np.float64), normals.numpy().astype(np.float64)

    rotation = trimesh.transformations.quaternion_matrix([orientation[3], *orientation[:3]])
    probe_cloud = np.asarray(centers[0]) + rng.uniform(-0.8, 0.8, (300, 3))
    for s, (mesh, center) in enumerate(zip(closed, centers)):
        placed = mesh.copy()
        placed.apply_transform(rotation)
        placed.apply_translation(center)
        points = placed.bounds[0] + rng.random((300, 3)) * (placed.bounds[1] - placed.bounds[0]) * 1.6 \
            - 0.3 * (placed.bounds[1] - placed.bounds[0])
        distance = trimesh.proximity.closest_point(placed, points)[1]
        sign = np.where(placed.contains(points), -1.0, 1.0)
        clear = distance > 1e-3  # the sign of a point on the surface is either
        d, n = device_distance(s, points)
        np.testing.assert_allclose(d[clear], (sign * distance)[clear], atol=1e-5)
        # The normal points from a closest point (there may be several at one distance, near the medial axis):
        # the point d along -n from each probe is on the surface, to the distance's tolerance.
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
        on_surface = trimesh.proximity.closest_point(placed, points - d[:, None] * n)[1]
        np.testing.assert_allclose(on_surface, 0.0, atol=2e-5)

    points = np.c_[rng.uniform(-0.8, 0.8, (300, 2)), rng.uniform(-0.4, 0.4, 300)]
    closest, distance, _ = trimesh.proximity.closest_point(field, points)
    below = np.array([_below(field, p) for p in points])
    clear = distance > 1e-3
    d, _ = device_distance(3, points)
    np.testing.assert_allclose(d[clear], np.where(below, -distance, distance)[clear], atol=1e-5)
    d, _ = device_distance(4, points)
    np.testing.assert_allclose(d, distance - 0.01, atol=1e-5)

    sphere = closed[0]
    depth = 0.1 * np.linalg.norm(sphere.bounds[1] - sphere.bounds[0])
    probes = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.5 + 0.5 * depth, 0.0], [0.0, 0.0, 0.5 + 2 * depth]])
    reference = -trimesh.proximity.closest_point(sphere, probes[:3])[1] * [1, 1, -1]
    d, _ = device_distance(5, probes)
    np.testing.assert_allclose(d[:3], reference, atol=1e-5)  # deep inside, inside, outside within its depth
    assert d[3] == pytest.approx(1.0e30)  # beyond its depth: out of reach

    # The same sphere signed by its winding number (placed as the first): the same distances.
    d0, _ = device_distance(0, probe_cloud)
    d6, _ = device_distance(6, probe_cloud)
    np.testing.assert_allclose(d6, d0, atol=1e-6)


def _grid_faces(n: int) -> np.ndarray:
    k = np.arange(n - 1)
    i, j = np.meshgrid(k, k, indexing="ij")
    a = (i * n + j).ravel()
    return np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])


def _below(field: trimesh.Trimesh, p: np.ndarray) -> bool:
    """Whether p is under the height field (a vertical ray up from it hits the surface)."""
    return len(field.ray.intersects_location([p], [[0.0, 0.0, 1.0]])[0]) > 0


# ------------------------------------------------------------------------------------------------ response


def slope_block(device, *, friction, static_friction=None, speed=0.0):
    """A 3 × 3 block of free particles (spacing 0.1 m, radius R) resting on the 30° mesh slope, started at
    ``speed`` [m/s] downhill: the model."""
    u = np.array([1.0, 0.0, 0.0])
    w = np.cross(NORMAL, u)
    k = np.arange(3) * 0.1
    grid = (k[:, None, None] * u + k[None, :, None] * w).reshape(-1, 3) + R * NORMAL
    builder = ws.ModelBuilder()
    builder.add_particles(grid, mass=0.01, radius=R, velocities=speed * DOWNHILL)
    vertices, faces = slope_mesh()
    builder.add_collider_mesh(vertices, faces=faces, sides="one_sided", friction=friction,
                              static_friction=static_friction, name="slope")
    return builder.finalize(device, contact_stage=True)


def test_block_slides_down_a_mesh_slope_at_coulomb_acceleration(device):
    """μ = 0.1 on a 30° mesh slope: every particle's speed after 1 s is g (sin θ - μ cos θ) t = 4.055 m/s
    (required within 2 %; the discrete speed is exact, tests/test_contacts.py, so it holds to float32 rounding
    of the mesh query, 1e-4 m/s), and every particle stays on the slope at distance r."""
    model = slope_block(device, friction=0.1)
    sim = run(model, frames=60)
    x, v = particles(sim)
    a = G * (math.sin(THETA) - 0.1 * math.cos(THETA))
    np.testing.assert_allclose(v @ DOWNHILL, a * 1.0, rtol=0.02)
    np.testing.assert_allclose(v @ DOWNHILL, a * 1.0, atol=1e-4)
    np.testing.assert_allclose(x @ NORMAL, R, atol=ON_SURFACE)


def test_block_creeps_less_than_a_millimetre_at_high_friction(device):
    """μ = 0.8 > tan 30°: in 2 s on the mesh slope no particle moves 1 mm (it sticks: each step's friction
    impulse cancels the h g sin θ gained, so it moves only by rounding)."""
    model = slope_block(device, friction=0.8)
    start = model.particle_q.numpy().astype(np.float64)
    sim = run(model, frames=120)
    x, v = particles(sim)
    assert np.linalg.norm(x - start, axis=1).max() < 1.0e-3
    assert np.linalg.norm(x - start, axis=1).max() < 1.0e-5  # what the model gives: rounding only


def test_static_friction_holds_and_kinetic_friction_slows(device):
    """μ_s = 0.8, μ_k = 0.1: a block at rest stays (|v_t| ≤ μ_s j_n every step), one launched at 1 m/s
    downhill slides and speeds up at g (sin θ - μ_k cos θ)."""
    at_rest = run(slope_block(device, friction=0.1, static_friction=0.8), frames=30)
    x, v = particles(at_rest)
    assert np.abs(v).max() == 0.0
    launched = run(slope_block(device, friction=0.1, static_friction=0.8, speed=1.0), frames=30)
    x, v = particles(launched)
    a = G * (math.sin(THETA) - 0.1 * math.cos(THETA))
    np.testing.assert_allclose(v @ DOWNHILL, 1.0 + a * 0.5, atol=1e-4)


def test_bounce_on_a_mesh_reaches_restitution_squared_times_the_drop_height(device):
    """Dropped from 1 m onto a closed mesh box of restitution e = 0.5, the particle rises to e² · 1 m within 2 %
    (the impact is resolved at the end of the step that reaches the surface: an error ≤ (1 + e) v h + g h²,
    as on analytic colliders, tests/test_colliders.py)."""
    e, height = 0.5, 1.0
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, height + R]], radius=R)
    builder.add_collider_mesh(trimesh.creation.box(extents=(2.0, 2.0, 0.2)), center=(0.0, 0.0, -0.1),
                              restitution=e, friction=0.0, name="slab")
    model = builder.finalize(device, contact_stage=True)
    sim = ws.Simulator(model, fps=960, substeps=2, guard=None)
    z = []
    for _ in range(round(1.2 * 960)):
        sim.step_frame()
        z.append(float(sim.state.particle_q.numpy()[0, 2]))
    z = np.array(z) - R
    assert z.min() >= -ON_SURFACE
    impact = int(np.argmin(z[: round(0.6 * 960)]))  # the first impact, at 0.45 s (the second is at 0.9 s)
    apex = z[impact:].max()
    assert apex == pytest.approx(e * e * height, rel=0.02)
    v_impact, h = math.sqrt(2 * G * height), sim.dt
    sampling = 0.5 * G * (1.0 / 960) ** 2  # the apex read at frames, not at its instant
    assert abs(apex - e * e * height) <= (1 + e) * v_impact * h + G * h * h + sampling


# ------------------------------------------------------------------------------------------ moving meshes

PLATFORM = ws.Track([0.0, 0.5, 1.5, 2.0], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.4, 0.0, 0.2], [0.4, 0.0, 0.2]],
                    interpolation="smooth")  # peak acceleration 2.4 m/s² < μ g: static friction can carry


def test_a_mesh_moved_by_a_track_carries_a_resting_particle(device):
    """A particle resting on a mesh box moved by a translation track keeps its place on it: each step the
    response moves it with the surface's displacement."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.1, 0.0, 0.1 + R]], radius=R)
    builder.add_collider_mesh(trimesh.creation.box(extents=(2.0, 2.0, 0.2)), friction=0.8, translation=PLATFORM,
                              name="platform")
    model = builder.finalize(device, contact_stage=True)
    assert model.shape_moving
    sim = ws.Simulator(model, fps=60, substeps=16)
    drift = 0.0
    for _ in range(120):
        sim.step_frame()
        x, _ = particles(sim)
        drift = max(drift, np.abs(x[0] - PLATFORM.sample(sim.time)[0][0] - [0.1, 0.0, 0.1 + R]).max())
    assert drift <= 1.0e-5  # float32 rounding of the frames and the query over 1920 steps
    _, v = particles(sim)
    np.testing.assert_allclose(v[0], 0.0, atol=1e-4)  # the platform is at rest again
    assert sim.contact_overflow().tolist() == [0]


def test_a_deforming_mesh_moves_particles_with_its_surface_velocity(device):
    """A floor whose points are set between frames. As a conveyor belt (points still, velocities 0.3 m/s
    along x), friction μ = 1 carries a resting particle at the belt's speed: relative to the surface it
    sticks. Rising at 0.2 m/s (points moved every frame, velocities from their change), it lifts the particle,
    which stays on it: its height follows the floor's within one frame's rise."""
    vertices, faces = floor_mesh()
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, R], [1.0, 1.0, R]], radius=R)
    builder.add_collider_mesh(vertices, faces=faces, sides="one_sided", friction=1.0, deforming=True,
                              name="belt")
    model = builder.finalize(device, contact_stage=True)
    belt = model.mesh_collider("belt")
    belt.set_points(vertices, velocities=(0.3, 0.0, 0.0))
    sim = run(model, frames=30)
    x, v = particles(sim)
    np.testing.assert_allclose(v, [[0.3, 0.0, 0.0]] * 2, atol=1e-5)
    np.testing.assert_allclose(x[:, 2], R, atol=ON_SURFACE)

    lift, frame = 0.2, 1.0 / 60
    sim = ws.Simulator(model, fps=60, substeps=16)
    gaps = []
    for k in range(1, 31):
        belt.set_points(vertices + [0.0, 0.0, lift * k * frame], dt=frame)
        sim.step_frame()
        x, v = particles(sim)
        gaps.append(x[:, 2] - lift * k * frame - R)
    gaps = np.array(gaps)
    assert gaps.min() >= -ON_SURFACE  # never under the floor
    assert gaps.max() <= lift * frame + 1e-6  # never ahead of it by more than one frame's rise
    np.testing.assert_allclose(x[:, 2].mean(), lift * 30 * frame + R, atol=lift * frame)


# ----------------------------------------------------------------------------------------------- tunnelling


@pytest.mark.parametrize("speed", [10.0, 100.0, 1000.0])
def test_fast_particles_never_end_on_the_wrong_side_of_thin_colliders(device, speed):
    """Particles shot at ``speed`` [m/s] (up to 1000 m/s: 1 m per step at h = 1/960 s, 500 times the thin
    box's thickness) at a zero-thickness mesh plane (two-sided, and one-sided from its front), a closed mesh
    slab 2 mm thick and an analytic box 2 mm thick, gravity off, 8 particles each at up to 0.6° from the
    normal: their path over each step is swept, so none ends past the collider; each stops on its own side
    at distance r (inelastic, frictionless: the normal velocity is removed; the crossing point of a float32
    ray is off by ~1e-7 of the step's 1 m path). Eight more at a capsule pole of radius 2 mm, aimed within
    half of r + 2 mm of its axis (6 of the 8 paths miss the pole itself; they touch it at most 30° from the
    top, where μ = 5 stops them: a grazing particle, or a frictionless one, slides around it instead): swept
    against the pole grown by the radius, each stops on its upper half, its centre r + 2 mm from the axis."""
    vertices, faces = floor_mesh(half=4.0, cells=2)
    builder = ws.ModelBuilder()
    builder.gravity = (0.0, 0.0, 0.0)
    rng = np.random.default_rng(3)
    for x_offset, kind in [(-15.0, "two_sided"), (-5.0, "one_sided"), (5.0, "slab"), (15.0, "box")]:
        start = np.c_[rng.uniform(-1.0, 1.0, 8) + x_offset, rng.uniform(-1.0, 1.0, 8), np.full(8, 0.5)]
        direction = np.c_[rng.uniform(-0.01, 0.01, (8, 2)), -np.ones(8)]
        direction /= np.linalg.norm(direction, axis=1)[:, None]
        builder.add_particles(start, radius=R, velocities=speed * direction)
        center = (x_offset, 0.0, 0.0)
        if kind in ("two_sided", "one_sided"):
            builder.add_collider_mesh(vertices, faces=faces, sides=kind, center=center, friction=0.0, name=kind)
        elif kind == "slab":
            builder.add_collider_mesh(trimesh.creation.box(extents=(8.0, 8.0, 0.002)), center=(x_offset, 0, -0.001),
                                      friction=0.0, name=kind)
        else:
            builder.add_collider_box(center=(x_offset, 0.0, -0.001), half_extents=(4.0, 4.0, 0.001), friction=0.0)
    pole = 0.002
    start = np.c_[25.0 + np.linspace(-0.5, 0.5, 8) * (R + pole), rng.uniform(-1.0, 1.0, 8), np.full(8, 0.5)]
    builder.add_particles(start, radius=R, velocities=(0.0, 0.0, -speed))
    builder.add_collider_capsule(center=(25.0, 0.0, 0.0), radius=pole, half_height=4.0, friction=5.0,
                                 orientation=(-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)))  # along y
    model = builder.finalize(device, contact_stage=True, contact_slots=2)
    assert model.contact_features().swept
    sim = run(model, fps=60, substeps=16, frames=4, guard=False)
    x, v = particles(sim)
    x, v, pole_x = x[:32], v[:32], x[32:]
    assert x[:, 2].min() > 0.0  # none past the plane z = 0
    np.testing.assert_allclose(x[:, 2], R, atol=1e-5 * max(1.0, speed / 100.0))
    np.testing.assert_allclose(v[:, 2], 0.0, atol=1e-6 * speed)
    assert pole_x[:, 2].min() > 0.0  # above the pole's axis: none passed it
    # It sticks where it touched: at R + r from the axis, but for a particle the closest point caught (10 m/s),
    # whose step along the tangent, at most h v, leaves it up to (h v)² / 2 (R + r) outside the curved surface.
    gap = np.hypot(pole_x[:, 0] - 25.0, pole_x[:, 2]) - (R + pole)
    assert gap.min() >= -1e-5 and gap.max() <= (speed / 960) ** 2 / (2 * (R + pole)) + 1e-5


# ----------------------------------------------------------------------------------------- overflow, input


def test_mesh_contact_overflow_is_counted_and_warned(device):
    """Three coincident mesh boxes and one contact slot: a resting particle touches all three every step; the
    two dropped contacts per step are counted and warned about (ContactOverflowWarning)."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 0.2 + R]], radius=R)
    for k in range(3):
        builder.add_collider_mesh(trimesh.creation.box(extents=(1.0, 1.0, 0.2)), center=(0.0, 0.0, 0.1),
                                  name=f"box{k}")
    model = builder.finalize(device, contact_stage=True, contact_slots=1)
    sim = ws.Simulator(model, fps=60, substeps=16)
    with pytest.warns(ContactOverflowWarning, match=r"frame 1: .*contact_slots=2"):
        sim.step_frame()
    assert sim.contact_overflow().tolist() == [2 * 16]
    x, _ = particles(sim)
    assert abs(x[0, 2] - (0.2 + R)) <= ON_SURFACE


def test_mesh_collider_input_is_checked(tmp_path):
    """Bad input gives one-line ConfigErrors naming what is wrong."""
    builder = ws.ModelBuilder()
    vertices, faces = floor_mesh()
    with pytest.raises(ConfigError, match="sides must be one of"):
        builder.add_collider_mesh(vertices, faces=faces, sides="inside")
    with pytest.raises(ConfigError, match="faces index vertices"):
        builder.add_collider_mesh(vertices, faces=faces + 100)
    with pytest.raises(ConfigError, match="need faces"):
        builder.add_collider_mesh(vertices)
    with pytest.raises(ConfigError, match="not found"):
        builder.add_collider_mesh(tmp_path / "missing.obj")
    with pytest.raises(ConfigError, match="static_friction"):
        builder.add_collider_mesh(vertices, faces=faces, friction=0.5, static_friction=0.2)
    builder.add_particles([[0.0, 0.0, 1.0]], radius=0.02)
    builder.add_collider_mesh(vertices, faces=faces, sides="one_sided", name="floor")
    model = builder.finalize("cpu")
    with pytest.raises(ConfigError, match="deforming=True"):
        model.mesh_collider("floor").set_points(vertices)
    with pytest.raises(ConfigError, match="no mesh collider 'wall'"):
        model.mesh_collider("wall")
    builder.add_collider_mesh(vertices, faces=faces, sides="two_sided", depth=0.01, name="thin")
    with pytest.raises(ConfigError, match="'thin': its depth .* must exceed the particle radius"):
        builder.finalize("cpu")


def test_mesh_collider_from_files(tmp_path):
    """A mesh collider from any file trimesh reads (an OBJ here) and from a USD prim, whose time-sampled points
    make it deform (points at each frame's end, velocities from their change)."""
    from pxr import Usd, UsdGeom

    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.export(tmp_path / "box.obj")
    stage = Usd.Stage.CreateNew(str(tmp_path / "floor.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    stage.SetTimeCodesPerSecond(24.0)
    mesh = UsdGeom.Mesh.Define(stage, "/World/floor")
    vertices, faces = floor_mesh(cells=1)
    mesh.GetFaceVertexCountsAttr().Set([3] * len(faces))
    mesh.GetFaceVertexIndicesAttr().Set(faces.ravel().tolist())
    for code, z in ((0.0, 0.0), (24.0, 0.5)):
        mesh.GetPointsAttr().Set([tuple(p) for p in vertices + [0.0, 0.0, z]], code)
    stage.Save()

    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 2.0]])
    builder.add_collider_mesh(tmp_path / "box.obj", center=(3.0, 0.0, 0.0), name="box")
    builder.add_collider_mesh(tmp_path / "floor.usda", sides="one_sided", name="floor")
    model = builder.finalize("cpu")
    np.testing.assert_allclose(model.mesh_collider("box").points(), box.vertices)
    floor = model.mesh_collider("floor")
    assert model.shape_deforming and floor.info.sampled
    np.testing.assert_allclose(floor.info.sample_times, [0.0, 1.0])
    ws.core.mesh_colliders.advance_mesh_colliders(model, 0.25, 0.5)
    np.testing.assert_allclose(floor.points()[:, 2], 0.25)
    np.testing.assert_allclose(floor.mesh.velocities.numpy()[:, 2], 0.5, rtol=1e-6)


def test_mesh_colliders_are_exported_beside_the_cloth(tmp_path, device):
    """A static mesh is a guide Mesh prim of its triangles, posed once; a tracked one's translate is sampled at
    every frame; a deforming one's points (and extent) are sampled at every frame, as they were set."""
    from pxr import Usd, UsdGeom

    from warpspring.io.usd import UsdWriter

    vertices, faces = floor_mesh(cells=2)
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0]], radius=R)
    builder.add_collider_mesh(trimesh.creation.icosphere(subdivisions=1), center=(2.0, 0.0, 0.0), name="rock")
    builder.add_collider_mesh(vertices, faces=faces, sides="one_sided", translation=PLATFORM, name="lift")
    builder.add_collider_mesh(vertices, faces=faces, sides="two_sided", deforming=True, name="sheet")
    model = builder.finalize(device, contact_stage=True)
    sheet = model.mesh_collider("sheet")
    with UsdWriter(tmp_path / "meshes.usdc", model, fps=2) as writer:
        for k in range(4):
            sheet.set_points(vertices + [0.0, 0.0, 0.1 * k], dt=0.5)
            writer.write_frame(model.state())
    stage = Usd.Stage.Open(str(tmp_path / "meshes.usdc"))
    rock = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/rock"))
    assert rock.GetPurposeAttr().Get() == "guide"
    assert len(rock.GetFaceVertexIndicesAttr().Get()) == 3 * 80 and not rock.GetDoubleSidedAttr().Get()
    assert rock.GetPointsAttr().GetTimeSamples() == []
    np.testing.assert_allclose(np.array(ops_of(rock)["translate"].Get()), [2.0, 0.0, 0.0])
    lift = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/lift"))
    translate = ops_of(lift)["translate"]
    assert translate.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    np.testing.assert_allclose(np.array(translate.Get(3.0)), PLATFORM.sample(1.5)[0][0], atol=1e-9)
    sheet_prim = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders/sheet"))
    assert sheet_prim.GetDoubleSidedAttr().Get()
    assert sheet_prim.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    np.testing.assert_allclose(np.array(sheet_prim.GetPointsAttr().Get(2.0))[:, 2], 0.2, atol=1e-7)


def ops_of(prim) -> dict:
    """The prim's xform ops by name ("translate", "orient")."""
    from pxr import UsdGeom

    return {op.GetOpName().split(":")[1]: op for op in UsdGeom.Xformable(prim).GetOrderedXformOps()}


def test_scene_mesh_collider(tmp_path):
    """A [[collider]] of type "mesh" reads its file relative to the scene, with its placement, sides, thickness,
    static and kinetic friction and tracks; keys of other types are refused. [contacts] switches triangle
    contacts on and swept paths off."""
    trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(tmp_path / "crate.obj")
    text = """version = 2
[cloth]
grid = { nx = 3, ny = 3, spacing = 0.1 }
origin = [0.0, 0.0, 1.0]
mass = 0.1
[[collider]]
type = "mesh"
file = "crate.obj"
name = "crate"
center = [0.0, 0.0, 0.5]
scale = 2.0
sides = "closed"
thickness = 0.005
friction = 0.3
static_friction = 0.6
translation = { times = [0.0, 1.0], values = [[0, 0, 0], [1, 0, 0]] }
[contacts]
triangles = true
swept = false
"""
    (tmp_path / "scene.toml").write_text(text)
    builder = load_scene(tmp_path / "scene.toml").builder()
    shape = builder._shapes[-1]
    assert (shape.kind, shape.name, shape.thickness, shape.friction, shape.static_friction) == \
        ("mesh", "crate", 0.005, 0.3, 0.6)
    np.testing.assert_allclose(np.abs(shape.mesh.vertices), 1.0)  # the unit box scaled by 2
    assert shape.moving and shape.mesh.sides == "closed"
    model = load_scene(tmp_path / "scene.toml").finalize("cpu")
    assert model.contact_triangles and not model.contact_swept and model.mesh_collider("crate").info.sides == "closed"
    (tmp_path / "bad.toml").write_text(text.replace('sides = "closed"', 'radius = 1.0'))
    with pytest.raises(ConfigError, match="radius does not apply to a mesh collider"):
        load_scene(tmp_path / "bad.toml")


# ------------------------------------------------------------------------------------- cloth triangles


def test_cloth_triangles_do_not_slip_over_a_small_sphere_or_a_thin_pole(device):
    """The seed's case: a soft cloth (k = 1 N/m, strain limited to 10 % as a user would) dropped on a sphere of
    radius 0.04 m, smaller than its 0.1 m particle spacing, resting on the ground, and another over a pole
    (a capsule of radius 1.5 cm) lying between two of its particle rows. With particle contacts only, the
    sphere pokes through the cloth (its centre ends within the radius of the cloth surface) and the second
    cloth falls through the pole to the ground. With ``contact_triangles``, each triangle's closest point is
    kept radius + r away: the cloth tents over the sphere and hangs over the pole (the centre and the axis
    end at least R + r/2 from the cloth, which lies above them)."""
    R, r, pole, pole_z = 0.04, 0.01, 0.015, 0.2
    sphere_center = np.array([0.03, 0.02, R])
    axis = np.c_[np.linspace(2.4, 3.6, 121), np.zeros(121), np.full(121, pole_z)]
    results = {}
    for triangles in (False, True):
        builder = ws.ModelBuilder()
        soft = ws.SpringMaterial(ke=1.0, kd=0.01)
        cloths = [builder.add_cloth_grid(nx=10, ny=10, spacing=0.1, origin=(x - 0.45, -0.45, 0.3), particle_mass=0.001,
                                         radius=r, structural=soft, shear=soft, bend=soft) for x in (0.0, 3.0)]
        builder.add_collider_sphere(center=sphere_center, radius=R, friction=0.5)
        builder.add_collider_capsule(center=(3.0, 0.0, pole_z), radius=pole, half_height=0.6,
                                     orientation=(0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5)), friction=0.5)  # along x
        builder.add_ground_plane(friction=0.8)
        model = builder.finalize(device)
        model.stabilizers = ws.Stabilizers(max_strain=0.1)
        model.contact_triangles = triangles
        sim = run(model, fps=60, substeps=20, frames=60)
        q = particles(sim)[0]
        faces = model.tri_indices.numpy()
        tent = trimesh.Trimesh(q, faces[: len(faces) // 2], process=False)
        drape = trimesh.Trimesh(q, faces[len(faces) // 2:], process=False)
        results[triangles] = (trimesh.proximity.closest_point(tent, [sphere_center])[1][0],
                              q[cloths[0].ravel(), 2].max(),
                              trimesh.proximity.closest_point(drape, axis)[1].min(),
                              q[cloths[1].ravel(), 2].max())
    sphere_gap, tent_top, pole_gap, drape_top = results[False]
    assert sphere_gap < R and tent_top < 2 * R  # points only: the sphere went through the cloth
    assert drape_top < pole_z  # and the cloth fell through the pole
    sphere_gap, tent_top, pole_gap, drape_top = results[True]
    assert sphere_gap >= R + 0.5 * r and tent_top >= 2 * R
    assert pole_gap >= pole + 0.5 * r and drape_top >= pole_z + pole


def test_run_summary_gives_the_contact_slots_held():
    """The run summary's line names the most contact slots held at a frame's end (with the contact stage),
    before the worlds' notes; without the stage it says nothing of them. Overflowing mesh caches are named."""
    from warpspring.app.runner import RunSummary

    common = dict(output="out.usdc", frames=10, simulated_time=1.0, wall_time=1.0, setup_time=0.5, substeps=16,
                  dt=1e-3, device="cpu", model="model", integrator="symplectic_euler", advice="")
    line = RunSummary(**common, peak_contacts=(37, 400), contact_overflow=3).line()
    assert "; model; at most 37 of 400 contact slots held at a frame's end; 3 contacts dropped" in line
    assert "contact slots held" not in RunSummary(**common).line()
    assert "; 5 full mesh queries for overflowing candidate caches" in RunSummary(**common, mesh_cache_overflow=5).line()
    assert "candidate caches" not in RunSummary(**common).line()


def test_thin_colliders_example_runs(tmp_path, device):
    """examples/thin_colliders.toml (three soft cloths on a small sphere, a thin pole and a mesh rock, with
    triangle contacts) builds, runs two frames and writes its cloths and colliders to USD."""
    from pathlib import Path

    from pxr import Usd

    from warpspring.io.usd import UsdWriter

    scene = load_scene(Path(__file__).parent.parent / "examples" / "thin_colliders.toml")
    model = scene.finalize(device)
    assert model.contact_triangles and [s.kind for s in model.shapes] == ["sphere", "capsule", "mesh", "plane"]
    sim = ws.Simulator(model, fps=60, substeps=20)
    with UsdWriter(tmp_path / "thin.usdc", model, fps=60) as writer:
        writer.write_frame(sim.state)
        for _ in range(2):
            sim.step_frame()
            writer.write_frame(sim.state)
    stage = Usd.Stage.Open(str(tmp_path / "thin.usdc"))
    assert stage.GetPrimAtPath("/World/tent").GetAttribute("points").GetTimeSamples() == [0.0, 1.0, 2.0]
    assert stage.GetPrimAtPath("/World/colliders/rock").GetTypeName() == "Mesh"
    assert np.isfinite(sim.state.particle_q.numpy()).all()


# ----------------------------------------------------------------------------------------- the candidate cache


def _cache_scene(device, *, candidates=32, moving=False):
    """Free particles (radius R) dropped, some at 20 m/s, on a closed icosphere, a two-sided bumpy sheet whose
    points the caller moves every frame (deforming) and a one-sided floor under both; with ``moving``, the
    sphere and the floor are moved by tracks instead (the sheet stays), in two worlds of their own gravity (so
    each world's frames and caches are its own). The model, the sheet and its points."""
    rng = np.random.default_rng(11)
    builder = ws.ModelBuilder()
    drop = np.c_[rng.uniform(-0.25, 0.25, (30, 2)), rng.uniform(0.7, 1.0, 30)]
    builder.add_particles(drop, radius=R, velocities=np.c_[rng.uniform(-0.5, 0.5, (30, 2)), np.zeros(30)])
    sheet_drop = np.c_[rng.uniform(1.6, 2.4, 30), rng.uniform(-0.4, 0.4, 30), rng.uniform(0.3, 0.6, 30)]
    speed = np.where(np.arange(30) % 3 == 0, -20.0, -1.0)  # a third fast: their paths are swept through the sheet
    builder.add_particles(sheet_drop, radius=R, velocities=np.c_[np.zeros((30, 2)), speed])
    track = {}
    if moving:
        track = {"translation": ws.Track([0.0, 1.0], [[0.0, 0.0, 0.0], [0.3, 0.0, 0.1]], interpolation="smooth"),
                 "rotation": ws.Track([0.0, 1.0], [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], interpolation="linear")}
    builder.add_collider_mesh(trimesh.creation.icosphere(subdivisions=3, radius=0.3), center=(0.0, 0.0, 0.3),
                              friction=0.3, name="ball", cache_candidates=candidates, **track)
    vertices, faces = floor_mesh(half=0.6, z=0.0, cells=8)
    builder.add_collider_mesh(vertices, faces=faces, sides="two_sided", center=(2.0, 0.0, 0.0), friction=0.2,
                              deforming=True, name="sheet", cache_candidates=candidates)
    floor, floor_faces = floor_mesh(half=4.0, z=-0.05, cells=6)
    builder.add_collider_mesh(floor, faces=floor_faces, sides="one_sided", friction=0.5, name="floor",
                              cache_candidates=candidates, **({"translation": track["translation"]} if moving else {}))
    model = builder.finalize(device, contact_stage=True, contact_slots=2, worlds=2 if moving else 1)
    if moving:
        model.set_world_values("gravity", [[0.0, 0.0, -G], [1.0, 0.0, -0.5 * G]])
    return model, model.mesh_collider("sheet"), vertices


def _cache_run(model, sheet, vertices, *, margin, frames=30):
    """Positions and velocities (every world) after ``frames`` frames (16 substeps each) with every mesh's cache
    margin set to ``margin`` [m] (0: the full query at every use; None: the default), the sheet waving."""
    for collider in model.mesh_colliders:
        collider.cache_margin = 0.25 * R if margin is None else margin  # the default: (radius + thickness) / 4
    sheet.set_points(vertices)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=None)
    x, y = vertices[:, 0], vertices[:, 1]
    for k in range(1, frames + 1):
        t = k / 60.0
        wave = vertices + np.c_[np.zeros((len(x), 2)), 0.05 * np.sin(4.0 * x + 3.0 * t) * np.cos(3.0 * y)]
        sheet.set_points(wave, dt=1.0 / 60.0)
        sim.step_frame()
    return sim.state.particle_q.numpy(), sim.state.particle_qd.numpy()


@pytest.mark.parametrize("moving", [False, True], ids=["static", "tracked"])
def test_mesh_cache_changes_the_work_never_the_answer(device, moving):
    """The candidate cache (margin 2R) against the full query at every use (``cache_margin = 0``): bit for bit
    the same positions and velocities after 480 substeps, for a closed mesh (static, or moved by tracks), a
    deforming two-sided sheet crossed by fast particles (swept paths) and a one-sided floor (static or
    tracked, in two worlds of their own gravity); and with the default margin (R / 4) and caches of 2
    triangles, which overflow (counted in every world), still the same bits. The cache is used: with it on, the full BVH queries are under an eighth of the uses (none
    are stored with it off); the particles rest on the colliders (none fell through)."""
    from warpspring.core.mesh_colliders import mesh_cache_counts

    model, sheet, vertices = _cache_scene(device, moving=moving)
    before = mesh_cache_counts(model)["refreshes"].sum()
    x_cached, v_cached = _cache_run(model, sheet, vertices, margin=2.0 * R)
    cached = mesh_cache_counts(model)
    x_full, v_full = _cache_run(model, sheet, vertices, margin=0.0)
    counts = mesh_cache_counts(model)
    np.testing.assert_array_equal(x_cached, x_full)
    np.testing.assert_array_equal(v_cached, v_full)
    refreshes = cached["refreshes"].sum() - before
    uses = 3 * model.state_size * 30 * 16  # collide queries the three meshes every substep (the response more)
    print(f"full queries with the cache: {refreshes} of {uses} uses or more")
    assert 0 < refreshes < uses / 8  # most from the cache
    assert (counts["refreshes"] == cached["refreshes"]).all()  # margin 0: never stored
    assert (counts["overflow"] == 0).all()
    assert x_full[:, 2].min() > -0.05 + R - 1e-4  # on or above the floor, 0.5 s after the drop (free fall: -1.2 m)
    assert (x_full[:, 2] > -0.06).all()

    small, sheet, vertices = _cache_scene(device, candidates=2, moving=moving)
    x_small, v_small = _cache_run(small, sheet, vertices, margin=None)
    np.testing.assert_array_equal(x_small, x_full)
    np.testing.assert_array_equal(v_small, v_full)
    assert (mesh_cache_counts(small)["overflow"] > 0).all()


def test_mesh_cache_resumes_bit_for_bit(device, tmp_path):
    """A run with mesh caches continued from a checkpoint equals the uninterrupted run bit for bit, in the same
    simulator rewound (its caches then hold entries from the run's later frames) and in a fresh one."""
    model, sheet, vertices = _cache_scene(device)
    for collider in model.mesh_colliders:
        collider.cache_margin = 2.0 * R
    sim = ws.Simulator(model, fps=60, substeps=16, guard=None)
    for _ in range(10):
        sim.step_frame()
    path = sim.save_checkpoint(tmp_path / "run.npz")
    for _ in range(10):
        sim.step_frame()
    expected = particles(sim)
    for resumed in (sim, ws.Simulator(model, fps=60, substeps=16, guard=None)):
        resumed.load_checkpoint(path)
        for _ in range(10):
            resumed.step_frame()
        x, v = particles(resumed)
        np.testing.assert_array_equal(x, expected[0])
        np.testing.assert_array_equal(v, expected[1])


def test_a_deforming_mesh_resumes_bit_for_bit(device, tmp_path):
    """A checkpoint keeps a deforming mesh's points as the host last set them (with their surface velocity, swept
    box and reach): a fresh simulator of the same scene, its sheet still as built, loads it and goes on waving
    the sheet (the velocity of each new set of points derived from the last, as the caller does) bit for bit
    as the uninterrupted run; without the sheet's entries (a checkpoint of an older version) it does not."""
    model, sheet, vertices = _cache_scene(device)
    x, y = vertices[:, 0], vertices[:, 1]

    def wave(k):  # the sheet at frame k, lifted on one side: its box grows as it waves
        return vertices + np.c_[np.zeros((len(x), 2)), 0.05 * np.sin(4.0 * x + 0.3 * k) * np.cos(3.0 * y) + 0.01 * k]

    def run(sim, sheet, frames):
        for k in frames:
            sheet.set_points(wave(k), dt=1.0 / 60.0)
            sim.step_frame()

    sim = ws.Simulator(model, fps=60, substeps=16, guard=None)
    run(sim, sheet, range(1, 11))
    path = sim.save_checkpoint(tmp_path / "run.npz")
    run(sim, sheet, range(11, 21))
    expected = particles(sim)

    fresh, fresh_sheet, _ = _cache_scene(device)
    resumed = ws.Simulator(fresh, fps=60, substeps=16, guard=None)
    resumed.load_checkpoint(path)
    np.testing.assert_array_equal(fresh_sheet.points(), wave(10))
    run(resumed, fresh_sheet, range(11, 21))
    np.testing.assert_array_equal(particles(resumed)[0], expected[0])
    np.testing.assert_array_equal(particles(resumed)[1], expected[1])

    saved = Checkpoint.load(path)
    older = Checkpoint(saved.header, {k: v for k, v in saved.arrays.items() if not k.startswith("colliders/")})
    stale, stale_sheet, _ = _cache_scene(device)
    without = ws.Simulator(stale, fps=60, substeps=16, guard=None)
    older.restore(without)
    run(without, stale_sheet, range(11, 21))
    assert not np.array_equal(particles(without)[1], expected[1])


def test_pseudo_normals_on_the_device_equal_the_float64_reference(device):
    """The device's pseudo-normals of a box (corners (±1, ±1, ±1)/√3, edges the sum of two face normals) and of
    a lumpy sphere whose points are then set (deforming) equal the host's float64 ones to float32 rounding."""
    from warpspring.core.mesh_colliders import pseudo_normals

    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    reference = pseudo_normals(box.vertices, box.faces)
    np.testing.assert_allclose(reference[:, 4:], np.sign(box.vertices[box.faces]) / math.sqrt(3.0), atol=1e-7)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 5.0]], radius=R)
    builder.add_collider_mesh(box, name="box")
    builder.add_collider_mesh(ball, deforming=True, center=(3.0, 0.0, 0.0), name="ball")
    model = builder.finalize(device, contact_stage=True)
    normals = model.shape_arrays.cache.normals.numpy().reshape(-1, 7, 3)
    np.testing.assert_allclose(normals[:len(box.faces)], reference, atol=1e-6)
    lumpy = ball.vertices * np.random.default_rng(5).uniform(0.8, 1.2, (len(ball.vertices), 1))
    model.mesh_collider("ball").set_points(lumpy)
    normals = model.shape_arrays.cache.normals.numpy().reshape(-1, 7, 3)
    np.testing.assert_allclose(normals[len(box.faces):], pseudo_normals(lumpy.astype(np.float32), ball.faces),
                               atol=1e-6)
