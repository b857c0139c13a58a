"""Run-time guards: detect a state going bad on the device, per world, without a host synchronisation per
substep.

A check is three launches and one per family, captured with the substeps (and, with the dissipation or the work of
wind and handles counted where the integrator's own force pass does not count them, a few more after every substep:
below): ``drive`` (per kinematic particle: the work its drive did since the previous check), ``measure`` (per particle:
non-finite position or velocity, the largest strain of its elements (the families' ``strain`` hook), kinetic energy
(of the free particles: a kinematic one moves as prescribed), and the work the loads did on it since the previous
check; per-block partials, no float atomics), ``element_energy_partials`` (one per family: per-block sums of
its elements' elastic energy, the families' ``energy`` hook), ``gather`` (per world: the world's kinetic
and elastic energy and work, summed in a fixed order, its largest strain, and the energy balance below; then
in its lane 0 the verdict: compare with the world's limits, latch the world's first failure with its substep, reset
the accumulators, and with ``stop_world`` set hold the failed world: ``world_enabled`` 0; in a world that failed at
this check only, its lanes then find the particle, element and family holding the largest strain, so that the record
is complete when the check ends and the host may read it a frame later: ``Simulator(defer_verdict=...)``).

**The work put in.** W sums, check by check, Σᵢ Fᵢ · (xᵢ - xᵢ') over the world's particles, xᵢ' the
positions at the previous check: weight mᵢ g and the control's external force on free particles, and for
kinematic particles (pins, tracks) the negative of the elements' force on them, i.e. the force the driver
applies through them. Weight and the drive's force enter by the trapezoidal rule (their values at both
checks; exact for constant gravity and still pins, second order for tracks), the control's force by its
value at the check (it is constant within a frame, set between frames). The families that do work from outside
(wind, handles) depend on the velocity and move with the cloth within a frame, so their work is summed after
every substep instead, while the balance is on (``guard_work_kernel``: their forces at the substep's midpoint
state over its displacement, midpoint rule; the battery's wind- and handle-driven cloth was unguarded by the
balance before, and RK4 ran 10 s at up to 1.4× its stability limit carrying a numerical oscillation out of which
the dampers took 30 to 350 times the stable runs' energy: bench/RESULTS.md §11). W⁺ sums the positive parts.

**The energy taken out.** D sums the power the dampers take out of the motion, P = Σ_springs kd ((vj - vi)·d̂)² +
Σ_hinges kd θ̇² + Σ_free particles c v·(v - u) (viscous drag c against the air's velocity u; the families'
``dissipation`` hook, so a new family brings its own), by the trapezoidal rule over every substep h: D += h (P' + P)/2
with P' the power after the previous substep. A check's reach is many substeps, and a damped mode's power
oscillates at twice its frequency, so sampling at the checks alone would alias; per substep it is second order in h
where the motion is smooth. Symplectic Euler samples the power at each substep's midpoint state instead (midpoint
rule, ``dissipation_rule_func``): its damper acts with the step's first velocity over a displacement made with its
last, and the trapezoid over-counts that loss. Each reducing block keeps its own running sum and last power
(``running[world, block]``: float64, no atomics, one launch per family and one for drag per substep, no per-world
pass; on the CPU one thread per world and family sums in order, a single block); ``gather`` adds a world's blocks in
order at the check and clears them.
Contact and friction losses are not counted (a contact's penalty work is neither potential nor separable
here), nor any other damping (stabilisers): what is not counted only loosens the balance, it never stops a
correct run. The host leaves D out altogether where the balance with it would not be exact up to the
integrator's error (``core/guards.py``: integrators that need damping to be stable, adaptive ones, models
with position corrections).

**Two energy criteria.** A world's kinetic plus elastic energy can never exceed its value at the start
plus the work its loads did since, less the energy the dampers took out: E(t) ≤ E(0) + W(t) - D(t).

* *Runaway*: the kinetic energy against ``limit + factor · W⁺`` (10⁶ times the scene's energy scale and
  the work put in by default), so that a pushed body at rest, whose energy scale is ~0, is not stopped
  for the energy it was given. Catches what has gone far wrong, whatever the model.
* *Balance*: the energy created, E(t) - (E_ref + W(t) - D(t)), against ``tolerance`` × the peak of E_ref + W
  (the most energy the world could physically hold so far) + ``floor``. An explicit integrator beyond its
  stability limit pumps energy into its unstable modes; where the nonlinearity saturates their growth the
  state stays finite and untorn but holds several times the energy of the converged solution, and the
  balance stops it when that excess first reaches ``tolerance`` of the budget. E_ref is taken at the first
  check after a rebase (the start, or a host write of the model's values, which changes the elastic
  energy without work), and D counts from there, so the energy balance holds from there on. Without D, the
  energy a long damped run dissipated would be slack: an unstable step would have to re-create all of it
  before the balance noticed. The families' energy is the potential
  of their force (biphasic knee, force clamp), so the balance is exact up to the integrator's own energy
  error, which the tolerance covers (symplectic Euler's is O(h): ~1 % of a swinging cloth at 1/120 s).

Once a world's record is latched, later checks leave it untouched, so the host reads each world's first
failure at the end of the frame. Held worlds are not checked. The records are one row per world, laid out
by the slots below. The check that latches a world's record also writes it, with the world's clock at the check,
into the *mirror* (a row of float64 per world, ``MIRROR_COLUMNS``; on CUDA pinned host memory the kernel writes
through its mapping, so that the host reads a frame's verdict with no copy queued behind the frame): the record's
ints first, the clock, then, after a system-wide fence, its reason, which the host reads first.
"""

import functools
from typing import NamedTuple

import warp as wp

from .families import elements, struct_type
from .forces import POWER_WORK, ForceFeatures, counts_work, power_sums_funcs
from .inputs import INPUT_DRAG, INPUT_GRAVITY, INPUT_WIND, input_funcs
from .kinematics import is_kinematic
from .linalg import block_barrier, block_reduce_funcs, reduction_funcs, system_fence
from .precision import vec3_type
from .springs import COINCIDENT_DISTANCE, SpringSpec, damper_step_func, spring_arrays_type, spring_sweep_funcs
from .sweep import grid_energy_pass, grid_vectorised
from .flatten import flat_kernel, launch_bounds_option

wp.set_module_options({"enable_backward": False})

# int32 status slots
GUARD_TRIPPED = 0  # 0 = fine, else one of the GUARD_* reasons
GUARD_SUBSTEP = 1  # substep (within the frame) of the check that tripped
GUARD_NONFINITE_PARTICLE = 2  # smallest index of a particle with a non-finite position or velocity
GUARD_STRAIN_PARTICLE = 3  # smallest index of a particle holding the largest strain
GUARD_STRAIN_ELEMENT = 4  # smallest index of an element with the largest strain
GUARD_NONFINITE_COUNT = 5  # particles with a non-finite position or velocity
GUARD_STRAIN_FAMILY = 6  # smallest index (in the model's families) of a family with the largest strain
GUARD_INTS = 7
# the mirror's columns (``gather_lanes``): the record's ints (as float64), then the world's clock at the check [s]
MIRROR_CLOCK = GUARD_INTS
MIRROR_COLUMNS = GUARD_INTS + 1
# float64 slots
GUARD_MAX_STRAIN = 0  # largest element strain (springs: |d|/L - 1) of the check
GUARD_KINETIC_ENERGY = 1  # Σ ½ m v² of the check [J]
GUARD_WORK = 2  # Σ F · Δx of the loads since the previous check [J] (W⁺, the running sum: ``work_total``)
GUARD_ELASTIC_ENERGY = 3  # Σ of the elements' elastic energy of the check [J]
GUARD_EXCESS = 4  # kinetic + elastic energy beyond the balance's budget E_ref + W [J]
GUARD_BUDGET = 5  # the budget's peak so far, max over checks of E_ref + W [J]
GUARD_FLOATS = 6
# float64 slots of a check's per-block partials (``partials[world, block, slot]``): GUARD_KINETIC_ENERGY,
# GUARD_MAX_STRAIN and GUARD_WORK, then the power sums' (``measure``'s ``power``)
PARTIAL_DISSIPATION = GUARD_FLOATS  # energy the dampers and drag took out since the last check [J]
PARTIAL_FAMILY_WORK = GUARD_FLOATS + 1  # work the loads from outside (wind, handles) did since the last check [J]
PARTIAL_CLOSE_DISSIPATION = GUARD_FLOATS + 2  # the power drag takes out at the check's state [W] (the closing term)
PARTIAL_CLOSE_WORK = GUARD_FLOATS + 3  # the power of the loads from outside at the check's state [W] (the closing term)
PARTIAL_DRIVE_WORK = GUARD_FLOATS + 4  # work the drives did through the kinematic particles since the last check [J]
PARTIAL_SLOTS = GUARD_FLOATS + 5
# float64 slots of a world's closing terms carried to the next span (``carry[world, slot]``): minus this check's share
# of h times the power at its state, which the next span's first step counts again in full (``guard_kernels``)
CARRY_DISSIPATION, CARRY_WORK = 0, 1
CARRY_SLOTS = 2
# How the integrator's force pass counts the power for the balance (``measure``'s ``power``; ``core/forces.PowerSums``):
# not at all (passes of their own), the energy over each step (symplectic Euler: f·(v + v')/2 h, exact), or h times
# the power at each step's start, which the check turns into the trapezoid of the power (RK4)
POWER_RULE_NONE, POWER_RULE_MEAN, POWER_RULE_START = 0, 1, 2
# float64 slots of the energy balance: carried from check to check
BALANCE_REFERENCE = 0  # E_ref: kinetic + elastic energy less the work counted, at the last rebase [J]
BALANCE_WORK = 1  # W: the loads' work since the start, signed [J]
BALANCE_PEAK = 2  # the peak of E_ref + W since the last rebase [J]
BALANCE_REBASE = 3  # 1: take the next check's energy as the reference (at the start, after a host write)
BALANCE_ENERGY = 4  # kinetic + elastic energy at the last check [J]
BALANCE_DISSIPATION = 5  # D: the energy the dampers and drag took out since the last rebase [J]
#: Integrators whose every step evaluates the forces once at its start state (``eval_forces`` on ``state_in``): there
#: the scattered springs' pass counts the dampers' dissipation (``DamperSums``) instead of a pass of its own.
DAMPERS_IN_FORCE_PASS = ("symplectic_euler", "rk4", "velocity_verlet")

