"""``gonio fit``: fit a BRDF model to samples or to a measured BRDF file."""

from __future__ import annotations

import contextlib
import math
import shutil
from collections.abc import Iterator
from pathlib import Path

import click

from gonio.errors import FitError, GonioError
from gonio.fitting.library_cli import FIT_SOURCE, library_dispatch
from gonio.fitting.svbrdf_cli import svbrdf_dispatch

__all__ = ["fit"]

_OUTPUTS = ("fit.json", "material.xml", "slices.png", "residuals.png")


def _load_input(path: Path):
    if path.suffix.lower() in (".h5", ".hdf5"):
        from gonio.dataset import load_samples

        return load_samples(path), "samples"
    from gonio.brdf import load
    from gonio.fitting.sampling import sample_brdf

    return sample_brdf(load(path), source=str(path)), "measured file sampled on a grid"


#: Largest --f-scale: residuals are in sigmas or BRDF units, and a scale past this makes
#: the robust loss plain least squares while its square overflows (1e308 read as "the
#: model is NaN or inf on these samples").
MAX_F_SCALE = 1e6


def _positive_scale(ctx, param, value: float) -> float:
    if not (math.isfinite(value) and 0 < value <= MAX_F_SCALE):
        raise click.BadParameter(
            f"expected a positive finite residual scale at most {MAX_F_SCALE:g}, got {value}"
        )
    return value


def _refuse_conflicts(
    model: str, options: dict[str, str], candidates: str | None, robust: str | None
) -> None:
    """Options that contradict each other or would be ignored: said, not resolved in
    silence (the last value won, or the option did nothing, exit 0)."""
    from gonio.brdf.registry import parse_model_spec

    _, in_spec = parse_model_spec(model)
    clash = sorted(k for k in options if k in in_spec and in_spec[k] != options[k])
    if clash:
        k = clash[0]
        raise click.UsageError(
            f"--model {model} sets {k}={in_spec[k]} and --option {k}={options[k]} another: "
            "give it once"
        )
    if candidates is not None and model != "auto":
        raise click.UsageError(f"--candidates chooses among models for --model auto, not {model}")
    if candidates is not None and not _split_candidates(candidates):
        raise click.BadParameter("expected at least one model name", param_hint="--candidates")
    ctx = click.get_current_context(silent=True)
    src = ctx.get_parameter_source("f_scale") if ctx is not None else None
    if robust is None and src == click.core.ParameterSource.COMMANDLINE:
        raise click.UsageError("--f-scale is the scale of --robust; give --robust too")


def _parse_options(items: tuple[str, ...]) -> dict[str, str]:
    opts: dict[str, str] = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq or not key.strip() or not value.strip():
            raise click.BadParameter(
                f"expected KEY=VALUE (e.g. fresnel=schlick), got {item!r}", param_hint="--option"
            )
        opts[key.strip()] = value.strip()
    return opts


def _split_candidates(text: str) -> tuple[str, ...]:
    """Split at commas outside brackets: 'a,b[x=1,y=2]' -> ('a', 'b[x=1,y=2]')."""
    parts, depth, cur = [], 0, ""
    for ch in text:
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            parts.append(cur.strip())
            cur = ""
        else:
            cur += ch
    parts.append(cur.strip())
    return tuple(p for p in parts if p)


