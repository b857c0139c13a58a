"""Symplectic Euler and the force terms against analytic solutions.

Symplectic Euler (v' = v + h a, x' = x + h v') has closed-form discrete solutions for the cases below,
so each test checks the simulated result against the exact discrete value (to rounding) and the
discrete value against the analytic solution within the method's error bound.
"""

import math

import numpy as np
import pytest

import warpspring as ws
from helpers import CUDA, ZERO_GRAVITY, hanging_cloth, run_frames, trajectory

G = 9.81
# Rounding budget of positions of O(1-10) m after O(10³) float32 steps (≈ √steps · 10 m · 6e-8, ×10);
# float64 is ~1e9 times tighter.
ROUNDING = {"float32": 5.0e-4, "float64": 1.0e-9}


def free_particle(device, precision, *, velocity=(0.0, 0.0, 0.0), drag=0.0, mass=2.0):
    builder = ws.ModelBuilder(drag=drag)
    builder.add_particles([[0.0, 0.0, 10.0]], velocities=[velocity], mass=mass)
    return builder.finalize(device, precision=precision)


def test_free_fall_is_half_g_t_squared(device, precision):
    """x(t) = x0 + v0 t - ½ g t²: symplectic Euler lands on the exact discrete value
    x0 + v0 t - ½ g t (t + h), i.e. its error is exactly ½ g h t (first order)."""
    v0 = np.array([1.5, -0.5, 3.0])
    model = free_particle(device, precision, velocity=v0)
    sim = ws.Simulator(model, fps=60, substeps=16)
    t, h = 1.0, sim.dt
    x = run_frames(sim, 60)[0]

    x0 = np.array([0.0, 0.0, 10.0])
    g = np.array([0.0, 0.0, -G])
    exact = x0 + v0 * t + 0.5 * g * t * t
    discrete = exact + 0.5 * g * h * t
    np.testing.assert_allclose(x, discrete, rtol=0, atol=ROUNDING[precision])
    # The error against the analytic solution is the method's first-order term ½ g h t (5 mm here),
    # ten times the float32 rounding budget, so this also checks the order of the method.
    assert abs(np.linalg.norm(x - exact) - 0.5 * G * h * t) < ROUNDING[precision]


def test_external_force_and_gravity_add(device):
    """A control force F on a falling particle gives a = g + F/m (same discrete law as free fall)."""
    mass, force = 2.0, np.array([4.0, 0.0, 30.0])
    model = free_particle(device, "float32", mass=mass)
    control = model.control()
    control.set_particle_force(force)
    sim = ws.Simulator(model, fps=60, substeps=16, control=control)
    x = run_frames(sim, 30)[0]
    t, h = 0.5, sim.dt
    a = np.array([0.0, 0.0, -G]) + force / mass
    np.testing.assert_allclose(x, [0.0, 0.0, 10.0] + 0.5 * a * t * (t + h), atol=ROUNDING["float32"])


def test_drag_reaches_terminal_velocity(device):
    """With drag c, a falling particle approaches v = m g / c (the fixed point of the update)."""
    mass, c = 0.5, 2.0
    model = free_particle(device, "float32", drag=c, mass=mass)
    sim = ws.Simulator(model, fps=60, substeps=8)
    run_frames(sim, 120)  # 2 s = 8 time constants m/c
    v = sim.state.particle_qd.numpy()[0]
    np.testing.assert_allclose(v, [0.0, 0.0, -mass * G / c], rtol=1e-3)


def test_spring_period(device, precision):
    """A mass on a spring oscillates with T = 2π√(m/k). Symplectic Euler's discrete period is
    2πh / arccos(1 - (ωh)²/2), so its relative period error is (ωh)²/24 + O((ωh)⁴)."""
    m, k, rest, amplitude = 0.5, 200.0, 1.0, 0.1
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0.0, 0.0, 0.0], [rest + amplitude, 0.0, 0.0]], mass=m, pinned=[0])
    builder.add_springs([[0, 1]], stiffness=k, rest_length=rest)
    model = builder.finalize(device, precision=precision)
    omega = math.sqrt(k / m)
    h = 0.1 / omega  # ωh = 0.1: 63 steps per period
    periods = 10
    steps = int(periods * 2 * math.pi / (omega * h)) + 5
    x = trajectory(model, ws.SymplecticEuler(model), h, steps)[:, 1, 0] - rest

    # Period from the upward zero crossings, linearly interpolated.
    up = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    crossings = (up + x[up] / (x[up] - x[up + 1])) * h
    measured = np.diff(crossings).mean()
    analytic = 2 * math.pi / omega
    discrete = 2 * math.pi * h / math.acos(1 - (omega * h) ** 2 / 2)
    assert len(up) >= periods - 1
    # Interpolating a sine across one step errs by O((ωh)³) of a period: 1e-6 of it here.
    np.testing.assert_allclose(measured, discrete, rtol=2e-5)
    assert abs(measured - analytic) / analytic <= 1.05 * (omega * h) ** 2 / 24


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_hanging_chain_stretch(device, precision):
    """At rest, spring i of a hanging chain stretches by (mass below it) · g / k."""
    n, m, k, spacing = 10, 0.1, 1.0e3, 0.1
    builder = ws.ModelBuilder(drag=3.2)  # ≈ critical damping of the slowest mode: settles in ~1 s
    q = np.zeros((n, 3))
    q[:, 2] = 2.0 - spacing * np.arange(n)
    builder.add_particles(q, mass=m, pinned=[0])
    builder.add_springs(np.stack([np.arange(n - 1), np.arange(1, n)], 1), stiffness=k)
    model = builder.finalize(device, precision=precision)
    sim = ws.Simulator(model, fps=60, substeps=16)
    x = run_frames(sim, 300)  # 5 s: drag decays every mode by e^(-c t / 2m) = e^-80

    stretch = -np.diff(x[:, 2]) - spacing
    expected = (n - 1 - np.arange(n - 1)) * m * G / k
    # float32: the equilibrium is exact up to force rounding k·|x|·ε / k ≈ 1e-7 m per particle.
    np.testing.assert_allclose(stretch, expected, rtol=0, atol=2e-6 if precision == "float32" else 1e-10)
    np.testing.assert_allclose(x[:, :2], 0.0, atol=1e-12)


