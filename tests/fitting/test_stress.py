"""Bad and extreme data: a clear error or a sound result, never NaN reported as success."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.dataset import BRDFSamples, Flag
from gonio.errors import FitError, UnknownNameError
from gonio.fitting import fit

TRUTH = {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": 0.15}


def _sound(r, truth=None, rtol=None):
    assert r.success, r.message
    for v in list(r.params.values()) + list(r.std.values()):
        assert not np.any(np.isnan(v))
    assert np.isfinite(r.cost)
    if truth is not None:
        for k, v in truth.items():
            np.testing.assert_allclose(r.params[k], np.broadcast_to(v, (3,)), rtol=rtol)


def test_nan_inf_samples_are_left_out_and_counted(make_samples):
    s = make_samples("lambert+ggx", TRUTH, n=200, seed=1)
    s.brdf[3, 1] = np.nan
    s.brdf[7, 0] = np.inf
    s.brdf[9, 2] = -np.inf
    s.wi[11] = np.nan
    r = fit(s, "lambert+ggx", loss="l2")
    _sound(r, TRUTH, 1e-6)
    assert r.n_samples == 196
    assert not r.used[[3, 7, 9, 11]].any()
    assert r.diagnostics["dropped"] == {"non-finite brdf": 3, "non-finite direction": 1}


def test_flagged_saturated_samples_are_excluded(make_samples):
    s = make_samples("lambert+ggx", TRUTH, n=200, seed=2)
    peak = s.brdf[:, 0] > np.quantile(s.brdf[:, 0], 0.9)
    s.brdf[peak] = 0.5  # clipped by saturation
    s.flags[peak] = Flag.SATURATED
    r = fit(s, "lambert+ggx", loss="l2")
    _sound(r, TRUTH, 1e-6)  # the unsaturated samples still determine the model exactly
    assert r.diagnostics["dropped"]["flagged"] == int(peak.sum())


def test_unflagged_saturated_and_negative_samples_give_a_sound_fit(make_samples):
    s = make_samples("lambert+ggx", TRUTH, n=300, seed=3, noise=1e-4, read=2e-3)
    s.brdf = np.minimum(s.brdf, 0.6)  # saturation nobody flagged
    s.brdf[:5] = -0.01  # negative values after dark subtraction
    r = fit(s, "lambert+ggx")
    _sound(r)
    assert r.n_samples == 300
    # a robust loss limits the damage of the clipped peak
    rr = fit(s, "lambert+ggx", robust="soft_l1", f_scale=3.0)
    _sound(rr)
    assert "full" in " ".join(rr.algorithm)


def test_grazing_samples(make_samples):
    rng = np.random.default_rng(4)
    n = 200
    t = np.radians(rng.uniform(85.0, 89.99, n))
    p = rng.uniform(0, 2 * np.pi, n)
    wi = np.stack([np.sin(t), np.zeros(n), np.cos(t)], -1)
    wo = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    m = get_model("lambert+ggx")
    f = m.eval(wi[:, None], wo[:, None], {k: np.asarray(v) for k, v in TRUTH.items()})
    r = fit(BRDFSamples(wi=wi, wo=wo, brdf=f), "lambert+ggx", loss="l2")
    _sound(r, TRUTH, 1e-6)


@pytest.mark.parametrize("alpha", [1e-3, 3e-3])
def test_near_mirror_lobe(alpha):
    # samples concentrated within a few alpha of the mirror direction, as a gonio-
    # reflectometer scanning a highlight would take them
    rng = np.random.default_rng(5)
    n = 300
    t = np.radians(rng.uniform(10, 60, n))
    wi = np.stack([np.sin(t), np.zeros(n), np.cos(t)], -1)
    h = np.column_stack([3 * alpha * rng.standard_normal((n, 2)), np.ones(n)])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    wo = 2 * np.sum(wi * h, axis=1, keepdims=True) * h - wi
    truth = {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": alpha}
    m = get_model("lambert+ggx")
    f = m.eval(wi[:, None], wo[:, None], {k: np.asarray(v) for k, v in truth.items()})
    r = fit(BRDFSamples(wi=wi, wo=wo, brdf=f), "lambert+ggx", loss="l2")
    _sound(r, truth, 1e-6)


def test_ten_samples(make_samples):
    s = make_samples("lambert+ggx", TRUTH, n=10, seed=6)
    r = fit(s, "lambert+ggx", loss="l2")
    _sound(r, TRUTH, 1e-6)


def test_too_few_samples_is_a_clear_error(make_samples):
    s = make_samples("lambert+ggx", TRUTH, n=2, seed=6)
    with pytest.raises(FitError, match="residuals.*7 parameters"):
        fit(s, "lambert+ggx", loss="l2")


@pytest.mark.slow
def test_a_million_samples(make_samples):
    s = make_samples("lambert+ggx", TRUTH, n=1_000_000, seed=7)
    r = fit(s, "lambert+ggx", loss="l2")
    _sound(r, TRUTH, 1e-6)
    assert "subset" in " ".join(r.algorithm)


def test_all_zero_data_is_a_clear_error(make_samples):
    s = make_samples("lambert", {"albedo": [0.5, 0.5, 0.5]}, n=50)
    s.brdf[:] = 0.0
    with pytest.raises(FitError, match="zero or negative"):
        fit(s, "lambert+ggx")
    with pytest.raises(FitError, match="zero or negative"):
        fit(s, "auto")


def test_all_invalid_is_a_clear_error(make_samples):
    s = make_samples("lambert", {"albedo": [0.5, 0.5, 0.5]}, n=50)
    s.flags[:] = Flag.EXCLUDED
    with pytest.raises(FitError, match="no usable sample.*flagged"):
        fit(s, "lambert")


def test_sigma_problems(make_samples):
    s = make_samples("lambert+ggx", TRUTH, n=100, seed=8, noise=1e-4, read=1e-3)
    s.brdf_std[4] = 0.0
    with pytest.raises(FitError, match="brdf_std.*index 4"):
        fit(s, "lambert+ggx")
    s.brdf_std[4] = np.nan  # unknown sigma: that sample cannot be weighted, left out
    r = fit(s, "lambert+ggx", loss="weighted_l2")
    _sound(r)
    assert r.diagnostics["dropped"] == {"non-finite brdf_std": 1}


def test_unknown_names(make_samples):
    s = make_samples("lambert", {"albedo": [0.5, 0.5, 0.5]}, n=50)
    with pytest.raises(UnknownNameError, match="LD_NOPE"):
        fit(s, "lambert", algorithm="LD_NOPE")
    with pytest.raises(UnknownNameError, match="loss"):
        fit(s, "lambert", loss="l3")
    with pytest.raises(UnknownNameError, match="robust"):
        fit(s, "lambert", robust="tukey")
    with pytest.raises(UnknownNameError):
        fit(s, "lambert+nonsense")


class _NaNBelow:
    """A real model whose values turn NaN for alpha below a threshold (like an overflowing
    implementation would), to check that no algorithm reports NaN as success."""

    def __init__(self, threshold: float) -> None:
        self.m = get_model("lambert+ggx")
        self.t = threshold
        for k in ("name", "param_names", "bounds", "defaults", "linear_params", "options"):
            setattr(self, k, getattr(self.m, k))

    def _poison(self, f, params):
        bad = np.asarray(params["alpha"]) < self.t
        return np.where(bad, np.nan, f)

    def eval(self, wi, wo, params):
        return self._poison(self.m.eval(wi, wo, params), params)

    def eval_with_grad(self, wi, wo, params):
        f, g = self.m.eval_with_grad(wi, wo, params)
        return self._poison(f, params), {k: self._poison(v, params) for k, v in g.items()}

    def albedo(self, theta_i, params):
        return self.m.albedo(theta_i, params)


@pytest.mark.parametrize("alg", ["auto", "LD_SLSQP", "LD_MMA", "LN_BOBYQA", "GN_CRS2_LM"])
def test_nan_model_values_never_reported_as_success(alg, make_samples):
    s = make_samples("lambert+ggx", {**TRUTH, "alpha": 0.02}, n=150, seed=9)
    try:
        r = fit(s, _NaNBelow(0.05), loss="l2", algorithm=alg)
    except FitError:
        return  # a clear error is acceptable
    # a result is acceptable if it is finite, and only reported as success when sound
    for v in r.params.values():
        assert np.all(np.isfinite(v))
    assert np.isfinite(r.cost)
    assert r.params["alpha"][0] >= 0.05
    if r.success:
        _sound(r)


@pytest.mark.parametrize(
    ("field", "brdf_scale", "std_scale"),
    [("samples.brdf", 1e300, 1.0), ("samples.brdf_std", 1.0, 1e-300)],
)
def test_values_whose_squares_overflow_are_named(make_samples, field, brdf_scale, std_scale):
    # A damaged file (f_r ~ 1e300): every model "failed" with numpy overflow warnings on
    # stderr and "produced non-finite parameters or cost", naming neither field nor sample.
    s = make_samples("lambert", {"albedo": [0.5, 0.5, 0.5]}, n=50, noise=0.01)
    s.brdf[7] *= brdf_scale
    s.brdf_std[7] *= std_scale
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning on the way to the error
        with pytest.raises(FitError, match=rf"{field}: sample 7 has .* beyond 1e\+100"):
            fit(s, "lambert", loss="weighted_l2")
