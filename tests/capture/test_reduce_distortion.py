"""The reduction with a distorting lens: rays undistorted, results as without distortion.

The simulator's renderer has no lens distortion in this branch (``Camera.distortion`` is
being added to it in parallel), so the distorted frames are made here: the scene is
rendered noise-free at twice the resolution through the pinhole, and each pixel of the
distorted 1x image averages that render at its four sub-pixel centres' *undistorted*
positions.  The inverse of the Brown-Conrady model is this file's own Newton iteration on
the closed-form forward model (checked against ``cv2.projectPoints``), independent of the
OpenCV iteration the reduction uses.  With zero distortion the same construction is an
exact 2x2 binning of the render: the undistorted reference.  The sensor (noise, clipping,
cos^4 vignetting at each pixel's place on the sensor) and the DNG round trip are the
simulator's own.

Checks: the distorted frames reduced with their ``dist`` give the reference's per-region
radiance ratios (``L / G``) within the noise and its directions; reduced as if the lens
were a pinhole they are measurably wrong; OpenCV's inversion round-trips to < 1e-6 px and
agrees with the Newton inverse; the ROI box holds the sample's distorted image.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from gonio.app.sim_reduction import setup_from_scene
from gonio.capture.fiducials import (
    UNDISTORT_TOLERANCE_PX,
    undistorted_coordinates,
)
from gonio.capture.pose_measure import measure_pose
from gonio.capture.raw import read_raw
from gonio.radiometry import spherical_to_direction

pytestmark = pytest.mark.slow

#: A strong barrel lens with a little decentring (k1, k2, p1, p2, k3): at the 400x300
#: image's corners it moves pixels by ~9 px.
DIST = np.array([-0.35, 0.12, 0.0015, -0.001, 0.0])
LIGHT = {
    "type": "disk",
    "position": [0.0, 0.25, 0.433],
    "look_at": [0, 0, 0],
    "radius": 0.01,
    "radiance": [2e4, 2e4, 2e4],
}
# (theta_i, phi_i, theta_o, phi_o) deg: on the specular lobe's flanks, where a direction
# error shows in the BRDF
POSES = [(30, 0, 50, 180), (45, 0, 30, 180)]
FULL_WELL_DN = 15871.0


def scene_doc(width: int, height: int) -> dict:
    return {
        "sample": {
            "width": 0.05,
            "height": 0.05,
            "brdf": {"model": "ggx", "params": {"alpha": 0.15, "ks": 0.8}},
        },
        "holder": {"width": 0.16, "height": 0.16, "board": {}},
        "lights": [LIGHT],
        "camera": {
            "resolution": [width, height],
            "focal_length": 0.016,
            "fov_deg": 30.0,
            "position": [0.1, -0.2, 0.35],
            "look_at": [0, 0, 0],
        },
        "render": {"strategy": "quadrature", "quadrature_order": 1},
    }


def brown_conrady(x, y, dist):
    """OpenCV's forward model on normalised coordinates, written out (k1, k2, p1, p2, k3)."""
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (
        x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    )


def newton_undistort(xd, yd, dist, steps=30):
    """Invert :func:`brown_conrady` by Newton's method with the analytic Jacobian."""
    k1, k2, p1, p2, k3 = dist
    x, y = xd.copy(), yd.copy()
    for _ in range(steps):
        fx, fy = brown_conrady(x, y, dist)
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        drad = 2 * (k1 + 2 * k2 * r2 + 3 * k3 * r2**2)  # d rad / d x = drad x
        a = rad + x * drad * x + 2 * p1 * y + 6 * p2 * x
        b = x * drad * y + 2 * p1 * x + 2 * p2 * y
        c = y * drad * x + 2 * p1 * x + 2 * p2 * y
        d = rad + y * drad * y + 6 * p1 * y + 2 * p2 * x
        ex, ey = fx - xd, fy - yd
        det = a * d - b * c
        x = x - (d * ex - b * ey) / det
        y = y - (a * ey - c * ex) / det
    return x, y


