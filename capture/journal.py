"""The session journal: append-only JSON lines, each one on disk before the rig moves again.

A session that runs for hours must lose nothing when the power goes, so every record is
written, flushed and ``fsync``-ed before :meth:`Journal.append` returns.  A crash can then
tear at most the line being written; :func:`read_journal` drops such a torn last line and
:meth:`Journal.open` truncates it away before appending, so the file stays valid JSON
lines.  RAW files are written atomically (:func:`write_atomic`) *before* their record, so a
journal entry never points at a missing or half-written file.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from gonio.atomic import fsync_dir
from gonio.atomic import write_bytes_atomic as write_atomic
from gonio.errors import FileFormatError

__all__ = [
    "Journal",
    "fsync_dir",
    "latest_shots",
    "read_journal",
    "session_file",
    "sha256_bytes",
    "sha256_file",
    "stale_temporaries",
    "write_atomic",
    "xxh3_bytes",
    "xxh3_file",
]


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def xxh3_bytes(data: bytes) -> str:
    """Hex XXH3-128 digest of ``data``: the journal's fast integrity check.

    The reduction checks every frame it reads against the journal.  sha256 runs at about
    1.3 GB/s here (half a LibRaw decode per frame); XXH3 at ~20 GB/s.  For what the check
    is for, an accidental change or corruption after capture, a 128-bit non-cryptographic
    digest is as good: anyone able to alter a RAW file can rewrite the unsigned journal
    next to it, so sha256's collision resistance buys nothing here.  The sha256 stays in
    the journal for ``sha256sum`` and ``gonio capture status --verify``.
    """
    import xxhash

    return xxhash.xxh3_128_hexdigest(data)


def frame_problem(data: bytes | int, record: Mapping[str, Any], digest: str = "xxh3") -> str | None:
    """Why a frame's bytes are not what its journal record says, or None when they are.

    Parameters
    ----------
    data
        The file's bytes, or only its size in bytes (then only the size is checked).
    record
        Its ``shot`` record (``bytes``, ``xxh3_128``, ``sha256``).
    digest
        ``"xxh3"`` (byte count and XXH3-128; sha256 for records from before XXH3),
        ``"sha256"`` (byte count and sha256) or ``"size"`` (byte count only).
    """
    n = record.get("bytes")
    size = data if isinstance(data, int) else len(data)
    if n is not None and size != int(n):
        return f"{size} bytes, the journal recorded {int(n)}"
    if digest == "size" or isinstance(data, int):
        return None
    if digest == "xxh3" and record.get("xxh3_128"):
        if xxh3_bytes(data) != record["xxh3_128"]:
            return "XXH3-128 digest differs from the journal"
    elif record.get("sha256") and sha256_bytes(data) != record["sha256"]:
        return "sha256 differs from the journal"
    return None


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of the file at ``path`` (read in 1 MiB chunks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def xxh3_file(path: str | os.PathLike) -> str:
    """Hex XXH3-128 digest of the file at ``path`` (read in 1 MiB chunks)."""
    import xxhash

    h = xxhash.xxh3_128()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _loads(line: bytes) -> Any:
    # A line of ten thousand '[' exhausts the parser's recursion, which json reports as
    # RecursionError rather than ValueError: damage all the same.
    try:
        return json.loads(line)
    except RecursionError:
        raise ValueError("nested too deeply") from None


def _parse_lines(path: Path, raw: bytes) -> tuple[list[dict[str, Any]], int, bool]:
    """Parse journal bytes.

    Returns the records, the byte length of the newline-terminated prefix, and whether the
    unterminated tail (if any) was a complete record (cut just before its newline).
    """
    *complete, tail = raw.split(b"\n")
    records: list[dict[str, Any]] = []
    for n, line in enumerate(complete):
        if not line.strip():
            continue
        try:
            rec = _loads(line)
        except ValueError as exc:
            # A crash can only tear the final, unterminated line; a bad terminated line
            # means the file was damaged by something else, which must not pass silently.
            raise FileFormatError(path, f"line {n + 1} is not valid JSON ({exc})") from None
        if not isinstance(rec, dict):
            raise FileFormatError(path, f"line {n + 1} is not a JSON object")
        records.append(rec)
    good = len(raw) - len(tail)
    tail_ok = False
    if tail.strip():
        try:
            rec = _loads(tail)
            tail_ok = isinstance(rec, dict)
        except ValueError:
            tail_ok = False
        if tail_ok:
            records.append(rec)
    return records, good, tail_ok


def read_journal(path: str | os.PathLike) -> list[dict[str, Any]]:
    """Read a session journal, ignoring a torn last line.

    Parameters
    ----------
    path
        ``journal.jsonl`` of a session (or its session directory).

    Returns
    -------
    list of dict
        The records in the order written.

    Raises
    ------
    FileFormatError
        A line other than the last is not a JSON object (the file was damaged by something
        other than a crash while appending).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "journal.jsonl"
    if not path.exists():
        raise FileFormatError(path, "journal not found")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise FileFormatError(path, f"cannot read the journal: {exc.strerror or exc}") from None
    records, _, _ = _parse_lines(path, raw)
    return records


