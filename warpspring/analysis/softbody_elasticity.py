"""How well a soft body's spring network honours Young's modulus: static float64 solves and a modal solve of its
linear stiffness (``core.softbody.stiffness_matrix``) against the closed forms of linear elasticity (small strain,
ν-independent where stated). Each function returns the relative error measured / closed form − 1.

* a cube of side h on frictionless ground under its own weight shortens by ρgh²/(2E) between its bottom and top
  layers (the ground holds the bottom layer's height only; the stress σ_zz = ρg(h − z) is uniaxial for any ν);
* a bar of length L and section A pulled by F at one end (its other end held axially) stretches by FL/(EA)
  and contracts sideways by ν times its strain (:func:`bar_poisson_ratio` returns ν itself);
* a cantilever of length L and square section s (L/s ≥ 10) clamped at one end deflects under its own weight
  q = ρgA by qL⁴/(8EI), I = s⁴/12 (Euler-Bernoulli; shear adds ~(s/L)² relative: Timoshenko's
  qL⁴/(8EI) + qL²/(2κGA), :func:`timoshenko_cantilever`), and rings in its first bending mode at Timoshenko's
  frequency (:func:`cantilever_frequency` against :func:`timoshenko_cantilever`);
* a free bar rings in its first longitudinal mode at f = √(E/ρ)/(2L) (lumped masses);
* a body under a uniform stress σ (tractions σn on its surface, no other load) stores the complementary
  energy ½ V σ:S:σ, S the compliance of the isotropic material (:func:`uniform_stress_compliance`: the
  patch test; linear tetrahedra pass it exactly, a spring network only where its relaxation is affine).

The static and modal checks take the body's stiffness from its spring network (``elasticity="springs"``, the
default) or, for a tetrahedral or Delaunay body built with ``add_soft_body(elasticity="neohookean")``, from the
neo-Hookean tets linearised at rest, which is linear elasticity's stiffness on the same tets
(``elasticity="neohookean"``, :func:`linear_fem_stiffness` of E and ``poisson_ratio``).
"""

from __future__ import annotations

import numpy as np

from ..core import soft_topologies, tet10
from ..core import softbody as sb
from ..kernels.neohookean import stable_lame

G = 9.81  # [m/s²]
#: What carries a tet body's elasticity: its spring network, or the neo-Hookean tet family.
ELASTICITIES = ("springs", "neohookean")


def body_stiffness(topology, *, elasticity: str = "springs", youngs_modulus: float | None = None,
                   poisson_ratio: float = 0.25):
    """The body's linear stiffness at rest, a ``scipy.sparse.csr_matrix`` [3n, 3n] float64: its spring network's
    (``"springs"``) or its tets' neo-Hookean energy linearised at rest (``"neohookean"``: linear elasticity on
    the tets, :func:`linear_fem_stiffness`, which needs E [Pa] and ν; ``tests/test_neohookean.py`` checks the
    family's forces against it)."""
    if elasticity == "springs":
        pairs = np.concatenate([p for p, _ in topology.springs.values()])
        ke = np.concatenate([k for _, k in topology.springs.values()])
        return sb.stiffness_matrix(topology.positions, pairs, ke)
    if elasticity != "neohookean":
        raise ValueError(f"elasticity must be one of {', '.join(ELASTICITIES)}, got {elasticity!r}")
    if getattr(topology, "tets", None) is None or youngs_modulus is None:
        raise ValueError("the neohookean stiffness needs a body with tets (tetrahedral, delaunay) and youngs_modulus")
    if topology.tets.shape[1] == 10:  # quadratic tets (tet10.quadratic_topology): the family's K̃ at rest
        mu, lam = stable_lame(youngs_modulus, poisson_ratio)
        return tet10.tet10_stiffness(topology.positions, topology.positions, topology.tets, mu, lam)
    return linear_fem_stiffness(topology.positions, topology.tets, youngs_modulus=youngs_modulus,
                                poisson_ratio=poisson_ratio)


