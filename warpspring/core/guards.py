"""Run-time guards of a simulation: stop with a clear error, naming frame, substep, world, particle or spring
and a remedy, when the state turns non-finite, a spring tears far past its rest length, or the kinetic
energy runs away. The checks run on the device inside the captured frame, per world
(``kernels/guards.py``); the host reads one small status record per world and frame. A failure stops the
run, or (``GuardLimits(stop="world")``) holds only the failed world while the others go on."""

from __future__ import annotations

import dataclasses
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
    GUARD_STRAIN_ELEMENT,
    GUARD_STRAIN_FAMILY,
    GUARD_STOP_WORLD,
    GUARD_SUBSTEP,
    GUARD_WORK_FACTOR,
    GUARD_TRIPPED,
    NO_PARTICLE,
    guard_kernels,
)
from ..errors import ConfigError
from ..kernels.flatten import flat_launch
from ..kernels.linalg import reduce_lanes, reduce_launch_dim
from .families import world_elastic_energy
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
        max_kinetic_energy: largest allowed kinetic energy of a world's free particles [J], fixed; ``None``: 10⁶ times
            the world's energy scale (initial kinetic + elastic energy + total weight × (extent + 1 m)) plus
            the work its loads put in so far (weight, the control's external force, the drive of kinematic
            particles; ``kernels/guards.py``), so a forced or driven run is never stopped for the energy
            it was given.
        stop: what a failure stops: "run" (the simulator raises a SimulationError at the end of the frame)
            or "world" (the failed world is held from the failing check on, its failure is recorded in
            ``Simulator.world_failures``, and the other worlds go on; the run stops only when every world
            has failed).
        max_strain: deprecated name of ``tear_strain`` (a DeprecationWarning; same value; also readable
            as a deprecated property).

    Raises:
        ConfigError: a value out of range.
        TypeError: both ``tear_strain`` and its deprecated name ``max_strain``.
    """

    every: int | None = None
    tear_strain: float = TEAR_STRAIN
    max_kinetic_energy: float | None = None
    stop: str = "run"

    def __init__(self, *, every: int | None = None, tear_strain: float | None = None,
                 max_kinetic_energy: float | None = None, stop: str = "run", max_strain: float | None = None):
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
        if stop not in ("run", "world"):
            raise ConfigError(f"guard stop must be 'run' or 'world', got {stop!r}")
        object.__setattr__(self, "stop", stop)
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
        world: the world it happened in.
        reason: "non-finite state", "strain" or "kinetic energy".
        substep: substep of the frame at whose check it was seen (the failure happened at or before it).
        particle: index of the offending particle (lowest-index non-finite one, or one holding the worst
            element).
        spring: index of the most strained spring, or ``None`` (also when the worst element is not a spring).
        nonfinite_count: particles with a non-finite position or velocity at that check.
        strain: largest element strain at that check [-] (springs: |d|/L - 1).
        family: name of the family of the most strained element ("springs", ...), or ``None``.
        element: index of the most strained element in its family, or ``None``.
        kinetic_energy: total kinetic energy at that check [J].
    """

    world: int
    reason: str
    substep: int
    particle: int | None
    spring: int | None
    strain: float
    kinetic_energy: float
    nonfinite_count: int = 0
    family: str | None = None
    element: int | None = None

    def describe(self, model: Model, *, name_world: bool = True) -> str:
        """One clause naming what went wrong and where (the world too, in a model of several, unless
        ``name_world`` is off)."""
        where = f"in world {self.world}, " if model.world_count > 1 and name_world else ""
        if self.reason == "non-finite state":
            if self.nonfinite_count == 1:
                return f"{where}particle {self.particle} has a non-finite position or velocity"
            return (f"{where}{self.nonfinite_count} of {model.particle_count} particles have non-finite positions or "
                    f"velocities (lowest index {self.particle})")
        if self.reason == "strain":
            family = next(f for f in model.families if f.name == self.family)
            return (f"{where}{family.describe_element(model, self.element)} stretched to {self.strain + 1:.3g}× its "
                    "rest length (guard limit exceeded)")
        return f"{where}the kinetic energy ran away to {self.kinetic_energy:.3g} J (guard limit exceeded)"


