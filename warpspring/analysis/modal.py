"""Dense float64 modal analysis of a spring network linearised at a state of rest: the exact reference the
advisor (:mod:`.stability`) is measured against. Dense eigenproblems cost O(n³) in the free coordinates,
so this is for models of a few thousand free coordinates at most.

About positions x* where the model is at rest (a static equilibrium, say), small motions obey
M δẍ + D δẋ + K δx = 0 with, over the free particles' coordinates:

* K = Σₛ kₛ [d̂d̂ᵀ + (1 - L/l)⁺ (I - d̂d̂ᵀ)] on each spring's 2 × 2 block pattern: the tangent stiffness,
  its transverse part clamped at compression as in the power iteration's kernels;
* D = Σₛ kdₛ d̂d̂ᵀ (the axial dampers; at rest their dependence on d̂ multiplies a zero velocity) plus the
  drag c on each particle;
* M the particle masses.

The undamped modes x_i (M-orthonormal, K x_i = ω_i² M x_i) carry the damping ratios
ζ_i = x_iᵀ D x_i / (2 ω_i), the modal damping the advisor assumes (exact where D is diagonal in the modes,
as for uniform Rayleigh damping); :func:`.stability.step_matrix` gives the whole system's one-step map,
which checks it. Linear springs and drag only: other element families raise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.model import Model
from ..errors import ConfigError
from .stability import free_particles, spectral_radius, step_matrix


@dataclass(frozen=True)
class Modes:
    """The undamped modes of a :class:`Linearisation`.

    Attributes:
        omega: angular frequencies ω_i [rad/s], ascending, float64, shape [n].
        zeta: modal damping ratios x_iᵀ D x_i / (2 ω_i) [-], shape [n] (0 where ω_i = 0).
        shapes: the M-orthonormal mode shapes x_i as columns [m/√kg], shape [n, n].
    """

    omega: np.ndarray
    zeta: np.ndarray
    shapes: np.ndarray

    def growth(self, integrator: str, dt: float, *, top: int | None = None) -> np.ndarray:
        """Each mode's growth factor per step ρ_i under ``integrator`` at step ``dt`` [s] (the spectral
        radius of its amplification matrix), shape [n], or of the ``top`` highest modes only."""
        picked = slice(None) if top is None else slice(len(self.omega) - top, None)
        return np.array([spectral_radius(integrator, w * dt, z) for w, z in zip(self.omega[picked],
                                                                                    self.zeta[picked])])


@dataclass(frozen=True)
class Linearisation:
    """M, K and D of a model about a state of rest, over its free particles' coordinates (module docstring).

    Attributes:
        mass: each coordinate's mass [kg], float64, shape [n] (n = 3 × the free particles).
        stiffness: K [N/m], float64, shape [n, n], symmetric positive semi-definite.
        damping: D [N·s/m], float64, shape [n, n], symmetric positive semi-definite.
    """

    mass: np.ndarray
    stiffness: np.ndarray
    damping: np.ndarray

    def modes(self) -> Modes:
        """The undamped modes and their modal damping ratios (dense ``eigh``)."""
        scale = 1.0 / np.sqrt(self.mass)
        eigenvalues, vectors = np.linalg.eigh(scale[:, None] * self.stiffness * scale[None, :])
        omega = np.sqrt(np.maximum(eigenvalues, 0.0))
        shapes = scale[:, None] * vectors
        dissipation = np.einsum("in,ij,jn->n", shapes, self.damping, shapes)
        zeta = np.divide(dissipation, 2.0 * omega, out=np.zeros_like(omega), where=omega > 0.0)
        return Modes(omega=omega, zeta=zeta, shapes=shapes)

    def step_matrix(self, integrator: str, dt: float) -> np.ndarray:
        """The one-step map of the linear system under ``integrator`` (:func:`.stability.step_matrix`)."""
        return step_matrix(integrator, dt, self.mass, self.stiffness, self.damping)


def linearise(model: Model, positions, *, world: int = 0) -> Linearisation:
    """M, K and D of ``world`` of ``model`` about ``positions`` [m] (shape [world_count · particle_count, 3]
    or [particle_count, 3] for the world alone), with that world's stiffness, damping, masses, drag and
    (plastic) rest lengths. Linear springs and drag only."""
    others = [f.name for f in model.families if f.name != "springs"]
    if others or model.spring_material_law.per_spring:
        what = ", ".join(others + (["non-linear spring laws"] if model.spring_material_law.per_spring else []))
        raise ConfigError(f"the dense linearisation covers linear springs and drag, not {what}: "
                          "use the advisor (warpspring.analysis.stability.advise) for this model")
    if not 0 <= world < model.world_count:
        raise ConfigError(f"world must be in [0, {model.world_count}), got {world}")
    n = model.particle_count
    q = np.asarray(positions, dtype=np.float64).reshape(-1, n, 3)
    q = q[world] if len(q) > 1 else q[0]
    stiffness = model.world_values("spring_stiffness")[world].astype(np.float64)
    damping = model.world_values("spring_damping")[world].astype(np.float64)
    rest = model.spring_rest_lengths()[world]
    i, j = model.spring_indices.numpy().reshape(-1, 2).T
    d = q[j] - q[i]
    length = np.linalg.norm(d, axis=1)
    acting = (rest >= 0.0) & (length > 0.0)  # broken or coincident springs carry nothing
    unit = d[acting] / length[acting, None]
    axial = unit[:, :, None] * unit[:, None, :]
    across = np.maximum(1.0 - rest[acting] / length[acting], 0.0)
    k_blocks = stiffness[acting, None, None] * (axial + across[:, None, None] * (np.eye(3) - axial))
    d_blocks = damping[acting, None, None] * axial
    K, D = np.zeros((3 * n, 3 * n)), np.zeros((3 * n, 3 * n))
    for matrix, blocks in ((K, k_blocks), (D, d_blocks)):
        view = matrix.reshape(n, 3, n, 3)
        for a, b, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
            np.add.at(view, (a[acting], slice(None), b[acting], slice(None)), sign * blocks)
    D[np.diag_indices(3 * n)] += float(model.world_values("drag")[world, 0])
    free = np.repeat(free_particles(model)[world], 3)
    mass = np.repeat(model.world_values("particle_mass")[world].astype(np.float64), 3)[free]
    return Linearisation(mass=mass, stiffness=K[np.ix_(free, free)], damping=D[np.ix_(free, free)])


def top_mode_limit(linearisation_at, integrator: str, dt: float, *, start: float, rtol: float = 1.0e-4) -> float:
    """The stiffness [N/m] from which the highest mode grows (ρ_top > 1) under ``integrator`` at step ``dt`` [s]:
    bracketed by doubling or halving from ``start`` [N/m], then bisected on log ke to ``rtol``.
    ``linearisation_at(ke)`` gives the :class:`Linearisation` at ke (e.g. about that stiffness's static
    equilibrium); ρ_top must grow with ke, as it does for a stiffer cloth at a fixed step."""
    def stable(ke: float) -> bool:
        return float(linearisation_at(ke).modes().growth(integrator, dt, top=1)[0]) <= 1.0

    low = high = float(start)
    for _ in range(64):
        if stable(high):
            low, high = high, 2.0 * high
        elif not stable(low):
            low, high = 0.5 * low, low
        else:
            break
    else:
        raise ConfigError(f"no stiffness within 2^±64 of {start:.4g} N/m brackets the top mode's limit for "
                          f"{integrator} at dt = {dt:.4g} s")
    return log_bisect(stable, low, high, rtol)


def log_bisect(holds, low: float, high: float, rtol: float) -> float:
    """The largest value where ``holds`` is true, by bisection on the logarithm of [low, high] (``holds(low)``
    true, ``holds(high)`` false) until high / low ≤ 1 + ``rtol``: the last ``low``."""
    while high / low > 1.0 + rtol:
        middle = float(np.sqrt(low * high))
        low, high = (middle, high) if holds(middle) else (low, middle)
    return low
