"""Per-particle update kernels of the integrators.

Symplectic Euler with gathered springs is one fused kernel per substep: each thread gathers its
particle's forces, updates velocity then position, and resolves the particle's contacts, reading
``state_in`` and writing ``state_out`` (so no thread sees another's update). With scattered springs the
forces come precomputed and only the update runs here.

Explicit Runge-Kutta methods share one combination kernel, y = y₀ + Σⱼ wⱼ kⱼ over stage derivatives
kⱼ = (vⱼ, M⁻¹ fⱼ); velocity Verlet has its drift and kick kernels. Kinematic particles (their flag
set, ``kinematics.py``) feel no force anywhere: they move on with their velocity, and a driven pin is
then put on its prescribed motion by the kinematics pass.

Every kernel that writes a step's (or a stage's) state also writes its time, t_out = t_in + h (or the
stage's t_in + c h), from its first thread: the states carry their time on the device, for keyframe
tracks and driven pins, at no extra launch. Those kernels take the step as two numbers of the model's
precision, the rounded step h the physics uses and what the rounding dropped (``step_arguments``), whose
float64 sum keeps a float32 model's clock exact (the rounded step alone would put it ~1e-7 s off per
thousand steps). A float64 argument would do the same but slows the fused kernel by 9-27 % on an H100
(bench/RESULTS.md §7).
"""

import functools

import warp as wp

from .families import FORCE_KERNEL_OPTIONS, elements
from .forces import ForceFeatures, counts_work, particle_force_func, particle_power_func, power_sums_funcs
from .kinematics import is_kinematic, particle_funcs
from .linalg import reduction_funcs, warp_total_func
from .precision import vec3_type
from .response import project_all_func
from .shapes import ContactFeatures, shapes_type
from .worlds import world_and_index
from .flatten import flat_kernel, launch_bounds_option

wp.set_module_options({"enable_backward": False})


@functools.cache
def symplectic_euler_funcs(scalar: type):
    """The symplectic Euler update of one particle."""
    vec3 = vec3_type(scalar)

    @wp.func
    def symplectic_euler_update(x: vec3, v: vec3, f: vec3, inv_mass: scalar, dt: scalar):
        """v' = v + h f / m, x' = x + h v' for position x [m], velocity v [m/s], force f [N]."""
        v_new = v + (dt * inv_mass) * f
        return x + dt * v_new, v_new

    return symplectic_euler_update


@functools.cache
def symplectic_euler_update_kernel(scalar: type, contacts: ContactFeatures, power: bool = False, work: bool = False):
    """Symplectic Euler + contact kernel from precomputed forces (the scatter path); ``contacts`` fused
    (static colliders, every one tested). With ``power`` each free particle adds to its entry of the guard's power
    sums -h f_d·(v + v')/2 and h f_w·(v + v')/2 from the dampers' and the outside loads' parts of its force, which the
    force passes wrote (``symplectic_euler_kernel``'s rule); ``work``: the sums carry the work
    (``forces.power_sums_funcs``)."""
    vec3 = vec3_type(scalar)
    sums = power_sums_funcs(scalar, work)
    Sums = sums.type
    pack = sums.pack
    Shapes = shapes_type(scalar)
    update = symplectic_euler_funcs(scalar)
    effective_inv_mass = particle_funcs(scalar)
    _, project_contacts = project_all_func(scalar, contacts)
    has_contacts = bool(contacts)

    @flat_kernel(module="unique", enable_backward=False, last=contacts.idle())
    def symplectic_euler_from_forces(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        particle_f_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        dt: scalar,
        dt_rest: scalar,
        # Guard in (the dampers' and the outside loads' parts of the force [N], read with ``power`` only):
        particle_fd: wp.array[vec3],
        particle_fw: wp.array[vec3],
        # State out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
        # In/out (the guard's power sums [J], read with ``power`` only):
        power_in_out: wp.array[Sums],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if i == 0:
            time_out[world] = time_in[world] + (wp.float64(dt) + wp.float64(dt_rest))
        h = dt
        flags = particle_flags[p]
        inv_mass = particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i]
        v_start = particle_qd_in[p]
        x, v = update(particle_q_in[p], v_start, particle_f_in[p], effective_inv_mass(flags, inv_mass), h)
        if wp.static(power):  # (a kinematic particle's stored parts: its elements' dampers only)
            mean = (v_start + v) * (scalar(0.5) * h)
            worked = scalar(0.0)
            if wp.static(work):
                worked = wp.dot(particle_fw[p], mean)
            power_in_out[p] += pack(-wp.dot(particle_fd[p], mean), worked)
        if wp.static(has_contacts):
            if not is_kinematic(flags):
                x, v = project_contacts(world, p, x, v, particle_radius[i], h, shapes, inputs)
        particle_q_out[p] = x
        particle_qd_out[p] = v

    return symplectic_euler_from_forces


