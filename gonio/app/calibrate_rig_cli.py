"""``gonio calibrate plan`` and ``gonio calibrate rig``: calibration plans and the rig
calibration.

``plan`` writes the joint poses of a camera or rig calibration (``[[joint_poses]]``, run
with ``gonio capture run``); for a rig plan it first shows that every parameter is
observable.  ``rig`` reads a calibration session's board views and mirror spots
(:func:`gonio.capture.rig_views.calibration_observations`), solves the as-built
parameters (:func:`gonio.rig.calibration.calibrate_rig`) with the camera calibration as
prior, prints them with their uncertainties, and writes the calibrated rig
configuration; it refuses a camera calibration of another camera, a session of another
rig, and an ill-conditioned fit, naming them, and never overwrites without ``--force``.

The commands are registered in the ``calibrate`` group (``gonio.app.calibrate_cli``) as
``plan_cmd`` and ``rig_cmd``.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import numpy as np

from gonio.cli import FiniteFloatRange

__all__ = ["camera_prior", "plan_cmd", "rig_cmd"]


def _load_rig(path: Path | None):
    from gonio.rig.config import default_rig_config, load_rig_config

    return load_rig_config(path) if path else default_rig_config()


def camera_prior(path: Path):
    """The camera calibration file (``gonio calibrate camera --out``, read by
    ``gonio.capture.camera_calibration.load_camera_calibration``) as the rig
    calibration's :class:`gonio.rig.calibration.CameraPrior`."""
    from gonio.capture.camera_calibration import load_camera_calibration
    from gonio.rig.calibration import CameraPrior

    cam = load_camera_calibration(path)
    rec = cam.calibration
    return CameraPrior(
        K=np.asarray(cam.K, float),
        dist=np.asarray(cam.dist, float),
        K_std=np.asarray(rec.K_std, float),
        dist_std=np.asarray(rec.dist_std, float),
        rms_px=float(rec.rms_px),
        digest=rec.digest,
        width=cam.width,
        height=cam.height,
        covariance=None if rec.covariance is None else np.asarray(rec.covariance, float),
    )


@click.command("plan")
@click.option(
    "--rig",
    "rig_path",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    help="The nominal rig configuration (default: the built-in preset).",
)
@click.option(
    "--kind",
    type=click.Choice(["camera", "rig"]),
    required=True,
    help="camera: board views for the intrinsics; rig: board and mirror views for the rig.",
)
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True)
@click.option(
    "--camera-calibration",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    help="Camera calibration for the observability check (default: a 640 x 480 guess).",
)
@click.option(
    "--seed",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Order of the board views.",
)
@click.option(
    "--spot-exposure",
    type=FiniteFloatRange(min=0, min_open=True),
    default=2e-5,
    show_default=True,
    help="Short exposure of each pose, s: the light's image in the mirror must not clip "
    "(a bright source needs it short; gonio calibrate rig says when it clipped).",
)
@click.option(
    "--board-exposure",
    type=FiniteFloatRange(min=0, min_open=True),
    default=0.02,
    show_default=True,
    help="Long exposure of each pose, s: the board's corners.",
)
@click.option(
    "--size",
    nargs=2,
    type=click.IntRange(16),
    default=(640, 480),
    show_default=True,
    metavar="W H",
    help="Simulated camera resolution written in [simulation] (a real camera ignores it); "
    "the camera and rig calibrations must be shot at the same size.",
)
@click.option("--force", is_flag=True, help="Overwrite an existing --out file.")
def plan_cmd(
    rig_path: Path | None,
    kind: str,
    out: Path,
    camera_calibration: Path | None,
    seed: int,
    spot_exposure: float,
    board_exposure: float,
    size: tuple[int, int],
    force: bool,
) -> None:
    """Write a calibration plan of joint poses (run it with `gonio capture run`).

    \b
    --kind camera: board views for `gonio calibrate camera` (tilted 0-45 deg, different
    parts of the image); --kind rig: board views at many tilts, spins and camera
    azimuths, each joint approached from both sides, then mirror views (a flat mirror
    in the sample's place: the light's image in it gives the light arm).  The plan is
    checked before it is written: every kinematic parameter must be observable.
    """
    from rich.console import Console

    from gonio.capture.plan import MAX_EXPOSURE_S
    from gonio.rig.calibration_plan import (
        camera_calibration_poses,
        check_observable,
        default_camera,
        rig_calibration_poses,
        write_plan,
    )
    from gonio.rig.calibration_record import CalibrationError

    # The plan's own bound, checked here: a plan written with a longer exposure is
    # refused only by the next step (`gonio capture run`), after this one said "wrote".
    for hint, value in (("--spot-exposure", spot_exposure), ("--board-exposure", board_exposure)):
        if value > MAX_EXPOSURE_S:
            raise click.BadParameter(
                f"expected at most {MAX_EXPOSURE_S:g} s (the longest exposure a plan "
                f"accepts), got {value:g} s",
                param_hint=hint,
            )
    if kind == "camera":
        # options of the rig plan only: said, not silently dropped
        ctx = click.get_current_context()
        given = [
            f"--{n.replace('_', '-')}"
            for n in ("camera_calibration", "seed")
            if ctx.get_parameter_source(n) == click.core.ParameterSource.COMMANDLINE
        ]
        if given:
            raise click.UsageError(
                f"{' and '.join(given)} {'apply' if len(given) > 1 else 'applies'} to "
                "--kind rig (the views' order, the observability check of the rig's "
                "parameters); a camera plan has neither"
            )
    console = Console()
    if out.exists() and not force:
        raise CalibrationError(f"{out} exists; not overwritten (use --force to replace it)")
    config = _load_rig(rig_path)
    if kind == "camera":
        poses = camera_calibration_poses(config)
    else:
        poses = rig_calibration_poses(config, seed=seed)
        camera = camera_prior(camera_calibration) if camera_calibration else default_camera()
        obs = check_observable(config, poses, camera)
        worst = max(obs.std, key=lambda n: obs.std[n] / _magnitude(n))
        console.print(
            f"every parameter observable; the least determined: {worst} "
            f"(predicted std {obs.std[worst]:.3g})"
        )
    n_mirror = sum(p.target == "mirror" for p in poses)
    write_plan(
        out,
        poses,
        kind=kind,
        force=force,
        exposures_s=(spot_exposure, board_exposure),
        width=size[0],
        height=size[1],
    )
    console.print(
        f"wrote {out}: {len(poses)} poses ({len(poses) - n_mirror} board, {n_mirror} mirror)",
        markup=False,
    )


