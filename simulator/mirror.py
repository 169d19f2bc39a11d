"""The flat first-surface mirror target: what the camera sees of the lights in it.

The rig calibration puts a mirror in the sample's place (flush with the holder, in the
plane z = 0) to measure the light's direction: the camera sees the light's image, a
bright spot.  A camera ray that meets the mirror at x continues along its reflection
about +z; the pixel's radiance is ``reflectance * L_e`` of the area light that the
reflected ray hits on its emitting side (unless an occluder is in the way), else 0.
Point lights have no area and cannot be seen in a mirror.  The light's emission profile
and face gradient shape the spot's brightness (not its outline).

By the law of reflection the spot is exactly the camera's image of the *mirrored* light
(the light reflected through z = 0), so the projection of the mirrored light centre
``(Lx, Ly, -Lz)`` is the spot's centre up to the perspective bias of a projected disk.
"""

from __future__ import annotations

import numpy as np

from gonio.simulator.geometry import PreparedOccluder, segments_blocked
from gonio.simulator.lights import PreparedLight

__all__ = ["light_hits", "mirror_radiance"]


def light_hits(
    light: PreparedLight,
    occluders: list[PreparedOccluder],
    camera: np.ndarray,
    x: np.ndarray,
) -> np.ndarray:
    """Whether the camera ray to each mirror point, reflected there, reaches the light.

    Parameters
    ----------
    light
        The light (a point light is never hit).
    occluders
        Occluders that may stand between the mirror and this light.
    camera
        Camera centre (3,), sample frame, m.
    x
        (M, 3) points on the mirror (z = 0), sample frame, m.

    Returns
    -------
    (M,) bool
    """
    return _hits(light, occluders, camera, x)[0]


def _hits(
    light: PreparedLight,
    occluders: list[PreparedOccluder],
    camera: np.ndarray,
    x: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(hit (M,), the reflected rays' points on the emitter (M, 3), their unnormalised
    directions (M, 3))."""
    m = x.shape[0]
    if light.is_point or m == 0:
        return np.zeros(m, bool), np.zeros((m, 3)), np.zeros((m, 3))
    d = (x - camera) * np.array([1.0, 1.0, -1.0])  # reflected about the mirror's +z normal
    denom = d @ light.normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((light.center - x) @ light.normal) / denom
    # one-sided emitter: the reflected ray must arrive against its emitting normal
    ok = (denom < 0) & np.isfinite(t) & (t > 0)
    p = x + np.where(ok, t, 0.0)[:, None] * d
    rel = p - light.center
    a, b = rel @ light.e1, rel @ light.e2
    if light.kind == "disk":
        inside = a * a + b * b <= light.size[0] ** 2
    else:
        inside = (np.abs(a) <= light.size[0] / 2) & (np.abs(b) <= light.size[1] / 2)
    hit = ok & inside
    if occluders and hit.any():
        idx = np.flatnonzero(hit)
        hit[idx] = ~segments_blocked(occluders, x[idx], p[idx])
    return hit, p, d


def mirror_radiance(
    lights: list[PreparedLight],
    light_occluders: list[list[PreparedOccluder]],
    camera: np.ndarray,
    x: np.ndarray,
    reflectance: float,
) -> np.ndarray:
    """Radiance (M, 3) towards the camera of mirror points x (M, 3), W/(sr m^2).

    ``reflectance * L_e`` summed over the area lights the reflected rays hit (lights do
    not overlap in a gonio scene; where they would, both count); ``L_e`` is the light's
    radiance towards the mirror point: its ``cos^n`` profile at the reflected ray's angle
    off the light's normal and its face gradient where the ray meets it.
    """
    out = np.zeros((x.shape[0], 3))
    for light, occ in zip(lights, light_occluders, strict=True):
        hit, p, d = _hits(light, occ, camera, x)
        if light.profile_n == 0.0 and light.gradient == 0.0:
            out[hit] += reflectance * light.rgb
            continue
        factor = np.ones(int(hit.sum()))
        dh = d[hit]
        prof = light.profile(-(dh @ light.normal) / np.linalg.norm(dh, axis=-1))
        if prof is not None:
            factor = factor * prof
        face = light.face(p[hit])
        if face is not None:
            factor = factor * face
        out[hit] += reflectance * factor[:, None] * light.rgb
    return out
