"""Particle-collider contact: shapes, their motion, the contact buffer and the response.

**Shapes.** Colliders are a struct of arrays (:func:`shapes_type`): kind, size, scale, mesh id,
friction (kinetic and static), restitution, thickness, a mesh's sides, and the shape's frame at the start
and at the end of the current step, [rows, shape_count] with one row for every world (static shapes) or one
per world (animated shapes, each world at its own time). A kernel is specialised for the set of kinds the
scene holds (:class:`ContactFeatures`); a kind adds a signed-distance function here and a branch in
``shape_surface``. A shape's distance is its surface's less its ``thickness``.

**Meshes** (``SHAPE_MESH``) are ``wp.Mesh`` BVHs in the shape's frame. A particle's contacts with one come
from :func:`mesh_cache_funcs`: the nearest triangle within the contact reach by an exact closest point per
triangle, signed by the pseudo-normal of its closest feature, from a per-particle candidate cache refreshed by
a BVH query only when the particle moved more than a margin (the cache changes the work, never the answer;
the argument is in its docstring). Warp's own queries (:func:`mesh_funcs`, below) serve points that are no
particle's (``p_index`` = -1), winding-number meshes, and meshes switched to them: the closest point
within the mesh's depth (``size[0]``; a query costs with the distance it may search: for points anywhere
around a 5120-triangle sphere, 40× more within 3 m than within 5 cm on the CPU, ``bench/mesh_queries.py``),
signed by the closest feature's angle-weighted pseudo-normal (closed and one-sided meshes; exact for a
watertight mesh) or the winding number (closed meshes that ask for it: robust to holes, 5.7× the cost near
the surface), or not at all
(two-sided open meshes); a point deep inside a closed mesh looks farther; the surface's
velocity adds the mesh's per-vertex velocities at the closest point (a deforming mesh). Warp's mesh
queries are float32: a float64 model rounds the query point.

**Swept paths** (``ContactFeatures.swept``). A particle that moved h v in a step may have passed through a
thin shape. Its path x0 = x - h v → x (x0 against the shape's frame at the step's start, x against the one
at its end: the path relative to the shape) is tested for entering a sphere, a box (slab test) or a capsule
(cylinder and caps), each grown by the particle's radius and the thickness (a path that grazes it within
the radius is caught too), or a mesh (a ray cast on its BVH against the surface itself; any face of a
two-sided mesh, a face's front otherwise); a path that entered is resolved against the plane of the
entered face, on the side it came from, whatever the closest point says (through a thin box the closest
face is the far one). For symplectic Euler x0 is exactly the step's start (and strain limiting, which
turns Δx into Δv = Δx / h, keeps it); for the other integrators it is the start of the straight path the
final velocity implies. A plane is a half-space: nothing passes it unseen.

**Motion.** ``shape_motion_kernel`` writes the frames of animated shapes at a step's start and end from
keyframe tracks: the shape's rest frame translated by T(t) and turned by the rotation vector φ(t) [rad]
about its own origin, R(φ(t)) R₀ (as pin groups move, ``kinematics.py``).

**The contact buffer.** ``collide_kernel`` finds, for every particle, the shapes whose surface is within
its radius plus a margin, and records them in per-particle slots (:class:`ContactSlots`): the shape
index, in shape order, at most ``slots`` of them. A particle touching more shapes than it has slots keeps
the first ``slots`` and adds the rest to its world's overflow counter (an integer atomic: the count is
exact, the kept contacts do not depend on thread order). With swept paths, a shape the path entered is
recorded too. The response pass walks a particle's own slots, so it writes every result once, without
atomics.

**The response** (position projection, inelastic or restitutive, Coulomb friction), relative to the
surface's velocity. A particle of radius r touches a shape when the signed distance d of its centre
from the surface is below r; it is projected to d = r. With the surface velocity v_s, the relative
velocity's normal part v_n < 0 (approaching) becomes -e v_n when the approach is faster than two steps
of gravity (2 |g| h: a resting particle does not hop) and 0 otherwise; the tangential part v_t stops when
|v_t| ≤ μ_s j_n (static friction; j_n = (1 + e)|v_n| the normal change) and otherwise shrinks by μ_k j_n
(kinetic friction; μ_s = μ_k unless set). The position takes the
tangential change too, h Δv_t, so a particle that sticks moves exactly with the surface — on a moving
platform it keeps its place — and one that slides travels h Σ v.

The surface velocity is the displacement of the surface point over the step: the point at x at the
step's end was at X₀ X₁⁻¹ x at its start, so v_s = (x - X₀ X₁⁻¹ x) / h.
"""

import dataclasses
import functools

import warp as wp

from .inputs import INPUT_GRAVITY
from .kinematics import is_kinematic
from .precision import transform_type, vec3_type
from .tracks import Tracks, track_sample
from .worlds import world_and_index
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})

#: Collider shape kinds (values of ``Shapes.kind``).
SHAPE_PLANE = 0
SHAPE_SPHERE = 1
SHAPE_BOX = 2
SHAPE_CAPSULE = 3
SHAPE_MESH = 4
SHAPE_NAMES = {SHAPE_PLANE: "plane", SHAPE_SPHERE: "sphere", SHAPE_BOX: "box", SHAPE_CAPSULE: "capsule",
               SHAPE_MESH: "mesh"}

#: How a mesh collider tells outside from inside (values of ``Shapes.sides``).
MESH_CLOSED = 0  # a closed mesh, signed by the closest feature's angle-weighted pseudo-normal (exact if watertight)
MESH_ONE_SIDED = 1  # an open mesh whose outside is the side its faces' normals point to (counter-clockwise)
MESH_TWO_SIDED = 2  # an open mesh with no inside: a shell of ``thickness`` on either side
MESH_WINDING = 3  # a closed mesh, inside where its winding number is above ½ (robust to holes; ~5× the cost)
MESH_SIDES = {"closed": MESH_CLOSED, "one_sided": MESH_ONE_SIDED, "two_sided": MESH_TWO_SIDED}

#: The kinds a particle's path is swept against (a plane is a half-space: nothing passes it unseen).
SWEPT_KINDS = (SHAPE_SPHERE, SHAPE_BOX, SHAPE_CAPSULE, SHAPE_MESH)

#: Slot of an empty contact, and of a contact with no feature (analytic shapes).
NO_SHAPE = -1


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
def contact_slots_type(scalar: type):
    """The ``wp.struct`` of the particle-shape contact buffer (see the module docstring)."""

    @wp.struct
    class ContactSlots:
        shape: wp.array2d[wp.int32]  # [state_size, slots], the shapes a particle touches, in shape order
        feature: wp.array2d[wp.int32]  # [state_size, slots], the touched feature (face) or NO_SHAPE
        count: wp.array[wp.int32]  # [state_size], filled slots
        overflow: wp.array[wp.int32]  # [world_count], contacts found beyond a particle's slots, accumulated
        margin: wp.array[scalar]  # [m], [1], distance beyond the radius at which a contact is recorded

    return ContactSlots