class Guard(StepHook):
    """Device-side checks of one simulator's states, per world; see :class:`GuardLimits`. A :class:`StepHook`:
    it clears its record at the start of every frame and checks after every ``every``-th substep and the
    last.

    The limits are device values: setting :attr:`limits` between frames changes no captured launch (but
    a new ``every`` does, and the stepper re-captures)."""

    def __init__(self, model: Model, limits: GuardLimits, substeps: int, *, control=None):
        self.model = model
        self.substeps = substeps
        #: The control whose external force counts as work put in (``None``: no external force).
        self.control = control
        self._tiled = model.device.is_cuda
        self._lanes = reduce_lanes(model.particle_count, model.block_dim, self._tiled)
        device, worlds = model.device, model.world_count
        status = np.tile([0, -1, NO_PARTICLE, NO_PARTICLE, NO_PARTICLE, 0, NO_PARTICLE], (worlds, 1))
        values = np.tile([-1.0, 0.0, 0.0], (worlds, 1))
        assert status.shape[1] == GUARD_INTS and values.shape[1] == GUARD_FLOATS
        self._status_clear = wp.array(status, dtype=wp.int32, device=device)
        self._values_clear = wp.array(values, dtype=wp.float64, device=device)
        self._status = wp.clone(self._status_clear)
        self._values = wp.clone(self._values_clear)
        grid = reduce_launch_dim(worlds, model.particle_count, self._lanes)
        self._partials = wp.zeros((worlds, grid[1], GUARD_FLOATS), dtype=wp.float64, device=device)
        self._limits = wp.zeros((worlds, GUARD_LIMITS), dtype=wp.float64, device=device)
        # The work put in since the start [J] per world, and the positions of the last check (its Δx; the
        # run's start state: :meth:`restart`).
        self._work_total = wp.zeros(worlds, dtype=wp.float64, device=device)
        self._previous_q = wp.clone(model.particle_q)
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
        if limits.stop == "world":
            self.model.hold_worlds()  # a failed world is held by the integrators' last pass
        self._write_limits()

    def refresh(self) -> None:
        """Re-derive a default kinetic-energy limit after the model's live inputs changed (gravity switched
        on mid-run raises the scene's energy scale); a value write, no re-capture. Call between frames (the
        Simulator does)."""
        if self._limits_host.max_kinetic_energy is None and self._input_version != self.model.input_version:
            self._write_limits()

    def _write_limits(self) -> None:
        limits = self._limits_host
        model = self.model
        self._input_version = model.input_version
        if limits.max_kinetic_energy is not None:
            self.world_max_kinetic_energy = np.full(model.world_count, limits.max_kinetic_energy)
        else:
            self.world_max_kinetic_energy = ENERGY_FACTOR * energy_scales(model)
        values = np.zeros((model.world_count, GUARD_LIMITS))
        values[:, GUARD_LIMIT_STRAIN] = limits.tear_strain
        values[:, GUARD_LIMIT_KINETIC_ENERGY] = self.world_max_kinetic_energy
        values[:, GUARD_STOP_WORLD] = 1.0 if limits.stop == "world" else 0.0
        values[:, GUARD_WORK_FACTOR] = ENERGY_FACTOR if limits.max_kinetic_energy is None else 0.0
        self._limits.assign(values)

    @property
    def max_kinetic_energy(self) -> float:
        """The kinetic-energy limit of world 0 [J] (every world's: ``world_max_kinetic_energy``)."""
        return float(self.world_max_kinetic_energy[0])

    @property
    def every(self) -> int:
        """Substeps between checks (the last substep of a frame is always checked)."""
        return self._every

    def begin(self) -> None:
        self.reset()

    def history(self) -> list:
        """The arrays a check carries to the next (the work put in, the last check's positions)."""
        return [self._work_total, self._previous_q]

    def restart(self, state: State | None = None) -> None:
        """Forget the work put in and measure from ``state`` (default the model's initial state) on."""
        self._work_total.zero_()
        wp.copy(self._previous_q, (state if state is not None else self.model).particle_q)

    def work(self) -> np.ndarray:
        """The work the loads put into each world since the start [J], float64, shape [world_count] (the
        positive parts, check by check; reads the device)."""
        return self._work_total.numpy().copy()

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
        force = self.control.particle_force if self.control is not None else None
        # The force on kinematic particles (a drive's work) is gathered even where the integrator scatters it.
        specs = tuple(dataclasses.replace(s, gathered=True) if getattr(s, "gathered", True) is False else s
                      for s in model.family_specs())
        measure, gather, locate, decide = guard_kernels(model.scalar, specs, self._tiled, force is not None)
        worlds, device = model.world_count, model.device
        flat_launch(measure, dim=reduce_launch_dim(worlds, model.particle_count, self._lanes), block_dim=self._lanes,
                    inputs=[model.particle_count, model.world_enabled, model.particle_flags, model.particle_mass,
                            model.elements, model.inputs, force if force is not None else state.particle_q,
                            state.particle_q, state.particle_qd],
                    outputs=[self._previous_q, self._status, self._partials], device=device)
        wp.launch(gather, dim=worlds, inputs=[model.world_enabled, self._partials, self._status],
                  outputs=[self._values, self._work_total], device=device)
        flat_launch(locate, dim=model.particle_dim, block_dim=model.block_dim,
                    inputs=[model.particle_count, model.world_enabled, model.elements, state.particle_q],
                    outputs=[self._status, self._values], device=device)
        wp.launch(decide, dim=worlds, inputs=[substep, self._limits, self._work_total],
                  outputs=[model.world_enabled, self._status, self._values], device=device)

    def reports(self) -> list[GuardReport]:
        """Each world's first failure since the last reset, in world order (reads the device: synchronises)."""
        status = self._status.numpy()
        values = self._values.numpy()
        reasons = {GUARD_NONFINITE: "non-finite state", GUARD_STRAIN: "strain", GUARD_ENERGY: "kinetic energy"}
        families = self.model.families
        found = []
        for world in np.flatnonzero(status[:, GUARD_TRIPPED]):
            row = status[world]
            reason = reasons[int(row[GUARD_TRIPPED])]
            particle = row[GUARD_NONFINITE_PARTICLE] if reason == "non-finite state" else row[GUARD_STRAIN_PARTICLE]
            index = row[GUARD_STRAIN_FAMILY]
            family = None if index == NO_PARTICLE or reason != "strain" else families[index].name
            element = None if family is None else int(row[GUARD_STRAIN_ELEMENT])
            found.append(GuardReport(
                world=int(world),
                reason=reason,
                substep=int(row[GUARD_SUBSTEP]),
                particle=None if particle == NO_PARTICLE else int(particle),
                spring=element if family == "springs" else None,
                strain=float(values[world, GUARD_MAX_STRAIN]),
                kinetic_energy=float(values[world, GUARD_KINETIC_ENERGY]),
                nonfinite_count=int(row[GUARD_NONFINITE_COUNT]),
                family=family,
                element=element,
            ))
        return found

    def report(self) -> GuardReport | None:
        """The earliest failure since the last reset (the lowest world among equals), or ``None`` (reads the
        device: synchronises)."""
        found = self.reports()
        return min(found, key=lambda r: (r.substep, r.world)) if found else None


def energy_scales(model: Model) -> np.ndarray:
    """Each world's energy scale [J], float64, shape [world_count]: initial kinetic + elastic energy (every
    family's) + total weight × (extent + 1 m), ≥ 1 µJ; the weight with the largest gravity the world has
    (now, or at any key of its gravity track)."""
    worlds, n = model.world_count, model.particle_count
    q = model.particle_q.numpy().astype(np.float64).reshape(worlds, n, 3)
    qd = model.particle_qd.numpy().astype(np.float64).reshape(worlds, n, 3)
    mass = model.world_values("particle_mass")
    kinetic = 0.5 * np.sum(mass * np.sum(qd * qd, axis=2), axis=1)
    elastic = world_elastic_energy(model)
    extent = np.ptp(q, axis=1).max(axis=1) if n else np.zeros(worlds)
    gravity = np.linalg.norm(model.world_values("gravity"), axis=1)
    for w in range(worlds):
        track = model.track("gravity", world=w)
        if track is not None:
            gravity[w] = max(gravity[w], float(np.linalg.norm(track.values, axis=1).max()))
    weight = mass.sum(axis=1) * gravity
    return np.maximum(kinetic + elastic + weight * (extent + 1.0), 1.0e-6)
