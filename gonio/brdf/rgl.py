"""Evaluate RGL-EPFL measured BRDFs stored in the adaptive parameterisation.

Dupuy & Jakob, "An Adaptive Parameterization for Efficient Material Acquisition and
Rendering", ACM TOG 37(6), 2018.  A material is tabulated not over directions but over the
unit square of *sample space*: the space in which the measured visible-normal distribution
(VNDF) of the micro-facets is uniform.  Evaluating ``f(wi, wo)`` therefore means

1. the half vector ``m = normalize(wi + wo)`` in spherical coordinates, mapped to the unit
   square by ``u = (sqrt(theta_m / (pi/2)), (phi_m - phi_i + pi) / 2pi)`` (the square-root
   spends resolution near the normal, where specular lobes live; isotropic files store
   ``phi_m`` relative to ``phi_i``);
2. the *inverse* of the VNDF sampling warp, which takes ``u`` to its position in sample
   space.  The forward warp samples the bilinear interpolant of the tabulated VNDF by
   inverting its marginal CDF (over ``phi_m``) and then its conditional CDF (over
   ``theta_m``), both continuous (Mitsuba's ``Marginal2D<..., Continuous=true>``); the
   inverse therefore just *evaluates* those two CDFs at ``u``
   (:meth:`RGLBRDF._invert_vndf`);
3. a bilinear look-up of the RGB table at that position, linearly interpolated between the
   tabulated incident elevations ``theta_i`` (and azimuths ``phi_i`` when anisotropic);
4. when the ``jacobian`` flag is set, the factor ``D(m) / (4 sigma(wi))`` (NDF over
   projected area) that turns the stored, sample-space-smooth quantity into ``f cos``.

The stored quantity is ``f_r cos(theta_o)`` (what Mitsuba's ``measured`` BSDF returns), so
``eval`` divides by ``cos(theta_o)`` to honour gonio's convention of returning ``f_r``.
Mitsuba's implementation (``src/bsdfs/measured.cpp`` + ``include/mitsuba/core/distr_2d.h``)
is the reference this module is tested against; this is an independent vectorised float64
numpy formulation of the same mathematics: the marginal/conditional CDFs are precomputed
per slice once, and parameter interpolation is applied to the tables themselves (not to
the result of the inversion), as the reference does.
"""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.errors import FileFormatError
from gonio.radiometry.frames import flat_pairs

__all__ = ["RGLBRDF", "read_rgl"]

Array = NDArray[np.float64]

_HALF_PI = 0.5 * np.pi
# Divisions by constants are multiplications by their reciprocals in both paths (within an
# ulp of the quotient; a division costs ~4x a multiplication in the kernel's throughput).
_INV_HALF_PI = 1.0 / _HALF_PI
_INV_2PI = 0.5 / np.pi
# Batch sizes for the numba kernel (see gonio.brdf.microfacet for the same two thresholds).
_MIN_FUSED = 4096
_FIRST_FUSED = 100_000


# The arctangent of the angles: libm's atan2 costs ~60 ns a call on the benchmark machine
# (four calls a pair: more than Mitsuba's whole evaluation), so both paths compute it as
# atan(t) = atan(t0) + atan(d), t0 = k / ATAN_NODES the nearest table node and
# d = (t - t0) / (1 + t t0), |d| <= 1 / (2 ATAN_NODES), by its series to d^7 (the next term
# is below 1e-22 of d).  Within 2 ulp of the correctly rounded value (tests/brdf/
# test_rgl_eval.py holds it to libm), and the same IEEE operations in numpy and numba, so
# the two paths agree bit for bit.
ATAN_NODES = 256
ATAN_TABLE = np.array([math.atan(k / ATAN_NODES) for k in range(ATAN_NODES + 1)])
ATAN_C3, ATAN_C5, ATAN_C7 = -1.0 / 3.0, 1.0 / 5.0, -1.0 / 7.0


def _atan01(t: Array) -> Array:
    """``arctan(t)`` for ``t`` in [0, 1]."""
    k = (t * ATAN_NODES + 0.5).astype(np.intp)
    t0 = k * (1.0 / ATAN_NODES)
    d = (t - t0) / (1.0 + t * t0)
    z = d * d
    return ATAN_TABLE[k] + (d + d * z * (ATAN_C3 + z * (ATAN_C5 + z * ATAN_C7)))


def _atan2_pos(y: Array, x: Array) -> Array:
    """``arctan2(y, x)`` for ``y, x >= 0`` (0 for 0, 0)."""
    hi = np.maximum(x, y)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(hi > 0.0, np.minimum(x, y) / hi, 0.0)
    a = _atan01(t)
    return np.where(y > x, _HALF_PI - a, a)


