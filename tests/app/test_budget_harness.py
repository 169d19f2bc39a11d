"""The accuracy harness's statistics on samples with a known error model (no session):
a right budget gives z RMS ~1 in every band, a budget that leaves out a term is caught."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gonio.app.budget_harness import (
    BANDS_DEG,
    MAX_JUDGED_DEG,
    MIN_BAND_SAMPLES,
    HarnessMaterial,
    default_materials,
    fit_statistics,
    judge,
    noise_only_outside,
    sample_statistics,
)
from gonio.dataset import BRDFSamples


@dataclasses.dataclass
class WithBudget(BRDFSamples):
    budget: dict | None = None


def _directions(rng, n):
    th = np.radians(rng.uniform(0, 80, n))
    ph = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)


def _samples(material: HarnessMaterial, n=4000, seed=0, geo_rel=0.03):
    """Samples of the material's truth with noise (1 %) and a 'geometric' error (3 %)
    drawn independently; the budget holds both, brdf_std their root sum of squares."""
    rng = np.random.default_rng(seed)
    wi, wo = _directions(rng, n), _directions(rng, n)
    f = material.truth().eval(wi, wo)
    noise = 0.01 * f + 1e-4
    geo = geo_rel * f
    y = f + noise * rng.standard_normal(f.shape) + geo * rng.standard_normal(f.shape)
    return WithBudget(
        wi=wi, wo=wo, brdf=y, brdf_std=np.hypot(noise, geo),
        budget={"noise": noise, "geometry": geo},
    )  # fmt: skip


def test_a_right_budget_passes_and_noise_alone_is_caught():
    ggx = default_materials(None)[0]
    s = _samples(ggx)
    st = sample_statistics(s, ggx.truth())
    assert st["budget"] and st["budget_terms"] == ["geometry", "noise"]
    assert set(st["full"]["bands"]) == {f"{lo}-{hi}" for lo, hi in BANDS_DEG[:8]}
    for band, row in st["full"]["bands"].items():
        for c in "RGB":
            assert 0.9 < row[c] < 1.1, (band, c, row)  # ~500 samples a band: +-3 %
            # noise alone (1 % of a 3.2 % total): z RMS ~3.2
            assert 2.8 < st["noise_only"]["bands"][band][c] < 3.6
    rep = {"samples": st, "fit": fit_statistics(s, ggx)}
    assert "z_full" not in judge(rep)
    big = [b for b, row in st["noise_only"]["bands"].items() if row["n"] >= MIN_BAND_SAMPLES]
    assert len(big) >= 6 and len(noise_only_outside(rep)) == 3 * len(big)
    # the fit: ~0.03 / sqrt(4000) relative errors, well inside 1 %; truth recovered
    assert rep["fit"]["median_rel_brdf_error"] < 0.01
    assert rep["fit"]["within_3_sigma"] >= 0.85


def test_a_budget_missing_a_term_fails_the_targets():
    ggx = default_materials(None)[0]
    s = _samples(ggx, seed=1)
    wrong = dataclasses.replace(s, brdf_std=s.budget["noise"])  # the geometric term lost
    rep = {"samples": sample_statistics(wrong, ggx.truth()), "fit": fit_statistics(wrong, ggx)}
    bad = judge(rep)
    judged = [
        b
        for b, row in rep["samples"]["full"]["bands"].items()
        if row["n"] >= MIN_BAND_SAMPLES and float(b.split("-")[0]) < MAX_JUDGED_DEG
    ]
    assert len(judged) >= 6 and len(bad["z_full"]) == 3 * len(judged)
    # 4000 samples of 3.2 % error reported as 1 %: the fitted parameters are off by
    # several of their (too small) sigmas
    assert rep["fit"]["max_abs_z"] > 3 and "params" in bad


def test_shared_calibration_scale_counts_in_the_full_budget():
    ggx = default_materials(None)[0]
    s = _samples(ggx, seed=2, geo_rel=0.0)
    scale = 1.0 + 0.05 * np.array([1.0, -1.0, 0.5])  # one 5 % calibration error per channel
    s = dataclasses.replace(s, brdf=s.brdf * scale, attrs={"calibration_rel_std": [0.05] * 3})
    st = sample_statistics(s, ggx.truth())
    # the shared scale dominates: without it z RMS is ~5, with it ~1.1 (the draws are
    # 1, 1, 0.5 sigma)
    assert all(st["noise_only"]["all"][c] > 2.0 for c in "RG")
    assert all(0.4 < st["full"]["all"][c] < 1.2 for c in "RGB")


@pytest.mark.parametrize("which", [0, 1])
def test_truth_of_the_analytic_materials_is_the_closed_form(which):
    from gonio.brdf import get_model

    m = default_materials(None)[which]
    wi, wo = _directions(np.random.default_rng(3), 50), _directions(np.random.default_rng(4), 50)
    opts = {"fresnel": "schlick"} if which else {}
    ref = get_model("lambert+ggx", **opts).eval(
        wi[:, None], wo[:, None], {k: np.asarray(v) for k, v in m.params.items()}
    )
    np.testing.assert_array_equal(m.truth().eval(wi, wo), ref)
