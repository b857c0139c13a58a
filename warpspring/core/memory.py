"""Memory a model and a run of it need, estimated from counts before anything is allocated, and the
memory the machine has free.

The estimate counts every array the code allocates, byte for byte, from the model's sizes: particles,
springs, hinges, triangles and colliders; worlds; the scalar type; the incidence tables' widths (keyframe
tracks, tens of bytes per key, are left out). The run's parts follow the code that allocates them: a :class:`~warpspring.core.stepper.Stepper` holds two states
(the current one and the scratch one it alternates with); each integrator allocates its own scratch
(:data:`INTEGRATOR_SCRATCH`, read from each ``__init__``); the guard one partial sum per reducing block, and
what it makes for the run's path (:func:`guard_path`: a substep's midpoint state, the scattered springs' damper
sums, the power sums of the integrator's force pass); strain limiting three position
buffers; the contact stage its slot buffer; the stepper's warm-up, copies of what a step carries to the next;
the USD writer a vertex-normal buffer on the device and, per frame, the positions and normals it reads back and
hands to USD. Warp's native memory counts too: each world's BVH of self-collision
(:func:`self_contact_bytes`, with its pair buffers and caches) and each mesh collider's ``wp.Mesh``
(:func:`mesh_native_bytes`), from the sizes Warp's ``bvh.cpp``/``bvh.cu`` and ``mesh.cu`` allocate.

Host memory is estimated as well, as what :meth:`ModelBuilder.finalize` holds at its peak beyond the
builder's own arrays: its concatenated copies and the temporaries of the incidence tables' stable sort
(:func:`warpspring.core.families.build_incidence`), which dominate on the host (~150 bytes per spring).
On the CPU the device is host memory, so both add up there.

Measured on the CPU (``tests/test_memory.py``; ``python tests/test_memory.py 256 512 1024`` prints the
table): the model's arrays, the states, every integrator's scratch, the guard's and the post-step buffers
agree with the estimate to the byte (but for keyframe tracks); the growth of the process's peak resident
memory while it builds and finalizes a 256² and 512² cloth grid (springs gathered and laid out by group) is below
:attr:`MemoryEstimate.finalize_peak` by 2.6 % and 3.7 % (held to :data:`PEAK_TOLERANCE`; ``bench/memory.py`` holds measured ≤ estimate ≤ 2 × measured
for every kind of scene), and that of a run of a few frames with the USD writer after it within -7 % … +11 %
(512² with four integrators, 1024²).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass

from .. import checks
from ..errors import ConfigError
from ..kernels.guards import (BALANCE_SLOTS, CARRY_SLOTS, ENERGY_BY_PARTICLES, FOLD_ABOVE, FOLD_CHUNK, GUARD_FLOATS,
                              GUARD_INTS, GUARD_LIMITS, MIRROR_COLUMNS, PARTIAL_SLOTS, RUNNING_SLOTS)
from ..kernels.inputs import INPUT_COUNT
from ..kernels.linalg import CG_SHORT_SLOTS, REDUCE_FILL_BLOCKS, REDUCE_PER_LANE, reduce_launch_dim
from ..kernels.selfcontact import (CACHE_SLOTS, COUNTER_COUNT, FLAG_KINDS, PAIRS_PER_VERTEX, PARAM_COUNT, PATCH_CHUNK,
                                   PATCH_COLUMNS, SCAN_BLOCK, patch_count)

#: Bytes per floating-point number of each precision.
SCALAR_BYTES = {"float32": 4, "float64": 8}

#: Scratch arrays each integrator allocates, from its ``__init__``: (vec3 arrays of one entry per particle of
#: every world, extra scalars per particle, float64 slots per reducing block of a world, float64 / int32 per world).
#:
#: * symplectic Euler: none;
#: * velocity Verlet: v½ and f(x', v½);
#: * explicit Runge-Kutta with S stages (Euler 1, midpoint 2, RK4 4): stage velocities and forces [S, n] and
#:   one stage position array: 2S + 1, and each world's stage time;
#: * dopri5 (7 stages): 15 as above plus its solution state y (positions, velocities, forces: 3); per world its
#:   step controller (8 float64), counters (6 int32), step size and two times; one error partial per block;
#: * implicit Euler: right-hand side, Δv, r, z, p, Ap and the driven pins' Δv (7), a 3 × 3 preconditioner
#:   block per particle (9 scalars), 7 CG partial sums per block, and per world 7 CG scalars and 2 counters.
INTEGRATOR_SCRATCH = {
    "symplectic_euler": (0, 0, 0, 0, 0),
    "velocity_verlet": (2, 0, 0, 0, 0),
    "explicit_euler": (3, 0, 0, 1, 0),
    "midpoint": (5, 0, 0, 1, 0),
    "rk4": (9, 0, 0, 1, 0),
    "dopri5": (18, 0, 1, 11, 6),
    "implicit_euler": (7, 9, 7, 7, 2),
}

#: Relative tolerances the estimate is held to against measurement (``tests/test_memory.py``): the model's
#: arrays (exact but for keyframe tracks), and the peak resident memory of building and finalizing a grid
#: (estimate above the measured peak by 1 … 2 %).
MODEL_TOLERANCE = 0.02
PEAK_TOLERANCE = 0.10

# Host bytes of the builder's arrays: per particle positions and velocities (float64 [n, 3] each), mass and
# radius (float64) and the pin flag (bool); per spring its pair (int64 [2]) and ke, kd, rest length (float64);
# per hinge its four particles (int64) and ke, kd, rest angle; per triangle its corners (int32 [3]); per mesh
# vertex its particle index (int64) and UV (float64 [2]).
_BUILDER_PARTICLE = 24 + 24 + 8 + 8 + 1
_BUILDER_SPRING = 16 + 3 * 8
_BUILDER_HINGE = 32 + 3 * 8
_BUILDER_TRIANGLE = 12
_BUILDER_VERTEX = 8 + 16

# Host bytes per incidence entry (one per element and member: 2 per spring, 4 per hinge) that
# ``build_incidence`` holds at its peak: the entries' owner, element and local value (int64) before and
# after the sort's permutation, the permutation, and the slot and head-mask arrays (see its code);
# measured 64-68 bytes per entry, counted as 76 so that the estimate of finalize's peak stays above the measured
# one (at 66 a 256² grid measured 4 % above it under load; at 76: +1.1 % and +1.8 % for 256² and 512²).
_INCIDENCE_ENTRY = 76
# Host bytes per spring of laying gathered springs out by group (``springs.group_head``: each entry's owner, spring,
# other particle and group (int64), their sort and its reordered copies): NumPy's allocations peak at 185 B per
# spring (``tracemalloc``, 128² to 512² grids), counted as 200; beyond the pairs finalize holds, and with the head
# tables made twice (NumPy's, then Warp's copy).
_GROUPED_LAYOUT_PER_SPRING = 200


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes a model and a run of it need, by part (all in bytes [B]).

    Attributes:
        device: the Warp device the model lives on ("cpu", "cuda:0").
        cuda: whether that device is a CUDA GPU (else its arrays are host memory).
        particles: particles per world.
        worlds: worlds of the model.
        model: the model's arrays on the device (particles, springs, hinges, incidence tables, triangles, colliders,
            live inputs).
        states: the two states a Stepper (and so a Simulator) advances: positions, velocities, forces and times.
        integrator: the integrator's scratch states and solver buffers.
        guard: the run-time guard's record and partial sums.
        post_step: strain limiting's buffers and the contact stage's slot buffer (0 when they are off).
        writer: the USD writer's device buffers (vertex normals, the exported triangles).
        builder: host memory the builder's NumPy arrays hold (allocated already when ``finalize`` runs).
        finalize_host: host memory ``finalize`` holds at its peak beyond the builder's arrays (concatenated
            copies, the incidence tables' sort), freed when it returns.
        frame_host: host memory of writing one frame to USD (positions and normals read back, USD's arrays).
        run_host: host memory of a run's setup (the guard's energy scale, the advisor's bound), freed after it.
        self_contact: self-collision's device arrays and BVHs (:func:`self_contact_bytes`; 0 without it).
        warmup: the stepper's copies of what a step carries to the next (the guard's and the integrator's), held
            during its warm-up step before a capture and freed after it.
        audit: the substep audit's record of every substep's positions on the device (:func:`audit_bytes`; 0 when
            the run does not audit).
        audit_host: the substep audit's host memory after a frame (the record read back, the pair lists).
        setup: the guard's energy scale's device temporaries at a run's start (every element's energy of one family
            in float64 per world, ``families.element_energies``), freed before the warm-up: the peak holds the larger.
    """

    device: str
    cuda: bool
    particles: int
    worlds: int
    model: int
    states: int
    integrator: int
    guard: int
    post_step: int
    writer: int
    builder: int
    finalize_host: int
    frame_host: int
    run_host: int
    self_contact: int = 0
    warmup: int = 0
    audit: int = 0
    audit_host: int = 0
    setup: int = 0

    @property
    def device_bytes(self) -> int:
        """The device memory of a run at its peak [B]: the model and the run's buffers, and the stepper's warm-up
        copies."""
        return (self.model + self.self_contact + self.states + self.integrator + self.guard + self.post_step
                + self.writer + max(self.warmup, self.setup) + self.audit)

    @property
    def host_bytes(self) -> int:
        """Peak host memory [B] beyond the builder's arrays: finalize's or a run's, whichever is larger. On the
        CPU the device arrays are host memory and are included."""
        on_host = 0 if self.cuda else 1
        finalize_peak = self.finalize_host + on_host * (self.model + self.self_contact)
        run_peak = max(self.frame_host, self.run_host, self.audit_host) + on_host * self.device_bytes
        return max(finalize_peak, run_peak)

    @property
    def finalize_peak(self) -> int:
        """Host memory [B] at the peak of building and finalizing: the builder's arrays, finalize's copies and (on
        the CPU) the model's arrays; what a process's peak resident memory grows by when it finalizes."""
        return self.builder + self.finalize_host + (0 if self.cuda else self.model + self.self_contact)

    def parts(self) -> dict:
        """The device parts by name [B], largest first, zero parts left out."""
        named = {"model": self.model, "self-collision": self.self_contact, "states": self.states,
                 "integrator": self.integrator, "guard": self.guard, "capture warm-up": self.warmup,
                 "stabilizers and contacts": self.post_step, "USD writer": self.writer,
                 "substep audit": self.audit}
        return dict(sorted(((k, v) for k, v in named.items() if v), key=lambda kv: -kv[1]))

    def describe(self) -> str:
        """One line: the device total with its parts, and the host peak."""
        parts = ", ".join(f"{name} {format_bytes(value)}" for name, value in self.parts().items())
        where = f"on {self.device}" if self.cuda else "of arrays"
        return (f"{format_bytes(self.device_bytes)} {where} ({parts}); peak host memory "
                f"{format_bytes(self.host_bytes)} beyond the builder's {format_bytes(self.builder)}")


