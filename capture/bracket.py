"""Adaptive exposure brackets: as few frames as the region of interest needs.

A pose starts with one frame at a predicted exposure.  If the region of interest (ROI)
clips, a frame ``step_ev`` stops shorter is added; if it sits under the noise floor, one
``step_ev`` stops longer; and so on until the shortest frame is unsaturated and the longest
is above the floor, or the frame budget or the camera's exposure range runs out.  A pose
whose first frame is fine gets exactly one frame.

The ROI statistics come from the reduction's linearisation
(:func:`gonio.capture.raw.roi_exposure_stats`), so "saturated" means the same thing here
as in the HDR merge.  Decisions depend only on the frames already taken, which lets a
resumed session re-derive the next exposure from the files on disk.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gonio.capture.plan import BracketPolicy

__all__ = ["FrameVerdict", "judge", "next_exposure", "predict_exposure", "roi_pixels"]


@dataclass(frozen=True)
class FrameVerdict:
    """How one frame's ROI is exposed.

    Attributes
    ----------
    exposure_time
        Exposure time of the frame, s.
    saturated
        More than ``saturated_fraction`` of the ROI pixels clip.
    underexposed
        The ROI's brightest channel median is under the noise floor (SNR below
        ``noise_floor_snr``).
    signal_fraction
        Brightest channel's median signal as a fraction of the headroom (0..1).
    """

    exposure_time: float
    saturated: bool
    underexposed: bool
    signal_fraction: float

    @property
    def good(self) -> bool:
        return not (self.saturated or self.underexposed)

    def to_json(self) -> dict:
        return {
            "saturated": self.saturated,
            "underexposed": self.underexposed,
            "signal_fraction": round(self.signal_fraction, 6),
        }


def roi_pixels(
    shape: tuple[int, int], roi: tuple[float, float, float, float] | None
) -> tuple[slice, slice] | None:
    """Pixel slices (rows, cols) of a fractional ROI ``(x0, y0, x1, y1)``; even-aligned so
    each slice holds whole Bayer quads."""
    if roi is None:
        return None
    h, w = shape
    x0, y0, x1, y1 = roi
    c0, c1 = 2 * int(x0 * w / 2), max(2 * int(x1 * w / 2), 2 * int(x0 * w / 2) + 2)
    r0, r1 = 2 * int(y0 * h / 2), max(2 * int(y1 * h / 2), 2 * int(y0 * h / 2) + 2)
    return slice(r0, min(r1, h)), slice(c0, min(c1, w))


def judge(stats, exposure_time: float, policy: BracketPolicy, read_noise_dn: float) -> FrameVerdict:
    """Classify a frame from its ROI statistics.

    Parameters
    ----------
    stats
        :class:`gonio.capture.raw.ExposureStats` of the frame's ROI.
    exposure_time
        The frame's exposure time, s.
    policy
        The plan's bracket policy (``saturated_fraction``, ``noise_floor_snr``).
    read_noise_dn
        Noise floor, DN rms.  With shot noise the SNR of a signal ``S`` DN is at least
        ``S / sqrt(read^2 + S)`` for a gain of 1 DN/e- or less; we use that bound, which
        never calls a frame good too early.
    """
    sig = np.asarray(stats.signal_dn, dtype=np.float64)
    top = float(np.nanmax(sig)) if np.isfinite(sig).any() else 0.0
    top = max(top, 0.0)
    snr = top / math.sqrt(read_noise_dn**2 + top) if top > 0 else 0.0
    headroom = float(stats.headroom_dn) if stats.headroom_dn > 0 else math.inf
    return FrameVerdict(
        exposure_time=float(exposure_time),
        saturated=bool(stats.saturated_fraction > policy.saturated_fraction),
        underexposed=bool(snr < policy.noise_floor_snr),
        signal_fraction=top / headroom,
    )


def next_exposure(verdicts: Sequence[FrameVerdict], policy: BracketPolicy) -> float | None:
    """The next exposure time (s) of the bracket, or None when it is complete.

    Complete when the shortest frame is not saturated and the longest is not under the
    noise floor, when ``max_frames`` frames were taken, or when the needed exposure would
    leave ``[min_exposure_s, max_exposure_s]``.
    """
    if not verdicts or len(verdicts) >= policy.max_frames:
        return None
    factor = 2.0**policy.step_ev
    shortest = min(verdicts, key=lambda v: v.exposure_time)
    longest = max(verdicts, key=lambda v: v.exposure_time)
    if shortest.saturated:
        t = shortest.exposure_time / factor
        if t >= policy.min_exposure_s * (1 - 1e-9):
            return t
    if longest.underexposed:
        t = longest.exposure_time * factor
        if t <= policy.max_exposure_s * (1 + 1e-9):
            return t
    return None


def predict_exposure(
    policy: BracketPolicy,
    previous: Sequence[FrameVerdict] | None,
    cos_theta_i_prev: float | None,
    cos_theta_i: float,
) -> float:
    """Predicted first exposure (s) of a pose.

    The previous pose's best frame (the good one with the most signal, else the frame
    nearest mid-scale) is scaled by the change of irradiance ``cos(theta_i)`` and, when it
    was under- or over-exposed, moved to aim at a quarter of the headroom.  The first pose
    uses ``policy.exposure_time_s``.
    """
    if not previous or cos_theta_i_prev is None:
        t = policy.exposure_time_s
    else:
        good = [v for v in previous if v.good]
        if good:
            best = max(good, key=lambda v: v.signal_fraction)
            t = best.exposure_time
        else:
            best = min(previous, key=lambda v: abs(math.log(max(v.signal_fraction, 1e-9) / 0.25)))
            scale = 0.25 / best.signal_fraction if best.signal_fraction > 0 else 2.0**policy.step_ev
            t = best.exposure_time * min(max(scale, 2.0**-policy.step_ev), 2.0**policy.step_ev)
        t *= max(cos_theta_i_prev, 1e-3) / max(cos_theta_i, 1e-3)
    return float(min(max(t, policy.min_exposure_s), policy.max_exposure_s))
