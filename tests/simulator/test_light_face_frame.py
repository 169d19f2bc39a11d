"""The light's face non-uniformity belongs to the light body: on a rig the light is fixed
to its arm, so the face pattern turns with the arm and stays put while the stage tilts
and spins.  (Before, the disk's tangent frame was built from the sample frame's x axis,
so the pattern turned with the stage; the mirror spot's centroid then moved with the
holder's spin and the rig calibration took it for a holder tilt: world seed 2086854768,
holder_tilt_y 5.8 std off its truth.)"""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from gonio.errors import ConfigError
from gonio.rig.config import default_rig_document
from gonio.simulator.lights import prepare_lights
from gonio.simulator.scene import parse_scene, scene_with_rig_poses
from gonio.simulator.world import draw_world
from gonio.simulator.world_kinematics import poses_from_joints

DOC = tomllib.loads(default_rig_document())
SCENE = {
    "sample": {"width": 0.05, "height": 0.05,
               "brdf": {"model": "lambert", "params": {"albedo": 0.5}}},
    "lights": [{"type": "disk", "position": [0.0, 0.25, 0.433], "look_at": [0.0, 0.0, 0.0],
                "radius": 0.002, "radiance": [1.0, 1.0, 1.0], "gradient": 0.04,
                "gradient_angle_deg": 40.0}],
    "camera": {"resolution": [64, 48], "focal_length": 0.035, "fov_deg": 30.0,
               "position": [0.0, -0.25, 0.433]},
}  # fmt: skip


def _gradient_direction_in_the_lab(q: dict) -> tuple[np.ndarray, np.ndarray]:
    """(unit direction of the face gradient, light centre), lab frame, at true joints q."""
    world = draw_world("realistic", 7)
    poses = poses_from_joints(world, DOC, q)
    light = prepare_lights(scene_with_rig_poses(parse_scene(SCENE), poses))[0]
    f1, f2 = light.f1, light.f2
    c, s = math.cos(light.gradient_angle), math.sin(light.gradient_angle)
    M, T = poses.sample_to_world, poses.sample_origin
    # the face's own evaluation along the direction, as the renderer sees it
    d = c * f1 + s * f2
    y = light.center + 0.5 * light.size[0] * d
    assert light.face(y[None])[0] > 1.0
    return M @ d, M @ light.center + T


def test_the_face_pattern_stays_with_the_light_when_the_stage_moves():
    base = {"light_azimuth": math.radians(-40), "camera_azimuth": math.radians(40)}
    ref, centre = _gradient_direction_in_the_lab({**base, "stage_tilt": 0.0, "stage_spin": 0.0})
    for tilt, spin in ((0.0, 90.0), (0.0, 180.0), (-20.0, -90.0), (25.0, 33.0)):
        q = {**base, "stage_tilt": math.radians(tilt), "stage_spin": math.radians(spin)}
        d, c = _gradient_direction_in_the_lab(q)
        np.testing.assert_allclose(c, centre, atol=1e-12)  # the light did not move
        np.testing.assert_allclose(d, ref, atol=1e-12, err_msg=f"tilt {tilt}, spin {spin}")


def test_the_face_pattern_turns_with_the_light_arm():
    q = {"camera_azimuth": math.radians(40), "stage_tilt": 0.0, "stage_spin": 0.0}
    d0, c0 = _gradient_direction_in_the_lab({**q, "light_azimuth": math.radians(-40)})
    for az in (-10.0, -75.0, 20.0):
        d, c = _gradient_direction_in_the_lab({**q, "light_azimuth": math.radians(az)})
        turn = math.radians(az + 40)
        Rz = np.array([[math.cos(turn), -math.sin(turn), 0], [math.sin(turn), math.cos(turn), 0],
                       [0, 0, 1]])  # fmt: skip
        np.testing.assert_allclose(Rz @ c0, c, atol=1e-12)  # the arm turns about the lab z
        np.testing.assert_allclose(Rz @ d0, d, atol=1e-12, err_msg=f"azimuth {az}")


def test_a_scene_without_a_body_frame_keeps_its_tangent_frame():
    light = prepare_lights(parse_scene(SCENE))[0]
    assert light.f1 is light.e1 and light.f2 is light.e2  # bit for bit the old face


def test_a_face_up_along_the_normal_is_refused_when_the_scene_is_read():
    doc = {**SCENE, "lights": [{**SCENE["lights"][0], "face_up": [0.0, -0.25, -0.433]}]}
    with pytest.raises(ConfigError, match=r"face_up \[0\.0, -0\.25, -0\.433\].*face plane"):
        parse_scene(doc)
