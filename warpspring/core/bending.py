"""Dihedral bending on the host: the hinge family's kernel spec and struct from the model's ``hinge_*``
arrays, its part of the advisor's Gershgorin bound, and the material of a family of hinges."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import checks
from ..errors import ConfigError
from ..kernels.hinges import HingeSpec, hinge_arrays_type
from .families import ElementFamily


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


def dihedral_gradients(x0: np.ndarray, x1: np.ndarray, x2: np.ndarray, x3: np.ndarray) -> np.ndarray:
    """∇θ of hinges (kernels/bending.py's closed form) in float64 NumPy: positions [m], shape [h, 3] each;
    returns [h, 4, 3] [1/m] (zero for degenerate hinges)."""
    e = x1 - x0
    n1 = np.cross(e, x2 - x0)
    n2 = np.cross(x3 - x0, e)
    length2 = np.einsum("ij,ij->i", e, e)
    a1 = np.einsum("ij,ij->i", n1, n1)
    a2 = np.einsum("ij,ij->i", n2, n2)
    ok = (length2 > 0.0) & (a1 > 0.0) & (a2 > 0.0)
    length = np.sqrt(length2)
    with np.errstate(divide="ignore", invalid="ignore"):
        g2 = np.where(ok[:, None], -(length / a1)[:, None] * n1, 0.0)
        g3 = np.where(ok[:, None], -(length / a2)[:, None] * n2, 0.0)
        s2 = np.where(ok, np.einsum("ij,ij->i", x2 - x0, e) / length2, 0.0)
        s3 = np.where(ok, np.einsum("ij,ij->i", x3 - x0, e) / length2, 0.0)
    g1 = -(s2[:, None] * g2 + s3[:, None] * g3)
    g0 = -(g1 + g2 + g3)
    return np.stack([g0, g1, g2, g3], axis=1)


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
        k = np.broadcast_to(model.hinge_stiffness.numpy().astype(np.float64), (worlds, len(ids)))
        q = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
        rows = np.zeros((worlds, n))
        for w in range(worlds):
            x = q[w][ids]  # [h, 4, 3]
            norms = np.linalg.norm(dihedral_gradients(x[:, 0], x[:, 1], x[:, 2], x[:, 3]), axis=2)  # [h, 4]
            free_norms = norms * free[w][ids]
            for a in range(4):
                others = free_norms.sum(axis=1) - free_norms[:, a] + norms[:, a]
                rows[w] += np.bincount(ids[:, a], weights=k[w] * norms[:, a] * others, minlength=n)
        return rows

    def describe_element(self, model, element: int) -> str:
        a, b, c, d = model.hinge_indices.numpy()[element]
        return f"hinge {element} (edge {a}-{b}, wings {c} and {d})"
