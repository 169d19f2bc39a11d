"""The simulator's as-built physics against the controller's (two implementations of one
definition): random worlds, random joints, the world's truth written into a RigConfig by
the table's "calibrated config field" column."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from gonio.radiometry.frames import normalize, rotation_about
from gonio.rig.asbuilt import rig_poses
from gonio.rig.config import RigConfig, default_rig_document, rig_config_from_dict
from gonio.rig.kinematics import Kinematics
from gonio.simulator.world import JOINTS, RIG_PARAMETERS, draw_world
from gonio.simulator.world_kinematics import (
    NominalRig,
    approach_from_servos,
    joint_truth,
    readings_from_pulses,
    true_poses,
)


def _rig_doc(direction_flip: bool = False, gear: float = 1.0) -> dict:
    doc = tomllib.loads(default_rig_document())
    if direction_flip:
        doc["servos"][1]["direction"] = -1 * doc["servos"][1].get("direction", 1)
        doc["servos"][2]["gear_ratio"] = gear
        doc["servos"][2]["min_deg"], doc["servos"][2]["max_deg"] = -60.0, 60.0
        doc["servos"][2]["operating_mode"] = "extended_position"
    return doc


def calibrated_config(truth: dict, doc: dict) -> RigConfig:
    """The i15 table's 'calibrated config field' column, written with the core's
    Rodrigues (gonio.radiometry.frames.rotation_about), not the simulator's."""
    doc = {
        **doc,
        "servos": [dict(s) for s in doc["servos"]],
        "geometry": dict(doc.get("geometry", {})),
    }
    for s in doc["servos"]:
        j = s["joint"]
        d, g = s.get("direction", 1), s.get("gear_ratio", 1.0)
        s["zero_deg"] = s.get("zero_deg", 180.0) - d * g * truth[f"{j}.offset"]
        s["backlash_deg"] = truth[f"{j}.backlash"]
        if j == "stage_tilt":
            s["compliance_deg"] = (
                truth["stage_tilt.compliance_a"],
                truth["stage_tilt.compliance_b"],
            )
        for lim in ("min_deg", "max_deg"):
            s[lim] = s.get(lim, -180.0 if lim == "min_deg" else 180.0)
        s["operating_mode"] = "extended_position"
    g = doc["geometry"]
    base = RigConfig.model_validate(rig_config_from_dict(_rig_doc(), "x").model_dump()).geometry
    k0 = np.array(g.get("tilt_axis", base.tilt_axis), float)
    n0 = np.array(g.get("rest_normal", base.rest_normal), float)
    r0 = np.array(g.get("rest_reference", base.rest_reference), float)
    z = np.array([0.0, 0.0, 1.0])
    k = rotation_about(normalize(np.cross(k0, z)), math.radians(truth["tilt_axis_pitch"])) @ k0
    u = normalize(np.cross(k0, n0))
    Ru = rotation_about(u, math.radians(truth["spin_axis_yaw"]))
    g.update(
        light_elevation_deg=truth["light_elevation"],
        camera_elevation_deg=truth["camera_elevation"],
        camera_radius_m=truth["camera_radius"],
        light_radius_m=truth["light_radius"],
        camera_mount_deg=tuple(truth[f"camera_mount_{a}"] for a in "xyz"),
        tilt_axis=tuple(k),
        rest_normal=tuple(Ru @ n0),
        rest_reference=tuple(Ru @ r0),
        holder_tilt_deg=(truth["holder_tilt_x"], truth["holder_tilt_y"]),
        holder_offset_m=tuple(truth[f"holder_offset_{a}"] for a in "xyz"),
        stage_offset_m=(truth["stage_offset_x"], truth["stage_offset_y"], 0.0),
    )
    return rig_config_from_dict(doc, "calibrated")


