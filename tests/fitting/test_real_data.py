"""Real data: the four shared RGL materials (measured BRDFs) fitted with six models.

Independent references: the measured files themselves (read by gonio.brdf.load) and the
gloss of the measured data at 60 deg computed directly from the file.
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.brdf import load
from gonio.fitting import fit
from gonio.fitting.sampling import sample_brdf
from gonio.fitting.select import gloss_units

MATERIALS = ("paper_white", "colodur_napoli_4f", "vch_golden_yellow", "cc_ibiza_sunset")
MODELS = (
    "lambert",
    "oren-nayar",
    "lambert+ggx",
    "lambert+beckmann",
    "lambert+ward",
    "lambert+blinn-phong",
)
# a coarser grid than the CLI's keeps the test fast
GRID = {"theta_i_deg": (0, 20, 40, 60, 75), "n_theta_o": 12, "n_phi_o": 24}


@pytest.fixture(scope="module")
def rgl_samples(rgl_file):
    return {m: (load(rgl_file(m)), sample_brdf(load(rgl_file(m)), **GRID)) for m in MATERIALS}


@pytest.mark.slow
@pytest.mark.parametrize("material", MATERIALS)
def test_rgl_materials_fit_with_every_model(material, rgl_samples):
    brdf, s = rgl_samples[material]
    lam = fit(s, "lambert")
    for name in MODELS:
        for loss in ("cosine_l2", "log"):
            r = fit(s, name, loss=loss)
            assert r.success, f"{material} {name} {loss}: {r.message}"
            for k, v in r.params.items():
                lo, hi = (0.0, np.inf) if k not in ("alpha", "sigma") else (0.0, 2.0)
                assert np.all(np.isfinite(v)) and np.all((v >= lo) & (v <= hi)), (name, k, v)
            if loss == "cosine_l2" and name.startswith("lambert+"):
                # a richer model never fits worse than Lambert (Lambert is nested in it;
                # not so Oren-Nayar, whose albedo bound is 0.99)
                assert r.cost <= lam.cost * (1 + 1e-9), (name, r.cost, lam.cost)
            assert (
                r.diagnostics["max_albedo"] is None or max(r.diagnostics["max_albedo"]) <= 1 + 1e-6
            )


@pytest.mark.slow
@pytest.mark.parametrize(
    ("material", "kind"),
    [
        ("paper_white", "diffuse"),
        ("colodur_napoli_4f", "diffuse"),
        ("vch_golden_yellow", "specular"),
        ("cc_ibiza_sunset", "specular"),
    ],
)
def test_auto_chooses_diffuse_for_paper_and_paint_specular_for_vinyl(material, kind, rgl_samples):
    brdf, s = rgl_samples[material]
    r = fit(s, "auto")
    assert r.success
    assert (r.model in ("lambert", "oren-nayar")) == (kind == "diffuse"), r.diagnostics["selection"]
    # the gloss criterion agrees with the measured file's own 60 deg gloss
    measured_gloss = float(np.mean(gloss_units(brdf)))
    assert (measured_gloss >= 10.0) == (kind == "specular"), measured_gloss
