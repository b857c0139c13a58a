"""Render one frame of a USD animation to a PNG with a small software rasterizer (NumPy, no GPU needed).

Reads the file back through pxr, so the picture shows what a DCC tool would load: every ``Mesh``
(cloth and ground), ``Sphere``, ``Cube`` and ``Capsule``, and ``Points`` (emitted particles, each a small
sphere of its width), with their world transforms at the frame's time
code (so a moving collider is drawn where it is at that frame). Colliders are drawn although warpspring
writes them with purpose ``guide``: the picture is for checking a run, and the cloth's contacts with
them are what it must show.

The pipeline: triangles are rasterized with a perspective camera into a supersampled visibility
buffer (the nearest triangle per sample, so nothing shows through), each visible sample is shaded
with smoothly interpolated vertex normals, a double-sided Lambert key light with soft shadows (a
shadow map rendered by the same rasterizer) and a sky/ground ambient term, and the samples are
averaged down to pixels. Rasterization is homogeneous (Olano & Greer, 1997): a triangle's corner
matrix inverse maps a sample straight to perspective-correct barycentric weights, so triangles that
reach behind the camera need no clipping.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass

import numpy as np

from ..core.mesh_files import check_usd_layers
from ..errors import ConfigError
from ..plotting import pyplot

_ELEVATION, _AZIMUTH = 18.0, -62.0  # direction from the scene to the camera [deg] (matplotlib's view_init)
_FOV = 30.0  # vertical field of view [deg]
_FILL = 0.85  # fraction of the half frame the framed geometry may use
_SUPERSAMPLE = 3  # samples per pixel along each axis
_LIGHT = np.array([-0.12, -0.7, 0.7]) / np.linalg.norm([-0.12, -0.7, 0.7])  # towards the light: upper left
_KEY, _SKY, _BOUNCE = 0.62, 0.5, 0.16  # key light, ambient from above and from below
_SHADOW_SIZE, _SHADOW_FOV = 1024, 8.0  # shadow map size [texels] and field of view [deg]
_SHADOW_TAPS = (-2, 0, 2)  # texel offsets of the percentage-closer filter, along each axis
_CHUNK = 1 << 18  # samples shaded at once
_BACKGROUND = np.array([1.0, 1.0, 1.0])
_COLORS = {"cloth": (0.85, 0.33, 0.22), "collider": (0.55, 0.62, 0.72), "ground": (0.9, 0.89, 0.86),
           "points": (0.98, 0.72, 0.2)}


@dataclass(frozen=True)
class _Scene:
    """Every triangle to draw, in the z-up view space, with per-vertex attributes."""

    points: np.ndarray  # (n, 3) vertex positions
    normals: np.ndarray  # (n, 3) unit vertex normals, oriented like the triangles' winding
    rgba: np.ndarray  # (n, 4) base colour and opacity (the ground fades out towards its rim)
    tris: np.ndarray  # (m, 3) vertex indices
    focus: np.ndarray  # (k, 3) points the view frames: cloth and colliders, not the whole ground


@dataclass(frozen=True)
class _Camera:
    """A pinhole camera: maps a world point p to ``linear @ p + offset`` = (x·w, y·w, w), sample coordinates
    (x right, y down) times the depth w along the view axis."""

    linear: np.ndarray  # (3, 3)
    offset: np.ndarray  # (3,)
    eye: np.ndarray  # (3,)
    focal: float  # focal length [samples]
    width: int
    height: int

    @classmethod
    def framing(cls, points, towards_eye, width: int, height: int, fov: float) -> _Camera:
        """Look at ``points`` (k, 3) from direction ``towards_eye``, as close as keeps them inside the frame."""
        forward = -np.asarray(towards_eye) / np.linalg.norm(towards_eye)
        right = np.cross(forward, (0.0, 0.0, 1.0))  # z is up; no view here looks straight down
        right /= np.linalg.norm(right)
        rotation = np.stack([right, np.cross(right, forward), forward])
        center = 0.5 * (points.min(axis=0) + points.max(axis=0))
        x, y, z = np.tensordot(rotation, (points - center).T, 1)
        tan_y = _FILL * np.tan(np.radians(fov) / 2)
        tan_x = tan_y * width / height
        distance = max(float(np.max(np.maximum(np.abs(x) / tan_x, np.abs(y) / tan_y) - z)), 1e-6)
        focal = 0.5 * height / np.tan(np.radians(fov) / 2)
        u, v = focal * x / (z + distance), focal * y / (z + distance)
        cx = 0.5 * width - 0.5 * (u.min() + u.max())  # centre the framed points' image
        cy = 0.5 * height + 0.5 * (v.min() + v.max())
        eye = center - distance * forward
        linear = np.array([[focal, 0.0, cx], [0.0, -focal, cy], [0.0, 0.0, 1.0]]) @ rotation
        return cls(linear, -(linear @ eye), eye, focal, width, height)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Homogeneous sample coordinates (x·w, y·w, w) of ``points`` given as (3, ...) coordinates."""
        return np.tensordot(self.linear, points, 1) + self.offset.reshape(3, *[1] * (points.ndim - 1))


