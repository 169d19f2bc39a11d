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

The texel section (``--section texels`` or ``all``): per-texel fits of an SVBRDF
(:func:`gonio.fitting.svbrdf.fit_block`, lambert+ggx per texel) on a synthetic texel file
of ``--texels N`` x N texels (known maps, ``--poses`` samples each, written once to a
temporary folder), as blocks of texels sized by measurement (~1 s of work,
:func:`gonio.fitting.svbrdf.plan_blocks`), with the same four sides and the same
projection in texel fits per second (a task fits ``block_texels`` texels)::

    texel_fits_per_s(N) = min(N / t_texel_s, block_texels / per_task_overhead_s)

and the bytes a worker reads per block (the hyperslab) beside the item and the result.
Top-level ``ratio``: the materials' all-cores speedup (unchanged), or the texels' with
``--section texels``; each section carries its own ``ratio`` too.

Run: .venv/bin/python benchmarks/scale.py [--section all|materials|texels]
[--sampling coarse|standard] [--copies 2] [--repeats 5] [--texels 12] [--poses 60]
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


def _texel_file(path: Path, n: int, poses: int) -> Path:
    """A synthetic n x n texel file: lambert+ggx maps (ramps) + 2 % + 2e-3 noise."""
    import numpy as np

    from gonio.brdf import get_model
    from gonio.texels import save_texels

    rng = np.random.default_rng(0)
    t = n * n
    yy, xx = np.mgrid[0:n, 0:n] / max(n - 1, 1)
    p = {
        "albedo": np.stack([0.2 + 0.4 * xx, 0.3 + 0.3 * yy, 0.25 + 0 * xx], -1).reshape(t, 1, 3),
        "ks": ((0.1 + 0.2 * yy)[..., None] * np.array([1.0, 0.9, 0.8])).reshape(t, 1, 3),
        "alpha": (0.08 + 0.3 * xx).reshape(t, 1, 1),
    }

    def dirs(k: int) -> np.ndarray:
        z = 0.17 + 0.83 * rng.random(k)
        phi = 2 * np.pi * rng.random(k)
        r = np.sqrt(1 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)

    wi = dirs(t * poses).reshape(t, poses, 3)
    wo = dirs(t * poses).reshape(t, poses, 3)
    f = get_model("lambert+ggx").eval(wi[:, :, None, :], wo[:, :, None, :], p)
    sig = 0.02 * f + 2e-3
    save_texels(
        path, wi=wi, wo=wo, brdf=f + sig * rng.standard_normal(f.shape), brdf_std=sig,
        flags=np.zeros((t, poses), np.uint32), pose=np.arange(poses, dtype=np.int32),
        texels=(n, n), sample_size=(0.05, 0.05),
    )  # fmt: skip
    return path


def _run_blocks(client, blocks) -> dict:
    from gonio.distributed import TaskFailure, map_tasks
    from gonio.fitting.svbrdf import fit_block

    out = map_tasks(client, fit_block, blocks, key_of=lambda b: b.name)
    failed = [k for k, v in out.items() if isinstance(v, TaskFailure)]
    if failed:
        raise SystemExit(f"texel blocks failed: {failed}: {[out[k] for k in failed]}")
    return out


