"""The seven spring topologies of soft bodies from a closed mesh (distributed mass-spring models).

Each method turns a surface mesh (vertices [m], triangles) into particles, groups of springs with their
stiffness from a Young's modulus E [Pa], a volume share per particle (for masses), and an *embedding*
of the surface: every mesh vertex is a fixed combination Σᵢ wᵢ xᵢ of particles with weights summing to 1
that reproduce the rest surface exactly, so the surface as authored follows the simulated body. All are
vectorised NumPy over trimesh (voxels, inside tests, ray casts with rtree) and scipy (k-d trees, Delaunay,
Poisson-disk sampling); the tetrahedral method uses fTetWild through the optional ``pytetwild``
(MPL-2.0; ``pip install warpspring[tet]``).

How E becomes k (small strain; ε the strain tensor, a spring of rest length L along n stretches by
L·(n·ε·n) and stores ½ k L² (n·ε·n)²):

* cubic lattice (voxel, grid) of spacing a — edges k₁, face diagonals k₂, body diagonals k₃, each voxel
  contributing k₁/4 to its 12 edges, k₂/2 to its 12 face diagonals and k₃ to its 4 body diagonals (so
  surface springs get the reduced share). Summing the energies of a homogeneous strain gives the cubic
  constants C₁₁ = (k₁ + 2k₂ + 4k₃/3)/a and C₁₂ = C₄₄ = (k₂ + 4k₃/3)/a: isotropic iff k₁ = k₂ + 8k₃/3, then
  λ = μ, ν = 1/4 and E = 5(k₂ + 4k₃/3)/(2a). Edge + face diagonals (k₃ = 0): k = 2aE/5 (E = 5k/(2a)).
  With body diagonals warpspring takes k₃ = 3k₂/8, k₁ = 2k₂, k₂ = 4aE/15. Edges alone (the grid's 6
  neighbours) have no shear stiffness (C₄₄ = 0): k = aE gives E along the axes only.
  Mass-spring networks of central springs are fixed at ν = 1/4 (Golec et al. 2020).
* tetrahedra: k_e = E·Σ_{t ∋ e} V_t / L_e², a heuristic (Van Gelder 1998 derived its 2-D form; Lloyd,
  Székely & Harders 2007 derive springs from linear FEM and Baudet et al. 2009 show the limits). Under an
  affine strain with edge directions spread evenly it stores E(2 tr ε² + (tr ε)²)/5, the isotropic solid of
  Young's modulus E and ν = 1/4; a real mesh is neither affine (its interior relaxes) nor evenly spread,
  and how well the rule holds depends on the mesh. On fTetWild's tets left at the target edge length the
  error falls with resolution (bar +15 → +7 → +3.5 %, cube +9 → −1 → ±5 % at 2/3/4 and 4/6/8 cells);
  fTetWild's coarsening (``coarsen=True``) leaves larger, less even tets and errors of −13 … +50 % that do not
  fall; a Delaunay lattice of a cube is 17-18 % too stiff at any resolution (``bench/RESULTS.md`` §18).
  Fitting each tet's six springs to its linear-FEM stiffness (ν = 1/4) by least squares (Lloyd et al. 2007,
  the 12×12 matrices in the Frobenius norm) measured worse: +5 … +62 %, with or without coarsening.
* the network methods (brute force, scaffold, shell) and the Delaunay edges use the same volume rule
  k_e = E·V_e/L_e² with Σ_e V_e = 6V (as Σ over a tet mesh's edges of ΣV_t is): brute force, scaffold and
  shell share 6V equally among their springs; the uniform grid's ties and skin edges take their layer's
  volume once (see :func:`grid_topology`). It is a heuristic for networks that are not a partition of
  the volume; how well each honours E is measured (``bench/softbody.py``), not promised.
"""

from __future__ import annotations

import inspect
import math
import os
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from . import memory

#: The seven methods, in the order of the soft-body seed's Table 1.
METHODS = ("brute_force", "voxel", "grid", "scaffold", "shell", "tetrahedral", "delaunay")
#: Methods that fill or offset into the volume: they need a closed (watertight) mesh.
VOLUME_METHODS = ("voxel", "grid", "shell", "tetrahedral", "delaunay")
#: Brute force joins every pair of vertices: above this many vertices it refuses (2,000 vertices already
#: make 1,999,000 springs, a thousand per particle: memory and the stable step both degrade quadratically).
BRUTE_FORCE_LIMIT = 2000
#: Cells of the spacing in the bounding box above which the voxel, grid, tetrahedral and Delaunay methods refuse
#: (a 270³ lattice).
MAX_CELLS = 20_000_000
#: A tetrahedron whose quality 6√2·V / L_rms³ (1 for a regular one) is below this is reported as a sliver.
SLIVER_QUALITY = 0.1
#: Neighbourhoods of a uniform grid: 6 (edges), 18 (+ face diagonals), 26 (+ body diagonals).
GRID_NEIGHBOURS = (6, 18, 26)
SCAFFOLDS = ("centre", "hull", "decimated")


@dataclass(frozen=True)
class SliverReport:
    """The tetrahedra that carry almost no volume (they force a tiny stable step).

    Attributes:
        count: tetrahedra of quality below ``threshold``.
        threshold: the quality 6√2·V / L_rms³ below which a tet counts (1 = regular) [-].
        min_quality: the worst tet's quality [-].
        tet_count: tetrahedra in all.
    """

    count: int
    threshold: float
    min_quality: float
    tet_count: int


@dataclass(frozen=True)
class Topology:
    """What a method makes of a mesh, in the mesh's frame and units (float64, NumPy).

    Attributes:
        positions: rest positions of the particles [m], shape [n, 3].
        springs: spring groups: name -> (pairs of particle indices [s, 2] int64, stiffness ke [N/m] [s]).
        volume: each particle's share of the body's volume [m³], shape [n] (> 0; sums to the body's volume).
        skin_indices: the particles each mesh vertex follows, shape [v, w] int64 (padding: weight 0).
        skin_weights: their weights [-], shape [v, w]; each row sums to 1 and Σ w x reproduces the vertex.
        stiffness_rule: how E was mapped to ke, in words.
        slivers: for tetrahedral bodies, the sliver report; else ``None``.
        tets: the tetrahedra (particle indices [t, 4]) for tetrahedral and Delaunay bodies; else ``None``.
    """

    positions: np.ndarray
    springs: dict
    volume: np.ndarray
    skin_indices: np.ndarray
    skin_weights: np.ndarray
    stiffness_rule: str
    slivers: SliverReport | None = None
    tets: np.ndarray | None = field(default=None, repr=False)

    @property
    def particle_count(self) -> int:
        return len(self.positions)

    @property
    def spring_counts(self) -> dict:
        """Springs per group."""
        return {name: len(pairs) for name, (pairs, _) in self.springs.items()}


