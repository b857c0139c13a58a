"""The speed/accuracy study's problems, each with its exact solution or the reference it is measured against.

* ``spring``, the seed case: a 45 kg block on a spring (k = 180 N/m, c = 18 N·s/m: ω₀ = 2 rad/s, ζ = 0.1)
  pushed from rest by a constant 75 N: it overshoots to 1.73× its 0.42 m equilibrium and rings down over
  the 10 s run (3.2 periods);
* ``stiff-spring``: 1 kg on k = 10⁴ N/m (ω₀ = 100 rad/s) with ζ = 0.01, pushed by 100 N, for 1 s (16 periods);
* ``cloth``: the hanging cloth of ANCHORS.md (0.1 m spacing, 0.1 kg particles, structural + shear + bend
  springs with ke = 1e3 N/m and kd = 10 N·s/m, two top corners pinned) released flat and swinging down
  for 1 s.

The springs are one particle tied by a spring to a pinned anchor, moving along x without gravity: the
closed form of :class:`~warpspring.analysis.analytic.DampedOscillator` is the reference. The cloth's reference is
a float64 RK4 run (:class:`ClothReference`, computed by the study: :mod:`warpspring.analysis.trade`). Each
problem builds its model and judges a run's errors (:meth:`SpringProblem.evaluate`,
:meth:`ClothProblem.evaluate`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..core.builder import ModelBuilder, SpringMaterial
from ..core.control import Control
from ..core.model import Model
from .analytic import DampedOscillator

#: A run whose position error exceeds this many times the problem's length scale has blown up.
BLOWUP_FACTOR = 10.0
#: ... and so has one that ends with more energy than the reference by more than this many times the
#: energy the motion was given: these damped systems cannot gain energy, so the integrator drove it.
ENERGY_BLOWUP = 1.0


@dataclass(frozen=True)
class SpringProblem:
    """One particle tied by a spring to a pinned anchor, driven by a constant force along x, without gravity.

    The anchor sits at x = −L and the particle starts at x₀ (the spring at its rest length L when x₀ = 0),
    so the particle's x coordinate is the oscillator's displacement and the spring stays along x: the
    motion is exactly that of :class:`DampedOscillator` with k = ke and c = kd.

    Attributes:
        name: problem name in tables and on the command line.
        oscillator: mass, stiffness, damping, force and initial state.
        duration: simulated time of each run [s].
        steps: fixed-step runs, as numbers of steps over ``duration`` (dt = duration / steps), coarse to fine.
        outputs: steps over ``duration`` of adaptive integrators (their dt, which they subdivide themselves).
        rest_length: L [m].
        plot_steps: the step count of the x(t), v(t) plot (``seed.png``), or ``None`` for no plot.
    """

    records_trajectory: ClassVar[bool] = True  # errors are taken over every step, not only at the end

    name: str
    oscillator: DampedOscillator
    duration: float
    steps: tuple[int, ...]
    outputs: int
    rest_length: float = 1.0
    plot_steps: int | None = None

    def describe(self) -> str:
        """One line naming the problem's parameters (inputs, not measurements)."""
        o = self.oscillator
        return (
            f"one {o.mass:g} kg particle on a spring to a pinned anchor, k = {o.stiffness:g} N/m, "
            f"c = {o.damping:g} N·s/m (ω₀ = {o.natural_frequency:.4g} rad/s, ζ = {o.damping_ratio:.3g}, "
            f"{o.regime}), pushed by F = {o.force:g} N along x from x(0) = {o.x0:g} m, v(0) = {o.v0:g} m/s, "
            f"no gravity; {self.duration:g} s simulated"
        )

    @property
    def fastest_frequency(self) -> float:
        """ω₀ [rad/s], the only frequency of the problem."""
        return self.oscillator.natural_frequency

    @property
    def length_scale(self) -> float:
        """Peak-to-peak excursion [m] of the exact x(t) over the run."""
        x = self.oscillator.position(np.linspace(0.0, self.duration, 20001))
        return float(np.ptp(x))

    def build(self, device, precision: str) -> tuple[Model, Control]:
        """The model (anchor = particle 0, pinned; block = particle 1) and a control holding the force."""
        o = self.oscillator
        builder = ModelBuilder(gravity=(0.0, 0.0, 0.0))
        builder.add_particles(
            [[-self.rest_length, 0.0, 0.0], [o.x0, 0.0, 0.0]],
            velocities=[[0.0, 0.0, 0.0], [o.v0, 0.0, 0.0]],
            mass=o.mass,
            pinned=[0],
        )
        builder.add_springs([[0, 1]], stiffness=o.stiffness, damping=o.damping, rest_length=self.rest_length)
        model = builder.finalize(device, precision=precision)
        control = model.control()
        control.set_particle_force([[0.0, 0.0, 0.0], [o.force, 0.0, 0.0]])
        return model, control

    def evaluate(self, t: np.ndarray, q: np.ndarray, qd: np.ndarray) -> dict:
        """Errors of a run sampled at times ``t`` [s], shape [samples], with positions ``q`` [m] and
        velocities ``qd`` [m/s], shape [samples, 2, 3]: the :class:`~warpspring.analysis.trade.Measurement` fields
        it determines."""
        x, v = q[:, 1, 0], qd[:, 1, 0]
        if not (np.isfinite(x).all() and np.isfinite(v).all()):
            return {"status": "non-finite"}
        exact = self.oscillator.position(t)
        error = np.abs(x - exact)
        if error.max() > BLOWUP_FACTOR * self.length_scale:
            return {"status": "blown up"}
        o = self.oscillator
        drift = float((o.state_energy(x[-1], v[-1]) - o.energy(t[-1])) / o.oscillation_energy)
        if drift > ENERGY_BLOWUP:
            return {"status": "blown up"}
        return {
            "status": "ok",
            "error_max": float(error.max()),
            "error_rms": float(np.sqrt(np.mean(error**2))),
            "error_end": float(error[-1]),
            "energy_drift": drift,
        }


