"""The tet volume family on the host: a bulk energy ½ K V₀ (J - 1)² per tetrahedron of a soft body
(``kernels/volume.py`` has the maths and the hooks), its live values, its part of the advisor's Gershgorin
bound, and float64 references of the volume, energy and forces for tests.

A mass-spring body resists a change of volume only through its springs, and a tet whose vertex was pushed
through its opposite face reaches a mirrored state in which its six springs are near rest again: dropped at
20 kPa, the tetrahedral and Delaunay balls collapsed to a quarter of their volume with a third of their tets
inverted (``bench/RESULTS.md`` §18b). The family adds the missing term: its energy grows with |J - 1| on the
signed volume, so it is larger inverted than flat and an inverted tet is pushed back.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.volume import VolumeSpec, volume_arrays_type
from .families import incidence_bytes
from .tets import TetFamily, signed_volumes

#: The Poisson ratio of a network of central springs (every soft-body lattice: ``core/soft_topologies.py``).
NETWORK_POISSON_RATIO = 0.25


def network_bulk_modulus(youngs_modulus: float, poisson_ratio: float = NETWORK_POISSON_RATIO) -> float:
    """K = E / (3 (1 - 2ν)) [Pa]: the bulk modulus of an isotropic solid of Young's modulus E [Pa] and Poisson
    ratio ν; at the spring networks' ν = 1/4, K = 2E/3."""
    return float(youngs_modulus) / (3.0 * (1.0 - 2.0 * float(poisson_ratio)))


def volume_gradients(positions: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """∇_aV [m²] of tets' signed volumes, the device's closed form (``kernels/volume.py``), float64, shape
    [..., t, 4, 3]."""
    p = np.asarray(positions, dtype=np.float64)[..., np.asarray(tets, dtype=np.int64), :]
    e1, e2, e3 = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :], p[..., 3, :] - p[..., 0, :]
    g1, g2, g3 = np.cross(e2, e3) / 6.0, np.cross(e3, e1) / 6.0, np.cross(e1, e2) / 6.0
    return np.stack([-(g1 + g2 + g3), g1, g2, g3], axis=-2)


def volume_energy_np(positions: np.ndarray, tets: np.ndarray, rest_volume: np.ndarray, bulk_modulus) -> np.ndarray:
    """Energies ½ (K/V₀)(V - V₀)² [J] of tets, float64, shape [..., t]."""
    d = signed_volumes(positions, tets) - rest_volume
    return 0.5 * np.asarray(bulk_modulus, dtype=np.float64) * d * d / rest_volume


def volume_stiffness_matrix(positions: np.ndarray, tets: np.ndarray, bulk_modulus):
    """The term's Gauss-Newton stiffness Σ_t (K/V₀) ∇V ∇Vᵀ at ``positions`` (its exact linear stiffness at rest), as a
    ``scipy.sparse.csr_matrix`` [3n, 3n] (float64), with V₀ the |volume| of each tet at ``positions`` [m], shape
    [n, 3]; ``bulk_modulus`` K [Pa], a number or one per tet. Beside ``softbody.stiffness_matrix`` (the springs')
    it gives a body's static response with the term."""
    import scipy.sparse as sp

    tets = np.asarray(tets, dtype=np.int64)
    rest = np.abs(signed_volumes(positions, tets))
    g = volume_gradients(positions, tets).reshape(len(tets), 12)
    dof = (3 * tets[:, :, None] + np.arange(3)[None, None, :]).reshape(len(tets), 12)
    blocks = (np.broadcast_to(np.asarray(bulk_modulus, dtype=np.float64), rest.shape) / rest)[:, None, None] \
        * g[:, :, None] * g[:, None, :]
    rows = np.repeat(dof[:, :, None], 12, axis=2).ravel()
    cols = np.repeat(dof[:, None, :], 12, axis=1).ravel()
    size = 3 * len(positions)
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(size, size))


