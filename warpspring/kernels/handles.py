"""PD-controlled handles: virtual springs and dampers that drag grabbed particles toward moving targets,
plugged into every kernel through the hooks of ``families.py``.

A handle grabs particles and carries a target frame: a translation T(t) [m] and a rotation vector φ(t) [rad]
about its pivot p (keyframe tracks, as pin groups have), so a particle grabbed at x₀ is pulled toward

    x*(t) = p + T(t) + R(φ(t)) (x₀ − p),   moving at   v*(t) = Ṫ + ω × R(φ)(x₀ − p)

by the control force u = Kp e + Kd ė with e = x* − x and ė = v* − v (per-handle gains Kp [N/m] and
Kd [N·s/m]), its magnitude capped at the handle's ``max_force`` [N] where a cap is compiled in. The element
is a grab (one particle of one handle); a particle may be in several handles.

The target frames depend on time, which the family hooks do not see: ``handle_frames_kernel`` writes each
world's frame of every handle with tracks (T, Ṫ, φ, ω) at the state's time before the forces are evaluated
(the host calls it wherever animated inputs are evaluated, ``core/tracks.evaluate_input_tracks``), and the
force hook reads them. A handle without a translation track is moved from the host between frames instead
(``HandleFamily.set_target``: a user dragging cloth interactively), its T and Ṫ live device values. Stiffness and damping matrices are exact for the uncapped law: K = Kp I and D = Kd I on
the grabbed particle. A handle does work (its target moves), so the family has no energy.
"""

import functools
from dataclasses import dataclass

import warp as wp

from .families import FamilyFuncs, Incidence, IncidenceShape, gathered_force, gathered_product, no_strain_func
from .kinematics import angular_velocity, rotate_by_vector
from .precision import mat33_type, vec3_type
from .tracks import Tracks, track_sample

wp.set_module_options({"enable_backward": False})


@functools.cache
def handle_arrays_type(scalar: type):
    """The struct of the handle family's arrays in one precision."""

    @wp.struct
    class HandleArrays:
        handle: wp.array[wp.int32]  # [grab_count]: the handle of each grab
        rest: wp.array[wp.vec3d]  # [m], [grab_count]: the grabbed particle's position at t = 0 (x₀)
        pivot: wp.array[wp.vec3d]  # [m], [handle_count]: p
        kp: wp.array2d[scalar]  # Kp [N/m], [1 or world_count, handle_count]
        kd: wp.array2d[scalar]  # Kd [N·s/m], [1 or world_count, handle_count]
        max_force: wp.array2d[scalar]  # [N], [1 or world_count, handle_count] (read where a cap is compiled in)
        translation: wp.array2d[wp.vec3d]  # T(t) [m], [world_count, handle_count], at the state's time
        velocity: wp.array2d[wp.vec3d]  # Ṫ(t) [m/s], same shape
        rotation: wp.array2d[wp.vec3d]  # φ(t) [rad], same shape
        angular: wp.array2d[wp.vec3d]  # ω(t) [rad/s], same shape
        incidence: Incidence  # entries (grab, 0); padding (0, -1)

    return HandleArrays


@dataclass(frozen=True)
class HandleSpec:
    """Compile-time switches of the handle family: its incidence table's shape, whether any handle rotates,
    and whether forces are capped."""

    incidence: IncidenceShape
    rotation: bool
    cap: bool

    def funcs(self, scalar: type) -> FamilyFuncs:
        return handle_family_funcs(scalar, self)


@wp.kernel(enable_backward=False)
def handle_frames_kernel(
    # Model:
    translation_track: wp.array[wp.int32],  # [handle_count], track of T(t), or -1
    rotation_track: wp.array[wp.int32],  # [handle_count], track of φ(t), or -1
    tracks: Tracks,
    # State in:
    time: wp.array[wp.float64],  # [world_count]
    # Out:
    translation_out: wp.array2d[wp.vec3d],
    velocity_out: wp.array2d[wp.vec3d],
    rotation_out: wp.array2d[wp.vec3d],
    angular_out: wp.array2d[wp.vec3d],
):
    """Every handle's target frame in every world at that world's time; launch over [world_count, handles]."""
    world, h = wp.tid()
    t = time[world]
    if translation_track[h] >= 0:  # (a part without a track keeps what the host set: HandleFamily.set_target)
        value, rate = track_sample(tracks, translation_track[h], t)
        translation_out[world, h] = value
        velocity_out[world, h] = rate
    if rotation_track[h] >= 0:
        phi, phi_rate = track_sample(tracks, rotation_track[h], t)
        rotation_out[world, h] = phi
        angular_out[world, h] = angular_velocity(phi, phi_rate)


