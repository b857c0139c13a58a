"""The extremes battery: stiffness from 1e-3 to 1e9 N/m, mass ratios of 1e6, steps up to 1/30 s,
zero-rest-length springs, coincident particles, 1e3 m/s launches and 1e5 substeps per frame.

For every case the expected outcome is written down: implicit Euler stays finite everywhere; an
explicit integrator either runs to the end finite (inside the limit the advisor predicts) or is
refused up front with the advisor's message (``--strict``) and, when run anyway, stops with the
guard's error naming frame and substep (or, where the growth is known to be slow, finishes finite) —
never a silent NaN, never a hang (every run is bounded).
"""

import re

import numpy as np
import pytest

import warpspring as ws
from helpers import ZERO_GRAVITY
from warpspring.analysis.advisor import advise

FRAMES = 20


def small_cloth(device, *, k, kd=0.0, mass=0.1, n=6, precision="float32"):
    """A 6 × 6 cloth 0.1 m apart, pinned at two corners, every spring family at stiffness k [N/m], without
    gravity and set in motion by random velocities of 0.1 m/s: growth can then only be numerical (with
    gravity, a 1e-3 N/m cloth would physically stretch by kilometres)."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    spring = ws.SpringMaterial(k, kd)
    ids = builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(0.0, 0.0, 1.0), particle_mass=mass,
                                 structural=spring, shear=spring, bend=spring, pin=["top-left", "top-right"])
    model = builder.finalize(device, precision=precision)
    velocity = np.random.default_rng(3).normal(scale=0.1, size=(ids.size, 3))
    velocity[[ids[-1, 0], ids[-1, -1]]] = 0.0  # the pins stay put
    model.particle_qd.assign(velocity.astype(np.float64 if precision == "float64" else np.float32))
    return model


def alternating_chain(device, *, ratio, k=100.0):
    """A free-hanging chain of 8 particles whose masses alternate 1 kg and 1/ratio kg."""
    builder = ws.ModelBuilder()
    q = np.zeros((8, 3))
    q[:, 2] = 1.0 - 0.1 * np.arange(8)
    builder.add_particles(q, mass=np.where(np.arange(8) % 2 == 0, 1.0, 1.0 / ratio), pinned=[0])
    builder.add_springs(np.stack([np.arange(7), np.arange(1, 8)], 1), stiffness=k)
    return builder.finalize(device)


def outcome(model, integrator, fps, substeps, frames=FRAMES):
    """Run ``frames`` frames with guards checking 10+ times per frame: "finished" (and finite) or "stopped"."""
    sim = ws.Simulator(model, integrator=ws.INTEGRATORS[integrator](model), fps=fps, substeps=substeps,
                       guard=ws.GuardLimits(every=max(1, substeps // 10)))
    try:
        for _ in range(frames):
            sim.step_frame()
        sim.settle()  # the last frame's verdict (on CUDA read a frame later)
    except ws.SimulationError as error:
        assert re.match(r"frame \d+, substep \d+ of \d+ ", str(error)), str(error)
        return "stopped"
    assert np.isfinite(sim.state.particle_q.numpy()).all()  # finished runs are finite: no silent NaN
    return "finished"

# What the advisor predicts for each integrator, and how the run must end:
STABLE = "stable"  # predicted stable: runs to the end, finite
STOPS = "stops"  # predicted unstable: refused under --strict; run anyway, the guard stops it
GROWS_SLOWLY = "grows slowly"  # predicted unstable, but the growth per run stays far inside the guard's limits

# (case, model factory, fps, substeps, {integrator: expected})
CASES = [
    # Forward Euler on undamped springs grows by (1 + (ωh)²)^½ per step: ω_max ≈ 0.3 rad/s, h = 1/30 s
    # gives 1 + 5e-5 per step, 1e-3 over the 20 steps.
    ("k=1e-3", lambda d: small_cloth(d, k=1e-3), 30, 1,
     {"symplectic_euler": STABLE, "rk4": STABLE, "explicit_euler": GROWS_SLOWLY, "implicit_euler": STABLE}),
    ("k=1e3", lambda d: small_cloth(d, k=1e3), 60, 10,
     {"symplectic_euler": STABLE, "rk4": STABLE, "explicit_euler": STOPS, "implicit_euler": STABLE}),
    ("k=1e6", lambda d: small_cloth(d, k=1e6), 60, 10,
     {"symplectic_euler": STOPS, "rk4": STOPS, "explicit_euler": STOPS, "implicit_euler": STABLE}),
    ("k=1e9, dt=1/30", lambda d: small_cloth(d, k=1e9), 30, 1,
     {"symplectic_euler": STOPS, "rk4": STOPS, "explicit_euler": STOPS, "implicit_euler": STABLE}),
    # Forward Euler needs damping: with kd/k = 1e-5 s it is stable only while h < kd/k = 10 µs.
    ("k=1e6 damped, 800 substeps", lambda d: small_cloth(d, k=1e6, kd=10.0), 60, 800,
     {"symplectic_euler": STABLE, "rk4": STABLE, "explicit_euler": STOPS, "implicit_euler": STABLE}),
    ("k=1e6 damped, 2000 substeps", lambda d: small_cloth(d, k=1e6, kd=10.0), 60, 2000,
     {"symplectic_euler": STABLE, "explicit_euler": STABLE}),
    ("mass ratio 1e6", lambda d: alternating_chain(d, ratio=1e6), 60, 16,
     {"symplectic_euler": STOPS, "rk4": STOPS, "explicit_euler": STOPS, "implicit_euler": STABLE}),
    # The light particles' ω ≈ √(2k/m) = 1.4e4 rad/s caps symplectic Euler's step at 2/ω = 141 µs (RK4's at
    # 200 µs): 400 substeps (h = 42 µs, ωh = 0.59) are enough with a 3.4× margin, and undamped explicit Euler
    # still grows, by √(1 + (ωh)²) = 1.16 per step. (Explicit Euler's slow growth, just past its limit, is the
    # "k=1e6 damped, 800 substeps" case; 2000 substeps here cost 20 s on the CPU, 400 cost a fifth.)
    ("mass ratio 1e6, enough substeps", lambda d: alternating_chain(d, ratio=1e6), 60, 400,
     {"symplectic_euler": STABLE, "rk4": STABLE, "explicit_euler": STOPS, "implicit_euler": STABLE}),
]


@pytest.mark.parametrize("case, build, fps, substeps, expected", CASES, ids=[c[0] for c in CASES])
def test_extremes_battery(device, case, build, fps, substeps, expected):
    """The advisor predicts each (case, integrator) as written, and the run ends as written: predicted-
    stable runs finish finite; predicted-unstable ones are refused under strict checking and, run anyway,
    are stopped by the guard naming frame and substep — or, where the growth is slow, finish finite."""
    model = build(device)
    dt = 1.0 / (fps * substeps)
    for integrator, want in expected.items():
        if want == STABLE:
            advice = advise(model, integrator, dt, fps=fps)
            assert advice.stable, f"{case}, {integrator}: {advice.message}"
        else:
            # Strict checking raises exactly when the advice is unstable, so one call asserts both (the
            # advisor's dry run of a 1e9 N/m cloth at its stable step costs ~5 s a call on the CPU).
            with pytest.raises(ws.ConfigError, match="unstable"):
                advise(model, integrator, dt, fps=fps, strict=True)
        result = outcome(model, integrator, fps, substeps, frames=FRAMES if substeps < 100 else 2)
        assert result == ("stopped" if want == STOPS else "finished"), f"{case}, {integrator}: {want} but {result}"


def test_unstable_explicit_run_far_outside_its_limit_stops_with_the_error(device):
    """Symplectic Euler at over 5× its stable step on a stiff cloth is stopped by the guard within two
    frames, naming the substep — the NaN never reaches the caller."""
    model = small_cloth(device, k=1e6)
    advice = advise(model, "symplectic_euler", 1.0 / 600.0, fps=60)
    assert advice.dt_stable < (1.0 / 600.0) / 5
    assert outcome(model, "symplectic_euler", 60, 10, frames=2) == "stopped"


def test_zero_rest_length_springs(device, precision):
    """A particle tied to a pinned anchor by a zero-rest-length spring oscillates through the anchor as the
    linear oscillator x'' = -(k/m) x (symplectic Euler's exact discrete solution), with no NaN when it
    passes through the anchor."""
    k, m = 400.0, 1.0
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], mass=m, pinned=[0])
    builder.add_springs([[0, 1]], stiffness=k, rest_length=0.0)
    model = builder.finalize(device, precision=precision)
    h, steps = 1e-3, 2000
    integrator = ws.SymplecticEuler(model)
    a, b = model.state(), model.state()
    x, v = 0.1, 0.0
    for _ in range(steps):
        integrator.step(a, b, None, h)
        a, b = b, a
        v -= h * k / m * x
        x += h * v
    np.testing.assert_allclose(a.particle_q.numpy()[1], [x, 0.0, 0.0], atol=1e-5 if precision == "float32" else 1e-12)


def test_coincident_particles_feel_no_spring_force(device):
    """Two particles at the same point joined by a spring of rest length 0.1 m exert no force on each
    other (the direction is undefined): they stay put, finite, while an offset pair springs apart."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0, 0, 0], [0, 0, 0], [1, 0, 0], [1.05, 0, 0]], mass=1.0)
    builder.add_springs([[0, 1], [2, 3]], stiffness=100.0, rest_length=0.1)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=8, guard=ws.GuardLimits(every=1))
    for _ in range(10):
        sim.step_frame()
    q = sim.state.particle_q.numpy()
    np.testing.assert_array_equal(q[:2], 0.0)
    assert np.isfinite(q).all() and abs(q[3, 0] - q[2, 0] - 0.05) > 0.01


