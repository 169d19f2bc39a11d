"""Radiometric calibration: from relative radiance to BRDF in 1/sr, with uncertainty.

A Lambertian reference target of known reflectance ``rho`` shot in the sample's place,
with the same light, gives the irradiance in the camera's own (relative) units:

    L_ref = rho / pi * E      =>      E = pi * L_ref / rho

and the sample's BRDF per channel is ``f = L_o / E`` (1/sr).  Because ``L_o`` and ``L_ref``
are read by the same camera in the same units, the camera's absolute response cancels.
The reflectance is a constant (per channel) or a spectrum from a CSV file (wavelength in
nm, reflectance 0..1), weighted per channel with the camera's spectral sensitivities and
the light's spectrum through colour-science.

When the reference was shot at another light position than the sample, the irradiance is
carried over with the light's geometry (:func:`irradiance_geometry`: the exact irradiance
of a Lambertian disk of unit radiance, or the point-source law), which cancels the light's
unknown absolute radiance.

Photometric values are not computed here: :mod:`gonio.radiometry.photometry` derives them,
and they never enter the BRDF.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.errors import ConfigError, FileFormatError


def reference_reflectance(
    value: float | ArrayLike | str | os.PathLike,
    *,
    sensitivities: str = "Nikon 5100 (NPL)",
    illuminant: str = "D65",
) -> NDArray[np.float64]:
    """Per-channel (R, G, B) reflectance of the reference target.

    Parameters
    ----------
    value
        A reflectance (scalar or three values) or the path of a CSV file with two columns,
        wavelength (nm) and reflectance (0..1); a header line is allowed.
    sensitivities
        Name in ``colour.MSDS_CAMERA_SENSITIVITIES`` used to weight a spectrum.
    illuminant
        Name in ``colour.SDS_ILLUMINANTS``: the light's spectrum for the weighting.

    Returns
    -------
    ndarray (3,)
        ``rho_c = sum rho(l) s_c(l) E(l) / sum s_c(l) E(l)``.

    Raises
    ------
    FileFormatError
        Unreadable CSV or reflectance outside (0, 1].
    ConfigError
        Unknown camera or illuminant name.
    """
    if isinstance(value, (str, os.PathLike)) and not _is_number(value):
        return _reflectance_from_csv(Path(value), sensitivities, illuminant)
    rho = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()
    if not np.all((rho > 0) & (rho <= 1)):
        raise ConfigError(f"reference reflectance must be in (0, 1], got {rho.tolist()}")
    return rho


def _is_number(v: object) -> bool:
    try:
        float(v)  # type: ignore[arg-type]
        return True
    except (TypeError, ValueError):
        return False


def _reflectance_from_csv(path: Path, sensitivities: str, illuminant: str) -> NDArray[np.float64]:
    import colour

    try:
        data = np.genfromtxt(path, delimiter=",", ndmin=2, invalid_raise=True)
    except (OSError, ValueError) as exc:
        raise FileFormatError(path, f"cannot read a reflectance spectrum ({exc})") from None
    data = data[np.all(np.isfinite(data), axis=1)] if data.size else data
    if data.ndim != 2 or data.shape[1] < 2 or len(data) < 2:
        raise FileFormatError(path, "expected two columns: wavelength (nm), reflectance (0..1)")
    wl, r = data[:, 0], data[:, 1]
    if np.any(np.diff(wl) <= 0):
        raise FileFormatError(path, "wavelengths must increase", "wavelength")
    if np.any((r < 0) | (r > 1)):
        raise FileFormatError(path, "reflectance values must lie in [0, 1]", "reflectance")
    if sensitivities not in colour.MSDS_CAMERA_SENSITIVITIES:
        raise ConfigError(f"unknown camera sensitivities {sensitivities!r}")
    if illuminant not in colour.SDS_ILLUMINANTS:
        raise ConfigError(f"unknown illuminant {illuminant!r}")
    cam = colour.MSDS_CAMERA_SENSITIVITIES[sensitivities]
    lam = np.asarray(cam.wavelengths, float)
    if wl[0] > lam[0] + 10 or wl[-1] < lam[-1] - 10:
        raise FileFormatError(
            path,
            f"spectrum covers {wl[0]:g}-{wl[-1]:g} nm, the camera needs {lam[0]:g}-{lam[-1]:g} nm",
            "wavelength",
        )
    ill = colour.SDS_ILLUMINANTS[illuminant]
    e = np.interp(lam, ill.wavelengths, ill.values)
    rho = np.interp(lam, wl, r)
    s = np.asarray(cam.values, float) * e[:, None]  # (L, 3)
    return (rho[:, None] * s).sum(0) / s.sum(0)


def irradiance_from_reference(
    radiance: ArrayLike,
    radiance_var: ArrayLike,
    reflectance: ArrayLike,
    reflectance_std: ArrayLike = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``E = pi L_ref / rho`` and its variance.

    Parameters
    ----------
    radiance, radiance_var
        Reference target radiance and its variance (camera units), per channel.
    reflectance, reflectance_std
        Its known reflectance and standard uncertainty, per channel.

    Returns
    -------
    (E, var_E)
    """
    L = np.asarray(radiance, float)
    rho = np.asarray(reflectance, float)
    E = np.pi * L / rho
    with np.errstate(divide="ignore", invalid="ignore"):
        rel2 = (
            np.asarray(radiance_var, float) / L**2 + (np.asarray(reflectance_std, float) / rho) ** 2
        )
    return E, E**2 * rel2


