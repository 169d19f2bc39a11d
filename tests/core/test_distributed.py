"""gonio.distributed: map_tasks' results and failures, retries, the local cluster's
processes, Ctrl-C, an unreachable scheduler, and the engine helpers the fitting commands
share (``check_engine``, ``task_engine``, ``run_tasks``)."""

from __future__ import annotations

import os
import pickle
import socket
import time

import dask
import psutil
import pytest

from gonio.distributed import (
    SchedulerUnreachable,
    TaskError,
    TaskFailure,
    check_engine,
    map_tasks,
    open_client,
    run_tasks,
    task_engine,
)
from gonio.errors import FileFormatError, GonioError


def _square_or_fail(x: int) -> int:
    if x == 3:
        raise FileFormatError("/data/three.bsdf", "truncated header")
    if x == 4:
        raise ValueError("four is not welcome")
    return x * x


def _fails_once(path: str) -> str:
    """Fails on the first attempt (leaves a marker), succeeds on the next."""
    if not os.path.exists(path):
        open(path, "w").close()
        raise OSError("first attempt fails")
    return "second attempt"


@pytest.fixture(scope="module")
def inproc_client():
    """A dask client on an in-process cluster (threads): cheap, the same scheduler."""
    from distributed import Client

    with Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as c:
        yield c


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("use_dask", [True, False], ids=["dask", "this-process"])
def test_failures_named_others_kept(use_dask, inproc_client):
    client = inproc_client if use_dask else None
    seen = []
    out = map_tasks(
        client,
        _square_or_fail,
        range(6),
        key_of=lambda x: f"m{x}",
        retries=0,
        progress=lambda key, outcome, done, total: seen.append((key, done, total)),
    )
    assert list(out) == [f"m{i}" for i in range(6)]  # the order of the items
    assert {k: out[k] for k in ("m0", "m1", "m2", "m5")} == {"m0": 0, "m1": 1, "m2": 4, "m5": 25}
    bad = out["m3"]
    assert isinstance(bad, TaskFailure) and bad.key == "m3"
    assert bad.kind == "FileFormatError"
    assert bad.error == "/data/three.bsdf: truncated header"  # the file named, as raised
    assert out["m4"] == TaskFailure("m4", "ValueError: four is not welcome", "ValueError")
    assert sorted(k for k, _, _ in seen) == sorted(out)
    assert [d for _, d, _ in seen] == [1, 2, 3, 4, 5, 6] and {t for _, _, t in seen} == {6}


@pytest.mark.parametrize("use_dask", [True, False], ids=["dask", "this-process"])
def test_retries(use_dask, inproc_client, tmp_path):
    client = inproc_client if use_dask else None
    once = map_tasks(client, _fails_once, [str(tmp_path / "a")], key_of=str, retries=1)
    assert once == {str(tmp_path / "a"): "second attempt"}
    none = map_tasks(client, _fails_once, [str(tmp_path / "b")], key_of=str, retries=0)
    assert isinstance(none[str(tmp_path / "b")], TaskFailure)
    assert none[str(tmp_path / "b")].error == "OSError: first attempt fails"


def test_distinct_keys_required():
    with pytest.raises(GonioError, match="repeated: a"):
        map_tasks(None, str, ["a", "a", "b"], key_of=str)


def test_task_error_survives_pickling():
    e = pickle.loads(pickle.dumps(TaskError("FileFormatError", "/x.bsdf: bad", True)))
    assert (e.kind, e.message, e.deliberate, str(e)) == (
        "FileFormatError",
        "/x.bsdf: bad",
        True,
        "/x.bsdf: bad",
    )
    assert str(TaskError("ValueError", "no")) == "ValueError: no"


def test_unreachable_scheduler_names_address():
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    with pytest.raises(SchedulerUnreachable) as info:
        with open_client(address, timeout_s=1.0):
            pytest.fail("entered the block without a scheduler")
    assert info.value.address == address
    assert address in str(info.value)


@pytest.mark.parametrize("bad", ["tcp://head", "http://head:8786", "head:port"])
def test_bad_address(bad):
    with pytest.raises(SchedulerUnreachable, match="expected tcp://HOST:PORT"):
        with open_client(bad):
            pass


def test_local_cluster_processes_and_ctrl_c():
    """Workers are separate processes with pinned thread pools; Ctrl-C (here raised by
    the progress callback after the first result) cancels the rest, and leaving the
    block leaves no worker process."""
    with pytest.raises(KeyboardInterrupt):
        with open_client(workers=2) as client:
            pids = client.run(os.getpid)
            env = client.run(os.getenv, "NUMBA_NUM_THREADS")
            profiling = client.run(dask.config.get, "distributed.worker.profile.enabled")
            procs = [psutil.Process(p) for p in pids.values()]

            def interrupt(key, outcome, done, total):
                raise KeyboardInterrupt

            # tasks of 1-2 s each (the work), 6 of them on 2 workers
            map_tasks(client, time.sleep, [1.0, 1.1, 1.2, 1.3, 1.4, 1.5], key_of=str,
                      progress=interrupt)  # fmt: skip
    assert len(pids) == 2 and os.getpid() not in pids.values()
    assert set(env.values()) == {"1"}
    assert set(profiling.values()) == {False}  # no dashboard: no profiler thread
    alive = [p.pid for p in procs if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert alive == []


def test_local_cluster_needs_a_worker():
    with pytest.raises(GonioError, match="at least 1 worker"):
        with open_client(workers=0):
            pass


@pytest.mark.parametrize(
    ("scheduler", "workers", "match"),
    [("tcp://127.0.0.1:8786", 2, "sets the size of the local cluster"), (None, -1, "got -1")],
)
def test_engine_choice_refused(scheduler, workers, match):
    with pytest.raises(GonioError, match=match):
        check_engine(scheduler, workers)


def test_engine_choices_accepted():
    for scheduler, workers in ((None, None), (None, 0), (None, 2), ("tcp://h:1", None)):
        check_engine(scheduler, workers)  # nothing raised, nothing opened


def test_task_engine_without_dask_and_its_failures_reported():
    """``workers=0``: no client (``on_client`` not called), the tasks run here; each
    outcome reaches ``arrived`` (failures as TaskFailure, after the one retry)."""
    called = []
    seen = {}
    with task_engine(None, 0, on_client=called.append) as (client, where):
        assert (client, where) == (None, "this process")
        out = run_tasks(
            client,
            _square_or_fail,
            range(5),
            key_of=lambda x: f"m{x}",
            description="squares",
            arrived=seen.__setitem__,
        )
    assert called == []
    assert seen == out and list(out) == [f"m{i}" for i in range(5)]
    assert [out[f"m{i}"] for i in (0, 1, 2)] == [0, 1, 4]
    assert out["m3"].error == "/data/three.bsdf: truncated header"


def test_task_engine_names_the_local_cluster(inproc_client, monkeypatch):
    """A local cluster is described by its worker count; ``on_client`` sees the client."""
    from contextlib import contextmanager

    import gonio.distributed as gd

    @contextmanager
    def fake_open_client(scheduler=None, *, workers=None, timeout_s=None):
        assert (scheduler, workers) == (None, 3)
        yield inproc_client

    monkeypatch.setattr(gd, "open_client", fake_open_client)
    called = []
    with task_engine(None, 3, on_client=called.append) as (client, where):
        assert client is inproc_client and where == "a local cluster of 1"
    assert called == [inproc_client]
