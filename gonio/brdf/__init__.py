"""BRDF models: analytic lobes by name, and measured BRDF files.

>>> from gonio.brdf import get_model, list_models, load
>>> m = get_model("lambert+ggx")
>>> f = m.eval(wi, wo, {"albedo": 0.5, "ks": 0.04, "alpha": 0.2})   # 1/sr

See DEVELOPING.md for the contract every model and measured file follows.
"""

from __future__ import annotations

from typing import Any


def __getattr__(name: str) -> Any:
    # Lazy so that `import gonio.brdf` stays cheap and the model and measured-file modules
    # can be developed independently.
    if name in ("get_model", "list_models"):
        from gonio.brdf import registry

        return getattr(registry, name)
    if name == "load":
        from gonio.brdf.measured import load

        return load
    raise AttributeError(f"module 'gonio.brdf' has no attribute {name!r}")


__all__ = ["get_model", "list_models", "load"]
