"""Radiometric calibration: reference reflectance, BRDF = L / E with uncertainty."""

from __future__ import annotations

import colour
import numpy as np
import pytest

from gonio.capture.calibration import (
    brdf_from_radiance,
    irradiance_from_reference,
    irradiance_geometry,
    reference_reflectance,
)
from gonio.errors import ConfigError, FileFormatError


def test_constant_reflectance_and_csv_spectra(tmp_path):
    assert reference_reflectance(0.99) == pytest.approx([0.99] * 3)
    assert reference_reflectance([0.9, 0.8, 0.7]) == pytest.approx([0.9, 0.8, 0.7])
    flat = tmp_path / "flat.csv"
    flat.write_text(
        "wavelength_nm,reflectance\n" + "\n".join(f"{w},0.5" for w in range(350, 801, 10))
    )
    assert reference_reflectance(flat) == pytest.approx([0.5] * 3, rel=1e-12)
    # a target that reflects only blue light: the B channel sees most of it, R almost none
    blue = tmp_path / "blue.csv"
    blue.write_text("\n".join(f"{w},{1.0 if w < 500 else 0.0}" for w in range(350, 801, 5)))
    r, g, b = reference_reflectance(blue)
    cam = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"]
    ill = colour.SDS_ILLUMINANTS["D65"]
    wl = cam.wavelengths
    w = cam.values[:, 2] * np.interp(wl, ill.wavelengths, ill.values)
    step = np.interp(
        wl, np.arange(350, 801, 5), [1.0 if x < 500 else 0.0 for x in range(350, 801, 5)]
    )
    assert b == pytest.approx(np.sum(step * w) / np.sum(w), rel=1e-9)
    assert b > 0.8 and r < 0.1 and r < g < b


@pytest.mark.parametrize(
    "text, what",
    [
        ("400,0.5\n", "two columns"),
        ("400,0.5\n500,1.5\n600,0.5\n", "reflectance"),
        ("600,0.5\n500,0.5\n400,0.5\n", "increase"),
        ("500,0.5\n600,0.5\n", "covers"),
    ],
)
def test_bad_reflectance_csv(tmp_path, text, what):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(FileFormatError, match=what):
        reference_reflectance(p)
    with pytest.raises(ConfigError, match="reflectance"):
        reference_reflectance(1.5)


def test_brdf_and_uncertainty_against_monte_carlo():
    rng = np.random.default_rng(0)
    L, sL = np.array([10.0, 20.0, 5.0]), np.array([0.1, 0.3, 0.05])
    Lr, sLr = np.array([300.0, 350.0, 200.0]), np.array([1.0, 2.0, 1.5])
    rho, srho = np.array([0.99, 0.98, 0.97]), np.array([0.005, 0.005, 0.01])
    E, vE = irradiance_from_reference(Lr, sLr**2, rho, srho)
    assert E == pytest.approx(np.pi * Lr / rho)
    f, sf = brdf_from_radiance(L, sL**2, E, vE)
    assert f == pytest.approx(L * rho / (np.pi * Lr))
    n = 400_000
    draws = (
        (L + sL * rng.standard_normal((n, 3)))
        * (rho + srho * rng.standard_normal((n, 3)))
        / (np.pi * (Lr + sLr * rng.standard_normal((n, 3))))
    )
    assert sf == pytest.approx(draws.std(axis=0), rel=0.02)


def test_irradiance_geometry_limits():
    p = np.array([[0.0, 0.0, 0.0], [0.01, -0.02, 0.0]])
    c = np.array([0.0, 0.3, 0.4])  # 0.5 m away, 36.9 deg from the normal
    n = -c / np.linalg.norm(c)
    # on the axis of a small disk: E = L pi r^2 cos / d^2 (1 - r^2/d^2 ...); far field
    r = 1e-3
    disk = irradiance_geometry(p, c, n, r)
    point = irradiance_geometry(p, c, n) * np.pi * r**2
    np.testing.assert_allclose(disk, point, rtol=1e-5)
    assert irradiance_geometry(p[:1], c)[0] == pytest.approx(0.8 / 0.25)
    # a disk seen face-on from its axis: E = pi L r^2 / (r^2 + d^2), exact
    axis = irradiance_geometry([[0, 0, 0]], [0, 0, 0.5], [0, 0, -1], 0.05)[0]
    assert axis == pytest.approx(np.pi * 0.05**2 / (0.05**2 + 0.25), rel=1e-10)


def test_disk_correction_used_by_the_reduction_matches_the_rim_integral():
    """measure_pose uses pi r^2 cos cos' / d^2 * d^2 / (d^2 + r^2) for a disk aimed at the
    sample centre; over a 5 cm sample lit from 0.5 m it equals the exact disk irradiance."""
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-0.025, 0.025, (200, 2)), np.zeros(200)])
    for theta in np.radians([0.0, 30.0, 60.0, 80.0]):
        c = 0.5 * np.array([np.sin(theta), 0.0, np.cos(theta)])
        n = -c / np.linalg.norm(c)
        r = 0.01
        exact = irradiance_geometry(pts, c, n, r)
        d2 = np.sum((c - pts) ** 2, axis=-1)
        approx = irradiance_geometry(pts, c, n) * np.pi * r**2 * d2 / (d2 + r**2)
        np.testing.assert_allclose(approx, exact, rtol=1e-4)
