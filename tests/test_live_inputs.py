"""Live inputs: gravity, drag and every stabiliser threshold live in a device table that captured frames
read, so changing them between frames gives exactly what an uncaptured loop gives, and loads no module.

The bug this guards against: a graph replays its kernels with the arguments it was captured with, so a
value passed by value (or compiled in) is frozen at its first frame. Each test first shows that the
change matters (a run without it ends elsewhere), so that the agreement it then asserts is not vacuous.
"""

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from helpers import loaded_modules, run_frames

STABILIZED = ws.Stabilizers(max_spring_force=40.0, max_particle_force=4.0, max_speed=3.0, max_strain=0.3,
                            strain_iterations=2, biphasic_strain=0.2, biphasic_ratio=3.0)


def cloth(device, *, evaluation="auto", stabilizers=STABILIZED, drag=0.01):
    """A 6 × 6 cloth hanging from its top corners, every stabiliser on."""
    builder = ws.ModelBuilder(drag=drag, stabilizers=stabilizers)
    builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, origin=(-0.25, -0.25, 1.0), particle_mass=0.02,
                           structural=ws.SpringMaterial(60.0, 0.05), shear=ws.SpringMaterial(20.0, 0.02),
                           bend=None, pin=["top-left", "top-right"])
    return builder.finalize(device, spring_evaluation=evaluation)


def change(model, frame):
    """The inputs a user changes between frames: gravity and drag after frame 1, every threshold after
    frame 2, gravity again after frame 3 (values only: every switch stays as it was)."""
    if frame == 1:
        model.gravity = (0.0, 0.0, -1.0)
        model.drag = 0.02
    elif frame == 2:
        model.stabilizers = ws.Stabilizers(max_spring_force=30.0, max_particle_force=3.5, max_speed=2.5,
                                           max_strain=0.25, strain_iterations=2, biphasic_strain=0.15,
                                           biphasic_ratio=4.0)
    elif frame == 3:
        model.gravity = (0.8, 0.0, -9.81)


def run(device, name, *, use_graph, changes=True, evaluation="auto", frames=5):
    model = cloth(device, evaluation=evaluation)
    sim = ws.Simulator(model, integrator=ws.INTEGRATORS[name](model), fps=60, substeps=8, use_graph=use_graph)
    path = []
    for frame in range(1, frames + 1):
        sim.step_frame()
        path.append(sim.state.particle_q.numpy().copy())
        if changes:
            change(model, frame)
    return np.stack(path), sim


@pytest.mark.parametrize("name", sorted(ws.INTEGRATORS))
def test_captured_frames_see_inputs_changed_between_frames(device, name):
    """Captured and uncaptured frame loops agree bit for bit, frame by frame, while gravity, drag and every
    stabiliser threshold change between frames; and the changes moved the cloth (by more than 1 mm)."""
    captured, sim = run(device, name, use_graph=True)
    plain, _ = run(device, name, use_graph=False)
    unchanged, _ = run(device, name, use_graph=True, changes=False)
    np.testing.assert_array_equal(captured, plain)
    assert np.abs(captured[-1] - unchanged[-1]).max() > 1e-3
    assert sim.stepper.captures == 1  # value changes never re-capture


@pytest.mark.parametrize("evaluation", ["gather", "scatter"])
def test_both_spring_paths_read_live_inputs(device, evaluation):
    """The fused gather kernel (CUDA's default) and the scatter path (the CPU's) both read the live table."""
    captured, _ = run(device, "symplectic_euler", use_graph=True, evaluation=evaluation)
    plain, _ = run(device, "symplectic_euler", use_graph=False, evaluation=evaluation)
    np.testing.assert_array_equal(captured, plain)


def test_the_reported_mid_run_change(device):
    """The run that exposed the frozen graph: gravity -9.81 → -1 m/s² and drag 0.01 → 0.02 after the
    first frame; after three frames the captured loop equals the uncaptured one (it differed by 1.2 cm)."""
    finals = []
    for use_graph in (True, False):
        builder = ws.ModelBuilder(drag=0.01)
        builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, mass=0.5, pin=["top-left", "top-right"])
        model = builder.finalize(device)
        sim = ws.Simulator(model, fps=60, substeps=16, use_graph=use_graph)
        sim.step_frame()
        model.gravity, model.drag = (0.0, 0.0, -1.0), 0.02
        finals.append(run_frames(sim, 2))
    np.testing.assert_array_equal(finals[0], finals[1])


