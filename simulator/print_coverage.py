"""Exact area coverage of the holder's board print on a pixel (anti-aliasing without rays).

A pixel whose centre and four corners all see the holder, with the same light-centre
visibility, but not all the same print colour (an *edge* of the printed squares or
marker cells) is, inside it, Lambertian paper of two albedos: its box-filtered radiance
is ``c L_white + (1 - c) L_black`` where ``c`` is the fraction of the pixel's area that
sees white print and ``L`` the radiance the pixel centre would have with either albedo
(the light's geometry changes by ~1e-3 across a pixel's footprint; the 3 x 3 or 4 x 4
sub-rays this replaces quantise ``c`` to steps of 1/9 or 1/16).

``c`` is computed exactly for the pinhole: the pixel's four corner rays meet the board
plane in a quadrilateral (a homography maps the pixel's square to it, straight edges to
straight edges); it is clipped (Sutherland-Hodgman) against each black *cell* of the
print that its bounding box meets, the clipped polygons are mapped back into the image
(normalised, undistorted coordinates) and their areas (shoelace) summed and divided by
the pixel's.  Areas are taken in the image, not on the board: the box filter averages
over the pixel, and a perspective footprint's board area is not uniform in it.  With
lens distortion the pixel's footprint is the quadrilateral of its undistorted corners
(its sides bend by ~1e-6 of a pixel at the demo's k1); the fraction is then exact to
second order in the pixel size.

The print (``Board.image()``, a raster of ``pixels_per_square`` texels per square) is
first merged into *cells*: the rows and columns where the raster changes cut it into a
non-uniform grid whose cells are each one colour (a ChArUco board: squares and marker
bits), so a footprint meets a handful of cells instead of dozens of texels.

:func:`coverage_numpy` is the vectorised reference; the renderer uses the numba kernel
:func:`gonio.simulator.render_kernels.print_coverage` (same algorithm, per pixel; the
two agree to rounding, ``tests/simulator/test_print_coverage.py``) from
``render_kernels`` batch sizes on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PrintCells", "coverage_numpy", "print_cells"]


@dataclass(frozen=True)
class PrintCells:
    """The board print as a grid of one-colour cells, in raster (texel) units.

    Attributes
    ----------
    col_edges
        (nc + 1,) float64 column boundaries, texels from the print's left edge (0 .. cols).
    row_edges
        (nr + 1,) float64 row boundaries, texels from the print's top (0 .. rows).
    black
        (nr, nc) uint8: 1 where the cell is black print.
    scale
        (4,) float64 ``(cols / (2 bh_x), bh_x, rows / (2 bh_y), bh_y)``: texels per metre
        and the board's half extent (m) along x and y, for the sample-frame mapping
        ``u = (x + bh_x) cols / (2 bh_x)``, ``v = (bh_y - y) rows / (2 bh_y)``.
    """

    col_edges: np.ndarray
    row_edges: np.ndarray
    black: np.ndarray
    scale: np.ndarray


def print_cells(board_img: np.ndarray, board_half: np.ndarray) -> PrintCells:
    """Merge a board print (rows, cols) bool (True white) into one-colour cells.

    Parameters
    ----------
    board_img
        (rows, cols) bool, row 0 at the board's top (+y), True = white.
    board_half
        (2,) the board's half extent along x and y, m.

    Returns
    -------
    PrintCells
    """
    img = np.asarray(board_img, dtype=bool)
    rows, cols = img.shape
    # a cut wherever any row (column) changes colour between two neighbouring columns (rows)
    cc = np.flatnonzero(np.any(img[:, 1:] != img[:, :-1], axis=0)) + 1
    rc = np.flatnonzero(np.any(img[1:, :] != img[:-1, :], axis=1)) + 1
    col_edges = np.concatenate([[0], cc, [cols]]).astype(np.float64)
    row_edges = np.concatenate([[0], rc, [rows]]).astype(np.float64)
    black = (~img[np.ix_(row_edges[:-1].astype(np.intp), col_edges[:-1].astype(np.intp))]).astype(
        np.uint8
    )
    bh = np.asarray(board_half, dtype=np.float64)
    scale = np.array([cols / (2 * bh[0]), bh[0], rows / (2 * bh[1]), bh[1]])
    return PrintCells(col_edges, row_edges, np.ascontiguousarray(black), scale)


def _to_image(u, v, scale, R, C):
    """Raster coordinates (u, v) on the board plane -> normalised image coordinates."""
    px = u / scale[0] - scale[1]
    py = scale[3] - v / scale[2]
    d0, d1, d2 = px - C[0], py - C[1], -C[2]
    q0 = R[0, 0] * d0 + R[0, 1] * d1 + R[0, 2] * d2
    q1 = R[1, 0] * d0 + R[1, 1] * d1 + R[1, 2] * d2
    q2 = R[2, 0] * d0 + R[2, 1] * d1 + R[2, 2] * d2
    return q0 / q2, q1 / q2


def _shoelace(xs, ys, n):
    """Absolute area of polygons (M, K) padded after their n (M,) vertices."""
    k = xs.shape[1]
    idx = np.arange(k)[None, :]
    nxt = np.where(idx + 1 < n[:, None], idx + 1, 0)
    valid = idx < n[:, None]
    x1 = np.take_along_axis(xs, nxt, 1)
    y1 = np.take_along_axis(ys, nxt, 1)
    cross = np.where(valid, xs * y1 - x1 * ys, 0.0)
    return 0.5 * np.abs(cross.sum(1))


def _clip(pu, pv, n, axis, bound, keep_above):
    """Sutherland-Hodgman: clip polygons (M, K) with n (M,) vertices against the
    half-plane ``coord >= bound`` (keep_above) or ``<= bound`` of coordinate ``axis``
    (0: u, 1: v); returns the polygons (M, K + 1) and their counts."""
    m, k = pu.shape
    idx = np.arange(k)[None, :]
    valid = idx < n[:, None]
    nxt = np.where(idx + 1 < n[:, None], idx + 1, 0)
    qu, qv = np.take_along_axis(pu, nxt, 1), np.take_along_axis(pv, nxt, 1)
    a, b = (pu, qu) if axis == 0 else (pv, qv)
    bound = bound[:, None]
    ina = (a >= bound) if keep_above else (a <= bound)
    inb = (b >= bound) if keep_above else (b <= bound)
    t = (bound - a) / (b - a)
    iu = pu + t * (qu - pu)
    iv = pv + t * (qv - pv)
    if axis == 0:
        iu = np.broadcast_to(bound, iu.shape).copy()
    else:
        iv = np.broadcast_to(bound, iv.shape).copy()
    # per edge: the start vertex if inside, then the crossing if the edge crosses
    ou = np.stack([pu, iu], 2).reshape(m, 2 * k)
    ov = np.stack([pv, iv], 2).reshape(m, 2 * k)
    keep = np.stack([valid & ina, valid & (ina != inb)], 2).reshape(m, 2 * k)
    order = np.argsort(~keep, axis=1, kind="stable")
    cnt = keep.sum(1)
    ou = np.take_along_axis(ou, order, 1)[:, : k + 1]
    ov = np.take_along_axis(ov, order, 1)[:, : k + 1]
    return ou, ov, cnt


def coverage_numpy(
    corners: np.ndarray, cells: PrintCells, R: np.ndarray, C: np.ndarray
) -> np.ndarray:
    """Fraction of each pixel's area that sees white print (the vectorised reference).

    Parameters
    ----------
    corners
        (P, 4, 3) the pixel's corner rays' points on the plane z = 0 (sample frame, m),
        in order around the pixel.
    cells
        :func:`print_cells` of the board.
    R, C
        (3, 3) world-to-camera rotation and (3,) camera centre, m.

    Returns
    -------
    numpy.ndarray
        (P,) white coverage in [0, 1] (1 - the black cells' share of the pixel's area
        in normalised image coordinates; outside the print counts as white).
    """
    corners = np.asarray(corners, dtype=np.float64)
    p = corners.shape[0]
    s = cells.scale
    u = (corners[..., 0] + s[1]) * s[0]
    v = (s[3] - corners[..., 1]) * s[2]
    four = np.full(p, 4)
    xi, yi = _to_image(u, v, s, R, C)
    full = _shoelace(xi, yi, four)
    ce, re = cells.col_edges, cells.row_edges
    nc, nr = len(ce) - 1, len(re) - 1
    c0 = np.clip(np.searchsorted(ce, u.min(1), "right") - 1, 0, nc - 1)
    c1 = np.clip(np.searchsorted(ce, u.max(1), "left") - 1, 0, nc - 1)
    r0 = np.clip(np.searchsorted(re, v.min(1), "right") - 1, 0, nr - 1)
    r1 = np.clip(np.searchsorted(re, v.max(1), "left") - 1, 0, nr - 1)
    # (pixel, cell) pairs over each footprint's bounding box of cells
    ncol, nrow = c1 - c0 + 1, r1 - r0 + 1
    cnt = ncol * nrow
    pix = np.repeat(np.arange(p), cnt)
    k = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    cc = c0[pix] + k % ncol[pix]
    rr = r0[pix] + k // ncol[pix]
    blk = cells.black[rr, cc] != 0
    pix, cc, rr = pix[blk], cc[blk], rr[blk]
    pu, pv, n = u[pix], v[pix], four[pix]
    # the padding after each polygon's count may hold inf or NaN (a parallel edge's
    # crossing); it is never read back
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for axis, bound, above in (
            (0, ce[cc], True),
            (0, ce[cc + 1], False),
            (1, re[rr], True),
            (1, re[rr + 1], False),
        ):
            pu, pv, n = _clip(pu, pv, n, axis, bound, above)
    pad = np.arange(pu.shape[1])[None, :] >= n[:, None]
    pu, pv = np.where(pad, pu[:, :1], pu), np.where(pad, pv[:, :1], pv)
    xs, ys = _to_image(pu, pv, s, R, C)
    area = np.where(n >= 3, _shoelace(xs, ys, n), 0.0)
    black = np.zeros(p)
    np.add.at(black, pix, area)
    return np.clip(1.0 - black / full, 0.0, 1.0)