@dataclass(frozen=True)
class AvailableMemory:
    """Memory free for a model, in bytes [B]; ``None`` where it cannot be known.

    Attributes:
        host: host memory available to this process (``MemAvailable`` of ``/proc/meminfo``, within a cgroup's
            limit), else free physical pages.
        device: free memory of the CUDA device (``wp.Device.free_memory``); ``None`` on the CPU.
        device_total: total memory of the CUDA device; ``None`` on the CPU.
    """

    host: int | None
    device: int | None = None
    device_total: int | None = None


def _mesh_cache_bytes(shapes: int, worlds: int, size: int, meshes: int, faces: int, candidates: int) -> int:
    """The mesh colliders' candidate cache (``mesh_colliders.make_mesh_cache``) [B]: slot, reach, margin and normal
    offset per collider; seven pseudo-normals per cached triangle; per cached mesh and state entry a reference
    position, a side, a count and C triangles; overflow and refresh counts per world. Without a cached mesh the
    per-particle arrays are one-entry placeholders."""
    meshes = checks.count("cached_meshes", meshes, minimum=0)
    faces = checks.count("mesh_faces", faces, minimum=0)
    candidates = checks.count("mesh_candidates", candidates, minimum=1) if meshes else 1
    rows, entries = (meshes, size) if meshes else (1, 1)
    return 16 * shapes + 12 * max(1, 7 * faces) + rows * entries * (12 + 4 + 4 + 4 * candidates) + 8 * worlds


#: Bytes per item of a Warp BVH's own native memory (``warp/native/bvh.cpp``, ``bvh.cu``), beyond its items' boxes
#: (which its caller owns): 2 n - 1 nodes of two 16-byte halves and a parent index, and a primitive index per item;
#: on CUDA (the LBVH builder) a refit count per node too. Its LBVH build on CUDA holds, until it returns, indices and
#: Morton keys doubled for the radix sort, deltas and three int32 arrays per node (52 bytes per item), and the sort's
#: own temporary storage (counted as 8 more).
BVH_NODE_BYTES = 36
BVH_NODE_BYTES_CUDA = 40
BVH_BUILD_TEMPORARY_CUDA = 60
#: Native bytes of a ``wp.Mesh`` per triangle beyond its points, velocities and indices (the caller's arrays): the
#: triangles' boxes (two vec3), its BVH, and with ``support_winding_number`` a 144-byte ``SolidAngleProps`` per BVH node
#: (2 per triangle); and per mesh or BVH its descriptors (a few hundred bytes, counted as 1 KiB).
MESH_BOX_BYTES = 24
MESH_WINDING_BYTES = 288
NATIVE_DESCRIPTOR_BYTES = 1024


