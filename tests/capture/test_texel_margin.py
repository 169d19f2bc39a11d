"""The margin a texel reduction keeps between its regions (``region_margin_px``).

Independent reference: the pixel grid itself.  A pixel counted in a region must not have
a pixel of another region within the reach of its footprint and Bayer stencil, so two
labelled pixels of different regions are at least ``2 * 1.5`` pixels apart (Chebyshev),
where with no margin they touch.
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.capture.fiducials import BoardSpec, CameraPose, map_regions
from gonio.capture.noise import NoiseModel
from gonio.capture.pose_measure import MAX_MARGIN_FRACTION, region_margins
from gonio.capture.reduction_config import ReductionSetup
from gonio.capture.texel_reduce import TEXEL_MARGIN_PX, texel_setup

K = np.array([[800.0, 0, 160], [0, 800.0, 120], [0, 0, 1]])
LIGHT = np.array([0.0, 0.25, 0.433])


def _camera(theta_deg: float) -> CameraPose:
    """A camera 0.4 m from the sample centre, tilted by theta about the x axis."""
    t = np.radians(theta_deg)
    C = 0.4 * np.array([0.0, -np.sin(t), np.cos(t)])
    z = -C / np.linalg.norm(C)  # forward
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # sample -> camera
    return CameraPose(R, -R @ C, C, np.nan, 0)


def _closest_foreign(label: np.ndarray) -> int:
    """Smallest Chebyshev distance (pixels) between labelled pixels of two regions."""
    for d in range(1, 8):
        a = np.pad(label, d, constant_values=-1)
        h, w = label.shape
        for dy in range(-d, d + 1):
            for dx in range(-d, d + 1):
                b = a[d + dy : d + dy + h, d + dx : d + dx + w]
                if np.any((label >= 0) & (b >= 0) & (b != label)):
                    return d
    return 8


def _setup(**kw) -> ReductionSetup:
    base = ReductionSetup(
        K=K,
        board=BoardSpec(),
        sample_size=(0.05, 0.05),
        noise=NoiseModel(0.4, 1.2),
        reflectance=np.full(3, 0.99),
    )
    return texel_setup(base, (4, 4)).replace(**kw) if kw else texel_setup(base, (4, 4))


@pytest.mark.parametrize("theta", [0.0, 45.0])
def test_texels_keep_their_neighbours_pixels_out(theta):
    cam = _camera(theta)
    for setup, least in ((_setup(), 3), (_setup(region_margin_px=0.0), 1)):
        margins = region_margins(cam, LIGHT, setup)
        reg = map_regions(
            cam, K, (240, 320), setup.sample_size, roi_fraction=1.0, grid=4,
            inner_margin=margins,
        )  # fmt: skip
        d = _closest_foreign(reg.label)
        assert d == least if least == 1 else d >= least, (theta, setup.region_margin_px, d)
        assert np.all(np.bincount(reg.label[reg.label >= 0], minlength=16) > 0)


def test_the_margin_is_capped_on_a_grazing_texel():
    setup = _setup(region_margin_px=50 * TEXEL_MARGIN_PX)
    mx, my = region_margins(_camera(70.0), LIGHT, setup)
    cell = 0.05 / 4
    assert mx == pytest.approx(MAX_MARGIN_FRACTION * cell) and my <= MAX_MARGIN_FRACTION * cell
