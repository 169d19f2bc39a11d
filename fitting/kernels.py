"""Fused numba kernels of the variable-projection fit: basis, normal equations, cost+gradient.

:class:`gonio.fitting.varpro.VarPro` evaluates the reduced cost ``c(u)`` many times per
fit.  Its numpy form streams the model's gradient dictionary (~30 temporaries of N
elements for a microfacet lobe), the three per-channel normal matrices and the residual
products through memory; measured on 10^5 samples it spent ~20 ms per evaluation, of
which ~2 ms are the model values.  Here one pass per evaluation fills the basis (the
microfacet lobe at unit ``ks`` and its derivative in ``alpha``) and accumulates the normal
equations, and a second pass forms the residuals, the cost and the gradient from the
stored basis, so nothing is computed twice between the objective and the gradient.

Sums run over fixed blocks of :data:`BLOCK` rows and then over the blocks in order, so
the result does not depend on the number of threads (one thread and all cores give the
same bits, and so do the ``*_serial`` twins).  The numpy path in
:mod:`gonio.fitting.varpro` stays the reference: the kernels are used only for the models
they cover (lambert + ggx/beckmann without Fresnel) and large problems
(:data:`MIN_ROWS`); ``GONIO_NUMBA=0`` keeps every fit on numpy, and
``tests/fitting/test_kernels.py`` holds the two paths together.

Compilation: ``cache=True`` (machine code stored beside this module, compiled once per
installation), ``fastmath=False`` and ``error_model="numpy"`` like
:mod:`gonio.brdf.kernels`, whose expressions (and operation order) the basis repeats.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = [
    "BLOCK",
    "MIN_ROWS",
    "PARALLEL_ROWS",
    "basis_microfacet",
    "basis_microfacet_serial",
    "cost_grad",
    "cost_grad_serial",
    "gauss_newton_sums",
    "gauss_newton_sums_serial",
    "normal_equations",
    "normal_equations_serial",
]

#: Rows per block of the blocked sums (and per parallel task).
BLOCK = 4096
#: Problems with fewer used samples than this stay on the numpy path (a ``gonio fit`` of
#: a measured file sampled on its 5832-direction grid never pays numba's ~0.5 s import).
MIN_ROWS = 50_000
#: From this many rows on the multi-threaded kernels are used (a 10^5-sample fit's
#: polish); below (its 20000-sample design subset) the ``*_serial`` twins: a parallel
#: launch waits for its slowest thread, which on a busy machine made a 2-thread fit 8x
#: slower than a 1-thread one.  Both give the same bits (the same blocked sums).
PARALLEL_ROWS = 65_536

DIST_GGX, DIST_BECKMANN = 0, 1
G1_EXACT, G1_RATIONAL = 0, 1

_INV_PI = 1.0 / math.pi
_INV_2SQRTPI = 0.5 / math.sqrt(math.pi)
_JIT = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}


@njit(**_JIT, inline="always")
def _ggx_g1_dln(cos_t, sin2_t, alpha):
    """GGX ``G1 / cos`` and ``d ln G1 / d alpha`` (gonio.brdf.microfacet.ggx_g1)."""
    a2 = alpha * alpha
    r = math.sqrt(cos_t * cos_t + a2 * sin2_t)
    g = 2.0 / (cos_t + r)
    return g, -(alpha * sin2_t / r) / (cos_t + r)


@njit(**_JIT, inline="always")
def _beckmann_g1_dln(cos_t, sin2_t, alpha, form):
    """Beckmann ``G1 / cos`` and ``d ln G1 / d alpha`` (gonio.brdf.microfacet.beckmann_g1)."""
    s = math.sqrt(sin2_t)
    a = cos_t / (alpha * s)
    if form == G1_EXACT:
        e = math.exp(-a * a)
        denom = cos_t - 0.5 * cos_t * math.erfc(a) + alpha * s * e * _INV_2SQRTPI
        g = 1.0 / denom
        return g, -g * s * e * _INV_2SQRTPI
    num = 3.535 + 2.181 * a
    den = 1.0 + 2.276 * a + 2.577 * a * a
    if a < 1.6:
        dlna = (3.535 + 4.362 * a) / num - a * (2.276 + 5.154 * a) / den
        return num / (alpha * s * den), -dlna / alpha
    return 1.0 / cos_t, 0.0


@njit(**_JIT, inline="always")
def _basis_block(wi, wo, alpha, dist, g1form, G, col, dG, blk):
    n = wi.shape[0]
    for i in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
        ix, iy, iz = wi[i, 0], wi[i, 1], wi[i, 2]
        ox, oy, oz = wo[i, 0], wo[i, 1], wo[i, 2]
        hx = ix + ox
        hy = iy + oy
        hz = iz + oz
        hxy2 = hx * hx + hy * hy
        hz2 = hz * hz
        hh = hxy2 + hz2
        si2 = ix * ix + iy * iy
        so2 = ox * ox + oy * oy
        a2 = alpha * alpha
        if dist == DIST_GGX:
            q = a2 * hz2 + hxy2
            t = hh / q
            D = (a2 * _INV_PI) * (t * t)
            dD = 2.0 / alpha - 4.0 * alpha * hz2 / q
            gi, dgi = _ggx_g1_dln(iz, si2, alpha)
            go, dgo = _ggx_g1_dln(oz, so2, alpha)
        else:
            tan2 = hxy2 / hz2
            D = math.exp(-tan2 / a2) * (hh * hh) / ((math.pi * a2) * (hz2 * hz2))
            dD = 2.0 * tan2 / (a2 * alpha) - 2.0 / alpha
            gi, dgi = _beckmann_g1_dln(iz, si2, alpha, g1form)
            go, dgo = _beckmann_g1_dln(oz, so2, alpha, g1form)
        base = 0.25 * D * gi * go
        if (iz <= 0.0) | (oz <= 0.0):
            G[i, col] = 0.0
            dG[i, 0] = 0.0
        else:
            G[i, col] = base
            dG[i, 0] = base * (dD + dgi + dgo)


@njit(**_JIT, parallel=True)
def basis_microfacet(wi, wo, alpha, dist, g1form, G, col, dG):
    """The microfacet lobe at ``ks = 1`` (1/sr) and its derivative in ``alpha``, per pair.

    Parameters
    ----------
    wi, wo : (N, 3) float64, C order
        Unit directions (sample frame).
    alpha : float
        Roughness.
    dist, g1form : int
        :data:`DIST_GGX` / :data:`DIST_BECKMANN`; :data:`G1_EXACT` / :data:`G1_RATIONAL`.
    G : (N, K) float64
        Basis; column ``col`` is written: ``f(ks=1)``, 0 below the horizon.
    col : int
    dG : (N, 1) float64
        Written: ``d f(ks=1) / d alpha``, 0 below the horizon.
    """
    for blk in prange((wi.shape[0] + BLOCK - 1) // BLOCK):
        _basis_block(wi, wo, alpha, dist, g1form, G, col, dG, blk)


@njit(**_JIT)
def basis_microfacet_serial(wi, wo, alpha, dist, g1form, G, col, dG):
    """:func:`basis_microfacet` on the calling thread (the same values)."""
    for blk in range((wi.shape[0] + BLOCK - 1) // BLOCK):
        _basis_block(wi, wo, alpha, dist, g1form, G, col, dG, blk)


@njit(**_JIT, inline="always")
def _ne_task(G, w2, w2y, Hp, bp, task):
    n, K = G.shape
    C = w2.shape[1]
    blk = task // C
    c = task % C
    lo = blk * BLOCK
    hi = min(n, lo + BLOCK)
    if K == 2:  # lambert + one lobe: five sums in registers
        h00 = 0.0
        h01 = 0.0
        h11 = 0.0
        b0 = 0.0
        b1 = 0.0
        for i in range(lo, hi):
            w = w2[i, c]
            wy = w2y[i, c]
            g0 = G[i, 0]
            g1 = G[i, 1]
            h00 += g0 * g0 * w
            h01 += g0 * g1 * w
            h11 += g1 * g1 * w
            b0 += g0 * wy
            b1 += g1 * wy
        Hp[blk, c, 0, 0] = h00
        Hp[blk, c, 0, 1] = h01
        Hp[blk, c, 1, 1] = h11
        bp[blk, c, 0] = b0
        bp[blk, c, 1] = b1
    else:
        for i in range(lo, hi):
            w = w2[i, c]
            wy = w2y[i, c]
            for j in range(K):
                bp[blk, c, j] += G[i, j] * wy
                for k in range(j, K):
                    Hp[blk, c, j, k] += G[i, j] * G[i, k] * w


@njit(**_JIT, inline="always")
def _ne_total(Hp, bp, H, b):
    nblk, C, K, _ = Hp.shape
    H[:] = 0.0
    b[:] = 0.0
    for blk in range(nblk):
        for c in range(C):
            for j in range(K):
                b[c, j] += bp[blk, c, j]
                for k in range(j, K):
                    H[c, j, k] += Hp[blk, c, j, k]
    for c in range(C):
        for j in range(K):
            for k in range(j):
                H[c, j, k] = H[c, k, j]


@njit(**_JIT, parallel=True)
def normal_equations(G, w2, w2y, H, b):
    """``H[c] = G^T diag(w2[:, c]) G`` and ``b[c] = G^T w2y[:, c]`` in blocked sums.

    Parameters
    ----------
    G : (N, K)
        Basis (one column per linear parameter).
    w2, w2y : (N, C)
        Squared weights and squared weights times the data.
    H : (C, K, K), b : (C, K)
        Written.
    """
    n, K = G.shape
    C = w2.shape[1]
    nblk = (n + BLOCK - 1) // BLOCK
    Hp = np.zeros((nblk, C, K, K))
    bp = np.zeros((nblk, C, K))
    for task in prange(nblk * C):
        _ne_task(G, w2, w2y, Hp, bp, task)
    _ne_total(Hp, bp, H, b)


@njit(**_JIT)
def normal_equations_serial(G, w2, w2y, H, b):
    """:func:`normal_equations` on the calling thread (the same bits)."""
    n, K = G.shape
    C = w2.shape[1]
    nblk = (n + BLOCK - 1) // BLOCK
    Hp = np.zeros((nblk, C, K, K))
    bp = np.zeros((nblk, C, K))
    for task in range(nblk * C):
        _ne_task(G, w2, w2y, Hp, bp, task)
    _ne_total(Hp, bp, H, b)


@njit(**_JIT, inline="always")
def _cg_task(G, dG, coupling, a, w2, y, cp, gp, task):
    n, K = G.shape
    C = y.shape[1]
    S = dG.shape[1]
    blk = task // C
    c = task % C
    lo = blk * BLOCK
    hi = min(n, lo + BLOCK)
    if K == 2 and S == 1:  # lambert + one lobe, one shape parameter: in registers
        a0 = a[0, c]
        a1 = a[1, c]
        ac = a[coupling[0], c]
        cs = 0.0
        gs = 0.0
        for i in range(lo, hi):
            r = G[i, 0] * a0 + G[i, 1] * a1 - y[i, c]
            wr = w2[i, c] * r
            cs += wr * r
            gs += wr * dG[i, 0]
        cp[blk, c] = cs
        gp[blk, c, 0] = gs * ac
    else:
        for i in range(lo, hi):
            r = -y[i, c]
            for j in range(K):
                r += G[i, j] * a[j, c]
            wr = w2[i, c] * r
            cp[blk, c] += wr * r
            for s in range(S):
                gp[blk, c, s] += wr * dG[i, s] * a[coupling[s], c]


@njit(**_JIT, inline="always")
def _cg_total(cp, gp, grad):
    nblk, C, S = gp.shape
    cost = 0.0
    grad[:] = 0.0
    for blk in range(nblk):
        for c in range(C):
            cost += cp[blk, c]
            for s in range(S):
                grad[s] += gp[blk, c, s]
    return 0.5 * cost


@njit(**_JIT, parallel=True)
def cost_grad(G, dG, coupling, a, w2, y, grad):
    """Reduced cost ``0.5 sum w2 (G a - y)^2`` and its gradient in the shape parameters.

    Parameters
    ----------
    G : (N, K)
        Basis at unit linear parameters.
    dG : (N, S)
        Derivative of the basis column ``coupling[s]`` in shape parameter ``s`` (natural
        units, per unit of the linear parameter).
    coupling : (S,) int
        The linear parameter each shape parameter scales with.
    a : (K, C)
        Linear parameters.
    w2, y : (N, C)
    grad : (S,)
        Written: ``dc / d theta_s`` (natural units).

    Returns
    -------
    float
        The cost.
    """
    n = G.shape[0]
    C = y.shape[1]
    nblk = (n + BLOCK - 1) // BLOCK
    cp = np.zeros((nblk, C))
    gp = np.zeros((nblk, C, dG.shape[1]))
    for task in prange(nblk * C):
        _cg_task(G, dG, coupling, a, w2, y, cp, gp, task)
    return _cg_total(cp, gp, grad)


@njit(**_JIT)
def cost_grad_serial(G, dG, coupling, a, w2, y, grad):
    """:func:`cost_grad` on the calling thread (the same bits)."""
    n = G.shape[0]
    C = y.shape[1]
    nblk = (n + BLOCK - 1) // BLOCK
    cp = np.zeros((nblk, C))
    gp = np.zeros((nblk, C, dG.shape[1]))
    for task in range(nblk * C):
        _cg_task(G, dG, coupling, a, w2, y, cp, gp, task)
    return _cg_total(cp, gp, grad)


@njit(**_JIT, inline="always")
def _gn_task(G, dG, w2, Hp, Dp, Ep, task):
    n, K = G.shape
    C = w2.shape[1]
    S = dG.shape[1]
    blk = task // C
    c = task % C
    lo = blk * BLOCK
    hi = min(n, lo + BLOCK)
    if K == 2 and S == 1:  # lambert + one lobe, one shape parameter: in registers
        h00 = 0.0
        h01 = 0.0
        h11 = 0.0
        d0 = 0.0
        d1 = 0.0
        e = 0.0
        for i in range(lo, hi):
            w = w2[i, c]
            g0 = G[i, 0] * w
            g1 = G[i, 1] * w
            ds = dG[i, 0]
            h00 += g0 * G[i, 0]
            h01 += g0 * G[i, 1]
            h11 += g1 * G[i, 1]
            d0 += g0 * ds
            d1 += g1 * ds
            e += ds * w * ds
        Hp[blk, c, 0, 0] = h00
        Hp[blk, c, 0, 1] = h01
        Hp[blk, c, 1, 1] = h11
        Dp[blk, c, 0, 0] = d0
        Dp[blk, c, 0, 1] = d1
        Ep[blk, c, 0, 0] = e
    else:
        for i in range(lo, hi):
            w = w2[i, c]
            for j in range(K):
                gj = G[i, j] * w
                for k in range(j, K):
                    Hp[blk, c, j, k] += gj * G[i, k]
                for s in range(S):
                    Dp[blk, c, s, j] += gj * dG[i, s]
            for s in range(S):
                ws = dG[i, s] * w
                for t in range(s, S):
                    Ep[blk, c, s, t] += ws * dG[i, t]


@njit(**_JIT, inline="always")
def _gn_total(Hp, Dp, Ep, H, D, E):
    nblk, C, K, _ = Hp.shape
    S = Dp.shape[2]
    H[:] = 0.0
    D[:] = 0.0
    E[:] = 0.0
    for blk in range(nblk):
        for c in range(C):
            for j in range(K):
                for k in range(j, K):
                    H[c, j, k] += Hp[blk, c, j, k]
            for s in range(S):
                for j in range(K):
                    D[c, s, j] += Dp[blk, c, s, j]
                for t in range(s, S):
                    E[c, s, t] += Ep[blk, c, s, t]
    for c in range(C):
        for j in range(K):
            for k in range(j):
                H[c, j, k] = H[c, k, j]
        for s in range(S):
            for t in range(s):
                E[c, s, t] = E[c, t, s]


@njit(**_JIT, parallel=True)
def gauss_newton_sums(G, dG, w2, H, D, E):
    """The weighted products of the basis and its shape derivatives, per channel, in
    blocked sums: the Gauss-Newton matrix ``J^T J`` of a linear-loss fit in pieces.

    Parameters
    ----------
    G : (N, K)
        Basis at unit linear parameters.
    dG : (N, S)
        Shape derivatives of the coupled basis columns (natural units).
    w2 : (N, C)
        Squared weights.
    H : (C, K, K), D : (C, S, K), E : (C, S, S)
        Written: ``H[c] = G^T diag(w2_c) G``, ``D[c] = dG^T diag(w2_c) G``, ``E[c] =
        dG^T diag(w2_c) dG``.
    """
    n, K = G.shape
    C = w2.shape[1]
    S = dG.shape[1]
    nblk = (n + BLOCK - 1) // BLOCK
    Hp = np.zeros((nblk, C, K, K))
    Dp = np.zeros((nblk, C, S, K))
    Ep = np.zeros((nblk, C, S, S))
    for task in prange(nblk * C):
        _gn_task(G, dG, w2, Hp, Dp, Ep, task)
    _gn_total(Hp, Dp, Ep, H, D, E)


@njit(**_JIT)
def gauss_newton_sums_serial(G, dG, w2, H, D, E):
    """:func:`gauss_newton_sums` on the calling thread (the same bits)."""
    n, K = G.shape
    C = w2.shape[1]
    S = dG.shape[1]
    nblk = (n + BLOCK - 1) // BLOCK
    Hp = np.zeros((nblk, C, K, K))
    Dp = np.zeros((nblk, C, S, K))
    Ep = np.zeros((nblk, C, S, S))
    for task in range(nblk * C):
        _gn_task(G, dG, w2, Hp, Dp, Ep, task)
    _gn_total(Hp, Dp, Ep, H, D, E)
