"""Fused numba kernels: the microfacet lobes (``ggx``, ``beckmann``) and RGL measured BRDFs.

Why hand-written: the numpy formulation in :mod:`gonio.brdf.microfacet` streams ~28 float64
temporaries through memory per evaluation, which ``benchmarks/brdf_eval.py`` measured as the
bottleneck (~0.13 of Mitsuba 3's vectorised ``roughconductor``); the RGL evaluator
(:mod:`gonio.brdf.rgl`) is dominated by gathers that numpy cannot fuse.  These kernels
compute the same expressions per direction pair in registers, in the same operation order
as the numpy code, so the two paths agree to the last bit wherever only ``+ - * / sqrt``
are involved and to a few ulp where libm (``exp``, ``erfc``, ``pow``, complex ``sqrt``,
``atan2``, ``asin``) replaces numpy's and scipy's implementations.
``tests/brdf/test_kernels.py`` compares the two.

Compilation is deliberately IEEE-strict: ``fastmath=False`` (no reassociation, NaN
propagates, reciprocity holds to rounding as in numpy) and ``error_model="numpy"`` (x / 0
gives inf or NaN like numpy instead of raising).  ``cache=True`` stores the machine code
next to this module, so the compile cost (~17 s for all kernels, cold) is paid once per
installation.  Importing numba and loading the cached code still costs ~0.5 s per process,
so the callers first import this module for a batch of 10^5 evaluations and from then on
use it from :data:`MIN_PAIRS`; CLI plots never import numba.  ``GONIO_NUMBA=0`` keeps
everything on numpy.  Threads: numba's default (all cores), overridden by
``NUMBA_NUM_THREADS``; batches below :data:`PARALLEL_PAIRS` run on the calling thread.

The numpy path stays the reference and handles everything the kernels do not (gradients,
parameter arrays of other shapes).
"""

from __future__ import annotations

import cmath
import math

from numba import njit, prange

from gonio.brdf.base import Array

__all__ = [
    "FRESNEL_CODES",
    "MIN_PAIRS",
    "PARALLEL_PAIRS",
    "ggx_hot",
    "ggx_hot_serial",
    "microfacet_eval",
    "microfacet_eval_serial",
    "rgl_eval",
]

#: Batches smaller than this (pairs times channels) stay on the numpy path.
MIN_PAIRS = 4096
#: From this many pairs times channels on, the multi-threaded kernels are used.  Below it
#: a thread launch costs more than it saves, and on a busy machine every launch waits for
#: the slowest thread to be scheduled (the model's 16384-row chunks made that 3x slower
#: than numpy).
PARALLEL_PAIRS = 65536

DIST_GGX, DIST_BECKMANN = 0, 1
G1_EXACT, G1_RATIONAL = 0, 1
FRESNEL_CODES = {"none": 0, "schlick": 1, "conductor": 2, "dielectric": 3}

_INV_PI = 1.0 / math.pi
_INV_2SQRTPI = 0.5 / math.sqrt(math.pi)
_HALF_PI = 0.5 * math.pi

_JIT = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}


@njit(**_JIT)
def _clip01(x: float) -> float:
    # np.clip semantics: NaN stays NaN.
    if x < 0.0:
        return 0.0
    if x > 1.0:
        return 1.0
    return x


@njit(**_JIT)
def _cdiv(a: complex, b: complex) -> complex:
    # numba's complex division raises on a zero divisor whatever the error model; numpy
    # gives NaN.  Reached only for wi == -wo (cos_d = 0, masked below the horizon).
    if b == 0.0:
        return complex(math.nan, math.nan)
    return a / b


@njit(**_JIT)
def _fresnel_complex(cos_d: float, eta: float, k: float) -> float:
    # Mirrors gonio.brdf.fresnel.fresnel_complex (see there for the why of each step).
    c = _clip01(cos_d)
    n = complex(eta, k)
    n2 = n * n
    s = cmath.sqrt(complex((eta - 1.0) * (eta + 1.0) - k * k + c * c, (2.0 * eta) * k))
    s = complex(s.real, abs(s.imag))
    rs = _cdiv(c - s, c + s)
    u = n2 * c
    if n2 == 0.0:
        rp = complex(-1.0, 0.0)
    else:
        rp = _cdiv(u - s, u + s)
    a = abs(rs)
    b = abs(rp)
    return 0.5 * (a * a + b * b)


