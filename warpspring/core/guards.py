"""Run-time guards of a simulation: stop with a clear error, naming frame, substep, particle or spring
and a remedy, when the state turns non-finite, a spring tears far past its rest length, or the kinetic
energy runs away. The checks run on the device inside the captured frame (``kernels/guards.py``); the
host reads one small status record per frame."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from .. import checks
from ..kernels.guards import (
    GUARD_ENERGY,
    GUARD_FLOATS,
    GUARD_INTS,
    GUARD_KINETIC_ENERGY,
    GUARD_LIMIT_KINETIC_ENERGY,
    GUARD_LIMIT_STRAIN,
    GUARD_LIMITS,
    GUARD_MAX_STRAIN,
    GUARD_NONFINITE,
    GUARD_NONFINITE_COUNT,
    GUARD_NONFINITE_PARTICLE,
    GUARD_STRAIN,
    GUARD_STRAIN_PARTICLE,
    GUARD_STRAIN_SPRING,
    GUARD_SUBSTEP,
    GUARD_TRIPPED,
    NO_PARTICLE,
    guard_kernels,
)
from ..kernels.linalg import reduce_launch_dim
from .model import Model, State
from .stepper import StepHook

#: Default limit of the kinetic energy, as a multiple of the scene's energy scale (see GuardLimits).
ENERGY_FACTOR = 1.0e6


#: Default spring strain at which the guard stops a run (eleven times the rest length).
TEAR_STRAIN = 10.0


@dataclass(frozen=True, init=False)
class GuardLimits:
    """What the run-time guard checks, and how often (each argument is also an attribute).

    Args:
        every: substeps between checks; ``None`` checks once per frame, after its last substep.
        tear_strain: spring strain |d|/L - 1 [-] at which a spring counts as torn and the run stops
            (default ``TEAR_STRAIN`` = 10: eleven times the rest length). Not the strain limit of
            ``Stabilizers.max_strain``.
        max_kinetic_energy: largest allowed total kinetic energy [J]; ``None``: 10⁶ times the scene's
            energy scale (initial kinetic + elastic energy + total weight × (extent + 1 m)).
        max_strain: deprecated name of ``tear_strain`` (a DeprecationWarning; same value; also readable
            as a deprecated property).

    Raises:
        ConfigError: a value out of range.
        TypeError: both ``tear_strain`` and its deprecated name ``max_strain``.
    """

    every: int | None = None
    tear_strain: float = TEAR_STRAIN
    max_kinetic_energy: float | None = None

    def __init__(self, *, every: int | None = None, tear_strain: float | None = None,
                 max_kinetic_energy: float | None = None, max_strain: float | None = None):
        name = "guard tear_strain"
        if max_strain is not None:
            if tear_strain is not None:
                raise TypeError("GuardLimits got tear_strain and max_strain, its deprecated name: pass tear_strain "
                                "only")
            warnings.warn(_MAX_STRAIN_RENAMED, DeprecationWarning, stacklevel=2)
            tear_strain, name = max_strain, "guard max_strain"
        elif tear_strain is None:
            tear_strain = TEAR_STRAIN
        if every is not None:
            checks.count("guard every", every, minimum=1)
        checks.positive(name, tear_strain)
        if max_kinetic_energy is not None:
            checks.positive("guard max_kinetic_energy", max_kinetic_energy)
        object.__setattr__(self, "every", every)
        object.__setattr__(self, "tear_strain", tear_strain)
        object.__setattr__(self, "max_kinetic_energy", max_kinetic_energy)

    @property
    def max_strain(self) -> float:
        """Deprecated name of :attr:`tear_strain` [-] (a DeprecationWarning)."""
        warnings.warn(_MAX_STRAIN_RENAMED, DeprecationWarning, stacklevel=2)
        return self.tear_strain


_MAX_STRAIN_RENAMED = (
    "GuardLimits.max_strain is deprecated: it is now GuardLimits.tear_strain (the strain at which a spring "
    "counts as torn; Stabilizers.max_strain is the strain limit)"
)


@dataclass(frozen=True)
class GuardReport:
    """The first failure a guard saw within a frame.

    Attributes:
        reason: "non-finite state", "strain" or "kinetic energy".
        substep: substep of the frame at whose check it was seen (the failure happened at or before it).
        particle: index of the offending particle (lowest-index non-finite one, or one holding the worst
            spring).
        spring: index of the most strained spring, or ``None``.
        nonfinite_count: particles with a non-finite position or velocity at that check.
        strain: largest spring strain at that check [-].
        kinetic_energy: total kinetic energy at that check [J].
    """

    reason: str
    substep: int
    particle: int | None
    spring: int | None
    strain: float
    kinetic_energy: float
    nonfinite_count: int = 0

    def describe(self, model: Model) -> str:
        """One clause naming what went wrong and where."""
        if self.reason == "non-finite state":
            if self.nonfinite_count == 1:
                return f"particle {self.particle} has a non-finite position or velocity"
            return (f"{self.nonfinite_count} of {model.particle_count} particles have non-finite positions or "
                    f"velocities (lowest index {self.particle})")
        if self.reason == "strain":
            a, b = model.spring_indices.numpy()[self.spring]
            return (f"spring {self.spring} (particles {a}-{b}) stretched to {self.strain + 1:.3g}× its rest "
                    "length (guard limit exceeded)")
        return f"the kinetic energy ran away to {self.kinetic_energy:.3g} J (guard limit exceeded)"


class Guard(StepHook):
    """Device-side checks of one simulator's states; see :class:`GuardLimits`. A :class:`StepHook`: it
    clears its record at the start of every frame and checks after every ``every``-th substep and the last.

    The limits are device values: setting :attr:`limits` between frames changes no captured launch (but
    a new ``every`` does, and the stepper re-captures)."""

    def __init__(self, model: Model, limits: GuardLimits, substeps: int):
        self.model = model
        self.substeps = substeps
        self._tiled = model.device.is_cuda
        device = model.device
        self._status_clear = wp.array([0, -1, NO_PARTICLE, NO_PARTICLE, NO_PARTICLE, 0], dtype=wp.int32, device=device)
        self._values_clear = wp.array([-1.0, 0.0], dtype=wp.float64, device=device)
        assert len(self._status_clear) == GUARD_INTS and len(self._values_clear) == GUARD_FLOATS
        self._status = wp.clone(self._status_clear)
        self._values = wp.clone(self._values_clear)
        self._limits = wp.zeros(GUARD_LIMITS, dtype=wp.float64, device=device)
        self.revision = 0
        self._every = None
        self.limits = limits

    @property
    def limits(self) -> GuardLimits:
        """What the guard checks (:class:`GuardLimits`); settable between frames."""
        return self._limits_host

    @limits.setter
    def limits(self, limits: GuardLimits) -> None:
        if not isinstance(limits, GuardLimits):
            raise TypeError(f"guard limits must be a warpspring.GuardLimits, got {type(limits).__name__}")
        self._limits_host = limits
        every = min(limits.every or self.substeps, self.substeps)
        if every != self._every:
            self._every = every
            self.revision += 1
        self._write_limits()

    def refresh(self) -> None:
        """Re-derive a default kinetic-energy limit after the model's live inputs changed (gravity switched
        on mid-run raises the scene's energy scale); a value write, no re-capture. Call between frames (the
        Simulator does)."""
        if self._limits_host.max_kinetic_energy is None and self._input_version != self.model.input_version:
            self._write_limits()

    def _write_limits(self) -> None:
        limits = self._limits_host
        self._input_version = self.model.input_version
        self.max_kinetic_energy = (
            limits.max_kinetic_energy if limits.max_kinetic_energy is not None
            else ENERGY_FACTOR * energy_scale(self.model)
        )
        values = [0.0] * GUARD_LIMITS
        values[GUARD_LIMIT_STRAIN] = limits.tear_strain
        values[GUARD_LIMIT_KINETIC_ENERGY] = self.max_kinetic_energy
        wp.copy(self._limits, wp.array(values, dtype=wp.float64, device="cpu"))

    @property
    def every(self) -> int:
        """Substeps between checks (the last substep of a frame is always checked)."""
        return self._every

    def begin(self) -> None:
        self.reset()

    def after_step(self, state: State, step: int, steps: int) -> None:
        if (step + 1) % self._every == 0 or step + 1 == steps:
            self.check(state, step)

    def reset(self) -> None:
        """Clear the record (device copies: capturable, done at the start of every frame)."""
        wp.copy(self._status, self._status_clear)
        wp.copy(self._values, self._values_clear)

    def check(self, state: State, substep: int) -> None:
        """Launch the checks of ``state`` after ``substep`` (device only; capturable)."""
        model = self.model
        measure, locate, decide = guard_kernels(model.scalar, model.spring_max_degree, self._tiled)
        block = model.block_dim if self._tiled else 1
        table = [model.particle_spring_neighbor, model.particle_spring_id, model.spring_rest_length]
        out = [self._status, self._values]
        wp.launch(measure, dim=reduce_launch_dim(model.particle_count, block), block_dim=block,
                  inputs=[model.particle_count, model.particle_mass, *table, state.particle_q, state.particle_qd],
                  outputs=out, device=model.device)
        wp.launch(locate, dim=model.particle_count, block_dim=model.block_dim,
                  inputs=[*table, state.particle_q], outputs=out, device=model.device)
        wp.launch(decide, dim=1, inputs=[substep, self._limits], outputs=out, device=model.device)

    def report(self) -> GuardReport | None:
        """The first failure since the last reset, or ``None`` (reads the device: synchronises)."""
        status = self._status.numpy()
        if status[GUARD_TRIPPED] == 0:
            return None
        values = self._values.numpy()
        reason = {GUARD_NONFINITE: "non-finite state", GUARD_STRAIN: "strain", GUARD_ENERGY: "kinetic energy"}[
            int(status[GUARD_TRIPPED])
        ]
        particle = status[GUARD_NONFINITE_PARTICLE] if reason == "non-finite state" else status[GUARD_STRAIN_PARTICLE]
        spring = status[GUARD_STRAIN_SPRING]
        return GuardReport(
            reason=reason,
            substep=int(status[GUARD_SUBSTEP]),
            particle=None if particle == NO_PARTICLE else int(particle),
            spring=None if spring == NO_PARTICLE else int(spring),
            strain=float(values[GUARD_MAX_STRAIN]),
            kinetic_energy=float(values[GUARD_KINETIC_ENERGY]),
            nonfinite_count=int(status[GUARD_NONFINITE_COUNT]),
        )


def energy_scale(model: Model) -> float:
    """A scene's energy scale [J]: initial kinetic + elastic energy + total weight × (extent + 1 m), ≥ 1 µJ;
    the weight with the largest gravity the scene has (now, or at any key of a gravity track)."""
    q = model.particle_q.numpy().astype(np.float64)
    qd = model.particle_qd.numpy().astype(np.float64)
    mass = model.particle_mass.numpy().astype(np.float64)
    kinetic = 0.5 * float(np.sum(mass * np.sum(qd * qd, axis=1)))
    elastic = 0.0
    if model.spring_count:
        pairs = model.spring_indices.numpy()
        stretch = np.linalg.norm(q[pairs[:, 1]] - q[pairs[:, 0]], axis=1) - model.spring_rest_length.numpy()
        elastic = 0.5 * float(np.sum(model.spring_stiffness.numpy() * stretch * stretch))
    extent = float(np.ptp(q, axis=0).max()) if len(q) else 0.0
    gravity = math.hypot(*model.gravity)
    track = model.track("gravity")
    if track is not None:
        gravity = max(gravity, float(np.linalg.norm(track.values, axis=1).max()))
    weight = float(mass.sum()) * gravity
    return max(kinetic + elastic + weight * (extent + 1.0), 1.0e-6)
