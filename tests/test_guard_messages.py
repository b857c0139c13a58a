"""A guard stop names what the scene holds that can drive it unstable (the step against its stiffest springs, its
contacts and loads, and nothing it does not hold) and a remedy that, tried as printed, completes the run with the
balance closed."""

import re
import warnings

import numpy as np
import pytest

import warpspring as ws
from helpers import run_frames

FRAMES = 30  # 0.5 s at 60 fps: the stiff cloth below blows up within a few frames at 1 substep


def stiff_cloth(device, *, collider: bool = False, wind: bool = False) -> ws.Model:
    """An 8 × 8 cloth of 10 g particles on 10 kN/m springs (a single spring's ω = √(2 ke/m) = 1414 rad/s: ω h = 24 at
    one substep of 1/60 s), hung from its top row; with a sphere collider below it (never touched in 0.5 s) and a
    3 m/s wind on its triangles."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=1.0e4, kd=0.05)
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, particle_mass=0.01, structural=spring, shear=spring,
                           pin=["top"])
    if collider:
        builder.add_collider_sphere(center=(0.35, 0.0, -5.0), radius=0.5)
    if wind:
        builder.add_aerodynamics(wind=(0.0, 3.0, 0.0))
    return builder.finalize(device)


def stopped_message(model, substeps: int) -> str:
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=substeps)
    with pytest.raises(ws.SimulationError) as stop:
        run_frames(sim, FRAMES)
    return str(stop.value)


@pytest.mark.parametrize("collider, wind", [(False, False), (True, True)])
def test_a_stop_names_the_scenes_suspects_and_its_remedy_works(device, collider, wind):
    """At one substep the stiff cloth is stopped; the message names the step against the stiffest springs (their
    ω_max h bound far above symplectic Euler's 2), and the collider and the wind exactly where the scene has them.
    The remedy's substeps, tried, run the 0.5 s to the end with the balance closed: the energy created within the
    guard's 10 % of the budget (and the run not stopped)."""
    message = stopped_message(stiff_cloth(device, collider=collider, wind=wind), 1)
    assert "suspects in this scene" in message
    bound = float(re.search(r"ω_max h ≤ ([0-9.]+) against symplectic_euler's limit 2.00", message).group(1))
    assert bound > 2.0  # the step is named because it is past the limit
    assert ("collider" in message) == collider
    assert ("wind triangles" in message) == wind
    assert "external force" not in message and "handle" not in message  # not in this scene
    substeps = int(re.search(r"substeps = (\d+)", message).group(1))
    assert substeps > 1
    model = stiff_cloth(device, collider=collider, wind=wind)
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=substeps)
    run_frames(sim, FRAMES)
    balance = sim.guard.energy_balance()
    assert np.all(np.isfinite(sim.state.particle_q.numpy()))
    assert balance.created[0] <= 0.1 * balance.peak[0]


def test_a_tear_at_a_step_within_the_limit_is_told_to_change_the_material(device):
    """A tear (a strain stop) names the scene's suspects too; where the springs' bound certifies the step stable at any
    stretch (ω_max h within the limit: a Hooke spring's stiffness across it is below ke) the springs really stretch
    that far, and the remedy is the material, not more substeps; past the limit it is the substeps."""
    from warpspring.core.guard_records import GuardReport, stop_advice

    model = stiff_cloth(device)
    report = GuardReport(world=0, reason="strain", substep=0, particle=0, spring=0, strain=11.0, kinetic_energy=0.0,
                         family="springs", element=0)
    soft = stop_advice(report, model, integrator="symplectic_euler", substeps=64, dt=1.0 / (60 * 64))
    assert "suspects in this scene" in soft and "stiffer springs" in soft and "substeps =" not in soft
    fast = stop_advice(report, model, integrator="symplectic_euler", substeps=1, dt=1.0 / 60)
    assert "suspects in this scene" in fast and "substeps =" in fast and "stiffer springs" not in fast


