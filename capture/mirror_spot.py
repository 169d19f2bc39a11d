"""The light's image in a mirror lying in the sample plane: where is its centre?

At a "mirror" step of a rig calibration a flat first-surface mirror replaces the sample,
and the camera sees the light's emitting disk mirrored in it: a small, very bright
blob.  Its centroid (with the rig's model of the camera) tells the calibration where the
light is.  The bracket's least-exposed frame is used: the blob is the brightest thing in
the picture and the first to saturate, while the board and holder around it are dim there.

Pixel coordinates follow OpenCV: the centre of pixel (row r, column c) is at u = c, v = r.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from gonio.capture.raw import RawFrame
from gonio.errors import ReductionError

__all__ = ["SpotError", "find_spot", "spot_centroid"]


class SpotError(ReductionError):
    """No usable light spot in a mirror frame."""


def _grey(frame: RawFrame) -> NDArray[np.float64]:
    # The linear (black-subtracted) mosaic: the spot is white, so every CFA site sees it
    # in proportion to its channel's response; the centroid uses the mosaic as it is.
    return np.asarray(frame.linear, dtype=np.float64)


def spot_centroid(
    image: NDArray[np.float64],
    *,
    name: str = "frame",
    threshold: float = 0.3,
    comparable: float = 0.25,
    margin_px: int = 3,
) -> tuple[float, float, dict[str, Any]]:
    """Intensity-weighted centroid of the brightest compact blob of a linear image.

    Parameters
    ----------
    image
        (H, W) linear signal above black (any units).
    name
        Frame name for messages.
    threshold
        Blobs are the connected pixels above this fraction of the way from the image's
        median (the background) to its peak; the spot is the blob holding the peak.
    comparable
        A second blob whose summed signal is at least this fraction of the brightest's
        makes the spot ambiguous.
    margin_px
        The centroid sums the blob's bounding box grown by this many pixels (so the
        partly lit rim pixels below the threshold count too), after subtracting the
        median of the box's border (the background).

    Returns
    -------
    u, v, info
        Centroid, px (OpenCV convention); ``info`` holds ``peak``, ``flux``,
        ``area_px``, ``box`` (row0, row1, col0, col1), ``background``.

    Raises
    ------
    SpotError
        No signal, or two comparable blobs (frame named).
    """
    img = np.asarray(image, dtype=np.float64)
    finite = np.where(np.isfinite(img), img, 0.0)
    peak = float(finite.max()) if finite.size else 0.0
    if not peak > 0:
        raise SpotError(f"{name}: no light spot (the frame has no signal)")
    # The threshold is set between the frame's median (the background: board, holder)
    # and the peak, so a bright background does not join the spot's blob.
    floor = float(np.median(finite))
    if not peak > floor:
        raise SpotError(f"{name}: no light spot (nothing brighter than the background)")
    mask = (finite > floor + threshold * (peak - floor)).astype(np.uint8)
    n, labels, stats, _c = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n < 2:
        raise SpotError(f"{name}: no light spot above {threshold:g} of the peak")
    flux = np.bincount(labels.ravel(), weights=finite.ravel() - floor, minlength=n)[1:]
    order = np.argsort(flux)[::-1]
    best = int(labels.flat[int(np.argmax(finite))])  # the blob holding the peak
    others = [int(k) for k in order if int(k) + 1 != best]
    if others and flux[others[0]] >= comparable * flux[best - 1]:
        x2, y2 = stats[others[0] + 1, :2]
        x1, y1 = stats[best, :2]
        raise SpotError(
            f"{name}: two comparable bright blobs (near pixel ({x1}, {y1}) and "
            f"({x2}, {y2}), signal ratio {flux[others[0]] / flux[best - 1]:.2f}): is "
            "something else reflecting, or the mirror not where the sample is?"
        )
    x, y, w, h, area = (int(s) for s in stats[best])
    H, W = img.shape
    r0, r1 = max(y - margin_px, 0), min(y + h + margin_px, H)
    c0, c1 = max(x - margin_px, 0), min(x + w + margin_px, W)
    box = finite[r0:r1, c0:c1]
    border = np.concatenate([box[0], box[-1], box[1:-1, 0], box[1:-1, -1]])
    bg = float(np.median(border))
    wgt = box - bg
    total = float(wgt.sum())
    if not total > 0:
        raise SpotError(f"{name}: the light spot is not brighter than its surroundings")
    rows = np.arange(r0, r1, dtype=np.float64)
    cols = np.arange(c0, c1, dtype=np.float64)
    u = float((wgt.sum(axis=0) @ cols) / total)
    v = float((wgt.sum(axis=1) @ rows) / total)
    info = {
        "peak": peak,
        "flux": total,
        "area_px": area,
        "box": (r0, r1, c0, c1),
        "background": bg,
    }
    return u, v, info


def _exposure(frame: RawFrame) -> float:
    # a frame that does not say how it was exposed sorts first (it is used as it is)
    try:
        return frame.exposure_factor()
    except ReductionError:
        return 0.0


def find_spot(
    frames: RawFrame | Sequence[RawFrame],
    *,
    name: str | None = None,
    threshold: float = 0.3,
    comparable: float = 0.25,
) -> tuple[float, float, dict[str, Any]]:
    """The light's mirror image in a bracket: centroid in its least-exposed frame.

    Parameters
    ----------
    frames
        One decoded frame or a pose's bracket (dark-subtracted or not: the local
        background is subtracted).
    name
        Pose name for messages (default: the frame names).
    threshold, comparable
        See :func:`spot_centroid`.

    Returns
    -------
    u, v, info
        Centroid, px (OpenCV convention); ``info`` as :func:`spot_centroid`'s plus
        ``frame`` (the name of the frame used).

    Raises
    ------
    SpotError
        No spot; the spot saturated in every frame (even the least exposed); two
        comparable blobs.  The frame or pose is named.
    """
    frs = [frames] if isinstance(frames, RawFrame) else list(frames)
    if not frs:
        raise SpotError(f"{name or 'pose'}: no frames to find the light spot in")
    frame = min(frs, key=_exposure)
    label = frame.name if name is None else f"{name} ({frame.name})"
    u, v, info = spot_centroid(_grey(frame), name=label, threshold=threshold, comparable=comparable)
    r0, r1, c0, c1 = info["box"]
    sat = frame.region((slice(r0, r1), slice(c0, c1)))[2]
    if sat.any():
        which = "the frame" if len(frs) == 1 else f"every one of the {len(frs)} frames"
        raise SpotError(
            f"{label}: the light spot is saturated ({int(sat.sum())} pixels) in {which}, "
            "even the least exposed; add a shorter exposure to the mirror steps"
        )
    info["frame"] = frame.name
    return u, v, info
