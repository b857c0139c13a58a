"""Stabilizers: biphasic springs, force and speed clamps, Provot strain limiting."""

import functools

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from helpers import run_frames
from warpspring.kernels.spring_laws import SpringLaw, spring_funcs
from warpspring.kernels.inputs import INPUT_COUNT, INPUTS

# A law is its switches; its values come from the live-input table, as in the simulation's kernels.
BIPHASIC = (SpringLaw(biphasic=True), {"biphasic_strain": 0.2, "biphasic_ratio": 4.0})
HOOKE = (SpringLaw(), {})


@functools.cache
def law_kernel(law):
    spring_law_values, spring_force, spring_energy, spring_stiffness_matrix = spring_funcs(wp.float64, law)

    @wp.kernel(module="unique", enable_backward=False)
    def kernel(
        xi: wp.array[wp.vec3d],
        xj: wp.array[wp.vec3d],
        vj: wp.array[wp.vec3d],
        rest: float,
        ke: float,
        kd: float,
        inputs: wp.array2d[wp.float64],
        force: wp.array[wp.vec3d],
        energy: wp.array[wp.float64],
        stiffness: wp.array[wp.mat33d],
    ):
        t = wp.tid()
        values = spring_law_values(inputs, 0)
        force[t] = spring_force(
            xi[t], xj[t], wp.vec3d(), vj[t], wp.float64(rest), wp.float64(ke), wp.float64(kd), values
        )
        energy[t] = spring_energy(xi[t], xj[t], wp.float64(rest), wp.float64(ke), values)
        stiffness[t] = spring_stiffness_matrix(xi[t], xj[t], wp.float64(rest), wp.float64(ke), False, values)

    return kernel


def evaluate_law(device, law, xi, xj, vj, rest=1.0, ke=10.0, kd=0.0):
    switches, values = law
    table = np.zeros((1, INPUT_COUNT))
    for name, value in values.items():
        table[0, INPUTS[name][0]] = value
    n = len(xi)
    out = [wp.empty(n, dtype=wp.vec3d, device=device), wp.empty(n, dtype=wp.float64, device=device),
           wp.empty(n, dtype=wp.mat33d, device=device)]
    arrays = [wp.array(a, dtype=wp.vec3d, device=device) for a in (xi, xj, vj)]
    inputs = wp.array(table, dtype=wp.float64, device=device)
    wp.launch(law_kernel(switches), dim=n, inputs=[*arrays, rest, ke, kd, inputs], outputs=out, device=device)
    return [a.numpy() for a in out]