@functools.cache
def coulomb_response_func(scalar: type):
    """The contact response with static and kinetic friction (see the module docstring)."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)

    @wp.func
    def coulomb_response(
        x: vec3, v: vec3, radius: scalar, distance: scalar, normal: vec3, surface_velocity: vec3,
        static_friction: scalar, kinetic_friction: scalar, restitution: scalar, bounce_speed: scalar, dt: scalar,
    ):
        """Project a particle out of a shape, with restitution and Coulomb friction relative to the surface: the
        relative tangential velocity v_t stops when |v_t| ≤ μ_s j_n, and otherwise loses μ_k j_n of its length
        (j_n = (1 + e)|v_n| the normal velocity change).

        Args:
            x: particle position [m]; v: particle velocity [m/s]; radius: particle radius [m];
            distance: signed distance of x from the surface [m]; normal: outward unit normal (world);
            surface_velocity: the surface's velocity at x [m/s]; static_friction: μ_s [-];
            kinetic_friction: μ_k [-]; restitution: e [-]; bounce_speed: approach speed [m/s] above which e
            applies; dt: the step that produced x and v [s].
        """
        penetration = radius - distance
        if penetration <= zero:
            return x, v
        x_out = x + normal * penetration
        relative = v - surface_velocity
        vn = wp.dot(relative, normal)
        if vn >= zero:
            return x_out, v
        vt = relative - normal * vn
        bounce = wp.where(-vn > bounce_speed, restitution, zero)
        vt_len = wp.length(vt)
        vt_out = vec3(zero)
        if vt_len + static_friction * (scalar(1.0) + bounce) * vn > zero:  # |v_t| > μ_s j_n: it slides
            slip = vt_len + kinetic_friction * (scalar(1.0) + bounce) * vn  # tangential speed left after μ_k j_n
            if slip > zero:
                vt_out = vt * (slip / vt_len)
        v_out = surface_velocity + vt_out - normal * (bounce * vn)
        return x_out + dt * (vt_out - vt), v_out

    return coulomb_response


@functools.cache
def contact_funcs(scalar: type):
    """Signed distances [m] and outward unit normals in a shape's frame, and the contact response."""
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

    coulomb_response = coulomb_response_func(scalar)

    @wp.func
    def contact_response(
        x: vec3, v: vec3, radius: scalar, distance: scalar, normal: vec3, surface_velocity: vec3,
        friction: scalar, restitution: scalar, bounce_speed: scalar, dt: scalar,
    ):
        """Project a particle out of a shape, with restitution and Coulomb friction relative to the surface.

        Args:
            x: particle position [m]; v: particle velocity [m/s]; radius: particle radius [m];
            distance: signed distance of x from the surface [m]; normal: outward unit normal (world);
            surface_velocity: the surface's velocity at x [m/s]; friction: Coulomb μ [-] (static = kinetic);
            restitution: e [-]; bounce_speed: approach speed [m/s] above which e applies;
            dt: the step that produced x and v [s].
        """
        return coulomb_response(x, v, radius, distance, normal, surface_velocity, friction, friction, restitution,
                                bounce_speed, dt)

    return plane_distance, sphere_distance, box_distance, capsule_distance, contact_response


