"""Wind on cloth triangles (kernels/aero.py): the model's invariants rather than its own formula, the closed
form of a plate falling through still air (its terminal velocity and the tanh approach to it, at first
order in dt), a flag's settled angle converging as the grid is refined, and the scene's [wind] table."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.core.aero import AIR_DENSITY, DEFAULT_DRAG
from warpspring.core.forces import eval_forces
from warpspring.kernels.aero import aero_funcs

G = 9.81


triangle_wind_force = aero_funcs(wp.float64)[0]


@wp.kernel
def wind_forces(x: wp.array2d[wp.vec3d], v: wp.array2d[wp.vec3d], wind: wp.array[wp.vec3d],
                cd: wp.float64, cl: wp.float64, out: wp.array[wp.vec3d]):
    t = wp.tid()
    out[t] = triangle_wind_force(x[t, 0], x[t, 1], x[t, 2], v[t, 0], v[t, 1], v[t, 2], wind[t], wp.float64(1.2),
                                 cd, cl)


def triangle_forces(x, v, wind, *, cd=1.2, cl=0.8, device="cpu") -> np.ndarray:
    """The model's force [N] on each triangle x [t, 3, 3] moving at v [t, 3, 3] in wind [t, 3] (float64)."""
    arrays = [wp.array(np.asarray(a, dtype=np.float64), dtype=wp.vec3d, device=device) for a in (x, v)]
    w = wp.array(np.asarray(wind, dtype=np.float64), dtype=wp.vec3d, device=device)
    out = wp.zeros(len(w), dtype=wp.vec3d, device=device)
    wp.launch(wind_forces, dim=len(w), inputs=[*arrays, w, wp.float64(cd), wp.float64(cl)], outputs=[out],
              device=device)
    return out.numpy()


def random_triangles(count: int, seed: int = 3):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(count, 3, 3)), rng.normal(size=(count, 3, 3)), 5.0 * rng.normal(size=(count, 3))


def test_the_force_ignores_which_side_faces_the_flow_and_scales_with_area_and_speed_squared(device):
    """Reversing the winding (the other side facing the flow) leaves every force unchanged; scaling the triangle
    by s and the relative velocity by k scales it by s²k²; for flow along the plane it is zero."""
    x, v, wind = random_triangles(64)
    f = triangle_forces(x, v, wind, device=device)
    assert np.abs(f).max() > 1.0
    np.testing.assert_allclose(triangle_forces(x[:, [0, 2, 1]], v[:, [0, 2, 1]], wind, device=device), f,
                               rtol=1e-12, atol=1e-12)
    s, k = 2.5, 3.0
    np.testing.assert_allclose(triangle_forces(s * x, k * v, k * wind, device=device), s**2 * k**2 * f, rtol=1e-11)
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    along = wind - (np.einsum("ij,ij->i", wind, normal) / np.einsum("ij,ij->i", normal, normal))[:, None] * normal
    still = np.zeros_like(v)
    assert np.abs(triangle_forces(x, still, along, device=device)).max() < 1e-12 * np.abs(f).max()


def test_a_plate_normal_to_the_flow_feels_its_drag(device):
    """Flow normal to the plate: drag ½ρC_D A|u|² along the flow and no lift; at 45° the lift is
    ½ρC_L A|u|² sin α cos α across the flow, drag ½ρC_D A|u|² sin α along it."""
    x = np.array([[[0, 0, 0], [2, 0, 0], [0, 1, 0]]], float)  # area 1 m², normal +z
    still = np.zeros_like(x)
    f = triangle_forces(x, still, [[0, 0, -4.0]], cd=1.2, cl=0.8, device=device)[0]
    np.testing.assert_allclose(f, [0.0, 0.0, -0.5 * 1.2 * 1.2 * 16.0], rtol=1e-12, atol=1e-12)
    u = 4.0 * np.array([1.0, 0.0, -1.0]) / np.sqrt(2.0)  # 45° to the plate, from above
    f = triangle_forces(x, still, [u], cd=1.2, cl=0.8, device=device)[0]
    s = c = np.sqrt(0.5)
    drag = 0.5 * 1.2 * 1.2 * 16.0 * s * u / 4.0
    lift_direction = np.array([-1.0, 0.0, -1.0]) / np.sqrt(2.0)  # the normal's part across the flow, downwind
    lift = 0.5 * 1.2 * 0.8 * 16.0 * s * c * lift_direction
    np.testing.assert_allclose(f, drag + lift, rtol=1e-12, atol=1e-12)