@dataclass(frozen=True)
class _Raster:
    """What a camera sees of a scene: per sample the nearest triangle, and how to interpolate over it."""

    camera: _Camera
    inverse_depth: np.ndarray  # (height, width) per sample, 1 / depth; 0 where empty
    nearest: np.ndarray  # (height, width) per sample, the nearest triangle; -1 where empty
    # (m, 3, 3) per triangle, the inverse of the matrix whose columns are its projected corners
    # (x·w, y·w, w): applied to a sample's (x, y, 1) it gives the barycentric weights divided by the
    # depth, so they sum to the inverse depth and are all ≥ 0 exactly inside the triangle.
    to_barycentric: np.ndarray


def render_usd(usd_path: str, png_path: str, *, frame: int = -1, width: int = 900) -> str:
    """Render ``frame`` (negative: from the end) of ``usd_path`` to ``png_path``; returns the PNG path."""
    plt = pyplot("rendering and its pictures")
    from pxr import Tf, Usd

    if not os.path.isfile(usd_path):
        raise ConfigError(f"USD file not found: {usd_path}")
    folder = os.path.dirname(os.path.abspath(png_path))
    if not os.path.isdir(folder):
        raise ConfigError(f"output folder does not exist: {folder}")
    try:
        layers = check_usd_layers(usd_path)  # every layer a regular file before USD opens it (held: reused)
        stage = Usd.Stage.Open(usd_path)
        del layers
    except Tf.ErrorException:
        stage = None
    if stage is None:
        raise ConfigError(f"cannot open {usd_path} as USD: expected a .usd, .usda or .usdc file")
    start, end = int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode())
    frames = _sampled_frames(stage) or list(range(start, end + 1))
    if not -len(frames) <= frame < len(frames):
        raise ConfigError(f"frame {frame} is out of range: the file has {len(frames)} frames")
    scene = _read_scene(stage, Usd.TimeCode(frames[frame]))
    if scene is None:
        raise ConfigError(f"{usd_path} holds no mesh or sphere to render")

    image = _render(scene, width, max(round(0.75 * width), 1))
    seconds = frames[frame] / stage.GetTimeCodesPerSecond()
    caption = f"{os.path.basename(usd_path)} — frame {frames[frame]} (t = {seconds:.2f} s)"
    _save(plt, image, png_path, caption)
    return png_path


def _sampled_frames(stage) -> list[int]:
    """Time codes at which any mesh's points are sampled, sorted (empty when no mesh is animated). Every
    mesh counts: a world the run-time guard stopped has fewer samples than the others."""
    from pxr import UsdGeom

    times = set()
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointBased) and not prim.IsA(UsdGeom.Curves):
            times.update(int(round(s)) for s in UsdGeom.PointBased(prim).GetPointsAttr().GetTimeSamples())
    return sorted(times)