def _magnitude(name: str) -> float:
    from gonio.rig.calibration import PARAMETERS

    return PARAMETERS[name].magnitude


def _as_nominal_readings(boards, spots, session_rig, nominal):
    """The observations' joints as the nominal rig reads them: a session captured with
    another ``zero_deg`` (e.g. an earlier calibration) journals its own readings."""
    import dataclasses
    import math

    shift = {}
    for s in session_rig.servos:
        n = nominal.servo_for(s.joint)
        shift[s.joint] = math.radians(s.direction * (s.zero_deg - n.zero_deg) / s.gear_ratio)
    if not any(shift.values()):
        return boards, spots

    def moved(o):
        joints = {j: float(q) + shift.get(j, 0.0) for j, q in o.joints.items()}
        return dataclasses.replace(o, joints=joints)

    return [moved(b) for b in boards], [moved(s) for s in spots]


#: Default half-size of the calibration mirror (a 50 mm square, the sample's size), m.
MIRROR_HALF_SIZE_M = 0.025
#: A spot whose centroid box (the blob and the rim the centroid sums) is unknown is not
#: used when its reflection point is closer than this to the mirror's edge, m: a lab
#: light's image on the mirror is up to ~5 mm wide (twice that at 60 deg incidence).
MIRROR_MARGIN_M = 0.007
#: A spot whose centroid box, met with the mirror, comes closer than this to the edge is
#: not used, m: where the edge cuts the summed pixels the centroid moves by pixels; the
#: guard covers the board pose's error (~0.1 mm) and a bevelled mirror edge.
MIRROR_EDGE_GUARD_M = 0.0005


def _on_mirror(pixels: np.ndarray, K, dist, R, centre) -> np.ndarray | None:
    """Where the pixels' rays (n, 2) meet the mirror plane z = 0, (n, 2) m; None when a
    ray runs parallel to it or meets it behind the camera."""
    import cv2

    xy = cv2.undistortPoints(np.asarray(pixels, float).reshape(-1, 1, 2), K, dist)[:, 0]
    rays = np.column_stack([xy, np.ones(len(xy))]) @ R  # R.T @ ray, row-wise
    if np.any(np.abs(rays[:, 2]) <= 1e-12):
        return None
    s = -centre[2] / rays[:, 2]
    if np.any(s <= 0):
        return None
    return (centre[None, :] + s[:, None] * rays)[:, :2]


