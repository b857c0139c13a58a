"""One output, one run: an advisory lock (``flock``) on ``out.usdc.lock`` beside a USD output, held by the run
that writes it; the kernel releases it when the process ends, however it ends."""

from __future__ import annotations

import fcntl
import os
import time

from ..errors import ConfigError, os_error_reason


def lock_path(path: str) -> str:
    """The lock file of the output ``path`` (``out.usdc.lock``, beside it), which the writing run holds."""
    return path + ".lock"


class OutputLock:
    """An output owned by one run: an advisory lock (``flock``) on ``out.usdc.lock`` beside the output, taken
    before anything of the output is read, removed or written and held until the file is packed; the lock file
    holds the owner's process id. The kernel releases the lock when the process ends, however it ends (a SIGKILL
    too), so nothing stays stuck: a lock file without a holder is taken over by the next run (and removed by the
    writer's companion process after a killed run). :meth:`release` removes the file while still holding it, and
    a run that opened the removed file sees that and takes the new one, so two runs never both hold the output.

    A second lock of the same output, from another process or from this one, is refused.

    Raises:
        ConfigError: another run holds the output (the message names its process), or the lock file cannot be
            created (the OS's reason).
    """

    def __init__(self, output: str | os.PathLike):
        self.output = os.fspath(output)
        self.path = lock_path(self.output)
        self._handle = None
        waited = 0.0
        while True:
            try:
                handle = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
            except OSError as exc:
                raise ConfigError(f"cannot create the USD file {self.output!r}: {os_error_reason(exc)}") from None
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if waited < _LOCK_PATIENCE:  # a holder about to let go (a killed run's companion process tidying)
                    os.close(handle)
                    time.sleep(0.02)
                    waited += 0.02
                    continue
                holder = _lock_holder(handle)
                os.close(handle)
                raise ConfigError(f"the USD output {self.output!r} is being written by another run ({holder}); "
                                  "wait for it to end, or write elsewhere with -o") from None
            except OSError as exc:
                os.close(handle)
                raise ConfigError(f"cannot lock the USD output {self.output!r}: {os_error_reason(exc)} (the file "
                                  "system does not lock files: write elsewhere with -o)") from None
            try:
                there = os.stat(self.path, follow_symlinks=False)
            except OSError:
                there = None
            mine = os.fstat(handle)
            if there is not None and (there.st_dev, there.st_ino) == (mine.st_dev, mine.st_ino):
                break
            os.close(handle)  # the holder removed it as we opened it: lock the new one
        os.ftruncate(handle, 0)
        os.write(handle, f"{os.getpid()}\n".encode())
        self._handle = handle

    @property
    def held(self) -> bool:
        """Whether this lock is held (taken, not yet released)."""
        return self._handle is not None

    def release(self) -> None:
        """Remove the lock file (while holding it) and let go. Safe to call twice."""
        handle, self._handle = self._handle, None
        if handle is None:
            return
        try:
            mine, there = os.fstat(handle), os.stat(self.path, follow_symlinks=False)
            if (there.st_dev, there.st_ino) == (mine.st_dev, mine.st_ino):
                os.remove(self.path)
        except OSError:
            pass
        os.close(handle)

    def __enter__(self) -> OutputLock:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _lock_holder(handle: int) -> str:
    """The process named in a held lock file, "process 1234"; it writes its id just after it locks."""
    for _ in range(50):
        text = os.pread(handle, 32, 0).decode(errors="replace").strip()
        if text.isdigit():
            return f"process {text}"
        time.sleep(0.01)
    return "a process that has not yet written its id"


#: Seconds a lock is tried again before the output is called taken.
_LOCK_PATIENCE = 0.25
