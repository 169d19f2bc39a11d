"""Fresnel reflectance terms for the microfacet lobes, with parameter derivatives.

Choices (option ``fresnel=`` of ``ggx`` and ``beckmann``):

======== ============== =====================================================
name     parameters     reflectance at ``cos = dot(wi, h)``
======== ============== =====================================================
none     --             1 (default)
schlick  ``f0``         ``f0 + (1 - f0) (1 - cos)^5``
conductor ``eta``, ``k`` exact unpolarised Fresnel of a metal, n = eta + i k
dielectric ``eta``      exact unpolarised Fresnel of a dielectric (relative IOR);
                        total internal reflection gives 1 when eta < 1
======== ============== =====================================================

The conductor and dielectric terms share one complex-valued implementation (a dielectric is
a conductor with ``k = 0``); the derivatives follow from the holomorphic derivative of the
amplitude coefficients ``r(n)``: ``d|r|^2/d eta = 2 Re(conj(r) r')`` and
``d|r|^2/dk = -2 Im(conj(r) r')``.  Hand-written because no installed library offers
vectorised complex Fresnel with parameter gradients.
"""

from __future__ import annotations

import numpy as np

from gonio.brdf.base import Array, ParamSpec

__all__ = ["FRESNEL_CHOICES", "fresnel_complex", "fresnel_specs", "fresnel_term"]

FRESNEL_CHOICES: tuple[str, ...] = ("none", "schlick", "conductor", "dielectric")


def fresnel_specs(kind: str) -> tuple[ParamSpec, ...]:
    """Parameters (with bounds and defaults) that Fresnel choice ``kind`` adds to a lobe."""
    if kind == "none":
        return ()
    if kind == "schlick":
        return (ParamSpec("f0", 0.0, 1.0, 0.04, doc="reflectance at normal incidence"),)
    if kind == "conductor":
        # Defaults: gold near 550 nm.  eta = k = 0 is allowed (F = 1, a perfect mirror).
        return (
            ParamSpec("eta", 0.0, 10.0, 0.43, doc="real part of the complex IOR"),
            ParamSpec("k", 0.0, 20.0, 2.46, doc="extinction coefficient"),
        )
    if kind == "dielectric":
        return (ParamSpec("eta", 1.0, 4.0, 1.5, doc="relative index of refraction"),)
    raise ValueError(kind)


def fresnel_complex(
    cos_i: Array, eta: Array, k: Array, grad: bool = False
) -> tuple[Array, Array | None, Array | None]:
    """Unpolarised Fresnel reflectance of an interface with complex relative IOR eta + i k.

    Parameters
    ----------
    cos_i
        Cosine of the angle between the incident direction and the (micro)normal, in [0, 1].
    eta, k
        Real and imaginary parts of the relative index of refraction (k >= 0).
    grad
        Also return ``dF/deta`` and ``dF/dk``.

    Returns
    -------
    F, dF_deta, dF_dk
        Reflectance in [0, 1]; the derivatives are None unless ``grad``.
    """
    c = np.clip(cos_i, 0.0, 1.0)
    n = eta + 1j * k
    n2 = n * n
    # n^2 - sin^2 as (n^2 - 1) + cos^2: exact at grazing incidence when n = 1, where the
    # naive form rounds cos^2 away and turns 0/0 into NaN gradients.
    s = np.sqrt(((eta - 1.0) * (eta + 1.0) - k * k + c * c) + 2j * eta * k)
    # Physical branch: Im(s) >= 0 (a decaying transmitted wave).  Im(n^2 - sin^2) >= 0 for
    # eta, k >= 0, where the principal root already has Im >= 0, except for a signed zero.
    s = s.real + 1j * np.abs(s.imag)
    rs = (c - s) / (c + s)
    u = n2 * c
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # replaced below
        rp = (u - s) / (u + s)
    # n = 0 (eta = k = 0, allowed by the bounds): rp -> -1, its limit, instead of 0/0;
    # so too for n^2 below the smallest normal (eta = 0, k ~ 1e-156): u underflows to a
    # subnormal, s rounds to 0, and the complex division u / u gives NaN.
    rp = np.where(np.abs(n2) < np.finfo(np.float64).tiny, -1.0, rp)
    F = 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)
    if not grad:
        return F, None, None
    ds_dn = n / s
    drs = -2.0 * c / (c + s) ** 2 * ds_dn
    drp = 2.0 * (s * 2.0 * n * c - u * ds_dn) / (u + s) ** 2
    w = np.conj(rs) * drs + np.conj(rp) * drp
    return F, w.real, -w.imag


def fresnel_term(
    kind: str, cos_d: Array, p: dict[str, Array], grad: bool
) -> tuple[Array | float, dict[str, Array]]:
    """Fresnel factor for choice ``kind`` at ``cos_d = dot(wi, h)``, and its derivatives.

    Returns
    -------
    F, dF
        ``F`` (the float 1.0 for ``"none"``), and ``{param: dF/dparam}`` when ``grad``.
    """
    if kind == "none":
        return 1.0, {}
    if kind == "schlick":
        f0 = p["f0"]
        m = (1.0 - np.clip(cos_d, 0.0, 1.0)) ** 5
        return f0 + (1.0 - f0) * m, ({"f0": 1.0 - m} if grad else {})
    if kind == "conductor":
        F, de, dk = fresnel_complex(cos_d, p["eta"], p["k"], grad)
        return F, ({"eta": de, "k": dk} if grad else {})
    if kind == "dielectric":
        F, de, _ = fresnel_complex(cos_d, p["eta"], np.zeros(()), grad)
        return F, ({"eta": de} if grad else {})
    raise ValueError(kind)
