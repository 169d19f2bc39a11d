"""Spatially varying samples: parameter maps, material mixes and their ground truth.

Texel convention (shared with the per-texel reduction and fit): the sample rectangle
(x in [-w/2, w/2], y in [-h/2, h/2], metres) is divided into ``nx x ny`` equal texels;
texel ``(row, col)`` has row 0 at +y and column 0 at -x (the ``albedo_map``
orientation), flat index ``row * nx + col``, centre ``x = -w/2 + (col + 0.5) w / nx``,
``y = h/2 - (row + 0.5) h / ny``.

Maps are piecewise constant: a surface point takes the value of the map texel it lies
in (each map at its own size), so every texel's truth is exact.  The scene's schema:

- ``[sample.maps]``: ``name = MAP`` for parameters of the analytic ``sample.brdf.model``;
  MAP is a path (``.npy`` (ny, nx) or (ny, nx, 3) in natural units, loaded without
  pickles; an 8/16-bit image -> [0, 1]), ``{ file = "...", range = [lo, hi] }`` (an image's
  [0, 1] taken to [lo, hi]) or an inline nested list (rows of numbers or of [r, g, b]).
  Parameters without a map keep ``sample.brdf.params`` (or the model's default).
- ``[sample.mix]``: ``mask`` (path or inline list of integer labels, (ny, nx)) and
  ``[[sample.mix.materials]]`` (each a ``BRDFSpec``: ``model`` + ``params`` or ``file``);
  texel label k has material k.

The ground truth of a simulated session (``SESSION/truth/svbrdf.h5``, :func:`truth_bytes`,
:func:`read_truth`) holds the maps resampled (nearest) to the finest map's grid.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gonio.errors import ConfigError, FileFormatError, GonioError

__all__ = [
    "ORIENTATION",
    "TRUTH_FILE",
    "TRUTH_SCHEMA",
    "SVBRDFTruth",
    "SampleLayout",
    "SpatialBRDF",
    "build_spatial_brdf",
    "check_layout",
    "load_layout",
    "read_truth",
    "texel_of",
    "truth_bytes",
    "write_truth",
]

ORIENTATION = "row 0 at +y, column 0 at -x"
TRUTH_SCHEMA = "gonio.svbrdf_truth"
TRUTH_VERSION = 1
#: Where a simulated session keeps its sample's ground truth (relative to SESSION).
TRUTH_FILE = "truth/svbrdf.h5"
#: Largest label a mask may hold (a label is an index into ``sample.mix.materials``).
_MAX_LABELS = 256


def texel_of(
    x: np.ndarray, y: np.ndarray, size: tuple[float, float], shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of the texel containing sample-frame points (nearest texel).

    Parameters
    ----------
    x, y
        Sample-frame coordinates, m, any matching shapes.
    size
        Sample width and height ``(w, h)``, m.
    shape
        Texel grid ``(ny, nx)``.

    Returns
    -------
    row, col
        Integer arrays (intp) of x's shape; points on or beyond the rim take the
        outermost texel (a pixel centre exactly on the sample's edge).
    """
    w, h = size
    ny, nx = shape
    col = np.floor((np.asarray(x, float) + w / 2) / w * nx)
    row = np.floor((h / 2 - np.asarray(y, float)) / h * ny)
    col = np.clip(np.nan_to_num(col, nan=0.0), 0, nx - 1).astype(np.intp)
    row = np.clip(np.nan_to_num(row, nan=0.0), 0, ny - 1).astype(np.intp)
    return row, col


