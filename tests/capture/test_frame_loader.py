"""The frame loader's worker and the calling thread sharing the decoding.

While the calling thread waits for a job a worker has started, it runs queued jobs no
worker has started (:meth:`FrameLoader._help`); what it hands back must be what the job
would have given, whoever ran it.  On a real camera's RAW file (LibRaw's decoding), so
``GONIO_REFDATA`` is needed; the whole reduction's independence of the thread count is
checked in ``test_reduce.py``.
"""

from __future__ import annotations

import shutil
import threading

import numpy as np
import pytest

from gonio.capture.frame_loader import FrameLoader, load_frame
from gonio.capture.journal import xxh3_bytes


@pytest.fixture()
def raw_session(refdata, tmp_path):
    """Four copies of the Kodak DC50 RAW as a session's frames, with journal records."""
    src = refdata / "raw" / "RAW_KODAK_DC50.KDC"
    (tmp_path / "raw").mkdir()
    data = src.read_bytes()
    recs = []
    for k in range(4):
        rel = f"raw/f{k}.kdc"
        shutil.copyfile(src, tmp_path / rel)
        recs.append(
            {"file": rel, "pose": k // 2, "frame": k % 2, "bytes": len(data)}
            | {"xxh3_128": xxh3_bytes(data)}
        )
    return tmp_path, recs


def test_the_waiting_thread_runs_queued_jobs_and_hands_back_their_results(raw_session):
    """Pose A's job is held in the worker until the calling thread, waiting for it, has
    run pose B's queued frame job itself (without the help the hold times out and A's
    value says so); B's frames then come from that run, the same as a fresh decode."""
    s, recs = raw_session
    a, b = recs[:2], recs[2:]
    started = threading.Event()
    with FrameLoader(s, None, 2) as loader:

        def then(results):
            started.set()
            # hold the worker until the calling thread has helped (or 30 s passed)
            for _ in range(3000):
                if loader.helped:
                    return "helped"
                threading.Event().wait(0.01)
            return "not helped"

        loader.prefetch_pose(a, then)
        assert started.wait(60)  # A runs in the worker
        loader.prefetch(b)  # queued behind A: no worker can start it while A is held
        results, value = loader.pose_results(a)
        assert value == "helped" and loader.helped >= 1
        assert all(fr is not None and p is None for fr, p in results)
        got = loader.results(b)
    for rec, (fr, problem) in zip(b, got, strict=True):
        assert problem is None
        want, _ = load_frame(s, None, rec)
        np.testing.assert_array_equal(fr.raw, want.raw)
        assert fr.cfa_pattern == want.cfa_pattern == "GRBG"


def test_one_thread_never_helps(raw_session):
    s, recs = raw_session
    with FrameLoader(s, None, 1) as loader:
        loader.prefetch(recs)
        assert all(fr is not None for fr, _ in loader.results(recs))
        assert loader.helped == 0
