"""Per-texel fits of a spatially varying sample: ``gonio fit TEXELS.h5 --svbrdf``.

One model with per-texel parameters.  Every texel of a texel file (:mod:`gonio.texels`)
is fitted on its own with the single-input fit (:func:`gonio.fitting.fit`, the same
loss, multistart and covariance), so a texel's parameters and standard deviations mean
what a ``gonio fit`` of that texel's samples would report.

The texels run as tasks on dask.distributed (:mod:`gonio.distributed`, the engine of the
material libraries).  A task is a block of consecutive texels, ``(path, t0, t1,
options)``; the worker reads that hyperslab itself (``open_texels(path).block(t0, t1)``)
and returns the parameter block (a few kB).  The block size is *measured*: the client
fits a few texels spread over the file first and sizes blocks to about
:data:`TARGET_TASK_S` of work, rounded to whole chunks of the file when a block spans
several.  Each texel's fit depends only on its own samples and a fixed seed, and runs
with BLAS on one thread (as ``fit_material`` in the library), so the maps are the same
bits whatever the block size, the worker or the engine (``workers=0``: this process).

``model="auto"``: model selection (:func:`gonio.fitting.fit` with ``"auto"``) on each
of up to :data:`AUTO_TEXELS` texels spread over the sample, the spec most of them chose
for every texel (pooled samples were tried first and called a glossy map matte: see
``_choose_model``).

A block that fails (its file unreadable, a worker lost twice) is reported by name
(``texels T0-T1``); its texels stay NaN with ``success`` False and the other blocks'
results are kept.

Spatial regularisation (``smooth > 0``, :func:`smooth_maps`) is a second, cheap pass on
the fitted maps, not a joint fit: see there.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from gonio.errors import FitError, GonioError

__all__ = [
    "AUTO_TEXELS",
    "TARGET_TASK_S",
    "SVBRDFOptions",
    "SVBRDFResult",
    "TexelBlock",
    "fit_block",
    "fit_svbrdf",
    "plan_blocks",
    "smooth_maps",
]

#: Work per task the block size aims at (s): long against dask's per-task overhead
#: (a few ms), short enough that a lost worker costs little and progress moves.
TARGET_TASK_S = 1.0
#: Texels whose own model selections choose the model for ``model="auto"`` (by majority).
AUTO_TEXELS = 16
#: Texels fitted in the client to measure the per-texel cost.
_PROBE_TEXELS = 3


@dataclasses.dataclass(frozen=True)
class SVBRDFOptions:
    """The options of a per-texel fit (the same for every texel).

    Attributes
    ----------
    model
        A model spec (``"lambert+ggx"``, ``"lambert+ggx[fresnel=schlick]"``) or ``"auto"``.
    model_options
        Sorted ``(key, value)`` pairs of model options (``--option``).
    candidates
        Candidate specs of ``model="auto"`` (None: the default set).
    loss, robust, f_scale, algorithm, energy_conservation
        As :func:`gonio.fitting.fit`.
    smooth
        Spatial regularisation weight lambda (dimensionless, >= 0; 0: none), see
        :func:`smooth_maps`.
    """

    model: str = "lambert+ggx"
    model_options: tuple[tuple[str, str], ...] = ()
    candidates: tuple[str, ...] | None = None
    loss: str = "auto"
    robust: str | None = None
    f_scale: float = 1.0
    algorithm: str = "auto"
    energy_conservation: bool = True
    smooth: float = 0.0

    def check(self) -> None:
        """Refuse an unknown model or option, or a bad ``smooth``, before any work.

        Raises
        ------
        GonioError
            The message names the model spec or the value.
        """
        if not (np.isfinite(self.smooth) and self.smooth >= 0):
            raise GonioError(f"--smooth must be a finite number >= 0, got {self.smooth}")
        for spec in [*(self.candidates or ()), *([] if self.model == "auto" else [self.model])]:
            _model_of(spec, self.model_options if spec == self.model else ())

    def fit_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :func:`gonio.fitting.fit` (the model left out)."""
        return {
            "loss": self.loss,
            "robust": self.robust,
            "f_scale": self.f_scale,
            "algorithm": self.algorithm,
            "energy_conservation": self.energy_conservation,
            "model_options": dict(self.model_options) or None,
        }


