"""``gonio capture reduce`` and ``gonio capture calibrate-noise``."""

from __future__ import annotations

import os
from pathlib import Path

import click

from gonio.cli import FiniteFloatRange, distinct_outputs
from gonio.errors import ReductionError


@click.command("reduce")
@click.argument("session_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Output file (default: SESSION/samples.h5).",
)
@click.option(
    "--config",
    "config_file",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    default=None,
    help="Reduction setup (camera matrix, board, sample, light, noise; see "
    "examples/reduction.toml) to use instead of SESSION/reduction.toml.",
)
@click.option(
    "--camera-calibration",
    "camera_file",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    default=None,
    help="Camera calibration from 'gonio calibrate camera' (camera.toml): its [camera] "
    "replaces the reduction setup's.  One made with another camera than the session's "
    "is refused.",
)
@click.option(
    "--noise",
    "noise_file",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    default=None,
    help="Noise model JSON from 'gonio capture calibrate-noise' "
    "(default: SESSION/noise.json, else the reduction.toml's [noise]).",
)
@click.option(
    "--grid",
    type=click.IntRange(1, 20),
    default=None,
    help="Regions per side of the sample's central area (each one a sample).",
)
@click.option(
    "--roi-fraction",
    type=FiniteFloatRange(0.05, 1.0),
    default=None,
    help="Fraction of the sample's width and height used (keeps off its edges).",
)
@click.option(
    "--tolerance-deg",
    type=FiniteFloatRange(0.0, min_open=True),
    default=None,
    help="Largest camera-direction disagreement between board and rig before the "
    "samples are flagged GEOMETRY_MISMATCH.",
)
@click.option(
    "--geometry",
    type=click.Choice(["auto", "board", "rig"]),
    default=None,
    help="Camera pose from the ChArUco board in each pose (board), from the rig's "
    "read-back pose through its kinematics (rig: a calibrated rig, or the exact simulated "
    "one), or (auto) from the board where it shows enough corners, is not too oblique "
    "and its covariance moves the directions less than the rig's calibration does, and "
    "the rig elsewhere; the board checks the rig wherever it is used.  "
    "[default: reduction.toml's, else auto]",
)
@click.option(
    "--max-region-spread-deg",
    "max_spread",
    type=FiniteFloatRange(0.0, 90.0, min_open=True),
    default=None,
    help="Trim each region to a spread of directions of at most this many degrees, seen "
    "from the camera and from the light (never along a grazing view's tilt).  "
    "[default: reduction.toml's, else whole regions]",
)
@click.option(
    "--threads",
    type=click.IntRange(1, 64),
    default=None,
    help="Threads, this one included (default: 2 on a machine with 2 or more cores): the "
    "others decode RAW files ahead while poses are measured.  The output is the same for "
    "any number.",
)
@click.option(
    "--texels",
    "texels_text",
    metavar="N|NXxNY",
    default=None,
    help="Also write SESSION/texels.h5: the sample divided into N x N texels (row 0 at "
    "+y, column 0 at -x), every texel's sample in every pose with its directions and "
    "full error budget, chunked by texels for per-texel fitting ('gonio fit "
    "SESSION/texels.h5 --svbrdf').  The region grid becomes the texel grid (N per side "
    "over the whole sample: not with --grid or --roi-fraction); samples.h5 holds the "
    "same samples pooled.  Refused when a texel would be narrower than 2 pixels at the "
    "best-resolving pose (the message gives the largest N that fits).  NXxNY: NX texels "
    "along x by NY along y (e.g. 16x12 for a 4:3 sample).",
)
@click.option("--no-plot", is_flag=True, help="Do not write SESSION/samples.png.")
@click.option(
    "--force", is_flag=True, help="Replace an existing --out file that is not a samples file."
)
@click.option("--quiet", is_flag=True, help="No progress bar or summary table.")
def reduce_cmd(
    session_dir: Path,
    out: Path | None,
    config_file: Path | None,
    camera_file: Path | None,
    noise_file: Path | None,
    grid: int | None,
    roi_fraction: float | None,
    tolerance_deg: float | None,
    geometry: str | None,
    max_spread: float | None,
    threads: int | None,
    texels_text: str | None,
    no_plot: bool,
    force: bool,
    quiet: bool,
) -> None:
    """Reduce a capture session's RAW brackets to calibrated BRDF samples.

    \b
    For every pose: check each RAW file against the journal (byte count and digest),
    decode the mosaics (no demosaicing), subtract the master dark, find the holder's
    ChArUco board to measure the camera pose, merge the bracket with inverse-variance
    weights, and average the sample's regions per colour channel.  The reference-target
    poses give the irradiance, so BRDF = L_o / E_i in 1/sr, with a standard deviation
    from the sensor's noise model.

    \b
    The camera matrix, board, sample size, light and noise model come from
    SESSION/reduction.toml (or --config; see examples/reduction.toml); the camera from
    its [camera] table, its [camera] file = "camera.toml", or --camera-calibration.

    \b
    Writes SESSION/samples.h5 (see gonio.dataset), SESSION/reduction.json (samples kept
    and rejected, with reasons) and SESSION/samples.png (samples over the angle domain).
    Re-running gives the same file; the RAW files are never modified.  One reduction at
    a time writes an output: a second one into the same file refuses.

    \b
    Spatially varying samples (--texels): the same per-pose reduction with one region
    per texel over the whole sample, less 1.5 pixels along each texel's boundaries (a
    pixel there sees the neighbouring texel too; [reduction] region_margin_px sets more);
    SESSION/texels.h5 (gonio.texels) holds, per texel and sample pose, wi, wo, the
    BRDF, its std and budget terms, flags and the geometry modes, and reduction.json
    gains a "texels" section (pixels per texel at the best-resolving pose, samples kept
    per texel, chunking).

    \b
    Examples:
      gonio capture reduce runs/paper/ --grid 3
      gonio capture reduce runs/paper/ --texels 16
    """
    from rich.console import Console
    from rich.markup import escape  # paths and plan tables ("[flats]") are not markup
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn
    from rich.table import Table

    from gonio.capture.manifest import load_manifest
    from gonio.capture.noise import NoiseModel
    from gonio.capture.reduce import reduce_session, resolve_setup

    texels = None
    if texels_text is not None:
        from gonio.capture.texel_reduce import parse_texels

        texels = parse_texels(texels_text)
        if grid is not None or roi_fraction is not None:
            raise ReductionError(
                "--texels sets the region grid (N per side) over the whole sample: "
                "leave out --grid and --roi-fraction"
            )
    console = Console(stderr=True, quiet=quiet)
    noise = NoiseModel.load(noise_file) if noise_file else None
    setup = resolve_setup(
        session_dir,
        load_manifest(session_dir),
        noise,
        config=config_file,
        camera_calibration=camera_file,
    )
    upd = {
        k: v
        for k, v in dict(
            grid=grid,
            roi_fraction=roi_fraction,
            geometry_tolerance_deg=tolerance_deg,
            geometry=geometry,
            max_region_spread_deg=max_spread,
        ).items()
        if v is not None
    }
    if upd:
        setup = setup.replace(**upd)
    _check_outputs(session_dir, out, force, plot=not no_plot)
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("reducing poses", total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        res = reduce_session(
            session_dir,
            out=out,
            setup=setup,
            plot=not no_plot,
            progress=progress,
            threads=threads,
            texels=texels,
        )
    table = Table(title="BRDF samples")
    table.add_column("samples", justify="right")
    table.add_column("count", justify="right")
    table.add_row("written", str(res.n_samples))
    table.add_row("kept (no flag)", str(res.n_kept))
    for reason, n in sorted(res.rejected.items()):
        table.add_row(escape(f"rejected: {reason}"), str(n))
    console.print(table)
    budget = res.summary.get("budget") or {}
    if budget.get("terms"):
        from gonio.capture.budget import budget_table

        console.print(budget_table(budget["terms"]))
        for w in budget.get("warnings", []):
            console.print(f"[yellow]budget: {escape(str(w))}", soft_wrap=True)
    for fp in res.summary["failed_poses"]:
        console.print(
            f"[yellow]pose {fp['pose']} ({fp['kind']}): {escape(str(fp['reason']))}", soft_wrap=True
        )
    for frame, why in res.summary.get("frame_problems", {}).items():
        console.print(f"[yellow]frame {escape(str(frame))}: {escape(str(why))}", soft_wrap=True)
    console.print(f"wrote {res.path}", soft_wrap=True, markup=False)
    tex = res.summary.get("texels")
    if tex:
        per = tex["kept_per_texel"]
        console.print(
            f"texels: {res.path.with_name(tex['file'])} ({tex['texels'][0]}x"
            f"{tex['texels'][1]} texels x {tex['poses']} poses; kept per texel "
            f"{per['min']}..{per['max']}, {tex['texels_without_samples']} texel(s) without)",
            soft_wrap=True,
            markup=False,
        )
    if res.plot:
        console.print(f"plot: {res.plot}", soft_wrap=True, markup=False)
    # What the session lacks and what it costs: printed even with --quiet (never silent),
    # plain text (the warnings name plan tables in brackets, which rich takes for markup).
    for w in getattr(res, "warnings", []):
        click.echo(f"warning: {w}", err=True)


@click.command("calibrate-noise")
@click.option(
    "--flat",
    "flats",
    multiple=True,
    required=True,
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    help="Flat-field RAW files (uniform target, nothing saturated); give them in "
    "pairs shot with identical settings, at two or more exposure levels.",
)
@click.option(
    "--dark",
    "darks",
    multiple=True,
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    help="Dark RAW files (lens capped), in pairs at the same ISO: pin the read noise.",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Where to write the noise model JSON (e.g. SESSION/noise.json).",
)
@click.option(
    "--plot",
    "plot_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also save the photon-transfer curve as an image.",
)
def calibrate_noise_cmd(
    flats: tuple[Path, ...], darks: tuple[Path, ...], out: Path, plot_file: Path | None
) -> None:
    """Estimate the camera's gain and read noise (photon transfer) from flat and dark pairs.

    \b
    The variance of the difference of two identical flats, over two, removes fixed-pattern
    noise; plotted against the mean it is a straight line: slope = gain (DN per electron),
    intercept = read noise squared.  The model feeds the per-sample standard deviations of
    'gonio capture reduce' (put it in SESSION/noise.json or pass --noise).

    \b
    Example:
      gonio capture calibrate-noise --flat f1a.dng --flat f1b.dng --flat f2a.dng \\
          --flat f2b.dng --dark d1.dng --dark d2.dng --out S/noise.json --plot ptc.png
    """
    from gonio.capture.noise import estimate_noise
    from gonio.capture.raw import read_raw

    if len(flats) % 2 or len(darks) % 2:
        raise ReductionError(
            f"flats and darks come in pairs; got {len(flats)} flats and {len(darks)} darks"
        )
    distinct_outputs(("--out", out), ("--plot", plot_file))
    if out.exists():
        raise ReductionError(f"{out} exists; refusing to overwrite a noise model")
    if plot_file is not None:  # checked before any work, so nothing is half written
        pf = Path(plot_file)
        if pf.suffix.lower() not in (".png", ".pdf", ".svg"):
            raise click.BadParameter(
                f"expected a .png, .pdf or .svg file name, got '{pf.name}'", param_hint="--plot"
            )
        if pf.exists():
            raise ReductionError(f"{pf} exists; refusing to overwrite a plot")
    fr = [read_raw(p) for p in flats]
    dk = [read_raw(p) for p in darks]
    pt = estimate_noise(
        list(zip(fr[0::2], fr[1::2], strict=True)), list(zip(dk[0::2], dk[1::2], strict=True))
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    pt.model.save(out)
    click.echo(
        f"gain {pt.model.gain:.4g} DN/e-, read noise {pt.model.read_noise:.4g} DN at ISO "
        f"{pt.model.iso:g} -> {out}"
    )
    if plot_file:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import numpy as np

        fig, ax = plt.subplots(figsize=(5, 4))
        for c, col in enumerate("rgb"):
            ax.plot(pt.means[:, c], pt.variances[:, c], "o", color=col, label="RGB"[c])
        x = np.linspace(0, np.nanmax(pt.means), 50)
        ax.plot(x, pt.model.variance(x), "k-", label="model")
        ax.set_xlabel("mean signal (DN above black)")
        ax.set_ylabel("temporal variance (DN^2)")
        ax.legend()
        fig.tight_layout()
        fig.savefig(plot_file, dpi=90)
        plt.close(fig)


def _check_outputs(session: Path, out: Path | None, force: bool, plot: bool) -> None:
    """Refuse, before anything is measured, an output that would destroy what is not a
    reduction's: a folder or a device at the path (``--force`` or not), a name the set
    writes beside it, one of the session's own files, and -- without ``--force`` -- a
    file that is not a gonio samples file at the path (the default ``SESSION/samples.h5``
    too) or a ``reduction.json`` / ``samples.png`` beside it that no reduction wrote."""
    from gonio.capture.reduce import PLOT_FILE, SAMPLES_FILE, SUMMARY_FILE, TEXELS_FILE
    from gonio.capture.session_dir import refuse_session_file

    path = out if out is not None else session / SAMPLES_FILE
    hint = "--out " if out is not None else ""
    if path.exists() and not path.is_file():
        # a folder, a device (/dev/null), a socket: --force must not replace it
        raise ReductionError(
            f"{hint}{path}: exists and is not a regular file; expected the path of a "
            "samples file (.h5)"
        )
    if path.name in (SUMMARY_FILE, PLOT_FILE, TEXELS_FILE):
        raise ReductionError(
            f"{hint}{path}: {SUMMARY_FILE}, {PLOT_FILE} and {TEXELS_FILE} are written "
            "beside the samples file; give the samples file another name"
        )
    refuse_session_file("--out", path, session)
    if force:
        return
    if path.exists() and not _is_samples_file(path):
        raise ReductionError(
            f"{path} exists and is not a gonio samples file; pass --force to replace it"
        )
    old_set = path.exists()  # a gonio samples file: its summary and plot go with it
    for name in (SUMMARY_FILE, PLOT_FILE) if plot else (SUMMARY_FILE,):
        p = path.with_name(name)
        # a link into an output set (this output's or another's in the folder, whose
        # files stay in its set folder) is a reduction's
        target = os.readlink(p) if p.is_symlink() else ""
        ours = target.startswith(".") and target.split("/", 1)[0].endswith(".set")
        if p.exists() and not ours and not old_set:
            raise ReductionError(
                f"{p} exists and no reduction of {path.name} wrote it; pass --force to "
                "replace it or choose another --out"
            )


def _is_samples_file(path: Path) -> bool:
    """Whether ``path`` is a samples.h5 (re-running a reduction may replace it)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("schema") == "gonio.samples"
    except OSError:
        return False
