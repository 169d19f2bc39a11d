"""The demo's figures on the machine's second core.

``gonio demo`` is a chain (capture, reduction, fit, report) in which each stage needs
the one before, and its main process is busy on one core throughout.  The report's
figures are the part that can run beside it: the residual map (the costliest) in a
second process while the main process draws the slices and the camera's frames.
A :class:`FigureWorker` is one spawned process, started when the demo starts so that its
imports (matplotlib, the BRDF kernels from numba's cache) are paid while the capture
runs, not while someone waits for the report.

The worker renders the same figures with the same functions as the main process would
(the files are the same); where no process can be spawned, everything is drawn in the
main process.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import Any

__all__ = ["FigureWorker", "residual_map", "result_path"]


def _init() -> None:
    # Ctrl-C in the terminal reaches the whole process group: the demo's main process
    # turns it into a clean stop and shuts this worker down; the worker must not die
    # half-way through a figure first (its files are atomic either way).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import matplotlib

    matplotlib.use("Agg")


def _warm() -> None:
    """Import what the figures use, so that the first figure does not wait for it."""
    import matplotlib.pyplot  # noqa: F401

    import gonio.dataset  # noqa: F401
    import gonio.fitting.plots  # noqa: F401


def residual_map(result: Any, samples_path: str, out: str) -> str:
    """:func:`gonio.fitting.plots.plot_residual_map` of ``result`` on the samples file."""
    from gonio.dataset import load_samples
    from gonio.fitting.plots import plot_residual_map

    return str(plot_residual_map(result, load_samples(samples_path), out))


def _call(fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)`` in the worker. gonio's own errors travel as themselves (they pickle);
    any other becomes a :class:`GonioError` with the message, since an error that cannot
    be unpickled in the main process (a third-party class with its own constructor)
    breaks the whole pool."""
    from gonio.errors import GonioError

    try:
        return fn(*args)
    except GonioError:
        raise
    except Exception as exc:  # noqa: BLE001 - re-raised in the main process, named
        raise GonioError(f"{fn.__name__}: {exc}") from None


class _Done(Future):
    """A future of work done in the calling process (no worker)."""

    def __init__(self, fn: Callable[..., Any], *args: Any) -> None:
        super().__init__()
        try:
            self.set_result(fn(*args))
        except BaseException as exc:  # noqa: BLE001 - raised by .result(), as a worker's
            self.set_exception(exc)


class FigureWorker(contextlib.AbstractContextManager):
    """One spawned process for figures; ``submit(fn, *args) -> Future``.

    ``fn`` is a module-level function of this module (the worker imports it by name).
    Used as a context manager: on exit the worker is shut down (an interrupted demo
    leaves no process behind), waiting for figures under way.
    """

    def __init__(self, enabled: bool = True) -> None:
        self._pool: ProcessPoolExecutor | None = None
        if enabled:
            try:
                self._pool = ProcessPoolExecutor(
                    1, mp_context=multiprocessing.get_context("spawn"), initializer=_init
                )
                self._pool.submit(_warm)
            except (OSError, ValueError):  # no process can be started: draw in-process
                self._pool = None

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future:
        if self._pool is not None:
            try:
                return self._pool.submit(_call, fn, *args)
            except RuntimeError:  # the pool broke (its process was killed): in-process
                self._pool = None
        return _Done(fn, *args)

    def close(self, cancel: bool = False) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=cancel)
            self._pool = None

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        self.close(cancel=exc_type is not None)


def result_path(future: Future) -> Path:
    """The figure a future wrote (its error raised here, in the main process)."""
    return Path(future.result())
