"""Simulated sessions end to end: real dynamixel-sdk on the virtual bus's pty, rendered DNGs,
journal against files, faults on the bus, resume, and refusals that protect a session."""

from __future__ import annotations

import contextlib
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import xxhash

from gonio.capture.journal import read_journal
from gonio.capture.plan import load_plan
from gonio.capture.sessions import inspect_session, resume_session, run_session
from gonio.cli import run
from gonio.errors import SessionError
from gonio.rig.config import load_rig_config, virtual_rig_document
from gonio.rig.kinematics import Kinematics

PLAN = """
name = "tiny"
seed = 3
[grid]
theta_i_deg = [20, 40]
phi_i_deg = [0]
theta_o_deg = [30, 50]
phi_o_deg = [180]
[bracket]
exposure_time_s = 0.01
roi = [0.4, 0.4, 0.6, 0.6]
[darks]
count = 1
[simulation]
width = 32
height = 24
"""


@pytest.fixture
def files(tmp_path):
    rig = virtual_rig_document()
    assert 'port = "virtual"' in rig
    (tmp_path / "rig.toml").write_text(rig)
    (tmp_path / "plan.toml").write_text(PLAN)
    return tmp_path


def run_simulated(files: Path, out: Path, *, fast: bool = True):
    """``gonio capture run`` of the test plan on the virtual rig and simulated camera
    (servo time virtual when ``fast``, else 20x the wall clock); the exit code."""
    speed = [] if fast else ["--sim-speed", "20"]
    return run(
        "capture",
        "run",
        str(files / "plan.toml"),
        "--rig",
        str(files / "rig.toml"),
        "--camera",
        "simulated",
        "--out",
        str(out),
        *speed,
        "--quiet",
    )