def test_pins_stay_put(device):
    """Pinned particles keep their exact initial positions while the cloth swings."""
    model, ids = hanging_cloth(device, n=10)
    q0 = model.particle_q.numpy()
    sim = ws.Simulator(model, fps=60, substeps=16)
    x = run_frames(sim, 30)
    pinned = [ids[-1, 0], ids[-1, -1]]
    np.testing.assert_array_equal(x[pinned], q0[pinned])
    free = np.setdiff1d(np.arange(model.particle_count), pinned)
    assert np.abs(x[free] - q0[free]).max() > 0.1  # the rest of the cloth fell


def test_cloth_on_sphere_never_penetrates(device):
    """A cloth dropped on a sphere ends with every particle at distance ≥ R + r from its centre,
    and rests on it (its lowest centre distances equal R + r)."""
    model, ids = hanging_cloth(device, n=12, sphere=True, pin=[], spacing=0.06, origin=(-0.33, -0.33, 1.0))
    sim = ws.Simulator(model, fps=60, substeps=16)
    center, R = np.array([0.0, 0.0, 0.5]), 0.3
    r = 0.25 * 0.06
    for _ in range(4):
        x = run_frames(sim, 15)
        d = np.linalg.norm(x - center, axis=1)
        assert d.min() >= R + r - 2e-6  # float32 rounding of a projection to ~1 m
    assert abs(d.min() - (R + r)) < 1e-5  # in contact, not hovering
    top = ids[5:7, 5:7].ravel()  # the middle particles rest on the top of the sphere
    np.testing.assert_allclose(x[top, 2], center[2] + np.sqrt((R + r) ** 2 - x[top, 0] ** 2 - x[top, 1] ** 2), atol=1e-4)


def test_ground_friction_stopping_distance(device):
    """A particle sliding on the ground at v0 stops after v0² / (2 μ g) (within v0·h, the first-order
    error of the discrete impulse), and rests exactly on the surface (height = radius)."""
    v0, mu, r = 2.0, 0.5, 0.05
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, r]], velocities=[[v0, 0.0, 0.0]], mass=1.0, radius=r)
    builder.add_ground_plane(friction=mu)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=16)
    x = run_frames(sim, 60)[0]
    assert abs(x[0] - v0 * v0 / (2 * mu * G)) <= v0 * sim.dt
    assert abs(x[2] - r) < 1e-6
    np.testing.assert_allclose(sim.state.particle_qd.numpy()[0], 0.0, atol=1e-6)


@pytest.mark.cuda
@pytest.mark.parametrize("precision, atol", [("float32", 1e-4), ("float64", 1e-10)])
def test_cpu_and_cuda_trajectories_agree(precision, atol):
    """The same cloth on cpu and cuda:0 follows the same trajectory (float32: FMA contraction and
    transcendental rounding differ, ~1e-6 m per frame over a smooth swing; float64 ~1e-14)."""
    if not CUDA:
        pytest.skip("no CUDA device")
    results = []
    for device in ("cpu", "cuda:0"):
        model, _ = hanging_cloth(device, n=12, precision=precision, sphere=True)
        results.append(run_frames(ws.Simulator(model, fps=60, substeps=16), 30))
    np.testing.assert_allclose(results[0], results[1], rtol=0, atol=atol)
    assert np.abs(results[0] - hanging_cloth("cpu", n=12)[0].particle_q.numpy()).max() > 0.1


def test_gather_and_scatter_spring_evaluation_agree(device):
    """Per-particle gathering and per-spring scattering give the same forces (to float32 summation
    rounding, ~1e-6 of the largest spring force) and the same trajectory."""
    rng = np.random.default_rng(5)
    results = {}
    for mode in ("gather", "scatter"):
        builder = ws.ModelBuilder(drag=0.1)
        builder.add_cloth_grid(nx=9, ny=7, spacing=0.1, mass=1.0, pin=["top-left"], origin=(0.0, 0.0, 0.3),
                               structural=ws.SpringMaterial(500.0, 0.1), shear=ws.SpringMaterial(100.0, 0.02),
                               bend=ws.SpringMaterial(20.0, 0.01))
        builder.add_ground_plane()
        model = builder.finalize(device, spring_evaluation=mode)
        assert model.spring_gather == (mode == "gather")
        state = model.state()
        q = model.particle_q.numpy() + rng.normal(scale=0.01, size=(model.particle_count, 3))
        rng = np.random.default_rng(5)  # the same perturbation for both modes
        state.particle_q.assign(q.astype(np.float32))
        ws.eval_forces(model, state, None)
        sim = ws.Simulator(model, fps=60, substeps=16)
        results[mode] = (state.particle_f.numpy(), run_frames(sim, 30))
    (f_gather, x_gather), (f_scatter, x_scatter) = results["gather"], results["scatter"]
    np.testing.assert_allclose(f_gather, f_scatter, rtol=0, atol=1e-5 * np.abs(f_gather).max())
    np.testing.assert_allclose(x_gather, x_scatter, rtol=0, atol=1e-5)
    assert x_gather[:, 2].min() < 0.1  # it fell onto the ground: contacts were exercised
