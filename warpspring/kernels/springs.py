"""The spring family: Hooke's springs with axial dampers (optionally biphasic or force-clamped) between
two particles, plugged into every kernel through the hooks of ``families.py``, and the spring passes.

Each spring's force, energy and stiffness follow its law (``SpringLaw``, ``spring_funcs``: ``spring_laws.py``).
Plastic springs keep their rest lengths per world, as state the post-step pass ``spring_plastic_kernel`` moves
(a negative rest length marks a broken spring, which carries no force).

Its incidence entries are (spring, other particle); padding entries point a particle at itself, a
coincident pair whose force, stiffness and strain are exactly zero (or "none"), so the head's unrolled
slot loop needs no branch. Where a group of springs shares one rest length, ke and kd, the head may be laid
out group by group and the gathered force read the group's values once instead of per slot
(``SpringSpec.slot_groups``); where the particles are one grid in grid order, it may also find each slot's
neighbour from the particle's row and column instead of the table (``SpringSpec.grid_slots``). The
stiffness matrix block Kₛ = ∂fᵢ/∂xⱼ is clamped positive semi-definite (the transverse term of a compressed
spring dropped), so K ⪰ 0 as implicit Euler and power iteration need.

Worlds: topology and rest lengths are shared (plastic springs: one rest length per world and spring,
world-major in the same ``rest_length`` field); stiffness and damping have one row for every world or one
row per world, read at row ``min(world, rows - 1)``.
"""

import functools
from dataclasses import dataclass
from typing import Any, NamedTuple

import warp as wp

from .families import FORCE_KERNEL_OPTIONS, FamilyFuncs, Incidence, IncidenceShape
from .kinematics import is_kinematic
from .precision import mat33_type, vec3_type
from .flatten import flat_kernel
from .spring_laws import (
    BROKEN_REST_LENGTH,
    COINCIDENT_DISTANCE,
    HOOKE,
    SpringLaw,
    spring_branch_funcs,
    spring_funcs,
    spring_law_type,
)

wp.set_module_options({"enable_backward": False})


def spring_arrays_type(scalar: type, per_spring_law: bool = False, grouped: bool = False, grid: bool = False):
    """The struct of the spring family's arrays in one precision; ``per_spring_law`` adds the per-spring law
    arrays (``SpringLaw.per_spring``), ``grouped`` the springs the gather reads each uniform group's values
    at (``SpringSpec.slot_groups``), ``grid`` (with ``grouped``) the grid's size the gather finds neighbours
    from (``SpringSpec.grid_slots``), so scenes of linear springs read per spring keep the struct, and every
    kernel's parameters, as they were. One struct type per combination, however the call spells it."""
    return _spring_arrays_type(scalar, bool(per_spring_law), bool(grouped), bool(grid) and bool(grouped))


@functools.cache
def _spring_arrays_type(scalar: type, per_spring_law: bool, grouped: bool, grid: bool):

    if grid:

        @wp.struct
        class SpringGridArrays:
            indices: wp.array[wp.vec2i]  # [spring_count]: the two particles of each spring (per-world indices)
            rest_length: wp.array[scalar]  # [m], [spring_count]
            stiffness: wp.array2d[scalar]  # ke [N/m], [1 or world_count, spring_count]
            damping: wp.array2d[scalar]  # kd [N·s/m], [1 or world_count, spring_count]
            incidence: Incidence  # entries (spring, other particle), group-major slots; padding (0, the particle)
            group_spring: wp.array[wp.int32]  # [group_count]: one spring of each group (a uniform group's values)
            grid_size: wp.array[wp.int32]  # [2]: (nx, ny), the grid's particles per row and rows (i = row·nx + col)

        return SpringGridArrays

    if grouped:

        @wp.struct
        class SpringGroupArrays:
            indices: wp.array[wp.vec2i]  # [spring_count]: the two particles of each spring (per-world indices)
            rest_length: wp.array[scalar]  # [m], [spring_count]
            stiffness: wp.array2d[scalar]  # ke [N/m], [1 or world_count, spring_count]
            damping: wp.array2d[scalar]  # kd [N·s/m], [1 or world_count, spring_count]
            incidence: Incidence  # entries (spring, other particle), group-major slots; padding (0, the particle)
            group_spring: wp.array[wp.int32]  # [group_count]: one spring of each group (a uniform group's values)

        return SpringGroupArrays

    if not per_spring_law:

        @wp.struct
        class SpringArrays:
            indices: wp.array[wp.vec2i]  # [spring_count]: the two particles of each spring (per-world indices)
            rest_length: wp.array[scalar]  # [m], [spring_count] (plastic law: [world_count · spring_count])
            stiffness: wp.array2d[scalar]  # ke [N/m], [1 or world_count, spring_count]
            damping: wp.array2d[scalar]  # kd [N·s/m], [1 or world_count, spring_count]
            incidence: Incidence  # entries (spring, other particle); padding (0, the particle itself)

        return SpringArrays

    @wp.struct
    class SpringLawArrays:
        indices: wp.array[wp.vec2i]  # [spring_count]: the two particles of each spring (per-world indices)
        rest_length: wp.array[scalar]  # [m], [spring_count] (plastic law: [world_count · spring_count])
        stiffness: wp.array2d[scalar]  # ke [N/m] (square springs: [N/m²]), [1 or world_count, spring_count]
        damping: wp.array2d[scalar]  # kd [N·s/m], [1 or world_count, spring_count]
        incidence: Incidence  # entries (spring, other particle); padding (0, the particle itself)
        law: wp.array[wp.int32]  # SPRING_LINEAR or SPRING_SQUARE, [spring_count]
        compression_ratio: wp.array[scalar]  # compression stiffness / ke [-], [spring_count]

    return SpringLawArrays


