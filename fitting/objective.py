"""The fitting problem: which samples enter, how parameters are laid out, and the full cost.

A :class:`Problem` holds the cleaned data (samples that may be used, their weights), the
model, and the *layout* of the parameter vector searched by the optimisers:

``x = [u_1 .. u_S, a_(1,1) .. a_(1,C), a_(2,1) .. a_(K,C)]``

where ``u`` are the S shape parameters (roughness, exponents), shared by all C channels and
possibly reparameterised (``u = ln alpha`` when a parameter spans decades: the cost is then
much closer to quadratic in ``u``), and ``a`` are the K linear parameters (albedo, ks) of
every channel, in natural units.  Sharing the shape across channels is the usual choice for
RGB BRDF fits: the colour of a material lives in its albedos, its gloss in its shape, and
three independent roughnesses would let noise in one channel make a coloured highlight.

:meth:`Problem.full_cost` evaluates the cost and its gradient for any loss, robust penalty
and algorithm; :mod:`gonio.fitting.varpro` evaluates the cost reduced to the shape
parameters for linear losses.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gonio.errors import FitError
from gonio.fitting.losses import Loss, robust_rho

__all__ = ["Problem", "prepare_problem"]

# A shape parameter is searched in log space when it is positive and spans this ratio.
_LOG_SPAN = 100.0

# Largest |brdf| (and, for weighted_l2, |brdf| / sigma) a fit accepts.  Residuals are
# squared and summed, so beyond ~1e154 the cost overflows to inf and every model "fails"
# with numpy overflow warnings and no word about the data; no f_r in 1/sr comes near
# (a polished metal's specular peak is ~1e4-1e6).  A damaged file, not a material.
_MAX_RESIDUAL_SCALE = 1e100


@dataclass
class Problem:
    """Cleaned samples + model + parameter layout.  Build with :func:`prepare_problem`."""

    model: Any
    wi: np.ndarray  # (N, 3) used samples only
    wo: np.ndarray
    y: np.ndarray  # (N, C)
    sigma: np.ndarray | None  # (N, C)
    cos_i: np.ndarray  # (N,)
    loss: Loss
    robust: str | None
    f_scale: float
    used: np.ndarray  # (N_in,) bool
    channels: tuple[str, ...]
    dropped: dict[str, int]
    shape_names: tuple[str, ...] = ()
    linear_names: tuple[str, ...] = ()
    log_shape: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    log_offset: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lb_shape: np.ndarray = field(default_factory=lambda: np.zeros(0))  # natural units
    ub_shape: np.ndarray = field(default_factory=lambda: np.zeros(0))
    lb_lin: np.ndarray = field(default_factory=lambda: np.zeros(0))
    ub_lin: np.ndarray = field(default_factory=lambda: np.zeros(0))
    nfev: int = 0
    njev: int = 0
    #: (N,) per-sample weights of the cost, ``0.5 * sum(w * rho(r**2))`` (None: all 1)
    sample_weight: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.weights = (
            self.loss.weights(self.y, self.sigma, self.cos_i) if self.loss.linear else None
        )
        # Without a robust penalty a sample weight is a residual scale (sqrt(w) r), which
        # keeps the loss linear (variable projection, the plain J^T J); with one it must
        # multiply rho itself: rho(w r^2) != w rho(r^2) for a robust rho.
        self.rho_weight: np.ndarray | None = None
        if self.sample_weight is not None:
            sw = np.asarray(self.sample_weight, dtype=np.float64)[:, None]
            if self.loss.linear and self.robust is None:
                self.weights = self.weights * np.sqrt(sw)
            else:
                self.rho_weight = sw
        self._wi_c = self.wi[:, None, :]
        self._wo_c = self.wo[:, None, :]

    # ---- layout -----------------------------------------------------------------------
    @property
    def n_channels(self) -> int:
        return self.y.shape[1]

    @property
    def n_shape(self) -> int:
        return len(self.shape_names)

    @property
    def n_linear(self) -> int:
        return len(self.linear_names)

    @property
    def n_params(self) -> int:
        return self.n_shape + self.n_linear * self.n_channels

    @property
    def labels(self) -> tuple[str, ...]:
        lin = tuple(f"{n}[{c}]" for n in self.linear_names for c in self.channels)
        return tuple(self.shape_names) + lin

    def to_u(self, theta: np.ndarray) -> np.ndarray:
        """Natural shape parameters -> search variables (``ln(theta + offset)`` or as is)."""
        theta = np.asarray(theta, dtype=np.float64)
        t = np.where(self.log_shape, theta + self.log_offset, 1.0)
        return np.where(self.log_shape, np.log(np.maximum(t, 1e-300)), theta)

    def from_u(self, u: np.ndarray) -> np.ndarray:
        """Search variables -> natural shape parameters."""
        u = np.asarray(u, dtype=np.float64)
        th = np.where(self.log_shape, np.exp(np.where(self.log_shape, u, 0.0)) - self.log_offset, u)
        # exp(log(bound)) can round outside the bound, which the model would reject
        return np.clip(th, self.lb_shape, self.ub_shape)

    def dtheta_du(self, theta: np.ndarray) -> np.ndarray:
        return np.where(self.log_shape, theta + self.log_offset, 1.0)

    @property
    def u_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.to_u(self.lb_shape), self.to_u(self.ub_shape)

    def x_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lu, uu = self.u_bounds
        lo = np.concatenate([lu, np.repeat(self.lb_lin, self.n_channels)])
        hi = np.concatenate([uu, np.repeat(self.ub_lin, self.n_channels)])
        return lo, hi

    def pack(self, theta: np.ndarray, a: np.ndarray) -> np.ndarray:
        """(theta (S,), a (K, C)) -> x."""
        return np.concatenate([self.to_u(theta), np.asarray(a, dtype=np.float64).ravel()])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """x -> (theta (S,) natural, a (K, C))."""
        x = np.asarray(x, dtype=np.float64)
        theta = self.from_u(x[: self.n_shape])
        a = x[self.n_shape :].reshape(self.n_linear, self.n_channels)
        return theta, a

    def params_dict(self, theta: np.ndarray, a: np.ndarray) -> dict[str, Any]:
        """Model parameters: shape as floats, linear as (C,) arrays."""
        p: dict[str, Any] = {n: float(t) for n, t in zip(self.shape_names, theta, strict=True)}
        for j, n in enumerate(self.linear_names):
            p[n] = np.asarray(a[j], dtype=np.float64)
        return p

    # ---- full-space cost ---------------------------------------------------------------
    def model_eval(self, theta: np.ndarray, a: np.ndarray, grad: bool) -> tuple[np.ndarray, dict]:
        """Model values (N, C) and, if ``grad``, derivatives by parameter name (N, C)."""
        p = self.params_dict(theta, a)
        if grad:
            self.njev += 1
            f, g = self.model.eval_with_grad(self._wi_c, self._wo_c, p)
            return np.asarray(f), g
        self.nfev += 1
        return np.asarray(self.model.eval(self._wi_c, self._wo_c, p)), {}

    def residuals(self, x: np.ndarray) -> np.ndarray:
        """Loss residuals (N, C) at ``x``."""
        theta, a = self.unpack(x)
        f, _ = self.model_eval(theta, a, grad=False)
        return self.loss.residual(f, self.y, self.weights, self.cos_i)[0]

    def jacobian_blocks(self, x: np.ndarray, natural: bool = False):
        """Residuals and their Jacobian in blocks.

        Returns ``r`` (N, C), ``J_shape`` (N, C, S) and ``J_lin`` (N, C, K) where
        ``J_lin[:, c, j]`` is the derivative with respect to ``a[j, c]`` (the only channel
        that parameter touches).  ``natural`` gives shape derivatives in natural units
        instead of search variables.
        """
        theta, a = self.unpack(x)
        f, g = self.model_eval(theta, a, grad=True)
        r, drdf = self.loss.residual(f, self.y, self.weights, self.cos_i)
        shp = f.shape
        dtu = np.ones_like(theta) if natural else self.dtheta_du(theta)
        js = np.empty(shp + (self.n_shape,))
        for s, n in enumerate(self.shape_names):
            js[..., s] = drdf * np.broadcast_to(g[n], shp) * dtu[s]
        jl = np.empty(shp + (self.n_linear,))
        for j, n in enumerate(self.linear_names):
            jl[..., j] = drdf * np.broadcast_to(g[n], shp)
        return r, js, jl

    def rho(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``w * rho(r**2)`` and ``w * rho'(r**2)`` (N, C): the robust penalty of the
        residuals ``r`` times the per-sample weights (those not folded into ``weights``)."""
        rho, drho = robust_rho(r * r, self.robust, self.f_scale)
        if self.rho_weight is not None:
            return rho * self.rho_weight, drho * self.rho_weight
        return rho, drho

    def full_cost(self, x: np.ndarray, want_grad: bool = True) -> tuple[float, np.ndarray]:
        """Cost ``0.5 * sum(w * rho(r**2))`` and its gradient with respect to ``x``."""
        if not want_grad:
            r = self.residuals(x)
            rho, _ = self.rho(r)
            return 0.5 * float(np.sum(rho)), np.empty(0)
        r, js, jl = self.jacobian_blocks(x)
        rho, drho = self.rho(r)
        wr = drho * r
        gs = np.einsum("nc,ncs->s", wr, js)
        gl = np.einsum("nc,ncj->jc", wr, jl)
        return 0.5 * float(np.sum(rho)), np.concatenate([gs, gl.ravel()])

    def dense_jacobian(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual vector (N*C,) and dense Jacobian (N*C, P) w.r.t. ``x``; for baselines."""
        r, js, jl = self.jacobian_blocks(x)
        n, c = r.shape
        J = np.zeros((n, c, self.n_params))
        J[:, :, : self.n_shape] = js
        for j in range(self.n_linear):
            for k in range(c):
                J[:, k, self.n_shape + j * c + k] = jl[:, k, j]
        return r.ravel(), J.reshape(n * c, -1)


def _rows_all(mask: np.ndarray) -> np.ndarray:
    """``np.all(mask, axis=1)`` for a narrow (N, K) mask, column by column: numpy's
    reduction along a 3-wide axis took ~5 ms on 10^5 rows, this ~0.5 ms."""
    if mask.shape[1] == 0:
        return np.ones(mask.shape[0], dtype=bool)
    out = mask[:, 0].copy()
    for k in range(1, mask.shape[1]):
        out &= mask[:, k]
    return out


def _row_norm(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=1)`` of (N, 3) vectors with the same bits (numpy sums a
    3-wide row as ``(x^2 + y^2) + z^2``; ``tests/fitting/test_optimize.py`` holds them
    equal) in a tenth of the time."""
    sq = v * v
    return np.sqrt((sq[:, 0] + sq[:, 1]) + sq[:, 2])


def _bounds_of(model: Any, name: str) -> tuple[float, float]:
    lo, hi = dict(getattr(model, "bounds", {}) or {}).get(name, (-np.inf, np.inf))
    lo = -np.inf if lo is None else float(lo)
    hi = np.inf if hi is None else float(hi)
    return lo, hi


def prepare_problem(
    model: Any,
    samples: Any,
    loss: Loss,
    robust: str | None = None,
    f_scale: float = 1.0,
    channels: tuple[str, ...] | None = None,
    sample_weight: np.ndarray | None = None,
) -> Problem:
    """Select the usable samples and set up the parameter layout.

    ``sample_weight`` (N,), finite and >= 0, multiplies each sample's term of the cost
    (``0.5 * sum(w * rho(r**2))``): importance weights, e.g.
    :func:`gonio.fitting.model_error.coverage_weights`.

    Samples are left out (and counted in ``Problem.dropped``) when flagged, when their
    value or direction is not finite, when a direction is at or below the horizon, when the
    weighted loss has no finite sigma for them, or when the log loss is undefined
    (``1 + y cos(theta_i) <= 0``).  Negative values are kept: they are what unbiased noise
    around a small BRDF looks like.

    Raises
    ------
    FitError
        No usable sample, all values zero or negative, a non-positive sigma, or fewer
        residuals than parameters.
    """
    wi = np.asarray(samples.wi, dtype=np.float64)
    wo = np.asarray(samples.wo, dtype=np.float64)
    y = np.asarray(samples.brdf, dtype=np.float64)
    if y.ndim == 1:
        y = y[:, None]
    if wi.shape != wo.shape or wi.ndim != 2 or wi.shape[1] != 3 or wi.shape[0] != y.shape[0]:
        raise FitError(
            f"samples: wi {wi.shape}, wo {wo.shape} and brdf {y.shape} must be (N, 3), (N, 3), "
            "(N, C) with the same N"
        )
    n_in, n_c = y.shape
    if n_in == 0:  # reshape(0, -1) below cannot infer a width from nothing
        raise FitError("samples: no samples to fit (the sample set is empty)")
    std = getattr(samples, "brdf_std", None)
    sigma = None if std is None else np.asarray(std, dtype=np.float64).reshape(n_in, -1)
    if sigma is not None and sigma.shape != y.shape:
        raise FitError(f"samples: brdf_std has shape {sigma.shape}, expected {y.shape}")
    flags = getattr(samples, "flags", None)
    dropped: dict[str, int] = {}

    def drop(mask: np.ndarray, why: str, keep: np.ndarray) -> np.ndarray:
        k = int(np.count_nonzero(keep & mask))
        if k:
            dropped[why] = dropped.get(why, 0) + k
        return keep & ~mask

    keep = np.ones(n_in, dtype=bool)
    if flags is not None:
        keep = drop(np.asarray(flags).reshape(n_in) != 0, "flagged", keep)
    keep = drop(~_rows_all(np.isfinite(y)), "non-finite brdf", keep)
    keep = drop(
        ~(_rows_all(np.isfinite(wi)) & _rows_all(np.isfinite(wo))),
        "non-finite direction",
        keep,
    )
    with np.errstate(invalid="ignore"):
        keep = drop(~((wi[:, 2] > 0) & (wo[:, 2] > 0)), "below horizon", keep)
    if loss.name == "weighted_l2":
        if sigma is None:
            raise FitError("loss 'weighted_l2' needs samples.brdf_std; use loss='cosine_l2'")
        keep = drop(~_rows_all(np.isfinite(sigma)), "non-finite brdf_std", keep)
        bad = keep & ~_rows_all(~(sigma <= 0))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise FitError(
                f"samples.brdf_std: {int(bad.sum())} used samples have sigma <= 0 (first at "
                f"index {i}: {sigma[i].tolist()}); weighted_l2 needs positive sigmas, use "
                "loss='cosine_l2' or 'l2' for noise-free data"
            )
    if sample_weight is not None:
        sample_weight = np.asarray(sample_weight, dtype=np.float64)
        if (
            sample_weight.shape != (n_in,)
            or not np.all(np.isfinite(sample_weight))
            or np.any(sample_weight < 0)
        ):
            raise FitError(
                f"sample_weight: expected {n_in} finite weights >= 0, got shape "
                f"{sample_weight.shape} (min {np.min(sample_weight, initial=np.inf)})"
            )
        keep = drop(sample_weight == 0, "zero weight", keep)
    all_kept = bool(keep.all())
    norm = _row_norm(wi if all_kept else np.where(keep[:, None], wi, 1.0))
    cos_i = np.where(keep, wi[:, 2] / np.where(norm > 0, norm, 1.0), 0.0)
    if loss.name == "log":
        with np.errstate(invalid="ignore"):
            keep = drop(~_rows_all(1.0 + y * cos_i[:, None] > 0), "log loss undefined", keep)
        all_kept = bool(keep.all())
    if not keep.any():
        raise FitError(f"no usable sample among {n_in} (left out: {dropped or 'none'})")

    def kept(a: np.ndarray) -> np.ndarray:
        # a copy is ~50x cheaper than boolean indexing when nothing is left out
        return a.copy() if all_kept else a[keep]

    yk = kept(y)
    if not np.any(yk > 0):
        raise FitError(
            f"samples.brdf: all {int(keep.sum())} usable values are zero or negative; "
            "there is no reflectance to fit"
        )
    _check_residual_scale(yk, None if sigma is None else kept(sigma), loss, keep)

    names = tuple(model.param_names)
    linear = tuple(n for n in names if n in set(getattr(model, "linear_params", ()) or ()))
    shape = tuple(n for n in names if n not in linear)
    lb_s = np.array([_bounds_of(model, n)[0] for n in shape], dtype=np.float64)
    ub_s = np.array([_bounds_of(model, n)[1] for n in shape], dtype=np.float64)
    lb_l = np.array([max(0.0, _bounds_of(model, n)[0]) for n in linear], dtype=np.float64)
    ub_l = np.array([_bounds_of(model, n)[1] for n in linear], dtype=np.float64)
    # ln(alpha) for a positive parameter spanning decades; ln(n + 1) for an exponent that
    # may be 0 but spans decades above 1
    pos = lb_s > 0
    log_s = pos & (np.isinf(ub_s) | (ub_s / np.where(pos, lb_s, 1.0) >= _LOG_SPAN))
    log1 = (lb_s == 0) & (ub_s >= _LOG_SPAN)
    log_off = np.where(log1, 1.0, 0.0)
    log_s = log_s | log1
    p = len(shape) + len(linear) * n_c
    m = int(keep.sum()) * n_c
    if m <= p:
        raise FitError(
            f"{int(keep.sum())} usable samples x {n_c} channels = {m} residuals, but model "
            f"{getattr(model, 'name', '?')} has {p} parameters; need more samples"
        )
    ch = tuple(channels or getattr(samples, "channels", None) or ())
    if len(ch) != n_c:
        ch = tuple(f"c{i}" for i in range(n_c))
    wk = wi / norm[:, None] if all_kept else wi[keep] / norm[keep, None]
    wok = kept(wo)
    ok = wok / _row_norm(wok)[:, None]
    return Problem(
        model=model,
        wi=wk,
        wo=ok,
        y=yk,
        sigma=None if sigma is None else kept(sigma),
        cos_i=kept(cos_i),
        loss=loss,
        robust=robust,
        f_scale=float(f_scale),
        used=keep,
        channels=ch,
        dropped=dropped,
        shape_names=shape,
        linear_names=linear,
        log_shape=log_s,
        log_offset=log_off,
        lb_shape=lb_s,
        ub_shape=ub_s,
        lb_lin=lb_l,
        ub_lin=ub_l,
        sample_weight=None if sample_weight is None else kept(sample_weight),
    )


def _check_residual_scale(
    y: np.ndarray, sigma: np.ndarray | None, loss: Loss, keep: np.ndarray
) -> None:
    """Refuse samples whose squared residuals would overflow (:data:`_MAX_RESIDUAL_SCALE`).

    Parameters
    ----------
    y, sigma
        The kept samples' BRDF values and standard deviations, (M, C), 1/sr.
    loss
        The loss: ``weighted_l2`` divides by sigma, so the ratio is checked as well.
    keep
        Which of the input samples are kept, (N,): to name the sample by its input index.

    Raises
    ------
    FitError
        Naming ``samples.brdf`` (or ``samples.brdf_std``), the sample and the value.
    """
    checks = [("samples.brdf", np.abs(y), "|brdf|")]
    if sigma is not None and loss.name == "weighted_l2":
        with np.errstate(over="ignore", divide="ignore"):
            checks.append(("samples.brdf_std", np.abs(y) / sigma, "|brdf| / brdf_std"))
    for name, scale, what in checks:
        if np.max(scale, initial=0.0) > _MAX_RESIDUAL_SCALE:
            j = int(np.argmax(np.max(scale, axis=1)))
            i = int(np.flatnonzero(keep)[j])
            raise FitError(
                f"{name}: sample {i} has {what} = {float(np.max(scale[j])):.3g}, beyond "
                f"{_MAX_RESIDUAL_SCALE:.0e}: its squared residual would overflow (expected "
                "f_r in 1/sr and its std; the file is damaged?)"
            )