def _atan2(y: Array, x: Array) -> Array:
    """``arctan2(y, x)`` with libm's signs of zero (atan2(+-0, -0) = +-pi)."""
    a = _atan2_pos(np.abs(y), np.abs(x))
    a = np.where(np.signbit(x), np.pi - a, a)
    return np.copysign(a, y)


def _elevation(v: Array) -> Array:
    # 2 asin(|v - z| / 2) instead of acos(v_z): accurate near the normal, where acos of a
    # value close to 1 loses half the digits (and sqrt(theta) magnifies that error).  It is
    # Mitsuba's formula, which matters for directions that are unit only to float32
    # precision.  The asin is taken as the arctangent of s / sqrt(1 - s^2).
    s = np.clip(0.5 * np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + (v[..., 2] - 1.0) ** 2), 0.0, 1.0)
    return 2.0 * _atan2_pos(s, np.sqrt((1.0 - s) * (1.0 + s)))


def _param_lerp(values: Array, x: Array) -> tuple[NDArray[np.intp], Array]:
    """Index of the interval of ``values`` holding ``x`` and the clamped weight of its end.

    A single tabulated value means "constant": index 0, weight 0.
    """
    n = values.size
    if n == 1:
        return np.zeros(x.shape, np.intp), np.zeros(x.shape)
    i = np.clip(np.searchsorted(values, x, side="left") - 1, 0, n - 2)
    inv = 1.0 / np.diff(values)  # a multiplication per query instead of a division
    w = np.clip((x - values[i]) * inv[i], 0.0, 1.0)
    return i, w


class _Slices:
    """Four (phi_i, theta_i) corners and their bilinear weights for a batch of queries."""

    def __init__(self, phi_vals: Array, theta_vals: Array, phi: Array, theta: Array) -> None:
        ip, wp = _param_lerp(phi_vals, phi)
        it, wt = _param_lerp(theta_vals, theta)
        n_t = theta_vals.size
        it1 = np.minimum(it + 1, n_t - 1)
        self.index = [ip * n_t + it, ip * n_t + it1]
        self.weight = [(1 - wp) * (1 - wt), (1 - wp) * wt]
        if phi_vals.size > 1:  # isotropic files have one phi_i: skip the zero-weight corners
            ip1 = np.minimum(ip + 1, phi_vals.size - 1)
            self.index += [ip1 * n_t + it, ip1 * n_t + it1]
            self.weight += [wp * (1 - wt), wp * wt]

    def take(self, rows: Array, cell: NDArray[np.intp]) -> Array:
        """Parameter-interpolated packed entries: ``sum_k w_k rows[:, slice_k, cell]``.

        ``rows`` has shape (K, slices, cells): K packed quantities, each flattened per
        slice.  Returns (K, n) with contiguous rows.  ``np.take`` on flat indices is ~5x
        faster than multi-array fancy indexing, which dominated the evaluation time.
        """
        k, n_slices, n_cells = rows.shape
        flat_rows = rows.reshape(k, n_slices * n_cells)
        out = np.zeros((k, cell.size))
        for s, w in zip(self.index, self.weight, strict=True):
            flat = s * n_cells + cell
            for j in range(k):
                out[j] += w * np.take(flat_rows[j], flat)
        return out


def _rows_equal(table: Array) -> bool:
    """Whether all rows of a 2-D ``table[y, x]`` (leading axes flattened into y) are equal."""
    rows = table.reshape(-1, table.shape[-1])
    return bool(np.all(rows == rows[:1]))


def _lerp_x(table: Array, x: Array) -> Array:
    """Linear interpolation along x of a table whose rows are all equal (its first row):
    :func:`_bilinear` without the blend of two equal rows (nodes at ``k / (n - 1)``,
    positions clamped to [0, 1])."""
    nx = table.shape[-1]
    px = np.clip(x, 0.0, 1.0) * (nx - 1)
    ix = np.minimum(px.astype(np.intp), nx - 2)
    fx = px - ix
    row = table.reshape(-1)[:nx]
    return (1 - fx) * np.take(row, ix) + fx * np.take(row, ix + 1)


