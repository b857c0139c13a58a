"""Run-time guards: the first failure of a frame is caught on the device and reported with its frame,
substep, particle or spring — and healthy runs are never stopped."""

import numpy as np
import pytest

import warpspring as ws
from helpers import ZERO_GRAVITY, hanging_cloth, run_frames


def test_healthy_run_is_not_stopped(device):
    """A stable hanging cloth with a sphere runs 60 frames with guards checking every substep."""
    model, _ = hanging_cloth(device, n=10, sphere=True)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(every=1))
    assert np.isfinite(run_frames(sim, 60)).all()


@pytest.mark.parametrize("every, expected_substep", [(None, 16), (1, 1), (4, 4)])
def test_non_finite_particle_is_named_with_its_substep(device, every, expected_substep):
    """A NaN velocity planted in free particle 7 is reported as particle 7 at the first check after it:
    substep 1 when checking every substep, 4 every fourth, 16 (the frame's end) once per frame."""
    builder = ws.ModelBuilder()
    builder.add_particles(np.arange(30.0).reshape(10, 3), mass=1.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(every=every))
    run_frames(sim, 2)
    qd = sim.state.particle_qd.numpy()
    qd[7] = np.nan
    sim.state.particle_qd.assign(qd)
    with pytest.raises(ws.SimulationError) as failure:
        sim.step_frame()
    assert failure.value.frame == 3 and failure.value.substep == expected_substep
    assert str(failure.value).startswith(f"frame 3, substep {expected_substep} of 16 (t ≤ ")
    assert str(failure.value).endswith("particle 7 has a non-finite position or velocity")
    assert sim.frame == 2  # the failed frame does not count


def test_non_finite_state_spreading_through_springs_is_counted(device):
    """A NaN spreads to the neighbours within a substep; the report counts the non-finite particles."""
    model, _ = hanging_cloth(device, n=6)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(every=1))
    qd = sim.state.particle_qd.numpy()
    qd[14] = np.nan
    sim.state.particle_qd.assign(qd)
    with pytest.raises(ws.SimulationError, match=r"frame 1, substep 1 of 16 .*: (\d+) of 36 particles have non-finite") as failure:
        sim.step_frame()
    count = int(str(failure.value).split(": ")[1].split(" of ")[0])
    assert 2 <= count <= 13  # particle 14 and, at most, its twelve spring neighbours


def test_torn_spring_is_named(device):
    """A spring pulled to 30× its rest length (the guard's default limit is 11×) is named with its two
    particles and its stretch."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], mass=1.0)
    builder.add_springs([[0, 1], [1, 2], [2, 3]], stiffness=1.0, rest_length=[1.0, 1.0 / 30.0, 1.0])
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=4)
    with pytest.raises(ws.SimulationError, match=r"spring 1 \(particles 1-2\) stretched to [0-9.]+× its rest length"):
        sim.step_frame()


def test_runaway_kinetic_energy_is_caught(device):
    """Kinetic energy beyond the configured limit stops the run with the energy named."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0, 0, 0]], velocities=[[10.0, 0, 0]], mass=2.0)  # ½ m v² = 100 J
    model = builder.finalize(device)
    ws.Simulator(model, fps=60, substeps=2, guard=ws.GuardLimits(max_kinetic_energy=150.0)).step_frame()
    sim = ws.Simulator(model, fps=60, substeps=2, guard=ws.GuardLimits(max_kinetic_energy=50.0))
    with pytest.raises(ws.SimulationError, match=r"kinetic energy ran away to 100 J"):
        sim.step_frame()


def test_default_energy_limit_tolerates_fast_initial_motion(device):
    """Particles launched at 1e3 m/s are not runaway energy: the default limit scales with the scene's own
    initial kinetic energy."""
    builder = ws.ModelBuilder()
    builder.add_particles(np.random.default_rng(0).uniform(-1, 1, (20, 3)),
                          velocities=np.full((20, 3), 1.0e3 / np.sqrt(3)), mass=0.1)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=8)
    assert np.isfinite(run_frames(sim, 10)).all()


@pytest.mark.parametrize("kwargs, message", [
    ({"every": 0}, "guard every must be an integer >= 1"),
    ({"every": 2.5}, "guard every must be an integer >= 1"),
    ({"tear_strain": 0.0}, "guard tear_strain must be a finite number > 0"),
    ({"tear_strain": float("nan")}, "guard tear_strain must be a finite number > 0"),
    ({"max_kinetic_energy": -1.0}, "guard max_kinetic_energy must be a finite number > 0"),
])
def test_guard_limits_reject_bad_values_when_made(kwargs, message):
    with pytest.raises(ws.ConfigError, match=message):
        ws.GuardLimits(**kwargs)


def test_guard_max_strain_is_a_deprecated_name_of_tear_strain():
    """GuardLimits.max_strain was renamed tear_strain (not Stabilizers.max_strain, the strain limit): the old
    keyword and attribute still work, with a DeprecationWarning; both names at once are refused."""
    with pytest.warns(DeprecationWarning, match="tear_strain"):
        limits = ws.GuardLimits(every=2, max_strain=3.0)
    assert limits == ws.GuardLimits(every=2, tear_strain=3.0) and limits.tear_strain == 3.0
    with pytest.warns(DeprecationWarning, match="tear_strain"):
        assert limits.max_strain == 3.0
    with pytest.warns(DeprecationWarning), pytest.raises(ws.ConfigError, match="guard max_strain must be"):
        ws.GuardLimits(max_strain=-1.0)
    with pytest.raises(TypeError, match="pass tear_strain only"):
        ws.GuardLimits(tear_strain=3.0, max_strain=3.0)
    assert ws.GuardLimits().tear_strain == 10.0
