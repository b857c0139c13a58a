"""Self-collision: nothing passes through itself, proven by float64 audits (``warpspring/analysis/audit.py``).

Every scene is audited at every output frame (zero segment–triangle intersections between elements sharing
no vertex, minimum vertex–triangle / edge–edge distance ≥ 0.5 × thickness) and over every substep (the
conservative-advancement crossing audit: no pair touches along the straight path between two states). Each
scene also checks that contact happened, so that a pass does not come from layers that never met.
"""

import math

import numpy as np
import pytest
import warp as wp

import warpspring as ws
from warpspring.analysis.audit import (
    audit_frame,
    audit_motion,
    brute_pairs,
    edge_edge_distance,
    surface_edges,
    vertex_triangle_distance,
)
import warpspring.core.selfcontact as selfcontact_host
from warpspring.core.selfcontact import DEFAULT_RELAXATION
from warpspring.io.scene import parse_scene

TAU = 0.004  # [m]: every scene's thickness, below 0.7 × the 0.02 m grids' smallest altitude (0.0141 m)
CLOTH = dict(structural=ws.SpringMaterial(300.0, 0.05), shear=ws.SpringMaterial(300.0, 0.05),
             bend=ws.SpringMaterial(0.5, 0.0))


def run_audited(model, integrator, dt, steps, *, frame_every):
    """Step ``model`` ``steps`` times, auditing every substep (crossings) and every ``frame_every``-th state
    (intersections, distances). Returns (touches, intersections, the smallest frame distance, final state)."""
    triangles = model.tri_indices.numpy()
    a, b = model.state(), model.state()
    touches, intersections, nearest = 0, 0, np.inf
    for k in range(steps):
        integrator.step(a, b, None, dt)
        x0, x1 = a.particle_q.numpy(), b.particle_q.numpy()
        touches += len(audit_motion(x0, x1, triangles).touches)
        if k % frame_every == frame_every - 1:
            frame = audit_frame(x1, triangles)
            intersections += len(frame.intersections)
            nearest = min(nearest, frame.min_distance)
        a, b = b, a
    if hasattr(model.self_contact, "overflow"):  # the pass itself (not a test's stand-in): no pair was dropped
        assert model.self_contact.overflow().sum() == 0
    return touches, intersections, nearest, a


# -- the audits themselves ------------------------------------------------------------------------------------


def test_audit_distances_match_sampling():
    """The float64 vertex–triangle and edge–edge distances equal the minimum over a dense sampling of the
    primitives to the sampling's resolution (random pairs, parallel and touching ones included)."""
    rng = np.random.default_rng(3)
    p, a, b, c = (rng.normal(size=(60, 3)) for _ in range(4))
    q = rng.normal(size=(60, 3))
    q[:10] = p[:10] + (b[:10] - a[:10])  # parallel segments
    u, v = np.meshgrid(np.linspace(0, 1, 101), np.linspace(0, 1, 101))
    keep = u + v <= 1
    u, v = u[keep], v[keep]
    tri = a[:, None] + u[None, :, None] * (b - a)[:, None] + v[None, :, None] * (c - a)[:, None]
    sampled = np.min(np.linalg.norm(tri - p[:, None], axis=2), axis=1)
    exact = vertex_triangle_distance(p, a, b, c)
    assert np.all(exact <= sampled + 1e-12)
    spacing = np.linalg.norm(b - a, axis=1) / 100 + np.linalg.norm(c - a, axis=1) / 100
    assert np.all(sampled - exact <= spacing)  # the sampling's own resolution
    s = np.linspace(0, 1, 201)
    seg1 = p[:, None] + s[None, :, None] * (q - p)[:, None]
    seg2 = a[:, None] + s[None, :, None] * (b - a)[:, None]
    sampled = np.min(np.linalg.norm(seg1[:, :, None] - seg2[:, None], axis=3), axis=(1, 2))
    exact = edge_edge_distance(p, q, a, b)
    assert np.all(exact <= sampled + 1e-12)
    assert np.all(sampled - exact <= (np.linalg.norm(q - p, axis=1) + np.linalg.norm(b - a, axis=1)) / 200)


def test_audits_find_what_they_look_for():
    """A vertex moving through a triangle is a touch over the step and its edges pierce the triangle afterwards;
    a vertex that stops short is neither (so the audits can fail)."""
    triangles = np.array([[0, 1, 2], [3, 4, 5]])
    x0 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 0.1], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]], float)
    through = x0.copy()
    through[3, 2] = -0.1
    short = x0.copy()
    short[3, 2] = 0.001
    assert len(audit_motion(x0, through, triangles).touches) > 0
    assert len(audit_frame(through, triangles).intersections) == 2  # the edges 3-4 and 3-5 pierce triangle 0
    assert len(audit_motion(x0, short, triangles).touches) == 0
    assert len(audit_frame(short, triangles).intersections) == 0
    assert audit_frame(short, triangles).min_vertex_triangle == pytest.approx(0.001, rel=1e-9)


# -- the device's broad phase ---------------------------------------------------------------------------------


def crumpled_pair(device):
    """Two 6 × 6 cloths, the upper one randomly crumpled so that it comes close to the lower in places."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=6, ny=6, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05, **CLOTH, name="lower")
    builder.add_cloth_grid(nx=6, ny=6, spacing=0.02, origin=(0.004, 0.007, 0.006), mass=0.05, **CLOTH, name="upper")
    builder.add_self_collision(thickness=TAU)
    model = builder.finalize(device)
    x = model.particle_q.numpy()
    x[36:] += np.random.default_rng(7).normal(scale=0.003, size=(36, 3))
    model.particle_q.assign(x)
    return model


def test_broad_phase_equals_brute_force(device):
    """The BVH walk finds, for every vertex, exactly the vertex–triangle and edge–edge pairs sharing no vertex
    within the reach that the all-pairs float64 reference finds, and the same nearest distance (float32
    rounding of the distances: 1e-6 m)."""
    model = crumpled_pair(device)
    state = model.state()
    reach = 0.012
    nearest, count = model.self_contact.proximity(state, reach)
    x = state.particle_q.numpy().astype(np.float64)
    triangles = model.tri_indices.numpy()
    edges = surface_edges(triangles)
    vt, dvt, ee, dee = brute_pairs(x, triangles, reach)
    members = np.concatenate([np.concatenate([vt[:, :1], triangles[vt[:, 1]]], axis=1),
                              np.concatenate([edges[ee[:, 0]], edges[ee[:, 1]]], axis=1)])
    distances = np.concatenate([dvt, dee])
    expected_count = np.bincount(members.ravel(), minlength=len(x))
    expected_nearest = np.full(len(x), reach)
    np.minimum.at(expected_nearest, members.ravel(), np.repeat(distances, 4))
    # A pair within float32 rounding of the reach may fall either side of it: its vertices are left out.
    vt_all, d_all, ee_all, de_all = brute_pairs(x, triangles, reach + 1e-5)
    near_reach = np.abs(np.concatenate([d_all, de_all]) - reach) < 1e-5
    all_members = np.concatenate([np.concatenate([vt_all[:, :1], triangles[vt_all[:, 1]]], axis=1),
                                  np.concatenate([edges[ee_all[:, 0]], edges[ee_all[:, 1]]], axis=1)])
    checked = np.ones(len(x), dtype=bool)
    checked[all_members[near_reach].ravel()] = False
    assert len(members) > 100 and checked.sum() > 0.8 * len(x)  # many pairs, few vertices left out
    np.testing.assert_array_equal(count[checked], expected_count[checked])
    np.testing.assert_allclose(nearest[checked], expected_nearest[checked], atol=1e-6)


#: The broad phase's forms (``core/selfcontact.py``): one query per primitive, the vertices' and the edges' in two
#: launches or in one; one query per triangle.
BROAD_FORMS = ["per primitive, two launches", "per primitive, one launch", "per triangle"]


def broad_form(monkeypatch, form: str) -> None:
    """Force the broad phase's ``form`` (one of ``BROAD_FORMS``) for the models built after the call."""
    monkeypatch.setattr(selfcontact_host, "BROAD_PER_PRIMITIVE", form != "per triangle")
    monkeypatch.setattr(selfcontact_host, "BROAD_SEPARATE", form == "per primitive, two launches")


