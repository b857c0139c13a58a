"""The float64 audits (``warpspring/analysis/audit.py``) against constructed crossings whose answers are known in
closed form: each kind found at its time, and the near misses that a sampled audit would confuse with a crossing
not reported."""

import numpy as np
import pytest

import warpspring as ws
from warpspring.analysis.audit import (
    SubstepAudit,
    SurfaceAudit,
    audit_frame,
    audit_motion,
    surface_edges,
)
from warpspring.errors import ConfigError

TAU = 0.01  # [m]: the thickness the constructed states are audited against

# Two triangles sharing no vertex: 0 lies in the plane y = 0 below the x axis, 1 in the plane x = 0 above
# z = h; moving 1 down by 2h sweeps its lower edge (0, ±1, z) through 0's upper edge (the x axis) at t = 1/2,
# while no vertex ever reaches the other triangle's plane inside it.
H = 0.1
CROSSED = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0],
                    [0.0, -1.0, H], [0.0, 1.0, H], [0.0, 0.0, 1.0 + H]])
PAIR = np.array([[0, 1, 2], [3, 4, 5]])


def lowered(x, dz, rows=slice(3, 6)):
    y = x.copy()
    y[rows, 2] -= dz
    return y


def edge_index(a, b):
    edges = surface_edges(PAIR)
    return int(np.flatnonzero((edges[:, 0] == min(a, b)) & (edges[:, 1] == max(a, b)))[0])


def test_edge_edge_pass_through_is_found_at_its_time():
    """Edge 3-4 passes through edge 0-1 at t = 1/2 exactly: one edge–edge crossing, between those two edges, at
    t = 0.5 to the CCD's time tolerance, and at the step's end edge 3-4 pierces triangle 0 (and 0-1 triangle 1)."""
    found = SurfaceAudit(PAIR).step(CROSSED, lowered(CROSSED, 2 * H), thickness=TAU)
    assert found.crossings.tolist() == [[1, edge_index(0, 1), edge_index(3, 4)]]
    assert found.time[0] == pytest.approx(0.5, abs=1e-3)  # TI-CCD's root is conservative: at or just before t
    assert sorted(map(tuple, found.intersections.tolist())) == sorted([(edge_index(3, 4), 0), (edge_index(0, 1), 1)])


def test_vertex_triangle_pass_through_is_found_at_its_time():
    """A vertex 0.1 above a triangle's interior moving 0.3 down crosses it at t = 1/3; its two edges pierce
    the triangle afterwards."""
    triangles = np.array([[0, 1, 2], [3, 4, 5]])
    x0 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 0.1], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]], float)
    x1 = x0.copy()
    x1[3, 2] = -0.2
    found = SurfaceAudit(triangles).step(x0, x1, thickness=TAU)
    assert found.crossings.tolist() == [[0, 3, 0]]
    assert found.time[0] == pytest.approx(1.0 / 3.0, abs=1e-3)
    assert len(found.intersections) == 2  # edges 3-4 and 3-5 through triangle 0
    assert audit_motion(x0, x1, triangles).touches.tolist() == [[0, 3, 0]]  # the one-call form agrees


def test_touches_any_agrees_with_the_listed_touches():
    """The early-stopping form (``SurfaceAudit.touches_any``): the vertex's pass through the triangle touches, the
    same vertex stopping 1e-4 above it does not, as :meth:`motion` lists them."""
    triangles = np.array([[0, 1, 2], [3, 4, 5]])
    x0 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 0.1], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]], float)
    through, short = x0.copy(), x0.copy()
    through[3, 2], short[3, 2] = -0.2, 1e-4
    audit = SurfaceAudit(triangles)
    assert audit.touches_any(x0, through) and len(audit.motion(x0, through).touches) == 1
    assert not audit.touches_any(x0, short) and len(audit.motion(x0, short).touches) == 0


def test_static_intersection_is_found_without_motion():
    """Two triangles already through each other (triangle 1 lowered by 2h before the step) and a step that does
    not move: no crossing happens during it, but the end state's intersections are found."""
    through = lowered(CROSSED, 2 * H)
    found = SurfaceAudit(PAIR).step(through, through, thickness=TAU)
    assert len(found.crossings) == 0
    assert len(found.intersections) == 2
    assert not found.clean


