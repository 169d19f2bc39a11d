"""Ray and segment geometry for the renderer: camera rays, the sample plane, occluders.

Hand-written because the scene is tiny (one plane and a few boxes and cylinders) and the
work is millions of segment tests per image: a general ray tracer (Mitsuba, Embree) would
cost more in setup and data transfer than these closed-form vectorised tests.

Lens distortion (OpenCV Brown-Conrady) is inverted here with a vectorised Newton
iteration rather than ``cv2.undistortPoints``, whose fixed 5 fixed-point iterations leave
errors of 1e-6 and more in the frame's corners.  A fixed camera's pixel grid is the same
for every render, so its undistorted coordinates are cached (:func:`pixel_grid`).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from gonio.errors import ConfigError
from gonio.simulator.scene import BoxOccluder, CylinderOccluder

__all__ = [
    "PreparedOccluder",
    "camera_rays",
    "distort_normalized",
    "intersect_plane_z0",
    "pixel_grid",
    "prepare_occluders",
    "rays_from_normalized",
    "segments_blocked",
    "undistort_normalized",
]

_EPS = 1e-9
#: Newton stops when the distorted point is reproduced to this (normalised units).
_UNDISTORT_TOL = 1e-13
#: ... and must have reached this, or the distortion is not invertible there.
UNDISTORT_ACCURACY = 1e-10
_NEWTON_MAX = 50
_GRID_CACHE: OrderedDict[bytes, tuple[np.ndarray, np.ndarray]] = OrderedDict()
_GRID_CACHE_SIZE = 8

Distortion = Sequence[float] | np.ndarray | None


def _has(dist: Distortion) -> bool:
    return dist is not None and bool(np.any(np.asarray(dist, float) != 0.0))


def distort_normalized(
    x: np.ndarray, y: np.ndarray, dist: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV Brown-Conrady distortion of normalised image coordinates.

    Parameters
    ----------
    x, y
        Undistorted normalised coordinates ``X/Z``, ``Y/Z`` (dimensionless), any shape.
    dist
        ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    x_d, y_d
        Distorted normalised coordinates (dimensionless).
    """
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


