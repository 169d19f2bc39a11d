"""Physical and numerical properties of every analytic model (Hypothesis).

Reciprocity, non-negativity, energy conservation (directional albedo <= 1 inside the
documented bounds), analytic gradients against central differences, linearity in the
declared linear parameters, and the stability cases of issue 2.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gonio.brdf import get_model

CONFIGS = [
    ("lambert", {}),
    ("oren-nayar", {}),
    ("phong", {}),
    ("blinn-phong", {}),
    ("ward", {}),
    ("ward-aniso", {}),
    ("ggx", {}),
    ("ggx", {"fresnel": "schlick"}),
    ("ggx", {"fresnel": "conductor"}),
    ("beckmann", {}),
    ("beckmann", {"g1": "rational", "fresnel": "dielectric"}),
    ("beckmann", {"fresnel": "conductor"}),
    ("lambert+ggx+ggx", {}),
]
IDS = [n + "".join(f"-{v}" for v in o.values()) for n, o in CONFIGS]
SINGLE_LOBES = [c for c in CONFIGS if "+" not in c[0]]
SINGLE_IDS = [i for i, c in zip(IDS, CONFIGS, strict=True) if "+" not in c[0]]

PROFILE = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=False
)


def _value(lo: float, hi: float, margin: float = 0.0) -> st.SearchStrategy[float]:
    """Uniform, log-uniform (wide positive ranges) and the bounds themselves."""
    if margin:
        span = hi - lo
        lo, hi = lo + margin * span if lo == 0 else lo * (1 + margin), hi - margin * span
    parts = [st.floats(lo, hi)]
    if hi / max(lo, 1e-3) > 100:
        log_lo, log_hi = math.log(max(lo, 1e-3)), math.log(hi)
        # exp(log(x)) may round just outside the bounds: clip back
        parts.append(st.floats(log_lo, log_hi).map(lambda v: min(max(math.exp(v), lo), hi)))
    if not margin:
        parts.append(st.sampled_from([lo, hi]))
    return st.one_of(*parts)


def _params(model, margin: float = 0.0):
    return st.fixed_dictionaries(
        {k: _value(lo, hi, margin) for k, (lo, hi) in model.bounds.items()}
    )


def _direction(upper_only: bool = True):
    top = math.pi / 2 if upper_only else math.pi
    return st.tuples(st.floats(0.0, top), st.floats(0.0, 2 * math.pi)).map(
        lambda t: np.array(
            [math.sin(t[0]) * math.cos(t[1]), math.sin(t[0]) * math.sin(t[1]), math.cos(t[0])]
        )
    )


@pytest.mark.parametrize("name, options", CONFIGS, ids=IDS)
def test_reciprocity(name, options):
    m = get_model(name, **options)

    @PROFILE
    @given(p=_params(m), wi=_direction(), wo=_direction())
    def check(p, wi, wo):
        a, b = m.eval(wi, wo, p), m.eval(wo, wi, p)
        # relative 1e-12; below the normal range (a lobe's far tail, ~1e-316) float64 keeps
        # only an absolute spacing of math.ulp(0.0) = 5e-324, so a few of those are allowed
        # (hypothesis found 3.1e-316 vs 3.1e-316 - 5e-324; above ~1e-300 the term is nil)
        assert abs(a - b) <= 1e-12 * max(abs(a), abs(b)) + 4 * math.ulp(0.0)

    check()


@pytest.mark.parametrize("name, options", CONFIGS, ids=IDS)
def test_non_negative_and_zero_below_horizon(name, options):
    m = get_model(name, **options)

    @PROFILE
    @given(p=_params(m), wi=_direction(False), wo=_direction(False))
    def check(p, wi, wo):
        f = m.eval(wi, wo, p)
        assert np.isfinite(f) and f >= 0.0
        if wi[2] <= 0 or wo[2] <= 0:
            assert f == 0.0

    check()


# Quadrature accuracy of the albedo (tests/brdf/test_models_albedo.py: <= 1e-9 on smooth
# lobes, <= 1e-4 where the integrand has kinks, and those lobes stay below 0.996).
ALBEDO_SLACK = 1e-8


@pytest.mark.parametrize("name, options", SINGLE_LOBES, ids=SINGLE_IDS)
def test_albedo_at_most_one_inside_bounds(name, options):
    m = get_model(name, **options)

    @settings(PROFILE, max_examples=25)
    @given(p=_params(m), theta=st.floats(0.0, math.pi / 2), phi=st.floats(0.0, math.pi))
    def check(p, theta, phi):
        a = m.albedo(theta, p, phi_i=phi)
        assert 0.0 <= a <= 1.0 + ALBEDO_SLACK

    check()


def test_albedo_of_a_sum_at_most_one_when_weights_sum_to_at_most_one():
    m = get_model("lambert+ggx+ggx", fresnel="schlick")

    @settings(PROFILE, max_examples=25)
    @given(
        p=_params(m),
        w=st.lists(st.floats(0.0, 1.0), min_size=3, max_size=3),
        theta=st.floats(0.0, math.pi / 2),
    )
    def check(p, w, theta):
        w = np.array(w) / max(1.0, sum(w))
        p = dict(p, albedo=w[0], ks_2=w[1], ks_3=w[2])
        assert m.albedo(theta, p) <= 1.0 + ALBEDO_SLACK

    check()


@pytest.mark.parametrize("name, options", CONFIGS, ids=IDS)
def test_gradients_match_central_differences(name, options):
    m = get_model(name, **options)

    @PROFILE
    @given(p=_params(m, margin=1e-3), wi=_direction(), wo=_direction())
    def check(p, wi, wo):
        f, grads = m.eval_with_grad(wi, wo, p)
        assert set(grads) == set(m.param_names)
        for k in m.param_names:
            h = 1e-6 * abs(p[k])  # p > 0: the strategy keeps a margin inside the bounds
            if f > 0 and grads[k] != 0:
                # steep exponentials (Ward/Beckmann tails): keep h * dlnf/dp <= 1e-4 so the
                # truncation error stays ~1e-9 relative
                h = min(h, 1e-4 * abs(f / grads[k]))
            fp = m.eval(wi, wo, dict(p, **{k: p[k] + h}))
            fm = m.eval(wi, wo, dict(p, **{k: p[k] - h}))
            fd = (fp - fm) / (2 * h)
            if max(abs(f), abs(fp), abs(fm)) < 1e-290:
                continue  # subnormal floats carry no relative precision
            # truncation O(h^2 f''') is ~1e-12 relative; rounding ~ eps |f| / h (x100)
            tol = 1e-5 * max(abs(grads[k]), abs(fd)) + 1e-14 * max(abs(f), abs(fp), abs(fm)) / h
            assert abs(grads[k] - fd) <= tol, (k, grads[k], fd)

    check()


@pytest.mark.parametrize("name, options", CONFIGS, ids=IDS)
def test_linear_params_enter_linearly(name, options):
    m = get_model(name, **options)
    rng = np.random.default_rng(3)
    wi = rng.normal(size=(50, 3))
    wo = rng.normal(size=(50, 3))
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    wi[:, 2] = np.abs(wi[:, 2])
    wo[:, 2] = np.abs(wo[:, 2])
    p = dict(m.defaults)
    f, g = m.eval_with_grad(wi, wo, p)
    zero = dict(p, **{k: 0.0 for k in m.linear_params})
    # f = sum_k p_k * df/dp_k over the linear parameters (and 0 when they all vanish).
    np.testing.assert_allclose(
        f, sum(p[k] * g[k] for k in m.linear_params), rtol=1e-13, atol=1e-300
    )
    assert np.all(m.eval(wi, wo, zero) == 0.0)


def _stability_directions():
    t90 = np.array([1.0, 0.0, 0.0])
    t90_cos = np.array([math.sin(math.pi / 2), 0.0, math.cos(math.pi / 2)])  # z = 6e-17
    n = np.array([0.0, 0.0, 1.0])
    a = np.array([math.sin(0.7) * math.cos(0.3), math.sin(0.7) * math.sin(0.3), math.cos(0.7)])
    refl = np.array([-a[0], -a[1], a[2]])
    g = np.array([math.sin(math.radians(89.999)), 0.0, math.cos(math.radians(89.999))])
    pairs = [
        (t90, t90),
        (t90, -t90 * np.array([1, 1, -1])),
        (t90_cos, t90_cos),
        (t90_cos, np.array([-t90_cos[0], 0.0, t90_cos[2]])),
        (t90_cos, n),
        (n, n),
        (n, a),
        (a, a),  # wi == wo
        (a, refl),  # wi == reflect(wo)
        (g, g),
        (g, np.array([-g[0], 0.0, g[2]])),
        (g, n),
    ]
    wi = np.array([p[0] for p in pairs])
    wo = np.array([p[1] for p in pairs])
    return wi, wo


def _extreme_params(m):
    """Defaults, every bound, and the issue's extremes (alpha 1e-4, exponent 1e6)."""
    sets = [dict(m.defaults)]
    for k, (lo, hi) in m.bounds.items():
        sets.append(dict(m.defaults, **{k: lo}))
        sets.append(dict(m.defaults, **{k: hi}))
    sets.append(
        {k: (lo if k.startswith("alpha") else m.defaults[k]) for k, (lo, _) in m.bounds.items()}
    )
    sets.append({k: (1e6 if k.startswith("n") else m.defaults[k]) for k in m.bounds})
    return sets


