"""Merge an exposure bracket into one relative-radiance mosaic with a per-pixel variance.

Each frame k gives an estimate ``x_k = S_k / e_k`` of the relative radiance (``S_k`` linear
DN, ``e_k`` the exposure factor ``t ISO/100 / N^2``).  Its variance follows from the
photon-transfer model, ``var(S_k) / e_k**2``, evaluated at the *predicted* signal
``R0 e_k`` rather than at the noisy ``S_k`` itself: weighting a pixel by its own noisy value
would favour frames that happened to read low and bias the merge.  ``R0`` is the
exposure-pooled estimate ``sum S_k / sum e_k`` over the unsaturated frames (the maximum
likelihood estimate under pure shot noise).  The merge is then

    R = sum_k w_k x_k / sum_k w_k,   w_k = 1 / var(x_k),   var(R) = 1 / sum_k w_k

over frames where the pixel is not saturated.  colour_hdri's ``image_stack_to_HDRI``
does the same weighted sum with a fixed weighting function of the normalised data and no
variance; the tests compare both.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gonio.capture.noise import NoiseModel
from gonio.capture.raw import RawFrame
from gonio.errors import ReductionError


@dataclass(frozen=True)
class MergedFrame:
    """A merged bracket on the mosaic.

    Attributes
    ----------
    value
        (H, W) relative radiance, DN per unit exposure factor; NaN where every frame of the
        bracket is saturated.
    variance
        (H, W) variance of ``value`` from the noise model.
    saturated
        (H, W) True where every frame is saturated (``value`` is then only a lower bound,
        and NaN).
    frames_used
        (H, W) number of frames that contributed.
    channel
        (H, W) channel index (R, G, B) of each pixel, from the frames.
    names
        The frames merged, shortest exposure first.
    """

    value: NDArray[np.float64]
    variance: NDArray[np.float64]
    saturated: NDArray[np.bool_]
    frames_used: NDArray[np.int64]
    channel: NDArray[np.int8]
    names: tuple[str, ...]


def check_bracket(frames: Sequence[RawFrame]) -> None:
    """Refuse an empty bracket, or one whose frames differ in size or CFA pattern.

    Raises
    ------
    ReductionError
        Naming the frame that differs.
    """
    if not frames:
        raise ReductionError("cannot merge an empty bracket")
    ref = frames[0]
    for f in frames[1:]:
        if f.shape != ref.shape or f.cfa_pattern != ref.cfa_pattern:
            raise ReductionError(
                f"{f.name}: {f.cfa_pattern} {f.shape} does not match {ref.name}: "
                f"{ref.cfa_pattern} {ref.shape} in the same bracket"
            )


def merge_bracket(
    frames: Sequence[RawFrame],
    noise: NoiseModel,
    dark_variance: float | NDArray[np.float64] = 0.0,
    region: tuple[slice, slice] | None = None,
) -> MergedFrame:
    """Inverse-variance merge of one pose's bracket.

    Parameters
    ----------
    frames
        Decoded (and, if wanted, dark-subtracted and flat-fielded) frames of one pose; all
        the same camera, any order.
    noise
        Photon-transfer model of the camera; rescaled to each frame's ISO.
    dark_variance
        Extra variance in DN^2 of the dark frame subtracted from every frame (the read
        noise of the master dark over its frame count), 0 if none.
    region
        Optional ``(row_slice, col_slice)`` to merge only a crop (the sample's ROI box),
        which saves time on large sensors.

    Returns
    -------
    MergedFrame

    Raises
    ------
    ReductionError
        No frames, or frames of different sizes or CFA.
    """
    check_bracket(frames)
    order = sorted(range(len(frames)), key=lambda k: frames[k].exposure_factor())
    frames = [frames[k] for k in order]
    sl = region if region is not None else (slice(None), slice(None))
    e = np.array([f.exposure_factor() for f in frames])
    crops = [f.region(sl) for f in frames]
    # Accumulated frame by frame rather than over a stacked (K, h, w) array: the same sums
    # in the same order (so the same numbers), without the K-fold temporaries.
    shape = crops[0][0].shape
    sum_s = np.zeros(shape)
    sum_e = np.zeros(shape)
    n_ok = np.zeros(shape, np.int64)
    oks = []
    for (S_k, _, sat_k), ek in zip(crops, e, strict=True):
        ok_k = ~sat_k
        oks.append(ok_k)
        sum_s += np.where(ok_k, S_k, 0.0)
        sum_e += np.where(ok_k, ek, 0.0)
        n_ok += ok_k
    dv = np.asarray(dark_variance, dtype=np.float64)
    dv = dv[sl] if dv.ndim == 2 else dv
    wsum = np.zeros(shape)
    vsum = np.zeros(shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        r0 = sum_s / sum_e
        for (S_k, _, _), ok_k, f, ek in zip(crops, oks, frames, e, strict=True):
            var_k = (noise.variance(r0 * ek, iso=f.iso) + dv) / ek**2
            w_k = np.where(ok_k, 1.0 / var_k, 0.0)
            wsum += w_k
            vsum += w_k * S_k / ek
        value = vsum / wsum
        variance = 1.0 / wsum
    allsat = n_ok == 0
    value[allsat] = np.nan
    variance[allsat] = np.nan
    return MergedFrame(value, variance, allsat, n_ok, crops[0][1], tuple(f.name for f in frames))
