"""Particle emitters (kernels/emitters.py): the live count follows rate × life span, a ballistic particle follows
the closed form (at first order in dt), a pool too small is reported, births land on the emitter's shape, the
USD points carry stable ids, a checkpointed run continues bit for bit, and the scene's [[emitter]] builds one."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from pxr import Usd, UsdGeom

import warpspring as ws
from warpspring.core.emitters import PoolTooSmallWarning
from warpspring.io.usd import UsdWriter

G = np.array([0.0, 0.0, -9.81])


def stream(device, *, rate=120.0, life=0.5, capacity=None, substeps=8, **options):
    builder = ws.ModelBuilder(gravity=tuple(G))
    emitter = builder.add_emitter(center=(0.0, 0.0, 1.0), rate=rate, life=life, velocity=(1.0, 0.0, 3.0),
                                  capacity=capacity, **options)
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=substeps)
    return model, emitter, sim


def test_the_live_count_follows_rate_times_life(device):
    """Before a life span has passed, r·t particles live (to one step's births); after, r·L, whatever the time."""
    rate, life = 120.0, 0.5
    model, emitter, sim = stream(device, rate=rate, life=life)
    per_step = rate * sim.dt
    for frame in range(1, 91):
        sim.step_frame()
        t = frame / 60.0
        expected = rate * min(t, life)
        assert abs(emitter.alive().sum() - expected) <= per_step + 1, (frame, emitter.alive().sum(), expected)
    assert emitter.recycled().sum() == 0 and emitter.capacity >= rate * life


def ballistic(device, substeps: int):
    """A burst of 8 particles at t = 0 from a point (spread 0.5 m/s, no drag), simulated for one frame in
    float64: the model, the emitter and the simulator."""
    builder = ws.ModelBuilder(gravity=tuple(G))
    emitter = builder.add_emitter(center=(0.0, 0.0, 2.0), bursts=[(0.0, 8)], life=10.0, velocity=(1.0, 0.5, 2.0),
                                  spread=0.5, seed=4)
    model = builder.finalize(device, precision="float64")
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=substeps)
    sim.step_frame()  # born at the end of the first step, t = dt, with their launch velocity
    return model, emitter, sim


def test_ballistic_particles_follow_the_closed_form_at_first_order(device):
    """Born at t_b = dt at the emitter with v₀: x(t) = x₀ + v₀ (t − t_b) + ½ g (t − t_b)²; symplectic Euler's
    error is ½ |g| h (t − t_b) exactly (it adds g·h before each move), so it falls 4× per 4× smaller step."""
    errors = []
    for substeps in (4, 16, 64):
        model, emitter, sim = ballistic(device, substeps)
        dt = sim.dt
        # The launch velocities: at the end of the first frame each has fallen for (1/60 − dt) s.
        first_frame_v = sim.state.particle_qd.numpy()[emitter.first:emitter.first + 8].astype(np.float64)
        age = 1.0 / 60.0 - dt
        v0 = first_frame_v - G * age
        for _ in range(29):
            sim.step_frame()
        t = 30 / 60.0 - dt
        x = sim.state.particle_q.numpy()[emitter.first:emitter.first + 8].astype(np.float64)
        exact = np.array([0.0, 0.0, 2.0]) + v0 * t + 0.5 * G * t**2
        error = np.abs(x - exact).max()
        assert error == pytest.approx(0.5 * 9.81 * dt * t, rel=1e-6)
        errors.append(error)
        assert np.ptp(v0[:, 0]) > 0.1  # the spread gave them different launches
    for coarse, fine in zip(errors, errors[1:]):
        assert coarse / fine == pytest.approx(4.0, rel=0.02)


