"""Figures of a fit: how well the fitted model matches the measured samples.

* :func:`plot_slices` - the classic BRDF plot: one panel per incidence angle, measured f_r
  with error bars for the samples near the plane of incidence, and the fitted model as a
  smooth curve along that plane.
* :func:`plot_residual_map` - every sample (in and out of the plane) on a polar map of the
  outgoing hemisphere per incidence angle, coloured by ``(measured - fitted) / sigma``, so
  systematic misfit (a lobe too wide, a missing grazing rise) shows as coloured patches.

matplotlib with the Agg backend (files only, no display needed).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gonio.atomic import atomic_path
from gonio.fitting.result import FitResult

__all__ = [
    "load_matplotlib",
    "plot_residual_map",
    "plot_slices",
    "residual_map_figure",
    "residuals_png",
    "scaled_residuals",
    "slices_figure",
    "slices_png",
]

#: Samples whose outgoing direction lies within this angle of the plane of incidence are
#: drawn in the slices (deg).
IN_PLANE_TOL_DEG = 10.0
#: Below this theta_i (deg) the plane of incidence is undefined: every wo is "in plane".
NORMAL_INCIDENCE_DEG = 1.0
#: Colour limit of the z map: |z| >= 5 is a misfit, whatever its size.
Z_LIMIT = 5.0
#: Colour limit of the log2(measured / fitted) map used when no sample has a sigma.
LOG2_LIMIT = 2.0

_CHANNEL_COLOURS = {"R": "tab:red", "G": "tab:green", "B": "tab:blue"}
_OTHER_COLOURS = ["k", "tab:orange", "tab:purple", "tab:brown", "tab:olive", "tab:cyan"]


def _figure(**kw: Any) -> Any:
    """A matplotlib Figure on an Agg canvas, without pyplot: files only, no figure manager
    to close, and ~0.1 s less import than ``matplotlib.pyplot``."""
    from matplotlib.figure import Figure

    from gonio.fitting.agg_text import TextCachingCanvas  # Agg, text drawn as in mpl 3.10

    fig = Figure(**kw)
    TextCachingCanvas(fig)
    return fig


def load_matplotlib() -> None:
    """Import matplotlib (Agg) now: the ~0.5 s a process pays before its first figure."""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.figure  # noqa: F401

    import gonio.fitting.agg_text  # noqa: F401


def _wrap(text: str, fig: Any) -> str:
    """Wrap a suptitle to the figure's width (about 13 characters per inch at 9 pt)."""
    import textwrap

    return textwrap.fill(text, width=max(40, int(fig.get_figwidth() * 13)))


def _colours(channels: tuple[str, ...]) -> list[str]:
    if len(channels) == 1:
        return ["k"]
    out, k = [], 0
    for name in channels:
        if name.upper() in _CHANNEL_COLOURS:
            out.append(_CHANNEL_COLOURS[name.upper()])
        else:
            out.append(_OTHER_COLOURS[k % len(_OTHER_COLOURS)])
            k += 1
    return out


@dataclass
class _Data:
    """The samples that entered the fit, with their angles (deg) and fitted values."""

    wi: np.ndarray
    wo: np.ndarray
    y: np.ndarray  # measured f_r (N, C), 1/sr
    sigma: np.ndarray  # its std (N, C), NaN when unknown
    f: np.ndarray  # fitted f_r at the same directions (N, C)
    theta_i: np.ndarray  # deg
    theta_o: np.ndarray  # deg
    signed_o: np.ndarray  # deg, + on the mirror side of the normal
    dphi: np.ndarray  # phi_o - phi_i, rad
    off_plane: np.ndarray  # angle of wo from the plane of incidence, deg
    n_hidden: int  # samples not shown (flagged or not used by the fit)


