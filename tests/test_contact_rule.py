"""Triangle contacts switched on by the scene (core/builder/colliders.py, the rule in its docstring): on where a
sphere or capsule is too thin for particle contacts to hold the cloth, off where they are enough, and the cloth
never closer to the collider than its radius (float64 distances of the cloth's triangles, every frame)."""

import math

import numpy as np
import pytest

import warpspring as ws
from helpers import points_samples
from warpspring.analysis.audit import edge_edge_distance, segment_crosses_triangle, vertex_triangle_distance
from warpspring.core.builder.colliders import covering_radius, model_triangle_contacts, triangle_contact_rule
from warpspring.core.records import ShapeInfo
from warpspring.app.runner import run_scene
from warpspring.io.scene import load_scene

SPACING, RADIUS = 0.1, 0.01  # seed 002's cloth: 10 cm between particles of 1 cm contact radius


def seed_cloth(collider: str, collider_radius: float, *, device, contact_triangles=None) -> ws.Model:
    """Seed 002's soft cloth (20 × 20, 0.4 kg, ke 1 / 0.5 / 0.05 N/m) released flat 0.3 m above a sphere or a
    capsule (axis along x) centred at the origin."""
    builder = ws.ModelBuilder()
    half = 0.5 * 19 * SPACING
    builder.add_cloth_grid(nx=20, ny=20, spacing=SPACING, origin=(-half, -half, 0.3 + collider_radius), mass=0.4,
                           radius=RADIUS, structural={"ke": 1.0, "kd": 0.0}, shear={"ke": 0.5, "kd": 0.0},
                           bend={"ke": 0.05, "kd": 0.0})
    if collider == "sphere":
        builder.add_collider_sphere(center=(0.0, 0.0, 0.0), radius=collider_radius)
    else:  # along x: its round side under the cloth
        s = math.sqrt(0.5)
        builder.add_collider_capsule(center=(0.0, 0.0, 0.0), radius=collider_radius, half_height=0.4,
                                     orientation=(0.0, s, 0.0, s))
    return builder.finalize(device, contact_triangles=contact_triangles)


def closest_distance(model: ws.Model, x: np.ndarray, collider: str) -> float:
    """The float64 distance from the collider's centre (sphere) or axis (capsule) to the nearest cloth triangle."""
    tris = model.tri_indices.numpy().reshape(-1, 3)
    a, b, c = (x[tris[:, k]].astype(np.float64) for k in range(3))
    if collider == "sphere":
        return float(vertex_triangle_distance(np.zeros(3), a, b, c).min())
    p, q = np.array([-0.4, 0.0, 0.0]), np.array([0.4, 0.0, 0.0])
    if segment_crosses_triangle(p, q, a, b, c).any():
        return 0.0
    d = min(float(edge_edge_distance(p, q, u, v).min()) for u, v in ((a, b), (b, c), (c, a)))
    return min(d, float(vertex_triangle_distance(p, a, b, c).min()), float(vertex_triangle_distance(q, a, b, c).min()))


def drop(model: ws.Model, collider: str, *, frames: int = 60, substeps: int = 20) -> float:
    """Seed 002's drop for 1 s at 60 fps and its 20 substeps: the closest distance [m] over every frame."""
    sim = ws.Simulator(model, fps=60.0, substeps=substeps)
    closest = math.inf
    for _ in range(frames):
        sim.step_frame()
        closest = min(closest, closest_distance(model, sim.state.particle_q.numpy(), collider))
    return closest


def test_covering_radius():
    # A right triangle: half its hypotenuse; an equilateral one of side s: s/√3; a degenerate one: half its length.
    corners = np.array([[[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]],
                        [[0, 0, 0], [1, 0, 0], [0.5, math.sqrt(0.75), 0]],
                        [[0, 0, 0], [1, 0, 0], [2, 0, 0]]], dtype=float)
    np.testing.assert_allclose(covering_radius(corners), [0.5 * math.hypot(0.1, 0.1), 1 / math.sqrt(3), 1.0],
                               rtol=1e-12)


