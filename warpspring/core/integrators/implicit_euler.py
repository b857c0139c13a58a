"""Linearised implicit (backward) Euler, Baraff & Witkin (1998), solved matrix-free by conjugate gradients.

Each step takes one Newton iteration of backward Euler:

    (M - h ∂f/∂v - h² ∂f/∂x) Δv = h (f + h ∂f/∂x v),    v' = v + Δv,    x' = x + h v'

with the spring stiffness and damping Jacobians applied matrix-free (``kernels/implicit.py``), the
compressive part of the spring Hessian clamped so the system stays positive definite, and pinned
particles filtered out. The solve is block-Jacobi preconditioned CG (``kernels/linalg.py``) with every
scalar on the device and the loop in ``wp.capture_while``: it stops when ‖r‖ ≤ tol·‖b‖, needs no host
synchronisation, and a frame of implicit steps stays one graph. (Warp's own ``warp.optim.linear.cg``
does the same on GPUs, but its tiled dot products cost ~0.5 ms each on the CPU, 30× our whole
iteration there.)
"""

from __future__ import annotations

import warp as wp

from ... import checks
from ...errors import ConfigError
from ..forces import eval_forces
from ...kernels.implicit import implicit_kernels
from ...kernels.linalg import CG_BB, CG_RR_LAST, CG_SCALARS, cg_kernels, reduce_launch_dim
from ...kernels.precision import mat33_type
from ..model import Control, Model, State
from .base import Integrator


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

    def __init__(self, model: Model, *, cg_iterations: int = 100, cg_tolerance: float = 1.0e-5):
        super().__init__(model)
        self.cg_iterations = checks.count("cg_iterations", cg_iterations, minimum=1)
        self.cg_tolerance = checks.positive("cg_tolerance", cg_tolerance)
        if self.cg_tolerance >= 1.0:
            raise ConfigError(f"cg_tolerance must be < 1 (a relative residual), got {cg_tolerance!r}")
        n, vec3, device = model.particle_count, model.vec3, model.device
        self._tiled = device.is_cuda
        self._block = model.block_dim if self._tiled else 1
        self._rhs = wp.zeros(n, dtype=vec3, device=device)
        self._delta_qd = wp.zeros(n, dtype=vec3, device=device)
        self._diagonal_inverse = wp.zeros(n, dtype=mat33_type(model.scalar), device=device)
        self._r, self._z, self._p, self._a_p = (wp.zeros(n, dtype=vec3, device=device) for _ in range(4))
        self._scalars = wp.zeros(CG_SCALARS, dtype=wp.float64, device=device)
        self._iteration = wp.zeros(1, dtype=wp.int32, device=device)
        self._keep_going = wp.zeros(1, dtype=wp.int32, device=device)

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        prepare, _, update = implicit_kernels(model.scalar, model.spring_max_degree, self._tiled, model.spring_law)
        per_particle = dict(dim=model.particle_count, block_dim=model.block_dim, device=model.device)
        h = model.scalar(dt)
        eval_forces(model, state_in, control)
        wp.launch(
            prepare,
            inputs=[*self._model_inputs(), state_in.particle_q, state_in.particle_qd, state_in.particle_f, h],
            outputs=[self._rhs, self._diagonal_inverse],
            **per_particle,
        )
        self._solve(state_in, h)
        wp.launch(
            update,
            inputs=[state_in.particle_q, state_in.particle_qd, self._delta_qd, h],
            outputs=[state_out.particle_q, state_out.particle_qd],
            **per_particle,
        )
        self.finish_step(state_out, dt)

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from Δv = 0."""
        self._delta_qd.zero_()

    def solve_report(self) -> tuple[int, float, float]:
        """(iterations, ‖b - A Δv‖, ‖b‖) of the last solve, read from the device (synchronises)."""
        scalars = self._scalars.numpy()
        return int(self._iteration.numpy()[0]), float(scalars[CG_RR_LAST]) ** 0.5, float(scalars[CG_BB]) ** 0.5

    # -- the CG solve of A Δv = b ------------------------------------------------------------------------

    def _model_inputs(self) -> list:
        model = self.model
        return [
            model.particle_mass,
            model.particle_inv_mass,
            model.particle_spring_neighbor,
            model.particle_spring_id,
            model.spring_rest_length,
            model.spring_stiffness,
            model.spring_damping,
            model.scalar(model.drag),
        ]

    def _solve(self, state: State, h) -> None:
        model = self.model
        n = model.particle_count
        start, update_solution, update_direction, condition = cg_kernels(model.scalar, self._tiled)
        _, matvec, _ = implicit_kernels(model.scalar, model.spring_max_degree, self._tiled, model.spring_law)
        reducing = dict(dim=reduce_launch_dim(n, self._block), block_dim=self._block, device=model.device)
        check = dict(
            dim=1,
            inputs=[wp.float64(self.cg_tolerance), self.cg_iterations, self._scalars],
            outputs=[self._iteration, self._keep_going],
            device=model.device,
        )

        def product(p):  # a_p = A p, scalars[p·Ap] += p·Ap
            wp.launch(matvec, inputs=[n, *self._model_inputs(), state.particle_q, h, p],
                      outputs=[self._a_p, self._scalars], **reducing)

        def iterate():
            product(self._p)
            wp.launch(update_solution, inputs=[n, self._p, self._a_p, self._diagonal_inverse],
                      outputs=[self._delta_qd, self._r, self._z, self._scalars], **reducing)
            wp.launch(update_direction, dim=n, block_dim=model.block_dim, inputs=[self._z, self._scalars],
                      outputs=[self._p], device=model.device)
            wp.launch(condition, **check)

        self._scalars.zero_()
        self._iteration.fill_(-1)
        product(self._delta_qd)  # the previous Δv is the initial guess
        wp.launch(start, inputs=[n, self._rhs, self._a_p, self._diagonal_inverse],
                  outputs=[self._r, self._z, self._p, self._scalars], **reducing)
        wp.launch(condition, **check)
        wp.capture_while(self._keep_going, iterate)
