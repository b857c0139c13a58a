"""Render one frame of a USD animation to a PNG with shaded triangles (matplotlib, no GPU needed).

Reads the file back through pxr, so the picture shows what a DCC tool would load: every ``Mesh``
(cloth and ground), every ``Sphere``, with their transforms, lit by one directional light.
"""

from __future__ import annotations

import os

import numpy as np

from .errors import ConfigError

_LIGHT = np.array([0.4, -0.5, 0.77])  # direction towards the light, z-up view space
_COLORS = {"cloth": (0.85, 0.33, 0.22), "collider": (0.55, 0.62, 0.72), "ground": (0.80, 0.80, 0.78)}


def render_usd(usd_path: str, png_path: str, *, frame: int = -1, width: int = 900) -> str:
    """Render ``frame`` (negative: from the end) of ``usd_path`` to ``png_path``; returns the PNG path."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection
    except ImportError:
        raise ConfigError("rendering needs matplotlib: pip install 'warpspring[plot]'") from None
    from pxr import Usd, UsdGeom

    if not os.path.isfile(usd_path):
        raise ConfigError(f"USD file not found: {usd_path}")
    stage = Usd.Stage.Open(usd_path)
    if stage is None:
        raise ConfigError(f"cannot open {usd_path} as USD")
    start, end = int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode())
    frames = _sampled_frames(stage) or list(range(start, end + 1))
    if not -len(frames) <= frame < len(frames):
        raise ConfigError(f"frame {frame} is out of range: the file has {len(frames)} frames")
    time = Usd.TimeCode(frames[frame])
    z_up = UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    cache = UsdGeom.XformCache(time)

    triangles, colors, focus = [], [], []
    for prim in stage.Traverse():
        world = np.array(cache.GetLocalToWorldTransform(prim)).T  # USD matrices are row-vector
        if prim.IsA(UsdGeom.Mesh):
            mesh = UsdGeom.Mesh(prim)
            points = np.asarray(mesh.GetPointsAttr().Get(time), dtype=np.float64)
            counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
            indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
            tris = _triangulate(counts, indices)
            kind = "ground" if "colliders" in str(prim.GetPath()) else "cloth"
            if kind == "ground":
                points, tris = _subdivide_quad(points)
        elif prim.IsA(UsdGeom.Sphere):
            points, tris = _sphere(UsdGeom.Sphere(prim).GetRadiusAttr().Get(time))
            kind = "collider"
        else:
            continue
        points = points @ world[:3, :3].T + world[:3, 3]
        if not z_up:
            points = points[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # y-up → z-up view
        triangles.append(points[tris])
        colors.append(np.broadcast_to(_COLORS[kind], (len(tris), 3)))
        if kind != "ground":  # the view frames the cloth and colliders, not the whole ground
            focus.append(points)
    if not triangles:
        raise ConfigError(f"{usd_path} holds no mesh or sphere to render")
    tris = np.concatenate(triangles)
    base = np.concatenate(colors)
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    light = _LIGHT / np.linalg.norm(_LIGHT)
    shade = 0.35 + 0.65 * np.abs(normals @ light)  # double-sided Lambert with ambient
    facecolors = np.clip(base * shade[:, None], 0.0, 1.0)

    fig = plt.figure(figsize=(width / 100, 0.75 * width / 100), dpi=100)
    ax = fig.add_subplot(projection="3d")
    ax.add_collection3d(Poly3DCollection(tris, facecolors=facecolors, edgecolors="none", linewidths=0))
    focus = np.concatenate(focus or [tris.reshape(-1, 3)])
    lo, hi = focus.min(axis=0), focus.max(axis=0)
    center, half = 0.5 * (lo + hi), 0.6 * float((hi - lo).max())
    ax.set_xlim(center[0] - half, center[0] + half)
    ax.set_ylim(center[1] - half, center[1] + half)
    ax.set_zlim(center[2] - half, center[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=18, azim=-62)
    ax.set_axis_off()
    t = frames[frame] / stage.GetTimeCodesPerSecond()
    ax.set_title(f"{os.path.basename(usd_path)} — frame {frames[frame]} (t = {t:.2f} s)", fontsize=10)
    fig.tight_layout()
    fig.savefig(png_path)
    plt.close(fig)
    return png_path


def _sampled_frames(stage) -> list[int]:
    from pxr import UsdGeom

    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            samples = UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples()
            if samples:
                return [int(round(s)) for s in samples]
    return []


def _triangulate(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons given as face vertex counts and indices."""
    tris, start = [], 0
    for c in counts:
        face = indices[start : start + c]
        tris.extend((face[0], face[k], face[k + 1]) for k in range(1, c - 1))
        start += c
    return np.asarray(tris, dtype=np.int64)


def _subdivide_quad(corners: np.ndarray, n: int = 12):
    """Split a quad into n × n cells so the painter's algorithm sorts it against the cloth."""
    u, v = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    a, b, c, d = corners[:4]
    pts = ((1 - u) * (1 - v))[..., None] * a + (u * (1 - v))[..., None] * b + (u * v)[..., None] * c
    pts = pts + ((1 - u) * v)[..., None] * d
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    q0, q1, q2, q3 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([q0, q1, q2], 1), np.stack([q0, q2, q3], 1)])
    return pts.reshape(-1, 3), tris


def _sphere(radius: float, n: int = 24):
    """A UV sphere of ``radius`` at the origin as (points, triangles)."""
    theta, phi = np.meshgrid(np.linspace(0, np.pi, n + 1), np.linspace(0, 2 * np.pi, 2 * n + 1), indexing="ij")
    pts = radius * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    idx = np.arange(pts.shape[0] * pts.shape[1]).reshape(pts.shape[:2])
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return pts.reshape(-1, 3), np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
