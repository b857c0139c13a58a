"""The CPU's symplectic Euler step: one thread per world sweeping its particles in order, each spring evaluated once.

Warp runs a CPU kernel's threads one after another on one core, so what makes the GPU's fused step fast (every
particle gathers its springs, each spring evaluated at both its ends, no atomics) doubles the CPU's arithmetic, and
the scatter (each spring once, then a pass of the update) pays a second launch, a force array's round trip and the
per-thread indexing of a (world, spring) launch. The sweep keeps the gather's data and its one launch and
evaluates each spring once: a world's particles are taken in order, and at particle i

* the forces of its springs to particles before it are complete in ``force_in_out[i]`` (added when those were
  swept), and those to particles after it are evaluated now (``springs.spring_sweep_funcs``'s ``forward``:
  i's share summed, the opposite added to the other particle's entry);
* so its force is complete: the other forces (gravity, drag, external, the other element families, gathered as in
  the fused step), the symplectic Euler update and the contacts follow at once.

The scratch entries are the states' force arrays (``state_in.particle_f`` for the forces, ``state_out.particle_f``
for the dampers' part, used only where the guard counts them: ``State``'s contract leaves both to the step), cleared
by the thread before its sweep and consumed by it: whatever they held before, the step is the same, and it leaves
those it used zero.

Per-world values (the springs' groups, rows and law values, the world's row of the input table) are read once per
world, not per particle. The results are the fused step's up to the order of the force's sums (float32 rounding).
The guard's power sums are counted as in the fused step (``integrators.symplectic_euler_kernel``'s ``power``), the
springs' dampers' part swept alongside their force (``dampers_in_out``). The springs must be the first family
(``Model.families``), gathered; a one-thread-per-world launch is for the CPU only.
"""

import functools

import warp as wp

from .families import FORCE_KERNEL_OPTIONS, elements
from .forces import (
    POWER_DAMPERS,
    ForceFeatures,
    counts_work,
    particle_force_func,
    particle_power_func,
    power_sums_funcs,
)
from .inputs import INPUT_MAX_PARTICLE_FORCE
from .integrators import symplectic_euler_funcs
from .kinematics import is_kinematic
from .precision import vec3_type
from .response import project_all_func
from .shapes import ContactFeatures, shapes_type
from .springs import SpringSpec, spring_sweep_funcs
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})


def sweeps(features: ForceFeatures) -> bool:
    """Whether the sweep can take a step of ``features``: the springs first among the families, gathered."""
    return bool(features.families) and isinstance(features.families[0], SpringSpec) and features.families[0].gathered