def _bilinear(table: Array, x: Array, y: Array) -> Array:
    """Bilinear interpolation of a 2-D ``table[y, x]`` at unit-square positions (x, y).

    Nodes sit at ``k / (n - 1)``; positions are clamped to [0, 1] (Mitsuba's ``eval``).
    """
    ny, nx = table.shape[-2:]
    px = np.clip(x, 0.0, 1.0) * (nx - 1)
    py = np.clip(y, 0.0, 1.0) * (ny - 1)
    ix = np.minimum(px.astype(np.intp), nx - 2)
    iy = np.minimum(py.astype(np.intp), ny - 2)
    fx, fy = px - ix, py - iy
    flat = table.reshape(-1)
    i00 = iy * nx + ix
    v00 = np.take(flat, i00)
    v10 = np.take(flat, i00 + 1)
    v01 = np.take(flat, i00 + nx)
    v11 = np.take(flat, i00 + nx + 1)
    return (1 - fy) * ((1 - fx) * v00 + fx * v10) + fy * ((1 - fx) * v01 + fx * v11)


class RGLBRDF:
    """A measured RGL-EPFL material (``*.bsdf``, tensor_file v1.0).

    Use :func:`gonio.brdf.load` (or :func:`read_rgl`) to create one.

    Attributes
    ----------
    format : str
        ``"rgl"``.
    description : str
        The material description stored in the file.
    metadata : dict
        ``path``, ``spectral``, ``isotropic``, ``jacobian``, ``theta_i_deg`` (tabulated
        incident elevations), ``phi_i_deg``, ``resolution`` (sample-space grid),
        ``vndf_resolution``, ``wavelengths_nm`` (spectral files), ``valid_fraction``.
    """

    format = "rgl"

    def __init__(self, path: str | Path, fields: dict[str, np.ndarray]) -> None:
        self.path = Path(path)
        _validate(self.path, fields)
        f64 = {k: np.asarray(v, dtype=np.float64) for k, v in fields.items()}
        self.spectral = "wavelengths" in fields
        self.description = bytes(np.asarray(fields["description"])).decode("utf-8", "replace")
        self.theta_i = f64["theta_i"]
        self.phi_i = f64["phi_i"]
        self.isotropic = self.phi_i.size <= 2
        self.jacobian = bool(fields["jacobian"][0])
        # Anisotropic files store one "wedge" of phi_i; 2 or 4 is how many mirror images
        # make up the full circle (Mitsuba's m_reduction).
        self.reduction = 0
        if not self.isotropic:
            span = self.phi_i[-1] - self.phi_i[0]
            self.reduction = int(np.rint(2 * np.pi / span))
        self._ndf = f64["ndf"]
        self._sigma = f64["sigma"]
        # Isotropic files with one phi_i and a projected area that does not vary with
        # phi_i (all rows equal: every file seen) need no incident azimuth at all: only
        # the half vector's azimuth relative to it, one arctangent instead of two.
        self._relative_only = self.phi_i.size == 1 and _rows_equal(self._sigma)
        # An NDF or projected area with all rows equal (isotropic: no dependence on the
        # azimuth) is interpolated along theta alone, half the look-ups of the bilinear
        self._ndf_flat = _rows_equal(self._ndf)
        self._sigma_flat = _rows_equal(self._sigma)
        vndf = f64["vndf"]
        n_phi, n_theta, h, w = vndf.shape
        self._vndf_shape = (h, w)
        vndf_n, cond, marg, self._vndf_norm = _marginal_tables(vndf.reshape(-1, h, w))
        self._vndf_raw = np.asarray(fields["vndf"], dtype=np.float32)  # for the kernel
        patch = _patch_table(vndf_n, cond, marg)
        # rows = packed quantities, then (slice, patch) flattened: see _Slices.take
        self._patch = np.ascontiguousarray(
            patch.reshape(patch.shape[0], -1, patch.shape[-1]).transpose(2, 0, 1)
        )
        spec = f64["spectra"] if self.spectral else f64["rgb"]
        n_ch, ry, rx = spec.shape[2:]
        # slice = phi_i index * n_theta + theta_i index
        spec = spec.reshape(n_phi * n_theta, n_ch, ry, rx)
        # rows (corner, channel) x (slice, patch): the 4 corner nodes of every bilinear
        # patch, so that one flat index per slice fetches a whole look-up
        corners = [spec[..., :-1, :-1], spec[..., :-1, 1:], spec[..., 1:, :-1], spec[..., 1:, 1:]]
        self._n_ch = n_ch
        self._spec_grid = (ry, rx)
        self._spec = np.ascontiguousarray(
            np.stack(corners, axis=0).transpose(0, 2, 1, 3, 4).reshape(4 * n_ch, len(spec), -1)
        )
        self.wavelengths = f64["wavelengths"] if self.spectral else None
        self._kernel_tables: tuple[Array, ...] | None = None  # built on first fused use
        valid = fields.get("valid")
        self.metadata: dict[str, Any] = {
            "path": str(self.path),
            "spectral": self.spectral,
            "isotropic": self.isotropic,
            "jacobian": self.jacobian,
            "theta_i_deg": np.degrees(self.theta_i).round(3).tolist(),
            "phi_i_deg": np.degrees(self.phi_i).round(3).tolist(),
            "resolution": (int(ry), int(rx)),
            "vndf_resolution": (int(h), int(w)),
            "channels": int(n_ch),
        }
        if self.spectral:
            self.metadata["wavelengths_nm"] = self.wavelengths.tolist()
        if valid is not None:
            bits = np.unpackbits(np.asarray(valid, dtype=np.uint8))
            self.metadata["valid_fraction"] = float(bits.mean())

    # ------------------------------------------------------------------ evaluation
    def eval(self, wi: ArrayLike, wo: ArrayLike) -> Array:
        """RGB BRDF value ``f_r(wi, wo)`` in 1/sr.

        Parameters
        ----------
        wi, wo
            Unit directions (towards light, towards camera) in the sample frame, shape
            ``(..., 3)``; broadcast against each other.

        Returns
        -------
        ndarray, shape ``broadcast(wi, wo)[:-1] + (3,)``
            0 where either direction is at or below the horizon; NaN for NaN (or
            infinite) input.

        Raises
        ------
        FileFormatError
            For spectral files (only RGB files can be evaluated to RGB here).
        """
        if self.spectral:
            raise FileFormatError(
                self.path,
                "spectral RGL file: RGB evaluation is not supported (use eval_channels for "
                f"the {len(self.wavelengths)} tabulated wavelengths, or the *_rgb.bsdf file)",
                field="spectra",
            )
        return self.eval_channels(wi, wo)

    def eval_channels(self, wi: ArrayLike, wo: ArrayLike) -> Array:
        """``f_r`` for every stored channel (3 for RGB files, one per wavelength otherwise)."""
        wi, wo, shape = flat_pairs(wi, wo)
        n_ch = self._n_ch
        if (fused := self._eval_fused(wi, wo)) is not None:  # the horizon and NaN included
            return fused.reshape(*shape, n_ch)
        out = np.zeros((wi.shape[0], n_ch))
        nan = ~(np.isfinite(wi).all(-1) & np.isfinite(wo).all(-1))
        active = (wi[:, 2] > 0) & (wo[:, 2] > 0) & ~nan
        if active.size and active.all():  # common: no copies of the inputs
            # C order, as the kernel and the masked path return it: a caller's sum over
            # the values (an einsum, directional_albedo) rounds by their layout, so the
            # same values must come in one layout whichever path made them
            out = np.ascontiguousarray(self._eval_active(wi, wo))
        elif active.any():
            out[active] = self._eval_active(wi[active], wo[active])
        out[nan] = np.nan
        return out.reshape(*shape, n_ch)

    def _eval_active(self, wi: Array, wo: Array) -> Array:
        wi = wi.copy()
        wo = wo.copy()
        if self.reduction >= 2:
            # The file holds one wedge of incident azimuths; mirror both directions into it
            # (the sign conventions of Mitsuba's mulsign_neg: flip where the sign is >= 0).
            sy = np.where(wi[:, 1] >= 0, -1.0, 1.0)
            sx = np.where(wi[:, 0] >= 0, -1.0, 1.0) if self.reduction == 4 else sy
            wi[:, 0] *= sx
            wi[:, 1] *= sy
            wo[:, 0] *= sx
            wo[:, 1] *= sy
        # the half vector's angles need no normalisation of wi + wo
        m = wi + wo
        theta_i = _elevation(wi)
        theta_m = _atan2_pos(np.sqrt(m[:, 0] * m[:, 0] + m[:, 1] * m[:, 1]), m[:, 2])
        if self._relative_only:
            # phi_m - phi_i as the azimuth of m in the frame of wi's azimuth; at normal
            # incidence (no azimuth) the convention phi_i = atan2(wi_y, wi_x) stays
            phi_i = np.zeros(len(wi))  # sigma's rows are equal: any phi_i gives the same
            rel = _atan2(
                m[:, 1] * wi[:, 0] - m[:, 0] * wi[:, 1], m[:, 0] * wi[:, 0] + m[:, 1] * wi[:, 1]
            )
            normal = (wi[:, 0] == 0) & (wi[:, 1] == 0)
            if normal.any():
                mn, wn = m[normal], wi[normal]
                rel[normal] = _atan2(mn[:, 1], mn[:, 0]) - _atan2(wn[:, 1], wn[:, 0])
        else:
            phi_i = _atan2(wi[:, 1], wi[:, 0])
            phi_m = _atan2(m[:, 1], m[:, 0])
            rel = phi_m - phi_i if self.isotropic else phi_m

        u_wi = (np.sqrt(theta_i * _INV_HALF_PI), (phi_i + np.pi) * _INV_2PI)
        um_y = (rel + np.pi) * _INV_2PI
        um_y -= np.floor(um_y)
        u_m = (np.sqrt(theta_m * _INV_HALF_PI), um_y)

        sl = _Slices(self.phi_i, self.theta_i, phi_i, theta_i)
        sx_, sy_ = self._invert_vndf(sl, *u_m)

        # Bilinear over the sample-space position, multilinear over (phi_i, theta_i).
        ry, rx = self._spec_grid
        px = np.clip(sx_, 0.0, 1.0) * (rx - 1)
        py = np.clip(sy_, 0.0, 1.0) * (ry - 1)
        ix = np.minimum(px.astype(np.intp), rx - 2)
        iy = np.minimum(py.astype(np.intp), ry - 2)
        fx, fy = px - ix, py - iy
        corner_w = ((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy)
        v = sl.take(self._spec, iy * (rx - 1) + ix).reshape(4, self._n_ch, -1)
        spec = sum(w * v[k] for k, w in enumerate(corner_w)).T  # (n, channels)
        wo_z = wo[:, 2]
        if self.jacobian:
            # The table stores a quantity smooth in sample space; the NDF over the
            # projected area restores f cos(theta_o) (paper, eq. for the Jacobian of the
            # VNDF warp: D(m) / (4 sigma(wi)), with sigma the projected-area normaliser).
            ndf = _lerp_x(self._ndf, u_m[0]) if self._ndf_flat else _bilinear(self._ndf, *u_m)
            sigma = (
                _lerp_x(self._sigma, u_wi[0]) if self._sigma_flat else _bilinear(self._sigma, *u_wi)
            )
            scale = ndf / (4.0 * sigma * wo_z)  # and f cos / cos: one division a pair
        else:
            scale = 1.0 / wo_z
        return spec * scale[:, None]

    def _eval_fused(self, wi: Array, wo: Array) -> Array | None:
        """``eval_channels`` of flat pairs by the numba kernel of :mod:`gonio.brdf.kernels`
        (same arithmetic; it also gives the horizon's 0 and the NaN of non-finite input, so
        no masks or copies are made here), or None for small batches or ``GONIO_NUMBA=0``.

        Same lazy rule as the microfacet lobes: numba is first imported by a batch of
        ``_FIRST_FUSED`` pairs, so that small evaluations never pay its load time."""
        n = wi.shape[0]
        if n < _MIN_FUSED or os.environ.get("GONIO_NUMBA") == "0":
            return None
        if n < _FIRST_FUSED and "gonio.brdf.kernels" not in sys.modules:
            return None
        from gonio.brdf import kernels

        if self._kernel_tables is None:
            self._kernel_tables = self.kernel_tables()
        out = np.empty((n, self._n_ch))
        (h, w), (ry, rx) = self._vndf_shape, self._spec_grid
        kernels.rgl_eval(
            kernels.readonly(np.ascontiguousarray(wi)),
            kernels.readonly(np.ascontiguousarray(wo)),
            self.phi_i,
            self.theta_i,
            *self._kernel_tables,
            h,
            w,
            ry,
            rx,
            self.reduction,
            self.isotropic,
            self._relative_only,
            self.jacobian,
            ATAN_TABLE,
            out,
        )
        return out

    def kernel_tables(self) -> tuple[Any, ...]:
        """The tables of :func:`gonio.brdf.kernels.rgl_eval`, built from the numpy path's.

        Slices last, so that the two theta_i slices a pair blends are adjacent (slice
        ``s`` and ``s + 1``; theta_i is padded to two slices when the file has one);
        values the file holds in float32 stay float32 (exact), the derived CDFs float64.
        What one pair reads is packed in records, so that a pair touches one or two cache
        lines per table instead of one per value (the tables do not fit in L2: the
        gathers' cache misses were the kernel's largest cost):

        - ``rec32`` / ``rec64``: two views of one 64-byte-aligned buffer of 32-byte
          records, one per (VNDF cell, slice): float32 slots 0-3 the cell's corner
          densities (00, 10, 01, 11, as in the file), float64 slots 2-3 the normalised
          conditional CDF before the cell in its lower and upper row;
        - ``rows[y, slice]``: the two row totals of row ``y``'s patches, the marginal CDF
          before the row and the slice's normalisation;
        - ``spec``: per (RGB cell, slice) a record of ``spec_stride`` float32 (a multiple
          of 16: 64-byte lines), the four corners of every channel, corner-major (RGB
          with a fourth, zero channel: the kernel's vector lanes).

        Returns ``(n_t2, rec32, rec64, rows, spec, spec_stride, ndf, sigma)``.
        """
        n_p, n_t = self.phi_i.size, self.theta_i.size
        n_t2 = max(n_t, 2)
        # slice index of the kernel's tables -> slice of the numpy tables
        src = (np.arange(n_p)[:, None] * n_t + np.minimum(np.arange(n_t2), n_t - 1)).ravel()
        n_s = src.size
        h, w = self._vndf_shape
        vndf = self._vndf_raw.reshape(n_p * n_t, h, w)[src].transpose(1, 2, 0)  # (h, w, s)
        # conditional CDF before each column: the packed patches' lower rows, and the
        # upper row of the last patch row for the top VNDF row
        lower = self._patch[4][src].reshape(n_s, h - 1, w - 1)
        upper = self._patch[5][src].reshape(n_s, h - 1, w - 1)
        cdf = np.empty((h, w - 1, n_s))
        cdf[:-1] = lower.transpose(1, 2, 0)
        cdf[-1] = upper[:, -1].T
        n_cells = (h - 1) * (w - 1)
        buf = _aligned_bytes(n_cells * n_s * 32)
        rec32 = buf.view(np.float32)
        rec64 = buf.view(np.float64)
        r32 = rec32.reshape(h - 1, w - 1, n_s, 8)
        r64 = rec64.reshape(h - 1, w - 1, n_s, 4)
        r32[..., 0] = vndf[:-1, :-1]
        r32[..., 1] = vndf[:-1, 1:]
        r32[..., 2] = vndf[1:, :-1]
        r32[..., 3] = vndf[1:, 1:]
        r64[..., 2] = cdf[:-1]
        r64[..., 3] = cdf[1:]
        first = np.arange(h - 1) * (w - 1)  # the first patch of each VNDF row
        rows = np.empty((h - 1, n_s, 4))
        for j, r in enumerate((6, 7, 8)):
            rows[:, :, j] = self._patch[r][src][:, first].T
        rows[:, :, 3] = self._vndf_norm[src][None, :]
        n_ch = self._n_ch
        cs = 4 if n_ch == 3 else n_ch  # RGB padded to 4 channel slots per corner
        corners = self._spec[:, src, :].transpose(2, 1, 0)  # (cells, slices, 4 n_ch)
        n_rc = corners.shape[0]
        stride = -(-4 * cs // 16) * 16
        spec = _aligned_bytes(n_rc * n_s * stride * 4).view(np.float32)
        spec[:] = 0.0
        rec = spec.reshape(n_rc, n_s, stride)[..., : 4 * cs].reshape(n_rc, n_s, 4, cs)
        rec[..., :n_ch] = corners.reshape(n_rc, n_s, 4, n_ch)
        ndf = np.ascontiguousarray(self._ndf.reshape(self._ndf.shape[-2:]))
        sigma = np.ascontiguousarray(self._sigma.reshape(self._sigma.shape[-2:]))
        return n_t2, rec32, rec64, rows, spec, stride, ndf, sigma

    def _invert_vndf(self, sl: _Slices, ux: Array, uy: Array) -> tuple[Array, Array]:
        """Inverse of the continuous marginal/conditional warp of the VNDF table.

        For the bilinear interpolant ``p(x, y)`` of the (per-slice normalised) VNDF, with
        ``x`` the ``theta_m`` axis and ``y`` the ``phi_m`` axis, the sample ``(sx, sy)`` that
        the forward warp maps to ``(x, y)`` is ``sy = int_0^y int_0^1 p dx' dy'`` (marginal
        CDF over y) and ``sx = int_0^x p(x', y) dx' / int_0^1 p(x', y) dx'`` (conditional
        CDF along x at height ``y``; ``p`` is linear in ``y`` inside a patch, so it is the
        linear blend of the cumulative tables of the two bounding rows).  Within a patch
        both integrals of a (bi)linear function are quadratic, so they are evaluated
        exactly from the patch corners plus the cumulative tables of whole patches.
        Tables are interpolated over (phi_i, theta_i) before use, as in the reference.
        """
        h, w = self._vndf_shape
        px = np.clip(ux, 0.0, 1.0) * (w - 1)
        py = np.clip(uy, 0.0, 1.0) * (h - 1)
        ix = np.minimum(px.astype(np.intp), w - 2)
        iy = np.minimum(py.astype(np.intp), h - 2)
        fx, fy = px - ix, py - iy
        packed = sl.take(self._patch, iy * (w - 1) + ix)
        v00, v10, v01, v11, prev0, prev1, r0, r1, marg_prev = packed

        c0 = v00 + (v01 - v00) * fy
        c1 = v10 + (v11 - v10) * fy
        # integral of the linear segment c0 -> c1 over [0, fx] (patch width 1/(w-1)), plus
        # the whole patches to the left of it in this row (blend of the bounding rows)
        sx = fx * (c0 + (c1 - c0) * 0.5 * fx) * (1.0 / (w - 1)) + prev0 + (prev1 - prev0) * fy
        row = r0 + (r1 - r0) * fy
        with np.errstate(invalid="ignore", divide="ignore"):
            sx = np.where(row > 0, sx / row, fx)
        sy = fy * (r0 + (r1 - r0) * 0.5 * fy) * (1.0 / (h - 1)) + marg_prev
        return sx, sy

    # ------------------------------------------------------------------ integrals
    def albedo(self, theta_i: ArrayLike) -> Array:
        """Directional albedo ``int f_r cos(theta_o) dw_o`` at incident elevations (rad).

        Returns
        -------
        ndarray, shape ``theta_i.shape + (3,)``
        """
        from gonio.brdf.measured import directional_albedo

        return directional_albedo(self.eval, theta_i)

    def __repr__(self) -> str:
        return f"RGLBRDF({str(self.path)!r}, {self.description!r})"


def _marginal_tables(vndf: Array) -> tuple[Array, Array, Array, Array]:
    """Per-slice normalised VNDF, conditional CDFs (rows), marginal CDF (over rows) and the
    normalisation factor of each slice.

    ``vndf`` has shape (slices, h, w) with x (theta_m) along the last axis.  Integrals are
    trapezoidal over the bilinear interpolant on the unit square (patch sizes 1/(w-1) and
    1/(h-1)); each slice is scaled to integrate to 1.
    """
    s, h, w = vndf.shape
    cond = np.cumsum(0.5 * (vndf[:, :, :-1] + vndf[:, :, 1:]), axis=2) / (w - 1)  # (s, h, w-1)
    rows = cond[:, :, -1]
    marg = np.cumsum(0.5 * (rows[:, :-1] + rows[:, 1:]), axis=1) / (h - 1)  # (s, h-1)
    total = marg[:, -1]
    with np.errstate(divide="ignore"):
        norm = np.where(total > 0, 1.0 / total, 0.0)
    return vndf * norm[:, None, None], cond * norm[:, None, None], marg * norm[:, None], norm


def _patch_table(vndf: Array, cond: Array, marg: Array) -> Array:
    """Everything the VNDF inversion reads for one bilinear patch, packed per patch.

    Returns shape (slices, h-1, w-1, 9): the 4 corner densities (00, 10, 01, 11), the
    conditional CDF before the patch in its lower and upper row (0 for the first column),
    the row totals of those two rows, and the marginal CDF before the patch's row.  All
    entries are linear in the tables, so interpolating packed rows over (phi_i, theta_i)
    equals interpolating the tables, and one gather per slice replaces nine.
    """
    s, h, w = vndf.shape
    cprev = np.concatenate([np.zeros((s, h, 1)), cond[:, :, :-1]], axis=2)  # (s, h, w-1)
    mprev = np.concatenate([np.zeros((s, 1)), marg[:, :-1]], axis=1)  # (s, h-1)
    shape = (s, h - 1, w - 1)
    parts = [
        vndf[:, :-1, :-1],
        vndf[:, :-1, 1:],
        vndf[:, 1:, :-1],
        vndf[:, 1:, 1:],
        cprev[:, :-1, :],
        cprev[:, 1:, :],
        np.broadcast_to(cond[:, :-1, -1:], shape),
        np.broadcast_to(cond[:, 1:, -1:], shape),
        np.broadcast_to(mprev[:, :, None], shape),
    ]
    return np.ascontiguousarray(np.stack(parts, axis=-1))


def _aligned_bytes(n: int, align: int = 64) -> NDArray[np.uint8]:
    """``n`` bytes starting on an ``align``-byte boundary (a cache line): numpy aligns to
    16 only, and a record that straddles two lines costs two cache misses."""
    raw = np.empty(n + align, np.uint8)
    off = -raw.ctypes.data % align
    return raw[off : off + n]


_REQUIRED = ("theta_i", "phi_i", "ndf", "sigma", "vndf", "luminance", "description", "jacobian")


def _validate(path: Path, f: dict[str, np.ndarray]) -> None:
    """Structure checks of Mitsuba's ``measured`` plugin, plus value checks."""

    def err(field: str, msg: str) -> FileFormatError:
        return FileFormatError(path, msg, field=field)

    for name in _REQUIRED:
        if name not in f:
            raise err(name, f"required field is missing (fields present: {', '.join(f)})")
    spectral = "wavelengths" in f
    data_name = "spectra" if spectral else "rgb"
    if data_name not in f:
        what = "a 'spectra' field (the file has 'wavelengths')" if spectral else "an 'rgb' field"
        raise err(data_name, f"required field is missing: expected {what}")

    def check(name: str, ndim: int, dtype: str) -> np.ndarray:
        a = f[name]
        if a.ndim != ndim or a.dtype != np.dtype(dtype):
            raise err(
                name,
                f"expected a {ndim}-d {np.dtype(dtype).name} array, got shape {a.shape} "
                f"{a.dtype.name}",
            )
        return a

    check("description", 1, "u1")
    theta = check("theta_i", 1, "<f4")
    phi = check("phi_i", 1, "<f4")
    ndf = check("ndf", 2, "<f4")
    sigma = check("sigma", 2, "<f4")
    vndf = check("vndf", 4, "<f4")
    lum = check("luminance", 4, "<f4")
    spec = check(data_name, 5, "<f4")
    jac = check("jacobian", 1, "u1")
    if jac.shape != (1,):
        raise err("jacobian", f"expected shape (1,), got {jac.shape}")
    n_phi, n_theta = phi.size, theta.size
    if n_theta < 1 or n_phi < 1:
        raise err("theta_i", "theta_i and phi_i need at least one value each")
    for name, a in (("vndf", vndf), ("luminance", lum), (data_name, spec)):
        if a.shape[:2] != (n_phi, n_theta):
            raise err(
                name,
                f"leading dimensions {a.shape[:2]} do not match (len(phi_i), len(theta_i)) "
                f"= {(n_phi, n_theta)}",
            )
    if lum.shape[2] != lum.shape[3]:
        raise err("luminance", f"expected a square N x N grid, got {lum.shape[2:]}")
    if spec.shape[3:] != lum.shape[2:]:
        raise err(data_name, f"grid {spec.shape[3:]} differs from luminance {lum.shape[2:]}")
    if spectral:
        wl = check("wavelengths", 1, "<f4")
        if spec.shape[2] != wl.size:
            raise err("spectra", f"{spec.shape[2]} channels but {wl.size} wavelengths")
    elif spec.shape[2] != 3:
        raise err("rgb", f"expected 3 colour channels, got {spec.shape[2]}")
    for name, a in (("ndf", ndf), ("sigma", sigma), ("vndf", vndf)):
        if min(a.shape[-2:]) < 2:
            raise err(name, f"interpolation grid must be at least 2 x 2, got {a.shape[-2:]}")
    if min(spec.shape[3:]) < 2:
        raise err(data_name, "interpolation grid must be at least 2 x 2")
    for name, a in (("theta_i", theta), ("phi_i", phi)):
        if not np.all(np.isfinite(a)):
            raise err(name, "contains NaN or infinite values")
        if a.size > 1 and np.any(np.diff(a) <= 0):
            raise err(name, "values must be strictly increasing")
    if theta.min() < 0 or theta.max() > _HALF_PI + 1e-5:
        raise err("theta_i", f"values must lie in [0, pi/2] rad, got {theta.min()}..{theta.max()}")
    if n_phi > 2:
        span = float(phi[-1] - phi[0])
        red = 2 * np.pi / span
        if not any(abs(red - k) < 1e-3 for k in (1, 2, 4)):
            raise err(
                "phi_i",
                f"anisotropic phi_i must span 2pi, pi or pi/2 (got {np.degrees(span):.3f} deg)",
            )
    for name, a in (("ndf", ndf), ("sigma", sigma), ("vndf", vndf), ("luminance", lum)):
        if not np.all(np.isfinite(a)):
            raise err(name, "contains NaN or infinite values")
        if np.any(a < 0):
            raise err(name, f"contains negative values (min {a.min():.4g}); densities are >= 0")
    if not np.all(np.isfinite(spec)):
        raise err(data_name, "contains NaN or infinite values")
    if np.any(sigma <= 0):
        raise err("sigma", "projected areas must be > 0 (they divide the NDF)")
    if np.any(vndf.reshape(n_phi * n_theta, -1).sum(axis=1) <= 0):
        raise err("vndf", "a (phi_i, theta_i) slice is all zero; it cannot be inverted")


def read_rgl(path: str | Path) -> RGLBRDF:
    """Read an RGL-EPFL ``*.bsdf`` file (strict; :class:`FileFormatError` on any defect)."""
    from gonio.brdf.tensor_file import read_tensor_file

    return RGLBRDF(path, read_tensor_file(path))
