"""The tet volume family: forces against its energy, the hydrostatic mode, inversion, energy conservation, every
integrator (float64 references).

Every model here is one regular tet with its six edges as springs and the volume term, in float64 without
gravity (ke and K are values, so the tests share one compiled feature set per integrator).
"""

import math
import os

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.analysis import stability as st
from warpspring.analysis.omega import estimate_omega_max
from warpspring.core.families import element_energies
from warpspring.core.integrators import make_integrator
from warpspring.core.volume import (
    VolumeFamily,
    inverted_tets,
    network_bulk_modulus,
    signed_volumes,
    volume_energy_np,
    volume_gradients,
)

from helpers import ZERO_GRAVITY

EDGE = 0.1  # a [m]
MASS = 0.01  # [kg] per particle
BULK = 1.0e4  # K [Pa]
TET = np.array([[0, 1, 2, 3]])
EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
#: A regular tet of edge EDGE centred at the origin (circumradius a √(3/8)), wound so that V > 0.
REST = np.array([[1.0, 1.0, 1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, -1.0, -1.0]]) * EDGE / (2.0 * math.sqrt(2.0))
REST_VOLUME = EDGE**3 / (6.0 * math.sqrt(2.0))


def tet_model(device, *, ke=0.0, kd=0.0, bulk=BULK, viscosity=0.0, pinned=None, worlds=1, precompute=True):
    """The regular tet at rest (springs of stiffness ``ke`` [N/m], damping ``kd`` [N·s/m], rest lengths a; volume
    term K = ``bulk`` [Pa], kd = ``viscosity`` [Pa·s], its factor precomputed per tet or not), float64, no
    gravity."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles(REST, mass=MASS, pinned=pinned)
    builder.add_springs(EDGES, stiffness=ke, damping=kd, rest_length=EDGE)
    family = builder.add_family(VolumeFamily(precompute=precompute))
    family.add(TET, REST, bulk_modulus=bulk, viscosity=viscosity)
    return builder.finalize(device, precision="float64", worlds=worlds), family


def mirrored(q: np.ndarray) -> np.ndarray:
    """The tet with vertex 3 reflected through the plane of its opposite face (every edge keeps its length)."""
    q = q.copy()
    n = np.cross(q[1] - q[0], q[2] - q[0])
    n /= np.linalg.norm(n)
    q[3] -= 2.0 * np.dot(q[3] - q[0], n) * n
    return q


def test_rest_volume_orientation_and_bulk_modulus():
    """A tet given in either winding is rewound to V₀ > 0; the network's K = E/(3(1 − 2ν)) is 2E/3 at ν = 1/4; a
    flat tet is refused."""
    assert signed_volumes(REST, TET)[0] == pytest.approx(REST_VOLUME, rel=1e-12)
    family = VolumeFamily()
    family.add([[1, 0, 2, 3]], REST, bulk_modulus=1.0)
    np.testing.assert_array_equal(family.tets, [[0, 1, 2, 3]])
    assert family.rest_volume[0] == pytest.approx(REST_VOLUME, rel=1e-12)
    assert network_bulk_modulus(3.0e4) == pytest.approx(2.0e4)
    flat = REST.copy()
    flat[3] = (flat[0] + flat[1] + flat[2]) / 3.0
    with pytest.raises(ws.ConfigError, match="no volume"):
        VolumeFamily().add(TET, flat, bulk_modulus=1.0)


def test_host_stiffness_matrix_is_the_energy_hessian_at_rest():
    """``volume_stiffness_matrix`` (the float64 reference behind the elasticity bench) equals the Hessian of
    ½ (K/V₀)(V - V₀)² at rest by central differences of the NumPy energy (step 1e-5 m: error ~1e-6 relative)."""
    from warpspring.core.volume import volume_stiffness_matrix

    q0 = REST + np.random.default_rng(4).normal(scale=0.1 * EDGE, size=(4, 3))
    rest = signed_volumes(q0, TET)[0]
    matrix = volume_stiffness_matrix(q0, TET, BULK).toarray()
    step, x0 = 1e-5, q0.ravel()
    hessian = np.zeros((12, 12))

    def energy(x):
        return volume_energy_np(x.reshape(4, 3), TET, rest, BULK)[0]

    for i in range(12):
        for j in range(12):
            e = np.zeros((4, 12))
            e[0, i] += step
            e[0, j] += step
            e[1, i] += step
            e[1, j] -= step
            e[2, i] -= step
            e[2, j] += step
            e[3, i] -= step
            e[3, j] -= step
            hessian[i, j] = (energy(x0 + e[0]) - energy(x0 + e[1]) - energy(x0 + e[2]) + energy(x0 + e[3])) / (4 * step**2)
    np.testing.assert_allclose(matrix, hessian, rtol=0, atol=1e-5 * np.abs(matrix).max())


@pytest.mark.parametrize("precompute", [True, False], ids=["precomputed", "per_corner"])
def test_volume_forces_are_minus_the_gradient_of_the_energy(device, precompute):
    """At a random deformation and at an inverted one, the gathered forces equal -∂E/∂x by float64 central
    differences of the family's energy hook (step 1e-7 m: truncation ~1e-14 relative, rounding ~1e-9), and
    -(K (J - 1) + kd J̇) ∇V of the NumPy reference with velocities; the energy hook equals ½ (K/V₀)(V - V₀)²;
    the forces sum to zero and exert no torque. Both gathers: the factor precomputed per tet (the default; every
    other test steps it) and computed by every corner; each corner's gradient from its opposite face."""
    viscosity = 3.0
    model, family = tet_model(device, viscosity=viscosity, precompute=precompute)
    rng = np.random.default_rng(7)
    for q in (REST + rng.normal(scale=0.2 * EDGE, size=(4, 3)), mirrored(REST) + rng.normal(scale=0.01, size=(4, 3))):
        v = rng.normal(size=(4, 3))
        state = model.state()
        state.particle_q.assign(q)
        state.particle_qd.assign(v)
        ws.eval_forces(model, state, None)
        force = state.particle_f.numpy()
        energy = element_energies(model, family, state.particle_q)[0, 0]
        assert energy == pytest.approx(volume_energy_np(q, TET, REST_VOLUME, BULK)[0], rel=1e-12)
        g = volume_gradients(q, TET)[0]
        rate = float(np.sum(g * v))
        pressure = BULK * (signed_volumes(q, TET)[0] / REST_VOLUME - 1.0) + viscosity * rate / REST_VOLUME
        np.testing.assert_allclose(force, -pressure * g, rtol=1e-12, atol=1e-12 * np.abs(force).max())
        np.testing.assert_allclose(force.sum(axis=0), 0.0, atol=1e-12 * np.abs(force).max())
        np.testing.assert_allclose(np.cross(q, force).sum(axis=0), 0.0, atol=1e-12 * np.abs(force).max() * EDGE)
        state.particle_qd.zero_()
        ws.eval_forces(model, state, None)
        elastic = state.particle_f.numpy()
        step = 1e-7
        numeric = np.zeros_like(q)
        for i in range(4):
            for c in range(3):
                energies = []
                for sign in (1.0, -1.0):
                    shifted = q.copy()
                    shifted[i, c] += sign * step
                    energies.append(element_energies(model, family, wp.array(shifted, dtype=wp.vec3d,
                                                                              device=model.device))[0, 0])
                numeric[i, c] = -(energies[0] - energies[1]) / (2.0 * step)
        np.testing.assert_allclose(elastic, numeric, rtol=1e-6, atol=1e-7 * np.abs(elastic).max())
        assert abs(signed_volumes(q, TET)[0] / REST_VOLUME - 1.0) > 0.03  # a change of volume, not only of shape


