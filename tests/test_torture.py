"""The self-collision torture battery (``warpspring/analysis/torture.py``) at small sizes, every substep audited
(``SubstepAudit``: continuous crossings, intersections, pairs closer than τ/2), and the cause of the twisted
strip's crossings pinned down on its own.

The twist's cause: the strip coils until a fold closes on itself between two parallel diagonals of neighbouring
quads, whose distance the cap lets shrink geometrically (each free vertex moves at most γD per step). Below
the float32 positions' resolution (D ~ 1e-8 m against coordinates of ~0.1-1 m, whose ulp is 4e-9 to 6e-8 m)
the capped position start + (γD/|Δ|) Δ rounds to a neighbouring float that lies further than γD from the start,
and D itself carries that much rounding: the cap's proof (exact arithmetic) no longer holds, and the pair
crossed (the full-size 720° twist, symplectic Euler: the first crossing at t = 2.46 s between four free
vertices 1.2e-8 m apart). The cap now takes a rounding pad off every bound and holds a vertex whose capped
position rounds past its bound where it started.
"""

import numpy as np
import pytest

import warpspring as ws
from warpspring.analysis.audit import SurfaceAudit, edge_edge_distance
from warpspring.analysis.torture import run_case
from warpspring.core.selfcontact import DEFAULT_RELAXATION

# Two triangles of the full-size twist at the substep before its first crossing (float32 positions as the run
# held them): the edges 0-2 and 3-5 are two diagonals of neighbouring quads folded onto each other, 1.18e-8 m apart.
FOLD = np.array([[0.2757205069065094, 0.050551995635032654, 0.8905785083770752],
                 [0.27755334973335266, 0.05304402858018875, 0.9050154685974121],
                 [0.2917456030845642, 0.04737451672554016, 0.9047380685806274],
                 [0.2867369055747986, 0.04014785960316658, 0.8931915163993835],
                 [0.28129470348358154, 0.05159085616469383, 0.8870314955711365],
                 [0.281884104013443, 0.057592060416936874, 0.9031822085380554]], np.float32)
FOLD_TRIANGLES = np.array([[0, 1, 2], [3, 4, 5]])


def test_cap_holds_below_the_precision(device):
    """The fold's two edges driven into each other at 1 m/s for 40 steps of 1/1200 s (each step's velocity
    re-imposed: a steady squeeze): no step moves a vertex of the pair further than γ times the pair's float64
    distance at the step's start (the cap's bound, which a rounded position used to overstep by a float32 ulp:
    3.7e-9 m against a bound of 2.9e-9 m), and no pair touches during any step (continuous audit)."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles(FOLD, mass=0.001, radius=0.001)
    builder.add_triangles(FOLD_TRIANGLES)
    builder.add_self_collision(thickness=0.002)
    model = builder.finalize(device)
    normal = np.cross(FOLD[2] - FOLD[0], FOLD[5] - FOLD[3])
    normal /= np.linalg.norm(normal)
    squeeze = np.zeros((6, 3), np.float32)
    squeeze[:3], squeeze[3:] = -normal, normal  # edge 0-2 toward edge 3-5 and back: 1 m/s each
    audit = SurfaceAudit(FOLD_TRIANGLES)
    integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
    for _ in range(40):
        a.particle_qd.assign(squeeze)
        integrator.step(a, b, None, 1.0 / 1200.0)
        x0, x1 = a.particle_q.numpy().astype(np.float64), b.particle_q.numpy().astype(np.float64)
        gap = edge_edge_distance(*x0[[0, 2, 3, 5]])
        moved = np.linalg.norm(x1 - x0, axis=1)[[0, 2, 3, 5]]
        assert moved.max() <= DEFAULT_RELAXATION * gap
        assert len(audit.motion(x0, x1).touches) == 0
        a, b = b, a


# The suite's battery at the small size (0.03 m spacing, τ = 5 mm), each scene at a share of its time scale
# (0.4: the twist turns in 1 s, the ring's pull takes 0.8 s, faster than at full size, so harder; the crumple and
# the turntable need their whole time to fold onto themselves), every scene under symplectic Euler and the twist
# under RK4 and implicit Euler too; bench/torture.py runs every pair at full size. Frames: None runs the scene.
KINEMATIC = pytest.mark.xfail(strict=True, reason=(
    "a pinned edge moves further in a substep than its distance to the free cloth (K >= D: beyond the cap, "
    "kernels/selfcontact.py); measured: twist1440 first crosses at t = 0.426 s, twist720 under implicit Euler at "
    "t = 0.937 s, each between a pinned and a free edge"))
SWEPT = pytest.mark.xfail(strict=True, reason=(
    "one crossing at t = 0.614 s (minimum distance 2e-6 m) under the CPU's symplectic Euler sweep, which sums each "
    "particle's springs in another order than the per-particle step (which audits 0 here); not yet diagnosed"))
BATTERY = [
    pytest.param("twist720", "symplectic_euler", 0.4, None, id="twist720-symplectic_euler", marks=SWEPT),
    pytest.param("twist720", "rk4", 0.4, None, id="twist720-rk4"),
    pytest.param("twist720", "implicit_euler", 0.4, 60, id="twist720-implicit_euler", marks=KINEMATIC),
    pytest.param("twist1440", "symplectic_euler", 0.4, 30, id="twist1440-symplectic_euler", marks=KINEMATIC),
    pytest.param("ring", "symplectic_euler", 0.4, None, id="ring-symplectic_euler"),
    pytest.param("stack", "symplectic_euler", 0.4, None, id="stack-symplectic_euler"),
    pytest.param("crumple", "symplectic_euler", 1.0, None, id="crumple-symplectic_euler"),
    pytest.param("turntable", "symplectic_euler", 0.6, None, id="turntable-symplectic_euler"),
]


@pytest.mark.slow
@pytest.mark.parametrize("scene, integrator, duration, frames", BATTERY)
def test_battery_never_crosses(scene, integrator, duration, frames):
    """A scene of the battery under an integrator (CPU, small size): no crossing during any substep and no
    intersection at any substep's end (float64 continuous audit), no pair list overflowed, no guard stop; and the
    surface did press on itself (pairs were pushed apart)."""
    result = run_case(scene, integrator, size="small", device="cpu", duration=duration, frames=frames)
    assert result.error is None
    assert result.audit.substeps == result.frames * result.substeps > 0
    assert result.audit.crossings == 0 and result.audit.intersections == 0, result.audit.line()
    assert result.overflow == 0
    assert result.pairs > 0


def test_overflow_is_said_and_still_does_not_cross():
    """The stack with its pair lists cut to 8 slots (far fewer than the landing cloths' pairs): the lists
    overflow, the audit's line says how many pairs were dropped, and no substep crosses or intersects (a world
    whose cap list overflowed keeps its free vertices where the step started)."""
    from warpspring.analysis.audit import SubstepAudit
    from warpspring.analysis.torture import build_case

    model, _ = build_case("stack", size="small", device="cpu")
    model.self_contact._allocate(8)
    sim = ws.Simulator(model, fps=60, substeps=20)
    audit = SubstepAudit().attach(sim)
    for _ in range(20):
        sim.step_frame()
    assert audit.overflow > 0 and f"{audit.overflow} self-collision pairs dropped" in audit.line()
    assert audit.crossings == 0 and audit.intersections == 0
