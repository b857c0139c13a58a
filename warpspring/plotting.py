"""matplotlib, loaded on demand: plots are an optional extra (``pip install 'warpspring[plot]'``)."""

from __future__ import annotations

from .errors import ConfigError


def pyplot(purpose: str):
    """``matplotlib.pyplot`` on the non-interactive Agg backend, or a ConfigError naming ``purpose`` and
    the install command. Call it before long work whose results it will plot, so a missing extra fails
    at once."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ConfigError(f"{purpose} need matplotlib: pip install 'warpspring[plot]'") from None
    return plt
