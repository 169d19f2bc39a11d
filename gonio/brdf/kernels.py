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
next to this module, so the compile cost is paid once per installation (cold, on the
2-core machine of 2026-12-03: the first RGL evaluation 25 s, the microfacet kernels
2-5 s each); every input is passed as a read-only view (:func:`gonio.brdf.base.readonly`)
so that one compilation serves all callers.  Importing numba and loading the cached code
still costs ~0.5 s per process, so the callers first import this module for a batch of
10^5 evaluations and from then on use it from :data:`MIN_PAIRS`; CLI plots never import
numba.  ``GONIO_NUMBA=0`` keeps everything on numpy.  Threads: numba's default (all
cores), overridden by ``NUMBA_NUM_THREADS``; batches below :data:`PARALLEL_PAIRS` run on
the calling thread.

The numpy path stays the reference and handles everything the kernels do not (gradients,
parameter arrays of other shapes).
"""

from __future__ import annotations

import cmath
import math

import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from gonio.brdf.base import Array, readonly
from gonio.brdf.rgl import ATAN_C3, ATAN_C5, ATAN_C7, ATAN_NODES

__all__ = [
    "FRESNEL_CODES",
    "MIN_PAIRS",
    "PARALLEL_PAIRS",
    "ggx_hot",
    "ggx_hot_serial",
    "microfacet_eval",
    "microfacet_eval_serial",
    "readonly",
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
_INV_HALF_PI = 1.0 / _HALF_PI  # gonio.brdf.rgl's reciprocals of constants
_INV_2PI = 0.5 / math.pi

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
# the same operation order (see there for the mathematics and the why of each step), so
# the two paths agree bit for bit.  Why it is shaped as it is (benchmarks/measured_eval.py):
# - the angles come from the table-plus-series arctangent of gonio.brdf.rgl (libm's atan2
#   cost ~60 ns a call here, four calls a pair, more than Mitsuba's whole evaluation), the
#   four of a block in passes of their own, so that all but the table loads vectorise
#   (AVX-512 host: the angle stage 17 -> 9 ms of 2e5 pairs, the kernel ~1.2x);
# - pairs go through in blocks of _RGL_BLOCK, one short loop per stage: one pair's chain
#   (angles -> VNDF cell -> gathers -> sample-space cell -> gathers) is longer than the
#   CPU's reorder window, so a loop over whole pairs waited for every cache miss in turn,
#   while a loop that only gathers keeps a dozen misses in flight;
# - the tables hold what the file holds in float32 (VNDF, RGB corners) as float32 (exact;
#   the normalisation is applied per slice on the fly, the same product the numpy path
#   stores), unpacked (1.5 MB instead of the numpy path's 9 MB of packed patches, mostly
#   in L2), the two theta_i slices one look-up blends side by side;
# - 512-bit vectors (_wide_vectors): LLVM's default on AVX-512 hosts is 256-bit, and the
#   loops over a block, gathers included, took 1.3x as long at that width;
# - the RGB blend is a loop over pairs like the others (numba does not run LLVM's SLP
#   vectoriser, so a blend over the four channel lanes of one pair stayed scalar: 40 % of
#   the kernel's time); the VNDF records a block reads are prefetched as soon as their
#   index is known, with the Jacobian's look-ups in between to hide the misses (the RGB
#   records prefetched one block ahead gained nothing: the copies it takes cost as much).

_RGL_BLOCK = 64
# unsigned offsets: numba indexes with them without the negative-index wraparound select
_U0, _U1, _U2, _U3, _U4, _U5, _U6, _U7, _U8, _U9, _U10, _U11, _U12, _U13, _U14, _U15 = (
    np.uint64(i) for i in range(16)
)


@intrinsic
def _wide_vectors(typingctx):
    """Let LLVM vectorise the calling function with 512-bit registers where it can.

    Its X86 cost model prefers 256-bit vectors on AVX-512 hosts (the frequency penalty of
    older Xeons); on the benchmark machine (Emerald Rapids) the RGL kernel ran 1.3x
    faster at 512 bits.  A function attribute, so that it applies to this kernel only
    and needs no process-wide ``NUMBA_CPU_FEATURES`` (which would also change every
    cache key); on a host without AVX-512 it changes nothing.  Emits no code.
    """

    def codegen(context, builder, signature, args):
        # llvmlite's attribute set admits only its list of keyword attributes; the
        # string attribute goes in through the set itself (a no-op if that ever fails)
        try:
            set.add(builder.function.attributes, '"prefer-vector-width"="512"')
        except TypeError:  # pragma: no cover - another llvmlite
            pass
        return context.get_dummy_value()

    return types.void(), codegen


@intrinsic
def _prefetch(typingctx, arr, idx):
    """Start loading the cache line of ``arr[idx]`` (a hint: no fault, no result)."""

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]])
        i32 = llvm_ir.IntType(32)
        fnty = llvm_ir.FunctionType(llvm_ir.VoidType(), [ptr.type, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [ptr, i32(0), i32(3), i32(1)])  # read, keep in all levels, data
        return context.get_dummy_value()

    return types.void(arr, idx), codegen


# prange iterations (each with its scratch): get_num_threads() would keep the code uncached
_RGL_CHUNKS = 64


@njit(**_JIT)
def _inv_spacing(values):
    """``1 / diff(values)``: gonio.brdf.rgl._param_lerp's reciprocal interval widths."""
    return 1.0 / (values[1:] - values[:-1])


