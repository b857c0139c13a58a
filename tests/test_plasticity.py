"""Plastic springs: rest lengths as state, moved by the post-step pass toward the springs' lengths past an
elastic limit (with creep, hardening and breaking), once per accepted step, per world, carried by
checkpoints.

Every model here is float64 with plastic linear springs (one law specialisation for the module), built with
gravity's switch on (set to zero where the scene needs none), so the kernels compile once.
"""

import math

import numpy as np
import pytest

import warpspring as ws
from warpspring.core.families import element_energies
from warpspring.core.integrators import make_integrator
from warpspring.io.scene import parse_scene
from warpspring.kernels.spring_laws import BROKEN_REST_LENGTH, SpringLaw

L0, KE = 1.0, 100.0


def pulled_spring(device, plasticity, *, pull=0.3, duration=1.0, kd=20.0, worlds=1):
    """Particle 0 pinned at the origin, particle 1 at (L₀, 0, 0) in a pin group that moves it to
    (L₀ + pull, 0, 0) at constant speed over ``duration`` [s] and holds it there; one plastic spring
    (ke = 100 N/m, kd [N·s/m]), 1 kg particles, no gravity."""
    builder = ws.ModelBuilder()
    builder.add_particles(np.array([[0.0, 0.0, 0.0], [L0, 0.0, 0.0]]), mass=1.0)
    builder.add_pin_group([0])
    builder.add_pin_group([1], translation=ws.Track([0.0, duration], [[0.0, 0.0, 0.0], [pull, 0.0, 0.0]],
                                                    interpolation="linear"))
    builder.add_springs([[0, 1]], stiffness=KE, damping=kd, plasticity=plasticity)
    model = builder.finalize(device, precision="float64", worlds=worlds)
    model.gravity = (0.0, 0.0, 0.0)
    assert model.spring_law == SpringLaw(plastic=True)
    return model


def run(sim, frames):
    for _ in range(frames):
        sim.step_frame()


@pytest.mark.parametrize("limit", ["strain, hardening 2", "force"])
def test_a_spring_pulled_past_its_limit_keeps_the_predicted_rest_length(device, limit):
    """Pulled to a total strain ε = 0.3 past the limit ε_y0 = 0.05 (as a strain with hardening H = 2, or as
    the force F_y = ke ε_y0 L₀ = 5 N), the rest length lands on (1 + α) L₀ with α = (ε - ε_y0)/(1 + ε_y0 H)
    (1.2273 L₀ with hardening, 1.25 L₀ without) to rounding, whatever the steps; released (the pin let go)
    the critically damped spring relaxes to that length and stays (its unloading is elastic: the
    compression it passes through stays below the limit)."""
    hardening = 2.0 if limit.startswith("strain") else 0.0
    plasticity = (ws.SpringPlasticity(yield_strain=0.05, hardening=hardening) if hardening
                  else ws.SpringPlasticity(yield_force=5.0))
    model = pulled_spring(device, plasticity)
    sim = ws.Simulator(model, fps=10.0, substeps=10, guard=None)  # steps of 0.01 s
    run(sim, 10)
    alpha = (0.3 - 0.05) / (1.0 + 0.05 * hardening)
    np.testing.assert_allclose(model.spring_rest_lengths()[0], [(1.0 + alpha) * L0], rtol=1e-12)
    np.testing.assert_allclose(model.spring_plastic_strain.numpy(), [alpha], rtol=1e-12)
    model.set_kinematic([1], False)
    run(sim, 30)
    length = np.linalg.norm(np.diff(sim.state.particle_q.numpy(), axis=0))
    np.testing.assert_allclose(model.spring_rest_lengths()[0], [(1.0 + alpha) * L0], rtol=1e-12)
    assert length == pytest.approx((1.0 + alpha) * L0, abs=1e-9)  # e^(-ω t) ≈ e^(-30) of the 0.05 m stretch


def host_return_map(lengths, dt, *, yield_strain, rate, hardening):
    """The plastic pass in float64 on the host, applied once per step to the lengths [m] of one spring at
    the end of each step: the rest length after each step."""
    rest, alpha, history = L0, 0.0, []
    for length in lengths:
        elastic = (length - rest) / L0
        excess = abs(elastic) - yield_strain * (1.0 + hardening * alpha)
        if excess > 0.0:
            flow = min(rate * dt, 1.0) * excess / (1.0 + yield_strain * hardening)
            rest += math.copysign(flow, elastic) * L0
            alpha += flow
        history.append(rest)
    return np.array(history)


