"""``gonio calibrate``: the calibrations a lab makes before measuring.

``camera`` solves the camera matrix and lens distortion from ChArUco views (read from a
session or a folder of images, or shot first through the session API exactly as
``gonio capture run`` shoots) and writes the ``[camera]`` table of ``reduction.toml``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from gonio.cli import LazyGroup

__all__ = ["calibrate", "camera_cmd"]


@click.group(
    cls=LazyGroup,
    lazy_commands={
        "plan": "gonio.app.calibrate_rig_cli:plan_cmd",
        "rig": "gonio.app.calibrate_rig_cli:rig_cmd",
    },
)
def calibrate() -> None:
    """Calibrations: the camera (intrinsics, distortion) and the rig as built.

    \b
    The lab path, in order (README, "The lab path"):
      gonio calibrate plan --rig rig.toml --kind camera --out cal/camera_plan.toml
      gonio calibrate camera --plan cal/camera_plan.toml --rig rig.toml \\
          --camera gphoto2 --out cal/camera_session --calibration cal/camera.toml
      gonio calibrate plan --rig rig.toml --kind rig --out cal/rig_plan.toml
      gonio capture run cal/rig_plan.toml --rig rig.toml --camera gphoto2 \\
          --out cal/rig_session
      gonio calibrate rig cal/rig_session --rig rig.toml \\
          --camera-calibration cal/camera.toml --out cal/rig_calibrated.toml
      gonio capture run plan.toml --rig cal/rig_calibrated.toml ... --out S/
      gonio capture reduce S/ --camera-calibration cal/camera.toml
    """


def _board_from(path: Path | None, session: Path | None) -> tuple[Any, str]:
    """The holder's board: ``--board`` (a ``[board]`` table, as in reduction.toml, or a
    scene's ``[holder.board]``), else a simulated session's scene, else the session's
    reduction.toml, else the default board."""
    from gonio.capture.fiducials import BoardSpec
    from gonio.config import read_toml
    from gonio.errors import ConfigError

    def from_doc(doc: dict[str, Any], where: str) -> Any:
        table = doc.get("board") or (doc.get("holder") or {}).get("board")
        if not isinstance(table, dict):
            return None
        try:
            board = BoardSpec.from_mapping(table)
        except (TypeError, ValueError) as exc:
            # (a board of more markers than its dictionary holds among them: it stalled
            # the calibration for minutes per image)
            raise ConfigError(f"{where}: [board]: {exc}") from None
        return board

    if path is not None:
        board = from_doc(read_toml(path, "board"), str(path))
        if board is None:
            raise ConfigError(f"{path}: no [board] (or [holder.board]) table")
        return board, str(path)
    if session is not None and (session / "manifest.json").is_file():
        from gonio.capture.manifest import load_manifest

        scene = ((load_manifest(session).get("simulation") or {}).get("scene")) or {}
        board = from_doc(scene, "the session's scene")
        if board is not None:
            return board, "the session's simulated scene"
    if session is not None and (session / "reduction.toml").is_file():
        board = from_doc(read_toml(session / "reduction.toml", "reduction setup"), "")
        if board is not None:
            return board, str(session / "reduction.toml")
    return BoardSpec(), "the default board (7x7 squares of 20 mm, DICT_4X4_50)"


def _session_identity(session: Path, size: tuple[int, int]) -> tuple[dict[str, Any], str | None]:
    """The camera identity of a session (its manifest) and the CFA pattern of its frames."""
    from gonio.capture.camera_calibration import camera_identity
    from gonio.capture.journal import read_journal, session_file
    from gonio.capture.manifest import read_manifest
    from gonio.capture.raw import read_raw

    ident = camera_identity(read_manifest(session).camera.model_dump(), size)
    cfa = None
    for rec in read_journal(session / "journal.jsonl"):
        if rec.get("type") == "shot" and rec.get("file"):
            path = session_file(session, rec)
            if path.is_file():
                cfa = read_raw(path).cfa_pattern
                break
    return ident, cfa


def _print_result(cal: Any, out: Path, board_source: str) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    con = Console()
    # escaped: sources, labels and paths may hold brackets, which rich reads as markup
    t = Table("parameter", "value", "std", title=escape(f"camera calibration ({board_source})"))
    for name, (v, s) in cal.parameters.items():
        unit = " px" if name in ("fx", "fy", "cx", "cy") else ""
        t.add_row(name, f"{v:.6g}{unit}", f"{s:.2g}{unit}")
    con.print(t)
    w, h = cal.image_size
    con.print(
        f"image {w}x{h}; reprojection RMS [bold]{cal.rms_px:.3f} px[/] over {cal.n_points} "
        f"corners in {len(cal.used)} views"
    )
    worst = sorted(cal.view_errors.items(), key=lambda kv: -kv[1])[:3]
    if worst:
        con.print(
            "largest per-view RMS: " + ", ".join(f"{k} {e:.3f} px" for k, e in worst),
            markup=False,
        )
    if cal.rejected:
        r = Table("view", "reason", title=f"{len(cal.rejected)} views rejected")
        for rej in cal.rejected:
            r.add_row(escape(rej.label), escape(rej.reason))
        con.print(r)
    con.print(f"wrote {out}", markup=False)


def plot_calibration(cal: Any, path: Path) -> None:
    """Per-view reprojection RMS (bars) and the corners used over the image (coverage),
    one PNG written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gonio.atomic import atomic_path

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    labels = list(cal.view_errors)
    a.bar(range(len(labels)), [cal.view_errors[k] for k in labels], color="tab:blue")
    a.axhline(cal.rms_px, color="k", lw=0.8, ls="--", label=f"all views {cal.rms_px:.3f} px")
    a.set_xticks(range(len(labels)), labels, rotation=90, fontsize=6)
    a.set_ylabel("reprojection RMS, px")
    a.set_title("per-view error", fontsize=9)
    a.legend(fontsize=7)
    w, h = cal.image_size
    for k in labels:
        p = cal.image_points[k]
        b.plot(p[:, 0], p[:, 1], ".", ms=2)
    b.set_xlim(0, w)
    b.set_ylim(h, 0)
    b.set_aspect("equal")
    b.set_title("corner coverage (distortion is known where there are corners)", fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


@calibrate.command("camera")
@click.argument(
    "source", required=False, type=click.Path(exists=True, file_okay=False, path_type=Path)
)
@click.option(
    "--calibration",
    "out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Camera calibration TOML to write (e.g. camera.toml).",
)
@click.option("--force", is_flag=True, help="Replace an existing --calibration (and plot).")
@click.option(
    "--plot",
    is_flag=True,
    help="Also write NAME_views.png beside the calibration: per-view errors, corner coverage.",
)
@click.option(
    "--board",
    "board_file",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    default=None,
    help="TOML with the board's [board] table (squares_x, squares_y, square_length, "
    "marker_length, dictionary), e.g. the lab's reduction.toml.",
)
@click.option("--plan", "plan_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--rig", "rig_file", type=click.Path(dir_okay=False), default=None)
@click.option(
    "--camera",
    "camera_backend",
    type=click.Choice(["simulated", "gphoto2"]),
    default="gphoto2",
    show_default=True,
    help="With --plan: the camera to shoot with; with an image folder: the backend the "
    "images came from (recorded in the calibration's identity with --camera-model and "
    "--camera-serial, and checked when the calibration is used).",
)
@click.option(
    "--out",
    "session_out",
    type=click.Path(file_okay=False, path_type=Path),
    help="With --plan: the new session directory the views are shot into.",
)
@click.option("--scene", "scene_file", type=click.Path(dir_okay=False), default=None)
@click.option(
    "--world",
    default=None,
    metavar="perfect|realistic|FILE",
    help="With --plan and --camera simulated: the as-built world (as gonio capture run).",
)
@click.option(
    "--world-seed",
    type=click.IntRange(0),
    default=None,
    help="Seed the world's errors are drawn from (as gonio capture run).",
)
@click.option("--camera-port", default=None, help="gphoto2 port (e.g. usb:001,004).")
@click.option("--camera-model", default=None, help="Image folder: the camera's model.")
@click.option("--camera-serial", default=None, help="Image folder: the camera's serial.")
@click.option("--min-views", default=6, show_default=True, type=click.IntRange(3))
@click.option("--min-corners", default=8, show_default=True, type=click.IntRange(4))
@click.option("--quiet", is_flag=True, help="No progress bar while shooting.")
@click.pass_context
def camera_cmd(
    ctx: click.Context,
    source: Path | None,
    out: Path,
    force: bool,
    plot: bool,
    board_file: Path | None,
    plan_file: Path | None,
    rig_file: str | None,
    camera_backend: str,
    session_out: Path | None,
    scene_file: str | None,
    world: str | None,
    world_seed: int | None,
    camera_port: str | None,
    camera_model: str | None,
    camera_serial: str | None,
    min_views: int,
    min_corners: int,
    quiet: bool,
) -> None:
    """Calibrate the camera: focal lengths, principal point, lens distortion.

    \b
    Show the holder's ChArUco board to the camera from many directions (the board
    tilted 0-45 deg, filling different parts of the image: corners near the image
    edges are what pin the distortion down), then either
      gonio calibrate camera SESSION/ --calibration camera.toml
      gonio calibrate camera FOLDER/  --calibration camera.toml   (RAW/DNG/PNG/JPEG)
    or let gonio shoot the views first, as 'gonio capture run' would:
      gonio calibrate camera --plan plan.toml --rig rig.toml --camera gphoto2 \\
          --out CAM/ --calibration camera.toml --plot

    \b
    The board is found in the best-exposed frame of every pose, OpenCV's
    calibrateCameraExtended solves fx, fy, cx, cy and k1 k2 p1 p2 (k3 held at 0, as
    usual for a non-wide lens) with a standard deviation each and their covariance
    (kept for the rig calibration's prior); views with fewer than --min-corners
    corners or an outlying error (over 3x the median view's and over 1 px) are left
    out, with the reason, and the solve repeated. Pixel coordinates: OpenCV's (pixel
    centres at integers).

    \b
    camera.toml holds a [camera] table that reduction.toml takes as is (K, dist,
    width, height, cfa_pattern) and [camera.calibration]: the standard deviations, the
    RMS, the views used and rejected, and the camera's identity and digest, so a
    calibration is never applied to another camera. An existing file is kept unless
    --force.
    """
    from gonio.capture.camera_calibration import (
        calibrate_camera,
        views_from_folder,
        views_from_session,
        write_camera_calibration,
    )

    if (source is None) == (plan_file is None):
        raise click.UsageError("give either SOURCE (a session or image folder) or --plan")
    if plan_file is not None and session_out is None:
        raise click.UsageError("--plan needs --out SESSION (the new session directory)")
    plot_path = out.with_name(out.stem + "_views.png")
    # refuse, before anything moves or is solved, to clobber a file
    for path, what in ((out, "--calibration"), *(((plot_path, "--plot"),) if plot else ())):
        if path.exists() and not force:
            raise click.BadParameter(
                f"'{path}' exists; pass --force to replace it or choose another file",
                param_hint=what,
            )
        if not path.parent.is_dir():
            raise click.BadParameter(f"folder '{path.parent}' does not exist", param_hint=what)
    if plan_file is not None:
        from gonio.app.capture_cli import run_cmd

        ctx.invoke(
            run_cmd,
            plan_file=plan_file,
            rig_file=rig_file,
            out=session_out,
            scene_file=scene_file,
            world=world,
            world_seed=world_seed,
            camera_backend=camera_backend,
            camera_port=camera_port,
            sim_speed=None,
            quiet=quiet,
        )
        source = session_out
    assert source is not None
    is_session = (source / "journal.jsonl").is_file()
    board, board_source = _board_from(board_file, source if is_session else None)
    if is_session:
        views = views_from_session(source, board)
    else:
        views = views_from_folder(source, board)
    cal = calibrate_camera(views, min_views=min_views, min_corners=min_corners, source=str(source))
    if is_session:
        identity, cfa = _session_identity(source, cal.image_size)
    else:
        identity = {
            "backend": camera_backend,
            "model": camera_model or "unknown",
            "serial": camera_serial,
            "resolution": list(cal.image_size),
        }
        cfa = None
    write_camera_calibration(out, cal, identity, cfa_pattern=cfa, force=force)
    if plot:
        plot_calibration(cal, plot_path)
    _print_result(cal, out, board_source)
    if plot:
        click.echo(f"wrote {plot_path}")
