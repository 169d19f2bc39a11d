"""The one result object every fit returns, whatever model, loss or algorithm ran.

Modelled on :class:`scipy.optimize.OptimizeResult`: a fixed set of documented fields, so
callers (the CLI, exports, plots, model selection) never need to know which path ran.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from gonio.brdf.base import BoundModel

__all__ = ["FitResult"]


@dataclass
class FitResult:
    """Outcome of :func:`gonio.fitting.fit`.

    Attributes
    ----------
    model : str
        Model name as understood by :func:`gonio.brdf.get_model` (e.g. ``"lambert+ggx"``).
    model_options : dict
        Keyword options the model was built with (e.g. ``{"fresnel": "schlick"}``).
    channels : tuple of str
        Colour channels, e.g. ``("R", "G", "B")``.
    params : dict of str -> ndarray, shape (C,)
        Fitted parameters per channel.  Shape parameters (roughness, exponents) are shared
        by all channels and repeated; linear parameters (albedo, ks) are per channel.
    std : dict of str -> ndarray, shape (C,)
        One-sigma standard deviations of ``params`` from the linearised covariance.  A
        parameter held at a bound has std 0 (it is listed in ``diagnostics["at_bounds"]``);
        an unidentifiable one has std ``inf``.
    covariance : ndarray, shape (P, P)
        Covariance of the free parameter vector, labelled by ``param_labels``.
    param_labels : tuple of str
        Labels of the covariance rows: shape parameter names, then ``"albedo[R]"`` and so on.
    shape_params, linear_params : tuple of str
        Which parameters are shared (searched nonlinearly) and which are per channel
        (solved by non-negative least squares inside the search).
    loss : str
        Loss that was minimised (``"weighted_l2"``, ``"cosine_l2"``, ``"l2"``, ``"log"``).
    robust : str or None
        Robust penalty applied to the residuals (``"soft_l1"``, ``"huber"``, ``"cauchy"``).
    cost : float
        Final value of the objective, ``0.5 * sum(rho(r**2))`` over samples and channels.
    residuals : ndarray, shape (N, C)
        Loss residuals at the optimum for the samples used (NaN where a sample was not used).
    used : ndarray of bool, shape (N,)
        Which input samples entered the fit.
    n_samples : int
        Number of samples used (``used.sum()``).
    n_params : int
        Number of free fitted parameters (shape + linear x channels).
    nfev, njev : int
        Evaluations of the model with and without gradients over all stages.
    algorithm : list of str
        The stages that ran, in order, e.g. ``["sobol(16)", "LD_LBFGS x2", "SLSQP(energy)"]``.
    status : int
        nlopt return code of the last nlopt stage (1..6 success, <0 failure; 0 if none ran).
    message : str
        Human-readable outcome.
    success : bool
        True when the optimiser converged and all parameters and the cost are finite.
    diagnostics : dict
        ``condition_number`` (of the scaled Jacobian), ``at_bounds`` (parameter labels at a
        bound), ``max_albedo`` (per channel, over theta_i), ``aic``, ``bic``,
        ``dropped`` (counts of samples left out and why), ``sigma_scale`` (residual
        standard deviation used to scale the covariance, 1 for known sigmas) and more.
        When the samples carry geometric modes (correlated direction errors, see
        :mod:`gonio.fitting.geometric_uncertainty`): ``variance_split`` (``labels`` as
        ``param_labels``; ``noise``, ``geometry``, ``calibration``: each parameter's
        variance by source, natural units, adding up to ``std**2``) and
        ``geometry_modes`` (mode names, session/pose counts, covariance columns).  With a
        shared calibration scale: ``calibration_rel_std`` (C,).
    """

    model: str
    model_options: dict[str, Any]
    channels: tuple[str, ...]
    params: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    covariance: np.ndarray
    param_labels: tuple[str, ...]
    shape_params: tuple[str, ...]
    linear_params: tuple[str, ...]
    loss: str
    robust: str | None
    cost: float
    residuals: np.ndarray
    used: np.ndarray
    n_samples: int
    n_params: int
    nfev: int
    njev: int
    algorithm: list[str]
    status: int
    message: str
    success: bool
    diagnostics: dict[str, Any] = field(default_factory=dict)

    @property
    def spec(self) -> str:
        """The model as ``--model`` spells it, options included
        (``lambert+ggx[fresnel=schlick]``)."""
        from gonio.brdf.registry import format_model_spec

        return format_model_spec(self.model, self.model_options)

    def params_for_channel(self, c: int | str) -> dict[str, float]:
        """Parameters of one channel (index or name) as plain floats."""
        i = self.channels.index(c) if isinstance(c, str) else int(c)
        return {k: float(v[i]) for k, v in self.params.items()}

    def bind(self) -> BoundModel:
        """The fitted model bound to its per-channel parameters.

        Returns a :class:`gonio.brdf.base.BoundModel` with ``eval(wi, wo) -> (..., C)``
        (1/sr) and ``albedo(theta_i) -> (..., C)`` for the fit's C channels (the same
        interface as a bound model or a measured file).
        """
        from gonio.brdf import get_model

        m = get_model(self.model, **self.model_options)
        return m.bind(self.params, channels=len(self.channels))

    def summary(self) -> str:
        """A short multi-line text summary (parameters +- std per channel, cost, status)."""
        lines = [
            f"model {self.model} ({self.loss}{'/' + self.robust if self.robust else ''}): "
            f"{'success' if self.success else 'FAILED'} - {self.message}",
            f"cost {self.cost:.6g} over {self.n_samples} samples x {len(self.channels)} "
            f"channels, {self.n_params} parameters, nfev {self.nfev}, "
            f"path {' -> '.join(self.algorithm)}",
        ]
        for name, v in self.params.items():
            s = self.std[name]
            vals = ", ".join(
                f"{c}={x:.6g}+-{e:.2g}" for c, x, e in zip(self.channels, v, s, strict=True)
            )
            lines.append(f"  {name}: {vals}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (arrays as lists, NaN/inf as None/strings)."""
        from gonio.fitting.export import result_to_dict

        return result_to_dict(self)
