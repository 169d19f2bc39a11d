"""Smith G1 against numerical integration of Smith's Lambda (scipy.integrate).

Lambda is integrated from its definitions, independently of the closed forms in
``gonio.brdf.microfacet``:

- 1-D (Smith 1967; Walter et al. 2007): ``Lambda(theta) = 1/mu int_mu^inf (q - mu) P(q) dq``
  with ``mu = cot(theta)`` and ``P`` the marginal slope density (Beckmann: Gaussian of
  std ``alpha / sqrt 2``; GGX: ``(1 + q^2/alpha^2)^(-3/2) / (2 alpha)``);
- 2-D (Heitz 2014, eq. 72): ``Lambda(w) = 1/cos(theta) int <w, m>^- D(m) dm`` over the
  microfacet normals' hemisphere, with the normal distribution D itself.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from gonio.brdf.microfacet import beckmann_g1, ggx_g1


def _lambda_1d(theta, alpha, kind):
    mu = 1.0 / math.tan(theta)
    if kind == "beckmann":

        def p(q):
            return math.exp(-q * q / alpha**2) / (alpha * math.sqrt(math.pi))
    else:

        def p(q):
            return (1.0 + q * q / alpha**2) ** -1.5 / (2.0 * alpha)

    val, err = integrate.quad(lambda q: (q - mu) * p(q), mu, np.inf, epsabs=0, epsrel=1e-13)
    return val / mu


def _lambda_2d_beckmann(theta, alpha):
    w = np.array([math.sin(theta), 0.0, math.cos(theta)])

    def integrand(phi_m, theta_m):
        m = (math.sin(theta_m) * math.cos(phi_m), math.sin(theta_m) * math.sin(phi_m))
        c = math.cos(theta_m)
        d = math.exp(-(math.tan(theta_m) ** 2) / alpha**2) / (math.pi * alpha**2 * c**4)
        dot = w[0] * m[0] + w[2] * c
        return max(-dot, 0.0) * d * math.sin(theta_m)

    # <w, m> < 0 only for theta_m > pi/2 - theta, and only for |phi_m| > pi/2.
    val, _ = integrate.dblquad(
        integrand,
        math.pi / 2 - theta,
        math.pi / 2,
        math.pi / 2,
        3 * math.pi / 2,
        epsabs=1e-14,
        epsrel=1e-10,
    )
    return val / math.cos(theta)


def _g1(kind, theta, alpha, form="exact"):
    c, s2 = np.array(math.cos(theta)), np.array(math.sin(theta) ** 2)
    if kind == "beckmann":
        g, _ = beckmann_g1(c, s2, np.array(alpha), form)
    else:
        g, _ = ggx_g1(c, s2, np.array(alpha))
    return float(g) * math.cos(theta)  # the functions return G1 / cos


THETAS_DEG = [1.0, 20.0, 45.0, 70.0, 85.0, 89.0, 89.9]


@pytest.mark.parametrize("alpha", [0.01, 0.1, 0.3, 0.7, 1.0])
@pytest.mark.parametrize("theta_deg", THETAS_DEG)
def test_beckmann_exact_g1_matches_integrated_lambda(theta_deg, alpha):
    theta = math.radians(theta_deg)
    ref = 1.0 / (1.0 + _lambda_1d(theta, alpha, "beckmann"))
    assert _g1("beckmann", theta, alpha) == pytest.approx(ref, rel=1e-10, abs=1e-300)


@pytest.mark.parametrize("alpha", [0.01, 0.1, 0.3, 0.7, 1.0])
@pytest.mark.parametrize("theta_deg", THETAS_DEG)
def test_ggx_g1_matches_integrated_lambda(theta_deg, alpha):
    theta = math.radians(theta_deg)
    ref = 1.0 / (1.0 + _lambda_1d(theta, alpha, "ggx"))
    assert _g1("ggx", theta, alpha) == pytest.approx(ref, rel=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("theta_deg, alpha", [(60.0, 0.5), (80.0, 0.3), (88.0, 0.2)])
def test_beckmann_exact_g1_matches_lambda_over_microfacet_normals(theta_deg, alpha):
    theta = math.radians(theta_deg)
    ref = 1.0 / (1.0 + _lambda_2d_beckmann(theta, alpha))
    assert _g1("beckmann", theta, alpha) == pytest.approx(ref, rel=1e-8)


@pytest.mark.parametrize("theta_deg", [30.0, 60.0, 80.0, 89.0])
@pytest.mark.parametrize("alpha", [0.1, 0.5])
def test_beckmann_rational_g1_is_close_to_exact(theta_deg, alpha):
    # The rational fit is documented to within ~0.35% of the exact form (Walter 2007).
    theta = math.radians(theta_deg)
    exact = _g1("beckmann", theta, alpha)
    assert _g1("beckmann", theta, alpha, "rational") == pytest.approx(exact, rel=4e-3)


def test_g1_is_one_at_normal_incidence():
    for kind in ("beckmann", "ggx"):
        assert _g1(kind, 0.0, 0.5) == 1.0
