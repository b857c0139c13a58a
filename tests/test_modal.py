"""The dense modal reference (``warpspring.analysis.modal``) and the advisor against it.

The reference is checked against closed forms (one damped oscillator under every explicit integrator; a
particle hanging on a spring, whose sideways modes are a pendulum's); the advisor, linearised at the
static equilibrium of a loaded cloth, against the whole linearised system's one-step map in float64.
"""

import math

import numpy as np
import pytest

import warpspring as ws
from warpspring.analysis import load_battery as lb
from warpspring.analysis import modal
from warpspring.analysis import stability as st
from warpspring.analysis.advisor import advise
from warpspring.analysis.damping import top_mode_ratios
from warpspring.analysis.omega import free_particles
from warpspring.analysis.under_load import static_equilibrium
from warpspring.errors import ConfigError

EXPLICIT = ["explicit_euler", "symplectic_euler", "velocity_verlet", "midpoint", "rk4", "dopri5"]


@pytest.mark.parametrize("integrator", EXPLICIT)
def test_step_matrix_of_one_oscillator_is_the_amplification_matrix(integrator):
    """The dense one-step map built from the update equations, for a 1 × 1 system m ẍ + c ẋ + k x = 0, is
    the theory's amplification matrix in the coordinates (ωx, v), to rounding."""
    omega, zeta, h, m = 7.0, 0.03, 0.05, 2.0
    R = st.step_matrix(integrator, h, [m], [[m * omega**2]], [[2.0 * zeta * omega * m]])
    scale = np.diag([omega, 1.0])
    assert np.allclose(scale @ R @ np.linalg.inv(scale), st.amplification_matrix(integrator, omega * h, zeta),
                       rtol=0.0, atol=1e-14)


def test_step_matrix_refuses_implicit_and_misshapen_input():
    with pytest.raises(ConfigError, match="explicit integrators only"):
        st.step_matrix("implicit_euler", 0.01, [1.0], [[1.0]], [[0.0]])
    with pytest.raises(ConfigError, match="shape"):
        st.step_matrix("rk4", 0.01, [1.0, 1.0], [[1.0]], [[0.0]])


def test_hanging_particle_modes_are_a_spring_and_a_pendulum(device):
    """A 0.2 kg particle on a spring (k = 50 N/m, kd = 0.3 N·s/m, L = 0.5 m) below a pin, at its static
    equilibrium l = L + mg/k: one axial mode ω² = k/m with ζ = kd / (2√(km)), and two sideways modes
    ω² = (T/l)/m = g/l (the pendulum of length l) carrying no damping; the drag c adds c/(2mω) to each."""
    m, k, kd, rest, g, c = 0.2, 50.0, 0.3, 0.5, 9.81, 0.01
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -g), drag=c)
    builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -rest]], mass=m, pinned=[0])
    builder.add_springs([[0, 1]], stiffness=k, damping=kd)
    model = builder.finalize(device)
    equilibrium = static_equilibrium(model)
    length = rest + m * g / k
    assert equilibrium.positions[1, 2] == pytest.approx(-length, rel=1e-5)
    modes = modal.linearise(model, equilibrium.positions).modes()
    pendulum, axial = math.sqrt(g / length), math.sqrt(k / m)
    # float32 positions: the equilibrium's ~1e-6 of l carries into T/l = k (1 - L/l) as ~1e-5.
    assert modes.omega == pytest.approx([pendulum, pendulum, axial], rel=1e-4)
    assert modes.zeta == pytest.approx([c / (2 * m * pendulum)] * 2 + [kd / (2 * math.sqrt(k * m)) + c / (2 * m * axial)],
                                       rel=1e-4)


def test_linearise_refuses_what_it_does_not_model(device):
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.1, particle_mass=0.1)
    builder.add_aerodynamics(wind=(0.0, 1.0, 0.0))
    model = builder.finalize(device)
    with pytest.raises(ConfigError, match="linear springs and drag, not .*use the advisor"):
        modal.linearise(model, model.particle_q.numpy())


