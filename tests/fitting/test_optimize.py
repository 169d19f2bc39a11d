"""The nlopt driver: NaN results are caught, nlopt's empty exceptions become FitError."""

from __future__ import annotations

import numpy as np
import pytest

from gonio.errors import FitError, UnknownNameError
from gonio.fitting.optimize import nlopt_minimize, sobol_design
from gonio.fitting.varpro import solve_box_qp


def _rosen(x, want):
    f = (1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2
    g = np.array([-2 * (1 - x[0]) - 400 * x[0] * (x[1] - x[0] ** 2), 200 * (x[1] - x[0] ** 2)])
    return f, g


@pytest.mark.parametrize("alg", ["LD_LBFGS", "LD_SLSQP", "LD_MMA", "LN_BOBYQA"])
def test_local_algorithms_find_the_rosenbrock_minimum(alg):
    r = nlopt_minimize(
        _rosen,
        np.array([-1.2, 1.0]),
        np.array([-2.0, -2.0]),
        np.array([2.0, 2.0]),
        alg,
        maxeval=5000,
    )
    assert r.success
    np.testing.assert_allclose(r.x, [1.0, 1.0], atol=1e-3)


@pytest.mark.parametrize("alg", ["LD_SLSQP", "LD_MMA", "LN_BOBYQA", "GN_CRS2_LM", "LD_LBFGS"])
def test_nan_objective_is_never_a_success(alg):
    def nan_everywhere_but_start(x, want):
        return float("nan"), np.full(2, np.nan)

    with pytest.raises(FitError, match="no finite cost"):
        nlopt_minimize(nan_everywhere_but_start, np.zeros(2), -np.ones(2), np.ones(2), alg)


def test_nan_region_keeps_best_finite_point():
    def half_nan(x, want):
        f, g = _rosen(x, want)
        return (float("nan"), g) if x[0] > 0.5 else (f, g)

    r = nlopt_minimize(
        half_nan, np.array([-1.2, 1.0]), -2 * np.ones(2), 2 * np.ones(2), "LN_BOBYQA", maxeval=500
    )
    assert np.isfinite(r.fun) and r.x[0] <= 0.5


def test_nlopt_errors_become_fit_errors():
    with pytest.raises(FitError, match="LD_LBFGS"):  # lower bound above upper bound
        nlopt_minimize(_rosen, np.zeros(2), np.ones(2), -np.ones(2), "LD_LBFGS")
    with pytest.raises(UnknownNameError, match="GN_NOPE"):
        nlopt_minimize(_rosen, np.zeros(2), -np.ones(2), np.ones(2), "GN_NOPE")


def test_box_qp_matches_scipy_lsq_linear():
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(0)
    for _ in range(50):
        A = rng.standard_normal((30, 3)) * np.array([1.0, 1e3, 1e-2])
        y = rng.standard_normal(30)
        lo, hi = np.array([0.0, 0.0, -1.0]), np.array([1.0, np.inf, 1.0])
        a = solve_box_qp((A.T @ A)[None], (A.T @ y)[None], lo, hi)[0]
        ref = lsq_linear(A, y, bounds=(lo, hi), tol=1e-14).x
        c = 0.5 * np.sum((A @ a - y) ** 2)
        cref = 0.5 * np.sum((A @ ref - y) ** 2)
        assert c <= cref * (1 + 1e-9) + 1e-15


def test_sobol_design_fills_the_box():
    U = sobol_design(np.array([0.0, -1.0]), np.array([1.0, 1.0]), 16, seed=0)
    assert U.shape == (16, 2)
    assert np.all((U >= [0, -1]) & (U <= [1, 1]))


@pytest.mark.parametrize(
    "alg", ["LD_SLSQP", "LD_MMA", "LN_BOBYQA", "GN_DIRECT_L", "GN_CRS2_LM", "G_MLSL_LDS"]
)
def test_every_algorithm_reaches_the_default_cost(alg, make_samples):
    from gonio.fitting import fit

    s = make_samples(
        "lambert+ggx",
        {"albedo": [0.2, 0.4, 0.6], "ks": [0.1, 0.2, 0.3], "alpha": 0.1},
        n=100,
        seed=1,
        noise=1e-4,
        read=1e-3,
    )
    ref = fit(s, "lambert+ggx", energy_conservation=False)
    r = fit(s, "lambert+ggx", algorithm=alg, energy_conservation=False)
    assert r.success, r.message
    assert any(alg in step for step in r.algorithm)
    assert abs(r.cost - ref.cost) <= 1e-9 * ref.cost