def distorted_radiance(render2, K1, dist):
    """(H, W, 3) radiance of the distorted 1x image from a (2H, 2W, 3) pinhole render.

    ``K1`` is the 1x camera matrix (OpenCV convention); the 2x render's is ``2 fx`` and
    ``2 c + 0.5``.
    """
    H, W = render2.shape[0] // 2, render2.shape[1] // 2
    v, u = np.mgrid[0:H, 0:W].astype(float)
    out = np.zeros((H, W, 3))
    for du in (-0.25, 0.25):
        for dv in (-0.25, 0.25):
            xd = (u + du - K1[0, 2]) / K1[0, 0]
            yd = (v + dv - K1[1, 2]) / K1[1, 1]
            x, y = newton_undistort(xd, yd, dist)
            u2 = 2 * K1[0, 0] * x + 2 * K1[0, 2] + 0.5
            v2 = 2 * K1[1, 1] * y + 2 * K1[1, 2] + 0.5
            for c in range(3):
                out[..., c] += 0.25 * map_coordinates(
                    render2[..., c], [v2, u2], order=1, mode="nearest"
                )
    return out


@pytest.fixture(scope="module")
def views():
    """Per pose: the rig's poses, the reference bracket and the distorted bracket."""
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.dng import dng_bytes
    from gonio.simulator.scene import parse_scene
    from gonio.simulator.sensor import mean_electrons, simulate_raw

    scene1 = parse_scene(scene_doc(400, 300))
    scene2 = parse_scene(scene_doc(800, 600))
    setup = setup_from_scene(scene1, 0.99)
    kin = Kinematics(default_rig_config())
    state = {}
    cam2 = SimulatedCamera(scene2, pose_provider=lambda: state["poses"])
    out = []
    for k, (ti, pi, to, po) in enumerate(POSES):
        wi = spherical_to_direction(np.radians(ti), np.radians(pi))
        wo = spherical_to_direction(np.radians(to), np.radians(po))
        state["poses"] = rp = kin.poses(kin.inverse(wi, wo))
        render2 = cam2.render("sample").radiance
        brackets = []
        for n, dist in enumerate((np.zeros(5), DIST)):
            rad = distorted_radiance(render2, setup.K, dist)
            e_per_s = mean_electrons(rad, scene1.camera, 1.0, 8.0)
            gain = scene1.camera.sensor.gain_at_base_iso
            t = 0.5 * FULL_WELL_DN / gain / np.percentile(e_per_s, 99.9)
            brackets.append(
                [
                    read_raw(
                        dng_bytes(
                            simulate_raw(
                                rad,
                                scene1.camera,
                                exposure_time=tt,
                                iso=100,
                                f_number=8.0,
                                seed=1000 * k + 10 * n + j,
                            )
                        ),
                        name=f"p{k}d{n}f{j}",
                    )
                    for j, tt in enumerate((t, 4 * t))
                ]
            )
        out.append((rp, *brackets))
    return setup, out, scene1.build_brdf()


def measure(frames, setup, rp):
    return measure_pose(
        frames,
        setup,
        rp.light_position,
        rp.light_normal,
        reported_wo=rp.wo,
        reported_camera=(rp.camera_position, rp.camera_rotation.T),
    )


def angles_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1, 1)))


def test_newton_inverse_is_the_inverse_of_opencvs_model():
    """The test's own inverse and forward model against cv2.projectPoints."""
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-0.3, 0.3, (2, 500))
    xd, yd = brown_conrady(x, y, DIST)
    uv, _ = cv2.projectPoints(
        np.c_[x, y, np.ones_like(x)], np.zeros(3), np.zeros(3), np.eye(3), DIST
    )
    np.testing.assert_allclose(uv.reshape(-1, 2), np.c_[xd, yd], rtol=0, atol=1e-14)
    xu, yu = newton_undistort(xd, yd, DIST)
    np.testing.assert_allclose(np.c_[xu, yu], np.c_[x, y], rtol=0, atol=1e-13)


def test_undistorted_coordinates_round_trip_and_match_newton(views):
    setup, _, _ = views
    box = (slice(0, 300), slice(0, 400))  # the whole image, corners included
    x, y = undistorted_coordinates(setup.K, DIST, box)
    pts = np.c_[x.ravel(), y.ravel(), np.ones(x.size)]
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), setup.K, DIST)
    v, u = np.mgrid[0:300, 0:400]
    err = np.linalg.norm(uv.reshape(-1, 2) - np.c_[u.ravel(), v.ravel()], axis=1)
    assert err.max() < UNDISTORT_TOLERANCE_PX
    K = setup.K
    xn, yn = newton_undistort((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], DIST)
    # 1e-6 px of round trip is 1e-6 / f in normalised units
    np.testing.assert_allclose(x, xn, rtol=0, atol=2e-6 / K[0, 0])
    np.testing.assert_allclose(y, yn, rtol=0, atol=2e-6 / K[1, 1])


