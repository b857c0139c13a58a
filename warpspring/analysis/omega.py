"""ω_max of a model, the highest angular frequency of its elements: the estimate the stability advisor
and the run-time watch use, its upper bounds, and the host eigensolvers of the float64 references.

**ω_max of a model** (:func:`estimate_omega_max`): power iteration on M⁻¹K on the model's device, with K
the springs' stiffness matrices at the current positions (compressive transverse part clamped, so
K ⪰ 0; clamping only adds stiffness, so the estimate is not lowered by it), pinned particles filtered
out, matrix-free through a gather over the incidence table (``kernels/stability.py``). Its Rayleigh
quotient never exceeds λ_max; the Gershgorin bound ω_max² ≤ maxᵢ (Σₛ kₛ + Σ_{s to free j} kₛ) / mᵢ
(:func:`gershgorin_omega_max`, host NumPy; each clamped spring block has spectral norm kₛ) never falls
below it, and is the cheap fallback. A model of several worlds gets one ω_max per world (each world's
stiffness and masses), all worlds iterating in the same launches, each to its own tolerance.

The power iteration's buffers and launches are :class:`PowerIteration`, shared by :func:`estimate_omega_max`
(to convergence) and the run-time watch (:class:`~warpspring.analysis.watch.StabilityWatch`), a few warm-started
iterations at a time; the advisor's dry run (:func:`~warpspring.analysis.under_load.transient_peak`) tracks the
top mode along a run by restarted Lanczos (:class:`Lanczos`), which reaches a mode that rises elsewhere sooner.
On the host, :func:`top_eigenpair` (sparse Lanczos) gives a stiffness matrix's top mode and
:func:`transverse_omega_max` the highest frequency of the stretched springs' undamped transverse stiffness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.kinematics import PARTICLE_KINEMATIC
from ..kernels.flatten import flat_launch
from ..kernels.linalg import reduce_lanes, reduce_launch_dim, sum_partials_kernel
from ..kernels.stability import (LZ_ALPHA, LZ_BETA, LZ_SLOTS, PI_LAMBDA, PI_PARTIALS, PI_RESIDUAL, PI_SCALARS,
                                 PI_XKX, lanczos_kernels, power_iteration_kernels)
from ..core.model import Model
from ..core.state import State
from ..core.springs import SPRING_LAWS, SpringFamily, spring_law_codes

# -- ω_max of a model ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class OmegaMaxEstimate:
    """The highest angular frequency of a model's springs by power iteration on M⁻¹K, per world.

    Attributes:
        world_omega_max: √θ [rad/s] of each world, θ its final Rayleigh quotient (θ ≤ λ_max(M⁻¹K)),
            float64, shape [world_count].
        world_iterations: power iterations each world ran, int, shape [world_count].
        world_residual: ‖M⁻¹Kx - θx‖_M / (θ‖x‖_M) of each world's final iterate [-], shape [world_count].
        world_converged: whether each world's residual reached the tolerance within the iteration budget,
            bool, shape [world_count].
        world_gershgorin: the Gershgorin upper bound on each world's ω_max [rad/s], shape [world_count]
            (:func:`world_gershgorin_omega_max`).
        world_mode: each world's final iterate, an approximate top mode shape [-], float64, shape
            [world_count, particle_count, 3], unit mass-norm, zero on pinned particles (zero everywhere in a
            world without stiffness).

    The scalar properties summarise all worlds: ``omega_max`` and ``mode`` are those of the stiffest world
    (``world``), ``iterations``, ``residual`` and ``gershgorin`` the largest over the worlds, ``converged``
    whether every world converged. For a single world they are its values.
    """

    world_omega_max: np.ndarray
    world_iterations: np.ndarray
    world_residual: np.ndarray
    world_converged: np.ndarray
    world_gershgorin: np.ndarray
    world_mode: np.ndarray

    @property
    def world(self) -> int:
        """The stiffest world (largest ω_max; the first of equals)."""
        return int(np.argmax(self.world_omega_max))

    @property
    def omega_max(self) -> float:
        """The largest ω_max over the worlds [rad/s]."""
        return float(self.world_omega_max[self.world])

    @property
    def iterations(self) -> int:
        """The most power iterations a world ran."""
        return int(self.world_iterations.max())

    @property
    def residual(self) -> float:
        """The largest final relative residual over the worlds [-]."""
        return float(self.world_residual.max())

    @property
    def converged(self) -> bool:
        """Whether every world converged."""
        return bool(self.world_converged.all())

    @property
    def gershgorin(self) -> float:
        """The largest Gershgorin bound over the worlds [rad/s]."""
        return float(self.world_gershgorin.max())

    @property
    def mode(self) -> np.ndarray:
        """The stiffest world's mode shape, shape [particle_count, 3]."""
        return self.world_mode[self.world]


