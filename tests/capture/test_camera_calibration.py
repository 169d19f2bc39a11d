"""Camera calibration: statistics on synthetic corners, rendered views, files and refusals."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gonio.capture.camera_calibration import (
    CalibrationView,
    CameraCalibrationError,
    CameraMismatch,
    calibrate_camera,
    camera_digest,
    check_camera,
    detect_views,
    load_camera_calibration,
    write_camera_calibration,
)
from gonio.capture.fiducials import BoardSpec
from gonio.errors import ConfigError, FileFormatError, GonioError
from gonio.radiometry import spherical_to_direction
from gonio.radiometry.frames import look_at_rotation

BOARD = BoardSpec(9, 7, 0.02, 0.015, "DICT_4X4_50")
K_TRUE = np.array([[1210.0, 0, 655.3], [0, 1205.0, 478.9], [0, 0, 1]])
DIST_TRUE = np.array([-0.12, 0.09, 0.0012, -0.0008, -0.03])
W, H = 1280, 960
IDENT = {"backend": "simulated", "model": "gonio-sim", "serial": "SIM-1", "resolution": [W, H]}


def synthetic_views(rng, sigma, n=15, K=K_TRUE, dist=DIST_TRUE):
    """Board corners projected by cv2.projectPoints from random tilted views, plus noise
    of ``sigma`` px on each coordinate."""
    obj = np.asarray(BOARD.cv_board().getChessboardCorners(), float)
    centre = obj.mean(0)
    views = []
    for k in range(n):
        th, ph = np.radians(rng.uniform(10, 45)), rng.uniform(0, 2 * np.pi)
        d = rng.uniform(0.35, 0.5)
        # the board frame's z points into the board: the camera is at -z
        pos = centre + d * np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)])
        R = look_at_rotation(
            pos, centre + np.r_[rng.normal(0, 0.02, 2), 0], up=np.array([0, -1.0, 0])
        )
        uv = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], -R @ pos, K, dist)[0].reshape(-1, 2)
        uv = uv + rng.normal(0, sigma, uv.shape)
        ok = (uv[:, 0] > 0) & (uv[:, 0] < W - 1) & (uv[:, 1] > 0) & (uv[:, 1] < H - 1)
        ids = np.nonzero(ok)[0].astype(np.int32)
        views.append(CalibrationView(f"view {k}", ids, uv[ok], obj[ok], (W, H)))
    return views


def _estimates(c):
    return np.r_[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], c.dist]


TRUTH = np.r_[K_TRUE[0, 0], K_TRUE[1, 1], K_TRUE[0, 2], K_TRUE[1, 2], DIST_TRUE]


def test_reported_std_matches_the_spread_over_seeds():
    """|estimate - truth| / std over 40 seeds has a standard deviation near 1 for every
    parameter (OpenCV's std: residual variance over 2N - p coordinates, times the
    diagonal of (J^T J)^-1), and the RMS is sigma sqrt(2 (1 - p / 2N))."""
    sigma = 0.3
    z, rms_ratio = [], []
    for seed in range(40):
        # flags=0: all five terms (these free-standing views of a wide-angle lens, with a
        # k3, pin it; the default holds k3 at 0 for the rig's ring of corners)
        c = calibrate_camera(synthetic_views(np.random.default_rng(seed), sigma), flags=0)
        assert not c.rejected
        z.append((_estimates(c) - TRUTH) / np.r_[c.K_std, c.dist_std])
        p = 9 + 6 * len(c.used)  # intrinsics + a pose per view
        rms_ratio.append(c.rms_px / (sigma * np.sqrt(2 * (1 - p / (2 * c.n_points)))))
    spread = np.std(z, axis=0)
    names = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
    assert np.all((spread >= 0.7) & (spread <= 1.4)), dict(zip(names, spread.round(2), strict=True))
    assert np.all(np.abs(np.asarray(rms_ratio) - 1) < 0.2), (min(rms_ratio), max(rms_ratio))
    # and the estimates are unbiased: the mean z is within 3/sqrt(40) of 0
    assert np.all(np.abs(np.mean(z, axis=0)) < 3 / np.sqrt(40))


def test_an_outlier_view_is_rejected_with_its_reason():
    views = synthetic_views(np.random.default_rng(1), 0.2, n=10)
    bad = views[4]
    shifted = bad.image_points + np.random.default_rng(9).normal(0, 6.0, bad.image_points.shape)
    views[4] = CalibrationView(bad.label, bad.ids, shifted, bad.object_points, bad.image_size)
    c = calibrate_camera(views, flags=0)  # these views' lens has a k3
    assert [r.label for r in c.rejected] == ["view 4"]
    assert "more than 3x the median" in c.rejected[0].reason
    assert "view 4" not in c.used and len(c.used) == 9
    assert np.all(np.abs(_estimates(c) - TRUTH) < 5 * np.r_[c.K_std, c.dist_std])


def test_too_few_views_is_refused():
    views = synthetic_views(np.random.default_rng(2), 0.2, n=5)
    few = CalibrationView("sparse", views[0].ids[:5], views[0].image_points[:5],
                          views[0].object_points[:5], (W, H))  # fmt: skip
    with pytest.raises(CameraCalibrationError, match="5 views with a board, need at least 6") as e:
        calibrate_camera([*views, few])
    assert "sparse: 5 corners, need at least 8" in str(e.value)


def test_a_board_never_found_is_refused():
    blank = [np.full((120, 160), 128, np.uint8) for _ in range(3)]
    with pytest.raises(CameraCalibrationError, match="not found in any of the 3 images"):
        detect_views(blank, BOARD, source="blank/")


def test_calibration_file_round_trip_refusal_and_digest(tmp_path):
    c = calibrate_camera(synthetic_views(np.random.default_rng(3), 0.2, n=8))
    path = tmp_path / "camera.toml"
    write_camera_calibration(path, c, IDENT, cfa_pattern="RGGB")
    before = path.read_bytes()
    with pytest.raises(CameraCalibrationError, match="exists"):
        write_camera_calibration(path, c, IDENT)
    assert path.read_bytes() == before
    cam = load_camera_calibration(path)
    assert np.array_equal(np.array(cam.K), c.K) and np.array_equal(cam.dist, c.dist)
    assert (cam.width, cam.height) == (W, H) and cam.cfa_pattern == "RGGB"
    assert cam.calibration.rms_px == c.rms_px
    # the digest is sha256 of the canonical JSON, computed here independently
    import hashlib
    import json

    text = json.dumps(IDENT, sort_keys=True, separators=(",", ":"))
    assert cam.calibration.digest == "sha256:" + hashlib.sha256(text.encode()).hexdigest()
    check_camera(cam, IDENT)
    other = {**IDENT, "serial": "SIM-2"}
    with pytest.raises(CameraMismatch) as e:
        check_camera(cam, other)
    assert camera_digest(IDENT) in str(e.value) and camera_digest(other) in str(e.value)
    # the reduction's [camera] fields are there as reduction.toml takes them
    from gonio.capture.reduction_config import CameraSection
    from gonio.config import read_toml

    doc = read_toml(path, "camera")["camera"]
    CameraSection(**{k: v for k, v in doc.items() if k != "calibration"})
    write_camera_calibration(path, c, other, force=True)
    assert load_camera_calibration(path).calibration.camera.serial == "SIM-2"


def test_a_damaged_calibration_file_is_refused(tmp_path):
    c = calibrate_camera(synthetic_views(np.random.default_rng(4), 0.2, n=8))
    path = tmp_path / "camera.toml"
    write_camera_calibration(path, c, IDENT)
    text = path.read_text()
    (tmp_path / "edited.toml").write_text(text.replace('serial = "SIM-1"', 'serial = "X"'))
    with pytest.raises(FileFormatError, match="digest"):
        load_camera_calibration(tmp_path / "edited.toml")
    (tmp_path / "bad.toml").write_text(text.replace("rms_px = ", "rms_px = -"))
    with pytest.raises(ConfigError, match="rms_px"):
        load_camera_calibration(tmp_path / "bad.toml")
    assert issubclass(CameraMismatch, GonioError)


@pytest.mark.slow
def test_rendered_views_recover_the_renderers_K():
    """Board views rendered by the simulated rig camera (no lens distortion in this
    renderer): the solve finds its K (OpenCV cx = scene cx - 0.5)."""
    from gonio.capture.raw import read_raw
    from gonio.simulator.rig_camera import SimulatedRigCamera

    doc = {
        "sample": {"width": 0.05, "height": 0.05,
                   "brdf": {"model": "lambert", "params": {"albedo": 0.5}}},
        "holder": {"width": 0.2, "height": 0.2, "board": {"squares_x": 9, "squares_y": 9,
                   "square_length": 0.018, "marker_length": 0.013}},
        "lights": [{"type": "disk", "position": [0.0, 0.25, 0.433], "look_at": [0, 0, 0],
                    "radius": 0.01, "radiance": [2e4] * 3}],
        "camera": {"resolution": [640, 480], "focal_length": 0.016, "fov_deg": 40.0,
                   "principal_point": [331.0, 236.5], "position": [0.1, -0.2, 0.35]},
        "render": {"tolerance": 1e-3},
    }  # fmt: skip
    state = {}
    cam = SimulatedRigCamera(doc, lambda: state["p"], seed=1)
    rng = np.random.default_rng(0)
    frames = []
    for k, (th, ph) in enumerate(
        [(15, 0), (35, 30), (35, 150), (35, 270), (50, 90), (50, 210), (50, 330), (25, 200)]
    ):
        C = 0.32 * spherical_to_direction(np.radians(th), np.radians(ph))
        R = look_at_rotation(C, np.r_[rng.normal(0, 0.01, 2), 0], up=np.array([0, 0, 1.0]))
        L = 0.5 * spherical_to_direction(np.radians(40), np.radians(ph + 180))
        # RigPoses' camera_rotation is camera-to-sample
        state["p"] = {"camera_position": C, "camera_rotation": R.T, "light_position": L,
                      "light_normal": -L / 0.5}  # fmt: skip
        cam.next_shot(k, 0)
        frames.append(read_raw(cam.capture(4e-4, 100, 8).data, name=f"view {k}"))
    b = cam.scene.holder.board
    board = BoardSpec(b.squares_x, b.squares_y, b.square_length, b.marker_length, b.dictionary)
    c = calibrate_camera(detect_views(frames, board))
    K = cam.scene.camera.intrinsics()
    truth = np.r_[K[0, 0], K[1, 1], K[0, 2] - 0.5, K[1, 2] - 0.5]
    est = _estimates(c)[:4]
    assert len(c.used) == 8 and c.rms_px < 0.3
    assert np.all(np.abs(est - truth) < 4 * c.K_std), (est - truth, c.K_std)
    assert abs(est[0] / truth[0] - 1) < 5e-3 and abs(est[1] / truth[1] - 1) < 5e-3


def test_all_views_degenerate_is_refused_with_the_reason():
    views = synthetic_views(np.random.default_rng(6), 0.2, n=7)
    line = []
    for v in views:  # keep the board's first row only: corners on one line
        row = np.isclose(v.object_points[:, 1], v.object_points[0, 1])
        line.append(CalibrationView(v.label, v.ids[row], v.image_points[row],
                                    v.object_points[row], v.image_size))  # fmt: skip
    with pytest.raises(CameraCalibrationError, match="0 views with a board, need at least 6") as e:
        calibrate_camera(line)
    assert "view 0: its corners lie on one line (degenerate)" in str(e.value)


def test_covariance_diagonal_is_opencvs_std_and_is_written(tmp_path):
    """The intrinsics' covariance (our Jacobian, the views' poses eliminated) has
    OpenCV's standard deviations on its diagonal, k3 held (row 0) by default, and the
    camera file keeps it; the correlations are what a prior needs (k1-k2 strong)."""
    c = calibrate_camera(synthetic_views(np.random.default_rng(6), 0.3))
    std = np.sqrt(np.diag(c.covariance))
    np.testing.assert_allclose(std, np.r_[c.K_std, c.dist_std], rtol=1e-3, atol=1e-12)
    assert c.dist_std[4] == 0 and c.dist[4] == 0 and not c.covariance[8].any()
    corr = c.covariance[4, 5] / (std[4] * std[5])
    assert abs(corr) > 0.5
    ident = {"backend": "simulated", "model": "m", "serial": "S", "resolution": [W, H]}
    write_camera_calibration(tmp_path / "c.toml", c, ident)
    back = load_camera_calibration(tmp_path / "c.toml").calibration.covariance
    np.testing.assert_allclose(np.asarray(back), c.covariance, rtol=1e-12)
