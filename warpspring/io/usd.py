"""Stream an animation to a USD file that DCC tools (Blender, Houdini, Maya, usdview) play.

What is authored, and why (USD's fallbacks are wrong for simulation caches):

* stage: ``/World`` as defaultPrim, ``upAxis``, ``metersPerUnit = 1`` (the fallback is centimetres),
  ``timeCodesPerSecond = framesPerSecond = fps`` (the fallback is 24), start/end time codes; frame k is
  time code ``start_frame + k`` (0 by default; 1 or 1001 as pipelines number frames);
* each cloth mesh: its faces as authored (a grid's cells and a USD mesh's quads stay quads; the simulation
  uses their triangles), in the input's vertex order, once; ``subdivisionScheme = "none"`` (the fallback,
  Catmull-Clark, makes Blender and Houdini subdivide the cloth), ``doubleSided``, ``primvars:st`` when the
  mesh has UVs, its face sets; per frame ``points``, ``extent``, vertex ``normals`` and ``velocities``
  [m/s] (renderers motion-blur from them); optionally the primvars ``strain`` and ``pinned`` per frame and
  ``rest`` (Pref) once. Normals are gathered per vertex in a fixed order (no atomics), so a rerun on the
  same device writes the same bytes;
* each soft body's mesh (``model.skins``) likewise, its faces as authored; per frame its points are the fixed
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

How frames reach the disk. While a run writes ``out.usdc``, its frames live in a folder beside it,
``out.usdc.frames/``: the static prims once (``static.usdc``), and each frame as its own small layer
(``frame.001001.usdc``), written whole through a temporary file and renamed, so a file is either absent
or complete; every 100 frames they are gathered into a chunk layer, and neighbouring chunks merge as they
grow (up to 64 MB), so the stage has few clips at any frame count. ``out.usdc`` itself is a small root layer, rewritten the same way after every frame: the
stage's metadata, the static layer as a sublayer, and the frames as value clips (a template of the frame
files up to the last one written). So at every moment the file is a valid stage holding every frame
written: another process can open it as often as it likes while the run goes on and never sees a torn
file or the frame count go backwards, and a run that is killed (even by SIGKILL) leaves every frame it
wrote. Each frame costs the same to write however many came before, for ``.usdc`` and ``.usda`` alike.
On :meth:`UsdWriter.close` the frames are packed into one self-contained layer, renamed over
``out.usdc``, and the folder is removed. A small companion process removes USD's temporary files if the
run dies while one is being written, so a killed run leaves its file, its frames folder and nothing else.

A save that fails (a full disk, the file or its folder removed) raises :class:`~warpspring.errors.OutputError`,
one line naming the frame and the OS's reason (USD's own errors often carry none: the file system is then
examined for one). The file keeps every frame saved before it, a valid stage through its frames folder,
and the writer drops the unsaved frame instead of trying to save it again on close.
"""

from __future__ import annotations

import errno
import math
import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError, OutputError, SimulationError, os_error_reason
from ..version import __version__
from ..kernels.geometry import vertex_normal_kernel
from ..core.model import Model
from ..kernels.kinematics import PARTICLE_KINEMATIC
from ..core.state import State
from ..core.transforms import quat_to_matrix

_EXTENSIONS = (".usdc", ".usda", ".usd")


