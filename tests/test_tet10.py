"""The quadratic (T10) neo-Hookean tet family: its mesh, masses and skin, its forces against its energy and the float64
references, its stiffness at rest against linear elasticity integrated independently, the product against its host
matrix, rigid motions, the integrators, the guard, checkpoints and USD, and the cantilever and cube against their
closed forms (where linear tets lock).

Device models are float64 with the builder's default gravity (one compiled feature set for the file).
"""

import math

import numpy as np
import pytest
import trimesh
import warp as wp

import warpspring as ws
from warpspring.analysis import softbody_elasticity as se
from warpspring.analysis.omega import estimate_omega_max, gershgorin_omega_max
from warpspring.core import softbody as sb
from warpspring.core import tet10 as t10
from warpspring.core.families import element_energies
from warpspring.core.soft_topologies import signed_volumes
from warpspring.kernels.neohookean import stable_lame

E, NU = 1.0e5, 0.3  # [Pa], [-]
MU, LAM = stable_lame(E, NU)
MASS = 0.01  # [kg] per particle
G = np.array([0.0, 0.0, -9.81])  # [m/s²], the builder's default gravity
#: An irregular tet (edges 0.05 … 0.12 m) made quadratic: 10 particles.
CORNERS = np.array([[0.0, 0.0, 0.0], [0.1, 0.01, -0.02], [0.03, 0.09, 0.01], [0.02, 0.03, 0.11]])
REST, TET = t10.quadratic_tets(CORNERS, np.array([[0, 1, 2, 3]]))


def tet_model(device, *, damping=0.0, positions=REST, tets=TET, precompute=True, worlds=1):
    """Particles at ``positions`` (MASS each) joined by T10 ``tets`` (E, NU, β = ``damping`` [s]), float64."""
    builder = ws.ModelBuilder()
    builder.add_particles(positions, mass=MASS)
    family = builder.add_family(t10.QuadraticTetFamily(precompute=precompute))
    family.add(tets, positions, youngs_modulus=E, poisson_ratio=NU, damping=damping)
    return builder.finalize(device, precision="float64", worlds=worlds), family


def forces(model, q, v=None):
    """The families' forces [N] at positions q and velocities v (default 0), gravity taken off."""
    state = model.state()
    state.particle_q.assign(q)
    state.particle_qd.assign(np.zeros_like(q) if v is None else v)
    ws.eval_forces(model, state, None)
    return state.particle_f.numpy() - MASS * G


def quadratic_field(x, seed=0, scale=0.02):
    """A displacement u(x) [m] quadratic in x (random seeded coefficients), shape like x."""
    rng = np.random.default_rng(seed)
    a, b = rng.normal(scale=scale, size=(3, 3)), rng.normal(scale=scale, size=(3, 6))
    quad = np.stack([x[..., 0] ** 2, x[..., 1] ** 2, x[..., 2] ** 2, x[..., 0] * x[..., 1], x[..., 1] * x[..., 2],
                     x[..., 0] * x[..., 2]], axis=-1) / 0.1  # [m²] / 0.1 m: comparable to the linear part
    return x @ a.T + quad @ b.T


# -- mesh, masses, skin ---------------------------------------------------------------------------------------------