@njit(**_JIT)
def _fresnel(code: int, cos_d: float, f0: float, eta: float, k: float) -> float:
    if code == 1:
        m = (1.0 - _clip01(cos_d)) ** 5.0
        return f0 + (1.0 - f0) * m
    if code == 2:
        return _fresnel_complex(cos_d, eta, k)
    return _fresnel_complex(cos_d, eta, 0.0)


@njit(**_JIT)
def _ggx_g1(cos_t: float, sin2_t: float, alpha: float) -> float:
    a2 = alpha * alpha
    r = math.sqrt(cos_t * cos_t + a2 * sin2_t)
    return 2.0 / (cos_t + r)


@njit(**_JIT)
def _beckmann_g1(cos_t: float, sin2_t: float, alpha: float, form: int) -> float:
    s = math.sqrt(sin2_t)
    a = cos_t / (alpha * s)
    if form == G1_EXACT:
        e = math.exp(-a * a)
        denom = cos_t - 0.5 * cos_t * math.erfc(a) + alpha * s * e * _INV_2SQRTPI
        return 1.0 / denom
    if a < 1.6:
        num = 3.535 + 2.181 * a
        den = 1.0 + 2.276 * a + 2.577 * a * a
        return num / (alpha * s * den)
    return 1.0 / cos_t


@njit(**_JIT, inline="always")
def _microfacet_pair(ix, iy, iz, ox, oy, oz, ks, alpha, f0, eta, k, dist, g1form, fresnel, out):
    # Bitwise |, not `or`: both tests always run, and NaN compares False on both, so NaN
    # directions reach the formula and come out NaN.
    below = (iz <= 0.0) | (oz <= 0.0)
    hx = ix + ox
    hy = iy + oy
    hz = iz + oz
    hxy2 = hx * hx + hy * hy
    hz2 = hz * hz
    hh = hxy2 + hz2
    si2 = ix * ix + iy * iy
    so2 = ox * ox + oy * oy
    cos_d = 0.5 * math.sqrt(hh)
    for c in range(out.shape[0]):
        al = alpha[c]
        a2 = al * al
        if dist == DIST_GGX:
            t = hh / (a2 * hz2 + hxy2)
            D = (a2 * _INV_PI) * (t * t)
            gi = _ggx_g1(iz, si2, al)
            go = _ggx_g1(oz, so2, al)
        else:
            tan2 = hxy2 / hz2
            D = math.exp(-tan2 / a2) * (hh * hh) / ((math.pi * a2) * (hz2 * hz2))
            gi = _beckmann_g1(iz, si2, al, g1form)
            go = _beckmann_g1(oz, so2, al, g1form)
        base = 0.25 * D * gi * go
        if fresnel == 0:
            v = ks[c] * base
        else:
            v = ks[c] * base * _fresnel(fresnel, cos_d, f0[c], eta[c], k[c])
        out[c] = 0.0 if below else v


@njit(**_JIT, parallel=True)
def microfacet_eval(
    wi: Array,
    wo: Array,
    ks: Array,
    alpha: Array,
    f0: Array,
    eta: Array,
    k: Array,
    dist: int,
    g1form: int,
    fresnel: int,
    out: Array,
) -> None:
    """Cook-Torrance ``ks D G1(wi) G1(wo) F / (4 cos_i cos_o)`` into ``out`` (1/sr).

    Parameters
    ----------
    wi, wo
        ``(N, 3)`` unit directions (local frame, +z the normal), C-contiguous, raveled to
        ``(3 N,)`` (interleaved rows: the loads vectorise), or ``(3, N)`` with contiguous
        rows (one per component, as the transposed Fortran-ordered chunks of
        :class:`gonio.brdf.base.Model`).
    ks, alpha, f0, eta, k
        ``(C,)`` parameter values per channel (unused ones may be any length-C array).
    dist, g1form, fresnel
        :data:`DIST_GGX`/:data:`DIST_BECKMANN`, :data:`G1_EXACT`/:data:`G1_RATIONAL`, and a
        value of :data:`FRESNEL_CODES`.
    out
        ``(N, C)`` result: exactly 0 where either ``z <= 0``, NaN where an input is NaN.
    """
    if wi.ndim == 1:
        for i in prange(out.shape[0]):
            j = 3 * i
            _microfacet_pair(
                wi[j], wi[j + 1], wi[j + 2], wo[j], wo[j + 1], wo[j + 2],
                ks, alpha, f0, eta, k, dist, g1form, fresnel, out[i],
            )  # fmt: skip
    else:
        for i in prange(out.shape[0]):
            _microfacet_pair(
                wi[0, i], wi[1, i], wi[2, i], wo[0, i], wo[1, i], wo[2, i],
                ks, alpha, f0, eta, k, dist, g1form, fresnel, out[i],
            )  # fmt: skip


