"""The simulation as a layer over the artist's own asset (:class:`LayerOver`, ``UsdWriter(layer_over=...)``,
``warpspring run --layer-over ASSET``).

A pipeline does not take a simulation as a new stage: it lays the simulated motion over the asset it already
has. The layer :class:`~warpspring.io.usd.UsdWriter` then writes overrides, at the asset's own prim paths, only
what the simulation changes: each simulated surface's ``points``, ``extent``, ``normals`` (with the interpolation
the asset authors, on ``primvars:normals`` where the asset uses that), ``velocities`` and ``accelerations``, and
the simulation's primvars asked for (``strain``, ``pinned``, ``rest``). Topology, UVs, every other primvar,
subsets, materials, the transforms: all stay the asset's. The asset file is never written.

The values are the asset's own frame: each prim's local space (the inverse of its local-to-world transform at
the frame's time code), the asset's ``metersPerUnit`` and ``upAxis``; frame k is time code ``start_frame + k ·
timeCodesPerSecond / fps`` at the asset's ``timeCodesPerSecond``. Velocities [units/s] and accelerations
[units/s²] are in the prim's local space too; normals are turned by the transform's inverse transpose.

How the layer reaches the asset (``arc``):

* ``"sublayer"`` (default): the layer's root sublayers the asset, so that opening the layer shows the dressed
  asset moving (what a DCC tool imports); its stage metadata are the asset's;
* ``"reference"``: each root prim of the asset is referenced at its own path (the asset's materials must then
  lie under a root prim that is referenced with the mesh, as Blender's exporter writes them);
* ``"none"``: overrides only, for a shot that composes them itself (``subLayers = [sim, asset]``).

Only the surfaces read from the asset are written (a cloth or a soft body with ``mesh = ASSET``); particles and
springs when asked for, and colliders with ``layer_colliders``, go under ``/warpspring``, an Xform that takes
warpspring's metres and up axis into the asset's.
"""

from __future__ import annotations

import os

import numpy as np

from ..core.mesh_files import USD_EXTENSIONS, check_regular_file, convert_up_axis, open_usd_stage
from ..errors import ConfigError

#: How the layer reaches the asset.
ARCS = ("sublayer", "reference", "none")
#: The root of the prims a layer adds beside the asset's (particles, springs, colliders when asked for).
EXTRAS_ROOT = "/warpspring"


