"""Checkpoints: a run saved at frame k and loaded into a new simulator of the same scene continues bit for
bit as the uninterrupted run (positions, velocities and each world's float64 time compared as raw bits);
live values changed mid-run, pin targets in flight, contact overflow and the guard's world failures come
back with it; a checkpoint of another scene, integrator, fps or substeps, and a damaged file, are refused
with a one-line ConfigError; an interrupted save leaves the previous checkpoint intact.

The scene is the live-input tests' small cloth (6 × 6, hanging from its top corners), in two worlds of
different stiffness, so that per-world solver state (dopri5's step sizes, implicit Euler's warm starts)
differs between worlds and must come back world by world.
"""

import warnings

import numpy as np
import pytest

import warpspring as ws
from warpspring.core.checkpoint import Checkpoint
from warpspring.core.integrators import make_integrator
from warpspring.errors import ContactOverflowWarning

FPS, SUBSTEPS = 60.0, 8
SAVE_AT, FRAMES = 2, 5  # save after frame 2, compare after frame 5
WORLD_STIFFNESS = np.array([1.0, 3.0])  # per-world stiffness scale


def cloth(device, *, n=6, drag=0.0, precision="float32") -> ws.Model:
    """An n × n cloth hanging from its top corners, under gravity, in two worlds of different stiffness."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81), drag=drag)
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.1, origin=(-0.25, -0.25, 1.0), particle_mass=0.02,
                           structural=ws.SpringMaterial(60.0, 0.05), shear=ws.SpringMaterial(20.0, 0.02),
                           bend=None, pin=["top-left", "top-right"])
    model = builder.finalize(device, worlds=len(WORLD_STIFFNESS), precision=precision)
    ke = model.world_values("spring_stiffness")[0]
    model.set_world_values("spring_stiffness", ke[None, :] * WORLD_STIFFNESS[:, None])
    return model


def simulator(model, integrator="symplectic_euler", *, fps=FPS, substeps=SUBSTEPS, **options) -> ws.Simulator:
    return ws.Simulator(model, integrator=make_integrator(integrator, model), fps=fps, substeps=substeps, **options)


def advance(sim, frames: int) -> None:
    for _ in range(frames):
        sim.step_frame()


def snapshot(sim) -> dict:
    """The state's arrays as host copies."""
    state = sim.state
    return {name: getattr(state, name).numpy().copy() for name in ("particle_q", "particle_qd", "time")}


def assert_bitwise_equal(a: dict, b: dict) -> None:
    """Every array of ``a`` has the dtype and the very bits of ``b``'s (NaN and signed zeros included)."""
    for name in a:
        assert a[name].dtype == b[name].dtype, name
        bits = np.dtype(f"u{a[name].itemsize}")
        assert np.array_equal(a[name].view(bits), b[name].view(bits)), f"{name} differs"


@pytest.mark.parametrize("name", sorted(ws.INTEGRATORS))
def test_a_restored_run_continues_bit_for_bit(device, name, tmp_path):
    """Every integrator: frames SAVE_AT+1 … FRAMES of a simulator loaded from the checkpoint equal the
    uninterrupted run's bit for bit; so does the same simulator rewound to the checkpoint (its captured
    graph stays valid: loading re-captures nothing)."""
    sim = simulator(cloth(device), name)
    advance(sim, SAVE_AT)
    path = sim.save_checkpoint(tmp_path / "run.npz")
    advance(sim, FRAMES - SAVE_AT)
    expected = snapshot(sim)

    fresh = simulator(cloth(device), name)
    fresh.load_checkpoint(path)
    assert fresh.frame == SAVE_AT and fresh.time == SAVE_AT / FPS
    advance(fresh, FRAMES - SAVE_AT)
    assert_bitwise_equal(snapshot(fresh), expected)

    captures = sim.stepper.captures  # (a graph per structure met: with a check spanning frames, two)
    sim.load_checkpoint(path)
    advance(sim, FRAMES - SAVE_AT)
    assert_bitwise_equal(snapshot(sim), expected)
    assert sim.stepper.captures == captures
    # The run moved (the comparison is not of a cloth at rest) and the worlds differ.
    q = expected["particle_q"].reshape(2, -1, 3)
    assert np.abs(q - cloth(device).particle_q.numpy().reshape(2, -1, 3)).max() > 1e-3
    assert np.abs(q[0] - q[1]).max() > 1e-5


