"""An adaptive session with the real camera backend (gphoto2, against libgphoto2's
virtual camera) on a virtual servo bus: the rounds need nothing of the camera beyond the
``Camera`` interface every session uses (the frames go through the same per-step
machinery).  The virtual camera serves JPEG bytes, which nothing can reduce, so the
advisor is the test's own (the choice is not what is tested here)."""

from __future__ import annotations

import hashlib
import os
import tempfile

import pytest

from gonio.capture.adaptive import Decision, round_records, session_steps

# must be set before python-gphoto2 is first imported in this process
os.environ.setdefault("VCAMERADIR", tempfile.mkdtemp(prefix="gonio-vcam-"))


class FirstOffered:
    def __init__(self) -> None:
        self.rounds: list[int] = []

    def advise(self, state):
        self.rounds.append(state.round)
        return Decision(state.pool_ids[:2].tolist(), None, {"note": "first offered"})


def test_adaptive_session_with_the_gphoto2_backend(tmp_path, monkeypatch):
    pytest.importorskip("gphoto2")
    import json
    import tomllib
    from importlib import resources

    from gonio.app.devices import open_rig
    from gonio.capture.camera import open_camera
    from gonio.capture.engine import SessionDevices
    from gonio.capture.journal import read_journal
    from gonio.capture.plan import plan_from_dict
    from gonio.capture.sessions import run_session
    from gonio.rig.config import rig_config_from_dict
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.servo_model import VirtualServo
    from gonio.simulator.virtual_bus import VirtualBus

    d = tmp_path / "vcam"
    d.mkdir()
    payload = bytes(range(256)) * 40
    (d / "frame.jpg").write_bytes(payload)
    monkeypatch.setenv("VCAMERADIR", str(d))
    cfg = rig_config_from_dict(
        tomllib.loads(resources.files("gonio.rig").joinpath("default_rig.toml").read_text())
    )
    plan = plan_from_dict(
        {
            "adaptive": {
                "seed_poses": 3,
                "retro_poses": 1,
                "in_plane_poses": 1,
                "batch_poses": 2,
                "max_poses": 7,
                "pool_step_deg": 30,
            },
            "reductions": {"isotropic": True},
            "exclusions": {"min_separation_deg": 10},
            "bracket": {"policy": "fixed", "exposures_s": [0.01], "iso": "camera"},
            "reference": {"poses": [{"theta_i_deg": 0, "theta_o_deg": 45, "phi_o_deg": 180}]},
        }
    )
    kin = Kinematics(cfg)
    servos = [
        VirtualServo(s.id, position=round(s.pulses(cfg.park_rad[s.joint]))) for s in cfg.servos
    ]
    out = tmp_path / "S"
    advisor = FirstOffered()
    with VirtualBus(servos, time_scale="virtual") as bus:
        real = cfg.model_copy(update={"bus": cfg.bus.model_copy(update={"port": bus.port})})
        with open_rig(real) as rig:
            cam = open_camera("gphoto2", require_raw=False)
            try:
                res = run_session(out, plan, cfg, SessionDevices(rig, cam, kinematics=kin),
                                  advisor=advisor)  # fmt: skip
            finally:
                cam.close()
    assert res.status == "completed"
    recs = read_journal(out / "journal.jsonl")
    rounds = round_records(recs)
    assert [len(r["chosen_ids"]) for r in rounds] == [2, 2, 0] and advisor.rounds == [0, 1]
    assert rounds[-1]["stop"] == "max_poses"
    steps = session_steps(json.loads((out / "manifest.json").read_text())["schedule"], recs)
    shots = [r for r in recs if r["type"] == "shot"]
    assert sorted(r["pose"] for r in shots) == list(range(len(steps))) == list(range(8))
    for r in shots:
        assert (out / r["file"]).read_bytes() == payload
        assert hashlib.sha256(payload).hexdigest() == r["sha256"]
