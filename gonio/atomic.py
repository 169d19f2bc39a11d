"""Atomic file writes: a file is either its old self (or absent) or complete.

Every writer in gonio (RAW frames, the manifest, samples.h5, ground truth, plots, JSON
results, MERL files) goes through :func:`atomic_path`: the content goes to a temporary
file beside the destination (``.NAME.XXXX.tmp``, so a crash leaves only dot-files a
session can clean up), which is flushed to disk, renamed over the destination, and the
directory entry flushed too.  On any error the temporary file is removed and the
destination is untouched.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path", "fsync_dir", "write_bytes_atomic", "write_text_atomic"]


def fsync_dir(path: str | os.PathLike) -> None:
    """``fsync`` a directory so a rename or create inside it survives a power cut."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: str | os.PathLike, *, parents: bool = False) -> Iterator[Path]:
    """A temporary path to write ``path``'s new content to; renamed over ``path`` when
    the block ends without an error, removed when it raises.

    ``parents`` creates missing parent directories (otherwise a missing directory is an
    error).  Writers that infer a format from the file name (matplotlib) must be told the
    format: the temporary name ends in ``.tmp``.
    """
    path = Path(path)
    parent = path.parent
    if parents:
        parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(parent)


def write_bytes_atomic(path: str | os.PathLike, data: bytes, *, parents: bool = False) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path, parents=parents) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str, *, parents: bool = False) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path, parents=parents) as tmp:
        tmp.write_text(text, encoding="utf-8")
