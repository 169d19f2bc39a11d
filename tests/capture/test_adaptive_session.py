"""Adaptive sessions on the simulated rig: rounds journaled before their poses, budgets,
resume replaying journaled rounds, reproducibility, bad input before anything moves.

Cheap: 16 x 12 frames and a stub advisor (the choice is the test's own), except the one
slow test that runs the real FitAdvisor on frames the reduction can measure.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from sim_sessions import scene_toml

from gonio.capture.adaptive import Decision, round_records, session_steps
from gonio.capture.journal import read_journal
from gonio.capture.plan import load_plan
from gonio.errors import ConfigError, SessionError
from gonio.rig.config import load_rig_config, virtual_rig_document

PLAN = """
name = "adaptive-test"
seed = 3
[adaptive]
seed_poses = 4
retro_poses = 1
in_plane_poses = 2
batch_poses = 3
max_poses = 10
pool_step_deg = 20
candidates = ["lambert"]
[reductions]
isotropic = true
[exclusions]
min_separation_deg = 10
[bracket]
policy = "fixed"
exposures_s = [0.004]
[darks]
count = 1
[reference]
poses = [{ theta_i_deg = 0, theta_o_deg = 45, phi_o_deg = 180 }]
[simulation]
width = 16
height = 12
"""


class Stub:
    """Chooses the first ``n`` ids it is offered (or what ``choose`` says), records every
    state it was given; ``stop_at``: the round it stops at; ``interrupt_at``: the round
    at which it raises KeyboardInterrupt (a Ctrl-C while advising)."""

    def __init__(self, n=3, stop_at=None, interrupt_at=None, choose=None):
        self.n, self.stop_at, self.interrupt_at, self.choose = n, stop_at, interrupt_at, choose
        self.states = []

    def advise(self, state):
        self.states.append(state)
        if state.round == self.interrupt_at:
            raise KeyboardInterrupt
        if state.round == self.stop_at:
            return Decision([], "enough", {"note": "stub stop"})
        ids = self.choose(state) if self.choose else state.pool_ids[: self.n].tolist()
        return Decision(list(ids), None, {"note": f"stub round {state.round}"})


def _files(d: Path, plan: str = PLAN) -> tuple[Path, object]:
    (d / "plan.toml").write_text(plan)
    (d / "rig.toml").write_text(virtual_rig_document())
    return d / "plan.toml", load_rig_config(d / "rig.toml")


def _run(d: Path, out: str, advisor, plan_text: str = PLAN, subscribers=()):
    from gonio.app.simulation import simulated_run
    from gonio.capture.sessions import run_session

    plan_path, cfg = _files(d, plan_text)
    plan = load_plan(plan_path)
    sim = simulated_run(plan, plan_path, None, "virtual")
    return run_session(
        d / out,
        plan,
        cfg,
        sim.opener,
        camera_backend="simulated",
        simulation=sim.simulation,
        attachments=sim.attachments,
        advisor=advisor,
        subscribers=subscribers,
    )


def _resume(session: Path, advisor, subscribers=()):
    from gonio.app.devices import device_opener
    from gonio.capture.sessions import resume_session

    return resume_session(
        session, device_opener(time_scale="virtual"), advisor=advisor, subscribers=subscribers
    )


def _journal(session: Path) -> list[dict]:
    return read_journal(session / "journal.jsonl")


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """One session of the plan with the stub advisor: (session, stub, result)."""
    d = tmp_path_factory.mktemp("adaptive_finished")
    stub = Stub()
    res = _run(d, "S", stub)
    return d / "S", stub, res


@pytest.fixture
def finished(finished_run) -> Path:
    return finished_run[0]


def test_rounds_are_journaled_before_their_poses_and_stop_at_max_poses(finished_run):
    S, stub, res = finished_run
    recs = _journal(S)
    manifest = json.loads((S / "manifest.json").read_text())
    rounds = round_records(recs, n_schedule=len(manifest["schedule"]))
    # seed 4, then 3 + 3 (max_poses 10 leaves room for 3 + 3), then the stop
    assert [len(r["chosen_ids"]) for r in rounds] == [3, 3, 0]
    assert rounds[-1]["stop"] == "max_poses" and rounds[-1]["steps"] == [
        {"kind": "dark", "wi": None, "wo": None}
    ]
    steps = session_steps(manifest["schedule"], recs)
    assert res.poses_total == len(steps) == 1 + 4 + 6 + 1 and res.status == "completed"
    assert res.adaptive_stop == {"round": 2, "stop": "max_poses", "poses_done": 10}
    assert [s["kind"] for s in steps] == ["reference"] + ["sample"] * 10 + ["dark"]
    # the advisor was offered only poses not yet taken, and the pool shrank by each batch
    pool = json.loads((S / "adaptive_pool.json").read_text())
    taken = [s["pool_id"] for s in steps if s["kind"] == "sample"]
    assert len(set(taken)) == 10
    for st in stub.states:
        before = {s["pool_id"] for s in steps[: st.measured_steps[-1] + 1] if "pool_id" in s}
        assert not before & set(st.pool_ids.tolist())
        assert len(st.pool_ids) == len(pool["wi"]) - len(before)
        assert np.allclose(st.pool_wi, np.asarray(pool["wi"])[st.pool_ids])
    # each round's record comes before any shot of its steps; its steps' directions are
    # the pool entries it chose, in its (travel) order
    index = {id(r): i for i, r in enumerate(recs)}
    for r in rounds:
        i = index[
            id(
                next(
                    x
                    for x in recs
                    if x.get("round") == r["round"] and x["type"] == "adaptive_round"
                )
            )
        ]
        for k, s in enumerate(r["steps"], r["first_step"]):
            assert all(j > i for j, x in enumerate(recs) if x.get("pose") == k)
            if s["kind"] == "sample":
                assert np.allclose(s["wi"], pool["wi"][s["pool_id"]])
        assert sorted(s["pool_id"] for s in r["steps"] if "pool_id" in s) == sorted(r["chosen_ids"])
    # the darks at the end were shot after the stop, at the samples' exposure
    dark = [x for x in recs if x["type"] == "shot" and x["kind"] == "dark"]
    assert len(dark) == 1 and dark[0]["pose"] == len(steps) - 1
    assert dark[0]["exposure_time_requested"] == 0.004


def test_advisor_stop_and_bad_ids(tmp_path):
    offered = {}

    def choose(state):
        offered[state.round] = state.pool_ids.tolist()
        return [10**6, state.pool_ids[0], state.pool_ids[0]]  # unknown id, duplicate

    _run(tmp_path, "S", Stub(stop_at=1, choose=choose))
    rounds = round_records(_journal(tmp_path / "S"))
    assert rounds[0]["chosen_ids"] == [offered[0][0]] and rounds[0]["ignored_ids"] == [10**6]
    assert rounds[1]["stop"] == "enough" and rounds[1]["note"] == "stub stop"


def test_time_budget_cuts_the_batch(tmp_path):
    from gonio.capture.sessions import plan_session

    plan_path, cfg = _files(tmp_path)
    plan = load_plan(plan_path)
    seed_s = plan_session(plan, cfg).schedule.estimated_duration_s
    # room for about one and a half more poses (one pose: settle + 1 frame + travel)
    per_pose = plan.bracket.exposures_s[0] + plan.bracket.shot_overhead_s
    budget = seed_s + 1.5 * per_pose + 2.0
    text = PLAN.replace("max_poses = 10", f"max_poses = 10\nmax_time_s = {budget}")
    _run(tmp_path, "S", Stub(), text)
    recs = _journal(tmp_path / "S")
    rounds = round_records(recs)
    assert rounds[-1]["stop"] == "max_time_s"
    kept = sum(len(r["chosen_ids"]) for r in rounds)
    assert 0 <= kept < 3
    # the estimate of what was planned, recomputed from the journal's joints, is within it
    from gonio.rig.kinematics import Kinematics

    kin = Kinematics(cfg)
    steps = session_steps(
        json.loads((tmp_path / "S" / "manifest.json").read_text())["schedule"], recs
    )
    q, travel = cfg.park_rad, 0.0
    for s in steps:
        if s.get("joints"):
            travel += kin.move_time(q, s["joints"])
            q = s["joints"]
    n = sum(s["kind"] in ("sample", "reference") for s in steps)
    # the estimator, written out for this plan: fixed bracket of one 4 ms frame with the
    # default 0.5 s download, no settle; one dark frame at that exposure
    per_frame = 0.004 + 0.5
    assert plan.settle_s == 0 and plan.bracket.shot_overhead_s == 0.5
    assert travel + n * per_frame + 1 * per_frame <= budget + 1e-9
    if kept:  # the batch of 3 was cut to what fits
        assert rounds[0]["cut_to_budget"] == {"asked": 3, "kept": kept}


def test_resume_replays_journaled_rounds_and_asks_only_for_the_rest(tmp_path):
    from gonio.capture.sessions import SessionStopped

    # interrupted while round 1 is being decided: round 0 is journaled and shot
    with pytest.raises(SessionStopped):
        _run(tmp_path, "S", Stub(interrupt_at=1))
    S = tmp_path / "S"
    before = round_records(_journal(S))
    assert [r["round"] for r in before] == [0]
    # an advisor that would choose differently: the journaled round must not be redone
    later = Stub(choose=lambda st: st.pool_ids[::-1][:3].tolist())
    _resume(S, later)
    assert [st.round for st in later.states] == [1]
    after = round_records(_journal(S))
    assert after[0] == before[0]

    # the same as a session that was never interrupted with that pair of advisors
    def switch(st):
        return st.pool_ids[:3].tolist() if st.round == 0 else st.pool_ids[::-1][:3].tolist()

    _run(tmp_path, "U", Stub(choose=switch))
    ref = round_records(_journal(tmp_path / "U"))
    assert [r["chosen_ids"] for r in after] == [r["chosen_ids"] for r in ref]
    assert [r["steps"] for r in after] == [r["steps"] for r in ref]


def test_progress_bar_grows_with_the_rounds_and_ends_full(tmp_path):
    """The start document counts the seed design only; each round adds its batch (the
    bar read 50/26 at the end of an adaptive session).  Checked against the journal's
    own pose_done records, through an interruption and its resume."""
    from gonio.app.progress import SessionProgress
    from gonio.capture.sessions import SessionStopped

    def bar_of(prog):
        return prog.progress.tasks[0]

    with SessionProgress(quiet=True) as prog, pytest.raises(SessionStopped):
        _run(tmp_path, "S", Stub(interrupt_at=1), subscribers=[prog])
    S = tmp_path / "S"
    recs = _journal(S)
    done = sum(r["type"] == "pose_done" for r in recs)
    assert [r["round"] for r in round_records(recs)] == [0]  # round 0's batch was shot
    assert bar_of(prog).completed == bar_of(prog).total == done
    with SessionProgress(quiet=True) as prog:
        _resume(S, Stub(), subscribers=[prog])
    done = sum(r["type"] == "pose_done" for r in _journal(S))
    assert len(round_records(_journal(S))) >= 2
    assert bar_of(prog).completed == bar_of(prog).total == done


_TIMES = ("time", "advise_s", "timing", "created")


def _strip(x):
    if isinstance(x, dict):
        return {k: _strip(v) for k, v in x.items() if k not in _TIMES}
    if isinstance(x, list):
        return [_strip(v) for v in x]
    return x


def test_two_runs_of_one_seed_are_identical(tmp_path, finished):
    A, B = finished, tmp_path / "B"
    _run(tmp_path, "B", Stub())
    ja, jb = _strip(_journal(A)), _strip(_journal(B))
    assert ja == jb
    raw_a = sorted((A / "raw").iterdir())
    assert [p.name for p in raw_a] == sorted(p.name for p in (B / "raw").iterdir())
    assert [p.read_bytes() for p in raw_a] == [(B / "raw" / p.name).read_bytes() for p in raw_a]
    assert (A / "adaptive_pool.json").read_bytes() == (B / "adaptive_pool.json").read_bytes()


def test_inspect_shows_the_rounds(finished):
    from click.testing import CliRunner

    from gonio.cli import cli

    out = CliRunner().invoke(cli, ["capture", "inspect", str(finished), "--json"])
    assert out.exit_code == 0, out.output
    info = json.loads(out.output)
    assert [(r["round"], r["poses"], r["stop"]) for r in info["rounds"]] == [
        (0, 3, None), (1, 3, None), (2, 0, "max_poses")
    ]  # fmt: skip
    assert info["poses_done"] == info["poses_total"] == 12
    table = CliRunner().invoke(cli, ["capture", "inspect", str(finished)], env={"COLUMNS": "160"})
    assert "adaptive rounds" in table.output and "max_poses" in table.output


MAX = "max_poses = 10"
BAD_INPUT = [
    ((MAX, MAX + "\nmax_time_s = 5"), ["adaptive.max_time_s = 5", "seed design"]),
    (('candidates = ["lambert"]', 'candidates = ["lambert", "blinn"]'), ["candidates", "blinn"]),
    ((MAX, MAX + "\ntarget_rel_sigma = { alpha = 0 }"), ["target_rel_sigma.alpha"]),
    ((MAX, "max_poses = 2"), ["max_poses = 2", "seed_poses = 4"]),
    (("[reductions]", "[grid]\ntheta_i_deg = [20]\ntheta_o_deg = [30]\n[reductions]"), ["[grid]"]),
    (("[reference]\nposes", "[reference]\nxposes"), ["reference"]),
]


@pytest.mark.parametrize(("edit", "words"), BAD_INPUT)
def test_bad_input_is_refused_before_anything_moves(tmp_path, capsys, edit, words):
    from gonio.cli import main

    text = PLAN.replace(*edit)
    assert text != PLAN
    _files(tmp_path, text)
    with pytest.raises(SystemExit) as e:
        main(["capture", "run", str(tmp_path / "plan.toml"), "--rig", str(tmp_path / "rig.toml"),
              "--camera", "simulated", "--quiet", "--out", str(tmp_path / "S")])  # fmt: skip
    err = capsys.readouterr().err
    assert e.value.code == 1 and err.startswith("error:") and "Traceback" not in err
    for w in words:
        assert w in err, err
    assert not (tmp_path / "S").exists()


def test_the_advisor_may_be_a_class_or_a_factory(tmp_path):
    made = []

    class Made(Stub):
        def __init__(self, plan):
            super().__init__(stop_at=0)
            made.append(plan.name)

    _run(tmp_path, "C", Made)
    _run(tmp_path, "F", lambda plan: Made(plan))
    assert made == ["adaptive-test", "adaptive-test"]
    for name in "CF":
        assert round_records(_journal(tmp_path / name))[0]["stop"] == "enough"


def test_adaptive_plan_without_advisor_is_refused(tmp_path):
    from gonio.capture.sessions import run_session

    plan_path, cfg = _files(tmp_path)
    with pytest.raises(SessionError, match="advisor"):
        run_session(tmp_path / "S", load_plan(plan_path), cfg, lambda req: None)
    assert not (tmp_path / "S").exists()


def test_a_pool_that_cannot_hold_the_seed_is_refused(tmp_path):
    from gonio.capture.sessions import plan_session

    plan_path, cfg = _files(
        tmp_path,
        PLAN.replace("pool_step_deg = 20", "pool_step_deg = 45").replace(
            "seed_poses = 4", "seed_poses = 9"
        ),
    )
    with pytest.raises(ConfigError, match="fewer than adaptive.seed_poses = 9"):
        plan_session(load_plan(plan_path), cfg)


# --------------------------------------------------------------------------------------
# The real advisor, on frames the reduction can measure

SCENE = scene_toml(
    brdf={"model": "lambert+ggx", "params": {"albedo": [0.5, 0.4, 0.3], "ks": 0.3, "alpha": 0.2}}
)

FIT_PLAN = """
name = "adaptive-fit"
seed = 5
[adaptive]
seed_poses = 6
retro_poses = 1
in_plane_poses = 3
batch_poses = 3
max_poses = 9
pool_step_deg = 20
candidates = ["lambert", "lambert+ggx"]
target_rel_sigma = { alpha = 0.0001 }
[reductions]
isotropic = true
[exclusions]
min_separation_deg = 10
grazing_limit_deg = 65
[bracket]
policy = "adaptive"
roi = [0.42, 0.42, 0.58, 0.58]
exposure_time_s = 0.0005
[reference]
poses = [{theta_i_deg = 0, theta_o_deg = 30}]
[simulation]
scene = "scene.toml"
"""


@pytest.mark.slow
def test_fit_advisor_session_is_reproducible_and_fits(tmp_path):
    """`gonio capture run` with an [adaptive] plan, twice, then `capture reduce` and
    `gonio fit`: the same journals (apart from timestamps) and samples.h5, every round
    with its fits and timings, and the fitted alpha near the scene's 0.2."""
    import h5py

    from gonio.cli import main

    def cli(*args: str) -> int:
        try:
            main(list(args))
        except SystemExit as exc:
            return int(exc.code or 0)
        return 0

    (tmp_path / "scene.toml").write_text(SCENE)
    _files(tmp_path, FIT_PLAN)
    for name in ("A", "B"):
        files = ("--rig", str(tmp_path / "rig.toml"), "--out", str(tmp_path / name))
        run = ("capture", "run", str(tmp_path / "plan.toml"), "--camera", "simulated", "--quiet")
        assert cli(*run, *files) == 0
        assert cli("capture", "reduce", str(tmp_path / name), "--quiet", "--no-plot") == 0
    ja, jb = (_strip(_journal(tmp_path / n)) for n in "AB")
    assert ja == jb
    rounds = round_records(_journal(tmp_path / "A"))
    assert [len(r["chosen_ids"]) for r in rounds] == [3, 0] and rounds[-1]["stop"] == "max_poses"
    r0 = rounds[0]
    assert {f["model"] for f in r0["fits"]} == {"lambert", "lambert+ggx"}
    assert r0["fit"]["model"] == "lambert+ggx" and r0["advise_s"] > 0 and r0["batch_time_s"] > 0
    # the scene's own model fits: no misfit is read from the data, the design is the plan's
    assert r0["misfit"]["tau"] == 0.0 and r0["misfit"]["chi2_dof"] < 4.0, r0["misfit"]
    assert "misfit" not in r0["why"]
    with (
        h5py.File(tmp_path / "A" / "samples.h5") as fa,
        h5py.File(tmp_path / "B" / "samples.h5") as fb,
    ):
        names = []
        fa.visit(names.append)
        for n in names:
            if isinstance(fa[n], h5py.Dataset):
                a, b = fa[n][()], fb[n][()]
                nan_ok = np.asarray(a).dtype.kind == "f"
                assert np.array_equal(a, b, equal_nan=nan_ok), n
    assert cli("fit", str(tmp_path / "A" / "samples.h5"), "-m", "lambert+ggx",
               "--out", str(tmp_path / "F")) == 0  # fmt: skip
    fit = json.loads((tmp_path / "F" / "fit.json").read_text())
    alpha = np.asarray(fit["params"]["alpha"], float)
    assert np.all(np.abs(alpha - 0.2) < 0.02), alpha  # the scene's truth
    assert math.isfinite(float(np.max(fit["std"]["alpha"])))


