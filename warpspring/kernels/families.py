"""Element families: how springs, dihedral hinges and any later element type plug into every kernel.

A family is a set of elements of one type (springs: 2 particles, hinges: 4) whose arrays travel together
in one ``wp.struct``. It supplies four ``@wp.func`` hooks, all gathered per particle over the family's
incidence (below), so every result is written once, without float atomics:

* ``force(world, i, base, xi, vi, arrays, inputs, particle_q, particle_qd) -> vec3``: the force [N] of the
  family's elements on particle i of ``world`` (its entries start at ``base`` of the state arrays);
* ``product(world, i, base, xi, arrays, inputs, particle_q, particle_flags, x, free_only, alpha, beta)
  -> (vec3, mat33)``: row i of (α K + β D) x, with K ⪰ 0 the family's stiffness matrix (-∂f/∂x, made
  positive semi-definite where the exact Hessian is not) and D ⪰ 0 its damping matrix (-∂f/∂v), and the
  diagonal block of α K + β D at i. With ``free_only`` the columns of kinematic particles other than i are
  dropped (Baraff-Witkin's filter). Implicit Euler's matrix-vector product (α = h², β = h), its
  right-hand side and preconditioner, and power iteration (α = 1, β = 0) all use it;
* ``strain(world, i, base, xi, arrays, particle_q) -> (float64, int)``: the largest strain [-] of the
  family's elements at particle i and the element holding it; (-1, -1) where the family has no strain
  (the guards compare it with their tear limit);
* ``energy(world, element, base, arrays, inputs, particle_q) -> scalar``: the elastic energy [J] of one
  element (the guards' energy scale; tests of conservation and of force = -∇E);
* ``dissipation(world, element, base, arrays, inputs, particle_q, particle_qd) -> scalar`` (optional,
  ``None`` where the family has no dampers): the power [W] ≥ 0 one element's dampers take out of the
  motion (the guards' energy balance integrates it per step, ``kernels/guards.py``).

A family's *spec* is a frozen dataclass holding its compile-time switches (hashable, and equal only to specs
of its own class, so kernel caches never confuse two families), with a method ``funcs(scalar) ->
FamilyFuncs``. Kernels take one struct argument ``elements`` for all families: a chain
``{head: arrays of family 0, tail: {head: arrays of family 1, tail: ...}}`` built here from the specs, and
the hooks of the chain are the family hooks added in a fixed order. A new family is a new spec and
struct: no kernel signature changes, and a scene compiles only the families it has.

Incidence (which elements touch a particle) is Bell & Garland's hybrid (HYB) layout, shared by every
family: an ELL head of a compile-time width, [head_slots, particle_count], whose slot k of consecutive
particles is contiguous (coalesced loads) and whose loop unrolls, and a CSR tail for the particles with
more elements than the head holds, compiled in only when some particle has one. A particle of degree 200
costs its own row, not every row; no degree is too large. Each entry is (element, local): ``local`` is an
int the family defines (springs: the other particle; hinges: the particle's role in the element). Padding
entries are the family's choice too (springs point a particle at itself: a coincident pair, zero force).
"""

import functools
from typing import Any, NamedTuple

import warp as wp

from .precision import mat33_type, vec3_type
from .flatten import flat_kernel
from .kinematics import is_kinematic

wp.set_module_options({"enable_backward": False})

#: Module options of the kernels that evaluate element forces. Fast math (approximate float32 division and
#: square root, a few ulp; float64 is unaffected) speeds the fused symplectic Euler step by 7-14 % on an
#: H200 (bench/RESULTS.md), well inside float32's own rounding of a swinging cloth.
FORCE_KERNEL_OPTIONS = {"fast_math": True}

#: Widest ELL head of an incidence table; entries beyond a particle's head go to its CSR tail.
MAX_HEAD_SLOTS = 32


@wp.struct
class Incidence:
    """The elements of one family at each particle (per-world indices), HYB layout (see the module)."""

    head_element: wp.array2d[wp.int32]  # [head_slots, particle_count]: element of the particle's k-th entry
    head_local: wp.array2d[wp.int32]  # [head_slots, particle_count]: the entry's family-defined int
    tail_start: wp.array[wp.int32]  # [particle_count + 1]: the particle's tail is [start[i], start[i + 1])
    tail_element: wp.array[wp.int32]  # [tail entries]
    tail_local: wp.array[wp.int32]  # [tail entries]


