"""Calibration plans: reachable poses, both approach sides, mirror views at the mirror
direction, observability checked before anything moves, the plan file and the CLI."""

from __future__ import annotations

import importlib.util
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from gonio.rig.calibration import MIN_MIRROR_VIEWS
from gonio.rig.calibration_plan import (
    JointPose,
    camera_calibration_poses,
    check_observable,
    rig_calibration_poses,
    write_plan,
)
from gonio.rig.calibration_record import CalibrationError
from gonio.rig.config import JOINT_NAMES, default_rig_config
from gonio.rig.kinematics import Kinematics


def _load_truth():
    path = Path(__file__).with_name("calibration_truth.py")
    spec = importlib.util.spec_from_file_location("gonio_tests_calibration_truth", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


ct = _load_truth()
NOMINAL = default_rig_config()
KIN = Kinematics(NOMINAL)


def _q(p: JointPose) -> dict[str, float]:
    vals = (p.light_azimuth_deg, p.camera_azimuth_deg, p.stage_tilt_deg, p.stage_spin_deg)
    return {j: math.radians(v) for j, v in zip(JOINT_NAMES, vals, strict=True)}


def _obliquity_deg(p: JointPose) -> float:
    _, wo = KIN.forward(_q(p))
    return math.degrees(math.acos(wo[2]))


def _check_reachable(poses):
    h = NOMINAL.motion.home_deg
    prev = JointPose(*(h[j] for j in JOINT_NAMES))  # the session starts from home
    for p in poses:
        assert KIN.joints_refusal(_q(p)) is None, p
        if prev is not None:
            assert KIN.path_refusal(_q(prev), _q(p)) is None, (prev, p)
        prev = p


def test_rig_plan_is_reachable_and_approaches_each_joint_from_both_sides():
    poses = rig_calibration_poses(NOMINAL)
    _check_reachable(poses)
    sides = ct.sides(poses, NOMINAL.motion.home_deg)
    boards = [s for p, s in zip(poses, sides, strict=True) if p.target == "sample"]
    mirrors = [s for p, s in zip(poses, sides, strict=True) if p.target == "mirror"]
    for j in ("camera_azimuth", "stage_tilt", "stage_spin"):
        assert {s[j] for s in boards} >= {1, -1}, j
    assert {s["light_azimuth"] for s in mirrors} >= {1, -1}
    assert len(mirrors) >= MIN_MIRROR_VIEWS
    obl = [_obliquity_deg(p) for p in poses if p.target == "sample"]
    assert max(obl) <= 55.0 + 1e-6 and max(obl) > 40.0
    tilts = {p.stage_tilt_deg for p in poses if p.target == "sample"}
    assert min(tilts) <= -45 and max(tilts) >= 45
    # the board poses first, then the mirror: one target change
    kinds = [p.target for p in poses]
    assert kinds == sorted(kinds, key=lambda k: k == "mirror")


def test_mirror_views_look_at_the_mirror_direction():
    for p in rig_calibration_poses(NOMINAL):
        if p.target != "mirror":
            continue
        wi, wo = KIN.forward(_q(p))
        mirrored = np.array([-wi[0], -wi[1], wi[2]])
        # level arms: a tilt t turns the reflection by 2 t out of the camera's plane
        limit = 2 * abs(p.stage_tilt_deg) + 1e-6
        assert math.degrees(math.acos(np.clip(mirrored @ wo, -1, 1))) <= limit


def test_camera_plan_views_the_board_from_many_obliquities():
    poses = camera_calibration_poses(NOMINAL)
    _check_reachable(poses)
    assert len(poses) >= 20 and all(p.target == "sample" for p in poses)
    obl = np.array([_obliquity_deg(p) for p in poses])
    assert obl.min() < 1.0 and 40.0 <= obl.max() <= 50.0
    assert len({p.stage_spin_deg for p in poses}) >= 10
    # tilted about different axes: both signs of tilt and of camera azimuth
    assert {np.sign(p.stage_tilt_deg) for p in poses} >= {1.0, -1.0}
    assert {np.sign(p.camera_azimuth_deg) for p in poses} >= {1.0, -1.0}


def test_default_plan_is_observable():
    obs = check_observable(NOMINAL, rig_calibration_poses(NOMINAL))
    assert not obs.refused
    assert all(np.isfinite(v) for v in obs.std.values())


def test_a_plan_without_mirror_views_names_the_light():
    boards = [p for p in rig_calibration_poses(NOMINAL) if p.target == "sample"]
    with pytest.raises(CalibrationError) as e:
        check_observable(NOMINAL, boards)
    for name in ("light_azimuth.offset", "light_azimuth.backlash", "light_elevation"):
        assert name in str(e.value)


def test_a_plan_tilting_one_way_names_the_tilt_backlash():
    poses = rig_calibration_poses(NOMINAL)
    # only tilts above home (0), visited in increasing order: always approached upwards
    up = sorted(
        (p for p in poses if p.target == "sample" and p.stage_tilt_deg > 0),
        key=lambda p: p.stage_tilt_deg,
    )
    sides = ct.sides(up, NOMINAL.motion.home_deg)
    assert {s["stage_tilt"] for s in sides} == {1}
    assert {s["stage_spin"] for s in sides} >= {1, -1}
    with pytest.raises(CalibrationError) as e:
        check_observable(NOMINAL, up)
    msg = str(e.value)
    assert "stage_tilt.backlash: every pose approaches stage_tilt from the same side" in msg
    assert "poses approached from both sides" in msg
    assert "stage_spin.backlash" not in msg


def test_plan_file(tmp_path):
    poses = rig_calibration_poses(NOMINAL)
    out = tmp_path / "rig_plan.toml"
    write_plan(out, poses)
    text = out.read_text()
    doc = tomllib.loads(text)
    assert len(doc["joint_poses"]) == len(poses)
    first = doc["joint_poses"][0]
    assert set(first) == {
        "light_azimuth_deg",
        "camera_azimuth_deg",
        "stage_tilt_deg",
        "stage_spin_deg",
        "target",
        "label",
    }
    assert first["stage_tilt_deg"] == pytest.approx(poses[0].stage_tilt_deg)
    assert {p["target"] for p in doc["joint_poses"]} == {"sample", "mirror"}
    assert doc["bracket"]["policy"] == "fixed" and len(doc["bracket"]["exposures_s"]) == 2
    assert doc["simulation"] == {"width": 640, "height": 480}
    with pytest.raises(CalibrationError, match="exists"):
        write_plan(out, poses[:3])
    assert out.read_text() == text


def test_plan_file_is_a_capture_plan(tmp_path):
    from gonio.capture.plan import Plan, load_plan

    if "joint_poses" not in Plan.model_fields:
        pytest.skip("the capture plan has no [[joint_poses]] yet (issue 15, C1's branch)")
    out = write_plan(tmp_path / "p.toml", rig_calibration_poses(NOMINAL))
    plan = load_plan(out)
    assert len(plan.joint_poses) == len(tomllib.loads(out.read_text())["joint_poses"])


def test_plan_command(tmp_path):
    from gonio.app.calibrate_rig_cli import plan_cmd

    out = tmp_path / "rig_plan.toml"
    res = CliRunner().invoke(plan_cmd, ["--kind", "rig", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "every parameter observable" in res.output
    n = len(tomllib.loads(out.read_text())["joint_poses"])
    assert n == len(rig_calibration_poses(NOMINAL))
    before = out.read_text()
    res = CliRunner().invoke(plan_cmd, ["--kind", "camera", "--out", str(out)])
    assert isinstance(res.exception, CalibrationError) and "exists" in str(res.exception)
    assert out.read_text() == before
    res = CliRunner().invoke(plan_cmd, ["--kind", "camera", "--out", str(out), "--force"])
    assert res.exit_code == 0, res.output
    assert len(tomllib.loads(out.read_text())["joint_poses"]) == len(
        camera_calibration_poses(NOMINAL)
    )
