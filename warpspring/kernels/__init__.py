"""Warp kernels of warpspring, installed as ``warpspring.kernels``.

A leaf package: it imports only ``warp`` and its sibling modules. Kernels are built by cached factories
keyed on the scene's feature set and the floating-point precision (a few that need neither are module-level
kernels), so a scene compiles and launches only what it uses. The maths lives in typed ``@wp.func`` helpers
that tests call directly. Kernel parameters follow one convention (grouped by role, inputs first, written
arrays ending in ``_out``), which ``tests/test_kernel_conventions.py`` checks.

Modules:
    precision: scalar/vector/transform types of each precision.
    flatten: struct kernel parameters compiled as flat array parameters (``flat_kernel``, ``flat_launch``).
    worlds: a thread's world and entry; the pass that holds disabled worlds.
    inputs: live inputs (gravity, drag, wind, limits) in one device table.
    tracks: keyframe tracks evaluated on the device; animated inputs.
    kinematics: the kinematic flag and pin-group motion.
    families: the element-family hooks, their composition into one struct and one set of funcs; incidence.
    spring_laws: the spring force laws (SpringLaw); one spring's force, energy and stiffness as typed funcs.
    springs, hinges: the spring family (hooks, scatter, the plastic pass) and the hinge family.
    bending: dihedral angle, gradient, energy and Gauss-Newton blocks.
    aero: wind drag and lift on triangles (a family).
    handles: PD handles (a family) and the pass of their target frames.
    volume, neohookean: the tet families (bulk volume energy; stable neo-Hookean).
    tet10: the stable neo-Hookean energy on quadratic 10-node tets (a family).
    emitters: births and deaths in an emitter's pool of particles.
    forces: gravity, drag, external and family forces per particle (gather, no atomics); force clamps.
    shapes: collider kinds, the colliders' struct of arrays, signed distances from each kind.
    mesh_colliders: mesh colliders: inside and outside, Warp's queries, pseudo-normals, the candidate cache.
    swept: particle paths swept against thin shapes; keyframed collider motion.
    response: the contact response (projection, restitution, Coulomb friction).
    contacts: the contact stage: per-particle contact slots, collide and project kernels.
    triangle_contacts: cloth triangles against small spheres and thin capsules.
    selfcontact: self-collision of triangle surfaces (broad phase, repulsion, displacement cap).
    selfcontact_cache: self-collision's pair cache (when to rebuild it, the cap over it).
    selfcontact_cap: self-collision's displacement cap (separating planes, its passes, the pairs beyond it).
    integrators: the per-particle update kernels of the integrators; dopri5's step control.
    frames: a frame's substeps of symplectic Euler in one launch, one thread block per world.
    sweep: the CPU's symplectic Euler step, a thread per world sweeping its particles, each spring once.
    implicit: the matrix-free system of linearised implicit Euler.
    linalg: device reductions and the preconditioned conjugate-gradient iteration.
    constraints: post-step passes (strain limiting, speed clamp, contacts).
    guards: run-time checks of non-finite state, torn springs and runaway energy.
    stability: power iteration for the highest spring frequency of a model; spring motion records.
    geometry: export helpers (vertex normals).
    adjoint: differentiable steps (the particle force, updates, smooth contact, loss) compiled with adjoints.
"""
