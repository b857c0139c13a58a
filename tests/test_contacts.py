"""A particle on a tilted plane (Coulomb friction: sliding and sticking) and kinematic (pinned) particles.

Contact model (``kernels/response.py``): after each symplectic Euler update x' = x + h v', v' = v + h g, a
particle closer than its radius r to a collider is moved back along the collider's normal onto the
surface, its approaching normal velocity is removed, and its tangential velocity is reduced by at most
μ·|Δv_n|, where μ is the *collider's* friction (``add_collider_plane(friction=μ)``, ``Model.shape_arrays.friction``):
particles have no friction coefficient of their own. The position takes the same tangential change
times h, so it stays x + h·v for the velocity friction leaves.

On a plane tilted by θ under gravity g, a particle resting on it (distance r) gains h g cosθ of normal
and h g sinθ of tangential speed per step; the contact removes the first, and friction removes
μ h g cosθ of the second. So with a⁺ = max(g (sinθ - μ cosθ), 0), after N steps (t = N h):

    speed down the slope  v_N = a⁺ t                  exact: no O(h) term
    distance down slope   s_N = ½ a⁺ t (t + h)        (each step adds h · v_{k+1})

Against the analytic s(t) = ½ a⁺ t², the error is ½ a⁺ h t: first order in h while sliding, and
zero while static friction holds (μ ≥ tanθ): a sticking particle does not creep.
"""

import math

import numpy as np
import pytest

import warpspring as ws

G = 9.81
THETA = math.radians(30.0)
NORMAL = np.array([0.0, -math.sin(THETA), math.cos(THETA)])  # +z turned 30° about +x
DOWNHILL = -np.array([0.0, math.cos(THETA), math.sin(THETA)])  # unit, in the plane, along gravity's tangential part
RADIUS = 0.05
T = 1.0  # simulated time [s]: 60 frames of 1/60 s

# Rounding budgets for ~10³ steps (float32 unit roundoff u = 6e-8; float64 u = 1.1e-16):
# speeds ≤ 2.4 m/s, rounded ~10 times per step: √N · 10 · u · 2.4 m/s ≈ 4e-5 (float32), ×2.5;
# positions ≤ 1.2 m, one accumulation rounding per step: N · u · 2 m ≈ 1.2e-4 (float32) worst case, ×1.7.
# float64 is ~1e9 times tighter. Both are far below the O(h) error a first-order velocity would show,
# a⁺ h t = 2.5e-3 m/s at h = 1/960.
SPEED_ROUNDING = {"float32": 1.0e-4, "float64": 1.0e-10}
POSITION_ROUNDING = {"float32": 2.0e-4, "float64": 1.0e-10}
# The last projection puts the centre at distance r up to one rounding of |x| ≤ 2 m (float32: 2.4e-7 m).
ON_PLANE = {"float32": 1.0e-6, "float64": 1.0e-12}


def slope_acceleration(mu: float) -> float:
    """a⁺ = max(g (sinθ - μ cosθ), 0) [m/s²]: Coulomb sliding, or 0 when static friction holds."""
    return max(G * (math.sin(THETA) - mu * math.cos(THETA)), 0.0)


def discrete_slope_distance(mu: float, h: float, t: float) -> float:
    """s_N = ½ a⁺ t (t + h) [m]: the distance symplectic Euler + contact projection travel."""
    return 0.5 * slope_acceleration(mu) * t * (t + h)


def slide(device, mu: float, *, substeps: int, precision: str = "float32"):
    """A 1 kg particle starting at rest on the 30° plane through the origin (its centre at distance r)
    after T seconds at 60 fps with ``substeps`` substeps: (position, velocity, dt), float64."""
    builder = ws.ModelBuilder()  # gravity -9.81 ẑ
    builder.add_particles([RADIUS * NORMAL], mass=1.0, radius=RADIUS)
    builder.add_collider_plane(point=(0.0, 0.0, 0.0), normal=NORMAL, friction=mu, name="slope")
    model = builder.finalize(device, precision=precision)
    sim = ws.Simulator(model, fps=60, substeps=substeps)
    for _ in range(round(60 * T)):
        sim.step_frame()
    x = sim.state.particle_q.numpy()[0].astype(np.float64)
    v = sim.state.particle_qd.numpy()[0].astype(np.float64)
    return x, v, sim.dt


def test_friction_coefficient_is_the_colliders():
    """The contact pass reads μ from the collider table only: the builder stores it per shape."""
    builder = ws.ModelBuilder()
    builder.add_particles([RADIUS * NORMAL], radius=RADIUS)
    builder.add_collider_plane(normal=NORMAL, friction=0.3, name="slope")
    model = builder.finalize("cpu")
    assert model.shapes[0].friction == 0.3
    np.testing.assert_allclose(model.shape_arrays.friction.numpy(), [0.3], rtol=1e-7)


