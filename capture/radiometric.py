"""From camera units to BRDF: the light's scale from the reference poses, and a region's
BRDF with its variance.

A Lambertian reference target of reflectance ``rho`` in the sample's place gives the
light's radiance in camera units, ``I = pi / rho * <L_ref(x) / G(x)>`` with ``G`` the
irradiance a unit-radiance light puts on point ``x``, pooled over the regions of every
reference pose; a sample region's BRDF is then ``f = <L(x)> / (I <G(x)>)`` in 1/sr.  The
camera's absolute response cancels (see :mod:`gonio.capture.calibration`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from gonio.capture.raw import CHANNELS
from gonio.errors import ReductionError

if TYPE_CHECKING:
    from gonio.capture.pose_measure import PoseMeasurement
    from gonio.capture.reduction_config import ReductionSetup

__all__ = [
    "RADIOMETRIC_TERMS",
    "DriftModel",
    "LightProfile",
    "ReferenceGroup",
    "brdf_of",
    "dark_offset_std",
    "drift_model",
    "effective_sites",
    "fit_light_profile",
    "flat_rel_std",
    "irradiance_rel_std",
    "light_scale",
    "reference_ratio",
    "region_flat_rel_std",
    "stray_rel_std",
]

#: The radiometric budget terms, relative std of the BRDF, (n, 3) per pose.
RADIOMETRIC_TERMS = ("drift", "flat", "dark", "irradiance", "stray")


def reference_ratio(
    references: list[PoseMeasurement],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Inverse-variance mean of ``L/G`` over every unflagged region of ``references``.

    Returns ``(q, q_var, ok)``: (3,) the mean ratio and its variance (statistics only,
    NaN in a channel without a usable region), and which channels have one.
    """
    q, qv = [], []
    for r in references:
        ok = (r.flags == 0)[:, None] & np.isfinite(r.ratio) & np.isfinite(r.ratio_var)
        q.append(np.where(ok, r.ratio, np.nan))
        qv.append(np.where(ok, r.ratio_var, np.nan))
    Q = np.concatenate(q)
    V = np.concatenate(qv)
    good = np.isfinite(Q)
    w = np.where(good, 1.0 / np.where(good, V, 1.0), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        qm = np.nansum(w * np.nan_to_num(Q), axis=0) / w.sum(0)
        qm_var = 1.0 / w.sum(0)
    return qm, qm_var, good.any(axis=0)


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


# --------------------------------------------------------------------------------------
# Drift: the light's output per reference group, interpolated in rig time


@dataclass
class ReferenceGroup:
    """Consecutive reference poses of one journal segment, and the light they measured.

    Attributes
    ----------
    poses
        Journal pose indices.
    segment
        Journal segment (0 = before the first resume).
    time
        Mean rig time of their shots, s (journal order when the segment has no rig
        time).
    I, I_rel_var
        (3,) light radiance in camera units (``pi / rho <L/G>``) and its relative
        variance from the regions' statistics (type A; the reflectance's is shared).
    """

    poses: list[int]
    segment: int
    time: float
    I: NDArray[np.float64]
    I_rel_var: NDArray[np.float64]


@dataclass
class DriftModel:
    """The light's output over the session: :meth:`at` gives it at a rig time."""

    groups: list[ReferenceGroup]
    pooled: NDArray[np.float64]
    drift_rel_std: float

    def at(self, segment: int, t: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``(I, rel_std)``: (3,) the light's radiance at rig time ``t`` of ``segment``,
        and the drift term's relative standard uncertainty there.

        One group in the segment (or none): the pooled ``I`` of every reference pose and
        the lab's ``drift_rel_std`` (type B).  Several, per channel:

        - between groups ``a`` and ``b`` (``x`` the place of ``t``, 0..1, ``dt`` their
          spacing): the chord corrected by the curvature, ``I = chord - k D dt^2 x (1 -
          x)`` (Newton's quadratic term), ``D`` the mean signed second divided difference
          of the triples of groups that contain the interval, ``k = D^2 / (D^2 + var
          D)`` (the least-squares shrinkage: close groups make ``D`` noisy, and a long
          interval turns its noise into a large error); ``u_B = h / I``, ``h = (S + (1
          - k) sqrt(D^2 + var D)) dt^2 x (1 - x)``, ``S`` the spread of those second
          differences (the curvature's change over the interval), at an end interval
          (one triple) at least ``|D|`` and the distance to the nearest triple's
          curvature extrapolated one step by the trend of the two nearest
          (:func:`_end_curvature`: a warm-up's curvature changes most at the start).
          Two groups: the chord and ``h = |I_b - I_a| x (1 - x)``;
        - after the last group: midway between the nearest interval's line extended and
          the parabola through the nearest triple, ``I = line + k q / 2``, ``h = |q| (1
          - k / 2)``, ``q = D_e (t - t_e) (t - t_n)`` (``D_e`` that triple's second
          difference, its size ``sqrt(D_e^2 + var D_e)`` in ``h``): a warm-up whose
          curvature fades lies between the two (the line alone erred by -0.03 % on
          average over drawn warm-ups, midway -0.005 %); before the first group, where
          the curvature grows going back, the parabola, ``h = |q|``; two groups: the
          line, ``h = |I_n - I_e| |x|``;
        - type A: the estimate is linear in the groups' values, ``I = sum_g w_g I_g``;
          ``u_A = sqrt(sum_g w_g^2 s_g^2) / I``, ``s`` the groups' statistical std.

        ``u = sqrt(u_A^2 + u_B^2)``.  ``h`` is taken as a standard uncertainty, not as
        a rectangular half width: the residual is a smooth function's, of the size of
        its bound, not spread evenly below it (with ``h / sqrt(3)`` the errors of
        simulated warm-ups came out at 1.5 stated sigma).  Why not the chord alone: on a
        warm-up of a 380 s time constant with groups every ~300 s it errs by ~0.1 %,
        the size of the noise of a grazing sample, always of one sign; why not the last
        group's value beyond it: a session's last poses after it saw the light go on
        drifting (world 3104: 0.17 % low after 220 s).
        """
        gs = [g for g in self.groups if g.segment == segment]
        if len(gs) < 2:
            return self.pooled.copy(), np.full(3, self.drift_rel_std)
        gs.sort(key=lambda g: g.time)
        # groups at one time (journal order without rig times cannot give two, but a
        # hand-edited journal can): the first of them, so that no spacing is zero
        gs = [g for k, g in enumerate(gs) if k == 0 or g.time > gs[k - 1].time]
        # a group without a finite value or variance tells nothing (and every group's
        # weight, even 0, would carry its NaN into the sums below)
        gs = [
            g
            for g in gs
            if np.all(np.isfinite(g.I)) and np.all(np.isfinite(g.I_rel_var) & (g.I_rel_var >= 0))
        ]
        if len(gs) < 2:
            return self.pooled.copy(), np.full(3, self.drift_rel_std)
        tk = np.array([g.time for g in gs])
        Ik = np.stack([g.I for g in gs])  # (G, 3)
        sk = np.sqrt(np.stack([g.I_rel_var for g in gs])) * np.abs(Ik)  # (G, 3) abs std
        n = len(tk)
        # The estimate is linear in the groups' values: w (G, 3) its weights, so that its
        # statistical (type A) std is exact, the curvature's noise included.
        w = np.zeros((n, 3))
        if t <= tk[0] or t >= tk[-1]:
            e, nb = (0, 1) if t <= tk[0] else (n - 1, n - 2)
            x = (t - tk[e]) / (tk[nb] - tk[e])
            w[e], w[nb] = 1 - x, x
            if n >= 3:
                dw = _second_difference_weights(tk, 0 if e == 0 else n - 3)
                D, keep, size = _curvature(dw, Ik, sk)
                span = (t - tk[e]) * (t - tk[nb])
                if e == n - 1:
                    # after the last group a warm-up's curvature fades: it lies between
                    # the line and the parabola through the nearest triple; midway
                    w += keep * dw[:, None] * span / 2
                    h = size * abs(span) * (1 - keep / 2)
                else:
                    # before the first group it grows going back: the parabola, and
                    # the truth beyond it by up to its size again
                    w += keep * dw[:, None] * span
                    h = size * abs(span)
            else:
                h = np.abs(Ik[nb] - Ik[e]) * abs(x)
        else:
            b = int(np.searchsorted(tk, t, side="right"))
            a = b - 1
            dt = tk[b] - tk[a]
            x = (t - tk[a]) / dt if dt > 0 else 0.0
            w[a], w[b] = 1 - x, x
            if n == 2:
                h = np.abs(Ik[b] - Ik[a]) * x * (1 - x)
            else:
                ks = [k for k in (a - 1, a) if 0 <= k <= n - 3]
                d = np.stack([_second_difference(tk, Ik, k) for k in ks])
                dw = np.mean([_second_difference_weights(tk, k) for k in ks], axis=0)
                D, keep, size = _curvature(dw, Ik, sk)
                spread = d.max(axis=0) - d.min(axis=0)
                if a == 0 or b == n - 1:
                    # one triple: its curvature's change unknown, so at least its size,
                    # and as far as the trend of the two nearest carries it
                    spread = np.maximum(spread, np.abs(D))
                    if n >= 4:
                        spread = np.maximum(spread, np.abs(_end_curvature(tk, Ik, a == 0) - D))
                w -= keep * dw[:, None] * dt**2 * x * (1 - x)
                # the part of the curvature not applied (not significant) stays a bias,
                # of the size the noisy D allows (D near 0 by noise is no small bias)
                h = (spread + (1 - keep) * size) * dt**2 * x * (1 - x)
        I = np.einsum("gc,gc->c", w, Ik)
        u_a = np.sqrt(np.einsum("gc,gc->c", w**2, sk**2))
        with np.errstate(invalid="ignore", divide="ignore"):
            return I, np.sqrt(u_a**2 + h**2) / np.abs(I)


def _second_difference_weights(t: NDArray, k: int) -> NDArray[np.float64]:
    """(G,) the weights of the groups in :func:`_second_difference` of triple ``k``."""
    w = np.zeros(len(t))
    t0, t1, t2 = t[k], t[k + 1], t[k + 2]
    w[k] = 1.0 / ((t1 - t0) * (t2 - t0))
    w[k + 1] = -1.0 / ((t1 - t0) * (t2 - t1))
    w[k + 2] = 1.0 / ((t2 - t1) * (t2 - t0))
    return w


def _curvature(
    dw: NDArray, I: NDArray, s: NDArray
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The second difference ``D = dw @ I`` (3,), the share of it worth applying, ``k =
    D^2 / (D^2 + var D)`` (the least-squares shrinkage: groups close in time make ``D``
    noisy, and a long interval turns its noise into a large error), and the size the
    curvature may have, ``sqrt(D^2 + var D)``."""
    D = dw @ I
    var = (dw**2) @ (s**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        keep = np.where(D * D + var > 0, D * D / (D * D + var), 0.0)
    return D, keep, np.sqrt(D * D + var)


#: The largest factor by which an end interval's curvature is extrapolated from the
#: trend of the two nearest triples (a warm-up's second differences change by a steady
#: factor from one triple to the next; noisy groups must not turn it into a blow-up).
END_CURVATURE_FACTOR = 3.0


def _end_curvature(t: NDArray, I: NDArray, first: bool) -> NDArray[np.float64]:
    """The curvature at an end interval extrapolated one step from the trend of the two
    nearest triples' second differences (geometrically, the factor clipped to
    [1/END_CURVATURE_FACTOR, END_CURVATURE_FACTOR]; the nearest triple's own where the two
    differ in sign)."""
    n = len(t)
    near, inner = (0, 1) if first else (n - 3, n - 4)
    d0, d1 = _second_difference(t, I, near), _second_difference(t, I, inner)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.clip(d0 / d1, 1 / END_CURVATURE_FACTOR, END_CURVATURE_FACTOR)
    return np.where((d0 * d1 > 0) & np.isfinite(ratio), d0 * ratio, d0)


def _second_difference(t: NDArray, I: NDArray, k: int) -> NDArray[np.float64]:
    """``I[t_k, t_k+1, t_k+2]``, the signed second divided difference (half the
    curvature of the parabola through the three groups), through the weights the
    estimate's type A uses (one formula for both)."""
    return _second_difference_weights(t, k) @ I


def drift_model(
    references: list[PoseMeasurement],
    stamps: dict[int, tuple[int, float]],
    order: list[int],
    kinds: dict[int, str],
    setup: ReductionSetup,
    pooled: NDArray[np.float64],
) -> DriftModel:
    """The reference groups of a session and the drift model through them.

    Parameters
    ----------
    references
        Measured reference poses.
    stamps
        Pose -> (journal segment, rig time or journal order) of its shots.
    order
        Every shot pose of the session in journal order (sample and reference).
    kinds
        Pose -> its kind: a sample pose between two reference poses separates groups.
    setup
        Gives the reflectance and ``drift_rel_std``.
    pooled
        (3,) the light's radiance from every reference pose (:func:`light_scale`).
    """
    by_pose = {m.pose: m for m in references}
    runs: list[list[int]] = []
    cur: list[int] = []
    cur_seg = None
    for p in order:
        kind, seg = kinds.get(p), stamps.get(p, (0, 0.0))[0]
        if kind == "reference":
            if cur and seg != cur_seg:  # a resume between: another segment's group
                runs.append(cur)
                cur = []
            if p in by_pose:
                cur.append(p)
                cur_seg = seg
        elif kind == "sample" and cur:  # a sample pose closes the group
            runs.append(cur)
            cur = []
    if cur:
        runs.append(cur)
    groups = []
    rho = setup.reflectance
    for run in runs:
        q, qv, ok = reference_ratio([by_pose[p] for p in run])
        if not ok.all():
            continue  # a group without a usable region in a channel tells nothing there
        seg = stamps.get(run[0], (0, 0.0))[0]
        t = float(np.mean([stamps.get(p, (0, 0.0))[1] for p in run]))
        groups.append(ReferenceGroup(run, seg, t, np.pi * q / rho, qv / q**2))
    return DriftModel(groups, np.asarray(pooled, float), float(setup.drift_rel_std))


# --------------------------------------------------------------------------------------
# The light's radiance profile


@dataclass
class LightProfile:
    """The fitted exponent of the light's ``cos^n(psi)`` radiance profile.

    ``n`` and its standard uncertainty ``n_std`` (NaN when the reference regions do not
    determine it), the regions used and the Birge ratio applied to ``n_std``."""

    n: float
    n_std: float
    n_regions: int
    birge: float

    def to_json(self) -> dict[str, Any]:
        def fin(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "n": fin(self.n),
            "n_std": fin(self.n_std),
            "regions": self.n_regions,
            "birge_ratio": fin(self.birge),
        }


def fit_light_profile(
    references: list[PoseMeasurement],
    cos_psi: dict[int, NDArray[np.float64]],
    applied_n: float = 0.0,
) -> LightProfile:
    """Fit ``n`` of the light's radiance profile ``L_e cos^n(psi)`` from the reference
    target's regions.

    A Lambertian target's ``L/G`` is ``rho/pi I cos^(n - n0)(psi)`` when G already
    holds ``cos^n0`` (``applied_n``): so ``ln(L/G) = a_(pose, channel) + (n - n0) ln
    cos(psi)``, one offset per pose and channel (the light may drift between poses),
    one slope for all.  Weighted least squares (weights ``(L/G)^2 / var``) on the
    within-offset deviations; ``n_std`` from the weights, times the Birge ratio
    ``sqrt(chi^2 / dof)`` when that exceeds 1 (type A).

    Parameters
    ----------
    references
        Measured reference poses.
    cos_psi
        Pose -> (n_regions,) cosine of each region's angle off the light's normal.
    applied_n
        The exponent already in G.
    """
    sxx = sxy = 0.0
    rows: list[tuple[NDArray, NDArray, NDArray]] = []
    for m in references:
        c = cos_psi.get(m.pose)
        if c is None:
            continue
        ok = (m.flags == 0)[:, None] & np.isfinite(m.ratio) & (m.ratio > 0)
        ok &= np.isfinite(m.ratio_var) & (m.ratio_var > 0) & (np.asarray(c) > 0)[:, None]
        for ch in range(m.ratio.shape[1]):
            k = ok[:, ch]
            if k.sum() < 2:
                continue
            x = np.log(np.asarray(c, float)[k])
            y = np.log(m.ratio[k, ch])
            w = m.ratio[k, ch] ** 2 / m.ratio_var[k, ch]
            xc = x - np.sum(w * x) / w.sum()
            yc = y - np.sum(w * y) / w.sum()
            sxx += float(np.sum(w * xc * xc))
            sxy += float(np.sum(w * xc * yc))
            rows.append((xc, yc, w))
    n_reg = int(sum(len(r[0]) for r in rows))
    if not rows or not sxx > 0:
        return LightProfile(float(applied_n), math.nan, n_reg, math.nan)
    slope = sxy / sxx
    chi2 = float(sum(np.sum(w * (yc - slope * xc) ** 2) for xc, yc, w in rows))
    dof = n_reg - len(rows) - 1
    birge = math.sqrt(chi2 / dof) if dof > 0 else math.nan
    std = math.sqrt(1.0 / sxx) * (max(1.0, birge) if np.isfinite(birge) else 1.0)
    return LightProfile(float(applied_n) + slope, std, n_reg, birge)


# --------------------------------------------------------------------------------------
# The per-region terms


def _sites_per_channel(n_pixels: NDArray, cell_channel: NDArray | None) -> NDArray[np.float64]:
    """(n, 3) CFA sites of each channel in a region of ``n_pixels`` pixels."""
    frac = np.array([0.25, 0.5, 0.25])
    if cell_channel is not None:
        cc = np.asarray(cell_channel).reshape(-1)
        frac = np.array([np.mean(cc == c) for c in range(3)])
    return np.asarray(n_pixels, float)[:, None] * frac[None, :]


def _region_site_weights(
    label: NDArray[np.integer],
    box: tuple[slice, slice],
    cell_channel: NDArray[np.integer],
    n_regions: int,
    mask: NDArray[np.bool_] | None,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """``(site, row, weight)`` of :func:`gonio.capture.bayer.bayer_region_entries` for the
    crop ``box`` of the frame (its CFA phase from the frame's 2x2 ``cell_channel``), the
    sites under ``mask`` handed to their channel's neighbours as the measurement hands
    them (:func:`gonio.capture.bayer.masked_site_shares`); ``site`` indexes the flattened
    crop."""
    from gonio.capture.bayer import bayer_region_entries, masked_site_shares

    lab = np.asarray(label)
    h, w = lab.shape
    r0 = box[0].start or 0
    c0 = box[1].start or 0
    cc = np.asarray(cell_channel).reshape(2, 2)
    channel = cc[((np.arange(h) + r0) % 2)[:, None], ((np.arange(w) + c0) % 2)[None, :]]
    site, row, wt = bayer_region_entries(lab, channel, n_regions)
    if mask is not None:
        site, row, wt = masked_site_shares(site, row, wt, np.asarray(mask, bool)[box], channel)
    return site, row, wt


def effective_sites(
    label: NDArray[np.integer],
    box: tuple[slice, slice],
    cell_channel: NDArray[np.integer],
    n_regions: int,
    mask: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """(n, 3) each region's effective number of independent CFA sites per channel.

    A region's value is the weighted mean of its sites with the Bayer weights ``W_q``
    (:func:`gonio.capture.bayer.bayer_region_entries`, the adjoint of bilinear
    interpolation, sites under ``mask`` handed to their neighbours, as the measurement
    does), so an error
    of std ``u`` independent from site to site (the master flat's noise, the DSNU)
    averages to ``u sqrt(sum W_q^2) / sum W_q``: the region counts as
    ``N_eff = (sum W_q)^2 / sum W_q^2`` sites.  That is not the ``N_c`` of
    :func:`_sites_per_channel` (the pixel count times the channel's share of the 2x2
    cell): the weights reach the sites just outside the region's edge, so a region of
    a few pixels' width has 10-35 % more in R and B (a 4 x 30 region: 1.26 N_c), and
    the ``flat`` term taken with ``N_c`` was that much too large (issue 16: 60-70 deg B
    z RMS 0.75 with a flat share of the budget up to 0.5).

    Parameters
    ----------
    label
        (h, w) region index of each pixel of the crop ``box``, -1 outside every region.
    box
        ``(row_slice, col_slice)``: where the crop lies in the frame (its CFA phase).
    cell_channel
        (2, 2) the frame's CFA channel of each cell position.
    n_regions
        Number of regions.
    mask
        (H, W) frame pixels left out of every region's sums, or None.

    Returns
    -------
    ndarray
        (n, 3); NaN where a region has no site of the channel.
    """
    _, row, wt = _region_site_weights(label, box, cell_channel, n_regions, mask)
    nr = n_regions * len(CHANNELS)
    s1 = np.bincount(row, wt, minlength=nr)
    s2 = np.bincount(row, wt * wt, minlength=nr)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(s2 > 0, s1 * s1 / s2, np.nan)
    return out.reshape(n_regions, len(CHANNELS))


def region_flat_rel_std(
    label: NDArray[np.integer],
    box: tuple[slice, slice],
    cell_channel: NDArray[np.integer],
    n_regions: int,
    pixel_rel_map: NDArray[np.float64],
    mask: NDArray[np.bool_] | None = None,
) -> NDArray[np.float64]:
    """The ``flat`` term of each region from the per-pixel map, (n, 3):
    ``sqrt(sum_q W_q^2 u_q^2) / sum_q W_q``.

    ``u_q`` is the relative std of site q's gain estimate at its own flat signal
    (:attr:`gonio.capture.pixel_calibration.FlatField.pixel_rel_map`), ``W_q`` the
    region's Bayer weights (:func:`effective_sites`); the errors are independent from
    site to site (the flats' and the master dark's noise).  Arguments as
    :func:`effective_sites`.
    """
    site, row, wt = _region_site_weights(label, box, cell_channel, n_regions, mask)
    u = np.asarray(pixel_rel_map, dtype=np.float64)[box].reshape(-1)[site]
    nr = n_regions * len(CHANNELS)
    s1 = np.bincount(row, wt, minlength=nr)
    s2 = np.bincount(row, wt * wt * u * u, minlength=nr)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(s1 > 0, np.sqrt(s2) / s1, np.nan)
    return out.reshape(n_regions, len(CHANNELS))


def flat_rel_std(
    n_pixels: NDArray,
    pixel_rel_std: NDArray,
    cell_channel: NDArray | None = None,
    n_sites: NDArray | None = None,
) -> NDArray[np.float64]:
    """The ``flat`` term: ``u_pix,c / sqrt(N_c)``, (n, 3).

    ``u_pix,c`` is the relative std of one pixel's gain in channel c: with flats the
    master flat's own noise (type A: ``sqrt(var(S_c)/N_flat + var_dark) / S_c`` at the
    flats' mean level ``S_c``), without flats the sensor's PRNU (type B: ``[noise]
    prnu``); independent pixels average it down over the region's ``N_c`` sites:
    ``n_sites`` ((n, 3), :func:`effective_sites`) when given, else the pixel count
    times the channel's share of the cell (an underestimate of the count).
    """
    n_c = _sites_per_channel(n_pixels, cell_channel) if n_sites is None else n_sites
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(pixel_rel_std, float)[None, :] / np.sqrt(n_c)


def dark_offset_std(
    radiance: NDArray,
    n_pixels: NDArray,
    exposures: list[tuple[float, float, float]],
    noise: Any,
    dsnu_e: float,
    cell_channel: NDArray | None = None,
    n_sites: NDArray | None = None,
) -> NDArray[np.float64]:
    """The ``dark`` term of a pose whose frames were not dark-subtracted, (n, 3), in
    the radiance's units (DN per exposure factor).

    Type B: the sensor's DSNU, ``dsnu_e`` electrons rms per pixel (``[noise] dsnu_e``),
    is an offset ``d_k = dsnu_e g_k`` DN (``g_k`` the gain at frame k's ISO) the merge
    divides by each frame's exposure factor ``e_k`` and weighs as it weighs the frame
    (``w_k = e_k^2 / var_k`` for the frames the region does not saturate, at its
    radiance ``L``): ``u = (sum_k w_k d_k / e_k / sum_k w_k) / sqrt(N_c)``. It stays
    finite where ``L`` is 0 (a black region is where the offset matters most).

    Parameters
    ----------
    radiance
        (n, 3) the regions' radiance ``L`` (DN per exposure factor).
    n_pixels
        (n,) pixels per region.
    exposures
        ``(exposure factor, ISO, headroom DN)`` of each frame of the bracket.
    noise
        The camera's :class:`~gonio.capture.noise.NoiseModel`.
    dsnu_e
        DSNU, electrons rms.
    cell_channel, n_sites
        As :func:`flat_rel_std`: the sites the offset averages over.
    """
    L = np.asarray(radiance, float)
    num = np.zeros_like(L)
    den = np.zeros_like(L)
    for e, iso, headroom in exposures:
        model = noise.at_iso(iso)
        S = L * e
        var = model.variance(S)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.where(S < headroom, e * e / var, 0.0)
        num += w * (dsnu_e * model.gain) / e
        den += w
    n_c = _sites_per_channel(n_pixels, cell_channel) if n_sites is None else n_sites
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den / np.sqrt(n_c)


def irradiance_rel_std(cos_psi: NDArray, cos_psi_ref: float, n_std: float) -> NDArray[np.float64]:
    """The ``irradiance`` term (the light's radiance profile), (n, 3).

    ``G`` scales with ``cos^n(psi)`` and the light scale ``I`` with the reference
    regions' mean of it, so ``d ln f / d n = -(ln cos psi - <ln cos psi>_ref)``:
    ``u = |ln cos psi - <ln cos psi>_ref| n_std``, ``n_std`` the fit's (type A) when the
    fitted n is applied, else the stated ``[light] profile_n_std`` (type B).
    ``cos_psi_ref`` is ``exp(<ln cos psi>_ref)``.
    """
    lc = np.log(np.clip(np.asarray(cos_psi, float), 1e-12, 1.0))
    lr = math.log(min(max(float(cos_psi_ref), 1e-12), 1.0))
    return np.repeat((np.abs(lc - lr) * float(n_std))[:, None], 3, axis=1)


def stray_rel_std(
    geometry: NDArray, g0: NDArray | float, stray_fraction: float
) -> NDArray[np.float64]:
    """The ``stray`` term, (n, 3): ``s / sqrt(3) * G0 / G``.

    Type B, rectangular: the room returns at most ``s`` (``[light] stray_fraction``) of
    the light's direct irradiance at normal incidence and nominal distance (``G0``,
    from the reference poses: median ``G / cos(theta_i)``) as a diffuse irradiance; a
    region whose direct irradiance is ``I G`` errs by up to ``s G0 / G`` of it.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        return stray_fraction / math.sqrt(3.0) * np.asarray(g0, float) / np.asarray(geometry)
