"""Spring laws per spring group: linear, square (T = k Δ|Δ|) and a compression branch of its own stiffness.

Every test here uses one law specialisation (square and asymmetric on, float64), so the kernels compile once
for the module: the linear springs of a scene are linear springs of that specialisation.
"""

import functools
import math

import numpy as np
import pytest
import scipy.integrate
import scipy.special
import warp as wp

import warpspring as ws
from warpspring.analysis.omega import world_gershgorin_omega_max
from warpspring.core.families import element_energies
from warpspring.core.integrators import make_integrator
from warpspring.kernels.inputs import INPUT_COUNT
from warpspring.kernels.spring_laws import SpringLaw, spring_funcs

LAW = SpringLaw(square=True, asymmetric=True)
G = 9.81


def reference_tension(stretch, ke, square, ratio):
    """T(Δ) [N] in float64: k Δ or k Δ|Δ|, k = ke in tension and ratio · ke in compression."""
    k = np.where(stretch < 0.0, ratio * ke, ke)
    return np.where(square, k * stretch * np.abs(stretch), k * stretch)


def reference_energy(stretch, ke, square, ratio):
    """∫₀^Δ T [J] in float64: ½ k Δ² or k |Δ|³ / 3."""
    k = np.where(stretch < 0.0, ratio * ke, ke)
    return np.where(square, k * np.abs(stretch) ** 3 / 3.0, 0.5 * k * stretch**2)


@functools.cache
def law_kernel():
    spring_law_values, spring_force, spring_energy, spring_stiffness_matrix = spring_funcs(wp.float64, LAW)

    @wp.kernel(module="unique", enable_backward=False)
    def kernel(
        xi: wp.array[wp.vec3d],
        xj: wp.array[wp.vec3d],
        square: wp.array[wp.int32],
        ratio: wp.array[wp.float64],
        rest: float,
        ke: float,
        inputs: wp.array2d[wp.float64],
        force: wp.array[wp.vec3d],
        energy: wp.array[wp.float64],
        stiffness: wp.array[wp.mat33d],
    ):
        t = wp.tid()
        values = spring_law_values(inputs, 0)
        values.square = square[t]
        values.compression_ratio = ratio[t]
        zero = wp.vec3d()
        force[t] = spring_force(xi[t], xj[t], zero, zero, wp.float64(rest), wp.float64(ke), wp.float64(0.0), values)
        energy[t] = spring_energy(xi[t], xj[t], wp.float64(rest), wp.float64(ke), values)
        stiffness[t] = spring_stiffness_matrix(xi[t], xj[t], wp.float64(rest), wp.float64(ke), False, values)

    return kernel


def evaluate(device, xi, xj, square, ratio, *, rest=1.0, ke=10.0):
    n = len(xi)
    out = [wp.empty(n, dtype=wp.vec3d, device=device), wp.empty(n, dtype=wp.float64, device=device),
           wp.empty(n, dtype=wp.mat33d, device=device)]
    inputs = [wp.array(xi, dtype=wp.vec3d, device=device), wp.array(xj, dtype=wp.vec3d, device=device),
              wp.array(square.astype(np.int32), dtype=wp.int32, device=device),
              wp.array(ratio, dtype=wp.float64, device=device)]
    table = wp.zeros((1, INPUT_COUNT), dtype=wp.float64, device=device)
    wp.launch(law_kernel(), dim=n, inputs=[*inputs, rest, ke, table], outputs=out, device=device)
    return [a.numpy() for a in out]


