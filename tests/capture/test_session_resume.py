"""Resume and inspect trust nothing they have not checked.

- 14.4: a same-size bit flip in a journaled RAW file made resume say "completed"; now it
  refuses naming the file, and ``--retake`` shoots the frame again (the simulated camera,
  seeded per (pose, frame), renders the very bytes that were lost).
- 14.10: a journal record naming ``../victim`` made inspect and resume open a file
  outside the session; now refused.
- 14.9: temporaries of an interrupted write are listed by inspect, removed by resume.
- 14.2: ``settle_s`` is waited after every move, on the servo clock.
- Relocatable sessions: the manifest holds no absolute path; a scene's albedo map is
  copied into the session, which resumes and inspects after being moved.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import tomli_w

from gonio.capture.journal import Journal, latest_shots, read_journal, session_file
from gonio.cli import run
from gonio.errors import FileFormatError
from gonio.locks import LOCK_NAME
from gonio.rig.config import virtual_rig_document

PLAN = """
name = "resume"
seed = 9
[grid]
theta_i_deg = [20, 40]
phi_i_deg = [0]
theta_o_deg = [30, 50]
phi_o_deg = [180]
[bracket]
policy = "fixed"
exposures_s = [0.004, 0.016]
[darks]
count = 1
[simulation]
width = 16
height = 12
"""


def _run(d: Path, out: Path, *extra: str) -> int:
    args = ["capture", "run", str(d / "plan.toml"), "--rig", str(d / "rig.toml")]
    return run(*args, "--camera", "simulated", "--out", str(out), "--quiet", *extra)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    d = tmp_path_factory.mktemp("resume")
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "plan.toml").write_text(PLAN)
    assert _run(d, d / "S") == 0
    return d / "S"


def _copy(src: Path, dest: Path) -> Path:
    shutil.copytree(src, dest)
    (dest / LOCK_NAME).unlink(missing_ok=True)
    return dest


def _shots(s: Path) -> list[dict]:
    return [r for r in read_journal(s / "journal.jsonl") if r["type"] == "shot"]


def test_resume_refuses_a_changed_frame_and_retake_shoots_it_again(finished, tmp_path, capsys):
    s = _copy(finished, tmp_path / "S")
    victim = _shots(s)[3]
    path = s / victim["file"]
    original = path.read_bytes()
    flipped = bytearray(original)
    flipped[len(flipped) // 2] ^= 0x10  # same size: only a digest sees it
    path.write_bytes(bytes(flipped))
    journal_before = (s / "journal.jsonl").read_bytes()

    assert run("capture", "resume", str(s), "--quiet") == 1
    err = capsys.readouterr().err
    assert victim["file"] in err and "XXH3-128" in err and "--retake" in err
    assert (s / "journal.jsonl").read_bytes() == journal_before  # nothing written

    assert run("capture", "resume", str(s), "--quiet", "--retake") == 0
    assert "shot again" in capsys.readouterr().out
    recs = read_journal(s / "journal.jsonl")
    new = [r for r in recs[len(read_journal(finished / "journal.jsonl")) :] if r["type"] == "shot"]
    assert len(new) == 1
    rec = new[0]
    assert (rec["pose"], rec["frame"]) == (victim["pose"], victim["frame"])
    assert rec["retake"] is True and rec["replaces"]["file"] == victim["file"]
    assert rec["file"] != victim["file"]  # the damaged file stays as it was found
    assert path.read_bytes() == bytes(flipped)
    # the seeded simulated camera renders exactly the frame that was damaged
    assert (s / rec["file"]).read_bytes() == original
    # the newest record of a frame is the one that counts, for inspect and the reduction
    assert latest_shots(recs)[(rec["pose"], rec["frame"])]["file"] == rec["file"]
    assert run("capture", "inspect", str(s), "--json") == 0
    info = json.loads(capsys.readouterr().out)
    assert info["bad_files"] == [] and info["retaken"] == [rec["file"]]
    assert info["superseded"] == [victim["file"]] and info["orphans"] == []


def test_journal_paths_outside_the_session_are_refused(finished, tmp_path, capsys):
    s = _copy(finished, tmp_path / "S")
    victim = tmp_path / "victim" / "v.txt"
    victim.parent.mkdir()
    victim.write_text("not yours")
    recs = read_journal(s / "journal.jsonl")
    shot = next(r for r in recs if r["type"] == "shot")
    lines = (s / "journal.jsonl").read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if json.loads(line) == shot)
    lines[i] = json.dumps({**shot, "file": "../victim/v.txt"})
    (s / "journal.jsonl").write_text("\n".join(lines) + "\n")
    for args in (
        ["inspect", str(s)],
        ["resume", str(s), "--quiet"],
        ["reduce", str(s), "--quiet", "--no-plot"],
    ):
        assert run("capture", *args) == 1
        err = capsys.readouterr().err
        assert "../victim/v.txt" in err and "outside the session" in err
    assert victim.read_text() == "not yours"


def test_session_file_refuses_absolute_and_symlinked_escapes(tmp_path):
    s = tmp_path / "S"
    (s / "raw").mkdir(parents=True)
    (tmp_path / "out.dng").write_bytes(b"x")
    (s / "raw" / "link.dng").symlink_to(tmp_path / "out.dng")
    assert session_file(s, {"file": "raw/p0000_f00_sample.dng"}) == s / "raw/p0000_f00_sample.dng"
    for bad in ("/etc/passwd", "../out.dng", "raw/../../out.dng", "raw/link.dng", "", 7):
        with pytest.raises(FileFormatError, match="file"):
            session_file(s, {"file": bad})


def test_stale_temporaries_are_listed_and_removed_by_resume(finished, tmp_path, capsys):
    s = _copy(finished, tmp_path / "S")
    stale = s / "raw" / ".p0001_f00_sample.dng.abcd1234.tmp"
    stale.write_bytes(b"half a frame")
    (s / ".samples.h5.x1y2z3w4.tmp").write_bytes(b"half a file")
    assert run("capture", "inspect", str(s), "--json") == 0
    info = json.loads(capsys.readouterr().out)
    assert info["stale_temporaries"] == [
        ".samples.h5.x1y2z3w4.tmp",
        "raw/.p0001_f00_sample.dng.abcd1234.tmp",
    ]
    assert info["orphans"] == []  # temporaries are not frames
    assert run("capture", "resume", str(s), "--quiet") == 0
    assert not stale.exists()  # its own kind: RAW temporaries
    assert (s / ".samples.h5.x1y2z3w4.tmp").exists()  # the reduction's to remove


def test_settle_time_is_waited_after_every_move_on_the_servo_clock(tmp_path):
    """Each pose's first frame is shot at least ``settle_s`` of servo time after the move
    ended.  Without settling, the gap is the read-back and one render (a few ms of wall
    time, well under 5 s of servo time at 100x)."""
    from gonio.app.devices import open_rig
    from gonio.capture.engine import SessionDevices
    from gonio.capture.plan import plan_from_dict
    from gonio.capture.sessions import run_session
    from gonio.rig.config import load_rig_config
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.rig_camera import SimulatedRigCamera
    from gonio.simulator.servo_model import VirtualServo
    from gonio.simulator.virtual_bus import VirtualBus

    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    cfg = load_rig_config(tmp_path / "rig.toml")
    settle = 5.0
    plan = plan_from_dict(
        {
            "settle_s": settle,
            "grid": {
                "theta_i_deg": [20, 40],
                "phi_i_deg": [0],
                "theta_o_deg": [30],
                "phi_o_deg": [180],
            },
            "bracket": {"policy": "fixed", "exposures_s": [0.004, 0.016]},
        }
    )
    kin = Kinematics(cfg)
    servos = [VirtualServo(s.id, position=cfg.park_pulses[s.id]) for s in cfg.servos]
    events: list[tuple[str, float]] = []
    hints: list = []
    with VirtualBus(servos, time_scale=100.0) as bus:
        real = cfg.model_copy(update={"bus": cfg.bus.model_copy(update={"port": bus.port})})

        class Timed:
            def __init__(self, rig):
                self.rig = rig

            def __getattr__(self, name):
                return getattr(self.rig, name)

            def move_to(self, wi, wo, *, joints=None):
                hints.append(joints)
                result = self.rig.move_to(wi, wo, joints=joints)
                events.append(("moved", bus.clock()))
                return result

        with open_rig(real) as rig:
            cam = SimulatedRigCamera(
                None, lambda: kin.poses(rig.read().joints), 0, width=16, height=12
            )
            capture = cam.capture

            def timed_capture(*a):
                events.append(("shot", bus.clock()))
                return capture(*a)

            cam.capture = timed_capture
            dev = SessionDevices(Timed(rig), cam, cam, cam, kin, bus.sleep)
            run_session(tmp_path / "S", plan, cfg, dev)
    moves = [k for k, (what, _) in enumerate(events) if what == "moved"]
    assert len(moves) == 2
    # the run asks the rig for the joints the dry run chose (recorded in the schedule)
    steps = json.loads((tmp_path / "S" / "manifest.json").read_text())["schedule"]
    assert hints == [s["joints"] for s in steps] and all(hints)
    for k in moves:
        assert events[k + 1][0] == "shot"
        assert events[k + 1][1] - events[k][1] >= settle


def test_a_moved_session_with_a_scene_file_resumes_and_inspects(tmp_path, capsys):
    from gonio.simulator.rig_camera import minimal_scene

    scene_dir = tmp_path / "scene"
    scene_dir.mkdir()
    albedo = np.linspace(0.2, 0.8, 8 * 8 * 3).reshape(8, 8, 3)
    np.save(scene_dir / "albedo.npy", albedo)
    scene = minimal_scene(16, 12)
    scene["sample"]["albedo_map"] = "albedo.npy"
    (scene_dir / "scene.toml").write_text(tomli_w.dumps(scene))
    d = tmp_path / "lab"
    d.mkdir()
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "plan.toml").write_text(PLAN)
    first = d / "S"
    assert _run(d, first, "--scene", str(scene_dir / "scene.toml")) == 0
    text = (first / "manifest.json").read_text()
    assert str(tmp_path) not in text  # no absolute path anywhere in the manifest
    manifest = json.loads(text)
    assert manifest["simulation"]["scene"]["sample"]["albedo_map"] == "sim/albedo.npy"
    assert np.array_equal(np.load(first / "sim" / "albedo.npy"), albedo)
    # cut the journal after the first pose, move the session, delete the scene's folder
    lines = (first / "journal.jsonl").read_bytes().splitlines(keepends=True)
    (first / "journal.jsonl").write_bytes(b"".join(lines[:4]))
    moved = tmp_path / "elsewhere" / "S2"
    moved.parent.mkdir()
    os.rename(first, moved)
    shutil.rmtree(scene_dir)
    assert run("capture", "resume", str(moved), "--quiet") == 0
    capsys.readouterr()
    assert run("capture", "inspect", str(moved), "--json") == 0
    info = json.loads(capsys.readouterr().out)
    assert info["status"] == "completed" and info["bad_files"] == []
    assert info["poses_done"] == info["poses_total"]


def test_retake_record_survives_a_journal_reopen(tmp_path):
    """The journal writer keeps the retake fields as they were given."""
    p = tmp_path / "journal.jsonl"
    with Journal.create(p) as j:
        j.append({"type": "shot", "pose": 0, "frame": 0, "file": "raw/a.dng"})
        j.append(
            {
                "type": "shot",
                "pose": 0,
                "frame": 0,
                "file": "raw/a.r1.dng",
                "retake": True,
                "replaces": {"file": "raw/a.dng"},
            }
        )
    assert latest_shots(read_journal(p))[(0, 0)]["file"] == "raw/a.r1.dng"