@dataclass(frozen=True)
class SampleLayout:
    """A spatially varying sample as loaded from the scene (values checked).

    Attributes
    ----------
    kind
        ``"maps"`` or ``"mix"``.
    size
        Sample ``(w, h)``, m.
    maps
        ``name -> (ny, nx, 3)`` float64 parameter maps (kind "maps").
    labels
        ``(ny, nx)`` int64 mask (kind "mix").
    """

    kind: str
    size: tuple[float, float]
    maps: dict[str, np.ndarray] = field(default_factory=dict)
    labels: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """The finest grid ``(ny, nx)``: the largest rows and columns of the maps."""
        if self.kind == "mix":
            assert self.labels is not None
            return self.labels.shape  # type: ignore[return-value]
        return (
            max(m.shape[0] for m in self.maps.values()),
            max(m.shape[1] for m in self.maps.values()),
        )


def _read_array(value: Any, scene: Any, what: str) -> tuple[np.ndarray, str, float | None]:
    """(array, where it came from for messages, the image's full scale or None) of a
    map's value; an image's values are divided by its full scale (255 or 65535)."""
    from gonio.simulator.scene import MapFile

    if isinstance(value, list):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ConfigError(
                f"{what} (inline): not a rectangular nested list of numbers; expected "
                "rows of equal length of numbers or of [r, g, b]"
            ) from None
        return arr, f"{what} (inline)", None
    path = scene.resolve(value.file if isinstance(value, MapFile) else value)
    where = f"{what} ({path})"
    if not path.is_file():
        raise ConfigError(f"{where}: the file does not exist")
    if path.suffix.lower() == ".npy":
        try:
            # Never unpickle: an object array in a scene's folder is refused, not run.
            arr = np.asarray(np.load(path, allow_pickle=False), dtype=np.float64)
        except (ValueError, TypeError, OSError, EOFError) as exc:
            why = (
                "holds Python objects (a pickled array), which gonio does not load"
                if "allow_pickle" in str(exc)
                else f"is not a numeric .npy array ({exc})"
            )
            raise ConfigError(f"{where}: {why}") from None
        return arr, where, None
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype not in (np.uint8, np.uint16):
        raise ConfigError(f"{where}: not a readable 8- or 16-bit image (or a .npy array)")
    full = 65535.0 if img.dtype == np.uint16 else 255.0
    arr = img.astype(np.float64) / full
    if arr.ndim == 3:
        arr = arr[..., 2::-1]  # OpenCV's BGR(A) -> RGB
    return arr, where, full


def _as_rgb_map(arr: np.ndarray, where: str) -> np.ndarray:
    if arr.ndim == 2:
        arr = np.repeat(arr[..., None], 3, -1)
    if arr.ndim != 3 or arr.shape[-1] not in (1, 3) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ConfigError(f"{where}: shape {tuple(arr.shape)}; expected (ny, nx) or (ny, nx, 3)")
    arr = np.broadcast_to(arr, arr.shape[:2] + (3,))
    bad = ~np.isfinite(arr)
    if np.any(bad):
        r, c, _ = np.argwhere(bad)[0]
        raise ConfigError(
            f"{where}: value {arr[r, c].tolist()} at texel (row {r}, column {c}) is not "
            "finite; expected numbers"
        )
    return np.ascontiguousarray(arr, dtype=np.float64)


def _model(scene: Any) -> Any:
    import gonio.brdf

    spec = scene.sample.brdf
    try:
        return gonio.brdf.get_model(spec.model, **spec.options)
    except GonioError as exc:
        raise ConfigError(f"sample.brdf: {exc}") from None


