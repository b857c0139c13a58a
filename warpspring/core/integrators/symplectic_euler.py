"""Symplectic (semi-implicit) Euler: v' = v + h M⁻¹ f(x, v); x' = x + h v'. First order, symplectic for
conservative forces. With gathered springs a step is one fused kernel (forces, update and contacts in one pass):
on CUDA one thread per particle; on the CPU one thread per world sweeping its particles in order, each spring
evaluated once (``kernels/sweep.py``). With scattered springs it is force evaluation then the update."""

from __future__ import annotations


from ...kernels.integrators import symplectic_euler_kernel, symplectic_euler_update_kernel
from ...kernels.shapes import NO_CONTACTS
from ...kernels.sweep import sweeps, symplectic_euler_sweep_kernel
from ..contacts import update_shape_frames
from ..forces import eval_forces, force_inputs
from ..kinematics import apply_kinematics
from ..state import State
from ..control import Control
from ..tracks import evaluate_input_tracks
from .base import Integrator, step_arguments
from ...kernels.flatten import flat_launch


class SymplecticEuler(Integrator):
    """Symplectic Euler with explicit spring damping. Stable for undamped springs while ω_max·h < 2.

    Args:
        model: the model.
        cpu_sweep: on the CPU, with gathered springs, step each world in one thread sweeping its particles in
            order, each spring evaluated once (``kernels/sweep.py``; 1.7-1.8x the per-particle step at 32²-64²,
            bench/results/performance_cpu.md §0); False: one thread per particle, as on CUDA. Both give the same
            forces, summed in another order (float rounding). No effect on CUDA or with scattered springs.
    """

    name = "symplectic_euler"
    order = 1

    def __init__(self, model, *, cpu_sweep: bool = True):
        super().__init__(model)
        self.cpu_sweep = bool(cpu_sweep)

    def step(self, state_in: State, state_out: State, control: Control | None, dt: float) -> None:
        model = self.model
        # Contacts fuse into the update unless other post-step passes (or the contact stage) must run first.
        fused = self.finish_step.only_contacts
        contacts = model.contact_features() if fused else NO_CONTACTS
        if fused:
            update_shape_frames(model, state_in.time, dt, ahead=True)
        common = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        if model.spring_gather or model.spring_count == 0:
            evaluate_input_tracks(model, state_in)
            features = model.force_features(control)
            power = None if self.power is None else self.power.modes
            swept = self.cpu_sweep and model.device.is_cpu and sweeps(features)
            if swept:  # one thread per world: the particles in order, each spring once
                kernel = symplectic_euler_sweep_kernel(model.scalar, features, contacts, power)
                # Its scratch: the two states' force arrays (the step's to use; left zero).
                common["dim"], scratch = model.world_count, [state_in.particle_f, state_out.particle_f]
            else:
                kernel, scratch = symplectic_euler_kernel(model.scalar, features, contacts, power), []
            flat_launch(
                kernel,
                inputs=[
                    model.particle_count,
                    model.particle_flags,
                    model.particle_inv_mass,
                    model.particle_radius,
                    model.shape_arrays,
                    *force_inputs(model, control, features),
                    state_in.particle_q,
                    state_in.particle_qd,
                    state_in.time,
                    *step_arguments(model.scalar, dt),
                ],
                outputs=[state_out.particle_q, state_out.particle_qd, state_out.time,
                         None if self.power is None else self.power.sums, *scratch],
                **common,
            )
        else:
            power = self.power
            eval_forces(model, state_in, control, dampers=self.dampers, power=power)
            counted = power is not None and power.forces is not None
            flat_launch(
                symplectic_euler_update_kernel(model.scalar, contacts, counted, counted and power.work),
                inputs=[
                    model.particle_count,
                    model.particle_flags,
                    model.particle_inv_mass,
                    model.particle_radius,
                    model.shape_arrays,
                    model.inputs,
                    state_in.particle_q,
                    state_in.particle_qd,
                    state_in.particle_f,
                    state_in.time,
                    *step_arguments(model.scalar, dt),
                    *(power.forces if counted else (None, None)),
                ],
                outputs=[state_out.particle_q, state_out.particle_qd, state_out.time,
                         power.sums if counted else None],
                **common,
            )
        apply_kinematics(model, control, state_in, state_out.particle_q, state_out.particle_qd, dt)
        if not fused:
            self.finish_step(state_out, dt, state_in)
        self.hold_worlds(state_in, state_out)