def mirror_footprints(boards, spots, camera) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """Where each spot's light is reflected, and where its centroid box lies on the mirror.

    The spot's pixel ray is met with the mirror plane (z = 0 of the sample frame), the
    camera posed by ``cv2.solvePnP`` (with the camera calibration) on the board seen around
    the mirror in the same view.  Spots without a board view of the same label are left
    out.

    Returns
    -------
    dict
        label -> (reflection point (2,) m, the centroid box's corners on the mirror (4, 2)
        m or None when the spot has no box).
    """
    import cv2

    K, dist = np.asarray(camera.K, float), np.asarray(camera.dist, float)
    by_label = {b.label: b for b in boards}
    out = {}
    for s in spots:
        b = by_label.get(s.label)
        if b is None or len(b.object_points) < 6:
            continue
        ok, rvec, tvec = cv2.solvePnP(
            np.asarray(b.object_points, float), np.asarray(b.image_points, float), K, dist
        )
        if not ok:
            continue
        R = cv2.Rodrigues(rvec)[0]
        centre = -R.T @ tvec.ravel()
        hit = _on_mirror(np.asarray(s.image_point, float)[None, :], K, dist, R, centre)
        if hit is None:
            continue
        corners = None
        if s.box is not None:
            u0, v0, u1, v1 = s.box
            corners = _on_mirror(
                np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]]), K, dist, R, centre
            )
        out[s.label] = (hit[0], corners)
    return out


def reflection_points(boards, spots, camera) -> dict[str, np.ndarray]:
    """Where each spot's light is reflected on the mirror, m (label -> (2,)); see
    :func:`mirror_footprints`."""
    return {k: hit for k, (hit, _c) in mirror_footprints(boards, spots, camera).items()}


def edge_problems(boards, spots, camera, half_size: tuple[float, float]) -> dict[str, str]:
    """label -> why, for the spots the mirror's edge may cut (see
    :data:`MIRROR_EDGE_GUARD_M`, :data:`MIRROR_MARGIN_M`)."""
    hx, hy = half_size
    out = {}
    for label, (h, corners) in mirror_footprints(boards, spots, camera).items():
        where = f"reflected at ({h[0] * 1e3:.1f}, {h[1] * 1e3:.1f}) mm"
        size = f"(half-size {hx * 1e3:.0f} x {hy * 1e3:.0f} mm)"
        if corners is None:
            if abs(h[0]) > hx - MIRROR_MARGIN_M or abs(h[1]) > hy - MIRROR_MARGIN_M:
                out[label] = (
                    f"{where}, within {MIRROR_MARGIN_M * 1e3:.0f} mm of the mirror's edge "
                    f"{size}, which may cut the light's image"
                )
            continue
        reach = np.abs(corners).max(axis=0)
        if reach[0] > hx - MIRROR_EDGE_GUARD_M or reach[1] > hy - MIRROR_EDGE_GUARD_M:
            out[label] = (
                f"{where}; the pixels its centroid sums reach ({reach[0] * 1e3:.1f}, "
                f"{reach[1] * 1e3:.1f}) mm, within {MIRROR_EDGE_GUARD_M * 1e3:.1f} mm of the "
                f"mirror's edge {size}, which cuts or may cut the light's image"
            )
    return out


def _mirror_half_size(manifest) -> tuple[float, float]:
    """A simulated session's mirror is its scene's sample rectangle; else the default."""
    sample = (((manifest.get("simulation") or {}).get("scene")) or {}).get("sample") or {}
    try:
        return float(sample["width"]) / 2, float(sample["height"]) / 2
    except (KeyError, TypeError, ValueError):
        return MIRROR_HALF_SIZE_M, MIRROR_HALF_SIZE_M


def _plot_residuals(path: Path, cal) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gonio.atomic import atomic_path

    fig, ax = plt.subplots(figsize=(10, 4))
    for kind, colour in (("board", "tab:blue"), ("spot", "tab:orange")):
        vs = [(i, v) for i, v in enumerate(cal.views) if v.kind == kind]
        if vs:
            ax.bar([i for i, _ in vs], [v.rms_px for _, v in vs], color=colour, label=kind)
    ax.set_xlabel("view")
    ax.set_ylabel("residual RMS (px)")
    ax.legend()
    ax.set_title("rig calibration residuals per view")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