@pytest.mark.parametrize("form", BROAD_FORMS)
@pytest.mark.parametrize("split", [None, 3])
def test_pair_list_equals_brute_force(device, split, form, monkeypatch):
    """The broad phase lists each vertex–triangle and edge–edge pair within the reach exactly once, the same set
    as the all-pairs float64 reference (pairs within float32 rounding of the reach may fall either side), and
    a second run on a fresh model lists the same set; with each triangle's query shared by the device's number of
    threads (``broad_split``: 1 on the CPU, up to 8 on CUDA) and by 3; in each of the broad phase's forms
    (``BROAD_FORMS``)."""
    monkeypatch.setattr(selfcontact_host, "BROAD_SPLIT", split)
    broad_form(monkeypatch, form)
    reach = 0.012
    runs = []
    for _ in range(2):
        model = crumpled_pair(device)
        runs.append(model.self_contact.pairs(model.state(), reach))
    x = model.state().particle_q.numpy().astype(np.float64)
    triangles = model.tri_indices.numpy()
    inner = brute_pairs(x, triangles, reach - 1e-5)
    outer = brute_pairs(x, triangles, reach + 1e-5)
    for (vt, ee) in runs:
        for found, sure, maybe in ((vt, inner[0], outer[0]), (ee, inner[2], outer[2])):
            assert np.all(found[:, 0] == 0)
            listed = [tuple(row) for row in found[:, 1:]]
            assert len(listed) == len(set(listed))  # each pair once
            assert set(map(tuple, sure)) <= set(listed) <= set(map(tuple, maybe))
        assert len(vt) > 100 and len(ee) > 100
    for a, b in zip(runs[0], runs[1]):
        assert set(map(tuple, a)) == set(map(tuple, b))