def test_mesh_masses_and_skin():
    """The mid-edge nodes are one per unique edge, at its middle; the consistent mass's row sums are the corners'
    −1/20 and the edges' 1/5 of the tet's mass (why it can not be lumped by rows), and the HRZ shares are its
    diagonal (6/420, 32/420) scaled to the mass: 1/36 and 4/27, positive, summing to the body's volume. The skin of
    a Delaunay box (vertices that are particles) and of a box embedded in fTetWild tets follows the quadratic
    field: moved by a quadratic displacement field, the skin's points are the vertices moved by that field (to
    rounding: T10 interpolates quadratics exactly)."""
    box = trimesh.creation.box((0.2, 0.2, 0.2))
    linear = se.box_topology("delaunay", (0.2, 0.2, 0.2), youngs_modulus=E, spacing=0.1)
    quadratic = t10.quadratic_topology(linear)
    tets = quadratic.tets
    ends = np.unique(np.sort(linear.tets[:, t10.EDGES].reshape(-1, 2), axis=1), axis=0)
    assert len(quadratic.positions) == len(linear.positions) + len(ends)
    x = quadratic.positions
    np.testing.assert_allclose(x[tets[:, 4:]], 0.5 * (x[tets[:, t10.EDGES[:, 0]]] + x[tets[:, t10.EDGES[:, 1]]]),
                               atol=1e-15)
    assert (signed_volumes(x, tets[:, :4]) > 0.0).all()
    mass = t10.consistent_mass_np(x, tets, 1000.0)
    tet_mass = 1000.0 * signed_volumes(x, tets[:, :4])
    np.testing.assert_allclose(mass.sum(axis=2) / tet_mass[:, None], [[-1 / 20] * 4 + [1 / 5] * 6] * len(tets),
                               rtol=1e-12)
    diagonal = np.diagonal(mass, axis1=1, axis2=2)
    np.testing.assert_allclose(diagonal / diagonal.sum(axis=1, keepdims=True),
                               [[t10.CORNER_SHARE] * 4 + [t10.EDGE_SHARE] * 6] * len(tets), rtol=1e-12)
    assert (quadratic.volume > 0.0).all()
    assert quadratic.volume.sum() == pytest.approx(box.volume, rel=1e-12)
    tetrahedral = pytest.importorskip("pytetwild") and se.box_topology("tetrahedral", (0.3, 0.2, 0.2), youngs_modulus=E,
                                                                        spacing=0.1, element="tet10")
    for topology in (quadratic, tetrahedral):
        np.testing.assert_allclose(topology.skin_weights.sum(axis=1), 1.0, atol=1e-12)
        vertices = np.einsum("vj,vjk->vk", topology.skin_weights, topology.positions[topology.skin_indices])
        moved = topology.positions + quadratic_field(topology.positions)
        skin = np.einsum("vj,vjk->vk", topology.skin_weights, moved[topology.skin_indices])
        np.testing.assert_allclose(skin, vertices + quadratic_field(vertices), atol=1e-14)


# -- the element ----------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def power_kernel():
    """A kernel writing the family's dissipation hook per element (float64), per spec."""
    cache = {}

    def get(spec):
        if spec not in cache:
            funcs = spec.funcs(wp.float64)

            @wp.kernel(module="unique", enable_backward=False)
            def power(arrays: funcs.arrays, inputs: wp.array2d[wp.float64], q: wp.array[wp.vec3d],
                      qd: wp.array[wp.vec3d], out: wp.array[wp.float64]):
                t = wp.tid()
                out[t] = funcs.dissipation(0, t, 0, arrays, inputs, q, qd)

            cache[spec] = power
        return cache[spec]

    return get


@pytest.mark.parametrize("precompute", [True, False], ids=["precomputed", "per_node"])
def test_forces_are_minus_the_gradient_of_the_energy(device, power_kernel, precompute):
    """At a large quadratic deformation (J at the Gauss points ≈ 0.8 … 1.2, with shear and bending), the gathered
    forces equal −∂E/∂x by float64 central differences of the energy hook (step 1e-7 m: truncation
    ~(1e-7/0.05)² ~ 1e-11 relative, rounding ~1e-16 · E/1e-7 ~ 1e-9), the energy hook equals the host reference, and
    with velocities the forces equal the float64 reference −Σ_q ¼V₀ P_q ∇N_a − β (K̃ v)_a; they sum to zero and exert
    no torque (the damper included); the dissipation hook is the damper's power −Σ f_damp·v > 0. Both gathers."""
    beta = 2.0e-3
    model, family = tet_model(device, damping=beta, precompute=precompute)
    rng = np.random.default_rng(3)
    q = REST + quadratic_field(REST, seed=1, scale=0.1) + rng.normal(scale=0.003, size=REST.shape)
    v = rng.normal(size=REST.shape)
    state = model.state()
    state.particle_q.assign(q)
    energy = element_energies(model, family, state.particle_q)[0, 0]
    assert energy == pytest.approx(t10.tet10_energy_np(q, REST, TET, MU, LAM)[0], rel=1e-12)
    elastic = forces(model, q)
    numeric = np.zeros_like(q)
    step = 1e-7
    for i in range(10):
        for c in range(3):
            e = []
            for sign in (1.0, -1.0):
                shifted = q.copy()
                shifted[i, c] += sign * step
                e.append(element_energies(model, family, wp.array(shifted, dtype=wp.vec3d, device=model.device))[0, 0])
            numeric[i, c] = -(e[0] - e[1]) / (2.0 * step)
    np.testing.assert_allclose(elastic, numeric, rtol=0, atol=1e-7 * np.abs(elastic).max())
    full = forces(model, q, v)
    reference = t10.tet10_forces_np(q, v, REST, TET, MU, LAM, beta)
    np.testing.assert_allclose(full, reference, rtol=0, atol=1e-11 * np.abs(reference).max())
    np.testing.assert_allclose(full.sum(axis=0), 0.0, atol=1e-11 * np.abs(full).max())
    np.testing.assert_allclose(np.cross(q, full).sum(axis=0), 0.0, atol=1e-12 * np.abs(full).max())
    out = wp.zeros(1, dtype=wp.float64, device=model.device)
    wp.launch(power_kernel(family.spec(model)), dim=1, inputs=[family.arrays(model), model.inputs,
              wp.array(q, dtype=wp.vec3d, device=model.device), wp.array(v, dtype=wp.vec3d, device=model.device)],
              outputs=[out], device=model.device)
    damper = full - elastic
    assert out.numpy()[0] == pytest.approx(-float(np.sum(damper * v)), rel=1e-10)
    assert out.numpy()[0] > 0.0