def load_layout(scene: Any) -> SampleLayout:
    """Read and check the scene's ``sample.maps`` or ``sample.mix`` (not the materials).

    Raises
    ------
    ConfigError
        A map or mask that is missing, unreadable, of the wrong shape, not finite, out of
        the model's bounds, or names no parameter of the model; a mask label without a
        material.  The field (``sample.maps.<name>``, ``sample.mix.mask``), the file (or
        "inline") and the value are named.
    """
    s = scene.sample
    size = (float(s.width), float(s.height))
    if s.mix is not None:
        arr, where, full = _read_array(s.mix.mask, scene, "sample.mix.mask")
        if full is not None:
            # a label image stores the label itself, not a fraction of full scale
            arr = np.rint(arr * full)
            if arr.ndim == 3:
                arr = arr[..., 0]
        if arr.ndim != 2 or 0 in arr.shape:
            raise ConfigError(f"{where}: shape {tuple(arr.shape)}; expected (ny, nx) labels")
        bad = ~np.isfinite(arr) | (arr != np.round(arr)) | (arr < 0)
        if np.any(bad):
            r, c = np.argwhere(bad)[0]
            raise ConfigError(
                f"{where}: value {arr[r, c]!r} at texel (row {r}, column {c}); expected "
                "integer labels >= 0"
            )
        n = len(s.mix.materials)
        over = arr >= n
        if np.any(over):
            r, c = np.argwhere(over)[0]
            raise ConfigError(
                f"{where}: label {int(arr[r, c])} at texel (row {r}, column {c}) has no "
                f"material: sample.mix.materials has {n} (labels 0 to {n - 1})"
            )
        return SampleLayout("mix", size, labels=arr.astype(np.int64))
    model = _model(scene)
    maps: dict[str, np.ndarray] = {}
    for name, value in s.maps.items():
        what = f"sample.maps.{name}"
        if name not in model.bounds:
            raise ConfigError(
                f"{what}: model '{model.name}' has no parameter {name!r}; its parameters "
                f"are: {', '.join(model.param_names)}"
            )
        arr, where, full = _read_array(value, scene, what)
        image = full is not None
        m = _as_rgb_map(arr, where)
        rng = getattr(value, "range", None)
        if image or rng is not None:
            if not image:
                raise ConfigError(f"{where}: 'range' applies to an image, not a .npy array")
            lo, hi = rng if rng is not None else (0.0, 1.0)
            m = lo + (hi - lo) * m
        lo, hi = model.bounds[name]
        out = (m < lo) | (m > hi)
        if np.any(out):
            r, c, k = np.argwhere(out)[0]
            raise ConfigError(
                f"{where}: value {m[r, c, k]:g} at texel (row {r}, column {c}) is outside "
                f"the bounds [{lo:g}, {hi:g}] of parameter {name!r} of model '{model.name}'"
            )
        maps[name] = m
    return SampleLayout("maps", size, maps=maps)


def check_layout(scene: Any) -> None:
    """The errors of :func:`build_spatial_brdf` without loading measured files (their
    existence is checked): ``parse_scene`` calls it, so a bad map or material is
    reported before anything renders or a session starts."""
    build_spatial_brdf(scene, load_measured=False)