@functools.cache
def symplectic_euler_particle_energy_func(scalar: type, features: ForceFeatures, contacts: ContactFeatures,
                                          power: tuple):
    """``step_particle(world, i, p, base, ..., q_in, qd_in, h) -> (x', v', taken, worked)``: one particle's fused
    symplectic Euler step (``symplectic_euler_particle_func``) with the energy [J] its dampers and drag took out over
    the step and the work [J] the loads from outside did on it (``symplectic_euler_kernel``'s rule; a kinematic
    particle: its elements' dampers' share, h times their power at the step's start), returned for the caller to sum."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    particle_force = particle_power_func(scalar, features, power)
    Elements = elements(scalar, features.families).arrays
    update = symplectic_euler_funcs(scalar)
    _, project_contacts = project_all_func(scalar, contacts)
    has_contacts = bool(contacts)

    @wp.func
    def step_particle_energy(world: int, i: int, p: int, base: int, particle_flags: wp.array[wp.int32],
                             particle_inv_mass: wp.array2d[scalar], particle_radius: wp.array[scalar], shapes: Shapes,
                             particle_mass: wp.array2d[scalar], element_arrays: Elements, inputs: wp.array2d[scalar],
                             particle_force_ext: wp.array[vec3], q_in: wp.array[vec3], qd_in: wp.array[vec3],
                             h: scalar):
        x = q_in[p]
        v = qd_in[p]
        x_new = x + h * v
        v_new = v
        worked = scalar(0.0)
        # (one gather of the forces for both kinds: a kinematic particle keeps only its elements' dampers' share)
        kinematic = is_kinematic(particle_flags[p])
        f, dampers, work = particle_force(world, i, base, x, v, not kinematic, particle_mass, element_arrays, inputs,
                                          particle_force_ext, q_in, qd_in)
        taken = -h * wp.dot(dampers, v)  # a kinematic particle: its elements' dampers (the drive's work has the rest)
        if not kinematic:
            inv_mass = particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i]
            x_new, v_new = update(x, v, f, inv_mass, h)
            mean = (v + v_new) * (scalar(0.5) * h)
            taken = -wp.dot(dampers, mean)
            worked = wp.dot(work, mean)
            if wp.static(has_contacts):
                x_new, v_new = project_contacts(world, p, x_new, v_new, particle_radius[i], h, shapes, inputs)
        return x_new, v_new, taken, worked

    return step_particle_energy


@functools.cache
def symplectic_euler_particle_func(scalar: type, features: ForceFeatures, contacts: ContactFeatures,
                                   power: tuple | None = None, warp_totals: bool = False):
    """``step_particle(world, i, p, base, ..., q_in, qd_in, h, power_in_out) -> (x', v')``: one particle's fused
    symplectic Euler step (forces gathered, velocity then position, contacts), the one body of the per-substep kernel
    (``symplectic_euler_kernel``) and of the one-launch frame (``kernels/frames.py``). A kinematic particle moves on
    with its velocity. With ``power`` the particle's share of the guard's power sums (``symplectic_euler_kernel``'s
    rule) is added to its entry, or with ``warp_totals`` on CUDA, where its warp's lanes step particles of one world,
    the warp's total to its first lane's entry (``linalg.warp_total``; ``p`` the launch's thread)."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    counted = power is not None
    sums = power_sums_funcs(scalar, counted and counts_work(features, power))
    Sums = sums.type
    pack = sums.pack
    particle_force = (particle_power_func(scalar, features, power) if counted
                      else particle_force_func(scalar, features))
    Elements = elements(scalar, features.families).arrays
    update = symplectic_euler_funcs(scalar)
    _, project_contacts = project_all_func(scalar, contacts)
    has_contacts = bool(contacts)
    warp_total = warp_total_func(scalar)
    worked_too = counted and counts_work(features, power)

    @wp.func
    def step_particle(world: int, i: int, p: int, base: int, particle_flags: wp.array[wp.int32],
                      particle_inv_mass: wp.array2d[scalar], particle_radius: wp.array[scalar], shapes: Shapes,
                      particle_mass: wp.array2d[scalar], element_arrays: Elements, inputs: wp.array2d[scalar],
                      particle_force_ext: wp.array[vec3], q_in: wp.array[vec3], qd_in: wp.array[vec3], h: scalar,
                      power_in_out: wp.array[Sums]):
        x = q_in[p]
        v = qd_in[p]
        x_new = x + h * v
        v_new = v
        taken = scalar(0.0)  # (with warp_totals: the particle's share, added by its warp below)
        worked = scalar(0.0)
        if is_kinematic(particle_flags[p]):
            if wp.static(counted):  # its elements' dampers: their share of the dampers' power (the drive's work has
                # the rest)
                _, dampers, _ = particle_force(world, i, base, x, v, False, particle_mass, element_arrays, inputs,
                                               particle_force_ext, q_in, qd_in)
                taken = -h * wp.dot(dampers, v)
                if wp.static(not warp_totals):
                    power_in_out[p] += pack(taken, scalar(0.0))
        else:
            inv_mass = particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i]
            if wp.static(counted):
                f, dampers, work = particle_force(world, i, base, x, v, True, particle_mass, element_arrays, inputs,
                                                  particle_force_ext, q_in, qd_in)
                x_new, v_new = update(x, v, f, inv_mass, h)
                mean = (v + v_new) * (scalar(0.5) * h)
                taken = -wp.dot(dampers, mean)
                worked = wp.dot(work, mean)
                if wp.static(not warp_totals):
                    power_in_out[p] += pack(taken, worked)
            else:
                f = particle_force(world, i, base, x, v, particle_mass, element_arrays, inputs, particle_force_ext,
                                   q_in, qd_in)
                x_new, v_new = update(x, v, f, inv_mass, h)
            if wp.static(has_contacts):
                x_new, v_new = project_contacts(world, p, x_new, v_new, particle_radius[i], h, shapes, inputs)
        if wp.static(counted and warp_totals):  # (every lane, the branches rejoined)
            taken = warp_total(taken, world)
            if wp.static(worked_too):
                worked = warp_total(worked, world)
            if taken != scalar(0.0) or worked != scalar(0.0):  # (adding zero changes no entry: its read skipped)
                power_in_out[p] += pack(taken, worked)
        return x_new, v_new

    return step_particle


