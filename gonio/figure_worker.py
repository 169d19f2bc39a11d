"""One process beside a command for its figures (``gonio fit``, ``gonio demo``).

Importing matplotlib (~0.5 s) and drawing a figure (0.4-0.9 s each) are a large part of
a ``gonio fit`` or of the demo's report, and they need nothing but the result they show.
A :class:`FigureWorker` is forked when the command starts, before it loads anything
(no thread, lock or numba pool exists yet to be inherited half-way): it runs ``warm``
(the imports) while the command works, then draws each submitted job in a process of
its own forked from the warm worker, so matplotlib is imported once and two figures
draw on two cores.  Results (return values, usually PNG bytes or a path) come back
through a pipe; a job that returns bytes lets the command write them into its own
staged output (``gonio fit``: only the command holds the folder's lock), a job may also
write its own file atomically and return the path (the demo's report).

Why not ``concurrent.futures.ProcessPoolExecutor``: its processes are started (spawn)
or forked when the first job arrives, so the imports would be paid then, and one pool
process draws one job at a time.  This is the ~200 lines that do "fork warm once, fork
per job" with nothing but ``os.fork`` and pipes.

Errors: a job's :class:`~gonio.errors.GonioError` is raised by :meth:`FigureJob.result`
as itself (gonio's errors pickle with their attributes); any other as a ``GonioError``
``"Type: message"``.  Ctrl-C: the worker and its drawers ignore SIGINT (the command
turns it into a clean stop and closes the worker, which ends its drawers).  Linux only
(``fork``); elsewhere, with ``GONIO_PLOT_WORKER=0``, with ``enabled=False`` or when the
fork fails, every job runs in the calling process when submitted (the same results).
"""

from __future__ import annotations

import contextlib
import os
import pickle
import selectors
import signal
import struct
import sys
from collections.abc import Callable
from typing import Any

from gonio.errors import GonioError

__all__ = ["ENV", "FigureJob", "FigureWorker"]

#: ``GONIO_PLOT_WORKER=0``: no worker process; every figure is drawn in the command.
ENV = "GONIO_PLOT_WORKER"

_HEADER = struct.Struct("!Q")


def _send(fd: int, obj: Any) -> None:
    _send_bytes(fd, pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))


def _send_bytes(fd: int, data: bytes) -> None:
    view = memoryview(_HEADER.pack(len(data)) + data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _read_exactly(fd: int, n: int) -> bytes | None:
    parts, got = [], 0
    while got < n:
        chunk = os.read(fd, min(n - got, 1 << 20))
        if not chunk:
            return None
        parts.append(chunk)
        got += len(chunk)
    return b"".join(parts)


def _recv(fd: int) -> Any:
    """The next message on ``fd``, or None at the end of the pipe."""
    head = _read_exactly(fd, _HEADER.size)
    if head is None:
        return None
    data = _read_exactly(fd, _HEADER.unpack(head)[0])
    return None if data is None else pickle.loads(data)


def _outcome(fn: Callable[..., Any], args: tuple) -> tuple[bool, Any]:
    """``(True, fn(*args))`` or ``(False, error)``: a GonioError as itself, any other
    exception as its text (its class may not pickle or exist in the command)."""
    try:
        return True, fn(*args)
    except GonioError as exc:
        return False, exc
    except Exception as exc:  # noqa: BLE001 - reported to the command, which raises
        return False, f"{type(exc).__name__}: {exc}"


def _numba_threads_started() -> bool:
    mod = sys.modules.get("numba.np.ufunc.parallel")
    return bool(getattr(mod, "_is_initialized", False))


class FigureJob:
    """A submitted figure; :meth:`result` waits for it."""

    def __init__(self, worker: FigureWorker | None, key: int, done: tuple | None = None):
        self._worker = worker
        self.key = key
        self._done = done

    def result(self) -> Any:
        """What the job's function returned; its error raised here (see the module)."""
        if self._done is None:
            assert self._worker is not None
            self._done = self._worker._wait(self.key)
        ok, payload = self._done
        if ok:
            return payload
        if isinstance(payload, BaseException):
            raise payload
        raise GonioError(str(payload))


class FigureWorker(contextlib.AbstractContextManager):
    """A forked, warm process that draws figures; ``submit(fn, *args) -> FigureJob``.

    Parameters
    ----------
    enabled
        False: no process; jobs run in the caller when submitted.
    warm
        Run first in the worker (imports), while the command goes on.

    ``fn`` and ``args`` cross a pipe: ``fn`` must be a module-level function, the
    arguments picklable.  As a context manager the worker is closed on exit (cancelled
    when the block raised).
    """

    def __init__(self, enabled: bool = True, warm: Callable[[], None] | None = None) -> None:
        self.pid = 0
        self._w = self._r = -1
        self._results: dict[int, tuple] = {}
        self._next = 0
        self._submitted = 0
        if not enabled or os.environ.get(ENV) == "0" or not sys.platform.startswith("linux"):
            return
        try:
            to_child_r, to_child_w = os.pipe()
            to_parent_r, to_parent_w = os.pipe()
            pid = os.fork()
        except OSError:
            return
        if pid == 0:  # the worker: never returns
            os.close(to_child_w)
            os.close(to_parent_r)
            _serve(to_child_r, to_parent_w, warm)
        os.close(to_child_r)
        os.close(to_parent_w)
        self.pid, self._w, self._r = pid, to_child_w, to_parent_r

    @property
    def active(self) -> bool:
        """True while a worker process draws the jobs."""
        return self.pid != 0

    def submit(self, fn: Callable[..., Any], *args: Any) -> FigureJob:
        """Start ``fn(*args)`` in its own drawing process (or here, now, without one)."""
        key = self._next
        self._next += 1
        if self.active:
            try:
                data = pickle.dumps((key, fn, args), protocol=pickle.HIGHEST_PROTOCOL)
            except (pickle.PicklingError, AttributeError, TypeError):
                data = None  # a job that cannot cross the pipe is drawn here
            if data is not None:
                try:
                    _send_bytes(self._w, data)
                    self._submitted += 1
                    return FigureJob(self, key)
                except OSError:  # the worker is gone: this job and the next ones here
                    self.close(cancel=True)
        return FigureJob(None, key, _outcome(fn, args))

    def _wait(self, key: int) -> tuple:
        while key not in self._results:
            msg = _recv(self._r) if self._r >= 0 else None
            if msg is None:
                self.close(cancel=True)
                return False, "the figure process ended without drawing the figure"
            self._results[msg[0]] = msg[1]
        return self._results.pop(key)

    def close(self, cancel: bool = False) -> None:
        """End the worker (idempotent): after its jobs, or at once with ``cancel`` (its
        drawers are ended too)."""
        if not self.active:
            return
        if self._w >= 0:
            os.close(self._w)  # the worker's end of input: it finishes and exits
            self._w = -1
        if cancel or self._submitted == 0:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGTERM)
        elif self._r >= 0:
            # drain what is still coming: a worker blocked on a full pipe never exits
            while (msg := _recv(self._r)) is not None:
                self._results[msg[0]] = msg[1]
        if self._r >= 0:
            os.close(self._r)
            self._r = -1
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)
        self.pid = 0

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        self.close(cancel=exc_type is not None)