@njit(**_JIT, inline="always")
def _lerp_index(values, inv, x):
    # gonio.brdf.rgl._param_lerp: searchsorted(side="left") as a count, without branches;
    # inv = _inv_spacing(values)
    n = values.size
    if n == 1:
        return 0, 0.0
    i = 0
    for k in range(n):
        i += values[k] < x
    i = min(max(i - 1, 0), n - 2)
    return i, _clip01((x - values[i]) * inv[i])


@njit(**_JIT, inline="always")
def _cell(u, v, nx, ny):
    """Bilinear cell (ix, iy) and fractions (fx, fy) of a unit-square position."""
    px = _clip01(u) * (nx - 1)
    py = _clip01(v) * (ny - 1)
    ix = min(int(px), nx - 2)
    iy = min(int(py), ny - 2)
    return ix, iy, px - ix, py - iy


@njit(**_JIT)
def _rows_equal(table):
    """gonio.brdf.rgl._rows_equal of a 2-D table."""
    for i in range(1, table.shape[0]):
        for k in range(table.shape[1]):
            if table[i, k] != table[0, k]:
                return False
    return True


@njit(**_JIT, inline="always")
def _lerp_x(table, u):
    """gonio.brdf.rgl._lerp_x: ``table`` along x at ``u``, all its rows being equal."""
    nx = table.shape[1]
    px = _clip01(u) * (nx - 1)
    ix = min(int(px), nx - 2)
    fx = px - ix
    return (1 - fx) * table[0, ix] + fx * table[0, ix + 1]


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
def _rgb_blend_store(out, i, spec, q, ps, w0, w1, fx, fy, scale, ok, masked):
    """Store the RGB ``f_r`` (1/sr) of one isotropic look-up in ``out[i, :3]``.

    The two theta_i slices of one RGB cell's record start at float32 slots ``q`` and
    ``q + ps`` of ``spec`` (4 corners x 4 channel slots each, corner-major); they are
    blended with the slice weights ``w0, w1``, then bilinearly over the cell (fractions
    ``fx, fy`` in [0, 1]), and multiplied by ``scale`` (the Jacobian over wo_z, or
    1 / wo_z without it).  A pair that is not ``ok`` gets ``masked`` (0 or NaN) instead.
    """
    # Channels padded to 4 (lane 3 is computed and dropped).  numba leaves LLVM's SLP
    # vectoriser off, so this stays scalar; only the general block, whose files are
    # rare, still uses it.  The operation order is the numpy path's (bit for bit).
    c00 = (1 - fx) * (1 - fy)
    c10 = fx * (1 - fy)
    c01 = (1 - fx) * fy
    c11 = fx * fy
    q1 = q + ps
    x00 = w0 * spec[q] + w1 * spec[q1]
    x01 = w0 * spec[q + _U1] + w1 * spec[q1 + _U1]
    x02 = w0 * spec[q + _U2] + w1 * spec[q1 + _U2]
    x03 = w0 * spec[q + _U3] + w1 * spec[q1 + _U3]
    x10 = w0 * spec[q + _U4] + w1 * spec[q1 + _U4]
    x11 = w0 * spec[q + _U5] + w1 * spec[q1 + _U5]
    x12 = w0 * spec[q + _U6] + w1 * spec[q1 + _U6]
    x13 = w0 * spec[q + _U7] + w1 * spec[q1 + _U7]
    x20 = w0 * spec[q + _U8] + w1 * spec[q1 + _U8]
    x21 = w0 * spec[q + _U9] + w1 * spec[q1 + _U9]
    x22 = w0 * spec[q + _U10] + w1 * spec[q1 + _U10]
    x23 = w0 * spec[q + _U11] + w1 * spec[q1 + _U11]
    x30 = w0 * spec[q + _U12] + w1 * spec[q1 + _U12]
    x31 = w0 * spec[q + _U13] + w1 * spec[q1 + _U13]
    x32 = w0 * spec[q + _U14] + w1 * spec[q1 + _U14]
    x33 = w0 * spec[q + _U15] + w1 * spec[q1 + _U15]
    v0 = c00 * x00
    v0 += c10 * x10
    v0 += c01 * x20
    v0 += c11 * x30
    v1 = c00 * x01
    v1 += c10 * x11
    v1 += c01 * x21
    v1 += c11 * x31
    v2 = c00 * x02
    v2 += c10 * x12
    v2 += c01 * x22
    v2 += c11 * x32
    v3 = c00 * x03
    v3 += c10 * x13
    v3 += c01 * x23
    v3 += c11 * x33
    v0 = v0 * scale
    v1 = v1 * scale
    v2 = v2 * scale
    v3 = v3 * scale
    out[i, 0] = v0 if ok else masked
    out[i, 1] = v1 if ok else masked
    out[i, 2] = v2 if ok else masked


