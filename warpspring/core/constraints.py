"""The passes every integrator runs on its result: strain limiting, speed clamping, contacts, and last the
plastic springs' pass (their rest lengths move toward their lengths in the finished state).

Only what the model asks for is launched: with no stabilizer and no collider nothing runs; with only
static colliders, one contact kernel (which symplectic Euler fuses into its update); with the contact
stage, the colliders' motion, ``collide`` and the response. The limits are live inputs, read at the
state's time.
"""

from __future__ import annotations

import warp as wp

from .contacts import Contacts, apply_contacts, collide_positions, empty_contacts, update_shape_frames
from .contacts import apply_triangle_contacts
from ..kernels.constraints import finish_step_kernel, strain_limit_kernel
from ..kernels.springs import spring_plastic_kernel
from .model import Model
from .state import State
from .tracks import evaluate_input_tracks
from ..kernels.flatten import flat_launch


class StepFinisher:
    """Applies the post-step passes of ``model`` to a state, in place (device work only: capturable).

    Which passes run follows the model's current stabiliser switches (a switch changed between frames is a
    structural change of the model, and the next capture picks it up)."""

    def __init__(self, model: Model):
        self.model = model
        self._buffers = None  # (positions before, two Jacobi buffers): allocated once strain limiting is on
        self._contacts = None
        #: Called as ``watch(state, -1.0)`` before the self-collision pass and ``watch(state, 1.0)`` after it (device
        #: work only), or ``None``: the guard's count of the energy that pass puts in (``Guard._watch_corrections``).
        self.watch = None

    @property
    def contacts(self) -> Contacts | None:
        """The contact buffer of the contact stage (made on first use), or ``None`` without one."""
        if not self.model.contact_stage:
            return None
        if self._contacts is None:
            self._contacts = Contacts(self.model)
        return self._contacts

    def history(self) -> list:
        """Device arrays one step leaves to the next: the contact buffer's overflow counters, the self-collision
        counters, the mesh caches' counters, and the plastic springs' rest lengths and plastic strains."""
        carried = self.contacts.history() if self.contacts is not None else []
        if self.model.self_contact is not None:
            carried += self.model.self_contact.history()
        if self.model.mesh_colliders:  # the mesh caches' counters (their entries never change a result)
            carried += [self.model.shape_arrays.cache.overflow, self.model.shape_arrays.cache.refreshes]
        if self.plastic:
            carried += [self.model.spring_plastic_rest_length, self.model.spring_plastic_strain]
        return carried

    @property
    def plastic(self) -> bool:
        """Whether some spring may yield or break: the plastic pass then ends every step."""
        return self.model.spring_plastic_count > 0

    def plastic_pass(self, state: State, dt: float) -> None:
        """Move the plastic springs' rest lengths (and plastic strains, and break springs) by the finished
        ``state`` of a step of ``dt`` [s], in every world that is not held (``kernels.springs.spring_plastic_kernel``).
        Runs once per step, after every other pass: Runge-Kutta stages, CG iterations and dopri5's rejected
        internal steps never reach it, so they all see the rest lengths of the step's start."""
        model = self.model
        if not self.plastic:
            return
        family = next(f for f in model.families if f.name == "springs")
        flat_launch(
            spring_plastic_kernel(model.scalar, model.spring_law),
            dim=(model.world_count, model.spring_plastic_count),
            inputs=[model.particle_count, model.world_enabled, model.spring_arrays(), family.plastic_arrays(model),
                    model.inputs, model.scalar(dt), state.particle_q],
            outputs=[model.spring_plastic_rest_length, model.spring_plastic_strain],
            device=model.device,
        )

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
    def stabilised(self) -> bool:
        """True when strain limiting or the speed clamp runs before the contacts."""
        return self.strain_limited or self.speed_clamped

    @property
    def only_contacts(self) -> bool:
        """True when the pass is just the contact response against every collider (no stabiliser, no contact
        stage, no plastic springs, no triangle contacts, no self-collision), which integrators may fuse into their
        update."""
        if self.model.self_contact is not None:  # self-collision reads the step's start: never fused
            return False
        return not (self.stabilised or self.model.contact_stage or self.plastic or self.model.contact_triangles)

    def __call__(self, state: State, dt: float, state_in: State | None = None) -> None:
        """Finish ``state``, the result of a step of ``dt`` [s] from ``state_in``: the stabilisers, the
        contacts, then self-collision (which needs ``state_in``: without it, self-collision is skipped), and last
        the plastic springs' rest lengths, from the finished state."""
        self_contact = self.model.self_contact if state_in is not None else None
        watch = self.watch if self_contact is not None else None
        if watch is not None and not self.stabilised:
            watch(state, -1.0)  # (the stabilisers' pass moves the pins to their targets: its bracket starts after it)
        self._finish(state, dt)
        if self_contact is not None:
            if watch is not None and self.stabilised:
                watch(state, -1.0)
            self_contact(state_in, state, dt)
            if watch is not None:
                watch(state, 1.0)
        self.plastic_pass(state, dt)

    def _finish(self, state: State, dt: float) -> None:
        model = self.model
        update_shape_frames(model, state.time, dt)
        if not self.stabilised:
            if model.contact_stage:
                collide_positions(model, state.particle_q, self.contacts, velocities=state.particle_qd, dt=dt)
            apply_contacts(model, state, dt, self.contacts)
            apply_triangle_contacts(model, state)
            return
        evaluate_input_tracks(model, state)
        common = dict(dim=model.particle_dim, block_dim=model.block_dim, device=model.device)
        corrected = state.particle_q
        strain_limited = self.strain_limited
        before = None
        if strain_limited:
            limit = strain_limit_kernel(model.scalar, model.spring_incidence_shape, model.spring_law)
            table = [model.particle_count, model.particle_flags, model.particle_inv_mass, model.spring_arrays(),
                     model.inputs]
            before, *jacobi = self._strain_buffers()
            wp.copy(before, state.particle_q)
            source = state.particle_q
            for k in range(model.stabilizers.strain_iterations):
                target = jacobi[k % 2]
                flat_launch(limit, inputs=[*table, source], outputs=[target], **common)
                source = target
            corrected = source
        if model.contact_stage:
            collide_positions(model, corrected, self.contacts, before=before, velocities=state.particle_qd, dt=dt)
        flat_launch(
            finish_step_kernel(model.scalar, model.contact_features(), self.speed_clamped, strain_limited),
            inputs=[
                model.particle_count,
                model.particle_flags,
                model.particle_radius,
                model.shape_arrays,
                (self.contacts or empty_contacts(model)).arrays,
                model.inputs,
                corrected,
                before if strain_limited else state.particle_q,
                model.scalar(dt),
            ],
            outputs=[state.particle_q, state.particle_qd],
            **common,
        )
        apply_triangle_contacts(model, state)