def box_topology(method: str, size, *, youngs_modulus: float, spacing: float, surface_spacing: float | None = None,
                 element: str = "tet4", **options):
    """The topology of an axis-aligned box of ``size`` (x, y, z) [m] centred at the origin by ``method``. For the
    methods whose particles include the mesh's vertices (all but voxel and tetrahedral) the box's faces are first
    subdivided to edges of about ``surface_spacing`` [m] (default ``spacing``): a box of 8 vertices would be held
    or pulled at its corners only. ``element="tet10"``: the method's tets made quadratic
    (:func:`~warpspring.core.tet10.quadratic_topology`: mid-edge particles, HRZ volume shares)."""
    import trimesh

    box = trimesh.creation.box(size)
    if method not in ("voxel", "tetrahedral"):
        edge = surface_spacing or spacing
        vertices, faces = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=edge * 1.5)
        box = trimesh.Trimesh(vertices, faces, process=True)
    topology = soft_topologies.build_topology(box, method, youngs_modulus=youngs_modulus, spacing=spacing, **options)
    return tet10.quadratic_topology(topology) if element == "tet10" else topology


#: The six tets of a unit cell around its main diagonal (Kuhn's or Freudenthal's subdivision): one per order in which
#: the path from corner (0, 0, 0) to (1, 1, 1) takes the three axes; corners numbered by their bits x + 2y + 4z.
KUHN_TETS = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def lattice_box_topology(size, *, cells: int, element: str = "tet4"):
    """An axis-aligned box of ``size`` (x, y, z) [m] centred at the origin, cut into a lattice of near-cubic cells,
    ``cells`` across its smallest side (each side gets round(side / pitch) cells, pitch = smallest side / ``cells``),
    and each cell into six tets around its main diagonal (:data:`KUHN_TETS`). Every cell is cut the same way, so two
    neighbours split their shared face along the same diagonal: the mesh is conforming, also for T10, and it needs no
    tetrahedraliser (fTetWild's meshes vary between builds and need the optional ``pytetwild``). For the neo-Hookean
    families (:func:`body_stiffness` with ``elasticity="neohookean"``, the bench's models): no springs; each particle
    its volume share (a quarter of each tet's, or the HRZ shares with ``element="tet10"``); the skin is the lattice's
    nodes themselves."""
    size = np.asarray(size, dtype=np.float64)
    counts = np.maximum(np.rint(size / (size.min() / cells)).astype(np.int64), 1)
    axes = [np.linspace(-0.5 * s, 0.5 * s, c + 1) for s, c in zip(size, counts)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    positions = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    node = np.arange(len(positions)).reshape(counts + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(c) for c in counts), indexing="ij"))
    corners = np.stack([node[i + (b & 1), j + ((b >> 1) & 1), k + ((b >> 2) & 1)] for b in range(8)], axis=1)
    tets, volume_t = soft_topologies.wound_tets(positions, corners[:, KUHN_TETS].reshape(-1, 4))
    volume = np.bincount(tets.ravel(), weights=np.repeat(volume_t / 4.0, 4), minlength=len(positions))
    n = len(positions)
    topology = soft_topologies.Topology(
        positions, {}, volume, np.arange(n, dtype=np.int64)[:, None], np.ones((n, 1)),
        "a lattice of cells of six tets each, no springs (for the neo-Hookean families)", tets=tets)
    return tet10.quadratic_topology(topology) if element == "tet10" else topology


def cube_shortening(topology, *, youngs_modulus: float, density: float, elasticity: str = "springs",
                    poisson_ratio: float = 0.25) -> float:
    """Relative error of the cube's shortening under its own weight on frictionless ground (the box of
    ``topology`` must be a cube); ``elasticity``, ``poisson_ratio``: see :func:`body_stiffness`."""
    x = topology.positions
    side = float(np.ptp(x[:, 2]))
    tolerance = 1.0e-6 * side
    bottom, top = x[:, 2] < x[:, 2].min() + tolerance, x[:, 2] > x[:, 2].max() - tolerance
    fixed = np.zeros(x.shape, dtype=bool)
    fixed[bottom, 2] = True
    _hold_rigid_in_plane(fixed, x, np.flatnonzero(bottom), (0, 1))
    force = np.zeros_like(x)
    force[:, 2] = -G * sb.distribute_mass(topology, density * side**3)
    u = sb.static_displacement(topology, force, fixed, stiffness=body_stiffness(
        topology, elasticity=elasticity, youngs_modulus=youngs_modulus, poisson_ratio=poisson_ratio))
    return (u[bottom, 2].mean() - u[top, 2].mean()) / (density * G * side**2 / (2.0 * youngs_modulus)) - 1.0


