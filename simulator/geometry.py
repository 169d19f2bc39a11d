"""Ray and segment geometry for the renderer: camera rays, the sample plane, occluders.

Hand-written because the scene is tiny (one plane and a few boxes and cylinders) and the
work is millions of segment tests per image: a general ray tracer (Mitsuba, Embree) would
cost more in setup and data transfer than these closed-form vectorised tests.
"""

from __future__ import annotations

import numpy as np

from gonio.simulator.scene import BoxOccluder, CylinderOccluder

__all__ = [
    "PreparedOccluder",
    "camera_rays",
    "intersect_plane_z0",
    "prepare_occluders",
    "segments_blocked",
]

_EPS = 1e-9


def camera_rays(K: np.ndarray, R: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """World-frame unit ray directions through image points (u, v) in pixels.

    Parameters
    ----------
    K
        Camera matrix (3, 3); pixel centres at integer + 0.5.
    R
        World-to-camera rotation (3, 3), OpenCV axes.
    u, v
        Image coordinates (pixels), any matching shapes.
    """
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
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
