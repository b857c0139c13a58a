"""Differentiable steps: the kernels a recorded run (``core/adjoint.py``) launches on a ``wp.Tape``.

They reuse the ordinary force of one particle (``forces.particle_force_func``: gravity, drag, wind and every
element family's gathered hook), so a differentiable run and an ordinary one step the same physics; what differs
is that these kernels are compiled with their adjoints (``enable_backward``), write every step into arrays of its
own (the tape replays them backwards), and meet colliders through a smooth penalty force instead of the
ordinary projection (a projection's gradient is undefined at first touch and zero along the pushed direction).

The smooth contact: a particle of radius r at signed distance d from a collider's surface penetrates by
φ = r + thickness - d; the contact pushes along the surface normal n with

    f_n = k_c · ε · softplus(φ / ε) · n,    softplus(s) = log(1 + exp(s)),

C∞ in the position, equal to the linear penalty k_c φ to within k_c ε e^(-|φ|/ε) away from the surface and
k_c ε log 2 at touch (ε [m]: the smoothing length; k_c [N/m]: the contact stiffness). A damper acts along n
with the same weight, -c_c σ(φ/ε) (v·n) n (σ the logistic function), and friction is smoothed Coulomb:
-μ |f_n| v_t / √(|v_t|² + v_ε²), a viscous law below the speed v_ε [m/s] and Coulomb's above it.

Colliders here are planes and spheres at rest (the analytic shapes the ordinary contacts have; boxes,
capsules, meshes and moving colliders are not differentiable yet). Driven pins move along linear or step
translation tracks whose keys are a differentiable array (``pin_tracks_type``), put on their track at each step's
end by the update kernels themselves (a pass of its own would overwrite the update's output on the tape).
"""

import functools

import warp as wp

from .families import elements
from .forces import ForceFeatures, particle_force_func
from .integrators import verlet_kick_kernel
from .kinematics import particle_funcs
from .precision import vec3_type
from .worlds import world_and_index

#: The smooth contact's live values, columns of the ``contact`` array (one row per world).
CONTACT_STIFFNESS = 0  # k_c [N/m]
CONTACT_SMOOTHING = 1  # ε [m]
CONTACT_DAMPING = 2  # c_c [N·s/m]
CONTACT_FRICTION = 3  # μ [-]
CONTACT_SLIP_SPEED = 4  # v_ε [m/s]
CONTACT_COUNT = 5


def vec4_type(scalar: type) -> type:
    """The 4-vector type of a scalar type (a driven pin's weights)."""
    return wp.vec4d if scalar == wp.float64 else wp.vec4f


def options(deterministic: bool, records: int = 0) -> dict:
    """Module options of these kernels: with ``deterministic``, Warp's run-to-run deterministic atomics (the
    adjoints of a gather add into shared gradient entries: in a fixed order then, at a cost); ``records``: the
    atomic adds one thread may make into one array, where a loop of run-time length hides it from Warp's count."""
    if not deterministic:
        return {"deterministic": wp.DeterministicMode.NOT_GUARANTEED}
    return {"deterministic": wp.DeterministicMode.RUN_TO_RUN, "deterministic_max_records": records}


@functools.cache
def smooth_colliders_type(scalar: type):
    """The static planes and spheres the smooth contact meets (float arrays of the model's precision)."""
    vec3 = vec3_type(scalar)

    @wp.struct
    class SmoothColliders:
        plane_normal: wp.array[vec3]  # [-], [plane_count]: the unit normal, pointing out of the solid
        plane_offset: wp.array[scalar]  # [m], [plane_count]: n·x of the plane's points
        plane_thickness: wp.array[scalar]  # [m], [plane_count]
        sphere_center: wp.array[vec3]  # [m], [sphere_count]
        sphere_radius: wp.array[scalar]  # [m], [sphere_count] (radius plus the shape's thickness)

    return SmoothColliders


