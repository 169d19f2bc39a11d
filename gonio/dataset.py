"""BRDF sample sets and their HDF5 file, ``samples.h5``.

A :class:`BRDFSamples` holds what a reduction produces and a fit consumes: per sample the
incident and outgoing directions in the sample frame, the BRDF per colour channel with its
standard deviation, and flags saying why a sample should not be trusted.

File layout (schema version 1)
------------------------------
Datasets at the root, ``N`` samples and ``C`` channels:

==============  ==========  =========  ==================================================
name            shape       units      meaning
==============  ==========  =========  ==================================================
``wi``          (N, 3)      1          unit vector towards the light, sample frame
``wo``          (N, 3)      1          unit vector towards the camera, sample frame
``theta_i`` ..  (N,)        rad        ``theta_i, phi_i, theta_o, phi_o`` of wi and wo
``brdf``        (N, C)      1/sr       f_r per channel
``brdf_std``    (N, C)      1/sr       one standard deviation of ``brdf``
``flags``       (N,)        bit mask   :class:`Flag`; 0 means usable
``radiance``    (N, C)      see below  optional: reflected radiance
``irradiance``  (N, C)      see below  optional: irradiance at the sample
``frames``      (N,)        str        optional: the RAW files a sample came from
==============  ==========  =========  ==================================================

Optional: the uncertainty budget (written by ``gonio capture reduce``; files without
it load as before, its fields None):

=========================  ==========  =====  ==============================================
name                       shape       units  meaning
=========================  ==========  =====  ==============================================
``budget/<term>``          (N, C)      1/sr   one std per term of :data:`BUDGET_TERMS`;
                                              ``brdf_std`` is their root sum of squares
``budget`` attributes      (C,)        1      shared terms (:data:`SHARED_BUDGET_TERMS`),
                                              relative std common to every sample
``geometry_modes``         (N, M, 6)   1      1-sigma change of ``(wi, wo)`` along mode j
``geometry_mode_scope``    (M,)        str    ``"session"`` (one error for all samples)
                                              or ``"pose"`` (one per journal pose)
``geometry_mode_names``    (M,)        str    what each mode is
``pose``                   (N,)        int32  journal pose index of each sample
``geometry_source``        (N,)        str    ``"board"``, ``"rig"`` or ``"none"``: where
                                              the sample's camera pose came from
``stray_gain``             (N, C)      1      ``G0 / G``: a diffuse room irradiance of
                                              fraction ``s`` of the light's direct one at
                                              normal incidence (``G0``) adds
                                              ``s stray_gain rho(theta_o) / pi`` to the
                                              BRDF (``rho``: directional albedo); root
                                              attributes ``stray_fraction`` (the stated
                                              bound ``s``) and ``stray_reference_gain``
                                              (C,: the reference regions' mean gain, by
                                              which the same light biases the light scale)
=========================  ==========  =====  ==============================================

Root attributes: ``schema`` (``"gonio.samples"``), ``schema_version``, ``channels``, and
free-form provenance (software version, session, creation time...).  Each dataset carries
a ``units`` attribute.  Those of ``radiance`` and ``irradiance`` say what is stored
(:attr:`BRDFSamples.units`): W/(sr m^2) and W/m^2 for calibrated values, or camera units
(the reduction stores camera DN) until a session is radiometrically calibrated.

What :func:`load_samples` refuses, naming the file and dataset: no samples (length 0),
finite ``wi``/``wo`` rows whose length differs from 1 by more than
:data:`UNIT_TOLERANCE`, ``flags`` that are not integers in [0, 2^32), non-numeric data,
shapes that do not match; in the budget: unknown terms, negative or infinite standard
deviations, modes whose scope or names do not match their count, scopes or geometry
sources outside their values, pose indices that are not int32 integers.
"""

from __future__ import annotations

import enum
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gonio.atomic import atomic_path
from gonio.errors import FileFormatError
from gonio.radiometry.frames import direction_to_spherical

if TYPE_CHECKING:
    import h5py

SCHEMA = "gonio.samples"
SCHEMA_VERSION = 1