def _model_of(spec: str, model_options: tuple[tuple[str, str], ...] = ()) -> Any:
    from gonio.brdf import get_model
    from gonio.fitting.select import parse_model_spec

    name, opts = parse_model_spec(spec)
    return get_model(name, **{**opts, **dict(model_options)})


@dataclasses.dataclass(frozen=True)
class TexelBlock:
    """One task: texels ``t0 <= t < t1`` of the texel file ``path`` (a few hundred bytes)."""

    path: str
    t0: int
    t1: int
    options: SVBRDFOptions

    @property
    def name(self) -> str:
        """The block's name in progress lines and failure reports."""
        return f"texels {self.t0}-{self.t1 - 1}"


def _fit_texel(samples: Any, options: SVBRDFOptions, names: tuple[str, ...], n_ch: int) -> dict:
    """Fit one texel; NaN parameters and a message when it cannot be fitted."""
    from gonio.fitting import fit

    n_valid = int(np.count_nonzero(samples.valid))
    empty = {
        "params": {k: np.full(n_ch, np.nan) for k in names},
        "std": {k: np.full(n_ch, np.nan) for k in names},
        "cost": np.nan,
        "rms": np.nan,
        "n": n_valid,
        "success": False,
    }
    try:
        r = fit(samples, options.model, **options.fit_kwargs())
    except FitError as exc:
        return {**empty, "message": str(exc)}
    v = samples.valid
    y = np.asarray(samples.brdf, dtype=np.float64)[v]
    f = r.bind().eval(samples.wi[v], samples.wo[v])
    sig = None if samples.brdf_std is None else np.asarray(samples.brdf_std)[v]
    if sig is not None and np.all(np.isfinite(sig)) and np.all(sig > 0):
        z = (y - f) / sig  # normalised: ~1 where the model and the sigmas fit
    else:
        z = (y - f) / max(float(np.sqrt(np.mean(y * y))), 1e-300)
    return {
        "params": {k: np.asarray(r.params[k], dtype=np.float64) for k in names},
        "std": {k: np.asarray(r.std[k], dtype=np.float64) for k in names},
        "cost": float(r.cost),
        "rms": float(np.sqrt(np.mean(z * z))),
        "n": int(r.n_samples),
        "success": bool(r.success),
        "message": "" if r.success else str(r.message),
    }


def _unfitted(n: int, n_ch: int, names: tuple[str, ...]) -> dict[str, Any]:
    """The per-texel arrays of ``n`` texels before any fit: NaN values, 0 samples, no
    success (what a texel that cannot be fitted, or a failed block, keeps)."""
    return {
        "params": {k: np.full((n, n_ch), np.nan) for k in names},
        "std": {k: np.full((n, n_ch), np.nan) for k in names},
        "cost": np.full(n, np.nan),
        "rms_residual": np.full(n, np.nan),
        "n_samples": np.zeros(n, dtype=np.int64),
        "success": np.zeros(n, dtype=bool),
    }


