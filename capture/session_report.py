"""``inspect``: what a session has done, what failed, what is left -- nothing written."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gonio.capture.adaptive import adaptive_steps, rounds_summary
from gonio.capture.journal import read_journal, stale_temporaries
from gonio.capture.manifest import check_journal_fits, read_manifest
from gonio.capture.session_dir import JOURNAL, session_state, verify_frames
from gonio.capture.session_plan import RAW_DIR

__all__ = ["SessionReport", "inspect_session"]


@dataclass
class SessionReport:
    """What a session has done, what failed, what is left (``gonio capture inspect``).

    ``to_json()`` gives the dict ``gonio capture inspect --json`` prints.
    """

    session: Path
    plan: str
    camera: str
    status: str
    poses_total: int
    poses_done: int
    partial_poses: list[int]
    shots: int
    faults: list[dict[str, Any]]
    skipped: list[dict[str, Any]]
    bad_files: list[str]
    orphans: list[str]
    files_verified: int
    retaken: list[str] = field(default_factory=list)
    superseded: list[str] = field(default_factory=list)
    stale_temporaries: list[str] = field(default_factory=list)
    #: The last reduction's budget (``reduction.json["budget"]``: its largest terms), or
    #: None when the session has not been reduced (or was reduced before budgets).
    budget: dict[str, Any] | None = None
    #: An adaptive session's rounds (:func:`gonio.capture.adaptive.rounds_summary`).
    rounds: list[dict[str, Any]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """No journaled frame is missing or changed."""
        return not self.bad_files

    def to_json(self) -> dict[str, Any]:
        return {
            "plan": self.plan,
            "camera": self.camera,
            "status": self.status,
            "poses_total": self.poses_total,
            "poses_done": self.poses_done,
            "partial_poses": self.partial_poses,
            "shots": self.shots,
            "faults": self.faults,
            "skipped": self.skipped,
            "bad_files": self.bad_files,
            "orphans": self.orphans,
            "files_verified": self.files_verified,
            "retaken": self.retaken,
            "superseded": self.superseded,
            "stale_temporaries": self.stale_temporaries,
            "budget": self.budget,
            "rounds": self.rounds,
        }


def inspect_session(session_dir: str | Path, verify: bool = True) -> SessionReport:
    """What a session has done, what failed, what is left; nothing is written.

    Parameters
    ----------
    session_dir
        The session directory.
    verify
        Hash every frame the session relies on and compare with its journaled sha256
        (otherwise only the byte counts are compared).

    Raises
    ------
    SessionError, FileFormatError
        Not a session, a damaged manifest or journal, or a journal record naming a
        file outside the session.
    """
    d = Path(session_dir)
    manifest = read_manifest(d)
    jp = d / JOURNAL
    records = read_journal(jp) if jp.exists() else []
    check_journal_fits(d, manifest, records)
    st = session_state(records, jp)
    bad, verified = verify_frames(d, st, "sha256" if verify else "size")
    newest = [s["file"] for shots in st.shots.values() for s in shots]
    superseded = [r["file"] for r in st.superseded]
    journaled = set(newest) | set(superseded)
    bad_files = [str(b) for b in bad]
    if len(set(newest)) != len(newest):
        bad_files.append("journal names a file more than once")
    raw = d / RAW_DIR
    orphans = (
        sorted(
            f"{RAW_DIR}/{p.name}"
            for p in raw.iterdir()
            if p.is_file() and not p.name.startswith(".") and f"{RAW_DIR}/{p.name}" not in journaled
        )
        if raw.is_dir()
        else []
    )
    status = (
        st.last_stop["status"]
        if st.last_stop
        else ("not started" if not records else "running or crashed")
    )
    if st.last_stop and records and records[-1].get("type") != "stop":
        status = "running or crashed"
    return SessionReport(
        session=d,
        plan=manifest.plan.name,
        camera=manifest.camera.backend,
        status=str(status),
        poses_total=len(manifest.schedule) + len(adaptive_steps(records)),
        poses_done=len(st.done),
        partial_poses=sorted(set(st.shots) - st.done),
        shots=st.n_shots,
        faults=st.faults,
        skipped=[{"pose": r["pose"], "reason": r.get("reason")} for r in st.skipped],
        bad_files=bad_files,
        orphans=orphans,
        files_verified=verified,
        retaken=[s["file"] for shots in st.shots.values() for s in shots if s.get("retake")],
        superseded=superseded,
        stale_temporaries=stale_temporaries(d),
        budget=_reduction_budget(d),
        rounds=rounds_summary(records),
    )


def _reduction_budget(d: Path) -> dict[str, Any] | None:
    """``SESSION/reduction.json``'s budget, read only; None when absent or unreadable
    (inspecting a session never fails on its reduction's summary)."""
    import json

    p = d / "reduction.json"
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    budget = doc.get("budget") if isinstance(doc, dict) else None
    if not isinstance(budget, dict) or not isinstance(budget.get("terms"), list):
        return None
    terms = [
        r
        for r in budget["terms"]
        if isinstance(r, dict)
        and isinstance(r.get("term"), str)
        and all(isinstance(r.get(k), int | float) for k in ("median_rel_std", "share"))
    ]
    return {**budget, "terms": terms}