@pytest.mark.parametrize("radius, needed", [(0.04, True), (0.45, True), (0.55, False), (1.0, False)])
def test_rule_threshold(radius, needed):
    # ρ = 0.0707 m, r = 0.01 m: the sag c - √(c² - ρ²) with c = R + r passes r/2 = 5 mm for R below ~0.49 m
    # (c² - (c - r/2)² = ρ² ⇒ c = (ρ² + r²/4) / r = 0.5025 m); R = 0.04 m slips through (ρ > c).
    shape = ShapeInfo(kind="sphere", name="s", position=(0, 0, 0), rotation=(0, 0, 0, 1), size=(radius, 0, 0),
                      friction=0.5)
    corners = np.array([[[0, 0, 0], [SPACING, 0, 0], [SPACING, SPACING, 0]]], dtype=float)
    rule = triangle_contact_rule([shape], corners, RADIUS)
    c = radius + RADIUS
    rho = math.hypot(SPACING, SPACING) / 2
    assert rule.needed is needed is (rho >= c or c - math.sqrt(c * c - rho * rho) > 0.5 * RADIUS)
    assert ("on" if needed else "off") in rule.reason and rule.collider == "s"


@pytest.mark.parametrize("collider", ["sphere", "capsule"])
@pytest.mark.parametrize("collider_radius, needed", [(0.04, True), (1.0, False)])
def test_cloth_stays_outside(device, collider, collider_radius, needed):
    model = seed_cloth(collider, collider_radius, device=device)
    assert model.contact_triangles is needed
    assert model_triangle_contacts(model).needed is needed
    closest = drop(model, collider)
    # The cloth's triangles never come closer to the centre (axis) than the collider's radius, in any frame (a
    # collider passing through a triangle would have to cross it; the cloth may slide off a small one sideways).
    assert closest >= collider_radius, (closest, collider_radius)


def test_thin_sphere_passes_without_triangles(device):
    # The control: the same drop with the key switching triangle contacts off lets the sphere through (seed 002).
    model = seed_cloth("sphere", 0.04, device=device, contact_triangles=False)
    assert model.contact_triangles is False
    closest = drop(model, "sphere")
    assert closest < 0.5 * 0.04


def test_seed_scene_holds(device, tmp_path):
    # Seed 002 as a scene file without a [contacts] table, at its 20 substeps and with "auto" (16 here: the contact
    # travel bound of analysis/step_choice.py): the rule switches triangle contacts on, the run says so, and the
    # sphere never comes through: every frame's cloth surface stays at least the sphere's radius from its centre
    # (measured on the CPU: 4.78 cm at 20 substeps, 4.64 cm at 16; with triangle contacts off the same run comes
    # within 0.76 cm: test_thin_sphere_passes_without_triangles).
    text = """
version = 2
[simulation]
fps = 60
frames = 60
SUBSTEPS
[world]
gravity = [0.0, 0.0, -9.81]
[cloth]
grid = { nx = 20, ny = 20, spacing = 0.1 }
origin = [-0.95, -0.95, 0.3]
mass = 0.4
radius = 0.01
structural = { ke = 1.0, kd = 0.0 }
shear = { ke = 0.5, kd = 0.0 }
bend = { ke = 0.05, kd = 0.0 }
[[collider]]
type = "sphere"
center = [0.0, 0.0, 0.0]
radius = 0.04
"""
    for substeps in ("substeps = 20", ""):
        path = tmp_path / "seed.toml"
        path.write_text(text.replace("SUBSTEPS", substeps))
        notes = []
        summary = run_scene(load_scene(str(path)), output=str(tmp_path / "seed.usdc"), device=device, progress=False,
                            note=notes.append)
        assert any(line.startswith("triangle contacts on") for line in summary.choices)
        assert any(line.startswith("substeps auto") for line in summary.choices) is (substeps == "")
        assert notes == list(summary.choices) and "triangle contacts on" in summary.line()
        samples, _, _ = points_samples(tmp_path / "seed.usdc")
        model = load_scene(str(path)).finalize(device)
        assert model.contact_triangles
        closest = min(closest_distance(model, np.asarray(x, dtype=np.float64), "sphere") for x in samples)
        assert closest >= 0.04, (substeps, closest)
