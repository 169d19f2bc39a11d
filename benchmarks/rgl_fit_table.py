"""Fit the four shared RGL materials with nine models; print the cost table as one JSON object.

For every material and model: the cosine-weighted L2 cost (fit with ``cosine_l2``) and the
log-loss cost (fit with ``log``), both ``0.5 * sum(r^2)`` over the samples of the CLI's
default direction grid (9 incidence angles x 18 x 36 outgoing directions), plus the RMS
residual, and what ``model="auto"`` chooses, with the default candidates and with the
Fresnel-weighted ones added (``FRESNEL_CANDIDATES``), and the wall time of both.  The
models include the microfacet lobes weighted by Schlick's Fresnel term (``f0``) and by the
exact dielectric one (``eta``), written as model specs ``lambert+ggx[fresnel=schlick]``.
The baseline of each row is Lambert; of the extended ``auto``, the default one.

Run: .venv/bin/python benchmarks/rgl_fit_table.py [--refdata ../shared/data]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from gonio.brdf import load
from gonio.fitting import fit
from gonio.fitting.sampling import sample_brdf
from gonio.fitting.select import (
    DEFAULT_CANDIDATES,
    FRESNEL_CANDIDATES,
    format_model_spec,
    gloss_units,
)

MATERIALS = ("paper_white", "colodur_napoli_4f", "vch_golden_yellow", "cc_ibiza_sunset")
MODELS = (
    "lambert",
    "oren-nayar",
    "lambert+ggx",
    "lambert+beckmann",
    "lambert+ward",
    "lambert+blinn-phong",
    "lambert+ggx[fresnel=schlick]",
    "lambert+ggx[fresnel=dielectric]",
    "lambert+beckmann[fresnel=schlick]",
)


def main() -> None:
    ap = argparse.ArgumentParser()
    default = os.environ.get(
        "GONIO_REFDATA", str(Path(__file__).resolve().parents[2] / "shared/data")
    )
    ap.add_argument("--refdata", default=default)
    args = ap.parse_args()
    table: dict = {}
    t0 = time.process_time()
    for mat in MATERIALS:
        b = load(Path(args.refdata) / "rgl" / f"{mat}_rgb.bsdf")
        s = sample_brdf(b)
        rows = {}
        for name in MODELS:
            rc = fit(s, name, loss="cosine_l2")
            rl = fit(s, name, loss="log")
            rows[name] = {
                "cosine_l2": rc.cost,
                "log": rl.cost,
                "rms_cosine_l2": rc.diagnostics["rms_residual"],
                "rms_log": rl.diagnostics["rms_residual"],
                "params_cosine_l2": {k: np.round(v, 5).tolist() for k, v in rc.params.items()},
                "success": bool(rc.success and rl.success),
            }
        t = time.perf_counter()
        auto = fit(s, "auto")
        t_auto = time.perf_counter() - t
        t = time.perf_counter()
        auto_f = fit(s, "auto", candidates=DEFAULT_CANDIDATES + FRESNEL_CANDIDATES)
        t_auto_f = time.perf_counter() - t
        table[mat] = {
            "n_samples": int(len(s.wi)),
            "gloss_60_measured_GU": np.round(gloss_units(b), 2).tolist(),
            "auto": auto.model,
            "auto_note": auto.diagnostics.get("selection_note", ""),
            "auto_seconds": round(t_auto, 2),
            "auto_with_fresnel": format_model_spec(auto_f.model, auto_f.model_options),
            "auto_with_fresnel_note": auto_f.diagnostics.get("selection_note", ""),
            "auto_with_fresnel_seconds": round(t_auto_f, 2),
            "auto_with_fresnel_time_ratio": round(t_auto_f / t_auto, 2),
            "models": rows,
        }
    print(
        json.dumps(
            {
                "benchmark": "rgl_fit_table",
                "figure": "cost per material and model (cosine_l2 and log losses)",
                "baseline": "lambert row",
                "cpu_seconds": time.process_time() - t0,
                "table": table,
            }
        )
    )


if __name__ == "__main__":
    main()
