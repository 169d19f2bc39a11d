"""Reading a session's frames: each file read once, checked against its journal record
and decoded from the same bytes, in worker threads that run ahead of the measurement.

:class:`FrameLoader` hands the frames out in journal order whoever decoded them, so the
reduction's output does not depend on the number of threads.
"""

from __future__ import annotations

import ctypes
import os
import sys
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from gonio.capture.journal import frame_problem, session_file
from gonio.capture.raw import CameraSignature, RawFrame, read_file, read_raw
from gonio.errors import FileFormatError, GonioError

__all__ = ["PREFETCH_POSES", "FrameLoader", "default_threads", "keep_freed_frames", "load_frame"]

#: Completed poses whose frames are decoded ahead of the one being measured.
PREFETCH_POSES = 2


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters
_malloc_tuned = False


def keep_freed_frames() -> None:
    """Have glibc's malloc keep freed frame-sized buffers for reuse (once per process).

    A reduction allocates every frame's bytes (and LibRaw's buffer) afresh.  By default
    glibc serves buffers that large with ``mmap`` and hands them back to the kernel when
    freed, or trims the heap when a pose's frames are freed together, so the next frame
    faults every page in again: measured 675 page faults and +6 ms per 1600x1200 frame
    (on this VM ~10 us a fault), a fifth of the reduction.  Buffers up to 32 MiB now come
    from the heap and up to 512 MiB of free heap is kept.  The process's memory stays at
    its peak instead of shrinking after a reduction; other platforms are left alone.
    """
    global _malloc_tuned
    if _malloc_tuned or not sys.platform.startswith("linux"):
        return
    _malloc_tuned = True
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(_M_MMAP_THRESHOLD, 32 << 20)  # glibc's largest heap allocation
        libc.mallopt(_M_TRIM_THRESHOLD, 512 << 20)
    except (OSError, AttributeError):  # not glibc (musl): nothing to tune
        pass


def default_threads() -> int:
    """Threads :func:`reduce_session` uses, the calling one included: 2 if the machine has
    2 or more cores (one measures poses and decodes, the other decodes ahead; more give
    little, since the measurement is serial and LibRaw's decoding is bound by memory)."""
    return 2 if (os.cpu_count() or 1) >= 2 else 1


def load_frame(
    session: Path, signature: CameraSignature | None, rec: Mapping[str, Any]
) -> tuple[RawFrame | None, str | None]:
    """Read one journal frame once, check it against the journal and decode it from the
    same bytes.

    The check is the journal's byte count and XXH3-128 digest (sessions from before it
    was recorded: sha256); see :func:`gonio.capture.journal.xxh3_bytes` for why.
    Returns ``(frame, None)``, or ``(None, problem)`` for a missing, changed, corrupt or
    foreign file.  Runs in worker threads: it touches no shared state.
    """
    rel = rec.get("file", "")
    try:
        path = session_file(session, rec)  # never a file outside the session
        if not path.is_file():
            raise FileFormatError(path, "missing (the journal lists it)")
        data = read_file(path)
        problem = frame_problem(data, rec)
        if problem is not None:
            raise FileFormatError(
                path, f"{problem}: the file was changed, truncated or corrupted after capture"
            )
        fr = read_raw(data, name=rel, expect=signature)
    except GonioError as exc:
        return None, str(exc)
    return (
        fr.with_exposure(
            exposure_time=rec.get("exposure_time") if not np.isfinite(fr.exposure_time) else None,
            iso=rec.get("iso") if not np.isfinite(fr.iso) else None,
            f_number=rec.get("f_number") if not np.isfinite(fr.f_number) else None,
        ),
        None,
    )