class UsdWriter:
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

    Raises:
        ConfigError: a bad path, fps, world, spacing, column count, primvar name, start frame or purpose,
            or (``keep_frames``) a file that is missing or holds fewer frames; nothing is written.
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
        kept = _read_frames(path, keep_frames, start_frame) if keep_frames else None  # before the file is replaced

        self.path = path
        self.parts = parts_folder(path)
        self.model = model
        self.fps = float(fps)
        self.start_frame = start_frame
        self.frame_count = 0
        self.frames_saved = 0  # frames on disk: 0 .. frames_saved - 1
        self._primvars = primvars
        self._purpose = collider_purpose
        self._closed = False
        self._failed = False
        self._reaper = None
        self._format = ".usda" if ext == ".usda" else ".usdc"
        try:
            _remove_output(path)
            os.makedirs(self.parts)
            self._reaper = _Reaper(path)
        except OSError as exc:
            reason = _reason(exc) or _diagnose(path) or "no reason given"
            raise ConfigError(f"cannot create the USD file {path!r}: {reason}") from None

        # The static layer: every prim, its topology and constant attributes, and an unvalued spec of each
        # animated attribute (the frames' samples compose onto them through the clips).
        self.stage = Usd.Stage.CreateInMemory(STATIC_NAME)
        stage = self.stage
        root = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(root.GetPrim())
        self._animated: list = []  # (attribute path, value type) of every attribute sampled per frame
        self._deforming_meshes: dict = {}  # world root → (MeshCollider, points path, extent path) of deforming meshes
        self._strain_ends = None  # the springs' particles, when strain is written
        self._radius = model.particle_radius.numpy().astype(np.float64)  # [m], for emitted particles' widths
        self._pending = None  # (time code, layer) of the frame being saved
        self._clips: list[_Clip] = []  # the clip layers in the frames folder, in time order
        self._loose: list = []  # (time code, layer) of the saved frames not yet gathered into a chunk
        self._loose_bytes = 0  # their size on disk [B]
        self._obsolete: list = []  # (when [s, monotonic], paths) of frame files a chunk replaced, to remove
        if world is not None and model.world_count > 1:
            root.GetPrim().SetCustomDataByKey("warpspring:world", world)
        self.worlds = [w for w, _ in roots]
        self._stopped: dict[int, int] = {}
        self._slots = []
        for w, path_root in roots:
            if offsets is not None:
                xform = UsdGeom.Xform.Define(stage, path_root)
                xform.AddTranslateOp().Set(Gf.Vec3d(*offsets[w]))
                xform.GetPrim().SetCustomDataByKey("warpspring:world", w)
            slot = self._define_world(w, path_root, particles=particles, springs=springs)
            slot.colliders = self._write_colliders(path_root)
            slot.skins = [self._define_skin(skin, w, path_root) for skin in model.skins]
            slot.mesh_colliders = self._deforming_meshes.pop(path_root, [])
            self._slots.append(slot)
        if model.tri_count and any(slot.meshes for slot in self._slots):
            self._normal_topology()
        if "strain" in primvars or springs:
            self._strain_topology()
        try:
            self._export(stage.GetRootLayer(), os.path.join(self.parts, STATIC_NAME))
            self._export(self._manifest(), os.path.join(self.parts, MANIFEST_NAME))
            if kept is not None:
                self._write_kept(kept, keep_frames)
            self._write_root()
        except (OSError, Tf.ErrorException) as exc:
            self._abandon()
            reason = _reason(exc) or _diagnose(path) or "USD gave no reason"
            raise ConfigError(f"cannot create the USD file {path!r}: {reason}") from None
        self.frames_saved = self.frame_count

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
        if any(slot.meshes for slot in live):
            normals_all = self._vertex_normals(state).reshape(q_all.shape)
        rest = self._rest_lengths() if self._strain_ends is not None else None
        kinematic = None
        if "pinned" in self._primvars:
            kinematic = (model.particle_flags.numpy().reshape(model.world_count, -1) & PARTICLE_KINEMATIC) != 0
        seconds = self.frame_count / self.fps
        poses = {shape.name: shape.frame(seconds) for shape in model.shapes if shape.moving}  # same in every world

        Vt, UsdGeom, Gf = self._Vt, self._UsdGeom, self._Gf
        samples = []  # (attribute path, value)
        for slot in live:
            q, v = q_all[slot.world], v_all[slot.world]
            strain = None if rest is None else self._spring_strain(q, rest[slot.world])
            vertex_strain = None if strain is None or "strain" not in self._primvars else self._vertex_strain(strain)
            for mesh in slot.meshes:
                particles = mesh.group.particles
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[particles]))
                samples += [(mesh.points, points), (mesh.extent, UsdGeom.PointBased.ComputeExtent(points)),
                            (mesh.normals, _vec3(Vt, normals_all[slot.world][particles])),
                            (mesh.velocities, _vec3(Vt, v[particles]))]
                if vertex_strain is not None:
                    samples.append((mesh.strain, Vt.FloatArray.FromNumpy(vertex_strain[particles])))
                if kinematic is not None:
                    samples.append((mesh.pinned, Vt.IntArray.FromNumpy(kinematic[slot.world][particles].astype(np.int32))))
            for skin in slot.skins:
                samples += self._skin_samples(skin, q, v, vertex_strain,
                                              kinematic=None if kinematic is None else kinematic[slot.world])
            if slot.points is not None:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q))
                samples += [(slot.points.points, points), (slot.points.velocities, _vec3(Vt, v)),
                            (slot.points.extent, UsdGeom.Points.ComputeExtent(points, self._widths))]
            for prims in slot.emitters:
                samples += self._emitter_samples(prims, slot.world, q, v)
            for curves in slot.curves:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[curves.particles]))
                segment = strain[curves.segments]  # per curve vertex: its two segments (a chain's ends: one)
                samples += [(curves.points, points), (curves.velocities, _vec3(Vt, v[curves.particles])),
                            (curves.extent, UsdGeom.Curves.ComputeExtent(points, self._curve_widths)),
                            (curves.strain, Vt.FloatArray.FromNumpy(segment.max(axis=1).astype(np.float32)))]
            for shape, translate, orient in slot.colliders:
                position, (x, y, z, w) = poses[shape.name]
                samples += [(translate, Gf.Vec3d(*(float(p) for p in position))),
                            (orient, Gf.Quatd(float(w), float(x), float(y), float(z)))]
            for collider, points_path, extent_path in slot.mesh_colliders:  # deforming meshes: their points now
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(collider.points(), dtype=np.float32))
                samples += [(points_path, points), (extent_path, UsdGeom.PointBased.ComputeExtent(points))]
        time_code = self.start_frame + self.frame_count
        self._pending = (time_code, self._frame_layer(time_code, samples))
        self.frame_count += 1
        self._save()

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

    def close(self) -> None:
        """Write the self-contained file (every frame in one layer at ``path``, the frames folder removed) and
        release the stage. Safe to call twice. After a failed save it only releases the stage: the file keeps
        the frames saved before the failure, in the frames folder beside it.

        Raises:
            OutputError: the file could not be written (the frames stay readable through the frames folder).
        """
        if self._closed:
            return
        try:
            if not self._failed:
                self._pack()
        finally:
            self._release()

    def __enter__(self) -> UsdWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- saving ---------------------------------------------------------------------------------------

    def _save(self) -> None:
        """Save the pending frame: its layer into the frames folder, then the root layer that makes it part of
        the stage. A failure releases the writer and raises OutputError; the file keeps the frames before."""
        frames = self.frame_count
        try:
            saved = self._save_layer()
            if saved is not False:
                self._add_clip(*self._pending)
                self._write_root()
        except (OSError, self._Tf.ErrorException) as exc:
            reason, code = _reason(exc), getattr(exc, "errno", None)
        else:
            if saved is not False:
                self.frames_saved = frames
                self._pending = None
                self._gather()
                return
            reason, code = "", None  # USD refused without a word
        if code is None:  # no OS error number: say what the file system shows
            diagnosis = _diagnose(self.path)
            reason = f"{reason} ({diagnosis})" if reason and diagnosis else reason or diagnosis
        reason = reason or "USD gave no reason (a full disk, or the file or its folder removed?)"
        saved = self.frames_saved
        lost = frames - saved
        what = f"frame {saved}" if lost == 1 else f"frames {saved}..{frames - 1}"
        held = f"frames 0..{saved - 1}" if saved > 1 else "frame 0" if saved == 1 else "no frame"
        self._failed = True
        self._release()  # the unsaved frame is dropped: the file keeps what was saved
        raise OutputError(f"cannot write {what} to the USD file {self.path!r}: {reason}; the file holds {held}",
                          path=self.path, frame=saved, frames_saved=saved, code=code)

    def _save_layer(self) -> bool:
        """Write the pending frame's layer into the frames folder: whether USD saved it (it may also raise
        OSError or Tf.ErrorException)."""
        time_code, layer = self._pending
        return self._export(layer, os.path.join(self.parts, frame_name(time_code, self._format)))

    def _export(self, layer, path: str) -> bool:
        """Write ``layer`` to ``path`` whole (USD writes a temporary file and renames it: a reader sees the
        old file or the new one, never a part)."""
        return layer.Export(path)

    def _add_clip(self, time_code: float, layer) -> None:
        """Count a frame saved in the frames folder as a clip of the stage, and keep its layer for its chunk."""
        name = frame_name(time_code, self._format)
        size = os.path.getsize(os.path.join(self.parts, name))
        self._clips.append(_Clip(time_code, time_code, name, -1, size))
        self._loose.append((time_code, layer))
        self._loose_bytes += size

    def _gather(self) -> None:
        """Keep the clips few, so that rewriting the root and opening the stage cost the same at any frame: the
        loose frames go into a chunk layer once they are many or large, and two neighbouring chunks of one
        level merge into one of the next level while together they stay below ``_CHUNK_BYTES`` (a binary
        counter: about log2 of the frames' chunks, plus one per ``_CHUNK_BYTES`` of frames). Frame and chunk
        files a merge replaced are removed ``_GRACE`` seconds later."""
        now = time.monotonic()
        while self._obsolete and self._obsolete[0][0] <= now:  # readers had _GRACE seconds to finish with them
            for path in self._obsolete.pop(0)[1]:
                try:
                    os.remove(path)
                except OSError:
                    pass
        if len(self._loose) < _CHUNK_FRAMES and self._loose_bytes < _CHUNK_BYTES:
            return
        loose, self._loose, self._loose_bytes = self._loose, [], 0
        if len(loose) >= 2:
            chunk = self._Sdf.Layer.CreateAnonymous(self._format)
            for _, layer in loose:
                self._copy_samples(layer, chunk)
            if not self._replace_clips(len(loose), chunk, level=0):
                return
        while len(self._clips) >= 2:
            a, b = self._clips[-2:]
            if a.level < 0 or a.level != b.level or a.size + b.size > _CHUNK_BYTES:
                return
            merged = self._Sdf.Layer.CreateAnonymous(self._format)
            for clip in (a, b):
                self._copy_samples(self._Sdf.Layer.OpenAsAnonymous(os.path.join(self.parts, clip.name)), merged)
            if not self._replace_clips(2, merged, level=a.level + 1):
                return

    def _replace_clips(self, count: int, layer, *, level: int) -> bool:
        """Write ``layer`` as one chunk in place of the last ``count`` clips, then the root that uses it;
        whether it worked (if not, the clips stay as they were: the file is as valid)."""
        replaced = self._clips[-count:]
        first, last = replaced[0].first, replaced[-1].last
        name = chunk_name(first, last, self._format)
        path = os.path.join(self.parts, name)
        clips = self._clips
        try:
            self._export(layer, path)
            self._clips = clips[:-count] + [_Clip(first, last, name, level, os.path.getsize(path))]
            self._write_root()
        except (OSError, self._Tf.ErrorException):
            self._clips = clips
            return False
        old = [os.path.join(self.parts, clip.name) for clip in replaced]
        self._obsolete.append((time.monotonic() + _GRACE, old))
        self._reaper.obsolete(old)
        return True

    def _copy_samples(self, source, target) -> None:
        """Copy every animated attribute's samples of layer ``source`` into layer ``target``."""
        Sdf = self._Sdf
        for attribute, value_type in self._animated:
            if not source.GetAttributeAtPath(attribute):
                continue
            if not target.GetAttributeAtPath(attribute):
                prim = Sdf.CreatePrimInLayer(target, attribute.GetPrimPath())
                Sdf.AttributeSpec(prim, attribute.name, value_type, Sdf.VariabilityVarying)
            for time_code in source.ListTimeSamplesForPath(attribute):
                target.SetTimeSample(attribute, time_code, source.QueryTimeSample(attribute, time_code))

    def _write_root(self) -> None:
        """Write the root layer at :attr:`path`: the stage's metadata, the static layer as a sublayer and the
        saved frames as value clips (chunks of frames, then the latest frames one by one)."""
        Sdf, Vt, Gf = self._Sdf, self._Vt, self._Gf
        layer = Sdf.Layer.CreateAnonymous(self._format)
        last = self.start_frame + max(self.frame_count - 1, 0)
        self._stage_metadata(layer, end=max(last, self.start_frame + 1))
        folder = os.path.basename(self.parts)
        layer.subLayerPaths.append(f"./{folder}/{STATIC_NAME}")
        if self._clips:
            world = Sdf.CreatePrimInLayer(layer, "/World")
            world.specifier = Sdf.SpecifierOver
            start = float(self.start_frame)
            world.SetInfo("clips", {"default": {
                "assetPaths": Sdf.AssetPathArray([Sdf.AssetPath(f"./{folder}/{c.name}") for c in self._clips]),
                "active": Vt.Vec2dArray([Gf.Vec2d(float(c.first), float(i)) for i, c in enumerate(self._clips)]),
                "times": Vt.Vec2dArray([Gf.Vec2d(start, start), Gf.Vec2d(float(last), float(last))]),
                "primPath": "/World",
                "manifestAssetPath": Sdf.AssetPath(f"./{folder}/{MANIFEST_NAME}"),
                "interpolateMissingClipValues": True,  # a stopped world holds its last sample
            }})
        self._export(layer, self.path)

    def _stage_metadata(self, layer, *, end: float) -> None:
        """Author what DCC tools need to play the file (USD's fallbacks are wrong for simulation caches)."""
        layer.defaultPrim = "World"
        layer.pseudoRoot.SetInfo("upAxis", self.model.up_axis)
        layer.pseudoRoot.SetInfo("metersPerUnit", 1.0)
        layer.timeCodesPerSecond = self.fps
        layer.framesPerSecond = self.fps
        layer.startTimeCode = float(self.start_frame)
        layer.endTimeCode = float(end)
        layer.customLayerData = {"generator": f"warpspring {__version__} (warp {wp.__version__})"}

    def _manifest(self):
        """The clips' manifest: every animated attribute, declared with its type and no value."""
        Sdf = self._Sdf
        layer = Sdf.Layer.CreateAnonymous(".usda")
        for attribute, value_type in self._animated:
            prim = Sdf.CreatePrimInLayer(layer, attribute.GetPrimPath())
            Sdf.AttributeSpec(prim, attribute.name, value_type, Sdf.VariabilityVarying)
        return layer

    def _frame_layer(self, time_code: float, samples: list):
        """A layer holding one frame's samples, each (attribute path, value), at ``time_code``."""
        Sdf = self._Sdf
        layer = Sdf.Layer.CreateAnonymous(self._format)
        types = self._types
        for attribute, value in samples:
            prim = Sdf.CreatePrimInLayer(layer, attribute.GetPrimPath())
            Sdf.AttributeSpec(prim, attribute.name, types[attribute], Sdf.VariabilityVarying)
            layer.SetTimeSample(attribute, time_code, value)
        return layer

    def _write_kept(self, kept: list, frames: int) -> None:
        """Write the frames of a stopped run being resumed, (attribute path, [(time code, value)]) pairs."""
        by_time: dict[float, list] = {}
        for attribute, values in kept:
            if attribute not in self._types:
                raise ConfigError(f"cannot resume {self.path!r}: it holds {attribute}, which this scene does not "
                                  "write (another scene or other export options)")
            for time_code, value in values:
                by_time.setdefault(time_code, []).append((attribute, value))
        for time_code in sorted(by_time):
            self._pending = (time_code, self._frame_layer(time_code, by_time[time_code]))
            self._save_layer()
            self._add_clip(*self._pending)
            self._gather()
        self._pending = None
        self.frame_count = frames

    def _pack(self) -> None:
        """Replace the root layer by one self-contained layer of every saved frame (the static layer with the
        frames' samples), written beside it and renamed over it, then remove the frames folder."""
        Sdf = self._Sdf
        packed = os.path.join(self.parts, PACKED_NAME + self._format)
        try:
            static = os.path.join(self.parts, STATIC_NAME)
            layer = Sdf.Layer.Find(packed)  # a stale one of an earlier writer of this path, in this process
            if layer is not None:
                layer.Clear()
            else:
                layer = Sdf.Layer.CreateNew(packed)
            layer.TransferContent(Sdf.Layer.FindOrOpen(static))
            self._stage_metadata(layer, end=self.start_frame + max(self.frames_saved - 1, 1))
            pending = 0  # bytes of samples (on disk, as clip files) gathered since the last save
            for clip in self._clips:
                clip_path = os.path.join(self.parts, clip.name)
                self._copy_samples(Sdf.Layer.OpenAsAnonymous(clip_path), layer)
                pending += os.path.getsize(clip_path)
                if not self._text and pending >= _PACK_FLUSH_BYTES:
                    layer.Save()  # a crate appends: the samples saved leave memory
                    pending = 0
            if not layer.Save():
                raise OSError("USD did not save the packed file")
            del layer
            os.replace(packed, self.path)
        except (OSError, self._Tf.ErrorException) as exc:
            self._failed = True
            reason = _reason(exc) or _diagnose(self.path) or "USD gave no reason"
            raise OutputError(f"cannot pack the USD file {self.path!r} into one file: {reason}; it holds frames "
                              f"0..{self.frames_saved - 1} through its frames folder {self.parts!r}",
                              path=self.path, frames_saved=self.frames_saved,
                              code=getattr(exc, "errno", None)) from None
        self._reaper.packed()
        shutil.rmtree(self.parts, ignore_errors=True)
        layer = Sdf.Layer.Find(self.path)
        if layer is not None:  # a stale layer of this path in this process's registry: read the new file
            layer.Reload()

    @property
    def _text(self) -> bool:
        return self._format == ".usda"

    def _release(self) -> None:
        """Drop the stage, and end the reaper: cleanly after a packed file, else it keeps the frames folder
        (the file's frames) and removes only temporaries."""
        self._closed = True
        self.stage = None
        self._slots = []
        self._pending = None
        if self._reaper is not None:
            self._reaper.finish()
            self._reaper = None

    def _abandon(self) -> None:
        """Undo a writer whose set-up failed: remove what it wrote."""
        self._release()
        shutil.rmtree(self.parts, ignore_errors=True)
        if os.path.isfile(self.path):
            os.remove(self.path)

    # -- prims ----------------------------------------------------------------------------------------

    def _animate(self, attribute):
        """Record ``attribute`` (a Usd.Attribute of the static stage) as sampled per frame; its path."""
        path = attribute.GetPath()
        self._animated.append((path, attribute.GetTypeName()))
        return path

    @property
    def _types(self) -> dict:
        return dict(self._animated)

    def _define_polygon_mesh(self, path: str, group):
        """A Mesh prim at ``path`` with ``group``'s faces as authored (its polygons where it has them, quads
        staying quads; else its triangles) and the attributes every warpspring surface carries: no
        subdivision, double-sided, right-handed, per-vertex normals. ``group``: a MeshGroup or a SkinGroup."""
        UsdGeom, Vt = self._UsdGeom, self._Vt
        mesh = UsdGeom.Mesh.Define(self.stage, path)
        if group.polygon_counts is not None:
            counts, indices = group.polygon_counts, group.polygon_indices
        else:
            counts, indices = np.full(len(group.faces), 3, np.int32), group.faces.reshape(-1)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts.astype(np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(indices.astype(np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateDoubleSidedAttr(True)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        return mesh

    def _define_world(self, world: int, root: str, *, particles: bool, springs: bool) -> _WorldPrims:
        """Define the prims of one exported world under ``root``; topology and constant attributes once."""
        from pxr import Sdf

        stage, UsdGeom, Vt, model = self.stage, self._UsdGeom, self._Vt, self.model
        meshes = []
        for group in model.meshes:
            mesh = self._define_polygon_mesh(f"{root}/{group.name}", group)
            primvars = UsdGeom.PrimvarsAPI(mesh)
            if group.uvs is not None:  # per vertex, or per corner where seams give a particle two UVs
                corners = group.uvs.ndim == 3
                st = primvars.CreatePrimvar(
                    "st", Sdf.ValueTypeNames.TexCoord2fArray,
                    UsdGeom.Tokens.faceVarying if corners else UsdGeom.Tokens.vertex,
                )
                st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(group.uvs.reshape(-1, 2), dtype=np.float32)))
            for name, faces in group.face_sets.items():
                UsdGeom.Subset.CreateGeomSubset(mesh, name, UsdGeom.Tokens.face, Vt.IntArray.FromNumpy(faces),
                                                familyName="warpspring")
            strain = pinned = None
            if "strain" in self._primvars:
                strain = self._animate(primvars.CreatePrimvar(
                    "strain", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).GetAttr())
            if "pinned" in self._primvars:
                pinned = self._animate(primvars.CreatePrimvar(
                    "pinned", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).GetAttr())
            if "rest" in self._primvars:  # the world's positions at the start
                q0 = model.particle_q.numpy().reshape(model.world_count, model.particle_count, 3)[world]
                primvars.CreatePrimvar("rest", Sdf.ValueTypeNames.Point3fArray, UsdGeom.Tokens.vertex).Set(
                    _vec3(Vt, q0[group.particles]))
            meshes.append(_MeshPrims(
                group,
                points=self._animate(mesh.CreatePointsAttr()),
                extent=self._animate(mesh.CreateExtentAttr()),
                normals=self._animate(mesh.CreateNormalsAttr()),
                velocities=self._animate(mesh.CreateVelocitiesAttr()),
                strain=strain, pinned=pinned,
            ))

        points = None
        if particles:
            prim = UsdGeom.Points.Define(stage, f"{root}/particles")
            radius = model.particle_radius.numpy().astype(np.float32)
            self._widths = Vt.FloatArray.FromNumpy(2.0 * radius)
            prim.CreateWidthsAttr(self._widths)
            prim.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            points = _PointsPrims(points=self._animate(prim.CreatePointsAttr()),
                                  extent=self._animate(prim.CreateExtentAttr()),
                                  velocities=self._animate(prim.CreateVelocitiesAttr()))

        curves = []
        if springs and model.spring_count:
            UsdGeom.Scope.Define(stage, f"{root}/springs")
            width = float(0.5 * model.particle_radius.numpy().mean()) or 1.0e-3
            self._curve_widths = Vt.FloatArray([width])
            ends = model.spring_indices.numpy()
            for family, members in model.spring_families.items():
                counts, particles, segments = spring_chains(ends[members])
                prim = UsdGeom.BasisCurves.Define(stage, f"{root}/springs/{family}")
                prim.CreateTypeAttr(UsdGeom.Tokens.linear)
                prim.CreateCurveVertexCountsAttr(Vt.IntArray.FromNumpy(counts))
                prim.CreateWidthsAttr(self._curve_widths)
                prim.SetWidthsInterpolation(UsdGeom.Tokens.constant)
                api = UsdGeom.PrimvarsAPI(prim)
                api.CreatePrimvar("warpspring:particle", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
                    Vt.IntArray.FromNumpy(particles))
                strain = api.CreatePrimvar("strain", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).GetAttr()
                curves.append(_CurvePrims(
                    particles=particles, segments=members[segments],
                    points=self._animate(prim.CreatePointsAttr()), extent=self._animate(prim.CreateExtentAttr()),
                    velocities=self._animate(prim.CreateVelocitiesAttr()), strain=self._animate(strain),
                ))
        emitters = []
        for emitter in model.emitters:  # the live particles only, with their birth serials as stable ids
            prim = UsdGeom.Points.Define(stage, f"{root}/{emitter.name}")
            prim.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            emitters.append(_EmitterPrims(
                emitter, points=self._animate(prim.CreatePointsAttr()), ids=self._animate(prim.CreateIdsAttr()),
                widths=self._animate(prim.CreateWidthsAttr()), velocities=self._animate(prim.CreateVelocitiesAttr()),
                extent=self._animate(prim.CreateExtentAttr()),
            ))
        return _WorldPrims(world, meshes, points, curves, emitters)

    def _define_skin(self, skin, world: int, root: str) -> _SkinPrims:
        """Define the USD mesh of a surface embedded in the particles (a soft body's mesh as authored): its faces,
        UVs and face sets once, like a cloth mesh's; its points, extent, normals and velocities per frame."""
        from pxr import Sdf

        UsdGeom, Vt, model = self._UsdGeom, self._Vt, self.model
        mesh = self._define_polygon_mesh(f"{root}/{skin.name}", skin)
        primvars = UsdGeom.PrimvarsAPI(mesh)
        if skin.uvs is not None:
            primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
                Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(skin.uvs, dtype=np.float32)))
        for name, faces in skin.face_sets.items():
            UsdGeom.Subset.CreateGeomSubset(mesh, name, UsdGeom.Tokens.face, Vt.IntArray.FromNumpy(faces),
                                            familyName="warpspring")
        strain = None
        if "strain" in self._primvars:
            strain = self._animate(primvars.CreatePrimvar(
                "strain", Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex).GetAttr())
        if "rest" in self._primvars:
            q0 = model.particle_q.numpy().reshape(model.world_count, model.particle_count, 3)[world]
            primvars.CreatePrimvar("rest", Sdf.ValueTypeNames.Point3fArray, UsdGeom.Tokens.vertex).Set(
                _vec3(Vt, skin.points(q0)))
        pinned = None
        if "pinned" in self._primvars:  # per frame: 1 where every particle the vertex follows is pinned
            pinned = self._animate(primvars.CreatePrimvar(
                "pinned", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).GetAttr())
        return _SkinPrims(skin, points=self._animate(mesh.CreatePointsAttr()),
                          extent=self._animate(mesh.CreateExtentAttr()),
                          normals=self._animate(mesh.CreateNormalsAttr()),
                          velocities=self._animate(mesh.CreateVelocitiesAttr()), strain=strain, pinned=pinned)

    def _skin_samples(self, prims, q: np.ndarray, v: np.ndarray, vertex_strain, *, kinematic=None) -> list:
        """One frame's samples of an embedded surface: its vertices Σ w x and velocities Σ w v by a host product
        over the positions already read back (no extra transfer, a fixed order: the same bytes on a rerun),
        area-weighted vertex normals, and the weighted mean of its particles' strain [-] when asked for."""
        Vt, UsdGeom = self._Vt, self._UsdGeom
        skin = prims.skin
        x = skin.points(q)
        corner = x[skin.faces]
        face_normal = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])  # length 2 × area
        normal = np.zeros_like(x)
        for k in range(3):
            np.add.at(normal, skin.faces[:, k], face_normal)
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0.0)
        points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(x, dtype=np.float32))
        samples = [(prims.points, points), (prims.extent, UsdGeom.PointBased.ComputeExtent(points)),
                   (prims.normals, _vec3(Vt, normal)), (prims.velocities, _vec3(Vt, skin.points(v)))]
        if prims.strain is not None and vertex_strain is not None:
            strain = (skin.weights * vertex_strain[skin.indices]).sum(axis=1)
            samples.append((prims.strain, Vt.FloatArray.FromNumpy(strain.astype(np.float32))))
        if prims.pinned is not None and kinematic is not None:  # held: no weight on a free particle
            held = ~((skin.weights != 0.0) & ~kinematic[skin.indices]).any(axis=1)
            samples.append((prims.pinned, Vt.IntArray.FromNumpy(held.astype(np.int32))))
        return samples

    def _emitter_samples(self, prims, world: int, q: np.ndarray, v: np.ndarray) -> list:
        """One frame's samples of an emitter's live particles in ``world``: points, ids, widths, velocities,
        extent (a point at the emitter's centre when none lives)."""
        Vt, Gf = self._Vt, self._Gf
        emitter = prims.emitter
        serial = emitter.serials(world)
        live = np.flatnonzero(serial >= 0)
        index = emitter.first + live
        points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[index]))
        widths = Vt.FloatArray.FromNumpy((2.0 * self._radius[index]).astype(np.float32))
        if len(live):
            extent = self._UsdGeom.Points.ComputeExtent(points, widths)
        else:
            c = Gf.Vec3f(*(float(x) for x in emitter.center))
            extent = Vt.Vec3fArray([c, c])
        return [(prims.points, points), (prims.ids, Vt.Int64Array.FromNumpy(serial[live].astype(np.int64))),
                (prims.widths, widths), (prims.velocities, _vec3(Vt, v[index])), (prims.extent, extent)]

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

    def _vertex_normals(self, state: State) -> np.ndarray:
        """Unit vertex normals of every particle, shape [state_size, 3] (those of exported worlds' meshes set)."""
        model = self.model
        wp.launch(vertex_normal_kernel(model.scalar), dim=model.state_size,
                  inputs=[self._export_tris, self._vertex_tri_start, self._vertex_tris, state.particle_q],
                  outputs=[self._normals], device=model.device)
        return self._normals.numpy()

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

    def _write_colliders(self, root: str) -> list:
        """Define the collider prims of one exported world under ``root``, each of the chosen purpose and posed
        at rest; returns (ShapeInfo, translate path, orient path) of each moving collider, sampled every frame."""
        from pxr import Gf, Vt

        UsdGeom = self._UsdGeom
        model = self.model
        if not model.shapes:
            return []
        UsdGeom.Scope.Define(self.stage, f"{root}/colliders")
        q0 = model.particle_q.numpy()
        moving = []
        for shape in model.shapes:
            path = f"{root}/colliders/{shape.name}"
            scale = None
            if shape.kind == "sphere":
                prim = UsdGeom.Sphere.Define(self.stage, path)
                r = float(shape.size[0])
                prim.CreateRadiusAttr(r)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-r, -r, -r), Gf.Vec3f(r, r, r)]))
            elif shape.kind == "box":  # a cube of size 2 spans ±1: scaled by the half extents, it spans the box
                prim = UsdGeom.Cube.Define(self.stage, path)
                prim.CreateSizeAttr(2.0)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-1.0, -1.0, -1.0), Gf.Vec3f(1.0, 1.0, 1.0)]))
                scale = Gf.Vec3d(*shape.size)
            elif shape.kind == "capsule":
                prim = UsdGeom.Capsule.Define(self.stage, path)
                r, half = float(shape.size[0]), float(shape.size[1])
                prim.CreateRadiusAttr(r)
                prim.CreateHeightAttr(2.0 * half)  # USD's height is the spine's length, without the caps
                prim.CreateAxisAttr(UsdGeom.Tokens.z)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-r, -r, -half - r), Gf.Vec3f(r, r, half + r)]))
            elif shape.kind == "plane":
                prim = UsdGeom.Mesh.Define(self.stage, path)
                half = _plane_half_size(shape, q0, self._tile)
                corners = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], np.float32)
                prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(corners))
                prim.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
                prim.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
                prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                prim.CreateDoubleSidedAttr(True)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-half, -half, 0), Gf.Vec3f(half, half, 0)]))
            elif shape.kind == "mesh":  # its triangles in its own frame; a deforming one's points sampled every frame
                prim = UsdGeom.Mesh.Define(self.stage, path)
                collider = model.mesh_collider(model.shapes.index(shape))
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(collider.points(), dtype=np.float32))
                prim.CreatePointsAttr(points)
                prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(shape.mesh.faces), 3, np.int32)))
                prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(shape.mesh.faces.reshape(-1).astype(np.int32)))
                prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                prim.CreateDoubleSidedAttr(shape.mesh.sides != "closed")
                prim.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
                if shape.mesh.deforming:
                    self._deforming_meshes.setdefault(root, []).append(
                        (collider, self._animate(prim.GetPointsAttr()), self._animate(prim.GetExtentAttr())))
            else:  # pragma: no cover - every collider kind is exported; a new kind must add a branch
                raise NotImplementedError(f"USD export of {shape.kind} colliders")
            prim.CreatePurposeAttr(self._purpose)
            translate = prim.AddTranslateOp()  # double precision, as the shape's frame
            orient = prim.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
            if scale is not None:
                prim.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(scale)
            _set_pose(translate, orient, shape.frame(0.0))  # default value: the rest pose, or a moving one's at t = 0
            if shape.moving:
                moving.append((shape, self._animate(translate.GetAttr()), self._animate(orient.GetAttr())))
        return moving


