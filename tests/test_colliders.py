"""Box and capsule colliders, colliders moved by keyframe tracks, restitution, and the contact stage.

The response (``kernels/response.py``) projects a particle of radius r whose centre is closer than r to a
surface back onto it, removes (or, above two steps of gravity, reverses by e) the normal velocity relative
to the surface, and takes μ·(1 + e)|Δv_n| off the relative tangential velocity. Relative to a surface that
moves rigidly from frame X₀ to X₁ in a step h, the surface velocity at x is (x - X₀X₁⁻¹x)/h, the exact
displacement of the surface point over the step: a particle that sticks moves with it to rounding.

Tolerances: float32 has unit roundoff u = 6e-8. A position near 1 m is rounded once per step (≤ 1.2e-7 m);
over the ~2e3 steps of a test that is at most ~2e-4 m in the worst (systematic) case and ~5e-6 m as a
random walk; the surface tests below stay within a few roundings of the surface because every step's
projection puts the particle back at distance r. float64 is 1e9 times tighter.
"""

import math
import warnings

import numpy as np
import pytest

import warpspring as ws
from warpspring.core.transforms import quat_to_matrix
from warpspring.errors import ConfigError, ContactOverflowWarning
from warpspring.kernels.shapes import SHAPE_BOX

G = 9.81
R = 0.05  # particle radius [m]
ON_SURFACE = {"float32": 2.0e-6, "float64": 1.0e-12}  # |distance - r| after the last projection [m]
DRIFT = {"float32": 5.0e-6, "float64": 1.0e-9}  # accumulated rounding of a position over ~2e3 steps [m]


def run(builder, device, *, seconds=1.0, fps=60, substeps=16, precision="float32", **finalize):
    model = builder.finalize(device, precision=precision, **finalize)
    sim = ws.Simulator(model, fps=fps, substeps=substeps)
    for _ in range(round(seconds * fps)):
        sim.step_frame()
    return model, sim


def particle(sim, i=0):
    return sim.state.particle_q.numpy()[i].astype(np.float64), sim.state.particle_qd.numpy()[i].astype(np.float64)


def box_distance(p_world, position, quaternion, half):
    """Signed distance [m] of world points from a box (host float64 reference), shape [n]."""
    local = quat_to_matrix(quaternion).T @ (np.atleast_2d(p_world) - position).T
    q = np.abs(local.T) - np.asarray(half)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


# -- resting contact -------------------------------------------------------------------------------------


def test_particle_rests_on_a_box_top(device, precision):
    """A particle put on a box's top face stays there for 1 s: each step's gravity h g sinks it by h² g,
    the projection lifts it back and removes the normal speed, so it is at distance r with zero velocity."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.1, -0.2, 0.5 + R]], radius=R)
    builder.add_collider_box(center=(0.0, 0.0, 0.25), half_extents=(0.5, 0.5, 0.25), friction=0.5)
    model, sim = run(builder, device, precision=precision)
    x, v = particle(sim)
    assert model.shape_types == (SHAPE_BOX,) and not model.contact_stage
    assert abs(x[2] - (0.5 + R)) <= ON_SURFACE[precision]
    np.testing.assert_allclose(x[:2], [0.1, -0.2], atol=ON_SURFACE[precision])
    np.testing.assert_allclose(v, 0.0, atol=1e-12)


def test_particle_rests_on_a_lying_capsule(device, precision):
    """On top of a capsule lying along x (radius 0.2 m, turned 90° about y), a particle over the
    cylindrical part rests at distance radius + r from the axis, without sliding along it."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.1, 0.0, 0.2 + R]], radius=R)
    builder.add_collider_capsule(center=(0.0, 0.0, 0.0), radius=0.2, half_height=0.5,
                                 orientation=ws.quat_from_axis_angle((0.0, 1.0, 0.0), math.pi / 2), friction=0.8)
    _, sim = run(builder, device, precision=precision)
    x, v = particle(sim)
    assert abs(math.hypot(x[1], x[2]) - (0.2 + R)) <= ON_SURFACE[precision]
    assert abs(x[0] - 0.1) <= DRIFT[precision]
    assert np.linalg.norm(v) <= 1e-4 if precision == "float32" else 1e-12