def brdf_from_radiance(
    radiance: ArrayLike,
    radiance_var: ArrayLike,
    irradiance: ArrayLike,
    irradiance_var: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``f = L_o / E`` in 1/sr and its standard deviation (first-order propagation).

    ``L_o`` and ``E`` come from different frames, so their errors are independent.
    """
    L = np.asarray(radiance, float)
    E = np.asarray(irradiance, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = L / E
        var = (
            np.asarray(radiance_var, float) / E**2 + f**2 * np.asarray(irradiance_var, float) / E**2
        )
    return f, np.sqrt(var)


def irradiance_geometry(
    points: ArrayLike,
    light_position: ArrayLike,
    light_normal: ArrayLike | None = None,
    radius: float | None = None,
    normal: ArrayLike = (0.0, 0.0, 1.0),
) -> NDArray[np.float64]:
    """Irradiance at surface points from a light of unit radiance (or unit intensity).

    Parameters
    ----------
    points
        (..., 3) points on the sample plane, metres.
    light_position, light_normal
        Light centre and emitting normal (towards the sample), sample frame.
    radius
        Disk radius, metres: exact irradiance of a Lambertian disk of radiance 1
        (:func:`gonio.radiometry.irradiance_disk`); None for a small source of on-axis
        intensity 1: ``cos(theta) / d^2``, times ``cos(theta')`` (Lambertian emitter)
        when ``light_normal`` is given.
    normal
        Surface normal of the points.

    Returns
    -------
    ndarray (...)
        W/m^2 per unit radiance (disk) or per unit intensity (point).
    """
    p = np.asarray(points, float)
    c = np.asarray(light_position, float)
    n = np.asarray(normal, float)
    if radius is not None and light_normal is not None:
        from gonio.radiometry.emitters import irradiance_disk

        # 64 rim nodes: the rim integral of an unclipped disk is periodic, so the
        # trapezoidal rule is already exact to ~1e-12; more nodes only cost time.
        return np.asarray(
            irradiance_disk(p, n, c, np.asarray(light_normal, float), radius, 1.0, n_nodes=64),
            float,
        )
    v = [c[a] - p[..., a] for a in range(3)]  # sums over a trailing axis of 3 are slow
    d2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    g = np.maximum(v[0] * n[0] + v[1] * n[1] + v[2] * n[2], 0.0) / d2**1.5
    if light_normal is not None:  # a small Lambertian emitter: intensity goes as cos
        ln = np.asarray(light_normal, float)
        cos_l = -(v[0] * ln[0] + v[1] * ln[1] + v[2] * ln[2])
        g = g * np.maximum(cos_l, 0.0) / np.sqrt(d2) / np.linalg.norm(ln)
    return g
