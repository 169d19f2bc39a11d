"""One pose's pixel work in one fused numba kernel: ROI labels, HDR merge, Bayer-centred
region sums, irradiance geometry and mean directions.

Why hand-written: after the board is found, the numpy path of
:func:`gonio.capture.pose_measure.measure_pose` (:func:`gonio.capture.fiducials.map_regions`,
:func:`gonio.capture.hdr.merge_bracket`, :func:`gonio.capture.bayer.bayer_region_entries`
and the weighted sums) streams ~60 full-size temporaries per pose through memory, ~12 ms
per pose at 1600x1200, which ``benchmarks/reduce.py`` measured as the largest part of the
reduction besides LibRaw's decoding.  This kernel computes the same quantities pixel by
pixel in registers: the labels and the direction sums in the numpy path's operation order
(so the same bit for bit), the merged values and weighted sums with reciprocals taken once
and in another summation order (so the same to rounding, ~1e-15 relative);
``tests/capture/test_pose_kernel.py`` compares the two paths.  The numpy path stays the
reference, and handles what the kernel does not (frames given as linear arrays rather than
a camera mosaic).  ``GONIO_NUMBA=0`` keeps the reduction on numpy.

It runs serially on the calling thread (``nogil``): the reduction decodes the next frames
on the other core meanwhile, and a serial sum is the same for any thread count.  Compiled
code is cached next to this module (``cache=True``, ~3 s cold, once per installation).

With lens distortion the pixels' rays come from the undistorted coordinates computed
once per pose (:func:`gonio.capture.fiducials.undistorted_coordinates`, in ``View``), the
numpy path's own arrays, so the labels and directions stay the same bit for bit; without
it the pinhole expressions run as they always did.

Its inputs come as three namedtuples (:class:`Bracket`, :class:`Stencils`, :class:`View`),
which numba passes as typed structs: named fields instead of 28 positional arguments.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from gonio.capture.hdr import CLIP_GUARD_SIGMAS

_JIT = {"cache": True, "fastmath": False, "error_model": "numpy", "nogil": True}

#: Columns of the per-(region, channel) sums: weight, weight * L, weight^2 * var(L),
#: weight * G, weight * L / G, weight^2 * var(L) / G^2, weight * saturated, weight^2
#: (the last gives a region's effective number of sites, (sum w)^2 / sum w^2, which the
#: radiometric budget needs: :func:`gonio.capture.radiometric.effective_sites`).
SUM_K, SUM_L, SUM_LV, SUM_G, SUM_Q, SUM_QV, SUM_SAT, SUM_K2 = range(8)
#: Columns of the per-(region, channel) sums.
N_SUMS = 8
#: Columns of the per-region direction sums: pixels, sum of wi (3), sum of wo (3).
DIR_N, DIR_WI, DIR_WO = 0, 1, 4
#: Columns of the per-region position sums on the sample plane: x, y (m), and about the
#: region's mean position x x, x y, y y (m^2): :func:`gonio.capture.aperture.region_moments`'
#: sums, in its order (the pixels row by row, the central moments in a second pass), so
#: its centroids and covariances to the bit without the (h, w) rays it needs.
MOM_X, MOM_Y, MOM_XX, MOM_XY, MOM_YY = range(5)


@njit(**_JIT, inline="always")
def _max0(x: float) -> float:
    # np.maximum(x, 0.0): NaN stays NaN
    return 0.0 if x < 0.0 else x


class Bracket(NamedTuple):
    """The pose's frames, cropped to the ROI's box, and the noise model per frame."""

    raws: NDArray[np.uint16]  # (F, h, w) mosaic crops, shortest exposure first
    black: NDArray[np.float64]  # (F, 2, 2) black level per CFA position of the crop
    sat_level: NDArray[np.float64]  # (F, 2, 2) raw value from which a pixel is saturated
    offset: NDArray[np.float64]  # (F, h, w) dark offset, or (F, 0, 0) for none
    gain: NDArray[np.float64]  # (F, h, w) flat-field gain, or (F, 0, 0) for none
    expo: NDArray[np.float64]  # (F,) exposure factors
    noise_gain: NDArray[np.float64]  # (F,) photon-transfer gain at each ISO, DN per electron
    noise_read2: NDArray[np.float64]  # (F,) read noise squared at each ISO, DN^2
    noise_quant: float  # quantisation variance added (0 or 1/12), DN^2
    dark_var: NDArray[np.float64]  # (h, w) variance of the subtracted master dark, or (0, 0)
    dark_var0: float  # its value when constant, DN^2
    mask: NDArray[np.bool_]  # (h, w) hot/dead pixels (unread; weights to neighbours), or (0, 0)


class Stencils(NamedTuple):
    """The CFA layout of the crop and, per CFA position (``2 y + x``), the pixels that
    use a site (:func:`gonio.capture.bayer.site_stencils`)."""

    cell_channel: NDArray[np.int64]  # (2, 2) channel of each CFA position of the crop
    size: NDArray[np.int64]  # (4,) stencil entries per CFA position
    dy: NDArray[np.int64]  # (4, 9) offsets (pixels) ...
    dx: NDArray[np.int64]
    weight: NDArray[np.float64]  # (4, 9) ... and weights


class View(NamedTuple):
    """Where the crop is, what the camera sees through it, and the light."""

    cam: NDArray[np.float64]  # (4,) fx, fy, cx, cy (pixels, OpenCV convention)
    rot: NDArray[np.float64]  # (3, 3) world-to-camera rotation
    cpos: NDArray[np.float64]  # (3,) camera centre, sample frame, metres
    r0: int  # crop origin in the image, pixels
    c0: int
    roi: NDArray[np.float64]  # (8,) half width, half height, cell width, cell height, used
    # half width, used half height (RoiGeometry.limit), margin in a cell along x, along y (m)
    grid: int  # regions along x (per side of a square grid)
    light: NDArray[np.float64]  # (3,) light position, metres
    light_normal: NDArray[np.float64]  # (3,) emitting normal (ignored unless has_normal)
    has_normal: bool
    light_radius: float  # disk radius, metres (0: a point source)
    profile_n: float  # the emitted radiance's cos^n(psi) profile about the normal (0: none)
    n_channels: int
    # A distorting lens: the (h, w) undistorted normalised coordinates of the crop's
    # pixels (gonio.capture.fiducials.undistorted_coordinates), the rays' directions;
    # (0, 0) arrays and False for a pinhole camera, whose rays come from ``cam``.
    ray_x: NDArray[np.float64]
    ray_y: NDArray[np.float64]
    undistorted: bool
    grid_y: int = -1  # regions along y; -1: grid (square)


@njit(**_JIT, inline="always")
def _neighbour(diag: bool, k: int) -> tuple[int, int]:
    """The k-th (0..3) nearest site of a site's own channel, as ``(dy, dx)``; pairs
    (0, 1) and (2, 3) lie symmetrically about it (:func:`gonio.capture.bayer.
    masked_site_shares`)."""
    if diag:
        return ((1, 1), (-1, -1), (1, -1), (-1, 1))[k]
    return ((0, 2), (0, -2), (2, 0), (-2, 0))[k]


@njit(**_JIT)
def _members(qi: int, qj: int, diag: bool, mask) -> int:
    """How many of a masked site's neighbours share its weights: both of a symmetric
    pair, when both are in the crop and not masked."""
    h, w = mask.shape
    n = 0
    for k in (0, 2):
        dy, dx = _neighbour(diag, k)
        ok = True
        for s in (1, -1):
            yy, xx = qi + s * dy, qj + s * dx
            if yy < 0 or yy > h - 1 or xx < 0 or xx > w - 1 or mask[yy, xx]:
                ok = False
        if ok:
            n += 2
    return n


@njit(**_JIT, inline="always")
def _stencil_add(i, j, share, label, st_n, st_dy, st_dx, st_w, regs, wts, nr) -> int:
    """Add site (i, j)'s stencil weights, times ``share``, to the site's regions
    (``regs[:nr]``, ``wts[:nr]``); the new ``nr``."""
    h, w = label.shape
    ps = 2 * (i % 2) + (j % 2)
    for t in range(st_n[ps]):
        yy = i + st_dy[ps, t]
        xx = j + st_dx[ps, t]
        # pixels on the crop's border do not count (their neighbours are unknown)
        if yy < 1 or yy > h - 2 or xx < 1 or xx > w - 2:
            continue
        lab = label[yy, xx]
        if lab < 0:
            continue
        for u in range(nr):
            if regs[u] == lab:
                wts[u] += share * st_w[ps, t]
                break
        else:
            regs[nr] = lab
            wts[nr] = share * st_w[ps, t]
            nr += 1
    return nr


@njit(**_JIT)
def pose_sums(bracket: Bracket, stencils: Stencils, view: View):
    """Region labels of the crop, per-(region, channel) sums and per-region directions.

    Returns ``(label (h, w) int64, sums (n, n_channels, N_SUMS), dirs (n, 7),
    moments (n, 5))``; see :data:`SUM_K`, :data:`DIR_N` and :data:`MOM_X` for the columns.
    """
    # field by field: numba passes a namedtuple as one struct, unpacked here for free
    raws, black, sat_level = bracket.raws, bracket.black, bracket.sat_level
    offset, gain, expo = bracket.offset, bracket.gain, bracket.expo
    noise_gain, noise_read2 = bracket.noise_gain, bracket.noise_read2
    noise_quant = bracket.noise_quant
    dark_var, dark_var0 = bracket.dark_var, bracket.dark_var0
    mask = bracket.mask
    cell_channel, st_n = stencils.cell_channel, stencils.size
    st_dy, st_dx, st_w = stencils.dy, stencils.dx, stencils.weight
    cam, rot, cpos, r0, c0 = view.cam, view.rot, view.cpos, view.r0, view.c0
    roi, grid, light, light_normal = view.roi, view.grid, view.light, view.light_normal
    has_normal, light_radius, n_channels = view.has_normal, view.light_radius, view.n_channels
    ray_x, ray_y, undistorted = view.ray_x, view.ray_y, view.undistorted
    profile_n = view.profile_n
    grid_y = grid if view.grid_y < 0 else view.grid_y
    F, h, w = raws.shape
    n = grid * grid_y
    label = np.full((h, w), -1, np.int64)
    sums = np.zeros((n, n_channels, N_SUMS))
    dirs = np.zeros((n, 7))
    moments = np.zeros((n, 5))
    # the labelled pixels' points, in pass 1's order, for the central moments
    seen_x = np.empty(h * w)
    seen_y = np.empty(h * w)
    seen_r = np.empty(h * w, np.int64)
    n_seen = 0
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    hw, hh, cell_x, cell_y, lim_x, lim_y = roi[0], roi[1], roi[2], roi[3], roi[4], roi[5]
    mx, my = roi[6], roi[7]
    # The per-pixel arithmetic (rays, plane points, directions, the HDR merge and the
    # irradiance geometry) runs a row at a time in branch-free loops over local scalars,
    # which LLVM vectorises (the divisions and square roots are the kernel's cost); the
    # labels and sums then read those rows in the original order.  Every value is the
    # same IEEE expression as before (no contraction: fastmath is off), so the results
    # are the same bit for bit.
    r00, r01, r02 = rot[0, 0], rot[0, 1], rot[0, 2]
    r10, r11, r12 = rot[1, 0], rot[1, 1], rot[1, 2]
    r20, r21, r22 = rot[2, 0], rot[2, 1], rot[2, 2]
    C0, C1, C2 = cpos[0], cpos[1], cpos[2]
    L0, L1, L2 = light[0], light[1], light[2]
    xs = np.empty(w)
    for j in range(w):
        xs[j] = (c0 + j - cx) / fx
    ys = np.empty(h)
    for i in range(h):
        ys[i] = (r0 + i - cy) / fy
    # each row's rays: the pinhole's (xs, and ys[i] in every column) or the undistorted
    row_y = np.empty(w)
    row_p0 = np.empty(w)
    row_p1 = np.empty(w)
    row_fx = np.empty(w)
    row_fy = np.empty(w)
    row_wi = np.empty((3, w))
    row_wo = np.empty((3, w))
    # pass 1: which region each pixel sees (map_regions), and the mean directions
    for i in range(h):
        if undistorted:
            rx = ray_x[i]
            ry = ray_y[i]
        else:
            row_y[:] = ys[i]
            rx = xs
            ry = row_y
        for j in range(w):
            x = rx[j]
            y = ry[j]
            d0 = r00 * x + r10 * y + r20
            d1 = r01 * x + r11 * y + r21
            d2 = r02 * x + r12 * y + r22
            s = -C2 / d2
            p0 = C0 + s * d0
            p1 = C1 + s * d1
            p2 = C2 + s * d2
            row_p0[j] = p0
            row_p1[j] = p1
            row_fx[j] = (p0 + hw) / cell_x
            row_fy[j] = (p1 + hh) / cell_y
            v0 = L0 - p0
            v1 = L1 - p1
            v2 = L2 - p2
            inv = 1.0 / math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            row_wi[0, j] = v0 * inv
            row_wi[1, j] = v1 * inv
            row_wi[2, j] = v2 * inv
            v0 = C0 - p0
            v1 = C1 - p1
            v2 = C2 - p2
            inv = 1.0 / math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            row_wo[0, j] = v0 * inv
            row_wo[1, j] = v1 * inv
            row_wo[2, j] = v2 * inv
        for j in range(w):
            p0 = row_p0[j]
            p1 = row_p1[j]
            ix = math.floor(row_fx[j])
            iy = math.floor(row_fy[j])
            if not (ix >= 0 and ix < grid and iy >= 0 and iy < grid_y):
                continue
            if not (abs(p0) < lim_x and abs(p1) < lim_y):
                continue
            ex = (p0 + hw) - ix * cell_x
            ey = (p1 + hh) - iy * cell_y
            if not (ex >= mx and ex <= cell_x - mx and ey >= my and ey <= cell_y - my):
                continue
            r = int(iy * grid + ix)
            label[i, j] = r
            dirs[r, DIR_N] += 1.0
            moments[r, MOM_X] += p0
            moments[r, MOM_Y] += p1
            seen_x[n_seen] = p0
            seen_y[n_seen] = p1
            seen_r[n_seen] = r
            n_seen += 1
            dirs[r, DIR_WI] += row_wi[0, j]
            dirs[r, DIR_WI + 1] += row_wi[1, j]
            dirs[r, DIR_WI + 2] += row_wi[2, j]
            dirs[r, DIR_WO] += row_wo[0, j]
            dirs[r, DIR_WO + 1] += row_wo[1, j]
            dirs[r, DIR_WO + 2] += row_wo[2, j]
    # the positions' second moments about each region's mean (region_moments' second pass)
    for q in range(n_seen):
        r = seen_r[q]
        dx = seen_x[q] - moments[r, MOM_X] / dirs[r, DIR_N]
        dy = seen_y[q] - moments[r, MOM_Y] / dirs[r, DIR_N]
        moments[r, MOM_XX] += dx * dx
        moments[r, MOM_XY] += dx * dy
        moments[r, MOM_YY] += dy * dy
    # pass 2: every CFA site used by a region (bayer_region_entries), merged and summed
    # a site's own stencil touches <= 9 pixels, and up to 4 masked neighbours give theirs
    regs = np.empty(45, np.int64)
    wts = np.empty(45)
    inv_e = 1.0 / expo
    expo2 = expo * expo  # 1 / var(S / e) = e^2 / var(S)
    N0, N1, N2 = light_normal[0], light_normal[1], light_normal[2]
    nrm = math.sqrt(N0 * N0 + N1 * N1 + N2 * N2)
    rr = light_radius * light_radius
    disk_area = math.pi * rr
    has_offset = offset.shape[1] > 0
    has_gain = gain.shape[1] > 0
    has_dark = dark_var.shape[0] > 0
    has_mask = mask.shape[0] > 0
    has_profile = has_normal and profile_n != 0.0
    has_disk = light_radius > 0.0
    lin = np.empty((F, w))
    clipv = np.empty((F, w))
    g_r0 = np.empty(w)
    g_v = np.empty(w)
    oks = np.empty((F, w), np.bool_)
    sum_s = np.empty(w)
    sum_e = np.empty(w)
    n_ok = np.empty(w, np.int64)
    r0e = np.empty(w)
    wsum = np.empty(w)
    vsum = np.empty(w)
    row_dv = np.empty(w)
    row_val = np.empty(w)
    row_var = np.empty(w)
    row_sat = np.empty(w, np.bool_)
    row_g = np.empty(w)
    row_ig = np.empty(w)
    for i in range(h):
        a = i % 2
        # the HDR merge of the row's sites (merge_bracket), a frame at a time; sums start
        # at +0 and so never are -0, which adding 0.0 for a rejected frame would change
        sum_s[:] = 0.0
        sum_e[:] = 0.0
        n_ok[:] = 0
        for k in range(F):
            raw_k = raws[k, i]
            b0 = black[k, a, 0]
            b1 = black[k, a, 1]
            s0 = sat_level[k, a, 0]
            s1 = sat_level[k, a, 1]
            e_k = expo[k]
            for j in range(w):
                odd = (j & 1) == 1
                q = raw_k[j]
                sk = q - (b1 if odd else b0)
                if has_offset:
                    sk -= offset[k, i, j]
                if has_gain:
                    sk /= gain[k, i, j]
                ok = q < (s1 if odd else s0)
                # the clip in the same units, as RawFrame.clip_region computes it
                cl = (s1 if odd else s0) - (b1 if odd else b0)
                if has_offset:
                    cl -= offset[k, i, j]
                if has_gain:
                    cl /= gain[k, i, j]
                clipv[k, j] = cl
                lin[k, j] = sk
                oks[k, j] = ok
                sum_s[j] += sk if ok else 0.0
                sum_e[j] += e_k if ok else 0.0
                n_ok[j] += 1 if ok else 0
        if has_dark:
            row_dv[:] = dark_var[i]
        else:
            row_dv[:] = dark_var0
        if F > 1:
            # merge_bracket's clip guard (hdr._guard_clips), the same arithmetic per site:
            # a frame whose value expected from the site's same-channel neighbours in the
            # row comes near its clip is left out
            for j in range(w):
                if n_ok[j] > 0:
                    rj = sum_s[j] / sum_e[j]
                    acc = 0.0
                    for k in range(F):
                        if oks[k, j]:
                            sj = rj * expo[k]
                            if sj < 0.0:
                                sj = 0.0
                            acc += noise_gain[k] * sj + noise_read2[k] + noise_quant + row_dv[j]
                    g_r0[j] = rj
                    g_v[j] = acc / (sum_e[j] * sum_e[j])
                else:
                    g_r0[j] = math.inf
                    g_v[j] = 0.0
            # a bound over the row: a frame whose largest possible expected value and
            # spread stay below its smallest clip is left out nowhere in the row (the
            # bound is >= every site's value, each operation being monotone)
            rmax = -math.inf
            vmax = 0.0
            dvmax = 0.0
            for j in range(w):
                rmax = max(rmax, g_r0[j])
                vmax = max(vmax, g_v[j])
                dvmax = max(dvmax, row_dv[j])
            for k in range(F - 1, -1, -1):
                e_k = expo[k]
                pmax = rmax * e_k
                if pmax < 0.0:
                    pmax = 0.0
                cmin = math.inf
                for j in range(w):
                    cmin = min(cmin, clipv[k, j])
                vb = noise_gain[k] * pmax + noise_read2[k] + noise_quant + dvmax
                if pmax + CLIP_GUARD_SIGMAS * math.sqrt(vb + (e_k * e_k) * vmax) < cmin:
                    continue
                for j in range(w):
                    if not oks[k, j] or n_ok[j] < 2:
                        continue
                    left = j >= 2 and not (has_mask and mask[i, j - 2])
                    right = j + 2 < w and not (has_mask and mask[i, j + 2])
                    if left and right:
                        rn = (g_r0[j - 2] + g_r0[j + 2]) / 2.0
                        vn = (g_v[j - 2] + g_v[j + 2]) / 4.0
                    elif left:
                        rn = g_r0[j - 2]
                        vn = g_v[j - 2]
                    elif right:
                        rn = g_r0[j + 2]
                        vn = g_v[j + 2]
                    else:
                        continue
                    p = rn * e_k
                    if p < 0.0:
                        p = 0.0
                    vk = noise_gain[k] * p + noise_read2[k] + noise_quant + row_dv[j]
                    if p + CLIP_GUARD_SIGMAS * math.sqrt(vk + (e_k * e_k) * vn) >= clipv[k, j]:
                        oks[k, j] = False
                        sum_s[j] = sum_s[j] - lin[k, j]
                        sum_e[j] = sum_e[j] - e_k
                        n_ok[j] -= 1
        for j in range(w):
            r0e[j] = sum_s[j] / sum_e[j]
        wsum[:] = 0.0
        vsum[:] = 0.0
        for k in range(F):
            e_k = expo[k]
            e2_k = expo2[k]
            ie_k = inv_e[k]
            g_k = noise_gain[k]
            rn_k = noise_read2[k]
            for j in range(w):
                sig = r0e[j] * e_k
                if sig < 0.0:
                    sig = 0.0
                w_k = e2_k / (g_k * sig + rn_k + noise_quant + row_dv[j])
                ok = oks[k, j]
                wsum[j] += w_k if ok else 0.0
                vsum[j] += w_k * lin[k, j] * ie_k if ok else 0.0
        if undistorted:
            rx = ray_x[i]
            ry = ray_y[i]
        else:
            rx = xs
            ry = row_y
            row_y[:] = ys[i]
        y = ys[i]
        for j in range(w):
            # natural vignetting (1 / cos^4, of the pixel's place on the sensor) and the
            # point this pixel sees (along its undistorted ray when the lens distorts)
            x = xs[j]
            r2 = x * x + y * y + 1.0
            r4 = r2 * r2
            inv_w = 1.0 / wsum[j]
            val = vsum[j] * inv_w * r4
            var = r4 * r4 * inv_w
            sat = n_ok[j] == 0 or not math.isfinite(val)
            row_val[j] = 0.0 if sat else val
            row_var[j] = 0.0 if sat else var
            row_sat[j] = sat
            x = rx[j]
            yy = ry[j]
            d0 = r00 * x + r10 * yy + r20
            d1 = r01 * x + r11 * yy + r21
            d2 = r02 * x + r12 * yy + r22
            s = -C2 / d2
            v0 = L0 - (C0 + s * d0)
            v1 = L1 - (C1 + s * d1)
            v2 = L2 - (C2 + s * d2)
            # irradiance_geometry (surface normal +z: cos = v2 / d, over d^2), the emitter's
            # cosine when it has a normal, and the disk's finite-size factor
            # A d^2 / (d^2 + r^2), as one numerator over one denominator
            dd = v0 * v0 + v1 * v1 + v2 * v2
            num = _max0(v2)
            if has_normal:
                cos_e = _max0(-(v0 * N0 + v1 * N1 + v2 * N2))
                num *= cos_e
                den = dd * dd * nrm
                if has_profile:  # the emitted radiance's cos^n(psi) about the normal
                    num *= (cos_e / (math.sqrt(dd) * nrm)) ** profile_n
            else:
                den = dd * math.sqrt(dd)
            if has_disk:
                num *= disk_area * dd
                den *= dd + rr
            row_g[j] = num / den
            row_ig[j] = den / num
        for j in range(w):
            # a hot or dead pixel's site weighs nothing in any region (not "saturated");
            # its weights go to its channel's neighbours (bayer.masked_site_shares)
            if has_mask and mask[i, j]:
                continue
            b = j % 2
            nr = _stencil_add(i, j, 1.0, label, st_n, st_dy, st_dx, st_w, regs, wts, 0)
            if has_mask:
                diag = cell_channel[a, b] == cell_channel[1 - a, 1 - b]
                for k in range(4):
                    dy, dx = _neighbour(diag, k)
                    qi, qj = i + dy, j + dx
                    if qi < 0 or qi > h - 1 or qj < 0 or qj > w - 1 or not mask[qi, qj]:
                        continue
                    # this site's pair, seen from q: q - (dy, dx) (this one), q + (dy, dx)
                    pi, pj = qi + dy, qj + dx
                    if pi < 0 or pi > h - 1 or pj < 0 or pj > w - 1 or mask[pi, pj]:
                        continue
                    n_q = _members(qi, qj, diag, mask)
                    nr = _stencil_add(
                        qi, qj, 1.0 / n_q, label, st_n, st_dy, st_dx, st_w, regs, wts, nr
                    )
            if nr == 0:
                continue
            val = row_val[j]
            var = row_var[j]
            sat = row_sat[j]
            g = row_g[j]
            inv_g = row_ig[j]
            c = cell_channel[a, b]
            for u in range(nr):
                wt = wts[u]
                r = regs[u]
                sums[r, c, SUM_K] += wt
                sums[r, c, SUM_K2] += wt * wt
                sums[r, c, SUM_L] += wt * val
                sums[r, c, SUM_LV] += wt * wt * var
                sums[r, c, SUM_G] += wt * g
                sums[r, c, SUM_Q] += wt * val * inv_g
                sums[r, c, SUM_QV] += wt * wt * var * (inv_g * inv_g)
                if sat:
                    sums[r, c, SUM_SAT] += wt
    return label, sums, dirs, moments


@njit(**_JIT)
def undistort_pixels(r0, c0, cam, dist, x_out, y_out):
    """Normalised undistorted coordinates of a crop's pixel centres, by Newton's method.

    ``cam`` is (fx, fy, cx, cy) in pixels, ``dist`` the five OpenCV coefficients (k1, k2,
    p1, p2, k3); ``x_out``, ``y_out`` (h, w) receive the coordinates ``(X / Z, Y / Z)``
    whose Brown-Conrady image is each pixel centre ``(c0 + j, r0 + i)``.  The caller
    checks the round trip (:func:`gonio.capture.fiducials.undistorted_coordinates`).
    """
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    h, w = x_out.shape
    for i in range(h):
        yd = (r0 + i - cy) / fy
        for j in range(w):
            xd = (c0 + j - cx) / fx
            x = xd
            y = yd
            for _ in range(30):
                r2 = x * x + y * y
                rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                drad = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3))  # d rad / d(x, y) / (x, y)
                ex = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
                ey = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
                a = rad + drad * x * x + 2.0 * p1 * y + 6.0 * p2 * x
                b = drad * x * y + 2.0 * p1 * x + 2.0 * p2 * y
                d = rad + drad * y * y + 6.0 * p1 * y + 2.0 * p2 * x
                det = a * d - b * b
                sx = (d * ex - b * ey) / det
                sy = (a * ey - b * ex) / det
                x -= sx
                y -= sy
                if abs(sx) + abs(sy) < 1e-15:
                    break
            x_out[i, j] = x
            y_out[i, j] = y