def plate_model(n: int, device, *, worlds: int = 1, wind=(3.0, -1.0, 8.0), precompute=False) -> ws.Model:
    """A 1 m square plate of n × n particles tilted 0.3 rad about y, no springs, in the wind."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=n, ny=n, spacing=1.0 / (n - 1), particle_mass=0.01, structural=False, shear=False,
                           bend=False, rotation=ws.quat_from_axis_angle((0.0, 1.0, 0.0), 0.3))
    builder.add_aerodynamics(wind=wind, drag=1.1, lift=0.9, precompute=precompute)
    return builder.finalize(device, worlds=worlds)


def total_force(model) -> np.ndarray:
    state = model.state()
    eval_forces(model, state, None)
    return state.particle_f.numpy().astype(np.float64).reshape(model.world_count, -1, 3).sum(axis=1)


@pytest.mark.parametrize("precompute", [False, True], ids=["per-corner", "precomputed"])
def test_a_flat_plate_feels_the_same_force_however_finely_it_is_split(device, precompute):
    """The total wind force on a flat plate at rest is the same for 2, 32 and 512 triangles, and a world with
    no wind feels none while another is in the wind (the wind is a per-world input); the same whether each
    corner computes its triangles' forces or a pass computes each once."""
    totals = [total_force(plate_model(n, device, precompute=precompute))[0] for n in (2, 5, 17)]
    assert np.linalg.norm(totals[0]) > 10.0
    for total in totals[1:]:
        np.testing.assert_allclose(total, totals[0], rtol=2e-5)
    model = plate_model(5, device, worlds=2, precompute=precompute)
    model.set_world_values("wind", [[3.0, -1.0, 8.0], [0.0, 0.0, 0.0]])
    both = total_force(model)
    np.testing.assert_allclose(both[0], totals[0], rtol=2e-5)
    assert np.abs(both[1]).max() == 0.0


def falling_plate(device, substeps: int, seconds: float = 1.0, precompute: bool = False):
    """A horizontal 0.5 m square of areal density σ = 0.1 kg/m² (masses lumped by area, no springs) falling from
    rest through still air: every particle's drag is proportional to its mass, so it falls flat. Its mean
    vertical velocity [m/s] each frame, their spread, and the closed form's terminal speed."""
    n = 6
    r, c = np.divmod(np.arange(n * n), n)
    vertices = np.stack([c * 0.5 / (n - 1), r * 0.5 / (n - 1), np.full(n * n, 10.0)], 1)
    a = (np.arange((n - 1) ** 2) // (n - 1)) * n + np.arange((n - 1) ** 2) % (n - 1)
    faces = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    builder = ws.ModelBuilder()
    builder.add_cloth_mesh(vertices, faces, density=0.1, structural=False, bend=False)
    builder.add_aerodynamics(precompute=precompute)
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=substeps)
    means, spreads = [], []
    for _ in range(int(seconds * 60)):
        sim.step_frame()
        vz = sim.state.particle_qd.numpy()[:, 2].astype(np.float64)
        means.append(vz.mean())
        spreads.append(vz.std())
    return np.array(means), np.array(spreads), np.sqrt(2.0 * 0.1 * G / (AIR_DENSITY * DEFAULT_DRAG))


@pytest.mark.parametrize("precompute", [False, True], ids=["per-corner", "precomputed"])
def test_a_falling_plate_reaches_its_terminal_speed_at_first_order(device, precompute):
    """v(t) = -v_t tanh(g t / v_t), v_t = √(2σg / (ρ C_D)): symplectic Euler's largest error over 1 s falls 4×
    when dt does (first order), and is below 0.1 % of v_t at dt = 1/3840 s; the plate stays flat."""
    errors = []
    for substeps in (4, 16, 64):
        means, spreads, terminal = falling_plate(device, substeps, precompute=precompute)
        t = np.arange(1, len(means) + 1) / 60.0
        errors.append(np.abs(means + terminal * np.tanh(G * t / terminal)).max())
        assert spreads.max() < 1e-5 * terminal
    assert errors[-1] < 1e-3 * terminal
    for coarse, fine in zip(errors, errors[1:]):
        assert 3.5 < coarse / fine < 4.5, errors


def flag_angle(n: int, device) -> tuple[float, float]:
    """A 0.6 m × 0.4 m flag (cotton-like, ``ClothMaterial``: the same cloth at any resolution) on a vertical
    pole along its left edge, in a steady 6 m/s wind across the pole, implicit Euler; over its third second,
    the mean and spread of the angle [deg] by which its centroid droops below the pole's centre."""
    builder = ws.ModelBuilder()
    material = ws.ClothMaterial(stretch=2000.0, shear=500.0, bending=1e-4, density=0.2, stretch_damping=2.0,
                                bending_damping=1e-5)
    ids = builder.add_cloth_grid(nx=n, ny=(n - 1) * 2 // 3 + 1, spacing=0.6 / (n - 1), origin=(0.0, 0.0, 1.0),
                                 rotation=ws.quat_from_axis_angle((1.0, 0.0, 0.0), np.pi / 2), material=material,
                                 pin=["left"])
    builder.add_aerodynamics(wind=(6.0, 0.0, 0.0))
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator("implicit_euler", model), fps=60, substeps=4)
    angles = []
    for frame in range(180):
        sim.step_frame()
        if frame >= 120:
            q = sim.state.particle_q.numpy().astype(np.float64)
            chord = q.mean(axis=0) - q[ids[:, 0]].mean(axis=0)
            angles.append(np.degrees(np.arctan2(-chord[2], chord[0])))
    return float(np.mean(angles)), float(np.std(angles))


