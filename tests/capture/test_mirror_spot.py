"""The light's mirror image: centroid of an exactly drawn disk, and the refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad

from gonio.capture.mirror_spot import SpotError, find_spot, spot_centroid
from gonio.capture.raw import RawFrame


def _overlap(a0: float, a1: float, b0: float, b1: float) -> float:
    return max(0.0, min(a1, b1) - max(a0, b0))


def _chord(x, cx, cy, r, y0, y1):
    s = math.sqrt(max(r * r - (x - cx) ** 2, 0.0))
    return _overlap(cy - s, cy + s, y0, y1)


def disk_coverage(shape, cx, cy, r):
    """Fraction of each pixel (centre at integer u, v; edges at +-0.5) inside the disk of
    centre (cx, cy) and radius r: exact up to quad's 1e-10 tolerance."""
    H, W = shape
    out = np.zeros(shape)
    for row in range(max(0, int(cy - r) - 1), min(H, int(cy + r) + 2)):
        y0, y1 = row - 0.5, row + 0.5
        for col in range(max(0, int(cx - r) - 1), min(W, int(cx + r) + 2)):
            x0, x1 = col - 0.5, col + 0.5
            lo, hi = max(x0, cx - r), min(x1, cx + r)
            if hi <= lo:
                continue

            out[row, col] = quad(
                _chord, lo, hi, args=(cx, cy, r, y0, y1), epsabs=1e-11, epsrel=1e-10, limit=200
            )[0]
    return out


def frame_of(img, *, white=4000.0, exposure_time=0.01, name="f"):
    img = np.asarray(img, float)
    H, W = img.shape
    return RawFrame(
        name,
        img,
        np.ones((H, W), np.int8),
        img >= white,
        np.zeros((H, W)),
        white,
        "RGGB",
        exposure_time=exposure_time,
        iso=100.0,
        f_number=8.0,
    )


@pytest.mark.parametrize("seed", range(6))
def test_centroid_of_an_exact_disk(seed):
    rng = np.random.default_rng(seed)
    cx, cy = rng.uniform(20, 44), rng.uniform(15, 33)
    r = rng.uniform(2.5, 6.0)
    img = 5.0 + 1000.0 * disk_coverage((48, 64), cx, cy, r)  # flat background of 5
    u, v, info = spot_centroid(img)
    assert abs(u - cx) < 0.02 and abs(v - cy) < 0.02, (u - cx, v - cy)
    assert info["background"] == pytest.approx(5.0)
    # independent check of the coverage itself: its sum is the disk's area
    assert disk_coverage((48, 64), cx, cy, r).sum() == pytest.approx(math.pi * r * r, rel=1e-9)


def test_find_spot_uses_the_least_exposed_frame():
    cov = disk_coverage((40, 50), 24.3, 17.8, 3.0)
    long_ = frame_of(100 + 8000 * cov, exposure_time=0.04, name="long")  # saturated spot
    short = frame_of(25 + 2000 * cov, exposure_time=0.01, name="short")
    u, v, info = find_spot([long_, short])
    assert info["frame"] == "short"
    assert abs(u - 24.3) < 0.02 and abs(v - 17.8) < 0.02


def test_saturated_in_every_frame_is_refused():
    cov = disk_coverage((40, 50), 24.3, 17.8, 3.0)
    frames = [frame_of(9000 * cov, exposure_time=t, name=f"t{t}") for t in (0.01, 0.02)]
    with pytest.raises(SpotError, match=r"t0\.01.*saturated.*every one of the 2 frames"):
        find_spot(frames, name="pose 4")


def test_no_spot_is_refused_naming_the_frame():
    with pytest.raises(SpotError, match="dark7: no light spot"):
        find_spot(frame_of(np.zeros((20, 20)), name="dark7"))


def test_two_comparable_blobs_are_refused():
    img = 1000 * (disk_coverage((40, 60), 15, 20, 3) + 0.8 * disk_coverage((40, 60), 45, 20, 3))
    with pytest.raises(SpotError, match="two comparable bright blobs"):
        find_spot(frame_of(img, name="twin"))
    # a faint second blob (a stray reflection) does not stop it
    img = 1000 * (disk_coverage((40, 60), 15, 20, 3) + 0.05 * disk_coverage((40, 60), 45, 20, 3))
    u, v, _ = find_spot(frame_of(img))
    assert abs(u - 15) < 0.02 and abs(v - 20) < 0.02