def _read_scene(stage, time) -> _Scene | None:
    """Every mesh, sphere, cube and capsule of ``stage`` at ``time`` (whatever its purpose) as triangles in
    z-up view space; None when there are none."""
    from pxr import UsdGeom

    z_up = UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    cache = UsdGeom.XformCache(time)
    parts = []
    for prim in stage.Traverse():
        shape = _triangles(prim, time)
        if shape is None:
            continue
        points, tris, kind = shape
        world = np.array(cache.GetLocalToWorldTransform(prim)).T  # USD matrices act on row vectors
        points = points @ world[:3, :3].T + world[:3, 3]
        if not z_up:
            points = points[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # y-up → z-up view
        if kind == "ground":
            points, tris = _subdivide_quad(points)
        parts.append((points, tris, kind))
    return _assemble(parts) if parts else None


def _triangles(prim, time):
    """A mesh, sphere, cube or capsule prim as (local points, triangles, kind) at ``time``, before the
    prim's transform (which scales a cube to a box); None for other prims and empty meshes."""
    from pxr import UsdGeom

    if prim.IsA(UsdGeom.Sphere):
        return (*_icosphere(UsdGeom.Sphere(prim).GetRadiusAttr().Get(time)), "collider")
    if prim.IsA(UsdGeom.Cube):
        return (*_box(0.5 * UsdGeom.Cube(prim).GetSizeAttr().Get(time)), "collider")
    if prim.IsA(UsdGeom.Capsule):
        capsule = UsdGeom.Capsule(prim)
        radius, height = capsule.GetRadiusAttr().Get(time), capsule.GetHeightAttr().Get(time)
        return (*_capsule(radius, 0.5 * height, capsule.GetAxisAttr().Get(time)), "collider")
    if prim.IsA(UsdGeom.Points):
        return _point_spheres(UsdGeom.Points(prim), time)
    if not prim.IsA(UsdGeom.Mesh):
        return None
    mesh = UsdGeom.Mesh(prim)
    points = np.asarray(mesh.GetPointsAttr().Get(time) or [], dtype=np.float64).reshape(-1, 3)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    tris = _triangulate(counts, indices)
    if not len(tris):
        return None
    if "colliders" not in str(prim.GetPath()):
        return points, tris, "cloth"
    return points, tris, "ground" if len(points) == 4 else "collider"  # warpspring writes a plane as a quad


def _point_spheres(points_prim, time):
    """A points prim's points as small spheres of their widths (a once-subdivided icosahedron each), or None
    without points."""
    points = np.asarray(points_prim.GetPointsAttr().Get(time) or [], dtype=np.float64).reshape(-1, 3)
    if not len(points):
        return None
    widths = np.asarray(points_prim.GetWidthsAttr().Get(time) or [0.01], dtype=np.float64)
    radius = 0.5 * np.broadcast_to(widths if len(widths) == len(points) else widths[:1], (len(points),))
    unit, tris = _icosphere(1.0, subdivisions=1)
    spheres = points[:, None, :] + radius[:, None, None] * unit[None, :, :]
    all_tris = (tris[None, :, :] + (np.arange(len(points)) * len(unit))[:, None, None]).reshape(-1, 3)
    return spheres.reshape(-1, 3), all_tris, "points"


def _assemble(parts: list) -> _Scene:
    """One scene of (points, triangles, kind) parts, with their vertex normals and colours."""
    offsets = np.cumsum([0] + [len(points) for points, _, _ in parts[:-1]])
    focus = [points for points, _, kind in parts if kind != "ground"]
    return _Scene(
        points=np.concatenate([points for points, _, _ in parts]),
        normals=np.concatenate([_vertex_normals(points, tris) for points, tris, _ in parts]),
        rgba=np.concatenate([_vertex_colors(points, kind) for points, _, kind in parts]),
        tris=np.concatenate([tris + offset for (_, tris, _), offset in zip(parts, offsets)]),
        focus=np.concatenate(focus or [points for points, _, _ in parts]),
    )


def _triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons given as face vertex counts and indices; (m, 3) vertex indices."""
    fans = np.maximum(counts - 2, 0)  # triangles per face
    first = np.repeat(np.cumsum(counts) - counts, fans)  # per triangle, its face's first vertex
    k = np.arange(fans.sum()) - np.repeat(np.cumsum(fans) - fans, fans) + 1
    return np.stack([indices[first], indices[first + k], indices[first + k + 1]], axis=1)


def _subdivide_quad(corners: np.ndarray, n: int = 24):
    """Split a quad into n × n cells, so the ground's opacity can fade out smoothly towards its rim."""
    u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    a, b, c, d = corners[:4]
    pts = ((1 - u) * (1 - v))[..., None] * a + (u * (1 - v))[..., None] * b + (u * v)[..., None] * c
    pts = pts + ((1 - u) * v)[..., None] * d
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    q0, q1, q2, q3 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([q0, q1, q2], 1), np.stack([q0, q2, q3], 1)])
    return pts.reshape(-1, 3), tris


