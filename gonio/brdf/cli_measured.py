"""``gonio brdf info`` and ``gonio brdf convert``: inspect and convert measured BRDF files."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from gonio.errors import FileFormatError

__all__ = ["info_cmd", "convert_cmd"]


def _parse_angles(text: str) -> np.ndarray:
    """``--theta-i-deg``: comma-separated incident elevations in [0, 90) degrees.

    Raises
    ------
    click.BadParameter
        Naming the option and the text: not numbers, none given, or outside [0, 90)
        (NaN included: it would otherwise print a table of NaN and exit 0).
    """
    hint = "--theta-i-deg"
    try:
        vals = np.array([float(t) for t in text.split(",") if t.strip()], dtype=np.float64)
    except ValueError as exc:
        raise click.BadParameter(
            f"expected comma-separated degrees, got {text!r}", param_hint=hint
        ) from exc
    # Written as "not inside" so that NaN, for which every comparison is false, is refused.
    if vals.size == 0 or not np.all((vals >= 0) & (vals < 90)):
        raise click.BadParameter(
            f"angles must lie in [0, 90) degrees, got {text!r}", param_hint=hint
        )
    return vals


@click.command("info")
@click.argument("file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--theta-i-deg",
    default="0,30,60,80",
    show_default=True,
    help="Incident elevations (degrees, comma-separated) at which to print the albedo.",
)
def info_cmd(file: Path, theta_i_deg: str) -> None:
    """Describe a measured BRDF FILE: format, material, dimensions, directional albedo.

    FILE is an RGL-EPFL material (*.bsdf, tensor_file v1.0) or a MERL table (*.binary);
    the format is recognised from the content, not the name.  The directional albedo
    a(theta_i) = integral of f_r cos(theta_o) over the hemisphere is printed per RGB
    channel, with its luminance-weighted value Y = 0.2126 R + 0.7152 G + 0.0722 B (the
    files' RGB is linear sRGB); a physically plausible material has a <= 1.

    \b
    Example:
      gonio brdf info paper_white_rgb.bsdf --theta-i-deg 0,45,75
    """
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from gonio.brdf.measured import load
    from gonio.radiometry.photometry import luminous_reflectance

    angles = _parse_angles(theta_i_deg)
    b = load(file)
    console = Console()
    meta = Table(title=escape(file.name), show_header=False)  # a name's brackets: not markup
    meta.add_column("key", style="bold")
    meta.add_column("value")
    meta.add_row("format", {"rgl": "RGL-EPFL tensor_file v1.0", "merl": "MERL binary"}[b.format])
    meta.add_row("description", escape(b.description))
    if b.format == "rgl":
        md = b.metadata
        meta.add_row(
            "kind",
            ("spectral" if md["spectral"] else "RGB")
            + (", isotropic" if md["isotropic"] else ", anisotropic"),
        )
        meta.add_row("theta_i (deg)", ", ".join(f"{t:.1f}" for t in md["theta_i_deg"]))
        meta.add_row("phi_i (deg)", ", ".join(f"{t:.1f}" for t in md["phi_i_deg"]))
        meta.add_row("sample-space grid", "{} x {}".format(*md["resolution"]))
        meta.add_row("VNDF grid", "{} x {}".format(*md["vndf_resolution"]))
        meta.add_row("channels", str(md["channels"]))
        if md["spectral"]:
            wl = md["wavelengths_nm"]
            meta.add_row("wavelengths (nm)", f"{wl[0]:.0f} .. {wl[-1]:.0f} ({len(wl)})")
    else:
        d = b.metadata["dimensions"]
        meta.add_row(
            "dimensions", f"theta_h {d['theta_h']} x theta_d {d['theta_d']} x phi_d {d['phi_d']}"
        )
        meta.add_row("missing entries", f"{100 * b.metadata['missing_fraction']:.2f} %")
    console.print(meta)

    if b.format == "rgl" and b.metadata["spectral"]:
        console.print("albedo: not computed (RGB evaluation of spectral files is not supported)")
        return
    alb = b.albedo(np.radians(angles))
    t = Table(title="directional albedo")
    t.add_column("theta_i (deg)", justify="right")
    for c in ("R", "G", "B", "Y (sRGB)"):
        t.add_column(c, justify="right")
    lum = luminous_reflectance(alb)
    for a, row, y in zip(angles, alb, lum, strict=True):
        t.add_row(f"{a:g}", *(f"{v:.4f}" for v in (*row, y)))
    console.print(t)


@click.command("convert")
@click.argument("src", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("dst", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--force", is_flag=True, help="Overwrite DST if it exists.")
def convert_cmd(src: Path, dst: Path, force: bool) -> None:
    """Resample a measured BRDF SRC into a MERL table DST (*.binary).

    SRC may be any file `gonio brdf info` reads.  Every node of the MERL grid (90 theta_h
    x 90 theta_d x 180 phi_d, half/difference angles) is evaluated from SRC; nodes whose
    incident or outgoing direction lies below the horizon are marked missing (-1), as in
    measured MERL files.  DST is never overwritten unless --force is given, and is written
    atomically (a failed conversion leaves an existing file intact).

    \b
    Example:
      gonio brdf convert vch_golden_yellow_rgb.bsdf golden_yellow.binary
    """
    from rich.markup import escape
    from rich.progress import Progress

    from gonio.brdf.measured import load
    from gonio.brdf.merl import resample, write_merl

    if dst.suffix.lower() != ".binary":
        raise click.BadParameter(
            f"only MERL output is supported: DST must end in .binary, got {dst.name}",
            param_hint="DST",
        )
    if dst.exists() and not force:
        raise FileFormatError(dst, "output exists; pass --force to overwrite it")
    if not dst.parent.is_dir():
        # Checked before the (slow) resampling so the user learns it at once.
        raise click.BadParameter(
            f"folder '{dst.parent}' of {dst.name} does not exist; create it first",
            param_hint="DST",
        )
    b = load(src)
    with Progress(transient=True) as prog:
        task = prog.add_task(escape(f"resampling {src.name}"), total=1.0)
        m = resample(
            b, description=b.description, progress=lambda d, n: prog.update(task, completed=d / n)
        )
    write_merl(dst, m, replace=force)
    pct = 100 * m.metadata["missing_fraction"]
    click.echo(f"wrote {dst} (MERL; {pct:.1f} % of nodes below the horizon, marked missing)")