@pytest.mark.parametrize("integrator", ["rk4", "dopri5"])
def test_rest_lengths_move_once_per_accepted_step(device, integrator):
    """A free particle flung along a creeping spring (ε_y0 = 0.02, creep rate 20/s, H = 1) that yields in
    tension and then in compression: the rest length after every step equals the host float64 return map
    applied once per step to the lengths the integrator reached (to 1e-12); a pass per Runge-Kutta stage, or
    per dopri5 internal step, would give another history. Dopri5 takes several internal steps per step
    (tolerance 1e-9) and rejects some, which leave no trace."""
    builder = ws.ModelBuilder()
    builder.add_particles(np.array([[0.0, 0.0, 0.0], [L0, 0.0, 0.0]]), velocities=np.array([[0.0] * 3, [3.0, 0, 0]]),
                          mass=1.0, pinned=[True, False])
    plasticity = ws.SpringPlasticity(yield_strain=0.02, yield_rate=20.0, hardening=1.0)
    builder.add_springs([[0, 1]], stiffness=KE, damping=0.5, plasticity=plasticity)
    model = builder.finalize(device, precision="float64")
    model.gravity = (0.0, 0.0, 0.0)
    options = {"tolerance": 1e-9} if integrator == "dopri5" else {}
    stepper = make_integrator(integrator, model, **options)
    dt, steps = 0.02, 60
    a, b = model.state(), model.state()
    lengths, rests = [], []
    for _ in range(steps):
        stepper.step(a, b, None, dt)
        a, b = b, a
        lengths.append(float(np.linalg.norm(np.diff(a.particle_q.numpy(), axis=0))))
        rests.append(model.spring_rest_lengths()[0, 0])
    expected = host_return_map(lengths, dt, yield_strain=0.02, rate=20.0, hardening=1.0)
    np.testing.assert_allclose(rests, expected, rtol=1e-12)
    assert max(expected) > L0 * 1.02 and min(np.diff(expected)) < 0.0  # it yielded both ways
    if integrator == "dopri5":
        assert stepper.accepted_steps > 2 * steps and stepper.rejected_steps > 0


def test_held_worlds_keep_their_rest_lengths_and_checkpoints_resume_bitwise(device, tmp_path):
    """Two worlds of the pulled spring (creep rate 5/s, so the rest lengths move every step): world 1 is held
    after the first frame and keeps its rest length and plastic strain exactly; a checkpoint saved at frame 3
    and loaded into a simulator of a fresh model continues to frame 6 with the same bits (positions,
    velocities, time, rest lengths, plastic strains) as the uninterrupted run. Simulator.reset puts the
    rest lengths back as built."""
    plasticity = ws.SpringPlasticity(yield_strain=0.05, yield_rate=5.0, hardening=0.5)
    model = pulled_spring(device, plasticity, worlds=2)
    sim = ws.Simulator(model, fps=10.0, substeps=10, guard=None)
    run(sim, 1)
    model.set_world_enabled([1], False)
    held = model.spring_rest_lengths()[1].copy()
    run(sim, 2)
    path = sim.save_checkpoint(tmp_path / "plastic.npz")
    run(sim, 3)
    first = {"q": sim.state.particle_q.numpy(), "qd": sim.state.particle_qd.numpy(), "time": sim.state.time.numpy(),
             "rest": model.spring_plastic_rest_length.numpy(), "alpha": model.spring_plastic_strain.numpy()}
    assert first["rest"][1] == held[0] and first["rest"][0] > held[0]

    other = pulled_spring(device, plasticity, worlds=2)
    resumed = ws.Simulator(other, fps=10.0, substeps=10, guard=None)
    resumed.load_checkpoint(path)
    run(resumed, 3)
    second = {"q": resumed.state.particle_q.numpy(), "qd": resumed.state.particle_qd.numpy(),
              "time": resumed.state.time.numpy(), "rest": other.spring_plastic_rest_length.numpy(),
              "alpha": other.spring_plastic_strain.numpy()}
    for name in first:
        assert np.array_equal(first[name].view(np.uint64), second[name].view(np.uint64)), name

    sim.reset()
    np.testing.assert_array_equal(model.spring_rest_lengths(), [[L0], [L0]])
    np.testing.assert_array_equal(model.spring_plastic_strain.numpy(), [0.0, 0.0])


