"""Gradients of a loss over a run (``core/adjoint.py``) against central finite differences in float64, on the
named scenes of ``analysis/grad_scenes.py``.

The loss is Σ |x(t) - x(0)|² over every particle at half the horizon and at its end: a smooth function of every
parameter. Each gradient of the named parameters (the chain through ``ParameterMap``) is compared with the
central difference (L(θ + h) - L(θ - h)) / 2h at h = 1e-4 θ: its truncation error is O(h²) · L''' ≈ 1e-8
relative for these smooth runs and its rounding ~1e-16 L / (h |dL/dθ|) ≲ 1e-9, so 1e-4 relative leaves a wide
margin for a right gradient and none for a wrong one (a wrong adjoint term is off by O(1)). Contact scenes are
smoothed (softplus of width ε, ``SmoothContact``): their loss is as smooth but its third derivative grows as
1/ε², hence 1e-3 there.
"""

from __future__ import annotations

import numpy as np
import pytest

from warpspring.analysis.grad_scenes import SCENES
from warpspring.core.adjoint import DiffRun, Target
from warpspring.core.adjoint_params import ParameterMap



def _run(scene, device, *, worlds=1, integrator=None, checkpoint_every=None, deterministic=False):
    names = list(scene.values)
    theta = np.array([scene.values[k] for k in names])
    mapping = ParameterMap(lambda v: scene.build(v, device), names, theta)
    model = scene.build(scene.values, device, worlds=worlds)
    run = DiffRun(model, dt=scene.dt, steps=scene.steps, integrator=integrator or scene.integrator,
                  contact=scene.contact, checkpoint_every=checkpoint_every, deterministic=deterministic)
    q0 = model.particle_q.numpy().astype(np.float64)[: model.particle_count]
    everyone = np.arange(model.particle_count)
    run.set_targets([Target(scene.steps // 2, everyone, q0), Target(scene.steps, everyone, q0)])
    return run, mapping, theta


def _named_gradient(run, mapping, thetas):
    derivatives = mapping.apply(run, thetas)
    loss, grads = run.gradient()
    return loss, mapping.chain(run, grads, derivatives)


def _finite_differences(run, mapping, theta, relative=1.0e-4):
    out = np.zeros(len(theta))
    for p in range(len(theta)):
        h = relative * abs(theta[p])
        up, down = theta.copy(), theta.copy()
        up[p] += h
        down[p] -= h
        mapping.apply(run, up[None])
        plus = run.loss()[0]
        mapping.apply(run, down[None])
        minus = run.loss()[0]
        out[p] = (plus - minus) / (2.0 * h)
    mapping.apply(run, theta[None])
    return out


def _check(scene_name, device, tolerance, integrator=None):
    scene = SCENES[scene_name]
    run, mapping, theta = _run(scene, device, integrator=integrator)
    loss, gradient = _named_gradient(run, mapping, theta[None])
    assert loss[0] > 1e-7  # the loss is not trivially zero (measured 6.7e-7 m² to 0.5 m²)
    fd = _finite_differences(run, mapping, theta)
    for name, g, f in zip(mapping.names, gradient[0], fd):
        assert abs(f) > 0.0, name  # a parameter the loss does not see would make the comparison vacuous
        assert abs(g - f) <= tolerance * abs(f), f"{scene_name}: d loss / d {name}: adjoint {g:.9e}, FD {f:.9e}"
    return run, mapping, theta, gradient


@pytest.mark.parametrize("integrator", ["symplectic_euler", "velocity_verlet"])
def test_hanging_cloth_gradients_match_finite_differences(device, integrator):
    _check("hanging_cloth", device, 1.0e-4, integrator)


def test_flag_in_wind_gradients_match_finite_differences(device):
    _check("flag", device, 1.0e-4)


def test_draped_cloth_gradients_match_finite_differences(device):
    _check("draped_cloth", device, 1.0e-3)


def test_voxel_ball_on_the_ground_gradients_match_finite_differences(device):
    _check("voxel_ball", device, 1.0e-3)


def test_neohookean_ball_gradients_in_e_and_nu_match_finite_differences(device):
    _check("neohookean_ball", device, 1.0e-4)


def test_spring_group_gradients_match_finite_differences(device):
    """Per-group spring constants (structural, shear and bend SpringMaterials of a 6 × 6 cloth hanging from two
    corners): each group's ke and kd moves its springs' rows (a linear map), within 1e-4 of central differences."""
    import warpspring as ws
    from warpspring.analysis.grad_scenes import GradScene

    def build(values, device=None, precision="float64", worlds=1):
        builder = ws.ModelBuilder(drag=0.01)
        builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, origin=(-0.25, -0.25, 1.0), particle_mass=0.01,
                               structural=ws.SpringMaterial(values["structural_ke"], values["structural_kd"]),
                               shear=ws.SpringMaterial(values["shear_ke"], 0.05),
                               bend=ws.SpringMaterial(values["bend_ke"], values["bend_kd"]),
                               pin=["top-left", "top-right"])
        return builder.finalize(device, precision=precision, worlds=worlds)

    scene = GradScene("spring_groups", build, {"structural_ke": 100.0, "structural_kd": 0.1, "shear_ke": 30.0,
                                               "bend_ke": 10.0, "bend_kd": 0.02}, dt=1.0e-3, steps=80)
    run, mapping, theta = _run(scene, device)
    assert mapping.linear
    loss, gradient = _named_gradient(run, mapping, theta[None])
    fd = _finite_differences(run, mapping, theta)
    for name, g, f in zip(mapping.names, gradient[0], fd):
        assert abs(f) > 0.0 and abs(g - f) <= 1e-4 * abs(f), f"{name}: {g:.9e} vs {f:.9e}"


@pytest.mark.parametrize("integrator", ["symplectic_euler", "velocity_verlet"])
def test_pin_track_keys_gradients_match_finite_differences(device, integrator):
    """The hanging cloth swung by its top row along a linear translation track: the gradient in each component of
    its two free keys (the chain through ``ParameterMap`` into ``pin_keys``), within 1e-4 of central differences
    (measured 1e-11 to 4e-9 on the CPU)."""
    _check("driven_cloth", device, 1.0e-4, integrator)
