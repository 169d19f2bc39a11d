"""Parameter covariance from the Jacobian at the optimum.

Linearised (Gauss-Newton) covariance ``s^2 (J^T J)^-1`` of the free parameters, in natural
units (``alpha``, not ``ln alpha``), where ``J`` is the Jacobian of the loss residuals:

- weighted L2 with the samples' sigmas (``absolute_sigma=True``, the default for
  ``weighted_l2``): the residuals are already in units of sigma, so ``s^2 = 1``.  This is
  what makes z-scores ``(p_hat - p_true) / std`` standard normal when the sigmas are right.
- any other loss, or when the sigmas are only relative: ``s^2 = 2 cost / (m - p)``, the
  residual variance estimated from the fit (as ``scipy.optimize.curve_fit`` with
  ``absolute_sigma=False``).

Robust penalties enter through the IRLS weights ``rho'(r^2)`` (``J_w = sqrt(rho') J``).
Parameters held at a bound are not free (their std is reported as 0 and they are listed);
directions the data cannot determine make the scaled ``J^T J`` singular: the parameters in
its null space get std ``inf`` and the condition number says so.

``J^T J`` is accumulated from blocks (shape parameters touch every channel, a linear
parameter only its own), so 10^6 samples x 3 channels never need a dense Jacobian.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gonio.fitting.objective import Problem

__all__ = ["Uncertainty", "add_calibration_uncertainty", "covariance_at"]


@dataclass
class Uncertainty:
    """Covariance (P, P), std (P,), labels at bounds, condition number, scale s."""

    covariance: np.ndarray
    std: np.ndarray
    at_bounds: list[str]
    condition_number: float
    sigma_scale: float
    free: np.ndarray
    residuals: np.ndarray  # (N, C) at x
    cost: float  # 0.5 * sum(rho(r^2)) at x
    #: pseudo-inverse of the (unscaled) Gauss-Newton matrix J^T J, zero outside ``free``;
    #: the "bread" of a sandwich covariance
    h_inverse: np.ndarray | None = None


def _at_bounds(prob: Problem, x: np.ndarray) -> np.ndarray:
    theta, a = prob.unpack(x)
    S = prob.n_shape
    out = np.zeros(prob.n_params, dtype=bool)
    lu, uu = prob.u_bounds
    u = x[:S]
    span = np.where(np.isfinite(uu - lu), uu - lu, 1.0)
    out[:S] = (u <= lu + 1e-7 * span) | (u >= uu - 1e-7 * span)
    scale = np.maximum(np.max(np.abs(a), axis=1, keepdims=True), 1e-300)
    lo = prob.lb_lin[:, None]
    hi = prob.ub_lin[:, None]
    out[S:] = ((a <= lo + 1e-10 * scale) | (a >= hi - 1e-10 * scale)).ravel()
    return out


def _jtj_of_blocks(prob: Problem, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Residuals, ``J^T J`` (with the robust IRLS weights) and the cost at ``x``."""
    r, js, jl = prob.jacobian_blocks(x, natural=True)
    rho, drho = prob.rho(r)
    cost = 0.5 * float(np.sum(rho))
    # (without a penalty or sample weights beyond the residuals' the IRLS weights are 1)
    if prob.robust is not None or prob.rho_weight is not None:
        sw = np.sqrt(drho)
        js = js * sw[..., None]
        jl = jl * sw[..., None]
    S, K, C = prob.n_shape, prob.n_linear, prob.n_channels
    P = prob.n_params
    H = np.zeros((P, P))
    H[:S, :S] = np.einsum("ncs,nct->st", js, js)
    sl = np.einsum("ncs,ncj->sjc", js, jl).reshape(S, K * C)
    H[:S, S:] = sl
    H[S:, :S] = sl.T
    ll = np.einsum("ncj,nck->cjk", jl, jl)
    for c in range(C):
        idx = S + np.arange(K) * C + c
        H[np.ix_(idx, idx)] = ll[c]
    return r, H, cost


