"""Soft bodies under every integrator on the device: the seven methods' bodies of one ball, each integrator's
discrete free fall of every particle while the springs are at rest, and a short oscillation of the deformed bodies
against a float64 small-step reference of the same network plus the integrator's own discretization error (the
same recurrence run in float64 on the network linearised at rest); a voxel cube settling to its static solve; and a
Delaunay ball whose neo-Hookean tets carry its elasticity, in each integrator's discrete free fall."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh

import warpspring as ws
from warpspring.core import soft_topologies
from warpspring.core import softbody as sb
from warpspring.core.soft_topologies import METHODS

try:
    import pytetwild  # noqa: F401  (the tetrahedral method's optional extra, warpspring[tet])

    TET = True
except ImportError:
    TET = False

E = 4.0e3  # [Pa]: the stiffest mode of the seven bodies (tetrahedral) has ω ≈ 84 rad/s, so ω·dt ≈ 0.06 ≤ 0.1
RHO = 1000.0  # [kg/m³]
G = 9.81  # [m/s²]
DT, STEPS = 7.0e-4, 80  # [s]: the schemes' falls differ by g·dt²·n = 3.8e-4 m, 380 times the free-fall tolerance
AMPLITUDE = 5.0e-4  # [m]: each particle's displacement from rest along each axis (strains up to ~2 %)

#: z_n − z₀ of a point mass falling from rest, per integrator's update: explicit Euler moves with the old
#: velocity (n(n−1)/2), symplectic and implicit Euler with the new (n(n+1)/2); the second-order and higher
#: methods integrate the quadratic exactly (n²/2).
FALL = {
    "explicit_euler": lambda n: n * (n - 1) / 2.0,
    "symplectic_euler": lambda n: n * (n + 1) / 2.0,
    "implicit_euler": lambda n: n * (n + 1) / 2.0,
    "velocity_verlet": lambda n: n * n / 2.0,
    "midpoint": lambda n: n * n / 2.0,
    "rk4": lambda n: n * n / 2.0,
    "dopri5": lambda n: n * n / 2.0,
}
#: Force evaluations per step (dopri5: per internal step; its error control bounds the rest).
STAGES = {"explicit_euler": 1, "symplectic_euler": 1, "implicit_euler": 1, "velocity_verlet": 2, "midpoint": 2,
          "rk4": 4, "dopri5": 7}


def _layered_ball(vertices, faces, options, *, limit):
    """A fixed tetrahedralisation in place of fTetWild's (same arguments and return as
    :func:`~warpspring.core.soft_topologies.run_tetwild`): the closed surface, a copy of it shrunk by half about the
    vertices' centroid, and the centroid; each triangle's prism between the two surfaces cut into three tets (every
    side face split from its lower-numbered outer corner, so that neighbours agree: the mesh is conforming), each inner
    triangle coned to the centroid (the icosphere is star-shaped about it). For the ball: 85 particles, 320 tets of
    quality ≥ 0.46, edges 0.055 to 0.13 m. fTetWild has no seed: its meshes of the ball differed from run to run
    (edges down to 0.033 m where 0.1 m was asked for), and with them the oscillation test's margin (0.4 to 0.94 of
    its tolerance for the Eulers, once over it: the short edges' strains, up to 5 %, made the springs' nonlinear part
    larger than the 5 % the tolerance allows)."""
    del options, limit
    n = len(vertices)
    centre = vertices.mean(axis=0)
    a, b, c = np.sort(faces, axis=1).T
    o = np.full_like(a, 2 * n)
    tets = np.stack([[a, b, c, c + n], [a, b, b + n, c + n], [a, a + n, b + n, c + n], [a + n, b + n, c + n, o]])
    return np.vstack([vertices, centre + 0.5 * (vertices - centre), centre]), tets.transpose(2, 0, 1).reshape(-1, 4)


@pytest.fixture(scope="module")
def bodies():
    """The seven methods' bodies of one ball (an icosphere of subdivision 1, radius 0.2 m, spacing 0.1 m: 42 to 85
    particles each), all at the origin (they do not touch: no contacts), built once; and the network in float64:
    particle pairs, stiffness [N/m] and rest lengths [m] of every spring. The tetrahedral method's tets are
    :func:`_layered_ball`'s, not fTetWild's, so that every run sees the same bodies and margins (its springs,
    masses and embedding are the method's own; it still needs pytetwild installed)."""
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    builder = ws.ModelBuilder()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(soft_topologies, "run_tetwild", _layered_ball)
        made = [builder.add_soft_body(ball, method=method, youngs_modulus=E, density=RHO, spacing=0.1, name=method)
                for method in METHODS if TET or method != "tetrahedral"]
    rest = np.zeros((sum(body.particle_count for body in made), 3))
    pairs, ke = [], []
    for body in made:
        rest[body.particles] = body.topology.positions  # origin 0, no rotation, scale 1: the mesh's frame
        for local, k in body.topology.springs.values():
            pairs.append(body.particles[local])
            ke.append(k)
    pairs, ke = np.concatenate(pairs), np.concatenate(ke)
    return builder, made, rest, pairs, ke


def _run(model, name, q0):
    """``STEPS`` steps of ``DT`` from positions ``q0`` (float32-rounded) at rest: the integrator and the final
    positions [m] (float64 copy). dopri5 at a local tolerance of 1e-7 (its default, 1e-6, summed over its ~80
    internal steps would bound its error only by ~1e-4 m, the size of the motion checked)."""
    options = {"tolerance": 1.0e-7} if name == "dopri5" else {}
    integrator = ws.make_integrator(name, model, **options)
    a, b = model.state(), model.state()
    a.particle_q.assign(q0.astype(np.float32))
    for _ in range(STEPS):
        integrator.step(a, b, None, DT)
        a, b = b, a
    return integrator, a.particle_q.numpy().astype(np.float64)


@pytest.mark.parametrize("name", sorted(FALL))
def test_every_method_falls_freely_with_every_integrator(device, bodies, name):
    """Springs at rest exert no force: every particle of every body follows the integrator's discrete free fall
    z₀ − g·dt²·FALL(n) exactly. Tolerance 1e-6 m: float32 positions of at most 0.2 m (1.5e-8 m a rounding) over
    80 steps, and float32 rest lengths (their rounding, ~1e-8 m, is a spring stretch whose force moves a particle
    by about as much); the schemes differ by 3.8e-4 m."""
    builder, made, rest, _, _ = bodies
    model = builder.finalize(device)
    integrator, q = _run(model, name, rest)
    expected = rest.astype(np.float32).astype(np.float64) - [0.0, 0.0, G * DT * DT * FALL[name](STEPS)]
    atol = 1.0e-6
    if integrator.adaptive:
        atol += integrator.accepted_steps * integrator.tolerance * (1.0 + np.abs(q).max())
    for body in made:
        np.testing.assert_allclose(q[body.particles], expected[body.particles], rtol=0.0, atol=atol, err_msg=body.method)


# -- the float64 reference ----------------------------------------------------------------------------------------


def _forces(x, pairs, ke, length0):
    """Hooke springs' forces [N] on every particle at positions x [m] (float64): ke (|d| − L) d̂ on the first end."""
    d = x[pairs[:, 1]] - x[pairs[:, 0]]
    length = np.linalg.norm(d, axis=1)
    f = (ke * (length - length0) / length)[:, None] * d
    out = np.zeros_like(x)
    for axis in range(3):
        out[:, axis] = np.bincount(pairs[:, 0], f[:, axis], len(x)) - np.bincount(pairs[:, 1], f[:, axis], len(x))
    return out


def _rk4(accel, x, v, h, steps):
    """``steps`` classic RK4 steps of x'' = accel(x): positions and velocities."""
    for _ in range(steps):
        k1x, k1v = v, accel(x)
        k2x, k2v = v + 0.5 * h * k1v, accel(x + 0.5 * h * k1x)
        k3x, k3v = v + 0.5 * h * k2v, accel(x + 0.5 * h * k2x)
        k4x, k4v = v + h * k3v, accel(x + h * k3x)
        x = x + h / 6.0 * (k1x + 2.0 * k2x + 2.0 * k3x + k4x)
        v = v + h / 6.0 * (k1v + 2.0 * k2v + 2.0 * k3v + k4v)
    return x, v


def _linear_step(name, accel, backward, u, v, h):
    """One step of integrator ``name`` on the linear system u'' = accel(u) = −M⁻¹K u + g. Implicit Euler is
    Baraff-Witkin, for a linear force exactly backward Euler: Δv = (M + h²K)⁻¹ M · h (accel(u) − h M⁻¹K v), with
    ``backward`` applying (M + h²K)⁻¹ M."""
    if name == "explicit_euler":
        return u + h * v, v + h * accel(u)
    if name == "symplectic_euler":
        v = v + h * accel(u)
        return u + h * v, v
    if name == "implicit_euler":
        stiffness_times_v = accel(np.zeros_like(v)) - accel(v)  # M⁻¹K v
        v = v + backward(h * (accel(u) - h * stiffness_times_v))
        return u + h * v, v
    if name == "velocity_verlet":
        v = v + 0.5 * h * accel(u)
        u = u + h * v
        return u, v + 0.5 * h * accel(u)
    if name == "midpoint":
        return u + h * (v + 0.5 * h * accel(u)), v + h * accel(u + 0.5 * h * v)
    return _rk4(accel, u, v, h, 1)


@pytest.fixture(scope="module")
def reference(bodies):
    """Each particle displaced by up to ``AMPLITUDE`` (seeded) and released at rest: the positions after
    ``STEPS`` × ``DT`` by the nonlinear network in float64 (RK4 at DT/4: error ~(ωh)⁴ωt/120 ≈ 2e-9 of the
    motion), the same without springs (free fall), and per integrator its own discretization error on the network
    linearised at rest (its recurrence run in float64, less RK4 at DT/16 on the same linear system)."""
    builder, made, rest, pairs, ke = bodies
    model = builder.finalize("cpu")
    mass = model.particle_mass.numpy()[0].astype(np.float64)
    rng = np.random.default_rng(11)
    q0 = (rest + rng.uniform(-AMPLITUDE, AMPLITUDE, rest.shape)).astype(np.float32).astype(np.float64)
    length0 = np.linalg.norm(rest[pairs[:, 1]] - rest[pairs[:, 0]], axis=1)
    gravity = np.array([0.0, 0.0, -G])

    def accel(x):
        return _forces(x, pairs, ke, length0) / mass[:, None] + gravity

    zero = np.zeros_like(q0)
    q_ref = _rk4(accel, q0, zero, DT / 4, 4 * STEPS)[0]
    q_fall = q0 + gravity * 0.5 * (DT * STEPS) ** 2
    K = sb.stiffness_matrix(rest, pairs, ke)
    m3 = np.repeat(mass, 3)

    def linear(u):
        return (-(K @ u.ravel()) / m3).reshape(-1, 3) + gravity

    implicit = spla.factorized((sp.diags(m3) + DT * DT * K).tocsc())

    def backward(b):  # (M + h²K)⁻¹ M b
        return implicit(m3 * b.ravel()).reshape(-1, 3)

    u0 = q0 - rest
    exact = _rk4(linear, u0, zero, DT / 4, 4 * STEPS)[0]
    error = {"dopri5": np.zeros_like(u0)}  # its own error control bounds it (see the test)
    for name in FALL.keys() - {"dopri5"}:
        u, v = u0, zero
        for _ in range(STEPS):
            u, v = _linear_step(name, linear, backward, u, v, DT)
        error[name] = u - exact
    return q0, q_ref, q_fall, error


@pytest.mark.parametrize("name", sorted(FALL))
def test_every_method_oscillates_as_the_float64_reference(device, bodies, reference, name):
    """The deformed bodies, released: after 80 steps every particle is where the float64 reference of the same
    network puts it plus the integrator's own discretization error, predicted on the network linearised at rest
    (2e-6 to 3e-5 m for the Eulers, 1e-8 to 6e-7 m for the second-order methods, 5e-13 to 7e-11 m for RK4).
    Tolerance: 5 % of the springs' part of that error (the free fall's part is exact; the springs' nonlinear part is
    of the order of the strain, ≤ 2 %) plus float32 round-off, bounded by one unit in the last place of the largest
    coordinate per force evaluation (steps × stages × 2⁻²³ |x|max); dopri5 adds its local tolerance per internal
    step. The test can fail: the springs moved every body by at least 10 times its tolerance (the reference against
    free fall)."""
    builder, made, _, _, _ = bodies
    q0, q_ref, q_fall, error = reference
    model = builder.finalize(device)
    integrator, q = _run(model, name, q0)
    fall = np.array([0.0, 0.0, G * DT * DT * (STEPS**2 / 2.0 - FALL[name](STEPS))])  # the scheme's lag in free fall
    steps = integrator.accepted_steps if integrator.adaptive else STEPS
    for body in made:
        p = body.particles
        atol = 0.05 * np.abs(error[name][p] - fall).max() + steps * STAGES[name] * 2.0**-23 * np.abs(q[p]).max()
        if integrator.adaptive:
            atol += integrator.accepted_steps * integrator.tolerance * (1.0 + np.abs(q[p]).max())
        assert np.abs(q_ref[p] - q_fall[p]).max() >= 10.0 * atol, body.method
        np.testing.assert_allclose(q[p], q_ref[p] + error[name][p], rtol=0.0, atol=atol, err_msg=body.method)


@pytest.fixture(scope="module")
def resting_cube():
    """A 0.2 m voxel cube (5 cm voxels, E = 100 kPa) just above frictionless ground, with drag, and the float64
    static solve's shortening between its bottom and top layers under its weight (bottom held on the ground)."""
    from warpspring.analysis.softbody_elasticity import _hold_rigid_in_plane
    from warpspring.core import softbody as sb

    cube = trimesh.creation.box((0.2, 0.2, 0.2))
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -G), drag=20.0)  # [N·s/m]: the slowest mode overdamped
    body = builder.add_soft_body(cube, method="voxel", youngs_modulus=1.0e5, density=RHO, spacing=0.05,
                                 origin=(0.0, 0.0, 0.1125))  # the bottom layer one particle radius up
    builder.add_ground_plane(friction=0.0)
    x = body.topology.positions
    bottom, top = x[:, 2] < x[:, 2].min() + 1.0e-6, x[:, 2] > x[:, 2].max() - 1.0e-6
    fixed = np.zeros(x.shape, dtype=bool)
    fixed[bottom, 2] = True
    _hold_rigid_in_plane(fixed, x, np.flatnonzero(bottom), (0, 1))
    force = np.zeros_like(x)
    force[:, 2] = -G * sb.distribute_mass(body.topology, body.mass)
    u = sb.static_displacement(body.topology, force, fixed)
    return builder, body, bottom, top, u[bottom, 2].mean() - u[top, 2].mean()