@pytest.mark.parametrize("form", BROAD_FORMS)
@pytest.mark.parametrize("split", [None, 3])
def test_watch_list_equals_brute_force(device, split, form, monkeypatch):
    """The cache's first build watches exactly the pairs between CACHE_REACH τ and WATCH_REACH τ apart (all-pairs
    float64 reference; pairs within float32 rounding of either reach may fall either side), each once; also with the
    broad phase's queries shared by 3 threads (``broad_split``), in each of its forms (``BROAD_FORMS``). Each watched
    pair's tag names its kind and the patches of its sides' owner triangles."""
    from warpspring.kernels.selfcontact import CACHE_REACH, WATCH_EDGE_EDGE, WATCH_PATCHES, WATCH_REACH

    monkeypatch.setattr(selfcontact_host, "BROAD_SPLIT", split)
    broad_form(monkeypatch, form)

    model = crumpled_pair(device)
    sc, state = model.self_contact, model.state()
    sc.repel(state, state.particle_q)  # the first step's build, at the start
    count = int(sc.watch_count.numpy()[0])
    tags = sc.watch_tag.numpy()[:count]
    vertices = sc.watch_vertex.numpy()[:count]
    x = state.particle_q.numpy().astype(np.float64)
    triangles = model.tri_indices.numpy()
    edges = surface_edges(triangles)
    triangle_of = {tuple(int(i) for i in t): k for k, t in enumerate(triangles)}
    edge_of = {tuple(int(i) for i in e): k for k, e in enumerate(edges)}
    surface = sc.surface
    vertex_owner, edge_owner = surface.vertex_owner.numpy(), surface.edge_owner.numpy()
    patch = surface.triangle_patch.numpy()
    listed = set()
    for tag, (a, b, c, d) in zip(tags, vertices):
        edge_edge = tag >= WATCH_EDGE_EDGE
        if edge_edge:  # (p1, q1, p2, q2): edge e, then the other edge f
            e, f = edge_of[(int(a), int(b))], edge_of[(int(c), int(d))]
            listed.add((-1 - e, f))
            owners = (edge_owner[e], edge_owner[f])
        else:  # (v, the triangle's corners)
            t = triangle_of[(int(b), int(c), int(d))]
            listed.add((int(a), t))
            owners = (vertex_owner[a], t)
        sides = int(tag) - (WATCH_EDGE_EDGE if edge_edge else 0)
        assert (sides // WATCH_PATCHES, sides % WATCH_PATCHES) == (patch[owners[0]], patch[owners[1]])
    assert len(listed) == count > 100  # each once, many

    def band(low, high):
        """The pairs at least ``low`` and closer than ``high`` [m] (VT as (v, t), EE as (-1 - e, f))."""
        vt, dvt, ee, dee = brute_pairs(x, triangles, high)
        return ({(int(v), int(t)) for (v, t), d in zip(vt, dvt) if d >= low}
                | {(-1 - int(e), int(f)) for (e, f), d in zip(ee, dee) if d >= low})

    sure = band(CACHE_REACH * TAU + 1e-5, WATCH_REACH * TAU - 1e-5)
    maybe = band(CACHE_REACH * TAU - 1e-5, WATCH_REACH * TAU + 1e-5)
    assert sure <= listed <= maybe


# -- scenes ---------------------------------------------------------------------------------------------------


def folding_cloth(device, nx=8, ny=5):
    """A cloth lying on the ground whose left edge a pin group lifts, carries over the cloth and lays down
    three thicknesses above it: the left part folds onto the right."""
    builder = ws.ModelBuilder()
    ids = builder.add_cloth_grid(nx=nx, ny=ny, spacing=0.02, origin=(0.0, 0.0, 0.003), mass=0.1, radius=0.003,
                                 **CLOTH)
    width = 0.02 * (nx - 1)
    track = ws.Track([0.0, 0.15, 0.45, 0.65], [[0, 0, 0], [0.02, 0, 0.05], [0.85 * width, 0, 0.05],
                                             [0.85 * width, 0, 3 * TAU]], interpolation="smooth")
    builder.add_pin_group(ids.reshape(ny, nx)[:, 0], translation=track)
    builder.add_ground_plane(friction=0.6)
    builder.add_self_collision(thickness=TAU, friction=0.3)
    return builder.finalize(device)


@pytest.mark.parametrize("integrator", ["symplectic_euler", "rk4", "implicit_euler"])
def test_folding_cloth_never_passes_through_itself(device, integrator):
    """A cloth folded onto itself by a moving pin group, 0.75 s at dt = 1 ms: in every frame (every 16 steps) no
    edge passes through a triangle and the layers stay at least half the thickness apart, and no pair
    touches during any step (float64 audits); the layers did meet (pairs were pushed apart, and the closest
    pair came within two thicknesses)."""
    model = folding_cloth(device)
    touches, intersections, nearest, state = run_audited(model, ws.INTEGRATORS[integrator](model), 1e-3, 750,
                                                         frame_every=16)
    assert touches == 0
    assert intersections == 0
    assert 0.5 * TAU <= nearest < 2.0 * TAU
    assert model.self_contact.counts()["pairs"][0] > 0
    x = state.particle_q.numpy()
    # Folded: the cloth spans less than its width. The fold's last 0.25 s is chaotic (stick-slip on the ground and
    # between the layers): in float64 the CPU's per-particle step and its sweep, whose sums differ by 1e-15 m at
    # 0.5 s, end 0.099 and 0.118 m across; both well under the 0.14 m of the flat cloth.
    assert x[:, 0].max() - x[:, 0].min() < 0.9 * 0.14


def test_stacked_cloths_keep_their_order(device):
    """Two cloths, one 8 mm above the other, dropped onto a box smaller than they are: they drape over it
    together, and every particle of the top cloth stays on the top side of the bottom cloth (its offset
    from the bottom cloth's particle of the same grid place, along that particle's normal, stays positive),
    with the frame and step audits clean."""
    builder = ws.ModelBuilder()
    for name, z in (("bottom", 0.12), ("top", 0.128)):
        builder.add_cloth_grid(nx=8, ny=8, spacing=0.02, origin=(-0.07, -0.07, z), mass=0.1, radius=0.003, **CLOTH,
                               name=name)
    builder.add_collider_box(center=(0.0, 0.0, 0.05), half_extents=(0.04, 0.04, 0.05), friction=0.5)
    builder.add_self_collision(thickness=TAU, friction=0.4)
    model = builder.finalize(device)
    triangles = model.tri_indices.numpy()
    bottom = triangles[: len(triangles) // 2]
    integrator = ws.SymplecticEuler(model)
    a, b = model.state(), model.state()
    worst = np.inf
    for k in range(400):  # 0.4 s at dt = 1 ms: the fall, the landing and the drape
        integrator.step(a, b, None, 1e-3)
        x0, x1 = a.particle_q.numpy().astype(np.float64), b.particle_q.numpy().astype(np.float64)
        assert len(audit_motion(x0, x1, triangles).touches) == 0
        if k % 25 == 24:
            frame = audit_frame(x1, triangles)
            assert len(frame.intersections) == 0 and frame.min_distance >= 0.5 * TAU
            faces = x1[bottom]
            normals = np.cross(faces[:, 1] - faces[:, 0], faces[:, 2] - faces[:, 0])
            vertex_normals = np.zeros((64, 3))
            np.add.at(vertex_normals, bottom.ravel(), np.repeat(normals, 3, axis=0))
            vertex_normals /= np.linalg.norm(vertex_normals, axis=1, keepdims=True)
            worst = min(worst, float(np.min(np.einsum("ij,ij->i", x1[64:] - x1[:64], vertex_normals))))
        a, b = b, a
    x = a.particle_q.numpy()
    assert x[:64, 2].min() < 0.06  # the cloths draped down the box's sides
    assert model.self_contact.overflow().sum() == 0
    assert worst > 0.5 * TAU


def test_twisted_strip_does_not_pass_through_itself(device):
    """A strip whose ends turn half a turn each in opposite directions while they approach (wrung): it coils
    into contact with itself, and the audits find no crossing, no intersection and no pair closer than
    half the thickness."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    ids = builder.add_cloth_grid(nx=16, ny=4, spacing=0.02, origin=(-0.15, -0.03, 0.5), mass=0.05, **CLOTH).reshape(4, 16)
    for column, sign in ((0, 1.0), (15, -1.0)):
        builder.add_pin_group(ids[:, column], rotation=ws.Track.rotation([0.0, 0.6], axis=(1, 0, 0), degrees=[0, 180 * sign],
                                                                          interpolation="smooth"),
                              translation=ws.Track([0.0, 0.6], [[0, 0, 0], [0.06 * sign, 0, 0]], interpolation="smooth"))
    builder.add_self_collision(thickness=TAU, friction=0.2)
    model = builder.finalize(device)
    touches, intersections, nearest, _ = run_audited(model, ws.SymplecticEuler(model), 1e-3, 650, frame_every=16)
    assert touches == 0 and intersections == 0
    assert 0.5 * TAU <= nearest < 2.0 * TAU
    assert model.self_contact.counts()["pairs"][0] > 0


def test_pinned_strip_pressed_into_a_free_cloth(device):
    """A pinned strip (kinematic: infinite mass, never capped) moves down at 0.3 m/s into a free cloth 8 mm below
    it and carries on 2.5 cm: the free cloth takes the whole correction, is pushed ahead of the strip, and
    neither the step audit nor the frame audit finds a crossing (the cap bounds a free vertex by its distance
    minus the strip's prescribed displacement, 0.3 mm per step, well below the layers' ~τ gap)."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=8, ny=8, spacing=0.02, origin=(-0.07, -0.07, 0.0), mass=0.05, **CLOTH, name="free")
    strip = builder.add_cloth_grid(nx=5, ny=2, spacing=0.02, origin=(-0.037, -0.013, 0.008), mass=0.05, **CLOTH,
                                   name="strip")
    builder.add_pin_group(strip.ravel(), translation=ws.Track([0.0, 0.11], [[0, 0, 0], [0, 0, -0.033]]))
    builder.add_self_collision(thickness=TAU, friction=0.2)
    model = builder.finalize(device)
    touches, intersections, nearest, state = run_audited(model, ws.SymplecticEuler(model), 1e-3, 110,
                                                         frame_every=10)
    x = state.particle_q.numpy()
    assert x[64:, 2].max() == pytest.approx(0.008 - 0.033, abs=1e-6)  # the strip went where it was told
    assert touches == 0 and intersections == 0 and nearest >= 0.5 * TAU
    assert x[:64, 2].min() < -0.02  # the free cloth was pushed down ahead of it
    assert model.self_contact.counts()["pairs"][0] > 0


def test_cap_subtracts_a_pins_prescribed_displacement(device):
    """One step in which a pinned cloth moves 9.6 mm down toward a free cloth 12 mm below it (beyond the
    repulsion's 8 mm reach) while the free cloth's integrator moves it 3.6 mm up: a cap of γD = 3 mm on the free
    side would let them cross (3 + 9.6 > 12); bounded by γ(D - K) = 0.6 mm, the free cloth stops short and the
    step audit finds no touch."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05, velocity=(0.0, 0.0, 3.6),
                           **CLOTH, name="free")
    pinned = builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.005, 0.005, 0.012), mass=0.05, **CLOTH,
                                    name="pinned")
    builder.add_pin_group(pinned.ravel(), translation=ws.Track([0.0, 1e-3], [[0, 0, 0], [0, 0, -0.0096]]))
    builder.add_self_collision(thickness=TAU)
    model = builder.finalize(device)
    touches, _, _, state = run_audited(model, ws.SymplecticEuler(model), 1e-3, 1, frame_every=1)
    z = state.particle_q.numpy()[:, 2]
    assert z[25:] == pytest.approx(0.012 - 0.0096, abs=1e-6)  # the pins moved as prescribed
    assert touches == 0
    assert z[:25].max() <= 0.25 * (0.012 - 0.0096) + 1e-6  # the free cloth moved at most γ(D - K)


# -- the cap is load-bearing ----------------------------------------------------------------------------------


class RepulsionOnly:
    """The self-collision pass without its displacement cap (the repulsion and friction alone)."""

    capturable = False

    def __init__(self, full):
        self.full = full

    def history(self):
        return []

    def __call__(self, state_in, state_out, dt):
        wp.copy(state_out.particle_q, self.full.repel(state_in, state_out.particle_q))


def thrown_cloth(device, worlds=1):
    """A cloth thrown at 15 m/s at another 1 cm below it: 12.5 mm per 0.83 ms step, beyond the gap and the
    repulsion's reach (2 τ = 8 mm at the step's start)."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05, **CLOTH, name="target")
    builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.005, 0.005, 0.01), mass=0.05, velocity=(0, 0, -15.0),
                           **CLOTH, name="thrown")
    builder.add_self_collision(thickness=TAU)
    return builder.finalize(device, worlds=worlds)


