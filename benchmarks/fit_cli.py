"""``gonio fit FILE.bsdf --model auto``: wall time of the whole command, start-up and plots.

Every run is a fresh process (``gonio fit ... --out NEW_DIR``), timed with the wall clock
from launch to exit.  Baseline, measured in the same run and interleaved: what a user
would write instead with scipy, in a fresh process too: load and sample the file the same
way (``gonio.fitting.sampling``), fit the same four candidates with
``scipy.optimize.least_squares`` (trf, analytic Jacobian, the same cosine-L2 residuals,
from the models' defaults), choose by the same BIC, and write the same fit.json and the
two figures in that process.  Settings:

- ``one_thread``: every pool pinned to one thread, gonio without its plot worker
  (``GONIO_PLOT_WORKER=0``: one process), against the baseline at one thread;
- ``all_cores``: gonio as installed (the plot worker, forked at the start, imports
  matplotlib while the command loads and fits, then draws slices.png and residuals.png in
  two processes, one per core) against the baseline with its BLAS on all cores.

Caches: the runs are *warm* (Python bytecode, matplotlib's font cache; numba is not
imported on this path: 5832 samples are below ``gonio.fitting.kernels.MIN_ROWS``, and the
JSON says whether a run imported it).  ``cold_s`` is one run with empty bytecode,
numba and matplotlib caches (``PYTHONPYCACHEPREFIX``, ``NUMBA_CACHE_DIR``, ``MPLCONFIGDIR``
pointing at new folders): the first command after an installation.
``breakdown`` times the command's stages in one process (sequential, one thread; medians
of ``--repeats``), so it says where the time goes.

Run: .venv/bin/python benchmarks/fit_cli.py [--file vch_golden_yellow ... | all] [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from equal_threads import all_cores, machine, speedup, stats  # noqa: E402

DATA = Path("/work/shared/data/rgl")
TARGET_S = 2.0
CANDIDATES = ("lambert", "oren-nayar", "lambert+ggx", "lambert+beckmann")


def _gonio_argv() -> list[str]:
    exe = Path(sys.executable).with_name("gonio")
    if exe.exists():
        return [str(exe)]
    return [sys.executable, "-c", "from gonio.cli import main; main()"]


def _env(threads: int, extra: dict[str, str] | None = None) -> dict[str, str]:
    env = dict(os.environ)
    for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[v] = str(threads)
    env.update(extra or {})
    return env


def _timed(argv: list[str], env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    res = subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    dt = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"{argv} failed ({res.returncode}): {res.stderr.decode()[-2000:]}")
    return dt


# ---- the baseline, run in its own process: python benchmarks/fit_cli.py --baseline F OUT --
def baseline_run(src: Path, out: Path) -> None:
    """Load, sample, fit the candidates with scipy, choose by BIC, write fit.json + plots."""
    import numpy as np
    from scipy.optimize import least_squares

    from gonio.brdf import get_model, load
    from gonio.fitting.losses import get_loss
    from gonio.fitting.objective import prepare_problem
    from gonio.fitting.plots import plot_residual_map, plot_slices
    from gonio.fitting.result import FitResult
    from gonio.fitting.sampling import sample_brdf

    samples = sample_brdf(load(src), source=str(src))
    m_eff = samples.attrs["effective_samples"]
    rows = []
    for name in CANDIDATES:
        model = get_model(name)
        prob = prepare_problem(model, samples, get_loss("cosine_l2"))
        d = model.defaults
        th0 = np.array([d[n] for n in prob.shape_names])
        a0 = np.array([[d[n]] * prob.n_channels for n in prob.linear_names])
        lo, hi = prob.x_bounds()
        res = least_squares(
            lambda x, p=prob: p.residuals(x).ravel(),
            np.clip(prob.pack(th0, a0), lo, hi),
            jac=lambda x, p=prob: p.dense_jacobian(x)[1],
            bounds=(lo, hi),
            method="trf",
        )
        m = res.fun.size
        bic = m_eff / m * m * np.log(max(2 * res.cost / m, 1e-300)) + prob.n_params * np.log(m_eff)
        rows.append((float(bic), name, prob, res))
    bic, name, prob, res = min(rows, key=lambda t: t[0])
    theta, a = prob.unpack(res.x)
    C = prob.n_channels
    params = {n: np.full(C, float(theta[s])) for s, n in enumerate(prob.shape_names)}
    params.update({n: a[j].copy() for j, n in enumerate(prob.linear_names)})
    params = {n: params[n] for n in prob.model.param_names}
    full_r = np.full((prob.used.size, C), np.nan)
    full_r[prob.used] = res.fun.reshape(-1, C)
    r = FitResult(
        model=name, model_options={}, channels=prob.channels, params=params,
        std={n: np.zeros(C) for n in params}, covariance=np.zeros((0, 0)),
        param_labels=prob.labels, shape_params=prob.shape_names,
        linear_params=prob.linear_names, loss="cosine_l2", robust=None,
        cost=float(res.cost), residuals=full_r, used=prob.used, n_samples=int(prob.used.sum()),
        n_params=prob.n_params, nfev=int(res.nfev), njev=int(res.njev or 0),
        algorithm=["scipy trf"], status=int(res.status), message=str(res.message),
        success=bool(res.success),
    )  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit.json").write_text(
        json.dumps(
            {"model": name, "bic": bic, "params": {k: v.tolist() for k, v in params.items()}}
        )
    )
    plot_slices(r, samples, out / "slices.png")
    plot_residual_map(r, samples, out / "residuals.png")


# ---- the stages of the command, in one process ---------------------------------------
_STAGES = r"""
import json, sys, time
t = [time.perf_counter()]
def lap(): t.append(time.perf_counter())
from pathlib import Path
import gonio.cli, gonio.fitting.cli, rich.console, rich.progress, rich.table; lap()
from gonio.brdf import load
from gonio.fitting.sampling import sample_brdf
from gonio.fitting import fit; lap()
src = Path(sys.argv[1]); out = Path(sys.argv[2]); out.mkdir(parents=True, exist_ok=True)
s = sample_brdf(load(src), source=str(src)); lap()
r = fit(s, "auto"); lap()
from gonio.fitting.export import save_json, save_mitsuba_xml
from gonio.errors import FitError
save_json(r, out / "fit.json")
try: save_mitsuba_xml(r, out / "material.xml")
except FitError: pass  # as the command: no Mitsuba export for this model
lap()
from gonio.fitting import plots
plots.load_matplotlib(); lap()
plots.plot_slices(r, s, out / "slices.png"); lap()
plots.plot_residual_map(r, s, out / "residuals.png"); lap()
names = ["import gonio.cli, click, rich (numpy, gonio.fitting, nlopt)",
         "import gonio.brdf, gonio.fitting.sampling", "load + sample",
         "fit (4 candidates + selection)", "fit.json + material.xml", "import matplotlib",
         "slices.png", "residuals.png"]
