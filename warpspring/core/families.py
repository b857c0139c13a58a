"""Element families on the host: the protocol a family implements, the incidence tables every family's
gather uses, and the family-wide quantities the analysis and guards need.

A family (springs, dihedral hinges, or one a user adds with :meth:`ModelBuilder.add_family`) implements
:class:`ElementFamily`; its kernel side (a ``wp.struct`` of its arrays and four ``@wp.func`` hooks) is
described in ``kernels/families.py``. Kernels take all families as one struct argument, so adding a family
changes no kernel signature; a model compiles only the families it has.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..kernels.families import MAX_HEAD_SLOTS, Incidence, IncidenceShape, element_energy_kernel
from ..kernels.flatten import flat_launch

#: Relative cost of a CSR tail entry against an ELL head slot in the choice of the head's width (an
#: uncoalesced load and a loop iteration against a coalesced, unrolled load).
TAIL_ENTRY_COST = 2.0


class ElementFamily:
    """The host side of an element family. Subclasses set :attr:`name` and implement the methods below.

    A family is created with its elements (NumPy, per-world particle indices) before ``finalize``; the
    builder then calls :meth:`finalize` once to put its arrays on the model's device. Everything else reads
    those arrays.
    """

    #: Plural noun naming the elements in messages and reports ("springs", "hinges").
    name: str = "elements"
    #: Whether the family's forces do work from outside (wind, handles): it has no energy, and the guards count
    #: its work (``kernels/guards.py``).
    does_work: bool = False

    def finalize(self, model) -> None:
        """Create the device arrays on ``model.device`` in ``model.scalar`` (called once by the builder)."""

    def device_bytes(self, particle_count: int, scalar_bytes: int, worlds: int) -> int:
        """Bytes of the device arrays :meth:`finalize` will make (for the memory estimate before finalize), with
        ``particle_count`` particles per world, scalars of ``scalar_bytes`` and ``worlds`` worlds; 0 where the
        family does not say."""
        return 0

    def damping_rates(self, model, positions: np.ndarray) -> np.ndarray:
        """The viscous damping [N·s/m] the family puts on each particle's own motion, like drag, at
        ``positions`` (float64, [world_count, particle_count, 3]), shape [world_count, particle_count]: the
        stability advisor adds it to the drag of the slow modes. Families whose damping couples particles
        (springs, hinges: kd along elements) report none here; they enter through their kd/k ratios."""
        return np.zeros((model.world_count, model.particle_count))

    def velocity_dependent(self, model) -> bool:
        """Whether the family's forces depend on velocity (a damper with a nonzero value in some world): velocity
        Verlet then runs its corrector. Read when an integrator is made."""
        return False

    def live_arrays(self) -> dict:
        """The family's device arrays a user may change between frames (live values, host-set targets), by name:
        checkpoints save them and :meth:`restore_live_array` puts them back. Default: none."""
        return {}

    def restore_live_array(self, model, name: str, values: np.ndarray) -> None:
        """Write a checkpoint's ``values`` of :meth:`live_arrays`' ``name`` (validated: same dtype, same shape or
        another number of world rows). Default: in place."""
        self.live_arrays()[name].assign(values)

    def tracks(self) -> tuple:
        """The keyframe tracks the family reads (they join the model's track table before :meth:`finalize`,
        with indices that never move)."""
        return ()

    def at_time(self, model, state) -> None:
        """Bring the family's time-dependent arrays to the time of ``state`` (device work, launched wherever
        animated inputs are evaluated, before forces); most families have none."""

    def time_dependent(self, model) -> bool:
        """Whether :meth:`at_time` has work to do in this model (a frame's substeps in one launch, which cannot
        launch it between substeps, is refused where it has). Default: whether the family overrides it."""
        return type(self).at_time is not ElementFamily.at_time

    @property
    def element_count(self) -> int:
        raise NotImplementedError

    def spec(self, model, *, linear: bool = False):
        """The family's kernel spec (hashable; ``kernels/families.py``). ``linear``: for the stability analysis,
        which linearises about the state (for springs: Hooke's law, the advisor scales biphasic stiffness)."""
        raise NotImplementedError

    def arrays(self, model, *, stiffness=None):
        """The family's ``wp.struct`` instance; ``stiffness``: a device array replacing its stiffness (the
        analysis's override), where the family has one."""
        raise NotImplementedError

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None) -> np.ndarray:
        """Upper bounds [N/m] on Σ_b ‖K_ab‖ over each row a of the family's stiffness matrix at the model's
        initial positions, float64, shape [world_count, particle_count], counting the diagonal block and the
        blocks of free neighbours (``free``: bool, [world_count, particle_count]) — the family's part of the
        advisor's Gershgorin bound."""
        raise NotImplementedError

    def describe_element(self, model, element: int) -> str:
        """A short name of one element for messages, e.g. "spring 12 (particles 3-4)"."""
        return f"{self.name[:-1] if self.name.endswith('s') else self.name} {element}"


# -- incidence tables ----------------------------------------------------------------------------------------


def head_slots(degree: np.ndarray) -> int:
    """Width of the ELL head for particles of the given degrees: the width minimising the padded head's
    slots plus ``TAIL_ENTRY_COST`` per tail entry (and a per-particle tail check once any tail exists),
    at most ``MAX_HEAD_SLOTS``. A uniform degree (a cloth) gives its maximum and no tail."""
    degree = np.asarray(degree, dtype=np.int64)
    n = len(degree)
    largest = int(degree.max()) if n else 0
    if largest == 0:
        return 0
    counts = np.bincount(degree, minlength=largest + 1)
    beyond = np.cumsum(counts[::-1])[::-1]  # beyond[k]: particles of degree ≥ k
    best, best_cost = largest, np.inf
    for width in range(1, min(largest, MAX_HEAD_SLOTS) + 1):
        overflow = int(beyond[width + 1:].sum())  # Σ max(0, d - width) = Σ_{k > width} #(degree ≥ k)
        cost = n * width + TAIL_ENTRY_COST * overflow + (2 * n if overflow else 0)
        if cost < best_cost:
            best, best_cost = width, cost
    return best


