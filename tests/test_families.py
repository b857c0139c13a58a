"""Element families: a family added from outside the package, dihedral hinges, and incidence of any degree.

The tether family below lives in this test module only: it reaches every kernel (forces, implicit Euler's
product, power iteration, guards' energy) through the family protocol, without any kernel changing.
"""

import functools
from dataclasses import dataclass
import math

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.core.families import ElementFamily, build_incidence, element_energies, head_slots, incidence_entries
from warpspring.core.hinges import dihedral_angle, dihedral_gradient
from warpspring.core.integrators import make_integrator
from warpspring.kernels.families import FamilyFuncs, Incidence, IncidenceShape
from warpspring.kernels.precision import vec3_type

from helpers import ZERO_GRAVITY, trajectory


# -- a family from a test module: zero-length tethers of particles to fixed anchors -----------------------


@functools.cache
def tether_arrays_type(scalar):
    @wp.struct
    class TetherArrays:
        anchor: wp.array[vec3_type(scalar)]  # [m], [tether_count]
        stiffness: wp.array[scalar]  # [N/m], [tether_count]
        incidence: Incidence  # entries (tether, 0); padding (0, -1)

    return TetherArrays


@dataclass(frozen=True)
class TetherSpec:
    incidence: IncidenceShape

    def funcs(self, scalar):
        return tether_funcs(scalar, self)


@functools.cache
def tether_funcs(scalar, spec: TetherSpec) -> FamilyFuncs:
    vec3 = vec3_type(scalar)
    Arrays = tether_arrays_type(scalar)
    slots = spec.incidence.head_slots

    @wp.func
    def force(world: int, i: int, base: int, xi: vec3, vi: vec3, tethers: Arrays, inputs: wp.array2d[scalar],
              particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> vec3:
        f = vec3(scalar(0.0))
        for k in range(wp.static(slots)):
            t = tethers.incidence.head_element[k, i]
            if tethers.incidence.head_local[k, i] >= 0:
                f -= tethers.stiffness[t] * (xi - tethers.anchor[t])
        return f

    @wp.func
    def product(world: int, i: int, base: int, xi: vec3, tethers: Arrays, inputs: wp.array2d[scalar],
                particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
                alpha: scalar, beta: scalar):
        k = scalar(0.0)
        for slot in range(wp.static(slots)):
            if tethers.incidence.head_local[slot, i] >= 0:
                k += tethers.stiffness[tethers.incidence.head_element[slot, i]]
        return (alpha * k) * x[base + i], (alpha * k) * wp.identity(n=3, dtype=scalar)

    @wp.func
    def strain(world: int, i: int, base: int, xi: vec3, tethers: Arrays, particle_q: wp.array[vec3]):
        return wp.float64(-1.0), -1

    @wp.func
    def energy(world: int, t: int, base: int, tethers: Arrays, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3]) -> scalar:
        return scalar(0.5) * tethers.stiffness[t] * wp.length_sq(particle_q[base + t] - tethers.anchor[t])

    return FamilyFuncs(Arrays, force, product, strain, energy)


class Tethers(ElementFamily):
    """Particle i (of the first ``len(anchors)``) tied to anchors[i] by a zero-length spring of stiffness k."""

    name = "tethers"

    def __init__(self, anchors, stiffness):
        self.anchors = np.asarray(anchors, dtype=np.float64)
        self.k = float(stiffness)

    @property
    def element_count(self):
        return len(self.anchors)

    def finalize(self, model):
        count = len(self.anchors)
        members = np.arange(count)[:, None]
        self.incidence, self.shape = build_incidence(members, model.particle_count, np.zeros_like(members), -1,
                                                     device=model.device)
        self.anchor = wp.array(self.anchors, dtype=model.vec3, device=model.device)
        self.stiffness = wp.full(count, self.k, dtype=model.scalar, device=model.device)

    def spec(self, model, *, linear=False):
        return TetherSpec(self.shape)

    def arrays(self, model, *, stiffness=None):
        arrays = tether_arrays_type(model.scalar)()
        arrays.anchor, arrays.stiffness, arrays.incidence = self.anchor, self.stiffness, self.incidence
        return arrays

    def gershgorin_rows(self, model, free, stiffness=None):
        rows = np.zeros((model.world_count, model.particle_count))
        rows[:, : len(self.anchors)] = self.k
        return rows