def test_a_guard_record_with_fewer_running_slots_still_loads(device, tmp_path):
    """A checkpoint whose guard's running sums have fewer slots per block (written before they held the working
    families' work) loads, the missing slots at zero, and the run and its energy balance continue bit for bit."""
    from warpspring.kernels.guards import RUNNING_SLOTS, RUNNING_WORK

    sim = simulator(cloth(device))
    advance(sim, SAVE_AT)
    checkpoint = Checkpoint.capture(sim)
    advance(sim, FRAMES - SAVE_AT)
    expected, balance = snapshot(sim), sim.guard.energy_balance()
    running = [k for k, v in checkpoint.arrays.items() if k.startswith("hooks/") and v.ndim == 3
               and v.shape[-1] == RUNNING_SLOTS]
    assert len(running) == 1 and RUNNING_WORK == RUNNING_SLOTS - 1
    assert not checkpoint.arrays[running[0]][..., RUNNING_WORK].any()  # zero at a frame's end
    checkpoint.arrays[running[0]] = checkpoint.arrays[running[0]][..., :RUNNING_WORK]
    fresh = simulator(cloth(device))
    checkpoint.restore(fresh)
    advance(fresh, FRAMES - SAVE_AT)
    assert_bitwise_equal(snapshot(fresh), expected)
    np.testing.assert_array_equal(fresh.guard.energy_balance().created, balance.created)


@pytest.mark.parametrize("name", ["implicit_euler", "dopri5"])
def test_the_integrators_history_is_restored(device, name, tmp_path):
    """The checkpoint holds what makes the stateful integrators' continuation exact: the restored arrays
    equal the saved simulator's and the run continues bit for bit, while the same restore with the
    integrator's history then forgotten (implicit Euler's warm start, dopri5's step sizes) ends elsewhere.
    One substep per frame (h = 1/60 s, ω h ≈ 2 in the stiffer world): dopri5 then takes several internal
    steps per step, so the step it proposes next matters."""
    sim = simulator(cloth(device), name, substeps=1)
    advance(sim, SAVE_AT)
    path = sim.save_checkpoint(tmp_path / "run.npz")
    saved = {key: a.numpy().copy() for key, a in sim.integrator.persistent_arrays().items()}
    assert saved  # these integrators carry history
    advance(sim, FRAMES - SAVE_AT)

    fresh = simulator(cloth(device), name, substeps=1)
    fresh.load_checkpoint(path)
    assert_bitwise_equal({k: a.numpy() for k, a in fresh.integrator.persistent_arrays().items()}, saved)
    advance(fresh, FRAMES - SAVE_AT)
    assert_bitwise_equal(snapshot(fresh), snapshot(sim))
    forgetful = simulator(cloth(device), name, substeps=1)
    forgetful.load_checkpoint(path)
    forgetful.integrator.reset()
    advance(forgetful, FRAMES - SAVE_AT)
    assert not np.array_equal(forgetful.state.particle_q.numpy(), sim.state.particle_q.numpy())


def test_values_changed_mid_run_are_restored(device, tmp_path):
    """Gravity changed, drag switched on, an external force applied, rest lengths, stiffness and per-world
    masses edited, a world held and a pin released mid-run: a simulator of the scene as built (without any
    of that) takes them all from the checkpoint and continues bit for bit."""
    model = cloth(device)
    sim = simulator(model)
    advance(sim, 1)
    model.gravity = (0.5, 0.0, -5.0)
    model.drag = 0.05  # off until now: a structural change
    sim.control.set_particle_force((0.01, 0.0, 0.0))
    model.spring_rest_length.assign(model.spring_rest_length.numpy() * np.float32(1.05))
    mass = model.world_values("particle_mass")[0]
    model.set_world_values("particle_mass", mass[None, :] * np.array([[1.0], [2.0]]))  # one row per world now
    model.set_world_enabled(1, False)
    model.set_kinematic([30], False)  # release the top-left pin
    advance(sim, 1)
    path = sim.save_checkpoint(tmp_path / "live.npz")
    advance(sim, 2)
    expected = snapshot(sim)

    fresh = simulator(cloth(device))
    fresh.load_checkpoint(path)
    restored = fresh.model
    assert restored.gravity == (0.5, 0.0, -5.0)
    assert restored.drag_enabled and restored.drag == pytest.approx(0.05)
    assert restored.world_enabled.numpy().tolist() == [1, 0]
    assert not restored.kinematic_mask(world=0)[30] and restored.kinematic_mask(world=0)[35]
    np.testing.assert_array_equal(restored.world_values("particle_mass"), model.world_values("particle_mass"))
    np.testing.assert_array_equal(restored.spring_rest_length.numpy(), model.spring_rest_length.numpy())
    np.testing.assert_array_equal(fresh.control.particle_force.numpy(), sim.control.particle_force.numpy())
    advance(fresh, 2)
    assert_bitwise_equal(snapshot(fresh), expected)


