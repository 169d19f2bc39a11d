"""The Markdown report of ``gonio demo``: tables and PNG plots next to it."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from gonio.atomic import write_text_atomic


def _sample_images(session: Path, out: Path, n: int = 3) -> list[tuple[Path, str]]:
    """Render a few of the session's RAW frames to PNG (rawpy demosaic, for looking only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import rawpy

    from gonio.capture.journal import read_journal

    shots = [
        r
        for r in read_journal(session / "journal.jsonl")
        if r.get("type") == "shot" and r.get("kind") == "sample"
    ]
    if not shots:
        return []
    picks = [shots[int(k)] for k in np.linspace(0, len(shots) - 1, min(n, len(shots)))]
    images = []
    for r in picks:
        with rawpy.imread(str(session / r["file"])) as raw:
            rgb = raw.postprocess(
                half_size=False, use_camera_wb=True, no_auto_bright=False, output_bps=8
            )
        path = out / f"frame_{Path(r['file']).stem}.png"
        plt.imsave(path, rgb)
        wi, wo = np.asarray(r["wi_achieved"]), np.asarray(r["wo_achieved"])
        ti, to = np.degrees(np.arccos(np.clip([wi[2], wo[2]], -1, 1)))
        caption = (
            f"pose {r['pose']}, frame {r['frame']}: theta_i {ti:.1f} deg, "
            f"theta_o {to:.1f} deg, exposure {r['exposure_time'] * 1e3:.2f} ms"
        )
        images.append((path, caption))
    return images


def _calibration_lines(cal: Any, out: Path) -> list[str]:
    """The calibrations beside the fit: residuals, and each estimate against the truth."""
    rms = ", ".join(f"{k} {v:.3f} px" for k, v in cal.rig_rms_px.items())
    lines = [
        "## Calibrations (the simulated rig as built)",
        "",
        f"Camera (`{Path(cal.camera_file).name}`): reprojection RMS {cal.camera_rms_px:.3f} px "
        f"over {cal.camera_views} views ({cal.camera_rejected} rejected). "
        f"Rig (`{Path(cal.rig_file).name}`): residual RMS {rms}. "
        "The session was captured with the calibrated rig and reduced with the calibrated "
        "camera. The truth is the simulator's as-built world, which the controller and the "
        "reduction never read; z = (estimate - truth) / sigma.",
        "",
        "| parameter | estimate | sigma | truth | unit | z |",
        "|---|---|---|---|---|---|",
    ]
    z = cal.z()
    for name, v, s, t, unit in cal.rows:
        lines.append(
            f"| {name} | {v:.6g} | {s:.2g} | {'-' if t is None else f'{t:.6g}'} | {unit} | "
            f"{f'{z[name]:+.2f}' if name in z else '-'} |"
        )
    return [*lines, ""]


def _retention_lines(ret: dict | None) -> list[str]:
    """``reduction.json``'s ``"retention"`` as a Markdown section."""
    if not ret:
        return []

    def pct(f: float | None) -> str:
        return "-" if f is None else f"{f:.1%}"

    src = ", ".join(f"{k} {v}" for k, v in ret.get("geometry_source", {}).items())
    lines = [
        "## Sample retention",
        "",
        f"Region samples kept of those planned, by theta band ({ret['band_by']}): "
        f"**{pct(ret['fraction'])}** up to {ret['up_to_deg']:g} deg "
        f"({ret['kept']} of {ret['planned']}).",
        "",
        "| theta (deg) | planned | kept | retained |",
        "|---|---|---|---|",
    ]
    for b in ret["bands"]:
        lo, hi = b["theta_deg"]
        lines.append(f"| {lo:g}-{hi:g} | {b['planned']} | {b['kept']} | {pct(b['fraction'])} |")
    if src:
        lines += ["", f"Where the kept samples' camera geometry came from: {src}."]
    return [*lines, ""]


def _budget_lines(summary: dict | None) -> list[str]:
    """``reduction.json``'s radiometric calibration and uncertainty budget as Markdown: what
    the session shot to calibrate the light and the sensor, how far the light drifted
    between its reference groups, and the budget's terms, largest first."""
    if not summary or not summary.get("budget"):
        return []
    lines = ["## Radiometric calibration and uncertainty budget", ""]
    rad = summary.get("radiometric") or {}
    groups = rad.get("reference_groups") or []
    shot = [
        f"{rad.get('dark_frames', 0)} dark frames",
        f"{rad.get('flat_frames', 0)} flat frames",
        f"{len(groups)} reference group{'s' if len(groups) != 1 else ''}",
    ]
    lines.append(f"The session shot {', '.join(shot)}.")
    if len(groups) > 1:
        # the light's output between the first and the last group, as the reduction saw it
        first = np.asarray(groups[0]["light_radiance_camera_units"], float)
        last = np.asarray(groups[-1]["light_radiance_camera_units"], float)
        change = ", ".join(f"{c} {v:+.2%}" for c, v in zip("RGB", last / first - 1, strict=True))
        span = (groups[-1]["time"] - groups[0]["time"]) / 60.0
        lines.append(
            f"The light's output changed by {change} over {span:.1f} min of rig time "
            "between the first and the last reference group; the reduction follows it "
            "from group to group."
        )
    for w in [*(summary.get("warnings") or []), *(summary["budget"].get("warnings") or [])]:
        lines += ["", f"Warning: {w}"]
    from gonio.capture.budget import BUDGET_COLUMNS, budget_cells

    lines += ["", f"| {' | '.join(BUDGET_COLUMNS)} |", "|---|---|---|---|"]
    for r in summary["budget"].get("terms", []):
        if r.get("share"):
            lines.append(f"| {' | '.join(budget_cells(r))} |")
    return [*lines, ""]