@functools.cache
def mesh_funcs(scalar: type):
    """Distance to a mesh collider and the crossing of a path with it, in the mesh's frame (Warp's mesh queries
    are float32: a float64 model rounds the query point and widens the results)."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)
    one = scalar(1.0)

    @wp.func
    def mesh_distance(mesh: wp.uint64, sides: int, depth: scalar, reach: scalar, lower: vec3, upper: vec3, p: vec3):
        """Signed distance [m] of the point p from the mesh, the outward unit normal, and the surface's velocity
        [m/s] at the closest point (the mesh's per-vertex velocities interpolated), all in the mesh's frame; a
        distance of 1e30 when p is farther than ``depth`` [m] from the surface (and not inside a closed mesh).
        Closed and one-sided meshes take the sign from the closest feature's angle-weighted pseudo-normal
        (exact for a watertight mesh), or from the winding number (``MESH_WINDING``); a point deep inside a
        closed mesh, which the parity of skew rays finds, looks for its closest point up to ``reach`` [m].
        Two-sided meshes are never inside (distance ≥ 0). A point more than ``depth`` outside the bounding
        box ``lower`` … ``upper`` is out of reach at once: a closest-point query costs with the distance it
        may search."""
        far = scalar(1.0e30)
        outside = vec3(wp.max(lower[0] - p[0], p[0] - upper[0]), wp.max(lower[1] - p[1], p[1] - upper[1]),
                       wp.max(lower[2] - p[2], p[2] - upper[2]))
        if wp.max(outside[0], wp.max(outside[1], outside[2])) > depth:
            return far, vec3(zero, zero, one), vec3(zero)
        q = wp.vec3f(p)
        limit = wp.float32(depth)
        found = bool(False)
        face = int(0)
        u = wp.float32(0.0)
        w = wp.float32(0.0)
        sign = wp.float32(1.0)
        if sides == MESH_WINDING:
            winding = wp.mesh_query_point_sign_winding_number(mesh, q, limit)
            found = bool(winding.result)
            face = int(winding.face)
            u = wp.float32(winding.u)
            w = wp.float32(winding.v)
            sign = wp.float32(winding.sign)
        elif sides == MESH_TWO_SIDED:
            shell = wp.mesh_query_point_no_sign(mesh, q, limit)
            found = bool(shell.result)
            face = int(shell.face)
            u = wp.float32(shell.u)
            w = wp.float32(shell.v)
        else:
            # Distances within 1e-5 of the mean edge length count as equal when the closest feature is chosen
            # (Warp's default, 1e-3, lets a slab 2 mm thick with 8 m faces take its far face for the near one).
            near = wp.mesh_query_point_sign_normal(mesh, q, limit, wp.float32(1.0e-5))
            found = bool(near.result)
            face = int(near.face)
            u = wp.float32(near.u)
            w = wp.float32(near.v)
            sign = wp.float32(near.sign)
        # A closed mesh with nothing within depth: p is far outside, or deep inside. The parity of three skew
        # rays (a majority: a ray through an edge or a vertex may count a crossing twice) tells them apart
        # cheaply; a point found inside looks for its closest point as far as it must.
        if not found and (sides == MESH_CLOSED or sides == MESH_WINDING):
            votes = wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(0.267261, 0.534522, 0.801784)) % 2
            votes += wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(-0.707107, 0.408248, 0.57735)) % 2
            votes += wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(0.123091, -0.492366, -0.861640)) % 2
            if votes >= 2:
                deep = wp.mesh_query_point_no_sign(mesh, q, wp.float32(reach))
                found = bool(deep.result)
                face = int(deep.face)
                u = wp.float32(deep.u)
                w = wp.float32(deep.v)
                sign = wp.float32(-1.0)
        if not found:
            return far, vec3(zero, zero, one), vec3(zero)
        sign = wp.where(sign < wp.float32(0.0), wp.float32(-1.0), wp.float32(1.0))
        offset = p - vec3(wp.mesh_eval_position(mesh, face, u, w))
        length = wp.length(offset)
        normal = vec3(wp.mesh_eval_face_normal(mesh, face))  # on the surface: the face's own normal
        if length > zero:
            normal = offset * (scalar(sign) / length)
        return scalar(sign) * length, normal, vec3(wp.mesh_eval_velocity(mesh, face, u, w))

    @wp.func
    def mesh_crossing(mesh: wp.uint64, sides: int, p0: vec3, p1: vec3):
        """Whether the segment p0 → p1 enters the mesh (any face of a two-sided mesh, a face's front otherwise),
        the first crossing point and the crossed face's unit normal on p0's side (mesh frame)."""
        d = p1 - p0
        if wp.length(d) > zero:
            ray = wp.mesh_query_ray(mesh, wp.vec3f(p0), wp.vec3f(d), wp.float32(1.0))  # t in units of |d|
            if ray.result and (sides == MESH_TWO_SIDED or ray.sign > wp.float32(0.0)):
                side = wp.where(ray.sign < wp.float32(0.0), scalar(-1.0), scalar(1.0))
                return True, p0 + scalar(ray.t) * d, vec3(ray.normal) * side
        return False, p1, vec3(zero, zero, one)

    return mesh_distance, mesh_crossing


#: Features of a triangle its closest point lies on (``mesh_cache_funcs``): the face, an edge, a vertex; the
#: index of its pseudo-normal among the face's seven (face, edges ab bc ca, vertices a b c).
FEATURE_FACE = 0
FEATURE_EDGE_AB = 1
FEATURE_EDGE_BC = 2
FEATURE_EDGE_CA = 3
FEATURE_VERTEX_A = 4
FEATURE_VERTEX_B = 5
FEATURE_VERTEX_C = 6
#: Pseudo-normals stored per face (``MeshCache.normals``).
FACE_NORMALS = 7
#: A mesh cache entry that must be refreshed (``MeshCache.side``): no valid candidates.
CACHE_INVALID = 0


@wp.struct
class MeshCache:
    """The mesh colliders' own data beside ``Shapes`` (float32, as Warp's meshes) and each particle's candidate
    cache (a Verlet list; see :func:`mesh_cache_funcs`)."""

    slot: wp.array[wp.int32]  # [shape_count], the shape's row in the cache arrays; -1: Warp's own queries
    reach: wp.array[wp.float32]  # [m], [shape_count], R: the distance from the surface resolved exactly
    margin: wp.array[wp.float32]  # [m], [shape_count], m: how far a particle may move before it queries again
    # (0: a full query at every use; < 0: Warp's own closest-point query, as ``p_index`` = -1 has)
    normal_offset: wp.array[wp.int32]  # [shape_count], the mesh's first entry of ``normals``
    normals: wp.array[wp.vec3f]  # [-], [7 · Σ faces], unit pseudo-normals per face (face, 3 edges, 3 corners)
    ref: wp.array2d[wp.vec3f]  # [m], [cached meshes, state_size], x_ref in the mesh's frame
    side: wp.array2d[wp.int32]  # [cached meshes, state_size], +1 outside, -1 inside at x_ref, 0: refresh
    count: wp.array2d[wp.int32]  # [cached meshes, state_size], candidates held
    face: wp.array3d[wp.int32]  # [cached meshes, state_size, C], the candidate triangles
    overflow: wp.array[wp.int32]  # [world_count], refreshes that found more than C candidates (full query then)
    refreshes: wp.array[wp.int32]  # [world_count], full queries made with the cache on (refreshes), accumulated



@wp.func
def face_unit_normal(mesh: wp.uint64, f: int) -> wp.vec3d:
    """Face f's unit normal (counter-clockwise), float64 from the mesh's float32 points; zero if degenerate."""
    a = wp.vec3d(wp.mesh_get_point(mesh, 3 * f))
    n = wp.cross(wp.vec3d(wp.mesh_get_point(mesh, 3 * f + 1)) - a, wp.vec3d(wp.mesh_get_point(mesh, 3 * f + 2)) - a)
    length = wp.length(n)
    if length > wp.float64(0.0):
        return n / length
    return wp.vec3d()


@wp.func
def face_corner_angle(mesh: wp.uint64, f: int, k: int) -> wp.float64:
    """Face f's interior angle [rad] at its corner k (0 for a degenerate corner)."""
    p = wp.vec3d(wp.mesh_get_point(mesh, 3 * f + k))
    u = wp.vec3d(wp.mesh_get_point(mesh, 3 * f + (k + 1) % 3)) - p
    w = wp.vec3d(wp.mesh_get_point(mesh, 3 * f + (k + 2) % 3)) - p
    lengths = wp.length(u) * wp.length(w)
    if lengths > wp.float64(0.0):
        return wp.acos(wp.clamp(wp.dot(u, w) / lengths, wp.float64(-1.0), wp.float64(1.0)))
    return wp.float64(0.0)


@wp.func
def unit_or_zero(n: wp.vec3d) -> wp.vec3f:
    length = wp.length(n)
    if length > wp.float64(0.0):
        return wp.vec3f(n / length)
    return wp.vec3f()


@wp.kernel(enable_backward=False)
def face_normals_kernel(mesh: wp.uint64, face_normal: wp.array[wp.vec3d], corner_angle: wp.array[wp.float64]):
    """Each face's unit normal and its angles [rad] at its corners (3 f + k), float64 from the mesh's points:
    the terms :func:`pseudo_normals_kernel` sums. Launch over the faces."""
    f = wp.tid()
    face_normal[f] = face_unit_normal(mesh, f)
    for k in range(3):
        corner_angle[3 * f + k] = face_corner_angle(mesh, f, k)


@wp.kernel(enable_backward=False)
def pseudo_normals_kernel(
    mesh: wp.uint64,
    face_normal: wp.array[wp.vec3d],  # [t], from face_normals_kernel
    corner_angle: wp.array[wp.float64],  # [rad], [3 t], from face_normals_kernel
    vertex_start: wp.array[wp.int32],  # [v + 1], CSR over the corners (3 f + k) at each vertex
    vertex_corner: wp.array[wp.int32],  # [3 t], in face order
    edge_group: wp.array[wp.int32],  # [3 t], the undirected edge of each face's edge k (ab, bc, ca)
    edge_start: wp.array[wp.int32],  # [edges + 1], CSR over the faces at each edge
    edge_face: wp.array[wp.int32],  # [3 t], in face order
    offset: int,
    normals: wp.array[wp.vec3f],
):
    """The seven unit pseudo-normals of face f (``MeshCache.normals``: face, edges ab bc ca, corners a b c),
    summed in float64 in a fixed order (no atomics). Launch over the faces."""
    f = wp.tid()
    base = offset + FACE_NORMALS * f
    normals[base] = unit_or_zero(face_normal[f])
    for k in range(3):
        group = edge_group[3 * f + k]
        edge = wp.vec3d()
        for j in range(edge_start[group], edge_start[group + 1]):
            edge += face_normal[edge_face[j]]
        normals[base + FEATURE_EDGE_AB + k] = unit_or_zero(edge)
        vertex = wp.mesh_get_index(mesh, 3 * f + k)
        corner_sum = wp.vec3d()
        for j in range(vertex_start[vertex], vertex_start[vertex + 1]):
            corner = vertex_corner[j]
            corner_sum += corner_angle[corner] * face_normal[corner / 3]
        normals[base + FEATURE_VERTEX_A + k] = unit_or_zero(corner_sum)

@functools.cache
def mesh_cache_funcs(scalar: type):
    """The mesh path of the particle contacts: exact closest points and path crossings on a mesh collider's
    triangles, from a full BVH query or from a particle's cached candidates, with the same answer either way.

    **The answer.** For a point q (the mesh's frame, float32) the result is the nearest triangle among those
    within R = ``reach`` of q (closest point per triangle by Ericson's regions, ties to the lowest face index,
    so it does not depend on the order triangles are visited), signed by the angle-weighted pseudo-normal of
    the feature (face, edge, vertex) the closest point lies on (closed and one-sided meshes; exact for a
    watertight mesh) or unsigned (two-sided). With none within R: out of reach, unless q is inside a closed mesh
    (the parity of three skew rays, as Warp's queries), which looks for its closest point as far as it must.
    R is the particles' largest radius plus the thickness (what the response and ``collide`` can touch), or
    for a one-sided mesh its depth (up to which behind it is inside). A path's crossing is the first triangle
    Woop's watertight ray test hits on the segment p0 → p1 (ties to the lowest face).

    **The cache.** A full query (``wp.mesh_query_aabb`` around q, then the exact test per triangle) also
    keeps, for its particle: x_ref = q, the side (inside or outside) at x_ref, and every triangle within
    R + m of x_ref (a float32-safe pad added), at most C; more is an overflow (counted; the particle queries
    fully again next time, so the answer never depends on C). Until the particle's point in the mesh's
    frame is more than m from x_ref (δ = |q - x_ref| ≤ m), only the candidates are evaluated:

    * every triangle within R of q is within R + δ ≤ R + m of x_ref, so it is a candidate: the nearest within
      R, and its feature, are the full query's;
    * with no candidate within R, q is out of reach unless it is inside; the side cannot have changed: a
      segment x_ref → q that crossed the surface at c would put c within δ of both ends (convexity of the
      ball of radius δ ≤ m about x_ref), so c's triangle would be a candidate within δ of q. When every
      candidate is farther than δ from q, q is on x_ref's side; otherwise (only when m exceeds R) it queries
      fully;
    * a swept path whose both ends are within m of x_ref lies in that ball (convexity), so every triangle it
      crosses is a candidate.

    A tracked mesh keeps x_ref in its own frame, so its motion needs no bound; a deforming mesh invalidates
    every cache entry when its points are set. Each thread writes only its particle's entries; the counters
    are integer atomics."""
    vec3 = vec3_type(scalar)
    f32 = wp.float32
    zero = scalar(0.0)
    one = scalar(1.0)
    none = f32(0.0)

    @wp.func
    def triangle_closest(a: wp.vec3f, b: wp.vec3f, c: wp.vec3f, p: wp.vec3f):
        """The point of triangle abc closest to p (Ericson's Voronoi regions), its barycentric weights of a and b,
        and the feature it lies on (``FEATURE_*``). A degenerate triangle gives one of its vertices or edges."""
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = wp.dot(ab, ap)
        d2 = wp.dot(ac, ap)
        if d1 <= none and d2 <= none:
            return a, f32(1.0), none, FEATURE_VERTEX_A
        bp = p - b
        d3 = wp.dot(ab, bp)
        d4 = wp.dot(ac, bp)
        if d3 >= none and d4 <= d3:
            return b, none, f32(1.0), FEATURE_VERTEX_B
        vc = d1 * d4 - d3 * d2
        if vc <= none and d1 >= none and d3 <= none and d1 - d3 > none:
            v = d1 / (d1 - d3)
            return a + v * ab, f32(1.0) - v, v, FEATURE_EDGE_AB
        cp = p - c
        d5 = wp.dot(ab, cp)
        d6 = wp.dot(ac, cp)
        if d6 >= none and d5 <= d6:
            return c, none, none, FEATURE_VERTEX_C
        vb = d5 * d2 - d1 * d6
        if vb <= none and d2 >= none and d6 <= none and d2 - d6 > none:
            w = d2 / (d2 - d6)
            return a + w * ac, f32(1.0) - w, none, FEATURE_EDGE_CA
        va = d3 * d6 - d5 * d4
        if va <= none and d4 - d3 >= none and d5 - d6 >= none and (d4 - d3) + (d5 - d6) > none:
            w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            return b + w * (c - b), none, f32(1.0) - w, FEATURE_EDGE_BC
        denom = va + vb + vc
        if denom > none:
            v = vb / denom
            w = vc / denom
            return a + ab * v + ac * w, f32(1.0) - v - w, v, FEATURE_FACE
        return a, f32(1.0), none, FEATURE_VERTEX_A

    @wp.func
    def face_closest(mesh: wp.uint64, f: int, q: wp.vec3f):
        """Distance [m] from q to face f of the mesh, the closest point, its weights of the face's first two
        vertices and its feature."""
        a = wp.mesh_get_point(mesh, 3 * f)
        b = wp.mesh_get_point(mesh, 3 * f + 1)
        c = wp.mesh_get_point(mesh, 3 * f + 2)
        closest, wa, wb, feature = triangle_closest(a, b, c, q)
        return wp.length(q - closest), closest, wa, wb, feature

    @wp.func
    def nearer(d: f32, f: int, best_d: f32, best_f: int) -> bool:
        """Whether face f at distance d beats the best so far (ties to the lower index: order-free)."""
        return best_f < 0 or d < best_d or (d == best_d and f < best_f)

    @wp.func
    def ray_triangle(a: wp.vec3f, b: wp.vec3f, c: wp.vec3f, o: wp.vec3f, d: wp.vec3f):
        """Woop, Benthin and Wald's watertight ray-triangle test of the segment o → o + d: whether it hits, the
        fraction t ∈ [0, 1] and whether it hit the front (counter-clockwise) side. A segment through an edge or a
        vertex hits at least one of the triangles that share it."""
        kz = int(0)
        if wp.abs(d[1]) > wp.abs(d[kz]):
            kz = 1
        if wp.abs(d[2]) > wp.abs(d[kz]):
            kz = 2
        kx = (kz + 1) % 3
        ky = (kx + 1) % 3
        if d[kz] < none:
            swap = kx
            kx = ky
            ky = swap
        sx = d[kx] / d[kz]
        sy = d[ky] / d[kz]
        sz = f32(1.0) / d[kz]
        A = a - o
        B = b - o
        C = c - o
        ax = A[kx] - sx * A[kz]
        ay = A[ky] - sy * A[kz]
        bx = B[kx] - sx * B[kz]
        by = B[ky] - sy * B[kz]
        cx = C[kx] - sx * C[kz]
        cy = C[ky] - sy * C[kz]
        # Edge functions from exact products (float32 × float32 fits float64), rounded once: the edge two
        # triangles share gives them opposite values, so no ray slips between them.
        U = f32(wp.float64(cx) * wp.float64(by) - wp.float64(cy) * wp.float64(bx))
        V = f32(wp.float64(ax) * wp.float64(cy) - wp.float64(ay) * wp.float64(cx))
        W = f32(wp.float64(bx) * wp.float64(ay) - wp.float64(by) * wp.float64(ax))
        if (U < none or V < none or W < none) and (U > none or V > none or W > none):
            return False, none, False
        det = U + V + W
        if det == none:
            return False, none, False
        T = U * (sz * A[kz]) + V * (sz * B[kz]) + W * (sz * C[kz])
        t = T / det
        if t < none or t > f32(1.0):
            return False, none, False
        return True, t, det > none

    @wp.func
    def face_ray(mesh: wp.uint64, f: int, o: wp.vec3f, dir: wp.vec3f):
        """``ray_triangle`` of the segment o → o + dir against face f of the mesh: hit, its parameter, front."""
        a = wp.mesh_get_point(mesh, 3 * f)
        b = wp.mesh_get_point(mesh, 3 * f + 1)
        c = wp.mesh_get_point(mesh, 3 * f + 2)
        hit, t, front = ray_triangle(a, b, c, o, dir)
        return hit, t, front

    @wp.func
    def face_result(mesh: wp.uint64, cache: MeshCache, s: int, sides: int, f: int, closest: wp.vec3f, wa: f32, wb: f32,
                    feature: int, p: vec3):
        """Signed distance [m] of p from face f's closest point, the outward unit normal and the surface's
        velocity [m/s] there (mesh frame); the sign from the feature's pseudo-normal (two-sided: unsigned)."""
        n = cache.normals[cache.normal_offset[s] + FACE_NORMALS * f + feature]
        sign = one
        if sides != MESH_TWO_SIDED:
            if wp.dot(wp.vec3f(p) - closest, n) < none:
                sign = -one
        offset = p - vec3(closest)
        length = wp.length(offset)
        normal = vec3(cache.normals[cache.normal_offset[s] + FACE_NORMALS * f])  # on the surface: the face's normal
        if length > zero:
            normal = offset * (sign / length)
        return sign * length, normal, vec3(wp.mesh_eval_velocity(mesh, f, wa, wb))

    @wp.func
    def deep_result(mesh: wp.uint64, cache: MeshCache, s: int, reach: scalar, p: vec3):
        """A point inside a closed mesh farther than R from it: its closest point, however far (distance < 0)."""
        q = wp.vec3f(p)
        deep = wp.mesh_query_point_no_sign(mesh, q, wp.float32(reach))
        if not deep.result:
            return scalar(1.0e30), vec3(zero, zero, one), vec3(zero)
        d, closest, wa, wb, feature = face_closest(mesh, deep.face, q)
        offset = p - vec3(closest)
        length = wp.length(offset)
        normal = vec3(cache.normals[cache.normal_offset[s] + FACE_NORMALS * deep.face])
        if length > zero:
            normal = offset * (-one / length)
        return -length, normal, vec3(wp.mesh_eval_velocity(mesh, deep.face, wa, wb))

    @wp.func
    def parity_inside(mesh: wp.uint64, q: wp.vec3f) -> bool:
        """Whether q is inside a closed mesh: the parity of three skew rays, by majority (a ray through an edge or
        a vertex may count a crossing twice)."""
        votes = wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(0.267261, 0.534522, 0.801784)) % 2
        votes += wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(-0.707107, 0.408248, 0.57735)) % 2
        votes += wp.mesh_query_ray_count_intersections(mesh, q, wp.vec3f(0.123091, -0.492366, -0.861640)) % 2
        return votes >= 2

    @wp.func
    def pad_for(q: wp.vec3f, lower: vec3, upper: vec3, extent: f32) -> f32:
        """A float32-safe pad [m] on distances of magnitude ``extent`` among coordinates like q's and the
        mesh's: rounding of the closest point, the distances and the displacement stays far below it."""
        size = wp.max(wp.max(wp.abs(q[0]), wp.abs(q[1])), wp.abs(q[2]))
        size = wp.max(size, f32(wp.max(wp.max(wp.abs(lower[0]), wp.abs(lower[1])), wp.abs(lower[2]))))
        size = wp.max(size, f32(wp.max(wp.max(wp.abs(upper[0]), wp.abs(upper[1])), wp.abs(upper[2]))))
        return f32(1.0e-5) * (size + extent) + f32(1.0e-30)

    @wp.func
    def mesh_surface_cached(
        mesh: wp.uint64, cache: MeshCache, s: int, sides: int, deep_reach: scalar, lower: vec3, upper: vec3,
        world: int, p_index: int, p: vec3,
    ):
        """Signed distance [m] of p (the mesh's frame) from mesh collider s, the outward unit normal and the
        surface's velocity [m/s] (see the factory's docstring); 1e30 out of reach. ``p_index`` is the
        particle's state entry (its cache row), -1 for none (a full query that keeps nothing)."""
        far = scalar(1.0e30)
        q = wp.vec3f(p)
        reach = cache.reach[s]
        margin = cache.margin[s]
        slot = cache.slot[s]
        closed = sides == MESH_CLOSED
        if p_index >= 0 and margin > none and cache.side[slot, p_index] != CACHE_INVALID:
            delta = wp.length(q - cache.ref[slot, p_index])
            if delta <= margin:
                best_d = none
                best_f = int(-1)
                best_c = wp.vec3f()
                best_a = none
                best_b = none
                best_feature = int(0)
                nearest = f32(3.0e38)
                for k in range(cache.count[slot, p_index]):
                    f = cache.face[slot, p_index, k]
                    d, closest, wa, wb, feature = face_closest(mesh, f, q)
                    nearest = wp.min(nearest, d)
                    if d <= reach and nearer(d, f, best_d, best_f):
                        best_d = d
                        best_f = f
                        best_c = closest
                        best_a = wa
                        best_b = wb
                        best_feature = feature
                if best_f >= 0:
                    distance, normal, velocity = face_result(mesh, cache, s, sides, best_f, best_c, best_a, best_b,
                                                             best_feature, p)
                    return distance, normal, velocity
                if not closed:
                    return far, vec3(zero, zero, one), vec3(zero)
                if nearest > delta + pad_for(q, lower, upper, delta):  # no crossing since x_ref: x_ref's side
                    if cache.side[slot, p_index] < 0:
                        distance, normal, velocity = deep_result(mesh, cache, s, deep_reach, p)
                        return distance, normal, velocity
                    return far, vec3(zero, zero, one), vec3(zero)
        # The full query (and, with a cache row and a margin, its refresh).
        store = p_index >= 0 and margin > none
        keep = wp.where(store, margin, none)
        pad = pad_for(q, lower, upper, reach + keep)
        extent = reach + keep + pad
        best_d = none
        best_f = int(-1)
        best_c = wp.vec3f()
        best_a = none
        best_b = none
        best_feature = int(0)
        count = int(0)
        overflow = bool(False)
        capacity = cache.face.shape[2]
        outside = wp.max(wp.max(f32(lower[0]) - q[0], q[0] - f32(upper[0])),
                         wp.max(wp.max(f32(lower[1]) - q[1], q[1] - f32(upper[1])),
                                wp.max(f32(lower[2]) - q[2], q[2] - f32(upper[2]))))
        if outside <= extent:
            query = wp.mesh_query_aabb(mesh, q - wp.vec3f(extent, extent, extent), q + wp.vec3f(extent, extent, extent))
            f = int(0)
            while wp.mesh_query_aabb_next(query, f):
                d, closest, wa, wb, feature = face_closest(mesh, f, q)
                if store and d <= extent:
                    if count < capacity:
                        cache.face[slot, p_index, count] = f
                        count += 1
                    else:
                        overflow = True
                if d <= reach and nearer(d, f, best_d, best_f):
                    best_d = d
                    best_f = f
                    best_c = closest
                    best_a = wa
                    best_b = wb
                    best_feature = feature
        side = int(1)
        distance = far
        normal = vec3(zero, zero, one)
        velocity = vec3(zero)
        if best_f >= 0:
            distance, normal, velocity = face_result(mesh, cache, s, sides, best_f, best_c, best_a, best_b,
                                                     best_feature, p)
            if distance < zero:
                side = -1
        elif closed and outside < none:
            if parity_inside(mesh, q):
                side = -1
                distance, normal, velocity = deep_result(mesh, cache, s, deep_reach, p)
        if store:
            cache.ref[slot, p_index] = q
            cache.count[slot, p_index] = count
            cache.side[slot, p_index] = wp.where(overflow, CACHE_INVALID, side)
            wp.atomic_add(cache.refreshes, world, 1)
            if overflow:
                wp.atomic_add(cache.overflow, world, 1)
        return distance, normal, velocity

    @wp.func
    def mesh_crossing_cached(mesh: wp.uint64, cache: MeshCache, s: int, sides: int, lower: vec3, upper: vec3,
                             p_index: int, p0: vec3, p1: vec3):
        """Whether the segment p0 → p1 (mesh frame) enters the mesh (any face of a two-sided mesh, a face's front
        otherwise: the first face it hits decides), the crossing point and the face's unit normal on p0's side:
        over the particle's candidates when both ends are within m of its x_ref, else over the triangles a BVH
        query of the segment's box returns."""
        d = p1 - p0
        if wp.length(d) > zero:
            o = wp.vec3f(p0)
            dir = wp.vec3f(d)
            best_t = none
            best_f = int(-1)
            best_front = bool(False)
            slot = cache.slot[s]
            margin = cache.margin[s]
            cached = bool(False)
            if p_index >= 0 and margin > none and cache.side[slot, p_index] != CACHE_INVALID:
                ref = cache.ref[slot, p_index]
                cached = wp.length(o - ref) <= margin and wp.length(wp.vec3f(p1) - ref) <= margin
            if cached:
                for k in range(cache.count[slot, p_index]):
                    f = cache.face[slot, p_index, k]
                    hit, t, front = face_ray(mesh, f, o, dir)
                    if hit and nearer(t, f, best_t, best_f):
                        best_t = t
                        best_f = f
                        best_front = front
            else:
                end = o + dir
                pad = pad_for(o, lower, upper, wp.length(dir))
                low = wp.vec3f(wp.min(o[0], end[0]) - pad, wp.min(o[1], end[1]) - pad, wp.min(o[2], end[2]) - pad)
                high = wp.vec3f(wp.max(o[0], end[0]) + pad, wp.max(o[1], end[1]) + pad, wp.max(o[2], end[2]) + pad)
                query = wp.mesh_query_aabb(mesh, low, high)
                f = int(0)
                while wp.mesh_query_aabb_next(query, f):
                    hit, t, front = face_ray(mesh, f, o, dir)
                    if hit and nearer(t, f, best_t, best_f):
                        best_t = t
                        best_f = f
                        best_front = front
            if best_f >= 0 and (sides == MESH_TWO_SIDED or best_front):
                n = vec3(cache.normals[cache.normal_offset[s] + FACE_NORMALS * best_f])
                return True, p0 + scalar(best_t) * d, wp.where(best_front, n, -n)
        return False, p1, vec3(zero, zero, one)

    return mesh_surface_cached, mesh_crossing_cached, triangle_closest, ray_triangle


