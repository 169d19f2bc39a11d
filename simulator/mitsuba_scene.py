"""Translate a gonio :class:`~gonio.simulator.scene.Scene` into a Mitsuba 3 scene.

Mitsuba is the independent oracle for the renderer (tests and
``benchmarks/render_vs_mitsuba.py``): the same camera (perspective, box pixel filter),
film, sample rectangle, BRDF (``diffuse``, ``roughconductor`` GGX, ``measured``), lights
(``point``; ``area`` emitters on ``disk`` / ``rectangle`` shapes) and occluders (``cube``,
``cylinder`` with ``disk`` caps), rendered with the ``direct`` integrator.

Supported sample BRDFs: ``lambert`` (albedo), ``ggx`` (ks = 1, no Fresnel: Mitsuba's
``roughconductor`` with its default F = 1), and measured RGL files.  The holder is
supported only as a plain Lambertian plate (no board print or patch).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gonio.simulator.lights import prepare_lights
from gonio.simulator.scene import BoxOccluder, Scene

__all__ = ["to_mitsuba_dict"]


def _m4(mi, cols_xyz_t: np.ndarray) -> Any:
    return mi.ScalarTransform4f(np.asarray(cols_xyz_t, float).tolist())


def _frame(mi, e1, e2, n, c) -> Any:
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = e1, e2, n, c
    return _m4(mi, m)


def _bsdf(scene: Scene) -> dict:
    if scene.sample.spatially_varying:
        raise ValueError("no Mitsuba equivalent here for a sample with maps or a mix")
    spec = scene.sample.brdf
    if spec.file is not None:
        return {"type": "measured", "filename": str(scene.resolve(spec.file))}
    p = {k: np.broadcast_to(np.asarray(v, float), (3,)) for k, v in spec.params.items()}
    if spec.model == "lambert":
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": p["albedo"].tolist()}}
    if spec.model == "ggx" and spec.options.get("fresnel", "none") == "none":
        if not np.allclose(p.get("ks", 1.0), 1.0) or np.ptp(p["alpha"]) > 0:
            raise ValueError("Mitsuba's roughconductor needs ks = 1 and a scalar alpha")
        return {"type": "roughconductor", "distribution": "ggx", "alpha": float(p["alpha"][0])}
    raise ValueError(f"no Mitsuba equivalent for model {spec.model!r} {spec.options}")


def to_mitsuba_dict(scene: Scene, mi: Any, spp: int, seed: int = 0) -> dict:
    """A ``mi.load_dict`` scene dictionary equivalent to ``scene``.

    Parameters
    ----------
    scene
        The gonio scene.
    mi
        The ``mitsuba`` module with a variant set (``gonio.mitsuba_oracle.load_mitsuba``).
    spp, seed
        Samples per pixel and sampler seed (use distinct seeds for independent renders).
    """
    C, R = scene.camera_pose()
    K = scene.camera.intrinsics()
    W, H = scene.camera.resolution
    if not np.allclose([K[0, 2], K[1, 2]], [W / 2, H / 2]):
        raise ValueError("only a centred principal point is supported")
    if scene.camera.has_distortion:
        raise ValueError("only a pinhole camera is supported (camera.distortion is set)")
    if scene.sample.mirror_reflectance is not None:
        raise ValueError("the mirror target is not supported")
    fov = np.degrees(2 * np.arctan(W / 2 / K[0, 0]))
    d: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "direct", "hide_emitters": True},
        "sensor": {
            "type": "perspective",
            "fov": float(fov),
            "fov_axis": "x",
            "near_clip": 1e-3,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=C.tolist(), target=(C + R[2]).tolist(), up=(-R[1]).tolist()
            ),
            "film": {
                "type": "hdrfilm",
                "width": W,
                "height": H,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
                "component_format": "float32",
            },
            "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
        },
        "sample": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().scale(
                [scene.sample.width / 2, scene.sample.height / 2, 1.0]
            ),
            "bsdf": _bsdf(scene),
        },
    }
    h = scene.holder
    if h is not None:
        if h.board is not None or h.reference_patch is not None:
            raise ValueError("only a plain holder (no board, no patch) is supported")
        # Four strips around the sample, so the holder does not overlap it.
        sw, sh = scene.sample.width / 2, scene.sample.height / 2
        hw, hh = h.width / 2, h.height / 2
        alb = np.broadcast_to(np.asarray(h.albedo_white, float), (3,)).tolist()
        strips = [
            ((-hw, sh), (hw, hh)),
            ((-hw, -hh), (hw, -sh)),
            ((-hw, -sh), (-sw, sh)),
            ((sw, -sh), (hw, sh)),
        ]
        for i, ((x0, y0), (x1, y1)) in enumerate(strips):
            d[f"holder_{i}"] = {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f().translate([(x0 + x1) / 2, (y0 + y1) / 2, 0])
                @ mi.ScalarTransform4f().scale([(x1 - x0) / 2, (y1 - y0) / 2, 1]),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": alb}},
            }
    for i, light in enumerate(prepare_lights(scene)):
        rgb = {"type": "rgb", "value": light.rgb.tolist()}
        if light.is_point:
            d[f"light_{i}"] = {"type": "point", "position": light.center.tolist(), "intensity": rgb}
            continue
        s1, s2 = light.size if light.kind == "disk" else np.divide(light.size, 2)
        d[f"light_{i}"] = {
            "type": light.kind,
            "to_world": _frame(mi, light.e1 * s1, light.e2 * s2, light.normal, light.center),
            "emitter": {"type": "area", "radiance": rgb},
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}},
        }
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}}
    for i, occ in enumerate(scene.occluders):
        if isinstance(occ, BoxOccluder):
            rot = occ.rotation()
            half = np.asarray(occ.size) / 2
            d[f"occ_{i}"] = {
                "type": "cube",
                "bsdf": black,
                "to_world": _frame(
                    mi, rot[:, 0] * half[0], rot[:, 1] * half[1], rot[:, 2] * half[2], occ.center
                ),
            }
        else:
            d[f"occ_{i}"] = {
                "type": "cylinder",
                "p0": list(occ.start),
                "p1": list(occ.end),
                "radius": occ.radius,
                "bsdf": black,
            }
            for j, (p, q) in enumerate(((occ.start, occ.end), (occ.end, occ.start))):
                n = np.subtract(p, q)
                n = n / np.linalg.norm(n)
                helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
                e1 = np.cross(helper, n)
                e1 /= np.linalg.norm(e1)
                e2 = np.cross(n, e1)
                d[f"occ_{i}_cap{j}"] = {
                    "type": "disk",
                    "bsdf": black,
                    "to_world": _frame(mi, e1 * occ.radius, e2 * occ.radius, n, p),
                }
    return d
