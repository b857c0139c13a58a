"""The CPU's symplectic Euler sweep (``kernels/sweep.py``): one thread per world, each spring evaluated once by its
first particle, against the per-particle fused step it replaces on the CPU (``SymplecticEuler(cpu_sweep=False)``,
the CUDA step).

Both evaluate the same force terms: only the order of each particle's sum differs. In float64 a force sum's
rounding is ~1e-16 relative to its terms, which symplectic Euler carries into the positions as h² f/m per step; over
the few dozen steps here the states agree to ~1e-13 m, and the tolerances (1e-10 m, 1e-9 m/s) are far below any
modelling difference (a spring left out or counted twice moves a particle by ≥ 1e-6 m in one step at these
stiffnesses) while well above the rounding. The CPU only: the sweep is not launched on CUDA.
"""

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.kernels.flatten import flat_launch
from warpspring.kernels.sweep import GRID_CHUNK, grid_vectorised, sweeps

DT = 1.0e-3
STEPS = 40
ATOL_Q, ATOL_QD = 1.0e-10, 1.0e-9


def cloth(*, worlds=1, ground=False, hinges=False, device="cpu", stabilizers=None, **finalize) -> ws.Model:
    """A 7 × 6 float64 cloth (structural, shear and bend springs of three stiffnesses), two corners pinned, with a
    pinch of drag; ``ground``: a ground plane it falls onto; ``hinges``: dihedral hinges too (a second family).
    Spaced 0.125 m, a binary fraction, so that every spring of a group has the very same rest length in float64 and
    the groups are uniform (the grid layout; 0.1 m gives lengths an ulp apart, hence the per-spring layout).
    ``stabilizers``: the builder's, if given."""
    builder = ws.ModelBuilder() if stabilizers is None else ws.ModelBuilder(stabilizers=stabilizers)
    builder.add_cloth_grid(nx=7, ny=6, spacing=0.125, origin=(0.0, 0.0, 0.05 if ground else 1.0), particle_mass=0.05,
                           structural=ws.SpringMaterial(800.0, 4.0), shear=ws.SpringMaterial(300.0, 2.0),
                           bend=ws.SpringMaterial(100.0, 1.0), pin=["top-left", "top-right"],
                           dihedral=ws.DihedralMaterial(1.0e-3, 1.0e-4) if hinges else None)
    if ground:
        builder.add_ground_plane(height=0.0)
    model = builder.finalize(device, precision="float64", spring_evaluation="gather", worlds=worlds, **finalize)
    model.gravity = (0.3, 0.0, -9.81)
    model.drag = 0.02
    return model


def both(model: ws.Model, steps: int = STEPS, *, velocities=None) -> tuple:
    """Trajectories of the sweep and of the per-particle step from the same start (random velocities, so that every
    damper works from the first step)."""
    start = model.state()
    rng = np.random.default_rng(3)
    qd = velocities if velocities is not None else rng.normal(scale=0.3, size=start.particle_qd.shape)
    runs = []
    for sweep in (True, False):
        integrator = ws.SymplecticEuler(model, cpu_sweep=sweep)
        a, b = model.state(), model.state()
        a.particle_qd.assign(qd)
        out = []
        for _ in range(steps):
            integrator.step(a, b, None, DT)
            a, b = b, a
            out.append((a.particle_q.numpy().copy(), a.particle_qd.numpy().copy()))
        runs.append(out)
    return runs


def assert_same(runs) -> None:
    for (q_sweep, qd_sweep), (q_fused, qd_fused) in zip(*runs):
        np.testing.assert_allclose(q_sweep, q_fused, rtol=0.0, atol=ATOL_Q)
        np.testing.assert_allclose(qd_sweep, qd_fused, rtol=0.0, atol=ATOL_QD)


@pytest.mark.parametrize("layout", [{}, {"spring_grid": False}, {"spring_groups": False}])
def test_the_sweep_steps_as_the_per_particle_step_in_every_layout(layout):
    """The grid layout (neighbours from rows and columns), the grouped table and the per-spring table: the same
    states as the per-particle step."""
    model = cloth(**layout)
    assert sweeps(model.force_features(None))
    # The grid layout's springs take the vectorised pass (``grid_spring_pass``), the tables ``forward``.
    assert grid_vectorised(model.force_features(None).families[0]) == (layout == {})
    assert_same(both(model))


