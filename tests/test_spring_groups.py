"""Spring data per group: where every spring of a group has one rest length, ke and kd, the gather reads them
once per group and never a slot's spring index (``Model.spring_slot_groups``, ``kernels/springs.py``).

The grouped force sums the same terms in the same slot order as the per-spring force over the same table, so
the two agree bit for bit; a per-spring value written between frames switches its group's slots to per-spring
reads (a structural change) and continues bit for bit as a model given that value before its first step.
"""

import numpy as np

import warpspring as ws
from helpers import trajectory

DT = 1.0 / 960.0
STEPS = 24
#: The ANCHORS grid's groups, in ``spring_families`` order, and the head they lay out (4 neighbours each).
GRID_SLOTS = (0,) * 4 + (1,) * 4 + (2,) * 4
#: The same once the structural group holds two values: its slots read per spring (-1).
MIXED_SLOTS = (-1,) * 4 + GRID_SLOTS[4:]
#: The structural spring from the top-left (pinned) corner: the first spring of the top row, 11 · 11.
CORNER_SPRING = 121


def cloth(device, *, scale=1.0, **finalize):
    """A 12 × 12 cloth hanging from its top corners, three uniform groups of stiffness × ``scale``, gathered."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=12, ny=12, spacing=0.1, origin=(-0.55, -0.55, 1.0), particle_mass=0.1,
                           structural=ws.SpringMaterial(1.0e3 * scale, 10.0),
                           shear=ws.SpringMaterial(500.0 * scale, 5.0), bend=ws.SpringMaterial(200.0 * scale, 2.0),
                           pin=["top-left", "top-right"])
    model = builder.finalize(device, **{"spring_evaluation": "gather", **finalize})
    model.gravity = (0.0, 0.0, -9.81)
    return model


def simulator(model, state=None):
    """A simulator of ``model`` (60 fps, 16 substeps, no guard), started from ``state`` if given."""
    sim = ws.Simulator(model, fps=60, substeps=16, guard=None)
    if state is not None:
        for name in ("particle_q", "particle_qd", "time"):
            getattr(sim.state, name).assign(getattr(state, name))
    return sim


def positions(model, steps=STEPS):
    return trajectory(model, ws.SymplecticEuler(model), DT, steps)


def test_a_grid_lays_out_one_slot_range_per_group():
    """The grid's structural, shear and bend groups each own four head slots; every entry of slot k is a
    spring of group k // 4 or padding (the particle itself), and the table holds each spring at both ends."""
    model = cloth("cpu")
    assert model.spring_slot_groups == GRID_SLOTS
    assert model.spring_incidence_shape == (12, False)
    element = model.spring_incidence.head_element.numpy()
    other = model.spring_incidence.head_local.numpy()
    group = np.zeros(model.spring_count, dtype=int)
    for g, members in enumerate(model.spring_families.values()):
        group[members] = g
    particle = np.broadcast_to(np.arange(model.particle_count), other.shape)
    real = other != particle
    assert (group[element[real]] == np.array(GRID_SLOTS)[:, None].repeat(other.shape[1], 1)[real]).all()
    ends = np.sort(np.stack([particle[real], other[real]]), axis=0)
    pairs = np.sort(model.spring_indices.numpy().reshape(-1, 2), axis=1)
    np.testing.assert_array_equal(ends.T, pairs[element[real]])
    assert real.sum() == 2 * model.spring_count
    for other_layout in (cloth("cpu", spring_groups=False), cloth("cpu", spring_evaluation="scatter")):
        assert other_layout.spring_slot_groups == ()


def test_grouped_gather_is_the_per_spring_gather_bit_for_bit(device):
    """Grouped and per-spring gathers over the same table give the same bits; the per-spring scatter (another
    summation order) agrees to float32 rounding: a few ulps of |x| ≈ 1 m per step, over the steps taken."""
    grouped = cloth(device)
    per_spring = cloth(device)
    revision = per_spring.revision
    per_spring.spring_slot_groups = ()  # the same table, values read per spring
    assert per_spring.revision == revision + 1
    path = positions(grouped)
    assert np.abs(path[-1] - path[0]).max() > 1.0e-3  # the cloth moved
    np.testing.assert_array_equal(path, positions(per_spring))
    scattered = positions(cloth(device, spring_evaluation="scatter"))
    np.testing.assert_allclose(scattered, path, rtol=0.0, atol=4 * STEPS * np.finfo(np.float32).eps)


