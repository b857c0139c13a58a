"""Collider shapes: their kinds, the struct of their arrays, and the signed distance of a point from each.

Colliders are a struct of arrays (:func:`shapes_type`): kind, size, scale, mesh id,
friction (kinetic and static), restitution, thickness, a mesh's sides, and the shape's frame at the start
and at the end of the current step, [rows, shape_count] with one row for every world (static shapes) or one
per world (animated shapes, each world at its own time). A kernel is specialised for the set of kinds the
scene holds (:class:`ContactFeatures`); a kind adds a signed-distance function here and a branch in
``shape_surface``. A shape's distance is its surface's less its ``thickness``. Mesh colliders' distances
come from ``mesh_colliders.py``; a particle's path against a shape is ``swept.py``'s, the response to a
contact ``response.py``'s.
"""

import dataclasses
import functools

import warp as wp

from .mesh_colliders import MeshCache, mesh_cache_funcs, mesh_funcs
from .precision import transform_type, vec3_type

wp.set_module_options({"enable_backward": False})

#: Collider shape kinds (values of ``Shapes.kind``).
SHAPE_PLANE = 0
SHAPE_SPHERE = 1
SHAPE_BOX = 2
SHAPE_CAPSULE = 3
SHAPE_MESH = 4
SHAPE_NAMES = {SHAPE_PLANE: "plane", SHAPE_SPHERE: "sphere", SHAPE_BOX: "box", SHAPE_CAPSULE: "capsule",
               SHAPE_MESH: "mesh"}


@dataclasses.dataclass(frozen=True)
class ContactFeatures:
    """What a scene's contacts compile: the shape kinds present (sorted), whether any shape moves (the
    response then reads the surface velocity), whether the response reads the contact buffer filled by
    ``collide_kernel`` (the contact stage) or tests every shape itself (the fused path for static analytic
    shapes), and whether a particle's path over the step is swept against thin shapes (``swept``). No kinds:
    no contact code at all; a mesh query is compiled only with ``SHAPE_MESH`` among the kinds."""

    kinds: tuple = ()
    moving: bool = False
    buffered: bool = False
    swept: bool = False  # test each particle's path of the step against spheres, boxes, capsules and meshes

    def __bool__(self) -> bool:
        return len(self.kinds) > 0

    def idle(self, shapes: str = "shapes", slots: str | None = None) -> tuple:
        """``flat_kernel(last=)`` names of the kernel parameters ``shapes`` (a Shapes struct) and ``slots`` (a
        ContactSlots struct) that the specialised response never reads."""
        idle = () if self else (shapes,)
        if self and SHAPE_MESH not in self.kinds:
            idle += (f"{shapes}__cache",)  # the mesh colliders' own arrays
        if slots is not None and not (self and self.buffered):
            idle += (slots,)
        return idle


NO_CONTACTS = ContactFeatures()


@functools.cache
def shapes_type(scalar: type):
    """The ``wp.struct`` of the colliders' arrays in one precision."""
    vec3 = vec3_type(scalar)
    transform = transform_type(scalar)

    @wp.struct
    class Shapes:
        kind: wp.array[wp.int32]  # [shape_count], SHAPE_*
        size: wp.array[vec3]  # [m], [shape_count]: sphere (r, 0, 0), box half extents, capsule (r, half height, 0),
        # mesh (depth: how far from its surface it is looked for; twice its bounding box's diagonal; 0)
        scale: wp.array[vec3]  # [-], [shape_count], a mesh's scale (1 for analytic shapes)
        mesh: wp.array[wp.uint64]  # [shape_count], a Warp mesh id (0 for analytic shapes)
        friction: wp.array[scalar]  # kinetic Coulomb coefficient μ_k [-], [shape_count]
        restitution: wp.array[scalar]  # coefficient e [-], [shape_count]
        transform_start: wp.array2d[transform]  # the shape frame at the step's start, [rows, shape_count]
        transform_end: wp.array2d[transform]  # the shape frame at the step's end, [rows, shape_count]
        thickness: wp.array[scalar]  # [m], [shape_count], a shell around the surface: contact at distance r + thickness
        static_friction: wp.array[scalar]  # Coulomb μ_s [-], [shape_count], ≥ ``friction`` (the kinetic μ_k)
        sides: wp.array[wp.int32]  # [shape_count], a mesh's MESH_* (how it tells inside from outside)
        lower: wp.array[vec3]  # [m], [shape_count], a mesh's bounding box in its frame (lower corner)
        upper: wp.array[vec3]  # [m], [shape_count], a mesh's bounding box in its frame (upper corner)
        cache: MeshCache  # the mesh colliders' pseudo-normals and each particle's candidate triangles

    return Shapes