@click.command("rig")
@click.argument("session_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option(
    "--rig",
    "rig_path",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    required=True,
    help="The nominal rig configuration the session was captured with.",
)
@click.option(
    "--camera-calibration",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    required=True,
    help="The camera calibration (`gonio calibrate camera --out`).",
)
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True)
@click.option(
    "--board-config",
    type=click.Path(dir_okay=False, exists=True, path_type=Path),
    help="A TOML with the holder's [board] (default: the session's scene or reduction.toml, "
    "else the default board).",
)
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path), help="Residual plot PNG.")
@click.option("--force", is_flag=True, help="Overwrite existing --out / --plot files.")
def rig_cmd(
    session_dir: Path,
    rig_path: Path,
    camera_calibration: Path,
    out: Path,
    board_config: Path | None,
    plot: Path | None,
    force: bool,
) -> None:
    """Calibrate the rig from a calibration session; write the calibrated configuration."""
    from rich.console import Console
    from rich.markup import escape as esc
    from rich.table import Table

    from gonio.app.calibrate_cli import _board_from
    from gonio.capture.camera_calibration import camera_digest, camera_identity
    from gonio.capture.manifest import load_manifest
    from gonio.capture.rig_views import calibration_observations
    from gonio.capture.session_dir import refuse_session_file
    from gonio.capture.sessions import _diff_keys
    from gonio.cli import distinct_outputs
    from gonio.rig.calibration import NOT_OBSERVABLE, calibrate_rig, write_calibrated_rig
    from gonio.rig.calibration_record import (
        CalibrationError,
        check_camera_digest,
        check_rig_digest,
        rig_digest,
    )
    from gonio.rig.config import load_rig_config, rig_config_from_dict

    console = Console()
    distinct_outputs(("--out", out), ("--plot", plot))
    refuse_session_file("--out", out, session_dir)
    refuse_session_file("--plot", plot, session_dir)
    for p in (out, plot):
        if p is not None and p.exists() and not force:
            raise CalibrationError(f"{p} exists; not overwritten (use --force to replace it)")
    nominal = load_rig_config(rig_path)
    manifest = load_manifest(session_dir)
    session_rig = rig_config_from_dict(manifest["rig"], f"{session_dir}/manifest.json: rig")
    check_rig_digest(rig_digest(nominal), rig_digest(session_rig), what=f"session {session_dir}")
    # the digest covers the servos only: a --rig of another geometry calibrated the
    # session against the wrong drawing and recorded its digest as the nominal's
    a = nominal.model_dump(mode="json", exclude={"bus", "name"})
    b = session_rig.model_dump(mode="json", exclude={"bus", "name"})
    if a != b:
        raise CalibrationError(
            f"--rig {rig_path} differs from the rig session {session_dir} ran with "
            f"({_diff_keys(a, b)}): calibrate against the nominal rig.toml the session used"
        )
    camera = camera_prior(camera_calibration)
    # The session's image size: a simulated session records it; a real camera's identity
    # carries its resolution setting, else the calibration's size stands in for it.
    sim = manifest.get("simulation") or {}
    size = (
        (sim["width"], sim["height"])
        if sim.get("width") and sim.get("height")
        else (camera.width, camera.height)
    )
    session_digest = camera_digest(camera_identity(manifest["camera"], size))
    check_camera_digest(camera.digest, session_digest, source=str(camera_calibration))

    board, board_source = _board_from(board_config, session_dir)
    # escaped: sources, labels, reasons and paths may hold brackets (rich markup)
    console.print(f"board: {board_source}", markup=False)
    boards, spots, problems = calibration_observations(session_dir, board)
    boards, spots = _as_nominal_readings(boards, spots, session_rig, nominal)
    for p in problems:
        console.print(f"[yellow]note[/]: {esc(p.label)}: no {esc(p.what)}: {esc(p.reason)}")
    hx, hy = _mirror_half_size(manifest)
    near_edge = edge_problems(boards, spots, camera, (hx, hy))
    for label, why in near_edge.items():
        console.print(f"[yellow]note[/]: {esc(label)}: spot not used: {esc(why)}")
    spots = [s for s in spots if s.label not in near_edge]
    if not boards:
        raise CalibrationError(f"{session_dir}: the board was not found in any frame")
    cal = calibrate_rig(nominal, boards, spots, camera, camera_digest=session_digest)

    table = Table(title=f"rig calibration ({cal.solve_time_s:.1f} s)")
    for col in ("parameter", "value", "std", "unit"):
        table.add_column(col, justify="left" if col == "parameter" else "right")
    for i, name in enumerate(cal.names):
        unit = cal.record.parameters.get(name) or cal.record.intrinsics.get(name)
        std = cal.std[i]
        table.add_row(
            name,
            f"{cal.values[i]:.6g}",
            f"{std:.3g}" if math.isfinite(std) else "inf",
            unit.unit if unit else "",
        )
    console.print(table)
    for kind, rms in cal.rms_px.items():
        views = [v for v in cal.views if v.kind == kind]
        worst = max(views, key=lambda v: v.max_px)
        console.print(
            f"{kind}: {len(views)} views, RMS {rms:.3f} px (sigma {cal.sigma_px[kind]:.3f} px), "
            f"largest {worst.max_px:.3f} px in {worst.label}",
            markup=False,
        )
    for label, why in cal.rejected.items():
        console.print(f"[yellow]rejected[/] {esc(label)}: {esc(why)}")
    console.print("not observable (kept nominal):")
    for name, why in NOT_OBSERVABLE.items():
        console.print(f"  {name}: {why}", markup=False)
    # the calibration first: a refused (ill-conditioned) one writes nothing, plot included
    write_calibrated_rig(out, cal, force=force)
    console.print(f"wrote {out}", markup=False)
    if plot is not None:
        _plot_residuals(plot, cal)
