"""A guard stop names what the scene holds that can drive it unstable (the step against its stiffest springs, its
contacts and loads, and nothing it does not hold) and a remedy that, tried as printed, completes the run with the
balance closed."""

import re

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


def test_the_advice_of_a_strain_stop_is_left_to_the_advisor(device):
    """A tear is over-stretch or instability, which the advisor tells apart (``analysis.advisor.diagnose``): the
    guard's own advice is empty for it."""
    from warpspring.core.guard_records import GuardReport, stop_advice

    model = stiff_cloth(device)
    report = GuardReport(world=0, reason="strain", substep=0, particle=0, spring=0, strain=11.0, kinetic_energy=0.0,
                         family="springs", element=0)
    assert stop_advice(report, model, integrator="symplectic_euler", substeps=1, dt=1.0 / 60.0) == ""