def _big_world(seed: int):
    """A world with errors far larger than realistic ones (a stronger check: small
    terms hide wrong signs and orders)."""
    rng = np.random.default_rng(seed)
    rig = {}
    for n in RIG_PARAMETERS:
        if n.endswith("backlash"):
            rig[n] = float(rng.uniform(0, 3))
        elif n.split("_")[-1] in ("x", "y", "z") and "offset" in n:
            rig[n] = float(rng.uniform(-0.02, 0.02))
        elif n.endswith("radius"):
            rig[n] = float(rng.uniform(-0.05, 0.05))
        elif n == "tilt_axis_pitch":
            rig[n] = float(rng.uniform(-8, 8))
        else:
            rig[n] = float(rng.uniform(-5, 5))
    return draw_world("realistic", seed, {"rig": rig})


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("odd_servos", [False, True])
def test_true_poses_equal_asbuilt_rig_poses(seed, odd_servos):
    doc = _rig_doc(odd_servos, gear=2.5)
    world = _big_world(seed) if seed % 2 else draw_world("realistic", seed)
    cfg = calibrated_config(world.truth_parameters(doc), doc)
    nominal = rig_config_from_dict(doc, "nominal")
    rng = np.random.default_rng(100 + seed)
    for _ in range(10):
        joints = {j: float(rng.uniform(-1.0, 1.0)) for j in JOINTS}
        dirs = {s.id: int(rng.choice([-1, 0, 1])) for s in nominal.servos}
        pulses = {s.id: nominal.servo_for(s.joint).pulses(joints[s.joint]) for s in nominal.servos}
        states = {i: (pulses[i], dirs[i]) for i in pulses}
        # the controller: readings through the CALIBRATED zero, approach in joint sense
        reported = {s.joint: cfg.servo_for(s.joint).joint_rad(pulses[s.id]) for s in cfg.servos}
        approach = {s.joint: dirs[s.id] * s.direction for s in nominal.servos}
        ref = rig_poses(cfg, reported, approach)
        got = true_poses(world, doc, states)
        for name in (
            "wi",
            "wo",
            "light_position",
            "light_normal",
            "camera_position",
            "camera_rotation",
            "sample_to_world",
            "sample_origin",
        ):
            np.testing.assert_allclose(
                getattr(got, name), getattr(ref, name), rtol=0, atol=1e-12, err_msg=name
            )


def test_perfect_world_is_the_nominal_kinematics():
    doc = _rig_doc()
    cfg = rig_config_from_dict(doc, "nominal")
    kin = Kinematics(cfg)
    world = draw_world("perfect")
    rng = np.random.default_rng(5)
    for _ in range(20):
        joints = {j: float(rng.uniform(-1.2, 1.2)) for j in JOINTS}
        states = {s.id: (s.pulses(joints[s.joint]), 1) for s in cfg.servos}
        ref, got = kin.poses(joints), true_poses(world, doc, states)
        for name in (
            "wi",
            "wo",
            "light_position",
            "light_normal",
            "camera_position",
            "camera_rotation",
            "sample_to_world",
        ):
            np.testing.assert_allclose(getattr(got, name), getattr(ref, name), atol=1e-12)


def test_backlash_side_follows_servo_direction():
    """A servo with direction -1 moving up in pulses moves its joint down: the joint
    lags by +backlash/2 (closed form)."""
    doc = _rig_doc(direction_flip=True)
    rig = NominalRig.of(doc)
    s = rig.servos[1]
    assert s.direction == -1
    world = draw_world("perfect", 0, {"rig": {f"{s.joint}.backlash": 0.4}})
    ap = approach_from_servos(rig, {s.id: +1})
    q = joint_truth(world, rig, {j: 0.1 for j in JOINTS}, ap)
    assert q[s.joint] == pytest.approx(0.1 + math.radians(0.2), abs=1e-15)


def test_readings_from_pulses_match_servo_config():
    doc = _rig_doc(direction_flip=True, gear=3.0)
    cfg = rig_config_from_dict(doc, "nominal")
    r = readings_from_pulses(NominalRig.of(doc), {s.id: 1234.5 + s.id for s in cfg.servos})
    for s in cfg.servos:
        assert r[s.joint] == pytest.approx(s.joint_rad(1234.5 + s.id), abs=1e-14)
