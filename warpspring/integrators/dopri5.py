"""Adaptive Dormand-Prince 5(4): an embedded Runge-Kutta pair that chooses its own step.

``step(state_in, state_out, control, dt)`` advances by ``dt`` in as many internal steps as the error
tolerance needs. Each internal step computes the 5th-order solution and the 4th-order embedded one;
their difference estimates the local error, scaled per component by atol + rtol·|y| (both equal to
``tolerance``) and max-reduced over particles. A step with scaled error ≤ 1 is accepted; the next step
size is h·min(5, max(0.2, 0.9·err^(-1/5))) (no growth right after a rejection). The error reduction is
read on the host after every internal step, so this integrator is not graph-capturable.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..errors import ConfigError, SimulationError
from ..forces import eval_forces
from ..kernels.integrators import rk_error_kernel
from ..model import Control, Model, State
from .runge_kutta import ExplicitRungeKutta

_SAFETY, _GROW, _SHRINK = 0.9, 5.0, 0.2


class DormandPrince(ExplicitRungeKutta):
    """Adaptive Dormand-Prince 5(4) with FSAL (first same as last: 6 force evaluations per accepted step).

    Args:
        model: the model.
        tolerance: local error tolerance per internal step, absolute and relative, on positions [m] and
            velocities [m/s].
        max_steps: most internal steps per call of ``step`` before it stops with a SimulationError.

    Attributes:
        accepted_steps, rejected_steps: internal steps taken since construction.
        step_size: the current internal step [s].
    """

    name = "dopri5"
    order = 5
    capturable = False
    adaptive = True
    a = (
        (),
        (1 / 5,),
        (3 / 40, 9 / 40),
        (44 / 45, -56 / 15, 32 / 9),
        (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
        (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
        (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
    )
    b = (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0)
    b_embedded = (5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40)

    def __init__(self, model: Model, *, tolerance: float = 1.0e-6, max_steps: int = 100_000):
        super().__init__(model)
        if not isinstance(tolerance, (int, float)) or not tolerance > 0.0:
            raise ConfigError(f"tolerance must be a number > 0, got {tolerance!r}")
        self.tolerance = float(tolerance)
        self.max_steps = int(max_steps)
        self.accepted_steps = 0
        self.rejected_steps = 0
        self.step_size = None
        self._error = wp.zeros(1, dtype=wp.float64, device=model.device)
        self._work = [model.state(), model.state()]
        self._error_weights = np.subtract(self.b, self.b_embedded)

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        y, y_new = self._work
        y.assign(state_in)
        proposed = dt if self.step_size is None else self.step_size
        t, grow, taken, f0_valid = 0.0, _GROW, 0, False
        while t < dt * (1.0 - 1e-12):
            h = min(proposed, dt - t)  # the last step may be cut short to land on dt
            if not f0_valid:
                eval_forces(self.model, y, control, self._stage_f[0])
            for k in range(1, 7):
                self.combine(y, self.a[k], h, self._stage_q, self._stage_qd[k], upto=k)
                eval_forces(self.model, self._stages[k], control)
            # The 5th-order solution is stage 6's state (a₆ = b), and f(y_new) its force (FSAL).
            wp.copy(y_new.particle_q, self._stage_q)
            wp.copy(y_new.particle_qd, self._stage_qd[6])
            error = self._scaled_error(y, y_new, h)
            taken += 1
            if error <= 1.0:
                y, y_new = y_new, y
                wp.copy(self._stage_f[0], self._stage_f[6])
                t += h
                self.accepted_steps += 1
                factor = min(grow, _SAFETY * error**-0.2) if error > 0.0 else grow
                grow = _GROW
            else:  # stage 0 (the force at y) stays valid for the retry
                self.rejected_steps += 1
                factor = _SAFETY * error**-0.2 if np.isfinite(error) else _SHRINK
                grow = 1.0
            f0_valid = True
            next_h = h * max(_SHRINK, factor)
            # A step cut short to land on dt says nothing against the step size in use before it.
            proposed = max(proposed, next_h) if error <= 1.0 and h < proposed else next_h
            if taken >= self.max_steps and t < dt * (1.0 - 1e-12):
                raise SimulationError(
                    f"dopri5 took {taken} internal steps without finishing a step of {dt:g} s (step size now "
                    f"{proposed:.3g} s, scaled error {error:.3g}): the state is diverging or the tolerance "
                    f"({self.tolerance:g}) is too tight; use an implicit integrator or loosen the tolerance"
                )
        self.step_size = proposed
        self._work = [y, y_new]
        state_out.assign(y)
        self.finish_step(state_out, dt)

    def _scaled_error(self, y: State, y_new: State, h: float) -> float:
        model = self.model
        self._error.zero_()
        weights = wp.types.vector(length=7, dtype=model.scalar)(*(h * self._error_weights))
        wp.launch(
            rk_error_kernel(model.scalar, 7),
            dim=model.particle_count,
            block_dim=model.block_dim,
            inputs=[
                model.particle_inv_mass,
                y.particle_qd,
                self._stage_qd,
                self._stage_f,
                weights,
                y_new.particle_q,
                y_new.particle_qd,
                model.scalar(self.tolerance),
                model.scalar(self.tolerance),
            ],
            outputs=[self._error],
            device=model.device,
        )
        return float(self._error.numpy()[0])