# The serial twins repeat their parallel kernels' bodies on purpose: compiling one Python
# function twice (njit(parallel=True) and njit) with cache=True would share one on-disk
# cache entry, since numba's cache index does not tell the two builds apart.
@njit(**_JIT)
def microfacet_eval_serial(wi, wo, ks, alpha, f0, eta, k, dist, g1form, fresnel, out):
    """:func:`microfacet_eval` on one thread (no launch cost: for small batches)."""
    if wi.ndim == 1:
        for i in range(out.shape[0]):
            j = 3 * i
            _microfacet_pair(
                wi[j], wi[j + 1], wi[j + 2], wo[j], wo[j + 1], wo[j + 2],
                ks, alpha, f0, eta, k, dist, g1form, fresnel, out[i],
            )  # fmt: skip
    else:
        for i in range(out.shape[0]):
            _microfacet_pair(
                wi[0, i], wi[1, i], wi[2, i], wo[0, i], wo[1, i], wo[2, i],
                ks, alpha, f0, eta, k, dist, g1form, fresnel, out[i],
            )  # fmt: skip


@njit(**_JIT, inline="always")
def _ggx_hot_pair(ix, iy, iz, ox, oy, oz, a2, one_m, scale):
    hx = ix + ox
    hy = iy + oy
    hz = iz + oz
    hxy2 = hx * hx + hy * hy
    hz2 = hz * hz
    t = (hxy2 + hz2) / (hz2 * a2 + hxy2)
    t = t * t
    ri = math.sqrt(iz * iz * one_m + a2) + iz
    ro = math.sqrt(oz * oz * one_m + a2) + oz
    v = t / (ri * ro) * scale
    # Branch-free (a select), so that LLVM vectorises the loop: 2x over a branch.
    return 0.0 if (iz <= 0.0) | (oz <= 0.0) else v


@njit(**_JIT, parallel=True)
def ggx_hot(wi: Array, wo: Array, ks: float, alpha: float, out: Array) -> None:
    """GGX with F = 1 and scalar ``ks``, ``alpha`` into ``out`` of shape ``(N,)`` (1/sr).

    ``wi``, ``wo`` as for :func:`microfacet_eval`.  The same expression and operation
    order as the numpy hot path of :class:`gonio.brdf.microfacet.GGXLobe` (which differs
    from the general path in the last bits when the directions are not exactly unit
    length): ``f = ks alpha^2 / pi t^2 / ((ci + ri)(co + ro))``.
    """
    a2 = alpha * alpha
    one_m = 1.0 - a2
    scale = ks * a2 * _INV_PI
    if wi.ndim == 1:
        for i in prange(out.shape[0]):
            j = 3 * i
            out[i] = _ggx_hot_pair(
                wi[j], wi[j + 1], wi[j + 2], wo[j], wo[j + 1], wo[j + 2], a2, one_m, scale
            )
    else:
        for i in prange(out.shape[0]):
            out[i] = _ggx_hot_pair(
                wi[0, i], wi[1, i], wi[2, i], wo[0, i], wo[1, i], wo[2, i], a2, one_m, scale
            )