def session_file(session: str | os.PathLike, record: Mapping[str, Any]) -> Path:
    """The file a journal record names, refused unless it lies inside the session.

    A journal is an unsigned text file: a record saying ``"file": "../victim/v.txt"`` (or
    an absolute path, or a symlink out of the session) must not make inspect, resume or
    the reduction open, hash or replace anything outside the session directory.

    Parameters
    ----------
    session
        The session directory.
    record
        A journal record with a ``file`` field (a path relative to the session).

    Raises
    ------
    FileFormatError
        The field is missing, not a relative path, or resolves outside the session.
    """
    root = Path(session)
    journal = root / "journal.jsonl"
    name = record.get("file")
    where = f"file (pose {record.get('pose')!r}, frame {record.get('frame')!r})"
    if not isinstance(name, str) or not name or "\x00" in name:
        raise FileFormatError(journal, f"expected a relative path, got {name!r}", where)
    rel = Path(name)
    if rel.is_absolute():
        raise FileFormatError(
            journal,
            f"{name!r} is an absolute path; journal files must be inside the session",
            where,
        )
    # os.path.realpath on strings is Path.resolve without pathlib's objects: the
    # reduction checks every frame's record this way (twice), ~0.3 ms a frame saved
    base = os.path.realpath(root)
    target = os.path.realpath(os.path.join(root, name))
    if target != base and not target.startswith(base.rstrip(os.sep) + os.sep):
        raise FileFormatError(
            journal, f"{name!r} resolves outside the session directory {root}; refused", where
        )
    return root / rel


def latest_shots(records: Iterable[Mapping[str, Any]]) -> dict[tuple[int, int], Mapping[str, Any]]:
    """The newest ``shot`` record of every (pose, frame).

    A frame shot again (``gonio capture resume --retake``, or a redo after a crash) is
    journaled as a new record for the same (pose, frame), after the old one; the newest
    is the one that counts.  The reduction and ``inspect`` read frames through this.
    """
    out: dict[tuple[int, int], Mapping[str, Any]] = {}
    for r in records:
        if r.get("type") == "shot":
            out[(int(r["pose"]), int(r["frame"]))] = r
    return out


def stale_temporaries(session: str | os.PathLike) -> list[str]:
    """Temporary files and directories a killed writer left in or beside a session.

    :mod:`gonio.atomic`'s ``.NAME.XXXX.tmp`` temporaries that no live writer holds,
    anywhere in the session, and ``.NAME.creating-PID`` directories (a session being
    created) inside it or beside it; relative to the session (``../`` for those beside).
    """
    from gonio.atomic import stale_temporaries as stale_in

    root = Path(session)
    if not root.is_dir():
        return []
    folders = [root, *sorted(p for p in root.rglob("*") if p.is_dir())]
    found = sorted(str(p.relative_to(root)) for d in folders for p in stale_in(d))
    found += [str(p.relative_to(root)) for p in sorted(root.rglob(".*.creating-*")) if p.is_dir()]
    if root.parent.is_dir():
        found += [
            f"../{p.name}"
            for p in sorted(root.parent.glob(f".{root.name}.creating-*"))
            if p.is_dir()
        ]
    return found


class Journal:
    """An open, append-only session journal.

    Use :meth:`create` for a new session and :meth:`open` to append after a crash; every
    :meth:`append` is durable when it returns.
    """

    def __init__(self, path: Path, fh) -> None:
        self.path = path
        self._fh = fh

    @classmethod
    def create(cls, path: str | os.PathLike) -> Journal:
        """Create a new, empty journal; fails if ``path`` exists."""
        path = Path(path)
        fh = open(path, "xb")  # noqa: SIM115 - closed by Journal.close
        fsync_dir(path.parent)
        return cls(path, fh)

    @classmethod
    def open(cls, path: str | os.PathLike) -> tuple[Journal, list[dict[str, Any]]]:
        """Open an existing journal for appending, dropping a torn last line.

        Returns
        -------
        journal, records
            The open journal and the records it already holds.
        """
        path = Path(path)
        raw = path.read_bytes()
        records, good, tail_ok = _parse_lines(path, raw)
        fh = open(path, "r+b")  # noqa: SIM115 - closed by Journal.close
        if good < len(raw):
            # Cut the torn tail, or re-terminate a complete last record that lost its "\n".
            fh.seek(good)
            if tail_ok:
                fh.write(raw[good:] + b"\n")
            fh.truncate()
            fh.flush()
            os.fsync(fh.fileno())
        fh.seek(0, os.SEEK_END)
        return cls(path, fh), records

    def append(self, record: dict[str, Any]) -> dict[str, Any]:
        """Write one record (adding ``time`` if missing), flush and fsync.

        Returns the record as written.
        """
        rec = dict(record)
        rec.setdefault("time", time.time())
        line = json.dumps(rec, separators=(",", ":"), allow_nan=False).encode() + b"\n"
        self._fh.write(line)
        self._fh.flush()
        os.fsync(self._fh.fileno())
        return rec

    def extend(self, records: Iterable[dict[str, Any]]) -> None:
        """Append several records (each durable in turn)."""
        for r in records:
            self.append(r)

    def close(self) -> None:
        """Close the file (idempotent)."""
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