def cloth_with_families(device):
    """The two-world cloth with its bottom row on a PD handle and a free neo-Hookean tet beside it."""
    from warpspring.core.neohookean import NeoHookeanFamily

    builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81))
    ids = builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, origin=(-0.25, -0.25, 1.0), particle_mass=0.02,
                                 structural=ws.SpringMaterial(60.0, 0.05), shear=ws.SpringMaterial(20.0, 0.02),
                                 bend=None, pin=["top-left", "top-right"])
    builder.add_handle(ids[0], kp=2.0, kd=0.05, max_force=1.0)
    rest = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]]) + [1.0, 0.0, 1.0]
    tet = builder.add_particles(rest, mass=0.01)
    family = builder.add_family(NeoHookeanFamily())
    positions = builder.particle_positions(np.arange(tet.max() + 1))
    family.add(np.array([tet]), positions, youngs_modulus=1.0e4, poisson_ratio=0.3, damping=1.0e-4)
    return builder.finalize(device, worlds=2), family


def test_family_live_values_are_restored(device, tmp_path):
    """A handle's gains and the target set from the host in one world, and a neo-Hookean tet's E and ν set in one
    world (its arrays then hold a row per world), changed mid-run: a simulator of the scene as built takes them
    from the checkpoint (``ElementFamily.live_arrays``) and continues bit for bit."""
    model, tets = cloth_with_families(device)
    sim = simulator(model)
    advance(sim, 1)
    handles = model.handles
    handles.set_gains(0, kp=3.0, kd=0.08, max_force=0.8)
    handles.set_target(0, (0.05, 0.1, 0.0), velocity=(0.0, 0.2, 0.0), world=1)
    tets.set_values(youngs_modulus=2.0e4, poisson_ratio=0.2, world=1)
    advance(sim, 1)
    path = sim.save_checkpoint(tmp_path / "families.npz")
    advance(sim, 2)
    expected = snapshot(sim)

    fresh_model, fresh_tets = cloth_with_families(device)
    fresh = simulator(fresh_model)
    fresh.load_checkpoint(path)
    np.testing.assert_array_equal(fresh_tets.values("mu"), tets.values("mu"))
    for name, array in handles.live_arrays().items():
        np.testing.assert_array_equal(fresh_model.handles.live_arrays()[name].numpy(), array.numpy(), err_msg=name)
    advance(fresh, 2)
    assert_bitwise_equal(snapshot(fresh), expected)
    # Without the families' arrays (a checkpoint from before they were saved) the run would not repeat.
    stale = simulator(cloth_with_families(device)[0])
    checkpoint = Checkpoint.load(path)
    checkpoint.arrays = {k: v for k, v in checkpoint.arrays.items() if not k.startswith("families/")}
    checkpoint.restore(stale)
    advance(stale, 2)
    assert not np.array_equal(snapshot(stale)["particle_q"], expected["particle_q"])


def test_integrator_settings_are_restored(device, tmp_path):
    """A tolerance set mid-run (a device value) comes back with the step-size history."""
    sim = simulator(cloth(device), "dopri5")
    advance(sim, 1)
    sim.integrator.tolerance = 1.0e-4
    advance(sim, 1)
    path = sim.save_checkpoint(tmp_path / "dopri5.npz")
    advance(sim, 2)
    fresh = simulator(cloth(device), "dopri5")
    fresh.load_checkpoint(path)
    assert fresh.integrator.tolerance == 1.0e-4
    advance(fresh, 2)
    assert_bitwise_equal(snapshot(fresh), snapshot(sim))


