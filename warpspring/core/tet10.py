"""Quadratic (10-node) neo-Hookean tetrahedra on the host: a tetrahedral body's elasticity carried by T10 elements,
whose displacement is quadratic in each tet, so that a body bends right at a few elements across its thickness
where the linear tets lock (``bench/results/softbody_tet10.md``: a cantilever at 3 tets across is 18 % too stiff
with linear tets, within 1 % with these). ``kernels/tet10.py`` has the element's maths and its hooks; this module
has the mesh (mid-edge nodes made from a linear tet mesh), the lumped masses, the skin, the family
(:class:`QuadraticTetFamily`) and float64 references of its energy, forces and stiffness for the tests and the
static and modal checks.

**Nodes.** A T10 is a linear tet (corners 0..3) plus a node at the middle of each edge, in the order of
:data:`EDGES`: 4 = (0, 1), 5 = (0, 2), 6 = (0, 3), 7 = (1, 2), 8 = (1, 3), 9 = (2, 3). :func:`quadratic_tets` makes
them from a linear mesh, one node per edge shared by the tets around it (the field stays continuous). Elements are
straight-sided (the mid-edge nodes start at the edges' middles), so the rest map is affine and the shape functions'
gradients are the linear tet's G_a (rows of D_m⁻¹) times barycentric weights:
∇N_a = (4L_a − 1) G_a at a corner, ∇N_ab = 4 (L_a G_b + L_b G_a) at edge (a, b).

**Quadrature.** Four Gauss points (barycentric (α, β, β, β) and its permutations, α = (5 + 3√5)/20, weight ¼ each):
exact for polynomials of degree 2, so the stiffness at rest (∇N ⊗ ∇N, degree 2) is integrated exactly: it is
linear elasticity's T10 stiffness (``tests/test_tet10.py``).

**Masses (lumped).** The consistent mass's row sums give a T10's corners −1/20 of its mass each (and its mid-edge
nodes 1/5): a lumped mass can not be made that way. The HRZ lumping (Hinton, Rock & Zienkiewicz 1976) scales the
consistent matrix's diagonal (6/420 and 32/420 of the tet's mass) to the tet's mass: 1/36 of it at each corner and
4/27 at each mid-edge node, positive and exact for rigid translation (:data:`CORNER_SHARE`, :data:`EDGE_SHARE`).

**Skin.** Each vertex of the authored mesh follows the quadratic field of the tet it lies in: its weights are the ten
shape functions at its barycentric coordinates (they sum to 1 and reproduce the vertex at rest), so the surface
bends with the elements instead of following their corners' chords.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.neohookean import stable_lame
from ..kernels.precision import mat33_type
from ..kernels.tet10 import (
    QUADRATURE_ALPHA,
    QUADRATURE_BETA,
    Tet10Spec,
    tet10_arrays_type,
    vec10i,
)
from .families import incidence_bytes
from .neohookean import poisson, write_elastic_values
from .soft_topologies import Topology, signed_volumes, wound_tets
from .tets import TetFamily

__all__ = ["CORNER_SHARE", "EDGES", "EDGE_SHARE", "ELEMENTS", "QuadraticTetFamily", "add_tet10_term", "consistent_mass_np",
           "quadratic_shape_gradients", "quadratic_shape_values", "quadratic_tets", "quadratic_topology",
           "tet10_energy_np", "tet10_forces_np", "tet10_stiffness", "tet10_tangent_blocks"]

#: The tets a neo-Hookean soft body's elasticity can ride on: linear (the method's tets) or quadratic (this module).
ELEMENTS = ("tet4", "tet10")
#: The corners of each mid-edge node 4..9.
EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
#: A T10's node order after its corners 0 and 1 are swapped (the winding flip), the edges renumbered with them.
SWAPPED = np.array([1, 0, 2, 3, 4, 7, 8, 5, 6, 9])
#: HRZ lumped mass of a straight T10 (module): the share of the tet's mass at each corner and at each mid-edge node.
CORNER_SHARE, EDGE_SHARE = 1.0 / 36.0, 4.0 / 27.0
#: Elements per batch of the host's Gershgorin rows (their blocks take ~7 kB an element in float64).
GERSHGORIN_CHUNK = 4096
#: The four Gauss points' barycentric coordinates [4, 4] (weight ¼ each).
QUADRATURE = np.full((4, 4), QUADRATURE_BETA) + np.eye(4) * (QUADRATURE_ALPHA - QUADRATURE_BETA)


# -- the mesh ------------------------------------------------------------------------------------------------


def quadratic_tets(positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mid-edge nodes for a linear tet mesh: (positions [n + e, 3], the n given then one per unique edge at its
    middle; tets [t, 10], the given corners then the edge nodes in :data:`EDGES` order). Float64, int64."""
    positions = np.asarray(positions, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    ends = np.sort(tets[:, EDGES].reshape(-1, 2), axis=1)
    pairs, inverse = np.unique(ends, axis=0, return_inverse=True)
    middles = 0.5 * (positions[pairs[:, 0]] + positions[pairs[:, 1]])
    edge_nodes = len(positions) + inverse.reshape(len(tets), 6)
    return np.concatenate([positions, middles]), np.concatenate([tets, edge_nodes], axis=1)


def quadratic_shape_values(bary: np.ndarray) -> np.ndarray:
    """The ten shape functions at barycentric coordinates ``bary`` [..., 4]: L_a(2L_a − 1) at the corners,
    4 L_a L_b at the edges; shape [..., 10]."""
    b = np.asarray(bary, dtype=np.float64)
    return np.concatenate([b * (2.0 * b - 1.0), 4.0 * b[..., EDGES[:, 0]] * b[..., EDGES[:, 1]]], axis=-1)


def linear_gradients(rest_positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The linear tet's gradients G_a [1/m] of the corners (the first four nodes) of ``tets`` at their rest
    positions: rows of D_m⁻¹ for a = 1..3, G_0 = −ΣG_k; float64, shape [t, 4, 3]."""
    p = np.asarray(rest_positions, dtype=np.float64)[np.asarray(tets, dtype=np.int64)[:, :4]]
    inverse = np.linalg.inv(np.swapaxes(p[:, 1:] - p[:, :1], 1, 2))
    return np.concatenate([-inverse.sum(axis=1, keepdims=True), inverse], axis=1)


def quadratic_shape_gradients(linear: np.ndarray, bary: np.ndarray = QUADRATURE) -> np.ndarray:
    """∇N_a [1/m] of the ten nodes of straight T10s with linear gradients ``linear`` [t, 4, 3] at barycentric points
    ``bary`` [q, 4] (default the Gauss points): shape [t, q, 10, 3]."""
    b = np.asarray(bary, dtype=np.float64)
    corner = (4.0 * b - 1.0)[None, :, :, None] * linear[:, None, :, :]
    i, j = EDGES[:, 0], EDGES[:, 1]
    edge = 4.0 * (b[None, :, i, None] * linear[:, None, j, :] + b[None, :, j, None] * linear[:, None, i, :])
    return np.concatenate([corner, edge], axis=2)


def wound_quadratic(rest_positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T10s (int64 [t, 10]) with each whose corners' signed volume is negative renumbered by :data:`SWAPPED`, and
    their volumes |V| [m³]."""
    tets = np.array(tets, dtype=np.int64).reshape(-1, 10)
    _, volume = wound_tets(rest_positions, tets[:, :4])
    flip = signed_volumes(rest_positions, tets[:, :4]) < 0.0
    tets[flip] = tets[flip][:, SWAPPED]
    return tets, volume


def consistent_mass_np(rest_positions: np.ndarray, tets: np.ndarray, density: float) -> np.ndarray:
    """The consistent mass matrix ∫ρ N_a N_b dV of straight T10s, exact by ∫ L^a L^b … dV = 6V a! b! … / (Σ + 3)!,
    per tet: float64, shape [t, 10, 10] [kg] (its row sums are the corners' −1/20 and the edges' 1/5 of the tet's
    mass; its diagonal, scaled, is the HRZ lumping)."""
    from math import factorial

    volume = np.abs(signed_volumes(rest_positions, np.asarray(tets)[:, :4]))
    # each shape function as a polynomial in L: {exponents (4,): coefficient}
    polys = []
    for a in range(4):
        e2, e1 = [0] * 4, [0] * 4
        e2[a], e1[a] = 2, 1
        polys.append({tuple(e2): 2.0, tuple(e1): -1.0})
    for a, b in EDGES:
        e = [0] * 4
        e[a] += 1
        e[b] += 1
        polys.append({tuple(e): 4.0})
    unit = np.zeros((10, 10))  # ∫ N_a N_b dV / V
    for i, p in enumerate(polys):
        for j, q in enumerate(polys):
            total = 0.0
            for ea, ca in p.items():
                for eb, cb in q.items():
                    e = np.add(ea, eb)
                    total += ca * cb * 6.0 * np.prod([factorial(k) for k in e]) / factorial(int(e.sum()) + 3)
            unit[i, j] = total
    return density * volume[:, None, None] * unit[None]


def lumped_volumes(rest_positions: np.ndarray, tets: np.ndarray, particle_count: int) -> np.ndarray:
    """Each node's HRZ share of the body's volume [m³] (module), shape [particle_count]."""
    volume = np.abs(signed_volumes(rest_positions, np.asarray(tets)[:, :4]))
    shares = np.concatenate([np.full(4, CORNER_SHARE), np.full(6, EDGE_SHARE)])
    return np.bincount(np.asarray(tets).ravel(), weights=(volume[:, None] * shares).ravel(), minlength=particle_count)


def quadratic_topology(topology: Topology) -> Topology:
    """A tetrahedral or Delaunay body's topology with T10 elements: its particles plus a mid-edge node per tet edge,
    ``tets`` [t, 10] (:func:`quadratic_tets`), each particle's HRZ volume share (the masses follow it), the skin's
    vertices on the quadratic field (module), and the linear topology's springs (on its corners; a body built with
    T10 makes none)."""
    if topology.tets is None:
        raise ConfigError("quadratic tets are made from a body's tets: use the tetrahedral or delaunay method")
    cracks = crack_count(topology.tets)
    if cracks:
        raise ConfigError(f"the body's tets leave {cracks} flat gap(s) inside it (four coplanar points whose flat tet the "
                          "mesher dropped: the two sides' faces differ, and quadratic tets there would not join up): use "
                          "method='tetrahedral', or another spacing or seed")
    positions, tets = quadratic_tets(topology.positions, topology.tets)
    tets, _ = wound_quadratic(positions, tets)
    indices, weights = _quadratic_skin(topology, positions, tets)
    return Topology(positions, topology.springs, lumped_volumes(positions, tets, len(positions)), indices, weights,
                    topology.stiffness_rule, slivers=topology.slivers, tets=tets)


def crack_count(tets: np.ndarray) -> int:
    """Flat gaps in a linear tet mesh: four points whose every triangle is a boundary face (a face of one tet only).
    Such a quad is triangulated twice, once on each side, where a flat tet was dropped: linear tets still join along it
    (each side's field is linear on the same plane quad... up to the diagonal), quadratic ones do not (each side has a
    mid-edge node on its own diagonal)."""
    tets = np.asarray(tets, dtype=np.int64)[:, :4]
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]]),
                    axis=1)
    unique, count = np.unique(faces, axis=0, return_counts=True)
    boundary = unique[count == 1]
    if len(boundary) < 4:
        return 0
    # pairs of boundary faces sharing an edge, and the four points they span
    edges = np.sort(np.concatenate([boundary[:, [0, 1]], boundary[:, [0, 2]], boundary[:, [1, 2]]]), axis=1)
    owner = np.tile(np.arange(len(boundary)), 3)
    _, edge_id = np.unique(edges, axis=0, return_inverse=True)
    order = np.argsort(edge_id.ravel(), kind="stable")
    edge_id, owner = edge_id.ravel()[order], owner[order]
    same = np.flatnonzero(edge_id[1:] == edge_id[:-1])
    quads = np.sort(np.concatenate([boundary[owner[same]], boundary[owner[same + 1]]], axis=1), axis=1)
    quads = np.unique(np.array([np.unique(q) for q in quads if len(np.unique(q)) == 4]).reshape(-1, 4), axis=0)
    if len(quads) == 0:
        return 0
    faces_of = {tuple(f) for f in boundary.tolist()}
    whole = [all(tuple(q[list(c)]) in faces_of for c in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))) for q in quads]
    return int(np.sum(whole))