#: The optional per-vertex primvars of :class:`UsdWriter`.
PRIMVARS = ("strain", "pinned", "rest")
#: The purposes a collider prim may have.
PURPOSES = ("guide", "default", "render", "proxy")
#: Names inside the frames folder.
STATIC_NAME = "static.usdc"
MANIFEST_NAME = "manifest.usda"
PACKED_NAME = "packed"
#: Bytes of samples a packed crate file gathers between two saves (each save appends them to the file).
_PACK_FLUSH_BYTES = 256 << 20
#: Frames, or bytes of frames, gathered into one chunk layer while a run writes.
_CHUNK_FRAMES = 100
_CHUNK_BYTES = 64 << 20
#: Seconds a frame file a chunk replaced stays, for readers that opened the root before the chunk came.
_GRACE = 10.0


def parts_folder(path: str) -> str:
    """The folder beside ``path`` that holds its frames while a run writes them (``out.usdc.frames``)."""
    return path + ".frames"


def frame_name(time_code: float, fmt: str) -> str:
    """The file name of one frame's layer in the frames folder."""
    return f"frame.{int(time_code):06d}{fmt}"


def chunk_name(first: float, last: float, fmt: str) -> str:
    """The file name of a chunk of the frames of time codes ``first`` .. ``last`` in the frames folder."""
    return f"chunk.{int(first):06d}-{int(last):06d}{fmt}"


