"""The run-time guard's settings and records: what it checks and how often (``GuardLimits``), its defaults and
the integrators and inputs its energy balance leaves out, the first failure it saw in a frame (``GuardReport``)
and each world's energy balance at its last check (``EnergyBalance``). The guard itself, the step hook that runs
the checks on the device, is ``guards.py``."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from .. import checks
from ..errors import ConfigError
from .model import Model

#: Default limit of the kinetic energy, as a multiple of the scene's energy scale (see GuardLimits).
ENERGY_FACTOR = 1.0e6


#: Default spring strain at which the guard stops a run (eleven times the rest length).
TEAR_STRAIN = 10.0

#: Default of the most frames one check may span where the scene allows it (``GuardLimits.check_frames``): a check
#: costs a fixed few microseconds of launches and block meetings however small the cloth, which a 32² frame of
#: symplectic Euler (~50 µs on an H200) cannot hide, while an instability the springs' bound does not certify is
#: checked every frame (or substep) as before; 8 frames are 0.13 s at 60 fps.
CHECK_FRAMES = 8

#: Default energy-balance tolerance: energy created beyond this fraction of the most energy the loads could
#: have supplied stops a run (``kernels/guards.py``). Symplectic Euler's own energy error on a swinging
#: cloth is ~1 % at 1/120 s and grows as O(h); an unstable RK4 cloth creates 30 % within 10 % above its
#: stability limit (bench/advisor_load.py).
ENERGY_BALANCE = 0.1
#: ... plus this fraction of the scene's energy scale (round-off of a world at rest).
BALANCE_FLOOR = 1.0e-3
#: Integrators whose balance leaves the dissipation out (D = 0, as before it was counted): those that need damping
#: to be stable. Their own energy error on a damped mode is a share of what its damper takes out that reaches
#: one at their stability limit (explicit Euler: ½ h² (m |a|² + vᵀ K v) per step, h / (2 kd/k) of the damping on
#: every spring mode; midpoint: (ωh)⁴/4 of the mode's energy per step against the damper's 2ζωh), so with D
#: their stable runs near the limit read as creating energy: explicit Euler's 1 MN/m cloth at 2000 substeps
#: (tests/test_extremes.py) and midpoint's battery cloth at 5.1 kN/m and 1/3840 s, inside the advisor's limit
#: (bench/RESULTS.md §11), were stopped. Adaptive integrators (dopri5) are left out too: their internal steps
#: are finer than the step the guard would integrate the power over.
DISSIPATION_UNCOUNTED = ("explicit_euler", "midpoint")
#: Integrators whose D samples the dampers' power at each substep's mean velocity (midpoint rule) instead of the
#: trapezoid of its ends: symplectic Euler's damper acts with the step's first velocity over the displacement
#: of its last, and the trapezoid over-counts what it takes out by ~(ωh)²/4 of it (+33 % at ωh = 1), read by
#: the balance as created energy (the battery's driven cloth at 1/480 s was stopped from 8.6 kN/m, where the
#: advisor passes 12.3 kN/m and the run is stable; bench/RESULTS.md §11).
MIDPOINT_DISSIPATION = ("symplectic_euler",)
#: Integrators whose balance cannot count the work of wind and handles: their forces damp (drag, a handle's Kd), and
#: explicit Euler creates ω²h² of a mode's energy per step at any step, a share ωh / 2ζ of what a damper of ratio ζ
#: takes out: counted exactly, a correct run reads as creating energy (a particle on a handle at ωh = 0.021,
#: ζ = 0.05: 20 % of the start's energy within 0.5 s, tests/test_guard_work.py). Midpoint's share, (ωh)³ / 8ζ, is
#: small but near its limit, where the springs' dampers (not counted for it) take the top modes: its battery in
#: wind and on a handle stopped no run the advisor passes (bench/RESULTS.md §11).
WORK_UNCOUNTED = ("explicit_euler",)
#: Live inputs whose value is part of the springs' potential: animated by a track, the elastic energy
#: changes without work and the balance is off.
POTENTIAL_INPUTS = ("biphasic_strain", "biphasic_ratio", "max_spring_force")


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
        energy_balance: energy created [-]: a world whose kinetic plus elastic energy exceeds its value at the
            start plus the work its loads put in since, less the energy its dampers and drag took out (counted
            per substep where the guard knows the step: a Simulator's; not for explicit Euler, midpoint and
            dopri5, ``DISSIPATION_UNCOUNTED``, nor with contacts or strain limiting, ``dissipation_exact``), by
            more than this fraction of the most
            energy they could have supplied so far (plus ``BALANCE_FLOOR`` × its energy scale) is unstable and
            stops
            (default ``ENERGY_BALANCE`` = 0.1; 0 switches it off). The balance re-bases when the model's
            values are written between frames, and is off where it cannot be kept: colliders that move (their
            work is not counted), the particle force clamp (not a potential), tracks of the springs' law
            (biphasic knee and ratio, force clamp), and unconditionally stable integrators (implicit Euler:
            the energy its one Newton step per step adds at large steps is not an instability).
        dissipation: count the energy the springs' and hinges' dampers and viscous drag take out (D) in the
            energy balance (default on): integrated after every substep (one launch per damped family, one for
            drag; ``kernels/guards.py``), so a long damped run keeps its sensitivity; off, that energy is
            slack the balance allows an instability to re-create.
        stop: what a failure stops: "run" (the simulator raises a SimulationError at the end of the frame)
            or "world" (the failed world is held from the failing check on, its failure is recorded in
            ``Simulator.world_failures``, and the other worlds go on; the run stops only when every world
            has failed).
        check_frames: the most frames a check may span (default ``CHECK_FRAMES`` = 8; 1 checks every frame) where
            the scene allows it: a simulator that reads each verdict a frame later (``defer_verdict``, the
            default) and not read frame by frame, ``stop="run"``, no frame watched (a step the springs' bound does
            not certify is checked after every substep for the first frames from a restart or a write; explicit
            Euler and midpoint, whose damping limit the bound cannot certify, never span), nothing
            the guard counts between substeps of its own (a step that sums the power itself), and loads that cannot
            change unseen between frames (gravity and the model's own springs; no control force, wind, handles,
            tracks, driven pins, moving colliders, emitters or self-collision). Where it
            spans, a frame's check also covers the frames since the last one (the balance, the work and the
            dissipation are sums over the span, not samples), and a frame that is read (``Simulator.settle``,
            ``Simulator.state``) is checked first. Elsewhere every frame is checked.
        max_strain: deprecated name of ``tear_strain`` (a DeprecationWarning; same value; also readable
            as a deprecated property).

    Raises:
        ConfigError: a value out of range.
        TypeError: both ``tear_strain`` and its deprecated name ``max_strain``.
    """

    every: int | None = None
    tear_strain: float = TEAR_STRAIN
    max_kinetic_energy: float | None = None
    energy_balance: float = ENERGY_BALANCE
    stop: str = "run"
    dissipation: bool = True
    check_frames: int = CHECK_FRAMES

    def __init__(self, *, every: int | None = None, tear_strain: float | None = None,
                 max_kinetic_energy: float | None = None, energy_balance: float = ENERGY_BALANCE, stop: str = "run",
                 max_strain: float | None = None, dissipation: bool = True, check_frames: int = CHECK_FRAMES):
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
        checks.count("guard check_frames", check_frames, minimum=1)
        checks.positive(name, tear_strain)
        if max_kinetic_energy is not None:
            checks.positive("guard max_kinetic_energy", max_kinetic_energy)
        if stop not in ("run", "world"):
            raise ConfigError(f"guard stop must be 'run' or 'world', got {stop!r}")
        checks.non_negative("guard energy_balance", energy_balance)
        if not isinstance(dissipation, bool):
            raise ConfigError(f"guard dissipation must be true or false, got {dissipation!r}")
        object.__setattr__(self, "dissipation", dissipation)
        object.__setattr__(self, "check_frames", int(check_frames))
        object.__setattr__(self, "energy_balance", float(energy_balance))
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
        reason: "non-finite state", "strain", "kinetic energy" or "energy balance".
        substep: substep of the frame at whose check it was seen (the failure happened at or before it).
        particle: index of the offending particle (lowest-index non-finite one, or one holding the worst
            element).
        spring: index of the most strained spring, or ``None`` (also when the worst element is not a spring).
        nonfinite_count: particles with a non-finite position or velocity at that check.
        strain: largest element strain at that check [-] (springs: |d|/L - 1).
        family: name of the family of the most strained element ("springs", ...), or ``None``.
        element: index of the most strained element in its family, or ``None``.
        kinetic_energy: total kinetic energy at that check [J].
        energy_created: kinetic + elastic energy beyond the start's plus the work put in, at that check [J].
        energy_budget: the most energy the start and the loads could have supplied so far [J].
        stability_ratio: with reason "stability limit" (found by the stability watch, not a check: ``StabilityWatch``
            given ``stop``), the world's ω_max over the highest frequency its step keeps stable; else ``None``.
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
    energy_created: float = 0.0
    energy_budget: float = 0.0
    stability_ratio: float | None = None

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
            family = next((f for f in model.families if f.name == self.family), None)
            if family is None or self.element is None:  # (a record whose search found no element: never expected)
                return (f"{where}an element stretched to {self.strain + 1:.3g}× its rest length (guard limit "
                        "exceeded; the element was not identified)")
            return (f"{where}{family.describe_element(model, self.element)} stretched to {self.strain + 1:.3g}× its "
                    "rest length (guard limit exceeded)")
        if self.reason == "stability limit":
            if self.stability_ratio is None:
                return f"{where}the state passed its step's stability limit (by the stability watch)"
            return (f"{where}the state passed its step's stability limit (ω_max {self.stability_ratio:.3g}× the highest "
                    "frequency the step keeps stable, by the stability watch)")
        if self.reason == "energy balance":
            share = self.energy_created / self.energy_budget if self.energy_budget > 0.0 else math.inf
            return (f"{where}the integration created {self.energy_created:.3g} J of energy ({share:.0%} of the "
                    f"{self.energy_budget:.3g} J the start and the loads supplied; guard limit exceeded): the step "
                    "is unstable at the state the run reached")
        return f"{where}the kinetic energy ran away to {self.kinetic_energy:.3g} J (guard limit exceeded)"


