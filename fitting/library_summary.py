"""The summary table of a material library: ``summary.csv`` and ``summary.parquet``.

One row per material folder of ``LIB/`` (from its ``fit.json`` and ``input.json``) and per
failure of the run, sorted by material name; columns in DEVELOPING.md, "Libraries and
Dask".
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["read_record", "read_summary_rows", "summary_rows", "write_summary"]

INPUT_RECORD = "input.json"


def read_record(folder: Path) -> dict[str, Any] | None:
    """The ``input.json`` of a material folder, or None (absent or unreadable)."""
    try:
        rec = json.loads((folder / INPUT_RECORD).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) else None


def _fit_row(folder: Path, status: str) -> dict[str, Any] | None:
    """The summary row of a material folder (from its fit.json and input.json)."""
    from gonio.fitting.select import format_model_spec

    rec = read_record(folder)
    try:
        fit_doc = json.loads((folder / "fit.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if rec is None:
        return None
    diag = fit_doc.get("diagnostics") or {}
    spec = format_model_spec(fit_doc["model"], fit_doc.get("model_options") or {})
    row: dict[str, Any] = {
        "material": folder.name,
        "status": status,
        "source": rec.get("source"),
        "kind": rec.get("kind"),
        "digest": rec.get("digest"),
        "model": spec,
        "n_samples": fit_doc.get("n_samples"),
        "cost": fit_doc.get("cost"),
        "bic": diag.get("bic"),
        "success": fit_doc.get("success"),
        "selection": json.dumps(
            [
                {k: s.get(k) for k in ("model", "criterion", "cost", "success")}
                for s in diag.get("selection") or []
            ]
        )
        if diag.get("selection")
        else None,
        "error": None if fit_doc.get("success") else fit_doc.get("message"),
    }
    channels = fit_doc.get("channels") or []
    for name, values in (fit_doc.get("params") or {}).items():
        sig = (fit_doc.get("std") or {}).get(name) or [None] * len(values)
        for c, v, s in zip(channels, values, sig, strict=False):
            row[f"param.{name}.{c}"] = _num(v)
            row[f"sigma.{name}.{c}"] = _num(s)
    return row


def _num(v: Any) -> float | None:
    if v is None:
        return None
    if isinstance(v, str):  # save_json writes inf as "inf"
        return float(v)
    return float(v)


_FIXED_COLUMNS = (
    "material", "status", "source", "kind", "digest", "model", "n_samples", "cost", "bic",
    "success", "selection", "error",
)  # fmt: skip


def _columns(rows: Sequence[dict[str, Any]]) -> list[str]:
    # parameter columns in order of appearance: each fit's own order (R, G, B)
    extra = dict.fromkeys(k for r in rows for k in r if k not in _FIXED_COLUMNS)
    return [*_FIXED_COLUMNS, *extra]


def write_summary(lib: Path, rows: list[dict[str, Any]]) -> None:
    import csv
    import io

    import pyarrow as pa
    import pyarrow.parquet as pq

    from gonio.atomic import atomic_path, write_text_atomic

    cols = _columns(rows)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({c: _csv_cell(r.get(c)) for c in cols})
    write_text_atomic(lib / "summary.csv", buf.getvalue())
    types = {
        "n_samples": pa.int64(),
        "cost": pa.float64(),
        "bic": pa.float64(),
        "success": pa.bool_(),
    }
    arrays = {}
    for c in cols:
        values = [r.get(c) for r in rows]
        if c.startswith(("param.", "sigma.")):
            arrays[c] = pa.array(values, type=pa.float64())
        else:
            arrays[c] = pa.array(values, type=types.get(c, pa.string()))
    with atomic_path(lib / "summary.parquet") as tmp:
        pq.write_table(pa.table(arrays), tmp)


def _csv_cell(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
    return str(v)


def read_summary_rows(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The rows of a library's ``summary.parquet`` (list of dicts; missing -> None)."""
    import pyarrow.parquet as pq

    return pq.read_table(path).to_pylist()


def summary_rows(
    lib: Path,
    materials: Sequence[Any],
    status: dict[str, str],
    failed: dict[str, str],
    digests: dict[str, str],
) -> list[dict[str, Any]]:
    """Every material folder of the library (fitted now, unchanged, or kept from earlier
    runs of other sources) and this run's failures, sorted by material name."""
    rows: dict[str, dict[str, Any]] = {}
    for folder in sorted(p for p in lib.iterdir() if p.is_dir() and not p.name.startswith(".")):
        name = folder.name
        st = status.get(name, "kept")
        if st == "failed":
            continue
        row = _fit_row(folder, st)
        if row is not None:
            rows[name] = row
    by_name = {m.name: m for m in materials}
    for name, message in failed.items():
        m = by_name.get(name)
        rows[name] = {
            "material": name,
            "status": "failed",
            "source": str(m.path) if m else name,
            "kind": m.kind if m else None,
            "digest": digests.get(name),
            "error": message,
        }
    return [rows[k] for k in sorted(rows)]
