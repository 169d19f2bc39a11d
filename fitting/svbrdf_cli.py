"""``gonio fit TEXELS.h5 --svbrdf``: the per-texel branch of ``gonio fit``.

``fitting/cli.py`` carries only ``@svbrdf_dispatch``; with ``--svbrdf`` the command runs
:func:`gonio.fitting.svbrdf.fit_svbrdf` and writes the folder of
:mod:`gonio.fitting.svbrdf_output`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
import numpy as np

from gonio.errors import FitError

__all__ = ["svbrdf_dispatch"]

_SVBRDF_PARAMS = ("svbrdf", "smooth", "block_texels")
_SVBRDF_HELP = """

    With --svbrdf, SOURCE is a texel file (texels.h5 from `gonio capture reduce
    --texels N`): every texel is fitted with one model (--model; auto: the model most of 16
    texels spread over the sample choose), as dask tasks of blocks of texels
    sized by measurement (a local cluster, --scheduler, or --workers 0: this process).
    --out defaults to SESSION/svbrdf/: svbrdf.h5 (maps and their sigmas), 16-bit PNG maps
    with their ranges in maps.json, residual.png, preview.png, material.xml (Mitsuba 3,
    bitmap textures) and material.mtlx (MaterialX standard_surface, lambert+ggx).

    \b
      gonio fit S/texels.h5 --svbrdf -m lambert+ggx
      gonio fit S/texels.h5 --svbrdf --smooth 0.5 --workers 0
      gonio fit S/texels.h5 --svbrdf --scheduler tcp://head:8786 --out maps/
    """


#: Largest --smooth: at 1 a neighbour difference weighs like a texel's own data; far
#: beyond, the maps are the regulariser's alone (1e20 gave all-zero maps, 1e308 a
#: singular solve and NaN maps, both "converged").
MAX_SMOOTH = 1e6


def _smooth_value(ctx: Any, param: Any, value: float | None) -> float | None:
    if value is not None and not (math.isfinite(value) and 0 <= value <= MAX_SMOOTH):
        raise click.BadParameter(f"expected a finite number in [0, {MAX_SMOOTH:g}], got {value}")
    return value


def svbrdf_dispatch(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorate ``gonio fit`` (outside ``@library_dispatch``): add ``--svbrdf``,
    ``--smooth``, ``--block-texels``; run the per-texel fit when ``--svbrdf`` is given."""

    @functools.wraps(fn)
    def command(**kwargs: Any) -> Any:
        sv = {k: kwargs.pop(k) for k in _SVBRDF_PARAMS}
        if sv["svbrdf"]:
            return _svbrdf_command(**kwargs, smooth=sv["smooth"], block_texels=sv["block_texels"])
        given = [f"--{k.replace('_', '-')}" for k in _SVBRDF_PARAMS[1:] if sv[k] is not None]
        if given:
            raise click.UsageError(f"{', '.join(given)} apply to --svbrdf fits only")
        if kwargs.get("out") is None:
            raise click.UsageError("Missing option '--out' / '-o'.")
        return fn(**kwargs)

    command.__doc__ = (fn.__doc__ or "").rstrip() + _SVBRDF_HELP
    for decorator in reversed(
        (
            click.option(
                "--svbrdf",
                is_flag=True,
                help="SOURCE is a texel file: fit every texel (parameter maps, exports).",
            ),
            click.option(
                "--smooth",
                type=float,
                default=None,
                callback=_smooth_value,
                metavar="LAMBDA",
                help="--svbrdf: spatial regularisation of the maps (dimensionless; 1 weighs "
                "a neighbour difference like a typical texel's own data; default 0: none).",
            ),
            click.option(
                "--block-texels",
                type=click.IntRange(min=1),
                default=None,
                metavar="N",
                help="--svbrdf: texels per dask task (default: measured, ~1 s of work).",
            ),
        )
    ):
        command = decorator(command)
    return command


def _svbrdf_command(
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
    out: Path | None,
    plots: bool,
    force: bool,
    scheduler: str | None,
    workers: int | None,
    sampling: str | None,
    connect_timeout: float | None,
    smooth: float | None,
    block_texels: int | None,
    **_other: Any,
) -> None:
    from rich.console import Console

    from gonio.fitting.cli import _parse_options, _split_candidates
    from gonio.fitting.library_cli import is_library_source
    from gonio.fitting.svbrdf import SVBRDFOptions, fit_svbrdf
    from gonio.fitting.svbrdf_output import output_folder, write_svbrdf

    if is_library_source(source):
        raise click.UsageError(f"--svbrdf fits one texel file, not a folder or a glob ({source})")
    if sampling is not None:
        raise click.UsageError("--sampling applies to measured files in a library, not --svbrdf")
    model_options = _parse_options(options)
    if model_options and model == "auto":
        raise click.UsageError(
            "--option sets options of one --model; with --model auto put them in the "
            "candidates: --candidates 'lambert,lambert+ggx[fresnel=schlick]'"
        )
    opts = SVBRDFOptions(
        model=model,
        model_options=tuple(sorted(model_options.items())),
        candidates=_split_candidates(candidates) if candidates else None,
        loss=loss,
        robust=robust,
        f_scale=f_scale,
        algorithm=algorithm,
        energy_conservation=not no_energy,
        smooth=smooth or 0.0,
    )
    opts.check()
    from gonio.texels import open_texels

    with open_texels(source):  # a FileFormatError names the file before any folder exists
        pass
    # not resolved: SESSION/texels.h5 may be a link into the reduction's output set
    out = Path(out) if out is not None else Path(source).absolute().parent / "svbrdf"
    console = Console()
    with output_folder(out, force) as keep:
        res = fit_svbrdf(
            source,
            opts,
            scheduler=scheduler,
            workers=workers,
            block_texels=block_texels,
            connect_timeout_s=connect_timeout,
            console=console,
        )
        if len(res.failed_blocks) == res.timing["n_blocks"]:
            raise FitError(
                f"{source}: every block of texels failed; nothing written "
                f"(first: {next(iter(res.failed_blocks.values()))})"
            )
        if not np.any(res.success) and not any(
            np.isfinite(res.params[k]).any() for k in res.param_names
        ):
            # (all zero BRDF, every sample flagged: 11 files of NaN maps and exit 0)
            raise FitError(
                f"{source}: no texel could be fitted (none converged, every map NaN); "
                "nothing written -- are the texels' samples all flagged or zero?"
            )
        written = write_svbrdf(res, out, plots=plots, keep=keep)
    ok = int(res.success.sum())
    console.print(
        f"{res.model}: {ok} of {res.success.size} texels converged; wrote {out}/ "
        f"({len(written['written'])} files)"
        + (f"; smoothed with lambda {res.smooth:g}" if res.smooth else ""),
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    for k in res.param_names:
        v = res.params[k]
        if np.isfinite(v).any():
            console.print(
                f"  {k}: median {np.nanmedian(v):.4g}, range {np.nanmin(v):.4g} .. "
                f"{np.nanmax(v):.4g}; median sigma {np.nanmedian(res.std[k]):.2g}",
                markup=False,
                highlight=False,
            )
    for note in written["notes"]:
        console.print(note, markup=False, highlight=False, soft_wrap=True)
    if res.failed_blocks:
        raise FitError(
            f"{source}: {len(res.failed_blocks)} block(s) of texels failed "
            f"({', '.join(res.failed_blocks)}); their texels are NaN in {out / 'svbrdf.h5'}, "
            "the others were written"
        )
