"""Misfit detection and the model-discrepancy sigma (``gonio.fitting.model_error``).

References are closed forms: a Lambertian with residuals of known size fitted by the real
``fit_model`` (nlopt), and the chi^2 equation solved by hand for equal sigmas.
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.dataset import BRDFSamples
from gonio.fitting import model_error
from gonio.fitting.fit import fit_model

ALBEDO = np.array([0.6, 0.5, 0.4])


def _samples(d: float, sigma: float, n: int = 64) -> BRDFSamples:
    """Lambertian samples, every value off by +-d (alternating, so the mean is exact)."""
    rng = np.random.default_rng(3)
    wi = rng.normal(size=(n, 3))
    wo = rng.normal(size=(n, 3))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]) + 0.3, np.abs(wo[:, 2]) + 0.3
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)[:, None]
    brdf = ALBEDO[None, :] / np.pi + d * sign
    return BRDFSamples(wi=wi, wo=wo, brdf=brdf, brdf_std=np.full_like(brdf, sigma))


@pytest.fixture(scope="module")
def misfit():
    s = _samples(d=0.01, sigma=1e-3)
    return s, fit_model(s, "lambert", loss="weighted_l2")


def test_a_misfit_gets_the_discrepancy_that_makes_chi2_per_dof_one(misfit):
    s, fit = misfit
    n, p = s.brdf.size, 3
    # residuals are exactly +-d about the exact albedo: chi^2/dof = d^2 N / (sigma^2 (N-p))
    assert model_error.chi2_dof(fit, s) == pytest.approx(1e-4 * n / (1e-6 * (n - p)), rel=1e-6)
    tau = model_error.model_error_scale([fit], s)
    # sum d^2 / (sigma^2 + tau^2) = N - p  ->  tau^2 = d^2 N / (N - p) - sigma^2
    assert tau == pytest.approx(np.sqrt(1e-4 * n / (n - p) - 1e-6), rel=1e-6)
    inflated = model_error.with_model_error(s, tau)
    assert model_error.chi2_dof(fit, inflated) == pytest.approx(1.0, rel=1e-6)
    assert s.brdf_std[0, 0] == 1e-3  # the input is not modified


def test_a_model_that_fits_is_left_alone():
    s = _samples(d=1e-3, sigma=1e-3)  # chi^2/dof ~ 1: noise, not misfit
    fit = fit_model(s, "lambert", loss="weighted_l2")
    assert model_error.model_error_scale([fit], s) == 0.0
    assert model_error.with_model_error(s, 0.0) is s


def _directions(ci, co, pd):
    """(wi, wo) with cos theta_i, cos theta_o and phi_d / pi as given (isotropic frame)."""
    si, so, p = np.sqrt(1 - ci**2), np.sqrt(1 - co**2), np.pi * pd
    wi = np.stack([si, np.zeros_like(si), ci], axis=1)
    wo = np.stack([so * np.cos(p), so * np.sin(p), co], axis=1)
    return wi, wo


def test_coverage_weights_undo_a_doubled_region():
    """A lattice uniform in (cos theta_i, cos theta_o, phi_d) -- uniform in solid angle --
    with one corner's points measured twice: the doubled points weigh half the others
    (the reference is the sampling density itself, 2 : 1), away from the corner's edge."""
    lo = np.cos(np.radians(80.0))
    g = (np.arange(8) + 0.5) / 8
    c = lo + (1 - lo) * g
    ci, co, pd = (a.ravel() for a in np.meshgrid(c, c, g, indexing="ij"))
    twice = (ci > lo + 0.5 * (1 - lo)) & (co > lo + 0.5 * (1 - lo)) & (pd > 0.5)
    wi, wo = _directions(np.r_[ci, ci[twice]], np.r_[co, co[twice]], np.r_[pd, pd[twice]])
    w = model_error.coverage_weights(wi, wo, bandwidth=0.06)
    n = len(ci)
    deep = twice & (ci > lo + 0.65 * (1 - lo)) & (co > lo + 0.65 * (1 - lo)) & (pd > 0.65)
    far = (ci < lo + 0.35 * (1 - lo)) & (co < lo + 0.35 * (1 - lo)) & (pd < 0.35)
    assert np.median(w[:n][deep]) / np.median(w[:n][far]) == pytest.approx(0.5, rel=0.05)
    # a uniform lattice alone gets equal weights, edges included (the kernel reflects)
    wi, wo = _directions(ci, co, pd)
    w = model_error.coverage_weights(wi, wo, bandwidth=0.06)
    assert np.max(np.abs(w - 1.0)) < 0.05
    assert w.mean() == pytest.approx(1.0)


def _ggx_samples(rel_noise: float, n: int = 400) -> BRDFSamples:
    """lambert+ggx (alpha 0.2) values times (1 + rel_noise * N(0, 1)), tiny sigmas."""
    from gonio.brdf import get_model

    rng = np.random.default_rng(8)
    ci, co, pd = rng.uniform(0.2, 1.0, n), rng.uniform(0.2, 1.0, n), rng.uniform(0, 1, n)
    wi, wo = _directions(ci, co, pd)
    p = {"albedo": ALBEDO, "ks": np.full(3, 0.3), "alpha": np.full(3, 0.2)}
    f = np.asarray(get_model("lambert+ggx").eval(wi[:, None], wo[:, None], p))
    brdf = f * (1.0 + rel_noise * rng.normal(size=f.shape))
    return BRDFSamples(wi=wi, wo=wo, brdf=brdf, brdf_std=np.full_like(brdf, 1e-5))


