"""``model="auto"``: fit candidate models and choose one by an information criterion.

Each candidate is fitted with the same loss and samples; the criterion (BIC by default,
AIC on request) is computed from the fitted cost (``-2 ln L = chi^2`` with absolute sigmas,
``m ln(RSS/m)`` otherwise) plus the parameter penalty (``p ln m`` or ``2 p``), with ``p``
the number of free parameters (shape + linear x channels, parameters held at a bound not
counted).  The model with the lowest criterion wins, so a specular lobe is reported only
when the data support its extra parameters.

Measured BRDFs are not noise-limited: with thousands of samples even a tiny systematic
misfit of a diffuse model is "significant".  Two safeguards keep the choice physical:

- ``m`` in the criterion is the *effective* number of samples.  Without sigmas, samples
  resampled from a tabulated BRDF (an RGL file sampled on a dense grid) are strongly
  correlated; ``effective_samples`` caps ``m`` (default: the number of samples, or 1/10 of
  it for samples made from a measured file by :func:`gonio.fitting.sampling.sample_brdf`).
- The lobe the criterion keeps must also be a *visible* specular reflection: the fitted
  BRDF's specular gloss at 60 deg (ISO 2813 geometry: receptor aperture 4.4 x 11.7 deg,
  in gloss units relative to black glass n = 1.567, 100 GU) must reach
  ``min_gloss`` (10 GU, the usual upper limit of "matte").  A broad forward-scattering
  sheen (paper: a GGX lobe with alpha ~ 0.55) or a faint highlight (matte wall paint:
  ks ~ 0.005) lowers the cost measurably yet leaves the surface matte; for such data the
  best diffuse candidate is returned and the rejected lobe is recorded in the diagnostics,
  unless the diffuse fit's cost exceeds ``MAX_DIFFUSE_COST_RATIO`` (10) times the best:
  then the diffuse model plainly cannot describe the data and the lobe is kept, matte or
  not.
- Ties (a specular weight at zero, so the same cost and free-parameter count) go to the
  earlier, simpler candidate.

Candidates are model *specs*: a name, optionally with model options in brackets,
``"lambert+ggx[fresnel=schlick]"`` (see :func:`parse_model_spec`).  The Fresnel-weighted
lobes are not in :data:`DEFAULT_CANDIDATES`: on the shared RGL files they lower the
cosine-L2 cost of ``cc_ibiza_sunset`` 7.5x and of the wall paint 4x, but not that of
``vch_golden_yellow`` (``f0`` goes to its bound 1: its coloured peak does not rise towards
grazing as a Fresnel term would); each costs one more shape parameter (a 2-D search:
``auto`` on the RGL files takes 2.3-5x longer, benchmarks/rgl_fit_table.py); on the wall
paint the diffuse cost becomes 7.1x the Fresnel fit's, close to the
``MAX_DIFFUSE_COST_RATIO`` (10) escape of the matte rule (on a coarser 5 x 12 x 24 grid it
passes it, and the 1-GU sheen is kept); and Mitsuba 3 has no exact counterpart for the
export (:func:`gonio.fitting.export.mitsuba_dict` refuses it).  Ask for them with
``candidates=DEFAULT_CANDIDATES + FRESNEL_CANDIDATES`` (CLI:
``--candidates lambert,oren-nayar,lambert+ggx,lambert+ggx[fresnel=schlick]``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from gonio.brdf.registry import format_model_spec, parse_model_spec  # noqa: F401 (re-exported)
from gonio.errors import FitError, UnknownNameError
from gonio.fitting.result import FitResult

__all__ = [
    "DEFAULT_CANDIDATES",
    "DIFFUSE_MODELS",
    "FRESNEL_CANDIDATES",
    "format_model_spec",
    "parse_model_spec",
    "gloss_units",
    "information_criterion",
    "select_model",
]

DEFAULT_CANDIDATES = ("lambert", "oren-nayar", "lambert+ggx", "lambert+beckmann")
DIFFUSE_MODELS = ("lambert", "oren-nayar")
#: Opt-in candidates: microfacet lobes weighted by Schlick's Fresnel term (one more shape
#: parameter, ``f0``, shared by the channels).
FRESNEL_CANDIDATES = ("lambert+ggx[fresnel=schlick]", "lambert+beckmann[fresnel=schlick]")
MIN_GLOSS = 10.0
#: The matte rule applies only while the best diffuse fit's cost is within this factor.
MAX_DIFFUSE_COST_RATIO = 10.0


def _fresnel_dielectric(cos_t: float, n: float) -> float:
    s2 = 1.0 - cos_t * cos_t
    ct = np.sqrt(1.0 - s2 / (n * n))
    rs = (cos_t - n * ct) / (cos_t + n * ct)
    rp = (n * cos_t - ct) / (n * cos_t + ct)
    return float(0.5 * (rs * rs + rp * rp))


def gloss_units(
    brdf: Any,
    theta_deg: float = 60.0,
    aperture_deg: tuple[float, float] = (4.4, 11.7),
    n_standard: float = 1.567,
    n_nodes: int = 15,
) -> np.ndarray:
    """Specular gloss (GU, per channel) of a BRDF in the ISO 2813 geometry.

    ``100 * (flux into the receptor aperture around the mirror direction) / (flux the black
    glass standard reflects there)``, both per unit irradiance at incidence ``theta_deg``.

    Parameters
    ----------
    brdf
        Anything with ``eval(wi, wo) -> (N, C)`` (a bound model, a measured file, or
        :meth:`FitResult.bind`).
    theta_deg
        Incidence angle (deg); 60 is the universal geometry, 20 for high gloss, 85 for matte.
    aperture_deg
        Receptor aperture (deg) in and perpendicular to the plane of incidence.
    """
    t = np.radians(theta_deg)
    da, dp = np.radians(aperture_deg)
    x = (np.arange(n_nodes) + 0.5) / n_nodes - 0.5
    to = t + da * x  # in-plane polar angle of the mirror lobe
    po = np.pi + (dp / np.sin(t)) * x  # azimuth spread giving the perpendicular width
    TO, PO = np.meshgrid(to, po, indexing="ij")
    wo = np.stack([np.sin(TO) * np.cos(PO), np.sin(TO) * np.sin(PO), np.cos(TO)], -1).reshape(-1, 3)
    wi = np.broadcast_to(np.array([np.sin(t), 0.0, np.cos(t)]), wo.shape)
    f = np.asarray(brdf.eval(wi, wo), dtype=np.float64).reshape(wo.shape[0], -1)
    dw = np.sin(TO).ravel() * (da / n_nodes) * (dp / np.sin(t) / n_nodes)
    flux = np.sum(f * (wo[:, 2] * dw)[:, None], axis=0)
    return 100.0 * flux / _fresnel_dielectric(np.cos(t), n_standard)


def information_criterion(
    r: FitResult, criterion: str = "bic", m_eff: float | None = None
) -> float:
    """AIC or BIC of a fit result, optionally with an effective sample count ``m_eff``.

    With ``m_eff`` the log-likelihood is rescaled by ``m_eff / m`` (each effective sample
    carries ``m / m_eff`` correlated residuals) and the BIC penalty uses ``ln m_eff``.
    """
    if criterion not in ("bic", "aic"):
        raise UnknownNameError(f"unknown criterion {criterion!r}; expected 'bic' or 'aic'")
    m = r.diagnostics["n_residuals"]
    p = r.n_params - len(r.diagnostics["at_bounds"])
    if r.diagnostics["absolute_sigma"]:
        m2ll = 2.0 * r.cost
    else:
        m2ll = m * np.log(max(2.0 * r.cost / m, 1e-300))
    me = float(m if m_eff is None else min(m_eff, m))
    m2ll *= me / m
    return float(m2ll + (p * np.log(me) if criterion == "bic" else 2.0 * p))


def _simplest_of_the_best(ok: list[tuple[float, int]], rows: list[dict[str, Any]]) -> int:
    """Index of the best criterion; among candidates that tie with it, the fewest parameters.

    A nested model whose extra parameter sits at its bound is the simpler model (Schlick
    with ``f0 = 1`` is ``F = 1``): its cost equals the simpler fit's to rounding and the
    bound parameter is not counted, so the criteria tie and their last bits would decide.
    Criteria within ``1e-9`` relative of the best are a tie; the candidate with the fewest
    nominal parameters wins, then the earlier one in the candidate list.
    """
    best = min(ic for ic, _ in ok)
    tol = 1e-9 * max(1.0, abs(best))
    tied = [i for ic, i in ok if ic <= best + tol]
    return min(tied, key=lambda i: (rows[i]["n_params"], i))


def select_model(
    samples: Any,
    candidates: tuple[str, ...] | None = None,
    criterion: str = "bic",
    effective_samples: float | None = None,
    min_gloss: float = MIN_GLOSS,
    progress: Callable[[str], None] | None = None,
    **fit_kwargs: Any,
) -> FitResult:
    """Fit ``candidates`` and return the best by ``criterion``.

    Parameters
    ----------
    samples
        BRDF samples (see :func:`gonio.fitting.fit`).
    candidates
        Model specs (default :data:`DEFAULT_CANDIDATES`): names, or names with options,
        ``"lambert+ggx[fresnel=schlick]"`` (see :data:`FRESNEL_CANDIDATES`).
    criterion
        ``"bic"`` (default) or ``"aic"``.
    effective_samples
        Number of independent samples for the criterion (see the module notes); default
        ``samples.attrs["effective_samples"]`` when present, else the number of residuals.
    min_gloss
        Gloss (GU at 60 deg) a specular model needs to be chosen over the diffuse ones.
    progress
        Called with the candidate name before each fit.
    **fit_kwargs
        Passed to :func:`gonio.fitting.fit.fit_model` (loss, algorithm, ...).

    Returns
    -------
    FitResult
        The chosen fit; ``diagnostics["selection"]`` lists every candidate with its
        criterion, cost and success, and ``diagnostics["criterion"]`` names the criterion.
    """
    from gonio.fitting.fit import fit_model

    cands = tuple(candidates or DEFAULT_CANDIDATES)
    if not cands:
        raise FitError("model='auto' needs at least one candidate model")
    if effective_samples is None:
        attrs = getattr(samples, "attrs", None) or {}
        if "effective_samples" in attrs:
            effective_samples = float(attrs["effective_samples"])
    fit_kwargs.pop("x0", None)
    rows: list[dict[str, Any]] = []
    results: list[FitResult] = []
    errors: list[str] = []
    for name in cands:
        if progress:
            progress(f"fitting {name}")
        try:
            r = fit_model(samples, name, **fit_kwargs)
        except FitError as exc:
            errors.append(f"{name}: {exc}")
            rows.append(
                {
                    "model": name,
                    "criterion": None,
                    "cost": None,
                    "success": False,
                    "error": str(exc),
                }
            )
            continue
        name = format_model_spec(r.model, r.model_options)
        m_eff = None
        if effective_samples is not None:
            m_eff = effective_samples * len(r.channels)
        ic = information_criterion(r, criterion, m_eff)
        rows.append(
            {
                "model": name,
                "criterion": ic,
                "cost": r.cost,
                "success": r.success,
                "n_params": r.n_params,
                "at_bounds": list(r.diagnostics["at_bounds"]),
            }
        )
        results.append(r)
    ok = [
        (row["criterion"], i)
        for i, row in enumerate(rows)
        if row["success"] and row["criterion"] is not None
    ]
    if not ok:
        raise FitError("model='auto': no candidate could be fitted: " + "; ".join(errors))
    by_name = {format_model_spec(r.model, r.model_options): r for r in results}
    for row in rows:
        r = by_name.get(row["model"])
        if r is not None and row["model"] not in DIFFUSE_MODELS:
            row["gloss_60"] = float(np.mean(gloss_units(r.bind())))
    best_row = _simplest_of_the_best(ok, rows)
    note = ""
    gloss = rows[best_row].get("gloss_60")
    if gloss is not None and gloss < min_gloss:
        # The matte rule is a prior for dense measured data, where BIC finds any extra
        # lobe significant (paper and wall paint: the diffuse cost is 1.6-2.1 times the
        # best).  It must not override a diffuse model that plainly cannot describe the
        # data (a low-gloss but strong lobe: thousands of times the cost).
        best_cost = rows[best_row]["cost"]
        diffuse = [
            (ic, i)
            for ic, i in ok
            if rows[i]["model"] in DIFFUSE_MODELS
            and rows[i]["cost"] <= MAX_DIFFUSE_COST_RATIO * best_cost
        ]
        if diffuse:
            note = (
                f"{rows[best_row]['model']} fits better but its lobe is matte "
                f"({gloss:.2f} GU < {min_gloss:g} GU at 60 deg): diffuse chosen"
            )
            best_row = min(diffuse)[1]
    chosen = by_name[rows[best_row]["model"]]
    chosen.diagnostics["criterion"] = criterion
    chosen.diagnostics["selection_note"] = note
    chosen.diagnostics["selection"] = rows
    chosen.algorithm = [f"auto:{criterion}({len(cands)})", *chosen.algorithm]
    return chosen
