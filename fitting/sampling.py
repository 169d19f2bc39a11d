"""Turn a BRDF (a measured file or a bound model) into samples on a grid of directions.

Used by ``gonio fit FILE.bsdf``: a tabulated BRDF has no samples of its own, so it is
evaluated on a regular grid: incidence angles ``theta_i`` at azimuth 0 (isotropic
materials), outgoing directions on a (theta_o, phi_o) grid over the hemisphere.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gonio.dataset import BRDFSamples

__all__ = ["direction_grid", "sample_brdf"]


def direction_grid(
    theta_i_deg: tuple[float, ...] = (0, 10, 20, 30, 40, 50, 60, 70, 80),
    n_theta_o: int = 18,
    n_phi_o: int = 36,
    max_theta_o_deg: float = 85.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Incident and outgoing unit directions (N, 3) of a regular measurement grid.

    Parameters
    ----------
    theta_i_deg
        Incidence angles in degrees (azimuth 0).
    n_theta_o, n_phi_o
        Outgoing polar (from 0 to ``max_theta_o_deg``, cell centres) and azimuth steps.
    max_theta_o_deg
        Largest outgoing polar angle, degrees.
    """
    ti = np.radians(np.asarray(theta_i_deg, dtype=np.float64))
    to = np.radians(max_theta_o_deg) * (np.arange(n_theta_o) + 0.5) / n_theta_o
    po = 2 * np.pi * np.arange(n_phi_o) / n_phi_o
    TI, TO, PO = np.meshgrid(ti, to, po, indexing="ij")
    wi = np.stack([np.sin(TI), np.zeros_like(TI), np.cos(TI)], axis=-1).reshape(-1, 3)
    wo = np.stack([np.sin(TO) * np.cos(PO), np.sin(TO) * np.sin(PO), np.cos(TO)], axis=-1)
    return wi, wo.reshape(-1, 3)


def sample_brdf(brdf: Any, source: str = "", **grid: Any) -> BRDFSamples:
    """Evaluate ``brdf.eval(wi, wo) -> (N, 3)`` on :func:`direction_grid` and wrap it.

    The samples have no sigmas (``brdf_std`` NaN, so the fit uses ``cosine_l2``), and
    ``attrs["effective_samples"]`` is a tenth of the sample count: neighbouring grid points
    interpolate the same few measured values, which model selection must not count as
    independent evidence.
    """
    wi, wo = direction_grid(**grid)
    f = np.asarray(brdf.eval(wi, wo), dtype=np.float64)
    if f.ndim == 1:
        f = f[:, None]
    n = wi.shape[0]
    return BRDFSamples(
        wi=wi,
        wo=wo,
        brdf=f,
        attrs={"source": str(source), "effective_samples": max(n // 10, 1)},
    )
