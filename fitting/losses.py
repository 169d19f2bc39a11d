"""Residual definitions (losses) and robust penalties for BRDF fitting.

A loss turns the model value ``f`` (1/sr) and the measurement ``y`` into a residual ``r``;
the objective is ``0.5 * sum(rho(r**2))`` with ``rho(z) = z`` unless a robust penalty is
chosen.  Losses whose residual is ``w * (f - y)`` with ``w`` independent of the model are
*linear*: for them variable projection solves the linear parameters exactly.

=============  ===========================================  ==========================
name           residual                                     use
=============  ===========================================  ==========================
weighted_l2    (f - y) / sigma                              measured data with sigmas
cosine_l2      (f - y) cos(theta_i)                         reflected radiance per
                                                            unit irradiance
l2             f - y                                        plain least squares
log            ln(1 + f cos theta_i) - ln(1 + y cos theta_i)  the log loss of the BRDF-
                                                            fitting literature (Low et
                                                            al. 2012, Ngan et al. 2005)
=============  ===========================================  ==========================

Robust penalties (the same definitions as :func:`scipy.optimize.least_squares`, with
``f_scale``): ``soft_l1``, ``huber``, ``cauchy``, ``arctan``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gonio.errors import UnknownNameError

__all__ = ["LOSSES", "ROBUST", "Loss", "get_loss", "robust_rho"]

LOSSES = ("weighted_l2", "cosine_l2", "l2", "log")
ROBUST = ("soft_l1", "huber", "cauchy", "arctan")


@dataclass(frozen=True)
class Loss:
    """A residual definition.

    Parameters
    ----------
    name
        One of :data:`LOSSES`.
    """

    name: str

    @property
    def linear(self) -> bool:
        """Residual is ``w * (f - y)``: variable projection is exact."""
        return self.name != "log"

    def weights(self, y: np.ndarray, sigma: np.ndarray | None, cos_i: np.ndarray) -> np.ndarray:
        """Residual weights ``w`` (N, C) of a linear loss."""
        if self.name == "weighted_l2":
            return 1.0 / sigma
        if self.name == "cosine_l2":
            return np.broadcast_to(cos_i[:, None], y.shape).copy()
        if self.name == "l2":
            return np.ones_like(y)
        raise ValueError(f"loss {self.name!r} is not linear")

    def residual(
        self, f: np.ndarray, y: np.ndarray, w: np.ndarray | None, cos_i: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Residual ``r`` and its derivative ``dr/df``, both (N, C).

        ``w`` are the weights of a linear loss (ignored by ``log``).
        """
        if self.linear:
            return w * (f - y), w
        c = cos_i[:, None]
        r = np.log1p(f * c) - np.log1p(y * c)
        return r, c / (1.0 + f * c)


def get_loss(name: str) -> Loss:
    """The loss called ``name``; :class:`~gonio.errors.UnknownNameError` if there is none."""
    if name not in LOSSES:
        raise UnknownNameError(f"unknown loss {name!r}; expected one of {', '.join(LOSSES)}")
    return Loss(name)


def robust_rho(
    z: np.ndarray, kind: str | None, f_scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Robust penalty ``rho(z)`` and ``rho'(z)`` of squared residuals ``z = r**2``.

    Scaled as in scipy: ``C**2 * rho0(z / C**2)`` with ``C = f_scale``, so the cost is
    ``0.5 * sum(rho)`` and small residuals are penalised like plain least squares.
    """
    if kind is None:
        return z, np.ones_like(z)
    if kind not in ROBUST:
        raise UnknownNameError(
            f"unknown robust penalty {kind!r}; expected one of {', '.join(ROBUST)} or None"
        )
    c2 = float(f_scale) ** 2
    u = z / c2
    if kind == "soft_l1":
        t = np.sqrt(1.0 + u)
        rho, d = 2.0 * (t - 1.0), 1.0 / t
    elif kind == "huber":
        small = u <= 1.0
        su = np.sqrt(np.where(small, 1.0, u))
        rho = np.where(small, u, 2.0 * su - 1.0)
        d = np.where(small, 1.0, 1.0 / su)
    elif kind == "cauchy":
        rho, d = np.log1p(u), 1.0 / (1.0 + u)
    else:  # arctan
        rho, d = np.arctan(u), 1.0 / (1.0 + u * u)
    return c2 * rho, d
