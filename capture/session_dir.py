"""The session directory: creating it, reading its journal's state, checking its frames.

Layout (DEVELOPING.md, "Session directory")::

    SESSION/manifest.json   what was planned with what (written once, atomically)
    SESSION/journal.jsonl   append-only record of what was done (fsync per record)
    SESSION/raw/            the RAW files, written atomically before they are journaled
    SESSION/sim/            files a simulated scene refers to (copied at creation)
    SESSION/.gonio.lock     held (flock) by the one process running or resuming it
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from gonio import __version__
from gonio.capture.journal import (
    frame_problem,
    fsync_dir,
    latest_shots,
    session_file,
    write_atomic,
)
from gonio.capture.manifest import MANIFEST, SCHEMA_VERSION, Manifest
from gonio.capture.plan import Plan, plan_digest
from gonio.capture.session_plan import RAW_DIR, PlanState
from gonio.config import validation_message
from gonio.devices import CameraInfo
from gonio.errors import FileFormatError, SessionError
from gonio.locks import LOCK_NAME, hold_lock

__all__ = [
    "JOURNAL",
    "BadFrame",
    "SessionState",
    "check_new_session_dir",
    "create_session",
    "session_state",
    "verify_frames",
]

JOURNAL = "journal.jsonl"


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def refuse_session_file(hint: str, path: Path | None, session: Path) -> None:
    """Refuse an output that is one of a capture session's own files (its journal,
    manifest, reduction.toml, lock, RAW frames or simulator records), ``--force`` or
    not: replacing it destroys the session.

    Raises
    ------
    click.UsageError
        Naming the option (``hint``) and the path.
    """
    import click

    from gonio.capture.reduction_config import CONFIG_FILE

    if path is None:
        return
    try:
        inside = Path(os.path.realpath(path)).relative_to(os.path.realpath(session))
    except ValueError:
        return
    own = {JOURNAL, MANIFEST, CONFIG_FILE, LOCK_NAME}
    # "sim": gonio.app.simulation.SIM_DIR, the simulated camera's records (an outer layer)
    if str(inside) in own or (len(inside.parts) > 1 and inside.parts[0] in (RAW_DIR, "sim")):
        raise click.UsageError(f"{hint} {path}: one of the session's own files; write elsewhere")


def check_new_session_dir(session_dir: Path) -> None:
    """Refuse to start a session where it would overwrite anything."""
    if (session_dir / MANIFEST).exists() or (session_dir / JOURNAL).exists():
        raise SessionError(
            f"{session_dir} already holds a session; continue it with "
            f"'gonio capture resume {session_dir}' or choose another --out"
        )
    if session_dir.exists() and (not session_dir.is_dir() or any(session_dir.iterdir())):
        raise SessionError(
            f"{session_dir} exists and is not an empty directory; choose a new --out "
            "(nothing was written)"
        )


def _manifest_bytes(d: Path, manifest: dict[str, Any]) -> bytes:
    """The manifest as written, checked as every reader will check it: a session that
    no reader accepts (an infinite estimate, a field out of its model) is never made."""
    try:
        text = json.dumps(manifest, indent=1, allow_nan=False)
        Manifest.model_validate(json.loads(text))
    except ValidationError as exc:
        raise SessionError(
            f"{d}: the session's manifest would be invalid "
            f"({validation_message(exc, 'manifest')}); nothing was written"
        ) from None
    except ValueError as exc:  # inf or nan, which JSON cannot hold
        raise SessionError(
            f"{d}: the session's manifest would hold a non-finite number ({exc}); "
            "nothing was written"
        ) from None
    return text.encode()


def create_session(
    session_dir: str | os.PathLike,
    plan: Plan,
    rig_config: Any,
    schedule: Any,
    camera_info: CameraInfo,
    simulation: Mapping[str, Any] | None = None,
    attachments: Mapping[str, str | os.PathLike] | None = None,
    hold: contextlib.ExitStack | None = None,
    files: Mapping[str, bytes] | None = None,
) -> Path:
    """Create a session directory: ``raw/``, attached files and the manifest.

    Parameters
    ----------
    session_dir
        The new session (must not exist, or be empty).
    plan, rig_config, schedule, camera_info
        What the manifest records (:class:`gonio.capture.schedule.Schedule`).
    simulation
        The simulation record (scene document with paths relative to the session).
    attachments
        Path inside the session -> source file, copied in before the manifest is written
        (what a simulated scene refers to, so the session is self-contained).
    files
        Path inside the session -> content, written before the manifest (what the
        devices contribute: :attr:`gonio.capture.engine.SessionDevices.files`).
    hold
        When given, the session's lock is taken (into this stack) before the directory
        appears under its name, so no other process can resume it in between.

    Raises
    ------
    SessionError
        When ``session_dir`` exists and is not empty (nothing is touched).
    """
    d = Path(session_dir)
    check_new_session_dir(d)
    d.parent.mkdir(parents=True, exist_ok=True)
    # Build the directory under a temporary name and rename it into place, so a crash
    # while creating leaves either no session or a complete one (never a half-made
    # directory that 'run' would refuse and 'resume' could not read).
    tmp = d.parent / f".{d.name}.creating-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        (tmp / RAW_DIR).mkdir()
        for rel, src in (attachments or {}).items():
            dest = tmp / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(dest, Path(src).read_bytes())
        for rel, data in (files or {}).items():
            dest = tmp / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            write_atomic(dest, data)
        manifest = {
            "schema_version": SCHEMA_VERSION,
            "software_version": __version__,
            "created": _now(),
            "rig": rig_config.model_dump(mode="json"),
            "rig_digest": plan_digest(rig_config),
            "camera": camera_info.to_json(),
            "plan": plan.model_dump(mode="json"),
            "plan_digest": plan_digest(plan),
            "seed": plan.seed,
            "reference": {"reflectance": plan.reference.reflectance},
            "simulation": dict(simulation) if simulation is not None else None,
            "schedule": schedule.steps,
            "excluded": [
                {**e.pose.to_json(), "reason": e.reason, "code": e.code}
                for e in schedule.expanded.excluded
            ],
            "estimated_duration_s": schedule.estimated_duration_s,
            "travel_time_s": schedule.travel_time_s,
        }
        write_atomic(tmp / MANIFEST, _manifest_bytes(d, manifest))
        if hold is not None:
            hold.enter_context(hold_lock(tmp / LOCK_NAME, f"session {d}"))
        fsync_dir(tmp)
        if d.exists():
            d.rmdir()  # empty (checked above); rename cannot replace it on every platform
        os.rename(tmp, d)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    fsync_dir(d.parent)
    return d


# --------------------------------------------------------------------------------------
# The journal's records, as the session reads them

_Count = Annotated[int, Field(strict=True, ge=0)]


class _Record(BaseModel):
    model_config = ConfigDict(extra="allow")


class _Verdict(_Record):
    saturated: bool
    underexposed: bool
    signal_fraction: Annotated[float, Field(allow_inf_nan=False)]


_Finite = Annotated[float, Field(allow_inf_nan=False)]
_Vec3 = tuple[_Finite, _Finite, _Finite]


class _Shot(_Record):
    type: Literal["shot"]
    pose: _Count
    frame: _Count
    kind: Literal["sample", "reference", "dark", "flat", "mirror"]
    file: str
    exposure_time_requested: Annotated[float, Field(gt=0, allow_inf_nan=False)]
    bytes: _Count | None = None
    sha256: str | None = None
    xxh3_128: str | None = None
    bracket: _Verdict | None = None
    # what the reduction computes with (a string or NaN here was a traceback or NaN
    # samples in `capture reduce` while `inspect` passed the journal); optional: older
    # journals and other cameras leave some out
    exposure_time: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = None
    rig_time: _Finite | None = None
    joints: dict[str, _Finite] | None = None
    approach: dict[str, Literal[-1, 0, 1]] | None = None
    wi_requested: _Vec3 | None = None
    wo_requested: _Vec3 | None = None
    wi_achieved: _Vec3 | None = None
    wo_achieved: _Vec3 | None = None


class _Closed(_Record):
    type: Literal["pose_done", "pose_skipped"]
    pose: _Count


@dataclass
class SessionState:
    """What the journal says: done poses, newest shots per pose, faults, last stop."""

    records: list[dict[str, Any]]
    done: set[int]
    shots: dict[int, list[dict[str, Any]]]
    faults: list[dict[str, Any]]
    last_stop: dict[str, Any] | None
    skipped: list[dict[str, Any]] = field(default_factory=list)
    records_per_frame: dict[tuple[int, int], int] = field(default_factory=dict)
    superseded: list[dict[str, Any]] = field(default_factory=list)

    @property
    def n_shots(self) -> int:
        return sum(len(v) for v in self.shots.values())

    def plan_state(self, retake: Mapping[int, set[int]] | None = None) -> PlanState:
        """The plan's view of this state (frames in ``retake`` are shot again)."""
        used = {
            float(r["exposure_time_requested"])
            for r in self.records
            if r.get("type") == "shot" and r.get("kind") not in ("dark", "flat")
        }
        return PlanState(
            done=set(self.done),
            shots={k: list(v) for k, v in self.shots.items()},
            retake={k: set(v) for k, v in (retake or {}).items()},
            used_exposures=used,
            records_per_frame=dict(self.records_per_frame),
        )