@njit(**_JIT)
def ggx_hot_serial(wi, wo, ks, alpha, out):
    """:func:`ggx_hot` on one thread (no launch cost: for small batches)."""
    a2 = alpha * alpha
    one_m = 1.0 - a2
    scale = ks * a2 * _INV_PI
    if wi.ndim == 1:
        for i in range(out.shape[0]):
            j = 3 * i
            out[i] = _ggx_hot_pair(
                wi[j], wi[j + 1], wi[j + 2], wo[j], wo[j + 1], wo[j + 2], a2, one_m, scale
            )
    else:
        for i in range(out.shape[0]):
            out[i] = _ggx_hot_pair(
                wi[0, i], wi[1, i], wi[2, i], wo[0, i], wo[1, i], wo[2, i], a2, one_m, scale
            )


# ---------------------------------------------------------------------------------------
# RGL-EPFL measured BRDFs: the per-pair form of gonio.brdf.rgl.RGLBRDF._eval_active, in
# the same operation order (see there for the mathematics and the why of each step).


@njit(**_JIT, inline="always")
def _param_lerp(values, x):
    n = values.size
    if n == 1:
        return 0, 0.0
    i = 0  # searchsorted(values, x, side="left")
    while i < n and values[i] < x:
        i += 1
    i = min(max(i - 1, 0), n - 2)
    p0 = values[i]
    p1 = values[i + 1]
    return i, _clip01((x - p0) / (p1 - p0))


@njit(**_JIT, inline="always")
def _elevation(x, y, z):
    d = math.sqrt(x * x + y * y + (z - 1.0) * (z - 1.0))
    return 2.0 * math.asin(_clip01(0.5 * d))


@njit(**_JIT, inline="always")
def _cell(u, v, nx, ny):
    """Bilinear cell (ix, iy) and fractions (fx, fy) of a unit-square position."""
    px = _clip01(u) * (nx - 1)
    py = _clip01(v) * (ny - 1)
    ix = min(int(px), nx - 2)
    iy = min(int(py), ny - 2)
    return ix, iy, px - ix, py - iy


@njit(**_JIT, inline="always")
def _bilinear(table, u, v):
    ny, nx = table.shape
    ix, iy, fx, fy = _cell(u, v, nx, ny)
    v00 = table[iy, ix]
    v10 = table[iy, ix + 1]
    v01 = table[iy + 1, ix]
    v11 = table[iy + 1, ix + 1]
    return (1 - fy) * ((1 - fx) * v00 + fx * v10) + fy * ((1 - fx) * v01 + fx * v11)


@njit(**_JIT, inline="always")
def _take(rows, j, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3):
    # _Slices.take: 0 + w0 v0 + w1 v1 (+ w2 v2 + w3 v3), in that order.
    v = 0.0
    v += w0 * rows[s0, cell, j]
    v += w1 * rows[s1, cell, j]
    if ns == 4:
        v += w2 * rows[s2, cell, j]
        v += w3 * rows[s3, cell, j]
    return v