@pytest.mark.parametrize("shape", [(37, 9), (150, 5)])
def test_the_vectorised_grid_pass_across_its_chunks(shape):
    """Grids larger than the pass's chunk of particles (``GRID_CHUNK``): rows that end inside a chunk (37 columns) and
    rows longer than a chunk (150), so that chunks start mid-row and the pairs wrapping onto the next row fall at
    every place in a chunk; two worlds of their own stiffness. The same states as the per-particle step."""
    nx, ny = shape
    assert nx * ny > 2 * GRID_CHUNK
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=nx, ny=ny, spacing=0.125, origin=(0.0, 0.0, 1.0), particle_mass=0.05,
                           structural=ws.SpringMaterial(800.0, 4.0), shear=ws.SpringMaterial(300.0, 2.0),
                           bend=ws.SpringMaterial(100.0, 1.0), pin=["top-left", "top-right"])
    model = builder.finalize("cpu", precision="float64", spring_evaluation="gather", worlds=2)
    assert grid_vectorised(model.force_features(None).families[0])
    ke = model.world_values("spring_stiffness")[0]
    model.set_world_values("spring_stiffness", ke[None, :] * np.array([1.0, 1.5])[:, None])
    assert_same(both(model, 10))


def test_the_vectorised_grid_pass_in_float32():
    """The grid's vectorised pass compiled for float32 against the per-particle step: the same forces summed in
    another order, so the states differ by float32 rounding only. Per step a force sum's rounding (~6e-8 relative,
    forces ~1 N on 0.05 kg) moves a velocity by ~h f/m · 6e-8 ≈ 1e-9 m/s; over 40 steps and the springs' coupling
    (ωh ≈ 0.4 here) the states agree to ~1e-6 m, far below a spring left out or counted twice (≥ 1e-4 m over
    these steps)."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=7, ny=6, spacing=0.1, origin=(0.0, 0.0, 1.0), particle_mass=0.05,
                           structural=ws.SpringMaterial(800.0, 4.0), shear=ws.SpringMaterial(300.0, 2.0),
                           bend=ws.SpringMaterial(100.0, 1.0), pin=["top-left", "top-right"])
    model = builder.finalize("cpu", spring_evaluation="gather")
    assert grid_vectorised(model.force_features(None).families[0])
    for (q_sweep, qd_sweep), (q_fused, qd_fused) in zip(*both(model)):
        np.testing.assert_allclose(q_sweep, q_fused, rtol=0.0, atol=1.0e-5)
        np.testing.assert_allclose(qd_sweep, qd_fused, rtol=0.0, atol=1.0e-3)


def test_the_sweep_with_worlds_of_their_own_values_and_a_held_world():
    """Three worlds with their own stiffness, damping, masses and gravity: each as in the per-particle step (every
    world's row read once per sweep), and a held world left as it was by the hold pass after the sweep."""
    model = cloth(worlds=3)
    ke = model.world_values("spring_stiffness")[0]
    model.set_world_values("spring_stiffness", ke[None, :] * np.array([0.5, 1.0, 2.0])[:, None])
    model.set_world_values("spring_damping", np.array([0.5, 3.0, 1.0])[:, None] * np.ones_like(ke)[None, :])
    model.set_world_values("particle_mass", np.array([0.04, 0.05, 0.08])[:, None] * np.ones(model.particle_count))
    model.set_world_values("gravity", [[0.0, 0.0, -9.81], [0.0, 1.0, -5.0], [0.5, 0.0, -12.0]])
    assert_same(both(model))
    model.set_world_enabled([1], False)
    runs = both(model)
    assert_same(runs)
    n = model.particle_count
    held = model.state().particle_q.numpy()[n:2 * n]
    np.testing.assert_array_equal(runs[0][-1][0][n:2 * n], held)


def test_the_sweep_with_contacts_a_second_family_and_external_forces():
    """A cloth falling onto the ground (contacts fused into the sweep) with dihedral hinges (a second family,
    gathered per particle) and an external force per particle (the control's)."""
    model = cloth(ground=True, hinges=True)
    assert len(model.families) == 2 and sweeps(model.force_features(None))
    runs = both(model, 60)
    assert_same(runs)
    assert runs[0][-1][0][:, 2].min() >= -1.0e-9  # the ground held it
    control = model.control()
    rng = np.random.default_rng(11)
    control.particle_force = wp.array(rng.normal(scale=0.2, size=(model.particle_count, 3)), dtype=model.vec3,
                                      device="cpu")
    out = []
    for sweep in (True, False):
        a, b = model.state(), model.state()
        integrator = ws.SymplecticEuler(model, cpu_sweep=sweep)
        for _ in range(STEPS):
            integrator.step(a, b, control, DT)
            a, b = b, a
        out.append(a.particle_q.numpy())
    np.testing.assert_allclose(out[0], out[1], rtol=0.0, atol=ATOL_Q)


def test_the_sweep_with_a_tail_and_per_spring_laws():
    """A random network (particles with more springs than the table's head holds go to its tail) of linear, square
    and asymmetric springs, rest lengths 0.6-1.4 times the built distances."""
    rng = np.random.default_rng(5)
    n = 40
    q = rng.uniform(-1.0, 1.0, (n, 3))
    builder = ws.ModelBuilder()
    builder.add_particles(q, mass=rng.uniform(0.5, 2.0, n))
    hub = np.stack([np.zeros(n - 1, dtype=np.int64), np.arange(1, n)], 1)  # particle 0 holds a spring to every other
    pairs = np.unique(np.sort(rng.integers(0, n, (200, 2)), axis=1), axis=0)
    pairs = np.concatenate([hub, pairs[(pairs[:, 0] != pairs[:, 1]) & (pairs[:, 0] != 0)]])
    for group, options in zip(np.array_split(pairs, 3), ({}, {"law": "square"}, {"compression_stiffness": 3.0})):
        distance = np.linalg.norm(q[group[:, 1]] - q[group[:, 0]], axis=1)
        builder.add_springs(group, stiffness=10.0, damping=0.2,
                            rest_length=distance * rng.uniform(0.6, 1.4, len(group)), **options)
    model = builder.finalize("cpu", precision="float64", spring_evaluation="gather")
    assert model.force_features(None).families[0].incidence.tail  # the hub's springs reach the tail
    runs = both(model, 30, velocities=rng.normal(scale=0.5, size=(n, 3)))
    assert_same(runs)


def test_the_guards_power_sums_are_the_per_particle_steps():
    """With the default guard the sweep counts the dampers' and drag's energy as the per-particle step does (the
    springs' dampers' part swept with their force), adding a world's up in float64 into its first entry where the
    per-particle step adds each particle's to its own: the balances the guard's checks took from the power sums (the
    sums themselves are cleared at every check) and the states agree."""
    sums, states = [], []
    for sweep in (True, False):
        model = cloth()
        sim = ws.Simulator(model, fps=60, substeps=8, integrator=ws.SymplecticEuler(model, cpu_sweep=sweep),
                           guard=ws.GuardLimits())
        sim.state.particle_qd.assign(np.random.default_rng(3).normal(scale=0.3, size=(model.particle_count, 3)))
        for _ in range(3):
            sim.step_frame()
        assert sim.integrator.power is not None  # counted in the step
        balance = sim.guard.energy_balance()
        sums.append(np.concatenate([balance.dissipated, balance.work, balance.energy]))
        states.append(sim.state.particle_q.numpy())
    assert np.abs(sums[1][:1]).max() > 1.0e-6  # the dampers' and drag's dissipation was counted (one world)
    np.testing.assert_allclose(sums[0], sums[1], rtol=1.0e-9, atol=1.0e-15)
    np.testing.assert_allclose(states[0], states[1], rtol=0.0, atol=ATOL_Q)


def test_the_sweep_ignores_what_the_force_arrays_held_and_leaves_them_zero():
    """The sweep's scratch is the two states' force arrays: whatever they held before a step (another integrator's
    forces, a user's writes), the step is the same; it leaves the input's zero (the output's is the dampers' scratch,
    used with the guard only: untouched here)."""
    model = cloth(worlds=2)
    integrator = ws.SymplecticEuler(model)
    clean = (model.state(), model.state())
    dirty = (model.state(), model.state())
    rng = np.random.default_rng(2)
    for state in dirty:
        state.particle_f.assign(rng.normal(scale=50.0, size=state.particle_f.shape + (3,)))
    for a, b in (clean, dirty):
        integrator.step(a, b, None, DT)
    np.testing.assert_array_equal(dirty[1].particle_q.numpy(), clean[1].particle_q.numpy())
    np.testing.assert_array_equal(dirty[1].particle_qd.numpy(), clean[1].particle_qd.numpy())
    np.testing.assert_array_equal(dirty[0].particle_f.numpy(), 0.0)


def test_the_option_changes_nothing_on_cuda(device):
    """``cpu_sweep`` selects the CPU's step only: on CUDA both settings launch the per-particle step (bit for bit the
    same states); on the CPU the two steps agree to the rounding of their sums."""
    model = cloth(device=device)
    runs = both(model, 10)
    if device == "cpu":
        assert_same(runs)
        return
    for (q_sweep, qd_sweep), (q_fused, qd_fused) in zip(*runs):
        np.testing.assert_array_equal(q_sweep, q_fused)
        np.testing.assert_array_equal(qd_sweep, qd_fused)


@pytest.mark.parametrize("layout", ["grid", "table"])
def test_the_force_sweep_is_eval_forces_per_particle(layout):
    """On the CPU the other integrators' force evaluation is the sweep's forces alone (``eval_forces``): at a moved,
    moving state of the hinged cloth with an external force, the same total force on every particle, pinned ones
    included, as the per-particle kernel (float64: the same terms summed in another order, 1e-12 of the largest
    force), with the force clamp on (the power not counted: the guard counts none under it), and with the guard's
    power sums counted the same h·power added to them (a step's start, RK4's rule). RK4, velocity Verlet and midpoint
    then step as before within the same rounding."""
    from warpspring.core.forces import PowerSums, eval_forces, force_inputs
    from warpspring.kernels.flatten import flat_launch
    from warpspring.kernels.forces import POWER_DAMPERS, POWER_WORK, eval_forces_kernel

    def forces(clamped: bool, counted: bool):
        model = cloth(hinges=True, spring_grid=layout == "grid",
                      stabilizers=ws.Stabilizers(max_particle_force=0.4) if clamped else None)
        control = model.control()
        control.set_particle_force((0.0, 0.05, 0.0))
        state = model.state()
        rng = np.random.default_rng(3)
        state.particle_q.assign(state.particle_q.numpy() + rng.uniform(-0.01, 0.01, (model.particle_count, 3)))
        state.particle_qd.assign(rng.uniform(-0.5, 0.5, (model.particle_count, 3)))
        features = model.force_features(control)
        assert sweeps(features) and features.clamp_particle_force == clamped
        modes = (POWER_DAMPERS, POWER_WORK) if counted else None  # the springs' dampers, the hinges' force
        results = []
        for swept in (True, False):
            out = wp.zeros_like(state.particle_f)
            power = (PowerSums(modes=modes, h=1e-3, sums=wp.zeros(model.particle_count, dtype=wp.vec2d, device="cpu"))
                     if counted else None)
            if swept:  # (the sweep's forces alone did run)
                import warpspring.core.forces as forces_module

                calls = []
                real = forces_module.symplectic_euler_sweep_kernel
                with pytest.MonkeyPatch.context() as patch:
                    patch.setattr(forces_module, "symplectic_euler_sweep_kernel",
                                  lambda *args: calls.append(args) or real(*args))
                    eval_forces(model, state, control, particle_f=out, power=power)
                assert len(calls) == 1 and calls[0][-1] is True
            else:
                flat_launch(eval_forces_kernel(model.scalar, features, modes), dim=model.particle_dim,
                            inputs=[model.particle_count, model.particle_flags, *force_inputs(model, control, features),
                                    state.particle_q, state.particle_qd, 1e-3],
                            outputs=[out, None, None, power.sums if counted else None], device="cpu")
            results.append((out.numpy(), power.sums.numpy() if counted else None))
        return results

    (f_swept, _), (f_plain, _) = forces(clamped=True, counted=False)
    assert np.linalg.norm(f_plain, axis=1).max() <= 0.4 * (1 + 1e-12)  # the clamp acted
    np.testing.assert_allclose(f_swept, f_plain, rtol=0, atol=1e-12 * np.abs(f_plain).max())
    (f_swept, p_swept), (f_plain, p_plain) = forces(clamped=False, counted=True)
    np.testing.assert_allclose(f_swept, f_plain, rtol=0, atol=1e-12 * np.abs(f_plain).max())
    np.testing.assert_allclose(p_swept, p_plain, rtol=0, atol=1e-12 * np.abs(p_plain).max())
    assert np.abs(p_plain[:, 0]).max() > 0  # the dampers took energy out
    for name in ("rk4", "velocity_verlet", "midpoint"):
        runs = []
        for swept in (True, False):
            m = cloth(hinges=True, spring_grid=layout == "grid")
            integrator = ws.core.integrators.make_integrator(name, m)
            a, b = m.state(), m.state()
            with pytest.MonkeyPatch.context() as patch:
                if not swept:  # the per-particle kernel alone
                    patch.setattr("warpspring.core.forces.sweeps", lambda features: False)
                for _ in range(20):
                    integrator.step(a, b, None, DT)
                    a, b = b, a
            runs.append(a.particle_q.numpy())
        np.testing.assert_allclose(runs[0], runs[1], rtol=0, atol=ATOL_Q, err_msg=name)


@pytest.mark.parametrize("precision, shape", [("float64", (7, 6)), ("float64", (150, 5)), ("float32", (37, 9))])
def test_the_grid_energy_pass_is_the_element_loop(precision, shape):
    """The guard's energy pass over a grid cloth's springs on the CPU (``sweep.grid_energy_pass``, walked by direction
    and row) against the element loop it replaces (``family_energy_func``: the same kernel compiled for CUDA's
    lanes, launched on the CPU one lane a world), and both against NumPy float64 over the model's springs: energy
    ½ ke (|d| - L)², strain |d|/L - 1 and the dampers' power kd ((vj - vi)·d̂)², in two worlds of their own
    stiffness, from random positions and velocities (every spring stretched or compressed, every damper working).
    Each spring's terms are the same operations in the model's precision, so the two passes' float64 sums differ
    by their order only (1e-12 relative) and their largest strain is the same number; against float64 NumPy the
    float32 model's terms round at 1e-6 relative."""
    from warpspring.kernels.guards import guard_energy_kernel

    nx, ny = shape
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=nx, ny=ny, spacing=0.125, origin=(0.0, 0.0, 1.0), particle_mass=0.05,
                           structural=ws.SpringMaterial(800.0, 4.0), shear=ws.SpringMaterial(300.0, 2.0),
                           bend=ws.SpringMaterial(100.0, 1.0), pin=["top-left"])
    model = builder.finalize("cpu", precision=precision, spring_evaluation="gather", worlds=2)
    family = model.families[0]
    spec = family.spec(model)
    assert grid_vectorised(spec)
    ke = model.world_values("spring_stiffness")[0]
    model.set_world_values("spring_stiffness", ke[None, :] * np.array([1.0, 1.5])[:, None])
    rng = np.random.default_rng(11)
    state = model.state()
    q = state.particle_q.numpy().astype(np.float64)
    state.particle_q.assign(q + rng.normal(scale=0.02, size=q.shape))
    state.particle_qd.assign(rng.normal(scale=0.5, size=q.shape))
    scalar = model.scalar
    worlds = model.world_count
    results = []
    for tiled in (False, True):  # the grid pass, then the element loop
        outs = [wp.zeros((worlds, 1), dtype=wp.float64), wp.full((worlds, 1), -1.0, dtype=wp.float64),
                wp.zeros((worlds, 1), dtype=wp.float64)]
        flat_launch(guard_energy_kernel(scalar, spec, tiled, True), dim=(worlds, 1, 1), block_dim=1,
                    inputs=[model.particle_count, family.element_count, 0, model.world_enabled,
                            family.arrays(model), model.inputs, wp.zeros((worlds, 7), dtype=wp.int32), state.particle_q,
                            state.particle_qd, 1],
                    outputs=outs, device="cpu")
        results.append([o.numpy()[:, 0] for o in outs])
    (energy, strain, power), (energy_loop, strain_loop, power_loop) = results
    np.testing.assert_allclose(energy, energy_loop, rtol=1.0e-12)
    np.testing.assert_array_equal(strain, strain_loop)
    np.testing.assert_allclose(power, power_loop, rtol=1.0e-12)
    # Against float64 NumPy over the model's spring list.
    ends = model.spring_indices.numpy()
    rest = model.spring_rest_length.numpy().astype(np.float64)
    x = state.particle_q.numpy().astype(np.float64).reshape(worlds, -1, 3)
    v = state.particle_qd.numpy().astype(np.float64).reshape(worlds, -1, 3)
    stiffness = model.world_values("spring_stiffness").astype(np.float64)
    damping = model.world_values("spring_damping").astype(np.float64)
    rtol = 1.0e-12 if precision == "float64" else 1.0e-5
    for w in range(worlds):
        d = x[w, ends[:, 1]] - x[w, ends[:, 0]]
        length = np.linalg.norm(d, axis=1)
        rate = np.einsum("ij,ij->i", v[w, ends[:, 1]] - v[w, ends[:, 0]], d / length[:, None])
        np.testing.assert_allclose(energy[w], np.sum(0.5 * stiffness[w] * (length - rest) ** 2), rtol=rtol)
        np.testing.assert_allclose(strain[w], np.max(length / rest - 1.0), rtol=rtol)
        np.testing.assert_allclose(power[w], np.sum(damping[w] * rate**2), rtol=rtol)
