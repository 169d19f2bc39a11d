"""gonio.fitting: objectives, the nlopt driver, uncertainty, model selection, exports.

>>> from gonio.fitting import fit
>>> r = fit(samples, "lambert+ggx")       # or model="auto"
>>> r.params["alpha"], r.std["alpha"], r.success
"""

from __future__ import annotations

from gonio.fitting.fit import fit, fit_model
from gonio.fitting.result import FitResult

__all__ = ["FitResult", "fit", "fit_model"]
