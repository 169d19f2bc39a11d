"""The board pose's covariance (``CameraPose.covariance``) against the scatter of the
solved pose over independent noisy corner draws (Monte Carlo): the first-order formula
``sigma^2 (J^T J)^-1`` must describe how far ``solvePnP`` really lands."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gonio.capture.fiducials import BoardSpec, _solve

K = np.array([[900.0, 0, 320], [0, 900.0, 240], [0, 0, 1]])
DIST = np.array([-0.08, 0.02, 0.0005, -0.0003, 0.0])
SIGMA_PX = 0.3


def _truth(theta_deg: float):
    """A camera 0.45 m from the sample centre, theta off the normal, looking at it."""
    th = np.radians(theta_deg)
    C = 0.45 * np.array([np.sin(th) * np.cos(0.4), np.sin(th) * np.sin(0.4), np.cos(th)])
    z = -C / np.linalg.norm(C)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0, 0])
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in the sample frame (sample -> camera)
    return R, -R @ C


@pytest.mark.parametrize("theta_deg", [10.0, 55.0])
def test_the_pose_covariance_matches_the_monte_carlo_scatter(theta_deg):
    board = BoardSpec()
    cvb = board.cv_board()
    obj_b = np.asarray(cvb.getChessboardCorners(), float)
    ids = np.arange(len(obj_b))
    R_bs, t_bs = board.transform()
    obj_s = obj_b @ R_bs.T + t_bs
    R, t = _truth(theta_deg)
    rvec0 = cv2.Rodrigues(R)[0]
    clean, _ = cv2.projectPoints(obj_s, rvec0, t, K, DIST)
    clean = clean.reshape(-1, 2)
    rng = np.random.default_rng(int(theta_deg))
    est, covs = [], []
    for _ in range(400):
        pose = _solve(board, clean + rng.normal(0, SIGMA_PX, clean.shape), ids, K, DIST)
        est.append(np.concatenate([cv2.Rodrigues(pose.rotation)[0].ravel(), pose.translation]))
        covs.append(pose.covariance)
    est = np.array(est)
    truth = np.concatenate([rvec0.ravel(), t])
    scatter = np.cov(est.T)
    predicted = np.mean(covs, axis=0)
    # per coordinate: the reported std is the scatter's within the sampling error of a
    # std from 400 draws (~3.5 %; 15 % is > 4 of those)
    ratio = np.sqrt(np.diag(scatter) / np.diag(predicted))
    assert np.all(np.abs(ratio - 1) < 0.15), ratio
    # the correlations too: the errors whitened by the reported covariance are chi^2 with
    # 6 degrees of freedom (mean 6, its sampling error over 400 draws ~0.17)
    inv = np.linalg.inv(predicted)
    d = est - truth
    m2 = np.einsum("ni,ij,nj->n", d, inv, d)
    assert abs(m2.mean() - 6.0) < 0.7, m2.mean()
    # a pose error is neither negligible nor absurd: 1e-5..1e-2 rad here
    assert 1e-5 < np.sqrt(predicted[0, 0]) < 1e-2


@pytest.mark.parametrize("theta_deg", [10.0, 55.0])
def test_the_intrinsics_sensitivity_matches_a_resolved_pose(theta_deg):
    """The pose's first-order response to an intrinsics error, against solvePnP run again
    on the same corners with the moved intrinsics (one intrinsic at a time)."""
    board = BoardSpec()
    obj_b = np.asarray(board.cv_board().getChessboardCorners(), float)
    ids = np.arange(len(obj_b))
    R_bs, t_bs = board.transform()
    obj_s = obj_b @ R_bs.T + t_bs
    R, t = _truth(theta_deg)
    img, _ = cv2.projectPoints(obj_s, cv2.Rodrigues(R)[0], t, K, DIST)
    img = img.reshape(-1, 2)
    pose = _solve(board, img, ids, K, DIST)
    S = pose.intrinsics_sensitivity
    assert S.shape == (6, 9)

    def resolve(Kc, dc):  # an independent solve, converged far below the changes
        from scipy.optimize import least_squares

        def res(p):
            uv, _ = cv2.projectPoints(obj_s, p[:3], p[3:], Kc, dc)
            return (uv.reshape(-1, 2) - img).ravel()

        x0 = np.concatenate([cv2.Rodrigues(R)[0].ravel(), t])
        return least_squares(res, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15).x

    base = resolve(K, DIST)
    # px, then coefficients
    steps = [1.0, 1.0, 1.0, 1.0, 1e-2, 1e-1, 1e-3, 1e-3, 1e-1]
    for k, h in enumerate(steps):
        Kp, dp = K.copy(), DIST.copy()
        if k < 4:
            i, j = [(0, 0), (1, 1), (0, 2), (1, 2)][k]
            Kp[i, j] += h
        else:
            dp[k - 4] += h
        got = resolve(Kp, dp)
        want = S[:, k] * h
        # first order: the re-solved pose agrees to a few percent of the change
        assert np.linalg.norm(got - base - want) <= 0.03 * np.linalg.norm(want), k


def test_the_public_functions_give_what_the_solved_pose_carries():
    """``_solve`` computes the covariance and the intrinsics sensitivity from one
    Jacobian; each public function alone gives the same numbers, and NaN for too few
    points."""
    from gonio.capture.fiducials import pose_covariance, pose_intrinsics_sensitivity

    board = BoardSpec()
    obj_b = np.asarray(board.cv_board().getChessboardCorners(), float)
    R_bs, t_bs = board.transform()
    obj_s = obj_b @ R_bs.T + t_bs
    R, t = _truth(30.0)
    img, _ = cv2.projectPoints(obj_s, cv2.Rodrigues(R)[0], t, K, DIST)
    img = img.reshape(-1, 2) + np.random.default_rng(3).normal(0, SIGMA_PX, (len(obj_s), 2))
    img = img.astype(np.float32).astype(float)  # as _solve hands them to OpenCV
    pose = _solve(board, img, np.arange(len(obj_s)), K, DIST)
    cov = pose_covariance(obj_s, img, pose.rotation, pose.translation, K, DIST)
    sens = pose_intrinsics_sensitivity(obj_s, pose.rotation, pose.translation, K, DIST)
    assert cov.shape == (6, 6) and sens.shape == (6, 9)
    np.testing.assert_array_equal(cov, pose.covariance)
    np.testing.assert_array_equal(sens, pose.intrinsics_sensitivity)
    assert np.all(np.isfinite(cov)) and np.all(np.isfinite(sens))
    assert np.isnan(pose_covariance(obj_s[:3], img[:3], R, t, K, DIST)).all()
    assert np.isnan(pose_intrinsics_sensitivity(obj_s[:3], R, t, K, DIST)).all()
