"""Linearised implicit (backward) Euler, Baraff & Witkin (1998), solved matrix-free by conjugate gradients.

Each step takes one Newton iteration of backward Euler:

    (M - h ∂f/∂v - h² ∂f/∂x) Δv = h (f + h ∂f/∂x v),    v' = v + Δv,    x' = x + h v'

with the spring stiffness and damping Jacobians applied matrix-free (``kernels/implicit.py``), the
compressive part of the spring Hessian clamped so the system stays positive definite, and kinematic
particles filtered out (driven pins are put at t + h first; their prescribed Δv enters the right-hand side). The solve is block-Jacobi preconditioned CG (``kernels/linalg.py``) with every
scalar on the device and the loop in ``wp.capture_while``: each world solves its own system, with its
own scalars and stopping test, and stops when its ‖r‖ ≤ tol·‖b‖; the loop needs no host synchronisation,
and a frame of implicit steps stays one graph. (Warp's own ``warp.optim.linear.cg``
does the same on GPUs, but its tiled dot products cost ~0.5 ms each on the CPU, 30× our whole
iteration there.)
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ... import checks
from ...errors import ConfigError
from ...kernels.implicit import implicit_kernels
from ...kernels.kinematics import PARTICLE_KINEMATIC
from ...kernels.linalg import (
    CG_BB,
    CG_MAX_ITERATIONS,
    CG_PAP,
    CG_RR_LAST,
    CG_RZ_NEW,
    CG_SCALARS,
    CG_SETTINGS,
    CG_SHORT_COUNT,
    CG_SHORT_SLOTS,
    CG_SHORT_WORST,
    CG_TOLERANCE,
    cg_kernels,
    reduce_lanes,
    reduce_launch_dim,
    sum_partials_kernel,
)
from ...kernels.precision import mat33_type
from ..forces import eval_forces
from ..kinematics import apply_kinematics
from ..model import Model
from ..state import State
from ..control import Control
from .base import Integrator, step_arguments, write_setting
from ...kernels.flatten import flat_launch


#: What a CG solve that stops at its iteration cap unconverged does (``ImplicitEuler(cg_unconverged=...)``).
UNCONVERGED = ("warn", "raise", "ignore")


#: The automatic iteration cap's least value (the fixed default before it).
AUTO_CAP_FLOOR = 100
#: The automatic cap's ceiling per unknown of a world (3 per particle): float32 CG loses orthogonality, so a few
#: passes over the unknowns rather than one.
CG_PASSES_PER_UNKNOWN = 4


def auto_iteration_cap(step_omega: float, tolerance: float, unknowns: int | None = None) -> int:
    """The default CG iteration cap for a step h with h ω_max = ``step_omega`` (ω_max bounded by Gershgorin) and a
    relative ``tolerance``: ⌈ln(2/tol)·(1 + h ω_max)⌉, at least :data:`AUTO_CAP_FLOOR`, and at most
    :data:`CG_PASSES_PER_UNKNOWN` times a world's ``unknowns`` (CG ends in as many iterations as unknowns in exact
    arithmetic: an absurd stiffness, 1e18 N/m on a 4 × 4 cloth, would otherwise ask for ~1e10). CG reaches tol within
    ½√κ ln(2/tol) iterations, and κ(M + h²K) ≤ 1 + (h ω_max)² with M as the preconditioner; block-Jacobi on these
    systems took up to 10 h ω_max at tol = 1e-5 (measured: a T10 ball dropped on the ground at 1/60 s, h ω_max = 61,
    618 iterations; linear tets 8, cloth 4 per unit of h ω_max; ``bench/results/softbody_tet10.md``), so the cap is
    twice the bound (12.2 h ω_max at 1e-5)."""
    cap = max(AUTO_CAP_FLOOR, int(math.ceil(math.log(2.0 / tolerance) * (1.0 + min(step_omega, 1e12)))))
    if unknowns is not None:
        cap = min(cap, max(AUTO_CAP_FLOOR, CG_PASSES_PER_UNKNOWN * unknowns))
    return cap


def gershgorin_bound(model: Model) -> float:
    """Gershgorin's upper bound on ω_max = √λ_max(M⁻¹K) [rad/s] over the worlds at the model's initial positions:
    every family's row bounds (``ElementFamily.gershgorin_rows``) over the free particles' masses (the stability
    advisor's bound, ``analysis.omega.gershgorin_omega_max``, without its stiffness overrides)."""
    if model.particle_count == 0:
        return 0.0
    flags = model.particle_flags.numpy().reshape(model.world_count, model.particle_count)
    free = (flags & PARTICLE_KINEMATIC) == 0
    rows = np.zeros((model.world_count, model.particle_count))
    for family in model.families:
        try:
            rows += family.gershgorin_rows(model, free, None)
        except NotImplementedError:  # a family without a row bound adds none
            continue
    return float(np.sqrt(np.where(free, rows / model.world_values("particle_mass"), 0.0).max()))


class ImplicitEuler(Integrator):
    """Linearised backward Euler: first order, unconditionally stable; damps a spring's amplitude by
    1/√(1 + ω²h²) per step.

    Args:
        model: the model.
        cg_iterations: most CG iterations per step; ``None`` (the default): chosen for the step and the model at the
            first step of each new dt, :func:`auto_iteration_cap` (at least 100; ~ ln(2/tol)·(1 + h ω_max)).
        cg_tolerance: CG stops when ‖b - A Δv‖ ≤ cg_tolerance · ‖b‖.
        cg_unconverged: what a solve that stops at ``cg_iterations`` short of ``cg_tolerance`` does: ``"warn"``
            (a :class:`~warpspring.errors.SolverWarning` from the :class:`~warpspring.core.simulator.Simulator`, once,
            with the residual reached and the remedy), ``"raise"`` (a :class:`~warpspring.errors.SimulationError`
            at the end of the frame) or ``"ignore"``. Such a step is not backward Euler's: an unfinished Δv can add
            energy that the method would have taken out.

    The previous step's Δv is the next solve's initial guess. Each world counts its solves that stopped at the cap
    unconverged, and the worst relative residual they left, on the device (:meth:`unconverged_solves`).
    """

    name = "implicit_euler"
    order = 1
    unconditionally_stable = True

    def __init__(self, model: Model, *, cg_iterations: int | None = None, cg_tolerance: float = 1.0e-5,
                 cg_unconverged: str = "warn"):
        super().__init__(model)
        if cg_unconverged not in UNCONVERGED:
            raise ConfigError(f"cg_unconverged must be one of {', '.join(UNCONVERGED)}, got {cg_unconverged!r}")
        self.cg_unconverged = cg_unconverged
        self._warned = False
        n, vec3, device = model.state_size, model.vec3, model.device
        worlds = model.world_count
        self._settings = wp.zeros(CG_SETTINGS, dtype=wp.float64, device=device)
        self._omega_max = None  # the Gershgorin bound on ω_max [rad/s] of an automatic cap, once needed
        self.cg_tolerance = cg_tolerance
        self.cg_iterations = cg_iterations
        self._tiled = device.is_cuda
        self._lanes = reduce_lanes(model.particle_count, model.block_dim, self._tiled)
        self._rhs = wp.zeros(n, dtype=vec3, device=device)
        self._delta_qd = wp.zeros(n, dtype=vec3, device=device)
        self._diagonal_inverse = wp.zeros(n, dtype=mat33_type(model.scalar), device=device)
        self._r, self._z, self._p, self._a_p = (wp.zeros(n, dtype=vec3, device=device) for _ in range(4))
        self._prescribed = wp.zeros(n, dtype=vec3, device=device)  # the driven pins' Δv (0 at free particles)
        grid = reduce_launch_dim(worlds, model.particle_count, self._lanes)
        self._partials = wp.zeros((worlds, grid[1], CG_SCALARS), dtype=wp.float64, device=device)
        self._scalars = wp.zeros((worlds, CG_SCALARS), dtype=wp.float64, device=device)
        self._iteration = wp.zeros(worlds, dtype=wp.int32, device=device)
        self._active = wp.zeros(worlds, dtype=wp.int32, device=device)
        self._keep_going = wp.zeros(1, dtype=wp.int32, device=device)
        self._shortfall = wp.zeros((worlds, CG_SHORT_SLOTS), dtype=wp.float64, device=device)

    @property
    def cg_iterations(self) -> int | None:
        """Most CG iterations per step as set (``None``: chosen per step, :attr:`iteration_cap`); settable between
        frames (a device value)."""
        return None if self._auto else self._iteration_cap

    @cg_iterations.setter
    def cg_iterations(self, value: int | None) -> None:
        self._auto = value is None
        self._cap_dt = None  # auto: chosen again at the next step
        self._write_cap(AUTO_CAP_FLOOR if value is None else checks.count("cg_iterations", value, minimum=1))

    @property
    def iteration_cap(self) -> int:
        """The most CG iterations the next solve may take (``cg_iterations``, or the cap chosen for the step)."""
        return self._iteration_cap

    def _write_cap(self, cap: int) -> None:
        self._iteration_cap = int(cap)
        write_setting(self._settings, CG_MAX_ITERATIONS, float(cap))

    def _choose_cap(self, dt: float) -> None:
        """With ``cg_iterations=None``: the cap for a step of ``dt`` [s], once per dt (host work: a Stepper's warm-up
        step makes it before a capture; never written while a graph is being captured)."""
        if not self._auto or dt == self._cap_dt or wp.get_device(self.model.device).is_capturing:
            return
        if self._omega_max is None:
            self._omega_max = gershgorin_bound(self.model)
        self._cap_dt = dt
        self._write_cap(auto_iteration_cap(dt * self._omega_max, self._cg_tolerance, 3 * self.model.particle_count))

    @property
    def cg_tolerance(self) -> float:
        """CG stops when ‖b - A Δv‖ ≤ cg_tolerance · ‖b‖; settable between frames (a device value)."""
        return self._cg_tolerance

    @cg_tolerance.setter
    def cg_tolerance(self, value: float) -> None:
        tolerance = checks.positive("cg_tolerance", value)
        if tolerance >= 1.0:
            raise ConfigError(f"cg_tolerance must be < 1 (a relative residual), got {value!r}")
        self._cg_tolerance = tolerance
        write_setting(self._settings, CG_TOLERANCE, tolerance)
        if getattr(self, "_auto", False):
            self._cap_dt = None  # the automatic cap depends on it: chosen again at the next step


    def _kernels(self):
        model = self.model
        driven = model.pin_groups is not None and model.pin_groups.driven
        return implicit_kernels(model.scalar, model.family_specs(), self._tiled, model.drag_enabled, driven)

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        prescribed, prepare, _, update = self._kernels()
        per_particle = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        self._choose_cap(dt)
        h = model.scalar(dt)
        eval_forces(model, state_in, control)
        # Driven pins first: where they are at t + h decides their Δv in the right-hand side.
        apply_kinematics(model, control, state_in, state_out.particle_q, state_out.particle_qd, dt)
        if model.pin_groups is not None and model.pin_groups.driven:
            wp.launch(prescribed, inputs=[model.particle_flags, state_in.particle_q, state_in.particle_qd,
                                          state_out.particle_q, h], outputs=[self._prescribed], **per_particle)
        flat_launch(
            prepare,
            inputs=[model.particle_count, model.particle_flags, model.particle_mass, model.elements, model.inputs,
                    state_in.particle_q, state_in.particle_qd, state_in.particle_f, h, self._prescribed],
            outputs=[self._rhs, self._diagonal_inverse],
            **per_particle,
        )
        self._solve(state_in, h)
        wp.launch(
            update,
            inputs=[model.particle_count, model.particle_flags, state_in.particle_q, state_in.particle_qd, state_in.time,
                    self._delta_qd, *step_arguments(model.scalar, dt)],
            outputs=[state_out.particle_q, state_out.particle_qd, state_out.time],
            **per_particle,
        )
        self.finish_step(state_out, dt, state_in)
        self.hold_worlds(state_in, state_out)

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from Δv = 0."""
        self._delta_qd.zero_()

    def persistent_arrays(self) -> dict[str, wp.array]:
        """The warm start: "delta_qd", the last solve's Δv [m/s], shape [world_count · particle_count], the next
        solve's initial guess."""
        return {"delta_qd": self._delta_qd}

    def history(self) -> list:
        """The warm start and the count of unconverged solves (:meth:`unconverged_solves`): a stepper's warm-up step
        before a capture mid-run (a new structure) solves once more, which the count must not keep."""
        return [*super().history(), self._shortfall]

    def solve_report(self, *, world: int = 0) -> tuple[int, float, float]:
        """(iterations, ‖b - A Δv‖, ‖b‖) of the last solve of ``world``, read from the device (synchronises)."""
        iterations, residual, rhs = self.world_solve_report()
        return int(iterations[world]), float(residual[world]), float(rhs[world])

    def unconverged_solves(self, *, clear: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Per world, the solves that stopped at ``cg_iterations`` with ‖b - A Δv‖ > cg_tolerance · ‖b‖ since the
        integrator was made (or last cleared): their count (int, shape [world_count]) and the largest relative
        residual ‖b - A Δv‖ / ‖b‖ one of them left (float64, shape [world_count]; 0 where none). Reads the device
        (synchronises); ``clear`` starts the count again."""
        record = self._shortfall.numpy().copy()  # (a CPU array's numpy() is a view: the clear would reach it)
        if clear:
            self._shortfall.zero_()
        return record[:, CG_SHORT_COUNT].astype(np.int64), np.sqrt(record[:, CG_SHORT_WORST])

    def solve_shortfall(self) -> str | None:
        """A line on the solves since the last call that stopped at the iteration cap unconverged (the worlds, how
        many, the residual reached against the tolerance, the remedy), or ``None``. With ``cg_unconverged="warn"``
        it reads the device until it has reported once (the Simulator warns with it after a frame), then no more;
        with ``"raise"`` after every frame (the Simulator raises with it: :attr:`strict_solves`)."""
        if self.cg_unconverged == "ignore" or (self._warned and self.cg_unconverged == "warn"):
            return None
        count, worst = self.unconverged_solves(clear=True)
        if not count.any():
            return None
        world = int(np.argmax(worst))
        where = f" (world {world} worst; {int((count > 0).sum())} of {len(count)} worlds)" if len(count) > 1 else ""
        message = (f"implicit Euler's CG stopped at its cap of {self.iteration_cap} iterations short of its tolerance "
                   f"in {int(count.sum())} solve(s){where}: relative residual {worst[world]:.2g} against "
                   f"{self.cg_tolerance:g}, so those steps are not backward Euler's and may add energy: raise "
                   f"cg_iterations (ImplicitEuler(model, cg_iterations={4 * self.iteration_cap})) or take more "
                   "substeps (a smaller step needs fewer iterations)")
        self._warned = True
        return message

    @property
    def strict_solves(self) -> bool:
        """Whether an unconverged solve stops the run (``cg_unconverged="raise"``)."""
        return self.cg_unconverged == "raise"

    def world_solve_report(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every world's last solve: CG iterations (int, shape [world_count]), ‖b - A Δv‖ and ‖b‖ (float64,
        shape [world_count]); read from the device (synchronises). A held world reports -1 iterations."""
        scalars = self._scalars.numpy()
        return self._iteration.numpy().copy(), np.sqrt(scalars[:, CG_RR_LAST]), np.sqrt(scalars[:, CG_BB])

    # -- the CG solve of A Δv = b ------------------------------------------------------------------------

    def _solve(self, state: State, h) -> None:
        model = self.model
        worlds = model.world_count
        begin, start, update_solution, update_direction, condition = cg_kernels(model.scalar, self._tiled)
        _, _, matvec, _ = self._kernels()
        reducing = dict(dim=reduce_launch_dim(worlds, model.particle_count, self._lanes), block_dim=self._lanes,
                        device=model.device)
        per_world = dict(dim=worlds, device=model.device)
        n = model.particle_count
        sum_partials = sum_partials_kernel(self._tiled)

        def total(first: int, count: int):  # scalars[w, first:first+count] = Σ partials over the world's blocks
            wp.launch(sum_partials, dim=(worlds, self._lanes), block_dim=self._lanes,
                      inputs=[first, count, self._partials], outputs=[self._scalars], device=model.device)

        def check():
            wp.launch(condition, inputs=[self._settings, self._scalars],
                      outputs=[self._iteration, self._active, self._keep_going, self._shortfall], **per_world)

        def product(p):  # a_p = A p and the partial sums of p·Ap, in the worlds still iterating
            flat_launch(matvec, inputs=[model.particle_count, model.particle_flags, model.particle_mass, model.elements,
                                      model.inputs, state.particle_q, h, self._active, p],
                      outputs=[self._a_p, self._partials], **reducing)
            total(CG_PAP, 1)

        def iterate():
            product(self._p)
            wp.launch(update_solution,
                      inputs=[n, self._active, self._p, self._a_p, self._diagonal_inverse, self._scalars],
                      outputs=[self._delta_qd, self._r, self._z, self._partials], **reducing)
            total(CG_RZ_NEW, 2)  # the new r·z and r·r
            check()
            wp.launch(update_direction, dim=model.particle_dim, block_dim=model.block_dim,
                      inputs=[n, self._active, self._z, self._scalars], outputs=[self._p], device=model.device)

        self._keep_going.zero_()
        wp.launch(begin, inputs=[model.world_enabled],
                  outputs=[self._scalars, self._iteration, self._active, self._keep_going], **per_world)
        product(self._delta_qd)  # the previous Δv is the initial guess
        wp.launch(start, inputs=[n, self._active, self._rhs, self._a_p, self._diagonal_inverse],
                  outputs=[self._r, self._z, self._p, self._partials], **reducing)
        total(CG_RZ_NEW, 3)  # r·z, r·r and b·b (consecutive slots)
        check()
        wp.capture_while(self._keep_going, iterate)
