"""The CPU's symplectic Euler step: one thread per world sweeping its particles in order, each spring evaluated once.

Warp runs a CPU kernel's threads one after another on one core, so what makes the GPU's fused step fast (every
particle gathers its springs, each spring evaluated at both its ends, no atomics) doubles the CPU's arithmetic, and
the scatter (each spring once, then a pass of the update) pays a second launch, a force array's round trip and the
per-thread indexing of a (world, spring) launch. The sweep keeps the gather's data and its one launch and
evaluates each spring once: a world's particles are taken in order, and at particle i

* the forces of its springs to particles before it are complete in ``force_in_out[i]`` (added when those were
  swept), and those to particles after it are evaluated now (``springs.spring_sweep_funcs``'s ``forward``:
  i's share summed, the opposite added to the other particle's entry);
* so its force is complete: the other forces (gravity, drag, external, the other element families, gathered as in
  the fused step), the symplectic Euler update and the contacts follow at once.

The scratch entries are the states' force arrays (``state_in.particle_f`` for the forces, ``state_out.particle_f``
for the dampers' part, used only where the guard counts them: ``State``'s contract leaves both to the step), cleared
by the thread before its sweep and consumed by it: whatever they held before, the step is the same, and it leaves
those it used zero.

Per-world values (the springs' groups, rows and law values, the world's row of the input table) are read once per
world, not per particle. The results are the fused step's up to the order of the force's sums (float32 rounding).

With a grid layout of uniform groups and Hooke's law (``grid_vectorised``), the springs are evaluated before the
particles' loop by a vectorised C++ pass (``grid_spring_pass``) into the same scratch, and ``forward`` is not run.
The step runs with subnormal floats flushed to zero (``flush_subnormals_begin``, restored at its end): a cloth at
rest along an axis carries components of ~1e-16 m whose products (its dampers' forces, their power) are subnormal,
which the x86 core computes in microcode, ~100 cycles each; flushed, values below 1.2e-38 (float32) read as zero.
That halved the guarded sweep at 32² and 64² (bench/results/cpu_regression.md).
The guard's power sums are counted as in the fused step (``integrators.symplectic_euler_kernel``'s ``power``), the
springs' dampers' part swept alongside their force (``dampers_in_out``). The springs must be the first family
(``Model.families``), gathered; a one-thread-per-world launch is for the CPU only.
"""

import functools

import warp as wp

from .families import FORCE_KERNEL_OPTIONS, elements
from .forces import (
    POWER_DAMPERS,
    ForceFeatures,
    counts_work,
    particle_force_func,
    particle_power_func,
    power_sums_funcs,
)
from .inputs import INPUT_MAX_PARTICLE_FORCE
from .integrators import symplectic_euler_funcs
from .kinematics import is_kinematic
from .precision import vec3_type
from .response import project_all_func
from .shapes import ContactFeatures, shapes_type
from .spring_laws import COINCIDENT_DISTANCE, HOOKE
from .springs import SpringSpec, spring_sweep_funcs
from .flatten import flat_kernel

wp.set_module_options({"enable_backward": False})


def sweeps(features: ForceFeatures) -> bool:
    """Whether the sweep can take a step of ``features``: the springs first among the families, gathered."""
    return bool(features.families) and isinstance(features.families[0], SpringSpec) and features.families[0].gathered


#: Particles whose springs ahead ``grid_spring_pass`` evaluates at a time (their forces in arrays on the stack, so that
#: the loops that add them to both ends have no dependence between iterations).
GRID_CHUNK = 128


def grid_vectorised(spec: SpringSpec) -> bool:
    """Whether the springs' forces can be evaluated by ``grid_spring_pass``: a grid layout whose every slot is a
    uniform group's, no tail, Hooke's law with an axial damper (no biphasic knee, clamp, per-spring law or plasticity).
    Then the same springs are summed as by ``forward``, in another order."""
    head_slots, tail = spec.incidence
    return (spec.gathered and not tail and spec.law == HOOKE and bool(spec.grid_slots)
            and len(spec.slot_groups) == head_slots and all(g >= 0 for g in spec.slot_groups))