def test_launch_at_1e3_meters_per_second(device):
    """A cloth launched at 1e3 m/s flies as a rigid body: after 10 frames its centre has moved v t + ½ g t²
    (symplectic Euler's ½ g t (t + h)) and its springs are unstrained; the guard's default energy limit
    does not fire."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(100.0, 0.1)
    velocity = np.array([1.0e3, 0.0, 0.0])
    builder.add_cloth_grid(nx=5, ny=5, spacing=0.1, particle_mass=0.1, velocity=velocity, structural=spring,
                           shear=spring, bend=spring)
    model = builder.finalize(device, precision="float64")
    q0 = model.particle_q.numpy()
    sim = ws.Simulator(model, fps=60, substeps=8)
    for _ in range(10):
        sim.step_frame()
    t, h = 10 / 60, sim.dt
    shift = sim.state.particle_q.numpy() - q0
    np.testing.assert_allclose(shift, np.broadcast_to(velocity * t + np.array([0, 0, -9.81]) * 0.5 * t * (t + h),
                                                      shift.shape), rtol=0, atol=1e-9)


def falling_particle(device, precision, *, fps, substeps):
    """One frame of a particle falling from z = 1 m at ``fps`` and ``substeps``: (z [m], exact z [m]),
    symplectic Euler's exact discrete solution ½ g t (t + h). On CUDA the frame is one captured graph. On the
    CPU it runs uncaptured: Warp's CPU capture records each launch in Python (~0.5 ms per substep here, 4×
    running it), which a single frame never earns back."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 1.0]], mass=1.0)
    model = builder.finalize(device, precision=precision)
    sim = ws.Simulator(model, fps=fps, substeps=substeps, use_graph=model.device.is_cuda)
    sim.step_frame()
    z = float(sim.state.particle_q.numpy()[0, 2])
    t, h = 1 / fps, sim.dt
    return z, 1.0 - 0.5 * 9.81 * t * (t + h)


