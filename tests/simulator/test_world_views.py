"""Corner-level views of the as-built world, checked against OpenCV and closed forms."""

from __future__ import annotations

import math
import tomllib

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gonio.rig.config import default_rig_document, rig_config_from_dict
from gonio.rig.kinematics import Kinematics
from gonio.simulator.calibration_views import (
    board_corners,
    board_views,
    camera_views,
    project,
    simulated_pose,
    spot_views,
)
from gonio.simulator.scene import Board, Camera
from gonio.simulator.world import draw_world

DOC = tomllib.loads(default_rig_document())
CFG = rig_config_from_dict(DOC, "nominal")
CAM = Camera(resolution=(1200, 800), focal_length=0.016, fov_deg=30.0)
BOARD = Board(squares_x=7, squares_y=7, square_length=0.02, marker_length=0.015)


def _pose_for(theta_i, theta_o, phi_o=180.0, spin=0.0):
    """Joints of a nominal in-plane pose (through the controller's inverse)."""
    from gonio.radiometry import spherical_to_direction

    kin = Kinematics(CFG)
    wi = spherical_to_direction(math.radians(theta_i), 0.0)
    wo = spherical_to_direction(math.radians(theta_o), math.radians(phi_o))
    return kin.inverse(wi, wo)


def _joints():
    out = []
    for ti in (20, 40):
        for to in (10, 30, 45):
            try:
                out.append(_pose_for(ti, to))
            except Exception:  # noqa: BLE001 - a pose the rig refuses is just skipped
                pass
    assert len(out) >= 4
    return out


def test_project_matches_cv2_projectPoints():
    rng = np.random.default_rng(0)
    K = np.array([[2000.0, 0, 610.3], [0, 2010.0, 390.7], [0, 0, 1]])
    for _ in range(5):
        dist = np.concatenate(
            [rng.uniform(-0.2, 0.2, 2), rng.uniform(-2e-3, 2e-3, 2), rng.uniform(-0.05, 0.05, 1)]
        )
        P = np.column_stack([rng.uniform(-0.1, 0.1, (50, 2)), rng.uniform(0.3, 0.6, 50)])
        ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)
        np.testing.assert_allclose(project(P, K, dist), ref.reshape(-1, 2), atol=1e-9)


def test_perfect_world_views_are_the_controllers_projection():
    """sigma 0, perfect world: the corners are cv2.projectPoints of the board through the
    controller's nominal kinematics and the scene's K (centres shifted by 0.5)."""
    world = draw_world("perfect")
    kin = Kinematics(CFG)
    poses = [simulated_pose(world, DOC, j, {}, label=f"p{i}") for i, j in enumerate(_joints())]
    views = board_views(world, DOC, CAM, BOARD, poses, 0.0, np.random.default_rng(0))
    assert len(views) >= 3
    K = CAM.intrinsics() - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    for v in views:
        p = kin.poses(v["joints"])
        R = p.camera_rotation.T
        t = -R @ p.camera_position
        ref, _ = cv2.projectPoints(v["object_points"], cv2.Rodrigues(R)[0], t, K, np.zeros(5))
        np.testing.assert_allclose(v["image_points"], ref.reshape(-1, 2), atol=1e-6)
        assert len(v["ids"]) == len(v["object_points"]) >= 6


def _solve_pnp(view, K, dist):
    ok, rvec, tvec = cv2.solvePnP(
        view["object_points"], view["image_points"], K, dist, flags=cv2.SOLVEPNP_ITERATIVE
    )
    assert ok
    R = cv2.Rodrigues(rvec)[0]  # sample -> camera
    return R, tvec.ravel()


def _angle(Ra, Rb):
    return math.degrees(Rotation.from_matrix(Ra @ Rb.T).magnitude())


def test_a_tilt_offset_shows_in_the_measured_camera_pose():
    """1 deg on the tilt joint: the board-measured camera pose differs from the
    controller's report by 1 deg (and agrees with the world's truth)."""
    world = draw_world("perfect", 0, {"rig": {"stage_tilt.offset": 1.0}})
    kin = Kinematics(CFG)
    poses = [simulated_pose(world, DOC, j, {}) for j in _joints()]
    views = board_views(world, DOC, CAM, BOARD, poses, 0.05, np.random.default_rng(1))
    K, dist = world.intrinsics(CAM)
    assert len(views) >= 3
    for v in views:
        R, _ = _solve_pnp(v, K, dist)
        reported = kin.poses(v["joints"]).camera_rotation.T
        assert _angle(R, reported) == pytest.approx(1.0, abs=0.05)
    perfect = draw_world("perfect")
    for v in board_views(
        perfect,
        DOC,
        CAM,
        BOARD,
        [simulated_pose(perfect, DOC, j, {}) for j in _joints()],
        0.05,
        np.random.default_rng(1),
    ):
        R, _ = _solve_pnp(v, K, dist)
        assert _angle(R, kin.poses(v["joints"]).camera_rotation.T) < 0.05


