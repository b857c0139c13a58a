"""The spring family on the host: its kernel spec and struct from the model's ``spring_*`` arrays, its part
of the advisor's Gershgorin bound, the spring laws a group of springs may follow and its plasticity."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError
from ..kernels.families import MAX_HEAD_SLOTS, Incidence, IncidenceShape
from ..kernels.spring_laws import SPRING_LINEAR, SPRING_SQUARE
from ..kernels.springs import SpringSpec, plastic_arrays_type, spring_arrays_type
from .families import ElementFamily, build_incidence, head_slots

#: The spring laws a group of springs may follow (``ModelBuilder.add_springs(law=...)``), by name: the
#: tension T at a stretch Δ = |d| - L is k Δ (linear, k in N/m) or k Δ|Δ| (square, k in N/m²).
SPRING_LAWS = {"linear": SPRING_LINEAR, "square": SPRING_SQUARE}


def spring_law_code(law: str) -> int:
    """The kernel code of the law named ``law``, or a one-line ConfigError naming the laws there are."""
    if law not in SPRING_LAWS:
        raise ConfigError(f"unknown spring law {law!r}: use one of {', '.join(map(repr, SPRING_LAWS))}")
    return SPRING_LAWS[law]


def spring_law_codes(model) -> np.ndarray:
    """Each spring's law code (``SPRING_LAWS``), int, shape [spring_count] (reads the device when some group is
    not linear)."""
    if model.spring_law_code is None:
        return np.full(model.spring_count, SPRING_LINEAR)
    return model.spring_law_code.numpy()


@dataclass(frozen=True)
class SpringPlasticity:
    """How a group of springs yields and breaks (``ModelBuilder.add_springs(plasticity=...)``).

    Past its elastic limit a spring's rest length L moves toward its current length, so the group keeps
    a deformation. With L₀ the rest length as built and α the accumulated plastic strain, a step whose
    elastic strain e = (|d| - L)/L₀ exceeds the limit ε_y = ε_y0 (1 + H α) in magnitude moves L by
    Δγ L₀ toward |d| and adds Δγ to α, where Δγ = min(1, r h) · (|e| - ε_y)/(1 + ε_y0 H): the return map
    of 1-D plasticity with linear isotropic hardening (Simo & Hughes, *Computational Inelasticity*, 1998,
    box 1.4), of which the share r h flows in a step of h (creep; r = inf: the rest length lands on the
    limit at once). Under a monotone pull to a total strain ε = |d|/L₀ - 1 > ε_y0 that gives
    α = (ε - ε_y0)/(1 + ε_y0 H) and L = (1 + α) L₀, whatever the steps. The update runs once per step, on
    the step's result (``StepFinisher``): never per Runge-Kutta stage or solver iteration.

    Attributes:
        yield_strain: ε_y0 [-] > 0, the elastic limit as a strain of L₀; ``None``: none.
        yield_force: F_y [N] > 0, the elastic limit as a tension magnitude, turned into a strain through the
            spring's law on the branch (tension or compression) it is on, at its current stiffness; the
            smaller of the two limits applies. ``None``: none.
        yield_rate: r [1/s] > 0, the share of the excess that flows per second; ``math.inf`` (default): all
            of it in the step that exceeds the limit.
        hardening: H [-] ≥ 0: the limit grows by the factor 1 + H α (0: perfectly plastic).
        break_strain: [-] > 0: the spring breaks once |d| > (1 + break_strain) L₀ and carries no force from
            then on (its rest length becomes negative); ``None``: it never breaks.
    """

    yield_strain: float | None = None
    yield_force: float | None = None
    yield_rate: float = math.inf
    hardening: float = 0.0
    break_strain: float | None = None

    def __post_init__(self):
        for name in ("yield_strain", "yield_force", "break_strain"):
            value = getattr(self, name)
            if value is not None:
                checks.positive(f"plasticity {name}", value)
        if not (isinstance(self.yield_rate, (int, float)) and self.yield_rate > 0.0):
            raise ConfigError(f"plasticity yield_rate must be a number > 0 [1/s] (inf: instant), got {self.yield_rate!r}")
        checks.non_negative("plasticity hardening", self.hardening)
        if self.yield_strain is None and self.yield_force is None and self.break_strain is None:
            raise ConfigError("plasticity needs yield_strain, yield_force or break_strain: give at least one")

    @property
    def row(self) -> tuple:
        """(ε_y0, F_y, r, H, ε_break) with ``inf`` for an absent limit: the arrays' entries for one spring."""
        inf = math.inf
        return (inf if self.yield_strain is None else float(self.yield_strain),
                inf if self.yield_force is None else float(self.yield_force), float(self.yield_rate),
                float(self.hardening), inf if self.break_strain is None else float(self.break_strain))