#: Largest accepted deviation of a finite ``wi``/``wo`` row's length from 1.  The writers
#: normalise in float64 (error ~1e-16) and HDF5 stores float64 exactly; 1e-6 still
#: accepts directions that went through float32 (~6e-8) while refusing scaled vectors,
#: degrees or points mistaken for directions.
UNIT_TOLERANCE = 1e-6

#: Per-sample budget terms (std in 1/sr, (N, C)) a file may hold.
BUDGET_TERMS: tuple[str, ...] = (
    "noise",
    "geometry",
    "irradiance",
    "drift",
    "flat",
    "dark",
    "stray",
)
#: Budget terms shared by every sample (relative std per channel, (C,)).
SHARED_BUDGET_TERMS: tuple[str, ...] = ("reference", "light_scale")
#: Values of ``geometry_mode_scope`` and of ``geometry_source``.
MODE_SCOPES: tuple[str, ...] = ("session", "pose")
GEOMETRY_SOURCES: tuple[str, ...] = ("board", "rig", "none")

#: Units of ``radiance`` and ``irradiance`` when the writer does not say (calibrated).
DEFAULT_UNITS = {"radiance": "W/(sr m^2)", "irradiance": "W/m^2"}


class Flag(enum.IntFlag):
    """Why a sample should not be used (bit mask; 0 = usable)."""

    SATURATED = 1
    UNDEREXPOSED = 2
    SHADOWED = 4
    GEOMETRY_MISMATCH = 8
    EXCLUDED = 16
    INVALID = 32


_UNITS = {
    "wi": "1",
    "wo": "1",
    "theta_i": "rad",
    "phi_i": "rad",
    "theta_o": "rad",
    "phi_o": "rad",
    "brdf": "1/sr",
    "brdf_std": "1/sr",
    "flags": "bitmask (gonio.dataset.Flag)",
    "radiance": "W/(sr m^2)",
    "irradiance": "W/m^2",
    "frames": "",
}