#: The battery's steps (``load_battery.STEPS``, the first of each) and a horizon for the growth.
STEPS = {name: 1.0 / (lb.FPS * substeps[0]) for name, substeps in lb.STEPS.items()}
HORIZON = 10.0
#: The cloth's stiffness [N/m]: its weight stretches the corner springs by ~20 %.
STIFFNESS = 700.0


@pytest.mark.parametrize("integrator", list(lb.EXPLICIT))
def test_advisor_at_the_equilibrium_is_the_linear_systems_limit(device, integrator):
    """The battery's hanging cloth (8 × 8 here), linearised at its static
    equilibrium. The advisor's step (``transient=False``) against the whole system's one-step map R
    (float64, every coupling of the axial dampers kept):

    * it is the top mode's exact limit, to the power iteration's accuracy (its Rayleigh quotient is within
      ~1e-4 of ω_max², which moves the step by as much: measured 1.8e-5 to 1.8e-4 above);
    * 5 % above it the top mode grows, as one of R's modes (to 1e-7) and its fastest, but for explicit
      Euler, whose undamped transverse modes grow faster still (see below);
    * 5 % below it R grows nothing for the integrators that damp or conserve an undamped mode, and for
      explicit Euler and midpoint exactly what the advisor reports as the transverse modes' growth over
      the horizon (ρ(R)^(T/h), to 1e-6 of its logarithm; measured 1e-8).
    """
    dt = STEPS[integrator]
    model = lb.battery_cloth("hanging", [STIFFNESS], device, n=8)
    advice = advise(model, integrator, dt, fps=lb.FPS, transient=False, horizon=HORIZON)
    positions = static_equilibrium(model).positions
    linear = modal.linearise(model, positions)
    modes = linear.modes()
    exact = st.stable_step(integrator, modes.omega[-1], modes.zeta[-1])
    assert advice.dt_stable == pytest.approx(exact, rel=5e-4)

    above = np.abs(np.linalg.eigvals(linear.step_matrix(integrator, 1.05 * exact)))
    top = modes.growth(integrator, 1.05 * exact, top=1)[0]
    assert top > 1.0
    assert np.abs(above - top).min() <= 1e-7 * top  # the modal picture's top mode is one of R's
    if integrator != "explicit_euler":  # whose undamped transverse modes grow faster still
        assert above.max() == pytest.approx(top, rel=1e-7)

    below = np.abs(np.linalg.eigvals(linear.step_matrix(integrator, 0.95 * exact))).max()
    if integrator in ("explicit_euler", "midpoint"):
        growth = advise(model, integrator, 0.95 * exact, fps=lb.FPS, transient=False,
                           horizon=HORIZON).transverse_growth
        assert growth > 1.0
        assert math.log(growth) == pytest.approx(HORIZON / (0.95 * exact) * math.log(below), rel=1e-6)
    else:
        assert below <= 1.0 + 1e-9


def test_top_mode_ratios_are_the_dense_quotient(device):
    """``top_mode_ratios`` on the dense reference's top mode at the equilibrium is xᵀDx / xᵀKx of its matrices
    (to 1e-9; the springs' axial dampers, no drag): explicit Euler's exact step limit for that mode."""
    model = lb.battery_cloth("hanging", [STIFFNESS], device, n=8)
    q = static_equilibrium(model).positions
    linear = modal.linearise(model, q)
    x = linear.modes().shapes[:, -1]
    full = np.zeros(3 * model.particle_count)
    full[np.repeat(free_particles(model)[0], 3)] = x
    ratio = top_mode_ratios(model, None, [full.reshape(-1, 3)], q)
    assert ratio[0] == pytest.approx((x @ linear.damping @ x) / (x @ linear.stiffness @ x), rel=1e-9)
    assert ratio[0] == pytest.approx(st.stable_step("explicit_euler", linear.modes().omega[-1],
                                                    linear.modes().zeta[-1]), rel=1e-6)


