"""Damaged manifests and journals: a clear error naming the file and field, never a
traceback or nonsense (issue 14.5), and fuzzed readers that only raise GonioErrors.

Before the manifest model: a JSON array gave ``AttributeError`` in ``load_manifest``, a
manifest without ``rig`` a ``KeyError`` in resume, ``plan.bracket.iso = "lots"`` a
``ValueError`` deep in the bracket, and a schedule cut to 5 of 21 poses "poses done
21/5", "left: -16 poses" with exit code 0.
"""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gonio.capture.journal import read_journal
from gonio.capture.manifest import read_manifest
from gonio.capture.session_dir import session_state
from gonio.cli import run
from gonio.errors import GonioError
from gonio.locks import LOCK_NAME
from gonio.rig.config import virtual_rig_document

PLAN = """
name = "manifest"
seed = 2
[grid]
theta_i_deg = [10, 20, 30, 40]
phi_i_deg = [0]
theta_o_deg = [30, 50]
phi_o_deg = [180]
[bracket]
policy = "fixed"
exposures_s = [0.004]
[simulation]
width = 16
height = 12
"""


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    d = tmp_path_factory.mktemp("manifest")
    (d / "rig.toml").write_text(virtual_rig_document())
    (d / "plan.toml").write_text(PLAN)
    args = ["capture", "run", str(d / "plan.toml"), "--rig", str(d / "rig.toml")]
    assert run(*args, "--camera", "simulated", "--out", str(d / "S"), "--quiet") == 0
    return d / "S"


def _damaged(finished: Path, dest: Path, change) -> Path:
    shutil.copytree(finished, dest)
    (dest / LOCK_NAME).unlink(missing_ok=True)
    doc = json.loads((dest / "manifest.json").read_text())
    new = change(doc)
    (dest / "manifest.json").write_text(json.dumps(doc if new is None else new))
    return dest


def _iso(doc):
    doc["plan"]["bracket"]["iso"] = "lots"


def _cut_schedule(doc):
    doc["schedule"] = doc["schedule"][:3]


CASES = {
    "array": (lambda doc: [doc], "expected a JSON object"),
    "no rig": (lambda doc: doc.pop("rig") and None, "field 'rig'"),
    "iso lots": (_iso, "field 'plan.bracket.iso'"),
    "short schedule": (_cut_schedule, "field 'schedule'"),
    "schema": (lambda doc: doc.update(schema_version=7), "schema_version 7"),
    "step kind": (lambda doc: doc["schedule"][0].update(kind="banana"), "schedule.0.kind"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_damaged_manifest_is_a_clear_error(finished, tmp_path, capsys, case):
    change, expected = CASES[case]
    s = _damaged(finished, tmp_path / "S", change)
    before = (s / "journal.jsonl").read_bytes()
    for args in (
        ["inspect", str(s)],
        ["resume", str(s), "--quiet"],
        ["reduce", str(s), "--quiet", "--no-plot"],
    ):
        code = run("capture", *args)
        err = capsys.readouterr().err
        assert code == 1, (args, err)
        assert "Traceback" not in err
        if args[0] != "reduce":  # the reduction's own messages are its engineer's
            assert "manifest.json" in err and expected in err, err
    assert (s / "journal.jsonl").read_bytes() == before


# --------------------------------------------------------------------------------------
# Fuzz: random bytes, random JSON, mutated valid documents

JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=8), c, max_size=4),
    max_leaves=12,
)
FUZZ = settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@FUZZ
@given(data=st.binary(max_size=400))
def test_read_journal_random_bytes(tmp_path_factory, data):
    p = tmp_path_factory.mktemp("j") / "journal.jsonl"
    p.write_bytes(data)
    try:
        records = read_journal(p)
        session_state(records, p)
    except GonioError:
        pass


@FUZZ
@given(records=st.lists(JSON, max_size=6), tail=st.binary(max_size=20))
def test_journal_of_random_json_lines(tmp_path_factory, records, tail):
    p = tmp_path_factory.mktemp("j") / "journal.jsonl"
    p.write_bytes(b"".join(json.dumps(r).encode() + b"\n" for r in records) + tail)
    try:
        session_state(read_journal(p), p)
    except GonioError:
        pass


def test_deeply_nested_journal_line_is_a_format_error(tmp_path):
    p = tmp_path / "journal.jsonl"
    p.write_bytes(b"[" * 100_000 + b"\n{}\n")
    with pytest.raises(GonioError, match="line 1"):
        read_journal(p)


def _paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*prefix, k))
    elif isinstance(node, list):
        for k, v in enumerate(node):
            yield from _paths(v, (*prefix, k))


@pytest.fixture(scope="module")
def valid_manifest(finished):
    return json.loads((finished / "manifest.json").read_text())


@FUZZ
@given(data=st.data())
def test_mutated_manifests_raise_only_gonio_errors(tmp_path_factory, valid_manifest, data):
    doc = copy.deepcopy(valid_manifest)
    paths = list(_paths(doc))[1:]
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(paths))
        node = doc
        try:
            for k in path[:-1]:
                node = node[k]
            if data.draw(st.booleans()) and isinstance(node, dict):
                node.pop(path[-1], None)
            else:
                node[path[-1]] = data.draw(JSON)
        except (KeyError, IndexError, TypeError):
            continue  # an earlier mutation removed the way there
    d = tmp_path_factory.mktemp("m")
    (d / "manifest.json").write_text(json.dumps(doc))
    try:
        read_manifest(d)
    except GonioError:
        pass


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), JSON.map(lambda v: json.dumps(v).encode())))
def test_random_manifests_raise_only_gonio_errors(tmp_path_factory, data):
    d = tmp_path_factory.mktemp("m")
    (d / "manifest.json").write_bytes(data)
    with pytest.raises(GonioError):
        read_manifest(d)


def test_a_manifest_no_reader_would_accept_is_never_written(tmp_path, monkeypatch, capsys):
    """An infinite estimate (JSON has no inf: ``json.dumps`` wrote ``Infinity``) made a
    session that inspect, resume and reduce refused for good; now nothing is made."""
    import gonio.capture.schedule as schedule

    real = schedule.build_schedule

    def infinite(*a, **k):
        s = real(*a, **k)
        s.estimated_duration_s = float("inf")
        return s

    monkeypatch.setattr(schedule, "build_schedule", infinite)
    monkeypatch.setattr("gonio.capture.sessions.build_schedule", infinite)
    (tmp_path / "rig.toml").write_text(virtual_rig_document())
    (tmp_path / "plan.toml").write_text(PLAN)
    out = tmp_path / "S"
    args = ["capture", "run", str(tmp_path / "plan.toml"), "--rig", str(tmp_path / "rig.toml")]
    assert run(*args, "--camera", "simulated", "--out", str(out), "--quiet") == 1
    assert "non-finite" in capsys.readouterr().err
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.toml", "rig.toml"]


def test_resume_with_another_camera_backend_is_refused(finished, tmp_path, capsys):
    """--camera on resume (accepted for old scripts) must name the session's own backend;
    the session is left as it was."""
    s = tmp_path / "S"
    shutil.copytree(finished, s)
    before = (s / "journal.jsonl").read_bytes()
    assert run("capture", "resume", str(s), "--camera", "gphoto2") == 1
    err = capsys.readouterr().err
    assert "simulated camera" in err and "--camera gphoto2" in err
    assert (s / "journal.jsonl").read_bytes() == before
    assert run("capture", "resume", str(s), "--camera", "simulated", "--quiet") == 0