@pytest.mark.parametrize("name, options", CONFIGS, ids=IDS)
def test_no_nan_or_inf_at_the_edges(name, options):
    m = get_model(name, **options)
    wi, wo = _stability_directions()
    for p in _extreme_params(m):
        f, g = m.eval_with_grad(wi, wo, p)
        assert np.all(np.isfinite(f)), (p, f)
        for k, v in g.items():
            assert np.all(np.isfinite(v)), (p, k, v)
        assert np.array_equal(f, m.eval(wi, wo, p)) or np.allclose(f, m.eval(wi, wo, p), rtol=1e-13)
        a = m.albedo(np.array([0.0, 0.3, math.pi / 2 - 1e-9, math.pi / 2]), p)
        assert np.all(np.isfinite(a)) and np.all(a >= 0)


def test_near_mirror_peak_is_finite_and_huge():
    m = get_model("ggx")
    a = np.array([math.sin(0.7), 0.0, math.cos(0.7)])
    f = m.eval(a, np.array([-a[0], 0.0, a[2]]), {"ks": 1.0, "alpha": 1e-4})
    # D(h = n) = 1 / (pi alpha^2), G ~ 1: f = 1 / (4 pi alpha^2 cos^2) -> ~ 1.3e7
    assert f == pytest.approx(1.0 / (4 * math.pi * 1e-8 * math.cos(0.7) ** 2), rel=1e-6)