@dataclass(frozen=True)
class EnergyBalance:
    """A guard's energy balance per world at its last check (``kernels/guards.py``), float64 arrays of shape
    [world_count].

    Attributes:
        energy: kinetic (free particles) + elastic energy [J].
        reference: E_ref, the energy at the last rebase less the work counted until then [J].
        work: the loads' net work since the start, W [J] (signed: weight, the control's force, drives).
        peak: the most energy the start and the loads could have supplied so far, max of E_ref + W [J].
        dissipated: D, the energy the springs' and hinges' dampers and viscous drag took out since the last
            rebase [J] (≥ 0; zero where the guard does not count it: no step given, balance off).
    """

    energy: np.ndarray
    reference: np.ndarray
    work: np.ndarray
    peak: np.ndarray
    dissipated: np.ndarray

    @property
    def created(self) -> np.ndarray:
        """Energy beyond the balance, E - (E_ref + W - D) [J]: ≈ 0 up to the integrator's energy error (and
        ≤ 0 by what is not counted: contact and friction losses)."""
        return self.energy - self.reference - self.work + self.dissipated


@dataclass(frozen=True)
class BalanceTerms:
    """What a guard's energy balance counts for a model as it is now, term by term as the scene names them
    (``Guard.balance_terms``, :func:`balance_terms`; the run summary prints :meth:`describe`).

    Attributes:
        on: whether the balance is kept (its tolerance > 0 and the work of every load in the scene known).
        counted: the loads whose work it counts and the losses it counts, exactly up to the integrator's error.
        losses: what takes energy out that it does not count (contacts, clamps, dampers without a count): the
            balance then checks E ≤ E_ref + W − D with D without them, one-sided (never a stop for them, but an
            instability must first re-create what they took out).
        off: why it is off, each a term whose energy it cannot count (empty where on); the guard then checks
            non-finite states, tears and runaway kinetic energy only.
    """

    on: bool
    counted: tuple = ()
    losses: tuple = ()
    off: tuple = ()

    def describe(self) -> str:
        """One clause for the run summary."""
        if not self.on:
            return (f"energy balance off ({'; '.join(self.off)}): the guard checks non-finite states, tears and "
                    "runaway kinetic energy")
        text = "energy balance counts " + (", ".join(self.counted) if self.counted else "the elastic energy")
        if self.losses:
            text += (f"; not counted, losses only: {', '.join(self.losses)} (the balance checks that the energy "
                     "stays at or below the start's plus the loads' work less the counted losses: one-sided)")
        return text


