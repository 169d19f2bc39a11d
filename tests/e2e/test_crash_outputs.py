"""Crash safety of the outputs (issue 14, "Must show"): ``gonio capture reduce``,
``gonio fit --force`` and two concurrent writers of one output, killed with SIGKILL at
random moments.

After every kill the output is either the complete previous set or the complete new set
(compared byte for byte with uninterrupted runs), and the next complete run leaves no
temporary file behind (:func:`gonio.atomic.stale_temporaries`).  Each command is a forked
child (after the heavy imports, as in ``tests/capture/test_crash.py``) running the real
CLI; kill times are drawn from a seeded generator, spread over the command's duration
measured first.  The deterministic tests kill the writer *inside* its output phase.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from sim_sessions import REFERENCE_NORMAL, REFERENCE_OBLIQUE, grid_plan, scene_toml

from gonio.atomic import stale_temporaries
from gonio.capture.reduce import output_lock
from gonio.cli import run
from gonio.rig.config import virtual_rig_document

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")

MIN_KILLS = 20


def _reduce_test_documents() -> tuple[str, str]:
    """The reduction tests' plan and scene (a lambertian sample the reduction measures, from
    the shared session factory), cut to two sample poses at 320 x 240 so that a reduction
    takes a fraction of a second."""
    plan = grid_plan(
        "reduce-test",
        seed=5,
        theta_i_deg=[20, 40],
        theta_o_deg=[30],
        darks=2,
        references=[REFERENCE_NORMAL, REFERENCE_OBLIQUE],
    )
    return plan, scene_toml(resolution=(320, 240))


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    """A small simulated session, reduced once; warms the imports forked children use."""
    d = tmp_path_factory.mktemp("crash_outputs")
    plan, scene = _reduce_test_documents()
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "plan.toml").write_text(plan)
    (d / "scene.toml").write_text(scene)
    argv = ["capture", "run", str(d / "plan.toml"), "--rig", str(d / "rig.toml")]
    assert run(*argv, "--camera", "simulated", "--sim-speed", "200", "--quiet",
               "--out", str(d / "S")) == 0  # fmt: skip
    assert run("capture", "reduce", str(d / "S"), "--quiet", "--no-plot") == 0
    import gonio.fitting.plots  # noqa: F401 - imported before forking

    return d / "S"


def _spawn(argv: list[str], log: Path | None = None, setup=None) -> int:
    """Fork a child that runs ``gonio ARGV`` (output to ``log``) and never returns."""
    pid = os.fork()
    if pid == 0:
        code = 70
        try:
            fd = os.open(log or os.devnull, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.dup2(fd, 1)
            os.dup2(fd, 2)
            sys.stdout = open(1, "w", closefd=False)  # noqa: SIM115
            sys.stderr = open(2, "w", closefd=False)  # noqa: SIM115
            if setup is not None:
                setup()
            from gonio.cli import main

            try:
                main(argv)
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
        finally:
            os._exit(code)
    return pid


def _wait(pid: int) -> int:
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


def _run_or_kill(pid: int, after_s: float) -> int | None:
    """Wait for the child up to ``after_s`` (polling); SIGKILL it then.  Returns its exit
    code, or None when it was killed."""
    deadline = time.monotonic() + after_s
    while time.monotonic() < deadline:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            return os.waitstatus_to_exitcode(status)
        time.sleep(0.002)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    return None


def _timed(argv: list[str]) -> float:
    t0 = time.monotonic()
    assert _wait(_spawn(argv)) == 0, argv
    return time.monotonic() - t0


def _snapshot(folder: Path, names: tuple[str, ...] | None = None) -> dict[str, str]:
    """sha256 of the output files in ``folder`` (the lock file is not an output)."""
    out = {}
    for p in sorted(folder.iterdir()) if folder.is_dir() else []:
        if p.is_file() and p.name != ".gonio.lock" and (names is None or p.name in names):
            out[p.name] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


# --------------------------------------------------------------------------------------
# gonio fit --force


def _fit_sets(session: Path, tmp_path: Path) -> tuple[Path, dict, list[str], dict]:
    """The previous set (lambert: fit.json, material.xml, two plots) in OLD/, and the new
    set's argv and snapshot (oren-nayar: no Mitsuba equivalent, so no material.xml)."""
    src = str(session / "samples.h5")
    old = tmp_path / "OLD"
    assert run("fit", src, "-m", "lambert", "--out", str(old)) == 0
    new_argv = ["fit", src, "-m", "oren-nayar", "--force", "--out"]
    ref = tmp_path / "NEW"
    assert run(*new_argv, str(ref)) == 0
    old_set, new_set = _snapshot(old), _snapshot(ref)
    assert set(old_set) == {"fit.json", "material.xml", "slices.png", "residuals.png"}
    assert set(new_set) == {"fit.json", "slices.png", "residuals.png"}
    shutil.rmtree(ref)
    return old, old_set, new_argv, new_set


