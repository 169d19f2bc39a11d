"""``gonio sim render``: render a scene file to a DNG (and its ground truth)."""

from __future__ import annotations

import math
from pathlib import Path

import click

from gonio.cli import distinct_outputs


def _positive(ctx, param, value: float | None) -> float | None:
    """Reject zero, negative, nan and infinite settings before anything is rendered."""
    if value is not None and not (math.isfinite(value) and value > 0):
        raise click.BadParameter(f"expected a positive finite number, got {value}")
    return value


def _exposure(ctx, param, value: float | None) -> float | None:
    """A positive exposure of at most an hour (the scene's and the sensor's bound)."""
    from gonio.simulator.scene import MAX_EXPOSURE_S

    value = _positive(ctx, param, value)
    if value is not None and value > MAX_EXPOSURE_S:
        raise click.BadParameter(f"expected at most {MAX_EXPOSURE_S:g} s, got {value:g} s")
    return value


@click.command("render")
@click.argument("scene_file", metavar="SCENE.toml", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--out",
    "out",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="DNG file to write (Bayer mosaic + metadata, readable by rawpy/LibRaw).",
)
@click.option(
    "--truth",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also write the ground truth (noise-free radiance, wi, wo, masks) as HDF5.",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Sensor-noise seed: the same seed gives the same file bit for bit.",
)
@click.option(
    "--exposure-time",
    type=float,
    callback=_exposure,
    default=None,
    help="Seconds (default: camera.exposure_time in the scene).",
)
@click.option(
    "--iso", type=float, default=None, callback=_positive, help="ISO (default: camera.iso)."
)
@click.option(
    "--f-number",
    type=float,
    default=None,
    callback=_positive,
    help="Aperture (default: camera.f_number).",
)
@click.option(
    "--tolerance",
    type=float,
    callback=_positive,
    default=None,
    help="Relative per-pixel error target of the light integral (default: render.tolerance).",
)
@click.option(
    "--strategy",
    type=click.Choice(["auto", "point", "quadrature", "mc"]),
    default=None,
    help="Light integration (default: render.strategy, normally auto).",
)
@click.option(
    "--reference",
    is_flag=True,
    help="Render a Lambertian reference target (albedo 0.99) in place of the sample.",
)
@click.option(
    "--preview",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Write a PNG preview of the radiance (and region mask) too.",
)
@click.option(
    "--max-memory-gb",
    type=float,
    default=None,
    callback=_positive,
    help="Refuse a render estimated to need more memory than this, GB (default: half of "
    "this machine's memory).",
)
@click.option("--force", is_flag=True, help="Overwrite existing output files.")
def render_cmd(
    scene_file,
    out,
    truth,
    seed,
    exposure_time,
    iso,
    f_number,
    tolerance,
    strategy,
    reference,
    preview,
    max_memory_gb,
    force,
):
    """Render SCENE.toml as the simulated camera would capture it, and write a DNG.

    \b
    The renderer solves the rendering equation on the sample plane (sample BRDF,
    Lambertian holder with its ChArUco board, point/disk/rectangle lights, box and
    cylinder occluders); the sensor model adds shot, read and dark noise and writes a
    Bayer mosaic with CFA pattern, black/white levels, colour matrix, as-shot neutral,
    exposure time, f-number and ISO.  See examples/scene.toml for the schema.

    \b
    Example:
      gonio sim render examples/scene.toml --out shot.dng --truth shot.h5 --seed 1
    """
    from rich.console import Console

    from gonio.app.scenes import load_scene
    from gonio.errors import ConfigError, FileFormatError
    from gonio.simulator.dng import dng_bytes, write_dng
    from gonio.simulator.render import render, save_truth
    from gonio.simulator.sensor import simulate_raw

    console = Console(stderr=True)
    if out.suffix.lower() != ".dng":
        raise click.BadParameter(f"expected a .dng file name, got '{out.name}'", param_hint="--out")
    if preview is not None and preview.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise click.BadParameter(
            f"expected a .png, .pdf or .svg file name, got '{preview.name}'", param_hint="--preview"
        )
    distinct_outputs(("--out", out), ("--truth", truth), ("--preview", preview))
    for hint, p in (("--out", out), ("--truth", truth), ("--preview", preview)):
        if p is None:
            continue
        if p.exists() and not force:
            raise FileFormatError(p, "exists; refusing to overwrite (use --force)")
        # Checked before rendering so a bad path cannot leave the DNG without its truth.
        if not p.parent.is_dir():
            raise click.BadParameter(
                f"folder '{p.parent}' of {p.name} does not exist; create it first",
                param_hint=hint,
            )
    scene = load_scene(scene_file)
    try:
        # the sample's BRDF is resolved lazily; fail now, naming the file (and keep it:
        # measured files, a mix's too, are slow to load)
        brdf = scene.build_brdf()
    except ConfigError as exc:
        raise ConfigError(f"{scene_file}: {exc}") from None
    if reference:
        scene, brdf = scene.with_reference_target(0.99), None
    limit = None if max_memory_gb is None else max_memory_gb * 1e9
    try:
        with console.status("rendering..."):
            result = render(
                scene, tolerance=tolerance, strategy=strategy, max_memory_bytes=limit, brdf=brdf
            )
        frame = simulate_raw(
            result.radiance,
            scene.camera,
            exposure_time=exposure_time,
            iso=iso,
            f_number=f_number,
            seed=seed,
        )
    except ConfigError as exc:  # the render's own checks (memory, albedo map, view)
        raise ConfigError(f"{scene_file}: {exc}") from None
    except MemoryError:
        # The estimate passed but the machine had less free memory than it has in all.
        w, h = scene.camera.resolution
        raise ConfigError(
            f"{scene_file}: out of memory rendering {w} x {h} pixels "
            f"(render.antialias = {scene.render.antialias}); lower camera.resolution or "
            "render.antialias, or free memory (nothing was written)"
        ) from None
    write_dng(out, dng_bytes(frame), overwrite=force)
    if truth is not None:
        save_truth(truth, result, scene, overwrite=force)
    if preview is not None:
        _preview(preview, result)
    s = result.stats
    for li in s.lights:
        console.print(
            f"light {li.kind}: {li.strategy}, {li.nodes} node(s), "
            f"estimated error {li.estimated_error:.2g}, "
            f"occluders tested {li.occluders_tested}, culled {li.occluders_culled}"
            + (
                f"; {li.penumbra_points} penumbra points at {li.penumbra_nodes} nodes "
                f"(estimated error {li.penumbra_error:.2g})"
                if li.penumbra_points
                else ""
            )
            + ("" if li.tolerance_met else " [tolerance NOT met]"),
            markup=False,  # rich took "[tolerance NOT met]" for a tag: the warning never showed
        )
    sat = float((frame.mosaic >= frame.white_level).mean())
    console.print(
        f"{s.pixels_shaded}/{s.pixels} pixels shaded, {s.pixels_skipped} skipped, "
        f"{s.edge_pixels} edge pixels anti-aliased; {s.seconds:.2f} s; "
        f"saturated {sat:.1%}"
    )
    console.print(f"wrote {out}" + (f" and {truth}" if truth else ""), markup=False)


def _preview(path: Path, result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    img = result.radiance
    scale = np.percentile(img[result.region > 0], 99.5) if np.any(result.region > 0) else 1.0
    fig, ax = plt.subplots(1, 2, figsize=(10, 4.5))
    ax[0].imshow(np.clip(img / max(scale, 1e-300), 0, 1) ** (1 / 2.2))
    ax[0].set_title("radiance (linear -> gamma 2.2)")
    ax[1].imshow(result.region, cmap="tab10", vmin=0, vmax=9)
    ax[1].set_title("region: 1 sample, 2 holder, 3 patch, 4 occluded")
    for a in ax:
        a.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