@pytest.mark.parametrize("name", sorted(FALL))
def test_voxel_cube_settles_to_the_static_solve(device, resting_cube, name):
    """After 0.3 s on the ground every integrator's cube is shortened as the static solve says (1.94 mm, strain
    1 %). Measured on the CPU: +1.3 % (explicit, symplectic Euler, midpoint), +1.9 % (RK4, dopri5), +2.5 %
    (velocity Verlet), +4.2 % (implicit Euler); a fixed point of every scheme is the same equilibrium, so the
    spread is the linear solve's: geometric nonlinearity (~ the strain, 1 %) and the ground's penalty contact
    against a held bottom layer, and implicit Euler's extra 3 % is not explained. Asserted: within 6 %."""
    builder, body, bottom, top, static = resting_cube
    model = builder.finalize(device)
    integrator = ws.make_integrator(name, model)
    a, b = model.state(), model.state()
    dt = 2.0e-4 if name == "explicit_euler" else 1.0e-3  # [s]: explicit Euler grows the stiffest mode by (ωdt)²/2
    for _ in range(round(0.3 / dt)):
        integrator.step(a, b, None, dt)
        a, b = b, a
    q = a.particle_q.numpy().astype(np.float64)[body.particles]
    shortening = 0.2 - (q[top, 2].mean() - q[bottom, 2].mean())
    assert shortening == pytest.approx(static, rel=0.06)