def _quadratic_skin(topology: Topology, positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The skin's rows [v, 10] on the quadratic field: a vertex that follows one particle keeps it; one embedded in a
    tet by barycentric weights takes the ten nodes of that tet and their shape functions there."""
    indices, weights = np.asarray(topology.skin_indices), np.asarray(topology.skin_weights, dtype=np.float64)
    out_indices = np.zeros((len(indices), 10), dtype=np.int64)
    out_weights = np.zeros((len(indices), 10))
    embedded = (weights != 0.0).sum(axis=1) > 1
    single = np.flatnonzero(~embedded)
    out_indices[single, 0] = indices[single, np.argmax(weights[single] != 0.0, axis=1)]
    out_indices[single] = out_indices[single, :1]
    out_weights[single, 0] = 1.0
    rows = np.flatnonzero(embedded)
    if len(rows):
        if indices.shape[1] != 4:
            raise ConfigError("a T10 skin is made from a skin embedded in tets (4 weights a vertex)")
        keys = np.sort(tets[:, :4], axis=1)
        table = {tuple(k): t for t, k in enumerate(keys.tolist())}
        owner = np.array([table[tuple(k)] for k in np.sort(indices[rows], axis=1).tolist()])
        points = np.einsum("vj,vjk->vk", weights[rows], topology.positions[indices[rows]])
        corners = positions[tets[owner, :4]]
        local = np.linalg.solve(np.swapaxes(corners[:, 1:] - corners[:, :1], 1, 2), (points - corners[:, 0])[..., None])
        bary = np.concatenate([1.0 - local[..., 0].sum(axis=1, keepdims=True), local[..., 0]], axis=1)
        out_indices[rows] = tets[owner]
        out_weights[rows] = quadratic_shape_values(bary)
    return out_indices, out_weights


# -- float64 references --------------------------------------------------------------------------------------


def _deformations(positions, rest_positions, tets):
    """F at the Gauss points [t, q, 3, 3], ∇N [t, q, 10, 3] and V₀ [t] of wound T10s."""
    gradients = quadratic_shape_gradients(linear_gradients(rest_positions, tets))
    x = np.asarray(positions, dtype=np.float64)[tets]
    return np.einsum("tai,tqaj->tqij", x, gradients), gradients, np.abs(signed_volumes(rest_positions, tets[:, :4]))


def _rest_volumes(linear: np.ndarray) -> np.ndarray:
    """V₀ [m³] of tets from their linear gradients [t, 4, 3] (rows 1..3 are D_m⁻¹): 1/(6 det D_m⁻¹)."""
    return 1.0 / (6.0 * np.abs(np.linalg.det(linear[:, 1:])))


def _cofactor(f: np.ndarray) -> np.ndarray:
    """cof F = ∂ det F/∂F, shape [..., 3, 3]."""
    c = np.empty_like(f)
    for i in range(3):
        for j in range(3):
            r = [k for k in range(3) if k != i]
            s = [k for k in range(3) if k != j]
            c[..., i, j] = (-1) ** (i + j) * (f[..., r[0], s[0]] * f[..., r[1], s[1]] - f[..., r[0], s[1]] * f[..., r[1], s[0]])
    return c


def tet10_energy_np(positions, rest_positions, tets, mu, lam) -> np.ndarray:
    """Ψ − Ψ_rest [J] per T10 (the energy hook), float64, shape [t]: Σ_q ¼V₀ [μ/2 (I_C − 3) + λ/2 (J − α)² − μ²/(2λ)]
    at the Gauss points, α = 1 + μ/λ."""
    tets, _ = wound_quadratic(rest_positions, tets)
    f, _, rest = _deformations(positions, rest_positions, tets)
    mu, lam = np.asarray(mu, dtype=np.float64), np.asarray(lam, dtype=np.float64)
    ic = (f**2).sum(axis=(2, 3)) - 3.0
    d = np.linalg.det(f) - 1.0 - np.asarray(mu / lam)[..., None]
    density = 0.5 * np.asarray(mu)[..., None] * ic + 0.5 * np.asarray(lam)[..., None] * d * d \
        - np.asarray(0.5 * mu * mu / lam)[..., None]
    return 0.25 * rest * density.sum(axis=1)


def tet10_tangent_blocks(positions, rest_positions, tets, mu, lam) -> np.ndarray:
    """The blocks K̃_ab [N/m] of the family's stiffness (its ``product``, ``kernels/tet10.py``) per T10 at
    ``positions``, float64, shape [t, 10, 10, 3, 3]: Σ_q ¼V₀ [μ (G_a·G_b) F Fᵀ + μ w_b w_aᵀ + λ_L⁻ w_a w_bᵀ
    + λ_L⁺ c_a c_bᵀ] at the Gauss points, G_a = ∇N_a, w_a = F G_a, c_a = cof F G_a, λ_L = λ − μ."""
    tets, _ = wound_quadratic(rest_positions, tets)
    return _tangent_blocks(positions, tets, linear_gradients(rest_positions, tets), mu, lam)


def _tangent_blocks(positions, tets, linear, mu, lam) -> np.ndarray:
    """:func:`tet10_tangent_blocks` of wound T10s from their linear gradients [t, 4, 3]."""
    g = quadratic_shape_gradients(linear)
    f = np.einsum("tai,tqaj->tqij", np.asarray(positions, dtype=np.float64)[tets], g)
    rest = _rest_volumes(linear)
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), rest.shape)
    lam_l = np.broadcast_to(np.asarray(lam, dtype=np.float64), rest.shape) - mu
    w = np.einsum("tqij,tqaj->tqai", f, g)
    c = np.einsum("tqij,tqaj->tqai", _cofactor(f), g)
    ffT = np.einsum("tqik,tqjk->tqij", f, f)
    scale = 0.25 * rest
    blocks = np.einsum("t,tqab,tqij->tabij", scale * mu, np.einsum("tqai,tqbi->tqab", g, g), ffT)
    blocks += np.einsum("t,tqbi,tqaj->tabij", scale * mu, w, w)
    blocks += np.einsum("t,tqai,tqbj->tabij", scale * np.minimum(lam_l, 0.0), w, w)
    blocks += np.einsum("t,tqai,tqbj->tabij", scale * np.maximum(lam_l, 0.0), c, c)
    return blocks


def tet10_stiffness(positions, rest_positions, tets, mu, lam):
    """The family's stiffness K̃ (:func:`tet10_tangent_blocks`) assembled, a ``scipy.sparse.csr_matrix`` [3n, 3n]
    float64; at rest, linear elasticity's T10 stiffness with the Lamé constants (μ, λ − μ)."""
    import scipy.sparse as sp

    tets, _ = wound_quadratic(rest_positions, tets)
    blocks = tet10_tangent_blocks(positions, rest_positions, tets, mu, lam).transpose(0, 1, 3, 2, 4).reshape(-1, 30, 30)
    dof = (3 * tets[:, :, None] + np.arange(3)).reshape(len(tets), 30)
    rows, cols = np.repeat(dof, 30, axis=1).ravel(), np.tile(dof, (1, 30)).ravel()
    size = 3 * len(positions)
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(size, size))