def test_pin_targets_in_flight_are_restored(device, tmp_path):
    """A control-driven pin group on its way to targets reached at frame 5 goes on along the same line."""
    def scene():
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, -9.81))
        builder.add_cloth_grid(nx=6, ny=6, spacing=0.1, origin=(-0.25, -0.25, 1.0), particle_mass=0.02,
                               structural=ws.SpringMaterial(60.0, 0.05), shear=ws.SpringMaterial(20.0, 0.02),
                               bend=None)
        builder.add_pin_group([30, 35], name="corners")
        return builder.finalize(device)

    model = scene()
    sim = simulator(model)
    start = model.particle_q.numpy()[[30, 35]].astype(np.float64)
    sim.control.set_pin_targets("corners", start + [0.2, 0.0, 0.1], time=5.0 / FPS)
    advance(sim, SAVE_AT)
    path = sim.save_checkpoint(tmp_path / "pins.npz")
    advance(sim, FRAMES - SAVE_AT)
    fresh = simulator(scene())
    fresh.load_checkpoint(path)
    advance(fresh, FRAMES - SAVE_AT)
    assert_bitwise_equal(snapshot(fresh), snapshot(sim))
    np.testing.assert_allclose(fresh.state.particle_q.numpy()[[30, 35]], start + [0.2, 0.0, 0.1], atol=1e-6)


def test_contact_overflow_is_restored(device, tmp_path):
    """Contacts dropped before the checkpoint count once: the restored counters go on from there, and the
    next frame warns about its own drops only (one slot, three coincident boxes: 2 per substep)."""
    radius = 0.05
    builder = ws.ModelBuilder()
    builder.add_particles([[0.0, 0.0, 0.2 + radius]], radius=radius)
    for k in range(3):
        builder.add_collider_box(center=(0.0, 0.0, 0.1), half_extents=(0.5, 0.5, 0.1), name=f"box{k}")
    sims = [ws.Simulator(builder.finalize(device, contact_stage=True, contact_slots=1), fps=60, substeps=16)
            for _ in range(2)]
    sim, fresh = sims
    with pytest.warns(ContactOverflowWarning):
        sim.step_frame()
    path = sim.save_checkpoint(tmp_path / "contacts.npz")
    fresh.load_checkpoint(path)
    assert fresh.contact_overflow().tolist() == [2 * 16]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fresh.step_frame()
        sim.step_frame()
    messages = [str(w.message) for w in caught]
    assert len(messages) == 2 and all(m.startswith("frame 2:") and "contacts dropped (32)" in m for m in messages)
    assert fresh.contact_overflow().tolist() == sim.contact_overflow().tolist() == [2 * 2 * 16]
    assert_bitwise_equal(snapshot(fresh), snapshot(sim))


def test_world_failures_are_restored(device, tmp_path):
    """A world the guard stopped stays stopped and named after a restore; the others go on bit for bit."""
    def scene():
        model = cloth(device)
        ke = model.world_values("spring_stiffness")
        model.set_world_values("spring_stiffness", ke * np.array([[1.0], [1.0e7]]))  # world 1 diverges at once
        return model

    guard = ws.GuardLimits(stop="world", every=1)
    sim = simulator(scene(), guard=guard)
    advance(sim, SAVE_AT)
    assert list(sim.world_failures) == [1]
    path = sim.save_checkpoint(tmp_path / "failed.npz")
    advance(sim, FRAMES - SAVE_AT)
    fresh = simulator(scene(), guard=guard)
    fresh.load_checkpoint(path)
    assert fresh.world_failures == {1: sim.world_failures[1]}
    assert fresh.describe_failure(1) == sim.describe_failure(1)
    assert fresh.model.world_enabled.numpy().tolist() == [1, 0]
    advance(fresh, FRAMES - SAVE_AT)
    assert_bitwise_equal(snapshot(fresh), snapshot(sim))


def test_float64_time_and_state_survive_the_round_trip_exactly(device, tmp_path):
    """A float64 model at a step that no binary fraction holds (1/420 s): the file keeps float64 bits, each
    world's clock comes back exactly, and the run continues bit for bit."""
    sim = simulator(cloth(device, precision="float64"), substeps=7)
    advance(sim, 3)
    path = sim.save_checkpoint(tmp_path / "f64.npz")
    saved = snapshot(sim)
    checkpoint = Checkpoint.load(path)
    assert checkpoint.arrays["state/time"].dtype == np.float64
    assert checkpoint.arrays["state/particle_q"].dtype == np.float64
    assert_bitwise_equal({k: checkpoint.arrays[f"state/{k}"] for k in saved}, saved)
    assert checkpoint.header["precision"] == "float64"

    fresh = simulator(cloth(device, precision="float64"), substeps=7)
    fresh.load_checkpoint(path)
    assert_bitwise_equal(snapshot(fresh), saved)
    assert fresh.time == sim.time
    advance(sim, 2)
    advance(fresh, 2)
    assert_bitwise_equal(snapshot(fresh), snapshot(sim))


