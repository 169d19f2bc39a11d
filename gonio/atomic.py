"""Atomic file writes: a file is either its old self (or absent) or complete.

Every writer in gonio (RAW frames, the manifest, samples.h5, ground truth, plots, JSON
results, MERL files) goes through :func:`atomic_path`: the content goes to a temporary
file beside the destination (``.NAME.XXXXXXXX.tmp``, so a crash leaves only dot-files a
session can clean up), which is flushed to disk, renamed over the destination, and the
directory entry flushed too.  On any error the temporary file is removed and the
destination is untouched.  :func:`atomic_directory` does the same for a folder of files
that must be replaced together (the outputs of ``gonio fit``).

Temporaries are created like a plain ``open`` (mode 0666 masked by the umask, so a lab's
group can read what gonio writes) and each is held with a lock for as long as its writer
lives: an open-file-description ``fcntl`` lock on a file (it does not interfere with the
``flock`` HDF5 takes on the same file), a ``flock`` on a directory.  The kernel drops the
lock when the writer dies, so a temporary that nobody holds is *stale*: the leftover of a
killed writer.  :func:`stale_temporaries` lists them, and every writer removes the stale
temporaries of its own destination before it writes.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import os
import re
import secrets
import shutil
import stat
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "atomic_directory",
    "atomic_path",
    "fsync_dir",
    "remove_stale_temporaries",
    "stale_temporaries",
    "write_bytes_atomic",
    "write_text_atomic",
]

# The naming scheme is the one tempfile.mkstemp used before (8 characters of this
# alphabet), so temporaries left by older versions are recognised too.
_ALPHABET = "abcdefghijklmnopqrstuvwxyz0123456789_"
_TOKEN_LEN = 8
_TEMP_RE = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp$")
_OFD_SETLK = getattr(fcntl, "F_OFD_SETLK", None)
_OFD_GETLK = getattr(fcntl, "F_OFD_GETLK", None)


def fsync_dir(path: str | os.PathLike) -> None:
    """``fsync`` a directory so a rename or create inside it survives a power cut."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _temp_name(name: str) -> str:
    token = "".join(secrets.choice(_ALPHABET) for _ in range(_TOKEN_LEN))
    return f".{name}.{token}.tmp"


def _flock_struct(kind: int) -> bytes:
    # struct flock {short l_type, l_whence; off_t l_start, l_len; pid_t l_pid;} (Linux,
    # 64-bit off_t); OFD locks require l_pid = 0.  The whole file: start 0, length 0.
    return struct.pack("hhqqi4x", kind, os.SEEK_SET, 0, 0, 0)


def _lock_file(fd: int) -> None:
    """Take the writer's lock on an open temporary file (non-blocking: it is new)."""
    if _OFD_SETLK is not None:
        fcntl.fcntl(fd, _OFD_SETLK, _flock_struct(fcntl.F_WRLCK))
    else:  # pragma: no cover - non-Linux: a POSIX record lock
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)


def _is_held(path: Path) -> bool:
    """Whether a live process (this one included) holds the writer's lock on ``path``."""
    try:
        if path.is_dir():
            fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
            return False
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return True  # vanished or unreadable: not ours to remove
    try:
        if _OFD_GETLK is not None:
            res = fcntl.fcntl(fd, _OFD_GETLK, _flock_struct(fcntl.F_WRLCK))
            return struct.unpack("hhqqi4x", res)[0] != fcntl.F_UNLCK
        try:  # pragma: no cover - non-Linux
            fcntl.lockf(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return True
        return False
    finally:
        os.close(fd)


def stale_temporaries(directory: str | os.PathLike, name: str | None = None) -> list[Path]:
    """Temporaries in ``directory`` left by writers that died (no live process holds them).

    Parameters
    ----------
    directory
        The folder to look in (not recursive).
    name
        Only the temporaries of the destination with this file name (``"samples.h5"``).

    Returns
    -------
    list of Path
        Sorted; files and directories named ``.NAME.XXXXXXXX.tmp``.  Empty when the
        folder does not exist.
    """
    d = Path(directory)
    prefix = "." if name is None else f".{name}."
    try:
        # A prefix test first: writers call this before every write, in folders (raw/)
        # of thousands of files.
        with os.scandir(d) as it:
            names = [e.name for e in it if e.name.startswith(prefix) and e.name.endswith(".tmp")]
    except (FileNotFoundError, NotADirectoryError):
        return []
    out = []
    for entry in names:
        m = _TEMP_RE.match(entry)
        if m and (name is None or m.group("name") == name) and not _is_held(d / entry):
            out.append(d / entry)
    return sorted(out)


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the stale temporaries of the destination ``path`` (only of its own name).

    Returns
    -------
    list of Path
        What was removed.
    """
    path = Path(path)
    removed = []
    for p in stale_temporaries(path.parent, path.name):
        with contextlib.suppress(FileNotFoundError):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
            removed.append(p)
    return removed


def _create_temp(parent: Path, name: str) -> tuple[Path, int]:
    for _ in range(100):
        tmp = parent / _temp_name(name)
        try:
            # 0o666 & ~umask, as a plain open() would create it (mkstemp forces 0600).
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
        except FileExistsError:
            continue
        except OSError as exc:
            # Name the file the user asked for, not our hidden temporary beside it (an
            # error "dir/.plot.png.k3j9x0qa.tmp: Permission denied" names neither).
            raise type(exc)(
                exc.errno,
                f"{exc.strerror} (creating a temporary file in {parent} to write it)",
                str(parent / name),
            ) from exc
        try:
            _lock_file(fd)
        except BaseException:
            os.close(fd)
            tmp.unlink(missing_ok=True)
            raise
        return tmp, fd
    raise FileExistsError(errno.EEXIST, "no free temporary name", str(parent))  # pragma: no cover


def _refuse_non_regular(path: Path) -> None:
    """Refuse to replace what exists at ``path`` and is not a regular file (through a
    symlink: its target): the rename would put a file in place of a folder, a FIFO or a
    device (``--out /dev/null`` as root replaced the device node)."""
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return
    if not stat.S_ISREG(st.st_mode):
        raise FileExistsError(
            errno.EEXIST,
            "exists and is not a regular file (a folder, a device, a FIFO): not replaced",
            str(path),
        )


@contextmanager
def atomic_path(
    path: str | os.PathLike, *, parents: bool = False, replace: bool = True
) -> Iterator[Path]:
    """A temporary path to write ``path``'s new content to; renamed over ``path`` when
    the block ends without an error, removed when it raises.

    ``parents`` creates missing parent directories (otherwise a missing directory is an
    error).  Writers that infer a format from the file name (matplotlib) must be told the
    format: the temporary name ends in ``.tmp``.  Stale temporaries of ``path`` (from a
    killed writer) are removed first; the new file's mode follows the umask.

    ``replace=False`` (an output that must not be overwritten): the new file is linked
    into place only if nothing is there by then, in one ``link`` call, so of two writers
    racing for one new path exactly one wins; the other gets ``FileExistsError`` (a
    check for the path's existence before the work let both write).
    """
    path = Path(path)
    parent = path.parent
    _refuse_non_regular(path)
    if parents:
        parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp, fd = _create_temp(parent, path.name)
    try:
        try:
            yield tmp
            os.fsync(fd)  # flushes the file's data whichever descriptor wrote it
            if replace:
                os.replace(tmp, path)
            else:
                try:
                    os.link(tmp, path)
                except FileExistsError:
                    raise FileExistsError(
                        errno.EEXIST,
                        "exists (written meanwhile by another process?); not replaced",
                        str(path),
                    ) from None
                tmp.unlink()
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    finally:
        os.close(fd)
    fsync_dir(parent)


def _exchange(a: Path, b: Path) -> bool:
    """Swap two directory entries atomically (Linux ``renameat2(RENAME_EXCHANGE)``).

    Returns False when the system or file system cannot (the caller falls back).
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):  # pragma: no cover - not glibc >= 2.28
        return False
    at_fdcwd, rename_exchange = -100, 2
    rc = renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):  # pragma: no cover
        return False
    raise OSError(err, os.strerror(err), str(b))


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