def test_a_spring_past_its_breaking_strain_carries_nothing(device):
    """Pulled past (1 + ε_break) L₀ = 1.2 m, the spring breaks in the step that crosses it: its rest length
    becomes negative, and from then on its force, energy and strain are zero (the pulled particle's
    neighbour, released, stays at rest)."""
    model = pulled_spring(device, ws.SpringPlasticity(yield_strain=0.05, break_strain=0.2), kd=0.0)
    sim = ws.Simulator(model, fps=10.0, substeps=10, guard=None)
    run(sim, 6)  # 0.6 s: length 1.18 m, not broken yet
    assert model.spring_rest_lengths()[0, 0] > 0.0
    run(sim, 1)  # 0.7 s: 1.21 m
    assert model.spring_rest_lengths()[0, 0] == BROKEN_REST_LENGTH
    model.set_kinematic([0], False)
    state = sim.state
    ws.eval_forces(model, state, None)
    np.testing.assert_array_equal(state.particle_f.numpy(), 0.0)
    assert element_energies(model, model.families[0], state.particle_q).sum() == 0.0
    q0 = state.particle_q.numpy()[0].copy()
    run(sim, 2)
    np.testing.assert_array_equal(sim.state.particle_q.numpy()[0], q0)


def test_each_world_reads_its_own_rest_lengths_gathered_and_scattered(device):
    """Two worlds of a random plastic network whose rest lengths were moved differently per world (and one
    spring broken in world 1): the gathered and scattered forces agree to rounding and equal a float64
    reference from each world's own rest lengths, a broken spring adding nothing. A model without plastic
    groups keeps the built rest lengths and its plain struct (no plastic arrays, nothing in the finisher's
    history)."""
    rng = np.random.default_rng(2)
    n = 40
    q = rng.uniform(-1.0, 1.0, (n, 3))
    builder = ws.ModelBuilder()
    builder.add_particles(q, mass=1.0)
    pairs = np.unique(np.sort(rng.integers(0, n, (150, 2)), axis=1), axis=0)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    builder.add_springs(pairs, stiffness=rng.uniform(5.0, 15.0, len(pairs)),
                        plasticity=ws.SpringPlasticity(yield_strain=0.1))
    rest = np.linalg.norm(q[pairs[:, 1]] - q[pairs[:, 0]], axis=1)[None, :] * rng.uniform(0.7, 1.3, (2, len(pairs)))
    rest[1, 3] = BROKEN_REST_LENGTH
    forces = []
    for evaluation in ("gather", "scatter"):
        model = builder.finalize(device, precision="float64", spring_evaluation=evaluation, worlds=2)
        model.gravity = (0.0, 0.0, 0.0)
        model.spring_plastic_rest_length.assign(rest.ravel())
        state = model.state()
        ws.eval_forces(model, state, None)
        forces.append(state.particle_f.numpy().reshape(2, n, 3))
    np.testing.assert_allclose(forces[0], forces[1], rtol=1e-12, atol=1e-12)
    ke = model.spring_stiffness.numpy()[0]
    d = q[pairs[:, 1]] - q[pairs[:, 0]]
    length = np.linalg.norm(d, axis=1)
    for w in range(2):
        tension = np.where(rest[w] < 0.0, 0.0, ke * (length - rest[w]))
        pull = d / length[:, None] * tension[:, None]
        expected = np.zeros((n, 3))
        np.add.at(expected, pairs[:, 0], pull)
        np.add.at(expected, pairs[:, 1], -pull)
        np.testing.assert_allclose(forces[0][w], expected, rtol=1e-10, atol=1e-12)

    elastic = ws.ModelBuilder()
    elastic.add_particles(q, mass=1.0)
    elastic.add_springs(pairs, stiffness=10.0)
    plain = elastic.finalize(device)
    assert plain.spring_law == SpringLaw() and plain.spring_plastic_rest_length is None
    assert make_integrator("symplectic_euler", plain).finish_step.history() == []
    assert not hasattr(plain.spring_arrays(), "law")


def lattice_bar(nx=2, ny=2, nz=10, a=0.1):
    """Nodes [m] of an nx × ny × nz cubic lattice of spacing a along z, and its springs: every edge and both
    diagonals of every face (the issue's voxel lattice without body diagonals)."""
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)
    index = np.arange(len(ijk)).reshape(nx, ny, nz)
    offsets = np.array([(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, -1, 0), (1, 0, 1), (1, 0, -1), (0, 1, 1),
                        (0, 1, -1)])
    pairs = []
    for o in offsets:
        other = ijk + o
        inside = ((other >= 0) & (other < [nx, ny, nz])).all(axis=1)
        pairs.append(np.stack([index[tuple(ijk[inside].T)], index[tuple(other[inside].T)]], axis=1))
    return ijk * a, np.concatenate(pairs)