class SpringFamily(ElementFamily):
    """Springs between two particles (the model's ``spring_*`` arrays and ``spring_incidence``)."""

    name = "springs"

    def __init__(self, model):
        self._model = model

    @property
    def element_count(self) -> int:
        return self._model.spring_count

    def spec(self, model, *, linear: bool = False) -> SpringSpec:
        # The stability analysis (``linear``) drops the stabilisers' parts of the law (it is given their
        # stiffest branch as a stiffness override) but keeps the material's: each spring's own law, whose
        # tangent at the state it linearises about, and the per-world rest lengths of plastic springs.
        material = model.spring_material_law
        gathered = model.spring_gather and not linear
        slot_groups = model.spring_slot_groups if gathered else ()
        return SpringSpec(
            incidence=model.spring_incidence_shape,
            law=material if linear else model.spring_law,
            gathered=gathered,
            slot_groups=slot_groups,
            grid_slots=model.spring_grid_slots if slot_groups else (),
        )

    def arrays(self, model, *, stiffness=None, grouped: bool | None = None):
        """The struct of the spring arrays for ``spec(model)`` (``grouped``: for a spec with slot groups, and
        the grid's directions where the model has them, or per spring; default the model's gather spec's)."""
        law = model.spring_material_law
        if grouped is None:
            grouped = bool(model.spring_slot_groups) and model.spring_gather
        grid = grouped and bool(model.spring_grid_slots)
        springs = spring_arrays_type(model.scalar, law.per_spring, grouped, grid)()
        if grouped:
            springs.group_spring = model.spring_group_spring
        if grid:
            springs.grid_size = model.spring_grid_size
        springs.indices = model.spring_indices
        springs.rest_length = model.spring_plastic_rest_length if law.plastic else model.spring_rest_length
        springs.stiffness = model.spring_stiffness if stiffness is None else stiffness
        springs.damping = model.spring_damping
        springs.incidence = model.spring_incidence
        if law.per_spring:
            springs.law = model.spring_law_code
            springs.compression_ratio = model.spring_compression_ratio
        return springs

    def plastic_arrays(self, model):
        """The struct of the plastic pass's parameters (``kernels.springs.plastic_arrays_type``)."""
        plastic = plastic_arrays_type(model.scalar)()
        plastic.index = model.spring_plastic_index
        plastic.rest_length_0 = model.spring_rest_length
        plastic.yield_strain = model.spring_yield_strain
        plastic.yield_force = model.spring_yield_force
        plastic.yield_rate = model.spring_yield_rate
        plastic.hardening = model.spring_hardening
        plastic.break_strain = model.spring_break_strain
        return plastic

    def tangent_factor(self, model, positions=None) -> np.ndarray:
        """dT/dΔ / ke [-] of each spring in each world at ``positions`` (default the model's initial ones;
        an array of shape [world_count · particle_count, 3]), float64, shape [world_count, spring_count]:
        1 for linear springs, 2|Δ| [m] for square ones (their ke is in N/m²), times the compression ratio on
        the compression branch; 0 for a broken spring. The advisor's linearisation: a square spring is as
        stiff as its tangent 2 ke |Δ| at that state's stretch, so at rest (Δ = 0) it adds nothing."""
        law, worlds, count = model.spring_material_law, model.world_count, model.spring_count
        factor = np.ones((worlds, count))
        if not (law.per_spring or law.plastic):
            return factor
        q = (model.particle_q if positions is None else positions)
        q = (q.numpy() if hasattr(q, "numpy") else np.asarray(q)).astype(np.float64).reshape(worlds, -1, 3)
        i, j = model.spring_indices.numpy().reshape(-1, 2).T
        length = np.linalg.norm(q[:, j] - q[:, i], axis=2)
        rest = model.spring_rest_lengths()
        stretch = length - rest
        if law.asymmetric:
            factor = np.where(stretch < 0.0, model.spring_compression_ratio.numpy()[None, :], factor)
        if law.square:
            factor = np.where(model.spring_law_code.numpy()[None, :] == SPRING_SQUARE, 2.0 * np.abs(stretch) * factor,
                              factor)
        return np.where(rest < 0.0, 0.0, factor)

    def gershgorin_rows(self, model, free: np.ndarray, stiffness: np.ndarray | None = None, *,
                        positions=None) -> np.ndarray:
        """Each clamped spring block has spectral norm ≤ kₛ (|T|/|d| ≤ kₛ when not compressed), so row i
        gains kₛ for its diagonal block and kₛ for the block of a free neighbour. kₛ is the law's tangent
        at ``positions`` (default the model's initial ones; ``tangent_factor``): for a square spring
        2 ke |Δ|, which also bounds its |T|/|d| = ke Δ²/|d| ≤ ke |Δ| when stretched."""
        worlds, n = model.world_count, model.particle_count
        if model.spring_count == 0:
            return np.zeros((worlds, n))
        values = model.spring_stiffness.numpy() if stiffness is None else stiffness
        k = np.broadcast_to(np.asarray(values, dtype=np.float64), (worlds, model.spring_count))
        k = k * self.tangent_factor(model, positions)
        i, j = model.spring_indices.numpy().reshape(-1, 2).T
        offset = (np.arange(worlds) * n)[:, None]
        wi, wj = (offset + i).ravel(), (offset + j).ravel()  # world-major entries of each world's spring ends
        rows = np.zeros(worlds * n)
        for ends, weights in ((wi, k), (wj, k), (wi, k * free[:, j]), (wj, k * free[:, i])):
            rows += np.bincount(ends, weights=weights.ravel(), minlength=worlds * n)
        return rows.reshape(worlds, n)

    def describe_element(self, model, element: int) -> str:
        a, b = model.spring_indices.numpy()[element]
        return f"spring {element} (particles {a}-{b})"