print(json.dumps({"stages": dict(zip(names, [b - a for a, b in zip(t, t[1:])])),
                  "numba_imported": "numba" in sys.modules, "model": r.model}))
"""


def breakdown(src: Path, repeats: int) -> dict:
    """Median seconds per stage (fresh process each, one thread, no plot worker), plus the
    interpreter's own start-up (``python -c pass``)."""
    env = _env(1)
    runs, start = [], []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as d:
            res = subprocess.run(
                [sys.executable, "-c", _STAGES, str(src), d], env=env, capture_output=True,
                check=True,
            )  # fmt: skip
            runs.append(json.loads(res.stdout))
        start.append(_timed([sys.executable, "-c", "pass"], env))
    stages = {k: statistics.median(run["stages"][k] for run in runs) for k in runs[0]["stages"]}
    return {
        "python start-up (python -c pass)": statistics.median(start),
        **stages,
        "numba_imported": any(r["numba_imported"] for r in runs),
        "note": "sequential in one process; the command overlaps 'import matplotlib' with "
        "the load and the fit, and draws 'slices.png' and 'residuals.png' side by side "
        "(plot worker and its child) on two cores",
    }


def bench_file(src: Path, repeats: int, cold: bool) -> dict:
    """The figures of one RGL file (see the module docstring)."""
    tmp = Path(tempfile.mkdtemp(prefix="fit_cli_"))
    counter = iter(range(10**6))

    def gonio_run(threads: int, worker: bool) -> float:
        extra = {} if worker else {"GONIO_PLOT_WORKER": "0"}
        out = tmp / f"g{next(counter)}"
        argv = [*_gonio_argv(), "fit", str(src), "--model", "auto", "--out", str(out)]
        return _timed(argv, _env(threads, extra))

    def baseline(threads: int) -> float:
        out = tmp / f"b{next(counter)}"
        return _timed([sys.executable, __file__, "--baseline", str(src), str(out)], _env(threads))

    result = {
        "benchmark": "fit_cli",
        "case": f"gonio fit {src.name} --model auto --out DIR (plots on), fresh process per run",
        "machine": machine(),
        "gonio": "the command as installed; one_thread: GONIO_PLOT_WORKER=0, 1 thread",
        "baseline": "scipy least_squares on the same 4 candidates + same BIC + same plots, "
        "fresh process (benchmarks/fit_cli.py --baseline)",
        "time_unit": "wall seconds, launch to exit",
        "caches": "warm (bytecode, matplotlib font cache); numba not on this path",
        "load_before": os.getloadavg(),
    }
    cores = all_cores()
    for key, n, worker in (("one_thread", 1, False), ("all_cores", cores, True)):
        # warm-up (bytecode, page cache), then interleaved repetitions
        gonio_run(n, worker)
        baseline(n)
        g, b = [], []
        for _ in range(repeats):
            g.append(gonio_run(n, worker))
            b.append(baseline(n))
        gs, bs = {**stats(g), "threads": n}, {**stats(b), "threads": n}
        result[key] = {"gonio": gs, "baseline": bs, "speedup": speedup(gs, bs), "threads": n}
    if cold:
        with tempfile.TemporaryDirectory() as cold_dir:
            extra = {
                "PYTHONPYCACHEPREFIX": str(Path(cold_dir) / "pyc"),
                "NUMBA_CACHE_DIR": str(Path(cold_dir) / "numba"),
                "MPLCONFIGDIR": str(Path(cold_dir) / "mpl"),
            }
            out = tmp / "cold"
            argv = [*_gonio_argv(), "fit", str(src), "--model", "auto", "--out", str(out)]
            result["cold_s"] = _timed(argv, _env(cores, extra))
    result["breakdown_s"] = breakdown(src, 3)
    result["load_after"] = os.getloadavg()
    default = result["all_cores"]["gonio"]
    sp = result["one_thread"]["speedup"]
    result.update(
        ratio=sp["median"],
        ratio_worst=sp["worst"],
        wall_median_s=default["median"],
        wall_max_s=default["max"],
        target=TARGET_S,
        target_unit="seconds of wall time of the default command (all_cores.gonio.median)",
        target_met=bool(default["median"] <= TARGET_S),
    )
    shutil.rmtree(tmp, ignore_errors=True)
    return result


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "--file",
        nargs="+",
        default=["vch_golden_yellow"],
        help="RGL material names (NAME for DATA/NAME_rgb.bsdf) or 'all'",
    )
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--baseline", nargs=2, metavar=("SRC", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--no-cold", action="store_true")
    args = ap.parse_args()
    if args.baseline:
        baseline_run(Path(args.baseline[0]), Path(args.baseline[1]))
        return
    names = (
        sorted(p.name.removesuffix("_rgb.bsdf") for p in DATA.glob("*_rgb.bsdf"))
        if args.file == ["all"]
        else args.file
    )
    repeats = max(5, args.repeats)
    per_file = {n: bench_file(DATA / f"{n}_rgb.bsdf", repeats, not args.no_cold) for n in names}
    if len(per_file) == 1:
        print(json.dumps(next(iter(per_file.values()))))
        return
    # several files: the top level is the slowest file's (its default command's median)
    slowest = max(per_file, key=lambda n: per_file[n]["wall_median_s"])
    top = dict(per_file[slowest])
    top.update(
        case=f"gonio fit FILE --model auto over {len(per_file)} RGL files; top level: the "
        f"slowest ({slowest})",
        slowest_file=slowest,
        wall_median_s_by_file={n: r["wall_median_s"] for n, r in per_file.items()},
        ratio_by_file={n: r["ratio"] for n, r in per_file.items()},
        target_met=all(r["target_met"] for r in per_file.values()),
        files=per_file,
    )
    print(json.dumps(top))


if __name__ == "__main__":
    main()
