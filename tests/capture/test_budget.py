"""The uncertainty budget's pieces (:mod:`gonio.capture.budget`) against independent
references.

- The geometric modes: their summed outer products must be the covariance of ``(wi, wo)``
  that first-order propagation gives, ``J C J^T``, with ``J`` a per-parameter finite
  difference through the rig's kinematics (one parameter at a time, not the modes'
  eigen-steps) and the moved camera's sample-plane point from the homography
  ``K [r1 r2 t]`` (not the budget's ray intersection).
- The model-free gradient: on samples of an analytic model (a measurement's pattern: 3 x
  3 regions per pose on a 10 degree pose grid), the BRDF change it predicts along random
  modes against the model's own central difference (``gonio.brdf`` eval), for a
  moderate and a near-mirror lobe.
- The isotropic chart (a material declared isotropic): its features against their
  closed form in ``(theta_i, theta_o, phi_o - phi_i)``, its Jacobian against central
  differences, and the gradient fitted on it against a closed-form lobe's analytic
  gradient (a Phong lobe about the mirror direction) on a session's pattern.
- The budget's summary rows against a hand computation.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.capture.budget import (
    POSE_MODE_NAMES,
    budget_rows,
    budget_table,
    centroid_points,
    direction_variance,
    geometry_std,
    isotropic_features,
    isotropic_jacobian,
    local_log_gradient,
    pose_modes,
    rig_shifts,
    session_modes,
)
from gonio.capture.fiducials import CameraPose
from gonio.rig.asbuilt import rig_poses
from gonio.rig.calibration import PARAMETER_NAMES, PARAMETERS, apply_parameters
from gonio.rig.calibration_record import (
    CalibrationRecord,
    ParameterCovariance,
    ParameterEstimate,
    rig_digest,
)
from gonio.rig.config import JOINT_NAMES, default_rig_config

NOMINAL = default_rig_config()
K = np.array([[900.0, 0, 320], [0, 900.0, 240], [0, 0, 1]])
INTR = ("fx", "fy", "cx", "cy")
INTR_STD = np.array([1.5, 1.5, 1.0, 1.0])


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _calibrated_rig(seed=3, scale=1.0):
    """A calibrated rig: as-built values, and a random (correlated) covariance over every
    rig parameter and fx, fy, cx, cy at a few percent of the parameters' magnitudes
    (times ``scale``)."""
    rng = np.random.default_rng(seed)
    values = {n: rng.normal(0, 0.3 * PARAMETERS[n].magnitude) for n in PARAMETER_NAMES}
    for j in JOINT_NAMES:
        values[f"{j}.backlash"] = abs(values[f"{j}.backlash"])
    g = NOMINAL.geometry
    values["light_elevation"] += g.light_elevation_deg
    values["camera_elevation"] += g.camera_elevation_deg
    values["camera_radius"] += g.camera_radius_m
    names = list(PARAMETER_NAMES) + list(INTR)
    sd = scale * np.array(
        [0.03 * PARAMETERS[n].magnitude for n in PARAMETER_NAMES] + list(INTR_STD)
    )
    A = rng.normal(size=(len(names), len(names)))
    S = A @ A.T + len(names) * np.eye(len(names))
    corr = S / np.sqrt(np.outer(np.diag(S), np.diag(S)))
    cov = corr * np.outer(sd, sd)
    rec = CalibrationRecord(
        created="2026-01-01T00:00:00+00:00",
        nominal_digest=rig_digest(NOMINAL),
        parameters={
            n: ParameterEstimate(value=values[n], std=sd[i], unit=PARAMETERS[n].unit)
            for i, n in enumerate(PARAMETER_NAMES)
        },
        covariance=ParameterCovariance(names=names, matrix=cov.tolist()),
        nominal=NOMINAL.model_dump(mode="json", exclude={"calibration"}, exclude_none=True),
    )
    rig = apply_parameters(NOMINAL, values).model_copy(update={"calibration": rec})
    return rig, values, names, cov


JOINTS = {"light_azimuth": -0.6, "camera_azimuth": 0.9, "stage_tilt": 0.35, "stage_spin": 1.2}
APPROACH = {"light_azimuth": 1, "camera_azimuth": -1, "stage_tilt": 1, "stage_spin": 1}


def _rig_at(values, joints, name=None, h=0.0):
    """Light centre, camera centre and sample->camera rotation with one parameter moved:
    joints read with the rig's zeros sit at reading + offset step."""
    v = dict(values)
    q = dict(joints)
    if name is not None and name in v:
        v[name] += h
        if name.endswith(".offset"):
            q[name.split(".")[0]] += math.radians(h)
    rp = rig_poses(apply_parameters(NOMINAL, v, validate=False), q, APPROACH)
    return rp.light_position, rp.camera_position, rp.camera_rotation.T


def _regions(C, R):
    """3 x 3 region centroids on the sample and their measured directions."""
    g = np.linspace(-0.012, 0.012, 3)
    X, Y = np.meshgrid(g, g)
    return np.stack([X.ravel(), Y.ravel(), np.zeros(9)], axis=1)


def _directions_via_homography(L, C, R, Kc, pix):
    """(wi, wo) of the sample points the pixels ``pix`` see, from the plane homography."""
    t = -R @ C
    H = Kc @ np.stack([R[:, 0], R[:, 1], t], axis=1)
    xy = np.linalg.solve(H, np.concatenate([pix, np.ones((len(pix), 1))], axis=1).T).T
    x = np.concatenate([xy[:, :2] / xy[:, 2:], np.zeros((len(pix), 1))], axis=1)
    return np.concatenate([_unit(L - x), _unit(C - x)], axis=1)


def _K_moved(name, h):
    Kc = K.copy()
    i, j = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}[name]
    Kc[i, j] += h
    return Kc