def test_the_aligned_fit_and_its_bic_choose_the_model_that_follows_the_data():
    # 3 % relative scatter with 1e-5 sigmas: chi^2/dof ~ 10^4 with the noise weights,
    # so the aligned fit is what a session would use; the relative residuals are ~0.4
    # Cauchy scales, and the lobe is what lambert cannot follow
    s = _ggx_samples(0.03)
    fits = [model_error.fit_aligned(s, m) for m in ("lambert", "lambert+ggx")]
    assert all(r.robust == "cauchy" and r.success for r in fits)
    w = model_error.aligned_bic_weights(fits)
    assert w[1] > 0.999, w
    ggx = fits[1]
    assert ggx.params["alpha"][0] == pytest.approx(0.2, rel=0.05)
    np.testing.assert_allclose(ggx.params["albedo"], ALBEDO, rtol=0.03)
    # the reported relative scale is the scatter's (1.4826 * MAD of N(0, 0.03))
    assert model_error.relative_model_error_scale(ggx, s) == pytest.approx(0.03, rel=0.15)
    # the Cauchy cost is the lower one, 4 cost + p ln m its BIC
    assert fits[1].cost < fits[0].cost
    m = fits[1].diagnostics["n_residuals"]
    p = 7  # albedo and ks per channel, alpha: counted whether or not one is at a bound
    assert model_error.aligned_bic(fits[1]) == pytest.approx(4 * fits[1].cost + p * np.log(m))


def test_the_aligned_fit_is_the_minimum_of_its_cauchy_cost():
    # independent reference: the Cauchy cost computed here from the fitted values is at
    # a minimum (no step along any parameter lowers it)
    rng = np.random.default_rng(4)
    n = 200
    wi, wo = _directions(rng.uniform(0.2, 1, n), rng.uniform(0.2, 1, n), rng.uniform(0, 1, n))
    out = np.where(np.arange(n) % 17 == 0, 3.0, 1.0)[:, None]  # 12 outliers, x3
    brdf = ALBEDO / np.pi * (1.0 + 0.05 * rng.normal(size=(n, 3))) * out
    s = BRDFSamples(wi=wi, wo=wo, brdf=brdf, brdf_std=np.full_like(brdf, 1e-5))
    r = model_error.fit_aligned(s, "lambert", coverage=False, iterations=30, rtol=1e-10)
    al = model_error.aligned_samples(s)

    def cost(a: np.ndarray) -> float:
        z = ((a[None, :] / np.pi - al.brdf) / al.brdf_std) ** 2
        return 0.5 * float(np.sum(np.log1p(z)))

    a = np.asarray(r.params["albedo"])
    c0 = cost(a)
    assert c0 == pytest.approx(r.cost, rel=1e-9)
    for k in range(3):
        for h in (-1e-3, 1e-3):
            d = np.zeros(3)
            d[k] = h * a[k]
            assert cost(a + d) >= c0 * (1 - 1e-9)
    # the outliers (x3) did not pull it: the albedo is the inliers' one
    np.testing.assert_allclose(a, ALBEDO, rtol=0.03)


def test_the_robust_start_chain_is_kept_when_its_cauchy_cost_is_lower():
    # one reweighting step per chain: the plain chain's step is the weighted-L2 fit the
    # outliers (every fifth sample x10) pull up; the second chain starts from the direct
    # robust fit and its step lands on the inliers' albedo.  The reference is the
    # Cauchy cost computed here from each result's albedo, and the inliers' ALBEDO.
    rng = np.random.default_rng(5)
    n = 300
    wi, wo = _directions(rng.uniform(0.2, 1, n), rng.uniform(0.2, 1, n), rng.uniform(0, 1, n))
    out = np.where(np.arange(n) % 5 == 0, 10.0, 1.0)[:, None]
    brdf = ALBEDO / np.pi * (1.0 + 0.03 * rng.normal(size=(n, 3))) * out
    s = BRDFSamples(wi=wi, wo=wo, brdf=brdf, brdf_std=np.full_like(brdf, 1e-5))
    al = model_error.aligned_samples(s)

    def cost(a: np.ndarray) -> float:
        z = ((a[None, :] / np.pi - al.brdf) / al.brdf_std) ** 2
        return 0.5 * float(np.sum(np.log1p(z)))

    kw = {"coverage": False, "iterations": 1}
    plain = model_error.fit_aligned(s, "lambert", robust_start=False, **kw)
    both = model_error.fit_aligned(s, "lambert", **kw)
    c_plain, c_both = cost(np.asarray(plain.params["albedo"])), cost(both.params["albedo"])
    assert plain.cost == pytest.approx(c_plain, rel=1e-9)
    assert both.cost == pytest.approx(c_both, rel=1e-9)
    assert plain.diagnostics["irls_chain"] == "plain"
    assert both.diagnostics["irls_chain"] == "robust_start"
    assert both.diagnostics["irls_costs"]["plain"] == pytest.approx(c_plain, rel=1e-9)
    assert c_both < 0.99 * c_plain
    np.testing.assert_allclose(both.params["albedo"], ALBEDO, rtol=0.01)
    assert np.max(np.abs(np.asarray(plain.params["albedo"]) / ALBEDO - 1.0)) > 0.01