def bar_stretch(topology, *, youngs_modulus: float, elasticity: str = "springs", poisson_ratio: float = 0.25,
                face_tolerance: float = 1.0e-6) -> float:
    """Relative error of a bar's stretch (the box of ``topology``, long along x) pulled by F at x = max, spread
    over that face by area (a Delaunay triangulation of its particles), its x = min face held axially;
    ``elasticity``, ``poisson_ratio``: see :func:`body_stiffness`. The end faces are the particles within
    ``face_tolerance`` × L of x = min and x = max (fTetWild leaves some within its envelope, ~1e-3 of the box's
    diagonal, off the plane: those are neither held nor pulled at the default)."""
    x, u, left, right, pull = _pulled_bar(topology, body_stiffness(topology, elasticity=elasticity,
                                                                   youngs_modulus=youngs_modulus,
                                                                   poisson_ratio=poisson_ratio), face_tolerance)
    length, side_y, side_z = np.ptp(x, axis=0)
    return (u[right, 0].mean() - u[left, 0].mean()) / (pull * length / (youngs_modulus * side_y * side_z)) - 1.0


def bar_poisson_ratio(topology, *, elasticity: str = "springs", poisson_ratio: float = 0.25) -> float:
    """Poisson's ratio of the pulled bar of :func:`bar_stretch`, −ε_lateral / ε_axial, the strains fitted by least
    squares to the displacements of the particles in its middle third (away from the ends' constraints);
    ``elasticity``, ``poisson_ratio`` (the neo-Hookean material's): see :func:`body_stiffness`."""
    x, u, _, _, _ = _pulled_bar(topology, body_stiffness(topology, elasticity=elasticity, youngs_modulus=1.0,
                                                         poisson_ratio=poisson_ratio))
    span = x[:, 0].max() - x[:, 0].min()
    middle = np.abs(x[:, 0] - x[:, 0].mean()) < span / 6.0
    strain = [np.polyfit(x[middle, k], u[middle, k], 1)[0] for k in range(3)]
    return -0.5 * (strain[1] + strain[2]) / strain[0]


def _pulled_bar(topology, stiffness=None, face_tolerance: float = 1.0e-6):
    """The bar of :func:`bar_stretch` solved (with ``stiffness``, default the springs'): positions, displacements,
    the end faces' masks and the pull [N]."""
    x = topology.positions
    length = float(np.ptp(x[:, 0]))
    tolerance = face_tolerance * length
    left, right = x[:, 0] < x[:, 0].min() + tolerance, x[:, 0] > x[:, 0].max() - tolerance
    fixed = np.zeros(x.shape, dtype=bool)
    fixed[left, 0] = True
    _hold_rigid_in_plane(fixed, x, np.flatnonzero(left), (1, 2))
    pull = 10.0  # [N]
    force = np.zeros_like(x)
    force[right, 0] = pull * face_shares(x[right][:, 1:])
    return x, sb.static_displacement(topology, force, fixed, stiffness=stiffness), left, right, pull


