"""The damping of a spring network's modes, as the stability advisor models it: for each world, the range of
kd/k ratios (stiffness-proportional damping) and c/m drag rates that :func:`~.stability.network_stable_step`
sweeps, from the springs' least damped ratio and the top mode's own ratio xᵀDx / xᵀKx on its
power-iteration vector (:func:`top_mode_ratios`), with each law's tangent stiffness at the state.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..core.model import Model
from ..core.springs import SpringFamily
from .omega import _stiffness_values, free_particles


def _damping_ranges(model: Model, stiffness: np.ndarray, modes: list, positions: wp.array | np.ndarray, *,
                    lowest_top: np.ndarray | None = None) -> list:
    """Each world's (kd/k values [s], c/m values [1/s]) for :func:`~.stability.network_stable_step`.

    kd/k: the springs' smallest ratio (the least damped modes, which explicit Euler and midpoint cannot
    integrate stably without damping) and the top mode's own ratio xᵀDx / xᵀKx on the world's
    power-iteration eigenvector x (D = Σₛ kdₛ d̂d̂ᵀ): a mode near ω_max strains the stiff springs, so the
    damping of soft, heavily damped families does not reach it. Without an eigenvector (``modes[w]`` is
    ``None``: Gershgorin) the largest ratio stands in for the top mode's, which is conservative for
    symplectic Euler but loose when the stiffest springs are the least damped. c/m: its extremes over the
    world's free particles (drag limits the slowest motions, each particle's velocity decaying at its own
    c/m), the largest with the damping the element families put on a particle's own motion (wind, handles:
    ``ElementFamily.damping_rates``), the smallest without (the wind damps only smooth motions). Stiffness,
    damping, masses and drag are each world's own.
    """
    worlds, n = model.world_count, model.particle_count
    free = free_particles(model)
    k_all = _tangent_stiffness(model, stiffness, positions)
    kd_all = model.world_values("spring_damping")
    mass_all = model.world_values("particle_mass")
    drag = model.world_values("drag")[:, 0]
    ends = model.spring_indices.numpy().reshape(-1, 2)
    q_all = np.asarray(positions if isinstance(positions, np.ndarray) else positions.numpy(), dtype=np.float64)
    q_all = q_all.reshape(worlds, n, 3)
    extra = sum((family.damping_rates(model, q_all) for family in model.extra_families),
                np.zeros((worlds, n)))
    rest_all = model.spring_rest_length.numpy().astype(np.float64)
    tops = _top_mode_ratios(k_all, (free, kd_all, ends, rest_all), modes, q_all)
    if lowest_top is not None:
        tops = np.fmin(tops, lowest_top)
    ranges = []
    for w in range(worlds):
        mass = mass_all[w][free[w]]
        rates = (np.concatenate([drag[w] / mass, (drag[w] + extra[w][free[w]]) / mass]) if len(mass)
                 else np.zeros(1))
        k, kd = k_all[w], kd_all[w]
        acting = (k > 0.0) & free[w][ends].any(axis=1)
        if not acting.any():
            ranges.append((np.zeros(1), rates))
            continue
        ratios = kd[acting] / k[acting]
        if modes[w] is None:
            ranges.append((ratios, rates))
            continue
        top = tops[w] if np.isfinite(tops[w]) else float(ratios.max())
        ranges.append((np.array([ratios.min(), top]), rates))
    return ranges


def _tangent_stiffness(model: Model, stiffness: np.ndarray, positions) -> np.ndarray:
    """Each world's springs' tangent stiffness [N/m] at ``positions``, shape [world_count, spring_count]."""
    springs = next((f for f in model.families if isinstance(f, SpringFamily)), None)
    k_all = np.broadcast_to(stiffness, (model.world_count, model.spring_count))
    if springs is not None:  # each law's tangent at the positions: kd/k is a ratio of tangents
        k_all = k_all * springs.tangent_factor(model, positions)
    return k_all


def top_mode_ratios(model: Model, stiffness, modes: list, positions) -> np.ndarray:
    """Each world's top-mode damping ratio xᵀDx / xᵀKx [s] on its power-iteration vector x (``modes[w]``,
    shape [particle_count, 3]) at ``positions`` [m], shape [world_count, particle_count, 3]: K the springs'
    tangent stiffness (transverse part clamped, as in the kernels), D their axial dampers. Explicit Euler's
    step limit for that mode is this ratio itself (h* = 2ζ/ω). NaN where ``modes[w]`` is ``None`` or no
    stretched direction carries stiffness. Shape [world_count]."""
    q_all = np.asarray(positions, dtype=np.float64).reshape(model.world_count, model.particle_count, 3)
    k_all = _tangent_stiffness(model, _stiffness_values(model, stiffness), q_all.reshape(-1, 3))
    return _top_mode_ratios(k_all, _ratio_arrays(model), modes, q_all)


def _ratio_arrays(model: Model) -> tuple:
    """What :func:`top_mode_ratios` reads of a model besides the stiffness and the state: (free particles
    [world_count, particle_count], kd [world_count, spring_count], spring ends [spring_count, 2], rest lengths
    [spring_count]), from the device."""
    return (free_particles(model), model.world_values("spring_damping"),
            model.spring_indices.numpy().reshape(-1, 2), model.spring_rest_length.numpy().astype(np.float64))


def _top_mode_ratios(k_all: np.ndarray, arrays: tuple, modes: list, q_all: np.ndarray) -> np.ndarray:
    """:func:`top_mode_ratios` from the tangent stiffness ``k_all`` [world_count, spring_count] and
    :func:`_ratio_arrays`."""
    free, kd_all, ends, rest_all = arrays
    tops = np.full(len(q_all), np.nan)
    for w in range(len(q_all)):
        k, kd = k_all[w], kd_all[w]
        acting = (k > 0.0) & free[w][ends].any(axis=1)
        if modes[w] is None or not acting.any():
            continue
        q = q_all[w]
        mode = modes[w] * free[w][:, None]
        i, j = ends[acting].T
        d = q[j] - q[i]
        length = np.linalg.norm(d, axis=1)
        coincident = length == 0.0  # no direction: no stiffness, no damping (as in the kernels)
        safe = np.where(coincident, 1.0, length)
        delta = mode[i] - mode[j]
        axial2 = (np.einsum("sk,sk->s", d, delta) / safe) ** 2
        rest = rest_all[acting]
        transverse = np.where(coincident, 0.0, np.maximum(1.0 - rest / safe, 0.0))  # clamped, as in K
        xkx = float((k[acting] * (axial2 + transverse * (np.einsum("sk,sk->s", delta, delta) - axial2))).sum())
        if xkx > 0.0:
            tops[w] = float((kd[acting] * axial2).sum()) / xkx
    return tops