def test_particle_slides_down_slope_at_coulomb_acceleration(device, precision):
    """μ = 0.3 < tan 30°: after 1 s the speed down the slope is g (sinθ - μ cosθ) t = 2.356 m/s.

    The discrete speed is exact (constant acceleration; the friction impulse μ h g cosθ per step is
    Coulomb's law over the step), so the tolerance is rounding only (SPEED_ROUNDING). The particle stays
    on the plane (distance = r to rounding, no normal or sideways velocity). Its distance down the slope
    is the discrete s_N, whose error against ½ a t² is the first-order term ½ a h t (1.2 mm at h = 1/960 s).
    """
    mu = 0.3
    x, v, h = slide(device, mu, substeps=16, precision=precision)
    a = slope_acceleration(mu)
    assert a * T == pytest.approx(2.356, abs=5e-4)

    assert abs(v @ DOWNHILL - a * T) <= SPEED_ROUNDING[precision]
    assert abs(v @ NORMAL) <= SPEED_ROUNDING[precision]
    assert abs(x @ NORMAL - RADIUS) <= ON_PLANE[precision]
    np.testing.assert_allclose([x[0], v[0]], 0.0, atol=1e-12)  # nothing pushes it sideways

    s = (x - RADIUS * NORMAL) @ DOWNHILL
    assert abs(s - discrete_slope_distance(mu, h, T)) <= POSITION_ROUNDING[precision]
    first_order = 0.5 * a * h * T
    assert abs((s - 0.5 * a * T * T) - first_order) <= POSITION_ROUNDING[precision]


def test_particle_sticks_when_friction_exceeds_tan_theta(device, precision):
    """μ = 0.7 > tan 30° = 0.577: static friction holds. Every step's friction impulse cancels the
    tangential speed h g sinθ gained, so the velocity is exactly zero, and the tangential displacement
    h² g sinθ of that step with it: the particle stays where it was put, on the plane, to rounding (a
    creep of h g sinθ = 5.1 mm/s would show as 5.1 mm after 1 s at h = 1/960).
    """
    mu = 0.7
    assert mu > math.tan(THETA)
    x, v, h = slide(device, mu, substeps=16, precision=precision)

    np.testing.assert_array_equal(v, 0.0)
    assert abs(x @ NORMAL - RADIUS) <= ON_PLANE[precision]
    s = (x - RADIUS * NORMAL) @ DOWNHILL
    assert abs(s) <= ON_PLANE[precision]
    assert abs(x[0]) <= 1e-12


def test_slope_error_is_first_order_in_dt(device):
    """At h = 1/240, 1/960, 1/3840 s (float64, sliding at μ = 0.3): the speed is a t at every h (no O(h)
    term), the distance is the discrete s_N, and its error against ½ a t² is ½ a h t, so it falls by
    exactly 4 per 4× smaller step (4.9, 1.2, 0.31 mm)."""
    mu = 0.3
    a = slope_acceleration(mu)
    errors, steps = [], []
    for substeps in (4, 16, 64):
        x, v, h = slide(device, mu, substeps=substeps, precision="float64")
        s = (x - RADIUS * NORMAL) @ DOWNHILL
        assert abs(v @ DOWNHILL - a * T) <= SPEED_ROUNDING["float64"]
        assert abs(x @ NORMAL - RADIUS) <= 1e-12
        assert abs(s - discrete_slope_distance(mu, h, T)) <= POSITION_ROUNDING["float64"]
        errors.append(s - 0.5 * a * T * T)
        steps.append(h)
    errors, steps = np.array(errors), np.array(steps)
    np.testing.assert_allclose(errors / steps, 0.5 * a * T, rtol=1e-7)
    np.testing.assert_allclose(errors[:-1] / errors[1:], 4.0, rtol=1e-7)


# -- kinematic (pinned) particles ------------------------------------------------------------------------
#
# What the package promises: pinned particles have zero inverse mass, "no force moves them"
# (ModelBuilder.add_particles), and they "are kinematic everywhere: they move with their velocity and
# feel no force" (kernels/integrators.py). Control has no input that drives them (only particle_force),
# so a pin either stays put (zero velocity) or moves at its constant initial velocity.

CHAIN, CHAIN_SPACING, CHAIN_MASS = 6, 0.1, 0.1
H, STEPS = 1.0e-3, 100
PIN_VELOCITY = np.array([0.5, -0.25, 0.75])