# -- entry point ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TopologyEstimate:
    """What a topology will hold and need, estimated from the mesh and the spacing before it is made.

    Attributes:
        particles, springs, tets: the counts (upper estimates).
        host: the host memory [B] making it holds at its peak (beyond what it returns; for the tetrahedral
            method this process's part: fTetWild runs in a child process capped by :func:`run_tetwild`).
    """

    particles: int
    springs: int
    tets: int
    host: int


#: Measured host bytes of making each topology (``bench/memory.py``), per unit of what drives it: the voxel
#: lattice per interior cell C = V/s³ and per surface cell S = A/s² (trimesh's voxelization and inside tests),
#: the grid's ray tests per spring, the tetrahedral post-processing per tet, Delaunay's per sample point,
#: brute force per spring, the shell and scaffold per mesh vertex.
TOPOLOGY_BYTES = {"voxel_cell": 700, "voxel_surface": 11_000, "grid_spring": 4_000, "tet": 850,
                  "delaunay_point": 48_000, "brute_spring": 160, "surface_vertex": 4_000}


def estimate_topology(mesh, method: str, *, spacing: float | None = None, **options) -> TopologyEstimate:
    """Estimate the counts and the host memory of :func:`build_topology` from the mesh's volume, area and vertex
    count and the spacing, before anything is made (counts per cell measured on spheres and boxes: the voxel
    lattice ~1.1 nodes and ~9.5 springs per cell; fTetWild ~6.5–8.5 tets per cell of the target edge; Poisson
    disks ~0.5 samples per cell of their radius, Delaunay ~6.5 tets and ~7.5 edges per point)."""
    if method not in METHODS:
        raise ConfigError(f"unknown soft-body method {method!r}: choose from {', '.join(METHODS)}")
    extent = np.ptp(np.asarray(mesh.vertices, dtype=np.float64), axis=0)
    if spacing is None:
        spacing = float(extent.max()) / 6.0
    if not (math.isfinite(spacing) and spacing > 0.0):
        raise ConfigError(f"soft-body spacing must be a finite length > 0 [m], got {spacing!r}")
    v = len(mesh.vertices)
    volume = abs(float(mesh.volume)) if mesh.is_watertight else float(np.prod(np.maximum(extent, spacing)))
    cells = volume / spacing**3
    surface = float(mesh.area) / spacing**2
    b = TOPOLOGY_BYTES
    if method == "voxel":
        particles, springs, tets = 1.1 * cells + surface, (10 + 4 * bool(options.get("body_diagonals"))) * cells + 5 * surface, 0
        host = b["voxel_cell"] * cells + b["voxel_surface"] * surface
    elif method == "grid":
        particles = 1.1 * cells + v
        neighbours, ties = (x if isinstance(x, (int, float)) else d for x, d in
                            ((options.get("neighbours", 18), 18), (options.get("ties", 4), 4)))
        springs = neighbours / 2 * cells + ties * v
        tets, host = 0, b["grid_spring"] * springs
    elif method == "tetrahedral":
        tets = 9 * cells + 3 * surface
        particles, springs, host = 1.6 * cells + surface, 1.3 * tets, b["tet"] * tets
    elif method == "delaunay":
        points = 0.5 * cells + v
        particles, springs, tets, host = points, 7.5 * points, 6.5 * points, b["delaunay_point"] * points
    elif method == "brute_force":
        particles, springs, tets = v, v * (v - 1) / 2, 0
        host = b["brute_spring"] * springs
    else:  # shell and scaffold: the surface's vertices and a copy or a reduced shape, ~10 springs per vertex
        particles, springs, tets, host = 2 * v, 10 * v, 0, b["surface_vertex"] * v
    return TopologyEstimate(int(particles), int(springs), int(tets), int(host))


def build_topology(mesh, method: str, *, youngs_modulus: float, spacing: float | None = None, source: str = "mesh",
                   **options) -> Topology:
    """The particles, springs and embedding of ``mesh`` by ``method``.

    Args:
        mesh: a ``trimesh.Trimesh`` with merged vertices (one vertex per position).
        method: one of :data:`METHODS`.
        youngs_modulus: E [Pa], > 0.
        spacing: the resolution [m], > 0: voxel pitch, grid spacing, target tet edge length, Poisson-disk
            radius; default a sixth of the mesh's largest extent. Not used by brute force, scaffold, shell.
        source: the mesh's name or file, for messages.
        **options: the method's own options (see each ``*_topology`` function).

    Raises:
        ConfigError: an unknown method or option, a volume method on an open mesh, brute force on too many
            vertices, a missing optional package.
    """
    if method not in METHODS:
        raise ConfigError(f"unknown soft-body method {method!r}: choose from {', '.join(METHODS)}")
    if method in VOLUME_METHODS:
        require_closed(mesh, method, source)
        _require_ray_tests(method)
    if spacing is None:
        spacing = float(np.ptp(mesh.vertices, axis=0).max()) / 6.0
    if not (math.isfinite(spacing) and spacing > 0.0):
        raise ConfigError(f"soft-body spacing must be a finite length > 0 [m], got {spacing!r}")
    if not (math.isfinite(youngs_modulus) and youngs_modulus > 0.0):
        raise ConfigError(f"youngs_modulus must be a finite number > 0 [Pa], got {youngs_modulus!r}")
    cells = float(np.prod(np.ptp(mesh.vertices, axis=0) / spacing + 1.0))
    if method in ("voxel", "grid", "tetrahedral", "delaunay") and cells > MAX_CELLS:
        raise ConfigError(f"{source}: a spacing of {spacing:g} m fills its bounding box with ~{cells:.3g} cells, more "
                          f"than {MAX_CELLS:,} (host memory and build time grow with them): use a larger spacing")
    make, fixed = {
        "brute_force": (brute_force_topology, {"source": source}),
        "voxel": (voxel_topology, {"pitch": spacing}),
        "grid": (grid_topology, {"spacing": spacing}),
        "scaffold": (scaffold_topology, {}),
        "shell": (shell_topology, {}),
        "tetrahedral": (tetrahedral_topology, {"edge_length": spacing}),
        "delaunay": (delaunay_topology, {"radius": spacing}),
    }[method]
    taken = set(inspect.signature(make).parameters) - {"mesh", "youngs_modulus"} - set(fixed)
    unknown = sorted(set(options) - taken)
    if unknown:
        raise ConfigError(f"the {method} method takes no option {unknown[0]!r}; its options: "
                          f"{', '.join(sorted(taken)) or 'none'}")
    return make(mesh, youngs_modulus=youngs_modulus, **fixed, **options)