def test_realistic_world_through_the_cli(tmp_path):
    """The as-built world, wired as every simulated session is (`--world realistic`):
    the session completes, and the rig went to the joints each round planned for it."""
    from gonio.cli import main

    _files(tmp_path)
    main(["capture", "run", str(tmp_path / "plan.toml"), "--rig", str(tmp_path / "rig.toml"),
          "--camera", "simulated", "--world", "realistic", "--world-seed", "3", "--quiet",
          "--out", str(tmp_path / "S")])  # fmt: skip
    recs = _journal(tmp_path / "S")
    assert recs[-1]["type"] == "stop" and recs[-1]["status"] == "completed"
    steps = session_steps(
        json.loads((tmp_path / "S" / "manifest.json").read_text())["schedule"], recs
    )
    assert sum(s["kind"] == "sample" for s in steps) == 10
    shots = {r["pose"]: r for r in recs if r["type"] == "shot"}
    for k, s in enumerate(steps):
        if s["kind"] == "sample":
            got = shots[k]["joints"]
            # one pulse of a 4096-pulse servo is 1.5 mrad
            assert max(abs(got[j] - s["joints"][j]) for j in got) < 0.01


@pytest.mark.parametrize(
    ("field", "value"),
    [("first_step", "x"), ("round", 5), ("steps", "dark"), ("chosen_ids", [-1])],
)
def test_a_damaged_round_record_is_named(tmp_path, finished, field, value):
    import shutil

    from gonio.capture.reduce import reduce_session
    from gonio.capture.sessions import inspect_session
    from gonio.errors import FileFormatError

    S = tmp_path / "S"
    shutil.copytree(finished, S)
    lines = (S / "journal.jsonl").read_text().splitlines()
    k = next(i for i, x in enumerate(lines) if '"adaptive_round"' in x)
    rec = json.loads(lines[k])
    rec[field] = value
    lines[k] = json.dumps(rec)
    (S / "journal.jsonl").write_text("\n".join(lines) + "\n")
    for call in (lambda: inspect_session(S), lambda: reduce_session(S), lambda: _resume(S, Stub())):
        with pytest.raises(FileFormatError) as e:
            call()
        assert "journal.jsonl" in str(e.value) and field in str(e.value), str(e.value)


