"""Figures of a BRDF: in-plane slices, a polar heat map, and the directional albedo.

Works for anything with ``eval(wi, wo) -> (..., 3)`` RGB f_r in 1/sr: a bound analytic
model (:meth:`gonio.brdf.base.Model.bind`) or a measured file (``gonio.brdf.load``).
matplotlib with the Agg backend (no display needed).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gonio.atomic import atomic_path

__all__ = ["plot_brdf"]

_COLOURS = ("tab:red", "tab:green", "tab:blue")


def _dir(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    st = np.sin(theta)
    return np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), np.cos(theta)), -1)


def plot_brdf(
    brdf: Any,
    theta_i_deg: Sequence[float],
    out: str | Path,
    *,
    phi_i_deg: float = 0.0,
    title: str | None = None,
    albedo_curve: bool = True,
    log: bool = True,
    replace: bool = True,
) -> Path:
    """Write a figure of ``brdf`` to ``out`` (format from the suffix: png, pdf, svg);
    ``replace=False`` keeps a file another writer put at ``out`` meanwhile
    (``FileExistsError``, :func:`gonio.atomic.atomic_path`).

    Parameters
    ----------
    brdf
        Object with ``eval(wi, wo) -> (..., 3)`` (1/sr) and optionally ``albedo(theta_i)``.
    theta_i_deg
        Incidence angles (deg) of the in-plane slices; the heat map uses the first.
    out
        Output path; written atomically (temporary file, then rename), so an existing file
        is only replaced by a complete figure.
    phi_i_deg
        Incidence azimuth (deg) measured from the sample's +x.
    albedo_curve
        Add a panel with the directional albedo against theta_i (needs ``albedo``).
    log
        Logarithmic f_r axis and colour scale.

    Returns
    -------
    Path
        ``out``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm, Normalize

    out = Path(out)
    phi_i = math.radians(phi_i_deg)
    has_albedo = albedo_curve and hasattr(brdf, "albedo")
    ncols = 3 if has_albedo else 2
    fig = plt.figure(figsize=(5.2 * ncols, 4.6))
    ax_s = fig.add_subplot(1, ncols, 1)

    # In-plane slices: theta_o > 0 on the specular side (phi_o = phi_i + pi).
    t_o = np.radians(np.linspace(-89.9, 89.9, 721))
    floor = np.inf
    for k, ti_deg in enumerate(theta_i_deg):
        wi = _dir(np.asarray(math.radians(ti_deg)), np.asarray(phi_i))
        wo = _dir(np.abs(t_o), np.where(t_o >= 0, phi_i + math.pi, phi_i))
        f = np.asarray(brdf.eval(np.broadcast_to(wi, wo.shape), wo), dtype=float)
        grey = np.allclose(f[..., 0], f[..., 1]) and np.allclose(f[..., 0], f[..., 2])
        style = ("-", "--", ":", "-.")[k % 4]
        if grey:
            ax_s.plot(np.degrees(t_o), f[..., 0], style, color="k", label=f"θi = {ti_deg:g}°")
        else:
            for c in range(3):
                ax_s.plot(
                    np.degrees(t_o),
                    f[..., c],
                    style,
                    color=_COLOURS[c],
                    label=f"θi = {ti_deg:g}°" if c == 0 else None,
                )
        pos = f[f > 0]
        if pos.size:
            floor = min(floor, max(float(pos.min()) * 0.5, float(pos.max()) * 1e-6))
    ax_s.set_xlabel("θo in the plane of incidence (deg, + = specular side)")
    ax_s.set_ylabel("f_r (1/sr)")
    if log:
        ax_s.set_yscale("log")
        if np.isfinite(floor):
            ax_s.set_ylim(bottom=floor)
    ax_s.axvline(0.0, color="0.8", lw=0.8)
    ax_s.legend(fontsize=8)
    ax_s.set_title("in-plane slices")

    # Polar heat map over the outgoing hemisphere for the first incidence angle.
    ax_p = fig.add_subplot(1, ncols, 2, projection="polar")
    ti = math.radians(theta_i_deg[0])
    th = np.radians(np.linspace(0.0, 89.5, 120))
    ph = np.linspace(0.0, 2 * math.pi, 241)
    TH, PH = np.meshgrid(th, ph, indexing="ij")
    wi = _dir(np.asarray(ti), np.asarray(phi_i))
    wo = _dir(TH, PH)
    f = np.asarray(brdf.eval(np.broadcast_to(wi, wo.shape), wo), dtype=float).mean(axis=-1)
    if log and np.any(f > 0):
        vmax = float(f.max())
        norm = LogNorm(vmin=max(vmax * 1e-5, np.min(f[f > 0])), vmax=vmax)
        f = np.maximum(f, norm.vmin)
    else:
        norm = Normalize(vmin=0.0, vmax=float(np.nanmax(f)) if np.any(f > 0) else 1.0)
    mesh = ax_p.pcolormesh(PH, np.degrees(TH), f, norm=norm, shading="auto", cmap="magma")
    ax_p.plot([phi_i + math.pi], [theta_i_deg[0]], "c+", ms=10, label="mirror direction")
    ax_p.plot([phi_i], [theta_i_deg[0]], "wx", ms=8, label="light")
    ax_p.set_ylim(0, 90)
    ax_p.set_rticks([30, 60, 90])
    ax_p.set_yticklabels(["30°", "60°", ""], fontsize=7, color="0.7")
    ax_p.set_title(
        f"f_r over the hemisphere, θi = {theta_i_deg[0]:g}° (mean of RGB)", fontsize=9, pad=14
    )
    ax_p.legend(loc="lower left", fontsize=7, bbox_to_anchor=(-0.15, -0.15))
    fig.colorbar(mesh, ax=ax_p, shrink=0.8, label="f_r (1/sr)")

    if has_albedo:
        ax_a = fig.add_subplot(1, ncols, 3)
        t = np.linspace(0.0, 89.0, 60)
        a = np.asarray(brdf.albedo(np.radians(t)), dtype=float)
        if a.ndim == 1:
            a = a[:, None]
        if np.allclose(a, a[:, :1]):
            ax_a.plot(t, a[:, 0], color="k")
        else:
            for c in range(a.shape[-1]):
                ax_a.plot(t, a[:, c], color=_COLOURS[c % 3])
        ax_a.axhline(1.0, color="tab:red", lw=0.8, ls="--")
        ax_a.set_xlabel("θi (deg)")
        ax_a.set_ylabel("directional albedo")
        ax_a.set_ylim(0, max(1.05, float(np.nanmax(a)) * 1.05))
        ax_a.set_title("energy check (must stay ≤ 1)")

    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.93) if title else None)
    try:
        with atomic_path(out, parents=True, replace=replace) as tmp:
            fig.savefig(tmp, dpi=110, format=out.suffix.lstrip("."))
    finally:
        plt.close(fig)
    return out
