"""The passes every integrator runs on its result: strain limiting, speed clamping, contacts.

Only what the model asks for is launched: with no stabilizer and no collider nothing runs; with only
colliders, one contact kernel.
"""

from __future__ import annotations

import warp as wp

from .forces import apply_contacts
from ..kernels.constraints import finish_step_kernel, strain_limit_kernel
from .model import Model, State


class StepFinisher:
    """Applies the post-step passes of ``model`` to a state, in place (device work only: capturable)."""

    def __init__(self, model: Model):
        self.model = model
        stabilizers = model.stabilizers
        self.strain_limited = stabilizers.max_strain is not None and model.spring_count > 0
        self.speed_clamped = stabilizers.max_speed is not None
        if self.strain_limited:
            n, vec3, device = model.particle_count, model.vec3, model.device
            self._before = wp.empty(n, dtype=vec3, device=device)
            self._buffers = (wp.empty(n, dtype=vec3, device=device), wp.empty(n, dtype=vec3, device=device))

    @property
    def only_contacts(self) -> bool:
        """True when the pass is just contact projection (which integrators may fuse into their update)."""
        return not (self.strain_limited or self.speed_clamped)

    def __call__(self, state: State, dt: float) -> None:
        model = self.model
        if self.only_contacts:
            apply_contacts(model, state, dt)
            return
        common = dict(dim=model.particle_count, block_dim=model.block_dim, device=model.device)
        corrected = state.particle_q
        if self.strain_limited:
            stabilizers = model.stabilizers
            limit = strain_limit_kernel(model.scalar, model.spring_max_degree, stabilizers.max_strain)
            table = [model.particle_inv_mass, model.particle_spring_neighbor, model.particle_spring_id,
                     model.spring_rest_length]
            wp.copy(self._before, state.particle_q)
            source = state.particle_q
            for k in range(stabilizers.strain_iterations):
                target = self._buffers[k % 2]
                wp.launch(limit, inputs=[*table, source], outputs=[target], **common)
                source = target
            corrected = source
        wp.launch(
            finish_step_kernel(model.scalar, model.shape_types, model.stabilizers.max_speed, self.strain_limited),
            inputs=[
                model.particle_inv_mass,
                model.particle_radius,
                model.shape_type,
                model.shape_transform,
                model.shape_size,
                model.shape_friction,
                corrected,
                self._before if self.strain_limited else state.particle_q,
                model.scalar(dt),
            ],
            outputs=[state.particle_q, state.particle_qd],
            **common,
        )
