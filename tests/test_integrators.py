"""Every integrator against the damped oscillator's closed form, energy behaviour, implicit Euler's
amplification and linear solve, and precision agreement.

The oscillator is one particle on a spring to a pinned anchor, moving along the spring axis, so the
3-D spring is exactly the linear ODE m x'' + c x' + k x = 0 with x(0) = A, v(0) = 0.
"""

import math

import numpy as np
import pytest

import warpspring as ws
from helpers import ZERO_GRAVITY, hanging_cloth, run_frames, trajectory

M, K, C, REST, AMPLITUDE = 1.0, 100.0, 2.0, 1.0, 0.1  # ω = 10 rad/s, ζ = 0.1
OMEGA = math.sqrt(K / M)


def oscillator(device, *, precision="float64", damping=C, stiffness=K):
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0.0, 0.0, 0.0], [REST + AMPLITUDE, 0.0, 0.0]], mass=M, pinned=[0])
    builder.add_springs([[0, 1]], stiffness=stiffness, damping=damping, rest_length=REST)
    return builder.finalize(device, precision=precision)


def exact_x(t):
    zeta = C / (2 * math.sqrt(K * M))
    wd = OMEGA * math.sqrt(1 - zeta * zeta)
    return AMPLITUDE * np.exp(-zeta * OMEGA * t) * (np.cos(wd * t) + zeta * OMEGA / wd * np.sin(wd * t))


# Step counts over t ∈ [0, 1] s inside each method's asymptotic range (ωh from 0.25 to 0.003), and
# above float64 round-off. The first-order methods start at 400 steps (ωh = 0.025: the error's next
# term, relative to the first, is of order ωh): measured orders 1.028 (explicit) and 0.973 (implicit
# Euler) on the CPU, against 1.014 and 0.986 from 800 to 6400 steps, at half the cost.
STEPS = {
    "explicit_euler": (400, 800, 1600, 3200),
    "symplectic_euler": (400, 800, 1600, 3200),
    "velocity_verlet": (100, 200, 400, 800),
    "midpoint": (100, 200, 400, 800),
    "rk4": (40, 80, 160, 320),
    "implicit_euler": (400, 800, 1600, 3200),
}


