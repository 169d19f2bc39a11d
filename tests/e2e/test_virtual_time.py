"""A virtual-time session is the watched session: same journal, same samples.h5.

The same plan and seed are captured twice through ``gonio capture run`` (real
dynamixel-sdk on the virtual bus's pty, rendered DNGs): once with servo time on the
virtual clock (the default), once on the wall clock at 20x (what sessions did before
virtual time).  The wall-clock run is the independent reference: its servos move in real
(scaled) time and are polled many times per move, its settle times are waited for, and
the camera's rendering time passes on its servo clock too.  Both are reduced, and the
journals must agree record by record apart from the timestamps, and every array and
attribute of the two ``samples.h5`` files must be equal.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from sim_sessions import (
    REFERENCE_NORMAL,
    REFERENCE_OBLIQUE,
    capture,
    grid_plan,
    scene_toml,
    write_inputs,
)

from gonio.capture.journal import read_journal
from gonio.cli import run

PLAN = grid_plan(
    "virtual-time",
    seed=11,
    settle_s=0.5,
    theta_i_deg=[20, 45],
    theta_o_deg=[30, 55],
    darks=1,
    references=[REFERENCE_NORMAL, REFERENCE_OBLIQUE],
)
# the reduction needs about this many pixels to find the reference target's region
SCENE = scene_toml(resolution=(400, 300))

#: Journal fields that are clock stamps by design: the wall clock's, and the rig time of
#: each shot (the servo clock, which on a watched bus runs with the wall clock).
TIMESTAMPS = {"time", "rig_time"}
#: samples.h5 attributes that are: the session's creation time (from its manifest).
H5_TIMESTAMPS = {"/@session"}


def capture_and_reduce(d: Path, name: str, *speed: str) -> Path:
    out = capture(d, name, *speed)
    reduce = ("capture", "reduce", str(out), "--grid", "2")
    assert run(*reduce, "--quiet", "--no-plot") == 0
    return out


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    d = tmp_path_factory.mktemp("vtime")
    write_inputs(d, PLAN, SCENE)
    virtual = capture_and_reduce(d, "virtual")  # the default: no --sim-speed
    watched = capture_and_reduce(d, "watched", "--sim-speed", "20")
    return virtual, watched


def _without_timestamps(rec: dict) -> dict:
    return {k: v for k, v in rec.items() if k not in TIMESTAMPS}


def test_the_sessions_ran_on_the_clocks_they_say(sessions):
    virtual, watched = sessions
    sims = [json.loads((s / "manifest.json").read_text())["simulation"] for s in sessions]
    assert [s["time_scale"] for s in sims] == ["virtual", 20.0]
    # the manifests differ in that record (and their creation time) only
    a, b = (json.loads((s / "manifest.json").read_text()) for s in (virtual, watched))
    for m in (a, b):
        m.pop("created")
        m["simulation"].pop("time_scale")
    assert a == b


def test_journals_are_identical_apart_from_timestamps(sessions):
    virtual, watched = sessions
    a, b = (read_journal(s / "journal.jsonl") for s in sessions)
    assert [r["type"] for r in a] == [r["type"] for r in b]
    assert a[-1]["type"] == "stop" and a[-1]["status"] == "completed"
    for ra, rb in zip(a, b, strict=True):
        assert _without_timestamps(ra) == _without_timestamps(rb)
    # every shot carries its rig time, a stamp of the servo clock that never runs back
    for journal in (a, b):
        stamps = [r["rig_time"] for r in journal if r["type"] == "shot"]
        assert stamps and all(isinstance(t, float) for t in stamps)
        assert all(t1 >= t0 for t0, t1 in zip(stamps, stamps[1:], strict=False))
        assert stamps[-1] > stamps[0]  # the moves between the poses took servo time
    # the comparison covers fields that move with the servos: the read-back joints and
    # the motors' temperatures, which rose above the 30 degC ambient during the moves
    shots = [r for r in a if r["type"] == "shot" and r["kind"] != "dark"]
    temps = {t for r in shots for t in r["temperatures"].values()}
    assert min(temps) == 30.0 and max(temps) > 30.0
    assert len({json.dumps(r["joints"], sort_keys=True) for r in shots}) >= 6  # six poses
    # and the RAW files are the same bytes
    for ra in a:
        if ra["type"] == "shot":
            assert (virtual / ra["file"]).read_bytes() == (watched / ra["file"]).read_bytes()


def _h5_items(path: Path) -> dict[str, object]:
    items: dict[str, object] = {}

    def visit(name: str, obj) -> None:
        for k, v in obj.attrs.items():
            items[f"{name}@{k}"] = v
        if isinstance(obj, h5py.Dataset):
            items[name] = obj[()]

    with h5py.File(path, "r") as f:
        for k, v in f.attrs.items():
            items[f"/@{k}"] = v
        f.visititems(visit)
    return items


def test_samples_are_identical(sessions):
    a, b = (_h5_items(s / "samples.h5") for s in sessions)
    assert sorted(a) == sorted(b)
    for items, s in zip((a, b), sessions, strict=True):
        created = json.loads((s / "manifest.json").read_text())["created"]
        assert {str(items.pop(k)) for k in H5_TIMESTAMPS} == {created}
    assert "brdf" in a and np.isfinite(np.asarray(a["brdf"], dtype=float)).any()
    for key in a:
        va, vb = np.asarray(a[key]), np.asarray(b[key])
        assert va.dtype == vb.dtype and va.shape == vb.shape, key
        if va.dtype.kind == "f":
            assert np.array_equal(va, vb, equal_nan=True), key
        else:
            assert np.array_equal(va, vb), key
