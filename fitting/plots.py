"""Figures of a fit: measured against fitted slices per incidence angle, and residual maps.

matplotlib with the Agg backend (files only, no display needed).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from gonio.fitting.result import FitResult

__all__ = ["plot_residual_map", "plot_slices"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _angles(wi: np.ndarray, wo: np.ndarray):
    ti = np.arccos(np.clip(wi[:, 2], -1, 1))
    to = np.arccos(np.clip(wo[:, 2], -1, 1))
    dphi = np.arctan2(wo[:, 1], wo[:, 0]) - np.arctan2(wi[:, 1], wi[:, 0])
    # + on the mirror side of the normal, - on the light's side
    signed = np.where(np.cos(dphi) <= 0, to, -to)
    return ti, signed, dphi


def plot_slices(r: FitResult, samples: Any, path: str | os.PathLike, n_bins: int = 6) -> Path:
    """Measured and fitted ``f_r cos(theta_o)`` against signed theta_o, one panel per theta_i.

    Samples are grouped into ``n_bins`` incidence-angle bins; theta_o is signed positive on
    the mirror side.  Samples near the plane of incidence (|sin dphi| < 0.26) are drawn
    solid, the others faint, so in-plane highlights stand out.
    """
    plt = _plt()
    wi = np.asarray(samples.wi)[r.used]
    wo = np.asarray(samples.wo)[r.used]
    y = np.asarray(samples.brdf)[r.used]
    f = r.bind().eval(wi, wo)
    ti, signed, dphi = _angles(wi, wo)
    edges = np.unique(np.quantile(ti, np.linspace(0, 1, n_bins + 1)))
    nb = max(len(edges) - 1, 1)
    cols = min(3, nb)
    rows = int(np.ceil(nb / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.2 * rows), squeeze=False)
    colours = ["tab:red", "tab:green", "tab:blue"] + ["k"] * 8
    inplane = np.abs(np.sin(dphi)) < 0.26
    for b in range(nb):
        ax = axes[b // cols][b % cols]
        sel = (ti >= edges[b]) & ((ti < edges[b + 1]) if b < nb - 1 else (ti <= edges[b + 1]))
        cos_o = wo[sel, 2]
        ip = inplane[sel]
        line = ip if ip.sum() >= 3 else np.ones_like(ip)  # fitted curve along the plane
        order = np.argsort(signed[sel][line])
        for c, name in enumerate(r.channels):
            col = colours[c]
            ax.scatter(signed[sel][ip], (y[sel, c] * cos_o)[ip], s=6, color=col, alpha=0.8)
            ax.scatter(signed[sel][~ip], (y[sel, c] * cos_o)[~ip], s=3, color=col, alpha=0.15)
            ax.plot(
                signed[sel][line][order],
                (f[sel, c] * cos_o)[line][order],
                lw=0.8,
                color=col,
                alpha=0.8,
                label=f"fit {name}",
            )
        ax.set_title(
            f"theta_i {np.degrees(edges[b]):.0f}-{np.degrees(edges[b + 1]):.0f} deg", fontsize=9
        )
        ax.set_xlabel("signed theta_o (rad, + = mirror side)", fontsize=8)
        ax.set_ylabel("f_r cos theta_o (1/sr)", fontsize=8)
        ax.set_yscale("symlog", linthresh=1e-3)
    for b in range(nb, rows * cols):
        axes[b // cols][b % cols].axis("off")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"{r.model}: measured (dots) vs fitted (lines)", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_residual_map(r: FitResult, samples: Any, path: str | os.PathLike) -> Path:
    """Relative residual ``(fit - measured) / max(measured, 1 % of the peak)`` over
    (theta_h, theta_d), one panel per channel, colour range at the 95th percentile:
    structure in this map is what the model cannot represent."""
    from gonio.radiometry.frames import half_diff_from_directions

    plt = _plt()
    wi = np.asarray(samples.wi)[r.used]
    wo = np.asarray(samples.wo)[r.used]
    y = np.asarray(samples.brdf)[r.used]
    f = r.bind().eval(wi, wo)
    th, _, td, _ = half_diff_from_directions(wi, wo)
    C = len(r.channels)
    fig, axes = plt.subplots(1, C, figsize=(4.0 * C, 3.4), squeeze=False)
    for c in range(C):
        ax = axes[0][c]
        floor = max(0.01 * float(np.max(np.abs(y[:, c]))), 1e-300)
        rel = (f[:, c] - y[:, c]) / np.maximum(np.abs(y[:, c]), floor)
        lim = max(float(np.percentile(np.abs(rel), 95)), 1e-12)
        sc = ax.scatter(
            np.degrees(th), np.degrees(td), c=rel, s=5, cmap="coolwarm", vmin=-lim, vmax=lim
        )
        ax.set_xlabel("theta_h (deg)")
        ax.set_ylabel("theta_d (deg)")
        ax.set_title(f"{r.channels[c]}: (fit - measured) / measured", fontsize=9)
        fig.colorbar(sc, ax=ax)
    fig.suptitle(f"{r.model} residuals ({r.loss})", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
