"""The adaptive design criterion (gonio.fitting.design) against closed forms.

The references are computed here from first principles: a Lambertian albedo's Fisher
information is ``sum 1 / (pi sigma_n)^2`` per channel; a lobe model's information and
its sensitivities come from central finite differences of the bound model, and the
D-optimal gain from two determinants, never from the module's own lemma path.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.dataset import BRDFSamples
from gonio.errors import FitError
from gonio.fitting import design
from gonio.fitting.fit import fit_model

from .conftest import model_samples, random_directions


def _noisy(name: str, params: dict, n: int, seed: int, rel: float) -> BRDFSamples:
    """Samples with a relative sigma ``rel`` (the truth's), their brdf_std that sigma."""
    clean = model_samples(name, params, n=n, seed=seed)
    rng = np.random.default_rng(seed + 1)
    sig = rel * clean.brdf
    y = clean.brdf + sig * rng.standard_normal(sig.shape)
    return BRDFSamples(wi=clean.wi, wo=clean.wo, brdf=y, brdf_std=sig)


@pytest.fixture(scope="module")
def lambert_fit():
    s = _noisy("lambert", {"albedo": [0.5, 0.4, 0.3]}, 200, 1, 0.02)
    return s, fit_model(s, "lambert")


@pytest.fixture(scope="module")
def ggx_fit():
    p = {"albedo": [0.5, 0.4, 0.3], "ks": [0.3] * 3, "alpha": [0.2] * 3}
    s = _noisy("lambert+ggx", p, 300, 2, 0.02)
    return s, fit_model(s, "lambert+ggx")


def _pool(n: int = 40, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return random_directions(rng, n, 80.0), random_directions(rng, n, 80.0)


def test_d_optimal_of_a_lambertian_albedo_is_the_closed_form(lambert_fit):
    s, r = lambert_fit
    wi, wo = _pool()
    rel = 0.01
    sc = design.score_candidates([r], [1.0], s, wi, wo, sample_rel_std=rel,
                                 weights={"discrimination": 0, "model_free": 0})  # fmt: skip
    # F_c = sum_n (1/pi)^2 / sigma_n^2 over the used samples; a new sample adds
    # (1/pi)^2 / (rel * albedo_c / pi)^2 = 1 / (rel albedo_c)^2
    a = np.asarray(r.params["albedo"])
    F0 = np.sum((1.0 / np.pi) ** 2 / np.asarray(s.brdf_std) ** 2, axis=0)
    gain = np.sum(np.log((F0 + 1.0 / (rel * a) ** 2) / F0))
    np.testing.assert_allclose(sc.d_optimal, gain, rtol=1e-9)
    np.testing.assert_allclose(sc.total, sc.d_optimal)


def _fd_jacobian(model, params: dict, labels, channels, wi, wo, h=1e-6) -> np.ndarray:
    """(K, C, P) central differences of the bound model w.r.t. each labelled parameter."""
    C = len(channels)
    out = np.zeros((len(wi), C, len(labels)))
    for j, lab in enumerate(labels):
        name, ch = lab[:-1].split("[") if "[" in lab else (lab, None)
        up = {k: np.array(v, dtype=np.float64) for k, v in params.items()}
        dn = {k: np.array(v, dtype=np.float64) for k, v in params.items()}
        sel = slice(None) if ch is None else channels.index(ch)
        step = h * max(1.0, abs(float(np.asarray(params[name]).reshape(-1)[0])))
        up[name][sel] += step
        dn[name][sel] -= step
        fu = model.eval(wi[:, None, :], wo[:, None, :], up)
        fd = model.eval(wi[:, None, :], wo[:, None, :], dn)
        out[:, :, j] = (fu - fd) / (2 * step)
    return out


def test_d_optimal_gain_is_the_log_det_ratio_of_the_information(ggx_fit):
    s, r = ggx_fit
    m = get_model("lambert+ggx")
    labels, ch = r.param_labels, r.channels
    wi, wo = _pool(12)
    rel = 0.01
    sc = design.score_candidates([r], [1.0], s, wi, wo, sample_rel_std=rel,
                                 weights={"discrimination": 0, "model_free": 0})  # fmt: skip
    # the information of the samples so far, from finite differences
    Js = _fd_jacobian(m, r.params, labels, ch, np.asarray(s.wi), np.asarray(s.wo))
    Js = Js / np.asarray(s.brdf_std)[:, :, None]
    F0 = np.einsum("ncp,ncq->pq", Js, Js)
    Jk = _fd_jacobian(m, r.params, labels, ch, wi, wo)
    f = np.asarray(r.bind().eval(wi, wo))
    for k in range(len(wi)):
        A = Jk[k] / (rel * f[k])[:, None]
        want = np.linalg.slogdet(F0 + A.T @ A)[1] - np.linalg.slogdet(F0)[1]
        assert sc.d_optimal[k] == pytest.approx(want, rel=1e-4, abs=1e-6)


def _with(r, **params):
    """A copy of fit ``r`` with other parameter values and no parameter uncertainty."""
    p = {k: np.array(v, dtype=np.float64) for k, v in r.params.items()}
    p.update({k: np.asarray(v, dtype=np.float64) for k, v in params.items()})
    return dataclasses.replace(r, params=p, covariance=np.zeros_like(r.covariance))


def test_discrimination_is_zero_where_candidates_agree_and_box_hill_where_they_differ(
    lambert_fit,
):
    s, r = lambert_fit
    wi, wo = _pool()
    rel = 0.01
    a = np.asarray(r.params["albedo"])
    same = design.score_candidates([_with(r), _with(r)], [0.5, 0.5], s, wi, wo,
                                   sample_rel_std=rel)  # fmt: skip
    np.testing.assert_array_equal(same.discrimination, 0.0)
    b = a * 1.03
    two = design.score_candidates([_with(r), _with(r, albedo=b)], [0.7, 0.3], s, wi, wo,
                                  sample_rel_std=rel)  # fmt: skip
    # no parameter uncertainty: D = pi1 pi2 sum_c (mu1 - mu2)^2 2 / s_c^2, with the
    # sample sigma s_c = rel x the weighted mean prediction
    mu1, mu2 = a / np.pi, b / np.pi
    sc = rel * (0.7 * mu1 + 0.3 * mu2)
    D = 0.7 * 0.3 * np.sum((mu1 - mu2) ** 2 * 2 / sc**2)
    np.testing.assert_allclose(two.discrimination, 0.5 * np.log1p(D), rtol=1e-12)


def test_discrimination_is_largest_where_the_models_differ_most(ggx_fit):
    s, r = ggx_fit
    diffuse = fit_model(s, "lambert")
    # a pool along the incidence plane at theta_i 30 deg: the lobe peaks at the mirror
    t = np.radians(np.arange(-80, 81, 5.0))
    wo = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], axis=1)
    wi = np.tile([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))], (len(t), 1))
    sc = design.score_candidates([r, diffuse], [0.5, 0.5], s, wi, wo, sample_rel_std=0.01)
    f1 = np.asarray(r.bind().eval(wi, wo))
    f2 = np.asarray(diffuse.bind().eval(wi, wo))
    mix = 0.5 * (f1 + f2)
    assert np.argmax(sc.discrimination) == np.argmax(np.sum((f1 - f2) ** 2 / mix**2, axis=1))
    assert np.degrees(t[np.argmax(sc.discrimination)]) == pytest.approx(-30.0)


