"""Differentiable runs: a loss over a run of a model and its gradient with respect to the model's values.

A :class:`DiffRun` steps a model with the differentiable kernels of ``kernels/adjoint.py`` (the ordinary
particle force, each step into arrays of its own, colliders met by a smooth penalty) on a ``wp.Tape`` and runs
the tape backwards. Memory is bounded by checkpoints: the forward pass keeps every ``checkpoint_every``-th state
only; the backward pass recomputes one segment at a time on a tape of its own, seeded with the adjoint the
later segment left at its start. Memory is then O(horizon / k + k) states instead of O(horizon).

What the gradient is taken with respect to (:attr:`DiffRun.values`, each a device array with one row per world,
so a batch of worlds gives a batch of gradients):

* ``particle_q``, ``particle_qd``: the initial positions [m] and velocities [m/s], [world_count · n] vec3;
* ``particle_mass`` [kg], ``particle_inv_mass`` [1/kg]: [world_count, n];
* ``inputs``: the live-input table [world_count, INPUT_COUNT] (gravity, drag, wind, air density, ...);
* ``<family>.<field>``: every per-world value of an element family (a 2-D float array with a row per world:
  ``springs.stiffness`` [N/m], ``springs.damping`` [N·s/m], ``hinges.stiffness`` [N·m/rad], ``hinges.damping``,
  the neo-Hookean tets' ``mu``, ``lam`` [Pa], ...), [world_count, element_count];
* ``contact``: the smooth contact's values [world_count, CONTACT_COUNT] (``SmoothContact``);
* ``pin_keys``: with driven pin groups, the key values [m] of the model's track table [world_count, key_count] vec3
  (the keys of a group's translation track: :meth:`DiffRun.pin_key_columns`).

Scalars a user names (a ``ClothMaterial``'s stretch, a spring group's stiffness) map onto these arrays
(``core/adjoint_params.py``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..errors import ConfigError
from ..kernels.adjoint import (
    CONTACT_COUNT,
    CONTACT_DAMPING,
    CONTACT_FRICTION,
    CONTACT_SLIP_SPEED,
    CONTACT_SMOOTHING,
    CONTACT_STIFFNESS,
    diff_force_kernel,
    diff_update_kernels,
    loss_kernel,
    pin_tracks_type,
    smooth_colliders_type,
    vec4_type,
)
from ..kernels.families import Incidence, IncidenceShape, elements, fill_elements
from ..kernels.springs import SpringSpec
from .kinematics import pin_group_index
from .model import Model
from .tracks import Track

#: The integrators a run differentiates.
DIFF_INTEGRATORS = ("symplectic_euler", "velocity_verlet")


@dataclass(frozen=True)
class SmoothContact:
    """The smooth penalty contact of a differentiable run (``kernels/adjoint.py``'s law).

    Attributes:
        stiffness: k_c [N/m] > 0, the penalty's stiffness.
        smoothing: ε [m] > 0, the softplus length: the force is k_c ε softplus(φ/ε) at penetration φ.
        damping: c_c [N·s/m] ≥ 0 along the normal, weighted by σ(φ/ε).
        slip_speed: v_ε [m/s] > 0: friction is viscous below it, Coulomb (each collider's ``friction``) above.
    """

    stiffness: float = 1.0e4
    smoothing: float = 1.0e-3
    damping: float = 10.0
    slip_speed: float = 1.0e-2

    def __post_init__(self):
        for name in ("stiffness", "smoothing", "slip_speed"):
            if not getattr(self, name) > 0.0:
                raise ConfigError(f"SmoothContact.{name} must be > 0, got {getattr(self, name)!r}")
        if not self.damping >= 0.0:
            raise ConfigError(f"SmoothContact.damping must be ≥ 0 [N·s/m], got {self.damping!r}")


@dataclass(frozen=True)
class Target:
    """Positions a run should reach: after ``step`` steps, particles ``particles`` (indices within a world) at
    ``positions`` [m], shape [world_count or 1, len(particles), 3], each weighted by ``weight`` [-]."""

    step: int
    particles: np.ndarray
    positions: np.ndarray
    weight: float = 1.0


class _Pool:
    """The arrays a run's steps write, rows of one block handed out in order: a segment's (``grad``: with
    gradients, zeroed at each reset with one fill) or, cycling, a ring of two steps' (forward only)."""

    def __init__(self, like: wp.array, count: int, grad: bool):
        self.block = wp.zeros((count, like.shape[0]), dtype=like.dtype, device=like.device, requires_grad=grad)
        self.rows = [self.block[r] for r in range(count)]
        self.next = 0

    def take(self) -> wp.array:
        row = self.rows[self.next % len(self.rows)]
        self.next += 1
        return row

    def reset(self) -> "_Pool":
        self.next = 0
        if self.block.requires_grad:
            self.block.grad.zero_()
        return self


class DiffRun:
    """``steps`` steps of ``dt`` of a model, differentiable; see the module docstring.

    Args:
        model: a finalized model (``precision="float64"`` for gradients checked against finite differences).
        dt: the step [s].
        steps: the horizon in steps.
        integrator: "symplectic_euler" or "velocity_verlet".
        contact: the smooth contact's values (default :class:`SmoothContact`); used when the model has colliders.
        checkpoint_every: keep every k-th state in the forward pass (None: ⌈√steps⌉).
        deterministic: compile the kernels with Warp's run-to-run deterministic atomics (their adjoints add
            into shared gradient entries; on the CPU every run is deterministic anyway).
    """

    def __init__(self, model: Model, *, dt: float, steps: int, integrator: str = "symplectic_euler",
                 contact: SmoothContact | None = None, checkpoint_every: int | None = None,
                 deterministic: bool = False):
        if integrator not in DIFF_INTEGRATORS:
            raise ConfigError(f"a differentiable run takes integrator {' or '.join(DIFF_INTEGRATORS)}, got {integrator!r}")
        if not (isinstance(steps, int) and steps >= 1):
            raise ConfigError(f"steps must be an int ≥ 1, got {steps!r}")
        if not dt > 0.0:
            raise ConfigError(f"dt must be > 0 [s], got {dt!r}")
        _check_model(model)
        self.model = model
        self.dt = float(dt)
        self.steps = steps
        self.integrator = integrator
        self.checkpoint_every = max(1, int(np.ceil(np.sqrt(steps)))) if checkpoint_every is None else int(checkpoint_every)
        if self.checkpoint_every < 1:
            raise ConfigError(f"checkpoint_every must be ≥ 1, got {checkpoint_every!r}")
        self.deterministic = bool(deterministic) and model.device.is_cuda  # the CPU runs threads in order
        device, scalar, worlds, n = model.device, model.scalar, model.world_count, model.particle_count
        self._n = worlds * n
        self.values: dict[str, wp.array] = {}

        def own(name, source, rows=None):
            host = source.numpy()
            if rows is not None:
                host = np.broadcast_to(host, (rows, *host.shape[1:]))
            self.values[name] = wp.array(np.ascontiguousarray(host), dtype=source.dtype, device=device,
                                         requires_grad=True)
            return self.values[name]

        own("particle_q", model.particle_q)
        own("particle_qd", model.particle_qd)
        own("particle_mass", model.particle_mass, worlds)
        own("particle_inv_mass", model.particle_inv_mass, worlds)
        own("inputs", model.inputs, worlds)
        specs, arrays = [], []
        for family in model.families:
            if family.name == "springs":  # per spring, gathered (the grouped layouts read a group's values once)
                spec = family.spec(model)
                spec = SpringSpec(incidence=spec.incidence, law=spec.law, gathered=True, slot_groups=(), grid_slots=())
                struct = family.arrays(model, grouped=False)
            else:
                spec, struct = family.spec(model), family.arrays(model)
                if getattr(spec, "precomputed", False):  # a pass of its own would be off the tape: per corner here
                    spec = dataclasses.replace(spec, precomputed=False)
            if spec.incidence.tail:  # a CSR tail is a dynamic loop, whose adjoint Warp does not sum right: no tail
                struct.incidence, shape = _without_tail(struct.incidence, spec.incidence, model.particle_count,
                                                        self_padding=family.name == "springs")
                spec = dataclasses.replace(spec, incidence=shape)
            for field in struct._cls.vars:
                value = getattr(struct, field)
                if (isinstance(value, wp.array) and value.ndim == 2 and value.dtype == scalar
                        and value.shape[0] in (1, worlds)):
                    setattr(struct, field, own(f"{family.name}.{field}", value, worlds))
            specs.append(spec)
            arrays.append(struct)
        self.features = model.force_features(None)._replace(families=tuple(specs), clamp_particle_force=False)
        self._elements = fill_elements(elements(scalar, self.features.families).arrays(), arrays)
        self._colliders, self._planes, self._spheres, friction = _colliders(model)
        contact = contact or SmoothContact()
        row = np.zeros(CONTACT_COUNT)
        row[[CONTACT_STIFFNESS, CONTACT_SMOOTHING, CONTACT_DAMPING, CONTACT_SLIP_SPEED]] = (
            contact.stiffness, contact.smoothing, contact.damping, contact.slip_speed)
        row[CONTACT_FRICTION] = friction
        self.values["contact"] = wp.array(np.tile(row, (worlds, 1)), dtype=scalar, device=device, requires_grad=True)
        self._pins = _pin_tracks(model, self.steps, self.dt)
        if self._pins is not None:
            keys = model.track_table.table.value.numpy()  # float64 [key_count, 3]
            self.values["pin_keys"] = wp.array(np.ascontiguousarray(np.broadcast_to(keys, (worlds, *keys.shape))),
                                               dtype=model.vec3, device=device, requires_grad=True)
            self._pin_arguments = [self._pins, self.values["pin_keys"]]
        else:
            self._pin_arguments = [_no_pin_tracks(model), wp.zeros((1, 0), dtype=model.vec3, device=device)]
        self._no_force = wp.zeros(0, dtype=model.vec3, device=device)
        self._zero_force = None if self._pins is None else wp.zeros(self._n, dtype=model.vec3, device=device)
        self._velocity_dependent = integrator == "velocity_verlet" and _velocity_dependent(model)
        self.targets: list[Target] = []
        self._device_targets: dict[int, tuple] = {}
        self._forward_pool = self._segment_pool = None

    # -- targets ---------------------------------------------------------------------------------------------

    def set_targets(self, targets: list[Target]) -> None:
        """The loss: Σ over ``targets`` of weight · |x_p(step) - target|², per world [m²] (one target per step)."""
        model = self.model
        worlds, n = model.world_count, model.particle_count
        self._device_targets = {}
        for t in targets:
            if not (0 <= t.step <= self.steps):
                raise ConfigError(f"a target's step must be in [0, {self.steps}], got {t.step}")
            if t.step in self._device_targets:
                raise ConfigError(f"two targets at step {t.step}: give one target per step")
            ids = np.asarray(t.particles, dtype=np.int64)
            pos = np.asarray(t.positions, dtype=np.float64)
            if pos.ndim == 2:
                pos = pos[None]
            if pos.shape[1:] != (len(ids), 3) or pos.shape[0] not in (1, worlds):
                raise ConfigError(f"target positions must have shape [1 or {worlds}, {len(ids)}, 3], got {pos.shape}")
            full = np.zeros((worlds, n, 3))
            weight = np.zeros((worlds, n))
            full[:, ids] = np.broadcast_to(pos, (worlds, len(ids), 3))
            weight[:, ids] = t.weight
            self._device_targets[t.step] = (wp.array(full.reshape(-1, 3), dtype=model.vec3, device=model.device),
                                            wp.array(weight.reshape(-1), dtype=model.scalar, device=model.device))
        self.targets = list(targets)

    # -- stepping --------------------------------------------------------------------------------------------

    def _forces(self, q, v, f):
        model = self.model
        wp.launch(
            diff_force_kernel(model.scalar, self.features, self._planes, self._spheres, self.deterministic),
            dim=self._n,
            inputs=[model.particle_count, self.values["particle_mass"], model.particle_radius, self._elements,
                    self.values["inputs"], self._colliders, self.values["contact"], self._no_force, q, v],
            outputs=[f],
            device=model.device,
        )

    @property
    def _arrays_per_step(self) -> int:
        if self.integrator == "symplectic_euler":
            return 3
        return 7 if self._velocity_dependent else 5

    def _ring(self) -> _Pool:
        """The forward-only arrays: a ring of two steps' (the start's two among them)."""
        if self._forward_pool is None:
            self._forward_pool = _Pool(self.values["particle_q"], 2 * self._arrays_per_step, grad=False)
        return self._forward_pool.reset()

    def pin_key_columns(self, group, *, world: int = 0) -> slice:
        """The columns of ``values["pin_keys"]`` (and of its gradient) holding the keys of pin ``group``'s
        translation track (a group index or name) in ``world``'s row."""
        pins = self.model.pin_groups
        g = pin_group_index(pins, group)
        rows = _pin_rows(pins)
        track = rows[world % len(rows)][g][0]
        first = int(self.model.track_table.table.key_start.numpy()[self.model.track_table.index(track)])
        return slice(first, first + len(track.times))

    def _step(self, q, v, pool: _Pool, step: int):
        """Step ``step`` (1, 2, ...) from (q, v) into arrays of ``pool``; returns the new (q, v)."""
        _fresh = pool.take
        model = self.model
        update, kick = diff_update_kernels(model.scalar, self.deterministic, self._pins is not None)
        mass = [model.particle_count, model.particle_flags, self.values["particle_inv_mass"]]
        pins = [*self._pin_arguments, step]
        h = model.scalar(self.dt)
        common = dict(dim=self._n, device=model.device)
        f = _fresh()
        self._forces(q, v, f)
        q_out, v_out = _fresh(), _fresh()
        if self.integrator == "symplectic_euler":
            wp.launch(update, inputs=[*mass, *pins, q, v, f, h, model.scalar(1.0)], outputs=[q_out, v_out], **common)
            return q_out, v_out
        v_half = _fresh()
        wp.launch(update, inputs=[*mass, *pins, q, v, f, h, model.scalar(0.5)], outputs=[q_out, v_half], **common)
        f_half = _fresh()
        self._forces(q_out, v_half, f_half)
        wp.launch(kick, inputs=[*mass, v_half, f_half, h], outputs=[v_out], **common)
        if self._velocity_dependent:  # the corrector of core/integrators/verlet.py: f(x', v*)
            f_star, v_final = _fresh(), _fresh()
            self._forces(q_out, v_out, f_star)
            wp.launch(kick, inputs=[*mass, v_half, f_star, h], outputs=[v_final], **common)
            v_out = v_final
        return q_out, v_out

    def _start(self, pool: _Pool):
        """The initial state (q, v): ``values``' particle_q and particle_qd, with driven pins put where their tracks
        are at t = 0 (the update kernel at h = 0, on the tape: the keys move the start too), as ``Model.state``
        puts them."""
        q, v = self.values["particle_q"], self.values["particle_qd"]
        if self._pins is None:
            return q, v
        model = self.model
        update = diff_update_kernels(model.scalar, self.deterministic, True)[0]
        q_out, v_out = pool.take(), pool.take()
        wp.launch(update, dim=self._n, device=model.device,
                  inputs=[model.particle_count, model.particle_flags, self.values["particle_inv_mass"],
                          *self._pin_arguments, 0, q, v, self._zero_force, model.scalar(0.0), model.scalar(1.0)],
                  outputs=[q_out, v_out])
        return q_out, v_out

    def _loss_at(self, step, q, loss, row):
        if step not in self._device_targets:
            return
        model = self.model
        target, weight = self._device_targets[step]
        records = model.particle_count if self.deterministic else 0
        wp.launch(loss_kernel(model.scalar, self.deterministic, records), dim=model.world_count,
                  inputs=[model.particle_count, q, target, weight, row], outputs=[loss], device=model.device)

    def trajectory(self, every: int = 1) -> np.ndarray:
        """Positions [m] of every ``every``-th step (step 0 first), float64, [steps // every + 1, world_count, n, 3]."""
        ring = self._ring()
        q, v = self._start(ring)
        out = [np.array(q.numpy(), dtype=np.float64)]  # (copies: on the CPU numpy() is a view of the ring)
        for k in range(1, self.steps + 1):
            q, v = self._step(q, v, ring, k)
            if k % every == 0:
                out.append(np.array(q.numpy(), dtype=np.float64))
        shape = (self.model.world_count, self.model.particle_count, 3)
        return np.stack([np.asarray(x, dtype=np.float64).reshape(shape) for x in out])

    def positions(self, steps) -> np.ndarray:
        """Positions [m] after each of ``steps`` (ascending step counts, 0 … :attr:`steps`), float64,
        [len(steps), world_count, n, 3] (a forward run, no tape)."""
        wanted = sorted(set(int(s) for s in steps))
        if wanted and not (0 <= wanted[0] and wanted[-1] <= self.steps):
            raise ConfigError(f"steps must be in [0, {self.steps}], got {wanted[0]} … {wanted[-1]}")
        shape = (self.model.world_count, self.model.particle_count, 3)
        ring = self._ring()
        q, v = self._start(ring)
        found = {0: np.array(q.numpy(), dtype=np.float64)} if 0 in wanted else {}
        for k in range(1, (wanted[-1] if wanted else 0) + 1):
            q, v = self._step(q, v, ring, k)
            if k in wanted:
                found[k] = np.array(q.numpy(), dtype=np.float64)  # (a copy: the ring's rows are reused)
        return np.stack([np.asarray(found[int(s)], dtype=np.float64).reshape(shape) for s in steps])

    # -- loss and gradient -----------------------------------------------------------------------------------

    def loss(self) -> np.ndarray:
        """The loss of every world [m²], float64, [world_count] (a forward run, no tape)."""
        worlds = self.model.world_count
        loss = wp.zeros((self.steps + 1, worlds), dtype=self.model.scalar, device=self.model.device)
        ring = self._ring()
        q, v = self._start(ring)
        self._loss_at(0, q, loss, 0)
        for k in range(1, self.steps + 1):
            q, v = self._step(q, v, ring, k)
            self._loss_at(k, q, loss, k)
        return loss.numpy().astype(np.float64).sum(axis=0)

    def gradient(self) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The loss of every world [m²] and its gradient with respect to every array of :attr:`values` (each
        world's gradient in its own rows), by checkpointed recomputation."""
        if not self.targets:
            raise ConfigError("the run has no targets: call set_targets first")
        model = self.model
        k = self.checkpoint_every
        for array in self.values.values():
            array.grad.zero_()
        # Forward: keep the state at every k-th step (no tape).
        checkpoints = {0: (self.values["particle_q"], self.values["particle_qd"])}
        ring = self._ring()
        q, v = self._start(ring)
        for step in range(1, self.steps + 1):
            q, v = self._step(q, v, ring, step)
            if step % k == 0 and step < self.steps:
                checkpoints[step] = (wp.clone(q), wp.clone(v))
        total = np.zeros(model.world_count)
        adj_q = adj_v = None
        if self._segment_pool is None:  # (kept between gradients: a fit evaluates many)
            self._segment_pool = _Pool(self.values["particle_q"], k * self._arrays_per_step + 2, grad=True)
        pool = self._segment_pool
        starts = sorted(checkpoints)
        for start in reversed(starts):
            end = min(start + k, self.steps)
            if start == 0:
                q0, v0 = checkpoints[0]
            else:
                q0, v0 = wp.clone(checkpoints[start][0], requires_grad=True), wp.clone(checkpoints[start][1],
                                                                                       requires_grad=True)
            loss = wp.zeros((end - start + 1, model.world_count), dtype=model.scalar, device=model.device,
                            requires_grad=True)
            tape = wp.Tape()
            pool.reset()
            with tape:
                q, v = q0, v0
                if start == 0:
                    q, v = self._start(pool)
                    self._loss_at(0, q, loss, 0)
                for step in range(start + 1, end + 1):
                    q, v = self._step(q, v, pool, step)
                    self._loss_at(step, q, loss, step - start)
            total += loss.numpy().astype(np.float64).sum(axis=0)
            grads = {loss: wp.ones_like(loss, requires_grad=False)}
            if adj_q is not None:
                grads[q] = adj_q
                grads[v] = adj_v
            tape.backward(grads=grads)
            adj_q, adj_v = q0.grad, v0.grad
        # The initial state's adjoint is in values["particle_q"/"particle_qd"].grad (segment 0 started there).
        grads = {name: array.grad.numpy().astype(np.float64) for name, array in self.values.items()}
        return total, grads


def _check_model(model: Model) -> None:
    """What a differentiable run does not cover raises here, with what to do instead."""
    if model.input_tracks is not None:
        raise ConfigError("a differentiable run does not evaluate keyframe tracks of inputs: set the inputs constant")
    pins = model.pin_groups
    for row in _pin_rows(pins) if pins is not None else ():
        for group, (translation, rotation) in zip(pins.groups, row):
            _check_pin_track(group.name, translation, rotation)
    if model.spring_plastic_count:
        raise ConfigError("a differentiable run does not take plastic springs (their flow has no gradient here)")
    if model.self_contact is not None:
        raise ConfigError("a differentiable run does not take self-collision: build the model without it")
    if model.shape_moving:
        raise ConfigError("a differentiable run takes colliders at rest only: remove the colliders' tracks")
    kinds = {shape.kind for shape in model.shapes} - {"plane", "sphere"}
    if kinds:
        raise ConfigError(f"a differentiable run meets planes and spheres only, not {', '.join(sorted(kinds))}")
    if model.emitters:
        raise ConfigError("a differentiable run does not take emitters")
    if model.stabilizers.max_particle_force is not None:
        raise ConfigError("a differentiable run does not clamp forces: set max_particle_force to None")


def _pin_rows(pins) -> list:
    """The (translation, rotation) tracks of every pin group, one list per row of the pin table (one row for
    every world, or one per world)."""
    return pins.world_tracks or [[(g.translation, g.rotation) for g in pins.groups]]


def _check_pin_track(name: str, translation: Track | None, rotation: Track | None) -> None:
    if translation is None and rotation is None:
        raise ConfigError(f"a differentiable run does not take pin group {name!r} driven through Control: give it a "
                          "translation track")
    if rotation is not None:
        raise ConfigError(f"a differentiable run moves pin groups by translation tracks only: pin group {name!r} has a "
                          "rotation track")
    if translation.interpolation not in ("linear", "step"):
        raise ConfigError(f"a differentiable run takes linear or step pin tracks: pin group {name!r}'s translation is "
                          f"{translation.interpolation!r} (its tangents depend on the keys)")


def _track_weights(track: Track, times: np.ndarray):
    """For each of ``times`` [s], the two keys (local indices a ≤ b) a linear or step track mixes and their weights
    in the value and in the rate, [len(times), 2] int and [len(times), 4], from the track's own host evaluation
    (sampled on the unit keys: the value is linear in the keys)."""
    count = len(track.times)
    value = np.empty((len(times), count))
    rate = np.empty((len(times), count))
    for j in range(count):
        unit = Track(track.times, np.eye(count)[j][:, None] * np.ones(3), interpolation=track.interpolation,
                     extrapolation=track.extrapolation)
        value[:, j], rate[:, j] = (part[:, 0] for part in unit.sample(times))
    moved = (value != 0.0) | (rate != 0.0)
    a = np.where(moved.any(axis=1), moved.argmax(axis=1), 0)
    b = np.minimum(a + 1, count - 1)
    rows = np.arange(len(times))
    weights = np.stack([value[rows, a], np.where(b > a, value[rows, b], 0.0), rate[rows, a],
                        np.where(b > a, rate[rows, b], 0.0)], axis=1)
    rest = moved.copy()
    rest[rows, a] = rest[rows, b] = False
    assert not rest.any(), "a linear or step track mixes two neighbouring keys at most"
    return np.stack([a, b], axis=1), weights


def _pin_tracks(model: Model, steps: int, dt: float):
    """The driven pins of a differentiable run (``kernels/adjoint.py``'s PinTracks), or None: each group's keys and
    weights at the end time of every step, the times summed step by step in float64 as the ordinary run's clock."""
    pins = model.pin_groups
    if pins is None or not pins.groups:
        return None
    device, scalar = model.device, model.scalar
    table = model.track_table
    first = table.table.key_start.numpy()
    times = np.concatenate([[0.0], np.cumsum(np.full(steps, dt))])
    rows = _pin_rows(pins)
    key = np.zeros((steps + 1, len(rows), len(pins.groups), 2), dtype=np.int32)
    weight = np.zeros((steps + 1, len(rows), len(pins.groups), 4))
    for r, row in enumerate(rows):
        for g, (translation, _) in enumerate(row):
            local, weight[:, r, g] = _track_weights(translation, times)
            key[:, r, g] = first[table.index(translation)] + local
    particle_pin = np.full(model.particle_count, -1, dtype=np.int32)
    driven = np.flatnonzero(pins.table.group.numpy() >= 0)
    particle_pin[pins.kinematic[driven]] = np.arange(len(driven))
    out = pin_tracks_type(scalar)()
    out.particle_pin = wp.array(particle_pin, dtype=wp.int32, device=device)
    out.pin_group = wp.array(pins.table.group.numpy()[driven], dtype=wp.int32, device=device)
    out.pin_rest = wp.array(pins.rest[driven], dtype=model.vec3, device=device)
    out.key = wp.array(key, dtype=wp.vec2i, device=device)
    out.weight = wp.array(weight, dtype=vec4_type(scalar), device=device)
    return out


def _no_pin_tracks(model: Model):
    """Pin tracks of a run without driven pins (empty arrays: the kernels compiled without pins never read them)."""
    out = pin_tracks_type(model.scalar)()
    device = model.device
    out.particle_pin = wp.zeros(0, dtype=wp.int32, device=device)
    out.pin_group = wp.zeros(0, dtype=wp.int32, device=device)
    out.pin_rest = wp.zeros(0, dtype=model.vec3, device=device)
    out.key = wp.zeros((0, 0, 0), dtype=wp.vec2i, device=device)
    out.weight = wp.zeros((0, 0, 0), dtype=vec4_type(model.scalar), device=device)
    return out


def _without_tail(table: Incidence, shape: IncidenceShape, n: int, *, self_padding: bool):
    """The incidence table with its CSR tail moved into a head as wide as the largest degree (a compile-time
    loop, whose adjoint Warp generates right). Padding entries as the families make them: element 0 with local
    the particle itself (springs, ``self_padding``) or -1."""
    head_element, head_local = table.head_element.numpy(), table.head_local.numpy()
    start = table.tail_start.numpy()
    tail_element, tail_local = table.tail_element.numpy(), table.tail_local.numpy()
    width = shape.head_slots + int(np.diff(start).max(initial=0))
    pad = np.arange(n) if self_padding else np.full(n, -1)
    element = np.zeros((width, n), dtype=np.int32)
    local = np.broadcast_to(pad.astype(np.int32), (width, n)).copy()
    element[: shape.head_slots] = head_element
    local[: shape.head_slots] = head_local
    for i in np.flatnonzero(np.diff(start)):
        count = start[i + 1] - start[i]
        element[shape.head_slots: shape.head_slots + count, i] = tail_element[start[i]: start[i + 1]]
        local[shape.head_slots: shape.head_slots + count, i] = tail_local[start[i]: start[i + 1]]
    out = Incidence()
    device = table.head_element.device
    out.head_element = wp.array(element, dtype=wp.int32, device=device)
    out.head_local = wp.array(local, dtype=wp.int32, device=device)
    out.tail_start = wp.zeros(n + 1, dtype=wp.int32, device=device)
    out.tail_element = wp.zeros(0, dtype=wp.int32, device=device)
    out.tail_local = wp.zeros(0, dtype=wp.int32, device=device)
    return out, IncidenceShape(head_slots=width, tail=False)


def _velocity_dependent(model: Model) -> bool:
    return (model.drag_enabled or bool(model.spring_count and (model.spring_damping.numpy() != 0.0).any())
            or any(family.velocity_dependent(model) for family in model.extra_families))


def _colliders(model: Model):
    """The smooth contact's struct of the model's planes and spheres, whether each kind is present, and the mean
    Coulomb coefficient (one μ for every collider in a differentiable run)."""
    scalar, vec3, device = model.scalar, model.vec3, model.device
    normals, offsets, thick, centers, radii, friction = [], [], [], [], [], []
    for shape in model.shapes:
        x, y, z, w = shape.rotation
        rotation = _quat_z(np.array([x, y, z, w], dtype=np.float64))
        position = np.asarray(shape.position, dtype=np.float64)
        friction.append(shape.friction)
        if shape.kind == "plane":
            normals.append(rotation)
            offsets.append(float(rotation @ position))
            thick.append(shape.thickness)
        else:
            centers.append(position)
            radii.append(shape.size[0] + shape.thickness)
    colliders = smooth_colliders_type(scalar)()
    colliders.plane_normal = wp.array(np.reshape(normals, (-1, 3)), dtype=vec3, device=device)
    colliders.plane_offset = wp.array(np.asarray(offsets, dtype=np.float64), dtype=scalar, device=device)
    colliders.plane_thickness = wp.array(np.asarray(thick, dtype=np.float64), dtype=scalar, device=device)
    colliders.sphere_center = wp.array(np.reshape(centers, (-1, 3)), dtype=vec3, device=device)
    colliders.sphere_radius = wp.array(np.asarray(radii, dtype=np.float64), dtype=scalar, device=device)
    mu = float(np.mean(friction)) if friction else 0.0
    return colliders, bool(normals), bool(centers), mu


def _quat_z(q: np.ndarray) -> np.ndarray:
    """The local +z axis (a plane's normal) turned by the unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)])
