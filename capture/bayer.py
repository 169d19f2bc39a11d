"""Which CFA sites a region's mean uses, and with what weight, per colour channel.

A region's pixels sample each channel at its own CFA sites only, half a pixel away from
the region's centroid for R and B; :func:`bayer_region_weights` spreads every pixel's unit
weight over its nearest sites of each channel (the adjoint of bilinear interpolation), so
every channel of a region is measured at the same centroid.  Used by the numpy path of
:func:`gonio.capture.pose_measure.measure_pose`; the fused kernel
(:mod:`gonio.capture.pose_kernel`) walks the same stencils (:func:`site_stencils`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "bayer_region_entries",
    "bayer_region_weights",
    "masked_site_shares",
    "site_stencils",
]


def bayer_region_weights(
    label: NDArray[np.integer],
    channel: NDArray[np.integer],
    n_regions: int,
    n_channels: int = 3,
) -> tuple[Any, NDArray[np.intp]]:
    """Weights of each CFA site in each region's mean, per channel, centred on the region.

    A region's pixels sample R and B at one site per 2x2 cell, G at two; the plain mean
    over a region's R pixels is centred half a pixel up-left of the region's pixel
    centroid (B down-right), while the region's directions are those of the centroid.
    On a lobe's flank that half pixel is a bias of the order of the noise (measured:
    z-score std 1.10-1.13 in R and B, 1.01 in G, at 640x480, 6x6 regions), and a region
    one or two pixels high at grazing angles may hold no R or B site at all.  Instead
    every pixel p of the region contributes a unit weight per channel: to itself when its
    filter passes the channel, else shared equally by its nearest sites of that channel
    (the 2 or 4 edge neighbours, or else the 4 diagonal ones), which lie symmetrically
    around p.  That is the adjoint of bilinear interpolation: the weighted mean is the
    region's mean of the channel bilinearly interpolated to every pixel, exact for any
    linear variation, so every channel is measured at the same centroid.  Sites shared by
    neighbouring pixels get larger weights; the variance of the mean is
    ``sum_q W_q^2 var_q / (sum_q W_q)^2`` over the independent sites q.

    Parameters
    ----------
    label
        (h, w) region index of each pixel, -1 outside every region.  Pixels on the
        crop's border (whose neighbours are unknown) are left out.
    channel
        (h, w) channel index of each pixel (a 2x2-periodic CFA).
    n_regions, n_channels
        Number of regions and channels.

    Returns
    -------
    A : scipy.sparse matrix
        (n_regions * n_channels, len(used)) weights; row ``r * n_channels + c``.  The row
        sum is the region's pixel count.
    used : ndarray
        Flat indices (into the (h, w) crop) of the sites the columns refer to.
    """
    from scipy.sparse import csr_matrix

    site, row, weight = bayer_region_entries(label, channel, n_regions, n_channels)
    used, col = np.unique(site, return_inverse=True)
    A = csr_matrix((weight, (row, col.ravel())), shape=(n_regions * n_channels, used.size))
    return A, used


def site_stencils(
    cell: NDArray[np.integer], n_channels: int
) -> dict[tuple[int, int], list[tuple[int, int, float]]]:
    """The pixels that use each CFA site for the site's own channel.

    Parameters
    ----------
    cell
        (2, 2) channel index of each CFA position (the pattern's 2x2 cell).
    n_channels
        Number of channels.

    Returns
    -------
    dict
        For each CFA position ``(y0, x0)`` of a site, ``[(dy, dx, weight), ...]``: the
        offsets (pixels) from the site of the pixels using it, and their weights (the
        weights of :func:`bayer_region_weights` seen from the site instead of the pixel).
    """
    edge = ((0, 1), (0, -1), (1, 0), (-1, 0))
    diag = ((1, 1), (1, -1), (-1, 1), (-1, -1))
    out: dict[tuple[int, int], list[tuple[int, int, float]]] = {
        (a, b): [] for a in range(2) for b in range(2)
    }
    for a in range(2):
        for b in range(2):
            for c in range(n_channels):
                if cell[a, b] == c:
                    offs: list[tuple[int, int]] = [(0, 0)]
                else:
                    offs = [o for o in edge if cell[(a + o[0]) % 2, (b + o[1]) % 2] == c]
                    offs = offs or [o for o in diag if cell[(a + o[0]) % 2, (b + o[1]) % 2] == c]
                for dy, dx in offs:
                    # pixel (a, b) uses the site at (a + dy, b + dx): seen from the site,
                    # the pixel sits at (-dy, -dx)
                    out[((a + dy) % 2, (b + dx) % 2)].append((-dy, -dx, 1.0 / len(offs)))
    return out


def bayer_region_entries(
    label: NDArray[np.integer],
    channel: NDArray[np.integer],
    n_regions: int,
    n_channels: int = 3,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """The non-zero weights of :func:`bayer_region_weights` as ``(site, row, weight)``.

    Each (site, row) pair appears once, its weight summed over the region's pixels that
    use the site, so a region's weighted sum of ``x`` is
    ``np.bincount(row, weight * x[site])`` (and its variance uses ``weight**2``).

    Built site by site rather than pixel by pixel: a site of channel c is used by the
    pixels of a fixed 3x3 stencil around it (the adjoint of bilinear interpolation), so
    its weight in a region is the stencil's weight over its neighbours in that region,
    one OpenCV 3x3 filter of the "pixel counts" mask; the region is the neighbours' label
    (a 3x3 dilation).  Assembling a sparse matrix pixel by pixel, which has to sum ~7
    duplicates per pixel, cost more than the rest of the pose.  A site with neighbours
    in two regions (a boundary closer than the margin map_regions keeps) gets one entry
    per region, computed neighbour by neighbour.

    Returns
    -------
    site : ndarray
        (m,) flat indices into the (h, w) crop.
    row : ndarray
        (m,) ``region * n_channels + channel``.
    weight : ndarray
        (m,) weights; per row they sum to the region's pixel count.
    """
    import cv2

    lab = np.asarray(label)
    h, w = lab.shape
    cell = np.asarray(channel)[:2, :2]
    if h < 3 or w < 3:  # no pixel with all its neighbours in the crop
        return np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0)
    # Labels of the pixels that count, padded by one so that a site's stencil never
    # leaves the array; pixels on the crop's border (neighbours unknown) do not count.
    # float32 holds labels exactly (to 2^24) and is what OpenCV's filters take.
    P = np.full((h + 2, w + 2), -1, np.float32)
    P[2:h, 2:w] = lab[1:-1, 1:-1]
    counts = (P >= 0).astype(np.float32)
    P_low = np.where(P >= 0, P, np.float32(np.inf))
    filtered: dict[bytes, tuple[NDArray, NDArray, NDArray]] = {}
    sites, rows, weights = [], [], []
    o_sites, o_rows, o_weights = [], [], []
    for (y0, x0), stencil in site_stencils(cell, n_channels).items():
        if y0 >= h or x0 >= w or not stencil:
            continue
        c = int(cell[y0, x0])
        kernel = np.zeros((3, 3), np.float32)
        for dy, dx, wt in stencil:
            kernel[1 + dy, 1 + dx] = wt  # powers of 2: the filtered sums are exact
        key = kernel.tobytes()
        if key not in filtered:
            el = (kernel > 0).astype(np.uint8)
            filtered[key] = (
                cv2.filter2D(counts, -1, kernel, borderType=cv2.BORDER_CONSTANT),
                cv2.dilate(P, el),  # highest label among the neighbours
                cv2.erode(P_low, el),  # lowest (inf: none)
            )
        wsum, top, low = (a[1 + y0 : 1 + h : 2, 1 + x0 : 1 + w : 2] for a in filtered[key])
        nx = top.shape[1]
        keep = np.flatnonzero((top >= 0) & (low == top))
        iy, ix = np.divmod(keep, nx)
        sites.append((y0 + 2 * iy) * w + x0 + 2 * ix)
        rows.append(top.ravel()[keep].astype(np.intp) * n_channels + c)
        weights.append(wsum.ravel()[keep].astype(np.float64))
        mixed = np.flatnonzero(low < top)
        if mixed.size:
            my, mx = np.divmod(mixed, nx)
            for dy, dx, wt in stencil:
                L = P[1 + y0 + 2 * my + dy, 1 + x0 + 2 * mx + dx]
                ok = L >= 0
                o_sites.append((y0 + 2 * my[ok]) * w + x0 + 2 * mx[ok])
                o_rows.append(L[ok].astype(np.intp) * n_channels + c)
                o_weights.append(np.full(int(ok.sum()), wt))
    if o_sites:
        # one entry per (site, row): several neighbours of a site may share the region
        n_rows = n_regions * n_channels
        key, inv = np.unique(
            np.concatenate(o_sites) * n_rows + np.concatenate(o_rows), return_inverse=True
        )
        sites.append(key // n_rows)
        rows.append(key % n_rows)
        weights.append(np.bincount(inv.ravel(), np.concatenate(o_weights)))
    if not sites:
        return np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0)
    return (
        np.concatenate(sites).astype(np.intp, copy=False),
        np.concatenate(rows).astype(np.intp, copy=False),
        np.concatenate(weights),
    )


#: The nearest sites of a site's own channel, in symmetric pairs: a channel at one site of
#: each 2x2 cell (R, B) has them 2 px along the rows and columns, one at two sites (G)
#: on the diagonals.
_AXIAL_PAIRS = (((0, 2), (0, -2)), ((2, 0), (-2, 0)))
_DIAGONAL_PAIRS = (((1, 1), (-1, -1)), ((1, -1), (-1, 1)))


def masked_site_shares(
    site: NDArray[np.intp],
    row: NDArray[np.intp],
    weight: NDArray[np.float64],
    mask: NDArray[np.bool_],
    channel: NDArray[np.integer],
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """:func:`bayer_region_entries`' entries with the masked (hot, dead) sites' weights
    handed to their channel's nearest sites.

    A masked site cannot be read, and dropping its weights moves the channel's weighted
    centroid off the region's (the centring :func:`bayer_region_weights` makes): on a
    steep gradient of a region a few sites wide (grazing views near a highlight, one
    pixel ~3 mm of sample) that was a 1-3 % error in one channel.  Its weight goes to
    its channel's nearest sites in symmetric pairs (both of a pair in the crop and not
    masked), equally: the bilinear interpolation of the missing site from them, so the
    channel is measured at the same centroid, exactly for a linear variation.  A masked
    site with no whole pair around it is dropped as before.

    Parameters
    ----------
    site, row, weight
        The entries (one per (site, row)).
    mask
        (h, w) the crop's masked pixels.
    channel
        (h, w) channel index of each pixel of the crop.

    Returns
    -------
    site, row, weight
        One entry per (site, row) again (weights of a site summed), masked sites left out.
    """
    msk = np.asarray(mask, bool)
    h, w = msk.shape
    flat = msk.reshape(-1)
    hit = flat[site]
    if not hit.any():
        return site, row, weight
    cell = np.asarray(channel)[:2, :2]
    q, r, wq = site[hit], row[hit], weight[hit]
    qy, qx = np.divmod(q, w)
    diag = cell[qy % 2, qx % 2] == cell[(qy + 1) % 2, (qx + 1) % 2]
    members = []  # (flat index, whole pair available) of the 4 neighbours
    n_ok = np.zeros(q.size)
    for p in range(2):
        both = np.ones(q.size, bool)
        pair = []
        for m in range(2):
            dy = np.where(diag, _DIAGONAL_PAIRS[p][m][0], _AXIAL_PAIRS[p][m][0])
            dx = np.where(diag, _DIAGONAL_PAIRS[p][m][1], _AXIAL_PAIRS[p][m][1])
            yy, xx = qy + dy, qx + dx
            inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
            idx = np.where(inside, yy * w + xx, 0)
            ok = inside & ~flat[idx]
            both &= ok
            pair.append(idx)
        n_ok += 2 * both
        members += [(idx, both) for idx in pair]
    keep = ~hit
    sites, rows, weights = [site[keep]], [row[keep]], [weight[keep]]
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(n_ok > 0, wq / n_ok, 0.0)
    for idx, ok in members:
        sites.append(idx[ok])
        rows.append(r[ok])
        weights.append(share[ok])
    s_all, r_all, w_all = np.concatenate(sites), np.concatenate(rows), np.concatenate(weights)
    # one entry per (site, row): a site's own weight and its shares are one weight (its
    # square, not the sum of squares, is what the variance takes)
    key = r_all.astype(np.int64) * (h * w) + s_all
    uniq, inv = np.unique(key, return_inverse=True)
    w_sum = np.bincount(inv.ravel(), w_all, minlength=uniq.size)
    return (uniq % (h * w)).astype(np.intp), (uniq // (h * w)).astype(np.intp), w_sum