def _check_journal_against_files(session: Path) -> list[dict]:
    recs = read_journal(session / "journal.jsonl")
    shots = [r for r in recs if r["type"] == "shot"]
    keys = [(r["pose"], r["frame"]) for r in shots]
    assert len(keys) == len(set(keys)), "duplicate shots in the journal"
    for r in shots:
        data = (session / r["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == r["sha256"]
        assert xxhash.xxh3_128_hexdigest(data) == r["xxh3_128"]
        assert len(data) == r["bytes"]
    on_disk = {f"raw/{p.name}" for p in (session / "raw").iterdir()}
    assert on_disk == {r["file"] for r in shots}
    return recs


def test_simulated_session_end_to_end(files):
    from gonio.capture.raw import read_raw

    out = files / "S"
    code = run_simulated(files, out)
    assert code == 0
    manifest = json.loads((out / "manifest.json").read_text())
    for key in (
        "schema_version",
        "software_version",
        "rig",
        "camera",
        "plan",
        "seed",
        "simulation",
    ):
        assert key in manifest
    recs = _check_journal_against_files(out)
    assert recs[0]["type"] == "start" and recs[-1] == {
        **recs[-1],
        "type": "stop",
        "status": "completed",
        "parked": True,
        "torque_off": True,
    }
    shots = [r for r in recs if r["type"] == "shot"]
    samples = [r for r in shots if r["kind"] == "sample"]
    assert {r["pose"] for r in samples} == {0, 1, 2, 3}
    kin = Kinematics(load_rig_config(files / "rig.toml"))
    for r in samples:
        # the file is a real DNG that rawpy decodes, with the journaled exposure
        frame = read_raw(out / r["file"])
        assert frame.exposure_time == pytest.approx(r["exposure_time"], rel=1e-6)
        assert frame.shape == (24, 32)
        # achieved directions follow from the read-back joints and are within a few
        # servo steps (0.088 deg) of the request
        wi, wo = kin.forward(r["joints"])
        assert np.allclose(wi, r["wi_achieved"]) and np.allclose(wo, r["wo_achieved"])
        err = np.degrees(np.arccos(np.clip(np.dot(r["wi_achieved"], r["wi_requested"]), -1, 1)))
        assert err < 0.3
        assert set(r["temperatures"]) == set(r["joints"])
    darks = [r for r in shots if r["kind"] == "dark"]
    assert sorted(r["exposure_time"] for r in darks) == sorted(
        {r["exposure_time"] for r in samples}
    )
    info = inspect_session(out)
    assert info.status == "completed" and info.files_verified == len(shots)
    assert info.poses_done == info.poses_total == 5


@contextlib.contextmanager
def devices_on(bus, cfg, seed: int, width: int = 32, height: int = 24):
    """The session devices the composition root builds, on a virtual bus the test holds
    (to inject faults into its servos)."""
    from gonio.app.devices import open_rig
    from gonio.capture.engine import SessionDevices
    from gonio.simulator.rig_camera import SimulatedRigCamera

    real = cfg.model_copy(update={"bus": cfg.bus.model_copy(update={"port": bus.port})})
    kin = Kinematics(cfg)
    with open_rig(real) as rig:
        cam = SimulatedRigCamera(
            None, lambda: kin.poses(rig.read().joints), seed, width=width, height=height
        )
        yield SessionDevices(rig, cam, cam, cam, kin, bus.sleep, None)


def test_fault_on_the_bus_stops_with_torque_off_and_resume_completes(files):
    from gonio.simulator.servo_model import VirtualServo
    from gonio.simulator.virtual_bus import VirtualBus

    plan = load_plan(files / "plan.toml")
    cfg = load_rig_config(files / "rig.toml")
    park = cfg.park_pulses
    servos = [VirtualServo(s.id, position=park[s.id]) for s in cfg.servos]
    out = files / "S"
    with VirtualBus(servos, time_scale="virtual", seed=0) as bus:
        state = {"armed": True}

        def inject(rec):
            # after pose 1 is done, overheat servo 2 half way through the next move
            if rec["type"] == "pose_done" and rec["pose"] == 1 and state["armed"]:
                bus.servos[2].inject_fault(0x04, during_next_move=0.5)
                state["armed"] = False

        with devices_on(bus, cfg, plan.seed) as dev:
            with pytest.raises(SessionError, match="fault") as info:
                run_session(out, plan, cfg, dev, subscribers=[inject])
            assert "resume" in str(info.value)
            assert all(v == 0 for v in bus.torque().values()), "torque must be off after a fault"
        recs = read_journal(out / "journal.jsonl")
        faults = [r for r in recs if r["type"] == "fault"]
        # the servo and its error bits come from the RigFault's fields: 0x04 overheating
        assert len(faults) == 1 and faults[0]["source"] == "rig"
        assert faults[0]["servo"] == 2 and faults[0]["error_bits"] == 0x04
        assert recs[-1]["type"] == "stop" and recs[-1]["status"] == "fault"
        assert recs[-1]["torque_off"] is True
        done_before = {r["pose"] for r in recs if r["type"] == "pose_done"}
        assert done_before == {0, 1}
        # the fault clears: opening the rig reboots the servo that reports it
        with devices_on(bus, cfg, plan.seed) as dev:
            assert resume_session(out, dev).status == "completed"
        assert all(v == 0 for v in bus.torque().values())
    recs = _check_journal_against_files(out)
    n_steps = len(json.loads((out / "manifest.json").read_text())["schedule"])
    assert {r["pose"] for r in recs if r["type"] == "pose_done"} == set(range(n_steps))
    assert recs[-1]["status"] == "completed"


def test_existing_session_dir_is_refused_and_untouched(files):
    out = files / "S"
    out.mkdir()
    (out / "notes.txt").write_text("precious")
    code = run_simulated(files, out, fast=False)
    assert code == 1
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    assert (out / "notes.txt").read_text() == "precious"


def test_resume_refuses_a_different_plan_unless_forced(files, capsys):
    out = files / "S"
    assert run_simulated(files, out) == 0
    other = files / "other.toml"
    other.write_text(PLAN.replace("exposure_time_s = 0.01", "exposure_time_s = 0.02"))
    before = (out / "journal.jsonl").read_bytes()
    assert run("capture", "resume", str(out), "--plan", str(other), "--quiet") == 1
    err = capsys.readouterr().err
    assert "bracket.exposure_time_s" in err and "--force" in err
    assert (out / "journal.jsonl").read_bytes() == before
    # ... and a different rig
    rig2 = files / "rig2.toml"
    rig_text = (files / "rig.toml").read_text()
    assert "light_radius_m = 0.5\n" in rig_text  # as tomli-w writes it
    rig2.write_text(rig_text.replace("light_radius_m = 0.5\n", "light_radius_m = 0.6\n"))
    assert run("capture", "resume", str(out), "--rig", str(rig2), "--quiet") == 1
    assert "geometry.light_radius_m" in capsys.readouterr().err
    assert (out / "journal.jsonl").read_bytes() == before
    # a run into the same directory is refused too, pointing at resume
    assert run_simulated(files, out, fast=False) == 1
    assert "gonio capture resume" in capsys.readouterr().err


def test_plan_dry_run_moves_nothing(files, capsys):
    code = run(
        "capture", "plan", str(files / "plan.toml"), "--rig", str(files / "rig.toml"), "--json"
    )
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["sample_poses"] == 4 and out["excluded"] == 0 and out["dark_steps"] == 1
    assert out["estimated_duration_s"] > out["travel_time_s"] > 0


def test_plan_with_no_reachable_pose_is_a_clear_error(files, capsys):
    bad = files / "bad.toml"
    # light and camera within 20 deg of each other at every grid pose, the plan wants 25
    bad.write_text(
        'name = "unreachable"\n[grid]\ntheta_i_deg = [20, 40]\ntheta_o_deg = [20, 40]\n'
        "[exclusions]\nmin_separation_deg = 25\n"
    )
    code = run("capture", "plan", str(bad), "--rig", str(files / "rig.toml"))
    assert code == 1
    err = capsys.readouterr().err
    assert "no reachable pose" in err


def test_invalid_plan_cli_names_the_field(files, capsys):
    bad = files / "bad.toml"
    bad.write_text(PLAN.replace("exposure_time_s = 0.01", "exposure_time_s = -1"))
    assert run("capture", "plan", str(bad)) == 1
    err = capsys.readouterr().err
    assert "bad.toml" in err and "bracket.exposure_time_s" in err


def test_inspect_finds_tampered_and_missing_files(files, capsys):
    out = files / "S"
    args = ["capture", "run", str(files / "plan.toml"), "--rig", str(files / "rig.toml")]
    assert run(*args, "--camera", "simulated", "--out", str(out), "--quiet") == 0
    capsys.readouterr()
    shots = [r for r in read_journal(out / "journal.jsonl") if r["type"] == "shot"]
    victim = out / shots[1]["file"]
    data = bytearray(victim.read_bytes())
    data[-1] ^= 0xFF
    victim.write_bytes(bytes(data))
    assert run("capture", "inspect", str(out)) == 1
    captured = capsys.readouterr()
    assert shots[1]["file"] in captured.out and "sha256 differs" in captured.out
    # resume refuses to continue a session whose journaled file has gone
    (out / shots[0]["file"]).unlink()
    assert run("capture", "resume", str(out), "--quiet") == 1
    assert "missing" in capsys.readouterr().err
