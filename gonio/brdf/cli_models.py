"""``gonio brdf list | plot | albedo``: browse the analytic models and check parameters."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
import numpy as np

from gonio.errors import ParameterError

__all__ = ["albedo_cmd", "list_cmd", "plot_cmd"]

_MEASURED_SUFFIXES = (".bsdf", ".binary")
_DEFAULT_THETAS = "0,10,20,30,40,50,60,70,80,85,89"


def _parse_params(items: tuple[str, ...]) -> dict[str, Any]:
    """``("alpha=0.2", "albedo=0.1,0.2,0.3")`` -> ``{"alpha": 0.2, "albedo": [0.1, 0.2, 0.3]}``."""
    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise click.BadParameter(f"expected NAME=VALUE, got {item!r}", param_hint="--param")
        try:
            vals = [float(v) for v in value.split(",")]
        except ValueError:
            raise click.BadParameter(
                f"{name.strip()}: expected a number or 3 comma-separated numbers (R,G,B), "
                f"got {value!r}",
                param_hint="--param",
            ) from None
        if len(vals) not in (1, 3):
            raise click.BadParameter(
                f"{name.strip()}: give 1 value or 3 (R,G,B), got {len(vals)}", param_hint="--param"
            )
        out[name.strip()] = vals[0] if len(vals) == 1 else vals
    return out


def _parse_thetas(texts: tuple[str, ...], default: str) -> list[float]:
    parts = [p for t in (texts or (default,)) for p in t.split(",") if p.strip()]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise click.BadParameter(
            f"expected degrees (numbers), got {', '.join(texts)!r}", param_hint="--theta-i"
        ) from None
    bad = [v for v in vals if not 0.0 <= v <= 90.0]
    if not vals or bad:
        raise click.BadParameter(
            f"incidence angles must lie in [0, 90] degrees, got {bad or vals}",
            param_hint="--theta-i",
        )
    return vals


def _resolve(target: str, params: dict[str, Any], fresnel: str | None, g1: str | None):
    """A BRDF object (bound analytic model or measured file) and a label for it."""
    path = Path(target)
    if path.is_file():
        if params or fresnel or g1:
            raise click.UsageError(
                f"{target} is a measured BRDF file: --param, --fresnel and --g1 apply to "
                "analytic models only"
            )
        from gonio.brdf import load

        brdf = load(path)
        return brdf, f"{path.name}: {getattr(brdf, 'description', '')}".rstrip(": ")
    if path.suffix.lower() in _MEASURED_SUFFIXES or "/" in target:
        raise click.BadParameter(f"no such file: {target}", param_hint="MODEL_OR_FILE")
    from gonio.brdf.registry import get_model, parse_model_spec

    # 'lambert+ggx[fresnel=schlick]', as `gonio fit --candidates` writes a model
    name, options = parse_model_spec(target)
    for k, v in (("fresnel", fresnel), ("g1", g1)):
        if v is None:
            continue
        if k in options and options[k] != v:
            raise click.UsageError(
                f"{target} sets {k}={options[k]} and --{k} {v} another: give it once"
            )
        options[k] = v
    model = get_model(name, **options)
    bound = model.bind(params)
    return bound, bound.description + "".join(f" [{k}={v}]" for k, v in options.items())


_model_arg = click.argument("model_or_file", metavar="MODEL_OR_FILE")
_param_opt = click.option(
    "--param",
    "-p",
    "params",
    multiple=True,
    metavar="NAME=VALUE",
    help="Model parameter; repeat for several.  VALUE is one number or R,G,B.  "
    "Parameters not given take their defaults (see `gonio brdf list`).",
)
_fresnel_opt = click.option(
    "--fresnel",
    type=click.Choice(["none", "schlick", "conductor", "dielectric"]),
    default=None,
    help="Fresnel term of ggx/beckmann lobes: none (F=1), schlick (f0), conductor "
    "(eta, k), dielectric (eta).  [default: none]",
)
_g1_opt = click.option(
    "--g1",
    type=click.Choice(["exact", "rational"]),
    default=None,
    help="Beckmann Smith G1: exact erf form or Mitsuba's rational fit.  [default: exact]",
)
_theta_opt = click.option(
    "--theta-i",
    "theta_i",
    multiple=True,
    metavar="DEG",
    help="Incidence angle(s) in degrees; repeat or comma-separate.",
)


@click.command("list")
def list_cmd() -> None:
    """List the analytic BRDF lobes with their parameters, bounds and defaults.

    Lobes combine with '+' into models (e.g. lambert+ggx); parameters keep their names
    when unique, repeated names get the lobe position as suffix (ggx+ggx: ks_1, ks_2).
    Parameters marked * enter f_r linearly.  Every model takes its parameters with
    --param NAME=VALUE in `gonio brdf plot` and `gonio brdf albedo`.
    """
    from rich.console import Console
    from rich.markup import escape

    from gonio.brdf.registry import get_model, list_models

    console = Console()
    console.print("[bold]Analytic BRDF lobes[/] (f_r in 1/sr; * = enters f_r linearly)\n")
    for name in list_models():
        m = get_model(name)
        lobe = m.lobes[0]
        console.print(f"[bold cyan]{name}[/]  {escape(lobe.summary)}")
        for k, lo, hi, d, lin, doc in m.describe_params():
            label = f"{k}{'*' if lin else ''}"
            console.print(f"    {label:<9} [{lo:g}, {hi:g}]".ljust(30) + f"default {d:<8g} {doc}")
        for k, v in lobe.option_choices.items():
            console.print(f"    option {k}: {' | '.join(v)} (default {v[0]})")
    console.print(
        "Fresnel parameters: schlick adds f0 [0, 1]; conductor adds eta [0, 10], k [0, 20]; "
        "dielectric adds eta [1, 4].\n"
        "Example: gonio brdf plot lambert+ggx --fresnel schlick -p albedo=0.4 -p ks=0.3 "
        "-p alpha=0.1 --theta-i 45 --out ggx.png"
    )


@click.command("plot")
@_model_arg
@_param_opt
@_fresnel_opt
@_g1_opt
@_theta_opt
@click.option(
    "--phi-i", "phi_i", type=float, default=0.0, show_default=True, help="Incidence azimuth (deg)."
)
@click.option(
    "--out",
    "-o",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Output image (.png, .pdf or .svg).",
)
@click.option("--linear", is_flag=True, help="Linear instead of logarithmic f_r scale.")
@click.option("--force", is_flag=True, help="Overwrite --out if it exists.")
def plot_cmd(
    model_or_file: str,
    params: tuple[str, ...],
    fresnel: str | None,
    g1: str | None,
    theta_i: tuple[str, ...],
    phi_i: float,
    out: Path,
    linear: bool,
    force: bool,
) -> None:
    """Plot a BRDF: in-plane slices, a polar heat map and (models) the albedo curve.

    MODEL_OR_FILE is an analytic model name (see `gonio brdf list`, sums like lambert+ggx
    work) or a measured BRDF file (RGL .bsdf, MERL .binary).  Slices are drawn for every
    --theta-i (default 0, 30, 60 deg); the heat map uses the first.

    \b
    Examples:
      gonio brdf plot ggx -p alpha=0.1 --theta-i 30,60 --out ggx.png
      gonio brdf plot lambert+ggx --fresnel schlick -p albedo=0.5,0.3,0.2 --out paint.png
      gonio brdf plot gold-metallic-paint_rgb.bsdf --theta-i 45 --out gold.png
    """
    from gonio.brdf.plots import plot_brdf

    if out.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise click.BadParameter(
            f"unsupported image type {out.suffix or '(none)'!r}; use .png, .pdf or .svg",
            param_hint="--out",
        )
    if not np.isfinite(phi_i):
        raise click.BadParameter(
            f"expected a finite angle in degrees, got {phi_i}", param_hint="--phi-i"
        )
    thetas = _parse_thetas(theta_i, "0,30,60")
    brdf, label = _resolve(model_or_file, _parse_params(params), fresnel, g1)
    # After the model and its parameters, whose errors the user should see first.
    if out.exists() and not force:
        raise click.BadParameter(
            f"'{out}' exists; pass --force to overwrite it or choose another file",
            param_hint="--out",
        )
    is_model = getattr(brdf, "format", "") == "analytic"
    plot_brdf(
        brdf,
        [min(t, 89.9) for t in thetas],
        out,
        phi_i_deg=phi_i,
        title=label,
        albedo_curve=is_model,
        log=not linear,
        replace=force,
    )
    click.echo(f"wrote {out}")


@click.command("albedo")
@_model_arg
@_param_opt
@_fresnel_opt
@_g1_opt
@_theta_opt
@click.option(
    "--strict", is_flag=True, help="Exit with status 1 when the albedo exceeds 1 anywhere."
)
def albedo_cmd(
    model_or_file: str,
    params: tuple[str, ...],
    fresnel: str | None,
    g1: str | None,
    theta_i: tuple[str, ...],
    strict: bool,
) -> None:
    """Directional albedo against incidence angle: the energy check to run before
    trusting a set of parameters.

    The directional albedo a(theta_i) is the integral of f_r cos(theta_o) over the
    outgoing hemisphere: the fraction of light from theta_i that is reflected.  A
    physically plausible BRDF has a <= 1 everywhere; a warning is printed otherwise.
    Default angles: 0, 10, ..., 80, 85, 89 degrees.  A coloured albedo also gets its
    luminance-weighted value, Y = 0.2126 R + 0.7152 G + 0.0722 B (linear sRGB).

    \b
    Example:
      gonio brdf albedo lambert+ggx -p albedo=0.8 -p ks=0.5 -p alpha=0.3
    """
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from gonio.radiometry.photometry import luminous_reflectance

    thetas = _parse_thetas(theta_i, _DEFAULT_THETAS)
    brdf, label = _resolve(model_or_file, _parse_params(params), fresnel, g1)
    a = np.asarray(brdf.albedo(np.radians(thetas)), dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    grey = bool(np.allclose(a, a[:, :1]))
    # escaped: a spec's "[fresnel=schlick]" or a file name's brackets are not markup
    table = Table(title=escape(f"directional albedo of {label}"))
    table.add_column("θi (deg)", justify="right")
    names = ("albedo",) if grey else ("R", "G", "B")
    for n in names:
        table.add_column(n, justify="right")
    if not grey:
        table.add_column("Y (sRGB)", justify="right")
        lum = luminous_reflectance(a)
    for i, (t, row) in enumerate(zip(thetas, a, strict=True)):
        vals = row[:1] if grey else row
        cells = [f"[bold red]{v:.6f}[/]" if v > 1.0 else f"{v:.6f}" for v in vals]
        if not grey:
            cells.append(f"{lum[i]:.6f}")
        table.add_row(f"{t:g}", *cells)
    Console().print(table)
    if np.any(a > 1.0):
        i, c = np.unravel_index(int(np.argmax(a)), a.shape)
        where = "" if grey else f" ({'RGB'[c]} channel)"
        msg = (
            f"warning: the directional albedo exceeds 1 (max {a[i, c]:.6f} at theta_i = "
            f"{thetas[i]:g} deg{where}): these parameters create energy"
        )
        click.secho(msg, fg="yellow", err=True)
        if strict:
            raise ParameterError(msg.removeprefix("warning: "))