def test_the_cap_is_load_bearing(device):
    """Repulsion alone lets the thrown cloth pass through the other (the step audit finds touches, and it
    ends below the target); with the cap nothing crosses, the cap acted, and two runs give the same
    bits (no float atomics)."""
    dt = 1.0 / 1200.0
    model = thrown_cloth(device)
    object.__setattr__(model, "self_contact", RepulsionOnly(model.self_contact))
    touches, _, _, state = run_audited(model, ws.SymplecticEuler(model), dt, 12, frame_every=1)
    z = state.particle_q.numpy()[:, 2]
    assert touches > 0 and z[25:].max() < z[:25].min()  # it went right through: now wholly below the target

    finals = []
    for _ in range(2):
        model = thrown_cloth(device)
        touches, intersections, nearest, state = run_audited(model, ws.SymplecticEuler(model), dt, 12, frame_every=1)
        assert touches == 0 and intersections == 0 and nearest > 0.0
        assert model.self_contact.counts()["capped"][0] > 0
        finals.append(state.particle_q.numpy())
    np.testing.assert_array_equal(finals[0], finals[1])


def test_a_capped_vertex_ends_at_its_bound_not_its_start(device):
    """The thrown cloth's first step (12.5 mm toward a target 10 mm below): the cap shortens every thrown vertex's step
    to γ (D - τ/2) = 2 mm along the layers' normal (D = 10 mm, the floor τ/2), and each ends there, to the rounding
    pad (a micrometre). Before, a capped position start + (bound/|Δ|) Δ that rounded past its bound (half of them:
    the rounding goes either way) was held at its start: 5 of the 25 did not move, and the repulsion's push of such
    a vertex was lost with its step."""
    model = thrown_cloth(device)
    a, b = model.state(), model.state()
    ws.SymplecticEuler(model).step(a, b, None, 1.0 / 1200.0)
    moved = np.linalg.norm(b.particle_q.numpy()[25:] - a.particle_q.numpy()[25:], axis=1)
    bound = DEFAULT_RELAXATION * (0.01 - 0.5 * TAU)
    assert np.all(moved <= bound) and np.all(moved > bound - 2e-6), moved
    assert model.self_contact.counts()["capped"][0] >= 25


def test_overflow_is_counted_and_safe(device):
    """With pair buffers of 4 slots the thrown cloth's pairs overflow them: the dropped pairs are counted, and a
    world whose cap list overflowed keeps its free vertices where the step started (nothing crosses, the
    thrown cloth stays where it was)."""
    dt = 1.0 / 1200.0
    model = thrown_cloth(device)
    sc = model.self_contact
    sc._allocate(4)
    z0 = model.particle_q.numpy()[:, 2]
    integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
    integrator.step(a, b, None, dt)
    assert len(audit_motion(a.particle_q.numpy(), b.particle_q.numpy(), model.tri_indices.numpy()).touches) == 0
    assert sc.overflow()[0] > 0 and sc.listed()["cap"][0] > 4  # the cap found more pairs than it could hold
    a = b
    np.testing.assert_array_equal(a.particle_q.numpy()[:, 2], z0)


# -- configuration --------------------------------------------------------------------------------------------


def test_bad_settings_are_one_line_errors():
    builder = ws.ModelBuilder()
    builder.add_cloth_grid(nx=4, ny=4, spacing=0.02, mass=0.05)
    with pytest.raises(ws.ConfigError, match="relaxation must be in"):
        builder.add_self_collision(thickness=TAU, relaxation=0.5)
    with pytest.raises(ws.ConfigError, match="thickness must be > 0"):
        builder.add_self_collision(thickness=-1.0)
    with pytest.raises(ws.ConfigError, match="no mesh named 'sheet'"):
        builder.add_self_collision(thickness=TAU, meshes="sheet")
    builder.add_self_collision(thickness=0.012)
    with pytest.raises(ws.ConfigError, match="too large for the mesh"):
        builder.finalize("cpu")


def test_scene_table_and_live_values():
    """``[self_collision]`` in a scene turns it on with its values; without it the model has none (and the
    contact response stays fusable); set() writes live values per world."""
    base = {"version": 2, "cloth": {"grid": {"nx": 4, "ny": 4, "spacing": 0.02}, "mass": 0.05}}
    model = parse_scene(base).finalize("cpu")
    assert model.self_contact is None and ws.SymplecticEuler(model).finish_step.only_contacts
    scene = parse_scene({**base, "self_collision": {"thickness": TAU, "friction": 0.3}})
    model = scene.finalize("cpu")
    assert model.self_contact.thickness == pytest.approx(TAU)
    model.self_contact.set(friction=0.6, world=0)
    np.testing.assert_allclose(model.self_contact.params.numpy()[0], [TAU, 0.6, 0.25], rtol=1e-6)
    with pytest.raises(ws.ConfigError, match="needs thickness"):
        parse_scene({**base, "self_collision": {"friction": 0.3}})


def test_captured_frames_equal_uncaptured(device):
    """Frames replayed from a captured graph (CUDA: the BVH refit is device work inside it) equal the same
    frames launched one by one, bit for bit; on the CPU, where Warp refits meshes on the host, the stepper
    runs them uncaptured and the two agree likewise."""
    finals = []
    for use_graph in (True, False):
        model = folding_cloth(device)
        sim = ws.Simulator(model, fps=60, substeps=8, guard=None, use_graph=use_graph)
        for _ in range(12):
            sim.step_frame()
        finals.append(sim.state.particle_q.numpy())
    np.testing.assert_array_equal(finals[0], finals[1])