class _Clip(NamedTuple):
    """One clip layer of the stage while it is written: a frame (level -1) or a chunk of frames."""

    first: float  # time code of its first frame
    last: float  # time code of its last frame
    name: str  # file name in the frames folder
    level: int  # -1: one frame; 0: a chunk of loose frames; k + 1: two chunks of level k merged
    size: int  # bytes on disk


def _remove_output(path: str) -> None:
    """Remove an earlier output at ``path`` and its frames folder (a killed run's)."""
    from pxr import Sdf

    if os.path.exists(path):
        os.remove(path)
    shutil.rmtree(parts_folder(path), ignore_errors=True)
    layer = Sdf.Layer.Find(path)
    if layer is not None:  # a stale layer of the same name in this process's registry
        layer.Clear()


def _vec3(Vt, values: np.ndarray):
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(values, dtype=np.float32))


def spring_chains(ends: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Springs as few linear chains as pairing them at each particle gives (each spring once): a grid's
    structural springs become its rows and columns, so a chain's inner points are shared by two springs.

    Args:
        ends: the two particles of each spring, shape [s, 2].

    Returns:
        counts: vertices per chain, shape [c], int32; particles: the particle of each chain vertex, shape
        [counts.sum()], int32; segments: for each chain vertex, the springs (indices into ``ends``) on either
        side of it, shape [counts.sum(), 2], int64 (a chain's end vertex repeats its one spring).
    """
    s = len(ends)
    corner = np.asarray(ends, dtype=np.int64).ravel()  # corner 2i + side is spring i's end at that side
    order = np.argsort(corner, kind="stable")
    sorted_vertex = corner[order]
    group_start = np.flatnonzero(np.r_[True, np.diff(sorted_vertex) != 0])
    rank = np.arange(2 * s) - np.repeat(group_start, np.diff(np.r_[group_start, 2 * s]))
    first = np.flatnonzero((rank % 2 == 0)[:-1] & (sorted_vertex[:-1] == sorted_vertex[1:]))
    mate = np.full(2 * s, -1, dtype=np.int64)  # the corner a chain continues through at the same particle
    mate[order[first]], mate[order[first + 1]] = order[first + 1], order[first]
    visited = np.zeros(s, dtype=bool)
    counts, particles, segments = [], [], []
    starts = np.r_[np.flatnonzero(mate < 0), np.arange(2 * s)]  # open chains first, then closed loops
    for begin in starts.tolist():
        if visited[begin // 2]:
            continue
        chain, springs = [int(corner[begin])], []
        c = begin
        while True:
            spring = c // 2
            visited[spring] = True
            springs.append(spring)
            other = c ^ 1
            chain.append(int(corner[other]))
            c = int(mate[other])
            if c < 0 or visited[c // 2]:
                break
        counts.append(len(chain))
        particles.extend(chain)
        springs = np.asarray(springs)
        segments.append(np.stack([np.r_[springs[:1], springs], np.r_[springs, springs[-1:]]], axis=1))
    return (np.asarray(counts, dtype=np.int32), np.asarray(particles, dtype=np.int32),
            np.concatenate(segments) if segments else np.zeros((0, 2), dtype=np.int64))


class _Reaper:
    """A small process that outlives a killed run: when the writer's process dies without finishing (even by
    SIGKILL, which no handler sees), it removes the temporary files USD was writing (USD writes a file as
    its name less the extension + "." + 6 characters, then renames it), so that a killed run leaves its file,
    its frames folder and nothing else. It notices the writer's death as the end of a pipe."""

    _CODE = r"""
import os, re, shutil, sys, time
parts, path = sys.argv[1:3]
started = time.time() - 1.0
said = sys.stdin.read().split("\n")
if "done" not in said:
    for line in said:
        if line.startswith("obsolete "):
            try:
                os.remove(line[len("obsolete "):])
            except OSError:
                pass
    for name in os.listdir(parts) if os.path.isdir(parts) else []:
        if name.startswith("packed.") or not name.endswith((".usdc", ".usda")):  # USD's temporaries
            try:
                os.remove(os.path.join(parts, name))
            except OSError:
                pass
    folder, stem = os.path.split(os.path.splitext(path)[0])
    pattern = re.compile(re.escape(stem) + r"\.[A-Za-z0-9]{6}$")
    for name in os.listdir(folder):
        full = os.path.join(folder, name)
        try:
            if pattern.match(name) and os.path.getmtime(full) >= started:
                os.remove(full)
        except OSError:
            pass
    if "packed" in said:
        shutil.rmtree(parts, ignore_errors=True)
"""

    def __init__(self, path: str):
        import subprocess
        import sys

        self._process = subprocess.Popen(
            [sys.executable, "-c", self._CODE, parts_folder(path), os.path.abspath(path)], stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, close_fds=True, start_new_session=True, text=True,
        )

    def _tell(self, word: str) -> None:
        try:
            self._process.stdin.write(word + "\n")
            self._process.stdin.flush()
        except (OSError, ValueError):
            pass

    def obsolete(self, paths: list) -> None:
        """Frame files that a chunk replaced: removed by the writer after a grace period, or by the reaper."""
        for path in paths:
            self._tell(f"obsolete {path}")

    def packed(self) -> None:
        """The self-contained file replaced the root: the frames folder is no longer needed."""
        self._tell("packed")

    def finish(self) -> None:
        """The writer ended on its own: nothing to clean up."""
        self._tell("done")
        try:
            self._process.stdin.close()
        except OSError:
            pass
        self._process.wait()


@dataclass
class _MeshPrims:
    """The animated attributes (paths) of one exported cloth mesh."""

    group: object  # MeshGroup
    points: object
    extent: object
    normals: object
    velocities: object
    strain: object = None
    pinned: object = None


@dataclass
class _SkinPrims:
    """The animated attributes (paths) of one exported embedded surface (a soft body's mesh)."""

    skin: object  # SkinGroup
    points: object
    extent: object
    normals: object
    velocities: object
    strain: object = None
    pinned: object = None


@dataclass
class _PointsPrims:
    """The animated attributes (paths) of the particles' points prim."""

    points: object
    extent: object
    velocities: object


@dataclass
class _CurvePrims:
    """One spring family's curves: the particle of each curve vertex, the springs beside it, and the animated
    attributes (paths)."""

    particles: np.ndarray
    segments: np.ndarray
    points: object
    extent: object
    velocities: object
    strain: object


@dataclass
class _EmitterPrims:
    """An emitter's points prim: its animated attributes (paths)."""

    emitter: object  # core.emitters.Emitter
    points: object
    ids: object
    widths: object
    velocities: object
    extent: object


@dataclass
class _WorldPrims:
    """The animated prims of one exported world."""

    world: int
    meshes: list  # _MeshPrims per cloth mesh
    points: object  # _PointsPrims of the particles, or None
    curves: list  # _CurvePrims per spring family
    emitters: list = field(default_factory=list)  # _EmitterPrims per emitter
    colliders: list = field(default_factory=list)  # (ShapeInfo, translate path, orient path) per moving collider
    skins: list = field(default_factory=list)  # _SkinPrims per embedded surface (soft bodies)
    mesh_colliders: list = field(default_factory=list)  # (MeshCollider, points path, extent path) per deforming mesh


def _set_pose(translate, orient, frame, time=None) -> None:
    """Set a collider's translate and orient ops to ``frame`` = (position [m], quaternion (x, y, z, w)): as a
    time sample at ``time``, or as the default value when ``time`` is None."""
    from pxr import Gf, Usd

    position, (x, y, z, w) = frame
    time = Usd.TimeCode.Default() if time is None else time
    translate.Set(Gf.Vec3d(*(float(p) for p in position)), time)
    orient.Set(Gf.Quatd(float(w), float(x), float(y), float(z)), time)


def _read_frames(path: str, frames: int, start_frame: int) -> list:
    """Every time sample of the first ``frames`` frames (time codes ``start_frame`` ..) of the USD file at
    ``path``, packed or a killed run's (read through its frames folder): (attribute path, [(time code, value)])
    pairs, read into memory so that the file can be replaced."""
    from pxr import Sdf, Tf, Usd

    if not os.path.isfile(path):
        raise ConfigError(f"cannot resume into {path!r}: the file is missing (resume writes into the stopped run's "
                          "output: pass the same -o)")
    try:
        layer = Sdf.Layer.FindOrOpen(path)
        if layer is not None:
            layer.Reload()
        stage = Usd.Stage.Open(layer if layer is not None else path)
    except Tf.ErrorException as exc:
        raise ConfigError(f"cannot resume into {path!r}: USD cannot read it ({_reason(exc) or 'no reason'})") from None
    kept, last = [], -1.0
    end = start_frame + frames
    for prim in stage.Traverse():
        for attribute in prim.GetAttributes():
            times = attribute.GetTimeSamples()
            last = max([last, *times])
            times = [t for t in times if start_frame <= t < end]
            if times:
                kept.append((attribute.GetPath(), [(t, attribute.Get(Usd.TimeCode(t))) for t in times]))
    del stage
    held = int(last) + 1 - start_frame
    if held < frames:
        raise ConfigError(f"cannot resume into {path!r}: it holds frames 0..{held - 1}, the checkpoint continues "
                          f"after frame {frames - 1}")
    return kept


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


def check_output_path(path: str | os.PathLike) -> str:
    """``path`` as a string if it can name a USD output file, else a ConfigError saying what is wrong.

    The extension picks the format (``.usdc`` or ``.usd``: binary crate; ``.usda``: text) and the folder
    must exist. Checked before a run builds its model, so a bad ``-o`` fails at once.
    """
    path = os.fspath(path)
    if os.path.splitext(path)[1].lower() not in _EXTENSIONS:
        raise ConfigError(f"USD output must end in .usdc (binary), .usda (text) or .usd (binary), got {path!r}")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ConfigError(f"output folder does not exist: {folder}")
    if os.path.isdir(path):
        raise ConfigError(f"USD output {path!r} is a folder, not a file")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"USD output {path!r} cannot be written: {os.strerror(errno.EACCES)} [EACCES] to "
                          f"create files in {folder}; check its permissions")
    if os.path.exists(path) and not os.access(path, os.W_OK):
        raise ConfigError(f"USD output {path!r} cannot be written: the file is read-only; check its permissions")
    problem = _probe_folder(folder)  # permissions do not tell all (a read-only or virtual file system, a quota)
    if problem:
        raise ConfigError(f"USD output {path!r} cannot be written: {problem}")
    return path


