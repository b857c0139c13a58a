"""Launch functions of the force terms and the contact pass. Each returns at once when the model lacks
what it would evaluate: nothing is launched for a feature the scene does not use. Forces are evaluated
at the time of the state they are given: animated inputs (keyframe tracks) are written for that time
first."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import warp as wp

from ..kernels.forces import clamp_forces_kernel, eval_forces_kernel
from ..kernels.shapes import NO_CONTACTS
from ..kernels.springs import DAMPER_NONE, spring_scatter_kernel
from ..kernels.sweep import sweeps, symplectic_euler_sweep_kernel
from .model import Model
from .state import State
from .control import Control
from .tracks import evaluate_input_tracks
from ..kernels.flatten import flat_launch


@dataclass
class DamperSums:
    """The scattered springs' dampers counted in their force pass (``spring_scatter_kernel``'s ``dissipation``): the
    guard that reads the sums hands them to its integrator (``Integrator.dampers``), which passes them to the
    evaluation at each step's start state (``eval_forces``'s ``dampers``).

    Attributes:
        rule: the ``DAMPER_*`` rule of ``kernels/springs.py``.
        h: the step [s].
        skip: per world, non-zero where the step before was counted already, int32, shape [world_count].
        damper: each spring's rate [m/s] or power [W] at the last step's start, shape [world_count · spring_count].
        dissipated: each spring's energy taken out since the guard last read it [J], float64, same shape.
    """

    rule: int
    h: float
    skip: wp.array
    damper: wp.array
    dissipated: wp.array


@dataclass
class PowerSums:
    """The power of the dampers, drag and the loads from outside, counted for the guard in the per-particle pass that
    already evaluates the forces: the guard hands them to its integrator (``Integrator.power``). Each free particle
    adds to its own entry (no atomics): symplectic Euler's fused step the energy over the step
    (``symplectic_euler_kernel``'s ``power``), the other integrators' evaluation at a step's start state h times the
    power there (``eval_forces``'s ``power``; the guard closes the trapezoid at its checks). Symplectic Euler with
    scattered springs (their dampers counted in their own pass: ``DamperSums``) stores the other dampers' and the
    outside loads' parts of the force instead (``forces``), and its update counts them with the step's velocities.

    Attributes:
        modes: one ``kernels/forces.POWER_*`` per family of the model, in its order.
        h: the step [s].
        sums: per particle, (energy the dampers and drag took out [J], work the loads from outside did [J]) since the
            guard's last check, vec2 of the model's precision, shape [world_count · particle_count]; the energy alone
            (a scalar) where nothing does work from outside (``work`` off: ``kernels/forces.counts_work``).
        work: whether ``sums`` carry the loads' work.
        forces: ``None``, or (the dampers' part [N], the outside loads' part [N]) of each particle's force, vec3
            arrays of the state's shape, which the force pass writes and symplectic Euler's update reads.
    """

    modes: tuple
    h: float
    sums: wp.array
    forces: tuple | None = None
    work: bool = True


def force_inputs(model: Model, control: Control | None, features) -> list:
    """The model and control arguments of every force-evaluating kernel, as ``particle_force`` takes them:
    masses, the element families' arrays, the live-input table (gravity, drag, limits), external force."""
    return [model.particle_mass, model.elements, model.inputs, control.particle_force if features.external else None]


def eval_forces(model: Model, state: State, control: Control | None, *, particle_f: wp.array | None = None,
                dampers: DamperSums | None = None, power: PowerSums | None = None) -> None:
    """Write the total force [N] on every particle (gravity, drag, external, element families) to ``particle_f``.

    Springs are gathered per particle or scattered per spring as ``model.spring_gather`` says; every other
    family is gathered. On the CPU, with gathered springs (and the guard's power summed, if asked, rather than its
    force parts stored), each world is one thread sweeping its particles, each spring evaluated once
    (``kernels/sweep.py``'s forces alone; the same forces summed in another order: float rounding).

    Args:
        model: the model.
        state: positions and velocities to evaluate at.
        control: external inputs, or ``None``.
        particle_f: output, shape [world_count · particle_count]; default ``state.particle_f``.
        dampers: the guard's springs' sums, given at a step's start state only (scattered springs: the step before
            counted), or ``None``.
        power: the guard's power sums, given at a step's start state only (h times the power there added), or
            ``None``.
    """
    if model.particle_count == 0:
        return
    evaluate_input_tracks(model, state)
    features = model.force_features(control)
    scatter = model.spring_count > 0 and not model.spring_gather
    out = state.particle_f if particle_f is None else particle_f
    stored = power is not None and power.forces is not None
    if model.device.is_cpu and not scatter and not stored and sweeps(features):
        modes = None if power is None else power.modes
        flat_launch(
            symplectic_euler_sweep_kernel(model.scalar, features, NO_CONTACTS, modes, True),
            dim=model.world_count,
            inputs=[model.particle_count, model.particle_flags, model.particle_inv_mass, model.particle_radius,
                    model.shape_arrays, *force_inputs(model, control, features), state.particle_q, state.particle_qd,
                    None, model.scalar(0.0 if power is None else power.h), model.scalar(0.0)],
            outputs=[None, None, None, None if power is None else power.sums, out,
                     None if power is None else _dampers_scratch(model)],
            device=model.device,
        )
        return
    flat_launch(
        # With scattered springs the force clamp must wait for the springs: a pass of its own below.
        eval_forces_kernel(model.scalar, features._replace(clamp_particle_force=False) if scatter else features,
                           None if power is None else power.modes, stored),
        dim=model.particle_dim,
        block_dim=model.block_dim,
        inputs=[model.particle_count, model.particle_flags, *force_inputs(model, control, features), state.particle_q,
                state.particle_qd, 0.0 if power is None else power.h],
        outputs=[out, *(power.forces if stored else (None, None)), None if power is None else power.sums],
        device=model.device,
    )
    if scatter:
        counted = dampers is not None
        flat_launch(
            spring_scatter_kernel(model.scalar, model.spring_law, dampers.rule if counted else DAMPER_NONE),
            dim=(model.world_count, model.spring_count),
            inputs=[model.particle_count, model.spring_arrays(), model.inputs, state.particle_q, state.particle_qd,
                    dampers.h if counted else 0.0, dampers.skip if counted else None],
            outputs=[out, dampers.damper if counted else None, dampers.dissipated if counted else None],
            device=model.device,
        )
        if features.clamp_particle_force:
            wp.launch(clamp_forces_kernel(model.scalar), dim=model.particle_dim, block_dim=model.block_dim,
                      inputs=[model.particle_count, model.inputs], outputs=[out], device=model.device)


_DAMPERS_SCRATCH = weakref.WeakKeyDictionary()


def _dampers_scratch(model: Model) -> wp.array:
    """The CPU force sweep's scratch for the springs' dampers' part [N] (a state's size; it leaves it zero)."""
    scratch = _DAMPERS_SCRATCH.get(model)
    if scratch is None or scratch.shape[0] != model.state_size:
        scratch = wp.zeros(model.state_size, dtype=model.vec3, device=model.device)
        _DAMPERS_SCRATCH[model] = scratch
    return scratch
