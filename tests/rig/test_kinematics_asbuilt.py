"""Kinematics of an as-built (calibrated) rig configuration.

The reference forward model is :func:`gonio.rig.asbuilt.rig_poses` (its own module,
tested against the nominal closed form); the approach signs a move implies are computed
here from the joint changes by hand.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.radiometry import spherical_to_direction
from gonio.radiometry.frames import rotation_about
from gonio.rig import asbuilt
from gonio.rig.config import JOINT_NAMES, default_rig_config, rig_config_from_dict
from gonio.rig.kinematics import Kinematics, is_nominal


def angle(a, b):
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)))


def asbuilt_config(rng: np.random.Generator, *, pitch_deg: float | None = None):
    """The default preset with random as-built terms of a few times the realistic size."""
    d = default_rig_config().model_dump()
    for s in d["servos"]:
        s["backlash_deg"] = float(rng.uniform(0.1, 0.5))
        s["zero_deg"] += float(rng.normal(0, 1.5))
        if s["joint"] == "stage_tilt":
            s["compliance_deg"] = tuple(float(x) for x in rng.normal(0, 0.3, 2))
    g = d["geometry"]
    g["light_elevation_deg"] = float(rng.normal(0, 0.5))
    g["camera_elevation_deg"] = float(rng.normal(0, 0.5))
    g["camera_mount_deg"] = tuple(float(x) for x in rng.normal(0, 1.0, 3))
    g["holder_tilt_deg"] = tuple(float(x) for x in rng.normal(0, 0.5, 2))
    g["holder_offset_m"] = tuple(float(x) for x in rng.normal(0, 0.002, 3))
    g["stage_offset_m"] = (*(float(x) for x in rng.normal(0, 0.002, 2)), 0.0)
    # The tilt axis pitched out of the horizontal plane (canonical tilt_axis_pitch).
    k0 = np.asarray(g["tilt_axis"], float)
    pitch = math.radians(rng.normal(0, 1.0) if pitch_deg is None else pitch_deg)
    axis = np.cross(k0, [0.0, 0.0, 1.0])
    k = rotation_about(axis / np.linalg.norm(axis), pitch) @ k0
    g["tilt_axis"] = tuple(float(x) for x in k)
    return rig_config_from_dict(d)


def hand_approach(config, current, q):
    """+1 / -1 by the sign of each joint's change, from an unknown side: a move shorter
    than the backlash's play plus the deadband does not take the play up, and the rig
    approaches such a goal from below (a pre-move), so its side is +1."""
    out = {}
    for s in config.servos:
        dp = round(s.pulses(q[s.joint])) - round(s.pulses(current[s.joint]))
        assert dp != 0, "the test poses move every joint"
        play = s.backlash_deg * s.gear_ratio * 4096 / 360
        if abs(dp) <= math.ceil(play) + config.motion.position_tolerance_pulses:
            out[s.joint] = 1
        else:
            out[s.joint] = 1 if (q[s.joint] - current[s.joint]) > 0 else -1
    return out


REQUESTS = [
    ((30, 0), (40, 180)),
    ((50, 20), (20, 140)),
    ((10, 90), (60, 300)),
    ((45, 200), (45, 70)),
]


@pytest.mark.parametrize("seed", range(6))
def test_forward_of_inverse_meets_the_request_on_random_asbuilt_rigs(seed):
    rng = np.random.default_rng(seed)
    cfg = asbuilt_config(rng, pitch_deg=8.0 if seed == 0 else None)
    assert not is_nominal(cfg)
    kin = Kinematics(cfg)
    current = cfg.home_rad
    n_met = 0
    for (ti, pi), (to, po) in REQUESTS:
        wi = spherical_to_direction(math.radians(ti), math.radians(pi))
        wo = spherical_to_direction(math.radians(to), math.radians(po))
        if kin.refusal(wi, wo, current) is not None:
            continue
        q = kin.inverse(wi, wo, current)
        appr = hand_approach(cfg, current, q)
        rp = asbuilt.rig_poses(cfg, q, appr)
        assert angle(rp.wi, wi) < 1e-9
        assert angle(rp.wo, wo) < 1e-9
        # The same joints read without the approach (or with the other side) miss by
        # about the backlash: the signs matter and the inverse used the right ones.
        flipped = asbuilt.rig_poses(cfg, q, {j: -v for j, v in appr.items()})
        assert max(angle(flipped.wi, wi), angle(flipped.wo, wo)) > 1e-4
        # Kinematics.forward with the approach agrees with the reference model.
        fi, fo = kin.forward(q, appr)
        assert angle(fi, rp.wi) < 1e-12 and angle(fo, rp.wo) < 1e-12
        current = q
        n_met += 1
    assert n_met >= 3


def test_joint_that_does_not_move_keeps_its_approach():
    rng = np.random.default_rng(11)
    cfg = asbuilt_config(rng)
    kin = Kinematics(cfg)
    wi = spherical_to_direction(math.radians(30), 0.0)
    wo = spherical_to_direction(math.radians(40), math.pi)
    q = kin.inverse(wi, wo, cfg.home_rad)
    appr_q = hand_approach(cfg, cfg.home_rad, q)
    # Asked again from q with the approach q really has: nothing needs to move.
    q1 = kin.inverse(wi, wo, q, approach=appr_q)
    for s in cfg.servos:
        assert round(s.pulses(q1[s.joint])) == round(s.pulses(q[s.joint]))
    # Told every joint came from the other side, the joints on the wrong side must move
    # across the backlash (by about it, the side the move then comes from).
    other = {j: -v for j, v in appr_q.items()}
    q2 = kin.inverse(wi, wo, q, approach=other)
    appr2, moved = {}, 0
    for s in cfg.servos:
        j = s.joint
        dp = round(s.pulses(q2[j])) - round(s.pulses(q[j]))
        appr2[j] = other[j] if dp == 0 else (1 if q2[j] > q[j] else -1)
        if dp:
            moved += 1
            assert abs(q2[j] - q[j]) == pytest.approx(math.radians(s.backlash_deg), rel=0.2)
    assert moved and appr2 == other  # they moved down: from above, as they were told
    rp = asbuilt.rig_poses(cfg, q2, appr2)
    assert angle(rp.wi, wi) < 1e-9 and angle(rp.wo, wo) < 1e-9


def test_nominal_config_is_recognised_and_unchanged():
    cfg = default_rig_config()
    assert is_nominal(cfg)
    kin = Kinematics(cfg)
    q = {"light_azimuth": -0.7, "camera_azimuth": 0.4, "stage_tilt": 0.3, "stage_spin": 1.1}
    # Nominal: the approach does not matter, and the closed form is what rig_poses gives.
    a = kin.forward(q)
    b = kin.forward(q, dict.fromkeys(JOINT_NAMES, -1))
    np.testing.assert_array_equal(a[0], b[0])
    rp = asbuilt.rig_poses(cfg, q)
    np.testing.assert_allclose(a[0], rp.wi, atol=1e-14)
    np.testing.assert_allclose(a[1], rp.wo, atol=1e-14)
    # Any single as-built term makes the config as-built.
    d = cfg.model_dump()
    d["servos"][2]["backlash_deg"] = 0.2
    assert not is_nominal(rig_config_from_dict(d))


def test_asbuilt_poses_match_the_reference_model():
    rng = np.random.default_rng(3)
    cfg = asbuilt_config(rng)
    kin = Kinematics(cfg)
    q = {"light_azimuth": -0.7, "camera_azimuth": 0.4, "stage_tilt": 0.3, "stage_spin": 1.1}
    appr = {"light_azimuth": 1, "camera_azimuth": -1, "stage_tilt": 1, "stage_spin": 0}
    got = kin.poses(q, appr)
    ref = asbuilt.rig_poses(cfg, q, appr)
    for name in ("wi", "wo", "light_position", "light_normal", "camera_position"):
        np.testing.assert_allclose(getattr(got, name), getattr(ref, name), atol=1e-14)
    np.testing.assert_allclose(got.camera_rotation, ref.camera_rotation, atol=1e-14)
    # the light's normal is not -wi once the sample is off the rotation centre
    assert angle(got.light_normal, -got.wi) > 1e-5


def test_inverse_and_rig_judge_a_deadband_move_as_the_session_journals_it():
    """The inverse's approach signs (``_move_signs``) are :func:`approach_of_move`'s for
    moves of 0, 1 and more pulses: within the position tolerance the side is kept."""
    import math

    from gonio.rig.config import JOINT_NAMES, default_rig_config
    from gonio.rig.kinematics import Kinematics, approach_of_move

    cfg = default_rig_config()
    kin = Kinematics(cfg)
    ref = {j: 0.1 for j in JOINT_NAMES}
    pulse = 2 * math.pi / 4096
    for steps in (-3, -1, 0, 1, 2):
        q = {j: ref[j] + steps * pulse for j in JOINT_NAMES}
        for keep in (-1, 1):
            appr = dict.fromkeys(JOINT_NAMES, keep)
            want = approach_of_move(cfg, ref, q, appr)
            got = kin._move_signs(np.array([[q[j] for j in JOINT_NAMES]]), ref, appr)[0]
            assert dict(zip(JOINT_NAMES, got.astype(int).tolist(), strict=True)) == want, steps
            if abs(steps) <= cfg.motion.position_tolerance_pulses:
                assert set(want.values()) == {keep}