def test_each_law_force_energy_and_tangent_against_float64(device):
    """Linear, square, and both with a compression branch (ratio 0.25 or 3), stretched and compressed: the
    force is T(Δ) d̂ and the energy ∫T (float64 closed forms, to rounding); the force is -∂E/∂x_i (= ∂E/∂x_j) and the
    stiffness matrix ∂f_i/∂x_j its Jacobian by central differences (step 1e-6 m: truncation ~1e-12,
    rounding ~1e-10 of values ~10)."""
    rng = np.random.default_rng(11)
    n = 64
    xi = rng.uniform(-1, 1, (n, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    length = rng.uniform(0.5, 1.6, n)
    xj = xi + direction * length[:, None]
    square = np.arange(n) % 2 == 1
    ratio = np.where(np.arange(n) % 4 < 2, 1.0, np.where(np.arange(n) % 8 < 4, 0.25, 3.0))
    force, energy, stiffness = evaluate(device, xi, xj, square, ratio)
    stretch = length - 1.0
    np.testing.assert_allclose(force, direction * reference_tension(stretch, 10.0, square, ratio)[:, None],
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(energy, reference_energy(stretch, 10.0, square, ratio), rtol=1e-12, atol=1e-14)
    assert (stretch < 0).sum() > 10 and (stretch > 0).sum() > 10
    eps = 1e-6
    for c in range(3):
        step = np.zeros(3)
        step[c] = eps
        f_plus, e_plus, _ = evaluate(device, xi, xj + step, square, ratio)
        f_minus, e_minus, _ = evaluate(device, xi, xj - step, square, ratio)
        # f_i = -∂E/∂x_i = ∂E/∂x_j (E depends on x_j - x_i only).
        np.testing.assert_allclose(force[:, c], (e_plus - e_minus) / (2 * eps), rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(stiffness[:, :, c], (f_plus - f_minus) / (2 * eps), rtol=1e-6, atol=1e-7)
    # The square law's axial tangent is 2k|Δ| on its branch.
    axial = np.einsum("ni,nij,nj->n", direction, stiffness, direction)
    k = np.where(stretch < 0, ratio * 10.0, 10.0)
    np.testing.assert_allclose(axial[square], (2.0 * k * np.abs(stretch))[square], rtol=1e-12)


def mixed_network(device, *, evaluation="auto", worlds=1):
    """A random network of 60 particles whose springs come in three groups: linear, square, and linear with
    a compression stiffness of 0.3 ke; rest lengths 0.6-1.4 times the built distances (stretched and
    compressed springs of every group)."""
    rng = np.random.default_rng(5)
    n = 60
    q = rng.uniform(-1.0, 1.0, (n, 3))
    builder = ws.ModelBuilder()
    builder.add_particles(q, velocities=rng.normal(scale=0.5, size=(n, 3)), mass=rng.uniform(0.5, 2.0, n))
    pairs = np.unique(np.sort(rng.integers(0, n, (300, 2)), axis=1), axis=0)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    groups = np.array_split(pairs, 3)
    for group, options in zip(groups, ({}, {"law": "square"}, {"compression_stiffness": 3.0})):
        distance = np.linalg.norm(q[group[:, 1]] - q[group[:, 0]], axis=1)
        builder.add_springs(group, stiffness=10.0, damping=0.2, rest_length=distance * rng.uniform(0.6, 1.4, len(group)),
                            **options)
    model = builder.finalize(device, precision="float64", spring_evaluation=evaluation, worlds=worlds)
    model.gravity = (0.0, 0.0, 0.0)
    return model, groups


def test_laws_forces_are_minus_the_gradient_of_the_family_energy_gathered_and_scattered(device):
    """On the three-group network, the gathered forces equal the scattered ones (float64, to rounding) and,
    with the dampers' share removed (velocities zero), -∂E/∂x of the family's energy hook by central
    differences (step 1e-6 m); the model compiles the square and asymmetric switches and reads the laws
    from the per-spring arrays."""
    gathered, _ = mixed_network(device, evaluation="gather")
    scattered, _ = mixed_network(device, evaluation="scatter")
    assert gathered.spring_law == LAW
    forces = []
    for model in (gathered, scattered):
        state = model.state()
        state.particle_qd.zero_()
        ws.eval_forces(model, state, None)
        forces.append(state.particle_f.numpy())
    np.testing.assert_allclose(forces[0], forces[1], rtol=1e-12, atol=1e-12)
    model = gathered
    family = model.families[0]
    q = model.particle_q.numpy()
    numeric = np.zeros_like(q)
    step = 1e-6
    rows = range(0, model.particle_count, 4)
    for i in rows:
        for c in range(3):
            energies = []
            for sign in (1.0, -1.0):
                shifted = q.copy()
                shifted[i, c] += sign * step
                probe = wp.array(shifted, dtype=model.vec3, device=model.device)
                energies.append(element_energies(model, family, probe).sum())
            numeric[i, c] = -(energies[0] - energies[1]) / (2.0 * step)
    picked = list(rows)
    np.testing.assert_allclose(forces[0][picked], numeric[picked], rtol=1e-6, atol=1e-8 * np.abs(forces[0]).max())


def square_pair(device, *, ke, mass, rest, stretch):
    """Particle 0 pinned at the origin, particle 1 free at (rest + stretch, 0, 0), one square spring; and two
    pinned particles joined by a spring with a compression branch, which acts on nothing but gives the
    model the module's law specialisation (no new compile)."""
    builder = ws.ModelBuilder()
    builder.add_particles(np.array([[0.0, 0.0, 0.0], [rest + stretch, 0.0, 0.0], [0.0, 5.0, 0.0], [1.0, 5.0, 0.0]]),
                          mass=mass, pinned=[True, False, True, True])
    builder.add_springs([[0, 1]], stiffness=ke, rest_length=rest, law="square")
    builder.add_springs([[2, 3]], stiffness=ke, compression_stiffness=0.5 * ke)
    model = builder.finalize(device, precision="float64")
    model.gravity = (0.0, 0.0, 0.0)
    return model


def test_implicit_euler_linearises_the_square_law_at_its_tangent(device):
    """One implicit Euler step of a square spring (Baraff-Witkin: one linearisation) equals the float64
    closed form of the linearised step along the spring, v⁺ = v + h (f + h f' v) / (m - h² f'), with
    f = -k Δ|Δ| and f' = -2k|Δ| the law's tangent; with Hooke's tangent k the step would differ by 20 %."""
    ke, mass, rest, stretch, h = 400.0, 0.1, 1.0, 0.05, 0.02
    model = square_pair(device, ke=ke, mass=mass, rest=rest, stretch=stretch)
    integrator = make_integrator("implicit_euler", model, cg_tolerance=1e-14, cg_iterations=20)
    a, b = model.state(), model.state()
    integrator.step(a, b, None, h)
    f, slope = -ke * stretch * abs(stretch), -2.0 * ke * abs(stretch)
    v = h * f / (mass - h * h * slope)
    x = rest + stretch + h * v
    got_q, got_v = b.particle_q.numpy()[1], b.particle_qd.numpy()[1]
    assert got_v[0] == pytest.approx(v, rel=1e-10)
    assert got_q[0] == pytest.approx(x, rel=1e-12)
    np.testing.assert_allclose(got_q[1:], 0.0, atol=1e-15)
    assert model.spring_law == LAW
    hooke = h * f / (mass + h * h * ke)
    assert abs(hooke - v) > 0.2 * abs(v)


def test_tension_compression_and_square_chains_sag_by_the_closed_form(device):
    """Three vertical chains of 6 particles (0.05 kg, 0.1 m apart) under gravity, brought to rest by implicit
    Euler steps of 0.05 s (a static solve): a hanging linear chain with ke = 400 N/m
    and kc = 100 N/m stretches spring i by W_i / ke (W_i the weight below it; the compression branch unused); a
    standing column of the same springs, pinned at its foot, shortens by W_i / kc; a hanging square chain
    (k = 2e4 N/m²) stretches by √(W_i / k)."""
    n, a, m, ke, kc, k2 = 6, 0.1, 0.05, 400.0, 100.0, 2.0e4
    builder = ws.ModelBuilder(up_axis="Z")
    hanging = builder.add_particles(np.stack([np.zeros(n), np.zeros(n), -a * np.arange(n)], axis=1), mass=m,
                                    pinned=np.arange(n) == 0)
    column = builder.add_particles(np.stack([np.ones(n), np.zeros(n), a * np.arange(n)], axis=1), mass=m,
                                   pinned=np.arange(n) == 0)
    square = builder.add_particles(np.stack([2 * np.ones(n), np.zeros(n), -a * np.arange(n)], axis=1), mass=m,
                                   pinned=np.arange(n) == 0)
    links = lambda ids: np.stack([ids[:-1], ids[1:]], axis=1)  # noqa: E731
    builder.add_springs(links(hanging), stiffness=ke, compression_stiffness=kc, damping=0.5)
    builder.add_springs(links(column), stiffness=ke, compression_stiffness=kc, damping=0.5)
    builder.add_springs(links(square), stiffness=k2, damping=0.5, law="square")
    model = builder.finalize(device, precision="float64")
    integrator = make_integrator("implicit_euler", model, cg_tolerance=1e-14, cg_iterations=100)
    a_state, b_state = model.state(), model.state()
    for _ in range(150):  # the error shrinks ~1000-fold per 40 steps (measured): 1e-7 after 80, passes at 120
        integrator.step(a_state, b_state, None, 0.05)
        a_state, b_state = b_state, a_state
    z = a_state.particle_q.numpy()[:, 2]
    below = m * G * np.arange(n - 1, 0, -1)  # the weight each spring holds, from the top (or foot)
    np.testing.assert_allclose(-np.diff(z[hanging]), a + below / ke, rtol=1e-9)
    np.testing.assert_allclose(np.diff(z[column]), a - below / kc, rtol=1e-9)
    np.testing.assert_allclose(-np.diff(z[square]), a + np.sqrt(below / k2), rtol=1e-9)
    assert np.abs(a_state.particle_qd.numpy()).max() < 1e-9


def square_period(ke, mass, amplitude):
    """The period [s] of m ẍ = -k x|x| from rest at x = A, by quadrature of T = 4 ∫₀^A dx / v(x) with
    ½ m v² = k (A³ - |x|³) / 3 (its closed form 4 √(3m / (2kA)) B(1/3, 1/2) / 3)."""
    integral, _ = scipy.integrate.quad(lambda u: 1.0 / math.sqrt(1.0 - u**3), 0.0, 1.0, limit=200)
    return 4.0 * math.sqrt(3.0 * mass / (2.0 * ke * amplitude)) * integral


def test_square_oscillator_period_by_quadrature_at_rk4_order(device):
    """A mass on a square spring released at stretch A returns to A after one period T (by quadrature): RK4
    over T in N = 64 and 128 equal steps misses A by errors that fall at least 2⁴-fold per halving, RK4's
    order (measured: 1.1e-7 m and 3.4e-9 m, ratio 32; asserted ≥ 12; the law's x|x| is only C¹ at the
    crossings, which RK4 passes without losing its order), and by less than 1e-5 A at N = 128."""
    ke, mass, rest, amplitude = 3.0e3, 0.2, 1.0, 0.1
    period = square_period(ke, mass, amplitude)
    quad_closed = 4.0 * math.sqrt(3.0 * mass / (2.0 * ke * amplitude)) * scipy.special.beta(1 / 3, 1 / 2) / 3.0
    assert period == pytest.approx(quad_closed, rel=1e-12)
    model = square_pair(device, ke=ke, mass=mass, rest=rest, stretch=amplitude)
    errors = []
    for steps in (64, 128):
        integrator = make_integrator("rk4", model)
        a, b = model.state(), model.state()
        for _ in range(steps):
            integrator.step(a, b, None, period / steps)
            a, b = b, a
        errors.append(abs(a.particle_q.numpy()[1, 0] - (rest + amplitude)))
    assert errors[0] / errors[1] >= 12.0
    assert errors[1] < 1e-5 * amplitude


def test_advisor_takes_the_square_law_tangent_at_the_state(device):
    """One free particle on a square spring: the advisor linearises at a state's stretch Δ, where the axial
    stiffness is the tangent 2k|Δ| (the transverse one, kΔ²/l, is lower): the Gershgorin bound at the
    model's initial stretch is √(2k|Δ|/m) exactly (its diagonal block; the neighbour is pinned), the same
    rows at rest are 0 (a square spring at rest adds nothing), and a doubled stretch doubles the row. (The
    power iteration's product is the family hook implicit Euler uses, checked against the tangent above.)"""
    ke, mass, rest, stretch = 500.0, 0.1, 1.0, 0.08
    model = square_pair(device, ke=ke, mass=mass, rest=rest, stretch=stretch)
    omega = math.sqrt(2.0 * ke * stretch / mass)
    assert world_gershgorin_omega_max(model)[0] == pytest.approx(omega, rel=1e-12)
    family = model.families[0]
    free = np.array([[False, True, False, False]])
    positions = model.particle_q.numpy().astype(np.float64)
    for factor, expected in ((0.0, 0.0), (1.0, 2.0 * ke * stretch), (2.0, 4.0 * ke * stretch)):
        positions[1, 0] = rest + factor * stretch
        assert family.gershgorin_rows(model, free, positions=positions)[0, 1] == pytest.approx(expected, rel=1e-12)
    np.testing.assert_allclose(family.tangent_factor(model)[0], [2.0 * stretch, 1.0], rtol=1e-12)