@njit(**_JIT)
def _rgl_block(
    wi, wo, b0, b1, phi_vals, theta_vals, inv_p, inv_t, n_t2, rec32, rec64, rows, spec,
    spec_stride, ndf, sigma, ndf_flat, sigma_flat, vh, vw, ry, rx, reduction, isotropic,
    relative_only, jacobian, atan_table, out, f, k, g,
):  # fmt: skip
    """Pairs ``b0 .. b1`` (at most _RGL_BLOCK); ``f``, ``k``, ``g`` are scratch."""
    _wide_vectors()
    nb = b1 - b0
    n_p = phi_vals.size
    n_s = n_p * n_t2  # slices
    n_ch = out.shape[1]
    # 1. directions -> angles -> unit-square coordinates.  The four arctangents of a pair
    # go through passes of their own (arguments; reduction to [0, 1] and table index;
    # table loads; series): a loop with a table load in it stays scalar, the passes
    # without one are vectorised (packed IEEE divisions and square roots, the same bits).
    # Scratch: g[0:4] |y| then the octant flag, g[4:8] |x| then the table node, g[8:12]
    # the reduced argument then the angle; f[7:11] the signed arguments of phi_i (or of
    # the relative azimuth) and of phi_m; k[0:4] the table indices, k[4] the relative path.
    for j in range(nb):
        wix, wiy, wiz = wi[b0 + j, 0], wi[b0 + j, 1], wi[b0 + j, 2]
        wox, woy, woz = wo[b0 + j, 0], wo[b0 + j, 1], wo[b0 + j, 2]
        # RGLBRDF.eval_channels' masks: non-finite input -> NaN, the horizon -> 0; such
        # pairs go through the arithmetic as the normal (table indices stay in range)
        finite = (
            math.isfinite(wix) and math.isfinite(wiy) and math.isfinite(wiz)
            and math.isfinite(wox) and math.isfinite(woy) and math.isfinite(woz)
        )  # fmt: skip
        k[5, j] = 0 if finite and wiz > 0 and woz > 0 else (1 if finite else 2)
        if k[5, j] != 0:
            wix = wiy = wox = woy = 0.0
            wiz = woz = 1.0
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
        mz = wiz + woz
        # gonio.brdf.rgl._elevation: 2 asin(|v - z| / 2), the asin as an arctangent
        s = _clip01(0.5 * math.sqrt(wix * wix + wiy * wiy + (wiz - 1.0) * (wiz - 1.0)))
        g[0, j] = s
        g[4, j] = math.sqrt((1.0 - s) * (1.0 + s))
        g[1, j] = math.sqrt(mx * mx + my * my)
        g[5, j] = mz
        rel_path = relative_only and (wix != 0.0 or wiy != 0.0)
        k[4, j] = rel_path
        if rel_path:
            cy = my * wix - mx * wiy
            cx = mx * wix + my * wiy
        else:
            cy = wiy
            cx = wix
        f[7, j] = cy
        f[8, j] = cx
        f[9, j] = my
        f[10, j] = mx
        g[2, j] = abs(cy)
        g[6, j] = abs(cx)
        g[3, j] = abs(my)
        g[7, j] = abs(mx)
        f[6, j] = woz
    for r in range(4):  # gonio.brdf.rgl._atan2_pos: the argument in [0, 1], its node
        for j in range(nb):
            y = g[r, j]
            x = g[4 + r, j]
            hi = max(x, y)
            t = min(x, y) / hi if hi > 0.0 else 0.0
            g[8 + r, j] = t
            k[r, j] = int(t * ATAN_NODES + 0.5)
            g[r, j] = 1.0 if y > x else 0.0
    for r in range(4):
        for j in range(nb):
            g[4 + r, j] = atan_table[k[r, j]]
    for r in range(4):  # gonio.brdf.rgl._atan01: table node + series of the remainder
        for j in range(nb):
            t = g[8 + r, j]
            t0 = k[r, j] * (1.0 / ATAN_NODES)
            d = (t - t0) / (1.0 + t * t0)
            z = d * d
            a = g[4 + r, j] + (d + d * z * (ATAN_C3 + z * (ATAN_C5 + z * ATAN_C7)))
            g[8 + r, j] = _HALF_PI - a if g[r, j] != 0.0 else a
    for j in range(nb):
        theta_i = 2.0 * g[8, j]
        theta_m = g[9, j]
        # gonio.brdf.rgl._atan2: the quadrant from the signs of the arguments
        a = g[10, j]
        a = math.pi - a if math.copysign(1.0, f[8, j]) < 0.0 else a
        c_angle = math.copysign(a, f[7, j])
        if k[4, j]:
            phi_i = 0.0
            rel = c_angle
        else:
            phi_i = c_angle
            a = g[11, j]
            a = math.pi - a if math.copysign(1.0, f[10, j]) < 0.0 else a
            phi_m = math.copysign(a, f[9, j])
            rel = phi_m - phi_i if isotropic else phi_m
            if relative_only:
                phi_i = 0.0
        um_y = (rel + math.pi) * _INV_2PI
        um_y -= math.floor(um_y)
        f[0, j] = theta_i
        f[1, j] = phi_i
        f[2, j] = math.sqrt(theta_i * _INV_HALF_PI)  # u_wi
        f[3, j] = (phi_i + math.pi) * _INV_2PI
        f[4, j] = math.sqrt(theta_m * _INV_HALF_PI)  # u_m
        f[5, j] = um_y
    # 2. (phi_i, theta_i) slices and weights (_Slices); the VNDF cell
    for j in range(nb):
        it, wt = _lerp_index(theta_vals, inv_t, f[0, j])
        ip, wp = _lerp_index(phi_vals, inv_p, f[1, j])
        k[0, j] = ip * n_t2 + it
        k[1, j] = min(ip + 1, n_p - 1) * n_t2 + it
        f[7, j] = (1 - wp) * (1 - wt)
        f[8, j] = (1 - wp) * wt
        f[9, j] = wp * (1 - wt)
        f[10, j] = wp * wt
        cx, cy, fx, fy = _cell(f[4, j], f[5, j], vw, vh)
        k[2, j] = cy * (vw - 1) + cx
        k[3, j] = cy
        f[11, j] = fx
        f[12, j] = fy
    # 3. gather the patch entries of the two theta_i slices (a loop of loads only): one
    # 32-byte record per (VNDF cell, slice), the two slices side by side
    for j in range(nb):
        q = np.uint64((k[2, j] * n_s + k[0, j]) * 8)  # float32 slot of (cell, s0)
        h = q >> _U1  # its float64 slot
        g[0, j] = rec32[q]
        g[1, j] = rec32[q + _U1]
        g[2, j] = rec32[q + _U2]
        g[3, j] = rec32[q + _U3]
        g[4, j] = rec64[h + _U2]
        g[5, j] = rec64[h + _U3]
        g[6, j] = rec32[q + _U8]
        g[7, j] = rec32[q + _U9]
        g[8, j] = rec32[q + _U10]
        g[9, j] = rec32[q + _U11]
        g[10, j] = rec64[h + _U6]
        g[11, j] = rec64[h + _U7]
    # 4. inverse VNDF warp (_invert_vndf) -> the sample-space cell
    inv_w1 = 1.0 / (vw - 1)
    inv_h1 = 1.0 / (vh - 1)
    for j in range(nb):
        s0 = k[0, j]
        cy = k[3, j]
        w0 = f[7, j]
        w1 = f[8, j]
        fx = f[11, j]
        fy = f[12, j]
        n0 = rows[cy, s0, 3]
        n1 = rows[cy, s0 + 1, 3]
        v00 = w0 * (g[0, j] * n0) + w1 * (g[6, j] * n1)
        v10 = w0 * (g[1, j] * n0) + w1 * (g[7, j] * n1)
        v01 = w0 * (g[2, j] * n0) + w1 * (g[8, j] * n1)
        v11 = w0 * (g[3, j] * n0) + w1 * (g[9, j] * n1)
        prev0 = w0 * g[4, j] + w1 * g[10, j]
        prev1 = w0 * g[5, j] + w1 * g[11, j]
        r0 = w0 * rows[cy, s0, 0] + w1 * rows[cy, s0 + 1, 0]
        r1 = w0 * rows[cy, s0, 1] + w1 * rows[cy, s0 + 1, 1]
        marg_prev = w0 * rows[cy, s0, 2] + w1 * rows[cy, s0 + 1, 2]
        if n_p > 1:
            s2 = k[1, j]
            w2 = f[9, j]
            w3 = f[10, j]
            n2 = rows[cy, s2, 3]
            n3 = rows[cy, s2 + 1, 3]
            q = np.uint64((k[2, j] * n_s + s2) * 8)
            h = q >> _U1
            v00 = v00 + w2 * (rec32[q] * n2) + w3 * (rec32[q + _U8] * n3)
            v10 = v10 + w2 * (rec32[q + _U1] * n2) + w3 * (rec32[q + _U9] * n3)
            v01 = v01 + w2 * (rec32[q + _U2] * n2) + w3 * (rec32[q + _U10] * n3)
            v11 = v11 + w2 * (rec32[q + _U3] * n2) + w3 * (rec32[q + _U11] * n3)
            prev0 = prev0 + w2 * rec64[h + _U2] + w3 * rec64[h + _U6]
            prev1 = prev1 + w2 * rec64[h + _U3] + w3 * rec64[h + _U7]
            r0 = r0 + w2 * rows[cy, s2, 0] + w3 * rows[cy, s2 + 1, 0]
            r1 = r1 + w2 * rows[cy, s2, 1] + w3 * rows[cy, s2 + 1, 1]
            marg_prev = marg_prev + w2 * rows[cy, s2, 2] + w3 * rows[cy, s2 + 1, 2]
        c0 = v00 + (v01 - v00) * fy
        c1 = v10 + (v11 - v10) * fy
        s_x = fx * (c0 + (c1 - c0) * 0.5 * fx) * inv_w1 + prev0 + (prev1 - prev0) * fy
        row = r0 + (r1 - r0) * fy
        s_x = s_x / row if row > 0 else fx
        s_y = fy * (r0 + (r1 - r0) * 0.5 * fy) * inv_h1 + marg_prev
        cx, cy, fx, fy = _cell(s_x, s_y, rx, ry)
        k[4, j] = cy * (rx - 1) + cx
        f[11, j] = fx
        f[12, j] = fy
    # 5. bilinear over the sample-space position, multilinear over (phi_i, theta_i): one
    # record of ps float32 per (cell, slice), the corners of every channel (corner-major)
    ps = np.uint64(spec_stride)
    # First only touch the two lines of every pair's records: a loop of independent loads
    # keeps many cache misses in flight, while the loop below, ~150 instructions a pair,
    # would wait for each in turn (the table does not stay in L2 beside the VNDF's).
    touch = 0.0
    for j in range(nb):
        q = np.uint64((k[4, j] * n_s + k[0, j]) * spec_stride)
        touch += spec[q] + spec[q + ps]
    g[0, 0] = touch  # keeps the loads (g is scratch, free again here)
    for j in range(nb):
        q = np.uint64((k[4, j] * n_s + k[0, j]) * spec_stride)
        w0 = f[7, j]
        w1 = f[8, j]
        fx = f[11, j]
        fy = f[12, j]
        c00 = (1 - fx) * (1 - fy)
        c10 = fx * (1 - fy)
        c01 = (1 - fx) * fy
        c11 = fx * fy
        # one division for all channels, as the numpy path
        if jacobian:
            dv = _lerp_x(ndf, f[4, j]) if ndf_flat else _bilinear(ndf, f[4, j], f[5, j])
            sv = _lerp_x(sigma, f[2, j]) if sigma_flat else _bilinear(sigma, f[2, j], f[3, j])
            scale = dv / (4.0 * sv * f[6, j])
        else:
            scale = 1.0 / f[6, j]
        flag = k[5, j]
        masked = 0.0 if flag == 1 else np.nan
        if n_ch == 3 and n_p == 1:
            _rgb_blend_store(out, b0 + j, spec, q, ps, w0, w1, fx, fy, scale, flag == 0, masked)
            continue
        q2 = np.uint64((k[4, j] * n_s + k[1, j]) * spec_stride)
        w2 = f[9, j]
        w3 = f[10, j]
        cs = 4 if n_ch == 3 else n_ch  # channel slots per corner (RGBRDF.kernel_tables)
        for ch in range(n_ch):
            e0 = np.uint64(ch)
            e1 = np.uint64(cs + ch)
            e2 = np.uint64(2 * cs + ch)
            e3 = np.uint64(3 * cs + ch)
            a0 = w0 * spec[q + e0] + w1 * spec[q + ps + e0]
            a1 = w0 * spec[q + e1] + w1 * spec[q + ps + e1]
            a2 = w0 * spec[q + e2] + w1 * spec[q + ps + e2]
            a3 = w0 * spec[q + e3] + w1 * spec[q + ps + e3]
            if n_p > 1:
                a0 = a0 + w2 * spec[q2 + e0] + w3 * spec[q2 + ps + e0]
                a1 = a1 + w2 * spec[q2 + e1] + w3 * spec[q2 + ps + e1]
                a2 = a2 + w2 * spec[q2 + e2] + w3 * spec[q2 + ps + e2]
                a3 = a3 + w2 * spec[q2 + e3] + w3 * spec[q2 + ps + e3]
            v = c00 * a0
            v += c10 * a1
            v += c01 * a2
            v += c11 * a3
            v = v * scale
            out[b0 + j, ch] = v if flag == 0 else masked


