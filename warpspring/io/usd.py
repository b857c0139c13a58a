"""Stream an animation to a USD file that DCC tools (Blender, Houdini, Maya, usdview) play.

What is authored, and why (USD's fallbacks are wrong for simulation caches):

* stage: ``/World`` as defaultPrim, ``upAxis``, ``metersPerUnit = 1`` (the fallback is centimetres),
  ``timeCodesPerSecond = framesPerSecond = fps`` (the fallback is 24), start/end time codes; frame k is
  time code ``start_frame + k`` (0 by default; 1 or 1001 as pipelines number frames);
* each cloth mesh: its faces as authored (a grid's cells and a USD mesh's quads stay quads; the simulation
  uses their triangles), in the input's vertex order, once; ``subdivisionScheme = "none"`` (the fallback,
  Catmull-Clark, makes Blender and Houdini subdivide the cloth), ``doubleSided``, ``primvars:st`` when the
  mesh has UVs, its face sets (a USD input: its whole dressing, name and kind); per frame ``points``,
  ``extent``, ``normals`` (per vertex, or with a USD input's interpolation: per face, or per face-vertex
  keeping its hard edges), ``velocities`` [m/s] and ``accelerations`` [m/s²] (renderers motion-blur from them;
  frame k's meets frame k + 1, added when that frame comes); optionally the primvars ``strain`` and ``pinned``
  per frame and ``rest`` (Pref) once. Normals are gathered per vertex in a fixed order (no atomics), so a rerun
  on the same device writes the same bytes;
* each soft body's mesh (``model.skins``) by the same path, its faces as authored; per frame its points are the fixed
  weighted sums of particles that embed it (a host product over the positions read back), with velocities,
  area-weighted normals, and optionally ``strain`` (its particles' weighted) and ``rest``;
* colliders as prims of purpose ``guide`` by default (shown in viewports, left out of final renders) with
  their transforms: a sphere as ``UsdGeom.Sphere``, a box as a ``UsdGeom.Cube`` of size 2 scaled by its
  half extents, a capsule as ``UsdGeom.Capsule`` (axis Z, height 2 · half_height), a plane as a finite quad
  fitted to the scene, a mesh collider as a ``UsdGeom.Mesh`` of its triangles in its own frame (double-sided
  unless closed; a deforming one's ``points`` and ``extent`` sampled at every frame). A static collider's
  translate and orient ops hold one default value; a moving one's (a collider with keyframe tracks) are also
  sampled at every written frame, at the frame's time;
* optionally the particles (``UsdGeom.Points`` with widths and velocities) and the springs: one
  ``UsdGeom.BasisCurves`` per spring family (structural, shear, bend, ...) of linear chains through the
  particles (a chain's inner points serve two springs; ``primvars:warpspring:particle`` names the particle
  of each curve vertex) with per-vertex ``strain``, the larger of the two springs beside the vertex.

Worlds: a model of one world, or one chosen world of a model of several (``world=k``), is written as
above, directly under ``/World``. Every world of a model of several is written as its own ``Xform``,
``/World/world_0003/<cloth>``, ``/World/world_0003/colliders/...``, with its own copy of the colliders
and a translation that lays the worlds out side by side on a grid in the ground plane
(:func:`world_offsets`); the points stay the world's simulated positions, the translation places them.
A world that the run-time guard stopped (:meth:`UsdWriter.stop_worlds`) gets no samples after its last
good frame: DCC tools hold a prim's last sample, so the file stays a valid animation of every world.

Over an asset (``layer_over``), the file is instead a layer of overrides at the asset's prim paths, in the asset's
frame (:mod:`~warpspring.io.usd_layer`).

How the frames reach the disk (a valid file at every moment, also after a kill) is
:mod:`~warpspring.io.usd_stream`'s; the prims of a world are defined in :mod:`~warpspring.io.usd_prims`.
"""

from __future__ import annotations

import math
import os

import numpy as np
import warp as wp

from .. import checks
from ..core.model import Model
from ..core.state import State
from ..errors import ConfigError, SimulationError
from ..kernels.geometry import vertex_normal_kernel
from ..kernels.kinematics import PARTICLE_KINEMATIC
from .usd_layer import ARCS, EXTRAS_ROOT, LayerOver
from .usd_normals import cancelled_vertices, fallback_normals
from .usd_prims import PRIMVARS, PURPOSES, UsdPrims, _WorldPrims, vec3_array
from .output_lock import OutputLock
from .usd_stream import STATIC_NAME, UsdStream, check_output_path, read_frames


