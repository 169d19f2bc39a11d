"""The fused fitting kernels (gonio.fitting.kernels) against the numpy path they replace.

The numpy variable projection (``GONIO_NUMBA=0``) evaluates the model's own analytic
gradient (``Model.eval_with_grad``, held to finite differences in tests/brdf) and solves
the normal equations with BLAS; the kernels recompute the microfacet basis and sums
themselves.  Each check below fails if a kernel formula, a block sum or the coupling of
alpha to ks is wrong.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from gonio.brdf import get_model
from gonio.fitting import fit
from gonio.fitting import kernels as k
from gonio.fitting.losses import get_loss
from gonio.fitting.objective import prepare_problem
from gonio.fitting.varpro import VarPro

TRUTH = {"albedo": [0.2, 0.4, 0.0], "ks": [0.1, 0.2, 0.3], "alpha": [0.15] * 3}


def _directions(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random pairs over the hemisphere to 89 deg, half of them near the mirror."""
    rng = np.random.default_rng(seed)

    def cap(m: int) -> np.ndarray:
        z = np.cos(np.radians(89.0)) + (1 - np.cos(np.radians(89.0))) * rng.random(m)
        p = 2 * np.pi * rng.random(m)
        r = np.sqrt(1 - z * z)
        return np.stack([r * np.cos(p), r * np.sin(p), z], axis=-1)

    wi, wo = cap(n), cap(n)
    h = np.column_stack([0.2 * rng.standard_normal((n // 2, 2)), np.ones(n // 2)])
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    mirror = 2 * np.sum(wi[: n // 2] * h, axis=1, keepdims=True) * h - wi[: n // 2]
    ok = mirror[:, 2] > 0.01
    wo[: n // 2][ok] = mirror[ok]
    return wi, wo


@pytest.mark.parametrize(
    "model,options,dist,g1",
    [
        ("lambert+ggx", {}, k.DIST_GGX, k.G1_EXACT),
        ("lambert+beckmann", {}, k.DIST_BECKMANN, k.G1_EXACT),
        ("lambert+beckmann", {"g1": "rational"}, k.DIST_BECKMANN, k.G1_RATIONAL),
    ],
)
@pytest.mark.parametrize("alpha", [2e-3, 0.15, 0.9])
def test_basis_is_the_models_ks_gradient_and_alpha_derivative(model, options, dist, g1, alpha):
    wi, wo = _directions(3000, 1)
    wi[0] = wo[0] = [0.0, 0.0, 1.0]  # the normal: 0/0-free forms in both paths
    m = get_model(model, **options)
    _, g = m.eval_with_grad(wi, wo, {"albedo": 1.0, "ks": 1.0, "alpha": alpha})
    G = np.empty((len(wi), 2))
    dG = np.empty((len(wi), 1))
    k.basis_microfacet(wi, wo, alpha, dist, g1, G, 1, dG)
    np.testing.assert_allclose(G[:, 1], g["ks"], rtol=1e-12, atol=0)
    np.testing.assert_allclose(dG[:, 0], g["alpha"], rtol=1e-9, atol=1e-300)


def test_normal_equations_and_cost_match_dense_numpy():
    rng = np.random.default_rng(2)
    n, K, C = 10_001, 3, 2  # not a multiple of BLOCK; the generic K (not 2) branch
    G = rng.random((n, K))
    dG = rng.standard_normal((n, 2))
    w2 = rng.random((n, C))
    y = rng.random((n, C))
    H = np.empty((C, K, K))
    b = np.empty((C, K))
    k.normal_equations(G, w2, w2 * y, H, b)
    for c in range(C):
        np.testing.assert_allclose(H[c], (G * w2[:, c, None]).T @ G, rtol=1e-12)
        np.testing.assert_allclose(b[c], G.T @ (w2[:, c] * y[:, c]), rtol=1e-12)
    a = rng.random((K, C))
    coupling = np.array([2, 0], dtype=np.int64)
    grad = np.empty(2)
    cost = k.cost_grad(G, dG, coupling, a, w2, y, grad)
    r = G @ a - y
    np.testing.assert_allclose(cost, 0.5 * np.sum(w2 * r * r), rtol=1e-12)
    want = [np.sum(w2 * r * dG[:, s, None] * a[coupling[s]][None, :]) for s in range(2)]
    np.testing.assert_allclose(grad, want, rtol=1e-10)
    # the serial twins (small problems) give the same bits as the threaded kernels
    H2, b2, grad2 = np.empty_like(H), np.empty_like(b), np.empty(2)
    k.normal_equations_serial(G, w2, w2 * y, H2, b2)
    assert np.array_equal(H2, H) and np.array_equal(b2, b)
    assert k.cost_grad_serial(G, dG, coupling, a, w2, y, grad2) == cost
    assert np.array_equal(grad2, grad)
    wi, wo = _directions(n, 3)
    B1, B2, d1, d2 = (np.zeros((n, 2)), np.zeros((n, 2)), np.zeros((n, 1)), np.zeros((n, 1)))
    k.basis_microfacet(wi, wo, 0.2, k.DIST_GGX, k.G1_EXACT, B1, 1, d1)
    k.basis_microfacet_serial(wi, wo, 0.2, k.DIST_GGX, k.G1_EXACT, B2, 1, d2)
    assert np.array_equal(B1, B2) and np.array_equal(d1, d2)


def test_reduced_cost_gradient_and_linear_parameters_match_the_numpy_path(
    monkeypatch, make_samples
):
    s = make_samples("lambert+ggx", TRUTH, n=60_000, seed=3, noise=1e-4, read=1e-3)
    prob = prepare_problem(get_model("lambert+ggx"), s, get_loss("weighted_l2"))
    fused = VarPro(prob)
    assert fused._fused is not None  # 60000 samples: the kernels are used
    monkeypatch.setenv("GONIO_NUMBA", "0")
    ref = VarPro(prob)
    assert ref._fused is None
    for alpha in (0.01, 0.15, 0.6):  # blue albedo 0: the bound is active in the QP
        u = np.log([alpha])
        c1, g1, a1 = fused.evaluate(u)
        c0, g0, a0 = ref.evaluate(u)
        np.testing.assert_allclose(c1, c0, rtol=1e-12)
        np.testing.assert_allclose(g1, g0, rtol=1e-8, atol=1e-9 * abs(c0))
        np.testing.assert_allclose(a1, a0, rtol=1e-10, atol=1e-13)


def test_one_thread_and_all_threads_give_the_same_bits(make_samples):
    s = make_samples("lambert+beckmann", TRUTH, n=60_000, seed=4, noise=1e-4, read=1e-3)
    vp = VarPro(prepare_problem(get_model("lambert+beckmann"), s, get_loss("weighted_l2")))
    u = np.log([0.2])
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = vp._fused.evaluate(u)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = vp._fused.evaluate(u)
    finally:
        numba.set_num_threads(before)
    assert one[0] == many[0]
    assert np.array_equal(one[1], many[1]) and np.array_equal(one[2], many[2])


def test_whole_fit_equals_the_numpy_fit(monkeypatch, make_samples):
    s = make_samples("lambert+ggx", TRUTH, n=60_000, seed=5, noise=1e-4, read=1e-3)
    r1 = fit(s, "lambert+ggx")
    monkeypatch.setenv("GONIO_NUMBA", "0")
    r0 = fit(s, "lambert+ggx")
    np.testing.assert_allclose(r1.cost, r0.cost, rtol=1e-12)
    for name in ("albedo", "ks", "alpha"):
        np.testing.assert_allclose(r1.params[name], r0.params[name], rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(r1.params["alpha"], 0.15, rtol=0.01)  # and near the truth


def test_gauss_newton_sums_match_dense_numpy():
    rng = np.random.default_rng(6)
    for n, K, S in ((10_001, 2, 1), (5_000, 3, 2)):  # the register branch and the generic one
        G, dG, w2 = rng.random((n, K)), rng.standard_normal((n, S)), rng.random((n, 3))
        H, D, E = np.empty((3, K, K)), np.empty((3, S, K)), np.empty((3, S, S))
        k.gauss_newton_sums(G, dG, w2, H, D, E)
        for c in range(3):
            np.testing.assert_allclose(H[c], (G * w2[:, c, None]).T @ G, rtol=1e-12)
            np.testing.assert_allclose(D[c], (dG * w2[:, c, None]).T @ G, rtol=1e-12)
            np.testing.assert_allclose(E[c], (dG * w2[:, c, None]).T @ dG, rtol=1e-12)
        H2, D2, E2 = np.empty_like(H), np.empty_like(D), np.empty_like(E)
        k.gauss_newton_sums_serial(G, dG, w2, H2, D2, E2)
        assert np.array_equal(H, H2) and np.array_equal(D, D2) and np.array_equal(E, E2)


def test_covariance_from_the_kernels_sums_is_the_models(make_samples):
    # the fused path's J^T J (VarPro.jtj) against covariance_at's own, formed from the
    # model's numpy gradients (Problem.jacobian_blocks)
    from gonio.fitting.uncertainty import _jtj_of_blocks, covariance_at

    s = make_samples("lambert+ggx", TRUTH, n=60_000, seed=7, noise=1e-4, read=1e-3)
    prob = prepare_problem(get_model("lambert+ggx"), s, get_loss("weighted_l2"))
    vp = VarPro(prob)
    assert vp._fused is not None
    x = prob.pack(np.array([0.17]), np.array([[0.21, 0.38, 0.01], [0.11, 0.19, 0.31]]))
    jtj = vp.jtj(x)
    fast = covariance_at(prob, x, True, jtj)
    ref = covariance_at(prob, x, True)
    np.testing.assert_allclose(fast.cost, ref.cost, rtol=1e-13)
    np.testing.assert_allclose(fast.residuals, ref.residuals, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(fast.covariance, ref.covariance, rtol=1e-10, atol=1e-20)
    np.testing.assert_allclose(jtj[1], _jtj_of_blocks(prob, x)[1], rtol=1e-12)


@pytest.mark.parametrize("numba_path", [True, False])
def test_curvature_is_the_reduced_costs_second_derivative_at_an_exact_fit(
    monkeypatch, make_samples, numba_path
):
    # noise-free samples at the truth: the residuals vanish, so the Gauss-Newton
    # curvature of the reduced cost is its exact second derivative (central differences
    # of the exact reduced gradient as the reference)
    if not numba_path:
        monkeypatch.setenv("GONIO_NUMBA", "0")
    truth = {"albedo": [0.2, 0.4, 0.3], "ks": [0.1, 0.2, 0.3], "alpha": [0.15] * 3}
    s = make_samples("lambert+ggx", truth, n=60_000, seed=8)
    prob = prepare_problem(get_model("lambert+ggx"), s, get_loss("l2"))
    vp = VarPro(prob)
    assert (vp._fused is not None) == numba_path
    u = np.log([0.15])
    h = 1e-4
    fd = (vp.evaluate(u + h)[1][0] - vp.evaluate(u - h)[1][0]) / (2 * h)
    curv = vp.curvature(u)
    np.testing.assert_allclose(curv, [fd], rtol=1e-6)
    # off the minimum the reduced cost's slope term (u = ln alpha) is in it too, and the
    # estimate stays positive and of the right size
    c2 = vp.curvature(u + 0.5)
    fd2 = (vp.evaluate(u + 0.5 + h)[1][0] - vp.evaluate(u + 0.5 - h)[1][0]) / (2 * h)
    assert 0.3 * fd2 < c2[0] < 3 * fd2