def write_report(
    out: Path,
    session: Path,
    samples: Any,
    result: Any,
    material: Any,
    red: Any,
    params: dict,
    sigma: dict,
    truth: dict | None,
    rel_error: dict,
    z: dict,
    brdf_err: float,
    seconds: dict,
    frames: int,
    calibration: Any = None,
    *,
    figures: Any = None,
) -> Path:
    """Write ``out/report.md`` and its plots; return the report's path.

    ``calibration`` (a :class:`gonio.app.demo_calibrations.CalibrationSummary`) adds the
    calibrations' residuals and estimates beside the fit (``--world realistic``).
    ``figures`` (a :class:`gonio.figure_worker.FigureWorker`) draws the residual map
    in its process while this one draws the slices and the frames."""
    from gonio.app.demo_figures import residual_map, result_path
    from gonio.figure_worker import FigureWorker
    from gonio.fitting.export import save_json
    from gonio.fitting.plots import plot_slices

    figs = out / "figures"
    figs.mkdir(exist_ok=True)
    worker = figures if figures is not None else FigureWorker(enabled=False)
    resid_job = worker.submit(residual_map, result, str(red.path), str(figs / "residuals.png"))
    slices = plot_slices(result, samples, figs / "slices.png")
    save_json(result, out / "fit.json")
    images = _sample_images(session, figs)
    resid = result_path(resid_job)
    lines = [
        "# gonio demo report",
        "",
        f"Ground truth: `{material.spec}`. Session: `{session.name}/` "
        f"({frames} RAW frames). Samples: `{Path(red.path).relative_to(out)}` "
        f"({red.n_kept} kept of {red.n_samples}).",
        "",
        f"Chosen model: **{result.spec}** "
        f"(cost {result.cost:.6g}, {result.n_samples} samples, "
        f"algorithm path {' -> '.join(result.algorithm)}).",
        "",
        "| parameter | channel | fitted | sigma | truth | rel. error | z |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, v in params.items():
        for c, ch in enumerate("RGB"):
            tr = truth.get(k) if truth else None
            lines.append(
                f"| {k} | {ch} | {v[c]:.5g} | {sigma[k][c]:.2g} | "
                f"{f'{tr[c]:.5g}' if tr else '-'} | "
                f"{f'{rel_error[k][c]:.2%}' if k in rel_error else '-'} | "
                f"{f'{z[k][c]:+.2f}' if k in z else '-'} |"
            )
    lines += [
        "",
        f"Median relative difference between the fitted and the true BRDF at the measured "
        f"directions: **{brdf_err:.2%}**.",
        "",
    ]
    if calibration is not None:
        lines += _calibration_lines(calibration, out)
    lines += _retention_lines(red.summary.get("retention") if red.summary else None)
    lines += _budget_lines(red.summary)
    lines += ["## Rejected samples", ""]
    if red.rejected:
        lines += ["| reason | count |", "|---|---|"]
        lines += [f"| {k} | {v} |" for k, v in red.rejected.items()]
    else:
        lines.append("None.")
    lines += ["", "## Time per stage", "", "| stage | seconds |", "|---|---|"]
    lines += [f"| {k} | {v:.1f} |" for k, v in seconds.items()]
    lines += [
        "",
        "## Measured against fitted",
        "",
        f"![slices]({slices.relative_to(out)})",
        "",
        f"![residuals]({resid.relative_to(out)})",
        "",
    ]
    if red.plot is not None:
        lines += [
            "## Samples over the angle domain",
            "",
            # the name the session shows (a link into its output set), not the set's
            # folder, which the next reduction of the session replaces
            f"![samples]({Path(os.path.relpath(red.plot, out)).as_posix()})",
            "",
        ]
    if images:
        lines += ["## What the camera saw", ""]
        for path, caption in images:
            lines += [f"![{caption}]({path.relative_to(out)})", "", f"*{caption}*", ""]
    report = out / "report.md"
    write_text_atomic(report, "\n".join(lines) + "\n")
    return report
