"""Directional albedo against closed forms and independent scipy quadrature.

References, none of which uses ``gonio.brdf.albedo``:
- closed forms: Lambert (= albedo), modified Phong at normal incidence (= ks),
  Ashikhmin-Shirley Blinn-Phong at normal incidence (polynomial integral below);
- 1-D scipy quadrature at normal incidence (GGX, Beckmann; anisotropic Ward with the
  azimuthal integral in closed form through the Bessel function I0);
- 2-D adaptive scipy quadrature over (theta_o, phi_o) of ``f cos`` for oblique incidence,
  and over the half vector with a breakpoint at the lobe width for near-mirror lobes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, special

from gonio.brdf import get_model

DEG = math.pi / 180


@pytest.mark.parametrize("theta_deg", [0.0, 30.0, 60.0, 85.0, 89.9])
def test_lambert_albedo_is_its_albedo(theta_deg):
    a = get_model("lambert").albedo(theta_deg * DEG, {"albedo": 0.7})
    assert a == pytest.approx(0.7, rel=1e-9)


@pytest.mark.parametrize("n", [0.0, 1.0, 20.0, 1e3, 1e6])
def test_phong_albedo_at_normal_incidence_is_ks(n):
    # (n+2)/(2 pi) int cos^n(a) cos(a) dw over the hemisphere around the normal = 1
    assert get_model("phong").albedo(0.0, {"ks": 0.8, "n": n}) == pytest.approx(0.8, rel=1e-9)


@pytest.mark.parametrize("n", [0.0, 10.0, 1e3, 1e6])
def test_blinn_phong_albedo_at_normal_incidence_closed_form(n):
    # theta_i = 0: theta_o = 2 theta_h, dwo = 4 cos(theta_h) dh, max(cos_i, cos_o) = 1:
    # a = ks (n+1) int_{1/sqrt2}^1 c^n (2c^2 - 1) dc
    ref = (n + 1) * (2 * (1 - 2 ** (-(n + 3) / 2)) / (n + 3) - (1 - 2 ** (-(n + 1) / 2)) / (n + 1))
    got = get_model("blinn-phong").albedo(0.0, {"ks": 1.0, "n": n})
    assert got == pytest.approx(ref, rel=1e-9)


def _normal_incidence_microfacet(kind, alpha):
    """2 pi int_0^{pi/4} D(th) G1(2 th) cos(th) sin(th) dth (G1(wi = n) = 1)."""

    def d(t):
        tan2 = math.tan(t) ** 2
        c4 = math.cos(t) ** 4
        if kind == "ggx":
            return alpha**2 / (math.pi * c4 * (alpha**2 + tan2) ** 2)
        return math.exp(-tan2 / alpha**2) / (math.pi * alpha**2 * c4)

    def g1(theta):
        if kind == "ggx":
            return 2.0 / (1.0 + math.sqrt(1.0 + alpha**2 * math.tan(theta) ** 2))
        a = 1.0 / (alpha * math.tan(theta))
        lam = (math.erf(a) - 1) / 2 + math.exp(-a * a) / (2 * a * math.sqrt(math.pi))
        return 1.0 / (1.0 + lam)

    def f(t):
        return 2 * math.pi * d(t) * g1(2 * t) * math.cos(t) * math.sin(t)

    w = math.atan(alpha)
    pts = [p for p in (w / 4, w, 4 * w, 16 * w) if p < math.pi / 4]
    return integrate.quad(f, 0, math.pi / 4, points=pts, limit=500, epsabs=0, epsrel=1e-12)[0]


@pytest.mark.parametrize("kind", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [1e-4, 1e-3, 0.05, 0.3, 1.0])
def test_microfacet_albedo_at_normal_incidence(kind, alpha):
    ref = _normal_incidence_microfacet(kind, alpha)
    assert get_model(kind).albedo(0.0, {"ks": 1.0, "alpha": alpha}) == pytest.approx(ref, rel=1e-9)


@pytest.mark.parametrize("ax, ay", [(0.01, 0.5), (0.2, 0.01), (0.3, 0.3), (1e-3, 0.05)])
def test_anisotropic_ward_albedo_at_normal_incidence(ax, ay):
    # Azimuthal integral of exp(-t^2 (cos^2/ax^2 + sin^2/ay^2)) = 2 pi e^{-t^2 A} I0(t^2 B).
    A = (1 / ax**2 + 1 / ay**2) / 2
    B = abs(1 / ax**2 - 1 / ay**2) / 2

    def g(th):
        t2 = math.tan(th) ** 2
        c = math.cos(th)
        azim = 2 * math.pi * math.exp(-t2 * (A - B)) * special.i0e(t2 * B)
        return azim / (math.pi * ax * ay * c**4) * math.cos(2 * th) / c * math.sin(th)

    w = math.atan(min(ax, ay))
    pts = [p for p in (w, 4 * w, 16 * w, 0.5) if p < math.pi / 4]
    ref = integrate.quad(g, 0, math.pi / 4, points=pts, limit=500, epsabs=0, epsrel=1e-12)[0]
    got = get_model("ward-aniso").albedo(0.0, {"ks": 1.0, "alpha_x": ax, "alpha_y": ay})
    assert got == pytest.approx(ref, rel=1e-8)


def _albedo_over_wo(m, p, theta_i, phi_i=0.0, width=None):
    """Adaptive cubature of f cos over (theta_o, phi_o), independent of the model's own
    quadrature; the box is split around the mirror direction at multiples of ``width``
    (rad) so that narrow lobes are found, and at theta_o = theta_i."""
    wi = np.array(
        [
            math.sin(theta_i) * math.cos(phi_i),
            math.sin(theta_i) * math.sin(phi_i),
            math.cos(theta_i),
        ]
    )

    def f(x):
        to, po = x[:, 0], x[:, 1]
        wo = np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], axis=-1)
        return m.eval(wi, wo, p) * np.cos(to) * np.sin(to)

    t_edges = {0.0, theta_i, math.pi / 2}
    p_edges = {phi_i, phi_i + math.pi, phi_i + 2 * math.pi}
    if width is not None:
        for s in (1, 4, 16, 64, 256):
            t_edges |= {min(max(theta_i + k * s * width, 0.0), math.pi / 2) for k in (-1, 1)}
            dp = s * width / max(math.sin(theta_i), 1e-3)
            p_edges |= {phi_i + math.pi + k * min(dp, math.pi) for k in (-1, 1)}
    te, pe = sorted(t_edges), sorted(p_edges)
    total = 0.0
    for a, b in zip(te[:-1], te[1:], strict=True):
        for c, d in zip(pe[:-1], pe[1:], strict=True):
            if b > a and d > c:
                r = integrate.cubature(f, [a, c], [b, d], rtol=1e-12, atol=1e-15)
                assert r.status == "converged"
                total += r.estimate
    return total


# Smooth lobes agree to ~1e-10; Oren-Nayar and Blinn-Phong have kinks (max()) inside the
# domain that cost the tensor Gauss rule accuracy: 1e-4 there.
OBLIQUE = [
    ("ggx", {}, {"ks": 1.0, "alpha": 0.2}, 60.0, 1e-8),
    ("ggx", {"fresnel": "conductor"}, {"ks": 1.0, "alpha": 0.5, "eta": 0.2, "k": 3.0}, 85.0, 1e-8),
    ("beckmann", {}, {"ks": 1.0, "alpha": 0.5}, 80.0, 1e-8),
    ("ward", {}, {"ks": 1.0, "alpha": 0.3}, 70.0, 1e-8),
    ("phong", {}, {"ks": 1.0, "n": 20.0}, 45.0, 1e-8),
    ("oren-nayar", {}, {"albedo": 0.9, "sigma": 0.5}, 70.0, 1e-4),
    ("blinn-phong", {}, {"ks": 1.0, "n": 10.0}, 60.0, 1e-4),
]


@pytest.mark.slow
@pytest.mark.parametrize("name, options, p, theta_deg, rtol", OBLIQUE, ids=[c[0] for c in OBLIQUE])
def test_albedo_oblique_matches_adaptive_quadrature(name, options, p, theta_deg, rtol):
    m = get_model(name, **options)
    ref = _albedo_over_wo(m, p, theta_deg * DEG)
    assert m.albedo(theta_deg * DEG, p) == pytest.approx(ref, rel=rtol)


@pytest.mark.slow
def test_anisotropic_albedo_oblique_matches_adaptive_quadrature():
    m = get_model("ward-aniso")
    p = {"ks": 1.0, "alpha_x": 0.1, "alpha_y": 0.4}
    ref = _albedo_over_wo(m, p, 50 * DEG, phi_i=0.3)
    # the psi-mapped azimuthal rule is less exact than the isotropic one: ~1e-8 measured
    assert m.albedo(50 * DEG, p, phi_i=0.3) == pytest.approx(ref, rel=1e-7)


@pytest.mark.slow
@pytest.mark.parametrize("alpha, theta_deg", [(1e-3, 75.0), (1e-2, 30.0)])
def test_near_mirror_albedo_matches_adaptive_quadrature(alpha, theta_deg):
    """Near-mirror lobes (a plain theta/phi grid misses them), gold-like conductor
    Fresnel; the reference cubature is split around the mirror direction."""
    m = get_model("ggx", fresnel="conductor")
    p = {"ks": 1.0, "alpha": alpha, "eta": 0.143, "k": 3.983}
    ref = _albedo_over_wo(m, p, theta_deg * DEG, width=2 * alpha)
    assert m.albedo(theta_deg * DEG, p) == pytest.approx(ref, rel=1e-8)


def test_albedo_shapes_and_edges():
    m = get_model("ggx")
    a = m.albedo(np.array([[0.0], [0.5]]), {"alpha": np.array([0.1, 0.2, 0.3])})
    assert a.shape == (2, 3)
    assert m.albedo(math.pi / 2, {}) == 0.0  # incidence in the horizon plane
    assert m.albedo(2.0, {}) == 0.0  # below the horizon
    assert np.isnan(m.albedo(np.nan, {}))