def test_capsule_end_cap_is_a_hemisphere(device):
    """A particle dropped onto the cap of an upright capsule lands at radius + r from the cap's centre
    (z = half height): the capsule is the segment's r-neighbourhood, not a cylinder with flat ends."""
    builder = ws.ModelBuilder()
    offset = np.array([0.05, 0.0, 0.0])
    builder.add_particles([offset + [0.0, 0.0, 0.6]], radius=R)
    builder.add_collider_capsule(center=(0.0, 0.0, 0.0), radius=0.2, half_height=0.3, friction=1.0)
    _, sim = run(builder, device, seconds=0.5)
    x, _ = particle(sim)
    assert np.linalg.norm(x - [0.0, 0.0, 0.3]) == pytest.approx(0.2 + R, abs=ON_SURFACE["float32"])


# -- Coulomb friction on a tilted box face -------------------------------------------------------------------

THETA = math.radians(30.0)


def tilted_box(device, mu, seconds, precision="float32"):
    """A particle released at rest on the top face of a 6 m box tilted 30° about x."""
    normal = np.array([0.0, -math.sin(THETA), math.cos(THETA)])
    builder = ws.ModelBuilder()
    builder.add_particles([(0.25 + R) * normal], radius=R)
    builder.add_collider_box(center=(0.0, 0.0, 0.0), half_extents=(3.0, 3.0, 0.25),
                             orientation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), THETA), friction=mu)
    _, sim = run(builder, device, seconds=seconds, precision=precision)
    x, v = particle(sim)
    return x - (0.25 + R) * normal, v, normal


def test_particle_slides_down_a_tilted_box_at_coulomb_acceleration(device, precision):
    """μ = 0.3 < tan 30°: after 1 s the speed down the face is g (sinθ - μ cosθ) t = 2.356 m/s. The issue
    asks for 2 %; the discrete speed is exact (constant acceleration, the friction impulse μ h g cosθ per
    step is Coulomb's law over the step), so rounding is the tolerance (test_contacts.py derives it)."""
    mu = 0.3
    displacement, v, normal = tilted_box(device, mu, 1.0, precision)
    a = G * (math.sin(THETA) - mu * math.cos(THETA))
    downhill = -np.array([0.0, math.cos(THETA), math.sin(THETA)])
    assert v @ downhill == pytest.approx(a, rel=0.02)
    assert abs(v @ downhill - a) <= (1e-4 if precision == "float32" else 1e-10)
    assert abs(displacement @ normal) <= ON_SURFACE[precision]
    assert abs(v @ normal) <= (1e-4 if precision == "float32" else 1e-10)


def test_particle_does_not_creep_when_friction_exceeds_tan_theta(device):
    """μ = 0.7 > tan 30°: static friction holds; the issue allows a creep of 1 mm in 2 s. What remains is
    rounding: the face's normal comes through the box's rotated frame, and each of the N = 1920 steps may
    round the 0.3 m position the same way, N u |x| = 3.5e-5 m at most (measured: 2.6e-5 m on the CPU; a
    creep of one step's h g sinθ per step would be 10 mm)."""
    displacement, v, _ = tilted_box(device, 0.7, 2.0)
    assert np.linalg.norm(displacement) < 1.0e-3
    steps, unit_roundoff = 2.0 * 60 * 16, 2.0**-24
    assert np.linalg.norm(displacement) <= steps * unit_roundoff * 0.3 * 2
    assert np.linalg.norm(v) <= 1e-4


# -- moving colliders -----------------------------------------------------------------------------------------

# Up 0.2 m and along x 0.4 m between t = 0.5 s and 1.5 s, at rest before and after (PCHIP keeps the flat
# ends flat): the largest acceleration, 6 Δ/T² = 2.4 m/s² along x, is below μ g = 7.8 m/s², so static
# friction can carry the particle without slipping.
PLATFORM = ws.Track([0.0, 0.5, 1.5, 2.0], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.4, 0.0, 0.2], [0.4, 0.0, 0.2]],
                    interpolation="smooth")


