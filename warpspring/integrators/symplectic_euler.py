"""Symplectic (semi-implicit) Euler: v' = v + h M⁻¹ f(x, v); x' = x + h v'. First order, symplectic for
conservative forces; one fused kernel per step (forces, update and contacts in one pass)."""

from __future__ import annotations

import warp as wp

from ..kernels.integrators import symplectic_euler_kernel
from ..model import Control, State
from .base import Integrator


class SymplecticEuler(Integrator):
    """Symplectic Euler with explicit spring damping. Stable for undamped springs while ω_max·h < 2."""

    name = "symplectic_euler"
    order = 1

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        features = model.force_features(control)
        wp.launch(
            symplectic_euler_kernel(model.scalar, features, model.shape_types),
            dim=model.particle_count,
            inputs=[
                model.particle_mass,
                model.particle_inv_mass,
                model.particle_radius,
                model.particle_spring_offset,
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
