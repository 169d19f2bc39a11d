"""Per-texel BRDF samples and their HDF5 file, ``texels.h5`` (issue 18, item 2).

A spatially varying reduction measures every texel of the sample in every pose: ``T``
texels times ``P`` poses.  ``texels.h5`` holds them as ``(T, P, ...)`` datasets chunked
along the texels only, so that a worker fitting texels ``t0 .. t1`` reads whole chunks of
that hyperslab and nothing else (HDF5 rather than Zarr: h5py is already a dependency and
one file opens in any HDF5 tool, where Zarr adds a dependency and a directory of many
small files).

Texel convention
----------------
The sample rectangle (sample frame, metres: x in [-w/2, w/2], y in [-h/2, h/2]) is divided
into ``nx x ny`` equal texels; texel ``(row, col)`` has row 0 at +y and column 0 at -x
(the orientation of the simulator's ``sample.albedo_map``), flat index
``t = row * nx + col``, centre ``x = -w/2 + (col + 0.5) w / nx``,
``y = h/2 - (row + 0.5) h / ny``.

File layout (schema ``gonio.texels``, version 1)
------------------------------------------------
Root attributes: ``schema``, ``schema_version``, ``channels`` (C,), ``texels`` [nx, ny],
``sample_size`` [w, h] (m), ``orientation`` ("row 0 at +y, column 0 at -x"), ``session``,
``created``, ``calibration_rel_std`` (C,) (the shared calibration scale, as in
``samples.h5``), ``units`` (JSON: what ``radiance``/``irradiance`` hold, if stored),
``chunk_texels``, and free-form provenance.

=========================  ==============  =====  ==========================================
name                       shape           units  meaning
=========================  ==============  =====  ==========================================
``wi``, ``wo``             (T, P, 3)       1      unit directions, sample frame (NaN: none)
``brdf``, ``brdf_std``     (T, P, C)       1/sr   f_r per channel and its std
``flags``                  (T, P)          bits   :class:`gonio.dataset.Flag`; a texel/pose
                                                  with no sample: ``INVALID`` and NaN
``pose``                   (P,)            int32  journal pose of column p
``budget/<term>``          (T, P, C)       1/sr   optional, :data:`gonio.dataset.BUDGET_TERMS`
``budget`` attributes      (C,)            1      shared terms (relative std)
``geometry_modes``         (T, P, M, 6)    1      optional, as in ``samples.h5``
``geometry_mode_scope``    (M,)            str    ``"session"`` or ``"pose"``
``geometry_mode_names``    (M,)            str    what each mode is
``radiance``               (T, P, C)       attr   optional
``irradiance``             (T, P, C)       attr   optional
=========================  ==============  =====  ==========================================

Every ``(T, ...)`` dataset is chunked ``(chunk_texels, P, ...)`` (:func:`chunk_texels_for`).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.atomic import atomic_path
from gonio.dataset import (
    BUDGET_TERMS,
    DEFAULT_UNITS,
    MODE_SCOPES,
    SHARED_BUDGET_TERMS,
    UNIT_TOLERANCE,
    BRDFSamples,
    Flag,
)
from gonio.errors import FileFormatError

__all__ = [
    "ORIENTATION",
    "SCHEMA",
    "SCHEMA_VERSION",
    "TEXELS_FILE",
    "TexelFile",
    "chunk_texels_for",
    "open_texels",
    "save_texels",
    "texel_centers",
]

SCHEMA = "gonio.texels"
SCHEMA_VERSION = 1
TEXELS_FILE = "texels.h5"
ORIENTATION = "row 0 at +y, column 0 at -x"
#: Target bytes of one chunk of the largest dataset.  h5py's default chunk cache per
#: dataset is 1 MiB: a chunk up to that size is decompressed once however a reader
#: slices it, and a worker's block of texels is a few whole chunks.
CHUNK_BYTES = 2**20

_RESERVED = {
    "schema",
    "schema_version",
    "channels",
    "texels",
    "sample_size",
    "orientation",
    "chunk_texels",
    "units",
}
_PER_SAMPLE_C = ("brdf", "brdf_std", "radiance", "irradiance")


def chunk_texels_for(n_texels: int, n_poses: int, row_bytes: int) -> int:
    """Texels per chunk: as many as keep one chunk of the largest dataset near
    :data:`CHUNK_BYTES`.

    Parameters
    ----------
    n_texels, n_poses
        T and P.
    row_bytes
        Bytes of the largest dataset per (texel, pose): 8 x 3 for directions, 8 x M x 6
        with geometry modes.

    Returns
    -------
    int
        In [1, T]: ``floor(CHUNK_BYTES / (P row_bytes))``, at least one texel (a chunk of
        one texel is then larger than the target: a texel is never split).
    """
    per_texel = max(1, int(n_poses) * int(row_bytes))
    return int(min(max(1, n_texels), max(1, CHUNK_BYTES // per_texel)))


def texel_centers(texels: tuple[int, int], sample_size: tuple[float, float]) -> NDArray[np.float64]:
    """Texel centres (T, 2), metres (x, y) in the sample frame, in flat index order.

    Parameters
    ----------
    texels
        ``(nx, ny)`` texels along x and y.
    sample_size
        ``(w, h)`` of the sample, metres.
    """
    nx, ny = (int(v) for v in texels)
    w, h = (float(v) for v in sample_size)
    row, col = np.divmod(np.arange(nx * ny), nx)
    return np.stack([-w / 2 + (col + 0.5) * w / nx, h / 2 - (row + 0.5) * h / ny], axis=1)


# -- writing ---------------------------------------------------------------------------
def _array(v: ArrayLike, name: str, shape: tuple[int | None, ...]) -> NDArray[np.float64]:
    a = np.asarray(v, dtype=np.float64)
    want = tuple(a.shape[k] if s is None and k < a.ndim else s for k, s in enumerate(shape))
    if a.shape != want:
        shown = "(" + ", ".join("M" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name} must have shape {shown}, got {a.shape}")
    return a


def _unit_rows(a: NDArray[np.float64], name: str) -> None:
    rows = a.reshape(-1, 3)
    finite = np.isfinite(rows).all(axis=1)
    with np.errstate(over="ignore"):
        norm = np.linalg.norm(rows[finite], axis=1)
    bad = ~(np.abs(norm - 1.0) <= UNIT_TOLERANCE)
    if bad.any():
        raise ValueError(
            f"{name}: {int(bad.sum())} finite rows are not unit vectors (one has length "
            f"{norm[np.argmax(bad)]:.9g}; expected 1 within {UNIT_TOLERANCE:g})"
        )


def _nonneg_std(a: NDArray[np.float64], name: str) -> None:
    if (a < 0).any() or np.isinf(a).any():
        raise ValueError(f"{name}: standard deviations must be >= 0 and finite (or NaN)")


def _attr_value(v: Any) -> Any:
    if isinstance(v, Mapping):
        return json.dumps(v, default=str)
    if v is None:
        return ""
    return v


def save_texels(
    path: str | os.PathLike,
    *,
    wi: ArrayLike,
    wo: ArrayLike,
    brdf: ArrayLike,
    brdf_std: ArrayLike,
    flags: ArrayLike,
    pose: ArrayLike,
    texels: tuple[int, int],
    sample_size: tuple[float, float],
    channels: Sequence[str] = ("R", "G", "B"),
    budget: Mapping[str, ArrayLike] | None = None,
    shared_budget: Mapping[str, ArrayLike] | None = None,
    geometry_modes: ArrayLike | None = None,
    geometry_mode_scope: Sequence[str] | None = None,
    geometry_mode_names: Sequence[str] | None = None,
    attrs: Mapping[str, Any] | None = None,
    chunk_texels: int | None = None,
    radiance: ArrayLike | None = None,
    irradiance: ArrayLike | None = None,
    units: Mapping[str, str] | None = None,
) -> Path:
    """Write per-texel samples to ``texels.h5`` atomically (:func:`gonio.atomic.atomic_path`).

    Parameters
    ----------
    path
        Destination file; an existing file is replaced only by a complete one.
    wi, wo
        (T, P, 3) unit directions towards light and camera, sample frame; NaN rows where
        a texel has no sample in a pose.
    brdf, brdf_std
        (T, P, C) f_r and its standard deviation, 1/sr.
    flags
        (T, P) :class:`gonio.dataset.Flag` bits (integers in [0, 2^32)).
    pose
        (P,) journal pose index of each column.
    texels
        ``(nx, ny)``; ``T = nx * ny`` in the flat order of the module's convention.
    sample_size
        ``(w, h)`` of the sample, metres (> 0).
    channels
        C channel names.
    budget
        Optional term (:data:`gonio.dataset.BUDGET_TERMS`) -> (T, P, C) std, 1/sr.
    shared_budget
        Optional shared term (:data:`gonio.dataset.SHARED_BUDGET_TERMS`) -> (C,) relative
        std.
    geometry_modes, geometry_mode_scope, geometry_mode_names
        Optional (T, P, M, 6) 1-sigma changes of ``(wi, wo)`` and their (M,) scopes and
        names (both required with the modes).
    attrs
        Provenance stored as root attributes (``session``, ``created``,
        ``calibration_rel_std`` among them; mappings are stored as JSON).  Without
        ``calibration_rel_std`` it is the root sum of squares of ``shared_budget``'s
        terms when those are given.  ``created`` defaults to now (UTC).
    chunk_texels
        Texels per chunk; :func:`chunk_texels_for` when None.
    radiance, irradiance
        Optional (T, P, C), in the units ``units`` states (keys ``"radiance"``,
        ``"irradiance"``; :data:`gonio.dataset.DEFAULT_UNITS` otherwise).

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    ValueError
        A shape, a term, a scope, a unit vector, a flag or a standard deviation that does
        not fit the layout (the message names the argument); nothing is written.
    """
    nx, ny = (int(v) for v in texels)
    if nx < 1 or ny < 1 or (nx, ny) != tuple(texels):
        raise ValueError(f"texels must be two integers >= 1 (nx, ny), got {texels!r}")
    w, h = (float(v) for v in sample_size)
    if not (np.isfinite([w, h]).all() and w > 0 and h > 0):
        raise ValueError(f"sample_size must be two lengths > 0 (m), got {sample_size!r}")
    t = nx * ny
    channels = tuple(str(c) for c in channels)
    c = len(channels)
    if c < 1:
        raise ValueError("channels: at least one channel name is needed")
    pose_a = np.asarray(pose)
    if pose_a.ndim != 1 or pose_a.dtype.kind not in "iu" or pose_a.size < 1:
        raise ValueError(
            f"pose must be (P,) integers with P >= 1, got {pose_a.dtype} {pose_a.shape}"
        )
    i32 = np.iinfo(np.int32)
    if pose_a.min() < i32.min or pose_a.max() > i32.max:
        raise ValueError(f"pose must fit int32, found {pose_a.min()} .. {pose_a.max()}")
    p = pose_a.size
    data: dict[str, NDArray] = {
        "wi": _array(wi, "wi", (t, p, 3)),
        "wo": _array(wo, "wo", (t, p, 3)),
        "brdf": _array(brdf, "brdf", (t, p, c)),
        "brdf_std": _array(brdf_std, "brdf_std", (t, p, c)),
    }
    _unit_rows(data["wi"], "wi")
    _unit_rows(data["wo"], "wo")
    _nonneg_std(data["brdf_std"], "brdf_std")
    for name, v in (("radiance", radiance), ("irradiance", irradiance)):
        if v is not None:
            data[name] = _array(v, name, (t, p, c))
    fl = np.asarray(flags)
    if fl.shape != (t, p):
        raise ValueError(f"flags must have shape ({t}, {p}), got {fl.shape}")
    if fl.dtype.kind not in "iub" or (fl.size and (fl.min() < 0 or fl.max() > 2**32 - 1)):
        raise ValueError("flags must be integers in [0, 2^32) (gonio.dataset.Flag bits)")
    data["flags"] = fl.astype(np.uint32)
    terms: dict[str, NDArray] = {}
    for term, v in (budget or {}).items():
        if term not in BUDGET_TERMS:
            raise ValueError(f"budget: unknown term {term!r}; known: {list(BUDGET_TERMS)}")
        terms[term] = _array(v, f"budget/{term}", (t, p, c))
        _nonneg_std(terms[term], f"budget/{term}")
    shared: dict[str, NDArray] = {}
    for term, v in (shared_budget or {}).items():
        if term not in SHARED_BUDGET_TERMS:
            raise ValueError(
                f"shared_budget: unknown term {term!r}; known: {list(SHARED_BUDGET_TERMS)}"
            )
        shared[term] = _array(np.reshape(v, -1), f"budget.{term}", (c,))
        _nonneg_std(shared[term], f"budget.{term}")
    modes = None
    if geometry_modes is not None:
        modes = _array(geometry_modes, "geometry_modes", (t, p, None, 6))
        if np.isinf(modes).any():
            raise ValueError("geometry_modes holds infinite values")
        m = modes.shape[2]
        for name, v in (
            ("geometry_mode_scope", geometry_mode_scope),
            ("geometry_mode_names", geometry_mode_names),
        ):
            if v is None:
                raise ValueError(f"{name} is required with geometry_modes")
            if np.asarray(v, dtype=str).reshape(-1).shape != (m,):
                raise ValueError(f"{name} must have {m} entries (one per mode)")
        scope = np.asarray(geometry_mode_scope, dtype=str).reshape(-1)
        if not np.isin(scope, MODE_SCOPES).all():
            raise ValueError(
                f"geometry_mode_scope: {sorted(set(scope) - set(MODE_SCOPES))} "
                f"not among {list(MODE_SCOPES)}"
            )
    elif geometry_mode_scope is not None or geometry_mode_names is not None:
        raise ValueError("geometry_mode_scope/geometry_mode_names given without geometry_modes")
    units_map = {**DEFAULT_UNITS, **{k: str(v) for k, v in (units or {}).items()}}
    unknown = set(units_map) - set(DEFAULT_UNITS)
    if unknown:
        raise ValueError(f"units apply to {sorted(DEFAULT_UNITS)}, not {sorted(unknown)}")
    extra = dict(attrs or {})
    clash = sorted(set(extra) & _RESERVED)
    if clash:
        raise ValueError(f"attrs: {clash} are written by save_texels itself")
    if "calibration_rel_std" not in extra and shared:
        extra["calibration_rel_std"] = np.sqrt(sum(v**2 for v in shared.values()))
    extra.setdefault("session", "")
    extra.setdefault("created", _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))
    row_bytes = 8 * max(3, c) if modes is None else 8 * modes.shape[2] * 6
    k = chunk_texels_for(t, p, row_bytes) if chunk_texels is None else int(chunk_texels)
    if not 1 <= k <= t:
        raise ValueError(f"chunk_texels must lie in [1, {t}], got {chunk_texels!r}")

    def put(where: h5py.Group, name: str, v: NDArray, unit: str) -> None:
        # what a chunk lost from the file's index would read as: no sample
        fill = np.uint32(Flag.INVALID) if v.dtype.kind == "u" else np.nan
        ds = where.create_dataset(
            name,
            data=v,
            fillvalue=fill,
            chunks=(k, *v.shape[1:]),
            compression="gzip",
            compression_opts=4,
            shuffle=True,
            # a checksum per chunk: a worker reading a damaged block gets an error
            # naming the dataset, never silently wrong numbers
            fletcher32=True,
        )
        ds.attrs["units"] = unit

    def strings(f: h5py.File, name: str, v: Sequence[str]) -> None:
        a = np.asarray(v, dtype=str).reshape(-1).astype(object)
        f.create_dataset(name, data=a, dtype=h5py.string_dtype()).attrs["units"] = ""

    path = Path(path)
    # libver "v110": object headers and chunk indexes carry checksums (HDF5 >= 1.10 reads
    # them), so a damaged header or index is an error too, not a chunk read as fill
    with (
        atomic_path(path, parents=True) as tmp,
        h5py.File(tmp, "w", libver=("v110", "latest")) as f,
    ):
        for key, v in extra.items():
            f.attrs[key] = _attr_value(v)
        f.attrs["schema"] = SCHEMA
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["channels"] = np.array(channels, dtype=h5py.string_dtype())
        f.attrs["texels"] = np.array([nx, ny], np.int64)
        f.attrs["sample_size"] = np.array([w, h], np.float64)
        f.attrs["orientation"] = ORIENTATION
        f.attrs["chunk_texels"] = k
        stored = {n: units_map[n] for n in DEFAULT_UNITS if n in data}
        f.attrs["units"] = json.dumps(stored)
        unit_of = {
            "wi": "1",
            "wo": "1",
            "brdf": "1/sr",
            "brdf_std": "1/sr",
            "flags": "bitmask (gonio.dataset.Flag)",
            **units_map,
        }
        for name, v in data.items():
            put(f, name, v, unit_of[name])
        f.create_dataset("pose", data=pose_a.astype(np.int32)).attrs["units"] = "journal pose index"
        if terms or shared:
            g = f.create_group("budget")
            for term, v in terms.items():
                put(g, term, v, "1/sr")
            for term, v in shared.items():
                g.attrs[term] = v
        if modes is not None:
            put(f, "geometry_modes", modes, "1")
            strings(f, "geometry_mode_scope", geometry_mode_scope)  # type: ignore[arg-type]
            strings(f, "geometry_mode_names", geometry_mode_names)  # type: ignore[arg-type]
    return path


# -- reading ---------------------------------------------------------------------------
def _text(v: Any) -> str:
    return v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)


class TexelFile:
    """An open ``texels.h5``: its header checked, its data read a block of texels at a time.

    Use :func:`open_texels` (a context manager).  Opening reads the header only (schema,
    attributes, dataset shapes and types); :meth:`block` reads one hyperslab of texels,
    which touches only the chunks holding them.

    Attributes
    ----------
    path
        The file.
    n_texels, n_poses
        T and P.
    shape
        ``(ny, nx)``, the texel grid as an image (row 0 at +y).
    texels
        ``(nx, ny)``.
    channels
        C channel names.
    sample_size
        ``(w, h)``, metres.
    orientation
        :data:`ORIENTATION` (a file with another is refused).
    chunk_texels
        Texels per chunk (a worker's block is best a multiple of it).
    pose
        (P,) int32 journal pose of each column.
    attrs
        The root attributes other than the layout's own.
    budget_terms
        The per-sample budget terms stored.
    has_geometry_modes
        Whether the geometry modes are stored.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileFormatError(self.path, "no such file")
        try:
            self._f = h5py.File(self.path, "r")
        except Exception as exc:  # h5py raises OSError, or worse on damaged superblocks
            raise FileFormatError(self.path, f"not a readable HDF5 file ({exc})") from None
        try:
            self._header()
        except FileFormatError:
            self._f.close()
            raise
        except Exception as exc:  # a damaged header can fail inside HDF5 anywhere
            self._f.close()
            raise FileFormatError(
                self.path, f"damaged or unreadable HDF5 content ({exc})"
            ) from None

    # the header ------------------------------------------------------------------------
    def _fail(self, message: str, name: str | None = None) -> FileFormatError:
        return FileFormatError(self.path, message, name)

    def _header(self) -> None:
        f = self._f
        schema = _text(f.attrs.get("schema", ""))
        if schema != SCHEMA:
            raise self._fail(f"expected schema '{SCHEMA}', found {schema!r}", "schema")
        try:
            version: Any = int(f.attrs.get("schema_version", -1))
        except (TypeError, ValueError):
            version = repr(f.attrs.get("schema_version"))
        if version != SCHEMA_VERSION:
            raise self._fail(
                f"schema version {version} is not supported (expected {SCHEMA_VERSION})",
                "schema_version",
            )
        tex = np.asarray(f.attrs.get("texels", ()))
        if tex.shape != (2,) or tex.dtype.kind not in "iu" or (tex < 1).any():
            raise self._fail(f"expected two integers >= 1 [nx, ny], found {tex!r}", "texels")
        self.texels = (int(tex[0]), int(tex[1]))
        self.shape = (self.texels[1], self.texels[0])
        self.n_texels = self.texels[0] * self.texels[1]
        size = np.asarray(f.attrs.get("sample_size", ()))
        if size.shape != (2,) or size.dtype.kind not in "iuf" or not (size > 0).all():
            raise self._fail(f"expected two lengths > 0 [w, h] (m), found {size!r}", "sample_size")
        self.sample_size = (float(size[0]), float(size[1]))
        self.orientation = _text(f.attrs.get("orientation", ""))
        if self.orientation != ORIENTATION:
            raise self._fail(f"expected {ORIENTATION!r}, found {self.orientation!r}", "orientation")
        ch = f.attrs.get("channels", ())
        if isinstance(ch, str | bytes) or np.ndim(ch) != 1 or len(ch) < 1:
            raise self._fail(f"expected a list of channel names, found {ch!r}", "channels")
        self.channels = tuple(_text(x) for x in ch)
        c = len(self.channels)
        if "pose" not in f or not isinstance(f["pose"], h5py.Dataset):
            raise self._fail("required dataset is missing", "pose")
        ds = f["pose"]
        if ds.ndim != 1 or ds.dtype.kind not in "iu" or ds.shape[0] < 1:
            raise self._fail(f"expected (P,) integers, found {ds.dtype} {ds.shape}", "pose")
        self.n_poses = int(ds.shape[0])
        self.pose = ds[()].astype(np.int32)
        t, p = self.n_texels, self.n_poses
        want = {
            "wi": (t, p, 3),
            "wo": (t, p, 3),
            "brdf": (t, p, c),
            "brdf_std": (t, p, c),
            "flags": (t, p),
        }
        for name in ("radiance", "irradiance"):
            if name in f:
                want[name] = (t, p, c)
        for name, shape in want.items():
            self._check(name, shape, "iu" if name == "flags" else "f")
        self.budget_terms: tuple[str, ...] = ()
        self._shared: dict[str, NDArray[np.float64]] = {}
        if "budget" in f:
            g = f["budget"]
            if not isinstance(g, h5py.Group):
                raise self._fail(f"expected a group, found {type(g).__name__}", "budget")
            for term in g:
                if term not in BUDGET_TERMS:
                    raise self._fail(
                        f"unknown budget term; expected one of {list(BUDGET_TERMS)}",
                        f"budget/{term}",
                    )
                self._check(f"budget/{term}", (t, p, c), "f")
            self.budget_terms = tuple(g)
            for term, v in g.attrs.items():
                a = np.asarray(v)
                if term not in SHARED_BUDGET_TERMS:
                    raise self._fail(
                        f"unknown shared budget term; expected one of {list(SHARED_BUDGET_TERMS)}",
                        f"budget.{term}",
                    )
                if a.dtype.kind not in "iuf" or a.reshape(-1).shape != (c,):
                    raise self._fail(f"expected {c} numbers, found {a!r}", f"budget.{term}")
                self._shared[term] = a.reshape(-1).astype(np.float64)
        self.has_geometry_modes = "geometry_modes" in f
        self._scope = self._names = None
        if self.has_geometry_modes:
            ds = self._dataset("geometry_modes")
            if ds.ndim != 4 or ds.shape[:2] != (t, p) or ds.shape[3] != 6 or ds.dtype.kind != "f":
                raise self._fail(
                    f"expected ({t}, {p}, M, 6) floats, found {ds.dtype} {ds.shape}",
                    "geometry_modes",
                )
            m = ds.shape[2]
            for name in ("geometry_mode_scope", "geometry_mode_names"):
                if name not in f:
                    raise self._fail("required with geometry_modes, missing", name)
                s = self._dataset(name)
                if s.dtype.kind not in "SOU" or s.shape != (m,):
                    raise self._fail(f"expected {m} strings, found {s.dtype} {s.shape}", name)
            self._scope = f["geometry_mode_scope"].asstr()[()]
            self._names = f["geometry_mode_names"].asstr()[()]
            if not np.isin(self._scope, MODE_SCOPES).all():
                raise self._fail(f"scopes must be among {list(MODE_SCOPES)}", "geometry_mode_scope")
        k = f.attrs.get("chunk_texels", f["brdf"].chunks[0] if f["brdf"].chunks else t)
        self.chunk_texels = int(k)
        try:
            self._units = {**DEFAULT_UNITS, **json.loads(_text(f.attrs.get("units", "{}")))}
        except (ValueError, TypeError):
            raise self._fail("expected a JSON object of units", "units") from None
        skip = _RESERVED
        self.attrs = {
            k: (_text(v) if isinstance(v, bytes) else v)
            for k, v in f.attrs.items()
            if k not in skip
        }

    def _dataset(self, name: str) -> h5py.Dataset:
        obj = self._f.get(name)
        if not isinstance(obj, h5py.Dataset):
            raise self._fail(f"expected a dataset, found {type(obj).__name__}", name)
        return obj

    def _check(self, name: str, shape: tuple[int, ...], kinds: str) -> None:
        if name not in self._f:
            raise self._fail("required dataset is missing", name)
        ds = self._dataset(name)
        if ds.dtype.kind not in kinds:
            want = "integers (a bit mask)" if kinds == "iu" else "floats"
            raise self._fail(f"expected {want}, found {ds.dtype}", name)
        if ds.shape != shape:
            raise self._fail(f"expected shape {shape} (T, P, ...), found {ds.shape}", name)

    # reading blocks --------------------------------------------------------------------
    def _read(self, name: str, t0: int, t1: int) -> NDArray:
        ds = self._f[name]
        try:
            k = ds.chunks[0] if ds.chunks else None
            if k is not None:
                # HDF5 reads a chunk missing from the index as the fill value, silently
                for c0 in range(t0 - t0 % k, t1, k):
                    info = ds.id.get_chunk_info_by_coord((c0,) + (0,) * (ds.ndim - 1))
                    if info.byte_offset is None:
                        raise self._fail(
                            f"texels {c0}..{min(c0 + k, ds.shape[0]) - 1}: the chunk is "
                            "missing from the file (damaged index)",
                            name,
                        )
            return ds[t0:t1]
        except FileFormatError:
            raise
        except Exception as exc:  # a damaged chunk fails inside HDF5's filters
            raise self._fail(
                f"texels {t0}..{t1 - 1}: damaged or unreadable data ({exc})", name
            ) from None

    def block(self, t0: int, t1: int) -> list[BRDFSamples]:
        """The samples of texels ``t0 .. t1 - 1``, one :class:`BRDFSamples` per texel.

        Each dataset's hyperslab ``[t0:t1]`` is read once (only the chunks holding those
        texels are read and decompressed).  A texel's samples are its P poses in the
        file's order, flagged ones included (INVALID with NaN where it had none); they
        carry ``brdf_std``, the budget with its shared terms, ``pose``, the geometry modes
        when stored, and ``attrs`` with the file's attributes (``calibration_rel_std``
        among them, as :func:`gonio.fitting.fit` reads it) plus ``texel``,
        ``texel_row``, ``texel_col`` and ``texel_center`` (x, y in metres).

        Raises
        ------
        IndexError
            ``t0 .. t1`` is empty or outside ``[0, n_texels)``.
        FileFormatError
            A chunk is damaged, or the values are outside their domain (non-unit
            directions, negative standard deviations); names the file and dataset.
        """
        t0, t1 = int(t0), int(t1)
        if not 0 <= t0 < t1 <= self.n_texels:
            raise IndexError(f"texels {t0}..{t1}: expected 0 <= t0 < t1 <= {self.n_texels}")
        names = ["wi", "wo", "brdf", "brdf_std", "flags"]
        names += [n for n in ("radiance", "irradiance") if n in self._f]
        arr = {n: self._read(n, t0, t1) for n in names}
        budget = {term: self._read(f"budget/{term}", t0, t1) for term in self.budget_terms}
        modes = self._read("geometry_modes", t0, t1) if self.has_geometry_modes else None
        for n in ("wi", "wo"):
            try:
                _unit_rows(arr[n], n)
            except ValueError as exc:
                raise self._fail(f"texels {t0}..{t1 - 1}: {exc}", n) from None
        centers = texel_centers(self.texels, self.sample_size)
        out = []
        has_budget = bool(budget) or bool(self._shared)
        for i, t in enumerate(range(t0, t1)):
            row, col = divmod(t, self.texels[0])
            attrs = {
                **self.attrs,
                "texel": t,
                "texel_row": row,
                "texel_col": col,
                "texel_center": centers[t].tolist(),
            }
            try:
                s = BRDFSamples(
                    wi=arr["wi"][i],
                    wo=arr["wo"][i],
                    brdf=arr["brdf"][i],
                    brdf_std=arr["brdf_std"][i],
                    flags=arr["flags"][i],
                    channels=self.channels,
                    radiance=arr["radiance"][i] if "radiance" in arr else None,
                    irradiance=arr["irradiance"][i] if "irradiance" in arr else None,
                    attrs=attrs,
                    units={k: self._units[k] for k in DEFAULT_UNITS},
                    budget={k: v[i] for k, v in budget.items()} if has_budget else None,
                    shared_budget=dict(self._shared) if has_budget else None,
                    geometry_modes=None if modes is None else modes[i],
                    geometry_mode_scope=self._scope,
                    geometry_mode_names=self._names,
                    pose=self.pose,
                )
            except ValueError as exc:
                raise self._fail(f"texel {t}: {exc}") from None
            out.append(s)
        return out

    def samples(self, t: int) -> BRDFSamples:
        """The samples of texel ``t`` (see :meth:`block`)."""
        t = int(t)
        if not 0 <= t < self.n_texels:
            raise IndexError(f"texel {t}: expected 0 <= t < {self.n_texels}")
        return self.block(t, t + 1)[0]

    def index(self, row: int, col: int) -> int:
        """Flat index ``row * nx + col`` of texel (row, col); row 0 at +y, column 0 at -x."""
        nx, ny = self.texels
        if not (0 <= row < ny and 0 <= col < nx):
            raise IndexError(f"texel ({row}, {col}) outside the {ny} x {nx} grid")
        return int(row) * nx + int(col)

    def blocks(self, size: int | None = None) -> Iterator[tuple[int, int]]:
        """``(t0, t1)`` ranges covering every texel, ``size`` (default: one chunk) each."""
        k = self.chunk_texels if size is None else max(1, int(size))
        for t0 in range(0, self.n_texels, k):
            yield t0, min(t0 + k, self.n_texels)

    def close(self) -> None:
        """Close the file."""
        self._f.close()

    def __enter__(self) -> TexelFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def open_texels(path: str | os.PathLike) -> Iterator[TexelFile]:
    """Open a ``texels.h5`` for reading (header checked; data read by block).

    Raises
    ------
    FileFormatError
        Missing, not HDF5, another schema or version, or a dataset missing or of the
        wrong type or shape; the message names the file and the dataset.
    """
    tf = TexelFile(path)
    try:
        yield tf
    finally:
        tf.close()
