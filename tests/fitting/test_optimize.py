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


@pytest.mark.parametrize("K", [1, 2])
def test_box_qp_with_one_or_two_parameters_matches_scipy_lsq_linear(K):
    # K <= 2 takes the edge solver (the minimiser on the box's edges), not enumeration
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(K)
    n_active = 0
    for _ in range(200):
        A = rng.standard_normal((20, K)) * np.array([1.0, 1e3])[:K]
        y = rng.standard_normal(20) * rng.uniform(0.1, 10)
        lo = np.where(rng.random(K) < 0.2, -np.inf, rng.uniform(-1, 0, K))
        hi = np.where(rng.random(K) < 0.2, np.inf, rng.uniform(0, 1, K) * np.array([1, 1e-3])[:K])
        a = solve_box_qp((A.T @ A)[None], (A.T @ y)[None], lo, hi)[0]
        ref = lsq_linear(A, y, bounds=(lo, hi), tol=1e-14).x
        assert np.all((a >= lo) & (a <= hi))
        c = 0.5 * np.sum((A @ a - y) ** 2)
        cref = 0.5 * np.sum((A @ ref - y) ** 2)
        assert c <= cref * (1 + 1e-9) + 1e-15
        n_active += bool(np.any((a == lo) | (a == hi)))
    assert n_active > 50  # the bounds were active in many of the problems


@pytest.mark.parametrize("d", [1, 2])
@pytest.mark.parametrize("seed", [0, 7])
def test_sobol_design_is_scipys_scrambled_sobol_bit_for_bit(d, seed):
    from scipy.stats import qmc

    lb, ub = np.array([-9.2, 0.0])[:d], np.array([0.0, 1.0])[:d]
    for n in (2, 16, 64, 1024):
        ref = qmc.scale(
            qmc.Sobol(d, scramble=True, seed=seed).random_base2(int(np.log2(n))), lb, ub
        )
        assert np.array_equal(sobol_design(lb, ub, n, seed=seed), ref)


def test_one_dimensional_search_stops_at_the_minimum_with_few_evaluations():
    # c(u) = cosh(u - 1.3) + 0.1 u^2: minimum where sinh(u - 1.3) + 0.2 u = 0
    from scipy.optimize import brentq

    u_star = brentq(lambda u: np.sinh(u - 1.3) + 0.2 * u, -5, 5, xtol=1e-15)
    seen = []

    def fun(u, want):
        seen.append(float(u[0]))
        return np.cosh(u[0] - 1.3) + 0.1 * u[0] ** 2, np.array([np.sinh(u[0] - 1.3) + 0.2 * u[0]])

    r = nlopt_minimize(fun, np.array([-2.0]), np.array([-5.0]), np.array([5.0]), "LD_LBFGS")
    assert r.success
    assert abs(r.x[0] - u_star) <= 1e-9 * max(1.0, abs(u_star))
    assert r.nfev == len(seen) < 30
    # a minimum on a bound is left to nlopt (no secant step outside the box)
    r = nlopt_minimize(fun, np.array([-2.0]), np.array([-5.0]), np.array([0.5]), "LD_LBFGS")
    assert r.x[0] == 0.5


def test_secant_stop_predicts_the_newton_step_of_a_quadratic():
    from gonio.fitting.optimize import _SecantStop

    # c = 0.5 k (u - m)^2: gradient k (u - m); the secant of two gradients is exact
    k, m = 4.0e8, -1.9

    def feed(stop, us):
        out = False
        for u in us:
            x = np.array([u])
            c = 0.5 * k * (u - m) ** 2
            out = stop.converged(x, np.array([k * (u - m)]), c, c)  # c: the best so far
        return out

    assert feed(_SecantStop(1e-9, [-5.0], [0.0]), [m + 1e-6, m + 1e-12])  # next step 1e-12
    assert not feed(_SecantStop(1e-9, [-5.0], [0.0]), [m + 1e-6, m + 1e-7])  # 1e-7 to go
    assert not feed(_SecantStop(1e-9, [-5.0], [0.0]), [m + 0.5, m + 1e-12])  # not local
    assert not feed(_SecantStop(1e-9, [-1.0], [0.0]), [-1.0, -1.0 + 1e-12])  # m outside
    # concave along the step: no prediction
    stop = _SecantStop(1e-9, [-5.0], [0.0])
    stop.converged(np.array([m]), np.array([1.0]), 0.0, 0.0)
    assert not stop.converged(np.array([m + 1e-12]), np.array([0.5]), 0.0, 0.0)


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


def test_preconditioned_search_takes_newtons_step_first():
    # c = 0.5 k (u - m)^2 + 0.01 k (u - m)^4 from u = 0: unscaled, L-BFGS's first step is
    # the gradient itself (k = 1e8: far past the bound); with x_scale = sqrt(c''(0)) it is
    # Newton's step, and the search ends at the same minimum in fewer evaluations
    k, m = 1.0e8, -1.9

    def run(x_scale):
        seen = []

        def fun(u, want):
            d = u[0] - m
            seen.append(float(u[0]))
            return 0.5 * k * d * d + 0.01 * k * d**4, np.array([k * d + 0.04 * k * d**3])

        lo, hi = np.array([-5.0]), np.array([0.5])
        return nlopt_minimize(fun, np.array([0.0]), lo, hi, "LD_LBFGS", x_scale=x_scale), seen

    curv0 = k + 0.12 * k * m * m  # c''(0)
    r1, seen1 = run(np.array([np.sqrt(curv0)]))
    r0, seen0 = run(None)
    assert seen1[0] == 0.0 and seen0[0] == 0.0  # the start itself, exactly
    g0 = k * (0 - m) + 0.04 * k * (0 - m) ** 3
    assert seen1[1] == pytest.approx(-g0 / curv0, rel=1e-12)  # Newton's step from 0
    assert seen0[1] == -5.0  # the unscaled step: to the lower bound
    for r in (r0, r1):
        assert r.success and abs(r.x[0] - m) <= 1e-9 * abs(m)
    assert len(seen1) < len(seen0)
    # a scale that is not finite and positive is ignored (the search is the unscaled one)
    r2, seen2 = run(np.array([np.nan]))
    assert seen2 == seen0 and r2.x[0] == r0.x[0]


def test_row_helpers_are_numpys_reductions_bit_for_bit():
    from gonio.fitting.objective import _row_norm, _rows_all

    rng = np.random.default_rng(0)
    v = rng.standard_normal((10_000, 3)) * 10.0 ** rng.integers(-3, 3, (10_000, 1))
    assert np.array_equal(_row_norm(v), np.linalg.norm(v, axis=1))
    mask = rng.random((10_000, 3)) > 0.1
    assert np.array_equal(_rows_all(mask), np.all(mask, axis=1))
    assert np.array_equal(_rows_all(np.ones((4, 0), bool)), np.ones(4, bool))