def balance_terms(model: Model, *, integrator, control, limits: GuardLimits, dissipation: bool,
                  work_countable: bool, counted_losses: bool) -> BalanceTerms:
    """Each term of ``model`` and its place in the energy balance (:class:`BalanceTerms`). ``dissipation``: the guard
    integrates the dampers' power (a step given, ``limits.dissipation``, an integrator outside
    ``DISSIPATION_UNCOUNTED``); ``counted_losses``: and the model lets it count them (``guards.dissipation_exact``);
    ``work_countable``: the integrator lets it count the work of wind and handles (``WORK_UNCOUNTED``)."""
    name = getattr(integrator, "name", None) or "the integrator"
    off = []
    if limits.energy_balance <= 0.0:
        off.append("switched off: energy_balance = 0")
    if getattr(integrator, "unconditionally_stable", False):
        off.append(f"{name} is unconditionally stable: the energy its steps add at large steps is no instability")
    if model.shape_moving:
        off.append("the work of moving colliders is not counted")
    if getattr(model, "shape_deforming", False):
        off.append("the work of deforming mesh colliders is not counted")
    if model.emitters:
        off.append("the energy entering with emitted particles is not counted")
    if model.stabilizers.enabled("max_particle_force"):
        off.append("the particle force clamp is not a potential")
    working = [family.name for family in model.families if family.does_work]
    if working and not work_countable:
        off.append(f"the work of {' and '.join(working)} is not counted for {name}")
    animated = [key for key in POTENTIAL_INPUTS if key in getattr(model, "_tracks", {})]
    if animated:
        off.append(f"animated {', '.join(animated)} change the springs' potential without work")
    features = model.force_features(control)
    counted, losses = [], []
    gravity = np.linalg.norm(model.world_values("gravity"), axis=1).max() > 0.0 or "gravity" in model._tracks
    if gravity:
        counted.append("the work of weight")
    if features.external:
        counted.append("the work of the control's external force")
    if model.kinematic_mask().any() or model.pin_groups is not None:
        counted.append("the work of the pins' drives (by the trapezoid of their force between checks)")
    counted += [f"the work of {family}" for family in working]
    if features.drag and features.wind:
        counted.append("the work of the wind's push through drag")
    counted += [f"the elastic energy of the {family.name}" for family in model.families
                if not family.does_work and family.element_count]
    damped = [family for family in model.families if not family.does_work and family.element_count]
    for family in damped:
        hooks = family.spec(model).funcs(model.scalar)
        if getattr(hooks, "dissipation", None) is not None and dissipation and counted_losses:
            counted.append(f"the loss to the {family.name}' dampers")
        else:
            losses.append(f"the {family.name}' damping")
    if features.drag:
        if dissipation and counted_losses:
            counted.append("the loss to drag")
        else:
            losses.append("drag")
    finish = getattr(integrator, "finish_step", None)
    # With self-collision the guard counts the energy change across the step's last passes (``Guard._count_corrections``):
    # the contacts' too, where no stabiliser runs before them (which moves the pins: its bracket starts after it).
    bracketed = getattr(model, "self_contact", None) is not None and finish is not None
    if model.shape_count:
        contacts = f"contacts with {model.shape_count} collider{'s' if model.shape_count > 1 else ''}"
        if bracketed and not finish.stabilised:
            counted.append(f"the work of {contacts} (the energy change across their pass)")
        else:
            losses.append(f"{contacts} (response and friction)")
    if bracketed:
        counted.append("the work of self-collision's corrections (the energy change across its pass)")
    elif getattr(model, "self_contact", None) is not None:
        losses.append("self-collision")
    if model.stabilizers.enabled("max_strain"):
        losses.append("strain limiting")
    if model.stabilizers.enabled("max_speed"):
        losses.append("the speed clamp")
    if model.spring_plastic_count:
        losses.append("plastic flow and breaking of springs")
    return BalanceTerms(on=not off, counted=tuple(counted), losses=tuple(losses), off=tuple(off))