def fit_block(block: TexelBlock) -> dict[str, Any]:
    """Read and fit one block of texels (a worker task).

    Returns
    -------
    dict
        ``params``/``std``: name -> (n, C) float64; ``cost`` (n,), ``rms_residual`` (n,)
        (RMS of the residuals over their sigmas, dimensionless; over the RMS datum when
        sigmas are unknown), ``n_samples`` (n,) int, ``success`` (n,) bool, ``messages``
        {texel: why} for texels not fitted or not converged, ``seconds`` (wall time).

    Raises
    ------
    GonioError
        The file or block cannot be read (the message names the file).
    """
    from threadpoolctl import threadpool_limits

    from gonio.fitting.library import load_kernels
    from gonio.texels import open_texels

    load_kernels()  # the same evaluation paths whatever the worker fitted before
    start = time.perf_counter()
    o = block.options
    names = tuple(_model_of(o.model, o.model_options).param_names)
    with open_texels(block.path) as tf:
        texels = tf.block(block.t0, block.t1)
        n_ch = len(tf.channels)
    n = block.t1 - block.t0
    out: dict[str, Any] = {**_unfitted(n, n_ch, names), "messages": {}}
    # BLAS on one thread: a pool of another size sums in another order, and the result
    # would depend on where the block ran (see fitting/library.py, fit_material).
    with threadpool_limits(limits=1):
        for i, s in enumerate(texels):
            r = _fit_texel(s, o, names, n_ch)
            for k in names:
                out["params"][k][i] = r["params"][k]
                out["std"][k][i] = r["std"][k]
            out["cost"][i] = r["cost"]
            out["rms_residual"][i] = r["rms"]
            out["n_samples"][i] = r["n"]
            out["success"][i] = r["success"]
            if r.get("message"):
                out["messages"][block.t0 + i] = r["message"]
    out["seconds"] = time.perf_counter() - start
    return out