def test_explicit_euler_verdict_holds_below_the_equilibriums_limit(device):
    """Explicit Euler's limit is the top mode's damping ratio xᵀDx / xᵀKx alone. ``--strict``'s verdict (the
    dry run from the equilibrium on) takes the lowest ratio the dry run passes through, so it lies at or below
    the exact limit at the equilibrium, within 2 % (measured 0.7 % below on the 8 × 8 hanging cloth). Taken at
    the peak ω_max alone it was 0.4 % above it: optimistic."""
    model = lb.battery_cloth("hanging", [STIFFNESS], device, n=8)
    modes = modal.linearise(model, static_equilibrium(model).positions).modes()
    exact = st.stable_step("explicit_euler", modes.omega[-1], modes.zeta[-1])
    verdict = advise(model, "explicit_euler", 1e-5, fps=lb.FPS, horizon=2.0).dt_stable
    assert 0.98 * exact <= verdict <= exact


@pytest.mark.parametrize("integrator, factor", [("midpoint", 1.05), ("explicit_euler", 1.05), ("rk4", 1.01),
                                                ("midpoint", 0.85)])
def test_advisor_states_how_fast_the_top_mode_grows(device, integrator, factor):
    """Past its limit the advisor says how much the top mode grows over the run (``Advice.top_growth``, in
    the message): the dense reference's ρ_top^(T/h), to the power iteration's accuracy: the advisor's limit is within 2e-4
    of the exact one, a share 2e-4 / (factor - 1) of the margin that sets the growth rate (2 % at 1 % past
    the limit; 5 % allowed); inside it, a decay."""
    model = lb.battery_cloth("hanging", [STIFFNESS], device, n=8)
    modes = modal.linearise(model, static_equilibrium(model).positions).modes()
    dt = factor * st.stable_step(integrator, modes.omega[-1], modes.zeta[-1])
    advice = advise(model, integrator, dt, fps=lb.FPS, transient=False, horizon=HORIZON)
    exact = HORIZON / dt * math.log(modes.growth(integrator, dt, top=1)[0])
    assert math.log(advice.top_growth) == pytest.approx(exact, rel=0.05)
    if factor > 1.0:
        assert not advice.stable and advice.top_growth > 1.0
        shown = f"{advice.top_growth:.3g}" if advice.top_growth < 1e6 else f"1e{math.log10(advice.top_growth):.0f}"
        assert f"past it their top mode grows ×{shown} over a 10 s run" in advice.message
    else:
        assert advice.stable and advice.top_growth < 1.0