@functools.cache
def smooth_contact_func(scalar: type, planes: bool, spheres: bool):
    """``contact_force(world, x, v, radius, colliders, contact) -> vec3``: the smooth contact force [N] of every
    collider on a particle at x [m] with velocity v [m/s] (the module docstring's law)."""
    vec3 = vec3_type(scalar)
    Colliders = smooth_colliders_type(scalar)

    @wp.func
    def softplus(s: scalar) -> scalar:
        # log(1 + e^s) without overflow: max(s, 0) + log(1 + e^-|s|)
        return wp.max(s, scalar(0.0)) + wp.log(scalar(1.0) + wp.exp(-wp.abs(s)))

    @wp.func
    def surface_force(x: vec3, v: vec3, n: vec3, phi: scalar, world: int, contact: wp.array2d[scalar]) -> vec3:
        row = wp.min(world, contact.shape[0] - 1)
        eps = contact[row, CONTACT_SMOOTHING]
        s = phi / eps
        fn = contact[row, CONTACT_STIFFNESS] * eps * softplus(s)
        weight = scalar(1.0) / (scalar(1.0) + wp.exp(-s))
        vn = wp.dot(v, n)
        vt = v - vn * n
        slip = wp.sqrt(wp.dot(vt, vt) + contact[row, CONTACT_SLIP_SPEED] * contact[row, CONTACT_SLIP_SPEED])
        return (fn - contact[row, CONTACT_DAMPING] * weight * vn) * n - (contact[row, CONTACT_FRICTION] * fn / slip) * vt

    @wp.func
    def contact_force(world: int, x: vec3, v: vec3, radius: scalar, colliders: Colliders,
                      contact: wp.array2d[scalar]) -> vec3:
        f = vec3(scalar(0.0))
        if wp.static(planes):
            for k in range(colliders.plane_offset.shape[0]):
                n = colliders.plane_normal[k]
                phi = radius + colliders.plane_thickness[k] - (wp.dot(n, x) - colliders.plane_offset[k])
                f += surface_force(x, v, n, phi, world, contact)
        if wp.static(spheres):
            for k in range(colliders.sphere_radius.shape[0]):
                d = x - colliders.sphere_center[k]
                length = wp.sqrt(wp.dot(d, d) + scalar(1.0e-24))  # (a particle at the centre: n = 0, no NaN)
                n = d / length
                phi = radius + colliders.sphere_radius[k] - length
                f += surface_force(x, v, n, phi, world, contact)
        return f

    return contact_force


