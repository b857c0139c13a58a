"""Keyframe tracks: the device evaluation against the host reference and SciPy, and animated inputs
evaluated at the time of every stage (a gravity ramp integrated exactly by RK4)."""

import numpy as np
import pytest
import warp as wp
from scipy.interpolate import PchipInterpolator

import warpspring as ws
from warpspring.core.tracks import TrackTable
from warpspring.kernels.tracks import sample_tracks

TIMES = [0.0, 0.4, 0.5, 1.3, 2.0]
VALUES = np.array([[0.0, 1.0, -2.0], [1.0, 1.5, -2.0], [0.2, 3.0, 0.0], [0.2, -1.0, 4.0], [2.0, 0.0, 1.0]])


def device_samples(device, track, t):
    """(value, rate) of ``track`` at times ``t`` evaluated by the device kernel, float64, [len(t), width]."""
    table = TrackTable([track], device)
    n = len(t)
    value = wp.empty(n, dtype=wp.vec3d, device=device)
    rate = wp.empty(n, dtype=wp.vec3d, device=device)
    wp.launch(sample_tracks, dim=n, inputs=[table.table, wp.zeros(n, dtype=wp.int32, device=device),
              wp.array(t, dtype=wp.float64, device=device)], outputs=[value, rate], device=device)
    return value.numpy()[:, : track.width], rate.numpy()[:, : track.width]


@pytest.mark.parametrize("interpolation", ["step", "linear", "smooth"])
@pytest.mark.parametrize("extrapolation", ["hold", "cycle"])
def test_device_evaluation_matches_the_host_reference(device, interpolation, extrapolation):
    """Value and rate on the device equal the host's float64 evaluation to rounding, at random times, at
    the keys themselves, before the first key and after the last."""
    track = ws.Track(TIMES, VALUES, interpolation=interpolation, extrapolation=extrapolation)
    t = np.concatenate([np.random.default_rng(3).uniform(-1.0, 4.5, 400), TIMES, [-0.1, 2.1, 7.9]])
    value, rate = device_samples(device, track, t)
    host_value, host_rate = track.sample(t)
    np.testing.assert_allclose(value, host_value, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(rate, host_rate, rtol=1e-10, atol=1e-10)


def test_host_reference_agrees_with_numpy_and_scipy():
    """Linear is numpy.interp; smooth is SciPy's PCHIP (values and derivatives); step holds each key's
    value up to the next key (and takes the new value at the key); hold extrapolates with rate 0; cycle
    repeats with period t_last - t_first."""
    t = np.linspace(0.0, 2.0, 1001)
    linear = ws.Track(TIMES, VALUES, interpolation="linear").sample(t)[0]
    for c in range(3):
        np.testing.assert_allclose(linear[:, c], np.interp(t, TIMES, VALUES[:, c]), rtol=0, atol=1e-14)
    value, rate = ws.Track(TIMES, VALUES, interpolation="smooth").sample(t)
    reference = PchipInterpolator(TIMES, VALUES, axis=0)
    np.testing.assert_allclose(value, reference(t), atol=1e-13)
    np.testing.assert_allclose(rate, reference.derivative()(t), atol=1e-11)
    step = ws.Track(TIMES, VALUES, interpolation="step")
    np.testing.assert_array_equal(step.sample([0.39999, 0.4, 0.45])[0], VALUES[[0, 1, 1]])
    held, held_rate = step.sample([-5.0, 9.0])
    np.testing.assert_array_equal(held, VALUES[[0, -1]])
    assert not held_rate.any()
    cyclic = ws.Track(TIMES, VALUES, extrapolation="cycle")
    np.testing.assert_allclose(cyclic.sample([0.3 + 2.0 * 3])[0], cyclic.sample([0.3])[0], atol=1e-12)


def test_smooth_tracks_do_not_overshoot_their_keys():
    """Monotone cubic derivatives: between two keys the smooth curve stays within their values."""
    track = ws.Track([0.0, 1.0, 1.1, 3.0], [0.0, 1.0, 1.0, 0.0], interpolation="smooth")
    value = track.sample(np.linspace(0.0, 3.0, 3001))[0][:, 0]
    assert value.min() >= -1e-15 and value.max() <= 1.0 + 1e-15


@pytest.mark.parametrize(
    "args, message",
    [
        (([], []), "non-empty"),
        (([0.0, 1.0, 1.0], [0, 1, 2]), "increase strictly: key 2"),
        (([0.0, np.nan], [0, 1]), "finite"),
        (([0.0, 1.0], [[0, 1], [1, 2]]), "each a number or 3 numbers"),
        (([0.0, 1.0], [0, np.inf]), "values must be finite"),
    ],
)
def test_bad_tracks_are_refused(args, message):
    with pytest.raises(ws.ConfigError, match=message):
        ws.Track(*args)


def test_bad_track_options_are_refused():
    with pytest.raises(ws.ConfigError, match="interpolation must be one of step, linear, smooth"):
        ws.Track([0.0, 1.0], [0.0, 1.0], interpolation="cubic")
    with pytest.raises(ws.ConfigError, match="at least two keys"):
        ws.Track([0.0], [0.0], extrapolation="cycle")
    with pytest.raises(ws.ConfigError, match="rotation axis"):
        ws.Track.rotation([0.0, 1.0], axis=(0, 0, 0), degrees=[0, 90])


def ramp_fall(device, name, steps, *, duration=0.5):
    """A free particle under a gravity track that ramps linearly from -9.81 to -4.81 m/s² over 1 s, with a
    horizontal component: its exact path is the cubic x(t) = x₀ + v₀t + g₀t²/2 + g′t³/6."""
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 10.0]], velocities=[[1.0, 0.0, 2.0]], mass=0.3)
    builder.set_track("gravity", ws.Track([0.0, 1.0], [[0.0, 0.0, -9.81], [3.0, 0.0, -4.81]]))
    model = builder.finalize(device, precision="float64")
    integrator = ws.make_integrator(name, model, **({"tolerance": 1e-10} if name == "dopri5" else {}))
    stepper = ws.Stepper(model, integrator, dt=duration / steps, steps=steps)
    stepper.advance()
    t = float(stepper.state.time.numpy()[0])
    exact = np.array([0.0, 0.0, 10.0]) + np.array([1.0, 0.0, 2.0]) * t + np.array([0.0, 0.0, -9.81]) * t**2 / 2 \
        + np.array([3.0, 0.0, 5.0]) * t**3 / 6
    return t, float(np.abs(stepper.state.particle_q.numpy()[0] - exact).max())


@pytest.mark.parametrize("name", ["rk4", "dopri5"])
def test_gravity_track_is_evaluated_at_every_stage(device, name):
    """RK4 integrates a cubic path exactly, and dopri5 too, but only if each stage sees gravity at its own
    time t + cₖh: evaluated once per step, the ramp would leave an O(h) error (here ~1e-3 m)."""
    t, error = ramp_fall(device, name, 20)
    assert t == pytest.approx(0.5, abs=1e-15)  # the state's time advanced with the steps
    assert error < 1e-12


@pytest.mark.parametrize("name, order", [("symplectic_euler", 1), ("explicit_euler", 1), ("midpoint", 2),
                                         ("velocity_verlet", 2), ("implicit_euler", 1)])
def test_gravity_track_keeps_each_integrators_order(device, name, order):
    """Halving the step divides the error by 2^order (within ±0.15 in the exponent): the forcing enters
    every method at the right times."""
    errors = [ramp_fall(device, name, n)[1] for n in (64, 128)]
    assert np.log2(errors[0] / errors[1]) == pytest.approx(order, abs=0.15)