def _icosphere(radius: float, subdivisions: int = 4):
    """A sphere of ``radius`` at the origin as (points, triangles): a subdivided icosahedron, no seams or poles."""
    g = (1.0 + 5.0**0.5) / 2.0
    points = np.array([(-1, g, 0), (1, g, 0), (-1, -g, 0), (1, -g, 0), (0, -1, g), (0, 1, g),
                       (0, -1, -g), (0, 1, -g), (g, 0, -1), (g, 0, 1), (-g, 0, -1), (-g, 0, 1)], float)
    tris = np.array([(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
                     (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
                     (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)])
    for _ in range(subdivisions):
        edges = np.sort(tris[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        ab, bc, ca = (len(points) + inverse.reshape(-1, 3)).T
        a, b, c = tris.T
        points = np.concatenate([points, points[unique].mean(axis=1)])
        tris = np.concatenate([np.stack(t, axis=1) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))])
    return radius * points / np.linalg.norm(points, axis=1, keepdims=True), tris


def _box(half: float):
    """A cube of half width ``half`` at the origin as (points, triangles): four corners of its own per face,
    so that its vertex normals are the faces' normals and its edges stay sharp."""
    points, tris = [], []
    for axis, sign in itertools.product(range(3), (-1.0, 1.0)):
        u, v = (axis + 1) % 3, (axis + 2) % 3  # (u, v, axis) is right-handed
        for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1)):  # counter-clockwise seen from +axis
            corner = np.zeros(3)
            corner[axis], corner[u], corner[v] = sign, a * sign, b
            points.append(corner)
        k = len(points) - 4
        tris += [(k, k + 1, k + 2), (k, k + 2, k + 3)]  # the face's winding points along sign · axis
    return half * np.array(points), np.array(tris)


def _capsule(radius: float, half_height: float, axis: str = "Z", segments: int = 48, rings: int = 12):
    """A capsule at the origin as (points, triangles): the points within ``radius`` of the segment from
    -``half_height`` to +``half_height`` along ``axis`` ("X", "Y" or "Z"), a cylinder between two
    hemispheres of ``rings`` latitude rows each, every row ``segments`` points round; outward winding."""
    theta = np.linspace(0.0, 0.5 * np.pi, rings + 1)[1:]  # polar angle of each row of the upper cap
    polar = np.concatenate([theta, np.pi - theta[::-1]])  # upper cap's rows, then the lower cap's
    centre = np.where(np.arange(2 * rings) < rings, half_height, -half_height)
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    rows = np.stack([
        radius * np.sin(polar)[:, None] * np.cos(phi),
        radius * np.sin(polar)[:, None] * np.sin(phi),
        np.broadcast_to((centre + radius * np.cos(polar))[:, None], (2 * rings, segments)),
    ], axis=-1).reshape(-1, 3)
    top, bottom = 2 * rings * segments, 2 * rings * segments + 1
    points = np.concatenate([rows, [(0.0, 0.0, half_height + radius), (0.0, 0.0, -half_height - radius)]])
    j = np.arange(segments)
    index = np.arange(2 * rings * segments).reshape(2 * rings, segments)
    a, b = index[:-1], index[1:]  # each row and the row below it
    c, d = np.roll(b, -1, axis=1), np.roll(a, -1, axis=1)
    tris = np.concatenate([
        np.stack([np.full(segments, top), index[0, j], index[0, (j + 1) % segments]], axis=1),
        np.stack([a, b, c], axis=-1).reshape(-1, 3),
        np.stack([a, c, d], axis=-1).reshape(-1, 3),
        np.stack([index[-1, j], np.full(segments, bottom), index[-1, (j + 1) % segments]], axis=1),
    ])
    # Built along z; a cyclic permutation of the coordinates (which keeps the winding) turns it onto x or y.
    return np.roll(points, {"X": 1, "Y": 2, "Z": 0}[str(axis)], axis=1), tris


def _vertex_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Unit vertex normals: the area-weighted sum of the adjacent triangles' normals."""
    face = np.cross(points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]])
    normals = np.zeros_like(points)
    for k in range(3):
        np.add.at(normals, tris[:, k], face)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)


def _vertex_colors(points: np.ndarray, kind: str) -> np.ndarray:
    """Base colour and opacity per vertex.

    The ground fades out between 45 % and 70 % of the distance from its centre to its corners, so
    the edges of its square (at ≥ 71 %) never show.
    """
    rgba = np.empty((len(points), 4))
    rgba[:, :3] = _COLORS[kind]
    rgba[:, 3] = 1.0
    if kind == "ground":
        radius = np.linalg.norm(points - points.mean(axis=0), axis=1)
        rgba[:, 3] = 1.0 - _smoothstep(0.45 * radius.max(), 0.7 * radius.max(), radius)
    return rgba


