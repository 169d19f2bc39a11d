"""Renderer exports of fitted SVBRDF maps: Mitsuba 3 (bitmap textures) and MaterialX.

**Mitsuba 3** (``material.xml``): the mapping of :mod:`gonio.fitting.export` per texel.
``lambert + ggx`` (albedo ``rho``, weight ``ks``, roughness ``alpha``) is a ``blendbsdf``
of ``diffuse`` (reflectance ``rho / (1 - w)``) and ``roughconductor``
(``material="none"``: Fresnel 1, ``specular_reflectance = ks / w``, ``alpha``), with the
blend weight ``w = max(ks) / (max(ks) + max(rho))`` of each texel as a texture too; every
texture is a 16-bit PNG ``bitmap`` (``raw``: linear values, ``filter_type="nearest"``:
one constant value per texel, as the fit).  Texture coordinates: ``u = (x + w/2) / w``,
``v = (y + h/2) / h`` over the sample rectangle (sample frame, m), so a Mitsuba
``rectangle`` shape spanning the sample carries the maps the right way up (Mitsuba reads
a bitmap's row 0 at ``v = 0``, so the ``mitsuba_*.png`` are stored -y row first, unlike
the other maps; MaterialX images have ``v = 0`` at the bottom row, so the ``mtlx_*.png``
are stored +y row first, as the maps).  The export
is exact but for the 16-bit quantisation (and values above 1, clipped and counted).

**MaterialX** (``material.mtlx``, ``standard_surface``): standard_surface has no
Fresnel-free additive lobe, so the mapping is approximate:

* ``specular_roughness = sqrt(alpha)`` (standard_surface squares it), ``specular = 1``,
  ``specular_anisotropy = 0``;
* the GGX lobe becomes the dielectric specular layer: ``specular_IOR`` is chosen so its
  normal-incidence reflectance ``F0 = ((n - 1) / (n + 1))^2`` is the largest ``ks`` of
  the material, and ``specular_color = ks / F0`` (so the lobes agree at normal incidence
  of the microfacets, and the dielectric Fresnel term makes it rise towards grazing);
* the base layer (``base = 1``, ``diffuse_roughness = 0``: Lambert, ``metalness = 0``)
  is attenuated by the specular layer's directional albedo ``E(theta_o)``, so
  ``base_color = rho / (1 - E_mean)`` (clipped to 1), ``E_mean`` the cosine-weighted
  mean of ``E`` over the hemisphere.

The closed form compared against (:func:`standard_surface_eval`), from the
standard_surface specification's layering (Autodesk Standard Surface 1.0, "specular"
and "base": base scaled by ``1 - E``), is
``f = base_color / pi * (1 - E(theta_o)) + specular_color * F_d(o.h) D G2 / (4 cos_i
cos_o)``, with the exact dielectric Fresnel ``F_d``, GGX ``D`` and the height-correlated
Smith ``G2`` (MaterialX's ``mx_ggx_smith_G2``); ``E`` is integrated numerically here.
MaterialX's GLSL also adds a multiple-scattering energy compensation, not modelled.
:func:`mtlx_mapping_error` reports the relative RMSE of that closed form against the
fitted model over a grid of directions (the README states the figure).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from gonio.errors import FitError

__all__ = [
    "MITSUBA_TEXTURES",
    "MTLX_TEXTURES",
    "mitsuba_svbrdf_xml",
    "mitsuba_textures",
    "mtlx_document",
    "mtlx_mapping",
    "mtlx_mapping_error",
    "standard_surface_eval",
    "texel_uv",
]

#: File names of the Mitsuba textures (written beside material.xml).
MITSUBA_TEXTURES = {
    "weight": "mitsuba_weight.png",
    "diffuse": "mitsuba_diffuse.png",
    "specular": "mitsuba_specular.png",
    "alpha": "mitsuba_alpha.png",
}
#: File names of the MaterialX textures (written beside material.mtlx).
MTLX_TEXTURES = {
    "base_color": "mtlx_base_color.png",
    "specular_color": "mtlx_specular_color.png",
    "specular_roughness": "mtlx_specular_roughness.png",
}


def texel_uv(shape: tuple[int, int]) -> np.ndarray:
    """(ny, nx, 2) texture coordinates ``(u, v)`` of the texel centres (see module doc)."""
    ny, nx = shape
    u = (np.arange(nx) + 0.5) / nx
    v = 1.0 - (np.arange(ny) + 0.5) / ny  # row 0 at +y: v near 1
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv], axis=-1)


def _lobes(model: str, options: dict[str, Any]) -> tuple[bool, str | None]:
    lobes = model.split("+")
    diffuse = lobes[0] == "lambert"
    spec = lobes[-1] if lobes[-1] in ("ggx", "beckmann") else None
    rest = lobes[1:] if diffuse else lobes
    if (spec is None and rest) or len(rest) > 1 or (not diffuse and spec is None):
        raise FitError(
            f"Mitsuba export: model {model!r} has no Mitsuba 3 counterpart (supported: "
            "lambert, ggx, beckmann, lambert+ggx, lambert+beckmann)"
        )
    if spec is not None and options.get("fresnel", "none") != "none":
        raise FitError(
            f"Mitsuba export: {spec} with fresnel={options['fresnel']!r} has no exact "
            "Mitsuba 3 counterpart (only fresnel='none' maps to roughconductor material='none')"
        )
    if spec == "beckmann" and options.get("g1", "exact") != "rational":
        raise FitError(
            "Mitsuba export: Mitsuba's Beckmann uses the rational G1; fit with --option g1=rational"
        )
    return diffuse, spec


def mitsuba_textures(
    model: str, options: dict[str, Any], params: dict[str, np.ndarray]
) -> tuple[dict[str, np.ndarray], int]:
    """The Mitsuba textures of fitted maps, values in [0, 1].

    Parameters
    ----------
    model, options
        The fitted model's name and options.
    params
        name -> (ny, nx, C) maps; C must be 3.

    Returns
    -------
    (textures, clipped)
        key of :data:`MITSUBA_TEXTURES` -> (ny, nx, 3) or (ny, nx) array (NaN texels as
        0); ``clipped``: texel values above 1 that were clipped.

    Raises
    ------
    FitError
        The model has no Mitsuba 3 counterpart, or not 3 channels.
    """
    diffuse, spec = _lobes(model, options)
    first = next(iter(params.values()))
    if first.shape[-1] != 3:
        raise FitError(f"Mitsuba export needs 3 colour channels, the maps have {first.shape[-1]}")
    ny, nx = first.shape[:2]
    zero = np.zeros((ny, nx, 3))
    rho = np.nan_to_num(params["albedo"]) if diffuse else zero
    ks = np.nan_to_num(params["ks"]) if spec else zero
    mr, mk = rho.max(axis=-1), ks.max(axis=-1)
    tot = mr + mk
    w = np.divide(mk, tot, out=np.zeros_like(mk), where=tot > 0)
    tex = {
        "weight": w,
        "diffuse": np.divide(rho, (1.0 - w)[..., None], out=zero.copy(), where=(w < 1)[..., None]),
        "specular": np.divide(ks, w[..., None], out=zero.copy(), where=(w > 0)[..., None]),
        "alpha": np.nan_to_num(params["alpha"][..., 0], nan=0.5)
        if spec
        else np.full((ny, nx), 0.5),
    }
    clipped = 0
    for k, v in tex.items():
        clipped += int(np.count_nonzero(v > 1.0))
        tex[k] = np.clip(v, 0.0, 1.0)
    return tex, clipped


def _bitmap(name: str, filename: str, indent: str) -> list[str]:
    return [
        f'{indent}<texture type="bitmap" name="{name}">',
        f'{indent}    <string name="filename" value="{filename}"/>',
        f'{indent}    <boolean name="raw" value="true"/>',
        f'{indent}    <string name="filter_type" value="nearest"/>',
        f'{indent}    <string name="wrap_mode" value="clamp"/>',
        f"{indent}</texture>",
    ]


def mitsuba_svbrdf_xml(model: str, options: dict[str, Any], bsdf_id: str = "svbrdf") -> str:
    """The Mitsuba 3 XML of the textured BSDF (textures named as :data:`MITSUBA_TEXTURES`,
    relative to the XML file: load it with ``mi.load_file``).

    Raises
    ------
    FitError
        The model has no Mitsuba 3 counterpart.
    """
    diffuse, spec = _lobes(model, options)
    t = MITSUBA_TEXTURES
    dif = [
        '        <bsdf type="diffuse">',
        *_bitmap("reflectance", t["diffuse"], " " * 12),
        "        </bsdf>",
    ]
    rough = [
        '        <bsdf type="roughconductor">',
        '            <string name="material" value="none"/>',
        f'            <string name="distribution" value="{spec}"/>',
        *_bitmap("alpha", t["alpha"], " " * 12),
        *_bitmap("specular_reflectance", t["specular"], " " * 12),
        "        </bsdf>",
    ]
    head = f'<bsdf type="blendbsdf" id="{bsdf_id}" version="3.0.0">'
    if spec is None:
        body = [line[4:] for line in dif]
        head = f'<bsdf type="diffuse" id="{bsdf_id}" version="3.0.0">'
        body = body[1:-1]
    elif not diffuse:
        head = f'<bsdf type="roughconductor" id="{bsdf_id}" version="3.0.0">'
        body = [line[4:] for line in rough][1:-1]
    else:
        body = [*_bitmap("weight", t["weight"], " " * 4), *dif, *rough]
    comment = (
        "<!-- gonio SVBRDF export: textures in u = (x + w/2)/w, v = (y + h/2)/h over the "
        "sample rectangle -->"
    )
    return "\n".join([comment, head, *body, "</bsdf>"]) + "\n"


# --------------------------------------------------------------------------- MaterialX


def _fresnel_dielectric(c: np.ndarray, n: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a dielectric of index n (from air), cos c."""
    c = np.clip(c, 0.0, 1.0)
    g2 = n * n - 1.0 + c * c
    g = np.sqrt(np.maximum(g2, 0.0))
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


