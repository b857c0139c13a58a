"""A frame's substeps in one launch (``kernels/frames.py``) against one launch per substep.

The one-launch frame loops the very per-particle step of the fused symplectic Euler kernel inside a thread block
per world, reading buffer k mod 2 at substep k as the stepper's alternation does: the same operations in the same
order. On the CPU positions, velocities, the worlds' clocks and the guard's energy and work agree to the last bit. On a
GPU the two kernels are compiled apart and the compiler fuses multiply-adds differently (an H200 gave 1-ulp
differences, 6e-8 m, after 10 frames with contacts): there they agree within float32 rounding, a few ulps of the
values per step. With the default guard on, colliders (ground and sphere), drag, an external force, per-world
stiffness, and an even or odd substep count.
"""

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.core.builder.spring_materials import DEFAULT_BEND

WORLDS = 3


def scene(device, *, worlds: int = WORLDS, **options) -> ws.Model:
    """A 10 × 10 cloth (0.02 kg particles, ke = 400 N/m) dropped flat onto a sphere above the ground, its two corners
    pinned, drag on, each world a different stiffness."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(400.0, 0.05)
    builder.add_cloth_grid(nx=10, ny=10, spacing=0.05, origin=(-0.225, -0.225, 0.235), particle_mass=0.02,
                           structural=spring, shear=spring, bend=ws.SpringMaterial(40.0, 0.005),
                           pin=["top-left", "top-right"], radius=0.01)
    builder.add_ground_plane()
    builder.add_collider_sphere(center=(0.0, 0.0, 0.12), radius=0.1)
    if options.pop("moving", False):
        builder.add_collider_sphere(center=(0.3, 0.0, 0.12), radius=0.05,
                                    translation=ws.Track([0.0, 1.0], [(0.0, 0.0, 0.0), (0.1, 0.0, 0.0)]))
    options.setdefault("contact_triangles", False)  # particle contacts: the sphere is 4 spacings across
    model = builder.finalize(device, worlds=worlds, **options)
    model.drag = 0.01
    base = model.spring_stiffness.numpy()[0].astype(np.float64)
    model.set_world_values("spring_stiffness", base[None, :] * np.linspace(0.8, 1.2, worlds)[:, None])
    return model


def run(device, *, one_launch: bool, substeps: int, frames: int = 10):
    model = scene(device)
    control = model.control()
    control.set_particle_force((0.01, 0.0, 0.0))  # a steady push [N] on every particle
    # On the CPU the per-substep path's reference is the per-particle step the one-launch frame loops (the CPU's
    # default sweep sums each particle's springs in another order).
    sim = ws.Simulator(model, integrator=ws.SymplecticEuler(model, one_launch=one_launch, cpu_sweep=False),
                       substeps=substeps, control=control)
    for _ in range(frames):
        sim.step_frame()
    wp.synchronize_device(model.device)
    return sim


@pytest.mark.parametrize("substeps", [8, 7])
def test_one_launch_frame_is_the_per_substep_frame_bit_for_bit(device, substeps):
    fused = run(device, one_launch=True, substeps=substeps)
    assert fused.integrator.frame_shape(fused.control, substeps) is not None  # the one-launch path ran
    plain = run(device, one_launch=False, substeps=substeps)
    assert plain.integrator.frame_shape(plain.control, substeps) is None
    steps = substeps * 10
    fused_balance, plain_balance = fused.guard.energy_balance(), plain.guard.energy_balance()
    for name in ("particle_q", "particle_qd", "time", "energy", "work"):
        if name in ("energy", "work"):  # the guard's (its sums taken at every frame's check)
            a, b = getattr(fused_balance, name), getattr(plain_balance, name)
        else:
            a, b = getattr(fused.state, name).numpy(), getattr(plain.state, name).numpy()
        if device == "cpu" or name == "time":
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:  # float32 rounding: 4 ulps of the largest value per step
            np.testing.assert_allclose(a, b, rtol=0, atol=4 * steps * np.finfo(np.float32).eps * np.abs(b).max(),
                                       err_msg=name)
    # the cloth fell onto the sphere (radius 0.1 m, the particles' 0.01 m): the contacts were in the loop
    q = fused.state.particle_q.numpy()
    assert np.linalg.norm(q - (0.0, 0.0, 0.12), axis=1).min() < 0.1 + 0.01 + 1e-3
    assert fused.guard.reports() == plain.guard.reports() == []


def test_one_launch_only_where_the_scene_allows_it(device):
    model = scene(device)
    assert ws.SymplecticEuler(model, one_launch=True).frame_shape(None, 8) is not None
    assert ws.SymplecticEuler(model, one_launch=True).frame_shape(None, 1) is None  # nothing to fuse
    assert ws.SymplecticEuler(model, one_launch=False).frame_shape(None, 8) is None
    # automatic: not for three worlds (one block each would leave the device idle), not on the CPU
    assert ws.SymplecticEuler(model).frame_shape(None, 8) is None
    moving = scene(device, moving=True)  # a collider on a track: its frames are written every substep
    assert ws.SymplecticEuler(moving, one_launch=True).frame_shape(None, 8) is None
    triangles = scene(device, contact_triangles=True)  # a contact pass of their own after the update
    assert ws.SymplecticEuler(triangles, one_launch=True).frame_shape(None, 8) is None
    scattered = scene(device, spring_evaluation="scatter")  # forces in a pass of their own
    assert ws.SymplecticEuler(scattered, one_launch=True).frame_shape(None, 8) is None


def test_a_world_spread_over_blocks_is_the_per_substep_frame(device):
    """A world over several blocks that meet at a counter between substeps (one block per multiprocessor, the
    path a GPU takes by default for one world of 1,024 particles or more) gives the same frame within float32
    rounding. The CPU runs a launch's threads in turn, so it never spreads a world: one thread per world."""
    if wp.get_device(device).is_cpu:
        assert ws.SymplecticEuler(scene(device), one_launch=True).frame_shape(None, 8) == (1, 1)
        return
    plain = run(device, one_launch=False, substeps=8)
    assert ws.SymplecticEuler(scene(device), one_launch=True).frame_shape(None, 8)[1] == 1  # 100 particles: one block
    spread = scene(device)
    integrator = ws.SymplecticEuler(spread, one_launch=True)
    integrator.SPREAD_LANES = 32  # 100 particles over 4 blocks of 32
    assert integrator.frame_shape(None, 8) == (32, 4)
    control = spread.control()
    control.set_particle_force((0.01, 0.0, 0.0))
    sim = ws.Simulator(spread, integrator=integrator, substeps=8, control=control)
    for _ in range(10):
        sim.step_frame()
    steps = 80
    for name in ("particle_q", "particle_qd"):
        a, b = getattr(sim.state, name).numpy(), getattr(plain.state, name).numpy()
        np.testing.assert_allclose(a, b, rtol=0, atol=4 * steps * np.finfo(np.float32).eps * np.abs(b).max(),
                                   err_msg=name)


