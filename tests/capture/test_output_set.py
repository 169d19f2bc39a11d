"""The reduction's outputs as one set: adoption of plain files, links, relocation."""

from __future__ import annotations

import os
import shutil

import pytest

from gonio.capture.output_set import output_set, set_folder

NAMES = ("samples.h5", "reduction.json", "samples.png")


def _write(stage, **files):
    for name, text in files.items():
        (stage / name).write_text(text)


def _read(d):
    return {n: (d / n).read_text() for n in NAMES if (d / n).exists()}


def test_a_new_set_replaces_plain_files_and_leaves_relative_links(tmp_path):
    for n in NAMES:
        (tmp_path / n).write_text(f"old {n}")
    with output_set(tmp_path / "samples.h5", NAMES) as stage:
        _write(stage, **{n: f"new {n}" for n in NAMES})
    assert _read(tmp_path) == {n: f"new {n}" for n in NAMES}
    for n in NAMES:
        assert (tmp_path / n).is_symlink()
        assert os.readlink(tmp_path / n) == f".samples.h5.set/{n}"  # relative: relocatable
    moved = tmp_path.parent / (tmp_path.name + "-moved")
    shutil.move(tmp_path, moved)
    assert _read(moved) == {n: f"new {n}" for n in NAMES}


def test_a_failed_write_keeps_the_old_set_whole(tmp_path):
    for n in NAMES:
        (tmp_path / n).write_text(f"old {n}")
    with pytest.raises(RuntimeError), output_set(tmp_path / "samples.h5", NAMES) as stage:
        _write(stage, **{"samples.h5": "new"})
        raise RuntimeError("killed half-way")
    assert _read(tmp_path) == {n: f"old {n}" for n in NAMES}
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []


def test_a_set_without_a_plot_drops_the_plot_link(tmp_path):
    with output_set(tmp_path / "samples.h5", NAMES) as stage:
        _write(stage, **{n: "1" for n in NAMES})
    with output_set(tmp_path / "samples.h5", NAMES) as stage:
        _write(stage, **{"samples.h5": "2", "reduction.json": "2"})
    assert _read(tmp_path) == {"samples.h5": "2", "reduction.json": "2"}
    assert not os.path.lexists(tmp_path / "samples.png")
    assert sorted(p.name for p in set_folder(tmp_path / "samples.h5").iterdir()) == [
        "reduction.json",
        "samples.h5",
    ]


def test_a_copied_session_with_plain_files_is_adopted_as_it_shows(tmp_path):
    """A copy that dereferenced the links holds plain files beside a stale set folder:
    what the names show is the set, until the new one is swapped in."""
    with output_set(tmp_path / "samples.h5", NAMES) as stage:
        _write(stage, **{n: "stale" for n in NAMES})
    for n in NAMES:
        (tmp_path / n).unlink()
        (tmp_path / n).write_text(f"shown {n}")
    with pytest.raises(RuntimeError), output_set(tmp_path / "samples.h5", NAMES):
        raise RuntimeError
    assert _read(tmp_path) == {n: f"shown {n}" for n in NAMES}
