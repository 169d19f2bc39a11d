"""One writer at a time: an OS-level lock on a session directory or an output.

Two processes resuming one session (or reducing into one ``samples.h5``, or fitting into
one output folder) interleave their writes and corrupt what both depend on.  Each writer
therefore holds an exclusive ``fcntl.flock`` on a lock file beside what it writes, for as
long as it writes.  The kernel releases a ``flock`` when its holder dies (SIGKILL, power
cut of the process), so a lock file left behind by a dead process is not held and the
next writer simply takes it over; the PID written into the file only serves the message
of a refused second writer.  ``flock`` is advisory and per open file description, which
is exactly the scope wanted: every gonio writer takes it, nothing else is affected.

Example
-------
>>> with hold_lock(session_dir / ".gonio.lock", f"session {session_dir}"):  # doctest: +SKIP
...     run()
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

from gonio.errors import GonioError

__all__ = ["LOCK_NAME", "LockedError", "hold_lock", "lock_holder"]

#: The lock file's name inside a session directory or output folder.
LOCK_NAME = ".gonio.lock"


class LockedError(GonioError):
    """Another live process holds the lock.

    Attributes
    ----------
    path
        The lock file.
    pid
        The holder's process ID as it wrote it (None if unreadable).
    """

    def __init__(self, message: str, path: Path, pid: int | None) -> None:
        self.path = path
        self.pid = pid
        super().__init__(message)


def lock_holder(path: str | os.PathLike) -> int | None:
    """PID recorded in a lock file, or None (absent, empty or not a number)."""
    try:
        text = Path(path).read_text(encoding="ascii", errors="replace").strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _locked_fd(path: Path, what: str) -> int:
    """Open ``path`` and take its flock; the descriptor of the file that *is* at ``path``.

    A holder may unlink its lock file when it is done (a lock beside a directory that
    is about to exist).  Whoever opened the old file before the unlink would then lock
    an inode no longer at ``path`` while a newcomer locks the new one: both would
    believe they hold it.  So after taking the lock, the descriptor's inode must still be
    the path's; if not, start again.
    """
    for _ in range(100):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)  # mode follows the umask
        except OSError as exc:
            raise GonioError(
                f"{what}: cannot create the lock file {path}: {exc.strerror}"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            pid = lock_holder(path)
            who = f"process {pid}" if pid is not None else "another process"
            raise LockedError(
                f"{what} is in use by {who} (lock {path}); wait for it to finish or stop it "
                "first (nothing was written)",
                path,
                pid,
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # we locked a file its holder had already removed
    raise GonioError(f"{what}: the lock file {path} keeps being replaced; try again")


@contextlib.contextmanager
def hold_lock(path: str | os.PathLike, what: str) -> Iterator[Path]:
    """Hold an exclusive lock on ``path`` for the duration of the block.

    Parameters
    ----------
    path
        The lock file (created if missing; its directory must exist).
    what
        What is being protected, for the message (``"session S/"``, ``"output fit/"``).

    Raises
    ------
    LockedError
        When another live process holds it (the message names its PID). Nothing is
        written in that case.
    """
    path = Path(path)
    fd = _locked_fd(path, what)
    try:
        # We hold it: whatever PID is in the file is from a holder that has died.
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        try:
            yield path
        finally:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
