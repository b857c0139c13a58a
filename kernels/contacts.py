"""Particle-collider contact: shapes, their motion, the contact buffer and the response.

**Shapes.** Colliders are a struct of arrays (:func:`shapes_type`): kind, size, scale, mesh id,
friction (kinetic and static), restitution, thickness, a mesh's sides, and the shape's frame at the start
and at the end of the current step, [rows, shape_count] with one row for every world (static shapes) or one
per world (animated shapes, each world at its own time). A kernel is specialised for the set of kinds the
scene holds (:class:`ContactFeatures`); a kind adds a signed-distance function here and a branch in
``shape_surface``. A shape's distance is its surface's less its ``thickness``.

**Meshes** (``SHAPE_MESH``, :func:`mesh_funcs`) are ``wp.Mesh`` BVHs in the shape's frame: the closest point
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
    sphere_crossing, box_crossing, capsule_crossing = sweep_funcs(scalar)
    kinds = features.kinds
    zero = scalar(0.0)

    @wp.func
    def shape_surface(shapes: Shapes, s: int, row: int, x: vec3):
        """Signed distance [m] of the world point x from shape s (its frame at the step's end, less the shape's
        thickness), the outward normal and the velocity of a deforming surface [m/s] (world)."""
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
                distance, normal, velocity = mesh_distance(shapes.mesh[s], shapes.sides[s], size[0], size[1],
                                                           shapes.lower[s], shapes.upper[s], p)
        return distance - shapes.thickness[s], wp.transform_vector(X, normal), wp.transform_vector(X, velocity)

    @wp.func
    def shape_distance(shapes: Shapes, s: int, row: int, x: vec3):
        """Signed distance [m] of the world point x from shape s (its frame at the step's end) and the
        outward normal in world coordinates."""
        distance, normal, velocity = shape_surface(shapes, s, row, x)
        return distance, normal

    @wp.func
    def shape_crossing(shapes: Shapes, s: int, row: int, x0: vec3, x: vec3, pad: scalar):
        """Whether the path from x0 (at the step's start, against the shape's start frame) to x (its end frame)
        entered shape s; if so, x's signed distance [m] from the plane of the entered face less the thickness
        (the response's distance), that face's normal on x0's side (world), and the fraction of the step at
        which the path entered. Spheres, boxes and capsules
        are grown by ``pad`` [m] (the particle's radius) and the thickness, so a path that only grazes them
        within the radius is caught too; a mesh is a ray cast against its surface."""
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
                crossed, hit, normal = mesh_crossing(shapes.mesh[s], shapes.sides[s], p0, p1)
        d = p1 - p0
        entry = wp.where(wp.dot(d, d) > zero, wp.clamp(wp.dot(hit - p0, d) / wp.dot(d, d), zero, scalar(1.0)), zero)
        return crossed, wp.dot(p1 - hit, normal) + offset, wp.transform_vector(X1, normal), entry

    @wp.func
    def shape_contact(
        shapes: Shapes, s: int, row: int, x0: vec3, x: vec3, v: vec3, radius: scalar, bounce_speed: scalar,
        dt: scalar,
    ):
        """Resolve the contact of one particle (x [m], v [m/s], radius [m]; at x0 [m] at the step's start) with
        shape s after a step dt [s]. A path that entered the shape where its end is out of reach or on the far
        side (the closest point's normal against the entered face's) is put back on the side it came from; the
        tangential change then moves it only over the part of the step after it touched (so a particle that
        sticks stays where it hit). Any other contact is the closest point's, as without sweeping."""
        distance, normal, surface_velocity = shape_surface(shapes, s, row, x)
        contact_dt = dt
        if wp.static(features.swept):
            crossed, crossed_distance, crossed_normal, entry = shape_crossing(shapes, s, row, x0, x, radius)
            if crossed and (distance >= radius or wp.dot(normal, crossed_normal) < zero):
                distance = crossed_distance
                normal = crossed_normal
                contact_dt = (scalar(1.0) - entry) * dt
        if wp.static(features.moving):
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
        world: int, x: vec3, v: vec3, radius: scalar, dt: scalar, shapes: Shapes, inputs: wp.array2d[scalar]
    ):
        """Resolve the contacts of a particle of ``world`` (position x [m], velocity v [m/s], radius [m])
        with every shape after a step of ``dt`` [s]; its path over the step is x - dt v → x."""
        row = wp.min(world, shapes.transform_end.shape[0] - 1)
        speed = bounce_speed(world, inputs, dt)
        x0 = x - dt * v
        for s in range(shapes.kind.shape[0]):
            x, v = shape_contact(shapes, s, row, x0, x, v, radius, speed, dt)
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
            row = wp.min(world, shapes.transform_end.shape[0] - 1)
            speed = bounce_speed(world, inputs, dt)
            x0 = x - dt * v
            for k in range(contacts.count[p]):
                x, v = shape_contact(shapes, contacts.shape[p, k], row, x0, x, v, radius, speed, dt)
            return x, v
        return project_contacts_all(world, x, v, radius, dt, shapes, inputs)

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
            row = wp.min(world, shapes.transform_end.shape[0] - 1)
            slots = contacts.shape.shape[1]
            for s in range(shapes.kind.shape[0]):
                distance, normal = shape_distance(shapes, s, row, x)
                touched = distance < reach
                if wp.static(features.swept):
                    if not touched:
                        crossed, crossed_distance, crossed_normal, entry = shape_crossing(
                            shapes, s, row, x0, x, particle_radius[i])
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