def free_particles(model: Model) -> np.ndarray:
    """Which particles of each world move (not kinematic), bool, shape [world_count, particle_count] (reads
    the device once)."""
    flags = model.particle_flags.numpy().reshape(model.world_count, model.particle_count)
    return (flags & PARTICLE_KINEMATIC) == 0


def world_dynamic_inv_mass(model: Model) -> np.ndarray:
    """The inverse masses the dynamics sees in each world [1/kg], float64, shape [world_count,
    particle_count]: 1/m, and 0 for kinematic particles (reads the device)."""
    return np.where(free_particles(model), model.world_values("particle_inv_mass"), 0.0)


def _biphasic_ratio(model: Model) -> np.ndarray:
    """Each world's largest biphasic stiffness ratio [-], shape [world_count]: its live value and the top of
    its track; 1 without biphasic springs."""
    ratio = np.ones(model.world_count)
    if model.spring_law.biphasic:  # the stiffest the ratio gets, its track included
        ratio = np.maximum(ratio, model.world_values("biphasic_ratio")[:, 0])
        for w in range(model.world_count):
            track = model.track("biphasic_ratio", world=w)
            if track is not None:
                ratio[w] = max(ratio[w], float(track.values.max()))
    return ratio


def _stiffness_values(model: Model, stiffness) -> np.ndarray:
    """The spring stiffness [N/m] the analysis uses, float64, shape [1 or world_count, spring_count]: an
    override of shape [spring_count] (every world) or [world_count, spring_count], or the model's own — for
    biphasic springs their stiffer branch, ratio × ke, which bounds the step once a spring stretches past
    its knee."""
    worlds, count = model.world_count, model.spring_count
    if stiffness is None:
        values = model.spring_stiffness.numpy().astype(np.float64)
        ratio = _biphasic_ratio(model)
        if (ratio != 1.0).any():
            values = values * (ratio[:, None] if (ratio != ratio[0]).any() else ratio[0])
        return values
    values = stiffness.numpy() if isinstance(stiffness, wp.array) else np.asarray(stiffness)
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        values = values[None]
    if values.shape not in ((1, count), (worlds, count)):
        shapes = f"({count},)" + (f" or ({worlds}, {count})" if worlds > 1 else "")
        raise ConfigError(f"stiffness must have shape {shapes}, got {np.shape(stiffness)}")
    if not (np.isfinite(values).all() and (values >= 0.0).all()):
        raise ConfigError("stiffness must be finite and >= 0")
    return values


def _stiffness_array(model: Model, values: np.ndarray) -> wp.array:
    """``values`` (from :func:`_stiffness_values`) on the model's device in its precision."""
    dtype = np.float64 if model.scalar is wp.float64 else np.float32
    return wp.array(np.ascontiguousarray(values, dtype=dtype), dtype=model.scalar, device=model.device)


def _gershgorin_rows(model: Model, stiffness: np.ndarray, free: np.ndarray, positions=None) -> np.ndarray:
    """Each particle's Gershgorin row bound of the stiffness [N/m], float64, shape [world_count, particle_count]:
    every family's row bounds, summed (see :func:`_gershgorin`)."""
    rows = np.zeros((model.world_count, model.particle_count))
    overrides = {"springs": stiffness}
    for family in model.families:
        if isinstance(family, SpringFamily):
            rows += family.gershgorin_rows(model, free, stiffness, positions=positions)
            continue
        rows += family.gershgorin_rows(model, free, overrides.get(family.name))
    return rows


