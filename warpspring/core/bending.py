"""Dihedral bending on the host: the hinge family's kernel spec and struct from the model's ``hinge_*``
arrays, its part of the advisor's Gershgorin bound, and the material of a family of hinges."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import checks
from ..errors import ConfigError
from ..kernels.hinges import HingeSpec, hinge_arrays_type
from .families import ElementFamily
from .hinges import dihedral_gradient


@dataclass(frozen=True)
class DihedralMaterial:
    """Stiffness and damping of dihedral (angular) springs on a mesh's interior edges.

    Attributes:
        ke: angular stiffness [N·m/rad], ≥ 0: the moment per radian of fold (energy ½ ke (θ - θ0)²).
        kd: angular damping [N·m·s/rad], ≥ 0: the moment per radian per second of folding.
        rest: "mesh" (rest angles from the mesh as given) or "flat" (every rest angle 0).
    """

    ke: float
    kd: float = 0.0
    rest: str = "mesh"

    def __post_init__(self):
        checks.non_negative("DihedralMaterial.ke", self.ke)
        checks.non_negative("DihedralMaterial.kd", self.kd)
        if self.rest not in ("mesh", "flat"):
            raise ConfigError(f"DihedralMaterial.rest must be 'mesh' or 'flat', got {self.rest!r}")


class HingeFamily(ElementFamily):
    """Dihedral springs on hinges of four particles (the model's ``hinge_*`` arrays and ``hinge_incidence``)."""

    name = "hinges"

    def __init__(self, model):
        self._model = model

    @property
    def element_count(self) -> int:
        return self._model.hinge_count

    def spec(self, model, *, linear: bool = False) -> HingeSpec:
        return HingeSpec(incidence=model.hinge_incidence_shape)

    def arrays(self, model, *, stiffness=None):
        hinges = hinge_arrays_type(model.scalar)()
        hinges.indices = model.hinge_indices
        hinges.rest_angle = model.hinge_rest_angle
        hinges.stiffness = model.hinge_stiffness if stiffness is None else stiffness
        hinges.damping = model.hinge_damping
        hinges.incidence = model.hinge_incidence
        return hinges

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None) -> np.ndarray:
        """The Gauss-Newton block ke ∇_aθ ∇_bθᵀ has spectral norm ke |∇_aθ| |∇_bθ|: row a gains it for b = a
        and for every free b ≠ a (at the model's initial positions)."""
        worlds, n = model.world_count, model.particle_count
        ids = model.hinge_indices.numpy().reshape(-1, 4)
        values = model.hinge_stiffness.numpy() if stiffness is None else stiffness
        k = np.broadcast_to(np.asarray(values, dtype=np.float64), (worlds, len(ids)))
        x = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)[:, ids]  # [worlds, h, 4, 3]
        norms = np.linalg.norm(dihedral_gradient(x[..., 0, :], x[..., 1, :], x[..., 2, :], x[..., 3, :]), axis=-1)
        free_norms = norms * free[:, ids]  # [worlds, h, 4]
        # Row a: ke |∇_aθ| (|∇_aθ| + Σ_{free b ≠ a} |∇_bθ|).
        weights = k[..., None] * norms * (free_norms.sum(axis=-1, keepdims=True) - free_norms + norms)
        entries = (np.arange(worlds) * n)[:, None, None] + ids[None]  # world-major entries of each member
        rows = np.bincount(entries.ravel(), weights=weights.ravel(), minlength=worlds * n)
        return rows.reshape(worlds, n)

    def describe_element(self, model, element: int) -> str:
        a, b, c, d = model.hinge_indices.numpy()[element]
        return f"hinge {element} (edge {a}-{b}, wings {c} and {d})"
