"""Sensor model against photon counting by hand and noise statistics."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.errors import ParameterError
from gonio.simulator.scene import Camera
from gonio.simulator.sensor import cfa_indices, simulate_raw

H_PLANCK, C_LIGHT = 6.62607015e-34, 299792458.0


def camera(**sensor):
    return Camera(
        resolution=(200, 100),
        focal_length=0.05,
        pixel_pitch=4e-6,
        position=(0, 0, 1),
        sensor=dict(vignetting=False, **sensor),
    )


def expected_electrons(L, cam, t, N, channel):
    s = cam.sensor
    E = L * np.pi / (4 * N**2)
    photons = E * cam.pitch**2 * t * s.wavelength_nm[channel] * 1e-9 / (H_PLANCK * C_LIGHT)
    return photons * s.quantum_efficiency[channel]


def test_mean_and_variance_follow_photon_transfer():
    cam = camera(read_noise=4.0, dark_current=50.0)
    L, t, N, iso = 0.1, 0.02, 4.0, 400
    fr = simulate_raw(np.full((100, 200, 3), L), cam, exposure_time=t, f_number=N, iso=iso, seed=1)
    s = cam.sensor
    gain = s.gain_at_base_iso * iso / s.base_iso
    idx = cfa_indices("RGGB", (100, 200))
    for c in range(3):
        mu_e = expected_electrons(L, cam, t, N, c) + s.dark_current * t
        dn = fr.mosaic[idx == c].astype(float)
        mean, var = s.black_level + gain * mu_e, gain**2 * (mu_e + s.read_noise**2) + 1 / 12
        assert abs(dn.mean() - mean) < 4 * np.sqrt(var / dn.size)
        # sample variance of ~5000-10000 values: relative sd ~ sqrt(2 / n) < 2 %
        assert abs(dn.var(ddof=1) / var - 1) < 0.08
    assert fr.extra["gain_dn_per_electron"] == gain


def test_natural_vignetting_is_cos4():
    cam = Camera(
        resolution=(400, 4),
        focal_length=0.01,
        pixel_pitch=2e-5,
        position=(0, 0, 1),
        sensor=dict(
            read_noise=0.0,
            dark_current=0.0,
            full_well=1e9,
            bits=16,
            black_level=0,
            gain_at_base_iso=0.001,
        ),
    )
    fr = simulate_raw(np.full((4, 400, 3), 100.0), cam, seed=0)
    assert fr.mosaic.max() < 65535
    g = fr.mosaic[0, 1::2].astype(float)  # green sites of an RGGB first row
    u = np.arange(1, 400, 2) + 0.5 - 200
    cos4 = np.cos(np.arctan(u * 2e-5 / 0.01)) ** 4
    ratio = g / g[np.argmax(cos4)]
    assert np.allclose(ratio, cos4, atol=0.02)
    assert ratio[0] < 0.8  # the edge is clearly darker (cos^4(21.8 deg) = 0.74)


def test_clipping_at_full_well_and_white_level_and_black():
    cam = camera(read_noise=0.0, dark_current=0.0, bits=16)
    bright = simulate_raw(np.full((100, 200, 3), 1e6), cam, seed=0)
    assert np.all(bright.mosaic == round(512 + 40000 * 0.4))  # full well * gain
    hot = camera(read_noise=0.0, dark_current=0.0, gain_at_base_iso=2.0)
    assert np.all(simulate_raw(np.full((100, 200, 3), 1e6), hot, seed=0).mosaic == 16383)
    dark = simulate_raw(np.zeros((100, 200, 3)), cam, seed=0)
    assert np.all(dark.mosaic == 512)


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_cfa_sites_sample_their_channel(pattern):
    cam = camera(read_noise=0.0, dark_current=0.0, cfa_pattern=pattern)
    rad = np.zeros((100, 200, 3))
    rad[..., 0] = 0.5  # red only
    fr = simulate_raw(rad, cam, seed=2)
    red_sites = np.zeros((2, 2), bool)
    red_sites.flat[pattern.index("R")] = True
    red = np.tile(red_sites, (50, 100))
    assert np.all(fr.mosaic[red] > 800) and np.all(fr.mosaic[~red] == 512)
    assert fr.cfa_pattern == pattern


def test_same_seed_same_frame():
    cam = camera()
    rad = np.random.default_rng(0).uniform(0, 2, (100, 200, 3))
    a = simulate_raw(rad, cam, seed=11).mosaic
    assert np.array_equal(a, simulate_raw(rad, cam, seed=11).mosaic)
    assert not np.array_equal(a, simulate_raw(rad, cam, seed=12).mosaic)


def test_bad_settings_raise():
    with pytest.raises(ParameterError, match="exposure_time"):
        simulate_raw(np.zeros((100, 200, 3)), camera(), exposure_time=-1)
    with pytest.raises(ParameterError, match="shape"):
        simulate_raw(np.zeros((100, 200)), camera())


# --- issue 14.6: huge exposures and radiances saturate instead of crashing numpy ---------


@pytest.mark.parametrize("t", [1e308, float("inf"), 3600.001])
def test_exposure_beyond_an_hour_is_a_parameter_error(t):
    with pytest.raises(ParameterError, match="exposure_time"):
        simulate_raw(np.ones((4, 4, 3)), camera(), exposure_time=t)


def test_a_poisson_mean_beyond_numpy_saturates_at_the_full_well():
    cam = camera(read_noise=0.0)
    L = np.full((100, 200, 3), 1.0)
    L[10:20, 30:40] = 1e300  # numpy: "lam value too large" before the fix
    L[50, 50] = np.inf
    f = simulate_raw(L, cam, exposure_time=3600.0, seed=3)
    s = cam.sensor
    full = min(s.white_level, round(s.black_level + s.full_well * s.gain_at_base_iso))
    assert (f.mosaic[10:20, 30:40] == full).all() and f.mosaic[50, 50] == full


def test_ordinary_frames_are_the_plain_poisson_draws():
    # The guard must not change a frame whose means numpy can draw: same seed, same bytes
    # as a hand-written Poisson + read-noise pipeline.
    cam = camera()
    s = cam.sensor
    rng = np.random.default_rng(11)
    L = rng.uniform(0, 50, (100, 200, 3))
    f = simulate_raw(L, cam, exposure_time=0.01, f_number=4.0, iso=200, seed=5)
    mu3 = np.stack([expected_electrons(L[..., k], cam, 0.01, 4.0, k) for k in range(3)], -1)
    idx = cfa_indices(s.cfa_pattern, L.shape[:2])
    mu = np.take_along_axis(mu3, idx[..., None], axis=2)[..., 0] + s.dark_current * 0.01
    r = np.random.default_rng(5)
    e = r.poisson(mu).astype(float) + r.normal(0.0, s.read_noise, mu.shape)
    e = np.clip(e, None, s.full_well)
    dn = np.clip(np.rint(s.black_level + e * s.gain_at_base_iso * 200 / s.base_iso), 0,
                 s.white_level).astype(np.uint16)  # fmt: skip
    np.testing.assert_array_equal(f.mosaic, dn)
