"""Kinematic particles: particles whose motion is prescribed, not integrated.

A particle is kinematic when its ``particle_flags`` entry has ``PARTICLE_KINEMATIC`` set; its mass stays
known (``particle_mass``, ``particle_inv_mass``), but no force moves it: every integrator gives it zero
acceleration (:func:`effective_inv_mass`), so on its own it moves on with its velocity (a fixed pin, or
one launched with a velocity, x₀ + u t).

A kinematic particle may belong to a *pin group* whose motion is driven:

* by keyframe tracks (``tracks.py``) of a rigid motion about the group's pivot p: a translation T(t) [m]
  and a rotation given as a rotation vector φ(t) [rad] (axis × angle), so a particle that started at x₀
  is at  x(t) = p + T(t) + R(φ(t)) (x₀ - p)  with velocity  v(t) = Ṫ + ω × R (x₀ - p),  ω = J(φ) φ̇
  (J the left Jacobian of the rotation exponential; ω = φ̇ for a rotation about a fixed axis);
* or by targets set through ``Control``: each particle moves in a straight line from where it is to its
  target, reaching it at the target's time, with the constant velocity that does so, and rests there
  until a new target comes.

``kinematics_kernel`` writes the position and velocity of every kinematic particle at time t + s, for a
state at time t and an offset s: integrators call it for the end of a step and for every stage time,
so a driven pin is exactly on its prescribed motion wherever forces are evaluated.

The flag is a live value: clearing it between frames releases a pin (the integrators move it from then
on, and the kinematics pass skips it); setting it pins a particle, which then moves on with its velocity.
"""

import functools

import warp as wp

from .precision import vec3_type
from .tracks import Tracks, track_sample

wp.set_module_options({"enable_backward": False})

#: Bit of ``particle_flags``: the particle is kinematic (prescribed motion, zero acceleration).
PARTICLE_KINEMATIC = 1
#: ``PinGroups.group`` of a kinematic particle in no driven group: it moves on with its velocity.
NO_GROUP = -1
#: ``PinTargets.time`` before any target was set: the group rests where it is.
NO_TARGET_TIME = -1.0e300
#: A target closer in time than this [s] counts as reached. A state's clock adds up its steps on the
#: device while a target's time is usually computed on the host (frame · frame_dt): the two may differ
#: by a few roundings, and a target 1e-16 s away must not be chased at (distance / 1e-16 s).
TARGET_TIME_TOLERANCE = 1.0e-9


@wp.func
def is_kinematic(flags: wp.int32) -> bool:
    """Whether particle flags mark a kinematic particle."""
    return (flags & PARTICLE_KINEMATIC) != 0


@functools.cache
def particle_funcs(scalar: type):
    """``effective_inv_mass(flags, inv_mass)``: the inverse mass the dynamics sees, 0 for kinematic particles."""

    @wp.func
    def effective_inv_mass(flags: wp.int32, inv_mass: scalar) -> scalar:
        return wp.where(is_kinematic(flags), scalar(0.0), inv_mass)

    return effective_inv_mass


@wp.struct
class PinGroups:
    """The kinematic particles of a model and the driven groups they belong to (float64 geometry)."""

    particle: wp.array[wp.int32]  # shape [kinematic_count], index (within its world) of each kinematic particle
    group: wp.array[wp.int32]  # shape [kinematic_count], its pin group, or NO_GROUP
    rest: wp.array[wp.vec3d]  # [m], shape [kinematic_count], its position at t = 0 (x₀)
    translation_track: wp.array2d[wp.int32]  # shape [rows, group_count], track of T(t) [m], or -1; row
    #   world % rows (one row for all worlds, or one per world)
    rotation_track: wp.array2d[wp.int32]  # shape [rows, group_count], track of φ(t) [rad], or -1; same rows
    pivot: wp.array[wp.vec3d]  # [m], shape [group_count], the pivot p of the group's rotation
    entry: wp.array[wp.int32]  # shape [particle_count], each particle's index in ``particle``, or -1 (not kinematic
    #   at finalize): for a kernel that steps a particle and then puts it on its prescribed motion itself


@wp.struct
class PinTargets:
    """Targets of the pin groups driven through ``Control`` (groups without tracks)."""

    position: wp.array2d[wp.vec3d]  # [m], shape [world_count, kinematic_count], target of each kinematic particle
    time: wp.array2d[wp.float64]  # [s], shape [world_count, group_count], when the group reaches its targets