def _degree_three_energy(x, tets, u, mu_l, lam_l):
    """½ uᵀKu of linear elasticity for a displacement u given at the T10 nodes, integrated by the degree-3 rule
    (centroid −4/5, the points (½, ⅙, ⅙, ⅙) 9/20; independent of the family's four-point rule): exact for T10, whose
    strain energy density is quadratic."""
    points = np.array([[0.25] * 4] + [[1 / 6] * 4 for _ in range(4)])
    points[1:] += np.eye(4) / 3.0
    weights = np.array([-0.8] + [0.45] * 4)
    total = 0.0
    for tet in tets:
        grads = t10.quadratic_shape_gradients(t10.linear_gradients(x, tet[None]), points)[0]  # [q, 10, 3]
        h = np.einsum("ai,qaj->qij", u[tet], grads)
        eps = 0.5 * (h + np.swapaxes(h, 1, 2))
        density = mu_l * (eps**2).sum(axis=(1, 2)) + 0.5 * lam_l * np.trace(eps, axis1=1, axis2=2) ** 2
        total += signed_volumes(x, tet[None, :4])[0] * (weights @ density)
    return total


def test_stiffness_at_rest_is_linear_elasticity(device):
    """At rest the forces vanish, and their Jacobian (float64 central differences, step 1e-8 m: truncation
    ~(1e-8/0.05)², rounding ~1e-16/1e-8 of K's scale) is the host K̃ (``tet10_stiffness``), which is linear
    elasticity of (E, ν) (Lamé μ, λ − μ) on T10: its energy ½uᵀK̃u of random quadratic fields on a Delaunay box (6
    elements) equals the strain energy integrated by an independent degree-3 rule (both exact for quadratic fields: to
    rounding)."""
    model, _ = tet_model(device)
    scale = E * signed_volumes(CORNERS, TET[:, :4])[0] ** (1.0 / 3.0)  # [N/m]
    np.testing.assert_allclose(forces(model, REST), 0.0, atol=1e-13 * scale)
    step = 1e-8
    jacobian = np.zeros((30, 30))
    for k in range(30):
        plus, minus = REST.copy(), REST.copy()
        plus.reshape(-1)[k] += step
        minus.reshape(-1)[k] -= step
        jacobian[:, k] = -(forces(model, plus) - forces(model, minus)).reshape(-1) / (2.0 * step)
    host = t10.tet10_stiffness(REST, REST, TET, MU, LAM).toarray()
    np.testing.assert_allclose(jacobian, host, rtol=0, atol=1e-6 * np.abs(host).max())
    box = t10.quadratic_topology(se.box_topology("delaunay", (0.2, 0.2, 0.2), youngs_modulus=E, spacing=0.1))
    stiffness = t10.tet10_stiffness(box.positions, box.positions, box.tets, MU, LAM)
    for seed in range(3):
        u = quadratic_field(box.positions, seed=seed, scale=1e-3)
        expected = _degree_three_energy(box.positions, box.tets, u, MU, LAM - MU)
        assert 0.5 * u.ravel() @ (stiffness @ u.ravel()) == pytest.approx(expected, rel=1e-12)


