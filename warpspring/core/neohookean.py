"""The neo-Hookean tet family on the host: a tetrahedral body's elasticity carried by its tets,
Ψ = V₀ [μ/2 (I_C − 3) + λ/2 (J − α)²], α = 1 + μ/λ, per tet (``kernels/neohookean.py`` has the maths, the
linearisation at rest and the hooks), its live values, its part of the advisor's Gershgorin bound, and float64
references of the energy and forces for tests.

Why: a spring network on fTetWild's tets (k_e = E·ΣV_t/L_e²) fails the patch test — under a uniform stress it is
3–19 % too compliant in tension and up to 2× in shear, set by the tets' shapes, not their size
(``bench/results/softbody_patch_test.md``) — so its error does not fall with resolution. The tets linearised at
rest are linear elasticity on the same tets, which passes the patch test to rounding.
``ModelBuilder.add_soft_body(elasticity="neohookean")`` builds a tetrahedral or Delaunay body's tets into this
family and no springs.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.neohookean import NeoHookeanSpec, neohookean_arrays_type, stable_lame
from ..kernels.precision import mat33_type
from .families import incidence_bytes
from .tets import TetFamily, signed_volumes, wound_tets
from .volume import volume_gradients

#: What carries a soft body's elasticity: its springs, or (tetrahedral and Delaunay bodies) the neo-Hookean tets.
ELASTICITIES = ("springs", "neohookean")

__all__ = ["ELASTICITIES", "NeoHookeanFamily", "add_neohookean_term", "neohookean_energy_np", "neohookean_forces_np",
           "shape_gradients", "stable_lame", "tangent_blocks", "tangent_stiffness"]


def wound(rest_positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """``tets`` (int64 [t, 4]) rewound as the family winds them: V₀ > 0 at ``rest_positions`` (the host references
    take either winding)."""
    return wound_tets(rest_positions, tets)[0]


def shape_gradients(positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """G_a [1/m] of tets at ``positions`` (their rest state): rows of D_m⁻¹ for a = 1..3, G_0 = −ΣG_k; float64,
    shape [t, 4, 3]."""
    p = np.asarray(positions, dtype=np.float64)[np.asarray(tets, dtype=np.int64)]
    inverse = np.linalg.inv(np.swapaxes(p[:, 1:] - p[:, :1], 1, 2))  # D_m⁻¹, D_m's columns X_k − X_0
    return np.concatenate([-inverse.sum(axis=1, keepdims=True), inverse], axis=1)


def neohookean_energy_np(positions: np.ndarray, rest_positions: np.ndarray, tets: np.ndarray, mu, lam) -> np.ndarray:
    """Ψ − Ψ_rest [J] of tets (the energy hook), float64, shape [t]: V₀ [μ/2 (I_C − 3) + λ/2 (J − α)² − μ²/(2λ)]."""
    tets = wound(rest_positions, tets)
    rest = signed_volumes(rest_positions, tets)
    f = np.einsum("tai,taj->tij", np.asarray(positions, dtype=np.float64)[tets], shape_gradients(rest_positions, tets))
    j = signed_volumes(positions, tets) / rest
    mu, lam = np.asarray(mu, dtype=np.float64), np.asarray(lam, dtype=np.float64)
    return rest * (0.5 * mu * ((f**2).sum(axis=(1, 2)) - 3.0) + 0.5 * lam * (j - 1.0 - mu / lam) ** 2
                   - 0.5 * mu * mu / lam)


def tangent_blocks(positions: np.ndarray, rest_positions: np.ndarray, tets: np.ndarray, mu, lam) -> np.ndarray:
    """The blocks K̃_ab [N/m] of the family's stiffness (its ``product``; ``kernels/neohookean.py``) at ``positions``,
    float64, shape [t, 4, 4, 3, 3]: V₀ [μ (G_a·G_b) F Fᵀ + μ w_b w_aᵀ + λ_L⁻ w_a w_bᵀ] + (λ_L⁺/V₀) ∇_aV ∇_bVᵀ,
    w_a = F G_a, λ_L = λ − μ; ``mu``, ``lam``: numbers or one per tet."""
    tets = wound(rest_positions, tets)
    return _tangent_blocks(positions, tets, shape_gradients(rest_positions, tets), signed_volumes(rest_positions, tets),
                           mu, lam)


def _tangent_blocks(positions, tets, g, rest, mu, lam) -> np.ndarray:
    """:func:`tangent_blocks` from the tets' G_a [t, 4, 3] and V₀ [t]."""
    x = np.asarray(positions, dtype=np.float64)
    f = np.einsum("tai,taj->tij", x[tets], g)
    w = np.einsum("tij,taj->tai", f, g)
    grad_v = volume_gradients(x, tets)
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), rest.shape)
    lam_l = np.broadcast_to(np.asarray(lam, dtype=np.float64), rest.shape) - mu
    ffT = np.einsum("tik,tjk->tij", f, f)
    blocks = (mu * rest)[:, None, None, None, None] * np.einsum("tab,tij->tabij", np.einsum("tai,tbi->tab", g, g), ffT)
    blocks += (mu * rest)[:, None, None, None, None] * np.einsum("tbi,taj->tabij", w, w)
    blocks += (np.minimum(lam_l, 0.0) * rest)[:, None, None, None, None] * np.einsum("tai,tbj->tabij", w, w)
    blocks += (np.maximum(lam_l, 0.0) / rest)[:, None, None, None, None] * np.einsum("tai,tbj->tabij", grad_v, grad_v)
    return blocks