def test_greedy_batch_never_picks_a_duplicate(ggx_fit):
    s, r = ggx_fit
    wi, wo = _pool(10)
    # the pool's best direction five times over
    sc0 = design.score_candidates([r], [1.0], s, wi, wo, sample_rel_std=0.01)
    k = int(np.argmax(sc0.total))
    wi2 = np.vstack([wi, np.repeat(wi[k : k + 1], 4, axis=0)])
    wo2 = np.vstack([wo, np.repeat(wo[k : k + 1], 4, axis=0)])
    sc = design.score_candidates([r], [1.0], s, wi2, wo2, sample_rel_std=0.01)
    every = design.choose_batch(sc, [r], wi2, wo2, len(wi2))
    assert sorted(every) == list(range(len(wi2)))
    twins = {k, *range(10, 14)}
    batch = design.choose_batch(sc, [r], wi2, wo2, 5, min_separation_deg=1.0)
    assert len(batch) == 5 and len(set(batch)) == 5
    assert len(twins & set(batch)) == 1  # the separation passes the copies over
    # without a separation the copies are still distinct entries, each picked once at most
    nosep = design.choose_batch(sc, [r], wi2, wo2, 8)
    assert nosep[0] in twins and len(set(nosep)) == 8


def test_space_filling_batch_takes_each_time_the_pose_farthest_from_all_before():
    """Against a brute force over every pool pose: each pick's smallest distance to the
    measured directions and the earlier picks is the largest the pool has."""
    wi, wo = _pool(60, seed=11)
    twi, two = _pool(25, seed=12)
    picks = design.space_filling_batch(wi, wo, twi, two, 6)
    assert len(set(picks)) == 6
    awi, awo = twi, two
    for k in picks:
        d = np.array(
            [
                design.pose_distance_deg(wi[j : j + 1], wo[j : j + 1], awi, awo).min()
                for j in range(60)
            ]
        )
        assert d[k] == pytest.approx(d.max(), abs=1e-9)
        awi, awo = np.vstack([awi, wi[k : k + 1]]), np.vstack([awo, wo[k : k + 1]])
    # nothing measured yet: the first pick is position 0, then the farthest from it
    first = design.space_filling_batch(wi, wo, np.zeros((0, 3)), np.zeros((0, 3)), 2)
    d0 = design.pose_distance_deg(wi[:1], wo[:1], wi, wo)[0]
    assert first == [0, int(np.argmax(d0))]
    # the whole pool, each once; more than the pool: the pool
    assert sorted(design.space_filling_batch(wi, wo, twi, two, 99)) == list(range(60))