@wp.func_native("""
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
const unsigned int csr = __builtin_ia32_stmxcsr();
__builtin_ia32_ldmxcsr(csr | 0x8040u);
return (int)csr;
#else
return 0;
#endif
""")
def flush_subnormals_begin() -> int:
    """Flush subnormal floats to zero (x86's FTZ and DAZ bits) on this CPU thread until ``flush_subnormals_end``;
    returns the control word to restore (0 and nothing done elsewhere)."""
    ...


@wp.func_native("""
#if defined(__x86_64__) && !defined(__CUDA_ARCH__)
__builtin_ia32_ldmxcsr((unsigned int)saved);
#endif
""")
def flush_subnormals_end(saved: int):
    """Restore the control word ``flush_subnormals_begin`` returned."""
    ...


@functools.cache
def grid_spring_pass(scalar: type, spec: SpringSpec, dampers: bool):
    """``grid_springs(particle_q, particle_qd, base, nx, ny, rest, ke, kd, force_in_out, dampers_in_out)``: add the
    force [N] of every spring of one world's grid (``grid_vectorised``) to both its particles' entries of
    ``force_in_out`` (and, with ``dampers``, its damper's part to ``dampers_in_out``); ``rest``, ``ke``, ``kd``: each
    group's rest length [m], stiffness [N/m] and damping [N·s/m] (``spring_sweep_funcs``' ``prepare``).

    The world's particles are taken in chunks of ``GRID_CHUNK`` consecutive indices, and in each chunk the springs of
    every slot ahead (direction (dx, dy) with dy > 0, or dy = 0 and dx > 0) from those particles i to j = i + dy·nx + dx:
    one loop evaluates them into arrays on the stack (the pairs whose j wraps onto another row, a row's first or last
    |dx| columns, are then zeroed: no spring), two more add them to i's entries and subtract them from j's. Each loop
    reads and writes unit-strided, unaliased memory with no dependence between iterations, which clang vectorises
    (``-march=native``: 16 floats an instruction with AVX-512) where a Warp loop over a Warp array is not
    (performance_cpu.md §0: its range iterator and its arrays' run-time strides); a chunk's particles, and the rows
    two ahead, stay in the L1 cache across its directions. On the reference cloth the sweep's spring part went from
    ~45 to ~5 µs a substep at 32² (bench/results/cpu_regression.md). CPU only (C++; the kernel is launched on the CPU).
    """
    real = {wp.float32: "float", wp.float64: "double"}[scalar]
    vec3 = vec3_type(scalar)
    group_count = max(spec.slot_groups) + 1
    group_values = wp.types.vector(length=group_count, dtype=scalar)
    # One block per slot ahead, with its direction and group as constants.
    blocks = []
    for (dx, dy), g in zip(spec.grid_slots, spec.slot_groups):
        if not (dy > 0 or (dy == 0 and dx > 0)):
            continue
        blocks.append(DIRECTION.format(dx=dx, dy=dy, g=g))
    damper_decl = DAMPER_DECL if dampers else ""
    damper_eval = DAMPER_EVAL if dampers else ""
    damper_add = DAMPER_ADD if dampers else ""
    damper_sub = DAMPER_SUB if dampers else ""
    damper_zero = DAMPER_ZERO if dampers else ""
    body = "".join(block.replace("@DAMPER_EVAL@", damper_eval).replace("@DAMPER_ADD@", damper_add)
                   .replace("@DAMPER_SUB@", damper_sub).replace("@DAMPER_ZERO@", damper_zero) for block in blocks)
    snippet = (GRID_PASS.replace("@BODY@", body).replace("@DAMPER_DECL@", damper_decl)
               .replace("@CHUNK@", str(GRID_CHUNK)).replace("@EPS@", repr(COINCIDENT_DISTANCE))
               .replace("@REAL@", real))

    @wp.func_native(snippet)
    def grid_springs(particle_q: wp.array[vec3], particle_qd: wp.array[vec3], base: int, nx: int, ny: int,
                     rest: group_values, ke: group_values, kd: group_values, force_in_out: wp.array[vec3],
                     dampers_in_out: wp.array[vec3]):
        ...

    return grid_springs