@click.command(name="fit")
@click.argument("source", type=FIT_SOURCE)
@click.option(
    "--model",
    "-m",
    default="auto",
    show_default=True,
    help="Model name (lambert, oren-nayar, lambert+ggx, lambert+beckmann, "
    "lambert+ward, lambert+blinn-phong, ...) or 'auto' to choose by BIC.",
)
@click.option(
    "--option",
    "options",
    multiple=True,
    metavar="KEY=VALUE",
    help="Model option for --model (repeatable), e.g. --option fresnel=schlick (adds f0) "
    "or fresnel=dielectric (adds eta); the same as -m 'lambert+ggx[fresnel=schlick]'.",
)
@click.option(
    "--candidates",
    default=None,
    help="Comma-separated candidate models for --model auto, options in brackets: "
    "lambert,oren-nayar,lambert+ggx,lambert+ggx[fresnel=schlick].",
)
@click.option(
    "--loss",
    default="auto",
    show_default=True,
    type=click.Choice(["auto", "weighted_l2", "cosine_l2", "l2", "log"]),
    help="auto: weighted_l2 when every sample has a sigma, else cosine_l2.",
)
@click.option(
    "--robust",
    default=None,
    type=click.Choice(["soft_l1", "huber", "cauchy", "arctan"]),
    help="Robust penalty against outliers (scale: --f-scale, residual units).",
)
@click.option(
    "--f-scale",
    default=1.0,
    show_default=True,
    type=float,
    callback=_positive_scale,
    help="Residual size at which --robust starts to down-weight (residual units, > 0).",
)
@click.option(
    "--algorithm",
    default="auto",
    show_default=True,
    help="auto (Sobol multistart + LD_LBFGS), a local nlopt algorithm (LD_SLSQP, "
    "LD_MMA, LN_BOBYQA) or a global one (GN_DIRECT_L, GN_CRS2_LM, G_MLSL_LDS).",
)
@click.option("--no-energy", is_flag=True, help="Do not enforce directional albedo <= 1.")
@click.option(
    "--out",
    "-o",
    "out",
    default=None,
    type=click.Path(file_okay=False, path_type=Path),
    help="Output folder: fit.json, material.xml (Mitsuba 3), slices.png, residuals.png "
    "(required but with --svbrdf, whose default is SESSION/svbrdf/).",
)
@click.option("--plots/--no-plots", default=True, show_default=True)
@click.option("--force", is_flag=True, help="Replace the outputs of an earlier fit in --out.")
@svbrdf_dispatch  # --svbrdf: SOURCE a texel file, per-texel fits (gonio.fitting.svbrdf)
@library_dispatch  # SOURCE a folder or a glob: a material library (gonio.fitting.library)
def fit(
    source: Path,
    model: str,
    options: tuple[str, ...],
    candidates: str | None,
    loss: str,
    robust: str | None,
    f_scale: float,
    algorithm: str,
    no_energy: bool,
    out: Path,
    plots: bool,
    force: bool,
) -> None:
    """Fit a BRDF model to SOURCE and write the result to --out.

    SOURCE is a samples file (samples.h5 from `gonio capture reduce`) or a measured BRDF
    file (RGL .bsdf, MERL .binary), which is sampled on a regular grid of directions first.

    \b
    Examples:
      gonio fit S/samples.h5 --out fit/                 choose the model by BIC
      gonio fit S/samples.h5 -m lambert+ggx --out fit/  one model
      gonio fit paper_white_rgb.bsdf -m auto --out paper/
      gonio fit film.bsdf -m lambert+ggx --option fresnel=schlick --out film/

    Shape parameters (roughness) are shared by all colour channels; albedo and ks are fitted
    per channel.  The summary shows each parameter with its one-sigma uncertainty.
    """
    if out.exists() and Path.cwd().resolve().is_relative_to(out.resolve()):
        # the outputs replace the folder as a whole (one rename): the current folder
        # cannot be renamed ('.': "Device or resource busy"), and an absolute path to it
        # was swapped from under the shell
        raise FitError(
            f"--out {out}: the current folder (or one holding it); fit replaces its --out "
            "folder as a whole: give a subfolder, e.g. --out fit/"
        )
    if out.exists() and not out.is_dir():
        # click's file_okay=False lets a device or a socket through (/dev/null)
        raise FitError(
            f"--out {out}: exists and is not a folder; expected a folder for "
            f"{', '.join(_OUTPUTS)}"
        )
    existing = _existing_outputs(out)
    if existing and not force:
        raise FitError(
            f"{out} already holds {', '.join(p.name for p in existing)}; "
            "use --force to replace them or choose another --out"
        )
    model_options = _parse_options(options)
    if model_options and model == "auto":
        raise click.UsageError(
            "--option sets options of one --model; with --model auto put them in the "
            "candidates: --candidates 'lambert,lambert+ggx[fresnel=schlick]'"
        )
    _refuse_conflicts(model, model_options, candidates, robust)
    # forked before the output lock is taken and before anything else is imported or
    # loaded: it imports matplotlib while this process loads and fits
    # (gonio.figure_worker), so the less the fork inherits the sooner it starts
    worker = _start_plot_worker() if plots else None
    try:
        from rich.console import Console

        console = Console(stderr=False)
        samples, kind = _load_input(source)
        cands = _split_candidates(candidates) if candidates else None
        with _output_folder(out, force):
            try:
                r, written = _fit_and_write(
                    console, samples, source, out, model, model_options, cands, loss, robust,
                    f_scale, algorithm, no_energy, plots, worker,
                )  # fmt: skip
            except FitError as exc:
                # the input named: a measured file's samples are made here, and their
                # errors spoke of "samples.brdf" only
                if str(source) in str(exc):
                    raise
                raise FitError(f"{source}: {exc}") from None
    finally:
        if worker is not None:
            worker.close()
    _report(console, r, source, kind, written)


