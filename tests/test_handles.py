"""PD-controlled handles (kernels/handles.py): a particle on a handle answers a step of its target as the closed-
form second-order system does (overshoot, settling time, the whole trajectory at first order in dt); a capped
handle pulls with constant force; the force at any state and time is Kp e + Kd ė toward the tracks' rigid
target motion; the advisor sees Kp; the scene's [[cloth.handle]] builds them."""

from __future__ import annotations

import numpy as np
import pytest

import warpspring as ws
from warpspring.core.forces import eval_forces

MASS, KP, KD, STEP = 0.5, 200.0, 4.0, 0.1  # [kg], [N/m], [N·s/m], [m]: ζ = 0.2, ω_n = 20 rad/s


def step_response(t: np.ndarray) -> np.ndarray:
    """x(t) [m] of m ẍ = Kp (d − x) − Kd ẋ from rest at 0, for the step d at t = 0 (underdamped)."""
    wn, zeta = np.sqrt(KP / MASS), KD / (2.0 * np.sqrt(KP * MASS))
    wd = wn * np.sqrt(1.0 - zeta**2)
    return STEP * (1.0 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / np.sqrt(1.0 - zeta**2) * np.sin(wd * t)))


def simulate_step(device, substeps: int, fps: int = 240, seconds: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """One free particle (no gravity, no cap) on a handle whose target steps by d along x at t = 0+ (a step
    track): its x [m] at every frame, and the frame times [s]."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles([[0.0, 0.0, 0.0]], mass=MASS)
    builder.add_handle([0], kp=KP, kd=KD,
                       translation=ws.Track([0.0, 1e-9], [[0, 0, 0], [STEP, 0, 0]], interpolation="step"))
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=fps, substeps=substeps)
    x = []
    for _ in range(int(seconds * fps)):
        sim.step_frame()
        x.append(float(sim.state.particle_q.numpy()[0, 0]))
    return np.array(x), np.arange(1, len(x) + 1) / fps


def settling_time(t: np.ndarray, x: np.ndarray, band: float = 0.02) -> float:
    """The first sampled time after which x stays within ``band`` of the step."""
    outside = np.flatnonzero(np.abs(x - STEP) > band * STEP)
    return float(t[outside[-1] + 1]) if len(outside) else float(t[0])


def test_a_step_of_the_target_gives_the_second_order_response(device):
    """Overshoot exp(−ζπ/√(1−ζ²)) = 52.7 % and 2 % settling time as the closed form's (sampled at the same
    times, within one sample); the trajectory's largest error falls 4× per 4× smaller step (first order)."""
    errors = []
    for substeps in (4, 16, 64):
        x, t = simulate_step(device, substeps)
        exact = step_response(t)
        errors.append(np.abs(x - exact).max())
    zeta = KD / (2.0 * np.sqrt(KP * MASS))
    overshoot = x.max() / STEP - 1.0
    assert overshoot == pytest.approx(np.exp(-zeta * np.pi / np.sqrt(1.0 - zeta**2)), abs=2e-3)
    assert overshoot == pytest.approx(exact.max() / STEP - 1.0, abs=10 * errors[-1] / STEP)
    assert settling_time(t, x) == pytest.approx(settling_time(t, exact), abs=1.5 / 240)
    assert errors[-1] < 1e-3 * STEP
    for coarse, fine in zip(errors, errors[1:]):
        assert 3.5 < coarse / fine < 4.5, errors


def test_a_capped_handle_pulls_with_its_largest_force(device):
    """A far target and no damping: the cap holds the force at max_force, so x(t) = ½ (F/m) t² (to the
    integrator's O(dt) error), until the particle comes within F/Kp of its target."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles([[0.0, 0.0, 0.0]], mass=MASS)
    builder.add_handle([0], kp=KP, kd=0.0, max_force=0.5, translation=ws.Track([0.0, 1e-9], [[0, 0, 0], [10, 0, 0]],
                                                                             interpolation="step"))
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=64)
    for _ in range(60):
        sim.step_frame()
    dt = 1.0 / (60 * 64)
    x = float(sim.state.particle_q.numpy()[0, 0])
    assert x == pytest.approx(0.5 * (0.5 / MASS) * 1.0**2, abs=(0.5 / MASS) * 1.0 * dt)


def test_the_force_pulls_toward_the_tracks_rigid_motion(device):
    """At a state of time t, each grabbed particle feels Kp (x* − x) + Kd (v* − v), x* = p + T(t) + R(φ(t))(x₀ − p)
    and v* its velocity, computed here in float64 from the same smooth tracks."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    start = np.array([[0.3, 0.0, 1.0], [0.0, 0.4, 1.0], [-0.2, -0.1, 1.2]])
    builder.add_particles(start, mass=0.1)
    translation = ws.Track([0.0, 1.0, 2.0], [[0, 0, 0], [0.5, 0.2, 0], [0.4, 0.6, 0.3]], interpolation="smooth")
    rotation = ws.Track.rotation([0.0, 2.0], axis=(0, 0, 1), degrees=[0, 120], interpolation="linear")
    pivot = np.array([0.1, 0.1, 1.0])
    builder.add_handle([0, 1, 2], kp=50.0, kd=2.0, translation=translation, rotation=rotation, pivot=pivot)
    model = builder.finalize(device, precision="float64")
    state = model.state()
    t = 0.7
    x = start + np.array([0.05, -0.02, 0.01])
    v = np.array([[0.1, 0.0, 0.0], [0.0, -0.2, 0.1], [0.3, 0.1, 0.0]])
    state.particle_q.assign(x)
    state.particle_qd.assign(v)
    state.time.assign([t])
    eval_forces(model, state, None)
    T, T_rate = (np.asarray(a)[0] for a in translation.sample(t))
    angle, rate = np.radians(120.0) * t / 2.0, np.radians(120.0) / 2.0
    R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    r = (start - pivot) @ R.T
    target = pivot + T + r
    target_velocity = T_rate + np.cross([0, 0, rate], r)
    np.testing.assert_allclose(state.particle_f.numpy(), 50.0 * (target - x) + 2.0 * (target_velocity - v),
                               rtol=1e-9, atol=1e-9)