def test_nan_in_nan_out():
    m = get_model("lambert+ggx")
    wi = np.array([[np.nan, 0.0, 1.0], [0.0, 0.0, np.nan], [0.0, 0.0, 1.0]])
    wo = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    f = m.eval(wi, wo, {})
    assert np.isnan(f[0]) and np.isnan(f[1]) and np.isfinite(f[2])


def test_broadcasting_over_directions_and_channels():
    m = get_model("lambert+ggx", fresnel="schlick")
    rng = np.random.default_rng(0)
    wi = np.abs(rng.normal(size=(7, 3)))
    wo = np.abs(rng.normal(size=(7, 3)))
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    p = {"albedo": np.array([0.1, 0.5, 0.9]), "ks": 0.3, "alpha": 0.2, "f0": [0.04, 0.05, 0.9]}
    f = m.eval(wi[:, None, :], wo[:, None, :], p)
    assert f.shape == (7, 3)
    f2, g = m.eval_with_grad(wi[:, None, :], wo[:, None, :], p)
    assert all(v.shape == (7, 3) for v in g.values())
    for c in range(3):
        pc = {k: np.broadcast_to(v, (3,))[c] for k, v in p.items()}
        np.testing.assert_allclose(f[:, c], m.eval(wi, wo, pc), rtol=1e-14)
    b = m.bind(p)
    np.testing.assert_array_equal(b.eval(wi, wo), f)
    # grid: every wi against every wo
    assert m.eval(wi[:, None, :], wo[None, :, :], {}).shape == (7, 7)
    assert b.albedo(np.array([0.0, 0.5])).shape == (2, 3)
    # scalar parameters are broadcast to 3 channels by bind
    assert get_model("ggx").bind({"alpha": 0.3}).eval(wi, wo).shape == (7, 3)


