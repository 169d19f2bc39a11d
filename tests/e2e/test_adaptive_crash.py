"""An adaptive session killed with SIGKILL at random moments and resumed takes exactly the
poses of an uninterrupted run of the same seed, each shot once, every RAW file matching
its journal hash, and ends with the same rounds.

Each run or resume is the real CLI (``gonio capture run|resume``, so the advisor is the
composition root's FitAdvisor) in a process forked from this one after the heavy
imports; the parent kills it at a random time, checks the session, and resumes (the
harness, ``tests/crash_harness.py``, is shared with the grid sessions' crash test).  The
frames are 16 x 12 (the advisor then has nothing it can reduce: the reference target is
not found at that size, and it falls back to its data-independent choice -- which is
what a kill must not change either).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from crash_harness import check_consistent, kill_sessions, run_to_completion, warm_renderer

from gonio.capture.adaptive import round_records, session_steps
from gonio.capture.journal import read_journal
from gonio.rig.config import virtual_rig_document

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")

PLAN = """
name = "adaptive-crash"
seed = 11
[adaptive]
seed_poses = 5
retro_poses = 1
in_plane_poses = 2
batch_poses = 3
max_poses = 11
pool_step_deg = 20
candidates = ["lambert"]
[reductions]
isotropic = true
[exclusions]
min_separation_deg = 10
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
MIN_KILLS = 10


def _consistent(session: Path) -> list[dict]:
    """After any kill: journal readable, no shot twice, every journaled file present
    with its hash, and a round's record always before the shots of its steps."""
    recs = check_consistent(session)
    first_shot: dict[int, int] = {}
    for i, r in enumerate(recs):
        if r["type"] == "shot":
            first_shot.setdefault(r["pose"], i)
    for i, r in enumerate(recs):
        if r["type"] == "adaptive_round":
            for k in range(r["first_step"], r["first_step"] + len(r["steps"])):
                assert first_shot.get(k, i + 1) > i, "a round's poses shot before its record"
    return recs


def _taken(session: Path) -> tuple[list, set, list]:
    """The session's steps (kind, requested directions, pool id), its shots (pose,
    frame, exposure) and its rounds (chosen ids, stop)."""
    recs = read_journal(session / "journal.jsonl")
    manifest = json.loads((session / "manifest.json").read_text())
    steps = session_steps(manifest["schedule"], recs)
    poses = [(s["kind"], s.get("wi"), s.get("wo"), s.get("pool_id")) for s in steps]
    shots = {(r["pose"], r["frame"], r["exposure_time"]) for r in recs if r["type"] == "shot"}
    rounds = [(r["chosen_ids"], r["stop"]) for r in round_records(recs)]
    return poses, shots, rounds


@pytest.fixture(scope="module")
def warm():
    """Import and exercise the renderer once so that forked children start warm (and
    import the advisor's modules)."""
    import gonio.app.adaptive_advisor  # noqa: F401

    warm_renderer()
    import gonio.capture.adaptive_reduce  # noqa: F401
    import gonio.fitting  # noqa: F401


@pytest.mark.slow
def test_sigkill_during_an_adaptive_session_then_resume(tmp_path, warm):
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    run_args = ["capture", "run", str(tmp_path / "plan.toml"), "--rig", str(tmp_path / "rig.toml"),
                "--camera", "simulated", "--sim-speed", "200", "--quiet", "--out"]  # fmt: skip
    rng = np.random.default_rng(20261202)

    t_session = run_to_completion([*run_args, str(tmp_path / "ref")])
    ref_poses, ref_shots, ref_rounds = _taken(tmp_path / "ref")
    # the plan's own numbers: seed 5 + rounds of 3 up to 11 poses, darks at the end
    assert sum(p[0] == "sample" for p in ref_poses) == 11
    assert [len(c) for c, _ in ref_rounds] == [3, 3, 0] and ref_rounds[-1][1] == "max_poses"
    assert ref_poses[-1][0] == "dark"
    assert len(ref_shots) == 2 * (len(ref_poses) - 1) + 2  # two exposures, two darks

    def completed(session: Path) -> None:
        recs = _consistent(session)
        assert recs[-1]["type"] == "stop" and recs[-1]["status"] == "completed"
        poses, shots, rounds = _taken(session)
        assert poses == ref_poses
        assert shots == ref_shots
        assert rounds == ref_rounds
        assert {f"raw/{p.name}" for p in (session / "raw").iterdir()} == {
            r["file"] for r in recs if r["type"] == "shot"
        }

    kills, n_session = kill_sessions(
        tmp_path,
        run_args,
        ["--quiet", "--sim-speed", "200"],
        rng,
        t_session,
        min_kills=MIN_KILLS,
        max_cycles=40,
        after_kill=_consistent,
        completed=completed,
    )
    print(f"\n{kills} kills over {n_session} adaptive sessions (one {t_session:.2f} s)")