class SpatialBRDF:
    """The sample's BRDF varying over the sample: per texel parameters or materials.

    ``eval_at(x, wi, wo)`` evaluates f_r (1/sr, (M, K, 3)) at sample points x (M, 3)
    for direction pairs (M, K, 3), each point with its texel's parameters (maps: one
    vectorised evaluation of the model with per-point parameter arrays, the same
    arithmetic as a bound model's) or material (mix: each material on its points).
    ``albedo_at(theta_o, x)`` is the directional albedo (M, 3) of each point's texel
    (tabulated as :func:`gonio.simulator.render.albedo_table`, per lobe and distinct
    non-linear parameters).
    """

    spatial = True

    def __init__(
        self,
        layout: SampleLayout,
        model: Any = None,
        base: dict | None = None,
        materials: list[Any] | None = None,
        specs: list[dict] | None = None,
    ) -> None:
        self.layout = layout
        self.model = model
        self.materials = materials or []
        self.specs = specs or []
        self.params: dict[str, np.ndarray] = {}
        if model is not None:
            bound = model.bind(base or {}, channels=3)
            self.params = {k: np.asarray(v, dtype=np.float64) for k, v in bound.params.items()}
        self._albedo: dict[Any, Any] = {}
        self.description = (
            f"{model.name} with maps of {', '.join(layout.maps)}"
            if layout.kind == "maps"
            else f"mix of {len(self.materials)} materials"
        )

    def _texels(self, x: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        return texel_of(x[..., 0], x[..., 1], self.layout.size, shape)

    def params_at(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """Every model parameter at points x (M, 3): ``name -> (M, 3)`` (kind "maps")."""
        out = {}
        for k, v in self.params.items():
            m = self.layout.maps.get(k)
            if m is None:
                out[k] = np.broadcast_to(v, x.shape[:-1] + (3,))
            else:
                r, c = self._texels(x, m.shape[:2])
                out[k] = m[r, c]
        return out

    def labels_at(self, x: np.ndarray) -> np.ndarray:
        """The mix's material label (M,) at points x (M, 3)."""
        assert self.layout.labels is not None
        r, c = self._texels(x, self.layout.labels.shape)
        return self.layout.labels[r, c]

    def eval_at(self, x: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        """f_r (M, K, 3), 1/sr, at points x (M, 3) for directions wi, wo (M, K, 3)."""
        if self.layout.kind == "maps":
            p = {k: v[:, None, :] for k, v in self.params_at(x).items()}
            return self.model.eval(wi[..., None, :], wo[..., None, :], p)
        out = np.zeros(wi.shape[:-1] + (3,))
        lab = self.labels_at(x)
        for k in np.unique(lab):
            on = lab == k
            out[on] = self.materials[int(k)].eval(wi[on], wo[on])
        return out

    def _lobes(self) -> list[tuple[Any, dict[str, str], list[str], list[str]]]:
        """(lobe, local -> public names, linear locals, other locals) of the model.

        The public names follow :class:`gonio.brdf.base.Model`'s rule (a name shared by
        two lobes gets the lobe's 1-based index); checked against ``param_names``."""
        lobes = self.model.lobes
        counts: dict[str, int] = {}
        for lobe in lobes:
            for sp in lobe.specs:
                counts[sp.name] = counts.get(sp.name, 0) + 1
        out = []
        for i, lobe in enumerate(lobes, start=1):
            names = {
                sp.name: sp.name if counts[sp.name] == 1 else f"{sp.name}_{i}" for sp in lobe.specs
            }
            lin = [sp.name for sp in lobe.specs if sp.linear]
            out.append((lobe, names, lin, [sp.name for sp in lobe.specs if not sp.linear]))
        public = [n for _, names, _, _ in out for n in names.values()]
        if sorted(public) != sorted(self.model.param_names):  # pragma: no cover - guard
            raise RuntimeError(f"lobe parameter names {public} are not {self.model.param_names}")
        return out

    def _lobe_table(self, i: int, lobe: Any, lin: list[str], key: dict[str, float]) -> np.ndarray:
        """Albedo (33,) at the table's angles of lobe i with its linear weights at 1."""
        from gonio.brdf.albedo import lobe_albedo
        from gonio.simulator.render import _ALBEDO_THETA

        k = (i, *sorted(key.items()))
        t = self._albedo.get(k)
        if t is None:
            p = {n: np.asarray(v, dtype=np.float64) for n, v in key.items()}
            p.update({n: np.asarray(1.0) for n in lin})
            t = np.asarray(lobe_albedo(lobe, _ALBEDO_THETA, p, 0.0), dtype=np.float64)
            self._albedo[k] = t
        return t

    def albedo_at(self, theta: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Directional albedo (M, 3) towards viewing angles theta (M,) rad at points x.

        A mix: each material's :func:`~gonio.simulator.render.albedo_table`.  Maps: a
        lobe's albedo is linear in its linear weight (``albedo``, ``ks``: f is), so each
        lobe is tabulated (33 angles, as ``albedo_table``, interpolated linearly) once per
        distinct value of its other parameters (e.g. ``alpha``) per channel, and scaled
        by the weight's map: ~0.15 s per distinct alpha for ggx instead of ~1.5 s per
        distinct texel.  Equal to ``albedo_table`` of the texel's bound model up to
        rounding (the sum of interpolated lobes is the interpolated sum).  Tables are kept
        in the object.
        """
        from gonio.simulator.render import _ALBEDO_THETA, albedo_table

        theta = np.asarray(theta, dtype=np.float64)
        out = np.zeros((x.shape[0], 3))
        if self.layout.kind == "mix":
            lab = self.labels_at(x)
            for k in np.unique(lab):
                t = self._albedo.get(("mix", int(k)))
                if t is None:
                    t = self._albedo[("mix", int(k))] = albedo_table(self.materials[int(k)])
                on = lab == k
                out[on] = t(theta[on])
            return out
        P = self.params_at(x)
        m = x.shape[0]
        th = np.repeat(theta, 3)  # one row per point and channel
        for i, (lobe, names, lin, other) in enumerate(self._lobes()):
            rows = np.stack([P[names[n]].reshape(-1) for n in other], -1) if other else None
            val = np.empty(m * 3)
            if rows is None:
                val[:] = np.interp(th, _ALBEDO_THETA, self._lobe_table(i, lobe, lin, {}))
            else:
                uniq, inv = np.unique(rows, axis=0, return_inverse=True)
                inv = np.reshape(inv, -1)
                for u in range(len(uniq)):
                    on = inv == u
                    key = {n: float(v) for n, v in zip(other, uniq[u], strict=True)}
                    val[on] = np.interp(th[on], _ALBEDO_THETA, self._lobe_table(i, lobe, lin, key))
            w = np.ones((m, 3))
            for n in lin:
                w = w * P[names[n]]
            out += w * val.reshape(m, 3)
        return out

    def __repr__(self) -> str:
        return f"<SpatialBRDF {self.description}>"


def build_spatial_brdf(scene: Any, *, load_measured: bool = True) -> SpatialBRDF:
    """The scene's spatially varying sample BRDF (:class:`SpatialBRDF`).

    ``load_measured=False`` checks that a mix's measured files exist without reading
    them (their materials are then None: for :func:`check_layout` only).

    Raises
    ------
    ConfigError
        As :func:`load_layout`; a material that is not a valid BRDF (its field
        ``sample.mix.materials[k]`` named) or a base parameter out of bounds.
    """
    import gonio.brdf

    layout = load_layout(scene)
    s = scene.sample
    if layout.kind == "maps":
        model = _model(scene)
        base = {k: np.asarray(v, dtype=np.float64) for k, v in s.brdf.params.items()}
        try:
            return SpatialBRDF(layout, model=model, base=base)
        except GonioError as exc:
            raise ConfigError(f"sample.brdf.params: {exc}") from None
    materials, specs = [], []
    for k, spec in enumerate(s.mix.materials):
        what = f"sample.mix.materials[{k}]"
        try:
            if spec.file is not None:
                path = scene.resolve(spec.file)
                if not path.is_file():
                    raise ConfigError(f"{what}.file: {path} does not exist")
                materials.append(gonio.brdf.load(path) if load_measured else None)
                specs.append({"file": path.name})
            else:
                model = gonio.brdf.get_model(spec.model, **spec.options)
                params = {n: np.asarray(v, dtype=np.float64) for n, v in spec.params.items()}
                materials.append(model.bind(params, channels=3))
                specs.append(
                    {
                        "model": spec.model,
                        "options": dict(spec.options),
                        "params": materials[-1].metadata["params"],
                    }
                )
        except ConfigError:
            raise
        except GonioError as exc:
            raise ConfigError(f"{what}: {exc}") from None
    return SpatialBRDF(layout, materials=materials, specs=specs)


# -- ground truth ---------------------------------------------------------------------


def _centres(size: tuple[float, float], shape: tuple[int, int]) -> np.ndarray:
    """Texel centres (ny, nx, 3) of a grid, sample frame, m."""
    w, h = size
    ny, nx = shape
    cx = -w / 2 + (np.arange(nx) + 0.5) * w / nx
    cy = h / 2 - (np.arange(ny) + 0.5) * h / ny
    X, Y = np.meshgrid(cx, cy)
    return np.stack([X, Y, np.zeros_like(X)], -1)


def truth_bytes(scene: Any, brdf: SpatialBRDF | None = None) -> bytes:
    """The ground-truth HDF5 file of a spatially varying sample, as bytes.

    Attributes ``schema`` ("gonio.svbrdf_truth"), ``schema_version`` (1), ``model`` (the
    spec string, or "mix"), ``options`` (JSON), ``texels`` [nx, ny] (the finest map's
    grid), ``sample_size`` [w, h] (m), ``orientation``, ``channels``; datasets
    ``params/<name>`` (ny, nx, 3) float64 for every parameter of the model (the maps
    resampled to the finest grid by nearest texel, the others constant); for a mix
    ``labels`` (ny, nx) int64 and ``materials`` (JSON list of the material specs), plus
    ``params/<name>`` when all materials are one analytic model.

    Raises
    ------
    ConfigError
        As :func:`build_spatial_brdf`.
    """
    import h5py

    b = build_spatial_brdf(scene) if brdf is None else brdf
    lay = b.layout
    ny, nx = lay.shape
    pts = _centres(lay.size, (ny, nx)).reshape(-1, 3)
    params: dict[str, np.ndarray] = {}
    if lay.kind == "maps":
        model_name = scene.sample.brdf.model
        options = dict(scene.sample.brdf.options)
        params = {k: v.reshape(ny, nx, 3) for k, v in b.params_at(pts).items()}
    else:
        model_name, options = "mix", {}
        analytic = [m for m in b.materials if getattr(m, "format", "") == "analytic"]
        names = {m.model.name for m in analytic}
        if len(analytic) == len(b.materials) and len(names) == 1:
            lab = b.labels_at(pts)
            for k in b.materials[0].params:
                stack = np.stack([np.broadcast_to(m.params[k], (3,)) for m in b.materials])
                params[k] = stack[lab].reshape(ny, nx, 3)
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.attrs["schema"] = TRUTH_SCHEMA
        f.attrs["schema_version"] = TRUTH_VERSION
        f.attrs["model"] = model_name
        f.attrs["options"] = json.dumps(options)
        f.attrs["texels"] = np.array([nx, ny], dtype=np.int64)
        f.attrs["sample_size"] = np.array(lay.size, dtype=np.float64)
        f.attrs["orientation"] = ORIENTATION
        f.attrs["channels"] = ["R", "G", "B"]
        g = f.create_group("params")
        for k, v in params.items():
            g.create_dataset(k, data=np.ascontiguousarray(v, dtype=np.float64), track_times=False)
        if lay.kind == "mix":
            assert lay.labels is not None
            f.create_dataset("labels", data=lay.labels.astype(np.int64), track_times=False)
            f.create_dataset("materials", data=json.dumps(b.specs), track_times=False)
    return buf.getvalue()


def write_truth(path: str | Path, scene: Any) -> Path:
    """Write :func:`truth_bytes` of ``scene`` to ``path`` atomically; returns the path."""
    from gonio.atomic import write_bytes_atomic

    p = Path(path)
    write_bytes_atomic(p, truth_bytes(scene), parents=True)
    return p


@dataclass(frozen=True)
class SVBRDFTruth:
    """A spatially varying sample's ground truth (:func:`read_truth`).

    Attributes
    ----------
    model
        The model spec string, or "mix".
    texels
        ``(nx, ny)`` of the stored grid.
    sample_size
        ``(w, h)``, m.
    params
        ``name -> (ny, nx, 3)`` float64.
    labels
        ``(ny, nx)`` int64 material labels (a mix), else None.
    materials
        The mix's material specs (JSON-decoded), else [].
    options
        The model's keyword options.
    """

    model: str
    texels: tuple[int, int]
    sample_size: tuple[float, float]
    params: dict[str, np.ndarray]
    labels: np.ndarray | None = None
    materials: list[Any] = field(default_factory=list)
    options: dict[str, Any] = field(default_factory=dict)

    def params_at(self, nx: int, ny: int) -> dict[str, np.ndarray]:
        """The parameters on another texel grid ``nx x ny``: ``name -> (ny, nx, 3)``.

        A finer grid (a multiple of the stored one) repeats each texel (exact); a coarser
        grid (the stored one a multiple of it) takes each block's mean, exact where the
        block is uniform (:meth:`uniform_at`).

        Raises
        ------
        ValueError
            The grids do not nest along an axis.
        """
        return {k: _resample(v, self.texels, (nx, ny)) for k, v in self.params.items()}

    def uniform_at(self, nx: int, ny: int) -> np.ndarray:
        """(ny, nx) bool: texels of the grid ``nx x ny`` whose truth is one value (every
        parameter and label constant over the texel)."""
        sx, sy = self.texels
        out = np.ones((ny, nx), bool)
        fields = list(self.params.values())
        if self.labels is not None:
            fields.append(self.labels[..., None].astype(np.float64))
        for v in fields:
            if nx >= sx and ny >= sy:
                break
            lo = -_resample(-v, self.texels, (nx, ny), np.max)
            hi = _resample(v, self.texels, (nx, ny), np.max)
            out &= np.all(lo == hi, axis=-1)
        return out


def _resample(v: np.ndarray, src: tuple[int, int], dst: tuple[int, int], reduce=np.mean):
    (sx, sy), (nx, ny) = src, dst
    for a, b, axis in ((sy, ny, 0), (sx, nx, 1)):
        if b % a and a % b:
            raise ValueError(
                f"texel grid {nx} x {ny} does not nest with the truth's {sx} x {sy} "
                "(one must be a whole multiple of the other along each axis)"
            )
        if b >= a:
            v = np.repeat(v, b // a, axis=axis)
        else:
            k = a // b
            shape = v.shape[:axis] + (b, k) + v.shape[axis + 1 :]
            v = reduce(v.reshape(shape), axis=axis + 1)
    return v


def read_truth(path: str | Path) -> SVBRDFTruth:
    """Read ``SESSION/truth/svbrdf.h5`` (:func:`truth_bytes`).

    Raises
    ------
    FileFormatError
        The file is missing, not HDF5, or not a gonio SVBRDF truth file of a known
        version (the file and what is wrong are named).
    """
    import h5py

    p = Path(path)
    if not p.is_file():
        raise FileFormatError(p, "does not exist")
    try:
        with h5py.File(p, "r") as f:
            if f.attrs.get("schema") != TRUTH_SCHEMA:
                raise FileFormatError(p, f"attribute 'schema' is not {TRUTH_SCHEMA!r}")
            if int(f.attrs.get("schema_version", -1)) != TRUTH_VERSION:
                raise FileFormatError(
                    p, f"schema_version {f.attrs.get('schema_version')!r}; expected 1"
                )
            nx, ny = (int(v) for v in f.attrs["texels"])
            params = {k: np.asarray(f["params"][k], dtype=np.float64) for k in f["params"]}
            for k, v in params.items():
                if v.shape != (ny, nx, 3):
                    raise FileFormatError(
                        p, f"dataset 'params/{k}' has shape {v.shape}, expected {(ny, nx, 3)}"
                    )
            labels = np.asarray(f["labels"], dtype=np.int64) if "labels" in f else None
            materials = json.loads(f["materials"].asstr()[()]) if "materials" in f else []
            return SVBRDFTruth(
                model=str(f.attrs["model"]),
                texels=(nx, ny),
                sample_size=tuple(float(v) for v in f.attrs["sample_size"]),  # type: ignore[arg-type]
                params=params,
                labels=labels,
                materials=materials,
                options=json.loads(f.attrs.get("options", "{}")),
            )
    except (OSError, KeyError) as exc:
        raise FileFormatError(p, f"not a readable SVBRDF truth file ({exc})") from None