@pytest.mark.parametrize("integrator, factor, steps", [("midpoint", 1.5, 2000), ("midpoint", 0.8, 2000), ("rk4", 1.001, 400)])
def test_the_kernels_follow_the_linear_map(device, integrator, factor, steps):
    """Past the top mode's limit a run is unstable, however slowly it grows; before it, that mode decays.
    The 8 × 8 hanging cloth in float64, at its static equilibrium plus 1e-8 m along its top mode, run by
    the integrator's kernels at ``factor`` × the exact limit: after ``steps`` steps its state is R^steps of
    the start's (R the dense one-step map), to the nonlinearity's share (∝ the amplitude: at 1e-8 m
    measured 4e-6 to 1.8e-4 of the state, 10× that at 1e-7 m), and the top mode's amplitude has changed by the theory's ρ^steps
    (×11.9 and ×0.76 for midpoint, ×17.6 for RK4 just 0.1 % past its limit), to the modal picture's
    coupling through the dampers (measured 2e-3; 1 %)."""
    model = lb.battery_cloth("hanging", [STIFFNESS], device, n=8, precision="float64")
    equilibrium = static_equilibrium(model, tolerance=1e-13, max_steps=2000)
    assert equilibrium.converged
    linear = modal.linearise(model, equilibrium.positions)
    modes = linear.modes()
    omega, shape = modes.omega[-1], modes.shapes[:, -1]
    dt = factor * st.stable_step(integrator, omega, modes.zeta[-1])
    growth = modes.growth(integrator, dt, top=1)[0] ** steps
    assert growth > 10.0 if factor > 1.0 else growth < 0.8

    free = np.repeat(free_particles(model)[0], 3)
    start = 1e-8 * shape / np.abs(shape).max()
    q = equilibrium.positions.reshape(-1).copy()
    q[free] += start
    state, scratch = model.state(), model.state()
    state.particle_q.assign(q.reshape(-1, 3))
    integrator_ = ws.make_integrator(integrator, model)
    for _ in range(steps):
        integrator_.step(state, scratch, None, dt)
        state, scratch = scratch, state
    n = len(start)
    measured = np.concatenate([state.particle_q.numpy().reshape(-1)[free] - equilibrium.positions.reshape(-1)[free],
                               state.particle_qd.numpy().reshape(-1)[free]])
    predicted = np.linalg.matrix_power(linear.step_matrix(integrator, dt), steps) @ np.concatenate([start, np.zeros(n)])
    weight = np.concatenate([np.full(n, omega), np.ones(n)])  # (ωx, v): both in m/s
    assert np.linalg.norm(weight * (measured - predicted)) <= 1e-3 * np.linalg.norm(weight * predicted)

    def amplitude(u):  # of the top mode, in (ωx, v)
        return math.hypot(omega * shape @ (linear.mass * u[:n]), shape @ (linear.mass * u[n:]))

    initial = amplitude(np.concatenate([start, np.zeros(n)]))
    assert amplitude(measured) / initial == pytest.approx(amplitude(predicted) / initial, rel=1e-4)
    assert amplitude(predicted) / initial == pytest.approx(growth, rel=0.01)


@pytest.mark.parametrize("start", [10.0, 1.0e4])
def test_top_mode_limit_brackets_from_either_side(start):
    """The bisection finds the stiffness where the 8 × 8 cloth's top mode turns unstable under midpoint at
    1/960 s, whether it starts below the limit or above it: stable there, growing 2 × rtol above."""
    dt, rtol = 1.0 / 960.0, 1.0e-2

    def at(ke):
        model = lb.battery_cloth("hanging", [ke], "cpu", n=8)
        return modal.linearise(model, static_equilibrium(model).positions)

    limit = modal.top_mode_limit(at, "midpoint", dt, start=start, rtol=rtol)
    assert at(limit).modes().growth("midpoint", dt, top=1)[0] <= 1.0
    assert at(limit * (1.0 + 2.0 * rtol)).modes().growth("midpoint", dt, top=1)[0] > 1.0


@pytest.mark.parametrize("scene", ["hanging", "forced"])
def test_top_modes_at_the_equilibrium_are_the_dense_top_mode(device, scene):
    """At a static equilibrium of springs and drag, the top mode frozen there (the springs' sparse tangent's
    top eigenvector, ω and ζ by central differences of the model's own forces along it) is the dense
    reference's highest mode: ω to 1e-9, ζ to 1e-6 (measured 3e-11 and 8e-9), in each of two worlds."""
    model = lb.battery_cloth(scene, [STIFFNESS, 300.0], device, n=8, precision="float64")
    control = lb.battery_control(scene, model)
    q = static_equilibrium(model, control=control).positions
    top = modal.top_modes(model, q, np.zeros_like(q), 0.0, control=control)
    for world in range(2):
        modes = modal.linearise(model, q, world=world).modes()
        assert top.omega[world] == pytest.approx(modes.omega[-1], rel=1e-9)
        assert top.zeta[world] == pytest.approx(modes.zeta[-1], rel=1e-6)
    assert top.growth("midpoint", 1.0 / 960.0) == pytest.approx(
        [modal.linearise(model, q, world=w).modes().growth("midpoint", 1.0 / 960.0, top=1)[0] for w in range(2)],
        rel=1e-10)


