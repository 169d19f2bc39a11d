"""Fused numba kernels of the renderer's per-pixel geometry: rays, hits, labels.

Why hand-written: a camera ray's way to its label (undistort the image point, turn it
into a world ray, meet the plane z = 0, find the sample, holder, reference patch and
board print there) is some thirty numpy passes over the image, each streaming a
temporary through memory; profiled on a 320 x 240 frame they were a third of the render
(pixel centres and corners, and the anti-aliasing sub-rays, whose Newton undistortion
iterates the whole batch until its slowest point has converged).  These kernels do it
per point in registers, in the numpy code's operation order
(:func:`gonio.simulator.geometry.rays_from_normalized`, ``intersect_plane_z0``,
:meth:`gonio.simulator.render.Surface.classify`), so the two paths agree to rounding:
numpy's ``(N, 3) @ (3, 3)`` goes through BLAS, which may fuse multiply-adds, and the
batch Newton iteration runs a converged point a step or two further than the per-point
one (both reproduce the distortion to 1e-13).  ``tests/simulator/test_render_kernels.py``
holds the two paths equal.

IEEE-strict as :mod:`gonio.brdf.kernels` (``fastmath=False``, ``error_model="numpy"``,
``cache=True``).  ``GONIO_NUMBA=0`` keeps the renderer on numpy (the reference).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = ["label_points", "subpixel_normalized"]

_JIT = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}

NONE, SAMPLE, HOLDER, PATCH = 0, 1, 2, 3


@njit(**_JIT, parallel=True)
def label_points(
    xn, yn, R, C, half, holder, board, board_half, patch, out_x, out_front, out_region, out_white
):
    """Hit points and labels of the rays through normalised image points.

    Parameters
    ----------
    xn, yn
        (N,) undistorted normalised coordinates.
    R
        (3, 3) world-to-camera rotation; C (3,) camera centre, m.
    half
        (2,) sample half-size, m.
    holder
        (2,) holder half-size, m, or (0,) without a holder.
    board
        (rows, cols) uint8 board print (1 white), or (0, 0) without a board;
        ``board_half`` (2,) its half extent, m.
    patch
        (4,) reference patch centre x, y and half-size x, y, m, or (0,) without one.
    out_x, out_front, out_region, out_white
        (N, 3) hit points (the camera centre where the ray misses), (N,) bool in front,
        (N,) uint8 region code, (N,) bool board print white (holder points only).
    """
    n = xn.shape[0]
    has_holder = holder.shape[0] == 2
    has_board = board.shape[0] > 0
    has_patch = patch.shape[0] == 4
    rows, cols = board.shape[0], board.shape[1]
    for i in prange(n):
        x, y = xn[i], yn[i]
        d0 = x * R[0, 0] + y * R[1, 0] + R[2, 0]
        d1 = x * R[0, 1] + y * R[1, 1] + R[2, 1]
        d2 = x * R[0, 2] + y * R[1, 2] + R[2, 2]
        norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        d0, d1, d2 = d0 / norm, d1 / norm, d2 / norm
        t = -C[2] / d2
        front = math.isfinite(t) and t > 0
        if not front:
            t = 0.0
        p0 = C[0] + t * d0
        p1 = C[1] + t * d1
        out_x[i, 0] = p0
        out_x[i, 1] = p1
        out_x[i, 2] = C[2] + t * d2
        out_front[i] = front
        ax, ay = abs(p0), abs(p1)
        region = NONE
        white = False
        if has_holder and front and ax <= holder[0] and ay <= holder[1]:
            region = HOLDER
            white = True
            if has_board:
                c = math.floor((p0 + board_half[0]) / (2 * board_half[0]) * cols)
                r = math.floor((board_half[1] - p1) / (2 * board_half[1]) * rows)
                if c >= 0 and c < cols and r >= 0 and r < rows:
                    white = board[int(r), int(c)] != 0
            if has_patch and abs(p0 - patch[0]) <= patch[2] and abs(p1 - patch[1]) <= patch[3]:
                region = PATCH
        if front and ax <= half[0] and ay <= half[1]:
            region = SAMPLE
        out_region[i] = region
        out_white[i] = white and region == HOLDER


@njit(**_JIT, inline="always")
def _undistort(xd, yd, k1, k2, p1, p2, k3, tol, max_iter):
    # geometry.undistort_normalized's Newton step, for one point
    # one step beyond the tolerance, as the batch iteration takes for all but its slowest
    # points: Newton's quadratic convergence then leaves rounding only
    x, y = xd, yd
    polish = False
    for _ in range(max_iter):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dradial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)
        fx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
        fy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
        if polish:
            break
        if abs(fx) + abs(fy) <= tol:
            polish = True
        a = radial + 2.0 * x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        c = 2.0 * x * y * dradial + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + 2.0 * y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * c
        x = x - (d * fx - b * fy) / det
        y = y - (a * fy - c * fx) / det
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xr = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yr = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return x, y, math.hypot(xr - xd, yr - yd)


@njit(**_JIT, parallel=True)
def subpixel_normalized(ei, ej, n_aa, K, dist, tol, max_iter, out_x, out_y, out_err):
    """Undistorted normalised coordinates of the ``n_aa`` x ``n_aa`` sub-pixel points of
    pixels (ei, ej) (columns, rows), in the renderer's order (pixel, then u, then v).

    ``dist`` (5,) or (0,) for a pinhole; ``out_err`` (M,) the distortion's residual at
    the result (0 for a pinhole).
    """
    m = ei.shape[0]
    has_dist = dist.shape[0] == 5
    nn = n_aa * n_aa
    for p in prange(m):
        for a in range(n_aa):
            ou = (a + 0.5) / n_aa
            for b in range(n_aa):
                ov = (b + 0.5) / n_aa
                k = p * nn + a * n_aa + b
                x = (ei[p] + ou - K[0, 2]) / K[0, 0]
                y = (ej[p] + ov - K[1, 2]) / K[1, 1]
                err = 0.0
                if has_dist:
                    x, y, err = _undistort(
                        x, y, dist[0], dist[1], dist[2], dist[3], dist[4], tol, max_iter
                    )
                out_x[k] = x
                out_y[k] = y
                out_err[k] = err


def board_uint8(img: np.ndarray | None) -> np.ndarray:
    """The board print as the kernels read it ((0, 0) without a board)."""
    if img is None:
        return np.zeros((0, 0), np.uint8)
    return np.ascontiguousarray(img, dtype=np.uint8)