BALANCE_SLOTS = 6
# float64 slots of a reducing block's running dissipation (``running[world, block, slot]``), carried from
# substep to substep
RUNNING_DISSIPATION = 0  # energy taken out since the last check [J]
RUNNING_POWER = 1  # the power after the last substep [W]; non-finite: none yet (the first trapezoid's start)
RUNNING_STEP_DISSIPATION = 2  # energy the dampers and drag took out since the last check, summed by symplectic
# Euler's fused step on CUDA (``integrators.symplectic_euler_blocks_kernel``) [J]
RUNNING_WORK = 3  # work the families that do work from outside did since the last check [J] (``guard_work_kernel``,
# and that step); the last slot: a checkpoint's running sums of fewer slots load with it zero (all but the power are
# zero at a frame's end)
RUNNING_SLOTS = 4
# float64 slots of the limits: live settings, read by ``gather``
GUARD_LIMIT_STRAIN = 0  # an element strain beyond this tears the run [-]
GUARD_LIMIT_KINETIC_ENERGY = 1  # a total kinetic energy beyond this is a runaway [J]
GUARD_STOP_WORLD = 2  # 1: a failed world is held and the others go on; 0: the run stops
GUARD_WORK_FACTOR = 3  # the kinetic-energy limit grows by this factor times the work put in [-]
GUARD_BALANCE_TOLERANCE = 4  # energy created beyond this fraction of the budget's peak stops the run; 0: off [-]
GUARD_BALANCE_FLOOR = 5  # ... plus this much [J] (round-off of a world at rest)
GUARD_LIMITS = 6
# reasons
GUARD_NONFINITE = 1
GUARD_STRAIN = 2
GUARD_ENERGY = 3
GUARD_BALANCE = 4
NO_PARTICLE = 2**31 - 1
#: How far below the check's largest strain, as a share of (1 + that strain), a strain the record's search finds still
#: counts as the largest (``gather``): the check's passes and the search evaluate strains in different kernels, whose
#: float32 roundings differ by a few units in the last place on CUDA (fused multiply-adds).
STRAIN_MATCH = 1e-5


@functools.cache
def particle_strain_func(scalar: type, specs: tuple):
    """``strain(world, i, base, xi, element_arrays, particle_q) -> float64``: the largest strain [-] of the elements at
    particle i over the families of ``specs`` without an ``element_strain`` hook (those with one are measured per
    element in the energy pass, ``guard_energy_kernel``); -1 where none."""
    vec3 = vec3_type(scalar)
    Elements = elements(scalar, specs).arrays
    if not specs:

        @wp.func
        def no_strain(world: int, i: int, base: int, xi: vec3, arrays: Elements, particle_q: wp.array[vec3]):
            return wp.float64(-1.0)

        return no_strain
    funcs = specs[0].funcs(scalar)
    skipped = getattr(funcs, "element_strain", None) is not None
    head_strain = funcs.strain

    @wp.func
    def head(world: int, i: int, base: int, xi: vec3, arrays: funcs.arrays, particle_q: wp.array[vec3]):
        if wp.static(skipped):
            return wp.float64(-1.0)
        worst, _ = head_strain(world, i, base, xi, arrays, particle_q)
        return worst

    if len(specs) == 1:

        @wp.func
        def strain_1(world: int, i: int, base: int, xi: vec3, arrays: Elements, particle_q: wp.array[vec3]):
            return head(world, i, base, xi, arrays.head, particle_q)

        return strain_1
    rest = particle_strain_func(scalar, specs[1:])

    @wp.func
    def strain_n(world: int, i: int, base: int, xi: vec3, arrays: Elements, particle_q: wp.array[vec3]):
        return wp.max(head(world, i, base, xi, arrays.head, particle_q), rest(world, i, base, xi, arrays.tail,
                                                                            particle_q))

    return strain_n


def guard_kernels(scalar: type, families: tuple, tiled: bool, external: bool, working: tuple = (),
                  power: int = POWER_RULE_NONE, power_features: ForceFeatures | None = None,
                  power_modes: tuple = (), dissipation: bool = False):
    """(measure, gather, drive) kernels of one precision and tuple of family specs; ``external``:
    the control has an external force (part of the loads' work); ``working``: the specs of the families that
    do work from outside (wind, handles: ``ElementFamily.does_work``), whose forces on free particles count
    among the loads here (not where the integrator's force pass counts their work).

    ``power`` (a ``POWER_RULE_*``): what the integrator's force pass added to the power sums since the last check,
    which ``measure`` takes into the check's partials and clears. With ``POWER_RULE_START`` the sums hold h times
    the power at each step's start; the check adds half of h times the power at its own state to its span and
    leaves minus that half for the next span, whose first step adds all of it: the trapezoid of the power over the
    substeps. With ``POWER_RULE_MEAN`` the sums hold each step's exact energy, -h f_d·(v + v')/2, whose sum
    over steps differs from the mean-rate rule's, Σ h c ((r + r')/2)² per damper (≥ 0 for each), by a quarter of
    h P at the span's ends (P = -f_d·v, the dampers' power: the algebra of (r + r')² = r² + 2 r r' + r'²): the
    check adds that quarter at its state and leaves minus it for the next span. The exact energy alone would
    count a damper that an unstable step drives (kd h/m past its limit) as putting energy in, and the balance
    would never see the energy that step creates; the mean rate keeps every damper's loss ≥ 0.

    The power at the check's state (the closing term) is summed where its parts are cheap to read, with no force
    evaluation per particle: drag's (c |v|²) and the wind's push through it (c u·v) on the free particles and the
    forces of the families of mode ``POWER_WORK`` (``power_modes``; wind, handles) in ``measure``; the dampers of
    the families of mode ``POWER_DAMPERS`` per element in the energy pass (their ``dissipation`` hook: the power
    of a family's damper forces over its particles, Σᵢ -f_d,ᵢ·vᵢ = Σ_e P_e; ``guard_energy_kernel``'s ``power``).
    ``gather`` adds the world's share of it, h times ``share`` times the power, and carries minus that share to the
    next span (``carry[world]``): one float64 per world instead of a value per particle, and ``measure`` no longer
    evaluates every particle's elements' forces (a 32² cloth's check on the CPU: 128 µs of ``measure`` before, of
    which ~90 µs was that evaluation; on CUDA it held most of the kernel's 112 registers). ``dissipation``:
    ``gather`` adds the dampers' and drag's energy to D (else only the loads' work counts: D left out,
    ``core/guards.dissipation_exact``)."""
    return _guard_parts(scalar, families, tiled, external, working, power, power_features, power_modes,
                        dissipation)[:3]