@functools.cache
def symplectic_euler_kernel(scalar: type, features: ForceFeatures, contacts: ContactFeatures,
                            power: tuple | None = None, bounds: tuple[int, int] | None = None,
                            warp_totals: bool = False):
    """Fused force + symplectic Euler + contact kernel: v' = v + h M⁻¹ f(x, v); x' = x + h v'; ``contacts``
    fused (static colliders, every one tested).

    With ``power`` (one ``forces.POWER_*`` mode per family of ``features``) each free particle also adds to its own
    entry of the guard's power sums (``core/forces.PowerSums``) the energy [J] its dampers and drag took out over
    the step, -h f_d·(v + v')/2, and the work the loads from outside did on it, h f_w·(v + v')/2 (f_d, f_w: their
    parts of f, ``forces.particle_power_func``; v' before the contacts). That is exactly what they changed its
    kinetic energy by, ½ m (|v'|² - |v|²) = h f·(v + v')/2, so the guard's balance closes up to the integrator's
    error in the elastic energy; one thread adds to each entry (Warp's ``+=`` on an array, an atomic add with a single
    writer: the same sum in any order), no pass of its own. With ``warp_totals`` (CUDA) a warp whose lanes step
    particles of one world adds their total (a fixed tree of shuffles) to its first lane's entry alone: one add to an
    entry a warp instead of one a particle (the check sums a world's entries), for a few instructions more in every
    thread (``SymplecticEuler.POWER_WARP_TOTALS_FROM``). A non-finite particle's share then reaches its warp's entry,
    where the check's ``measure`` leaves a non-finite particle's own entry out: its world stops as non-finite at that
    check either way.

    ``bounds`` (threads a block, blocks a multiprocessor): ``flatten.launch_bounds_option``."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    Sums = power_sums_funcs(scalar, power is not None and counts_work(features, power)).type
    composed = elements(scalar, features.families)
    Elements = composed.arrays
    step_particle = symplectic_euler_particle_func(scalar, features, contacts, power, warp_totals)

    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 **launch_bounds_option(bounds),
                 last=contacts.idle() + composed.last("element_arrays"))
    def symplectic_euler(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        # Model, the forces:
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        dt: scalar,
        dt_rest: scalar,
        # State out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
        # In/out (the guard's power sums [J], read with ``power`` only):
        power_in_out: wp.array[Sums],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if i == 0:
            time_out[world] = time_in[world] + (wp.float64(dt) + wp.float64(dt_rest))
        x, v = step_particle(world, i, p, p - i, particle_flags, particle_inv_mass, particle_radius, shapes,
                             particle_mass, element_arrays, inputs, particle_force_ext, particle_q_in, particle_qd_in,
                             dt, power_in_out)
        particle_q_out[p] = x
        particle_qd_out[p] = v

    return symplectic_euler


@functools.cache
def symplectic_euler_blocks_kernel(scalar: type, features: ForceFeatures, contacts: ContactFeatures, power: tuple,
                                   tiled: bool = True):
    """``symplectic_euler_kernel`` with the guard's power summed per block instead of per particle: launched over
    ``linalg.reduce_launch_dim(world_count, particle_count, lanes)`` with ``block_dim`` = lanes, thread (w, b, l) steps
    particle b·lanes + l of world w (if there is one), the block's lanes sum what their particles' dampers and drag
    took out and what the loads from outside put in (``block_sum``: a fixed-order tree, float64) and lane 0 adds the
    two to ``running[w, b]`` (``RUNNING_STEP_DISSIPATION``, ``RUNNING_WORK`` of ``kernels/guards.py``): no read and
    write of a per-particle sum every substep (+14-16 % of the step on an H200 at 1024², bench/results/guard_cost.md),
    no float atomics. On the CPU (``tiled`` off, a test's configuration) a block is one thread."""
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    composed = elements(scalar, features.families)
    Elements = composed.arrays
    step_energy = symplectic_euler_particle_energy_func(scalar, features, contacts, power)
    block_sum, _ = reduction_funcs(tiled)
    work = counts_work(features, power)

    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 last=contacts.idle() + composed.last("element_arrays"))
    def symplectic_euler_blocks(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        particle_radius: wp.array[scalar],
        shapes: Shapes,
        # Model, the forces:
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        dt: scalar,
        dt_rest: scalar,
        # Guard in (the slots of ``running`` the step adds to):
        taken_slot: int,
        worked_slot: int,
        # State out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
        # In/out (the guard's running sums per block [J]):
        running_in_out: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        i = block * wp.block_dim() + lane
        taken = wp.float64(0.0)
        worked = wp.float64(0.0)
        if i < particle_count:
            p = world * particle_count + i
            if i == 0:
                time_out[world] = time_in[world] + (wp.float64(dt) + wp.float64(dt_rest))
            x, v, t, w = step_energy(world, i, p, p - i, particle_flags, particle_inv_mass, particle_radius, shapes,
                                     particle_mass, element_arrays, inputs, particle_force_ext, particle_q_in,
                                     particle_qd_in, dt)
            particle_q_out[p] = x
            particle_qd_out[p] = v
            taken = wp.float64(t)
            worked = wp.float64(w)
        taken = block_sum(taken)
        if wp.static(work):
            worked = block_sum(worked)
        if lane == 0:
            running_in_out[world, block, taken_slot] += taken
            if wp.static(work):
                running_in_out[world, block, worked_slot] += worked

    return symplectic_euler_blocks


@functools.cache
def rk_combine_kernel(scalar: type, with_first: bool, terms: int):
    """Runge-Kutta combination y = y₀ + w₀ k₀ + Σⱼ wⱼ kⱼ for one particle per thread.

    Stage 0's derivative is (v₀, M⁻¹ f₀): its velocity is the input velocity itself, its force a separate
    array; ``with_first`` says whether it contributes. ``terms`` later stages follow as rows of 2-D
    arrays of stage velocities and forces, weighted by a vector of ``terms`` weights. Every weight is
    multiplied by the world's step, ``step[world % len(step)]``: fixed-step methods pass h·aᵢⱼ with one
    step of 1 for all worlds, adaptive ones pass aᵢⱼ and each world's current step, which lives on the
    device. The result's time is t₀ + ``time_weight``·step (the stage's c h, or h for the step).
    """
    vec3 = vec3_type(scalar)
    weights_type = wp.types.vector(length=max(terms, 1), dtype=scalar)
    effective_inv_mass = particle_funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def rk_combine(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        first_f: wp.array[vec3],
        stage_qd: wp.array2d[vec3],
        stage_f: wp.array2d[vec3],
        first_weight: scalar,
        weights: weights_type,
        time_weight: wp.float64,
        step: wp.array[wp.float64],
        # Out:
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        h64 = step[wp.min(world, step.shape[0] - 1)]
        if i == 0:
            time_out[world] = time_in[world] + time_weight * h64
        h = scalar(h64)
        inv_mass = effective_inv_mass(particle_flags[p], particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i])
        v0 = particle_qd_in[p]
        x = particle_q_in[p]
        v = v0
        if wp.static(with_first):
            x += (h * first_weight) * v0
            v += (h * first_weight * inv_mass) * first_f[p]
        for j in range(wp.static(terms)):
            w = h * weights[j]
            x += w * stage_qd[j, p]
            v += (w * inv_mass) * stage_f[j, p]
        particle_q_out[p] = x
        particle_qd_out[p] = v

    return rk_combine


# Slots of the step-control arrays (float64 control, int32 counters) and the controller's constants. The
# tolerance and the attempt budget are live settings: the kernels read them from the control array.
STEP_INTERVAL, STEP_TIME, STEP_SIZE, STEP_PROPOSED, STEP_GROWTH, STEP_ERROR, STEP_TOLERANCE, STEP_MAX_ATTEMPTS = range(8)
STEP_CONTROL_SLOTS = 8
STEP_ACCEPTED, STEP_REJECTED, STEP_ATTEMPTS_NOW, STEP_LAST_ACCEPTED, STEP_FAILED, STEP_RUNNING = range(6)
STEP_COUNTERS = 6
STEP_SAFETY, STEP_MAX_GROWTH, STEP_MIN_GROWTH = 0.9, 5.0, 0.2


@functools.cache
def rk_error_kernel(scalar: type, stages: int, tiled: bool):
    """Scaled local error of an embedded Runge-Kutta pair, max-reduced per world.

    The error estimate is e = h Σⱼ eⱼ kⱼ (eⱼ = bⱼ - b*ⱼ, h = the world's ``control[w, STEP_SIZE]``), for
    positions and velocities alike; each component is divided by tol + tol·|y_new| (tol =
    ``control[w, STEP_TOLERANCE]``, absolute and relative); each block writes its largest ratio to
    ``partials[w, block]`` and ``decide`` takes the world's largest. Launch over
    [world, block, lane] (``linalg.reduce_launch_dim``). Kinematic particles do not count: their motion is
    prescribed, exactly, at every stage. Worlds that are not running skip the work.
    """
    vec3 = vec3_type(scalar)
    weights_type = wp.types.vector(length=stages, dtype=scalar)
    effective_inv_mass = particle_funcs(scalar)
    _, block_max = reduction_funcs(tiled)

    @wp.func
    def scaled(e: vec3, y: vec3, atol: scalar, rtol: scalar) -> scalar:
        worst = scalar(0.0)
        for c in range(3):
            worst = wp.max(worst, wp.abs(e[c]) / (atol + rtol * wp.abs(y[c])))
        return worst

    @wp.kernel(module="unique", enable_backward=False)
    def rk_error(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        # State in:
        particle_qd_in: wp.array[vec3],
        stage_qd: wp.array2d[vec3],
        stage_f: wp.array2d[vec3],
        error_weights: weights_type,
        particle_q_new: wp.array[vec3],
        particle_qd_new: wp.array[vec3],
        control: wp.array2d[wp.float64],
        counters: wp.array2d[wp.int32],
        # Out:
        partials_out: wp.array2d[wp.float64],
    ):
        world, block, lane = wp.tid()
        if counters[world, STEP_RUNNING] == 0:
            return
        i = block * wp.block_dim() + lane
        worst = wp.float64(0.0)
        if i < particle_count:
            p = world * particle_count + i
            h = scalar(control[world, STEP_SIZE])
            tolerance = scalar(control[world, STEP_TOLERANCE])
            inv_mass = effective_inv_mass(particle_flags[p], particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i])
            ex = (h * error_weights[0]) * particle_qd_in[p]
            ev = (h * error_weights[0] * inv_mass) * stage_f[0, p]
            for j in range(1, wp.static(stages)):
                w = h * error_weights[j]
                ex += w * stage_qd[j, p]
                ev += (w * inv_mass) * stage_f[j, p]
            worst = wp.float64(wp.max(
                scaled(ex, particle_q_new[p], tolerance, tolerance), scaled(ev, particle_qd_new[p], tolerance, tolerance)
            ))
            if is_kinematic(particle_flags[p]):
                worst = wp.float64(0.0)  # a prescribed motion has no integration error to control
            if not wp.isfinite(worst):
                worst = wp.float64(wp.inf)  # a NaN must reject the step, and a max would drop it
        worst = block_max(worst)
        if lane == 0:
            partials_out[world, block] = worst

    return rk_error