def test_the_runners_remedies_complete_the_run_with_the_balance_closed(tmp_path):
    """The CLI's stop (``run_scene``): the test scene's 5 × 5 cloth on the ground with 4 kN/m structural springs at
    one substep is stopped, and the text names its suspects (the step against its springs, the ground's contacts;
    no wind, no handle, nothing generic) and remedies: the guard's ``substeps = N`` and the runner's own
    ``--substeps M``. Each, tried as printed, runs the scene's 5 frames to the end with the balance closed (the
    energy created at the end within the guard's 10 % of its budget)."""
    from helpers import write_scene
    from warpspring.app.runner import run_scene
    from warpspring.io.scene import load_scene

    path = write_scene(tmp_path, {"substeps = 4": "substeps = 1", "structural = { ke = 40.0, kd = 0.01 }":
                                  "structural = { ke = 4000.0, kd = 0.01 }", "frames = 5": "frames = 20"})
    with pytest.raises(ws.SimulationError) as stop:
        run_scene(load_scene(str(path)), output=str(tmp_path / "stopped.usdc"), progress=False, watch=0)
    message = str(stop.value)
    assert "suspects in this scene" in message and "contacts with 1 collider" in message
    assert "wind" not in message and "handle" not in message and "external force" not in message
    assert "look at contacts, external forces or extreme parameters" not in message
    remedies = {int(n) for n in re.findall(r"substeps = (\d+)", message) + re.findall(r"--substeps (\d+)", message)}
    assert len(remedies) >= 2 and min(remedies) > 1
    for substeps in sorted(remedies):
        summary = run_scene(load_scene(str(path)), output=str(tmp_path / f"remedy_{substeps}.usdc"),
                            progress=False, watch=0, substeps=substeps)
        assert summary.frames == 20
        assert summary.balance_created is not None and summary.balance_created <= 0.1
        assert "energy balance counts" in summary.line()
    if "implicit_euler" in message:  # the advisor's other remedy: an unconditionally stable integrator, whose
        # run completes; its balance is off by design (its steps' energy error is no instability), and says so
        scene = load_scene(str(path))
        scene.integrator = "implicit_euler"
        summary = run_scene(scene, output=str(tmp_path / "implicit.usdc"), progress=False, watch=0)
        assert summary.frames == 20 and summary.balance_created is None
        assert "energy balance off (implicit_euler is unconditionally stable" in summary.line()


def test_dampers_past_their_limit_are_named_and_their_remedy_works(device):
    """A cloth whose springs are well within symplectic Euler's stiffness limit (ω_max h ≤ 0.76 against 2) but whose
    dampers are not (kd = 10 N·s/m on 20 g particles: their rate bound λ_D h ≈ 8 against 1) is stopped, the message
    names the dampers' rate beside the stiffness, and the remedy's substeps, tried, run the 0.5 s to the end with the
    balance closed."""
    def damped():
        builder = ws.ModelBuilder()
        spring = ws.SpringMaterial(ke=1.0e3, kd=10.0)
        builder.add_cloth_grid(nx=8, ny=8, spacing=0.05, particle_mass=0.02, structural=spring, shear=spring,
                               bend=spring, pin=["top-left", "top-right"])
        return builder.finalize(device)

    message = stopped_message(damped(), 24)
    stiffness = float(re.search(r"ω_max h ≤ ([0-9.]+) against symplectic_euler's limit 2.00", message).group(1))
    rate = float(re.search(r"dampers' rate λ_D h ≤ ([0-9.]+) against 1", message).group(1))
    assert stiffness < 2.0 < rate  # the dampers, not the stiffness, are past their limit, and the message says so
    substeps = int(re.search(r"substeps = (\d+)", message).group(1))
    assert substeps >= 24 * rate  # their rate brought to 1/h
    model = damped()
    sim = ws.Simulator(model, integrator=ws.make_integrator("symplectic_euler", model), fps=60, substeps=substeps)
    run_frames(sim, FRAMES)
    balance = sim.guard.energy_balance()
    assert np.all(np.isfinite(sim.state.particle_q.numpy()))
    assert balance.created[0] <= 0.1 * balance.peak[0]