@pytest.fixture
def saved_run(device, tmp_path):
    """A checkpoint of a dopri5 run of the two-world cloth after one frame."""
    sim = simulator(cloth(device), "dopri5")
    advance(sim, 1)
    return sim.save_checkpoint(tmp_path / "dopri5.npz")


@pytest.mark.parametrize("build, match", [
    (lambda d: simulator(cloth(d, n=7), "dopri5"), r"particles per world 36, but this simulator has 49: load it "
                                                   r"into a simulator built from the scene"),
    (lambda d: simulator(cloth(d), "rk4"), r"integrator dopri5, but this simulator has rk4: build the simulator "
                                           r"with integrator=make_integrator\('dopri5', model\)"),
    (lambda d: simulator(cloth(d), "dopri5", fps=30.0), r"fps 60.0, but this simulator has 30.0: build the "
                                                        r"simulator with fps=60.0"),
    (lambda d: simulator(cloth(d), "dopri5", substeps=4), r"substeps 8, but this simulator has 4"),
    (lambda d: simulator(cloth(d, precision="float64"), "dopri5"), r"precision float32, but this simulator has "
                                                                   r"float64"),
], ids=["particles", "integrator", "fps", "substeps", "precision"])
def test_a_mismatched_simulator_is_refused_with_one_clear_line(device, saved_run, build, match):
    sim = build(device)
    before = snapshot(sim)
    with pytest.raises(ws.ConfigError, match=match) as error:
        sim.load_checkpoint(saved_run)
    assert "\n" not in str(error.value) and str(saved_run) in str(error.value)
    assert_bitwise_equal(snapshot(sim), before)  # nothing was written
    assert sim.frame == 0


def damage(path, kind):
    data = path.read_bytes()
    if kind == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "garbage":
        path.write_bytes(b"not a checkpoint\n" * 64)
    elif kind == "flipped":  # one byte of an array's data changed: the archive's CRC no longer matches
        at = data.index(b"state/particle_q.npy") + 200
        path.write_bytes(data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1:])
    elif kind == "other npz":
        with path.open("wb") as file:
            np.savez(file, positions=np.zeros((4, 3)))
    elif kind == "missing":
        path.unlink()


@pytest.mark.parametrize("kind, match", [
    ("truncated", "cannot be read .*truncated, damaged or not a warpspring checkpoint"),
    ("empty", "cannot be read"),
    ("garbage", "cannot be read"),
    ("flipped", "cannot be read"),
    ("other npz", "is not a warpspring checkpoint"),
    ("missing", "does not exist"),
])
def test_a_damaged_file_is_refused_with_a_clear_error(device, saved_run, kind, match):
    damage(saved_run, kind)
    sim = simulator(cloth(device), "dopri5")
    with pytest.raises(ws.ConfigError, match=match) as error:
        sim.load_checkpoint(saved_run)
    assert "\n" not in str(error.value)


def test_an_interrupted_save_leaves_the_previous_checkpoint_intact(device, tmp_path, monkeypatch):
    """The file is written under a temporary name and renamed at the end: a save killed half-way (here an
    exception from inside the write) leaves the checkpoint of frame 1 as it was, and no temporary file."""
    sim = simulator(cloth(device))
    advance(sim, 1)
    path = sim.save_checkpoint(tmp_path / "run.npz")
    advance(sim, 1)

    def killed(file, **arrays):
        file.write(b"PK\x03\x04 half an archive")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", killed)
    with pytest.raises(KeyboardInterrupt):
        sim.save_checkpoint(path)
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["run.npz"]
    assert Checkpoint.load(path).frame == 1
    with pytest.raises(ws.ConfigError, match="cannot write checkpoint .*missing"):
        sim.save_checkpoint(tmp_path / "missing" / "run.npz")
