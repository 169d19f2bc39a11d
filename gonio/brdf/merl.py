"""MERL BRDF database files (``*.binary``): read, write byte-exactly, evaluate, resample.

Matusik, Pfister, Brand, McMillan, "A Data-Driven Reflectance Model", SIGGRAPH 2003.
Layout (little-endian, as written by the reference ``BRDFRead.cpp``)::

    int32 x 3      dimensions (90, 90, 180): theta_h, theta_d, phi_d bins
    float64 x 3N   N = 90*90*180 values per channel, channels R, G, B one after the other,
                   each C-ordered [theta_h][theta_d][phi_d]

A stored value times the channel scale (1/1500, 1.15/1500, 1.66/1500) is f_r in 1/sr;
a negative value marks a configuration that was not measured.  Coordinates are
Rusinkiewicz's half/difference angles; the bins are

* ``theta_h``: index ``i`` <-> ``theta_h = (i / 90)^2 * 90 deg`` (square-root spacing,
  dense near the specular peak);
* ``theta_d``: index ``j`` <-> ``j`` degrees;
* ``phi_d``: index ``k`` <-> ``k`` degrees in [0, 180): reciprocity makes
  ``f(phi_d) = f(phi_d + 180 deg)`` (swapping wi and wo adds 180 deg), so half is stored.

The reference look-up truncates to the bin index (nearest-lower node).  :meth:`MERLBRDF.eval`
offers that (``interpolation="nearest"``) and, by default, trilinear interpolation between
the nodes above (periodic in ``phi_d``), which is continuous and exact at the nodes.
Hand-written: no maintained Python package reads or writes this format.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.atomic import write_bytes_atomic
from gonio.errors import FileFormatError
from gonio.radiometry.frames import (
    directions_from_half_diff,
    flat_pairs,
    half_diff_from_directions,
)

__all__ = [
    "DIMS",
    "SCALES",
    "MERLBRDF",
    "read_merl",
    "write_merl",
    "resample",
    "looks_like_merl",
    "bin_angles",
    "indices_reference",
]

Array = NDArray[np.float64]

DIMS = (90, 90, 180)
SCALES = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
_N = DIMS[0] * DIMS[1] * DIMS[2]
_HEADER = np.array(DIMS, dtype="<i4").tobytes()
FILE_SIZE = 12 + 3 * _N * 8  # 34,992,012 bytes


def looks_like_merl(head: bytes, size: int) -> bool:
    """Whether a file's first bytes look like a MERL header (three small positive int32).

    Deliberately lenient (the size and the exact dimensions are not checked) so that a
    truncated or odd-sized MERL file is routed to :func:`read_merl`, whose error then says
    precisely what is wrong.
    """
    if len(head) < 12 or size < 12:
        return False
    dims = np.frombuffer(head[:12], dtype="<i4")
    return bool(np.all((dims >= 1) & (dims <= 100_000)))


def bin_angles() -> tuple[Array, Array, Array]:
    """Angles (rad) of the table nodes: ``theta_h`` (90), ``theta_d`` (90), ``phi_d`` (180)."""
    i = np.arange(DIMS[0])
    theta_h = (i / 90.0) ** 2 * (np.pi / 2)
    theta_d = np.arange(DIMS[1]) * (np.pi / 2) / 90.0
    phi_d = np.arange(DIMS[2]) * np.pi / 180.0
    return theta_h, theta_d, phi_d


def _continuous_index(theta_h: Array, theta_d: Array, phi_d: Array) -> tuple[Array, Array, Array]:
    # theta_h index: sqrt(theta_h_deg * 90) = 90 sqrt(theta_h / (pi/2)) (the format's
    # non-linear mapping); phi_d folded to [0, pi) by reciprocity.
    uh = 90.0 * np.sqrt(np.clip(theta_h, 0.0, None) / (np.pi / 2))
    ud = theta_d / (np.pi / 2) * 90.0
    up = np.mod(phi_d, np.pi) / np.pi * 180.0
    return uh, ud, up


def indices_reference(theta_h: ArrayLike, theta_d: ArrayLike, phi_d: ArrayLike) -> tuple:
    """Integer bin indices exactly as the reference ``BRDFRead.cpp`` computes them.

    ``phi_d`` in (-pi, pi]: negative values get +pi, then ``int(phi_d / pi * 180)``;
    every index is clamped to its range.
    """
    theta_h = np.asarray(theta_h, dtype=np.float64)
    theta_d = np.asarray(theta_d, dtype=np.float64)
    phi_d = np.asarray(phi_d, dtype=np.float64)
    th_deg = theta_h / (np.pi / 2) * 90.0
    ih = np.where(theta_h <= 0, 0, np.sqrt(np.clip(th_deg * 90.0, 0, None)).astype(np.intp))
    ih = np.clip(ih, 0, DIMS[0] - 1)
    idd = np.clip((theta_d / (np.pi / 2) * 90.0).astype(np.intp), 0, DIMS[1] - 1)
    pd = np.where(phi_d < 0, phi_d + np.pi, phi_d)
    ip = np.clip((pd / np.pi * 180.0).astype(np.intp), 0, DIMS[2] - 1)
    return ih, idd, ip


class MERLBRDF:
    """A MERL-format isotropic BRDF table.

    Parameters
    ----------
    raw
        Stored values, shape ``(3, 90, 90, 180)`` (channel, theta_h, theta_d, phi_d), before
        the channel scales; negative = missing.  Kept bit-for-bit so that writing the file
        back reproduces it exactly.
    path, description
        Where it came from and a human-readable name.
    """

    format = "merl"

    def __init__(
        self, raw: ArrayLike, path: str | Path | None = None, description: str | None = None
    ) -> None:
        raw = np.asarray(raw, dtype=np.float64)
        if raw.shape != (3, *DIMS):
            raise ValueError(f"MERL table must have shape (3, 90, 90, 180), got {raw.shape}")
        self.raw = raw
        self.path = Path(path) if path is not None else None
        self.description = description or (self.path.stem if self.path else "MERL BRDF")
        missing = raw < 0
        self.metadata: dict[str, Any] = {
            "path": str(self.path) if self.path else None,
            "dimensions": {"theta_h": DIMS[0], "theta_d": DIMS[1], "phi_d": DIMS[2]},
            "channel_scales": SCALES.tolist(),
            "missing_fraction": float(missing.mean()),
        }
        # f_r table with missing entries as NaN, for interpolation with renormalised weights
        f = np.where(missing, np.nan, raw * SCALES[:, None, None, None])
        # (node, channel) rows: one gather per corner fetches the three channels
        self._f = np.ascontiguousarray(f.reshape(3, -1).T)

    def eval(self, wi: ArrayLike, wo: ArrayLike, interpolation: str = "linear") -> Array:
        """RGB ``f_r(wi, wo)`` in 1/sr.

        Parameters
        ----------
        wi, wo
            Unit directions in the sample frame, shape ``(..., 3)``, broadcast together.
        interpolation
            ``"linear"`` (trilinear between the table nodes, periodic in ``phi_d``; missing
            nodes are left out and the remaining weights renormalised) or ``"nearest"`` (the
            reference look-up: truncation to the bin index).

        Returns
        -------
        ndarray, shape ``broadcast(wi, wo)[:-1] + (3,)``
            0 below the horizon and where every contributing node is missing; NaN for NaN
            input.
        """
        wi, wo, shape = flat_pairs(wi, wo)
        with np.errstate(invalid="ignore"):
            th, _, td, pd = half_diff_from_directions(wi, wo)
        nan = np.isnan(wi).any(-1) | np.isnan(wo).any(-1)
        active = (wi[:, 2] > 0) & (wo[:, 2] > 0) & ~nan
        out = np.zeros((wi.shape[0], 3))
        if active.any():
            th, td, pd = th[active], td[active], pd[active]
            if interpolation == "nearest":
                ih, idd, ip = indices_reference(th, td, pd)
                v = self._f[(ih * DIMS[1] + idd) * DIMS[2] + ip]
                out[active] = np.nan_to_num(v, nan=0.0)
            elif interpolation == "linear":
                out[active] = self._trilinear(th, td, pd)
            else:
                raise ValueError(
                    f"interpolation must be 'linear' or 'nearest', got {interpolation!r}"
                )
        out[nan] = np.nan
        return out.reshape(*shape, 3)

    def _trilinear(self, th: Array, td: Array, pd: Array) -> Array:
        uh, ud, up = _continuous_index(th, td, pd)
        uh = np.clip(uh, 0, DIMS[0] - 1)
        ud = np.clip(ud, 0, DIMS[1] - 1)
        ih = np.minimum(uh.astype(np.intp), DIMS[0] - 2)
        idd = np.minimum(ud.astype(np.intp), DIMS[1] - 2)
        ip = np.minimum(up.astype(np.intp), DIMS[2] - 1)
        fh, fd, fp = uh - ih, ud - idd, up - ip
        ip1 = (ip + 1) % DIMS[2]  # phi_d is periodic with period 180 deg
        acc = np.zeros((th.size, 3))
        wsum = np.zeros((th.size, 3))
        for a, wa in ((ih, 1 - fh), (ih + 1, fh)):
            for b, wb in ((idd, 1 - fd), (idd + 1, fd)):
                row = (a * DIMS[1] + b) * DIMS[2]
                wab = wa * wb
                for c, wc in ((ip, 1 - fp), (ip1, fp)):
                    v = self._f[row + c]  # (n, 3)
                    ok = ~np.isnan(v)
                    w = np.where(ok, (wab * wc)[:, None], 0.0)
                    acc += np.where(ok, v, 0.0) * w
                    wsum += w
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(wsum > 0, acc / wsum, 0.0)

    def albedo(self, theta_i: ArrayLike) -> Array:
        """Directional albedo at incident elevations ``theta_i`` (rad), shape ``(..., 3)``."""
        from gonio.brdf.measured import directional_albedo

        return directional_albedo(self.eval, theta_i)

    def write(self, path: str | Path) -> None:
        """Write the table as a MERL binary (see :func:`write_merl`)."""
        write_merl(path, self)

    def __repr__(self) -> str:
        return f"MERLBRDF({self.description!r})"


def read_merl(path: str | Path) -> MERLBRDF:
    """Read a MERL ``*.binary`` file.

    Raises
    ------
    FileFormatError
        Unreadable, wrong header dimensions, wrong size (truncated or trailing bytes),
        NaN or infinite values.
    """
    path = Path(path)
    try:
        buf = path.read_bytes()
    except OSError as exc:
        raise FileFormatError(path, f"cannot read file: {exc.strerror or exc}") from exc
    if len(buf) < 12:
        raise FileFormatError(
            path, f"file too small for the MERL header ({len(buf)} bytes, needs 12)"
        )
    dims = tuple(int(d) for d in np.frombuffer(buf, dtype="<i4", count=3))
    if dims != DIMS:
        raise FileFormatError(
            path,
            f"header dimensions are {dims}, expected {DIMS} (theta_h, theta_d, phi_d)",
            field="header",
        )
    if len(buf) != FILE_SIZE:
        what = "truncated" if len(buf) < FILE_SIZE else "has trailing bytes"
        raise FileFormatError(
            path,
            f"file {what}: {len(buf)} bytes, expected {FILE_SIZE} (12-byte header + 3 x "
            f"{_N} float64)",
            field="data",
        )
    raw = np.frombuffer(buf, dtype="<f8", offset=12).reshape(3, *DIMS)
    bad = ~np.isfinite(raw)
    if bad.any():
        ch, i, j, k = (int(x[0]) for x in np.nonzero(bad))
        raise FileFormatError(
            path,
            f"{int(bad.sum())} non-finite values (first: channel {'RGB'[ch]}, theta_h bin {i}, "
            f"theta_d bin {j}, phi_d bin {k}); expected finite values, negative for missing",
            field="data",
        )
    return MERLBRDF(raw.copy(), path=path)


def write_merl(path: str | Path, brdf: MERLBRDF, *, replace: bool = True) -> None:
    """Write ``brdf.raw`` as a MERL binary (header + float64, little-endian), atomically.

    The file is written to a temporary name beside ``path`` and renamed, so an existing
    file is never left half-written; ``replace=False``: a file at ``path`` by then (another
    writer's) is kept and ``FileExistsError`` raised (:func:`gonio.atomic.atomic_path`).
    """
    data = np.ascontiguousarray(brdf.raw, dtype="<f8").tobytes()
    write_bytes_atomic(path, _HEADER + data, replace=replace)


def resample(
    brdf: Any,
    params: Mapping[str, Any] | None = None,
    description: str | None = None,
    symmetrize: bool = True,
    chunk: int = 262_144,
    progress: Callable[[int, int], None] | None = None,
) -> MERLBRDF:
    """Tabulate any BRDF on the MERL grid.

    Parameters
    ----------
    brdf
        An object with ``eval(wi, wo) -> (..., 3)`` (a measured file, a bound model), or an
        analytic model from :func:`gonio.brdf.get_model` together with ``params``.
    params
        Model parameters, when ``brdf`` is an unbound model (bound with ``model.bind``).
    description
        Stored as the result's description.
    symmetrize
        Store ``(f(wi, wo) + f(wo, wi)) / 2``.  The MERL layout can only hold reciprocal
        BRDFs (it folds ``phi_d`` onto [0, 180) deg); measured sources are only
        approximately reciprocal, and the symmetric part is the closest reciprocal BRDF
        (in the least-squares sense).  Reciprocal models are unchanged by it.
    chunk
        Direction pairs evaluated per call (memory bound).
    progress
        Called as ``progress(done, total)`` after each chunk (for progress bars).

    Returns
    -------
    MERLBRDF
        Values at the table nodes (``bin_angles``) with ``phi_h = 0``; nodes whose ``wi``
        or ``wo`` is below the horizon are marked missing (-1), as in measured files.
        Negative values (RGB conversions of measured spectra dip slightly below 0) are
        clamped to 0, since the format reserves negative numbers for "missing".
    """
    if params is not None:
        brdf = brdf.bind(params)
    th, td, pd = bin_angles()
    TH, TD, PD = np.meshgrid(th, td, pd, indexing="ij")
    wi, wo = directions_from_half_diff(TH.ravel(), 0.0, TD.ravel(), PD.ravel())
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    up = np.flatnonzero(~below)  # only nodes above the horizon are evaluated
    f = np.zeros((wi.shape[0], 3))
    for s in range(0, up.size, chunk):
        idx = up[s : s + chunk]
        a, b = wi[idx], wo[idx]
        v = np.asarray(brdf.eval(a, b), dtype=np.float64)[..., :3]
        if symmetrize:
            v = 0.5 * (v + np.asarray(brdf.eval(b, a), dtype=np.float64)[..., :3])
        f[idx] = v
        if progress is not None:
            progress(min(s + chunk, up.size), up.size)
    # A node the source cannot evaluate (NaN/inf) is stored as missing rather than
    # written as a value every MERL reader would choke on; the count is kept in metadata.
    bad = ~np.isfinite(f).all(axis=1)
    raw = np.maximum(f, 0.0) / SCALES
    raw[below | bad] = -1.0
    raw = raw.T.reshape(3, *DIMS)
    if description is None:
        description = f"resampled {getattr(brdf, 'description', type(brdf).__name__)}"
    out = MERLBRDF(raw, description=description)
    out.metadata["nonfinite_nodes"] = int(bad.sum())
    return out
