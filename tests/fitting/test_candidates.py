"""Candidate fits and their weights (``gonio.fitting.candidates``), as the adaptive
advisor and ``benchmarks/adaptive.py`` use them.

References: the generating model's parameters and values (closed forms evaluated by
``gonio.brdf``), the select module's matte rule preconditions checked here, and the BIC's
parameter count (the weight ratio of two fits of equal cost is ``m^(-dp/2)``).
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.dataset import BRDFSamples
from gonio.errors import FitError
from gonio.fitting import model_error
from gonio.fitting.candidates import fit_candidates
from gonio.fitting.select import MAX_DIFFUSE_COST_RATIO, MIN_GLOSS, gloss_units

ALBEDO = np.array([0.6, 0.5, 0.4])


def _directions(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo) uniform in (cos theta_i, cos theta_o, phi_d) over theta <= 78 deg."""
    ci, co, pd = rng.uniform(0.2, 1, n), rng.uniform(0.2, 1, n), rng.uniform(0, 1, n)
    si, so, p = np.sqrt(1 - ci**2), np.sqrt(1 - co**2), np.pi * pd
    wi = np.stack([si, np.zeros_like(si), ci], axis=1)
    wo = np.stack([so * np.cos(p), so * np.sin(p), co], axis=1)
    return wi, wo


def _samples(model: str, params: dict, rel_noise: float, sigma_rel: float, n: int = 400,
             seed: int = 8) -> tuple[BRDFSamples, np.ndarray]:  # fmt: skip
    """``model`` values times (1 + rel_noise N(0, 1)) with sigmas ``sigma_rel * f``."""
    rng = np.random.default_rng(seed)
    wi, wo = _directions(n, rng)
    p = {k: np.asarray(v, dtype=np.float64) for k, v in params.items()}
    f = np.asarray(get_model(model).eval(wi[:, None], wo[:, None], p))
    brdf = f * (1.0 + rel_noise * rng.normal(size=f.shape))
    return BRDFSamples(wi=wi, wo=wo, brdf=brdf, brdf_std=sigma_rel * f), f


ROUGH = {"albedo": ALBEDO, "ks": np.full(3, 0.15), "alpha": np.full(3, 0.5)}


def test_a_model_that_fits_is_ranked_by_the_gaussian_bic():
    # noise as the sigmas say: no misfit, the noise-sigma fits and select's BIC
    s, _ = _samples("lambert+ggx", ROUGH, 0.01, 0.01)
    cf = fit_candidates(s, ("lambert", "lambert+ggx"))
    assert cf.criterion == "bic" and not cf.is_misfit and cf.misfit["tau"] == 0.0
    assert cf.samples is s
    assert cf.best.model == "lambert+ggx"
    assert cf.best.params["alpha"][0] == pytest.approx(0.5, rel=0.05)


def test_a_misfit_is_refitted_aligned_and_a_matte_lobe_is_not_dropped_for_lambert():
    # 3 % scatter with 0.1 % sigmas: chi^2/dof ~ 900, a misfit; the lobe is matte
    # (paper_white's kind: alpha 0.5, ks 0.15), the case where select's matte rule applied
    # to Cauchy costs sent every fit to lambert
    s, f = _samples("lambert+ggx", ROUGH, 0.03, 0.001)
    cf = fit_candidates(s, ("lambert", "lambert+ggx"))
    assert cf.is_misfit and cf.misfit["fit"] == "aligned" and cf.criterion == "aligned_bic"
    assert all(r.robust == "cauchy" for r in cf.fits)
    by = {r.model: r for r in cf.fits}
    # the matte rule's preconditions hold: it would have picked lambert
    assert float(np.mean(gloss_units(by["lambert+ggx"].bind()))) < MIN_GLOSS
    assert by["lambert"].cost <= MAX_DIFFUSE_COST_RATIO * by["lambert+ggx"].cost
    assert cf.best.model == "lambert+ggx" and cf.weights[cf.best_index] > 0.999
    # and the chosen model is the closer one to the generating values
    rel = {
        k: float(np.median(np.abs(np.asarray(r.bind().eval(s.wi, s.wo)).reshape(f.shape) / f - 1)))
        for k, r in by.items()
    }
    assert rel["lambert+ggx"] < 0.01 < rel["lambert"]
    # the samples fitted are the aligned ones
    np.testing.assert_allclose(cf.samples.brdf_std, model_error.aligned_samples(s).brdf_std)


def test_a_nested_model_at_its_bound_is_charged_its_parameter():
    # Lambertian data with a misfit: oren-nayar's sigma goes to its bound 0, where it is
    # lambert; equal costs, and the BIC counts its extra parameter: weight ratio
    # exp(-ln(m) / 2) = m^(-1/2)
    s, _ = _samples("lambert", {"albedo": ALBEDO}, 0.03, 0.001)
    cf = fit_candidates(s, ("lambert", "oren-nayar"))
    assert cf.criterion == "aligned_bic"
    lam, on = cf.fits
    assert on.params["sigma"][0] == pytest.approx(0.0, abs=1e-6)
    assert on.cost == pytest.approx(lam.cost, rel=1e-6)
    m = lam.diagnostics["n_residuals"]
    assert m == s.brdf.size
    assert cf.weights[1] / cf.weights[0] == pytest.approx(m**-0.5, rel=1e-3)
    assert cf.best.model == "lambert"


def test_nothing_fitted_is_an_error_naming_the_candidates():
    s, _ = _samples("lambert", {"albedo": ALBEDO}, 0.0, 0.01, n=20)
    bad = BRDFSamples(wi=s.wi, wo=s.wo, brdf=np.full_like(s.brdf, np.nan), brdf_std=s.brdf_std)
    with pytest.raises(FitError, match="lambert"):
        fit_candidates(bad, ("lambert", "oren-nayar"))
