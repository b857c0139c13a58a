"""Stream an animation to a USD file that DCC tools (Blender, Houdini, Maya, usdview) play.

What is authored, and why (USD's fallbacks are wrong for simulation caches):

* stage: ``/World`` as defaultPrim, ``upAxis``, ``metersPerUnit = 1`` (the fallback is centimetres),
  ``timeCodesPerSecond = framesPerSecond = fps`` (the fallback is 24), start/end time codes;
* each cloth mesh: topology once, ``subdivisionScheme = "none"`` (the fallback, Catmull-Clark, makes
  Blender and Houdini subdivide the cloth), ``doubleSided``, ``primvars:st`` when the mesh has UVs, and
  per frame ``points``, ``extent`` and vertex ``normals``;
* colliders as prims of purpose ``guide`` (shown in viewports, left out of final renders) with their
  transforms: a sphere as ``UsdGeom.Sphere``, a box as a ``UsdGeom.Cube`` of size 2 scaled by its half
  extents, a capsule as ``UsdGeom.Capsule`` (axis Z, height 2 · half_height), a plane as a finite quad
  fitted to the scene. A static collider's translate and orient ops hold one default value; a moving
  one's (a collider with keyframe tracks) are also sampled at every written frame, at the frame's time;
* optionally the particles (``UsdGeom.Points``) and springs (``UsdGeom.BasisCurves``).

Worlds: a model of one world, or one chosen world of a model of several (``world=k``), is written as
above, directly under ``/World``. Every world of a model of several is written as its own ``Xform``,
``/World/world_0003/<cloth>``, ``/World/world_0003/colliders/...``, with its own copy of the colliders
and a translation that lays the worlds out side by side on a grid in the ground plane
(:func:`world_offsets`); the points stay the world's simulated positions, the translation places them.
A world that the run-time guard stopped (:meth:`UsdWriter.stop_worlds`) gets no samples after its last
good frame: DCC tools hold a prim's last sample, so the file stays a valid animation of every world.

Frames are written as they are produced. A ``.usdc`` layer is saved after every frame: crate files
append the new samples, and the samples already on disk are not kept in memory, so memory does not
grow with the frame count and the file on disk is a complete, valid stage after every frame, also when
a run stops early. A ``.usda`` file (text, for inspection) is rewritten whole on save, so it is saved at
most once per second of wall time and on :meth:`UsdWriter.close`.

A save that fails (a full disk, the file or its folder removed) raises :class:`~warpspring.errors.OutputError`,
one line naming the frame and the OS's reason (USD's own errors often carry none: the file system is then
examined for one). The file keeps every frame saved before it, a valid stage (USD writes a crate's new
samples before the table of contents that points at them, and a text file through a temporary file), and
the writer drops the unsaved frame instead of trying to save it again on close.
"""

from __future__ import annotations

import errno
import math
import os
import re
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError, OutputError, SimulationError, os_error_reason
from ..kernels.geometry import vertex_normal_kernels
from ..core.model import Model, State
from ..core.transforms import quat_to_matrix

_EXTENSIONS = (".usdc", ".usda", ".usd")


