"""One entry point for measured BRDF files: :func:`load` recognises the format by content.

>>> from gonio.brdf import load
>>> b = load("paper_white_rgb.bsdf")          # RGL-EPFL tensor file  -> RGLBRDF
>>> b = load("gold-metallic-paint.binary")    # MERL binary            -> MERLBRDF
>>> f = b.eval(wi, wo)                        # (..., 3) RGB f_r in 1/sr
>>> a = b.albedo(np.radians([0, 30, 60]))     # (3, 3) directional albedo

Both classes share the interface of a bound analytic model (``eval``, ``albedo``) plus
``description``, ``metadata`` (dict) and ``format`` (``"rgl"`` or ``"merl"``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.errors import FileFormatError

__all__ = ["MeasuredBRDF", "load", "sniff_format", "directional_albedo"]

Array = NDArray[np.float64]


class MeasuredBRDF(Protocol):
    """What :func:`load` returns (see DEVELOPING.md)."""

    format: str
    description: str
    metadata: dict

    def eval(self, wi: ArrayLike, wo: ArrayLike) -> Array: ...

    def albedo(self, theta_i: ArrayLike) -> Array: ...


def sniff_format(path: str | Path) -> str:
    """``"rgl"`` or ``"merl"`` from the first bytes and size of the file, never its name.

    Raises
    ------
    FileFormatError
        Unreadable file, or content matching neither format.
    """
    from gonio.brdf import merl
    from gonio.brdf.tensor_file import MAGIC

    path = Path(path)
    try:
        with path.open("rb") as fh:
            head = fh.read(16)
        size = path.stat().st_size
    except OSError as exc:
        raise FileFormatError(path, f"cannot read file: {exc.strerror or exc}") from exc
    if head.startswith(MAGIC[:11]):
        return "rgl"
    if merl.looks_like_merl(head, size):
        return "merl"
    raise FileFormatError(
        path,
        f"unrecognised measured-BRDF format (first bytes {head[:12]!r}, {size} bytes); "
        "expected an RGL tensor_file (starts with b'tensor_file') or a MERL binary "
        "(int32 header 90, 90, 180 followed by float64 data)",
    )


def load(path: str | Path) -> MeasuredBRDF:
    """Load a measured BRDF file, recognising its format from its content.

    Parameters
    ----------
    path
        An RGL-EPFL ``*.bsdf`` (tensor_file v1.0) or a MERL ``*.binary`` file.

    Returns
    -------
    RGLBRDF or MERLBRDF
        Object with ``eval(wi, wo) -> (..., 3)`` (f_r in 1/sr), ``albedo(theta_i)``,
        ``description``, ``metadata`` and ``format``.

    Raises
    ------
    FileFormatError
        Unknown format, truncated file, missing or malformed field, invalid values.
    """
    kind = sniff_format(path)
    if kind == "rgl":
        from gonio.brdf.rgl import read_rgl

        return read_rgl(path)
    from gonio.brdf.merl import read_merl

    return read_merl(path)


def _gauss_legendre_01(n: int) -> tuple[Array, Array]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


def directional_albedo(
    eval_fn: Callable[[Array, Array], Array],
    theta_i: ArrayLike,
    n_u: int = 192,
    n_phi: int = 96,
) -> Array:
    """Directional albedo ``a(theta_i) = int f_r(wi, wo) cos(theta_o) dw_o`` (per channel).

    The integral is taken over the half vector ``h`` rather than ``wo``: with
    ``wo = 2 (wi.h) h - wi`` one has ``dw_o = 4 (wi.h) dw_h``, and a grid in
    ``theta_h = (pi/2) u^2`` (Gauss-Legendre in ``u``, midpoint in ``phi_h``) puts most nodes
    near the mirror direction, where glossy lobes are narrow, while diffuse parts stay
    smooth.  The horizon (``wo_z = 0``) cuts this grid obliquely, a kink in the integrand
    that limits the accuracy to ~1e-4 (6e-5 for a Lambertian, 3e-5 for a GGX lobe of
    roughness 0.05 against closed forms).  ``wi`` lies in the x-z plane (isotropy is not
    assumed: an anisotropic BRDF gives its albedo for phi_i = 0).

    Parameters
    ----------
    eval_fn
        ``eval(wi, wo) -> (..., C)`` returning f_r in 1/sr.
    theta_i
        Incident elevations in radians, any shape.
    n_u, n_phi
        Quadrature nodes in ``sqrt(theta_h / (pi/2))`` and in ``phi_h``.

    Returns
    -------
    ndarray, shape ``theta_i.shape + (C,)``
    """
    theta_i = np.asarray(theta_i, dtype=np.float64)
    u, wu = _gauss_legendre_01(n_u)
    phi = (np.arange(n_phi) + 0.5) * (2 * np.pi / n_phi)
    th = 0.5 * np.pi * u**2
    # dw_h = sin(theta_h) dtheta_h dphi_h, dtheta_h = pi u du
    wh = (wu * np.pi * u * np.sin(th))[:, None] * np.full(n_phi, 2 * np.pi / n_phi)[None, :]
    st, ct = np.sin(th)[:, None], np.cos(th)[:, None]
    h = np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), ct), axis=-1).reshape(
        -1, 3
    )
    wh = wh.reshape(-1)
    out = []
    for t in theta_i.reshape(-1):
        wi = np.array([np.sin(t), 0.0, np.cos(t)])
        if not np.isfinite(t):
            out.append(None)
            continue
        c = h @ wi
        wo = 2.0 * c[:, None] * h - wi
        ok = (c > 0) & (wo[:, 2] > 0)
        f = eval_fn(np.broadcast_to(wi, wo[ok].shape), wo[ok])
        w = (wh * 4.0 * c)[ok] * wo[ok, 2]
        out.append(np.einsum("n,nc->c", w, f))
    n_ch = next((len(o) for o in out if o is not None), 3)
    res = np.array([o if o is not None else np.full(n_ch, np.nan) for o in out])
    return res.reshape(*theta_i.shape, n_ch)
