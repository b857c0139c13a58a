"""A check that spans frames (``GuardLimits.check_frames``): where the verdict is read a frame later and the frames are
not read one by one, a scene of springs and gravity at a step the watched frames passed leaves up to
``check_frames - 1`` frames in a row to the next check; that check's balance, work and dissipation are sums over the
span, so they equal the every-frame run's up to the rounding of the power sums kept longer; a failure inside a span
stops the run at the span's check; a read checks its frame first; and a scene whose loads may change unseen keeps a
check every frame."""

import numpy as np
import pytest

import warpspring as ws
from helpers import damped_gathered_cloth, hanging_cloth

FRAMES = 14


def _checked_frames(device, check_frames, *, read=False, frames=FRAMES, control_force=False,
                    integrator="symplectic_euler"):
    """The cloth's run of ``frames`` frames, deferred: (whether each frame's end was checked, the simulator)."""
    model, _ = hanging_cloth(device, n=12)
    control = model.control()
    if control_force:
        control.set_particle_force(np.zeros((model.particle_count, 3)))
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(check_frames=check_frames),
                       defer_verdict=True, control=control, integrator=ws.make_integrator(integrator, model))
    checked = []
    for _ in range(frames):
        sim.step_frame()
        checked.append(not sim.guard.frame_unchecked)
        if read:
            sim.state
    return checked, sim


def test_a_check_spans_frames_and_sums_over_them(device):
    """After the frames from the start that are checked (the first, or the watched ones), three frames in four go
    unchecked (``check_frames=4``); at a frame both runs check, the balance's energy is the same and its work and
    dissipation agree with the every-frame run's within the float32 rounding of the power sums each particle keeps
    four times as long (~64 additions: ~64 × 2⁻²⁴ of the sum, 1e-5 with room)."""
    spanned, sim = _checked_frames(device, 4)
    captures = sim.stepper.captures  # (the checked frame's graph and the unchecked one's, each captured once)
    for _ in range(8):
        sim.step_frame()
    assert sim.stepper.captures == captures <= 3
    every, reference = _checked_frames(device, 1)
    assert all(every)
    first = spanned.index(False)
    assert all(spanned[:first]) and first >= 1
    assert spanned[first:] == ([False, False, False, True] * FRAMES)[:FRAMES - first]
    last = max(k for k, checked in enumerate(spanned) if checked)
    assert last >= first + 3
    # Both runs stopped at FRAMES; compare at the spanned run's last checked frame, replaying the reference to it.
    _, reference = _checked_frames(device, 1, frames=last + 1)
    _, sim = _checked_frames(device, 4, frames=last + 1)
    sim.settle()
    reference.settle()
    a, b = sim.guard.energy_balance(), reference.guard.energy_balance()
    assert a.energy[0] == pytest.approx(b.energy[0], rel=1e-12)
    assert a.work[0] == pytest.approx(b.work[0], rel=1e-5)
    assert a.dissipated[0] == pytest.approx(b.dissipated[0], rel=1e-5)
    assert a.dissipated[0] > 0.0 and a.work[0] > 0.0


@pytest.mark.parametrize("how", ["settle", "balance"])
def test_a_read_checks_its_frame_first(device, how):
    """Reading the state every frame keeps every frame checked (the read would otherwise check it on its own); after
    two unchecked frames, ``settle`` or a read of the guard's balance checks the last one first: the balance read is
    that frame's, as the every-frame run's."""
    checked, _ = _checked_frames(device, 4, read=True)
    assert all(checked)
    spanned, _ = _checked_frames(device, 4)
    frames = spanned.index(False) + 2  # ending on the second unchecked frame in a row
    spanned, sim = _checked_frames(device, 4, frames=frames)
    assert spanned[-2:] == [False, False] and sim.guard.frame_unchecked
    if how == "settle":
        sim.settle()
    energy = sim.guard.energy_balance().energy[0]
    assert not sim.guard.frame_unchecked
    _, reference = _checked_frames(device, 1, frames=frames)
    assert energy == pytest.approx(reference.guard.energy_balance().energy[0], rel=1e-12)
    _, stale = _checked_frames(device, 4, frames=frames - 2)  # the last check before the span: another energy
    assert stale.guard.energy_balance().energy[0] != pytest.approx(energy, rel=1e-6)