def test_cli_audit_of_a_usd_file(tmp_path, capsys):
    """``warpspring audit`` reads an animated mesh's frames from USD: a vertex pushed through a triangle in
    the second frame is found (exit status 6), a file without one passes (0), and --thickness counts the
    frames whose layers come closer than half of it."""
    from pxr import Usd, UsdGeom

    from warpspring.app.cli import EXIT_AUDIT, main

    def write(path, second_z):
        stage = Usd.Stage.CreateNew(str(path))
        mesh = UsdGeom.Mesh.Define(stage, "/World/cloth")
        mesh.CreateFaceVertexCountsAttr([3, 3])
        mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 4, 5])
        points = mesh.CreatePointsAttr()
        x = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0.2, 0.2, 0.1), (0.3, 0.2, 0.5), (0.2, 0.3, 0.5)]
        points.Set(x, 0.0)
        points.Set(x[:3] + [(0.2, 0.2, second_z)] + x[4:], 1.0)
        stage.GetRootLayer().Save()

    write(tmp_path / "through.usda", -0.1)
    write(tmp_path / "above.usda", 0.002)
    assert main(["audit", str(tmp_path / "through.usda")]) == EXIT_AUDIT
    assert "2 frames: 2 segment-triangle intersections" in capsys.readouterr().out
    assert main(["audit", str(tmp_path / "above.usda")]) == 0
    assert main(["audit", str(tmp_path / "above.usda"), "--thickness", "0.01"]) == EXIT_AUDIT
    assert "1 frames closer than half the thickness" in capsys.readouterr().out


@pytest.mark.parametrize("example", ["cloth_fold_on_bar", "twisted_cloth", "stacked_cloths"])
def test_example_scenes_build(example):
    """The self-collision examples parse and build with it (their runs are minutes on a CPU:
    bench/results/selfcontact.md has them audited over their frames)."""
    from pathlib import Path

    from warpspring.io.scene import load_scene

    scene = load_scene(Path(__file__).parent.parent / "examples" / f"{example}.toml")
    model = scene.finalize("cpu")
    assert model.self_contact is not None and model.self_contact.thickness == pytest.approx(scene.self_collision["thickness"])


def test_worlds_do_not_couple(device):
    """Two worlds of the thrown cloth, the second with its own thickness (a live value per world): each equals
    the same world run alone, bit for bit."""
    dt = 1.0 / 1200.0

    def run(model):
        integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
        for _ in range(12):
            integrator.step(a, b, None, dt)
            a, b = b, a
        return a.particle_q.numpy().reshape(model.world_count, model.particle_count, 3)

    both = thrown_cloth(device, worlds=2)
    both.self_contact.set(thickness=0.003, world=1)
    alone = thrown_cloth(device)
    thinner = thrown_cloth(device)
    thinner.self_contact.set(thickness=0.003)
    q = run(both)
    np.testing.assert_array_equal(q[0], run(alone)[0])
    np.testing.assert_array_equal(q[1], run(thinner)[0])
    assert not np.array_equal(q[0], q[1])


# -- the pair cache -------------------------------------------------------------------------------------------


class BroadPhaseEveryStep:
    """The pass with its pair cache rebuilt at every step's start and the cap's swept broad phase run at every
    step (the work the cache saves, done every time)."""

    capturable = False

    def __init__(self, full):
        self.full = full

    def history(self):
        return []

    def __call__(self, state_in, state_out, dt):
        sc = self.full
        sc.cache_reach.zero_()  # a reach of 0 fails the drift check: the cache is rebuilt at this step's start
        repelled = sc.repel(state_in, state_out.particle_q)
        flags = sc.flags.numpy()
        worlds = sc.model.world_count
        flags[1] = 1
        flags[2 + worlds:2 + 2 * worlds] = 1  # every world's cap runs the swept broad phase
        sc.flags.assign(flags)
        sc.cap(state_in, repelled, state_out, dt)


def cached_and_every_step(make, steps: int, dt: float) -> tuple[list, list]:
    """``steps`` symplectic Euler steps of ``dt`` [s] of a model from ``make()`` with the pass as it runs (its cache),
    then of another with ``BroadPhaseEveryStep``: ([final positions], [counters and cache counters]) of both."""
    finals, counts = [], []
    for every_step in (False, True):
        model = make()
        if every_step:
            object.__setattr__(model, "self_contact", BroadPhaseEveryStep(model.self_contact))
        integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
        for _ in range(steps):
            integrator.step(a, b, None, dt)
            a, b = b, a
        finals.append(a.particle_q.numpy())
        sc = model.self_contact if not every_step else model.self_contact.full
        counts.append({**sc.counts(), **sc.cache_counts()})
    return finals, counts


def wrung_strip(device, worlds=1):
    """twisted strip's scene (pins turning and approaching: kinematic displacements in the cap's bounds)."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    ids = builder.add_cloth_grid(nx=16, ny=4, spacing=0.02, origin=(-0.15, -0.03, 0.5), mass=0.05, **CLOTH).reshape(4, 16)
    for column, sign in ((0, 1.0), (15, -1.0)):
        builder.add_pin_group(ids[:, column], rotation=ws.Track.rotation([0.0, 0.6], axis=(1, 0, 0), degrees=[0, 180 * sign],
                                                                          interpolation="smooth"),
                              translation=ws.Track([0.0, 0.6], [[0, 0, 0], [0.06 * sign, 0, 0]], interpolation="smooth"))
    builder.add_self_collision(thickness=TAU, friction=0.2)
    return builder.finalize(device, worlds=worlds)


@pytest.mark.parametrize("scene", ["wrung", "thrown"])
def test_cache_changes_the_work_not_the_answer(device, scene):
    """The pass over its pair cache (rebuilt only when a vertex drifted, the cap's swept broad phase only where a
    free vertex moves too far for the cache) gives the same bits as the broad phase at every step of both
    stages: through the wrung strip's coiling (pins turning, layers in contact) and the thrown cloth (fast,
    two worlds with their own thickness, the cap acting); and the cache did save work (fewer rebuilds than
    steps) and the fallback did run where the thrown cloth is fast."""
    steps, dt = (650, 1e-3) if scene == "wrung" else (12, 1.0 / 1200.0)
    make = (lambda: wrung_strip(device)) if scene == "wrung" else (lambda: thrown_cloth(device, worlds=2))
    def configured():
        model = make()
        if scene == "thrown":  # world 1's τ = 2 mm: its cap needs the swept broad phase at other steps than world 0's
            model.self_contact.set(thickness=0.002, world=1)
        return model

    finals, counts = cached_and_every_step(configured, steps, dt)
    np.testing.assert_array_equal(finals[0], finals[1])
    cached, full = counts
    np.testing.assert_array_equal(cached["pairs"], full["pairs"])
    np.testing.assert_array_equal(cached["capped"], full["capped"])
    assert cached["pairs"].sum() > 0
    assert np.all(full["rebuilds"] == steps)
    if scene == "wrung":  # slow motion: the cache holds for several steps
        assert np.all(cached["rebuilds"] < steps // 2)
    else:  # 12.5 mm per step: the cap's swept broad phase runs, and caps
        assert cached["capped"].sum() > 0 and cached["fallbacks"].sum() > 0
        # One world's cap ran its swept broad phase while the other's read its cache (their rebuilds, 2 each, fall on
        # the same steps since the cap keeps the layers τ/2 apart: both land on the target at the third step).
        assert cached["fallbacks"][0] != cached["fallbacks"][1]


def gliding_layers(device, speed):
    """Two 5 × 5 cloths 2.5 τ apart (their pairs cached, none repelled), gliding together along x at ``speed``
    [m/s] without gravity: no relative drift, every free vertex moving the same step."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    for z in (0.0, 2.5 * TAU):
        builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, z), mass=0.05, velocity=(speed, 0.0, 0.0),
                               **CLOTH)
    builder.add_self_collision(thickness=TAU)
    return builder.finalize(device)