def _smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    """0 below ``lo``, 1 above ``hi``, a smooth cubic between."""
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _render(scene: _Scene, width: int, height: int) -> np.ndarray:
    """The scene as an (height, width, 3) RGB image in [0, 1]: the mean of each pixel's s × s samples.

    Samples are shaded in chunks, so memory stays bounded whatever the image size.
    """
    s = _SUPERSAMPLE
    elevation, azimuth = np.radians(_ELEVATION), np.radians(_AZIMUTH)
    towards_eye = np.cos(elevation) * np.array([np.cos(azimuth), np.sin(azimuth), np.tan(elevation)])
    view = _rasterize(_Camera.framing(scene.focus, towards_eye, s * width, s * height, _FOV), scene)
    shadow = _rasterize(_Camera.framing(scene.focus, _LIGHT, _SHADOW_SIZE, _SHADOW_SIZE, _SHADOW_FOV), scene)
    facing = _facing(scene, view.camera.eye)
    samples = np.flatnonzero(view.nearest >= 0)
    pixels = samples // view.camera.width // s * width + samples % view.camera.width // s
    total = np.zeros((3, width * height))  # per pixel, the sum of its covered samples' colours
    for start in range(0, len(samples), _CHUNK):
        part = slice(start, start + _CHUNK)
        for channel, colors in zip(total, _shade(scene, view, samples[part], facing, shadow)):
            channel += np.bincount(pixels[part], colors, minlength=width * height)
    empty = s * s - np.bincount(pixels, minlength=width * height)
    image = (total + empty * _BACKGROUND[:, None]) / (s * s)
    return image.reshape(3, height, width).transpose(1, 2, 0)


def _rasterize(camera: _Camera, scene: _Scene) -> _Raster:
    """The nearest triangle of ``scene`` at every sample of ``camera``, by a depth test per sample."""
    corners = camera.project(scene.points.T[:, scene.tris]).transpose(1, 0, 2)  # (m, coordinate, corner)
    det = np.linalg.det(corners)
    valid = np.abs(det) > 1e-12 * np.prod(np.linalg.norm(corners, axis=1), axis=1)  # not seen edge-on
    inverse = np.zeros_like(corners)
    inverse[valid] = np.linalg.inv(corners[valid])
    boxes = _sample_boxes(corners, camera.width, camera.height)
    valid &= (boxes[:, 1] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 2])

    inverse_depth = np.zeros((camera.height, camera.width))
    nearest = np.full((camera.height, camera.width), -1, dtype=np.int32)
    xs, ys = np.arange(camera.width) + 0.5, np.arange(camera.height)[:, None] + 0.5
    for t in np.flatnonzero(valid):
        x0, x1, y0, y1 = boxes[t]
        m = inverse[t][:, :, None, None]
        weights = m[:, 0] * xs[x0:x1] + m[:, 1] * ys[y0:y1] + m[:, 2]
        depth = weights.sum(axis=0)
        window = inverse_depth[y0:y1, x0:x1]
        hit = (weights.min(axis=0) >= 0.0) & (depth > window)
        window[hit] = depth[hit]
        nearest[y0:y1, x0:x1][hit] = t
    return _Raster(camera, inverse_depth, nearest, inverse)


def _sample_boxes(corners: np.ndarray, width: int, height: int) -> np.ndarray:
    """Per triangle, the sample rows and columns [x0, x1) × [y0, y1) its image can cover.

    A triangle reaching behind the camera may cover any sample: its box is the whole frame.
    """
    w = corners[:, 2]
    in_front = np.all(w > 0.0, axis=1)
    xy = corners[:, :2] / np.where(in_front[:, None], w, 1.0)[:, None, :]
    lo = np.where(in_front[:, None], np.floor(xy.min(axis=2)), 0.0)
    hi = np.where(in_front[:, None], np.ceil(xy.max(axis=2)), np.inf)
    size = np.array([width, height])
    lo, hi = np.clip(lo, 0, size).astype(np.int64), np.clip(hi, 0, size).astype(np.int64)
    boxes = np.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], axis=1)
    boxes[np.all(w <= 0.0, axis=1)] = 0  # wholly behind the camera
    return boxes


