"""Exceptions that carry a message meant for the user: what is wrong and how to fix it."""


class WarpspringError(Exception):
    """Base class of every error warpspring raises on purpose."""


class ConfigError(WarpspringError, ValueError):
    """Invalid input: a builder argument, a mesh, a scene file or a command-line option."""


class SimulationError(WarpspringError, RuntimeError):
    """A simulation went numerically bad (non-finite or runaway state) and was stopped.

    Attributes:
        frame: index of the frame being computed when the problem was found.
        substep: substep within that frame (``None`` when only known per frame).
    """

    def __init__(self, message: str, *, frame: int | None = None, substep: int | None = None):
        super().__init__(message)
        self.frame = frame
        self.substep = substep


class ContactOverflowWarning(UserWarning):
    """Contacts were found beyond a particle's slots in the contact buffer and dropped: those particles were
    not kept out of those colliders. Raise ``contact_slots`` in ``ModelBuilder.finalize``."""