def _ggx_d(cos_h: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    a2 = alpha * alpha
    t = cos_h * cos_h * (a2 - 1.0) + 1.0
    return a2 / (math.pi * t * t)


def _g2_height_correlated(ci: np.ndarray, co: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    a2 = alpha * alpha
    li = np.sqrt(a2 + (1.0 - a2) * ci * ci)
    lo = np.sqrt(a2 + (1.0 - a2) * co * co)
    return 2.0 * ci * co / (li * co + lo * ci)


def _specular_albedo(cos_o: np.ndarray, alpha: np.ndarray, ior: float, n: int = 48) -> np.ndarray:
    """Directional albedo of the dielectric GGX layer (tint 1) at cos_o (broadcast with
    alpha), integrated over half vectors drawn by GGX's own distribution (a midpoint grid
    in its CDF: exact for the normalised D, accurate for any alpha)."""
    cos_o = np.asarray(cos_o, dtype=np.float64)[..., None, None]
    alpha = np.asarray(alpha, dtype=np.float64)[..., None, None]
    xi = (np.arange(n) + 0.5) / n
    phi = 2 * math.pi * (np.arange(2 * n) + 0.5) / (2 * n)
    th = np.arctan(alpha * np.sqrt(xi[:, None] / (1.0 - xi[:, None])))
    ch, sh = np.cos(th), np.sin(th)
    so = np.sqrt(np.maximum(1.0 - cos_o * cos_o, 0.0))
    # o in the xz plane; h = (sh cos phi, sh sin phi, ch)
    oh = so * sh * np.cos(phi) + cos_o * ch
    ci = 2.0 * oh * ch - cos_o
    ok = (oh > 0) & (ci > 0)
    ci_s = np.where(ok, ci, 1.0)
    g = _g2_height_correlated(ci_s, cos_o, alpha)
    val = np.where(ok, _fresnel_dielectric(oh, ior) * g * oh / (cos_o * ch), 0.0)
    return val.mean(axis=(-1, -2))


def mtlx_mapping(params: dict[str, np.ndarray]) -> dict[str, Any]:
    """standard_surface inputs of lambert+ggx maps (see the module doc).

    Parameters
    ----------
    params
        ``albedo``, ``ks``, ``alpha``: (ny, nx, C) maps.

    Returns
    -------
    dict
        ``base_color``, ``specular_color`` (ny, nx, C) and ``specular_roughness``
        (ny, nx) maps in [0, 1]; ``specular_IOR`` (float); ``f0``; ``clipped`` (count of
        base_color values above 1).
    """
    rho = np.nan_to_num(params["albedo"])
    ks = np.nan_to_num(params["ks"])
    alpha = np.nan_to_num(params["alpha"][..., 0], nan=0.5)
    f0 = float(np.clip(ks.max(), 1e-4, 0.999))
    s = math.sqrt(f0)
    ior = (1.0 + s) / (1.0 - s)
    # E_mean: cosine-weighted mean of E(theta_o): 2 * int E(mu) mu dmu (Gauss-Legendre)
    x, wq = np.polynomial.legendre.leggauss(12)
    mu = 0.5 * (x + 1.0)
    e = _specular_albedo(mu[None, None, :], alpha[..., None], ior)
    e_mean = np.sum(e * mu * wq * 0.5, axis=-1) * 2.0
    base = rho / (1.0 - e_mean)[..., None]
    return {
        "base_color": np.clip(base, 0.0, 1.0),
        "specular_color": np.clip(ks / f0, 0.0, 1.0),
        "specular_roughness": np.sqrt(np.clip(alpha, 0.0, 1.0)),
        "specular_IOR": ior,
        "f0": f0,
        "clipped": int(np.count_nonzero(base > 1.0)),
    }


def standard_surface_eval(
    wi: np.ndarray,
    wo: np.ndarray,
    base_color: np.ndarray,
    specular_color: np.ndarray,
    specular_roughness: np.ndarray,
    ior: float,
) -> np.ndarray:
    """The closed-form standard_surface BRDF of the mapping (1/sr, not times cos).

    Parameters
    ----------
    wi, wo
        (N, 3) unit directions (sample frame).
    base_color, specular_color
        (C,) colours of one texel.
    specular_roughness
        That texel's roughness (alpha = roughness^2).
    ior
        ``specular_IOR``.

    Returns
    -------
    (N, C) f_r; 0 where either direction is at or below the horizon.
    """
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    alpha = float(specular_roughness) ** 2
    ci, co = wi[:, 2], wo[:, 2]
    up = (ci > 0) & (co > 0)
    ci_s, co_s = np.where(up, ci, 1.0), np.where(up, co, 1.0)
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    oh = np.sum(wo * h, axis=1)
    spec = (
        _fresnel_dielectric(oh, ior)
        * _ggx_d(h[:, 2], np.float64(alpha))
        * _g2_height_correlated(ci_s, co_s, np.float64(alpha))
        / (4.0 * ci_s * co_s)
    )
    # E depends on theta_o only: once per distinct cos_o (a grid has few)
    cos_u, inv = np.unique(co_s, return_inverse=True)
    e = np.concatenate(
        [
            _specular_albedo(part, np.float64(alpha), ior)
            for part in np.array_split(cos_u, max(1, cos_u.size // 256))
        ]
    )[inv]
    f = (
        np.asarray(base_color)[None, :] / math.pi * (1.0 - e)[:, None]
        + spec[:, None] * np.asarray(specular_color)[None, :]
    )
    return np.where(up[:, None], f, 0.0)


def mtlx_mapping_error(
    params: dict[str, np.ndarray], mapping: dict[str, Any], max_texels: int = 16
) -> dict[str, float]:
    """Relative RMSE of the standard_surface closed form against the fitted model.

    Over a grid of directions (theta_i, theta_o in 5..80 deg, 8 x 8 x 12 azimuths),
    cosine-weighted (``f cos_i``, what a render sees), for up to ``max_texels`` texels
    spread over the map: ``sqrt(mean((f_mtlx - f)^2) / mean(f^2))`` per texel.

    Returns
    -------
    dict
        ``median``, ``max`` over the texels (dimensionless), ``texels`` compared.
    """
    from gonio.brdf import get_model

    m = get_model("lambert+ggx")
    th = np.radians(np.linspace(5.0, 80.0, 8))
    ph = np.radians(np.linspace(0.0, 180.0, 12))
    ti, to, po = np.meshgrid(th, th, ph, indexing="ij")
    wi = np.stack([np.sin(ti), np.zeros_like(ti), np.cos(ti)], -1).reshape(-1, 3)
    wo = np.stack([np.sin(to) * np.cos(po), np.sin(to) * np.sin(po), np.cos(to)], -1).reshape(-1, 3)
    ny, nx = params["albedo"].shape[:2]
    flat = np.unique(np.linspace(0, ny * nx - 1, min(max_texels, ny * nx)).round().astype(int))
    errs = []
    for t in flat:
        r, c = divmod(int(t), nx)
        p = {k: params[k][r, c] for k in ("albedo", "ks", "alpha")}
        if not all(np.all(np.isfinite(v)) for v in p.values()):
            continue
        f = m.bind({"albedo": p["albedo"], "ks": p["ks"], "alpha": p["alpha"][0]}).eval(wi, wo)
        g = standard_surface_eval(
            wi, wo, mapping["base_color"][r, c], mapping["specular_color"][r, c],
            mapping["specular_roughness"][r, c], mapping["specular_IOR"],
        )  # fmt: skip
        cw = wi[:, 2:3]
        errs.append(math.sqrt(np.mean(((g - f) * cw) ** 2) / np.mean((f * cw) ** 2)))
    if not errs:
        return {"median": float("nan"), "max": float("nan"), "texels": 0}
    return {"median": float(np.median(errs)), "max": float(np.max(errs)), "texels": len(errs)}


def mtlx_document(mapping: dict[str, Any], name: str = "gonio_svbrdf") -> str:
    """A MaterialX document (standard_surface with image textures of
    :data:`MTLX_TEXTURES`, relative to the .mtlx file), written with the ``MaterialX``
    package and validated by it.

    Raises
    ------
    FitError
        MaterialX finds the document invalid (the message gives its reason).
    """
    import MaterialX as mx

    doc = mx.createDocument()
    graph = doc.addNodeGraph(f"NG_{name}")
    outs = {}
    for key, kind in (
        ("base_color", "color3"),
        ("specular_color", "color3"),
        ("specular_roughness", "float"),
    ):
        img = graph.addNode("image", f"{key}_image", kind)
        img.setInputValue("file", MTLX_TEXTURES[key], "filename")
        # linear data: no colour-space transform
        img.getInput("file").setAttribute("colorspace", "raw")
        img.setInputValue("filtertype", "closest")
        img.setInputValue("uaddressmode", "clamp")
        img.setInputValue("vaddressmode", "clamp")
        out = graph.addOutput(f"{key}_out", kind)
        out.setConnectedNode(img)
        outs[key] = out
    shader = doc.addNode("standard_surface", f"SR_{name}", "surfaceshader")
    for key, out in outs.items():
        kind = "float" if key == "specular_roughness" else "color3"
        inp = shader.addInput(key, kind)
        inp.setNodeGraphString(graph.getName())
        inp.setOutputString(out.getName())
    shader.setInputValue("base", 1.0)
    shader.setInputValue("diffuse_roughness", 0.0)
    shader.setInputValue("metalness", 0.0)
    shader.setInputValue("specular", 1.0)
    shader.setInputValue("specular_IOR", float(mapping["specular_IOR"]))
    shader.setInputValue("specular_anisotropy", 0.0)
    mat = doc.addMaterialNode(name, shader)
    mat.setDocString("gonio SVBRDF export (lambert+ggx mapped to standard_surface)")
    ok, why = doc.validate()
    if not ok:
        raise FitError(f"MaterialX export: the document is not valid: {why}")
    return mx.writeToXmlString(doc)
