"""Stream an animation to a USD file that DCC tools (Blender, Houdini, Maya, usdview) play.

What is authored, and why (USD's fallbacks are wrong for simulation caches):

* stage: ``/World`` as defaultPrim, ``upAxis``, ``metersPerUnit = 1`` (the fallback is centimetres),
  ``timeCodesPerSecond = framesPerSecond = fps`` (the fallback is 24), start/end time codes;
* each cloth mesh: topology once, ``subdivisionScheme = "none"`` (the fallback, Catmull-Clark, makes
  Blender and Houdini subdivide the cloth), ``doubleSided``, ``primvars:st`` when the mesh has UVs, and
  per frame ``points``, ``extent`` and vertex ``normals``;
* colliders as prims with their transforms (a sphere as ``UsdGeom.Sphere``, a plane as a finite quad);
* optionally the particles (``UsdGeom.Points``) and springs (``UsdGeom.BasisCurves``).

Frames are written as they are produced. A ``.usdc`` layer is saved after every frame: crate files
append the new samples, and the samples already on disk are not kept in memory, so memory does not
grow with the frame count and the file on disk is a complete, valid stage after every frame, also when
a run stops early. A ``.usda`` file (text, for inspection) is rewritten whole on save, so it is saved at
most once per second of wall time and on :meth:`UsdWriter.close`.
"""

from __future__ import annotations

import os
import time

import numpy as np
import warp as wp

