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

The guard's power sums are counted as in the fused step (``integrators.symplectic_euler_kernel``'s ``power``), the
springs' dampers' part swept alongside their force (``dampers_in_out``); the step adds them up over the world in
float64 and adds the total to the world's first entry once (the guard's check sums a world's entries; a read, add and
write of every particle's entry every substep cost about 1 µs of an 11 µs substep at 32²: the dissipation's sums
5.3-5.9 against 4.2-5.1 µs in alternating runs, bench/results/guard_cost_cpu.md). The force sweep
(``forces_only``) leaves them per particle, as ``forces.eval_forces_kernel`` does. The springs must be the first family
(``Model.families``), gathered; a one-thread-per-world launch is for the CPU only.

With a grid layout of uniform groups and Hooke's law (``grid_vectorised``), the springs are evaluated before the
particles' loop by a vectorised C++ pass (``grid_spring_pass``: ``forward``'s forces and sums, bit for bit) into the
same scratch, and ``forward`` is not run. The step runs with subnormal floats flushed to zero
(``flush_subnormals_begin``, restored at its end): a cloth at rest along an axis carries components of ~1e-16 m whose
products (its dampers' forces, their power) are subnormal, which the x86 core computes in microcode; flushed, values
below 1.2e-38 (float32) read as zero. Replaying one state of the reference cloth, that took the guarded sweep from 28
to 17 µs at 32²; in frame throughput the difference was within the noise (bench/results/cpu_regression.md).
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
GRID_CHUNK = 64


def grid_vectorised(spec: SpringSpec) -> bool:
    """Whether the springs' forces can be evaluated by ``grid_spring_pass``: a grid layout whose every slot is a
    uniform group's, no tail, Hooke's law with an axial damper (no biphasic knee, clamp, per-spring law or plasticity).
    Then the same springs are summed as by ``forward``, in the same order."""
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


def _grid_native_types(scalar: type, spec: SpringSpec) -> tuple:
    """What the grid's native passes are written for: the C++ scalar type, the vector type, the groups' values type
    and the (dx, dy, group) of each slot ahead (a later row, or later on the same one)."""
    real = {wp.float32: "float", wp.float64: "double"}[scalar]
    group_values = wp.types.vector(length=max(spec.slot_groups) + 1, dtype=scalar)
    ahead = [(dx, dy, g) for (dx, dy), g in zip(spec.grid_slots, spec.slot_groups) if dy > 0 or (dy == 0 and dx > 0)]
    return real, vec3_type(scalar), group_values, tuple(ahead)


def _grid_source_head(real: str, ahead: tuple) -> str:
    """The C++ both grid passes begin with: the scalar and vector types, the world's positions ``X`` and velocities
    ``V`` as flat arrays, the coincidence distance and each slot ahead's (dx, dy) in ``DX``, ``DY``."""
    return f"""
typedef {real} real;
typedef wp::vec_t<3, real> v3;
const real* __restrict__ X = (const real*)(particle_q.data + base);
const real* __restrict__ V = (const real*)(particle_qd.data + base);
(void)V;
const real eps = (real){COINCIDENT_DISTANCE!r};
const int DX[{len(ahead)}] = {{{", ".join(str(dx) for dx, _, _ in ahead)}}};
const int DY[{len(ahead)}] = {{{", ".join(str(dy) for _, dy, _ in ahead)}}};"""


@functools.cache
def grid_spring_pass(scalar: type, spec: SpringSpec, dampers: bool):
    """``grid_springs(particle_q, particle_qd, base, nx, ny, rest, ke, kd, force_in_out, dampers_in_out)``: write each
    particle's force [N] of one world's grid springs (``grid_vectorised``) into ``force_in_out`` (zero on entry) and,
    with ``dampers``, their dampers' part into ``dampers_in_out``; ``rest``, ``ke``, ``kd``: each group's rest length
    [m], stiffness [N/m] and damping [N·s/m] (``spring_sweep_funcs``' ``prepare``).

    The world's particles are taken in chunks of ``GRID_CHUNK`` consecutive indices. In a chunk, the springs of every
    slot ahead (direction (dx, dy) with dy > 0, or dy = 0 and dx > 0) from those particles i to j = i + dy·nx + dx are
    evaluated by one loop per direction into arrays on the stack (the pairs whose j wraps onto another row, a row's
    first or last |dx| columns, then zeroed: no spring) and summed into the chunk's own forces; then subtracted from
    their other ends j, direction by direction in decreasing dy·nx + dx; then each particle of the chunk takes its
    own springs' sum plus what the earlier particles' springs left it. Each loop reads and writes unit-strided,
    unaliased memory with no dependence between iterations, which clang vectorises (``-march=native``: 16 floats an
    instruction with AVX-512) where a Warp loop over a Warp array is not (performance_cpu.md §0).

    A spring's force is computed by Warp's own vector functions in ``spring_force``'s order, and the sums are made in
    ``forward``'s order (a particle's springs ahead in slot order, then those of the particles before it in their
    order), so the result is ``forward``'s bit for bit: the grid layout steps as the table layout does
    (tests/test_grid_layout.py). CPU only (C++; the kernel is launched on the CPU).
    """
    real, vec3, group_values, ahead = _grid_native_types(scalar, spec)

    @wp.func_native(grid_pass_source(real, ahead, dampers))
    def grid_springs(particle_q: wp.array[vec3], particle_qd: wp.array[vec3], base: int, nx: int, ny: int,
                     rest: group_values, ke: group_values, kd: group_values, force_in_out: wp.array[vec3],
                     dampers_in_out: wp.array[vec3]):
        ...

    return grid_springs


def grid_pass_source(real: str, ahead: tuple, dampers: bool) -> str:
    """The C++ of ``grid_spring_pass``: ``real`` the scalar type, ``ahead`` the (dx, dy, group) of each slot ahead in
    slot order, ``dampers`` whether the dampers' part is summed too."""
    count, chunk = len(ahead), GRID_CHUNK
    arrays = ("T", "U") if dampers else ("T",)  # per direction: the springs' forces (T) and dampers' parts (U)
    sums = ("A", "B") if dampers else ("A",)  # the chunk's own springs' sums of T and U
    targets = {"T": "F", "U": "D", "A": "F", "B": "D"}
    out = [_grid_source_head(real, ahead) + f"""
real* __restrict__ F = (real*)(force_in_out.data + base);
real* __restrict__ D = (real*)(dampers_in_out.data + base);
(void)D;
const int n = nx * ny;
int offset[{count}], first[{count}], last[{count}], order[{count}], start[{count}], size[{count}];
for (int d = 0; d < {count}; ++d) {{
  offset[d] = DY[d] * nx + DX[d];
  first[d] = DX[d] < 0 ? -DX[d] : 0;
  last[d] = (ny - DY[d]) * nx - (DX[d] > 0 ? DX[d] : 0);
  order[d] = d;
}}
// The subtractions in decreasing offset: each particle gets those of the particles before it in their order.
for (int p = 1; p < {count}; ++p) {{
  for (int q = p; q > 0 && offset[order[q - 1]] < offset[order[q]]; --q) {{
    const int t = order[q]; order[q] = order[q - 1]; order[q - 1] = t;
  }}
}}
"""]
    out += [f"real {a}[{count}][3][{chunk}];" for a in arrays] + [f"real {a}[3][{chunk}];" for a in sums]
    out.append(f"""
for (int a0 = 0; a0 < n; a0 += {chunk}) {{
  const int m0 = n - a0 < {chunk} ? n - a0 : {chunk};
  for (int k = 0; k < 3; ++k) for (int c = 0; c < {chunk}; ++c) {{ {" ".join(f"{a}[k][c] = 0;" for a in sums)} }}""")
    for d, (dx, dy, g) in enumerate(ahead):
        bad_first, bad_end = (f"nx - {dx}", "nx") if dx > 0 else ("0", str(-dx))
        damper = ("const v3 u = wp::mul(normal, wp::mul(kdamp, wp::dot(wp::sub(qj, qi), normal)));\n"
                  f"      U[{d}][0][s + c] = u.c[0]; U[{d}][1][s + c] = u.c[1]; U[{d}][2][s + c] = u.c[2];")
        out.append(f"""
  {{
    const int a = a0 > first[{d}] ? a0 : first[{d}];
    const int e = a0 + {chunk} < last[{d}] ? a0 + {chunk} : last[{d}];
    const int s = a - a0, m = e > a ? e - a : 0;
    start[{d}] = s; size[{d}] = m;
    const real L = rest.c[{g}], k = ke.c[{g}], kdamp = kd.c[{g}];
    const real* __restrict__ xi = X + 3 * a;
    const real* __restrict__ xj = X + 3 * (a + offset[{d}]);
    const real* __restrict__ vi = V + 3 * a;
    const real* __restrict__ vj = V + 3 * (a + offset[{d}]);
    for (int c = 0; c < m; ++c) {{
      const v3 pi(xi[3 * c], xi[3 * c + 1], xi[3 * c + 2]), pj(xj[3 * c], xj[3 * c + 1], xj[3 * c + 2]);
      const v3 qi(vi[3 * c], vi[3 * c + 1], vi[3 * c + 2]), qj(vj[3 * c], vj[3 * c + 1], vj[3 * c + 2]);
      const v3 delta = wp::sub(pj, pi);
      const real length = wp::length(delta);
      const v3 normal = wp::mul(delta, wp::where(length > eps, wp::div((real)1, length), (real)0));
      const real magnitude = wp::add(wp::mul(k, wp::sub(length, L)),
                                     wp::mul(kdamp, wp::dot(wp::sub(qj, qi), normal)));
      const v3 f = wp::mul(normal, magnitude);
      T[{d}][0][s + c] = f.c[0]; T[{d}][1][s + c] = f.c[1]; T[{d}][2][s + c] = f.c[2];
      {damper if dampers else ""}
    }}
    // The pairs whose neighbour is off the grid (wrapped onto the next row): no spring, no force.
    for (int r = a / nx; r * nx < e; ++r) {{
      for (int col = {bad_first}; col < {bad_end}; ++col) {{
        const int c = r * nx + col - a;
        if (c >= 0 && c < m) {{ {" ".join(f"{x}[{d}][{k}][s + c] = 0;" for x in arrays for k in range(3))} }}
      }}
    }}
    for (int c = s; c < s + m; ++c) {{
      {" ".join(f"{y}[{k}][c] += {x}[{d}][{k}][c];" for x, y in zip(arrays, sums) for k in range(3))}
    }}
  }}""")
    subtract = "\n".join(f"""
    {{
      real* __restrict__ out = {targets[x]} + 3 * (a0 + s + offset[d]);
      for (int c = 0; c < m; ++c) {{
        out[3 * c] -= {x}[d][0][s + c]; out[3 * c + 1] -= {x}[d][1][s + c]; out[3 * c + 2] -= {x}[d][2][s + c];
      }}
    }}""" for x in arrays)
    finish = "\n".join(f"""
  {{
    real* __restrict__ own = {targets[y]} + 3 * a0;
    for (int c = 0; c < m0; ++c) {{
      own[3 * c] = {y}[0][c] + own[3 * c]; own[3 * c + 1] = {y}[1][c] + own[3 * c + 1];
      own[3 * c + 2] = {y}[2][c] + own[3 * c + 2];
    }}
  }}""" for y in sums)
    out.append(f"""
  for (int o = 0; o < {count}; ++o) {{
    const int d = order[o], s = start[d], m = size[d];{subtract}
  }}{finish}
}}
""")
    return "\n".join(out)


@functools.cache
def grid_energy_pass(scalar: type, spec: SpringSpec, power: bool):
    """``grid_energy(particle_q, particle_qd, base, nx, ny, rest, ke, kd) -> vec3d``: over one world's grid springs
    (``grid_vectorised``), their elastic energy [J] ½ ke (|d| - L)², their largest strain |d|/L - 1 and with ``power``
    the power [W] their dampers take out, kd ((vj - vi)·d̂)²; each spring once, in the model's precision as the
    guard's energy pass evaluates it (``springs.spring_funcs``' energy, ``element_strain`` and ``dissipation``
    hooks), added up in float64 direction by direction and row by row (the pass's own order). ``rest``, ``ke``,
    ``kd``: each group's values (``spring_sweep_funcs``' ``prepare``).

    The guard's energy pass walks a family's elements one at a time, reading its indices and values per spring; for a
    grid cloth this pass walks each direction's springs row by row over unit-strided positions, in chunks (the layout
    ``grid_spring_pass`` uses for the forces): 76 → 21.6 µs a check of a 32² cloth (bench/results/guard_cost_cpu.md).
    CPU only."""
    real, vec3, group_values, ahead = _grid_native_types(scalar, spec)

    @wp.func_native(grid_energy_source(real, ahead, power))
    def grid_energy(particle_q: wp.array[vec3], particle_qd: wp.array[vec3], base: int, nx: int, ny: int,
                    rest: group_values, ke: group_values, kd: group_values) -> wp.vec3d:
        ...

    return grid_energy


def grid_energy_source(real: str, ahead: tuple, power: bool) -> str:
    """The C++ of ``grid_energy_pass``: ``real`` the scalar type, ``ahead`` the (dx, dy, group) of each slot ahead,
    ``power`` whether the dampers' power is summed too."""
    count, chunk = len(ahead), GRID_CHUNK
    damper = """
        const real inverse = length > eps ? (real)1 / length : (real)0;
        const v3 normal = wp::mul(delta, inverse);
        const v3 qi(vi[3 * c], vi[3 * c + 1], vi[3 * c + 2]), qj(vj[3 * c], vj[3 * c + 1], vj[3 * c + 2]);
        const real rate = wp::dot(wp::sub(qj, qi), normal);
        P[c - c0 - a] = kdamp * rate * rate;""" if power else ""
    add_power = "\n        p0 += (double)P[c];" if power else ""
    add_power4 = ("\n        p0 += (double)P[c]; p1 += (double)P[c + 1]; p2 += (double)P[c + 2]; "
                  "p3 += (double)P[c + 3];") if power else ""
    add_power_total = "\n      taken += (p0 + p1) + (p2 + p3);" if power else ""
    return _grid_source_head(real, ahead) + f"""
const int G[{count}] = {{{", ".join(str(g) for _, _, g in ahead)}}};
real E[{chunk}], S[{chunk}], P[{chunk}];
(void)P;
double energy = 0.0, strain = -1.0, taken = 0.0;
for (int d = 0; d < {count}; ++d) {{
  const int dx = DX[d], dy = DY[d], offset = dy * nx + dx;
  const real L = rest.c[G[d]], k = ke.c[G[d]], kdamp = kd.c[G[d]];
  (void)kdamp;
  const int c0 = dx < 0 ? -dx : 0, c1 = dx > 0 ? nx - dx : nx;
  for (int r = 0; r + dy < ny; ++r) {{
    const real* __restrict__ xi = X + 3 * (r * nx);
    const real* __restrict__ xj = X + 3 * (r * nx + offset);
    const real* __restrict__ vi = V + 3 * (r * nx);
    const real* __restrict__ vj = V + 3 * (r * nx + offset);
    (void)vi; (void)vj;
    for (int a = 0; c0 + a < c1; a += {chunk}) {{
      const int m = c1 - c0 - a < {chunk} ? c1 - c0 - a : {chunk};
      for (int c = c0 + a; c < c0 + a + m; ++c) {{
        const v3 pi(xi[3 * c], xi[3 * c + 1], xi[3 * c + 2]), pj(xj[3 * c], xj[3 * c + 1], xj[3 * c + 2]);
        const v3 delta = wp::sub(pj, pi);
        const real length = wp::length(delta);
        const real stretch = length - L;
        E[c - c0 - a] = (real)0.5 * k * stretch * stretch;
        S[c - c0 - a] = length / L;{damper}
      }}
      // Four running sums a chunk, each in a register of its own (no chain of dependent additions), then added in
      // a fixed order; the largest strain likewise (a maximum is exact in any order).
      double e0 = 0.0, e1 = 0.0, e2 = 0.0, e3 = 0.0, p0 = 0.0, p1 = 0.0, p2 = 0.0, p3 = 0.0;
      real w0 = S[0], w1 = S[0], w2 = S[0], w3 = S[0];
      int c = 0;
      for (; c + 4 <= m; c += 4) {{
        e0 += (double)E[c]; e1 += (double)E[c + 1]; e2 += (double)E[c + 2]; e3 += (double)E[c + 3];
        w0 = S[c] > w0 ? S[c] : w0; w1 = S[c + 1] > w1 ? S[c + 1] : w1;
        w2 = S[c + 2] > w2 ? S[c + 2] : w2; w3 = S[c + 3] > w3 ? S[c + 3] : w3;{add_power4}
      }}
      for (; c < m; ++c) {{
        e0 += (double)E[c];
        w0 = S[c] > w0 ? S[c] : w0;{add_power}
      }}
      (void)p0; (void)p1; (void)p2; (void)p3;
      energy += (e0 + e1) + (e2 + e3);
      w0 = w1 > w0 ? w1 : w0; w2 = w3 > w2 ? w3 : w2; w0 = w2 > w0 ? w2 : w0;
      strain = (double)w0 - 1.0 > strain ? (double)w0 - 1.0 : strain;{add_power_total}
    }}
  }}
}}
return wp::vec_t<3, double>(energy, strain, taken);
"""

@functools.cache
def symplectic_euler_sweep_kernel(scalar: type, features: ForceFeatures, contacts: ContactFeatures,
                                  power: tuple | None = None, forces_only: bool = False):
    """Symplectic Euler step of every world, one thread per world (module docstring): the arguments of
    ``integrators.symplectic_euler_kernel`` and the two scratch arrays (module docstring). Launch over
    ``world_count``. With ``forces_only`` (no contacts) the sweep evaluates the forces alone: each particle's total
    force [N] (``forces.eval_forces_kernel``'s, summed in the sweep's order) into ``force_in_out`` (the output:
    whatever it held is overwritten), and with ``power`` h times the power its dampers take out and the loads from
    outside put in at this state added to its power sums (h = ``dt``: ``eval_forces_kernel``'s rule), nothing else
    written: the CPU's force evaluation for the other integrators."""
    if not sweeps(features):
        raise ValueError(f"the sweep needs the springs first among the families, gathered; got {features.families}")
    if forces_only and contacts:
        raise ValueError("a sweep of the forces alone resolves no contact")
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
        if wp.static(not forces_only):
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
        taken = wp.float64(0.0)  # the world's power sums over the sweep (with ``power``): one entry, once a step
        worked = wp.float64(0.0)
        for i in range(particle_count):
            p = base + i
            x = particle_q_in[p]
            v = particle_qd_in[p]
            springs_f = force_in_out[p]  # the grid pass's sum: its own springs' and those before it
            springs_d = vec3(scalar(0.0))
            if wp.static(spring_dampers):
                springs_d = dampers_in_out[p]
            if wp.static(not vectorised):
                springs_f, springs_d = forward(i, row, column, base, x, v, springs, prepared, particle_q_in,
                                               particle_qd_in, force_in_out, dampers_in_out)
                springs_f += force_in_out[p]
                if wp.static(spring_dampers):
                    springs_d += dampers_in_out[p]
            if wp.static(not forces_only):
                force_in_out[p] = vec3(scalar(0.0))
            if wp.static(spring_dampers):
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
            if wp.static(forces_only):  # every particle's force, kinematic or not (the clamp as eval_forces has it:
                # not where the power is counted, which the guard does not do under the clamp)
                if wp.static(features.clamp_particle_force and not counted):
                    max_force = inputs[world, INPUT_MAX_PARTICLE_FORCE]
                    magnitude = wp.length(f)
                    if magnitude > max_force:
                        f = f * (max_force / magnitude)
                force_in_out[p] = f
                if wp.static(counted):  # (per particle: the force evaluation's sums, as ``eval_forces`` leaves them)
                    power_in_out[p] += pack(-h * wp.dot(dampers, v), h * wp.dot(work, v))
                continue
            if not free:  # moves on with its velocity; its elements' dampers: their share of the dampers' power
                particle_q_out[p] = x + h * v
                particle_qd_out[p] = v
                if wp.static(counted):
                    taken += wp.float64(-h * wp.dot(dampers, v))
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
                taken += wp.float64(-wp.dot(dampers, mean))
                worked += wp.float64(wp.dot(work, mean))
            if wp.static(has_contacts):
                x, v = project_contacts(world, p, x, v, particle_radius[i], h, shapes, inputs)
            particle_q_out[p] = x
            particle_qd_out[p] = v
        if wp.static(counted and not forces_only):  # (the check sums a world's entries: its first carries the step's)
            if particle_count > 0:
                power_in_out[base] += pack(scalar(taken), scalar(worked))
        flush_subnormals_end(saved)

    return symplectic_euler_sweep