@functools.cache
def _guard_parts(scalar: type, families: tuple, tiled: bool, external: bool, working: tuple, power: int,
                 power_features: ForceFeatures | None, power_modes: tuple, dissipation: bool):
    """:func:`guard_kernels`' three kernels and :func:`guard_lane_funcs`' three functions."""
    vec3 = vec3_type(scalar)
    counted = power != POWER_RULE_NONE
    sums_funcs = power_sums_funcs(scalar, counted and counts_work(power_features, power_modes))
    Sums = sums_funcs.type
    pack = sums_funcs.pack
    sums_dissipated = sums_funcs.dissipated
    sums_worked = sums_funcs.worked
    drag_closing = counted and power_features.drag
    wind_closing = drag_closing and power_features.wind
    pushing = counted and POWER_WORK in power_modes
    push_force = pushing_force_func(scalar, families, power_modes) if pushing else None
    # The closing terms' shares of h times the power at the check's state (dampers, loads from outside): the
    # trapezoid's halves (RK4), or for symplectic Euler's D a quarter, which turns its exact step energy into the
    # mean-rate rule's (below); its loads' work stays exact.
    share_dampers = 0.5 if power == POWER_RULE_START else 0.25
    share_work = 0.5 if power == POWER_RULE_START else 0.0
    block_sum, _ = reduction_funcs(tiled)
    Seven, reduce_seven = block_reduce_funcs(tiled, 6, 1)  # six sums and a largest, in one round
    composed = elements(scalar, families)
    Elements = composed.arrays
    element_strain = composed.strain
    particle_strain = particle_strain_func(scalar, families)
    # Whether measure sees any strain (a family without an ``element_strain`` hook; those with one are measured per
    # element in the energy pass): else lane 0's own value is written, never reduced.
    strained = any(getattr(spec.funcs(scalar), "element_strain", None) is None for spec in families)
    element_force = composed.force
    work_composed = elements(scalar, working)
    WorkElements = work_composed.arrays
    work_force = work_composed.force
    input_vec3 = input_funcs(scalar)

    @wp.func
    def measure_lanes(
        # Where: the world, the lane's block of the world and its lane there (``lanes`` a block):
        world: int,
        block: int,
        lane: int,
        lanes: int,
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        work_arrays: WorkElements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Guards in (the lead λ [s]: the steady loads' work on free particles is F·(Δx + λ Δv)):
        lead: scalar,
        # Launch (the items between a lane's successive particles: ``linalg.reduce_stride``):
        stride: int,
        # In/out:
        power_in_out: wp.array[Sums],
        previous_q_in_out: wp.array[vec3],
        previous_qd_in_out: wp.array[vec3],
        previous_load_in_out: wp.array[vec3],
        status_in_out: wp.array2d[wp.int32],
        partials_out: wp.array3d[wp.float64],
    ):
        """``measure``'s work for one lane (also run by the one-launch frame's lanes at its end)."""
        # A failed or held world is measured as any other (its sums cleared, its last check's state and loads kept:
        # released without a restart, its first check counts from here), but its record is left as it was.
        live = status_in_out[world, GUARD_TRIPPED] == 0 and world_enabled[world] != 0
        i = block * lanes + lane
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        work = wp.float64(0.0)
        dissipated = wp.float64(0.0)
        family_work = wp.float64(0.0)
        close_dissipated = wp.float64(0.0)
        close_work = wp.float64(0.0)
        while i < particle_count:  # every stride-th particle from the lane's first
            base = world * particle_count
            p = base + i
            # Every read of the particle's entries first, in one round trip: the stores below may alias them, and a
            # read behind a store waits for its own (this pass ran at a fifth of the bandwidth, each warp stalled
            # on its reads in turn: ncu on an H200, bench/results/guard_cost.md).
            x = particle_q[p]
            v = particle_qd[p]
            x_before = previous_q_in_out[p]
            v_before = previous_qd_in_out[p]
            load_before = previous_load_in_out[p]
            flags = particle_flags[p]
            mass = particle_mass[wp.min(world, particle_mass.shape[0] - 1), i]
            sums = pack(scalar(0.0), scalar(0.0))
            if wp.static(counted):
                sums = power_in_out[p]
            if wp.isfinite(x) and wp.isfinite(v):
                worst = wp.max(worst, particle_strain(world, i, base, x, element_arrays, particle_q))
                free = not is_kinematic(flags)
                if free:  # (a kinematic particle moves as prescribed: no runaway of its own; its drive's work: ``drive``)
                    held = vec3(scalar(0.0))  # a load constant within a frame: its value at the check
                    # (in float64: a runaway's |v|² overflows float32 long before its state does)
                    energy += wp.float64(0.5) * wp.float64(mass) * (wp.float64(v[0]) * wp.float64(v[0])
                                                                   + wp.float64(v[1]) * wp.float64(v[1])
                                                                   + wp.float64(v[2]) * wp.float64(v[2]))
                    load = mass * input_vec3(inputs, world, INPUT_GRAVITY)
                    if wp.static(len(working) > 0):  # wind, handles: forces from outside the cloth
                        load += work_force(world, i, base, x, v, work_arrays, inputs, particle_q, particle_qd)
                    if wp.static(external):
                        held = particle_force_ext[p]
                    steady = mass * input_vec3(inputs, world, INPUT_GRAVITY) + held
                    before = load_before
                    if not wp.isfinite(before):  # the first check: no earlier value
                        before = load
                    work += wp.float64(wp.dot(scalar(0.5) * (load + before) + held, x - x_before)
                                      + lead * wp.dot(steady, v - v_before))
                    previous_load_in_out[p] = load
                if wp.static(counted):  # (a kinematic particle's sums: its elements' dampers only)
                    dissipated += wp.float64(sums_dissipated(sums))
                    family_work += wp.float64(sums_worked(sums))
                    power_in_out[p] = pack(scalar(0.0), scalar(0.0))
                    # The closing term's parts on a free particle (its elements' dampers: the energy pass).
                    if free:
                        if wp.static(drag_closing):  # drag against still air, -c v: power c |v|² taken out
                            close_dissipated += wp.float64(inputs[world, INPUT_DRAG] * wp.dot(v, v))
                            if wp.static(wind_closing):  # the wind's push c u
                                close_work += wp.float64(inputs[world, INPUT_DRAG]
                                                         * wp.dot(input_vec3(inputs, world, INPUT_WIND), v))
                        if wp.static(pushing):
                            close_work += wp.float64(wp.dot(push_force(world, i, base, x, v, element_arrays, inputs,
                                                                       particle_q, particle_qd), v))
            elif live:
                wp.atomic_min(status_in_out, world, GUARD_NONFINITE_PARTICLE, i)
                wp.atomic_add(status_in_out, world, GUARD_NONFINITE_COUNT, 1)
            previous_q_in_out[p] = x
            previous_qd_in_out[p] = v
            i += stride
        # (one round for all: the entries a scene does not count are zero in every lane, their sums zero)
        reduced = reduce_seven(Seven(energy, work, dissipated, family_work, close_dissipated, close_work, worst))
        if wp.static(strained):
            worst = reduced[6]
        if lane == 0:
            partials_out[world, block, GUARD_KINETIC_ENERGY] = reduced[0]
            partials_out[world, block, GUARD_MAX_STRAIN] = worst
            partials_out[world, block, GUARD_WORK] = reduced[1]
            if wp.static(counted):
                partials_out[world, block, PARTIAL_DISSIPATION] = reduced[2]
                partials_out[world, block, PARTIAL_FAMILY_WORK] = reduced[3]
                partials_out[world, block, PARTIAL_CLOSE_DISSIPATION] = reduced[4]
                partials_out[world, block, PARTIAL_CLOSE_WORK] = reduced[5]

    @flat_kernel(module="unique", enable_backward=False,
                 last=composed.last("element_arrays") + work_composed.last("work_arrays"))
    def measure(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        work_arrays: WorkElements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Guards in (the lead λ [s]: the steady loads' work on free particles is F·(Δx + λ Δv)):
        lead: scalar,
        # Launch (the items between a lane's successive particles: ``linalg.reduce_stride``):
        stride: int,
        # In/out:
        power_in_out: wp.array[Sums],
        previous_q_in_out: wp.array[vec3],
        previous_qd_in_out: wp.array[vec3],
        previous_load_in_out: wp.array[vec3],
        status_in_out: wp.array2d[wp.int32],
        partials_out: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        measure_lanes(world, block, lane, wp.block_dim(), particle_count, world_enabled, particle_flags, particle_mass,
                      element_arrays, work_arrays, inputs, particle_force_ext, particle_q, particle_qd, lead, stride,
                      power_in_out, previous_q_in_out, previous_qd_in_out, previous_load_in_out, status_in_out,
                      partials_out)

    @wp.func
    def drive_lanes(
        # Where (``measure_lanes``):
        world: int,
        block: int,
        lane: int,
        lanes: int,
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Guards in (the positions at the last check):
        previous_q: wp.array[vec3],
        # Launch (the items between a lane's successive particles: ``linalg.reduce_stride``):
        stride: int,
        # In/out:
        previous_load_in_out: wp.array[vec3],
        partials_out: wp.array3d[wp.float64],
    ):
        """``drive``'s work for one lane: the work the drives did through the kinematic particles (pins, tracks)
        since the last check: the negative of
        the elements' force on each, by the trapezoid of its values at the two checks, over its displacement; launched
        before ``measure`` (which then moves ``previous_q`` on) over its grid. A pass of its own: the elements' force
        evaluated in ``measure`` for its few kinematic particles held 113 registers a thread there (64 without it; on
        sm_90, ``bench/guard_registers.py``), and so its occupancy, for every particle."""
        i = block * lanes + lane
        work = wp.float64(0.0)
        while i < particle_count:
            base = world * particle_count
            p = base + i
            if is_kinematic(particle_flags[p]):
                x = particle_q[p]
                v = particle_qd[p]
                if wp.isfinite(x) and wp.isfinite(v):
                    load = -element_force(world, i, base, x, v, element_arrays, inputs, particle_q, particle_qd)
                    before = previous_load_in_out[p]
                    if not wp.isfinite(before):  # the first check: no earlier value
                        before = load
                    work += wp.float64(wp.dot(scalar(0.5) * (load + before), x - previous_q[p]))
                    previous_load_in_out[p] = load
            i += stride
        work = block_sum(work)
        if lane == 0:
            partials_out[world, block, PARTIAL_DRIVE_WORK] = work

    @flat_kernel(module="unique", enable_backward=False, last=composed.last("element_arrays"))
    def drive(
        # Model:
        particle_count: int,
        particle_flags: wp.array[wp.int32],
        element_arrays: Elements,
        inputs: wp.array2d[scalar],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Guards in (the positions at the last check):
        previous_q: wp.array[vec3],
        # Launch (the items between a lane's successive particles: ``linalg.reduce_stride``):
        stride: int,
        # In/out:
        previous_load_in_out: wp.array[vec3],
        partials_out: wp.array3d[wp.float64],
    ):
        """(``drive_lanes``, launched before ``measure`` over its grid.)"""
        world, block, lane = wp.tid()
        drive_lanes(world, block, lane, wp.block_dim(), particle_count, particle_flags, element_arrays, inputs,
                    particle_q, particle_qd, previous_q, stride, previous_load_in_out, partials_out)

    @wp.func
    def gather_lanes(
        # Where: the world and this lane of the block that gathers it (``lanes`` lanes):
        world: int,
        lane: int,
        lanes: int,
        # Model:
        particle_count: int,
        element_arrays: Elements,
        # State in:
        particle_q: wp.array[vec3],
        # Guards in (the check's partials, the energy pass's dampers' power at the check's state, its substep, the
        # limits, the step h [s] of the closing term; ``carry_only`` 1: a restart, only the closing term carried):
        partials: wp.array3d[wp.float64],
        energy_partials: wp.array2d[wp.float64],
        strain_partials: wp.array2d[wp.float64],
        power_partials: wp.array2d[wp.float64],
        substep: int,
        limits: wp.array2d[wp.float64],
        power_h: wp.float64,
        carry_only: int,
        # In/out:
        world_enabled_in_out: wp.array[wp.int32],
        status_in_out: wp.array2d[wp.int32],
        running_in_out: wp.array3d[wp.float64],
        values_in_out: wp.array2d[wp.float64],
        work_total_in_out: wp.array[wp.float64],
        balance_in_out: wp.array2d[wp.float64],
        carry_in_out: wp.array2d[wp.float64],
        # The world's clock at the check [s], and the record's mirror (written where the world fails here):
        clock: wp.float64,
        mirror_out: wp.array2d[wp.float64],
    ):
        """``gather``'s work for one lane of the world's block: a world's kinetic and elastic energy, the work put
        in and the energy dissipated since the last
        check (its blocks' partials and running sums: the dissipation and the working families' work, the running
        sums cleared; with the power counted in the force pass, the closing term at this state: its share added, minus
        it carried to the next span; the work and the dissipation
        added to the balance, the work's positive part to the world's running total W⁺), its largest strain,
        and the energy beyond the balance's budget. Run by one block of ``lanes`` lanes per world (one lane on the
        CPU): each lane sums every lanes-th block in order, then a fixed-order tree (``block_sum``) joins the lanes,
        so the sums are deterministic; one thread walking a world's ~10³ blocks of a 512² cloth in turn took 0.9 ms
        on an H100, most of a check. Lane 0 then decides: the world's sums and its verdict in one pass."""
        if status_in_out[world, GUARD_TRIPPED] != 0 or world_enabled_in_out[world] == 0:
            # A failed or held world: its record stays as it was, the running sums of its steps since the last check
            # are dropped (released without a restart, its first check counts from here).
            b = lane
            while b < running_in_out.shape[1]:
                running_in_out[world, b, RUNNING_DISSIPATION] = wp.float64(0.0)
                running_in_out[world, b, RUNNING_WORK] = wp.float64(0.0)
                running_in_out[world, b, RUNNING_STEP_DISSIPATION] = wp.float64(0.0)
                b += lanes
            if lane == 0:
                carry_in_out[world, CARRY_DISSIPATION] = wp.float64(0.0)
                carry_in_out[world, CARRY_WORK] = wp.float64(0.0)
            return
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        work = wp.float64(0.0)
        dissipated = wp.float64(0.0)
        close_dissipated = wp.float64(0.0)
        close_work = wp.float64(0.0)
        b = lane
        while b < partials.shape[1]:
            energy += partials[world, b, GUARD_KINETIC_ENERGY]
            worst = wp.max(worst, partials[world, b, GUARD_MAX_STRAIN])
            work += partials[world, b, GUARD_WORK] + partials[world, b, PARTIAL_DRIVE_WORK]
            if wp.static(counted):
                work += partials[world, b, PARTIAL_FAMILY_WORK]
                close_dissipated += partials[world, b, PARTIAL_CLOSE_DISSIPATION]
                close_work += partials[world, b, PARTIAL_CLOSE_WORK]
                if wp.static(dissipation):
                    dissipated += partials[world, b, PARTIAL_DISSIPATION]
            b += lanes
        elastic = wp.float64(0.0)
        b = lane
        while b < energy_partials.shape[1]:
            elastic += energy_partials[world, b]
            worst = wp.max(worst, strain_partials[world, b])
            if wp.static(counted):
                close_dissipated += power_partials[world, b]
            b += lanes
        b = lane
        while b < running_in_out.shape[1]:
            dissipated += running_in_out[world, b, RUNNING_DISSIPATION]
            work += running_in_out[world, b, RUNNING_WORK]
            if wp.static(counted and dissipation):  # (the fused step's: counted where the power sums' are)
                dissipated += running_in_out[world, b, RUNNING_STEP_DISSIPATION]
            running_in_out[world, b, RUNNING_DISSIPATION] = wp.float64(0.0)
            running_in_out[world, b, RUNNING_WORK] = wp.float64(0.0)
            running_in_out[world, b, RUNNING_STEP_DISSIPATION] = wp.float64(0.0)
            b += lanes
        reduced = reduce_seven(Seven(energy, work, elastic, dissipated, close_dissipated, close_work, worst))
        energy = reduced[0]
        work = reduced[1]
        elastic = reduced[2]
        dissipated = reduced[3]
        close_dissipated = reduced[4]
        close_work = reduced[5]
        worst = reduced[6]
        if lane == 0:
            # The world's rows read first, all at once, then the verdict in registers, then the writes: one memory
            # latency instead of a chain of ~30 reads behind writes that might alias them (the gather of a 64² cloth
            # took 21 µs a frame on an H200, most of it lane 0 waiting on that chain).
            carry_dissipated = carry_in_out[world, CARRY_DISSIPATION]
            carry_work = carry_in_out[world, CARRY_WORK]
            total = work_total_in_out[world]
            reference = balance_in_out[world, BALANCE_REFERENCE]
            balance_work = balance_in_out[world, BALANCE_WORK]
            peak = balance_in_out[world, BALANCE_PEAK]
            rebase = balance_in_out[world, BALANCE_REBASE]
            taken = balance_in_out[world, BALANCE_DISSIPATION]
            last_energy = balance_in_out[world, BALANCE_ENERGY]
            excess = values_in_out[world, GUARD_EXCESS]
            budget_peak = values_in_out[world, GUARD_BUDGET]
            tear = limits[world, GUARD_LIMIT_STRAIN]
            runaway = limits[world, GUARD_LIMIT_KINETIC_ENERGY]
            stop_world = limits[world, GUARD_STOP_WORLD]
            factor = limits[world, GUARD_WORK_FACTOR]
            tolerance = limits[world, GUARD_BALANCE_TOLERANCE]
            floor = limits[world, GUARD_BALANCE_FLOOR]
            nonfinite = status_in_out[world, GUARD_NONFINITE_PARTICLE]
            if wp.static(counted):  # the closing term: this span's share at its state, minus it opens the next
                left_dissipated = power_h * wp.float64(share_dampers) * close_dissipated
                left_work = power_h * wp.float64(share_work) * close_work
                if wp.static(dissipation):
                    dissipated += left_dissipated + carry_dissipated
                work += left_work + carry_work
                carry_in_out[world, CARRY_DISSIPATION] = -left_dissipated
                carry_in_out[world, CARRY_WORK] = -left_work
            if carry_only == 0:
                held = energy + elastic
                if wp.isfinite(work) and wp.isfinite(held) and wp.isfinite(dissipated):
                    # The balance: the check's work and dissipation added (re-based where asked), the energy beyond
                    # its budget and the budget's peak (a non-finite world's balance stays as it was: it stops).
                    total += wp.max(work, wp.float64(0.0))
                    balance_work += work
                    taken += dissipated
                    if rebase != wp.float64(0.0):
                        reference = held - balance_work
                        peak = held
                        taken = wp.float64(0.0)
                        rebase = wp.float64(0.0)
                    last_energy = held
                    budget = reference + balance_work
                    peak = wp.max(peak, budget)
                    excess = held - (budget - taken)
                    budget_peak = peak
                    work_total_in_out[world] = total
                    balance_in_out[world, BALANCE_REFERENCE] = reference
                    balance_in_out[world, BALANCE_WORK] = balance_work
                    balance_in_out[world, BALANCE_PEAK] = peak
                    balance_in_out[world, BALANCE_REBASE] = rebase
                    balance_in_out[world, BALANCE_DISSIPATION] = taken
                    balance_in_out[world, BALANCE_ENERGY] = last_energy
                # The verdict: the world's first failure latched with the check's substep (and with ``stop_world``
                # the world held: ``world_enabled`` 0), or the check's values cleared for the next.
                reason = 0
                if nonfinite != NO_PARTICLE or not wp.isfinite(energy):
                    reason = GUARD_NONFINITE
                elif worst > tear:
                    reason = GUARD_STRAIN
                elif energy > runaway + factor * total:
                    reason = GUARD_ENERGY
                elif tolerance > wp.float64(0.0) and excess > tolerance * wp.max(budget_peak, wp.float64(0.0)) + floor:
                    reason = GUARD_BALANCE
                values_in_out[world, GUARD_WORK] = work
                values_in_out[world, GUARD_BUDGET] = budget_peak
                if reason != 0:
                    values_in_out[world, GUARD_KINETIC_ENERGY] = energy
                    values_in_out[world, GUARD_ELASTIC_ENERGY] = elastic
                    values_in_out[world, GUARD_MAX_STRAIN] = worst
                    values_in_out[world, GUARD_EXCESS] = excess
                    status_in_out[world, GUARD_TRIPPED] = reason
                    status_in_out[world, GUARD_SUBSTEP] = substep
                    if stop_world != wp.float64(0.0):
                        world_enabled_in_out[world] = 0
                else:
                    values_in_out[world, GUARD_KINETIC_ENERGY] = wp.float64(0.0)
                    values_in_out[world, GUARD_ELASTIC_ENERGY] = wp.float64(0.0)
                    values_in_out[world, GUARD_MAX_STRAIN] = wp.float64(-1.0)
                    values_in_out[world, GUARD_EXCESS] = wp.float64(0.0)
                    status_in_out[world, GUARD_STRAIN_PARTICLE] = NO_PARTICLE
                    status_in_out[world, GUARD_STRAIN_ELEMENT] = NO_PARTICLE
                    status_in_out[world, GUARD_STRAIN_FAMILY] = NO_PARTICLE
        if carry_only != 0:
            return
        block_barrier()  # lane 0's verdict is seen by the world's lanes
        # A world that failed at this check (it was live when the check began: the early return above): the most
        # strained particle, element and family, found on the state the check measured, so that the record is complete
        # when the frame ends (the host may read it a frame later). A check that passes costs nothing here.
        if status_in_out[world, GUARD_TRIPPED] == 0:
            return
        largest = values_in_out[world, GUARD_MAX_STRAIN]
        if largest >= wp.float64(0.0):  # (the same for every lane of the block)
            # A strain within the rounding of the check's own (``STRAIN_MATCH``: the check's passes evaluate it in
            # other kernels, which on CUDA contract other multiply-adds), in three rounds so that the three entries
            # name one element: the smallest family, then its smallest element, then that element's smallest
            # particle.
            near = largest - wp.float64(STRAIN_MATCH) * (wp.float64(1.0) + largest)
            base = world * particle_count
            chosen_family = int(NO_PARTICLE)
            chosen_element = int(NO_PARTICLE)
            for level in range(3):  # the family, then its element, then that element's particle
                if level > 0:
                    block_barrier()  # the last round's atomics done
                    chosen_family = status_in_out[world, GUARD_STRAIN_FAMILY]
                    chosen_element = status_in_out[world, GUARD_STRAIN_ELEMENT]
                i = lane
                while i < particle_count:
                    strain, element, family = element_strain(world, i, base, particle_q[base + i], element_arrays,
                                                             particle_q)
                    if (wp.float64(strain) >= near and (level == 0 or family == chosen_family)
                            and (level < 2 or element == chosen_element)):
                        if level == 0:
                            wp.atomic_min(status_in_out, world, GUARD_STRAIN_FAMILY, family)
                        elif level == 1:
                            wp.atomic_min(status_in_out, world, GUARD_STRAIN_ELEMENT, element)
                        else:
                            wp.atomic_min(status_in_out, world, GUARD_STRAIN_PARTICLE, i)
                    i += lanes
            block_barrier()  # every lane's atomics done: the record is complete
        if lane == 0:  # the mirror: the record and the clock, then (fenced) the reason the host reads first
            k = int(1)
            while k < GUARD_INTS:
                mirror_out[world, k] = wp.float64(status_in_out[world, k])
                k += 1
            mirror_out[world, MIRROR_CLOCK] = clock
            system_fence()
            mirror_out[world, GUARD_TRIPPED] = wp.float64(status_in_out[world, GUARD_TRIPPED])

    @flat_kernel(module="unique", enable_backward=False, last=composed.last("element_arrays"))
    def gather(
        # Model:
        particle_count: int,
        element_arrays: Elements,
        # State in:
        particle_q: wp.array[vec3],
        clock: wp.array[wp.float64],  # the worlds' clocks [s]
        # Guards in (``gather_lanes``):
        partials: wp.array3d[wp.float64],
        energy_partials: wp.array2d[wp.float64],
        strain_partials: wp.array2d[wp.float64],
        power_partials: wp.array2d[wp.float64],
        substep: int,
        limits: wp.array2d[wp.float64],
        power_h: wp.float64,
        carry_only: int,
        # In/out:
        world_enabled_in_out: wp.array[wp.int32],
        status_in_out: wp.array2d[wp.int32],
        running_in_out: wp.array3d[wp.float64],
        values_in_out: wp.array2d[wp.float64],
        work_total_in_out: wp.array[wp.float64],
        balance_in_out: wp.array2d[wp.float64],
        carry_in_out: wp.array2d[wp.float64],
        # Out (the record's mirror):
        mirror_out: wp.array2d[wp.float64],
    ):
        """(``gather_lanes``.) Launched over [world, lanes] with ``block_dim`` = lanes (one lane on the CPU)."""
        world, lane = wp.tid()
        gather_lanes(world, lane, wp.block_dim(), particle_count, element_arrays, particle_q, partials,
                     energy_partials, strain_partials, power_partials, substep, limits, power_h, carry_only,
                     world_enabled_in_out, status_in_out, running_in_out, values_in_out, work_total_in_out,
                     balance_in_out, carry_in_out, clock[world], mirror_out)

    return measure, gather, drive, measure_lanes, drive_lanes, gather_lanes


def guard_lane_funcs(scalar: type, families: tuple, tiled: bool, external: bool, working: tuple = (),
                     power: int = POWER_RULE_NONE, power_features: ForceFeatures | None = None,
                     power_modes: tuple = (), dissipation: bool = False):
    """(measure_lanes, drive_lanes, gather_lanes): the bodies of :func:`guard_kernels`' kernels as functions of the
    lane, for a kernel that runs the check at its own end (the one-launch frame, ``kernels/frames.py``): the same
    arithmetic in the same order, given where the lane is (world, its block of the world, its lane there, the
    block's lanes)."""
    parts = _guard_parts(scalar, families, tiled, external, working, power, power_features, power_modes, dissipation)
    return parts[3], parts[4], parts[5]


@functools.cache
def guard_check_kernel(scalar: type, families: tuple, tiled: bool, external: bool, working: tuple = (),
                       power: int = POWER_RULE_NONE, power_features: ForceFeatures | None = None,
                       power_modes: tuple = (), dissipation: bool = False, walked=None, walked_power: bool = False,
                       bounds: tuple[int, int] | None = None):
    """``check_particles``: a check's passes over the particles in one launch over the check's grid, each lane over
    its particles in turn: the drives' work (``drive_lanes``), then ``measure_lanes`` (which moves the last check's
    positions on: the lane has read them for its drives first, as the two launches ordered it), then, with
    ``walked`` (the spec of a family with a gathered ``particle_energy`` hook), that family's energy, strain and
    (``walked_power``) dampers' power at the check, as ``guard_energy_kernel``'s walk writes them (its partials at
    ``walked_offset``): the arithmetic of the three kernels, three launches and three reads of the state fewer, as the
    one-launch frame's check does at its end. The arguments of :func:`guard_kernels`; ``bounds``:
    ``flatten.launch_bounds_option``."""
    vec3 = vec3_type(scalar)
    measure_lanes, drive_lanes, _ = guard_lane_funcs(scalar, families, tiled, external, working, power,
                                                     power_features, power_modes, dissipation)
    counted = power != POWER_RULE_NONE
    Sums = power_sums_funcs(scalar, counted and counts_work(power_features, power_modes)).type
    composed = elements(scalar, families)
    Elements = composed.arrays
    work_composed = elements(scalar, working)
    WorkElements = work_composed.arrays
    walks = walked is not None
    walk_funcs = walked.funcs(scalar) if walks else None
    WalkArrays = walk_funcs.arrays if walks else elements(scalar, ()).arrays
    walk_energy = walk_energy_func(scalar, walked) if walks else None
    write = energy_partials_func(tiled, walks and getattr(walk_funcs, "element_strain", None) is not None,
                                 walked_power)
    walk_idle = tuple(f"walk_arrays__{path}" for path in walk_funcs.idle) if walks else ("walk_arrays",)

    @flat_kernel(module="unique", enable_backward=False, **launch_bounds_option(bounds),
                 last=composed.last("element_arrays") + work_composed.last("work_arrays") + walk_idle)
    def check_particles(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        element_arrays: Elements,
        work_arrays: WorkElements,
        inputs: wp.array2d[scalar],
        # Control:
        particle_force_ext: wp.array[vec3],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Guards in (the lead λ [s]: ``measure``):
        lead: scalar,
        # Launch (the items between a lane's successive particles: ``linalg.reduce_stride``):
        stride: int,
        # The walked family (``measure``'s arguments come first, then these):
        walk_arrays: WalkArrays,
        walk_offset: int,
        # In/out:
        power_in_out: wp.array[Sums],
        previous_q_in_out: wp.array[vec3],
        previous_qd_in_out: wp.array[vec3],
        previous_load_in_out: wp.array[vec3],
        status_in_out: wp.array2d[wp.int32],
        partials_out: wp.array3d[wp.float64],
        energy_partials_out: wp.array2d[wp.float64],
        strain_partials_out: wp.array2d[wp.float64],
        power_partials_out: wp.array2d[wp.float64],
    ):
        world, block, lane = wp.tid()
        lanes = wp.block_dim()
        drive_lanes(world, block, lane, lanes, particle_count, particle_flags, element_arrays, inputs, particle_q,
                    particle_qd, previous_q_in_out, stride, previous_load_in_out, partials_out)
        measure_lanes(world, block, lane, lanes, particle_count, world_enabled, particle_flags, particle_mass,
                      element_arrays, work_arrays, inputs, particle_force_ext, particle_q, particle_qd, lead, stride,
                      power_in_out, previous_q_in_out, previous_qd_in_out, previous_load_in_out, status_in_out,
                      partials_out)
        if wp.static(walks):
            if status_in_out[world, GUARD_TRIPPED] == 0 and world_enabled[world] != 0:  # (the energy pass's skip)
                energy, worst, taken = walk_energy(world, block * lanes + lane, stride, particle_count,
                                                   world * particle_count, walk_arrays, inputs, particle_q,
                                                   particle_qd)
                write(world, block, lane, walk_offset, energy, worst, taken, energy_partials_out,
                      strain_partials_out, power_partials_out)

    return check_particles


#: Partial sums a thread of the check's fold adds in turn (``guard_fold_kernel``; Warp unrolls a loop of up to 16: at
#: 32 it runs as a loop, as measured).
FOLD_CHUNK = 32
#: A check folds where a world has more partial sums than this (``core/guards.py``): a 1024² cloth's ~7,000 folded
#: and gathered in 3.8 µs a substep against 5.0 gathered alone; a 64² cloth's ~900 in 2.8 against 0.9 (H200).
FOLD_ABOVE = 2048
#: The columns a fold adds, one thread each per chunk: ``measure``'s partial slots, the families' energy, strain and
#: dampers' power, and the running sums' energy and work slots.
FOLD_COLUMNS = PARTIAL_SLOTS + 3 + 3


@functools.cache
def guard_fold_kernel():
    """``fold``: the check's per-block partial sums (``measure``'s, the families' energy, strain and dampers' power,
    and the running sums of the substeps' passes, which it clears) added in chunks of FOLD_CHUNK blocks into arrays of
    the same layout, which ``gather`` then adds in place of the originals: a 1024² cloth's check leaves ~3,000 spring
    blocks and ~4,000 running blocks, which ``gather``'s one block per world walked in 84 µs on an H200, its lanes'
    reads in a serial chain. One thread per chunk and column adds its FOLD_CHUNK values in order (no barrier, no
    block reduction: a fold by block reductions, 18 of them a block one after another, took 25 µs at 64² and 75 µs
    at 1024²; this one 42 µs at 1024², with gather 19 µs against 84; H200), strains by their largest (none: -1).
    Launch over [world, chunks, FOLD_COLUMNS]."""

    @wp.kernel(module="unique", enable_backward=False)
    def fold(
        # Guards in (the per-block partials):
        partials: wp.array3d[wp.float64],
        energy_partials: wp.array2d[wp.float64],
        strain_partials: wp.array2d[wp.float64],
        power_partials: wp.array2d[wp.float64],
        # In/out (the substeps' running sums, their energy and work slots folded and cleared, the power kept):
        running_in_out: wp.array3d[wp.float64],
        # Out:
        folded_out: wp.array3d[wp.float64],
        folded_energy_out: wp.array2d[wp.float64],
        folded_strain_out: wp.array2d[wp.float64],
        folded_power_out: wp.array2d[wp.float64],
        folded_running_out: wp.array3d[wp.float64],
    ):
        world, chunk, column = wp.tid()
        first = chunk * FOLD_CHUNK
        if column < PARTIAL_SLOTS:
            count = partials.shape[1]
            strain = column == GUARD_MAX_STRAIN
            total = wp.float64(0.0)
            if strain:
                total = wp.float64(-1.0)
            for k in range(wp.static(FOLD_CHUNK)):
                if first + k < count:
                    value = partials[world, first + k, column]
                    if strain:
                        total = wp.max(total, value)
                    else:
                        total += value
            folded_out[world, chunk, column] = total
        elif column == PARTIAL_SLOTS + 1:  # the families' strain
            count = strain_partials.shape[1]
            total = wp.float64(-1.0)
            for k in range(wp.static(FOLD_CHUNK)):
                if first + k < count:
                    total = wp.max(total, strain_partials[world, first + k])
            folded_strain_out[world, chunk] = total
        elif column < PARTIAL_SLOTS + 3:  # their energy and dampers' power
            values = energy_partials
            if column == PARTIAL_SLOTS + 2:
                values = power_partials
            count = values.shape[1]
            total = wp.float64(0.0)
            for k in range(wp.static(FOLD_CHUNK)):
                if first + k < count:
                    total += values[world, first + k]
            if column == PARTIAL_SLOTS:
                folded_energy_out[world, chunk] = total
            else:
                folded_power_out[world, chunk] = total
        else:
            slot = RUNNING_DISSIPATION
            if column == PARTIAL_SLOTS + 4:
                slot = RUNNING_WORK
            elif column == PARTIAL_SLOTS + 5:
                slot = RUNNING_STEP_DISSIPATION
            count = running_in_out.shape[1]
            total = wp.float64(0.0)
            for k in range(wp.static(FOLD_CHUNK)):
                if first + k < count:
                    total += running_in_out[world, first + k, slot]
            folded_running_out[world, chunk, slot] = total
            for k in range(wp.static(FOLD_CHUNK)):
                if first + k < count:
                    running_in_out[world, first + k, slot] = wp.float64(0.0)

    return fold


@functools.cache
def family_energy_func(scalar: type, spec, power: bool = False):
    """``family_energy(world, first, stride, count, base, arrays, inputs, particle_q, particle_qd)``: over one
    family's elements ``first``, ``first + stride``, ... below ``count`` (``arrays`` its own struct, ``base`` the
    world's first particle), their elastic energy [J], their largest strain where the family measures it per element
    (its ``element_strain`` hook; -1: none) and with ``power`` the power its dampers take out at this state [W] (its
    ``dissipation`` hook); in float64, added in the elements' order. The element loop of :func:`guard_energy_kernel`'s
    pass and of the one-launch frame's check (:func:`energy_lanes_func`)."""
    vec3 = vec3_type(scalar)
    funcs = spec.funcs(scalar)
    Arrays = funcs.arrays
    energy_func = funcs.energy
    strain_func = getattr(funcs, "element_strain", None)
    strained = strain_func is not None
    power_func = funcs.dissipation if power else None

    @wp.func
    def family_energy(world: int, first: int, stride: int, count: int, base: int, arrays: Arrays,
                      inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        taken = wp.float64(0.0)
        element = first
        while element < count:  # every stride-th element from the lane's first
            energy += wp.float64(energy_func(world, element, base, arrays, inputs, particle_q))
            if wp.static(strained):
                worst = wp.max(worst, strain_func(world, element, base, arrays, particle_q))
            if wp.static(power):
                taken += wp.float64(power_func(world, element, base, arrays, inputs, particle_q, particle_qd))
            element += stride
        return energy, worst, taken

    return family_energy


@functools.cache
def walk_energy_func(scalar: type, spec):
    """``walk(world, first, stride, particle_count, base, arrays, inputs, particle_q, particle_qd)``: a family's
    elastic energy [J], largest strain [-] and dampers' power at this state [W] (float64) walked by particles with its
    gathered ``particle_energy`` hook (each element once, at one of its particles), every stride-th particle from
    ``first``: :func:`family_energy_func`'s sums in another order, its largest strain the same."""
    vec3 = vec3_type(scalar)
    funcs = spec.funcs(scalar)
    Arrays = funcs.arrays
    share = funcs.particle_energy

    @wp.func
    def walk(world: int, first: int, stride: int, particle_count: int, base: int, arrays: Arrays,
             inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
        energy = wp.float64(0.0)
        worst = wp.float64(-1.0)
        taken = wp.float64(0.0)
        i = first
        while i < particle_count:
            e, strain, p = share(world, i, base, particle_q[base + i], particle_qd[base + i], arrays, inputs,
                                 particle_q, particle_qd)
            energy += e
            worst = wp.max(worst, strain)
            taken += p
            i += stride
        return energy, worst, taken

    return walk


@functools.cache
def energy_partials_func(tiled: bool, strained: bool, power: bool):
    """``write(world, block, lane, offset, energy, worst, taken, partials_out, strain_partials_out,
    power_partials_out)``: a block's sum of its lanes' energy, their largest strain (``strained``) and the sum of their
    dampers' power (``power``), written by lane 0 at ``offset + block`` (every lane of the block calls it)."""
    Three, reduce_three = block_reduce_funcs(tiled, 2, 1)

    @wp.func
    def write(world: int, block: int, lane: int, offset: int, energy: wp.float64, worst: wp.float64,
              taken: wp.float64, partials_out: wp.array2d[wp.float64], strain_partials_out: wp.array2d[wp.float64],
              power_partials_out: wp.array2d[wp.float64]):
        # (one round for the three; an entry not counted keeps lane 0's own, as it did)
        reduced = reduce_three(Three(energy, taken, worst))
        energy = reduced[0]
        if wp.static(strained):
            worst = reduced[2]
        if wp.static(power):
            taken = reduced[1]
        if lane == 0:
            partials_out[world, offset + block] = energy
            if wp.static(strained):
                strain_partials_out[world, offset + block] = worst
            if wp.static(power):
                power_partials_out[world, offset + block] = taken

    return write


@functools.cache
def guard_energy_kernel(scalar: type, spec, tiled: bool, power: bool = False, walk: bool = False,
                        bounds: tuple[int, int] | None = None):
    """Kernel writing per-block sums of the elastic energy [J] of one family's elements in every world into
    ``partials[world, offset + block]``, and where the family has an ``element_strain`` hook the block's largest
    strain [-] into ``strain_partials[world, offset + block]`` (each element once, with the length its energy
    takes: ``measure`` then leaves the family out of its per-particle strain); with ``power`` (the family's dampers
    counted in the integrator's force pass, mode ``POWER_DAMPERS``) the power its dampers take out at this state [W]
    (its ``dissipation`` hook: the closing term of ``guard_kernels``) into ``power_partials[world, offset + block]``.
    Launch over ``reduce_launch_dim(worlds, element_count, lanes, REDUCE_PER_LANE)`` on CUDA (``stride``: that grid's
    ``reduce_stride``), one lane per block on the CPU. With ``walk`` the lanes walk the particles instead, over the
    check's particle grid (:func:`walk_energy_func`: a family with a gathered ``particle_energy`` hook; a grid cloth's
    pass then reads the state and the groups' values, not a spring table, which at 1024² was ~60 B for each of 6.3 M
    springs). ``bounds`` (threads a block, blocks a multiprocessor): ``flatten.launch_bounds_option``."""
    vec3 = vec3_type(scalar)
    funcs = spec.funcs(scalar)
    Arrays = funcs.arrays
    strained = getattr(funcs, "element_strain", None) is not None
    family_energy = family_energy_func(scalar, spec, power)
    walk_energy = walk_energy_func(scalar, spec) if walk else None
    write = energy_partials_func(tiled, strained, power)
    # A grid cloth's springs on the CPU (one thread a world): the vectorised pass over the grid's directions.
    grid = not walk and not tiled and isinstance(spec, SpringSpec) and grid_vectorised(spec)
    grid_energy = grid_energy_pass(scalar, spec, power) if grid else None
    prepare = spring_sweep_funcs(scalar, spec).prepare if grid else None
    # An element's energy reads its own entries, never the incidence table; a walk the incidence, never ``indices``.
    idle = tuple(f"arrays__{path}" for path in funcs.idle) if walk else ("arrays__incidence",)

    @flat_kernel(module="unique", enable_backward=False, last=idle, **launch_bounds_option(bounds))
    def element_energy_partials(
        # Model:
        particle_count: int,
        element_count: int,
        offset: int,
        world_enabled: wp.array[wp.int32],
        arrays: Arrays,
        inputs: wp.array2d[scalar],
        # Guards in:
        status: wp.array2d[wp.int32],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # Launch (the items between a lane's successive elements, or particles with ``walk``: ``reduce_stride``):
        stride: int,
        # Out:
        partials_out: wp.array2d[wp.float64],
        strain_partials_out: wp.array2d[wp.float64],
        power_partials_out: wp.array2d[wp.float64],
    ):
        world, block, lane = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        first = block * wp.block_dim() + lane
        if wp.static(walk):
            energy, worst, taken = walk_energy(world, first, stride, particle_count, world * particle_count, arrays,
                                               inputs, particle_q, particle_qd)
        elif wp.static(grid):  # (one lane a world: the whole family)
            prepared = prepare(world, arrays, inputs)
            terms = grid_energy(particle_q, particle_qd, world * particle_count, prepared.nx, prepared.ny,
                                prepared.rest, prepared.ke, prepared.kd)
            energy = terms[0]
            worst = terms[1]
            taken = terms[2]
        else:
            energy, worst, taken = family_energy(world, first, stride, element_count, world * particle_count, arrays,
                                                 inputs, particle_q, particle_qd)
        write(world, block, lane, offset, energy, worst, taken, partials_out, strain_partials_out, power_partials_out)

    return element_energy_partials


#: Whether the check's energy pass walks a family with a gathered ``particle_energy`` hook (gathered springs) by its
#: particles (``guard_energy_kernel``'s ``walk``) rather than by its elements, per device (``is_cuda``; ``Guard._walks``):
#: the CPU's one thread a world keeps the element pass (a grid cloth's vectorised one).
ENERGY_BY_PARTICLES = {True: True, False: False}
#: Whether a check's passes over the particles (the drives' work, ``measure``, a walked family's energy) run as one
#: launch (``guard_check_kernel``, ``Guard._fused_walk``), per device (``is_cuda``).
CHECK_FUSED = {True: True, False: False}
#: Blocks of the check's lanes a multiprocessor must hold in that pass and in the walk on CUDA (``__launch_bounds__``; ``None``: as
#: many registers as the compiler takes).
ENERGY_WALK_MIN_BLOCKS = 2


@functools.cache
def pushing_force_func(scalar: type, specs: tuple, modes: tuple):
    """``push(world, i, base, xi, vi, element_arrays, inputs, particle_q, particle_qd) -> force``: the force [N] on
    particle i of the families whose mode in ``modes`` (one ``forces.POWER_*`` per spec) is ``POWER_WORK`` (wind,
    handles: work from outside), the others not evaluated; ``element_arrays`` is ``elements(scalar, specs).arrays``."""
    vec3 = vec3_type(scalar)
    Elements = elements(scalar, specs).arrays
    if not specs:

        @wp.func
        def push_none(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Elements, inputs: wp.array2d[scalar],
                      particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
            return vec3(scalar(0.0))

        return push_none
    funcs = specs[0].funcs(scalar)
    pushes = modes[0] == POWER_WORK
    head_force = funcs.force

    @wp.func
    def push_head(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: funcs.arrays,
                  inputs: wp.array2d[scalar], particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
        if wp.static(pushes):
            return head_force(world, i, base, xi, vi, arrays, inputs, particle_q, particle_qd)
        return vec3(scalar(0.0))

    if len(specs) == 1:

        @wp.func
        def push_1(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Elements, inputs: wp.array2d[scalar],
                   particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
            return push_head(world, i, base, xi, vi, arrays.head, inputs, particle_q, particle_qd)

        return push_1
    rest = pushing_force_func(scalar, specs[1:], modes[1:])

    @wp.func
    def push_n(world: int, i: int, base: int, xi: vec3, vi: vec3, arrays: Elements, inputs: wp.array2d[scalar],
               particle_q: wp.array[vec3], particle_qd: wp.array[vec3]):
        return push_head(world, i, base, xi, vi, arrays.head, inputs, particle_q, particle_qd) + rest(
            world, i, base, xi, vi, arrays.tail, inputs, particle_q, particle_qd)

    return push_n


@functools.cache
def dissipation_rule_func(midpoint: bool):
    """``accumulate(running, world, block, power, h)``: a block's running dissipation over one substep.

    * trapezoidal (``midpoint`` off): D += h (P' + P) / 2, P the power at the step's end state and P' the one
      recorded after the previous substep (none yet: P only recorded);
    * midpoint (on): D += h P, P the power at the step's midpoint state ((x_n + x_{n+1}) / 2, (v_n + v_{n+1}) / 2;
      the caller passes it). Symplectic Euler's damper acts with v_n over a displacement h v_{n+1}: on a damped
      oscillator the trapezoid of c v² over-counts its loss by ~(ωh)²/4 of it (+6.7 % at ωh = 0.5, +33 % at 1,
      +129 % at 1.5), which the balance reads as energy created; c ((v_n + v_{n+1})/2)² closes it to 1e-3
      (``tests/test_dissipation.py``)."""

    @wp.func
    def accumulate(running: wp.array3d[wp.float64], world: int, block: int, power: wp.float64, h: wp.float64):
        if wp.static(midpoint):
            running[world, block, RUNNING_DISSIPATION] += h * power
        else:
            before = running[world, block, RUNNING_POWER]
            if wp.isfinite(before):
                running[world, block, RUNNING_DISSIPATION] += wp.float64(0.5) * h * (before + power)
        running[world, block, RUNNING_POWER] = power

    return accumulate


@functools.cache
def step_midpoint_kernel(scalar: type):
    """Kernel writing a substep's midpoint state, the means of the positions [m], velocities [m/s] and each
    world's time [s] at its start and end; one thread per particle of every world (as many as worlds at least)."""
    vec3 = vec3_type(scalar)

    @wp.kernel(module="unique", enable_backward=False)
    def step_midpoint(
        # State in (the step's start and end):
        start_q: wp.array[vec3],
        start_qd: wp.array[vec3],
        start_time: wp.array[wp.float64],
        end_q: wp.array[vec3],
        end_qd: wp.array[vec3],
        end_time: wp.array[wp.float64],
        # Out (the midpoint):
        q_out: wp.array[vec3],
        qd_out: wp.array[vec3],
        time_out: wp.array[wp.float64],
    ):
        i = wp.tid()
        q_out[i] = (start_q[i] + end_q[i]) * scalar(0.5)
        qd_out[i] = (start_qd[i] + end_qd[i]) * scalar(0.5)
        if i < time_out.shape[0]:
            time_out[i] = (start_time[i] + end_time[i]) * wp.float64(0.5)

    return step_midpoint


@functools.cache
def guard_dissipation_kernel(scalar: type, spec, tiled: bool, midpoint: bool = False):
    """Kernel adding to ``running[world, offset + block]`` the energy [J] one family's dampers took out over
    the last substep (the family's ``dissipation`` hook; trapezoidal rule, or with ``midpoint`` the power at
    the velocity passed, the step's mean: ``dissipation_rule_func``) after every substep. On CUDA
    (``tiled``) per-block sums, launched over ``reduce_launch_dim(worlds, element_count, lanes)``; on the CPU,
    where a kernel's threads run in turn anyway, one thread per world sums its elements in order (launched
    over ``worlds``, block 0): no per-element running sums to read and write."""
    vec3 = vec3_type(scalar)
    block_sum, _ = reduction_funcs(tiled)
    funcs = spec.funcs(scalar)
    Arrays = funcs.arrays
    power_func = funcs.dissipation
    accumulate = dissipation_rule_func(midpoint)

    # An element's damping power reads its own entries, never the incidence table.
    @flat_kernel(module="unique", enable_backward=False, last=("arrays__incidence",))
    def element_dissipation(
        # Model:
        particle_count: int,
        element_count: int,
        offset: int,
        h: wp.float64,
        world_enabled: wp.array[wp.int32],
        arrays: Arrays,
        inputs: wp.array2d[scalar],
        # Guards in:
        status: wp.array2d[wp.int32],
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out:
        running_in_out: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        base = world * particle_count
        power = wp.float64(0.0)
        if wp.static(tiled):
            element = block * wp.block_dim() + lane
            if element < element_count:
                power = wp.float64(power_func(world, element, base, arrays, inputs, particle_q, particle_qd))
            power = block_sum(power)
        else:
            for element in range(element_count):
                power += wp.float64(power_func(world, element, base, arrays, inputs, particle_q, particle_qd))
        if lane == 0:
            accumulate(running_in_out, world, offset + block, power, h)

    return element_dissipation


@functools.cache
def guard_damper_kernel(scalar: type, law, tiled: bool, rule: int):
    """Kernel closing the springs' dissipation counted by the scattered force pass (``spring_scatter_kernel``'s
    ``dissipation``) at a check: each spring's last step (its damper at the check's state against the value kept at
    the step's start, ``damper_step_func``), then the springs' running sums into ``running[world, offset + block,
    RUNNING_DISSIPATION]`` in a fixed order (per-block tile sums on CUDA, one thread per world in spring order on
    the CPU), the sums cleared, the values at the check's state kept, and the world marked counted (``skip``: the
    next step starts from this state, whose step the force pass must not count again). With ``h`` = 0 it only
    records the state (a restart). Launch over ``reduce_launch_dim(worlds, spring_count, lanes)`` on CUDA,
    ``(worlds, 1, 1)`` on the CPU."""
    vec3 = vec3_type(scalar)
    block_sum, _ = reduction_funcs(tiled)
    SpringArrays = spring_arrays_type(scalar, law.per_spring)
    damper_step = damper_step_func(scalar, rule)

    @wp.func
    def close(world: int, s: int, base: int, springs: SpringArrays, particle_q: wp.array[vec3],
              particle_qd: wp.array[vec3], h: wp.float64, damper: wp.array[scalar],
              dissipated: wp.array[wp.float64]) -> wp.float64:
        ends = springs.indices[s]
        d = particle_q[base + ends[1]] - particle_q[base + ends[0]]
        length = wp.length(d)
        n = d * wp.where(length > scalar(COINCIDENT_DISTANCE), scalar(1.0) / length, scalar(0.0))
        rate = wp.dot(particle_qd[base + ends[1]] - particle_qd[base + ends[0]], n)
        k = world * springs.indices.shape[0] + s
        kd = springs.damping[wp.min(world, springs.damping.shape[0] - 1), s]
        energy, value = damper_step(kd, rate, damper[k], wp.int32(0), h)
        total = dissipated[k] + energy
        dissipated[k] = wp.float64(0.0)
        damper[k] = value
        return total

    @flat_kernel(module="unique", enable_backward=False, last=("springs__incidence",))
    def spring_damper_close(
        # Model:
        particle_count: int,
        offset: int,
        h: wp.float64,
        springs: SpringArrays,
        # State in:
        particle_q: wp.array[vec3],
        particle_qd: wp.array[vec3],
        # In/out:
        damper_in_out: wp.array[scalar],
        dissipated_in_out: wp.array[wp.float64],
        skip_in_out: wp.array[wp.int32],
        running_in_out: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        base = world * particle_count
        spring_count = springs.indices.shape[0]
        total = wp.float64(0.0)
        if wp.static(tiled):
            s = block * wp.block_dim() + lane
            if s < spring_count:
                total = close(world, s, base, springs, particle_q, particle_qd, h, damper_in_out, dissipated_in_out)
            total = block_sum(total)
        else:
            for s in range(spring_count):
                total += close(world, s, base, springs, particle_q, particle_qd, h, damper_in_out, dissipated_in_out)
        if lane == 0:
            running_in_out[world, offset + block, RUNNING_DISSIPATION] += total
            if block == 0:
                skip_in_out[world] = 1

    return spring_damper_close


@functools.cache
def guard_skip_clear_kernel():
    """Kernel clearing each world's ``skip`` after the step that started from a check's state (``guard_damper_kernel``)."""

    @wp.kernel(module="unique", enable_backward=False)
    def skip_clear(
        # Out:
        skip_out: wp.array[wp.int32],
    ):
        skip_out[wp.tid()] = 0

    return skip_clear


@functools.cache
def guard_drag_kernel(scalar: type, tiled: bool, wind: bool, midpoint: bool = False, air_only: bool = False):
    """Kernel adding to ``running[world, block]`` the energy [J] viscous drag took out of the free particles
    over the last substep: power c v·(v - u) (u the air's velocity where the model has wind, else 0;
    trapezoidal rule, or midpoint as ``guard_dissipation_kernel``); with ``air_only``, only the wind's work with the sign of
    a loss, -c u·v: drag against moving air is drag against still air, -c v (a loss, c |v|², left out where the
    balance leaves D out), plus the steady push c u of the wind, a load whose work c u·v the balance must count
    wherever it is on. On CUDA per-block sums over
    ``reduce_launch_dim(worlds, particle_count, lanes)``, on the CPU one thread per world (as
    ``guard_dissipation_kernel``)."""
    vec3 = vec3_type(scalar)
    block_sum, _ = reduction_funcs(tiled)
    input_vec3 = input_funcs(scalar)
    accumulate = dissipation_rule_func(midpoint)

    @wp.func
    def drag_power(world: int, p: int, particle_flags: wp.array[wp.int32], inputs: wp.array2d[scalar],
                   particle_qd: wp.array[vec3]) -> wp.float64:
        if is_kinematic(particle_flags[p]):  # a kinematic particle moves as prescribed: drag does nothing
            return wp.float64(0.0)
        v = particle_qd[p]
        air = vec3(scalar(0.0))
        if wp.static(wind):
            air = input_vec3(inputs, world, INPUT_WIND)
        if wp.static(air_only):
            return wp.float64(-inputs[world, INPUT_DRAG] * wp.dot(air, v))
        return wp.float64(inputs[world, INPUT_DRAG] * wp.dot(v, v - air))

    @wp.kernel(module="unique", enable_backward=False)
    def drag_dissipation(
        # Model:
        particle_count: int,
        h: wp.float64,
        world_enabled: wp.array[wp.int32],
        particle_flags: wp.array[wp.int32],
        inputs: wp.array2d[scalar],
        # Guards in:
        status: wp.array2d[wp.int32],
        # State in:
        particle_qd: wp.array[vec3],
        # In/out:
        running_in_out: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        base = world * particle_count
        power = wp.float64(0.0)
        if wp.static(tiled):
            i = block * wp.block_dim() + lane
            if i < particle_count:
                power = drag_power(world, base + i, particle_flags, inputs, particle_qd)
            power = block_sum(power)
        else:
            for i in range(particle_count):
                power += drag_power(world, base + i, particle_flags, inputs, particle_qd)
        if lane == 0:
            accumulate(running_in_out, world, block, power, h)

    return drag_dissipation


@functools.cache
def guard_work_kernel(scalar: type, working: tuple, tiled: bool):
    """Kernel adding to ``running[world, block, RUNNING_WORK]`` the work [J] the families that do work from outside
    (``working``: their specs; wind, handles) did on the free particles over the last substep:
    Σᵢ Fᵢ(x̄, v̄) · (xᵢ' - xᵢ), the forces at the substep's midpoint state (x̄, v̄) = ((x + x')/2, (v + v')/2) over its
    displacement (midpoint rule, as ``dissipation_rule_func``). Their forces depend on the velocity (drag, a PD
    handle's damper) and the state (a handle's spring), so sampling them at the checks alone would alias as the
    dampers' power would; a constant force's work is exact. Launched as ``guard_drag_kernel`` (per-block sums on
    CUDA over ``reduce_launch_dim(worlds, particle_count, lanes)``, one thread per world on the CPU), into the
    drag's blocks' own slot."""
    vec3 = vec3_type(scalar)
    block_sum, _ = reduction_funcs(tiled)
    composed = elements(scalar, working)
    WorkElements = composed.arrays
    work_force = composed.force

    @wp.func
    def particle_work(world: int, i: int, base: int, particle_flags: wp.array[wp.int32], work_arrays: WorkElements,
                      inputs: wp.array2d[scalar], mid_q: wp.array[vec3], mid_qd: wp.array[vec3],
                      start_q: wp.array[vec3], end_q: wp.array[vec3]) -> wp.float64:
        p = base + i
        if is_kinematic(particle_flags[p]):  # a kinematic particle moves as prescribed: no work on it counts
            return wp.float64(0.0)
        force = work_force(world, i, base, mid_q[p], mid_qd[p], work_arrays, inputs, mid_q, mid_qd)
        return wp.float64(wp.dot(force, end_q[p] - start_q[p]))

    @flat_kernel(module="unique", enable_backward=False, last=composed.last("work_arrays"))
    def family_work(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        particle_flags: wp.array[wp.int32],
        work_arrays: WorkElements,
        inputs: wp.array2d[scalar],
        # Guards in:
        status: wp.array2d[wp.int32],
        # State in (the substep's midpoint, start and end):
        mid_q: wp.array[vec3],
        mid_qd: wp.array[vec3],
        start_q: wp.array[vec3],
        end_q: wp.array[vec3],
        # In/out:
        running_in_out: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        if status[world, GUARD_TRIPPED] != 0 or world_enabled[world] == 0:
            return
        base = world * particle_count
        work = wp.float64(0.0)
        if wp.static(tiled):
            i = block * wp.block_dim() + lane
            if i < particle_count:
                work = particle_work(world, i, base, particle_flags, work_arrays, inputs, mid_q, mid_qd, start_q,
                                     end_q)
            work = block_sum(work)
        else:
            for i in range(particle_count):
                work += particle_work(world, i, base, particle_flags, work_arrays, inputs, mid_q, mid_qd, start_q,
                                      end_q)
        if lane == 0:
            running_in_out[world, block, RUNNING_WORK] += work

    return family_work


@functools.cache
def guard_correction_kinetic_kernel(scalar: type, tiled: bool):
    """Kernel adding ``sign`` times each world's kinetic energy of its free particles [J] (float64) to
    ``running[world, first_block + block, RUNNING_WORK]``: launched with sign -1 before the passes that move particles
    outside the forces (the contacts' and self-collision's) and +1 after them, with
    :func:`guard_correction_energy_kernel`, it counts the energy those passes put in as work. Launch over a striding
    reducing grid [world_count, blocks, lanes] (``linalg.reduce_launch_dim``, ``stride`` its ``reduce_stride``) with
    ``block_dim`` = lanes: each lane sums its particles block · lanes + lane, then every stride-th, in order, a
    fixed-order tree joins the lanes (``block_sum``; one lane on the CPU) and the block adds its sum to its own slot:
    deterministic, no atomics (``gather`` adds the blocks' slots in order)."""
    vec3 = vec3_type(scalar)
    block_sum, _ = reduction_funcs(tiled)

    @wp.kernel(module="unique", enable_backward=False)
    def correction_kinetic(
        # Model:
        particle_count: int,
        world_enabled: wp.array[wp.int32],
        particle_flags: wp.array[wp.int32],
        particle_mass: wp.array2d[scalar],
        # Guards in:
        status: wp.array2d[wp.int32],
        first_block: int,
        stride: int,
        sign: wp.float64,
        # State in:
        particle_qd: wp.array[vec3],
        # Out:
        running_in_out: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        live = status[world, GUARD_TRIPPED] == 0 and world_enabled[world] != 0
        base = world * particle_count
        energy = wp.float64(0.0)
        i = block * wp.block_dim() + lane
        while live and i < particle_count:
            p = base + i
            v = particle_qd[p]
            if not is_kinematic(particle_flags[p]) and wp.isfinite(v):
                mass = wp.float64(particle_mass[wp.min(world, particle_mass.shape[0] - 1), i])
                energy += wp.float64(0.5) * mass * (wp.float64(v[0]) * wp.float64(v[0]) + wp.float64(v[1])
                                                     * wp.float64(v[1]) + wp.float64(v[2]) * wp.float64(v[2]))
            i += stride
        energy = block_sum(energy)  # (every lane reaches it: the tile needs them all)
        if lane == 0 and live:
            slot = first_block + block
            running_in_out[world, slot, RUNNING_WORK] = running_in_out[world, slot, RUNNING_WORK] + sign * energy

    return correction_kinetic


@functools.cache
def guard_correction_energy_kernel(scalar: type, spec, tiled: bool):
    """Kernel adding ``sign`` times each world's elastic energy of one family's elements [J] (its ``energy`` hook,
    float64) to ``running[world, first_block + block, RUNNING_WORK]`` (as :func:`guard_correction_kinetic_kernel`,
    launched the same way over the family's elements; the weight's work over the passes' displacement is in the
    checks' Σ m g·Δx already)."""
    vec3 = vec3_type(scalar)
    block_sum, _ = reduction_funcs(tiled)
    funcs = spec.funcs(scalar)
    Arrays = funcs.arrays
    energy_func = funcs.energy

    @flat_kernel(module="unique", enable_backward=False, last=("arrays__incidence",))
    def correction_energy(
        # Model:
        particle_count: int,
        element_count: int,
        world_enabled: wp.array[wp.int32],
        arrays: Arrays,
        inputs: wp.array2d[scalar],
        # Guards in:
        status: wp.array2d[wp.int32],
        first_block: int,
        stride: int,
        sign: wp.float64,
        # State in:
        particle_q: wp.array[vec3],
        # Out:
        running_in_out: wp.array3d[wp.float64],
    ):
        world, block, lane = wp.tid()
        live = status[world, GUARD_TRIPPED] == 0 and world_enabled[world] != 0
        energy = wp.float64(0.0)
        element = block * wp.block_dim() + lane
        while live and element < element_count:
            energy += wp.float64(energy_func(world, element, world * particle_count, arrays, inputs, particle_q))
            element += stride
        energy = block_sum(energy)  # (every lane reaches it: the tile needs them all)
        if lane == 0 and live:
            slot = first_block + block
            running_in_out[world, slot, RUNNING_WORK] = running_in_out[world, slot, RUNNING_WORK] + sign * energy

    return correction_energy


@functools.cache
def energy_lanes_func(scalar: type, specs: tuple, powers: tuple):
    """``energy_lanes(world, first, stride, base, counts, family, arrays, inputs, particle_q, particle_qd)``: what
    :func:`guard_energy_kernel`'s passes sum, over every family of ``specs`` at once (their arrays the one struct
    ``families.elements`` composes, ``counts[family + k]`` the k-th family's elements per world): the elastic energy
    [J] of the lane's elements ``first``, ``first + stride``, ... of each family, their largest strain where a family
    measures it per element (-1: none), and where ``powers[k]`` the power the k-th family's dampers take out at this
    state [W]; in float64. For the one-launch frame's check, whose lanes then add them per block
    (``kernels/frames.py``)."""
    vec3 = vec3_type(scalar)
    composed = elements(scalar, specs)
    Arrays = composed.arrays
    if not specs:
        @wp.func
        def no_energy(world: int, first: int, stride: int, base: int, counts: wp.array[wp.int32], family: int,
                      arrays: Arrays, inputs: wp.array2d[scalar], particle_q: wp.array[vec3],
                      particle_qd: wp.array[vec3]):
            return wp.float64(0.0), wp.float64(-1.0), wp.float64(0.0)

        return no_energy
    family_energy = family_energy_func(scalar, specs[0], bool(powers[0]))
    rest = energy_lanes_func(scalar, specs[1:], powers[1:]) if len(specs) > 1 else None
    more = rest is not None

    @wp.func
    def energy_lanes(world: int, first: int, stride: int, base: int, counts: wp.array[wp.int32], family: int,
                     arrays: Arrays, inputs: wp.array2d[scalar], particle_q: wp.array[vec3],
                     particle_qd: wp.array[vec3]):
        energy, worst, taken = family_energy(world, first, stride, counts[family], base, arrays.head, inputs,
                                             particle_q, particle_qd)
        if wp.static(more):
            e, w, t = rest(world, first, stride, base, counts, family + 1, arrays.tail, inputs, particle_q,
                           particle_qd)
            energy += e
            worst = wp.max(worst, w)
            taken += t
        return energy, worst, taken

    return energy_lanes


class FrameCheck(NamedTuple):
    """What the one-launch frame's check at its end is compiled for (``kernels/frames.py``): the arguments
    :func:`guard_lane_funcs` takes beyond the precision and the families (the step's), no family doing work
    from outside counted at the checks (wind, handles: those scenes check apart); and per family
    whether its dampers' power at the check's state is summed (``powers``, :func:`energy_lanes_func`)."""

    tiled: bool
    external: bool
    power: int
    power_features: ForceFeatures | None
    power_modes: tuple
    dissipation: bool
    powers: tuple


@functools.cache
def frame_check_arrays_type(scalar: type) -> type:
    """The struct of a guard's arrays that the one-launch frame's check reads and writes (the arguments of
    ``measure``, ``drive``, the energy passes and ``gather`` that the frame does not already take), in ``scalar``'s
    vectors: the worlds' enabled flags, the record, the last check's positions, velocities and loads, the check's
    per-block partial sums (one block of the frame each), the families' element counts per world, the limits, the
    running sums, the values, the work total, the balance and the carried closing term; the lead λ [s] and the
    closing term's step h [s]."""
    vec3 = vec3_type(scalar)
    fields = {
        "world_enabled": wp.array[wp.int32],
        "status": wp.array2d[wp.int32],
        "previous_q": wp.array[vec3],
        "previous_qd": wp.array[vec3],
        "previous_load": wp.array[vec3],
        "partials": wp.array3d[wp.float64],
        "energy_partials": wp.array2d[wp.float64],
        "strain_partials": wp.array2d[wp.float64],
        "power_partials": wp.array2d[wp.float64],
        "counts": wp.array[wp.int32],
        "limits": wp.array2d[wp.float64],
        "running": wp.array3d[wp.float64],
        "values": wp.array2d[wp.float64],
        "work_total": wp.array[wp.float64],
        "balance": wp.array2d[wp.float64],
        "carry": wp.array2d[wp.float64],
        "mirror": wp.array2d[wp.float64],
        "lead": scalar,
        "power_h": wp.float64,
    }
    return struct_type(f"FrameCheckArrays_{scalar.__name__}", fields)
