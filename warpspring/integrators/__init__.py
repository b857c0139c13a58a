"""Integrators behind one interface, ``step(state_in, state_out, control, dt)``."""

from __future__ import annotations

import inspect

from ..errors import ConfigError
from .base import Integrator
from .symplectic_euler import SymplecticEuler

#: Integrator classes by their scene-file / command-line name.
INTEGRATORS: dict[str, type[Integrator]] = {cls.name: cls for cls in (SymplecticEuler,)}


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


__all__ = ["INTEGRATORS", "Integrator", "SymplecticEuler", "make_integrator"]