class UsdWriter:
    """Writes the frames of a simulation of ``model`` to ``path`` as time samples.

    Use as a context manager, or call :meth:`close`. Time code k is frame k (t = k / fps seconds).

    Args:
        path: output file; ``.usdc`` (binary, default choice) or ``.usda`` (text); ``.usd`` is binary.
        model: the simulated model (topology, colliders and up axis are taken from it).
        fps: frames per second of the animation [1/s].
        particles: also write the particles as ``UsdGeom.Points`` (widths = 2 × radius).
        springs: also write the springs as linear ``UsdGeom.BasisCurves``.
        text_save_interval: for ``.usda``, the least wall time [s] between two saves.
        world: export only this world, directly under ``/World`` as a one-world model; ``None``: every
            world (each under ``/World/world_NNNN`` when the model has several).
        world_spacing: distance [m] between neighbouring worlds on the export grid, when every world
            of a model of several is written; ``None``: :func:`default_world_spacing`.
        world_columns: worlds per row of the export grid; ``None``: ceil(√world_count).
        keep_frames: keep the first ``keep_frames`` frames (time codes 0 .. keep_frames - 1) of the file
            already at ``path``, written by a run of the same scene and export options that stopped, and
            append after them (``warpspring run --resume``); later samples of that file are dropped.

    Raises:
        ConfigError: a bad path, fps, world, spacing or column count, or (``keep_frames``) a file that is
            missing or holds fewer frames; nothing is written.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        model: Model,
        *,
        fps: float,
        particles: bool = False,
        springs: bool = False,
        text_save_interval: float = 1.0,
        world: int | None = None,
        world_spacing: float | None = None,
        world_columns: int | None = None,
        keep_frames: int = 0,
    ):
        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

        self._Usd, self._UsdGeom, self._Vt, self._Tf = Usd, UsdGeom, Vt, Tf
        path = check_output_path(path)
        ext = os.path.splitext(path)[1].lower()
        fps = checks.positive("fps", fps)
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
        kept = _read_frames(path, keep_frames) if keep_frames else None  # before the file is replaced
        try:
            if os.path.exists(path):
                os.remove(path)
            layer = Sdf.Layer.FindOrOpen(path)
            if layer is not None:  # a stale layer of the same name in this process's registry
                layer.Clear()
                self.stage = Usd.Stage.Open(layer)
            else:
                self.stage = Usd.Stage.CreateNew(path)
        except (OSError, Tf.ErrorException) as exc:
            reason = _reason(exc) or _diagnose(path) or "USD gave no reason"
            raise ConfigError(f"cannot create the USD file {path!r}: {reason}") from None
        self.path = path
        self.model = model
        self.fps = float(fps)
        self.frame_count = 0
        self.frames_saved = 0  # frames on disk: 0 .. frames_saved - 1
        self._text = ext == ".usda"
        self._save_interval = float(text_save_interval)
        self._last_save = 0.0
        self._closed = False

        stage = self.stage
        root = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(root.GetPrim())
        UsdGeom.SetStageUpAxis(stage, {"Y": UsdGeom.Tokens.y, "Z": UsdGeom.Tokens.z}[model.up_axis])
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        stage.SetStartTimeCode(0.0)
        stage.SetEndTimeCode(1.0)
        from .. import __version__

        stage.GetRootLayer().customLayerData = {"generator": f"warpspring {__version__} (warp {wp.__version__})"}

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
            self._slots.append(slot)
        if model.tri_count and any(slot.meshes for slot in self._slots):
            # Every exported world's triangles, in state-array indices: one launch computes all their normals.
            n = model.particle_count
            tri = model.tri_indices.numpy()
            tri = np.concatenate([tri + w * n for w in self.worlds]).astype(np.int32)
            self._export_tris = wp.array(tri, dtype=wp.int32, device=model.device)
            self._normals = wp.empty(model.state_size, dtype=wp.vec3f, device=model.device)
        if kept is not None:
            for attribute, samples in kept:
                target = stage.GetAttributeAtPath(attribute)
                if not target:
                    raise ConfigError(f"cannot resume {path!r}: it holds {attribute}, which this scene does not "
                                      "write (another scene or other export options)")
                for time_code, value in samples:
                    target.Set(value, Usd.TimeCode(time_code))
            self.frame_count = keep_frames
            stage.SetEndTimeCode(float(max(keep_frames - 1, 1)))
        self._save(force=True)

    # -- frames ---------------------------------------------------------------------------------------

    def write_frame(self, state: State) -> None:
        """Append ``state`` as the next frame (time code :attr:`frame_count`, time :attr:`frame_count` / fps
        seconds) and save the file. Moving colliders get their pose at that time. Worlds that were stopped
        (:meth:`stop_worlds`) get no sample.

        Raises:
            SimulationError: a position of an exported world that is not stopped is NaN or infinite;
                nothing of the frame is written.
            OutputError: the file could not be saved (a full disk, the file or its folder removed): the message
                names the frame and the OS's reason; the file on disk keeps the frames saved before it (a valid
                stage), and the writer is closed without saving again.
        """
        if self._closed:
            raise RuntimeError("UsdWriter is closed")
        Vt, UsdGeom = self._Vt, self._UsdGeom
        t = self._Usd.TimeCode(float(self.frame_count))
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
        seconds = self.frame_count / self.fps
        poses = {shape.name: shape.frame(seconds) for shape in model.shapes if shape.moving}  # same in every world
        normals_all = None
        if any(slot.meshes for slot in live):
            normals_all = self._vertex_normals(state).reshape(model.world_count, model.particle_count, 3)
        for slot in live:
            q = q_all[slot.world]
            for group, points_attr, extent_attr, normals_attr in slot.meshes:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[group.particles]))
                points_attr.Set(points, t)
                extent_attr.Set(UsdGeom.PointBased.ComputeExtent(points), t)
                normals = normals_all[slot.world][group.particles]
                normals_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals)), t)
            if slot.points is not None:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q))
                slot.points.GetPointsAttr().Set(points, t)
                slot.points.GetExtentAttr().Set(UsdGeom.Points.ComputeExtent(points, self._widths), t)
            if slot.curves is not None:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[self._spring_ends]))
                slot.curves.GetPointsAttr().Set(points, t)
                slot.curves.GetExtentAttr().Set(UsdGeom.Curves.ComputeExtent(points, self._curve_widths), t)
            for shape, translate, orient in slot.colliders:
                _set_pose(translate, orient, poses[shape.name], t)
        self.stage.SetEndTimeCode(float(max(self.frame_count, 1)))
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
        sample is at time code that number - 1)."""
        return dict(self._stopped)

    def close(self) -> None:
        """Save the file and release the stage. Safe to call twice. After a failed save it only releases the
        stage: the file keeps the frames saved before the failure.

        Raises:
            OutputError: the last save failed (see :meth:`write_frame`).
        """
        if not self._closed:
            try:
                self._save(force=True)
            finally:
                self._release()

    def __enter__(self) -> UsdWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals ------------------------------------------------------------------------------------

    def _save(self, force: bool = False) -> None:
        """Save the layer and its :attr:`frame_count` frames (a text layer at most once per ``text_save_interval``
        unless ``force``). A failure releases the stage unsaved and raises OutputError."""
        frames = self.frame_count
        now = time.monotonic()
        if self._text and not force and now - self._last_save < self._save_interval:
            return
        try:
            saved = self._save_layer()
        except (OSError, self._Tf.ErrorException) as exc:
            reason, code = _reason(exc), getattr(exc, "errno", None)
        else:
            if saved is not False:
                self._last_save = now
                self.frames_saved = frames
                return
            reason, code = "", None  # USD refused without a word
        if code is None:  # no OS error number: say what the file system shows
            diagnosis = _diagnose(self.path)
            reason = f"{reason} ({diagnosis})" if reason and diagnosis else reason or diagnosis
        reason = reason or "USD gave no reason (a full disk, or the file or its folder removed?)"
        saved = self.frames_saved
        lost = frames - saved
        what = ("the file" if lost <= 0 else f"frame {saved}" if lost == 1 else f"frames {saved}..{frames - 1}")
        held = f"frames 0..{saved - 1}" if saved > 1 else "frame 0" if saved == 1 else "no frame"
        self._release()  # the unsaved samples are dropped: the file keeps what was saved
        raise OutputError(f"cannot write {what} to the USD file {self.path!r}: {reason}; the file holds {held}",
                          path=self.path, frame=saved if lost > 0 else None, frames_saved=saved, code=code)

    def _save_layer(self) -> bool:
        """Write the root layer to disk: whether USD saved it (it may also raise OSError or Tf.ErrorException)."""
        return self.stage.GetRootLayer().Save()

    def _release(self) -> None:
        """Drop the stage, so that an unsaved layer does not stay in USD's registry (a later open of the path
        reads the file on disk)."""
        self._closed = True
        self.stage = None
        self._slots = []

    def _define_world(self, world: int, root: str, *, particles: bool, springs: bool) -> _WorldPrims:
        """Define the prims of one exported world under ``root``; topology and constant attributes once."""
        from pxr import Sdf

        stage, UsdGeom, Vt, model = self.stage, self._UsdGeom, self._Vt, self.model
        meshes = []
        for group in model.meshes:
            mesh = UsdGeom.Mesh.Define(stage, f"{root}/{group.name}")
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(group.faces)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(group.faces.reshape(-1).astype(np.int32)))
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.CreateDoubleSidedAttr(True)
            mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
            mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            if group.uvs is not None:  # per vertex, or per corner where seams give a particle two UVs
                corners = group.uvs.ndim == 3
                st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
                    "st", Sdf.ValueTypeNames.TexCoord2fArray,
                    UsdGeom.Tokens.faceVarying if corners else UsdGeom.Tokens.vertex,
                )
                st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(group.uvs.reshape(-1, 2), dtype=np.float32)))
            meshes.append((group, mesh.GetPointsAttr(), mesh.GetExtentAttr(), mesh.GetNormalsAttr()))

        points = None
        if particles:
            points = UsdGeom.Points.Define(stage, f"{root}/particles")
            radius = model.particle_radius.numpy().astype(np.float32)
            self._widths = Vt.FloatArray.FromNumpy(2.0 * radius)
            points.CreateWidthsAttr(self._widths)
            points.SetWidthsInterpolation(UsdGeom.Tokens.vertex)

        curves = None
        if springs and model.spring_count:
            curves = UsdGeom.BasisCurves.Define(stage, f"{root}/springs")
            curves.CreateTypeAttr(UsdGeom.Tokens.linear)
            curves.CreateCurveVertexCountsAttr(Vt.IntArray([2] * model.spring_count))
            width = float(0.5 * model.particle_radius.numpy().mean()) or 1.0e-3
            self._curve_widths = Vt.FloatArray([width])
            curves.CreateWidthsAttr(self._curve_widths)
            curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
            self._spring_ends = model.spring_indices.numpy().reshape(-1)
        return _WorldPrims(world, meshes, points, curves)

    def _vertex_normals(self, state: State) -> np.ndarray:
        """Unit vertex normals of every particle, shape [state_size, 3] (those of exported worlds' meshes set)."""
        model = self.model
        accumulate, normalize = vertex_normal_kernels(model.scalar)
        self._normals.zero_()
        wp.launch(accumulate, dim=self._export_tris.shape[0], inputs=[self._export_tris, state.particle_q],
                  outputs=[self._normals], device=model.device)
        wp.launch(normalize, dim=model.state_size, inputs=[self._normals], device=model.device)
        return self._normals.numpy()

    def _write_colliders(self, root: str) -> list:
        """Define the collider prims of one exported world under ``root``, each of purpose guide and posed at
        rest; returns (ShapeInfo, translate op, orient op) of each moving collider, to sample every frame."""
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
            else:  # pragma: no cover - every collider kind is exported; a new kind must add a branch
                raise NotImplementedError(f"USD export of {shape.kind} colliders")
            prim.CreatePurposeAttr(UsdGeom.Tokens.guide)
            translate = prim.AddTranslateOp()  # double precision, as the shape's frame
            orient = prim.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
            if scale is not None:
                prim.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(scale)
            _set_pose(translate, orient, shape.frame(0.0))  # default value: the rest pose, or a moving one's at t = 0
            if shape.moving:
                moving.append((shape, translate, orient))
        return moving


