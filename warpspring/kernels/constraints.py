"""Post-step passes: Provot strain limiting, speed clamping and contact projection.

Strain limiting (Provot 1995) shortens every spring longer than (1 + ε)·L back to that length by moving
its two ends along the spring, each by its share of the inverse mass (a kinematic end does not move).
The limit ε and the speed limit are live inputs (``inputs.py``): changing them compiles nothing.
It runs as Jacobi passes over the springs' incidence table: each particle moves by the average of the
corrections its over-stretched springs ask for, reading one position buffer and writing another (so
the result does not depend on thread order). The finishing pass then turns the total displacement
into a velocity change (Δv = Δx / h), clamps the speed, and resolves contacts.
"""

import functools

import warp as wp

from .contacts import contact_slots_type, project_contacts_func
from .families import IncidenceShape
from .inputs import INPUT_MAX_SPEED, INPUT_MAX_STRAIN
from .kinematics import is_kinematic, particle_funcs
from .precision import vec3_type
from .shapes import ContactFeatures, shapes_type
from .spring_laws import HOOKE, SpringLaw
from .springs import spring_access_funcs, spring_arrays_type
from .worlds import world_and_index
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})


@functools.cache
def strain_limit_kernel(scalar: type, incidence: IncidenceShape, law: SpringLaw = HOOKE):
    """One Jacobi pass of strain limiting at the strain ``INPUT_MAX_STRAIN`` over the springs' incidence table
    of shape ``incidence``, for the springs' struct of ``law`` (plastic springs: each world's rest lengths;
    a broken spring is never corrected)."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)
    SpringArrays = spring_arrays_type(scalar, law.per_spring)
    rest_at, _ = spring_access_funcs(scalar, law)
    head_slots, tail = incidence

    @wp.func
    def correction_of(
        i: int, neighbor: int, s: int, world: int, base: int, xi: vec3, wi: scalar, stretch_limit: scalar,
        mass_row: int,
        springs: SpringArrays, particle_flags: wp.array[wp.int32], particle_inv_mass: wp.array2d[scalar],
        particle_q_in: wp.array[vec3],
    ):
        """Particle i's share of the correction of spring s to ``neighbor``, and 1 if it is over-stretched."""
        j = base + neighbor
        d = particle_q_in[j] - xi
        length = wp.length(d)
        rest = rest_at(springs, world, s)
        allowed = stretch_limit * rest
        if neighbor != i and rest >= scalar(0.0) and length > allowed:
            share = wi / (wi + effective_inv_mass(particle_flags[j], particle_inv_mass[mass_row, neighbor]))
            return d * (share * (length - allowed) / length), scalar(1.0)
        return vec3(scalar(0.0)), scalar(0.0)

    idle = ("springs__indices", *(f"springs__{p}" for p in incidence.idle()))  # leaves this pass never reads

    @flat_kernel(module="unique", enable_backward=False, last=idle)
    def strain_limit(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        springs: SpringArrays,
        inputs: wp.array2d[scalar],
        # In:
        particle_q_in: wp.array[vec3],
        # Out:
        particle_q_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        base = p - i
        mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        xi = particle_q_in[p]
        wi = effective_inv_mass(particle_flags[p], particle_inv_mass[mass_row, i])
        stretch_limit = scalar(1.0) + inputs[world, INPUT_MAX_STRAIN]
        correction = vec3(scalar(0.0))
        violated = scalar(0.0)
        if wi > scalar(0.0):
            incidence = springs.incidence
            for k in range(wp.static(head_slots)):
                dx, count = correction_of(i, incidence.head_local[k, i], incidence.head_element[k, i], world, base, xi, wi,
                                          stretch_limit, mass_row, springs, particle_flags, particle_inv_mass,
                                          particle_q_in)
                correction += dx
                violated += count
            if wp.static(tail):
                for t in range(incidence.tail_start[i], incidence.tail_start[i + 1]):
                    dx, count = correction_of(i, incidence.tail_local[t], incidence.tail_element[t], world, base, xi, wi,
                                              stretch_limit, mass_row, springs, particle_flags, particle_inv_mass,
                                              particle_q_in)
                    correction += dx
                    violated += count
        if violated > scalar(0.0):
            xi = xi + correction / violated
        particle_q_out[p] = xi

    return strain_limit


@functools.cache
def finish_step_kernel(scalar: type, contacts: ContactFeatures, clamp_speed: bool, from_displacement: bool):
    """The finishing pass: Δv = (x - x_before)/h after position corrections (``from_displacement``),
    speed clamp to the input ``INPUT_MAX_SPEED`` [m/s] (``clamp_speed``), contact response (``contacts``:
    against every collider, or the contact buffer's slots)."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    ContactSlots = contact_slots_type(scalar)
    project_contacts = project_contacts_func(scalar, contacts)
    has_contacts = bool(contacts)

    @flat_kernel(module="unique", enable_backward=False, last=contacts.idle("shapes", "contact_slots"))
    def finish_step(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        contact_slots: ContactSlots,
        inputs: wp.array2d[scalar],
        # In:
        particle_q_corrected: wp.array[vec3],
        particle_q_before: wp.array[vec3],
        dt: scalar,
        # State in/out:
        particle_q_in_out: wp.array[vec3],
        particle_qd_in_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if is_kinematic(particle_flags[p]):
            return
        x = particle_q_in_out[p]
        v = particle_qd_in_out[p]
        if wp.static(from_displacement):
            x = particle_q_corrected[p]
            v = v + (x - particle_q_before[p]) / dt
        if wp.static(clamp_speed):
            speed_limit = inputs[world, INPUT_MAX_SPEED]
            speed = wp.length(v)
            if speed > speed_limit:
                v = v * (speed_limit / speed)
        if wp.static(has_contacts):
            x, v = project_contacts(world, p, x, v, particle_radius[i], dt, shapes, contact_slots, inputs)
        particle_q_in_out[p] = x
        particle_qd_in_out[p] = v

    return finish_step