def require_closed(mesh, method: str, source: str) -> None:
    """Raise a one-line ConfigError unless ``mesh`` is watertight (every edge shared by exactly two faces)."""
    import trimesh  # trimesh loads lazily

    if mesh.is_watertight:
        if not mesh.volume > 0.0:
            raise ConfigError(f"{source}: the mesh is closed but encloses no volume (its faces wind inward, or it is "
                              "flat): fix its winding (trimesh.repair.fix_normals)")
        return
    open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
    raise ConfigError(
        f"{source}: the {method} method fills the volume and needs a closed (watertight) mesh, but it has "
        f"{open_edges} open edge(s) (or edges shared by more than two faces): close it (trimesh.repair.fill_holes) "
        "or use method='brute_force' or 'scaffold'"
    )


#: Points per call of trimesh's inside test (``inside_mesh``): its ray tests build every ray's candidate triangles at
#: once, and without embreex (rtree's path) a 5 mm voxel sphere's 64k centres took 3.5 GB of host memory in one call;
#: 512 at a time it grew 68 MiB (1,024: 130 MiB; 4,096: 478 MiB) in the same 6 s, within the voxel method's estimate.
INSIDE_CHUNK = 512


def inside_mesh(mesh, points: np.ndarray) -> np.ndarray:
    """``mesh.contains(points)`` [bool, shape [n]], asked ``INSIDE_CHUNK`` points at a time so that its memory is
    bounded whichever ray engine trimesh uses."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) <= INSIDE_CHUNK:
        return np.asarray(mesh.contains(points), dtype=bool)
    return np.concatenate([np.asarray(mesh.contains(points[k:k + INSIDE_CHUNK]), dtype=bool)
                           for k in range(0, len(points), INSIDE_CHUNK)])


def _require_ray_tests(method: str) -> None:
    """The volume methods test points inside the mesh and cast rays: trimesh needs embreex or rtree for that."""
    import importlib.util

    if importlib.util.find_spec("embreex") is None and importlib.util.find_spec("rtree") is None:
        raise ConfigError(f"the {method} method casts rays through the mesh, which trimesh does with rtree (or embreex): "
                          "pip install 'warpspring[soft]'")


# -- the seven methods ------------------------------------------------------------------------------------


def brute_force_topology(mesh, *, youngs_modulus: float, source: str = "mesh",
                         max_vertices: int = BRUTE_FORCE_LIMIT) -> Topology:
    """Every vertex a particle, every pair of vertices a spring (n(n−1)/2), stiffness by the volume rule.

    Args:
        max_vertices: refuse above this many vertices (springs grow as n²/2).
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    n = len(vertices)
    if n > max_vertices:
        raise ConfigError(
            f"{source}: brute force joins every pair of its {n} vertices ({n * (n - 1) // 2:,} springs); it refuses "
            f"more than {max_vertices} vertices because springs, memory and the stiffest mode grow as n²: "
            "decimate the mesh or use the voxel or tetrahedral method"
        )
    pairs = np.column_stack(np.triu_indices(n, k=1)).astype(np.int64)
    volume = _body_volume(mesh)
    ke = _volume_rule(youngs_modulus, np.full(len(pairs), 6.0 * volume / len(pairs)), vertices, pairs)
    return Topology(vertices, {"brute": (pairs, ke)}, _area_shares(mesh) * volume / mesh.area,
                    *_identity(n), "volume rule k = E·(6V/S)/L² (heuristic)")