@pytest.mark.parametrize("step", [0.6, 0.8])
def test_the_cache_serves_the_cap_up_to_its_least_outside_distance(device, step):
    """The cap needs its swept broad phase only where a vertex's step could reach a pair outside the cache: γ times
    (the least distance A of such a pair, less the pins' step). A is what the cache knows of them (the reach at
    its anchors less the drifts' spread, their boxes' gap, the watched pairs' own distances; CACHE_REACH τ right
    after a rebuild), not the repulsion's reach 2 τ: two layers gliding together 0.6 τ a step (within γ 3 τ =
    0.75 τ, past γ 2 τ = 0.5 τ) cap from their cache at every step, 0.8 τ a step needs the swept
    broad phase at every step; either way the same bits as the broad phase at every step."""
    dt, steps = 1.0 / 1200.0, 20
    finals, counts = cached_and_every_step(lambda: gliding_layers(device, step * TAU / dt), steps, dt)
    np.testing.assert_array_equal(finals[0], finals[1])
    x = finals[0]
    np.testing.assert_allclose(x[:, 0] - gliding_layers("cpu", 0.0).particle_q.numpy()[:, 0], step * TAU * steps,
                               rtol=1e-4)  # they glided, untouched
    fallbacks = int(counts[0]["fallbacks"].sum())
    assert fallbacks == (0 if step == 0.6 else steps), fallbacks


@pytest.mark.parametrize("layout", ["tilted", "flat"])
def test_cache_holds_while_the_drifts_spread_less_than_its_slack(device, layout):
    """Two cloths 0.1 m apart (beyond the cache's reach), one still, one sliding past it at 1.5 m/s (1.5 mm per
    1 ms step, along the sheets' common plane, no gravity, springs at rest): every relative drift lies along one
    axis. Tilted 45° (their boxes overlap though the sheets are 0.1 m apart), the cache holds while the spread of
    the drifts across patches whose boxes lie within 2τ, the slider's displacement since the last build, stays
    within R - 2τ = 2.5τ (R = WATCH_REACH τ: the sheets' in-plane pairs between 3τ and 4.5τ are watched; less
    SAFETY, 1/64): 10.5 mm > 9.84 mm ≥ 9.0 mm, so it is rebuilt every seventh step (steps 0, 7, ..., 28: 5 in 30),
    where the largest drift from a reference vertex alone (≤ 1.25τ) would rebuild every fourth step (8). Flat (one above the other, their boxes 0.1 m apart), no pair across them can come within 2τ
    whatever their drifts: built once, never rebuilt. Nothing is cached and no step reaches the repulsion's budget
    γ · 2τ (2 mm), so the pair stages never run (their flag stays down) and the slider moves exactly as
    integrated."""
    from warpspring.kernels.selfcontact import FLAG_WORK

    half = np.sin(np.pi / 8.0), np.cos(np.pi / 8.0)
    tilted = layout == "tilted"
    rotation = (0.0, half[0], 0.0, half[1]) if tilted else (0.0, 0.0, 0.0, 1.0)
    normal = np.array([np.sqrt(0.5), 0.0, np.sqrt(0.5)]) if tilted else np.array([0.0, 0.0, 1.0])
    nx = 13 if tilted else 5
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=nx, ny=5, spacing=0.02, origin=(0.0, 0.0, 0.0), rotation=rotation, mass=0.05, **CLOTH,
                           name="still")
    builder.add_cloth_grid(nx=nx, ny=5, spacing=0.02, origin=tuple(0.1 * normal), rotation=rotation, mass=0.05,
                           velocity=(0.0, 1.5, 0.0), **CLOTH, name="slider")
    builder.add_self_collision(thickness=TAU)
    model = builder.finalize(device)
    sc = model.self_contact
    integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
    start = a.particle_q.numpy().astype(np.float64)
    work = []
    for _ in range(30):
        integrator.step(a, b, None, 1e-3)
        a, b = b, a
        work.append(int(sc.flags.numpy()[2 + FLAG_WORK * model.world_count]))
    assert sc.cache_counts()["rebuilds"][0] == (5 if tilted else 1)
    assert sc.listed()["cache"][0] == 0 and not any(work)
    moved = a.particle_q.numpy().astype(np.float64) - start
    half_count = len(moved) // 2
    np.testing.assert_allclose(moved[:half_count], 0.0, atol=1e-7)
    np.testing.assert_allclose(moved[half_count:], np.tile([0.0, 0.045, 0.0], (half_count, 1)), atol=1e-5)  # 30 × 1.5 mm


def test_the_stages_skip_cached_pairs_beyond_their_reach(device):
    """Two 5 × 5 sheets 2.6τ apart, the upper one closing at 0.1τ a step (no gravity): at the first build their pairs
    are cached (within CACHE_REACH τ) but beyond the repulsion's reach (2τ). The pair stages run from the first step
    whose start has a cached pair within 2τ (1 + SAFETY) (the sheets' gap there, in float64: step 6), not before:
    from step 3 on, the pairs' least distance at the anchors less twice the largest drift (``cache_near``) no longer
    keeps them beyond the reach, and the watched pairs' check then measures the cached pairs' own distances
    (FLAG_CACHED). The run equals the pass with its stages every step (``BroadPhaseEveryStep``), bit for bit, with
    pairs pushed."""
    from warpspring.kernels.selfcontact import FLAG_WORK, SAFETY

    def make():
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05, **CLOTH, name="still")
        builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, 2.6 * TAU), mass=0.05,
                               velocity=(0.0, 0.0, -0.1 * TAU / 1e-3), **CLOTH, name="closing")
        builder.add_self_collision(thickness=TAU)
        return builder.finalize(device)

    steps = 20
    model = make()
    sc = model.self_contact
    integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
    work, cached, gaps = [], [], []
    for _ in range(steps):
        z = a.particle_q.numpy().astype(np.float64)[:, 2]
        gaps.append(z[25:].min() - z[:25].max())  # the sheets' gap at the step's start: their VT pairs' least distance
        integrator.step(a, b, None, 1e-3)
        a, b = b, a
        work.append(int(sc.flags.numpy()[2 + FLAG_WORK * model.world_count]))
        cached.append(int(sc.listed()["cache"][0]))
    within = [gap < 2.0 * TAU * (1.0 + SAFETY) for gap in gaps]
    first = within.index(True)
    assert cached[0] > 0 and first == 6, (gaps, first)
    assert work[:first] == [0] * first and work[first] == 1 and work[-1] == 1, (work, first)
    skipped_with_pairs = sum(1 for w, c in zip(work, cached) if w == 0 and c > 0)
    assert skipped_with_pairs >= first and sc.cache_counts()["stages"][0] == sum(work)
    finals, counts = cached_and_every_step(make, steps, 1e-3)
    np.testing.assert_array_equal(finals[0], finals[1])
    assert counts[0]["pairs"].sum() > 0 and counts[0]["pairs"].sum() == counts[1]["pairs"].sum()