def _gershgorin(model: Model, stiffness: np.ndarray, free: np.ndarray, positions=None) -> np.ndarray:
    """Each world's Gershgorin bound [rad/s], shape [world_count], for spring stiffness rows ``stiffness`` and
    free particles ``free`` [world_count, particle_count]: every family's row bounds, summed. The springs'
    rows take each law's tangent at ``positions`` (default the model's initial ones; ``SpringFamily.
    tangent_factor``): a square spring counts as 2 ke |Δ| at that stretch, a tension/compression spring with
    the stiffness of the branch it is on."""
    rows = _gershgorin_rows(model, stiffness, free, positions)
    ratio = np.where(free, rows / model.world_values("particle_mass"), 0.0)
    return np.sqrt(ratio.max(axis=1)) if model.particle_count else np.zeros(model.world_count)


def world_gershgorin_omega_max(model: Model, *, stiffness=None) -> np.ndarray:
    """Upper bound [rad/s] on each world's ω_max from Gershgorin's theorem for 3 × 3 blocks (host NumPy),
    float64, shape [world_count].

    Row i of M⁻¹K holds the diagonal block Σₛ Kₛ / mᵢ and one block Kₛ / mᵢ per spring to a free particle;
    each clamped spring block has spectral norm kₛ, so λ_max ≤ maxᵢ (Σₛ kₛ + Σ_{s to free j} kₛ) / mᵢ over
    free particles, with each world's stiffness and masses. (2 Σₛ kₛ / mᵢ, the bound usually quoted, is
    this with every neighbour free.) Other element families add their own row bounds
    (``ElementFamily.gershgorin_rows``). 0 in a world without stiffness or free particles.

    Args:
        model: the model.
        stiffness: spring stiffness [N/m] to use instead of the model's, shape [spring_count] or
            [world_count, spring_count].
    """
    return _gershgorin(model, _stiffness_values(model, stiffness), free_particles(model))


def gershgorin_omega_max(model: Model, *, stiffness=None) -> float:
    """The largest of :func:`world_gershgorin_omega_max` over the worlds [rad/s] (for one world: its bound)."""
    return float(world_gershgorin_omega_max(model, stiffness=stiffness).max())


def estimate_omega_max(
    model: Model,
    *,
    state: State | None = None,
    stiffness=None,
    max_iterations: int = 1000,
    tolerance: float = 1.0e-3,
    seed: int = 0,
) -> OmegaMaxEstimate:
    """ω_max = √λ_max(M⁻¹K) of each world's springs by power iteration, all worlds in the same launches on
    the model's device.

    K is assembled matrix-free from the clamped spring stiffness matrices at ``state``'s positions (default
    the model's initial ones), with each world's stiffness and masses; pinned particles are filtered out.
    Each world stops when its relative residual ‖M⁻¹Kx - θx‖_M / (θ‖x‖_M) ≤ ``tolerance`` or after
    ``max_iterations``; its Rayleigh quotient θ then approximates λ_max from below, its relative error
    typically well under the residual (a residual of 1e-3 leaves ω_max within ~2e-4 on cloths). Every world
    starts from the same random vector (restricted to its free particles), so a world's result does not
    depend on the others: it is the one a model of that world alone gives.

    Args:
        model: the model.
        state: positions to linearise about; default the model's initial positions.
        stiffness: spring stiffness [N/m], shape [spring_count] (every world) or [world_count,
            spring_count]; default the model's, with biphasic springs at their stiffer branch (ratio × ke).
        max_iterations: iteration budget per world (≥ 1).
        tolerance: relative residual at which a world stops, in (0, 1).
        seed: seed of the random start vector.
    """
    _check_iteration(max_iterations, tolerance)
    return _power_iteration(model, _stiffness_values(model, stiffness), state, max_iterations, tolerance, seed)