def _texel_section(c1, c2, args, per_task: float) -> dict:
    import tempfile

    import cloudpickle
    import h5py

    from gonio.fitting.svbrdf import (
        SVBRDFOptions,
        TexelBlock,
        _measure_cost,
        plan_blocks,
    )

    with tempfile.TemporaryDirectory(prefix="gonio-scale-") as tmp:
        path = _texel_file(Path(tmp) / "texels.h5", args.texels, args.poses)
        options = SVBRDFOptions(model="lambert+ggx")
        with h5py.File(path, "r") as f:
            chunk = int(f.attrs["chunk_texels"])
            per_texel_bytes = sum(
                f[k].dtype.itemsize * int(f[k][0].size)
                for k in ("wi", "wo", "brdf", "brdf_std", "flags")
            )
        cost = _measure_cost(path, options)
        spans = plan_blocks(args.texels**2, cost, chunk)
        blocks = [TexelBlock(str(path), a, b, options) for a, b in spans]
        n = args.texels**2
        one = compare(
            {
                "gonio": lambda: _run_blocks(c1, blocks),
                "baseline": lambda: _run_blocks(None, blocks),
            },
            repeats=args.repeats,
            threads=1,
        )
        allc = compare(
            {
                "gonio": lambda: _run_blocks(c2, blocks),
                "baseline": lambda: _run_blocks(None, blocks),
            },
            repeats=args.repeats,
            threads=2,
        )
        sample = next(iter(_run_blocks(c2, blocks[:1]).values()))
    block = spans[0][1] - spans[0][0]

    def fps(stats: dict) -> float:
        return n / stats["median"]

    fps_1w = fps(one["gonio"])
    t_texel = 1.0 / fps_1w
    projected = {}
    for workers in (16, 256):
        rate = min(workers / t_texel, block / per_task)
        projected[str(workers)] = {
            "texel_fits_per_s": rate,
            "bound": "workers" if workers / t_texel < block / per_task else "scheduler",
            "shared_fs_read_MB_per_s": rate * per_texel_bytes / 1e6,
            "results_into_client_MB_per_s": rate / block * len(cloudpickle.dumps(sample)) / 1e6,
        }
    sp_one = speedup(one["gonio"], one["baseline"])
    sp_all = speedup(allc["gonio"], allc["baseline"])
    return {
        "case": f"{n} texel fits ({args.texels} x {args.texels} texels, {args.poses} samples "
        f"each, lambert+ggx) in {len(blocks)} blocks of {block}: LocalCluster workers vs "
        "the single-process loop",
        "one_thread": {**one, "speedup": sp_one, "workers": 1},
        "all_cores": {**allc, "speedup": sp_all, "threads": 2, "workers": 2},
        "texel_fits_per_s": {
            "loop_1_thread": fps(one["baseline"]),
            "loop_2_threads": fps(allc["baseline"]),
            "workers_1": fps_1w,
            "workers_2": fps(allc["gonio"]),
        },
        "ratio": sp_all["median"],
        "ratio_worst": sp_all["worst"],
        "target": TARGET,
        "target_met": sp_all["median"] >= TARGET,
        "texel_cost_s": cost,
        "block_texels": block,
        "per_task_s": block * t_texel,
        "overhead_share_of_task": per_task / (block * t_texel),
        "bytes_per_task": {
            "item_sent": len(cloudpickle.dumps(blocks[0])),
            "result_returned": len(cloudpickle.dumps(sample)),
            "input_read_by_worker": block * per_texel_bytes,
        },
        "projection": {
            "formula": "texel_fits_per_s(N) = min(N / t_texel_s, block_texels / "
            "per_task_overhead_s); t_texel_s = 1 / workers_1 texel_fits_per_s",
            "workers": projected,
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--section", default="all", choices=["all", "materials", "texels"])
    ap.add_argument("--sampling", default="coarse", choices=["coarse", "standard"])
    ap.add_argument("--copies", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--texels", type=int, default=12, help="texels per side (N x N)")
    ap.add_argument("--poses", type=int, default=60, help="samples per texel")
    args = ap.parse_args()
    if args.section == "texels":
        from gonio.distributed import open_client

        with open_client(workers=1) as c1, open_client(workers=2) as c2:
            per_task, round_trip = _overhead(c2)
            tex = _texel_section(c1, c2, args, per_task)
        out = {
            "benchmark": "scale",
            "machine": machine(),
            "texels": tex,
            "ratio": tex["ratio"],
            "per_task_overhead_s": per_task,
            "round_trip_s": round_trip,
            "repeats": args.repeats,
        }
        json.dump(out, sys.stdout, indent=2)
        print()
        return

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
            tex = _texel_section(c1, c2, args, per_task) if args.section == "all" else None
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
    if tex is not None:
        out["texels"] = tex
    json.dump(out, sys.stdout, indent=2)
    print()


if __name__ == "__main__":
    main()
