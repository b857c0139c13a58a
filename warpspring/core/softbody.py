"""A soft body as the builder adds it (``SoftBody``), its particle masses (``distribute_mass``) and the float64
reference of its spring network at rest (``stiffness_matrix``, ``static_displacement``). The topologies it is
built from, and how each maps E to k, are in ``soft_topologies.py``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from .soft_topologies import SliverReport, Topology


@dataclass(frozen=True)
class SoftBody:
    """What :meth:`~warpspring.ModelBuilder.add_soft_body` added.

    Attributes:
        name: the exported mesh's name.
        method: the topology (one of :data:`~warpspring.core.soft_topologies.METHODS`).
        particles: global indices of its particles, shape [n], consecutive.
        springs: group name -> global indices of its springs (family ``<name>_<group>``).
        skin: the embedded surface (:class:`~warpspring.core.records.SkinGroup`), in global particle indices.
        stiffness_rule: how E was mapped to ke, in words.
        youngs_modulus: E [Pa].
        mass: total mass [kg].
        slivers: the sliver report of a tetrahedral body, else ``None``.
        topology: the method's output in the mesh's (scaled) frame, local indices.
        build_seconds: wall time of the build [s].
        volume_tets: with ``volume=True``, the slice of the tet volume family's elements holding its tets (the
            ``tets`` argument of ``VolumeFamily.set_values``); else ``None``.
        elasticity: what carries its elasticity, ``"springs"`` or ``"neohookean"``.
        elastic_tets: with ``elasticity="neohookean"``, the slice of the neo-Hookean family's elements holding its
            tets (``NeoHookeanFamily.set_values(tets=)``, or ``QuadraticTetFamily``'s for ``element="tet10"``); else
            ``None``.
        element: the tets of a neo-Hookean body, ``"tet4"`` or ``"tet10"`` (then ``topology.tets`` is [t, 10]).
    """

    name: str
    method: str
    particles: np.ndarray
    springs: dict
    skin: object
    stiffness_rule: str
    youngs_modulus: float
    mass: float
    slivers: SliverReport | None
    topology: Topology = field(repr=False)
    build_seconds: float = 0.0
    volume_tets: slice | None = None
    elasticity: str = "springs"
    elastic_tets: slice | None = None
    element: str = "tet4"

    @property
    def particle_count(self) -> int:
        return len(self.particles)

    @property
    def spring_count(self) -> int:
        return sum(len(s) for s in self.springs.values())

    @property
    def spring_counts(self) -> dict:
        """Springs per group."""
        return {group: len(s) for group, s in self.springs.items()}


# -- masses -------------------------------------------------------------------------------------------------


def distribute_mass(topology: Topology, total: float, *, distribution: str = "volume", weights=None,
                    skin_factor: float = 1.0, gradient=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Particle masses [kg], shape [n], summing to ``total`` [kg].

    Args:
        distribution: ``"volume"`` (each particle's volume share) or ``"uniform"`` (equal).
        weights: relative weights per particle multiplied in: an array [n] > 0, or a function of the rest
            positions [n, 3] returning one.
        skin_factor: multiplies the weight of every particle the surface follows (a heavier skin), > 0.
        gradient: g [1/m]: weights × (1 + g·(x − centroid)), a body heavier on one side (it rights itself).
    """
    n = topology.particle_count
    if distribution == "volume":
        share = topology.volume.copy()
    elif distribution == "uniform":
        share = np.ones(n)
    else:
        raise ConfigError(f"mass distribution must be 'volume' or 'uniform', got {distribution!r}")
    if weights is not None:
        w = np.asarray(weights(topology.positions) if callable(weights) else weights, dtype=np.float64)
        if w.shape != (n,) or not (np.isfinite(w).all() and (w > 0.0).all()):
            raise ConfigError(f"mass weights must be {n} finite numbers > 0 (one per particle), got shape {w.shape}")
        share = share * w
    if not (math.isfinite(skin_factor) and skin_factor > 0.0):
        raise ConfigError(f"skin_mass_factor must be > 0, got {skin_factor!r}")
    if skin_factor != 1.0:
        skin = np.zeros(n, dtype=bool)
        skin[topology.skin_indices[topology.skin_weights != 0.0]] = True
        share = np.where(skin, share * skin_factor, share)
    g = np.asarray(gradient, dtype=np.float64)
    if g.shape != (3,) or not np.isfinite(g).all():
        raise ConfigError(f"mass_gradient must be a 3-vector [1/m], got {gradient!r}")
    if g.any():
        bias = 1.0 + (topology.positions - topology.positions.mean(axis=0)) @ g
        if (bias <= 0.0).any():
            raise ConfigError(f"mass_gradient {g.tolist()} makes a particle's weight ≤ 0: |g| must stay below "
                              f"1 / {float(np.abs(topology.positions - topology.positions.mean(axis=0)).max()):.4g} m")
        share = share * bias
    if not (share > 0.0).all():
        raise ConfigError("a particle of the soft body has no mass share: use distribution='uniform' or weights")
    return share * (total / share.sum())


# -- static checks --------------------------------------------------------------------------------------------


def stiffness_matrix(positions: np.ndarray, pairs: np.ndarray, stiffness: np.ndarray):
    """The spring network's linear stiffness at rest, K = Σ_e k_e (n nᵀ ⊗ [[1, −1], [−1, 1]]), as a
    ``scipy.sparse.csr_matrix`` [3n, 3n] (float64): small displacements u store ½ uᵀ K u."""
    import scipy.sparse as sp

    d = positions[pairs[:, 1]] - positions[pairs[:, 0]]
    n = d / np.linalg.norm(d, axis=1, keepdims=True)
    block = stiffness[:, None, None] * n[:, :, None] * n[:, None, :]  # [s, 3, 3]
    a, b = 3 * pairs[:, 0], 3 * pairs[:, 1]
    k3 = np.arange(3)
    rows, cols, values = [], [], []
    for p, q, sign in ((a, a, 1.0), (b, b, 1.0), (a, b, -1.0), (b, a, -1.0)):
        rows.append((p[:, None, None] + k3[None, :, None]).repeat(3, axis=2).ravel())
        cols.append((q[:, None, None] + k3[None, None, :]).repeat(3, axis=1).ravel())
        values.append((sign * block).ravel())
    size = 3 * len(positions)
    return sp.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))), shape=(size, size))


def static_displacement(topology: Topology, force: np.ndarray, fixed: np.ndarray, *, stiffness=None) -> np.ndarray:
    """Small displacements [m], shape [n, 3], of the body under ``force`` [N] (shape [n, 3]) with the degrees of
    freedom in the boolean mask ``fixed`` (shape [n, 3]) held at zero: K u = f solved in float64 (sparse LU).
    ``stiffness``: the [3n, 3n] matrix K (default the spring network's, :func:`stiffness_matrix`)."""
    import scipy.sparse.linalg as spla

    if stiffness is None:
        pairs = np.concatenate([p for p, _ in topology.springs.values()])
        ke = np.concatenate([k for _, k in topology.springs.values()])
        K = stiffness_matrix(topology.positions, pairs, ke)
    else:
        K = stiffness.tocsr()
    free = np.flatnonzero(~np.asarray(fixed).ravel())
    u = np.zeros(K.shape[0])
    u[free] = spla.spsolve(K[free][:, free].tocsc(), np.asarray(force, dtype=np.float64).ravel()[free])
    return u.reshape(-1, 3)
