"""The output folder of ``gonio fit TEXELS.h5 --svbrdf`` (default ``SESSION/svbrdf/``).

::

    svbrdf.h5          params/<name>, std/<name> (ny, nx, C) float64, cost, rms_residual,
                       n_samples, success (ny, nx); attrs: schema "gonio.svbrdf",
                       schema_version 1, model, channels, texels [nx, ny], sample_size,
                       orientation, source, smooth, failed_blocks (JSON)
    <name>.png         16-bit PNG per parameter map, <name>_std.png its one sigma;
    residual.png       the residual RMS map (over the sigmas);
    maps.json          each PNG's value range: value = lo + (hi - lo) * pixel / 65535
    preview.png        a figure of the maps
    material.xml       Mitsuba 3 (mitsuba_*.png textures), when the model maps
    material.mtlx      MaterialX standard_surface (mtlx_*.png textures), lambert+ggx only

PNG row 0 is texel row 0 (+y), column 0 is -x: the image looks at the sample from above.
NaN texels (not fitted) are stored as pixel 0 and listed by ``success`` in svbrdf.h5.
The folder is held by ``.gonio.lock`` and replaced as one set
(:func:`gonio.atomic.atomic_directory`), as ``gonio fit --out`` does.
"""

from __future__ import annotations

import contextlib
import json
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from gonio.errors import FitError
from gonio.fitting.svbrdf import SVBRDFResult

__all__ = ["OUTPUT_NAMES", "output_folder", "read_png_map", "write_png16", "write_svbrdf"]

SCHEMA = "gonio.svbrdf"
#: Fixed names this command writes (besides the per-parameter PNGs).
OUTPUT_NAMES = ("svbrdf.h5", "maps.json", "residual.png", "preview.png")


def _encode_png16(values: np.ndarray, lo: float, hi: float) -> bytes:
    import cv2

    v = np.asarray(values, dtype=np.float64)
    span = hi - lo if hi > lo else 1.0
    q = np.clip(np.rint((np.nan_to_num(v, nan=lo) - lo) / span * 65535.0), 0, 65535)
    img = q.astype(np.uint16)
    if img.ndim == 3:
        img = img[..., ::-1]  # OpenCV writes BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:  # pragma: no cover - OpenCV always encodes uint16 PNG
        raise FitError("cannot encode a 16-bit PNG")
    return buf.tobytes()


def write_png16(path: Path, values: np.ndarray, lo: float = 0.0, hi: float = 1.0) -> dict:
    """Write (ny, nx) or (ny, nx, 3) values as a 16-bit PNG over ``[lo, hi]``.

    Returns
    -------
    dict
        ``{"range": [lo, hi], "channels": ...}`` (the maps.json entry).
    """
    Path(path).write_bytes(_encode_png16(values, lo, hi))
    v = np.asarray(values)
    return {"range": [float(lo), float(hi)], "channels": 1 if v.ndim == 2 else int(v.shape[2])}


