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

import numpy as np
import warp as wp

from ... import checks
from ...errors import ConfigError
from ...kernels.implicit import implicit_kernels
from ...kernels.linalg import (
    CG_BB,
    CG_MAX_ITERATIONS,
    CG_PAP,
    CG_RR_LAST,
    CG_RZ_NEW,
    CG_SCALARS,
    CG_SETTINGS,
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


class ImplicitEuler(Integrator):
    """Linearised backward Euler: first order, unconditionally stable; damps a spring's amplitude by
    1/√(1 + ω²h²) per step.

    Args:
        model: the model.
        cg_iterations: most CG iterations per step.
        cg_tolerance: CG stops when ‖b - A Δv‖ ≤ cg_tolerance · ‖b‖.

    The previous step's Δv is the next solve's initial guess.
    """

    name = "implicit_euler"
    order = 1
    unconditionally_stable = True

    def __init__(self, model: Model, *, cg_iterations: int = 100, cg_tolerance: float = 1.0e-5):
        super().__init__(model)
        n, vec3, device = model.state_size, model.vec3, model.device
        worlds = model.world_count
        self._settings = wp.zeros(CG_SETTINGS, dtype=wp.float64, device=device)
        self.cg_iterations = cg_iterations
        self.cg_tolerance = cg_tolerance
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

    @property
    def cg_iterations(self) -> int:
        """Most CG iterations per step; settable between frames (a device value)."""
        return self._cg_iterations

    @cg_iterations.setter
    def cg_iterations(self, value: int) -> None:
        self._cg_iterations = checks.count("cg_iterations", value, minimum=1)
        write_setting(self._settings, CG_MAX_ITERATIONS, float(self._cg_iterations))

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


    def _kernels(self):
        model = self.model
        driven = model.pin_groups is not None and model.pin_groups.driven
        return implicit_kernels(model.scalar, model.family_specs(), self._tiled, model.drag_enabled, driven)

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        prescribed, prepare, _, update = self._kernels()
        per_particle = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
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

    def solve_report(self, *, world: int = 0) -> tuple[int, float, float]:
        """(iterations, ‖b - A Δv‖, ‖b‖) of the last solve of ``world``, read from the device (synchronises)."""
        iterations, residual, rhs = self.world_solve_report()
        return int(iterations[world]), float(residual[world]), float(rhs[world])

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
                      outputs=[self._iteration, self._active, self._keep_going], **per_world)

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