def _data(r: FitResult, samples: Any) -> _Data:
    wi_all = np.asarray(samples.wi, dtype=np.float64)
    n = wi_all.shape[0]
    used = np.asarray(r.used, dtype=bool).reshape(-1)
    if used.shape[0] != n:
        raise ValueError(f"the fit used a mask of {used.shape[0]} samples, samples has {n}")
    valid = getattr(samples, "valid", None)
    keep = used & (np.asarray(valid, dtype=bool) if valid is not None else True)
    wi = wi_all[keep]
    wo = np.asarray(samples.wo, dtype=np.float64)[keep]
    b = np.asarray(samples.brdf, dtype=np.float64)
    y = (b[:, None] if b.ndim == 1 else b)[keep]
    std = getattr(samples, "brdf_std", None)
    sigma = (
        np.full_like(y, np.nan)
        if std is None
        else np.asarray(std, dtype=np.float64).reshape(b.shape[0], -1)[keep]
    )
    f = r.bind().eval(wi, wo).reshape(y.shape) if len(wi) else np.zeros_like(y)
    ti = np.degrees(np.arccos(np.clip(wi[:, 2], -1.0, 1.0)))
    to = np.degrees(np.arccos(np.clip(wo[:, 2], -1.0, 1.0)))
    dphi = np.arctan2(wo[:, 1], wo[:, 0]) - np.arctan2(wi[:, 1], wi[:, 0])
    signed = np.where(np.cos(dphi) <= 0, to, -to)
    # Angular distance of wo from the plane spanned by the normal and wi: near the normal
    # every azimuth is close to the plane, so an azimuth tolerance alone would drop them.
    off = np.degrees(np.arcsin(np.clip(np.abs(np.sin(np.radians(to)) * np.sin(dphi)), 0, 1)))
    # At normal incidence the plane of incidence is undefined and, for the isotropic models
    # fitted here, every azimuth is equivalent: all such samples belong to the slice.
    off[ti < NORMAL_INCIDENCE_DEG] = 0.0
    return _Data(wi, wo, y, sigma, f, ti, to, signed, dphi, off, int(n - keep.sum()))


def _theta_i_bins(ti: np.ndarray, n_bins: int, gap: float = 2.0, max_span: float = 8.0):
    """Bin index per sample and the list of bins.

    A measurement plan has a few discrete incidence angles (each spread by a degree or two
    over the sample's regions): group samples separated by gaps of more than ``gap`` deg.
    When that does not give a few tight groups, fall back to ``n_bins`` quantile bins.
    """
    if ti.size == 0:
        return np.zeros(0, dtype=int), 0
    s = np.sort(ti)
    cuts = np.nonzero(np.diff(s) > gap)[0]
    starts = np.r_[0, cuts + 1]
    ends = np.r_[cuts, s.size - 1]
    spans = s[ends] - s[starts]
    if len(starts) <= 12 and np.all(spans <= max_span):
        edges = 0.5 * (s[ends[:-1]] + s[starts[1:]])
    else:
        q = np.quantile(ti, np.linspace(0, 1, n_bins + 1))
        edges = np.unique(q[1:-1])
    return np.searchsorted(edges, ti, side="right"), len(edges) + 1


_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")


def _decade_label(value: float, pos: Any = None) -> str:
    """Tick label of a decade, ``10⁻²`` (the locator puts ticks on decades only)."""
    exponent = round(np.log10(value)) if value > 0 else 0
    return "10" + str(int(exponent)).translate(_SUPERSCRIPT)


def _bin_title(ti: np.ndarray) -> str:
    if ti.size == 0:
        return "theta_i ?"
    lo, hi = float(ti.min()), float(ti.max())
    if hi - lo < 1.0:
        return f"theta_i = {np.mean(ti):.1f}°"
    return f"theta_i {lo:.1f}-{hi:.1f}° (curve at {np.mean(ti):.1f}°)"


def _in_plane_curve(bound: Any, theta_i_deg: float, x_deg: np.ndarray) -> np.ndarray:
    """Model f_r (M, C) with wi at ``theta_i_deg`` (azimuth 0) and wo in the plane of
    incidence at signed angles ``x_deg`` (+ towards the mirror direction)."""
    t = np.radians(theta_i_deg)
    x = np.radians(x_deg)
    wi = np.broadcast_to(np.array([np.sin(t), 0.0, np.cos(t)]), (x.size, 3))
    wo = np.stack([-np.sin(x), np.zeros_like(x), np.cos(x)], axis=-1)
    return np.asarray(bound.eval(wi, wo), dtype=np.float64).reshape(x.size, -1)


