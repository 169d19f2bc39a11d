"""Atomic writes: the destination is either the old file or the complete new one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from gonio.atomic import (
    atomic_directory,
    atomic_path,
    remove_stale_temporaries,
    stale_temporaries,
    write_bytes_atomic,
    write_text_atomic,
)


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


@pytest.mark.parametrize("parent", ["missing", "a_file"])
def test_an_unwritable_place_is_named_by_the_output_not_the_temporary(tmp_path, parent):
    # The error named the hidden temporary (".plot.png.k3j9x0qa.tmp: Permission denied"),
    # a file the user never asked for; the CLI prints the OSError's filename.
    (tmp_path / "a_file").write_bytes(b"x")
    target = tmp_path / parent / "plot.png"
    with pytest.raises(OSError) as info:
        write_bytes_atomic(target, b"png")
    assert info.value.filename == str(target)
    assert str(tmp_path / parent) in info.value.strerror and ".tmp" not in str(info.value)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a_file"]


# --- file modes follow the umask (issue 13.6 / 14.12) -------------------------------

_MODE_SCRIPT = """
import os, stat, sys
from pathlib import Path
os.umask(int(sys.argv[2], 8))
from gonio.atomic import write_bytes_atomic
d = Path(sys.argv[1])
write_bytes_atomic(d / "via_gonio.bin", b"x")
with open(d / "via_open.bin", "wb") as fh:  # the reference: what a plain open gives
    fh.write(b"x")
print(oct(stat.S_IMODE(os.stat(d / "via_gonio.bin").st_mode)),
      oct(stat.S_IMODE(os.stat(d / "via_open.bin").st_mode)))
"""


@pytest.mark.parametrize(("umask", "expected"), [("022", 0o644), ("002", 0o664), ("077", 0o600)])
def test_file_modes_follow_the_umask_like_open(tmp_path, umask, expected):
    # A subprocess: the umask is process-wide and pytest-xdist workers share nothing else.
    out = subprocess.run(
        [sys.executable, "-c", _MODE_SCRIPT, str(tmp_path), umask],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    assert out == [oct(expected), oct(expected)]


# --- stale temporaries (issue 14.9) --------------------------------------------------

_KILLED_WRITER = """
import os, sys, signal
from gonio.atomic import atomic_path
with atomic_path(sys.argv[1]) as tmp:
    tmp.write_bytes(b"half")
    print(tmp, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)
"""

_LIVE_WRITER = """
import sys
from gonio.atomic import atomic_path
with atomic_path(sys.argv[1]) as tmp:
    tmp.write_bytes(b"in progress")
    print(tmp, flush=True)
    sys.stdin.readline()
"""


def _killed_temporary(dest: Path) -> Path:
    p = subprocess.run(
        [sys.executable, "-c", _KILLED_WRITER, str(dest)], capture_output=True, text=True
    )
    assert p.returncode == -signal.SIGKILL
    tmp = Path(p.stdout.strip())
    assert tmp.exists()
    return tmp


def test_stale_temporaries_lists_only_what_dead_writers_left(tmp_path):
    dest = tmp_path / "samples.h5"
    live = subprocess.Popen(
        [sys.executable, "-c", _LIVE_WRITER, str(dest)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        live_tmp = Path(live.stdout.readline().strip())
        assert live_tmp.exists()
        stale = _killed_temporary(dest)  # started after the live one: both exist now
        other = _killed_temporary(tmp_path / "fit.json")
        (tmp_path / ".hidden.tmp").write_bytes(b"not ours: no token")
        (tmp_path / "notes.txt").write_bytes(b"user file")
        assert stale_temporaries(tmp_path) == sorted([stale, other])
        assert stale_temporaries(tmp_path, "samples.h5") == [stale]
        # The next writer of samples.h5 removes its own stale temporary, not the live
        # writer's, not fit.json's, not the user's files.
        write_bytes_atomic(dest, b"new")
        assert not stale.exists() and live_tmp.exists() and other.exists()
        assert (tmp_path / ".hidden.tmp").exists() and (tmp_path / "notes.txt").exists()
    finally:
        live.communicate("go\n")
    assert dest.read_bytes() == b"in progress"  # the live writer finished after us
    assert stale_temporaries(tmp_path) == [other]
    assert remove_stale_temporaries(tmp_path / "fit.json") == [other]
    assert stale_temporaries(tmp_path) == []


def test_a_file_open_in_hdf5_keeps_its_writer_lock(tmp_path):
    # HDF5 flocks the files it writes; the writer's lock must not conflict with it.
    import h5py

    with atomic_path(tmp_path / "s.h5") as tmp, h5py.File(tmp, "w") as f:
        f["x"] = [1.0]
        assert stale_temporaries(tmp_path) == []
    with h5py.File(tmp_path / "s.h5", "r") as f:
        assert f["x"][0] == 1.0


def test_atomic_directory_replaces_the_set_and_keeps_named_files(tmp_path):
    out = tmp_path / "fit"
    with atomic_directory(out) as d:
        (d / "fit.json").write_text("old")
        (d / "slices.png").write_text("old plot")
    (out / "notes.txt").write_text("mine")
    with atomic_directory(out, keep=("notes.txt",)) as d:
        (d / "fit.json").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["fit.json", "notes.txt"]
    assert (out / "fit.json").read_text() == "new"
    with pytest.raises(RuntimeError), atomic_directory(out) as d:
        (d / "fit.json").write_text("half")
        raise RuntimeError("cut")
    assert (out / "fit.json").read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit"]


@pytest.mark.parametrize("kind", ["folder", "fifo"])
def test_what_is_not_a_regular_file_is_never_replaced(tmp_path, kind):
    """``--out /dev/null`` as root renamed a file over the device node: a folder, a FIFO
    (standing in for a device here) or a device at the destination is refused, and
    stays what it was."""
    import stat as st

    target = tmp_path / "out"
    if kind == "folder":
        target.mkdir()
    else:
        os.mkfifo(target)
    with pytest.raises(FileExistsError, match="not a regular file") as exc:
        write_bytes_atomic(target, b"data")
    assert exc.value.filename == str(target)
    mode = os.lstat(target).st_mode
    assert st.S_ISDIR(mode) if kind == "folder" else st.S_ISFIFO(mode)
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary left


def test_a_write_that_must_not_replace_keeps_what_appeared_meanwhile(tmp_path):
    """``replace=False``: two writers racing for one new output (two `brdf convert` to one
    DST both passed their existence check and both wrote): the file that is there when
    the second commits stays, the second gets FileExistsError, no temporary is left."""
    target = tmp_path / "out.binary"
    with pytest.raises(FileExistsError, match="not replaced"):
        with atomic_path(target, replace=False) as tmp:
            tmp.write_bytes(b"second")
            target.write_bytes(b"first")  # the other writer commits meanwhile
    assert target.read_bytes() == b"first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.binary"]
    fresh = tmp_path / "new.binary"
    write_bytes_atomic(fresh, b"data", replace=False)
    assert fresh.read_bytes() == b"data"
