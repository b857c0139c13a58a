"""The guard's verdict a frame later (``Simulator(defer_verdict=True)``, the default on CUDA): a frame's record is read
once the next frame is queued, a failure is raised at the next ``step_frame`` or at ``settle`` (or a read of the
state) naming its own frame and substep, and a run that passes is the run without deferral, bit for bit."""

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from helpers import ZERO_GRAVITY, battery_cloth, hanging_cloth, run_frames


def _nan_at_frame_3(device, **options):
    """Ten free particles run two frames, with a NaN velocity then planted in particle 7."""
    builder = ws.ModelBuilder()
    builder.add_particles(np.arange(30.0).reshape(10, 3), mass=1.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=16, defer_verdict=True, **options)
    run_frames(sim, 2)
    qd = sim.state.particle_qd.numpy()
    qd[7] = np.nan
    sim.state.particle_qd.assign(qd)
    return sim


def test_deferred_failure_raises_at_the_next_frame_naming_its_own(device):
    """The frame that goes non-finite returns; the next ``step_frame`` raises for it (frame 3, substep 16: the frame's
    check), and the frames counted are the two before it."""
    sim = _nan_at_frame_3(device)
    sim.step_frame()  # frame 3: its verdict is not read yet
    assert sim.frame == 3
    with pytest.raises(ws.SimulationError) as failure:
        sim.step_frame()
    assert failure.value.frame == 3 and failure.value.substep == 16
    assert str(failure.value).startswith("frame 3, substep 16 of 16 (t ≤ ")
    assert str(failure.value).endswith("particle 7 has a non-finite position or velocity")
    assert sim.frame == 2  # the failed frame does not count


@pytest.mark.parametrize("how", ["settle", "state"])
def test_settle_and_reading_the_state_raise_for_the_last_frame(device, how):
    """A loop that ends on the failed frame still stops: ``settle()``, or reading ``state``, raises for it."""
    sim = _nan_at_frame_3(device)
    sim.step_frame()
    with pytest.raises(ws.SimulationError, match=r"^frame 3, substep 16 of 16 .*particle 7 has a non-finite"):
        sim.settle() if how == "settle" else sim.state
    assert sim.frame == 2
    sim.settle()  # settled: nothing left to raise


def test_deferred_torn_spring_is_named_on_the_state_it_tore_in(device):
    """The most strained spring of a failed check is found by that check (``gather``), so the report names it though
    the next frame ran before the record was read: spring 1, pulled to 30× its rest length."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], mass=1.0)
    builder.add_springs([[0, 1], [1, 2], [2, 3]], stiffness=1.0, rest_length=[1.0, 1.0 / 30.0, 1.0])
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=4, defer_verdict=True)
    sim.step_frame()
    with pytest.raises(ws.SimulationError, match=r"^frame 1, .*spring 1 \(particles 1-2\) stretched to [0-9.]+× its"):
        sim.step_frame()



def test_a_deferred_failure_is_raised_before_the_next_frames_integrator_stop(device):
    """Frame 1 tears spring 1 (its verdict read a frame later); frame 2's adaptive integrator then gives up. The
    earlier failure is the one raised, naming frame 1 and the spring, not frame 2's integrator (which, raised
    first, would have counted frame 1 as passed)."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], mass=1.0)
    builder.add_springs([[0, 1], [1, 2], [2, 3]], stiffness=1.0, rest_length=[1.0, 1.0 / 30.0, 1.0])
    model = builder.finalize(device)
    integrator = ws.DormandPrince(model)
    sim = ws.Simulator(model, integrator=integrator, fps=60, substeps=4, defer_verdict=True)
    sim.step_frame()
    integrator.failure = lambda: "dopri5 gave up (a stand-in for this frame's failure)"
    with pytest.raises(ws.SimulationError, match=r"^frame 1, .*spring 1 \(particles 1-2\) stretched") as stop:
        sim.step_frame()
    assert stop.value.frame == 1 and sim.frame == 0

def test_deferred_world_stop_records_each_world_once_with_its_frame(device):
    """``stop="world"``: RK4 at one 1/60 s step stops the battery cloth's unstable world 1 (the case of
    ``test_guards.py``), recorded once, at the frame whose check failed (the same frame as without deferral), while
    world 0 runs on; the two runs' states agree bit for bit."""
    runs = {}
    for defer in (False, True):
        model = battery_cloth(device, [300.0, 480.0])
        sim = ws.Simulator(model, integrator=ws.make_integrator("rk4", model), fps=60, substeps=1,
                           guard=ws.GuardLimits(stop="world"), defer_verdict=defer)
        for _ in range(40):
            sim.step_frame()
        sim.settle()
        runs[defer] = (dict(sim.world_failures), sim.state.particle_q.numpy())
    assert list(runs[True][0]) == [1]
    assert runs[True][0][1][0] == runs[False][0][1][0]  # the frame
    assert runs[True][0][1][1] == runs[False][0][1][1]  # the report
    np.testing.assert_array_equal(runs[True][1], runs[False][1])