# The common case, every shared file: isotropic, one phi_i, sigma independent of phi_i (one
# arctangent for the relative azimuth), NDF and sigma with equal rows (linear in theta
# alone), RGB.  Every pass is a loop of fixed trip count
# _RGL_BLOCK over rows of two scratch arrays (float64 S, integer K) with no branch in it
# (selects, bitwise & and | on booleans instead of `and`/`or`, which are branches), so
# that LLVM vectorises all of them, the table look-ups included (AVX-512 gathers): the
# general block above, whose passes mix three scratch arrays and branch per pair, stayed
# mostly scalar.  A block past the end of the input repeats the last pair (reads stay in
# bounds) and stores only its nb results.  The same IEEE operations as the numpy path.
# Rows of S (float64): the arctangents' arguments (Y, X) and results (A), the signed
# arguments of the azimuth's (CY, CX), phi_i at normal incidence, wo_z, the value of
# a masked pair (0 or NaN), the unit-square coordinates, the slice weights, the cell
# fractions in the VNDF (FX, FY) and the RGB table (SX, SY), the Jacobian, 12 gathered
# VNDF record entries (G0...), the three channels' results (R0...).  Rows of K (intp): the
# relative path, the unmasked flag, the theta_i slice, the VNDF cell and row, the RGB cell.
Y0, Y1, Y2, X0, X1, X2, A0, A1, A2, CY, CX, PHI0, WOZ, MVAL = range(14)
UWI, UMX, UMY, W0, W1, FX, FY, SX, SY, SCALE, G0 = range(14, 25)
R0 = G0 + 12
_NS = R0 + 3
KREL, KOK, KIT, KCELL, KCY, KSPEC = range(6)
_NK = 6