def spring_access_funcs(scalar: type, law: SpringLaw, grouped: bool = False, grid: bool = False):
    """(rest_at, law_at): a spring's current rest length in a world, and the law's values completed with a
    spring's own (its law code and compression ratio), for the struct of ``spring_arrays_type`` of ``law``
    (and ``grouped``, ``grid``)."""
    return _spring_access_funcs(scalar, law, bool(grouped), bool(grid) and bool(grouped))


@functools.cache
def _spring_access_funcs(scalar: type, law: SpringLaw, grouped: bool, grid: bool):
    SpringArrays = spring_arrays_type(scalar, law.per_spring, grouped, grid)
    SpringLawValues = spring_law_type(scalar)

    @wp.func
    def rest_at(springs: SpringArrays, world: int, s: int) -> scalar:
        """Rest length [m] of spring s in ``world`` (the plastic law keeps one per world, world-major)."""
        if wp.static(law.plastic):
            return springs.rest_length[world * springs.stiffness.shape[1] + s]
        return springs.rest_length[s]

    @wp.func
    def law_at(values: SpringLawValues, springs: SpringArrays, s: int) -> SpringLawValues:
        """``values`` with spring s's own law code and compression ratio filled in."""
        if wp.static(law.per_spring):
            own = SpringLawValues()
            own.knee_strain = values.knee_strain
            own.extra_stiffness = values.extra_stiffness
            own.max_force = values.max_force
            own.square = springs.law[s]
            own.compression_ratio = springs.compression_ratio[s]
            return own
        return values

    return rest_at, law_at


@wp.func
def grid_neighbour(i: int, row: int, column: int, nx: int, ny: int, dx: int, dy: int) -> int:
    """The particle (dx, dy) columns and rows from particle i = row·nx + column of an nx × ny grid in grid
    order: i + dy·nx + dx, or i itself (a padding entry: zero force) where that is off the grid."""
    c = column + dx
    r = row + dy
    inside = c >= 0 and c < nx and r >= 0 and r < ny
    return wp.where(inside, i + dy * nx + dx, i)


@dataclass(frozen=True)
class SpringSpec:
    """Compile-time switches of the spring family.

    Attributes:
        incidence: shape of the springs' incidence table.
        law: the force law's optional parts.
        gathered: the force hook sums the springs at each particle; False when they are scattered per
            spring instead (``spring_scatter_kernel``, the CPU default), so the hook adds nothing.
        slot_groups: with the head laid out group by group (slot k holds springs of one group only, or
            padding), the group of each slot whose group is uniform (every spring of it has one rest length,
            ke and kd per stiffness and damping row), -1 for a slot of a group read per spring: the gathered
            force reads each uniform group's values once, at ``group_spring[g]``, and in its slots never the
            spring index. ``()``: values per spring everywhere. Only a gathered spec without tail, per-spring
            law arrays or plasticity has groups.
        grid_slots: with ``slot_groups``, where the particles are one grid in grid order (i = row·nx + col,
            nx and ny read from ``grid_size``), the direction (dx, dy) in columns and rows of each head slot's
            neighbour: in a uniform group's slot the gathered force takes j = i + dy·nx + dx, or i itself
            (padding) where that is off the grid, and loads nothing of the incidence table; slots of -1 still
            read it. A particle's springs of a group lie in its slots in these directions' order, those off the
            grid left out (``core/springs.grid_slots`` checks it), so both layouts sum the same terms in the same
            order. ``()``: the table everywhere.
    """

    incidence: IncidenceShape
    law: SpringLaw = HOOKE
    gathered: bool = True
    slot_groups: tuple = ()
    grid_slots: tuple = ()

    def funcs(self, scalar: type) -> FamilyFuncs:
        return spring_family_funcs(scalar, self)


