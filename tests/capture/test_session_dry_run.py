"""The dry run executes the session's own plan against the kinematics alone, each move
solved from the previous pose's joints with its path check -- not from home, as the old
schedule did (so path refusals appeared only at run time)."""

from __future__ import annotations

import math

import numpy as np

from gonio.capture.plan import plan_from_dict
from gonio.capture.schedule import DryRunRig, build_schedule
from gonio.errors import PoseRefused, RefusalReason


class PathLimitedKinematics:
    """Kinematics of a toy rig whose only joint is theta_i (rad): a move of more than
    30 deg from the present pose makes the arms pass each other; from home (no present
    pose) every pose is reachable."""

    config = None

    def refusal(self, wi, wo, current=None):
        return None

    def inverse(self, wi, wo, current=None):
        q = {"theta_i": math.acos(float(np.clip(wi[2] / np.linalg.norm(wi), -1, 1)))}
        if current is not None and abs(q["theta_i"] - current["theta_i"]) > math.radians(30):
            raise PoseRefused(
                RefusalReason.PATH,
                "the move would make the light and camera arms pass or touch each other",
            )
        return q

    def move_time(self, a, b):
        return abs(float(a["theta_i"]) - float(b["theta_i"]))

    def forward(self, joints):
        t = float(joints["theta_i"])
        return np.array([math.sin(t), 0.0, math.cos(t)]), np.array([-0.5, 0.0, math.sqrt(0.75)])


PLAN = {
    "grid": {"theta_i_deg": [10, 50], "phi_i_deg": [0], "theta_o_deg": [30], "phi_o_deg": [180]},
    "bracket": {"policy": "fixed", "exposures_s": [0.01]},
    "exclusions": {"min_separation_deg": 0, "check_rig": False},
}


def test_path_from_the_previous_pose_is_checked_and_refusals_recorded():
    kin = PathLimitedKinematics()
    sched = build_schedule(plan_from_dict(PLAN), kin, {"theta_i": 0.0})
    thetas = [round(math.degrees(math.acos(s["wi"][2]))) for s in sched.steps]
    assert sorted(thetas) == [10, 50]
    # from home (0 deg) or from 10 deg, 50 deg is more than 30 deg away: refused by the
    # path rule, with its code; the other pose is solved and its joints recorded
    assert len(sched.refused) == 1
    r = sched.refused[0]
    assert thetas[r.step] == 50 and r.code == RefusalReason.PATH.value
    assert sched.steps[r.step]["refused"]["code"] == "path"
    assert "joints" not in sched.steps[r.step]
    ok = 1 - r.step
    assert math.isclose(sched.steps[ok]["joints"]["theta_i"], math.radians(10))


def test_dry_run_rig_solves_from_its_last_accepted_pose():
    kin = PathLimitedKinematics()
    rig = DryRunRig(kin, {"theta_i": 0.0})
    d = lambda deg: np.array([math.sin(math.radians(deg)), 0.0, math.cos(math.radians(deg))])  # noqa: E731
    wo = np.array([-0.5, 0.0, math.sqrt(0.75)])
    rig.move_to(d(25), wo)
    try:
        rig.move_to(d(70), wo)  # 45 deg from 25
    except PoseRefused as exc:
        assert exc.reason is RefusalReason.PATH
    else:
        raise AssertionError("a 45 deg move must be refused")
    assert math.isclose(rig.read().joints["theta_i"], math.radians(25))  # nothing moved
    res = rig.move_to(d(50), wo)  # 25 deg from 25: fine
    assert math.isclose(res.joints["theta_i"], math.radians(50))
    assert math.isclose(res.duration, math.radians(25))


def test_the_dry_run_reports_each_stage_to_its_end():
    """A large dry run takes minutes: every stage is reported, each up to its total."""
    from gonio.capture.sessions import plan_session
    from gonio.rig.config import default_rig_config

    plan = plan_from_dict(
        {
            "grid": {
                "theta_i_deg": [10, 30, 50],
                "phi_i_deg": [0],
                "theta_o_deg": [20, 40],
                "phi_o_deg": [150, 180],
            }
        }
    )
    seen: list[tuple[str, int, int]] = []
    dry = plan_session(plan, default_rig_config(), progress=lambda *a: seen.append(a))
    stages = list(dict.fromkeys(s for s, _, _ in seen))
    assert stages == ["expand", "solve", "order", "dry run"]
    for stage in stages:
        last = [(d, t) for s, d, t in seen if s == stage][-1]
        assert last[0] == last[1] > 0
    solved = [t for s, _, t in seen if s == "solve"][-1]
    assert solved == len(dry.schedule.expanded.poses)
    assert [t for s, _, t in seen if s == "dry run"][-1] == len(dry.schedule.steps)
