"""``gonio fit DIR_OR_GLOB --out LIB/``: the library branch of ``gonio fit``.

``fitting/cli.py`` (the single-input command) carries only ``@library_dispatch`` and the
SOURCE type :data:`FIT_SOURCE`; a folder or glob SOURCE runs
:func:`gonio.fitting.library.fit_library` with the same fit options.
"""

from __future__ import annotations

import functools
import glob
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from gonio.errors import FitError
from gonio.fitting.library import SAMPLINGS, FitOptions, fit_library

__all__ = ["FIT_SOURCE", "is_library_source", "library_dispatch"]


def is_library_source(source: str | os.PathLike) -> bool:
    """True for a folder, or a glob pattern that is not itself an existing file."""
    p = Path(source)
    return p.is_dir() or (glob.has_magic(str(source)) and not p.exists())


class _FitSourceType(click.ParamType):
    """``gonio fit``'s SOURCE: an existing file, a folder, or a glob pattern (quoted)."""

    name = "path"

    def convert(self, value: Any, param: Any, ctx: Any) -> Path:
        if isinstance(value, Path):
            return value
        p = Path(value)
        if p.exists() or glob.has_magic(str(value)):
            return p
        self.fail(f"Path {str(value)!r} does not exist.", param, ctx)


#: The click type of ``gonio fit``'s SOURCE argument.
FIT_SOURCE = _FitSourceType()


def _positive_seconds(ctx: Any, param: Any, value: float | None) -> float | None:
    """``--connect-timeout``: a positive, finite number of seconds (None: the default).

    NaN and negative values reached dask's time parser, whose KeyError/ValueError came out
    as a traceback.
    """
    if value is not None and not (math.isfinite(value) and value > 0):
        raise click.BadParameter(f"expected a positive finite number of seconds, got {value}")
    return value


_LIBRARY_PARAMS = ("scheduler", "workers", "sampling", "connect_timeout")
_LIBRARY_HELP = """

    SOURCE may also be a folder or a quoted glob: a material library.  Every samples.h5,
    .bsdf and .binary file found is fitted, one material per dask task (a local cluster,
    or --scheduler), into one folder per material in --out, plus summary.csv and
    summary.parquet; materials whose file and options are unchanged are skipped.

    \b
      gonio fit measured/ --model auto --out LIB/
      gonio fit 'sessions/*/samples.h5' --out LIB/ --scheduler tcp://head:8786
    """


def library_dispatch(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorate ``gonio fit``: add the library options, and run :func:`fit_library` when
    SOURCE is a folder or a glob (the single-input command otherwise, unchanged)."""

    @functools.wraps(fn)
    def command(**kwargs: Any) -> Any:
        lib_kwargs = {k: kwargs.pop(k) for k in _LIBRARY_PARAMS}
        if is_library_source(kwargs["source"]):
            return _library_command(**kwargs, **lib_kwargs)
        given = [f"--{k.replace('_', '-')}" for k in _LIBRARY_PARAMS if lib_kwargs[k] is not None]
        if given:
            raise click.UsageError(
                f"{', '.join(given)} apply to a library: SOURCE a folder or a glob "
                f"(got the file {kwargs['source']})"
            )
        return fn(**kwargs)

    command.__doc__ = (fn.__doc__ or "").rstrip() + _LIBRARY_HELP
    for decorator in reversed(
        (
            click.option(
                "--scheduler",
                default=None,
                metavar="tcp://HOST:PORT",
                help="Library and --svbrdf: fit on this dask scheduler's workers (they must "
                "see the same files at the same paths); default a local cluster.",
            ),
            click.option(
                "--workers",
                type=int,
                default=None,
                help="Library and --svbrdf: worker processes of the local cluster (default one per "
                "core; 0: no dask, fit in this process).",
            ),
            click.option(
                "--sampling",
                type=click.Choice(list(SAMPLINGS)),
                default=None,
                help="Library: grid measured files are sampled on (default standard, the "
                "grid of a single-input fit; coarse: 810 pairs).",
            ),
            click.option(
                "--connect-timeout",
                type=float,
                default=None,
                callback=_positive_seconds,
                metavar="SECONDS",
                help="Library and --svbrdf: how long to wait for --scheduler (default 10).",
            ),
        )
    ):
        command = decorator(command)
    return command


def _library_command(
    *,
    source: Path,
    model: str,
    options: tuple[str, ...],
    candidates: str | None,
    loss: str,
    robust: str | None,
    f_scale: float,
    algorithm: str,
    no_energy: bool,
    out: Path,
    plots: bool,
    force: bool,
    scheduler: str | None,
    workers: int | None,
    sampling: str | None,
    connect_timeout: float | None,
    **_single_input_only: Any,  # options of `gonio fit` added later: not used by a library
) -> None:
    # The option parsing of the single-input command, so both read --option and
    # --candidates alike.
    from gonio.fitting.cli import _parse_options, _split_candidates

    model_options = _parse_options(options)
    if model_options and model == "auto":
        raise click.UsageError(
            "--option sets options of one --model; with --model auto put them in the "
            "candidates: --candidates 'lambert,lambert+ggx[fresnel=schlick]'"
        )
    fit_options = FitOptions(
        model=model,
        model_options=tuple(sorted(model_options.items())),
        candidates=_split_candidates(candidates) if candidates else None,
        loss=loss,
        robust=robust,
        f_scale=f_scale,
        algorithm=algorithm,
        energy_conservation=not no_energy,
        plots=plots,
        sampling=sampling or "standard",
    )
    report = fit_library(
        source,
        out,
        fit_options,
        scheduler=scheduler,
        workers=workers,
        force=force,
        connect_timeout_s=connect_timeout,
    )
    from rich.console import Console

    console = Console()
    console.print(
        f"{len(report.fitted)} fitted, {len(report.skipped)} unchanged, "
        f"{len(report.failed)} failed; summary: {Path(out) / 'summary.csv'}, "
        f"{Path(out) / 'summary.parquet'}",
        highlight=False,
        soft_wrap=True,
        markup=False,
    )
    bad = [*report.failed, *report.not_converged]
    if bad:
        what = []
        if report.failed:
            what.append(f"{len(report.failed)} failed ({', '.join(report.failed)})")
        if report.not_converged:
            what.append(
                f"{len(report.not_converged)} did not converge ({', '.join(report.not_converged)})"
            )
        raise FitError(
            f"library {out}: {'; '.join(what)}; the others were written (see summary.csv)"
        )