@pytest.fixture(scope="module")
def neohookean_ball():
    """A seeded Delaunay ball (the icosphere of ``bodies``, spacing 0.1 m) whose tets carry its elasticity
    (``elasticity="neohookean"``, no springs), with its damper on (β = 1 ms: the velocity-dependent path of every
    integrator), float64."""
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    builder = ws.ModelBuilder()
    body = builder.add_soft_body(ball, method="delaunay", youngs_modulus=E, density=RHO, spacing=0.1, damping=1.0e-3,
                                 elasticity="neohookean", poisson_ratio=0.3)
    return builder, body


@pytest.mark.parametrize("name", sorted(FALL))
def test_neohookean_body_falls_freely_with_every_integrator(device, neohookean_ball, name):
    """At rest the neo-Hookean tets exert no force (μV₀(F - I)G_a and λ(J - α) + μ cancel to rounding, ~1e-16 of
    μV₀|G| ≈ 1e-3 N per unit strain here) and their damper none on a uniform velocity (Ė = 0): every particle follows
    the integrator's discrete free fall z₀ − g·dt²·FALL(n). Tolerance 1e-12 m: float64 positions of 0.2 m (3e-17 m
    a rounding) over 80 steps; the schemes differ by 3.8e-4 m."""
    builder, body = neohookean_ball
    model = builder.finalize(device, precision="float64")
    assert model.spring_count == 0
    # implicit Euler: a uniform Δv = h g solves its system exactly (the tets' K and D vanish on it); CG's
    # tolerance is what it leaves
    options = {"dopri5": {"tolerance": 1.0e-9}, "implicit_euler": {"cg_tolerance": 1.0e-14}}.get(name, {})
    integrator = ws.make_integrator(name, model, **options)
    a, b = model.state(), model.state()
    rest = a.particle_q.numpy().copy()
    for _ in range(STEPS):
        integrator.step(a, b, None, DT)
        a, b = b, a
    expected = rest - [0.0, 0.0, G * DT * DT * FALL[name](STEPS)]
    atol = 1.0e-12
    if integrator.adaptive:
        atol += integrator.accepted_steps * integrator.tolerance * (1.0 + np.abs(rest).max())
    np.testing.assert_allclose(a.particle_q.numpy(), expected, rtol=0.0, atol=atol)


