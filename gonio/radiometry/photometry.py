"""Radiometric to photometric conversion (through colour-science).

Photometric values are derived quantities: they are computed from radiometric arrays on
demand and never stored in them.  ``K_m = 683 lm/W`` is the maximum luminous efficacy
(``colour.constants.CONSTANT_K_M``).
"""

from __future__ import annotations

import colour
import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def _photopic(sd: colour.SpectralDistribution) -> float:
    lef = colour.colorimetry.SDS_LEFS_PHOTOPIC["CIE 1924 Photopic Standard Observer"]
    return float(colour.luminous_flux(sd, lef=lef, K_m=colour.constants.CONSTANT_K_M))


def luminance_from_spectrum(sd: colour.SpectralDistribution) -> float:
    """Luminance (cd/m^2) of a spectral radiance in W/(sr m^2 nm).

    ``L_v = K_m * integral L_e(lambda) V(lambda) dlambda`` with the CIE 1924 photopic
    luminous efficiency function.
    """
    return _photopic(sd)


def illuminance_from_spectrum(sd: colour.SpectralDistribution) -> float:
    """Illuminance (lux) of a spectral irradiance in W/(m^2 nm)."""
    return _photopic(sd)


def _y_from_rgb(rgb: ArrayLike, matrix_rgb_to_xyz: ArrayLike) -> Array:
    rgb = np.asarray(rgb, dtype=np.float64)
    M = np.asarray(matrix_rgb_to_xyz, dtype=np.float64)
    if rgb.shape[-1] != 3 or M.shape != (3, 3):
        raise ValueError(
            f"expected RGB values (..., 3) and a 3x3 matrix, got {rgb.shape} and {M.shape}"
        )
    return colour.algebra.vecmul(M, rgb)[..., 1]


def luminance_from_rgb(radiance_rgb: ArrayLike, matrix_rgb_to_xyz: ArrayLike) -> Array:
    """Luminance (cd/m^2) of camera-RGB radiance.

    Parameters
    ----------
    radiance_rgb
        Radiance per camera channel, shape (..., 3), in W/(sr m^2) units of the camera.
    matrix_rgb_to_xyz
        3x3 matrix from camera RGB to CIE XYZ, scaled so that ``Y`` equals
        ``integral L_e(lambda) V(lambda) dlambda`` in W/(sr m^2) (a radiometrically
        calibrated camera matrix).

    Returns
    -------
    ndarray
        ``K_m * Y`` in cd/m^2.
    """
    return colour.constants.CONSTANT_K_M * _y_from_rgb(radiance_rgb, matrix_rgb_to_xyz)


def illuminance_from_rgb(irradiance_rgb: ArrayLike, matrix_rgb_to_xyz: ArrayLike) -> Array:
    """Illuminance (lux) of camera-RGB irradiance; see :func:`luminance_from_rgb`."""
    return colour.constants.CONSTANT_K_M * _y_from_rgb(irradiance_rgb, matrix_rgb_to_xyz)