@functools.cache
def spring_family_funcs(scalar: type, spec: SpringSpec) -> FamilyFuncs:
    """The family hooks of springs (``families.py``) for one precision and spec."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    head_slots, tail = spec.incidence
    grouped = bool(spec.slot_groups) and spec.gathered
    if grouped and (tail or spec.law.per_spring or spec.law.plastic or len(spec.slot_groups) != head_slots):
        raise ValueError(f"slot groups need one group per head slot, no tail, no per-spring law arrays and no "
                         f"plasticity; got {spec}")
    grid = grouped and bool(spec.grid_slots)
    if grid and len(spec.grid_slots) != head_slots:
        raise ValueError(f"grid slots need one direction per head slot; got {spec}")
    SpringArrays = spring_arrays_type(scalar, spec.law.per_spring, grouped, grid)
    spring_law_values, spring_force, spring_energy, spring_stiffness_matrix = spring_funcs(scalar, spec.law)
    rest_at, law_at = spring_access_funcs(scalar, spec.law, grouped, grid)
    _, prepare = spring_world_funcs(scalar, spec)  # (the per-world reads of force_split and particle_energy)
    SpringLawValues = spring_law_type(scalar)
    # The group of each slot, a constant of the kernel (the unrolled slot loop indexes it at fixed k).
    slot_group = wp.constant(wp.types.vector(length=max(head_slots, 1), dtype=wp.int32)(
        *(spec.slot_groups if grouped else (0,) * max(head_slots, 1))))
    # The grid's direction of each slot, constants likewise (zeros without a grid: never read).
    directions = spec.grid_slots if grid else ((0, 0),) * max(head_slots, 1)
    slot_dx = wp.constant(wp.types.vector(length=max(head_slots, 1), dtype=wp.int32)(*(d[0] for d in directions)))
    slot_dy = wp.constant(wp.types.vector(length=max(head_slots, 1), dtype=wp.int32)(*(d[1] for d in directions)))
    # Whether each slot's direction points to a later particle (i + dy·nx + dx > i): the slot ``particle_energy`` walks.
    slot_forward = wp.constant(wp.types.vector(length=max(head_slots, 1), dtype=wp.int32)(
        *(int(d[1] > 0 or (d[1] == 0 and d[0] > 0)) for d in directions)))

    @wp.func
    def spring_block(
        xi: vec3, xj: vec3, rest: scalar, ke: scalar, kd: scalar, alpha: scalar, beta: scalar,
        values: SpringLawValues,
    ) -> mat33:
        """α Kₛ + β kd d̂d̂ᵀ [N/m · α]: the coupling block of the spring (i, j) in α K + β D."""
        d = xj - xi
        length = wp.length(d)
        n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        return (beta * kd) * wp.outer(n, n) + alpha * spring_stiffness_matrix(xi, xj, rest, ke, True, values)

    # The dampers' part of a spring's force is separable for the laws whose dissipation the guard counts.
    splittable = not (spec.law.clamp_force or spec.law.plastic)

    @wp.func
    def damper_force(xi: vec3, xj: vec3, vi: vec3, vj: vec3, kd: scalar) -> vec3:
        """The damper's part [N] of the spring (i, j)'s force on i, kd ((vj - vi)·d̂) d̂ (0 where the law's force is
        not separable: ``splittable``); the same terms as ``spring_force``, which the compiler shares."""
        if wp.static(not splittable):
            return vec3(scalar(0.0))
        d = xj - xi
        length = wp.length(d)
        n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        return n * (kd * wp.dot(vj - vi, n))

    @wp.func
    def force_split(
        world: int, i: int, base: int, xi: vec3, vi: vec3, springs: SpringArrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ):
        """(sum of the forces [N] of the springs at particle i of ``world``, their dampers' part [N])."""
        f = vec3(scalar(0.0))
        damping_part = vec3(scalar(0.0))
        # The world's values (``prepare``): with uniform groups each group's rest length, ke and kd once, then per
        # slot only its other particle (the slots of a group read per spring also load their spring and its values).
        shared = prepare(world, springs, inputs)
        values = shared.values
        stiffness_row = shared.stiffness_row
        damping_row = shared.damping_row
        if wp.static(grouped):
            rest = shared.rest
            ke = shared.ke
            kd = shared.kd
            head_local = springs.incidence.head_local
            head_element = springs.incidence.head_element
            # The grid: i's row and column once; nx and ny are data, so every size shares the kernel.
            nx = shared.nx
            ny = shared.ny
            row = int(0)
            column = int(0)
            if wp.static(grid):
                row = i // nx
                column = i - row * nx
            for k in range(wp.static(head_slots)):
                g = slot_group[k]  # a constant once the loop is unrolled: the branch compiles away
                if g >= 0:
                    if wp.static(grid):
                        j = base + grid_neighbour(i, row, column, nx, ny, slot_dx[k], slot_dy[k])
                    else:
                        j = base + head_local[k, i]
                    f += spring_force(xi, particle_q[j], vi, particle_qd[j], rest[g], ke[g], kd[g], values)
                    damping_part += damper_force(xi, particle_q[j], vi, particle_qd[j], kd[g])
                else:
                    j = base + head_local[k, i]
                    s = head_element[k, i]
                    f += spring_force(xi, particle_q[j], vi, particle_qd[j], springs.rest_length[s],
                                      springs.stiffness[stiffness_row, s], springs.damping[damping_row, s], values)
                    damping_part += damper_force(xi, particle_q[j], vi, particle_qd[j], springs.damping[damping_row, s])
        elif wp.static(spec.gathered):
            # The arrays in locals once: the slot loop then indexes them without reloading the struct.
            rest_length = springs.rest_length
            stiffness = springs.stiffness
            damping = springs.damping
            head_local = springs.incidence.head_local
            head_element = springs.incidence.head_element
            rest_base = shared.rest_base  # (plastic rest lengths are world-major: world w's start)
            for k in range(wp.static(head_slots)):
                j = base + head_local[k, i]
                s = head_element[k, i]
                f += spring_force(xi, particle_q[j], vi, particle_qd[j], rest_length[rest_base + s],
                                  stiffness[stiffness_row, s], damping[damping_row, s], law_at(values, springs, s))
                damping_part += damper_force(xi, particle_q[j], vi, particle_qd[j], damping[damping_row, s])
            if wp.static(tail):
                tail_start = springs.incidence.tail_start
                tail_local = springs.incidence.tail_local
                tail_element = springs.incidence.tail_element
                for t in range(tail_start[i], tail_start[i + 1]):
                    j = base + tail_local[t]
                    s = tail_element[t]
                    f += spring_force(xi, particle_q[j], vi, particle_qd[j], rest_length[rest_base + s],
                                      stiffness[stiffness_row, s], damping[damping_row, s], law_at(values, springs, s))
                    damping_part += damper_force(xi, particle_q[j], vi, particle_qd[j], damping[damping_row, s])
        return f, damping_part

    @wp.func
    def force(
        world: int, i: int, base: int, xi: vec3, vi: vec3, springs: SpringArrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ) -> vec3:
        """Sum of the forces [N] of the springs at particle i of ``world`` (``force_split``'s first part)."""
        f, _ = force_split(world, i, base, xi, vi, springs, inputs, particle_q, particle_qd)
        return f

    @wp.func
    def product_entry(
        world: int, i: int, base: int, xi: vec3, xi_operand: vec3, j_local: int, s: int, springs: SpringArrays,
        stiffness_row: int, damping_row: int, values: SpringLawValues, particle_q: wp.array[vec3],
        particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool, alpha: scalar, beta: scalar,
    ):
        j = base + j_local
        block = spring_block(xi, particle_q[j], rest_at(springs, world, s), springs.stiffness[stiffness_row, s],
                             springs.damping[damping_row, s], alpha, beta, law_at(values, springs, s))
        xj = x[j]
        if free_only:
            xj = wp.where(is_kinematic(particle_flags[j]), vec3(scalar(0.0)), xj)
        return block * (xi_operand - xj), block

    @wp.func
    def product(
        world: int, i: int, base: int, xi: vec3, springs: SpringArrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
        alpha: scalar, beta: scalar,
    ):
        """Row i of (α K + β D) x over the springs at particle i, and its diagonal block."""
        values = spring_law_values(inputs, world)
        stiffness_row = wp.min(world, springs.stiffness.shape[0] - 1)
        damping_row = wp.min(world, springs.damping.shape[0] - 1)
        incidence = springs.incidence
        xi_operand = x[base + i]
        y = vec3(scalar(0.0))
        diagonal = mat33(scalar(0.0))
        for k in range(wp.static(head_slots)):
            yk, block = product_entry(world, i, base, xi, xi_operand, incidence.head_local[k, i],
                                      incidence.head_element[k, i], springs, stiffness_row, damping_row, values,
                                      particle_q, particle_flags, x, free_only, alpha, beta)
            y += yk
            diagonal += block
        if wp.static(tail):
            for t in range(incidence.tail_start[i], incidence.tail_start[i + 1]):
                yk, block = product_entry(world, i, base, xi, xi_operand, incidence.tail_local[t],
                                          incidence.tail_element[t], springs, stiffness_row, damping_row, values,
                                          particle_q, particle_flags, x, free_only, alpha, beta)
                y += yk
                diagonal += block
        return y, diagonal

    @wp.func
    def spring_strain(i: int, j: int, xi: vec3, xj: vec3, rest: scalar) -> wp.float64:
        """|d|/L - 1 of the spring (i, j); -1 for a padding entry (j = i) or a zero rest length."""
        if j == i or rest <= scalar(0.0):
            return wp.float64(-1.0)
        return wp.float64(wp.length(xj - xi) / rest) - wp.float64(1.0)

    @wp.func
    def strain(world: int, i: int, base: int, xi: vec3, springs: SpringArrays, particle_q: wp.array[vec3]):
        """The largest strain |d|/L - 1 of the springs at particle i and the smallest spring holding it."""
        incidence = springs.incidence
        worst = wp.float64(-1.0)
        element = int(-1)
        for k in range(wp.static(head_slots)):
            j = incidence.head_local[k, i]
            s = incidence.head_element[k, i]
            e = spring_strain(i, j, xi, particle_q[base + j], rest_at(springs, world, s))
            if e > worst or (e == worst and e >= wp.float64(0.0) and s < element):
                worst = e
                element = s
        if wp.static(tail):
            for t in range(incidence.tail_start[i], incidence.tail_start[i + 1]):
                j = incidence.tail_local[t]
                s = incidence.tail_element[t]
                e = spring_strain(i, j, xi, particle_q[base + j], rest_at(springs, world, s))
                if e > worst or (e == worst and e >= wp.float64(0.0) and s < element):
                    worst = e
                    element = s
        return worst, wp.where(worst > wp.float64(-1.0), element, -1)

    @wp.func
    def element_strain(world: int, s: int, base: int, springs: SpringArrays, particle_q: wp.array[vec3]) -> wp.float64:
        """|d|/L - 1 of spring s in ``world`` (``spring_strain`` from its first end: the bits ``strain`` gives at
        either)."""
        ends = springs.indices[s]
        return spring_strain(ends[0], ends[1], particle_q[base + ends[0]], particle_q[base + ends[1]],
                             rest_at(springs, world, s))

    @wp.func
    def energy(world: int, s: int, base: int, springs: SpringArrays, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3]) -> scalar:
        """Elastic energy [J] of spring s in ``world``."""
        ends = springs.indices[s]
        return spring_energy(particle_q[base + ends[0]], particle_q[base + ends[1]], rest_at(springs, world, s),
                             springs.stiffness[wp.min(world, springs.stiffness.shape[0] - 1), s],
                             law_at(spring_law_values(inputs, world), springs, s))

    @wp.func
    def dissipation(world: int, s: int, base: int, springs: SpringArrays, inputs: wp.array2d[scalar],
                    particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> scalar:
        """Power [W] the damper of spring s takes out in ``world``: kd ((vj - vi)·d̂)² ≥ 0. Zero under the
        force clamp (the damper's share of a clamped force is not separable: not counted, so the guard's
        balance stays one-sided) and for a broken plastic spring."""
        if wp.static(spec.law.clamp_force):
            return scalar(0.0)
        if wp.static(spec.law.plastic):
            if rest_at(springs, world, s) < scalar(0.0):
                return scalar(0.0)
        ends = springs.indices[s]
        d = particle_q[base + ends[1]] - particle_q[base + ends[0]]
        length = wp.length(d)
        n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        rate = wp.dot(particle_qd[base + ends[1]] - particle_qd[base + ends[0]], n)
        return springs.damping[wp.min(world, springs.damping.shape[0] - 1), s] * rate * rate

    @wp.func
    def pair_terms(i: int, j: int, xi: vec3, xj: vec3, vi: vec3, vj: vec3, rest: scalar, ke: scalar, kd: scalar,
                   values: SpringLawValues):
        """The spring (i, j)'s elastic energy [J] (``energy``'s terms), strain [-] (``spring_strain``'s bits) and its
        damper's power [W] (``dissipation``'s terms), in float64."""
        power = wp.float64(0.0)
        if wp.static(not spec.law.clamp_force):
            d = xj - xi
            length = wp.length(d)
            n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
            rate = wp.dot(vj - vi, n)
            power = wp.float64(kd * rate * rate)
            if wp.static(spec.law.plastic):
                power = wp.where(rest >= scalar(0.0), power, wp.float64(0.0))
        return wp.float64(spring_energy(xi, xj, rest, ke, values)), spring_strain(i, j, xi, xj, rest), power

    @wp.func
    def particle_energy(
        world: int, i: int, base: int, xi: vec3, vi: vec3, springs: SpringArrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ):
        """(the elastic energy [J] of the springs from particle i to particles after it, their largest strain [-] (-1:
        none), the power their dampers take out [W]) in float64, from the gathered incidence like ``force_split``:
        each spring at the lower of its two ends (on a grid the slots whose direction points forward, known when the
        kernel compiles; a padding entry, the particle itself, is never after it), so the particles' values sum to
        ``energy`` and ``dissipation`` over the springs (in another order) and their largest strain is
        ``element_strain``'s."""
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        taken = wp.float64(0.0)
        shared = prepare(world, springs, inputs)  # (the world's values, read as the CPU's sweep reads them)
        values = shared.values
        stiffness_row = shared.stiffness_row
        damping_row = shared.damping_row
        if wp.static(grouped):
            rest = shared.rest
            ke = shared.ke
            kd = shared.kd
            head_local = springs.incidence.head_local
            head_element = springs.incidence.head_element
            nx = shared.nx
            ny = shared.ny
            row = int(0)
            column = int(0)
            if wp.static(grid):
                row = i // nx
                column = i - row * nx
            for k in range(wp.static(head_slots)):
                g = slot_group[k]  # constants once the loop is unrolled: the branches compile away
                local = int(-1)  # (a backward grid slot: none)
                if g < 0 or not wp.static(grid):
                    local = head_local[k, i]
                elif slot_forward[k] != 0:
                    local = grid_neighbour(i, row, column, nx, ny, slot_dx[k], slot_dy[k])
                if local > i:
                    if g >= 0:
                        e, strained, power = pair_terms(i, local, xi, particle_q[base + local], vi,
                                                        particle_qd[base + local], rest[g], ke[g], kd[g], values)
                    else:
                        s = head_element[k, i]
                        e, strained, power = pair_terms(i, local, xi, particle_q[base + local], vi,
                                                        particle_qd[base + local], springs.rest_length[s],
                                                        springs.stiffness[stiffness_row, s],
                                                        springs.damping[damping_row, s], values)
                    energy += e
                    worst = wp.max(worst, strained)
                    taken += power
        elif wp.static(spec.gathered):
            rest_length = springs.rest_length
            stiffness = springs.stiffness
            damping = springs.damping
            head_local = springs.incidence.head_local
            head_element = springs.incidence.head_element
            rest_base = shared.rest_base
            for k in range(wp.static(head_slots)):
                local = head_local[k, i]
                if local > i:
                    s = head_element[k, i]
                    e, strained, power = pair_terms(i, local, xi, particle_q[base + local], vi,
                                                    particle_qd[base + local], rest_length[rest_base + s],
                                                    stiffness[stiffness_row, s], damping[damping_row, s],
                                                    law_at(values, springs, s))
                    energy += e
                    worst = wp.max(worst, strained)
                    taken += power
            if wp.static(tail):
                tail_start = springs.incidence.tail_start
                tail_local = springs.incidence.tail_local
                tail_element = springs.incidence.tail_element
                for t in range(tail_start[i], tail_start[i + 1]):
                    local = tail_local[t]
                    if local > i:
                        s = tail_element[t]
                        e, strained, power = pair_terms(i, local, xi, particle_q[base + local], vi,
                                                        particle_qd[base + local], rest_length[rest_base + s],
                                                        stiffness[stiffness_row, s], damping[damping_row, s],
                                                        law_at(values, springs, s))
                        energy += e
                        worst = wp.max(worst, strained)
                        taken += power
        return energy, worst, taken

    # The gathered hooks find a spring's other end in the incidence entry, never in ``indices``.
    return FamilyFuncs(SpringArrays, force, product, strain, energy, ("indices", *spec.incidence.idle()),
                       dissipation=dissipation, split=force_split if splittable else None,
                       element_strain=element_strain, particle_energy=particle_energy if spec.gathered else None)


class SweepFuncs(NamedTuple):
    """``spring_sweep_funcs``'s hooks: ``prepare(world, springs, inputs) -> SpringWorld``, a world's values read once;
    ``forward(i, row, column, base, xi, vi, springs, world_values, particle_q, particle_qd, force_in_out,
    dampers_in_out) -> (force, dampers)``: particle i's springs to the particles after it, each evaluated once."""

    world_type: type
    prepare: Any
    forward: Any


@functools.cache
def spring_world_funcs(scalar: type, spec: SpringSpec) -> tuple[type, Any]:
    """``(SpringWorld, prepare)``: the struct of what the gathered springs of ``spec`` read per world and is the same
    for all of a world's particles (the law's values, the stiffness and damping rows, the first plastic rest length,
    the uniform groups' rest length, ke and kd, the grid's size), and ``prepare(world, springs, inputs)``, which
    reads it: once per world in the CPU's sweep (``spring_sweep_funcs``), once per particle in the gathered force
    (``force_split``) and in the walk of the springs' energy (``particle_energy``)."""
    grouped = bool(spec.slot_groups) and spec.gathered
    grid = grouped and bool(spec.grid_slots)
    SpringArrays = spring_arrays_type(scalar, spec.law.per_spring, grouped, grid)
    spring_law_values = spring_funcs(scalar, spec.law)[0]
    SpringLawValues = spring_law_type(scalar)
    group_count = max(spec.slot_groups, default=-1) + 1
    group_values = wp.types.vector(length=max(group_count, 1), dtype=scalar)

    @wp.struct
    class SpringWorld:
        values: SpringLawValues  # the law's values of the world
        stiffness_row: int  # the world's rows of stiffness and damping
        damping_row: int
        rest_base: int  # the world's first plastic rest length (0 otherwise)
        rest: group_values  # each uniform group's rest length [m], ke [N/m] and kd [N·s/m]
        ke: group_values
        kd: group_values
        nx: int  # the grid's particles per row and rows (grid layout only)
        ny: int

    @wp.func
    def prepare(world: int, springs: SpringArrays, inputs: wp.array2d[scalar]) -> SpringWorld:
        prepared = SpringWorld()
        prepared.values = spring_law_values(inputs, world)
        prepared.stiffness_row = wp.min(world, springs.stiffness.shape[0] - 1)
        prepared.damping_row = wp.min(world, springs.damping.shape[0] - 1)
        prepared.rest_base = int(0)
        if wp.static(spec.law.plastic):
            prepared.rest_base = world * springs.stiffness.shape[1]
        rest = group_values()
        ke = group_values()
        kd = group_values()
        if wp.static(grouped):
            for g in range(wp.static(group_count)):
                s = springs.group_spring[g]
                rest[g] = springs.rest_length[s]
                ke[g] = springs.stiffness[prepared.stiffness_row, s]
                kd[g] = springs.damping[prepared.damping_row, s]
        prepared.rest = rest
        prepared.ke = ke
        prepared.kd = kd
        prepared.nx = int(0)
        prepared.ny = int(0)
        if wp.static(grid):
            prepared.nx = springs.grid_size[0]
            prepared.ny = springs.grid_size[1]
        return prepared

    return SpringWorld, prepare


@functools.cache
def spring_sweep_funcs(scalar: type, spec: SpringSpec, dampers: bool = False) -> SweepFuncs:
    """The gathered springs of ``spec`` (its incidence table and layout) evaluated once each, for a sweep over one
    world's particles in order (``kernels/sweep.py``, the CPU's symplectic Euler step).

    ``forward`` evaluates, of the springs at particle i, those whose other particle j comes after i (j > i): it
    returns their force on i and adds the opposite force to j's entry of ``force_in_out`` (a scratch array that
    holds, when the sweep reaches a particle, the forces of its springs to the particles before it). A spring (i, j)
    is thus evaluated once, by its first particle, where the gather evaluates it at both (the gather's per-spring
    forces, summed in another order). With ``dampers`` the dampers' part of those forces likewise (its
    return's second value, ``dampers_in_out``; zero where the law's is not separable, as ``force_split``).

    What ``force_split`` reads per particle and is the same for all of a world's particles (the law's values, the
    stiffness and damping rows, the uniform groups' rest length, ke and kd, the grid's size) ``prepare`` reads once
    per world."""
    vec3 = vec3_type(scalar)
    head_slots, tail = spec.incidence
    grouped = bool(spec.slot_groups) and spec.gathered
    grid = grouped and bool(spec.grid_slots)
    SpringArrays = spring_arrays_type(scalar, spec.law.per_spring, grouped, grid)
    spring_force = spring_funcs(scalar, spec.law)[1]
    _, law_at = spring_access_funcs(scalar, spec.law, grouped, grid)
    SpringLawValues = spring_law_type(scalar)
    width = max(head_slots, 1)
    slot_group = wp.constant(wp.types.vector(length=width, dtype=wp.int32)(
        *(spec.slot_groups if grouped else (0,) * width)))
    directions = spec.grid_slots if grid else ((0, 0),) * width
    slot_dx = wp.constant(wp.types.vector(length=width, dtype=wp.int32)(*(d[0] for d in directions)))
    slot_dy = wp.constant(wp.types.vector(length=width, dtype=wp.int32)(*(d[1] for d in directions)))
    # A grid slot's neighbour comes after the particle where it is on a later row, or later on the same one.
    slot_ahead = wp.constant(wp.types.vector(length=width, dtype=wp.int32)(
        *(int(dy > 0 or (dy == 0 and dx > 0)) for dx, dy in directions)))
    splittable = not (spec.law.clamp_force or spec.law.plastic)
    counted = dampers and splittable

    SpringWorld, prepare = spring_world_funcs(scalar, spec)

    @wp.func
    def spring_pair(xi: vec3, xj: vec3, vi: vec3, vj: vec3, rest: scalar, ke: scalar, kd: scalar,
                    values: SpringLawValues):
        """(force [N] of the spring (i, j) on i, its damper's part [N]: zero unless ``counted``)."""
        f = spring_force(xi, xj, vi, vj, rest, ke, kd, values)
        damping = vec3(scalar(0.0))
        if wp.static(counted):
            d = xj - xi
            length = wp.length(d)
            n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
            damping = n * (kd * wp.dot(vj - vi, n))
        return f, damping

    @wp.func
    def forward(
        i: int, row: int, column: int, base: int, xi: vec3, vi: vec3, springs: SpringArrays, prepared: SpringWorld,
        particle_q: wp.array[vec3], particle_qd: wp.array[vec3], force_in_out: wp.array[vec3],
        dampers_in_out: wp.array[vec3],
    ):
        f = vec3(scalar(0.0))
        damping = vec3(scalar(0.0))
        values = prepared.values
        head_local = springs.incidence.head_local
        head_element = springs.incidence.head_element
        for k in range(wp.static(head_slots)):
            g = slot_group[k]  # constants once the loop is unrolled: the branches compile away
            if wp.static(grouped) and g >= 0:
                j_local = i
                if wp.static(grid):
                    # A slot ahead (dy > 0, or dy = 0 and dx > 0): its neighbour, where on the grid (row + dy ≥ 0).
                    if slot_ahead[k] != 0:
                        c = column + slot_dx[k]
                        if c >= 0 and c < prepared.nx and row + slot_dy[k] < prepared.ny:
                            j_local = i + slot_dy[k] * prepared.nx + slot_dx[k]
                else:
                    j_local = head_local[k, i]
                if j_local > i:
                    j = base + j_local
                    fk, dk = spring_pair(xi, particle_q[j], vi, particle_qd[j], prepared.rest[g], prepared.ke[g],
                                         prepared.kd[g], values)
                    f += fk
                    force_in_out[j] = force_in_out[j] - fk
                    if wp.static(counted):
                        damping += dk
                        dampers_in_out[j] = dampers_in_out[j] - dk
            else:
                j_local = head_local[k, i]
                if j_local > i:
                    j = base + j_local
                    s = head_element[k, i]
                    fk, dk = spring_pair(xi, particle_q[j], vi, particle_qd[j],
                                         springs.rest_length[prepared.rest_base + s],
                                         springs.stiffness[prepared.stiffness_row, s],
                                         springs.damping[prepared.damping_row, s], law_at(values, springs, s))
                    f += fk
                    force_in_out[j] = force_in_out[j] - fk
                    if wp.static(counted):
                        damping += dk
                        dampers_in_out[j] = dampers_in_out[j] - dk
        if wp.static(tail):
            for t in range(springs.incidence.tail_start[i], springs.incidence.tail_start[i + 1]):
                j_local = springs.incidence.tail_local[t]
                if j_local > i:
                    j = base + j_local
                    s = springs.incidence.tail_element[t]
                    fk, dk = spring_pair(xi, particle_q[j], vi, particle_qd[j],
                                         springs.rest_length[prepared.rest_base + s],
                                         springs.stiffness[prepared.stiffness_row, s],
                                         springs.damping[prepared.damping_row, s], law_at(values, springs, s))
                    f += fk
                    force_in_out[j] = force_in_out[j] - fk
                    if wp.static(counted):
                        damping += dk
                        dampers_in_out[j] = dampers_in_out[j] - dk
        return f, damping

    return SweepFuncs(SpringWorld, prepare, forward)


#: ``spring_scatter_kernel``'s ``dissipation`` rules (``DAMPER_*``): none, the trapezoid of the dampers' power, or
#: the power at the mean of the damper rates of a step's two ends (symplectic Euler's; ``guards.py``).
DAMPER_NONE, DAMPER_TRAPEZOID, DAMPER_MEAN_RATE = 0, 1, 2


@functools.cache
def damper_step_func(scalar: type, rule: int):
    """``(running, value) = damper_step(kd, rate, previous, skip, h)``: spring s's damper over the step that ended at
    the state where its rate (vj - vi)·d̂ [m/s] is ``rate``, and the value to keep for the next step; ``previous``
    is the value kept at the step's start (its rate, or with ``DAMPER_TRAPEZOID`` its power [W]), ``skip`` non-zero
    where that step was counted already (``guards.py``: the check counts the last step of its span)."""

    @wp.func
    def damper_step(kd: scalar, rate: scalar, previous: scalar, skip: wp.int32, h: wp.float64):
        value = rate
        energy = wp.float64(0.0)
        if wp.static(rule == DAMPER_TRAPEZOID):
            value = kd * rate * rate
            if skip == 0:
                energy = wp.float64(0.5) * h * wp.float64(previous + value)
        else:
            mean = scalar(0.5) * (previous + rate)
            if skip == 0:
                energy = h * wp.float64(kd * mean * mean)
        return energy, value

    return damper_step


@functools.cache
def spring_scatter_kernel(scalar: type, law: SpringLaw, dissipation: int = DAMPER_NONE):
    """Kernel adding every spring's force to its two particles (one thread per spring of every world).

    Each spring is evaluated once, but its two ends are written with atomic adds: on the CPU, where Warp
    runs a kernel's threads in order, the sums are deterministic; it is the CPU's default (``finalize``).

    With ``dissipation`` (a ``DAMPER_*`` rule; Hooke's law, its biphasic and asymmetric kinds: no force clamp, no
    plasticity), the evaluation at a step's start also adds to spring s's running sum ``dissipated_in_out[world,
    s]`` the energy [J] its damper took out over the step before, from the value kept in ``damper_in_out``
    (``damper_step_func``): the guard's dissipation counted in the pass that already reads the springs, no pass of
    its own per substep (``guards.py``). Each thread writes its own spring's entries: no atomics.
    """
    vec3 = vec3_type(scalar)
    SpringArrays = spring_arrays_type(scalar, law.per_spring)
    spring_law_values, spring_force, _, _ = spring_funcs(scalar, law)
    rest_at, law_at = spring_access_funcs(scalar, law)
    counted = dissipation != DAMPER_NONE
    if counted and (law.clamp_force or law.plastic):
        raise ValueError(f"the dampers' dissipation is not separable under {law}")
    damper_step = damper_step_func(scalar, dissipation if counted else DAMPER_TRAPEZOID)

    # The scatter walks the springs, never the incidence table.
    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 last=("springs__incidence",))
    def scatter_springs(
        # Model:
        particle_count: int,
        springs: SpringArrays,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Guard in:
        h: wp.float64,  # the step [s] (read with ``dissipation`` only)
        damper_skip: wp.array[wp.int32],  # per world: non-zero where the step before was counted already
        # In/out:
        particle_f_in_out: wp.array[vec3],
        damper_in_out: wp.array[scalar],
        dissipated_in_out: wp.array[wp.float64],
    ):
        world, s = wp.tid()
        base = world * particle_count
        ends = springs.indices[s]
        i = base + ends[0]
        j = base + ends[1]
        kd = springs.damping[wp.min(world, springs.damping.shape[0] - 1), s]
        f = spring_force(
            particle_q[i], particle_q[j], particle_qd[i], particle_qd[j], rest_at(springs, world, s),
            springs.stiffness[wp.min(world, springs.stiffness.shape[0] - 1), s],
            kd,
            law_at(spring_law_values(inputs, world), springs, s),
        )
        wp.atomic_add(particle_f_in_out, i, f)
        wp.atomic_sub(particle_f_in_out, j, f)
        if wp.static(counted):
            d = particle_q[j] - particle_q[i]
            length = wp.length(d)
            rate = wp.where(length > scalar(COINCIDENT_DISTANCE), wp.dot(particle_qd[j] - particle_qd[i], d) / length,
                            scalar(0.0))
            k = world * springs.indices.shape[0] + s
            energy, value = damper_step(kd, rate, damper_in_out[k], damper_skip[world], h)
            dissipated_in_out[k] += energy
            damper_in_out[k] = value

    return scatter_springs