def pins_through_free_cloth(device, *, travel: float) -> ws.Model:
    """A free 5 × 5 cloth moving up at 1 m/s under a pinned one 12 mm above it (τ = 4 mm, no gravity), the pinned
    cloth driven down by ``travel`` [m] over the first millisecond and then held."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    cloth = dict(structural=ws.SpringMaterial(300.0, 0.05), shear=ws.SpringMaterial(300.0, 0.05))
    builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05, velocity=(0.0, 0.0, 1.0),
                           **cloth)
    pinned = builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.005, 0.005, 0.012), mass=0.05, **cloth)
    builder.add_pin_group(pinned.ravel(), translation=ws.Track([0.0, 1e-3], [[0, 0, 0], [0, 0, -travel]]))
    builder.add_self_collision(thickness=0.004)
    return builder.finalize(device)


def test_a_pin_driven_through_cloth_that_cannot_give_way_stops_the_run(device, tmp_path):
    """The pinned cloth driven 13 mm down in one 1 ms step onto the free cloth rising toward it: the cap cannot hold
    the pair apart (``SelfContact.outrun``, counted in ``test_torture``), the surface may cross, and the default
    guard stops the run at that frame with a message naming the cause and the remedies; no frame was completed. The
    same scene with the pins driven 2 mm (the free cloth then has room: it is pushed back) runs on: the stop is
    the outrun's, not self-collision's or the pins'."""
    sim = ws.Simulator(pins_through_free_cloth(device, travel=0.013), fps=1000, substeps=1)
    sim.step_frame()  # the frame's self-collision review is read at the next frame or a read of the state
    with pytest.raises(ws.SimulationError) as stop:
        sim.settle()
    message = str(stop.value)
    assert message.startswith("frame 1: a pinned part of the surface closed in on free cloth")
    assert "beyond the self-collision cap" in message and "τ = 4 mm" in message
    assert "slow the tracks, lower the self-collision thickness" in message
    assert sim.frame == 0 and stop.value.frame == 1
    at_once = ws.Simulator(pins_through_free_cloth(device, travel=0.013), fps=1000, substeps=1, defer_verdict=False)
    with pytest.raises(ws.SimulationError, match="^frame 1: a pinned part of the surface"):
        at_once.step_frame()  # without deferred verdicts, the frame's own step stops
    assert at_once.frame == 0
    restored = ws.Simulator(pins_through_free_cloth(device, travel=0.013), fps=1000, substeps=1)
    saved = restored.save_checkpoint(tmp_path / "start.npz")
    restored.step_frame()  # the frame that outruns the cap, its review posted ...
    restored.load_checkpoint(saved)  # ... and left behind with the run: no stop for it
    assert restored.frame == 0
    unguarded = ws.Simulator(pins_through_free_cloth(device, travel=0.013), fps=1000, substeps=1, guard=None)
    unguarded.step_frame()  # no stop without a guard; the frame's review, posted, is read by the next review
    assert unguarded.model.self_contact.review()[0] > 0
    gentle = ws.Simulator(pins_through_free_cloth(device, travel=0.002), fps=1000, substeps=1)
    run_frames(gentle, 5)
    assert gentle.frame == 5 and gentle.model.self_contact.outrun()[0] == 0


def test_a_voxel_body_torn_at_twice_its_limit_names_the_spring(device):
    """examples/soft_ball.toml at twice the advisor's limit (the guard's battery's case): stopped for strain, the
    message naming the spring and its particles. On an H200 the record's search for the most strained element once
    found none (the check's passes and the search round the strain differently there), and the stop's message raised
    StopIteration instead."""
    import pathlib

    from warpspring.analysis.guard_battery import run_case

    ball = pathlib.Path(__file__).resolve().parents[1] / "examples" / "soft_ball.toml"
    # (the simulator alone, without the watch ``warpspring run`` attaches: its frames not read one by one, the
    # default guard's check spans frames and the state reaches a tear before the check sees the balance)
    outcome = run_case(ball, "as is", "symplectic_euler", "twice", device=device, frames=60, watch=False)
    assert outcome.passed and outcome.reason == "strain", outcome.row() + "\n" + outcome.message
    assert re.search(r"spring \d+ \(particles \d+-\d+\) stretched to [0-9.e+]+× its rest length", outcome.message), \
        outcome.message


def test_a_strain_record_without_its_element_is_still_told(device):
    """A strain report whose element the record does not hold reads as a sentence, not a traceback."""
    model = stiff_cloth(device)
    from warpspring.core.guard_records import GuardReport

    report = GuardReport(world=0, reason="strain", substep=3, particle=None, spring=None, strain=11.5,
                            kinetic_energy=1.0)
    assert report.describe(model) == ("an element stretched to 12.5× its rest length (guard limit exceeded; the "
                                      "element was not identified)")


