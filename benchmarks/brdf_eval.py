"""Throughput of ``gonio.brdf`` GGX against Mitsuba 3's ``roughconductor`` at equal threads.

The same 10^6 direction pairs go through ``get_model("ggx").eval`` (float64; the default
path, the fused numba kernels of ``gonio.brdf.kernels``) and Mitsuba 3's vectorised
``roughconductor`` (GGX, F = 1, ``llvm_ad_rgb``), timed by
``benchmarks/equal_threads.compare``: interleaved repetitions with every thread pool
pinned, once at one thread each (the top-level ``ratio``) and once at all cores each
(numba's threads against Dr.Jit's pool).  Prints ONE JSON object in issue 19's shape; the
results are compared (``max_rel_diff_vs_mitsuba``, ``max_rel_diff_numba_vs_numpy``), so
all sides are known to compute the same function.  ``baseline_incl_transfer`` (one
thread) is Mitsuba with the numpy -> Dr.Jit -> numpy round trip a numpy caller pays.

    .venv/bin/python benchmarks/brdf_eval.py [--pairs 1000000] [--repeats 7]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gonio.brdf import get_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from equal_threads import all_cores, compare, machine, speedup  # noqa: E402

TARGET = 1.0  # issue 19: every hot path at least level with its peer at equal threads


def _directions(rng: np.random.Generator, n: int) -> np.ndarray:
    ct = rng.uniform(0.0, 1.0, n)
    ph = rng.uniform(0.0, 2 * math.pi, n)
    st = np.sqrt(1.0 - ct * ct)
    return np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=7, help="interleaved repetitions (>= 5)")
    args = ap.parse_args()
    n = args.pairs
    alpha = 0.2
    rng = np.random.default_rng(0)
    wi = _directions(rng, n).astype(np.float32).astype(np.float64)
    wo = _directions(rng, n).astype(np.float32).astype(np.float64)

    model = get_model("ggx")
    params = {"ks": 1.0, "alpha": alpha}
    os.environ.pop("GONIO_NUMBA", None)
    t0 = time.perf_counter()
    ours = model.eval(wi, wo, params)  # warm-up: numba compile or cache load
    t_first = time.perf_counter() - t0
    # The kernels load lazily, only for batches the model hands them whole (see
    # gonio.brdf.microfacet); say whether the figures are theirs.
    fused = "gonio.brdf.kernels" in sys.modules

    os.environ["GONIO_NUMBA"] = "0"  # the numpy reference path, for the agreement
    try:
        ours_np = model.eval(wi, wo, params)
    finally:
        del os.environ["GONIO_NUMBA"]
    both = (ours_np != 0) & np.isfinite(ours_np)
    numba_vs_numpy = np.abs(ours[both] - ours_np[both]) / ours_np[both]

    os.environ.setdefault("DRJIT_CACHE_DIR", tempfile.mkdtemp(prefix="drjit-"))
    from gonio.mitsuba_oracle import load_mitsuba

    mi, variant = load_mitsuba("llvm")
    if not variant.startswith("llvm"):
        sys.exit(f"error: Mitsuba's vectorised variant is unavailable (got {variant})")
    import drjit as dr

    bsdf = mi.load_dict({"type": "roughconductor", "distribution": "ggx", "alpha": alpha})
    ctx = mi.BSDFContext()

    def to_mi(a: np.ndarray):
        return mi.Vector3f(*(mi.Float(np.ascontiguousarray(a[:, k], np.float32)) for k in range(3)))

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = to_mi(wi)
    wo_mi = to_mi(wo)

    def mitsuba_kernel():
        v = bsdf.eval(ctx, si, wo_mi)
        dr.eval(v)
        dr.sync_thread()
        return v

    def mitsuba_from_numpy():
        s = dr.zeros(mi.SurfaceInteraction3f, n)
        s.wi = to_mi(wi)
        v = bsdf.eval(ctx, s, to_mi(wo))
        return np.array(v[0])

    def gonio():
        return model.eval(wi, wo, params)

    ref = np.array(mitsuba_kernel()[0], dtype=np.float64)  # warm-up (JIT compile)
    ok = np.isfinite(ref) & (ref > 0)
    rel = np.abs(ours[ok] * wo[ok, 2] - ref[ok]) / ref[ok]

    one = compare(
        {"gonio": gonio, "baseline": mitsuba_kernel, "baseline_incl_transfer": mitsuba_from_numpy},
        repeats=args.repeats,
        threads=1,
    )
    cores = all_cores()
    every = compare(
        {"gonio": gonio, "baseline": mitsuba_kernel}, repeats=args.repeats, threads=cores
    )
    s1 = speedup(one["gonio"], one["baseline"])
    sa = speedup(every["gonio"], every["baseline"])

    def evals(st: dict) -> int:
        return round(n / st["median"])

    result = {
        "benchmark": "brdf_eval",
        "case": f"GGX (alpha {alpha}, F = 1) on {n} uniform hemisphere pairs: gonio float64 "
        f"numba kernel vs Mitsuba {mi.__version__} roughconductor ({variant}, float32 SIMD)",
        "machine": machine(),
        "one_thread": {
            "gonio": one["gonio"],
            "baseline": one["baseline"],
            "speedup": s1,
            "baseline_incl_transfer": one["baseline_incl_transfer"],
            "speedup_vs_incl_transfer": speedup(one["gonio"], one["baseline_incl_transfer"]),
            "gonio_evals_per_s": evals(one["gonio"]),
            "baseline_evals_per_s": evals(one["baseline"]),
        },
        "all_cores": {
            "gonio": every["gonio"],
            "baseline": every["baseline"],
            "speedup": sa,
            "threads": cores,
            "gonio_evals_per_s": evals(every["gonio"]),
            "baseline_evals_per_s": evals(every["baseline"]),
        },
        "ratio": s1["median"],
        "ratio_worst": s1["worst"],
        "ratio_all_cores": sa["median"],
        "target": TARGET,
        "target_met": s1["median"] >= TARGET,
        "numba_path_used": fused,
        "numba_first_call_s": t_first,
        "max_rel_diff_vs_mitsuba": float(rel.max()),
        "max_rel_diff_numba_vs_numpy": float(numba_vs_numpy.max(initial=0.0)),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