#: The largest ω h [-] at which each fixed-step integrator is stable on an undamped mode (its amplification's
#: modulus reaches 1 there: symplectic Euler and velocity Verlet 2, RK4 2√2); the others need damping
#: (explicit Euler, midpoint) or have no limit.
STABLE_OMEGA_H = {"symplectic_euler": 2.0, "velocity_verlet": 2.0, "rk4": 2.0 * math.sqrt(2.0)}

#: The amplification per step of an undamped mode of angular frequency ω [rad/s] at step h [s], |R(iωh)|, of the
#: integrators that have no undamped limit (any undamped mode grows: their limit is their damping's): explicit Euler
#: √(1 + (ωh)²), midpoint √(1 + (ωh)⁴/4). Past their damping limit a mode grows by little more than 1 per step, but a
#: mode with ωh of a few grows by several (the spring made 100× stiffer in the guard's battery: non-finite within the
#: frame after the write, checked once a frame).
UNDAMPED_GROWTH = {"explicit_euler": lambda omega_h: math.sqrt(1.0 + omega_h ** 2),
                   "midpoint": lambda omega_h: math.sqrt(1.0 + 0.25 * omega_h ** 4)}


def spring_bounds(model: Model, world: int = 0) -> tuple[int, float, float, float] | None:
    """(the particle whose springs bound the network, its stiffest spring's ke [N/m], Gershgorin bounds of ω_max
    [rad/s] and of the damping rate λ_D [1/s]) of ``world``'s springs: ω_max² ≤ maxᵢ Σₛ keₛ (wᵢ + √(wᵢ wⱼ)) over the
    springs s = (i, j) at i, w the inverse masses (a kinematic end: w = 0), and λ_D likewise with kd; ``None``
    without springs with a free end (float64, reads the device)."""
    if model.spring_count == 0:
        return None
    ends = model.spring_indices.numpy()
    ke = model.world_values("spring_stiffness")[world]
    kd = model.world_values("spring_damping")[world]
    w = model.world_values("particle_inv_mass")[world]
    stiffness = np.zeros(model.particle_count)
    damping = np.zeros(model.particle_count)
    for a, b in ((0, 1), (1, 0)):
        i, j = ends[:, a], ends[:, b]
        share = w[i] + np.sqrt(w[i] * w[j])
        np.add.at(stiffness, i, ke * share)
        np.add.at(damping, i, kd * share)
    particle = int(np.argmax(stiffness))
    if stiffness[particle] <= 0.0:
        return None
    at = (ends[:, 0] == particle) | (ends[:, 1] == particle)
    return particle, float(ke[at].max()), float(math.sqrt(stiffness[particle])), float(damping.max())