def bvh_bytes(items: int, *, cuda: bool, building: bool = False) -> int:
    """The native memory of a Warp BVH over ``items`` boxes [B] (measured equal on the CPU through Warp's allocation
    tracker, ``tests/test_memory_native.py``); ``building``: with its CUDA build's temporaries."""
    items = checks.count("bvh items", items, minimum=0)
    if not items:
        return NATIVE_DESCRIPTOR_BYTES
    nodes = 2 * items - 1
    persistent = (BVH_NODE_BYTES_CUDA if cuda else BVH_NODE_BYTES) * nodes + 4 * items + NATIVE_DESCRIPTOR_BYTES
    return persistent + (BVH_BUILD_TEMPORARY_CUDA * items if cuda and building else 0)


def mesh_native_bytes(faces: int, *, winding_number: bool, cuda: bool) -> int:
    """The native memory of a ``wp.Mesh`` of ``faces`` triangles [B]: boxes, BVH (its CUDA build's temporaries
    included: a peak, conservatively counted as kept), winding-number tables."""
    faces = checks.count("mesh faces", faces, minimum=0)
    return (MESH_BOX_BYTES * faces + bvh_bytes(faces, cuda=cuda, building=True)
            + (MESH_WINDING_BYTES * faces if winding_number else 0))