@functools.cache
def diff_force_kernel(scalar: type, features: ForceFeatures, planes: bool, spheres: bool, deterministic: bool = False):
    """Kernel writing each particle's total force [N] at (x, v): the ordinary particle force plus the smooth
    contact, with its adjoint. With ``deterministic``, the adjoint's adds per thread into one array are bounded by
    the incidence: at most 10 particles (a quadratic tet) and their values per slot of every family's head (a head
    wider than Warp's unrolling, 16 slots, is a loop Warp does not count), and a margin for the colliders' loops."""
    vec3 = vec3_type(scalar)
    particle_force = particle_force_func(scalar, features)
    Elements = elements(scalar, features.families).arrays
    Colliders = smooth_colliders_type(scalar)
    contact_force = smooth_contact_func(scalar, planes, spheres)
    touching = planes or spheres
    records = 10 * sum(spec.incidence.head_slots for spec in features.families) + 64

    @wp.kernel(module="unique", enable_backward=True, module_options=options(deterministic, records))
    def diff_forces(
        # Model:
        particle_count: int,
        particle_mass: wp.array2d[scalar],
        particle_radius: wp.array[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        colliders: Colliders,
        contact: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Out:
        particle_f_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        x = particle_q[p]
        v = particle_qd[p]
        f = particle_force(world, i, p - i, x, v, particle_mass, element_arrays, inputs, particle_force_ext,
                           particle_q, particle_qd)
        if wp.static(touching):
            f += contact_force(world, x, v, particle_radius[i], colliders, contact)
        particle_f_out[p] = f

    return diff_forces


@functools.cache
def pin_tracks_type(scalar: type):
    """Driven pins of a differentiable run: each pin's translation at each step's time as a mix of two keys of its
    track, x = x₀ + w_a K_a + w_b K_b and v = r_a K_a + r_b K_b (linear and step tracks, hold and cycle: the host
    finds each step's keys and weights; the keys K [m] themselves are a differentiable array, a row per world)."""
    vec3 = vec3_type(scalar)
    vec4 = vec4_type(scalar)

    @wp.struct
    class PinTracks:
        particle_pin: wp.array[wp.int32]  # [particle_count]: the driven pin a particle (of a world) is, or -1
        pin_group: wp.array[wp.int32]  # [pin_count]: its pin group
        pin_rest: wp.array[vec3]  # [m], [pin_count]: its position at t = 0 (x₀)
        key: wp.array3d[wp.vec2i]  # [steps + 1, rows, group_count]: columns a, b of the keys a group's translation
        #   mixes at step k's time; row world % rows (one row for all worlds, or one per world)
        weight: wp.array3d[vec4]  # [-, -, 1/s, 1/s], same shape: (w_a, w_b, r_a, r_b)

    return PinTracks


@functools.cache
def pin_motion_func(scalar: type):
    """``pin_motion(world, pin, step, pins, keys) -> (x, v)``: a driven pin's position [m] and velocity [m/s] at
    step ``step``'s time (``pin_tracks_type``)."""
    PinTracks = pin_tracks_type(scalar)
    vec3 = vec3_type(scalar)

    @wp.func
    def pin_motion(world: int, pin: int, step: int, pins: PinTracks, keys: wp.array2d[vec3]):
        g = pins.pin_group[pin]
        row = wp.min(world, pins.key.shape[1] - 1)
        ab = pins.key[step, row, g]
        c = pins.weight[step, row, g]
        key_row = wp.min(world, keys.shape[0] - 1)
        ka = keys[key_row, ab[0]]
        kb = keys[key_row, ab[1]]
        return pins.pin_rest[pin] + c[0] * ka + c[1] * kb, c[2] * ka + c[3] * kb

    return pin_motion


@functools.cache
def diff_update_kernels(scalar: type, deterministic: bool = False, pins: bool = False):
    """(update, kick): symplectic Euler's update and velocity Verlet's drift, and Verlet's kick, from precomputed
    forces, with adjoints.

    ``update``: v' = v + share h M⁻¹ f, x' = x + h v', with ``share`` 1 for symplectic Euler's update and ½ for
    Verlet's drift (v' is then v½). ``kick``: v' = v½ + ½h M⁻¹ f. Kinematic particles have M⁻¹ = 0 (they keep their
    velocity); with ``pins``, a driven pin is put on its track at the step's end instead (``pin_motion_func``; its
    velocity there standing in for v½, and the kick then keeps it), as the ordinary integrators' kinematics pass
    puts it."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)
    PinTracks = pin_tracks_type(scalar)
    pin_motion = pin_motion_func(scalar)

    @wp.kernel(module="unique", enable_backward=True, module_options=options(deterministic))
    def update(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        # Control (the driven pins, read with ``pins``; ``step``: the step whose end this update reaches):
        pin_tracks: PinTracks,
        pin_keys: wp.array2d[vec3],
        step: int,
        # State in (``share``: the step's share the velocity takes, 1 or ½):
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        particle_f: wp.array[vec3],
        dt: scalar,
        share: scalar,
        # Out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        w = effective_inv_mass(particle_flags[p], particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i])
        v = particle_qd_in[p] + (share * dt * w) * particle_f[p]
        x = particle_q_in[p] + dt * v
        if wp.static(pins):
            pin = pin_tracks.particle_pin[i]
            if pin >= 0:
                x, v = pin_motion(world, pin, step, pin_tracks, pin_keys)
        particle_qd_out[p] = v
        particle_q_out[p] = x

    return update, kick_kernel(scalar, deterministic)


def kick_kernel(scalar: type, deterministic: bool = False):
    """Velocity Verlet's kick v' = v½ + ½h M⁻¹ f, with its adjoint (``diff_update_kernels``): the integrator's own
    kick compiled with its backward pass and these kernels' module options."""
    return verlet_kick_kernel(scalar, True, tuple(options(deterministic).items()))


@functools.cache
def loss_kernel(scalar: type, deterministic: bool = False, particle_count: int = 0):
    """Kernel writing each world's weighted squared distance [m²] of its particles from targets into row ``row`` of
    ``loss_out``: one thread per world sums its particles in order (no float atomics, the same bits every run).
    With ``deterministic``, ``particle_count`` bounds the adjoint's adds per thread (one per particle)."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=True, module_options=options(deterministic, particle_count))
    def position_loss(
        # Model:
        particle_count: int,
        # State in:
        particle_q: wp.array[vec3],
        # Control (targets [m] and weights [-], [world_count · particle_count]; a weight of 0 skips a particle):
        target: wp.array[vec3],
        weight: wp.array[scalar],
        row: int,
        # Out (row ``row`` of [rows, world_count]):
        loss_out: wp.array2d[scalar],
    ):
        world = wp.tid()
        total = scalar(0.0)
        for i in range(particle_count):
            p = world * particle_count + i
            d = particle_q[p] - target[p]
            total += weight[p] * wp.dot(d, d)
        loss_out[row, world] = total

    return position_loss
