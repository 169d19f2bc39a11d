"""The renderer with lens distortion against OpenCV: rays project back onto the pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gonio.errors import ConfigError
from gonio.simulator.geometry import (
    camera_rays,
    distort_normalized,
    pixel_grid,
    rays_from_normalized,
    undistort_normalized,
)
from gonio.simulator.render import render
from gonio.simulator.scene import look_at_rotation, parse_scene
from gonio.simulator.sensor import mean_electrons

DIST = (-0.15, 0.03, 0.0012, -0.0008, -0.004)
W, H = 320, 240


def camera_doc(dist=DIST, fov=60.0, pp=(163.7, 117.2), resolution=(W, H)):
    cam = {
        "resolution": list(resolution),
        "focal_length": 0.016,
        "fov_deg": fov,
        "principal_point": list(pp),
        "position": [0.02, -0.18, 0.3],
        "look_at": [0.0, 0.0, 0.0],
    }
    if dist is not None:
        cam["distortion"] = list(dist)
    return cam


def scene_doc(**cam):
    return {
        "sample": {
            "width": 0.05,
            "height": 0.05,
            "brdf": {"model": "lambert", "params": {"albedo": 0.5}},
        },
        "holder": {"width": 0.16, "height": 0.16},
        "lights": [
            {
                "type": "disk",
                "position": [0.0, 0.25, 0.433],
                "look_at": [0, 0, 0],
                "radius": 0.01,
                "radiance": [2e4, 2e4, 2e4],
            }
        ],
        "camera": camera_doc(**cam),
        "render": {"tolerance": 1e-3},
    }


def opencv_K(K):
    """The OpenCV matrix of a scene camera: pixel centres at integers, not at + 0.5."""
    Kc = np.array(K, float)
    Kc[0, 2] -= 0.5
    Kc[1, 2] -= 0.5
    return Kc


def project(rays_world, R, Kc, dist):
    """OpenCV's projection of world directions seen from the camera centre (origin)."""
    rvec, _ = cv2.Rodrigues(R)
    pts = rays_world.reshape(-1, 3)
    img, _ = cv2.projectPoints(pts, rvec, np.zeros(3), Kc, np.asarray(dist, float))
    return img.reshape(rays_world.shape[:-1] + (2,))


@pytest.mark.parametrize("dist", [DIST, (-0.15, 0.0, 0.0, 0.0, 0.0)])
def test_pixel_rays_project_back_onto_pixel_centres_and_corners(dist):
    cam = parse_scene(scene_doc(dist=dist)).camera
    K = cam.intrinsics()
    R = look_at_rotation(cam.position, cam.look_at, cam.up)
    Kc = opencv_K(K)
    # pixel centres: OpenCV's (i, j) for the scene's (i + 0.5, j + 0.5)
    d = rays_from_normalized(R, *pixel_grid(K, W, H, dist))
    uv = project(d, R, Kc, dist)
    jj, ii = np.mgrid[0:H, 0:W]
    err = np.hypot(uv[..., 0] - ii, uv[..., 1] - jj)
    # the frame's corners are where k1 = -0.15 moves pixels most (tens of pixels here)
    x, y = pixel_grid(K, W, H, dist)
    shift = np.hypot(x - (ii + 0.5 - K[0, 2]) / K[0, 0], y - (jj + 0.5 - K[1, 2]) / K[1, 1])
    assert shift[0, 0] * K[0, 0] > 10  # the distortion is not negligible there
    assert err.max() < 1e-6
    assert err[0, 0] < 1e-6 and err[-1, -1] < 1e-6 and err[0, -1] < 1e-6 and err[-1, 0] < 1e-6
    # pixel corners (anti-aliasing edges): OpenCV's (i - 0.5, j - 0.5)
    dc = rays_from_normalized(R, *pixel_grid(K, W, H, dist, corners=True))
    uvc = project(dc, R, Kc, dist)
    jc, ic = np.mgrid[0 : H + 1, 0 : W + 1]
    assert np.hypot(uvc[..., 0] - (ic - 0.5), uvc[..., 1] - (jc - 0.5)).max() < 1e-6
    # arbitrary sub-pixel points (the anti-aliasing sub-rays)
    rng = np.random.default_rng(3)
    u, v = rng.uniform(0, W, 500), rng.uniform(0, H, 500)
    uvs = project(camera_rays(K, R, u, v, dist), R, Kc, dist)
    assert np.hypot(uvs[:, 0] - (u - 0.5), uvs[:, 1] - (v - 0.5)).max() < 1e-6


def test_newton_inverse_beats_opencvs_default_undistortion():
    # The reason for the own iteration: cv2.undistortPoints (5 iterations) is off by
    # far more than 1e-10 in the corners of a k1 = -0.15 frame.
    xd = np.array([0.7, -0.65, 0.5])
    yd = np.array([0.5, 0.48, -0.45])
    x, y = undistort_normalized(xd, yd, DIST)
    xr, yr = distort_normalized(x, y, DIST)
    assert np.hypot(xr - xd, yr - yd).max() < 1e-10
    cv = cv2.undistortPoints(np.stack([xd, yd], -1)[:, None], np.eye(3), np.array(DIST))
    xc, yc = cv.reshape(-1, 2).T
    assert np.hypot(xc - x, yc - y).max() > 1e-6
    # ... and OpenCV's forward model agrees with distort_normalized
    pts = np.stack([x, y, np.ones_like(x)], -1)
    img, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.array(DIST))
    assert np.abs(img.reshape(-1, 2) - np.stack([xd, yd], -1)).max() < 1e-12