def _covaried(r, name: str, rel: float):
    """Fit ``r`` with the std (and the covariance's diagonal) of ``name`` set to ``rel``
    times its value and no other uncertainty."""
    labels = list(r.param_labels)
    cov = np.zeros((len(labels), len(labels)))
    std = {k: np.zeros_like(np.asarray(v, dtype=np.float64)) for k, v in r.std.items()}
    for j, lab in enumerate(labels):
        n, c = lab[:-1].split("[") if "[" in lab else (lab, None)
        if n == name:
            i = 0 if c is None else r.channels.index(c)
            v = float(np.asarray(r.params[n]).reshape(-1)[i])
            cov[j, j] = (rel * v) ** 2
            std[n][:] = rel * abs(v) if c is None else std[n]
            if c is not None:
                std[n][i] = rel * abs(v)
    return dataclasses.replace(r, covariance=cov, std=std)


def test_stopping_uses_the_covariance_it_is_given(ggx_fit, lambert_fit):
    _, r = ggx_fit
    wi, wo = design.hemisphere_directions(80.0, 256)
    ok, st = design.stopping([_covaried(r, "alpha", 0.009)], [1.0], {"alpha": 0.01}, None,
                             wi, wo)  # fmt: skip
    assert ok and st["rel_sigma"]["alpha"] == pytest.approx(0.009)
    ok, st = design.stopping([_covaried(r, "alpha", 0.011)], [1.0], {"alpha": 0.01}, None,
                             wi, wo)  # fmt: skip
    assert not ok and "alpha rel sigma 0.011 > 0.01" in st["reason"]
    # the best model (largest weight) is judged; a parameter it lacks is never reached
    _, lam = lambert_fit
    ok, st = design.stopping([_covaried(r, "alpha", 0.001), lam], [0.2, 0.8], {"alpha": 0.01},
                             None, wi, wo)  # fmt: skip
    assert not ok and st["model"] == "lambert" and st["rel_sigma"]["alpha"] is None
    # a Lambertian albedo with 2 % relative sigma predicts f to 2 % everywhere
    lam2 = _covaried(lam, "albedo", 0.02)
    ok, st = design.stopping([lam2], [1.0], None, 0.021, wi, wo)
    assert ok and st["brdf_rel_sigma"] == pytest.approx(0.02, rel=1e-9)
    ok, _ = design.stopping([lam2], [1.0], None, 0.019, wi, wo)
    assert not ok
    ok, st = design.stopping([lam2], [1.0], None, None, wi, wo)
    assert not ok and "no precision target" in st["reason"]


