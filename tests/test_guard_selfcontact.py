"""The guard's energy balance with self-collision: the self-collision pass moves particles outside the forces (its
repulsion and cap), so a driven pin pressing cloth against itself does work through the pass, not through a force.
The guard counts that work as each world's kinetic plus elastic energy after the pass less before it
(``Guard._count_corrections``). Left out, it stopped the torture battery's twist1440, whose run is clean, for energy
"created"; counted, that run goes on, and an unstable step in the same scene is still stopped by the balance."""

import numpy as np
import pytest

import warpspring as ws
from warpspring.analysis import torture
from warpspring.kernels.guards import RUNNING_WORK


@pytest.mark.parametrize("n", [6, 24])
def test_the_pass_energy_change_is_counted_exactly(device, n):
    """The count around a change of the state equals the float64 change of the free particles' kinetic energy and the
    springs' elastic energy (to float32 round-off of the positions: the energies are summed in float64), added up
    over every block of the count's grids (24²: several blocks per pass on CUDA)."""
    builder = ws.ModelBuilder()
    springs = ws.SpringMaterial(ke=500.0, kd=0.5)
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, particle_mass=0.1, structural=springs, shear=springs, bend=None,
                           pin=["top-left"])
    builder.add_self_collision(thickness=0.01)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=4)
    guard = sim.guard
    watch = sim.integrator.finish_step.watch
    assert watch is not None and "the work of self-collision's corrections" in guard.balance_terms().describe()
    state = model.state()
    rng = np.random.default_rng(3)
    q0 = model.particle_q.numpy().astype(np.float64) + rng.normal(0.0, 0.01, (model.particle_count, 3))
    v0 = rng.normal(0.0, 0.5, (model.particle_count, 3))
    q1, v1 = q0 + rng.normal(0.0, 0.01, q0.shape), v0 + rng.normal(0.0, 0.5, v0.shape)
    guard._running.zero_()
    state.particle_q.assign(q0.astype(np.float32))
    state.particle_qd.assign(v0.astype(np.float32))
    watch(state, -1.0)
    state.particle_q.assign(q1.astype(np.float32))
    state.particle_qd.assign(v1.astype(np.float32))
    watch(state, 1.0)
    running = guard._running.numpy()[0, :, RUNNING_WORK]
    counted = sum(running[first:first + grid[1]].sum() for _, _, grid, first in guard._correction_layout)
    if device == "cuda:0" and n == 24:
        assert sum(grid[1] for _, _, grid, _ in guard._correction_layout) > 2  # the blocks share the work

    mass = model.world_values("particle_mass")[0].astype(np.float64)
    free = ~model.kinematic_mask()
    ends = model.spring_indices.numpy()
    ke = model.world_values("spring_stiffness")[0].astype(np.float64)
    rest = model.spring_rest_length.numpy().astype(np.float64)

    def energy(q, v):
        q, v = q.astype(np.float32).astype(np.float64), v.astype(np.float32).astype(np.float64)
        stretch = np.linalg.norm(q[ends[:, 0]] - q[ends[:, 1]], axis=1) - rest
        return 0.5 * np.sum(mass[free] * np.sum(v[free] ** 2, axis=1)) + 0.5 * np.sum(ke * stretch ** 2)

    expected = energy(q1, v1) - energy(q0, v0)
    # Each element's energy is evaluated in float32 (the families' energy hooks): relative round-off ~1e-6 of the
    # energies' size, well below the change (a few J here).
    assert counted == pytest.approx(expected, rel=1e-4, abs=1e-5 * energy(q1, v1))


def test_twist1440_is_not_stopped_and_an_unstable_step_in_it_is(device):
    """The torture battery's twist1440 (small, duration 0.7) at 58 substeps (symplectic Euler, ω_max h ≤ 0.66 by the
    springs' bound; the scene's own step is now twice as fine, the pins within a quarter of the cap's reach): with
    the pass's work left out the default guard stopped it at frame 47 for 0.226 J "created" (14 % of the budget)
    while the run was clean; counted, the 48 frames run. Then every spring is made 30 times stiffer (the bound 3.6
    against symplectic Euler's 2) while the cloth presses on itself: the energy balance stops the run within the
    next frame, before any non-finite value."""
    model, _ = torture.build_case("twist1440", size="small", device=device, duration=0.7)
    substeps = 58
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=torture.FPS,
                       substeps=substeps)
    assert "the work of self-collision's corrections" in sim.guard.balance_terms().describe()
    for _ in range(48):
        sim.step_frame()
    sim.settle()
    assert model.self_contact.counts()["pairs"].sum() > 0  # the cloth presses on itself
    model.set_world_values("spring_stiffness", 30.0 * model.world_values("spring_stiffness"))
    with pytest.raises(ws.SimulationError) as stop:
        for _ in range(2):
            sim.step_frame()
        sim.settle()
    assert stop.value.reason == "energy balance", str(stop.value)
    assert sim.frame <= 49


def test_pins_lowering_stacked_cloth_onto_a_collider_are_not_stopped(device):
    """The torture battery's stack (small; its first 60 frames, unaudited) under symplectic Euler with the default
    guard: the pins lower the layers onto the collider, whose contacts' pass does work that the guard must count (in
    the self-collision bracket, which starts before the contacts). A change that took the contacts out of the bracket
    (symplectic Euler fusing them into its update with self-collision too) stopped this clean run at frame 53 for
    0.051 J "created" (14 % of 0.354 J)."""
    result = torture.run_case("stack", "symplectic_euler", size="small", device=device, frames=60, audit_from=60)
    assert result.error is None and result.frames == 60


def test_with_self_collision_the_contacts_work_is_counted_too(device):
    """In a scene with self-collision the bracket starts before the contacts' pass: the summary counts the colliders'
    work with the self-collision's; with strain limiting first (which moves the pins) only the self-collision pass is
    bracketed and the contacts stay a loss left out."""
    for strain, where in ((None, "counted"), (0.1, "losses")):
        builder = ws.ModelBuilder()
        springs = ws.SpringMaterial(ke=500.0, kd=0.5)
        builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, particle_mass=0.1, structural=springs, shear=springs,
                               bend=None, pin=["top-left"])
        builder.add_collider_sphere(center=(0.25, 0.25, -0.2), radius=0.1)
        builder.add_self_collision(thickness=0.01)
        if strain is not None:
            builder.stabilizers = ws.Stabilizers(max_strain=strain)
        model = builder.finalize(device)
        terms = ws.Simulator(model, fps=60, substeps=4).guard.balance_terms()
        contacts = [term for term in getattr(terms, where) if term.startswith("contacts with 1 collider")
                    or term.startswith("the work of contacts with 1 collider")]
        assert contacts and terms.on, terms.describe()
        assert "the work of self-collision's corrections (the energy change across its pass)" in terms.counted