def test_a_pool_too_small_is_reported_and_recycles_the_oldest(tmp_path):
    """capacity < rate × life: a PoolTooSmallWarning when built, at most capacity particles live, and the run's
    summary counts the particles recycled before their life span ended."""
    from warpspring.app.cli import main

    with pytest.warns(PoolTooSmallWarning, match="smaller than the 60"):
        model, emitter, sim = stream("cpu", rate=120.0, life=0.5, capacity=40)
    for _ in range(60):
        sim.step_frame()
    assert emitter.alive().sum() == 40
    # 120 births in 1 s; each slot past the 40th birth recycles a particle that still had life left
    assert emitter.recycled().sum() == pytest.approx(120 - 40, abs=2)
    scene = tmp_path / "small.toml"
    scene.write_text("""\
version = 2
[simulation]
frames = 60
substeps = 4
[[emitter]]
rate = 120.0
life = 0.5
capacity = 40
""")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoolTooSmallWarning)
        assert main(["run", str(scene), "-o", str(tmp_path / "small.usdc"), "--device", "cpu", "--quiet"]) == 0


def test_births_land_on_the_shape(device):
    """A box emitter's births lie in the box and fill it; a mesh emitter's lie on its triangles (a unit square
    in z = 0.5 split in two), spread over its area."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    box = builder.add_emitter(shape="box", center=(1.0, 2.0, 3.0), half_extents=(0.5, 0.2, 0.1), bursts=[(0.0, 400)],
                              life=1.0, name="box")
    square = (np.array([[0, 0, 0.5], [1, 0, 0.5], [1, 1, 0.5], [0, 1, 0.5]]), np.array([[0, 1, 2], [0, 2, 3]]))
    mesh = builder.add_emitter(shape="mesh", mesh=square, bursts=[(0.0, 400)], life=1.0, name="sheet")
    model = builder.finalize(device, precision="float64")
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=600, substeps=1)
    sim.step_frame()
    q = sim.state.particle_q.numpy()
    inside = q[box.first:box.first + 400] - [1.0, 2.0, 3.0]
    assert (np.abs(inside) <= [0.5, 0.2, 0.1]).all()
    assert (np.ptp(inside, axis=0) > 0.9 * np.array([1.0, 0.4, 0.2])).all()
    on = q[mesh.first:mesh.first + 400]
    np.testing.assert_allclose(on[:, 2], 0.5, atol=1e-12)
    assert ((on[:, :2] >= 0.0) & (on[:, :2] <= 1.0)).all()
    assert abs(np.mean(on[:, 0] > on[:, 1]) - 0.5) < 0.1  # both triangles, by area


def test_usd_points_carry_the_live_particles_with_stable_ids(tmp_path):
    """Per frame the emitter's Points hold exactly the live particles; a particle keeps its id from frame to
    frame and moves by its velocity; widths are twice the radius; the validators pass."""
    from pxr import UsdValidation

    model, emitter, sim = stream("cpu", rate=60.0, life=0.3, radius=0.004)
    path = tmp_path / "sparks.usdc"
    with UsdWriter(path, model, fps=60) as usd:
        usd.write_frame(sim.state)
        counts = [0]
        for _ in range(40):
            sim.step_frame()
            usd.write_frame(sim.state)
            counts.append(int(emitter.alive().sum()))
    stage = Usd.Stage.Open(str(path))
    points = UsdGeom.Points(stage.GetPrimAtPath("/World/emitter"))
    for k in (10, 30):
        ids0, ids1 = np.array(points.GetIdsAttr().Get(k)), np.array(points.GetIdsAttr().Get(k + 1))
        assert len(ids0) == counts[k] and len(np.array(points.GetPointsAttr().Get(k))) == counts[k]
        x0, x1 = np.array(points.GetPointsAttr().Get(k)), np.array(points.GetPointsAttr().Get(k + 1))
        v0 = np.array(points.GetVelocitiesAttr().Get(k))
        common, i0, i1 = np.intersect1d(ids0, ids1, return_indices=True)
        assert len(common) > 5
        np.testing.assert_allclose(x1[i1], x0[i0] + v0[i0] / 60.0 + 0.5 * G / 3600.0, atol=2e-3)
        np.testing.assert_allclose(np.array(points.GetWidthsAttr().Get(k)), 0.008, rtol=1e-6)
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    assert [e.GetMessage() for e in UsdValidation.ValidationContext(validators).Validate(stage)] == []


def test_a_checkpointed_emitter_run_continues_bit_for_bit(tmp_path, device):
    """Save after 20 frames, run 20 more; a new simulator loading the checkpoint runs the same 20: the same
    positions, velocities, serials and counts, bit for bit."""
    model, emitter, sim = stream(device, rate=200.0, life=0.25, spread=0.3)
    for _ in range(20):
        sim.step_frame()
    saved = sim.save_checkpoint(tmp_path / "run.npz")
    for _ in range(20):
        sim.step_frame()
    model2, emitter2, sim2 = stream(device, rate=200.0, life=0.25, spread=0.3)
    sim2.load_checkpoint(saved)
    for _ in range(20):
        sim2.step_frame()
    np.testing.assert_array_equal(sim2.state.particle_q.numpy(), sim.state.particle_q.numpy())
    np.testing.assert_array_equal(sim2.state.particle_qd.numpy(), sim.state.particle_qd.numpy())
    np.testing.assert_array_equal(emitter2.serials(), emitter.serials())


def test_the_scene_emitter_table_builds_an_emitter(tmp_path):
    from warpspring.io.scene import load_scene

    path = tmp_path / "sparks.toml"
    path.write_text("""\
