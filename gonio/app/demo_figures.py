"""The demo's figures on the machine's second core.

``gonio demo`` is a chain (capture, reduction, fit, report) in which each stage needs
the one before, and its main process is busy on one core throughout.  The report's
figures are the part that can run beside it: the residual map (the costliest) in a
second process while the main process draws the slices and the camera's frames.  The
process is :class:`gonio.figure_worker.FigureWorker` (the one ``gonio fit`` uses too),
forked when the demo starts so that its imports are paid while the capture runs, not
while someone waits for the report; :func:`figure_worker` makes it with the demo's
warm-up.  The worker draws with the same functions as the main process would (the
files are the same); where no process can be forked, everything is drawn in the main
process.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gonio.figure_worker import FigureJob, FigureWorker

__all__ = ["figure_worker", "residual_map", "result_path"]


def _warm() -> None:
    """Import what the figures use, so that the first figure does not wait for it."""
    import gonio.dataset  # noqa: F401
    import gonio.fitting.plots as plots

    plots.load_matplotlib()


def figure_worker(enabled: bool = True) -> FigureWorker:
    """The demo's figure process (``enabled=False``: none, all drawn in this one)."""
    return FigureWorker(enabled=enabled, warm=_warm)


def residual_map(result: Any, samples_path: str, out: str) -> str:
    """:func:`gonio.fitting.plots.plot_residual_map` of ``result`` on the samples file."""
    from gonio.dataset import load_samples
    from gonio.fitting.plots import plot_residual_map

    return str(plot_residual_map(result, load_samples(samples_path), out))


def result_path(job: FigureJob) -> Path:
    """The figure a job wrote (its error raised here, in the main process)."""
    return Path(job.result())