def tangent_stiffness(positions: np.ndarray, rest_positions: np.ndarray, tets: np.ndarray, mu, lam):
    """The family's stiffness K̃ (:func:`tangent_blocks`) assembled, a ``scipy.sparse.csr_matrix`` [3n, 3n] float64;
    at rest it is linear elasticity's (``analysis.softbody_elasticity.linear_fem_stiffness``)."""
    import scipy.sparse as sp

    tets = wound(rest_positions, tets)
    blocks = tangent_blocks(positions, rest_positions, tets, mu, lam).transpose(0, 1, 3, 2, 4).reshape(-1, 12, 12)
    dof = (3 * tets[:, :, None] + np.arange(3)).reshape(len(tets), 12)
    rows, cols = np.repeat(dof, 12, axis=1).ravel(), np.tile(dof, (1, 12)).ravel()
    size = 3 * len(positions)
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(size, size))


def neohookean_forces_np(positions: np.ndarray, velocities: np.ndarray, rest_positions: np.ndarray, tets: np.ndarray,
                         mu, lam, beta=0.0) -> np.ndarray:
    """Forces [N] of tets on every particle, float64, shape [n, 3]: −μ V₀ F G_a − λ (J − α) ∇_aV − β (K̃ v)_a
    (``kernels/neohookean.py``)."""
    tets = wound(rest_positions, tets)
    x = np.asarray(positions, dtype=np.float64)
    v = np.asarray(velocities, dtype=np.float64)
    rest = signed_volumes(rest_positions, tets)
    g = shape_gradients(rest_positions, tets)
    f = np.einsum("tai,taj->tij", x[tets], g)
    j = signed_volumes(x, tets) / rest
    mu, lam = np.broadcast_to(mu, rest.shape), np.broadcast_to(lam, rest.shape)
    corner = -(mu * rest)[:, None, None] * np.einsum("tij,taj->tai", f, g) \
        - (lam * (j - 1.0 - mu / lam))[:, None, None] * volume_gradients(x, tets)
    corner -= beta * np.einsum("tabij,tbj->tai", tangent_blocks(x, rest_positions, tets, mu, lam), v[tets])
    out = np.zeros_like(x)
    for axis in range(3):
        out[:, axis] = np.bincount(tets.ravel(), weights=corner[..., axis].ravel(), minlength=len(x))
    return out


