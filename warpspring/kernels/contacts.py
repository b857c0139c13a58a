"""The contact stage: the particle-shape contact buffer, the kernel that fills it and the kernel that applies the
response to a state from it.

The contact code is spread by topic: the colliders and their distances (``shapes.py``, mesh colliders in
``mesh_colliders.py``), paths over a step and the shapes' motion (``swept.py``), and the response
(``response.py``). Here they meet.

**The contact buffer.** ``collide_kernel`` finds, for every particle, the shapes whose surface is within
its radius plus a margin, and records them in per-particle slots (:class:`ContactSlots`): the shape
index, in shape order, at most ``slots`` of them. A particle touching more shapes than it has slots keeps
the first ``slots`` and adds the rest to its world's overflow counter (an integer atomic: the count is
exact, the kept contacts do not depend on thread order). With swept paths, a shape the path entered is
recorded too. The response pass walks a particle's own slots, so it writes every result once, without
atomics.
"""

import functools

import warp as wp

from .flatten import flat_kernel
from .kinematics import is_kinematic
from .precision import vec3_type
from .response import project_all_func, shape_contact_func
from .shapes import ContactFeatures, shapes_type, surface_funcs
from .swept import shape_crossing_func
from .worlds import world_and_index

wp.set_module_options({"enable_backward": False})

#: Slot of an empty contact, and of a contact with no feature (analytic shapes).
NO_SHAPE = -1


@functools.cache
def contact_slots_type(scalar: type):
    """The ``wp.struct`` of the particle-shape contact buffer (see the module docstring)."""

    @wp.struct
    class ContactSlots:
        shape: wp.array2d[wp.int32]  # [state_size, slots], the shapes a particle touches, in shape order
        feature: wp.array2d[wp.int32]  # [state_size, slots], the touched feature (face) or NO_SHAPE
        count: wp.array[wp.int32]  # [state_size], filled slots
        overflow: wp.array[wp.int32]  # [world_count], contacts found beyond a particle's slots, accumulated
        margin: wp.array[scalar]  # [m], [1], distance beyond the radius at which a contact is recorded

    return ContactSlots


@functools.cache
def project_contacts_func(scalar: type, features: ContactFeatures):
    """Contact response of one particle: against every shape (the fused path) or against the shapes in its
    contact slots (the contact stage), in shape order either way."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    ContactSlots = contact_slots_type(scalar)
    shape_contact = shape_contact_func(scalar, features)
    bounce_speed, project_contacts_all = project_all_func(scalar, features)

    @wp.func
    def project_contacts(
        world: int, p: int, x: vec3, v: vec3, radius: scalar, dt: scalar, shapes: Shapes, contacts: ContactSlots,
        inputs: wp.array2d[scalar],
    ):
        """Resolve the contacts of state entry p of ``world`` (position x [m], velocity v [m/s], radius [m])
        after a step of ``dt`` [s]."""
        if wp.static(features.buffered):
            speed = bounce_speed(world, inputs, dt)
            x0 = x - dt * v
            for k in range(contacts.count[p]):
                x, v = shape_contact(shapes, contacts.shape[p, k], world, p, x0, x, v, radius, speed, dt)
            return x, v
        return project_contacts_all(world, p, x, v, radius, dt, shapes, inputs)

    return project_contacts


@functools.cache
def collide_kernel(scalar: type, features: ContactFeatures):
    """Kernel filling the contact slots of every dynamic particle of a state from its positions (the shapes'
    frames at the step's end), and with ``features.swept`` from its path over the step, from
    ``particle_q_before`` - dt ``particle_qd`` (the positions before strain limiting, or the state's own) to
    ``particle_q``. Launch over the state's entries."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    ContactSlots = contact_slots_type(scalar)
    _, shape_distance = surface_funcs(scalar, features)
    shape_crossing = shape_crossing_func(scalar, features)

    @flat_kernel(module="unique", enable_backward=False)
    def collide(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        # State in:
        particle_q: wp.array[vec3],
        particle_q_before: wp.array[vec3],
        particle_qd: wp.array[vec3],
        dt: scalar,
        # In/out (the contact buffer; its margin in, its slots out):
        contacts_in_out: ContactSlots,
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        found = int(0)
        if not is_kinematic(particle_flags[p]):
            x = particle_q[p]
            x0 = particle_q_before[p] - dt * particle_qd[p]  # the response's path start (see the module docstring)
            reach = particle_radius[i] + contacts_in_out.margin[0]
            slots = contacts_in_out.shape.shape[1]
            for s in range(shapes.kind.shape[0]):
                distance, normal = shape_distance(shapes, s, world, p, x)
                touched = distance < reach
                if wp.static(features.swept):
                    if not touched:
                        crossed, crossed_distance, crossed_normal, entry = shape_crossing(
                            shapes, s, world, p, x0, x, particle_radius[i])
                        touched = crossed
                if touched:
                    if found < slots:
                        contacts_in_out.shape[p, found] = s
                        contacts_in_out.feature[p, found] = NO_SHAPE
                        found += 1
                    else:
                        wp.atomic_add(contacts_in_out.overflow, world, 1)
        contacts_in_out.count[p] = found

    return collide


@functools.cache
def project_contacts_kernel(scalar: type, features: ContactFeatures):
    """Kernel applying the contact response to every dynamic particle of a state, in place."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    ContactSlots = contact_slots_type(scalar)
    project_contacts = project_contacts_func(scalar, features)

    @flat_kernel(module="unique", enable_backward=False)
    def project(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        inputs: wp.array2d[scalar],
        # Contacts in (the buffer collide filled), the step:
        contacts: ContactSlots,
        dt: scalar,
        # State in/out:
        particle_q_in_out: wp.array[vec3],
        particle_qd_in_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if is_kinematic(particle_flags[p]):
            return
        x, v = project_contacts(world, p, particle_q_in_out[p], particle_qd_in_out[p], particle_radius[i], dt,
                                shapes, contacts, inputs)
        particle_q_in_out[p] = x
        particle_qd_in_out[p] = v

    return project
