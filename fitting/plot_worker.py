"""Draw ``slices.png`` and ``residuals.png`` in two other processes while ``gonio fit`` fits.

Importing matplotlib (~0.45 s) and drawing the two figures (~0.5 and ~0.4 s) were most of
a ``gonio fit FILE.bsdf`` command's time.  A :class:`PlotWorker` is forked when the
command starts, before it loads its input: it imports matplotlib while the parent loads
and fits, then receives the fit and the samples through a pipe and forks once more (so
matplotlib is imported once and the job crosses the pipe once): the grandchild draws the
residual map while the worker draws the slices, one figure per core, and the worker sends
both PNGs back.  The parent only waits and writes them into its staged output set.

The workers never touch the disk, so a parent killed mid-way leaves nothing of them
behind (their next write to a pipe fails and they exit), and the parent is the only
process that ever holds the output folder's lock (the worker is forked before the lock
is taken).  Linux only (``fork``); elsewhere, with ``GONIO_PLOT_WORKER=0``, or when the
fork fails, :func:`start` returns None and the command draws both figures itself.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import sys
from typing import Any

from gonio.errors import FitError

__all__ = ["FIGURES", "PlotWorker", "start"]

#: The files a worker draws, in the order of its reply.
FIGURES = ("slices.png", "residuals.png")

_HEADER = struct.Struct("!Q")


def start() -> PlotWorker | None:
    """Fork the worker, or None when this platform or the environment says no."""
    if not sys.platform.startswith("linux") or os.environ.get("GONIO_PLOT_WORKER") == "0":
        return None
    try:
        return PlotWorker()
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


class PlotWorker:
    """A forked process that draws :data:`FIGURES` (``plots.slices_png``,
    ``plots.residuals_png``) as PNG bytes."""

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

    def result(self) -> dict[str, bytes]:
        """File name -> PNG bytes of :data:`FIGURES`; a :class:`FitError` naming the
        figure if drawing it failed."""
        try:
            msg = _recv(self._r)
        finally:
            self.close()
        if msg is None:
            raise FitError("the plotting process ended without drawing the figures")
        out = {}
        for name, (ok, payload) in zip(FIGURES, pickle.loads(msg), strict=True):
            if not ok:
                raise FitError(f"drawing {name} failed: {payload}")
            out[name] = payload
        return out

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


def _draw(fn: Any, r: Any, samples: Any) -> tuple[bool, Any]:
    try:
        return True, fn(r, samples)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
        return False, f"{type(exc).__name__}: {exc}"


def _serve(rfd: int, wfd: int) -> None:
    """The worker's life: import matplotlib, wait for one job, fork the residual map's
    drawer, draw the slices, answer with both, exit."""
    code = 0
    try:
        # the parent's numba thread pool (if any) did not survive the fork: numpy only
        os.environ["GONIO_NUMBA"] = "0"
        from gonio.fitting import plots

        plots.load_matplotlib()
        msg = _recv(rfd)
        if msg is not None:
            os.close(rfd)
            r, samples = pickle.loads(msg)
            residuals = _fork_drawer(plots.residuals_png, r, samples, wfd)
            slices = _draw(plots.slices_png, r, samples)
            reply = (slices, residuals())
            _send(wfd, pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL))
    except BaseException:  # noqa: BLE001 - a broken pipe (parent gone) or an interrupt
        code = 1
    finally:
        os._exit(code)


def _fork_drawer(fn: Any, r: Any, samples: Any, parent_fd: int) -> Any:
    """Draw ``fn(r, samples)`` in a forked process; returns a function that waits for it
    and gives ``(ok, png bytes or error text)``.  Without a fork: drawn here, now.
    ``parent_fd`` (the pipe to the command) is closed in the child, so that the command
    sees the end of the pipe as soon as the worker itself is gone."""
    try:
        rfd, wfd = os.pipe()
        pid = os.fork()
    except OSError:
        done = _draw(fn, r, samples)
        return lambda: done
    if pid == 0:
        code = 0
        try:
            os.close(rfd)
            os.close(parent_fd)
            _send(wfd, pickle.dumps(_draw(fn, r, samples), protocol=pickle.HIGHEST_PROTOCOL))
        except BaseException:  # noqa: BLE001 - the worker is gone
            code = 1
        finally:
            os._exit(code)
    os.close(wfd)

    def wait() -> tuple[bool, Any]:
        try:
            msg = _recv(rfd)
        finally:
            os.close(rfd)
            os.waitpid(pid, 0)
        if msg is None:
            return False, "the drawing process ended without an answer"
        return pickle.loads(msg)

    return wait