def test_an_overflowed_cache_runs_the_stages_by_its_world_bound(device):
    """Two pairs of sheets: 9 × 9 ones resting 2.9τ apart (their ~2,900 pairs cached, beyond the repulsion's reach),
    listed first, and 3 × 3 ones closing at 0.2τ a step from 2.6τ; the cache given 2,100 slots, so that it keeps the
    resting sheets' pairs and drops the closing ones'. The world's bound on its cached pairs (``cache_near``, which
    counts the dropped pairs) then runs the stages, not the check of the stored pairs' own distances (which would see
    only the resting ones and skip the stages): the cap's swept broad phase holds the closing sheets at least τ/2
    apart (without this, 0.45τ)."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_cloth_grid(nx=9, ny=9, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05, **CLOTH, name="low")
    builder.add_cloth_grid(nx=9, ny=9, spacing=0.02, origin=(0.0, 0.0, 2.9 * TAU), mass=0.05, **CLOTH, name="high")
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.02, origin=(1.0, 0.0, 0.0), mass=0.05, **CLOTH, name="still")
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.02, origin=(1.0, 0.0, 2.6 * TAU), mass=0.05,
                           velocity=(0.0, 0.0, -0.2 * TAU / 1e-3), **CLOTH, name="closing")
    builder.add_self_collision(thickness=TAU)
    model = builder.finalize(device)
    sc = model.self_contact
    sc._allocate(700)  # the cache's 3 × 700 slots: fewer than its pairs
    integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
    gaps = []
    for _ in range(20):
        integrator.step(a, b, None, 1e-3)
        a, b = b, a
        z = a.particle_q.numpy().astype(np.float64)[:, 2]
        gaps.append(z[171:].min() - z[162:171].max())
    assert sc.cache.count.numpy()[0] > sc.cache_capacity and sc.overflow()[0] > 0
    assert min(gaps) >= 0.5 * TAU * (1.0 - 1e-4), min(gaps) / TAU


@pytest.mark.parametrize("chunk", [512, 5])
def test_patch_boxes_hold_their_corners(device, chunk, monkeypatch):
    """The cache's check (``kernels/selfcontact_cache.py``) reduces each patch's boxes of its triangles' corners: the
    positions at the step's start and the drifts from the anchors (relative to the reference vertex). Against NumPy
    in float64 after a wrung strip's steps (two worlds, moving pins): each box holds every corner and is no wider than
    the tight box by more than one unit τ/4096 and the rounding pad on either side; with blocks of 5 triangles (a
    patch over several blocks, their maxima merged by integer atomics) likewise; and the check's two forms (one block
    per chunk with block-wide maxima, as on CUDA; one thread per chunk, as on the CPU) give the same integers."""
    import warpspring.core.selfcontact as host
    from warpspring.kernels.selfcontact import KINEMATIC_STEPS, PATCH_DRIFT, PATCH_POSITION
    from warpspring.kernels.selfcontact_cache import LENGTH_LIMIT

    monkeypatch.setattr(host, "PATCH_CHUNK", chunk)
    model = wrung_strip(device, worlds=2)
    sc = model.self_contact
    integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
    for _ in range(40):
        start = a.particle_q.numpy().astype(np.float64).reshape(2, model.particle_count, 3)
        anchor = sc.cache_anchor.numpy().astype(np.float64).reshape(2, model.particle_count, 3)
        integrator.step(a, b, None, 1e-3)
        a, b = b, a
    assert sc.patch_count > 1 and (chunk > 100 or sc.chunk_count > sc.patch_count)
    boxes = sc.patch_box.numpy().astype(np.int64) - LENGTH_LIMIT
    unit = TAU / KINEMATIC_STEPS
    triangles = sc.surface.triangle.numpy()
    ref = triangles[len(triangles) // 2][0]
    for world in range(2):
        drift = start[world] - anchor[world] - (start[world, ref] - anchor[world, ref])
        for patch in range(sc.patch_count):
            corners = np.unique(triangles[sc.patch_triangles[patch]])
            for column, values in ((PATCH_POSITION, start[world, corners]), (PATCH_DRIFT, drift[corners])):
                high, low = boxes[world, patch, column:column + 3] * unit, -boxes[world, patch, column + 3:column + 6] * unit
                assert np.all(high >= values.max(axis=0)) and np.all(low <= values.min(axis=0))
                slack = unit + 1e-5 * (np.abs(values).max() + 1.0)  # a unit of rounding up and the pads (BOX_PAD each)
                assert np.all(high - values.max(axis=0) <= slack) and np.all(values.min(axis=0) - low <= slack)
    last = a.particle_q  # the last step's end: its check again, in both forms
    forms = []
    for tiled in (True, False):
        sc._step_scratch.zero_()
        sc._check(b.particle_q, last, tiled=tiled)
        forms.append(sc._step_scratch.numpy())
    np.testing.assert_array_equal(forms[0], forms[1])
    assert np.any(forms[0] != 0)


@pytest.mark.parametrize("split", [None, 3])
def test_watched_pairs_rebuild_the_cache(device, split, monkeypatch):
    """A cloth 13 mm (3.25τ) above a still one, coming down at 1.5 m/s (1.5 mm per 1 ms step, no gravity): its pairs
    with the other lie between the cache's reach (3τ) and WATCH_REACH τ (4.5τ) at the first build, so they are
    watched, not cached. Their drifts stay within the slack (2.5τ, 9.84 mm) until the eighth step, but at the fifth
    step's start they are 7 mm apart, within the repulsion's reach (2τ = 8 mm): the watch must rebuild the cache
    there, and the repulsion pushes from the sixth step on. The run equals the broad phase at every step, bit for
    bit, with pairs pushed; a cache that trusted the drifts alone would miss them (checked: with the watch's test
    disabled, this run differs). Also with the broad phase and the watch shared by 3 threads a triangle and a
    particle (``broad_split``; on CUDA by default up to 8)."""
    monkeypatch.setattr(selfcontact_host, "BROAD_SPLIT", split)

    def make():
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.05, **CLOTH, name="still")
        builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, 3.25 * TAU), mass=0.05,
                               velocity=(0.0, 0.0, -1.5), **CLOTH, name="falling")
        builder.add_self_collision(thickness=TAU)
        return builder.finalize(device)

    finals, counts = cached_and_every_step(make, 8, 1e-3)
    np.testing.assert_array_equal(finals[0], finals[1])
    assert counts[0]["pairs"].sum() > 0 and counts[0]["pairs"].sum() == counts[1]["pairs"].sum()
    assert 1 < counts[0]["rebuilds"][0] < 8


def _two_sheets(device, gap: float = 0.003):
    """Two 8 × 8 sheets ``gap`` apart without gravity, τ = 4 mm."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    spring = ws.SpringMaterial(ke=100.0, kd=0.01)
    for z in (0.0, gap):
        builder.add_cloth_grid(nx=8, ny=8, spacing=0.01, mass=1.0, origin=(0.0, 0.0, z), structural=spring,
                               shear=spring, name=f"sheet{z}")
    builder.add_self_collision(thickness=0.004)
    return builder.finalize(device)