def read_png_map(path: Path, entry: dict) -> np.ndarray:
    """A map back from a PNG and its maps.json entry (values in natural units)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FitError(f"{path}: not a PNG image")
    if img.ndim == 3:
        img = img[..., ::-1]
    lo, hi = entry["range"]
    return lo + (hi - lo) * img.astype(np.float64) / 65535.0


def _range(v: np.ndarray) -> tuple[float, float]:
    f = np.asarray(v)[np.isfinite(v)]
    if f.size == 0:
        return 0.0, 1.0
    lo, hi = float(f.min()), float(f.max())
    lo = min(lo, 0.0)
    return lo, hi if hi > lo else lo + 1.0


def _map_view(v: np.ndarray) -> np.ndarray:
    """(ny, nx, C) -> an image: one channel when the map is equal over C (a shape
    parameter, shared by the channels) or C is not 3."""
    v = np.asarray(v)
    if v.ndim == 3 and (
        v.shape[2] != 3 or np.array_equal(v, v[..., :1].repeat(3, -1), equal_nan=True)
    ):
        return v[..., 0]
    return v


def _write_h5(res: SVBRDFResult, path: Path, extra: dict[str, Any]) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        a = f.attrs
        a["schema"] = SCHEMA
        a["schema_version"] = 1
        a["model"] = res.model
        a["channels"] = list(res.channels)
        a["texels"] = [res.shape[1], res.shape[0]]
        a["sample_size"] = list(res.sample_size)
        a["orientation"] = "row 0 at +y, column 0 at -x"
        a["source"] = str(res.source)
        a["smooth"] = float(res.smooth)
        a["failed_blocks"] = json.dumps(res.failed_blocks)
        a["exports"] = json.dumps(extra)
        for k in res.param_names:
            f.create_dataset(f"params/{k}", data=res.params[k])
            f.create_dataset(f"std/{k}", data=res.std[k])
            if res.params_unsmoothed is not None:
                f.create_dataset(f"unsmoothed/{k}", data=res.params_unsmoothed[k])
        f.create_dataset("cost", data=res.cost)
        f.create_dataset("rms_residual", data=res.rms_residual)
        f.create_dataset("n_samples", data=res.n_samples)
        f.create_dataset("success", data=res.success)


def _preview(res: SVBRDFResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gonio.atomic import atomic_path

    panels = [(k, _map_view(res.params[k])) for k in res.param_names]
    panels.append(("residual RMS (/sigma)", res.rms_residual))
    n = len(panels)
    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.2), squeeze=False)
    w, h = res.sample_size
    ext = (-w / 2 * 1e3, w / 2 * 1e3, -h / 2 * 1e3, h / 2 * 1e3)
    for ax, (title, v) in zip(axes[0], panels, strict=True):
        if v.ndim == 3:
            scale = np.nanmax(v) if np.isfinite(np.nanmax(v)) and np.nanmax(v) > 0 else 1.0
            ax.imshow(np.clip(np.nan_to_num(v / scale), 0, 1), extent=ext, interpolation="nearest")
            ax.set_title(f"{title} (RGB / {scale:.3g})")
        else:
            im = ax.imshow(v, extent=ext, interpolation="nearest", cmap="viridis")
            fig.colorbar(im, ax=ax, fraction=0.046)
            ax.set_title(title)
        ax.set_xlabel("x (mm)")
    axes[0][0].set_ylabel("y (mm)")
    smooth = f", smoothed (lambda {res.smooth:g})" if res.smooth else ""
    fig.suptitle(f"{res.model}: {res.shape[1]} x {res.shape[0]} texels, {res.source.name}{smooth}")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def write_svbrdf(
    res: SVBRDFResult, out: Path, *, plots: bool = True, keep: tuple[str, ...] = ()
) -> dict[str, Any]:
    """Write the output set of ``res`` into ``out`` (replaced as one set).

    Returns
    -------
    dict
        ``written`` (file names), ``notes`` (exports left out and why, clipped values),
        ``mtlx_error`` (the MaterialX mapping's relative RMSE, when exported).
    """
    from gonio.atomic import atomic_directory
    from gonio.fitting.select import parse_model_spec
    from gonio.fitting.svbrdf_export import (
        MITSUBA_TEXTURES,
        MTLX_TEXTURES,
        mitsuba_svbrdf_xml,
        mitsuba_textures,
        mtlx_document,
        mtlx_mapping,
        mtlx_mapping_error,
    )

    name, opts = parse_model_spec(res.model)
    notes: list[str] = []
    extra: dict[str, Any] = {}
    maps: dict[str, Any] = {
        "schema": "gonio.svbrdf_maps",
        "schema_version": 1,
        "encoding": "16-bit PNG: value = lo + (hi - lo) * pixel / 65535",
        "orientation": "row 0 at +y, column 0 at -x",
        "maps": {},
    }
    with atomic_directory(out, keep=keep) as stage:
        for k in res.param_names:
            for suffix, src in (("", res.params[k]), ("_std", res.std[k])):
                v = _map_view(src)
                lo, hi = _range(v)
                maps["maps"][f"{k}{suffix}.png"] = {
                    "parameter": k,
                    "quantity": "std" if suffix else "value",
                    **write_png16(stage / f"{k}{suffix}.png", v, lo, hi),
                }
        lo, hi = _range(res.rms_residual)
        maps["maps"]["residual.png"] = {
            "quantity": "rms residual over sigma",
            **write_png16(stage / "residual.png", res.rms_residual, lo, hi),
        }
        try:
            tex, clipped = mitsuba_textures(name, opts, res.params)
        except FitError as exc:
            notes.append(f"no Mitsuba export: {exc}")
        else:
            for key, fname in MITSUBA_TEXTURES.items():
                if key in tex:
                    # Mitsuba reads a bitmap's row 0 at v = 0 (-y): stored bottom row first
                    maps["maps"][fname] = {
                        "quantity": f"Mitsuba {key} texture",
                        "orientation": "row 0 at -y (Mitsuba: row 0 at v = 0)",
                        **write_png16(stage / fname, np.flipud(tex[key])),
                    }
            (stage / "material.xml").write_text(mitsuba_svbrdf_xml(name, opts), encoding="utf-8")
            if clipped:
                notes.append(f"Mitsuba export: {clipped} texture value(s) above 1 clipped")
            extra["mitsuba"] = {"clipped": clipped}
        if (
            name == "lambert+ggx"
            and opts.get("fresnel", "none") == "none"
            and len(res.channels) == 3
        ):
            mp = mtlx_mapping(res.params)
            for key, fname in MTLX_TEXTURES.items():
                maps["maps"][fname] = {
                    "quantity": f"MaterialX {key}",
                    **write_png16(stage / fname, mp[key]),
                }
            (stage / "material.mtlx").write_text(mtlx_document(mp), encoding="utf-8")
            err = mtlx_mapping_error(res.params, mp)
            extra["materialx"] = {
                "specular_IOR": mp["specular_IOR"],
                "f0": mp["f0"],
                "base_color_clipped": mp["clipped"],
                "relative_rmse": err,
            }
            notes.append(
                f"MaterialX standard_surface mapping: relative RMSE {err['median']:.1%} median, "
                f"{err['max']:.1%} max over {err['texels']} texels (approximate: see "
                "gonio.fitting.svbrdf_export)"
            )
        else:
            notes.append(f"no MaterialX export: mapped for lambert+ggx only, not {res.model}")
        maps["exports"] = extra
        (stage / "maps.json").write_text(json.dumps(maps, indent=2) + "\n", encoding="utf-8")
        _write_h5(res, stage / "svbrdf.h5", extra)
        if plots:
            _preview(res, stage / "preview.png")
        written = sorted(p.name for p in stage.iterdir() if not p.name.startswith("."))
    return {"written": written, "notes": notes, "mtlx_error": extra.get("materialx")}


@contextlib.contextmanager
def output_folder(out: Path, force: bool) -> Iterator[tuple[str, ...]]:
    """Hold ``out/.gonio.lock`` while fitting; yields the names to keep (not ours).

    Refuses (FitError) a folder that already holds an SVBRDF output without ``force``;
    removes a folder this call created when the run fails before writing.
    """
    from gonio.locks import LOCK_NAME, hold_lock

    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with hold_lock(out / LOCK_NAME, f"output {out}/"):
            ours = _ours(out)
            if ours and not force:
                raise FitError(
                    f"{out} already holds an SVBRDF fit ({', '.join(sorted(ours)[:4])}, ...); "
                    "use --force to replace it or choose another --out"
                )
            yield tuple(p.name for p in out.iterdir() if p.name not in ours)
    except BaseException:
        if created and {p.name for p in out.iterdir()} <= {LOCK_NAME}:
            shutil.rmtree(out, ignore_errors=True)
        raise


def _ours(out: Path) -> set[str]:
    """Names in ``out`` that a previous SVBRDF output wrote (from its maps.json)."""
    names = {n for n in OUTPUT_NAMES if (out / n).exists()}
    try:
        doc = json.loads((out / "maps.json").read_text(encoding="utf-8"))
        names |= {n for n in doc.get("maps", {}) if (out / n).exists()}
    except (OSError, ValueError):
        pass
    for n in ("material.xml", "material.mtlx"):
        if (out / n).exists() and (out / "svbrdf.h5").exists():
            names.add(n)
    return names
