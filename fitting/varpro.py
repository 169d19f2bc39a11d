"""Variable projection: solve the linear parameters exactly inside the nonlinear search.

A BRDF model is ``f = sum_j a_j g_j(w; theta)`` in its linear parameters ``a`` (albedo,
ks).  For a linear loss ``r = w (f - y)`` the best ``a`` for given shape ``theta`` is a
small bound-constrained least-squares problem per channel, solved here exactly.  The
optimiser then searches only ``theta`` (one or two numbers for most models), on the
*reduced* cost ``c(theta) = min_a 0.5 |w (G(theta) a - y)|^2`` (Golub & Pereyra 1973).

Gradient: by the envelope theorem the derivative of the reduced cost is the partial
derivative of the full cost at fixed ``a = a*(theta)``; it holds with the bounds on ``a``
because they do not depend on ``theta`` (the value function of a strictly convex QP is
C^1), so ``dc/dtheta = sum w^2 (f - y) df/dtheta |_(a*)`` with no derivative of ``a*``.
"""

from __future__ import annotations

import itertools
import os
import sys
from typing import Any

import numpy as np

from gonio.fitting.objective import Problem

__all__ = ["VarPro", "solve_box_qp"]

# Largest number of linear parameters solved by active-set enumeration (3**K systems).
_ENUM_MAX = 4
# Elements of a model evaluation per chunk in batched design evaluations.
_CHUNK = 2_000_000
# Fits from this many samples import the numba kernels (~0.5 s once per process, which a
# `gonio fit` of a 5832-direction grid would not win back); once loaded, from 4096 on.
_FIRST_FUSED = 50_000


