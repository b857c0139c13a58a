"""The builder's collider recipes: an infinite plane (and the ground), a sphere, a box, a capsule and a triangle
mesh (:mod:`warpspring.core.mesh_colliders`), each optionally moved by keyframe tracks; the device bytes of
mesh colliders for the memory estimate; and the rule that switches triangle contacts on where a collider is too
thin for particle contacts alone (:func:`triangle_contact_rule`).

**The rule.** Particle contacts keep every particle's centre ``c = R + thickness + r`` from the centre (or the
axis) of a sphere or a capsule of radius R, r the particle's contact radius. Between the particles the cloth's
triangles are flat: the point of a triangle farthest from its corners lies ρ from each of them, ρ the triangle's
covering radius (its circumradius if acute, half its longest edge if not). With the corners at distance c, that
point dips to √(c² - ρ²) from the centre: the triangle sags into the collider by s = c - √(c² - ρ²), and for
ρ ≥ c the collider slips between the corners (seed 002: R = 4 cm under a cloth of 10 cm spacing). Triangle
contacts switch on when the sag of the cloth's largest triangle exceeds half the particle radius, s > r/2, so
that without them the surface stays at least R + thickness + r/2 from the centre; the half is the margin
for the stretch a falling cloth picks up. Boxes and meshes have edges and corners of zero radius, but triangle
contacts do not cover them (``kernels/triangle_contacts.py``: spheres and capsules), so the rule concerns spheres
and capsules only.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ... import checks
from ...errors import ConfigError
from ...kernels.shapes import SHAPE_BOX, SHAPE_CAPSULE, SHAPE_NAMES, SHAPE_PLANE, SHAPE_SPHERE
from ...kernels.shapes import SHAPE_MESH
from ...kernels.triangle_contacts import TRIANGLE_KINDS
from ..mesh_colliders import check_mesh_file_room, edge_groups, mesh_shape
from ..mesh_files import USD_EXTENSIONS, load_mesh_file, read_usd_mesh, read_usd_mesh_samples
from ..records import ShapeInfo
from ..tracks import Track, as_track
from ..transforms import quat_between
from .arguments import _quaternion


def _mesh_collider_bytes(meshes: list) -> int:
    """Device bytes of mesh colliders (``mesh_colliders.MeshCollider``): the ``wp.Mesh``'s points, velocities and
    triangle indices, and for a cached mesh (not signed by its winding number) the pseudo-normals' face terms and
    CSR tables (per vertex, per corner, per edge group); the BVH lives in Warp's native memory, not counted."""
    total = 0
    for info in meshes:
        v, f = len(info.points_at(0.0)), len(info.faces)
        total += 24 * v + 12 * f
        if not info.winding_number:
            groups = int(edge_groups(info.faces.astype(np.int64)).max()) + 1 if f else 0
            total += 48 * f + 4 * (v + 1) + 36 * f + 4 * (groups + 1)
    return total


@dataclass(frozen=True)
class TriangleContactRule:
    """Whether a scene needs triangle contacts (:func:`triangle_contact_rule`), and why.

    Attributes:
        needed: whether some sphere or capsule is too thin for particle contacts to hold the cloth.
        reason: one line naming the binding collider, its radius [m], the triangles' covering radius ρ [m],
            the particle radius r [m] and the sag [m] against r/2; empty when the scene has no cloth
            triangles or no sphere or capsule.
        collider: the binding collider's name (the largest sag), or "".
    """

    needed: bool
    reason: str = ""
    collider: str = ""


def covering_radius(corners: np.ndarray) -> np.ndarray:
    """Each triangle's covering radius [m]: the largest distance from a point of the triangle to its nearest
    corner (the circumradius of an acute triangle, half the longest edge of a right or obtuse one).

    Args:
        corners: the triangles' corners [m], shape [t, 3, 3].

    Returns:
        float64, shape [t].
    """
    x = np.asarray(corners, dtype=np.float64)
    edges = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1)  # opposite each corner
    squared = np.einsum("tij,tij->ti", edges, edges)
    longest = squared.max(axis=1)
    area2 = np.linalg.norm(np.cross(edges[:, 0], edges[:, 1]), axis=1)  # twice the area
    obtuse = 2.0 * longest >= squared.sum(axis=1)  # a² ≥ b² + c² for the longest side a
    with np.errstate(divide="ignore", invalid="ignore"):
        circum = np.sqrt(squared.prod(axis=1)) / (2.0 * area2)
    return np.where(obtuse | ~(area2 > 0.0), 0.5 * np.sqrt(longest), circum)