@njit(**_JIT, inline="always")
def _rgl_block_rel(
    wi, wo, b0, nb, n, theta_vals, inv_t, n_t2, rec32, rec64, rows, spec, spec_stride, ndf,
    sigma, vh, vw, ry, rx, jacobian, atan_table, out, S, K,
):  # fmt: skip
    """:func:`_rgl_block` for the common case: pairs ``b0 .. b0 + nb`` of ``n``."""
    # pass 1: directions
    last = n - 1
    for j in range(_RGL_BLOCK):
        jj = min(b0 + j, last)
        wix = wi[jj, 0]
        wiy = wi[jj, 1]
        wiz = wi[jj, 2]
        wox = wo[jj, 0]
        woy = wo[jj, 1]
        woz = wo[jj, 2]
        finite = (
            math.isfinite(wix) & math.isfinite(wiy) & math.isfinite(wiz)
            & math.isfinite(wox) & math.isfinite(woy) & math.isfinite(woz)
        )  # fmt: skip
        ok = finite & (wiz > 0.0) & (woz > 0.0)
        S[MVAL, j] = 0.0 if finite else np.nan
        K[KOK, j] = ok
        wix = wix if ok else 0.0
        wiy = wiy if ok else 0.0
        wox = wox if ok else 0.0
        woy = woy if ok else 0.0
        wiz = wiz if ok else 1.0
        woz = woz if ok else 1.0
        mx = wix + wox
        my = wiy + woy
        mz = wiz + woz
        s = _clip01(0.5 * math.sqrt(wix * wix + wiy * wiy + (wiz - 1.0) * (wiz - 1.0)))
        S[Y0, j] = s
        S[X0, j] = math.sqrt((1.0 - s) * (1.0 + s))
        S[Y1, j] = math.sqrt(mx * mx + my * my)
        S[X1, j] = mz
        rel = (wix != 0.0) | (wiy != 0.0)
        K[KREL, j] = rel
        cy = my * wix - mx * wiy if rel else my
        cx = mx * wix + my * wiy if rel else mx
        S[CY, j] = cy
        S[CX, j] = cx
        S[Y2, j] = abs(cy)
        S[X2, j] = abs(cx)
        # phi_i = atan2(wiy, wix) of a normal incidence (both +-0): the arctangent's value
        a = math.pi if math.copysign(1.0, wix) < 0.0 else 0.0
        S[PHI0, j] = math.copysign(a, wiy)
        S[WOZ, j] = woz
    # the three arctangents
    for j in range(_RGL_BLOCK):
        for r in range(3):
            y = S[Y0 + r, j]
            x = S[X0 + r, j]
            hi = max(x, y)
            t = min(x, y) / hi if hi > 0.0 else 0.0
            kk = int(t * ATAN_NODES + 0.5)
            t0 = kk * (1.0 / ATAN_NODES)
            d = (t - t0) / (1.0 + t * t0)
            z = d * d
            a = atan_table[kk] + (d + d * z * (ATAN_C3 + z * (ATAN_C5 + z * ATAN_C7)))
            S[A0 + r, j] = _HALF_PI - a if y > x else a
    for j in range(_RGL_BLOCK):
        theta_i = 2.0 * S[A0, j]
        theta_m = S[A1, j]
        a = S[A2, j]
        a = math.pi - a if math.copysign(1.0, S[CX, j]) < 0.0 else a
        c = math.copysign(a, S[CY, j])
        rel = c if K[KREL, j] else c - S[PHI0, j]
        um_y = (rel + math.pi) * _INV_2PI
        um_y -= math.floor(um_y)
        S[A0, j] = theta_i
        S[UWI, j] = math.sqrt(theta_i * _INV_HALF_PI)
        S[UMX, j] = math.sqrt(theta_m * _INV_HALF_PI)
        S[UMY, j] = um_y
    # theta_i slices
    n_t = theta_vals.size
    for j in range(_RGL_BLOCK):
        K[KIT, j] = 0
    for q in range(n_t):
        tv = theta_vals[q]
        for j in range(_RGL_BLOCK):
            K[KIT, j] += tv < S[A0, j]
    for j in range(_RGL_BLOCK):
        if n_t == 1:
            it = 0
            wt = 0.0
        else:
            it = min(max(K[KIT, j] - 1, 0), n_t - 2)
            wt = _clip01((S[A0, j] - theta_vals[it]) * inv_t[it])
        K[KIT, j] = it
        S[W0, j] = 1.0 - wt
        S[W1, j] = wt
        cx, cy, fx, fy = _cell(S[UMX, j], S[UMY, j], vw, vh)
        K[KCELL, j] = cy * (vw - 1) + cx
        K[KCY, j] = cy
        S[FX, j] = fx
        S[FY, j] = fy
    # VNDF records: prefetched now (one line a pair, ~4 MB of them: mostly not in L2), and
    # the Jacobian's small tables read while they arrive
    n_s = n_t2
    for j in range(_RGL_BLOCK):
        _prefetch(rec32, np.uint64((K[KCELL, j] * n_s + K[KIT, j]) * 8))
    if jacobian:  # the rows of ndf and sigma are equal on this path
        for j in range(_RGL_BLOCK):
            dv = _lerp_x(ndf, S[UMX, j])
            sv = _lerp_x(sigma, S[UWI, j])
            S[SCALE, j] = dv / (4.0 * sv * S[WOZ, j])
    else:
        for j in range(_RGL_BLOCK):
            S[SCALE, j] = 1.0 / S[WOZ, j]
    for j in range(_RGL_BLOCK):
        q = np.uint64((K[KCELL, j] * n_s + K[KIT, j]) * 8)
        h = q >> _U1
        S[G0 + 0, j] = rec32[q]
        S[G0 + 1, j] = rec32[q + _U1]
        S[G0 + 2, j] = rec32[q + _U2]
        S[G0 + 3, j] = rec32[q + _U3]
        S[G0 + 4, j] = rec64[h + _U2]
        S[G0 + 5, j] = rec64[h + _U3]
        S[G0 + 6, j] = rec32[q + _U8]
        S[G0 + 7, j] = rec32[q + _U9]
        S[G0 + 8, j] = rec32[q + _U10]
        S[G0 + 9, j] = rec32[q + _U11]
        S[G0 + 10, j] = rec64[h + _U6]
        S[G0 + 11, j] = rec64[h + _U7]
    inv_w1 = 1.0 / (vw - 1)
    inv_h1 = 1.0 / (vh - 1)
    for j in range(_RGL_BLOCK):
        s0 = K[KIT, j]
        cy = K[KCY, j]
        w0 = S[W0, j]
        w1 = S[W1, j]
        fx = S[FX, j]
        fy = S[FY, j]
        n0 = rows[cy, s0, 3]
        n1 = rows[cy, s0 + 1, 3]
        v00 = w0 * (S[G0 + 0, j] * n0) + w1 * (S[G0 + 6, j] * n1)
        v10 = w0 * (S[G0 + 1, j] * n0) + w1 * (S[G0 + 7, j] * n1)
        v01 = w0 * (S[G0 + 2, j] * n0) + w1 * (S[G0 + 8, j] * n1)
        v11 = w0 * (S[G0 + 3, j] * n0) + w1 * (S[G0 + 9, j] * n1)
        prev0 = w0 * S[G0 + 4, j] + w1 * S[G0 + 10, j]
        prev1 = w0 * S[G0 + 5, j] + w1 * S[G0 + 11, j]
        r0 = w0 * rows[cy, s0, 0] + w1 * rows[cy, s0 + 1, 0]
        r1 = w0 * rows[cy, s0, 1] + w1 * rows[cy, s0 + 1, 1]
        marg_prev = w0 * rows[cy, s0, 2] + w1 * rows[cy, s0 + 1, 2]
        c0 = v00 + (v01 - v00) * fy
        c1 = v10 + (v11 - v10) * fy
        s_x = fx * (c0 + (c1 - c0) * 0.5 * fx) * inv_w1 + prev0 + (prev1 - prev0) * fy
        row = r0 + (r1 - r0) * fy
        s_x = s_x / row if row > 0 else fx
        s_y = fy * (r0 + (r1 - r0) * 0.5 * fy) * inv_h1 + marg_prev
        cx, cy, fx, fy = _cell(s_x, s_y, rx, ry)
        K[KSPEC, j] = cy * (rx - 1) + cx
        S[SX, j] = fx
        S[SY, j] = fy
    # the RGB blend (_rgb_blend_store's arithmetic), one channel at a time across pairs
    ps = np.uint64(spec_stride)
    for j in range(_RGL_BLOCK):
        q = np.uint64((K[KSPEC, j] * n_s + K[KIT, j]) * spec_stride)
        q1 = q + ps
        w0 = S[W0, j]
        w1 = S[W1, j]
        fx = S[SX, j]
        fy = S[SY, j]
        c00 = (1 - fx) * (1 - fy)
        c10 = fx * (1 - fy)
        c01 = (1 - fx) * fy
        c11 = fx * fy
        scale = S[SCALE, j]
        ok = K[KOK, j] != 0
        masked = S[MVAL, j]
        v = _rgb_channel(spec, q, q1, _U0, w0, w1, c00, c10, c01, c11) * scale
        S[R0, j] = v if ok else masked
        v = _rgb_channel(spec, q, q1, _U1, w0, w1, c00, c10, c01, c11) * scale
        S[R0 + 1, j] = v if ok else masked
        v = _rgb_channel(spec, q, q1, _U2, w0, w1, c00, c10, c01, c11) * scale
        S[R0 + 2, j] = v if ok else masked
    for j in range(nb):
        out[b0 + j, 0] = S[R0, j]
        out[b0 + j, 1] = S[R0 + 1, j]
        out[b0 + j, 2] = S[R0 + 2, j]