# The C++ of ``grid_spring_pass`` (``real``: float or double; @...@: filled in per spec). X, V, F, D: the world's
# positions, velocities, forces and dampers' forces as flat arrays of x, y, z.
GRID_PASS = """
typedef @REAL@ real;
const real* __restrict__ X = (const real*)(particle_q.data + base);
const real* __restrict__ V = (const real*)(particle_qd.data + base);
real* __restrict__ F = (real*)(force_in_out.data + base);
real* __restrict__ D = (real*)(dampers_in_out.data + base);
(void)D;
real Tx[@CHUNK@], Ty[@CHUNK@], Tz[@CHUNK@];
@DAMPER_DECL@
const real eps = (real)@EPS@;
for (int a0 = 0; a0 < nx * ny; a0 += @CHUNK@) {
@BODY@
}
"""

DAMPER_DECL = "real Ux[@CHUNK@], Uy[@CHUNK@], Uz[@CHUNK@];"

DIRECTION = """
{{
  const int dx = {dx}, dy = {dy};
  const real L = rest.c[{g}], k = ke.c[{g}], kdamp = kd.c[{g}];
  const int bad_first = dx > 0 ? nx - dx : 0, bad_end = dx > 0 ? nx : -dx;
  const int offset = dy * nx + dx;
  const int i_first = dx < 0 ? -dx : 0, i_end = (ny - dy) * nx - (dx > 0 ? dx : 0);
  const int a = a0 > i_first ? a0 : i_first;
  const int e = (a0 + @CHUNK@) < i_end ? (a0 + @CHUNK@) : i_end;
  if (a < e) {{
    const int m = e - a;
    {{
      const real* __restrict__ xi = X + 3 * a;
      const real* __restrict__ xj = X + 3 * (a + offset);
      const real* __restrict__ vi = V + 3 * a;
      const real* __restrict__ vj = V + 3 * (a + offset);
      for (int c = 0; c < m; ++c) {{
        const real ex = xj[3 * c] - xi[3 * c], ey = xj[3 * c + 1] - xi[3 * c + 1], ez = xj[3 * c + 2] - xi[3 * c + 2];
        const real length = sqrt(ex * ex + ey * ey + ez * ez);
        const real inverse = length > eps ? (real)1 / length : (real)0;
        const real nx_ = ex * inverse, ny_ = ey * inverse, nz_ = ez * inverse;
        const real rate = (vj[3 * c] - vi[3 * c]) * nx_ + (vj[3 * c + 1] - vi[3 * c + 1]) * ny_
                        + (vj[3 * c + 2] - vi[3 * c + 2]) * nz_;
        const real magnitude = k * (length - L) + kdamp * rate;
        Tx[c] = nx_ * magnitude; Ty[c] = ny_ * magnitude; Tz[c] = nz_ * magnitude;
        @DAMPER_EVAL@
      }}
    }}
    // The pairs whose neighbour is off the grid (a row's last or first dx columns, wrapped onto the next row):
    // no spring, so no force.
    for (int r = a / nx; r * nx < a + m; ++r) {{
      for (int col = bad_first; col < bad_end; ++col) {{
        const int c = r * nx + col - a;
        if (c >= 0 && c < m) {{ Tx[c] = 0; Ty[c] = 0; Tz[c] = 0; @DAMPER_ZERO@ }}
      }}
    }}
    {{
      real* __restrict__ fi = F + 3 * a;
      for (int c = 0; c < m; ++c) {{ fi[3 * c] += Tx[c]; fi[3 * c + 1] += Ty[c]; fi[3 * c + 2] += Tz[c]; }}
    }}
    {{
      real* __restrict__ fj = F + 3 * (a + offset);
      for (int c = 0; c < m; ++c) {{ fj[3 * c] -= Tx[c]; fj[3 * c + 1] -= Ty[c]; fj[3 * c + 2] -= Tz[c]; }}
    }}
    @DAMPER_ADD@
    @DAMPER_SUB@
  }}
}}
"""