@pytest.mark.slow
def test_fit_force_killed_at_random_leaves_the_old_or_the_new_set(session, tmp_path):
    old, old_set, new_argv, new_set = _fit_sets(session, tmp_path)
    out = tmp_path / "F"
    shutil.copytree(old, out)
    t_fit = _timed([*new_argv, str(out)])
    assert _snapshot(out) == new_set
    rng = np.random.default_rng(20261201)
    kills = finished = 0
    while kills < MIN_KILLS:
        shutil.rmtree(out)
        shutil.copytree(old, out)
        code = _run_or_kill(_spawn([*new_argv, str(out)]), rng.uniform(0.0, 1.1 * t_fit))
        if code is None:
            kills += 1
        else:
            assert code == 0
            finished += 1
        assert _snapshot(out) in (old_set, new_set), f"a mixed set after {kills} kills"
    # The next complete run replaces the set and removes every leftover of the kills.
    assert _wait(_spawn([*new_argv, str(out)])) == 0
    assert _snapshot(out) == new_set
    assert stale_temporaries(tmp_path) == [] and stale_temporaries(out) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["F", "OLD"]
    print(f"\nfit --force: {kills} kills, {finished} finished (one run {t_fit:.2f} s)")


def test_fit_killed_inside_its_output_phase_keeps_the_old_set(session, tmp_path):
    old, old_set, new_argv, _ = _fit_sets(session, tmp_path)
    out = tmp_path / "F"
    shutil.copytree(old, out)

    def die_while_plotting():
        import gonio.fitting.plots as plots

        # the in-process drawing path, so that the command itself dies in its output phase
        # (with the figure worker the figures are drawn in other processes)
        os.environ["GONIO_PLOT_WORKER"] = "0"

        def killed(*a, **k):  # fit.json and slices.png of the new set are written by now
            os.kill(os.getpid(), signal.SIGKILL)

        plots.plot_residual_map = killed

    assert _wait(_spawn([*new_argv, str(out)], setup=die_while_plotting)) == -signal.SIGKILL
    assert _snapshot(out) == old_set
    assert len(stale_temporaries(tmp_path)) == 1  # the staged set, until the next fit
    assert _wait(_spawn([*new_argv, str(out)])) == 0
    assert stale_temporaries(tmp_path) == []


@pytest.mark.slow
def test_two_concurrent_fits_on_one_output_killed_at_random(session, tmp_path):
    old, old_set, new_argv, new_set = _fit_sets(session, tmp_path)
    out = tmp_path / "F"
    shutil.copytree(old, out)
    t_fit = _timed([*new_argv, str(out)])
    rng = np.random.default_rng(20261202)
    kills = refused = 0
    trial = 0
    while kills < MIN_KILLS:
        trial += 1
        shutil.rmtree(out)
        shutil.copytree(old, out)
        logs = [tmp_path / f"a{trial}.log", tmp_path / f"b{trial}.log"]
        pids = [_spawn([*new_argv, str(out)], logs[0]), _spawn([*new_argv, str(out)], logs[1])]
        victim = int(rng.integers(2))
        code_v = _run_or_kill(pids[victim], rng.uniform(0.0, 1.1 * t_fit))
        code_o = _wait(pids[1 - victim])
        kills += code_v is None
        for pid, code, log, other in (
            (pids[victim], code_v, logs[victim], pids[1 - victim]),
            (pids[1 - victim], code_o, logs[1 - victim], pids[victim]),
        ):
            if code == 1:  # refused: the other one held the output, and it says so
                text = " ".join(log.read_text().split())
                assert f"is in use by process {other}" in text, text
                refused += 1
            else:
                assert code in (0, None), f"pid {pid} exited {code}: {log.read_text()}"
        assert _snapshot(out) in (old_set, new_set), f"a mixed set in trial {trial}"
        for log in logs:
            log.unlink()
    assert refused > 0  # the two did overlap, and one was turned away
    assert _wait(_spawn([*new_argv, str(out)])) == 0
    assert _snapshot(out) == new_set
    assert stale_temporaries(tmp_path) == [] and stale_temporaries(out) == []
    print(f"\nconcurrent fits: {kills} kills over {trial} trials, {refused} refused")


# --------------------------------------------------------------------------------------
# gonio capture reduce

REDUCE_OUTPUTS = ("samples.h5", "reduction.json")