def tethered_particle(device, *, mass=0.5, k=200.0, amplitude=0.01):
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[amplitude, 0.0, 1.0]], mass=mass)
    builder.add_family(Tethers([[0.0, 0.0, 1.0]], k))
    return builder.finalize(device)


def crossing_period(signal: np.ndarray, dt: float) -> float:
    """Mean period [s] from the upward zero crossings of a sampled signal (linear interpolation)."""
    s = np.asarray(signal)
    up = np.flatnonzero((s[:-1] < 0.0) & (s[1:] >= 0.0))
    times = (up + s[up] / (s[up] - s[up + 1])) * dt
    return float(np.diff(times).mean())


@pytest.mark.parametrize("integrator", ["symplectic_euler", "implicit_euler", "rk4"])
def test_a_family_from_a_test_module_reaches_every_integrator(device, integrator):
    """A tethered particle oscillates at its integrator's discrete frequency for ω = √(k/m): symplectic
    Euler cos(ω̃h) = 1 - (ωh)²/2, backward Euler tan(ω̃h) = ωh (its linearisation is exact for a linear
    force), RK4 ω̃ = ω to O((ωh)⁴). Four periods, ωh = 0.05: float32 rounding of the crossings leaves
    ~1e-5 of the period."""
    mass, k = 0.5, 200.0
    model = tethered_particle(device, mass=mass, k=k)
    omega = math.sqrt(k / mass)
    dt = 0.05 / omega
    discrete = {"symplectic_euler": math.acos(1.0 - 0.5 * (omega * dt) ** 2) / dt,
                "implicit_euler": math.atan(omega * dt) / dt, "rk4": omega}[integrator]
    steps = int(4.5 * 2.0 * math.pi / (omega * dt))
    x = trajectory(model, make_integrator(integrator, model), dt, steps)[:, 0, 0]
    assert crossing_period(x, dt) == pytest.approx(2.0 * math.pi / discrete, rel=2e-4)
    assert "1 tethers" in model.describe()


def test_a_family_from_a_test_module_in_energy_and_advisor(device):
    """The family's energy hook gives ½ k A², and its stiffness product and Gershgorin rows give the advisor
    ω_max = √(k/m) from both power iteration and the bound."""
    mass, k, amplitude = 0.5, 200.0, 0.01
    model = tethered_particle(device, mass=mass, k=k, amplitude=amplitude)
    family = model.families[0]
    np.testing.assert_allclose(element_energies(model, family), [[0.5 * k * amplitude**2]], rtol=1e-5)
    estimate = ws.analysis.omega.estimate_omega_max(model)
    assert estimate.omega_max == pytest.approx(math.sqrt(k / mass), rel=1e-4)
    assert estimate.gershgorin == pytest.approx(math.sqrt(k / mass), rel=1e-6)


def test_add_family_rejects_what_is_not_a_family():
    builder = ws.ModelBuilder()
    with pytest.raises(ws.ConfigError, match="ElementFamily"):
        builder.add_family(object())


# -- dihedral hinges ---------------------------------------------------------------------------------------


def hinge_pair(device, *, ke=0.02, kd=0.0, fold=0.01, mass=0.01, precision="float32", edges=0.0):
    """Two triangles sharing the edge (0, 1) along x; 0, 1 and 2 pinned, wing 3 (mass ``mass``, height
    0.1 m over the edge) folded by ``fold`` rad from flat, with a flat rest angle; with ``edges`` [N/m],
    springs along the wing's two triangle edges hold its distance to the hinge (a free wing, pushed only
    perpendicular to its radius, drifts outward: r̈ = r θ̇²)."""
    height = 0.1
    q = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.1, 0.1, 0.0],
                  [0.1, -height * math.cos(fold), -height * math.sin(fold)]])
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles(q, mass=mass, pinned=[True, True, True, False])
    builder.add_hinges([[0, 1, 2, 3]], stiffness=ke, damping=kd, rest_angle=0.0)
    if edges:
        builder.add_springs([[3, 0], [3, 1]], stiffness=edges)
    return builder.finalize(device, precision=precision), height


def hinge_angles(positions: np.ndarray) -> np.ndarray:
    return dihedral_angle(positions[:, 0], positions[:, 1], positions[:, 2], positions[:, 3])


