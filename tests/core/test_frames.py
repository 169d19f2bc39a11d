"""Frames, spherical coordinates, reflection and Rusinkiewicz coordinates."""

import numpy as np
import pytest

from gonio.radiometry import (
    direction_to_spherical,
    directions_from_half_diff,
    frame_from_normal,
    half_diff_from_directions,
    normalize,
    reflect,
    spherical_to_direction,
    to_local,
    to_world,
)

rng = np.random.default_rng(12)


def upper(n):
    v = normalize(rng.normal(size=(n, 3)))
    v[:, 2] = np.abs(v[:, 2])
    return v


def test_spherical_round_trip_and_known_values():
    theta = rng.uniform(0, np.pi, 1000)
    phi = rng.uniform(-np.pi, np.pi, 1000)
    w = spherical_to_direction(theta, phi)
    np.testing.assert_allclose(np.linalg.norm(w, axis=-1), 1.0, atol=1e-15)
    t2, p2 = direction_to_spherical(w)
    np.testing.assert_allclose(t2, theta, atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (p2 - phi))), 0.0, atol=1e-12)
    np.testing.assert_allclose(spherical_to_direction(np.pi / 2, np.pi / 2), [0, 1, 0], atol=1e-16)
    assert direction_to_spherical([0.0, 0.0, 1.0]) == (0.0, 0.0)


def test_reflect_is_an_involution_and_mirrors_about_z():
    w = upper(100)
    r = reflect(w)
    np.testing.assert_allclose(r[:, :2], -w[:, :2])
    np.testing.assert_allclose(r[:, 2], w[:, 2])
    np.testing.assert_allclose(reflect(r), w, atol=1e-15)


@pytest.mark.parametrize("with_tangent", [False, True])
def test_frames_are_orthonormal_and_round_trip(with_tangent):
    n = normalize(rng.normal(size=(500, 3)))
    n[0] = [0, 0, -1]  # the branch point of the branchless basis
    n[1] = [0, 0, 1]
    t = rng.normal(size=(500, 3)) if with_tangent else None
    F = frame_from_normal(n, t)
    np.testing.assert_allclose(F @ np.swapaxes(F, -1, -2), np.broadcast_to(np.eye(3), F.shape),
                               atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-14)  # right-handed
    np.testing.assert_allclose(F[:, 2], n, atol=1e-15)
    v = rng.normal(size=(500, 3))
    np.testing.assert_allclose(to_world(to_local(v, F), F), v, atol=1e-14)
    np.testing.assert_allclose(to_local(n, F), np.tile([0, 0, 1.0], (500, 1)), atol=1e-14)


def test_half_diff_known_values():
    a = 0.3
    wi = [np.sin(a), 0, np.cos(a)]
    wo = [-np.sin(a), 0, np.cos(a)]
    th, ph, td, pd = half_diff_from_directions(wi, wo)
    assert th == pytest.approx(0.0, abs=1e-15)
    assert td == pytest.approx(a, abs=1e-15)
    # wi == wo: the half vector is wi itself and the difference angle is 0
    th, ph, td, pd = half_diff_from_directions(wi, wi)
    assert th == pytest.approx(a) and ph == pytest.approx(0.0) and td == pytest.approx(0.0)


def test_half_diff_round_trip_both_ways():
    wi, wo = upper(2000), upper(2000)
    back_i, back_o = directions_from_half_diff(*half_diff_from_directions(wi, wo))
    np.testing.assert_allclose(back_i, wi, atol=1e-13)
    np.testing.assert_allclose(back_o, wo, atol=1e-13)
    th = rng.uniform(0, np.pi / 2, 1000)
    ph = rng.uniform(-np.pi, np.pi, 1000)
    td = rng.uniform(0, np.pi / 2, 1000)
    pd = rng.uniform(-np.pi, np.pi, 1000)
    angles = half_diff_from_directions(*directions_from_half_diff(th, ph, td, pd))
    np.testing.assert_allclose(angles[0], th, atol=1e-12)
    np.testing.assert_allclose(angles[2], td, atol=1e-12)
    np.testing.assert_allclose(np.cos(angles[1] - ph), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.cos(angles[3] - pd), 1.0, atol=1e-12)


def test_nan_in_nan_out():
    w = np.array([[np.nan, 0, 1.0], [0, 0, 1.0]])
    theta, phi = direction_to_spherical(w)
    assert np.isnan(theta[0]) and theta[1] == 0.0
    assert np.isnan(normalize([0.0, 0.0, 0.0])).all()
    out = half_diff_from_directions(w, w)
    assert np.isnan(out[0][0]) and np.isfinite(out[0][1])


def test_bad_shape_is_a_clear_error():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        normalize(np.zeros((4, 2)))
