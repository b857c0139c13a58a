"""The stability advisor during a run (StabilityWatch): a state that stiffens toward its step's limit is
warned about, with the substeps it needs, before the run blows up; a run well inside it is not."""

import warnings

import numpy as np
import pytest

import warpspring as ws
from helpers import battery_cloth, run_frames
from warpspring.analysis.watch import WATCH_MARGIN, StabilityWatch


def _run(device, stiffness, *, frames, substeps=1, integrator="rk4", watch=5):
    model = battery_cloth(device, [stiffness])
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=substeps,
                       guard=ws.GuardLimits(energy_balance=0.0))
    stability_watch = StabilityWatch.attach(sim, every=watch)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_frames(sim, frames)
    return sim, stability_watch, [w.message for w in caught if isinstance(w.message, ws.StabilityWarning)]


def test_a_cloth_stiffening_under_load_is_warned_before_it_blows_up(device):
    """RK4 at 1/60 s on the battery cloth at ke = 480 N/m: stable where it starts (flat and unstretched), not
    once its corners stretch under its weight (the energy balance stops it near frame 32). The watch, every
    5 frames, warns within the first 30, naming the substeps; the ω_max it sees is the loaded one, above
    the start's."""
    _, watch, found = _run(device, 480.0, frames=30)
    assert found, "no StabilityWarning"
    message = str(found[0])
    assert message.startswith("frame ") and int(message.split(":")[0].split()[1]) <= 30
    needed = watch.warned[0]
    assert needed >= 2 and f"--substeps {needed}" in message
    assert watch.omega[0] >= WATCH_MARGIN * watch.omega_limit[0]


def test_a_run_inside_its_limit_is_not_warned(device):
    """The same cloth at 10 substeps (a tenth of the step) sags to the same state without a warning; the
    watch's ω_max there agrees with the advisor linearised about the frame's state within 1 %."""
    from warpspring.analysis.omega import estimate_omega_max

    sim, watch, found = _run(device, 480.0, frames=30, substeps=10)
    assert not found
    reference = estimate_omega_max(sim.model, state=sim.state, tolerance=1e-6, max_iterations=5000).omega_max
    watch.collect()  # on CUDA the re-check after frame 30 is read at the next one
    assert watch.frame == 30
    assert watch.omega[0] == pytest.approx(reference, rel=0.01)


def test_implicit_euler_is_not_watched(device):
    """An unconditionally stable step has no limit to approach: the watch stays idle."""
    _, watch, found = _run(device, 480.0, frames=5, integrator="implicit_euler")
    assert not found and not watch.active and np.isinf(watch.omega_limit).all()
