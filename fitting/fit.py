"""``fit``: fit one BRDF model (or choose one) to BRDF samples.

The default strategy, for a model with S shape parameters and K linear parameters per
channel:

1. **Variable projection** (:mod:`gonio.fitting.varpro`): the linear parameters (albedo,
   ks of every channel) are solved exactly inside the search, which therefore runs over the
   S shape parameters only (S = 0..2 for the usual models), searched in log space where
   they span decades (``ln alpha``, ``ln n``).
2. **Global stage**: the reduced cost is evaluated on a scrambled Sobol design over the
   bounds (16 points for S = 1, 64 for S = 2) in one broadcast model call; the best
   distinct design points, and the caller's start if any, seed
3. **local searches** with nlopt ``LD_LBFGS`` and the exact reduced gradient.  Any nlopt
   algorithm can replace it (``algorithm="LD_SLSQP"``), and a global nlopt algorithm
   (``GN_DIRECT_L``, ``GN_CRS2_LM``, ``G_MLSL_LDS``) can replace the Sobol stage.
4. Non-linear losses (``log``) and robust penalties: the variable-projection solution of the
   cosine-weighted L2 problem starts a full-space local search (shape + all linear
   parameters).
5. **Energy conservation**: if the fitted directional albedo exceeds 1 at some incidence,
   the fit is redone in full space with ``LD_SLSQP`` under the nonlinear inequality
   constraints ``albedo(theta_i) <= 1`` on a grid of incidence angles, per channel.
6. Covariance from the Jacobian (:mod:`gonio.fitting.uncertainty`), checks for finiteness,
   and one :class:`~gonio.fitting.result.FitResult`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from gonio.errors import FitError, UnknownNameError
from gonio.fitting.geometric_uncertainty import (
    GeometricModes,
    geometric_modes_of,
    sandwich_covariance,
)
from gonio.fitting.losses import LOSSES, get_loss
from gonio.fitting.objective import Problem, prepare_problem
from gonio.fitting.optimize import (
    ALGORITHMS,
    GLOBAL_ALGORITHMS,
    NloptResult,
    nlopt_minimize,
    sobol_design,
)
from gonio.fitting.result import FitResult
from gonio.fitting.uncertainty import add_calibration_uncertainty, covariance_at
from gonio.fitting.varpro import VarPro, unit_values

__all__ = ["fit", "fit_model", "resolve_loss"]

# Incidence angles (rad) at which energy conservation is checked and enforced.
ENERGY_THETA = np.radians([0.0, 20.0, 40.0, 55.0, 65.0, 75.0, 82.0, 87.0])
_ENERGY_TOL = 1e-6
# Design points screened subsample size: above it the design runs on a random subset.
_SCREEN_MAX = 20_000


def resolve_loss(loss: str, samples: Any) -> str:
    """``"auto"`` -> ``"weighted_l2"`` when every valid sample has a finite sigma, else
    ``"cosine_l2"``; other names are checked and returned."""
    if loss != "auto":
        if loss not in LOSSES:
            raise UnknownNameError(
                f"unknown loss {loss!r}; expected 'auto' or one of {', '.join(LOSSES)}"
            )
        return loss
    std = getattr(samples, "brdf_std", None)
    if std is None:
        return "cosine_l2"
    std = np.asarray(std, dtype=np.float64)
    if std.size and np.isfinite(std).all():
        return "weighted_l2"  # every sigma finite: the valid ones too (no mask to build)
    valid = getattr(samples, "valid", None)
    if valid is not None:
        std = std[np.asarray(valid)]
    if std.size and np.all(np.isfinite(std)):
        return "weighted_l2"  # (a sigma <= 0 is then reported as an error, not ignored)
    return "cosine_l2"


def _get_model(model: Any, options: dict[str, Any]) -> tuple[Any, str, dict[str, Any]]:
    if isinstance(model, str):
        from gonio.brdf import get_model
        from gonio.fitting.select import parse_model_spec

        # "lambert+ggx[fresnel=schlick]": options in the name (model selection candidates,
        # the CLI's --model); explicit model_options win over them
        name, spec_opts = parse_model_spec(model)
        opts = {**spec_opts, **options}
        m = get_model(name, **opts)
        return m, name, opts
    name = getattr(model, "name", None)
    if name is None or not hasattr(model, "eval_with_grad"):
        raise FitError(f"model must be a name or a gonio.brdf model, got {model!r}")
    return model, name, dict(getattr(model, "options", {}) or {})


def fit(
    samples: Any,
    model: Any = "auto",
    *,
    loss: str = "auto",
    robust: str | None = None,
    f_scale: float = 1.0,
    algorithm: str = "auto",
    x0: dict[str, float] | None = None,
    n_starts: int | None = None,
    energy_conservation: bool = True,
    absolute_sigma: bool | None = None,
    varpro: bool = True,
    maxeval: int = 400,
    candidates: tuple[str, ...] | None = None,
    criterion: str = "bic",
    seed: int = 0,
    model_options: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
    sample_weight: np.ndarray | None = None,
) -> FitResult:
    """Fit a BRDF model to samples.

    Parameters
    ----------
    samples
        A :class:`gonio.dataset.BRDFSamples` (``wi``, ``wo`` (N, 3), ``brdf`` and
        ``brdf_std`` (N, C) in 1/sr, ``flags``).  Flagged and non-finite samples are left
        out and counted in ``diagnostics["dropped"]``.
    model
        A model name for :func:`gonio.brdf.get_model` (``"lambert+ggx"``), optionally with
        model options in brackets (``"lambert+ggx[fresnel=schlick]"``), a model object,
        or ``"auto"``: fit the candidates and choose by ``criterion``
        (see :func:`gonio.fitting.select.select_model`).
    loss
        ``"auto"`` (``weighted_l2`` when all samples have sigmas, else ``cosine_l2``),
        ``"weighted_l2"``, ``"cosine_l2"``, ``"l2"`` or ``"log"``.
    robust, f_scale
        Robust penalty (``"soft_l1"``, ``"huber"``, ``"cauchy"``, ``"arctan"``) and its
        scale in residual units, for data with outliers.
    algorithm
        ``"auto"`` (Sobol multistart + ``LD_LBFGS``), a local nlopt algorithm used in place
        of ``LD_LBFGS`` (``LD_SLSQP``, ``LD_MMA``, ``LN_BOBYQA``, ...), or a global one used
        in place of the Sobol stage (``GN_DIRECT_L``, ``GN_CRS2_LM``, ``G_MLSL_LDS``).
    x0
        Starting shape parameters (natural units); it is one more local start.
    n_starts
        Sobol design size (default 16 for one shape parameter, 64 for two, 128 beyond);
        0 runs the local search from ``x0`` or the defaults only.
    energy_conservation
        Constrain the directional albedo to <= 1 when the free fit exceeds it.
    absolute_sigma
        Trust the samples' sigmas as absolute (default: True for ``weighted_l2``).
    varpro
        Solve linear parameters by variable projection (default).  False searches all
        parameters with the chosen algorithm (for comparison; slower).
    maxeval
        Evaluation budget of each local search (and of a global nlopt algorithm x 4).
    candidates, criterion
        For ``model="auto"``: candidate model specs (default
        :data:`gonio.fitting.select.DEFAULT_CANDIDATES`; add
        :data:`~gonio.fitting.select.FRESNEL_CANDIDATES` for Fresnel-weighted lobes) and
        ``"bic"`` or ``"aic"``.
    seed
        Seed of the Sobol design and of nlopt's stochastic algorithms.
    model_options
        Keyword options of the model (``{"fresnel": "schlick"}``).
    progress
        Called with a short text after each stage (used by the CLI's progress bar).
    sample_weight
        (N,) weights >= 0 of the samples' terms in the cost, ``0.5 * sum(w * rho(r**2))``
        (importance weights: :func:`gonio.fitting.model_error.coverage_weights`); None: 1.

    Returns
    -------
    FitResult
        See :class:`gonio.fitting.result.FitResult`.

    Raises
    ------
    FitError
        No usable data, all-zero data, fewer residuals than parameters, or no finite cost.
    UnknownNameError
        Unknown model, loss, robust penalty or algorithm.
    """
    if isinstance(model, str) and model == "auto":
        from gonio.fitting.select import select_model

        if model_options:
            raise FitError(
                f"model_options {model_options} apply to one model; with model='auto' write "
                "them into the candidate specs, e.g. candidates=('lambert', "
                "'lambert+ggx[fresnel=schlick]')"
            )

        # The candidates are fitted without the geometric modes (their covariance is not
        # what ranks them); the chosen one gets them afterwards, at its optimum.
        modes = geometric_modes_of(samples)
        result = select_model(
            samples if modes is None else _WithoutModes(samples),
            candidates=candidates,
            criterion=criterion,
            loss=loss,
            robust=robust,
            f_scale=f_scale,
            algorithm=algorithm,
            energy_conservation=energy_conservation,
            absolute_sigma=absolute_sigma,
            maxeval=maxeval,
            seed=seed,
            progress=progress,
            sample_weight=sample_weight,
        )
        if modes is not None:
            _geometry_after_selection(result, samples, modes, f_scale, sample_weight)
    else:
        result = fit_model(
            samples,
            model,
            loss=loss,
            robust=robust,
            f_scale=f_scale,
            algorithm=algorithm,
            x0=x0,
            n_starts=n_starts,
            energy_conservation=energy_conservation,
            absolute_sigma=absolute_sigma,
            varpro=varpro,
            maxeval=maxeval,
            seed=seed,
            model_options=model_options,
            progress=progress,
            sample_weight=sample_weight,
        )
    rel = getattr(samples, "attrs", {}).get("calibration_rel_std")
    if rel is not None:
        add_calibration_uncertainty(result, rel)
    return result


class _WithoutModes:
    """The samples as model selection sees them: every attribute but the geometric modes."""

    def __init__(self, samples: Any) -> None:
        self._samples = samples

    def __getattr__(self, name: str) -> Any:
        if name == "geometry_modes":
            return None
        return getattr(self._samples, name)


def _geometry_after_selection(
    result: FitResult,
    samples: Any,
    modes: GeometricModes,
    f_scale: float,
    sample_weight: np.ndarray | None = None,
) -> None:
    """Give the selected fit the covariance with the geometric modes (in place)."""
    from gonio.brdf import get_model

    m = get_model(result.model, **result.model_options)
    prob = prepare_problem(
        m, samples, get_loss(result.loss), result.robust, f_scale, sample_weight=sample_weight
    )
    theta = np.array([result.params[n][0] for n in prob.shape_names])
    a = np.array([result.params[n] for n in prob.linear_names]).reshape(
        prob.n_linear, prob.n_channels
    )
    x = prob.pack(theta, a)
    absolute_sigma = bool(result.diagnostics["absolute_sigma"])
    unc = covariance_at(prob, x, absolute_sigma)
    unc, split = _add_geometry(prob, x, unc, modes.subset(prob.used), absolute_sigma)
    result.covariance = unc.covariance
    result.std = _std_by_name(prob, unc.std)
    result.diagnostics.update(split)


def _std_by_name(prob: Problem, std_x: np.ndarray) -> dict[str, np.ndarray]:
    """Per-parameter std (C,) in the model's parameter order from the std of ``x``."""
    C, S = prob.n_channels, prob.n_shape
    std: dict[str, np.ndarray] = {}
    for s, n in enumerate(prob.shape_names):
        std[n] = np.full(C, float(std_x[s]))
    for j, n in enumerate(prob.linear_names):
        std[n] = std_x[S + j * C : S + (j + 1) * C].copy()
    return {n: std[n] for n in prob.model.param_names}


def _check_algorithm(name: str) -> None:
    if name != "auto" and name not in ALGORITHMS:
        raise UnknownNameError(
            f"unknown algorithm {name!r}; expected 'auto' or one of {', '.join(ALGORITHMS)}"
        )


def _design_size(S: int, n_starts: int | None) -> int:
    if n_starts is not None:
        return int(n_starts)
    return {0: 0, 1: 16, 2: 64}.get(S, 128)


def _distinct_best(U: np.ndarray, costs: np.ndarray, k: int, span: np.ndarray) -> list[np.ndarray]:
    """The ``k`` lowest-cost points that are not neighbours of a better one."""
    order = np.argsort(costs)
    out: list[np.ndarray] = []
    for i in order:
        if not np.isfinite(costs[i]):
            break
        if all(np.max(np.abs(U[i] - v) / span) > 0.12 for v in out):
            out.append(U[i])
        if len(out) >= k:
            break
    return out


def fit_model(
    samples: Any,
    model: Any,
    *,
    loss: str = "auto",
    robust: str | None = None,
    f_scale: float = 1.0,
    algorithm: str = "auto",
    x0: dict[str, float] | None = None,
    n_starts: int | None = None,
    energy_conservation: bool = True,
    absolute_sigma: bool | None = None,
    varpro: bool = True,
    maxeval: int = 400,
    seed: int = 0,
    model_options: dict[str, Any] | None = None,
    progress: Callable[[str], None] | None = None,
    sample_weight: np.ndarray | None = None,
) -> FitResult:
    """Fit one model; the parameters are those of :func:`fit` (without ``model="auto"``)."""
    _check_algorithm(algorithm)
    m, model_name, opts = _get_model(model, dict(model_options or {}))
    loss_name = resolve_loss(loss, samples)
    loss_obj = get_loss(loss_name)
    if robust is not None:
        from gonio.fitting.losses import ROBUST

        if robust not in ROBUST:
            raise UnknownNameError(
                f"unknown robust penalty {robust!r}; expected one of {', '.join(ROBUST)}"
            )
    prob = prepare_problem(m, samples, loss_obj, robust, f_scale, sample_weight=sample_weight)
    # read (and checked) before the search: a malformed mode table fails fast
    modes = geometric_modes_of(samples)
    if absolute_sigma is None:
        absolute_sigma = loss_name == "weighted_l2"
    path: list[str] = []
    status = 0
    message = ""
    say = progress or (lambda s: None)

    # --- stage A: shape search by variable projection on a linear loss ------------------
    linear_ok = loss_obj.linear and robust is None
    # non-linear losses start from the variable-projection fit of the nearest linear loss
    init_loss = loss_obj if loss_obj.linear else get_loss("cosine_l2")
    init_prob = (
        prob if linear_ok else prepare_problem(m, samples, init_loss, sample_weight=sample_weight)
    )
    local_alg = (
        algorithm if algorithm in ALGORITHMS and algorithm not in GLOBAL_ALGORITHMS else "LD_LBFGS"
    )
    user_u = None
    if x0:
        vp_tmp = prob
        th = np.array([float(x0.get(n, np.nan)) for n in vp_tmp.shape_names])
        if np.all(np.isfinite(th)):
            user_u = vp_tmp.to_u(np.clip(th, vp_tmp.lb_shape, vp_tmp.ub_shape))

    # the variable projection that found x_best, when it is the fitted problem's own: its
    # kernels' sums at the optimum give the covariance's J^T J (VarPro.jtj)
    vp_best: VarPro | None = None
    if varpro or not linear_ok:
        x_best, status, message, vp_best = _varpro_stage(
            init_prob, algorithm, local_alg, user_u, n_starts, maxeval, seed, path, say
        )
        if not linear_ok:
            vp_best = None
            # the search variables are the same in both problems (same model and samples
            # apart from the log-loss exclusions), so x carries over
            x_best, status, message = _full_local(prob, x_best, local_alg, maxeval, path, say)
    else:
        vp = VarPro(prob)
        th0 = prob.from_u(user_u) if user_u is not None else vp.default_theta()
        d = dict(getattr(m, "defaults", {}) or {})
        a0 = np.array([[float(d.get(n, 0.5))] * prob.n_channels for n in prob.linear_names])
        a0 = (
            np.clip(
                a0.reshape(prob.n_linear, prob.n_channels),
                prob.lb_lin[:, None],
                prob.ub_lin[:, None],
            )
            if prob.n_linear
            else a0.reshape(0, prob.n_channels)
        )
        x_start = prob.pack(th0, a0)
        if algorithm in GLOBAL_ALGORITHMS:
            lo, hi = prob.x_bounds()
            hi = np.where(np.isfinite(hi), hi, np.maximum(10 * np.abs(lo), 10.0))
            r = nlopt_minimize(
                prob.full_cost, x_start, lo, hi, algorithm, maxeval=maxeval * 4, seed=seed
            )
            path.append(f"{algorithm}(full)")
            x_start = r.x
        x_best, status, message = _full_local(prob, x_start, local_alg, maxeval, path, say)

    # --- stage C: energy conservation ---------------------------------------------------
    max_alb = None
    if energy_conservation:
        max_alb = _max_albedo(prob, x_best)
        if max_alb is not None and np.any(max_alb > 1.0 + _ENERGY_TOL):
            say("energy conservation")
            x_best, status, message = _energy_stage(prob, x_best, maxeval, path)
            max_alb = _max_albedo(prob, x_best)
            vp_best = None
    jtj = None if vp_best is None else vp_best.jtj(x_best)
    return _finish(
        prob,
        x_best,
        status,
        message,
        path,
        absolute_sigma,
        max_alb,
        model_name,
        opts,
        modes,
        jtj,
    )


def _varpro_stage(
    prob: Problem, algorithm: str, local_alg: str, user_u, n_starts, maxeval, seed, path, say
):
    vp = VarPro(prob)
    S = prob.n_shape
    if S == 0:
        _, _, a = vp.evaluate(np.zeros(0), want_grad=False)
        path.append("linear-lsq")
        return prob.pack(np.zeros(0), a), 1, "linear least squares (exact)", vp
    lo, hi = prob.u_bounds
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise FitError(
            f"model {getattr(prob.model, 'name', '?')}: shape parameters "
            f"{prob.shape_names} need finite bounds for the global search, got {lo}, {hi}"
        )
    span = np.where(hi > lo, hi - lo, 1.0)

    def fun(u: np.ndarray, want: bool):
        c, g, _ = vp.evaluate(u, want)
        return c, g

    # Large data sets: design and local searches on a random subset, then one polish on
    # all samples from the subset's optimum (the same basin; 5x fewer full evaluations).
    screen = _screen_problem(prob, seed) if algorithm not in GLOBAL_ALGORITHMS else prob
    vs = vp if screen is prob else VarPro(screen)

    def fun_s(u: np.ndarray, want: bool):
        c, g, _ = vs.evaluate(u, want)
        return c, g

    starts: list[np.ndarray] = []
    if algorithm in GLOBAL_ALGORITHMS:
        r = nlopt_minimize(
            fun,
            0.5 * (lo + hi) if user_u is None else user_u,
            lo,
            hi,
            algorithm,
            maxeval=maxeval * 4,
            seed=seed,
        )
        path.append(f"{algorithm}({r.nfev})")
        starts.append(r.x)
    else:
        nd = _design_size(S, n_starts)
        if nd > 0:
            U = sobol_design(lo, hi, nd, seed=seed)
            costs = vs.batch_cost(U)
            path.append(f"sobol({U.shape[0]})")
            starts.extend(_distinct_best(U, costs, 2 if S == 1 else 3, span))
            say("global design")
    if user_u is not None:
        starts.append(np.clip(user_u, lo, hi))
    if not starts:
        starts.append(prob.to_u(vp.default_theta()))
    best: NloptResult | None = None
    for s in starts:
        r = nlopt_minimize(
            fun_s, s, lo, hi, local_alg, maxeval=maxeval, seed=seed, x_scale=_scale(vs, s, lo, hi)
        )
        if best is None or r.fun < best.fun:
            best = r
    assert best is not None
    path.append(f"{local_alg} x{len(starts)}")
    if screen is not prob:
        prob.njev += screen.njev
        path[-1] += f" (subset {screen.wi.shape[0]})"
        # a step of 1e-9 in ln(alpha) changes the cost by ~1e-18 relative at the minimum
        best = nlopt_minimize(
            fun,
            best.x,
            lo,
            hi,
            local_alg,
            maxeval=maxeval,
            seed=seed,
            xtol_rel=1e-9,
            x_scale=_scale(vp, best.x, lo, hi),
        )
        path.append(f"{local_alg}(all {prob.wi.shape[0]})")
    say("local search")
    _, _, a = vp.evaluate(best.x, want_grad=False)
    return np.concatenate([best.x, a.ravel()]), best.status, best.message, vp


def _scale(vp: VarPro, u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
    """The local search's preconditioner at its start ``u``: the square root of the
    reduced cost's Gauss-Newton curvature (``VarPro.curvature``), so that the search's
    first step is Newton's; None when unknown.  (Measured on 10^5 samples: the polish
    from the subset's optimum took 5 evaluations, its first step going to a bound.)"""
    curv = vp.curvature(np.clip(np.asarray(u, dtype=np.float64), lo, hi))
    if curv is None or not np.all(np.isfinite(curv) & (curv > 0)):
        return None
    return np.sqrt(curv)


def _screen_problem(prob: Problem, seed: int) -> Problem:
    """A random subset of at most ``_SCREEN_MAX`` samples for the design stage."""
    n = prob.wi.shape[0]
    if n <= _SCREEN_MAX:
        return prob
    idx = np.sort(np.random.default_rng(seed).choice(n, _SCREEN_MAX, replace=False))
    return Problem(
        model=prob.model,
        wi=prob.wi[idx],
        wo=prob.wo[idx],
        y=prob.y[idx],
        sigma=None if prob.sigma is None else prob.sigma[idx],
        cos_i=prob.cos_i[idx],
        loss=prob.loss,
        robust=prob.robust,
        f_scale=prob.f_scale,
        used=prob.used,
        channels=prob.channels,
        dropped={},
        shape_names=prob.shape_names,
        linear_names=prob.linear_names,
        log_shape=prob.log_shape,
        log_offset=prob.log_offset,
        lb_shape=prob.lb_shape,
        ub_shape=prob.ub_shape,
        lb_lin=prob.lb_lin,
        ub_lin=prob.ub_lin,
        sample_weight=None if prob.sample_weight is None else prob.sample_weight[idx],
    )


def _full_local(prob: Problem, x: np.ndarray, alg: str, maxeval: int, path, say):
    lo, hi = prob.x_bounds()
    r = nlopt_minimize(prob.full_cost, x, lo, hi, alg, maxeval=maxeval * 2)
    path.append(f"{alg}(full)")
    if r.status < 0 and alg != "LD_SLSQP":
        # nlopt's L-BFGS gives up with a bare failure when its line search stalls near
        # the minimum (robust penalties): finish from its best point with SLSQP
        r2 = nlopt_minimize(prob.full_cost, r.x, lo, hi, "LD_SLSQP", maxeval=maxeval * 2)
        path.append("LD_SLSQP(full, after failure)")
        if r2.fun <= r.fun:
            r = r2
    say("full-space search")
    return r.x, r.status, r.message


def _albedo_basis(
    prob: Problem, thetas: np.ndarray, nodes: np.ndarray = ENERGY_THETA
) -> np.ndarray:
    """Directional albedo per unit linear parameter at ``nodes`` (T,) polar angles (rad,
    default ENERGY_THETA): (M, T, K) for shape parameter sets ``thetas`` (M, S), in one
    broadcast call of the model's quadrature."""
    unit = unit_values(prob)
    thetas = np.atleast_2d(thetas)
    K = prob.n_linear
    lobes = _lobe_parameters(prob.model)
    if lobes is not None:
        # One quadrature per lobe at its own unit weight: the model's albedo would
        # integrate every lobe for every column, K - 1 of them at weight 0.
        from gonio.brdf.albedo import lobe_albedo

        shape = {n: thetas[:, s, None] for s, n in enumerate(prob.shape_names)}
        out = np.empty((thetas.shape[0], nodes.size, K))
        for lobe, names in lobes:
            lin = [n for n in names.values() if n in prob.linear_names]
            j = prob.linear_names.index(lin[0])
            lp = {
                local: np.asarray(shape[n] if n in shape else unit[j], dtype=np.float64)
                for local, n in names.items()
            }
            if getattr(lobe, "kind", "") == "lambert":
                # f = albedo / pi integrates to the albedo exactly (the quadrature gives
                # it to 2e-11 in 19 ms, 3 of the 4 `--model auto` candidates have one)
                out[:, :, j] = 1.0
                continue
            out[:, :, j] = lobe_albedo(lobe, nodes[None, :], lp) / unit[j]
        return out
    p: dict[str, Any] = {n: thetas[:, s, None, None] for s, n in enumerate(prob.shape_names)}
    eye = np.eye(K)
    for j, n in enumerate(prob.linear_names):
        p[n] = (unit[j] * eye[j])[None, None, :]  # lobe j alone in column j
    out = prob.model.albedo(nodes[None, :, None], p)
    out = np.broadcast_to(out, (thetas.shape[0], nodes.size, K))
    return out / unit


def _lobe_parameters(model: Any) -> list[tuple[Any, dict[str, str]]] | None:
    """``(lobe, {local name: public name})`` per lobe of a model when every lobe has
    exactly one linear parameter and the names are the model's, else None.

    The public names follow gonio.brdf.base.Model (a name repeated across lobes gets the
    lobe's 1-based position as suffix); a model whose names do not match is left to the
    model's own albedo."""
    lobes = tuple(getattr(model, "lobes", ()) or ())
    if not lobes:
        return None
    counts: dict[str, int] = {}
    for lobe in lobes:
        for sp in lobe.specs:
            counts[sp.name] = counts.get(sp.name, 0) + 1
    out, seen = [], []
    linear = set(getattr(model, "linear_params", ()) or ())
    for i, lobe in enumerate(lobes, start=1):
        names = {
            sp.name: sp.name if counts[sp.name] == 1 else f"{sp.name}_{i}" for sp in lobe.specs
        }
        if sum(n in linear for n in names.values()) != 1:
            return None
        seen += names.values()
        out.append((lobe, names))
    if sorted(seen) != sorted(model.param_names):
        return None
    return out


def _max_albedo(prob: Problem, x: np.ndarray) -> np.ndarray | None:
    """Largest directional albedo over ENERGY_THETA per channel (C,), or None if unknown."""
    if not hasattr(prob.model, "albedo") or prob.n_linear == 0:
        return None
    theta, a = prob.unpack(x)
    try:
        B = _albedo_basis(prob, theta)[0]  # (T, K)
    except (ImportError, NotImplementedError):  # a model without albedo: nothing to check
        return None
    return np.max(B @ a, axis=0)


def _energy_stage(prob: Problem, x: np.ndarray, maxeval: int, path: list[str]):
    """Refit in full space under albedo(theta_i) <= 1 (per channel) with LD_SLSQP."""
    S, K, C = prob.n_shape, prob.n_linear, prob.n_channels
    T = ENERGY_THETA.size

    cache: dict[str, Any] = {}

    def basis_fd(xx: np.ndarray) -> np.ndarray:
        # albedo bases at theta and at theta + h e_s (forward differences in u), cached
        # because SLSQP asks for the constraints at the point it just evaluated
        key = xx[:S].tobytes()
        if cache.get("key") != key:
            u = xx[:S]
            hs = 1e-6 * np.maximum(1.0, np.abs(u))
            us = np.vstack([u, u + np.diag(hs)]) if S else u[None, :]
            cache.update(key=key, B=_albedo_basis(prob, prob.from_u(us)), h=hs)
        return cache["B"], cache["h"]

    def cons(xx: np.ndarray, grad: np.ndarray) -> np.ndarray:
        theta, a = prob.unpack(xx)
        Bs, hs = basis_fd(xx)
        B = Bs[0]
        val = (B @ a).T.ravel() - 1.0  # (C*T,) ordered channel-major
        if grad.size:
            grad[:] = 0.0
            for s in range(S):
                grad[:, s] = (((Bs[1 + s] - B) @ a).T.ravel()) / hs[s]
            for c in range(C):
                for j in range(K):
                    grad[c * T : (c + 1) * T, S + j * C + c] = B[:, j]
        return val

    # start from a feasible point: scale the linear parameters down
    theta, a = prob.unpack(x)
    B = _albedo_basis(prob, theta)[0]
    worst = np.max(B @ a, axis=0)
    a0 = a / np.maximum(worst, 1.0)[None, :] * (1 - 1e-9)
    x0 = prob.pack(theta, a0)
    lo, hi = prob.x_bounds()
    r = nlopt_minimize(
        prob.full_cost,
        x0,
        lo,
        hi,
        "LD_SLSQP",
        maxeval=maxeval * 2,
        ineq=cons,
        n_ineq=C * T,
        ineq_tol=1e-10,
    )
    path.append("LD_SLSQP(energy)")
    return r.x, r.status, r.message + " (albedo <= 1 enforced)"


def _add_geometry(prob: Problem, x: np.ndarray, unc: Any, modes: GeometricModes, absolute_sigma):
    """The covariance with the correlated geometric errors (sandwich), and the variance
    split per parameter for the diagnostics."""

    def albedo_at(nodes: np.ndarray) -> np.ndarray:
        # the fitted model's directional albedo (T, C): the stray light's shape
        if prob.n_linear == 0 or not hasattr(prob.model, "albedo"):
            raise NotImplementedError
        theta, a = prob.unpack(x)
        return _albedo_basis(prob, theta, np.asarray(nodes, dtype=np.float64))[0] @ a

    noise, geometry, systematic, info = sandwich_covariance(
        prob, x, unc.h_inverse, unc.covariance, modes, absolute_sigma, albedo_at
    )
    cov = noise + geometry + systematic
    # an undetermined parameter (std inf) stays undetermined; one at a bound stays at 0
    std = np.where(np.isfinite(unc.std), np.sqrt(np.clip(np.diag(cov), 0.0, None)), unc.std)
    std = np.where(unc.free, std, 0.0)
    split = {
        "variance_split": {
            "labels": list(prob.labels),
            "noise": np.diag(noise).tolist(),
            "geometry": np.diag(geometry).tolist(),
            "systematic": np.diag(systematic).tolist(),
            "calibration": [0.0] * prob.n_params,
        },
        "geometry_modes": info,
    }
    return dataclasses.replace(unc, covariance=cov, std=std), split


def _finish(
    prob: Problem,
    x: np.ndarray,
    status: int,
    message: str,
    path: list[str],
    absolute_sigma: bool,
    max_alb,
    model_name: str,
    opts: dict[str, Any],
    modes: GeometricModes | None = None,
    jtj: tuple[np.ndarray, np.ndarray] | None = None,
) -> FitResult:
    if not np.all(np.isfinite(x)):
        raise FitError(
            f"fit of {model_name} produced non-finite parameters ({message}); x={x.tolist()}"
        )
    theta, a = prob.unpack(x)
    unc = covariance_at(prob, x, absolute_sigma, jtj)
    cost = unc.cost
    finite = bool(np.all(np.isfinite(x)) and np.isfinite(cost))
    if not finite:
        raise FitError(
            f"fit of {model_name} produced non-finite parameters or cost ({message}); "
            f"x={x.tolist()}"
        )
    C = prob.n_channels
    split = None
    if modes is not None:
        unc, split = _add_geometry(prob, x, unc, modes.subset(prob.used), absolute_sigma)
    params: dict[str, np.ndarray] = {}
    std: dict[str, np.ndarray] = {}
    S = prob.n_shape
    # natural-unit parameter vector in label order
    names = list(prob.model.param_names)
    for s, n in enumerate(prob.shape_names):
        params[n] = np.full(C, float(theta[s]))
        std[n] = np.full(C, float(unc.std[s]))
    for j, n in enumerate(prob.linear_names):
        params[n] = a[j].copy()
        std[n] = unc.std[S + j * C : S + (j + 1) * C].copy()
    params = {n: params[n] for n in names}
    std = {n: std[n] for n in names}
    r = unc.residuals
    if prob.used.all():
        full_r = np.array(r, dtype=np.float64)  # (a copy: boolean assignment is ~50x slower)
    else:
        full_r = np.full((prob.used.size, C), np.nan)
        full_r[prob.used] = r
    m = r.size
    p = int(unc.free.sum())
    if absolute_sigma:
        m2ll = 2.0 * cost
    else:
        m2ll = m * np.log(max(2.0 * cost / m, 1e-300))
    success = status > 0 and finite
    diag = {
        "condition_number": unc.condition_number,
        "at_bounds": unc.at_bounds,
        "max_albedo": None if max_alb is None else np.asarray(max_alb).tolist(),
        "aic": float(m2ll + 2 * p),
        "bic": float(m2ll + p * np.log(m)),
        "dropped": dict(prob.dropped),
        "sigma_scale": unc.sigma_scale,
        "absolute_sigma": bool(absolute_sigma),
        "n_residuals": m,
        "rms_residual": float(np.sqrt(2.0 * cost / m)),
    }
    if split is not None:
        diag.update(split)
    return FitResult(
        model=model_name,
        model_options=dict(opts),
        channels=prob.channels,
        params=params,
        std=std,
        covariance=unc.covariance,
        param_labels=prob.labels,
        shape_params=tuple(prob.shape_names),
        linear_params=tuple(prob.linear_names),
        loss=prob.loss.name,
        robust=prob.robust,
        cost=float(cost),
        residuals=full_r,
        used=prob.used.copy(),
        n_samples=int(prob.used.sum()),
        n_params=prob.n_params,
        nfev=prob.nfev,
        njev=prob.njev,
        algorithm=path,
        status=int(status),
        message=message,
        success=bool(success),
        diagnostics=diag,
    )
