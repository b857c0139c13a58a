"""Explicit Runge-Kutta integrators from Butcher tableaux: explicit Euler, midpoint (RK2), classic RK4.

The state y = (x, v) obeys y' = (v, M⁻¹ f(x, v)). Stage k evaluates the forces at
yₖ = y₀ + h Σⱼ aₖⱼ kⱼ; the step is y₁ = y₀ + h Σⱼ bⱼ kⱼ. Stage velocities and forces live in
preallocated [stages, world_count · particle_count] arrays owned by the integrator; stage 0 is the input state, so
its velocity is read in place. Stage k is at time t + cₖ h (cₖ = Σⱼ aₖⱼ): animated inputs and driven pins
are evaluated there, so a prescribed motion enters every stage exactly and the method keeps its order.
Contacts are resolved once, on the result of the step.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import warp as wp

from ...kernels.integrators import rk_combine_kernel
from ..forces import eval_forces
from ..kinematics import apply_kinematics
from ..model import Model
from ..state import State
from ..control import Control
from .base import Integrator


class ExplicitRungeKutta(Integrator):
    """An explicit Runge-Kutta method given by its Butcher tableau (class attributes ``a`` and ``b``).

    Attributes:
        a: lower-triangular stage coefficients, one row per stage (row k has k entries).
        b: weights of the stage derivatives in the step, one per stage.
    """

    a: tuple = ()
    b: tuple = ()

    def __init__(self, model: Model):
        super().__init__(model)
        stages, n, vec3 = len(self.b), model.state_size, model.vec3
        self._stage_qd = wp.zeros((stages, n), dtype=vec3, device=model.device)
        self._stage_f = wp.zeros((stages, n), dtype=vec3, device=model.device)
        self._stage_q = wp.zeros(n, dtype=vec3, device=model.device)
        self._stage_time = wp.zeros(model.world_count, dtype=wp.float64, device=model.device)
        # Stage k > 0 evaluates forces at (stage_q, stage_qd[k]) at time stage_time; stage 0 at the input state.
        self._stages = [
            State(particle_q=self._stage_q, particle_qd=self._stage_qd[k], particle_f=self._stage_f[k],
                  time=self._stage_time)
            for k in range(stages)
        ]

    def combine(self, state_in: State, control: Control | None, coefficients, dt, state_out: State, upto: int):
        """Write y₀ + h Σⱼ cⱼ kⱼ over stages j < ``upto`` to ``state_out`` (time t₀ + h Σⱼ cⱼ), skipping leading
        zero cⱼ, then put the kinematic particles at that time.

        ``dt`` is the step h [s], or a device array of each world's step (adaptive steps).
        """
        model = self.model
        on_device = isinstance(dt, wp.array)
        scale, step = (1.0, dt) if on_device else (dt, model.unit_step)
        c = np.asarray(coefficients[:upto], dtype=np.float64)
        first = 1 + int(np.argmax(c[1:] != 0.0)) if np.any(c[1:] != 0.0) else upto
        terms = upto - first
        weights = wp.types.vector(length=max(terms, 1), dtype=model.scalar)(*(scale * c[first:upto] if terms else [0.0]))
        # The result's time offset, in units of step[0]: the stage's c = Σⱼ aⱼ (1 for the step itself), summed as
        # the tableau's rationals, so that a step lands on t + h exactly.
        fraction = scale * float(sum(Fraction(x).limit_denominator(10**9) for x in c))
        wp.launch(
            rk_combine_kernel(model.scalar, bool(c[0] != 0.0), terms),
            dim=model.particle_dim,
            block_dim=model.block_dim,
            inputs=[
                model.particle_count,
                model.particle_flags,
                model.particle_inv_mass,
                state_in.particle_q,
                state_in.particle_qd,
                state_in.time,
                self._stage_f[0],
                self._stage_qd[first:upto] if terms else self._stage_qd[0:1],
                self._stage_f[first:upto] if terms else self._stage_f[0:1],
                model.scalar(scale * c[0]),
                weights,
                wp.float64(fraction),
                step,
            ],
            outputs=[state_out.particle_q, state_out.particle_qd, state_out.time],
            device=model.device,
        )
        apply_kinematics(model, control, state_in, state_out.particle_q, state_out.particle_qd, fraction,
                         step if on_device else None)

    def eval_stages(self, state_in: State, control: Control | None, dt, *, first: bool = True) -> None:
        """Evaluate the forces of every stage of a step of ``dt`` (seconds, or a device array holding
        them) from ``state_in``; with ``first=False`` stage 0's forces are already in place."""
        if first:
            eval_forces(self.model, state_in, control, particle_f=self._stage_f[0], dampers=self.dampers,
                        power=self.power)
        for k in range(1, len(self.b)):
            self.combine(state_in, control, self.a[k], dt, self._stages[k], upto=k)
            eval_forces(self.model, self._stages[k], control)

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        self.eval_stages(state_in, control, dt)
        self.combine(state_in, control, self.b, dt, state_out, upto=len(self.b))
        self.finish_step(state_out, dt, state_in)
        self.hold_worlds(state_in, state_out)


class ExplicitEuler(ExplicitRungeKutta):
    """Forward Euler: x' = x + h v, v' = v + h M⁻¹ f(x, v). First order; unstable for undamped springs
    at every step size (its amplification factor is √(1 + ω²h²) per step)."""

    name = "explicit_euler"
    order = 1
    a = ((),)
    b = (1.0,)


class Midpoint(ExplicitRungeKutta):
    """Explicit midpoint rule (RK2): forces at y₀ + ½h k₀. Second order; mildly unstable for undamped
    springs (|R(iωh)|² = 1 + (ωh)⁴/4)."""

    name = "midpoint"
    order = 2
    a = ((), (0.5,))
    b = (0.0, 1.0)


class RK4(ExplicitRungeKutta):
    """Classic fourth-order Runge-Kutta. Stable for undamped springs while ω h ≤ 2√2."""

    name = "rk4"
    order = 4
    a = ((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0))
    b = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)
