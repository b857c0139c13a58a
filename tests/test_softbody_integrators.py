"""Soft bodies under every integrator on the device: a voxel and a tetrahedral body, deformed and falling
together, whose centres of mass follow each integrator's exact discrete free fall (springs are internal forces:
they sum to zero over a body, so its centre of mass sees gravity alone)."""

import numpy as np
import pytest
import trimesh

import warpspring as ws

try:
    import pytetwild  # noqa: F401  (the tetrahedral method's optional extra, warpspring[tet])

    TET = True
except ImportError:
    TET = False

E = 1.0e3  # [Pa]: ω ≈ √(2Σk/m) ≈ 100 rad/s on the 5 cm lattice, so ω·dt ≈ 0.1 for every integrator
RHO = 1000.0  # [kg/m³]
G = 9.81  # [m/s²]
DT, STEPS = 1.0e-3, 20  # [s]: the drop's schemes differ by g·dt²·n = 2e-4 m, twenty times the tolerance

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


@pytest.fixture(scope="module")
def bodies():
    """The builder's bodies (a 0.2 m cube as a voxel body and, with pytetwild, as a tetrahedral one), built once."""
    cube = trimesh.creation.box((0.2, 0.2, 0.2))
    builder = ws.ModelBuilder()
    methods = ["voxel"] + (["tetrahedral"] if TET else [])
    options = {"tetrahedral": {"epsilon": 1.0e-2}}
    made = [builder.add_soft_body(cube, method=method, youngs_modulus=E, density=RHO, spacing=0.05,
                                  origin=(0.5 * i, 0.0, 1.0), name=method, options=options.get(method))
            for i, method in enumerate(methods)]
    return builder, made


@pytest.mark.parametrize("name", sorted(FALL))
def test_deformed_bodies_fall_with_every_integrator(device, bodies, name):
    """Each particle displaced by up to 2 mm (springs strained by up to 8 %) and released: after 20 steps the
    centre of mass of each body is at z₀ − g·dt²·FALL(n). Tolerance 1e-5 m: float32 positions near 1 m (6e-8 m
    a rounding) over 20 steps of up to 7 stages, and the spring forces' float32 sum (the largest ~0.1 N on
    0.016 kg particles) moving the centre by less; dopri5 adds its tolerance per accepted internal step.
    The bodies did deform: some particle moves 0.1 mm or more relative to its body's centre of mass."""
    builder, made = bodies
    model = builder.finalize(device)
    integrator = ws.make_integrator(name, model)
    a, b = model.state(), model.state()
    rng = np.random.default_rng(7)
    q0 = a.particle_q.numpy().astype(np.float64) + rng.uniform(-2.0e-3, 2.0e-3, (model.particle_count, 3))
    a.particle_q.assign(q0.astype(np.float32))
    q0 = a.particle_q.numpy().astype(np.float64)
    mass = model.particle_mass.numpy()[0].astype(np.float64)  # one world
    for _ in range(STEPS):
        integrator.step(a, b, None, DT)
        a, b = b, a
    q = a.particle_q.numpy().astype(np.float64)
    atol = 1.0e-5
    if integrator.adaptive:
        atol += integrator.accepted_steps * integrator.tolerance * (1.0 + np.abs(q).max())
    for body in made:
        m = mass[body.particles]
        centre0, centre = m @ q0[body.particles] / m.sum(), m @ q[body.particles] / m.sum()
        expected = centre0 - np.array([0.0, 0.0, G * DT * DT * FALL[name](STEPS)])
        np.testing.assert_allclose(centre, expected, rtol=0.0, atol=atol, err_msg=body.method)
        relative = (q[body.particles] - centre) - (q0[body.particles] - centre0)
        assert np.abs(relative).max() > 1.0e-4, body.method


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