class IncidenceShape(NamedTuple):
    """The compile-time shape of an incidence table: ELL head width and whether a CSR tail exists."""

    head_slots: int
    tail: bool

    def idle(self, field: str = "incidence") -> tuple:
        """Flat leaf paths (``flatten.py``) of an Incidence struct field that no hook reads: its CSR tail
        when there is none."""
        return () if self.tail else tuple(f"{field}__{leaf}" for leaf in ("tail_start", "tail_element", "tail_local"))


class FamilyFuncs(NamedTuple):
    """What a family supplies to the kernels (see the module docstring for the hooks' signatures)."""

    arrays: type  # the wp.struct of the family's arrays
    force: Any
    product: Any
    strain: Any
    energy: Any
    # Flat leaf paths of ``arrays`` that the gathered hooks (force, product, strain) never read in this spec;
    # kernels taking the family through ``elements`` pass them last (``flat_kernel(last=)``).
    idle: tuple = ()
    dissipation: Any = None  # per element, like ``energy``; None: the family dissipates nothing of its own
    # Optional, gathered like ``force``: (force, its dampers' part) at particle i, the guard's power counted in the
    # pass that evaluates the force (``forces.particle_power_func``); None: the guard counts a pass of its own.
    split: Any = None
    # Optional, per element like ``energy``: ``element_strain(world, element, base, arrays, particle_q) -> float64``,
    # the strain ``strain`` gives at its particles (the same bits); the guard measures it in its energy pass.
    element_strain: Any = None
    # Optional, gathered like ``force``: ``particle_energy(world, i, base, xi, vi, arrays, inputs, particle_q,
    # particle_qd) -> (energy, strain, dampers' power)`` in float64 of the elements particle i stands for (each element
    # at one of its particles): their ``energy``, largest ``element_strain`` and ``dissipation``, so that the
    # particles' values sum to the elements' totals. The guard's energy pass then walks particles, not elements.
    particle_energy: Any = None


@functools.cache
def no_strain_func(scalar: type, arrays: type):
    """The ``strain`` hook of a family that has none for the guards (wind, handles, hinges, tets: a fold, a pull or
    a compression is not a tear): (-1, -1) for every particle. ``arrays``: the family's struct type."""
    vec3 = vec3_type(scalar)

    @wp.func
    def strain(world: int, i: int, base: int, xi: vec3, elements: arrays, particle_q: wp.array[vec3]):
        return wp.float64(-1.0), -1

    return strain


# -- gathering over the incidence ----------------------------------------------------------------------------


@functools.cache
def masked_operand(scalar: type):
    """``operand(b, particle_flags, x, free_only) -> vec3``: x_b, or 0 for a kinematic particle when
    ``free_only`` (Baraff-Witkin's filter; a row exists only for a free particle, so its own entry is never
    dropped)."""
    vec3 = vec3_type(scalar)

    @wp.func
    def operand(b: int, particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool) -> vec3:
        value = x[b]
        if free_only:
            value = wp.where(is_kinematic(particle_flags[b]), vec3(scalar(0.0)), value)
        return value

    return operand


class FourPointFuncs(NamedTuple):
    """``@wp.func`` helpers of families whose elements are four particles with one scalar measure each
    (dihedral hinges: the angle; tets: the volume), in one precision (see ``four_point_funcs``)."""

    gradient_of_role: wp.Function
    gauss_newton_entry: wp.Function


@functools.cache
def four_point_funcs(scalar: type) -> FourPointFuncs:
    """``gradient_of_role(role, g0, g1, g2, g3) -> vec3``: the gradient of particle ``role`` (0..3) among the
    four, without dynamic tuple indexing.

    ``gauss_newton_entry(k, role, base, ids, g0, g1, g2, g3, particle_flags, x, free_only) -> (vec3, mat33)``:
    the element's Gauss-Newton stiffness k g gᵀ (g the measure's gradient over the four particles ``ids``,
    from state entry ``base``) applied to x, row ``role``: k g_role Σ_b g_b · x_b (x masked by
    ``masked_operand``), and its diagonal block k g_role g_roleᵀ."""
    vec3 = vec3_type(scalar)
    operand = masked_operand(scalar)

    @wp.func
    def gradient_of_role(role: int, g0: vec3, g1: vec3, g2: vec3, g3: vec3) -> vec3:
        return wp.where(role == 0, g0, wp.where(role == 1, g1, wp.where(role == 2, g2, g3)))

    @wp.func
    def gauss_newton_entry(k: scalar, role: int, base: int, ids: wp.vec4i, g0: vec3, g1: vec3, g2: vec3, g3: vec3,
                           particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool):
        ga = gradient_of_role(role, g0, g1, g2, g3)
        rate = wp.dot(g0, operand(base + ids[0], particle_flags, x, free_only))
        rate += wp.dot(g1, operand(base + ids[1], particle_flags, x, free_only))
        rate += wp.dot(g2, operand(base + ids[2], particle_flags, x, free_only))
        rate += wp.dot(g3, operand(base + ids[3], particle_flags, x, free_only))
        return (k * rate) * ga, k * wp.outer(ga, ga)

    return FourPointFuncs(gradient_of_role, gauss_newton_entry)