def _start_plot_worker():
    from gonio.figure_worker import FigureWorker

    return FigureWorker(warm=_load_plots)


def _load_plots() -> None:
    """The figure worker's warm-up: matplotlib, the plot module and the module of the
    samples (each job unpickles them in a process forked from this one: what is imported
    here is imported once, not once per figure)."""
    import gonio.dataset  # noqa: F401
    from gonio.fitting import plots

    plots.load_matplotlib()


def _existing_outputs(out: Path) -> list[Path]:
    return [out / n for n in _OUTPUTS if (out / n).exists()]


@contextlib.contextmanager
def _output_folder(out: Path, force: bool) -> Iterator[None]:
    """Hold the output folder for one writer (its ``.gonio.lock``) while fitting.

    A second ``gonio fit --out`` on the same folder is refused naming the holder's PID.
    A folder this call created is removed again when the fit fails before writing.
    """
    from gonio.locks import LOCK_NAME, hold_lock

    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with hold_lock(out / LOCK_NAME, f"output {out}/"):
            # Checked again under the lock: another fit may have finished meanwhile.
            existing = _existing_outputs(out)
            if existing and not force:
                raise FitError(
                    f"{out} already holds {', '.join(p.name for p in existing)}; "
                    "use --force to replace them or choose another --out"
                )
            yield
    except BaseException:
        if created and {p.name for p in out.iterdir()} <= {LOCK_NAME}:
            shutil.rmtree(out, ignore_errors=True)
        raise


def _write_outputs(console, r, samples, out: Path, plots: bool, worker=None) -> list[Path]:
    """Write fit.json, material.xml and the plots as one set (gonio.atomic.atomic_directory):
    a reader, or a kill at any moment, sees the previous set or this one, never a mix."""
    from gonio.atomic import atomic_directory
    from gonio.fitting.export import save_json, save_mitsuba_xml

    keep = tuple(p.name for p in out.iterdir() if p.name not in _OUTPUTS)
    names = []
    with atomic_directory(out, keep=keep) as stage:
        save_json(r, stage / "fit.json")
        names.append("fit.json")
        try:
            save_mitsuba_xml(r, stage / "material.xml")
            names.append("material.xml")
        except FitError as exc:
            # (--force) the set replaces the old one whole: no old material.xml survives
            console.print(f"no Mitsuba export: {exc}", style="yellow", markup=False)
        if plots:
            if worker is None or not worker.active:
                from gonio.fitting import plots as fig

                fig.plot_slices(r, samples, stage / "slices.png")
                fig.plot_residual_map(r, samples, stage / "residuals.png")
            else:  # both figures drawn beside this process, one per core
                from gonio.atomic import atomic_path
                from gonio.fitting import plots as fig

                jobs = {
                    "slices.png": worker.submit(fig.slices_png, r, samples),
                    "residuals.png": worker.submit(fig.residuals_png, r, samples),
                }
                for name, job in jobs.items():
                    try:
                        png = job.result()
                    except GonioError as exc:
                        raise FitError(f"drawing {name} failed: {exc}") from None
                    with atomic_path(stage / name) as tmp:
                        tmp.write_bytes(png)
            names += ["slices.png", "residuals.png"]
    return [out / n for n in names]