@njit(**_JIT, inline="always")
def _rgl_pair(
    ix_, iy_, iz_, ox_, oy_, oz_, phi_vals, theta_vals, patch, spec, ndf, sigma,
    vh, vw, ry, rx, reduction, isotropic, jacobian, out,
):  # fmt: skip
    wix, wiy, wox, woy = ix_, iy_, ox_, oy_
    if reduction >= 2:
        sy = -1.0 if wiy >= 0 else 1.0
        sx = sy
        if reduction == 4:
            sx = -1.0 if wix >= 0 else 1.0
        wix *= sx
        wiy *= sy
        wox *= sx
        woy *= sy
    mx = wix + wox
    my = wiy + woy
    mz = iz_ + oz_
    norm = math.sqrt(mx * mx + my * my + mz * mz)
    mx /= norm
    my /= norm
    mz /= norm
    theta_i = _elevation(wix, wiy, iz_)
    phi_i = math.atan2(wiy, wix)
    theta_m = _elevation(mx, my, mz)
    phi_m = math.atan2(my, mx)
    u_wi_x = math.sqrt(theta_i / _HALF_PI)
    u_wi_y = (phi_i + math.pi) / (2 * math.pi)
    rel = phi_m - phi_i if isotropic else phi_m
    um_y = (rel + math.pi) / (2 * math.pi)
    um_y -= math.floor(um_y)
    um_x = math.sqrt(theta_m / _HALF_PI)

    # (phi_i, theta_i) corner slices and weights (_Slices)
    ip, wp = _param_lerp(phi_vals, phi_i)
    it, wt = _param_lerp(theta_vals, theta_i)
    n_t = theta_vals.size
    it1 = min(it + 1, n_t - 1)
    s0 = ip * n_t + it
    s1 = ip * n_t + it1
    w0 = (1 - wp) * (1 - wt)
    w1 = (1 - wp) * wt
    ns = 2
    s2 = s3 = 0
    w2 = w3 = 0.0
    if phi_vals.size > 1:
        ip1 = min(ip + 1, phi_vals.size - 1)
        s2 = ip1 * n_t + it
        s3 = ip1 * n_t + it1
        w2 = wp * (1 - wt)
        w3 = wp * wt
        ns = 4

    # inverse VNDF warp (_invert_vndf)
    cx, cy, fx, fy = _cell(um_x, um_y, vw, vh)
    cell = cy * (vw - 1) + cx
    v00 = _take(patch, 0, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    v10 = _take(patch, 1, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    v01 = _take(patch, 2, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    v11 = _take(patch, 3, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    prev0 = _take(patch, 4, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    prev1 = _take(patch, 5, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    r0 = _take(patch, 6, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    r1 = _take(patch, 7, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    marg_prev = _take(patch, 8, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
    c0 = v00 + (v01 - v00) * fy
    c1 = v10 + (v11 - v10) * fy
    s_x = fx * (c0 + (c1 - c0) * 0.5 * fx) / (vw - 1) + prev0 + (prev1 - prev0) * fy
    row = r0 + (r1 - r0) * fy
    s_x = s_x / row if row > 0 else fx
    s_y = fy * (r0 + (r1 - r0) * 0.5 * fy) / (vh - 1) + marg_prev

    # bilinear over the sample-space position, multilinear over (phi_i, theta_i)
    cx, cy, fx, fy = _cell(s_x, s_y, rx, ry)
    cell = cy * (rx - 1) + cx
    c00 = (1 - fx) * (1 - fy)
    c10 = fx * (1 - fy)
    c01 = (1 - fx) * fy
    c11 = fx * fy
    n_ch = out.shape[0]
    scale = 1.0
    if jacobian:
        scale = _bilinear(ndf, um_x, um_y) / (4.0 * _bilinear(sigma, u_wi_x, u_wi_y))
    for c in range(n_ch):
        f = c00 * _take(spec, c, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
        f += c10 * _take(spec, n_ch + c, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
        f += c01 * _take(spec, 2 * n_ch + c, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
        f += c11 * _take(spec, 3 * n_ch + c, cell, ns, s0, s1, s2, s3, w0, w1, w2, w3)
        if jacobian:
            f = f * scale
        out[c] = f / oz_


@njit(**_JIT, parallel=True)
def rgl_eval(
    wi, wo, phi_vals, theta_vals, patch, spec, ndf, sigma,
    vh, vw, ry, rx, reduction, isotropic, jacobian, out,
):  # fmt: skip
    """``f_r`` (1/sr) of an RGL measured BRDF for ``(N, 3)`` pairs above the horizon.

    The arguments are the tables of :class:`gonio.brdf.rgl.RGLBRDF` (``_patch`` and
    ``_spec`` transposed to ``(slices, cells, rows)``, so that the rows one look-up reads
    share a cache line; ``_ndf``, ``_sigma``, grid sizes and flags); ``out`` is
    ``(N, channels)``.
    Bit for bit the numpy path where numpy's and libm's ``arctan2``/``arcsin`` agree (they
    differ in the last bit for ~8% of arguments; see tests/brdf/test_kernels.py).
    """
    for i in prange(wi.shape[0]):
        _rgl_pair(
            wi[i, 0], wi[i, 1], wi[i, 2], wo[i, 0], wo[i, 1], wo[i, 2], phi_vals,
            theta_vals, patch, spec, ndf, sigma, vh, vw, ry, rx, reduction, isotropic,
            jacobian, out[i],
        )  # fmt: skip
