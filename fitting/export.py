"""Write fit results: JSON, and the fitted material for Mitsuba 3 (scene dict and XML).

Mitsuba 3 has no additive BSDF, only ``blendbsdf`` (``(1 - w) f_1 + w f_2``), so
``lambert + ggx`` with albedo ``rho`` and weight ``ks`` becomes a blend of ``diffuse``
(reflectance ``rho / (1 - w)``) and ``roughconductor`` (``material="none"``: Fresnel 1,
specular_reflectance ``ks / w``) with ``w`` chosen to keep both reflectances <= 1 where
possible.  Mitsuba's ``roughconductor`` uses the separable Smith shadowing of our
microfacet lobes; its Beckmann G1 is the rational approximation (``g1="rational"``).
Models without a Mitsuba 3 counterpart (Oren-Nayar, Phong, Ward, Fresnel-weighted lobes)
raise :class:`~gonio.errors.FitError`.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from gonio.atomic import write_text_atomic
from gonio.errors import FitError
from gonio.fitting.result import FitResult

__all__ = ["mitsuba_dict", "mitsuba_xml", "result_to_dict", "save_json", "save_mitsuba_xml"]


def _clean(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, np.ndarray):
        return _clean(v.tolist())
    if isinstance(v, (np.floating, float)):
        f = float(v)
        if math.isnan(f):
            return None
        if math.isinf(f):
            return "inf" if f > 0 else "-inf"
        return f
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v


def result_to_dict(r: FitResult, include_residuals: bool = False) -> dict[str, Any]:
    """JSON-ready dictionary of a :class:`FitResult` (NaN -> null, inf -> "inf").

    Residuals are left out unless ``include_residuals`` (they are per sample).
    """
    d: dict[str, Any] = {
        "schema": "gonio.fit",
        "schema_version": 1,
        "model": r.model,
        "model_options": r.model_options,
        "channels": list(r.channels),
        "params": r.params,
        "std": r.std,
        "param_labels": list(r.param_labels),
        "covariance": r.covariance,
        "shape_params": list(r.shape_params),
        "linear_params": list(r.linear_params),
        "loss": r.loss,
        "robust": r.robust,
        "cost": r.cost,
        "n_samples": r.n_samples,
        "n_params": r.n_params,
        "nfev": r.nfev,
        "njev": r.njev,
        "algorithm": list(r.algorithm),
        "status": r.status,
        "message": r.message,
        "success": r.success,
        "diagnostics": r.diagnostics,
    }
    if include_residuals:
        d["residuals"] = r.residuals
    return _clean(d)


def save_json(r: FitResult, path: str | os.PathLike, include_residuals: bool = False) -> Path:
    """Write :func:`result_to_dict` to ``path`` atomically (temp file + rename)."""
    path = Path(path)
    write_text_atomic(
        path, json.dumps(result_to_dict(r, include_residuals), indent=2), parents=True
    )
    return path


def _rgb(v: np.ndarray) -> dict[str, Any]:
    return {"type": "rgb", "value": [float(x) for x in np.broadcast_to(v, (3,))]}


def _specular(kind: str, alpha: float, ks: np.ndarray, options: dict[str, Any]) -> dict[str, Any]:
    fresnel = options.get("fresnel", "none")
    if fresnel != "none":
        raise FitError(
            f"Mitsuba export: {kind} with fresnel={fresnel!r} has no exact Mitsuba 3 "
            "counterpart (only fresnel='none' maps to roughconductor material='none')"
        )
    if kind == "beckmann" and options.get("g1", "exact") != "rational":
        raise FitError(
            "Mitsuba export: Mitsuba's Beckmann uses the rational G1; fit with "
            "model_options={'g1': 'rational'}"
        )
    return {
        "type": "roughconductor",
        "material": "none",
        "distribution": kind,
        "alpha": float(alpha),
        "specular_reflectance": _rgb(ks),
    }


def mitsuba_dict(r: FitResult) -> dict[str, Any]:
    """A Mitsuba 3 BSDF dictionary (for ``mi.load_dict``) equal to the fitted model.

    Supported: ``lambert``, ``ggx``, ``beckmann``, ``lambert+ggx``, ``lambert+beckmann``
    (microfacet lobes with ``fresnel="none"``), three channels.
    """
    if len(r.channels) != 3:
        raise FitError(f"Mitsuba export needs 3 colour channels, the fit has {len(r.channels)}")
    lobes = r.model.split("+")
    p = r.params
    if lobes == ["lambert"]:
        return {"type": "diffuse", "reflectance": _rgb(p["albedo"])}
    if len(lobes) == 1 and lobes[0] in ("ggx", "beckmann"):
        return _specular(lobes[0], p["alpha"][0], p["ks"], r.model_options)
    if len(lobes) == 2 and lobes[0] == "lambert" and lobes[1] in ("ggx", "beckmann"):
        rho = np.asarray(p["albedo"], dtype=np.float64)
        ks = np.asarray(p["ks"], dtype=np.float64)
        mr, mk = float(rho.max()), float(ks.max())
        if mk <= 0:
            return {"type": "diffuse", "reflectance": _rgb(rho)}
        if mr <= 0:
            return _specular(lobes[1], p["alpha"][0], ks, r.model_options)
        w = mk / (mk + mr)
        return {
            "type": "blendbsdf",
            "weight": w,
            "bsdf_0": {"type": "diffuse", "reflectance": _rgb(rho / (1.0 - w))},
            "bsdf_1": _specular(lobes[1], p["alpha"][0], ks / w, r.model_options),
        }
    raise FitError(
        f"Mitsuba export: model {r.model!r} has no Mitsuba 3 counterpart (supported: lambert, "
        "ggx, beckmann, lambert+ggx, lambert+beckmann)"
    )


def _xml(d: dict[str, Any], indent: str = "", name: str | None = None) -> list[str]:
    attrs = f' type="{d["type"]}"' + (f' name="{name}"' if name else "")
    out = [f"{indent}<bsdf{attrs}>"]
    for k, v in d.items():
        if k == "type":
            continue
        if isinstance(v, dict) and v.get("type") == "rgb":
            vals = ", ".join(f"{x:.9g}" for x in v["value"])
            out.append(f'{indent}    <rgb name="{k}" value="{vals}"/>')
        elif isinstance(v, dict):
            out.extend(_xml(v, indent + "    "))
        elif isinstance(v, str):
            out.append(f'{indent}    <string name="{k}" value="{v}"/>')
        else:
            out.append(f'{indent}    <float name="{k}" value="{float(v):.9g}"/>')
    out.append(f"{indent}</bsdf>")
    return out


def save_mitsuba_xml(r: FitResult, path: str | os.PathLike, bsdf_id: str = "fitted") -> Path:
    """Write :func:`mitsuba_xml` to ``path`` atomically (temp file + rename).

    Raises
    ------
    FitError
        The model has no Mitsuba equivalent (nothing is written).
    """
    path = Path(path)
    write_text_atomic(path, mitsuba_xml(r, bsdf_id), parents=True)
    return path


def mitsuba_xml(r: FitResult, bsdf_id: str = "fitted") -> str:
    """The fitted material as a Mitsuba 3 XML ``<bsdf>`` snippet (see :func:`mitsuba_dict`)."""
    d = mitsuba_dict(r)
    lines = _xml(d)
    lines[0] = lines[0].replace("<bsdf ", f'<bsdf id="{bsdf_id}" ', 1)
    return "\n".join(lines) + "\n"
