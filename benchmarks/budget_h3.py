"""How honest are the reduced samples' error bars? z-scores against the simulator's truth.

Runs ``gonio demo --world realistic`` (camera and rig calibrated first, as in a lab) on
world seeds no test picks, or reads the demo directories given, and compares every
unflagged sample with the closed-form truth at its reported directions:
``z = (f - f_true) / sigma`` with ``sigma`` the noise term alone (``budget["noise"]``,
today's ``brdf_std``) and the full budget (``brdf_std``, plus the shared calibration
scale).  Prints one JSON object: std of z per channel and per theta band
(``max(theta_i, theta_o)``), for both, the figure being the full budget's overall std
(1 is honest), the baseline the noise-only one.

    python benchmarks/budget_h3.py                       # seeds 4242, 4243 (a few minutes)
    python benchmarks/budget_h3.py /tmp/demo-a /tmp/demo-b
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

BANDS_DEG = ((0, 30), (30, 50), (50, 70), (70, 80), (80, 90))
SEEDS = (4242, 4243)
DEFAULT_MATERIAL = "lambert+ggx albedo=0.50,0.40,0.30 ks=0.2 alpha=0.2"  # gonio demo's


def _run_demo(out: Path, seed: int) -> Path:
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "gonio",
            "demo",
            "--out",
            str(out),
            "--world",
            "realistic",
            "--world-seed",
            str(seed),
            "--json",
        ],
        check=True,
        stdout=subprocess.PIPE,
        text=True,
    )
    (out / "demo.json").write_text(res.stdout)
    return out


def _stats(z: np.ndarray) -> dict[str, float]:
    z = z[np.isfinite(z)]
    if z.size < 3:
        return {"n": int(z.size)}
    mad = 1.4826 * float(np.median(np.abs(z - np.median(z))))
    return {
        "n": int(z.size),
        "std": round(float(np.std(z, ddof=1)), 3),
        "robust_std": round(mad, 3),
        "mean": round(float(np.mean(z)), 3),
    }


def z_scores(demo_dir: Path) -> dict[str, np.ndarray]:
    """Per unflagged sample and channel: z with noise only and with the full budget, and
    ``max(theta_i, theta_o)`` in degrees."""
    from gonio.app.demo import parse_material
    from gonio.dataset import load_samples

    spec = DEFAULT_MATERIAL
    for name in ("demo.json", "fit.json"):  # the demo's --json output names its material
        p = demo_dir / name
        if p.exists():
            spec = json.loads(p.read_text()).get("material") or spec
            break
    s = load_samples(demo_dir / "session" / "samples.h5")
    ok = s.valid
    truth = parse_material(spec).truth().eval(s.wi[ok], s.wo[ok])
    f = s.brdf[ok]
    cal = np.asarray(s.attrs.get("calibration_rel_std", np.zeros(3)), float)
    full = np.sqrt(s.brdf_std[ok] ** 2 + (cal * f) ** 2)
    noise = s.budget["noise"][ok] if s.budget else s.brdf_std[ok]
    a = s.angles()
    theta = np.degrees(np.maximum(a["theta_i"], a["theta_o"]))[ok]
    return {"noise": (f - truth) / noise, "full": (f - truth) / full, "theta": theta}


def main(argv: list[str]) -> None:
    if argv:
        dirs = [Path(a) for a in argv]
    else:
        tmp = Path(tempfile.mkdtemp(prefix="budget_h3_"))
        dirs = [_run_demo(tmp / f"seed{s}", s) for s in SEEDS]
    parts = [z_scores(d) for d in dirs]
    z = {k: np.concatenate([p[k] for p in parts]) for k in ("noise", "full", "theta")}
    out: dict[str, object] = {"demos": [str(d) for d in dirs]}
    for which in ("noise", "full"):
        zz = z[which]
        res: dict[str, object] = {"all": _stats(zz)}
        for c, name in enumerate("RGB"):
            res[name] = _stats(zz[:, c])
        for lo, hi in BANDS_DEG:
            sel = (z["theta"] >= lo) & (z["theta"] < hi)
            res[f"theta {lo}-{hi}"] = _stats(zz[sel])
        out[which] = res
    full, noise = out["full"]["all"], out["noise"]["all"]  # type: ignore[index]
    out["figure"] = full.get("std")
    out["baseline"] = noise.get("std")
    if full.get("std") and noise.get("std"):
        out["ratio"] = round(noise["std"] / full["std"], 3)
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1:])
