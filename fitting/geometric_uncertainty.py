"""Correlated geometric errors in a fit's parameter covariance (a sandwich estimator).

A reduced session's directions are not exact: the rig calibration, the camera intrinsics
(scope ``"session"``: one error shared by every sample) and each pose's board fit (scope
``"pose"``: one error shared by the regions of that pose) move ``(wi, wo)`` of many
samples together.  ``samples.h5`` describes them as modes: ``geometry_modes (N, M, 6)``,
the 1-sigma perturbation of ``(wi, wo)`` of each sample along mode ``j``, with
``geometry_mode_scope (M,)``, ``geometry_mode_names (M,)`` and ``pose (N,)``.  The
samples' ``brdf_std`` holds the geometric term only as a marginal std
(``budget["geometry"]``): correct for one sample, wrong for a fit, whose errors average
down as ``1/sqrt(N)`` only for independent errors.

With the fit's estimator linearised at the optimum, ``dp = A dr`` with
``A = H^-1 Q^T`` (``H`` the Gauss-Newton matrix, ``Q = rho' J`` the weighted Jacobian of
the residuals, :mod:`gonio.fitting.uncertainty`), the covariance of the parameters is

``cov = A diag(var_u) A^T + (A B)(A B)^T``

- ``var_u``: the uncorrelated residual variance, from ``brdf_std^2 - budget["geometry"]^2``
  (weighted L2 with absolute sigmas; otherwise the fit's own noise covariance is kept);
- ``B``: one column per correlated error: ``dr/df * df_j`` with
  ``df_j = (f(w + m_j) - f(w - m_j)) / 2`` through the fitted model (central difference
  along the mode, directions renormalised; one-sided where a perturbed direction leaves
  the upper hemisphere), a mode of scope ``"pose"`` giving one column per pose.

Radiometric terms of the budget that are one error of one sign shared by every sample
(:data:`CORRELATED_TERMS`: the stray light, whose stated bound the reduction turns into
``budget["stray"]`` -- it only ever adds light; and the drift's interpolation error: the
residual of the curvature-corrected interpolation between reference groups is a smooth
function of time, alike in the channels, largest where a warm-up's curvature changes
most; and the light
profile's: one exponent n for the whole session, its stated or fitted uncertainty moving
every sample's irradiance together -- the budget keeps its size, not its sign, so one
same-signed column is the conservative reading) enter the same way, one column each,
``dr/df * budget[term]``, as the ``systematic`` part, and leave
``var_u`` too.  Averaged as if independent, a 0.05 % stray-light bias on the diffuse part
of every sample would be reported as 0.003 % on the albedo.

The stray light's column takes its shape from the physics when the samples say how
strongly the room's light enters each one (``stray_gain = G0 / G`` and the attributes
``stray_fraction`` ``s`` and ``stray_reference_gain`` ``g_ref``): a diffuse irradiance
``s E0`` reflects as ``s E0 rho(theta_o) / pi`` (reciprocity: the directional albedo at
the camera's angle), which the reduction divides by ``E = E0 / stray_gain``; the same
light in the reference shots raises the light scale by ``s g_ref``.  So
``df = s / sqrt(3) (stray_gain rho(theta_o) / pi - g_ref f)`` with ``rho`` the fitted
model's.  ``budget["stray"]`` states ``s / sqrt(3) stray_gain f``, exact only for a
Lambertian sample: on a glossy one the flat ``rho / pi`` widens the lobe's wings at
grazing incidence, which moves the roughness, not the lobe's height (world 2102,
``lambert+ggx``: alpha 3.6 sigma off with the budget's shape, 2.1 sigma with this one,
as in the same world without stray light).

The fit itself (its weights, hence its parameters) does not change: only its covariance.
Samples without modes (older files, no budget) skip all of this.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from gonio.errors import FitError
from gonio.fitting.objective import Problem

__all__ = [
    "CORRELATED_TERMS",
    "GeometricModes",
    "geometric_modes_of",
    "sandwich_covariance",
    "STRAY_ALBEDO_NODES",
    "stray_column",
    "stray_effect",
]

SCOPES = ("session", "pose")
#: Budget terms that are one error of one sign shared by all samples of a session
#: (see the module docstring for why each is).
CORRELATED_TERMS = ("stray", "drift", "irradiance")


@dataclass(frozen=True)
class GeometricModes:
    """The correlated geometric errors of the samples used by a fit.

    Attributes
    ----------
    modes : ndarray, shape (N, M, 6)
        1-sigma perturbation of ``(wi, wo)`` (sample frame) of each sample along mode j.
    scope : ndarray of str, shape (M,)
        ``"session"`` (one error shared by all samples) or ``"pose"`` (one per pose).
    names : tuple of str
        Mode names (for diagnostics).
    pose : ndarray of int, shape (N,) or None
        Pose index of each sample (needed when a mode has scope ``"pose"``).
    geometry_std : ndarray, shape (N, C) or None
        ``budget["geometry"]``: the marginal std of the modes that ``brdf_std`` holds, 1/sr.
    correlated : dict of str to ndarray (N, C)
        The budget's :data:`CORRELATED_TERMS` present in the samples, 1/sr.
    stray_gain : ndarray, shape (N, C) or None
        ``G0 / G`` per sample (NaN: unknown), with ``stray_fraction`` (the stated bound)
        and ``stray_reference_gain`` (C,): the stray light's shape (module docstring).
    """

    modes: np.ndarray
    scope: np.ndarray
    names: tuple[str, ...]
    pose: np.ndarray | None
    geometry_std: np.ndarray | None
    correlated: dict[str, np.ndarray] | None = None
    stray_gain: np.ndarray | None = None
    stray_fraction: float = 0.0
    stray_reference_gain: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> GeometricModes:
        """The modes of the samples selected by the boolean mask ``keep``."""
        return GeometricModes(
            modes=self.modes[keep],
            scope=self.scope,
            names=self.names,
            pose=None if self.pose is None else self.pose[keep],
            geometry_std=None if self.geometry_std is None else self.geometry_std[keep],
            correlated={k: v[keep] for k, v in (self.correlated or {}).items()},
            stray_gain=None if self.stray_gain is None else self.stray_gain[keep],
            stray_fraction=self.stray_fraction,
            stray_reference_gain=self.stray_reference_gain,
        )


def geometric_modes_of(samples: Any) -> GeometricModes | None:
    """The samples' geometric modes, or None when they carry none (M = 0 or absent).

    Reads ``geometry_modes``, ``geometry_mode_scope``, ``geometry_mode_names``, ``pose``
    and ``budget["geometry"]`` of a :class:`gonio.dataset.BRDFSamples` (any object with
    those attributes).

    Raises
    ------
    FitError
        A field with the wrong shape, an unknown scope, non-finite modes, or modes of
        scope ``"pose"`` without ``pose`` (the field and what was expected named).
    """
    raw = getattr(samples, "geometry_modes", None)
    if raw is None:
        return None
    n = np.asarray(samples.wi).shape[0]
    c = np.asarray(samples.brdf).reshape(n, -1).shape[1]
    modes = np.asarray(raw, dtype=np.float64)
    if modes.ndim != 3 or modes.shape[0] != n or modes.shape[2] != 6:
        raise FitError(
            f"samples.geometry_modes has shape {modes.shape}, expected (N, M, 6) with N = {n}"
        )
    m = modes.shape[1]
    if m == 0:
        return None
    scope_raw = getattr(samples, "geometry_mode_scope", None)
    if scope_raw is None:
        raise FitError("samples.geometry_modes given without geometry_mode_scope (M,)")
    scope = np.asarray(scope_raw).astype(str).reshape(-1)
    if scope.shape != (m,):
        raise FitError(f"samples.geometry_mode_scope has shape {scope.shape}, expected ({m},)")
    bad = sorted(set(scope.tolist()) - set(SCOPES))
    if bad:
        raise FitError(f"samples.geometry_mode_scope: unknown scope(s) {bad}; expected {SCOPES}")
    names_raw = getattr(samples, "geometry_mode_names", None)
    names = (
        tuple(f"mode{j}" for j in range(m))
        if names_raw is None
        else tuple(np.asarray(names_raw).astype(str).reshape(-1).tolist())
    )
    if len(names) != m:
        raise FitError(f"samples.geometry_mode_names has {len(names)} names for {m} modes")
    pose_raw = getattr(samples, "pose", None)
    pose = None
    if pose_raw is not None:
        pose = np.asarray(pose_raw).reshape(-1)
        if pose.shape != (n,) or not np.issubdtype(pose.dtype, np.integer):
            raise FitError(
                f"samples.pose has shape {pose.shape} and dtype {pose.dtype}, expected "
                f"({n},) integers"
            )
    if pose is None and np.any(scope == "pose"):
        raise FitError("samples.geometry_mode_scope has 'pose' modes but samples.pose is missing")
    budget = getattr(samples, "budget", None) or {}
    geo = budget.get("geometry") if isinstance(budget, dict) else None
    if geo is not None:
        geo = np.asarray(geo, dtype=np.float64)
        if geo.shape != (n, c):
            raise FitError(f"samples.budget['geometry'] has shape {geo.shape}, expected {(n, c)}")
    correlated = {}
    for term in CORRELATED_TERMS:
        v = budget.get(term) if isinstance(budget, dict) else None
        if v is None:
            continue
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (n, c):
            raise FitError(f"samples.budget[{term!r}] has shape {v.shape}, expected {(n, c)}")
        correlated[term] = np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0)
    gain, s_frac, g_ref = _stray_of(samples, n, c)
    return GeometricModes(
        modes=modes, scope=scope, names=names, pose=pose, geometry_std=geo,
        correlated=correlated, stray_gain=gain, stray_fraction=s_frac,
        stray_reference_gain=g_ref,
    )  # fmt: skip


def _stray_of(samples: Any, n: int, c: int) -> tuple[np.ndarray | None, float, np.ndarray | None]:
    """``(stray_gain, stray_fraction, stray_reference_gain)`` of samples that carry them
    (a finite bound > 0 and a finite reference gain), else ``(None, 0, None)``."""
    gain = getattr(samples, "stray_gain", None)
    attrs = getattr(samples, "attrs", None) or {}
    if gain is None or "stray_fraction" not in attrs:
        return None, 0.0, None
    gain = np.asarray(gain, dtype=np.float64)
    if gain.shape != (n, c):
        raise FitError(f"samples.stray_gain has shape {gain.shape}, expected {(n, c)}")
    try:
        s_frac = float(attrs["stray_fraction"])
        g_ref = np.broadcast_to(
            np.asarray(attrs.get("stray_reference_gain", 1.0), dtype=np.float64), (c,)
        ).copy()
    except (TypeError, ValueError) as e:
        raise FitError(
            f"samples attributes stray_fraction / stray_reference_gain: {e}; expected a "
            f"number and {c} numbers"
        ) from None
    if not (np.isfinite(s_frac) and s_frac > 0 and np.all(np.isfinite(g_ref))):
        return None, 0.0, None
    return gain, s_frac, g_ref


#: Polar angles (rad) the directional albedo is taken at for the stray light's shape: it is
#: smooth in theta_o and changes most at grazing angles, so 12 nodes even in cos(theta_o),
#: linear between them (<= 0.09 % off 200 nodes on lambert+ggx with Schlick's Fresnel;
#: half the time of 24 nodes even in theta, 0.07 %).
STRAY_ALBEDO_NODES = np.arccos(np.linspace(1.0, math.cos(math.radians(89.9)), 12))


def stray_effect(
    stray_fraction: float,
    gain: np.ndarray,
    reference_gain: np.ndarray,
    wo: np.ndarray,
    rho: np.ndarray,
    nodes: np.ndarray,
    f: np.ndarray,
) -> np.ndarray:
    """The stray light's 1-sigma effect on samples, (N, C) in 1/sr (module docstring).

    ``s / sqrt(3) (gain rho(theta_o) / pi - g_ref f)``: the room's diffuse irradiance
    ``s E0`` reflects as ``s E0 rho(theta_o) / pi`` (``gain = G0 / G`` puts it over the
    region's direct irradiance) and lifts the light scale by ``s g_ref``.

    Parameters
    ----------
    stray_fraction
        ``s``, the stated bound (rectangular), dimensionless.
    gain, reference_gain
        (N, C) ``G0 / G`` per sample and (C,) the reference regions' mean gain.
    wo
        (N, 3) outgoing unit vectors.
    rho, nodes
        (T, C) the material's directional albedo at the polar angles ``nodes`` (T,), rad
        (linear between them).
    f
        (N, C) the BRDF, 1/sr.
    """
    theta_o = np.arccos(np.clip(np.asarray(wo, dtype=np.float64)[:, 2], -1.0, 1.0))
    rho = np.asarray(rho, dtype=np.float64)
    rho_o = np.stack([np.interp(theta_o, nodes, rho[:, k]) for k in range(rho.shape[1])], 1)
    g_ref = np.asarray(reference_gain, dtype=np.float64)
    return stray_fraction / np.sqrt(3.0) * (gain * rho_o / np.pi - g_ref[None, :] * f)


def stray_column(
    prob: Problem,
    x: np.ndarray,
    modes: GeometricModes,
    albedo_at: Callable[[np.ndarray], np.ndarray],
) -> np.ndarray | None:
    """The stray light's 1-sigma effect on the used samples, (N, C) in 1/sr, shaped by
    the fitted model's directional albedo (module docstring), or None when the samples
    or the model cannot say.

    ``albedo_at(theta)`` gives the fitted model's directional albedo (T, C) at polar
    angles ``theta`` (T,), radians.  Samples without a known gain take the budget's
    stated value (``budget["stray"]``).
    """
    if modes.stray_gain is None or modes.stray_reference_gain is None:
        return None
    nodes = STRAY_ALBEDO_NODES
    try:
        rho = np.asarray(albedo_at(nodes), dtype=np.float64)  # (T, C)
    except (ImportError, NotImplementedError, AttributeError):
        return None
    if rho.shape != (nodes.size, prob.n_channels) or not np.all(np.isfinite(rho)):
        return None
    theta, a = prob.unpack(x)
    f = np.asarray(prob.model.eval(prob._wi_c, prob._wo_c, prob.params_dict(theta, a)))
    col = stray_effect(
        modes.stray_fraction, modes.stray_gain, modes.stray_reference_gain, prob.wo, rho,
        nodes, f,
    )  # fmt: skip
    stated = (modes.correlated or {}).get("stray")
    fallback = stated if stated is not None else np.zeros_like(col)
    return np.where(np.isfinite(col), col, fallback)


def _unit(v: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def mode_effects(prob: Problem, x: np.ndarray, modes: np.ndarray) -> np.ndarray:
    """``df_j`` (N, C, M): the fitted model's change along each 1-sigma mode, 1/sr.

    Central difference ``(f(w + m) - f(w - m)) / 2`` with renormalised directions; one
    side only where the other leaves the upper hemisphere (or is not finite), 0 where both
    do.
    """
    theta, a = prob.unpack(x)
    p = prob.params_dict(theta, a)
    f0 = np.asarray(prob.model.eval(prob._wi_c, prob._wo_c, p))  # (N, C)
    m = np.moveaxis(modes, 1, 0)  # (M, N, 6)
    out = []
    for sign in (1.0, -1.0):
        wi = _unit(prob.wi[None] + sign * m[..., :3])
        wo = _unit(prob.wo[None] + sign * m[..., 3:])
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        wi = np.where(up[..., None], wi, prob.wi[None])  # keep the model away from z <= 0
        wo = np.where(up[..., None], wo, prob.wo[None])
        f = np.asarray(prob.model.eval(wi[..., None, :], wo[..., None, :], p))  # (M, N, C)
        ok = up[..., None] & np.isfinite(f)
        out.append((f, ok))
    (fp, okp), (fm, okm) = out
    df = np.where(
        okp & okm,
        0.5 * (fp - fm),
        np.where(okp, fp - f0, np.where(okm, f0 - fm, 0.0)),
    )
    prob.nfev += 3
    return np.moveaxis(df, 0, 2)  # (N, C, M)


def _columns(t: np.ndarray, modes: GeometricModes) -> np.ndarray:
    """Sum per-sample contributions ``t`` (N, P, M) into the correlated columns (P, M')."""
    cols = []
    sess = modes.scope == "session"
    if sess.any():
        cols.append(t[:, :, sess].sum(axis=0))
    if (~sess).any():
        assert modes.pose is not None
        _, group = np.unique(modes.pose, return_inverse=True)
        tp = t[:, :, ~sess]
        g = np.zeros((group.max() + 1,) + tp.shape[1:])
        np.add.at(g, group, tp)
        cols.append(np.moveaxis(g, 0, -1).reshape(tp.shape[1], -1))  # (P, M_pose * Q)
    return np.concatenate(cols, axis=1)


def sandwich_covariance(
    prob: Problem,
    x: np.ndarray,
    h_inverse: np.ndarray,
    noise_covariance: np.ndarray,
    modes: GeometricModes,
    absolute_sigma: bool,
    albedo_at: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
    """Noise and geometric parts of the parameter covariance, in natural units (P, P).

    Parameters
    ----------
    prob, x
        The fitted problem and its optimum (search variables).
    h_inverse
        Pseudo-inverse of the Gauss-Newton matrix (``Uncertainty.h_inverse``).
    noise_covariance
        The fit's covariance from its residuals' own sigmas (``Uncertainty.covariance``):
        kept as the noise part unless the loss is weighted L2 with absolute sigmas and
        ``budget["geometry"]`` says how much of ``brdf_std`` is geometric.
    modes
        The used samples' modes (:meth:`GeometricModes.subset` with ``prob.used``).
    absolute_sigma
        The fit trusts the sigmas as absolute.
    albedo_at
        The fitted model's directional albedo (T, C) at polar angles (T,), radians: shapes
        the stray light's column (:func:`stray_column`); None keeps the budget's shape.

    Returns
    -------
    noise, geometry, systematic, info
        The covariance parts (uncorrelated noise; geometric modes; the correlated
        radiometric terms) and a summary (mode counts, columns).
    """
    r, js, jl = prob.jacobian_blocks(x, natural=True)
    theta, a = prob.unpack(x)
    f, _ = prob.model_eval(theta, a, grad=False)
    _, drdf = prob.loss.residual(f, prob.y, prob.weights, prob.cos_i)
    _, drho = prob.rho(r)
    S, K, C = prob.n_shape, prob.n_linear, prob.n_channels
    P = prob.n_params
    # Q = rho' J: the estimating equations' weights (J^T r = 0 without a robust penalty)
    qs = js * drho[..., None]
    ql = jl * drho[..., None]

    def per_sample(e: np.ndarray) -> np.ndarray:
        """sum_c Q[n, c, :] e[n, c, m] -> (N, P, M)."""
        t = np.zeros((e.shape[0], P, e.shape[2]))
        t[:, :S] = np.einsum("ncs,ncm->nsm", qs, e)
        for j in range(K):
            t[:, S + j * C : S + (j + 1) * C] = ql[:, :, j, None] * e
        return t

    df = mode_effects(prob, x, modes.modes)
    e = drdf[..., None] * df  # (N, C, M) residual change along each mode
    G = _columns(per_sample(e), modes)
    AG = h_inverse @ G
    geometry = AG @ AG.T
    corr = modes.correlated or {}
    systematic = np.zeros_like(geometry)
    stray_shaped = False
    if corr:
        cols = dict(corr)
        if "stray" in cols and albedo_at is not None:
            shaped = stray_column(prob, x, modes, albedo_at)
            if shaped is not None:
                cols["stray"], stray_shaped = shaped, True
        # one column per term: every sample's error of the same sign, 1 sigma
        e_sys = np.stack([drdf * cols[t] for t in cols], axis=-1)  # (N, C, T)
        AS = h_inverse @ per_sample(e_sys).sum(axis=0)
        systematic = AS @ AS.T
    noise = noise_covariance
    use_uncorrelated = (
        prob.loss.name == "weighted_l2" and absolute_sigma and modes.geometry_std is not None
    )
    if use_uncorrelated:
        removed = modes.geometry_std**2 + sum(v**2 for v in corr.values())
        var_u = np.clip(prob.sigma**2 - removed, 0.0, None)
        v = (drho * drdf) ** 2 * var_u  # variance of rho' r per residual
        meat = np.zeros((P, P))
        meat[:S, :S] = np.einsum("ncs,nct,nc->st", js, js, v)
        sl = np.einsum("ncs,ncj,nc->sjc", js, jl, v).reshape(S, K * C)
        meat[:S, S:] = sl
        meat[S:, :S] = sl.T
        ll = np.einsum("ncj,nck,nc->cjk", jl, jl, v)
        for c in range(C):
            idx = S + np.arange(K) * C + c
            meat[np.ix_(idx, idx)] = ll[c]
        noise = h_inverse @ meat @ h_inverse
    n_sess = int(np.count_nonzero(modes.scope == "session"))
    info = {
        "modes": list(modes.names),
        "session_modes": n_sess,
        "pose_modes": int(modes.scope.size - n_sess),
        "columns": int(G.shape[1]),
        "noise_from_uncorrelated_variance": bool(use_uncorrelated),
        "correlated_terms": sorted(corr),
        "stray_shaped_by_albedo": stray_shaped,
    }
    return noise, geometry, systematic, info
