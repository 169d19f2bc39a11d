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
from gonio.capture.noise import NoiseModel
from gonio.capture.raw import RawFrame
from numpy.typing import NDArray

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
    if not frames:
        raise ReductionError("cannot merge an empty bracket")
    ref = frames[0]
    for f in frames[1:]:
        if f.shape != ref.shape or f.cfa_pattern != ref.cfa_pattern:
            raise ReductionError(
                f"{f.name}: {f.cfa_pattern} {f.shape} does not match {ref.name}: "
                f"{ref.cfa_pattern} {ref.shape} in the same bracket"
            )
    order = sorted(range(len(frames)), key=lambda k: frames[k].exposure_factor())
    frames = [frames[k] for k in order]
    sl = region if region is not None else (slice(None), slice(None))
    e = np.array([f.exposure_factor() for f in frames])
    crops = [f.region(sl) for f in frames]
    S = np.stack([c[0] for c in crops])  # (K, h, w)
    ok = ~np.stack([c[2] for c in crops])
    n_ok = ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r0 = np.where(ok, S, 0.0).sum(axis=0) / np.where(ok, e[:, None, None], 0.0).sum(axis=0)
        dv = np.asarray(dark_variance, dtype=np.float64)
        dv = dv[sl] if dv.ndim == 2 else dv
        var_k = np.stack(
            [noise.variance(r0 * ek, iso=f.iso) + dv for f, ek in zip(frames, e, strict=True)]
        ) / (e[:, None, None] ** 2)
        w = np.where(ok, 1.0 / var_k, 0.0)
        wsum = w.sum(axis=0)
        value = (w * S / e[:, None, None]).sum(axis=0) / wsum
        variance = 1.0 / wsum
    allsat = n_ok == 0
    value[allsat] = np.nan
    variance[allsat] = np.nan
    return MergedFrame(value, variance, allsat, n_ok, crops[0][1], tuple(f.name for f in frames))