def scaled_residuals(r: FitResult, samples: Any) -> tuple[np.ndarray, str, float]:
    """Per-sample misfit of a fit, on a scale where systematic errors stand out.

    Parameters
    ----------
    r
        The fit.
    samples
        The :class:`~gonio.dataset.BRDFSamples` it was fitted to.

    Returns
    -------
    values : ndarray, shape (N_shown, C)
        ``(measured - fitted) / brdf_std`` (dimensionless z) when any shown sample has a
        finite positive sigma (NaN for those that do not); otherwise
        ``log2(measured / fitted)`` (NaN where either is not positive).  Rows are the
        samples the fit used that are not flagged, in input order.
    label : str
        What ``values`` is, for a colour-bar label.
    limit : float
        Symmetric colour limit: 5 for z, 2 (a factor of 4) for the log ratio.
    """
    d = _data(r, samples)
    return _scaled(d)


def _scaled(d: _Data) -> tuple[np.ndarray, str, float]:
    ok = np.isfinite(d.sigma) & (d.sigma > 0)
    if ok.any():
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(ok, (d.y - d.f) / np.where(ok, d.sigma, 1.0), np.nan)
        return z, "(measured - fitted) / sigma", Z_LIMIT
    pos = (d.y > 0) & (d.f > 0)
    # over: a fitted value below ~1e-308 (a lobe far from its peak) makes y / f inf, which
    # the colour map clips like any ratio beyond its limit
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lr = np.where(pos, np.log2(np.where(pos, d.y, 1.0) / np.where(pos, d.f, 1.0)), np.nan)
    return lr, "log2(measured / fitted)  (no sigmas)", LOG2_LIMIT


