"""Photometric conversion against the SI definition of the candela."""

import colour
import numpy as np
import pytest

from gonio.radiometry.photometry import (
    illuminance_from_rgb,
    illuminance_from_spectrum,
    luminance_from_rgb,
    luminance_from_spectrum,
)


def _line(wavelength_nm, value):
    wl = np.arange(360, 831)
    return colour.SpectralDistribution(dict(zip(wl, np.where(wl == wavelength_nm, value, 0.0),
                                                strict=True)))


def test_555nm_radiance_gives_683_cd_per_watt():
    # 1 W/(sr m^2) concentrated at 555 nm (V = 1.000 there) is 683 cd/m^2 by definition.
    assert luminance_from_spectrum(_line(555, 1.0)) == pytest.approx(683.0, rel=2e-4)
    assert illuminance_from_spectrum(_line(555, 2.0)) == pytest.approx(1366.0, rel=2e-4)


def test_rgb_with_identity_y_row():
    M = np.array([[0.4, 0.3, 0.2], [0.2, 0.7, 0.1], [0.0, 0.1, 0.9]])
    rgb = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    expected = 683.0 * (0.2 * 1 + 0.7 * 2 + 0.1 * 3)
    np.testing.assert_allclose(luminance_from_rgb(rgb, M), [expected, 0.0])
    np.testing.assert_allclose(illuminance_from_rgb(rgb[0], M), expected)


def test_bad_matrix_shape():
    with pytest.raises(ValueError, match="3x3"):
        luminance_from_rgb([1, 2, 3], np.eye(2))