def build_incidence(members: np.ndarray, particle_count: int, local: np.ndarray, pad_local, *, device,
                    slots: int | None = None) -> tuple[Incidence, IncidenceShape]:
    """The incidence table of a family (HYB layout, ``kernels/families.py``) on ``device``.

    Args:
        members: particles of each element, int, shape [element_count, arity] (per-world indices).
        particle_count: particles per world.
        local: the family-defined int of each (element, member) entry, shape [element_count, arity].
        pad_local: the ``local`` of padding entries: an int, or a function of the particle indices
            (an int array of shape [particle_count]) giving one per particle. Padding entries have element 0.
        device: the Warp device.
        slots: the ELL head's width; default :func:`head_slots` of the degrees.

    Entries of a particle are in member order (its role in the element), then element order; the first
    ``slots`` fill its head.
    """
    members = np.asarray(members, dtype=np.int64)
    elements_count, arity = members.shape
    # Role-major: a particle's entries as member 0 of their elements first, then as member 1, ...; within a
    # role in element order. Consecutive particles then share the layout of their slots (in a cloth, slot k
    # is the same neighbour direction), so the gather's neighbour loads of a warp fall close together.
    owner = members.T.ravel()
    element = np.tile(np.arange(elements_count, dtype=np.int64), arity)
    value = np.asarray(local, dtype=np.int64).T.ravel()
    order = np.argsort(owner, kind="stable")
    owner, element, value = owner[order], element[order], value[order]
    degree = np.bincount(owner, minlength=particle_count)
    width = head_slots(degree) if slots is None else int(slots)
    start = np.concatenate([[0], np.cumsum(degree)])
    slot = np.arange(len(owner)) - start[owner]  # position of each entry in its particle's list
    particles = np.arange(particle_count)
    pad = pad_local(particles) if callable(pad_local) else np.full(particle_count, pad_local)
    head_element = np.zeros((width, particle_count), dtype=np.int32)
    head_local = np.broadcast_to(np.asarray(pad, dtype=np.int32), (width, particle_count)).copy()
    in_head = slot < width
    head_element[slot[in_head], owner[in_head]] = element[in_head]
    head_local[slot[in_head], owner[in_head]] = value[in_head]
    tail = ~in_head
    tail_degree = np.bincount(owner[tail], minlength=particle_count)
    table = Incidence()
    table.head_element = wp.array(head_element, dtype=wp.int32, device=device)
    table.head_local = wp.array(head_local, dtype=wp.int32, device=device)
    table.tail_start = wp.array(np.concatenate([[0], np.cumsum(tail_degree)]).astype(np.int32), dtype=wp.int32,
                                device=device)
    table.tail_element = wp.array(element[tail].astype(np.int32), dtype=wp.int32, device=device)
    table.tail_local = wp.array(value[tail].astype(np.int32), dtype=wp.int32, device=device)
    return table, IncidenceShape(head_slots=width, tail=bool(tail.any()))


def incidence_bytes(members, particle_count: int) -> int:
    """Bytes of an incidence table (:func:`build_incidence`) of elements with these particles, int, shape
    [element_count, arity]: an ELL head of element and local per slot and particle, the tail's start per
    particle, and element and local per tail entry."""
    degree = np.bincount(np.asarray(members, dtype=np.int64).ravel(), minlength=particle_count)
    slots = head_slots(degree)
    tail = int(np.maximum(degree - slots, 0).sum())
    return 8 * slots * particle_count + 4 * (particle_count + 1) + 8 * tail


def incidence_entries(table: Incidence, shape: IncidenceShape) -> list[list[tuple[int, int]]]:
    """Every particle's (element, local) entries of an incidence table, head then tail, without padding (a
    host read, for tests and inspection)."""
    head_element = table.head_element.numpy()
    head_local = table.head_local.numpy()
    start = table.tail_start.numpy()
    tail_element = table.tail_element.numpy()
    tail_local = table.tail_local.numpy()
    n = len(start) - 1
    entries = []
    for i in range(n):
        row = [(int(head_element[k, i]), int(head_local[k, i])) for k in range(shape.head_slots)]
        row += [(int(tail_element[t]), int(tail_local[t])) for t in range(start[i], start[i + 1])]
        entries.append(row)
    return entries


# -- family-wide quantities ----------------------------------------------------------------------------------


def element_energies(model, family: ElementFamily, particle_q: wp.array | None = None) -> np.ndarray:
    """The elastic energy [J] of every element of ``family`` in every world at ``particle_q`` (default the
    model's initial positions), float64, shape [world_count, element_count] (one device launch)."""
    energy = wp.zeros((model.world_count, family.element_count), dtype=wp.float64, device=model.device)
    if family.element_count:
        flat_launch(element_energy_kernel(model.scalar, family.spec(model)),
                  dim=(model.world_count, family.element_count),
                  inputs=[model.particle_count, family.arrays(model), model.inputs,
                          model.particle_q if particle_q is None else particle_q],
                  outputs=[energy], device=model.device)
    return energy.numpy()


def world_elastic_energy(model, particle_q: wp.array | None = None) -> np.ndarray:
    """Each world's elastic energy [J], the sum over every family's elements, float64, shape [world_count]."""
    total = np.zeros(model.world_count)
    for family in model.families:
        total += element_energies(model, family, particle_q).sum(axis=1)
    return total