@dataclass(frozen=True)
class ClothProblem:
    """The hanging cloth of ANCHORS.md: ``size`` × ``size`` particles ``spacing`` apart, ``particle_mass`` each,
    structural + shear + bend springs of one material, the two top corners pinned, gravity 9.81 m/s² down z.
    It starts flat, horizontal and at rest at z = 1 m, and swings down.

    Attributes:
        name: problem name in tables and on the command line.
        size: particles per side.
        duration: simulated time of each run [s]; errors are taken at its end.
        steps: fixed-step runs, as numbers of steps over ``duration``, coarse to fine.
        outputs: steps over ``duration`` of adaptive integrators.
        spacing: particle spacing [m].
        particle_mass: [kg].
        spring: stiffness ke [N/m] and damping kd [N·s/m] of every spring.
    """

    records_trajectory: ClassVar[bool] = False

    name: str
    size: int
    duration: float
    steps: tuple[int, ...]
    outputs: int
    spacing: float = 0.1
    particle_mass: float = 0.1
    spring: SpringMaterial = SpringMaterial(ke=1.0e3, kd=10.0)

    def describe(self) -> str:
        """One line naming the problem's parameters (inputs, not measurements)."""
        return (
            f"{self.size} × {self.size} particles {self.spacing:g} m apart, {self.particle_mass:g} kg each, "
            f"structural + shear + bend springs ke = {self.spring.ke:g} N/m, kd = {self.spring.kd:g} N·s/m, "
            f"two top corners pinned, released flat at rest under gravity; {self.duration:g} s simulated"
        )

    @property
    def length_scale(self) -> float:
        """Side length of the cloth [m]."""
        return (self.size - 1) * self.spacing

    def build(self, device, precision: str) -> tuple[Model, Control]:
        """The model and an empty control."""
        builder = ModelBuilder()
        half = 0.5 * self.length_scale
        builder.add_cloth_grid(
            nx=self.size,
            ny=self.size,
            spacing=self.spacing,
            origin=(-half, -half, 1.0),
            particle_mass=self.particle_mass,
            structural=self.spring,
            shear=self.spring,
            bend=self.spring,
            pin=["top-left", "top-right"],
        )
        model = builder.finalize(device, precision=precision)
        return model, model.control()

    def evaluate(self, q: np.ndarray, qd: np.ndarray, reference: ClothReference) -> dict:
        """Errors of the end state (positions ``q`` [m], velocities ``qd`` [m/s], shape [particles, 3])
        against ``reference``: the :class:`~warpspring.analysis.trade.Measurement` fields it determines."""
        if not (np.isfinite(q).all() and np.isfinite(qd).all()):
            return {"status": "non-finite"}
        error = np.linalg.norm(q - reference.q, axis=1)
        if error.max() > BLOWUP_FACTOR * self.length_scale:
            return {"status": "blown up"}
        drift = float((reference.geometry.energy(q, qd) - reference.energy) / reference.released)
        if drift > ENERGY_BLOWUP:
            return {"status": "blown up"}
        return {
            "status": "ok",
            "error_max": float(error.max()),
            "error_rms": float(np.sqrt(np.mean(error**2))),
            "energy_drift": drift,
            "max_strain": reference.geometry.max_strain(q),
        }