@pytest.mark.parametrize("name", list(STEPS))
def test_convergence_order_on_damped_oscillator(name):
    """The global error at t = ¼, ½, ¾, 1 s falls as h^p with p the method's order (±0.15), fitted over four
    halvings of the step (``STEPS``: in each method's asymptotic range, so the fit measures p)."""
    cls = ws.INTEGRATORS[name]
    errors, steps_sizes = [], []
    for n in STEPS[name]:
        model = oscillator("cpu")
        integrator = cls(model, cg_tolerance=1e-12) if name == "implicit_euler" else cls(model)
        h = 1.0 / n
        x = trajectory(model, integrator, h, n, every=n // 4)[:, 1, 0] - REST
        errors.append(np.abs(x - exact_x(np.arange(5) * 0.25)).max())
        steps_sizes.append(h)
    order = np.polyfit(np.log(steps_sizes), np.log(errors), 1)[0]
    assert abs(order - cls.order) <= 0.15, f"{name}: measured order {order:.3f}, errors {errors}"


@pytest.mark.parametrize("tolerance", [1e-5, 1e-8])
def test_dopri5_meets_its_tolerance(tolerance):
    """The adaptive pair keeps the global error within the sum of its local tolerances (≤ steps · tol),
    takes more steps for a tighter tolerance, and lands exactly on each requested step's end."""
    model = oscillator("cpu")
    integrator = ws.DormandPrince(model, tolerance=tolerance)
    x = trajectory(model, integrator, 0.25, 4)[:, 1, 0] - REST  # four outer steps of ¼ s
    error = np.abs(x - exact_x(np.arange(5) * 0.25)).max()
    assert error <= integrator.accepted_steps * tolerance
    assert error > 0.0
    # 5th-order local error: the step count grows like tol^(-1/5) (a factor 4 for 1000× tighter).
    assert integrator.accepted_steps >= {1e-5: 8, 1e-8: 30}[tolerance]


def test_dopri5_rejects_a_step_that_is_too_large():
    """Starting with one step of a whole period, the controller rejects, shrinks and still meets the
    tolerance; rejected steps are counted."""
    model = oscillator("cpu", damping=0.0)
    integrator = ws.DormandPrince(model, tolerance=1e-7)
    x = trajectory(model, integrator, 2 * math.pi / OMEGA, 1)[-1, 1, 0] - REST
    assert integrator.rejected_steps >= 1
    assert abs(x - AMPLITUDE) <= integrator.accepted_steps * 1e-7 * 2  # back at the start after a period


def energy_ratio(x, v):
    return (OMEGA**2 * x * x + v * v) / (OMEGA**2 * AMPLITUDE**2)


def oscillator_energy_trace(name, periods):
    """Energy / initial energy of the undamped oscillator at ωh = 0.1 over ``periods`` periods, one sample
    per frame of 630 steps."""
    model = oscillator("cpu", damping=0.0)
    h = WH / OMEGA
    steps_per_frame = 630  # 10.03 periods: the sampled phase drifts, covering the whole orbit
    sim = ws.Simulator(model, integrator=ws.INTEGRATORS[name](model), fps=1.0 / (h * steps_per_frame),
                       substeps=steps_per_frame)
    frames = int(periods * 2 * math.pi / (WH * steps_per_frame))
    ratios = []
    for _ in range(frames):
        sim.step_frame()
        x = sim.state.particle_q.numpy()[1, 0] - REST
        v = sim.state.particle_qd.numpy()[1, 0]
        ratios.append(energy_ratio(x, v))
    return np.array(ratios)


WH = 0.1
# Each symplectic method conserves a modified energy exactly; on the level set through (x, v) = (A, 0) the
# true energy E = ½(ω²x² + v²) then stays in a band: symplectic Euler conserves v² + ω²x² - ωh·ωx·v, so
# E/E₀ ∈ [1/(1 + ωh/2), 1/(1 - ωh/2)] (±ωh/2 to first order); velocity Verlet conserves
# v² + (1 - (ωh)²/4) ω²x², so E/E₀ ∈ [1 - (ωh)²/4, 1].
ENERGY_BANDS = {
    "symplectic_euler": (1 / (1 + WH / 2), 1 / (1 - WH / 2)),
    "velocity_verlet": (1 - WH**2 / 4, 1.0),
}


@pytest.mark.parametrize("name", list(ENERGY_BANDS))
def test_symplectic_methods_keep_energy_bounded_over_1e4_periods(name):
    """At ωh = 0.1 over 10⁴ periods the energy stays inside the band of the method's conserved modified
    energy (to float64 round-off), fills it, and does not drift."""
    lower, upper = ENERGY_BANDS[name]
    ratios = oscillator_energy_trace(name, 10_000)
    assert len(ratios) >= 990
    slack = 1e-9  # float64 round-off over 6.3e5 steps
    assert lower - slack <= ratios.min() and ratios.max() <= upper + slack
    assert ratios.max() - ratios.min() >= 0.9 * (upper - lower)  # the sampling sees the whole band
    assert abs(np.percentile(ratios[-300:], 50) - np.percentile(ratios[:300], 50)) <= 0.05 * (upper - lower)


def test_explicit_euler_energy_grows_at_its_predicted_rate():
    """Forward Euler multiplies ω²x² + v² by exactly 1 + ω²h² per step: ×1.87 per period at ωh = 0.1
    (the amplitude ×1.37), ×22.8 over five periods."""
    model = oscillator("cpu", damping=0.0)
    integrator = ws.ExplicitEuler(model)
    h, steps = WH / OMEGA, 314  # five periods: the amplitude grows 4.8× to 0.48 m, still short of the
    # spring's 1 m rest length, so the 3-D spring stays the linear oscillator
    a, b = model.state(), model.state()
    for _ in range(steps):
        integrator.step(a, b, None, h)
        a, b = b, a
    x, v = a.particle_q.numpy()[1, 0] - REST, a.particle_qd.numpy()[1, 0]
    np.testing.assert_allclose(energy_ratio(x, v), (1 + (OMEGA * h) ** 2) ** steps, rtol=1e-9)


def test_implicit_euler_damps_by_its_amplification_factor_at_omega_h_100():
    """Backward Euler on an undamped spring shrinks √(ω²x² + v²) by exactly 1/√(1 + ω²h²) per step,
    and stays finite, at ωh = 100."""
    model = oscillator("cpu", damping=0.0)
    integrator = ws.ImplicitEuler(model, cg_tolerance=1e-13)
    h = 100.0 / OMEGA
    a, b = model.state(), model.state()
    norm = OMEGA * AMPLITUDE
    for _ in range(4):
        integrator.step(a, b, None, h)
        a, b = b, a
        x, v = a.particle_q.numpy()[1, 0] - REST, a.particle_qd.numpy()[1, 0]
        new_norm = math.hypot(OMEGA * x, v)
        assert new_norm == pytest.approx(norm / math.sqrt(1 + (OMEGA * h) ** 2), rel=1e-9)
        norm = new_norm


def test_implicit_euler_stays_finite_on_a_stiff_cloth_at_a_large_step(device):
    """A cloth 100× stiffer than the ANCHORS one (ω_max·h ≈ 100 at one step per 1/30 s frame) falls,
    hangs from its pins and stays finite under implicit Euler; its pins do not move."""
    stiff = ws.SpringMaterial(1.0e5, 10.0)
    model, ids = hanging_cloth(device, n=10, structural=stiff, shear=stiff, bend=stiff)
    sim = ws.Simulator(model, integrator=ws.ImplicitEuler(model), fps=30, substeps=1)
    x = run_frames(sim, 30)
    q0 = model.particle_q.numpy()
    assert np.isfinite(x).all()
    np.testing.assert_array_equal(x[[ids[-1, 0], ids[-1, -1]]], q0[[ids[-1, 0], ids[-1, -1]]])
    assert x[ids[0, :], 2].max() < q0[ids[0, 0], 2] - 0.5  # the free edge swung down
    # Stiff springs barely stretch: the hanging cloth keeps its rest lengths to a few per cent.
    pairs = model.spring_indices.numpy()
    strain = np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1) / model.spring_rest_length.numpy() - 1
    assert np.abs(strain).max() < 0.05


