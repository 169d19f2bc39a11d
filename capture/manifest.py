"""``manifest.json``: what a session planned with what, validated on every read.

The manifest is written once, atomically, when a session is created; everything that
reads it (run, resume, inspect, the reduction) goes through :func:`read_manifest`, which
validates the whole document with pydantic -- the plan and the rig configuration with
their own models -- so a damaged or hand-edited manifest is a
:class:`~gonio.errors.FileFormatError` naming the file and the field (``plan.bracket.iso``,
``rig``, ``schedule``), never an ``AttributeError`` or a nonsense count later on.

The manifest holds no absolute path: files a simulated scene refers to are copied into
the session at creation and named relative to it, so a session directory can be moved or
shared.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gonio.capture.plan import Plan
from gonio.config import validation_message
from gonio.errors import FileFormatError, SessionError
from gonio.rig.config import RigConfig

__all__ = [
    "MANIFEST",
    "SCHEMA_VERSION",
    "CameraRecord",
    "Manifest",
    "ScheduleStep",
    "SimulationRecord",
    "check_journal_fits",
    "refuse_calibration_session",
    "load_manifest",
    "read_manifest",
]

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"

_Finite = Annotated[float, Field(allow_inf_nan=False)]
_Vec3 = tuple[_Finite, _Finite, _Finite]


class _Open(BaseModel):
    # Newer gonio versions may add fields; an older reader keeps them and ignores them.
    model_config = ConfigDict(extra="allow", frozen=True)


class ScheduleStep(_Open):
    """One step of the schedule (journaled as pose ``k``).

    ``joints`` are the joint angles (rad) the dry run chose for the step, from the
    previous step's (a joint-pose plan's own joints); ``refused`` holds ``{"code",
    "message"}`` when the dry run's kinematics refused it (the run still asks the rig,
    which decides).  ``kind = "mirror"``: a rig calibration's view of the flat mirror.
    """

    kind: Literal["sample", "reference", "dark", "flat", "mirror"]
    wi: _Vec3 | None = None
    wo: _Vec3 | None = None
    joints: dict[str, _Finite] | None = None
    refused: dict[str, str] | None = None

    @model_validator(mode="after")
    def _directions(self) -> ScheduleStep:
        if self.kind not in ("dark", "flat") and (self.wi is None or self.wo is None):
            raise ValueError(f"a {self.kind} step needs 'wi' and 'wo' (unit vectors)")
        return self


class CameraRecord(_Open):
    """The camera as it described itself (:class:`gonio.devices.CameraInfo`)."""

    backend: str
    model: str
    sensor_size_mm: tuple[_Finite, _Finite] | None = None
    settings: dict[str, Any] = Field(default_factory=dict)


class SimulationRecord(_Open):
    """How a simulated session renders: the scene document (file paths relative to the
    session directory) and the virtual bus's speed: ``"virtual"`` (servo time advanced
    by the commanded motion) or a speed-up factor over the wall clock."""

    scene: dict[str, Any] | None = None
    width: Annotated[int, Field(ge=8)] | None = None
    height: Annotated[int, Field(ge=8)] | None = None
    time_scale: Annotated[float, Field(gt=0, allow_inf_nan=False)] | Literal["virtual"] | None = (
        None
    )
    reference_reflectance: float | tuple[float, float, float] | None = None


class Manifest(_Open):
    """The whole ``manifest.json`` (see DEVELOPING.md, "Session directory")."""

    schema_version: Literal[1]
    software_version: str
    created: str
    rig: RigConfig
    rig_digest: str
    camera: CameraRecord
    plan: Plan
    plan_digest: str
    seed: Annotated[int, Field(ge=0)]
    reference: dict[str, Any] = Field(default_factory=dict)
    simulation: SimulationRecord | None = None
    schedule: list[ScheduleStep] = Field(min_length=1)
    excluded: list[dict[str, Any]] = Field(default_factory=list)
    estimated_duration_s: _Finite
    travel_time_s: _Finite | None = None


def _path(session_dir: str | os.PathLike) -> Path:
    return Path(session_dir) / MANIFEST


def _load_json(path: Path) -> Any:
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise FileFormatError(path, f"cannot read the manifest: {exc.strerror or exc}") from None
    try:
        return json.loads(raw)
    except (ValueError, RecursionError) as exc:
        raise FileFormatError(path, f"cannot read the manifest: not valid JSON ({exc})") from None


def read_manifest(session_dir: str | os.PathLike) -> Manifest:
    """Read and validate a session's ``manifest.json``.

    Raises
    ------
    SessionError
        The directory holds no manifest (not a session).
    FileFormatError
        The manifest is not JSON, not an object, of another schema version, or a field
        is missing or invalid (each named, e.g. ``field 'plan.bracket.iso'``).
    """
    path = _path(session_dir)
    if not path.is_file():
        raise SessionError(f"{session_dir}: not a session directory (no {MANIFEST})")
    data = _load_json(path)
    if not isinstance(data, dict):
        raise FileFormatError(
            path, f"expected a JSON object (the session manifest), got {type(data).__name__}"
        )
    version = data.get("schema_version")
    if version != SCHEMA_VERSION:
        raise FileFormatError(
            path, f"schema_version {version!r}, this gonio reads {SCHEMA_VERSION}", "schema_version"
        )
    try:
        return Manifest.model_validate(data)
    except ValidationError as exc:
        raise FileFormatError(path, validation_message(exc, "invalid manifest")) from None
    except (ValueError, TypeError, RecursionError) as exc:  # a validator's own failure
        raise FileFormatError(path, f"invalid manifest ({exc})") from None


def load_manifest(session_dir: str | os.PathLike) -> dict[str, Any]:
    """The validated manifest as the JSON document it is (for readers of plain dicts,
    such as the reduction); see :func:`read_manifest`."""
    read_manifest(session_dir)
    return _load_json(_path(session_dir))


def refuse_calibration_session(session_dir: str | os.PathLike, manifest: Any) -> None:
    """Refuse to reduce a calibration session (its plan lists joint poses).

    ``manifest``: the :class:`Manifest` or its JSON document (:func:`load_manifest`).

    Raises
    ------
    SessionError
        When the session's plan has ``joint_poses``.
    """
    plan = manifest.plan if isinstance(manifest, Manifest) else (manifest or {}).get("plan")
    has = (
        plan.is_joint_pose_plan if isinstance(plan, Plan) else bool((plan or {}).get("joint_poses"))
    )
    if has:
        raise SessionError(
            f"{session_dir}: a calibration session (joint poses); use gonio calibrate "
            "camera|rig on it"
        )


def check_journal_fits(
    session_dir: str | os.PathLike, manifest: Manifest, records: list[dict[str, Any]]
) -> None:
    """Refuse a journal that names poses the manifest's schedule does not have.

    A schedule cut short by hand (5 steps) under a journal of 21 poses would otherwise
    read as "poses done 21/5" and resume would run nothing.

    Raises
    ------
    FileFormatError
        Naming the manifest, its ``schedule`` field and the first pose beyond it.
    """
    from gonio.capture.adaptive import adaptive_steps, round_records

    # an adaptive session's rounds add their steps after the schedule's
    n = len(manifest.schedule)
    n += len(adaptive_steps(round_records(records, _path(session_dir).parent / "journal.jsonl", n)))
    for r in records:
        pose = r.get("pose")
        if r.get("type") in ("shot", "pose_done", "pose_skipped") and isinstance(pose, int):
            if not 0 <= pose < n:
                raise FileFormatError(
                    _path(session_dir),
                    f"the schedule has {n} steps but the journal records pose {pose}: the "
                    "manifest or the journal was changed after the session started",
                    "schedule",
                )