@dataclass
class BRDFSamples:
    """BRDF samples in the sample frame.

    Parameters
    ----------
    wi, wo
        Unit directions towards light and camera, shape (N, 3).
    brdf
        f_r in 1/sr, shape (N, C); a 1-D array is taken as one channel.
    brdf_std
        Standard deviation of ``brdf`` (1/sr), same shape; defaults to NaN (unknown).
    flags
        :class:`Flag` bit mask per sample, shape (N,); defaults to 0.
    channels
        Channel names, length C.
    radiance, irradiance
        Optional radiance (W/(sr m^2)) and irradiance (W/m^2), shape (N, C).
    frames
        Optional RAW file names each sample came from, shape (N,).
    attrs
        Provenance attributes stored on the file root.
    units
        Units of what ``radiance`` and ``irradiance`` hold (keys ``"radiance"``,
        ``"irradiance"``; missing keys take :data:`DEFAULT_UNITS`), e.g.
        ``{"radiance": "camera DN/s", ...}`` for an uncalibrated reduction.
    budget
        Optional per-sample uncertainty budget: term (:data:`BUDGET_TERMS`) -> (N, C)
        std in 1/sr.
    shared_budget
        Optional shared terms (:data:`SHARED_BUDGET_TERMS`) -> (C,) relative std.
    geometry_modes
        Optional (N, M, 6) 1-sigma perturbations of ``(wi, wo)`` along M modes.
    geometry_mode_scope, geometry_mode_names
        (M,) each mode's scope (:data:`MODE_SCOPES`) and name; required with the modes.
    pose
        Optional (N,) int32 journal pose index of each sample.
    geometry_source
        Optional (N,) where each sample's camera pose came from (:data:`GEOMETRY_SOURCES`).
    stray_gain
        Optional (N, C) ``G0 / G``, dimensionless: how strongly the room's diffuse light
        enters each sample, relative to its direct irradiance (the table above).
    """

    wi: NDArray[np.float64]
    wo: NDArray[np.float64]
    brdf: NDArray[np.float64]
    brdf_std: NDArray[np.float64] | None = None
    flags: NDArray[np.uint32] | None = None
    channels: tuple[str, ...] | None = None
    radiance: NDArray[np.float64] | None = None
    irradiance: NDArray[np.float64] | None = None
    frames: NDArray[np.str_] | None = None
    attrs: dict[str, Any] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    budget: dict[str, NDArray[np.float64]] | None = None
    shared_budget: dict[str, NDArray[np.float64]] | None = None
    geometry_modes: NDArray[np.float64] | None = None
    geometry_mode_scope: NDArray[np.str_] | None = None
    geometry_mode_names: NDArray[np.str_] | None = None
    pose: NDArray[np.int32] | None = None
    geometry_source: NDArray[np.str_] | None = None
    stray_gain: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        unknown = set(self.units) - set(DEFAULT_UNITS)
        if unknown:
            raise ValueError(f"units apply to {sorted(DEFAULT_UNITS)}, not {sorted(unknown)}")
        self.units = {**DEFAULT_UNITS, **{k: str(v) for k, v in self.units.items()}}
        self.wi = _vec3(self.wi, "wi")
        self.wo = _vec3(self.wo, "wo")
        n = self.wi.shape[0]
        if self.wo.shape[0] != n:
            raise ValueError(f"wo has {self.wo.shape[0]} samples, wi has {n}")
        self.brdf = _per_channel(self.brdf, n, "brdf")
        c = self.brdf.shape[1]
        if self.brdf_std is None:
            self.brdf_std = np.full_like(self.brdf, np.nan)
        self.brdf_std = _per_channel(self.brdf_std, n, "brdf_std", c)
        if self.flags is None:
            self.flags = np.zeros(n, dtype=np.uint32)
        self.flags = np.asarray(self.flags, dtype=np.uint32).reshape(n)
        if self.channels is None:
            self.channels = ("R", "G", "B") if c == 3 else tuple(f"c{k}" for k in range(c))
        self.channels = tuple(str(x) for x in self.channels)
        if len(self.channels) != c:
            raise ValueError(f"{len(self.channels)} channel names for {c} channels")
        for name in ("radiance", "irradiance"):
            v = getattr(self, name)
            if v is not None:
                setattr(self, name, _per_channel(v, n, name, c))
        if self.frames is not None:
            self.frames = np.asarray(self.frames, dtype=str).reshape(n)
        self._check_budget(n, c)

    def _check_budget(self, n: int, c: int) -> None:
        if self.budget is not None:
            unknown = sorted(set(self.budget) - set(BUDGET_TERMS))
            if unknown:
                raise ValueError(f"budget: unknown term(s) {unknown}; known: {list(BUDGET_TERMS)}")
            self.budget = {
                t: _std(_per_channel(v, n, f"budget/{t}", c), f"budget/{t}")
                for t, v in self.budget.items()
            }
        if self.shared_budget is not None:
            unknown = sorted(set(self.shared_budget) - set(SHARED_BUDGET_TERMS))
            if unknown:
                raise ValueError(
                    f"budget: unknown shared term(s) {unknown}; known: {list(SHARED_BUDGET_TERMS)}"
                )
            out = {}
            for t, v in self.shared_budget.items():
                a = np.asarray(v, dtype=np.float64).reshape(-1)
                if a.shape != (c,):
                    raise ValueError(f"budget.{t} must have {c} values, got shape {a.shape}")
                out[t] = _std(a, f"budget.{t}")
            self.shared_budget = out
        if self.geometry_modes is not None:
            m = np.asarray(self.geometry_modes, dtype=np.float64)
            if m.ndim != 3 or m.shape[0] != n or m.shape[2] != 6:
                raise ValueError(f"geometry_modes must have shape ({n}, M, 6), got {m.shape}")
            if np.isinf(m).any():
                raise ValueError("geometry_modes holds infinite values")
            self.geometry_modes = m
            k = m.shape[1]
            for name, allowed in (
                ("geometry_mode_scope", MODE_SCOPES),
                ("geometry_mode_names", None),
            ):
                v = getattr(self, name)
                if v is None:
                    raise ValueError(f"{name} is required with geometry_modes")
                a = np.asarray(v, dtype=str).reshape(-1)
                if a.shape != (k,):
                    raise ValueError(f"{name} must have {k} entries (one per mode), got {a.size}")
                if allowed is not None and not np.isin(a, allowed).all():
                    bad = sorted(set(a.tolist()) - set(allowed))
                    raise ValueError(f"{name}: {bad} not among {list(allowed)}")
                setattr(self, name, a)
        elif self.geometry_mode_scope is not None or self.geometry_mode_names is not None:
            raise ValueError("geometry_mode_scope/geometry_mode_names given without geometry_modes")
        if self.pose is not None:
            a = np.asarray(self.pose)
            if a.shape not in ((n,), (n, 1)) or a.dtype.kind not in "iu":
                raise ValueError(f"pose must be ({n},) integers, got {a.dtype} {a.shape}")
            lo, hi = np.iinfo(np.int32).min, np.iinfo(np.int32).max
            if a.size and (a.min() < lo or a.max() > hi):
                raise ValueError(f"pose must fit int32, found {a.min()} .. {a.max()}")
            self.pose = a.reshape(n).astype(np.int32)
        if self.geometry_source is not None:
            a = np.asarray(self.geometry_source, dtype=str).reshape(-1)
            if a.shape != (n,):
                raise ValueError(f"geometry_source must have shape ({n},), got {a.shape}")
            if not np.isin(a, GEOMETRY_SOURCES).all():
                bad = sorted(set(a.tolist()) - set(GEOMETRY_SOURCES))[:5]
                raise ValueError(f"geometry_source: {bad} not among {list(GEOMETRY_SOURCES)}")
            self.geometry_source = a
        if self.stray_gain is not None:
            g = _per_channel(self.stray_gain, n, "stray_gain", c)
            if np.any(g < 0) or np.any(np.isinf(g)):
                raise ValueError("stray_gain must be >= 0 and finite (NaN: unknown)")
            self.stray_gain = g

    def __len__(self) -> int:
        return self.wi.shape[0]

    @property
    def n_channels(self) -> int:
        """Number of colour channels C."""
        return self.brdf.shape[1]

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Samples with no flag set and finite, non-negative-variance values."""
        finite = np.isfinite(self.brdf).all(axis=1)
        finite &= np.isfinite(self.wi).all(axis=1) & np.isfinite(self.wo).all(axis=1)
        return (self.flags == 0) & finite

    def angles(self) -> dict[str, NDArray[np.float64]]:
        """``theta_i, phi_i, theta_o, phi_o`` in radians."""
        ti, pi = direction_to_spherical(self.wi)
        to, po = direction_to_spherical(self.wo)
        return {"theta_i": ti, "phi_i": pi, "theta_o": to, "phi_o": po}

    def subset(self, mask: ArrayLike) -> BRDFSamples:
        """The samples selected by a boolean mask or index array."""
        idx = np.asarray(mask)

        def pick(v: Any) -> Any:
            return None if v is None else v[idx]

        return BRDFSamples(
            wi=self.wi[idx],
            wo=self.wo[idx],
            brdf=self.brdf[idx],
            brdf_std=pick(self.brdf_std),
            flags=pick(self.flags),
            channels=self.channels,
            radiance=pick(self.radiance),
            irradiance=pick(self.irradiance),
            frames=pick(self.frames),
            attrs=dict(self.attrs),
            units=dict(self.units),
            budget=None if self.budget is None else {t: v[idx] for t, v in self.budget.items()},
            shared_budget=None if self.shared_budget is None else dict(self.shared_budget),
            geometry_modes=pick(self.geometry_modes),
            geometry_mode_scope=self.geometry_mode_scope,
            geometry_mode_names=self.geometry_mode_names,
            pose=pick(self.pose),
            geometry_source=pick(self.geometry_source),
            stray_gain=pick(self.stray_gain),
        )


def _vec3(v: ArrayLike, name: str) -> NDArray[np.float64]:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    return a


def _std(a: NDArray[np.float64], name: str) -> NDArray[np.float64]:
    """A standard deviation array: NaN (unknown) allowed, negative or infinite not."""
    if (a < 0).any() or np.isinf(a).any():
        raise ValueError(f"{name}: standard deviations must be >= 0 and finite (or NaN)")
    return a


def _per_channel(v: ArrayLike, n: int, name: str, c: int | None = None) -> NDArray[np.float64]:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] != n or (c is not None and a.shape[1] != c):
        want = f"({n}, {c if c is not None else 'C'})"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    return a


def save_samples(path: str | os.PathLike, samples: BRDFSamples) -> Path:
    """Write ``samples`` to an HDF5 file atomically.

    The file is written next to its destination under a temporary name, flushed and
    renamed (:func:`gonio.atomic.atomic_path`), so an existing file is replaced only by a
    complete one.

    Returns
    -------
    Path
        The written file.
    """
    # imported on use: ~0.15 s of start-up that a `gonio fit FILE.bsdf` never needs
    import h5py

    path = Path(path)
    with atomic_path(path, parents=True) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["schema"] = SCHEMA
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["channels"] = np.array(samples.channels, dtype=h5py.string_dtype())
        for k, v in samples.attrs.items():
            f.attrs[k] = _attr_value(v)
        data: dict[str, Any] = {
            "wi": samples.wi,
            "wo": samples.wo,
            **samples.angles(),
            "brdf": samples.brdf,
            "brdf_std": samples.brdf_std,
            "flags": samples.flags,
            "radiance": samples.radiance,
            "irradiance": samples.irradiance,
        }
        for name, v in data.items():
            if v is None:
                continue
            ds = f.create_dataset(name, data=v, compression="gzip", compression_opts=4)
            ds.attrs["units"] = samples.units.get(name, _UNITS[name])
        if samples.frames is not None:
            ds = f.create_dataset(
                "frames", data=samples.frames.astype(object), dtype=h5py.string_dtype()
            )
            ds.attrs["units"] = ""
        _save_budget(f, samples)
    return path


def _save_budget(f: h5py.File, s: BRDFSamples) -> None:
    import h5py

    def numbers(name: str, v: NDArray, units: str, where: Any = f) -> None:
        # an empty dataset cannot be chunked (compressed); the byte shuffle lets deflate
        # see the modes' many small floats of similar exponent (the largest dataset)
        opts = {"compression": "gzip", "compression_opts": 4, "shuffle": True} if v.size else {}
        where.create_dataset(name, data=v, **opts).attrs["units"] = units

    def strings(name: str, v: NDArray) -> None:
        f.create_dataset(name, data=v.astype(object), dtype=h5py.string_dtype()).attrs["units"] = ""

    if s.budget is not None or s.shared_budget is not None:
        g = f.create_group("budget")
        for t, v in (s.budget or {}).items():
            numbers(t, v, "1/sr", g)
        for t, v in (s.shared_budget or {}).items():
            g.attrs[t] = v
    if s.geometry_modes is not None:
        numbers("geometry_modes", s.geometry_modes, "1")
        strings("geometry_mode_scope", s.geometry_mode_scope)
        strings("geometry_mode_names", s.geometry_mode_names)
    if s.pose is not None:
        numbers("pose", s.pose.astype(np.int32), "journal pose index")
    if s.geometry_source is not None:
        strings("geometry_source", s.geometry_source)
    if s.stray_gain is not None:
        numbers("stray_gain", s.stray_gain, "1")


def _attr_value(v: Any) -> Any:
    if isinstance(v, Mapping):
        import json

        return json.dumps(v, default=str)
    if v is None:
        return ""
    return v


def load_samples(path: str | os.PathLike) -> BRDFSamples:
    """Read a ``samples.h5`` file written by :func:`save_samples`.

    Returns
    -------
    BRDFSamples
        With ``units`` as the file's ``radiance``/``irradiance`` datasets state them.

    Raises
    ------
    FileFormatError
        If the file is missing, not HDF5 or damaged, of another schema or version, holds
        no samples, or a dataset is absent, of the wrong type or shape, or holds values
        outside its domain (non-unit directions, non-integer flags); the message names
        the file and the dataset.
    """
    import h5py

    path = Path(path)
    if not path.is_file():
        raise FileFormatError(path, "no such file")
    try:
        f = h5py.File(path, "r")
    except Exception as exc:  # h5py raises OSError, or worse on damaged superblocks
        raise FileFormatError(path, f"not a readable HDF5 file ({exc})") from None
    try:
        with f:
            out, channels, attrs, units = _read(path, f)
    except FileFormatError:
        raise
    except Exception as exc:  # a damaged file can fail inside HDF5 anywhere
        raise FileFormatError(path, f"damaged or unreadable HDF5 content ({exc})") from None
    try:
        samples = BRDFSamples(channels=channels or None, attrs=attrs, units=units, **out)
    except ValueError as exc:
        raise FileFormatError(path, str(exc)) from None
    _check_values(path, samples)
    return samples


def _dataset(path: Path, f: h5py.File, name: str) -> h5py.Dataset:
    import h5py

    obj = f.get(name)
    if not isinstance(obj, h5py.Dataset):
        raise FileFormatError(path, f"expected a dataset, found {type(obj).__name__}", name)
    return obj


def _read(path: Path, f: h5py.File) -> tuple[dict[str, Any], tuple, dict, dict]:
    schema = f.attrs.get("schema")
    if isinstance(schema, bytes):
        schema = schema.decode("utf-8", "replace")
    if not isinstance(schema, str) or schema != SCHEMA:
        raise FileFormatError(path, f"expected schema '{SCHEMA}', found {schema!r}", "schema")
    raw_version = f.attrs.get("schema_version", -1)
    try:
        version: Any = int(raw_version)
    except (TypeError, ValueError):
        version = repr(raw_version)
    if version != SCHEMA_VERSION:
        raise FileFormatError(
            path,
            f"schema version {version} is not supported (expected {SCHEMA_VERSION})",
            "schema_version",
        )
    out: dict[str, Any] = {}
    units: dict[str, str] = {}
    for name in ("wi", "wo", "brdf"):
        if name not in f:
            raise FileFormatError(path, "required dataset is missing", name)
    for name in ("wi", "wo", "brdf", "brdf_std", "flags", "radiance", "irradiance"):
        if name not in f:
            continue
        ds = _dataset(path, f, name)
        kinds = "iu" if name == "flags" else "iuf"
        if ds.dtype.kind not in kinds:
            want = "integers (a bit mask)" if name == "flags" else "numbers"
            raise FileFormatError(path, f"expected {want}, found {ds.dtype}", name)
        if ds.ndim == 0 or ds.shape[0] == 0:
            raise FileFormatError(path, f"no samples (shape {ds.shape})", name)
        _check_size(path, ds, name)
        out[name] = ds[()]
        if name in DEFAULT_UNITS and "units" in ds.attrs:
            u = ds.attrs["units"]
            units[name] = u.decode("utf-8", "replace") if isinstance(u, bytes) else str(u)
    if "flags" in out:
        fl = out["flags"]
        if fl.size and (fl.min() < 0 or fl.max() > np.iinfo(np.uint32).max):
            raise FileFormatError(
                path, f"flags must lie in [0, 2^32), found {fl.min()} .. {fl.max()}", "flags"
            )
    if "frames" in f:
        ds = _dataset(path, f, "frames")
        if ds.dtype.kind not in "SOU":
            raise FileFormatError(path, f"expected strings, found {ds.dtype}", "frames")
        _check_size(path, ds, "frames")
        out["frames"] = ds.asstr()[()]
    out.update(_read_budget(path, f))
    raw_channels = f.attrs.get("channels", ())
    if isinstance(raw_channels, str | bytes) or np.ndim(raw_channels) != 1:
        raise FileFormatError(
            path, f"expected a list of channel names, found {raw_channels!r}", "channels"
        )
    channels = tuple(
        c.decode("utf-8", "replace") if isinstance(c, bytes) else str(c) for c in raw_channels
    )
    attrs = {
        k: (v.decode("utf-8", "replace") if isinstance(v, bytes) else v)
        for k, v in f.attrs.items()
        if k not in ("schema", "schema_version", "channels")
    }
    return out, channels, attrs, units


def _read_budget(path: Path, f: h5py.File) -> dict[str, Any]:
    """The optional budget datasets, type-checked (shapes are checked by BRDFSamples)."""
    import h5py

    out: dict[str, Any] = {}

    def numeric(name: str, obj: Any, kinds: str = "iuf") -> NDArray:
        if not isinstance(obj, h5py.Dataset):
            raise FileFormatError(path, f"expected a dataset, found {type(obj).__name__}", name)
        if obj.dtype.kind not in kinds:
            raise FileFormatError(path, f"expected numbers, found {obj.dtype}", name)
        _check_size(path, obj, name)
        return obj[()]

    def strings(name: str) -> NDArray:
        ds = _dataset(path, f, name)
        if ds.dtype.kind not in "SOU" or ds.ndim != 1:
            raise FileFormatError(path, f"expected a list of strings, found {ds.dtype}", name)
        _check_size(path, ds, name)
        return ds.asstr()[()]

    if "budget" in f:
        g = f["budget"]
        if not isinstance(g, h5py.Group):
            raise FileFormatError(path, f"expected a group, found {type(g).__name__}", "budget")
        budget = {}
        for t in g:
            if t not in BUDGET_TERMS:
                raise FileFormatError(
                    path,
                    f"unknown budget term; expected one of {list(BUDGET_TERMS)}",
                    f"budget/{t}",
                )
            budget[t] = numeric(f"budget/{t}", g[t])
        shared = {}
        for t, v in g.attrs.items():
            if t not in SHARED_BUDGET_TERMS:
                raise FileFormatError(
                    path,
                    f"unknown shared budget term; expected one of {list(SHARED_BUDGET_TERMS)}",
                    f"budget.{t}",
                )
            a = np.asarray(v)
            if a.dtype.kind not in "iuf":
                raise FileFormatError(path, f"expected numbers, found {a.dtype}", f"budget.{t}")
            shared[t] = a
        out["budget"] = budget
        out["shared_budget"] = shared
    if "geometry_modes" in f:
        out["geometry_modes"] = numeric("geometry_modes", f["geometry_modes"], "f")
        for name in ("geometry_mode_scope", "geometry_mode_names"):
            if name not in f:
                raise FileFormatError(path, "required with geometry_modes, missing", name)
            out[name] = strings(name)
    if "pose" in f:
        out["pose"] = numeric("pose", f["pose"], "iu")
    if "geometry_source" in f:
        out["geometry_source"] = strings("geometry_source")
    if "stray_gain" in f:
        out["stray_gain"] = numeric("stray_gain", f["stray_gain"], "f")
    return out


# deflate, the strongest compression HDF5 applies here, packs at most ~1032:1.
_MAX_COMPRESSION = 1100


def _check_size(path: Path, ds: h5py.Dataset, name: str) -> None:
    """Refuse a dataset whose header claims more data than the file can hold: a damaged
    header would otherwise have numpy allocate whatever it says."""
    limit = _MAX_COMPRESSION * path.stat().st_size + 2**20
    if ds.size * ds.dtype.itemsize > limit:
        raise FileFormatError(
            path,
            f"the dataset claims shape {ds.shape} ({ds.size * ds.dtype.itemsize:,} bytes), "
            f"more than a file of {path.stat().st_size:,} bytes can hold: damaged",
            name,
        )


def _check_values(path: Path, s: BRDFSamples) -> None:
    for name in ("wi", "wo"):
        v = getattr(s, name)
        # A non-finite row is an unusable sample (BRDFSamples.valid drops it), not a
        # malformed file; a finite row must be a direction.
        finite = np.isfinite(v).all(axis=1)
        with np.errstate(over="ignore"):  # a huge component is simply not a unit vector
            norm = np.linalg.norm(v[finite], axis=1)
        bad = ~(np.abs(norm - 1.0) <= UNIT_TOLERANCE)
        if bad.any():
            k = int(np.flatnonzero(finite)[np.argmax(bad)])
            raise FileFormatError(
                path,
                f"{int(bad.sum())} of {len(v)} rows are not unit vectors (row {k} has "
                f"length {norm[np.argmax(bad)]:.9g}; expected 1 within {UNIT_TOLERANCE:g})",
                name,
            )