@functools.cache
def verlet_kernels(scalar: type):
    """Velocity Verlet's drift (x' = x + h v + ½h² a, v½ = v + ½h a) and kick (v' = v½ + ½h a') kernels."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def verlet_drift(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        # State in:
        particle_q_in: wp.array[vec3],
        particle_qd_in: wp.array[vec3],
        particle_f_in: wp.array[vec3],
        time_in: wp.array[wp.float64],
        dt: scalar,
        dt_rest: scalar,
        # Out:
        particle_q_out: wp.array[vec3],
        particle_qd_half_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if i == 0:
            time_out[world] = time_in[world] + (wp.float64(dt) + wp.float64(dt_rest))
        h = dt
        inv_mass = effective_inv_mass(particle_flags[p], particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i])
        v_half = particle_qd_in[p] + (scalar(0.5) * h * inv_mass) * particle_f_in[p]
        particle_q_out[p] = particle_q_in[p] + h * v_half
        particle_qd_half_out[p] = v_half

    return verlet_drift, verlet_kick_kernel(scalar)


@functools.cache
def verlet_kick_kernel(scalar: type, backward: bool = False, module_options: tuple = ()):
    """Velocity Verlet's kick (v' = v½ + ½h a') kernel; with ``backward`` and ``module_options`` (the items of a
    module options dict) the differentiable runs' (``adjoint.kick_kernel``)."""
    vec3 = vec3_type(scalar)
    effective_inv_mass = particle_funcs(scalar)

    @wp.kernel(module="unique", enable_backward=backward, module_options=dict(module_options))
    def verlet_kick(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        particle_inv_mass: wp.array2d[scalar],
        # State in:
        particle_qd_half: wp.array[vec3],
        particle_f: wp.array[vec3],
        dt: scalar,
        # Out:
        particle_qd_out: wp.array[vec3],
    ):
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        inv_mass = effective_inv_mass(particle_flags[p], particle_inv_mass[wp.min(world, particle_inv_mass.shape[0] - 1), i])
        particle_qd_out[p] = particle_qd_half[p] + (scalar(0.5) * dt * inv_mass) * particle_f[p]

    return verlet_kick