def test_near_pair_is_found_and_a_near_miss_is_not_a_crossing():
    """A vertex ending 0.4 τ above a triangle is one pair closer than τ/2 (and no crossing); a vertex sweeping
    across the triangle's plane just outside its edge (missing it by 1e-4 m, far less than the step's travel of
    0.3 m: at both ends it is on different sides of the plane, which a sampled audit would take for a crossing)
    is neither a crossing nor an intersection; nor is an edge sweeping 1e-4 m past another's end."""
    triangles = np.array([[0, 1, 2], [3, 4, 5]])
    x0 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 0.1], [0.3, 0.2, 0.5], [0.2, 0.3, 0.5]], float)
    near = x0.copy()
    near[3, 2] = 0.4 * TAU
    found = SurfaceAudit(triangles).step(x0, near, thickness=TAU)
    assert len(found.crossings) == 0 and len(found.intersections) == 0
    assert found.close == 1 and found.min_distance == pytest.approx(0.4 * TAU, rel=1e-9)
    # The vertex passes below the triangle's edge y = 0 (at y = -1e-4) from z = +0.15 to z = -0.15.
    x0[3] = (0.2, -1e-4, 0.15)
    x0[4:] = ((0.3, -0.3, 0.5), (0.2, -0.3, 0.55))
    miss = x0.copy()
    miss[3, 2] = -0.15
    found = SurfaceAudit(triangles).step(x0, miss, thickness=TAU)
    assert len(found.crossings) == 0 and len(found.intersections) == 0 and found.close == 0
    # The crossed pair's motion with triangle 1 in the plane x = 1 + 1e-4: its lower edge sweeps down past the
    # end (1, 0, 0) of edge 0-1, 1e-4 m beside it at t = 1/2.
    beside = CROSSED.copy()
    beside[3:, 0] += 1.0 + 1e-4
    found = SurfaceAudit(PAIR).step(beside, lowered(beside, 2 * H), thickness=TAU)
    assert len(found.crossings) == 0 and len(found.intersections) == 0
    assert found.close == 1  # vertex (1, 0, 0) ends 1e-4 m beside triangle 1: near, not through
    assert audit_frame(lowered(beside, H), PAIR).min_edge_edge == pytest.approx(1e-4, rel=1e-6)


def test_rows_index_the_surface_not_the_particles():
    """A surface whose vertices are not the first particles (interior points before and between): the rows
    name the particles and triangles as given."""
    x0 = np.vstack([np.full((2, 3), 5.0), CROSSED[:3], np.full((1, 3), -5.0), CROSSED[3:]])
    triangles = np.array([[2, 3, 4], [6, 7, 8]])
    x1 = x0.copy()
    x1[6:, 2] -= 0.2
    x1[5] = (0.0, 0.0, 0.0)  # an interior point moving through triangle 0 is no vertex of the surface: not audited
    found = SurfaceAudit(triangles).step(x0, x1, thickness=TAU)
    edges = surface_edges(triangles)
    named = [tuple(edges[e]) for e in found.crossings[0, 1:]]
    assert found.crossings[:, 0].tolist() == [1] and named == [(2, 3), (6, 7)]


def _thrown(device, *, self_collision: bool, frames: int = 1, workers: int = 1) -> SubstepAudit:
    """Two 3 × 3 cloths, the upper tilted by 0.1 rad with its lowest edge 8.5 mm above the lower one, thrown down
    at 3 m/s through the pinned lower one, every substep audited (τ = 4 mm)."""
    builder = ws.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    springs = dict(structural=ws.SpringMaterial(10.0, 0.0), shear=False, bend=False)
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.02, origin=(0.0, 0.0, 0.0), mass=0.1, pin=["left", "right"],
                           name="lower", **springs)
    tilt = (np.sin(0.05), 0.0, 0.0, np.cos(0.05))  # 0.1 rad about x: no edge parallel to the lower cloth's
    builder.add_cloth_grid(nx=3, ny=3, spacing=0.02, origin=(0.005, 0.003, 0.0085), rotation=tilt, mass=0.1,
                           velocity=(0.0, 0.0, -3.0), name="upper", **springs)
    if self_collision:
        builder.add_self_collision(thickness=0.004)
    model = builder.finalize(device)
    sim = ws.Simulator(model, fps=60, substeps=10)
    audit = SubstepAudit(thickness=0.004, workers=workers).attach(sim)
    try:
        for _ in range(frames):
            sim.step_frame()
    finally:
        audit.close_workers()
    return audit


