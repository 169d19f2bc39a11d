"""The one layout of gonio's rich progress bars (sessions, dry runs, dask task maps).

A core module so that the composition root (``gonio.app``) and the core's own task map
(:mod:`gonio.distributed`) draw their bars from one piece of code; rich is imported only
when a bar is made.
"""

from __future__ import annotations

from typing import Any

__all__ = ["task_progress"]


def task_progress(label: str = "{task.description}", *extra: Any, eta: bool = True, **kw: Any):
    """A ``rich.progress.Progress``: label, bar, done/total, ``extra`` columns, times.

    Parameters
    ----------
    label
        The first column's text (rich markup and ``{task...}`` fields allowed).
    *extra
        More columns (rich column objects or format strings) after done/total.
    eta
        Show the elapsed time and the estimated time remaining.
    **kw
        Passed to ``Progress`` (``console``, ``transient``, ``disable``, ...).

    Returns
    -------
    rich.progress.Progress
        Not started: use it as a context manager (or ``start()``).
    """
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns: list[Any] = [TextColumn(label), BarColumn(), MofNCompleteColumn()]
    columns += [TextColumn(c) if isinstance(c, str) else c for c in extra]
    if eta:
        columns += [TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
    return Progress(*columns, **kw)