def test_particle_on_a_moving_platform_keeps_its_place(device, precision):
    """A particle resting on a box moved by a translation track stays where it was on it, to rounding:
    the response's surface velocity moves it by exactly the surface's displacement every step."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.1, 0.0, 0.1 + R]], radius=R)
    builder.add_collider_box(center=(0.0, 0.0, 0.0), half_extents=(1.0, 1.0, 0.1), friction=0.8,
                             translation=PLATFORM, name="platform")
    model = builder.finalize(device, precision=precision)
    assert model.shape_moving and model.contact_stage
    sim = ws.Simulator(model, fps=60, substeps=16)
    drift = 0.0
    for _ in range(120):
        sim.step_frame()
        x, _ = particle(sim)
        offset = PLATFORM.sample(sim.time)[0][0]
        drift = max(drift, np.abs(x - offset - [0.1, 0.0, 0.1 + R]).max())
    assert drift <= DRIFT[precision]
    _, v = particle(sim)
    np.testing.assert_allclose(v, 0.0, atol=1e-4)  # the platform is at rest again
    assert sim.contact_overflow().tolist() == [0]


def test_fused_path_moves_colliders_too(device):
    """contact_stage=False with a moving collider: the fused update reads the frames written before it,
    and gives the contact stage's result (the particle touches one collider: the two paths do the same
    arithmetic)."""
    finals = []
    for stage in (True, False):
        builder = ws.ModelBuilder()
        builder.add_particles([[0.1, 0.0, 0.1 + R]], radius=R)
        builder.add_collider_box(center=(0.0, 0.0, 0.0), half_extents=(1.0, 1.0, 0.1), friction=0.8,
                                 translation=PLATFORM)
        _, sim = run(builder, device, seconds=1.0, contact_stage=stage)
        finals.append(particle(sim))
    np.testing.assert_array_equal(finals[0][0], finals[1][0])
    np.testing.assert_array_equal(finals[0][1], finals[1][1])


def test_bounce_reaches_restitution_squared_times_the_drop_height(device):
    """Dropped from 1 m onto ground of restitution e = 0.5, the particle rises to e² · 1 m = 0.25 m within
    2 %. Sampled every step (h = 1/1920 s); the contact is resolved at the end of the step that reaches
    the ground, which misplaces the impact by at most v h (2.3 mm at 4.4 m/s), i.e. ≤ 1 % of the apex."""
    e, height = 0.5, 1.0
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, height + R]], radius=R)
    builder.add_ground_plane(restitution=e, friction=0.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=1920, substeps=1, guard=None)
    z = []
    for _ in range(round(1.2 * 1920)):  # impact at 0.45 s, apex 0.23 s later
        sim.step_frame()
        z.append(float(sim.state.particle_q.numpy()[0, 2]))
    z = np.array(z) - R
    impact = int(np.argmin(z))
    assert z[impact] >= -ON_SURFACE["float32"]  # never below the ground
    apex = z[impact:].max()
    assert apex == pytest.approx(e * e * height, rel=0.02)
    v_impact, h = math.sqrt(2 * G * height), sim.dt
    assert abs(apex - e * e * height) <= (1 + e) * v_impact * h + G * h * h


def test_resting_particle_does_not_hop_on_a_restitutive_surface(device):
    """Restitution applies only to approaches faster than two steps of gravity: a particle resting on a
    ground of e = 0.9 stays at rest (its per-step approach h g is never bounced)."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, R]], radius=R)
    builder.add_ground_plane(restitution=0.9)
    _, sim = run(builder, device)
    x, v = particle(sim)
    assert abs(x[2] - R) <= ON_SURFACE["float32"]
    np.testing.assert_allclose(v, 0.0, atol=1e-12)


def test_cloth_draped_over_a_rotating_box(device):
    """A cloth falls on a box that then turns 90° about the vertical (a rotation track, at rest before 0.5 s,
    smooth start). At every frame no particle is inside the box (distance ≥ r up to rounding), the cloth
    drapes below the top (its overhang hangs), and the part lying on the top turns with the box: friction
    μ = 1 against the moving surface holds it (it turns by the box's 90° within 2°)."""
    spin = ws.Track.rotation([0.0, 0.5, 2.5], axis=(0.0, 0.0, 1.0), degrees=[0.0, 0.0, 90.0],
                             interpolation="smooth")
    half = np.array([0.3, 0.3, 0.2])
    radius = 0.01
    builder = ws.ModelBuilder()
    builder.add_collider_box(center=(0.0, 0.0, 0.2), half_extents=half, friction=1.0, rotation=spin, name="turntable")
    builder.add_ground_plane()
    spring = ws.SpringMaterial(ke=500.0, kd=0.5)
    builder.add_cloth_grid(nx=20, ny=20, spacing=0.04, origin=(-0.38, -0.38, 0.45), particle_mass=0.01,
                           structural=spring, shear=spring, bend=spring, radius=radius)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=32)
    box = model.shapes[0]
    start = None
    for frame in range(150):
        sim.step_frame()
        x = sim.state.particle_q.numpy().astype(np.float64)
        position, quaternion = box.frame(sim.time)
        assert box_distance(x, position, quaternion, half).min() >= radius - 1e-5, f"frame {frame + 1}"
        if frame + 1 == 30:  # t = 0.5 s: settled on the top, the box about to turn
            start = x.copy()
    on_top = np.abs(start[:, 2] - (0.4 + radius)) < 1e-4
    assert on_top.sum() > 100 and x[:, 2].min() < 0.4 - 0.03  # lying on the top, its edges hanging down
    turned = np.angle(np.exp(1j * (np.arctan2(x[on_top, 1], x[on_top, 0])
                                   - np.arctan2(start[on_top, 1], start[on_top, 0]))))
    assert np.degrees(np.median(turned)) == pytest.approx(90.0, abs=2.0)