def _link_into(src: Path, dst: Path) -> None:
    """Give ``dst`` the content of ``src`` without touching ``src``: hard links (the
    same inodes, so a lock held on a kept file stays held), copies where links fail."""
    if dst.exists() or not (src.exists() or src.is_symlink()):
        return
    if src.is_symlink():
        os.symlink(os.readlink(src), dst)
    elif src.is_dir():
        shutil.copytree(src, dst, symlinks=True, copy_function=_link_or_copy)
    else:
        _link_or_copy(str(src), str(dst))


@contextmanager
def atomic_directory(path: str | os.PathLike, *, keep: tuple[str, ...] = ()) -> Iterator[Path]:
    """A temporary folder to write ``path``'s new set of files to; it replaces ``path``
    as a whole when the block ends without an error, and is removed when it raises.

    Readers see either the old folder or the new one, never a mix: the new folder is
    swapped with the old one in one ``renameat2(RENAME_EXCHANGE)`` call (where the system
    lacks it: the old folder is renamed aside and the new one into place, so a crash in
    between leaves the old set under a stale temporary name, never a mixed folder).

    Parameters
    ----------
    path
        The folder to replace (created when absent; its parent must exist).
    keep
        Names in the old folder that are not part of the set: hard-linked (or copied;
        folders as trees of links) into the new folder just before the swap, so they
        survive it; the old folder's entries are never moved, so a crash loses none.
        Everything else of the old folder is dropped with it.
    """
    path = Path(path)
    parent = path.parent
    remove_stale_temporaries(path)
    for _ in range(100):
        stage = parent / _temp_name(path.name)
        try:
            stage.mkdir(mode=0o777)  # masked by the umask like any mkdir
            break
        except FileExistsError:
            continue
    dfd = os.open(stage, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        fcntl.flock(dfd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        try:
            yield stage
            if path.is_dir():
                for name in keep:
                    _link_into(path / name, stage / name)
                # The folder keeps its mode and group (a lab's setgid group folder).
                st = path.stat()
                os.chmod(stage, stat.S_IMODE(st.st_mode))
                with contextlib.suppress(OSError):
                    os.chown(stage, -1, st.st_gid)
            for p in stage.iterdir():
                if p.is_file():
                    with open(p, "rb") as fh:
                        os.fsync(fh.fileno())
            fsync_dir(stage)
            if not path.exists():
                os.rename(stage, path)
            elif _exchange(stage, path):
                pass  # the old set now lives at ``stage``: removed below
            else:  # pragma: no cover - no RENAME_EXCHANGE
                aside = parent / _temp_name(path.name)
                os.rename(path, aside)
                os.rename(stage, path)
                shutil.rmtree(aside, ignore_errors=True)
            fsync_dir(parent)
        finally:
            shutil.rmtree(stage, ignore_errors=True)
    finally:
        os.close(dfd)


def write_bytes_atomic(
    path: str | os.PathLike, data: bytes, *, parents: bool = False, replace: bool = True
) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path, parents=parents, replace=replace) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str, *, parents: bool = False) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path, parents=parents) as tmp:
        tmp.write_text(text, encoding="utf-8")
