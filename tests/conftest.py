"""Shared fixtures: where the real third-party reference data live."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def refdata_dir() -> Path:
    """``$GONIO_REFDATA`` or ``../shared/data`` next to the repository."""
    return Path(os.environ.get("GONIO_REFDATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def refdata() -> Path:
    """The shared reference data folder; skips the test (with the reason) when absent."""
    d = refdata_dir()
    if not d.is_dir():
        pytest.skip(f"reference data not found at {d} (set GONIO_REFDATA)")
    return d


@pytest.fixture(scope="session")
def rgl_file(refdata):
    """Factory: path of a shared RGL .bsdf file by material name."""

    def get(name: str) -> Path:
        p = refdata / "rgl" / f"{name}_rgb.bsdf"
        if not p.is_file():
            pytest.skip(f"RGL file {p} not found")
        return p

    return get


def _free_dask_cluster(tmp: Path):
    """A real ``dask scheduler`` and two ``dask worker`` processes on localhost (random
    free ports, found through the scheduler file)."""
    sched_file = tmp / "scheduler.json"
    env = {**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    dask = [sys.executable, "-m", "dask"]
    procs = [
        subprocess.Popen(
            [*dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
             "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(sched_file),
             "--idle-timeout", "900"],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
    ]  # fmt: skip
    for _ in range(2):
        procs.append(
            subprocess.Popen(
                [*dask, "worker", "--scheduler-file", str(sched_file), "--host", "127.0.0.1",
                 "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                 "--death-timeout", "60", "--local-directory", str(tmp)],
                env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            )
        )  # fmt: skip
    return sched_file, procs


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    """(address, client) of a real cluster for the module (a ``dask scheduler`` and two
    ``dask worker`` processes on localhost); torn down at the end.  Shared by the
    library and the per-texel fit tests."""
    from distributed import Client

    tmp = tmp_path_factory.mktemp("dask")
    sched_file, procs = _free_dask_cluster(tmp)
    try:
        client = Client(scheduler_file=str(sched_file), timeout=60, set_as_default=False)
        client.wait_for_workers(2, timeout=120)
        yield client.scheduler.address, client
        client.close()
    finally:
        for p in reversed(procs):  # workers first, then the scheduler
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