@pytest.mark.parametrize("source", ["board", "rig"])
def test_session_modes_give_the_propagated_covariance(source):
    rig, values, names, cov = _calibrated_rig()
    modes = session_modes(rig)
    assert modes.source == "calibration" and len(modes) == len(names)
    L, C, R = _rig_at(values, JOINTS)
    x = _regions(C, R)
    wi, wo = _unit(L - x), _unit(C - x)
    cam = CameraPose(R, -R @ C, C, 0.1, 24)
    shifts = rig_shifts(modes, [JOINTS], [APPROACH])
    m = pose_modes(wi, wo, cam, L, source=source, session=modes, shifts=shifts.at(0), K=K)
    assert m.shape == (9, len(names) + 6, 6)
    assert np.all(m[:, len(names) :] == 0)  # no board covariance given: no pose modes
    got = np.einsum("nmi,nmj->nij", m[:, : len(names)], m[:, : len(names)])
    # the reference: d(wi, wo)/d(parameter), one parameter at a time (central, small step)
    pix = (x @ R.T + (-R @ C)) @ K.T
    pix = pix[:, :2] / pix[:, 2:]
    J = np.zeros((9, 6, len(names)))
    for k, name in enumerate(names):
        h = 1e-4 * (PARAMETERS[name].magnitude if name in PARAMETERS else 1.0)
        side = []
        for s in (1.0, -1.0):
            Lp, Cp, Rp = _rig_at(values, JOINTS, name, s * h)
            if source == "board":  # the camera is the board's: only the light moves
                side.append(np.concatenate([_unit(Lp - x), wo], axis=1))
            else:
                Kc = _K_moved(name, s * h) if name in INTR else K
                side.append(_directions_via_homography(Lp, Cp, Rp, Kc, pix))
        J[:, :, k] = (side[0] - side[1]) / (2 * h)
    want = np.einsum("nik,kl,njl->nij", J, cov, J)
    scale = np.max(np.abs(want))
    assert scale > 1e-9  # the rig's uncertainty does move the directions
    np.testing.assert_allclose(got, want, atol=0.02 * scale)
    if source == "board":
        assert np.all(m[:, :, 3:] == 0)  # wo is the board's
    else:  # the intrinsics move the camera's rays: wo changes too
        assert np.max(np.abs(m[:, :, 3:])) > 1e-6


def test_without_a_record_the_nominal_joint_tolerance_moves_each_joint():
    modes = session_modes(NOMINAL, nominal_joint_std_deg=0.2)
    assert modes.source == "nominal" and len(modes) == len(JOINT_NAMES)
    shifts = rig_shifts(modes, [JOINTS], [APPROACH])
    L0 = rig_poses(NOMINAL, JOINTS, APPROACH).light_position
    # the light moves by 0.2 deg of its azimuth on the light's own mode (arc length)
    k = [n.endswith("light_azimuth.offset") for n in modes.names].index(True)
    step = np.linalg.norm(shifts.light[k, 0, 0] - L0)
    ang = math.degrees(step / np.linalg.norm(L0))
    assert 0.02 < ang <= 0.2 + 1e-9
    # a pose without joints gets no session modes, not an error
    shifts = rig_shifts(modes, [None], [None])
    assert np.isnan(shifts.light).all()


@pytest.mark.parametrize("calibrated", [True, False])
def test_rig_shifts_of_a_pose_do_not_depend_on_the_batch(calibrated):
    """The reduction computes every pose's shifts in one batch and reuses them for the
    budget, which used to compute them again over the sample poses alone: a pose's
    numbers must be the same bits in any batch."""
    rig = _calibrated_rig()[0] if calibrated else NOMINAL
    modes = session_modes(rig, nominal_joint_std_deg=0.1)
    rng = np.random.default_rng(5)
    joints = [{j: JOINTS[j] + rng.normal(0, 0.2) for j in JOINT_NAMES} for _ in range(7)]
    joints[3] = None  # a pose without joints in the batch changes nothing either
    approach = [APPROACH] * 7
    whole = rig_shifts(modes, joints, approach)
    for k in (0, 2, 6):
        alone = rig_shifts(modes, [joints[k]], [approach[k]])
        some = rig_shifts(modes, [joints[5], joints[k]], [approach[5], approach[k]])
        for a, b, c in zip(whole.at(k), alone.at(0), some.at(1), strict=True):
            assert np.array_equal(a, b) and np.array_equal(a, c)


def _board_camera(seed, C, rot_std, trans_std):
    """A camera at ``C`` looking at the origin, with a random (correlated) board pose
    covariance of about ``rot_std`` (rad) and ``trans_std`` (m)."""
    rng = np.random.default_rng(seed)
    z = _unit(-C)
    xa = _unit(np.cross(z, [0.0, 0, 1]))
    R = np.stack([xa, np.cross(z, xa), z])
    A = rng.normal(size=(6, 6))
    cov = (A @ A.T + 6 * np.eye(6)) * np.array([rot_std] * 3 + [trans_std] * 3) ** 2 / 6
    return CameraPose(R, -R @ C, C, 0.1, 24, 0.5 * (cov + cov.T))


def _board_jacobian(L, C, R, x):
    """(n, 6, 6) d(wi, wo)/d(rvec, tvec) of a board pose at the sample points ``x``, by
    central differences through the plane homography."""
    t = -R @ C
    pix = (x @ R.T + t) @ K.T
    pix = pix[:, :2] / pix[:, 2:]
    rvec = cv2.Rodrigues(R)[0].ravel()
    J = np.zeros((len(x), 6, 6))
    for k in range(6):
        h = 1e-7
        side = []
        for s in (1.0, -1.0):
            dp = np.zeros(6)
            dp[k] = s * h
            Rp = cv2.Rodrigues(rvec + dp[:3])[0]
            side.append(_directions_via_homography(L, -Rp.T @ (t + dp[3:]), Rp, K, pix))
        J[:, :, k] = (side[0] - side[1]) / (2 * h)
    return J