def test_as_built_kinematics_rounds_plan_the_joints_the_rig_takes(tmp_path):
    """On an as-built rig (1 deg backlash on every joint, zero offsets) a direction's
    joints depend on the side each joint approaches from.  Each round's dry run plans
    from where the path left the rig -- joints and approach signs -- so the rig moves to
    the planned joints (a hint the present approach makes miss would be re-solved, about
    a backlash away)."""
    import tomllib

    import tomli_w

    from gonio.app.simulation import simulated_run
    from gonio.capture.sessions import run_session
    from gonio.rig.config import rig_config_from_dict

    doc = tomllib.loads(virtual_rig_document())
    for k, s in enumerate(doc["servos"]):
        s["backlash_deg"] = 1.0
        s["zero_deg"] = s.get("zero_deg", 0.0) + 0.3 * (k + 1)
    (tmp_path / "rig.toml").write_text(tomli_w.dumps(doc))
    (tmp_path / "plan.toml").write_text(PLAN)
    cfg = rig_config_from_dict(tomllib.loads((tmp_path / "rig.toml").read_text()))
    from gonio.rig.kinematics import Kinematics

    assert not Kinematics(cfg).nominal
    plan = load_plan(tmp_path / "plan.toml")
    sim = simulated_run(plan, tmp_path / "plan.toml", None, "virtual")
    run_session(tmp_path / "S", plan, cfg, sim.opener, camera_backend="simulated",
                simulation=sim.simulation, attachments=sim.attachments, advisor=Stub())  # fmt: skip
    recs = _journal(tmp_path / "S")
    schedule = json.loads((tmp_path / "S" / "manifest.json").read_text())["schedule"]
    steps = session_steps(schedule, recs)
    shots = {r["pose"]: r for r in recs if r["type"] == "shot"}
    pulse = 2 * math.pi / 4096
    in_rounds = [k for k in range(len(schedule), len(steps)) if steps[k]["kind"] == "sample"]
    assert len(in_rounds) == 6
    for k, s in enumerate(steps):
        if s["kind"] == "sample":
            got = shots[k]["joints"]
            assert max(abs(got[j] - s["joints"][j]) for j in got) < 2 * pulse, (k, got, s)
