"""Velocity Verlet (kick-drift-kick leapfrog), second order.

    v½ = v + ½h M⁻¹ f(x, v);   x' = x + h v½;   v' = v½ + ½h M⁻¹ f(x', v')

The last force depends on v' when springs are damped or drag acts. Evaluating it at v½ instead would
drop the method to first order, so a corrector runs: v* = v½ + ½h M⁻¹ f(x', v½), then
v' = v½ + ½h M⁻¹ f(x', v*), whose error is O(h³) per step. Without velocity-dependent forces the
corrector is skipped (it would change nothing) and the method is the symplectic Störmer-Verlet.
"""

from __future__ import annotations

import warp as wp

from ...kernels.integrators import verlet_kernels
from ..forces import eval_forces
from ..kinematics import apply_kinematics
from ..model import Model
from ..state import State
from ..control import Control
from .base import Integrator, step_arguments


class VelocityVerlet(Integrator):
    """Velocity Verlet; stable for undamped springs while ω h < 2. Two force evaluations per step, three
    when forces depend on velocity (drag or spring damping: a corrector keeps second order).

    Forces depend on velocity when the model's drag is on, some spring is damped, or an added element family says
    it has a damper (``ElementFamily.velocity_dependent``). Drag is a live input
    (switching it on is a structural change the next capture sees); spring damping is read from the model
    at construction: after writing nonzero values into an undamped ``model.spring_damping``, make a new
    integrator (or the corrector stays off and the step is first order)."""

    name = "velocity_verlet"
    order = 2

    def __init__(self, model: Model):
        super().__init__(model)
        n, vec3, device = model.state_size, model.vec3, model.device
        # The half-step state: positions and time are state_out's (set per step), velocities v½, forces f(x', v½).
        self._half = State(
            particle_q=None,
            particle_qd=wp.zeros(n, dtype=vec3, device=device),
            particle_f=wp.zeros(n, dtype=vec3, device=device),
            time=None,
        )
        self._damped_springs = bool(model.spring_count and (model.spring_damping.numpy() != 0.0).any())  # any world
        self._damped_springs |= any(family.velocity_dependent(model) for family in model.extra_families)

    @property
    def velocity_dependent(self) -> bool:
        """Whether the forces depend on velocity (then the corrector runs)."""
        return self.model.drag_enabled or self._damped_springs

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        drift, kick = verlet_kernels(model.scalar)
        common = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        h = model.scalar(dt)
        half = self._half
        mass = [model.particle_count, model.particle_flags, model.particle_inv_mass]
        eval_forces(model, state_in, control, dampers=self.dampers)
        wp.launch(
            drift,
            inputs=[*mass, state_in.particle_q, state_in.particle_qd, state_in.particle_f, state_in.time,
                    *step_arguments(model.scalar, dt)],
            outputs=[state_out.particle_q, half.particle_qd, state_out.time],
            **common,
        )
        half.particle_q, half.time = state_out.particle_q, state_out.time
        # Driven pins at t + h: their exact velocity there stands in for v½ (the kicks leave it unchanged).
        apply_kinematics(model, control, state_in, state_out.particle_q, half.particle_qd, dt)
        eval_forces(model, half, control)  # f(x', v½)
        wp.launch(kick, inputs=[*mass, half.particle_qd, half.particle_f, h], outputs=[state_out.particle_qd], **common)
        if self.velocity_dependent:
            eval_forces(model, state_out, control)  # f(x', v*)
            wp.launch(kick, inputs=[*mass, half.particle_qd, state_out.particle_f, h],
                      outputs=[state_out.particle_qd], **common)
        self.finish_step(state_out, dt, state_in)
        self.hold_worlds(state_in, state_out)