@functools.cache
def distance_funcs(scalar: type):
    """Signed distances [m] and outward unit normals in a shape's frame."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)

    @wp.func
    def plane_distance(p: vec3):
        """The plane z = 0, normal +z."""
        return p[2], vec3(zero, zero, scalar(1.0))

    @wp.func
    def sphere_distance(p: vec3, radius: scalar):
        """A sphere of ``radius`` at the origin."""
        length = wp.length(p)
        if length > zero:
            return length - radius, p / length
        return -radius, vec3(zero, zero, scalar(1.0))  # at the centre every direction is outward: +z

    @wp.func
    def box_distance(p: vec3, half: vec3):
        """A box of half extents ``half`` centred at the origin, axis-aligned. Outside, the normal points
        from the nearest surface point; inside, along the axis of the nearest face."""
        q = vec3(wp.abs(p[0]) - half[0], wp.abs(p[1]) - half[1], wp.abs(p[2]) - half[2])
        outside = vec3(wp.max(q[0], zero), wp.max(q[1], zero), wp.max(q[2], zero))
        out_length = wp.length(outside)
        if out_length > zero:
            n = vec3(wp.sign(p[0]) * outside[0], wp.sign(p[1]) * outside[1], wp.sign(p[2]) * outside[2])
            return out_length, n / out_length
        # Inside (or on the surface): the face of the largest q is nearest; ties go to the last axis (z).
        axis = 2
        if q[0] > q[1] and q[0] > q[2]:
            axis = 0
        elif q[1] > q[2]:
            axis = 1
        n = vec3(zero)
        n[axis] = wp.where(p[axis] < zero, scalar(-1.0), scalar(1.0))
        return q[axis], n

    @wp.func
    def capsule_distance(p: vec3, radius: scalar, half_height: scalar):
        """A capsule along z: the points within ``radius`` of the segment z ∈ [-half_height, half_height]."""
        d = vec3(p[0], p[1], p[2] - wp.clamp(p[2], -half_height, half_height))
        length = wp.length(d)
        if length > zero:
            return length - radius, d / length
        return -radius, vec3(scalar(1.0), zero, zero)  # on the axis: push along +x

    return plane_distance, sphere_distance, box_distance, capsule_distance


@functools.cache
def surface_funcs(scalar: type, features: ContactFeatures):
    """Distance to one shape, specialised for the scene's kinds: ``shape_surface`` (distance, normal and the
    velocity of a deforming surface) and ``shape_distance`` (distance and normal)."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    plane_distance, sphere_distance, box_distance, capsule_distance = distance_funcs(scalar)
    mesh_distance, _ = mesh_funcs(scalar)
    mesh_surface_cached, _, _, _ = mesh_cache_funcs(scalar)
    kinds = features.kinds
    zero = scalar(0.0)
    zero32 = wp.float32(0.0)

    @wp.func
    def shape_surface(shapes: Shapes, s: int, world: int, p_index: int, x: vec3):
        """Signed distance [m] of the world point x from shape s (its frame at the step's end, less the shape's
        thickness), the outward normal and the velocity of a deforming surface [m/s] (world), for a particle of
        ``world`` (whose row of the frames it reads). ``p_index``: the
        particle's state entry, whose mesh cache a mesh collider uses (``mesh_cache_funcs``), or -1: a mesh
        collider's distance by Warp's own query, up to its depth (as for a mesh whose cache margin is < 0, or
        one signed by its winding number)."""
        row = wp.min(world, shapes.transform_end.shape[0] - 1)
        X = shapes.transform_end[row, s]
        p = wp.transform_point(wp.transform_inverse(X), x)
        kind = shapes.kind[s]
        size = shapes.size[s]
        distance = scalar(1.0e30)
        normal = vec3(zero, zero, scalar(1.0))
        velocity = vec3(zero)
        if wp.static(SHAPE_PLANE in kinds):
            if kind == SHAPE_PLANE:
                distance, normal = plane_distance(p)
        if wp.static(SHAPE_SPHERE in kinds):
            if kind == SHAPE_SPHERE:
                distance, normal = sphere_distance(p, size[0])
        if wp.static(SHAPE_BOX in kinds):
            if kind == SHAPE_BOX:
                distance, normal = box_distance(p, size)
        if wp.static(SHAPE_CAPSULE in kinds):
            if kind == SHAPE_CAPSULE:
                distance, normal = capsule_distance(p, size[0], size[1])
        if wp.static(SHAPE_MESH in kinds):
            if kind == SHAPE_MESH:
                if p_index >= 0 and shapes.cache.slot[s] >= 0 and shapes.cache.margin[s] >= zero32:
                    distance, normal, velocity = mesh_surface_cached(
                        shapes.mesh[s], shapes.cache, s, shapes.sides[s], size[1], shapes.lower[s], shapes.upper[s],
                        world, p_index, p)
                else:
                    distance, normal, velocity = mesh_distance(shapes.mesh[s], shapes.sides[s], size[0], size[1],
                                                               shapes.lower[s], shapes.upper[s], p)
        return distance - shapes.thickness[s], wp.transform_vector(X, normal), wp.transform_vector(X, velocity)

    @wp.func
    def shape_distance(shapes: Shapes, s: int, world: int, p_index: int, x: vec3):
        """Signed distance [m] of the world point x from shape s (its frame at the step's end) and the
        outward normal in world coordinates (``p_index`` as ``shape_surface``'s)."""
        distance, normal, velocity = shape_surface(shapes, s, world, p_index, x)
        return distance, normal

    return shape_surface, shape_distance