def gathered_force(scalar: type, Arrays, shape: IncidenceShape, entry):
    """A family's ``force`` hook summing ``entry`` over particle i's incidence entries (head, then tail).

    ``entry(world, element, local, i, base, xi, vi, arrays, inputs, particle_q, particle_qd) -> vec3`` is the
    force [N] of one element on particle i (0 for a padding entry: the family's padding ``local``)."""
    vec3 = vec3_type(scalar)
    head_slots, tail = shape

    @wp.func
    def force(
        world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Arrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ) -> vec3:
        incidence = arrays.incidence
        f = vec3(scalar(0.0))
        for k in range(wp.static(head_slots)):
            f += entry(world, incidence.head_element[k, i], incidence.head_local[k, i], i, base, xi, vi, arrays,
                       inputs, particle_q, particle_qd)
        if wp.static(tail):
            for e in range(incidence.tail_start[i], incidence.tail_start[i + 1]):
                f += entry(world, incidence.tail_element[e], incidence.tail_local[e], i, base, xi, vi, arrays, inputs,
                           particle_q, particle_qd)
        return f

    return force


def gathered_product(scalar: type, Arrays, shape: IncidenceShape, entry):
    """A family's ``product`` hook summing ``entry`` over particle i's incidence entries (head, then tail).

    ``entry(world, element, local, i, base, arrays, inputs, particle_q, particle_flags, x, free_only, alpha,
    beta) -> (vec3, mat33)`` is one element's part of row i of (α K + β D) x and of its diagonal block."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    head_slots, tail = shape

    @wp.func
    def product(
        world: int, i: int, base: int, xi: vec3, arrays: Arrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
        alpha: scalar, beta: scalar,
    ):
        incidence = arrays.incidence
        y = vec3(scalar(0.0))
        diagonal = mat33(scalar(0.0))
        for k in range(wp.static(head_slots)):
            yk, block = entry(world, incidence.head_element[k, i], incidence.head_local[k, i], i, base, arrays,
                              inputs, particle_q, particle_flags, x, free_only, alpha, beta)
            y += yk
            diagonal += block
        if wp.static(tail):
            for e in range(incidence.tail_start[i], incidence.tail_start[i + 1]):
                yk, block = entry(world, incidence.tail_element[e], incidence.tail_local[e], i, base, arrays, inputs,
                                  particle_q, particle_flags, x, free_only, alpha, beta)
                y += yk
                diagonal += block
        return y, diagonal

    return product


# -- composition ---------------------------------------------------------------------------------------------


def struct_type(name: str, fields: dict) -> type:
    """A Warp struct type named ``name`` with ``fields`` (name → type), made at run time (a factory's struct)."""
    cls = type(name, (), {"__annotations__": fields, "__module__": __name__})
    return wp.struct(cls)


class Elements(NamedTuple):
    """The composed hooks of a tuple of families and the struct type of their arrays (a head/tail chain)."""

    arrays: type
    force: Any
    product: Any
    strain: Any
    idle: tuple = ()  # flat leaf paths of ``arrays`` no hook reads (``flat_kernel(last=)``)

    def last(self, parameter: str) -> tuple:
        """``flat_kernel(last=)`` names of the idle leaves of a kernel parameter ``parameter`` of this type."""
        return tuple(f"{parameter}__{path}" for path in self.idle)


@functools.cache
def elements(scalar: type, specs: tuple) -> Elements:
    """The hooks of ``specs`` (a tuple of family specs) composed into one set, summed in their order.

    An empty tuple gives a placeholder struct and hooks that return zero (kernels compile them away).
    """
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    if not specs:
        Arrays = struct_type("NoElements", {"placeholder": wp.int32})

        @wp.func
        def no_force(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Arrays, inputs: wp.array2d[scalar],
                     particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> vec3:
            return vec3(scalar(0.0))

        @wp.func
        def no_product(world: int, i: int, base: int, xi: vec3, arrays: Arrays, inputs: wp.array2d[scalar],
                       particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3],
                       free_only: bool, alpha: scalar, beta: scalar):
            return vec3(scalar(0.0)), mat33(scalar(0.0))

        @wp.func
        def no_strain(world: int, i: int, base: int, xi: vec3, arrays: Arrays, particle_q: wp.array[vec3]):
            return wp.float64(-1.0), -1, -1

        return Elements(Arrays, no_force, no_product, no_strain, ("placeholder",))

    head = specs[0].funcs(scalar)
    if len(specs) == 1:
        Arrays = struct_type(f"Elements_{type(specs[0]).__name__}", {"head": head.arrays})

        @wp.func
        def force_1(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Arrays, inputs: wp.array2d[scalar],
                    particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> vec3:
            return head.force(world, i, base, xi, vi, arrays.head, inputs, particle_q, particle_qd)

        @wp.func
        def product_1(world: int, i: int, base: int, xi: vec3, arrays: Arrays, inputs: wp.array2d[scalar],
                      particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3],
                      free_only: bool, alpha: scalar, beta: scalar):
            return head.product(world, i, base, xi, arrays.head, inputs, particle_q, particle_flags, x, free_only,
                                alpha, beta)

        @wp.func
        def strain_1(world: int, i: int, base: int, xi: vec3, arrays: Arrays, particle_q: wp.array[vec3]):
            strain, element = head.strain(world, i, base, xi, arrays.head, particle_q)
            return strain, element, wp.where(element >= 0, 0, -1)

        return Elements(Arrays, force_1, product_1, strain_1, tuple(f"head__{p}" for p in head.idle))

    rest = elements(scalar, specs[1:])
    Arrays = struct_type(f"Elements_{type(specs[0]).__name__}_{len(specs)}", {"head": head.arrays, "tail": rest.arrays})

    @wp.func
    def force_n(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Arrays, inputs: wp.array2d[scalar],
                particle_q: wp.array[vec3], particle_qd: wp.array[vec3]) -> vec3:
        return head.force(world, i, base, xi, vi, arrays.head, inputs, particle_q, particle_qd) + rest.force(
            world, i, base, xi, vi, arrays.tail, inputs, particle_q, particle_qd
        )

    @wp.func
    def product_n(world: int, i: int, base: int, xi: vec3, arrays: Arrays, inputs: wp.array2d[scalar],
                  particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3],
                  free_only: bool, alpha: scalar, beta: scalar):
        y, diagonal = head.product(world, i, base, xi, arrays.head, inputs, particle_q, particle_flags, x, free_only,
                                   alpha, beta)
        y_rest, diagonal_rest = rest.product(world, i, base, xi, arrays.tail, inputs, particle_q, particle_flags, x,
                                             free_only, alpha, beta)
        return y + y_rest, diagonal + diagonal_rest

    @wp.func
    def strain_n(world: int, i: int, base: int, xi: vec3, arrays: Arrays, particle_q: wp.array[vec3]):
        strain, element = head.strain(world, i, base, xi, arrays.head, particle_q)
        strain_rest, element_rest, family_rest = rest.strain(world, i, base, xi, arrays.tail, particle_q)
        if strain_rest > strain:
            return strain_rest, element_rest, family_rest + 1
        return strain, element, wp.where(element >= 0, 0, -1)

    idle = tuple(f"head__{p}" for p in head.idle) + tuple(f"tail__{p}" for p in rest.idle)
    return Elements(Arrays, force_n, product_n, strain_n, idle)


