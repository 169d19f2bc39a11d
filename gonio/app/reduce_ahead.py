"""The demo's reduction beside its capture: poses measured on the second core as they
are done.

A forked process (forked when the demo starts, before any thread, like
:mod:`gonio.figure_worker`) holds a :class:`gonio.capture.live_reduce.LiveReduction` of
the session: the capture's ``start`` document tells it the session, each ``pose_done``
that frames are waiting, and :meth:`ReduceAhead.finish` has it write the reduction
(the same files as :func:`gonio.capture.reduce.reduce_session` of the finished
session).  Without a process (``GONIO_REDUCE_AHEAD=0``, not Linux, a failed fork, or a
process that died) :meth:`ReduceAhead.finish` reduces the session here.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import warnings
from pathlib import Path
from typing import Any

from gonio.app.forked_server import ForkedServer
from gonio.errors import GonioError

__all__ = ["ENV", "ReduceAhead"]

#: ``GONIO_REDUCE_AHEAD=0``: no process; the demo reduces after the capture.
ENV = "GONIO_REDUCE_AHEAD"


def _setup(session: Path, overrides: dict[str, Any]) -> Any:
    from gonio.capture.manifest import load_manifest
    from gonio.capture.reduce import resolve_setup

    return dataclasses.replace(resolve_setup(session, load_manifest(session)), **overrides)


def _serve(conn: Any) -> None:
    """The process's loop: ``("start", session, overrides)``, ``("poll",)``,
    ``("finish", plot)`` answered by ``(ok, result or error)``, ``("close",)``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the command's to handle
    # rawpy warns in any multiprocessing child forked with OpenMP built in: the risk is an
    # OpenMP pool started before the fork, and this process is forked when the demo
    # starts, before anything has decoded a frame (no pool exists to be inherited).
    warnings.filterwarnings(
        "ignore", message="rawpy is being used in a process created by multiprocessing"
    )
    from gonio.capture.live_reduce import LiveReduction

    live: Any = None
    broken: str | None = None
    pending: Any = None
    while True:
        try:
            msg, pending = (pending if pending is not None else conn.recv()), None
        except (EOFError, OSError):
            break
        kind = msg[0]
        if kind == "close":
            break
        try:
            if kind == "start":
                live = LiveReduction(msg[1], _setup(Path(msg[1]), msg[2]))
            elif kind == "poll":
                while conn.poll():  # polls queued up: one look at the journal for all
                    nxt = conn.recv()
                    if nxt[0] != "poll":
                        pending = nxt
                        break
                if live is not None and broken is None:
                    live.add()
            elif kind == "finish":
                if live is None or broken is not None:
                    reply: tuple = (False, broken or "no session started")
                else:
                    reply = (True, live.finish(plot=msg[1]))
                conn.send(reply)
        except GonioError as exc:
            if kind == "finish":
                conn.send((False, exc))
            else:
                broken = str(exc)
        except Exception as exc:  # noqa: BLE001 - the command reduces the session itself
            if kind == "finish":
                conn.send((False, f"{type(exc).__name__}: {exc}"))
            else:
                broken = f"{type(exc).__name__}: {exc}"
    os._exit(0)


class ReduceAhead(ForkedServer):
    """A forked process that reduces a session's poses while it is captured.

    Parameters
    ----------
    enabled
        False: no process (the reduction runs in :meth:`finish`).
    """

    def __init__(self, enabled: bool = True) -> None:
        self._session: Path | None = None
        self._overrides: dict[str, Any] = {}
        super().__init__(_serve, name="reduce-ahead", env=ENV, enabled=enabled)

    def subscriber(self, session: Path, **overrides: Any) -> Any:
        """A session subscriber (``run_session(subscribers=...)``) that starts the
        reduction of ``session`` with the setup's ``overrides`` (``ReductionSetup``
        fields) at the ``start`` document and measures each pose when it is done."""
        self._session, self._overrides = Path(session), dict(overrides)

        def on_document(doc: dict[str, Any]) -> None:
            t = doc.get("type")
            if t == "start" and not doc.get("resumed"):
                self._send(("start", str(session), self._overrides))
            elif t == "pose_done":
                self._send(("poll",))

        return on_document

    def finish(self, *, plot: bool = True) -> Any:
        """The session's reduction (:class:`gonio.capture.reduce.ReductionResult`): from
        the process, or made here when there is none (or it failed other than with a
        :class:`~gonio.errors.GonioError` of the reduction itself, raised here)."""
        assert self._session is not None, "subscriber() first"
        if self._send(("finish", plot)):
            try:
                ok, payload = self._conn.recv()
            except (EOFError, OSError):
                ok, payload = False, "the reduction process ended"
            if ok:
                return payload
            if isinstance(payload, GonioError):
                raise payload
        from gonio.capture.reduce import reduce_session

        return reduce_session(
            self._session, setup=_setup(self._session, self._overrides), plot=plot
        )
