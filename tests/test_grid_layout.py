"""The grid layout of the spring gather (``Model.spring_layout == "grid"``): on a model that is one cloth grid in
grid order, a uniform group's slot finds its neighbour from the particle's row and column and a compile-time
direction, never from the incidence table (``SpringSpec.grid_slots``, ``kernels/springs.grid_neighbour``).

finalize takes it only where the grouped table is exactly what the directions give, so the grid and table
gathers sum the same terms in the same order (zeros where the table has padding): they agree bit for bit, which
is what these tests assert, with the table's entries of the uniform slots overwritten in the grid model to show
that it never reads them. The grid's size and the groups' values are device data: sizes share one kernel, and
values written between frames act.
"""

import numpy as np
import pytest

import warpspring as ws
from helpers import loaded_modules, trajectory
from warpspring.core.integrators import INTEGRATORS, make_integrator

DT = 1.0 / 960.0
STEPS = 24
#: The ANCHORS grid's slot directions (dx, dy) [columns, rows]: structural, shear, bend, each a particle's springs
#: where it is the first end (in spring order: along rows, then along columns), then where it is the second.
GRID_DIRECTIONS = ((1, 0), (0, 1), (-1, 0), (0, -1), (1, 1), (-1, 1), (-1, -1), (1, -1),
                   (2, 0), (0, 2), (-2, 0), (0, -2))
GRID_SLOTS = (0,) * 4 + (1,) * 4 + (2,) * 4
MIXED_SLOTS = (-1,) * 4 + GRID_SLOTS[4:]


def cloth(device, *, nx=12, ny=12, pin=("top-left", "top-right"), scale=1.0, **finalize):
    """An nx × ny cloth (the springs of test_spring_groups.py, stiffness × ``scale``), gathered, gravity on."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=nx, ny=ny, spacing=0.1, origin=(-0.55, -0.55, 1.0), particle_mass=0.1,
                           structural=ws.SpringMaterial(1.0e3 * scale, 10.0),
                           shear=ws.SpringMaterial(500.0 * scale, 5.0), bend=ws.SpringMaterial(200.0 * scale, 2.0),
                           pin=list(pin))
    model = builder.finalize(device, **{"spring_evaluation": "gather", **finalize})
    model.gravity = (0.0, 0.0, -9.81)
    return model


def pair(device, **options):
    """The same cloth in the grid layout and in the grouped table's."""
    grid, table = cloth(device, **options), cloth(device, spring_grid=False, **options)
    assert (grid.spring_layout, table.spring_layout) == ("grid", "groups")
    assert grid.spring_slot_groups == table.spring_slot_groups
    return grid, table


def hide_table(model):
    """Overwrite the table's entries of the uniform groups' slots with particle 0 and spring 0: a gather that
    read them would sum wrong springs."""
    uniform = np.array(model.spring_slot_groups) >= 0
    for name in ("head_local", "head_element"):
        array = getattr(model.spring_incidence, name)
        values = array.numpy()
        values[uniform] = 0
        array.assign(values)


def positions(model, steps=STEPS, velocities=None):
    if velocities is not None:
        model.particle_qd.assign(velocities.astype(np.float32))
    return trajectory(model, ws.SymplecticEuler(model), DT, steps)


def simulator(model, state=None):
    """A simulator of ``model`` (60 fps, 16 substeps, no guard), started from ``state`` if given."""
    sim = ws.Simulator(model, fps=60, substeps=16, guard=None)
    if state is not None:
        for name in ("particle_q", "particle_qd", "time"):
            getattr(sim.state, name).assign(getattr(state, name))
    return sim


def test_the_grid_layout_is_taken_for_one_grid_in_grid_order_only():
    """One gathered grid: the grid layout, its directions and (nx, ny) on the device; the options and the
    scatter keep theirs; a mesh cloth, a grid with one more particle, two grids, a grid too small for a particle
    to hold every direction, and a grid with springs the directions do not give keep the table."""
    model = cloth("cpu", nx=9, ny=14)
    assert model.spring_layout == "grid" and model.spring_grid_slots == GRID_DIRECTIONS
    np.testing.assert_array_equal(model.spring_grid_size.numpy(), [9, 14])
    assert "springs (grid)" in model.describe()
    assert cloth("cpu", spring_grid=False).spring_layout == "groups"
    assert cloth("cpu", spring_groups=False).spring_layout == "springs"
    assert cloth("cpu", spring_evaluation="scatter").spring_layout == "scatter"

    def layout(build):
        builder = ws.ModelBuilder()
        build(builder)
        model = builder.finalize("cpu", spring_evaluation="gather")
        assert model.spring_grid_slots == () and model.spring_grid_size is None
        return model.spring_layout

    def grid(builder, n=6):
        return builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, particle_mass=0.1)

    def tethered(builder):  # springs of a fourth group that no direction gives
        grid(builder)
        builder.add_springs([[0, 14], [3, 20]], stiffness=10.0, rest_length=0.3, family="tethers")

    rows, columns = np.meshgrid(np.arange(6), np.arange(6), indexing="ij")
    vertices = np.stack([columns * 0.1, rows * 0.1, 0.0 * rows], axis=-1).reshape(-1, 3)
    quads = (rows * 6 + columns)[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([quads, quads + 1, quads + 7], 1), np.stack([quads, quads + 7, quads + 6], 1)])
    assert layout(lambda b: b.add_cloth_mesh(vertices, faces, mass=1.0)) in ("groups", "springs")
    assert layout(lambda b: (grid(b), b.add_particles([[0.0, 0.0, 1.0]]))) == "groups"
    assert layout(lambda b: (grid(b), grid(b))) == "groups"
    assert layout(lambda b: grid(b, 3)) == "groups"
    assert layout(tethered) == "groups"