@pytest.mark.parametrize("how", ["unread", "read", "settled inside the span"])
def test_a_failure_inside_a_span_stops_at_its_check(device, how):
    """A non-finite velocity planted after the first unchecked frame: the run stops at the span's check (the next
    checked frame), naming that frame and the frames the check spanned; read every frame, at the frame it was planted
    in; settled at the planted frame (a read inside the span), there, naming the frames left unchecked before it."""
    spanned, _ = _checked_frames(device, 4)
    first = spanned.index(False) + 1  # the first unchecked frame (1-based)
    planted = first + 1  # the second
    span_check = first + 3  # the frame whose check ends the span
    model, _ = hanging_cloth(device, n=12)
    sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(check_frames=4), defer_verdict=True)
    with pytest.raises(ws.SimulationError, match="non-finite") as stop:
        for frame in range(1, FRAMES + 1):
            sim.step_frame()
            if frame == planted - 1:
                qd = sim.stepper.state.particle_qd.numpy()
                qd[70] = np.nan
                sim.stepper.state.particle_qd.assign(qd)
            if how == "read" or (how == "settled inside the span" and frame == planted):
                sim.settle()
        sim.settle()
    message = str(stop.value)
    if how == "unread":
        assert stop.value.frame == span_check
        assert message.startswith(f"frame {span_check} (its check spanned frames {first}-{span_check}: the failure")
    elif how == "read":
        assert stop.value.frame == planted and message.startswith(f"frame {planted}, substep 16 of 16")
    else:
        assert stop.value.frame == planted
        assert message.startswith(f"frame {planted} (its check spanned frames {first}-{planted}: the failure")


@pytest.mark.parametrize("case", ["control force", "every frame", "not deferred", "explicit euler", "midpoint"])
def test_no_span_where_loads_may_change_unseen_or_asked(device, case):
    """A control force (which may change between frames without a write the guard sees), ``check_frames=1``, a
    simulator that reads each verdict at once, and explicit Euler and midpoint (whose damping limit the springs' bound
    cannot certify, so no frame of theirs is watched: a spring made 100× stiffer went non-finite inside a span in the
    guard's battery) keep a check every frame."""
    if case == "not deferred":
        model, _ = hanging_cloth(device, n=12)
        sim = ws.Simulator(model, fps=60, substeps=16, guard=ws.GuardLimits(check_frames=4), defer_verdict=False)
        checked = []
        for _ in range(FRAMES):
            sim.step_frame()
            checked.append(not sim.guard.frame_unchecked)
    elif case in ("explicit euler", "midpoint"):
        checked, _ = _checked_frames(device, 4, integrator=case.replace(" ", "_"))
    else:
        checked, _ = _checked_frames(device, 1 if case == "every frame" else 4, control_force=case == "control force")
    assert all(checked)


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4"])
def test_dampers_raised_through_the_model_are_caught_before_they_overflow(device, integrator):
    """``test_guard_power.py``'s unstable dampers under the default guard, its checks spanning frames: an 8 × 8 cloth
    swings 1 s unread, then its dampers are raised past the step's damping limit through the model
    (``set_world_values``: a write the guard sees, so the next frames are watched, every substep checked): the run
    stops for the energy the overshooting step creates within 60 frames, not for a non-finite state."""
    model = damped_gathered_cloth(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=16,
                       defer_verdict=True)
    spanned = []
    for _ in range(60):
        sim.step_frame()
        spanned.append(sim.guard.frame_unchecked)
    assert any(spanned)
    model.set_world_values("spring_damping", 21.0 if integrator == "symplectic_euler" else 30.0)
    with pytest.raises(ws.SimulationError, match="energy") as stop:
        for _ in range(60):
            sim.step_frame()
        sim.settle()
    assert stop.value.reason in ("energy balance", "kinetic energy")
