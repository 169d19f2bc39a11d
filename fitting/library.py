"""Material libraries: ``gonio fit DIR_OR_GLOB --model auto --out LIB/``.

Every samples file (``samples.h5``) and measured BRDF file (RGL ``.bsdf``, MERL ``.binary``)
found under a folder, or matched by a glob, is fitted with the fit of the single-input
``gonio fit`` (:func:`gonio.fitting.fit`, model selection included), one material per
task on dask.distributed (:mod:`gonio.distributed`), and written to its own folder::

    LIB/
      .gonio.lock            one writer at a time (gonio.locks)
      paper_white_rgb/       fit.json, material.xml, slices.png, residuals.png (as
                             `gonio fit`), input.json (source, content digest, options)
      ...
      summary.csv            one row per material: status, source, digest, model,
      summary.parquet        parameters and sigmas, cost, BIC, the selection, the error

Who does what: the client (this process) finds the inputs, digests them (XXH3-64 of the
bytes) and skips a material whose ``input.json`` records the same digest and the same fit
options; the workers read and fit the others and send back the files' bytes; the client
writes each material's folder once, atomically (:func:`gonio.atomic.atomic_directory`), as
its result arrives.  So a task redone after a worker was killed is still written once,
only the client needs write access to ``LIB/``, and only paths travel to the workers.

A file that cannot be read (or fitted) is reported by name, the others are fitted, the
summary lists the failure and the command ends with exit code 1.  Ctrl-C stops the
workers; the materials written so far stay and are skipped by the next run.

Per-texel fits (issue 18, SVBRDF) will use the same engine: a task is then a block of
texels of one chunked samples file (``(path, texel range)`` as the item), the worker
reads its chunk and returns the parameter block; see DEVELOPING.md, "Libraries and Dask".
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import glob
import json
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from gonio.errors import FitError, GonioError
from gonio.fitting.library_summary import (
    INPUT_RECORD,  # per-material record of what was fitted: the skip test
    read_record,
    summary_rows,
    write_summary,
)

__all__ = [
    "INPUT_RECORD",
    "SAMPLINGS",
    "FitOptions",
    "LibraryReport",
    "Material",
    "file_digest",
    "find_materials",
    "fit_library",
    "fit_material",
]

#: The files of one single-input ``gonio fit`` (the same set per material).
FIT_OUTPUTS = ("fit.json", "material.xml", "slices.png", "residuals.png")
SUMMARY_NAMES = ("summary.csv", "summary.parquet")
_MEASURED_SUFFIXES = (".bsdf", ".binary")
_SAMPLES_SUFFIXES = (".h5", ".hdf5")
_SAMPLES_NAME = "samples.h5"

#: Direction grids a measured file is sampled on before fitting
#: (:func:`gonio.fitting.sampling.direction_grid` keyword arguments).  ``standard`` is
#: the grid of the single-input ``gonio fit`` (9 x 18 x 36 = 5832 pairs); ``coarse``
#: (5 x 9 x 18 = 810 pairs) is for quick looks and the tests.
SAMPLINGS: dict[str, dict[str, Any]] = {
    "standard": {},
    "coarse": {"theta_i_deg": (0.0, 20.0, 40.0, 60.0, 80.0), "n_theta_o": 9, "n_phi_o": 18},
}


# --------------------------------------------------------------------------- inputs


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """Everything that changes a material's result folder (part of the skip test).

    Attributes mirror the options of ``gonio fit``: ``model`` (a name or ``"auto"``),
    ``model_options`` (sorted ``(key, value)`` pairs), ``candidates`` (model specs for
    ``auto``, None for the default set), ``loss``, ``robust``, ``f_scale`` (residual
    units), ``algorithm``, ``energy_conservation``, ``plots``, and ``sampling`` (a key of
    :data:`SAMPLINGS`, for measured files).
    """

    model: str = "auto"
    model_options: tuple[tuple[str, str], ...] = ()
    candidates: tuple[str, ...] | None = None
    loss: str = "auto"
    robust: str | None = None
    f_scale: float = 1.0
    algorithm: str = "auto"
    energy_conservation: bool = True
    plots: bool = True
    sampling: str = "standard"

    def __post_init__(self) -> None:
        if self.sampling not in SAMPLINGS:
            raise GonioError(
                f"unknown sampling {self.sampling!r}; expected one of {', '.join(SAMPLINGS)}"
            )

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form (what ``input.json`` records)."""
        d = dataclasses.asdict(self)
        d["model_options"] = dict(self.model_options)
        d["candidates"] = None if self.candidates is None else list(self.candidates)
        return d

    def digest(self, kind: str = "measured") -> str:
        """XXH3-64 of the canonical JSON of :meth:`as_dict` (hex).

        For ``kind="samples"`` the sampling is left out: it applies to measured files
        only, so changing it does not refit sessions.
        """
        import xxhash

        d = self.as_dict()
        if kind == "samples":
            d.pop("sampling")
        text = json.dumps(d, sort_keys=True, separators=(",", ":"))
        return xxhash.xxh3_64_hexdigest(text.encode())

    def check(self) -> None:
        """Refuse an unknown model (or candidate) or option here, before any work, rather
        than once per material on the workers.

        Raises
        ------
        GonioError
            The message names the model spec.
        """
        from gonio.brdf import get_model
        from gonio.fitting.select import parse_model_spec

        specs = [] if self.model == "auto" else [self.model]
        specs += list(self.candidates or ())
        for spec in specs:
            name, opts = parse_model_spec(spec)
            if spec == self.model:
                opts = {**opts, **dict(self.model_options)}
            get_model(name, **opts)