def test_hydrostatic_compression_rings_at_the_bulk_frequency(device):
    """A regular tet scaled by s about its centre has V = s³V₀, energy ½ K V₀ (s³ - 1)² and kinetic energy ½ (4 m R²) ṡ²
    (R² = 3a²/8): released from s = 1 - δ, its volume oscillates about V₀ at ω² = 9 K V₀ / (4 m R²) = K a / (√2 m).
    Symplectic Euler at ωh = 0.02 has the discrete frequency cos(ω̃h) = 1 - (ωh)²/2; the amplitude δ = 1e-3 shifts
    the period by O(δ²) and the centre of the oscillation by O(δ²) V₀. The advisor's power iteration on the
    Gauss-Newton stiffness (rank one here) gives the same ω exactly, and Gershgorin bounds it from above."""
    model, _ = tet_model(device)
    omega = math.sqrt(BULK * EDGE / (math.sqrt(2.0) * MASS))
    estimate = estimate_omega_max(model)
    assert estimate.omega_max == pytest.approx(omega, rel=1e-6)
    assert estimate.gershgorin >= omega * (1.0 - 1e-9)
    delta = 1e-3
    state = model.state()
    state.particle_q.assign(REST * (1.0 - delta))
    dt = 0.02 / omega
    steps = int(3.5 * 2.0 * math.pi / (omega * dt))
    integrator = make_integrator("symplectic_euler", model)
    a, b = state, model.state()
    volumes = [REST_VOLUME * (1.0 - delta) ** 3]
    for _ in range(steps):
        integrator.step(a, b, None, dt)
        a, b = b, a
        volumes.append(signed_volumes(a.particle_q.numpy(), TET)[0])
    excess = np.array(volumes) - REST_VOLUME
    up = np.flatnonzero((excess[:-1] < 0.0) & (excess[1:] >= 0.0))
    period = float(np.diff(up + excess[up] / (excess[up] - excess[up + 1])).mean()) * dt
    discrete = math.acos(1.0 - 0.5 * (omega * dt) ** 2) / dt
    assert period == pytest.approx(2.0 * math.pi / discrete, rel=1e-4)
    assert 0.5 * (excess.max() + excess.min()) == pytest.approx(0.0, abs=10.0 * delta**2 * REST_VOLUME)
    assert -excess.min() == pytest.approx(3.0 * delta * REST_VOLUME, rel=3.0 * delta)
    # the motion stays a uniform scaling: the edges keep equal lengths
    q = a.particle_q.numpy()
    lengths = np.linalg.norm(q[EDGES[:, 1]] - q[EDGES[:, 0]], axis=1)
    np.testing.assert_allclose(lengths, lengths.mean(), rtol=1e-10)


