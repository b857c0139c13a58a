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

The small twist's crossing under the CPU's symplectic Euler sweep (which sums each particle's springs in another
order than the per-particle step, so that the run follows another path) was not a rounding case: it was the
kinematic one. Its one crossing (substep 18 of the 60th frame, t = 0.998 s) was between the turned, pinned edge
104-125, which moves 0.356 mm in the substep, and the free edge 123-124 beside it, 0.115 mm away at the substep's
start (K >= D); the cap, which bounded free vertices' displacements only, held 123 and 124 at their start (jammed
between the pin and a vertex 0.33 mm behind them) and the pin ran through them. The cap now bounds each side's
approach along the pair's separating direction, takes a pin's approach off the free side's share (a negative share:
the free side must give way, along the step the repulsion gave it), and places a vertex that cannot give way so
again where its neighbours leave room (``kernels/selfcontact.py``, the cap); the pairs it still cannot hold apart
are counted (``SelfContact.outrun()``).
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
    assert model.self_contact.outrun()[0] == 0  # no kinematic vertex: no pair beyond the cap


# Thirteen vertices of the small 720° twist under symplectic Euler (the CPU's sweep) at the substep of its crossing
# (ending at t = 0.9983 s): their float32 positions at the substep's start and where the integrator put them (before the
# self-collision pass). Vertices 1, 5, 9 and 12 belong to the turned, pinned edge; the pinned edge 5-9 moves
# 0.356 mm (vertex 5) in the substep while it is 0.115 mm from the free edge 7-8 (K >= D).
PIN_START = np.array([[0.42078709602355957, -0.05107592046260834, 1.017996907234192],
                      [0.40049999952316284, -0.059970393776893616, 1.0018846988677979],
                      [0.3604561388492584, -0.016450107097625732, 1.0127071142196655],
                      [0.39043647050857544, -0.02927558310329914, 1.0041227340698242],
                      [0.4137327969074249, -0.02177150920033455, 1.026587963104248],
                      [0.40049999952316284, -0.029985196888446808, 1.000942349433899],
                      [0.38383808732032776, 0.006440571043640375, 1.0127016305923462],
                      [0.4007644057273865, -0.004865719936788082, 0.99404376745224],
                      [0.3988684117794037, 0.007346036843955517, 1.0241520404815674],
                      [0.40049999952316284, 4.980254943170744e-21, 1.0],
                      [0.3947053551673889, 0.022860651835799217, 0.980657696723938],
                      [0.38202792406082153, 0.03110901452600956, 1.00885009765625],
                      [0.40049999952316284, 0.029985196888446808, 0.9990576505661011]], np.float32)
PIN_END = np.array([[0.4208385944366455, -0.051199864596128464, 1.0174322128295898],
                    [0.40033334493637085, -0.059986840933561325, 1.0012565851211548],
                    [0.3600389361381531, -0.016362536698579788, 1.0114816427230835],
                    [0.39006370306015015, -0.029046833515167236, 1.0041780471801758],
                    [0.4132039546966553, -0.022191962227225304, 1.0260456800460815],
                    [0.40033334493637085, -0.029993420466780663, 1.0006282329559326],
                    [0.38372260332107544, 0.006590315140783787, 1.013662338256836],
                    [0.4022946059703827, -0.004235601052641869, 0.9945881366729736],
                    [0.3986777663230896, 0.006720912177115679, 1.0247043371200562],
                    [0.40033334493637085, 2.2135478399921897e-21, 1.0],
                    [0.3943417966365814, 0.02385111153125763, 0.9811563491821289],
                    [0.3795190453529358, 0.030062543228268623, 1.0107945203781128],
                    [0.40033334493637085, 0.029993420466780663, 0.9993717074394226]], np.float32)
PIN_PINNED = [1, 5, 9, 12]
PIN_TRIANGLES = np.array([[0, 1, 5], [2, 3, 7], [3, 4, 8], [4, 5, 9], [6, 7, 10], [7, 8, 11], [8, 9, 12], [0, 5, 4],
                          [2, 7, 6], [3, 8, 7], [4, 9, 8], [7, 11, 10], [8, 12, 11]])


def pinned_edge_step(device):
    """One substep of 1/1200 s in which every vertex moves from PIN_START toward PIN_END (velocities (end -
    start)/h, no force: symplectic Euler lands on the run's integrator result), then the self-collision pass.
    Returns (model, x0, x1), the positions in float64."""
    h = 1.0 / 1200.0
    x0 = PIN_START.astype(np.float64)
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles(PIN_START, velocities=(PIN_END.astype(np.float64) - x0) / h, mass=1.0 / 1283.3334,
                          radius=0.001, pinned=PIN_PINNED)
    builder.add_triangles(PIN_TRIANGLES)
    builder.add_self_collision(thickness=0.005, friction=0.2)
    model = builder.finalize(device)
    a, b = model.state(), model.state()
    ws.SymplecticEuler(model).step(a, b, None, h)
    x1 = b.particle_q.numpy().astype(np.float64)
    # The pins land where the run put them, to the float32 rounding of x + v h (an ulp of the coordinates, 1.2e-7 m).
    np.testing.assert_allclose(x1[PIN_PINNED], PIN_END[PIN_PINNED], rtol=0.0, atol=1.2e-7)
    return model, x0, x1