def voxel_topology(mesh, *, pitch: float, youngs_modulus: float, body_diagonals: bool = False) -> Topology:
    """A lattice of the corners of the mesh's voxels (``mesh.voxelized(pitch).fill()``, those whose centre is
    inside, with the mesh's lower bounds on voxel faces: a box of sides that are multiples of the pitch is
    exact).

    Springs along voxel edges and face diagonals (and body diagonals with ``body_diagonals``), each voxel
    adding its share (k₁/4, k₂/2, k₃) so the lattice is isotropic with E = 5(k₂ + 4k₃/3)/(2a), ν = 1/4.
    Each mesh vertex follows the 8 corners of its voxel by trilinear weights. A corner's volume is an
    eighth of each voxel it belongs to.
    """
    from scipy.spatial import cKDTree

    # trimesh centres voxels on multiples of the pitch: shift the mesh so that its lower bounds fall on voxel
    # faces, voxelize and fill it, and keep the voxels whose centre is inside (a surface voxelization keeps
    # every voxel the surface touches, a body up to a voxel too large per side: E would look 1.5× too high
    # at 4 voxels across)
    shift = 0.5 * pitch - mesh.bounds[0]
    shifted = mesh.copy()
    shifted.apply_translation(shift)
    grid = shifted.voxelized(pitch).fill()
    transform = np.asarray(grid.transform, dtype=np.float64)
    if not np.allclose(transform[:3, :3], pitch * np.eye(3), rtol=1e-9, atol=0.0):
        raise ConfigError(f"the voxel grid is not axis-aligned with pitch {pitch} (trimesh returned {transform[:3, :3]})")
    filled = np.argwhere(grid.matrix)  # voxel indices [c, 3]
    filled = filled[inside_mesh(shifted, filled * pitch + transform[:3, 3])]
    if len(filled) == 0:
        raise ConfigError(f"no voxel of pitch {pitch} m has its centre inside the mesh: use a smaller spacing")
    transform[:3, 3] -= shift
    dims = np.asarray(grid.matrix.shape) + 1  # corner lattice
    corner = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)])  # local corner c = dx + 2dy + 4dz
    lattice = filled[:, None, :] + corner[None]  # [c, 8, 3]
    node_ids, local = np.unique(np.ravel_multi_index(lattice.reshape(-1, 3).T, dims), return_inverse=True)
    local = local.reshape(-1, 8)
    nodes = np.column_stack(np.unravel_index(node_ids, dims)).astype(np.float64)
    positions = (nodes - 0.5) * pitch + transform[:3, 3]  # voxel (i, j, k) is centred at T·(i, j, k)

    a = pitch
    if body_diagonals:
        k2 = 4.0 * a * youngs_modulus / 15.0
        k1, k3 = 2.0 * k2, 3.0 * k2 / 8.0
        rule = f"cubic lattice, k₁ = 2k₂, k₃ = 3k₂/8, E = 5(k₂ + 4k₃/3)/(2a): k₂ = 4aE/15 = {k2:.6g} N/m"
    else:
        k1 = k2 = 2.0 * a * youngs_modulus / 5.0
        k3 = 0.0
        rule = f"cubic lattice of edge + face-diagonal springs, E = 5k/(2a): k = 2aE/5 = {k1:.6g} N/m"
    first, second = np.triu_indices(8, k=1)
    bits = np.array([bin(int(i ^ j)).count("1") for i, j in zip(first, second)])
    springs = {}
    for name, order, share in (("edge", 1, k1 / 4.0), ("face_diagonal", 2, k2 / 2.0),
                               ("body_diagonal", 3, k3)):
        if share == 0.0:
            continue
        i, j = first[bits == order], second[bits == order]
        ends = np.sort(np.stack([local[:, i].ravel(), local[:, j].ravel()], axis=1), axis=1)
        pairs, count = np.unique(ends, axis=0, return_counts=True)
        springs[name] = (pairs.astype(np.int64), share * count)
    volume = np.bincount(local.ravel(), minlength=len(positions)) * (a**3 / 8.0)

    # each vertex follows the corners of the filled voxel nearest to it: its own, or one it overhangs by less
    # than half a voxel (then the trilinear weights extrapolate a little, still exactly)
    centres = filled * a + transform[:3, 3]
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    _, voxel = cKDTree(centres).query(vertices)
    t = (vertices - (centres[voxel] - 0.5 * a)) / a  # local coordinates in [0, 1]³
    weights = np.prod(np.where(corner[None] == 1, t[:, None, :], 1.0 - t[:, None, :]), axis=2)
    return Topology(positions, springs, volume, local[voxel].astype(np.int64), weights, rule)


def grid_topology(mesh, *, spacing: float, youngs_modulus: float, neighbours: int = 18, ties: int = 4) -> Topology:
    """Interior nodes of a uniform grid, joined to their 6, 18 or 26 neighbours, plus the mesh vertices as
    particles, each tied to the ``ties`` nearest nodes it reaches without leaving the body.

    No spring crosses the surface: a lattice spring or a tie is kept only if the ray from its node towards its
    other end meets the surface no sooner than that end (:func:`segments_cross`; exact up to the ray engine, so a
    spring that crosses a gap thinner than the spacing between test points is caught) and none of 7 points
    along it lies outside (:func:`springs_leave`). Where the grid cuts a non-convex surface (the inside of a
    bend, a torus's hole) a vertex's nearest nodes may lie across outside space: its ties then go to the nearest
    of its ``max(4·ties, 16)`` nearest nodes that it reaches from inside.

    Lattice springs take the full interior shares of the cubic-lattice rule (18: k = 2aE/5; 26: k₂ = 4aE/15,
    k₁ = 2k₂, k₃ = 3k₂/8; 6: k = aE, no shear stiffness). Ties and the mesh's edges take k = E·V/L² with the
    skin layer's volume (area × a/2) as V, shared among a vertex's ties and by area among the edges, without the
    factor 6 of the isotropic rule (a tie across the layer of thickness t ≈ L is then the layer's E·A/t; with
    the factor the grid bodies measured 30-60 % too stiff); a node's volume is a³, a vertex's its area share × a/2.
    """
    from scipy.spatial import cKDTree

    if neighbours not in GRID_NEIGHBOURS:
        raise ConfigError(f"grid neighbours must be one of {GRID_NEIGHBOURS}, got {neighbours!r}")
    if int(ties) < 1:
        raise ConfigError(f"grid ties must be ≥ 1 (nodes each mesh vertex is sprung to), got {ties!r}")
    a = spacing
    lo, hi = mesh.bounds
    shape = np.maximum(np.floor((hi - lo) / a).astype(np.int64), 1)
    origin = lo + 0.5 * ((hi - lo) - (shape - 1) * a)  # centred: a box of sides n·a gets nodes a/2 inside
    index = np.indices(shape).reshape(3, -1).T
    inside = inside_mesh(mesh, origin + index * a)
    if inside.sum() < 4:
        raise ConfigError(f"a grid of spacing {a} m has {int(inside.sum())} node(s) inside the mesh: use a smaller spacing")
    number = np.full(int(np.prod(shape)), -1, dtype=np.int64)
    number[np.flatnonzero(inside)] = np.arange(inside.sum())
    nodes = origin + index[inside] * a

    offsets = np.array([o for o in np.ndindex(3, 3, 3)]) - 1
    offsets = offsets[[tuple(o) > (0, 0, 0) for o in offsets]]  # one of each ± pair: 13
    order = np.abs(offsets).sum(axis=1)
    if neighbours == 6:
        stiffness = {1: a * youngs_modulus}
        rule = f"grid of edges only, k = aE = {a * youngs_modulus:.6g} N/m (no shear stiffness)"
    elif neighbours == 18:
        k = 2.0 * a * youngs_modulus / 5.0
        stiffness = {1: k, 2: k}
        rule = f"interior cubic lattice, E = 5k/(2a): k = 2aE/5 = {k:.6g} N/m; ties by the volume rule"
    else:
        k2 = 4.0 * a * youngs_modulus / 15.0
        stiffness = {1: 2.0 * k2, 2: k2, 3: 3.0 * k2 / 8.0}
        rule = f"interior cubic lattice, k₁ = 2k₂, k₃ = 3k₂/8: k₂ = 4aE/15 = {k2:.6g} N/m; ties by the volume rule"
    names = {1: "edge", 2: "face_diagonal", 3: "body_diagonal"}
    inner = index[inside]
    n_nodes = len(nodes)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    positions = np.concatenate([nodes, vertices])
    tolerance = 1.0e-9 * float(np.ptp(vertices, axis=0).max())
    # A ray's hit at a tie's vertex may land short of it by the ray engine's rounding (Embree: float32).
    hair = 1.0e-5 * float(np.ptp(vertices, axis=0).max() + np.abs(vertices).max())
    springs = {}
    for o, name in names.items():
        if o not in stiffness:
            continue
        group = []
        for offset in offsets[order == o]:
            other = inner + offset
            ok = ((other >= 0) & (other < shape)).all(axis=1)
            j = np.full(len(inner), -1, dtype=np.int64)
            j[ok] = number[np.ravel_multi_index(other[ok].T, shape)]
            i = np.flatnonzero(j >= 0)
            group.append(np.column_stack([i, j[i]]))
        pairs = np.concatenate(group)
        pairs = pairs[~_leaves(mesh, positions, pairs, tolerance=tolerance, hair=hair)]
        springs[name] = (pairs, np.full(len(pairs), stiffness[o]))

    count = min(int(ties), n_nodes)
    candidates = min(max(4 * count, 16), n_nodes)
    _, nearest = cKDTree(nodes).query(vertices, k=candidates)
    nearest = nearest.reshape(len(vertices), candidates)
    # Each tie as (node, vertex): the ray is cast from the node, inside the body, to the vertex on its surface.
    tie = np.column_stack([nearest.ravel(), np.repeat(n_nodes + np.arange(len(vertices)), candidates)])
    visible = ~_leaves(mesh, positions, tie, tolerance=tolerance, hair=hair).reshape(len(vertices), candidates)
    keep = visible & (np.cumsum(visible, axis=1) <= count)  # the nearest `count` it reaches from inside
    tied = keep.sum(axis=1)
    if (tied == 0).any():
        raise ConfigError(f"mesh vertex {int(np.flatnonzero(tied == 0)[0])} reaches none of its {candidates} nearest "
                          "grid nodes without leaving the body: use a smaller spacing")
    tie = tie[keep.ravel()][:, ::-1]  # (vertex, node)
    skin_volume = _area_shares(mesh) * (0.5 * a)
    tie_volume = skin_volume[tie[:, 0] - n_nodes] / tied[tie[:, 0] - n_nodes]
    springs["tie"] = (tie, _volume_rule(youngs_modulus, tie_volume, positions, tie))
    edges = np.asarray(mesh.edges_unique, dtype=np.int64)
    edge_volume = _edge_area(mesh) * (0.5 * a)
    springs["skin"] = (edges + n_nodes, _volume_rule(youngs_modulus, edge_volume, vertices, edges))
    volume = np.concatenate([np.full(n_nodes, a**3), skin_volume])
    return Topology(positions, springs, volume, *_identity(len(vertices), offset=n_nodes), rule)


