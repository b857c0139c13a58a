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

What still crossed (twist720 under implicit Euler, twist1440 under every integrator) was the pins' travel a step:
the turned edge moved up to 3.1 mm a substep at 20 substeps against the γ τ = 1.25 mm a substep the cap's later
passes may move a free vertex to give way (free layers jammed between the pin and more cloth). Each scene now takes
the substeps that keep its driven pins within a quarter of that reach (``step_choice.pin_substeps``, which
``substeps = "auto"`` also applies); the battery's scenes under the three integrators run in ``bench/torture.py``
(``bench/results/torture_cpu*.md``), and the suite keeps the twist1440 case.

What then still came closer than τ/2, without crossing (the ring under every integrator, the stack under RK4, the
twists), was the cap's own bound: a kept pair could close by γ G a side a step, to (1 - 2γ) of its gap, and where the
repulsion could not part it (a vertex pressed from both sides, whose pairs' corrections cancel in the Jacobi mean;
the stack's vertex held between the box and a triangle stretched over its edge) the steps compounded: the ring's
folds came to 7 µm. The ring's first such pair (t = 0.94 s, symplectic Euler) was two diagonals of neighbouring
quads 2.7 mm apart, which the integrator closed to 1.8 mm and the repulsion parted to 2.7 mm, after which the cap
held one of its vertices at its start: a capped position start + (bound/|Δ|) Δ that rounded past its bound was held
there, which happened to half the capped vertices (the rounding goes either way) and threw their repulsion away.
The cap now bounds a pair's approach by its gap less τ/2 (``CAP_FLOOR``: a pair τ/2 apart comes no closer, a closer
one may part but not close in), and pulls a position rounded past its bound back by the rounding pad.