def test_rigid_motions_and_the_product(device):
    """A rigidly rotated and moved element has no energy and no force (to rounding); the advisor's power iteration
    (the product hook, α = 1, β = 0) finds √λ_max(M⁻¹K̃) of the host matrix at a deformed state (to its tolerance), the
    state matters, and the Gershgorin bound lies above it at the initial positions; E and ν written for world 1 alone
    scale its forces as the reference with its own μ, λ."""
    model, family = tet_model(device, worlds=2)
    axis = np.array([1.0, -2.0, 0.5]) / np.linalg.norm([1.0, -2.0, 0.5])
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    rotation = np.eye(3) + math.sin(2.1) * k + (1.0 - math.cos(2.1)) * k @ k
    moved = REST @ rotation.T + [0.3, -0.2, 0.7]
    scale = MU * signed_volumes(CORNERS, TET[:, :4])[0] / 0.05  # [N] per unit strain
    np.testing.assert_allclose(forces(model, np.concatenate([moved, moved]))[:10], 0.0, atol=1e-13 * scale)
    state = model.state()
    state.particle_q.assign(np.concatenate([moved, moved]))
    assert abs(element_energies(model, family, state.particle_q)[0, 0]) < 1e-14 * scale

    q = REST + quadratic_field(REST, seed=4, scale=0.05)
    state.particle_q.assign(np.concatenate([q, q]))

    def omega_max(positions):
        return math.sqrt(np.linalg.eigvalsh(t10.tet10_stiffness(positions, REST, TET, MU, LAM).toarray() / MASS).max())

    estimate = estimate_omega_max(model, state=state, tolerance=1e-8, max_iterations=5000)
    assert estimate.omega_max == pytest.approx(omega_max(q), rel=1e-6)
    assert abs(omega_max(q) / omega_max(REST) - 1.0) > 1e-3
    assert gershgorin_omega_max(model) >= omega_max(REST) * (1.0 - 1e-9)

    family.set_values(youngs_modulus=3.0 * E, poisson_ratio=0.1, world=1)
    f = forces(model, np.concatenate([q, q])).reshape(2, 10, 3)
    zero = np.zeros_like(q)
    np.testing.assert_allclose(f[0], t10.tet10_forces_np(q, zero, REST, TET, MU, LAM), atol=1e-11 * np.abs(f[0]).max())
    np.testing.assert_allclose(f[1], t10.tet10_forces_np(q, zero, REST, TET, *stable_lame(3.0 * E, 0.1)),
                               atol=1e-11 * np.abs(f[1]).max())


# -- bodies -----------------------------------------------------------------------------------------------------------


def cube_body(builder, *, damping=2.0e-3, pin_bottom=True):
    """A seeded Delaunay cube (0.2 m, spacing 0.1 m) of T10s, E = 1 MPa, ρ = 1000 kg/m³, its bottom face pinned."""
    body = builder.add_soft_body(trimesh.creation.box((0.2, 0.2, 0.2)), method="delaunay", youngs_modulus=1.0e6,
                                 density=1000.0, spacing=0.1, damping=damping, elasticity="neohookean",
                                 poisson_ratio=NU, element="tet10")
    x = body.topology.positions
    bottom = x[:, 2] < x[:, 2].min() + 1e-9
    if pin_bottom:
        builder.pin_particles(body.particles[bottom])
    return body, bottom


def test_resting_cube_settles_to_the_linear_static_solve(device):
    """The T10 cube with its bottom pinned, under gravity, stepped by implicit Euler (h = 2 ms, β = 2 ms; the product
    hook is its matrix) for 1 s, rests where the float64 static solve with the family's stiffness at rest (linear
    elasticity on T10, lumped masses) puts it. Tolerance 2ρgh/E of the largest displacement: the strain is ρgh/E ≈
    2e-3 and the nonlinear terms the linear solve leaves out are of that order relative to u."""
    builder = ws.ModelBuilder()
    body, bottom = cube_body(builder)
    model = builder.finalize(device, precision="float64")
    assert body.element == "tet10" and body.spring_count == 0 and body.stiffness_rule.startswith("quadratic")
    x = body.topology.positions
    force = np.zeros_like(x)
    force[:, 2] = -9.81 * sb.distribute_mass(body.topology, body.mass)
    expected = sb.static_displacement(body.topology, force, np.repeat(bottom[:, None], 3, axis=1),
                                      stiffness=se.body_stiffness(body.topology, elasticity="neohookean",
                                                                  youngs_modulus=1.0e6, poisson_ratio=NU))
    integrator = ws.make_integrator("implicit_euler", model, cg_tolerance=1e-10)
    a, b = model.state(), model.state()
    for _ in range(500):
        integrator.step(a, b, None, 2.0e-3)
        a, b = b, a
    u = a.particle_q.numpy() - x
    scale = np.abs(expected).max()
    assert scale > 1e-5
    np.testing.assert_allclose(u, expected, rtol=0, atol=2.0 * 1000.0 * 9.81 * 0.2 / 1.0e6 * scale)