def brdf_scale(m, model):
    """(n, 3) ``L / G`` over the true BRDF at the measured directions: the light's
    radiance in camera units, the same for every region when the geometry is right."""
    return m.ratio / model.eval(m.wi, m.wo)


@pytest.mark.parametrize("pose", [0, 1])
def test_distorted_frames_reduce_to_the_undistorted_result(views, pose):
    """With the camera pose from the (exact) rig, so that only the pixels' rays differ:
    one board view's pose is good to a few hundredths of a degree, which on the lobe's
    flank is already a few 1e-3 of BRDF, more than the noise."""
    setup, poses, model = views
    rp, ref_frames, dist_frames = poses[pose]
    rig = setup.replace(geometry="rig")
    ref = measure(ref_frames, rig, rp)
    got = measure(dist_frames, rig.replace(dist=DIST), rp)
    wrong = measure(dist_frames, rig, rp)  # the lens taken for a pinhole
    assert all((m.flags == 0).all() for m in (ref, got, wrong)), (ref.reasons, got.reasons)
    assert got.kernel == ref.kernel == "numba"
    # the ROI's pixels: the distorted image of the same sample cells
    assert abs((got.regions.label >= 0).sum() / (ref.regions.label >= 0).sum() - 1) < 0.1
    # the BRDF each reports, in the light's units taken from the undistorted reduction
    scale = np.median(brdf_scale(ref, model), axis=0)
    rel_std = np.sqrt(ref.ratio_var) / ref.ratio
    err_ref = brdf_scale(ref, model) / scale - 1
    err = brdf_scale(got, model) / scale - 1
    z = (got.ratio - ref.ratio) / np.sqrt(ref.ratio_var + got.ratio_var)
    d_wo = angles_deg(got.wo, ref.wo)
    print(
        f"pose {pose}: median |BRDF error| undistorted {np.median(np.abs(err_ref)):.2e}, "
        f"distorted {np.median(np.abs(err)):.2e}; median rel std {np.median(rel_std):.2e}; "
        f"|z| max {np.abs(z).max():.2f}; wo off by {d_wo.max():.4f} deg"
    )
    # with its dist: the undistorted reduction's BRDF, within the noise
    assert np.median(np.abs(err)) < 2.5 * np.median(rel_std)
    assert np.abs(z).max() < 4.5  # 27 (nearly) independent z-scores
    assert d_wo.max() < 0.01
    # each pixel's point on the sample: the test's own ray through the Newton inverse
    R, C = np.asarray(rp.camera_rotation).T, np.asarray(rp.camera_position)
    off = {}
    for key, m in (("distorted", got), ("dist ignored", wrong)):
        rows, cols = m.regions.box
        v, u = np.mgrid[rows, cols]
        K = setup.K
        x, y = newton_undistort((u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], DIST)
        d = np.stack([x, y, np.ones_like(x)], axis=-1) @ R  # R^T d, sample frame
        s = -C[2] / d[..., 2]
        px = m.regions.label >= 0
        dx = m.regions.xyz[0] - (C[0] + s * d[..., 0])
        dy = m.regions.xyz[1] - (C[1] + s * d[..., 1])
        off[key] = float(np.hypot(dx, dy)[px].max())
    print(f"pose {pose}: pixels' points off by (m) {off}")
    assert off["distorted"] < 1e-9  # 1e-6 px would be ~6e-10 m
    # ignored: near the image centre, where the ROI is, the lens moves pixels by a few
    # hundredths of a pixel (~15 um on the sample), too little to show in the BRDF; the
    # board, out to the image's edges, shows it (test_board_pose_from_distorted_frames)
    assert off["dist ignored"] > 5e-6