def chain(device, precision, velocity=(0.0, 0.0, 0.0)):
    """A vertical chain of CHAIN particles (damped springs, ke = 1e3 N/m), particle 0 pinned by the
    ``pinned`` mask and particle 3 by ``pin_particles``; every particle starts at ``velocity``."""
    builder = ws.ModelBuilder()
    q = np.zeros((CHAIN, 3))
    q[:, 0] = 0.3
    q[:, 2] = 1.0 - CHAIN_SPACING * np.arange(CHAIN)
    builder.add_particles(q, velocities=velocity, mass=CHAIN_MASS, pinned=[0])
    builder.pin_particles([3])
    builder.add_springs(np.stack([np.arange(CHAIN - 1), np.arange(1, CHAIN)], 1), stiffness=1.0e3, damping=1.0)
    return builder.finalize(device, precision=precision)


PINS = [0, 3]
FREE = [1, 2, 4, 5]


def run(model, integrator):
    """Positions and velocities of STEPS steps of H, shape [STEPS + 1, CHAIN, 3] each, in the model's precision."""
    a, b = model.state(), model.state()
    q, qd = [a.particle_q.numpy().copy()], [a.particle_qd.numpy().copy()]  # copies: on the CPU numpy() is a view
    for _ in range(STEPS):
        integrator.step(a, b, None, H)
        a, b = b, a
        q.append(a.particle_q.numpy().copy())
        qd.append(a.particle_qd.numpy().copy())
    return np.stack(q), np.stack(qd)


@pytest.mark.parametrize("name", list(ws.INTEGRATORS))
def test_pins_stay_bitwise_fixed_under_gravity_and_springs(device, precision, name):
    """With zero velocity, pinned particles keep their exact (bitwise) positions and zero velocity for
    100 steps of every integrator, while gravity and the springs pull on them."""
    model = chain(device, precision)
    q, qd = run(model, ws.make_integrator(name, model))
    np.testing.assert_array_equal(q[:, PINS], np.broadcast_to(q[0, PINS], q[:, PINS].shape))
    np.testing.assert_array_equal(qd[:, PINS], 0.0)

    # They did feel force: at rest length the top pin feels its weight m g only; 0.1 s later the sagging
    # spring below adds a pull of more than ½ m g (measured 1.3–1.8 m g, by integrator).
    state = model.state()
    state.particle_q.assign(q[-1])
    state.particle_qd.assign(qd[-1])
    ws.eval_forces(model, state, None)
    assert -state.particle_f.numpy()[0, 2] > 1.5 * CHAIN_MASS * G
    assert np.abs(q[-1, FREE] - q[0, FREE]).max() > 5e-4  # and the free particles moved (1.3–1.8 mm)


@pytest.mark.parametrize("name", list(ws.INTEGRATORS))
def test_pinned_particles_move_with_their_velocity_and_the_chain_follows(device, name):
    """A pin with initial velocity u moves along x₀ + u t with velocity exactly u, under gravity and
    spring forces, for every integrator (float64).

    With every particle starting at u and no drag (drag acts on absolute velocity), the free particles
    follow: the run equals the resting chain's run shifted by u t (Galilean invariance: gravity is
    uniform, springs see only relative positions and velocities).

    Tolerances: 100 steps of ≤ 7 stage additions, each rounding by ≤ ½ ulp of |x| ≤ 2 m (2.2e-16 m):
    1.6e-13 m, so 1e-12. The adaptive integrator picks its own internal steps from errors scaled by
    |y|, which differ between the two runs; each accepted internal step errs by ≤ tolerance·(1 + |y|),
    so the two runs may differ by that many of them.
    """
    still = chain(device, "float64")
    moving = chain(device, "float64", velocity=PIN_VELOCITY)
    integrator_still, integrator_moving = ws.make_integrator(name, still), ws.make_integrator(name, moving)
    q0, _ = run(still, integrator_still)
    q, qd = run(moving, integrator_moving)
    t = H * np.arange(STEPS + 1)[:, None, None]

    np.testing.assert_allclose(q[:, PINS], q[0, PINS] + t * PIN_VELOCITY, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(qd[:, PINS], np.broadcast_to(PIN_VELOCITY, qd[:, PINS].shape))

    atol = 1e-12
    if integrator_moving.adaptive:
        internal = integrator_still.accepted_steps + integrator_moving.accepted_steps
        atol += internal * integrator_moving.tolerance * (1.0 + np.abs(q).max() + np.abs(qd).max())
    np.testing.assert_allclose(q - t * PIN_VELOCITY, q0, rtol=0, atol=atol)
    assert np.abs(q0[-1, FREE] - q0[0, FREE]).max() > 5e-4  # the chain did move under gravity (1.3–1.8 mm)
