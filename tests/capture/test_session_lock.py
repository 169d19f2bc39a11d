"""One process per session (issue 14.1): a second run or resume is refused with the
holder's PID and writes nothing; a dead holder's lock is taken over.

Before the lock, two ``gonio capture resume S/`` at once both exited 0, the journal got
interleaved (invalid lines in the middle), a pose went missing and RAW files were
orphaned.  Real CLI processes on the virtual bus, rendered DNGs.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from gonio.capture.journal import read_journal
from gonio.cli import run
from gonio.locks import LOCK_NAME, hold_lock, lock_holder
from gonio.rig.config import virtual_rig_document

GONIO = [sys.executable, "-m", "gonio"]

# settle_s = 2 s of servo time per pose: a resume at --sim-speed 1 takes several seconds
# of wall time, far longer than a second process needs to reach the lock.
PLAN = """
name = "lock"
seed = 4
settle_s = 2.0
[grid]
theta_i_deg = [10, 20, 30, 40]
phi_i_deg = [0]
theta_o_deg = [30, 50]
phi_o_deg = [180]
[bracket]
policy = "fixed"
exposures_s = [0.004, 0.016]
[simulation]
width = 16
height = 12
"""


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    d = tmp_path_factory.mktemp("lock")
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "plan.toml").write_text(PLAN)
    args = ["capture", "run", str(d / "plan.toml"), "--rig", str(d / "rig.toml")]
    code = run(*args, "--camera", "simulated", "--out", str(d / "S"), "--quiet")
    assert code == 0
    return d


def _copy(finished: Path, dest: Path, keep_lines: int | None = None) -> Path:
    shutil.copytree(finished / "S", dest)
    (dest / LOCK_NAME).unlink(missing_ok=True)
    if keep_lines is not None:
        jp = dest / "journal.jsonl"
        lines = jp.read_bytes().splitlines(keepends=True)
        assert len(lines) > keep_lines
        jp.write_bytes(b"".join(lines[:keep_lines]))
    return dest


def _snapshot(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def test_resume_of_a_held_session_is_refused_and_writes_nothing(finished, tmp_path, capsys):
    s = _copy(finished, tmp_path / "S", keep_lines=12)
    with hold_lock(s / LOCK_NAME, "test holder"):
        before = _snapshot(s)
        assert run("capture", "resume", str(s), "--quiet") == 1
        err = capsys.readouterr().err
        assert f"process {os.getpid()}" in err and "in use" in err
        assert _snapshot(s) == before
    # released: the resume goes ahead
    assert run("capture", "resume", str(s), "--quiet") == 0


def test_run_into_an_out_being_created_is_refused(finished, tmp_path, capsys):
    out = tmp_path / "new"
    with hold_lock(tmp_path / f".new{LOCK_NAME}", "test holder"):
        args = ["capture", "run", str(finished / "plan.toml"), "--rig", str(finished / "rig.toml")]
        code = run(*args, "--camera", "simulated", "--out", str(out), "--quiet")
        assert code == 1
        assert f"process {os.getpid()}" in capsys.readouterr().err
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == [f".new{LOCK_NAME}"]


@pytest.mark.slow
def test_two_resumes_at_once_one_refused_session_intact(finished, tmp_path):
    """The issue's reproduction: copy a finished session, cut its journal to 12 lines,
    start two resumes at once."""
    s = _copy(finished, tmp_path / "S", keep_lines=12)
    argv = [*GONIO, "capture", "resume", str(s), "--quiet", "--sim-speed", "1"]
    procs = [
        subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 1], outs
    loser = outs[[p.returncode for p in procs].index(1)][1]
    winner = procs[[p.returncode for p in procs].index(0)].pid
    assert f"in use by process {winner}" in loser
    recs = read_journal(s / "journal.jsonl")  # every line valid JSON
    shots = [r for r in recs if r["type"] == "shot"]
    keys = [(r["pose"], r["frame"]) for r in shots]
    assert len(keys) == len(set(keys)), "duplicate shots: two writers"
    steps = json.loads((s / "manifest.json").read_text())["schedule"]
    assert {r["pose"] for r in recs if r["type"] == "pose_done"} == set(range(len(steps)))
    assert sum(r["type"] == "start" for r in recs) == 2  # the run's and one resume's
    r = subprocess.run(
        [*GONIO, "capture", "inspect", str(s), "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["status"] == "completed" and info["orphans"] == [] and info["bad_files"] == []


def test_a_dead_holders_lock_is_taken_over(finished, tmp_path):
    s = _copy(finished, tmp_path / "S", keep_lines=12)
    code = (
        "import sys, time\nfrom gonio.locks import hold_lock\n"
        f"with hold_lock({str(s / LOCK_NAME)!r}, 'x'):\n"
        "    print('held', flush=True)\n    time.sleep(600)\n"
    )
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        assert lock_holder(s / LOCK_NAME) == p.pid
        assert run("capture", "resume", str(s), "--quiet") == 1  # alive
        os.kill(p.pid, signal.SIGKILL)
    finally:
        p.kill()
        p.wait(timeout=30)
    assert lock_holder(s / LOCK_NAME) == p.pid  # the dead holder's PID is still written
    assert run("capture", "resume", str(s), "--quiet") == 0
    assert read_journal(s / "journal.jsonl")[-1]["status"] == "completed"