def _serve(rfd: int, wfd: int, warm: Callable[[], None] | None) -> None:
    """The worker's life: warm up, then fork one drawer per job and forward each
    drawer's answer to the command until the command closes its end and the drawers
    are done."""
    code = 0
    drawers: dict[int, tuple[int, int]] = {}  # result fd -> (pid, key)

    def end(*_: Any) -> None:  # SIGTERM from close(cancel=True): end the drawers too
        for pid, _key in drawers.values():
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        os._exit(1)

    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, end)
        if _numba_threads_started():
            # a numba thread pool does not survive a fork: the numpy paths (same maths)
            os.environ["GONIO_NUMBA"] = "0"
        if warm is not None:
            with contextlib.suppress(Exception):  # a failed warm-up shows in the jobs
                warm()
        sel = selectors.DefaultSelector()
        sel.register(rfd, selectors.EVENT_READ)
        reading = True
        while reading or drawers:
            for sk, _ in sel.select():
                if sk.fd == rfd:
                    job = _recv(rfd)
                    if job is None:
                        sel.unregister(rfd)
                        reading = False
                        continue
                    # SIGTERM held from the fork until the drawer is registered: a
                    # cancel in between would end the worker and orphan the drawer
                    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
                    try:
                        fd, pid = _fork_drawer(job, (rfd, wfd))
                        drawers[fd] = (pid, job[0])
                    finally:
                        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
                    sel.register(fd, selectors.EVENT_READ)
                else:
                    pid, key = drawers.pop(sk.fd)
                    sel.unregister(sk.fd)
                    msg = _recv(sk.fd)
                    os.close(sk.fd)
                    os.waitpid(pid, 0)
                    done = msg if msg is not None else (False, "the drawing process died")
                    _send(wfd, (key, done))
    except BaseException:  # noqa: BLE001 - a broken pipe (command gone) or an interrupt
        code = 1
    finally:
        os._exit(code)


def _fork_drawer(job: tuple, inherited: tuple[int, int]) -> tuple[int, int]:
    """Fork a process drawing ``job``; (read end of its answer pipe, its pid)."""
    _key, fn, args = job
    rfd, wfd = os.pipe()
    pid = os.fork()
    if pid == 0:
        code = 0
        try:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})  # held by the worker
            os.close(rfd)
            for fd in inherited:  # the command sees its pipes end when the worker does
                os.close(fd)
            _send(wfd, _outcome(fn, args))
        except BaseException:  # noqa: BLE001 - the worker is gone
            code = 1
        finally:
            os._exit(code)
    os.close(wfd)
    return rfd, pid
