"""Reported uncertainties are calibrated: z-scores over noise realisations have unit spread.

Noise: photon (variance proportional to f) plus read noise (constant variance), with the
true per-sample sigma stored in ``brdf_std`` as a reduction would.  Over 200 realisations
the z-score ``(p_hat - p_true) / std`` of every parameter must have a standard deviation
in [0.8, 1.25] (the sampling spread of a std over 200 draws is ~5 %).
"""

from __future__ import annotations

import numpy as np
import pytest

from gonio.dataset import BRDFSamples
from gonio.fitting import fit

N_REAL = 200


def _z_scores(make_samples, name, truth, n, noise, read):
    base = make_samples(name, truth, n=n, seed=11)
    f = base.brdf
    sig = np.sqrt(noise * f + read**2)
    rng = np.random.default_rng(2024)
    zs = {k: [] for k in truth}
    for _ in range(N_REAL):
        y = f + sig * rng.standard_normal(f.shape)
        s = BRDFSamples(wi=base.wi, wo=base.wo, brdf=y, brdf_std=sig)
        # the truth conserves energy, so the constraint is not what is tested here
        r = fit(s, name, energy_conservation=False)
        assert r.success, r.message
        for k, v in truth.items():
            zs[k].append((r.params[k] - np.asarray(v)) / r.std[k])
    return {k: np.asarray(v) for k, v in zs.items()}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("name", "truth"),
    [
        ("lambert+ggx", {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": 0.15}),
        ("oren-nayar", {"albedo": [0.3, 0.5, 0.7], "sigma": 0.35}),
    ],
)
def test_z_scores_have_unit_spread(name, truth, make_samples):
    z = _z_scores(make_samples, name, truth, n=120, noise=2e-4, read=2e-3)
    for k, v in z.items():
        sd = np.std(v, axis=0, ddof=1)  # per channel (shape parameters: identical columns)
        assert np.all((sd >= 0.8) & (sd <= 1.25)), f"{name} {k}: z-score std {sd}"
        assert np.all(np.abs(np.mean(v, axis=0)) < 0.3), f"{name} {k}: z-score mean biased"


def test_std_scales_with_noise(make_samples):
    # doubling every sigma doubles the reported std when sigmas are absolute
    truth = {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": 0.15}
    s = make_samples("lambert+ggx", truth, n=150, seed=4)
    s.brdf_std = np.full_like(s.brdf, 0.01)
    r1 = fit(s, "lambert+ggx", energy_conservation=False)
    s.brdf_std = np.full_like(s.brdf, 0.02)
    r2 = fit(s, "lambert+ggx", energy_conservation=False)
    for k in truth:
        np.testing.assert_allclose(r2.std[k], 2 * r1.std[k], rtol=1e-6)
    # relative sigmas (absolute_sigma=False) scale by the residual spread instead: zero
    # residuals here, so the std collapses
    r3 = fit(s, "lambert+ggx", absolute_sigma=False, energy_conservation=False)
    assert r3.std["alpha"][0] < 1e-6 * r2.std["alpha"][0]
