"""Atomic writes: the destination is either the old file or the complete new one."""

from __future__ import annotations

import pytest

from gonio.atomic import atomic_path, write_bytes_atomic, write_text_atomic


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    p = tmp_path / "samples.h5"
    p.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(p) as tmp:
        tmp.write_bytes(b"half of the new")
        raise RuntimeError("cut")
    assert p.read_bytes() == b"old"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["samples.h5"]


def test_writes_replace_whole_files_and_create_parents_only_when_asked(tmp_path):
    write_text_atomic(tmp_path / "a.json", "{}\n")
    write_text_atomic(tmp_path / "a.json", "[]\n")
    assert (tmp_path / "a.json").read_text() == "[]\n"
    with pytest.raises(FileNotFoundError):
        write_bytes_atomic(tmp_path / "missing" / "b.dng", b"x")
    write_bytes_atomic(tmp_path / "made" / "b.dng", b"x", parents=True)
    assert (tmp_path / "made" / "b.dng").read_bytes() == b"x"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.json", "made"]
