"""The SIGKILL-and-resume harness of the crash tests (grid and adaptive sessions).

Each run or resume is the real CLI in a process forked from the test's (after the heavy
imports, so that a trial costs the session's work rather than Python's start-up); the
parent kills it with SIGKILL at a random moment, checks the session folder, and resumes
until the session completes.  What must hold after every kill is checked by the test's
own ``after_kill`` (on top of :func:`check_consistent`); what must hold at the end, by the
test on the finished session.

Imported by name (``from crash_harness import ...``; ``tests/conftest.py`` puts this
folder on ``sys.path``).
"""

from __future__ import annotations

import hashlib
import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gonio.capture.journal import read_journal

#: Seconds between two looks at a running child (short: the kill time is what is random).
POLL_S = 0.002


def spawn_cli(argv: list[str]) -> int:
    """Fork a child that runs ``gonio`` with ``argv`` (output to /dev/null); its pid.

    The child never returns into pytest: it leaves with the command's exit code (70 if
    the command raised something other than SystemExit).
    """
    pid = os.fork()
    if pid == 0:  # child: run the CLI, never return into pytest
        code = 70
        try:
            fd = os.open(os.devnull, os.O_WRONLY)
            os.dup2(fd, 1)
            os.dup2(fd, 2)
            sys.stdout = open(1, "w", closefd=False)  # noqa: SIM115
            sys.stderr = open(2, "w", closefd=False)  # noqa: SIM115
            from gonio.cli import main

            try:
                main(argv)
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
        finally:
            os._exit(code)
    return pid


def run_to_completion(argv: list[str]) -> float:
    """Run ``argv`` in a forked child to the end; asserts exit 0; wall seconds it took."""
    t0 = time.monotonic()
    pid = spawn_cli(argv)
    assert os.waitpid(pid, 0)[1] == 0, f"{argv} failed"
    return time.monotonic() - t0


def check_consistent(session: Path) -> list[dict]:
    """What must hold after any crash: the journal readable, no shot recorded twice,
    every journaled file present with its hash.  Returns the journal's records ([] when
    the session has no journal yet)."""
    if not (session / "journal.jsonl").exists():
        return []
    recs = read_journal(session / "journal.jsonl")
    shots = [r for r in recs if r["type"] == "shot"]
    keys = [(r["pose"], r["frame"]) for r in shots]
    assert len(keys) == len(set(keys)), f"duplicate shot records in {session}"
    for r in shots:
        data = (session / r["file"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == r["sha256"], r["file"]
    return recs


def kill_until_complete(
    session: Path,
    run_argv: list[str],
    resume_argv: list[str],
    rng: np.random.Generator,
    t_session: float,
    *,
    max_cycles: int,
    after_kill: Callable[[Path], None],
) -> int:
    """Start the session (``run_argv``, then ``resume_argv`` once it has a manifest),
    SIGKILL each child at a uniform random time in [0, 1.1 t_session] s, and call
    ``after_kill(session)`` after each kill, until a child completes (asserted exit 0).

    Returns
    -------
    int
        The kills this session took.
    """
    kills, cycles = 0, 0
    while True:
        argv = resume_argv if (session / "manifest.json").exists() else run_argv
        pid = spawn_cli(argv)
        deadline = time.monotonic() + rng.uniform(0.0, 1.1 * t_session)
        finished = None
        while time.monotonic() < deadline:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                finished = status
                break
            time.sleep(POLL_S)
        if finished is not None:
            assert os.waitstatus_to_exitcode(finished) == 0, f"{argv} failed"
            return kills
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        kills += 1
        after_kill(session)
        cycles += 1
        assert cycles < max_cycles, "session makes no progress under repeated kills"


def kill_sessions(
    folder: Path,
    run_argv: list[str],
    resume_options: list[str],
    rng: np.random.Generator,
    t_session: float,
    *,
    min_kills: int,
    max_cycles: int,
    after_kill: Callable[[Path], None],
    completed: Callable[[Path], None],
) -> tuple[int, int]:
    """Sessions ``folder/S0``, ``S1``, ... each through :func:`kill_until_complete` until
    ``min_kills`` kills in all; ``completed(session)`` checks each finished one.

    ``run_argv`` ends with ``--out`` (the session folder is appended); a resume is
    ``capture resume SESSION *resume_options``.  Returns (kills, sessions).
    """
    kills, n = 0, 0
    while kills < min_kills:
        session = folder / f"S{n}"
        n += 1
        kills += kill_until_complete(
            session,
            [*run_argv, str(session)],
            ["capture", "resume", str(session), *resume_options],
            rng,
            t_session,
            max_cycles=max_cycles,
            after_kill=after_kill,
        )
        completed(session)
    return kills, n


def warm_renderer(*, dark: bool = False) -> None:
    """Import the session's modules and render one small frame (and a dark one), so that
    forked children start warm."""
    import gonio.app.capture_cli  # noqa: F401
    import gonio.app.devices  # noqa: F401
    import gonio.rig.device  # noqa: F401
    import gonio.simulator.virtual_bus  # noqa: F401
    from gonio.rig.config import default_rig_config
    from gonio.rig.kinematics import Kinematics
    from gonio.simulator.rig_camera import SimulatedRigCamera

    cfg = default_rig_config()
    kin = Kinematics(cfg)
    cam = SimulatedRigCamera(None, lambda: kin.poses(cfg.park_rad), 0, width=16, height=12)
    cam.capture(0.01, 100, 8)
    if dark:
        cam.set_light(False)
        cam.capture(0.01, 100, 8)