def plan_blocks(
    n_texels: int, texel_cost_s: float, chunk_texels: int = 1, target_s: float = TARGET_TASK_S
) -> list[tuple[int, int]]:
    """Split ``n_texels`` into blocks of about ``target_s`` of fitting each.

    A block of several chunks is a whole number of chunks (a worker then reads whole
    chunks only); a block smaller than a chunk divides it evenly where it can.

    Returns
    -------
    list of (t0, t1)
        Consecutive, covering ``0 <= t < n_texels``.
    """
    n_texels = int(n_texels)
    if n_texels <= 0:
        return []
    cost = float(texel_cost_s)
    size = n_texels if not (np.isfinite(cost) and cost > 0) else int(round(target_s / cost))
    size = max(1, min(size, n_texels))
    ct = max(1, int(chunk_texels))
    if size >= ct:
        size = (size // ct) * ct
    else:
        while ct % size:
            size -= 1
    return [(t0, min(t0 + size, n_texels)) for t0 in range(0, n_texels, size)]


def _spread(n_texels: int, k: int) -> np.ndarray:
    """``k`` texel indices spread evenly over ``0..n_texels-1``."""
    return np.unique(np.linspace(0, n_texels - 1, min(k, n_texels)).round().astype(int))


def _choose_model(path: Path, options: SVBRDFOptions) -> tuple[str, Any]:
    """Model selection by the texels: ``fit(samples, "auto")`` on each of up to
    :data:`AUTO_TEXELS` texels spread over the sample, then the spec most of them chose
    (ties: the earlier, simpler candidate).

    Not on the pooled samples: pooled, the texels' different albedos are the largest
    misfit of every candidate, so the diffuse model's cost stays within the matte rule's
    10x of the lobe's and a glossy sample was called matte (the test map: "lambert").
    """
    from threadpoolctl import threadpool_limits

    from gonio.fitting import fit
    from gonio.fitting.select import DEFAULT_CANDIDATES, format_model_spec
    from gonio.texels import open_texels

    kw = options.fit_kwargs()
    kw.pop("model_options")
    votes: dict[str, int] = {}
    with open_texels(path) as tf, threadpool_limits(limits=1):
        for t in _spread(tf.n_texels, AUTO_TEXELS):
            s = tf.samples(int(t))
            try:
                r = fit(s, "auto", candidates=options.candidates, **kw)
            except FitError:
                continue  # a texel without enough samples has no vote
            spec = format_model_spec(r.model, r.model_options)
            votes[spec] = votes.get(spec, 0) + 1
    if not votes:
        raise FitError(f"{path}: --model auto: no texel could be fitted to choose a model")
    order = list(options.candidates or DEFAULT_CANDIDATES)
    rank = {
        spec: (-n, order.index(spec) if spec in order else len(order)) for spec, n in votes.items()
    }
    best = min(votes, key=lambda spec: rank[spec])
    table = [
        {"model": spec, "texels": n}
        for spec, n in sorted(votes.items(), key=lambda kv: rank[kv[0]])
    ]
    return best, table


@dataclasses.dataclass
class SVBRDFResult:
    """Fitted parameter maps of one texel file.

    Attributes
    ----------
    source
        The texel file.
    model
        The model spec fitted per texel.
    param_names, channels
        The model's parameters and the colour channels.
    shape
        ``(ny, nx)`` texels; row 0 at +y, column 0 at -x (the texel convention).
    sample_size
        ``(w, h)`` of the sample rectangle (m).
    params, std
        name -> (ny, nx, C) float64 maps (natural units; shape parameters repeated over C).
        ``std``: one sigma of each texel's fit.
    cost, rms_residual
        (ny, nx): each texel's fit cost and residual RMS (over the sigmas).
    n_samples
        (ny, nx) int: samples each texel's fit used.
    success
        (ny, nx) bool.
    failed_blocks
        Block name -> error of the blocks that failed (their texels NaN).
    messages
        Flat texel index -> why, for texels not fitted or not converged.
    selection
        ``model="auto"``: ``[{"model": spec, "texels": votes}]``, the winner first.
    smooth
        The regularisation weight applied (0: none); ``params_unsmoothed`` then holds
        the per-texel fits.
    timing
        ``texel_cost_s`` (measured, per texel), ``block_texels``, ``n_blocks``,
        ``task_bytes`` (one item, pickled), ``result_bytes`` (one block's result, pickled),
        ``wall_s``, ``engine``.
    """

    source: Path
    model: str
    param_names: tuple[str, ...]
    channels: tuple[str, ...]
    shape: tuple[int, int]
    sample_size: tuple[float, float]
    params: dict[str, np.ndarray]
    std: dict[str, np.ndarray]
    cost: np.ndarray
    rms_residual: np.ndarray
    n_samples: np.ndarray
    success: np.ndarray
    failed_blocks: dict[str, str] = dataclasses.field(default_factory=dict)
    messages: dict[int, str] = dataclasses.field(default_factory=dict)
    selection: Any = None
    smooth: float = 0.0
    params_unsmoothed: dict[str, np.ndarray] | None = None
    timing: dict[str, Any] = dataclasses.field(default_factory=dict)


def _measure_cost(path: Path, options: SVBRDFOptions) -> float:
    """Seconds per texel, from fitting a few texels spread over the file here."""
    with _texel_file(path) as tf:
        n = tf.n_texels
    ts = _spread(n, _PROBE_TEXELS)
    times = []
    for t in ts:
        r = fit_block(TexelBlock(str(path), int(t), int(t) + 1, options))
        times.append(r["seconds"])
    return float(np.median(times))


@contextlib.contextmanager
def _texel_file(path: Path):
    from gonio.texels import open_texels

    with open_texels(path) as tf:
        yield tf


def fit_svbrdf(
    path: str | Path,
    options: SVBRDFOptions = SVBRDFOptions(),
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    block_texels: int | None = None,
    connect_timeout_s: float | None = None,
    console: Any = None,
    err_console: Any = None,
    on_client: Callable[[Any], None] | None = None,
) -> SVBRDFResult:
    """Fit every texel of a texel file.

    Parameters
    ----------
    path
        A texel file (``texels.h5``, :mod:`gonio.texels`).
    options
        The fit options.
    scheduler
        A dask scheduler address (``tcp://HOST:PORT``); None: a local cluster.
    workers
        Local worker processes (default one per core); 0: fit in this process, block
        after block (no dask).  Not with ``scheduler``.
    block_texels
        Texels per task; default: measured (:data:`TARGET_TASK_S` of work per task).
    connect_timeout_s
        Seconds to wait for ``scheduler``.
    console, err_console
        rich consoles for progress and for the failed blocks' lines.
    on_client
        Called with the dask client once it is connected (tests, benchmarks).

    Returns
    -------
    SVBRDFResult
        Failed blocks are in it; this function does not raise for them.

    Raises
    ------
    FileFormatError
        ``path`` is not a texel file (raised before any work).
    GonioError
        Unknown model or option; ``scheduler`` with ``workers``; the scheduler cannot be
        reached (before any task).
    """
    import pickle

    from rich.console import Console

    from gonio.distributed import TaskFailure, check_engine, run_tasks, task_engine

    console = console or Console()
    err_console = err_console or Console(stderr=True)
    path = Path(path).absolute()
    check_engine(scheduler, workers)
    options.check()
    with _texel_file(path) as tf:
        n_texels, shape, channels = tf.n_texels, tuple(tf.shape), tuple(tf.channels)
        sample_size, chunk = tuple(tf.sample_size), int(tf.chunk_texels)
    # The engine first: a scheduler that cannot be reached is reported before any work
    # (the model vote and the cost probe fit texels here).
    engine = task_engine(
        scheduler, workers, connect_timeout_s=connect_timeout_s, on_client=on_client
    )
    with engine as (client, where):
        selection = None
        if options.model == "auto":
            spec, selection = _choose_model(path, options)
            console.print(
                f"model selection on {sum(row['texels'] for row in selection)} texels spread "
                f"over the sample: {spec} ("
                + ", ".join(f"{row['model']} {row['texels']}" for row in selection)
                + "), fitted per texel",
                markup=False,
                highlight=False,
                soft_wrap=True,
            )
            options = dataclasses.replace(options, model=spec, model_options=(), candidates=None)
        names = tuple(_model_of(options.model, options.model_options).param_names)
        start = time.perf_counter()
        if block_texels is None:
            cost = _measure_cost(path, options)
            blocks = plan_blocks(n_texels, cost, chunk)
        else:
            cost = float("nan")
            blocks = plan_blocks(n_texels, TARGET_TASK_S / max(int(block_texels), 1), 1)
        items = [TexelBlock(str(path), t0, t1, options) for t0, t1 in blocks]
        n_ch = len(channels)
        flat = _unfitted(n_texels, n_ch, names)
        failed: dict[str, str] = {}
        messages: dict[int, str] = {}
        by_name = {b.name: b for b in items}
        result_bytes = 0
        console.print(
            f"fitting {options.model} to {n_texels} texels ({shape[1]} x {shape[0]}) in "
            f"{len(items)} block(s) of {blocks[0][1] - blocks[0][0]} on {where}"
            + ("" if not np.isfinite(cost) else f" (measured {cost * 1e3:.0f} ms per texel)"),
            markup=False,
            highlight=False,
            soft_wrap=True,
        )

        def arrived(name: Any, outcome: Any) -> None:
            nonlocal result_bytes
            b = by_name[name]
            if isinstance(outcome, TaskFailure):
                failed[name] = outcome.error
                err_console.print(
                    f"error: {path}: {name}: {outcome.error}",
                    style="red",
                    markup=False,
                    highlight=False,
                    soft_wrap=True,
                )
            else:
                sl = slice(b.t0, b.t1)
                for k in names:
                    flat["params"][k][sl] = outcome["params"][k]
                    flat["std"][k][sl] = outcome["std"][k]
                for k in ("cost", "rms_residual", "n_samples", "success"):
                    flat[k][sl] = outcome[k]
                messages.update(outcome["messages"])
                if not result_bytes:
                    result_bytes = len(pickle.dumps(outcome))

        run_tasks(
            client,
            fit_block,
            items,
            key_of=lambda b: b.name,
            description="fitting texels",
            arrived=arrived,
            console=console,
        )
    ny, nx = shape
    res = SVBRDFResult(
        source=path,
        model=options.model,
        param_names=names,
        channels=channels,
        shape=(ny, nx),
        sample_size=(float(sample_size[0]), float(sample_size[1])),
        params={k: v.reshape(ny, nx, n_ch) for k, v in flat["params"].items()},
        std={k: v.reshape(ny, nx, n_ch) for k, v in flat["std"].items()},
        cost=flat["cost"].reshape(ny, nx),
        rms_residual=flat["rms_residual"].reshape(ny, nx),
        n_samples=flat["n_samples"].reshape(ny, nx),
        success=flat["success"].reshape(ny, nx),
        failed_blocks=failed,
        messages=dict(sorted(messages.items())),
        selection=selection,
        timing={
            "texel_cost_s": cost,
            "block_texels": blocks[0][1] - blocks[0][0],
            "n_blocks": len(items),
            "task_bytes": len(pickle.dumps(items[0])),
            "result_bytes": result_bytes,
            "wall_s": time.perf_counter() - start,
            "engine": where,
        },
    )
    if options.smooth > 0:
        res.params_unsmoothed = {k: v.copy() for k, v in res.params.items()}
        res.params = smooth_maps(res.params, res.std, options.smooth, _model_of(options.model))
        res.smooth = float(options.smooth)
    return res


def smooth_maps(
    params: dict[str, np.ndarray], std: dict[str, np.ndarray], lam: float, model: Any
) -> dict[str, np.ndarray]:
    """Spatially regularised maps: a Gaussian Markov random field on the fitted maps.

    For each parameter and channel, the map ``p`` minimising
    ``sum_t w_t (p_t - phat_t)^2 + lam * wbar * sum_{t~s} (p_t - p_s)^2`` over the
    4-neighbour edges ``t~s``, with ``phat`` the per-texel fit, ``w_t = 1 / std_t^2``
    its precision (0 where the texel has no fit: such texels are filled from their
    neighbours) and ``wbar`` the median precision, so ``lam`` is dimensionless:
    ``lam = 1`` weighs a neighbour difference like a typical texel's own data.  Shape
    parameters (roughness) are smoothed in log space (their std as ``std / value``).
    One sparse solve per map (``scipy.sparse.linalg.spsolve``); the result is clipped to
    the model's bounds.

    This is a post-fit regularisation, not a joint fit: the samples are not revisited,
    and the maps' ``std`` stay those of the per-texel fits (the prior's information is
    not counted, so they are conservative).

    Parameters
    ----------
    params, std
        name -> (ny, nx, C) maps (natural units).
    lam
        The weight (>= 0; 0 returns the maps unchanged).
    model
        The fitted model (its ``bounds`` and ``linear_params``).

    Returns
    -------
    dict
        name -> (ny, nx, C) smoothed maps.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    out = {k: np.array(v, dtype=np.float64, copy=True) for k, v in params.items()}
    if lam <= 0:
        return out
    any_map = next(iter(params.values()))
    ny, nx = any_map.shape[:2]
    idx = np.arange(ny * nx).reshape(ny, nx)
    edges = np.concatenate(
        [
            np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], axis=1),
            np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], axis=1),
        ]
    )
    n = ny * nx
    ones = np.ones(len(edges))
    adj = sp.coo_matrix((ones, (edges[:, 0], edges[:, 1])), shape=(n, n))
    adj = (adj + adj.T).tocsr()
    lap = sp.diags(np.asarray(adj.sum(axis=1)).ravel()) - adj
    linear = set(getattr(model, "linear_params", ()))
    for name, p in params.items():
        log = name not in linear
        for c in range(p.shape[2]):
            v = p[:, :, c].ravel()
            s = std[name][:, :, c].ravel()
            ok = np.isfinite(v) & np.isfinite(s) & (s > 0) & ((v > 0) if log else True)
            if not ok.any():
                continue
            x = np.where(ok, np.log(np.where(ok, v, 1.0)) if log else v, 0.0)
            s_x = np.where(ok, s / np.abs(np.where(ok, v, 1.0)) if log else s, np.inf)
            w = np.where(ok, 1.0 / np.square(s_x), 0.0)
            wbar = float(np.median(w[ok]))
            a = (sp.diags(w) + lam * wbar * lap).tocsc()
            sol = spsolve(a, w * x)
            sol = np.exp(sol) if log else sol
            lo, hi = model.bounds.get(name, (-np.inf, np.inf))
            out[name][:, :, c] = np.clip(sol, lo, hi).reshape(ny, nx)
    return out
