"""Closed-form solutions the integrators are measured against.

:class:`DampedOscillator` is the driven, damped spring-mass m ẍ + c ẋ + k x = F with x(0) = x₀, ẋ(0) = v₀:
under-, critically and over-damped, its exact position, velocity and mechanical energy at any time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError


@dataclass(frozen=True)
class DampedOscillator:
    """The driven, damped oscillator m ẍ + c ẋ + k x = F, x(0) = x₀, ẋ(0) = v₀, solved in closed form.

    With y = x − F/k (the displacement from equilibrium), σ = c / 2m and λ = k/m − σ² the solution is
    y(t) = e^(−σt) (y₀ C(t) + (v₀ + σ y₀) S(t)), ẋ(t) = e^(−σt) (v₀ C(t) − (σ v₀ + ω₀² y₀) S(t)), where
    C = cos(ω_d t), S = sin(ω_d t) / ω_d with ω_d = √λ (underdamped, λ > 0); C = 1, S = t (critical, λ = 0);
    C = cosh(γ t), S = sinh(γ t) / γ with γ = √(−λ) (overdamped, λ < 0). S is evaluated in forms that stay
    accurate as λ → 0 from either side and that never overflow for large t.

    Attributes:
        mass: m [kg], > 0.
        damping: c [N·s/m], ≥ 0.
        stiffness: k [N/m], > 0.
        force: constant driving force F [N].
        x0: initial position x(0) [m], measured from the spring's rest length.
        v0: initial velocity ẋ(0) [m/s].

    Example:
        >>> block = DampedOscillator(mass=45.0, damping=18.0, stiffness=180.0, force=75.0)
        >>> round(block.natural_frequency, 3), round(block.damping_ratio, 3), block.regime
        (2.0, 0.1, 'underdamped')
    """

    mass: float
    damping: float
    stiffness: float
    force: float = 0.0
    x0: float = 0.0
    v0: float = 0.0

    def __post_init__(self):
        for name in ("mass", "damping", "stiffness", "force", "x0", "v0"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise ConfigError(f"oscillator {name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ConfigError(f"oscillator {name} must be finite, got {value!r}")
        if self.mass <= 0.0 or self.stiffness <= 0.0 or self.damping < 0.0:
            raise ConfigError(
                f"oscillator needs mass > 0, stiffness > 0 and damping >= 0, got m = {self.mass}, "
                f"k = {self.stiffness}, c = {self.damping}"
            )

    @classmethod
    def from_frequency(
        cls, *, omega: float, zeta: float, mass: float = 1.0, force: float = 0.0, x0: float = 0.0, v0: float = 0.0
    ) -> DampedOscillator:
        """The oscillator of natural frequency ``omega`` [rad/s] and damping ratio ``zeta`` [-] for ``mass`` [kg]:
        k = m ω², c = 2 ζ m ω."""
        damping, stiffness = 2.0 * zeta * mass * omega, mass * omega * omega
        return cls(mass=mass, damping=damping, stiffness=stiffness, force=force, x0=x0, v0=v0)

    # -- characteristics ----------------------------------------------------------------------------

    @property
    def natural_frequency(self) -> float:
        """ω₀ = √(k/m) [rad/s]."""
        return math.sqrt(self.stiffness / self.mass)

    @property
    def damping_ratio(self) -> float:
        """ζ = c / (2√(km)) [-]."""
        return self.damping / (2.0 * math.sqrt(self.stiffness * self.mass))

    @property
    def decay_rate(self) -> float:
        """σ = c / 2m [1/s]: the envelope of an underdamped motion decays as e^(−σt)."""
        return self.damping / (2.0 * self.mass)

    @property
    def equilibrium(self) -> float:
        """x_eq = F / k [m], where the motion comes to rest."""
        return self.force / self.stiffness

    @property
    def regime(self) -> str:
        """"underdamped" (ζ < 1), "critical" (ζ = 1) or "overdamped" (ζ > 1), from the sign of 4km − c²."""
        discriminant = 4.0 * self.stiffness * self.mass - self.damping * self.damping
        return "underdamped" if discriminant > 0.0 else "critical" if discriminant == 0.0 else "overdamped"

    # -- solution -------------------------------------------------------------------------------------

    def _basis(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(e^(−σt) C(t), e^(−σt) S(t)) of the class docstring."""
        sigma = self.decay_rate
        lam = (4.0 * self.stiffness * self.mass - self.damping * self.damping) / (4.0 * self.mass * self.mass)
        if lam > 0.0:
            omega_d = math.sqrt(lam)
            envelope = np.exp(-sigma * t)
            # sin(ω_d t) / ω_d = t · sinc(ω_d t / π): no division by a small ω_d near critical damping.
            return envelope * np.cos(omega_d * t), envelope * t * np.sinc(omega_d * t / math.pi)
        if lam == 0.0:
            envelope = np.exp(-sigma * t)
            return envelope, envelope * t
        gamma = math.sqrt(-lam)
        slow = -self.natural_frequency**2 / (sigma + gamma)  # −σ + γ without cancellation
        fast = -sigma - gamma
        e_slow, e_fast = np.exp(slow * t), np.exp(fast * t)
        # e^(−σt) sinh(γt)/γ = e^(slow·t) (1 − e^(−2γt)) / 2γ: exact as γ → 0, no overflow as t → ∞.
        return 0.5 * (e_slow + e_fast), e_slow * -np.expm1(-2.0 * gamma * t) / (2.0 * gamma)

    def position(self, t) -> np.ndarray:
        """x(t) [m] at times ``t`` [s] (a scalar or an array; the result has its shape)."""
        return self.state(t)[0]

    def velocity(self, t) -> np.ndarray:
        """ẋ(t) [m/s] at times ``t`` [s] (a scalar or an array; the result has its shape)."""
        return self.state(t)[1]

    def state(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(x(t) [m], ẋ(t) [m/s]) at times ``t`` [s], each of the shape of ``t``."""
        t = np.asarray(t, dtype=np.float64)
        decaying_cos, decaying_sin = self._basis(t)
        sigma, y0 = self.decay_rate, self.x0 - self.equilibrium
        x = self.equilibrium + y0 * decaying_cos + (self.v0 + sigma * y0) * decaying_sin
        v = self.v0 * decaying_cos - (sigma * self.v0 + self.natural_frequency**2 * y0) * decaying_sin
        return x, v

    # -- energy ---------------------------------------------------------------------------------------

    def state_energy(self, x, v) -> np.ndarray:
        """Mechanical energy [J] of any state (x [m], ẋ [m/s]): E = ½ m ẋ² + ½ k x² − F x.

        The last term is the potential of the constant force, so that dE/dt = −c ẋ² along the motion.
        Shapes broadcast.
        """
        x, v = np.asarray(x, dtype=np.float64), np.asarray(v, dtype=np.float64)
        return 0.5 * self.mass * v * v + 0.5 * self.stiffness * x * x - self.force * x

    def energy(self, t) -> np.ndarray:
        """Mechanical energy [J] of the exact solution at times ``t`` [s] (see :meth:`state_energy`)."""
        return self.state_energy(*self.state(t))

    @property
    def oscillation_energy(self) -> float:
        """E(0) − E(x_eq, 0) [J]: the energy above rest that damping removes over the whole motion."""
        return float(self.state_energy(self.x0, self.v0) - self.state_energy(self.equilibrium, 0.0))