class NeoHookeanFamily(TetFamily):
    """The neo-Hookean energy of every tet of a model's soft bodies built with ``elasticity="neohookean"`` (one family
    per model, each body's tets appended by :meth:`add`).

    Live values (per world, in device memory, read by the kernels; writing them compiles nothing): ``mu`` μ [Pa],
    ``lam`` λ [Pa] (the energy's, λ = λ_L + μ, :func:`stable_lame`) and ``damping`` β [s] per tet
    (:meth:`set_values`).

    Args:
        precompute: compute each tet's stress S and pressure p once per force evaluation in a pass of its own
            (``at_time``; ten scalars per tet and world) and let each corner's gather read them with its own face's
            gradient; ``False``: every corner computes its tet's F, Ḟ and volume gradient itself.
    """

    name = "neo-Hookean tets"
    live_names = ("mu", "lam", "damping")
    damper = "damping"
    label = "the neo-Hookean family"
    element_label = "neo-Hookean tet"
    precompute_kernel = "tet_stresses"

    def __init__(self, *, precompute: bool = True):
        super().__init__(precompute=precompute)
        self._inverse: list[np.ndarray] = []

    # -- building -----------------------------------------------------------------------------------------

    def add(self, tets, positions, *, youngs_modulus: float, poisson_ratio: float = 0.25, damping: float = 0.0,
            source: str = "soft body") -> slice:
        """Add tets of one body.

        Args:
            tets: particle indices (per world) of each tet, shape [t, 4], either winding: each is rewound so that
                its rest volume is positive.
            positions: the rest positions [m] of the model's particles so far, shape [n, 3] (float64).
            youngs_modulus: E [Pa], > 0.
            poisson_ratio: ν, in (−1, ½).
            damping: β [s], ≥ 0: Rayleigh's stiffness-proportional damper −β K̃ v on the family's stiffness K̃
                (``kernels/neohookean.py``: it acts on the Green strain's rate and the volume's, so it exerts nothing
                on rigid motions); at rest a mode of angular frequency ω is damped by ζ = βω/2, as the springs'
                kd = β ke.
            source: the body's name, for messages.

        Returns:
            The slice of the family's elements these tets occupy.

        Raises:
            ConfigError: no tets, an index out of range, a tet of (nearly) zero rest volume, E or ν out of range.
        """
        e = checks.positive(f"{source}: youngs_modulus [Pa]", youngs_modulus)
        nu = poisson(poisson_ratio, source)
        mu, lam = stable_lame(e, nu)
        values = {"mu": mu, "lam": lam, "damping": checks.non_negative(f"{source}: damping [s]", damping)}
        added, tets, _ = self._add_tets(tets, positions, values, source)
        self._inverse.append(shape_gradients(np.asarray(positions, dtype=np.float64), tets)[:, 1:])
        return added

    def device_bytes(self, particle_count: int, scalar_bytes: int, worlds: int) -> int:
        """Indices, V₀, D_m⁻¹, μ, λ and β per tet (one row each), and the incidence table."""
        stress = 10 * scalar_bytes * (worlds * self.element_count if self.precompute else 1)
        return (16 + 13 * scalar_bytes) * self.element_count + stress + incidence_bytes(self.tets, particle_count)

    def finalize(self, model) -> None:
        self._finalize_tets(model)
        device, scalar = model.device, model.scalar
        self._rest_inverse = wp.array(np.concatenate(self._inverse), dtype=mat33_type(scalar), device=device)
        slots = model.world_count * self.element_count if self.precompute else 1
        self._stress = wp.zeros(slots, dtype=mat33_type(scalar), device=device)
        self._pressure = wp.zeros(slots, dtype=scalar, device=device)

    # -- live values -------------------------------------------------------------------------------------------

    def set_values(self, *, youngs_modulus=None, poisson_ratio=None, damping=None, world: int | None = None,
                   tets=None) -> None:
        """Change E [Pa] and ν (together: μ and λ follow, :func:`stable_lame`) and/or β [s] between frames: live
        values (nothing compiles or re-captures, except the first write to a single world, which gives the arrays
        one row per world: a structural change).

        Args:
            youngs_modulus, poisson_ratio: numbers; give both or neither.
            damping: a number, or one per selected tet; ≥ 0, finite.
            world: one world, or every world (``None``).
            tets: the tets to change (an index array, a slice such as the one :meth:`add` returned, or ``None``).
        """
        write_elastic_values(self, "neo-Hookean tets", youngs_modulus=youngs_modulus, poisson_ratio=poisson_ratio,
                             damping=damping, world=world, tets=tets)

    # -- the protocol ----------------------------------------------------------------------------------------------

    def spec(self, model, *, linear: bool = False) -> NeoHookeanSpec:
        return NeoHookeanSpec(incidence=self.shape, precomputed=self.precompute)

    def arrays(self, model, *, stiffness=None):
        arrays = neohookean_arrays_type(model.scalar)()
        arrays.indices = self._indices
        arrays.rest_volume = self._rest_volume
        arrays.rest_inverse = self._rest_inverse
        arrays.mu = self._live_arrays["mu"]
        arrays.lam = self._live_arrays["lam"]
        arrays.damping = self._live_arrays["damping"]
        arrays.stress = self._stress
        arrays.pressure = self._pressure
        arrays.incidence = self.incidence
        return arrays

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None) -> np.ndarray:
        """Row a gains the spectral norm of the product's block K̃_ab (:func:`tangent_blocks`, at the model's initial
        positions) for b = a and for every free b ≠ a."""
        worlds, n = model.world_count, model.particle_count
        tets = self.tets
        g = np.concatenate(self._inverse)
        g = np.concatenate([-g.sum(axis=1, keepdims=True), g], axis=1)
        x = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
        mu, lam = self.values("mu"), self.values("lam")
        rows = np.zeros((worlds, n))
        columns = np.maximum(free[:, tets][:, :, None, :].astype(np.float64), np.eye(4)[None, None])  # [w, t, a, b]
        for world in range(worlds):
            blocks = _tangent_blocks(x[world], tets, g, self.rest_volume, mu[world], lam[world])
            norms = np.linalg.norm(blocks, ord=2, axis=(-2, -1))  # [t, 4, 4]
            rows[world] = np.bincount(tets.ravel(), weights=(norms * columns[world]).sum(axis=-1).ravel(), minlength=n)
        return rows


