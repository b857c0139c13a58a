"""``warpspring view OUT.usdc``: a USD file's frames in the browser (play, pause, scrub), followed as it grows.

:class:`UsdFrames` reads a frame of a file written by ``warpspring run`` (any USD file of meshes, points,
curves and the usual collider shapes) into a :class:`~warpspring.app.viewer.Picture`: every ``Mesh`` under
a ``colliders`` scope is a collider, every other ``Mesh`` a surface (its per-vertex float primvars and its
``velocities`` as speed are colours), ``Points`` are particles, ``BasisCurves`` springs, the vertices whose
``pinned`` primvar is 1 pins; a ``world_NNNN`` prim in a path names the world. Transforms are applied at the
frame's time code, so moving colliders and the layout of worlds are as the file has them.

A file still being written is followed: :meth:`UsdFrames.refresh` re-opens its layers when the root file
changed on disk and reads the new end time code.
"""

from __future__ import annotations

import os
import re
import threading
import time

import numpy as np

from ..errors import ConfigError
from .viewer import Picture, Surface, Viewer

_WORLD = re.compile(r"^world_\d+$")


class UsdFrames:
    """The frames of a USD file, read on demand.

    Args:
        path: the USD file.
    """

    def __init__(self, path: str | os.PathLike):
        from pxr import Usd, UsdGeom

        self._Usd, self._UsdGeom = Usd, UsdGeom
        self.path = os.fspath(path)
        if not os.path.isfile(self.path):
            raise ConfigError(f"{self.path}: no such file; write one with warpspring run SCENE -o {self.path}")
        try:
            self.stage = Usd.Stage.Open(self.path)
        except Exception as exc:  # pxr's Tf errors: a file that is not USD
            raise ConfigError(f"{self.path} cannot be read as USD: {' '.join(str(exc).split())[:200]}") from None
        self.up_axis = str(UsdGeom.GetStageUpAxis(self.stage))
        self.fps = float(self.stage.GetTimeCodesPerSecond() or 24.0)
        self._stamp = self._disk_stamp()
        self._topology: dict = {}

    def _disk_stamp(self):
        try:
            st = os.stat(self.path)
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size

    @property
    def first(self) -> int:
        return int(self.stage.GetStartTimeCode())

    @property
    def last(self) -> int:
        return int(self.stage.GetEndTimeCode())

    def refresh(self) -> bool:
        """Re-open the file's layers if it changed on disk; whether it did."""
        stamp = self._disk_stamp()
        if stamp is None or stamp == self._stamp:
            return False
        self._stamp = stamp
        try:
            self.stage.Reload()
        except Exception:  # caught mid-write: try again at the next poll
            self._stamp = None
            return False
        return True

    def picture(self, frame: int) -> Picture:
        """Frame ``frame`` (a time code) as a :class:`Picture`."""
        UsdGeom = self._UsdGeom
        t = self._Usd.TimeCode(frame)
        cache = UsdGeom.XformCache(t)
        picture = Picture(time=frame / self.fps)
        for prim in self.stage.Traverse():
            if not prim.IsA(UsdGeom.Gprim):
                continue
            if UsdGeom.Imageable(prim).ComputeVisibility(t) == UsdGeom.Tokens.invisible:
                continue
            parts = str(prim.GetPath()).split("/")
            world = next((p for p in parts if _WORLD.match(p)), "")
            matrix = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)
            collider = "colliders" in parts
            name = prim.GetName()
            if prim.IsA(UsdGeom.Mesh):
                surface = self._mesh(prim, t, matrix, name)
                if surface is None:
                    continue
                (picture.colliders if collider else picture.surfaces).setdefault(world, []).append(surface)
                pinned = surface.values.get("pinned")
                if pinned is not None and not collider:
                    pins = surface.points[np.asarray(pinned) > 0.5]
                    picture.pins[world] = np.concatenate([picture.pins.get(world, np.zeros((0, 3))), pins])
            elif prim.IsA(UsdGeom.Sphere) or prim.IsA(UsdGeom.Cube) or prim.IsA(UsdGeom.Capsule):
                vertices, faces = self._shape(prim, t)
                picture.colliders.setdefault(world, []).append(Surface(name, _apply(matrix, vertices), faces))
            elif prim.IsA(UsdGeom.Points):
                points = prim.GetAttribute("points").Get(t)
                if points is not None and len(points):
                    add = _apply(matrix, np.asarray(points, dtype=np.float64))
                    picture.particles[world] = np.concatenate([picture.particles.get(world, np.zeros((0, 3))), add])
            elif prim.IsA(UsdGeom.BasisCurves):
                points = prim.GetAttribute("points").Get(t)
                counts = prim.GetAttribute("curveVertexCounts").Get(t)
                if points is None or counts is None or not len(points):
                    continue
                points = _apply(matrix, np.asarray(points, dtype=np.float64))
                ends = np.cumsum(np.asarray(counts))
                starts = np.arange(len(points) - 1)
                keep = ~np.isin(starts + 1, ends)  # no segment from a curve's last point to the next curve's first
                segments = np.stack([points[starts[keep]], points[starts[keep] + 1]], axis=1)
                picture.springs[world] = np.concatenate([picture.springs.get(world, np.zeros((0, 2, 3))), segments])
        return picture

    def _mesh(self, prim, t, matrix, name) -> Surface | None:
        UsdGeom = self._UsdGeom
        points = prim.GetAttribute("points").Get(t)
        if points is None or not len(points):
            return None
        points = np.asarray(points, dtype=np.float64)
        key = str(prim.GetPath())
        faces = self._topology.get(key)
        if faces is None:
            counts = np.asarray(prim.GetAttribute("faceVertexCounts").Get(t), dtype=np.int64)
            indices = np.asarray(prim.GetAttribute("faceVertexIndices").Get(t), dtype=np.int64)
            faces = self._topology[key] = triangulate(counts, indices)
        values = {}
        velocities = prim.GetAttribute("velocities").Get(t) if prim.HasAttribute("velocities") else None
        if velocities is not None and len(velocities) == len(points):
            values["speed"] = np.linalg.norm(np.asarray(velocities, dtype=np.float64), axis=1)
        for primvar in UsdGeom.PrimvarsAPI(prim).GetPrimvars():
            if primvar.GetInterpolation() != UsdGeom.Tokens.vertex or primvar.GetBaseName() == "st":
                continue
            value = primvar.Get(t)
            if value is None:
                continue
            array = np.asarray(value)
            if array.ndim == 1 and len(array) == len(points) and array.dtype.kind in "fiub":
                values[str(primvar.GetBaseName())] = array.astype(np.float64)
        return Surface(name, _apply(matrix, points), faces, values)

    def _shape(self, prim, t):
        import trimesh  # optional: trimesh (primitive meshes of the collider shapes)

        UsdGeom = self._UsdGeom
        if prim.IsA(UsdGeom.Sphere):
            mesh = trimesh.creation.icosphere(subdivisions=3, radius=prim.GetAttribute("radius").Get(t))
        elif prim.IsA(UsdGeom.Cube):
            mesh = trimesh.creation.box(extents=[prim.GetAttribute("size").Get(t)] * 3)
        else:
            radius, height = prim.GetAttribute("radius").Get(t), prim.GetAttribute("height").Get(t)
            mesh = trimesh.creation.capsule(height=height, radius=radius)
            axis = str(prim.GetAttribute("axis").Get(t) or "Z")
            if axis != "Z":  # trimesh's capsule runs along z
                turn = {"X": trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]),
                        "Y": trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0])}[axis]
                mesh.apply_transform(turn)
        return np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int32)


def triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Polygons (vertex counts, vertex indices) as triangle fans, int32 [F, 3]."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    rows = []
    for c in np.unique(counts):
        if c < 3:
            continue
        first = starts[counts == c][:, None]
        k = np.arange(1, c - 1)
        fan = np.stack([np.broadcast_to(indices[first], (len(first), c - 2)), indices[first + k],
                        indices[first + k + 1]], axis=-1)
        rows.append(fan.reshape(-1, 3))
    return np.concatenate(rows).astype(np.int32) if rows else np.zeros((0, 3), np.int32)


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points transformed by a USD (row-vector) 4×4 matrix."""
    return points @ matrix[:3, :3] + matrix[3, :3]


class FileView:
    """The file viewer: a :class:`~warpspring.app.viewer.Viewer` with playback controls over :class:`UsdFrames`.

    Args:
        path: the USD file.
        host, port: where the page listens (see :class:`~warpspring.app.viewer.Viewer`).
        follow: re-read the file as it grows, every ``poll`` seconds, and stay on its last frame while
            playing at the end.
    """

    def __init__(self, path, *, host: str = "127.0.0.1", port: int = 0, follow: bool = True, poll: float = 0.5):
        self.frames = UsdFrames(path)
        self.viewer = Viewer(host=host, port=port, up_axis=self.frames.up_axis, title=os.path.basename(path))
        self.poll = poll
        gui = self.viewer.server.gui
        with gui.add_folder("Playback", order=-1):
            self.play = gui.add_checkbox("play", False)
            self.slider = gui.add_slider("frame", self.frames.first, max(self.frames.last, self.frames.first + 1), 1,
                                         self.frames.first)
            self.loop = gui.add_checkbox("loop", True)
            self.follow = gui.add_checkbox("follow the file", follow)
        self.slider.on_update(lambda _: self._show(int(self.slider.value)))
        self._shown = None
        self._stop = threading.Event()
        self._show(self.frames.first)
        self._thread = threading.Thread(target=self._run, name="warpspring-view-play", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return self.viewer.url

    def _show(self, frame: int) -> None:
        frame = int(np.clip(frame, self.frames.first, self.frames.last))
        if frame == self._shown:
            return
        self._shown = frame
        self.viewer.show(self.frames.picture(frame))

    def _run(self) -> None:
        next_poll = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if self.follow.value and now >= next_poll:
                next_poll = now + self.poll
                if self.frames.refresh():
                    self.slider.max = max(self.frames.last, self.frames.first + 1)
                    if self._shown is not None:
                        shown, self._shown = self._shown, None
                        self._show(shown)  # a frame may have been re-written
            if self.play.value:
                frame = int(self.slider.value) + 1
                if frame > self.frames.last:
                    frame = self.frames.first if self.loop.value and not self.follow.value else self.frames.last
                if frame != int(self.slider.value):
                    self.slider.value = frame
                    self._show(frame)
            self._stop.wait(1.0 / self.frames.fps)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.viewer.close()