from .. import checks
from ..errors import ConfigError, SimulationError
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
    ):
        from pxr import Sdf, Tf, Usd, UsdGeom, Vt

        self._Usd, self._UsdGeom, self._Vt, self._Tf = Usd, UsdGeom, Vt, Tf
        path = check_output_path(path)
        ext = os.path.splitext(path)[1].lower()
        fps = checks.positive("fps", fps)
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
            raise ConfigError(f"cannot create the USD file {path!r}: {exc}") from None
        self.path = path
        self.model = model
        self.fps = float(fps)
        self.frame_count = 0
        self._text = ext == ".usda"
        self._save_interval = float(text_save_interval)
        self._last_save = 0.0
        self._closed = False

        stage = self.stage
        world = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(world.GetPrim())
        UsdGeom.SetStageUpAxis(stage, {"Y": UsdGeom.Tokens.y, "Z": UsdGeom.Tokens.z}[model.up_axis])
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        stage.SetStartTimeCode(0.0)
        stage.SetEndTimeCode(1.0)
        from .. import __version__

        stage.GetRootLayer().customLayerData = {"generator": f"warpspring {__version__} (warp {wp.__version__})"}

        self._meshes = []
        for group in model.meshes:
            mesh = UsdGeom.Mesh.Define(stage, f"/World/{group.name}")
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
            self._meshes.append((group, mesh.GetPointsAttr(), mesh.GetExtentAttr(), mesh.GetNormalsAttr()))

        self._points = None
        if particles:
            pts = UsdGeom.Points.Define(stage, "/World/particles")
            radius = model.particle_radius.numpy().astype(np.float32)
            self._widths = Vt.FloatArray.FromNumpy(2.0 * radius)
            pts.CreateWidthsAttr(self._widths)
            pts.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            self._points = pts

        self._curves = None
        if springs and model.spring_count:
            curves = UsdGeom.BasisCurves.Define(stage, "/World/springs")
            curves.CreateTypeAttr(UsdGeom.Tokens.linear)
            curves.CreateCurveVertexCountsAttr(Vt.IntArray([2] * model.spring_count))
            width = float(0.5 * model.particle_radius.numpy().mean()) or 1.0e-3
            curves.CreateWidthsAttr(Vt.FloatArray([width]))
            curves.SetWidthsInterpolation(UsdGeom.Tokens.constant)
            self._spring_ends = model.spring_indices.numpy().reshape(-1)
            self._curves = curves

        self._write_colliders()
        if model.tri_count:
            self._normals = wp.empty(model.particle_count, dtype=wp.vec3f, device=model.device)
        self._save(force=True)

    # -- frames ---------------------------------------------------------------------------------------

    def write_frame(self, state: State) -> None:
        """Append ``state`` as the next frame (time code :attr:`frame_count`) and save the file.

        Raises:
            SimulationError: a position is NaN or infinite; nothing of the frame is written.
        """
        if self._closed:
            raise RuntimeError("UsdWriter is closed")
        Vt, UsdGeom = self._Vt, self._UsdGeom
        t = self._Usd.TimeCode(float(self.frame_count))
        with np.errstate(over="ignore", invalid="ignore"):
            q = state.particle_q.numpy().astype(np.float32)  # USD points are float32: check what is written
        bad = np.flatnonzero(~np.isfinite(q).all(axis=1))
        if len(bad):
            raise SimulationError(
                f"particle {int(bad[0])} has a non-finite position or one beyond float32 range "
                f"({len(bad)} of {len(q)} particles); the frame was not written"
            )
        if self._meshes:
            normals = self._vertex_normals(state)
            for group, points_attr, extent_attr, normals_attr in self._meshes:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[group.particles]))
                points_attr.Set(points, t)
                extent_attr.Set(UsdGeom.PointBased.ComputeExtent(points), t)
                normals_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals[group.particles])), t)
        if self._points is not None:
            points = Vt.Vec3fArray.FromNumpy(q)
            self._points.GetPointsAttr().Set(points, t)
            self._points.GetExtentAttr().Set(UsdGeom.Points.ComputeExtent(points, self._widths), t)
        if self._curves is not None:
            points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(q[self._spring_ends]))
            self._curves.GetPointsAttr().Set(points, t)
            self._curves.GetExtentAttr().Set(
                UsdGeom.Curves.ComputeExtent(points, self._curves.GetWidthsAttr().Get()), t
            )
        self.stage.SetEndTimeCode(float(max(self.frame_count, 1)))
        self.frame_count += 1
        self._save()

    def close(self) -> None:
        """Save the file and release the stage. Safe to call twice."""
        if not self._closed:
            self._save(force=True)
            self._closed = True
            self.stage = None

    def __enter__(self) -> UsdWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals ------------------------------------------------------------------------------------

    def _save(self, force: bool = False) -> None:
        now = time.monotonic()
        if self._text and not force and now - self._last_save < self._save_interval:
            return
        try:
            saved = self.stage.GetRootLayer().Save()
        except self._Tf.ErrorException as exc:
            saved, why = False, f": {exc}"
        else:
            why = ""
        if not saved:
            raise OSError(f"cannot save the USD file {self.path!r}{why} (disk full or file removed?)")
        self._last_save = now

    def _vertex_normals(self, state: State) -> np.ndarray:
        model = self.model
        accumulate, normalize = vertex_normal_kernels(model.scalar)
        self._normals.zero_()
        wp.launch(accumulate, dim=model.tri_count, inputs=[model.tri_indices, state.particle_q],
                  outputs=[self._normals], device=model.device)
        wp.launch(normalize, dim=model.particle_count, inputs=[self._normals], device=model.device)
        return self._normals.numpy()

    def _write_colliders(self) -> None:
        from pxr import Gf, Vt

        UsdGeom = self._UsdGeom
        model = self.model
        if not model.shapes:
            return
        UsdGeom.Scope.Define(self.stage, "/World/colliders")
        q0 = model.particle_q.numpy()
        for shape in model.shapes:
            path = f"/World/colliders/{shape.name}"
            if shape.kind == "sphere":
                prim = UsdGeom.Sphere.Define(self.stage, path)
                r = float(shape.size[0])
                prim.CreateRadiusAttr(r)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-r, -r, -r), Gf.Vec3f(r, r, r)]))
            elif shape.kind == "plane":
                prim = UsdGeom.Mesh.Define(self.stage, path)
                half = _plane_half_size(shape, q0)
                corners = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], np.float32)
                prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(corners))
                prim.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
                prim.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
                prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
                prim.CreateDoubleSidedAttr(True)
                prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(-half, -half, 0), Gf.Vec3f(half, half, 0)]))
            else:  # pragma: no cover - every collider kind is exported; a new kind must add a branch
                raise NotImplementedError(f"USD export of {shape.kind} colliders")
            prim.AddTranslateOp().Set(Gf.Vec3d(*shape.position))
            x, y, z, w = shape.rotation
            prim.AddOrientOp().Set(Gf.Quatf(float(w), float(x), float(y), float(z)))


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
    if not os.access(folder, os.W_OK | os.X_OK) or (os.path.exists(path) and not os.access(path, os.W_OK)):
        raise ConfigError(f"USD output {path!r} cannot be written: check the permissions of {folder}")
    return path


def _plane_half_size(shape, particle_q: np.ndarray) -> float:
    """Half width [m] of the quad that shows an infinite plane: twice the scene's reach around it, ≥ 1 m."""
    if shape.size[0] > 0.0:
        return float(shape.size[0])
    R = quat_to_matrix(shape.rotation)
    local = (particle_q - np.asarray(shape.position)) @ R  # rows: particle positions in the plane frame
    reach = float(np.abs(local[:, :2]).max()) if len(local) else 0.0
    return max(2.0 * reach, 1.0)
