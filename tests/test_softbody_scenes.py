"""Soft-body scene keys (``[[soft_body]] pin = {min, max}`` and ``plasticity = {...}``) and a plastic body through
the stability advisor, whose static solve and dry run must leave its springs as built."""

import os

import numpy as np
import pytest

import warpspring as ws
from warpspring.errors import ConfigError
from warpspring.io.scene import parse_scene

BAR = os.path.join(os.path.dirname(__file__), "..", "examples", "meshes", "bar.obj")  # 1 × 0.1 × 0.1 m


def bar_scene(**keys) -> dict:
    """A foam bar (voxels of 5 cm: 21 × 3 × 3 particles) at z = 0.5 m, gravity on; ``keys`` go into its table."""
    body = {"mesh": BAR, "method": "voxel", "spacing": 0.05, "youngs_modulus": 1.5e6, "density": 50.0,
            "origin": [0.0, 0.0, 0.5], **keys}
    return {"version": 2, "simulation": {"fps": 60, "frames": 1, "substeps": 200},
            "world": {"gravity": [0.0, 0.0, -9.81]}, "soft_body": [body]}


PIN = {"min": [-0.51, -1.0, 0.0], "max": [-0.49, 1.0, 1.0]}  # the bar's left face: its 3 × 3 particles


def test_pin_box_and_plasticity_keys(device):
    """``pin`` pins exactly the particles inside its box (the 9 of the left face, by their positions as
    placed); ``plasticity`` gives every spring of the body the limits (all 7 families' springs plastic)."""
    scene = parse_scene(bar_scene(pin=PIN, plasticity={"yield_strain": 0.03, "hardening": 2.0}))
    model = scene.finalize(device)
    q = model.particle_q.numpy()
    pinned = model.particle_flags.numpy() != 0
    np.testing.assert_array_equal(pinned, np.isclose(q[:, 0], -0.5))
    assert pinned.sum() == 9
    assert model.spring_plastic_count == model.spring_count > 0


@pytest.mark.parametrize("keys, message", [
    ({"pin": {"min": [2.0, 2.0, 2.0], "max": [3.0, 3.0, 3.0]}}, "holds none of its particles"),
    ({"pin": {"min": [0.0, 0.0, 0.0], "max": [-1.0, 1.0, 1.0]}}, "above max"),
    ({"pin": {"min": [0.0, 0.0, 0.0]}}, "needs min"),
    ({"plasticity": {"hardening": 1.0}}, "needs yield_strain"),
    ({"plasticity": {"yield_strain": -0.1}}, "yield_strain"),
])
def test_bad_soft_body_keys_are_named(keys, message):
    """Each mistake is a one-line ConfigError naming the key and the fix."""
    with pytest.raises(ConfigError, match=message) as info:
        parse_scene(bar_scene(**keys)).builder()
    assert "\n" not in str(info.value)


def test_advice_leaves_plastic_springs_as_built(device):
    """The advisor's static solve under gravity and its dry run step the model; the pinned plastic bar's springs
    (yield at 0.5 %, which its own weight exceeds at the root: ε ≈ 3ρgL²/(Es) = 1 %) keep their rest lengths and
    no plastic strain afterwards. Before the fix, ``examples/plastic_bar.toml`` started its run with rest lengths
    moved by up to 0.19 m (measured)."""
    model = parse_scene(bar_scene(pin=PIN, plasticity={"yield_strain": 0.005})).finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=200)
    rest = model.spring_plastic_rest_length.numpy().copy()
    ws.advise(model, "symplectic_euler", sim.dt, fps=60.0, control=sim.control, horizon=0.5)
    np.testing.assert_array_equal(model.spring_plastic_rest_length.numpy(), rest)
    np.testing.assert_array_equal(model.spring_plastic_strain.numpy(), 0.0)
    for _ in range(8):  # and the run itself yields within 0.13 s (a quarter of the bending period), as the dry run had
        sim.step_frame()
    assert np.abs(model.spring_plastic_rest_length.numpy() - rest).max() > 1.0e-4


def test_skin_pinned_primvar(device, tmp_path):
    """``primvars = ("pinned",)`` on a soft body's mesh: 1 at the 4 vertices of the bar's pinned left face (each
    follows one pinned corner particle), 0 at the 4 of its free right face."""
    from pxr import Usd, UsdGeom

    from warpspring.io.usd import UsdWriter

    model = parse_scene(bar_scene(pin=PIN)).finalize(device)
    path = tmp_path / "bar.usda"
    with UsdWriter(path, model, fps=60.0, primvars=("pinned",)) as writer:
        writer.write_frame(model.state())
    stage = Usd.Stage.Open(str(path))  # held: a prim does not keep its stage alive
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/soft_body"))
    points = np.asarray(mesh.GetPointsAttr().Get(0))
    pinned = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("pinned").Get(0))
    np.testing.assert_array_equal(pinned, np.isclose(points[:, 0], -0.5).astype(np.int32))