def test_a_plastic_bar_keeps_its_bend_and_an_elastic_one_returns(device):
    """Two 2 × 2 × 10 lattice bars (0.1 m cells, ke = 2000 N/m, 10 g nodes), clamped at z = 0, each loaded at
    its tip by 0.7 N across for 1.5 s, then released for 2 s (drag 0.2 N·s/m per node settles them): one
    bar's springs yield at a strain of 0.01 (perfectly plastic), the other's are elastic. Loaded, both tips
    deflect ~0.07 m; released, the elastic tip returns to within 1e-6 m of straight (measured 5e-8 m) while
    the plastic one keeps a bend of more than a tenth of its loaded deflection (measured 8.4e-3 m of 7.3e-2 m)
    held by its moved rest lengths: both at rest (speeds below 1e-5 m/s)."""
    q, pairs = lattice_bar()
    builder = ws.ModelBuilder(up_axis="Z", drag=0.2)
    bars = []
    for offset, plasticity in ((0.0, ws.SpringPlasticity(yield_strain=0.01)), (1.0, None)):
        ids = builder.add_particles(q + [offset, 0.0, 0.0], mass=0.01, pinned=q[:, 2] == 0.0)
        builder.add_springs(ids[pairs], stiffness=2000.0, plasticity=plasticity)
        bars.append(ids)
    model = builder.finalize(device, precision="float64")
    model.gravity = (0.0, 0.0, 0.0)
    tips = [ids[q[:, 2] == q[:, 2].max()] for ids in bars]
    control = model.control()
    load = np.zeros((model.particle_count, 3))
    load[np.concatenate(tips), 0] = 0.7 / 4
    control.set_particle_force(load)
    sim = ws.Simulator(model, fps=40.0, substeps=100, control=control, guard=None)  # steps of 0.25 ms

    def deflection():
        x = sim.state.particle_q.numpy()
        return np.array([x[tip, 0].mean() - x[bar[q[:, 2] == 0.0], 0].mean() for tip, bar in zip(tips, bars)])

    run(sim, 60)
    loaded = deflection()
    control.set_particle_force(np.zeros_like(load))
    run(sim, 80)
    plastic, elastic = deflection()
    assert np.all((loaded > 0.05) & (loaded < 0.09)), loaded
    assert abs(elastic) < 1e-6
    assert plastic > 0.1 * loaded[0]
    assert np.abs(sim.state.particle_qd.numpy()).max() < 1e-5
    moved = np.abs(model.spring_rest_lengths()[0] - model.spring_rest_length.numpy())
    assert moved[: len(pairs)].max() > 1e-4 and moved[len(pairs):].max() == 0.0


def cloth_scene(**structural):
    return {"cloth": {"grid": {"nx": 3, "ny": 3, "spacing": 0.1}, "particle_mass": 0.01, "pin": ["top"],
                      "structural": {"ke": 200.0, **structural}, "bend": False}}


def test_scene_spring_tables_take_the_law_and_plasticity():
    """A [cloth] spring table's law, compression_ke and plasticity keys reach that group's springs (and only
    them); a wrong value is a one-line error naming the table."""
    scene = parse_scene(cloth_scene(law="square", compression_ke=50.0, yield_strain=0.05, hardening=0.5,
                                    yield_rate=20.0, break_strain=0.5), path="s.toml")
    model = scene.builder().finalize("cpu", precision="float64")
    assert model.spring_law == SpringLaw(square=True, asymmetric=True, plastic=True)
    structural = model.spring_families["structural"]
    shear = model.spring_families["shear"]
    np.testing.assert_array_equal(model.spring_law_code.numpy()[structural], 1)
    np.testing.assert_array_equal(model.spring_law_code.numpy()[shear], 0)
    np.testing.assert_allclose(model.spring_compression_ratio.numpy()[structural], 0.25)
    np.testing.assert_array_equal(model.spring_plastic_index.numpy(), structural)
    for name, value in (("yield_strain", 0.05), ("hardening", 0.5), ("yield_rate", 20.0), ("break_strain", 0.5)):
        np.testing.assert_allclose(getattr(model, f"spring_{name}").numpy()[structural], value)
    assert np.isinf(model.spring_yield_force.numpy()).all() and np.isinf(model.spring_yield_strain.numpy()[shear]).all()
    for bad, message in (({"law": "cubic"}, "s.toml: cloth.structural: unknown spring law 'cubic'"),
                         ({"hardening": 1.0}, "plasticity needs yield_strain, yield_force or break_strain"),
                         ({"yield_rate": -1.0}, "yield_rate"),
                         ({"compression_ke": 10.0, "ke": 0.0}, None)):
        if message is None:  # caught by the builder: kc without ke
            with pytest.raises(ws.ConfigError, match="stiffness 0") as error:
                parse_scene(cloth_scene(**bad), path="s.toml").builder()
        else:
            with pytest.raises(ws.ConfigError, match=message) as error:
                parse_scene(cloth_scene(**bad), path="s.toml")
        assert "\n" not in str(error.value)
