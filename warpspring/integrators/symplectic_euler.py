"""Symplectic (semi-implicit) Euler: v' = v + h M⁻¹ f(x, v); x' = x + h v'. First order, symplectic for
conservative forces. With gathered springs (CUDA) a step is one fused kernel (forces, update and
contacts in one pass); with scattered springs (CPU) it is force evaluation then the update."""

from __future__ import annotations

import warp as wp

from ..forces import eval_forces
from ..kernels.integrators import symplectic_euler_kernel, symplectic_euler_update_kernel
from ..model import Control, State
from .base import Integrator


class SymplecticEuler(Integrator):
    """Symplectic Euler with explicit spring damping. Stable for undamped springs while ω_max·h < 2."""

    name = "symplectic_euler"
    order = 1

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        if not model.spring_gather and model.spring_count:
            eval_forces(model, state_in, control)
            wp.launch(
                symplectic_euler_update_kernel(model.scalar, model.shape_types),
                dim=model.particle_count,
            block_dim=model.block_dim,
                inputs=[
                    model.particle_inv_mass,
                    model.particle_radius,
                    model.shape_type,
                    model.shape_transform,
                    model.shape_size,
                    model.shape_friction,
                    state_in.particle_q,
                    state_in.particle_qd,
                    state_in.particle_f,
                    model.scalar(dt),
                ],
                outputs=[state_out.particle_q, state_out.particle_qd],
                device=model.device,
            )
            return
        features = model.force_features(control)
        wp.launch(
            symplectic_euler_kernel(model.scalar, features, model.shape_types),
            dim=model.particle_count,
            block_dim=model.block_dim,
            inputs=[
                model.particle_mass,
                model.particle_inv_mass,
                model.particle_radius,
                                model.particle_spring_neighbor,
                model.particle_spring_id,
                model.spring_rest_length,
                model.spring_stiffness,
                model.spring_damping,
                model.shape_type,
                model.shape_transform,
                model.shape_size,
                model.shape_friction,
                model.vec3(*model.gravity),
                model.scalar(model.drag),
                control.particle_force if features.external else None,
                state_in.particle_q,
                state_in.particle_qd,
                model.scalar(dt),
            ],
            outputs=[state_out.particle_q, state_out.particle_qd],
            device=model.device,
        )