def covariance_at(
    prob: Problem,
    x: np.ndarray,
    absolute_sigma: bool,
    jtj: tuple[np.ndarray, np.ndarray] | None = None,
) -> Uncertainty:
    """Covariance of the parameters ``x`` of ``prob`` (labels ``prob.labels``).

    Parameters
    ----------
    prob
        The fitted problem.
    x
        Optimum in search variables (shape parameters possibly in log space).
    absolute_sigma
        Treat the residuals as already scaled by the true sigmas (``s^2 = 1``).
    jtj
        Residuals (N, C) and ``J^T J`` (P, P, natural units, ``prob.labels`` order) at
        ``x`` when the caller has them (``VarPro.jtj``: the fused kernels' sums; no
        robust penalty); else they are formed here from ``prob.jacobian_blocks``.
    """
    if jtj is not None:
        if prob.robust is not None:
            raise ValueError("covariance_at: jtj is the plain J^T J, without robust weights")
        r, H = jtj
        cost = 0.5 * float(np.sum(r * r))
    else:
        r, H, cost = _jtj_of_blocks(prob, x)
    P = prob.n_params
    bound = _at_bounds(prob, x)
    free = ~bound
    m = r.size
    pf = int(free.sum())
    if absolute_sigma:
        s2 = 1.0
    else:
        s2 = 2.0 * cost / max(m - pf, 1)
    cov = np.zeros((P, P))
    hinv = np.zeros((P, P))
    std = np.zeros(P)
    cond = 1.0
    if pf:
        Hf = H[np.ix_(free, free)]
        d = np.sqrt(np.clip(np.diag(Hf), 0.0, None))
        dz = d > 0
        dd = np.where(dz, d, 1.0)
        Hs = Hf / np.outer(dd, dd)
        w, V = np.linalg.eigh(Hs)
        wmax = max(float(w[-1]), 1e-300)
        sing = (w <= 1e-14 * wmax) | ~np.isfinite(w)
        cond = float(np.sqrt(wmax / w[0])) if w[0] > 0 and not sing.any() else np.inf
        winv = np.where(sing, 0.0, 1.0 / np.where(sing, 1.0, w))
        covs = (V * winv) @ V.T
        covf = covs / np.outer(dd, dd) * s2
        stdf = np.sqrt(np.clip(np.diag(covf), 0.0, None))
        # parameters that take part in an undetermined direction, or never affect the cost
        null = np.any(np.abs(V[:, sing]) > 1e-3, axis=1) if sing.any() else np.zeros(pf, bool)
        stdf = np.where(null | ~dz, np.inf, stdf)
        cov[np.ix_(free, free)] = covf
        hinv[np.ix_(free, free)] = covs / np.outer(dd, dd)
        std[free] = stdf
    labels = prob.labels
    return Uncertainty(
        covariance=cov,
        std=std,
        at_bounds=[labels[i] for i in np.flatnonzero(bound)],
        condition_number=cond,
        sigma_scale=float(np.sqrt(s2)),
        free=free,
        residuals=r,
        cost=cost,
        h_inverse=hinv,
    )


def add_calibration_uncertainty(result: Any, rel_std: Any) -> Any:
    """Add a radiometric calibration's fully correlated uncertainty to a fit result.

    A reduced session's BRDF values share one calibration scale per channel (the light's
    radiance from the reference target), with relative standard uncertainty ``rel_std``.
    A common scale error multiplies every linear parameter (albedo, ks) of that channel
    and leaves the shape parameters alone, so it adds ``p_i p_j rel_std_c^2`` to the
    covariance of the linear parameters ``p_i, p_j`` of channel ``c``.  The samples' own
    sigmas do not contain it (see ``calibration_rel_std`` in ``samples.h5``).

    Parameters
    ----------
    result
        A :class:`~gonio.fitting.result.FitResult`; updated in place and returned.
    rel_std
        Relative standard uncertainty of the calibration per channel, shape (C,).
    """
    rel = np.broadcast_to(np.asarray(rel_std, dtype=np.float64), (len(result.channels),))
    if not np.all(np.isfinite(rel)) or not np.any(rel > 0):
        return result
    labels = list(result.param_labels)
    cov = np.array(result.covariance, dtype=np.float64, copy=True)
    for c, ch in enumerate(result.channels):
        names = [n for n in result.linear_params if f"{n}[{ch}]" in labels]
        idx = [labels.index(f"{n}[{ch}]") for n in names]
        vals = np.array([result.params[n][c] for n in names])
        cov[np.ix_(idx, idx)] += np.outer(vals, vals) * rel[c] ** 2
        for n, i in zip(names, idx, strict=True):
            if np.isfinite(result.std[n][c]):
                result.std[n][c] = float(np.sqrt(max(cov[i, i], 0.0)))
    split = result.diagnostics.get("variance_split")
    if split is not None:
        split["calibration"] = (
            np.diag(cov) - np.diag(np.asarray(result.covariance, dtype=np.float64))
        ).tolist()
    result.covariance = cov
    result.diagnostics["calibration_rel_std"] = rel.tolist()
    return result