def cantilever_tip(topology, *, youngs_modulus: float, density: float, elasticity: str = "springs",
                   poisson_ratio: float = 0.25, gravity: float = G) -> float:
    """The tip deflection [m] (> 0 downwards; the mean over the tip face's particles) of a cantilever under its own
    weight by a float64 static solve: the box of ``topology``, long along x, clamped (every component held) at
    x = min, gravity ``gravity`` [m/s²] along −z, masses as the builder lumps them; ``elasticity``, ``poisson_ratio``:
    see :func:`body_stiffness`."""
    x = topology.positions
    length, side, _ = np.ptp(x, axis=0)
    tolerance = 1.0e-6 * length
    root, tip = x[:, 0] < x[:, 0].min() + tolerance, x[:, 0] > x[:, 0].max() - tolerance
    fixed = np.zeros(x.shape, dtype=bool)
    fixed[root] = True
    force = np.zeros_like(x)
    force[:, 2] = -gravity * sb.distribute_mass(topology, density * length * side * side)
    u = sb.static_displacement(topology, force, fixed, stiffness=body_stiffness(
        topology, elasticity=elasticity, youngs_modulus=youngs_modulus, poisson_ratio=poisson_ratio))
    return float(-u[tip, 2].mean())


def cantilever_deflection(topology, *, youngs_modulus: float, density: float, elasticity: str = "springs",
                          poisson_ratio: float = 0.25) -> float:
    """Relative error of a cantilever's tip deflection under its own weight (:func:`cantilever_tip`) against
    Euler-Bernoulli's qL⁴/(8EI), q = ρgA, I = s⁴/12 (:func:`timoshenko_cantilever` adds the shear)."""
    length, side, _ = np.ptp(topology.positions, axis=0)
    tip = cantilever_tip(topology, youngs_modulus=youngs_modulus, density=density, elasticity=elasticity,
                         poisson_ratio=poisson_ratio)
    q = density * G * side * side
    return tip / (q * length**4 / (8.0 * youngs_modulus * side**4 / 12.0)) - 1.0


def cantilever_frequency(topology, *, youngs_modulus: float, density: float, elasticity: str = "springs",
                         poisson_ratio: float = 0.25) -> float:
    """The first bending frequency [Hz] along z of the cantilever of :func:`cantilever_tip` (clamped at x = min) by a
    float64 modal solve with the builder's lumped masses. A square section has two bending modes of nearly one
    frequency (along y and z; the tets' layout splits them slightly and the solver returns any two orthogonal
    mixtures): the two lowest modes (the first bending pair; torsion and stretch ring 9× and 15× higher) are combined
    into the one whose tip does not move along y, and its frequency is that mixture's Rayleigh quotient."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    x = topology.positions
    length, side_y, side_z = np.ptp(x, axis=0)
    root = x[:, 0] < x[:, 0].min() + 1.0e-6 * length
    tip = x[:, 0] > x[:, 0].max() - 1.0e-6 * length
    mass = np.repeat(sb.distribute_mass(topology, density * length * side_y * side_z), 3)
    free = np.flatnonzero(~np.repeat(root, 3))
    scale = sp.diags(1.0 / np.sqrt(mass[free]))
    stiffness = body_stiffness(topology, elasticity=elasticity, youngs_modulus=youngs_modulus,
                               poisson_ratio=poisson_ratio).tocsr()[free][:, free]
    omega2, vectors = spla.eigsh((scale @ stiffness @ scale).tocsc(), k=2, sigma=0.0, which="LM")
    shapes = np.zeros((3 * len(x), 2))
    shapes[free] = vectors / np.sqrt(mass[free])[:, None]
    sideways = shapes.reshape(len(x), 3, 2)[tip, 1].mean(axis=0)  # each mode's mean tip motion along y
    mix = np.array([sideways[1], -sideways[0]])
    mix /= np.linalg.norm(mix)
    return float(np.sqrt(mix**2 @ omega2) / (2.0 * np.pi))


def timoshenko_cantilever(*, length: float, side: float, youngs_modulus: float, poisson_ratio: float, density: float,
                          gravity: float = G, elements: int = 2000) -> tuple[float, float]:
    """Timoshenko's beam for a cantilever of square section ``side`` [m]: (tip deflection [m] under its own weight
    along ``gravity`` [m/s²], first bending frequency [Hz]), in float64 by a fine 1-D model (``elements`` linear
    elements of w and the section's rotation ψ, shear by one-point integration, consistent masses ρA and rotary ρI),
    converged as (L/elements)² (2000: ~1e-7 relative). Shear coefficient Cowper's κ = 10(1 + ν)/(12 + 11ν) of a square.
    The tip deflection is the closed form qL⁴/(8EI) + qL²/(2κGA) (the 1-D model reproduces it; a test checks)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    e, nu, rho = float(youngs_modulus), float(poisson_ratio), float(density)
    area, inertia = side * side, side**4 / 12.0
    kappa_ga = 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu) * e / (2.0 * (1.0 + nu)) * area
    h = length / elements
    # element matrices on (w1, ψ1, w2, ψ2)
    bend = e * inertia / h * np.array([[0, 0, 0, 0], [0, 1, 0, -1], [0, 0, 0, 0], [0, -1, 0, 1.0]])
    b = np.array([-1.0 / h, -0.5, 1.0 / h, -0.5])
    k_e = bend + kappa_ga * h * np.outer(b, b)
    m_e = np.zeros((4, 4))
    m_e[np.ix_([0, 2], [0, 2])] = rho * area * h / 6.0 * np.array([[2.0, 1.0], [1.0, 2.0]])
    m_e[np.ix_([1, 3], [1, 3])] = rho * inertia * h / 6.0 * np.array([[2.0, 1.0], [1.0, 2.0]])
    dof = 2 * np.arange(elements)[:, None] + np.arange(4)
    rows, cols = np.repeat(dof, 4, axis=1).ravel(), np.tile(dof, (1, 4)).ravel()
    size = 2 * (elements + 1)
    k = sp.csr_matrix((np.tile(k_e.ravel(), elements), (rows, cols)), shape=(size, size))[2:, 2:].tocsc()
    m = sp.csr_matrix((np.tile(m_e.ravel(), elements), (rows, cols)), shape=(size, size))[2:, 2:].tocsc()
    load = np.zeros(size)
    np.add.at(load, 2 * np.arange(elements), 0.5 * rho * area * gravity * h)
    np.add.at(load, 2 * np.arange(1, elements + 1), 0.5 * rho * area * gravity * h)
    tip = float(spla.spsolve(k, load[2:])[-2])
    omega2 = spla.eigsh(k, k=1, M=m, sigma=0.0, which="LM", return_eigenvectors=False)
    return tip, float(np.sqrt(omega2[0]) / (2.0 * np.pi))