# -- the contact stage ----------------------------------------------------------------------------------------


def cloth_over_sphere(device, **finalize):
    builder = ws.ModelBuilder()
    builder.add_collider_sphere(center=(0.0, 0.0, 0.3), radius=0.2, friction=0.4)
    builder.add_ground_plane(friction=0.6)
    spring = ws.SpringMaterial(ke=500.0, kd=0.5)
    builder.add_cloth_grid(nx=16, ny=16, spacing=0.04, origin=(-0.3, -0.3, 0.6), particle_mass=0.01,
                           structural=spring, shear=spring, bend=spring, radius=0.01)
    return builder.finalize(device, **finalize)


def test_contact_stage_gives_the_fused_result(device):
    """On static colliders the stage (collide into the buffer, then respond to the slots) resolves the same
    contacts in the same order as the fused update. From a cloth lying over a sphere and the ground (40
    frames in), one step of each gives the same bits on the CPU; on CUDA the fused update is compiled with
    fast math (approximate sqrt and division, ≤ 2 ulp each) and the stage's response is not, so they agree
    to a few float32 roundings of |x| ≤ 1 m (2e-6 m); over many steps the cloth's chaos would amplify that."""
    fused, stage = cloth_over_sphere(device), cloth_over_sphere(device, contact_stage=True)
    assert (fused.contact_stage, stage.contact_stage) == (False, True)
    sim = ws.Simulator(fused, fps=60, substeps=16)
    for _ in range(40):
        sim.step_frame()
    results = []
    for model in (fused, stage):
        state_in, state_out = model.state(), model.state()
        state_in.assign(sim.state)
        integrator = ws.SymplecticEuler(model)
        integrator.step(state_in, state_out, None, sim.dt)
        results.append((state_out.particle_q.numpy(), state_out.particle_qd.numpy(), integrator))
    contacts = results[1][2].finish_step.contacts
    assert contacts.slots == 2 and contacts.capacity == 2 * stage.state_size
    touching = contacts.counts()[0]
    assert (touching >= 1).sum() > 50 and contacts.overflow().tolist() == [0]
    if device == "cpu":
        np.testing.assert_array_equal(results[0][0], results[1][0])
        np.testing.assert_array_equal(results[0][1], results[1][1])
    else:
        np.testing.assert_allclose(results[0][0], results[1][0], rtol=0, atol=2e-6)
        np.testing.assert_allclose(results[0][1], results[1][1], rtol=0, atol=1e-5)  # 2 ulp of ≤ 5 m/s, × 8


def test_collide_records_the_touched_colliders_in_order(device):
    """collide() on a state: particles inside two overlapping boxes get both, in collider order; one in
    neither gets none; kinematic particles are skipped."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 0.0], [0.9, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.1, 0.0]], radius=0.01,
                          pinned=[False, False, False, True])
    builder.add_collider_box(center=(0.5, 0.0, 0.0), half_extents=(0.5, 0.5, 0.5), name="right")
    builder.add_collider_box(center=(-0.5, 0.0, 0.0), half_extents=(0.6, 0.5, 0.5), name="left")
    model = builder.finalize(device, contact_stage=True)
    contacts = ws.Contacts(model)
    ws.collide(model, model.state(), contacts)
    assert contacts.shapes() == [[0, 1], [0], [], []]


def test_overflow_is_counted_warned_and_summarised(device):
    """Three coincident boxes and one contact slot: a resting particle touches all three every step, keeps
    the first, and the two dropped contacts per step are counted on the device, reported by the guard as a
    ContactOverflowWarning naming the frame and the remedy, and kept out of the warm-up."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 0.2 + R]], radius=R)
    for k in range(3):
        builder.add_collider_box(center=(0.0, 0.0, 0.1), half_extents=(0.5, 0.5, 0.1), name=f"box{k}")
    model = builder.finalize(device, contact_stage=True, contact_slots=1)
    sim = ws.Simulator(model, fps=60, substeps=16)
    with pytest.warns(ContactOverflowWarning, match=r"frame 1: .*contact_slots=2"):
        sim.step_frame()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(2):
            sim.step_frame()
    assert [str(w.message)[:8] for w in caught] == ["frame 2:", "frame 3:"]
    assert sim.contact_overflow().tolist() == [2 * 16 * 3]
    x, _ = particle(sim)
    assert abs(x[2] - (0.2 + R)) <= ON_SURFACE["float32"]  # the kept contact still holds it
    sim.reset()
    assert sim.contact_overflow().tolist() == [0]

    roomy = builder.finalize(device, contact_stage=True, contact_slots=3)
    sim = ws.Simulator(roomy, fps=60, substeps=16)
    with warnings.catch_warnings():
        warnings.simplefilter("error", ContactOverflowWarning)
        sim.step_frame()
    assert sim.contact_overflow().tolist() == [0]