@pytest.mark.slow
def test_a_flag_in_steady_wind_settles_to_an_angle_that_converges_with_resolution(device):
    """Grids of 4, 8 and 16 cells along the flag: each settles (its angle varies by < 0.2° over a second) and
    the settled angle's change halves with each refinement (first order in the spacing). (Slow: 10–20 s
    on the CPU.)"""
    (a4, s4), (a8, s8), (a16, s16) = (flag_angle(n, device) for n in (5, 9, 17))
    assert max(s8, s16) < 0.2
    assert 0.0 < a16 - a8 < 0.65 * (a8 - a4), (a4, a8, a16)


def test_the_scene_wind_table_sets_inputs_tracks_and_noise(tmp_path):
    """[wind]: a gust track on the velocity, the density and noise amplitude as inputs, the noise compiled in
    (the family's spec), and the coefficients; an unknown mesh is refused naming the table."""
    from warpspring.io.scene import load_scene

    path = tmp_path / "flag.toml"
    path.write_text("""\
version = 2
[cloth]
name = "flag"
grid = { nx = 5, ny = 4, spacing = 0.1 }
mass = 0.1
pin = ["left"]

[wind]
velocity = { times = [0.0, 1.0, 2.0], values = [[4, 0, 0], [9, 0, 1], [4, 0, 0]], interpolation = "smooth" }
air_density = 1.1
noise = 0.3
noise_scale = 0.4
seed = 7
drag = 1.3
lift = 0.7
""")
    model = load_scene(path).finalize("cpu")
    family = next(f for f in model.families if f.name == "wind triangles")
    assert family.spec(model).noise and family.seed == 7 and family.noise_scale == 0.4
    assert np.all(family.drag == 1.3) and np.all(family.lift == 0.7) and family.element_count == 2 * 4 * 3
    np.testing.assert_allclose(model.world_values("wind")[0], [4.0, 0.0, 0.0])
    assert model.world_values("air_density")[0, 0] == pytest.approx(1.1)
    assert model.world_values("wind_noise")[0, 0] == pytest.approx(0.3)
    assert model.track("wind") is not None
    path.write_text(path.read_text().replace("lift = 0.7", 'lift = 0.7\nmeshes = ["sail"]'))
    with pytest.raises(ws.ConfigError, match=r"flag.toml.*wind.*no mesh named 'sail'"):
        load_scene(path).finalize("cpu")


def test_the_advisor_sees_the_wind_damping():
    """A triangle at rest in a wind normal to it: each corner is damped by a third of D_u's largest eigenvalue,
    ½ρA(C_D|u·n| + (C_D + C_L)|u|); the advisor's limit for symplectic Euler on a stiff triangle falls when a
    strong wind blows (the drag-like damping lowers it), and stays put in calm air."""
    def triangle(wind):
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        ids = builder.add_particles([[0, 0, 1], [1, 0, 1], [0, 1, 1]], mass=1e-3)
        builder.add_springs([[ids[0], ids[1]], [ids[1], ids[2]], [ids[2], ids[0]]], stiffness=100.0)
        builder.add_triangles([ids])
        builder.add_aerodynamics(wind=wind, drag=1.2, lift=0.8)
        return builder.finalize("cpu")

    model = triangle((0.0, 0.0, -30.0))
    family = next(f for f in model.families if f.name == "wind triangles")
    rates = family.damping_rates(model, model.particle_q.numpy().reshape(1, 3, 3).astype(np.float64))
    expected = 0.5 * AIR_DENSITY * 0.5 * (1.2 * 30.0 + (1.2 + 0.8) * 30.0) / 3.0
    np.testing.assert_allclose(rates, expected, rtol=1e-6)  # (the input table holds ρ in float32)
    calm = ws.advise(triangle((0.0, 0.0, 0.0)), "symplectic_euler", dt=1e-4).dt_stable
    windy = ws.advise(model, "symplectic_euler", dt=1e-4).dt_stable
    assert windy < 0.95 * calm


def test_precomputed_triangle_forces_equal_the_corners_own(device):
    """On a crumpled, moving cloth in noisy wind, every particle's force is the same whether its triangles'
    forces were computed once per evaluation or by each corner (to float32 rounding)."""
    forces = []
    for precompute in (False, True):
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        builder.add_cloth_grid(nx=9, ny=7, spacing=0.1, particle_mass=0.01, structural=False, shear=False, bend=False)
        builder.add_aerodynamics(wind=(2.0, 1.0, 6.0), noise=0.4, noise_scale=0.3, seed=5, precompute=precompute)
        model = builder.finalize(device)
        rng = np.random.default_rng(1)
        state = model.state()
        state.particle_q.assign(model.particle_q.numpy() + 0.03 * rng.normal(size=(model.particle_count, 3)))
        state.particle_qd.assign(rng.normal(size=(model.particle_count, 3)))
        eval_forces(model, state, None)
        forces.append(state.particle_f.numpy().astype(np.float64))
    assert np.abs(forces[0]).max() > 0.1
    np.testing.assert_allclose(forces[1], forces[0], rtol=1e-5, atol=1e-6)