def slices_figure(
    r: FitResult, samples: Any, n_bins: int = 6, tol_deg: float = IN_PLANE_TOL_DEG
) -> Any:
    """The figure drawn by :func:`plot_slices` (a matplotlib ``Figure``, not saved).

    The fitted curves are ``Line2D`` objects with ``gid`` ``"fit:<channel>"``; their x data
    are signed theta_o in degrees, y data f_r in 1/sr.
    """
    d = _data(r, samples)
    C = d.y.shape[1]
    names = tuple(r.channels) if len(r.channels) == C else tuple(f"c{k}" for k in range(C))
    colours = _colours(names)
    bins, nb = _theta_i_bins(d.theta_i, n_bins)
    nb = max(nb, 1)
    cols = min(3, nb)
    rows = int(np.ceil(nb / cols))
    fig = _figure(figsize=(4.6 * cols, 3.5 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    bound = r.bind()
    xg = np.linspace(-89.0, 89.0, 713)
    in_plane = d.off_plane <= tol_deg
    panels = []
    for b in range(nb):
        sel = bins == b
        sel_ip = sel & in_plane
        if not sel.any():
            panels.append(None)
            continue
        ti_b = d.theta_i[sel]
        t_mean = float(np.mean(ti_b))
        curve = _in_plane_curve(bound, t_mean, xg)
        # The bin's samples span a few degrees of theta_i: show the model over that span
        # so a point off the central curve is not mistaken for misfit.
        t_ip = d.theta_i[sel_ip] if sel_ip.any() else ti_b
        band = None
        if t_ip.max() - t_ip.min() > 0.5:
            stack = np.stack(
                [_in_plane_curve(bound, t, xg) for t in np.linspace(t_ip.min(), t_ip.max(), 5)]
            )
            band = (stack.min(axis=0), stack.max(axis=0))
        ys = d.y[sel_ip]
        positive = np.concatenate([curve[curve > 0], ys[ys > 0]])
        panels.append((sel, sel_ip, ti_b, t_mean, curve, band, positive))
    # One y scale for all panels, so they compare at a glance: log when any spans > 30x.
    log = any(
        p is not None and p[6].size and p[6].max() / max(p[6].min(), 1e-300) > 30.0 for p in panels
    )
    for b in range(nb):
        ax = axes[b // cols][b % cols]
        if panels[b] is None:
            ax.text(0.5, 0.5, "no usable samples", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
            continue
        sel, sel_ip, ti_b, t_mean, curve, band, positive = panels[b]
        x = d.signed_o[sel_ip]
        top = float(positive.max()) if positive.size else 1.0
        floor = max(float(positive.min()) if positive.size else top, top * 1e-5) * 0.5
        for c in range(C):
            col = colours[c]
            if band is not None:
                ax.fill_between(xg, band[0][:, c], band[1][:, c], color=col, alpha=0.12, lw=0)
            ax.plot(
                xg, curve[:, c], color=col, lw=1.4, label=f"fit {names[c]}", gid=f"fit:{names[c]}"
            )
            yc = d.y[sel_ip, c]
            sc = d.sigma[sel_ip, c]
            err = np.where(np.isfinite(sc) & (sc > 0), sc, 0.0)
            shown = yc > 0 if log else np.isfinite(yc)
            # Filled: within half the tolerance of the plane; hollow: further off, where a
            # narrow lobe already differs from its in-plane value.
            near = d.off_plane[sel_ip] <= 0.5 * tol_deg
            for part, face, tag in ((near, col, "measured"), (~near, "none", "measured-off")):
                m = shown & part
                if not m.any():
                    continue
                if not np.any(err[m] > 0):
                    # no sigma to show: markers only (an errorbar of zero bars costs ~10x)
                    ax.plot(x[m], yc[m], "o", ms=3.4, mfc=face, mec=col, mew=0.7, alpha=0.75,
                            gid=f"{tag}:{names[c]}")  # fmt: skip
                    continue
                ax.errorbar(
                    x[m],
                    yc[m],
                    yerr=err[m],
                    fmt="o",
                    ms=3.4,
                    mfc=face,
                    mec=col,
                    mew=0.7,
                    ecolor=col,
                    elinewidth=0.8,
                    alpha=0.75,
                    gid=f"{tag}:{names[c]}",
                )
            if log and (~shown).any():
                # Non-positive measurements cannot sit on a log axis: mark them at its floor.
                ax.plot(x[~shown], np.full((~shown).sum(), floor), "v", color=col, mfc="none", ms=4)
        ax.axvline(t_mean, color="0.4", ls="--", lw=0.8)
        if b == 0:  # named once (and in the legend): a text per panel is drawing time
            ax.text(
                t_mean,
                1.0,
                " mirror",
                color="0.3",
                fontsize=7,
                va="top",
                ha="left",
                transform=ax.get_xaxis_transform(),
            )
        if log and positive.size:
            from matplotlib.ticker import FuncFormatter, LogLocator, NullLocator

            ax.set_yscale("log")
            ax.set_ylim(bottom=floor, top=top * 2.0)
            # decades only: the log axis' minor ticks were half the figure's drawing time
            ax.yaxis.set_major_locator(LogLocator(base=10.0, numticks=12))
            ax.yaxis.set_minor_locator(NullLocator())
            # "10⁻²" in plain text: matplotlib's mathtext labels cost a parser build per
            # process and a layout per label
            ax.yaxis.set_major_formatter(FuncFormatter(_decade_label))
        else:
            ax.set_ylim(bottom=min(0.0, float(np.nanmin(d.y[sel_ip])) if sel_ip.any() else 0.0))
        ax.set_xlim(-90, 90)
        ax.set_xticks(np.arange(-90, 91, 30))
        n_ip, n_all = int(sel_ip.sum()), int(sel.sum())
        normal = " (normal incidence: all azimuths)" if ti_b.max() < NORMAL_INCIDENCE_DEG else ""
        # an explicit y: matplotlib's automatic title position measures every tick label
        ax.set_title(
            f"{_bin_title(ti_b)}\n{n_ip} of {n_all} samples in plane{normal}", fontsize=9, y=1.01
        )
        if not n_ip:
            ax.text(
                0.5,
                0.5,
                f"no samples within {tol_deg:g}° of the plane",
                ha="center",
                va="center",
                transform=ax.transAxes,
                fontsize=8,
                color="0.3",
            )
        # axis labels on the outer panels only, x tick labels on the bottom row only
        # (every panel spans -90..90 deg): text is most of the figure's drawing time
        bottom = b + cols >= nb
        if bottom:
            ax.set_xlabel("signed theta_o (deg, + = mirror side)", fontsize=8)
        else:
            ax.tick_params(labelbottom=False)
        if b % cols == 0:
            ax.set_ylabel("f_r (1/sr)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.25, lw=0.5)
    for b in range(nb, rows * cols):
        axes[b // cols][b % cols].set_axis_off()
    ax0 = axes[0][0]
    handles, _ = ax0.get_legend_handles_labels()
    if handles:
        from matplotlib.lines import Line2D

        handles += [
            Line2D([], [], ls="--", color="0.4", lw=0.8, label="mirror direction"),
            Line2D(
                [],
                [],
                ls="none",
                marker="o",
                color="0.4",
                ms=4,
                label=f"measured, <= {0.5 * tol_deg:g}° off plane",
            ),
            Line2D(
                [],
                [],
                ls="none",
                marker="o",
                mfc="none",
                color="0.4",
                ms=4,
                label=f"measured, <= {tol_deg:g}° off plane",
            ),
        ]
        ax0.legend(handles=handles, fontsize=6.5, loc="upper left")
    hidden = f" {d.n_hidden} flagged/unused samples not shown." if d.n_hidden else ""
    text = (
        f"{r.model}: measured f_r (dots; bars +-1 sigma where known) within {tol_deg:g}° of "
        f"the plane of incidence vs the fitted model along that plane (curve; band = model "
        f"over the bin's theta_i range).{hidden} All samples, out-of-plane too: "
        "see residuals.png."
    )
    W, H = fig.get_figwidth(), fig.get_figheight()
    title = fig.suptitle(_wrap(text, fig), fontsize=9, y=1 - 0.08 / H, va="top")
    # fixed margins in inches (tight_layout measured every tick label: ~1/3 of the cost)
    head = 0.25 + 0.16 * (title.get_text().count("\n") + 1)
    fig.subplots_adjust(
        left=0.75 / W, right=1 - 0.15 / W, bottom=0.5 / H, top=1 - (head + 0.45) / H,
        wspace=0.75 / 4.6 * 1.6, hspace=0.95 / 3.5 * 1.6,
    )  # fmt: skip
    return fig


def plot_slices(r: FitResult, samples: Any, path: str | os.PathLike, n_bins: int = 6) -> Path:
    """Measured and fitted f_r in the plane of incidence, one panel per incidence angle.

    Parameters
    ----------
    r
        The fit.
    samples
        The :class:`~gonio.dataset.BRDFSamples` it was fitted to.
    path
        PNG file to write.
    n_bins
        Number of theta_i bins when the samples' incidence angles are not a few discrete
        values (a plan's ``theta_i_deg`` list gives one panel per value).

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    Points: samples within 10° of the plane of incidence, f_r (1/sr) with one-sigma error
    bars from ``brdf_std`` (none where it is NaN), per channel.  Curve: the fitted model
    evaluated along the plane at the bin's mean theta_i, x = signed theta_o in degrees
    (positive on the mirror side; the dashed line marks the mirror direction); the shaded
    band is the model over the bin's theta_i spread.  Log y axis when the values span more
    than a factor of 30.  Flagged samples and samples the fit did not use are not drawn.
    """
    fig = slices_figure(r, samples, n_bins=n_bins)
    return _save(fig, path, dpi=SLICES_DPI)


#: dpi of the two figures.
SLICES_DPI = 110
RESIDUALS_DPI = 90


def slices_png(r: FitResult, samples: Any, n_bins: int = 6) -> bytes:
    """The PNG file :func:`plot_slices` writes, as bytes (for a process that does not own
    the output folder: :mod:`gonio.figure_worker`)."""
    return _png(slices_figure(r, samples, n_bins=n_bins), SLICES_DPI)


def residuals_png(r: FitResult, samples: Any) -> bytes:
    """The PNG file :func:`plot_residual_map` writes, as bytes (for
    :mod:`gonio.figure_worker`)."""
    return _png(residual_map_figure(r, samples), RESIDUALS_DPI)


def _png(fig: Any, dpi: int) -> bytes:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png", **_savefig_kwargs("png"))
    return buf.getvalue()


def _savefig_kwargs(fmt: str) -> dict[str, Any]:
    # zlib level 1: a third of the encoding time of the default 6, files ~1.3x larger
    return {"pil_kwargs": {"compress_level": 1}} if fmt == "png" else {}


def _save(fig: Any, path: str | os.PathLike, dpi: int) -> Path:
    """Write a figure atomically (a killed process leaves no half PNG)."""
    path = Path(path)
    fmt = path.suffix.lstrip(".").lower() or "png"
    with atomic_path(path) as tmp:
        # the temporary name ends in .tmp
        fig.savefig(tmp, dpi=dpi, format=fmt, **_savefig_kwargs(fmt))
    return path


def residual_map_figure(r: FitResult, samples: Any, n_bins: int = 6) -> Any:
    """The figure drawn by :func:`plot_residual_map` (a matplotlib ``Figure``, not saved).

    One axes per channel holds the polar maps of all theta_i bins side by side (bin ``b``
    centred at x = ``b * pitch``): one scatter per channel instead of one axes per panel,
    which is what the figure's cost was (layout and ticks of C x bins axes).
    """
    d = _data(r, samples)
    vals, label, lim = _scaled(d)
    C = d.y.shape[1]
    names = tuple(r.channels) if len(r.channels) == C else tuple(f"c{k}" for k in range(C))
    bins, nb = _theta_i_bins(d.theta_i, n_bins)
    nb = max(nb, 1)
    size = 2.5
    fig = _figure(figsize=(size * nb + 1.6, size * C + 1.5))
    # Polar map of wo, x towards the mirror direction: (theta_o cos, theta_o sin) in deg.
    px = -d.theta_o * np.cos(d.dphi)
    py = d.theta_o * np.sin(d.dphi)
    # Zoom to the measured part of the hemisphere (a plan may stop at theta_o = 50 deg).
    extent = float(min(92.0, (np.max(d.theta_o) if d.theta_o.size else 90.0) + 8.0))
    pitch = 2.0 * extent * 1.08
    ring = np.linspace(0, 2 * np.pi, 181)
    # rings at 30/60/90 deg and the plane of incidence, every panel, NaN-separated: one line
    guide_x, guide_y = [], []
    for b in range(nb):
        for rad in (30, 60, 90):
            guide_x += [b * pitch + rad * np.cos(ring), [np.nan]]
            guide_y += [rad * np.sin(ring), [np.nan]]
        guide_x += [[b * pitch - extent, b * pitch + extent, np.nan]]
        guide_y += [[0.0, 0.0, np.nan]]
    gx, gy = np.concatenate(guide_x), np.concatenate(guide_y)
    off = bins * pitch  # x offset of every sample's panel
    counts = np.bincount(bins, minlength=nb) if bins.size else np.zeros(nb, dtype=int)
    ms_bin = np.clip(2500.0 / np.maximum(counts, 1), 6.0, 60.0)
    # one marker size for all the panels when the bins are equal (a grid): a scalar size
    # draws the scatter ~2x faster than a per-point array
    sizes = ms_bin[bins] if bins.size else ms_bin[:0]
    if sizes.size and np.all(sizes == sizes[0]):
        sizes = np.full(1, sizes[0])
    left, right, bottom, top = 0.9, 1.3, 0.55, 1.0  # inches of margin
    W, H = fig.get_figwidth(), fig.get_figheight()
    row_h = (H - bottom - top) / C
    mappable = None
    axes = []
    for c in range(C):
        ax = fig.add_axes(
            (left / W, (bottom + (C - 1 - c) * row_h) / H, (W - left - right) / W, 0.8 * row_h / H)
        )
        axes.append(ax)
        ax.plot(gx, gy, color="0.8", lw=0.5, zorder=0)
        ax.set_xlim(-extent, (nb - 1) * pitch + extent)
        ax.set_ylim(-extent, extent)
        ax.set_aspect("equal")
        # no ticks: the rings (labelled in the first panel) give theta_o; ticks and their
        # labels were a third of the figure's drawing time
        ax.set_xticks([])
        ax.set_yticks([])
        for rad in (30, 60, 90):
            if rad < extent:
                ax.text(rad * 0.7071, -rad * 0.7071, f"{rad}°", fontsize=6, color="0.2",
                        ha="left", va="top", zorder=5)  # fmt: skip
        ax.set_ylabel(f"channel {names[c]}", fontsize=8)
        v = vals[:, c]
        fin = np.isfinite(v)
        if (~fin).any():
            ax.scatter(px[~fin] + off[~fin], py[~fin], s=_sel(sizes, ~fin), c="0.75",
                       marker="x", lw=0.6)  # fmt: skip
        if fin.any():
            mappable = ax.scatter(
                px[fin] + off[fin],
                py[fin],
                s=_sel(sizes, fin),
                c=v[fin],
                cmap="RdBu_r",
                vmin=-lim,
                vmax=lim,
                edgecolors="none",
                rasterized=True,
            )
        means = [float(np.mean(d.theta_i[bins == b])) if counts[b] else np.nan for b in range(nb)]
        ax.plot(np.arange(nb) * pitch + np.nan_to_num(means), np.zeros(nb), "+", color="k",
                ms=7, mew=1.0)  # fmt: skip
        for b in range(nb):
            sel = bins == b
            if not counts[b]:
                ax.text(b * pitch, 0, "no samples", ha="center", va="center", fontsize=7)
                continue
            vb = v[sel]
            fb = np.isfinite(vb)
            summary = ""
            if fb.any():
                if label.startswith("(measured"):
                    summary = f"chi2/n {np.mean(vb[fb] ** 2):.3g}"
                else:
                    summary = f"median |log2| {np.median(np.abs(vb[fb])):.2f}"
            title = f"{names[c]}  {_bin_title(d.theta_i[sel]).split(' (')[0]}\n{summary}"
            ax.text(b * pitch, extent * 1.02, title, ha="center", va="bottom", fontsize=7)
    axes[-1].set_xlabel(
        "one polar map of wo per theta_i: radius theta_o (rings at 30, 60, 90°), "
        "+x = mirror side, y out of the plane of incidence",
        fontsize=7,
    )
    if mappable is not None:
        cax = fig.add_axes(((W - right + 0.35) / W, 0.2, 0.12 / W, 0.6))
        cb = fig.colorbar(mappable, cax=cax, extend="both")
        cb.set_label(label, fontsize=8)
        cb.ax.tick_params(labelsize=7)
    hidden = f" {d.n_hidden} flagged/unused samples not shown." if d.n_hidden else ""
    text = (
        f"{r.model} misfit of every sample over the outgoing hemisphere, per theta_i "
        f"(+ = mirror direction; grey x = no sigma).{hidden}"
    )
    fig.suptitle(_wrap(text, fig), fontsize=9, y=1 - 0.15 / H, va="top")
    return fig


def _sel(sizes: np.ndarray, mask: np.ndarray) -> Any:
    """Marker sizes of the samples in ``mask``: the one shared size, or theirs."""
    return float(sizes[0]) if sizes.size == 1 else sizes[mask]


def plot_residual_map(r: FitResult, samples: Any, path: str | os.PathLike) -> Path:
    """Misfit of every sample, in and out of the plane of incidence, as polar maps of wo.

    Parameters
    ----------
    r
        The fit.
    samples
        The :class:`~gonio.dataset.BRDFSamples` it was fitted to.
    path
        PNG file to write.

    Returns
    -------
    Path
        ``path``.

    Notes
    -----
    One column per incidence-angle bin, one row per channel.  Each sample is a dot at
    (theta_o cos, theta_o sin) of its outgoing direction relative to the plane of incidence
    (degrees; the mirror direction, marked +, lies on the positive x axis), coloured by
    ``(measured - fitted) / sigma`` on a diverging scale centred on 0 with limits +-5: red
    where the model is too low, blue where too high.  Without any sigma (a tabulated file
    sampled on a grid) the colour is ``log2(measured / fitted)``, limits +-2 (a factor 4).
    See :func:`scaled_residuals` for the values.
    """
    fig = residual_map_figure(r, samples)
    return _save(fig, path, dpi=RESIDUALS_DPI)