class VolumeFamily(TetFamily):
    """The volume term of every tet of a model's soft bodies built with ``volume=True`` (one family per model,
    each body's tets appended by :meth:`add`).

    Live values (per world, in device memory, read by the kernels; writing them compiles nothing):
    ``bulk_modulus`` K [Pa] and ``viscosity`` kd [Pa·s] per tet (:meth:`set_values`).

    Args:
        precompute: compute each tet's factor K (J - 1) + kd J̇ once per force evaluation in a pass of its own
            (``at_time``) and let each corner's gather read it with its own gradient (one launch and one scalar
            per tet and world more, a quarter of the gather's loads); ``False``: every corner computes its tet's
            volume, rate and gradients. On the CPU the term costs 2.00× against 2.10× the substep without it
            (``bench/RESULTS.md`` §18d; ``bench/softbody.py --family-cost`` compares both on a GPU).
    """

    name = "volume tets"
    live_names = ("bulk_modulus", "viscosity")
    damper = "viscosity"
    label = "the volume term"
    element_label = "volume tet"
    precompute_kernel = "tet_pressures"

    # -- building -----------------------------------------------------------------------------------------

    def add(self, tets, positions, *, bulk_modulus: float, viscosity: float = 0.0, source: str = "soft body") -> slice:
        """Add tets of one body.

        Args:
            tets: particle indices (per world) of each tet, shape [t, 4], either winding: each is rewound so that
                its rest volume is positive.
            positions: the rest positions [m] of the model's particles so far, shape [n, 3] (float64).
            bulk_modulus: K [Pa], ≥ 0.
            viscosity: kd [Pa·s], ≥ 0: the volumetric damper (a soft body's stiffness-proportional β gives β K).
            source: the body's name, for messages.

        Returns:
            The slice of the family's elements these tets occupy.

        Raises:
            ConfigError: no tets, an index out of range, or a tet of (nearly) zero rest volume.
        """
        values = {"bulk_modulus": checks.non_negative(f"{source}: bulk_modulus [Pa]", bulk_modulus),
                  "viscosity": checks.non_negative(f"{source}: volume viscosity [Pa·s]", viscosity)}
        return self._add_tets(tets, positions, values, source)[0]

    def device_bytes(self, particle_count: int, scalar_bytes: int, worlds: int) -> int:
        """Indices, V₀, K and kd per tet (one row of K and kd), the factor per tet and world where precomputed, and
        the incidence table."""
        factor = scalar_bytes * (worlds * self.element_count if self.precompute else 1)
        return (16 + 3 * scalar_bytes) * self.element_count + factor + incidence_bytes(self.tets, particle_count)

    def finalize(self, model) -> None:
        self._finalize_tets(model)
        slots = model.world_count * self.element_count if self.precompute else 1
        self._pressure = wp.zeros(slots, dtype=model.scalar, device=model.device)

    # -- live values -------------------------------------------------------------------------------------------

    def set_values(self, *, bulk_modulus=None, viscosity=None, world: int | None = None, tets=None) -> None:
        """Change K [Pa] and/or kd [Pa·s] between frames: live values (nothing compiles or re-captures, except the
        first write to a single world, which gives the array one row per world: a structural change).

        Args:
            bulk_modulus, viscosity: a number, or one per selected tet; ≥ 0, finite.
            world: one world, or every world (``None``).
            tets: the tets to change (an index array, a slice such as the one :meth:`add` returned, or ``None``
                for all).
        """
        writes = {}
        for name, value in (("bulk_modulus", bulk_modulus), ("viscosity", viscosity)):
            if value is None:
                continue
            v = np.asarray(value, dtype=np.float64)
            if not (np.isfinite(v).all() and (v >= 0.0).all()):
                raise ConfigError(f"the volume term's {name} must be finite and >= 0, got {value!r}")
            writes[name] = v
        self._write_values(writes, world=world, tets=tets)

    # -- the protocol ----------------------------------------------------------------------------------------------

    def spec(self, model, *, linear: bool = False) -> VolumeSpec:
        return VolumeSpec(incidence=self.shape, precomputed=self.precompute)

    def arrays(self, model, *, stiffness=None):
        arrays = volume_arrays_type(model.scalar)()
        arrays.indices = self._indices
        arrays.rest_volume = self._rest_volume
        arrays.bulk_modulus = self._live("bulk_modulus") if stiffness is None else stiffness
        arrays.viscosity = self._live("viscosity")
        arrays.pressure = self._pressure
        arrays.incidence = self.incidence
        return arrays

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None) -> np.ndarray:
        """The Gauss-Newton block (K/V₀) ∇_aV ∇_bVᵀ has spectral norm (K/V₀)|∇_aV||∇_bV|: row a gains it for b = a
        and for every free b ≠ a (at the model's initial positions)."""
        worlds, n = model.world_count, model.particle_count
        tets = self.tets
        values = self.values("bulk_modulus") if stiffness is None else stiffness
        k = np.broadcast_to(np.asarray(values, dtype=np.float64), (worlds, len(tets))) / self.rest_volume
        x = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
        norms = np.linalg.norm(volume_gradients(x, tets), axis=-1)  # [worlds, t, 4]
        free_norms = norms * free[:, tets]
        weights = k[..., None] * norms * (free_norms.sum(axis=-1, keepdims=True) - free_norms + norms)
        entries = (np.arange(worlds) * n)[:, None, None] + tets[None]
        rows = np.bincount(entries.ravel(), weights=weights.ravel(), minlength=worlds * n)
        return rows.reshape(worlds, n)


def inverted_tets(positions: np.ndarray, family: VolumeFamily) -> np.ndarray:
    """How many of the family's tets are inverted (V ≤ 0 against their positive rest volume) in each world, for
    positions [world_count · particle_count, 3] or [world_count, particle_count, 3]; int, shape [world_count]."""
    model = family._model
    x = np.asarray(positions, dtype=np.float64).reshape(model.world_count, model.particle_count, 3)
    return (signed_volumes(x, family.tets) <= 0.0).sum(axis=1)


def add_volume_term(builder, topology, ids: np.ndarray, *, volume, method: str, youngs_modulus: float,
                    bulk_modulus: float | None, damping: float, source: str) -> slice:
    """The volume term of a soft body (``ModelBuilder.add_soft_body(volume=True)``): its topology's tets, with
    global particle indices ``ids``, added to the builder's :class:`VolumeFamily` (created on first use) with
    K = ``bulk_modulus`` or 2E/3, and kd = β K for the body's stiffness-proportional damping β = ``damping`` [s].
    Returns the slice of the family's elements."""
    if not isinstance(volume, (bool, np.bool_)):
        raise ConfigError(f"{source}: volume= must be True or False, got {volume!r} (K goes in bulk_modulus=)")
    if not volume:
        raise ConfigError(f"{source}: bulk_modulus= is the volume term's K: give volume=True with it")
    if topology.tets is None:
        raise ConfigError(f"{source}: the volume term needs tets, which the {method} method does not make: use "
                          "method='tetrahedral' or 'delaunay'")
    k = network_bulk_modulus(youngs_modulus) if bulk_modulus is None else checks.positive(
        f"{source}: bulk_modulus [Pa]", bulk_modulus)
    family = next((f for f in builder._families if isinstance(f, VolumeFamily)), None)
    if family is None:
        family = builder.add_family(VolumeFamily())
    tets = ids[topology.tets]
    return family.add(tets, builder.particle_positions(np.arange(int(tets.max()) + 1)), bulk_modulus=k,
                      viscosity=damping * k, source=source)