def test_pinned_edge_outrunning_its_gap_does_not_cross(device):
    """The twist's crossing cut out of the run (``pinned_edge_step``): the pinned edge 5-9 moves further (K) than its
    distance D to the free edge 7-8. The cap bounds each side's approach along the pair's separating direction and
    takes the pin's approach off the free side's share, so the free edge gives way along its repelled step instead
    of being held where the pin runs into it: no pair touches during the substep (float64 continuous audit), and no
    pair is left beyond the cap. (Before, the cap held the free edge at its start and the pinned edge crossed it.)"""
    x0 = PIN_START.astype(np.float64)
    gap = edge_edge_distance(*x0[[5, 9, 7, 8]])
    reach = np.linalg.norm(PIN_END.astype(np.float64)[[5, 9]] - x0[[5, 9]], axis=1).max()
    assert reach > 3.0 * gap  # the case: K = 0.356 mm against D = 0.115 mm
    model, x0, x1 = pinned_edge_step(device)
    assert len(SurfaceAudit(PIN_TRIANGLES).motion(x0, x1).touches) == 0
    assert model.self_contact.outrun()[0] == 0
    assert np.linalg.norm(x1[[7, 8]] - x0[[7, 8]], axis=1).min() > reach  # it gave way, further than the pin moved


def test_a_pin_outrunning_a_vertex_that_cannot_give_way_is_counted(device):
    """A pinned cloth moved 13 mm in one step toward a free cloth 12 mm below it, beyond the repulsion's reach, whose
    integrator moves it up toward the pins: the cap only shortens a free vertex's step, so the free cloth cannot
    give way and the pins pass through it. The pass counts the pairs it could not hold apart
    (``SelfContact.outrun()``), and the continuous audit sees the crossing that the count announces."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    cloth = dict(structural=ws.SpringMaterial(300.0, 0.05), shear=ws.SpringMaterial(300.0, 0.05))
    builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05, velocity=(0.0, 0.0, 1.0),
                           **cloth)
    pinned = builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.005, 0.005, 0.012), mass=0.05, **cloth)
    builder.add_pin_group(pinned.ravel(), translation=ws.Track([0.0, 1e-3], [[0, 0, 0], [0, 0, -0.013]]))
    builder.add_self_collision(thickness=0.004)
    model = builder.finalize(device)
    a, b = model.state(), model.state()
    ws.SymplecticEuler(model).step(a, b, None, 1e-3)
    x0, x1 = a.particle_q.numpy().astype(np.float64), b.particle_q.numpy().astype(np.float64)
    np.testing.assert_allclose(x1[25:, 2], 0.012 - 0.013, atol=1e-6)  # the pins went where they were told
    assert len(SurfaceAudit(model.tri_indices.numpy()).motion(x0, x1).touches) > 0
    assert model.self_contact.outrun()[0] > 0


# The suite's battery at the small size (0.03 m spacing, τ = 5 mm), each scene at a share of its time scale
# (0.4: the twist turns in 1 s, the ring's pull takes 0.8 s, faster than at full size, so harder; the crumple and
# the turntable need their whole time to fold onto themselves), every scene under symplectic Euler and the twist
# under RK4 and implicit Euler too; bench/torture.py runs every pair at full size. Frames: None runs the scene.
# Beyond the cap (a strict xfail: the pass counts these pairs, ``SelfContact.outrun()``): free cloth layered between
# a turning pinned edge and more cloth, closer than the pin moves in a substep, where the cap's passes cannot make
# room through the layers (each moves a free vertex at most ρ = γτ = 1.25 mm and takes only the room its neighbours
# leave). Measured: twist720 under implicit Euler, t = 0.998 s: the pinned edge 125-146 closes in 0.31 mm a substep
# on the free edge 123-144 (0.21, 0.15, 0.12, 0.046 mm over four substeps), 18-20 vertices jammed around it;
# twist1440 under symplectic Euler, from t = 0.497 s: pins moving up to 3.1 mm a substep (4 turns/s at 0.15 m)
# against cloth within 0.05-2.5 mm, and pairs whose both sides hold pins (the first row of cloth wrapped back onto
# the turning edge, its pinned ends closing in by 1.2 mm along n on a 0.93 mm gap).
LAYERED = pytest.mark.xfail(strict=True, reason=(
    "a pinned edge closes in on free cloth layered against more cloth faster than the cap's passes can make room "
    "(kernels/selfcontact.py: beyond the cap, counted by SelfContact.outrun())"))
BATTERY = [
    pytest.param("twist720", "symplectic_euler", 0.4, None, id="twist720-symplectic_euler"),
    pytest.param("twist720", "rk4", 0.4, None, id="twist720-rk4"),
    pytest.param("twist720", "implicit_euler", 0.4, 60, id="twist720-implicit_euler", marks=LAYERED),
    pytest.param("twist1440", "symplectic_euler", 0.4, 30, id="twist1440-symplectic_euler", marks=LAYERED),
    pytest.param("ring", "symplectic_euler", 0.4, None, id="ring-symplectic_euler"),
    pytest.param("stack", "symplectic_euler", 0.4, None, id="stack-symplectic_euler"),
    pytest.param("crumple", "symplectic_euler", 1.0, None, id="crumple-symplectic_euler"),
    pytest.param("turntable", "symplectic_euler", 0.6, None, id="turntable-symplectic_euler"),
]


@pytest.mark.slow
@pytest.mark.parametrize("scene, integrator, duration, frames", BATTERY)
def test_battery_never_crosses(scene, integrator, duration, frames):
    """A scene of the battery under an integrator (CPU, small size): no crossing during any substep and no
    intersection at any substep's end (float64 continuous audit), no pair list overflowed, no pair beyond the cap
    (a pin outrunning its distance), no guard stop; and the surface did press on itself (pairs were pushed apart)."""
    result = run_case(scene, integrator, size="small", device="cpu", duration=duration, frames=frames)
    assert result.error is None
    assert result.audit.substeps == result.frames * result.substeps > 0
    assert result.audit.crossings == 0 and result.audit.intersections == 0, result.audit.line()
    assert result.overflow == 0
    assert result.outrun == 0  # no pair the cap could not hold apart
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