def test_hemisphere_directions_cover_the_cap_uniformly_in_solid_angle():
    wi, wo = design.hemisphere_directions(80.0, 4096)
    again = design.hemisphere_directions(80.0, 4096)
    np.testing.assert_array_equal(wi, again[0])
    for w in (wi, wo):
        np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=1e-12)
        assert np.degrees(np.arccos(w[:, 2].min())) <= 80.0
        # uniform in solid angle: cos theta uniform on [cos 80, 1], azimuth uniform
        cmin = np.cos(np.radians(80.0))
        assert np.mean(w[:, 2]) == pytest.approx((1 + cmin) / 2, abs=2e-3)
        assert abs(np.mean(np.cos(np.arctan2(w[:, 1], w[:, 0])))) < 5e-3


def test_pose_distance_is_zero_under_isotropy_and_reciprocity():
    rng = np.random.default_rng(3)
    wi, wo = random_directions(rng, 20, 80.0), random_directions(rng, 20, 80.0)
    a = rng.uniform(0, 2 * np.pi, 20)
    rot = np.stack([np.stack([np.cos(a), -np.sin(a), 0 * a], -1),
                    np.stack([np.sin(a), np.cos(a), 0 * a], -1),
                    np.stack([0 * a, 0 * a, 1 + 0 * a], -1)], axis=1)  # fmt: skip
    wi_r, wo_r = np.einsum("nij,nj->ni", rot, wi), np.einsum("nij,nj->ni", rot, wo)
    d_rot = np.diag(design.pose_distance_deg(wi, wo, wi_r, wo_r))
    d_swap = np.diag(design.pose_distance_deg(wi, wo, wo, wi))
    np.testing.assert_allclose(d_rot, 0.0, atol=1e-6)
    np.testing.assert_allclose(d_swap, 0.0, atol=1e-6)
    # a 10 deg change of theta_h at theta_d 0 is 10 deg
    n = np.array([[0.0, 0.0, 1.0]])
    t = np.radians(10.0)
    tilted = np.array([[np.sin(t), 0.0, np.cos(t)]])
    assert design.pose_distance_deg(n, n, tilted, tilted)[0, 0] == pytest.approx(10.0)


def test_bad_input_is_refused_with_the_value(lambert_fit):
    s, r = lambert_fit
    wi, wo = _pool(5)
    with pytest.raises(FitError, match="2 model weights"):
        design.score_candidates([r], [0.5, 0.5], s, wi, wo, sample_rel_std=0.01)
    with pytest.raises(FitError, match="sample_rel_std"):
        design.score_candidates([r], [1.0], s, wi, wo, sample_rel_std=0.0)
    with pytest.raises(FitError, match="unknown term 'bogus'"):
        design.score_candidates([r], [1.0], s, wi, wo, sample_rel_std=0.01, weights={"bogus": 1})
    with pytest.raises(FitError, match=r"\(K, 3\)"):
        design.score_candidates([r], [1.0], s, wi[:, :2], wo, sample_rel_std=0.01)
    with pytest.raises(FitError, match="max_theta_deg"):
        design.hemisphere_directions(95.0)
