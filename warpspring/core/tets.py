"""What the element families of a soft body's tetrahedra share (the volume term, ``core/volume.py``; the
neo-Hookean tets, ``core/neohookean.py``): tets appended body by body, wound so that V₀ > 0 and refused where
V₀ ≈ 0; an incidence table of roles 0..3; per-tet values that live on the device, one row for every world or
one per world, written between frames without compiling; and, where ``precompute`` is on, a pass over the tets
before the corners gather (``at_time``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from .families import ElementFamily, build_incidence
from .soft_topologies import signed_volumes, wound_tets

__all__ = ["TetFamily", "signed_volumes", "wound_tets"]


class TetFamily(ElementFamily):
    """An element family of tets with live per-tet values. A subclass names its values (``live_names``, the one
    whose non-zero makes forces depend on velocity: ``damper``), its phrase in messages (``label``), its
    elements' (``element_label``) and the ``FamilyFuncs`` kernel ``at_time`` launches where precomputed
    (``precompute_kernel``), and calls :meth:`_add_tets`, :meth:`_finalize_tets` and :meth:`_write_values`."""

    live_names: tuple = ()
    #: Particles per element: 4 (linear tets) or 10 (quadratic: corners first), and the index vector type on the device.
    nodes: int = 4
    index_type = wp.vec4i
    damper: str = ""
    label: str = ""
    element_label: str = ""
    precompute_kernel: str = ""

    def __init__(self, *, precompute: bool = True):
        self.precompute = bool(precompute)
        self._tets: list[np.ndarray] = []
        self._rest: list[np.ndarray] = []
        self._values = {name: [] for name in self.live_names}
        self._live_arrays: dict[str, wp.array] = {}
        self._model = None

    # -- building -----------------------------------------------------------------------------------------

    def _add_tets(self, tets, positions, values: dict, source: str) -> tuple[slice, np.ndarray, np.ndarray]:
        """Validate and append one body's tets with each live value (a number per name); returns the slice of
        the family's elements they occupy, the tets as wound and their rest volumes V₀ [m³]."""
        tets = np.array(tets, dtype=np.int64).reshape(-1, self.nodes)
        positions = np.asarray(positions, dtype=np.float64)
        if len(tets) == 0:
            raise ConfigError(f"{source}: {self.label} needs tetrahedra, and the body has none")
        if tets.min() < 0 or tets.max() >= len(positions):
            raise ConfigError(f"{source}: a tet's particle index is outside 0..{len(positions) - 1}")
        tets, volume = self._wind(positions, tets)
        edges = np.linalg.norm(positions[tets[:, 1:4]] - positions[tets[:, :1]], axis=-1).max(axis=1)
        flat = np.flatnonzero(~(volume > 1.0e-12 * edges**3))
        if len(flat):
            raise ConfigError(f"{source}: tet {int(flat[0])} {tets[flat[0]].tolist()} has no volume at rest "
                              f"({len(flat)} such tets): {self.label} needs V₀ > 0")
        start = self.element_count
        self._tets.append(tets)
        self._rest.append(volume)
        for name in self.live_names:
            self._values[name].append(np.full(len(tets), float(values[name])))
        return slice(start, start + len(tets)), tets, volume

    def _wind(self, positions: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``tets`` rewound so that V₀ > 0 (corners 0..3), and their volumes |V₀| [m³]."""
        return wound_tets(positions, tets)

    @property
    def element_count(self) -> int:
        return sum(len(t) for t in self._tets)

    @property
    def tets(self) -> np.ndarray:
        """Every tet's particles (per-world indices, wound so that V₀ > 0), int64, shape [tet_count, nodes]."""
        return np.concatenate(self._tets) if self._tets else np.zeros((0, self.nodes), dtype=np.int64)

    @property
    def rest_volume(self) -> np.ndarray:
        """V₀ [m³] of every tet, float64, shape [tet_count]."""
        return np.concatenate(self._rest) if self._rest else np.zeros(0)

    def _finalize_tets(self, model) -> None:
        """The incidence table (roles 0..nodes - 1), the indices, V₀ and one row of each live value on the device."""
        device, scalar = model.device, model.scalar
        tets = self.tets
        roles = np.broadcast_to(np.arange(self.nodes), tets.shape)
        self.incidence, self.shape = build_incidence(tets, model.particle_count, roles, -1, device=device)
        self._indices = wp.array(tets.astype(np.int32), dtype=self.index_type, device=device)
        self._rest_volume = wp.array(self.rest_volume, dtype=scalar, device=device)
        self._live_arrays = {name: wp.array(np.concatenate(v)[None, :], dtype=scalar, device=device)
                             for name, v in self._values.items()}
        self._model = model

    # -- live values -------------------------------------------------------------------------------------------

    def values(self, name: str) -> np.ndarray:
        """Every world's value ``name`` (one of ``live_names``) per tet, float64, [world_count, tet_count]."""
        data = self._live(name).numpy().astype(np.float64)
        return np.broadcast_to(data, (self._model.world_count, data.shape[1])).copy()

    def _live(self, name: str) -> wp.array:
        if self._model is None:
            raise ConfigError(f"{self.label}'s values live on the device: finalize the model first")
        if name not in self._live_arrays:
            raise ConfigError(f"{self.label} has no value {name!r}: {', '.join(self.live_names)}")
        return self._live_arrays[name]

    def _write_values(self, writes: dict, *, world: int | None, tets) -> None:
        """Write each validated value (a number, or one per selected tet) to ``tets`` (an index array, a slice,
        ``None``: all) of ``world`` (``None``: every world). The first write to a single world of a multi-world
        model gives the array one row per world: a structural change."""
        model = self._model
        if model is None:
            raise ConfigError(f"{self.label}'s values live on the device: finalize the model first")
        select = np.arange(self.element_count)[slice(None) if tets is None else tets]
        if world is not None:
            world = checks.count("world", world, minimum=0)
            if world >= model.world_count:
                raise ConfigError(f"world {world} does not exist: the model has worlds 0..{model.world_count - 1}")
        for name, value in writes.items():
            rows = self._live(name).numpy().astype(np.float64)
            if world is not None and rows.shape[0] == 1 and model.world_count > 1:
                rows = np.repeat(rows, model.world_count, axis=0)
            try:
                rows[slice(None) if world is None else world, select] = value
            except ValueError:
                raise ConfigError(f"{self.label}'s {name} must be a number or one per selected tet ({len(select)}), "
                                  f"got shape {np.shape(value)}") from None
            self._store(model, name, rows.astype(np.float32 if model.scalar is wp.float32 else np.float64))
        model.input_version += 1  # the elastic energy changed without work: the guard re-bases

    def _store(self, model, name: str, rows: np.ndarray) -> None:
        """Write ``rows`` (the model's dtype) to the live value ``name``: in place, or (one row for every world
        against one per world) as a new array, a structural change."""
        array = self._live(name)
        if rows.shape == array.shape:
            array.assign(rows)
        else:
            self._live_arrays[name] = wp.array(rows, dtype=model.scalar, device=model.device)
            model._structure_changed()

    def live_arrays(self) -> dict:
        """Each live value's array, [1 or world_count, tet_count] (checkpoints)."""
        return dict(self._live_arrays)

    def restore_live_array(self, model, name: str, values: np.ndarray) -> None:
        """In place, or (one row for every world against one per world) a new array: a structural change."""
        self._store(model, name, values)
        model.input_version += 1  # the elastic energy changed without work: the guard re-bases

    # -- the protocol ----------------------------------------------------------------------------------------------

    def velocity_dependent(self, model) -> bool:
        """Whether some tet's damper is on in some world."""
        return bool((self.values(self.damper) != 0.0).any())

    def time_dependent(self, model) -> bool:
        """Only where precomputed (each corner's gather otherwise evaluates its tets' factors itself)."""
        return self.precompute

    def at_time(self, model, state) -> None:
        """Where precomputed: each tet's shared factors at ``state``, before the corners gather them."""
        if not self.time_dependent(model):
            return
        wp.launch(getattr(self.spec(model).funcs(model.scalar), self.precompute_kernel),
                  dim=(model.world_count, self.element_count),
                  inputs=[model.particle_count, state.particle_q, state.particle_qd, self.arrays(model)],
                  device=model.device)

    def describe_element(self, model, element: int) -> str:
        a, b, c, d = self.tets[element]
        return f"{self.element_label} {element} (particles {a}, {b}, {c}, {d})"
