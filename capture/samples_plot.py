"""The reduction's plot: where a session's samples lie in the angle domain (``samples.png``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gonio.atomic import atomic_path

if TYPE_CHECKING:
    from gonio.dataset import BRDFSamples

__all__ = ["plot_samples"]


def plot_samples(samples: BRDFSamples, path: str | os.PathLike) -> Path:
    """Plot samples over the angle domain into a PNG file, atomically.

    Left: theta_i against theta_o (deg), coloured by log10 of the G channel's BRDF
    (1/sr); right: the directions projected on the unit disk.  Rejected samples are
    crosses.

    Returns
    -------
    Path
        The written file.
    """
    path = Path(path)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ang = samples.angles()
    ok = samples.valid
    g = samples.brdf[:, 1 if samples.n_channels > 1 else 0]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    ax = axes[0]
    sc = ax.scatter(
        np.degrees(ang["theta_i"][ok]),
        np.degrees(ang["theta_o"][ok]),
        c=np.log10(np.clip(g[ok], 1e-6, None)),
        s=14,
        cmap="viridis",
    )
    ax.scatter(
        np.degrees(ang["theta_i"][~ok]),
        np.degrees(ang["theta_o"][~ok]),
        marker="x",
        c="red",
        s=18,
        label=f"rejected ({int((~ok).sum())})",
    )
    ax.set_xlabel("theta_i (deg)")
    ax.set_ylabel("theta_o (deg)")
    ax.set_title(f"{int(ok.sum())} samples kept")
    fig.colorbar(sc, ax=ax, label="log10 f_r (G channel, 1/sr)")
    if (~ok).any():
        ax.legend(loc="upper left")
    ax = axes[1]
    for sel, style in (
        (ok, dict(c="tab:blue", s=10, label="wo")),
        (ok, dict(c="tab:orange", s=10, label="wi")),
    ):
        w = samples.wo if style["label"] == "wo" else samples.wi
        ax.scatter(w[sel, 0], w[sel, 1], **style)
    ax.add_patch(plt.Circle((0, 0), 1.0, fill=False, color="grey"))
    ax.set_aspect("equal")
    ax.set_xlim(-1.05, 1.05)
    ax.set_ylim(-1.05, 1.05)
    ax.set_xlabel("x (sample frame)")
    ax.set_ylabel("y")
    ax.set_title("directions seen from above")
    ax.legend(loc="upper right")
    fig.tight_layout()
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=90, format="png")
    finally:
        plt.close(fig)
    return path