def fill_elements(chain, family_arrays: list):
    """Fill ``chain``, an instance of the chain struct of :func:`elements`, with ``family_arrays`` (the struct
    instance of each family, in order); returns it."""
    if family_arrays:
        chain.head = family_arrays[0]
        if len(family_arrays) > 1:
            tail = chain.tail
            chain.tail = fill_elements(tail, family_arrays[1:])
    return chain


# -- per-element kernels -------------------------------------------------------------------------------------


@functools.cache
def element_energy_kernel(scalar: type, spec):
    """Kernel writing the elastic energy [J] of every element of one family in every world, float64, into
    ``energy_out[world, element]``; launch over (world_count, element_count)."""
    vec3 = vec3_type(scalar)
    funcs = spec.funcs(scalar)
    Arrays = funcs.arrays
    energy_func = funcs.energy

    # An element's energy reads its own entries, never the incidence table.
    @flat_kernel(module="unique", enable_backward=False, last=("arrays__incidence",))
    def element_energy(
        # Model:
        particle_count: int,
        arrays: Arrays,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        # Out:
        energy_out: wp.array2d[wp.float64],
    ):
        world, element = wp.tid()
        energy_out[world, element] = wp.float64(
            energy_func(world, element, world * particle_count, arrays, inputs, particle_q)
        )

    return element_energy