class LayerOver:
    """The asset a layer is written over, and its frame: units, up axis, time codes, each prim's transform.

    Args:
        asset: the artist's USD file (never written).
        output: the layer's path (the asset is named relative to its folder).
        fps: the simulation's frames per second [1/s].
        up_axis: warpspring's up axis of the model ("Y" or "Z").
        arc: ``"sublayer"``, ``"reference"`` or ``"none"`` (the module's description).

    Raises:
        ConfigError: the asset is not a readable USD file, or ``arc`` is unknown.
    """

    def __init__(self, asset: str | os.PathLike, *, output: str, fps: float, up_axis: str, arc: str = "sublayer"):
        from pxr import Usd, UsdGeom

        self.file = os.fspath(asset)
        if arc not in ARCS:
            raise ConfigError(f"layer_arc must be one of {', '.join(ARCS)}, got {arc!r}")
        if not self.file.lower().endswith(USD_EXTENSIONS):
            raise ConfigError(f"layer_over {self.file!r}: the asset must be a USD file ({', '.join(USD_EXTENSIONS)})")
        check_regular_file(self.file, "layer_over asset")
        if os.path.abspath(self.file) == os.path.abspath(output):
            raise ConfigError(f"layer_over {self.file!r} is the output itself: the asset is never written; "
                              "choose another -o")
        self.arc = arc
        self.stage = open_usd_stage(self.file)
        self.up_axis = str(UsdGeom.GetStageUpAxis(self.stage))
        self.meters_per_unit = float(UsdGeom.GetStageMetersPerUnit(self.stage))
        self.time_codes_per_second = float(self.stage.GetTimeCodesPerSecond())
        self.frames_per_second = float(self.stage.GetFramesPerSecond())
        self.default_prim = self.stage.GetRootLayer().defaultPrim
        self.sim_up_axis = up_axis
        self.step = self.time_codes_per_second / float(fps)  # time codes per simulated frame
        folder = os.path.dirname(os.path.abspath(output))
        try:
            relative = os.path.relpath(os.path.abspath(self.file), folder)
            self.asset_path = relative if relative.startswith("..") else f"./{relative}"
        except ValueError:  # another drive
            self.asset_path = os.path.abspath(self.file)
        self.roots = [p.GetName() for p in self.stage.GetPseudoRoot().GetAllChildren()]
        self._Usd = Usd
        self._xforms = UsdGeom.XformCache()

    def owns(self, dressing) -> bool:
        """Whether a surface's dressing was read from this asset."""
        if dressing is None or not dressing.prim_path:
            return False
        try:
            return os.path.samefile(dressing.source, self.file)
        except OSError:
            return False

    def check_prim(self, dressing, vertex_count: int) -> None:
        """ConfigError unless the asset's prim of ``dressing`` is a mesh of ``vertex_count`` points."""
        from pxr import UsdGeom

        prim = self.stage.GetPrimAtPath(dressing.prim_path)
        points = UsdGeom.Mesh(prim).GetPointsAttr().Get(self._Usd.TimeCode.EarliestTime()) if prim else None
        if points is None or len(points) != vertex_count:
            raise ConfigError(f"layer_over {self.file!r}: prim {dressing.prim_path} is not the mesh of {vertex_count} "
                              "points the simulation read; was the asset changed during the run?")

    def local(self, prim_path: str, time_code: float, points: np.ndarray, vectors=(), normals=None):
        """Values in warpspring's frame (metres, its up axis, world space) in the asset's frame for the prim at
        ``prim_path`` at ``time_code``: ``points`` [m] → local points [units]; each of ``vectors`` (velocities
        [m/s], accelerations [m/s²]) → local [units/s, units/s²]; ``normals`` (unit) → local unit normals (the
        inverse transpose). Returns (points, [vectors], normals), float64."""
        prim = self.stage.GetPrimAtPath(prim_path)
        self._xforms.SetTime(self._Usd.TimeCode(time_code))
        matrix = np.array(self._xforms.GetLocalToWorldTransform(prim), dtype=np.float64)
        linear, translation = matrix[:3, :3], matrix[3, :3]
        inverse = np.linalg.inv(linear)
        scale = 1.0 / self.meters_per_unit

        def asset(values):
            return convert_up_axis(np.asarray(values, dtype=np.float64), self.sim_up_axis, self.up_axis)

        local_points = (asset(points) * scale - translation) @ inverse
        local_vectors = [(asset(v) * scale) @ inverse for v in vectors]
        local_normals = None
        if normals is not None:
            n = asset(normals) @ linear.T
            length = np.linalg.norm(n, axis=1, keepdims=True)
            local_normals = np.divide(n, length, out=np.zeros_like(n), where=length > 0.0)
        return local_points, local_vectors, local_normals

    def extras_matrix(self) -> np.ndarray:
        """The 4 × 4 (row-vector) transform of :data:`EXTRAS_ROOT`: warpspring's metres and up axis into the
        asset's units and up axis."""
        matrix = np.eye(4)
        matrix[:3, :3] = convert_up_axis(np.eye(3), self.sim_up_axis, self.up_axis) / self.meters_per_unit
        return matrix

    def stage_metadata(self, layer) -> None:
        """The asset's stage metadata on the layer (its default prim, up axis, units, time codes)."""
        if self.default_prim:
            layer.defaultPrim = self.default_prim
        layer.pseudoRoot.SetInfo("upAxis", self.up_axis)
        layer.pseudoRoot.SetInfo("metersPerUnit", self.meters_per_unit)
        layer.timeCodesPerSecond = self.time_codes_per_second
        layer.framesPerSecond = self.frames_per_second

    def author_arc(self, layer) -> None:
        """The arc from the layer (the root written beside the output, or the packed output) to the asset."""
        from pxr import Sdf

        if self.arc == "sublayer":
            layer.subLayerPaths.append(self.asset_path)
        elif self.arc == "reference":
            for name in self.roots:
                spec = layer.GetPrimAtPath(f"/{name}") or Sdf.CreatePrimInLayer(layer, f"/{name}")
                spec.referenceList.Prepend(Sdf.Reference(self.asset_path, f"/{name}"))
