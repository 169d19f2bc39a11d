"""The aperture bias of a region: its BRDF is a mean over its pixels, reported at one direction.

A region's value is the mean of ``f`` over the points ``x`` of the sample its pixels see,
while its direction is that of their centroid ``x0``.  To second order in the offset
``d = x - x0`` (a point on the sample plane, m)

``<f(x)> = f(x0) + 1/2 tr(H S)``,  ``H = d^2 f / dx^2``,  ``S = <d d^T>``

(the first-order term vanishes: ``<d> = 0`` at the centroid).  On a glossy lobe the bias
has one sign over a whole flank and no zero mean: near the peak (concave) every region
comes out low, on the tails (convex) high.  It grows where a step on the sample turns the
half vector most: at grazing near-specular poses ``|wi + wo| = 2 cos(theta_d)`` is small,
and a step across the plane of incidence, which turns ``wi`` and ``wo`` in azimuth
together, tilts ``h`` by ``(1/d_light + 1/d_camera) / (2 cos theta_d)`` per metre.  On the
realistic world (alpha = 0.2, 6 x 6 regions of 8 mm, theta_i = 70 deg, theta_o = 80 deg)
``h`` spans 2.5 deg out of the plane within one region and the in-plane regions came out
0.7 % low (12 sigma of their noise), the off-plane ones 0.2 % high: a bias the budget had
no term for, shared by the near-specular samples of every pose (the fit's ks came out
0.25 % low, 3.8 of its sigma).

``H`` is measured, not modelled (capture has no BRDF model): the regions of one pose sample
``f`` over the sample at a spacing of one region, and a weighted quadratic of ``log f`` in
the sample position over each region's nearest neighbours (LOESS of degree 2, as
:func:`gonio.capture.budget.local_log_gradient` does over directions) gives the log
gradient ``g`` and Hessian ``H_l``; ``H = f (H_l + g g^T)``.  ``log f`` because a lobe is
closer to a Gaussian (a quadratic log) than to a quadratic over three regions.  ``S`` is
the covariance of the region's own pixel positions (exact for the pixel sets the kernel
sums, whatever their trimming).  The correction's noise, propagated from the neighbours'
noise through the fit's linear weights, joins the noise term.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["aperture_bias", "region_moments"]

Array = NDArray[np.float64]
#: regions per local quadratic (a region and its eight neighbours on the grid)
NEIGHBOURS = 9
#: the quadratic in two position coordinates has six coefficients
_N_COEF = 6
#: The largest condition number of a neighbourhood's normal matrix (positions scaled to
#: its radius) whose curvature is used; above it the region is left as measured.
MAX_CONDITION = 3e4


def region_moments(
    label: NDArray[np.int64], x: Array, y: Array, n_regions: int
) -> tuple[Array, Array]:
    """Centroid and covariance of each region's pixel positions on the sample plane.

    Parameters
    ----------
    label
        (h, w) region index of each pixel, -1 outside every region.
    x, y
        (h, w) sample-frame coordinates (m) of the point each pixel's ray meets the plane
        at (NaN off the plane).
    n_regions
        Number of regions.

    Returns
    -------
    centroid : ndarray
        (n, 2) mean position, m (NaN for a region without pixels).
    covariance : ndarray
        (n, 2, 2) covariance of the positions about it, m^2 (NaN without pixels).
    """
    lab = np.asarray(label)
    xs, ys = np.asarray(x, float), np.asarray(y, float)
    inside = (lab >= 0) & np.isfinite(xs) & np.isfinite(ys)
    lab, xs, ys = lab[inside], xs[inside], ys[inside]
    cnt = np.bincount(lab, minlength=n_regions).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        mx = np.bincount(lab, xs, minlength=n_regions) / cnt
        my = np.bincount(lab, ys, minlength=n_regions) / cnt
        # central moments in a second pass: the positions are ~1e-2 m, their spread ~1e-3
        dx, dy = xs - mx[lab], ys - my[lab]
        sxx = np.bincount(lab, dx * dx, minlength=n_regions) / cnt
        sxy = np.bincount(lab, dx * dy, minlength=n_regions) / cnt
        syy = np.bincount(lab, dy * dy, minlength=n_regions) / cnt
    cov = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
    return np.stack([mx, my], -1), cov


def aperture_bias(
    centroid: Array,
    covariance: Array,
    brdf: Array,
    brdf_std: Array,
    usable: NDArray[np.bool_],
    *,
    k: int = NEIGHBOURS,
) -> tuple[Array, Array]:
    """Each region's aperture bias ``<f> - f(x0)`` from its pose's neighbouring regions.

    Parameters
    ----------
    centroid
        (n, 2) the regions' pixel centroids on the sample, m (one pose).
    covariance
        (n, 2, 2) their pixel positions' covariance, m^2.
    brdf, brdf_std
        (n, C) measured f_r and its noise std, 1/sr.
    usable
        (n,) regions that may serve as neighbours (unflagged); only those with every
        channel finite and positive are used.
    k
        Neighbours per local quadratic (at least 6).

    Returns
    -------
    bias : ndarray
        (n, C) ``1/2 tr(H S)``, 1/sr: subtract it from ``brdf`` for the value at the
        reported direction; 0 where fewer than ``k`` neighbours (or a neighbourhood that
        does not span both axes) leave the curvature unknown.
    bias_std : ndarray
        (n, C) its std from the neighbours' noise, 1/sr (0 where ``bias`` is 0).
    """
    P = np.asarray(centroid, float)
    S = np.asarray(covariance, float)
    f = np.asarray(brdf, float)
    sd = np.asarray(brdf_std, float)
    n, C = f.shape
    bias = np.zeros((n, C))
    bias_std = np.zeros((n, C))
    ok = (
        np.asarray(usable, bool)
        & np.isfinite(P).all(axis=1)
        & np.isfinite(f).all(axis=1)
        & (f > 0).all(axis=1)
        & np.isfinite(sd).all(axis=1)
    )
    pool = np.flatnonzero(ok)
    kk = min(int(k), len(pool))
    if kk < max(int(k), _N_COEF):
        return bias, bias_std
    from scipy.spatial import cKDTree

    q = np.flatnonzero(np.isfinite(P).all(axis=1) & np.isfinite(S).all(axis=(1, 2)))
    if not q.size:
        return bias, bias_std
    dist, idx = cKDTree(P[pool]).query(P[q], k=kk)
    nb = pool[idx]  # (Q, k)
    h = dist[:, -1] + 1e-12  # the neighbourhood's radius scales the design (conditioning)
    D = (P[nb] - P[q][:, None, :]) / h[:, None, None]
    u, v = D[..., 0], D[..., 1]
    A = np.stack([np.ones_like(u), u, v, 0.5 * u * u, u * v, 0.5 * v * v], axis=-1)
    AtA = A.transpose(0, 2, 1) @ A
    # A neighbourhood along one line only (a grid of one row) has no 2-D curvature, and
    # one that is nearly so extrapolates it: beside a gap (saturated regions of a glint)
    # the nearest usable regions span two rows and a far one, and the curvature across
    # them came out -7.2 % where the truth was -0.3 % (world 1607, theta_i 75 / theta_o
    # 80).  Such designs had condition numbers 2e5-5e6, the regions of a full grid 80-3e3.
    cond = np.linalg.cond(AtA)
    good = np.isfinite(cond) & (cond < MAX_CONDITION)
    W = np.zeros((len(q), _N_COEF, kk))  # coefficients = W @ log f
    W[good] = np.linalg.solve(AtA[good], A[good].transpose(0, 2, 1))
    logf = np.log(f[nb])  # (Q, k, C)
    beta = W @ logf  # (Q, 6, C)
    g = beta[:, 1:3, :] / h[:, None, None]  # d log f / dx, per metre
    Hl = np.empty((len(q), 2, 2, C))
    Hl[:, 0, 0] = beta[:, 3]
    Hl[:, 0, 1] = Hl[:, 1, 0] = beta[:, 4]
    Hl[:, 1, 1] = beta[:, 5]
    Hl /= (h**2)[:, None, None, None]
    Sq = S[q]
    # 1/2 tr((H_l + g g^T) S): relative bias
    rel = 0.5 * (np.einsum("qabc,qba->qc", Hl, Sq) + np.einsum("qac,qab,qbc->qc", g, Sq, g))
    # its noise, to first order: d rel = 1/2 tr(dH_l S) + g^T S dg, both linear in the
    # neighbours' log f (the rows of W), d log f = sigma / f
    r_h = (
        0.5
        * (
            W[:, 3] * Sq[:, 0, 0, None]
            + 2.0 * W[:, 4] * Sq[:, 0, 1, None]
            + W[:, 5] * Sq[:, 1, 1, None]
        )
        / (h**2)[:, None]
    )  # (Q, k)
    r = r_h[:, :, None] + np.einsum("qac,qab,qbk->qkc", g, Sq, W[:, 1:3] / h[:, None, None])
    rel_sd = np.sqrt(np.einsum("qkc,qkc->qc", r**2, (sd[nb] / f[nb]) ** 2))
    rel = np.where(good[:, None], rel, 0.0)
    rel_sd = np.where(good[:, None], rel_sd, 0.0)
    fq = np.where(np.isfinite(f[q]), f[q], 0.0)
    bias[q] = rel * fq
    bias_std[q] = rel_sd * np.abs(fq)
    return bias, bias_std