def dense_implicit_system(model, state, h):
    """A and b of the Baraff-Witkin step assembled densely in float64 with NumPy (clamped Hessian)."""
    n = model.particle_count
    q = state.particle_q.numpy().astype(np.float64)
    v = state.particle_qd.numpy().astype(np.float64)
    mass = model.particle_mass.numpy()[0].astype(np.float64)
    free = ~model.kinematic_mask()
    A = np.zeros((3 * n, 3 * n))
    dfdx = np.zeros((3 * n, 3 * n))
    f = np.tile(np.asarray(model.gravity), (n, 1)) * mass[:, None] - model.drag * v
    for (i, j), rest, ke, kd in zip(model.spring_indices.numpy(), model.spring_rest_length.numpy(),
                                    model.spring_stiffness.numpy()[0], model.spring_damping.numpy()[0]):
        d = q[j] - q[i]
        length = np.linalg.norm(d)
        nd = d / length
        f[i] += (ke * (length - rest) + kd * np.dot(v[j] - v[i], nd)) * nd
        f[j] -= (ke * (length - rest) + kd * np.dot(v[j] - v[i], nd)) * nd
        Ks = ke * (np.outer(nd, nd) + max(0.0, 1 - rest / length) * (np.eye(3) - np.outer(nd, nd)))
        block = h * kd * np.outer(nd, nd) + h * h * Ks
        for a, b_ in ((i, i), (j, j)):
            A[3 * a:3 * a + 3, 3 * b_:3 * b_ + 3] += block
            dfdx[3 * a:3 * a + 3, 3 * b_:3 * b_ + 3] -= Ks
        for a, b_ in ((i, j), (j, i)):
            A[3 * a:3 * a + 3, 3 * b_:3 * b_ + 3] -= block
            dfdx[3 * a:3 * a + 3, 3 * b_:3 * b_ + 3] += Ks
    A += np.kron(np.diag(mass + h * model.drag), np.eye(3))
    b = h * (f.ravel() + h * dfdx @ v.ravel())
    keep = np.repeat(free, 3)
    return A[np.ix_(keep, keep)], b[keep], keep


