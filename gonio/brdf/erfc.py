"""The complementary error function in numpy, the same doubles as ``scipy.special.erfc`` here.

Beckmann's exact Smith G1 (:mod:`gonio.brdf.microfacet`) needs one special function.
Importing ``scipy.special`` for it costs ~0.2 s of every process that evaluates a Beckmann
lobe (its array-API layer imports ``numpy.testing``, ``numpy.f2py`` and more): a fifth of
``gonio fit FILE --model auto``, which always tries ``lambert+beckmann``.

This is Cephes' ``erfc`` (S. L. Moshier, ``ndtr.c``; scipy evaluates the same rational
approximations in the same order), vectorised: for ``|x| < 1`` ``1 - erf(x)`` with
``erf(x) = x T(x^2) / U(x^2)``; for ``1 <= |x| < 8`` ``exp(-x^2) P(|x|) / Q(|x|)``; beyond
``exp(-x^2) R(|x|) / S(|x|)``; ``2 - erfc(|x|)`` for negative ``x``; 0 (2 for negative ``x``)
once ``exp(-x^2)`` underflows.  Every step is one float64 operation in Cephes' order and
``np.exp`` is libm's ``exp`` on this build, so the results equal scipy's bit for bit
(on this build; ``tests/brdf/test_erfc.py`` compares with scipy on 10^6 points of every
branch, to 2 ulp so that another libm's last-bit rounding of ``exp`` does not fail it);
relative error < 1e-15 (Cephes' figures).
"""

from __future__ import annotations

import numpy as np

__all__ = ["erfc"]

# Coefficients, highest power first (Cephes ndtr.c).  Q, S and U have a leading 1 implied
# (Cephes' p1evl).
_P = (
    2.46196981473530512524e-10,
    5.64189564831068821977e-1,
    7.46321056442269912687e0,
    4.86371970985681366614e1,
    1.96520832956077098242e2,
    5.26445194995477358631e2,
    9.34528527171957607540e2,
    1.02755188689515710272e3,
    5.57535335369399327526e2,
)
_Q = (
    1.32281951154744992508e1,
    8.67072140885989742329e1,
    3.54937778887819891062e2,
    9.75708501743205489753e2,
    1.82390916687909736289e3,
    2.24633760818710981792e3,
    1.65666309194161350182e3,
    5.57535340817727675546e2,
)
_R = (
    5.64189583547755073984e-1,
    1.27536670759978104416e0,
    5.01905042251180477414e0,
    6.16021097993053585195e0,
    7.40974269950448939160e0,
    2.97886665372100240670e0,
)
_S = (
    2.26052863220117276590e0,
    9.39603524938001434673e0,
    1.20489539808096656605e1,
    1.70814450747565897222e1,
    9.60896809063285878198e0,
    3.36907645100081516050e0,
)
_T = (
    9.60497373987051638749e0,
    9.00260197203842689217e1,
    2.23200534594684319226e3,
    7.00332514112805075473e3,
    5.55923013010394962768e4,
)
_U = (
    3.35617141647503099647e1,
    5.21357949780152679795e2,
    4.59432382970980127987e3,
    2.26290000613890934246e4,
    4.92673942608635921086e4,
)
#: ln of the largest double (Cephes' MAXLOG): below exp(-MAXLOG) erfc underflows to 0.
_MAXLOG = 7.09782712893383996843e2


def _polevl(x: np.ndarray, coef: tuple[float, ...]) -> np.ndarray:
    """Horner's scheme, highest power first (Cephes ``polevl``)."""
    ans = np.full_like(x, coef[0])
    for c in coef[1:]:
        ans *= x
        ans += c
    return ans


def _p1evl(x: np.ndarray, coef: tuple[float, ...]) -> np.ndarray:
    """Horner's scheme with an implied leading coefficient 1 (Cephes ``p1evl``)."""
    ans = x + coef[0]
    for c in coef[1:]:
        ans *= x
        ans += c
    return ans


def _exp_libm(z: np.ndarray) -> np.ndarray:
    """``exp(z)`` as libm computes it (what Cephes calls).  ``np.exp`` on float64 is
    numpy's own SIMD routine, which differs from libm in the last bit for ~5% of
    arguments; numpy's complex ``exp`` calls libm's ``cexp``, whose real part for a zero
    imaginary part is ``exp(z) * 1`` (glibc).  ~10x the cost of ``np.exp``, paid only
    for the arguments that need it (1 <= |x| < 26.6)."""
    return np.exp(z.astype(np.complex128)).real


def erfc(x: np.ndarray | float) -> np.ndarray | float:
    """``erfc(x) = 1 - erf(x)`` elementwise (dimensionless), float64.

    Parameters
    ----------
    x
        Any real array (or scalar); NaN gives NaN, ``+inf`` 0 and ``-inf`` 2.

    Returns
    -------
    ndarray or float
        ``erfc(x)``, the same shape as ``x`` (a Python float for a scalar), equal to
        ``scipy.special.erfc(x)``.
    """
    # Underflow (tiny x squared, subnormal results near |x| = 26.6) and overflow (x^2 of
    # huge x, which then takes the limit) are the approximation working: no warnings.
    with np.errstate(under="ignore", over="ignore"):
        return _erfc(np.asarray(x, dtype=np.float64))


def _erfc(a: np.ndarray) -> np.ndarray | float:
    scalar = a.ndim == 0
    a = np.atleast_1d(a)
    ax = np.abs(a)
    # the limits first: 0 (2 for negative x) once exp(-x^2) underflows, NaN for NaN
    out = np.where(a < 0, 2.0, 0.0)
    out[np.isnan(a)] = np.nan
    small = ax < 1.0
    if small.any():
        s = a[small]
        z = s * s
        out[small] = 1.0 - s * _polevl(z, _T) / _p1evl(z, _U)
    z_all = -(a * a)  # Cephes' z = -a * a (-inf for huge |a|: the limits above)
    for sel, num, den in (
        ((ax >= 1.0) & (ax < 8.0), _P, _Q),
        ((ax >= 8.0) & (z_all >= -_MAXLOG), _R, _S),
    ):
        if not sel.any():
            continue
        s, sx = a[sel], ax[sel]
        y = (_exp_libm(z_all[sel]) * _polevl(sx, num)) / _p1evl(sx, den)
        y = np.where(s < 0, 2.0 - y, y)
        # Cephes: a quotient that underflowed to 0 returns the limit
        out[sel] = np.where(y == 0.0, np.where(s < 0, 2.0, 0.0), y)
    return float(out[0]) if scalar else out