@dataclass
class _WorldPrims:
    """The animated prims of one exported world."""

    world: int
    meshes: list  # (MeshGroup, points, extent and normals attributes) per cloth mesh
    points: object  # UsdGeom.Points of the particles, or None
    curves: object  # UsdGeom.BasisCurves of the springs, or None
    colliders: list = field(default_factory=list)  # (ShapeInfo, translate op, orient op) per moving collider


def _set_pose(translate, orient, frame, time=None) -> None:
    """Set a collider's translate and orient ops to ``frame`` = (position [m], quaternion (x, y, z, w)): as a
    time sample at ``time``, or as the default value when ``time`` is None."""
    from pxr import Gf, Usd

    position, (x, y, z, w) = frame
    time = Usd.TimeCode.Default() if time is None else time
    translate.Set(Gf.Vec3d(*(float(p) for p in position)), time)
    orient.Set(Gf.Quatd(float(w), float(x), float(y), float(z)), time)


def _read_frames(path: str, frames: int) -> list:
    """Every time sample of the first ``frames`` frames of the USD file at ``path``: (attribute path, [(time
    code, value)]) pairs, read into memory so that the file can be replaced."""
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
    held = int(stage.GetEndTimeCode()) + 1 if stage.HasAuthoredTimeCodeRange() else 0
    if held < frames:
        raise ConfigError(f"cannot resume into {path!r}: it holds frames 0..{held - 1}, the checkpoint continues "
                          f"after frame {frames - 1}")
    kept = []
    for prim in stage.Traverse():
        for attribute in prim.GetAttributes():
            times = [t for t in attribute.GetTimeSamples() if t < frames]
            if times:
                kept.append((attribute.GetPath(), [(t, attribute.Get(Usd.TimeCode(t))) for t in times]))
    del stage
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
