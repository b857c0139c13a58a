"""The heavy elastica in float64: a strip clamped horizontally at one end and bent by its own weight, and the
overhang at which the line from the clamp to its tip falls by a given angle (ASTM D1388's cantilever test).

A strip of bending rigidity B [N·m] (per unit width) and weight w = ρ_A g [N/m²] (per unit area) overhangs
the clamp by L [m]. With s the arc length from the clamp and θ(s) the angle of the strip below the horizontal,
the moment of the weight beyond s balances B θ'(s); differentiated::

    B θ'' = -w (L - s) cos θ,    θ(0) = 0 (clamped),    θ'(L) = 0 (free end: no moment).

Scaled by the bending length c = (B / w)^⅓ (s = c σ, Λ = L / c) it has one parameter, Λ:
θ'' = -(Λ - σ) cos θ. Its shape is x = ∫ cos θ, y = -∫ sin θ, and the tip's chord angle
atan(-y(L) / x(L)) grows with Λ alone. D1388 slides the strip off the platform until its tip meets a plane
inclined at 41.5° below the platform's edge: the chord angle is then 41.5°, and the overhang L = Λ* c, Λ* from
:func:`overhang_ratio`. Peirce (1930, "The handle of cloth as a measurable quantity", J. Textile Inst. 21,
T377) chose 41.5° so that c = L / 2; the exact elastica gives Λ* = 2.0003 (c = 0.4999 L), his approximate
formula c = L (cos ½θ / 8 tan θ)^⅓ gives Λ = 1.963 (:func:`peirce_ratio`).

Solved with SciPy's ``solve_bvp`` (collocation, residual tolerance 1e-10) and checked by shooting with
``solve_ivp`` in the tests.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
from scipy.integrate import cumulative_trapezoid, solve_bvp
from scipy.optimize import brentq

from .. import checks

#: ASTM D1388's incline below the horizontal [rad] (41.5°).
D1388_ANGLE = math.radians(41.5)
_TOLERANCE = 1.0e-10


class Elastica(NamedTuple):
    """A clamped heavy strip's shape, scaled by its bending length c (multiply lengths by c for metres)."""

    sigma: np.ndarray  # [-], arc length / c from the clamp, shape [n]
    theta: np.ndarray  # [rad], angle below the horizontal, shape [n]
    x: np.ndarray  # [-], horizontal distance from the clamp / c, shape [n]
    y: np.ndarray  # [-], height above the clamp / c (≤ 0), shape [n]

    @property
    def chord_angle(self) -> float:
        """Angle [rad] below the horizontal of the line from the clamp to the tip."""
        return math.atan2(-self.y[-1], self.x[-1])

    @property
    def tip_drop(self) -> float:
        """The tip's drop below the clamp / c."""
        return -self.y[-1]


@functools.cache
def elastica(overhang_ratio: float, points: int = 401) -> Elastica:
    """The clamped heavy elastica of scaled length Λ = L / c (``overhang_ratio``, > 0)."""
    span = checks.positive("overhang_ratio", overhang_ratio)
    sigma = np.linspace(0.0, span, points)

    def rhs(s, u):  # u = (θ, θ')
        return np.vstack([u[1], -(span - s) * np.cos(u[0])])

    def bc(ua, ub):
        return np.array([ua[0], ub[1]])

    # Start from the small-deflection solution θ = (Λ³ - (Λ - σ)³) / 6.
    guess = np.vstack([(span**3 - (span - sigma) ** 3) / 6.0, 0.5 * (span - sigma) ** 2])
    solution = solve_bvp(rhs, bc, sigma, guess, tol=_TOLERANCE, max_nodes=100_000)
    if not solution.success:  # pragma: no cover - the problem is smooth and well posed for every Λ
        raise RuntimeError(f"the heavy elastica did not converge at L/c = {span}: {solution.message}")
    fine = np.linspace(0.0, span, 20 * (points - 1) + 1)  # every 20th is a point of sigma
    theta = solution.sol(fine)[0]
    x = cumulative_trapezoid(np.cos(theta), fine, initial=0.0)
    y = -cumulative_trapezoid(np.sin(theta), fine, initial=0.0)
    keep = slice(None, None, 20)
    return Elastica(fine[keep], theta[keep], x[keep], y[keep])


@functools.cache
def overhang_ratio(angle: float = D1388_ANGLE) -> float:
    """Λ* = L / c at which the clamp-to-tip chord falls by ``angle`` [rad] (default 41.5°, D1388)."""
    angle = checks.positive("angle", angle)
    if angle >= 0.5 * math.pi:
        raise ValueError(f"angle must be below π/2 (a strip never hangs past vertical), got {angle}")
    upper = 1.0
    while elastica(upper).chord_angle < angle:
        upper *= 2.0
    return brentq(lambda span: elastica(span).chord_angle - angle, 1e-3, upper, xtol=1e-12, rtol=1e-12)


def bending_length(bending: float, density: float, gravity: float = 9.81) -> float:
    """c = (B / (ρ_A g))^⅓ [m] of a sheet of bending stiffness B [N·m] and areal density ρ_A [kg/m²]."""
    return (checks.positive("bending", bending) / (checks.positive("density", density) * gravity)) ** (1.0 / 3.0)


def d1388_overhang(bending: float, density: float, gravity: float = 9.81) -> float:
    """The overhang [m] at which ASTM D1388's strip meets the 41.5° incline: Λ* c."""
    return overhang_ratio() * bending_length(bending, density, gravity)


def peirce_ratio(angle: float = D1388_ANGLE) -> float:
    """Peirce's approximate L / c = (8 tan θ / cos ½θ)^⅓ (1.963 at 41.5°, 1.8 % below the exact 2.0003)."""
    return (8.0 * math.tan(angle) / math.cos(0.5 * angle)) ** (1.0 / 3.0)
