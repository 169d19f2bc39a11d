"""Camera interface and the gphoto2 backend, against libgphoto2's virtual camera.

libgphoto2's virtual camera (enabled by ``VCAMERADIR`` before python-gphoto2 is imported)
serves the files of that directory, has real configuration widgets (shutterspeed,
f-number, no ISO) and a capture that copies a file from the directory: it exercises the
transport, settings and download path, not RAW content (see libraries.md).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from gonio.capture.camera import (
    CAMERA_BACKENDS,
    Camera,
    open_camera,
    parse_f_number,
    parse_iso,
    parse_shutter_speed,
)
from gonio.errors import CameraError, UnknownNameError

# must be set before python-gphoto2 is first imported in this process
_VDIR = Path(os.environ.setdefault("VCAMERADIR", tempfile.mkdtemp(prefix="gonio-vcam-")))


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("1/250", 1 / 250),
        ("0.0100s", 0.01),
        ('2"', 2.0),
        ("30", 30.0),
        ("1/8000", 1 / 8000),
        ("bulb", math.nan),
    ],
)
def test_parse_shutter_speed(text, value):
    got = parse_shutter_speed(text)
    assert (math.isnan(got) and math.isnan(value)) or got == pytest.approx(value)


def test_parse_f_number_and_iso():
    assert (
        parse_f_number("f/8") == 8.0
        and parse_f_number("F5.6") == 5.6
        and parse_f_number("11") == 11
    )
    assert parse_iso("ISO 400") == 400 and parse_iso("100") == 100 and math.isnan(parse_iso("Auto"))


def test_unknown_backend():
    with pytest.raises(UnknownNameError, match="gphoto2"):
        open_camera("hasselblad")
    # the simulated camera belongs to the simulator; only gonio.app wires it in
    assert set(CAMERA_BACKENDS) == {"gphoto2"}
    with pytest.raises(UnknownNameError):
        open_camera("simulated")


@pytest.fixture
def vcam(tmp_path, monkeypatch):
    pytest.importorskip("gphoto2")
    d = tmp_path / "vcam"
    d.mkdir()
    payload = bytes(range(256)) * 40
    (d / "frame.jpg").write_bytes(payload)
    monkeypatch.setenv("VCAMERADIR", str(d))
    return d, payload


def test_virtual_camera_settings_and_download(vcam):
    d, payload = vcam
    cam = open_camera("gphoto2", require_raw=False)
    try:
        assert isinstance(cam, Camera)
        info = cam.describe()
        assert info.backend == "gphoto2" and "D750" in info.model
        shot = cam.capture(0.011, None, 7.9)
        # nearest offered values: 0.0100 s and f/8; the file arrives byte for byte
        assert shot.exposure_time == pytest.approx(0.01) and shot.f_number == 8.0
        assert math.isnan(shot.iso)
        assert shot.data == payload and shot.suffix == ".jpg"
        assert cam.describe().settings["exposure_time"] == "0.0100s"
    finally:
        cam.close()


def test_unsupported_settings_are_named(vcam):
    cam = open_camera("gphoto2", require_raw=False)
    try:
        with pytest.raises(CameraError, match="no iso setting"):
            cam.capture(0.01, 100, None)
        with pytest.raises(CameraError, match=r"does not support exposure_time = 30"):
            cam.capture(30.0, None, None)
    finally:
        cam.close()


def test_non_raw_file_is_refused(vcam):
    cam = open_camera("gphoto2")
    try:
        with pytest.raises(CameraError, match="not a RAW file"):
            cam.capture(0.01, None, None)
    finally:
        cam.close()


def test_no_camera_is_a_clear_error(tmp_path):
    pytest.importorskip("gphoto2")
    env = {k: v for k, v in os.environ.items() if k != "VCAMERADIR"}
    code = "from gonio.capture.camera import GPhoto2Camera\nGPhoto2Camera()"
    r = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60
    )
    assert r.returncode != 0
    assert "CameraError" in r.stderr and "no camera found" in r.stderr


def test_camera_that_disappears_mid_session(vcam, tmp_path):
    """A session with the gphoto2 backend whose camera goes away after the first pose:
    the session stops with the fault journaled and torque off, every journaled file
    intact; when the camera is back, resume completes it."""
    import hashlib
    import tomllib
    from importlib import resources

    from gonio.app.devices import open_rig
    from gonio.capture.engine import SessionDevices
    from gonio.capture.journal import read_journal
    from gonio.capture.plan import plan_from_dict
    from gonio.capture.sessions import resume_session, run_session
    from gonio.errors import SessionError
    from gonio.rig.config import rig_config_from_dict
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.servo_model import VirtualServo
    from gonio.simulator.virtual_bus import VirtualBus

    d, payload = vcam
    cfg = rig_config_from_dict(
        tomllib.loads(resources.files("gonio.rig").joinpath("default_rig.toml").read_text())
    )
    plan = plan_from_dict(
        {
            "grid": {
                "theta_i_deg": [20, 40],
                "phi_i_deg": [0],
                "theta_o_deg": [40],
                "phi_o_deg": [180],
            },
            "bracket": {"policy": "fixed", "exposures_s": [0.01, 0.05], "iso": "camera"},
        }
    )
    kin = Kinematics(cfg)
    servos = [
        VirtualServo(s.id, position=round(s.pulses(cfg.park_rad[s.joint]))) for s in cfg.servos
    ]
    out = tmp_path / "S"
    with VirtualBus(servos, time_scale=100.0) as bus:
        real = cfg.model_copy(update={"bus": cfg.bus.model_copy(update={"port": bus.port})})

        def unplug(rec):
            if rec["type"] == "pose_done" and rec["pose"] == 0:
                for f in d.iterdir():
                    f.unlink()

        with open_rig(real) as rig:
            cam = open_camera("gphoto2", require_raw=False)
            with pytest.raises(SessionError, match="camera fault"):
                run_session(
                    out, plan, cfg, SessionDevices(rig, cam, kinematics=kin), subscribers=[unplug]
                )
            cam.close()
            assert all(v == 0 for v in bus.torque().values())
        recs = read_journal(out / "journal.jsonl")
        fault = [r for r in recs if r["type"] == "fault"]
        assert len(fault) == 1 and fault[0]["source"] == "camera"
        assert "connected" in fault[0]["error"]
        assert recs[-1]["status"] == "fault" and recs[-1]["torque_off"] is True
        kept = [r for r in recs if r["type"] == "shot"]
        assert len(kept) == 2 and all(r["pose"] == 0 for r in kept)
        for r in kept:
            assert hashlib.sha256((out / r["file"]).read_bytes()).hexdigest() == r["sha256"]
        # the camera is back
        (d / "frame.jpg").write_bytes(payload)
        with open_rig(real) as rig:
            cam = open_camera("gphoto2", require_raw=False)
            result = resume_session(out, SessionDevices(rig, cam, kinematics=kin))
            assert result.status == "completed"
            cam.close()
    shots = [r for r in read_journal(out / "journal.jsonl") if r["type"] == "shot"]
    assert sorted((r["pose"], r["frame"]) for r in shots) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert all((out / r["file"]).read_bytes() == payload for r in shots)
