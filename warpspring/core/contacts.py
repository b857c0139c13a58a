"""The contact stage: collider motion, the contact buffer, ``collide`` and the response.

A step that meets colliders ends with three launches when the model uses the contact stage
(``Model.contact_stage``: by default when a collider moves):

1. :func:`update_shape_frames` writes every animated collider's frame at the step's start and end (each
   world at its own time), from which the response takes the surface velocity;
2. :func:`collide` records, for every particle, the colliders it touches in its slots of a
   :class:`Contacts` buffer (at most ``Model.contact_slots`` each; more are counted as overflow);
3. the response (:func:`apply_contacts`, or the integrators' finishing kernel) projects every particle out
   of the colliders in its slots, with restitution and friction relative to the moving surface.

With static colliders only, the response instead tests every collider itself, fused into the update
(``kernels/contacts.py`` has the maths). A scene without colliders launches none of this.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels.contacts import NO_SHAPE, collide_kernel, contact_slots_type, project_contacts_kernel
from ..kernels.swept import shape_motion_kernel
from .. import checks
from ..errors import ConfigError
from .model import Model
from .state import State
from ..kernels.flatten import flat_launch
from ..kernels.triangle_contacts import TRIANGLE_KINDS, triangle_gather_kernel, triangle_push_kernel
from ..kernels.shapes import ContactFeatures


class Contacts:
    """A fixed-capacity buffer of particle-collider contacts: ``slots`` per particle of every world.

    Args:
        model: the model whose states it serves.
        slots: contacts a particle can hold; default ``model.contact_slots`` (0: a buffer that records none,
            what kernels that test every collider themselves are handed).
        margin: distance beyond a particle's radius [m] at which a contact is recorded, ≥ 0 (the response
            acts only on particles within their radius; a margin lets positions change between ``collide``
            and the response).

    Attributes:
        arrays: the device struct the kernels read (``kernels.contacts.contact_slots_type``).
        slots: contacts per particle.
    """

    def __init__(self, model: Model, *, slots: int | None = None, margin: float = 0.0):
        self.model = model
        self.slots = model.contact_slots if slots is None else checks.count("contact slots", slots, minimum=0)
        margin = checks.non_negative("contact margin", margin)
        device, size = model.device, model.state_size
        arrays = contact_slots_type(model.scalar)()
        arrays.shape = wp.full((size, self.slots), NO_SHAPE, dtype=wp.int32, device=device)
        arrays.feature = wp.full((size, self.slots), NO_SHAPE, dtype=wp.int32, device=device)
        arrays.count = wp.zeros(size, dtype=wp.int32, device=device)
        arrays.overflow = wp.zeros(model.world_count, dtype=wp.int32, device=device)
        arrays.margin = wp.array([margin], dtype=model.scalar, device=device)
        self.arrays = arrays

    @property
    def capacity(self) -> int:
        """Contacts the buffer holds in all: slots × particles × worlds."""
        return self.slots * self.model.state_size

    def overflow(self) -> np.ndarray:
        """Contacts found beyond a particle's slots (and so not resolved) since the buffer was made or
        :meth:`reset`, per world, int64, shape [world_count] (reads the device)."""
        return self.arrays.overflow.numpy().astype(np.int64)

    def counts(self) -> np.ndarray:
        """Contacts each particle holds now, int32, shape [world_count, particle_count] (reads the device)."""
        return self.arrays.count.numpy().reshape(self.model.world_count, self.model.particle_count)

    def shapes(self, world: int = 0) -> list[list[int]]:
        """The colliders each particle of ``world`` touches now, in collider order (reads the device)."""
        count = self.counts()[world]
        shape = self.arrays.shape.numpy().reshape(self.model.world_count, self.model.particle_count, self.slots)[world]
        return [list(map(int, shape[i, : count[i]])) for i in range(self.model.particle_count)]

    def reset(self) -> None:
        """Zero the overflow counters."""
        self.arrays.overflow.zero_()

    def history(self) -> list:
        """The device arrays a step leaves to the next (the overflow counters): a Stepper restores them
        around its warm-up step, so it counts nothing twice."""
        return [self.arrays.overflow]


def update_shape_frames(model: Model, time: wp.array, dt: float, *, ahead: bool = False) -> None:
    """Write every collider's frame at the start and end of a step of ``dt`` [s] (device work; nothing is
    launched unless a collider moves). ``time`` [s] per world is the step's end, or with ``ahead`` its start."""
    if not model.shape_moving:
        return
    flat_launch(
        shape_motion_kernel(model.scalar),
        dim=(model.world_count, model.shape_count),
        inputs=[model.shape_rest, model.shape_translation_track, model.shape_rotation_track,
                model.track_table.table, time, wp.float64(dt), wp.float64(dt if ahead else 0.0)],
        outputs=[model.shape_arrays],
        device=model.device,
    )


def collide(model: Model, state: State, contacts: Contacts, *, dt: float = 0.0) -> None:
    """Fill ``contacts`` with the colliders every dynamic particle of ``state`` touches, against the
    colliders' current frames (those of the last step, or the rest frames before the first). With ``dt`` [s]
    > 0 (the step that produced ``state``), also those its path x - dt v → x entered (spheres, boxes,
    meshes). Capturable."""
    q = state.particle_q
    if (q.shape[0], q.dtype, str(q.device)) != (model.state_size, model.vec3, str(model.device)):
        raise ConfigError(f"collide: the state has {q.shape[0]} particles of {q.dtype.__name__} on {q.device}, but "
                          f"the model's have {model.state_size} of {model.vec3.__name__} on {model.device}: use a "
                          "state made by this model's state()")
    collide_positions(model, state.particle_q, contacts, velocities=state.particle_qd, dt=dt)


