"""Per-sample cost weights (``fit_model(..., sample_weight=w)``).

Reference: an integer weight is the same sample counted that many times, so a weighted
fit must equal the unweighted fit of the samples with the weighted ones duplicated (the
real ``fit_model``, nlopt, with and without a robust penalty).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.dataset import BRDFSamples
from gonio.errors import FitError
from gonio.fitting.fit import fit_model
from gonio.fitting.losses import get_loss
from gonio.fitting.objective import prepare_problem


def _samples(n: int = 160) -> BRDFSamples:
    rng = np.random.default_rng(11)
    wi = rng.normal(size=(n, 3))
    wo = rng.normal(size=(n, 3))
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]) + 0.2, np.abs(wo[:, 2]) + 0.2
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    # a Lambertian with a lobe-like excess where wo is near the mirror of wi: a
    # Lambertian cannot follow it, so where the weight sits moves the fit
    mirror = wi * np.array([-1.0, -1.0, 1.0])
    excess = 0.5 * np.exp((np.sum(mirror * wo, axis=1) - 1.0) / 0.05)
    brdf = np.array([0.5, 0.4, 0.3])[None, :] / np.pi + excess[:, None]
    brdf = brdf * (1.0 + 0.01 * rng.normal(size=brdf.shape))
    return BRDFSamples(wi=wi, wo=wo, brdf=brdf, brdf_std=0.01 * np.abs(brdf) + 1e-3)


def _take(s: BRDFSamples, idx: np.ndarray) -> BRDFSamples:
    return dataclasses.replace(s, wi=s.wi[idx], wo=s.wo[idx], brdf=s.brdf[idx],
                               brdf_std=s.brdf_std[idx], flags=None)  # fmt: skip


def _weighted() -> tuple[BRDFSamples, np.ndarray, BRDFSamples]:
    s = _samples()
    # the samples in the lobe count thrice, and every third other one twice
    lobe = s.brdf[:, 0] > 1.2 * 0.5 / np.pi
    w = np.where(lobe, 3.0, np.where(np.arange(len(s.wi)) % 3 == 0, 2.0, 1.0))
    assert 3 <= lobe.sum() <= len(lobe) // 2
    return s, w, _take(s, np.repeat(np.arange(len(s.wi)), w.astype(int)))


@pytest.mark.parametrize(
    ("model", "robust"), [("lambert", None), ("lambert+ggx", None), ("lambert", "cauchy")]
)
def test_an_integer_weight_is_the_sample_counted_that_often(robust, model):
    s, w, dup = _weighted()
    kw = {"loss": "weighted_l2", "robust": robust, "f_scale": 1.0, "energy_conservation": False}
    a = fit_model(s, model, sample_weight=w, **kw)
    b = fit_model(dup, model, **kw)
    plain = fit_model(s, model, **kw)
    assert a.cost == pytest.approx(b.cost, rel=1e-6)
    for k in a.params:
        np.testing.assert_allclose(a.params[k], b.params[k], rtol=2e-4)
    if robust is not None:  # the penalty discounts the lobe: the weights barely move it
        return
    # and the weights did move the compromise (the test can fail)
    assert not np.allclose(a.params["albedo"], plain.params["albedo"], rtol=1e-2)


@pytest.mark.parametrize("robust", [None, "cauchy"])
def test_the_weighted_cost_and_gradient_are_the_duplicated_samples(robust):
    # (a fit of lambert+ggx under a Cauchy penalty has several local minima: the searches
    # of the two problems may end in different ones, so the objective itself is compared)
    s, w, dup = _weighted()
    m = get_model("lambert+ggx")
    a = prepare_problem(m, s, get_loss("weighted_l2"), robust, 1.0, sample_weight=w)
    b = prepare_problem(m, dup, get_loss("weighted_l2"), robust, 1.0)
    rng = np.random.default_rng(5)
    for _ in range(5):
        x = a.pack(rng.uniform(0.05, 0.5, 1), rng.uniform(0.0, 0.6, (2, 3)))
        ca, ga = a.full_cost(x)
        cb, gb = b.full_cost(x)
        assert ca == pytest.approx(cb, rel=1e-12)
        np.testing.assert_allclose(ga, gb, rtol=1e-10, atol=1e-12 * np.abs(gb).max())


def test_a_bad_weight_vector_is_named():
    s = _samples(40)
    with pytest.raises(FitError, match="sample_weight: expected 40 finite weights"):
        fit_model(s, "lambert", sample_weight=np.ones(39))
    with pytest.raises(FitError, match="sample_weight"):
        fit_model(s, "lambert", sample_weight=np.full(40, -1.0))
