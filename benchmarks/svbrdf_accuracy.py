"""SVBRDF accuracy: per-texel fits of a simulated sample against its known maps.

A simulated session of a spatially varying lambert+ggx sample (the inline 4 x 4 maps of
``examples/svbrdf_scene.toml``: albedo 0.20-0.70 per channel, ks 0.05-0.45, alpha
0.10-0.45) on the demo's simulated camera (:func:`gonio.app.demo.scene_document`: a 2 mm
disk light, 30 deg field of view, 3 x 3 anti-aliasing), then the user's commands:
``gonio capture run`` (virtual bus), ``gonio capture reduce --texels N``, ``gonio fit
TEXELS.h5 --svbrdf -m lambert+ggx --workers 0``.  ``--world realistic`` first calibrates
the simulated as-built rig and camera (:func:`gonio.app.budget_harness.calibrate_world`,
what ``gonio demo --world realistic`` does) and measures and reduces with the
calibrations.

The plan (why these poses): lambert+ggx has, per texel, albedo and ks per channel and one
alpha.  alpha and ks are fixed by the shape of the specular lobe, so the plan passes
through every texel's lobe -- two mirror configurations (theta_i = theta_o = 20 and 45
deg, the light and camera opposite): across the 5 cm sample the half vector moves by
~3-4 deg, so every texel sees its lobe at a slightly different offset -- and along its
flanks (theta_o 0 and 60 deg: half-vector offsets 7.5-22 deg, where a glossy lobe has
fallen by orders of magnitude and a rough one by a few times); the off-specular poses are
diffuse-dominated and fix albedo.  Two poses leave lambert+ggx underdetermined (S2).

Per texel, parameter and channel: ``z = (fit - truth) / sigma`` (alpha once per texel: one
value for all channels), the fraction of texels with every parameter within 3 sigma and
of all values within 3 sigma, the largest |z|, and the median relative error per map.
Baseline: the pooled fit of the same session (``gonio fit samples.h5``, one material for
the whole sample, what one would get without ``--texels``) against every texel's truth;
``ratio`` = the baseline's median relative error over the per-texel fit's (median over
maps), both one thread.  Timings per stage (capture, reduce, fit, pooled fit).

Usage::

    python benchmarks/svbrdf_accuracy.py [--world perfect|realistic|both] [--texels 4]
        [--size 320x240] [--world-seed 11] [--keep DIR]

Prints one JSON object.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

#: The plan's in-plane grid (deg): mirror configurations 20/20 and 45/45 plus flanks.
GRID = {"theta_i_deg": [20, 45], "theta_o_deg": [0, 20, 45, 60], "phi_o_deg": [180]}


def svbrdf_scene(width: int, height: int) -> dict[str, Any]:
    """The demo's simulated camera scene with the example's lambert+ggx maps."""
    from gonio.app.demo import Material, scene_document

    example = tomllib.loads((REPO / "examples" / "svbrdf_scene.toml").read_text())
    scene = scene_document(Material("svbrdf", model="lambert"), width, height)
    scene["sample"].update(
        width=example["sample"]["width"],
        height=example["sample"]["height"],
        brdf=example["sample"]["brdf"],
        maps=example["sample"]["maps"],
    )
    return scene


def plan_document(size: tuple[int, int], grid: dict[str, list[float]], seed: int) -> dict:
    """A plan of the in-plane ``grid`` with one reference group and darks."""
    return {
        "name": "svbrdf accuracy",
        "seed": seed,
        "settle_s": 0.0,
        "grid": {"kind": "spherical", "phi_i_deg": [0.0], **grid},
        "bracket": {
            "policy": "adaptive",
            "exposure_time_s": 0.002,
            "roi": [0.42, 0.42, 0.58, 0.58],
        },
        "darks": {"count": 1},
        "reference": {"poses": [{"theta_i_deg": 0, "theta_o_deg": 30}]},
        "simulation": {"scene": "scene.toml", "width": size[0], "height": size[1]},
    }


def compare_with_truth(fitted: dict, std: dict, truth: dict) -> dict[str, Any]:
    """z, the 3-sigma fractions, the undetermined texels and the median relative error
    per map.

    ``fitted``, ``std``, ``truth``: {name: (ny, nx, C)}.  alpha is one parameter per
    texel (the same value in every channel), so it counts once.
    """
    per_texel_ok, all_z, rel, zmax, undetermined = [], [], {}, {}, []
    for k, t in truth.items():
        v, s = np.asarray(fitted[k]), np.asarray(std[k])
        # a std of inf (a direction the texel's data do not determine) or 0 (at a bound)
        # would make any error "within 3 sigma": such a value counts as outside
        bad = ~(np.isfinite(s) & (s > 0) & np.isfinite(v))
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(bad, np.inf, (v - t) / s)
        if k == "alpha":
            z, bad = z[..., :1], bad[..., :1]
        all_z.append(z.reshape(-1))
        undetermined.append(np.any(bad, axis=-1))
        per_texel_ok.append(np.all(np.abs(z) < 3, axis=-1))
        rel[k] = float(np.median(np.abs(v / t - 1)))
        zmax[k] = float(np.max(np.abs(z[np.isfinite(z)]), initial=0.0))
    zs = np.concatenate(all_z)
    fin = zs[np.isfinite(zs)]
    return {
        "texels_all_params_within_3_sigma": float(np.mean(np.all(per_texel_ok, axis=0))),
        "values_within_3_sigma": float(np.mean(np.abs(zs) < 3)),
        "texels_undetermined": int(np.sum(np.any(undetermined, axis=0))),
        "z_rms": float(np.sqrt(np.mean(fin**2))),
        "max_abs_z": zmax,
        "median_rel_error": rel,
    }


def _run(*args: str) -> None:
    from gonio.cli import run

    with contextlib.redirect_stdout(sys.stderr):
        rc = run(*args)
    if rc != 0:
        raise SystemExit(f"gonio {' '.join(args)} exited {rc}")


def measure(root: Path, world: str, seed: int, size: tuple[int, int], texels: int) -> dict:
    """One world: (calibrate,) capture, reduce per texel, fit per texel and pooled."""
    import h5py
    import tomli_w

    from gonio.rig.config import virtual_rig_document
    from gonio.simulator.svbrdf import read_truth

    root.mkdir(parents=True, exist_ok=True)
    sec: dict[str, float] = {}
    rig = root / "rig.toml"
    rig.write_text(virtual_rig_document())
    world_args: tuple[str, ...] = ()
    reduce_args: tuple[str, ...] = ()
    calibration = None
    if world != "perfect":
        from gonio.app.budget_harness import calibrate_world

        t = time.perf_counter()
        cal = calibrate_world(root / "calibration", seed, size, world=world)
        sec["calibration"] = time.perf_counter() - t
        rig = cal.rig_file
        world_args = ("--world", world, "--world-seed", str(seed))
        reduce_args = ("--camera-calibration", str(cal.camera_file))
        calibration = {"z_abs_max": cal.to_json()["z_abs_max"]}
    (root / "scene.toml").write_text(tomli_w.dumps(svbrdf_scene(*size)))
    (root / "plan.toml").write_text(tomli_w.dumps(plan_document(size, GRID, seed)))
    s = root / "S"
    t = time.perf_counter()
    _run("capture", "run", str(root / "plan.toml"), "--rig", str(rig), "--camera", "simulated",
         *world_args, "--out", str(s), "--quiet")  # fmt: skip
    sec["capture"] = time.perf_counter() - t
    t = time.perf_counter()
    _run("capture", "reduce", str(s), "--texels", str(texels), *reduce_args, "--quiet", "--no-plot")
    sec["reduce"] = time.perf_counter() - t
    t = time.perf_counter()
    # --no-energy: the example's bright blue texels (albedo 0.65 + ks 0.45) reflect more
    # than they receive at some angles; the energy bound would hold the fit off the truth.
    fit = ("-m", "lambert+ggx", "--no-energy", "--workers", "0")
    _run("fit", str(s / "texels.h5"), "--svbrdf", *fit, "--no-plots", "--out", str(root / "svb"))
    sec["fit_svbrdf"] = time.perf_counter() - t
    t = time.perf_counter()
    _run("fit", str(s / "samples.h5"), "-m", "lambert+ggx", "--no-energy", "--no-plots",
         "--out", str(root / "pooled"))  # fmt: skip
    sec["fit_pooled"] = time.perf_counter() - t

    truth = read_truth(s / "truth" / "svbrdf.h5").params_at(texels, texels)
    with h5py.File(root / "svb" / "svbrdf.h5", "r") as f:
        fitted = {k: f[f"params/{k}"][()] for k in truth}
        std = {k: f[f"std/{k}"][()] for k in truth}
        success = float(np.mean(f["success"][()]))
        n_samples = f["n_samples"][()]
    out = compare_with_truth(fitted, std, truth)
    pooled = _pooled_params(root / "pooled", truth)
    out["baseline_pooled_median_rel_error"] = {
        k: float(np.median(np.abs(pooled[k] / t - 1))) for k, t in truth.items()
    }
    out.update(
        world=world,
        world_seed=seed if world != "perfect" else None,
        calibration=calibration,
        texels=[texels, texels],
        success_fraction=success,
        samples_per_texel={"min": int(np.min(n_samples)), "max": int(np.max(n_samples))},
        seconds={k: round(v, 2) for k, v in sec.items()},
    )
    return out


def _pooled_params(out: Path, truth: dict) -> dict[str, np.ndarray]:
    """The pooled fit's parameters broadcast to every texel, (ny, nx, C)."""
    doc = json.loads((out / "fit.json").read_text())
    params = doc.get("params") or doc["fit"]["params"]
    return {k: np.broadcast_to(np.asarray(params[k], float), t.shape) for k, t in truth.items()}