def scaffold_topology(mesh, *, youngs_modulus: float, scaffold: str = "centre", scale: float = 0.5,
                      faces: int = 64, ties: int = 3) -> Topology:
    """The mesh's vertices sprung to a reduced shape inside (``scale`` < 1) or outside (> 1) it.

    Args:
        scaffold: ``"centre"`` (one particle at the centroid), ``"hull"`` (the convex hull) or ``"decimated"``
            (the mesh decimated to ``faces`` faces; needs the ``fast-simplification`` package, MIT), scaled by
            ``scale`` about the centroid.
        ties: scaffold vertices each mesh vertex is sprung to (the nearest; 1 for the centre).

    Springs: the mesh's edges ("skin"), the scaffold's edges ("scaffold") and the ties ("tie"), all by the
    volume rule with 6V shared equally. Volumes: each tie's pyramid (vertex area share × length / 3) split
    between its two ends.
    """
    from scipy.spatial import cKDTree

    if scaffold not in SCAFFOLDS:
        raise ConfigError(f"scaffold must be one of {', '.join(SCAFFOLDS)}, got {scaffold!r}")
    if not (math.isfinite(scale) and scale > 0.0 and scale != 1.0):
        raise ConfigError(f"scaffold scale must be > 0 and not 1 (< 1 inside, > 1 outside), got {scale!r}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    centre = vertices.mean(axis=0)
    if scaffold == "centre":
        inner, inner_edges = centre[None], np.zeros((0, 2), np.int64)
    else:
        if scaffold == "hull":
            reduced = mesh.convex_hull
        else:
            try:
                reduced = mesh.simplify_quadric_decimation(face_count=int(faces))
            except ImportError:
                raise ConfigError("scaffold='decimated' needs the fast-simplification package (MIT licence): "
                                  "pip install fast-simplification, or use scaffold='hull' or 'centre'") from None
        inner = centre + scale * (np.asarray(reduced.vertices, dtype=np.float64) - centre)
        inner_edges = np.asarray(reduced.edges_unique, dtype=np.int64)
    n = len(vertices)
    positions = np.concatenate([vertices, inner])
    count = min(int(ties), len(inner))
    _, nearest = cKDTree(inner).query(vertices, k=count)
    tie = np.column_stack([np.repeat(np.arange(n), count), n + nearest.reshape(n, count).ravel()])
    groups = {"skin": np.asarray(mesh.edges_unique, dtype=np.int64), "tie": tie}
    if len(inner_edges):
        groups["scaffold"] = inner_edges + n
    total = sum(len(p) for p in groups.values())
    share = 6.0 * _body_volume(mesh) / total
    springs = {name: (pairs, _volume_rule(youngs_modulus, share, positions, pairs)) for name, pairs in groups.items()}
    length = np.linalg.norm(positions[tie[:, 1]] - positions[tie[:, 0]], axis=1)
    pyramid = _area_shares(mesh)[tie[:, 0]] / count * length / 3.0
    volume = np.bincount(tie.ravel(), weights=np.repeat(0.5 * pyramid, 2), minlength=len(positions))
    return Topology(positions, springs, volume, *_identity(n),
                    f"{scaffold} scaffold, volume rule k = E·(6V/S)/L² (heuristic)")


def shell_topology(mesh, *, youngs_modulus: float, thickness: float | None = None,
                   feature_fraction: float = 0.4) -> Topology:
    """The surface and an inner copy offset along the inward vertex normals, linked by radial springs and
    shear crossings (each mesh edge (a, b) adds a–b' and b–a').

    Args:
        thickness: the offset [m]; default a tenth of the largest extent. At each vertex it is cut to
            ``feature_fraction`` of the local feature size (the distance along the inward normal to the
            opposite side, by a ray cast), so the inner layer never crosses itself or leaves the body.

    Springs (volume rule, 6·(area × offset) shared equally): "skin" (outer edges), "inner" (inner edges),
    "radial", "shear". Volumes: each vertex's area share × offset, half to each layer.
    """
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if thickness is None:
        thickness = 0.1 * float(np.ptp(vertices, axis=0).max())
    if not (math.isfinite(thickness) and thickness > 0.0):
        raise ConfigError(f"shell thickness must be a length > 0 [m], got {thickness!r}")
    if not 0.0 < feature_fraction < 0.5:
        raise ConfigError(f"shell feature_fraction must be in (0, 0.5), got {feature_fraction!r}")
    inward = -np.asarray(mesh.vertex_normals, dtype=np.float64)
    n = len(vertices)
    extent = float(np.ptp(vertices, axis=0).max())
    # Every hit along the inward normal, the nearest one beyond a hair of the start: a ray from a vertex can
    # graze its own triangles (rtree's intersector reports them, Embree's does not), and a zero feature size
    # would collapse the inner layer onto the skin (zero volume, zero mass).
    hair = 1.0e-4 * extent
    locations, ray, _ = mesh.ray.intersects_location(vertices, inward, multiple_hits=True)
    distance = np.einsum("ij,ij->i", locations - vertices[ray], inward[ray])
    far = distance > hair
    feature = np.full(n, np.inf)
    np.minimum.at(feature, ray[far], distance[far])
    offset = np.minimum(thickness, feature_fraction * feature)
    positions = np.concatenate([vertices, vertices + offset[:, None] * inward])
    edges = np.asarray(mesh.edges_unique, dtype=np.int64)
    groups = {
        "skin": edges,
        "inner": edges + n,
        "radial": np.column_stack([np.arange(n), np.arange(n) + n]),
        "shear": np.concatenate([np.column_stack([edges[:, 0], edges[:, 1] + n]),
                                 np.column_stack([edges[:, 1], edges[:, 0] + n])]),
    }
    layer = _area_shares(mesh) * offset
    total = sum(len(p) for p in groups.values())
    share = 6.0 * layer.sum() / total
    springs = {name: (pairs, _volume_rule(youngs_modulus, share, positions, pairs)) for name, pairs in groups.items()}
    return Topology(positions, springs, np.concatenate([0.5 * layer, 0.5 * layer]), *_identity(n),
                    "shell, volume rule k = E·(6V/S)/L² over the shell's volume (heuristic)")


def tetrahedral_topology(mesh, *, edge_length: float, youngs_modulus: float, epsilon: float = 1.0e-3,
                         optimize: bool = True, coarsen: bool = False,
                         sliver_quality: float = SLIVER_QUALITY) -> Topology:
    """A conforming tetrahedralisation by fTetWild (``pytetwild``, MPL-2.0, the optional extra ``tet``).

    fTetWild keeps the boundary within ``epsilon`` × the bounding-box diagonal of the surface, so no tet
    sticks out of a non-convex body (plain Delaunay does). Tet edges are springs with
    k_e = E·Σ_{t ∋ e} V_t / L_e² (a heuristic: see the module's docstring); a particle's volume is a quarter of
    each tet it belongs to; each mesh vertex follows its tet by barycentric weights (affine coordinates of
    the tet nearest to containing it: exact, summing to 1, slightly outside [0, 1] within the envelope).

    Args:
        edge_length: the target edge length [m].
        epsilon: the envelope, relative to the bounding-box diagonal.
        optimize: let fTetWild improve the tets' quality (without it fTetWild's output hardly follows
            ``edge_length`` and keeps slivers of quality ~1e-6).
        coarsen: let fTetWild also coarsen the mesh as far as its quality allows: fewer, larger and less even
            tets than ``edge_length`` asks for, on which the volume rule misses E by −13 … +50 % (module
            docstring); off by default. fTetWild has no seed: its meshes differ slightly from run to run.
        sliver_quality: the quality below which a tet is reported as a sliver.
    """
    try:
        import pytetwild
    except ImportError as exc:
        raise ConfigError("the tetrahedral method needs the optional tetrahedraliser pytetwild (fTetWild, MPL-2.0): "
                          f"pip install 'warpspring[tet]' ({exc})") from None
    del pytetwild  # it runs in the child process
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    positions, tets = run_tetwild(vertices, np.asarray(mesh.faces, dtype=np.int32),
                                  dict(edge_length_abs=float(edge_length), epsilon=float(epsilon), optimize=bool(optimize),
                                       coarsen=bool(optimize and coarsen), num_threads=1, quiet=True),
                                  limit=memory.available_memory(None).host)
    positions = np.asarray(positions, dtype=np.float64)
    tets, volume_t = wound_tets(positions, tets)
    flat = volume_t <= 1.0e-12 * float(np.ptp(positions, axis=0).max()) ** 3
    if flat.any():  # fTetWild without optimisation may leave a few flat tets: no volume, no embedding
        tets, volume_t = tets[~flat], volume_t[~flat]
    pairs, ke = _tet_springs(positions, tets, volume_t, youngs_modulus)
    rule = "tetrahedral edges, k_e = E·ΣV_t/L_e² (volume-weighted heuristic)"
    volume = np.bincount(tets.ravel(), weights=np.repeat(volume_t / 4.0, 4), minlength=len(positions))
    indices, weights = _barycentric_embedding(positions, tets, vertices)
    return Topology(positions, {"tet_edge": (pairs, ke)}, volume, indices, weights, rule,
                    slivers=_slivers(positions, tets, volume_t, sliver_quality), tets=tets)


def run_tetwild(vertices: np.ndarray, faces: np.ndarray, options: dict, *, limit: int | None) -> tuple:
    """``pytetwild.tetrahedralize(vertices, faces, **options)`` in a child process whose address space may grow by
    ``limit`` bytes once pytetwild is loaded (``RLIMIT_AS``; ``None``: uncapped): fTetWild's peak memory cannot be predicted from the
    mesh, so a run that would exhaust the host's memory fails in the child, and is reported in one line, instead
    of taking the machine down. The child (a fresh interpreter running :data:`_TETWILD_CHILD`: numpy and
    pytetwild only) works in a temporary directory, which also takes fTetWild's scratch file
    ("__tracked_surface.stl", written to the working directory).

    Returns:
        (positions [m], shape [p, 3]; tets, shape [t, 4]).

    Raises:
        ConfigError: fTetWild ran out of memory within ``limit``, failed, or its process died.
    """
    import json
    import subprocess
    import sys
    import tempfile

    edge = options.get("edge_length_abs")
    with tempfile.TemporaryDirectory(prefix="warpspring_tet_") as scratch:
        np.savez(os.path.join(scratch, "in.npz"), vertices=np.asarray(vertices, dtype=np.float64),
                 faces=np.asarray(faces, dtype=np.int32))
        done = subprocess.run([sys.executable, "-c", _TETWILD_CHILD, scratch, str(int(limit or 0)), json.dumps(options)],
                              cwd=scratch, capture_output=True, text=True)
        if done.returncode == 0:
            with np.load(os.path.join(scratch, "out.npz")) as out:
                return out["positions"], out["tets"]
    cap = f"the available host memory, {memory.format_bytes(limit)}" if limit else "no limit"
    said = [line for line in done.stderr.splitlines() if line.strip()]
    if done.returncode in (_TETWILD_OUT_OF_MEMORY, -6, 134) or "bad_alloc" in done.stderr:
        raise ConfigError(f"fTetWild ran out of memory tetrahedralizing {len(faces):,} triangles at edge length "
                          f"{edge:g} m (its process was limited to {cap}): use a larger spacing")
    raise ConfigError(f"fTetWild failed at edge length {edge:g} m (exit code {done.returncode}"
                      f"{': ' + said[-1][:300] if said else ''}; its process was limited to {cap})")


#: The exit code of :data:`_TETWILD_CHILD` when fTetWild runs out of memory (a MemoryError).
_TETWILD_OUT_OF_MEMORY = 3
#: The child of :func:`run_tetwild`: cap the address space, read the surface, tetrahedralize in the working
#: directory, write the result (arguments: the directory, the limit in bytes or 0, the options as JSON).
_TETWILD_CHILD = f"""
import json, resource, sys
import numpy as np
import pytetwild
folder, limit, options = sys.argv[1], int(sys.argv[2]), json.loads(sys.argv[3])
if limit:  # the cap counts what fTetWild allocates: its code and the interpreter's are mapped already
    try:
        with open("/proc/self/status") as status:
            mapped = next((int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:")), 0)
    except OSError:  # not Linux: the interpreter's own mapping is not known, the cap counts it
        mapped = 0
    hard = resource.getrlimit(resource.RLIMIT_AS)[1]
    cap = mapped + limit
    resource.setrlimit(resource.RLIMIT_AS, (cap if hard == resource.RLIM_INFINITY else min(cap, hard), hard))
surface = np.load(folder + "/in.npz")
try:
    positions, tets = pytetwild.tetrahedralize(surface["vertices"], surface["faces"], **options)
    np.savez(folder + "/out.npz", positions=np.asarray(positions, dtype=np.float64), tets=np.asarray(tets))
except MemoryError:
    sys.exit({_TETWILD_OUT_OF_MEMORY})
"""


def delaunay_topology(mesh, *, radius: float, youngs_modulus: float, seed: int = 0) -> Topology:
    """The mesh's vertices plus Poisson-disk samples inside it (``scipy.stats.qmc.PoissonDisk``, at least
    ``radius`` apart and half a radius from the surface), their Delaunay tetrahedra whose centroids lie
    inside, and those tets' edges that stay inside the body as springs (k_e = E·ΣV_t/L_e² over the kept
    tets). A particle's volume is a quarter of each kept tet it belongs to.
    """
    from scipy.spatial import Delaunay
    from scipy.stats import qmc

    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = mesh.bounds
    size = float((hi - lo).max())
    samples = qmc.PoissonDisk(d=3, radius=radius, l_bounds=lo, u_bounds=hi, ncandidates=10, seed=seed).fill_space()
    samples = samples[inside_mesh(mesh, samples)]
    if len(samples):
        samples = samples[mesh.nearest.signed_distance(samples) > 0.5 * radius]
    positions = np.concatenate([vertices, samples])
    tets = np.asarray(Delaunay(positions).simplices, dtype=np.int64)
    tets = tets[inside_mesh(mesh, positions[tets].mean(axis=1))]
    volume_t = signed_volumes(positions, tets)
    keep = np.abs(volume_t) > 1.0e-12 * size**3
    tets, volume_t = tets[keep], np.abs(volume_t[keep])
    pairs, ke = _tet_springs(positions, tets, volume_t, youngs_modulus)
    inside = ~springs_leave(mesh, positions, pairs, tolerance=1.0e-9 * size)
    volume = np.bincount(tets.ravel(), weights=np.repeat(volume_t / 4.0, 4), minlength=len(positions))
    lonely = np.flatnonzero(volume <= 0.0)
    if len(lonely):
        raise ConfigError(f"Delaunay: vertex {int(lonely[0])} of the mesh is in no tetrahedron inside the body "
                          "(a mesh too thin for its vertices): use a smaller radius or the tetrahedral method")
    return Topology(positions, {"delaunay_edge": (pairs[inside], ke[inside])}, volume, *_identity(len(vertices)),
                    "Delaunay edges inside the body, k_e = E·ΣV_t/L_e² (heuristic)", tets=tets)


# -- geometry helpers ----------------------------------------------------------------------------------------


def springs_leave(mesh, positions: np.ndarray, pairs: np.ndarray, *, tolerance: float, samples: int = 7) -> np.ndarray:
    """Which springs leave the body: a point at t = 1/8 … 7/8 along the spring lies outside ``mesh`` by more
    than ``tolerance`` [m]. Shape [s], bool."""
    if len(pairs) == 0:
        return np.zeros(0, dtype=bool)
    t = np.arange(1, samples + 1) / (samples + 1)
    a, b = positions[pairs[:, 0]], positions[pairs[:, 1]]
    points = (a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]).reshape(-1, 3)
    outside = ~inside_mesh(mesh, points)
    if outside.any():
        where = np.flatnonzero(outside)
        _, distance, _ = mesh.nearest.on_surface(points[where])
        outside[where] = distance > tolerance
    return outside.reshape(len(pairs), samples).any(axis=1)


