"""The sensor's fixed pattern from a session's darks and flats: the PRNU gain map and the
hot/dead pixel mask.

- :func:`prnu_gain`: the master flat (mean of the flat frames minus the master dark at
  their exposure and ISO) times the reduction's own vignetting model ``1 / cos^4`` (the
  one :mod:`gonio.capture.pose_kernel` and :func:`gonio.capture.fiducials.map_regions`
  divide out), normalised to 1 per CFA channel.  Dividing a frame by it and then by
  ``cos^4`` corrects the pixels' gain and whatever of the lens's vignetting the
  ``cos^4`` model misses -- without correcting ``cos^4`` twice.
- :func:`hot_pixels` and :func:`odd_gain_pixels`: pixels whose dark signal (against its
  same-colour neighbours), or whose flat-field gain, stands out of their channel's robust
  spread by more than
  :data:`OUTLIER_SIGMA` (a hot pixel's dark current varies from frame to frame more than
  a master dark can remove; a dead or stuck one has no useful gain).  The reduction
  reads them nowhere (their weights go to their neighbours: bayer.masked_site_shares).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gonio.capture.raw import CHANNELS
from gonio.errors import ReductionError

__all__ = [
    "OUTLIER_SIGMA",
    "FlatField",
    "cos4_inverse",
    "hot_pixels",
    "odd_gain_pixels",
    "prnu_gain",
    "robust_std",
]

#: Robust standard deviations from the channel's median beyond which a pixel is masked:
#: a Gaussian pixel passes it with probability 1 - 2e-9 (no pixel of a 24 MP sensor).
OUTLIER_SIGMA = 6.0


def robust_std(x: NDArray[np.float64]) -> float:
    """``1.4826 * median(|x - median(x)|)``: the std of a Gaussian bulk, blind to outliers."""
    x = np.asarray(x, float)
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def cos4_inverse(shape: tuple[int, int], K: NDArray[np.float64]) -> NDArray[np.float64]:
    """(H, W) ``1 / cos^4`` of each pixel's angle to the optical axis (pinhole ``K``,
    pixel centres at integers): the reduction's natural-vignetting model."""
    K = np.asarray(K, float)
    x = (np.arange(shape[1]) - K[0, 2]) / K[0, 0]
    y = (np.arange(shape[0]) - K[1, 2]) / K[1, 1]
    r2 = x[None, :] ** 2 + y[:, None] ** 2 + 1.0
    return r2 * r2


def hot_pixels(
    master_dark: NDArray[np.float64],
    channel: NDArray[np.int8],
    floor_std: float = 0.0,
    variance: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
) -> NDArray[np.bool_]:
    """Pixels of a master dark that stand above their own neighbourhood: more than
    :data:`OUTLIER_SIGMA` std above the median of the 3 x 3 sites of the same CFA
    position around them.

    The std is the larger of the residuals' robust std over the channel, ``floor_std``
    (DN: the master dark's read noise, so a clean, quiet dark masks nothing) and, when
    ``variance`` is given (DN^2 of one master-dark pixel whose expected value is the
    given signal, DN: the noise model over the darks averaged), its root at the local
    median: the ambient image's photon noise, which the channel's robust std (set by the
    black background) does not see.

    Why the neighbourhood and not the channel's median: a hot pixel is a defect of one
    pixel, while a dark taken with the light switched off holds the room's ambient light
    reflected by whatever the camera sees (the sample, holder and board at the rig's
    pose).  Against the channel's median that smooth image stood out as thousands of
    "hot" pixels (world 1606: 2626, 1.5 % of the frame, against ~90 drawn), all on the
    sample where the last pose saw it, and masking them moved the regions' CFA-weighted
    means off their reported directions (up to 5 % on a grazing lobe's flank).  The
    residual against the local median keeps an isolated outlier whole (one of nine
    values cannot move a median) and leaves a smooth image at the noise.
    """
    from scipy.ndimage import median_filter

    d = np.asarray(master_dark, float)
    local = np.zeros(d.shape)
    for i in range(2):
        for j in range(2):
            sub = d[i::2, j::2]  # one CFA position: the same filter colour
            if sub.size:
                local[i::2, j::2] = median_filter(sub, size=3, mode="mirror")
    resid = d - local
    pix_std = np.sqrt(np.asarray(variance(local), float)) if variance is not None else None
    out = np.zeros(d.shape, bool)
    for c in range(len(CHANNELS)):
        m = channel == c
        if not m.any():
            continue
        v = resid[m]
        s = np.asarray(max(robust_std(v), float(floor_std)))
        if pix_std is not None:
            s = np.maximum(s, pix_std[m])
        out[m] = (v > np.median(v) + OUTLIER_SIGMA * s) & (s > 0)
    return out


