"""Integrators behind one interface, ``step(state_in, state_out, control, dt)``."""

from __future__ import annotations

from ..errors import ConfigError
from .base import Integrator
from .symplectic_euler import SymplecticEuler

#: Integrator classes by their scene-file / command-line name.
INTEGRATORS: dict[str, type[Integrator]] = {cls.name: cls for cls in (SymplecticEuler,)}


def make_integrator(name: str, model, **options) -> Integrator:
    """Build the integrator called ``name`` (see :data:`INTEGRATORS`) for ``model``."""
    try:
        cls = INTEGRATORS[name]
    except KeyError:
        raise ConfigError(f"unknown integrator {name!r}: choose one of {', '.join(sorted(INTEGRATORS))}") from None
    return cls(model, **options)


__all__ = ["INTEGRATORS", "Integrator", "SymplecticEuler", "make_integrator"]