@pytest.mark.parametrize("integrator", ["symplectic_euler", "implicit_euler"])
def test_hinge_released_from_a_fold_oscillates_at_its_linearised_period(device, integrator):
    """A free wing at height r over the hinge's edge has |∇θ| = 1/r, so the linearised hinge is an
    oscillator of ω² = ke / (m r²): T = 2π r √(m / ke) (the edge springs, at rest length, add no
    transverse stiffness). Folded by 0.01 rad, the springs let r grow by m r θ̇² / k ~ 1e-6 r and the
    nonlinearity shifts the period by O(θ²) ~ 1e-4; the integrators' dispersion is in the discrete
    frequency below (symplectic Euler's (ωh)²/24, backward Euler's (ωh)²/3 at ωh = 0.02)."""
    ke, mass = 0.02, 0.01
    model, r = hinge_pair(device, ke=ke, mass=mass, edges=100.0)
    assert model.hinge_count == 1 and "1 hinges" in model.describe()
    omega = math.sqrt(ke / (mass * r * r))
    dt = 0.02 / omega
    discrete = {"symplectic_euler": math.acos(1.0 - 0.5 * (omega * dt) ** 2) / dt,
                "implicit_euler": math.atan(omega * dt) / dt}[integrator]
    steps = int(3.5 * 2.0 * math.pi / (omega * dt))
    theta = hinge_angles(trajectory(model, make_integrator(integrator, model), dt, steps))
    assert crossing_period(theta, dt) == pytest.approx(2.0 * math.pi / discrete, rel=1e-3)
    assert abs(theta[0]) == pytest.approx(0.01, rel=1e-4)


def test_host_hinge_gradient_is_the_derivative_of_the_angle():
    """The host ∇θ behind the hinges' Gershgorin rows equals central differences of θ (float64, step 1e-6:
    error ~1e-9), and is zero for a degenerate hinge, as on the device."""
    x = np.random.default_rng(1).normal(size=(50, 4, 3))
    gradient = dihedral_gradient(x[:, 0], x[:, 1], x[:, 2], x[:, 3])
    step = 1e-6
    for a in range(4):
        for c in range(3):
            plus, minus = x.copy(), x.copy()
            plus[:, a, c] += step
            minus[:, a, c] -= step
            numeric = (hinge_angles(plus) - hinge_angles(minus)) / (2.0 * step)
            np.testing.assert_allclose(gradient[:, a, c], numeric, atol=1e-7)
    flat = np.zeros((1, 3))
    assert not dihedral_gradient(flat, flat, flat, flat).any()


def test_hinge_advisor_frequency_is_the_linearised_one(device):
    """Power iteration on the Gauss-Newton stiffness gives ω_max = √(ke / (m r²)) exactly at rest (and the
    Gershgorin bound is above it)."""
    ke, mass = 0.02, 0.01
    model, r = hinge_pair(device, ke=ke, mass=mass, fold=0.0)
    estimate = ws.analysis.omega.estimate_omega_max(model)
    omega = math.sqrt(ke / (mass * r * r))
    assert estimate.omega_max == pytest.approx(omega, rel=1e-4)
    assert estimate.gershgorin >= omega * (1.0 - 1e-6)