def scene_suspects(model: Model, *, control=None) -> list[str]:
    """What in ``model`` can put energy into a run besides its elastic forces, each named as the scene has it:
    contacts (colliders, self-collision, the ground), loads (the control's force, wind, handles, driven pins,
    animated inputs, emitters)."""
    found = []
    if model.shape_count:
        found.append(f"contacts with {model.shape_count} collider{'s' if model.shape_count > 1 else ''}")
    if getattr(model, "self_contact", None) is not None:
        found.append("self-collision")
    if control is not None and getattr(control, "particle_force", None) is not None:
        found.append("the control's external force")
    for family in model.families:
        if family.does_work:
            found.append(family.name)
    if getattr(model, "pin_groups", None) is not None:
        found.append("driven pins")
    tracks = sorted(getattr(model, "_tracks", {}))
    if tracks:
        found.append("animated " + ", ".join(tracks))
    if getattr(model, "emitters", None):
        found.append("emitters")
    return found


def remedy_substeps(model: Model, *, integrator: str | None, substeps: int, dt: float, world: int = 0) -> int:
    """The substeps :func:`stop_advice` prints as a remedy for ``world``: twice ``substeps``, or as many as bring the
    springs' bound of ω_max h (:func:`spring_bounds`) to half the integrator's undamped limit and their dampers'
    rate to 1/h, whichever is more."""
    target = 2 * substeps
    limit = STABLE_OMEGA_H.get(integrator or "")
    bounds = spring_bounds(model, world)
    if bounds is not None and limit is not None:
        _, _, omega, damping = bounds
        target = max(target, math.ceil(substeps * omega * dt / (0.5 * limit)), math.ceil(substeps * damping * dt))
    return target


