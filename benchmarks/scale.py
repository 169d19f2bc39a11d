"""Material fits per second on dask workers of this machine against the single-process loop.

The work is the library's task (:func:`gonio.fitting.library.fit_material`: read an RGL
file, sample it on a grid, fit with model selection, render fit.json and material.xml;
no plots) for the 4 shared RGL files, each ``--copies`` times, so both workers have
several tasks of unequal cost.  Four sides, timed with ``equal_threads.compare``
(interleaved repetitions, wall clock, pools pinned):

* ``one_thread``: a ``LocalCluster`` of 1 worker (1 thread) against the loop in this
  process (``map_tasks(None, ...)``) with every pool at 1 thread;
* ``all_cores``: 2 workers (1 thread each) against the same loop with every pool at 2
  threads (equal cores; the loop's numba kernels may use both, its fits are serial).

``ratio`` = 2-worker throughput / loop throughput at equal cores (all_cores' median
speedup); target 1.5: two processes on two cores should come near 2x over a loop whose
fits cannot use the second core, less the scheduler, the transfers and the unequal task
sizes.  The clusters are started before the timing (their start-up is reported apart).

Then the engine's own cost: ``per_task_overhead_s`` (500 no-op tasks through the
2-worker cluster: wall time / tasks, the scheduler-bound rate), ``round_trip_s`` (one
no-op task submitted and gathered, median of 20), and the bytes per task (the item sent,
the result returned, the input file each worker reads).  From these the throughput on 16
and 256 workers on paper::

    fits_per_s(N) = min(N / t_task_s, 1 / per_task_overhead_s)
    t_task_s      = 1 / (1-worker fits per second)     (a fit plus its per-task cost)

with the shared file system bandwidth it needs (``N * input_bytes / t_task_s``) and the
result traffic into the client stated beside it.

Run: .venv/bin/python benchmarks/scale.py [--sampling coarse|standard] [--copies 2]
[--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from equal_threads import compare, machine, speedup

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgl"
TARGET = 1.5


def _tasks(sampling: str, copies: int) -> list:
    from gonio.fitting.library import FitOptions, Material, _Task, find_materials

    found, _ = find_materials(DATA)
    options = FitOptions(plots=False, sampling=sampling)
    return [
        _Task(Material(f"{m.name}#{k}", m.path, m.kind), options)
        for k in range(copies)
        for m in found
    ]


def _run(client, tasks) -> dict:
    from gonio.distributed import TaskFailure, map_tasks
    from gonio.fitting.library import fit_material

    out = map_tasks(client, fit_material, tasks, key_of=lambda t: t.material.name)
    failed = [k for k, v in out.items() if isinstance(v, TaskFailure)]
    if failed:
        raise SystemExit(f"tasks failed: {failed}: {[out[k] for k in failed]}")
    return out


def _overhead(client, n: int = 500) -> tuple[float, float]:
    from gonio.distributed import map_tasks

    map_tasks(client, abs, range(-50, 0), key_of=str)  # warm the comms
    t0 = time.perf_counter()
    map_tasks(client, abs, range(n), key_of=str)
    per_task = (time.perf_counter() - t0) / n
    trips = []
    for i in range(20):
        t0 = time.perf_counter()
        map_tasks(client, abs, [i], key_of=str)
        trips.append(time.perf_counter() - t0)
    return per_task, statistics.median(trips)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sampling", default="coarse", choices=["coarse", "standard"])
    ap.add_argument("--copies", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    import cloudpickle

    from gonio.distributed import open_client

    tasks = _tasks(args.sampling, args.copies)
    n = len(tasks)
    t0 = time.perf_counter()
    with open_client(workers=1) as c1:
        start_1 = time.perf_counter() - t0
        t0 = time.perf_counter()
        with open_client(workers=2) as c2:
            start_2 = time.perf_counter() - t0
            # warm-up inside compare (imports, numba caches in every worker)
            one = compare(
                {"gonio": lambda: _run(c1, tasks), "baseline": lambda: _run(None, tasks)},
                repeats=args.repeats,
                threads=1,
            )
            allc = compare(
                {"gonio": lambda: _run(c2, tasks), "baseline": lambda: _run(None, tasks)},
                repeats=args.repeats,
                threads=2,
            )
            per_task, round_trip = _overhead(c2)
            sample = _run(c2, tasks[:1])
    result = next(iter(sample.values()))
    item_bytes = len(cloudpickle.dumps(tasks[0]))
    result_bytes = len(cloudpickle.dumps(result))
    input_bytes = statistics.mean(t.material.path.stat().st_size for t in tasks)

    def fps(stats: dict) -> float:
        return n / stats["median"]

    fps_1w, fps_2w = fps(one["gonio"]), fps(allc["gonio"])
    t_task = 1.0 / fps_1w
    projected = {}
    for workers in (16, 256):
        rate = min(workers / t_task, 1.0 / per_task)
        projected[str(workers)] = {
            "fits_per_s": rate,
            "bound": "workers" if workers / t_task < 1.0 / per_task else "scheduler",
            "shared_fs_read_MB_per_s": rate * input_bytes / 1e6,
            "results_into_client_MB_per_s": rate * result_bytes / 1e6,
        }
    sp_one = speedup(one["gonio"], one["baseline"])
    sp_all = speedup(allc["gonio"], allc["baseline"])
    out = {
        "benchmark": "scale",
        "case": f"{n} material fits (4 RGL files x {args.copies}, {args.sampling} grid, "
        "model auto, no plots): LocalCluster workers vs the single-process loop",
        "machine": machine(),
        "one_thread": {**one, "speedup": sp_one, "workers": 1},
        "all_cores": {**allc, "speedup": sp_all, "threads": 2, "workers": 2},
        "fits_per_s": {
            "loop_1_thread": fps(one["baseline"]),
            "loop_2_threads": fps(allc["baseline"]),
            "workers_1": fps_1w,
            "workers_2": fps_2w,
        },
        "ratio": sp_all["median"],
        "ratio_worst": sp_all["worst"],
        "target": TARGET,
        "target_met": sp_all["median"] >= TARGET,
        "cluster_start_s": {"workers_1": start_1, "workers_2": start_2},
        "per_task_overhead_s": per_task,
        "round_trip_s": round_trip,
        "t_task_s": t_task,
        "overhead_share_of_task": per_task / t_task,
        "bytes_per_task": {
            "item_sent": item_bytes,
            "result_returned": result_bytes,
            "input_read_by_worker": input_bytes,
        },
        "projection": {
            "formula": "fits_per_s(N) = min(N / t_task_s, 1 / per_task_overhead_s); "
            "t_task_s = 1 / workers_1 fits_per_s; needs a shared file system delivering "
            "fits_per_s(N) * input_read_by_worker bytes/s",
            "workers": projected,
        },
        "repeats": args.repeats,
    }
    json.dump(out, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