def test_biphasic_law_force_energy_and_jacobian(device):
    """Beyond the knee (1 + ε)L the tension grows with stiffness r·ke: T = ke s + (r-1) ke max(s - εL, 0);
    the force is -∂E/∂x_i of the energy and the stiffness matrix is its Jacobian (central differences)."""
    rng = np.random.default_rng(8)
    n = 40
    xi = rng.uniform(-1, 1, (n, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    length = rng.uniform(0.7, 1.6, n)  # compressed, below and beyond the knee at 1.2
    xj = xi + direction * length[:, None]
    force, energy, stiffness = evaluate_law(device, BIPHASIC, xi, xj, np.zeros((n, 3)))
    stretch = length - 1.0
    tension = 10.0 * stretch + 3.0 * 10.0 * np.maximum(stretch - 0.2, 0.0)
    np.testing.assert_allclose(force, direction * tension[:, None], rtol=1e-12, atol=1e-12)
    assert (length > 1.2).sum() > 5 and (length < 1.0).sum() > 5

    eps = 1e-6
    for c in range(3):
        step = np.zeros(3)
        step[c] = eps
        e_plus = evaluate_law(device, BIPHASIC, xi, xj + step, np.zeros((n, 3)))[1]
        e_minus = evaluate_law(device, BIPHASIC, xi, xj - step, np.zeros((n, 3)))[1]
        f_plus = evaluate_law(device, BIPHASIC, xi, xj + step, np.zeros((n, 3)))[0]
        f_minus = evaluate_law(device, BIPHASIC, xi, xj - step, np.zeros((n, 3)))[0]
        np.testing.assert_allclose(force[:, c], (e_plus - e_minus) / (2 * eps), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(stiffness[:, :, c], (f_plus - f_minus) / (2 * eps), rtol=1e-5, atol=1e-5)


def test_spring_force_clamp_bounds_elastic_plus_damping(device):
    """With max_force F every spring's force has magnitude ≤ F along d̂, whatever its stretch or speed."""
    law = (SpringLaw(clamp_force=True), {"max_spring_force": 2.5})
    rng = np.random.default_rng(9)
    n = 64
    xi, xj = rng.uniform(-1, 1, (n, 3)), rng.uniform(-1, 1, (n, 3))
    vj = rng.normal(scale=5.0, size=(n, 3))
    force = evaluate_law(device, law, xi, xj, vj, kd=3.0)[0]
    plain = evaluate_law(device, HOOKE, xi, xj, vj, kd=3.0)[0]
    magnitude = np.linalg.norm(force, axis=1)
    assert magnitude.max() <= 2.5 * (1 + 1e-12) and (np.linalg.norm(plain, axis=1) > 2.5).sum() > 10
    clamped = np.linalg.norm(plain, axis=1) > 2.5
    np.testing.assert_allclose(force[clamped], plain[clamped] * (2.5 / np.linalg.norm(plain[clamped], axis=1))[:, None])
    np.testing.assert_allclose(force[~clamped], plain[~clamped])


@pytest.mark.parametrize("law", [
    (SpringLaw(clamp_force=True), {"max_spring_force": 2.5}),
    (SpringLaw(biphasic=True, clamp_force=True), {"biphasic_strain": 0.2, "biphasic_ratio": 4.0, "max_spring_force": 2.5}),
    (SpringLaw(biphasic=True, clamp_force=True), {"biphasic_strain": 0.2, "biphasic_ratio": 4.0, "max_spring_force": 4.0}),
], ids=["hooke", "biphasic, clamped below the knee", "biphasic, clamped beyond the knee"])
def test_clamped_spring_energy_is_the_potential_of_its_force(device, law):
    """With the force clamp (no damping) the elastic force is -∂E/∂x of the family's energy, compressed,
    stretched below the clamp and far beyond it (central differences): the guard's energy balance holds
    for clamped springs."""
    rng = np.random.default_rng(10)
    n = 60
    xi = rng.uniform(-1, 1, (n, 3))
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    length = rng.uniform(0.5, 1.9, n)  # the clamp (2.5 N at ke = 10) binds beyond |s| = 0.25 (and the knee)
    xj = xi + direction * length[:, None]
    zero = np.zeros((n, 3))
    force = evaluate_law(device, law, xi, xj, zero)[0]
    assert (np.linalg.norm(force, axis=1) >= law[1]["max_spring_force"] * (1 - 1e-12)).sum() > 10
    eps = 1e-6
    for c in range(3):
        step = np.zeros(3)
        step[c] = eps
        e_plus = evaluate_law(device, law, xi, xj + step, zero)[1]
        e_minus = evaluate_law(device, law, xi, xj - step, zero)[1]
        np.testing.assert_allclose(force[:, c], (e_plus - e_minus) / (2 * eps), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("evaluation", ["gather", "scatter"])
def test_particle_force_clamp(device, evaluation):
    """With max_particle_force F every total force above F is scaled down to magnitude F, direction kept,
    and the others are untouched, by either spring evaluation."""
    def forces(stabilizers):
        builder = ws.ModelBuilder(stabilizers=stabilizers)
        builder.add_cloth_grid(nx=6, ny=5, spacing=0.1, mass=1.0, structural=ws.SpringMaterial(200.0, 1.0))
        model = builder.finalize(device, spring_evaluation=evaluation)
        state = model.state()
        rng = np.random.default_rng(1)
        state.particle_q.assign(model.particle_q.numpy() + rng.normal(scale=0.03, size=(model.particle_count, 3)))
        ws.eval_forces(model, state, None)
        return state.particle_f.numpy().astype(np.float64)

    plain = forces(ws.Stabilizers())
    magnitude = np.linalg.norm(plain, axis=1)
    ordered = np.sort(magnitude)
    half = len(ordered) // 2
    limit = float(0.5 * (ordered[half - 1] + ordered[half]))  # half the particles get clamped, none is at the limit
    clamped = forces(ws.Stabilizers(max_particle_force=limit))
    big = magnitude > limit
    assert big.sum() >= 10 and (~big).sum() >= 10
    # Float32 sums of ~12 springs; on CUDA the scatter's atomics add them in a varying order.
    tolerance = dict(rtol=0, atol=1e-5 * magnitude.max())
    np.testing.assert_allclose(clamped[big], plain[big] * (limit / magnitude[big])[:, None], **tolerance)
    np.testing.assert_allclose(clamped[~big], plain[~big], **tolerance)


def test_speed_clamp(device):
    """A particle falling under gravity with max_speed 2 m/s reaches 2 m/s after 2/g s and then falls at
    exactly that speed."""
    builder = ws.ModelBuilder(stabilizers=ws.Stabilizers(max_speed=2.0))
    builder.add_particles([[0.0, 0.0, 10.0]], mass=1.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=16)
    x = run_frames(sim, 60)[0]
    np.testing.assert_allclose(sim.state.particle_qd.numpy()[0], [0.0, 0.0, -2.0], rtol=1e-6)
    t_reach = 2.0 / 9.81
    expected_drop = 0.5 * 9.81 * t_reach**2 + 2.0 * (1.0 - t_reach)
    assert abs((10.0 - x[2]) - expected_drop) < 9.81 * sim.dt  # first-order error of the kink


def soft_cloth(device, stabilizers, n=12):
    """A soft cloth pinned at two corners: plain springs stretch it far past 10 % (super-elasticity)."""
    builder = ws.ModelBuilder(stabilizers=stabilizers)
    soft = ws.SpringMaterial(50.0, 0.5)
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(0, 0, 2), particle_mass=0.05, structural=soft,
                           shear=soft, bend=ws.SpringMaterial(5.0, 0.05), pin=["top-left", "top-right"])
    return builder.finalize(device)


def peak_strain(model, frames, substeps=16):
    """Largest spring strain over ``frames`` frames, sampled every frame."""
    sim = ws.Simulator(model, fps=60, substeps=substeps)
    pairs, rest = model.spring_indices.numpy(), model.spring_rest_length.numpy()
    peak = 0.0
    for _ in range(frames):
        x = run_frames(sim, 1)
        peak = max(peak, float((np.linalg.norm(x[pairs[:, 1]] - x[pairs[:, 0]], axis=1) / rest - 1).max()))
    return peak


def test_strain_limiting_caps_strain_where_plain_springs_overstretch(device):
    """Provot strain limiting at 10 % with 16 Jacobi passes keeps every spring within 10.5 % of its rest
    length at every frame, where the same cloth without it stretches by more than 100 %."""
    assert peak_strain(soft_cloth(device, ws.Stabilizers()), 60) > 1.0
    limited = peak_strain(soft_cloth(device, ws.Stabilizers(max_strain=0.1, strain_iterations=16)), 60)
    assert limited <= 0.105


def test_biphasic_springs_reduce_peak_strain(device):
    """Springs 10× stiffer beyond 10 % strain cut the cloth's peak strain at least fourfold (stable at this
    step: the advisor's ω uses the stiff branch)."""
    plain = peak_strain(soft_cloth(device, ws.Stabilizers()), 60)
    stiffening = soft_cloth(device, ws.Stabilizers(biphasic_strain=0.1, biphasic_ratio=10.0))
    assert ws.advise(stiffening, "symplectic_euler", 1.0 / (60 * 16)).stable  # judged at the stiff branch
    biphasic = peak_strain(stiffening, 60)
    assert biphasic < plain / 4


def test_strain_limiting_respects_pins_and_gravity_equilibrium(device):
    """A hanging chain whose springs would stretch by 49-245 % hangs with every spring at the 5 % cap
    when limited there: the pinned top stays fixed, the corrections fall on the free ends."""
    n, spacing = 6, 0.1
    builder = ws.ModelBuilder(drag=0.5, stabilizers=ws.Stabilizers(max_strain=0.05, strain_iterations=32))
    q = np.zeros((n, 3))
    q[:, 2] = 1.0 - spacing * np.arange(n)
    builder.add_particles(q, mass=0.1, pinned=[0])
    builder.add_springs(np.stack([np.arange(n - 1), np.arange(1, n)], 1), stiffness=20.0)
    model = builder.finalize(device)
    x = run_frames(ws.Simulator(model, fps=60, substeps=16), 120)
    strain = -np.diff(x[:, 2]) / spacing - 1
    np.testing.assert_allclose(x[0], q[0])
    assert strain.max() <= 0.05 + 1e-4
    assert strain[0] >= 0.05 - 1e-3  # the top spring is held at the cap, not below it


def test_strain_limiting_splits_the_correction_by_inverse_mass(device):
    """A 1 kg and a 3 kg particle at rest, 1.5 L apart on a force-free spring: one pass brings the spring
    to exactly 1.1 L, the light particle taking w₁/(w₁+w₂) = 3/4 of the 0.4 L correction and the heavy one
    1/4, so the centre of mass stays put; each velocity is its displacement / dt."""
    dt, rest = 1.0e-3, 1.0
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0), stabilizers=ws.Stabilizers(max_strain=0.1, strain_iterations=1))
    builder.add_particles([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0]], mass=np.array([1.0, 3.0]))
    builder.add_springs([[0, 1]], stiffness=0.0, rest_length=rest)
    model = builder.finalize(device)
    a, b = model.state(), model.state()
    ws.make_integrator("symplectic_euler", model).step(a, b, None, dt)
    x, v = b.particle_q.numpy().astype(np.float64), b.particle_qd.numpy().astype(np.float64)
    np.testing.assert_allclose(x[:, 0], [0.3, 1.4], atol=1e-6)
    np.testing.assert_allclose(x[:, 1:], 0.0, atol=1e-7)
    np.testing.assert_allclose(v[:, 0], [0.3 / dt, -0.1 / dt], rtol=1e-4)
    assert abs(1.0 * x[0, 0] + 3.0 * x[1, 0] - 4.5) < 1e-5
