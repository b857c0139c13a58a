"""What a differentiable run (``core/adjoint.py``) shares with the ordinary one and how its gradient behaves:
the same forward trajectory, checkpoints that change nothing, a batch of worlds giving each world's own gradient,
the spread of gradients between runs, and the scenes it refuses."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.analysis.grad_scenes import SCENES, hanging_cloth
from warpspring.core.adjoint import DiffRun, Target
from warpspring.core.adjoint_params import ParameterMap
from warpspring.errors import ConfigError

import helpers

HANGING = SCENES["hanging_cloth"]


def _targets(model, steps):
    q0 = model.particle_q.numpy().astype(np.float64)[: model.particle_count]
    everyone = np.arange(model.particle_count)
    return [Target(steps // 2, everyone, q0), Target(steps, everyone, q0 + 0.01)]


@pytest.mark.parametrize("scene", ["hanging_cloth", "driven_cloth"])
@pytest.mark.parametrize("integrator", ["symplectic_euler", "velocity_verlet"])
def test_forward_run_is_the_ordinary_run(device, integrator, scene):
    """Without colliders the differentiable kernels evaluate the ordinary particle force and update: the same
    float64 positions as the ordinary integrator's (measured: identical bits on the CPU for the hanging cloth; the
    driven pins' x₀ + w_a K_a + w_b K_b rounds otherwise than the kinematics pass's p + (x₀ - p) + T, 2e-16 m; CUDA
    may contract a multiply-add differently, hence 1e-12 m)."""
    model = SCENES[scene].build(SCENES[scene].values, device)
    steps = 40
    run = DiffRun(model, dt=HANGING.dt, steps=steps, integrator=integrator)
    ours = run.trajectory()[-1, 0]
    reference = helpers.trajectory(model, ws.make_integrator(integrator, model), HANGING.dt, steps)[-1]
    assert np.abs(reference - ours).max() <= 1e-12
    assert np.abs(reference - model.particle_q.numpy()).max() > 1e-3  # it moved (measured 2 cm)


def test_checkpoints_change_no_gradient(device):
    """Recomputing segments from checkpoints repeats the same launches on the same values: the gradient is the
    one-tape gradient (identical bits on the CPU; on CUDA up to the adjoints' atomic order, ~1e-15 relative)."""
    model = hanging_cloth(HANGING.values, device)
    grads = {}
    for every in (7, 60):
        run = DiffRun(model, dt=HANGING.dt, steps=60, checkpoint_every=every)
        run.set_targets(_targets(model, 60))
        grads[every] = run.gradient()
    (loss_a, a), (loss_b, b) = grads[7], grads[60]
    assert loss_a[0] == loss_b[0]
    for name in a:
        scale = np.abs(b[name]).max()
        assert np.abs(a[name] - b[name]).max() <= 1e-12 * scale, name
    assert np.abs(a["springs.stiffness"]).max() > 0.0


def test_a_batch_of_worlds_gives_each_world_its_gradient(device):
    """Three worlds at three materials: each world's named gradient is that of a run of one world at its values
    (worlds never couple; measured identical to 1e-15 relative)."""
    names = ["stretch", "bending", "stretch_damping"]
    base = np.array([HANGING.values[k] for k in names])
    mapping = ParameterMap(lambda v: hanging_cloth({**HANGING.values, **v}, device), names, base)
    thetas = base[None] * np.array([[1.0], [1.3], [0.7]])
    steps = 40
    batch = DiffRun(hanging_cloth(HANGING.values, device, worlds=3), dt=HANGING.dt, steps=steps)
    batch.set_targets(_targets(batch.model, steps))
    derivatives = mapping.apply(batch, thetas)
    loss, grads = batch.gradient()
    together = mapping.chain(batch, grads, derivatives)
    for w in range(3):
        single = DiffRun(hanging_cloth(HANGING.values, device), dt=HANGING.dt, steps=steps)
        single.set_targets(_targets(single.model, steps))
        d = mapping.apply(single, thetas[w][None])
        loss_w, grads_w = single.gradient()
        alone = mapping.chain(single, grads_w, d)[0]
        assert loss[w] == pytest.approx(loss_w[0], rel=1e-13)
        np.testing.assert_allclose(together[w], alone, rtol=1e-12)
    assert np.abs(together[1] - together[0]).max() > 1e-3 * np.abs(together[0]).max()  # the worlds differ


@pytest.mark.parametrize("deterministic", [False, True])
def test_gradient_spread_between_runs(device, deterministic):
    """Warp's adjoints of the gather add into the gradients of neighbours' positions with atomics, and so do those of
    a pin-track key read by every pin of its group. On the CPU the threads run in order: every run gives the same
    bits (measured: spread 0). On CUDA the order of those adds varies between runs unless the kernels are compiled
    with Warp's deterministic mode (``deterministic=True``: the same bits); without it each reordered sum differs by
    a few ulps (1e-16 relative), carried back through 60 steps of a cloth whose gradients change by O(1) over them:
    bounded here by 1e-12 relative to each array's largest entry. The driven cloth's every array is checked, the
    pin-track keys included."""
    scene = SCENES["driven_cloth"]
    model = scene.build(scene.values, device)
    run = DiffRun(model, dt=scene.dt, steps=60, deterministic=deterministic)
    run.set_targets(_targets(model, 60))
    results = [run.gradient()[1] for _ in range(4)]
    exact = deterministic or wp.get_device(device).is_cpu
    checked = 0
    for name in results[0]:
        scale = np.abs(results[0][name]).max()
        spread = max(np.abs(r[name] - results[0][name]).max() for r in results[1:])
        if scale == 0.0:
            continue  # (the contact's values, without colliders)
        checked += 1
        if exact:
            assert spread == 0.0, name
        else:
            assert spread <= 1e-12 * scale, f"{name}: spread {spread / scale:.1e} relative"
    assert checked >= 8 and "pin_keys" in results[0]


def test_pin_tracks_of_each_world_give_each_world_its_gradient(device):
    """Two worlds of the driven cloth, world 1's top row moved by a track of its own (other key times, three keys
    more): the forward run is the ordinary run in both worlds, and world 1's loss and key gradient (its track's
    columns of ``pin_keys``) are those of a one-world run on that track (measured identical to 1e-15 relative)."""
    scene = SCENES["driven_cloth"]
    other = ws.Track([0.0, 0.0125, 0.0305, 0.0455, 0.0605, 0.0755], [[0.0, 0.0, 0.0], [0.01, 0.0, 0.02],
                     [-0.02, 0.01, 0.03], [0.0, 0.02, -0.01], [0.03, 0.0, 0.0], [0.0, 0.0, 0.04]])
    batch_model = scene.build(scene.values, device, worlds=2)
    batch_model.set_pin_group_tracks("top", translation=other, world=1)
    single_model = scene.build(scene.values, device)
    single_model.set_pin_group_tracks("top", translation=other)
    steps = 80  # past the last key (75.5 ms): every key moves the loss
    batch = DiffRun(batch_model, dt=scene.dt, steps=steps)
    reference = helpers.trajectory(batch_model, ws.make_integrator("symplectic_euler", batch_model), scene.dt, steps)
    assert np.abs(reference[-1] - batch.trajectory()[-1].reshape(-1, 3)).max() <= 1e-12
    single = DiffRun(single_model, dt=scene.dt, steps=steps)
    results = []
    for run in (batch, single):
        run.set_targets(_targets(run.model, steps))
        results.append(run.gradient())
    (loss_b, grads_b), (loss_s, grads_s) = results
    mine, its = batch.pin_key_columns("top", world=1), single.pin_key_columns("top")
    assert mine.stop - mine.start == its.stop - its.start == 6
    assert loss_b[1] == pytest.approx(loss_s[0], rel=1e-13)
    np.testing.assert_allclose(grads_b["pin_keys"][1, mine], grads_s["pin_keys"][0, its], rtol=1e-12, atol=0.0)
    assert np.abs(grads_s["pin_keys"][0, its]).min() > 0.0
    assert not grads_b["pin_keys"][1, batch.pin_key_columns("top", world=0)].any()  # world 1 reads its own keys
    assert not grads_b["pin_keys"][0, mine].any()


def test_refused_scenes_say_why(device):
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.1, particle_mass=0.1)
    builder.add_collider_box(center=(0.0, 0.0, -0.5), half_extents=(1.0, 1.0, 0.1))
    model = builder.finalize(device, precision="float64")
    with pytest.raises(ConfigError, match="planes and spheres only"):
        DiffRun(model, dt=1e-3, steps=10)
    model = hanging_cloth(HANGING.values, device)
    with pytest.raises(ConfigError, match="symplectic_euler or velocity_verlet"):
        DiffRun(model, dt=1e-3, steps=10, integrator="implicit_euler")
    for track, match in ((dict(translation=ws.Track([0.0, 1.0], [[0, 0, 0], [0, 0, 1]], interpolation="smooth")),
                          "linear or step pin tracks"),
                         (dict(rotation=ws.Track.rotation([0.0, 1.0], axis=(0, 0, 1), degrees=[0, 90])),
                          "translation tracks only")):
        driven = SCENES["driven_cloth"].build(SCENES["driven_cloth"].values, device)
        driven.set_pin_group_tracks("top", **track)
        with pytest.raises(ConfigError, match=match):
            DiffRun(driven, dt=1e-3, steps=10)
    builder = ws.ModelBuilder()
    builder.add_pin_group(builder.add_cloth_grid(nx=3, ny=3, spacing=0.1, particle_mass=0.1)[-1], name="hand")
    with pytest.raises(ConfigError, match="driven through Control"):
        DiffRun(builder.finalize(device, precision="float64"), dt=1e-3, steps=10)
    run = DiffRun(model, dt=1e-3, steps=10)
    with pytest.raises(ConfigError, match="no targets"):
        run.gradient()
    with pytest.raises(ConfigError, match="step must be in"):
        run.set_targets([Target(11, np.arange(3), np.zeros((3, 3)))])
