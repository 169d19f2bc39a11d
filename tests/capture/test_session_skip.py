"""A planned pose the rig refuses at run time: ``pose_skipped`` through the real path.

The session is interrupted (as by Ctrl-C) after its first sample pose; the operator then
narrows the light arm's travel (say a cable snags beyond -35 deg) and resumes with that
rig configuration and ``--force``.  The dry run had allowed theta_i = 40 deg (light arm
at -40 deg); the narrowed rig refuses it before moving, so the session journals one
``pose_skipped`` and shoots every other pose once.  Real dynamixel-sdk on the virtual
bus's pty, rendered DNGs, the CLI for resume, inspect and reduce.

Also: a servo that stops answering raises a bus error (not ``PoseRefused``) inside
``move_to``; that is a fault, not a refusal, and must stop the session instead of
skipping every remaining pose.  The session tells them apart by exception type only.
"""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
from sim_sessions import REFERENCE_OBLIQUE, grid_plan, scene

from gonio.app.devices import device_opener
from gonio.capture.journal import read_journal
from gonio.capture.plan import load_plan
from gonio.capture.sessions import plan_session, resume_session, run_session
from gonio.cli import run
from gonio.dataset import load_samples
from gonio.errors import SessionError
from gonio.rig.config import load_rig_config, virtual_rig_document
from gonio.rig.kinematics import Kinematics

# Steps: the reference (30, 30) first, the samples theta_i = 20, 30, 40 deg (light arm at
# -20, -30, -40 deg) in travel order, then the darks.
PLAN = grid_plan(
    "skip",
    seed=11,
    theta_i_deg=[20, 30, 40],
    theta_o_deg=[30],
    darks=1,
    references=[REFERENCE_OBLIQUE],
    roi=[0.4, 0.4, 0.6, 0.6],
    simulation={"width": 320, "height": 240},
)

LIMIT_DEG = -35.0


@pytest.fixture
def files(tmp_path):
    rig = virtual_rig_document()
    assert 'port = "virtual"' in rig
    (tmp_path / "rig.toml").write_text(rig)
    # The narrowed light arm: limits [-35, 170] deg; home/park moved inside them.
    light = 'joint = "light_azimuth"\nzero_deg = 180.0\nmin_deg = -170.0'
    assert light in rig and "light_azimuth = -45.0" in rig
    tight = rig.replace(light, light.replace("min_deg = -170.0", f"min_deg = {LIMIT_DEG}"))
    tight = tight.replace("light_azimuth = -45.0", "light_azimuth = -30.0")
    (tmp_path / "tight.toml").write_text(tight)
    (tmp_path / "plan.toml").write_text(PLAN)
    return tmp_path


def _simulation(plan, time_scale="virtual"):
    return {
        # The reduction finds the reference target through the holder's fiducial board,
        # so the frames must be large enough for ArUco (160 x 120 px) and the scene must
        # carry a board (a fresh document each time: a session may keep it).
        "scene": scene(render={"strategy": "point"}),
        "width": plan.simulation.width,
        "height": plan.simulation.height,
        "time_scale": time_scale,
    }


def _start_and_interrupt(files, after_pose: int):
    """Create the session as ``capture run`` does; Ctrl-C once ``after_pose`` is done."""
    plan = load_plan(files / "plan.toml")
    cfg = load_rig_config(files / "rig.toml")
    dry = plan_session(plan, cfg)
    out = files / "S"
    sim = _simulation(plan)

    def interrupt(rec):
        if rec["type"] == "pose_done" and rec["pose"] == after_pose:
            raise KeyboardInterrupt

    with pytest.raises(SessionError, match="interrupted"):
        run_session(
            out,
            plan,
            cfg,
            device_opener(),
            camera_backend="simulated",
            dry_run=dry,
            simulation=sim,
            subscribers=[interrupt],
        )
    return out, dry.schedule


def _sample_theta_i(step) -> float:
    return round(math.degrees(math.acos(step["wi"][2])), 6)