@functools.cache
def sweep_funcs(scalar: type):
    """Where a particle's path p0 → p1 (in a shape's frame) first enters a sphere, a box or a capsule that p0 is
    outside."""
    vec3 = vec3_type(scalar)
    zero = scalar(0.0)
    one = scalar(1.0)

    @wp.func
    def sphere_entry(p0: vec3, d: vec3, radius: scalar) -> scalar:
        """The fraction t ∈ [0, 1] of the path p0 → p0 + d at which it enters the sphere of ``radius`` [m] at the
        origin from outside, or -1."""
        a = wp.dot(d, d)
        b = wp.dot(p0, d)
        c = wp.dot(p0, p0) - radius * radius
        disc = b * b - a * c
        if c > zero and a > zero and disc >= zero:
            t = (-b - wp.sqrt(disc)) / a
            if t >= zero and t <= one:
                return t
        return -one

    @wp.func
    def sphere_crossing(p0: vec3, p1: vec3, radius: scalar):
        """Whether p0 → p1 enters the sphere of ``radius`` [m] at the origin, the entry point and its normal."""
        t = sphere_entry(p0, p1 - p0, radius)
        if t >= zero:
            hit = p0 + t * (p1 - p0)
            return True, hit, wp.normalize(hit)
        return False, p1, vec3(zero, zero, one)

    @wp.func
    def capsule_crossing(p0: vec3, p1: vec3, radius: scalar, half_height: scalar):
        """Whether p0 → p1 enters the capsule of ``radius`` [m] around the segment z ∈ [-half_height,
        half_height] from outside: its side (a cylinder) or a cap (a sphere), whichever comes first; the entry
        point and its outward normal."""
        d = p1 - p0
        best = scalar(2.0)
        normal = vec3(zero, zero, one)
        a = d[0] * d[0] + d[1] * d[1]
        b = p0[0] * d[0] + p0[1] * d[1]
        c = p0[0] * p0[0] + p0[1] * p0[1] - radius * radius
        disc = b * b - a * c
        if c > zero and a > zero and disc >= zero:
            t = (-b - wp.sqrt(disc)) / a
            z = p0[2] + t * d[2]
            if t >= zero and t <= one and z >= -half_height and z <= half_height:
                best = t
                normal = vec3(p0[0] + t * d[0], p0[1] + t * d[1], zero) / radius
        for k in range(2):
            cap = vec3(zero, zero, wp.where(k == 0, half_height, -half_height))
            t = sphere_entry(p0 - cap, d, radius)
            if t >= zero and t < best:
                best = t
                normal = wp.normalize(p0 + t * d - cap)
        if best <= one:
            return True, p0 + best * d, normal
        return False, p1, vec3(zero, zero, one)

    @wp.func
    def box_crossing(p0: vec3, p1: vec3, half: vec3):
        """Whether p0 → p1 enters the axis-aligned box of half extents ``half`` [m] at the origin from outside
        (slab test), the entry point and the entry face's outward normal."""
        d = p1 - p0
        enter = zero
        leave = one
        axis = int(-1)
        for k in range(3):
            if wp.abs(d[k]) > zero:
                ta = (-half[k] - p0[k]) / d[k]
                tb = (half[k] - p0[k]) / d[k]
                if wp.min(ta, tb) > enter:
                    enter = wp.min(ta, tb)
                    axis = k
                leave = wp.min(leave, wp.max(ta, tb))
            elif wp.abs(p0[k]) > half[k]:
                leave = -one  # parallel to this slab and outside it: no entry
        if axis >= 0 and enter <= leave:
            n = vec3(zero)
            n[axis] = wp.where(d[axis] > zero, scalar(-1.0), scalar(1.0))
            return True, p0 + enter * d, n
        return False, p1, vec3(zero, zero, one)

    return sphere_crossing, box_crossing, capsule_crossing