def test_an_inverted_tet_is_pushed_back(device):
    """A tet with a vertex reflected through its opposite face has every spring at rest (then disturbed by 1 % of
    an edge): with springs alone (world 0: K = 0) it settles inverted, at -V₀; with the volume term (world 1) it
    returns to +V₀ (damped by β = 1/ω of the bulk mode in springs and volume: after 10 of its periods the slowest
    spring mode, ω² = ke/m, has decayed by e^(-10π (ω_s/ω)²) = e^-4.4 and the others by more; they are orthogonal
    to ∇V, so what is left of them changes V only to second order, and V is ±V₀ to 1e-4). (Undisturbed, the tet keeps its symmetry and shrinks
    to an inverted regular tet where springs and volume balance: a saddle of the energy, which any asymmetry
    leaves.)"""
    ke = 100.0
    omega = math.sqrt(BULK * EDGE / (math.sqrt(2.0) * MASS))
    beta = 1.0 / omega
    model, family = tet_model(device, ke=ke, kd=beta * ke, viscosity=beta * BULK, worlds=2)
    family.set_values(bulk_modulus=0.0, viscosity=0.0, world=0)
    np.testing.assert_allclose(family.values("bulk_modulus"), [[0.0], [BULK]])
    np.testing.assert_allclose(family.values("viscosity"), [[0.0], [beta * BULK]])
    start = mirrored(REST)
    assert signed_volumes(start, TET)[0] == pytest.approx(-REST_VOLUME, rel=1e-12)
    start += np.random.default_rng(2).normal(scale=0.01 * EDGE, size=(4, 3))
    state = model.state()
    state.particle_q.assign(np.concatenate([start, start]))
    dt = 0.05 / math.sqrt(omega**2 + 4.0 * ke / MASS)
    integrator = make_integrator("symplectic_euler", model)
    a, b = state, model.state()
    for _ in range(int(10 * 2.0 * math.pi / omega / dt)):
        integrator.step(a, b, None, dt)
        a, b = b, a
    q = a.particle_q.numpy().reshape(2, 4, 3)
    assert signed_volumes(q[0], TET)[0] == pytest.approx(-REST_VOLUME, rel=1e-4)  # springs alone: stays inverted
    assert signed_volumes(q[1], TET)[0] == pytest.approx(REST_VOLUME, rel=1e-4)
    np.testing.assert_array_equal(inverted_tets(a.particle_q.numpy(), family), [1, 0])


