"""Journal: append-only JSON lines, durable appends, torn last lines, atomic RAW writes."""

from __future__ import annotations

import json
import os

import pytest

from gonio.capture.journal import Journal, read_journal, sha256_file, write_atomic
from gonio.errors import FileFormatError


def test_append_and_read_back(tmp_path):
    p = tmp_path / "journal.jsonl"
    with Journal.create(p) as j:
        j.append({"type": "start"})
        j.append({"type": "shot", "pose": 0, "frame": 0})
    recs = read_journal(p)
    assert [r["type"] for r in recs] == ["start", "shot"]
    assert all("time" in r for r in recs)
    # one JSON object per line, newline-terminated
    lines = p.read_bytes().split(b"\n")
    assert lines[-1] == b"" and len(lines) == 3
    assert json.loads(lines[1])["pose"] == 0


def test_create_refuses_existing(tmp_path):
    p = tmp_path / "journal.jsonl"
    p.write_text("")
    with pytest.raises(FileExistsError):
        Journal.create(p)


@pytest.mark.parametrize("cut", [1, 5, 17])
def test_torn_last_line_is_ignored_and_truncated_on_open(tmp_path, cut):
    p = tmp_path / "journal.jsonl"
    good = b'{"type":"start"}\n{"type":"shot","pose":0}\n'
    torn = b'{"type":"shot","pose":1,"sha256":"abc"}'[:cut]
    p.write_bytes(good + torn)
    assert [r["type"] for r in read_journal(p)] == ["start", "shot"]
    j, recs = Journal.open(p)
    assert len(recs) == 2
    j.append({"type": "pose_done", "pose": 0})
    j.close()
    assert p.read_bytes().startswith(good)
    assert [r["type"] for r in read_journal(p)] == ["start", "shot", "pose_done"]


def test_complete_last_record_without_newline_is_kept(tmp_path):
    p = tmp_path / "journal.jsonl"
    p.write_bytes(b'{"type":"start"}\n{"type":"pose_done","pose":3}')
    assert read_journal(p)[-1] == {"type": "pose_done", "pose": 3}
    j, _ = Journal.open(p)
    j.append({"type": "stop"})
    j.close()
    assert [r["type"] for r in read_journal(p)] == ["start", "pose_done", "stop"]


def test_damage_before_the_last_line_is_an_error(tmp_path):
    p = tmp_path / "journal.jsonl"
    p.write_bytes(b'{"type":"start"}\n{"type": garbage\n{"type":"stop"}\n')
    with pytest.raises(FileFormatError, match="line 2"):
        read_journal(p)


def test_missing_journal(tmp_path):
    with pytest.raises(FileFormatError, match="not found"):
        read_journal(tmp_path / "nope.jsonl")


def test_write_atomic_replaces_whole_file(tmp_path):
    p = tmp_path / "a.dng"
    write_atomic(p, b"old contents")
    write_atomic(p, b"new")
    assert p.read_bytes() == b"new"
    assert [f.name for f in tmp_path.iterdir()] == ["a.dng"]  # no temp file left
    import hashlib

    assert sha256_file(p) == hashlib.sha256(b"new").hexdigest()


def test_append_is_fsynced(tmp_path, monkeypatch):
    calls = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (calls.append(fd), real(fd))[1])
    with Journal.create(tmp_path / "j.jsonl") as j:
        n0 = len(calls)
        j.append({"type": "shot"})
        assert len(calls) == n0 + 1
