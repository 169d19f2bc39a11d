"""Evaluations per second of gonio's RGL evaluator vs Mitsuba 3's ``measured`` plugin.

Same file, same random direction pairs, same process.  Mitsuba runs in its vectorised
``llvm_ad_rgb`` variant when libLLVM 19 works (one thread), else ``scalar_rgb`` (a Python
loop over single evaluations); the variant is named in the output.  Prints ONE JSON
object: ``figure`` (gonio evals/s, the default path, the numba kernel of
``gonio.brdf.kernels``, on one thread like Mitsuba), ``baseline`` (Mitsuba evals/s),
``ratio``; for context also gonio on numba's threads and the numpy reference path
(``GONIO_NUMBA=0``).

    python benchmarks/measured_eval.py [--n 200000] [--file paper_white_rgb.bsdf]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def _pairs(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)

    def hemi(m: int) -> np.ndarray:
        z = rng.random(m)
        r = np.sqrt(1 - z * z)
        p = 2 * np.pi * rng.random(m)
        return np.stack([r * np.cos(p), r * np.sin(p), z], axis=-1)

    return hemi(n).astype(np.float32), hemi(n).astype(np.float32)


def _best_of(fn, repeats: int) -> float:
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    data = Path(os.environ.get("GONIO_REFDATA", REPO.parent / "shared" / "data"))
    ap.add_argument("--file", default=str(data / "rgl" / "vch_golden_yellow_rgb.bsdf"))
    ap.add_argument("--n", type=int, default=200_000, help="direction pairs per timing")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    os.environ.setdefault("DRJIT_CACHE_DIR", tempfile.mkdtemp(prefix="drjit"))

    from gonio.brdf import load
    from gonio.mitsuba_oracle import load_mitsuba

    wi, wo = _pairs(args.n)
    wi64, wo64 = wi.astype(np.float64), wo.astype(np.float64)
    brdf = load(args.file)
    t0 = time.perf_counter()
    ours = brdf.eval(wi64, wo64) * wo64[:, 2:3]  # warm-up: numba import + cache load
    t_first = time.perf_counter() - t0
    t_gonio = _best_of(lambda: brdf.eval(wi64, wo64), args.repeats)
    fused = "gonio.brdf.kernels" in sys.modules
    import numba

    n_threads = numba.get_num_threads()
    numba.set_num_threads(1)  # like for like with Mitsuba's one thread
    t_gonio_1 = _best_of(lambda: brdf.eval(wi64, wo64), args.repeats)
    numba.set_num_threads(n_threads)
    os.environ["GONIO_NUMBA"] = "0"  # the numpy reference path, for context
    ours_np = brdf.eval(wi64, wo64) * wo64[:, 2:3]
    t_numpy = _best_of(lambda: brdf.eval(wi64, wo64), args.repeats)
    del os.environ["GONIO_NUMBA"]
    both = np.isfinite(ours_np) & (ours_np != 0)
    numba_vs_numpy = np.abs(ours[both] - ours_np[both]) / ours_np[both]

    mi, variant = load_mitsuba("llvm")
    import drjit as dr

    dr.set_thread_count(1)
    bsdf = mi.load_dict({"type": "measured", "filename": str(args.file)})
    ctx = mi.BSDFContext()
    if variant.startswith("llvm"):
        n_mi = args.n
        si = dr.zeros(mi.SurfaceInteraction3f, n_mi)
        si.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
        wo_mi = mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])

        def run_mi():
            v = bsdf.eval(ctx, si, wo_mi)
            dr.eval(v)
            return np.array(v)

        run_mi()  # JIT compilation is not part of the figure
        t_mi = _best_of(run_mi, args.repeats)
        ref = run_mi().T
    else:
        n_mi = min(args.n, 20_000)
        si = mi.SurfaceInteraction3f()

        def run_mi():
            out = np.empty((n_mi, 3))
            for j in range(n_mi):
                si.wi = mi.Vector3f(*wi[j].tolist())
                out[j] = list(bsdf.eval(ctx, si, mi.Vector3f(*wo[j].tolist())))
            return out

        t_mi = _best_of(run_mi, 1)
        ref = run_mi()
    sel = ref > 1e-3 * ref.max()
    rel = np.abs(ours[:n_mi] - ref)[sel[: len(ref)]] / ref[sel]
    figure = args.n / t_gonio_1
    baseline = n_mi / t_mi
    print(
        json.dumps(
            {
                "benchmark": "measured_eval",
                "file": Path(args.file).name,
                "pairs": args.n,
                "figure": round(figure),
                "figure_unit": "RGL evaluations/s (gonio float64, numba kernel, 1 thread)",
                "baseline": round(baseline),
                "baseline_name": f"Mitsuba {mi.__version__} measured, {variant}, 1 thread",
                "ratio": round(figure / baseline, 3),
                "numba_path_used": fused,
                "gonio_numba_threads": n_threads,
                "gonio_all_threads": round(args.n / t_gonio),
                "ratio_all_threads_vs_mitsuba_1thread": round(args.n / t_gonio / baseline, 3),
                "gonio_numpy": round(args.n / t_numpy),
                "ratio_numpy": round(args.n / t_numpy / baseline, 3),
                "numba_first_call_s": round(t_first, 3),
                "max_rel_diff_numba_vs_numpy": float(numba_vs_numpy.max(initial=0.0)),
                "agreement_median_rel": float(np.median(rel)),
                "load_average_1min": round(os.getloadavg()[0], 2),
            }
        )
    )


if __name__ == "__main__":
    main()