@dataclass(frozen=True)
class SpringNetwork:
    """Host copies (float64) of what the energy and strain of a spring network need (one world of a model).

    Attributes:
        mass: particle masses [kg], shape [particles].
        gravity: gravitational acceleration [m/s²], shape [3].
        springs: particle pairs, shape [springs, 2].
        rest_length: [m], shape [springs].
        stiffness: ke [N/m], shape [springs].
        initial_q: initial positions [m], shape [particles, 3].
        free: whether each particle moves (nonzero inverse mass), shape [particles].
    """

    mass: np.ndarray
    gravity: np.ndarray
    springs: np.ndarray
    rest_length: np.ndarray
    stiffness: np.ndarray
    initial_q: np.ndarray
    free: np.ndarray

    @classmethod
    def of(cls, model: Model, *, world: int = 0) -> SpringNetwork:
        """Read the arrays of ``world`` of ``model``."""
        n = model.particle_count
        return cls(
            mass=model.world_values("particle_mass")[world],
            gravity=model.world_values("gravity")[world],
            springs=model.spring_indices.numpy().reshape(-1, 2).astype(np.int64),
            rest_length=model.spring_rest_length.numpy().astype(np.float64),
            stiffness=model.world_values("spring_stiffness")[world],
            initial_q=model.particle_q.numpy().astype(np.float64)[world * n : (world + 1) * n],
            free=~model.kinematic_mask(world=world),
        )

    def lengths(self, q: np.ndarray) -> np.ndarray:
        """Spring lengths [m] at positions ``q`` [m], shape [particles, 3]."""
        return np.linalg.norm(q[self.springs[:, 1]] - q[self.springs[:, 0]], axis=1)

    def energy(self, q: np.ndarray, qd: np.ndarray) -> float:
        """Kinetic + gravitational (zero at the initial positions) + elastic energy [J]."""
        kinetic = 0.5 * float(np.sum(self.mass * np.sum(qd * qd, axis=1)))
        gravitational = -float(np.sum(self.mass * ((q - self.initial_q) @ self.gravity)))
        stretch = self.lengths(q) - self.rest_length
        return kinetic + gravitational + 0.5 * float(np.sum(self.stiffness * stretch * stretch))

    def max_strain(self, q: np.ndarray) -> float:
        """Largest (|d| − L) / L over the springs [-]."""
        return float(np.max(self.lengths(q) / self.rest_length - 1.0))


@dataclass(frozen=True)
class ClothReference:
    """The reference end state of a cloth problem.

    Attributes:
        integrator: integrator name.
        dt: its step [s].
        q: positions at the end [m], shape [particles, 3].
        energy: mechanical energy at the end [J] (see :meth:`SpringNetwork.energy`).
        released: gravitational energy released by the end [J]: the scale of the energy drift.
        max_strain: largest spring strain at the end [-].
        self_difference: max |q(dt) − q(2 dt)| [m]: the reference against itself at twice the step.
        fastest_frequency: ω_max of the cloth at rest [rad/s] (power iteration: ``estimate_omega_max``).
        wall: wall time of the two reference runs [s].
        geometry: the network's host arrays.
    """

    integrator: str
    dt: float
    q: np.ndarray
    energy: float
    released: float
    max_strain: float
    self_difference: float
    fastest_frequency: float
    wall: float
    geometry: SpringNetwork


#: The seed case and the stiff spring; see the module docstring.
SEED = DampedOscillator(mass=45.0, damping=18.0, stiffness=180.0, force=75.0)
STIFF = DampedOscillator.from_frequency(omega=100.0, zeta=0.01, mass=1.0, force=100.0)