def test_the_guard_balances_and_a_checkpoint_continues(device, tmp_path):
    """The T10 cube, free, set vibrating (random velocities of zero mean), damper on (β = 0.2 ms: ζ ≈ 0.03 at its
    slowest mode), falling for 0.25 s of velocity Verlet (ω_max h ≤ 0.1 by the Gershgorin bound): the guard's energy
    (kinetic + the energy hook), work and dissipation (the dissipation hook) balance to the integrator's error,
    bounded by (ωh)²/4 of the vibration's energy E₀ at the balance's first check (measured 2e-5 of it), while the
    damper took out more than a tenth of E₀ (measured 0.67), so without its power the balance fails. A checkpoint
    saved at frame 10 and loaded into a fresh simulator of the same scene continues bit for bit."""
    def simulator():
        builder = ws.ModelBuilder()
        body, _ = cube_body(builder, damping=2.0e-4, pin_bottom=False)
        model = builder.finalize(device, precision="float64")
        substeps = int(np.ceil(gershgorin_omega_max(model) / 0.1 / 60.0))
        return body, ws.Simulator(model, integrator=ws.make_integrator("velocity_verlet", model), fps=60,
                                  substeps=substeps)

    body, sim = simulator()
    velocity = np.random.default_rng(1).normal(scale=0.5, size=(body.particle_count, 3))
    velocity -= velocity.mean(axis=0)
    sim.state.particle_qd.assign(velocity)
    assert sim.guard.counts_dissipation
    for _ in range(10):
        sim.step_frame()
    path = sim.save_checkpoint(tmp_path / "run.npz")
    for _ in range(5):
        sim.step_frame()
    balance = sim.guard.energy_balance()
    internal = balance.reference[0]  # the vibration's energy at the balance's first check, a frame in (measured 1.0 J)
    assert balance.dissipated[0] > 0.1 * internal
    assert abs(balance.created[0]) < 0.25 * 0.1**2 * internal
    _, fresh = simulator()
    fresh.load_checkpoint(path)
    for _ in range(5):
        fresh.step_frame()
    np.testing.assert_array_equal(fresh.state.particle_q.numpy(), sim.state.particle_q.numpy())
    np.testing.assert_array_equal(fresh.state.particle_qd.numpy(), sim.state.particle_qd.numpy())


def test_usd_skin_follows_the_quadratic_field(tmp_path):
    """The exported surface of a T10 box is its authored mesh moved by the quadratic field: with the particles moved
    by a quadratic displacement, the written points are the authored vertices moved by it (float32 rounding)."""
    from pxr import Usd, UsdGeom

    from warpspring.io.usd import UsdWriter

    box = trimesh.creation.box((0.2, 0.2, 0.2))
    builder = ws.ModelBuilder()
    body = builder.add_soft_body(box, method="delaunay", youngs_modulus=E, density=1000.0, spacing=0.1,
                                 elasticity="neohookean", element="tet10", name="box")
    model = builder.finalize("cpu")
    state = model.state()
    x = body.topology.positions
    state.particle_q.assign(x + quadratic_field(x, seed=2))
    path = tmp_path / "out.usda"
    with UsdWriter(path, model, fps=30.0) as writer:
        writer.write_frame(state)
    stage = Usd.Stage.Open(str(path))
    points = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/World/box")).GetPointsAttr().Get(0), dtype=np.float64)
    np.testing.assert_allclose(points, box.vertices + quadratic_field(np.asarray(box.vertices), seed=2), atol=2e-7)


@pytest.mark.parametrize("keys, message", [
    ({"element": "tet20"}, "element must be one of tet4, tet10"),
    ({"element": "tet10", "elasticity": "springs"}, "give elasticity='neohookean' with it"),
])
def test_bad_element_keys_are_named(keys, message):
    """Each mistake is a one-line ConfigError naming the key and the fix; a Delaunay mesh with flat gaps (a box's
    regular surface points leave coplanar quads whose flat tets are dropped, triangulated differently on each side:
    6 here) is refused for T10, whose mid-edge nodes there would not join up (``crack_count``)."""
    options = {"elasticity": "neohookean", "spacing": 0.1, **keys}
    with pytest.raises(ws.ConfigError, match=message) as info:
        ws.ModelBuilder().add_soft_body(trimesh.creation.box((0.3, 0.2, 0.2)), method="delaunay", youngs_modulus=E,
                                        density=1000.0, **options)
    assert "\n" not in str(info.value)
    cracked = se.box_topology("delaunay", (0.3, 0.2, 0.2), youngs_modulus=E, spacing=0.1)
    assert t10.crack_count(cracked.tets) == 6
    with pytest.raises(ws.ConfigError, match="flat gap") as info:
        t10.quadratic_topology(cracked)
    assert "\n" not in str(info.value)


# -- against the closed forms ---------------------------------------------------------------------------------------