def solve_box_qp(H: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Minimise ``0.5 a^T H a - b^T a`` subject to ``lo <= a <= hi``, batched.

    Exact for the few (K <= 4) linear parameters of a BRDF model: the minimiser's free
    components solve the reduced normal equations for *some* assignment of every
    component to {free, lower, upper}, so trying all 3**K assignments and keeping the
    best feasible one finds it.  scipy's ``nnls``/``lsq_linear`` do the same work with
    a Python call per channel and per design point, which is what made this worth writing.

    Parameters
    ----------
    H : (B, K, K) symmetric positive semi-definite
    b : (B, K)
    lo, hi : (K,)  (``-inf`` / ``inf`` allowed)

    Returns
    -------
    a : (B, K)
    """
    B, K = b.shape
    if K == 0:
        return np.zeros((B, 0))
    # Jacobi scaling: basis functions differ by many orders of magnitude (a near-mirror
    # lobe peaks at 1e5 /sr, a Lambert term is 0.1 /sr), so the normal equations are
    # solved for a_s = d * a with unit diagonal.  A ridge at round-off level keeps the
    # solve defined when a basis function vanishes on all samples (its coefficient is 0).
    d = np.sqrt(np.clip(np.diagonal(H, axis1=1, axis2=2), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    H = H / (d[:, :, None] * d[:, None, :]) + 1e-14 * np.eye(K)
    b = b / d
    lo_s = lo[None, :] * d  # bounds of the scaled variables, per batch row
    hi_s = hi[None, :] * d
    a = np.linalg.solve(H, b[..., None])[..., 0]
    ok = np.all((a >= lo_s) & (a <= hi_s), axis=1)
    if not ok.all():
        if K <= 2:
            a = _box_qp_edges(H, b, a, ok, lo_s, hi_s)
        else:
            a = _enumerate_active_sets(H, b, a, ok, lo_s, hi_s)
    # (bound * d) / d can round past the bound, which the model would reject
    return np.clip(a / d, lo, hi)


def _box_qp_edges(H, b, a, ok, lo, hi):
    """Exact box-QP solution for K <= 2 on the rows ``~ok`` (unconstrained minimiser
    outside the box): the minimiser then lies on an edge of the box, and on each edge
    (one variable at a bound) the 1-D minimiser is the clipped stationary point, so the
    best of the (at most 4) edge minimisers is the answer.  The same result as
    :func:`_enumerate_active_sets` in ~10 numpy calls instead of ~15 per pattern x 3**K
    patterns, which dominated small fits (a 6000-sample ``gonio fit`` with one albedo at
    0: a quarter of its time).  ``lo``/``hi`` are per row (B, K)."""
    idx = np.flatnonzero(~ok)
    Hs, bs, los, his = H[idx], b[idx], lo[idx], hi[idx]
    K = bs.shape[1]
    if K == 1:
        a[idx] = np.clip(bs / Hs[:, 0], los, his)
        return a
    best = np.full(idx.size, np.inf)
    best_a = np.clip(a[idx], los, his)
    for fix in (0, 1):
        free = 1 - fix
        for bound in (los[:, fix], his[:, fix]):
            fin = np.isfinite(bound)
            if not fin.any():
                continue
            v = np.where(fin, bound, 0.0)
            w = np.clip((bs[:, free] - Hs[:, free, fix] * v) / Hs[:, free, free],
                        los[:, free], his[:, free])  # fmt: skip
            cand = np.empty_like(bs)
            cand[:, fix] = v
            cand[:, free] = w
            obj = 0.5 * np.einsum("bi,bij,bj->b", cand, Hs, cand) - np.einsum("bi,bi->b", bs, cand)
            better = fin & (obj < best)
            best[better] = obj[better]
            best_a[better] = cand[better]
    a[idx] = best_a
    return a


def _enumerate_active_sets(H, b, a, ok, lo, hi):
    """Exact box-QP solution by trying every free/lower/upper assignment (rows ~ok).

    ``lo``/``hi`` are per row (B, K) here (the scaled bounds).
    """
    B, K = b.shape
    idx = np.flatnonzero(~ok)
    if K > _ENUM_MAX:  # pragma: no cover - no model has this many linear parameters
        from scipy.optimize import minimize

        for i in idx:
            res = minimize(
                lambda v, i=i: (0.5 * v @ H[i] @ v - b[i] @ v, H[i] @ v - b[i]),
                np.clip(a[i], lo[i], hi[i]),
                jac=True,
                bounds=list(zip(lo[i], hi[i], strict=True)),
                method="L-BFGS-B",
            )
            a[i] = res.x
        return a
    Hs, bs, los, his = H[idx], b[idx], lo[idx], hi[idx]
    best = np.full(idx.size, np.inf)
    best_a = np.clip(a[idx], los, his)
    for pattern in itertools.product((0, 1, 2), repeat=K):
        pat = np.array(pattern)
        cand = np.where(pat == 1, los, np.where(pat == 2, his, 0.0))
        fin = np.all(np.isfinite(cand[:, pat != 0]), axis=1)
        if not fin.any():
            continue
        cand = np.where(np.isfinite(cand), cand, 0.0)
        free = np.flatnonzero(pat == 0)
        fixed = np.flatnonzero(pat != 0)
        if free.size:
            rhs = bs[:, free] - np.einsum("bij,bj->bi", Hs[:, free][:, :, fixed], cand[:, fixed])
            sol = np.linalg.solve(Hs[:, free][:, :, free], rhs[..., None])[..., 0]
            cand[:, free] = sol
            feas = np.all((sol >= los[:, free]) & (sol <= his[:, free]), axis=1)
        else:
            feas = np.ones(idx.size, dtype=bool)
        feas &= fin
        obj = 0.5 * np.einsum("bi,bij,bj->b", cand, Hs, cand) - np.einsum("bi,bi->b", bs, cand)
        better = feas & (obj < best)
        best[better] = obj[better]
        best_a[better] = cand[better]
    a[idx] = best_a
    return a


def unit_values(problem: Problem) -> np.ndarray:
    """A value inside the bounds for each linear parameter at which basis functions are
    evaluated (1, or the upper bound when it is below 1: Oren-Nayar albedo <= 0.99)."""
    return np.array([min(1.0, hi) if hi > 0 else 1.0 for hi in problem.ub_lin], dtype=np.float64)


class VarPro:
    """The reduced cost ``c(u)`` over shape search variables ``u`` of a linear-loss problem.

    Parameters
    ----------
    problem
        A :class:`~gonio.fitting.objective.Problem` whose loss is linear and unpenalised.
    """

    def __init__(self, problem: Problem) -> None:
        if not problem.loss.linear or problem.robust is not None:
            raise ValueError("variable projection needs a linear loss without robust penalty")
        self.p = problem
        self.w2 = problem.weights**2  # (N, C)
        self.w2y = self.w2 * problem.y
        self.unit = unit_values(problem)
        self._fused = _fused_plan(self)
        # the fused models' alpha scales with ks (linear parameter 1): no need to probe
        # the model for it (two model evaluations, ~5 ms of a fit)
        self.coupling = [1] if self._fused is not None else self._detect_coupling()
        self._last: tuple | None = None
        self._basis: tuple | None = None  # (theta bytes, G, g) of the last numpy basis

    def _unit_params(self, theta: np.ndarray) -> dict[str, Any]:
        p: dict[str, Any] = {n: float(t) for n, t in zip(self.p.shape_names, theta, strict=True)}
        for j, n in enumerate(self.p.linear_names):
            p[n] = float(self.unit[j])
        return p

    def _detect_coupling(self) -> list[int] | None:
        """For each shape parameter the one linear parameter it scales with, else None.

        When every shape parameter belongs to exactly one lobe with one linear factor,
        ``df/dtheta`` at any ``a`` is ``a_j * dg_j/dtheta``, and one model evaluation with
        all ``a = 1`` gives everything the gradient needs.
        """
        p = self.p
        if p.n_shape == 0:
            return []
        if p.n_linear == 0:
            return None
        sel = slice(0, min(256, p.wi.shape[0]))
        theta = self.default_theta()
        out: list[int] = []
        nz = np.zeros((p.n_shape, p.n_linear), dtype=bool)
        for j, _ in enumerate(p.linear_names):
            prm = self._unit_params(theta)
            for jj, n in enumerate(p.linear_names):
                prm[n] = float(self.unit[jj]) if jj == j else 0.0
            _, g = p.model.eval_with_grad(p.wi[sel], p.wo[sel], prm)
            for s, n in enumerate(p.shape_names):
                nz[s, j] = bool(np.any(np.asarray(g[n]) != 0))
        for s in range(p.n_shape):
            js = np.flatnonzero(nz[s])
            if js.size != 1:
                return None
            out.append(int(js[0]))
        return out

    def default_theta(self) -> np.ndarray:
        """The model's default shape parameters, clipped into the bounds."""
        p = self.p
        d = dict(getattr(p.model, "defaults", {}) or {})
        th = np.array([float(d.get(n, np.nan)) for n in p.shape_names])
        mid = np.where(
            p.log_shape,
            np.sqrt(np.abs(p.lb_shape * p.ub_shape)),
            0.5 * (np.nan_to_num(p.lb_shape, neginf=-1.0) + np.nan_to_num(p.ub_shape, posinf=1.0)),
        )
        th = np.where(np.isfinite(th), th, mid)
        return np.clip(th, p.lb_shape, p.ub_shape)

    def basis(self, theta: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Basis ``G`` (N, K) (one column per linear parameter) and the gradients at the unit
        values of the linear parameters."""
        p = self.p
        p.njev += 1
        _, g = p.model.eval_with_grad(p.wi, p.wo, self._unit_params(theta))
        n = p.wi.shape[0]
        G = np.empty((n, p.n_linear))
        for j, name in enumerate(p.linear_names):
            G[:, j] = np.broadcast_to(g[name], (n,))
        return G, g

    def solve_linear(self, G: np.ndarray) -> np.ndarray:
        """Best linear parameters (K, C) for basis ``G`` (N, K)."""
        p = self.p
        # normal equations by BLAS products: H_c = G^T diag(w_c^2) G, b_c = G^T (w_c^2 y_c)
        H = np.stack([(G.T * self.w2[:, c]) @ G for c in range(self.w2.shape[1])])
        b = (G.T @ self.w2y).T
        # contiguous: numpy's matmul with a strided tiny operand is ~50x slower
        return np.ascontiguousarray(solve_box_qp(H, b, p.lb_lin, p.ub_lin).T)

    def evaluate(self, u: np.ndarray, want_grad: bool = True):
        """Reduced cost, its gradient w.r.t. ``u``, and the linear parameters (K, C).

        The last evaluation is remembered: the optimiser's final point is asked for again
        for its linear parameters, and on a large problem that is a whole pass."""
        u = np.asarray(u, dtype=np.float64)
        key = (u.tobytes(), want_grad)
        last = self._last
        if last is not None and (last[0] == key or (last[0][0] == key[0] and last[0][1])):
            c, g, a = last[1]
            return c, g.copy(), a.copy()
        out = self._evaluate(u, want_grad)
        self._last = (key, (out[0], out[1].copy(), out[2].copy()))
        return out

    def _evaluate(self, u: np.ndarray, want_grad: bool):
        if self._fused is not None:
            return self._fused.evaluate(u)
        p = self.p
        u = np.asarray(u, dtype=np.float64)
        theta = p.from_u(u)
        G, g = self.basis(theta)
        self._basis = (theta.tobytes(), G, g)
        a = self.solve_linear(G)
        res = G @ a
        res -= p.y
        wres = self.w2 * res
        cost = 0.5 * float(np.einsum("nc,nc->", wres, res))
        if not want_grad or p.n_shape == 0:
            return cost, np.zeros(p.n_shape), a
        dtu = p.dtheta_du(theta)
        grad = np.empty(p.n_shape)
        n = G.shape[0]
        if self.coupling is not None:
            for s, name in enumerate(p.shape_names):
                j = self.coupling[s]
                gs = np.broadcast_to(g[name], (n,))
                grad[s] = float((gs @ wres) @ (a[j] / self.unit[j])) * dtu[s]
        else:
            _, gf = p.model_eval(theta, a, grad=True)
            for s, name in enumerate(p.shape_names):
                grad[s] = np.sum(wres * np.broadcast_to(gf[name], res.shape)) * dtu[s]
        return cost, grad, a

    def gauss_newton(self, u: np.ndarray):
        """Gauss-Newton pieces at ``u``: ``H (C, K, K)``, ``D (C, S, K)``, ``E (C, S, S)``
        (:func:`gonio.fitting.kernels.gauss_newton_sums`, per unit linear parameter) and
        the linear parameters ``a (K, C)``; None when a shape parameter does not scale
        with exactly one linear parameter (``coupling``).

        The Jacobian of the residuals ``w (G a - y)`` is ``w G`` for the linear
        parameters and ``w a_j dG`` for a shape parameter coupled to ``a_j``, so these
        sums are ``J^T J`` in pieces (natural units).
        """
        coupling = self._fused.coupling if self._fused is not None else self.coupling
        if coupling is None or self.p.n_shape == 0:
            return None
        u = np.asarray(u, dtype=np.float64)
        p = self.p
        theta = p.from_u(u)
        _, _, a = self.evaluate(u, want_grad=False)
        # the remembered evaluation does not say where the basis arrays were last filled
        # (batch_cost evaluates past the memory): fill them again if elsewhere
        if self._fused is not None:
            if self._fused.alpha != float(theta[0]):
                self._fused.evaluate(u)
            H, D, E = self._fused.gauss_newton_sums()
        else:
            if self._basis is None or self._basis[0] != theta.tobytes():
                self._evaluate(u, want_grad=False)
            _, G, g = self._basis
            n = G.shape[0]
            dG = np.stack(
                [
                    np.broadcast_to(g[name], (n,)) / self.unit[coupling[s]]
                    for s, name in enumerate(p.shape_names)
                ],
                axis=1,
            )
            H = np.einsum("nj,nc,nk->cjk", G, self.w2, G)
            D = np.einsum("ns,nc,nj->csj", dG, self.w2, G)
            E = np.einsum("ns,nc,nt->cst", dG, self.w2, dG)
        return H, D, E, a

    def curvature(self, u: np.ndarray) -> np.ndarray | None:
        """Gauss-Newton estimate of the reduced cost's second derivatives ``d^2 c / du_s^2``
        (S,) at ``u`` (the diagonal; None when unknown): the preconditioner of the local
        searches (:func:`gonio.fitting.optimize.nlopt_minimize` ``x_scale``).

        The reduced cost's Gauss-Newton Hessian in theta is the Schur complement of the
        full one, ``J_s^T J_s - J_s^T J_l (J_l^T J_l)^-1 J_l^T J_s`` per channel over
        the linear parameters off their bounds; the search variable ``u = ln theta``
        adds ``dc/dtheta * d^2 theta / du^2``.
        """
        u = np.asarray(u, dtype=np.float64)
        _, g_u, _ = self.evaluate(u, want_grad=True)
        gn = self.gauss_newton(u)
        if gn is None:
            return None
        H, D, E, a = gn
        p = self.p
        coupling = self._fused.coupling if self._fused is not None else self.coupling
        S, C = p.n_shape, p.n_channels
        scale = a[np.asarray(coupling)] / self.unit[np.asarray(coupling)][:, None]  # (S, C)
        hth = np.zeros(S)
        span = np.maximum(np.abs(a), 1e-300)
        for c in range(C):
            Acs = scale[:, c]
            jss = np.diag(E[c]) * Acs * Acs
            jsl = Acs[:, None] * D[c]  # (S, K)
            free = (a[:, c] > p.lb_lin + 1e-12 * span[:, c]) & (
                a[:, c] < p.ub_lin - 1e-12 * span[:, c]
            )
            if free.any():
                Hf = H[c][np.ix_(free, free)]
                try:
                    sol = np.linalg.solve(Hf, jsl[:, free].T)  # (F, S)
                except np.linalg.LinAlgError:
                    return None
                jss = jss - np.einsum("sf,fs->s", jsl[:, free], sol)
            hth += jss
        theta = p.from_u(u)
        dtu = p.dtheta_du(theta)
        # d^2 theta / du^2 = dtheta/du for theta = exp(u) - offset, 0 for theta = u
        curv = hth * dtu * dtu + np.where(p.log_shape, g_u, 0.0)
        gn_only = hth * dtu * dtu
        curv = np.where(np.isfinite(curv) & (curv > 0), curv, gn_only)
        return np.where(np.isfinite(curv) & (curv > 0), curv, np.nan)

    def jtj(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Residuals ``r`` (N, C) and the Gauss-Newton matrix ``J^T J`` (P, P) in natural
        units and ``Problem.labels`` order at ``x``, from the fused kernels' sums (the
        model's numpy gradients on 10^5 samples were most of the covariance's time);
        None on the numpy path (``covariance_at`` forms them from the model)."""
        if self._fused is None or self.p.robust is not None:
            return None
        p = self.p
        S, K, C = p.n_shape, p.n_linear, p.n_channels
        _, a = p.unpack(x)
        gn = self.gauss_newton(np.asarray(x, dtype=np.float64)[:S])
        if gn is None:  # pragma: no cover - the fused models are all coupled
            return None
        H, D, E, _ = gn
        coupling = np.asarray(self._fused.coupling)
        A = a[coupling]  # (S, C): the linear parameter each shape parameter scales with
        P = p.n_params
        J = np.zeros((P, P))
        J[:S, :S] = np.einsum("sc,tc,cst->st", A, A, E)
        for c in range(C):
            idx = S + np.arange(K) * C + c
            J[:S, idx] = A[:, c, None] * D[c]
            J[idx, :S] = J[:S, idx].T
            J[np.ix_(idx, idx)] = H[c]
        G = self._fused.G
        f = G[:, 0, None] * a[0][None, :] + G[:, 1, None] * a[1][None, :]
        r = p.weights * (f - p.y)
        return r, J

    def batch_cost(self, U: np.ndarray) -> np.ndarray:
        """Reduced cost at many points ``U`` (M, S) at once (one broadcast model call)."""
        p = self.p
        U = np.atleast_2d(np.asarray(U, dtype=np.float64))
        M = U.shape[0]
        if self._fused is not None:
            c = np.array([self._fused.evaluate(row)[0] for row in U])
            return np.where(np.isfinite(c), c, np.inf)
        n = p.wi.shape[0]
        out = np.empty(M)
        step = max(1, _CHUNK // max(n * max(p.n_linear, 1), 1))
        for s0 in range(0, M, step):
            th = p.from_u(U[s0 : s0 + step])  # (m, S)
            m = th.shape[0]
            prm: dict[str, Any] = {n_: th[:, s, None] for s, n_ in enumerate(p.shape_names)}
            for j, n_ in enumerate(p.linear_names):
                prm[n_] = float(self.unit[j])
            p.njev += 1
            _, g = p.model.eval_with_grad(p.wi, p.wo, prm)
            G = np.empty((m, n, p.n_linear))
            for j, name in enumerate(p.linear_names):
                G[:, :, j] = np.broadcast_to(g[name], (m, n))
            K = p.n_linear
            Gt = np.swapaxes(G, 1, 2)  # (m, K, n)
            H = np.stack(
                [np.matmul(Gt * self.w2[None, None, :, c], G) for c in range(self.w2.shape[1])],
                axis=1,
            )  # (m, C, K, K)
            b = np.swapaxes(np.matmul(Gt, self.w2y), 1, 2)  # (m, C, K)
            a = solve_box_qp(H.reshape(-1, K, K), b.reshape(-1, K), p.lb_lin, p.ub_lin)
            a = a.reshape(m, -1, K)  # (m, C, K)
            res = np.matmul(G, np.ascontiguousarray(np.swapaxes(a, 1, 2))) - p.y[None]  # (m, n, C)
            c = 0.5 * np.sum(self.w2[None] * res * res, axis=(1, 2))
            out[s0 : s0 + m] = np.where(np.isfinite(c), c, np.inf)
        return out


def _fused_plan(vp: VarPro) -> _FusedVarPro | None:
    """The numba evaluation of ``vp`` (:mod:`gonio.fitting.kernels`), or None: numpy.

    Used for lambert + one microfacet lobe (ggx, beckmann; no Fresnel factor) on at least
    :data:`~gonio.fitting.kernels.MIN_ROWS` samples (or fewer once the kernels are loaded:
    the design subset of a large fit), unless ``GONIO_NUMBA=0``.
    """
    p = vp.p
    n = p.wi.shape[0]
    if os.environ.get("GONIO_NUMBA") == "0" or n < 4096:
        return None
    if n < _FIRST_FUSED and "gonio.fitting.kernels" not in sys.modules:
        return None
    lobes = tuple(getattr(p.model, "lobes", ()))
    kinds = tuple(getattr(lobe, "kind", "") for lobe in lobes)
    if (
        len(lobes) != 2
        or kinds[0] != "lambert"
        or kinds[1] not in ("ggx", "beckmann")
        or lobes[1].options.get("fresnel", "none") != "none"
        or tuple(p.model.param_names) != ("albedo", "ks", "alpha")
        or p.shape_names != ("alpha",)
        or p.linear_names != ("albedo", "ks")
    ):
        return None
    return _FusedVarPro(vp, kinds[1], lobes[1].options.get("g1", "exact"))


class _FusedVarPro:
    """:meth:`VarPro.evaluate` for lambert + microfacet by the kernels: one pass for the
    basis and its alpha derivative, one for the normal equations, one for cost+gradient."""

    def __init__(self, vp: VarPro, dist: str, g1: str) -> None:
        from gonio.fitting import kernels

        self.vp = vp
        parallel = vp.p.wi.shape[0] >= kernels.PARALLEL_ROWS
        self.gn_sums = kernels.gauss_newton_sums if parallel else kernels.gauss_newton_sums_serial
        self.kernels = (
            (kernels.basis_microfacet, kernels.normal_equations, kernels.cost_grad)
            if parallel
            else (
                kernels.basis_microfacet_serial,
                kernels.normal_equations_serial,
                kernels.cost_grad_serial,
            )
        )
        p = vp.p
        self.wi = np.ascontiguousarray(p.wi)
        self.wo = np.ascontiguousarray(p.wo)
        self.w2 = np.ascontiguousarray(vp.w2)
        self.w2y = np.ascontiguousarray(vp.w2y)
        self.y = np.ascontiguousarray(p.y)
        n = self.wi.shape[0]
        below = (self.wi[:, 2] <= 0.0) | (self.wo[:, 2] <= 0.0)
        self.G = np.empty((n, 2))
        self.G[:, 0] = np.where(below, 0.0, 1.0 / np.pi)  # Lambert: df/d albedo = 1/pi
        self.dG = np.empty((n, 1))
        self.dist = kernels.DIST_GGX if dist == "ggx" else kernels.DIST_BECKMANN
        self.g1 = kernels.G1_RATIONAL if g1 == "rational" else kernels.G1_EXACT
        self.coupling = np.array([1], dtype=np.int64)
        C = self.y.shape[1]
        self.H = np.empty((C, 2, 2))
        self.b = np.empty((C, 2))
        self.alpha = np.nan

    def gauss_newton_sums(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`~gonio.fitting.kernels.gauss_newton_sums` of the current basis."""
        C = self.y.shape[1]
        H, D, E = np.empty((C, 2, 2)), np.empty((C, 1, 2)), np.empty((C, 1, 1))
        self.gn_sums(self.G, self.dG, self.w2, H, D, E)
        return H, D, E

    def evaluate(self, u: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        p = self.vp.p
        theta = p.from_u(u)
        p.njev += 1
        basis, normal, cost_grad = self.kernels
        basis(self.wi, self.wo, float(theta[0]), self.dist, self.g1, self.G, 1, self.dG)
        self.alpha = float(theta[0])  # where G and dG are now
        normal(self.G, self.w2, self.w2y, self.H, self.b)
        a = np.ascontiguousarray(solve_box_qp(self.H, self.b, p.lb_lin, p.ub_lin).T)
        grad = np.empty(1)
        cost = cost_grad(self.G, self.dG, self.coupling, a, self.w2, self.y, grad)
        return float(cost), grad * p.dtheta_du(theta), a
