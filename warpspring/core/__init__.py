"""The simulation core, in pipeline order.

``builder`` (ModelBuilder: particles, springs, triangles, colliders, in bulk; its recipes and finalize) →
``model`` (Model: static arrays and live inputs), ``state`` (State), ``control`` (Control) → per step:
``forces`` (force terms) and ``integrators`` (one ``step(state_in, state_out, control, dt)`` contract) →
``constraints`` (post-step passes: strain limiting, speed clamp, contacts) → ``guards`` (run-time checks) →
``stepper`` (capture and replay) → ``simulator`` (frames of substeps, frame hooks).
``docs/architecture.md`` walks through it and its extension points.
"""