def test_grid_gather_is_the_table_gather_bit_for_bit(device):
    """A free 9 × 14 grid given random velocities (every spring of every direction works, rows and columns
    differ) and the 12 × 12 grid hanging from its pinned corners: the grid layout, with the uniform slots'
    table entries overwritten, gives the table layout's positions bit for bit after 24 substeps. The second
    size loads no new kernel module: nx and ny are data."""
    rng = np.random.default_rng(7)
    free = pair(device, nx=9, ny=14, pin=())
    velocities = rng.uniform(-0.5, 0.5, (free[0].particle_count, 3))
    hide_table(free[0])
    paths = [positions(model, velocities=velocities) for model in free]
    assert np.abs(paths[0][-1] - paths[0][0]).max() > 1.0e-3  # the cloth moved
    np.testing.assert_array_equal(paths[0], paths[1])
    before = loaded_modules()
    hanging = pair(device)
    hide_table(hanging[0])
    paths = [positions(model) for model in hanging]
    assert loaded_modules() == before
    np.testing.assert_array_equal(paths[0], paths[1])
    corners = [11 * 12, 11 * 12 + 11]  # the top row's ends, pinned
    np.testing.assert_array_equal(paths[0][:, corners], paths[0][:1, corners].repeat(STEPS + 1, 0))


def test_worlds_keep_the_grid_and_match_the_table(device):
    """Three worlds with their own gravity and stiffness rows (×1, ×4, ×0.25 in every group) keep the grid layout,
    read each world's values, and match the table layout bit for bit; the worlds differ."""
    models = pair(device, worlds=3)
    ke = models[0].world_values("spring_stiffness")[0]
    for model in models:
        model.set_world_values("gravity", [[0.0, 0.0, -9.81], [0.0, 0.0, -4.0], [2.0, 0.0, -9.81]])
        model.set_world_values("spring_stiffness", ke[None, :] * np.array([[1.0], [4.0], [0.25]]))
    assert models[0].spring_layout == "grid" and models[0].spring_stiffness.shape[0] == 3
    hide_table(models[0])
    grid, table = (positions(model) for model in models)
    np.testing.assert_array_equal(grid, table)
    worlds = grid[-1].reshape(3, -1, 3)
    # Well beyond float32's rounding of |x| ≈ 1 m (1.2e-7): the worlds' own values are read.
    assert np.abs(worlds[1] - worlds[0]).max() > 1.0e-6 and np.abs(worlds[2] - worlds[0]).max() > 1.0e-6


def test_group_values_written_between_frames_act(device):
    """Every stiffness doubled between captured frames is a value write (same revision, still the grid) and the
    run continues bit for bit as a cloth built twice as stiff from the same state, away from the run without it."""
    model = cloth(device)
    sim = simulator(model)
    sim.step_frame()
    revision = model.revision
    unchanged = simulator(cloth(device), sim.state)
    doubled = simulator(cloth(device, scale=2.0), sim.state)
    model.set_world_values("spring_stiffness", 2.0 * model.world_values("spring_stiffness"))
    assert (model.revision, model.spring_layout) == (revision, "grid")
    for run in (sim, unchanged, doubled):
        for _ in range(2):
            run.step_frame()
    np.testing.assert_array_equal(sim.state.particle_q.numpy(), doubled.state.particle_q.numpy())
    assert np.abs(sim.state.particle_q.numpy() - unchanged.state.particle_q.numpy()).max() > 1.0e-6


def test_a_per_spring_value_reads_its_group_from_the_table(device):
    """One structural spring's damping written in place, then ``refresh_spring_layout``: the structural slots read
    the table per spring (a structural change) while shear and bend stay on the grid, and the run continues bit
    for bit as the table layout given the same value; the shear and bend slots' entries still go unread."""
    models = pair(device)
    for model in models:
        kd = model.spring_damping.numpy()
        kd[0, 3] *= 5.0
        model.spring_damping.assign(kd)
        revision = model.revision
        model.refresh_spring_layout()
        assert model.revision > revision and model.spring_slot_groups == MIXED_SLOTS
    assert models[0].spring_layout == "grid" and models[0].spring_grid_slots == GRID_DIRECTIONS
    hide_table(models[0])
    grid, table = (positions(model) for model in models)
    np.testing.assert_array_equal(grid, table)


@pytest.mark.slow
def test_every_integrator_steps_the_grid_to_the_tables_bits(device):
    """Each of the seven integrators (whose force evaluations go through the same gathered hook; implicit Euler's
    products, dopri5's error control read the table as before), two worlds, four steps: the grid layout gives
    the table layout's positions bit for bit. (Slow: it compiles every integrator's kernels for both layouts.)"""
    for name in sorted(INTEGRATORS):
        models = pair(device, worlds=2)
        grid, table = (trajectory(model, make_integrator(name, model), DT, 4) for model in models)
        assert np.abs(grid[-1] - grid[0]).max() > 1.0e-5, name  # it moved: 4 steps of free fall drop 1.1e-4 m
        np.testing.assert_array_equal(grid, table, err_msg=name)