def collide_positions(model: Model, positions: wp.array, contacts: Contacts, *, before: wp.array | None = None,
                      velocities: wp.array | None = None, dt: float = 0.0) -> None:
    """:func:`collide` for a positions array of a state's size (e.g. after strain limiting). A particle's path
    over the step starts at ``before`` - dt ``velocities`` (``before``: the positions before the correction,
    default ``positions``); without velocities or with dt = 0 no path is swept."""
    if model.shape_count == 0:
        contacts.arrays.count.zero_()
        return
    before = positions if before is None else before
    if velocities is None:
        velocities, dt = positions, 0.0
    flat_launch(
        collide_kernel(model.scalar, model.contact_features()),
        dim=model.particle_dim,
        block_dim=model.block_dim,
        inputs=[model.particle_count, model.particle_flags, model.particle_radius, model.shape_arrays, positions,
                before, velocities, model.scalar(dt)],
        outputs=[contacts.arrays],
        device=model.device,
    )


def apply_contacts(model: Model, state: State, dt: float, contacts: Contacts | None = None) -> None:
    """Project the dynamic particles of ``state`` out of the colliders, with restitution and friction, in
    place; ``dt`` [s] is the step that produced ``state``. With the contact stage, only the colliders in
    each particle's slots of ``contacts`` (fill them with :func:`collide` first)."""
    if model.shape_count == 0:
        return
    features = model.contact_features()
    if features.buffered and contacts is None:
        raise ConfigError("this model resolves contacts through the contact stage: pass the Contacts that "
                         "collide() filled")
    flat_launch(
        project_contacts_kernel(model.scalar, features),
        dim=model.particle_dim,
        block_dim=model.block_dim,
        inputs=[model.particle_count, model.particle_flags, model.particle_radius, model.shape_arrays, model.inputs,
                (contacts or empty_contacts(model)).arrays, model.scalar(dt)],
        outputs=[state.particle_q, state.particle_qd],
        device=model.device,
    )


#: Jacobi passes of the triangle contacts per step: one pass moves a particle by the mean of its triangles'
#: corrections, which a heavy cloth outruns on a small sphere (seed 002's soft cloth on a 4 cm sphere at 20
#: substeps: its surface 1.2 mm inside the sphere after one pass, none after four; ``tests/test_contact_rule.py``).
TRIANGLE_ITERATIONS = 4


def apply_triangle_contacts(model: Model, state: State) -> None:
    """Push the cloth's triangles out of the spheres and capsules (``kernels/triangle_contacts.py``), in place:
    each triangle's corners get the barycentric share of its correction, each particle the mean of its
    corners' (no float atomics), ``TRIANGLE_ITERATIONS`` times. Nothing runs unless ``model.contact_triangles``
    is set and the model has triangles and a sphere or capsule. Capturable."""
    kinds = tuple(k for k in model.shape_types if k in TRIANGLE_KINDS)
    if not (model.contact_triangles and model.tri_count and kinds):
        return
    buffers = model.__dict__.get("_triangle_contacts")
    if buffers is None:  # the particles' incident corners (CSR), and a correction per corner of every world
        corners = model.tri_indices.numpy().reshape(-1)
        order = np.argsort(corners, kind="stable").astype(np.int32)
        start = np.zeros(model.particle_count + 1, dtype=np.int32)
        np.cumsum(np.bincount(corners, minlength=model.particle_count), out=start[1:])
        device = model.device
        buffers = model.__dict__["_triangle_contacts"] = (
            wp.array(start, dtype=wp.int32, device=device), wp.array(order, dtype=wp.int32, device=device),
            wp.zeros(3 * model.world_count * model.tri_count, dtype=model.vec3, device=device))
    start, index, push = buffers
    for _ in range(TRIANGLE_ITERATIONS):
        _triangle_pass(model, state, kinds, start, index, push)


def _triangle_pass(model: Model, state: State, kinds: tuple, start, index, push) -> None:
    """One Jacobi pass of :func:`apply_triangle_contacts`: every triangle's corrections, then every particle's mean."""
    flat_launch(
        triangle_push_kernel(model.scalar, ContactFeatures(kinds=kinds)),
        dim=model.world_count * model.tri_count,
        inputs=[model.particle_count, model.tri_indices, model.particle_radius, model.shape_arrays, state.particle_q],
        outputs=[push],
        device=model.device,
    )
    wp.launch(
        triangle_gather_kernel(model.scalar),
        dim=model.particle_dim,
        block_dim=model.block_dim,
        inputs=[model.particle_count, model.tri_count, model.particle_flags, start, index, push],
        outputs=[state.particle_q, state.particle_qd],
        device=model.device,
    )


def empty_contacts(model: Model) -> Contacts:
    """A buffer of no slots, for the kernels' contact argument where the response tests every collider
    itself (one per model, made once)."""
    empty = model.__dict__.get("_empty_contacts")
    if empty is None:
        empty = model.__dict__["_empty_contacts"] = Contacts(model, slots=0)
    return empty
