"""Solid angles and irradiance against closed forms and brute-force quadrature."""

import functools

import numpy as np
import pytest
from scipy import integrate

from gonio.radiometry import (
    frame_from_normal,
    irradiance_disk,
    irradiance_point,
    irradiance_rectangle,
    normalize,
    solid_angle_cap,
    solid_angle_disk,
    solid_angle_element,
    solid_angle_rectangle,
)


def test_hemisphere_and_sphere():
    assert solid_angle_cap(np.pi / 2) == pytest.approx(2 * np.pi, rel=1e-15)
    assert solid_angle_cap(np.pi) == pytest.approx(4 * np.pi, rel=1e-15)
    # an infinite plane below a point fills a hemisphere
    assert solid_angle_disk([0, 0, 1.0], [0, 0, 0], [0, 0, 1], 1e9) == pytest.approx(
        2 * np.pi, rel=1e-8
    )
    # the six faces of a cube seen from its centre fill the sphere
    faces = [(a * s) for a in np.eye(3) for s in (1, -1)]
    total = sum(
        solid_angle_rectangle([0, 0, 0], f, f, np.roll(np.abs(f), 1), [2.0, 2.0]) for f in faces
    )
    assert total == pytest.approx(4 * np.pi, rel=1e-14)


def test_cap_small_angle_precision():
    a = 1e-9
    assert solid_angle_cap(a) == pytest.approx(np.pi * a**2, rel=1e-12)


@pytest.mark.parametrize("h,R", [(0.5, 0.01), (1.0, 1.0), (0.01, 3.0)])
def test_on_axis_disk(h, R):
    omega = solid_angle_disk([0, 0, 0], [0, 0, h], [0, 0, -1], R)
    assert omega == pytest.approx(2 * np.pi * (1 - h / np.hypot(h, R)), rel=1e-13)
    e = irradiance_disk([0, 0, 0], [0, 0, 1], [0, 0, h], [0, 0, -1], R, 3.0)
    assert e == pytest.approx(3.0 * np.pi * R**2 / (h**2 + R**2), rel=1e-12)


@functools.lru_cache(maxsize=8)
def _disk_frame(m: tuple[float, float, float]) -> np.ndarray:
    # dblquad calls the integrand ~10^5 times with one disk: building its frame on every
    # call was nine tenths of the reference's time (the same frame, bit for bit).
    return frame_from_normal(np.array(m))


def _disk_points(c, m, R, r, t):
    F = _disk_frame(tuple(float(v) for v in m))
    return c + r * (np.cos(t) * F[0] + np.sin(t) * F[1])


@pytest.mark.parametrize("seed", range(4))
def test_off_axis_disk_solid_angle_matches_quadrature(seed):
    rng = np.random.default_rng(seed)
    p, c = rng.normal(size=3), 0.5 * rng.normal(size=3)
    m, R = normalize(rng.normal(size=3)), rng.uniform(0.2, 1.5)

    def f(r, t):
        d = _disk_points(c, m, R, r, t) - p
        return abs(d @ m) / np.linalg.norm(d) ** 3 * r

    ref = integrate.dblquad(f, 0, 2 * np.pi, 0, R, epsabs=1e-14, epsrel=1e-12)[0]
    assert solid_angle_disk(p, c, m, R) == pytest.approx(ref, rel=1e-10)


def test_disk_solid_angle_on_the_rim_and_outside_continuity():
    h, R = 0.3, 1.0
    rho = np.array([1 - 1e-9, 1.0, 1 + 1e-9])
    pts = np.stack([rho, 0 * rho, h + 0 * rho], axis=-1)
    omega = solid_angle_disk(pts, [0, 0, 0], [0, 0, 1], R)
    np.testing.assert_allclose(omega, omega[1], rtol=1e-7)


@pytest.mark.parametrize("seed", range(4))
def test_disk_irradiance_matches_quadrature_when_fully_visible(seed):
    rng = np.random.default_rng(100 + seed)
    c = np.array([0.0, 0.0, 1.0]) + 0.3 * rng.normal(size=3)
    m = normalize(np.array([0, 0, -1.0]) + 0.4 * rng.normal(size=3))
    n = normalize(np.array([0, 0, 1.0]) + 0.3 * rng.normal(size=3))
    R = 0.2

    def f(r, t):
        x = _disk_points(c, m, R, r, t)
        d = x
        dist = np.linalg.norm(d)
        return max(d @ n / dist, 0) * max(-d @ m / dist, 0) / dist**2 * r

    ref = integrate.dblquad(f, 0, 2 * np.pi, 0, R, epsabs=1e-15, epsrel=1e-12)[0]
    assert irradiance_disk([0, 0, 0], n, c, m, R, 1.0) == pytest.approx(ref, rel=1e-10)


def test_disk_crossing_the_horizon_is_clipped_exactly():
    # A vertical disk half above the receiver plane: by symmetry, its irradiance is the
    # (closed-form) irradiance of the rectangle-free half... compare with quadrature over
    # the upper half only, where the integrand is smooth.
    c, m, R = np.array([0.0, 1.0, 0.0]), np.array([0.0, -1.0, 0.0]), 0.5

    def f(r, t):
        x = c + r * np.array([np.cos(t), 0.0, np.sin(t)])
        dist = np.linalg.norm(x)
        return (x[2] / dist) * (x[1] / dist) / dist**2 * r

    ref = integrate.dblquad(f, 0, np.pi, 0, R, epsabs=1e-15, epsrel=1e-12)[0]
    assert irradiance_disk([0, 0, 0], [0, 0, 1], c, m, R, 1.0) == pytest.approx(ref, rel=1e-10)