def segments_cross(mesh, starts: np.ndarray, ends: np.ndarray, *, hair: float) -> np.ndarray:
    """Which segments from ``starts`` (inside the body) to ``ends`` (inside or on its surface) cross the
    surface: the first hit of the ray from the start towards the end lies more than ``hair`` [m] short of the
    end. A segment from inside that passes outside, or ends outside, must cross the surface before its end, so
    this holds however thin the outside space it passes; a vertex's own faces (hit at the end) do not count.
    Positions [m], shape [s, 3]; returns shape [s], bool."""
    cross = np.zeros(len(starts), dtype=bool)
    if len(starts) == 0:
        return cross
    d = ends - starts
    length = np.linalg.norm(d, axis=1)
    locations, ray, _ = mesh.ray.intersects_location(starts, d / length[:, None], multiple_hits=False)
    distance = np.linalg.norm(locations - starts[ray], axis=1)
    cross[ray[distance < length[ray] - hair]] = True
    return cross


def _leaves(mesh, positions: np.ndarray, pairs: np.ndarray, *, tolerance: float, hair: float) -> np.ndarray:
    """Springs (first end inside the body) that cross the surface by the ray test or leave it at a test point."""
    crossing = segments_cross(mesh, positions[pairs[:, 0]], positions[pairs[:, 1]], hair=hair)
    return crossing | springs_leave(mesh, positions, pairs, tolerance=tolerance)