What then still came closer than τ/2, without crossing (the full-size 1440° twist under implicit Euler: 2.490 mm
from t = 3.109 s), was the rounding of a capped end against a pair on that floor. The coil's pairs sit there for
thousands of substeps (implicit Euler's step drives the layers together by up to 0.6 mm a substep, the cap holds
them): a pair within the rounding pads of τ/2 has no room (G' = 0, shares 0), so the cap lets its vertices part, not
close in; but a vertex capped to a short step by another pair, start + s Δ̂ with s Δ̂ of some 35 nm, keeps that step
only in its small coordinates (y = -0.006 m, ulp 4.7e-10 m) and drops it in its large ones (0.39 and 0.99 m, ulp 3e-8
and 6e-8 m): the end as stored moved 19 nm along +y where Δ̂ retreated from the pair, 12 nm toward it along n. The pair
(edges 771-813 and 812-854, two diagonals of the squeezed strip's last rows) lost 7.75 nm each time, 0.2 µm a frame.
The cap now checks a capped end, as stored, against the pairs that leave its vertex no approach and holds it at its
start where it closes one in (and the later passes check their bounds on the stored end).

What then still came closer than τ/2 (the small 720° twist at its full duration under symplectic Euler: 823 pairs,
1.134 mm, from t = 2.417 s) was the cap's later passes: the pinned edge 125-146 closed on the free edge 144-165 by
85 µm more a substep than its room while 144 and 165 lay on the floor over the layers behind them, which had room
to move away but moved at most 2 µm in the later passes (144 and 165 stayed). A jammed vertex's point "where it wanted to go" was the alternating projections' compromise between
the pin's bound and its bounds against those layers as they stood, which asked them for no room. That point now keeps
only the bounds against what cannot make room (kinematic vertices, earlier pushers), so the layers behind move away
and the jammed vertex follows.

What then still came closer than τ/2 (the same twist at duration 0.98, or with its particles moved by up to 1 µm: 2.42
and 2.48 mm) was a squeeze passed through several free layers, a chain of pushers. A pusher placed in the same pass as
the pusher it had to make room for was placed against where that one stood, which it already kept: it stayed, lost its
role, and the two took turns at every level (a pin on four layers never moved the second). A pusher now counts as
where it wants to go for the pushers of its own pass too, and the cap runs 5 levels (room is made from the back, about
a layer every two levels; it ran 2).
"""

import numpy as np
import warp as wp

import warpspring as ws
from warpspring.analysis.audit import SurfaceAudit, edge_edge_distance, vertex_triangle_distance
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


def squeezed_sheets(device):
    """Three free 2 × 2-quad sheets (no springs, no gravity, τ = 4 mm) 8 mm apart, the middle one shifted in its
    plane (the outer two are to be driven toward it). Returns (model, triangles)."""
    grid = np.stack(np.meshgrid(np.arange(3) * 0.02, np.arange(3) * 0.02, indexing="xy"), -1).reshape(-1, 2)
    quads = [(r * 3 + c) for r in range(2) for c in range(2)]
    sheet = np.array([t for a in quads for t in ([a, a + 1, a + 4], [a, a + 4, a + 3])])
    x = np.concatenate([np.column_stack([grid + shift, np.full(9, z)])
                        for z, shift in ((0.008, 0.0), (0.0, (0.005, 0.007)), (-0.008, 0.0))]).astype(np.float32)
    triangles = np.concatenate([sheet, sheet + 9, sheet + 18])
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles(x, mass=0.001, radius=0.001)
    builder.add_triangles(triangles)
    builder.add_self_collision(thickness=0.004)
    return builder.finalize(device), triangles


def test_the_cap_keeps_a_pressed_pair_half_the_thickness_apart(device):
    """The three sheets pressed together at 3 m/s each (2.5 mm a step of 1/1200 s), the outer sheets' velocities
    re-imposed before every step (a steady press), 40 steps: the repulsion cannot part the layers (the middle sheet's
    vertices are pushed from both sides, and their pairs' corrections cancel in the Jacobi mean), so the cap holds
    them. No pair touches during any step (continuous audit) and none ends a step closer than τ/2 (the cap's floor:
    a kept pair approaches by at most γ times its distance less τ/2 a side), while the layers were pressed onto that
    floor (the closest pair within 0.6 τ). Before the floor the cap let a kept pair close to (1 - 2γ) of its gap a
    step, which the steady press compounded: 52 pairs closer than τ/2 at the first step that failed (1.7 mm), the
    closest 0.145 mm by the 40th; the cause of the battery's close pairs (ring, stack, twists)."""
    tau, speed = 0.004, 3.0
    model, triangles = squeezed_sheets(device)
    audit = SurfaceAudit(triangles)
    integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
    nearest = np.inf
    for _ in range(40):
        v = a.particle_qd.numpy()
        v[:9], v[18:] = (0.0, 0.0, -speed), (0.0, 0.0, speed)
        a.particle_qd.assign(v)
        integrator.step(a, b, None, 1.0 / 1200.0)
        step = audit.step(a.particle_q.numpy().astype(np.float64), b.particle_q.numpy().astype(np.float64),
                          thickness=tau)
        assert len(step.crossings) == 0 and len(step.intersections) == 0
        assert step.close == 0, f"{step.close} pairs closer than τ/2, the closest {step.min_distance:.3e} m"
        nearest = min(nearest, step.min_distance)
        a, b = b, a
    assert 0.5 * tau <= nearest < 0.6 * tau  # pressed onto the floor
    assert model.self_contact.counts()["pairs"][0] > 0 and model.self_contact.outrun()[0] == 0



def _repel_and_cap(model, stepped: np.ndarray):
    """The self-collision's repulsion and cap of one 1 ms step from the model's start to the integrator's result
    ``stepped`` [m]: the positions before and after (float64)."""
    start, state = model.state(), model.state()
    state.particle_q.assign(stepped)
    repelled = wp.array(stepped, dtype=wp.vec3, device=model.device)
    model.self_contact.repel(start, repelled)
    model.self_contact.cap(start, repelled, state, 1e-3)
    return start.particle_q.numpy().astype(np.float64), state.particle_q.numpy().astype(np.float64)


def test_a_rounded_end_does_not_close_a_pair_on_the_floor(device):
    """A vertex 1 µm above the floor from one triangle (T1, whose normal is the diagonal (1, 1, 0)/√2: the pair has
    no room, G' = 0, within the rounding pads of τ/2) steps away from it along (2, -1, 0)/√5, toward another triangle
    (T2, normal -x) whose room above the floor is 3e-8 m (τ chosen for that in the cap's float32 arithmetic): T2's
    plane caps the step to 3e-8 m along x. Its capped end start + s Δ̂ rounds coordinate by coordinate: x (1.5, ulp
    1.2e-7) keeps none of its 3e-8 m, y (0.003, ulp 2.3e-10) keeps its -1.5e-8 m, so the end as stored moves along
    -y, toward T1 by 2.6e-9 m, where the step itself retreats from it. The pair on the floor must not close in: the
    cap checks its rounded end against such pairs and holds the vertex at its start where it would. Before, the end
    closed the pair by 2.6e-9 m; a pair pressed onto the floor lost that each step (the full-size 1440° twist under
    implicit Euler, held by the cap for thousands of substeps: 2.490 mm, 10 µm inside τ/2, by t = 4 s)."""
    f32 = np.float32
    p = np.array([1.5, 0.003, 0.25])
    diagonal = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)  # T1's normal
    across, up = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0), np.array([0.0, 0.0, 1.0])  # in T1's plane
    plane = f32(1.502) + f32(5e-6)  # T2's x
    # The cap's gap of the pair (vertex, T2) in float32 (kernels/selfcontact_cap.py, pair_shares): its slab width less
    # two rounding pads; τ/2 (the floor) 3e-8 m below it.
    gap = (plane - f32(p[0])) - f32(2e-6) * (plane + f32(1.0))
    tau = 2.0 * (float(gap) - 3e-8)
    floor = 0.5 * tau
    closest = p - (floor + 1e-6) * diagonal
    t1 = [closest - 8e-3 * across, closest + 1.5e-3 * across + 7e-3 * up, closest + 1.5e-3 * across - 7e-3 * up]
    t2 = [(0.0, 0.011, 0.25), (0.0, -0.001, 0.257), (0.0, -0.001, 0.243)]
    x = np.array([p, p + (-3e-3, 9.5e-3, 0.0), p + (-3e-3, 4.5e-3, 8.5e-3), *t1, *t2], dtype=np.float32)
    x[6:, 0] = plane
    triangles = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_particles(x, mass=0.001, radius=0.001)
    builder.add_triangles(triangles)
    builder.add_self_collision(thickness=tau)
    model = builder.finalize(device)
    stepped = x.copy()
    stepped[0] += (50e-6 * np.array([2.0, -1.0, 0.0]) / np.sqrt(5.0)).astype(np.float32)
    before, after = _repel_and_cap(model, stepped)
    to_t1 = [vertex_triangle_distance(y[[0]], y[[3]], y[[4]], y[[5]])[0] for y in (before, after)]
    to_t2 = [vertex_triangle_distance(y[[0]], y[[6]], y[[7]], y[[8]])[0] for y in (before, after)]
    assert floor < to_t1[0] < floor + 2e-6 and floor < to_t2[0] < floor + 6e-6  # both pairs at the floor's pads
    assert model.self_contact.counts()["capped"][0] > 0  # the step was capped
    assert to_t1[1] >= to_t1[0], f"closed in by {to_t1[0] - to_t1[1]:.2e} m"
    assert to_t2[1] >= floor


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
    # It gave way: the pair parted while the pin moved on it (it gives way no further than its other pairs, below the
    # cap's floor at this fold, leave room: 0.26 mm for vertex 7, not the pin's whole 0.356 mm).
    assert edge_edge_distance(*x1[[5, 9, 7, 8]]) > gap


def _triangle(size: float, z: float) -> np.ndarray:
    """An equilateral triangle's corners [m], circumradius ``size``, in the plane at height ``z``."""
    angles = np.deg2rad([90.0, 210.0, 330.0])
    return np.column_stack([size * np.cos(angles), size * np.sin(angles), np.full(3, z)])


def _pinned_step_down(device, x: np.ndarray, tau: float, approach: float, *, held: tuple = ()):
    """Triangles of corners ``x`` (three rows each, the first triangle pinned, and those ``held`` names, standing),
    self-colliding at ``tau``: the first stepped ``approach`` [m] down, the others where they are, through the
    repulsion and the cap of one 1 ms step. Returns the self-collision, the triangles and the positions before and
    after (float64); asserts that the pinned triangle went where it was told."""
    triangles = np.arange(len(x)).reshape(-1, 3)
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    pinned = [0, 1, 2] + [3 * t + k for t in held for k in range(3)]
    builder.add_particles(x.astype(np.float32), mass=0.001, radius=0.001, pinned=pinned)
    builder.add_triangles(triangles)
    builder.add_self_collision(thickness=tau)
    model = builder.finalize(device)
    stepped = x.astype(np.float32)
    stepped[:3, 2] -= approach  # the pin's prescribed step
    x0, x1 = _repel_and_cap(model, stepped)
    np.testing.assert_array_equal(x1[:3], stepped[:3])
    return model.self_contact, triangles, x0, x1


def test_a_pin_squeezing_a_layer_on_the_floor_makes_the_layer_behind_give_way(device):
    """Three parallel triangles, τ = 4 mm (floor 2 mm): a pinned one (P) 50 µm above the floor over a small free one
    (M), which lies 5 µm above the floor over a large free one (L) with nothing behind it. The cap stage alone on a
    step that drives P 0.1 mm down and leaves M and L where they are (M's step toward L as the repulsion gives it
    would be capped anyway): M's pairs with P ask it to give way by 0.1 mm less P's room, (1 - γ) 50 µm, but its
    pairs with L, on the floor, leave it no approach: it is jammed, and L must make room. L can: it moves down as far
    as M needs, M follows, and no pair ends closer than τ/2. Before, M's point "where it wanted to go" was the
    compromise of the alternating projections onto all its bounds, L's as they stood included, so L was asked for no
    room, stayed, M stayed and P closed the pair to 1.95 mm (the small 720° twist under symplectic Euler at its full
    duration: 823 pairs closer than τ/2 from t = 2.417 s, the pinned edge 125-146 closing on the free edge 144-165 on
    layers at the floor, which moved at most 2 µm where 85 µm of room was needed)."""
    tau, approach = 0.004, 1e-4
    floor = 0.5 * tau

    x = np.concatenate([_triangle(0.04, floor + 5e-5), _triangle(0.006, 0.0), _triangle(0.04, -floor - 5e-6)])
    self_contact, triangles, x0, x1 = _pinned_step_down(device, x, tau, approach)
    step = SurfaceAudit(triangles).step(x0, x1, thickness=tau)
    assert len(step.crossings) == 0 and len(step.intersections) == 0
    assert step.close == 0, f"{step.close} pairs closer than τ/2, the closest {step.min_distance:.4e} m"
    # M gave way by what P's room lacked, and L made room for it: both moved down, by at least 0.1 mm less the rooms.
    room = (1.0 - DEFAULT_RELAXATION) * 5e-5
    assert np.all(x0[3:, 2] - x1[3:, 2] >= approach - room - 1e-7)
    assert np.all(x0[6:, 2] - x1[6:, 2] >= approach - room - 5e-6 - 1e-7)
    assert self_contact.outrun()[0] == 0


def test_a_pin_pressing_a_layer_held_by_a_pin_is_counted_as_squeezed(device):
    """The squeeze of the test above with the layer behind (L) pinned where it stands: the free one between (M) has no
    room, so the driven pin (P) closes its pair with M from 50 µm above the floor τ/2 to about 50 µm below it, far
    short of the gap (no outrun, no crossing). The cap counts that pair-step as pressed below the floor
    (``SelfContact.squeezed``), and the audit sees the pairs closer than τ/2 it announces; the run's summary says
    so."""
    from warpspring.app.runner import RunSummary

    tau, approach = 0.004, 1e-4
    floor = 0.5 * tau
    x = np.concatenate([_triangle(0.04, floor + 5e-5), _triangle(0.006, 0.0), _triangle(0.04, -floor - 5e-6)])
    self_contact, triangles, x0, x1 = _pinned_step_down(device, x, tau, approach, held=(2,))
    step = SurfaceAudit(triangles).step(x0, x1, thickness=tau)
    assert len(step.crossings) == 0 and len(step.intersections) == 0
    assert step.close > 0 and floor - approach < step.min_distance < floor  # pressed below τ/2, not through
    np.testing.assert_array_equal(x1[6:], x0[6:])  # L held
    assert self_contact.outrun()[0] == 0
    squeezed = int(self_contact.squeezed()[0])
    assert squeezed > 0
    summary = RunSummary(output="out.usdc", frames=1, simulated_time=1e-3, wall_time=0.0, setup_time=0.0, substeps=1,
                         dt=1e-3, device="cpu", model="model", integrator="symplectic_euler", advice="",
                         self_contact=(0, 0, 0, 0, squeezed)).line()
    assert f", {squeezed} pair-steps pressed below τ/2" in summary


def test_a_pin_squeezing_four_layers_on_the_floor_makes_them_all_give_way(device):
    """The same squeeze through four free triangles (alternately small and large), each 5 µm above the floor over the
    next, the last with nothing behind it: the pinned one (P, 50 µm above the floor) driven 0.1 mm down must move all
    four. The room is made from the back: the last layer moves, then the one before it can, and so on, one layer a
    level of the cap's later passes. A pusher placed in the same pass as the pusher it must make room for keeps that
    one's wanted point among its bounds (and in its own wanted point); before, it was placed against where that one
    stood, which it already kept, so it was accepted without moving, lost its role, and the two pushers took turns
    (the second layer never moved, at any number of levels: 6 pairs at 1.950 mm). The small 720° twist at duration
    0.98 (t = 2.348 s) and with its particles moved by up to 1 µm (t = 2.223 s) showed it: free vertices pressed by
    the pinned edge through three or four layers stayed while the pins closed pairs to 2.42 and 2.48 mm."""
    _squeeze_free_layers(device, 4)


def _squeeze_free_layers(device, layers: int) -> None:
    """The pinned triangle (50 µm above the floor over the first free one) driven 0.1 mm down onto ``layers`` free
    triangles, alternately small and large, each 5 µm above the floor over the next: no crossing, no intersection,
    no pair closer than τ/2, no pair beyond the cap, and each layer given way by what P's room and the 5 µm rooms
    between the layers before it lacked."""
    tau, approach = 0.004, 1e-4
    floor = 0.5 * tau
    heights = [floor + 5e-5, 0.0] + [-k * (floor + 5e-6) for k in range(1, layers)]
    x = np.concatenate([_triangle(0.006 if k % 2 else 0.04, z) for k, z in enumerate(heights)])
    self_contact, triangles, x0, x1 = _pinned_step_down(device, x, tau, approach)
    step = SurfaceAudit(triangles).step(x0, x1, thickness=tau)
    assert len(step.crossings) == 0 and len(step.intersections) == 0
    assert step.close == 0, f"{step.close} pairs closer than τ/2, the closest {step.min_distance:.4e} m"
    room = (1.0 - DEFAULT_RELAXATION) * 5e-5
    for k in range(layers):
        layer = slice(3 * (k + 1), 3 * (k + 2))
        assert np.all(x0[layer, 2] - x1[layer, 2] >= approach - room - k * 5e-6 - 1e-7), k
    assert self_contact.outrun()[0] == 0 and self_contact.squeezed()[0] == 0


def test_pushers_of_a_chain_are_placed_from_the_back(device):
    """Five free layers under the pinned triangle (as above, one more): a chain of five pushers, the last with
    nothing behind it, each pressing the next across a pair on the floor. The pushers' pass places them by depth (their
    distance from the squeeze, in layers), the deeper first in sub-passes of alternate depths: a pusher is placed
    against where the one behind it went, not beside it in one pass (where each is held to its share of the other's
    room), and the wanted point of a pusher counts those in front of it only (the ones behind make room for it). The
    room is then made a layer a level, and ``CAP_LEVELS`` levels move the five. Before, a pusher's wanted point kept
    the wanted points of the pushers behind it, and the chain made room a layer every two levels: the front three
    layers stayed and the pin closed 3 pairs to 1.950 mm. The small 720° twist at duration 0.98 showed
    it: the pushers behind vertex 187 (100, 165, 78) were placed with it in every pass, 187 held to its share of
    23.8 µm against 78-100 where it needed 267 µm, and the pins closed pairs to 1.664 mm."""
    _squeeze_free_layers(device, 5)


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
    assert SurfaceAudit(model.tri_indices.numpy()).touches_any(x0, x1)  # (listing its ~230 touches costs ~20 s)
    outrun = int(model.self_contact.outrun()[0])
    assert outrun > 0
    # The run's summary says so (the runner passes the same counters), and names the remedy.
    from warpspring.app.runner import RunSummary

    counts = model.self_contact.counts()
    summary = RunSummary(output="out.usdc", frames=1, simulated_time=1e-3, wall_time=0.0, setup_time=0.0, substeps=1,
                         dt=1e-3, device="cpu", model="model", integrator="symplectic_euler", advice="",
                         self_contact=(int(counts["pairs"][0]), int(counts["capped"][0]), 0, outrun, 0)).line()
    assert f", {outrun} pair-steps beyond the cap where pins closed in faster" in summary
    assert 'substeps = "auto" keeps pins within a quarter of the cap\'s reach' in summary
    assert "pairs dropped" not in summary


def test_pins_driven_through_pins_are_counted(device):
    """Two pinned cloths, the upper one driven 4 mm down a step through the lower one 12 mm below it, to 4 mm beneath
    it (τ = 4 mm): the user's own motion crosses them, which no pass can prevent (no free vertex); the pass counts the
    pair-steps beyond the cap (``SelfContact.outrun()``) from the step the two pinned sides close in by their gap,
    and the continuous audit sees the crossing."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    lower = builder.add_cloth_grid(nx=3, ny=3, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05)
    upper = builder.add_cloth_grid(nx=3, ny=3, spacing=0.02, origin=(0.005, 0.005, 0.012), mass=0.05)
    builder.add_pin_group(lower.ravel(), name="lower")
    builder.add_pin_group(upper.ravel(), name="upper", translation=ws.Track([0.0, 4e-3], [[0, 0, 0], [0, 0, -0.016]]))
    builder.add_self_collision(thickness=0.004)
    model = builder.finalize(device)
    integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
    audit, touched, counted = SurfaceAudit(model.tri_indices.numpy()), [], []
    for _ in range(4):
        integrator.step(a, b, None, 1e-3)
        touched.append(audit.touches_any(a.particle_q.numpy().astype(np.float64),
                                         b.particle_q.numpy().astype(np.float64)))
        counted.append(int(model.self_contact.outrun()[0]))
        a, b = b, a
    np.testing.assert_allclose(a.particle_q.numpy()[9:, 2], 0.012 - 0.016, atol=1e-6)  # the pins went where told
    assert any(touched)  # the surface crossed itself
    first = touched.index(True)
    assert counted[first] > 0, (touched, counted)  # counted no later than the step that crossed


# The battery's scenes under the three integrators run in bench/torture.py (bench/results/torture_cpu*.md); the
# suite runs the one case of the issue that crossed at every integrator: the strip turned 1440° in 1 s (its pins at
# up to 3.8 m/s, 3.1 mm a substep at 20 substeps against the 1.25 mm a substep the cap's passes may move a free
# vertex to give way). The scene now takes the substeps of step_choice.pin_substeps (a pin moves at most a quarter
# of the cap's reach γ τ a step).


def test_pin_substeps_bound_the_pins_travel():
    """A pinned bar turning at a constant 4 turns/s about its centre line (a linear rotation track), its ends 0.15 m
    from the axis, with self-collision τ = 5 mm and γ = 1/4: the pins' speed is ω r = 8π · 0.15 m/s, and the rule
    asks the fewest substeps of a 1/60 s frame in which that moves at most PIN_TRAVEL γ τ a step, and
    substeps = "auto" takes them; without self-collision, or with the pins standing, it asks nothing."""
    from warpspring.analysis.step_choice import PIN_TRAVEL, choose_substeps, pin_substeps

    def model(self_collision: bool, turns: float):
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        ids = builder.add_cloth_grid(nx=3, ny=3, spacing=0.15, origin=(0.0, -0.15, 0.0), mass=0.1).reshape(3, 3)
        builder.add_pin_group(ids[:, 0], name="bar", pivot=(0.0, 0.0, 0.0), rotation=ws.Track.rotation(
            [0.0, 1.0], axis=(1, 0, 0), degrees=[0.0, 360.0 * turns]))
        if self_collision:
            builder.add_self_collision(thickness=0.005, relaxation=0.25)
        return builder.finalize("cpu")

    speed = 4.0 * 2.0 * np.pi * 0.15
    substeps, why = pin_substeps(model(True, 4.0), fps=60.0)
    assert substeps == int(np.ceil(speed / (60.0 * PIN_TRAVEL * 0.25 * 0.005)))
    assert speed / (60.0 * substeps) <= PIN_TRAVEL * 0.25 * 0.005 < speed / (60.0 * (substeps - 1))
    assert f"{speed:.3g} m/s" in why
    assert pin_substeps(model(False, 4.0), fps=60.0) is None
    assert pin_substeps(model(True, 0.0), fps=60.0) is None
    # substeps = "auto" takes it where it asks more than the integrator's stability (10 here).
    choice = choose_substeps(model(True, 4.0), "symplectic_euler", fps=60.0)
    assert choice.substeps == substeps and why in choice.reason


def test_twist1440_at_its_substeps_never_crosses():
    """The 1440° twist (small size, turned in 1 s; CPU, symplectic Euler) over its first 0.5 s, every substep from
    0.4 s on audited (the window in which the former 20 substeps crossed; at 101 substeps, half the cap's reach a
    step, the strip stayed 4.3 mm from itself through 0.5 s, audited from 0.3 s): at the scene's 202 substeps (a
    quarter of the reach) no crossing, no intersection, no pair closer than τ/2 and no pair beyond the cap. At the
    battery's former 20 substeps the same half second crossed (0.497 s: 1838 crossings over the run,
    bench/results/torture_cpu_twist.md), the pins outrunning the cap's passes."""
    from warpspring.analysis.torture import scene_substeps, build_case

    model, _ = build_case("twist1440", size="small", device="cpu", duration=0.4)
    assert scene_substeps(model) == 202
    result = run_case("twist1440", "symplectic_euler", size="small", device="cpu", duration=0.4, frames=30,
                      audit_from=24)
    assert result.substeps == 202 and result.error is None
    assert result.audit.substeps == 6 * 202
    assert result.audit.crossings == 0 and result.audit.intersections == 0, result.audit.line()
    assert result.audit.close == 0 and result.outrun == 0 and result.overflow == 0
    assert result.pairs > 0  # the strip did press on itself