def test_1e5_substeps_per_frame(device):
    """One frame of 1e5 substeps (h = 0.17 µs) runs as one graph without hanging, and in float64 a falling
    particle lands on ½ g t (t + h) within 1e-9 m (1e5 roundings of ≤ 1.1e-16 m each add up to ≤ 1.1e-11 m).
    The one run of 1e5 substeps the suite keeps; float32 at the same step is shown on a shorter frame below."""
    z, exact = falling_particle(device, "float64", fps=60, substeps=100_000)
    assert abs(z - exact) < 1e-9


def test_float32_cannot_resolve_a_submicrosecond_step(device):
    """At h = 0.17 µs (the step of 1e5 substeps per 1/60 s frame) each float32 position increment h·v is
    below the resolution of a coordinate near 1 m (6e-8 m), so a falling particle barely moves: float64 is
    required. The resolution argument depends on h and v only, so one 1/600 s frame of 1e4 substeps (the
    same h; v ≤ g t = 0.016 m/s, h·v ≤ 3e-9 m) shows it at a tenth of the cost. The float64 counterpart,
    which lands on ½ g t (t + h), is test_1e5_substeps_per_frame."""
    z, exact = falling_particle(device, "float32", fps=600, substeps=10_000)
    assert abs(z - exact) > 0.1 * (1.0 - exact)  # off by more than 10 % of the 14 µm drop


def test_float64_resolves_a_stiff_chain_that_float32_cannot(device):
    """A chain of 1e9 N/m springs under gravity stretches by 1e-9…9e-9 m per spring. Implicit Euler settles
    it; float64 reproduces the stretches (mass below · g / k) within 1 %, while float32, whose coordinate
    resolution near 1 m is 6e-8 m, cannot represent them at all."""
    n, m, k = 10, 0.1, 1e9
    results = {}
    for precision in ("float32", "float64"):
        builder = ws.ModelBuilder(drag=50.0)
        q = np.zeros((n, 3))
        q[:, 2] = 1.0 - 0.1 * np.arange(n)
        builder.add_particles(q, mass=m, pinned=[0])
        builder.add_springs(np.stack([np.arange(n - 1), np.arange(1, n)], 1), stiffness=k)
        model = builder.finalize(device, precision=precision)
        # Each precision asks CG for what it can attain: 1e-12 in float32 (ε = 6e-8) only iterates rounding
        # noise, which at this conditioning (k h² / m ~ 3e6) can diverge.
        tolerance = 1e-12 if precision == "float64" else 1e-6
        sim = ws.Simulator(model, integrator=ws.ImplicitEuler(model, cg_tolerance=tolerance, cg_iterations=200),
                           fps=60, substeps=1)
        for _ in range(60):
            sim.step_frame()
        results[precision] = -np.diff(sim.state.particle_q.numpy().astype(np.float64)[:, 2]) - 0.1
    expected = (n - 1 - np.arange(n - 1)) * m * 9.81 / k
    np.testing.assert_allclose(results["float64"], expected, rtol=1e-2)
    assert np.abs(results["float32"] - expected).max() > expected.max()  # float32 error ≥ the stretch itself