@functools.cache
def shape_funcs(scalar: type, features: ContactFeatures):
    """Distance to one shape and the response against one shape, specialised for the scene's kinds."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    plane_distance, sphere_distance, box_distance, capsule_distance, _ = contact_funcs(scalar)
    coulomb_response = coulomb_response_func(scalar)
    mesh_distance, mesh_crossing = mesh_funcs(scalar)
    mesh_surface_cached, mesh_crossing_cached, _, _ = mesh_cache_funcs(scalar)
    sphere_crossing, box_crossing, capsule_crossing = sweep_funcs(scalar)
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

    @wp.func
    def shape_crossing(shapes: Shapes, s: int, world: int, p_index: int, x0: vec3, x: vec3, pad: scalar):
        """Whether the path from x0 (at the step's start, against the shape's start frame) to x (its end frame)
        entered shape s; if so, x's signed distance [m] from the plane of the entered face less the thickness
        (the response's distance), that face's normal on x0's side (world), and the fraction of the step at
        which the path entered. Spheres, boxes and capsules
        are grown by ``pad`` [m] (the particle's radius) and the thickness, so a path that only grazes them
        within the radius is caught too; a mesh is a ray cast against its surface."""
        row = wp.min(world, shapes.transform_end.shape[0] - 1)
        X1 = shapes.transform_end[row, s]
        p0 = wp.transform_point(wp.transform_inverse(shapes.transform_start[row, s]), x0)
        p1 = wp.transform_point(wp.transform_inverse(X1), x)
        kind = shapes.kind[s]
        size = shapes.size[s]
        grow = pad + shapes.thickness[s]
        crossed = bool(False)
        hit = p1
        normal = vec3(zero, zero, scalar(1.0))
        offset = -shapes.thickness[s]  # the entered surface's distance from the response's zero
        if wp.static(SHAPE_SPHERE in kinds):
            if kind == SHAPE_SPHERE:
                crossed, hit, normal = sphere_crossing(p0, p1, size[0] + grow)
                offset = pad
        if wp.static(SHAPE_BOX in kinds):
            if kind == SHAPE_BOX:
                crossed, hit, normal = box_crossing(p0, p1, size + vec3(grow, grow, grow))
                offset = pad
        if wp.static(SHAPE_CAPSULE in kinds):
            if kind == SHAPE_CAPSULE:
                crossed, hit, normal = capsule_crossing(p0, p1, size[0] + grow, size[1])
                offset = pad
        if wp.static(SHAPE_MESH in kinds):
            if kind == SHAPE_MESH:
                if p_index >= 0 and shapes.cache.slot[s] >= 0 and shapes.cache.margin[s] >= zero32:
                    crossed, hit, normal = mesh_crossing_cached(shapes.mesh[s], shapes.cache, s, shapes.sides[s],
                                                                shapes.lower[s], shapes.upper[s], p_index, p0, p1)
                else:
                    crossed, hit, normal = mesh_crossing(shapes.mesh[s], shapes.sides[s], p0, p1)
        d = p1 - p0
        entry = wp.where(wp.dot(d, d) > zero, wp.clamp(wp.dot(hit - p0, d) / wp.dot(d, d), zero, scalar(1.0)), zero)
        return crossed, wp.dot(p1 - hit, normal) + offset, wp.transform_vector(X1, normal), entry

    @wp.func
    def shape_contact(
        shapes: Shapes, s: int, world: int, p_index: int, x0: vec3, x: vec3, v: vec3, radius: scalar,
        bounce_speed: scalar, dt: scalar,
    ):
        """Resolve the contact of one particle (x [m], v [m/s], radius [m]; at x0 [m] at the step's start) with
        shape s after a step dt [s]. A path that entered the shape where its end is out of reach or on the far
        side (the closest point's normal against the entered face's) is put back on the side it came from; the
        tangential change then moves it only over the part of the step after it touched (so a particle that
        sticks stays where it hit). Any other contact is the closest point's, as without sweeping."""
        distance, normal, surface_velocity = shape_surface(shapes, s, world, p_index, x)
        contact_dt = dt
        if wp.static(features.swept):
            crossed, crossed_distance, crossed_normal, entry = shape_crossing(shapes, s, world, p_index, x0, x, radius)
            if crossed and (distance >= radius or wp.dot(normal, crossed_normal) < zero):
                distance = crossed_distance
                normal = crossed_normal
                contact_dt = (scalar(1.0) - entry) * dt
        if wp.static(features.moving):
            row = wp.min(world, shapes.transform_end.shape[0] - 1)
            X0 = shapes.transform_start[row, s]
            X1 = shapes.transform_end[row, s]
            surface_velocity = surface_velocity + (
                x - wp.transform_point(X0, wp.transform_point(wp.transform_inverse(X1), x))) / dt
        return coulomb_response(x, v, radius, distance, normal, surface_velocity, shapes.static_friction[s],
                                shapes.friction[s], shapes.restitution[s], bounce_speed, contact_dt)

    return shape_distance, shape_contact, shape_crossing


@functools.cache
def project_all_func(scalar: type, features: ContactFeatures):
    """Contact response of one particle against every shape, in shape order (the fused path)."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    _, shape_contact, _ = shape_funcs(scalar, features)

    @wp.func
    def bounce_speed(world: int, inputs: wp.array2d[scalar], dt: scalar) -> scalar:
        """Approach speed [m/s] above which restitution applies: two steps of the world's gravity."""
        g = vec3(inputs[world, INPUT_GRAVITY], inputs[world, INPUT_GRAVITY + 1], inputs[world, INPUT_GRAVITY + 2])
        return scalar(2.0) * wp.length(g) * dt

    @wp.func
    def project_contacts_all(
        world: int, p: int, x: vec3, v: vec3, radius: scalar, dt: scalar, shapes: Shapes, inputs: wp.array2d[scalar]
    ):
        """Resolve the contacts of state entry p of ``world`` (position x [m], velocity v [m/s], radius [m])
        with every shape after a step of ``dt`` [s]; its path over the step is x - dt v → x."""
        speed = bounce_speed(world, inputs, dt)
        x0 = x - dt * v
        for s in range(shapes.kind.shape[0]):
            x, v = shape_contact(shapes, s, world, p, x0, x, v, radius, speed, dt)
        return x, v

    return bounce_speed, project_contacts_all


@functools.cache
def project_contacts_func(scalar: type, features: ContactFeatures):
    """Contact response of one particle: against every shape (the fused path) or against the shapes in its
    contact slots (the contact stage), in shape order either way."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    ContactSlots = contact_slots_type(scalar)
    _, shape_contact, _ = shape_funcs(scalar, features)
    bounce_speed, project_contacts_all = project_all_func(scalar, features)

    @wp.func
    def project_contacts(
        world: int, p: int, x: vec3, v: vec3, radius: scalar, dt: scalar, shapes: Shapes, contacts: ContactSlots,
        inputs: wp.array2d[scalar],
    ):
        """Resolve the contacts of state entry p of ``world`` (position x [m], velocity v [m/s], radius [m])
        after a step of ``dt`` [s]."""
        if wp.static(features.buffered):
            speed = bounce_speed(world, inputs, dt)
            x0 = x - dt * v
            for k in range(contacts.count[p]):
                x, v = shape_contact(shapes, contacts.shape[p, k], world, p, x0, x, v, radius, speed, dt)
            return x, v
        return project_contacts_all(world, p, x, v, radius, dt, shapes, inputs)

    return project_contacts


@functools.cache
def collide_kernel(scalar: type, features: ContactFeatures):
    """Kernel filling the contact slots of every dynamic particle of a state from its positions (the shapes'
    frames at the step's end), and with ``features.swept`` from its path over the step, from
    ``particle_q_before`` - dt ``particle_qd`` (the positions before strain limiting, or the state's own) to
    ``particle_q``. Launch over the state's entries."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    ContactSlots = contact_slots_type(scalar)
    shape_distance, _, shape_crossing = shape_funcs(scalar, features)

    @flat_kernel(module="unique", enable_backward=False)
    def collide(
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        particle_q: wp.array[vec3],
        particle_q_before: wp.array[vec3],
        particle_qd: wp.array[vec3],
        dt: scalar,
        contacts: ContactSlots,
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        found = int(0)
        if not is_kinematic(particle_flags[p]):
            x = particle_q[p]
            x0 = particle_q_before[p] - dt * particle_qd[p]  # the response's path start (see the module docstring)
            reach = particle_radius[i] + contacts.margin[0]
            slots = contacts.shape.shape[1]
            for s in range(shapes.kind.shape[0]):
                distance, normal = shape_distance(shapes, s, world, p, x)
                touched = distance < reach
                if wp.static(features.swept):
                    if not touched:
                        crossed, crossed_distance, crossed_normal, entry = shape_crossing(
                            shapes, s, world, p, x0, x, particle_radius[i])
                        touched = crossed
                if touched:
                    if found < slots:
                        contacts.shape[p, found] = s
                        contacts.feature[p, found] = NO_SHAPE
                        found += 1
                    else:
                        wp.atomic_add(contacts.overflow, world, 1)
        contacts.count[p] = found

    return collide


@functools.cache
def project_contacts_kernel(scalar: type, features: ContactFeatures):
    """Kernel applying the contact response to every dynamic particle of a state, in place."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    ContactSlots = contact_slots_type(scalar)
    project_contacts = project_contacts_func(scalar, features)

    @flat_kernel(module="unique", enable_backward=False)
    def project(
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        contacts: ContactSlots,
        inputs: wp.array2d[scalar],
        dt: scalar,
        particle_q_in_out: wp.array[vec3],
        particle_qd_in_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if is_kinematic(particle_flags[p]):
            return
        x, v = project_contacts(world, p, particle_q_in_out[p], particle_qd_in_out[p], particle_radius[i], dt,
                                shapes, contacts, inputs)
        particle_q_in_out[p] = x
        particle_qd_in_out[p] = v

    return project


@wp.func
def rotation_vector_quat(phi: wp.vec3d) -> wp.quatd:
    """The unit quaternion of the rotation vector φ [rad] (axis × angle)."""
    angle = wp.length(phi)
    if angle < wp.float64(1.0e-12):
        return wp.quatd(phi[0] * wp.float64(0.5), phi[1] * wp.float64(0.5), phi[2] * wp.float64(0.5), wp.float64(1.0))
    return wp.quat_from_axis_angle(phi / angle, angle)


@wp.func
def shape_frame(
    tracks: Tracks, rest: wp.transformd, translation: int, rotation: int, t: wp.float64
) -> wp.transformd:
    """A shape's frame at time t: the rest frame turned by R(φ(t)) about its origin and moved by T(t)."""
    position = wp.transform_get_translation(rest)
    orientation = wp.transform_get_rotation(rest)
    if rotation >= 0:
        phi, phi_rate = track_sample(tracks, rotation, t)
        orientation = wp.normalize(rotation_vector_quat(phi) * orientation)
    if translation >= 0:
        offset, offset_rate = track_sample(tracks, translation, t)
        position = position + offset
    return wp.transformd(position, orientation)


@functools.cache
def shape_motion_kernel(scalar: type):
    """Kernel writing every shape's frame at the start t₁ - dt and end t₁ = ``time[world]`` + ``ahead`` [s] of
    a step (each world at its own time). Launch over [world_count, shape_count]; shapes without tracks keep
    their rest frame."""
    vec3 = vec3_type(scalar)
    transform = transform_type(scalar)
    quat = wp.types.quaternion(dtype=scalar)
    Shapes = shapes_type(scalar)

    @wp.func
    def rounded(X: wp.transformd) -> transform:
        return transform(vec3(wp.transform_get_translation(X)), quat(wp.transform_get_rotation(X)))

    @flat_kernel(module="unique", enable_backward=False)
    def shape_motion(
        rest: wp.array[wp.transformd],
        translation_track: wp.array[wp.int32],
        rotation_track: wp.array[wp.int32],
        tracks: Tracks,
        time: wp.array[wp.float64],
        dt: wp.float64,
        ahead: wp.float64,
        shapes: Shapes,
    ):
        world, s = wp.tid()
        t1 = time[world] + ahead
        X0 = shape_frame(tracks, rest[s], translation_track[s], rotation_track[s], t1 - dt)
        X1 = shape_frame(tracks, rest[s], translation_track[s], rotation_track[s], t1)
        shapes.transform_start[world, s] = rounded(X0)
        shapes.transform_end[world, s] = rounded(X1)

    return shape_motion