def test_substep_audit_of_a_run(device):
    """The thrown cloth with no self-collision: the run's substep audit finds the crossings, in the substep where
    they begin (5 mm per substep at 60 fps × 10 substeps: the lowest edge reaches the lower cloth in the second
    substep, t ≤ 2/600 s); with self-collision (τ = 4 mm) the same throw audits clean over every substep."""
    crossed = _thrown(device, self_collision=False)
    assert crossed.substeps == 10 and crossed.crossings > 0
    assert crossed.first[0] == pytest.approx(2 / 600, rel=1e-9)  # the end of the substep that crossed
    assert "crossing" in crossed.first[2]
    kept = _thrown(device, self_collision=True)
    assert kept.substeps == 10 and kept.clean and kept.min_distance >= 0.002
    assert "0 crossings" in kept.line()


def test_audit_workers_find_what_one_process_finds(device):
    """Two frames of the thrown cloth without self-collision, each frame's 10 substeps split between 3 worker
    processes: the same crossings, intersections, close pairs, smallest distance and first finding (its substep
    and world) as the audit in one process. Bad worker counts are refused."""
    one = _thrown(device, self_collision=False, frames=2)
    three = _thrown(device, self_collision=False, frames=2, workers=3)
    assert one.crossings > 0 and one.intersections > 0 and one.close > 0  # every tally has something to agree on
    fields = ("substeps", "crossings", "intersections", "close", "min_distance", "first")
    assert [getattr(three, f) for f in fields] == [getattr(one, f) for f in fields]
    with pytest.raises(ConfigError, match="workers must be a whole number"):
        SubstepAudit(workers=0)


SCENE = """
version = 2
[simulation]
fps = 60
frames = 2
substeps = 10
[world]
gravity = [0.0, 0.0, 0.0]
[[cloth]]
name = "{name}"
grid = {{ nx = 3, ny = 3, spacing = 0.02 }}
origin = [0.0, 0.0, 0.0]
mass = 0.1
pin = ["left", "right"]
structural = {{ ke = 10.0, kd = 0.0 }}
shear = false
bend = false
[[cloth]]
name = "upper"
grid = {{ nx = 3, ny = 3, spacing = 0.02 }}
origin = [0.005, 0.003, 0.0085]
rotation = {{ axis = [1.0, 0.0, 0.0], degrees = 5.729578 }}
velocity = [0.0, 0.0, -3.0]
mass = 0.1
structural = {{ ke = 10.0, kd = 0.0 }}
shear = false
bend = false
{self_collision}
"""


def _run_audited(tmp_path, capsys, *, self_collision: bool, options=()) -> tuple[int, str]:
    """``warpspring run --audit-substeps`` of the thrown cloth's scene file: (exit status, the audit's line)."""
    from warpspring.app.cli import main

    table = "[self_collision]\nthickness = 0.004\n" if self_collision else ""
    scene = tmp_path / "thrown.toml"
    scene.write_text(SCENE.format(name="lower", self_collision=table))
    status = main(["run", str(scene), "-o", str(tmp_path / "out.usdc"), "--device", "cpu", "-q", "--audit-substeps",
                   *options])
    out = capsys.readouterr().out
    return status, next(row for row in out.splitlines() if row.startswith("substep audit:"))


@pytest.mark.parametrize("self_collision", [False, True])
def test_run_option_audits_every_substep(tmp_path, capsys, self_collision):
    """``warpspring run --audit-substeps``: the thrown cloth of the run test from a scene file, 2 frames of 10
    substeps: without self-collision it prints the crossings and exits with EXIT_AUDIT; with it (τ = 4 mm) it
    prints a clean audit of the 20 substeps and exits 0."""
    from warpspring.app.cli import EXIT_AUDIT

    status, line = _run_audited(tmp_path, capsys, self_collision=self_collision)
    assert "20 substeps" in line
    if self_collision:
        assert status == 0 and "0 crossings, 0 intersections, 0 pairs closer" in line
    else:
        assert status == EXIT_AUDIT and "0 crossings" not in line and "first at t = " in line


def test_run_option_audit_workers_print_the_same_line(tmp_path, capsys):
    """``--audit-workers 2`` beside ``--audit-substeps``: the crossing run's audit line and exit status as with one
    process; without ``--audit-substeps`` the option is refused with what to add."""
    from warpspring.app.cli import EXIT_CONFIG, main

    one = _run_audited(tmp_path, capsys, self_collision=False)
    two = _run_audited(tmp_path, capsys, self_collision=False, options=["--audit-workers", "2"])
    assert two == one and "first at t = " in one[1]
    status = main(["run", str(tmp_path / "thrown.toml"), "-o", str(tmp_path / "out.usdc"), "--device", "cpu", "-q",
                   "--audit-workers", "2"])
    assert status == EXIT_CONFIG and "add --audit-substeps" in capsys.readouterr().err
