"""Shared fixtures: where the real third-party reference data live."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

# The helper modules beside this file (sim_sessions, crash_harness) are imported by name:
# under --import-mode=importlib pytest puts no test folder on sys.path itself.
if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))

#: The BLAS libraries' thread-count variables (numpy/scipy's OpenBLAS, OpenCV's own
#: OpenBLAS, MKL where installed).  Not OMP_NUM_THREADS: numba's kernels are tested
#: multithreaded and keep their own pool (NUMBA_NUM_THREADS).
BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _pin_blas_under_xdist() -> None:
    """Under ``pytest -n N`` give each worker's BLAS ``cores // N`` threads (at least 1).

    N workers with a BLAS pool of all cores each oversubscribe the machine N times, and
    OpenBLAS's idle threads spin: on CI's 2 cores and 2 workers a calibration solve (small
    dense matrices) took ~1.7x the CPU time with 2 BLAS threads as with 1.  Set here, at
    the first conftest's import, before any test module imports numpy, and inherited by
    the ``gonio`` subprocesses the tests start.  A variable the user set is kept.  The
    values a test computes change by roundoff at most (a sum's order); no test checks a
    thread count of BLAS.
    """
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if workers < 2:
        return
    n = str(max(1, (os.cpu_count() or 1) // workers))
    for var in BLAS_THREAD_VARS:
        os.environ.setdefault(var, n)
    if "numpy" in sys.modules:  # a plugin loaded it first: its pool already started
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=int(os.environ[BLAS_THREAD_VARS[0]]), user_api="blas")


_pin_blas_under_xdist()


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