@dataclasses.dataclass(frozen=True)
class Material:
    """One input of a library.

    Attributes
    ----------
    name
        The result folder's name: the input's path below the search root, ``/`` as
        ``__``, without the suffix (measured files) or the ``samples.h5`` (sessions).
    path
        The input file (absolute).
    kind
        ``"samples"`` or ``"measured"``.
    """

    name: str
    path: Path
    kind: str


@dataclasses.dataclass(frozen=True)
class _Task:
    """What travels to a worker: one material and the options (a few hundred bytes)."""

    material: Material
    options: FitOptions


def file_digest(path: str | os.PathLike) -> str:
    """XXH3-64 of a file's bytes, hex (read in 4 MiB blocks).

    Raises
    ------
    OSError
        The file cannot be read.
    """
    import xxhash

    h = xxhash.xxh3_64()
    with open(path, "rb") as fh:
        for block in iter(functools.partial(fh.read, 1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def _kind_of(path: Path) -> str | None:
    suffix = path.suffix.lower()
    if suffix in _MEASURED_SUFFIXES:
        return "measured"
    if suffix in _SAMPLES_SUFFIXES:
        return "samples"
    return None


def _glob_root(pattern: str) -> Path:
    """The folder a glob pattern's matches are named relative to: its literal prefix."""
    parts = Path(pattern).parts
    lit = []
    for part in parts:
        if glob.has_magic(part):
            break
        lit.append(part)
    return Path(*lit) if lit else Path(".")


def _walk(folder: Path, skip: Path | None) -> list[Path]:
    found = []
    for dirpath, dirnames, filenames in os.walk(folder):
        d = Path(dirpath)
        # hidden folders (temporaries of atomic writes) and the library itself
        dirnames[:] = sorted(
            n
            for n in dirnames
            if not n.startswith(".") and (skip is None or (d / n).resolve() != skip)
        )
        for n in sorted(filenames):
            if n.startswith("."):
                continue
            if n == _SAMPLES_NAME or Path(n).suffix.lower() in _MEASURED_SUFFIXES:
                found.append(d / n)
    return found


def _material_name(path: Path, root: Path, kind: str) -> str:
    try:
        rel = path.resolve().relative_to(root.resolve())
    except ValueError:
        rel = Path(path.name)
    if kind == "samples" and rel.name.lower() == _SAMPLES_NAME:
        rel = rel.parent if rel.parent != Path(".") else Path(root.resolve().name)
    else:
        rel = rel.with_suffix("")
    name = "__".join(rel.parts)
    return name if name and not name.startswith(".") else f"_{name}"


def find_materials(
    source: str | os.PathLike, *, exclude: Path | None = None
) -> tuple[list[Material], list[tuple[Path, str]]]:
    """The inputs of a library under a folder or matched by a glob.

    Parameters
    ----------
    source
        A folder (searched recursively for ``samples.h5``, ``*.bsdf``, ``*.binary``;
        hidden entries skipped) or a glob pattern (``**`` recursive); a matched folder is
        searched, a matched file is taken when it is a samples or measured file.
    exclude
        A folder not to search (the library itself, when it lies under ``source``).

    Returns
    -------
    (materials, rejected)
        Materials sorted by name (names made distinct with a hash of the path where two
        inputs would share one); ``rejected``: matched files of no known kind, with why.

    Raises
    ------
    GonioError
        Nothing to fit was found (the message names ``source``).
    """
    text = str(source)
    rejected: list[tuple[Path, str]] = []
    if Path(text).is_dir():
        root = Path(text)
        files = _walk(root, exclude)
    else:
        root = _glob_root(text)
        files = []
        for m in sorted(glob.glob(text, recursive=True)):
            p = Path(m)
            if p.is_dir():
                files += _walk(p, exclude)
            elif _kind_of(p) is None:
                rejected.append(
                    (p, "not a samples file (.h5) or a measured BRDF file (.bsdf, .binary)")
                )
            else:
                files.append(p)
    seen: dict[Path, None] = {}
    for f in files:
        seen.setdefault(f.resolve(), None)
    materials = []
    for f in seen:
        kind = _kind_of(f)
        assert kind is not None
        materials.append(Material(_material_name(f, root, kind), f, kind))
    counts: dict[str, int] = {}
    for m in materials:
        counts[m.name] = counts.get(m.name, 0) + 1
    if any(c > 1 for c in counts.values()):
        import xxhash

        def tagged(m: Material) -> Material:
            tag = xxhash.xxh3_64_hexdigest(str(m.path).encode())[:6]
            return dataclasses.replace(m, name=f"{m.name}-{tag}")

        materials = [tagged(m) if counts[m.name] > 1 else m for m in materials]
    if not materials and not rejected:
        raise GonioError(
            f"{source}: no samples.h5, .bsdf or .binary files found "
            "(a folder is searched recursively; quote a glob so the shell leaves it alone)"
        )
    return sorted(materials, key=lambda m: m.name), rejected


# --------------------------------------------------------------------------- the task


def _load(material: Material, sampling: str) -> Any:
    if material.kind == "samples":
        from gonio.dataset import load_samples

        return load_samples(material.path)
    from gonio.brdf import load
    from gonio.fitting.sampling import sample_brdf

    return sample_brdf(load(material.path), source=str(material.path), **SAMPLINGS[sampling])


def _write_fit_files(r: Any, samples: Any, folder: Path, plots: bool) -> list[str]:
    """The files of a single-input ``gonio fit`` into ``folder``; returns notes."""
    from gonio.fitting.export import save_json, save_mitsuba_xml

    notes = []
    save_json(r, folder / "fit.json")
    try:
        save_mitsuba_xml(r, folder / "material.xml")
    except FitError as exc:
        notes.append(f"no Mitsuba export: {exc}")
    if plots:
        from gonio.fitting.plots import plot_residual_map, plot_slices

        plot_slices(r, samples, folder / "slices.png")
        plot_residual_map(r, samples, folder / "residuals.png")
    return notes


def load_kernels() -> None:
    """Load the numba kernels before a task fits (every engine, so the same paths).

    The evaluators take numba for a mid-size batch (4096 to 10^5 pairs) only once its
    kernels are loaded (``gonio.brdf.microfacet``, ``gonio.fitting.varpro``: a small CLI
    job never pays numba's import), and numba's sums round differently from numpy's in
    the last bits.  Without this, whether a fit's energy check or design ran on numba
    would depend on what the process had fitted before (the first 10^5-pair quadrature
    loads the kernels): a worker's history, so the bytes would depend on how tasks were
    spread over workers.  ``GONIO_NUMBA=0`` keeps numpy everywhere.
    """
    if os.environ.get("GONIO_NUMBA") == "0":
        return
    import gonio.brdf.kernels  # noqa: F401
    import gonio.fitting.kernels  # noqa: F401


def fit_material(task: _Task) -> dict[str, Any]:
    """Read and fit one material; the files of its result folder as bytes (a worker task).

    Returns
    -------
    dict
        ``files`` (name -> bytes: fit.json, material.xml, the plots), ``digest`` (of the
        bytes this worker read), ``n_samples``, ``success``, ``message``, ``notes``.

    Raises
    ------
    GonioError
        The file cannot be read or fitted (the message names it).
    """
    import tempfile

    from gonio.fitting import fit

    m, o = task.material, task.options
    try:
        digest = file_digest(m.path)
    except OSError as exc:
        raise GonioError(f"{m.path}: cannot read: {exc.strerror or exc}") from None
    from threadpoolctl import threadpool_limits

    load_kernels()
    samples = _load(m, o.sampling)
    # BLAS on one thread in every engine: a pool of another size sums in another order,
    # and nlopt's stopping test can then end a candidate's search one step apart
    # ("roundoff limited" against "ftol reached", same cost), so the library's bytes
    # would depend on where the task ran. Tasks, not BLAS, are the parallelism here.
    with threadpool_limits(limits=1):
        r = fit(
            samples,
            o.model,
            loss=o.loss,
            robust=o.robust,
            f_scale=o.f_scale,
            algorithm=o.algorithm,
            energy_conservation=o.energy_conservation,
            candidates=o.candidates,
            model_options=dict(o.model_options) or None,
        )
    with tempfile.TemporaryDirectory(prefix="gonio-fit-") as tmp:
        notes = _write_fit_files(r, samples, Path(tmp), o.plots)
        files = {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir())}
    return {
        "files": files,
        "digest": digest,
        "n_samples": int(r.n_samples),
        "success": bool(r.success),
        "message": str(r.message),
        "notes": notes,
    }


# --------------------------------------------------------------------------- the library


@dataclasses.dataclass
class LibraryReport:
    """What one library run did.

    Attributes
    ----------
    fitted, skipped
        Material names fitted now / skipped (input and options unchanged).
    failed
        Material name (or path, for an input of no known kind) -> error message.
    not_converged
        Materials written whose fit did not converge.
    written
        Material folders this run wrote (each once).
    rows
        The summary rows (as written to summary.csv / summary.parquet).
    """

    fitted: list[str] = dataclasses.field(default_factory=list)
    skipped: list[str] = dataclasses.field(default_factory=list)
    failed: dict[str, str] = dataclasses.field(default_factory=dict)
    not_converged: list[str] = dataclasses.field(default_factory=list)
    written: list[Path] = dataclasses.field(default_factory=list)
    rows: list[dict[str, Any]] = dataclasses.field(default_factory=list)


def _refuse_foreign_outputs(lib: Path, names: list[str]) -> None:
    """Refuse (before any fit) to write over files no library fit wrote: a material's
    folder that holds files but no library record, or ``summary.csv`` / ``summary.parquet``
    in a folder where no material has a record (a user's own files were replaced, exit 0).

    Raises
    ------
    FitError
        Naming the files; ``--force`` replaces them.
    """
    if not lib.is_dir():
        return
    foreign = []
    for name in names:
        folder = lib / name
        if folder.is_dir() and any(folder.iterdir()) and read_record(folder) is None:
            foreign.append(str(folder))
    ours = any(d.is_dir() and read_record(d) is not None for d in lib.iterdir())
    if not ours:
        foreign += [str(lib / n) for n in ("summary.csv", "summary.parquet") if (lib / n).exists()]
    if foreign:
        raise FitError(
            f"library {lib}: {', '.join(foreign)} exist(s) and no library fit wrote them; "
            "use --force to replace them or choose another --out"
        )


def _up_to_date(folder: Path, digest: str, options_digest: str) -> bool:
    rec = read_record(folder)
    return (
        rec is not None
        and rec.get("digest") == digest
        and rec.get("options_digest") == options_digest
        and (folder / "fit.json").is_file()
    )


def _write_material(
    lib: Path, material: Material, options: FitOptions, result: dict[str, Any]
) -> Path:
    from gonio.atomic import atomic_directory

    folder = lib / material.name
    record = {
        "schema": "gonio.library_input",
        "schema_version": 1,
        "material": material.name,
        "source": str(material.path),
        "kind": material.kind,
        "digest": result["digest"],
        "digest_algorithm": "xxh3_64",
        "options": options.as_dict(),
        "options_digest": options.digest(material.kind),
        "n_samples": result["n_samples"],
        "notes": result["notes"],
    }
    ours = {*FIT_OUTPUTS, INPUT_RECORD}
    keep = tuple(p.name for p in folder.iterdir() if p.name not in ours) if folder.is_dir() else ()
    with atomic_directory(folder, keep=keep) as stage:
        for name, data in result["files"].items():
            (stage / name).write_bytes(data)
        (stage / INPUT_RECORD).write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    return folder


@contextlib.contextmanager
def _library_folder(lib: Path) -> Iterator[None]:
    """Hold ``LIB/.gonio.lock`` for the run; remove a LIB/ this run created and left empty."""
    from gonio.locks import LOCK_NAME, hold_lock

    created = not lib.exists()
    lib.mkdir(parents=True, exist_ok=True)
    try:
        with hold_lock(lib / LOCK_NAME, f"library {lib}/"):
            yield
    except BaseException:
        if created and {p.name for p in lib.iterdir()} <= {LOCK_NAME}:
            shutil.rmtree(lib, ignore_errors=True)
        raise


def fit_library(
    source: str | os.PathLike,
    lib: str | os.PathLike,
    options: FitOptions = FitOptions(),
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    force: bool = False,
    connect_timeout_s: float | None = None,
    console: Any = None,
    err_console: Any = None,
    on_client: Callable[[Any], None] | None = None,
) -> LibraryReport:
    """Fit every material under ``source`` into the library folder ``lib``.

    Parameters
    ----------
    source
        A folder or a glob pattern (:func:`find_materials`).
    lib
        The library folder (created; one writer at a time).
    options
        The fit options (the same for every material).
    scheduler
        A dask scheduler address (``tcp://HOST:PORT``); None: a local cluster.
    workers
        Local worker processes (default one per core); 0: fit in this process, one
        material after the other (no dask).  Not with ``scheduler``.
    force
        Refit materials that are up to date.
    connect_timeout_s
        Seconds to wait for ``scheduler`` (default
        :data:`gonio.distributed.DEFAULT_CONNECT_TIMEOUT_S`).
    console, err_console
        rich consoles for progress and per-material lines / error lines.
    on_client
        Called with the dask client once it is connected (tests and benchmarks: to watch
        or disturb the workers); not called with ``workers=0``.

    Returns
    -------
    LibraryReport
        Failures are in it (and in the summary); this function does not raise for them.

    Raises
    ------
    GonioError
        Nothing found under ``source``; the library is in use by another process
        (:class:`gonio.locks.LockedError`); the scheduler cannot be reached
        (:class:`gonio.distributed.SchedulerUnreachable`: before any work, nothing
        written).
    """
    from rich.console import Console

    from gonio.distributed import TaskFailure, check_engine, run_tasks, task_engine

    console = console or Console()
    err_console = err_console or Console(stderr=True)
    lib = Path(lib)
    check_engine(scheduler, workers)
    options.check()
    materials, rejected = find_materials(source, exclude=lib.resolve() if lib.exists() else None)
    if not force:
        _refuse_foreign_outputs(lib, [m.name for m in materials])
    report = LibraryReport()
    status: dict[str, str] = {}

    def fail(name: str, path: Path, message: str) -> None:
        report.failed[name] = message
        status[name] = "failed"
        shown = message if str(path) in message else f"{path}: {message}"
        err_console.print(
            f"error: {shown}", style="red", markup=False, highlight=False, soft_wrap=True
        )

    engine = task_engine(
        scheduler, workers, connect_timeout_s=connect_timeout_s, on_client=on_client
    )
    with _library_folder(lib), engine as (client, where):
        for path, why in rejected:
            fail(str(path), path, why)
        todo: list[Material] = []
        digests: dict[str, str] = {}
        for m in materials:
            try:
                digests[m.name] = file_digest(m.path)
            except OSError as exc:
                fail(m.name, m.path, f"cannot read: {exc.strerror or exc}")
                continue
            if not force and _up_to_date(lib / m.name, digests[m.name], options.digest(m.kind)):
                report.skipped.append(m.name)
                status[m.name] = "unchanged"
            else:
                todo.append(m)
        if report.skipped:
            console.print(
                f"{len(report.skipped)} material(s) unchanged since their last fit: skipped",
                highlight=False,
                soft_wrap=True,
                markup=False,
            )
        by_name = {m.name: m for m in todo}
        console.print(
            f"fitting {len(todo)} material(s) on {where}",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )

        def arrived(name: Any, outcome: Any) -> None:
            m = by_name[name]
            if isinstance(outcome, TaskFailure):
                fail(m.name, m.path, outcome.error)
                return
            try:
                report.written.append(_write_material(lib, m, options, outcome))
            except OSError as exc:
                fail(m.name, lib / m.name, f"cannot write: {exc.strerror or exc}")
                return
            report.fitted.append(m.name)
            status[m.name] = "fitted"
            if not outcome["success"]:
                report.not_converged.append(m.name)
            for note in outcome["notes"]:
                console.print(f"{m.name}: {note}", markup=False, highlight=False, soft_wrap=True)

        run_tasks(
            client,
            fit_material,
            [_Task(m, options) for m in todo],
            key_of=lambda t: t.material.name,
            description="fitting",
            arrived=arrived,
            console=console,
        )
        report.rows = summary_rows(lib, materials, status, report.failed, digests)
        write_summary(lib, report.rows)
    return report