@functools.cache
def symplectic_euler_sweep_kernel(scalar: type, features: ForceFeatures, contacts: ContactFeatures,
                                  power: tuple | None = None):
    """Symplectic Euler step of every world, one thread per world (module docstring): the arguments of
    ``integrators.symplectic_euler_kernel`` and the two scratch arrays (module docstring). Launch over
    ``world_count``."""
    if not sweeps(features):
        raise ValueError(f"the sweep needs the springs first among the families, gathered; got {features.families}")
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    counted = power is not None
    springs_spec, others = features.families[0], features.families[1:]
    spring_dampers = counted and power[0] == POWER_DAMPERS
    _, prepare, forward = spring_sweep_funcs(scalar, springs_spec, spring_dampers)
    # The other forces as the fused step's ``particle_force`` has them, without the springs and the clamp (which
    # takes the whole force: below).
    rest = features._replace(families=others, clamp_particle_force=False)
    particle_force = particle_power_func(scalar, rest, power[1:]) if counted else particle_force_func(scalar, rest)
    sums = power_sums_funcs(scalar, counted and counts_work(features, power))
    Sums = sums.type
    pack = sums.pack
    composed = elements(scalar, features.families)
    Elements = composed.arrays
    NoElements = elements(scalar, ()).arrays
    has_others = bool(others)
    update = symplectic_euler_funcs(scalar)
    _, project_contacts = project_all_func(scalar, contacts)
    has_contacts = bool(contacts)
    grid = bool(springs_spec.grid_slots) and bool(springs_spec.slot_groups)

    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 last=contacts.idle() + composed.last("element_arrays"))
    def symplectic_euler_sweep(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        # Model, the forces:
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        dt: scalar,
        dt_rest: scalar,
        # State out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
        # In/out:
        power_in_out: wp.array[Sums],  # the guard's power sums [J] (read with ``power`` only)
        force_in_out: wp.array[vec3],  # scratch: the forces [N] of the springs to particles already swept
        dampers_in_out: wp.array[vec3],  # scratch: their dampers' part [N] (with the springs' dampers counted)
    ):
        world = wp.tid()
        base = world * particle_count
        k = base  # a while loop, which clang may vectorise (a range loop it never does: performance_cpu.md §0)
        while k < base + particle_count:
            force_in_out[k] = vec3(scalar(0.0))
            if wp.static(spring_dampers):
                dampers_in_out[k] = vec3(scalar(0.0))
            k += 1
        time_out[world] = time_in[world] + (wp.float64(dt) + wp.float64(dt_rest))
        h = dt
        springs = element_arrays.head
        prepared = prepare(world, springs, inputs)
        inv_mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        row = int(0)
        column = int(0)
        for i in range(particle_count):
            p = base + i
            x = particle_q_in[p]
            v = particle_qd_in[p]
            springs_f, springs_d = forward(i, row, column, base, x, v, springs, prepared, particle_q_in,
                                           particle_qd_in, force_in_out, dampers_in_out)
            springs_f += force_in_out[p]
            force_in_out[p] = vec3(scalar(0.0))
            if wp.static(spring_dampers):
                springs_d += dampers_in_out[p]
                dampers_in_out[p] = vec3(scalar(0.0))
            if wp.static(grid):
                column += 1
                if column == prepared.nx:
                    column = 0
                    row += 1
            free = not is_kinematic(particle_flags[p])
            f = vec3(scalar(0.0))
            dampers = vec3(scalar(0.0))
            work = vec3(scalar(0.0))
            if wp.static(counted):
                if wp.static(has_others):
                    f, dampers, work = particle_force(world, i, base, x, v, free, particle_mass, element_arrays.tail,
                                                      inputs, particle_force_ext, particle_q_in, particle_qd_in)
                else:
                    f, dampers, work = particle_force(world, i, base, x, v, free, particle_mass, NoElements(), inputs,
                                                      particle_force_ext, particle_q_in, particle_qd_in)
                dampers += springs_d
            else:
                if wp.static(has_others):
                    f = particle_force(world, i, base, x, v, particle_mass, element_arrays.tail, inputs,
                                       particle_force_ext, particle_q_in, particle_qd_in)
                else:
                    f = particle_force(world, i, base, x, v, particle_mass, NoElements(), inputs, particle_force_ext,
                                       particle_q_in, particle_qd_in)
            f += springs_f
            if not free:  # moves on with its velocity; its elements' dampers: their share of the dampers' power
                particle_q_out[p] = x + h * v
                particle_qd_out[p] = v
                if wp.static(counted):
                    power_in_out[p] += pack(-h * wp.dot(dampers, v), scalar(0.0))
                continue
            if wp.static(features.clamp_particle_force):
                max_force = inputs[world, INPUT_MAX_PARTICLE_FORCE]
                magnitude = wp.length(f)
                if magnitude > max_force:
                    f = f * (max_force / magnitude)
            inv_mass = particle_inv_mass[inv_mass_row, i]
            v_start = v
            x, v = update(x, v, f, inv_mass, h)
            if wp.static(counted):
                mean = (v_start + v) * (scalar(0.5) * h)
                power_in_out[p] += pack(-wp.dot(dampers, mean), wp.dot(work, mean))
            if wp.static(has_contacts):
                x, v = project_contacts(world, p, x, v, particle_radius[i], h, shapes, inputs)
            particle_q_out[p] = x
            particle_qd_out[p] = v

    return symplectic_euler_sweep
