"""Photometric conversion against the SI definition of the candela."""

import colour
import numpy as np
import pytest

from gonio.errors import ParameterError, UnknownNameError
from gonio.radiometry.photometry import (
    illuminance_from_rgb,
    illuminance_from_spectrum,
    luminance_from_rgb,
    luminance_from_spectrum,
    luminous_reflectance,
)


def _line(wavelength_nm, value):
    wl = np.arange(360, 831)
    return colour.SpectralDistribution(
        dict(zip(wl, np.where(wl == wavelength_nm, value, 0.0), strict=True))
    )


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


def test_a_dng_colour_matrix_is_inverted_first():
    # A DNG ColorMatrix maps XYZ to camera RGB: camera RGB made from known XYZ, with the
    # inverse passed in, gives back 683 Y (the convention the removed copy in
    # gonio.capture.calibration used, from the other side).
    xyz_to_cam = np.array([[1.2, -0.3, -0.1], [-0.4, 1.3, 0.1], [0.0, -0.2, 0.9]])
    xyz = np.array([[0.3, 0.4, 0.2], [1.0, 1.0, 1.0]])
    rgb = xyz @ xyz_to_cam.T
    lum = luminance_from_rgb(rgb, np.linalg.inv(xyz_to_cam))
    np.testing.assert_allclose(lum, 683.0 * xyz[:, 1], rtol=1e-12)


def test_bad_matrix_shape():
    with pytest.raises(ParameterError, match="3x3"):
        luminance_from_rgb([1, 2, 3], np.eye(2))


# ITU-R BT.709-6, item 3.2: E'Y = 0.2126 E'R + 0.7152 E'G + 0.0722 E'B (the same primaries
# and white as sRGB, IEC 61966-2-1).  Independent of colour-science, which derives its
# BT.709 weights from the primaries and white point.
BT709_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])


def test_luminous_reflectance_uses_the_bt709_weights():
    rgb = np.array([[0.2, 0.5, 0.8], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(luminous_reflectance(rgb), rgb @ BT709_WEIGHTS, rtol=1e-12)
    # the weights from the primaries agree with the standard's four decimals
    np.testing.assert_allclose(
        luminous_reflectance(rgb, "ITU-R BT.709"), rgb @ BT709_WEIGHTS, atol=5e-5
    )


def test_luminous_reflectance_of_white_is_one_in_any_colourspace():
    for name in ("sRGB", "ITU-R BT.2020", "ACEScg", "Adobe RGB (1998)"):
        assert luminous_reflectance([1.0, 1.0, 1.0], name) == pytest.approx(1.0, abs=1e-12)


def test_luminous_reflectance_is_vectorised_and_keeps_nan():
    rgb = np.random.default_rng(3).uniform(size=(4, 5, 3))
    rgb[1, 2, 0] = np.nan
    y = luminous_reflectance(rgb)
    assert y.shape == (4, 5)
    assert np.isnan(y[1, 2])
    assert np.isfinite(np.delete(y.ravel(), 7)).all()
    np.testing.assert_allclose(np.delete(y.ravel(), 7), np.delete(rgb @ BT709_WEIGHTS, 7))


def test_luminous_reflectance_bad_input_names_it():
    with pytest.raises(UnknownNameError, match="'sRGB-ish'"):
        luminous_reflectance([0.1, 0.2, 0.3], "sRGB-ish")
    with pytest.raises(ParameterError, match=r"\(4,\)"):
        luminous_reflectance([0.1, 0.2, 0.3, 0.4])