# About 3.5 s (two rig openings, renders at 320 x 240, a reduction): not marked slow.
def test_pose_refused_by_a_narrowed_rig_is_skipped_and_the_rest_completes(files, capsys):
    out, sched = _start_and_interrupt(files, after_pose=1)
    steps = sched.steps
    kinds = [s["kind"] for s in steps]
    assert kinds == ["reference", "sample", "sample", "sample", "dark"]
    thetas = [_sample_theta_i(s) if s["kind"] != "dark" else None for s in steps]
    assert sorted(thetas[1:4]) == [20.0, 30.0, 40.0]
    victim = thetas.index(40.0)  # light arm at -40 deg, beyond the narrowed -35 deg
    assert victim > 1, "the refused pose must still be ahead when the session is cut"
    before = read_journal(out / "journal.jsonl")
    assert {r["pose"] for r in before if r["type"] == "pose_done"} == {0, 1}

    # the narrowed rig is refused without --force, nothing is written
    jbytes = (out / "journal.jsonl").read_bytes()
    args = ["capture", "resume", str(out), "--rig", str(files / "tight.toml"), "--quiet"]
    assert run(*args) == 1
    assert "light_azimuth" in capsys.readouterr().err
    assert (out / "journal.jsonl").read_bytes() == jbytes
    assert run(*args, "--force") == 0
    said = capsys.readouterr().out
    assert f"pose {victim} skipped" in said and "1 pose skipped" in said

    recs = read_journal(out / "journal.jsonl")
    skipped = [r for r in recs if r["type"] == "pose_skipped"]
    assert len(skipped) == 1
    assert skipped[0]["pose"] == victim
    reason = skipped[0]["reason"]
    # the reason names the joint, the angle it would need and the limit it breaks, and
    # its code says which rule refused it
    assert "light_azimuth" in reason and "-40.0" in reason and f"{LIMIT_DEG:.1f}" in reason
    assert "cannot reach" in reason and skipped[0]["code"] == "joint_limit"
    # nothing was shot for it; every other step was shot and closed exactly once
    shots = [r for r in recs if r["type"] == "shot"]
    assert victim not in {r["pose"] for r in shots}
    keys = [(r["pose"], r["frame"]) for r in shots]
    assert len(keys) == len(set(keys))
    done = [r["pose"] for r in recs if r["type"] == "pose_done"]
    assert sorted(done) == [k for k in range(len(steps)) if k != victim]
    assert {r["pose"] for r in shots} == set(done)
    assert recs[-1]["type"] == "stop" and recs[-1]["status"] == "completed"
    assert recs[-1]["parked"] is True and recs[-1]["torque_off"] is True
    # the pose after the skip was taken where it was asked (the skip moved nothing bad)
    kin = Kinematics(load_rig_config(files / "tight.toml"))
    for r in shots:
        assert sum(1 for s in shots if s["file"] == r["file"]) == 1
        data = (out / r["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == r["sha256"]
        if r["kind"] == "dark":
            continue
        assert r["joints"]["light_azimuth"] >= math.radians(LIMIT_DEG) - 1e-3 or r["pose"] <= 1
        wi, _ = kin.forward(r["joints"])
        err = math.degrees(math.acos(min(1.0, float(np.dot(wi, r["wi_requested"])))))
        assert err < 0.3
    assert {f"raw/{p.name}" for p in (out / "raw").iterdir()} == {r["file"] for r in shots}

    # inspect: status completed, the pose listed as skipped with its reason, exit 0
    # (a skip is a recorded outcome, not damage: only bad files make inspect fail)
    assert run("capture", "inspect", str(out), "--json") == 0
    info = json.loads(capsys.readouterr().out)
    assert info["status"] == "completed"
    assert info["skipped"] == [{"pose": victim, "reason": reason}]
    assert info["poses_total"] == len(steps)
    assert info["bad_files"] == [] and info["orphans"] == []
    assert info["files_verified"] == len(shots)
    assert run("capture", "inspect", str(out)) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert f"poses done {len(steps)}/{len(steps)} (1 of them skipped)" in text
    assert f"skipped pose {victim}: cannot reach" in text

    # a second resume does not retry or duplicate anything
    jbytes = (out / "journal.jsonl").read_bytes()
    assert run("capture", "resume", str(out), "--quiet") == 0
    capsys.readouterr()
    again = read_journal(out / "journal.jsonl")
    assert (out / "journal.jsonl").read_bytes().startswith(jbytes)
    assert [r["type"] for r in again[len(recs) :]] == ["start", "stop"]

    # reduce: no crash; the skipped pose is absent from samples.h5, the others present
    assert (out / "reduction.toml").is_file()  # written when the session was created
    assert run("capture", "reduce", str(out), "--quiet", "--no-plot") == 0
    samples = load_samples(out / "samples.h5")
    sample_poses = {k for k, s in enumerate(steps) if s["kind"] == "sample" and k != victim}
    poses_in_file = {int(f.split("/p")[1][:4]) for f in samples.frames}
    assert poses_in_file == sample_poses
    assert not np.any(np.isclose(np.degrees(np.arccos(samples.wi[:, 2])), 40.0, atol=5.0))
    # the calibration is intact: the Lambertian sample's closed form albedo / pi
    assert samples.valid.all()
    rel = np.abs(samples.brdf / (np.array([0.6, 0.5, 0.4]) / np.pi) - 1)
    assert np.median(rel) <= 0.01
    summary = json.loads((out / "reduction.json").read_text())
    assert summary["sample_poses"] == len(sample_poses) and summary["failed_poses"] == []


@pytest.mark.parametrize("when", ["between poses", "as the move starts"])
def test_a_servo_that_stops_answering_is_a_fault_not_a_skipped_pose(files, when):
    """A servo going silent makes the bus raise an error that is not ``PoseRefused``.
    Before typed refusals the session journaled that as ``pose_skipped`` for every
    remaining pose and ended "completed": the rest of the plan lost for good, as resume
    never retries a skipped pose.  It must stop on a fault, ready to resume."""
    from gonio.app.devices import open_rig
    from gonio.capture.engine import SessionDevices
    from gonio.simulator.rig_camera import SimulatedRigCamera
    from gonio.simulator.servo_model import VirtualServo
    from gonio.simulator.virtual_bus import VirtualBus

    plan = load_plan(files / "plan.toml")
    cfg = load_rig_config(files / "rig.toml")
    kin = Kinematics(cfg)
    dry = plan_session(plan, cfg)
    park = cfg.park_pulses
    servos = [VirtualServo(s.id, position=park[s.id]) for s in cfg.servos]
    out = files / "S"
    with VirtualBus(servos, time_scale="virtual", seed=0) as bus:
        real = cfg.model_copy(update={"bus": cfg.bus.model_copy(update={"port": bus.port})})

        def unplug(rec):
            if rec["type"] == "pose_done" and rec["pose"] == 1 and when == "between poses":
                bus.servos[3].silent = True  # the stage tilt servo's cable comes loose

        class UnplugAtMove:
            """The real rig; the cable comes loose just as the move to pose 2 starts."""

            moves = 0

            def __init__(self, rig):
                self.rig = rig

            def __getattr__(self, name):
                return getattr(self.rig, name)

            def move_to(self, wi, wo, *, joints=None):
                UnplugAtMove.moves += 1
                if UnplugAtMove.moves == 3 and when == "as the move starts":
                    bus.servos[3].silent = True
                return self.rig.move_to(wi, wo, joints=joints)

        def devices(rig):
            cam = SimulatedRigCamera(
                None, lambda: kin.poses(rig.read().joints), plan.seed, width=32, height=24
            )
            return SessionDevices(rig, cam, cam, cam, kin)

        with open_rig(real) as rig:
            with pytest.raises(SessionError, match="fault") as info:
                run_session(
                    out, plan, cfg, devices(UnplugAtMove(rig)), dry_run=dry, subscribers=[unplug]
                )
            assert "resume" in str(info.value) and "did not answer" in str(info.value)
        recs = read_journal(out / "journal.jsonl")
        assert [r for r in recs if r["type"] == "pose_skipped"] == []
        faults = [r for r in recs if r["type"] == "fault"]
        assert len(faults) == 1 and faults[0]["source"] == "rig"
        assert "did not answer" in faults[0]["error"]
        assert recs[-1]["type"] == "stop" and recs[-1]["status"] == "fault"
        # the silent servo could not confirm torque off: the journal says so, it does not
        # claim a safe state nobody saw
        assert recs[-1]["torque_off"] is False and recs[-1]["torque_unconfirmed"] == [3]
        assert {r["pose"] for r in recs if r["type"] == "pose_done"} == {0, 1}
        # the cable is plugged back in: resume shoots every remaining pose
        bus.servos[3].silent = False
        with open_rig(real) as rig:
            assert resume_session(out, devices(rig)).status == "completed"
        assert all(v == 0 for v in bus.torque().values())
    recs = read_journal(out / "journal.jsonl")
    assert [r for r in recs if r["type"] == "pose_skipped"] == []
    done = sorted(r["pose"] for r in recs if r["type"] == "pose_done")
    assert done == list(range(len(dry.steps)))
    keys = [(r["pose"], r["frame"]) for r in recs if r["type"] == "shot"]
    assert len(keys) == len(set(keys))


def test_progress_says_once_when_adaptive_rounds_cannot_reduce(capsys):
    """A round whose poses could not be reduced chooses its batch blind: the bar says so,
    once a cause, with the reduction's own words (brackets and all)."""
    from gonio.app.progress import SessionProgress

    why = "S: pose 1: the sample's ROI (columns 28..134, rows -2..122) is not inside [img]"
    with SessionProgress(quiet=False) as prog:
        prog({"type": "start", "poses": 2, "done": 0})
        for k in range(3):
            prog({"type": "adaptive_round", "round": k, "steps": [{}], "reduction_error": why})
        prog({"type": "adaptive_round", "round": 3, "steps": [], "reduction_error": "other"})
    out = " ".join(capsys.readouterr().out.split())  # however rich wraps the lines
    assert out.count("could not be reduced") == 2 and out.count(why) == 1, out
    assert prog.progress.tasks[0].total == 5


def test_progress_bar_counts_a_skipped_pose_as_finished():
    """The progress bar reached only N-1 of N when a pose was skipped."""
    from gonio.app.progress import SessionProgress

    with SessionProgress(quiet=True) as prog:
        for rec in (
            {"type": "start", "poses": 3, "done": 0},
            {"type": "pose_done", "pose": 0},
            {"type": "pose_skipped", "pose": 1, "reason": "refused"},
            {"type": "pose_done", "pose": 2},
        ):
            prog(rec)
    task = prog.progress.tasks[0]
    assert task.completed == task.total == 3 and prog.skipped == 1