def test_hinge_forces_are_minus_the_gradient_of_the_family_energy(device):
    """On a perturbed icosphere with dihedral springs (rest angles from the unperturbed mesh, float64), the
    gathered hinge forces equal -∂E/∂x by central differences of the family's energy hook (step 1e-6 m:
    truncation ~1e-12 relative, rounding ~1e-10)."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.5)
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_cloth_mesh(mesh, density=1.0, structural=None, bend=None,
                           dihedral=ws.DihedralMaterial(ke=0.3, kd=0.0))
    model = builder.finalize(device, precision="float64")
    rng = np.random.default_rng(3)
    q = model.particle_q.numpy() + rng.normal(scale=0.02, size=(model.particle_count, 3))
    state = model.state()
    state.particle_q.assign(q)
    ws.eval_forces(model, state, None)
    force = state.particle_f.numpy()
    family = model.families[0]
    step = 1e-6
    numeric = np.zeros_like(q)
    for i in range(0, model.particle_count, 3):
        for c in range(3):
            energies = []
            for sign in (1.0, -1.0):
                shifted = q.copy()
                shifted[i, c] += sign * step
                probe = wp.array(shifted, dtype=model.vec3, device=model.device)
                energies.append(element_energies(model, family, probe).sum())
            numeric[i, c] = -(energies[0] - energies[1]) / (2.0 * step)
    rows = slice(0, model.particle_count, 3)
    np.testing.assert_allclose(force[rows], numeric[rows], rtol=1e-6, atol=1e-9 * np.abs(force).max())
    assert np.abs(force).max() > 1e-3  # the perturbation bends the hinges


def test_hinge_damping_decays_at_its_rate_and_set_world_values_reaches_hinges(device):
    """Two worlds of the folded hinge, the second with an angular damper of ratio ζ = kd / (2 √(ke m r²)) =
    0.2: after two damped periods T_d = 2π / (ω √(1 - ζ²)) the undamped world is at fold · cos(ω 2 T_d) and
    the damped one at fold · exp(-ζ ω 2 T_d) (a damped oscillator's phase is 0 there). Symplectic Euler at
    ωh = 0.005 errs by O(ωh) in the decay rate: 2 %."""
    ke, mass, fold = 0.02, 0.01, 0.01
    model, r = hinge_pair(device, ke=ke, mass=mass, fold=fold, precision="float64")
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles(model.particle_q.numpy(), mass=mass, pinned=[True, True, True, False])
    builder.add_hinges([[0, 1, 2, 3]], stiffness=ke, rest_angle=0.0)
    builder.add_springs([[3, 0], [3, 1]], stiffness=100.0)
    model = builder.finalize(device, precision="float64", worlds=2)
    zeta = 0.2
    kd = zeta * 2.0 * math.sqrt(ke * mass * r * r)
    model.set_world_values("hinge_damping", [[0.0], [kd]])
    np.testing.assert_allclose(model.world_values("hinge_damping"), [[0.0], [kd]])
    omega = math.sqrt(ke / (mass * r * r))
    dt = 0.005 / omega
    steps = int(round(2.0 * 2.0 * math.pi / (omega * math.sqrt(1.0 - zeta**2)) / dt))
    q = trajectory(model, make_integrator("symplectic_euler", model), dt, steps)
    theta = [hinge_angles(q[:, 4 * w: 4 * w + 4]) for w in range(2)]
    assert theta[0][-1] == pytest.approx(fold * math.cos(omega * steps * dt), rel=2e-3)
    assert theta[1][-1] == pytest.approx(fold * math.exp(-zeta * omega * steps * dt), rel=2e-2)


# -- incidence of any degree -----------------------------------------------------------------------------------


def test_head_width_follows_the_degree_distribution():
    """A uniform degree gets its own width and no tail; one hub of degree 200 among degree-4 particles
    gets a narrow head and the hub's entries in the tail; nothing is wider than 32 slots."""
    assert head_slots(np.full(1000, 12)) == 12
    hub = np.concatenate([[200], np.full(999, 4)])
    assert head_slots(hub) == 4
    assert head_slots(np.full(10, 40)) == 32


def test_a_hub_of_200_springs_gathers_exactly_what_scatter_gives(device):
    """A star of 200 springs around one particle (and a ring among the leaves): the gathered forces (head +
    tail) equal the scattered ones (float64, to rounding); the hub's 200 entries are all in its row and
    the gather is deterministic (bitwise equal on a second evaluation)."""
    n = 201
    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, 3))
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles(q, velocities=rng.normal(size=(n, 3)), mass=1.0)
    star = np.stack([np.zeros(200, dtype=int), np.arange(1, n)], axis=1)
    ring = np.stack([np.arange(1, n), np.roll(np.arange(1, n), 1)], axis=1)
    pairs = np.concatenate([star, ring])
    builder.add_springs(pairs, stiffness=rng.uniform(10, 20, len(pairs)), damping=0.5,
                        rest_length=rng.uniform(0.5, 1.5, len(pairs)))
    forces = {}
    for evaluation in ("gather", "scatter"):
        model = builder.finalize(device, precision="float64", spring_evaluation=evaluation)
        state = model.state()
        ws.eval_forces(model, state, None)
        forces[evaluation] = state.particle_f.numpy()
        if evaluation == "gather":
            shape = model.spring_incidence_shape
            assert shape.tail and shape.head_slots == 3  # the leaves: hub + two ring neighbours
            entries = incidence_entries(model.spring_incidence, shape)
            assert sorted(s for s, _ in entries[0]) == list(range(200))
            ws.eval_forces(model, state, None)
            np.testing.assert_array_equal(state.particle_f.numpy(), forces["gather"])
    np.testing.assert_allclose(forces["gather"], forces["scatter"], rtol=1e-12, atol=1e-12)