def test_the_runners_watch_stops_a_step_past_its_limit_where_the_balance_is_off(tmp_path):
    """The CLI (``run_scene``) on the test scene with 400 N/m springs at one substep (3.2 times the step's limit) and
    a sphere that slides far below the cloth (a moving collider: the guard's balance off): its stability watch,
    re-checking after every frame, stops the run at frame 1, the file keeping frame 0, and the message names the
    ratio, why the balance is off, the scene's suspects and remedies; each numbered remedy, tried as printed, runs
    the scene's 20 frames to the end."""
    from helpers import write_scene
    from warpspring.app.runner import run_scene
    from warpspring.io.scene import load_scene

    sphere = """
[[collider]]
type = "sphere"
center = [0.2, 0.0, -3.0]
radius = 0.3
translation = { times = [0.0, 2.0], values = [[0, 0, 0], [0.5, 0, 0]] }
"""
    path = write_scene(tmp_path, {"[simulation]": "version = 2\n[simulation]", "substeps = 4": "substeps = 1",
                                  "structural = { ke = 40.0, kd = 0.01 }": "structural = { ke = 400.0, kd = 0.01 }",
                                  "frames = 5": "frames = 20"}, extra=sphere)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ws.StabilityWarning)
        with pytest.raises(ws.SimulationError) as stop:
            run_scene(load_scene(str(path)), output=str(tmp_path / "stopped.usdc"), device="cpu", progress=False,
                      watch=1)
    message = str(stop.value)
    assert stop.value.frame == 1 and message.endswith("stopped.usdc holds frames 0..0")
    assert re.match(r"frame 1: the state is past the stability limit of symplectic_euler: ω_max ≈ [0-9.]+ rad/s is "
                    r"3\.\d\d× the", message), message
    assert "energy balance off in this scene (the work of moving colliders is not counted)" in message
    assert "the springs at particle" in message and "contacts with 2 colliders" in message
    remedies = {int(n) for n in re.findall(r"substeps = (\d+)", message) + re.findall(r"--substeps (\d+)", message)
                + re.findall(r"at least (\d+) substeps", message)}
    assert len(remedies) >= 2 and min(remedies) > 1
    for substeps in sorted(remedies):
        summary = run_scene(load_scene(str(path)), output=str(tmp_path / f"remedy_{substeps}.usdc"), device="cpu",
                            progress=False, watch=1, substeps=substeps)
        assert summary.frames == 20


@pytest.mark.parametrize("integrator, substeps", [("explicit_euler", 200), ("midpoint", 40)])
def test_a_spring_made_stiffer_under_a_damping_limited_integrator_is_watched(device, integrator, substeps):
    """Explicit Euler and midpoint, whose limit is their damping's: an 8 × 8 damped cloth (1 kN/m, kd = 1 N·s/m,
    10 g particles) is certified by the springs' bound at 200 and 40 substeps (an undamped mode at it grows < 10× a
    frame), so its frames are checked once each; one spring made 100 times stiffer through the model (ω h ×10: an
    undamped mode there grows ~1.07× (explicit Euler) or ~2× (midpoint) a step) has the next frames checked after
    every substep, and the run is stopped for an instability, not as a non-finite state. Checked once a frame, the
    battery's cloths under both integrators overflowed within the frame after such a write."""
    builder = ws.ModelBuilder()
    spring = ws.SpringMaterial(ke=1.0e3, kd=1.0)
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.1, particle_mass=0.01, structural=spring, shear=spring, pin=["top"])
    model = builder.finalize(device)
    sim = ws.Simulator(model, integrator=ws.make_integrator(integrator, model), fps=60, substeps=substeps)
    run_frames(sim, 2)
    assert not sim.guard._watching
    stiffness = model.world_values("spring_stiffness").copy()
    stiffness[:, 0] *= 100.0
    model.set_world_values("spring_stiffness", stiffness)
    with pytest.raises(ws.SimulationError) as stop:
        for _ in range(3):
            sim.step_frame()
            assert sim.guard._watching
        sim.settle()
    assert stop.value.reason != "non-finite state", str(stop.value)