def self_contact_bytes(*, particles: int, worlds: int, triangles: int, edges: int, surface_vertices: int,
                       precision: str = "float32", cuda: bool = False) -> int:
    """Device bytes of self-collision (``core/selfcontact.py``'s :class:`SelfContact`) [B], from its counts, before it
    is made: the surface's topology, each world's triangle boxes and BVH (with one CUDA build's temporaries), the live
    values, counters, the cache's reach, floor and nearest pair (and a scratch one), flags, scan blocks and the cap's
    roles and targets, the repelled positions and the cache's anchors, and the two pair buffers (the cache of ``CACHE_SLOTS`` × the cap's ``PAIRS_PER_VERTEX`` slots per surface vertex, each slot a key, four
    vertices, four CSR entries and a distance, with per-particle CSR counts, starts and cursors), and the cache's
    per-slot corrections and weights.

    Args:
        particles: particles per world; worlds: worlds of the model.
        triangles, edges, surface_vertices: the colliding surface's triangles, unique edges and vertices (per world).
        precision: the model's "float32" or "float64"; cuda: whether the device is a CUDA GPU.
    """
    n = checks.count("particles", particles, minimum=0)
    w = checks.count("worlds", worlds, minimum=1)
    t = checks.count("self-collision triangles", triangles, minimum=0)
    if not t:
        return 0
    e = checks.count("self-collision edges", edges, minimum=0)
    v = checks.count("self-collision vertices", surface_vertices, minimum=0)
    f = SCALAR_BYTES[precision]
    size = w * n
    capacity = max(64, PAIRS_PER_VERTEX * v)

    def pair_buffer(slots_per_world: int) -> int:  # key, four vertices, four entries, distance; CSR per particle
        slots = w * slots_per_world
        return (8 + 16 + 16 + f) * slots + 4 * (size + 1) * 2 + 4 * size + 4 * w

    surface = 48 * t + 12 * e + 4 * n + 24 * w * t + 8 * w
    live = ((PARAM_COUNT * f + 4 * COUNTER_COUNT + 2 * f + 2 * 4) * w + 4 * (2 + FLAG_KINDS * w)
            + 4 * w * -(-n // SCAN_BLOCK))
    live += 2 * (4 + 3 * f) * size  # the cap's roles and pushers' targets, twice
    patches = patch_count(t, cuda)
    live += (4 + (4 + 16) * capacity) * w + (4 + 4 + 16) * w  # the cache's watch list (tags, vertices), the empty one
    chunks = 3 * t // PATCH_CHUNK + patches + 1  # at most (the patches' corners: at most 3 per triangle)
    live += 4 * 3 * t + 4 * (2 * chunks + 1) + 4 * (PATCH_COLUMNS + 1) * w * patches  # the check's corners, chunks,
    live += 4 * t  # boxes and marks; each triangle's patch
    positions = 2 * 3 * f * size  # the repelled positions and the cache's anchors
    pairs = pair_buffer(CACHE_SLOTS * capacity) + pair_buffer(capacity) + 4 * w * CACHE_SLOTS * capacity * 4 * f
    bvhs = w * bvh_bytes(t, cuda=cuda) + (BVH_BUILD_TEMPORARY_CUDA * t if cuda else 0)
    return int(surface + live + positions + pairs + bvhs)


#: Host bytes per colliding triangle of making self-collision (``make_self_contact``): the surface's topology (its
#: sorted sides and their unique edges) and the smallest altitude's float64 corners and products; the peak of
#: NumPy's allocations (``tracemalloc``) measured 556-559 B for 128² and 256² cloths, counted as 600.
SELF_CONTACT_HOST_PER_TRIANGLE = 600
#: Host bytes per triangle of a mesh collider that finalize holds beyond the model's arrays (the points' float32
#: cast and float64 copy, the pseudo-normals' tables, the edge groups): the peak of NumPy's allocations measured
#: 243 B for a 977k-triangle sheet (the resident memory grows less: freed heap is reused), counted as 260.
MESH_FINALIZE_HOST_PER_FACE = 260
#: Host bytes per triangle the builder keeps of a mesh collider read from a file (its vertices and faces, the
#: reader's cached copy): measured 144 B (``tracemalloc``), counted as 160.
MESH_COLLIDER_KEPT_PER_FACE = 160


#: Host bytes per vertex of the audited surface that auditing a substep holds at its peak (``analysis/audit.py``,
#: :class:`~warpspring.analysis.audit.SurfaceAudit`): continuous collision detection (the surface's topology, IPC
#: Toolkit's collision mesh, the substep's ends in float64, the broad phase's candidate pairs: ~8.8 a vertex of a
#: cloth whatever its layering, the neighbours' boxes touching) measured 2.9 KB (two stacked 120² sheets, the first
#: substep's peak of resident memory), counted as 4 KiB; and with a thickness, the collision set within it (the pairs'
#: lists and distances), measured 10.6 KB where the sheets lie within it (5.9 pairs closer than half of it a vertex)
#: and 0.25 KB where nothing does, counted as 16 KiB (the dense case).
AUDIT_MOTION_PER_VERTEX = 4 * 1024
AUDIT_NEAR_PER_VERTEX = 16 * 1024


def audit_bytes(*, particles: int, worlds: int, substeps: int, surface_vertices: int, thickness: bool,
                precision: str = "float32", cuda: bool = False) -> tuple[int, int]:
    """(device, host) bytes [B] of auditing every substep of a run (``warpspring run --audit-substeps``,
    :class:`~warpspring.analysis.audit.SubstepAudit`), before it is attached: on the device the record of every
    substep's positions (substeps + 1 states); on the host after each frame the record read back (a copy on CUDA)
    and as float64, and a substep's audit of the surface (:data:`AUDIT_MOTION_PER_VERTEX`, and with a thickness
    :data:`AUDIT_NEAR_PER_VERTEX`).

    Args:
        particles: particles per world; worlds: worlds of the model; substeps: substeps per frame.
        surface_vertices: vertices of the audited surface (the self-collision's, else the model's triangles').
        thickness: whether the audit measures the pairs within a thickness (given, or the self-collision's).
        precision: the model's "float32" or "float64"; cuda: whether the device is a CUDA GPU.
    """
    size = checks.count("particles", particles, minimum=0) * checks.count("worlds", worlds, minimum=1)
    states = checks.count("substeps", substeps, minimum=1) + 1
    vec3 = 3 * SCALAR_BYTES[precision]
    record = states * size * vec3
    per_vertex = AUDIT_MOTION_PER_VERTEX + (AUDIT_NEAR_PER_VERTEX if thickness else 0)
    host = states * size * (24 + (vec3 if cuda else 0)) + per_vertex * checks.count("surface vertices",
                                                                                     surface_vertices, minimum=0)
    return record, host


#: What the guard allocates for each integrator beyond its fixed buffers, by the rules of ``core/guards.py`` (with its
#: default limits: the energy balance and the dissipation on), read from ``core/guard_records.py``'s integrator lists
#: and the integrators' ``adaptive`` and ``unconditionally_stable`` (``tests/test_memory.py`` checks both): (the
#: dissipation counted, at each substep's midpoint state, the work of wind and handles counted, the scattered springs'
#: dampers counted in their force pass, how the integrator's force pass counts the power: "mean" over the step,
#: "start" of the step, "" not at all).
#:
#: * symplectic Euler: everything, its D at the midpoint, its fused pass the step's mean power;
#: * velocity Verlet: D and work by passes of their own, the springs' dampers in their scattered pass;
#: * explicit Euler: neither D nor work (``DISSIPATION_UNCOUNTED``, ``WORK_UNCOUNTED``); midpoint: work only;
#: * RK4: D, work, the dampers in the scattered pass, the power at each step's start in its evaluation;
#: * dopri5 (adaptive) and implicit Euler (unconditionally stable, no balance): nothing.
GUARD_RULES = {
    "symplectic_euler": (True, True, True, True, "mean"),
    "velocity_verlet": (True, False, True, True, ""),
    "explicit_euler": (False, False, False, False, ""),
    "midpoint": (False, False, True, False, ""),
    "rk4": (True, False, True, True, "start"),
    "dopri5": (False, False, False, False, ""),
    "implicit_euler": (False, False, False, False, ""),
}


@dataclass(frozen=True)
class GuardPath:
    """What the run-time guard allocates beyond its fixed buffers, for a run's integrator and model
    (:func:`guard_path`).

    Attributes:
        midpoint: a substep's midpoint state (positions, velocities, each world's time).
        dampers: the scattered springs' damper sums (a rate and the float64 energy per spring, a flag per world).
        power: scalars per particle of the power sums the integrator's force pass adds to (0: none; 1: the energy
            the dampers and drag take out; 2: with the work of the loads from outside).
        stored_forces: the dampers' and loads' parts of the force per particle (two vec3 arrays), stored by the
            force passes of symplectic Euler on scattered springs for its update.
    """

    midpoint: bool
    dampers: bool
    power: int
    stored_forces: bool


def guard_path(*, integrator: str, springs: int, gathered: bool, drag: bool = False, wind: bool = False,
               working: bool = False, exact: bool = True, spring_force_clamp: bool = False, plastic: bool = False,
               particle_force_clamp: bool = False) -> GuardPath:
    """The guard's path for a run with the default limits (``core/guards.py``: ``Guard.limits``,
    ``_force_pass_dampers``, ``_power_rule``, ``_power_modes``), from the integrator's name and the model's features.

    Args:
        integrator: the integrator's name (:data:`GUARD_RULES`).
        springs: springs per world; gathered: whether they are gathered per particle (else scattered).
        drag: viscous drag on; wind: a family moves the air; working: a family does work from outside (wind, handles).
        exact: no stage moves particles outside the forces (no collider, self-collision or strain limiting: the
            guard's ``dissipation_exact``).
        spring_force_clamp, plastic: the springs' force clamp, plastic springs (their dampers' part not separable).
        particle_force_clamp: the particle force clamp (the power not counted in the force pass).
    """
    dissipation, midpoint, work, dampers_in_pass, rule = GUARD_RULES[integrator]
    working = work and working  # the wind's and handles' work counted per substep
    dampers = (dissipation and dampers_in_pass and exact and springs > 0 and not gathered
               and not (spring_force_clamp or plastic))
    if particle_force_clamp or (rule == "mean" and springs and not gathered and not (drag or working)):
        rule = ""  # scattered springs count their dampers in their own pass: the update counts only drag and work
    # The power sums carry the work done besides the energy taken out where a family's work or drag in wind counts.
    power = (2 if working or (drag and wind) else 1) if rule else 0
    return GuardPath(midpoint=(dissipation and midpoint) or working, dampers=dampers, power=power,
                     stored_forces=rule == "mean" and springs > 0 and not gathered)


def estimate_memory(
    *,
    particles: int,
    springs: int = 0,
    hinges: int = 0,
    triangles: int = 0,
    colliders: int = 0,
    worlds: int = 1,
    precision: str = "float32",
    device: str = "cpu",
    spring_evaluation: str = "auto",
    spring_groups: int | None = None,
    spring_grid: bool = True,
    spring_group_slots: int | None = None,
    integrator: str = "symplectic_euler",
    spring_slots: int | None = None,
    spring_tail: int = 0,
    hinge_slots: int | None = None,
    hinge_tail: int = 0,
    pinned: int = 0,
    mesh_vertices: int | None = None,
    strain_limiting: bool = False,
    contact_slots: int = 0,
    moving_colliders: bool = False,
    exported_worlds: int | None = None,
    block_dim: int = 256,
    family_bytes: int = 0,
    cached_meshes: int = 0,
    mesh_faces: int = 0,
    mesh_candidates: int = 1,
    mesh_bytes: int = 0,
    self_contact_triangles: int = 0,
    self_contact_edges: int | None = None,
    self_contact_vertices: int | None = None,
    collider_faces: int = 0,
    emitter_slots: int = 0,
    drag: bool = False,
    wind: bool = False,
    working_families: bool = False,
    spring_force_clamp: bool = False,
    particle_force_clamp: bool = False,
    plastic_springs: int = 0,
    spring_law_arrays: bool = False,
    family_elements: tuple = (),
    audit_substeps: int = 0,
    audit_thickness: bool | None = None,
) -> MemoryEstimate:
    """Estimate the memory of a model and of a run of it, from counts, before anything is allocated.

    Args:
        particles: particles per world.
        springs, hinges, triangles, colliders: elements per world (shared by the worlds).
        worlds: worlds of the model.
        precision: "float32" or "float64".
        spring_evaluation: as :meth:`ModelBuilder.finalize`'s: "auto" and "gather" gather the springs per particle,
            "scatter" scatters them per spring (the guard's damper sums then count).
        spring_groups: groups of gathered springs laid out by group (``springs.set_spring_layout``: each keeps one
            spring's index on the device; default 3, a cloth's structural, shear and bend springs; 0: not grouped).
        spring_grid: whether that layout reads the springs as one cloth grid (its size, two int32, on the device).
        spring_group_slots: that layout's head width, each group's largest degree at one particle summed (default
            ``spring_slots``: the groups of a cloth grid fill the per-spring head's width exactly).
        device: the Warp device name ("cpu", "cuda:0", ...); only whether it is CUDA matters.
        integrator: the integrator's name (:data:`INTEGRATOR_SCRATCH`).
        spring_slots, hinge_slots: ELL head widths of the incidence tables; default the mean number of elements
            per particle, rounded up (exact for a uniform degree, as a cloth grid's:
            :meth:`ModelBuilder.estimate_memory` computes the exact widths).
        spring_tail, hinge_tail: entries beyond the head (the CSR tail) of each table.
        pinned: kinematic particles in pin groups (0 when the model has no pin group).
        mesh_vertices: particles that belong to triangle meshes (default: every particle when there are triangles).
        strain_limiting: whether ``Stabilizers.max_strain`` is on (three more position buffers).
        contact_slots: slots per particle of the contact stage's buffer (0: no contact stage).
        moving_colliders: whether a collider moves (keyframe tracks): the colliders' frames are then per world.
        exported_worlds: worlds the USD writer exports (default: every world).
        block_dim: CUDA threads per reducing block (the partial sums' count); the CPU reduces per particle.
        family_bytes: the device arrays of the element families beyond springs and hinges (wind, handles: each
            family's ``ElementFamily.device_bytes``) [B].
        cached_meshes: mesh colliders with a candidate cache (every mesh not signed by its winding number).
        mesh_faces: the triangles of those meshes, in all (seven pseudo-normals each).
        mesh_candidates: the largest ``cache_candidates`` among them (C: the cache's triangles per particle).
        mesh_bytes: the mesh colliders' own device memory (points, velocities, triangles, the cached meshes'
            pseudo-normal tables, and each ``wp.Mesh``'s native boxes, BVH and winding-number tables,
            :func:`mesh_native_bytes`: ``ModelBuilder.estimate_memory`` counts them from the meshes) [B].
        self_contact_triangles: triangles of the self-colliding surface (0: no self-collision).
        self_contact_edges, self_contact_vertices: its unique edges and vertices (default the upper bounds 3 × its
            triangles and every particle; ``ModelBuilder.estimate_memory`` counts them exactly).
        collider_faces: the triangles of every mesh collider (the builder's copies, their host temporaries in
            finalize).
        emitter_slots: the particles of every emitter's pool (a run carries their slots from step to step).
        drag, wind, working_families, spring_force_clamp, particle_force_clamp: what decides the guard's path
            (:func:`guard_path`): viscous drag on, a family that moves the air (wind), a family that does work from
            outside (wind, handles), the springs' force clamp (``Stabilizers.max_spring_force``), the particle force
            clamp.
        plastic_springs: springs that may yield or break (``add_springs(plasticity=...)``): with any, every spring
            has its yield parameters and each world its rest lengths and plastic strains (which the stepper's
            warm-up copies too); and the guard's path changes.
        spring_law_arrays: whether some spring follows the square law or has a compression stiffness of its own (a
            law code and a compression ratio per spring).
        audit_substeps: substeps per frame of a run that audits every substep (:func:`audit_bytes`; 0: none): the
            audited surface is the self-collision's (``self_contact_vertices``), else the meshes' (``mesh_vertices``).
        audit_thickness: whether that audit measures the pairs within a thickness (default: with self-collision,
            whose thickness it takes).
        family_elements: the elements per world of each family beyond springs and hinges (wind's triangles, handles'
            particles, tets): the guard sums their elastic energy and strain per reducing block.

    Returns:
        The :class:`MemoryEstimate`.

    Raises:
        ConfigError: a negative count, an unknown precision or integrator.
    """
    n = checks.count("particles", particles, minimum=0)
    s = checks.count("springs", springs, minimum=0)
    h = checks.count("hinges", hinges, minimum=0)
    t = checks.count("triangles", triangles, minimum=0)
    shapes = checks.count("colliders", colliders, minimum=0)
    w = checks.count("worlds", worlds, minimum=1)
    pinned = checks.count("pinned", pinned, minimum=0)
    collider_faces = checks.count("collider_faces", collider_faces, minimum=0)
    plastic = checks.count("plastic_springs", plastic_springs, minimum=0)
    if precision not in SCALAR_BYTES:
        raise ConfigError(f"precision must be 'float32' or 'float64', got {precision!r}")
    if spring_evaluation not in ("auto", "gather", "scatter"):
        raise ConfigError(f"spring_evaluation must be 'auto', 'gather' or 'scatter', got {spring_evaluation!r}")
    if integrator not in INTEGRATOR_SCRATCH:
        raise ConfigError(f"unknown integrator {integrator!r}: choose one of {', '.join(sorted(INTEGRATOR_SCRATCH))}")
    f = SCALAR_BYTES[precision]
    vec3 = 3 * f
    cuda = str(device).startswith("cuda")
    groups = 3 if spring_groups is None else checks.count("spring_groups", spring_groups, minimum=0)
    grouped = bool(s and groups and spring_evaluation != "scatter")  # gathered springs laid out by group
    size = w * n  # entries of a state's per-particle arrays
    spring_slots = _mean_degree(2 * s, n) if spring_slots is None else checks.count("spring_slots", spring_slots,
                                                                                   minimum=0)
    group_slots = spring_slots if spring_group_slots is None else checks.count("spring_group_slots",
                                                                               spring_group_slots, minimum=0)
    hinge_slots = _mean_degree(4 * h, n) if hinge_slots is None else checks.count("hinge_slots", hinge_slots, minimum=0)
    vertices = (n if t else 0) if mesh_vertices is None else checks.count("mesh_vertices", mesh_vertices, minimum=0)
    exported = w if exported_worlds is None else checks.count("exported_worlds", exported_worlds, minimum=1)
    blocks = w * (n if not cuda else -(-n // _lanes(n, block_dim)))  # reducing blocks of every world

    def incidence(slots: int, tail: int) -> int:  # head element and local [slots, n], tail start [n + 1], tail
        return 8 * slots * n + 4 * (n + 1) + 8 * tail

    model = (
        4 * w + INPUT_COUNT * f * w + 8 + 4  # world_enabled, the live-input table, unit_step, an empty track table
        + 2 * vec3 * size + 4 * size  # initial positions and velocities, flags: per world
        + 3 * f * n  # mass, inverse mass (one row for every world), radius
        + (32 * pinned + 4 * n if pinned else 0)  # pin groups: index, group, rest position (float64) per pinned
        #   particle, and each particle's entry among them
        + (8 + 3 * f) * s  # pairs, rest length, ke and kd rows
        + (incidence(group_slots, 0) if grouped else incidence(spring_slots, spring_tail))
        + ((4 * groups + (8 if spring_grid else 0)) if grouped else 0)  # each group's spring, the grid's size
        + ((4 + f) * s if spring_law_arrays else 0)  # each spring's law code and compression ratio
        # plastic springs: their indices; each spring's five yield parameters, and per world and spring its rest
        # length and plastic strain
        + ((4 * plastic + (5 + 2 * w) * f * s) if plastic else 0)
        + (16 + 3 * f) * h + incidence(hinge_slots, hinge_tail)  # hinges, rest angle, ke and kd rows
        + 12 * t  # triangles
        # colliders: kind, size, scale, friction, restitution, mesh, rest frame, track indices; their frames at a
        # step's start and end in one row, or one row per world when a collider moves
        + shapes * (4 + 8 * f + 8 + 56 + 8) + 14 * f * shapes * (w if moving_colliders else 1)
        + 36 * shapes  # thickness, static friction, sides, and the bounds (lower, upper) of each collider
        + checks.count("family_bytes", family_bytes, minimum=0)
        + _mesh_cache_bytes(shapes, w, size, cached_meshes, mesh_faces, mesh_candidates)
        + checks.count("mesh_bytes", mesh_bytes, minimum=0)
    )
    states = 2 * (3 * vec3 * size + 8 * w)
    per_vec3, per_scalar, per_block, per_world_f64, per_world_i32 = INTEGRATOR_SCRATCH[integrator]
    scratch = per_vec3 * vec3 * size + per_scalar * f * size + 8 * per_block * blocks + 8 * per_world_f64 * w
    scratch += 4 * per_world_i32 * w + (4 if integrator in ("dopri5", "implicit_euler") else 0)
    if integrator == "implicit_euler":
        scratch += 16 + 8 * CG_SHORT_SLOTS * w  # the CG settings; each world's solves stopped at the cap, worst residual
    # The guard: its records (and their clear copies), partial sums per block, limits, each world's work put in
    # and energy balance, the positions, velocities and loads of its last check, and the elastic energy's partial
    # sums per block of each family's elements, and the running dissipation of those blocks and the particles'
    # blocks; and what it allocates for the path the run takes (:func:`guard_path`): a substep's midpoint state,
    # the scattered springs' damper sums, the power sums it hands the integrator and the force parts they store.
    def element_blocks(count: int, per_lane: int = 1, fill: int = 0) -> int:
        return w * (count if not cuda else reduce_launch_dim(w, count, _lanes(count, block_dim), per_lane, fill)[1])

    def check_blocks_of(count: int) -> int:
        """The blocks of a check's striding pass (``reduce_launch_dim``: up to REDUCE_PER_LANE items a lane on CUDA,
        one thread per world on the CPU); the dissipation's passes do not stride."""
        if not cuda:
            return w if count else 0
        return element_blocks(count, REDUCE_PER_LANE, REDUCE_FILL_BLOCKS)

    check_blocks = check_blocks_of(n)

    path = guard_path(integrator=integrator, springs=s, gathered=spring_evaluation != "scatter", drag=drag,
                      wind=wind, working=working_families, exact=not (shapes or self_contact_triangles
                                                                       or strain_limiting),
                      spring_force_clamp=spring_force_clamp, plastic=plastic > 0,
                      particle_force_clamp=particle_force_clamp)
    others = [checks.count("family_elements", e, minimum=0) for e in family_elements]
    by_elements = sum(check_blocks_of(e) for e in (s, h, *others))
    # On CUDA gathered springs' energy is walked by particles, over the check's grid (``Guard._walks``).
    walked = cuda and s > 0 and spring_evaluation != "scatter" and ENERGY_BY_PARTICLES[True]
    energy_blocks = by_elements - check_blocks_of(s) + check_blocks if walked else by_elements
    # With self-collision, the blocks that count the energy its pass puts in: the check's grids of the particles and
    # of each family's elements (``Guard._count_corrections``).
    corrections = check_blocks + by_elements if self_contact_triangles else 0
    running_rows = blocks + element_blocks(s) + element_blocks(h) + corrections  # (CUDA) particles', dampers' blocks
    running = 8 * RUNNING_SLOTS * (running_rows if cuda else w * (1 + bool(s) + bool(h)) + corrections)
    dampers = (4 + (f + 8) * s) * w if path.dampers else 0
    power = path.power * f * size  # the power sums the guard hands the integrator (energy out[, work in])
    carried = (8 * w + 8 * BALANCE_SLOTS * w + 3 * vec3 * size + running + dampers + power  # what a check carries on,
               + 8 * CARRY_SLOTS * w)  # each world's share of the closing term among it
    # The check's fold on CUDA, where a world's partial sums are more than FOLD_ABOVE: the
    # partials, energy, strain, power and running sums of each chunk of FOLD_CHUNK of them (``Guard._fold``).
    most = max(check_blocks, energy_blocks, running_rows) // max(w, 1)
    folds = cuda and most > FOLD_ABOVE
    fold = w * -(-most // FOLD_CHUNK) * 8 * (PARTIAL_SLOTS + 3 + RUNNING_SLOTS) if folds else 0
    guard = (2 * (4 * GUARD_INTS + 8 * GUARD_FLOATS) * w + 8 * PARTIAL_SLOTS * check_blocks + 8 * GUARD_LIMITS * w
             + fold
             + 3 * 8 * max(energy_blocks, w)  # every family's energy, strain and dampers' power partial sums
             + (0 if cuda else 8 * MIRROR_COLUMNS * w)  # the record's mirror (pinned host memory on CUDA)
             + carried + (2 * vec3 * size + 8 * w if path.midpoint else 0)
             + (2 * vec3 * size if path.stored_forces else 0)
             # the one-launch frame's check: its partial sums, one per block of the frame (at most one per 32
             # particles on CUDA, one on the CPU), and the families' element counts
             + 8 * (PARTIAL_SLOTS + 3) * w * (-(-max(n, 1) // 32) if cuda else 1)
             + 4 * max(bool(s) + bool(h) + len(others), 1))
    # The stepper's warm-up before a capture copies what a step carries to the next (the guard's sums and record, the
    # integrator's per-world state and implicit Euler's Δv, the emitters' flags and slots, the plastic springs' rest
    # lengths and strains, the contact, self-collision and mesh caches' counters), and frees the copies once the
    # warm-up step is undone.
    slots = checks.count("emitter_slots", emitter_slots, minimum=0)
    warmup = (carried + (4 * GUARD_INTS + 8 * GUARD_FLOATS) * w  # with the guard's record
              + 8 * per_world_f64 * w + 4 * per_world_i32 * w + 64 * w
              + (vec3 * size if integrator == "implicit_euler" else 0)
              + ((4 * size + (12 * slots + 32) * w) if slots else 0)
              + (2 * f * w * s if plastic else 0))
    post_step = (3 * vec3 * size if strain_limiting and s else 0)
    if contact_slots:
        post_step += (8 * contact_slots + 4) * size + 4 * w + f  # colliders and features per slot, counts, overflow
    writer = (12 * size + 12 * t * exported) if t else 0  # vertex normals (float32) and the exported triangles

    builder = (_BUILDER_PARTICLE * n + _BUILDER_SPRING * s + _BUILDER_HINGE * h + _BUILDER_TRIANGLE * t
               + _BUILDER_VERTEX * vertices + MESH_COLLIDER_KEPT_PER_FACE * collider_faces)
    # finalize: the concatenated pairs (int64) stay for the whole call; each family's incidence sort peaks at
    # _INCIDENCE_ENTRY per entry plus its head tables (int32); the particles' copies (float64 and cast) come first.
    springs_peak = 16 * s + _INCIDENCE_ENTRY * 2 * s + 8 * spring_slots * n
    if grouped:  # then the layout by group, after the incidence's sort
        springs_peak = max(springs_peak, 16 * s + _GROUPED_LAYOUT_PER_SPRING * s + 2 * 8 * group_slots * n)
    hinges_peak = 16 * s + 32 * h + _INCIDENCE_ENTRY * 4 * h + 8 * hinge_slots * n
    particles_peak = 24 * n + (24 + vec3) * size
    # Self-collision is made last, its host temporaries after the others are freed.
    self_t = checks.count("self_contact_triangles", self_contact_triangles, minimum=0)
    self_e = 3 * self_t if self_contact_edges is None else self_contact_edges
    self_v = n if self_contact_vertices is None else self_contact_vertices
    self_contact = self_contact_bytes(particles=n, worlds=w, triangles=self_t, edges=self_e, surface_vertices=self_v,
                                      precision=precision, cuda=cuda)
    finalize_host = (max(springs_peak, hinges_peak, particles_peak, SELF_CONTACT_HOST_PER_TRIANGLE * self_t)
                     + MESH_FINALIZE_HOST_PER_FACE * collider_faces)
    # A frame: positions read back (a copy on CUDA) and cast to float32, normals read back, and per exported mesh
    # vertex its points and normals gathered, then copied into USD arrays.
    frame_host = (vec3 * size if cuda else 0) + 12 * size + (12 * size if t else 0) + 48 * vertices * exported
    # Setup: the guard's energy scale reads positions and velocities as float64 and sums element energies
    # (float64 per element and world); the advisor's Gershgorin bound bincounts each spring's ends per world.
    run_host = 48 * size + 8 * w * (s + h) + (40 * w * s + 8 * size if s else 0)
    audit, audit_host = (audit_bytes(particles=n, worlds=w, substeps=audit_substeps,
                                     surface_vertices=self_v if self_t else vertices, precision=precision, cuda=cuda,
                                     thickness=bool(self_t) if audit_thickness is None else audit_thickness)
                         if checks.count("audit_substeps", audit_substeps, minimum=0) else (0, 0))
    return MemoryEstimate(
        device=str(device), cuda=cuda, particles=n, worlds=w, model=int(model), states=int(states),
        integrator=int(scratch), guard=int(guard), post_step=int(post_step), writer=int(writer),
        builder=int(builder), finalize_host=int(finalize_host), frame_host=int(frame_host), run_host=int(run_host),
        self_contact=int(self_contact), warmup=int(warmup), audit=int(audit), audit_host=int(audit_host),
        setup=8 * w * max([s, h, *others]),
    )


def _mean_degree(entries: int, n: int) -> int:
    """Elements per particle, rounded up: the ELL head width of a uniform degree."""
    return -(-entries // n) if n else 0


def _lanes(count: int, block_dim: int) -> int:
    """Lanes per reducing block on CUDA (``kernels.linalg.reduce_lanes``)."""
    return int(min(block_dim, max(32, 1 << max(count - 1, 1).bit_length())))


# -- what is free --------------------------------------------------------------------------------------------


def available_memory(device=None) -> AvailableMemory:
    """The memory free for a model on ``device`` (a ``wp.Device``; ``None``: the host's only, without touching
    Warp): the host's, and the CUDA device's.

    Tests replace this function (``monkeypatch.setattr(warpspring.core.memory, "available_memory", ...)``) to
    stand for a smaller machine; :meth:`ModelBuilder.finalize` looks it up here at every call.
    """
    host = host_available_memory()
    if getattr(device, "is_cuda", False):
        return AvailableMemory(host=host, device=int(device.free_memory), device_total=int(device.total_memory))
    return AvailableMemory(host=host)


#: Environment variable capping the host memory warpspring counts as available (bytes, or with a unit:
#: "8GiB", "512MiB"): a process sharing a machine, or a watchdog's limit, tells the checks what it may use.
MEMORY_LIMIT_VARIABLE = "WARPSPRING_MEMORY_LIMIT"
_UNITS = {"": 1, "B": 1, "KIB": 2**10, "MIB": 2**20, "GIB": 2**30, "TIB": 2**40, "KB": 10**3, "MB": 10**6, "GB": 10**9,
          "TB": 10**12, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def parse_bytes(text: str, *, name: str = MEMORY_LIMIT_VARIABLE) -> int:
    """A byte count from "123", "8GiB", "1.5 GB", "512M" (binary units for K/M/G/T alone)."""
    match = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*([A-Za-z]*)\s*", str(text))
    unit = match.group(2).upper() if match else None
    if not match or unit not in _UNITS:
        raise ConfigError(f"{name} must be a number of bytes, optionally with a unit (e.g. 8GiB, 512MiB), got {text!r}")
    return int(float(match.group(1)) * _UNITS[unit])


def _process_limit() -> int | None:
    """What this process may still take [B] by its own limits: :data:`MEMORY_LIMIT_VARIABLE` less its resident
    memory, and the address-space limit (``RLIMIT_AS``) less its virtual size; ``None`` without either."""
    limits = []
    text = os.environ.get(MEMORY_LIMIT_VARIABLE, "").strip()
    if text:
        limits.append(parse_bytes(text) - (_status_bytes("VmRSS") or 0))
    try:
        import resource  # optional: POSIX only

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            limits.append(soft - (_status_bytes("VmSize") or 0))
    except (ImportError, OSError, ValueError):
        pass
    return max(min(limits), 0) if limits else None


def _status_bytes(key: str) -> int | None:
    """A memory figure of this process from ``/proc/self/status`` [B] (VmRSS, VmSize, VmHWM); ``None`` off Linux."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def host_available_memory() -> int | None:
    """Host memory available to this process [B]: ``MemAvailable`` (Linux), capped by the cgroup's memory
    limit less its usage where a container sets one, and by the process's own limits (:data:`MEMORY_LIMIT_VARIABLE`,
    ``RLIMIT_AS``); elsewhere the free physical pages; ``None`` if unknown."""
    machine = _machine_available_memory()
    limit = _process_limit()
    if limit is None:
        return machine
    return limit if machine is None else min(machine, limit)


def _machine_available_memory() -> int | None:
    """``MemAvailable`` within a cgroup's limit, else the free physical pages [B]."""
    available = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        available = None
    if available is None:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (AttributeError, ValueError, OSError):
            return None
    for limit_path, usage_path in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            with open(limit_path) as f:
                limit = f.read().strip()
            with open(usage_path) as f:
                usage = int(f.read().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 2**60:  # "max" or a huge number: no limit
            available = min(available, max(int(limit) - usage, 0))
        break
    return int(available)


# -- the check -----------------------------------------------------------------------------------------------


def check_host_room(what: str, needed: int, *, remedy: str) -> None:
    """Refuse, before it is made, something that needs ``needed`` bytes of host memory [B] when less is
    available (:func:`available_memory`): one line naming ``what``, the estimate, what is available and ``remedy``.
    An unknown amount is not checked."""
    available = available_memory(None).host
    if available is not None and needed > available:
        raise ConfigError(f"{what} needs an estimated {format_bytes(needed)} of host memory, but "
                          f"{format_bytes(available)} is available: {remedy}")


def check_device_room(what: str, needed: int, device, *, remedy: str) -> None:
    """Refuse, before it is made, something that needs ``needed`` bytes [B] of ``device`` (a ``wp.Device``): on a CUDA
    device against its free memory, on the CPU against the host's available memory (:func:`check_host_room`). One
    line naming ``what``, the estimate, what is free and ``remedy``; an unknown amount is not checked."""
    if not getattr(device, "is_cuda", False):
        check_host_room(what, needed, remedy=remedy)
        return
    free = available_memory(device).device
    if free is not None and needed > free:
        raise ConfigError(f"{what} needs an estimated {format_bytes(needed)} on {device}, but {format_bytes(free)} is "
                          f"free: {remedy}")


def check_fits(estimate: MemoryEstimate, available: AvailableMemory, *, precision: str = "float32") -> None:
    """Refuse a model that cannot fit: a ConfigError naming the estimate, what is available and a remedy.

    The device part is compared with the CUDA device's free memory; the host peak (on the CPU, device arrays
    included) with the host's available memory. Unknown amounts are not checked.
    """
    shortfalls = []
    if estimate.cuda and available.device is not None and estimate.device_bytes > available.device:
        total = f" of {format_bytes(available.device_total)}" if available.device_total else ""
        shortfalls.append((estimate.device_bytes / max(available.device, 1),
                           f"{format_bytes(estimate.device_bytes)} on {estimate.device} "
                           f"({_parts(estimate)}) but {format_bytes(available.device)}{total} is free"))
    if available.host is not None and estimate.host_bytes > available.host:
        shortfalls.append((estimate.host_bytes / max(available.host, 1),
                           f"{format_bytes(estimate.host_bytes)} of host memory at its peak ("
                           + ("" if estimate.cuda else f"arrays: {_parts(estimate)}; ")
                           + f"finalize's copies {format_bytes(estimate.finalize_host)}) but "
                           f"{format_bytes(available.host)} is available"))
    if not shortfalls:
        return
    ratio = max(r for r, _ in shortfalls)
    raise ConfigError(f"the model does not fit in memory: it needs an estimated {'; and '.join(m for _, m in shortfalls)}. "
                      + remedy(estimate, ratio, precision=precision))


def remedy(estimate: MemoryEstimate, ratio: float, *, precision: str = "float32") -> str:
    """What to change so that a model ``ratio`` times too large fits: fewer particles (a smaller grid side),
    float32, fewer worlds."""
    share = 1.0 / (ratio * 1.05)  # memory grows with the particle count; 5 % to spare
    fewer = max(int(estimate.particles * share), 1)
    side = int(math.isqrt(fewer))
    advice = [f"a smaller cloth (at most about {fewer:,} particles per world, e.g. a {side} × {side} grid)"]
    if precision == "float64":
        advice.append("precision='float32' (half the floating-point arrays)")
    if estimate.worlds > 1:
        advice.append(f"fewer worlds (about {max(int(estimate.worlds * share), 1)} fit)")
    if estimate.self_contact > estimate.device_bytes / 2:
        advice.insert(0, "self-collision on fewer or coarser meshes (add_self_collision(meshes=[...]): it holds "
                         f"{format_bytes(estimate.self_contact)} here)")
    return "Use " + ", or ".join(advice) + "."


def _parts(estimate: MemoryEstimate) -> str:
    return ", ".join(f"{name} {format_bytes(value)}" for name, value in estimate.parts().items())


def format_bytes(count: float | None) -> str:
    """A byte count in binary units: "512 B", "3.2 MiB", "15.1 GiB"."""
    if count is None:
        return "an unknown amount"
    value = float(count)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(value) < 1024.0 or unit == "GiB":
            break
        value /= 1024.0
    if unit == "GiB" and abs(value) >= 1024.0:
        return f"{value / 1024.0:.3g} TiB"
    return f"{value:.0f} {unit}" if unit == "B" else f"{value:.3g} {unit}"


def out_of_memory(error: BaseException) -> bool:
    """Whether ``error`` is Warp's failed allocation (a RuntimeError "Failed to allocate N bytes on device ...")."""
    return isinstance(error, (RuntimeError, MemoryError)) and (
        isinstance(error, MemoryError) or "Failed to allocate" in str(error) or "out of memory" in str(error).lower()
    )