def _facing(scene: _Scene, eye: np.ndarray) -> np.ndarray:
    """Per triangle, +1 when its winding's front faces ``eye`` and -1 when its back does (double-sided)."""
    a, b, c = (scene.points[scene.tris[:, k]] for k in range(3))
    return np.where(np.einsum("ij,ij->i", np.cross(b - a, c - a), eye - a) >= 0.0, 1.0, -1.0)


def _shade(scene: _Scene, view: _Raster, samples: np.ndarray, facing: np.ndarray, shadow: _Raster) -> np.ndarray:
    """Colours (3, n) of covered ``samples`` (flat indices into ``view``): their nearest triangle, lit.

    Per-sample arrays are component-major, (3, n), and gathered with 1-D ``take``: several times faster
    than fancy-indexing rows of (n, 3) arrays.
    """
    t = view.nearest.ravel().take(samples)
    x, y = samples % view.camera.width + 0.5, samples // view.camera.width + 0.5
    m = view.to_barycentric.reshape(-1, 9).T
    weights = [m[3 * k].take(t) * x + m[3 * k + 1].take(t) * y + m[3 * k + 2].take(t) for k in range(3)]
    inverse_depth = sum(weights)
    weights = [w / inverse_depth for w in weights]  # perspective-correct barycentric coordinates
    corners = [scene.tris[:, k].take(t) for k in range(3)]

    def interpolate(attribute):  # per vertex (v, c) → per sample (c, n)
        return np.array([sum(w * a.take(v) for w, v in zip(weights, corners)) for a in attribute.T])

    normals = interpolate(scene.normals)
    normals *= facing.take(t) / np.linalg.norm(normals, axis=0)
    diffuse = np.maximum(_LIGHT @ normals, 0.0)
    lit = np.flatnonzero(diffuse)  # only these can be in a shadow
    diffuse[lit] *= _lit_fraction(shadow, interpolate(scene.points)[:, lit], normals[:, lit])
    up = 0.5 + 0.5 * normals[2]
    shade = _KEY * diffuse + _SKY * up + _BOUNCE * (1.0 - up)
    rgba = interpolate(scene.rgba)
    color = np.clip(rgba[:3] * shade, 0.0, 1.0)
    return rgba[3] * color + (1.0 - rgba[3]) * _BACKGROUND[:, None]


def _lit_fraction(shadow: _Raster, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Fraction of the shadow map taps around each point (3, n) that see it: percentage-closer soft shadows.

    ``shadow`` is the scene seen from the light. Against shadow acne, the points are lifted along their
    ``normals`` (which face the light) off their surface by more than the farthest tap's offset: then no
    tap sees a flat surface in front of them.
    """
    light, reach = shadow.camera, max(map(abs, _SHADOW_TAPS))
    texel = np.linalg.norm(light.eye - points.mean(axis=1)) / light.focal  # its size [m] near the points
    x, y, w = light.project(points + (np.sqrt(2.0) * reach + 1.0) * texel * normals)
    pad = 2 * reach + 1  # an empty border, so wide that the taps of any point clamped into it stay in it
    padded = np.pad(shadow.inverse_depth, pad).ravel()
    rows, cols = light.height + 2 * pad, light.width + 2 * pad
    col = np.clip(np.floor(x / w).astype(np.int64) + pad, reach, cols - 1 - reach)
    row = np.clip(np.floor(y / w).astype(np.int64) + pad, reach, rows - 1 - reach)
    center, depth = row * cols + col, (1.0 + 1e-4) / w  # inverse depth, nudged towards the light
    lit = np.zeros(len(w))
    for dy, dx in itertools.product(_SHADOW_TAPS, repeat=2):
        lit += depth >= padded.take(center + (dy * cols + dx))
    return lit / len(_SHADOW_TAPS) ** 2


def _save(plt, image: np.ndarray, png_path: str, caption: str) -> None:
    """Write ``image`` pixel for pixel to ``png_path`` with a small caption at the top."""
    height, width = image.shape[:2]
    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    fig.figimage(image, resize=True)
    fig.text(0.5, 1.0 - 8.0 / height, caption, ha="center", va="top", fontsize=10 * width / 900, color="0.3")
    fig.savefig(png_path, dpi=100)
    plt.close(fig)
