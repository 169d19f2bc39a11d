"""Shared fixtures: where the real third-party reference data live."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

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