# -- spring data per group -----------------------------------------------------------------------------------


def uniform_groups(model) -> np.ndarray:
    """Whether each spring group (``model.spring_families``, in order) has one rest length, and one ke and one kd
    in each stiffness and damping row, bool, shape [group_count] (reads the device)."""
    rest, ke, kd = (model.spring_rest_length.numpy(), model.spring_stiffness.numpy(), model.spring_damping.numpy())
    return np.array([len(members) > 0 and bool(np.all(rest[members] == rest[members[0]])
                                               and np.all(ke[:, members] == ke[:, members[:1]])
                                               and np.all(kd[:, members] == kd[:, members[:1]]))
                     for members in model.spring_families.values()], dtype=bool)


def group_incidence(springs: np.ndarray, group: np.ndarray, particle_count: int, *, device):
    """The springs' incidence (entries (spring, other particle)) laid out group by group: group g owns the
    head slots [start_g, start_g + width_g), width_g its largest degree at one particle, and a particle's
    springs of group g fill its slots from start_g (role-major, then in spring order, as ``build_incidence``),
    the rest padding (0, the particle itself). Every entry is in the head: there is no tail.

    Args:
        springs: the two particles of each spring (per-world indices), int, shape [spring_count, 2].
        group: each spring's group, int in [0, group_count), shape [spring_count].
        particle_count: particles per world.
        device: the Warp device.

    Returns:
        (table, shape, slot_groups): the Incidence, its IncidenceShape and the group of each head slot; or
        None when the head would be wider than ``MAX_HEAD_SLOTS``.
    """
    return head_incidence(group_head(springs, group, particle_count), particle_count, device=device)