DAMPER_EVAL = "const real damping = kdamp * rate; Ux[c] = nx_ * damping; Uy[c] = ny_ * damping; Uz[c] = nz_ * damping;"
DAMPER_ZERO = "Ux[c] = 0; Uy[c] = 0; Uz[c] = 0;"
DAMPER_ADD = ("{ real* __restrict__ di = D + 3 * a;\n      for (int c = 0; c < m; ++c) "
              "{ di[3 * c] += Ux[c]; di[3 * c + 1] += Uy[c]; di[3 * c + 2] += Uz[c]; } }")
DAMPER_SUB = ("{ real* __restrict__ dj = D + 3 * (a + offset);\n      for (int c = 0; c < m; ++c) "
              "{ dj[3 * c] -= Ux[c]; dj[3 * c + 1] -= Uy[c]; dj[3 * c + 2] -= Uz[c]; } }")


@functools.cache
def symplectic_euler_sweep_kernel(scalar: type, features: ForceFeatures, contacts: ContactFeatures,
                                  power: tuple | None = None):
    """Symplectic Euler step of every world, one thread per world (module docstring): the arguments of
    ``integrators.symplectic_euler_kernel`` and the two scratch arrays (module docstring). Launch over
    ``world_count``."""
    if not sweeps(features):
        raise ValueError(f"the sweep needs the springs first among the families, gathered; got {features.families}")
    vec3 = vec3_type(scalar)
    Shapes = shapes_type(scalar)
    counted = power is not None
    springs_spec, others = features.families[0], features.families[1:]
    spring_dampers = counted and power[0] == POWER_DAMPERS
    _, prepare, forward = spring_sweep_funcs(scalar, springs_spec, spring_dampers)
    # The other forces as the fused step's ``particle_force`` has them, without the springs and the clamp (which
    # takes the whole force: below).
    rest = features._replace(families=others, clamp_particle_force=False)
    particle_force = particle_power_func(scalar, rest, power[1:]) if counted else particle_force_func(scalar, rest)
    sums = power_sums_funcs(scalar, counted and counts_work(features, power))
    Sums = sums.type
    pack = sums.pack
    composed = elements(scalar, features.families)
    Elements = composed.arrays
    NoElements = elements(scalar, ()).arrays
    has_others = bool(others)
    update = symplectic_euler_funcs(scalar)
    _, project_contacts = project_all_func(scalar, contacts)
    has_contacts = bool(contacts)
    grid = bool(springs_spec.grid_slots) and bool(springs_spec.slot_groups)
    # The grid's springs in a vectorised pass before the particles' loop (``grid_spring_pass``), else by ``forward``.
    vectorised = grid_vectorised(springs_spec)
    grid_springs = grid_spring_pass(scalar, springs_spec, spring_dampers) if vectorised else None

    @flat_kernel(module="unique", enable_backward=False, module_options=FORCE_KERNEL_OPTIONS,
                 last=contacts.idle() + composed.last("element_arrays"))
    def symplectic_euler_sweep(
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
        # In/out:
        power_in_out: wp.array[Sums],  # the guard's power sums [J] (read with ``power`` only)
        force_in_out: wp.array[vec3],  # scratch: the forces [N] of the springs to particles already swept
        dampers_in_out: wp.array[vec3],  # scratch: their dampers' part [N] (with the springs' dampers counted)
    ):
        world = wp.tid()
        saved = flush_subnormals_begin()
        base = world * particle_count
        k = base  # a while loop, which clang may vectorise (a range loop it never does: performance_cpu.md §0)
        while k < base + particle_count:
            force_in_out[k] = vec3(scalar(0.0))
            if wp.static(spring_dampers):
                dampers_in_out[k] = vec3(scalar(0.0))
            k += 1
        time_out[world] = time_in[world] + (wp.float64(dt) + wp.float64(dt_rest))
        h = dt
        springs = element_arrays.head
        prepared = prepare(world, springs, inputs)
        if wp.static(vectorised):
            grid_springs(particle_q_in, particle_qd_in, base, prepared.nx, prepared.ny, prepared.rest, prepared.ke,
                         prepared.kd, force_in_out, dampers_in_out)
        inv_mass_row = wp.min(world, particle_inv_mass.shape[0] - 1)
        row = int(0)
        column = int(0)
        for i in range(particle_count):
            p = base + i
            x = particle_q_in[p]
            v = particle_qd_in[p]
            springs_f = vec3(scalar(0.0))
            springs_d = vec3(scalar(0.0))
            if wp.static(not vectorised):
                springs_f, springs_d = forward(i, row, column, base, x, v, springs, prepared, particle_q_in,
                                               particle_qd_in, force_in_out, dampers_in_out)
            springs_f += force_in_out[p]
            force_in_out[p] = vec3(scalar(0.0))
            if wp.static(spring_dampers):
                springs_d += dampers_in_out[p]
                dampers_in_out[p] = vec3(scalar(0.0))
            if wp.static(grid and not vectorised):
                column += 1
                if column == prepared.nx:
                    column = 0
                    row += 1
            free = not is_kinematic(particle_flags[p])
            f = vec3(scalar(0.0))
            dampers = vec3(scalar(0.0))
            work = vec3(scalar(0.0))
            if wp.static(counted):
                if wp.static(has_others):
                    f, dampers, work = particle_force(world, i, base, x, v, free, particle_mass, element_arrays.tail,
                                                      inputs, particle_force_ext, particle_q_in, particle_qd_in)
                else:
                    f, dampers, work = particle_force(world, i, base, x, v, free, particle_mass, NoElements(), inputs,
                                                      particle_force_ext, particle_q_in, particle_qd_in)
                dampers += springs_d
            else:
                if wp.static(has_others):
                    f = particle_force(world, i, base, x, v, particle_mass, element_arrays.tail, inputs,
                                       particle_force_ext, particle_q_in, particle_qd_in)
                else:
                    f = particle_force(world, i, base, x, v, particle_mass, NoElements(), inputs, particle_force_ext,
                                       particle_q_in, particle_qd_in)
            f += springs_f
            if not free:  # moves on with its velocity; its elements' dampers: their share of the dampers' power
                particle_q_out[p] = x + h * v
                particle_qd_out[p] = v
                if wp.static(counted):
                    power_in_out[p] += pack(-h * wp.dot(dampers, v), scalar(0.0))
                continue
            if wp.static(features.clamp_particle_force):
                max_force = inputs[world, INPUT_MAX_PARTICLE_FORCE]
                magnitude = wp.length(f)
                if magnitude > max_force:
                    f = f * (max_force / magnitude)
            inv_mass = particle_inv_mass[inv_mass_row, i]
            v_start = v
            x, v = update(x, v, f, inv_mass, h)
            if wp.static(counted):
                mean = (v_start + v) * (scalar(0.5) * h)
                power_in_out[p] += pack(-wp.dot(dampers, mean), wp.dot(work, mean))
            if wp.static(has_contacts):
                x, v = project_contacts(world, p, x, v, particle_radius[i], h, shapes, inputs)
            particle_q_out[p] = x
            particle_qd_out[p] = v
        flush_subnormals_end(saved)

    return symplectic_euler_sweep
