"""Fused numba kernels for the microfacet lobes (``ggx``, ``beckmann``).

Why hand-written: the numpy formulation in :mod:`gonio.brdf.microfacet` streams ~28 float64
temporaries through memory per evaluation, which ``benchmarks/brdf_eval.py`` measured as the
bottleneck (~0.13 of Mitsuba 3's vectorised ``roughconductor``).  These kernels compute the
same expressions per direction pair in registers, in the same operation order as the numpy
code, so the two paths agree to the last bit wherever only ``+ - * / sqrt`` are involved
and to a few ulp where libm (``exp``, ``erfc``, ``pow``, complex ``sqrt``) replaces numpy's
and scipy's implementations.  ``tests/brdf/test_kernels.py`` compares the two.

Compilation is deliberately IEEE-strict: ``fastmath=False`` (no reassociation, NaN
propagates, reciprocity is preserved bit for bit) and ``error_model="numpy"`` (x / 0 gives
inf or NaN like numpy instead of raising).  ``cache=True`` stores the machine code next to
this module, so the compile cost (a few seconds) is paid once per installation; the
microfacet lobes import this module only for batches of at least :data:`MIN_PAIRS`
evaluations, so small evaluations (CLI plots, tests) never import numba.  Threads: numba's
default (all cores), overridden by ``NUMBA_NUM_THREADS``.

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