def main() -> None:
    from equal_threads import machine

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--world", choices=["perfect", "realistic", "both"], default="both")
    ap.add_argument("--world-seed", type=int, default=11)
    ap.add_argument("--texels", type=int, default=4)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--keep", type=Path, default=None, help="Keep the sessions in DIR.")
    args = ap.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    worlds = ["perfect", "realistic"] if args.world == "both" else [args.world]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        runs = {w: measure(root / w, w, args.world_seed, size, args.texels) for w in worlds}
    head = runs[worlds[0]]
    figure = float(np.median(list(head["median_rel_error"].values())))
    baseline = float(np.median(list(head["baseline_pooled_median_rel_error"].values())))
    print(
        json.dumps(
            {
                "benchmark": "svbrdf_accuracy",
                "figure": round(figure, 5),
                "figure_is": f"median over maps of the per-texel fit's median relative "
                f"error ({worlds[0]} world)",
                "baseline": round(baseline, 5),
                "baseline_is": "the same for the pooled fit (one material for the sample)",
                "ratio": round(baseline / figure, 2),
                "threads": 1,
                "target": {"texels_within_3_sigma": 0.95},
                "size": list(size),
                "grid_deg": GRID,
                "worlds": runs,
                "seconds": round(time.perf_counter() - t0, 1),
                "machine": machine(),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