def ring_frequency(topology, *, youngs_modulus: float, density: float, modes: int = 24, elasticity: str = "springs",
                   poisson_ratio: float = 0.25) -> float:
    """Relative error of a free bar's first longitudinal frequency (the box of ``topology``, long along x): of its
    ``modes`` lowest modes (lumped masses, a shift-invert eigensolve), the one closest in shape to cos(πx/L);
    ``elasticity``, ``poisson_ratio``: see :func:`body_stiffness`."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    x = topology.positions
    length, side_y, side_z = np.ptp(x, axis=0)
    mass = sb.distribute_mass(topology, density * length * side_y * side_z)
    scale = sp.diags(np.repeat(1.0 / np.sqrt(mass), 3))
    a = scale @ body_stiffness(topology, elasticity=elasticity, youngs_modulus=youngs_modulus,
                               poisson_ratio=poisson_ratio) @ scale
    shift = -1.0e-6 * a.diagonal().mean()
    omega2, vectors = spla.eigsh(a.tocsc(), k=min(modes, a.shape[0] - 2), sigma=shift, which="LM")
    shapes = (vectors / np.repeat(np.sqrt(mass), 3)[:, None]).reshape(len(x), 3, -1)
    ideal = np.cos(np.pi * (x[:, 0] - x[:, 0].min()) / length)
    weight = mass[:, None] * shapes[:, 0]
    likeness = np.abs(ideal @ weight) / np.sqrt((mass[:, None, None] * shapes**2).sum(axis=(0, 1)) * (mass @ ideal**2))
    best = int(np.argmax(likeness))
    measured = np.sqrt(max(omega2[best], 0.0)) / (2.0 * np.pi)
    return measured / (np.sqrt(youngs_modulus / density) / (2.0 * length)) - 1.0


def face_shares(points_2d: np.ndarray) -> np.ndarray:
    """Each point's share (summing to 1) of a convex planar face's area, by a Delaunay triangulation: a third of
    each of its triangles."""
    from scipy.spatial import Delaunay

    tri = Delaunay(points_2d).simplices
    corner = points_2d[tri]
    d1, d2 = corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0]
    area = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    share = np.bincount(tri.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(points_2d))
    return share / share.sum()


def _hold_rigid_in_plane(fixed: np.ndarray, x: np.ndarray, layer: np.ndarray, axes: tuple) -> None:
    """Hold the in-plane rigid motions of a layer of particles whose normal component is held: both in-plane
    components of the particle nearest the layer's centre, and the second of the one farthest along the first."""
    i, j = axes
    centre = x[layer][:, list(axes)].mean(axis=0)
    a = layer[np.argmin(np.linalg.norm(x[layer][:, list(axes)] - centre, axis=1))]
    b = layer[np.argmax(np.abs(x[layer, i] - x[a, i]) - 10.0 * np.abs(x[layer, j] - x[a, j]))]
    fixed[a, i] = fixed[a, j] = True
    fixed[b, j] = True