def poisson(value, source: str) -> float:
    """ν as a float in (−1, ½), or a one-line ConfigError."""
    try:
        nu = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{source}: poisson_ratio must be a number in (-1, 0.5), got {value!r}") from None
    if not (-1.0 < nu < 0.5):
        raise ConfigError(f"{source}: poisson_ratio must lie in (-1, 0.5) (0.5 is incompressible, which linear tets "
                          f"lock on), got {value!r}")
    return nu


def add_neohookean_term(builder, topology, ids: np.ndarray, *, method: str, youngs_modulus: float,
                        poisson_ratio: float, damping: float, source: str) -> slice:
    """The tets of a soft body built with ``elasticity="neohookean"`` (with global particle indices ``ids``), added
    to the builder's :class:`NeoHookeanFamily` (created on first use) with E, ν and the damper's β = ``damping`` [s].
    Returns the slice of the family's elements."""
    if topology.tets is None:
        raise ConfigError(f"{source}: elasticity='neohookean' needs tets, which the {method} method does not make: "
                          "use method='tetrahedral' or 'delaunay'")
    family = next((f for f in builder._families if isinstance(f, NeoHookeanFamily)), None)
    if family is None:
        family = builder.add_family(NeoHookeanFamily())
    tets = ids[topology.tets]
    return family.add(tets, builder.particle_positions(np.arange(int(tets.max()) + 1)), youngs_modulus=youngs_modulus,
                      poisson_ratio=poisson_ratio, damping=damping, source=source)


def write_elastic_values(family: TetFamily, label: str, *, youngs_modulus, poisson_ratio, damping, world, tets) -> None:
    """The live-value writes of a neo-Hookean tet family (linear or quadratic): E [Pa] and ν together (μ and λ by
    :func:`stable_lame`) and/or β [s], checked (one-line ConfigErrors naming ``label``) and written to ``tets`` of
    ``world``."""
    if (youngs_modulus is None) != (poisson_ratio is None):
        raise ConfigError("give youngs_modulus and poisson_ratio together (μ and λ follow from both)")
    writes = {}
    if youngs_modulus is not None:
        writes["mu"], writes["lam"] = stable_lame(checks.positive("youngs_modulus [Pa]", youngs_modulus),
                                                  poisson(poisson_ratio, label))
    if damping is not None:
        value = np.asarray(damping, dtype=np.float64)
        if not (np.isfinite(value).all() and (value >= 0.0).all()):
            raise ConfigError(f"the {label}' damping must be finite and >= 0 [s], got {damping!r}")
        writes["damping"] = value
    family._write_values(writes, world=world, tets=tets)