@functools.cache
def step_control_kernels(scalar: type, tiled: bool = False):
    """Device-side step-size control of an embedded Runge-Kutta pair, one controller per world (one thread
    per world, but ``commit``: one per particle, and ``decide``: a block of lanes per world, launched over
    [world, lanes] with ``block_dim`` = lanes, one lane on the CPU, ``tiled`` off).

    Row w of the control array holds, by the ``STEP_*`` slots: the target interval, the time reached, the
    step in use, the proposed step, the growth cap, the scaled error of the last attempt, the error
    tolerance and the most attempts per interval; row w of the counters holds accepted, rejected and
    attempted steps, whether the last attempt was accepted, whether the interval failed, and whether the
    world is still running; ``step`` holds each world's step in use (what the stage kernels read).
    ``keep_going`` counts the running worlds: the attempt loop ends at zero.
    """
    vec3 = vec3_type(scalar)
    _, block_max = reduction_funcs(tiled)

    @wp.kernel(module="unique", enable_backward=False)
    def begin(
        # In:
        interval: wp.float64,
        world_enabled: wp.array[wp.int32],
        # In/out (the step control):
        control_in_out: wp.array2d[wp.float64],
        counters_out: wp.array2d[wp.int32],
        step_out: wp.array[wp.float64],
        keep_going_out: wp.array[wp.int32],
    ):
        """Start an interval in every enabled world (``keep_going`` zeroed beforehand): t = 0,
        h = min(proposed, interval)."""
        world = wp.tid()
        control_in_out[world, STEP_INTERVAL] = interval
        control_in_out[world, STEP_TIME] = wp.float64(0.0)
        proposed = control_in_out[world, STEP_PROPOSED]
        proposed = wp.where(proposed > wp.float64(0.0), proposed, interval)
        control_in_out[world, STEP_PROPOSED] = proposed
        control_in_out[world, STEP_GROWTH] = wp.float64(STEP_MAX_GROWTH)
        control_in_out[world, STEP_ERROR] = wp.float64(0.0)
        counters_out[world, STEP_ATTEMPTS_NOW] = 0
        counters_out[world, STEP_LAST_ACCEPTED] = 0
        running = world_enabled[world]
        counters_out[world, STEP_RUNNING] = running
        # A world that does not run takes steps of 0: its stages reproduce its state.
        control_in_out[world, STEP_SIZE] = wp.where(running != 0, wp.min(proposed, interval), wp.float64(0.0))
        step_out[world] = control_in_out[world, STEP_SIZE]
        if running != 0:
            wp.atomic_add(keep_going_out, 0, 1)

    @wp.kernel(module="unique", enable_backward=False)
    def decide(
        # In (the attempt's block partials):
        partials: wp.array2d[wp.float64],
        # In/out (the step control):
        control_in_out: wp.array2d[wp.float64],
        counters_in_out: wp.array2d[wp.int32],
        step_out: wp.array[wp.float64],
        keep_going_out: wp.array[wp.int32],
    ):
        """Accept or reject the attempt (its error: the largest of the world's block partials), choose the
        next step, and whether the world goes on."""
        world, lane = wp.tid()
        if counters_in_out[world, STEP_RUNNING] == 0:
            if lane == 0:
                counters_in_out[world, STEP_LAST_ACCEPTED] = 0
            return
        # The lanes take every lanes-th block partial, then the block's max (one thread walking ~10³ blocks
        # of a 512² cloth in turn costs ~1 ms per attempt on a GPU).
        error = wp.float64(0.0)
        b = lane
        while b < partials.shape[1]:
            error = wp.max(error, partials[world, b])
            b += wp.block_dim()
        error = block_max(error)
        if lane != 0:
            return
        h = control_in_out[world, STEP_SIZE]
        proposed = control_in_out[world, STEP_PROPOSED]
        accept = error <= wp.float64(1.0)
        factor = wp.float64(STEP_MIN_GROWTH)
        if wp.isfinite(error) and error > wp.float64(0.0):
            factor = wp.max(factor, wp.float64(STEP_SAFETY) * wp.pow(error, wp.float64(-0.2)))
        elif error == wp.float64(0.0):
            factor = control_in_out[world, STEP_GROWTH]
        counters_in_out[world, STEP_ATTEMPTS_NOW] = counters_in_out[world, STEP_ATTEMPTS_NOW] + 1
        control_in_out[world, STEP_ERROR] = error
        if accept:
            control_in_out[world, STEP_TIME] = control_in_out[world, STEP_TIME] + h
            counters_in_out[world, STEP_ACCEPTED] = counters_in_out[world, STEP_ACCEPTED] + 1
            next_h = h * wp.min(control_in_out[world, STEP_GROWTH], factor)
            # A step cut short to land on the interval's end says nothing against the step in use before.
            proposed = wp.where(h < proposed, wp.max(proposed, next_h), next_h)
            control_in_out[world, STEP_GROWTH] = wp.float64(STEP_MAX_GROWTH)
            counters_in_out[world, STEP_LAST_ACCEPTED] = 1
        else:
            counters_in_out[world, STEP_REJECTED] = counters_in_out[world, STEP_REJECTED] + 1
            proposed = h * wp.min(wp.float64(1.0), factor)
            control_in_out[world, STEP_GROWTH] = wp.float64(1.0)
            counters_in_out[world, STEP_LAST_ACCEPTED] = 0
        control_in_out[world, STEP_PROPOSED] = proposed
        remaining = control_in_out[world, STEP_INTERVAL] - control_in_out[world, STEP_TIME]
        unfinished = remaining > wp.float64(1.0e-12) * control_in_out[world, STEP_INTERVAL]
        exhausted = wp.float64(counters_in_out[world, STEP_ATTEMPTS_NOW]) >= control_in_out[world, STEP_MAX_ATTEMPTS]
        if unfinished and exhausted:
            counters_in_out[world, STEP_FAILED] = 1
        if unfinished and not exhausted:
            control_in_out[world, STEP_SIZE] = wp.min(proposed, remaining)
        else:
            control_in_out[world, STEP_SIZE] = wp.float64(0.0)
            counters_in_out[world, STEP_RUNNING] = 0
            wp.atomic_sub(keep_going_out, 0, 1)
        step_out[world] = control_in_out[world, STEP_SIZE]

    @wp.kernel(module="unique", enable_backward=False)
    def commit(
        # Model:
        particle_count: int,
        # Step control in:
        counters: wp.array2d[wp.int32],
        # Stage in (the last stage):
        stage_q: wp.array[vec3],
        stage_qd: wp.array[vec3],
        stage_time: wp.array[wp.float64],
        stage_f_last: wp.array[vec3],
        # Out (on acceptance):
        particle_q_out: wp.array[vec3],
        particle_qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
        stage_f_first_out: wp.array[vec3],
    ):
        """On acceptance: y ← the last stage's state (its time t + h included), and its force becomes
        stage 0's (FSAL)."""
        p = wp.tid()
        world, i = world_and_index(p, particle_count)
        if counters[world, STEP_LAST_ACCEPTED] == 1:
            if i == 0:
                time_out[world] = stage_time[world]
            particle_q_out[p] = stage_q[p]
            particle_qd_out[p] = stage_qd[p]
            stage_f_first_out[p] = stage_f_last[p]

    return begin, decide, commit
