"""The reduction's outputs as one set: ``samples.h5``, ``reduction.json``, ``samples.png``.

A kill between writing two files of a set would leave the new samples beside the old
summary.  The files of one output therefore live together in a hidden folder beside it
(``.samples.h5.set/``), which :func:`gonio.atomic.atomic_directory` replaces as a whole
(one ``RENAME_EXCHANGE``), and the names users know (``SESSION/samples.h5``,
``reduction.json``, ``samples.png``) are relative symbolic links into it that never change
once made.  Readers open the names as before and always see one complete set; the
session stays relocatable (the links are relative).

Outputs written before sets existed (plain files) are first adopted: hard-linked into a
set folder, then each name turned into a link to the identical content, so at every
moment each name shows the old set until the new one is swapped in.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

from gonio.atomic import atomic_directory, fsync_dir

__all__ = ["output_set", "set_folder"]


def set_folder(path: str | os.PathLike) -> Path:
    """The hidden folder that holds the set of output ``path`` (``.NAME.set`` beside it)."""
    p = Path(path)
    return p.with_name(f".{p.name}.set")


def _link(name: Path, target: str) -> None:
    """Make ``name`` a symbolic link to ``target`` atomically (replacing what is there)."""
    if name.is_symlink() and os.readlink(name) == target:
        return
    tmp = name.with_name(f".{name.name}.link-{os.getpid()}")
    with contextlib.suppress(FileNotFoundError):
        tmp.unlink()
    os.symlink(target, tmp)
    os.replace(tmp, name)


def _adopt(folder: Path, names: Sequence[Path]) -> None:
    """Turn plain output files (an older reduction's, or a copy's) into a set holding
    exactly what each name shows now (content unchanged)."""
    plain = [n for n in names if n.is_file() and not n.is_symlink()]
    if not plain:
        return
    with atomic_directory(folder) as stage:
        for n in names:
            if n.is_file():  # a plain file, or a link into the set: what readers see
                os.link(n.resolve(), stage / n.name)
    for n in plain:
        _link(n, f"{folder.name}/{n.name}")
    fsync_dir(folder.parent)


@contextlib.contextmanager
def output_set(path: str | os.PathLike, names: Sequence[str]) -> Iterator[Path]:
    """A folder to write a new set of outputs to; it replaces the old set as a whole.

    Parameters
    ----------
    path
        The main output (``SESSION/samples.h5``); the set's folder is named after it.
    names
        The file names of the set, as they appear beside ``path`` (``path.name`` among
        them).  A name the new set lacks (no plot this time) loses its link.

    Yields
    ------
    Path
        The staging folder: write each file of the set there under its name.
    """
    p = Path(path)
    folder = set_folder(p)
    visible = [p.with_name(n) for n in names]
    _adopt(folder, visible)
    with atomic_directory(folder) as stage:
        yield stage
    for v in visible:
        target = f"{folder.name}/{v.name}"
        if (folder / v.name).exists():
            _link(v, target)
        elif v.is_symlink() and os.readlink(v) == target:
            v.unlink()
    fsync_dir(p.parent)
