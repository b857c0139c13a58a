"""Launch functions of the force terms and the contact pass. Each returns at once when the model lacks
what it would evaluate: nothing is launched for a feature the scene does not use. Forces are evaluated
at the time of the state they are given: animated inputs (keyframe tracks) are written for that time
first."""

from __future__ import annotations

import warp as wp

from ..kernels.forces import clamp_forces_kernel, eval_forces_kernel
from ..kernels.springs import spring_scatter_kernel
from .model import Model
from .state import State
from .control import Control
from .tracks import evaluate_input_tracks
from ..kernels.flatten import flat_launch


def force_inputs(model: Model, control: Control | None, features) -> list:
    """The model and control arguments of every force-evaluating kernel, as ``particle_force`` takes them:
    masses, the element families' arrays, the live-input table (gravity, drag, limits), external force."""
    return [model.particle_mass, model.elements, model.inputs, control.particle_force if features.external else None]


def eval_forces(model: Model, state: State, control: Control | None, *, particle_f: wp.array | None = None) -> None:
    """Write the total force [N] on every particle (gravity, drag, external, element families) to ``particle_f``.

    Springs are gathered per particle or scattered per spring as ``model.spring_gather`` says; every other
    family is gathered.

    Args:
        model: the model.
        state: positions and velocities to evaluate at.
        control: external inputs, or ``None``.
        particle_f: output, shape [world_count · particle_count]; default ``state.particle_f``.
    """
    if model.particle_count == 0:
        return
    evaluate_input_tracks(model, state)
    features = model.force_features(control)
    scatter = model.spring_count > 0 and not model.spring_gather
    out = state.particle_f if particle_f is None else particle_f
    flat_launch(
        # With scattered springs the force clamp must wait for the springs: a pass of its own below.
        eval_forces_kernel(model.scalar, features._replace(clamp_particle_force=False) if scatter else features),
        dim=model.particle_dim,
        block_dim=model.block_dim,
        inputs=[model.particle_count, *force_inputs(model, control, features), state.particle_q, state.particle_qd],
        outputs=[out],
        device=model.device,
    )
    if scatter:
        flat_launch(
            spring_scatter_kernel(model.scalar, model.spring_law),
            dim=(model.world_count, model.spring_count),
            inputs=[model.particle_count, model.spring_arrays(), model.inputs, state.particle_q, state.particle_qd],
            outputs=[out],
            device=model.device,
        )
        if features.clamp_particle_force:
            wp.launch(clamp_forces_kernel(model.scalar), dim=model.particle_dim, block_dim=model.block_dim,
                      inputs=[model.particle_count, model.inputs], outputs=[out], device=model.device)