def test_board_pose_modes_give_the_pose_covariance_propagated():
    C = np.array([0.15, -0.2, 0.35])
    cam = _board_camera(5, C, 1e-4, 3e-4)
    R, cov = cam.rotation, cam.covariance
    L = np.array([-0.1, 0.2, 0.4])
    x = _regions(C, R)
    wi, wo = _unit(L - x), _unit(C - x)
    m = pose_modes(wi, wo, cam, L, source="board")
    assert m.shape == (9, 6, 6)
    got = np.einsum("nmi,nmj->nij", m, m)
    J = _board_jacobian(L, C, R, x)
    want = np.einsum("nik,kl,njl->nij", J, cov, J)
    np.testing.assert_allclose(got, want, atol=0.02 * np.max(np.abs(want)))
    # a rig-sourced pose has no board modes; "none" has no modes at all
    assert np.all(pose_modes(wi, wo, cam, L, source="rig") == 0)
    assert np.all(pose_modes(wi, wo, cam, L, source="none") == 0)


ROI_HALF = (0.012, 0.009)


def _roi_points(half):
    """The ROI's centre and four corners on the sample (the points the variance averages)."""
    return np.array([[0, 0, 0], [1, 1, 0], [-1, 1, 0], [1, -1, 0], [-1, -1, 0]]) * [*half, 0]


def test_direction_variance_is_the_trace_of_the_propagated_covariance():
    C = np.array([0.1, -0.25, 0.33])
    cam = _board_camera(8, C, 2e-4, 5e-4)
    R, cov = cam.rotation, cam.covariance
    L = np.array([0.2, 0.1, 0.45])
    got = direction_variance(cam, L, ROI_HALF, source="board")
    J = _board_jacobian(L, C, R, _roi_points(ROI_HALF))
    want = np.mean(np.einsum("nik,kl,nil->n", J, cov, J))
    assert want > 0
    assert got == pytest.approx(want, rel=0.02)
    # the variance of the rig's source, without rig modes, is none
    assert direction_variance(cam, L, ROI_HALF, source="rig") == 0.0


@pytest.mark.parametrize(
    "rig_scale, board_std_rad, want_rig", [(0.05, 1e-3, True), (3.0, 1e-4, False)]
)
def test_auto_geometry_takes_the_source_whose_covariance_moves_the_directions_less(
    rig_scale, board_std_rad, want_rig
):
    """``geometry = "auto"``'s choice at a trustworthy board view, judged by the traces of
    the two propagated covariances computed here independently (the rig's by one
    parameter at a time through its kinematics, the board's through the homography)."""
    from types import SimpleNamespace

    from gonio.app.demo import parse_material, scene_document
    from gonio.app.sim_reduction import setup_from_scene
    from gonio.capture.reduce import _PoseRun
    from gonio.simulator.scene import parse_scene

    rig, values, names, cov = _calibrated_rig(scale=rig_scale)
    L, C, R = _rig_at(values, JOINTS)
    scene = parse_scene(scene_document(parse_material("lambert albedo=0.5"), 320, 240))
    setup = setup_from_scene(scene, 0.99).replace(K=K, dist=None)
    half = tuple(0.5 * setup.roi_fraction * np.asarray(setup.sample_size))
    x = _roi_points(half)
    cov_b = np.diag([board_std_rad**2] * 3 + [(0.4 * board_std_rad) ** 2] * 3)
    board = CameraPose(R, -R @ C, C, 0.1, 24, cov_b)
    run = _PoseRun(Path("."), setup, SimpleNamespace(config=rig), [])
    last = {"joints": JOINTS, "approach": APPROACH}
    got = run._rig_beats_board(board, L, (C, R), 0, last)
    # the references: trace of J C J^T of each source, averaged over the same points
    pix = (x @ R.T + (-R @ C)) @ K.T
    pix = pix[:, :2] / pix[:, 2:]
    Jr = np.zeros((len(x), 6, len(names)))
    for k, name in enumerate(names):
        h = 1e-4 * (PARAMETERS[name].magnitude if name in PARAMETERS else 1.0)
        side = []
        for s in (1.0, -1.0):
            Lp, Cp, Rp = _rig_at(values, JOINTS, name, s * h)
            Kc = _K_moved(name, s * h) if name in INTR else K
            side.append(_directions_via_homography(Lp, Cp, Rp, Kc, pix))
        Jr[:, :, k] = (side[0] - side[1]) / (2 * h)
    v_rig = np.mean(np.einsum("nik,kl,nil->n", Jr, cov, Jr))
    # the board's source: its pose covariance, and the rig's modes moving the light only
    Jb = _board_jacobian(L, C, R, x)
    Jl = np.zeros((len(x), 6, len(names)))
    for k, name in enumerate(names):
        h = 1e-4 * (PARAMETERS[name].magnitude if name in PARAMETERS else 1.0)
        side = [_unit(_rig_at(values, JOINTS, name, s * h)[0] - x) for s in (1.0, -1.0)]
        Jl[:, :3, k] = (side[0] - side[1]) / (2 * h)
    v_board = np.mean(
        np.einsum("nik,kl,nil->n", Jb, cov_b, Jb) + np.einsum("nik,kl,nil->n", Jl, cov, Jl)
    )
    assert (v_rig < v_board) == want_rig, (v_rig, v_board)  # the case is what it says
    assert max(v_rig, v_board) > 3 * min(v_rig, v_board)  # and not a close call
    assert got == want_rig
    # a board view without its covariance, too few corners or no joints: the board stays
    bare = CameraPose(R, -R @ C, C, 0.1, 24)
    few = CameraPose(R, -R @ C, C, 0.1, setup.min_board_corners - 1, cov_b)
    assert not run._rig_beats_board(bare, L, (C, R), 0, last)
    assert not run._rig_beats_board(few, L, (C, R), 0, last)
    assert not run._rig_beats_board(board, L, (C, R), 1, {"joints": None})