def test_top_modes_take_a_handle_along_the_mode(device):
    """The battery's *pulled* cloth at its start (flat, unstretched, at rest; the PD handle on its bottom row
    on target, so not capped): the springs' top mode x, and the whole model's ω² and 2ζω along it are the
    springs' xᵀKx and xᵀDx plus the handle's Kp and Kd times x's share on the handled particles, to the
    differences' rounding (1e-9)."""
    model = lb.battery_cloth("pulled", [STIFFNESS], device, n=8, precision="float64")
    state = model.state()
    q = state.particle_q.numpy()
    top = modal.top_modes(model, q, state.particle_qd.numpy(), 0.0)
    x = top.shapes[0].reshape(-1)
    K, D = modal.spring_tangent(model, q)
    handled = (x.reshape(-1, 3)[:8] ** 2).sum()  # row 0, the handle's 8 particles
    assert handled * 20.0 > 1e-5 * top.omega[0] ** 2  # the handle's share (8e-5 of ω²) is far above 1e-9
    assert top.omega[0] ** 2 == pytest.approx(x @ K @ x + 20.0 * handled, rel=1e-9)
    assert 2.0 * top.zeta[0] * top.omega[0] == pytest.approx(x @ D @ x + 0.5 * handled, rel=1e-9)


def test_top_modes_refuse_what_they_cannot_follow(device):
    model = lb.battery_cloth("hanging", [STIFFNESS], device, n=4)
    q = model.particle_q.numpy()
    with pytest.raises(ConfigError, match="needs float64"):
        modal.top_modes(model, q, np.zeros_like(q), 0.0)
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.1, particle_mass=0.1)
    builder.add_hinges([[0, 4, 1, 3]], stiffness=1.0)
    model = builder.finalize(device, precision="float64")
    q = model.particle_q.numpy()
    with pytest.raises(ConfigError, match="springs' top mode, with wind and handles along it; this model has hinges"):
        modal.top_modes(model, q, np.zeros_like(q), 0.0)


def test_top_modes_growth_is_undefined_where_a_world_has_no_mode():
    """A world whose state was not finite, or torn apart (no stiffness along its mode), has no growth: NaN,
    not an error, so that a grid's other worlds are still judged."""
    top = modal.TopModes(omega=np.array([np.nan, 200.0, np.nan]), zeta=np.array([np.nan, 0.002, np.nan]),
                         shapes=np.zeros((3, 1, 3)))
    growth = top.growth("midpoint", 1.0 / 960.0)
    assert np.isnan(growth[[0, 2]]).all()
    assert growth[1] == pytest.approx(st.spectral_radius("midpoint", 200.0 / 960.0, 0.002), rel=1e-15)


@pytest.mark.parametrize("low, high, grows", [(0.1, 1.3, True), (0.6, 1.6, False)])
def test_the_kernels_follow_the_frozen_growth(device, low, high, grows):
    """The measure behind :func:`load_battery.frozen_growth`, against the kernels, on a system whose top mode
    changes along the run: a 0.1 kg particle hanging on a 400 N/m spring (no damper) in a drag that follows
    a keyframe track between ``low`` and ``high`` × ζ*, midpoint's limit damping at ωh = 0.2, every 0.5 s. The
    frozen ρ of its axial mode (``top_modes`` at each step's state and time) crosses 1 twice a cycle; over 3 s
    the kernels' axial amplitude, started 1e-6 m from the equilibrium, changes by Π ρ to 1e-3 (measured 4e-5
    and 2e-4), so it grows or decays as the mean of log ρ says, not as its peak or its trough."""
    m, k, rest, g = 0.1, 400.0, 0.5, 9.81
    omega = math.sqrt(k / m)
    h = 0.2 / omega
    zstar = modal.log_bisect(lambda z: st.spectral_radius("midpoint", 0.2, z) > 1.0, 1e-6, 0.1, 1e-9)
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -g))
    below = rest + m * g / k  # the equilibrium
    builder.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, -below - 1e-6]], mass=m, pinned=[0])
    builder.add_springs([[0, 1]], stiffness=k, rest_length=rest)
    drag = [[2.0 * m * omega * f * zstar] for f in (low, high, low)]
    builder.set_track("drag", ws.Track([0.0, 0.25, 0.5], drag, interpolation="smooth", extrapolation="cycle"))
    model = builder.finalize(device, precision="float64")
    integrator = ws.make_integrator("midpoint", model)
    state, scratch = model.state(), model.state()
    logs, growth = [], []
    for _ in range(int(round(3.0 / h))):
        top = modal.top_modes(model, state.particle_q.numpy(), state.particle_qd.numpy(), state.time.numpy())
        growth.append(top.growth("midpoint", h)[0])
        integrator.step(state, scratch, None, h)
        state, scratch = scratch, state
    assert min(growth) < 1.0 < max(growth)
    x = state.particle_q.numpy()[1, 2] + below
    measured = math.hypot(omega * x, state.particle_qd.numpy()[1, 2]) / (omega * 1e-6)
    predicted = math.exp(np.log(growth).sum())
    assert measured == pytest.approx(predicted, rel=1e-3)
    assert (predicted > 1.0) == grows


