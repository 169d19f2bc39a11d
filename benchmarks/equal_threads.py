"""Equal-thread timing for the benchmarks: thread limits, interleaved repetitions, one JSON shape.

Every benchmark compares gonio with what a user would run instead *at equal threads*: one
thread against one thread (the top-level ``ratio``), and all cores against all cores where
the baseline can use them.  This module is the one place that knows how to pin the thread
pools the two sides use (numba for gonio's kernels, the BLAS/OpenMP pools scipy and numpy
call through threadpoolctl, Dr.Jit's pool for Mitsuba) and how to time them fairly:
repetitions are interleaved (A B A B ...), so a burst of load on the shared machine hits
both sides, and the statistics are the median with min and max of at least 5 runs.

Usage (in a benchmark script run as ``python benchmarks/NAME.py``)::

    from equal_threads import compare, threads, summary

    result = compare({"gonio": run_gonio, "scipy": run_scipy}, repeats=5, threads=1)
    # result["gonio"] == {"median": s, "min": s, "max": s, "runs": [...], "threads": 1}

``threads`` is a context manager (``with threads(1): ...``) that pins every pool it can
reach; ``all_cores()`` is the machine's core count (``os.sched_getaffinity``).
"""

from __future__ import annotations

import contextlib
import os
import statistics
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any

MIN_REPEATS = 5


def all_cores() -> int:
    """Cores this process may run on (the affinity mask, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


@contextlib.contextmanager
def threads(n: int) -> Iterator[int]:
    """Pin numba, BLAS/OpenMP (threadpoolctl) and Dr.Jit (when imported) to ``n`` threads.

    Pools a library has not created yet are pinned when it is imported (the environment
    variables), pools it has are limited in place; all are restored on exit.
    """
    n = max(1, int(n))
    saved_env = {v: os.environ.get(v) for v in _ENV_VARS}
    for v in _ENV_VARS:
        os.environ[v] = str(n)
    with contextlib.ExitStack() as stack:
        try:
            from threadpoolctl import threadpool_limits

            stack.enter_context(threadpool_limits(limits=n))
        except ImportError:  # pragma: no cover - threadpoolctl comes with scikit stacks
            pass
        numba_before = _numba_threads(n)
        drjit_before = _drjit_threads(n)
        try:
            yield n
        finally:
            if numba_before is not None:
                _numba_threads(numba_before)
            if drjit_before is not None:
                _drjit_threads(drjit_before)
            for v, old in saved_env.items():
                if old is None:
                    os.environ.pop(v, None)
                else:
                    os.environ[v] = old


_ENV_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _numba_threads(n: int) -> int | None:
    import sys

    if "numba" not in sys.modules:
        return None
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    return before


def _drjit_threads(n: int) -> int | None:
    import sys

    if "drjit" not in sys.modules:
        return None
    import drjit as dr

    before = dr.thread_count()
    dr.set_thread_count(n)
    return before


def stats(runs: list[float]) -> dict[str, Any]:
    """Median, min, max and the runs themselves (seconds)."""
    return {
        "median": statistics.median(runs),
        "min": min(runs),
        "max": max(runs),
        "runs": [round(r, 6) for r in runs],
    }


def compare(
    fns: Mapping[str, Callable[[], Any]],
    *,
    repeats: int = MIN_REPEATS,
    threads: int = 1,
    warmup: bool = True,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, dict[str, Any]]:
    """Time each callable ``repeats`` times, interleaved, all pools pinned to ``threads``.

    Parameters
    ----------
    fns : mapping name -> zero-argument callable
        The sides of the comparison (e.g. ``{"gonio": ..., "scipy": ...}``).
    repeats : int
        Repetitions per side (at least ``MIN_REPEATS``).
    threads : int
        Thread count for every pool during the runs.
    warmup : bool
        Call each side once before timing (JIT compilation, caches, imports).
    clock : callable
        Wall clock by default; ``time.process_time`` would count CPU seconds of all
        threads and so penalise a threaded side.

    Returns
    -------
    dict
        name -> ``stats(runs)`` plus ``"threads"``.
    """
    repeats = max(int(repeats), MIN_REPEATS)
    runs: dict[str, list[float]] = {k: [] for k in fns}
    with _threads_ctx(threads):
        if warmup:
            for fn in fns.values():
                fn()
        for _ in range(repeats):
            for k, fn in fns.items():
                t0 = clock()
                fn()
                runs[k].append(clock() - t0)
    return {k: {**stats(v), "threads": threads} for k, v in runs.items()}


_threads_ctx = threads


def speedup(fast: Mapping[str, Any], slow: Mapping[str, Any]) -> dict[str, float]:
    """Ratio ``slow / fast`` of two ``compare`` entries: the median and the worst case.

    ``worst`` pairs the fast side's slowest run with the slow side's fastest run, the
    most pessimistic reading of the spread.
    """
    return {
        "median": slow["median"] / fast["median"],
        "worst": slow["min"] / fast["max"],
        "best": slow["max"] / fast["min"],
    }


def machine() -> dict[str, Any]:
    """What the figures were measured on (cores, load average at the time)."""
    return {"cores": all_cores(), "load_average_1min": round(os.getloadavg()[0], 2)}