STRESS_MODES = ("xx", "yy", "zz", "yz", "xz", "xy")


def uniform_stress_compliance(topology, *, youngs_modulus: float, poisson_ratio: float = 0.25,
                              stiffness=None) -> dict:
    """The patch test of a tetrahedral body: for each of the six unit stress states σ (three uniaxial, three
    pure shears) the body's surface carries the tractions σn (each boundary triangle's σ·a shared equally by
    its corners, a its outward area vector) and nothing holds it but the six rigid motions (a 3-2-1 support,
    which carries no reaction under self-equilibrated loads); the float64 static solve's complementary energy
    ½ fᵀu against the continuum's ½ V σ:S:σ, S of (E, ν). Returns {mode: ratio} (1 = the body is exactly as
    compliant as the material; > 1 softer), modes :data:`STRESS_MODES`.

    Args:
        topology: a body with tetrahedra (``Topology.tets``: the tetrahedral and Delaunay methods).
        stiffness: the [3n, 3n] stiffness to test (default the springs', ``softbody.stiffness_matrix``);
            :func:`linear_fem_stiffness` gives linear elasticity's on the same tets, which passes exactly.
    """
    import scipy.sparse.linalg as spla

    if getattr(topology, "tets", None) is None:
        raise ValueError("uniform_stress_compliance needs a body with tetrahedra (methods tetrahedral, delaunay)")
    x = np.asarray(topology.positions, dtype=np.float64)
    tets = np.asarray(topology.tets)
    if stiffness is None:
        pairs = np.concatenate([p for p, _ in topology.springs.values()])
        ke = np.concatenate([k for _, k in topology.springs.values()])
        stiffness = sb.stiffness_matrix(x, pairs, ke)
    faces, area = boundary_faces(x, tets)
    volume = float(np.abs(soft_topologies.signed_volumes(x, tets)).sum())
    free = np.setdiff1d(np.arange(3 * len(x)), _rigid_support(x))
    solve = spla.splu(stiffness.tocsr()[free][:, free].tocsc()).solve
    e, nu = float(youngs_modulus), float(poisson_ratio)
    ratios = {}
    for name in STRESS_MODES:
        i, j = ("xyz".index(name[0]), "xyz".index(name[1]))
        sigma = np.zeros((3, 3))
        sigma[i, j] = sigma[j, i] = 1.0
        strain = (1.0 + nu) / e * sigma - nu / e * np.trace(sigma) * np.eye(3)
        force = np.zeros((len(x), 3))
        np.add.at(force, faces.ravel(), np.repeat(area @ sigma / 3.0, 3, axis=0))
        f = force.ravel()
        u = np.zeros_like(f)
        u[free] = solve(f[free])
        ratios[name] = float(0.5 * f @ u / (0.5 * volume * np.sum(sigma * strain)))
    return ratios