@njit(**_JIT, inline="always")
def _rgb_channel(spec, q, q1, ch, w0, w1, c00, c10, c01, c11):
    """Channel ``ch`` of one look-up (see :func:`_rgb_blend_store`), without the scale."""
    x0 = w0 * spec[q + ch] + w1 * spec[q1 + ch]
    x1 = w0 * spec[q + ch + _U4] + w1 * spec[q1 + ch + _U4]
    x2 = w0 * spec[q + ch + _U8] + w1 * spec[q1 + ch + _U8]
    x3 = w0 * spec[q + ch + _U12] + w1 * spec[q1 + ch + _U12]
    v = c00 * x0
    v += c10 * x1
    v += c01 * x2
    v += c11 * x3
    return v


@njit(**_JIT, parallel=True)
def rgl_eval(
    wi, wo, phi_vals, theta_vals, n_t2, rec32, rec64, rows, spec, spec_stride, ndf, sigma,
    vh, vw, ry, rx, reduction, isotropic, relative_only, jacobian, atan_table, out,
):  # fmt: skip
    """``f_r`` (1/sr) of an RGL measured BRDF for ``(N, 3)`` pairs: 0 where either
    direction is at or below the horizon, NaN where any component is NaN or infinite.

    The tables are :meth:`gonio.brdf.rgl.RGLBRDF.kernel_tables`, slices last so that the
    two theta_i slices a pair blends are adjacent: the file's VNDF (``vndf[y, x, slice]``,
    float32 as stored), the normalised conditional CDF before each VNDF column
    (``cdf[y, x, slice]``, float64); per (VNDF row, slice) the two row totals of the row's
    patches, the marginal CDF before the row and the slice's normalisation (``rows``);
    per (RGB cell, slice) the four corners of every channel (``spec``, float32,
    corner-major); ``n_t2`` slices per phi_i (theta_i padded to two, so that slice
    ``s + 1`` exists).
    ``relative_only`` is :attr:`gonio.brdf.rgl.RGLBRDF._relative_only` (one arctangent for
    the relative azimuth, phi_i = 0 for sigma); an NDF or sigma whose rows are all equal
    is interpolated along x alone, as the numpy path does; ``atan_table`` is
    :data:`gonio.brdf.rgl.ATAN_TABLE` (an argument: a global array would keep numba from
    caching the machine code); ``out`` is ``(N, channels)``.  Bit for bit
    the numpy path.
    """
    n = wi.shape[0]
    fast = relative_only and reduction < 2 and phi_vals.size == 1 and out.shape[1] == 3
    ndf_flat = _rows_equal(ndf)
    sigma_flat = _rows_equal(sigma)
    fast = fast and ndf_flat and sigma_flat
    n_blocks = (n + _RGL_BLOCK - 1) // _RGL_BLOCK
    n_chunks = min(n_blocks, _RGL_CHUNKS)  # static shares for numba's threads
    inv_p = _inv_spacing(phi_vals)
    inv_t = _inv_spacing(theta_vals)
    # Two parallel loops, so two functions for LLVM: inlined into one, the general block
    # kept the fast one's last loop from being vectorised (1.4x its time).
    if fast:
        for chunk in prange(n_chunks):
            _wide_vectors()  # the attribute goes on the function of the loop's body
            S = np.empty((_NS, _RGL_BLOCK))
            K = np.empty((_NK, _RGL_BLOCK), np.intp)
            for blk in range(chunk * n_blocks // n_chunks, (chunk + 1) * n_blocks // n_chunks):
                b0 = blk * _RGL_BLOCK
                _rgl_block_rel(
                    wi, wo, b0, min(_RGL_BLOCK, n - b0), n, theta_vals, inv_t, n_t2, rec32,
                    rec64, rows, spec, spec_stride, ndf, sigma, vh, vw, ry, rx, jacobian,
                    atan_table, out, S, K,
                )  # fmt: skip
    else:
        for chunk in prange(n_chunks):
            f = np.empty((13, _RGL_BLOCK))
            k = np.empty((6, _RGL_BLOCK), np.intp)
            g = np.empty((12, _RGL_BLOCK))
            for blk in range(chunk * n_blocks // n_chunks, (chunk + 1) * n_blocks // n_chunks):
                b0 = blk * _RGL_BLOCK
                _rgl_block(
                    wi, wo, b0, min(b0 + _RGL_BLOCK, n), phi_vals, theta_vals, inv_p, inv_t,
                    n_t2, rec32, rec64, rows, spec, spec_stride, ndf, sigma, ndf_flat,
                    sigma_flat, vh, vw, ry, rx, reduction, isotropic, relative_only, jacobian,
                    atan_table, out, f, k, g,
                )  # fmt: skip
