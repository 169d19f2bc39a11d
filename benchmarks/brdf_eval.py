"""Throughput of ``gonio.brdf`` GGX against Mitsuba 3's ``roughconductor``.

Prints one JSON object: evaluations per second of ``get_model("ggx").eval`` on 10^6
direction pairs (float64; the figure is the default path, the fused numba kernels of
``gonio.brdf.kernels``; the numpy reference path, forced with ``GONIO_NUMBA=0``, is given
for context) and, in the same run, of Mitsuba 3's vectorised ``roughconductor`` (GGX,
F = 1) in ``llvm_ad_rgb`` when libLLVM 19 works (else ``scalar_rgb``, named in the
output), and the ratios.  Best of several repeats, after a warm-up call (the numba compile,
or the load of its on-disk cache, is reported separately as ``numba_first_call_s``).
The results are compared, so all sides are known to compute the same function.

    .venv/bin/python benchmarks/brdf_eval.py [--pairs 1000000] [--repeats 10]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time

import numpy as np

from gonio.brdf import get_model


def _directions(rng: np.random.Generator, n: int) -> np.ndarray:
    ct = rng.uniform(0.0, 1.0, n)
    ph = rng.uniform(0.0, 2 * math.pi, n)
    st = np.sqrt(1.0 - ct * ct)
    return np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=-1)


def _best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=10)
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
    t_ours = _best(lambda: model.eval(wi, wo, params), args.repeats)
    # The kernels load lazily, only for batches the model hands them whole (see
    # gonio.brdf.microfacet); say whether the figure above is theirs.
    fused = "gonio.brdf.kernels" in sys.modules
    import numba

    # One thread each, like for like: on a shared machine (CI, 2 busy cores) a thread
    # that is not scheduled stalls every multi-threaded launch, numba's as Mitsuba's.
    n_threads = numba.get_num_threads()
    numba.set_num_threads(1)
    t_ours_1 = _best(lambda: model.eval(wi, wo, params), args.repeats)
    numba.set_num_threads(n_threads)

    os.environ["GONIO_NUMBA"] = "0"  # the numpy reference path, for context
    ours_np = model.eval(wi, wo, params)
    t_np = _best(lambda: model.eval(wi, wo, params), args.repeats)
    del os.environ["GONIO_NUMBA"]
    both = (ours_np != 0) & np.isfinite(ours_np)
    numba_vs_numpy = np.abs(ours[both] - ours_np[both]) / ours_np[both]

    os.environ.setdefault("DRJIT_CACHE_DIR", tempfile.mkdtemp(prefix="drjit-"))
    from gonio.mitsuba_oracle import load_mitsuba

    mi, variant = load_mitsuba("llvm")
    import drjit as dr

    bsdf = mi.load_dict({"type": "roughconductor", "distribution": "ggx", "alpha": alpha})
    ctx = mi.BSDFContext()
    result: dict[str, object] = {"benchmark": "brdf_eval", "pairs": n, "mitsuba_variant": variant}
    if variant.startswith("llvm"):

        def to_mi(a: np.ndarray):
            return mi.Vector3f(
                *(mi.Float(np.ascontiguousarray(a[:, k], np.float32)) for k in range(3))
            )

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

        ref = np.array(mitsuba_kernel()[0], dtype=np.float64)  # warm-up (JIT compile)
        t_mi = _best(mitsuba_kernel, args.repeats)
        t_mi_np = _best(mitsuba_from_numpy, args.repeats)
        threads = dr.thread_count()
        dr.set_thread_count(1)
        mitsuba_kernel()
        t_mi_1 = _best(mitsuba_kernel, args.repeats)
        dr.set_thread_count(threads)
        result["mitsuba_threads"] = threads
    else:
        # scalar_rgb: one Python call per pair; time a subset and extrapolate.
        m = min(n, 20_000)

        def mitsuba_scalar():
            out = np.empty(m)
            for i in range(m):
                s = mi.SurfaceInteraction3f()
                s.wi = mi.Vector3f(*wi[i])
                out[i] = bsdf.eval(ctx, s, mi.Vector3f(*wo[i]))[0]
            return out

        ref = np.full(n, np.nan)
        ref[:m] = mitsuba_scalar()
        t_mi = t_mi_np = t_mi_1 = _best(mitsuba_scalar, 1) * n / m
        result["mitsuba_threads"] = 1
    ok = np.isfinite(ref) & (ref > 0)
    rel = np.abs(ours[ok] * wo[ok, 2] - ref[ok]) / ref[ok]
    result.update(
        {
            "figure": "gonio_ggx_evals_per_s",
            "gonio_ggx_evals_per_s": n / t_ours,
            "baseline": "mitsuba_roughconductor_evals_per_s",
            "mitsuba_roughconductor_evals_per_s": n / t_mi,
            "ratio": t_mi / t_ours,
            "gonio_ggx_numpy_evals_per_s": n / t_np,
            "ratio_numpy": t_mi / t_np,
            "numba_speedup_over_numpy": t_np / t_ours,
            "numba_path_used": fused,
            "numba_threads": n_threads,
            "numba_first_call_s": t_first,
            "gonio_ggx_1thread_evals_per_s": n / t_ours_1,
            "mitsuba_1thread_evals_per_s": n / t_mi_1,
            "ratio_1thread_vs_1thread": t_mi_1 / t_ours_1,
            "mitsuba_incl_numpy_transfer_evals_per_s": n / t_mi_np,
            "ratio_vs_incl_transfer": t_mi_np / t_ours,
            "max_rel_diff_vs_mitsuba": float(rel.max()),
            "max_rel_diff_numba_vs_numpy": float(numba_vs_numpy.max(initial=0.0)),
            "notes": "gonio: float64, numba fused kernel (numba_threads threads; numpy "
            "path: 1 thread, chunked); mitsuba: float32 JIT SIMD, mitsuba_threads threads. "
            "best of repeats; 'incl_transfer' = numpy -> drjit -> numpy round trip",
        }
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