def elastic_energy(q: np.ndarray, ke: float) -> float:
    length = np.linalg.norm(q[EDGES[:, 1]] - q[EDGES[:, 0]], axis=1)
    return float(0.5 * ke * ((length - EDGE) ** 2).sum() + volume_energy_np(q, TET, REST_VOLUME, BULK).sum())


def test_velocity_verlet_conserves_the_energy_of_an_undamped_tet_body(device):
    """The tet with springs and the volume term, thrown into a large deformation (random velocities of zero
    momentum; edges strained by up to 75 %): over four periods of its fastest mode velocity Verlet's energy error
    stays bounded and is second order, falling by 4 (measured 3.996, and 4.001 from ωh = 0.025 to 0.0125; ±5 %
    for higher-order terms) when h halves, and below (ωh)² of the energy (measured 1.8e-4 at ωh = 0.05)."""
    ke = 100.0
    model, _ = tet_model(device, ke=ke)
    rng = np.random.default_rng(5)
    v = rng.normal(size=(4, 3))
    v -= v.mean(axis=0)
    omega = math.sqrt(BULK * EDGE / (math.sqrt(2.0) * MASS) + 4.0 * ke / MASS)
    v *= 0.2 * EDGE * omega / np.abs(v).max()
    errors = []
    for omega_h in (0.05, 0.025):
        dt = omega_h / omega
        state = model.state()
        state.particle_qd.assign(v)
        a, b = state, model.state()
        integrator = make_integrator("velocity_verlet", model)
        energy0 = 0.5 * MASS * float((v**2).sum()) + elastic_energy(REST, ke)
        worst = 0.0
        for _ in range(int(round(4.0 * 2.0 * math.pi / omega_h))):
            integrator.step(a, b, None, dt)
            a, b = b, a
            q, qd = a.particle_q.numpy(), a.particle_qd.numpy()
            worst = max(worst, abs(0.5 * MASS * float((qd**2).sum()) + elastic_energy(q, ke) - energy0))
        errors.append(worst / energy0)
    assert errors[0] < 0.05**2
    assert errors[0] / errors[1] == pytest.approx(4.0, rel=0.05)