def _identity(n: int, *, offset: int = 0):
    """The embedding of a surface whose vertices are particles offset .. offset + n - 1."""
    return (np.arange(offset, offset + n, dtype=np.int64)[:, None], np.ones((n, 1)))


def _volume_rule(youngs_modulus: float, volume, positions: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(positions[pairs[:, 1]] - positions[pairs[:, 0]], axis=1)
    if (length <= 0.0).any():
        raise ConfigError("two particles of the soft body coincide: a spring of zero length (a degenerate mesh)")
    return youngs_modulus * np.broadcast_to(volume, length.shape) / length**2


def _body_volume(mesh) -> float:
    volume = float(mesh.volume) if mesh.is_watertight else float(mesh.convex_hull.volume)
    if not volume > 0.0:
        raise ConfigError("the mesh encloses no volume (flat or inside out): fix its winding (trimesh.repair.fix_normals)")
    return volume


def _area_shares(mesh) -> np.ndarray:
    """A third of each incident triangle's area per vertex [m²]."""
    return np.bincount(np.asarray(mesh.faces).ravel(), weights=np.repeat(mesh.area_faces / 3.0, 3),
                       minlength=len(mesh.vertices))


def _edge_area(mesh) -> np.ndarray:
    """A third of each adjacent triangle's area per unique edge [m²]."""
    return np.bincount(mesh.edges_unique_inverse, weights=np.repeat(mesh.area_faces / 3.0, 3),
                       minlength=len(mesh.edges_unique))


def signed_volumes(positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes V [m³] of tets, (x1 - x0)·((x2 - x0) × (x3 - x0))/6, float64, shape [..., t] for positions
    [..., n, 3] and tets [t, 4]."""
    p = np.asarray(positions, dtype=np.float64)[..., np.asarray(tets, dtype=np.int64), :]
    e1, e2, e3 = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :], p[..., 3, :] - p[..., 0, :]
    return np.einsum("...i,...i->...", e1, np.cross(e2, e3)) / 6.0


def wound_tets(positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A copy of ``tets`` (int64 [t, 4]) with each tet whose signed volume at ``positions`` [m] is negative
    rewound (its first two corners swapped), and the tets' volumes |V| [m³], float64 [t]."""
    tets = np.array(tets, dtype=np.int64).reshape(-1, 4)
    volume = signed_volumes(positions, tets)
    flip = volume < 0.0
    tets[flip] = tets[flip][:, [1, 0, 2, 3]]
    return tets, np.abs(volume)



_TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])