def head_incidence(head, particle_count: int, *, device):
    """``group_incidence``'s result on ``device`` from ``group_head``'s (None stays None)."""
    if head is None:
        return None
    head_element, head_local, slot_groups = head
    table = Incidence()
    table.head_element = wp.array(head_element, dtype=wp.int32, device=device)
    table.head_local = wp.array(head_local, dtype=wp.int32, device=device)
    table.tail_start = wp.zeros(particle_count + 1, dtype=wp.int32, device=device)
    table.tail_element = wp.zeros(0, dtype=wp.int32, device=device)
    table.tail_local = wp.zeros(0, dtype=wp.int32, device=device)
    return table, IncidenceShape(head_slots=len(slot_groups), tail=False), slot_groups


def group_head(springs: np.ndarray, group: np.ndarray, particle_count: int):
    """The head of ``group_incidence`` on the host: (head_element, head_local, slot_groups), int32 arrays of
    shape [head_slots, particle_count] and the group of each slot; or None when wider than ``MAX_HEAD_SLOTS``."""
    count = len(springs)
    group_count = int(group.max()) + 1 if count else 0
    owner = springs.T.ravel()
    element = np.tile(np.arange(count), 2)
    other = springs[:, ::-1].T.ravel()
    entry_group = np.tile(group, 2)
    order = np.lexsort((element, np.repeat([0, 1], count), entry_group, owner))  # owner, group, role, spring
    owner, element, other, entry_group = owner[order], element[order], other[order], entry_group[order]
    key = owner * group_count + entry_group
    first = np.searchsorted(key, key)  # first entry of the same (particle, group); key is sorted
    rank = np.arange(len(key)) - first
    width = np.zeros(group_count, dtype=np.int64)
    np.maximum.at(width, entry_group, rank + 1)
    if width.sum() > MAX_HEAD_SLOTS:
        return None
    start = np.concatenate([[0], np.cumsum(width)])
    slot = start[entry_group] + rank
    head_slots = int(width.sum())
    head_element = np.zeros((head_slots, particle_count), dtype=np.int32)
    head_local = np.broadcast_to(np.arange(particle_count, dtype=np.int32), (head_slots, particle_count)).copy()
    head_element[slot, owner] = element
    head_local[slot, owner] = other
    return head_element, head_local, tuple(int(g) for g in np.repeat(np.arange(group_count), width))


def grid_slots(head_local: np.ndarray, slot_groups: tuple, grid_shape: tuple) -> tuple:
    """The grid direction of each head slot of a group-by-group table (``group_head``), or () where the table
    is not the one the grid's directions give.

    The particles must be an nx × ny grid in grid order (particle i at row i // nx, column i % nx). Each group's
    directions (dx, dy) [columns, rows] are read at the first particle that fills all of the group's slots;
    the table qualifies when, at every particle, the group's slots hold the neighbours in those directions that
    lie on the grid, in that order, and padding (the particle itself) after them: what the implicit gather
    (``kernels.springs.grid_neighbour``) sums, in the same order, with zeros where the table has none.

    Args:
        head_local: the other particle of each entry, int, shape [head_slots, particle_count].
        slot_groups: each slot's group (contiguous ranges), length head_slots.
        grid_shape: (nx, ny).
    """
    nx, ny = grid_shape
    particle = np.arange(nx * ny)
    if head_local.shape[1] != len(particle) or not len(slot_groups):
        return ()
    row, column = np.divmod(particle, nx)
    groups = np.asarray(slot_groups)
    directions = []
    for g in dict.fromkeys(slot_groups):
        slots = np.flatnonzero(groups == g)
        other = head_local[slots[0] : slots[-1] + 1].astype(np.int64)
        full = np.flatnonzero((other != particle).all(axis=0))
        if not len(full):
            return ()
        dx, dy = other[:, full[0]] % nx - column[full[0]], other[:, full[0]] // nx - row[full[0]]
        c, r = column + dx[:, None], row + dy[:, None]
        inside = (c >= 0) & (c < nx) & (r >= 0) & (r < ny)
        expected = np.broadcast_to(particle, other.shape).copy()
        k, q = np.nonzero(inside)
        expected[(np.cumsum(inside, axis=0) - 1)[k, q], q] = q + dy[k] * nx + dx[k]
        if not np.array_equal(expected, other):
            return ()
        directions += zip(dx.tolist(), dy.tolist())
    return tuple(directions)