def test_the_advisor_sees_the_handle_stiffness(device):
    """A particle held only by a handle: ω_max = √(Kp/m), so symplectic Euler's largest stable step is 2/ω."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles([[0.0, 0.0, 0.0]], mass=MASS)
    builder.add_handle([0], kp=KP, kd=0.0)
    model = builder.finalize(device)
    advice = ws.advise(model, "symplectic_euler", dt=1e-3)
    assert advice.omega_max == pytest.approx(np.sqrt(KP / MASS), rel=1e-3)
    assert advice.dt_stable == pytest.approx(2.0 / np.sqrt(KP / MASS), rel=1e-3)


def test_the_scene_handle_table_builds_handles(tmp_path):
    """[[cloth.handle]]: grabbed particles by edge name, gains, cap and track; a missing kp is one line."""
    from warpspring.io.scene import load_scene

    path = tmp_path / "pull.toml"
    path.write_text("""\
version = 2
[cloth]
grid = { nx = 4, ny = 3, spacing = 0.1 }
mass = 0.1

[[cloth.handle]]
name = "hand"
particles = ["left"]
kp = 40.0
kd = 0.5
max_force = 1.5
translation = { times = [0.0, 2.0], values = [[0, 0, 0], [-1, 0, 0]], interpolation = "smooth" }
""")
    model = load_scene(path).finalize("cpu")
    family = next(f for f in model.families if f.name == "handle grabs")
    (handle,) = family.handles
    assert handle.name == "hand" and (handle.kp, handle.kd, handle.max_force) == (40.0, 0.5, 1.5)
    np.testing.assert_array_equal(handle.particles, [0, 4, 8])  # column 0 of the 4 × 3 grid
    assert family.spec(model).cap and not family.spec(model).rotation and handle.translation is not None
    path.write_text(path.read_text().replace("kp = 40.0\n", ""))
    with pytest.raises(ws.ConfigError, match=r"pull.toml: \[cloth.handle\] needs kp"):
        load_scene(path)


def test_the_advisor_counts_the_handle_damping(device):
    """Kd damps the grabbed particle's own motion like drag: the advisor's limit for symplectic Euler is the damped
    oscillator's, stable_step(ω = √(Kp/m), ζ = Kd / (2 m ω)), below the undamped 2/ω."""
    from warpspring.analysis.stability import stable_step

    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles([[0.0, 0.0, 0.0]], mass=MASS)
    builder.add_handle([0], kp=KP, kd=40.0)
    model = builder.finalize(device)
    advice = ws.advise(model, "symplectic_euler", dt=1e-3)
    omega = np.sqrt(KP / MASS)
    expected = stable_step("symplectic_euler", omega, 40.0 / (2.0 * MASS * omega))
    assert expected < 0.9 * 2.0 / omega
    assert advice.dt_stable == pytest.approx(expected, rel=2e-3)


def test_a_handle_is_dragged_from_the_host_between_frames(device):
    """Without a track a handle is moved from the host (set_target, a live value: no re-capture): the particle
    settles on the new target; set_gains(kp=0, kd=0) lets go, and it coasts on at its velocity."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles([[0.0, 0.0, 0.0]], mass=MASS)
    builder.add_handle([0], kp=KP, kd=2.0 * np.sqrt(KP * MASS), name="hand")  # critically damped
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=16)
    sim.step_frame()
    captures = sim.stepper.captures
    model.handles.set_target("hand", (0.2, -0.1, 0.0))
    for _ in range(60):
        sim.step_frame()
    np.testing.assert_allclose(sim.state.particle_q.numpy()[0], [0.2, -0.1, 0.0], atol=1e-6)
    model.handles.set_target(0, (0.5, -0.1, 0.0))
    for _ in range(3):
        sim.step_frame()
    model.handles.set_gains("hand", kp=0.0, kd=0.0)
    v = sim.state.particle_qd.numpy()[0].copy()
    x = sim.state.particle_q.numpy()[0].copy()
    for _ in range(6):
        sim.step_frame()
    np.testing.assert_allclose(sim.state.particle_q.numpy()[0], x + 0.1 * v, rtol=1e-5, atol=1e-7)
    assert sim.stepper.captures == captures
    tracked = ws.ModelBuilder()
    tracked.add_particles([[0.0, 0.0, 0.0]], mass=MASS)
    tracked.add_handle([0], kp=KP, translation=ws.Track([0.0, 1.0], [[0, 0, 0], [1, 0, 0]]), name="rail")
    with pytest.raises(ws.ConfigError, match="'rail' follows a translation track"):
        tracked.finalize(device).handles.set_target("rail", (1.0, 0.0, 0.0))