@functools.cache
def handle_funcs(scalar: type):
    """``pd_force(x, v, target, target_velocity, kp, kd) -> vec3``: the control force Kp e + Kd ė [N]."""
    vec3 = vec3_type(scalar)

    @wp.func
    def pd_force(x: vec3, v: vec3, target: vec3, target_velocity: vec3, kp: scalar, kd: scalar) -> vec3:
        return kp * (target - x) + kd * (target_velocity - v)

    @wp.func
    def capped(u: vec3, limit: scalar) -> vec3:
        """``u`` with its magnitude at most ``limit`` [N]."""
        magnitude = wp.length(u)
        if magnitude > limit and magnitude > scalar(0.0):
            return u * (limit / magnitude)
        return u

    return pd_force, capped


@functools.cache
def handle_family_funcs(scalar: type, spec: HandleSpec) -> FamilyFuncs:
    """The family hooks of PD handles (``families.py``) for one precision and spec."""
    vec3 = vec3_type(scalar)
    mat33 = mat33_type(scalar)
    HandleArrays = handle_arrays_type(scalar)
    pd_force, capped = handle_funcs(scalar)

    @wp.func
    def grab_force(
        world: int, g: int, local: int, i: int, base: int, xi: vec3, vi: vec3, handles: HandleArrays,
        inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3],
    ) -> vec3:
        """The force [N] of grab g on its particle i at xi moving at vi (0 for a padding entry)."""
        if local < 0:
            return vec3(scalar(0.0))
        h = handles.handle[g]
        pivot = handles.pivot[h]
        r = handles.rest[g] - pivot
        target_velocity = handles.velocity[world, h]
        if wp.static(spec.rotation):
            r = rotate_by_vector(handles.rotation[world, h], r)
            target_velocity += wp.cross(handles.angular[world, h], r)
        target = pivot + handles.translation[world, h] + r
        u = pd_force(xi, vi, vec3(target), vec3(target_velocity),
                     handles.kp[wp.min(world, handles.kp.shape[0] - 1), h],
                     handles.kd[wp.min(world, handles.kd.shape[0] - 1), h])
        if wp.static(spec.cap):
            u = capped(u, handles.max_force[wp.min(world, handles.max_force.shape[0] - 1), h])
        return u

    @wp.func
    def product_entry(
        world: int, g: int, local: int, i: int, base: int, handles: HandleArrays, inputs: wp.array2d[scalar],
        particle_q: wp.array[vec3], particle_flags: wp.array[wp.int32], x: wp.array[vec3], free_only: bool,
        alpha: scalar, beta: scalar,
    ):
        """(α Kp + β Kd) x_i and the diagonal block (α Kp + β Kd) I of grab g (0 for a padding entry)."""
        if local < 0:
            return vec3(scalar(0.0)), mat33(scalar(0.0))
        h = handles.handle[g]
        k = alpha * handles.kp[wp.min(world, handles.kp.shape[0] - 1), h] + beta * handles.kd[
            wp.min(world, handles.kd.shape[0] - 1), h]
        return k * x[base + i], k * wp.identity(n=3, dtype=scalar)

    force = gathered_force(scalar, HandleArrays, spec.incidence, grab_force)
    product = gathered_product(scalar, HandleArrays, spec.incidence, product_entry)

    strain = no_strain_func(scalar, HandleArrays)  # no strain for the guards

    @wp.func
    def energy(world: int, g: int, base: int, handles: HandleArrays, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3]) -> scalar:
        """A handle does work (its target moves): no energy."""
        return scalar(0.0)

    return FamilyFuncs(HandleArrays, force, product, strain, energy, spec.incidence.idle())