def _check_iteration(max_iterations: int, tolerance: float) -> None:
    checks.count("max_iterations", max_iterations, minimum=1)
    if checks.positive("tolerance", tolerance) >= 1.0:
        raise ConfigError(f"tolerance must be a number in (0, 1), got {tolerance!r}")


class PowerIteration:
    """The device buffers and launches of power iteration on M⁻¹K for every world of a model at once
    (``kernels/stability.py``): :func:`estimate_omega_max` runs it to convergence in a ``capture_while``
    loop, the run-time :class:`~warpspring.analysis.watch.StabilityWatch` a few warm-started iterations at a
    time. ``stiffness`` as in :func:`estimate_omega_max` (values, shape [spring_count] or [world_count,
    spring_count]); ``start``: the initial iterate, shape [world_count, particle_count, 3]."""

    def __init__(self, model: Model, stiffness: np.ndarray, start: np.ndarray):
        worlds, n, device = model.world_count, model.particle_count, model.device
        self.model = model
        tiled = device.is_cuda
        self.lanes = reduce_lanes(n, model.block_dim, tiled)
        self.grid = reduce_launch_dim(worlds, n, self.lanes)
        self.kernels = power_iteration_kernels(model.scalar, model.family_specs(linear=True), tiled)
        self.sum_partials = sum_partials_kernel(tiled)
        self.element_arrays = model.element_arrays(linear=True, stiffness={"springs": _stiffness_array(model, stiffness)})
        self.x = wp.array(np.asarray(start).reshape(-1, 3), dtype=model.vec3, device=device)
        self.y = wp.zeros(worlds * n, dtype=model.vec3, device=device)
        self.partials = wp.zeros((worlds, self.grid[1], PI_PARTIALS), dtype=wp.float64, device=device)
        self.scalars = wp.zeros((worlds, PI_SCALARS), dtype=wp.float64, device=device)
        self.iteration = wp.zeros(worlds, dtype=wp.int32, device=device)
        self.active = wp.zeros(worlds, dtype=wp.int32, device=device)
        self.keep_going = wp.zeros(1, dtype=wp.int32, device=device)
        self.tolerance, self.max_iterations = 1.0e-3, 1

    def restart(self, running: np.ndarray, *, max_iterations: int, tolerance: float) -> None:
        """Iterate the worlds where ``running`` (bool, [world_count]) from the current iterate, each until
        its residual reaches ``tolerance`` or for ``max_iterations`` more iterations."""
        self.tolerance, self.max_iterations = float(tolerance), int(max_iterations)
        self.iteration.zero_()
        self.active.assign(np.asarray(running, dtype=np.int32))
        self.keep_going.assign(np.array([int(np.count_nonzero(running))], dtype=np.int32))

    def iterate(self, particle_q: wp.array) -> None:
        """One iteration about the positions ``particle_q`` on the current stream (device launches only)."""
        model, device = self.model, self.model.device
        product, normalize, condition = self.kernels
        flat_launch(
            product, dim=self.grid, block_dim=self.lanes, device=device,
            inputs=[model.particle_count, model.particle_flags, model.particle_mass, self.element_arrays, model.inputs,
                    particle_q, self.active, self.x],
            outputs=[self.y, self.partials],
        )
        wp.launch(self.sum_partials, dim=(model.world_count, self.lanes), block_dim=self.lanes, device=device,
                  inputs=[PI_XKX, PI_PARTIALS, self.partials], outputs=[self.scalars])
        wp.launch(normalize, dim=model.particle_dim, block_dim=model.block_dim, device=device,
                  inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, self.active, self.y,
                          self.scalars], outputs=[self.x])
        wp.launch(condition, dim=model.world_count, device=device,
                  inputs=[wp.float64(self.tolerance), self.max_iterations],
                  outputs=[self.scalars, self.iteration, self.active, self.keep_going])