def triangle_contact_rule(shapes: list, corners: np.ndarray, radius: float) -> TriangleContactRule:
    """The rule of this module's docstring: triangle contacts are needed where, for some sphere or capsule
    of radius R and thickness t, the cloth's largest triangle sags more than r/2 into it,
    c - √(c² - ρ²) > r/2 with c = R + t + r (or ρ ≥ c: the collider slips between the corners).

    Args:
        shapes: the colliders (:class:`~warpspring.core.records.ShapeInfo`).
        corners: the cloth triangles' corners at rest [m], shape [t, 3, 3].
        radius: the particles' contact radius r [m] (the smallest of the triangles' corners).
    """
    thin = [s for s in shapes if s.kind in {SHAPE_NAMES[k] for k in TRIANGLE_KINDS}]
    if not thin or len(corners) == 0:
        return TriangleContactRule(False)
    rho = float(covering_radius(corners).max())
    r = float(radius)
    worst = None
    for shape in thin:
        c = shape.size[0] + shape.thickness + r
        sag = c - math.sqrt(c * c - rho * rho) if rho < c else math.inf
        if worst is None or sag > worst[0]:
            worst = (sag, shape)
    sag, shape = worst
    needed = sag > 0.5 * r
    sagged = "slips between the particles" if sag == math.inf else f"sags {sag * 1e3:.3g} mm into it"
    verdict = "more than" if needed else "at most"
    reason = (f"triangle contacts {'on' if needed else 'off'}: against the {shape.kind} {shape.name!r} (radius "
              f"{shape.size[0]:g} m) a cloth triangle of covering radius {rho:.3g} m between particles of radius "
              f"{r:g} m {sagged}, {verdict} r/2 = {0.5 * r * 1e3:.3g} mm")
    return TriangleContactRule(needed, reason, shape.name)


def model_triangle_contacts(model) -> TriangleContactRule:
    """:func:`triangle_contact_rule` of a finalized model (its colliders, its triangles at their initial
    positions in world 0, the smallest radius of their corners): what ``finalize`` decided by when it was not
    told (the run summary states it)."""
    if not model.tri_count or not model.shapes:
        return TriangleContactRule(False)
    tris = model.tri_indices.numpy().reshape(-1, 3)
    q = model.particle_q.numpy()[: model.particle_count].astype(np.float64)
    r = np.broadcast_to(model.particle_radius.numpy(), (model.particle_count,))
    return triangle_contact_rule(model.shapes, q[tris], float(r[tris].min()))