def linear_fem_stiffness(positions: np.ndarray, tets: np.ndarray, *, youngs_modulus: float,
                         poisson_ratio: float = 0.25):
    """Linear elasticity's stiffness on linear tetrahedra (constant strain per tet, Lamé λ, μ of (E, ν)), a
    ``scipy.sparse.csr_matrix`` [3n, 3n] float64: the reference :func:`uniform_stress_compliance` compares the
    springs with."""
    import scipy.sparse as sp

    e, nu = float(youngs_modulus), float(poisson_ratio)
    lam, mu = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), e / (2.0 * (1.0 + nu))
    x = np.asarray(positions, dtype=np.float64)
    corner = x[tets]
    edges = np.swapaxes(corner[:, 1:] - corner[:, :1], 1, 2)  # [t, 3, 3], columns x_k − x_0
    inverse = np.linalg.inv(edges)
    grad = np.concatenate([-inverse.sum(axis=1, keepdims=True), inverse], axis=1)  # [t, 4, 3]: ∇N_a
    b = np.zeros((len(tets), 6, 12))  # Voigt strain (xx, yy, zz, xy, yz, xz) of the 12 corner displacements
    for a in range(4):
        gx, gy, gz = grad[:, a, 0], grad[:, a, 1], grad[:, a, 2]
        b[:, 0, 3 * a], b[:, 1, 3 * a + 1], b[:, 2, 3 * a + 2] = gx, gy, gz
        b[:, 3, 3 * a], b[:, 3, 3 * a + 1] = gy, gx
        b[:, 4, 3 * a + 1], b[:, 4, 3 * a + 2] = gz, gy
        b[:, 5, 3 * a], b[:, 5, 3 * a + 2] = gz, gx
    c = np.zeros((6, 6))
    c[:3, :3] = lam
    c[np.arange(3), np.arange(3)] += 2.0 * mu
    c[3:, 3:] = mu * np.eye(3)
    element = np.abs(soft_topologies.signed_volumes(x, tets))[:, None, None] * np.einsum("tai,ab,tbj->tij", b, c, b)
    dof = (3 * tets[:, :, None] + np.arange(3)).reshape(len(tets), 12)
    rows, cols = np.repeat(dof, 12, axis=1).ravel(), np.tile(dof, (1, 12)).ravel()
    return sp.csr_matrix((element.ravel(), (rows, cols)), shape=(3 * len(x), 3 * len(x)))


def boundary_faces(positions: np.ndarray, tets: np.ndarray):
    """The faces that belong to one tet only, [f, 3], and their outward area vectors [m²], [f, 3]."""
    faces = np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]])
    opposite = np.concatenate([tets[:, 3], tets[:, 2], tets[:, 1], tets[:, 0]])
    _, inverse, count = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    once = count[inverse.ravel()] == 1
    faces, opposite = faces[once], opposite[once]
    p = positions[faces]
    area = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    inward = np.einsum("ij,ij->i", area, p.mean(axis=1) - positions[opposite]) < 0.0
    area[inward] *= -1.0
    return faces, area


def _rigid_support(x: np.ndarray) -> np.ndarray:
    """Six degrees of freedom whose holding removes exactly the rigid motions (3-2-1): all of the particle
    nearest the centroid, the two components across the line to the farthest particle that vary least along
    it, and the component most normal to the plane through a third particle farthest from that line."""
    a = int(np.argmin(np.linalg.norm(x - x.mean(axis=0), axis=1)))
    d = x - x[a]
    b = int(np.argmax(np.linalg.norm(d, axis=1)))
    axis = d[b] / np.linalg.norm(d[b])
    across = d - np.outer(d @ axis, axis)
    c = int(np.argmax(np.linalg.norm(across, axis=1)))
    normal = np.cross(axis, across[c])
    held = [3 * a, 3 * a + 1, 3 * a + 2, *(3 * b + np.argsort(np.abs(axis))[:2]),
            3 * c + int(np.argmax(np.abs(normal)))]
    return np.asarray(held, dtype=np.int64)