class FrameLoader:
    """Reads, hashes and decodes frames in worker threads, handing them out in order.

    File reads, hashing, LibRaw's unpack, OpenCV's board detection and the fused pose
    kernel release the GIL, so with two threads the worker decodes the next poses' frames
    while this thread measures the current pose.  When this thread needs frames the
    worker has not started, it decodes them itself rather than wait (decoding takes
    longer than measuring, so the two threads share it).  Every frame is decoded
    independently and the results are collected in journal order, so the output does not
    depend on the thread count.  With one thread frames are decoded on demand.
    """

    def __init__(self, session: Path, signature: CameraSignature | None, threads: int) -> None:
        keep_freed_frames()
        self._args = (session, signature)
        # ``threads`` counts this thread: the pool has the others
        self._pool = ThreadPoolExecutor(threads - 1, "gonio-reduce") if threads > 1 else None
        self._pending: dict[int, Future] = {}
        self._poses: dict[int, Future] = {}
        #: whether the last pose queued by prefetch_pose was not ready when asked for
        #: (the worker is behind the measurement: give it less to do ahead)
        self.behind = False

    def __enter__(self) -> FrameLoader:
        return self

    def __exit__(self, *exc: object) -> None:
        for fut in [*self._pending.values(), *self._poses.values()]:
            fut.cancel()
        self._pending.clear()
        self._poses.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def prefetch(self, recs: list[dict[str, Any]]) -> None:
        """Queue these frames for decoding (no-op with one thread or when already queued,
        here or as a pose by :meth:`prefetch_pose`)."""
        if self._pool is None or id(recs) in self._poses:
            return
        for rec in recs:
            if id(rec) not in self._pending:
                self._pending[id(rec)] = self._pool.submit(load_frame, *self._args, rec)

    def prefetch_pose(
        self,
        recs: list[dict[str, Any]],
        then: Callable[[list[tuple[RawFrame | None, str | None]]], Any],
    ) -> None:
        """Queue a pose's frames as one job that, once they are decoded, also runs
        ``then(results)`` in the worker (the board detection: OpenCV releases the GIL, so
        it overlaps the measurement of the previous pose); :meth:`pose_results` returns
        both.  No-op with one thread or when the pose or any of its frames is already
        queued."""
        if (
            self._pool is None
            or id(recs) in self._poses
            or any(id(rec) in self._pending for rec in recs)  # queued frame by frame
        ):
            return

        def job() -> tuple[list[tuple[RawFrame | None, str | None]], Any]:
            out = [load_frame(*self._args, rec) for rec in recs]
            return out, then(out)

        self._poses[id(recs)] = self._pool.submit(job)

    def pose_results(
        self, recs: list[dict[str, Any]]
    ) -> tuple[list[tuple[RawFrame | None, str | None]], Any]:
        """``(results(recs), then's value)`` of a pose queued by :meth:`prefetch_pose`;
        ``(results(recs), None)`` when it was not, or no worker had started it (this
        thread then decodes the frames, and the caller runs ``then``'s work itself)."""
        fut = self._poses.pop(id(recs), None)
        if fut is not None and not fut.cancel():
            self.behind = not fut.done()
            return fut.result()
        if fut is not None:  # cancelled: no worker had started it
            self.behind = True
        else:  # queued frame by frame (or not at all): behind unless all were decoded
            queued = [self._pending.get(id(rec)) for rec in recs]
            if any(f is not None for f in queued):
                self.behind = not all(f is not None and f.done() for f in queued)
        return self.results(recs), None

    def results(self, recs: list[dict[str, Any]]) -> list[tuple[RawFrame | None, str | None]]:
        """``(frame, problem)`` of each record, in the order given."""
        futs = [self._pending.pop(id(rec), None) for rec in recs]
        # frames no worker has started are decoded here (cancel() fails once started)
        local = [fut is None or fut.cancel() for fut in futs]
        out: list[Any] = [
            load_frame(*self._args, rec) if here else None
            for rec, here in zip(recs, local, strict=True)
        ]
        for k, (fut, here) in enumerate(zip(futs, local, strict=True)):
            if not here:
                out[k] = fut.result()
        return out
