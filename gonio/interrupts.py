"""Ctrl-C that cannot be lost: the command line notes every SIGINT as well as raising it.

Python raises ``KeyboardInterrupt`` from its SIGINT handler at the next bytecode of the
main thread.  When that bytecode belongs to a garbage-collector callback (distributed's
``GCDiagnosis`` runs one in every process that hosts a scheduler), the interpreter prints
"Exception ignored in ..." and carries on: the user's Ctrl-C is gone and a long fit runs
to exit 0 (seen in CI, 2026-12-03).  :func:`noting` installs a handler that records the
signal before raising (and keeps the lost exception's "Exception ignored" report off the
terminal), so the command's waiting loops (:func:`gonio.distributed.map_tasks`)
and its exit code can still honour it.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from typing import Any

__all__ = ["noted", "noting"]

_noted: list[int] = []


def noted() -> bool:
    """Whether a Ctrl-C arrived inside the innermost :func:`noting` block (False outside
    any: library callers keep Python's own handling)."""
    return bool(_noted)


@contextlib.contextmanager
def noting() -> Iterator[None]:
    """SIGINT raises ``KeyboardInterrupt`` as Python's default handler does, and is also
    recorded for :func:`noted` until the block ends.  A no-op outside the main thread, or
    when SIGINT is not at Python's default (ignored, or a caller's own handler)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def note(signum: int, frame: Any) -> None:
        _noted.append(signum)
        raise KeyboardInterrupt

    previous_hook = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        # A lost interrupt (from this handler or from a waiting loop's own) is noted, and
        # its "Exception ignored" traceback, the only traceback a user would see from
        # gonio, is not printed.
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            _noted.append(signal.SIGINT)
        else:
            previous_hook(unraisable)

    saved = list(_noted)
    _noted.clear()
    signal.signal(signal.SIGINT, note)
    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous_hook
        signal.signal(signal.SIGINT, signal.default_int_handler)
        _noted[:] = saved