@pytest.mark.parametrize("name", sorted(FALL))
def test_neohookean_stresses_are_fresh_at_every_stage(device, name):
    """The neo-Hookean family computes each tet's stress once per force evaluation in a pass of its own (``at_time``);
    if a stage of some integrator read stresses of an earlier state, its motion would differ from the family that
    computes them in every corner's gather. A deformed, damped Delaunay ball (each particle displaced by up to 5 mm,
    so it rings by millimetres) after 80 steps of each integrator: both families agree to 1e-12 m (the same float64
    arithmetic in another order; measured bit for bit on the CPU)."""
    from warpspring.core.neohookean import NeoHookeanFamily

    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    results = []
    for precompute in (True, False):
        builder = ws.ModelBuilder()
        builder.add_family(NeoHookeanFamily(precompute=precompute))  # add_soft_body appends its tets to it
        builder.add_soft_body(ball, method="delaunay", youngs_modulus=E, density=RHO, spacing=0.1, damping=1.0e-3,
                              elasticity="neohookean", poisson_ratio=0.3)
        model = builder.finalize(device, precision="float64")
        x = model.particle_q.numpy()
        integrator = ws.make_integrator(name, model)
        a, b = model.state(), model.state()
        start = x + np.random.default_rng(2).uniform(-5.0e-3, 5.0e-3, x.shape)
        a.particle_q.assign(start)
        for _ in range(STEPS):
            integrator.step(a, b, None, DT)
            a, b = b, a
        results.append(a.particle_q.numpy())
    shape = (results[0] - results[0].mean(axis=0)) - (start - start.mean(axis=0))
    assert np.abs(shape).max() > 2.0e-3  # the body's shape changed (measured 8.8 mm under RK4), not only its place
    np.testing.assert_allclose(results[0], results[1], rtol=0.0, atol=1.0e-12)