def test_new_threshold_values_load_no_module(device):
    """After the first frame, new values of every threshold, of gravity and of drag load no new kernel
    module (0.10, 0.11, 0.12, ...); switching a stabiliser off is a structural change (a new revision and capture)."""
    model = cloth(device)
    sim = ws.Simulator(model, integrator=ws.RK4(model), fps=60, substeps=4)
    sim.step_frame()
    before = loaded_modules()
    for k, strain in enumerate((0.10, 0.11, 0.12)):
        model.stabilizers = ws.Stabilizers(max_spring_force=30.0 + k, max_particle_force=3.0 + k, max_speed=2.0 + k,
                                           max_strain=strain, strain_iterations=2, biphasic_strain=0.1 + strain,
                                           biphasic_ratio=2.0 + k)
        model.gravity = (0.0, 0.1 * k, -9.81)
        model.drag = 0.01 * (k + 1)
        sim.step_frame()
    assert loaded_modules() == before
    assert sim.stepper.captures == 1
    revision = model.revision
    model.stabilizers = ws.Stabilizers(max_spring_force=30.0, max_particle_force=3.0, max_strain=0.1,
                                       strain_iterations=2, biphasic_strain=0.2)  # speed clamp off
    sim.step_frame()
    # A switch is structural: a new revision and a new capture. (Whether it loads a module depends on what
    # other tests of the same process compiled before, so the count is not asserted here.)
    assert model.revision > revision and sim.stepper.captures == 2


def test_recapture_follows_structural_changes_only(device):
    """The stepper re-captures exactly when something a graph bakes in changes: a term switched on, an
    input allocated, a track set, the guard's check interval; not for values (control force values,
    guard limits, solver tolerances)."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=4, ny=4, spacing=0.1, mass=0.2, pin=["top-left"])
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.ImplicitEuler(model), fps=60, substeps=4)
    steps = [(lambda: None, 1),
             (lambda: setattr(model, "gravity", (0.0, 0.0, -9.81)), 2),  # gravity switched on
             (lambda: setattr(model, "gravity", (0.0, 0.0, -1.0)), 2),  # a value
             (lambda: setattr(model, "drag", 0.0), 2),  # zero drag: stays off
             (lambda: setattr(model, "drag", 0.05), 3),  # drag switched on
             (lambda: sim.control.set_particle_force((0.0, 0.01, 0.0)), 4),  # the force array allocated
             (lambda: sim.control.set_particle_force((0.0, 0.02, 0.0)), 4),  # its values
             (lambda: setattr(sim.integrator, "cg_tolerance", 1e-7), 4),  # a device setting
             (lambda: setattr(sim.guard, "limits", ws.GuardLimits(max_kinetic_energy=1e3)), 4),  # limit values
             (lambda: setattr(sim.guard, "limits", ws.GuardLimits(every=2, max_kinetic_energy=1e3)), 5),
             (lambda: model.set_track("drag", ws.Track([0.0, 1.0], [0.05, 0.5])), 6),
             (lambda: model.spring_stiffness.assign(model.spring_stiffness.numpy() * 2), 6),  # values in place
             (lambda: setattr(model, "spring_stiffness", wp.clone(model.spring_stiffness)), 7)]
    for act, captures in steps:
        act()
        sim.step_frame()
        assert sim.stepper.captures == captures


def test_zero_values_keep_results_bit_identical_to_switched_off_terms(device):
    """A term switched on but set to zero adds exactly nothing: a cloth whose drag was switched on and set
    back to 0 follows the never-dragged cloth bit for bit (so switches need never turn off by themselves)."""
    runs = []
    for touch in (False, True):
        builder = ws.ModelBuilder()
        builder.add_cloth_grid(nx=5, ny=5, spacing=0.1, mass=0.3, pin=["top-left", "top-right"], **SOFT)
        model = builder.finalize(device)
        if touch:
            model.drag = 0.5
            model.drag = 0.0
            assert model.drag_enabled
        runs.append(run_frames(ws.Simulator(model, fps=60, substeps=8), 3))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_live_input_errors_are_clear():
    """Bad values are refused with the quantity named; a track needs its stabiliser on."""
    model = cloth("cpu")
    with pytest.raises(ws.ConfigError, match="gravity must be 3 numbers"):
        model.gravity = (0.0, -9.81)
    with pytest.raises(ws.ConfigError, match="drag must be a finite number >= 0"):
        model.drag = -1.0
    with pytest.raises(ws.ConfigError, match="stabilizers must be a warpspring.Stabilizers"):
        model.stabilizers = {"max_strain": 0.1}
    with pytest.raises(ws.ConfigError, match="no live input 'breeze'"):
        model.set_track("breeze", ws.Track([0.0], [1.0]))
    with pytest.raises(ws.ConfigError, match="3-vectors"):
        model.set_track("gravity", ws.Track([0.0, 1.0], [1.0, 2.0]))
    plain = cloth("cpu", stabilizers=ws.Stabilizers())
    with pytest.raises(ws.ConfigError, match="its stabiliser is off"):
        plain.set_track("max_speed", ws.Track([0.0, 1.0], [1.0, 2.0]))


#: Springs soft enough for 1/480 s steps of 14 g particles (the defaults are not: ωh ≈ 2.3).
SOFT = dict(structural=ws.SpringMaterial(100.0, 0.1), shear=ws.SpringMaterial(50.0, 0.05), bend=None)


def test_guard_limit_follows_gravity_switched_on_mid_run(device):
    """A cloth built without gravity gets a tiny default kinetic-energy limit; switching gravity on between
    frames re-derives the limit (a value write), so the correct falling run is not stopped."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, mass=0.5, pin=["top-left", "top-right"], **SOFT)
    model = builder.finalize(device)
    assert ws.advise(model, "symplectic_euler", 1 / 480).stable  # so a stop could only be the guard's limit
    sim = ws.Simulator(model, fps=60, substeps=8, guard=ws.GuardLimits(check_frames=1))  # (captures counted below)
    sim.step_frame()
    before = sim.guard.max_kinetic_energy
    model.gravity = (0.0, 0.0, -9.81)
    run_frames(sim, 60)  # raised SimulationError ("kinetic energy ran away") before the limit followed
    assert sim.guard.max_kinetic_energy > 100 * before and sim.stepper.captures == 2


