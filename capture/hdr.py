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

A frame is also left out where its *expected* value comes within
:data:`CLIP_GUARD_SIGMAS` standard deviations of its clip level
(:meth:`~gonio.capture.raw.RawFrame.clip_region`): a frame judged saturated by its own
reading keeps only the draws that read low, so a pixel whose mean sits near the clip
merged low (on a realistic world a whole pose's G channel 0.13 % low, where the long
frame's sample sat at the clip).  The expectation is the merged value of the pixel's
same-channel neighbours in its row, so whether a frame is kept depends on none of the
pixel's own readings (a prediction from its other frames would select their noise
instead: the long frame dropped where the short one read high leaves a high value).
Frames are judged from the longest down, and the last one is always kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gonio.capture.noise import NoiseModel
from gonio.capture.raw import RawFrame
from gonio.errors import ReductionError

#: A frame is left out of a pixel's merge where its value expected from the pixel's
#: same-channel row neighbours lies within this many standard deviations (its own noise
#: and the prediction's) of its clip level: P(a kept frame clips) < 3e-5, so censoring
#: no longer biases the merge.
CLIP_GUARD_SIGMAS = 4.0


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
    mask: NDArray[np.bool_] | None = None,
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
    mask
        Optional (H, W) hot/dead pixels of the full frame: merged like the others, but
        never a neighbour's prediction in the clip guard (module docstring).

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
    clips = [f.clip_region(sl) for f in frames]
    if len(frames) > 1 and all(c is not None for c in clips):
        usable = np.ones(shape, bool) if mask is None else ~np.asarray(mask, bool)[sl]
        _guard_clips(crops, e, frames, clips, oks, sum_s, sum_e, n_ok, noise, dv, usable)
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


def _guard_clips(
    crops: list,
    e: NDArray[np.float64],
    frames: Sequence[RawFrame],
    clips: list,
    oks: list[NDArray[np.bool_]],
    sum_s: NDArray[np.float64],
    sum_e: NDArray[np.float64],
    n_ok: NDArray[np.int64],
    noise: NoiseModel,
    dv: NDArray[np.float64],
    usable: NDArray[np.bool_],
) -> None:
    """Leave out, in place, each frame whose expected value comes within
    :data:`CLIP_GUARD_SIGMAS` of its clip (module docstring); the kernel
    :func:`gonio.capture.pose_kernel.pose_sums` does the same arithmetic per site.

    The expected value is the pooled estimate of the pixel's same-channel neighbours in
    its row (``j - 2`` and ``j + 2``, those in the crop and ``usable``: not a hot or dead
    pixel), not the pixel's own: a decision made on the pixel's own readings selects
    their noise.  A neighbour saturated in every frame predicts +inf; a pixel without a
    neighbour is not guarded.

    Where the mean of the two neighbours predicts low the guard does not fire and the
    censoring stays: on the bright side of a bright/dark edge along the row (-1.6e-3 at
    an 8x bracket, as without the guard), at a highlight a few pixels wide (-5e-4), and
    beside an unmasked dead pixel.  The brighter neighbour instead fixes the edge but lets
    every unmasked hot pixel take its neighbours' long frames (noise, not bias); the
    regions lie inside the sample, away from its edges, so the mean is kept."""

    def var(k: int, signal: NDArray[np.float64]) -> NDArray[np.float64]:
        return noise.variance(signal, iso=frames[k].iso) + dv

    with np.errstate(invalid="ignore", divide="ignore"):
        r0 = sum_s / sum_e
        acc = np.zeros_like(r0)
        for k in range(len(frames)):
            acc = acc + np.where(oks[k], var(k, r0 * e[k]), 0.0)
        v_r0 = np.where(n_ok > 0, acc / (sum_e * sum_e), 0.0)
        r0 = np.where(n_ok > 0, r0, np.inf)
        rl, rr = np.zeros_like(r0), np.zeros_like(r0)
        vl, vr = np.zeros_like(r0), np.zeros_like(r0)
        al, ar = np.zeros(r0.shape, bool), np.zeros(r0.shape, bool)
        rl[:, 2:], vl[:, 2:], al[:, 2:] = r0[:, :-2], v_r0[:, :-2], usable[:, :-2]
        rr[:, :-2], vr[:, :-2], ar[:, :-2] = r0[:, 2:], v_r0[:, 2:], usable[:, 2:]
        both = al & ar
        r_nb = np.where(both, (rl + rr) / 2.0, np.where(al, rl, np.where(ar, rr, np.nan)))
        v_nb = np.where(both, (vl + vr) / 4.0, np.where(al, vl, np.where(ar, vr, 0.0)))
        for k in range(len(frames) - 1, -1, -1):
            cand = oks[k] & (n_ok >= 2) & (al | ar)
            if not cand.any():
                continue
            e_k = e[k]
            p = np.maximum(r_nb * e_k, 0.0)
            spread = np.sqrt(var(k, p) + (e_k * e_k) * v_nb)
            drop = cand & (p + CLIP_GUARD_SIGMAS * spread >= clips[k])
            if drop.any():
                oks[k] &= ~drop
                sum_s[drop] -= crops[k][0][drop]
                sum_e[drop] -= e_k
                n_ok[drop] -= 1
