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

__all__ = [
    "PARALLEL_POINTS",
    "edge_pixels",
    "edge_print_pixels",
    "lambert_albedo",
    "lambert_radiance",
    "lambert_shade",
    "label_points",
    "label_points_serial",
    "node_geometry",
    "print_coverage",
    "print_coverage_grid",
    "subpixel_normalized",
    "subpixel_normalized_serial",
    "subsample_mean",
]

#: From this many points on, the multi-threaded kernels are used (below, a thread launch
#: costs more than it saves, and on a busy machine each launch waits for a thread to be
#: scheduled: a 320 x 240 frame's 77k rays run on the calling thread).
PARALLEL_POINTS = 262144

_JIT = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}

NONE, SAMPLE, HOLDER, PATCH = 0, 1, 2, 3


#: Points per block of :func:`label_points`: each block's rays and hits are computed in a
#: loop of their own, without branches, which LLVM vectorises (packed IEEE division and
#: square root: the scalar bits), and labelled in a second loop: 0.69 -> 0.48 ms for a
#: 320 x 240 frame's pixel centres (the fused loop's branches kept it scalar).
_BLOCK = 512


# The loop's invariants are read into locals before the loop: indexing these small arrays
# inside it (a per-point helper taking them) made the kernel ~10x slower -- measured 54 ns
# a point on a 320 x 240 frame against 13 ns hoisted, whatever LLVM could not prove about
# their aliasing the outputs.  The serial twin repeats the loop on purpose (see
# gonio.brdf.kernels: numba's cache index does not tell two builds of one function apart).
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
    has_holder = holder.shape[0] == 2
    has_board = board.shape[0] > 0
    has_patch = patch.shape[0] == 4
    rows, cols = board.shape[0], board.shape[1]
    r00, r10, r20 = R[0, 0], R[1, 0], R[2, 0]
    r01, r11, r21 = R[0, 1], R[1, 1], R[2, 1]
    r02, r12, r22 = R[0, 2], R[1, 2], R[2, 2]
    c0, c1, c2 = C[0], C[1], C[2]
    h0, h1 = half[0], half[1]
    hh0 = holder[0] if has_holder else 0.0
    hh1 = holder[1] if has_holder else 0.0
    bh0, bh1 = board_half[0], board_half[1]
    pa0 = patch[0] if has_patch else 0.0
    pa1 = patch[1] if has_patch else 0.0
    pa2 = patch[2] if has_patch else 0.0
    pa3 = patch[3] if has_patch else 0.0
    n = xn.shape[0]
    for b in prange((n + _BLOCK - 1) // _BLOCK):
        s = b * _BLOCK
        m = min(_BLOCK, n - s)
        q0, q1, q2 = np.empty(_BLOCK), np.empty(_BLOCK), np.empty(_BLOCK)
        qf = np.empty(_BLOCK, np.bool_)
        for j in range(m):  # the ray and its hit: branch-free, so LLVM vectorises it
            x, y = xn[s + j], yn[s + j]
            d0 = x * r00 + y * r10 + r20
            d1 = x * r01 + y * r11 + r21
            d2 = x * r02 + y * r12 + r22
            norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            d0, d1, d2 = d0 / norm, d1 / norm, d2 / norm
            t = -c2 / d2
            front = (t > 0.0) & (t < math.inf)  # finite and positive
            t = t if front else 0.0
            q0[j] = c0 + t * d0
            q1[j] = c1 + t * d1
            q2[j] = c2 + t * d2
            qf[j] = front
        for j in range(m):  # the labels
            i = s + j
            p0, p1, front = q0[j], q1[j], qf[j]
            out_x[i, 0] = p0
            out_x[i, 1] = p1
            out_x[i, 2] = q2[j]
            out_front[i] = front
            ax, ay = abs(p0), abs(p1)
            region = NONE
            white = False
            if has_holder and front and ax <= hh0 and ay <= hh1:
                region = HOLDER
                white = True
                if has_board:
                    c = math.floor((p0 + bh0) / (2 * bh0) * cols)
                    r = math.floor((bh1 - p1) / (2 * bh1) * rows)
                    if c >= 0 and c < cols and r >= 0 and r < rows:
                        white = board[int(r), int(c)] != 0
                if has_patch and abs(p0 - pa0) <= pa2 and abs(p1 - pa1) <= pa3:
                    region = PATCH
            if front and ax <= h0 and ay <= h1:
                region = SAMPLE
            out_region[i] = region
            out_white[i] = white and region == HOLDER


@njit(**_JIT)
def label_points_serial(
    xn, yn, R, C, half, holder, board, board_half, patch, out_x, out_front, out_region, out_white
):
    """:func:`label_points` on the calling thread (no thread launch: small batches)."""
    has_holder = holder.shape[0] == 2
    has_board = board.shape[0] > 0
    has_patch = patch.shape[0] == 4
    rows, cols = board.shape[0], board.shape[1]
    r00, r10, r20 = R[0, 0], R[1, 0], R[2, 0]
    r01, r11, r21 = R[0, 1], R[1, 1], R[2, 1]
    r02, r12, r22 = R[0, 2], R[1, 2], R[2, 2]
    c0, c1, c2 = C[0], C[1], C[2]
    h0, h1 = half[0], half[1]
    hh0 = holder[0] if has_holder else 0.0
    hh1 = holder[1] if has_holder else 0.0
    bh0, bh1 = board_half[0], board_half[1]
    pa0 = patch[0] if has_patch else 0.0
    pa1 = patch[1] if has_patch else 0.0
    pa2 = patch[2] if has_patch else 0.0
    pa3 = patch[3] if has_patch else 0.0
    n = xn.shape[0]
    q0, q1, q2 = np.empty(_BLOCK), np.empty(_BLOCK), np.empty(_BLOCK)
    qf = np.empty(_BLOCK, np.bool_)
    for b in range((n + _BLOCK - 1) // _BLOCK):
        s = b * _BLOCK
        m = min(_BLOCK, n - s)
        for j in range(m):  # the ray and its hit: branch-free, so LLVM vectorises it
            x, y = xn[s + j], yn[s + j]
            d0 = x * r00 + y * r10 + r20
            d1 = x * r01 + y * r11 + r21
            d2 = x * r02 + y * r12 + r22
            norm = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            d0, d1, d2 = d0 / norm, d1 / norm, d2 / norm
            t = -c2 / d2
            front = (t > 0.0) & (t < math.inf)  # finite and positive
            t = t if front else 0.0
            q0[j] = c0 + t * d0
            q1[j] = c1 + t * d1
            q2[j] = c2 + t * d2
            qf[j] = front
        for j in range(m):  # the labels
            i = s + j
            p0, p1, front = q0[j], q1[j], qf[j]
            out_x[i, 0] = p0
            out_x[i, 1] = p1
            out_x[i, 2] = q2[j]
            out_front[i] = front
            ax, ay = abs(p0), abs(p1)
            region = NONE
            white = False
            if has_holder and front and ax <= hh0 and ay <= hh1:
                region = HOLDER
                white = True
                if has_board:
                    c = math.floor((p0 + bh0) / (2 * bh0) * cols)
                    r = math.floor((bh1 - p1) / (2 * bh1) * rows)
                    if c >= 0 and c < cols and r >= 0 and r < rows:
                        white = board[int(r), int(c)] != 0
                if has_patch and abs(p0 - pa0) <= pa2 and abs(p1 - pa1) <= pa3:
                    region = PATCH
            if front and ax <= h0 and ay <= h1:
                region = SAMPLE
            out_region[i] = region
            out_white[i] = white and region == HOLDER


@njit(**_JIT, inline="always")
def _undistort(xd, yd, x0, y0, k1, k2, p1, p2, k3, tol, max_iter):
    # geometry.undistort_normalized's Newton step, for one point, from (x0, y0); one step
    # beyond the tolerance, as the batch iteration takes for all but its slowest points:
    # Newton's quadratic convergence then leaves rounding only
    x, y = x0, y0
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
def subpixel_normalized(
    ei, ej, n_aa, K, dist, grid_x, grid_y, tol, max_iter, out_x, out_y, out_err
):
    """Undistorted normalised coordinates of the ``n_aa`` x ``n_aa`` sub-pixel points of
    pixels (ei, ej) (columns, rows), in the renderer's order (pixel, then u, then v).

    ``dist`` (5,) or (0,) for a pinhole; ``grid_x``, ``grid_y`` (H, W) the pixel
    centres' undistorted coordinates (:func:`gonio.simulator.geometry.pixel_grid`; the
    starting point); ``out_err`` (M,) the distortion's residual at the result (0 for a
    pinhole).  The invariants are read before the loop (see :func:`label_points`).
    """
    has_dist = dist.shape[0] == 5
    nn = n_aa * n_aa
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    k1 = dist[0] if has_dist else 0.0
    k2 = dist[1] if has_dist else 0.0
    q1 = dist[2] if has_dist else 0.0
    q2 = dist[3] if has_dist else 0.0
    k3 = dist[4] if has_dist else 0.0
    for p in prange(ei.shape[0]):
        i, j = ei[p], ej[p]
        # Newton starts from the pixel centre's undistorted point shifted by the sub-pixel
        # offset (the lens is locally a near-identity map): two steps fewer than from the
        # distorted point, the same root
        xc = (i + 0.5 - cx) / fx
        yc = (j + 0.5 - cy) / fy
        gx = grid_x[j, i] if has_dist else 0.0
        gy = grid_y[j, i] if has_dist else 0.0
        for a in range(n_aa):
            ou = (a + 0.5) / n_aa
            for b in range(n_aa):
                ov = (b + 0.5) / n_aa
                k = p * nn + a * n_aa + b
                x = (i + ou - cx) / fx
                y = (j + ov - cy) / fy
                err = 0.0
                if has_dist:
                    x0 = gx + (x - xc)
                    y0 = gy + (y - yc)
                    x, y, err = _undistort(x, y, x0, y0, k1, k2, q1, q2, k3, tol, max_iter)
                out_x[k] = x
                out_y[k] = y
                out_err[k] = err


@njit(**_JIT)
def subpixel_normalized_serial(
    ei, ej, n_aa, K, dist, grid_x, grid_y, tol, max_iter, out_x, out_y, out_err
):
    """:func:`subpixel_normalized` on the calling thread."""
    has_dist = dist.shape[0] == 5
    nn = n_aa * n_aa
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    k1 = dist[0] if has_dist else 0.0
    k2 = dist[1] if has_dist else 0.0
    q1 = dist[2] if has_dist else 0.0
    q2 = dist[3] if has_dist else 0.0
    k3 = dist[4] if has_dist else 0.0
    for p in range(ei.shape[0]):
        i, j = ei[p], ej[p]
        # Newton starts from the pixel centre's undistorted point shifted by the sub-pixel
        # offset (the lens is locally a near-identity map): two steps fewer than from the
        # distorted point, the same root
        xc = (i + 0.5 - cx) / fx
        yc = (j + 0.5 - cy) / fy
        gx = grid_x[j, i] if has_dist else 0.0
        gy = grid_y[j, i] if has_dist else 0.0
        for a in range(n_aa):
            ou = (a + 0.5) / n_aa
            for b in range(n_aa):
                ov = (b + 0.5) / n_aa
                k = p * nn + a * n_aa + b
                x = (i + ou - cx) / fx
                y = (j + ov - cy) / fy
                err = 0.0
                if has_dist:
                    x0 = gx + (x - xc)
                    y0 = gy + (y - yc)
                    x, y, err = _undistort(x, y, x0, y0, k1, k2, q1, q2, k3, tol, max_iter)
                out_x[k] = x
                out_y[k] = y
                out_err[k] = err


# One thread only: numba's parallel lowering of this loop mistypes the node row index
# (float64); the shading's BRDF evaluation, its larger cost, runs on numba's threads.
@njit(**_JIT)
def node_geometry(x, y, w, normal, is_point, profile_n, face, out_wi, out_g):
    """Directions to a light's nodes and their geometric factors.

    Parameters
    ----------
    x
        (M, 3) surface points, m.
    y, w
        (1 or M, K, 3) nodes on the light, m, and (1 or M, K) their area weights, m^2.
    normal
        (3,) the light's emitting normal; ``is_point``: a point light (``g = cos / r^2``).
    profile_n
        The emission profile's exponent (0: Lambertian).
    face
        (1 or M, K) the face's non-uniformity at the nodes, or (0, K) for a uniform face.
    out_wi, out_g
        (M, K, 3) unit directions to the nodes, (M, K) ``w cos cos' prof face / r^2``
        (1/sr for a point light's unit intensity).
    """
    # render._Integrator._shade_nodes' geometry, in its operation order; one row of
    # nodes, weights, face for all points, or a row per point.  Invariants read before
    # the loop (see label_points).
    n0, n1, n2 = normal[0], normal[1], normal[2]
    ny, nw, nf = y.shape[0] - 1, w.shape[0] - 1, face.shape[0] - 1
    has_face = face.shape[0] > 0
    kk = y.shape[1]
    for i in range(x.shape[0]):
        yi = min(i, ny)
        wj = min(i, nw)
        fi = min(i, nf)
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        for k in range(kk):
            d0 = y[yi, k, 0] - x0
            d1 = y[yi, k, 1] - x1
            d2 = y[yi, k, 2] - x2
            r2 = d0 * d0 + d1 * d1 + d2 * d2
            r = math.sqrt(r2)
            w0, w1, w2 = d0 / r, d1 / r, d2 / r
            out_wi[i, k, 0] = w0
            out_wi[i, k, 1] = w1
            out_wi[i, k, 2] = w2
            cos_s = 0.0 if w2 < 0.0 else w2
            if is_point:
                g = cos_s / r2
            else:
                c = -(w0 * n0 + w1 * n1 + w2 * n2)
                cos_l = 0.0 if c < 0.0 else c
                g = w[wj, k] * cos_s * cos_l / r2
                if profile_n != 0.0:
                    g = g * cos_l**profile_n
                if has_face:
                    g = g * face[fi, k]
            out_g[i, k] = g


@njit(**_JIT)
def lambert_radiance(region, white, g, table, out):
    """``albedo / pi * sum_k g`` (M, 3) into the rows of ``out`` that are not the sample
    (region 1); ``table`` (3, 3) the black print's, white print's and reference patch's
    albedo (Surface.lambert_albedo)."""
    tab = table / math.pi  # (3, 3): table[row, c] / pi as the loop divided it, once
    kk = g.shape[1]
    for i in range(region.shape[0]):
        reg = region[i]
        if reg == SAMPLE:
            continue
        row = 2 if reg == PATCH else (1 if white[i] else 0)
        gs = 0.0
        for k in range(kk):
            gs += g[i, k]
        for c in range(3):
            out[i, c] = tab[row, c] * gs


@njit(**_JIT)
def lambert_shade(x, region, white, y, w, normal, is_point, profile_n, face, table, rgb, out):
    """:func:`node_geometry` and :func:`lambert_radiance` fused, times the light's colour,
    for the points that are not the sample (region 1; their rows of ``out`` (M, 3) are
    left as they are): ``albedo / pi * sum_k g * rgb`` without the (M, K, 3) directions
    (only the sample's BRDF needs them).  Arguments as there; ``rgb`` (3,)."""
    n0, n1, n2 = normal[0], normal[1], normal[2]
    ny, nw, nf = y.shape[0] - 1, w.shape[0] - 1, face.shape[0] - 1
    has_face = face.shape[0] > 0
    kk = y.shape[1]
    # table[row, c] / pi as lambert_radiance divides it, read once (see label_points)
    b0, b1, b2 = table[0, 0] / math.pi, table[0, 1] / math.pi, table[0, 2] / math.pi
    w0_, w1_, w2_ = table[1, 0] / math.pi, table[1, 1] / math.pi, table[1, 2] / math.pi
    p0, p1, p2 = table[2, 0] / math.pi, table[2, 1] / math.pi, table[2, 2] / math.pi
    c0, c1, c2 = rgb[0], rgb[1], rgb[2]
    for i in range(x.shape[0]):
        reg = region[i]
        if reg == SAMPLE:
            continue
        yi = min(i, ny)
        wj = min(i, nw)
        fi = min(i, nf)
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        gs = 0.0
        for k in range(kk):
            # node_geometry's expressions, in its order
            d0 = y[yi, k, 0] - x0
            d1 = y[yi, k, 1] - x1
            d2 = y[yi, k, 2] - x2
            r2 = d0 * d0 + d1 * d1 + d2 * d2
            r = math.sqrt(r2)
            w0, w1, w2 = d0 / r, d1 / r, d2 / r
            cos_s = 0.0 if w2 < 0.0 else w2
            if is_point:
                g = cos_s / r2
            else:
                c = -(w0 * n0 + w1 * n1 + w2 * n2)
                cos_l = 0.0 if c < 0.0 else c
                g = w[wj, k] * cos_s * cos_l / r2
                if profile_n != 0.0:
                    g = g * cos_l**profile_n
                if has_face:
                    g = g * face[fi, k]
            gs += g
        if reg == PATCH:
            a0, a1, a2 = p0, p1, p2
        elif white[i]:
            a0, a1, a2 = w0_, w1_, w2_
        else:
            a0, a1, a2 = b0, b1, b2
        out[i, 0] = a0 * gs * c0
        out[i, 1] = a1 * gs * c1
        out[i, 2] = a2 * gs * c2


@njit(**_JIT)
def lambert_albedo(region, white, table, out):
    """The albedo (3,) of every point that is not the sample, into ``out`` (M, 3); the
    table's rows read once (see :func:`label_points`)."""
    b0, b1, b2 = table[0, 0], table[0, 1], table[0, 2]
    w0, w1, w2 = table[1, 0], table[1, 1], table[1, 2]
    p0, p1, p2 = table[2, 0], table[2, 1], table[2, 2]
    for i in range(region.shape[0]):
        reg = region[i]
        if reg == SAMPLE:
            continue
        if reg == PATCH:
            out[i, 0], out[i, 1], out[i, 2] = p0, p1, p2
        elif white[i]:
            out[i, 0], out[i, 1], out[i, 2] = w0, w1, w2
        else:
            out[i, 0], out[i, 1], out[i, 2] = b0, b1, b2


@njit(**_JIT)
def edge_pixels(code_c, code_k, out):
    """``out`` (H, W) = whether a pixel's centre code ``code_c`` (H, W) differs from any
    of its four corners' ``code_k`` (H + 1, W + 1) (the anti-aliasing's edge test)."""
    for j in range(code_c.shape[0]):
        for i in range(code_c.shape[1]):
            c = code_c[j, i]
            out[j, i] = (
                code_k[j, i] != c
                or code_k[j + 1, i] != c
                or code_k[j, i + 1] != c
                or code_k[j + 1, i + 1] != c
            )


@njit(**_JIT)
def subsample_mean(sub, n, ej, ei, out):
    """Box-filter the anti-aliasing sub-samples: ``out[ej[p], ei[p]]`` (H, W, 3) = the
    mean of rows ``p n .. p n + n - 1`` of ``sub`` (P n, 3), summed in row order from the
    first row and divided by n, as numpy's ``sub.reshape(P, n, 3).mean(1)`` does."""
    for p in range(ej.shape[0]):
        base = p * n
        s0, s1, s2 = sub[base, 0], sub[base, 1], sub[base, 2]
        for q in range(1, n):
            s0 += sub[base + q, 0]
            s1 += sub[base + q, 1]
            s2 += sub[base + q, 2]
        j, i = ej[p], ei[p]
        out[j, i, 0] = s0 / n
        out[j, i, 1] = s1 / n
        out[j, i, 2] = s2 / n


def board_uint8(img: np.ndarray | None) -> np.ndarray:
    """The board print as the kernels read it ((0, 0) without a board)."""
    if img is None:
        return np.zeros((0, 0), np.uint8)
    return np.ascontiguousarray(img, dtype=np.uint8)


@njit(**_JIT, inline="always")
def _clip_poly(su, sv, n, du, dv, axis, bound, above):
    # one Sutherland-Hodgman pass of print_coverage.coverage_numpy's _clip: the polygon
    # (su, sv)[:n] against coord >= bound (above) or <= bound, into (du, dv); its count
    m = 0
    for i in range(n):
        j = i + 1 if i + 1 < n else 0
        a = su[i] if axis == 0 else sv[i]
        b = su[j] if axis == 0 else sv[j]
        ina = a >= bound if above else a <= bound
        inb = b >= bound if above else b <= bound
        if ina:
            du[m] = su[i]
            dv[m] = sv[i]
            m += 1
        if ina != inb:
            t = (bound - a) / (b - a)
            if axis == 0:
                du[m] = bound
                dv[m] = sv[i] + t * (sv[j] - sv[i])
            else:
                du[m] = su[i] + t * (su[j] - su[i])
                dv[m] = bound
            m += 1
    return m


@njit(**_JIT, inline="always")
def _image_area(pu, pv, n, s0, s1, s2, s3, R, C):
    # shoelace area in normalised image coordinates of a raster-coordinate polygon
    acc = 0.0
    if n < 3:
        return 0.0
    xf, yf, x0, y0 = 0.0, 0.0, 0.0, 0.0
    for i in range(n):
        px = pu[i] / s0 - s1
        py = s3 - pv[i] / s2
        d0, d1, d2 = px - C[0], py - C[1], -C[2]
        q0 = R[0, 0] * d0 + R[0, 1] * d1 + R[0, 2] * d2
        q1 = R[1, 0] * d0 + R[1, 1] * d1 + R[1, 2] * d2
        q2 = R[2, 0] * d0 + R[2, 1] * d1 + R[2, 2] * d2
        x, y = q0 / q2, q1 / q2
        if i == 0:
            xf, yf = x, y
        else:
            acc += x0 * y - x * y0
        x0, y0 = x, y
    acc += x0 * yf - xf * y0
    return 0.5 * abs(acc)


@njit(**_JIT, inline="always")
def _coverage_of(qu, qv, col_edges, row_edges, black, scale, R, C, au, av, bu, bv):
    # one pixel: its footprint (qu, qv)[:4] in raster coordinates; au..bv scratch (16,)
    s0, s1, s2, s3 = scale[0], scale[1], scale[2], scale[3]
    nc, nr = col_edges.shape[0] - 1, row_edges.shape[0] - 1
    umin, umax, vmin, vmax = qu[0], qu[0], qv[0], qv[0]
    for c in range(1, 4):
        umin, umax = min(umin, qu[c]), max(umax, qu[c])
        vmin, vmax = min(vmin, qv[c]), max(vmax, qv[c])
    full = _image_area(qu, qv, 4, s0, s1, s2, s3, R, C)
    c0 = min(max(np.searchsorted(col_edges, umin, side="right") - 1, 0), nc - 1)
    c1 = min(max(np.searchsorted(col_edges, umax, side="left") - 1, 0), nc - 1)
    r0 = min(max(np.searchsorted(row_edges, vmin, side="right") - 1, 0), nr - 1)
    r1 = min(max(np.searchsorted(row_edges, vmax, side="left") - 1, 0), nr - 1)
    blk = 0.0
    for r in range(r0, r1 + 1):
        for c in range(c0, c1 + 1):
            if black[r, c] == 0:
                continue
            for k in range(4):
                au[k], av[k] = qu[k], qv[k]
            n = _clip_poly(au, av, 4, bu, bv, 0, col_edges[c], True)
            n = _clip_poly(bu, bv, n, au, av, 0, col_edges[c + 1], False)
            n = _clip_poly(au, av, n, bu, bv, 1, row_edges[r], True)
            n = _clip_poly(bu, bv, n, au, av, 1, row_edges[r + 1], False)
            blk += _image_area(au, av, n, s0, s1, s2, s3, R, C)
    cov = 1.0 - blk / full
    return 0.0 if cov < 0.0 else (1.0 if cov > 1.0 else cov)


@njit(**_JIT)
def print_coverage(corners, col_edges, row_edges, black, scale, R, C, out):
    """White-print area fraction of pixels: :func:`gonio.simulator.print_coverage.
    coverage_numpy` per pixel (its arguments; ``out`` (P,)).  The same algorithm and
    operations, summed per pixel in cell order rather than numpy's pairwise order."""
    s0, s1, s2, s3 = scale[0], scale[1], scale[2], scale[3]
    au, av = np.empty(16), np.empty(16)
    bu, bv = np.empty(16), np.empty(16)
    qu, qv = np.empty(4), np.empty(4)
    for p in range(corners.shape[0]):
        for c in range(4):
            qu[c] = (corners[p, c, 0] + s1) * s0
            qv[c] = (s3 - corners[p, c, 1]) * s2
        out[p] = _coverage_of(qu, qv, col_edges, row_edges, black, scale, R, C, au, av, bu, bv)


@njit(**_JIT)
def print_coverage_grid(grid, rows, cols, col_edges, row_edges, black, scale, R, C, out):
    """:func:`print_coverage` of pixels (rows, cols) (P,) whose corners are read from the
    corner rays' points ``grid`` (H + 1, W + 1, 3) (pixel (j, i): corners (j, i),
    (j, i + 1), (j + 1, i + 1), (j + 1, i)), without gathering them first."""
    s0, s1, s2, s3 = scale[0], scale[1], scale[2], scale[3]
    au, av = np.empty(16), np.empty(16)
    bu, bv = np.empty(16), np.empty(16)
    qu, qv = np.empty(4), np.empty(4)
    for p in range(rows.shape[0]):
        j, i = rows[p], cols[p]
        for c in range(4):
            jj = j + (1 if c >= 2 else 0)
            ii = i + (1 if c == 1 or c == 2 else 0)
            qu[c] = (grid[jj, ii, 0] + s1) * s0
            qv[c] = (s3 - grid[jj, ii, 1]) * s2
        out[p] = _coverage_of(qu, qv, col_edges, row_edges, black, scale, R, C, au, av, bu, bv)


@njit(**_JIT)
def edge_print_pixels(code_c, code_k, holder, out_edge, out_print):
    """:func:`edge_pixels` into ``out_edge``, and into ``out_print`` the edge pixels whose
    centre's region (code & 7) is ``holder`` and whose corners differ from it in the
    print bit (8) alone (render._print_only)."""
    for j in range(code_c.shape[0]):
        for i in range(code_c.shape[1]):
            c = code_c[j, i]
            k0, k1 = code_k[j, i], code_k[j + 1, i]
            k2, k3 = code_k[j, i + 1], code_k[j + 1, i + 1]
            e = k0 != c or k1 != c or k2 != c or k3 != c
            out_edge[j, i] = e
            b = c & ~8
            out_print[j, i] = (
                e
                and (c & 7) == holder
                and (k0 & ~8) == b
                and (k1 & ~8) == b
                and (k2 & ~8) == b
                and (k3 & ~8) == b
            )
