"""Joint-pose plans (calibration plans): validation, schedule in the plan's order, the
mirror target, the refusal to reduce them, and the approach signs a session journals."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from sim_sessions import fast_rig_config

from gonio.capture.engine import SessionDevices
from gonio.capture.journal import read_journal
from gonio.capture.plan import estimate_plan, plan_digest, plan_from_dict
from gonio.capture.sessions import plan_session, resume_session, run_session
from gonio.devices import CameraInfo, Shot
from gonio.errors import ConfigError, SessionError
from gonio.rig import asbuilt
from gonio.rig.config import JOINT_NAMES, default_rig_config, rig_config_from_dict
from gonio.rig.device import Rig
from gonio.rig.kinematics import Kinematics
from gonio.simulator.loopback import LoopbackTransport
from gonio.simulator.virtual_bus import ServoBus

# (light, camera, tilt, spin) deg, target.  The home/park pose of the preset is
# (-45, 0, 0, 0); these stay within its limits and keep the arms apart.
POSES = [
    (-40.0, 20.0, 10.0, 0.0, "sample"),  # spin does not move from park
    (-60.0, 30.0, 5.0, 30.0, "mirror"),  # tilt down, spin up
    (-60.0, 25.0, 5.0, 10.0, "mirror"),  # light and tilt stay: zero moves
    (-50.0, 25.0, 15.0, 10.0, "sample"),  # camera and spin stay
]


def plan_doc(poses=POSES, **extra):
    doc = {
        "name": "cal",
        "joint_poses": [
            {
                "light_azimuth_deg": a,
                "camera_azimuth_deg": c,
                "stage_tilt_deg": t,
                "stage_spin_deg": s,
                "target": target,
                "label": f"pose {k}",
            }
            for k, (a, c, t, s, target) in enumerate(poses)
        ],
        "bracket": {"policy": "fixed", "exposures_s": [0.01]},
    }
    doc.update(extra)
    return doc


def joints_of(a, c, t, s):
    return dict(zip(JOINT_NAMES, np.radians([a, c, t, s]), strict=True))


# ------------------------------------------------------------------ the plan file


def test_grid_and_joint_poses_are_exclusive_and_errors_name_the_entry():
    with pytest.raises(ConfigError, match=r"field 'grid'.*not both"):
        plan_from_dict({**plan_doc(), "grid": {"theta_i_deg": [0], "theta_o_deg": [30]}}, "p.toml")
    with pytest.raises(ConfigError, match=r"field .grid.*required: a \[grid\]"):
        plan_from_dict({"name": "empty"}, "p.toml")
    bad = plan_doc()
    bad["joint_poses"][2]["target"] = "reference"
    with pytest.raises(ConfigError, match=r"p\.toml.*joint_poses\.2\.target"):
        plan_from_dict(bad, "p.toml")
    bad = plan_doc()
    del bad["joint_poses"][1]["stage_tilt_deg"]
    with pytest.raises(ConfigError, match=r"joint_poses\.1\.stage_tilt_deg"):
        plan_from_dict(bad, "p.toml")


def test_a_grid_plan_dumps_and_digests_as_before():
    doc = {"name": "g", "grid": {"theta_i_deg": [10], "theta_o_deg": [30]}}
    plan = plan_from_dict(doc)
    dumped = plan.model_dump(mode="json")
    assert "joint_poses" not in dumped and "grid" in dumped
    # the joint-pose fields are absent from the digest's document, so it is unchanged
    assert plan_digest(plan) == plan_digest(dumped)
    jp = plan_from_dict(plan_doc())
    assert "grid" not in jp.model_dump(mode="json")
    assert plan_from_dict(jp.model_dump(mode="json")) == jp


def test_estimate_counts_the_joint_poses():
    plan = plan_from_dict(
        plan_doc(reference={"poses": [{"theta_i_deg": 0, "theta_o_deg": 30}]}, darks={"count": 2})
    )
    est = estimate_plan(plan)
    assert est.n_grid == 4 and est.n_poses == 5
    assert est.n_frames == 5 * 1 + 2 * 1


# ------------------------------------------------------------------ the schedule


def test_schedule_keeps_the_plan_order_and_joints_and_checks_each_pose():
    cfg = default_rig_config()
    poses = POSES + [(-40.0, 20.0, 10.0, 0.0, "sample")]  # again: reachable, kept
    poses.insert(2, (-40.0, 20.0, 10.0, 250.0, "sample"))  # spin beyond its limits
    dry = plan_session(plan_from_dict(plan_doc(poses)), cfg)
    steps = dry.steps
    kept = [p for k, p in enumerate(poses) if k != 2]
    assert [s["kind"] for s in steps] == [p[4] for p in kept]
    assert [s["label"] for s in steps] == [f"pose {k}" for k in (0, 1, 3, 4, 5)]
    for s, (a, c, t, sp, _) in zip(steps, kept, strict=True):
        q = joints_of(a, c, t, sp)
        assert s["joints"] == pytest.approx(q, abs=1e-15)
        # requested directions: the nominal forward (reference: rig.asbuilt at zero terms)
        rp = asbuilt.rig_poses(cfg, q)
        np.testing.assert_allclose(s["wi"], rp.wi, atol=2e-12)
        np.testing.assert_allclose(s["wo"], rp.wo, atol=2e-12)
    (ex,) = dry.schedule.expanded.excluded
    assert "joint_poses[2] (pose 2)" in ex.reason and "stage_spin" in ex.reason
    assert ex.code == "joint_limit"
    summary = dry.summary()
    assert summary["joint_poses"] == 6 and summary["mirror_poses"] == 2
    assert summary["sample_poses"] == 3 and summary["excluded"] == 1


def test_schedule_refuses_a_path_through_the_other_arm():
    cfg = default_rig_config()
    # light from -40 to +40 while the camera stays at 20: the arms would cross
    poses = [(-40.0, 20.0, 10.0, 0.0, "sample"), (40.0, 20.0, 10.0, 0.0, "sample")]
    dry = plan_session(plan_from_dict(plan_doc(poses)), cfg)
    assert [r.step for r in dry.refused] == [1]
    assert dry.steps[1]["refused"]["code"] in ("path", "arm_clearance")


# ------------------------------------------------------------------ sessions


class RecordingCamera:
    """A camera and target changer that records what it was asked (fixed bracket: the
    frames are never decoded)."""

    def __init__(self):
        self.targets: list[str] = []
        self.target = "sample"

    def describe(self):
        return CameraInfo("fake", "recording camera")

    def capture(self, exposure_time, iso, f_number):
        return Shot(f"{self.target} {exposure_time}".encode(), ".raw", exposure_time, 100.0, 8.0)

    def set_target(self, kind):
        self.targets.append(kind)
        self.target = kind

    def close(self):
        pass


def open_rig(cfg):
    bus = ServoBus([s.id for s in cfg.servos], time_scale=200.0, seed=0)
    for s in cfg.servos:
        bus.servos[s.id].set_position(round(s.pulses(cfg.park_rad[s.joint])))
    return Rig(cfg, transport=LoopbackTransport(bus))


def test_mirror_steps_without_a_target_changer_are_refused_before_anything(tmp_path):
    cfg = fast_rig_config()
    plan = plan_from_dict(plan_doc())
    out = tmp_path / "S"
    with open_rig(cfg) as rig:
        before = rig.read().joints
        with pytest.raises(SessionError, match=r"2 step\(s\) view the calibration mirror"):
            run_session(
                out, plan, cfg, SessionDevices(rig, RecordingCamera(), kinematics=rig.kinematics)
            )
        assert rig.read().joints == before
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("backlash", [0.0, 0.25])
def test_session_journals_approach_signs_of_its_moves(tmp_path, backlash):
    cfg = fast_rig_config(backlash)
    plan = plan_from_dict(plan_doc())
    out = tmp_path / "S"
    cam = RecordingCamera()
    pre_moves = []
    with open_rig(cfg) as rig:

        def watch(doc):
            if doc.get("type") == "shot":
                pre_moves.append(dict(rig.last_pre_move))

        dev = SessionDevices(rig, cam, target=cam, kinematics=rig.kinematics)
        result = run_session(out, plan, cfg, dev, subscribers=[watch])
    assert result.status == "completed"
    assert cam.targets == ["mirror", "sample", "sample"]  # the finalizer puts it back
    shots = [r for r in read_journal(out / "journal.jsonl") if r["type"] == "shot"]
    assert [r["kind"] for r in shots] == [p[4] for p in POSES]
    assert [r["file"].rsplit("_", 1)[1] for r in shots] == [
        "sample.raw", "mirror.raw", "mirror.raw", "sample.raw",
    ]  # fmt: skip
    # Reference: the sign of each joint's change between successive journaled poses
    # (from park), kept where it did not change; the first move's unmoved joint is +1
    # after the pre-move when it has backlash -- stated, or assumed by a rig without a
    # calibration record (gonio.rig.kinematics.take_up_servo) -- unknown (0) otherwise.
    takes_up = backlash > 0 or cfg.calibration is None
    # A change within the position tolerance (a pulse) does not move a servo: kept.
    tol = math.radians(0.088) * (cfg.motion.position_tolerance_pulses + 0.5)
    prev = dict(cfg.park_rad)
    expected = dict.fromkeys(JOINT_NAMES, 0)
    for k, r in enumerate(shots):
        now = dict(r["joints"])
        for j in JOINT_NAMES:
            if abs(now[j] - prev[j]) > tol / cfg.servo_for(j).gear_ratio:
                expected[j] = 1 if now[j] > prev[j] else -1
            elif k == 0 and takes_up:
                expected[j] = 1
        assert r["approach"] == expected, f"pose {k}"
        prev = now
    # spot checks against the plan itself: tilt went down at pose 1 and kept it at pose 2
    assert shots[1]["approach"]["stage_tilt"] == -1 == shots[2]["approach"]["stage_tilt"]
    assert shots[0]["approach"]["stage_spin"] == (1 if takes_up else 0)
    # the pre-move: only on the first move, only for the unmoved joint, only with backlash
    assert pre_moves[0] == ({"stage_spin": 1} if takes_up else {})
    assert all(p == {} for p in pre_moves[1:])


def test_asbuilt_session_meets_the_directions_the_schedule_planned(tmp_path):
    # backlash in the rig config: the schedule's requested directions are the as-built
    # forward with the approach of the run, and the run reaches them.
    cfg = fast_rig_config(0.25)
    plan = plan_from_dict(plan_doc())
    dry = plan_session(plan, cfg)
    kin = Kinematics(cfg)
    cam = RecordingCamera()
    with open_rig(cfg) as rig:
        dev = SessionDevices(rig, cam, target=cam, kinematics=rig.kinematics)
        run_session(tmp_path / "S", plan, cfg, dev, dry_run=dry)
    shots = [r for r in read_journal(tmp_path / "S" / "journal.jsonl") if r["type"] == "shot"]
    for s, r in zip(dry.steps, shots, strict=True):
        assert r["wi_requested"] == s["wi"]
        wi, _ = kin.forward(r["joints"], r["approach"])
        np.testing.assert_allclose(r["wi_achieved"], wi, atol=1e-15)
        ref = asbuilt.rig_poses(cfg, r["joints"], r["approach"])
        # within the pulse quantisation of the requested directions
        assert np.degrees(np.arccos(np.clip(np.dot(ref.wi, s["wi"]), -1, 1))) < 0.2


def test_a_calibration_session_is_not_reduced(tmp_path):
    from gonio.capture.reduce import reduce_session

    cfg = fast_rig_config()
    plan = plan_from_dict(plan_doc())
    cam = RecordingCamera()
    out = tmp_path / "S"
    with open_rig(cfg) as rig:
        run_session(out, plan, cfg, SessionDevices(rig, cam, target=cam, kinematics=rig.kinematics))
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(
        SessionError,
        match=r"a calibration session \(joint poses\); use gonio calibrate camera\|rig",
    ):
        reduce_session(out)
    assert sorted(p.name for p in out.iterdir()) == before
    # and resume refuses mirror steps without a target changer too
    manifest = json.loads((out / "manifest.json").read_text())
    assert [s["kind"] for s in manifest["schedule"]] == [p[4] for p in POSES]
    with open_rig(cfg) as rig:
        with pytest.raises(SessionError, match="calibration mirror"):
            resume_session(out, SessionDevices(rig, cam, kinematics=rig.kinematics))


def test_asbuilt_rig_config_puts_the_true_directions_where_a_grid_plan_asks(tmp_path):
    # A calibrated rig (1 deg of backlash per joint, sample 3 mm above the rotation
    # centre, holder tilted): the run's encoder angles, read through the as-built model
    # with the journaled approach, give the requested directions to within the pulse
    # quantisation; ignoring the approach would miss by about half the backlash.
    d = fast_rig_config(1.0).model_dump()
    d["geometry"]["holder_offset_m"] = (0.0, 0.0, 0.003)
    d["geometry"]["holder_tilt_deg"] = (0.5, -0.3)
    cfg = rig_config_from_dict(d)
    plan = plan_from_dict(
        {
            "name": "grid",
            "grid": {"theta_i_deg": [20, 45], "theta_o_deg": [30, 60], "phi_o_deg": [150]},
            "bracket": {"policy": "fixed", "exposures_s": [0.01]},
        }
    )
    cam = RecordingCamera()
    with open_rig(cfg) as rig:
        run_session(tmp_path / "S", plan, cfg, SessionDevices(rig, cam, kinematics=rig.kinematics))
    shots = [r for r in read_journal(tmp_path / "S" / "journal.jsonl") if r["type"] == "shot"]
    assert len(shots) == 4
    worst_blind = 0.0
    for r in shots:
        assert all(r["approach"][j] in (1, -1) for j in JOINT_NAMES)
        true = asbuilt.rig_poses(cfg, r["joints"], r["approach"])
        blind = asbuilt.rig_poses(cfg, r["joints"])
        for got, want in ((true.wi, r["wi_requested"]), (true.wo, r["wo_requested"])):
            assert math.degrees(math.acos(min(1.0, float(np.dot(got, want))))) < 0.1
        worst_blind = max(
            worst_blind,
            math.degrees(math.acos(min(1.0, float(np.dot(blind.wi, r["wi_requested"]))))),
        )
    assert worst_blind > 0.3