def test_no_distortion_gives_todays_rays_bit_for_bit():
    cam = parse_scene(scene_doc(dist=None)).camera
    K = cam.intrinsics()
    R = look_at_rotation(cam.position, cam.look_at, cam.up)

    def old_camera_rays(u, v):  # the renderer's rays before distortion existed
        x = (u - K[0, 2]) / K[0, 0]
        y = (v - K[1, 2]) / K[1, 1]
        d = np.stack([x, y, np.ones_like(x)], axis=-1) @ R
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    jj, ii = np.mgrid[0:H, 0:W]
    jc, ic = np.mgrid[0 : H + 1, 0 : W + 1]
    for dist in (None, (0.0, 0.0, 0.0, 0.0, 0.0)):
        centres = rays_from_normalized(R, *pixel_grid(K, W, H, dist))
        assert np.array_equal(centres, old_camera_rays(ii + 0.5, jj + 0.5))
        corners = rays_from_normalized(R, *pixel_grid(K, W, H, dist, corners=True))
        assert np.array_equal(corners, old_camera_rays(ic.astype(float), jc.astype(float)))
        u = np.array([0.25, 17.75, 300.1])
        assert np.array_equal(camera_rays(K, R, u, u / 2, dist), old_camera_rays(u, u / 2))
    a = render(parse_scene(scene_doc(dist=None)))
    b = render(parse_scene(scene_doc(dist=(0.0,) * 5)))
    assert np.array_equal(a.radiance, b.radiance)


def test_distorted_render_sees_the_surface_where_opencv_projects_it():
    doc = scene_doc()
    doc["holder"] = {"width": 1.0, "height": 1.0}  # fills the frame, corners included
    res = render(parse_scene(doc))
    cam = parse_scene(doc).camera
    R = look_at_rotation(cam.position, cam.look_at, cam.up)
    seen = np.isfinite(res.points[..., 0])
    rvec, _ = cv2.Rodrigues(R)
    tvec = -R @ np.asarray(cam.position)
    img, _ = cv2.projectPoints(
        res.points[seen], rvec, tvec, opencv_K(cam.intrinsics()), np.array(DIST)
    )
    jj, ii = np.nonzero(seen)
    err = np.hypot(img[:, 0, 0] - ii, img[:, 0, 1] - jj)
    assert seen.all()
    assert err.max() < 1e-6


def test_vignetting_follows_the_true_ray_angle():
    cam = parse_scene(scene_doc()).camera
    flat = np.ones((H, W, 3))
    on = mean_electrons(flat, cam, 0.01, 8.0)
    off_cam = cam.model_copy(update={"sensor": cam.sensor.model_copy(update={"vignetting": False})})
    ratio = on / mean_electrons(flat, off_cam, 0.01, 8.0)
    # reference: the field angle of each pixel from OpenCV's iterative undistortion
    jj, ii = np.mgrid[0:H, 0:W]
    pts = np.stack([ii, jj], -1).reshape(-1, 1, 2).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-16)
    und = cv2.undistortPoints(
        pts, opencv_K(cam.intrinsics()), np.array(DIST), None, None, criteria=crit
    ).reshape(H, W, 2)
    cos_theta = 1 / np.sqrt(1 + (und**2).sum(-1))
    assert np.abs(ratio[..., 1] / cos_theta**4 - 1).max() < 1e-9
    # with k1 < 0 the corner's true angle is wider than its pinhole angle: darker
    K = cam.intrinsics()
    r2_pin = ((0.5 - K[0, 2]) ** 2 + (0.5 - K[1, 2]) ** 2) / K[0, 0] ** 2
    assert ratio[0, 0, 1] < 0.97 / (1 + r2_pin) ** 2


def test_a_distortion_that_folds_over_is_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"camera\.distortion.*not invertible"):
        render(parse_scene(scene_doc(dist=(-2.0, 0.0, 0.0, 0.0, 0.0))))


def test_the_pixel_grid_is_computed_once_per_camera():
    cam = parse_scene(scene_doc()).camera
    K = cam.intrinsics()
    a = pixel_grid(K, W, H, DIST)
    assert pixel_grid(K, W, H, DIST)[0] is a[0]
    assert pixel_grid(K, W, H, (-0.1, 0, 0, 0, 0))[0] is not a[0]


def test_board_pose_from_a_distorted_render_needs_the_true_distortion():
    from gonio.capture.fiducials import BoardSpec, detect_pose, grey_from_mosaic
    from gonio.capture.raw import read_raw
    from gonio.simulator.camera import SimulatedCamera

    doc = scene_doc(fov=40.0, resolution=(800, 600), pp=(409.3, 292.6))
    doc["camera"]["position"] = [0.03, -0.12, 0.2]
    scene = parse_scene(doc)
    cam = SimulatedCamera(scene)
    frame = read_raw(cam.capture(3e-4, 100, 8.0, seed=1), name="distorted")
    C = np.asarray(scene.camera.position)
    R = look_at_rotation(C, scene.camera.look_at, scene.camera.up)
    Kc = opencv_K(scene.camera.intrinsics())
    grey = grey_from_mosaic(frame)
    board = BoardSpec()
    good = detect_pose(grey, board, Kc, np.array(DIST))
    bad = detect_pose(grey, board, Kc, None)
    errs = {}
    for name, pose in (("true dist", good), ("dist = 0", bad)):
        mm = np.linalg.norm(pose.position - C) * 1e3
        deg = np.degrees(pose.angle_to(R))
        errs[name] = (mm, deg, pose.reprojection_rms)
        print(f"{name}: {mm:.3f} mm, {deg:.4f} deg, rms {pose.reprojection_rms:.3f} px")
    mm, deg, rms = errs["true dist"]
    assert mm < 0.5 and deg < 0.1 and rms < 0.5
    mm0, deg0, rms0 = errs["dist = 0"]
    assert rms0 > 4 * rms and (mm0 > 2 * mm or deg0 > 2 * deg)
