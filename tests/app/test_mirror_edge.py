"""``gonio calibrate rig`` leaves out mirror spots the mirror's edge cuts, and only those.

The light's image is rendered in a 50 mm mirror (the simulator's mirror target) with its
reflection point walked towards the edge.  The reference is the closed form: the image of
a point in a flat mirror is the projection of its reflection.  Spots the rule keeps must
sit on it; spots whose centroid the edge biases must be refused.  A fixed 7 mm margin
refused every spot beyond 18 mm, which left worlds with large arm offsets (world 129347241
of the lab walkthrough) with fewer than the six mirror views the light needs.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gonio.app.calibrate_rig_cli import edge_problems
from gonio.capture.mirror_spot import SpotError, spot_centroid
from gonio.rig.calibration import CameraPrior
from gonio.rig.calibration_data import BoardObservation, SpotObservation
from gonio.simulator.render import render
from gonio.simulator.rig_camera import minimal_scene
from gonio.simulator.scene import look_at_rotation, parse_scene

CAMERA = np.array([0.0, -0.25, 0.433])
LIGHT_HEIGHT = 0.54  # m above the mirror
HALF = 0.025  # the mirror's half-size, m
# The board's inner corners around the mirror (20 mm squares), in the sample frame.
BOARD = np.array(
    [
        [x, y, 0.0]
        for x in np.arange(-0.05, 0.051, 0.02)
        for y in np.arange(-0.05, 0.051, 0.02)
        if max(abs(x), abs(y)) > 0.03
    ]
)


def _scene(reflection_point):
    """A scene whose light reflects into the camera at ``reflection_point`` (x, y, 0)."""
    P = np.asarray(reflection_point, float)
    mirrored = P + (P - CAMERA) * (LIGHT_HEIGHT / CAMERA[2])
    d = minimal_scene(480, 360)
    d["lights"][0].update(position=list(mirrored * [1.0, 1.0, -1.0]), radius=0.004)
    d["camera"].update(look_at=[0.0, 0.0, 0.0], fov_deg=16.0)
    d["render"].update(antialias=4, spot_antialias=16)
    return parse_scene(d).with_mirror_target()


def _truth(scene):
    """Camera matrix, pose, and the closed-form image of the mirrored light's centre."""
    cam = scene.camera
    C = np.asarray(cam.position, float)
    R = look_at_rotation(C, cam.look_at, cam.up)
    K = np.array(cam.intrinsics(), float)
    K[0, 2] -= 0.5  # OpenCV's pixel centres
    K[1, 2] -= 0.5
    rvec, _ = cv2.Rodrigues(R)
    tvec = -R @ C
    light = np.asarray(scene.lights[0].position, float) * [1.0, 1.0, -1.0]
    ref = cv2.projectPoints(light[None], rvec, tvec, K, np.zeros(5))[0].reshape(2)
    return K, rvec, tvec, ref


@pytest.mark.parametrize(
    "x_mm, cut",
    [(0.0, False), (15.0, False), (20.0, False), (21.5, False), (24.0, True), (25.0, True)],
)
def test_spots_the_edge_cuts_are_refused_and_the_others_kept(x_mm, cut):
    scene = _scene((x_mm * 1e-3, 0.004, 0.0))
    K, rvec, tvec, ref = _truth(scene)
    try:
        u, v, info = spot_centroid(render(scene).radiance[..., 1])
    except SpotError:
        pytest.fail(f"{x_mm} mm: no spot found")
    err = float(np.hypot(u - ref[0], v - ref[1]))
    r0, r1, c0, c1 = info["box"]
    spot = SpotObservation("p", {}, {}, np.array([u, v]), (c0 - 0.5, r0 - 0.5, c1 - 0.5, r1 - 0.5))
    uv = cv2.projectPoints(BOARD, rvec, tvec, K, np.zeros(5))[0][:, 0]
    board = BoardObservation("p", {}, {}, BOARD, uv)
    why = edge_problems([board], [spot], CameraPrior(K, np.zeros(5), np.ones(4), np.ones(5)),
                        (HALF, HALF))  # fmt: skip
    if cut:
        assert err > 0.3, f"{x_mm} mm: the edge should bias the centroid ({err:.3f} px)"
        assert "p" in why and "edge" in why["p"], why
    else:
        assert err < 0.01, f"{x_mm} mm: centroid off the closed form by {err:.4f} px"
        assert why == {}, why


def test_a_spot_without_its_box_keeps_the_fixed_margin():
    """Observations that do not say which pixels the centroid summed (older callers) are
    judged by the reflection point and ``MIRROR_MARGIN_M``."""
    from gonio.app.calibrate_rig_cli import MIRROR_MARGIN_M

    scene = _scene((0.0, 0.0, 0.0))
    K, rvec, tvec, _ref = _truth(scene)
    board = BoardObservation(
        "p", {}, {}, BOARD, cv2.projectPoints(BOARD, rvec, tvec, K, np.zeros(5))[0][:, 0]
    )
    cam = CameraPrior(K, np.zeros(5), np.ones(4), np.ones(5))
    for x, refused in (
        (HALF - MIRROR_MARGIN_M - 1e-3, False),
        (HALF - MIRROR_MARGIN_M + 1e-3, True),
    ):
        pt = np.array([[x, 0.0, 0.0]])
        uv = cv2.projectPoints(pt, rvec, tvec, K, np.zeros(5))[0].reshape(2)
        why = edge_problems([board], [SpotObservation("p", {}, {}, uv)], cam, (HALF, HALF))
        assert ("p" in why) == refused, (x, why)