@pytest.mark.parametrize("integrator", sorted(ws.INTEGRATORS))
def test_every_integrator_steps_the_volume_term_as_its_linear_theory(device, integrator):
    """With three corners pinned, V is linear in the free corner x3 (V - V₀ = ∇₃V · Δx3) and the term is an exact
    damped oscillator along ∇₃V: ω² = K |∇₃V|² / (V₀ m), 2ζω = kd |∇₃V|² / (V₀ m). One step of each fixed-step
    integrator from unit displacement and unit velocity (two worlds) is its amplification matrix R (float64, to
    rounding; implicit Euler's solve with the family's Jacobian-vector product, CG to 1e-14, is exact for a
    linear force); dopri5 (tolerance 1e-13) gives the exact map exp(A h) to its tolerance."""
    zeta, omega_h, amplitude = 0.3, 0.7, 1e-3
    g = volume_gradients(REST, TET)[0, 3]
    omega = math.sqrt(BULK * float(g @ g) / (REST_VOLUME * MASS))
    viscosity = 2.0 * zeta * omega * REST_VOLUME * MASS / float(g @ g)
    model, _ = tet_model(device, viscosity=viscosity, pinned=[True, True, True, False], worlds=2)
    n = g / np.linalg.norm(g)
    q = np.concatenate([REST, REST])
    q[3] += amplitude / omega * n
    qd = np.zeros((8, 3))
    qd[7] = amplitude * n
    state = model.state()
    state.particle_q.assign(q)
    state.particle_qd.assign(qd)
    options = {"implicit_euler": {"cg_tolerance": 1e-14}, "dopri5": {"tolerance": 1e-13}}.get(integrator, {})
    after = model.state()
    make_integrator(integrator, model, **options).step(state, after, None, omega_h / omega)
    x, v = after.particle_q.numpy().reshape(2, 4, 3), after.particle_qd.numpy().reshape(2, 4, 3)
    np.testing.assert_array_equal(x[:, :3], REST[None, :3].repeat(2, axis=0))  # the pins did not move
    measured = np.array([[omega * (x[w, 3] - REST[3]) @ n, v[w, 3] @ n] for w in range(2)]).T / amplitude
    if integrator == "dopri5":
        from scipy.linalg import expm

        expected = expm(np.array([[0.0, omega_h], [-omega_h, -2.0 * zeta * omega_h]]))
        # a local error of 1e-13 m on x3 per internal step is ω·1e-13/amplitude in these units; ten steps at most
        np.testing.assert_allclose(measured, expected, rtol=0, atol=10.0 * omega * 1e-13 / amplitude)
    else:
        # Positions near 0.05 m hold the 1e-3 m/ω displacement to ~1e-12 relative in float64.
        np.testing.assert_allclose(measured, st.amplification_matrix(integrator, omega_h, zeta), rtol=0, atol=1e-10)
    # nothing moved off the line along ∇₃V
    np.testing.assert_allclose(np.cross(x[:, 3] - REST[3], n), 0.0, atol=1e-15)


BAR = os.path.join(os.path.dirname(__file__), "..", "examples", "meshes", "bar.obj")  # 1 × 0.1 × 0.1 m


def bar_scene(**keys) -> dict:
    body = {"mesh": BAR, "method": "delaunay", "spacing": 0.05, "youngs_modulus": 3.0e4, "density": 100.0,
            "damping": 2.0e-3, **keys}
    return {"version": 2, "simulation": {"fps": 60, "frames": 1, "substeps": 10}, "soft_body": [body]}


def test_soft_body_volume_key_wires_its_tets(device):
    """``[[soft_body]] volume = true`` gives the model one volume family holding the body's tets (as particles of
    the model, wound positive), K = 2E/3 and kd = β K per tet; ``bulk_modulus`` sets K. A body without the key
    adds no family (nothing of it compiles or launches)."""
    from warpspring.io.scene import parse_scene

    scene = parse_scene(bar_scene(volume=True))
    model = scene.finalize(device)
    family = next(f for f in model.families if isinstance(f, VolumeFamily))
    assert family.element_count > 0 and f"{family.element_count} volume tets" in model.describe()
    q = model.particle_q.numpy().astype(np.float64)
    np.testing.assert_allclose(signed_volumes(q, family.tets), family.rest_volume, rtol=1e-5)
    assert (family.rest_volume > 0.0).all()
    np.testing.assert_allclose(family.values("bulk_modulus"), 2.0e4, rtol=1e-6)
    np.testing.assert_allclose(family.values("viscosity"), 2.0e-3 * 2.0e4, rtol=1e-6)
    assert family.velocity_dependent(model)
    model = parse_scene(bar_scene(volume=True, bulk_modulus=5.0e5)).finalize(device)
    np.testing.assert_allclose(model.families[-1].values("bulk_modulus"), 5.0e5, rtol=1e-6)
    assert not any(isinstance(f, VolumeFamily) for f in parse_scene(bar_scene()).finalize(device).families)


@pytest.mark.parametrize("keys, message", [
    ({"method": "voxel"}, "needs tets, which the voxel method does not make"),
    ({"bulk_modulus": 1.0e4, "volume": False}, "give volume=True"),
    ({"volume": "yes"}, "volume"),
])
def test_bad_volume_keys_are_named(keys, message):
    """Each mistake is a one-line ConfigError naming the key and the fix."""
    from warpspring.io.scene import parse_scene

    keys = {"volume": True, **keys}
    with pytest.raises(ws.ConfigError, match=message) as info:
        parse_scene(bar_scene(**keys)).builder()
    assert "\n" not in str(info.value)
