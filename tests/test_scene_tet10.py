"""The ``[[soft_body]] element`` scene key: ``"tet10"`` builds the body of quadratic neo-Hookean tets that
``ModelBuilder.add_soft_body(..., element="tet10")`` builds; a bad value or a T10 without the neo-Hookean material
is a one-line ConfigError."""

import os

import pytest

import warpspring as ws
from warpspring.core.neohookean import NeoHookeanFamily
from warpspring.core.tet10 import QuadraticTetFamily
from warpspring.io.scene import parse_scene

CUBE = os.path.join(os.path.dirname(__file__), "..", "examples", "meshes", "cube.obj")  # 0.3 m a side
BODY = {"mesh": CUBE, "method": "delaunay", "spacing": 0.1, "youngs_modulus": 1.0e5, "density": 1000.0,
        "elasticity": "neohookean"}


def cube_scene(**keys) -> dict:
    return {"version": 2, "simulation": {"fps": 60, "frames": 1, "substeps": 10}, "soft_body": [{**BODY, **keys}]}


def families(model) -> dict:
    return {type(f): f for f in model.families}


def test_tet10_scene_builds_the_quadratic_family():
    """``element = "tet10"`` gives the model the quadratic tet family with the elements and particles (corners
    plus mid-edge nodes) the API call with the same arguments makes, no linear tets and no springs; leaving the
    key out keeps the linear tets."""
    model = parse_scene(cube_scene(element="tet10"), path="s.toml").finalize("cpu")
    builder = ws.ModelBuilder()
    body = builder.add_soft_body(CUBE, method="delaunay", spacing=0.1, youngs_modulus=1.0e5, density=1000.0,
                                 elasticity="neohookean", element="tet10")
    assert body.element == "tet10"
    found = families(model)
    assert QuadraticTetFamily in found and NeoHookeanFamily not in found and model.spring_count == 0
    assert found[QuadraticTetFamily].element_count == len(body.topology.tets) > 0
    assert model.particle_count == len(body.particles) == builder.particle_count
    linear = families(parse_scene(cube_scene(), path="s.toml").finalize("cpu"))
    assert NeoHookeanFamily in linear and QuadraticTetFamily not in linear


@pytest.mark.parametrize("keys, message", [
    ({"element": "tet20"}, r"soft_body\.element must be one of 'tet4', 'tet10', got 'tet20'"),
    ({"element": "tet10", "elasticity": "springs"}, "give elasticity='neohookean' with it"),
])
def test_bad_element_keys_are_named(keys, message):
    """A value outside tet4/tet10 is refused when the scene is read; tet10 with spring elasticity by the builder.
    Each is one line naming the file."""
    with pytest.raises(ws.ConfigError, match=message) as info:
        parse_scene(cube_scene(**keys), path="s.toml").builder()
    assert "\n" not in str(info.value) and "s.toml" in str(info.value)