class UsdWriter(UsdPrims, UsdStream):
    """Writes the frames of a simulation of ``model`` to ``path`` as time samples.

    Use as a context manager, or call :meth:`close`. Frame k (t = k / fps seconds of simulated time) is
    time code ``start_frame + k``.

    Args:
        path: output file; ``.usdc`` (binary, default choice) or ``.usda`` (text); ``.usd`` is binary.
        model: the simulated model (topology, colliders and up axis are taken from it).
        fps: frames per second of the animation [1/s].
        particles: also write the particles as ``UsdGeom.Points`` (widths = 2 × radius, velocities).
        springs: also write the springs, one ``UsdGeom.BasisCurves`` of linear chains per spring family.
        primvars: optional per-vertex primvars of the meshes, any of ``"strain"`` (per frame: the largest
            strain (l − L)/L of the springs at the vertex [-]), ``"pinned"`` (per frame: 1 where the particle
            is kinematic, else 0; on a soft body's mesh, 1 where every particle the vertex follows is) and
            ``"rest"`` (once: the positions at the start [m], Pref for procedural
            textures that must stick to the cloth).
        start_frame: the time code of frame 0 (0, 1 or 1001 as pipelines use), ≥ 0.
        collider_purpose: the USD purpose of collider prims: ``"guide"`` (shown in viewports, left out of
            renders), ``"default"``, ``"render"`` or ``"proxy"``.
        world: export only this world, directly under ``/World`` as a one-world model; ``None``: every
            world (each under ``/World/world_NNNN`` when the model has several).
        world_spacing: distance [m] between neighbouring worlds on the export grid, when every world
            of a model of several is written; ``None``: :func:`default_world_spacing`.
        world_columns: worlds per row of the export grid; ``None``: ceil(√world_count).
        keep_frames: keep the first ``keep_frames`` frames of the file already at ``path``, written by a run
            of the same scene and export options that stopped (or was killed), and append after them
            (``warpspring run --resume``); later samples of that file are dropped.
        lock: the :class:`~warpspring.io.output_lock.OutputLock` of ``path`` the caller holds (the runner takes it
            before it builds the model, and releases it after :meth:`close`); ``None``: the writer takes it and
            releases it when it closes. One run owns an output: while it is held, another writer of ``path``
            (another process, or this one) is refused.
        accelerations: write each surface's ``accelerations`` [m/s²]: frame k's is 2 (x_{k+1} − x_k − v_k Δt) / Δt²,
            so that the quadratic a renderer draws between samples (x + v t + ½ a t²) passes through the next frame
            (across an impact the velocity alone overshoots). It needs frame k + 1: frame k's file is rewritten (whole,
            renamed) when frame k + 1 comes, so a reader sees every frame so far and the last one without its
            accelerations (USD then holds the frame before's); the packed file gives it the frame before's.
        layer_over: an asset (a USD file) to write the simulation over, as a layer of overrides at the asset's own
            prim paths of what the simulation changes (:mod:`~warpspring.io.usd_layer`): in the asset's units, up
            axis, time codes and each prim's local space; ``None``: a stage of its own.
        layer_arc: how the layer reaches the asset: ``"sublayer"``, ``"reference"`` or ``"none"``.
        layer_colliders: over an asset, also write the colliders (under ``/warpspring``).

    Raises:
        ConfigError: a bad path, fps, world, spacing, column count, primvar name, start frame or purpose,
            or (``keep_frames``) a file that is missing or holds fewer frames; nothing is written. Another run
            writes ``path`` (the message names its process); nothing is touched.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        model: Model,
        *,
        fps: float,
        particles: bool = False,
        springs: bool = False,
        primvars=(),
        start_frame: int = 0,
        collider_purpose: str = "guide",
        world: int | None = None,
        world_spacing: float | None = None,
        world_columns: int | None = None,
        keep_frames: int = 0,
        lock: OutputLock | None = None,
        accelerations: bool = True,
        layer_over: str | os.PathLike | None = None,
        layer_arc: str = "sublayer",
        layer_colliders: bool = False,
    ):
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

        self._Usd, self._UsdGeom, self._Vt, self._Tf, self._Sdf, self._Gf = Usd, UsdGeom, Vt, Tf, Sdf, Gf
        path = check_output_path(path)
        ext = os.path.splitext(path)[1].lower()
        fps = checks.positive("fps", fps)
        start_frame = checks.count("start_frame", start_frame, minimum=0)
        primvars = tuple(dict.fromkeys([primvars] if isinstance(primvars, str) else primvars))
        unknown = [p for p in primvars if p not in PRIMVARS]
        if unknown:
            raise ConfigError(f"unknown primvar {unknown[0]!r}: choose from {', '.join(PRIMVARS)}")
        if collider_purpose not in PURPOSES:
            raise ConfigError(f"collider_purpose must be one of {', '.join(PURPOSES)}, got {collider_purpose!r}")
        if world is not None:
            world = checks.count("world", world, minimum=0)
            if world >= model.world_count:
                raise ConfigError(f"cannot export world {world}: the model has {model.world_count} world(s), "
                                  f"0..{model.world_count - 1}")
        self._tile = None  # half the width [m] of a world's cell on the export grid, when worlds are laid out
        if world is None and model.world_count > 1:
            if world_spacing is None:
                world_spacing = default_world_spacing(model)
            offsets = world_offsets(model, spacing=world_spacing, columns=world_columns)  # checks both first
            roots = [(w, f"/World/{world_prim_name(w, model.world_count)}") for w in range(model.world_count)]
            self._tile = 0.5 * world_spacing if world_spacing > 0 else None
        else:
            offsets = None
            roots = [(0 if world is None else world, "/World")]
        keep_frames = checks.count("keep_frames", keep_frames, minimum=0)
        self._layer = None
        if layer_over is not None:
            self._layer = LayerOver(layer_over, output=path, fps=fps, up_axis=model.up_axis, arc=layer_arc)
            if world is None and model.world_count > 1:
                raise ConfigError(f"a layer over {os.fspath(layer_over)!r} holds one world: choose it with world=K "
                                  f"(--world K), 0..{model.world_count - 1}")
            roots, offsets = [(roots[0][0], EXTRAS_ROOT)], None
            self._tile = None
        elif layer_arc not in ARCS:
            raise ConfigError(f"layer_arc must be one of {', '.join(ARCS)}, got {layer_arc!r}")
        self._accelerations = bool(accelerations)
        self._layer_colliders = bool(layer_colliders)
        if lock is not None and (not lock.held or lock.output != path):
            raise ValueError(f"the lock given is not a held lock of {path!r}")
        self._owns_lock = lock is None
        self._lock = OutputLock(path) if lock is None else lock  # this writer owns the output from here
        try:
            self._begin(path, ext, model, fps=fps, start_frame=start_frame, primvars=primvars,
                        collider_purpose=collider_purpose, world=world, offsets=offsets, roots=roots,
                        particles=particles, springs=springs, keep_frames=keep_frames)
        except BaseException:
            self._release()
            raise

    def _begin(self, path: str, ext: str, model: Model, *, fps, start_frame, primvars, collider_purpose, world,
               offsets, roots, particles, springs, keep_frames) -> None:
        """Read what a resume keeps, begin the file and define the static stage (the output's lock is held)."""
        Usd, UsdGeom, Gf = self._Usd, self._UsdGeom, self._Gf
        step = 1.0 if self._layer is None else self._layer.step
        kept = read_frames(path, keep_frames, start_frame, step=step) if keep_frames else None  # before it is replaced

        self.model = model
        self.fps = float(fps)
        self.start_frame = start_frame
        self._codes_per_second = None if self._layer is None else self._layer.time_codes_per_second
        self._primvars = primvars
        self._purpose = collider_purpose
        self._open(path, ext)  # the frames folder beside the file, and its reaper
        self._keep_last = self._accelerations  # a frame's accelerations are added when the next frame comes

        # The static layer: every prim, its topology and constant attributes, and an unvalued spec of each
        # animated attribute (the frames' samples compose onto them through the clips).
        self.stage = Usd.Stage.CreateInMemory(STATIC_NAME)
        stage = self.stage
        layer = self._layer
        self._clip_roots = ["/World"] if layer is None else []
        self._held, self._held_next, self._amend = {}, {}, []  # accelerations' look-ahead (UsdPrims._look_ahead)
        if layer is None:
            root = UsdGeom.Xform.Define(stage, "/World")
            stage.SetDefaultPrim(root.GetPrim())
        self._deforming_meshes: dict = {}  # world root → (MeshCollider, points path, extent path) of deforming meshes
        self._strain_ends = None  # the springs' particles, when strain is written
        self._radius = model.particle_radius.numpy().astype(np.float64)  # [m], for emitted particles' widths
        if world is not None and model.world_count > 1 and layer is None:
            root.GetPrim().SetCustomDataByKey("warpspring:world", world)
        self.worlds = [w for w, _ in roots]
        self._stopped: dict[int, int] = {}
        self._previous_normals: dict = {}  # normals attribute → the normals written last (fallbacks)
        self._orphans = None  # cloth vertices whose triangles cancel in pairs (their normal is found on the host)
        self._slots = []
        for w, path_root in roots:
            if offsets is not None:
                xform = UsdGeom.Xform.Define(stage, path_root)
                xform.AddTranslateOp().Set(Gf.Vec3d(*offsets[w]))
                xform.GetPrim().SetCustomDataByKey("warpspring:world", w)
            if layer is not None:
                slot = self._define_layer(w, particles=particles, springs=springs)
            else:
                slot = self._define_world(w, path_root, particles=particles, springs=springs)
                slot.colliders = self._write_colliders(path_root)
                q0 = model.particle_q.numpy().reshape(model.world_count, model.particle_count, 3)[w]
                slot.skins = [self._define_surface(path_root, skin, skin.points(q0)) for skin in model.skins]
            slot.mesh_colliders = self._deforming_meshes.pop(path_root, [])
            self._slots.append(slot)
        if model.tri_count and any(slot.meshes for slot in self._slots):
            self._normal_topology()
        if "strain" in primvars or springs:
            self._strain_topology()
        self._start(kept, keep_frames)
        if kept and self._accelerations:  # the last kept frame gets its accelerations from the next one
            self._held = _last_kept(kept, self._animated)

    def _define_layer(self, world: int, *, particles: bool, springs: bool) -> _WorldPrims:
        """The overrides of a layer over an asset (``_layer``) for ``world``: every surface read from the asset, at
        its prim path; particles, springs and emitters when asked for, and colliders with ``layer_colliders``,
        under ``/warpspring`` (warpspring's metres and up axis turned into the asset's)."""
        layer, model, UsdGeom = self._layer, self.model, self._UsdGeom
        q0 = model.particle_q.numpy().reshape(model.world_count, model.particle_count, 3)[world]
        meshes = [g for g in model.meshes if layer.owns(g.dressing)]
        skins = [s for s in model.skins if layer.owns(s.dressing)]
        if not meshes and not skins:
            raise ConfigError(f"layer_over {layer.file!r}: the scene reads no mesh from that file; give a cloth or soft "
                              "body mesh = that file (and prim = its mesh), or write a stage of its own (no layer_over)")
        for group in meshes:
            layer.check_prim(group.dressing, len(group.particles))
        for skin in skins:
            layer.check_prim(skin.dressing, len(skin.indices))
        extras = particles or springs or bool(model.emitters) or (self._layer_colliders and bool(model.shapes))
        if extras:
            xform = UsdGeom.Xform.Define(self.stage, EXTRAS_ROOT)
            xform.AddTransformOp().Set(self._Gf.Matrix4d(layer.extras_matrix().tolist()))
            slot = self._define_world(world, EXTRAS_ROOT, particles=particles, springs=springs, surfaces=False)
            if self._layer_colliders:
                slot.colliders = self._write_colliders(EXTRAS_ROOT)
        else:
            slot = _WorldPrims(world, [], None, [])
        slot.meshes = [self._define_surface(None, g, q0[g.particles]) for g in meshes]
        slot.skins = [self._define_surface(None, s, s.points(q0)) for s in skins]
        tops = ["/" + p.prim_path.split("/")[1] for p in slot.meshes + slot.skins] + ([EXTRAS_ROOT] if extras else [])
        self._clip_roots = list(dict.fromkeys(tops))
        return slot

    # -- frames ---------------------------------------------------------------------------------------

    def write_frame(self, state: State) -> None:
        """Append ``state`` as the next frame (time code ``start_frame`` + :attr:`frame_count`, time
        :attr:`frame_count` / fps seconds) and save it. Moving colliders get their pose at that time. Worlds
        that were stopped (:meth:`stop_worlds`) get no sample.

        Raises:
            SimulationError: a position of an exported world that is not stopped is NaN or infinite;
                nothing of the frame is written.
            OutputError: the frame could not be saved (a full disk, the file or its folder removed): the
                message names the frame and the OS's reason; the file on disk keeps the frames saved before
                it (a valid stage), and the writer is closed without saving again.
        """
        if self._closed:
            raise RuntimeError("UsdWriter is closed")
        model = self.model
        live = [slot for slot in self._slots if slot.world not in self._stopped]
        with np.errstate(over="ignore", invalid="ignore"):  # USD points are float32: check what is written
            q_all = state.particle_q.numpy().reshape(model.world_count, model.particle_count, 3).astype(np.float32)
        for slot in live:
            bad = np.flatnonzero(~np.isfinite(q_all[slot.world]).all(axis=1))
            if len(bad):
                where = f"world {slot.world}: " if model.world_count > 1 else ""
                raise SimulationError(
                    f"{where}particle {int(bad[0])} has a non-finite position or one beyond float32 range "
                    f"({len(bad)} of {model.particle_count} particles); the frame was not written"
                )
        with np.errstate(over="ignore", invalid="ignore"):
            v_all = state.particle_qd.numpy().reshape(q_all.shape).astype(np.float32)
        v_all[~np.isfinite(v_all)] = 0.0  # a velocity beyond float32 blurs nothing useful
        normals_all = None
        if any(mesh.front is None for slot in live for mesh in slot.meshes):
            normals_all = self._vertex_normals(state).reshape(q_all.shape)
        rest = self._rest_lengths() if self._strain_ends is not None else None
        kinematic = None
        if "pinned" in self._primvars:
            kinematic = (model.particle_flags.numpy().reshape(model.world_count, -1) & PARTICLE_KINEMATIC) != 0
        seconds = self.frame_count / self.fps
        poses = {shape.name: shape.frame(seconds) for shape in model.shapes if shape.moving}  # same in every world

        Vt, UsdGeom, Gf = self._Vt, self._UsdGeom, self._Gf
        samples = []  # (attribute path, value)
        self._held_next, self._amend = {}, []  # accelerations: this frame's values; the frame before's samples
        for slot in live:
            q, v = q_all[slot.world], v_all[slot.world]
            strain = None if rest is None else self._spring_strain(q, rest[slot.world])
            vertex_strain = None if strain is None or "strain" not in self._primvars else self._vertex_strain(strain)
            for mesh in slot.meshes:  # (strain, pinned: None where the input authors its own, which is kept)
                particles = mesh.group.particles
                samples += self._surface_samples(
                    mesh, q[particles], v[particles],
                    normals=normals_all[slot.world][particles] if mesh.front is None else None,
                    strain=None if vertex_strain is None else vertex_strain[particles],
                    pinned=None if kinematic is None else kinematic[slot.world][particles])
            for skin in slot.skins:
                samples += self._surface_samples(skin, **self._skin_values(
                    skin.group, q, v, vertex_strain, None if kinematic is None else kinematic[slot.world]))
            if slot.points is not None:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q))
                samples += [(slot.points.points, points), (slot.points.velocities, vec3_array(Vt, v)),
                            (slot.points.extent, UsdGeom.Points.ComputeExtent(points, self._widths))]
            for prims in slot.emitters:
                samples += self._emitter_samples(prims, slot.world, q, v)
            for curves in slot.curves:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[curves.particles]))
                segment = strain[curves.segments]  # per curve vertex: its two segments (a chain's ends: one)
                samples += [(curves.points, points), (curves.velocities, vec3_array(Vt, v[curves.particles])),
                            (curves.extent, UsdGeom.Curves.ComputeExtent(points, self._curve_widths)),
                            (curves.strain, Vt.FloatArray.FromNumpy(segment.max(axis=1).astype(np.float32)))]
            for shape, translate, orient in slot.colliders:
                position, (x, y, z, w) = poses[shape.name]
                samples += [(translate, Gf.Vec3d(*(float(p) for p in position))),
                            (orient, Gf.Quatd(float(w), float(x), float(y), float(z)))]
            for collider, points_path, extent_path in slot.mesh_colliders:  # deforming meshes: their points now
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(collider.points(), dtype=np.float32))
                samples += [(points_path, points), (extent_path, UsdGeom.PointBased.ComputeExtent(points))]
        self._held = self._held_next
        self._append(samples, amend=self._amend)

    def _closing_samples(self) -> list:
        """The last frame's accelerations when the file is packed: the frame before's (no next frame tells more;
        USD would hold it too), zero after a single frame."""
        given = dict(self._amend)
        return [(attribute, given.get(attribute, self._Vt.Vec3fArray(len(x))))
                for attribute, (x, _) in self._held.items()]

    def stop_worlds(self, worlds) -> None:
        """Write no further samples of ``worlds`` (an index or indices; worlds not exported are ignored):
        they keep the samples written so far, their last one being their final pose in every DCC tool.
        For worlds the run-time guard stopped: call before writing the frame in which they failed."""
        for w in np.unique(np.asarray(worlds, dtype=np.int64).ravel()).tolist():
            if w in self.worlds and w not in self._stopped:
                self._stopped[w] = self.frame_count

    @property
    def stopped_worlds(self) -> dict[int, int]:
        """The exported worlds that were stopped, each with the number of frames written of it (its last
        sample is at time code ``start_frame`` + that number - 1)."""
        return dict(self._stopped)

    # -- normals and strain -------------------------------------------------------------------------------

    def _normal_topology(self) -> None:
        """The CSR table of vertex → incident triangles (ascending) of every exported world's meshes, in
        state-array indices: one launch gathers all their normals, in a fixed order."""
        model = self.model
        n = model.particle_count
        tri = model.tri_indices.numpy()
        tri = np.concatenate([tri + w * n for w in self.worlds]).astype(np.int32)
        corner_vertex = tri.ravel()
        order = np.argsort(corner_vertex, kind="stable")  # by vertex, then by triangle
        start = np.searchsorted(corner_vertex[order], np.arange(model.state_size + 1))
        device = model.device
        self._export_tris = wp.array(tri, dtype=wp.int32, device=device)
        self._vertex_tri_start = wp.array(start.astype(np.int32), dtype=wp.int32, device=device)
        self._vertex_tris = wp.array((order // 3).astype(np.int32), dtype=wp.int32, device=device)
        self._normals = wp.empty(model.state_size, dtype=wp.vec3f, device=device)
        orphans = cancelled_vertices(tri)
        if len(orphans):  # their triangles: those of any orphan, in order
            self._orphans = (orphans, tri[np.isin(tri, orphans).any(axis=1)])

    def _vertex_normals(self, state: State) -> np.ndarray:
        """Unit vertex normals of every particle, shape [state_size, 3] (those of exported worlds' meshes set).
        A vertex whose triangles cancel in pairs (one triangle with both windings) gets the normal of its first
        triangle of nonzero area, else the one it had the frame before (:func:`fallback_normals`)."""
        model = self.model
        wp.launch(vertex_normal_kernel(model.scalar), dim=model.state_size,
                  inputs=[self._export_tris, self._vertex_tri_start, self._vertex_tris, state.particle_q],
                  outputs=[self._normals], device=model.device)
        normals = self._normals.numpy()
        if self._orphans is not None:
            orphans, tris = self._orphans
            normals[orphans] = fallback_normals(state.particle_q.numpy(), tris, orphans, model.up_axis,
                                                self._previous_normals.get("cloth"))
            self._previous_normals["cloth"] = normals[orphans]  # a copy
        return normals

    def _strain_topology(self) -> None:
        """Spring ends sorted by particle, for the per-vertex maximum of the springs' strain."""
        ends = self.model.spring_indices.numpy().astype(np.int64)
        self._strain_ends = ends if len(ends) else None
        if self._strain_ends is None:
            return
        corner = ends.ravel()
        self._corner_order = np.argsort(corner, kind="stable")
        sorted_vertex = corner[self._corner_order]
        self._corner_start = np.flatnonzero(np.r_[True, np.diff(sorted_vertex) != 0])
        self._corner_vertex = sorted_vertex[self._corner_start]

    def _rest_lengths(self) -> np.ndarray:
        """Each world's current rest lengths [m], shape [world_count, spring_count] (plastic springs: where
        they have moved; a broken spring's is negative and its strain written as 0)."""
        return self.model.spring_rest_lengths()

    def _spring_strain(self, q: np.ndarray, rest: np.ndarray) -> np.ndarray:
        """The strain (l − L)/L of every spring [-], shape [spring_count], float32 (0 for L = 0)."""
        ends = self._strain_ends
        length = np.linalg.norm(q[ends[:, 1]].astype(np.float64) - q[ends[:, 0]], axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            strain = np.where(rest > 0.0, length / rest - 1.0, 0.0)
        return strain.astype(np.float32)

    def _vertex_strain(self, strain: np.ndarray) -> np.ndarray:
        """Per particle, the largest strain of its springs [-], shape [particle_count] (0 with no spring)."""
        out = np.zeros(self.model.particle_count, dtype=np.float32)
        per_corner = strain[self._corner_order // 2]
        out[self._corner_vertex] = np.maximum.reduceat(per_corner, self._corner_start)
        return out


def _last_kept(kept: list, animated: list) -> dict:
    """The points and velocities of the last kept frame of a resumed file, by the accelerations attribute they
    belong to (what :meth:`~warpspring.io.usd_prims.UsdPrims._look_ahead` holds)."""
    values = {attribute: samples[-1] for attribute, samples in kept}  # attribute → (time code, value)
    last = max((t for t, _ in values.values()), default=None)
    held = {}
    for attribute, _ in animated:
        if attribute.name != "accelerations":
            continue
        points = values.get(attribute.GetPrimPath().AppendProperty("points"))
        velocities = values.get(attribute.GetPrimPath().AppendProperty("velocities"))
        if points is not None and velocities is not None and points[0] == last == velocities[0]:
            held[attribute] = (np.array(points[1], dtype=np.float64), np.array(velocities[1], dtype=np.float64))
    return held


def world_prim_name(world: int, world_count: int) -> str:
    """The prim name of ``world`` when every world is exported: ``world_0003`` (at least 4 digits, as many
    as the largest index of ``world_count`` worlds needs, so the names sort in world order)."""
    return f"world_{world:0{max(4, len(str(world_count - 1)))}d}"


def world_offsets(model: Model, *, spacing: float | None = None, columns: int | None = None) -> np.ndarray:
    """Where each world is placed when every world is exported: translations [m], shape [world_count, 3].

    World w sits in column w mod ``columns`` and row w // ``columns`` of a grid in the ground plane:
    columns along +x, rows along +y (Z-up) or +z (Y-up), ``spacing`` metres apart.

    Args:
        model: the model (its world count, up axis and, for the default spacing, initial positions).
        spacing: distance [m] between neighbouring worlds, ≥ 0 (0: all at the origin, overlaid);
            ``None``: :func:`default_world_spacing`.
        columns: worlds per row, ≥ 1; ``None``: ceil(√world_count).
    """
    spacing = default_world_spacing(model) if spacing is None else checks.non_negative("world spacing", spacing)
    count = model.world_count
    columns = math.ceil(math.sqrt(count)) if columns is None else checks.count("world columns", columns, minimum=1)
    w = np.arange(count)
    offsets = np.zeros((count, 3))
    offsets[:, 0] = spacing * (w % columns)
    offsets[:, 1 if model.up_axis == "Z" else 2] = spacing * (w // columns)
    return offsets


def default_world_spacing(model: Model) -> float:
    """The default distance [m] between exported worlds: twice the larger horizontal extent of world 0's
    initial particles, at least 1 m (room for a cloth to swing or spread without touching its neighbours)."""
    q0 = model.particle_q.numpy()[: model.particle_count].astype(np.float64)
    horizontal = [0, 1] if model.up_axis == "Z" else [0, 2]
    extent = float(np.ptp(q0[:, horizontal], axis=0).max()) if len(q0) else 0.0
    return max(2.0 * extent, 1.0)