@pytest.mark.parametrize("pose", [0, 1])
def test_board_pose_from_distorted_frames(views, pose):
    """The camera pose from the board of a distorted frame (``geometry = "board"``, the
    default): as close to the truth (the rig pose it was rendered at) as from an
    undistorted frame, and millimetres off when the distortion is ignored, which shows
    in the BRDF far beyond the noise."""
    setup, poses, model = views
    rp, ref_frames, dist_frames = poses[pose]
    C = np.asarray(rp.camera_position)
    # the light's scale in camera units from the exact (rig) geometry
    exact = measure(ref_frames, setup.replace(geometry="rig"), rp)
    scale = np.median(brdf_scale(exact, model), axis=0)
    rel_std = np.median(np.sqrt(exact.ratio_var) / exact.ratio)
    out = {}
    for key, frames, su in (
        ("undistorted", ref_frames, setup),
        ("distorted", dist_frames, setup.replace(dist=DIST)),
        ("dist ignored", dist_frames, setup),
    ):
        m = measure(frames, su, rp)
        err = np.median(np.abs(brdf_scale(m, model) / scale - 1))
        out[key] = (np.linalg.norm(m.camera.position - C) * 1e3, m.camera.reprojection_rms, err)
    print(f"pose {pose}: (camera off mm, rms px, median |BRDF error|) {out}; noise {rel_std:.1e}")
    assert out["distorted"][0] < 0.6 and out["undistorted"][0] < 0.6
    assert out["dist ignored"][0] > 1.2
    assert out["distorted"][1] < 0.15 < out["dist ignored"][1]
    assert out["dist ignored"][2] > 5 * rel_std


def test_roi_box_holds_the_distorted_image_of_the_roi(views):
    """Every pixel whose undistorted ray meets the ROI lies inside the box: found over a
    margin around it."""
    from gonio.capture.fiducials import pixel_rays, roi_geometry

    setup, poses, _ = views
    rp, _, dist_frames = poses[1]
    cam = measure(dist_frames, setup.replace(dist=DIST), rp).camera
    roi = roi_geometry(cam, setup.K, (300, 400), setup.sample_size, dist=DIST)
    pin = roi_geometry(cam, setup.K, (300, 400), setup.sample_size)
    assert roi.box != pin.box  # the distortion moved it
    (rs, cs) = roi.box
    big = (slice(max(rs.start - 12, 0), rs.stop + 12), slice(max(cs.start - 12, 0), cs.stop + 12))
    (x, y, _), _ = pixel_rays(cam, setup.K, big, DIST)
    hw, hh = roi.half_size
    inside = (np.abs(x) <= hw) & (np.abs(y) <= hh)
    r, c = np.nonzero(inside)
    r, c = r + big[0].start, c + big[1].start
    assert inside.sum() > 1000
    assert r.min() >= rs.start and r.max() < rs.stop
    assert c.min() >= cs.start and c.max() < cs.stop


def test_opencvs_longer_models_and_a_folding_lens():
    """Eight coefficients (rational model) go through OpenCV's inversion, checked the
    same way; a lens model that folds over inside the crop is refused, naming a pixel."""
    from gonio.errors import ReductionError

    K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
    box = (slice(0, 480), slice(0, 640))
    rational = np.array([-0.2, 0.05, 0.001, 0.0, 0.0, 0.1, 0.0, 0.0])
    x, y = undistorted_coordinates(K, rational, box)
    pts = np.c_[x.ravel(), y.ravel(), np.ones(x.size)]
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, rational)
    v, u = np.mgrid[box]
    err = np.linalg.norm(uv.reshape(-1, 2) - np.c_[u.ravel(), v.ravel()], axis=1)
    assert err.max() < UNDISTORT_TOLERANCE_PX
    # five coefficients: the compiled Newton iteration, against the test's own
    xn, yn = undistorted_coordinates(K, DIST, box)
    xr, yr = newton_undistort((u - 319.5) / 800.0, (v - 239.5) / 800.0, DIST)
    np.testing.assert_allclose(xn, xr, rtol=0, atol=1e-12)
    np.testing.assert_allclose(yn, yr, rtol=0, atol=1e-12)
    with pytest.raises(ReductionError, match=r"cannot be inverted at pixel \(u=\d+, v=\d+\)"):
        undistorted_coordinates(K, [-3.0, 0.0, 0.0, 0.0, 0.0], box)
