"""The spring family on the host: its kernel spec and struct from the model's ``spring_*`` arrays, and its
part of the advisor's Gershgorin bound."""

from __future__ import annotations

import numpy as np

from ..kernels.springs import HOOKE, SpringSpec, spring_arrays_type
from .families import ElementFamily


class SpringFamily(ElementFamily):
    """Springs between two particles (the model's ``spring_*`` arrays and ``spring_incidence``)."""

    name = "springs"

    def __init__(self, model):
        self._model = model

    @property
    def element_count(self) -> int:
        return self._model.spring_count

    def spec(self, model, *, linear: bool = False) -> SpringSpec:
        return SpringSpec(
            incidence=model.spring_incidence_shape,
            law=HOOKE if linear else model.spring_law,
            gathered=model.spring_gather and not linear,
        )

    def arrays(self, model, *, stiffness=None):
        springs = spring_arrays_type(model.scalar)()
        springs.indices = model.spring_indices
        springs.rest_length = model.spring_rest_length
        springs.stiffness = model.spring_stiffness if stiffness is None else stiffness
        springs.damping = model.spring_damping
        springs.incidence = model.spring_incidence
        return springs

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None) -> np.ndarray:
        """Each clamped spring block has spectral norm ≤ kₛ (|T|/|d| ≤ kₛ when not compressed), so row i
        gains kₛ for its diagonal block and kₛ for the block of a free neighbour."""
        worlds, n = model.world_count, model.particle_count
        if model.spring_count == 0:
            return np.zeros((worlds, n))
        values = model.spring_stiffness.numpy() if stiffness is None else stiffness
        k = np.broadcast_to(np.asarray(values, dtype=np.float64), (worlds, model.spring_count))
        i, j = model.spring_indices.numpy().reshape(-1, 2).T
        offset = (np.arange(worlds) * n)[:, None]
        wi, wj = (offset + i).ravel(), (offset + j).ravel()  # world-major entries of each world's spring ends
        rows = np.zeros(worlds * n)
        for ends, weights in ((wi, k), (wj, k), (wi, k * free[:, j]), (wj, k * free[:, i])):
            rows += np.bincount(ends, weights=weights.ravel(), minlength=worlds * n)
        return rows.reshape(worlds, n)

    def describe_element(self, model, element: int) -> str:
        a, b = model.spring_indices.numpy()[element]
        return f"spring {element} (particles {a}-{b})"
