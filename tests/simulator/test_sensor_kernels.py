"""The sensor's fused kernels against its numpy path (issue 19.2): the same bytes.

The numpy path (``GONIO_NUMBA=0``) is the reference: the kernels must reproduce it bit
for bit (the noise draws are numpy's in both), on a realistic world's frame (distortion,
vignetting, PRNU, DSNU, hot pixels), without fixed patterns, without read noise, and with
means beyond numpy's Poisson range.  ``test_sensor.py`` holds the numpy path against a
hand-written photon-counting pipeline and the noise statistics.
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.simulator.rig_camera import minimal_scene
from gonio.simulator.scene import Camera, parse_scene
from gonio.simulator.sensor import _MIN_KERNEL_SITES, simulate_mosaic
from gonio.simulator.sensor_defects import fixed_pattern
from gonio.simulator.world import draw_world


@pytest.fixture(scope="module")
def realistic():
    """A realistic world's as-built camera (lens distortion: vignetting from the true
    ray) with its fixed patterns, and a site radiance spanning dark to saturated."""
    world = draw_world("realistic", 5)
    cam = world.as_built_camera(parse_scene(minimal_scene(160, 120)).camera)
    # more hot pixels than the draw's 1e-4..5e-4 (a few in 19200 sites, maybe none)
    radiometry = world.radiometry.model_copy(update={"hot_pixel_fraction": 0.01})
    pattern = fixed_pattern(radiometry, world.seed, (120, 160))
    assert pattern.gain is not None and pattern.dark_offset is not None
    assert len(pattern.hot_index) > 0
    rng = np.random.default_rng(3)
    sites = rng.uniform(0.0, 2.0, (120, 160)) ** 4  # many sites near 0 e-, some at 1e4+
    sites[:5, :5] = 0.0
    return cam, pattern, sites


def _both(monkeypatch, sites, cam, **kw):
    monkeypatch.setenv("GONIO_NUMBA", "0")
    ref = simulate_mosaic(sites, cam, seed=np.random.default_rng(7), **kw).mosaic
    monkeypatch.setenv("GONIO_NUMBA", "1")
    fast = simulate_mosaic(sites, cam, seed=np.random.default_rng(7), **kw).mosaic
    return fast, ref


@pytest.mark.parametrize("t", [1e-4, 0.01, 0.3, 30.0])
def test_kernel_mosaic_is_the_numpy_mosaic_with_fixed_patterns(realistic, monkeypatch, t):
    cam, pattern, sites = realistic
    assert sites.size >= _MIN_KERNEL_SITES  # the kernel path runs
    fast, ref = _both(monkeypatch, sites, cam, exposure_time=t, iso=400, f_number=4.0,
                      fixed_pattern=pattern)  # fmt: skip
    assert fast.dtype == ref.dtype == np.uint16
    # the frame exercises what the kernels do: black, mid-range, clipped sites
    assert (ref == cam.sensor.white_level).any() or t < 1.0
    assert len(np.unique(ref)) > 50
    np.testing.assert_array_equal(fast, ref)


def test_kernel_mosaic_without_fixed_patterns_or_read_noise(realistic, monkeypatch):
    cam, _, sites = realistic
    fast, ref = _both(monkeypatch, sites, cam, exposure_time=0.05)
    np.testing.assert_array_equal(fast, ref)
    quiet = cam.model_copy(update={"sensor": cam.sensor.model_copy(update={"read_noise": 0.0})})
    fast, ref = _both(monkeypatch, sites, quiet, exposure_time=0.05)
    np.testing.assert_array_equal(fast, ref)


def test_kernel_saturates_means_beyond_numpy_like_the_numpy_path(monkeypatch):
    cam = Camera(resolution=(100, 50), focal_length=0.05, pixel_pitch=4e-6,
                 position=(0, 0, 1), sensor={"read_noise": 0.0})  # fmt: skip
    sites = np.full((50, 100), 1.0)
    sites[10:20, 30:40] = 1e300
    fast, ref = _both(monkeypatch, sites, cam, exposure_time=3600.0)
    s = cam.sensor
    full = min(s.white_level, round(s.black_level + s.full_well * s.gain_at_base_iso))
    assert (ref[10:20, 30:40] == full).all()
    np.testing.assert_array_equal(fast, ref)


def test_hot_map_holds_the_hot_pixels_current(realistic):
    _, pattern, _ = realistic
    m = pattern.hot_map()
    assert m.shape == (120 * 160,) and not m.flags.writeable
    np.testing.assert_array_equal(np.flatnonzero(m), pattern.hot_index)
    np.testing.assert_array_equal(m[pattern.hot_index], pattern.hot_current)
    assert pattern.hot_map() is m  # built once


def test_kernel_read_noise_draws_and_advances_the_generator_as_numpy(realistic, monkeypatch):
    # the read noise is drawn inside the kernel (numba's Generator.normal): the same
    # numbers as rng.normal(0, read_noise, n), and the caller's generator left where the
    # numpy path leaves it (a caller that goes on drawing sees the same stream)
    cam, pattern, sites = realistic
    assert cam.sensor.read_noise > 0
    gens = {}
    for flag in ("0", "1"):
        monkeypatch.setenv("GONIO_NUMBA", flag)
        g = np.random.default_rng(11)
        m = simulate_mosaic(sites, cam, exposure_time=0.02, seed=g, fixed_pattern=pattern)
        gens[flag] = (m.mosaic, g.random(4))
    np.testing.assert_array_equal(gens["1"][0], gens["0"][0])
    np.testing.assert_array_equal(gens["1"][1], gens["0"][1])
