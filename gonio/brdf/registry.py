"""Analytic BRDF models by name.

>>> m = get_model("lambert+ggx", fresnel="schlick")
>>> m.param_names
('albedo', 'ks', 'alpha', 'f0')
>>> list_models()
['beckmann', 'blinn-phong', 'ggx', 'lambert', 'oren-nayar', 'phong', 'ward', 'ward-aniso']

Names join lobes with ``+``; options (keyword arguments) go to every lobe that accepts
them: ``fresnel`` (``none``, ``schlick``, ``conductor``, ``dielectric``) for ``ggx`` and
``beckmann``, ``g1`` (``exact``, ``rational``) for ``beckmann``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from gonio.brdf.base import Lobe, Model
from gonio.brdf.lobes import BlinnPhongLobe, LambertLobe, OrenNayarLobe, PhongLobe, WardLobe
from gonio.brdf.microfacet import BeckmannLobe, GGXLobe
from gonio.errors import ParameterError, UnknownNameError

__all__ = [
    "LOBES",
    "format_model_spec",
    "get_model",
    "list_models",
    "lobe_class",
    "parse_model_spec",
]

LOBES: dict[str, Callable[..., Lobe]] = {
    "lambert": LambertLobe,
    "oren-nayar": OrenNayarLobe,
    "phong": PhongLobe,
    "blinn-phong": BlinnPhongLobe,
    "ward": lambda **o: WardLobe(anisotropic=False, **o),
    "ward-aniso": lambda **o: WardLobe(anisotropic=True, **o),
    "ggx": GGXLobe,
    "beckmann": BeckmannLobe,
}

_OPTIONS: dict[str, dict[str, tuple[str, ...]]] = {
    "lambert": LambertLobe.option_choices,
    "oren-nayar": OrenNayarLobe.option_choices,
    "phong": PhongLobe.option_choices,
    "blinn-phong": BlinnPhongLobe.option_choices,
    "ward": WardLobe.option_choices,
    "ward-aniso": WardLobe.option_choices,
    "ggx": GGXLobe.option_choices,
    "beckmann": BeckmannLobe.option_choices,
}


def list_models() -> list[str]:
    """Names of the analytic lobes, sorted.  Any ``+``-joined sum of them is a model too."""
    return sorted(LOBES)


def lobe_class(name: str) -> Callable[..., Lobe]:
    """Constructor of the lobe called ``name`` (see :func:`list_models`)."""
    return LOBES[_canonical(name)]


def _canonical(part: str) -> str:
    key = part.strip().lower().replace("_", "-")
    if key not in LOBES:
        raise UnknownNameError(
            f"unknown BRDF model {part.strip()!r}; known models: {', '.join(list_models())} "
            "(sums are written with '+', e.g. 'lambert+ggx')"
        )
    return key


def get_model(name: str, **options: str) -> Model:
    """Build the analytic model ``name``: one lobe or a ``+``-joined sum of lobes.

    Parameters
    ----------
    name
        For example ``"ggx"``, ``"lambert+ggx"``, ``"lambert+ggx+ggx"`` (repeated parameter
        names get the lobe position as suffix: ``ks_2``, ``ks_3``).
    **options
        ``fresnel="none"|"schlick"|"conductor"|"dielectric"`` (microfacet lobes),
        ``g1="exact"|"rational"`` (Beckmann).  Each option goes to every lobe that takes it.

    Raises
    ------
    UnknownNameError
        Unknown lobe name or option value; the message lists the known ones.
    ParameterError
        An option that no lobe of the model accepts.
    """
    if not isinstance(name, str) or not name.strip():
        raise UnknownNameError(f"empty BRDF model name; known models: {', '.join(list_models())}")
    kinds = [_canonical(part) for part in name.split("+")]
    accepted: set[str] = set()
    for kind in kinds:
        accepted.update(_OPTIONS[kind])
    for key, value in options.items():
        if key not in accepted:
            known = ", ".join(sorted(accepted)) or "none"
            raise ParameterError(
                f"model '{'+'.join(kinds)}' takes no option {key!r}; its options: {known}"
            )
        choices = {c for kind in kinds for c in _OPTIONS[kind].get(key, ())}
        if value not in choices:
            raise UnknownNameError(
                f"unknown value {value!r} for option {key!r}; choices: {', '.join(sorted(choices))}"
            )
    lobes = []
    for kind in kinds:
        mine = {k: v for k, v in options.items() if k in _OPTIONS[kind]}
        lobes.append(LOBES[kind](**mine))
    return Model(lobes, options=dict(options))


def parse_model_spec(spec: str) -> tuple[str, dict[str, str]]:
    """Split a model spec ``"name[key=value,key=value]"`` into the name and its options.

    ``"lambert+ggx[fresnel=schlick]"`` -> ``("lambert+ggx", {"fresnel": "schlick"})``;
    a plain name has no options.  The name and values are checked later by
    :func:`get_model`.

    Raises
    ------
    UnknownNameError
        Unbalanced brackets or an option not written ``key=value``.
    """
    s = spec.strip()
    if "[" not in s and "]" not in s:
        return s, {}
    if not (s.endswith("]") and s.count("[") == 1 and s.count("]") == 1 and s.index("[") > 0):
        raise UnknownNameError(
            f"model spec {spec!r}: expected 'name' or 'name[key=value,...]', "
            "e.g. 'lambert+ggx[fresnel=schlick]'"
        )
    name, body = s[:-1].split("[", 1)
    opts: dict[str, str] = {}
    for item in filter(None, (x.strip() for x in body.split(","))):
        key, eq, value = item.partition("=")
        if not eq or not key.strip() or not value.strip():
            raise UnknownNameError(
                f"model spec {spec!r}: option {item!r} is not written key=value "
                "(e.g. fresnel=schlick)"
            )
        key, value = key.strip(), value.strip()
        if key in opts and opts[key] != value:
            raise UnknownNameError(
                f"model spec {spec!r}: option {key!r} given twice ({opts[key]}, {value})"
            )
        opts[key] = value
    return name.strip(), opts


def format_model_spec(name: str, options: dict[str, Any] | None) -> str:
    """Inverse of :func:`parse_model_spec`: ``name`` or ``name[key=value,...]``."""
    if not options:
        return name
    return f"{name}[{','.join(f'{k}={v}' for k, v in sorted(options.items()))}]"