def _tet_springs(positions: np.ndarray, tets: np.ndarray, volume_t: np.ndarray, youngs_modulus: float):
    """Unique tet edges [s, 2] and k_e = E·Σ_{t ∋ e} V_t / L_e² [N/m]."""
    ends = np.sort(tets[:, _TET_EDGES].reshape(-1, 2), axis=1)
    pairs, inverse = np.unique(ends, axis=0, return_inverse=True)
    summed = np.bincount(inverse.ravel(), weights=np.repeat(volume_t, 6), minlength=len(pairs))
    return pairs, _volume_rule(youngs_modulus, summed, positions, pairs)


def _slivers(positions: np.ndarray, tets: np.ndarray, volume_t: np.ndarray, threshold: float) -> SliverReport:
    p = positions[tets]
    edges = p[:, _TET_EDGES[:, 1]] - p[:, _TET_EDGES[:, 0]]
    rms = np.sqrt((edges**2).sum(axis=2).mean(axis=1))
    quality = 6.0 * math.sqrt(2.0) * volume_t / rms**3
    return SliverReport(count=int((quality < threshold).sum()), threshold=float(threshold),
                        min_quality=float(quality.min()) if len(quality) else 1.0, tet_count=len(tets))


def _barycentric_embedding(positions: np.ndarray, tets: np.ndarray, points: np.ndarray, candidates: int = 16):
    """Per point, the tet (of the ``candidates`` with nearest centroids) it lies deepest inside, and its
    barycentric coordinates there: indices [p, 4], weights [p, 4] (exact affine coordinates)."""
    from scipy.spatial import cKDTree

    k = min(candidates, len(tets))
    _, near = cKDTree(positions[tets].mean(axis=1)).query(points, k=k)
    near = near.reshape(len(points), k)
    corners = positions[tets[near]]  # [p, k, 4, 3]
    basis = np.swapaxes(corners[:, :, 1:] - corners[:, :, :1], -1, -2)  # [p, k, 3, 3], columns x_i - x_0
    local = np.linalg.solve(basis, (points[:, None, :] - corners[:, :, 0])[..., None])[..., 0]
    bary = np.concatenate([1.0 - local.sum(axis=2, keepdims=True), local], axis=2)  # [p, k, 4]
    best = np.argmax(bary.min(axis=2), axis=1)
    rows = np.arange(len(points))
    return tets[near[rows, best]], bary[rows, best]