@functools.cache
def plastic_arrays_type(scalar: type):
    """The struct of the plastic springs' parameters (values, every world; their state, the rest lengths and
    plastic strains per world, is the pass's in/out arrays)."""

    @wp.struct
    class PlasticArrays:
        index: wp.array[wp.int32]  # [plastic_count]: the springs that may yield or break
        rest_length_0: wp.array[scalar]  # L₀ [m], [spring_count]: rest lengths as built
        yield_strain: wp.array[scalar]  # ε_y [-], [spring_count]: elastic limit as a strain (inf: none)
        yield_force: wp.array[scalar]  # F_y [N], [spring_count]: elastic limit as a tension magnitude (inf: none)
        yield_rate: wp.array[scalar]  # r [1/s], [spring_count]: share of the excess that flows per second (inf: all)
        hardening: wp.array[scalar]  # H [-], [spring_count]: the limit grows by the factor 1 + H α
        break_strain: wp.array[scalar]  # [-], [spring_count]: breaks once |d| > (1 + it) L₀ (inf: never)

    return PlasticArrays


@functools.cache
def spring_plastic_kernel(scalar: type, law: SpringLaw):
    """The post-step pass of plastic springs, one thread per (world, plastic spring), on an accepted state.

    Per spring, with L₀ its built rest length, L its current one and α its accumulated plastic strain, the
    elastic strain is e = (|d| - L)/L₀ and the limit ε_y = ε_y0 (1 + H α), ε_y0 the smaller of the yield
    strain and the stretch at which the base law reaches the yield force on the branch of e's sign
    (``base_stretch_at`` at the current stiffness, divided by L₀). If |e| > ε_y, the rest length moves toward |d| by Δγ L₀ (``plastic_flow``) and α
    grows by Δγ: under a monotone pull held instantly at its limit, α = (ε - ε_y0)/(1 + ε_y0 H) for a
    total strain ε = |d|/L₀ - 1, whatever the steps. A spring longer than (1 + ε_break) L₀ breaks: its rest
    length becomes ``BROKEN_REST_LENGTH`` and it carries nothing from then on. Held worlds are skipped.
    """
    vec3 = vec3_type(scalar)
    SpringArrays = spring_arrays_type(scalar, law.per_spring)
    PlasticArrays = plastic_arrays_type(scalar)
    spring_law_values, _, _, _ = spring_funcs(scalar, law)
    _, law_at = spring_access_funcs(scalar, law)
    branch_stiffness, base_stretch_at = spring_branch_funcs(scalar, law)

    @wp.func
    def plastic_flow(excess: scalar, rate_dt: scalar, limit_0: scalar, hardening: scalar) -> scalar:
        """The plastic strain increment Δγ [-] of one step for an elastic strain ``excess`` f > 0 beyond the
        limit: the return map of linear hardening (Simo & Hughes 1998, box 1.4), Δγ = f / (1 + ε_y0 H), of
        which the share min(1, r h) flows in a step of h (creep; r = inf: all of it)."""
        return wp.min(rate_dt, scalar(1.0)) * excess / (scalar(1.0) + limit_0 * hardening)

    # The rest lengths are read and written through ``rest_length_in_out``, never through the struct.
    @flat_kernel(module="unique", enable_backward=False,
                 last=("springs__incidence", "springs__rest_length", "springs__damping"))
    def plastic_springs(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        springs: SpringArrays,
        plastic: PlasticArrays,
        inputs: wp.array2d[scalar],
        dt: scalar,
        # State in (the accepted step):
        particle_q: wp.array[vec3],
        # In/out (the plastic state):
        rest_length_in_out: wp.array[scalar],
        plastic_strain_in_out: wp.array[scalar],
    ):
        world, k = wp.tid()
        if world_enabled[world] == 0:
            return
        s = plastic.index[k]
        r = world * springs.stiffness.shape[1] + s
        rest = rest_length_in_out[r]
        if rest < scalar(0.0):
            return  # broken already
        ends = springs.indices[s]
        base = world * particle_count
        length = wp.length(particle_q[base + ends[1]] - particle_q[base + ends[0]])
        rest_0 = plastic.rest_length_0[s]
        if length > (scalar(1.0) + plastic.break_strain[s]) * rest_0:
            rest_length_in_out[r] = scalar(BROKEN_REST_LENGTH)
            return
        elastic = (length - rest) / rest_0
        values = law_at(spring_law_values(inputs, world), springs, s)
        ke = springs.stiffness[wp.min(world, springs.stiffness.shape[0] - 1), s]
        # The elastic limit as a strain: the yield strain, or the yield force's stretch on e's branch.
        limit_0 = wp.min(plastic.yield_strain[s],
                         base_stretch_at(plastic.yield_force[s], branch_stiffness(elastic, ke, values), values) / rest_0)
        alpha = plastic_strain_in_out[r]
        hardening = plastic.hardening[s]
        excess = wp.abs(elastic) - limit_0 * (scalar(1.0) + hardening * alpha)
        if excess > scalar(0.0):
            flow = plastic_flow(excess, plastic.yield_rate[s] * dt, limit_0, hardening)
            rest_length_in_out[r] = rest + wp.sign(elastic) * flow * rest_0
            plastic_strain_in_out[r] = alpha + flow

    return plastic_springs