def test_deferred_run_that_passes_is_the_same_run(device):
    """A healthy run gives the same bits, the same balance and the same work with or without deferral (a check every
    frame: a check spanning frames, which deferral allows, sums the same power over its span in another order,
    ``tests/test_guard_spans.py``)."""
    results = []
    for defer in (False, True):
        model, _ = hanging_cloth(device, n=8, drag=0.2)
        sim = ws.Simulator(model, fps=60, substeps=8, defer_verdict=defer, guard=ws.GuardLimits(check_frames=1))
        q = run_frames(sim, 12)
        results.append((q, sim.guard.energy_balance().created, sim.guard.work()))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])
    np.testing.assert_array_equal(results[0][2], results[1][2])


def test_a_failure_of_the_next_frame_is_not_read_as_the_frame_before(device):
    """A frame's deferred read takes the failures latched up to its own end, not one the next frame (already run on
    the CPU, running on a GPU) latched since: a particle flung from a pinned one at 12 m/s on a soft 1 m spring passes
    a 30 % strain in the second frame (20 % at the first frame's end, 40 % at the second's), so the read of frame 1,
    made after frame 2 ran, passes, and frame 2 is the one named."""
    builder = ws.ModelBuilder(gravity=ZERO_GRAVITY)
    builder.add_particles([[0, 0, 0], [1, 0, 0]], velocities=[[0, 0, 0], [12.0, 0, 0]], mass=1.0, pinned=[0])
    builder.add_springs([[0, 1]], stiffness=1.0)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=4, defer_verdict=True, guard=ws.GuardLimits(tear_strain=0.3))
    sim.step_frame()
    sim.step_frame()  # frame 2 tears the spring; frame 1's verdict is read after it ran
    assert sim.frame == 2
    with pytest.raises(ws.SimulationError, match=r"^frame 2, .*spring 0 \(particles 0-1\) stretched") as stop:
        sim.settle()
    assert stop.value.frame == 2 and sim.frame == 1


def test_a_deferred_frame_that_passes_reads_nothing_from_the_device(device, monkeypatch):
    """The read a frame later waits for its frame's event and reads the mirror in host memory: a frame that passes
    makes no array read (``wp.array.numpy``) and no wait for the whole stream or device, any of which would hold the
    host until the frame queued behind it ends (on an H200 a read of that kind every frame took the default 64² run
    from 0.70 to 0.47 of guard off)."""
    model, _ = hanging_cloth(device, n=8)
    sim = ws.Simulator(model, fps=60, substeps=8, defer_verdict=True)
    run_frames(sim, 6)  # past the frames watched from the start
    waits = []
    numpy = wp.array.numpy
    monkeypatch.setattr(wp.array, "numpy", lambda self: (waits.append(("numpy", self.shape)), numpy(self))[1])
    for name in ("synchronize", "synchronize_device", "synchronize_stream"):
        monkeypatch.setattr(wp, name, lambda *a, _name=name, _original=getattr(wp, name), **k: (
            waits.append((_name,)), _original(*a, **k))[1])
    for _ in range(3):
        sim.step_frame()
    assert waits == []


def test_deferred_world_stops_in_different_frames_are_each_named_with_their_own(device):
    """Three of four worlds fail, in frames 8, 17 and 32 on the CPU (RK4 at one 1/60 s step, stiffer worlds sooner;
    the case of ``test_deferred_world_stop_records_each_world_once_with_its_frame``): read a frame later, each is
    recorded with the frame and the report it has without deferral, though the frame after it had run before its
    frame's read, and the states agree bit for bit."""
    runs = {}
    for defer in (False, True):
        model = battery_cloth(device, [300.0, 480.0, 1000.0, 700.0])
        sim = ws.Simulator(model, integrator=ws.make_integrator("rk4", model), fps=60, substeps=1,
                           guard=ws.GuardLimits(stop="world"), defer_verdict=defer)
        for _ in range(40):
            sim.step_frame()
        sim.settle()
        runs[defer] = ({world: (frame, str(report)) for world, (frame, report) in sim.world_failures.items()},
                       sim.state.particle_q.numpy())
    assert sorted(runs[True][0]) == [1, 2, 3]
    assert len({frame for frame, _ in runs[True][0].values()}) == 3  # three different frames
    assert runs[True][0] == runs[False][0]
    np.testing.assert_array_equal(runs[True][1], runs[False][1])