def tet10_forces_np(positions, velocities, rest_positions, tets, mu, lam, beta=0.0) -> np.ndarray:
    """Forces [N] of T10s on every particle, float64, shape [n, 3]: −Σ_q ¼V₀ P_q ∇N_a(q) with
    P = μF + λ(J − α) cof F, less the damper β (K̃ v)_a (``kernels/tet10.py``)."""
    tets, _ = wound_quadratic(rest_positions, tets)
    x = np.asarray(positions, dtype=np.float64)
    v = np.asarray(velocities, dtype=np.float64)
    f, g, rest = _deformations(x, rest_positions, tets)
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), rest.shape)
    lam = np.broadcast_to(np.asarray(lam, dtype=np.float64), rest.shape)
    p = mu[:, None, None, None] * f + (lam * 1.0)[:, None, None, None] * (
        np.linalg.det(f) - 1.0 - (mu / lam)[:, None])[..., None, None] * _cofactor(f)
    corner = -np.einsum("t,tqij,tqaj->tai", 0.25 * rest, p, g)
    corner -= beta * np.einsum("tabij,tbj->tai", tet10_tangent_blocks(x, rest_positions, tets, mu, lam), v[tets])
    out = np.zeros_like(x)
    for axis in range(3):
        out[:, axis] = np.bincount(tets.ravel(), weights=corner[..., axis].ravel(), minlength=len(x))
    return out


