"""From camera units to BRDF: the light's scale from the reference poses, and a region's
BRDF with its variance.

A Lambertian reference target of reflectance ``rho`` in the sample's place gives the
light's radiance in camera units, ``I = pi / rho * <L_ref(x) / G(x)>`` with ``G`` the
irradiance a unit-radiance light puts on point ``x``, pooled over the regions of every
reference pose; a sample region's BRDF is then ``f = <L(x)> / (I <G(x)>)`` in 1/sr.  The
camera's absolute response cancels (see :mod:`gonio.capture.calibration`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from gonio.capture.raw import CHANNELS
from gonio.errors import ReductionError

if TYPE_CHECKING:
    from gonio.capture.pose_measure import PoseMeasurement
    from gonio.capture.reduction_config import ReductionSetup

__all__ = ["brdf_of", "light_scale"]


def light_scale(
    references: list[PoseMeasurement], setup: ReductionSetup
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The light's radiance in camera units per channel, from the reference poses.

    ``I_c = pi / rho_c * <L_ref / G>``, pooled with inverse-variance weights over every
    unflagged region of every reference pose; the variance includes the reflectance's
    uncertainty.

    Parameters
    ----------
    references
        The measured reference-target poses.
    setup
        Gives the target's reflectance and its uncertainty.

    Returns
    -------
    I, I_var : ndarray
        (3,) light radiance in camera units (DN per exposure factor) and its variance.

    Raises
    ------
    ReductionError
        When no usable reference region exists.
    """
    q, qv = [], []
    for r in references:
        ok = (r.flags == 0)[:, None] & np.isfinite(r.ratio) & np.isfinite(r.ratio_var)
        q.append(np.where(ok, r.ratio, np.nan))
        qv.append(np.where(ok, r.ratio_var, np.nan))
    if not q:
        raise ReductionError(
            "the session has no reference-target frames: the irradiance is unknown"
        )
    Q = np.concatenate(q)
    V = np.concatenate(qv)
    good = np.isfinite(Q)
    if not good.any(axis=0).all():
        missing = [CHANNELS[c] for c in range(len(CHANNELS)) if not good[:, c].any()]
        raise ReductionError(
            f"no usable reference-target region in channel(s) {', '.join(missing)} "
            "(all flagged saturated, underexposed, or without the board)"
        )
    w = np.where(good, 1.0 / np.where(good, V, 1.0), 0.0)
    qm = np.nansum(w * np.nan_to_num(Q), axis=0) / w.sum(0)
    qm_var = 1.0 / w.sum(0)
    rho = setup.reflectance
    I = np.pi * qm / rho
    I_var = I**2 * (qm_var / qm**2 + (setup.reflectance_std / rho) ** 2)
    return I, I_var


def brdf_of(
    m: PoseMeasurement, I: NDArray[np.float64], I_var: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """BRDF, its standard deviation, and the irradiance of each region of a sample pose.

    ``f = <L> / (I <G>)``; ``var f = var<L> / E^2 + f^2 var(I) / I^2`` with ``E = I <G>``.

    Parameters
    ----------
    m
        A measured sample pose.
    I, I_var
        (3,) light radiance in camera units and its variance (:func:`light_scale`).

    Returns
    -------
    f, f_std : ndarray
        (n, 3) BRDF, 1/sr, and its standard deviation.
    E, E_var : ndarray
        (n, 3) irradiance in camera units (times sr) and its variance.
    """
    E = I[None, :] * m.geometry
    with np.errstate(invalid="ignore", divide="ignore"):
        f = m.radiance / E
        var = m.radiance_var / E**2 + f**2 * (I_var / I**2)[None, :]
    return f, np.sqrt(var), E, I_var[None, :] * m.geometry**2