def test_centroid_points_see_the_camera_along_wo():
    C = np.array([0.1, 0.2, 0.4])
    x = np.array([[0.01, -0.02, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(centroid_points(C, _unit(C - x)), x, atol=1e-15)


# ------------------------------------------------------------------ the local gradient
def _sph(t, p):
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)


def _pattern(regions: int, theta_i_max: int, min_separation_deg: float = 0.0):
    """``regions x regions`` regions (2.4 cm) per pose, light at 0.5 m, camera at 0.45 m,
    on a grid of theta_i 0..theta_i_max, theta_o 0..80 (10 deg) and four azimuth
    differences; poses with light and camera closer than ``min_separation_deg`` left
    out."""
    g = np.linspace(-0.012, 0.012, regions)
    X, Y = np.meshgrid(g, g)
    pts = np.stack([X.ravel(), Y.ravel(), 0 * X.ravel()], 1)
    wi, wo = [], []
    for ti in range(0, theta_i_max + 1, 10):
        for to in range(0, 81, 10):
            for dp in (180, 150, 120, 90):
                li, co = _sph(np.radians(ti), 0.0), _sph(np.radians(to), np.radians(dp))
                if min_separation_deg and np.degrees(np.arccos(li @ co)) < min_separation_deg:
                    continue
                wi.append(_unit(0.5 * li - pts))
                wo.append(_unit(0.45 * co - pts))
    return np.concatenate(wi), np.concatenate(wo)


def _measurement_pattern():
    """3 x 3 regions per pose, theta_i 0..70 (:func:`_pattern`)."""
    return _pattern(3, 70)


@pytest.mark.parametrize(
    ("alpha", "iqr", "corr"),
    # The stated accuracy of the model-free gradient on this pattern: the median ratio
    # of predicted to true marginal geometric std within 10 %, the middle half of the
    # samples within [0.85, 1.15] (alpha 0.2) or [0.8, 1.25] (alpha 0.05: the lobe is as
    # narrow as the pose spacing, only a pose's own regions resolve it), and the signed
    # change along each mode correlated with the model's by > 0.95 or > 0.75.
    [(0.2, (0.85, 1.15), 0.95), (0.05, (0.8, 1.25), 0.75)],
)
def test_the_local_gradient_predicts_the_models_change_along_modes(alpha, iqr, corr):
    wi, wo = _measurement_pattern()
    model = get_model("lambert+ggx")
    p = {"albedo": 0.5, "ks": 0.2, "alpha": alpha}
    f = model.eval(wi, wo, p)[:, None]
    rng = np.random.default_rng(1)
    M = 8
    d = rng.normal(size=(len(wi), M, 6)) * np.radians(0.1)
    d[..., :3] -= (d[..., :3] * wi[:, None]).sum(-1, keepdims=True) * wi[:, None]
    d[..., 3:] -= (d[..., 3:] * wo[:, None]).sum(-1, keepdims=True) * wo[:, None]
    grad = local_log_gradient(wi, wo, f)
    got = geometry_std(f, grad, d)[:, 0]
    df = np.stack(
        [
            0.5
            * (
                model.eval(_unit(wi + d[:, j, :3]), _unit(wo + d[:, j, 3:]), p)
                - model.eval(_unit(wi - d[:, j, :3]), _unit(wo - d[:, j, 3:]), p)
            )
            for j in range(M)
        ],
        axis=1,
    )
    want = np.sqrt((df**2).sum(1))
    big = want / f[:, 0] > 0.002  # where geometry matters (0.2 % of f or more)
    assert big.sum() > 500
    r = got[big] / want[big]
    q25, q50, q75 = np.percentile(r, [25, 50, 75])
    print(f"alpha {alpha}: ratio quartiles {q25:.2f} {q50:.2f} {q75:.2f}")
    assert 0.9 <= q50 <= 1.1
    assert iqr[0] <= q25 and q75 <= iqr[1]
    # signed, mode by mode: the prediction follows the model's change
    pred = np.einsum("nf,nmf->nm", grad[:, 0], d[..., [0, 1, 3, 4]]) * f
    rho = np.corrcoef(pred[big].ravel(), df[big].ravel())[0, 1]
    print(f"alpha {alpha}: correlation with the model's change {rho:.3f}")
    assert rho > corr


def _random_pairs(n, seed):
    rng = np.random.default_rng(seed)
    wi = _unit(rng.normal(size=(n, 3)) * [1, 1, 0.6] + [0, 0, 1.2])
    wo = _unit(rng.normal(size=(n, 3)) * [1, 1, 0.6] + [0, 0, 1.2])
    return wi, wo


def test_the_local_gradient_of_a_quadratic_in_log_f_is_exact():
    """log f quadratic in the features: the local fit returns its gradient (no ridge)."""
    wi, wo = _random_pairs(3000, 2)
    slope = np.array([0.3, -0.2, 0.5, 0.1])
    X = np.concatenate([wi[:, :2], wo[:, :2]], axis=1)
    f = np.exp(X @ slope + 2.0 * X[:, 0] * X[:, 2] - X[:, 1] ** 2)[:, None]
    want = slope + np.stack([2 * X[:, 2], -2 * X[:, 1], 2 * X[:, 0], 0 * X[:, 0]], axis=1)
    g = local_log_gradient(wi, wo, f, ridge=0.0, curvature_ridge=0.0)
    np.testing.assert_allclose(g[:, 0, :], want, atol=1e-6)
    # non-positive samples are no neighbours; too few neighbours give NaN
    f2 = f.copy()
    f2[::2] = -1.0
    g2 = local_log_gradient(wi, wo, f2, ridge=0.0, curvature_ridge=0.0)
    np.testing.assert_allclose(g2[1::2, 0], want[1::2], atol=1e-6)
    assert np.isnan(local_log_gradient(wi[:5], wo[:5], f[:5])).all()


# ------------------------------------------------------------------ the isotropic chart
def _z_of(a):
    return np.sqrt(1.0 - np.sum(a * a, axis=-1))


def _upper_pairs(n, seed):
    """Random pairs above the horizon (z > 0.05: central differences stay on the disk)."""
    wi, wo = _random_pairs(n, seed)
    keep = (wi[:, 2] > 0.05) & (wo[:, 2] > 0.05)
    return wi[keep], wo[keep]


def _pairs_of(X):
    """(wi, wo) of projected features X (N, 4): the upper hemisphere's z."""
    a, b = X[:, :2], X[:, 2:]
    return np.c_[a, _z_of(a)], np.c_[b, _z_of(b)]


def test_isotropic_features_are_their_closed_form_and_rotation_invariant():
    wi, wo = _upper_pairs(500, 7)
    ti, pi = np.arccos(wi[:, 2]), np.arctan2(wi[:, 1], wi[:, 0])
    to, po = np.arccos(wo[:, 2]), np.arctan2(wo[:, 1], wo[:, 0])
    si, so, pd = np.sin(ti), np.sin(to), po - pi
    r = np.hypot(si, so)
    want = (
        np.stack([si**2 - so**2, 2 * si * so * np.cos(pd), 2 * si * so * np.sin(pd)], axis=1)
        / r[:, None]
    )
    Y = isotropic_features(wi, wo)
    np.testing.assert_allclose(Y, want, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(Y, axis=1), r, rtol=1e-13)
    # a rotation about the normal leaves them alone; a mirror image flips the third
    c, s_ = np.cos(1.1), np.sin(1.1)
    Rz = np.array([[c, -s_, 0], [s_, c, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(isotropic_features(wi @ Rz.T, wo @ Rz.T), Y, atol=1e-14)
    flip = np.array([1.0, -1.0, 1.0])
    np.testing.assert_allclose(isotropic_features(wi * flip, wo * flip), Y * [1, 1, -1], atol=1e-14)
    # both at the normal: no chart there (NaN, not an exception); NaN in, NaN out
    z = np.array([[0.0, 0.0, 1.0]])
    assert np.isnan(isotropic_features(z, z)).all()
    assert np.isnan(isotropic_features(z * np.nan, wo[:1])).all()


def test_the_isotropic_jacobian_is_the_features_derivative():
    """Against central differences of the features over ``(wi_x, wi_y, wo_x, wo_y)``;
    its null space is the rotation about the normal."""
    wi, wo = _upper_pairs(300, 8)
    X = np.concatenate([wi[:, :2], wo[:, :2]], axis=1)
    J = isotropic_jacobian(wi, wo)
    h = 1e-6
    want = np.zeros_like(J)
    for k in range(4):
        e = np.zeros(4)
        e[k] = h
        want[:, :, k] = (
            isotropic_features(*_pairs_of(X + e)) - isotropic_features(*_pairs_of(X - e))
        ) / (2 * h)
    np.testing.assert_allclose(J, want, atol=1e-8)
    rot = np.stack([-X[:, 1], X[:, 0], -X[:, 3], X[:, 2]], axis=1)
    np.testing.assert_allclose(np.einsum("nyx,nx->ny", J, rot), 0.0, atol=1e-14)


def test_the_isotropic_gradient_of_a_quadratic_in_its_chart_is_exact():
    """log f quadratic in the isotropic features: the local fit on that chart returns the
    gradient over ``(wi_x, wi_y, wo_x, wo_y)`` that central differences of the closed
    form give (no ridge), and nothing along the rotation about the normal."""
    wi, wo = _upper_pairs(4000, 9)
    slope = np.array([0.4, -0.3, 0.7])

    def logf(wi, wo):
        Y = isotropic_features(wi, wo)
        return Y @ slope + 1.5 * Y[:, 0] * Y[:, 2] - Y[:, 1] ** 2

    X = np.concatenate([wi[:, :2], wo[:, :2]], axis=1)
    h = 1e-6
    want = np.zeros((len(X), 4))
    for k in range(4):
        e = np.zeros(4)
        e[k] = h
        want[:, k] = (logf(*_pairs_of(X + e)) - logf(*_pairs_of(X - e))) / (2 * h)
    f = np.exp(logf(wi, wo))[:, None]
    g = local_log_gradient(wi, wo, f, ridge=0.0, curvature_ridge=0.0, isotropic=True)
    assert g.shape == (len(X), 1, 4)
    np.testing.assert_allclose(g[:, 0], want, atol=1e-6)
    # the projected chart is not exact here: log f is no quadratic in its features
    gp = local_log_gradient(wi, wo, f, ridge=0.0, curvature_ridge=0.0)
    assert np.max(np.abs(gp[:, 0] - want)) > 1e-3


def _phong(wi, wo, kappa=200.0, c=0.05):
    """``f = c + exp(kappa (r . wo - 1))``, ``r = (-wi_x, -wi_y, wi_z)`` the mirror
    direction: isotropic, and its log gradient over ``(wi_x, wi_y, wo_x, wo_y)`` in
    closed form (``wi_z = sqrt(1 - wi_x^2 - wi_y^2)``)."""
    a, b, zi, zo = wi[:, :2], wo[:, :2], wi[:, 2], wo[:, 2]
    e = np.exp(kappa * (zi * zo - np.sum(a * b, axis=1) - 1.0))
    f = c + e
    dS = np.concatenate([-b - (zo / zi)[:, None] * a, -a - (zi / zo)[:, None] * b], axis=1)
    return f[:, None], (kappa * e / f)[:, None] * dS


def _session_pattern():
    """6 x 6 regions per pose, theta_i 0..80, poses closer than 12 deg between light and
    camera left out (the plans' min_separation_deg; :func:`_pattern`)."""
    return _pattern(6, 80, 12.0)


def test_the_isotropic_gradient_follows_a_closed_form_lobe_at_grazing_angles():
    """A narrow lobe (Phong, kappa 200) on a session's pattern: the change along random
    0.1 deg modes that the gradient predicts against the lobe's analytic gradient.  At
    max(theta_i, theta_o) >= 70 deg a pose's regions across the plane of incidence
    differ mostly by a common rotation, which the projected chart reads as a shallow
    slope; the isotropic chart knows the rotation changes nothing and puts the change
    where it is, in ``phi_o - phi_i``.  (Measured: correlation 0.93 isotropic, 0.82
    projected; median error of the signed change 27 % against 51 %.)"""
    wi, wo = _session_pattern()
    f, want_g = _phong(wi, wo)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(len(wi), 8, 6)) * np.radians(0.1)
    d[..., :3] -= (d[..., :3] * wi[:, None]).sum(-1, keepdims=True) * wi[:, None]
    d[..., 3:] -= (d[..., 3:] * wo[:, None]).sum(-1, keepdims=True) * wo[:, None]
    dX = d[..., [0, 1, 3, 4]]
    want = np.einsum("nf,nmf->nm", want_g, dX)
    theta = np.degrees(np.maximum(np.arccos(wi[:, 2]), np.arccos(wo[:, 2])))
    big = np.sqrt(np.sum(want**2, axis=1)) > 0.002  # geometry matters: 0.2 % of f
    grazing = big & (theta >= 70)
    assert big.sum() > 1000 and grazing.sum() > 150

    def scores(isotropic, sel):
        g = local_log_gradient(wi, wo, f, isotropic=isotropic)[:, 0]
        pred = np.einsum("nf,nmf->nm", g, dX)
        rho = np.corrcoef(pred[sel].ravel(), want[sel].ravel())[0, 1]
        err = np.median(np.abs(pred[sel] - want[sel])) / np.median(np.abs(want[sel]))
        ratio = np.sqrt(np.sum(pred[sel] ** 2, 1) / np.sum(want[sel] ** 2, 1))
        return rho, err, np.percentile(ratio, [25, 50, 75])

    rho_i, err_i, q_i = scores(True, grazing)
    rho_p, err_p, _ = scores(False, grazing)
    print(f"grazing: isotropic rho {rho_i:.3f} err {err_i:.3f}; projected {rho_p:.3f} {err_p:.3f}")
    assert rho_i > 0.9 and err_i < 0.35
    assert 0.9 <= q_i[1] <= 1.1 and 0.8 <= q_i[0] and q_i[2] <= 1.2
    assert err_i < 0.75 * err_p  # the fix: the projected chart's error at grazing
    # over every sample where geometry matters it is no worse than the projected chart
    rho_all, err_all, q_all = scores(True, big)
    assert rho_all > 0.95 and err_all < 0.2 and 0.9 <= q_all[1] <= 1.1


def test_noise_alone_gives_a_small_geometry_term():
    """A Lambertian surface measured with 0.5 % noise: the fitted gradient is noise, and
    the geometry term it gives for 0.05 deg modes stays far below the noise."""
    wi, wo = _measurement_pattern()
    rng = np.random.default_rng(4)
    f = (0.5 / np.pi) * (1 + 0.005 * rng.normal(size=(len(wi), 3)))
    d = rng.normal(size=(len(wi), 10, 6)) * np.radians(0.05)
    geo = geometry_std(f, local_log_gradient(wi, wo, f), d)
    assert np.median(geo / f) < 0.1 * 0.005


# ------------------------------------------------------------------ summary
def test_budget_rows_are_the_hand_computed_shares():
    f = np.array([[1.0, 2.0], [2.0, 4.0], [1.0, np.nan]])
    budget = {
        "noise": np.array([[0.01, 0.02], [0.02, 0.04], [0.01, 0.01]]),  # 1 % everywhere
        "geometry": np.array([[0.02, 0.0], [0.0, 0.0], [0.0, 0.0]]),  # 2 % on one
    }
    rows = budget_rows(budget, f, shared={"reference": [0.01, 0.01]})
    by = {r["term"]: r for r in rows}
    # usable: the first two samples (the third has a NaN channel); 4 values
    # relative variances: noise 4 x 1e-4, geometry 4e-4, shared 1e-4 per value (4 values)
    total = 4e-4 + 4e-4 + 4e-4
    assert by["noise"]["share"] == pytest.approx(4e-4 / total)
    assert by["geometry"]["share"] == pytest.approx(4e-4 / total)
    assert by["reference"]["share"] == pytest.approx(4e-4 / total)
    assert by["noise"]["median_rel_std"] == pytest.approx(0.01)
    assert by["geometry"]["median_rel_std"] == pytest.approx(0.0)
    assert by["reference"]["scope"] == "shared"
    from rich.console import Console

    con = Console(width=100, record=True)
    con.print(budget_table(rows))
    text = con.export_text()
    assert "noise" in text and "33.3%" in text and "1.000%" in text
    assert POSE_MODE_NAMES[0] == "board pose 1"


@pytest.mark.parametrize("theta_deg", [85.0, 89.0, 89.9])
def test_grazing_modes_and_budget_are_finite(theta_deg):
    """Out to 89.9 deg the modes, the gradient and the geometry term stay finite."""
    rig, values, names, cov = _calibrated_rig()
    modes = session_modes(rig)
    th = np.radians(theta_deg)
    C = 0.45 * np.array([np.sin(th), 0.0, np.cos(th)])
    z = _unit(-C)
    xa = _unit(np.cross(z, [0.0, 0, 1]))
    R = np.stack([xa, np.cross(z, xa), z])
    cam = CameraPose(R, -R @ C, C, 0.1, 24, np.diag([1e-8] * 3 + [1e-8] * 3))
    L = 0.5 * _unit(np.array([-np.sin(th), 0.0, np.cos(th)]))
    x = _regions(C, R)
    wi, wo = _unit(L - x), _unit(C - x)
    shifts = rig_shifts(modes, [JOINTS], [APPROACH])
    for source in ("board", "rig"):
        m = pose_modes(wi, wo, cam, L, source=source, session=modes, shifts=shifts.at(0), K=K)
        assert np.isfinite(m).all()
    wi_all, wo_all = _measurement_pattern()
    wi_all = np.concatenate([wi_all, wi])
    wo_all = np.concatenate([wo_all, wo])
    model = get_model("lambert+ggx")
    f = model.eval(wi_all, wo_all, {"albedo": 0.5, "ks": 0.2, "alpha": 0.2})[:, None]
    g = local_log_gradient(wi_all, wo_all, f)
    modes_all = np.zeros((len(f), m.shape[1], 6))
    modes_all[-9:] = m
    geo = geometry_std(f, g, modes_all)
    assert np.isfinite(geo).all() and np.isfinite(g[-9:]).all()


def test_camera_modes_move_a_board_pose_as_a_resolved_pose_does():
    """A board pose's camera modes (the camera calibration's intrinsics errors) against
    the independent route: solve the board pose again with the moved intrinsics
    (scipy least squares on cv2.projectPoints) and find the centroid pixel's sample point
    through the moved homography; covariances compared as J C J^T."""
    from scipy.optimize import least_squares

    from gonio.capture.budget import camera_modes
    from gonio.capture.fiducials import BoardSpec, _solve

    board = BoardSpec()
    obj_b = np.asarray(board.cv_board().getChessboardCorners(), float)
    R_bs, t_bs = board.transform()
    obj = obj_b @ R_bs.T + t_bs
    C = np.array([0.05, -0.08, 0.42])  # 13 deg off the normal: nearly fronto-parallel
    z = _unit(-C)
    xa = _unit(np.cross(z, [0.0, 0, 1]))
    R = np.stack([xa, np.cross(z, xa), z])
    t = -R @ C
    img, _ = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, np.zeros(5))
    img = img.reshape(-1, 2)
    cam = _solve(board, img, np.arange(len(obj)), K, None)
    cal = {"K_std": [2.0, 2.0, 4.5, 3.8], "dist_std": [0.0] * 5}
    cm = camera_modes(cal)
    assert len(cm) == 4 and all(n.startswith("camera ") for n in cm.names)
    L = np.array([-0.1, 0.2, 0.4])
    x = _regions(C, R)
    wi, wo = _unit(L - x), _unit(C - x)
    m = pose_modes(wi, wo, cam, L, source="board", K=K, camera_modes=cm, dist=None)
    assert m.shape == (9, 4 + 6, 6)
    got = np.einsum("nmi,nmj->nij", m[:, :4], m[:, :4])
    pix = (x @ R.T + t) @ K.T
    pix = pix[:, :2] / pix[:, 2:]

    def resolve(Kc):
        def res(p):
            uv, _ = cv2.projectPoints(obj, p[:3], p[3:], Kc, np.zeros(5))
            return (uv.reshape(-1, 2) - img).ravel()

        x0 = np.concatenate([cv2.Rodrigues(R)[0].ravel(), t])
        p = least_squares(res, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        Rp = cv2.Rodrigues(p[:3])[0]
        return _directions_via_homography(L, -Rp.T @ p[3:], Rp, Kc, pix)

    J = np.zeros((9, 6, 4))
    for k, name in enumerate(INTR):
        h = 0.05
        J[:, :, k] = (resolve(_K_moved(name, h)) - resolve(_K_moved(name, -h))) / (2 * h)
    want = np.einsum("nik,k,njk->nij", J, np.array(cal["K_std"]) ** 2, J)
    scale = np.max(np.abs(want))
    # the principal point's error moves a near-normal camera's wo by ~ its angle
    assert np.degrees(np.sqrt(scale)) > 0.05
    np.testing.assert_allclose(got, want, atol=0.03 * scale)
    # on a rig pose the camera modes are the rig covariance's business: zeros
    m_rig = pose_modes(wi, wo, cam, L, source="rig", K=K, camera_modes=cm)
    assert np.all(m_rig[:, :4] == 0)


def test_local_log_gradient_is_the_same_block_by_block(monkeypatch):
    """The neighbourhood fits are solved a block of samples at a time (bounded memory on
    texel reductions): one block or blocks of 7 give the same numbers, bit for bit."""
    from gonio.capture import budget
    from gonio.radiometry import normalize

    rng = np.random.default_rng(4)
    n = 200
    wi = normalize(np.abs(rng.normal(size=(n, 3))) + [0, 0, 0.5])
    wo = normalize(np.abs(rng.normal(size=(n, 3))) + [0, 0, 0.5])
    f = np.exp(0.1 * rng.normal(size=(n, 3))) * (1 + 5 * (wi[:, 2:3] * wo[:, 2:3]) ** 8)
    f[3] = np.nan
    whole = budget.local_log_gradient(wi, wo, f)
    monkeypatch.setattr(budget, "_GRADIENT_BLOCK", 7)
    np.testing.assert_array_equal(budget.local_log_gradient(wi, wo, f), whole)
    # a sample without a usable BRDF is not a neighbour, but still gets its neighbours' slope
    assert np.isfinite(whole).all()


@pytest.mark.parametrize("shape", [(4, 30), (3, 41), (10, 10), (21, 16)])
@pytest.mark.parametrize("offset", [(0, 0), (1, 0), (1, 1)])
def test_effective_sites_are_those_of_bilinear_interpolation(shape, offset):
    """A region's value is the mean over its pixels of each channel bilinearly
    interpolated to every pixel; site errors of std u average to u sqrt(sum W^2) / N with
    W_q = sum over the region's pixels of the interpolation kernel at q (here by a
    convolution, not the reduction's stencil filters).  N_eff = N^2 / sum W^2 exceeds
    the pixel count times the channel's share (the sites just outside the edge count)."""
    from scipy.ndimage import correlate

    from gonio.capture.radiometric import (
        _sites_per_channel,
        effective_sites,
        flat_rel_std,
        region_flat_rel_std,
    )

    H, W = 40, 60
    r0, c0 = 5 + offset[0], 7 + offset[1]  # the crop's place in the frame (CFA phase)
    cell = np.array([[0, 1], [1, 2]])  # RGGB
    yy, xx = np.mgrid[0:H, 0:W]
    channel = cell[(yy + r0) % 2, (xx + c0) % 2]
    label = -np.ones((H, W), int)
    a, b = shape
    label[8 : 8 + a, 9 : 9 + b] = 0
    inside = (label == 0).astype(float)
    kernels = {
        0: np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]]),
        1: np.array([[0.0, 0.25, 0.0], [0.25, 1.0, 0.25], [0.0, 0.25, 0.0]]),
    }
    kernels[2] = kernels[0]
    want = []
    for c in range(3):
        w = correlate(inside, kernels[c], mode="constant") * (channel == c)
        want.append(w.sum() ** 2 / np.sum(w**2))
    box = (slice(r0, r0 + H), slice(c0, c0 + W))
    got = effective_sites(label, box, cell, 1)
    np.testing.assert_allclose(got[0], want, rtol=1e-12)
    share = _sites_per_channel(np.array([a * b]), cell)[0]
    assert np.all(got[0] > share)
    u = np.array([0.004, 0.003, 0.005])
    np.testing.assert_allclose(
        flat_rel_std(np.array([a * b]), u, cell, got)[0], u / np.sqrt(want), rtol=1e-12
    )
    # a map of per-site stds: sqrt(sum W^2 u^2) / sum W (a uniform map: u / sqrt(N_eff))
    u_map = np.random.default_rng(3).uniform(0.002, 0.006, (200, 200))
    want_map = []
    for c in range(3):
        w = correlate(inside, kernels[c], mode="constant") * (channel == c)
        want_map.append(np.sqrt(np.sum(w**2 * u_map[box] ** 2)) / w.sum())
    got_map = region_flat_rel_std(label, box, cell, 1, u_map)
    np.testing.assert_allclose(got_map[0], want_map, rtol=1e-12)
    flat_map = np.full((200, 200), 0.004)
    np.testing.assert_allclose(
        region_flat_rel_std(label, box, cell, 1, flat_map)[0], 0.004 / np.sqrt(want), rtol=1e-12
    )
    # a masked site leaves the sums: fewer effective sites
    mask = np.zeros((200, 200), bool)
    mask[r0 + 8 + a // 2, c0 + 9 + b // 2] = True
    assert np.all(effective_sites(label, box, cell, 1, mask)[0] <= got[0] + 1e-12)


def test_the_flat_maps_pixel_std_is_the_scatter_of_the_gain_over_flat_draws():
    """The master flat's per-pixel relative std (``FlatField.pixel_rel_map``) against
    the scatter of the gain estimate over 400 independent sets of noisy flats of a scene
    twice as bright at the centre as at the edge (Gaussian photon + read noise of a known
    model): the map follows each pixel's own level, the channel's ``pixel_rel_std`` its
    mean level only."""
    from gonio.capture.noise import NoiseModel
    from gonio.capture.pixel_calibration import cos4_inverse, prnu_gain

    H, W = 24, 32
    K = np.array([[40.0, 0, W / 2 - 0.5], [0, 40.0, H / 2 - 0.5], [0, 0, 1]])
    cell = np.array([[0, 1], [1, 2]])
    ch = cell[np.arange(H)[:, None] % 2, np.arange(W)[None, :] % 2]
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((yy - H / 2) / H) ** 2 + ((xx - W / 2) / W) ** 2
    S = 3000.0 * (2.0 - r2 / r2.max()) / cos4_inverse((H, W), K)
    noise = NoiseModel(gain=0.4, read_noise=1.2, iso=100.0, quantisation=False)
    sd = np.sqrt(noise.variance(S))
    rng = np.random.default_rng(5)
    n_flats, draws = 3, 400
    gains, maps = [], []
    for _ in range(draws):
        flats = [S + sd * rng.standard_normal((H, W)) for _ in range(n_flats)]
        ff = prnu_gain(flats, ch, K, pixel_variance=noise.variance, dark_variance=0.0)
        # the per-channel normalisation moves every pixel alike: take it out
        g = ff.gain.copy()
        for c in range(3):
            g[ch == c] /= np.mean((S * cos4_inverse((H, W), K))[ch == c])
        gains.append(g)
        maps.append(ff.pixel_rel_map)
    gains = np.array(gains)
    rel = gains.std(axis=0) / gains.mean(axis=0)
    want = np.sqrt(noise.variance(S) / n_flats) / S
    # 400 draws: the std of a std is 1/sqrt(800) = 3.5 %; over 768 pixels the median
    # ratio is within 1 %
    assert np.median(rel / want) == pytest.approx(1.0, abs=0.01)
    assert np.median(np.mean(maps, axis=0) / want) == pytest.approx(1.0, abs=0.005)
    # the centre's pixels are known better than the channel's mean level says (by the
    # square root of their level over the mean: 0.87 here)
    centre = r2 < 0.1 * r2.max()
    at_mean = ff.pixel_rel_std[ch[centre]]
    assert np.median(want[centre] / at_mean) < 0.9
    assert np.median(np.mean(maps, axis=0)[centre] / at_mean) < 0.9