def test_noise_and_distortion_of_the_views():
    world = draw_world("realistic", 3)
    K, dist = world.intrinsics(CAM)
    assert np.any(dist != 0)
    poses = [
        simulated_pose(world, DOC, j, {"stage_tilt": 1}, np.random.default_rng(2))
        for j in _joints()
    ]
    clean = board_views(world, DOC, CAM, BOARD, poses, 0.0, np.random.default_rng(0))
    noisy = board_views(world, DOC, CAM, BOARD, poses, 0.3, np.random.default_rng(0))
    d = np.concatenate(
        [n["image_points"] - c["image_points"] for n, c in zip(noisy, clean, strict=True)]
    )
    assert d.std() == pytest.approx(0.3, rel=0.15)
    # the clean corners are not the pinhole's: distortion is applied
    from gonio.simulator.world_kinematics import true_poses

    v = clean[0]
    truth = true_poses(world, DOC, poses[0]["servo_states"])
    R = truth.camera_rotation.T
    t = -R @ truth.camera_position
    pin, _ = cv2.projectPoints(v["object_points"], cv2.Rodrigues(R)[0], t, K, np.zeros(5))
    assert np.abs(pin.reshape(-1, 2) - v["image_points"]).max() > 0.5
    ref, _ = cv2.projectPoints(v["object_points"], cv2.Rodrigues(R)[0], t, K, dist)
    np.testing.assert_allclose(v["image_points"], ref.reshape(-1, 2), atol=1e-6)


def test_hidden_corners_and_oblique_views_are_left_out():
    world = draw_world("perfect")
    poses = [simulated_pose(world, DOC, j, {}) for j in _joints()]
    all_ = board_views(world, DOC, CAM, BOARD, poses, 0.0, np.random.default_rng(0))
    cut = board_views(
        world, DOC, CAM, BOARD, poses, 0.0, np.random.default_rng(0), hidden=(0.05, 0.05)
    )
    for a, c in zip(all_, cut, strict=True):
        assert np.all(np.abs(c["object_points"][:, :2]).max(axis=1) >= 0.025)
        assert len(c["ids"]) < len(a["ids"])
    none = board_views(
        world, DOC, CAM, BOARD, poses, 0.0, np.random.default_rng(0), max_view_deg=1.0
    )
    assert none == []


def test_spot_is_the_mirror_image_of_the_light():
    """sigma 0: the pixel's ray hits z = 0 at a point from which light and camera make
    equal angles with the normal, in one plane with it (the law of reflection)."""
    world = draw_world("realistic", 5)
    K, dist = world.intrinsics(CAM)
    from gonio.simulator.world_kinematics import true_poses

    poses = []
    for t in (20, 30, 40):
        try:
            poses.append(simulated_pose(world, DOC, _pose_for(t, t), {}, label=f"t{t}"))
        except Exception:  # noqa: BLE001
            pass
    spots = spot_views(world, DOC, CAM, (0.05, 0.05), poses, 0.0, np.random.default_rng(0))
    assert len(spots) >= 2
    by_label = {p["label"]: p for p in poses}
    for s in spots:
        pose = by_label[s["label"]]
        truth = true_poses(world, DOC, pose["servo_states"])
        und = cv2.undistortPoints(s["image_point"].reshape(1, 1, 2), K, dist).ravel()
        ray = truth.camera_rotation @ np.array([und[0], und[1], 1.0])
        C, L = truth.camera_position, truth.light_position
        hit = C + ray * (-C[2] / ray[2])
        a, b = C - hit, L - hit
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        np.testing.assert_allclose([a[0], a[1], a[2]], [-b[0], -b[1], b[2]], atol=1e-7)
    assert spot_views(world, DOC, CAM, (1e-4, 1e-4), poses, 0.0, np.random.default_rng(0)) == []


def test_camera_views_are_consistent_with_cv2():
    world = draw_world("realistic", 8)
    K, dist = world.intrinsics(CAM)
    poses = [simulated_pose(world, DOC, j, {}) for j in _joints()]
    views = camera_views(world, DOC, CAM, BOARD, poses, 0.0, np.random.default_rng(0))
    assert views
    board_pts, _ = board_corners(BOARD)
    for v in views:
        np.testing.assert_allclose(
            v["camera_points"], v["object_points"] @ v["R"].T + v["t"], atol=1e-12
        )
        ref, _ = cv2.projectPoints(v["object_points"], cv2.Rodrigues(v["R"])[0], v["t"], K, dist)
        np.testing.assert_allclose(v["image_points"], ref.reshape(-1, 2), atol=1e-6)
        np.testing.assert_array_equal(v["object_points"], board_pts[v["ids"]])