def test_self_collision_captured_lands_on_the_uncaptured_bits(device):
    """The 720° twist turned in 0.5 s, 12 frames of 20 substeps (its pair cache rebuilt and its cap's swept broad
    phase run hundreds of times: both conditional branches taken): captured in one graph (Warp's CPU graph records
    the BVH's refit and the conditional nodes), it lands on the same bits as the same frames run uncaptured."""
    from warpspring.analysis.torture import build_case

    runs = []
    for use_graph in (False, True):
        model, _ = build_case("twist720", size="small", device=device, duration=0.2)
        sim = ws.Simulator(model, fps=60, substeps=20, use_graph=use_graph)
        for _ in range(12):
            sim.step_frame()
        runs.append((sim.state.particle_q.numpy(), model.self_contact.counts()["pairs"], sim.stepper.captures,
                     model.self_contact.cache_counts()))
    (plain, plain_pairs, plain_captures, cache), (graph, graph_pairs, graph_captures, _) = runs
    assert plain_captures == 0 and graph_captures == 1
    assert cache["rebuilds"][0] > 10 and cache["fallbacks"][0] > 10
    assert plain_pairs[0] > 0 and np.array_equal(plain_pairs, graph_pairs)
    np.testing.assert_array_equal(plain, graph)


def test_overflow_is_said_and_still_does_not_cross(monkeypatch):
    """The stack with its pair lists cut to 8 slots (far fewer than the landing cloths' pairs): the lists
    overflow (from its 7th frame), the audit's line says how many pairs were dropped, and no substep of the frames
    around it (5 to 9) crosses or intersects (a world whose cap list overflowed keeps its free vertices where the
    step started)."""
    from warpspring.analysis.audit import SubstepAudit
    from warpspring.analysis.torture import build_case

    from warpspring.core import selfcontact

    monkeypatch.setattr(selfcontact, "GROW_ABOVE", 1.0)  # grow only after dropping pairs: the test wants them dropped
    model, _ = build_case("stack", size="small", device="cpu")
    model.self_contact._allocate(8)
    sim = ws.Simulator(model, fps=60, substeps=20)
    for _ in range(4):
        sim.step_frame()
    audit = SubstepAudit().attach(sim)
    for _ in range(5):
        sim.step_frame()
    assert audit.substeps == 5 * 20
    assert audit.overflow > 0 and f"{audit.overflow} self-collision pairs dropped" in audit.line()
    assert audit.crossings == 0 and audit.intersections == 0