def _probe_folder(folder: str) -> str:
    """Why no file can be created in ``folder`` (the OS's reason), or "" when a probe file can be."""
    try:
        handle, probe = tempfile.mkstemp(prefix=".warpspring-", suffix=".probe", dir=folder)
    except OSError as exc:
        return f"cannot create a file in {folder}: {os_error_reason(exc)}"
    os.close(handle)
    try:
        os.remove(probe)
    except OSError:
        pass
    return ""


def _reason(error: BaseException) -> str:
    """The reason an OS or USD (Tf) error gives, on one line; "" when it gives none. A Tf error's text is
    USD's call stack: only its messages (the quoted last part of each entry) are kept."""
    if isinstance(error, OSError) and (error.strerror or error.errno):
        return os_error_reason(error)
    entries = [str(a) for a in getattr(error, "args", ()) if str(a).strip()] or [str(error)]
    messages = []
    for entry in entries:
        for line in entry.strip().splitlines():
            found = re.search(r" : '(.*)'\s*$", line.strip())
            message = " ".join((found.group(1) if found else line).split())
            if message and message not in messages:
                messages.append(message)
    return "; ".join(messages)


def _diagnose(path: str) -> str:
    """What the file system shows about writing ``path`` when a write failed without an OS reason: a full
    disk, a folder that is gone or refuses new files, a read-only file; "" when nothing is wrong there."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        return f"its folder {folder} does not exist"
    try:
        fs = os.statvfs(folder)
    except OSError:
        fs = None
    if fs is not None and fs.f_blocks > 0 and fs.f_bavail * fs.f_frsize < _LOW_SPACE:  # (virtual file systems: 0)
        return f"{os.strerror(errno.ENOSPC)} [ENOSPC]: {fs.f_bavail * fs.f_frsize} bytes free in {folder}"
    if os.path.exists(path) and not os.access(path, os.W_OK):
        return "the file is read-only"
    return _probe_folder(folder)


#: Free space [B] below which a failed write is put down to a full disk.
_LOW_SPACE = 1 << 20


def _plane_half_size(shape, particle_q: np.ndarray, tile: float | None = None) -> float:
    """Half width [m] of the quad that shows a plane: a finite plane's own; an infinite plane's twice the
    scene's reach around it, ≥ 1 m, and at most ``tile`` (half a world's cell when worlds are laid out
    side by side, so that their ground quads tile the ground instead of overlapping)."""
    if shape.size[0] > 0.0:
        return float(shape.size[0])
    R = quat_to_matrix(shape.rotation)
    local = (particle_q - np.asarray(shape.position)) @ R  # rows: particle positions in the plane frame
    reach = float(np.abs(local[:, :2]).max()) if len(local) else 0.0
    half = max(2.0 * reach, 1.0)
    return min(half, tile) if tile is not None else half