def test_cantilever_bends_and_rings_right_where_linear_tets_lock():
    """The issue's cantilever (1 × 0.1 × 0.1 m, E = 1 MPa, ν = 0.3, ρ = 1000 kg/m³, clamped, g/100) on fTetWild's tets
    at 3 across, float64 static and modal solves with lumped masses: T10 within 3 % of Timoshenko's tip deflection
    (14.865 mm) and first bending frequency (0.5069 Hz; measured −0.5 … −1.0 % and +0.2 … +0.5 % over builds at 3
    and 4 across, bench/results/softbody_tet10.md; the −1 % that stays is the solid's clamp against the beam's), while
    linear tets on the same mesh lock (more than 10 % too stiff; measured −18 %). The 1-D Timoshenko model reproduces
    the closed-form tip qL⁴/(8EI) + qL²/(2κGA) to 1e-6."""
    pytest.importorskip("pytetwild")
    g = 9.81 / 100.0
    tip, frequency = se.timoshenko_cantilever(length=1.0, side=0.1, youngs_modulus=1.0e6, poisson_ratio=NU,
                                              density=1000.0, gravity=g)
    q, inertia, kappa = 1000.0 * g * 0.01, 1.0e-4 / 12.0, 10.0 * (1.0 + NU) / (12.0 + 11.0 * NU)
    closed = q / (8.0 * 1.0e6 * inertia) + q / (2.0 * kappa * 1.0e6 / (2.0 * (1.0 + NU)) * 0.01)
    assert tip == pytest.approx(closed, rel=1e-6)
    assert tip == pytest.approx(14.86e-3, abs=0.01e-3)  # the number
    linear = se.box_topology("tetrahedral", (1.0, 0.1, 0.1), youngs_modulus=1.0e6, spacing=0.1 / 3)
    quadratic = t10.quadratic_topology(linear)
    keys = {"youngs_modulus": 1.0e6, "density": 1000.0, "elasticity": "neohookean", "poisson_ratio": NU}
    assert se.cantilever_tip(quadratic, gravity=g, **keys) == pytest.approx(tip, rel=0.03)
    assert se.cantilever_frequency(quadratic, **keys) == pytest.approx(frequency, rel=0.03)
    assert se.cantilever_tip(linear, gravity=g, **keys) < 0.9 * tip


def test_cube_settles_within_two_percent():
    """A cube on frictionless ground under its own weight (a seeded Delaunay cube of 0.2 m, 119 particles), T10,
    float64 static solves: with the builder's lumped masses its shortening lies within 2 % of ρgh²/(2E) at ν = 0.3
    (measured +1.5 %; fTetWild's tets, finer, −0.1 … −0.6 %: the slow test below). At ν = 0 the continuum's
    displacement is quadratic in z (σ_zz = ρg(h − z), no lateral strain), which T10 holds exactly: with the consistent
    loads ρg∫N_a (a tet's corners −1/20 and edges 1/5 of its weight) the solve meets the closed form and the field to
    rounding, so the +3.3 % that lumped loads leave there is the lumping's, not the element's (it falls with the
    mesh: +0.2 … +0.5 % on fTetWild's)."""
    cube = se.box_topology("delaunay", (0.2, 0.2, 0.2), youngs_modulus=E, spacing=0.1, element="tet10")
    assert abs(se.cube_shortening(cube, youngs_modulus=E, density=1000.0, elasticity="neohookean",
                                  poisson_ratio=0.3)) < 0.02
    x, tets = cube.positions, cube.tets
    weight = 1000.0 * 9.81 * signed_volumes(x, tets[:, :4])
    shares = np.concatenate([np.full(4, -1.0 / 20.0), np.full(6, 1.0 / 5.0)])
    force = np.zeros_like(x)
    force[:, 2] = -np.bincount(tets.ravel(), weights=(weight[:, None] * shares).ravel(), minlength=len(x))
    bottom, top = x[:, 2] < x[:, 2].min() + 1e-9, x[:, 2] > x[:, 2].max() - 1e-9
    fixed = np.zeros(x.shape, dtype=bool)
    fixed[bottom, 2] = True
    fixed[np.flatnonzero(bottom)[:1]] = True  # with ν = 0 nothing moves sideways: hold one bottom particle's x, y
    fixed[np.flatnonzero(bottom)[1], :2] = True
    u = sb.static_displacement(cube, force, fixed, stiffness=se.body_stiffness(cube, elasticity="neohookean",
                                                                               youngs_modulus=E, poisson_ratio=0.0))
    h, z = np.ptp(x[:, 2]), x[:, 2] - x[:, 2].min()
    exact = 1000.0 * 9.81 * h * h / (2.0 * E)
    assert u[bottom, 2].mean() - u[top, 2].mean() == pytest.approx(exact, rel=1e-9)
    np.testing.assert_allclose(u[:, 2], -1000.0 * 9.81 / E * (h * z - 0.5 * z**2), atol=1e-9 * exact)


