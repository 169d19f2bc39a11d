"""The advisor of an adaptive session: reduce the new poses, fit, choose the next batch.

Capture may not import fitting, so the composition root wires them:
:class:`FitAdvisor` implements :class:`gonio.capture.adaptive.Advisor` with the
session's :class:`gonio.capture.reduce.IncrementalReduction`, a fit of every candidate
model of the plan (:func:`gonio.fitting.fit`, their BIC giving the model weights, the
lowest BIC the winner, as ``gonio fit --model auto`` ranks them) and the design
criterion of :mod:`gonio.fitting.design` (``score_candidates``, ``choose_batch``,
``stopping``).  While that module is absent, a placeholder stands behind the same call:
the batch is the farthest-point choice in ``(wi, wo)`` from what was measured, and the
stop is the target relative sigma of the winning fit's parameters.  The placeholder's
choice depends on the poses taken alone, not on what was measured there.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from gonio.capture.adaptive import AdaptiveState, Decision
from gonio.capture.adaptive_pool import farthest_point, pool_features, read_pool
from gonio.capture.plan import Plan
from gonio.errors import GonioError

__all__ = ["FitAdvisor", "STOP_TARGET"]

STOP_TARGET = "target precision reached"
#: How many scored candidates a round's journal record lists.
TOP_SCORED = 20


def _design() -> Any:
    try:
        from gonio.fitting import design
    except ImportError:
        return None
    return design


def _rel_sigma(fit: Any) -> dict[str, float]:
    """Parameter -> relative 1-sigma (the largest over the channels)."""
    out = {}
    for name, v in fit.params.items():
        v = np.asarray(v, float)
        s = np.asarray(fit.std.get(name, np.full_like(v, np.nan)), float)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.abs(s / v)
        r = r[np.isfinite(r)] if np.isfinite(r).any() else np.array([math.inf])
        out[name] = float(np.max(r))
    return out


def _json_float(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _jsonable(x: Any) -> Any:
    """``x`` with numpy scalars and arrays made plain, non-finite floats None (journal)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.bool_ | bool):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, float | np.floating):
        return _json_float(float(x))
    return x


