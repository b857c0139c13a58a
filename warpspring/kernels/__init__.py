"""Warp kernels of warpspring, installed as ``warpspring.kernels``.

A leaf package: it imports only ``warp`` and its sibling modules. Every kernel is built by a cached
factory keyed on the scene's feature set and the floating-point precision, so a scene compiles and
launches only what it uses. The maths lives in typed ``@wp.func`` helpers that tests call directly.

Modules:
    precision: scalar/vector/transform types of each precision.
    forces: spring, gravity, drag and external forces (per-particle gather, no atomics).
    contacts: particle-collider contact projection with Coulomb friction.
    integrators: the per-particle update kernels of the integrators.
    implicit: the matrix-free system of linearised implicit Euler.
    linalg: device reductions and the preconditioned conjugate-gradient iteration.
    constraints: post-step passes (strain limiting, speed clamp, contacts).
    guards: run-time checks of non-finite state, torn springs and runaway energy.
    stability: power iteration for the highest spring frequency of a model.
    geometry: export helpers (vertex normals).
"""
