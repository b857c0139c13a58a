"""Launches per substep: a plain cloth (springs, gravity, two pinned corners; no colliders, tracks, held worlds,
clamps or guard) launches its force and update kernels and nothing for what the scene lacks.

Counted through wrappers of ``wp.launch`` and of a recorded launch's replay during uncaptured frames: the Stepper captures the very same launches
(its capture runs the same ``_run``), so what is counted here is what every replayed frame runs. The positive
controls (a held world, the contact stage, a pin track, the guard) show that the counter sees a pass when the
scene has one, so the absences asserted for the plain cloth are not vacuous.
"""

import contextlib

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.kernels.flatten import flat_launch

SUBSTEPS = 4

#: Words naming the passes a plain cloth must not launch (matched in the kernels' names).
ABSENT = ("kinematic", "pin", "track", "contact", "collide", "shape", "hold_worlds", "clamp", "strain",
          "plastic", "guard", "emit", "aero", "self")


def cloth(device, evaluation: str = "auto", *, worlds: int = 1, track: bool = False, **finalize) -> ws.Model:
    """An 8 × 8 ANCHORS cloth (0.1 kg particles, ke = 1e3 N/m, kd = 10 N·s/m springs) hung from two corners; with
    ``track``, its top row moves on a keyframe track instead."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(1.0e3, 10.0)
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, origin=(0.0, 0.0, 1.0), particle_mass=0.1, structural=spring,
                           shear=spring, bend=spring, pin=[] if track else ["top-left", "top-right"])
    if track:
        builder.add_pin_group(np.arange(56, 64), translation=ws.Track([0.0, 1.0], [(0.0, 0.0, 0.0), (0.1, 0.0, 0.0)]))
    if finalize.pop("ground", False):
        builder.add_ground_plane()
    return builder.finalize(device, spring_evaluation=evaluation, worlds=worlds, **finalize)


@contextlib.contextmanager
def counted_launches(monkeypatch):
    """Every kernel launched inside the block, in order, by name (a factory's kernel by its factory and its own
    name: ``guard_kernels.measure``): each ``wp.launch`` and each replay of a recorded launch (``wp.Launch.launch``,
    which ``flat_launch`` replays on the CPU); recording one (``record_cmd``) launches nothing."""
    names = []
    launch, replay = wp.launch, wp.Launch.launch

    def name(kernel) -> str:
        return kernel.key.replace("__locals__", ".")

    def counting(kernel, *args, **kwargs):
        if not kwargs.get("record_cmd"):
            names.append(name(kernel))
        return launch(kernel, *args, **kwargs)

    def counting_replay(command, *args, **kwargs):
        names.append(name(command.kernel))
        return replay(command, *args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(wp, "launch", counting)
        patch.setattr(wp.Launch, "launch", counting_replay)
        yield names


def frame_launches(model: ws.Model, monkeypatch, guard=None) -> list[str]:
    """The kernels one uncaptured frame of ``SUBSTEPS`` substeps launches, after a first frame (compiles, the
    guard's first check)."""
    sim = ws.Simulator(model, substeps=SUBSTEPS, use_graph=False, guard=guard)
    sim.step_frame()
    with counted_launches(monkeypatch) as names:
        sim.step_frame()
    return names


def step_kernels(model: ws.Model) -> list[str]:
    """The kernels of one symplectic Euler substep of a plain cloth: the fused gather step (on the CPU its sweep, one
    thread per world: ``kernels/sweep.py``), or the scattered springs' three passes (the other forces, the springs,
    the update)."""
    if model.spring_gather:
        if model.device.is_cpu:
            return ["symplectic_euler_sweep_kernel.symplectic_euler_sweep"]
        return ["symplectic_euler_kernel.symplectic_euler"]
    return ["eval_forces_kernel.eval_forces", "spring_scatter_kernel.scatter_springs",
            "symplectic_euler_update_kernel.symplectic_euler_from_forces"]


@pytest.mark.parametrize("evaluation", ["auto", "gather", "scatter"])
def test_a_plain_cloth_launches_its_step_kernels_and_nothing_else(device, evaluation, monkeypatch):
    model = cloth(device, evaluation)
    names = frame_launches(model, monkeypatch)
    assert names == step_kernels(model) * SUBSTEPS
    assert len(names) / SUBSTEPS <= 3
    lacking = [name for name in names if any(word in name for word in ABSENT)]
    assert not lacking, f"launched for passes the scene lacks: {lacking}"


def test_auto_takes_one_launch_per_substep_on_the_cpu(monkeypatch):
    """``auto`` picks the gathered springs on the CPU, whose symplectic Euler step is the sweep there (measured
    faster than the scatter and than the per-particle step: bench/results/performance_cpu.md): one launch per
    substep, one thread per world."""
    model = cloth("cpu")
    assert model.spring_gather
    assert frame_launches(model, monkeypatch) == ["symplectic_euler_sweep_kernel.symplectic_euler_sweep"] * SUBSTEPS


def collider_cloth(*, moving: bool = False) -> ws.Model:
    """The plain cloth (``cloth``) on the CPU above a sphere collider it falls onto; ``moving``: the sphere slides on a
    keyframe track."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(1.0e3, 10.0)
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, origin=(0.0, 0.0, 1.0), particle_mass=0.1, structural=spring,
                           shear=spring, bend=spring, pin=["top-left", "top-right"])
    track = ws.Track([0.0, 1.0], [(0.0, 0.0, 0.0), (0.2, 0.0, 0.0)]) if moving else None
    builder.add_collider_sphere(center=(0.35, 0.3, 0.9), radius=0.2, translation=track)
    return builder.finalize("cpu")


def test_a_cloth_with_a_collider_launches_one_pass_per_substep_on_the_cpu(monkeypatch):
    """A static collider on the CPU: its contacts are projected inside the sweep, so a substep is still the one sweep
    launch: no collider-motion, kinematics, contact-buffer or clamp pass. The same collider on a track adds what its
    motion needs (its motion, the collision and the projection per substep: the positive control, the counter sees
    the passes a scene has)."""
    model = collider_cloth()
    assert model.shape_count == 1
    names = frame_launches(model, monkeypatch)
    assert names == ["symplectic_euler_sweep_kernel.symplectic_euler_sweep"] * SUBSTEPS
    moving = frame_launches(collider_cloth(moving=True), monkeypatch)
    assert len(moving) > len(names), "a collider on a track launched nothing for its motion"
    assert moving.count("symplectic_euler_sweep_kernel.symplectic_euler_sweep") == SUBSTEPS


def test_a_held_world_adds_one_pass_per_substep(device, monkeypatch):
    """Positive control: the hold pass is counted when a world is held, and only then."""
    model = cloth(device, worlds=2)
    assert not [name for name in frame_launches(model, monkeypatch) if "hold_worlds" in name]
    model.set_world_enabled([1], False)
    names = frame_launches(model, monkeypatch)
    assert names == (step_kernels(model) + ["hold_worlds_kernel.hold_worlds"]) * SUBSTEPS


def test_a_pin_track_and_the_contact_stage_are_counted(device, monkeypatch):
    """Positive controls: a track's kinematics and the contact stage launch passes the plain cloth has not."""
    plain = set(frame_launches(cloth(device), monkeypatch))
    tracked = frame_launches(cloth(device, track=True), monkeypatch)
    staged = frame_launches(cloth(device, ground=True, contact_stage=True), monkeypatch)
    assert set(tracked) - plain, "a pin track launched nothing more than the plain cloth"
    assert set(staged) - plain, "the contact stage launched nothing more than the plain cloth"
    assert len(staged) > len(frame_launches(cloth(device), monkeypatch))


def test_the_guard_launches_only_at_its_checks(device, monkeypatch):
    """Positive control and bound: the default guard adds its passes at its checks, not to every substep."""
    model = cloth(device)
    names = frame_launches(model, monkeypatch, guard=ws.GuardLimits())
    extra = [name for name in names if name not in step_kernels(model)]
    assert any("guard" in name for name in extra)
    assert names.count(step_kernels(model)[0]) == SUBSTEPS


@wp.kernel(module="unique", enable_backward=False)
def scale_add(
    # Control:
    factor: float,
    # In/out:
    x_in_out: wp.array[float],
):
    i = wp.tid()
    x_in_out[i] = factor * x_in_out[i] + 1.0


def test_cpu_launches_outside_a_graph_replay_what_they_recorded(monkeypatch):
    """``flat_launch`` on the CPU records a launch once and replays it while its arguments are the same arrays and
    equal values; a new value, or a new array (even one at a dead array's address and id), is recorded anew."""
    with counted_launches(monkeypatch) as names:
        x = wp.zeros(4, dtype=float, device="cpu")
        for _ in range(3):
            flat_launch(scale_add, dim=4, inputs=[2.0], outputs=[x], device="cpu")
    np.testing.assert_array_equal(x.numpy(), 7.0)  # 0 → 1 → 3 → 7
    assert len(names) == 3
    assert len(scale_add._recorded_launches) == 1  # recorded once, replayed twice
    flat_launch(scale_add, dim=4, inputs=[3.0], outputs=[x], device="cpu")
    np.testing.assert_array_equal(x.numpy(), 22.0)  # the new factor, not the recorded one
    del x
    for _ in range(3):  # arrays freed and made again: the recorded command's address would be stale
        y = wp.zeros(4, dtype=float, device="cpu")
        flat_launch(scale_add, dim=4, inputs=[2.0], outputs=[y], device="cpu")
        np.testing.assert_array_equal(y.numpy(), 1.0)
    z = wp.zeros(4, dtype=float, device="cpu")
    scale_add._recorded_launches.clear()
    flat_launch(scale_add, dim=4, inputs=[0.0], outputs=[z], device="cpu")
    flat_launch(scale_add, dim=4, inputs=[-0.0], outputs=[z], device="cpu")  # -0.0 == 0.0, yet its own value
    assert len(scale_add._recorded_launches) == 2


def test_an_uncaptured_cpu_frame_launches_nothing_anew(monkeypatch):
    """After its first frame, an uncaptured frame of the plain cloth replays recorded launches only (no argument
    packing), to the same bits as the captured frames."""
    graph = ws.Simulator(cloth("cpu"), substeps=SUBSTEPS, use_graph=True, guard=None)
    loose = ws.Simulator(cloth("cpu"), substeps=SUBSTEPS, use_graph=False, guard=None)
    for sim in (graph, loose):
        sim.step_frame()
    packed = []
    launch = wp.launch
    monkeypatch.setattr(wp, "launch", lambda kernel, *a, **k: packed.append(kernel) or launch(kernel, *a, **k))
    for sim in (graph, loose):
        sim.step_frame()
    assert packed == []
    np.testing.assert_array_equal(loose.state.particle_q.numpy(), graph.state.particle_q.numpy())
