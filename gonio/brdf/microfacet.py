"""Cook-Torrance microfacet lobes: ``ggx`` and ``beckmann``.

``f = ks D(h) G1(wi) G1(wo) F(dot(wi, h)) / (4 cos_i cos_o)`` with the separable
(uncorrelated) Smith masking-shadowing ``G = G1(wi) G1(wo)``, as Mitsuba 3's
``roughconductor``.  The cosines are folded into ``G1 / cos`` forms that stay finite at
grazing angles, and every trigonometric quantity comes from vector components, so the
normal direction, ``wi == wo`` and ``alpha = 1e-4`` need no special cases.

Beckmann's Smith G1 is offered in two forms (option ``g1=``):

- ``"exact"`` (default): ``G1 = 1 / (1 + Lambda(a))``, ``a = 1 / (alpha tan theta)``,
  ``Lambda(a) = (erf(a) - 1) / 2 + exp(-a^2) / (2 a sqrt(pi))`` (Walter et al. 2007);
- ``"rational"``: the rational fit ``(3.535 a + 2.181 a^2) / (1 + 2.276 a + 2.577 a^2)``
  for ``a < 1.6`` and 1 beyond, as in Mitsuba and PBRT.
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np

from gonio.brdf.base import Array, Geometry, Lobe, ParamSpec
from gonio.brdf.erfc import erfc  # scipy.special's, without its 0.2 s import
from gonio.brdf.fresnel import FRESNEL_CHOICES, fresnel_specs, fresnel_term

__all__ = ["BeckmannLobe", "GGXLobe", "beckmann_g1", "ggx_g1"]

_INV_PI = 1.0 / math.pi
_INV_2SQRTPI = 0.5 / math.sqrt(math.pi)
# Batches (pairs x channels) from which the fused kernels are used; equals
# gonio.brdf.kernels.MIN_PAIRS, repeated here so that small batches need not import numba.
# GONIO_NUMBA=0 in the environment keeps every batch on the numpy (reference) path.
_MIN_FUSED = 4096
# Importing numba and loading the cached kernels costs ~0.5 s once per process, which a
# CLI plot (< 10^5 evaluations, ~3 ms in numpy) would never win back: the kernels are
# first loaded by a batch of this size, and from then on serve batches >= _MIN_FUSED.
_FIRST_FUSED = 100_000


def ggx_g1(cos_t: Array, sin2_t: Array, alpha: Array, grad: bool = False):
    """GGX Smith ``G1 / cos(theta)`` and ``d ln(G1) / d alpha``.

    ``G1 = 2 / (1 + sqrt(1 + alpha^2 tan^2))``, rewritten as
    ``G1 / cos = 2 / (cos + sqrt(cos^2 + alpha^2 sin^2))`` (finite at the horizon).
    """
    a2 = alpha * alpha
    r = np.sqrt(cos_t * cos_t + a2 * sin2_t)
    g = 2.0 / (cos_t + r)
    if not grad:
        return g, None
    return g, -(alpha * sin2_t / r) / (cos_t + r)


def beckmann_g1(cos_t: Array, sin2_t: Array, alpha: Array, form: str, grad: bool = False):
    """Beckmann Smith ``G1 / cos(theta)`` (``form`` ``"exact"`` or ``"rational"``) and
    ``d ln(G1) / d alpha``."""
    s = np.sqrt(sin2_t)
    with np.errstate(divide="ignore", invalid="ignore"):
        return _beckmann_g1(cos_t, s, cos_t / (alpha * s), alpha, form, grad)


def _beckmann_g1(cos_t, s, a, alpha, form, grad):
    # a = inf at the normal: G1 = 1 there in both forms.
    if form == "exact":
        e = np.exp(-a * a)
        # cos * (1 + Lambda) written without 1/a, so that a -> 0 (grazing) is finite.
        denom = cos_t - 0.5 * cos_t * erfc(a) + alpha * s * e * _INV_2SQRTPI
        g = 1.0 / denom
        if not grad:
            return g, None
        return g, -g * s * e * _INV_2SQRTPI
    num = 3.535 + 2.181 * a
    den = 1.0 + 2.276 * a + 2.577 * a * a
    small = a < 1.6
    g = np.where(small, num / (alpha * s * den), 1.0 / cos_t)
    if not grad:
        return g, None
    dlna = (3.535 + 4.362 * a) / num - a * (2.276 + 5.154 * a) / den  # a dlnG1/da
    return g, np.where(small, -dlna / alpha, 0.0)


class _Microfacet(Lobe):
    option_choices = {"fresnel": FRESNEL_CHOICES}

    def _specs(self) -> tuple[ParamSpec, ...]:
        return (
            ParamSpec("ks", 0.0, 1.0, 0.5, linear=True, doc="specular weight"),
            ParamSpec("alpha", 1e-4, 1.0, 0.2, doc="roughness (rms slope / GGX width)"),
            *fresnel_specs(self.options["fresnel"]),
        )

    def lobe_width(self, p: dict[str, Array]) -> Array:
        return np.arctan(p["alpha"])

    def fused_eval(self, wi: Array, wo: Array, p: dict[str, Array]) -> Array | None:
        """Whole-batch f (1/sr) from the numba kernels, below-horizon pairs already 0, or
        None when the batch is small or of a shape only the numpy path handles.

        For :class:`gonio.brdf.base.Model`, which can then skip its chunked numpy loop."""
        return _fused(self, wi, wo, p)

    def _ndf(self, g: Geometry, alpha: Array, grad: bool):
        raise NotImplementedError

    def _g1(self, cos_t: Array, sin2_t: Array, alpha: Array, grad: bool):
        raise NotImplementedError

    def evaluate(self, g, p, grad):
        if not grad and (f := _fused(self, g.wi, g.wo, p)) is not None:
            return f, None
        alpha = p["alpha"]
        ks = p["ks"]
        D, dD = self._ndf(g, alpha, grad)
        gi, dgi = self._g1(g.iz, g.si2, alpha, grad)
        go, dgo = self._g1(g.oz, g.so2, alpha, grad)
        base = 0.25 * D * gi * go
        kind = self.options["fresnel"]
        if kind == "none":
            f = ks * base
            F: Array | float = 1.0
            dF: dict[str, Array] = {}
        else:
            F, dF = fresnel_term(kind, g.cos_d, p, grad)
            f = ks * base * F
        if not grad:
            return f, None
        grads = {"ks": base * F, "alpha": f * (dD + dgi + dgo)}
        for name, d in dF.items():
            grads[name] = ks * base * d
        return f, grads


def _kernel_layout(w: Array) -> Array:
    """``(N, 3)`` directions as the kernels read them without a copy where possible: C
    order raveled to ``(3 N,)``, Fortran order (the model's chunks) as its ``(3, N)``
    transpose; anything else is copied to C order.  Only these layouts vectorise."""
    if w.flags.c_contiguous:
        return w.reshape(-1)
    if w.flags.f_contiguous:
        return w.T
    return np.ascontiguousarray(w).reshape(-1)


def _fused(lobe: _Microfacet, wi: Array, wo: Array, p: dict[str, Array]) -> Array | None:
    """f from the numba kernels of :mod:`gonio.brdf.kernels`, or None (numpy path) when
    the batch is small or not of the common shapes: equal-shape direction arrays with
    scalar parameters, or with per-channel ``(C,)`` parameters against ``(..., 1, 3)``
    directions.  Pairs below the horizon are exactly 0 (the kernels apply the rule)."""
    if wi.shape != wo.shape or wi.ndim < 2 or any(v.ndim > 1 for v in p.values()):
        return None
    lead = wi.shape[:-1]
    sizes = {v.size for v in p.values() if v.ndim == 1}
    if len(sizes - {1}) > 1 or (sizes - {1} and lead[-1] != 1):
        return None
    chans = max(sizes, default=1)
    n = math.prod(lead)
    size = n * chans
    if size < _MIN_FUSED or os.environ.get("GONIO_NUMBA") == "0":
        return None
    if size < _FIRST_FUSED and "gonio.brdf.kernels" not in sys.modules:
        return None
    # Imported only here: small evaluations (CLI, plots) never pay numba's import time.
    from gonio.brdf import kernels

    wi2, wo2 = _kernel_layout(wi.reshape(n, 3)), _kernel_layout(wo.reshape(n, 3))
    if wi2.ndim != wo2.ndim:
        wi2 = np.ascontiguousarray(wi.reshape(n, 3)).reshape(-1)
        wo2 = np.ascontiguousarray(wo.reshape(n, 3)).reshape(-1)
    kind = lobe.options["fresnel"]
    if lobe.kind == "ggx" and kind == "none" and not sizes:
        out = np.empty(lead)
        hot = kernels.ggx_hot if n >= kernels.PARALLEL_PAIRS else kernels.ggx_hot_serial
        ro = kernels.readonly
        hot(ro(wi2), ro(wo2), float(p["ks"]), float(p["alpha"]), out.reshape(n))
        return out

    def row(name: str) -> Array:
        v = p.get(name, np.zeros(()))
        r = np.ascontiguousarray(np.broadcast_to(v, (chans,)), dtype=np.float64)
        return kernels.readonly(r)

    out = np.empty((n, chans))
    parallel = n * chans >= kernels.PARALLEL_PAIRS
    (kernels.microfacet_eval if parallel else kernels.microfacet_eval_serial)(
        kernels.readonly(wi2),
        kernels.readonly(wo2),
        row("ks"),
        row("alpha"),
        row("f0"),
        row("eta"),
        row("k"),
        kernels.DIST_GGX if lobe.kind == "ggx" else kernels.DIST_BECKMANN,
        kernels.G1_RATIONAL if lobe.options.get("g1") == "rational" else kernels.G1_EXACT,
        kernels.FRESNEL_CODES[kind],
        out,
    )
    shape = np.broadcast_shapes(lead, (chans,)) if sizes else lead
    return out.reshape(shape)


class GGXLobe(_Microfacet):
    """GGX (Trowbridge-Reitz) microfacet lobe."""

    kind = "ggx"
    summary = "Cook-Torrance, GGX normal distribution, Smith G"

    def _ndf(self, g, alpha, grad):
        a2 = alpha * alpha
        q = a2 * g.hz2 + g.hxy2
        t = g.hh / q  # 1 / (cos^2 + sin^2 / alpha^2) up to alpha^2: no cancellation
        D = (a2 * _INV_PI) * (t * t)
        if not grad:
            return D, None
        return D, 2.0 / alpha - 4.0 * alpha * g.hz2 / q

    def _g1(self, cos_t, sin2_t, alpha, grad):
        return ggx_g1(cos_t, sin2_t, alpha, grad)

    def evaluate(self, g, p, grad):
        if not grad and (f := _fused(self, g.wi, g.wo, p)) is not None:
            return f, None
        alpha = p["alpha"]
        if (
            grad
            or self.options["fresnel"] != "none"
            or alpha.ndim
            or p["ks"].ndim
            or g.wi.ndim < 2
            or g.wi.shape != g.wo.shape
        ):
            return super().evaluate(g, p, grad)
        # Hot path (fitting loops, the simulator, benchmarks/brdf_eval.py): F = 1, no
        # gradient, scalar parameters.  f = ks alpha^2 / pi * t^2 / ((ci + ri)(co + ro))
        # with t = |h|^2 / (alpha^2 hz^2 + hxy^2), ri = sqrt(alpha^2 + (1 - alpha^2) ci^2);
        # in-place updates on as few temporaries as possible.
        a2 = float(alpha) ** 2
        hx = g.ix + g.ox
        hy = g.iy + g.oy
        hz = g.iz + g.oz
        hx *= hx
        hy *= hy
        hx += hy  # hxy^2
        hz *= hz
        hy = np.add(hx, hz, out=hy)  # |h|^2
        hz *= a2
        hz += hx  # alpha^2 hz^2 + hxy^2
        t = np.divide(hy, hz, out=hy)
        t *= t
        one_m = 1.0 - a2
        ci, co = g.iz, g.oz
        ri = ci * ci
        ri *= one_m
        ri += a2
        np.sqrt(ri, out=ri)
        ri += ci
        ro = co * co
        ro *= one_m
        ro += a2
        np.sqrt(ro, out=ro)
        ro += co
        ri *= ro
        t /= ri
        t *= float(p["ks"]) * a2 * _INV_PI
        return t, None


class BeckmannLobe(_Microfacet):
    """Beckmann microfacet lobe with exact (erf) or rational Smith G1."""

    kind = "beckmann"
    summary = "Cook-Torrance, Beckmann normal distribution, Smith G"
    option_choices = {"fresnel": FRESNEL_CHOICES, "g1": ("exact", "rational")}

    def _ndf(self, g, alpha, grad):
        a2 = alpha * alpha
        tan2 = g.hxy2 / g.hz2
        D = np.exp(-tan2 / a2) * (g.hh * g.hh) / ((math.pi * a2) * (g.hz2 * g.hz2))
        if not grad:
            return D, None
        return D, 2.0 * tan2 / (a2 * alpha) - 2.0 / alpha

    def _g1(self, cos_t, sin2_t, alpha, grad):
        return beckmann_g1(cos_t, sin2_t, alpha, self.options["g1"], grad)