class Lanczos:
    """``steps`` steps of Lanczos on M⁻¹K for every world of a model at once, restarted from the top Ritz vector
    (``kernels/stability.py``): what the advisor's dry run (:func:`~warpspring.analysis.under_load.transient_peak`)
    tracks ω_max with along a run. Started from a vector near the top mode, a Krylov space of a few steps finds a
    higher mode that rises elsewhere in the cloth far sooner than as many power iterations: along the 1.94 s dry run
    of the 32² folded cloth of :mod:`.stability_battery` (CPU), re-estimated every 1/240 s, 20 power iterations a
    re-estimate peak at 1146.36 rad/s, 10 at 1126.97 and 4 at 1107.54 (they stay on the mode they started on), where 4
    Lanczos steps peak at 1146.39 and float64 Lanczos to convergence at 1146.64.
    ``stiffness`` and ``start`` (shape [world_count, particle_count, 3]) as in :class:`PowerIteration`; the worlds
    that run: ``active`` (int32, [world_count]), all at first."""

    def __init__(self, model: Model, stiffness: np.ndarray, start: np.ndarray, *, steps: int):
        worlds, n, device = model.world_count, model.particle_count, model.device
        self.model, self.steps = model, checks.count("steps", steps, minimum=1)
        tiled = device.is_cuda
        self.lanes = reduce_lanes(n, model.block_dim, tiled)
        self.grid = reduce_launch_dim(worlds, n, self.lanes)
        self.product = power_iteration_kernels(model.scalar, model.family_specs(linear=True), tiled)[0]
        self.kernels = lanczos_kernels(model.scalar, tiled)
        self.sum_partials = sum_partials_kernel(tiled)
        self.element_arrays = model.element_arrays(linear=True, stiffness={"springs": _stiffness_array(model, stiffness)})
        self.basis = wp.zeros((steps + 1, worlds * n), dtype=model.vec3, device=device)
        self.rows = [self.basis[j] for j in range(steps + 1)]  # views made once: the CPU replays launches on them
        self.rows[0].assign(np.asarray(start).reshape(-1, 3))
        self.y = wp.zeros(worlds * n, dtype=model.vec3, device=device)
        self.partials = wp.zeros((worlds, self.grid[1], PI_PARTIALS), dtype=wp.float64, device=device)
        self.scalars = wp.zeros((worlds, PI_SCALARS), dtype=wp.float64, device=device)
        self.norm_partials = wp.zeros((worlds, self.grid[1], 1), dtype=wp.float64, device=device)
        self.norms = wp.zeros((worlds, 1), dtype=wp.float64, device=device)
        self.coefficients = wp.zeros((worlds, steps + 1, LZ_SLOTS), dtype=wp.float64, device=device)
        self.combination = wp.zeros((worlds, steps), dtype=wp.float64, device=device)
        self.active = wp.array(np.ones(worlds, dtype=np.int32), dtype=wp.int32, device=device)

    def expand(self, particle_q: wp.array) -> None:
        """The Krylov basis of the current v_0 about the positions ``particle_q`` (device launches only: capturable)."""
        model, device = self.model, self.model.device
        direction, advance, _ = self.kernels
        for j in range(self.steps):
            flat_launch(
                self.product, dim=self.grid, block_dim=self.lanes, device=device,
                inputs=[model.particle_count, model.particle_flags, model.particle_mass, self.element_arrays,
                        model.inputs, particle_q, self.active, self.rows[j]],
                outputs=[self.y, self.partials],
            )
            wp.launch(self.sum_partials, dim=(model.world_count, self.lanes), block_dim=self.lanes, device=device,
                      inputs=[PI_XKX, PI_PARTIALS, self.partials], outputs=[self.scalars])
            previous = self.rows[j - 1] if j else self.rows[self.steps]  # β_0 = 0: any finite row
            wp.launch(direction, dim=self.grid, block_dim=self.lanes, device=device,
                      inputs=[model.particle_count, model.particle_flags, model.particle_mass, model.particle_inv_mass,
                              self.active, j, self.scalars, self.y, previous],
                      outputs=[self.rows[j], self.coefficients, self.rows[j + 1], self.norm_partials])
            if j + 1 < self.steps:
                wp.launch(self.sum_partials, dim=(model.world_count, self.lanes), block_dim=self.lanes,
                          device=device, inputs=[0, 1, self.norm_partials], outputs=[self.norms])
                wp.launch(advance, dim=model.particle_dim, block_dim=model.block_dim, device=device,
                          inputs=[model.particle_count, self.active, j, self.norms],
                          outputs=[self.rows[j + 1], self.coefficients])

    def restart(self) -> np.ndarray:
        """Each world's top Ritz value's √ [rad/s] (0 where it does not run), shape [world_count], after
        :meth:`expand`; v_0 becomes the top Ritz vector (one host read of the tridiagonals)."""
        values = self.coefficients.numpy()
        running = self.active.numpy().astype(bool)
        theta = np.zeros(len(values))
        combination = np.zeros((len(values), self.steps))
        for w in np.flatnonzero(running):
            alpha, beta = values[w, :self.steps, LZ_ALPHA], values[w, 1:self.steps, LZ_BETA]
            if not (np.isfinite(alpha).all() and np.isfinite(beta).all()):
                theta[w] = math.nan
                continue
            ritz, vectors = np.linalg.eigh(np.diag(alpha) + np.diag(beta, 1) + np.diag(beta, -1))
            theta[w], combination[w] = ritz[-1], vectors[:, -1]
        self.combination.assign(combination)
        wp.launch(self.kernels[2], dim=self.model.particle_dim, block_dim=self.model.block_dim, device=self.model.device,
                  inputs=[self.model.particle_count, self.active, self.combination], outputs=[self.basis])
        return np.sqrt(np.maximum(theta, 0.0))

    @property
    def x(self) -> wp.array:
        """v_0: after :meth:`restart`, each world's top Ritz vector, M-normalised (a state-like array)."""
        return self.rows[0]


