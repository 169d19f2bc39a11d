"""Frames, spherical coordinates, reflection and Rusinkiewicz coordinates."""

import numpy as np
import pytest

from gonio.radiometry import (
    angle_between,
    direction_to_spherical,
    directions_from_half_diff,
    frame_from_normal,
    half_diff_from_directions,
    look_along_rotation,
    look_at_rotation,
    normalize,
    reflect,
    rotation_about,
    rotation_angle,
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
    np.testing.assert_allclose(
        F @ np.swapaxes(F, -1, -2), np.broadcast_to(np.eye(3), F.shape), atol=1e-14
    )
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


# --- rotations, angles and camera frames: the helpers the rig, the fiducials and the scene
# share.  References: scipy.spatial.transform.Rotation and closed forms.
def test_rotation_about_equals_scipy_rotvec_batched_and_broadcast():
    from scipy.spatial.transform import Rotation

    axes = normalize(rng.normal(size=(4, 5, 3)))
    angles = rng.uniform(-2 * np.pi, 2 * np.pi, size=(4, 5))
    R = rotation_about(axes, angles)
    assert R.shape == (4, 5, 3, 3)
    ref = Rotation.from_rotvec((axes * angles[..., None]).reshape(-1, 3)).as_matrix()
    np.testing.assert_allclose(R.reshape(-1, 3, 3), ref, atol=4e-15)
    # one axis, many angles (the rig's stage joints)
    z = rotation_about([0.0, 0.0, 1.0], angles[0])
    assert z.shape == (5, 3, 3)
    c, s = np.cos(angles[0]), np.sin(angles[0])
    np.testing.assert_allclose(z[:, 0, :2], np.stack([c, -s], -1), atol=1e-15)
    assert np.isnan(rotation_about([np.nan, 0.0, 1.0], 0.3)).any()
    assert np.isnan(rotation_about([0.0, 0.0, 1.0], np.nan)).all(axis=(-2, -1)).any()


def test_rotation_angle_equals_scipy_magnitude():
    from scipy.spatial.transform import Rotation

    r1 = Rotation.random(200, random_state=1)
    r2 = Rotation.random(200, random_state=2)
    R1, R2 = r1.as_matrix(), r2.as_matrix()
    np.testing.assert_allclose(rotation_angle(R1), r1.magnitude(), atol=1e-7)
    between = rotation_angle(R1 @ np.swapaxes(R2, -1, -2))
    np.testing.assert_allclose(between, (r1 * r2.inv()).magnitude(), atol=1e-7)
    assert rotation_angle(np.eye(3)) == 0.0
    assert rotation_angle(np.diag([1.0, -1.0, -1.0])) == pytest.approx(np.pi, abs=1e-15)
    assert np.isnan(rotation_angle(np.full((3, 3), np.nan)))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\)"):
        rotation_angle(np.eye(2))


def test_angle_between_closed_forms():
    x = np.array([1.0, 0.0, 0.0])
    assert angle_between(x, x) == 0.0
    assert angle_between(x, [0.0, 2.0, 0.0]) == pytest.approx(np.pi / 2, abs=1e-16)
    assert angle_between(x, -x) == pytest.approx(np.pi, abs=1e-16)
    # accurate where arccos of the dot product is not: 1e-10 rad and pi - 1e-10 rad
    for e in (1e-10, 1e-5):
        w = np.array([np.cos(e), np.sin(e), 0.0])
        assert angle_between(x, w) == pytest.approx(e, rel=1e-14)
        assert angle_between(-x, w) == pytest.approx(np.pi - e, rel=1e-15)
    a, b = rng.normal(size=(2, 50, 3))
    ref = np.arccos(np.clip(np.sum(normalize(a) * normalize(b), -1), -1, 1))
    np.testing.assert_allclose(angle_between(3.0 * a, b), ref, atol=1e-7)
    assert np.isnan(angle_between([np.nan, 0, 1], x))


def _scipy_camera(forward, up):
    """Camera-to-world rotation with z on ``forward`` exactly and -y as close to ``up``."""
    from scipy.spatial.transform import Rotation

    rot, _ = Rotation.align_vectors(
        [forward, up], [[0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], weights=[np.inf, 1.0]
    )
    return rot.as_matrix()


def test_look_at_rotation_equals_scipy_alignment():
    positions = rng.normal(size=(30, 3))
    target = np.array([0.01, -0.02, 0.0])
    ups = rng.normal(size=(30, 3))
    R = look_at_rotation(positions, target, ups)
    assert R.shape == (30, 3, 3)
    for p, u, r in zip(positions, ups, R, strict=True):
        f = (target - p) / np.linalg.norm(target - p)
        np.testing.assert_allclose(r.T, _scipy_camera(f, u), atol=1e-12)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-15
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-15)
    np.testing.assert_allclose(look_along_rotation(R[:, 2], ups), R, atol=0)


def test_look_at_rotation_closed_forms_fallback_and_nan():
    # overhead camera, image up +y: right +x, down -y, forward -z
    R = look_at_rotation([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0])
    np.testing.assert_array_equal(R, [[1, 0, 0], [0, -1, 0], [0, 0, -1]])
    # up parallel to the view: the world's +y takes its place, then +x
    np.testing.assert_array_equal(look_at_rotation([0, 0, 1.0], [0, 0, 0.0]), R)
    Rx = look_at_rotation([0, 2.0, 0], [0, 0, 0.0], up=[0, 1.0, 0])
    np.testing.assert_allclose(Rx, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-16)
    assert np.isnan(look_at_rotation([1.0, 0, 0], [1.0, 0, 0])).all()
    assert np.isnan(look_at_rotation([np.nan, 0, 1], [0, 0, 0.0])).all()
    assert np.isnan(look_at_rotation([0, 0, 1.0], [0, 0, 0.0], up=[np.nan, 0, 1])).all()