@pytest.mark.parametrize("drag", [0.0, 0.3])
def test_implicit_euler_solves_the_baraff_witkin_system(device, drag):
    """On a perturbed, moving cloth the step's Δv solves the densely assembled system A Δv = b (float64
    NumPy reference with the drag in both A and b, pinned particles filtered) to the CG tolerance,
    within the iteration limit."""
    model, _ = hanging_cloth(device, n=8, precision="float64", drag=drag)
    rng = np.random.default_rng(4)
    state, out = model.state(), model.state()
    state.particle_q.assign(model.particle_q.numpy() + rng.normal(scale=0.02, size=(model.particle_count, 3)))
    state.particle_qd.assign(rng.normal(scale=0.5, size=(model.particle_count, 3)))
    h = 1.0 / 60.0
    integrator = ws.ImplicitEuler(model, cg_tolerance=1e-10, cg_iterations=200)
    integrator.step(state, out, None, h)
    iterations, residual, rhs_norm = integrator.solve_report()
    assert 1 <= iterations < 200 and residual <= 1e-10 * rhs_norm

    A, b, keep = dense_implicit_system(model, state, h)
    assert np.linalg.eigvalsh(A).min() > 0  # the clamped system is positive definite
    delta_v = (out.particle_qd.numpy() - state.particle_qd.numpy()).ravel()
    np.testing.assert_allclose(delta_v[keep], np.linalg.solve(A, b), rtol=0, atol=1e-9 * np.abs(delta_v).max())
    np.testing.assert_array_equal(delta_v[~keep], 0.0)  # pinned particles do not move
    np.testing.assert_allclose(out.particle_q.numpy(), state.particle_q.numpy() + h * out.particle_qd.numpy(), rtol=1e-14)


def test_cg_reaches_its_tolerance_on_the_hanging_cloth(device):
    """Every implicit step of the (float32) hanging cloth converges: ‖r‖ ≤ tol·‖b‖ in fewer than the
    allowed iterations."""
    model, _ = hanging_cloth(device, n=16)
    integrator = ws.ImplicitEuler(model, cg_tolerance=1e-5, cg_iterations=100)
    a, b = model.state(), model.state()
    for _ in range(20):
        integrator.step(a, b, None, 1.0 / 120.0)
        iterations, residual, rhs_norm = integrator.solve_report()
        assert iterations < 100 and residual <= 1e-5 * rhs_norm
        a, b = b, a


@pytest.mark.parametrize("name", list(ws.INTEGRATORS))
def test_float32_and_float64_agree(device, name):
    """The same cloth in float32 and float64 differs by float32 rounding only: ≤ 1e-5 m (≈ 100 float32
    ulps of a 1 m coordinate) after ½ s of swinging. (No collider here: a contact that switches on in one
    precision and not the other is a discontinuity, not a rounding difference.)"""
    results = {}
    for precision in ("float32", "float64"):
        model, _ = hanging_cloth(device, n=8, precision=precision)
        integrator = ws.INTEGRATORS[name](model)
        results[precision] = run_frames(ws.Simulator(model, integrator=integrator, fps=60, substeps=16), 30)
    difference = np.abs(results["float32"] - results["float64"]).max()
    assert 0.0 < difference <= 1e-5


@pytest.mark.parametrize("name", list(ws.INTEGRATORS))
def test_frame_graph_reproduces_the_plain_loop(device, name):
    """A frame captured as a graph (CUDA graph, or Warp's CPU graph) replays bitwise like the uncaptured
    loop, with contacts and, for implicit Euler, the CG loop inside the graph; an odd substep count
    (the frame ends with a copy back into the current state) included."""
    runs = []
    for use_graph in (True, False):
        model, _ = hanging_cloth(device, n=8, sphere=True)
        sim = ws.Simulator(model, integrator=ws.INTEGRATORS[name](model), fps=60, substeps=17, use_graph=use_graph)
        runs.append(run_frames(sim, 20))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert np.isfinite(runs[0]).all()


def test_dopri5_runs_captured_and_reports_an_exhausted_step_budget(device):
    """The adaptive controller runs on the device: a frame of dopri5 steps captures into a graph that
    replays like the uncaptured loop; when a step needs more internal steps than ``max_steps`` allows,
    the frame stops with a SimulationError that names the budget and the tolerance."""
    runs = []
    for use_graph in (True, False):
        model, _ = hanging_cloth(device, n=6)
        integrator = ws.DormandPrince(model, tolerance=1e-5)
        runs.append(run_frames(ws.Simulator(model, integrator=integrator, fps=60, substeps=2, use_graph=use_graph), 5))
        assert integrator.accepted_steps > 10  # it subdivided the 8.3 ms steps
    np.testing.assert_array_equal(runs[0], runs[1])

    model, _ = hanging_cloth(device, n=6)
    sim = ws.Simulator(model, integrator=ws.DormandPrince(model, tolerance=1e-9, max_steps=3), fps=60, substeps=1)
    with pytest.raises(ws.SimulationError, match=r"frame 1: dopri5 needed more than 3 internal steps .*tolerance \(1e-09\)"):
        sim.step_frame()
