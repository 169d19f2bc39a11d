"""Mitsuba 3 (``scalar_rgb``) as an independent oracle for ``lambert``, ``ggx``, ``beckmann``.

Mitsuba returns ``f_r * cos(theta_o)`` computed in float32; we compare ``eval * wo_z`` on
float32-rounded directions.  Each configuration uses 10^4 direction pairs up to
theta = 89.5 deg: half uniform over the hemisphere (mostly lobe tails), half near the
mirror direction (microfacet normal drawn at the lobe's scale), so the peak is covered
even for alpha = 0.01.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gonio.brdf import get_model

pytestmark = [pytest.mark.slow, pytest.mark.mitsuba]

N_PAIRS = 10_000
ALPHAS = (0.01, 0.05, 0.2, 0.5)
COS_MIN = math.cos(math.radians(89.5))
RTOL = 1e-5


@pytest.fixture(scope="module")
def mi(tmp_path_factory):
    import os

    os.environ.setdefault("DRJIT_CACHE_DIR", str(tmp_path_factory.mktemp("drjit")))
    from gonio.mitsuba_oracle import load_mitsuba

    try:
        mi, variant = load_mitsuba("scalar")
    except ImportError as exc:
        pytest.skip(str(exc))
    import drjit as dr

    dr.set_thread_count(1)
    assert variant == "scalar_rgb"
    return mi


def _uniform(rng, n):
    ct = rng.uniform(COS_MIN, 1.0, n)
    ph = rng.uniform(0.0, 2 * math.pi, n)
    st = np.sqrt(1.0 - ct * ct)
    return np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=-1)


def _pairs(rng, alpha):
    """Half uniform pairs, half with wo reflected about a normal tilted by ~alpha."""
    n = N_PAIRS // 2
    wi_u, wo_u = _uniform(rng, n), _uniform(rng, n)
    wi_s, wo_s = [], []
    while sum(len(a) for a in wi_s) < n:
        wi = _uniform(rng, n)
        t = alpha * np.abs(rng.standard_normal(n)) * rng.choice([0.3, 1.0, 3.0], n)
        ph = rng.uniform(0.0, 2 * math.pi, n)
        h = np.stack([np.sin(np.arctan(t)) * np.cos(ph), np.sin(np.arctan(t)) * np.sin(ph)], -1)
        h = np.concatenate([h, np.cos(np.arctan(t))[:, None]], axis=-1)
        wo = 2.0 * np.sum(wi * h, axis=-1, keepdims=True) * h - wi
        ok = wo[:, 2] > COS_MIN
        wi_s.append(wi[ok])
        wo_s.append(wo[ok])
    wi = np.concatenate([wi_u, np.concatenate(wi_s)[:n]])
    wo = np.concatenate([wo_u, np.concatenate(wo_s)[:n]])
    # Mitsuba computes in float32: give both sides the same float32-rounded directions.
    return wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64)


def _mitsuba_eval(mi, bsdf, wi, wo):
    ctx = mi.BSDFContext()
    out = np.empty((len(wi), 3))
    for i in range(len(wi)):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*wi[i])
        out[i] = np.array(bsdf.eval(ctx, si, mi.Vector3f(*wo[i])))
    return out


def test_lambert_matches_mitsuba_diffuse(mi):
    rng = np.random.default_rng(11)
    wi, wo = _uniform(rng, N_PAIRS), _uniform(rng, N_PAIRS)
    wi, wo = wi.astype(np.float32).astype(float), wo.astype(np.float32).astype(float)
    rgb = [0.2, 0.5, 0.8]
    ref = _mitsuba_eval(
        mi, mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}), wi, wo
    )
    ours = get_model("lambert").eval(wi[:, None, :], wo[:, None, :], {"albedo": np.array(rgb)})
    ours = ours * wo[:, 2:3]
    np.testing.assert_allclose(ours, ref, rtol=RTOL, atol=0)


def _check(ours, ref, tol_extra=None):
    """Relative error <= RTOL (+ tol_extra) where Mitsuba is non-zero; return max rel."""
    pos = ref > 0
    rel = np.abs(ours[pos] - ref[pos]) / ref[pos]
    tol = RTOL if tol_extra is None else RTOL + np.broadcast_to(tol_extra, ref.shape)[pos]
    worst = np.argmax(rel - tol)
    assert np.all(rel <= tol), f"max rel error {rel.max():.3g} (worst excess at {worst})"
    return rel.max()


@pytest.mark.parametrize("fresnel", ["none", "Au"])
@pytest.mark.parametrize("alpha", ALPHAS)
def test_ggx_matches_mitsuba_roughconductor(mi, alpha, fresnel):
    rng = np.random.default_rng(int(alpha * 1000) + (fresnel == "Au"))
    wi, wo = _pairs(rng, alpha)
    spec = {"type": "roughconductor", "distribution": "ggx", "alpha": alpha}
    if fresnel == "Au":
        spec["material"] = "Au"
    bsdf = mi.load_dict(spec)
    ref = _mitsuba_eval(mi, bsdf, wi, wo)
    ours = _ours("ggx", {}, mi, bsdf, alpha, fresnel, wi, wo)
    assert np.all(ref > 0)  # GGX tails never underflow here: every pair is compared
    _check(ours, ref)


@pytest.mark.parametrize("fresnel", ["none", "Au"])
@pytest.mark.parametrize("alpha", ALPHAS)
def test_beckmann_rational_matches_mitsuba_roughconductor(mi, alpha, fresnel):
    rng = np.random.default_rng(int(alpha * 1000) + 7 + (fresnel == "Au"))
    wi, wo = _pairs(rng, alpha)
    spec = {"type": "roughconductor", "distribution": "beckmann", "alpha": alpha}
    if fresnel == "Au":
        spec["material"] = "Au"
    bsdf = mi.load_dict(spec)
    ref = _mitsuba_eval(mi, bsdf, wi, wo)
    ours = _ours("beckmann", {"g1": "rational"}, mi, bsdf, alpha, fresnel, wi, wo)
    # Mitsuba zeroes its microfacet density where D cos(theta_h) < 1e-20 (float32 guard
    # in MicrofacetDistribution::eval): there we only require our value to be that small.
    zero = ref == 0
    h = wi + wo
    cos_h = h[:, 2] / np.linalg.norm(h, axis=-1)
    assert np.all(ours[zero] <= 1.01e-20 / (4 * cos_h[:, None] * wi[:, 2:3]).repeat(3, 1)[zero])
    assert (~zero).sum() > N_PAIRS // 2  # the near-mirror half is always compared
    # The float32 oracle evaluates exp(-x), x = tan^2(theta_h) / alpha^2, with an absolute
    # error of a few float32 ulps of x, i.e. a relative error ~ x * 2^-23 per ulp that
    # grows to ~1.6e-5 in the far tail (x ~ 50, f ~ 1e-20).  Allow 8 ulps of x on top.
    x = ((h[:, 0] ** 2 + h[:, 1] ** 2) / h[:, 2] ** 2 / alpha**2)[:, None]
    _check(ours, ref, tol_extra=8 * 2.0**-23 * x)
    # and the plain 1e-5 where the oracle's own exponent error is below 1e-6 (x <= 2):
    near = np.broadcast_to(x <= 2.0, ref.shape)
    assert near[:, 0].sum() > 1000
    _check(np.where(near, ours, 1.0), np.where(near, ref, 1.0))


def _ours(name, options, mi, bsdf, alpha, fresnel, wi, wo):
    if fresnel == "Au":
        # Mitsuba's own RGB eta and k for 'Au', read from the loaded plugin (its spectral
        # data as converted to RGB by Mitsuba), not typed in: eta ~ (0.143, 0.375, 1.442),
        # k ~ (3.983, 2.386, 1.603).
        params = mi.traverse(bsdf)
        eta = np.array(params["eta.value"], dtype=float).ravel()
        k = np.array(params["k.value"], dtype=float).ravel()
        assert eta.shape == (3,) and np.all(k > 1.0)
        m = get_model(name, fresnel="conductor", **options)
        f = m.eval(wi[:, None, :], wo[:, None, :], {"ks": 1.0, "alpha": alpha, "eta": eta, "k": k})
    else:
        m = get_model(name, **options)
        f = np.repeat(m.eval(wi, wo, {"ks": 1.0, "alpha": alpha})[:, None], 3, axis=1)
    return f * wo[:, 2:3]
