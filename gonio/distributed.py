"""Independent tasks on dask.distributed: this machine (a ``LocalCluster``) or a cluster.

A material library, and later the texels of a spatially varying sample, is a set of
independent fits.  gonio runs them through dask.distributed rather than a process pool of
its own, with the same call on a laptop and on a cluster:

>>> with open_client() as client:                      # doctest: +SKIP
...     out = map_tasks(client, fit_one, paths, key_of=str)
>>> with open_client("tcp://head:8786") as client:     # doctest: +SKIP
...     out = map_tasks(client, fit_one, paths, key_of=str)

``out`` maps each key to the task's return value or to a :class:`TaskFailure` (the task
failed after its retries): one bad input never loses the others' results.  ``client=None``
runs the same tasks in this process, one after the other (the single-process path, which
must give the same results).

Only the items travel to the workers (paths and options, a few hundred bytes); workers
read the input files themselves, so a cluster's workers must see the same files at the
same paths (a shared file system).  Ctrl-C (``KeyboardInterrupt``) cancels the submitted
futures, and :func:`open_client` closes the local cluster on the way out, killing any
worker process that outlives the close: nothing keeps running.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import signal
import threading
import uuid
from collections.abc import Callable, Hashable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

from gonio import interrupts
from gonio.errors import GonioError

if TYPE_CHECKING:
    from distributed import Client

__all__ = [
    "DEFAULT_CONNECT_TIMEOUT_S",
    "SchedulerUnreachable",
    "TaskError",
    "TaskFailure",
    "check_engine",
    "map_tasks",
    "open_client",
    "rich_progress",
    "run_tasks",
    "task_engine",
]

#: Seconds to wait for a scheduler to answer (and for its first worker) before giving up.
DEFAULT_CONNECT_TIMEOUT_S = 10.0

# The thread pools a worker's tasks use (BLAS/OpenMP, numba).  A worker runs
# ``threads_per_worker`` tasks at once; letting every task start a pool of all cores
# would oversubscribe the machine by that factor.
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


class SchedulerUnreachable(GonioError):
    """No dask scheduler answered at an address (or it has no workers).

    Attributes
    ----------
    address
        The address that was tried (``tcp://HOST:PORT``).
    """

    def __init__(self, address: str, message: str) -> None:
        self.address = address
        super().__init__(message)


class TaskError(Exception):
    """What a task raised, carried back as its type name and message.

    The original exception class may not survive pickling (a third-party error with its
    own constructor; gonio's own errors pickle) or may not be importable on the client
    (a worker's environment can differ); its name and message always do.
    """

    def __init__(self, kind: str, message: str, deliberate: bool = False) -> None:
        super().__init__(kind, message, deliberate)
        self.kind = kind
        self.message = message
        self.deliberate = deliberate

    def __str__(self) -> str:
        return self.message if self.deliberate else f"{self.kind}: {self.message}"


@dataclasses.dataclass(frozen=True)
class TaskFailure:
    """A task that failed after its retries.

    Attributes
    ----------
    key
        The task's key (as ``key_of`` gave it).
    error
        The message: a :class:`~gonio.errors.GonioError`'s own (it names the file or value),
        else ``"Type: message"``.
    kind
        The exception's class name (``"FileFormatError"``, ``"KilledWorker"``).
    """

    key: Hashable
    error: str
    kind: str = "Exception"


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _run_guarded(fn: Callable[[Any], Any], item: Any) -> Any:
    """Run one task; re-raise its error as a :class:`TaskError` (always picklable).

    Still an exception, so dask's ``retries=`` applies to it.
    """
    try:
        return fn(item)
    except Exception as exc:
        raise TaskError(type(exc).__name__, str(exc), isinstance(exc, GonioError)) from None


def _failure(key: Hashable, exc: BaseException | None) -> TaskFailure:
    if isinstance(exc, TaskError):
        return TaskFailure(key, str(exc), exc.kind)
    if exc is None:
        return TaskFailure(key, "the task was lost (cancelled by the scheduler)", "Cancelled")
    return TaskFailure(key, f"{type(exc).__name__}: {exc}", type(exc).__name__)


@contextlib.contextmanager
def _sigint_caught(*, at_once: bool) -> Iterator[list[int]]:
    """Ctrl-C noted in the yielded list and raised as ``KeyboardInterrupt`` once the block
    is done; ``at_once`` also raises it at once.

    Deferred (``at_once=False``): a cluster shutting down must not be interrupted (a second
    Ctrl-C must not leave half of it running).  At once, but noted too: an interrupt
    raised inside a garbage-collector callback (distributed's GCDiagnosis) is printed as
    "Exception ignored" and lost, so a waiting loop checks the note as well."""
    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield caught
        return

    def note(signum: int, frame: Any) -> None:
        caught.append(signum)
        if at_once:
            raise KeyboardInterrupt

    old = signal.signal(signal.SIGINT, note)
    try:
        yield caught
    finally:
        signal.signal(signal.SIGINT, old)
    if caught:
        raise KeyboardInterrupt


def _check_address(scheduler: str) -> str:
    address = scheduler.strip()
    if "://" not in address:
        address = f"tcp://{address}"
    proto, _, rest = address.partition("://")
    host, colon, port = rest.rpartition(":")
    if proto not in ("tcp", "tls", "ucx", "inproc") or not colon or not host or not port.isdigit():
        raise SchedulerUnreachable(
            scheduler,
            f"scheduler address {scheduler!r}: expected tcp://HOST:PORT (e.g. tcp://head:8786)",
        )
    return address


def _kill_leftovers(pids: Iterable[int]) -> None:
    """Kill the worker processes of our local cluster that survived its close."""
    import psutil

    procs = []
    for pid in pids:
        with contextlib.suppress(psutil.Error):
            p = psutil.Process(pid)
            if p.ppid() == os.getpid():  # still our child: not a recycled PID
                procs.append(p)
    for p in procs:
        with contextlib.suppress(psutil.Error):
            p.kill()
    psutil.wait_procs(procs, timeout=10)


def _spawned_children() -> set[int]:
    """Our child processes that multiprocessing spawned (a local cluster's workers; a
    nanny restarts a killed worker as a new one)."""
    import psutil

    out = set()
    for p in psutil.Process().children(recursive=False):
        with contextlib.suppress(psutil.Error):
            if any("spawn_main" in part for part in p.cmdline()):
                out.add(p.pid)
    return out


@contextlib.contextmanager
def _local_client(workers: int, threads_per_worker: int) -> Iterator[Client]:
    import dask
    from distributed import Client, LocalCluster

    env = {v: str(threads_per_worker) for v in _THREAD_VARS}
    pids: set[int] = set()
    cluster = client = None
    try:
        # No dashboard, so the workers' statistical profiler (a thread sampling every
        # stack each 10 ms, for the dashboard's profile page) would only take the GIL
        # from the fits.  The nannies hand this config to the worker processes.
        with dask.config.set({"distributed.worker.profile.enabled": False}):
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=threads_per_worker,
                processes=True,
                # loopback only; the scheduler's HTTP routes on a free port (":8787" clashes
                # with any other cluster on the machine), no dashboard
                host="127.0.0.1",
                dashboard_address="127.0.0.1:0",
                scheduler_kwargs={"dashboard": False},
                silence_logs=logging.CRITICAL,
                env=env,
            )
        client = Client(cluster, set_as_default=False)
        pids = set(client.run(os.getpid).values())
        yield client
    finally:
        with _sigint_caught(at_once=False):
            pids |= _spawned_children()
            if client is not None:
                with contextlib.suppress(Exception):
                    client.close()
            if cluster is not None:
                with contextlib.suppress(Exception):
                    cluster.close()
            _kill_leftovers(pids)


@contextlib.contextmanager
def _remote_client(scheduler: str, timeout_s: float) -> Iterator[Client]:
    from distributed import Client

    address = _check_address(scheduler)
    try:
        client = Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise SchedulerUnreachable(
            address,
            f"no dask scheduler answered at {address} within {timeout_s:g} s ({exc}); "
            "start one with `dask scheduler` (and workers with `dask worker "
            f"{address}`) or check the address (no task was submitted)",
        ) from None
    try:
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except (OSError, TimeoutError):
            raise SchedulerUnreachable(
                address,
                f"the dask scheduler at {address} has no workers (waited {timeout_s:g} s); "
                f"start them with `dask worker {address}` (no task was submitted)",
            ) from None
        yield client
    finally:
        with _sigint_caught(at_once=False):
            client.close()


@contextlib.contextmanager
def open_client(
    scheduler: str | None = None,
    *,
    workers: int | None = None,
    threads_per_worker: int = 1,
    timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S,
) -> Iterator[Client]:
    """A dask.distributed client for the duration of the block.

    Parameters
    ----------
    scheduler
        None: start a ``LocalCluster`` of worker *processes* on this machine (closed, and
        its workers gone, when the block ends, Ctrl-C included).  An address
        (``tcp://HOST:PORT``; a bare ``HOST:PORT`` means tcp): connect to a running
        scheduler (``dask scheduler``) whose workers (``dask worker``) see the same files.
    workers
        Worker processes of the local cluster (default: one per core).  Not used with
        ``scheduler``.
    threads_per_worker
        Tasks a local worker runs at once; its BLAS and numba pools get as many threads.
    timeout_s
        Seconds to wait for the scheduler to answer and to have at least one worker.

    Raises
    ------
    SchedulerUnreachable
        Nothing answered at ``scheduler`` (or it has no workers) within ``timeout_s``:
        the message names the address.  Raised before any task is submitted.
    GonioError
        ``workers`` or ``threads_per_worker`` below 1.
    """
    if scheduler is None:
        n = _cores() if workers is None else int(workers)
        if n < 1 or threads_per_worker < 1:
            raise GonioError(
                f"a local cluster needs at least 1 worker of at least 1 thread, got "
                f"workers={workers}, threads_per_worker={threads_per_worker}"
            )
        with _local_client(n, int(threads_per_worker)) as client:
            yield client
    else:
        with _remote_client(scheduler, float(timeout_s)) as client:
            yield client


ProgressFn = Callable[[Hashable, Any, int, int], None]


def map_tasks(
    client: Client | None,
    fn: Callable[[Any], Any],
    items: Iterable[Any],
    *,
    key_of: Callable[[Any], Hashable],
    retries: int = 1,
    progress: ProgressFn | None = None,
) -> dict[Hashable, Any]:
    """Run ``fn(item)`` for every item, as independent tasks; collect them as they finish.

    Parameters
    ----------
    client
        A client from :func:`open_client`, or None to run the tasks here, one after the
        other (the single-process path: same results, same failure reports).
    fn
        A module-level function (the workers import it by name) of one item.  It reads
        whatever it needs itself: only ``item`` travels.
    items
        The tasks' inputs (small and picklable: paths, options).
    key_of
        A distinct name per item (a material's name): the key of the result, of the
        progress report and of a failure.
    retries
        Extra attempts of a task that raised (dask's ``retries=``).  A task lost with a
        killed worker is redone by the scheduler regardless (``distributed.scheduler.
        allowed-failures`` times) and then fails as ``KilledWorker``.
    progress
        Called in this process as each task finishes, in completion order, with
        ``(key, outcome, done, total)``; ``outcome`` is the result or a
        :class:`TaskFailure`.  An exception from it stops the run (the futures are
        cancelled) and propagates.

    Returns
    -------
    dict
        key -> result or :class:`TaskFailure`, in the order of ``items``.

    Raises
    ------
    GonioError
        Two items with the same key.
    KeyboardInterrupt
        Ctrl-C: the futures are cancelled first (the local cluster is closed by
        :func:`open_client`).
    """
    items = list(items)
    keys = [key_of(it) for it in items]
    if len(set(keys)) != len(keys):
        dup = sorted({str(k) for k in keys if keys.count(k) > 1})
        raise GonioError(f"tasks need distinct keys; repeated: {', '.join(dup)}")
    total = len(items)
    results: dict[Hashable, Any] = {}

    def done(key: Hashable, outcome: Any) -> None:
        results[key] = outcome
        if progress is not None:
            progress(key, outcome, len(results), total)

    if client is None:
        for key, item in zip(keys, items, strict=True):
            outcome: Any = None
            for _ in range(max(int(retries), 0) + 1):
                try:
                    outcome = _run_guarded(fn, item)
                    break
                except TaskError as exc:
                    outcome = _failure(key, exc)
            done(key, outcome)
        return {k: results[k] for k in keys}

    from distributed import as_completed

    # Keys are unique per run: two runs (two libraries) on one scheduler must never share
    # a task because their materials have the same names.
    run = uuid.uuid4().hex[:12]
    futures = []
    by_dask_key: dict[str, Hashable] = {}
    try:
        if interrupts.noted():  # a Ctrl-C lost before the run began (gonio.interrupts)
            raise KeyboardInterrupt
        for key, item in zip(keys, items, strict=True):
            fut = client.submit(
                _run_guarded, fn, item, key=f"gonio-{key}-{run}", retries=retries, pure=False
            )
            futures.append(fut)
            by_dask_key[fut.key] = key
        with _sigint_caught(at_once=True) as interrupted:
            for fut in as_completed(futures, loop=client.loop):
                if interrupted or interrupts.noted():
                    raise KeyboardInterrupt
                _collect(fut, by_dask_key[fut.key], done)
    except BaseException:
        with _sigint_caught(at_once=False), contextlib.suppress(Exception):
            client.cancel(futures, force=True)
        raise
    return {k: results[k] for k in keys}


def _collect(fut: Any, key: Hashable, done: Callable[[Hashable, Any], None]) -> None:
    """One finished future's outcome, reported to ``done``."""
    if fut.status == "finished":
        try:
            outcome = fut.result()
        except Exception as exc:  # lost between the report and the fetch
            outcome = _failure(key, exc)
    else:
        outcome = _failure(key, fut.exception() if fut.status == "error" else None)
    fut.release()
    done(key, outcome)


@contextlib.contextmanager
def rich_progress(total: int, description: str, console: Any = None) -> Iterator[ProgressFn]:
    """A rich progress bar for :func:`map_tasks`: yields a ``progress`` callback.

    Parameters
    ----------
    total
        Number of tasks.
    description
        The bar's label; the key of the last finished task is shown after it.
    console
        A ``rich.console.Console`` (default: rich's own, on stdout).
    """
    from rich.markup import escape

    from gonio.progress import task_progress

    with task_progress(console=console, transient=True) as bar:
        task = bar.add_task(escape(description), total=total)

        def update(key: Hashable, outcome: Any, done: int, total_: int) -> None:
            mark = "failed" if isinstance(outcome, TaskFailure) else "done"
            # escaped: a material's name may hold brackets, which rich reads as markup
            shown = escape(f"{description} ({key}: {mark})")
            bar.update(task, completed=done, description=shown)

        yield update


def check_engine(scheduler: str | None, workers: int | None) -> None:
    """Refuse an engine choice that cannot be honoured, before anything is opened.

    Raises
    ------
    GonioError
        ``scheduler`` with ``workers`` (a remote cluster's size is not ours to set), or
        ``workers`` below 0.
    """
    if scheduler is not None and workers is not None:
        raise GonioError(
            "--workers sets the size of the local cluster; a scheduler's workers are "
            "started on the cluster with `dask worker ADDRESS`"
        )
    if workers is not None and workers < 0:
        raise GonioError(f"--workers must be >= 0 (0: no dask, this process), got {workers}")


@contextlib.contextmanager
def task_engine(
    scheduler: str | None,
    workers: int | None,
    *,
    connect_timeout_s: float | None = None,
    on_client: Callable[[Any], None] | None = None,
) -> Iterator[tuple[Client | None, str]]:
    """The engine the fitting commands run their tasks on, for the duration of the block.

    One place for what the library and the per-texel fits share (``--workers 0``: no
    dask; else :func:`open_client`), so that both choose and describe it alike.

    Parameters
    ----------
    scheduler, workers
        As :func:`open_client`; ``workers=0``: no client, the tasks run in this process.
    connect_timeout_s
        Seconds to wait for ``scheduler`` (default :data:`DEFAULT_CONNECT_TIMEOUT_S`).
    on_client
        Called with the client once it is connected (tests, benchmarks); not called
        without one.

    Yields
    ------
    (client or None, where)
        ``where`` names the engine for the command's output ("this process", the
        scheduler's address or "a local cluster of N").
    """
    timeout = DEFAULT_CONNECT_TIMEOUT_S if connect_timeout_s is None else connect_timeout_s
    client_cm: contextlib.AbstractContextManager[Client | None] = (
        contextlib.nullcontext(None)
        if workers == 0
        else open_client(scheduler, workers=workers, timeout_s=timeout)
    )
    with client_cm as client:
        if client is not None and on_client is not None:
            on_client(client)
        where = (
            "this process"
            if client is None
            else scheduler or f"a local cluster of {len(client.scheduler_info()['workers'])}"
        )
        yield client, where


def run_tasks(
    client: Client | None,
    fn: Callable[[Any], Any],
    items: Iterable[Any],
    *,
    key_of: Callable[[Any], Hashable],
    description: str,
    arrived: Callable[[Hashable, Any], None],
    console: Any = None,
) -> dict[Hashable, Any]:
    """:func:`map_tasks` (one retry) under a :func:`rich_progress` bar.

    Parameters
    ----------
    client, fn, items, key_of
        As :func:`map_tasks`.
    description
        The bar's label.
    arrived
        Called with ``(key, outcome)`` as each task finishes, before the bar moves on
        (the caller stores or writes the result there: nothing waits for the whole run).
    console
        The ``rich.console.Console`` of the bar.

    Returns
    -------
    dict
        As :func:`map_tasks`.
    """
    items = list(items)
    with rich_progress(len(items), description, console=console) as bar:

        def progress(key: Hashable, outcome: Any, done: int, total: int) -> None:
            arrived(key, outcome)
            bar(key, outcome, done, total)

        return map_tasks(client, fn, items, key_of=key_of, retries=1, progress=progress)
