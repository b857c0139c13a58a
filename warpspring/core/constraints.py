"""The passes every integrator runs on its result: strain limiting, speed clamping, contacts.

Only what the model asks for is launched: with no stabilizer and no collider nothing runs; with only
colliders, one contact kernel. The limits are live inputs, read at the state's time.
"""

from __future__ import annotations

import warp as wp

from .forces import apply_contacts
from ..kernels.constraints import finish_step_kernel, strain_limit_kernel
from .model import Model, State
from .tracks import evaluate_input_tracks


class StepFinisher:
    """Applies the post-step passes of ``model`` to a state, in place (device work only: capturable).

    Which passes run follows the model's current stabiliser switches (a switch changed between frames is a
    structural change of the model, and the next capture picks it up)."""

    def __init__(self, model: Model):
        self.model = model
        self._buffers = None  # (positions before, two Jacobi buffers): allocated once strain limiting is on

    def _strain_buffers(self):
        if self._buffers is None:
            n, vec3, device = self.model.state_size, self.model.vec3, self.model.device
            self._buffers = tuple(wp.empty(n, dtype=vec3, device=device) for _ in range(3))
        return self._buffers

    @property
    def strain_limited(self) -> bool:
        return self.model.stabilizers.max_strain is not None and self.model.spring_count > 0

    @property
    def speed_clamped(self) -> bool:
        return self.model.stabilizers.max_speed is not None

    @property
    def only_contacts(self) -> bool:
        """True when the pass is just contact projection (which integrators may fuse into their update)."""
        return not (self.strain_limited or self.speed_clamped)

    def __call__(self, state: State, dt: float) -> None:
        model = self.model
        if self.only_contacts:
            apply_contacts(model, state, dt)
            return
        evaluate_input_tracks(model, state)
        common = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        corrected = state.particle_q
        strain_limited = self.strain_limited
        before = None
        if strain_limited:
            limit = strain_limit_kernel(model.scalar, model.spring_incidence_shape)
            table = [model.particle_count, model.particle_flags, model.particle_inv_mass, model.spring_arrays(),
                     model.inputs]
            before, *jacobi = self._strain_buffers()
            wp.copy(before, state.particle_q)
            source = state.particle_q
            for k in range(model.stabilizers.strain_iterations):
                target = jacobi[k % 2]
                wp.launch(limit, inputs=[*table, source], outputs=[target], **common)
                source = target
            corrected = source
        wp.launch(
            finish_step_kernel(model.scalar, model.shape_types, self.speed_clamped, strain_limited),
            inputs=[
                model.particle_count,
                model.particle_flags,
                model.particle_radius,
                model.shape_type,
                model.shape_transform,
                model.shape_size,
                model.shape_friction,
                model.inputs,
                corrected,
                before if strain_limited else state.particle_q,
                model.scalar(dt),
            ],
            outputs=[state.particle_q, state.particle_qd],
            **common,
        )