def test_pair_buffers_grow_before_they_fill(device):
    """Two sheets at rest 6 mm apart (τ = 4 mm: every vertex within the cache's reach of a dozen of the other sheet's
    triangles, none pushed), the buffers sized so that the cache holds ~85 % of its slots: the frame drops no pair,
    and the buffers grow by PAIR_GROWTH after it (fuller than GROW_ABOVE), so that a tightening surface gets room
    before it drops pairs and their repulsion; half full after that, they do not grow again."""
    from warpspring.core.selfcontact import GROW_ABOVE, PAIR_GROWTH
    from warpspring.kernels.selfcontact import CACHE_SLOTS

    probe = _two_sheets(device, 0.006)
    probe.self_contact._allocate(20_000)
    ws.Simulator(probe, fps=60, substeps=4).step_frame()
    cached = int(probe.self_contact.listed()["cache"][0])
    assert 0 < cached < CACHE_SLOTS * 20_000
    slots = math.ceil(cached / (0.85 * CACHE_SLOTS))
    assert cached / (CACHE_SLOTS * slots) > GROW_ABOVE
    model = _two_sheets(device, 0.006)
    contact = model.self_contact
    contact._allocate(slots)
    sim = ws.Simulator(model, fps=60, substeps=4)
    sim.step_frame()
    assert contact.capacity == slots  # the frame's review is read at the next frame, or at a read of the state ...
    sim.settle()
    assert contact.overflow().sum() == 0  # nothing dropped ...
    assert contact.capacity == math.ceil(PAIR_GROWTH * slots)  # ... and room made before it would be
    sim.step_frame()
    sim.settle()
    assert int(contact.listed()["cache"][0]) == cached  # the same pairs, rebuilt into the grown cache
    assert contact.capacity == math.ceil(PAIR_GROWTH * slots)  # under half full now: no further growth


def test_pair_buffers_grow_after_a_frame_that_dropped_pairs(device, monkeypatch):
    """Two 8 × 8 sheets 3 mm apart (τ = 4 mm: every vertex near a dozen of the other sheet's triangles), their pair
    buffers cut to one slot per surface vertex: the first frame drops pairs (counted), the buffers then grow by
    PAIR_GROWTH a frame until none is dropped (5 frames here), and the sheets end no closer than τ/2 with nothing crossed."""
    from warpspring.core import selfcontact

    monkeypatch.setattr(selfcontact, "PAIRS_PER_VERTEX", 1)
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    spring = ws.SpringMaterial(ke=100.0, kd=0.01)
    for z in (0.0, 0.003):
        builder.add_cloth_grid(nx=8, ny=8, spacing=0.01, mass=1.0, origin=(0.0, 0.0, z), structural=spring,
                               shear=spring, name=f"sheet{z}")
    builder.add_self_collision(thickness=0.004)
    model = builder.finalize(device)
    contact = model.self_contact
    initial = contact.capacity
    assert initial == 128  # a slot per surface vertex
    sim = ws.Simulator(model, fps=60, substeps=8)
    dropped, capacity = [], []
    for _ in range(10):
        sim.step_frame()
        dropped.append(int(contact.overflow().sum()))
        capacity.append(contact.capacity)
    assert dropped[0] > 0  # the first frame overflowed, and said so
    assert contact.capacity > initial  # ... and the buffers grew
    # Each frame's review is read at the next frame, which already runs on the buffers it found: a growth takes
    # effect a frame later, and the frame that ran on the old buffers meanwhile asks for none (no two in a row).
    grew = [after > before for before, after in zip([initial] + capacity, capacity)]
    assert not grew[0] and grew[1]
    assert not any(a and b for a, b in zip(grew, grew[1:]))
    # ... and its drops on the replaced buffers ask for none later either: the buffers stop growing once they hold
    # every pair (2048 slots here).
    assert capacity[-3] == capacity[-2] == capacity[-1]
    assert dropped[-1] == dropped[-3]  # none dropped in the last frames: the grown buffers hold every pair
    x = sim.state.particle_q.numpy().astype(np.float64)
    gap = np.abs(x[64:, 2].mean() - x[:64, 2].mean())
    assert gap >= 0.5 * 0.004  # held apart by the floor at least


def raised_thickness_runs(device, *, gap: float, factor: float, closing: float, steps: int, **collision):
    """Two 5 × 5 layers ``gap`` τ apart at rest, one step of 1 ms (the cache built), then τ raised ``factor`` times and
    the layers sent at each other ``closing`` τ (the old τ) a step each, ``steps`` steps more: for the pass with its
    cache and with ``BroadPhaseEveryStep``, ([final positions], [pairs pushed], the cached pass's (cached pairs,
    pairs pushed) after the build)."""
    def layers():
        builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        for z in (0.0, gap * TAU):
            builder.add_cloth_grid(nx=5, ny=5, spacing=0.02, origin=(0.0, 0.0, z), mass=0.05, **CLOTH)
        builder.add_self_collision(thickness=TAU, **collision)
        return builder.finalize(device)

    dt, finals, pushed, built = 1e-3, [], [], None
    for every_step in (False, True):
        model = layers()
        sc = model.self_contact
        if every_step:
            object.__setattr__(model, "self_contact", BroadPhaseEveryStep(sc))
        integrator, a, b = ws.SymplecticEuler(model), model.state(), model.state()
        integrator.step(a, b, None, dt)  # at rest: the cache is built
        a, b = b, a
        if not every_step:
            built = (int(sc.listed()["cache"][0]), int(sc.counts()["pairs"].sum()))
        sc.set(thickness=factor * TAU)
        qd = np.zeros((model.particle_count, 3))
        qd[:25, 2], qd[25:, 2] = closing * TAU / dt, -closing * TAU / dt
        a.particle_qd.assign(qd)
        for _ in range(steps):
            integrator.step(a, b, None, dt)
            a, b = b, a
        finals.append(a.particle_q.numpy())
        pushed.append(int(sc.counts()["pairs"].sum()))
    return finals, pushed, built


def test_a_thickness_raised_mid_run_keeps_the_cached_pairs_in_reach(device):
    """Two layers 2.3 τ apart, their pairs cached at rest (within CACHE_REACH τ, beyond the repulsion's 2τ: the pair
    stages skip them), then τ raised 1.3× (the repulsion's reach now 2.6 of the old τ) and the layers sent at each
    other 0.55 of the old τ a step, within the step test's budget: the cached pairs' least distance is read in units of
    the τ the cache was built with, so the stages run and push. The cached pass gives the broad phase's bits (read in
    the new τ, 2.99 old τ, the stages were skipped and nothing pushed)."""
    finals, pushed, built = raised_thickness_runs(device, gap=2.3, factor=1.3, closing=0.55, steps=2)
    assert built[0] > 0 and built[1] == 0
    np.testing.assert_array_equal(finals[0], finals[1])
    assert pushed[0] > 0 and pushed[0] == pushed[1]


def test_a_thickness_raised_mid_run_keeps_the_cache_honest(device):
    """Two layers 3.2 τ apart (their pairs watched, not cached), the cache built at rest, then τ raised 1.4× and the
    layers sent at each other 1.65 τ a step (γ = 0.49): the pairs outside the cache were CACHE_REACH τ of the τ it was
    built with apart, not of the new τ. The cached pass gives the broad phase's bits at every step and the layers
    stay apart (a bound from the new τ let them cross: the cap read its cache past what it holds)."""
    finals, _, _ = raised_thickness_runs(device, gap=3.2, factor=1.4, closing=1.65, steps=3, relaxation=0.49)
    np.testing.assert_array_equal(finals[0], finals[1])
    z = finals[0][:, 2]
    assert z[25:].min() > z[:25].max()  # the upper layer is still above the lower one
