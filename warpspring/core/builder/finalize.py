"""The builder's last step: :meth:`Finalization.finalize` copies the scene to a device as a Model, after
:meth:`Finalization.estimate_memory` has checked that it fits; the spring groups' laws and plasticity on the
model; and one world's per-world rows (:meth:`Finalization.world_rows`) for sweeps."""

from __future__ import annotations

import numpy as np
import warp as wp

from ... import checks
from ...errors import ConfigError
from ...kernels.families import MAX_HEAD_SLOTS
from ...kernels.kinematics import PARTICLE_KINEMATIC
from ...kernels.precision import scalar_type, vec3_type
from ...kernels.spring_laws import SpringLaw
from .. import memory
from ..families import build_incidence, head_slots
from ..kinematics import PinGroupTable
from ..model import Model
from ..selfcontact import make_self_contact
from ..springs import SPRING_LAWS, set_spring_layout
from .colliders import _mesh_collider_bytes


class Finalization:
    """:meth:`finalize` and :meth:`estimate_memory` of :class:`~warpspring.core.builder.ModelBuilder` (a mixin: it
    reads everything the builder collected)."""

    def world_rows(self) -> dict[str, np.ndarray]:
        """The per-world parameters this builder gives one world, as ``Model.set_world_values`` takes them
        (float64, in the order ``finalize`` stores them): ``spring_stiffness`` [N/m] and ``spring_damping``
        [N·s/m], shape [spring_count]; ``particle_mass`` [kg], shape [particle_count]. A sweep builds each
        variant's builder on the host and gives its rows to one world of a shared model."""
        def joined(blocks):
            return np.concatenate(blocks).astype(np.float64) if blocks else np.zeros(0)

        return {"spring_stiffness": joined(self._spring_ke), "spring_damping": joined(self._spring_kd),
                "particle_mass": joined(self._mass)}

    def finalize(self, device=None, *, precision: str = "float32", spring_evaluation: str = "auto",
                 worlds: int = 1, contact_stage: bool | None = None, contact_slots: int | None = None,
                 integrator: str = "symplectic_euler", check_memory: bool = True, spring_groups: bool = True,
                 spring_grid: bool = True, contact_triangles: bool | None = None) -> Model:
        """Copy the scene to ``device`` as a :class:`Model`.

        Before it allocates anything, finalize estimates the memory of the model and of a run of it
        (:meth:`estimate_memory`) and refuses, with a :class:`~warpspring.ConfigError` naming the estimate, what is
        free and a remedy, a model that cannot fit: on a CUDA device its arrays against the device's free memory,
        and the host's peak (on the CPU, the arrays too) against the available host memory. A failed device
        allocation becomes the same error.

        Args:
            device: Warp device ("cpu", "cuda:0", ...); default Warp's default device.
            worlds: independent copies of the scene in the model, stepped together in every launch and never
                coupled (a batch of environments, a parameter sweep). Each starts as this builder's scene;
                give them their own parameters with :meth:`Model.set_world_values` and
                :meth:`Model.set_track`.
            precision: "float32" (default) or "float64" for every floating-point array and kernel.
            spring_evaluation: "gather" (per particle, no atomics, fusable, any number of springs per particle),
                "scatter" (per spring, each evaluated once, atomic adds: deterministic only on the CPU) or
                "auto": gather, the faster on each device as measured (on the CPU its step is the sweep, 4.6-8x the
                scatter at 32² and 64² with the guard on or off: bench/results/cpu_regression.md).
            contact_stage: resolve contacts through the contact stage (``collide`` fills a per-particle contact
                buffer, the response reads it) instead of testing every collider in the update (the fused path).
                Default: the stage when a collider moves, the fused path for static ones.
            contact_slots: contacts a particle can hold in the stage's buffer [1, 64]; default min(colliders, 4).
                More contacts at one particle are dropped, counted and reported (``Contacts.overflow``, the
                guard, the run summary).
            integrator: the name of the integrator the model will be stepped with; only the memory check uses it
                (its scratch states count in the estimate). The default, symplectic Euler, needs the least.
            check_memory: refuse a model whose estimate does not fit (default); ``False`` skips the check.
            spring_groups: with gathered springs, read each spring group's rest length, ke and kd once per
                group where every spring of the group has the same ones (``Model.spring_slot_groups``), instead
                of once per spring; ``False`` reads them per spring.
            spring_grid: with ``spring_groups``, where the scene is one :meth:`add_cloth_grid` and nothing else
                (its particles in grid order), find a uniform group's neighbours from the particle's row and
                column instead of the incidence table (``Model.spring_layout`` "grid"; the same bits, fewer bytes
                per step); ``False`` keeps the table ("groups").
            contact_triangles: push the cloth's triangles out of spheres and capsules too
                (``Model.contact_triangles``); default (``None``): on where a sphere or capsule is too thin for
                particle contacts to hold the cloth, by the rule of :meth:`triangle_contacts`
                (``core/builder/colliders.py``).

        Raises:
            ConfigError: a bad option, a scene beyond the kernels' 32-bit indices, or a model that does not fit in
                memory.
        """
        if spring_evaluation not in ("auto", "gather", "scatter"):
            raise ConfigError(f"spring_evaluation must be 'auto', 'gather' or 'scatter', got {spring_evaluation!r}")
        if self._particle_count == 0:
            raise ConfigError("the scene has no particles: add a cloth, a mesh or particles first")
        try:
            scalar = scalar_type(precision)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        device = wp.get_device(device)
        worlds = checks.count("worlds", worlds, minimum=1)
        n = self._particle_count
        spring_total = sum(len(k) for k in self._springs)
        if max(n * worlds, 2 * spring_total) >= 2**31:
            raise ConfigError(
                f"{worlds} world(s) of {n} particles and {spring_total} springs exceed the 32-bit indices of the "
                "kernels (at most 2^31 - 1 particles in all worlds and 2^30 springs): use fewer worlds per model"
            )
        estimate = self.estimate_memory(device, precision=precision, worlds=worlds, integrator=integrator,
                                        contact_stage=contact_stage, contact_slots=contact_slots,
                                        spring_evaluation=spring_evaluation, spring_groups=spring_groups,
                                        spring_grid=spring_grid)
        if check_memory:
            memory.check_fits(estimate, memory.available_memory(device), precision=precision)
        try:
            model = self._finalize(device, precision, scalar, worlds, spring_evaluation, contact_stage, contact_slots,
                                   spring_groups=spring_groups, spring_grid=spring_grid)
            model.contact_triangles = (self.triangle_contacts().needed if contact_triangles is None
                                       else bool(contact_triangles))
            return model
        except (RuntimeError, MemoryError) as exc:
            if not memory.out_of_memory(exc):
                raise
            raise ConfigError(
                f"out of memory while finalizing the model on {device} ({exc}); the estimate was "
                f"{estimate.describe()}. " + memory.remedy(estimate, 1.25, precision=precision)
            ) from None

    def estimate_memory(self, device=None, *, precision: str = "float32", worlds: int = 1,
                        integrator: str = "symplectic_euler", contact_stage: bool | None = None,
                        contact_slots: int | None = None, spring_evaluation: str = "auto", spring_groups: bool = True,
                        spring_grid: bool = True, audit_substeps: int = 0,
                        audit_thickness: bool | None = None) -> memory.MemoryEstimate:
        """Estimate the memory :meth:`finalize` and a run of the model will need, before anything is allocated
        (:func:`warpspring.core.memory.estimate_memory` with this builder's counts and its incidence tables'
        exact widths).

        Args:
            device: the Warp device the model will live on (default: Warp's default).
            precision, worlds, contact_stage, contact_slots, spring_evaluation, spring_groups, spring_grid: as
                :meth:`finalize`.
            integrator: the integrator's name (its scratch states count).
            audit_substeps: substeps per frame of a run that audits every substep (``warpspring run
                --audit-substeps``; its record and pair lists count); 0: none. audit_thickness: whether it
                measures the pairs within a thickness (default: with self-collision).

        Returns:
            The :class:`~warpspring.core.memory.MemoryEstimate`.
        """
        device = wp.get_device(device)
        n = self._particle_count
        spring_degree = np.zeros(n, dtype=np.int64)
        for block in self._springs:  # per block: no concatenated copy of every spring
            spring_degree += np.bincount(block.ravel(), minlength=n)
        hinge_degree = np.zeros(n, dtype=np.int64)
        for block in self._hinges:
            hinge_degree += np.bincount(block.ravel(), minlength=n)
        spring_slots, hinge_slots = head_slots(spring_degree), head_slots(hinge_degree)
        groups, group_slots = (self._spring_group_layout(precision, spring_slots)
                               if spring_groups and spring_evaluation != "scatter" else (0, spring_slots))
        moving = any(s.translation_track is not None or s.rotation_track is not None for s in self._shapes)
        stage = bool(self._shapes) and (moving if contact_stage is None else bool(contact_stage))
        slots = max(1, min(len(self._shapes), 4)) if contact_slots is None else contact_slots
        pinned = sum(len(g.particles) for g in self._pin_groups)
        if pinned:  # the table holds every kinematic particle once there are groups
            mask = np.concatenate(self._pinned)
            for extra in self._extra_pins:
                mask[extra] = True
            pinned = int(mask.sum())
        cached = [s for s in self._shapes if getattr(s, "mesh", None) is not None and not s.mesh.winding_number]
        meshes = [s.mesh for s in self._shapes if getattr(s, "mesh", None) is not None]
        surface = self._self_contact_surface()
        return memory.estimate_memory(
            particles=n,
            springs=self._spring_count,
            hinges=self._hinge_count,
            triangles=sum(len(g.faces) for g in self._meshes),
            colliders=len(self._shapes),
            worlds=worlds,
            precision=precision,
            device=str(device),
            spring_evaluation=spring_evaluation,
            spring_groups=groups,
            spring_group_slots=group_slots,
            spring_grid=bool(spring_grid) and self._one_grid(),
            integrator=integrator,
            spring_slots=spring_slots,
            spring_tail=int(np.maximum(spring_degree - spring_slots, 0).sum()),
            hinge_slots=hinge_slots,
            hinge_tail=int(np.maximum(hinge_degree - hinge_slots, 0).sum()),
            pinned=pinned,
            mesh_vertices=sum(len(g.particles) for g in self._meshes),
            strain_limiting=self.stabilizers.max_strain is not None,
            contact_slots=slots if stage else 0,
            moving_colliders=moving,
            block_dim=_block_dim(device, n * worlds),
            family_bytes=sum(f.device_bytes(n, 8 if precision == "float64" else 4, worlds) for f in self._families)
            + sum(e.device_bytes(worlds) for e in self._emitters),
            cached_meshes=len(cached),
            mesh_faces=sum(len(s.mesh.faces) for s in cached),
            mesh_candidates=max([s.mesh.cache_candidates for s in cached], default=1),
            mesh_bytes=_mesh_collider_bytes(meshes) + sum(
                memory.mesh_native_bytes(len(m.faces), winding_number=m.winding_number, cuda=device.is_cuda)
                for m in meshes),
            collider_faces=sum(len(m.faces) for m in meshes),
            emitter_slots=sum(e.capacity for e in self._emitters),
            drag=self.drag != 0.0 or "drag" in self._tracks,
            wind=any(getattr(f, "moves_air", False) for f in self._families),
            working_families=any(f.does_work for f in self._families),
            spring_force_clamp=self.stabilizers.max_spring_force is not None,
            particle_force_clamp=self.stabilizers.max_particle_force is not None,
            plastic_springs=sum(law[0] for law in self._spring_law if law[3]),
            spring_law_arrays=any(law[0] and (law[1] == SPRING_LAWS["square"] or np.any(np.asarray(law[2]) != 1.0))
                                  for law in self._spring_law),
            family_elements=tuple(f.element_count for f in self._families),
            audit_substeps=audit_substeps,
            audit_thickness=audit_thickness,
            **_surface_counts(surface, n),
        )

    def _spring_group_layout(self, precision: str, width: int) -> tuple[int, int]:
        """(the spring families that ``springs.set_spring_layout`` lays out by group, each keeping one spring's index
        on the device; the grouped head's width, the sum of each family's largest degree at one particle), or
        (0, ``width``) where it lays them out per spring (``springs.spring_layout``'s rules): with per-spring law
        arrays or plasticity, where no family has one rest length, ke and kd in the model's precision
        (``springs.uniform_groups``), where the grouped head is wider than ``MAX_HEAD_SLOTS`` or moves more bytes than
        the per-spring head of ``width`` slots."""
        laws = [law for law in self._spring_law if law[0]]
        if not laws or any(law[1] == SPRING_LAWS["square"] or law[3] or np.any(np.asarray(law[2]) != 1.0)
                           for law in laws):
            return 0, width
        scalar = np.float64 if precision == "float64" else np.float32
        first: dict = {}
        uniform: dict = {}
        degree: dict = {}
        n = self._particle_count
        for family, springs, *values in zip(self._spring_family, self._springs, self._spring_rest, self._spring_ke,
                                            self._spring_kd):
            degree[family] = degree.get(family, 0) + np.bincount(np.asarray(springs).ravel(), minlength=n)
            values = [np.asarray(v).astype(scalar) for v in values]
            if not len(values[0]):
                continue
            head = first.setdefault(family, [v[0] for v in values])
            uniform[family] = uniform.get(family, True) and all(bool(np.all(v == h)) for v, h in zip(values, head))
        widths = {family: int(np.max(d, initial=0)) for family, d in degree.items()}
        grouped = sum(widths.values())
        per_spring_slot = 8 + 3 * (8 if precision == "float64" else 4)
        moved = 4 * grouped + (per_spring_slot - 4) * sum(w for f, w in widths.items() if not uniform.get(f, False))
        if not any(uniform.values()) or grouped > MAX_HEAD_SLOTS or moved > per_spring_slot * width:
            return 0, width
        return len(widths), grouped

    def _one_grid(self) -> bool:
        """Whether the scene is one cloth grid holding every particle, in grid order (its first particle is 0)."""
        grids = self._cloth_grids
        return len(grids) == 1 and grids[0][0] == 0 and grids[0][1] * grids[0][2] == self._particle_count

    def _self_contact_surface(self) -> np.ndarray | None:
        """The triangles (per-world particle indices, [t, 3]) that self-collision is asked for, or ``None``."""
        if self._self_collision is None:
            return None
        chosen = self._self_collision["meshes"]
        groups = [g for g in self._meshes if chosen is None or g.name in chosen]
        return np.concatenate([g.particles[g.faces] for g in groups]) if groups else np.zeros((0, 3), np.int64)

    def _finalize(self, device, precision: str, scalar, worlds: int, spring_evaluation: str,
                  contact_stage: bool | None, contact_slots: int | None, *, spring_groups: bool = True,
                  spring_grid: bool = True) -> Model:
        """The model's arrays on ``device`` (the arguments checked by :meth:`finalize`)."""
        vec3 = vec3_type(scalar)
        float_np = np.float64 if scalar is wp.float64 else np.float32
        model = Model(device, precision, scalar, world_count=worlds)
        model.up_axis = self.up_axis
        model.gravity = self.gravity
        model.drag = float(self.drag)
        for name, value in self._air.items():
            model.set_world_values(name, value)
        model.stabilizers = self.stabilizers
        n = self._particle_count

        mass = np.concatenate(self._mass)
        pinned = np.concatenate(self._pinned)
        for extra in self._extra_pins:
            pinned[extra] = True

        def farray(values, dtype=None, *, name="a shape parameter"):
            with np.errstate(over="ignore"):
                cast = np.asarray(values, dtype=float_np)
            if not np.isfinite(cast).all():
                raise ConfigError(
                    f"{name} overflows {precision} (largest magnitude {np.max(np.abs(values)):.3g}): "
                    "rescale the scene to SI units of sensible size or finalize with precision='float64'"
                )
            return wp.array(cast, dtype=dtype or scalar, device=device)

        def iarray(values, dtype=wp.int32):
            return wp.array(np.ascontiguousarray(values, dtype=np.int32), dtype=dtype, device=device)

        def every_world(values):  # one world's per-particle values, repeated for every world (world-major)
            return np.tile(values, (worlds,) + (1,) * (np.ndim(values) - 1))

        model.particle_count = n
        model.block_dim = _block_dim(device, n * worlds)
        model.particle_q = farray(every_world(np.concatenate(self._q)), vec3, name="a particle position [m]")
        model.particle_qd = farray(every_world(np.concatenate(self._qd)), vec3, name="a particle velocity [m/s]")
        model.particle_mass = farray(mass[None, :], name="a particle mass [kg]")
        model.particle_inv_mass = farray(1.0 / mass[None, :], name="an inverse particle mass [1/kg]")
        model.particle_radius = farray(np.concatenate(self._radius), name="a particle radius [m]")
        model.particle_flags = iarray(every_world(np.where(pinned, PARTICLE_KINEMATIC, 0)))
        # Tracks: the colliders' and pin groups' first (their indices stay put), then the animated inputs.
        model._shape_tracks = [t for shape in self._shapes for t in (shape.translation_track, shape.rotation_track)
                               if t is not None]
        model._pin_tracks = [t for g in self._pin_groups for t in (g.translation, g.rotation) if t is not None]
        model._family_tracks = [t for family in self._families for t in family.tracks()]
        model._rebuild_tracks()
        if self._pin_groups:
            model.pin_groups = PinGroupTable(
                np.flatnonzero(pinned), self._pin_groups, np.concatenate(self._q), model.track_table.index, device
            )
        for name, track in self._tracks.items():
            model.set_track(name, track)

        springs = np.concatenate(self._springs) if self._springs else np.zeros((0, 2), dtype=np.int64)
        s = len(springs)
        model.spring_count = s
        model.spring_indices = iarray(springs, wp.vec2i)
        names = np.repeat(np.array(self._spring_family, dtype=object), [len(b) for b in self._springs])
        model.spring_families = {name: np.flatnonzero(names == name) for name in dict.fromkeys(self._spring_family)}
        model.spring_rest_length = farray(np.concatenate(self._spring_rest) if s else [], name="a spring rest length [m]")
        model.spring_stiffness = farray(np.concatenate(self._spring_ke)[None, :] if s else np.zeros((1, 0)),
                                        name="a spring stiffness [N/m]")
        model.spring_damping = farray(np.concatenate(self._spring_kd)[None, :] if s else np.zeros((1, 0)),
                                      name="a spring damping [N·s/m]")
        degree = np.bincount(springs.ravel(), minlength=n) if s else np.zeros(n, dtype=np.int64)
        model.spring_max_degree = int(degree.max())
        if spring_evaluation == "auto":
            # The faster on each device, measured: on CUDA (bench/results/cloth*.md) and on the CPU, where the sweep (one
            # launch, a grid's springs vectorised) runs 4.6-8x the scatter (bench/results/cpu_regression.md).
            spring_evaluation = "gather"
        model.spring_gather = spring_evaluation == "gather"
        # The incidence also serves the stiffness products of implicit integration and stability analysis.
        model.spring_incidence, model.spring_incidence_shape = build_incidence(
            springs, n, springs[:, ::-1], lambda particles: particles, device=device
        )
        self._finalize_spring_laws(model, farray, iarray)
        model._spring_grouping = spring_groups
        # The grid layout: one cloth grid holding every particle, in grid order (its first particle is 0).
        if self._one_grid():
            model.spring_grid_shape = self._cloth_grids[0][1:]
        model._spring_grid = bool(spring_grid)
        set_spring_layout(model, spring_groups)

        hinges = np.concatenate(self._hinges) if self._hinges else np.zeros((0, 4), dtype=np.int64)
        model.hinge_count = len(hinges)
        model.hinge_indices = iarray(hinges, wp.vec4i)
        model.hinge_rest_angle = farray(np.concatenate(self._hinge_rest) if len(hinges) else [])
        model.hinge_stiffness = farray(np.concatenate(self._hinge_ke)[None, :] if len(hinges) else np.zeros((1, 0)),
                                       name="a hinge stiffness [N·m/rad]")
        model.hinge_damping = farray(np.concatenate(self._hinge_kd)[None, :] if len(hinges) else np.zeros((1, 0)),
                                     name="a hinge damping [N·m·s/rad]")
        model.hinge_incidence, model.hinge_incidence_shape = build_incidence(
            hinges, n, np.broadcast_to(np.arange(4), hinges.shape), -1, device=device
        )

        tris = [g.particles[g.faces] for g in self._meshes]
        tri_indices = np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)
        model.tri_count = len(tri_indices)
        model.tri_indices = wp.array(tri_indices.astype(np.int32), dtype=wp.int32, device=device)
        model.meshes = list(self._meshes)
        model.skins = list(self._skins)

        model.shapes = list(self._shapes)
        model._finalize_shapes(
            size=farray(np.array([shape.size for shape in self._shapes]).reshape(-1, 3), vec3,
                        name="a collider size [m]"),
            stage=contact_stage,
            slots=contact_slots,
        )
        for family in self._families:
            family.finalize(model)
        model.extra_families = tuple(self._families)
        for emitter in self._emitters:
            emitter.finalize(model)
        model.emitters = list(self._emitters)
        if self._self_collision is not None:
            surface = self._self_contact_surface()
            model.self_contact = make_self_contact(model, surface, np.concatenate(self._q), self._self_collision)
        model._finalized = True
        return model

    def _finalize_spring_laws(self, model: Model, farray, iarray) -> None:
        """The spring groups' laws and plasticity on the model: only the arrays and switches the groups use."""
        groups = [group for group in self._spring_law if group[0]]
        counts = np.array([group[0] for group in groups], dtype=np.int64)
        codes = np.array([group[1] for group in groups], dtype=np.int32)
        plastic_groups = np.array([group[3] for group in groups], dtype=bool)
        square = bool((codes == SPRING_LAWS["square"]).any())
        asymmetric = any(np.any(np.asarray(group[2]) != 1.0) for group in groups)
        model.spring_material_law = SpringLaw(square=square, asymmetric=asymmetric, plastic=bool(plastic_groups.any()))
        if square or asymmetric:
            model.spring_law_code = iarray(np.repeat(codes, counts))
            ratio = np.concatenate([np.broadcast_to(np.asarray(group[2], dtype=np.float64), (group[0],))
                                    for group in groups])
            model.spring_compression_ratio = farray(ratio, name="a spring compression ratio [-]")
        if plastic_groups.any():
            worlds = model.world_count
            plastic = np.repeat(plastic_groups, counts)
            rows = np.repeat(np.array([group[4] for group in groups]), counts, axis=0)
            model.spring_plastic_count = int(plastic.sum())
            model.spring_plastic_index = iarray(np.flatnonzero(plastic))
            dtype = np.float64 if model.scalar is wp.float64 else np.float32
            for column, name in enumerate(("yield_strain", "yield_force", "yield_rate", "hardening", "break_strain")):
                # inf (no limit, instant flow) is a value here: stored as is, not refused as an overflow.
                setattr(model, f"spring_{name}", wp.array(rows[:, column].astype(dtype), dtype=model.scalar,
                                                          device=model.device))
            model.spring_plastic_rest_length = farray(np.tile(np.concatenate(self._spring_rest), worlds),
                                                      name="a spring rest length [m]")
            model.spring_plastic_strain = farray(np.zeros(worlds * len(plastic)))


def _block_dim(device, n: int) -> int:
    """Threads per block for per-particle kernels: 256, or fewer for small models so that the blocks
    spread over all multiprocessors (a 4096-particle cloth in 16 blocks would use 16 of 132 SMs)."""
    if not device.is_cuda:
        return 256
    per_sm = n // max(device.sm_count, 1)
    return int(min(256, max(32, 1 << max(per_sm, 1).bit_length() - 1)))


def _surface_counts(surface: np.ndarray | None, n: int) -> dict:
    """The self-colliding surface's triangles, unique edges and vertices (``memory.estimate_memory``'s arguments)."""
    if surface is None or not len(surface):
        return {}
    t = np.asarray(surface, dtype=np.int64)
    sides = np.sort(np.stack([t, np.roll(t, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    keys = np.sort(sides[:, 0] * n + sides[:, 1])  # sorted, the distinct ones counted (np.unique hashes: slower)
    return dict(self_contact_triangles=len(t), self_contact_edges=1 + int(np.count_nonzero(np.diff(keys))),
                self_contact_vertices=int(np.count_nonzero(np.bincount(t.ravel(), minlength=n))))