def session_state(
    records: Sequence[dict[str, Any]], journal: str | os.PathLike = JOURNAL
) -> SessionState:
    """Summarise journal records (see :func:`gonio.capture.journal.read_journal`).

    Raises
    ------
    FileFormatError
        A ``shot``, ``pose_done`` or ``pose_skipped`` record lacks a field or holds a
        wrong value (the record's line and the field are named), or a frame's records
        are not numbered 0, 1, 2, ... within their pose.
    """
    done: set[int] = set()
    faults, skipped = [], []
    last_stop = None
    per_frame: dict[tuple[int, int], int] = {}
    for n, r in enumerate(records, 1):
        t = r.get("type")
        model = _Shot if t == "shot" else _Closed if t in ("pose_done", "pose_skipped") else None
        if model is not None:
            try:
                model.model_validate(r)
            except ValidationError as exc:
                raise FileFormatError(
                    journal, validation_message(exc, f"record {n} ({t})")
                ) from None
        if t == "shot":
            key = (r["pose"], r["frame"])
            per_frame[key] = per_frame.get(key, 0) + 1
        elif t in ("pose_done", "pose_skipped"):
            done.add(r["pose"])
            if t == "pose_skipped":
                skipped.append(r)
        elif t == "fault":
            faults.append(r)
        elif t == "stop":
            last_stop = r
    latest = latest_shots(records)
    shots: dict[int, list[dict[str, Any]]] = {}
    for pose, frame in sorted(latest):
        shots.setdefault(pose, []).append(dict(latest[(pose, frame)]))
    for pose, frames in shots.items():
        if [s["frame"] for s in frames] != list(range(len(frames))):
            raise FileFormatError(
                journal,
                f"pose {pose} has frames {[s['frame'] for s in frames]}, expected 0, 1, 2, ...",
                "frame",
            )
    newest = {id(v) for v in latest.values()}
    superseded = [r for r in records if r.get("type") == "shot" and id(r) not in newest]
    return SessionState(
        list(records), done, shots, faults, last_stop, skipped, per_frame, superseded
    )