def spring_layout(model):
    """The spring layout the model's values call for: (table, shape, slot_groups, grid_slots), the first three
    of ``group_incidence`` with the slots of non-uniform groups marked -1, where the springs are gathered
    without per-spring law arrays or plasticity, some group is uniform, the grouped head fits and moves no more
    bytes than the per-spring head; else None (per spring, role-major). ``grid_slots`` are the directions of
    ``grid_slots`` where the model is one grid in grid order (``Model.spring_grid_shape``) whose table they
    give and the finalize option allows it (``spring_grid``), else (). A function of the topology and the
    values alone, so a model switched between frames gets what a model built with its values gets."""
    law = model.spring_material_law
    if not (model.spring_gather and model.spring_count) or law.per_spring or law.plastic:
        return None
    uniform = uniform_groups(model)
    if not uniform.any():
        return None
    springs = model.spring_indices.numpy().reshape(-1, 2).astype(np.int64)
    group = np.zeros(model.spring_count, dtype=np.int64)
    for g, members in enumerate(model.spring_families.values()):
        group[members] = g
    # The grouped table and its grid directions depend on the topology alone: built once, kept for later
    # switches (``_spring_groups``).
    cached = getattr(model, "_spring_groups", None)
    if cached is None:
        head = group_head(springs, group, model.particle_count)
        directions = ()
        if head is not None and model._spring_grid and model.spring_grid_shape is not None:
            directions = grid_slots(head[1], head[2], model.spring_grid_shape)
        cached = (head_incidence(head, model.particle_count, device=model.device), directions)
    model._spring_groups = cached
    layout, directions = cached
    if layout is None:
        return None
    table, shape, slot_groups = layout
    slot_groups = tuple(g if uniform[g] else -1 for g in slot_groups)
    # Per particle: a grouped slot moves one int (the other particle), a slot read per spring two ints and a
    # rest length, ke and kd; the per-spring head moves the latter in every slot (and its tail's start).
    scalar = wp.types.type_size_in_bytes(model.scalar)
    per_spring_slot = 8 + 3 * scalar
    grouped_bytes = 4 * len(slot_groups) + (per_spring_slot - 4) * slot_groups.count(-1)
    degree = np.bincount(springs.ravel(), minlength=model.particle_count)
    width = head_slots(degree)
    if grouped_bytes > per_spring_slot * width:
        return None
    return table, shape, slot_groups, directions


def set_spring_layout(model, grouped: bool) -> None:
    """Lay the springs out as ``spring_layout`` says (``grouped``) or per spring (role-major incidence,
    ``build_incidence``), setting ``spring_incidence``, ``spring_incidence_shape``, ``spring_slot_groups``,
    ``spring_group_spring``, ``spring_grid_slots`` and ``spring_grid_size``. On a finalized model, a layout
    other than the current one replaces them (a structural change); the same layout changes nothing."""
    layout = spring_layout(model) if grouped else None
    current = ((getattr(model, "spring_slot_groups", None), getattr(model, "spring_grid_slots", None))
               if hasattr(model, "spring_incidence") else None)
    if (layout[2:] if layout else ((), ())) == current:
        return
    if layout is None:
        springs = model.spring_indices.numpy().reshape(-1, 2).astype(np.int64)
        model.spring_incidence, model.spring_incidence_shape = build_incidence(
            springs, model.particle_count, springs[:, ::-1], lambda particles: particles, device=model.device)
        model.spring_slot_groups = ()
        model.spring_group_spring = None
        model.spring_grid_slots = ()
        model.spring_grid_size = None
        return
    firsts = [int(members[0]) if len(members) else 0 for members in model.spring_families.values()]
    model.spring_incidence, model.spring_incidence_shape, model.spring_slot_groups, model.spring_grid_slots = layout
    model.spring_group_spring = wp.array(np.asarray(firsts, dtype=np.int32), dtype=wp.int32, device=model.device)
    model.spring_grid_size = (wp.array(np.asarray(model.spring_grid_shape, dtype=np.int32), dtype=wp.int32,
                                       device=model.device) if model.spring_grid_slots else None)