def undistort_normalized(
    xd: np.ndarray, yd: np.ndarray, dist: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort_normalized` by Newton's method (vectorised).

    Parameters
    ----------
    xd, yd
        Distorted normalised coordinates (dimensionless), any matching shapes.
    dist
        ``(k1, k2, p1, p2, k3)``.

    Returns
    -------
    x, y
        Undistorted normalised coordinates whose distortion reproduces ``(xd, yd)`` to
        better than 1e-10 (typically 1e-16 after 3-5 steps).

    Raises
    ------
    ConfigError
        Where the iteration does not reach 1e-10: the distortion folds over (is not
        invertible) inside the frame; ``camera.distortion`` is named.
    """
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    xd = np.asarray(xd, float)
    yd = np.asarray(yd, float)
    x, y = xd.copy(), yd.copy()
    for _ in range(_NEWTON_MAX):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        # d radial / d r2
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        if np.all(np.abs(fx) + np.abs(fy) <= _UNDISTORT_TOL):
            break
        a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        c = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * c
        with np.errstate(divide="ignore", invalid="ignore"):
            x = x - (d * fx - b * fy) / det
            y = y - (a * fy - c * fx) / det
    xr, yr = distort_normalized(x, y, dist)
    err = np.hypot(xr - xd, yr - yd)
    bad = ~(err <= UNDISTORT_ACCURACY)
    if np.any(bad):
        i = np.flatnonzero(bad.ravel())[0]
        raise ConfigError(
            f"camera.distortion = {[k1, k2, p1, p2, k3]}: not invertible at the normalised "
            f"image point ({xd.ravel()[i]:.6g}, {yd.ravel()[i]:.6g}) (the lens model folds "
            "over inside the frame); expected a distortion that is monotonic over the image"
        )
    return x, y


def _normalized(
    K: np.ndarray, u: np.ndarray, v: np.ndarray, dist: Distortion
) -> tuple[np.ndarray, np.ndarray]:
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    if _has(dist):
        x, y = undistort_normalized(x, y, dist)
    return x, y


def pixel_grid(
    K: np.ndarray, width: int, height: int, dist: Distortion, corners: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates of every pixel centre (or corner), cached.

    Parameters
    ----------
    K
        Camera matrix (3, 3); pixel centres at integer + 0.5.
    width, height
        Resolution, pixels.
    dist
        ``(k1, k2, p1, p2, k3)`` or None.
    corners
        The (H + 1, W + 1) pixel corners instead of the (H, W) centres.

    Returns
    -------
    x, y
        (H, W) or (H + 1, W + 1) arrays (dimensionless; read-only, shared by the cache).
    """
    dist_arr = np.zeros(5) if dist is None else np.asarray(dist, float)
    key = b"".join(
        [np.asarray(K, float).tobytes(), dist_arr.tobytes(), bytes([corners])]
        + [int(width).to_bytes(8, "little"), int(height).to_bytes(8, "little")]
    )
    hit = _GRID_CACHE.get(key)
    if hit is not None:
        _GRID_CACHE.move_to_end(key)
        return hit
    if corners:
        jj, ii = np.mgrid[0 : height + 1, 0 : width + 1]
        u, v = ii.astype(float), jj.astype(float)
    else:
        jj, ii = np.mgrid[0:height, 0:width]
        u, v = ii + 0.5, jj + 0.5
    x, y = _normalized(K, u, v, dist)
    x.flags.writeable = False
    y.flags.writeable = False
    _GRID_CACHE[key] = (x, y)
    while len(_GRID_CACHE) > _GRID_CACHE_SIZE:
        _GRID_CACHE.popitem(last=False)
    return x, y


def rays_from_normalized(R: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """World-frame unit rays of undistorted normalised coordinates (x, y).

    Parameters
    ----------
    R
        World-to-camera rotation (3, 3), OpenCV axes.
    x, y
        Normalised coordinates ``X/Z``, ``Y/Z`` (dimensionless), matching shapes.
    """
    d_cam = np.stack([x, y, np.ones_like(x)], axis=-1)
    d = d_cam @ R  # R^T d_cam, row-vector form
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def camera_rays(
    K: np.ndarray, R: np.ndarray, u: np.ndarray, v: np.ndarray, dist: Distortion = None
) -> np.ndarray:
    """World-frame unit ray directions through image points (u, v) in pixels.

    Parameters
    ----------
    K
        Camera matrix (3, 3); pixel centres at integer + 0.5.
    R
        World-to-camera rotation (3, 3), OpenCV axes.
    u, v
        Image coordinates (pixels), any matching shapes.
    dist
        OpenCV ``(k1, k2, p1, p2, k3)``, or None (pinhole): each image point's ray is
        the undistorted direction that the lens images there.
    """
    x, y = _normalized(K, u, v, dist)
    d_cam = np.stack([x, y, np.ones_like(x)], axis=-1)
    d = d_cam @ R  # R^T d_cam, row-vector form
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def intersect_plane_z0(origin: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Hit points of rays with the plane z = 0 and whether the hit is in front.

    Returns
    -------
    points (..., 3), hit (...) bool
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -origin[2] / d[..., 2]
    hit = np.isfinite(t) & (t > 0)
    t = np.where(hit, t, 0.0)
    return origin + t[..., None] * d, hit


class PreparedOccluder:
    """An occluder in the form the segment tests need, with its bounding box."""

    def __init__(self, occ: BoxOccluder | CylinderOccluder) -> None:
        self.kind = occ.type
        if isinstance(occ, BoxOccluder):
            self.center = np.asarray(occ.center, float)
            self.axes = occ.rotation()  # columns: box axes in world
            self.half = np.asarray(occ.size, float) / 2
            corners = np.array(
                [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float
            )
            pts = self.center + (corners * self.half) @ self.axes.T
            self.lo, self.hi = pts.min(0), pts.max(0)
        else:
            self.p0 = np.asarray(occ.start, float)
            p1 = np.asarray(occ.end, float)
            axis = p1 - self.p0
            self.length = float(np.linalg.norm(axis))
            self.axis = axis / self.length
            self.radius = float(occ.radius)
            self.lo = np.minimum(self.p0, p1) - self.radius
            self.hi = np.maximum(self.p0, p1) + self.radius

    def overlaps(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Whether the occluder's bounding box meets the box [lo, hi]."""
        return bool(np.all(self.lo <= hi) and np.all(self.hi >= lo))

    def blocks(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Whether the open segments p -> q (..., 3) pass through the occluder."""
        d = q - p
        if self.kind == "box":
            return _segment_box(p, d, self.center, self.axes, self.half)
        return _segment_cylinder(p, d, self.p0, self.axis, self.length, self.radius)


def prepare_occluders(occluders) -> list[PreparedOccluder]:
    """Prepare scene occluders for the segment tests."""
    return [PreparedOccluder(o) for o in occluders]


def _segment_box(p, d, center, axes, half) -> np.ndarray:
    # Slab test in the box's own frame.
    lp = (p - center) @ axes
    ld = d @ axes
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / ld
        t1 = (-half - lp) * inv
        t2 = (half - lp) * inv
    # A segment parallel to a slab: inside it (0 * inf = nan) -> unbounded, else empty.
    tlo = np.minimum(t1, t2)
    thi = np.maximum(t1, t2)
    par = ld == 0
    inside = np.abs(lp) <= half
    tlo = np.where(par, np.where(inside, -np.inf, np.inf), tlo)
    thi = np.where(par, np.where(inside, np.inf, -np.inf), thi)
    tmin = tlo.max(-1)
    tmax = thi.min(-1)
    return (tmax >= tmin) & (tmax > _EPS) & (tmin < 1 - _EPS)


def _segment_cylinder(p, d, p0, axis, length, radius) -> np.ndarray:
    q = p - p0
    qa = q @ axis
    da = d @ axis
    qp = q - qa[..., None] * axis
    dp = d - da[..., None] * axis
    a = np.einsum("...i,...i->...", dp, dp)
    b = 2 * np.einsum("...i,...i->...", qp, dp)
    c = np.einsum("...i,...i->...", qp, qp) - radius**2
    disc = b * b - 4 * a * c
    hit = np.zeros(p.shape[:-1], bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        sq = np.sqrt(np.maximum(disc, 0))
        for t in ((-b - sq) / (2 * a), (-b + sq) / (2 * a)):
            s = qa + t * da
            hit |= (disc >= 0) & (a > 0) & (t > _EPS) & (t < 1 - _EPS) & (s >= 0) & (s <= length)
        for s_cap in (0.0, length):
            t = (s_cap - qa) / da
            r = qp + t[..., None] * dp
            rr = np.einsum("...i,...i->...", r, r)
            hit |= (da != 0) & (t > _EPS) & (t < 1 - _EPS) & (rr <= radius**2)
    return hit


def segments_blocked(occluders: list[PreparedOccluder], p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Whether any occluder blocks each segment p -> q (broadcast shapes (..., 3))."""
    shape = np.broadcast_shapes(p.shape, q.shape)[:-1]
    out = np.zeros(shape, bool)
    p = np.broadcast_to(p, shape + (3,))
    q = np.broadcast_to(q, shape + (3,))
    for occ in occluders:
        out |= occ.blocks(p, q)
    return out