class ColliderRecipes:
    """The collider recipes of :class:`~warpspring.core.builder.ModelBuilder` (a mixin: it adds to the builder's
    shapes)."""

    def triangle_contacts(self) -> TriangleContactRule:
        """Whether this scene needs triangle contacts (:func:`triangle_contact_rule` on its cloth triangles
        at rest, its spheres and capsules and the smallest radius of the triangles' corners); ``finalize``
        switches them on by it unless told otherwise."""
        faces = [g.particles[g.faces] for g in self._meshes]
        if not faces or not self._shapes:
            return TriangleContactRule(False)
        tris = np.concatenate(faces)
        q, r = np.concatenate(self._q), np.concatenate(self._radius)
        return triangle_contact_rule(self._shapes, q[tris], float(r[tris].min()))

    def add_collider_plane(self, *, point=(0.0, 0.0, 0.0), normal=None, friction: float = 0.5,
                           restitution: float = 0.0, translation: Track | None = None,
                           rotation: Track | None = None, name="ground", static_friction: float | None = None,
                           thickness: float = 0.0) -> int:
        """Add an infinite plane; particles stay on the side its normal points to.

        Args:
            point: a point on the plane [m].
            normal: plane normal (normalised here); default the up axis.
            friction: Coulomb coefficient μ [-], ≥ 0.
            restitution: coefficient of restitution e [-] in [0, 1]: the normal speed an impact keeps.
            translation, rotation: keyframe tracks moving the plane (see :meth:`add_collider_box`).
            name: prim name for export.

        Returns:
            The collider's index.
        """
        n = self.up_vector if normal is None else checks.vector("plane normal", normal)
        length = np.linalg.norm(n)
        if length == 0.0:
            raise ConfigError("plane normal must be a nonzero vector")
        orientation = quat_between(np.array([0.0, 0.0, 1.0]), n / length)
        return self._add_shape(SHAPE_PLANE, checks.vector("plane point", point), orientation, (0.0, 0.0, 0.0),
                               friction, restitution, translation, rotation, name, static_friction=static_friction,
                               thickness=thickness)

    def add_ground_plane(self, *, height: float = 0.0, friction: float = 0.5, restitution: float = 0.0,
                         name: str = "ground") -> int:
        """Add the ground: a plane through ``height`` [m] along the up axis, normal up."""
        height = checks.number("ground height", height, minimum=-np.inf, inclusive=True)
        return self.add_collider_plane(point=self.up_vector * height, friction=friction, restitution=restitution,
                                       name=name)

    def add_collider_sphere(self, *, center, radius: float, friction: float = 0.5, restitution: float = 0.0,
                            translation: Track | None = None, rotation: Track | None = None,
                            name="sphere", static_friction: float | None = None, thickness: float = 0.0) -> int:
        """Add a sphere of ``radius`` [m] at ``center`` [m] (other arguments as :meth:`add_collider_box`)."""
        size = (checks.positive("sphere radius", radius), 0.0, 0.0)
        return self._add_shape(SHAPE_SPHERE, checks.vector("sphere center", center), (0.0, 0.0, 0.0, 1.0), size,
                               friction, restitution, translation, rotation, name, static_friction=static_friction,
                               thickness=thickness)

    def add_collider_box(self, *, center, half_extents, orientation=(0.0, 0.0, 0.0, 1.0), friction: float = 0.5,
                         restitution: float = 0.0, translation: Track | None = None,
                         rotation: Track | None = None, name="box", static_friction: float | None = None,
                         thickness: float = 0.0) -> int:
        """Add a box collider.

        Args:
            center: the box's centre [m] at rest (time 0 without tracks).
            half_extents: half the box's size along its own x, y, z axes [m], each > 0.
            orientation: the box's rest orientation, a quaternion (x, y, z, w).
            friction: Coulomb coefficient μ [-], ≥ 0, against the moving surface.
            restitution: coefficient of restitution e [-] in [0, 1] (applies to impacts faster than two steps of
                gravity, so that a resting particle does not hop).
            translation: :class:`Track` of T(t) [m], 3-vectors added to ``center``.
            rotation: :class:`Track` of the rotation vector φ(t) [rad] (axis × angle, see
                :meth:`Track.rotation`) turning the box about its centre: orientation R(φ(t)) · rest.
            name: prim name for export.
            static_friction: Coulomb μ_s [-] ≥ ``friction`` (then the kinetic μ_k): a contact sticks while its
                tangential speed change stays within μ_s times the normal one; default μ_k.
            thickness: a shell around the surface [m], ≥ 0: particles stay radius + thickness from it.

        Returns:
            The collider's index. With a track the collider moves; particles touching it take its surface
            velocity (friction acts relative to it), and it is exported with time-sampled transforms.
        """
        half = checks.vector("box half_extents", half_extents)
        if not (half > 0.0).all():
            raise ConfigError(f"box half_extents must all be > 0 [m], got {tuple(half)}")
        return self._add_shape(SHAPE_BOX, checks.vector("box center", center), _quaternion(orientation),
                               tuple(half), friction, restitution, translation, rotation, name,
                               static_friction=static_friction, thickness=thickness)

    def add_collider_capsule(self, *, center, radius: float, half_height: float,
                             orientation=(0.0, 0.0, 0.0, 1.0), friction: float = 0.5, restitution: float = 0.0,
                             translation: Track | None = None, rotation: Track | None = None,
                             name="capsule", static_friction: float | None = None, thickness: float = 0.0) -> int:
        """Add a capsule: the points within ``radius`` [m] of the segment from -``half_height`` to
        +``half_height`` [m] along its own z axis (USD's ``Capsule`` with axis "Z" and height 2 ·
        half_height). Other arguments as :meth:`add_collider_box`."""
        size = (checks.positive("capsule radius", radius), checks.non_negative("capsule half_height", half_height),
                0.0)
        return self._add_shape(SHAPE_CAPSULE, checks.vector("capsule center", center), _quaternion(orientation),
                               size, friction, restitution, translation, rotation, name,
                               static_friction=static_friction, thickness=thickness)

    def add_collider_mesh(self, mesh, *, faces=None, prim: str | None = None, center=(0.0, 0.0, 0.0),
                          orientation=(0.0, 0.0, 0.0, 1.0), scale=1.0, sides: str = "closed", thickness: float = 0.0,
                          friction: float = 0.5, static_friction: float | None = None, restitution: float = 0.0,
                          deforming: bool = False, depth: float | None = None, winding_number: bool = False,
                          translation: Track | None = None, rotation: Track | None = None, name: str = "mesh",
                          cache_candidates: int = 32, cache_margin: float | None = None) -> int:
        """Add a triangle-mesh collider (``core/mesh_colliders.py``).

        Args:
            mesh: a file (any format trimesh reads, or ``.usd``/``.usda``/``.usdc``: see
                :func:`~warpspring.core.mesh_files.read_usd_mesh`, whose time-sampled points make the collider
                deform), a ``trimesh.Trimesh``, or vertices [m], shape [v, 3] (then ``faces`` is required).
                Its coordinates are the collider's own frame.
            faces: vertex indices of each triangle, shape [t, 3], counter-clockwise seen from outside.
            prim: the USD mesh prim to read (a file of one mesh needs none).
            center: where the collider's frame origin is at rest [m]; orientation: its rest orientation,
                a quaternion (x, y, z, w); scale: a factor [-] (or one per axis) on the vertices.
            sides: "closed" (a watertight solid: inside by the pseudo-normals of its closest features, or with
                ``winding_number=True`` by its winding number: robust to holes, ~5× the cost), "one_sided" (an
                open mesh whose outside is where its normals point) or "two_sided" (an open shell, kept apart on
                both sides).
            depth: how far from its surface the mesh is looked for [m] (one-sided: up to this deep behind it,
                beyond its border edges too, is inside; a point deep inside a closed mesh looks as far as it
                must); default a tenth of its bounding box's diagonal; more than the particles' radius plus the
                thickness. A closest-point query costs with it.
            thickness: a shell around the surface [m], ≥ 0: particles stay radius + thickness from it.
            friction: kinetic Coulomb coefficient μ_k [-]; static_friction: μ_s ≥ μ_k [-], default μ_k.
            restitution: coefficient of restitution e [-] in [0, 1] (see :meth:`add_collider_box`).
            deforming: its points may change between frames (``model.mesh_collider(name).set_points``);
                implied by time-sampled USD points.
            translation, rotation: keyframe tracks moving its frame (see :meth:`add_collider_box`).
            name: prim name for export.
            cache_candidates, cache_margin: each particle's candidate cache (at most this many triangles; a full
                query only after it moved more than the margin [m]; see ``core/mesh_colliders.py``).

        Returns:
            The collider's index.
        """
        samples = None
        if isinstance(mesh, (str, os.PathLike)):
            path = os.fspath(mesh)
            if path.lower().endswith(USD_EXTENSIONS):
                check_mesh_file_room(path, prim=prim)
                read = read_usd_mesh(path, prim=prim, up_axis=self.up_axis)
                vertices, faces = read.vertices, read.triangles
                samples = read_usd_mesh_samples(path, prim=read.prim, up_axis=self.up_axis)
            else:
                check_mesh_file_room(path)
                loaded = load_mesh_file(path, what="mesh collider")
                vertices, faces = np.asarray(loaded.vertices), np.asarray(loaded.faces)
        elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
            vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        else:
            if faces is None:
                raise ConfigError("add_collider_mesh: vertices need faces=[t, 3] (or pass a file or a trimesh.Trimesh)")
            vertices = mesh
        factor = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
        if not (np.isfinite(factor).all() and (factor > 0.0).all()):
            raise ConfigError(f"mesh collider scale must be > 0 (a number or one per axis), got {scale!r}")
        vertices = np.asarray(vertices, dtype=np.float64)
        times, points = (None, None) if samples is None else samples
        info = mesh_shape(vertices * factor if vertices.ndim == 2 else vertices, faces, sides=sides,
                          deforming=deforming, sample_times=times, depth=depth, winding_number=winding_number,
                          sample_points=None if points is None else points * factor,
                          cache_candidates=cache_candidates, cache_margin=cache_margin)
        return self._add_shape(SHAPE_MESH, checks.vector("mesh center", center), _quaternion(orientation),
                               (0.0, 0.0, 0.0), friction, restitution, translation, rotation, name,
                               static_friction=static_friction, thickness=thickness, mesh=info)

    def _add_shape(self, kind, position, orientation, size, friction, restitution, translation, rotation, name, *,
                   static_friction=None, thickness=0.0, mesh=None):
        friction = checks.non_negative("friction", friction)
        thickness = checks.non_negative("collider thickness", thickness)
        if static_friction is not None:
            static_friction = checks.non_negative("static_friction", static_friction)
            if static_friction < friction:
                raise ConfigError(f"static_friction ({static_friction}) must be at least the kinetic friction "
                                  f"({friction}): a contact slides above μ_s and then feels μ_k ≤ μ_s")
        restitution = checks.number("restitution", restitution, minimum=0.0)
        if restitution > 1.0:
            raise ConfigError(f"restitution must be in [0, 1] (the share of the normal speed an impact keeps), "
                              f"got {restitution}")
        translation = None if translation is None else as_track("a collider's translation", translation, 3)
        rotation = None if rotation is None else as_track("a collider's rotation", rotation, 3)
        self._shapes.append(ShapeInfo(
            kind=SHAPE_NAMES[kind],
            name=self._unique_name(name, [s.name for s in self._shapes]),
            position=tuple(float(x) for x in position),
            rotation=tuple(float(x) for x in orientation),
            size=tuple(float(x) for x in size),
            friction=friction,
            restitution=restitution,
            translation_track=translation,
            rotation_track=rotation,
            thickness=thickness,
            static_friction=static_friction,
            mesh=mesh,
        ))
        return len(self._shapes) - 1
