"""Draw ``slices.png`` in a second process while ``gonio fit`` fits and draws the rest.

Importing matplotlib (~0.6 s) and drawing the two figures (~0.5 s each) were most of a
``gonio fit FILE.bsdf`` command's time, all on one core of a two-core machine.  A
:class:`SlicesWorker` is forked when the command starts, before the fit: it imports
matplotlib while the parent fits, receives the fit and the samples through a pipe, draws
the slices figure and sends the PNG bytes back; the parent draws the residual map itself
and writes both files into its staged output set.

The worker never touches the disk, so a parent killed mid-way leaves nothing of the
worker behind (its next write to the pipe fails and it exits), and the parent is the
only process that ever holds the output folder's lock (the worker is forked before the
lock is taken).  Linux only (``fork``); elsewhere, with ``GONIO_PLOT_WORKER=0``, or when
the fork fails, :func:`start` returns None and the command draws both figures itself.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import sys
from typing import Any

from gonio.errors import FitError

__all__ = ["SlicesWorker", "start"]

_HEADER = struct.Struct("!Q")


def start() -> SlicesWorker | None:
    """Fork the worker, or None when this platform or the environment says no."""
    if not sys.platform.startswith("linux") or os.environ.get("GONIO_PLOT_WORKER") == "0":
        return None
    try:
        return SlicesWorker()
    except OSError:
        return None


def _send(fd: int, data: bytes) -> None:
    view = memoryview(_HEADER.pack(len(data)) + data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _recv(fd: int) -> bytes | None:
    head = _read_exactly(fd, _HEADER.size)
    if head is None:
        return None
    (n,) = _HEADER.unpack(head)
    return _read_exactly(fd, n)


def _read_exactly(fd: int, n: int) -> bytes | None:
    parts, got = [], 0
    while got < n:
        chunk = os.read(fd, min(n - got, 1 << 20))
        if not chunk:
            return None
        parts.append(chunk)
        got += len(chunk)
    return b"".join(parts)


class SlicesWorker:
    """A forked process that draws :func:`gonio.fitting.plots.slices_figure` as PNG bytes."""

    def __init__(self) -> None:
        to_child_r, to_child_w = os.pipe()
        to_parent_r, to_parent_w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the worker
            os.close(to_child_w)
            os.close(to_parent_r)
            _serve(to_child_r, to_parent_w)  # never returns
        os.close(to_child_r)
        os.close(to_parent_w)
        self.pid = pid
        self._w = to_child_w
        self._r = to_parent_r
        self._submitted = False

    def submit(self, r: Any, samples: Any) -> None:
        """Hand the fit and its samples to the worker (it starts drawing)."""
        self._submitted = True
        _send(self._w, pickle.dumps((r, samples), protocol=pickle.HIGHEST_PROTOCOL))

    def result(self) -> bytes:
        """The PNG bytes of the slices figure; a :class:`FitError` if the worker failed."""
        try:
            msg = _recv(self._r)
        finally:
            self.close()
        if msg is None:
            raise FitError("the plotting process ended without drawing slices.png")
        ok, payload = pickle.loads(msg)
        if not ok:
            raise FitError(f"drawing slices.png failed: {payload}")
        return payload

    def close(self) -> None:
        """End the worker (idempotent): close the pipes and reap it."""
        for fd in (self._w, self._r):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._w = self._r = -1
        if self.pid:
            if not self._submitted:  # the fit failed: no need to let it finish importing
                try:
                    os.kill(self.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            try:
                os.waitpid(self.pid, 0)
            except ChildProcessError:
                pass
            self.pid = 0


def _serve(rfd: int, wfd: int) -> None:
    """The worker's life: import matplotlib, wait for one job, answer it, exit."""
    code = 0
    try:
        # the parent's numba thread pool (if any) did not survive the fork: numpy only
        os.environ["GONIO_NUMBA"] = "0"
        from gonio.fitting import plots

        plots.load_matplotlib()
        msg = _recv(rfd)
        if msg is not None:
            try:
                r, samples = pickle.loads(msg)
                reply = (True, plots.slices_png(r, samples))
            except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
                reply = (False, f"{type(exc).__name__}: {exc}")
            _send(wfd, pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL))
    except BaseException:  # noqa: BLE001 - a broken pipe (parent gone) or an interrupt
        code = 1
    finally:
        os._exit(code)