def test_large_disk_gives_pi_L():
    assert irradiance_disk([0, 0, 0], [0, 0, 1], [0, 0, 1], [0, 0, -1], 1e7, 2.0) == pytest.approx(
        2 * np.pi, rel=1e-9
    )


@pytest.mark.parametrize("W,H,h", [(1.0, 2.0, 0.5), (0.1, 0.1, 2.0), (3.0, 0.2, 1.0)])
def test_parallel_rectangle_corner_form_factor(W, H, h):
    # Classical form factor from a differential area below the corner of a parallel
    # rectangle (e.g. Howell's catalogue, configuration B-3).
    a, b = W / h, H / h
    F = (
        a / np.sqrt(1 + a**2) * np.arctan(b / np.sqrt(1 + a**2))
        + b / np.sqrt(1 + b**2) * np.arctan(a / np.sqrt(1 + b**2))
    ) / (2 * np.pi)
    e = irradiance_rectangle(
        [0, 0, 0], [0, 0, 1], [W / 2, H / 2, h], [0, 0, -1], [1, 0, 0], [W, H], 1.0
    )
    assert e == pytest.approx(np.pi * F, rel=1e-13)


def test_rectangle_crossing_horizon_and_back_side():
    # A vertical square straddling the receiver plane: only the upper half counts.
    full = irradiance_rectangle([0, 0, 0], [0, 0, 1], [0, 1, 0], [0, -1, 0], [1, 0, 0], [1, 1], 1)
    upper = irradiance_rectangle(
        [0, 0, 0], [0, 0, 1], [0, 1, 0.25], [0, -1, 0], [1, 0, 0], [1, 0.5], 1
    )
    assert full == pytest.approx(upper, rel=1e-13) and full > 0
    # Seen from behind, a one-sided emitter gives nothing.
    assert (
        irradiance_rectangle([0, 0, 0], [0, 0, 1], [0, 0, 1], [0, 0, 1], [1, 0, 0], [1, 1], 1)
        == 0.0
    )


def test_point_source_inverse_square_and_cosine_laws():
    I = 2.0
    r = np.array([0.5, 1.0, 2.0])
    pts = np.zeros((3, 3))
    src = np.stack([0 * r, 0 * r, r], axis=-1)
    e = irradiance_point(pts, [0, 0, 1], src, I)
    np.testing.assert_allclose(e * r**2, I, rtol=1e-15)
    theta = np.linspace(0, np.pi, 7)
    normals = np.stack([np.sin(theta), 0 * theta, np.cos(theta)], axis=-1)
    e = irradiance_point([0, 0, 0], normals, [0, 0, 1.0], I)
    np.testing.assert_allclose(e, I * np.maximum(np.cos(theta), 0), atol=1e-15)


def test_solid_angle_element_matches_small_disk():
    A, d = 1e-8, 0.7
    small = solid_angle_disk([0, 0, 0], [0, 0, d], [0, 0, 1], np.sqrt(A / np.pi))
    assert solid_angle_element(A, 1.0, d) == pytest.approx(small, rel=1e-7)


def test_vectorised_over_many_points():
    pts = np.random.default_rng(0).normal(size=(50, 7, 3)) * 0.1
    e = irradiance_disk(pts, [0, 0, 1], [0, 0, 1.0], [0, 0, -1], 0.05, 1.0)
    assert e.shape == (50, 7) and np.all(e > 0)
    omega = solid_angle_rectangle(pts, [0, 0, 1.0], [0, 0, -1], [1, 0, 0], [0.1, 0.2])
    assert omega.shape == (50, 7)


def test_nan_in_nan_out(recwarn):
    assert np.isnan(solid_angle_disk([np.nan, 0, 1], [0, 0, 0], [0, 0, 1], 1.0))
    pts = [[np.nan, 0, 0], [0, 0, 0]]
    e = irradiance_disk(pts, [0, 0, 1], [0, 0, 0.5], [0, 0, -1], 0.01, 1.0)
    assert np.isnan(e[0]) and e[1] > 0
    e = irradiance_rectangle(pts, [0, 0, 1], [0, 0, 0.5], [0, 0, -1], [1, 0, 0], [0.1, 0.1], 1)
    assert np.isnan(e[0]) and e[1] > 0
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def test_adaptive_rim_quadrature_matches_a_fine_rule_near_and_far():
    rng = np.random.default_rng(5)
    for scale in (0.03, 0.3, 3.0):  # receivers far from, near and around the rim
        pts = rng.normal(size=(200, 3)) * scale
        pts[:, 2] = 0.0
        auto = irradiance_disk(pts, [0, 0, 1], [0, 0.1, 0.3], [0, -0.3, -1], 0.05, 1.0)
        fine = irradiance_disk(
            pts, [0, 0, 1], [0, 0.1, 0.3], [0, -0.3, -1], 0.05, 1.0, n_nodes=4096
        )
        np.testing.assert_allclose(auto, fine, rtol=1e-11, atol=1e-300)
