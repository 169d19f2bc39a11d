"""Radiometric to photometric conversion (through colour-science).

Photometric values are derived quantities: they are computed from radiometric arrays on
demand and never stored in them.  ``K_m = 683 lm/W`` is the maximum luminous efficacy
(``colour.constants.CONSTANT_K_M``).

Every matrix here maps RGB to CIE XYZ (``XYZ = M @ rgb``), the convention of
colour-science's ``RGB_Colourspace.matrix_RGB_to_XYZ``; a DNG ``ColorMatrix`` maps the
other way (XYZ to camera) and must be inverted before it is passed in.
"""

from __future__ import annotations

import colour
import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.errors import ParameterError, UnknownNameError

Array = NDArray[np.float64]

__all__ = [
    "illuminance_from_rgb",
    "illuminance_from_spectrum",
    "luminance_from_rgb",
    "luminance_from_spectrum",
    "luminous_reflectance",
]


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
    if rgb.ndim == 0 or rgb.shape[-1] != 3 or M.shape != (3, 3):
        raise ParameterError(
            f"expected RGB values of shape (..., 3) and a 3x3 RGB -> XYZ matrix, "
            f"got {rgb.shape} and {M.shape}"
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
        ``K_m * Y`` in cd/m^2, shape (...).  NaN in -> NaN out.

    Raises
    ------
    ParameterError
        When the last axis is not 3 or the matrix is not 3x3.
    """
    return colour.constants.CONSTANT_K_M * _y_from_rgb(radiance_rgb, matrix_rgb_to_xyz)


def illuminance_from_rgb(irradiance_rgb: ArrayLike, matrix_rgb_to_xyz: ArrayLike) -> Array:
    """Illuminance (lux) of camera-RGB irradiance; see :func:`luminance_from_rgb`."""
    return colour.constants.CONSTANT_K_M * _y_from_rgb(irradiance_rgb, matrix_rgb_to_xyz)


def luminous_reflectance(rgb: ArrayLike, colourspace: str = "sRGB") -> Array:
    """Luminance-weighted value of a linear RGB reflectance, albedo or BRDF.

    The CIE ``Y`` of ``rgb`` in ``colourspace``, normalised so that the colourspace's
    white (1, 1, 1) gives 1: for sRGB (ITU-R BT.709 primaries, D65 white) that is
    ``0.2126 R + 0.7152 G + 0.0722 B``.  It is the fraction of the white's luminance
    that is reflected, the single number a photometer would read.

    Parameters
    ----------
    rgb
        Linear RGB values, shape (..., 3); dimensionless (reflectance, albedo) or any unit
        (f_r in 1/sr gives Y in 1/sr).
    colourspace
        A name in ``colour.RGB_COLOURSPACES`` whose primaries ``rgb`` is expressed in.

    Returns
    -------
    ndarray
        Shape (...), in the unit of ``rgb``.  NaN in -> NaN out.

    Raises
    ------
    UnknownNameError
        When colour-science does not know ``colourspace``.
    ParameterError
        When the last axis of ``rgb`` is not 3.
    """
    try:
        space = colour.RGB_COLOURSPACES[colourspace]
    except KeyError:
        raise UnknownNameError(
            f"unknown RGB colourspace {colourspace!r}; colour-science knows e.g. 'sRGB', "
            f"'ITU-R BT.2020', 'ACEScg'"
        ) from None
    M = np.asarray(space.matrix_RGB_to_XYZ, dtype=np.float64)
    return _y_from_rgb(rgb, M) / M[1].sum()
