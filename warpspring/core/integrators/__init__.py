"""Integrators behind one interface, ``step(state_in, state_out, control, dt)``."""

from __future__ import annotations

import inspect

from ...errors import ConfigError
from .base import Integrator
from .dopri5 import DormandPrince
from .implicit_euler import ImplicitEuler
from .runge_kutta import RK4, ExplicitEuler, ExplicitRungeKutta, Midpoint
from .symplectic_euler import SymplecticEuler
from .verlet import VelocityVerlet

#: Integrator classes by their scene-file / command-line name.
INTEGRATORS: dict[str, type[Integrator]] = {
    cls.name: cls
    for cls in (ExplicitEuler, SymplecticEuler, VelocityVerlet, Midpoint, RK4, ImplicitEuler, DormandPrince)
}


def make_integrator(name: str, model, **options) -> Integrator:
    """Build the integrator called ``name`` (see :data:`INTEGRATORS`) for ``model`` with keyword ``options``.

    Raises:
        ConfigError: an unknown integrator name or an option the integrator does not take.
    """
    try:
        cls = INTEGRATORS[name]
    except KeyError:
        raise ConfigError(f"unknown integrator {name!r}: choose one of {', '.join(sorted(INTEGRATORS))}") from None
    params = inspect.signature(cls).parameters.values()
    allowed = [p.name for p in params if p.kind is p.KEYWORD_ONLY]
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise ConfigError(
            f"integrator {name!r} has no option {unknown[0]!r}; it takes: {', '.join(allowed) or 'no options'}"
        )
    return cls(model, **options)


__all__ = [
    "INTEGRATORS",
    "RK4",
    "DormandPrince",
    "ExplicitEuler",
    "ExplicitRungeKutta",
    "ImplicitEuler",
    "Integrator",
    "Midpoint",
    "SymplecticEuler",
    "VelocityVerlet",
    "make_integrator",
]
