"""``[reduction] geometry``: where a pose's camera comes from, and what is flagged.

Frames are rendered by the simulated camera at placed poses (the demo's scene at its
320 x 240), so the truth of every pose is known: the rig's report is exact unless a test
turns it.  ``auto`` takes the board where it shows ``min_board_corners`` corners and is
seen at most ``max_board_obliquity_deg`` off its normal, else the rig's pose without a
flag; a trusted board still flags a rig that disagrees with it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.app.demo import parse_material, scene_document
from gonio.app.sim_reduction import setup_from_scene
from gonio.capture.pose_measure import board_obliquity_deg, measure_pose
from gonio.capture.raw import read_raw
from gonio.dataset import Flag
from gonio.radiometry import look_at_rotation, rotation_about, spherical_to_direction

pytestmark = pytest.mark.slow

FULL_WELL_DN = 15871.0


def place(theta_o, phi_o=90.0, theta_i=35.0):
    lp = 0.5 * spherical_to_direction(math.radians(theta_i), 0.0)
    cp = 0.4 * spherical_to_direction(math.radians(theta_o), math.radians(phi_o))
    return {
        "light_position": lp,
        "light_normal": -lp / np.linalg.norm(lp),
        "camera_position": cp,
        "camera_rotation": look_at_rotation(cp, np.zeros(3)).T,
    }


@pytest.fixture(scope="module")
def views():
    from gonio.simulator.camera import SimulatedCamera
    from gonio.simulator.scene import parse_scene
    from gonio.simulator.sensor import mean_electrons

    scene = parse_scene(scene_document(parse_material("lambert albedo=0.5"), 320, 240))
    state = {}
    cam = SimulatedCamera(scene, pose_provider=lambda: state["pose"])
    out = {}
    for k, theta_o in enumerate((20.0, 72.0)):
        state["pose"] = pose = place(theta_o)
        truth = cam.render("sample")
        e = mean_electrons(truth.radiance, scene.camera, 1.0, 8.0)
        t = 0.5 * FULL_WELL_DN / scene.camera.sensor.gain_at_base_iso / e.max()
        frames = [
            read_raw(cam.capture(tt, 100, 8.0, seed=10 * k + j), name=f"v{k}f{j}")
            for j, tt in enumerate((t, 4 * t))
        ]
        out[theta_o] = (pose, frames)
    return setup_from_scene(scene, 0.99).replace(grid=3), out


def measure(setup, pose, frames, *, turn_deg=0.0):
    """The pose measured with the rig reporting the camera turned by ``turn_deg`` about
    the sample's x axis (about the sample centre: direction and position both off)."""
    R = rotation_about(np.array([1.0, 0.0, 0.0]), math.radians(turn_deg))
    cp = R @ pose["camera_position"]
    c2s = R @ pose["camera_rotation"]
    return measure_pose(
        frames,
        setup,
        pose["light_position"],
        pose["light_normal"],
        reported_wo=cp / np.linalg.norm(cp),
        reported_camera=(cp, c2s.T),
    )


def mismatch(m):
    return bool((m.flags & Flag.GEOMETRY_MISMATCH).any())


def test_auto_takes_a_trustworthy_board_and_it_still_checks_the_rig(views):
    setup, out = views
    pose, frames = out[20.0]
    assert setup.geometry == "auto"  # the default
    m = measure(setup, pose, frames)
    assert m.geometry_source == "board" and not mismatch(m), m.reasons[0]
    assert m.camera.n_corners >= setup.min_board_corners
    # the board's own obliquity is the placed theta_o (an independent number)
    assert abs(board_obliquity_deg(m.camera) - 20.0) < 0.5
    # the board's pose, not the rig's (which is exact here): close, but not the same
    assert 0 < np.linalg.norm(m.camera.position - pose["camera_position"]) < 0.005
    # a rig 1 deg off is a real disagreement: flagged, with the reason
    off = measure(setup, pose, frames, turn_deg=1.0)
    assert off.geometry_source == "board" and mismatch(off)
    assert any("camera direction from the board" in r for r in off.reasons[0])
    assert (off.flags & Flag.GEOMETRY_MISMATCH).all()


def test_auto_falls_back_to_the_rig_unflagged_where_the_board_is_not_trustworthy(views):
    setup, out = views
    pose, frames = out[20.0]
    for limits in ({"max_board_obliquity_deg": 15.0}, {"min_board_corners": 40}):
        # a board taken as untrustworthy says nothing against a rig 1 deg off
        m = measure(setup.replace(**limits), pose, frames, turn_deg=1.0)
        assert m.geometry_source == "rig" and not mismatch(m), (limits, m.reasons[0])
    # a grazing view: the board shows too little of itself (or nothing) at 72 deg
    pose, frames = out[72.0]
    m = measure(setup, pose, frames)
    assert m.geometry_source == "rig" and not mismatch(m), m.reasons[0]
    np.testing.assert_array_equal(m.camera.position, pose["camera_position"])
    assert (m.flags == 0).any()  # its regions are measured
    # "board" there: the rig's pose stands in only with a flag when the board is lost,
    # and a board found is used as it is
    b = measure(setup.replace(geometry="board"), pose, frames)
    if b.geometry_source == "rig":
        assert mismatch(b) and "board not found" in b.reasons[0][0]
    else:
        assert b.camera.n_corners < setup.min_board_corners or (
            board_obliquity_deg(b.camera) > setup.max_board_obliquity_deg
        )


def test_rig_takes_the_rigs_pose_and_the_board_checks_it(views):
    setup, out = views
    pose, frames = out[20.0]
    rig = setup.replace(geometry="rig")
    m = measure(rig, pose, frames)
    assert m.geometry_source == "rig" and not mismatch(m)
    np.testing.assert_array_equal(m.camera.position, pose["camera_position"])
    off = measure(rig, pose, frames, turn_deg=1.0)
    assert off.geometry_source == "rig" and mismatch(off)