def _reduce_sets(session: Path, tmp_path: Path) -> tuple[Path, dict, dict]:
    """A session copy holding a previous reduction's outputs (a different, valid sample
    set and summary), and the snapshot of this session's own reduction."""
    from gonio.dataset import BRDFSamples, save_samples
    from gonio.radiometry import normalize

    new_set = _snapshot(session, REDUCE_OUTPUTS)
    assert set(new_set) == set(REDUCE_OUTPUTS)
    s = tmp_path / "S"
    shutil.copytree(session, s, ignore=shutil.ignore_patterns("samples.*", "reduction.json"))
    rng = np.random.default_rng(3)
    w = normalize(rng.normal(size=(5, 3)) + [0, 0, 3])
    save_samples(s / "samples.h5", BRDFSamples(wi=w, wo=w[::-1], brdf=np.full((5, 3), 0.1)))
    (s / "reduction.json").write_text(json.dumps({"samples": 5, "previous": True}))
    old_set = _snapshot(s, REDUCE_OUTPUTS)
    assert old_set.keys() == new_set.keys() and old_set != new_set
    return s, old_set, new_set


def _per_file_old_or_new(s: Path, old_set: dict, new_set: dict) -> dict:
    now = _snapshot(s, REDUCE_OUTPUTS)
    assert set(now) == set(REDUCE_OUTPUTS), f"an output went missing: {sorted(now)}"
    for name, digest in now.items():
        assert digest in (old_set[name], new_set[name]), f"{name} is neither old nor new"
    return now


@pytest.mark.slow
def test_reduce_killed_at_random_leaves_whole_files(session, tmp_path):
    s, old_set, new_set = _reduce_sets(session, tmp_path)
    argv = ["capture", "reduce", str(s), "--quiet", "--no-plot"]
    backup = {n: (s / n).read_bytes() for n in REDUCE_OUTPUTS}
    t_reduce = _timed(argv)
    assert _snapshot(s, REDUCE_OUTPUTS) == new_set
    rng = np.random.default_rng(20261203)
    kills = 0
    while kills < MIN_KILLS:
        for n, data in backup.items():
            (s / n).write_bytes(data)
        if _run_or_kill(_spawn(argv), rng.uniform(0.0, 1.1 * t_reduce)) is None:
            kills += 1
        now = _per_file_old_or_new(s, old_set, new_set)
        assert now in (old_set, new_set), f"a mixed set after {kills} kills"
    assert _wait(_spawn(argv)) == 0
    assert _snapshot(s, REDUCE_OUTPUTS) == new_set
    assert stale_temporaries(s) == [] and stale_temporaries(s / "raw") == []
    print(f"\nreduce: {kills} kills (one run {t_reduce:.2f} s)")


def test_reduce_killed_between_its_outputs_keeps_the_old_set(session, tmp_path):
    s, old_set, _ = _reduce_sets(session, tmp_path)

    def die_before_the_summary():
        import gonio.capture.reduce as reduce

        def killed(*a, **k):  # samples.h5 is in place by now
            os.kill(os.getpid(), signal.SIGKILL)

        reduce._write_json = killed

    argv = ["capture", "reduce", str(s), "--quiet", "--no-plot"]
    assert _wait(_spawn(argv, setup=die_before_the_summary)) == -signal.SIGKILL
    assert _snapshot(s, REDUCE_OUTPUTS) == old_set


@pytest.mark.slow
def test_two_concurrent_reduces_killed_at_random_leave_whole_files(session, tmp_path):
    s, old_set, new_set = _reduce_sets(session, tmp_path)
    argv = ["capture", "reduce", str(s), "--quiet", "--no-plot"]
    backup = {n: (s / n).read_bytes() for n in REDUCE_OUTPUTS}
    t_reduce = _timed(argv)
    rng = np.random.default_rng(20261204)
    kills = 0
    while kills < MIN_KILLS:
        for n, data in backup.items():
            (s / n).write_bytes(data)
        pids = [_spawn(argv), _spawn(argv)]
        victim = int(rng.integers(2))
        kills += _run_or_kill(pids[victim], rng.uniform(0.0, 1.1 * t_reduce)) is None
        assert _wait(pids[1 - victim]) in (0, 1)  # 1: refused by a reduce lock
        _per_file_old_or_new(s, old_set, new_set)
    assert _wait(_spawn(argv)) == 0
    assert _snapshot(s, REDUCE_OUTPUTS) == new_set
    assert stale_temporaries(s) == []


_HOLDER = """
import sys
from gonio.locks import hold_lock
with hold_lock(sys.argv[1], "test"):
    print("held", flush=True)
    sys.stdin.readline()
"""


def test_a_reduce_into_a_held_session_is_refused_naming_the_pid(session, tmp_path):
    s, old_set, _ = _reduce_sets(session, tmp_path)
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(output_lock(s / "samples.h5"))],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline() == "held\n"
        log = tmp_path / "reduce.log"
        code = _wait(_spawn(["capture", "reduce", str(s), "--quiet", "--no-plot"], log))
    finally:
        holder.communicate("done\n")
    assert code == 1 and f"process {holder.pid}" in " ".join(log.read_text().split())
    assert _snapshot(s, REDUCE_OUTPUTS) == old_set
