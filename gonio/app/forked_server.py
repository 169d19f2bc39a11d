"""A helper process forked at construction that serves messages on a pipe.

The demo's render-ahead and reduce-ahead workers share this life cycle: fork before the
command starts threads (the child keeps only the forking thread), send tuples, and on close
say ``("close",)`` (not only an end of input: a process forked later may hold this end),
join, and terminate a process that does not end. multiprocessing's Pool and
concurrent.futures would re-import or pickle the warm state these workers exist to keep.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
from collections.abc import Callable
from typing import Any

__all__ = ["ForkedServer"]


class ForkedServer(contextlib.AbstractContextManager):
    """A forked process running ``serve(conn)`` on the child's end of a pipe.

    Parameters
    ----------
    serve
        The child's loop; it reads tuples from its connection and ends on ``("close",)``.
    name
        The process's name.
    env
        An environment variable that, set to ``"0"``, disables the process.
    enabled
        False: no process (:attr:`active` is False and :meth:`_send` returns False).
    """

    def __init__(
        self, serve: Callable[[Any], None], *, name: str, env: str, enabled: bool = True
    ) -> None:
        self._proc: Any = None
        self._conn: Any = None
        if not enabled or os.environ.get(env) == "0" or not sys.platform.startswith("linux"):
            return
        try:
            ctx = multiprocessing.get_context("fork")
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=serve, args=(child,), daemon=True, name=name)
            proc.start()
        except OSError:
            return
        child.close()
        self._proc, self._conn = proc, parent

    @property
    def active(self) -> bool:
        """True while the process serves."""
        return self._conn is not None

    def _send(self, msg: tuple) -> bool:
        """Send ``msg``; False (and the process closed) when there is none or it is gone."""
        if self._conn is None:
            return False
        try:
            self._conn.send(msg)
            return True
        except (OSError, ValueError):
            self.close()
            return False

    def close(self) -> None:
        """End the process (idempotent)."""
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        if conn is not None:
            with contextlib.suppress(OSError, ValueError):
                conn.send(("close",))
            with contextlib.suppress(OSError):
                conn.close()
        if proc is not None:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=5.0)

    def __exit__(self, *exc: object) -> None:
        self.close()