def _fit_and_write(
    console, samples, source, out, model, model_options, cands, loss, robust, f_scale,
    algorithm, no_energy, plots, worker=None,
):  # fmt: skip
    from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from gonio.fitting import fit as run_fit

    n_steps = (len(cands) if cands else 4) + 3 if model == "auto" else 4
    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}", markup=False),  # a spec's "[...]" is not markup
        BarColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as prog:
        task = prog.add_task(f"fitting {model} to {len(samples.wi)} samples", total=n_steps)

        def step(msg: str) -> None:
            prog.update(task, advance=1, description=msg)

        r = run_fit(
            samples,
            model,
            loss=loss,
            robust=robust,
            f_scale=f_scale,
            algorithm=algorithm,
            energy_conservation=not no_energy,
            candidates=cands,
            model_options=model_options or None,
            progress=step,
        )
        prog.update(task, description="writing outputs")
        written = _write_outputs(console, r, samples, out, plots, worker)
        prog.update(task, completed=n_steps)
    return r, written


def variance_split_rows(r) -> list[tuple[str, float, tuple[float, ...]]]:
    """``(label, std, (noise, geometry, systematic, calibration) shares)`` per free
    parameter of a fit whose samples carried geometric modes
    (``diagnostics["variance_split"]``; ``systematic``: the correlated radiometric budget
    terms, 0 in fits from before it), else []."""
    split = r.diagnostics.get("variance_split")
    if not split:
        return []
    rows = []
    for i, label in enumerate(split["labels"]):
        parts = tuple(
            float(split[k][i]) if k in split else 0.0
            for k in ("noise", "geometry", "systematic", "calibration")
        )
        total = sum(parts)
        if not (math.isfinite(total) and total > 0):
            continue  # at a bound (0) or undetermined (inf): no split to show
        rows.append((label, math.sqrt(total), tuple(x / total for x in parts)))
    return rows


def _report(console, r, source: Path, kind: str, written: list[Path]) -> None:
    from rich.markup import escape
    from rich.table import Table

    # escaped: rich reads a spec's options ("[fresnel=schlick]") as markup and drops them
    table = Table(
        title=escape(f"{r.spec} fitted to {source.name} ({kind}, {r.n_samples} samples)")
    )
    table.add_column("parameter")
    for c in r.channels:
        table.add_column(c, justify="right")
    for name, v in r.params.items():
        s = r.std[name]
        table.add_row(name, *[f"{x:.5g} ± {e:.2g}" for x, e in zip(v, s, strict=True)])
    console.print(table)
    split = variance_split_rows(r)
    if split:
        vt = Table(
            title="share of each parameter's variance (correlated errors: geometry modes, "
            "stray light, calibration scale)"
        )
        for col in ("parameter", "std", "noise", "geometry", "systematic", "calibration"):
            vt.add_column(col, justify="left" if col == "parameter" else "right")
        for label, std, shares in split:
            vt.add_row(label, f"{std:.2g}", *[f"{x:.0%}" for x in shares])
        console.print(vt)
    sel = r.diagnostics.get("selection")
    if sel:
        st = Table(title=f"model selection ({r.diagnostics.get('criterion', 'bic')})")
        for col in ("model", "criterion", "cost", "gloss 60° (GU)"):
            st.add_column(col)
        for row in sel:
            ic = row.get("criterion")
            st.add_row(
                escape(row["model"]),
                "failed" if ic is None else f"{ic:.1f}",
                "" if row.get("cost") is None else f"{row['cost']:.4g}",
                "" if row.get("gloss_60") is None else f"{row['gloss_60']:.1f}",
            )
        console.print(st)
        if r.diagnostics.get("selection_note"):
            console.print(r.diagnostics["selection_note"], markup=False)
    console.print(
        f"loss {r.loss}, cost {r.cost:.6g}, {'success' if r.success else 'FAILED'} "
        f"({r.message}); path {' -> '.join(r.algorithm)}; "
        f"condition number {r.diagnostics['condition_number']:.3g}",
        markup=False,
    )
    if r.diagnostics["at_bounds"]:
        console.print(f"at bounds: {', '.join(r.diagnostics['at_bounds'])}", markup=False)
    console.print("wrote " + ", ".join(str(p) for p in written), markup=False)
    if not r.success:
        raise FitError(f"the fit did not converge: {r.message}")
