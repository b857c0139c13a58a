"""Exceptions that carry a message meant for the user: what is wrong and how to fix it."""

from __future__ import annotations

import errno as _errno
import os as _os


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


class OutputError(WarpspringError, OSError):
    """An output file could not be written: a full disk, a file or folder removed or made read-only mid-run.
    The message is one line naming the file, what could not be written (the frame) and the OS's reason;
    the command line ends with exit status 4.

    Attributes:
        path: the file.
        frame: the frame that could not be written, or ``None`` (not a frame: creating the file, closing it).
        frames_saved: frames the file holds on disk (frames 0 .. frames_saved - 1), or ``None`` if unknown.
        errno: the OS error number where one is known (e.g. ``errno.ENOSPC``), else ``None``.
    """

    def __init__(self, message: str, *, path: str | None = None, frame: int | None = None,
                 frames_saved: int | None = None, code: int | None = None):
        super().__init__(message)
        self.path = path
        self.frame = frame
        self.frames_saved = frames_saved
        self.errno = code


def os_error_reason(error: BaseException) -> str:
    """The reason of an OS error in words, never empty: its text and errno name ("No space left on device
    [ENOSPC]"), else the exception's own text on one line, else its class name."""
    code = getattr(error, "errno", None)
    name = _errno.errorcode.get(code) if isinstance(code, int) else None
    text = getattr(error, "strerror", None)
    if not text and isinstance(code, int):
        text = _os.strerror(code)
    if text:
        return f"{text} [{name}]" if name else str(text)
    words = " ".join(str(error).split())
    return words or f"{type(error).__name__} (no reason given)"


class StabilityWarning(UserWarning):
    """A run's state drifted toward the stability limit of its step (the run-time re-check of
    :class:`~warpspring.analysis.watch.StabilityWatch`): it may blow up. The message names the frame, the
    world and the substeps the state needs."""


class SolverWarning(UserWarning):
    """An implicit step's inner solve stopped at its iteration cap short of its tolerance (once per run, from the
    :class:`~warpspring.core.simulator.Simulator`): those steps are not the method's and may add energy. The message
    gives the residual reached and the remedy (more ``cg_iterations``, or more substeps)."""


class ContactOverflowWarning(UserWarning):
    """Contacts were found beyond a particle's slots in the contact buffer and dropped: those particles were
    not kept out of those colliders. Raise ``contact_slots`` in ``ModelBuilder.finalize``."""