def test_lattice_cantilever_bends_right_without_a_tetrahedraliser():
    """The lattice of six tets per cell (``lattice_box_topology``: the cost benchmark's mesh, no pytetwild) is a
    conforming partition of the box: positive tets filling its volume, every face shared by two tets but the boundary's
    two triangles per lattice square, no flat gaps. On it the issue's cantilever at 3 across (30 × 3 × 3 cells), float64
    static and modal solves: T10 within 3 % of Timoshenko's tip and first frequency (measured −1.1 %, +0.6 %), linear
    tets on the same mesh locked (measured −32 %); the unit cube at 3 per side within 2 % (measured +0.1 %)."""
    beam = se.lattice_box_topology((1.0, 0.1, 0.1), cells=3)
    tets = beam.tets
    assert len(tets) == 6 * 30 * 3 * 3 and len(beam.positions) == 31 * 4 * 4
    volumes = signed_volumes(beam.positions, tets)
    assert (volumes > 0.0).all() and volumes.sum() == pytest.approx(0.01, rel=1e-12)
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]]),
                    axis=1)
    _, count = np.unique(faces, axis=0, return_counts=True)
    assert set(count.tolist()) == {1, 2} and (count == 1).sum() == 2 * 2 * (30 * 3 + 30 * 3 + 3 * 3)
    assert t10.crack_count(tets) == 0
    g = 9.81 / 100.0
    tip, frequency = se.timoshenko_cantilever(length=1.0, side=0.1, youngs_modulus=1.0e6, poisson_ratio=NU,
                                              density=1000.0, gravity=g)
    keys = {"youngs_modulus": 1.0e6, "density": 1000.0, "elasticity": "neohookean", "poisson_ratio": NU}
    quadratic = t10.quadratic_topology(beam)
    assert se.cantilever_tip(quadratic, gravity=g, **keys) == pytest.approx(tip, rel=0.03)
    assert se.cantilever_frequency(quadratic, **keys) == pytest.approx(frequency, rel=0.03)
    assert se.cantilever_tip(beam, gravity=g, **keys) < 0.8 * tip
    cube = se.lattice_box_topology((1.0, 1.0, 1.0), cells=3, element="tet10")
    assert abs(se.cube_shortening(cube, **keys)) < 0.02


def test_voxel_springs_ring_within_three_percent_at_two_resolutions():
    """The issue's second deliverable for the voxel springs (ν = ¼, their fixed ratio): the cantilever's first bending
    frequency by the float64 modal solve within 3 % of Timoshenko's at 6 and 8 cells across (measured +1.7 %, +1.1 %;
    the error falls with the mesh, bench/results/softbody_tet10.md)."""
    frequency = se.timoshenko_cantilever(length=1.0, side=0.1, youngs_modulus=1.0e6, poisson_ratio=0.25,
                                         density=1000.0)[1]
    for n in (6, 8):
        beam = se.box_topology("voxel", (1.0, 0.1, 0.1), youngs_modulus=1.0e6, spacing=0.1 / n)
        assert se.cantilever_frequency(beam, youngs_modulus=1.0e6, density=1000.0) == pytest.approx(frequency, rel=0.03)


@pytest.mark.slow
def test_linear_tets_ring_within_three_percent_when_fine():
    """The same for linear neo-Hookean tets (ν = 0.3) on the lattice of six tets per cell: within 3 % at 10 and 12
    across (measured +2.7 %, +2.0 %; +3.9 % at 8, +21.7 % at 3: they lock), where T10 is within 1 % at 2–4 across."""
    frequency = se.timoshenko_cantilever(length=1.0, side=0.1, youngs_modulus=1.0e6, poisson_ratio=NU,
                                         density=1000.0)[1]
    keys = {"youngs_modulus": 1.0e6, "density": 1000.0, "elasticity": "neohookean", "poisson_ratio": NU}
    for n in (10, 12):
        beam = se.lattice_box_topology((1.0, 0.1, 0.1), cells=n)
        assert se.cantilever_frequency(beam, **keys) == pytest.approx(frequency, rel=0.03)