def test_the_automatic_shape_takes_one_launch_only_where_it_was_measured_faster():
    """The GPU's automatic choice (``SymplecticEuler.launch_shape``, on an H200's 132 multiprocessors): one world of
    32²-128² spread over blocks, springs only or not; many worlds one block each for the hanging cloth (1.02-1.18x
    measured), but not for a scene that evaluates more inside (a flag in a gusting wind on a moving pole: 0.40-0.89x
    at 1,056 and 4,096 worlds), nor where the worlds are too few to fill the device; ``one_launch=True`` forces it."""
    integrator = ws.SymplecticEuler(scene("cpu"))
    for n in (32, 64, 128):
        for heavy in (False, True):
            assert integrator.launch_shape(n * n, 1, 132, heavy=heavy) == (128, n * n // 128)
    assert integrator.launch_shape(128 * 128, 4, 132) is None  # 512 blocks do not fit at once
    assert integrator.launch_shape(32 * 32, 1056, 132) == (128, 1)
    assert integrator.launch_shape(64 * 64, 4096, 132) == (256, 1)
    for n, worlds in ((32, 1056), (32, 4096), (64, 1056), (128, 4096)):
        assert integrator.launch_shape(n * n, worlds, 132, heavy=True) is None
        assert integrator.launch_shape(n * n, worlds, 132, heavy=True, forced=True) is not None
    assert integrator.launch_shape(32 * 32, 132, 132) is None  # 128 threads a multiprocessor: too few
    assert integrator.launch_shape(16 * 16, 1, 132) is None  # under SPREAD_MIN_PARTICLES, one block: too few



def test_no_frame_is_launched_wider_than_the_kernels_bound():
    """The frame kernel is compiled for blocks of at most ``FRAME_MAX_LANES`` threads (``__launch_bounds__``, which a
    wider launch fails on CUDA): the automatic shape keeps within it, a wider ``SPREAD_LANES`` is clamped to it, and
    ``advance_frame`` refuses a wider shape with the bound named."""
    from warpspring.kernels.frames import FRAME_MAX_LANES

    model = scene("cpu")
    integrator = ws.SymplecticEuler(model)
    for particles in (16 * 16, 32 * 32, 64 * 64, 128 * 128, 1024 * 1024):
        for worlds in (1, 4, 1056, 4096):
            shape = integrator.launch_shape(particles, worlds, 132, forced=True)
            assert shape is not None and shape[0] <= FRAME_MAX_LANES
    integrator.SPREAD_LANES = 4 * FRAME_MAX_LANES
    assert integrator.launch_shape(64 * 64, 1, 132) == (FRAME_MAX_LANES, 64 * 64 // FRAME_MAX_LANES)
    state_a, state_b = model.state(), model.state()
    with pytest.raises(ValueError, match=f"at most {FRAME_MAX_LANES} threads a block"):
        integrator.advance_frame(state_a, state_b, None, 1.0e-3, 4, (2 * FRAME_MAX_LANES, 1))

def test_one_launch_frame_counts_the_dampers_as_the_per_substep_frame(device):
    """The one-launch frame keeps the guard's power sums in each lane's registers over the frame (float64), one entry
    per lane written at its end: a damped cloth without colliders (its D counted) gives the same positions (to the
    last bit on the CPU) and the same D and W as one launch per substep, up to the float32 rounding of the entries
    the per-substep path adds to every step (~1e-7 of each step's energy, 160 steps: 1e-5 of D)."""
    results = []
    for one_launch in (True, False):
        model = _damped_cloth(device, bend=DEFAULT_BEND)
        integrator = ws.SymplecticEuler(model, one_launch=one_launch, cpu_sweep=False)
        sim = ws.Simulator(model, integrator=integrator, substeps=8)
        for _ in range(20):
            sim.step_frame()
        assert (integrator.frame_shape(sim.control, 8) is not None) == one_launch
        assert sim.guard.counts_dissipation
        results.append((sim.state.particle_q.numpy(), sim.guard.energy_balance()))
    (q_fused, fused), (q_plain, plain) = results
    if device == "cpu":
        np.testing.assert_array_equal(q_fused, q_plain)
    assert (fused.dissipated > 0.01 * fused.peak).all()
    np.testing.assert_allclose(fused.dissipated, plain.dissipated, rtol=1e-5)
    np.testing.assert_allclose(fused.work, plain.work, rtol=1e-5)


def both_paths(make, *, substeps: int, frames: int, each_frame=None) -> list:
    """The Simulator (default guard) of a model from ``make()`` stepped ``frames`` frames in one launch a frame, then
    of another one launch per substep (``each_frame(sim, frame)`` before each frame, if given), each asserted to take
    its path: [fused, plain]."""
    sims = []
    for one_launch in (True, False):
        model = make()
        integrator = ws.SymplecticEuler(model, one_launch=one_launch, cpu_sweep=False)
        sim = ws.Simulator(model, integrator=integrator, substeps=substeps)
        for frame in range(frames):
            if each_frame is not None:
                each_frame(sim, frame)
            sim.step_frame()
        wp.synchronize_device(model.device)
        fused = integrator.frame_shape(sim.control, substeps) is not None and sim.guard.quiet_between_steps(substeps)
        assert fused == one_launch
        sims.append(sim)
    return sims


def assert_same_frames(device, fused, plain, steps: int) -> None:
    """To the last bit on the CPU; on a GPU within float32 rounding, 4 ulps of the largest value per step."""
    if device == "cpu":
        np.testing.assert_array_equal(fused, plain)
    else:
        np.testing.assert_allclose(fused, plain, rtol=0, atol=4 * steps * np.finfo(np.float32).eps * np.abs(plain).max())


def flag(device, **wind) -> ws.Model:
    """A 10 × 10 flag pinned at two corners in a wind of (3, 0, 1) m/s through the aerodynamic family, two worlds."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(400.0, 0.05)
    builder.add_cloth_grid(nx=10, ny=10, spacing=0.05, particle_mass=0.02, structural=spring, shear=spring,
                           bend=ws.SpringMaterial(40.0, 0.005), pin=["top-left", "top-right"], name="flag")
    builder.add_aerodynamics(wind=(3.0, 0.0, 1.0), **wind)
    return builder.finalize(device, worlds=2, spring_evaluation="gather")


def test_the_wind_blows_inside_the_one_launch_frame(device):
    """The aerodynamic family evaluated by each corner (no per-triangle pass between substeps) runs inside the
    one-launch frame with the default guard on: the same positions (to the last bit on the CPU) and the same work
    the wind did and energy the dampers took as one launch per substep; a noisy wind whose forces are
    precomputed per triangle, a pass of its own before every substep's gather, keeps one launch per substep."""
    one, per_substep = both_paths(lambda: flag(device), substeps=8, frames=20)
    assert_same_frames(device, one.state.particle_q.numpy(), per_substep.state.particle_q.numpy(), 160)
    fused, plain = one.guard.energy_balance(), per_substep.guard.energy_balance()
    assert (fused.work > 1.0).all()  # the wind did work on the flag (4.6 J in 1/3 s)
    np.testing.assert_allclose(fused.work, plain.work, rtol=1e-5)
    np.testing.assert_allclose(fused.dissipated, plain.dissipated, rtol=1e-5)
    noisy = flag(device, noise=0.3, precompute=True)
    assert ws.SymplecticEuler(noisy, one_launch=True).frame_shape(None, 8) is None


def test_animated_inputs_are_evaluated_inside_the_one_launch_frame(device):
    """Animated inputs (a gust of wind through the aerodynamic family in every world, gravity turning in world 1
    alone) are written at each substep's time inside the one-launch frame, by the world's own lanes, as the
    per-substep path writes them before each step: the same positions (to the last bit on the CPU), clocks and
    inputs at the end, with the default guard on and the frame's substep count odd."""
    gust = ws.Track([0.0, 0.1, 0.3], [(0.0, 0.0, 0.0), (6.0, 0.0, 2.0), (1.0, 0.0, 0.0)], interpolation="smooth")
    turning = ws.Track([0.0, 0.3], [(0.0, 0.0, -9.81), (3.0, 0.0, -9.0)])
    def animated():
        model = flag(device)
        model.set_track("wind", gust)
        model.set_track("gravity", turning, world=1)
        return model

    fused, plain = ([sim.state.particle_q.numpy(), sim.state.time.numpy(), sim.model.inputs.numpy()]
                    for sim in both_paths(animated, substeps=7, frames=18))
    np.testing.assert_array_equal(fused[1], plain[1])  # the clocks: the same float64 sums
    # The inputs the last substep read, in both worlds (float64 sampling rounded to float32: equal, but a GPU's two
    # kernels are compiled apart, the frame's with fast math: within an ulp there)
    assert_same_frames(device, fused[2], plain[2], 1)
    assert_same_frames(device, fused[0], plain[0], 126)
    q = fused[0].reshape(2, -1, 3)
    assert np.abs(q[1] - q[0]).max() > 1e-3  # world 1's turning gravity moved it apart from world 0


def test_driven_pins_move_inside_the_one_launch_frame(device):
    """Pins driven by tracks (one edge turned and carried) and through Control (the other edge sent to a target each
    frame) are put on their prescribed motion inside the one-launch frame by the lane that steps them, at each
    substep's end, as the per-substep path's kinematics pass puts them: the same positions and velocities (to the
    last bit on the CPU), the pins exactly where their motion says, with the default guard on."""
    ids = np.arange(48).reshape(4, 12)  # the 12 × 4 grid's particles, row by row

    def wrung():
        builder = ws.ModelBuilder()
        spring = ws.SpringMaterial(400.0, 0.05)
        builder.add_cloth_grid(nx=12, ny=4, spacing=0.03, particle_mass=0.02, structural=spring, shear=spring,
                               bend=ws.SpringMaterial(40.0, 0.005))
        builder.add_pin_group(ids[:, 0], rotation=ws.Track.rotation([0.0, 0.3], axis=(1, 0, 0), degrees=[0, 90]),
                              translation=ws.Track([0.0, 0.3], [(0, 0, 0), (0.05, 0, 0)], interpolation="smooth"),
                              name="turned")
        builder.add_pin_group(ids[:, -1], name="sent")
        return builder.finalize(device, worlds=2, spring_evaluation="gather")

    sent = wrung().particle_q.numpy()[ids[:, -1]]

    def send(sim, frame):
        sim.set_pin_targets("sent", sent + (0.0, 0.0, 0.004 * (frame + 1)))

    fused, plain = both_paths(wrung, substeps=8, frames=15, each_frame=send)
    for name in ("particle_q", "particle_qd"):
        assert_same_frames(device, getattr(fused.state, name).numpy(), getattr(plain.state, name).numpy(), 120)
    q = fused.state.particle_q.numpy().reshape(2, -1, 3)
    np.testing.assert_allclose(q[:, ids[:, -1]], np.broadcast_to(sent + (0.0, 0.0, 0.06), (2, 4, 3)), atol=1e-6)
    assert fused.guard.reports() == plain.guard.reports() == []


def test_moving_colliders_move_inside_the_one_launch_frame(device):
    """A collider on a track, its contacts fused into the update (``contact_stage=False``; by default a moving
    collider takes the contact stage, a pass of its own, and the frame stays one launch per substep): each substep's
    lanes write the world's colliders' frames at its start and end, as ``update_shape_frames`` does before each
    step, and the frame is the per-substep frame (to the last bit on the CPU)."""
    assert ws.SymplecticEuler(scene(device, moving=True), one_launch=True).frame_shape(None, 8) is None
    fused, plain = both_paths(lambda: scene(device, moving=True, contact_stage=False), substeps=8, frames=12)
    ends = fused.model.shape_arrays.transform_end.numpy()
    assert_same_frames(device, ends, plain.model.shape_arrays.transform_end.numpy(), 1)  # the last substep's frames
    assert np.abs(ends[:, 2, 0] - 0.3 - 0.02).max() < 1e-6  # the small sphere carried 0.2 s × 0.1 m/s along x
    assert_same_frames(device, fused.state.particle_q.numpy(), plain.state.particle_q.numpy(), 96)


#: Where a one-launch frame's guard check runs: at the frame kernel's end, in one launch of the checked kernel after
#: the frame (``SymplecticEuler.CHECK_LAUNCH_APART``), or in the check's own kernels (``guards.CHECK_IN_FRAME`` off).
CHECK_PLACES = ("end", "launch", "apart")


def _checked(make, *, where: str, substeps: int, frames: int, limits=None, control=None, spread_lanes=None):
    """A Simulator of ``make()`` in one launch a frame, its guard's check where ``where`` (``CHECK_PLACES``) says,
    stepped ``frames`` frames (or until the guard stops it: the error returned); ``spread_lanes``: each world spread
    over blocks of that many threads (on a GPU)."""
    from warpspring.core import guards

    device = make().device
    in_frame = where != "apart"
    saved = dict(guards.CHECK_IN_FRAME)
    guards.CHECK_IN_FRAME[device.is_cuda] = in_frame
    try:
        model = make()
        integrator = ws.SymplecticEuler(model, one_launch=True, cpu_sweep=False)
        integrator.CHECK_LAUNCH_APART = {device.is_cuda: where == "launch"}
        launched = []  # the steps of each launch of a frame kernel (the stepper may capture them once)
        launch_frame = integrator._launch_frame
        integrator._launch_frame = lambda kernel, steps, *rest: (launched.append(steps),
                                                                 launch_frame(kernel, steps, *rest))
        if spread_lanes is not None:
            integrator.SPREAD_LANES = spread_lanes
        sim = ws.Simulator(model, integrator=integrator, substeps=substeps,
                           guard=limits if limits is not None else ws.GuardLimits(),
                           control=control(model) if control is not None else None)
        shape = integrator.frame_shape(sim.control, substeps)
        if spread_lanes is not None and device.is_cuda:
            assert shape[1] > 1  # the world's blocks meet at the counter before the first gathers
        offered = sim.guard.frame_check(substeps, shape, integrator=integrator, control=sim.control)
        assert (offered is not None) == in_frame
        error = None
        for _ in range(frames):
            try:
                sim.step_frame()
                sim.settle()  # (on CUDA the verdict comes a frame later: the same frame named either way)
            except ws.SimulationError as exc:
                error = exc
                break
        wp.synchronize_device(device)
        assert launched[:2] == [substeps, 0] if where == "launch" else launched[0] == substeps and 0 not in launched
        return sim, error
    finally:
        guards.CHECK_IN_FRAME.update(saved)


def _damped_cloth(device, n: int = 8, *, bend=ws.SpringMaterial(ke=40.0, kd=0.05)):
    """An n × n cloth (0.02 kg particles, ke = 400 N/m, kd = 0.5 N·s/m; ``bend`` its bend springs' material) hung
    from its two top corners, in drag: two worlds, springs gathered."""
    builder = ws.ModelBuilder(drag=0.02)
    spring = ws.SpringMaterial(ke=400.0, kd=0.5)
    builder.add_cloth_grid(nx=n, ny=n, spacing=0.05, particle_mass=0.02, structural=spring, shear=spring,
                           bend=bend, pin=["top-left", "top-right"])
    return builder.finalize(device, worlds=2, spring_evaluation="gather")


def _pushed(model):
    control = model.control()
    control.set_particle_force((0.01, 0.0, 0.0))
    return control


@pytest.mark.parametrize("where", ["end", "launch"])
@pytest.mark.parametrize("case", ["damped", "contacts", "spread"])
def test_the_check_inside_the_frame_is_the_check_in_its_own_launches(device, case, where):
    """The guard's check at the end of a one-launch frame (its passes run by the frame's lanes, its verdict by each
    world's first block: ``kernels/frames.py``), or by those functions in one launch of the checked kernel with no
    steps after the frame kernel (``where``: ``CHECK_PLACES``), against the same check in its own four launches after
    the frame:
    the same positions to the bit (the check writes no state; on a GPU, with contacts, to 1e-6 m: the frame kernel
    compiled with the check may round the contact step's float32 arithmetic differently, by 1.3e-7 m after 12 frames
    on an H200), and the same energy balance, work and values up to
    the order in which the families' energies are added (float64: 1e-12 of the energy on the CPU). On a GPU the frame
    kernel is compiled with fast math and the check's own kernels without: each element's float32 energy may differ
    in its last bits (6.6e-8 of the energy measured on an H200), so there 1e-6 (8 float32 units in the last place).
    A damped cloth whose D is counted (the power sums and the dampers' closing term at the check), and the push,
    drag, sphere and ground of ``scene`` (three worlds of different stiffness); and on a GPU a 12 × 12 damped cloth
    spread over five blocks of 32 threads a world (the same on the CPU, one thread a world)."""
    make = {"damped": lambda: _damped_cloth(device), "contacts": lambda: scene(device),
            "spread": lambda: _damped_cloth(device, 12)}[case]
    runs = [_checked(make, where=place, substeps=8, frames=12, control=_pushed,
                     spread_lanes=32 if case == "spread" else None) for place in (where, "apart")]
    (inside, error_inside), (apart, error_apart) = runs
    assert error_inside is None and error_apart is None
    q_inside, q_apart = inside.state.particle_q.numpy(), apart.state.particle_q.numpy()
    if wp.get_device(device).is_cpu or case != "contacts":
        np.testing.assert_array_equal(q_inside, q_apart)
    else:  # (the contact step compiled beside the check: its float32 roundings may differ, 1.3e-7 m on an H200)
        np.testing.assert_allclose(q_inside, q_apart, rtol=0, atol=1e-6)
    a, b = inside.guard.energy_balance(), apart.guard.energy_balance()
    scale = np.abs(b.peak).max() * (1e-12 if wp.get_device(device).is_cpu else 1e-6)
    for name in ("energy", "reference", "work", "peak", "dissipated"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=scale, err_msg=name)
    if case != "contacts":
        assert inside.guard.counts_dissipation and (a.dissipated > 0.01 * a.peak).all()
    np.testing.assert_allclose(inside.guard.work(), apart.guard.work(), rtol=0, atol=scale)
    np.testing.assert_array_equal(inside.guard._status.numpy(), apart.guard._status.numpy())


@pytest.mark.parametrize("where", ["end", "launch"])
def test_a_spring_torn_inside_the_frame_is_reported_as_apart(device, where):
    """A failure found by the check inside the frame (at its end or in the launch after it) is the same report as the
    check apart gives: a cloth whose pins
    are pulled apart, checked with a low tear strain, stops at the same frame and substep, naming the same world,
    particle, spring and family."""
    def make():
        builder = ws.ModelBuilder()
        spring = ws.SpringMaterial(ke=50.0, kd=0.05)
        builder.add_cloth_grid(nx=6, ny=6, spacing=0.05, particle_mass=0.05, structural=spring, shear=spring,
                               pin=["top-left", "top-right"])
        return builder.finalize(device, worlds=2, spring_evaluation="gather")

    limits = ws.GuardLimits(tear_strain=0.3)
    runs = [_checked(make, where=place, substeps=8, frames=60, limits=limits) for place in (where, "apart")]
    (inside, error_inside), (apart, error_apart) = runs
    assert error_inside is not None and error_apart is not None
    assert str(error_inside) == str(error_apart)
    assert error_inside.frame == error_apart.frame and error_inside.substep == error_apart.substep
    assert getattr(error_inside, "reason", None) == getattr(error_apart, "reason", None)
    np.testing.assert_array_equal(inside.guard._status.numpy(), apart.guard._status.numpy())


def test_a_frame_check_mark_left_by_an_error_is_forgotten():
    """The mark that the frame ran the guard's check (``Guard.frame_checked``, consumed by the last step's
    ``after_step``) does not outlive its advance: one left behind (an error between the frame and its hooks) is
    dropped at the next advance's start, whose check then runs as it should (the balance moves on)."""
    model = _damped_cloth("cpu")
    sim = ws.Simulator(model, integrator=ws.SymplecticEuler(model, one_launch=False), substeps=8, use_graph=False)
    for _ in range(3):
        sim.step_frame()
    before = sim.guard.energy_balance().energy.copy()
    sim.guard.frame_checked()  # as if a frame's check ran and its after_step never came
    sim.step_frame()
    assert not np.array_equal(sim.guard.energy_balance().energy, before)  # the check ran: the balance moved on