class FitAdvisor:
    """Implements :class:`gonio.capture.adaptive.Advisor` (see the module docstring).

    Parameters
    ----------
    plan
        The session's plan (its ``[adaptive]`` table: candidates, targets, weights).
    reduction_setup
        The reduction facts; None: the session's ``reduction.toml``, read at the first
        round (a simulated session writes it at creation).
    fit_options
        Passed to :func:`gonio.fitting.fit` for every candidate.
    """

    def __init__(
        self,
        plan: Plan,
        reduction_setup: Any = None,
        *,
        fit_options: dict[str, Any] | None = None,
    ) -> None:
        if plan.adaptive is None:
            raise GonioError(f"plan {plan.name!r} has no [adaptive] table")
        self.plan = plan
        self.setup = reduction_setup
        self.fit_options = dict(fit_options or {})
        self._reduction: Any = None
        self._pool: Any = None
        self._eval: Any = None
        self._misfit: dict[str, float] | None = None

    # -- the parts ---------------------------------------------------------------------
    def _samples(self, state: AdaptiveState) -> Any:
        from gonio.capture.reduce import IncrementalReduction

        if self._reduction is None:
            self._reduction = IncrementalReduction(state.session_dir, self.setup)
        return self._reduction.add(state.measured_steps)

    def _fits(self, samples: Any) -> tuple[list[Any], np.ndarray, list[dict[str, Any]], Any]:
        """Every candidate fitted by :func:`gonio.fitting.candidates.fit_candidates` (the
        fit ``benchmarks/adaptive.py`` measures: on a misfit the data show, the aligned
        fit ranked by its common criterion).  Returns the fits, their weights, the
        journal rows and the samples fitted (the aligned sigmas on a misfit)."""
        from gonio.fitting import model_error
        from gonio.fitting.candidates import fit_candidates
        from gonio.fitting.select import format_model_spec

        specs = list(self.plan.adaptive.candidates)  # type: ignore[union-attr]
        self._misfit = None
        try:
            cf = fit_candidates(samples, specs, fit_options=self.fit_options)
        except GonioError as exc:
            return [], np.zeros(0), [{"model": c, "error": str(exc)} for c in specs], samples
        self._misfit = cf.misfit
        rows: list[dict[str, Any]] = [{"model": c, "error": e} for c, e in cf.errors.items()]
        for r, score, w in zip(cf.fits, cf.scores, cf.weights, strict=True):
            rows.append(
                {
                    "model": format_model_spec(r.model, r.model_options),
                    "params": {k: np.asarray(v, float).tolist() for k, v in r.params.items()},
                    "rel_sigma": {k: _json_float(v) for k, v in _rel_sigma(r).items()},
                    "bic": float(score),
                    "criterion": cf.criterion,
                    "weight": float(w),
                }
            )
        if cf.is_misfit and cf.criterion == "aligned_bic" and self._misfit is not None:
            self._misfit["rel_scale"] = float(
                model_error.relative_model_error_scale(cf.best, cf.samples)
            )
        return cf.fits, cf.weights, rows, cf.samples

    def _stop(self, fits: list[Any], w: np.ndarray, design: Any) -> tuple[bool, dict[str, Any]]:
        a = self.plan.adaptive
        assert a is not None
        if not fits:
            return False, {"reached": False, "why": "no candidate could be fitted yet"}
        if design is not None:
            if self._eval is None:  # the fixed evaluation set of the predicted-f target
                self._eval = design.hemisphere_directions(a.max_theta_deg)
            ev_wi, ev_wo = self._eval
            reached, status = design.stopping(
                fits, w, dict(a.target_rel_sigma), a.target_brdf_rel_sigma, ev_wi, ev_wo
            )
            return bool(reached), _jsonable(status)
        best = fits[int(np.argmax(w))]
        rel = _rel_sigma(best)
        if not a.target_rel_sigma:
            why = "no target_rel_sigma (target_brdf_rel_sigma needs gonio.fitting.design)"
            return False, {"reached": False, "why": why}
        missing = [p for p in a.target_rel_sigma if p not in rel]
        reached = not missing and all(rel[p] <= t for p, t in a.target_rel_sigma.items())
        return reached, {
            "reached": reached,
            "rel_sigma": {p: _json_float(rel.get(p, math.inf)) for p in a.target_rel_sigma},
            "target_rel_sigma": dict(a.target_rel_sigma),
            "not_in_winner": missing,
        }

    def _choose(
        self, state: AdaptiveState, samples: Any, fits: list[Any], w: np.ndarray, design: Any
    ) -> tuple[list[int], dict[str, Any]]:
        a = self.plan.adaptive
        assert a is not None
        n = min(a.batch_poses, len(state.pool_ids))
        if design is not None and fits:
            # a misfit makes the model's parameter information beside the point: the
            # batch fills the pose space (what benchmarks/adaptive.py measures)
            misfit = bool(self._misfit and self._misfit["tau"] > 0.0)
            if misfit:
                idx = design.space_filling_batch(
                    state.pool_wi, state.pool_wo, *design.measured_directions(samples), n
                )
                why = (
                    "misfit: space-filling, farthest in pose distance from the measured "
                    "directions (no candidate follows the material)"
                )
                return [int(state.pool_ids[i]) for i in idx], {"scored": [], "why": why}
            ok = (samples.flags == 0) & np.all(np.isfinite(samples.brdf), axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                rel = samples.brdf_std[ok] / np.abs(samples.brdf[ok])
            rel = rel[np.isfinite(rel)]
            # a pose measures R regions about its direction: the design wants the
            # per-sample figure over sqrt(R)
            poses = getattr(samples, "pose", None)
            n_poses = len(np.unique(poses)) if poses is not None and len(poses) else 1
            per_pose = max(1.0, len(samples) / max(n_poses, 1))
            sample_rel = (float(np.median(rel)) if rel.size else 0.01) / math.sqrt(per_pose)
            weights = a.weights.model_dump()
            scores = design.score_candidates(
                fits,
                w,
                samples,
                state.pool_wi,
                state.pool_wo,
                sample_rel_std=sample_rel,
                weights=weights,
            )
            idx = design.choose_batch(
                scores, fits, state.pool_wi, state.pool_wo, n, min_separation_deg=a.separation_deg
            )
            top = np.argsort(-np.asarray(scores.total), kind="stable")[:TOP_SCORED]
            scored = [
                {
                    "id": int(state.pool_ids[i]),
                    "total": float(scores.total[i]),
                    "d_optimal": float(scores.d_optimal[i]),
                    "discrimination": float(scores.discrimination[i]),
                    "model_free": float(scores.model_free[i]),
                }
                for i in top
            ]
            why = (
                f"greedy by expected information (weights {weights}), "
                f"sample rel sigma {sample_rel:.3g}, min separation {a.separation_deg:g} deg"
            )
            return [int(state.pool_ids[i]) for i in idx], {"scored": scored, "why": why}
        # placeholder: farthest in (wi, wo) from every pose taken so far (the seed and
        # the earlier rounds), whatever was measured there
        if self._pool is None:
            self._pool = read_pool(state.session_dir)
        pool = self._pool
        allowed = np.zeros(len(pool), bool)
        allowed[state.pool_ids] = True
        taken = np.flatnonzero(~allowed).tolist()
        idx = farthest_point(pool_features(pool.wi, pool.wo), n, chosen=taken, allowed=allowed)
        why = "farthest-point in (wi, wo) from the poses taken (placeholder: no design)"
        return [int(i) for i in idx], {"scored": [], "why": why}

    # -- the protocol ------------------------------------------------------------------
    def advise(self, state: AdaptiveState) -> Decision:
        """Reduce the new poses, fit the candidates, stop or choose the next batch."""
        design = _design()
        t0 = time.perf_counter()
        record: dict[str, Any] = {}
        try:
            samples = self._samples(state)
        except GonioError as exc:  # nothing to fit yet (e.g. no pose could be reduced)
            samples, record["reduction_error"] = None, str(exc)
        t1 = time.perf_counter()
        self._misfit = None
        if samples is not None:
            fits, w, rows, samples = self._fits(samples)
        else:
            fits, w, rows = [], np.zeros(0), []
        t2 = time.perf_counter()
        reached, status = self._stop(fits, w, design)
        record.update(
            {"fits": rows, "stopping": status, "samples": 0 if samples is None else len(samples)}
        )
        if self._misfit is not None:
            record["misfit"] = self._misfit
        if fits:
            best = fits[int(np.argmax(w))]
            from gonio.fitting.select import format_model_spec

            rel = _rel_sigma(best)
            a = self.plan.adaptive
            # sigma ~ 1/sqrt(poses): what max_poses would give if the next poses were
            # worth the ones so far (a target far below it is not reachable in the budget)
            scale = math.sqrt(max(state.poses_done, 1) / a.max_poses)  # type: ignore[union-attr]
            record["fit"] = {
                "model": format_model_spec(best.model, best.model_options),
                "rel_sigma": {k: _json_float(v) for k, v in rel.items()},
                "forecast_at_max_poses": {k: _json_float(v * scale) for k, v in rel.items()},
            }
        if reached:
            record["why"] = "every target reached: " + str(status)
            record["timing"] = {"reduce_s": t1 - t0, "fit_s": t2 - t1}
            return Decision([], STOP_TARGET, _jsonable(record))
        chosen, extra = self._choose(state, samples, fits, w, design)
        record.update(extra)
        record["design"] = "gonio.fitting.design" if design is not None else "placeholder"
        record["timing"] = {
            "reduce_s": t1 - t0,
            "fit_s": t2 - t1,
            "choose_s": time.perf_counter() - t2,
        }
        return Decision(chosen, None, _jsonable(record))