@wp.func
def rotation_coefficients(theta: wp.float64):
    """sin θ/θ, (1 - cos θ)/θ² and (θ - sin θ)/θ³, by their series below θ = 10⁻² (no cancellation)."""
    if theta < wp.float64(1.0e-2):
        t2 = theta * theta
        a = wp.float64(1.0) - t2 / wp.float64(6.0) + t2 * t2 / wp.float64(120.0)
        b = wp.float64(0.5) - t2 / wp.float64(24.0) + t2 * t2 / wp.float64(720.0)
        c = wp.float64(1.0) / wp.float64(6.0) - t2 / wp.float64(120.0) + t2 * t2 / wp.float64(5040.0)
        return a, b, c
    s = wp.sin(theta)
    t2 = theta * theta
    return s / theta, (wp.float64(1.0) - wp.cos(theta)) / t2, (theta - s) / (t2 * theta)


@wp.func
def rotate_by_vector(phi: wp.vec3d, r: wp.vec3d) -> wp.vec3d:
    """R(φ) r for the rotation vector φ [rad] (Rodrigues: r + a φ×r + b φ×(φ×r))."""
    a, b, c = rotation_coefficients(wp.length(phi))
    phi_r = wp.cross(phi, r)
    return r + a * phi_r + b * wp.cross(phi, phi_r)


@wp.func
def angular_velocity(phi: wp.vec3d, phi_rate: wp.vec3d) -> wp.vec3d:
    """ω [rad/s] of R(φ(t)) in the world frame: J(φ) φ̇ = φ̇ + b φ×φ̇ + c φ×(φ×φ̇)."""
    a, b, c = rotation_coefficients(wp.length(phi))
    cross = wp.cross(phi, phi_rate)
    return phi_rate + b * cross + c * wp.cross(phi, cross)


@functools.cache
def prescribed_func(scalar: type, targets: bool):
    """``prescribed(world, k, q, qd, t_in, s, groups, tracks, pin_targets) -> (x, v)``: the position [m] and velocity
    [m/s] at time t_in + s of kinematic entry k of world ``world`` (``groups.particle[k]``), at ``q``, ``qd`` at
    t_in (``kinematics_kernel``'s rule, for the callers that step particles themselves)."""
    vec3 = vec3_type(scalar)

    @wp.func
    def prescribed(world: int, k: int, q: vec3, qd: vec3, t_in: wp.float64, s: wp.float64, groups: PinGroups,
                   tracks: Tracks, pin_targets: PinTargets):
        g = groups.group[k]
        if g == NO_GROUP:
            # On with its velocity, rounded as the integrators' own updates x + h v round.
            return q + scalar(s) * qd, qd
        x = wp.vec3d(q)
        v = wp.vec3d(wp.float64(0.0))
        translation = groups.translation_track[wp.min(world, groups.translation_track.shape[0] - 1), g]
        rotation = groups.rotation_track[wp.min(world, groups.rotation_track.shape[0] - 1), g]
        if translation >= 0 or rotation >= 0:
            pivot = groups.pivot[g]
            r = groups.rest[k] - pivot
            if rotation >= 0:
                phi, phi_rate = track_sample(tracks, rotation, t_in + s)
                r = rotate_by_vector(phi, r)
                v = wp.cross(angular_velocity(phi, phi_rate), r)
            x = pivot + r
            if translation >= 0:
                offset, offset_rate = track_sample(tracks, translation, t_in + s)
                x = x + offset
                v = v + offset_rate
        elif wp.static(targets):
            # Driven through Control: a straight line to the target, reached at the target's time; at
            # rest where it is before the first target and after the last.
            remaining = pin_targets.time[world, g] - t_in
            if remaining > wp.float64(TARGET_TIME_TOLERANCE):
                target = pin_targets.position[world, k]
                v = (target - x) / remaining
                x = wp.where(s >= remaining - wp.float64(TARGET_TIME_TOLERANCE), target, x + s * v)
        return vec3(x), vec3(v)

    return prescribed


@functools.cache
def kinematics_kernel(scalar: type, targets: bool):
    """Kernel writing the position and velocity of every kinematic particle of every world at time t + s,
    from a state at time t (``time_in[world]``), with s = ``fraction`` · the world's step (``step[world %
    len(step)]``). Launch over [world_count, kinematic_count]. ``targets``: whether groups driven through
    ``Control`` read its targets (otherwise they rest where they are)."""
    vec3 = vec3_type(scalar)
    prescribed = prescribed_func(scalar, targets)

    @wp.kernel(module="unique", enable_backward=False)
    def kinematics(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        groups: PinGroups,
        tracks: Tracks,
        # Control:
        pin_targets: PinTargets,
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        step: wp.array[wp.float64],
        fraction: wp.float64,
        # Out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
    ):
        world, k = wp.tid()
        i = world * particle_count + groups.particle[k]
        if not is_kinematic(particle_flags[i]):
            return  # released since finalize: the integrators move it now
        s = fraction * step[wp.min(world, step.shape[0] - 1)]
        x, v = prescribed(world, k, particle_q_in[i], particle_qd_in[i], time_in[world], s, groups, tracks,
                          pin_targets)
        particle_q_out[i] = x
        particle_qd_out[i] = v

    return kinematics
