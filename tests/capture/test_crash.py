"""Crash safety: sessions killed with SIGKILL at random moments and resumed end with
exactly the planned shots, none twice, every RAW file matching its journal hash.

Each run or resume is a separate process (forked from this one after the heavy imports,
so a trial costs the session's work rather than Python's start-up) running the real CLI:
virtual servo bus on a pty, dynamixel-sdk, rendered DNGs.  The parent kills it with
SIGKILL at a random time, checks the session directory, and resumes (the harness,
``tests/crash_harness.py``, is shared with the adaptive crash test).
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from crash_harness import (
    check_consistent,
    kill_sessions,
    run_to_completion,
    spawn_cli,
    warm_renderer,
)

from gonio.capture.journal import read_journal
from gonio.rig.config import virtual_rig_document

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")

PLAN = """
name = "crash"
seed = 11
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
[reference]
poses = [{ theta_i_deg = 0, theta_o_deg = 45, phi_o_deg = 180 }]
[simulation]
width = 16
height = 12
"""
MIN_KILLS = 20


def _planned(session: Path) -> set[tuple[int, int, float]]:
    """(pose, frame, exposure) the plan asks for, from the plan's own numbers: every
    sample and reference pose gets both exposures; the dark step one frame per exposure."""
    import json

    steps = json.loads((session / "manifest.json").read_text())["schedule"]
    exposures = (0.004, 0.016)
    out = set()
    for k in range(len(steps)):
        for f, t in enumerate(exposures):
            out.add((k, f, t))
    assert sum(s["kind"] == "dark" for s in steps) == 1
    assert sum(s["kind"] == "reference" for s in steps) == 1
    assert sum(s["kind"] == "sample" for s in steps) == 4
    return out


@pytest.fixture(scope="module")
def warm():
    """Import and exercise the renderer (lit and dark) once so that forked children start
    warm."""
    warm_renderer(dark=True)


@pytest.mark.slow
def test_sigkill_at_random_points_then_resume(tmp_path, warm):
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    run_args = [
        "capture",
        "run",
        str(tmp_path / "plan.toml"),
        "--rig",
        str(tmp_path / "rig.toml"),
        "--camera",
        "simulated",
        "--sim-speed",
        "200",
        "--quiet",
        "--out",
    ]
    rng = np.random.default_rng(20261122)

    # an uninterrupted session: how long one takes (to spread the kills over it)
    t_session = run_to_completion([*run_args, str(tmp_path / "ref")])
    planned = _planned(tmp_path / "ref")

    orphans_seen = 0

    def after_kill(session: Path) -> None:
        nonlocal orphans_seen
        recs = check_consistent(session)
        journaled = {r["file"] for r in recs if r["type"] == "shot"}
        if (session / "raw").is_dir():
            orphans_seen += sum(
                1 for p in (session / "raw").iterdir() if f"raw/{p.name}" not in journaled
            )

    def completed(session: Path) -> None:
        # exactly the planned shots, each once, every file matching its hash
        recs = check_consistent(session)
        shots = [r for r in recs if r["type"] == "shot"]
        got = {(r["pose"], r["frame"], r["exposure_time"]) for r in shots}
        assert len(shots) == len(planned) and got == planned
        assert {f"raw/{p.name}" for p in (session / "raw").iterdir()} == {r["file"] for r in shots}
        assert recs[-1]["type"] == "stop" and recs[-1]["status"] == "completed"

    kills, n_session = kill_sessions(
        tmp_path,
        run_args,
        ["--quiet", "--sim-speed", "200"],
        rng,
        t_session,
        min_kills=MIN_KILLS,
        max_cycles=60,
        after_kill=after_kill,
        completed=completed,
    )
    print(
        f"\n{kills} kills over {n_session} sessions (one session {t_session:.2f} s); "
        f"orphan RAW files seen after kills: {orphans_seen}"
    )


def test_sigterm_stops_with_the_finalizer(tmp_path, warm):
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    session = tmp_path / "S"
    pid = spawn_cli(
        [
            "capture",
            "run",
            str(tmp_path / "plan.toml"),
            "--rig",
            str(tmp_path / "rig.toml"),
            "--camera",
            "simulated",
            "--sim-speed",
            "5",
            "--quiet",
            "--out",
            str(session),
        ]
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # wait for the first completed pose
        jp = session / "journal.jsonl"
        if jp.exists() and any(r["type"] == "pose_done" for r in read_journal(jp)):
            break
        time.sleep(0.01)
    os.kill(pid, signal.SIGTERM)
    status = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
    assert status == 1
    recs = check_consistent(session)
    stop = recs[-1]
    assert stop["type"] == "stop" and stop["status"] == "interrupted"
    assert stop["torque_off"] is True