def odd_gain_pixels(gain: NDArray[np.float64], channel: NDArray[np.int8]) -> NDArray[np.bool_]:
    """Pixels whose flat-field gain is not finite and positive, or lies more than
    :data:`OUTLIER_SIGMA` robust std from its channel's median (dead, stuck, dusty)."""
    g = np.asarray(gain, float)
    out = ~(np.isfinite(g) & (g > 0))
    for c in range(len(CHANNELS)):
        m = (channel == c) & ~out
        if not m.any():
            continue
        v = g[m]
        s = max(robust_std(v), 1e-6 * abs(float(np.median(v))))
        out[m] = np.abs(v - np.median(v)) > OUTLIER_SIGMA * s
    return out


@dataclass
class FlatField:
    """What the flats give the reduction.

    Attributes
    ----------
    gain
        (H, W) PRNU gain map, mean 1 per channel over the unmasked pixels (1 where
        masked): frames are divided by it.
    odd
        (H, W) pixels the flat says are unusable (saturated in a flat, dead, outliers).
    level
        (3,) mean dark-subtracted flat signal per channel, DN.
    pixel_rel_std
        (3,) relative std of one pixel's gain estimate (the flats' noise and the master
        dark's), per channel: the budget's ``flat`` term before averaging.
    n_frames
        Flat frames averaged.
    pixel_rel_map
        (H, W) the same per pixel, at the pixel's own flat signal (None: not known).
        The sample sits near the image centre, where the flat is brighter than its mean
        over the frame (cos^4, vignetting: 7 % on the realistic world), so its pixels'
        gains are known better than ``pixel_rel_std`` says.
    """

    gain: NDArray[np.float64]
    odd: NDArray[np.bool_]
    level: NDArray[np.float64]
    pixel_rel_std: NDArray[np.float64]
    n_frames: int
    pixel_rel_map: NDArray[np.float64] | None = None


def prnu_gain(
    flats: list[NDArray[np.float64]],
    channel: NDArray[np.int8],
    K: NDArray[np.float64],
    *,
    dark: NDArray[np.float64] | None = None,
    saturated: NDArray[np.bool_] | None = None,
    pixel_variance: object = None,
    dark_variance: float = 0.0,
    mask: NDArray[np.bool_] | None = None,
) -> FlatField:
    """The PRNU gain map of a set of flat frames (see the module docstring).

    Parameters
    ----------
    flats
        (H, W) linear flat frames (DN above black), same exposure and ISO.
    channel
        (H, W) CFA channel of each pixel.
    K
        Camera matrix (the vignetting model's optical axis and focal lengths), pixels.
    dark
        The master dark at the flats' exposure and ISO (DN), subtracted; None for none.
    saturated
        Pixels saturated in any flat (masked).
    pixel_variance
        ``signal DN -> variance DN^2`` of one frame's pixel (the noise model), for
        :attr:`FlatField.pixel_rel_std`; None: 0.
    dark_variance
        Variance of the subtracted master dark, DN^2.
    mask
        Pixels already known to be bad (hot), left out of the normalisation.

    Raises
    ------
    ReductionError
        No flat, or a channel without signal.
    """
    if not flats:
        raise ReductionError("the flat field needs at least one flat frame")
    mean = np.mean(flats, axis=0)
    if dark is not None:
        mean = mean - dark
    seen = mean * cos4_inverse(mean.shape, K)
    bad = np.zeros(mean.shape, bool) if mask is None else np.asarray(mask, bool).copy()
    if saturated is not None:
        bad |= saturated
    level = np.empty(len(CHANNELS))
    rel = np.zeros(len(CHANNELS))
    rel_map = None
    if pixel_variance is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            v_pix = np.asarray(pixel_variance(np.maximum(mean, 0.0)), dtype=np.float64)  # type: ignore[operator]
            rel_map = np.where(mean > 0, np.sqrt(v_pix / len(flats) + dark_variance) / mean, np.inf)
    gain = np.ones_like(seen)
    for c in range(len(CHANNELS)):
        m = (channel == c) & ~bad
        lev = float(np.mean(seen[m])) if m.any() else 0.0
        if not lev > 0:
            raise ReductionError(f"the flat frames have no signal in channel {CHANNELS[c]}")
        gain[channel == c] = seen[channel == c] / lev
        level[c] = float(np.mean(mean[m]))
        if pixel_variance is not None:
            v = float(np.asarray(pixel_variance(level[c])))  # type: ignore[operator]
            rel[c] = np.sqrt(v / len(flats) + dark_variance) / level[c]
    odd = odd_gain_pixels(np.where(bad, 1.0, gain), channel) | bad
    if odd.any():  # renormalise without them
        for c in range(len(CHANNELS)):
            m = (channel == c) & ~odd
            gain[channel == c] /= float(np.mean(gain[m]))
    gain[odd] = 1.0
    return FlatField(gain, odd, level, rel, len(flats), rel_map)