def _power_iteration(model: Model, stiffness: np.ndarray, state: State | None, max_iterations: int,
                     tolerance: float, seed: int) -> OmegaMaxEstimate:
    worlds, n = model.world_count, model.particle_count
    free = free_particles(model)
    bound = _gershgorin(model, stiffness, free, None if state is None else state.particle_q)
    start = np.random.default_rng(seed).normal(size=(n, 3))[None] * free[..., None]
    if not bound.any():
        return OmegaMaxEstimate(
            world_omega_max=np.zeros(worlds), world_iterations=np.zeros(worlds, dtype=np.int64),
            world_residual=np.zeros(worlds), world_converged=np.ones(worlds, dtype=bool), world_gershgorin=bound,
            world_mode=np.zeros((worlds, n, 3)),
        )
    iteration = PowerIteration(model, stiffness, start)
    # A world without stiffness or free particles has λ_max = 0: nothing to iterate.
    iteration.restart(bound > 0.0, max_iterations=max_iterations, tolerance=tolerance)
    q = model.particle_q if state is None else state.particle_q
    wp.capture_while(iteration.keep_going, lambda: iteration.iterate(q))
    values = iteration.scalars.numpy()
    residual = values[:, PI_RESIDUAL].copy()
    return OmegaMaxEstimate(
        world_omega_max=np.sqrt(np.maximum(values[:, PI_LAMBDA], 0.0)),
        world_iterations=iteration.iteration.numpy().astype(np.int64),
        world_residual=residual,
        world_converged=residual <= tolerance,
        world_gershgorin=bound,
        world_mode=iteration.x.numpy().astype(np.float64).reshape(worlds, n, 3),
    )



# -- on the host: sparse matrices and their top mode ----------------------------------------------------


def pair_block_matrix(n: int, i: np.ndarray, j: np.ndarray, blocks: np.ndarray):
    """Σₑ of a two-particle element's 3 × 3 ``blocks`` [e, 3, 3] placed +B on (i, i) and (j, j) and −B on
    (i, j) and (j, i): the stiffness or damping of springs (and their like) over the 3 ``n`` coordinates of
    n particles, a ``scipy.sparse.csr_matrix`` [3n, 3n] (duplicate entries summed)."""
    import scipy.sparse

    rows, cols, values = [], [], []
    for a, b, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
        rows.append((3 * a[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2).ravel())
        cols.append((3 * b[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1).ravel())
        values.append(sign * blocks.ravel())
    return scipy.sparse.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(cols))),
                                   shape=(3 * n, 3 * n))