def test_large_batches_equal_small_batches():
    # Large batches are evaluated in chunks; the result must not depend on that.
    m = get_model("ggx")
    rng = np.random.default_rng(5)
    wi = rng.normal(size=(50_000, 3))
    wo = rng.normal(size=(50_000, 3))
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    big = m.eval(wi, wo, {"alpha": 0.1})
    small = np.concatenate(
        [m.eval(wi[i : i + 100], wo[i : i + 100], {"alpha": 0.1}) for i in range(0, 50_000, 100)]
    )
    np.testing.assert_array_equal(big, small)
    # and the fast path agrees with the general (gradient) path
    np.testing.assert_allclose(big, m.eval_with_grad(wi, wo, {"alpha": 0.1})[0], rtol=1e-13)


def test_sum_is_the_sum_of_its_lobes():
    rng = np.random.default_rng(2)
    wi = np.abs(rng.normal(size=(20, 3)))
    wo = np.abs(rng.normal(size=(20, 3)))
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=-1, keepdims=True)
    m = get_model("lambert+ggx+ggx")
    assert m.param_names == ("albedo", "ks_2", "alpha_2", "ks_3", "alpha_3")
    assert m.linear_params == ("albedo", "ks_2", "ks_3")
    p = {"albedo": 0.3, "ks_2": 0.2, "alpha_2": 0.05, "ks_3": 0.4, "alpha_3": 0.5}
    ref = (
        get_model("lambert").eval(wi, wo, {"albedo": 0.3})
        + get_model("ggx").eval(wi, wo, {"ks": 0.2, "alpha": 0.05})
        + get_model("ggx").eval(wi, wo, {"ks": 0.4, "alpha": 0.5})
    )
    np.testing.assert_allclose(m.eval(wi, wo, p), ref, rtol=1e-14)
    a_ref = (
        get_model("lambert").albedo(0.4, {"albedo": 0.3})
        + get_model("ggx").albedo(0.4, {"ks": 0.2, "alpha": 0.05})
        + get_model("ggx").albedo(0.4, {"ks": 0.4, "alpha": 0.5})
    )
    assert m.albedo(0.4, p) == pytest.approx(a_ref, rel=1e-14)


def test_conductor_fresnel_is_continuous_down_to_a_vanishing_index():
    """eta = 0 with k so small that n^2 is subnormal (hypothesis found k = 6.1e-156 at
    normal incidence): the reflectance is the n = 0 limit, 1, not NaN from 0/0, and the
    BRDF is continuous in k down to 0."""
    from gonio.brdf.fresnel import fresnel_complex

    for k in (6.149631732925564e-156, 1e-160, 1e-150, 0.0):
        F, _, _ = fresnel_complex(np.array([1.0, 0.5, 0.0]), np.array(0.0), np.array(k))
        np.testing.assert_allclose(F, 1.0, rtol=1e-12)
    m = get_model("beckmann", fresnel="conductor")
    n = np.array([0.0, 0.0, 1.0])
    p = {"ks": 0.5, "alpha": 1.0, "eta": 0.0}
    vals = [float(m.eval(n, n, p | {"k": k})) for k in (0.0, 6.149631732925564e-156, 1e-3)]
    assert all(np.isfinite(vals))
    np.testing.assert_allclose(vals, vals[0], rtol=1e-9)