def test_per_world_rows_keep_the_groups(device):
    """Three worlds with their own stiffness rows (×1, ×4, ×0.25 in every group) stay grouped, read each world's
    row, and match the per-spring gather bit for bit; the worlds differ (their rows are read)."""
    models = [cloth(device, worlds=3), cloth(device, worlds=3)]
    ke = models[0].world_values("spring_stiffness")[0]
    for model in models:
        model.set_world_values("spring_stiffness", ke[None, :] * np.array([[1.0], [4.0], [0.25]]))
    assert models[0].spring_slot_groups == GRID_SLOTS and models[0].spring_stiffness.shape[0] == 3
    models[1].spring_slot_groups = ()
    grouped, per_spring = (positions(model) for model in models)
    np.testing.assert_array_equal(grouped, per_spring)
    worlds = grouped[-1].reshape(3, -1, 3)
    # Near the pins the rows move the worlds apart by far more than float32's rounding of |x| ≈ 1 m (1.2e-7).
    assert np.abs(worlds[1] - worlds[0]).max() > 1.0e-6 and np.abs(worlds[2] - worlds[0]).max() > 1.0e-6


def test_a_per_spring_value_between_frames_switches_to_per_spring_data(device):
    """Doubling every stiffness between frames keeps the groups (no new revision) and continues bit for bit as
    a cloth built twice as stiff; then stiffening the top-left corner's structural spring 5× reads the
    structural slots per spring (revision bumped, the other groups still per group) and continues bit for bit
    as a model given those values before its first step, and as the per-spring gather, away from the run
    without it (so the agreement is not vacuous)."""
    model = cloth(device)
    sim = simulator(model)
    sim.step_frame()
    revision = model.revision
    ke = model.world_values("spring_stiffness")[0]
    model.set_world_values("spring_stiffness", 2.0 * ke)  # every group stays uniform: a value write
    assert (model.revision, model.spring_slot_groups) == (revision, GRID_SLOTS)
    doubled = simulator(cloth(device, scale=2.0), sim.state)
    for run in (sim, doubled):
        run.step_frame()
    np.testing.assert_array_equal(sim.state.particle_q.numpy(), doubled.state.particle_q.numpy())

    stiffer = 2.0 * ke
    stiffer[CORNER_SPRING] *= 5.0
    model.set_world_values("spring_stiffness", stiffer)
    assert model.revision > revision and model.spring_slot_groups == MIXED_SLOTS
    built = cloth(device, scale=2.0)
    built.spring_stiffness.assign(stiffer[None, :].astype(np.float32))
    built.refresh_spring_layout()
    assert built.spring_slot_groups == MIXED_SLOTS
    per_spring = cloth(device, scale=2.0)
    per_spring.spring_stiffness.assign(stiffer[None, :].astype(np.float32))
    per_spring.spring_slot_groups = ()  # the same table, every value per spring
    reference, gathered = simulator(built, sim.state), simulator(per_spring, sim.state)
    for run in (sim, reference, gathered, doubled):
        for _ in range(2):
            run.step_frame()
    np.testing.assert_array_equal(sim.state.particle_q.numpy(), reference.state.particle_q.numpy())
    np.testing.assert_array_equal(sim.state.particle_q.numpy(), gathered.state.particle_q.numpy())
    assert np.abs(sim.state.particle_q.numpy() - doubled.state.particle_q.numpy()).max() > 1.0e-6


def test_in_place_per_spring_writes_switch_after_refresh(device):
    """Per-spring damping written in place, then ``refresh_spring_layout``: the structural slots read per
    spring; once every group holds two values, the role-major table of a per-spring model comes back; a
    refresh that changes nothing bumps no revision."""
    model = cloth(device)
    revision = model.revision
    model.refresh_spring_layout()
    assert model.revision == revision
    kd = model.spring_damping.numpy()
    kd[0, 3] = 0.5
    model.spring_damping.assign(kd)
    model.refresh_spring_layout()
    assert model.revision > revision and model.spring_slot_groups == MIXED_SLOTS
    for members in list(model.spring_families.values())[1:]:
        kd[0, members[0]] = 0.5
    model.spring_damping.assign(kd)
    model.refresh_spring_layout()
    assert model.spring_slot_groups == ()
    per_spring = cloth(device, spring_groups=False)
    assert model.spring_incidence_shape == per_spring.spring_incidence_shape
    np.testing.assert_array_equal(model.spring_incidence.head_element.numpy(),
                                  per_spring.spring_incidence.head_element.numpy())