def transverse_omega_max(model: Model, positions, world: int = 0, *, stiffness=None) -> float:
    """The highest frequency [rad/s] of ``world``'s springs' *transverse* stiffness at ``positions`` [m]
    (shape [world_count · particle_count, 3]): λ_max of M⁻¹K_t, K_t = Σₛ kₛ (1 - L/l)⁺ (I - d̂d̂ᵀ) across
    each stretched spring, which its axial damper does not damp; pinned particles held. Sparse Lanczos
    (``scipy.sparse.linalg.eigsh``) on the host; 0 where no spring is stretched."""
    n = model.particle_count
    free = free_particles(model)[world]
    q = np.asarray(positions if isinstance(positions, np.ndarray) else positions.numpy(), dtype=np.float64)
    q = q.reshape(model.world_count, n, 3)[world]
    i, j = model.spring_indices.numpy().reshape(-1, 2).T
    k = np.broadcast_to(_stiffness_values(model, stiffness), (model.world_count, model.spring_count))[world]
    d = q[j] - q[i]
    length = np.linalg.norm(d, axis=1)
    rest = model.spring_rest_lengths()[world]  # plastic springs: where they are now (negative: broken)
    stretched = (length > rest) & (rest >= 0.0)
    if not stretched.any() or not free.any():
        return 0.0
    i, j, d, length = i[stretched], j[stretched], d[stretched], length[stretched]
    # T/l: k (1 - L/l) for a linear spring, k Δ²/l = (k |Δ|)(1 - L/l) for a square one.
    tension_scale = np.where(spring_law_codes(model)[stretched] == SPRING_LAWS["square"],
                             length - rest[stretched], 1.0)
    across = k[stretched] * tension_scale * (1.0 - rest[stretched] / length)
    unit = d / length[:, None]
    blocks = across[:, None, None] * (np.eye(3)[None] - unit[:, :, None] * unit[:, None, :])  # [s, 3, 3]
    keep = np.repeat(free, 3)
    mass = np.repeat(model.world_values("particle_mass")[world], 3)[keep]
    top, _ = top_eigenpair(pair_block_matrix(n, i, j, blocks)[keep][:, keep], mass, tol=1e-6)
    return math.sqrt(max(top, 0.0))


def top_eigenpair(stiffness, mass: np.ndarray, *, start: np.ndarray | None = None, tol: float = 0.0) -> tuple:
    """The largest eigenvalue λ [1/s²] of K x = λ M x and its M-orthonormal eigenvector x (xᵀ M x = 1) [m/√kg],
    shape [n]: ``stiffness`` K a symmetric ``scipy.sparse`` matrix [n, n] [N/m], ``mass`` the diagonal of M
    [kg], shape [n]. Lanczos on M^-½ K M^-½ (``scipy.sparse.linalg.eigsh``, relative accuracy ``tol``; 0:
    machine precision), started from ``start`` (an earlier x, say) where given; dense below 4 coordinates."""
    import scipy.sparse
    import scipy.sparse.linalg

    scale = 1.0 / np.sqrt(np.asarray(mass, dtype=np.float64))
    reduced = scipy.sparse.diags(scale) @ scipy.sparse.csr_matrix(stiffness) @ scipy.sparse.diags(scale)
    if reduced.shape[0] <= 3:
        values, vectors = np.linalg.eigh(reduced.toarray())
        top, y = values[-1], vectors[:, -1]
    else:
        v0 = None if start is None else np.asarray(start, dtype=np.float64) / scale
        values, vectors = scipy.sparse.linalg.eigsh(reduced, k=1, which="LA", tol=tol, v0=v0)
        top, y = values[0], vectors[:, 0]
    return float(top), scale * y