def describe_suspects(model: Model, *, control=None) -> str:
    """The scene's suspects besides its elements and the step (:func:`scene_suspects`) as one phrase."""
    found = scene_suspects(model, control=control)
    return "; ".join(found) if found else "none besides its elements (no contacts, no loads from outside)"


def stop_advice(report: GuardReport, model: Model, *, integrator: str | None, substeps: int, dt: float,
                control=None) -> str:
    """What to suspect and what to try after a stop: the step h [s] (``substeps`` per frame, with ``integrator``)
    against the stiffest spring's bound of ω_max h (:func:`spring_bounds`) and the integrator's limit, then the scene's
    other suspects (:func:`scene_suspects`), and a remedy a run can take as printed: twice the substeps, or as many
    as bring the bound to half the limit and the dampers' rate to 1/h, whichever is more. A tear (``strain``) at a
    step whose bound is within the limit is over-stretch (the bound holds at every stretch of a Hooke spring: its
    stiffness across the spring is below ke), and the remedy is the material, not the step (the advisor's
    diagnosis, ``analysis.advisor.diagnose``, tells it at the stretched state the run reached). Empty for a scene
    with neither springs nor other suspects (free particles under steady loads: no step of theirs is unstable)."""
    clauses = []
    target = remedy_substeps(model, integrator=integrator, substeps=substeps, dt=dt, world=report.world)
    limit = STABLE_OMEGA_H.get(integrator or "")
    bounds = spring_bounds(model, report.world)
    step = f"the step (h = {dt * 1e3:.3g} ms, {substeps} substeps per frame)"
    within = False
    if bounds is not None:
        particle, ke, omega, damping = bounds
        where = f"the springs at particle {particle}, ke up to {ke:.3g} N/m: ω_max h ≤ {omega * dt:.2f}"
        if limit is not None:
            where += f" against {integrator}'s limit {limit:.2f}"
            if damping * dt > 1.0:  # the dampers past their own limit: named, whatever the stiffness says
                where += f", their dampers' rate λ_D h ≤ {damping * dt:.2f} against 1"
            # (the bound covers Hooke springs only: not biphasic ones, hinges or tets)
            hooke = (not model.stabilizers.enabled("biphasic_strain")
                     and all(family.name == "springs" or family.does_work for family in model.families))
            within = hooke and omega * dt <= limit and damping * dt <= 1.0
        step += f" against the stiffest elements ({where})"
    others = scene_suspects(model, control=control)
    if bounds is None and not others:
        return ""  # free particles under steady loads: no step is unstable, nothing in the scene to name
    clauses.append(step)
    clauses += others
    suspects = f"suspects in this scene: {'; '.join(clauses)}."
    if report.reason == "strain" and within:
        return (f"{suspects} The step is within the limit for these springs at any stretch, so they really stretch "
                "that far: stiffer springs (ke), strain limiting (Stabilizers(max_strain=0.1)) or biphasic springs")
    return (f"{suspects} Remedy: run with substeps = {target} (a bound: the advisor's estimate, where it runs, is "
            "tighter)")