@pytest.mark.slow
def test_tetrahedral_cube_settles_within_two_percent():
    """The unit cube of fTetWild's tets at 3 and 4 per side, T10 with lumped masses: the shortening within 2 % of
    ρgh²/(2E) at ν = 0.3 and 0.25 (measured −0.1 … −0.7 % over builds; linear tets −0.7 … −1.0 %)."""
    pytest.importorskip("pytetwild")
    for n in (3, 4):
        cube = se.box_topology("tetrahedral", (1.0, 1.0, 1.0), youngs_modulus=E, spacing=1.0 / n, element="tet10")
        for nu in (0.3, 0.25):
            assert abs(se.cube_shortening(cube, youngs_modulus=E, density=1000.0, elasticity="neohookean",
                                          poisson_ratio=nu)) < 0.02


INTEGRATORS = ["explicit_euler", "symplectic_euler", "implicit_euler", "velocity_verlet", "midpoint", "rk4", "dopri5"]


@pytest.mark.parametrize("name", [pytest.param(n, marks=() if n == "rk4" else pytest.mark.slow) for n in INTEGRATORS])
def test_stresses_are_fresh_at_every_stage(device, name):
    """The family computes each element's Gauss-point stresses once per force evaluation in a pass of its own
    (``at_time``); if a stage of some integrator read stresses of an earlier state, its motion would differ from the
    family that computes them in every node's gather. A deformed, damped T10 ball (seeded Delaunay icosphere, E = 4 kPa,
    β = 1 ms, each particle displaced by up to 5 mm) after 80 steps of 0.2 ms (ω_max h ≈ 0.1): both agree to 1e-12 m
    (the same float64 arithmetic in another order), and the body's shape changed by millimetres. RK4 (four stages) in
    the quick suite, the others marked slow."""
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    results = []
    for precompute in (True, False):
        builder = ws.ModelBuilder()
        builder.add_family(t10.QuadraticTetFamily(precompute=precompute))  # add_soft_body appends its elements to it
        builder.add_soft_body(ball, method="delaunay", youngs_modulus=4.0e3, density=1000.0, spacing=0.1,
                              damping=1.0e-3, elasticity="neohookean", poisson_ratio=0.3, element="tet10")
        model = builder.finalize(device, precision="float64")
        x = model.particle_q.numpy()
        integrator = ws.make_integrator(name, model)
        a, b = model.state(), model.state()
        start = x + np.random.default_rng(2).uniform(-5.0e-3, 5.0e-3, x.shape)
        a.particle_q.assign(start)
        for _ in range(80):
            integrator.step(a, b, None, 2.0e-4)
            a, b = b, a
        results.append(a.particle_q.numpy())
    shape = (results[0] - results[0].mean(axis=0)) - (start - start.mean(axis=0))
    assert np.abs(shape).max() > 1.0e-3
    np.testing.assert_allclose(results[0], results[1], rtol=0.0, atol=1.0e-12)


@pytest.mark.parametrize("name", ["symplectic_euler", "implicit_euler"])
def test_worlds_step_as_each_world_alone(device, name):
    """Two worlds of the free T10 cube, the second's E tripled (1 → 3 MPa) and ν 0.3 → 0.1 (``set_values(world=1)``), set vibrating:
    after 40 steps of 0.2 ms each world's state equals, bit for bit, that of a one-world model given its values (every
    reduction is per world in a fixed order, implicit Euler's CG included), and the two worlds differ."""
    start = None
    results = {}
    for worlds, world_values in ((2, None), (1, (1.0e6, NU)), (1, (3.0e6, 0.1))):
        builder = ws.ModelBuilder()
        body, _ = cube_body(builder, pin_bottom=False)
        model = builder.finalize(device, precision="float64", worlds=worlds)
        family = next(f for f in model.families if isinstance(f, t10.QuadraticTetFamily))
        if worlds == 2:
            family.set_values(youngs_modulus=3.0e6, poisson_ratio=0.1, world=1)
        if world_values is not None:
            family.set_values(youngs_modulus=world_values[0], poisson_ratio=world_values[1])
        if start is None:
            start = np.random.default_rng(5).normal(scale=0.2, size=(body.particle_count, 3))
        integrator = ws.make_integrator(name, model)
        a, b = model.state(), model.state()
        a.particle_qd.assign(np.tile(start, (worlds, 1)))
        for _ in range(40):
            integrator.step(a, b, None, 2.0e-4)
            a, b = b, a
        results[world_values] = a.particle_q.numpy().reshape(worlds, -1, 3)
    both = results[None]
    np.testing.assert_array_equal(both[0], results[(1.0e6, NU)][0])
    np.testing.assert_array_equal(both[1], results[(3.0e6, 0.1)][0])
    assert np.abs(both[0] - both[1]).max() > 1e-6