def test_moving_colliders_are_per_world(device):
    """Each world samples a collider's tracks at its own time: a world held for a frame (its time stands
    still) sees the platform where it was, the other where it moved on."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.1, 0.0, 0.1 + R]], radius=R)
    builder.add_collider_box(center=(0.0, 0.0, 0.0), half_extents=(1.0, 1.0, 0.1), friction=0.8,
                             translation=PLATFORM)
    model = builder.finalize(device, worlds=2)
    model.hold_worlds()
    sim = ws.Simulator(model, fps=60, substeps=16)
    for _ in range(30):
        sim.step_frame()
    model.set_world_enabled([1], False)
    for _ in range(60):
        sim.step_frame()
    times = sim.state.time.numpy()
    assert times[0] == pytest.approx(1.5) and times[1] == pytest.approx(0.5)
    x = sim.state.particle_q.numpy().astype(np.float64)
    for w in range(2):
        expected = PLATFORM.sample(times[w])[0][0] + [0.1, 0.0, 0.1 + R]
        np.testing.assert_allclose(x[w], expected, atol=DRIFT["float32"])


def test_collider_arguments_are_checked():
    builder = ws.ModelBuilder()
    with pytest.raises(ConfigError, match="half_extents must all be > 0"):
        builder.add_collider_box(center=(0, 0, 0), half_extents=(1.0, 0.0, 1.0))
    with pytest.raises(ConfigError, match="restitution must be in"):
        builder.add_collider_sphere(center=(0, 0, 0), radius=1.0, restitution=1.5)
    with pytest.raises(ConfigError, match="capsule radius"):
        builder.add_collider_capsule(center=(0, 0, 0), radius=-1.0, half_height=0.5)
    builder.add_particles([[0.0, 0.0, 1.0]])
    builder.add_ground_plane()
    with pytest.raises(ConfigError, match="contact_slots must be at most 64"):
        builder.finalize("cpu", contact_slots=65)


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4", "velocity_verlet", "implicit_euler"])
def test_a_particle_sliding_off_a_boxs_edge_falls_from_the_edge(device, integrator):
    """A particle (r = 1 cm) sliding at 1 m/s on a frictionless table (a box) leaves it where its centre passes the
    edge (v²/r = 100 m/s² ≫ g: it does not roll round the edge) and falls freely: z(t) = z₀ - g (t - tₑ)² / 2. The
    swept test of a box grown by the radius once had square edges, which held the particle up until its centre was a
    radius past the edge under every integrator but symplectic Euler (29 mm high after 0.5 s, at any step). The
    tolerance is twice g h (t - tₑ), first order in the step."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.4, 0.0, 0.81]], velocities=[[1.0, 0.0, 0.0]], mass=0.1, radius=0.01)
    builder.add_collider_box(center=(0.0, 0.0, 0.4), half_extents=(0.6, 0.45, 0.4), friction=0.0, name="table")
    model = builder.finalize(device, precision="float64")
    fps, substeps, frames = 60.0, 40, 30
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=fps, substeps=substeps, guard=None)
    for _ in range(frames):
        sim.step_frame()
    x, _, z = sim.state.particle_q.numpy()[0]
    t, g, h = frames / fps, 9.81, 1.0 / (fps * substeps)
    falling = t - (0.6 - 0.4) / 1.0
    assert abs(x - (0.4 + t)) < 1e-9
    assert abs(z - (0.81 - 0.5 * g * falling**2)) < 2.0 * g * h * falling
