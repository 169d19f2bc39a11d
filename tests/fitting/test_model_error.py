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
