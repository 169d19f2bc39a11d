"""Exports: JSON round trip, and the Mitsuba 3 material evaluated by Mitsuba equals our model."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from gonio.errors import FitError
from gonio.fitting import fit
from gonio.fitting.export import mitsuba_dict, mitsuba_xml, save_json


def test_json_has_the_documented_fields(tmp_path, make_samples):
    s = make_samples(
        "lambert+ggx",
        {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": 0.2},
        n=120,
        seed=1,
        noise=1e-4,
        read=1e-3,
    )
    r = fit(s, "lambert+ggx")
    p = save_json(r, tmp_path / "fit.json")
    d = json.loads(p.read_text())
    for k in (
        "params",
        "std",
        "covariance",
        "cost",
        "nfev",
        "njev",
        "algorithm",
        "status",
        "message",
        "success",
        "diagnostics",
        "param_labels",
    ):
        assert k in d
    np.testing.assert_allclose(d["params"]["ks"], r.params["ks"], rtol=0, atol=0)
    assert len(d["covariance"]) == len(d["param_labels"]) == 7
    assert "condition_number" in d["diagnostics"] and "at_bounds" in d["diagnostics"]


def test_models_without_mitsuba_counterpart_are_refused(make_samples):
    s = make_samples("oren-nayar", {"albedo": [0.3, 0.5, 0.7], "sigma": 0.3}, n=60)
    with pytest.raises(FitError, match="no Mitsuba 3 counterpart"):
        mitsuba_dict(fit(s, "oren-nayar", loss="l2"))


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize(
    ("name", "truth", "options"),
    [
        ("lambert", {"albedo": [0.2, 0.5, 0.8]}, {}),
        ("lambert+ggx", {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": 0.2}, {}),
        (
            "lambert+beckmann",
            {"albedo": [0.3, 0.2, 0.1], "ks": [0.3, 0.3, 0.2], "alpha": 0.3},
            {"g1": "rational"},
        ),
        ("ggx", {"ks": [0.5, 0.6, 0.7], "alpha": 0.08}, {}),
    ],
)
def test_mitsuba_material_matches_our_model(name, truth, options, tmp_path, make_samples):
    os.environ.setdefault("DRJIT_CACHE_DIR", str(tmp_path / "drjit"))
    from gonio.mitsuba_oracle import load_mitsuba

    mi, _ = load_mitsuba("scalar")
    import drjit as dr

    dr.set_thread_count(1)
    s = make_samples(name, truth, n=150, seed=2, options=options)
    r = fit(s, name, loss="l2", model_options=options)
    xml = mitsuba_xml(r).replace("<bsdf ", '<bsdf version="3.0.0" ', 1)
    bsdfs = [mi.load_dict(mitsuba_dict(r)), mi.load_string(xml)]
    rng = np.random.default_rng(3)
    bound = r.bind()
    worst = 0.0
    for _ in range(60):
        ti, to, po = rng.uniform(0, 1.45), rng.uniform(0, 1.45), rng.uniform(0, 2 * np.pi)
        # Mitsuba computes in float32: feed float32-rounded directions to both
        wi = np.array([np.sin(ti), 0.0, np.cos(ti)], dtype=np.float32).astype(np.float64)
        wo = np.array(
            [np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], dtype=np.float32
        ).astype(np.float64)
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*wi)
        ours = bound.eval(wi[None], wo[None])[0] * wo[2]  # Mitsuba returns f cos(theta_o)
        for b in bsdfs:  # the scene dict and the XML snippet
            v = b.eval(mi.BSDFContext(), si, mi.Vector3f(*wo))
            theirs = np.array([v[0], v[1], v[2]], dtype=np.float64)
            worst = max(worst, float(np.max(np.abs(theirs - ours) / np.maximum(ours, 1e-6))))
    assert worst < 2e-5, worst
