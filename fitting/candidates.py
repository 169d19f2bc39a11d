"""Every candidate model fitted, a misfit read from the data, and the models' weights.

One function, :func:`fit_candidates`, for everything that fits a set of candidate models
to one sample set and needs to know which of them to believe: the adaptive session's
advisor (``gonio.app.adaptive_advisor.FitAdvisor``) and ``benchmarks/adaptive.py`` (its
grids and its adaptive runs) call it, so that what the benchmark measures is what a
session does.

1. Every candidate is fitted with the samples' noise sigmas (weighted L2,
   :func:`gonio.fitting.fit.fit_model`).
2. When the best of them leaves ``chi^2 / dof > MISFIT_CHI2_DOF`` (no candidate follows
   the material, :mod:`gonio.fitting.model_error`), every candidate is fitted again by
   the aligned fit (:func:`gonio.fitting.model_error.fit_aligned`: a Cauchy penalty on
   relative residuals, coverage weights), or, with ``aligned=False``, with the model
   discrepancy ``tau`` added to the sigmas.
3. The weights.  Without a misfit: the BIC posterior ``exp(-BIC / 2)`` of the Gaussian
   likelihood the noise sigmas define, with the model ``gonio fit --model auto`` reports
   (:func:`gonio.fitting.select.select_model`'s matte rule) given the largest weight.
   On an aligned misfit the candidates are compared on one criterion computed the same
   way for all of them from their fitted values (:func:`aligned_criterion`), never on
   each fit's own ``cost`` through a rule calibrated on Gaussian costs: the matte rule's
   cost ratio (a diffuse fit within 2.2x of the best one's cost) applied to Cauchy
   costs, which grow only logarithmically with the residuals, made every misfit
   "choose" ``lambert``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gonio.errors import FitError

__all__ = ["CandidateFits", "aligned_criterion", "chosen_index", "fit_candidates"]


@dataclass(frozen=True)
class CandidateFits:
    """What :func:`fit_candidates` returns.

    Attributes
    ----------
    fits
        The candidates fitted successfully, in the order asked (FitResult each).
    weights
        (F,) the models' weights (sum 1); the largest is the model to report.
    samples
        The samples the fits were made to: the input's noise sigmas, or on a misfit the
        aligned sigmas (:func:`gonio.fitting.model_error.aligned_samples`) or the
        discrepancy's (``sigma^2 + tau^2``), 1/sr.
    misfit
        None without the misfit check; else ``chi2_dof`` (the best candidate's, noise
        sigmas), ``tau`` (1/sr; 0: no misfit) and, on a misfit, ``fit`` (``"aligned"``
        or ``"tau"``).
    criterion
        What ranked the candidates: ``"bic"`` (noise sigmas, matte rule) or
        ``"aligned_bic"``.
    scores
        (F,) that criterion per fit (lower is better; dimensionless).
    errors
        Candidate spec -> why it could not be fitted (left out of ``fits``).
    """

    fits: list[Any]
    weights: np.ndarray
    samples: Any
    misfit: dict[str, Any] | None
    criterion: str
    scores: np.ndarray
    errors: dict[str, str] = field(default_factory=dict)

    @property
    def best_index(self) -> int:
        """Position in ``fits`` of the model with the largest weight."""
        return int(np.argmax(self.weights))

    @property
    def best(self) -> Any:
        """The fit with the largest weight."""
        return self.fits[self.best_index]

    @property
    def is_misfit(self) -> bool:
        """True when the data showed a misfit (``tau > 0``)."""
        return bool(self.misfit and self.misfit.get("tau", 0.0) > 0.0)


def aligned_criterion(fits: Sequence[Any]) -> np.ndarray:
    """The criterion aligned fits of one sample set are ranked by (F,), lower is better.

    :func:`gonio.fitting.model_error.aligned_bic`: ``4 cost + p ln m`` with ``cost`` the
    Cauchy cost of the aligned residuals (the same samples, sigmas and coverage weights
    for every candidate: one likelihood for all of them) and ``p`` every parameter of
    the model.  An unsuccessful fit is ``inf``.
    """
    from gonio.fitting.model_error import aligned_bic

    return np.array([aligned_bic(r) for r in fits], dtype=np.float64)


def _posterior(scores: np.ndarray) -> np.ndarray:
    ok = np.isfinite(scores)
    if not ok.any():
        raise FitError("no candidate model was fitted successfully")
    w = np.where(ok, np.exp(-0.5 * (scores - np.min(scores[ok]))), 0.0)
    return w / w.sum()


def chosen_index(fits: Sequence[Any], w: np.ndarray) -> int:
    """The model :func:`gonio.fitting.select.select_model` reports among ``fits`` (noise
    sigmas, Gaussian costs): the lowest BIC, unless that lobe is matte (< ``MIN_GLOSS``
    GU at 60 deg) and a diffuse candidate's cost is within ``MAX_DIFFUSE_COST_RATIO`` of
    it (select's rule, applied to fits already made instead of fitting every candidate
    twice)."""
    from gonio.fitting.select import DIFFUSE_MODELS, MAX_DIFFUSE_COST_RATIO, MIN_GLOSS, gloss_units

    best = int(np.argmax(w))
    if fits[best].model in DIFFUSE_MODELS:
        return best
    if float(np.mean(gloss_units(fits[best].bind()))) >= MIN_GLOSS:
        return best
    diffuse = [
        i
        for i, r in enumerate(fits)
        if r.model in DIFFUSE_MODELS and r.cost <= MAX_DIFFUSE_COST_RATIO * fits[best].cost
    ]
    return max(diffuse, key=lambda i: w[i]) if diffuse else best


def _fit_all(
    samples: Any, candidates: Sequence[str], fitter: Callable[..., Any], options: Mapping[str, Any]
) -> tuple[list[Any], dict[str, str]]:
    fits, errors = [], {}
    for c in candidates:
        try:
            r = fitter(samples, c, **options)
        except FitError as exc:
            errors[c] = str(exc)
            continue
        if r.success and np.isfinite(r.cost):
            fits.append(r)
        else:
            errors[c] = r.message or "no finite fit"
    return fits, errors


def fit_candidates(
    samples: Any,
    candidates: Sequence[str],
    *,
    misfit: bool = True,
    aligned: bool = True,
    coverage: bool = False,
    fit_options: Mapping[str, Any] | None = None,
) -> CandidateFits:
    """Fit every candidate; on a misfit refit them (aligned fit); weigh the models.

    Parameters
    ----------
    samples
        :class:`gonio.dataset.BRDFSamples` (``brdf``, ``brdf_std`` in 1/sr).
    candidates
        Model specs (``"lambert+ggx"``, ``"lambert+beckmann[fresnel=schlick]"``, ...).
    misfit
        Read a misfit from the best candidate's ``chi^2 / dof`` (see the module
        docstring); False: the noise-sigma fits whatever they leave.
    aligned
        On a misfit, the aligned fit (default); False: the discrepancy ``tau`` added to
        every sigma and the candidates fitted again (one noise model, so the Gaussian BIC
        still compares them).
    coverage
        With ``aligned=False``: also weigh the samples by
        :func:`gonio.fitting.model_error.coverage_weights`.  (The aligned fit always
        does.)
    fit_options
        Passed to every fit (``fit_model``'s keywords, e.g. ``maxeval``, ``seed``).

    Returns
    -------
    CandidateFits

    Raises
    ------
    FitError
        No candidate could be fitted (each candidate's reason in the message).
    """
    from gonio.fitting import model_error
    from gonio.fitting.design import bic_weights
    from gonio.fitting.fit import fit_model

    opts = dict(fit_options or {})
    fits, errors = _fit_all(samples, candidates, fit_model, opts)
    if not fits:
        why = "; ".join(f"{k}: {v}" for k, v in errors.items())
        raise FitError(f"no candidate model could be fitted ({why})")
    info: dict[str, Any] | None = None
    fitted = samples
    if misfit:
        chi2 = min(model_error.chi2_dof(r, samples) for r in fits)
        tau = model_error.model_error_scale(fits, samples)
        info = {"chi2_dof": float(chi2), "tau": float(tau)}
        if tau > 0.0 and aligned:
            info["fit"] = "aligned"
            afits, aerr = _fit_all(samples, candidates, model_error.fit_aligned, opts)
            if afits:
                scores = aligned_criterion(afits)
                return CandidateFits(afits, _posterior(scores),
                                     model_error.aligned_samples(samples), info,
                                     "aligned_bic", scores, aerr)  # fmt: skip
            info["fit"] = "aligned failed: noise sigmas"
        elif tau > 0.0:
            info["fit"] = "tau"
            fitted = model_error.with_model_error(samples, tau)
            if coverage:
                w = model_error.coverage_weights(fitted.wi, fitted.wo)
                fitted = model_error.with_weights(fitted, w)
            tfits, terr = _fit_all(fitted, candidates, fit_model, opts)
            if tfits:
                fits, errors = tfits, terr
            else:
                fitted = samples
    from gonio.fitting.select import information_criterion

    scores = np.array([information_criterion(r, "bic") for r in fits])
    w = bic_weights(fits)
    k = chosen_index(fits, w)
    if w[k] < w.max():  # the matte rule's prior: the reported model is the one designed for
        w = w.copy()
        w[k] = w.max() * (1.0 + 1e-9)
        w = w / w.sum()
    return CandidateFits(fits, w, fitted, info, "bic", scores, errors)