def test_gravity_track_sets_the_guard_scale_and_the_start_value(device):
    """A gravity track ramping up from zero: the model reports the track's value at t = 0 before any step,
    and the guard's default limit is scaled by the track's largest gravity, so the run is not stopped."""
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, mass=0.5, pin=["top-left", "top-right"], **SOFT)
    builder.set_track("gravity", ws.Track([0.0, 0.5], [[0, 0, 0], [0, 0, -9.81]]))
    model = builder.finalize(device)
    assert model.gravity == (0.0, 0.0, 0.0)
    assert ws.advise(model, "symplectic_euler", 1 / 480).stable
    run_frames(ws.Simulator(model, fps=60, substeps=8), 60)


def test_animated_and_constant_inputs_are_range_checked():
    """Tracks and constants of an input meet the same bounds as the scene schema; values that overflow the
    model's precision are refused instead of turning into inf."""
    model = cloth("cpu")
    with pytest.raises(ws.ConfigError, match="a key of a track of max_speed must be > 0"):
        model.set_track("max_speed", ws.Track([0.0, 1.0], [2.0, -1.0]))
    with pytest.raises(ws.ConfigError, match="biphasic_ratio must be >= 1"):
        model.set_track("biphasic_ratio", ws.Track([0.0, 1.0], [2.0, 0.5]))
    with pytest.raises(ws.ConfigError, match="drag must be >= 0"):
        model.set_track("drag", ws.Track([0.0, 1.0], [0.1, -0.1]))
    with pytest.raises(ws.ConfigError, match="gravity overflows float32"):
        model.gravity = (0.0, 0.0, -1e40)
    assert model.track("max_speed") is None and model.gravity[2] == pytest.approx(-9.81)


def test_states_of_another_model_are_refused():
    """A state of another size or precision is a clear error, not a launch failure or a partial copy."""
    small = cloth("cpu")
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.1, mass=0.1)
    other = builder.finalize("cpu", precision="float64")
    with pytest.raises(ws.ConfigError, match="use a state made by this model's state"):
        ws.Stepper(small, ws.SymplecticEuler(small), dt=1e-3, steps=1, state=other.state())
    sim = ws.Simulator(small)
    with pytest.raises(ws.ConfigError, match="9 particles of vec3d"):
        sim.reset(other.state())


def test_replacing_a_control_input_recaptures(device):
    """Assigning a new array to a Control field is structural (the graph pointed to the old one)."""
    model = cloth(device)
    sim = ws.Simulator(model, fps=60, substeps=2)
    sim.control.set_particle_force((0.0, 0.0, 1.0))
    sim.step_frame()
    sim.control.particle_force = wp.zeros(model.particle_count, dtype=model.vec3, device=model.device)
    sim.step_frame()
    assert sim.stepper.captures == 2