version = 2
[[emitter]]
name = "sparks"
shape = "box"
center = [0, 0, 1]
half_extents = [0.1, 0.1, 0.1]
rate = 50.0
bursts = [[0.5, 20]]
life = 1.0
velocity = [1, 0, 0]
spread = 0.2
seed = 9
""")
    model = load_scene(path).finalize("cpu")
    (emitter,) = model.emitters
    assert (emitter.name, emitter.shape, emitter.rate, emitter.life, emitter.seed) == ("sparks", "box", 50.0, 1.0, 9)
    assert emitter.bursts.tolist() == [[0.5, 20.0]] and emitter.capacity == int(np.ceil(1.05 * 70))
    path.write_text(path.read_text().replace("life = 1.0\n", ""))
    with pytest.raises(ws.ConfigError, match=r"sparks.toml: \[emitter\] needs life"):
        load_scene(path)


def test_an_emitter_changes_between_frames_without_a_recapture(device):
    """set(rate=, center=, velocity=) takes effect at the next frame: births follow the new rate from the new
    place, and nothing is re-captured."""
    model, emitter, sim = stream(device, rate=60.0, life=10.0, capacity=700)
    for _ in range(30):
        sim.step_frame()
    captures, before = sim.stepper.captures, int(emitter.alive().sum())
    emitter.set(rate=240.0, center=(5.0, 0.0, 1.0), velocity=(0.0, 0.0, 0.0))
    sim.step_frame()
    serial = emitter.serials()
    newest = np.argsort(serial)[-int(240.0 / 60.0):]
    np.testing.assert_allclose(sim.state.particle_q.numpy()[emitter.first + newest, 0], 5.0, atol=0.01)
    assert int(emitter.alive().sum()) - before == pytest.approx(240.0 / 60.0, abs=1)
    assert sim.stepper.captures == captures


def test_a_scene_emitter_reads_its_mesh_file(tmp_path):
    """[[emitter]] mesh = "file": the shape is the mesh (relative to the scene's folder); a missing file is one
    line naming it."""
    from warpspring.io.scene import load_scene

    (tmp_path / "plate.obj").write_text("v 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\nf 1 2 3\nf 1 3 4\n")
    path = tmp_path / "spray.toml"
    path.write_text('version = 2\n[[emitter]]\nmesh = "plate.obj"\nrate = 10.0\nlife = 1.0\n')
    (emitter,) = load_scene(path).finalize("cpu").emitters
    assert emitter.shape == "mesh" and len(emitter.mesh_faces) == 2
    np.testing.assert_allclose(emitter.mesh_points[:, 2], 1.0)
    path.write_text(path.read_text().replace("plate.obj", "missing.obj"))
    with pytest.raises(ws.ConfigError, match=r"emitter mesh file not found: .*missing.obj"):
        load_scene(path).finalize("cpu")