@pytest.mark.parametrize("scene", ["hanging", "windy"])
def test_frozen_growth_finds_the_runs_that_grow(device, scene):
    """The battery's cloth under midpoint at 1/960 s, 2 s runs at 0.93× and 1.07× its equilibrium's linear
    limit (694.9 N/m): neither blows up, but the top mode frozen at the states of the runs' second half
    decays on average in the first and grows in the second (the hanging cloth's runs cross over within
    0.6 % of the equilibrium's limit over 10 s; the windy one's within 0.3 %)."""
    ke = np.array([0.93, 1.07]) * 694.9
    outcome = lb.blow_ups(scene, "midpoint", 16, ke, device, 2.0, sample_every=6)
    assert not outcome.blown.any() and len(outcome.samples) == 10
    growth = lb.frozen_growth(scene, "midpoint", 1.0 / 960.0, ke, outcome.samples)
    assert growth[0] < 1.0 < growth[1]


def test_battery_table_gives_the_lowest_limit():
    """A case's limit is the lowest of its 10 s blow-up, its linear limit at the equilibrium and the stiffness
    from which its run's top mode grows; the table adds those columns where some case has one, a dash where
    one has none."""
    hanging = lb.LoadCase(scene="hanging", integrator="midpoint", substeps=16, dt=1 / 960, blow_up=1111.0,
                          passed=668.6, unsafe=0, torn=0.0, runs=64, seconds=1.0, linear=694.9, grows=700.0)
    windy = lb.LoadCase(scene="windy", integrator="midpoint", substeps=16, dt=1 / 960, blow_up=1138.0,
                        passed=668.6, unsafe=0, torn=0.0, runs=64, seconds=1.0, grows=690.0)
    driven = lb.LoadCase(scene="driven", integrator="rk4", substeps=4, dt=1 / 240, blow_up=6421.0, passed=5922.0,
                         unsafe=0, torn=0.0, runs=64, seconds=1.0)
    assert hanging.limit == 694.9 and hanging.ratio_to_limit == pytest.approx(668.6 / 694.9)
    assert windy.limit == 690.0 and windy.ratio_to_limit == pytest.approx(668.6 / 690.0)
    assert driven.limit == 6421.0 and driven.ratio_to_limit == pytest.approx(5922.0 / 6421.0)
    lines = lb.table([hanging, windy, driven])
    assert lines[0].endswith("| unstable at equilibrium from | top mode grows along the run from | passed but grows "
                             "| ratio to the lowest |")
    assert lines[2].endswith("| 0.602 | 0 | 694.9 N/m | 700 N/m | 0 | 0.962 |")
    assert lines[3].endswith("| 0 | – | 690 N/m | 0 | 0.969 |")
    assert lines[4].endswith("| 0 | – | – | – | 0.922 |")
    assert lines[-1] == ("Against the lowest of the blow-up and the linear limits: 0.922 … 0.969; worlds the advisor "
                         "passed whose top mode grows along the run: 0.")
    assert "unstable at equilibrium" not in lb.table([driven])[0]