# -- the family ----------------------------------------------------------------------------------------------


class QuadraticTetFamily(TetFamily):
    """The neo-Hookean energy of every T10 of a model's soft bodies built with ``element="tet10"`` (one family per
    model, each body's elements appended by :meth:`add`), integrated at four Gauss points per element.

    Live values (per world, in device memory, read by the kernels): ``mu`` μ [Pa], ``lam`` λ [Pa] (the energy's,
    :func:`~warpspring.kernels.neohookean.stable_lame`) and ``damping`` β [s] per element (:meth:`set_values`).

    Args:
        precompute: compute each element's first Piola stress at its four Gauss points once per force evaluation in a
            pass of its own (``at_time``; 36 scalars per element and world), and let each node's gather read them;
            ``False``: every node of an element computes them itself (ten times the work).
    """

    name = "quadratic neo-Hookean tets"
    live_names = ("mu", "lam", "damping")
    damper = "damping"
    label = "the quadratic neo-Hookean family"
    element_label = "quadratic tet"
    precompute_kernel = "tet10_stresses"
    nodes = 10
    index_type = vec10i

    def __init__(self, *, precompute: bool = True):
        super().__init__(precompute=precompute)
        self._inverse: list[np.ndarray] = []

    def _wind(self, positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return wound_quadratic(positions, tets)

    def add(self, tets, positions, *, youngs_modulus: float, poisson_ratio: float = 0.25, damping: float = 0.0,
            source: str = "soft body") -> slice:
        """Add T10s of one body.

        Args:
            tets: particle indices (per world) of each element, shape [t, 10]: corners, then the mid-edge nodes in
                :data:`EDGES` order (:func:`quadratic_tets`); either winding.
            positions: the rest positions [m] of the model's particles so far, shape [n, 3]; the mid-edge nodes at
                their edges' middles (straight elements).
            youngs_modulus: E [Pa], > 0.
            poisson_ratio: ν, in (−1, ½).
            damping: β [s], ≥ 0: Rayleigh's stiffness-proportional damper −β K̃ v on the family's stiffness (it spares
                rigid motions; a mode of angular frequency ω is damped by ζ = βω/2 at rest).
            source: the body's name, for messages.

        Returns:
            The slice of the family's elements these occupy.

        Raises:
            ConfigError: no elements, an index out of range, a flat element, a mid-edge node off its edge's middle, E
                or ν out of range.
        """
        e = checks.positive(f"{source}: youngs_modulus [Pa]", youngs_modulus)
        nu = poisson(poisson_ratio, source)
        mu, lam = stable_lame(e, nu)
        values = {"mu": mu, "lam": lam, "damping": checks.non_negative(f"{source}: damping [s]", damping)}
        tets = np.array(tets, dtype=np.int64)
        if tets.ndim != 2 or tets.shape[1] != 10:
            raise ConfigError(f"{source}: quadratic tets are 10 particles each (4 corners, 6 mid-edge nodes), got "
                              f"shape {tets.shape}")
        positions = np.asarray(positions, dtype=np.float64)
        added, tets, _ = self._add_tets(tets, positions, values, source)
        middle = 0.5 * (positions[tets[:, EDGES[:, 0]]] + positions[tets[:, EDGES[:, 1]]])
        edge = np.linalg.norm(positions[tets[:, EDGES[:, 1]]] - positions[tets[:, EDGES[:, 0]]], axis=-1)
        off = np.linalg.norm(positions[tets[:, 4:]] - middle, axis=-1) > 1.0e-6 * edge
        if off.any():
            t = int(np.flatnonzero(off.any(axis=1))[0])
            raise ConfigError(f"{source}: quadratic tet {t}'s mid-edge nodes are not at their edges' middles (curved "
                              "elements are not supported): make them with quadratic_tets")
        self._inverse.append(linear_gradients(positions, tets)[:, 1:])
        return added

    def device_bytes(self, particle_count: int, scalar_bytes: int, worlds: int) -> int:
        """Indices, V₀, D_m⁻¹, μ, λ and β per element (one row each), the stresses, and the incidence table."""
        stress = 36 * scalar_bytes * (worlds * self.element_count if self.precompute else 1)
        return (40 + 13 * scalar_bytes) * self.element_count + stress + incidence_bytes(self.tets, particle_count)

    def finalize(self, model) -> None:
        self._finalize_tets(model)
        device, scalar = model.device, model.scalar
        self._rest_inverse = wp.array(np.concatenate(self._inverse), dtype=mat33_type(scalar), device=device)
        slots = 4 * model.world_count * self.element_count if self.precompute else 1
        self._stress = wp.zeros(slots, dtype=mat33_type(scalar), device=device)

    def set_values(self, *, youngs_modulus=None, poisson_ratio=None, damping=None, world: int | None = None,
                   tets=None) -> None:
        """Change E [Pa] and ν (together: μ and λ follow) and/or β [s] between frames: live values (nothing compiles
        or re-captures, except the first write to a single world: a structural change).

        Args:
            youngs_modulus, poisson_ratio: numbers; give both or neither.
            damping: a number, or one per selected element; ≥ 0, finite.
            world: one world, or every world (``None``).
            tets: the elements to change (an index array, a slice such as the one :meth:`add` returned, or ``None``).
        """
        write_elastic_values(self, "quadratic tets", youngs_modulus=youngs_modulus, poisson_ratio=poisson_ratio,
                             damping=damping, world=world, tets=tets)

    def spec(self, model, *, linear: bool = False) -> Tet10Spec:
        return Tet10Spec(incidence=self.shape, precomputed=self.precompute)

    def arrays(self, model, *, stiffness=None):
        arrays = tet10_arrays_type(model.scalar)()
        arrays.indices = self._indices
        arrays.rest_volume = self._rest_volume
        arrays.rest_inverse = self._rest_inverse
        arrays.mu = self._live_arrays["mu"]
        arrays.lam = self._live_arrays["lam"]
        arrays.damping = self._live_arrays["damping"]
        arrays.stress = self._stress
        arrays.incidence = self.incidence
        return arrays

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None) -> np.ndarray:
        """Row a gains the spectral norm of the product's block K̃_ab (:func:`tet10_tangent_blocks`, at the model's
        initial positions) for b = a and for every free b ≠ a."""
        worlds, n = model.world_count, model.particle_count
        tets = self.tets
        x = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
        linear = np.concatenate(self._inverse)
        linear = np.concatenate([-linear.sum(axis=1, keepdims=True), linear], axis=1)
        mu, lam = self.values("mu"), self.values("lam")
        rows = np.zeros((worlds, n))
        columns = np.maximum(free[:, tets][:, :, None, :].astype(np.float64), np.eye(10)[None, None])  # [w, t, a, b]
        for world in range(worlds):
            for start in range(0, len(tets), GERSHGORIN_CHUNK):  # 7 kB of blocks per element: bounded host memory
                part = slice(start, start + GERSHGORIN_CHUNK)
                blocks = _tangent_blocks(x[world], tets[part], linear[part], mu[world, part], lam[world, part])
                norms = np.linalg.norm(blocks, ord=2, axis=(-2, -1))  # [t, 10, 10]
                rows[world] += np.bincount(tets[part].ravel(), weights=(norms * columns[world, part]).sum(axis=-1).ravel(),
                                           minlength=n)
        return rows

    def describe_element(self, model, element: int) -> str:
        return f"{self.element_label} {element} (corners {', '.join(str(int(i)) for i in self.tets[element, :4])})"


def add_tet10_term(builder, topology: Topology, ids: np.ndarray, *, youngs_modulus: float, poisson_ratio: float,
                   damping: float, source: str) -> slice:
    """The T10s of a soft body built with ``element="tet10"`` (``topology`` from :func:`quadratic_topology`, global
    particle indices ``ids``), added to the builder's :class:`QuadraticTetFamily` (created on first use). Returns the
    slice of the family's elements."""
    family = next((f for f in builder._families if isinstance(f, QuadraticTetFamily)), None)
    if family is None:
        family = builder.add_family(QuadraticTetFamily())
    tets = ids[topology.tets]
    return family.add(tets, builder.particle_positions(np.arange(int(tets.max()) + 1)), youngs_modulus=youngs_modulus,
                      poisson_ratio=poisson_ratio, damping=damping, source=source)
