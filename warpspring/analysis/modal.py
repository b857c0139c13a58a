"""Dense float64 modal analysis of a spring network linearised at a state of rest: the exact reference the
advisor (:mod:`.advisor`) is measured against. Dense eigenproblems cost O(n³) in the free coordinates,
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
import warp as wp

from ..core.forces import eval_forces
from ..core.model import Model
from ..errors import ConfigError
from .omega import free_particles, pair_block_matrix, top_eigenpair
from .stability import spectral_radius, step_matrix


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
    if others:
        raise ConfigError(f"the dense linearisation covers linear springs and drag, not {', '.join(others)}: "
                          "use the advisor (warpspring.analysis.advisor.advise) for this model, or top_modes "
                          "for its springs' top mode")
    _check_world(model, world)
    n = model.particle_count
    q = np.asarray(positions, dtype=np.float64).reshape(-1, n, 3)
    K, D = spring_tangent(model, q[world] if len(q) > 1 else q[0], world=world)
    D = D.toarray()
    D[np.diag_indices(3 * n)] += float(model.world_values("drag")[world, 0])
    free = np.repeat(free_particles(model)[world], 3)
    mass = np.repeat(model.world_values("particle_mass")[world].astype(np.float64), 3)[free]
    return Linearisation(mass=mass, stiffness=K.toarray()[np.ix_(free, free)], damping=D[np.ix_(free, free)])


def spring_tangent(model: Model, positions, *, world: int = 0) -> tuple:
    """The springs' tangent stiffness K [N/m] and their dampers' D [N·s/m] (module docstring) of ``world`` at
    ``positions`` [m] (that world's particles, shape [particle_count, 3]), ``scipy.sparse.csr_matrix`` [3n, 3n]
    each over every particle's coordinates, kinematic ones included. Linear springs only."""
    springs = _Springs(model)
    return springs.stiffness_matrix(positions, world), springs.damping_matrix(positions, world)


class _Springs:
    """A model's linear springs as the host reads them once (ends, and each world's ke, kd and rest lengths), to
    assemble their tangent stiffness and damping at any number of states."""

    def __init__(self, model: Model):
        if model.spring_material_law.per_spring:
            raise ConfigError("the springs' tangent here is that of linear springs, not of non-linear spring laws: "
                              "use the advisor (warpspring.analysis.advisor.advise) for this model")
        self.n = model.particle_count
        self.i, self.j = model.spring_indices.numpy().reshape(-1, 2).T
        self.ke = model.world_values("spring_stiffness").astype(np.float64)
        self.kd = model.world_values("spring_damping").astype(np.float64)
        self.rest = model.spring_rest_lengths()

    def _axes(self, positions, world: int) -> tuple:
        """(acting, their unit directions d̂ [s, 3], d̂d̂ᵀ [s, 3, 3], (1 - L/l)⁺ [s]) at ``positions``."""
        q = np.asarray(positions, dtype=np.float64).reshape(self.n, 3)
        rest = self.rest[world]
        d = q[self.j] - q[self.i]
        length = np.linalg.norm(d, axis=1)
        acting = (rest >= 0.0) & (length > 0.0)  # broken or coincident springs carry nothing
        unit = d[acting] / length[acting, None]
        across = np.maximum(1.0 - rest[acting] / length[acting], 0.0)
        return acting, unit[:, :, None] * unit[:, None, :], across

    def stiffness_matrix(self, positions, world: int):
        acting, axial, across = self._axes(positions, world)
        blocks = self.ke[world, acting, None, None] * (axial + across[:, None, None] * (np.eye(3) - axial))
        return pair_block_matrix(self.n, self.i[acting], self.j[acting], blocks)

    def damping_matrix(self, positions, world: int):
        acting, axial, _ = self._axes(positions, world)
        return pair_block_matrix(self.n, self.i[acting], self.j[acting], self.kd[world, acting, None, None] * axial)


def _check_world(model: Model, world: int) -> None:
    if not 0 <= world < model.world_count:
        raise ConfigError(f"world must be in [0, {model.world_count}), got {world}")


#: The force terms :func:`top_modes` takes along the springs' top mode: the springs, and terms whose stiffness
#: and damping only shift it a little (wind on the cloth's triangles, PD handles).
ALONG_SPRINGS = ("springs", "wind triangles", "handle grabs")


@dataclass(frozen=True)
class TopModes:
    """Each world's highest mode, frozen at a state that need not be at rest (:func:`top_modes`).

    Attributes:
        omega: ω = √(xᵀ K x) [rad/s], shape [world_count], K = −∂F/∂x of the whole model's forces.
        zeta: ζ = xᵀ D x / (2ω) [-], shape [world_count], D = −∂F/∂v. Both NaN in a world whose state is not
            finite or that has no stiffness along x (torn apart).
        shapes: x, the top mode of the springs' tangent stiffness, M-orthonormal (xᵀ M x = 1) [m/√kg], shape
            [world_count, particle_count, 3], 0 on kinematic particles. NaN everywhere in a world whose state
            is not finite.
    """

    omega: np.ndarray
    zeta: np.ndarray
    shapes: np.ndarray

    def growth(self, integrator: str, dt: float) -> np.ndarray:
        """Each world's top-mode growth factor per step ρ [-] under ``integrator`` at step ``dt`` [s], shape
        [world_count] (NaN where the state was not finite)."""
        return np.array([spectral_radius(integrator, w * dt, z) if np.isfinite(w) and np.isfinite(z) else np.nan
                         for w, z in zip(self.omega, self.zeta)])


def top_modes(model: Model, positions, velocities, time, *, control=None, starts=None,
              step: float = 1.0e-6) -> TopModes:
    """Every world's highest mode frozen at a state in motion: the top mode x of its springs' tangent
    stiffness there (:func:`spring_tangent`, sparse Lanczos), with ω² and ζ the Rayleigh quotients of the
    whole model's force Jacobian along x, by central differences of :func:`~warpspring.core.forces.eval_forces`
    (the model's own kernels: the springs, their dampers, drag, wind, handles, at the state's time). To first
    order in what the other terms add to the springs, these are the top mode's ω and ζ; at a static
    equilibrium of springs and drag they are :meth:`Linearisation.modes`' highest.

    Args:
        model: a float64 model (the differences need its precision) whose force terms are in
            ``ALONG_SPRINGS``.
        positions, velocities: the state [m], [m/s], shape [world_count · particle_count, 3] (any precision).
        time: the state's time [s], one number or one per world.
        control: the run's Control, or ``None``.
        starts: earlier ``shapes`` to start each world's Lanczos from (a sequence of nearby states).
        step: the largest displacement [m] (and velocity change [m/s]) of a coordinate in the differences.
    """
    if model.scalar is not wp.float64:
        raise ConfigError("top_modes differentiates the model's forces, which needs float64: build the model with "
                          "precision='float64'")
    others = [f.name for f in model.families if f.name not in ALONG_SPRINGS]
    if others or model.spring_count == 0:
        raise ConfigError("top_modes follows the springs' top mode, with wind and handles along it; this model has "
                          f"{', '.join(others) if others else 'no springs'}")
    worlds, n = model.world_count, model.particle_count
    springs = _Springs(model)
    q = np.asarray(positions, dtype=np.float64).reshape(worlds, n, 3)
    v = np.asarray(velocities, dtype=np.float64).reshape(worlds, n, 3)
    finite = np.isfinite(q).all(axis=(1, 2)) & np.isfinite(v).all(axis=(1, 2))
    free = np.repeat(free_particles(model), 3, axis=1)
    mass = np.repeat(model.world_values("particle_mass").astype(np.float64), 3, axis=1)
    starts = None if starts is None else np.asarray(starts, dtype=np.float64).reshape(worlds, 3 * n)
    shapes = np.full((worlds, 3 * n), np.nan)
    for w in np.flatnonzero(finite):
        keep = free[w]
        start = None if starts is None else starts[w, keep]
        K = springs.stiffness_matrix(q[w], w)
        shapes[w] = 0.0
        shapes[w, keep] = top_eigenpair(K[keep][:, keep], mass[w, keep],
                                        start=start if start is not None and np.isfinite(start).all() else None)[1]
    shapes = shapes.reshape(worlds, n, 3)
    reach = step / np.where(finite, np.abs(np.nan_to_num(shapes)).max(axis=(1, 2)), 1.0)[:, None, None]
    probe = model.state()
    probe.time.assign(np.broadcast_to(np.asarray(time, dtype=np.float64), (worlds,)))

    def forces(dq, dv):
        probe.particle_q.assign((q + dq).reshape(-1, 3))
        probe.particle_qd.assign((v + dv).reshape(-1, 3))
        eval_forces(model, probe, control)
        return probe.particle_f.numpy().astype(np.float64).reshape(worlds, n, 3)

    dx = np.nan_to_num(reach * shapes)
    along_x = -(forces(dx, 0.0) - forces(-dx, 0.0)) / (2.0 * reach)  # K x
    along_v = -(forces(0.0, dx) - forces(0.0, -dx)) / (2.0 * reach)  # D x
    omega = np.sqrt(np.maximum(np.einsum("wij,wij->w", shapes, along_x), 0.0))
    finite &= omega > 0.0  # a world torn apart: no stiffness along x
    zeta = np.einsum("wij,wij->w", shapes, along_v) / (2.0 * np.where(finite, omega, 1.0))
    return TopModes(omega=np.where(finite, omega, np.nan), zeta=np.where(finite, zeta, np.nan), shapes=shapes)


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