# --------------------------------------------------------------------------------------
# Checking frames against the journal


@dataclass(frozen=True)
class BadFrame:
    """A journaled frame whose file is missing, outside the session or changed."""

    pose: int
    frame: int
    file: str
    problem: str

    def __str__(self) -> str:
        return f"{self.file}: {self.problem}"


def verify_frames(
    session: Path, state: SessionState, digest: Literal["xxh3", "sha256", "size"] = "xxh3"
) -> tuple[list[BadFrame], int]:
    """Check every frame the session relies on (the newest record of each).

    Parameters
    ----------
    session
        The session directory.
    state
        Its journal's state.
    digest
        ``"xxh3"`` (the byte count and XXH3-128; sha256 for records that have no XXH3),
        ``"sha256"`` (the byte count and sha256) or ``"size"`` (the byte count only).

    Returns
    -------
    bad, verified
        The frames that failed, and how many were hashed and matched.

    Raises
    ------
    FileFormatError
        A record's ``file`` is not a path inside the session (nothing is opened).
    """
    bad: list[BadFrame] = []
    verified = 0
    for shots in state.shots.values():
        for s in shots:
            p = session_file(session, s)
            name = s["file"]
            if not p.is_file():
                bad.append(BadFrame(s["pose"], s["frame"], name, "missing"))
                continue
            try:
                # the size alone needs no read; a digest needs the bytes
                data = p.read_bytes() if digest != "size" else p.stat().st_size
            except OSError as exc:
                bad.append(BadFrame(s["pose"], s["frame"], name, f"unreadable ({exc})"))
                continue
            problem = frame_problem(data, s, digest)
            if problem is not None:
                bad.append(BadFrame(s["pose"], s["frame"], name, problem))
            elif digest != "size":
                verified += 1
    return bad, verified
